//! Extension terms found by diagnosis (DESIGN.md section 4), as `exolan.extensions.ExtendedModel`
//! defines them. A tensor absent from the file means the term is off.
//!
//! Inverse dynamics (measured coordinates in, predicted recorded total torque out):
//!   τ_app = τ_e(t − d)   (recorded exo torque delayed; the caller supplies it, see `ExoTorque`)
//!   q_p = q − δ − τ_app/k_s,  q̇_p = q̇ − τ̇_app/k_s,  q̈_p = q̈ − τ̈_app/k_s      (offset, strap)
//!   τ_rec = H q̈_p + c + g − B f_v  (all at q_p, q̇_p)
//!         + D q̇_p + Fc ⊙ tanh(q̇_p/ε) + Fs ⊙ e^{−(q̇_p/vs)²} ⊙ tanh(q̇_p/ε)   (dissipation, passive)
//!         + (τ_e − τ_app) + τ0 + (1 − 1/k) ⊙ τ_e                              (recording terms)
//! Forward dynamics works in physical coordinates (q, q̇ are q_p, q̇_p, as in torch):
//!   q̈ = H⁻¹(τ − recording terms − dissipation(q̇) + B f_v − c − g).

use crate::error::{Error, Result};

#[derive(Debug, Clone, Default)]
pub struct Ext {
    /// D (n×n, row-major), symmetric PSD.
    pub damping: Option<Vec<f64>>,
    pub coulomb: Option<Vec<f64>>,
    pub stribeck_fs: Option<Vec<f64>>,
    pub stribeck_vs: Option<Vec<f64>>,
    pub encoder_offset: Option<Vec<f64>>,
    pub torque_bias: Option<Vec<f64>>,
    /// k as stored; the engine uses a = 1 − 1/k.
    pub torque_gain: Option<Vec<f64>>,
    /// d in seconds (0 on joints without the effect).
    pub delay: Option<Vec<f64>>,
    /// Strap stiffness k_s as stored (+inf on joints without the effect).
    pub strap_compliance: Option<Vec<f64>>,
    /// 1/k_s (0 where k_s = inf), precomputed.
    pub(crate) compliance: Option<Vec<f64>>,
}

/// Tensors an exporter may write; any other `ext.*` name is an error.
pub const EXT_TENSORS: [&str; 9] = [
    "ext.damping",
    "ext.coulomb",
    "ext.stribeck_fs",
    "ext.stribeck_vs",
    "ext.encoder_offset",
    "ext.torque_bias",
    "ext.torque_gain",
    "ext.delay",
    "ext.strap_compliance",
];

impl Ext {
    /// `get(name, shape, allow_pos_inf)` returns the tensor if present.
    pub(crate) fn load(
        n: usize,
        mut get: impl FnMut(&str, &[usize], bool) -> Result<Option<Vec<f64>>>,
    ) -> Result<Ext> {
        let mut ext = Ext {
            damping: get("ext.damping", &[n, n], false)?,
            coulomb: get("ext.coulomb", &[n], false)?,
            stribeck_fs: get("ext.stribeck_fs", &[n], false)?,
            stribeck_vs: get("ext.stribeck_vs", &[n], false)?,
            encoder_offset: get("ext.encoder_offset", &[n], false)?,
            torque_bias: get("ext.torque_bias", &[n], false)?,
            torque_gain: get("ext.torque_gain", &[n], false)?,
            delay: get("ext.delay", &[n], false)?,
            strap_compliance: get("ext.strap_compliance", &[n], true)?,
            compliance: None,
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
        ext.compliance = ext.strap_compliance.as_ref().map(|k| k.iter().map(|k| 1.0 / k).collect());
        Ok(ext)
    }

    /// Whether any term reads the recorded exoskeleton torque τ_e.
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

    /// Measured → physical: x_p = x − (δ for positions) − τ_app^{(i)}/k_s.
    #[inline(always)]
    pub(crate) fn physical(&self, x: &[f64], offset: bool, strap: Option<&[f64]>, out: &mut [f64]) {
        out.copy_from_slice(x);
        if offset {
            if let Some(d) = &self.encoder_offset {
                for i in 0..out.len() {
                    out[i] -= d[i];
                }
            }
        }
        if let (Some(c), Some(t)) = (&self.compliance, strap) {
            for i in 0..out.len() {
                out[i] -= c[i] * t[i];
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

    /// Recording terms (τ_e − τ_app) + τ0 + (1 − 1/k) τ_e, added to `tau`.
    #[inline(always)]
    pub(crate) fn add_recording(&self, tau_e: Option<&[f64]>, tau_app: Option<&[f64]>, tau: &mut [f64]) {
        let n = tau.len();
        if let Some(b) = &self.torque_bias {
            for i in 0..n {
                tau[i] += b[i];
            }
        }
        if let Some(te) = tau_e {
            if let (Some(_), Some(ta)) = (&self.delay, tau_app) {
                for i in 0..n {
                    tau[i] += te[i] - ta[i];
                }
            }
            if let Some(k) = &self.torque_gain {
                for i in 0..n {
                    tau[i] += (1.0 - 1.0 / k[i]) * te[i];
                }
            }
        }
    }
}
