//! Opt-in float32 single-sample calls: inverse dynamics, forward dynamics and single rollouts in a
//! [`Workspace<f32>`] (`Model::workspace_f32`). The pass is `delan::eval` and the kernels of `mlp.rs`,
//! generic over [`Real`](crate::real::Real), monomorphised for f32 (16 outputs per AVX-512 register
//! instead of 8, the float32 networks of the lane rollouts, `math32`'s tanh, sin/cos, softplus); inputs
//! and outputs stay float64 and are checked as in float64. A rollout integrates its state in float64
//! from the float32 q̈. Deterministic (fixed operation order); not bit-exact with the float64 calls:
//! `tests/single_f32.rs` bounds the difference. Models with extension terms are refused
//! (`Error::Unsupported`), as in the float32 lane rollouts.

use crate::delan::{eval_dispatch32, Workspace};
use crate::dynamics::{check, solve};
use crate::error::{Error, Result};
use crate::lanes::LaneBufs;
use crate::model::Model;
use crate::rollout::{Inputs, ZSeq};

impl Model {
    /// A workspace for the float32 single-sample calls (allocates; once per thread).
    pub fn workspace_f32(&self) -> Workspace<f32> {
        Workspace::build(self, LaneBufs::default())
    }

    /// The checks every float32 call shares (its other input, f_v, its output's length); q and q̇ into the
    /// workspace in float32.
    fn prepare_f32(&self, ws: &mut Workspace<f32>, q: &[f64], qd: &[f64], input: (&str, &[f64]), f_v: f64, out: (&str, usize)) -> Result<()> {
        let n = self.n;
        if self.ext.any() {
            return Err(Error::Unsupported("float32 single-sample calls run models without extension terms; use float64".into()));
        }
        if ws.n != n || ws.z.len() != self.dz {
            return Err(Error::InputShape("workspace was made for a different model".into()));
        }
        if !ws.z_ready {
            return Err(Error::InputShape(format!("context z (dimension {}) not set: call set_z first", self.dz)));
        }
        check("q", q, n)?;
        check("qd", qd, n)?;
        check(input.0, input.1, n)?;
        if !f_v.is_finite() {
            return Err(Error::NonFiniteInput("f_v".into()));
        }
        if out.1 != n {
            return Err(Error::InputShape(format!("{} output has {} entries, expected {n}", out.0, out.1)));
        }
        for i in 0..n {
            ws.qp[i] = q[i] as f32;
            ws.qdp[i] = qd[i] as f32;
        }
        Ok(())
    }

    /// The network pass with c at `ws.qp`, `ws.qdp`.
    #[inline]
    fn eval_f32(&self, ws: &mut Workspace<f32>) {
        let qd = std::mem::take(&mut ws.qdp);
        eval_dispatch32(self, ws, &qd, true);
        ws.qdp = qd;
    }

    /// q̈ = H⁻¹(τ + B f_v − c − g) into `ws.qdd` once `ws` holds the pass.
    #[inline]
    fn qdd_f32(&self, ws: &mut Workspace<f32>, tau: &[f64], f_v: f64) -> Result<()> {
        let fv = f_v as f32;
        for i in 0..self.n {
            ws.rhs[i] = tau[i] as f32 - (ws.c[i] + ws.g[i] - ws.b[i] * fv);
        }
        solve(self.n, &ws.h, &ws.l, &ws.rhs, &mut ws.qdd)
    }

    /// `inverse_dynamics` in float32 (no extension terms): τ = H q̈ + c + g − B f_v.
    #[allow(clippy::too_many_arguments)]
    pub fn inverse_dynamics_f32(&self, ws: &mut Workspace<f32>, q: &[f64], qd: &[f64], qdd: &[f64], f_v: f64, tau: &mut [f64]) -> Result<()> {
        let n = self.n;
        self.prepare_f32(ws, q, qd, ("qdd", qdd), f_v, ("tau", tau.len()))?;
        for i in 0..n {
            ws.qddp[i] = qdd[i] as f32;
        }
        self.eval_f32(ws);
        let fv = f_v as f32;
        for i in 0..n {
            let mut s = 0.0f32;
            for j in 0..n {
                s += ws.h[i * n + j] * ws.qddp[j];
            }
            tau[i] = (s + ws.c[i] + ws.g[i] - ws.b[i] * fv) as f64;
        }
        Ok(())
    }

    /// `forward_dynamics` in float32 (no extension terms): q̈ = H⁻¹(τ + B f_v − c − g); H is refused
    /// beyond cond 1e6 (`Error::IllConditioned`).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_dynamics_f32(&self, ws: &mut Workspace<f32>, q: &[f64], qd: &[f64], tau: &[f64], f_v: f64, qdd: &mut [f64]) -> Result<()> {
        let n = self.n;
        self.prepare_f32(ws, q, qd, ("tau", tau), f_v, ("qdd", qdd.len()))?;
        self.eval_f32(ws);
        self.qdd_f32(ws, tau, f_v)?;
        for i in 0..n {
            qdd[i] = ws.qdd[i] as f64;
        }
        Ok(())
    }

    /// `rollout` with float32 dynamics: each step's q̈ in float32, the semi-implicit Euler update and
    /// the state in float64 (no extension terms; `inp.tau_e` is checked and unused).
    #[allow(clippy::too_many_arguments)]
    pub fn rollout_f32(&self, ws: &mut Workspace<f32>, q0: &[f64], qd0: &[f64], inp: Inputs, dt: f64, q_out: &mut [f64], qd_out: &mut [f64]) -> Result<()> {
        let n = self.n;
        if self.ext.any() {
            return Err(Error::Unsupported("float32 single rollouts run models without extension terms; use float64".into()));
        }
        let t_len = self.rollout_begin(ws, q0, qd0, &inp, dt, q_out, qd_out)?;
        for k in 0..t_len {
            if let ZSeq::PerStep(z) = inp.z {
                ws.set_z(self, &z[k * self.dz..(k + 1) * self.dz])?;
            }
            for i in 0..n {
                ws.qp[i] = q_out[k * n + i] as f32;
                ws.qdp[i] = qd_out[k * n + i] as f32;
            }
            self.eval_f32(ws);
            self.qdd_f32(ws, &inp.tau[k * n..(k + 1) * n], inp.f_v.map_or(0.0, |f| f[k]))?;
            let (qp, qn) = q_out[k * n..(k + 2) * n].split_at_mut(n);
            let (qdp, qdn) = qd_out[k * n..(k + 2) * n].split_at_mut(n);
            for i in 0..n {
                qdn[i] = qdp[i] + dt * ws.qdd[i] as f64;
                qn[i] = qp[i] + dt * qdn[i];
            }
            if qn.iter().chain(qdn.iter()).any(|v| !v.is_finite()) {
                return Err(Error::Diverged { step: k + 1 });
            }
        }
        Ok(())
    }
}
