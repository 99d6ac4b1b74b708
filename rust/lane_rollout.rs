//! Lane-major batched rollouts, the opt-in float32 path (`Model::rollout_batch_f32`): groups of
//! `T::LANES` rollouts (16 at float32, one AVX-512 register) whose whole state lives in SIMD lanes.
//! Per step: the group's inputs are gathered into lanes, the context layers, φ(q), the L and LIM
//! networks (L with its q-tangents) run over the lanes (the kernels of `lanes.rs`, with the float32
//! copies of the weights), g = ∂V/∂q by one reverse pass through V (`grad_lanes`), then the dynamics
//! tail over all lanes (`lane_tail.rs`: L, H, c, B, the solve, semi-implicit Euler) in `T`
//! arithmetic; the state never leaves the lanes between steps.
//!
//! Unlike the float64 batches (`batch.rs`), a lane is not the same bits as a single rollout: the
//! float32 result agrees with the float64 path to float32 rounding amplified by the dynamics (tested:
//! `tests/rollout_f32.rs`). Deterministic: a lane's arithmetic does not depend on its group, the
//! thread or the thread count. Models with extension terms are refused (`Error::Unsupported`).

use crate::delan::check_z;
use crate::error::{Error, Result};
use crate::lane_tail::{at, step_lanes};
use crate::lanes::{dense_lanes, first_lanes, first_tangents, rest_lanes, supported, LaneBufs};
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
    pub(crate) n: usize,
    pub(crate) dz: usize,
    pub(crate) bufs: LaneBufs<T>,
    /// State, the step's τ and f_v, [joint][lane] / [lane].
    pub(crate) q: Vec<T>,
    pub(crate) qd: Vec<T>,
    pub(crate) tau: Vec<T>,
    pub(crate) fv: Vec<T>,
    /// The networks' outputs: L with its q-tangents ([nt·n(n+1)/2][lane]), ∂V/∂q_k at [k+1][lane] (block 0
    /// unused), LIM ([n][lane]).
    pub(crate) out_l: Vec<T>,
    pub(crate) out_v: Vec<T>,
    pub(crate) out_b: Vec<T>,
    /// V's hidden activations (the reverse pass reads them back) and ∂V/∂φ, [unit][lane].
    pub(crate) stash: Vec<T>,
    pub(crate) gphi: Vec<T>,
    /// Per lane: still running, and the error that stopped it.
    pub(crate) active: Vec<bool>,
    pub(crate) status: Vec<Option<Error>>,
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
    /// extension terms, more than 3 joints or no hidden layer in V, and `IllConditioned` beyond
    /// cond(H) = 1e6 (`Real::COND_MAX`).
    #[allow(clippy::too_many_arguments)]
    pub fn rollout_batch_f32(&self, pool: &Pool, lws: &mut [LaneWorkspace], q0: &[f64], qd0: &[f64], inp: Inputs, dt: f64, q_out: &mut [f64], qd_out: &mut [f64]) -> Result<()> {
        self.rollout_lanes(pool, lws, q0, qd0, inp, dt, q_out, qd_out, group_f32_simd)
    }

    /// `rollout_batch_f32` at any `Real` (float64 lanes: the tests' check of the lane algorithm).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn rollout_lanes<T: Real>(&self, pool: &Pool, lws: &mut [LaneWorkspace<T>], q0: &[f64], qd0: &[f64], inp: Inputs, dt: f64, q_out: &mut [f64], qd_out: &mut [f64], run: GroupFn<T>) -> Result<()> {
        let n = self.n;
        if !supported(self) || self.ext.any() || self.net_v.layers.len() < 2 {
            let msg = "lane (float32) rollouts run models of up to 3 joints, with a hidden layer in V and without extension terms; use float64";
            return Err(Error::Unsupported(msg.into()));
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
        }
        if let ZSeq::Const(z) = sub.z {
            for (j, zj) in z.iter().enumerate() {
                lw.bufs.zin[j * L + l] = T::of(*zj);
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
        first::<T, L, FMA, WIDE>(net, &s.zb[t], &s.phi, &s.dphi, &m.phi_cols, ntn, &mut s.a);
        rest_lanes::<T, L, FMA, WIDE>(net, ntn, &mut s.a, &mut s.b);
        let dst = if t == 0 { &mut lw.out_l } else { &mut lw.out_b };
        let len = dst.len().min(ntn * net.d_out() * L);
        debug_assert!(t != 2 || len == n * L);
        dst[..len].copy_from_slice(&s.a[..len]);
    }
}

/// Layer 0's pre-activations over the lanes: W0[:, φ] φ as a GEMM (`Mlp::phi_part`) plus the z part
/// `zb`, then the nt − 1 tangent blocks (`first_tangents`).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn first<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(net: &Mlp<T>, zb: &[T], phi: &[T], dphi: &[T], cols: &[(usize, usize)], nt: usize, a: &mut [T]) {
    let Some(p) = &net.phi_part else {
        return first_lanes::<T, L, FMA>(&net.layers[0], zb, phi, dphi, cols, nt, a);
    };
    let h = p.out * L;
    dense_lanes::<T, L, FMA, WIDE>(p, 1, phi, a);
    for (x, z) in a[..h].iter_mut().zip(&zb[..h]) {
        *x = *x + *z;
    }
    first_tangents::<T, L, FMA>(&net.layers[0], dphi, cols, nt, a);
}

/// g = ∂V/∂q_k (before v_scale) of every lane into `out_v[(k+1)·L..]` by one reverse pass through V:
/// the value forward (hidden activations kept in `stash`), then δ back through the transposed layers
/// (`Mlp::back`) and φ's derivative. It replaces the forward tangents (n extra blocks per hidden layer)
/// with one transposed product per hidden layer; V itself is not needed for the dynamics.
#[inline(always)]
fn grad_lanes<T: Real, const L: usize, const FMA: bool, const WIDE: bool>(m: &Model, net: &Mlp<T>, lw: &mut LaneWorkspace<T>) {
    let (s, stash, last) = (&mut lw.bufs, &mut lw.stash, net.layers.len() - 1);
    let one = T::of(1.0);
    first::<T, L, FMA, WIDE>(net, &s.zb[1], &s.phi, &s.dphi, &m.phi_cols, 1, &mut s.a);
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
