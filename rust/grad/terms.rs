//! The Lagrangian's terms and their reverse pass (see the module's page): tiles of samples through the inertia
//! network with its q-tangents (`net.rs`) and the potential network with its gradient (`potential.rs`), the head
//! per group of samples (`head.rs`).

use super::dispatch::KernelReal;
use super::head::{self, Lanes, Num, Outs, MMAX, NMAX};
use super::net::{self, BackBufs, Net, Tile};
use super::potential::{self, PotBufs};
use super::tape::Tape;
use super::{check_net, sum_chunks, unpad, LayerRef, NetGrads, CHUNK_TILES, TILE};
use crate::error::{Error, Result};
use crate::model::JointType;
use crate::pool::{Chunks, Pool};
use crate::real::Real;
use crate::simd::Simd;

/// The prepared weights of a Lagrangian (inertia network `l`, potential network `v`) and its shape.
pub struct TermsKernel<T> {
    n: usize,
    dz: usize,
    dphi: usize,
    /// φ's columns of each joint: (cos, sin) for a revolute joint, (q, usize::MAX) for a prismatic one.
    cols: Vec<(usize, usize)>,
    offset: T,
    v_scale: T,
    l: Net<T>,
    v: Net<T>,
    simd: Simd,
}

impl<T: KernelReal> TermsKernel<T> {
    /// Prepare a Lagrangian's networks (copied, transposed and padded once per call).
    pub fn new(joint_types: &[JointType], dz: usize, softplus_offset: f64, v_scale: f64,
               l_layers: &[LayerRef<T>], v_layers: &[LayerRef<T>]) -> Result<TermsKernel<T>> {
        let n = joint_types.len();
        if n == 0 || n > NMAX {
            return Err(Error::InputShape(format!("the training kernel handles 1 to {NMAX} joints, got {n}")));
        }
        let rev: Vec<usize> = (0..n).filter(|&j| joint_types[j] == JointType::Revolute).collect();
        let r = rev.len();
        let mut cols = vec![(0, usize::MAX); n];
        let mut pri = 0;
        for j in 0..n {
            cols[j] = match rev.iter().position(|&x| x == j) {
                Some(i) => (i, r + i),
                None => {
                    pri += 1;
                    (2 * r + pri - 1, usize::MAX)
                }
            };
        }
        let dphi = 2 * r + pri;
        let l = check_net("inertia", l_layers, dphi + dz, n * (n + 1) / 2)?;
        let v = check_net("potential", v_layers, dphi + dz, 1)?;
        Ok(TermsKernel { n, dz, dphi, cols, offset: T::of(softplus_offset), v_scale: T::of(v_scale), l, v, simd: crate::simd::detect() })
    }

    pub fn n(&self) -> usize {
        self.n
    }

    /// (out, in) of every layer of the inertia and the potential network.
    pub fn shapes(&self) -> (Vec<(usize, usize)>, Vec<(usize, usize)>) {
        let of = |net: &Net<T>| net.layers.iter().map(|l| (l.out, l.inp)).collect();
        (of(&self.l), of(&self.v))
    }

    /// L, H (N × n × n), c and g (N × n) at N samples of q, q̇ (N × n) and z (N × dz); with `tape`, what the
    /// reverse pass needs is kept there.
    #[allow(clippy::too_many_arguments)]
    pub fn forward(&self, q: &[T], qd: &[T], z: &[T], l_out: &mut [T], h_out: &mut [T], c_out: &mut [T],
                   g_out: &mut [T], tape: Option<&mut Tape<T>>, pool: &Pool) -> Result<()> {
        let (n, dz) = (self.n, self.dz);
        let samples = q.len() / n;
        if q.len() != samples * n || qd.len() != q.len() || z.len() != samples * dz
            || l_out.len() != samples * n * n || h_out.len() != samples * n * n || c_out.len() != q.len() || g_out.len() != q.len() {
            return Err(Error::InputShape(format!("forward: inconsistent lengths for {samples} samples of {n} joints and z of {dz}")));
        }
        let tiles = samples.div_ceil(TILE);
        let chunks = tiles.div_ceil(CHUNK_TILES);
        let tl = self.tile_len();
        let mut none = Vec::new();
        let (data, keep): (&mut [T], bool) = match tape {
            Some(t) => {
                t.q.clear();
                t.q.extend_from_slice(q);
                t.qd.clear();
                t.qd.extend_from_slice(qd);
                (t.prepare(samples, tiles * tl), true)
            }
            None => (&mut none, false),
        };
        let per_chunk = CHUNK_TILES * tl;
        let outs = (Chunks::new(data, per_chunk), Chunks::new(l_out, CHUNK_TILES * TILE * n * n),
                    Chunks::new(h_out, CHUNK_TILES * TILE * n * n), Chunks::new(c_out, CHUNK_TILES * TILE * n),
                    Chunks::new(g_out, CHUNK_TILES * TILE * n));
        let job = FwdJob { k: self, q, qd, z, samples, keep };
        pool.run(chunks, &|ci| {
            // SAFETY: each chunk index is taken by one task only.
            let (tp, lo, ho, co, go) = unsafe { (outs.0.get(ci), outs.1.get(ci), outs.2.get(ci), outs.3.get(ci), outs.4.get(ci)) };
            T::forward_chunk(self.simd, &job, ci, tp, [lo, ho, co, go]);
        });
        Ok(())
    }

    /// The reverse pass over a tape of `forward`: the gradients of L, H, c, g in, those of q, q̇, z out, and
    /// every weight's (returned in torch's layout, inertia network first).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(&self, tape: &Tape<T>, dl: &[T], dh: &[T], dc: &[T], dg: &[T], dq: &mut [T], dqd: &mut [T],
                    dz: &mut [T], pool: &Pool) -> Result<(NetGrads<T>, NetGrads<T>)> {
        let (n, samples) = (self.n, tape.samples);
        if tape.data.len() != samples.div_ceil(TILE) * self.tile_len() {
            return Err(Error::InputShape("backward: the tape was not written by this kernel's forward pass".into()));
        }
        if dl.len() != samples * n * n || dh.len() != dl.len() || dc.len() != samples * n || dg.len() != dc.len()
            || dq.len() != dc.len() || dqd.len() != dc.len() || dz.len() != samples * self.dz {
            return Err(Error::InputShape(format!("backward: inconsistent lengths for {samples} samples of {n} joints")));
        }
        let chunks = samples.div_ceil(TILE).div_ceil(CHUNK_TILES);
        let (gl, gv) = (self.l.grad_len(), self.v.grad_len());
        let mut partial = vec![T::default(); chunks * (gl + gv)];
        {
            let outs = (Chunks::new(&mut partial, gl + gv), Chunks::new(dq, CHUNK_TILES * TILE * n),
                        Chunks::new(dqd, CHUNK_TILES * TILE * n), Chunks::new(dz, CHUNK_TILES * TILE * self.dz));
            let job = BwdJob { k: self, tape, dl, dh, dc, dg };
            pool.run(chunks, &|ci| {
                // SAFETY: each chunk index is taken by one task only.
                let (pg, q, qd, z) = unsafe { (outs.0.get(ci), outs.1.get(ci), outs.2.get(ci), outs.3.get(ci)) };
                T::backward_chunk(self.simd, &job, ci, pg, [q, qd, z]);
            });
        }
        let total = sum_chunks(&partial, gl + gv);
        Ok((unpad(&self.l, &total[..gl]), unpad(&self.v, &total[gl..])))
    }
}

impl<T: Real> TermsKernel<T> {
    fn streams(&self) -> usize {
        self.n + 1
    }

    /// Values of one tile's tape: x, ∂φ/∂q, then each network's blocks.
    fn tile_len(&self) -> usize {
        let rows = self.streams() * TILE;
        TILE * self.l.layers[0].ip + TILE * self.n * 2 + self.l.tape_len(rows) + potential::tape_len(&self.v, TILE, self.n)
    }

    fn width(&self) -> usize {
        self.l.width()
    }
}

#[doc(hidden)]
pub struct FwdJob<'a, T> {
    k: &'a TermsKernel<T>,
    q: &'a [T],
    qd: &'a [T],
    z: &'a [T],
    samples: usize,
    keep: bool,
}

#[doc(hidden)]
pub struct BwdJob<'a, T: KernelReal> {
    k: &'a TermsKernel<T>,
    tape: &'a Tape<T>,
    dl: &'a [T],
    dh: &'a [T],
    dc: &'a [T],
    dg: &'a [T],
}

/// A tile's x = [φ(q), z, 0…] and ∂φ/∂q (samples past the end: q = 0, z = 0; their outputs are dropped).
#[inline(always)]
fn tile_inputs<T: Real>(k: &TermsKernel<T>, q: &[T], z: &[T], first: usize, count: usize, x: &mut [T], dphi: &mut [T]) {
    let (n, dz, ip) = (k.n, k.dz, k.l.layers[0].ip);
    x.fill(T::default());
    dphi.fill(T::default());
    for r in 0..count {
        let s = first + r;
        for j in 0..n {
            let (ca, cb) = k.cols[j];
            let qj = q[s * n + j];
            if cb == usize::MAX {
                x[r * ip + ca] = qj;
                dphi[(r * n + j) * 2] = T::of(1.0);
            } else {
                let (sn, cs) = qj.sin_cos();
                x[r * ip + ca] = cs;
                x[r * ip + cb] = sn;
                dphi[(r * n + j) * 2] = -sn;
                dphi[(r * n + j) * 2 + 1] = cs;
            }
        }
        x[r * ip + k.dphi..r * ip + k.dphi + dz].copy_from_slice(&z[s * dz..(s + 1) * dz]);
    }
    // padding rows keep φ(0) so every row is a valid input (cos 0 = 1)
    for r in count..TILE {
        for j in 0..n {
            let (ca, cb) = k.cols[j];
            if cb != usize::MAX {
                x[r * ip + ca] = T::of(1.0);
            }
        }
    }
}

/// Samples that go through the head side by side (a tile is a whole number of such groups).
const HL: usize = 16;
type Ln<T> = Lanes<T, HL>;
const _: () = assert!(TILE % HL == 0);

/// The network outputs of samples r0..r0+HL of a tile from its tape: the inertia network's output block and
/// the potential's g/v_scale (`gq`, TILE × n).
#[inline(always)]
fn outs_of<T: Real>(k: &TermsKernel<T>, lo: &[T], gq: &[T], r0: usize) -> (Outs<Ln<T>>, [Ln<T>; NMAX]) {
    let (n, m) = (k.n, k.n * (k.n + 1) / 2);
    let opl = k.l.layers.last().unwrap().op;
    let z = Ln::<T>::default();
    let mut o = Outs { u: [z; MMAX], ud: [[z; MMAX]; NMAX] };
    let mut gv = [z; NMAX];
    for l in 0..HL {
        let r = r0 + l;
        for i in 0..m {
            o.u[i].0[l] = lo[r * opl + i];
        }
        for kk in 0..n {
            let row = (1 + kk) * TILE + r;
            for i in 0..m {
                o.ud[kk][i].0[l] = lo[row * opl + i];
            }
            gv[kk].0[l] = gq[r * n + kk];
        }
    }
    (o, gv)
}

/// Rows r0.. of an (N × w) array as lanes (zero past `count` rows).
#[inline(always)]
fn gather<T: Real, const W: usize>(a: &[T], w: usize, first: usize, count: usize) -> [Ln<T>; W] {
    let mut out = [Ln::<T>::default(); W];
    for l in 0..HL.min(count) {
        for i in 0..w {
            out[i].0[l] = a[(first + l) * w + i];
        }
    }
    out
}

/// Lanes back into rows first.. of an (N × w) array (the first `count` lanes).
#[inline(always)]
fn scatter<T: Real>(v: &[Ln<T>], w: usize, a: &mut [T], first: usize, count: usize) {
    for l in 0..HL.min(count) {
        for i in 0..w {
            a[(first + l) * w + i] = v[i].0[l];
        }
    }
}

#[inline(always)]
pub(super) fn forward_chunk<T: Real, const FMA: bool, const WIDE: bool>(job: &FwdJob<T>, ci: usize, tape: &mut [T], outs: [&mut [T]; 4]) {
    let k = job.k;
    let (n, s) = (k.n, k.streams());
    let rows = s * TILE;
    let (ip0, tl) = (k.l.layers[0].ip, k.tile_len());
    // without a tape, one tile's worth of it is reused tile after tile
    let mut own = if job.keep { Vec::new() } else { vec![T::default(); tl] };
    let [lo, ho, co, go] = outs;
    let first_tile = ci * CHUNK_TILES;
    let tiles = (job.samples.div_ceil(TILE) - first_tile).min(CHUNK_TILES);
    for ti in 0..tiles {
        let first = (first_tile + ti) * TILE;
        let count = (job.samples - first).min(TILE);
        let tt = if job.keep { &mut tape[ti * tl..(ti + 1) * tl] } else { &mut own[..] };
        let (x, rest) = tt.split_at_mut(TILE * ip0);
        let (dphi, rest) = rest.split_at_mut(TILE * n * 2);
        tile_inputs(k, job.q, job.z, first, count, x, dphi);
        let (lt, vt) = rest.split_at_mut(k.l.tape_len(rows));
        let tile = Tile { t: TILE, s, x, dphi, cols: &k.cols };
        net::forward::<T, FMA, WIDE>(&k.l, &tile, lt);
        potential::forward::<T, FMA, WIDE>(&k.v, &tile, vt);
        let (lo_t, vo_t) = (&lt[k.l.out_offset(rows)..], &vt[potential::g_offset(&k.v, TILE, n)..]);
        let of = |x: T| Ln::<T>::of(x.to_f64());
        for r0 in (0..count).step_by(HL) {
            let (o, gv) = outs_of(k, lo_t, vo_t, r0);
            let c = count - r0;
            let qd = gather::<T, NMAX>(job.qd, n, first + r0, c);
            let z = Ln::<T>::default();
            let (mut l, mut h, mut cc, mut g) = ([z; NMAX * NMAX], [z; NMAX * NMAX], [z; NMAX], [z; NMAX]);
            head::forward(n, &o, &gv, &qd, of(k.offset), of(k.v_scale), &mut l, &mut h, &mut cc, &mut g);
            let e = ti * TILE + r0;
            scatter(&l[..n * n], n * n, lo, e, c);
            scatter(&h[..n * n], n * n, ho, e, c);
            scatter(&cc[..n], n, co, e, c);
            scatter(&g[..n], n, go, e, c);
        }
    }
}

#[inline(always)]
pub(super) fn backward_chunk<T: KernelReal, const FMA: bool, const WIDE: bool>(job: &BwdJob<T>, ci: usize, grad: &mut [T], outs: [&mut [T]; 3]) {
    let k = job.k;
    let (n, s, dz) = (k.n, k.streams(), k.dz);
    let rows = s * TILE;
    let (ip0, tl) = (k.l.layers[0].ip, k.tile_len());
    let opl = k.l.layers.last().unwrap().op;
    let samples = job.tape.samples;
    let mut bufs = BackBufs::new(rows * k.width());
    let mut pbufs = PotBufs::new(&k.v, TILE);
    let mut gx = vec![T::default(); TILE * ip0];
    let mut gdphi = vec![T::default(); TILE * n * 2];
    let (gl, gv_) = grad.split_at_mut(k.l.grad_len());
    let [dq, dqd, dzo] = outs;
    let first_tile = ci * CHUNK_TILES;
    let tiles = (samples.div_ceil(TILE) - first_tile).min(CHUNK_TILES);
    for ti in 0..tiles {
        let first = (first_tile + ti) * TILE;
        let count = (samples - first).min(TILE);
        let tt = &job.tape.data[(first_tile + ti) * tl..(first_tile + ti + 1) * tl];
        let (x, rest) = tt.split_at(TILE * ip0);
        let (dphi, rest) = rest.split_at(TILE * n * 2);
        let (lt, vt) = rest.split_at(k.l.tape_len(rows));
        let tile = Tile { t: TILE, s, x, dphi, cols: &k.cols };
        let (lo_t, vo_t) = (&lt[k.l.out_offset(rows)..], &vt[potential::g_offset(&k.v, TILE, n)..]);
        // the head's reverse, sample by sample, into the output blocks' gradients
        let mut gu_l = vec![T::default(); rows * opl];
        let mut gu_v = vec![T::default(); TILE * n];
        let m = n * (n + 1) / 2;
        let of = |x: T| Ln::<T>::of(x.to_f64());
        let nn = n * n;
        for r0 in (0..count).step_by(HL) {
            let (o, _) = outs_of(k, lo_t, vo_t, r0);
            let (c, e) = (count - r0, first + r0);
            let qd = gather::<T, NMAX>(&job.tape.qd, n, e, c);
            let (dl, dh) = (gather::<T, { NMAX * NMAX }>(job.dl, nn, e, c), gather::<T, { NMAX * NMAX }>(job.dh, nn, e, c));
            let (dc, dg) = (gather::<T, NMAX>(job.dc, n, e, c), gather::<T, NMAX>(job.dg, n, e, c));
            let back = head::backward(n, &o, &qd, of(k.offset), of(k.v_scale), &dl, &dh, &dc, &dg);
            for l in 0..HL {
                let r = r0 + l;
                for i in 0..m {
                    gu_l[r * opl + i] = back.u[i].0[l];
                }
                for kk in 0..n {
                    let row = (1 + kk) * TILE + r;
                    for i in 0..m {
                        gu_l[row * opl + i] = back.ud[kk][i].0[l];
                    }
                    gu_v[r * n + kk] = back.gv[kk].0[l];
                }
            }
            scatter(&back.qd[..n], n, dqd, ti * TILE + r0, c);
        }
        gx.fill(T::default());
        gdphi.fill(T::default());
        bufs.g[..rows * opl].copy_from_slice(&gu_l);
        net::backward::<T, FMA, WIDE>(&k.l, &tile, lt, &mut bufs, gl, &mut gx, &mut gdphi);
        potential::backward::<T, FMA, WIDE>(&k.v, &tile, vt, &gu_v, &mut pbufs, gv_, &mut gx, &mut gdphi);
        // x̄ and ∂φ/∂q's gradient to q̄ (φ = cos, sin: ∂/∂q of (cos, sin, −sin, cos) = (−sin, cos, −cos, −sin)); z̄
        for r in 0..count {
            let e = ti * TILE + r;
            for j in 0..n {
                let (ca, cb) = k.cols[j];
                let gp = &gdphi[(r * n + j) * 2..(r * n + j) * 2 + 2];
                dq[e * n + j] = if cb == usize::MAX {
                    gx[r * ip0 + ca]
                } else {
                    let (sn, cs) = (x[r * ip0 + cb], x[r * ip0 + ca]);
                    gx[r * ip0 + cb] * cs - gx[r * ip0 + ca] * sn - gp[0] * cs - gp[1] * sn
                };
            }
            dzo[e * dz..(e + 1) * dz].copy_from_slice(&gx[r * ip0 + k.dphi..r * ip0 + k.dphi + dz]);
        }
    }
}
