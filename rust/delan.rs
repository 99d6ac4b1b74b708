//! The Lagrangian dynamics (DESIGN.md section 2) with hand-derived forward-mode derivatives.
//!
//! One pass per sample: φ(q) and dφ/dq, the L and V networks with their q-tangents, then
//!   H = L Lᵀ,  c = Ḣ q̇ − ½ ∂(q̇ᵀ H q̇)/∂q,  g = v_scale ∂V/∂q,  B = lim_scale · lim([φ; z]).
//! With L̇ = Σ_k ∂L/∂q_k q̇_k:  Ḣ q̇ = L̇ (Lᵀ q̇) + L (L̇ᵀ q̇)  and  ½ ∂(q̇ᵀ H q̇)/∂q_k = (∂L/∂q_k ᵀ q̇)·(Lᵀ q̇).
//!
//! Everything a call needs lives in a preallocated [`Workspace`]; no call allocates. The public calls
//! (inverse/forward dynamics, terms, energy) and the solve: `dynamics.rs`.

use crate::error::{Error, Result};
use crate::math::{madd, softplus};
use crate::lanes::LaneBufs;
use crate::mlp::{mlp_rest, Dense, Mlp};
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

/// Scratch memory for one thread of evaluation, sized at creation from the model.
#[derive(Debug, Clone)]
pub struct Workspace {
    pub(crate) n: usize,
    pub(crate) z: Vec<f64>,
    pub(crate) z_ready: bool,
    pub(crate) zb_l: Vec<f64>,
    pub(crate) zb_v: Vec<f64>,
    pub(crate) zb_lim: Vec<f64>,
    pub(crate) phi: Vec<f64>,
    pub(crate) dphi: Vec<f64>,
    pub(crate) qp: Vec<f64>,
    pub(crate) qdp: Vec<f64>,
    pub(crate) qddp: Vec<f64>,
    pub(crate) bufs_l: Vec<Vec<f64>>,
    pub(crate) bufs_v: Vec<Vec<f64>>,
    pub(crate) bufs_lim: Vec<Vec<f64>>,
    pub(crate) l: Vec<f64>,
    pub(crate) dl: Vec<f64>,
    pub(crate) ld: Vec<f64>,
    pub(crate) h: Vec<f64>,
    pub(crate) c: Vec<f64>,
    pub(crate) g: Vec<f64>,
    pub(crate) b: Vec<f64>,
    pub(crate) v: f64,
    /// Order of the hidden layers' weights in the next `eval` (alternates, see there).
    pub(crate) flip: bool,
    pub(crate) t1: Vec<f64>,
    pub(crate) t2: Vec<f64>,
    pub(crate) rhs: Vec<f64>,
    pub(crate) qdd: Vec<f64>,
    pub(crate) tau_e_del: Vec<f64>,
    /// Outcome of the last batched task run in this workspace.
    pub(crate) status: Option<Error>,
    /// Scratch of a batched group led by this workspace (`lanes.rs`).
    pub(crate) lanes: LaneBufs<f64>,
}

impl Workspace {
    pub fn new(m: &Model) -> Workspace {
        let n = m.n;
        let nt = n + 1;
        let mut ws = Workspace {
            n,
            z: vec![0.0; m.dz],
            z_ready: m.dz == 0,
            zb_l: vec![0.0; m.net_l.layers[0].out],
            zb_v: vec![0.0; m.net_v.layers[0].out],
            zb_lim: m.net_lim.as_ref().map(|l| vec![0.0; l.layers[0].out]).unwrap_or_default(),
            phi: vec![0.0; m.dphi],
            dphi: vec![0.0; 2 * n],
            qp: vec![0.0; n],
            qdp: vec![0.0; n],
            qddp: vec![0.0; n],
            bufs_l: m.net_l.buffers(nt),
            bufs_v: m.net_v.buffers(nt),
            bufs_lim: m.net_lim.as_ref().map(|l| l.buffers(1)).unwrap_or_default(),
            l: vec![0.0; n * n],
            dl: vec![0.0; n * n * n],
            ld: vec![0.0; n * n],
            h: vec![0.0; n * n],
            c: vec![0.0; n],
            g: vec![0.0; n],
            b: vec![0.0; n],
            v: 0.0,
            flip: false,
            t1: vec![0.0; n],
            t2: vec![0.0; n],
            rhs: vec![0.0; n],
            qdd: vec![0.0; n],
            tau_e_del: vec![0.0; n],
            status: None,
            lanes: LaneBufs::new(m),
        };
        let z = vec![0.0; m.dz];
        ws.compute_z(m, &z);
        ws.z_ready = m.dz == 0;
        ws
    }

    fn compute_z(&mut self, m: &Model, z: &[f64]) {
        self.z.copy_from_slice(z);
        z_bias_dispatch(m.simd, m, self, z);
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
    pub fn h(&self) -> &[f64] {
        &self.h
    }
    /// Cholesky-like factor L (lower triangular) of H.
    pub fn l(&self) -> &[f64] {
        &self.l
    }
    /// c of the last call.
    pub fn c(&self) -> &[f64] {
        &self.c
    }
    /// g of the last call.
    pub fn g(&self) -> &[f64] {
        &self.g
    }
    /// LIM moment arms B (τ_c = B f_v) of the last call (zeros without LIM).
    pub fn b(&self) -> &[f64] {
        &self.b
    }
    /// Potential energy V of the last call.
    pub fn potential(&self) -> f64 {
        self.v
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

#[inline(always)]
fn z_bias_all<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace, z: &[f64]) {
    m.net_l.z_bias_fast::<FMA, WIDE>(z, &mut ws.zb_l);
    m.net_v.z_bias_fast::<FMA, WIDE>(z, &mut ws.zb_v);
    if let Some(lim) = &m.net_lim {
        lim.z_bias_fast::<FMA, WIDE>(z, &mut ws.zb_lim);
    }
}

simd_dispatch!(fn z_bias_dispatch(m: &Model, ws: &mut Workspace, z: &[f64]) = z_bias_all;);

#[inline(always)]
fn first_layer<const FMA: bool>(
    l0: &Dense,
    zb: &[f64],
    phi: &[f64],
    dphi: &[f64],
    cols: &[(usize, usize)],
    nt: usize,
    a: &mut [f64],
) {
    let h = l0.out;
    let (a0, tang) = a[..nt * h].split_at_mut(h);
    // 8 outputs at a time kept in registers across the φ columns (not stored per column); same sums
    let (wt, mut i0) = (&l0.wt[..phi.len() * h], 0);
    while i0 + 8 <= h {
        let mut acc: [f64; 8] = zb[i0..i0 + 8].try_into().unwrap();
        for (c, &p) in phi.iter().enumerate() {
            let w = &wt[c * h + i0..c * h + i0 + 8];
            for l in 0..8 {
                acc[l] = madd::<FMA>(w[l], p, acc[l]);
            }
        }
        a0[i0..i0 + 8].copy_from_slice(&acc);
        i0 += 8;
    }
    for i in i0..h {
        a0[i] = phi.iter().enumerate().fold(zb[i], |s, (c, &p)| madd::<FMA>(wt[c * h + i], p, s));
    }
    // ∂a/∂q_k only touches the (one or two) columns of φ that depend on q_k.
    for k in 0..nt - 1 {
        let dk = &mut tang[k * h..(k + 1) * h];
        let (ca, cb) = cols[k];
        let wa = l0.col(ca);
        let va = dphi[2 * k];
        if cb == usize::MAX {
            for (di, wi) in dk.iter_mut().zip(wa) {
                *di = wi * va;
            }
        } else {
            let vb = dphi[2 * k + 1];
            for ((di, wai), wbi) in dk.iter_mut().zip(wa).zip(l0.col(cb)) {
                *di = madd::<FMA>(*wbi, vb, wai * va);
            }
        }
    }
}

#[inline(always)]
fn run_net<const FMA: bool, const WIDE: bool>(net: &Mlp, zb: &[f64], phi: &[f64], dphi: &[f64], cols: &[(usize, usize)], nt: usize, bufs: &mut [Vec<f64>]) {
    first_layer::<FMA>(&net.layers[0], zb, phi, dphi, cols, nt, &mut bufs[0]);
    mlp_rest::<FMA, WIDE>(net, nt, bufs, false);
}

/// φ(q) and dφ/dq at `ws.qp`, layer 0 of L and V (with tangents), and the whole LIM pass (B).
#[inline(always)]
fn eval_head<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace) {
    let n = m.n;
    let nt = n + 1;
    for (j, &(ca, cb)) in m.phi_cols.iter().enumerate() {
        let qj = ws.qp[j];
        if cb == usize::MAX {
            ws.phi[ca] = qj;
            ws.dphi[2 * j] = 1.0;
            ws.dphi[2 * j + 1] = 0.0;
        } else {
            let (s, c) = qj.sin_cos();
            ws.phi[ca] = c;
            ws.phi[cb] = s;
            ws.dphi[2 * j] = -s;
            ws.dphi[2 * j + 1] = c;
        }
    }
    first_layer::<FMA>(&m.net_l.layers[0], &ws.zb_l, &ws.phi, &ws.dphi, &m.phi_cols, nt, &mut ws.bufs_l[0]);
    first_layer::<FMA>(&m.net_v.layers[0], &ws.zb_v, &ws.phi, &ws.dphi, &m.phi_cols, nt, &mut ws.bufs_v[0]);
    if let Some(lim) = &m.net_lim {
        run_net::<FMA, WIDE>(lim, &ws.zb_lim, &ws.phi, &ws.dphi, &m.phi_cols, 1, &mut ws.bufs_lim);
        let out = ws.bufs_lim.last().unwrap();
        for i in 0..n {
            ws.b[i] = m.meta.lim_scale * out[i];
        }
    }
}

/// H, (c), g, B, V at the physical coordinates `ws.qp`.
#[inline(always)]
fn eval<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    let nt = m.n + 1;
    eval_head::<FMA, WIDE>(m, ws);
    // The two hidden layers (2 x 32 KB at 64 wide) overflow L1 together: every other call walks them in
    // reverse order (the last weights used come first), so part of them is still cached. Same results.
    ws.flip = !ws.flip;
    if ws.flip {
        mlp_rest::<FMA, WIDE>(&m.net_l, nt, &mut ws.bufs_l, false);
        mlp_rest::<FMA, WIDE>(&m.net_v, nt, &mut ws.bufs_v, false);
    } else {
        mlp_rest::<FMA, WIDE>(&m.net_v, nt, &mut ws.bufs_v, true);
        mlp_rest::<FMA, WIDE>(&m.net_l, nt, &mut ws.bufs_l, true);
    }
    eval_tail(m, ws, qd, want_c);
}

/// From the networks' outputs: L, ∂L/∂q, H = LLᵀ, g, V and (want_c) c.
#[inline(always)]
pub(crate) fn eval_tail(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    let n = m.n;
    let nn = n * n;
    // L and ∂L/∂q_k (dl[k][i][j]) from the L network's outputs: n diagonal then strictly lower.
    let mo = n * (n + 1) / 2;
    let u = ws.bufs_l.last().unwrap();
    let off = m.meta.softplus_offset;
    for i in 0..n {
        ws.l[i * n + i] = softplus(u[i]) + off;
        let s = 1.0 / (1.0 + (-u[i]).exp()); // softplus' = sigmoid
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
            let mut s = 0.0;
            for k in 0..=j {
                s += ws.l[i * n + k] * ws.l[j * n + k];
            }
            ws.h[i * n + j] = s;
            ws.h[j * n + i] = s;
        }
    }
    // g = v_scale ∂V/∂q; V itself for energy.
    let vo = ws.bufs_v.last().unwrap();
    ws.v = m.meta.v_scale * vo[0];
    for k in 0..n {
        ws.g[k] = m.meta.v_scale * vo[k + 1];
    }
    if !want_c {
        return;
    }
    // Lᵀ q̇ → t1; L̇ → ld; L̇ᵀ q̇ → t2.
    for j in 0..n {
        let mut s = 0.0;
        for i in j..n {
            s += ws.l[i * n + j] * qd[i];
        }
        ws.t1[j] = s;
    }
    for e in 0..nn {
        let mut s = 0.0;
        for k in 0..n {
            s += ws.dl[k * nn + e] * qd[k];
        }
        ws.ld[e] = s;
    }
    for j in 0..n {
        let mut s = 0.0;
        for i in 0..n {
            s += ws.ld[i * n + j] * qd[i];
        }
        ws.t2[j] = s;
    }
    for i in 0..n {
        let mut s = 0.0;
        for j in 0..n {
            s += ws.ld[i * n + j] * ws.t1[j] + ws.l[i * n + j] * ws.t2[j];
        }
        // ½ ∂(q̇ᵀHq̇)/∂q_i = Σ_j (Σ_a ∂L_aj/∂q_i q̇_a) (Lᵀq̇)_j
        let mut d = 0.0;
        for j in 0..n {
            let mut w = 0.0;
            for a in 0..n {
                w += ws.dl[i * nn + a * n + j] * qd[a];
            }
            d += w * ws.t1[j];
        }
        ws.c[i] = s - d;
    }
}

simd_dispatch!(fn eval_simd(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) = eval;);

#[inline]
pub(crate) fn eval_dispatch(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    eval_simd(m.simd, m, ws, qd, want_c)
}
