//! The public per-sample calls on a [`Model`]: terms, energy, inverse and forward dynamics (with the
//! extension terms), and the solve H⁻¹ rhs. The network pass itself is `delan.rs`.

use crate::delan::{eval_dispatch, ExoTorque, Workspace};
use crate::real::Real;
use crate::error::{Error, Result};
use crate::model::Model;

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
/// substitution with L (H = L Lᵀ is already a Cholesky factorisation). Refused beyond `T::COND_MAX`.
pub(crate) fn solve<T: Real>(n: usize, h: &[T], l: &[T], rhs: &[T], out: &mut [T]) -> Result<()> {
    let (zero, cmax) = (T::default(), T::COND_MAX);
    if n == 1 {
        let det = h[0];
        if !(det > zero) || !det.to_f64().is_finite() {
            return Err(Error::IllConditioned { det: det.to_f64(), cond: f64::INFINITY });
        }
        out[0] = rhs[0] / det;
        return Ok(());
    }
    if n == 2 {
        let (a, b, d) = (h[0], h[1], h[3]);
        let det = a * d - b * b;
        let half_tr = T::of(0.5) * (a + d);
        let disc = (T::of(0.25) * (a - d) * (a - d) + b * b).sqrt();
        let lmax = half_tr + disc;
        let lmin = det / lmax; // product of eigenvalues = det (no cancellation)
        let cond = (lmax / lmin).to_f64();
        if !(det > zero) || !(lmin > zero) || !(cond <= cmax) || !det.to_f64().is_finite() {
            return Err(Error::IllConditioned { det: det.to_f64(), cond: if cond.is_finite() && cond > 0.0 { cond } else { f64::INFINITY } });
        }
        let inv = T::of(1.0) / det;
        out[0] = (d * rhs[0] - b * rhs[1]) * inv;
        out[1] = (a * rhs[1] - b * rhs[0]) * inv;
        return Ok(());
    }
    let (mut dmin, mut dmax, mut det) = (T::of(f64::INFINITY), zero, T::of(1.0));
    for i in 0..n {
        let d = l[i * n + i];
        dmin = dmin.min(d);
        dmax = dmax.max(d);
        det = det * (d * d);
    }
    // (max L_ii / min L_ii)² is a lower bound of cond(H).
    let cond = ((dmax / dmin) * (dmax / dmin)).to_f64();
    if !(dmin > zero) || !(cond <= cmax) || !det.to_f64().is_finite() {
        return Err(Error::IllConditioned { det: det.to_f64(), cond });
    }
    for i in 0..n {
        let mut s = rhs[i];
        for k in 0..i {
            s = s - l[i * n + k] * out[k];
        }
        out[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = out[i];
        for k in i + 1..n {
            s = s - l[k * n + i] * out[k];
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
        eval_dispatch(self, ws, qd, true);
        self.forward_after_eval(ws, qd, tau, f_v, tau_e, qdd)
    }

    /// Forward dynamics once `ws` holds the pass at (q, q̇) (`eval`).
    #[inline]
    pub(crate) fn forward_after_eval(
        &self,
        ws: &mut Workspace,
        qd: &[f64],
        tau: &[f64],
        f_v: f64,
        tau_e: Option<ExoTorque>,
        qdd: &mut [f64],
    ) -> Result<()> {
        let n = self.n;
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
