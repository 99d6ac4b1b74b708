//! The Lagrangian dynamics (DESIGN.md section 2) with hand-derived forward-mode derivatives.
//!
//! One pass per sample: φ(q) and dφ/dq, the L and V networks with their q-tangents, then
//!   H = L Lᵀ,  c = Ḣ q̇ − ½ ∂(q̇ᵀ H q̇)/∂q,  g = v_scale ∂V/∂q,  B = lim_scale · lim([φ; z]).
//! With L̇ = Σ_k ∂L/∂q_k q̇_k:  Ḣ q̇ = L̇ (Lᵀ q̇) + L (L̇ᵀ q̇)  and  ½ ∂(q̇ᵀ H q̇)/∂q_k = (∂L/∂q_k ᵀ q̇)·(Lᵀ q̇).
//!
//! Everything a call needs lives in a preallocated [`Workspace`]; no call allocates. The public calls
//! (inverse/forward dynamics, terms, energy) and the solve: `dynamics.rs`.

use crate::error::{Error, Result};
use crate::lanes::LaneBufs;
use crate::mlp::{mlp_rest, Dense, Mlp};
use crate::real::Real;
use crate::model::Model;
use crate::simd::simd_dispatch;

/// Largest condition number of H accepted by forward dynamics (beyond it q̈ has no correct digits
/// worth integrating; the caller gets `Error::IllConditioned` instead of garbage).
pub const COND_MAX: f64 = 1e12;

/// The recorded exoskeleton torque for the extension terms that need it (DESIGN.md section 4,
/// `exolan.extensions`). Without it (None) those terms see τ_e = 0.
#[derive(Debug, Clone, Copy)]
pub struct ExoTorque<'a> {
    /// τ_e(t) as recorded, N m.
    pub now: &'a [f64],
    /// Applied torque τ_app = τ_e(t − d) (None: τ_e(t), i.e. no delay).
    pub applied: Option<&'a [f64]>,
    /// dτ_app/dt for the strap correction of q̇ (None: 0).
    pub applied_d: Option<&'a [f64]>,
    /// d²τ_app/dt² for the strap correction of q̈ (None: 0).
    pub applied_dd: Option<&'a [f64]>,
}

impl<'a> ExoTorque<'a> {
    /// Only the current recorded torque (no delay, no derivatives).
    pub fn now(tau_e: &'a [f64]) -> Self {
        ExoTorque { now: tau_e, applied: None, applied_d: None, applied_dd: None }
    }
    pub(crate) fn app(&self) -> &'a [f64] {
        self.applied.unwrap_or(self.now)
    }
}

/// Scratch memory for one thread of evaluation, sized at creation from the model. `Workspace<f32>`
/// (`Model::workspace_f32`): the opt-in float32 single-sample calls (`single_f32.rs`).
#[derive(Debug, Clone)]
pub struct Workspace<T = f64> {
    pub(crate) n: usize,
    pub(crate) z: Vec<f64>,
    /// z in this precision (the input of the z layers).
    pub(crate) zt: Vec<T>,
    pub(crate) z_ready: bool,
    pub(crate) zb_l: Vec<T>,
    pub(crate) zb_v: Vec<T>,
    pub(crate) zb_lim: Vec<T>,
    pub(crate) phi: Vec<T>,
    pub(crate) dphi: Vec<T>,
    pub(crate) qp: Vec<T>,
    pub(crate) qdp: Vec<T>,
    pub(crate) qddp: Vec<T>,
    pub(crate) bufs_l: Vec<Vec<T>>,
    pub(crate) bufs_v: Vec<Vec<T>>,
    pub(crate) bufs_lim: Vec<Vec<T>>,
    pub(crate) l: Vec<T>,
    pub(crate) dl: Vec<T>,
    pub(crate) ld: Vec<T>,
    pub(crate) h: Vec<T>,
    pub(crate) c: Vec<T>,
    pub(crate) g: Vec<T>,
    pub(crate) b: Vec<T>,
    pub(crate) v: T,
    /// Order of the hidden layers' weights in the next `eval` (alternates, see there).
    pub(crate) flip: bool,
    pub(crate) t1: Vec<T>,
    pub(crate) t2: Vec<T>,
    pub(crate) rhs: Vec<T>,
    pub(crate) qdd: Vec<T>,
    pub(crate) tau_e_del: Vec<f64>,
    /// Outcome of the last batched task run in this workspace.
    pub(crate) status: Option<Error>,
    /// Scratch of a batched group led by this workspace (`lanes.rs`).
    pub(crate) lanes: LaneBufs<f64>,
}

impl Workspace {
    pub fn new(m: &Model) -> Workspace {
        Workspace::build(m, LaneBufs::new(m))
    }
}

impl<T: Real> Workspace<T> {
    /// Sized for `m` (the networks in precision T); `lanes`: the group scratch (float64 only).
    pub(crate) fn build(m: &Model, lanes: LaneBufs<f64>) -> Workspace<T> {
        let n = m.n;
        let nt = n + 1;
        let [nl, nv, nlim] = T::nets(m);
        let (nl, nv) = (nl.expect("L network"), nv.expect("V network"));
        let zero = |len: usize| vec![T::default(); len];
        let mut ws = Workspace {
            n,
            z: vec![0.0; m.dz],
            zt: zero(m.dz),
            z_ready: m.dz == 0,
            zb_l: zero(nl.layers[0].out),
            zb_v: zero(nv.layers[0].out),
            zb_lim: nlim.map(|l| zero(l.layers[0].out)).unwrap_or_default(),
            phi: zero(m.dphi),
            dphi: zero(2 * n),
            qp: zero(n),
            qdp: zero(n),
            qddp: zero(n),
            bufs_l: nl.buffers_t(nt),
            bufs_v: nv.buffers_t(nt),
            bufs_lim: nlim.map(|l| l.buffers_t(1)).unwrap_or_default(),
            l: zero(n * n),
            dl: zero(n * n * n),
            ld: zero(n * n),
            h: zero(n * n),
            c: zero(n),
            g: zero(n),
            b: zero(n),
            v: T::default(),
            flip: false,
            t1: zero(n),
            t2: zero(n),
            rhs: zero(n),
            qdd: zero(n),
            tau_e_del: vec![0.0; n],
            status: None,
            lanes,
        };
        let z = vec![0.0; m.dz];
        ws.compute_z(m, &z);
        ws.z_ready = m.dz == 0;
        ws
    }

    fn compute_z(&mut self, m: &Model, z: &[f64]) {
        self.z.copy_from_slice(z);
        for (t, x) in self.zt.iter_mut().zip(z) {
            *t = T::of(*x);
        }
        T::z_bias(m, self);
        self.z_ready = true;
    }

    /// Set the context z: the first layers' z contributions (W_z z + b) are computed here, once,
    /// and reused by every call until the next `set_z`. A z equal (bitwise) to the current one is free.
    pub fn set_z(&mut self, m: &Model, z: &[f64]) -> Result<()> {
        check_z(m, z)?;
        if self.z_ready && self.z.iter().zip(z).all(|(a, b)| a.to_bits() == b.to_bits()) {
            return Ok(());
        }
        self.compute_z(m, z);
        Ok(())
    }

    /// The current context.
    pub fn z(&self) -> &[f64] {
        &self.z
    }
    /// H (n×n, row-major) of the last `terms`/dynamics call.
    pub fn h(&self) -> &[T] {
        &self.h
    }
    /// Cholesky-like factor L (lower triangular) of H.
    pub fn l(&self) -> &[T] {
        &self.l
    }
    /// c of the last call.
    pub fn c(&self) -> &[T] {
        &self.c
    }
    /// g of the last call.
    pub fn g(&self) -> &[T] {
        &self.g
    }
    /// LIM moment arms B (τ_c = B f_v) of the last call (zeros without LIM).
    pub fn b(&self) -> &[T] {
        &self.b
    }
    /// Potential energy V of the last call.
    pub fn potential(&self) -> f64 {
        self.v.to_f64()
    }
}

/// A context z's length and finiteness.
pub(crate) fn check_z(m: &Model, z: &[f64]) -> Result<()> {
    if z.len() != m.dz {
        return Err(Error::InputShape(format!("z has {} entries, the model's z_dim is {}", z.len(), m.dz)));
    }
    if z.iter().any(|x| !x.is_finite()) {
        return Err(Error::NonFiniteInput("z".into()));
    }
    Ok(())
}

/// The first layers' z parts of `ws.zt` (`set_z`).
#[inline(always)]
fn z_bias_all<T: Real, const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<T>) {
    let [nl, nv, nlim] = T::nets(m);
    let z = &ws.zt;
    nl.unwrap().z_bias_fast::<FMA, WIDE>(z, &mut ws.zb_l);
    nv.unwrap().z_bias_fast::<FMA, WIDE>(z, &mut ws.zb_v);
    if let Some(lim) = nlim {
        lim.z_bias_fast::<FMA, WIDE>(z, &mut ws.zb_lim);
    }
}

#[inline(always)]
fn z_bias64<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<f64>) {
    z_bias_all::<f64, FMA, WIDE>(m, ws)
}
#[inline(always)]
fn z_bias32<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<f32>) {
    z_bias_all::<f32, FMA, WIDE>(m, ws)
}
simd_dispatch!(pub(crate) fn z_bias_dispatch64(m: &Model, ws: &mut Workspace<f64>) = z_bias64;);
simd_dispatch!(pub(crate) fn z_bias_dispatch32(m: &Model, ws: &mut Workspace<f32>) = z_bias32;);

#[inline(always)]
fn first_layer<T: Real, const FMA: bool>(
    l0: &Dense<T>,
    zb: &[T],
    phi: &[T],
    dphi: &[T],
    cols: &[(usize, usize)],
    nt: usize,
    a: &mut [T],
) {
    let h = l0.out;
    let (a0, tang) = a[..nt * h].split_at_mut(h);
    // 8 outputs at a time kept in registers across the φ columns (not stored per column); same sums
    let (wt, mut i0) = (&l0.wt[..phi.len() * h], 0);
    while i0 + 8 <= h {
        let mut acc: [T; 8] = zb[i0..i0 + 8].try_into().unwrap();
        for (c, &p) in phi.iter().enumerate() {
            let w = &wt[c * h + i0..c * h + i0 + 8];
            for l in 0..8 {
                acc[l] = T::madd::<FMA>(w[l], p, acc[l]);
            }
        }
        a0[i0..i0 + 8].copy_from_slice(&acc);
        i0 += 8;
    }
    for i in i0..h {
        a0[i] = phi.iter().enumerate().fold(zb[i], |s, (c, &p)| T::madd::<FMA>(wt[c * h + i], p, s));
    }
    // ∂a/∂q_k only touches the (one or two) columns of φ that depend on q_k.
    for k in 0..nt - 1 {
        let dk = &mut tang[k * h..(k + 1) * h];
        let (ca, cb) = cols[k];
        let wa = l0.col(ca);
        let va = dphi[2 * k];
        if cb == usize::MAX {
            for (di, wi) in dk.iter_mut().zip(wa) {
                *di = *wi * va;
            }
        } else {
            let vb = dphi[2 * k + 1];
            for ((di, wai), wbi) in dk.iter_mut().zip(wa).zip(l0.col(cb)) {
                *di = T::madd::<FMA>(*wbi, vb, *wai * va);
            }
        }
    }
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn run_net<T: Real, const FMA: bool, const WIDE: bool>(net: &Mlp<T>, zb: &[T], phi: &[T], dphi: &[T], cols: &[(usize, usize)], nt: usize, bufs: &mut [Vec<T>]) {
    first_layer::<T, FMA>(&net.layers[0], zb, phi, dphi, cols, nt, &mut bufs[0]);
    mlp_rest::<T, FMA, WIDE>(net, nt, bufs, false);
}

/// φ(q) and dφ/dq at `ws.qp`, layer 0 of L and V (with tangents), and the whole LIM pass (B).
#[inline(always)]
fn eval_head<T: Real, const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<T>) {
    let n = m.n;
    let nt = n + 1;
    let [nl, nv, nlim] = T::nets(m);
    for (j, &(ca, cb)) in m.phi_cols.iter().enumerate() {
        let qj = ws.qp[j];
        if cb == usize::MAX {
            ws.phi[ca] = qj;
            ws.dphi[2 * j] = T::of(1.0);
            ws.dphi[2 * j + 1] = T::default();
        } else {
            let (s, c) = qj.sin_cos();
            ws.phi[ca] = c;
            ws.phi[cb] = s;
            ws.dphi[2 * j] = -s;
            ws.dphi[2 * j + 1] = c;
        }
    }
    first_layer::<T, FMA>(&nl.unwrap().layers[0], &ws.zb_l, &ws.phi, &ws.dphi, &m.phi_cols, nt, &mut ws.bufs_l[0]);
    first_layer::<T, FMA>(&nv.unwrap().layers[0], &ws.zb_v, &ws.phi, &ws.dphi, &m.phi_cols, nt, &mut ws.bufs_v[0]);
    if let Some(lim) = nlim {
        run_net::<T, FMA, WIDE>(lim, &ws.zb_lim, &ws.phi, &ws.dphi, &m.phi_cols, 1, &mut ws.bufs_lim);
        let out = ws.bufs_lim.last().unwrap();
        for i in 0..n {
            ws.b[i] = T::of(m.meta.lim_scale) * out[i];
        }
    }
}

/// H, (c), g, B, V at the physical coordinates `ws.qp`.
#[inline(always)]
fn eval<T: Real, const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<T>, qd: &[T], want_c: bool) {
    let nt = m.n + 1;
    let [nl, nv, _] = T::nets(m);
    let (nl, nv) = (nl.unwrap(), nv.unwrap());
    eval_head::<T, FMA, WIDE>(m, ws);
    // The two hidden layers (2 x 32 KB at 64 wide) overflow L1 together: every other call walks them in
    // reverse order (the last weights used come first), so part of them is still cached. Same results.
    ws.flip = !ws.flip;
    if ws.flip {
        mlp_rest::<T, FMA, WIDE>(nl, nt, &mut ws.bufs_l, false);
        mlp_rest::<T, FMA, WIDE>(nv, nt, &mut ws.bufs_v, false);
    } else {
        mlp_rest::<T, FMA, WIDE>(nv, nt, &mut ws.bufs_v, true);
        mlp_rest::<T, FMA, WIDE>(nl, nt, &mut ws.bufs_l, true);
    }
    eval_tail(m, ws, qd, want_c);
}

/// From the networks' outputs: L, ∂L/∂q, H = LLᵀ, g, V and (want_c) c.
#[inline(always)]
pub(crate) fn eval_tail<T: Real>(m: &Model, ws: &mut Workspace<T>, qd: &[T], want_c: bool) {
    let n = m.n;
    let nn = n * n;
    // L and ∂L/∂q_k (dl[k][i][j]) from the L network's outputs: n diagonal then strictly lower.
    let mo = n * (n + 1) / 2;
    let u = ws.bufs_l.last().unwrap();
    let off = T::of(m.meta.softplus_offset);
    for i in 0..n {
        let (sp, s) = u[i].softplus_sigmoid(); // softplus' = sigmoid
        ws.l[i * n + i] = sp + off;
        for k in 0..n {
            ws.dl[k * nn + i * n + i] = s * u[(k + 1) * mo + i];
        }
    }
    let mut t = n;
    for i in 1..n {
        for j in 0..i {
            ws.l[i * n + j] = u[t];
            for k in 0..n {
                ws.dl[k * nn + i * n + j] = u[(k + 1) * mo + t];
            }
            t += 1;
        }
    }
    // H = L Lᵀ (lower-triangular sums only; the result is exactly symmetric).
    for i in 0..n {
        for j in 0..=i {
            let mut s = T::default();
            for k in 0..=j {
                s = s + ws.l[i * n + k] * ws.l[j * n + k];
            }
            ws.h[i * n + j] = s;
            ws.h[j * n + i] = s;
        }
    }
    // g = v_scale ∂V/∂q; V itself for energy.
    let vo = ws.bufs_v.last().unwrap();
    let vs = T::of(m.meta.v_scale);
    ws.v = vs * vo[0];
    for k in 0..n {
        ws.g[k] = vs * vo[k + 1];
    }
    if !want_c {
        return;
    }
    // Lᵀ q̇ → t1; L̇ → ld; L̇ᵀ q̇ → t2.
    for j in 0..n {
        let mut s = T::default();
        for i in j..n {
            s = s + ws.l[i * n + j] * qd[i];
        }
        ws.t1[j] = s;
    }
    for e in 0..nn {
        let mut s = T::default();
        for k in 0..n {
            s = s + ws.dl[k * nn + e] * qd[k];
        }
        ws.ld[e] = s;
    }
    for j in 0..n {
        let mut s = T::default();
        for i in 0..n {
            s = s + ws.ld[i * n + j] * qd[i];
        }
        ws.t2[j] = s;
    }
    for i in 0..n {
        let mut s = T::default();
        for j in 0..n {
            s = s + (ws.ld[i * n + j] * ws.t1[j] + ws.l[i * n + j] * ws.t2[j]);
        }
        // ½ ∂(q̇ᵀHq̇)/∂q_i = Σ_j (Σ_a ∂L_aj/∂q_i q̇_a) (Lᵀq̇)_j
        let mut d = T::default();
        for j in 0..n {
            let mut w = T::default();
            for a in 0..n {
                w = w + ws.dl[i * nn + a * n + j] * qd[a];
            }
            d = d + w * ws.t1[j];
        }
        ws.c[i] = s - d;
    }
}

#[inline(always)]
fn eval64<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<f64>, qd: &[f64], want_c: bool) {
    eval::<f64, FMA, WIDE>(m, ws, qd, want_c)
}
#[inline(always)]
fn eval32<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace<f32>, qd: &[f32], want_c: bool) {
    eval::<f32, FMA, WIDE>(m, ws, qd, want_c)
}
simd_dispatch!(fn eval_simd(m: &Model, ws: &mut Workspace<f64>, qd: &[f64], want_c: bool) = eval64;);
simd_dispatch!(fn eval_simd32(m: &Model, ws: &mut Workspace<f32>, qd: &[f32], want_c: bool) = eval32;);

#[inline]
pub(crate) fn eval_dispatch(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    eval_simd(m.simd, m, ws, qd, want_c)
}

/// `eval_dispatch` in float32 (`single_f32.rs`).
#[inline]
pub(crate) fn eval_dispatch32(m: &Model, ws: &mut Workspace<f32>, qd: &[f32], want_c: bool) {
    eval_simd32(m.simd, m, ws, qd, want_c)
}
