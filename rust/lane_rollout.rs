//! Lane-major batched rollouts, the opt-in float32 path (`Model::rollout_batch_f32`): groups of
//! `T::LANES` rollouts (16 at float32, one AVX-512 register) whose whole state lives in SIMD lanes.
//! Per step: the group's inputs are gathered into lanes, the context layers, φ(q), the L, V and LIM
//! networks with their q-tangents run over the lanes (the kernels of `lanes.rs`, with the float32
//! copies of the weights), then each lane's tail (L, H, c, g, B, the solve, semi-implicit Euler) in
//! `T` arithmetic; the state never leaves the lanes between steps.
//!
//! Unlike the float64 batches (`batch.rs`), a lane is not the same bits as a single rollout: the
//! float32 result agrees with the float64 path to float32 rounding amplified by the dynamics (tested:
//! `tests/rollout_f32.rs`). Deterministic: a lane's arithmetic does not depend on its group, the
//! thread or the thread count. Models with extension terms are refused (`Error::Unsupported`).

use crate::delan::check_z;
use crate::error::{Error, Result};
use crate::lanes::{dense_lanes, first_lanes, net_lanes, supported, LaneBufs};
use crate::mlp::Mlp;
use crate::model::Model;
use crate::pool::{Chunks, Pool};
use crate::real::Real;
use crate::rollout::{Inputs, ZSeq};
use crate::simd::{simd_dispatch, Simd};

/// Scratch of one group of lane rollouts (float32 by default): make them once with
/// [`Model::lane_workspaces`], outside the hot loop.
#[derive(Debug, Clone)]
pub struct LaneWorkspace<T = f32> {
    n: usize,
    dz: usize,
    bufs: LaneBufs<T>,
    /// State, the step's τ and f_v, [joint][lane] / [lane].
    q: Vec<T>,
    qd: Vec<T>,
    tau: Vec<T>,
    fv: Vec<T>,
    /// The networks' outputs with tangents: L ([nt·n(n+1)/2][lane]), V ([nt][lane]), LIM ([n][lane]).
    out_l: Vec<T>,
    out_v: Vec<T>,
    out_b: Vec<T>,
    /// V's hidden activations (the reverse pass reads them back) and ∂V/∂φ, [unit][lane].
    stash: Vec<T>,
    gphi: Vec<T>,
    /// Per lane: still running, and the error that stopped it.
    active: Vec<bool>,
    status: Vec<Option<Error>>,
}

impl<T: Real> LaneWorkspace<T> {
    pub(crate) fn new(m: &Model) -> Self {
        let (n, lanes) = (m.n, T::LANES);
        let v = |len: usize| vec![T::default(); len * lanes];
        LaneWorkspace {
            n,
            dz: m.dz,
            bufs: LaneBufs::new(m),
            q: v(n),
            qd: v(n),
            tau: v(n),
            fv: v(1),
            out_l: v((n + 1) * n * (n + 1) / 2),
            out_v: v(n + 1),
            out_b: v(n),
            stash: v(m.net_v.layers[..m.net_v.layers.len() - 1].iter().map(|d| d.out).sum()),
            gphi: v(m.dphi),
            active: vec![false; lanes],
            status: vec![None; lanes],
        }
    }
}

/// One batch's inputs, shared by its groups.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Job<'a> {
    q0: &'a [f64],
    qd0: &'a [f64],
    inp: Inputs<'a>,
    bsz: usize,
    t_len: usize,
    dt: f64,
}

impl<'a> Job<'a> {
    /// Element b's inputs.
    fn element(&self, m: &Model, b: usize) -> ([&'a [f64]; 2], Inputs<'a>) {
        let (n, dz, t) = (m.n, m.dz, self.t_len);
        let inp = &self.inp;
        let sub = Inputs {
            tau: &inp.tau[b * t * n..(b + 1) * t * n],
            z: match inp.z {
                ZSeq::Keep => ZSeq::Keep,
                ZSeq::Const(z) => ZSeq::Const(&z[b * dz..(b + 1) * dz]),
                ZSeq::PerStep(z) => ZSeq::PerStep(&z[b * t * dz..(b + 1) * t * dz]),
            },
            f_v: inp.f_v.map(|f| &f[b * t..(b + 1) * t]),
            tau_e: inp.tau_e.map(|f| &f[b * t * n..(b + 1) * t * n]),
        };
        ([&self.q0[b * n..(b + 1) * n], &self.qd0[b * n..(b + 1) * n]], sub)
    }
}

impl Model {
    /// Scratch for float32 batched rollouts of up to `bsz` elements (one per group of 16).
    pub fn lane_workspaces(&self, bsz: usize) -> Vec<LaneWorkspace> {
        (0..bsz.div_ceil(f32::LANES)).map(|_| LaneWorkspace::new(self)).collect()
    }

    /// `rollout_batch` computed in float32 (inputs and outputs stay float64): B rollouts in groups of
    /// 16 SIMD lanes, `lws` from `lane_workspaces(B)` (or more). The same shapes and errors as
    /// `rollout_batch` (the first failing element decides), plus `Error::Unsupported` for models with
    /// extension terms or more than 3 joints, and `IllConditioned` beyond cond(H) = 1e6.
    #[allow(clippy::too_many_arguments)]
    pub fn rollout_batch_f32(&self, pool: &Pool, lws: &mut [LaneWorkspace], q0: &[f64], qd0: &[f64], inp: Inputs, dt: f64, q_out: &mut [f64], qd_out: &mut [f64]) -> Result<()> {
        self.rollout_lanes(pool, lws, q0, qd0, inp, dt, q_out, qd_out, group_f32_simd)
    }

    #[allow(clippy::too_many_arguments)]
    pub(crate) fn rollout_lanes<T: Real>(&self, pool: &Pool, lws: &mut [LaneWorkspace<T>], q0: &[f64], qd0: &[f64], inp: Inputs, dt: f64, q_out: &mut [f64], qd_out: &mut [f64], run: GroupFn<T>) -> Result<()> {
        let n = self.n;
        if !supported(self) || self.ext.any() {
            return Err(Error::Unsupported("lane (float32) rollouts run models of up to 3 joints without extension terms; use float64".into()));
        }
        if !q0.len().is_multiple_of(n) {
            return Err(Error::InputShape(format!("q0 has {} values, not B·n with n = {n}", q0.len())));
        }
        let bsz = q0.len() / n;
        if bsz == 0 {
            return Ok(());
        }
        let t_len = self.check_batch(bsz, q0, qd0, &inp, q_out, qd_out)?;
        let groups = bsz.div_ceil(T::LANES);
        if lws.len() < groups || lws.iter().any(|w| (w.n, w.dz) != (n, self.dz)) {
            return Err(Error::InputShape(format!("need {groups} lane workspaces of this model (Model::lane_workspaces(B)), got {}", lws.len())));
        }
        let job = Job { q0, qd0, inp, bsz, t_len, dt };
        let per = T::LANES * (t_len + 1) * n;
        let (wc, qc, qdc) = (Chunks::new(&mut lws[..groups], 1), Chunks::new(q_out, per), Chunks::new(qd_out, per));
        pool.run(groups, &|g| {
            // SAFETY: the pool hands each index to exactly one task.
            let (lw, qo, qdo) = unsafe { (&mut wc.get(g)[0], qc.get(g), qdc.get(g)) };
            run(self.simd, self, lw, &job, g, qo, qdo);
        });
        let mut first = None;
        for (g, lw) in lws[..groups].iter_mut().enumerate() {
            for (l, st) in lw.status.iter_mut().enumerate() {
                if let Some(e) = st.take() {
                    first.get_or_insert_with(|| crate::batch::in_element(g * T::LANES + l, e));
                }
            }
        }
        first.map_or(Ok(()), Err)
    }
}

/// A group's rollout at the chosen code path.
pub(crate) type GroupFn<T> = fn(Simd, &Model, &mut LaneWorkspace<T>, &Job, usize, &mut [f64], &mut [f64]);

#[inline(always)]
fn group_f32<const FMA: bool, const WIDE: bool>(m: &Model, lw: &mut LaneWorkspace<f32>, job: &Job, g: usize, qo: &mut [f64], qdo: &mut [f64]) {
    rollout_group::<f32, 16, FMA, WIDE>(m, lw, job, g, qo, qdo)
}
simd_dispatch!(fn group_f32_simd(m: &Model, lw: &mut LaneWorkspace<f32>, job: &Job, g: usize, qo: &mut [f64], qdo: &mut [f64]) = group_f32;);

#[cfg(test)]
#[inline(always)]
fn group_f64<const FMA: bool, const WIDE: bool>(m: &Model, lw: &mut LaneWorkspace<f64>, job: &Job, g: usize, qo: &mut [f64], qdo: &mut [f64]) {
    rollout_group::<f64, 8, FMA, WIDE>(m, lw, job, g, qo, qdo)
}
#[cfg(test)]
simd_dispatch!(pub(crate) fn group_f64_simd(m: &Model, lw: &mut LaneWorkspace<f64>, job: &Job, g: usize, qo: &mut [f64], qdo: &mut [f64]) = group_f64;);

/// Group g (elements g·L..): check each element, load its state, then step all lanes together.
#[inline(always)]
fn rollout_group<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(m: &Model, lw: &mut LaneWorkspace<T>, job: &Job, g: usize, qo: &mut [f64], qdo: &mut [f64]) {
    let (n, per) = (m.n, (job.t_len + 1) * m.n);
    let (b0, cnt) = (g * L, L.min(job.bsz - g * L));
    for l in 0..L {
        lw.active[l] = false;
        let Some(e) = (l < cnt).then_some(b0 + l) else { continue };
        let ([q0, qd0], sub) = job.element(m, e);
        let r = m.check_rollout(q0, qd0, &sub, job.dt, [per; 2]).and_then(|_| match sub.z {
            ZSeq::Const(z) => check_z(m, z),
            ZSeq::Keep if m.dz > 0 => Err(Error::InputShape(format!("context z (dimension {}) not set", m.dz))),
            _ => Ok(()),
        });
        if let Err(err) = r {
            lw.status[l] = Some(err);
            continue;
        }
        lw.active[l] = true;
        qo[l * per..l * per + n].copy_from_slice(q0);
        qdo[l * per..l * per + n].copy_from_slice(qd0);
        for i in 0..n {
            (lw.q[i * L + l], lw.qd[i * L + l]) = (T::of(q0[i]), T::of(qd0[i]));
            if let ZSeq::Const(z) = sub.z {
                for (j, zj) in z.iter().enumerate() {
                    lw.bufs.zin[j * L + l] = T::of(*zj);
                }
            }
        }
    }
    if !matches!(job.inp.z, ZSeq::PerStep(_)) {
        context::<T, L, FMA, WIDE>(m, &mut lw.bufs);
    }
    for k in 0..job.t_len {
        if !lw.active.iter().any(|a| *a) {
            return;
        }
        gather::<T, L>(m, lw, job, b0, k);
        if matches!(job.inp.z, ZSeq::PerStep(_)) {
            context::<T, L, FMA, WIDE>(m, &mut lw.bufs);
        }
        pass::<T, L, FMA, WIDE>(m, lw);
        step_lanes::<T, L>(m, lw, job.dt);
        for l in 0..L {
            if !lw.active[l] {
                continue;
            }
            let at = l * per + (k + 1) * n;
            for i in 0..n {
                (qo[at + i], qdo[at + i]) = (lw.q[i * L + l].to_f64(), lw.qd[i * L + l].to_f64());
            }
            if !qo[at..at + n].iter().chain(&qdo[at..at + n]).all(|v| v.is_finite()) {
                (lw.active[l], lw.status[l]) = (false, Some(Error::Diverged { step: k + 1 }));
            }
        }
    }
}

/// Step k's τ, f_v and per-step z of the active lanes into the lanes.
#[inline(always)]
fn gather<T: Real, const L: usize>(m: &Model, lw: &mut LaneWorkspace<T>, job: &Job, b0: usize, k: usize) {
    let (n, dz, t) = (m.n, m.dz, job.t_len);
    for l in 0..L {
        if !lw.active[l] {
            continue;
        }
        let b = b0 + l;
        for i in 0..n {
            lw.tau[i * L + l] = T::of(job.inp.tau[(b * t + k) * n + i]);
        }
        lw.fv[l] = T::of(job.inp.f_v.map_or(0.0, |f| f[b * t + k]));
        if let ZSeq::PerStep(z) = job.inp.z {
            for (j, zj) in z[(b * t + k) * dz..(b * t + k + 1) * dz].iter().enumerate() {
                lw.bufs.zin[j * L + l] = T::of(*zj);
            }
        }
    }
}

/// The first layers' z parts (b + W_z z) from the lanes' z.
#[inline(always)]
fn context<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(m: &Model, s: &mut LaneBufs<T>) {
    for (t, net) in T::nets(m).iter().enumerate() {
        let Some(net) = net else { continue };
        match &net.z_part {
            Some(d) => dense_lanes::<T, L, FMA, WIDE>(d, 1, &s.zin, &mut s.zb[t]),
            None => {
                for (i, bi) in net.layers[0].b.iter().enumerate() {
                    s.zb[t][i * L..(i + 1) * L].fill(*bi);
                }
            }
        }
    }
}

/// φ(q) and dφ/dq of the lanes, then the three networks (outputs with tangents into `out_*`).
#[inline(always)]
fn pass<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(m: &Model, lw: &mut LaneWorkspace<T>) {
    let (n, nt) = (m.n, m.n + 1);
    let s = &mut lw.bufs;
    for (j, &(ca, cb)) in m.phi_cols.iter().enumerate() {
        let q: &[T; L] = lw.q[j * L..(j + 1) * L].try_into().unwrap();
        for l in 0..L {
            let (d0, d1) = ((2 * j) * L + l, (2 * j + 1) * L + l);
            if cb == usize::MAX {
                (s.phi[ca * L + l], s.dphi[d0], s.dphi[d1]) = (q[l], T::of(1.0), T::default());
            } else {
                let (sn, cs) = q[l].sin_cos();
                (s.phi[ca * L + l], s.phi[cb * L + l], s.dphi[d0], s.dphi[d1]) = (cs, sn, -sn, cs);
            }
        }
    }
    for (t, net) in T::nets(m).iter().enumerate() {
        let Some(net) = net else { continue };
        if t == 1 {
            grad_lanes::<T, L, FMA, WIDE>(m, net, lw);
            continue;
        }
        let s = &mut lw.bufs;
        let ntn = if t == 2 { 1 } else { nt };
        net_lanes::<T, L, FMA, WIDE>(net, &s.zb[t], &s.phi, &s.dphi, &m.phi_cols, ntn, &mut s.a, &mut s.b);
        let dst = if t == 0 { &mut lw.out_l } else { &mut lw.out_b };
        let len = dst.len().min(ntn * net.d_out() * L);
        debug_assert!(t != 2 || len == n * L);
        dst[..len].copy_from_slice(&s.a[..len]);
    }
}

/// g = ∂V/∂q_k (before v_scale) of every lane into `out_v[(k+1)·L..]` by one reverse pass through V:
/// the value forward (hidden activations kept in `stash`), then δ back through the transposed layers
/// (`Mlp::back`) and φ's derivative. It replaces the forward tangents (n extra blocks per hidden layer)
/// with one transposed product per hidden layer; V itself is not needed for the dynamics.
#[inline(always)]
fn grad_lanes<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(m: &Model, net: &Mlp<T>, lw: &mut LaneWorkspace<T>) {
    let (s, stash, last) = (&mut lw.bufs, &mut lw.stash, net.layers.len() - 1);
    let one = T::of(1.0);
    first_lanes::<T, L, FMA>(&net.layers[0], &s.zb[1], &s.phi, &s.dphi, &m.phi_cols, 1, &mut s.a);
    let mut off = 0;
    for l in 0..last {
        let w = net.layers[l].out * L;
        T::tanh_tangent::<FMA, WIDE>(&mut s.a, w, 1);
        stash[off..off + w].copy_from_slice(&s.a[..w]);
        off += w;
        if l + 1 < last {
            dense_lanes::<T, L, FMA, WIDE>(&net.layers[l + 1], 1, &s.a, &mut s.b);
            std::mem::swap(&mut s.a, &mut s.b);
        }
    }
    // δ at the last hidden layer: the output weights times tanh' = 1 − h²
    let out = &net.layers[last];
    off -= out.inp * L;
    for i in 0..out.inp {
        // a local copy: with two views into workspace buffers LLVM left this loop scalar (aliasing)
        let (h, w): ([T; L], T) = (*at::<T, L>(stash, off / L + i), out.rows[i]);
        let d: &mut [T; L] = (&mut s.a[i * L..(i + 1) * L]).try_into().unwrap();
        for l in 0..L {
            d[l] = w * (one - h[l] * h[l]);
        }
    }
    for l in (1..last).rev() {
        dense_lanes::<T, L, FMA, WIDE>(&net.back[l], 1, &s.a, &mut s.b);
        off -= net.layers[l - 1].out * L;
        for i in 0..net.layers[l - 1].out {
            let h: [T; L] = *at::<T, L>(stash, off / L + i);
            let d: &mut [T; L] = (&mut s.b[i * L..(i + 1) * L]).try_into().unwrap();
            for j in 0..L {
                d[j] = d[j] * (one - h[j] * h[j]);
            }
        }
        std::mem::swap(&mut s.a, &mut s.b);
    }
    dense_lanes::<T, L, FMA, WIDE>(&net.back[0], 1, &s.a, &mut lw.gphi);
    for (k, &(ca, cb)) in m.phi_cols.iter().enumerate() {
        let (ga, va, vb) = (at::<T, L>(&lw.gphi, ca), at::<T, L>(&s.dphi, 2 * k), at::<T, L>(&s.dphi, 2 * k + 1));
        let dst: &mut [T; L] = (&mut lw.out_v[(k + 1) * L..(k + 2) * L]).try_into().unwrap();
        for l in 0..L {
            dst[l] = ga[l] * va[l];
        }
        if cb != usize::MAX {
            let gb = at::<T, L>(&lw.gphi, cb);
            for l in 0..L {
                dst[l] = dst[l] + gb[l] * vb[l];
            }
        }
    }
}

/// acc += a·b lane by lane (unfused).
#[inline(always)]
fn acc<T: Real, const L: usize>(acc: &mut [T; L], a: &[T; L], b: &[T; L]) {
    for l in 0..L {
        acc[l] = acc[l] + a[l] * b[l];
    }
}

/// The L rows of lane buffer `buf` at index e ([e][lane] layout).
#[inline(always)]
fn at<T: Real, const L: usize>(buf: &[T], e: usize) -> &[T; L] {
    buf[e * L..(e + 1) * L].try_into().unwrap()
}

/// q̈ of every lane from the networks' outputs (as `eval_tail` and `forward_after_eval`, in `T`;
/// each operation over all lanes at once), then semi-implicit Euler on the state. A lane whose H is
/// ill-conditioned is stopped with its error.
#[inline(always)]
fn step_lanes<T: Real, const L: usize>(m: &Model, lw: &mut LaneWorkspace<T>, dt: f64) {
    let (n, nn, mo) = (m.n, m.n * m.n, m.n * (m.n + 1) / 2);
    let zero = [T::default(); L];
    let (mut lm, mut dl, mut h) = ([zero; 9], [zero; 27], [zero; 9]);
    let off = T::of(m.meta.softplus_offset);
    for i in 0..n {
        let (u, mut sg, d) = (at::<T, L>(&lw.out_l, i), zero, &mut lm[i * n + i]);
        for l in 0..L {
            let (sp, s) = u[l].softplus_sigmoid();
            (d[l], sg[l]) = (sp + off, s);
        }
        for k in 0..n {
            let (du, d) = (at::<T, L>(&lw.out_l, (k + 1) * mo + i), &mut dl[k * nn + i * n + i]);
            for l in 0..L {
                d[l] = sg[l] * du[l];
            }
        }
    }
    let mut t = n;
    for i in 1..n {
        for j in 0..i {
            lm[i * n + j] = *at::<T, L>(&lw.out_l, t);
            for k in 0..n {
                dl[k * nn + i * n + j] = *at::<T, L>(&lw.out_l, (k + 1) * mo + t);
            }
            t += 1;
        }
    }
    for i in 0..n {
        for j in 0..=i {
            let mut s = zero;
            for k in 0..=j {
                acc(&mut s, &lm[i * n + k], &lm[j * n + k]);
            }
            (h[i * n + j], h[j * n + i]) = (s, s);
        }
    }
    let qd: [[T; L]; 3] = std::array::from_fn(|i| if i < n { *at::<T, L>(&lw.qd, i) } else { zero });
    // Lᵀ q̇ → t1; L̇ → ld; L̇ᵀ q̇ → t2
    let (mut t1, mut t2, mut ld) = ([zero; 3], [zero; 3], [zero; 9]);
    for j in 0..n {
        for i in j..n {
            acc(&mut t1[j], &lm[i * n + j], &qd[i]);
        }
    }
    for e in 0..nn {
        for k in 0..n {
            acc(&mut ld[e], &dl[k * nn + e], &qd[k]);
        }
    }
    for j in 0..n {
        for i in 0..n {
            acc(&mut t2[j], &ld[i * n + j], &qd[i]);
        }
    }
    let rhs = rhs_lanes::<T, L>(m, lw, &lm, &dl, &ld, &qd, &t1, &t2);
    let qdd = solve_lanes::<T, L>(n, &h, &lm, &rhs, lw);
    let dt = T::of(dt);
    for i in 0..n {
        let (q, v): (&mut [T; L], &mut [T; L]) = ((&mut lw.q[i * L..(i + 1) * L]).try_into().unwrap(), (&mut lw.qd[i * L..(i + 1) * L]).try_into().unwrap());
        for l in 0..L {
            v[l] = qd[i][l] + dt * qdd[i][l];
            q[l] = q[l] + dt * v[l];
        }
    }
}

/// τ − (c + g − B f_v) over the lanes, c = L̇ t1 + L t2 − (∂L/∂q_i ᵀ q̇)·t1.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn rhs_lanes<T: Real, const L: usize>(m: &Model, lw: &LaneWorkspace<T>, lm: &[[T; L]; 9], dl: &[[T; L]; 27], ld: &[[T; L]; 9], qd: &[[T; L]; 3], t1: &[[T; L]; 3], t2: &[[T; L]; 3]) -> [[T; L]; 3] {
    let (n, nn) = (m.n, m.n * m.n);
    let zero = [T::default(); L];
    let (vs, ls, lim) = (T::of(m.meta.v_scale), T::of(m.meta.lim_scale), m.net_lim.is_some());
    let mut rhs = [zero; 3];
    for i in 0..n {
        let (mut s, mut d) = (zero, zero);
        for j in 0..n {
            let mut w = zero;
            for a in 0..n {
                acc(&mut w, &dl[i * nn + a * n + j], &qd[a]);
            }
            let (ldij, t1j, lmij, t2j) = (&ld[i * n + j], &t1[j], &lm[i * n + j], &t2[j]);
            for l in 0..L {
                s[l] = s[l] + ldij[l] * t1j[l] + lmij[l] * t2j[l];
                d[l] = d[l] + w[l] * t1j[l];
            }
        }
        let (gv, bv, tau, fv) = (at::<T, L>(&lw.out_v, i + 1), at::<T, L>(&lw.out_b, i), at::<T, L>(&lw.tau, i), at::<T, L>(&lw.fv, 0));
        let r = &mut rhs[i];
        for l in 0..L {
            let b = if lim { ls * bv[l] } else { T::default() };
            r[l] = tau[l] - ((s[l] - d[l]) + vs * gv[l] - b * fv[l]);
        }
    }
    rhs
}

/// H⁻¹ rhs over the lanes as `dynamics::solve` (n = 1, 2 analytic; n = 3 by L); an active lane
/// beyond `T::COND_MAX` (or with det ≤ 0) is stopped with `IllConditioned`.
#[inline(always)]
fn solve_lanes<T: Real, const L: usize>(n: usize, h: &[[T; L]; 9], lm: &[[T; L]; 9], rhs: &[[T; L]; 3], lw: &mut LaneWorkspace<T>) -> [[T; L]; 3] {
    let (zero, one) = (T::default(), T::of(1.0));
    let mut out = [[zero; L]; 3];
    let (mut det, mut cond) = ([zero; L], [0.0f64; L]);
    match n {
        1 => {
            for l in 0..L {
                (det[l], out[0][l]) = (h[0][l], rhs[0][l] / h[0][l]);
            }
        }
        2 => {
            let (a, b, d) = (&h[0], &h[1], &h[3]);
            for l in 0..L {
                det[l] = a[l] * d[l] - b[l] * b[l];
                let disc = (T::of(0.25) * (a[l] - d[l]) * (a[l] - d[l]) + b[l] * b[l]).sqrt();
                let lmax = T::of(0.5) * (a[l] + d[l]) + disc;
                cond[l] = (lmax / (det[l] / lmax)).to_f64();
                let inv = one / det[l];
                out[0][l] = (d[l] * rhs[0][l] - b[l] * rhs[1][l]) * inv;
                out[1][l] = (a[l] * rhs[1][l] - b[l] * rhs[0][l]) * inv;
            }
        }
        _ => {
            for l in 0..L {
                let (mut dmin, mut dmax, mut dt) = (f64::INFINITY, 0.0f64, 1.0f64);
                for i in 0..n {
                    let d = lm[i * n + i][l].to_f64();
                    (dmin, dmax, dt) = (dmin.min(d), dmax.max(d), dt * d * d);
                }
                (det[l], cond[l]) = (T::of(dt), if dmin > 0.0 { (dmax / dmin) * (dmax / dmin) } else { f64::INFINITY });
                for i in 0..n {
                    let mut s = rhs[i][l];
                    for k in 0..i {
                        s = s - lm[i * n + k][l] * out[k][l];
                    }
                    out[i][l] = s / lm[i * n + i][l];
                }
                for i in (0..n).rev() {
                    let mut s = out[i][l];
                    for k in i + 1..n {
                        s = s - lm[k * n + i][l] * out[k][l];
                    }
                    out[i][l] = s / lm[i * n + i][l];
                }
            }
        }
    }
    for l in 0..L {
        let d = det[l].to_f64();
        if lw.active[l] && (!(d > 0.0) || !d.is_finite() || !(cond[l] <= T::COND_MAX)) {
            let c = if cond[l].is_finite() && cond[l] > 0.0 { cond[l] } else { f64::INFINITY };
            (lw.active[l], lw.status[l]) = (false, Some(Error::IllConditioned { det: d, cond: c }));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{random_weights, SynthConfig};

    /// The lane algorithm itself, run in float64: the float64 batches to rounding (the operations differ
    /// in order only), so what the float32 path adds is float32 rounding alone.
    #[test]
    fn f64_lanes_match_the_f64_batches() {
        let d = SynthConfig::default();
        for cfg in [d.clone(), SynthConfig { joint_types: vec!["revolute", "prismatic", "revolute"], ..d.clone() }, SynthConfig { encoder: "none", lim: false, ..d }] {
            let m = Model::from_bytes(&random_weights(&cfg)).unwrap();
            let (n, bsz, t_len) = (m.n, 19, 20);
            let f = |k: usize, s: f64| (0..k).map(|i| ((i as f64) * 0.37 + s).sin()).collect::<Vec<f64>>();
            let (q0, tau, z, f_v) = (f(bsz * n, 0.1), f(bsz * t_len * n, 0.2), f(bsz * t_len * m.dz, 0.3), f(bsz * t_len, 0.4));
            let f_v: Vec<f64> = f_v.iter().map(|v| 200.0 * (1.0 + v)).collect();
            let zs = if m.dz > 0 { ZSeq::PerStep(&z) } else { ZSeq::Keep };
            let inp = Inputs { tau: &tau, z: zs, f_v: Some(&f_v), tau_e: None };
            let pool = Pool::new(1).unwrap();
            let len = bsz * (t_len + 1) * n;
            let (mut q, mut qd, mut ql, mut qdl) = (vec![0.0; len], vec![0.0; len], vec![0.0; len], vec![0.0; len]);
            let mut wss: Vec<_> = (0..bsz).map(|_| m.workspace()).collect();
            m.rollout_batch(&pool, &mut wss, &q0, &q0, inp, 0.005, &mut q, &mut qd).unwrap();
            let mut lws: Vec<LaneWorkspace<f64>> = (0..bsz.div_ceil(8)).map(|_| LaneWorkspace::new(&m)).collect();
            m.rollout_lanes(&pool, &mut lws, &q0, &q0, inp, 0.005, &mut ql, &mut qdl, group_f64_simd).unwrap();
            let scale = q.iter().chain(&qd).fold(0.0f64, |s, v| s.max(v.abs()));
            let worst = q.iter().chain(&qd).zip(ql.iter().chain(&qdl)).fold(0.0f64, |s, (a, b)| s.max((a - b).abs()));
            assert!(worst < 1e-12 * scale, "n = {n}: {worst:e} (scale {scale})");
        }
    }
}
