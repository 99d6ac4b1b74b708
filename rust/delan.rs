//! The Lagrangian dynamics (DESIGN.md section 2) with hand-derived forward-mode derivatives.
//!
//! One pass per sample: φ(q) and dφ/dq, the L and V networks with their q-tangents, then
//!   H = L Lᵀ,  c = Ḣ q̇ − ½ ∂(q̇ᵀ H q̇)/∂q,  g = v_scale ∂V/∂q,  B = lim_scale · lim([φ; z]).
//! With L̇ = Σ_k ∂L/∂q_k q̇_k:  Ḣ q̇ = L̇ (Lᵀ q̇) + L (L̇ᵀ q̇)  and  ½ ∂(q̇ᵀ H q̇)/∂q_k = (∂L/∂q_k ᵀ q̇)·(Lᵀ q̇).
//!
//! Everything a call needs lives in a preallocated [`Workspace`]; no call allocates.

use crate::error::{Error, Result};
use crate::math::{madd, softplus};
use crate::mlp::{mlp_rest, Dense, Mlp};
use crate::model::Model;

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
    fn app(&self) -> &'a [f64] {
        self.applied.unwrap_or(self.now)
    }
}

/// Scratch memory for one thread of evaluation, sized at creation from the model.
#[derive(Debug, Clone)]
pub struct Workspace {
    pub(crate) n: usize,
    pub(crate) z: Vec<f64>,
    pub(crate) z_ready: bool,
    zb_l: Vec<f64>,
    zb_v: Vec<f64>,
    zb_lim: Vec<f64>,
    phi: Vec<f64>,
    dphi: Vec<f64>,
    pub(crate) qp: Vec<f64>,
    qdp: Vec<f64>,
    qddp: Vec<f64>,
    bufs_l: Vec<Vec<f64>>,
    bufs_v: Vec<Vec<f64>>,
    bufs_lim: Vec<Vec<f64>>,
    l: Vec<f64>,
    dl: Vec<f64>,
    ld: Vec<f64>,
    h: Vec<f64>,
    c: Vec<f64>,
    g: Vec<f64>,
    b: Vec<f64>,
    v: f64,
    t1: Vec<f64>,
    t2: Vec<f64>,
    pub(crate) rhs: Vec<f64>,
    pub(crate) qdd: Vec<f64>,
    pub(crate) tau_e_del: Vec<f64>,
    /// Outcome of the last batched task run in this workspace.
    pub(crate) status: Option<Error>,
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
            t1: vec![0.0; n],
            t2: vec![0.0; n],
            rhs: vec![0.0; n],
            qdd: vec![0.0; n],
            tau_e_del: vec![0.0; n],
            status: None,
        };
        let z = vec![0.0; m.dz];
        ws.compute_z(m, &z);
        ws.z_ready = m.dz == 0;
        ws
    }

    fn compute_z(&mut self, m: &Model, z: &[f64]) {
        self.z.copy_from_slice(z);
        #[cfg(target_arch = "x86_64")]
        if m.simd == crate::model::Simd::Avx2Fma {
            // SAFETY: the level is only set when the CPU reports AVX2 and FMA (checked at load).
            unsafe { z_bias_fma(m, self, z) };
            self.z_ready = true;
            return;
        }
        z_bias_all::<false>(m, self, z);
        self.z_ready = true;
    }

    /// Set the context z: the first layers' z contributions (W_z z + b) are computed here, once,
    /// and reused by every call until the next `set_z`. A z equal (bitwise) to the current one is free.
    pub fn set_z(&mut self, m: &Model, z: &[f64]) -> Result<()> {
        if z.len() != m.dz {
            return Err(Error::InputShape(format!("z has {} entries, the model's z_dim is {}", z.len(), m.dz)));
        }
        if z.iter().any(|x| !x.is_finite()) {
            return Err(Error::NonFiniteInput("z".into()));
        }
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

#[inline(always)]
fn z_bias_all<const FMA: bool>(m: &Model, ws: &mut Workspace, z: &[f64]) {
    m.net_l.z_bias_fast::<FMA>(z, &mut ws.zb_l);
    m.net_v.z_bias_fast::<FMA>(z, &mut ws.zb_v);
    if let Some(lim) = &m.net_lim {
        lim.z_bias_fast::<FMA>(z, &mut ws.zb_lim);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn z_bias_fma(m: &Model, ws: &mut Workspace, z: &[f64]) {
    z_bias_all::<true>(m, ws, z)
}

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
    a0.copy_from_slice(&zb[..h]);
    for (c, &p) in phi.iter().enumerate() {
        for (ai, wi) in a0.iter_mut().zip(l0.col(c)) {
            *ai = madd::<FMA>(*wi, p, *ai);
        }
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
    mlp_rest::<FMA, WIDE>(net, nt, bufs);
}

/// H, (c), g, B, V at the physical coordinates `ws.qp`.
#[inline(always)]
fn eval<const FMA: bool, const WIDE: bool>(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    let n = m.n;
    let nt = n + 1;
    let nn = n * n;
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
    run_net::<FMA, WIDE>(&m.net_l, &ws.zb_l, &ws.phi, &ws.dphi, &m.phi_cols, nt, &mut ws.bufs_l);
    run_net::<FMA, WIDE>(&m.net_v, &ws.zb_v, &ws.phi, &ws.dphi, &m.phi_cols, nt, &mut ws.bufs_v);
    if let Some(lim) = &m.net_lim {
        run_net::<FMA, WIDE>(lim, &ws.zb_lim, &ws.phi, &ws.dphi, &m.phi_cols, 1, &mut ws.bufs_lim);
        let out = ws.bufs_lim.last().unwrap();
        for i in 0..n {
            ws.b[i] = m.meta.lim_scale * out[i];
        }
    }

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

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn eval_fma(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    eval::<true, false>(m, ws, qd, want_c)
}

#[inline]
pub(crate) fn eval_dispatch(m: &Model, ws: &mut Workspace, qd: &[f64], want_c: bool) {
    #[cfg(target_arch = "x86_64")]
    match m.simd {
        // SAFETY: the level is only set when the CPU reports these features (checked at load).
        crate::model::Simd::Avx2Fma => return unsafe { eval_fma(m, ws, qd, want_c) },
        crate::model::Simd::Portable => {}
    }
    eval::<false, false>(m, ws, qd, want_c)
}

pub(crate) fn check(name: &str, x: &[f64], n: usize) -> Result<()> {
    if x.len() != n {
        return Err(Error::InputShape(format!("{name} has {} entries, expected {n}", x.len())));
    }
    if x.iter().any(|v| !v.is_finite()) {
        return Err(Error::NonFiniteInput(name.to_string()));
    }
    Ok(())
}

/// H⁻¹ rhs. n = 2: the analytic inverse of the 2×2 matrix; general n: forward and back
/// substitution with L (H = L Lᵀ is already a Cholesky factorisation).
pub(crate) fn solve(n: usize, h: &[f64], l: &[f64], rhs: &[f64], out: &mut [f64]) -> Result<()> {
    if n == 1 {
        let det = h[0];
        if !(det > 0.0) || !det.is_finite() {
            return Err(Error::IllConditioned { det, cond: f64::INFINITY });
        }
        out[0] = rhs[0] / det;
        return Ok(());
    }
    if n == 2 {
        let (a, b, d) = (h[0], h[1], h[3]);
        let det = a * d - b * b;
        let half_tr = 0.5 * (a + d);
        let disc = (0.25 * (a - d) * (a - d) + b * b).sqrt();
        let lmax = half_tr + disc;
        let lmin = det / lmax; // product of eigenvalues = det (no cancellation)
        let cond = lmax / lmin;
        if !(det > 0.0) || !(lmin > 0.0) || !(cond <= COND_MAX) || !det.is_finite() {
            return Err(Error::IllConditioned { det, cond: if cond.is_finite() && cond > 0.0 { cond } else { f64::INFINITY } });
        }
        let inv = 1.0 / det;
        out[0] = (d * rhs[0] - b * rhs[1]) * inv;
        out[1] = (a * rhs[1] - b * rhs[0]) * inv;
        return Ok(());
    }
    let (mut dmin, mut dmax, mut det) = (f64::INFINITY, 0.0f64, 1.0);
    for i in 0..n {
        let d = l[i * n + i];
        dmin = dmin.min(d);
        dmax = dmax.max(d);
        det *= d * d;
    }
    // (max L_ii / min L_ii)² is a lower bound of cond(H).
    let cond = (dmax / dmin) * (dmax / dmin);
    if !(dmin > 0.0) || !(cond <= COND_MAX) || !det.is_finite() {
        return Err(Error::IllConditioned { det, cond });
    }
    for i in 0..n {
        let mut s = rhs[i];
        for k in 0..i {
            s -= l[i * n + k] * out[k];
        }
        out[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = out[i];
        for k in i + 1..n {
            s -= l[k * n + i] * out[k];
        }
        out[i] = s / l[i * n + i];
    }
    Ok(())
}

impl Model {
    /// A workspace for this model (allocates; do it once per thread, outside the hot loop).
    pub fn workspace(&self) -> Workspace {
        Workspace::new(self)
    }

    fn prepare(&self, ws: &mut Workspace, q: &[f64], tau_e: Option<ExoTorque>) -> Result<()> {
        let n = self.n;
        if ws.n != n || ws.z.len() != self.dz {
            return Err(Error::InputShape("workspace was made for a different model".into()));
        }
        if !ws.z_ready {
            return Err(Error::InputShape(format!("context z (dimension {}) not set: call set_z first", self.dz)));
        }
        check("q", q, n)?;
        if let Some(te) = tau_e {
            check("tau_e", te.now, n)?;
            for (name, x) in [("tau_e applied", te.applied), ("tau_e applied_d", te.applied_d), ("tau_e applied_dd", te.applied_dd)] {
                if let Some(x) = x {
                    check(name, x, n)?;
                }
            }
        }
        Ok(())
    }

    /// H, c, g (and B, V) at (q, q̇) for the workspace's z; read them with `ws.h()`, `ws.c()`, ...
    /// (The base model's terms at the given coordinates: no extension shifts.)
    pub fn terms(&self, ws: &mut Workspace, q: &[f64], qd: &[f64]) -> Result<()> {
        self.prepare(ws, q, None)?;
        ws.qp.copy_from_slice(q);
        check("qd", qd, self.n)?;
        eval_dispatch(self, ws, qd, true);
        Ok(())
    }

    /// Kinetic and potential energy (T, V) at (q, q̇).
    pub fn energy(&self, ws: &mut Workspace, q: &[f64], qd: &[f64]) -> Result<(f64, f64)> {
        self.prepare(ws, q, None)?;
        ws.qp.copy_from_slice(q);
        check("qd", qd, self.n)?;
        eval_dispatch(self, ws, qd, false);
        let n = self.n;
        let mut t = 0.0;
        for i in 0..n {
            for j in 0..n {
                t += qd[i] * ws.h[i * n + j] * qd[j];
            }
        }
        Ok((0.5 * t, ws.v))
    }

    /// τ = H q̈ + c + g − B f_v (+ extension terms): the predicted recorded total torque.
    #[allow(clippy::too_many_arguments)]
    pub fn inverse_dynamics(
        &self,
        ws: &mut Workspace,
        q: &[f64],
        qd: &[f64],
        qdd: &[f64],
        f_v: f64,
        tau_e: Option<ExoTorque>,
        tau: &mut [f64],
    ) -> Result<()> {
        let n = self.n;
        self.prepare(ws, q, tau_e)?;
        check("qd", qd, n)?;
        check("qdd", qdd, n)?;
        if !f_v.is_finite() {
            return Err(Error::NonFiniteInput("f_v".into()));
        }
        if tau.len() != n {
            return Err(Error::InputShape(format!("tau output has {} entries, expected {n}", tau.len())));
        }
        // measured → physical coordinates (encoder offset, strap deflection)
        let app = tau_e.map(|t| t.app());
        let mut qdp = std::mem::take(&mut ws.qdp);
        let mut qddp = std::mem::take(&mut ws.qddp);
        {
            let ext = &self.ext;
            ext.physical(q, true, app, &mut ws.qp);
            ext.physical(qd, false, tau_e.and_then(|t| t.applied_d), &mut qdp);
            ext.physical(qdd, false, tau_e.and_then(|t| t.applied_dd), &mut qddp);
        }
        eval_dispatch(self, ws, &qdp, true);
        for i in 0..n {
            let mut s = 0.0;
            for j in 0..n {
                s += ws.h[i * n + j] * qddp[j];
            }
            tau[i] = s + ws.c[i] + ws.g[i] - ws.b[i] * f_v;
        }
        self.ext.add_dissipation(&qdp, self.meta.coulomb_eps, tau);
        self.ext.add_recording(tau_e.map(|t| t.now), app, tau);
        ws.qdp = qdp;
        ws.qddp = qddp;
        Ok(())
    }

    /// q̈ = H⁻¹ (τ + B f_v − c − g − extension terms), where τ is the recorded total torque and
    /// (q, q̇) are physical coordinates (with extensions: offset and strap deflection removed).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_dynamics(
        &self,
        ws: &mut Workspace,
        q: &[f64],
        qd: &[f64],
        tau: &[f64],
        f_v: f64,
        tau_e: Option<ExoTorque>,
        qdd: &mut [f64],
    ) -> Result<()> {
        let n = self.n;
        self.prepare(ws, q, tau_e)?;
        check("qd", qd, n)?;
        check("tau", tau, n)?;
        if !f_v.is_finite() {
            return Err(Error::NonFiniteInput("f_v".into()));
        }
        if qdd.len() != n {
            return Err(Error::InputShape(format!("qdd output has {} entries, expected {n}", qdd.len())));
        }
        ws.qp.copy_from_slice(q);
        self.forward_unchecked(ws, qd, tau, f_v, tau_e, qdd)
    }

    /// Forward dynamics at `ws.qp` (inputs already checked).
    #[inline]
    pub(crate) fn forward_unchecked(
        &self,
        ws: &mut Workspace,
        qd: &[f64],
        tau: &[f64],
        f_v: f64,
        tau_e: Option<ExoTorque>,
        qdd: &mut [f64],
    ) -> Result<()> {
        let n = self.n;
        eval_dispatch(self, ws, qd, true);
        // Everything but H q̈ on the torque side: c + g − B f_v + extensions; rhs = τ − that.
        for i in 0..n {
            ws.t1[i] = ws.c[i] + ws.g[i] - ws.b[i] * f_v;
        }
        if self.ext.any() {
            let (t1, ext) = (&mut ws.t1, &self.ext);
            ext.add_dissipation(qd, self.meta.coulomb_eps, t1);
            ext.add_recording(tau_e.map(|t| t.now), tau_e.map(|t| t.app()), t1);
        }
        for i in 0..n {
            ws.rhs[i] = tau[i] - ws.t1[i];
        }
        solve(n, &ws.h, &ws.l, &ws.rhs, qdd)
    }
}
