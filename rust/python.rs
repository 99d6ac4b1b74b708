//! The Python binding: `exolan._native`. Conversion only: shapes are checked, arrays borrowed, and the
//! core is called; every engine error becomes a Python exception carrying the engine's message.
//!
//! The batch methods take C-contiguous float64 arrays with the leading dimension in place
//! (`python/exolan/engine.py` arranges it) and run with the GIL released (`Python::detach`). The
//! `*_one` methods are the single-sample fast path: they keep the GIL (a call is ~1.5 µs; releasing and
//! re-taking the GIL costs more, and can wait a switch interval behind another thread) and raise
//! `TypeError` for anything that is not one plain sample, so the wrapper falls back to the batch path.

use numpy::{PyArray1, PyArrayDyn, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::python_conv::{bad, expect_shape, is_f32, lock, pool_for, rows, samples, scale_in_place, sum, to_py, view};
use crate::rollout::delayed_into;
use crate::batch::Samples;
use crate::python_engine::{ArrayPair, Engine};
use crate::{EncoderKind, Inputs, JointType, Model, ZSeq};

#[pymethods]
impl Engine {
    #[new]
    fn new(py: Python<'_>, path: std::path::PathBuf) -> PyResult<Self> {
        Ok(Engine::with_model(py.detach(|| Model::load(&path)).map_err(to_py)?))
    }

    /// Load from the bytes of a weight file.
    #[staticmethod]
    fn from_bytes(data: &[u8]) -> PyResult<Self> {
        Ok(Engine::with_model(Model::from_bytes(data).map_err(to_py)?))
    }

    #[getter]
    fn n(&self) -> usize {
        self.model.n
    }
    #[getter]
    fn z_dim(&self) -> usize {
        self.model.dz
    }
    #[getter]
    fn context_dim(&self) -> usize {
        self.model.context_dim()
    }
    #[getter]
    fn method(&self) -> String {
        self.model.meta.method.clone()
    }
    #[getter]
    fn lim(&self) -> bool {
        self.model.meta.lim
    }
    #[getter]
    fn encoder(&self) -> &'static str {
        match self.model.meta.encoder {
            EncoderKind::None => "none",
            EncoderKind::Tcn => "tcn",
            EncoderKind::Lstm => "lstm",
        }
    }
    #[getter]
    fn joint_names(&self) -> Vec<String> {
        self.model.meta.joint_names.clone()
    }
    #[getter]
    fn joint_types(&self) -> Vec<&'static str> {
        self.model
            .meta
            .joint_types
            .iter()
            .map(|t| if *t == JointType::Revolute { "revolute" } else { "prismatic" })
            .collect()
    }
    #[getter]
    fn context_channels(&self) -> Vec<String> {
        self.model.meta.context_channels.clone()
    }
    #[getter]
    fn dt(&self) -> f64 {
        self.model.meta.dt
    }
    /// Names of the extension tensors present (`ext.*`).
    #[getter]
    fn extensions(&self) -> Vec<&'static str> {
        let e = &self.model.ext;
        let mut v = vec![];
        for (name, on) in [
            ("ext.damping", e.damping.is_some()),
            ("ext.coulomb", e.coulomb.is_some()),
            ("ext.stribeck_fs", e.stribeck_fs.is_some()),
            ("ext.stribeck_vs", e.stribeck_vs.is_some()),
            ("ext.encoder_offset", e.encoder_offset.is_some()),
            ("ext.torque_bias", e.torque_bias.is_some()),
            ("ext.torque_gain", e.torque_gain.is_some()),
            ("ext.delay", e.delay.is_some()),
            ("ext.strap_compliance", e.strap_compliance.is_some()),
        ] {
            if on {
                v.push(name);
            }
        }
        v
    }
    /// Every metadata entry of the weight file.
    #[getter]
    fn metadata<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for (k, v) in &self.model.meta.raw {
            d.set_item(k, v)?;
        }
        Ok(d)
    }
    /// Code path in use: "avx512", "avx2-fma" or "portable".
    #[getter]
    fn simd(&self) -> &'static str {
        self.model.simd().name()
    }

    /// τ (N, n) from q, qd, qdd (N, n), z (N, dz), f_v (N,), optional exo torques (N, n).
    #[pyo3(signature = (q, qd, qdd, z=None, f_v=None, tau_e=None, tau_app=None, tau_app_d=None, tau_app_dd=None))]
    #[allow(clippy::too_many_arguments)]
    fn inverse_dynamics<'py>(
        &self,
        py: Python<'py>,
        q: PyReadonlyArrayDyn<'py, f64>,
        qd: PyReadonlyArrayDyn<'py, f64>,
        qdd: PyReadonlyArrayDyn<'py, f64>,
        z: Option<PyReadonlyArrayDyn<'py, f64>>,
        f_v: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_e: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_app: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_app_d: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_app_dd: Option<PyReadonlyArrayDyn<'py, f64>>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let n = self.model.n;
        let (sq, q) = view("q", &q)?;
        let ns = samples("q", &sq, n)?;
        let (s, qd) = view("qd", &qd)?;
        expect_shape("qd", &s, &[ns, n])?;
        let (s, qdd) = view("qdd", &qdd)?;
        expect_shape("qdd", &s, &[ns, n])?;
        let [z, f_v] = self.z_fv(ns, &z, &f_v)?;
        let w = [ns, n];
        let tau_e = [rows("tau_e", &tau_e, &w)?, rows("tau_app", &tau_app, &w)?, rows("tau_app_d", &tau_app_d, &w)?, rows("tau_app_dd", &tau_app_dd, &w)?];
        let s = Samples { z, f_v, tau_e };
        let out = self.per_sample(py, ns, n, |p, wss, out| self.model.inverse_dynamics_many(p, wss, q, qd, qdd, s, out))?;
        Ok(PyArray1::from_vec(py, out))
    }

    /// q̈ (N, n) from q, qd, tau (N, n), z, f_v, optional tau_e and tau_app (N, n).
    #[pyo3(signature = (q, qd, tau, z=None, f_v=None, tau_e=None, tau_app=None))]
    #[allow(clippy::too_many_arguments)]
    fn forward_dynamics<'py>(
        &self,
        py: Python<'py>,
        q: PyReadonlyArrayDyn<'py, f64>,
        qd: PyReadonlyArrayDyn<'py, f64>,
        tau: PyReadonlyArrayDyn<'py, f64>,
        z: Option<PyReadonlyArrayDyn<'py, f64>>,
        f_v: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_e: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_app: Option<PyReadonlyArrayDyn<'py, f64>>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let n = self.model.n;
        let (sq, q) = view("q", &q)?;
        let ns = samples("q", &sq, n)?;
        let (s, qd) = view("qd", &qd)?;
        expect_shape("qd", &s, &[ns, n])?;
        let (s, tau) = view("tau", &tau)?;
        expect_shape("tau", &s, &[ns, n])?;
        let [z, f_v] = self.z_fv(ns, &z, &f_v)?;
        let w = [ns, n];
        let s = Samples { z, f_v, tau_e: [rows("tau_e", &tau_e, &w)?, rows("tau_app", &tau_app, &w)?, None, None] };
        let out = self.per_sample(py, ns, n, |p, wss, out| self.model.forward_dynamics_many(p, wss, q, qd, tau, s, out))?;
        Ok(PyArray1::from_vec(py, out))
    }

    /// Single-sample τ: q, qd, qdd (n,) or (1, n), z (dz,) or (1, dz), f_v a number. `TypeError` for
    /// anything else (use `inverse_dynamics`). `precision` "f64" or "f32" (`inverse_dynamics_f32`).
    #[pyo3(signature = (q, qd, qdd, z=None, f_v=None, precision="f64"))]
    #[allow(clippy::too_many_arguments)]
    fn inverse_dynamics_one<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        qd: &Bound<'py, PyAny>,
        qdd: &Bound<'py, PyAny>,
        z: Option<&Bound<'py, PyAny>>,
        f_v: Option<&Bound<'py, PyAny>>,
        precision: &str,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        if is_f32(precision)? {
            return self.single(py, [q, qd, qdd], z, f_v, &self.ws32, |m, ws, [q, qd, qdd], f, out| m.inverse_dynamics_f32(ws, q, qd, qdd, f, out));
        }
        self.single(py, [q, qd, qdd], z, f_v, &self.ws, |m, ws, [q, qd, qdd], f, out| m.inverse_dynamics(ws, q, qd, qdd, f, None, out))
    }

    /// Single-sample q̈, as `inverse_dynamics_one`.
    #[pyo3(signature = (q, qd, tau, z=None, f_v=None, precision="f64"))]
    #[allow(clippy::too_many_arguments)]
    fn forward_dynamics_one<'py>(
        &self,
        py: Python<'py>,
        q: &Bound<'py, PyAny>,
        qd: &Bound<'py, PyAny>,
        tau: &Bound<'py, PyAny>,
        z: Option<&Bound<'py, PyAny>>,
        f_v: Option<&Bound<'py, PyAny>>,
        precision: &str,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        if is_f32(precision)? {
            return self.single(py, [q, qd, tau], z, f_v, &self.ws32, |m, ws, [q, qd, tau], f, out| m.forward_dynamics_f32(ws, q, qd, tau, f, out));
        }
        self.single(py, [q, qd, tau], z, f_v, &self.ws, |m, ws, [q, qd, tau], f, out| m.forward_dynamics(ws, q, qd, tau, f, None, out))
    }

    /// Flat [H (n·n), c (n), g (n), B (n)] per sample, (N·(n·n+3n),) — split by the wrapper.
    #[pyo3(signature = (q, qd, z=None))]
    fn terms<'py>(
        &self,
        py: Python<'py>,
        q: PyReadonlyArrayDyn<'py, f64>,
        qd: PyReadonlyArrayDyn<'py, f64>,
        z: Option<PyReadonlyArrayDyn<'py, f64>>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let (n, dz) = (self.model.n, self.model.dz);
        let (sq, q) = view("q", &q)?;
        let ns = samples("q", &sq, n)?;
        let (s, qd) = view("qd", &qd)?;
        expect_shape("qd", &s, &[ns, n])?;
        // f_v is not needed for the terms, even with LIM
        let z = rows("z", &z, &[ns, dz])?;
        if z.is_none() && dz > 0 {
            return Err(bad(format!("this model needs a context z of dimension {dz}")));
        }
        let out = self.per_sample(py, ns, n * n + 3 * n, |p, wss, out| self.model.terms_many(p, wss, q, qd, z, out))?;
        Ok(PyArray1::from_vec(py, out))
    }

    /// Batched rollouts: q0, qd0 (B, n), tau (B, T, n), z (B, dz) or (B, T, dz), f_v (B, T),
    /// tau_e (B, T, n); `threads` (None: one per core); `precision` "f64" (bit-exact) or "f32"
    /// (`rollout_batch_f32`; B = 1: `rollout_f32`). Returns flat q and qd, each B·(T+1)·n.
    #[pyo3(signature = (q0, qd0, tau, dt, z=None, f_v=None, tau_e=None, threads=None, precision="f64"))]
    #[allow(clippy::too_many_arguments)]
    fn rollout<'py>(
        &self,
        py: Python<'py>,
        q0: PyReadonlyArrayDyn<'py, f64>,
        qd0: PyReadonlyArrayDyn<'py, f64>,
        tau: PyReadonlyArrayDyn<'py, f64>,
        dt: f64,
        z: Option<PyReadonlyArrayDyn<'py, f64>>,
        f_v: Option<PyReadonlyArrayDyn<'py, f64>>,
        tau_e: Option<PyReadonlyArrayDyn<'py, f64>>,
        threads: Option<usize>,
        precision: &str,
    ) -> PyResult<ArrayPair<'py>> {
        let m = &self.model;
        let f32 = is_f32(precision)?;
        let (n, dz) = (m.n, m.dz);
        let (s, q0) = view("q0", &q0)?;
        let b = samples("q0", &s, n)?;
        let (s, qd0) = view("qd0", &qd0)?;
        expect_shape("qd0", &s, &[b, n])?;
        let (s, tau) = view("tau", &tau)?;
        let t_len = match s.as_slice() {
            [bb, t, k] if *bb == b && *k == n => *t,
            _ => return Err(bad(format!("bad input shape: tau has shape {s:?}, expected (B={b}, T, n={n})"))),
        };
        let zs = match &z {
            Some(a) => {
                let (s, d) = view("z", a)?;
                if s == [b, dz] {
                    ZSeq::Const(d)
                } else if s == [b, t_len, dz] {
                    ZSeq::PerStep(d)
                } else {
                    return Err(bad(format!("bad input shape: z has shape {s:?}, expected ({b}, {dz}) or ({b}, {t_len}, {dz})")));
                }
            }
            None if dz > 0 => return Err(bad(format!("this model needs a context z of dimension {dz}"))),
            None => ZSeq::Keep,
        };
        let f_v = rows("f_v", &f_v, &[b, t_len])?;
        if f_v.is_none() && m.meta.lim {
            return Err(bad("a model with LIM needs the insole force f_v".into()));
        }
        let tau_e = rows("tau_e", &tau_e, &[b, t_len, n])?;
        let mut q = vec![0.0; b * (t_len + 1) * n];
        let mut qd = vec![0.0; b * (t_len + 1) * n];
        let pool = pool_for(if b == 1 { Some(1) } else { threads })?;
        py.detach(|| {
            let inp = Inputs { tau, z: zs, f_v, tau_e };
            if f32 && b == 1 && !m.ext.any() {
                let mut ws = lock(&self.ws32);
                if dz == 0 {
                    ws.set_z(m, &[])?;
                }
                m.rollout_f32(&mut ws, q0, qd0, inp, dt, &mut q, &mut qd)
            } else if f32 {
                self.with_lanes(b, |lws| m.rollout_batch_f32(&pool, lws, q0, qd0, inp, dt, &mut q, &mut qd))
            } else if b == 1 {
                let mut ws = self.ws();
                if dz == 0 {
                    ws.set_z(m, &[])?;
                }
                m.rollout(&mut ws, q0, qd0, inp, dt, &mut q, &mut qd)
            } else {
                self.with_workspaces(b, |wss| m.rollout_batch(&pool, wss, q0, qd0, inp, dt, &mut q, &mut qd))
            }
        })
        .map_err(to_py)?;
        Ok((PyArray1::from_vec(py, q), PyArray1::from_vec(py, qd)))
    }

    /// Stream raw context sequences x (B, T, C) through the encoder from zero state, one sample at
    /// a time; returns flat z, B·T·dz.
    fn encode<'py>(&self, py: Python<'py>, x: PyReadonlyArrayDyn<'py, f64>) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let m = &self.model;
        let (c, dz) = (m.context_dim(), m.dz);
        if m.meta.encoder == EncoderKind::None {
            return Err(bad(format!("method {:?} has no context encoder", m.meta.method)));
        }
        let (s, x) = view("x", &x)?;
        let (b, t_len) = match s.as_slice() {
            [b, t, k] if *k == c => (*b, *t),
            _ => return Err(bad(format!("bad input shape: x has shape {s:?}, expected (B, T, C={c})"))),
        };
        let mut z = vec![0.0; b * t_len * dz];
        if t_len > 0 && dz > 0 {
            let pool = pool_for(None)?;
            py.detach(|| {
                let mut states: Vec<_> = (0..b).map(|_| m.encoder_state()).collect();
                m.encode_batch(&pool, &mut states, x, &mut z)
            })
            .map_err(to_py)?;
        }
        Ok(PyArray1::from_vec(py, z))
    }

    /// Native per-call cost of a hot path, timed inside Rust (`exolan::timing::time_hot`), seconds.
    #[pyo3(signature = (op, per_batch=200, batches=100))]
    fn time_hot(&self, py: Python<'_>, op: &str, per_batch: usize, batches: usize) -> PyResult<f64> {
        py.detach(|| crate::timing::time_hot(&self.model, op, per_batch, batches)).map_err(to_py)
    }

    /// The applied exoskeleton torque τ_e(t − d) of a recorded sequence (T, n), with the model's
    /// `ext.delay` (linear interpolation, clamped at the first sample); τ_e itself without delay.
    fn applied_exo<'py>(&self, py: Python<'py>, tau_e: PyReadonlyArrayDyn<'py, f64>, dt: f64) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let n = self.model.n;
        let (s, te) = view("tau_e", &tau_e)?;
        let t_len = samples("tau_e", &s, n)?;
        if !(dt.is_finite() && dt > 0.0) {
            return Err(bad(format!("dt must be finite and > 0, got {dt}")));
        }
        let mut out = te.to_vec();
        if let Some(d) = &self.model.ext.delay {
            for k in 0..t_len {
                delayed_into(te, n, k, dt, d, &mut out[k * n..(k + 1) * n]);
            }
        }
        Ok(PyArray1::from_vec(py, out))
    }
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", crate::VERSION)?;
    m.add("FORMAT_VERSION", crate::model::FORMAT_VERSION)?;
    m.add_function(wrap_pyfunction!(sum, m)?)?;
    m.add_function(wrap_pyfunction!(scale_in_place, m)?)?;
    m.add_class::<Engine>()?;
    m.add_function(wrap_pyfunction!(crate::python_grad::terms_forward, m)?)?;
    m.add_class::<crate::python_grad::TermsCall>()?;
    m.add_function(wrap_pyfunction!(crate::python_grad::mlp_forward, m)?)?;
    m.add_class::<crate::python_grad::MlpCall>()?;
    m.add_function(wrap_pyfunction!(crate::python_tcn::tcn_forward, m)?)?;
    m.add_class::<crate::python_tcn::TcnCall>()?;
    Ok(())
}
