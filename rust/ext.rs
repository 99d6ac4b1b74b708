//! Extension terms found by diagnosis (DESIGN.md section 4). A tensor absent from the file means
//! the term is off. The learned model predicts the recorded total torque τ_rec; the terms enter as
//!
//!   τ_rec = H q̈ + c + g − B f_v              (physics at the corrected coordinates)
//!         + D q̇ + Fc ⊙ tanh(q̇/ε) + Fs ⊙ e^{−(q̇/vs)²} ⊙ tanh(q̇/ε)     (dissipation, passive)
//!         + τ0 + (1 − 1/k) ⊙ τ_e + (τ_e(t) − τ_e(t − d))                 (exoskeleton torque sensor)
//!
//! with the physics evaluated at q − δ (encoder offset) and q − τ_e/k_s (strap compliance).
//! Forward dynamics solves the same relation for q̈.

use crate::error::{Error, Result};

#[derive(Debug, Clone, Default)]
pub struct Ext {
    /// D (n×n, row-major), PSD.
    pub damping: Option<Vec<f64>>,
    pub coulomb: Option<Vec<f64>>,
    pub stribeck_fs: Option<Vec<f64>>,
    pub stribeck_vs: Option<Vec<f64>>,
    pub encoder_offset: Option<Vec<f64>>,
    pub torque_bias: Option<Vec<f64>>,
    pub torque_gain: Option<Vec<f64>>,
    pub delay: Option<Vec<f64>>,
    pub strap_compliance: Option<Vec<f64>>,
}

impl Ext {
    pub(crate) fn load(
        n: usize,
        mut get: impl FnMut(&str, &[usize]) -> Result<Option<Vec<f64>>>,
    ) -> Result<Ext> {
        let v = |get: &mut dyn FnMut(&str, &[usize]) -> Result<Option<Vec<f64>>>, name: &str| get(name, &[n]);
        let ext = Ext {
            damping: get("ext.damping", &[n, n])?,
            coulomb: v(&mut get, "ext.coulomb")?,
            stribeck_fs: v(&mut get, "ext.stribeck_fs")?,
            stribeck_vs: v(&mut get, "ext.stribeck_vs")?,
            encoder_offset: v(&mut get, "ext.encoder_offset")?,
            torque_bias: v(&mut get, "ext.torque_bias")?,
            torque_gain: v(&mut get, "ext.torque_gain")?,
            delay: v(&mut get, "ext.delay")?,
            strap_compliance: v(&mut get, "ext.strap_compliance")?,
        };
        let bad = |name: &str, msg: &str| Err(Error::NonFiniteWeight(format!("{name} ({msg})")));
        if let Some(d) = &ext.damping {
            for i in 0..n {
                for j in 0..n {
                    if (d[i * n + j] - d[j * n + i]).abs() > 1e-9 * (1.0 + d[i * n + j].abs()) {
                        return bad("ext.damping", "must be symmetric");
                    }
                }
                if d[i * n + i] < 0.0 {
                    return bad("ext.damping", "must be positive semidefinite");
                }
            }
        }
        for (name, t) in [("ext.coulomb", &ext.coulomb), ("ext.stribeck_fs", &ext.stribeck_fs), ("ext.delay", &ext.delay)] {
            if t.as_ref().is_some_and(|v| v.iter().any(|x| *x < 0.0)) {
                return bad(name, "must be ≥ 0");
            }
        }
        if ext.stribeck_fs.is_some() != ext.stribeck_vs.is_some() {
            return bad("ext.stribeck_fs/ext.stribeck_vs", "both or neither");
        }
        for (name, t) in [
            ("ext.stribeck_vs", &ext.stribeck_vs),
            ("ext.torque_gain", &ext.torque_gain),
            ("ext.strap_compliance", &ext.strap_compliance),
        ] {
            if t.as_ref().is_some_and(|v| v.iter().any(|x| !(*x > 0.0))) {
                return bad(name, "must be > 0");
            }
        }
        Ok(ext)
    }

    /// Whether any term needs the recorded exoskeleton torque τ_e.
    pub fn needs_tau_e(&self) -> bool {
        self.torque_gain.is_some() || self.delay.is_some() || self.strap_compliance.is_some()
    }

    pub fn any(&self) -> bool {
        self.damping.is_some()
            || self.coulomb.is_some()
            || self.stribeck_fs.is_some()
            || self.encoder_offset.is_some()
            || self.torque_bias.is_some()
            || self.needs_tau_e()
    }

    /// Coordinates at which the physics is evaluated: q − δ − τ_e/k_s.
    #[inline(always)]
    pub(crate) fn physical_q(&self, q: &[f64], tau_e: Option<&[f64]>, out: &mut [f64]) {
        out.copy_from_slice(q);
        if let Some(d) = &self.encoder_offset {
            for i in 0..out.len() {
                out[i] -= d[i];
            }
        }
        if let (Some(k), Some(te)) = (&self.strap_compliance, tau_e) {
            for i in 0..out.len() {
                out[i] -= te[i] / k[i];
            }
        }
    }

    /// Dissipative torque D q̇ + Fc tanh(q̇/ε) + Fs e^{−(q̇/vs)²} tanh(q̇/ε), added to `tau`.
    #[inline(always)]
    pub(crate) fn add_dissipation(&self, qd: &[f64], eps: f64, tau: &mut [f64]) {
        let n = qd.len();
        if let Some(d) = &self.damping {
            for i in 0..n {
                let mut s = 0.0;
                for j in 0..n {
                    s += d[i * n + j] * qd[j];
                }
                tau[i] += s;
            }
        }
        if self.coulomb.is_some() || self.stribeck_fs.is_some() {
            for i in 0..n {
                let t = (qd[i] / eps).tanh();
                if let Some(fc) = &self.coulomb {
                    tau[i] += fc[i] * t;
                }
                if let (Some(fs), Some(vs)) = (&self.stribeck_fs, &self.stribeck_vs) {
                    let r = qd[i] / vs[i];
                    tau[i] += fs[i] * (-(r * r)).exp() * t;
                }
            }
        }
    }

    /// Sensor terms τ0 + (1 − 1/k) τ_e + (τ_e − τ_e(t−d)), added to `tau`.
    /// `tau_e_delayed` is τ_e(t − d) (the caller interpolates it from the recorded history).
    #[inline(always)]
    pub(crate) fn add_sensor(&self, tau_e: Option<&[f64]>, tau_e_delayed: Option<&[f64]>, tau: &mut [f64]) {
        let n = tau.len();
        if let Some(b) = &self.torque_bias {
            for i in 0..n {
                tau[i] += b[i];
            }
        }
        if let Some(te) = tau_e {
            if let Some(k) = &self.torque_gain {
                for i in 0..n {
                    tau[i] += (1.0 - 1.0 / k[i]) * te[i];
                }
            }
            if let (Some(_), Some(ted)) = (&self.delay, tau_e_delayed) {
                for i in 0..n {
                    tau[i] += te[i] - ted[i];
                }
            }
        }
    }
}
