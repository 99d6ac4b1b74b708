//! Semi-implicit Euler rollouts (DESIGN.md section 5), single and batched.
//!
//!   q̈_k = forward_dynamics(q_k, q̇_k, τ_k, z_k, f_v,k),  q̇_{k+1} = q̇_k + dt q̈_k,  q_{k+1} = q_k + dt q̇_{k+1}
//!
//! Outputs hold T+1 states, index 0 being the initial one. Batches of rollouts: `batch.rs`.

use crate::delan::{ExoTorque, Workspace};
use crate::delan::eval_dispatch;
use crate::dynamics::check;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::real::Real;

/// The context over a rollout.
#[derive(Debug, Clone, Copy)]
pub enum ZSeq<'a> {
    /// No context (models without encoder), or keep whatever `set_z` last set.
    Keep,
    /// One z for the whole horizon (dz values; batched: B·dz).
    Const(&'a [f64]),
    /// z_k per step (T·dz; batched: B·T·dz).
    PerStep(&'a [f64]),
}

/// The recorded inputs of a rollout over T steps (batched: each array stacked over the batch).
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    /// τ_k, T·n.
    pub tau: &'a [f64],
    pub z: ZSeq<'a>,
    /// f_v,k, T (None: zeros).
    pub f_v: Option<&'a [f64]>,
    /// Recorded exoskeleton torque τ_e,k, T·n (None: the terms that need it are off).
    pub tau_e: Option<&'a [f64]>,
}

/// τ_e(t − d) by linear interpolation in the recorded sequence, clamped at its first sample
/// (as `ExtendedModel._shift` over a history clamped at the trial start).
pub fn delayed_into(tau_e: &[f64], n: usize, k: usize, dt: f64, delay: &[f64], out: &mut [f64]) {
    for i in 0..n {
        // the same arithmetic as torch: s = d/dt samples, x0 = k0 back, x1 = k0+1 back
        let s = delay[i] / dt;
        let k0f = s.floor();
        let frac = s - k0f;
        let k0 = k0f as usize;
        let i0 = k.saturating_sub(k0);
        let i1 = k.saturating_sub(k0 + 1);
        out[i] = (1.0 - frac) * tau_e[i0 * n + i] + frac * tau_e[i1 * n + i];
    }
}

impl Model {
    /// Roll out T = `tau.len()/n` steps from (q0, q̇0). Writes (T+1)·n values to `q_out` and `qd_out`.
    #[allow(clippy::too_many_arguments)]
    pub fn rollout(
        &self,
        ws: &mut Workspace,
        q0: &[f64],
        qd0: &[f64],
        inp: Inputs,
        dt: f64,
        q_out: &mut [f64],
        qd_out: &mut [f64],
    ) -> Result<()> {
        let t_len = self.rollout_begin(ws, q0, qd0, &inp, dt, q_out, qd_out)?;
        for k in 0..t_len {
            self.step_begin(ws, &inp, k, dt, q_out, qd_out, false)?;
            let qd = std::mem::take(&mut ws.qdp);
            eval_dispatch(self, ws, &qd, true);
            ws.qdp = qd;
            self.step_end(ws, &inp, k, dt, q_out, qd_out)?;
        }
        Ok(())
    }

    /// Check a rollout's inputs, set a constant z, write the initial state; returns T.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn rollout_begin<T: Real>(
        &self,
        ws: &mut Workspace<T>,
        q0: &[f64],
        qd0: &[f64],
        inp: &Inputs,
        dt: f64,
        q_out: &mut [f64],
        qd_out: &mut [f64],
    ) -> Result<usize> {
        let n = self.n;
        let t_len = self.check_rollout(q0, qd0, inp, dt, [q_out.len(), qd_out.len()])?;
        if let ZSeq::Const(z) = inp.z {
            ws.set_z(self, z)?;
        }
        if !ws.z_ready && !matches!(inp.z, ZSeq::PerStep(_)) {
            return Err(Error::InputShape(format!("context z (dimension {}) not set", self.dz)));
        }
        if ws.n != n {
            return Err(Error::InputShape("workspace was made for a different model".into()));
        }
        q_out[..n].copy_from_slice(q0);
        qd_out[..n].copy_from_slice(qd0);
        Ok(t_len)
    }

    /// The checks of one rollout's inputs (a constant z is checked where it is set) and its outputs'
    /// lengths; returns T.
    pub(crate) fn check_rollout(&self, q0: &[f64], qd0: &[f64], inp: &Inputs, dt: f64, out_lens: [usize; 2]) -> Result<usize> {
        let n = self.n;
        check("q0", q0, n)?;
        check("qd0", qd0, n)?;
        if !(dt.is_finite() && dt > 0.0) {
            return Err(Error::NonFiniteInput(format!("dt must be finite and > 0, got {dt}")));
        }
        if !inp.tau.len().is_multiple_of(n) {
            return Err(Error::InputShape(format!("tau has {} values, not a multiple of n = {n}", inp.tau.len())));
        }
        let t_len = inp.tau.len() / n;
        if out_lens != [(t_len + 1) * n; 2] {
            return Err(Error::InputShape(format!("outputs must hold (T+1)·n = {} values", (t_len + 1) * n)));
        }
        if inp.tau.iter().any(|v| !v.is_finite()) {
            return Err(Error::NonFiniteInput("tau".into()));
        }
        if let Some(f) = inp.f_v {
            if f.len() != t_len {
                return Err(Error::InputShape(format!("f_v has {} values, expected T = {t_len}", f.len())));
            }
            if f.iter().any(|v| !v.is_finite()) {
                return Err(Error::NonFiniteInput("f_v".into()));
            }
        }
        if let Some(te) = inp.tau_e {
            if te.len() != t_len * n {
                return Err(Error::InputShape(format!("tau_e has {} values, expected T·n = {}", te.len(), t_len * n)));
            }
            if te.iter().any(|v| !v.is_finite()) {
                return Err(Error::NonFiniteInput("tau_e".into()));
            }
        }
        if let ZSeq::PerStep(z) = inp.z {
            if z.len() != t_len * self.dz {
                return Err(Error::InputShape(format!("z has {} values, expected T·dz = {}", z.len(), t_len * self.dz)));
            }
            if z.iter().any(|v| !v.is_finite()) {
                return Err(Error::NonFiniteInput("z".into()));
            }
        }
        Ok(t_len)
    }

    /// Step k before the network pass: z_k (unless `z_set`: a group set it), the delayed exo torque,
    /// the state into `ws.qp`/`ws.qdp`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn step_begin(&self, ws: &mut Workspace, inp: &Inputs, k: usize, dt: f64, q_out: &[f64], qd_out: &[f64], z_set: bool) -> Result<()> {
        let n = self.n;
        if let (ZSeq::PerStep(z), false) = (inp.z, z_set) {
            ws.set_z(self, &z[k * self.dz..(k + 1) * self.dz])?;
        }
        if let (Some(te), Some(d)) = (inp.tau_e, self.ext.delay.as_deref()) {
            delayed_into(te, n, k, dt, d, &mut ws.tau_e_del);
        }
        // the state is in physical coordinates (as torch's ExtendedModel.forward_dynamics)
        ws.qp.copy_from_slice(&q_out[k * n..(k + 1) * n]);
        ws.qdp.copy_from_slice(&qd_out[k * n..(k + 1) * n]);
        Ok(())
    }

    /// Step k after the network pass: q̈ from H, c, g, B and the extensions, then semi-implicit Euler.
    pub(crate) fn step_end(&self, ws: &mut Workspace, inp: &Inputs, k: usize, dt: f64, q_out: &mut [f64], qd_out: &mut [f64]) -> Result<()> {
        let n = self.n;
        let te_now = inp.tau_e.map(|te| &te[k * n..(k + 1) * n]);
        let del = std::mem::take(&mut ws.tau_e_del);
        let tau_e = match (te_now, self.ext.delay.is_some()) {
            (Some(now), true) => Some(ExoTorque { now, applied: Some(&del), applied_d: None, applied_dd: None }),
            (Some(now), false) => Some(ExoTorque::now(now)),
            _ => None,
        };
        let f_v = inp.f_v.map_or(0.0, |f| f[k]);
        let (mut qdd, qd) = (std::mem::take(&mut ws.qdd), std::mem::take(&mut ws.qdp));
        let r = self.forward_after_eval(ws, &qd, &inp.tau[k * n..(k + 1) * n], f_v, tau_e, &mut qdd);
        ws.tau_e_del = del;
        ws.qdp = qd;
        if r.is_ok() {
            let (qp, qn) = q_out[k * n..(k + 2) * n].split_at_mut(n);
            let (qdp, qdn) = qd_out[k * n..(k + 2) * n].split_at_mut(n);
            for i in 0..n {
                qdn[i] = qdp[i] + dt * qdd[i];
                qn[i] = qp[i] + dt * qdn[i];
            }
        }
        ws.qdd = qdd;
        r?;
        let next = (k + 1) * n..(k + 2) * n;
        if q_out[next.clone()].iter().chain(&qd_out[next]).any(|v| !v.is_finite()) {
            return Err(Error::Diverged { step: k + 1 });
        }
        Ok(())
    }
}
