//! The Python binding: `exolan._native`. Thin by design: argument checking and conversion only;
//! the work happens in the pure-Rust core with the GIL released (`Python::detach`).
//!
//! The methods take C-contiguous float64 arrays with the leading batch dimension already in place
//! (`python/exolan/engine.py` adds it for single samples); shapes are checked here and every
//! engine error becomes a Python exception carrying the engine's message.

use std::sync::Mutex;

use numpy::{PyArray1, PyReadonlyArray1, PyReadonlyArrayDyn, PyReadwriteArray1, PyUntypedArrayMethods};
use pyo3::exceptions::{PyArithmeticError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;

use crate::rollout::delayed_into;
use crate::{EncoderKind, Error, ExoTorque, Inputs, JointType, Model, Workspace, ZSeq};

/// Sum of a contiguous float64 array (read without copying).
#[pyfunction]
fn sum(xs: PyReadonlyArray1<'_, f64>) -> PyResult<f64> {
    let s = xs
        .as_slice()
        .map_err(|_| PyValueError::new_err("sum: array must be contiguous float64"))?;
    Ok(crate::sum(s))
}

/// Multiply a contiguous float64 array by `k` in place; returns the address of the data it
/// worked on so a test can check that it is numpy's own buffer (zero copy).
#[pyfunction]
fn scale_in_place(mut xs: PyReadwriteArray1<'_, f64>, k: f64) -> PyResult<usize> {
    let s = xs
        .as_slice_mut()
        .map_err(|_| PyValueError::new_err("scale_in_place: array must be contiguous float64"))?;
    let addr = s.as_ptr() as usize;
    crate::scale_in_place(s, k);
    Ok(addr)
}

fn to_py(e: Error) -> PyErr {
    let msg = e.to_string();
    match e {
        Error::Io(_) => PyOSError::new_err(msg),
        Error::IllConditioned { .. } | Error::Diverged { .. } => PyArithmeticError::new_err(msg),
        _ => PyValueError::new_err(msg),
    }
}

fn bad(msg: String) -> PyErr {
    PyValueError::new_err(msg)
}

/// Shape and data of a contiguous array.
fn view<'a>(name: &str, a: &'a PyReadonlyArrayDyn<'_, f64>) -> PyResult<(Vec<usize>, &'a [f64])> {
    let s = a.as_slice().map_err(|_| bad(format!("{name} must be a C-contiguous float64 array")))?;
    Ok((a.shape().to_vec(), s))
}

fn expect_shape(name: &str, shape: &[usize], want: &[usize]) -> PyResult<()> {
    if shape != want {
        return Err(bad(format!("bad input shape: {name} has shape {shape:?}, expected {want:?}")));
    }
    Ok(())
}

/// Run `f` on a rayon pool of `threads` threads (cached per count), or on the global pool.
fn with_threads<T: Send>(threads: Option<usize>, f: impl FnOnce() -> T + Send) -> PyResult<T> {
    use std::collections::HashMap;
    use std::sync::{Arc, OnceLock};
    static POOLS: OnceLock<Mutex<HashMap<usize, Arc<rayon::ThreadPool>>>> = OnceLock::new();
    match threads {
        None | Some(0) => Ok(f()),
        Some(t) => {
            let pool = {
                let mut pools = POOLS.get_or_init(|| Mutex::new(HashMap::new())).lock().unwrap_or_else(|p| p.into_inner());
                match pools.get(&t) {
                    Some(p) => p.clone(),
                    None => {
                        let p = Arc::new(
                            rayon::ThreadPoolBuilder::new()
                                .num_threads(t)
                                .build()
                                .map_err(|e| PyValueError::new_err(format!("cannot start {t} threads: {e}")))?,
                        );
                        pools.insert(t, p.clone());
                        p
                    }
                }
            };
            Ok(pool.install(f))
        }
    }
}

type ArrayPair<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

/// Samples per rayon task: small batches stay on the calling thread.
const CHUNK: usize = 64;

/// A loaded model. Methods take batched arrays (leading dimension N or B).
#[pyclass(module = "exolan._native", frozen)]
struct Engine {
    model: Model,
    /// Workspace for single-sample calls (no allocation per call).
    ws: Mutex<Workspace>,
}

/// The per-sample optional arrays of inverse/forward dynamics, as slices.
struct Opt<'a> {
    z: Option<&'a [f64]>,
    f_v: Option<&'a [f64]>,
    tau_e: Option<&'a [f64]>,
    tau_app: Option<&'a [f64]>,
    tau_app_d: Option<&'a [f64]>,
    tau_app_dd: Option<&'a [f64]>,
}

impl Engine {
    fn check_opt<'a>(
        &self,
        n_samples: usize,
        z: &'a Option<PyReadonlyArrayDyn<'_, f64>>,
        f_v: &'a Option<PyReadonlyArrayDyn<'_, f64>>,
        tau_e: [&'a Option<PyReadonlyArrayDyn<'_, f64>>; 4],
    ) -> PyResult<Opt<'a>> {
        let (n, dz) = (self.model.n, self.model.dz);
        let z = match z {
            Some(a) => {
                let (s, d) = view("z", a)?;
                expect_shape("z", &s, &[n_samples, dz])?;
                Some(d)
            }
            None if dz > 0 => return Err(bad(format!("this model ({}) needs a context z of dimension {dz}", self.model.meta.method))),
            None => None,
        };
        let f_v = match f_v {
            Some(a) => {
                let (s, d) = view("f_v", a)?;
                expect_shape("f_v", &s, &[n_samples])?;
                Some(d)
            }
            None if self.model.meta.lim => return Err(bad("a model with LIM needs the insole force f_v".into())),
            None => None,
        };
        let names = ["tau_e", "tau_app", "tau_app_d", "tau_app_dd"];
        let mut te: [Option<&[f64]>; 4] = [None; 4];
        for (k, a) in tau_e.iter().enumerate() {
            if let Some(a) = a {
                let (s, d) = view(names[k], a)?;
                expect_shape(names[k], &s, &[n_samples, n])?;
                te[k] = Some(d);
            }
        }
        if te[0].is_none() && te[1..].iter().any(|x| x.is_some()) {
            return Err(bad("tau_app/tau_app_d/tau_app_dd need tau_e".into()));
        }
        Ok(Opt { z, f_v, tau_e: te[0], tau_app: te[1], tau_app_d: te[2], tau_app_dd: te[3] })
    }

    /// Run `f(ws, i, out_i)` for every sample i, in parallel chunks for large N.
    fn per_sample<F>(&self, py: Python<'_>, n_samples: usize, width: usize, o: &Opt, f: F) -> PyResult<Vec<f64>>
    where
        F: Fn(&Model, &mut Workspace, usize, Option<ExoTorque>, &mut [f64]) -> Result<(), Error> + Sync,
    {
        let m = &self.model;
        let (n, dz) = (m.n, m.dz);
        let run = |ws: &mut Workspace, i0: usize, out: &mut [f64]| -> Result<(), Error> {
            for (r, o_i) in out.chunks_mut(width).enumerate() {
                let i = i0 + r;
                if let Some(z) = o.z {
                    ws.set_z(m, &z[i * dz..(i + 1) * dz])?;
                }
                let te = o.tau_e.map(|t| ExoTorque {
                    now: &t[i * n..(i + 1) * n],
                    applied: o.tau_app.map(|x| &x[i * n..(i + 1) * n]),
                    applied_d: o.tau_app_d.map(|x| &x[i * n..(i + 1) * n]),
                    applied_dd: o.tau_app_dd.map(|x| &x[i * n..(i + 1) * n]),
                });
                f(m, ws, i, te, o_i).map_err(|e| match e {
                    Error::IllConditioned { .. } | Error::Diverged { .. } => e,
                    Error::NonFiniteInput(s) => Error::NonFiniteInput(format!("{s} (sample {i})")),
                    other => other,
                })?;
            }
            Ok(())
        };
        let mut out = vec![0.0; n_samples * width];
        let shared = &self.ws;
        py.detach(|| {
            if n_samples <= CHUNK {
                let mut ws = shared.lock().unwrap_or_else(|p| p.into_inner());
                run(&mut ws, 0, &mut out)
            } else {
                // Each chunk has its own workspace; every sample is computed by the same
                // sequential code whatever the thread count, so results are bit-identical.
                let errs: Vec<Option<Error>> = out
                    .par_chunks_mut(CHUNK * width)
                    .enumerate()
                    .map(|(c, chunk)| {
                        let mut ws = m.workspace();
                        run(&mut ws, c * CHUNK, chunk).err()
                    })
                    .collect();
                match errs.into_iter().flatten().next() {
                    Some(e) => Err(e),
                    None => Ok(()),
                }
            }
        })
        .map_err(to_py)?;
        Ok(out)
    }
}

fn samples(name: &str, shape: &[usize], n: usize) -> PyResult<usize> {
    match shape {
        [s, k] if *k == n => Ok(*s),
        _ => Err(bad(format!("bad input shape: {name} has shape {shape:?}, expected (N, {n})"))),
    }
}

#[pymethods]
impl Engine {
    #[new]
    fn new(py: Python<'_>, path: std::path::PathBuf) -> PyResult<Self> {
        let model = py.detach(|| Model::load(&path)).map_err(to_py)?;
        let ws = Mutex::new(model.workspace());
        Ok(Engine { model, ws })
    }

    /// Load from the bytes of a weight file.
    #[staticmethod]
    fn from_bytes(data: &[u8]) -> PyResult<Self> {
        let model = Model::from_bytes(data).map_err(to_py)?;
        let ws = Mutex::new(model.workspace());
        Ok(Engine { model, ws })
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
    /// Code path in use: "avx2-fma" or "portable".
    #[getter]
    fn simd(&self) -> &'static str {
        match self.model.simd() {
            crate::Simd::Avx2Fma => "avx2-fma",
            crate::Simd::Portable => "portable",
        }
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
        let o = self.check_opt(ns, &z, &f_v, [&tau_e, &tau_app, &tau_app_d, &tau_app_dd])?;
        let out = self.per_sample(py, ns, n, &o, |m, ws, i, te, out| {
            let f = o.f_v.map_or(0.0, |f| f[i]);
            m.inverse_dynamics(ws, &q[i * n..(i + 1) * n], &qd[i * n..(i + 1) * n], &qdd[i * n..(i + 1) * n], f, te, out)
        })?;
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
        let o = self.check_opt(ns, &z, &f_v, [&tau_e, &tau_app, &None, &None])?;
        let out = self.per_sample(py, ns, n, &o, |m, ws, i, te, out| {
            let f = o.f_v.map_or(0.0, |f| f[i]);
            m.forward_dynamics(ws, &q[i * n..(i + 1) * n], &qd[i * n..(i + 1) * n], &tau[i * n..(i + 1) * n], f, te, out)
        })?;
        Ok(PyArray1::from_vec(py, out))
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
        let n = self.model.n;
        let (sq, q) = view("q", &q)?;
        let ns = samples("q", &sq, n)?;
        let (s, qd) = view("qd", &qd)?;
        expect_shape("qd", &s, &[ns, n])?;
        // f_v is not needed for the terms, even with LIM
        let zz = match &z {
            Some(a) => {
                let (s, d) = view("z", a)?;
                expect_shape("z", &s, &[ns, self.model.dz])?;
                Some(d)
            }
            None if self.model.dz > 0 => return Err(bad(format!("this model needs a context z of dimension {}", self.model.dz))),
            None => None,
        };
        let o = Opt { z: zz, f_v: None, tau_e: None, tau_app: None, tau_app_d: None, tau_app_dd: None };
        let w = n * n + 3 * n;
        let out = self.per_sample(py, ns, w, &o, |m, ws, i, _, out| {
            m.terms(ws, &q[i * n..(i + 1) * n], &qd[i * n..(i + 1) * n])?;
            out[..n * n].copy_from_slice(ws.h());
            out[n * n..n * n + n].copy_from_slice(ws.c());
            out[n * n + n..n * n + 2 * n].copy_from_slice(ws.g());
            out[n * n + 2 * n..].copy_from_slice(ws.b());
            Ok(())
        })?;
        Ok(PyArray1::from_vec(py, out))
    }

    /// Batched rollouts: q0, qd0 (B, n), tau (B, T, n), z (B, dz) or (B, T, dz), f_v (B, T),
    /// tau_e (B, T, n). Returns flat q and qd, each B·(T+1)·n.
    #[pyo3(signature = (q0, qd0, tau, dt, z=None, f_v=None, tau_e=None, threads=None))]
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
    ) -> PyResult<ArrayPair<'py>> {
        let m = &self.model;
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
        let f_v = match &f_v {
            Some(a) => {
                let (s, d) = view("f_v", a)?;
                expect_shape("f_v", &s, &[b, t_len])?;
                Some(d)
            }
            None if m.meta.lim => return Err(bad("a model with LIM needs the insole force f_v".into())),
            None => None,
        };
        let tau_e = match &tau_e {
            Some(a) => {
                let (s, d) = view("tau_e", a)?;
                expect_shape("tau_e", &s, &[b, t_len, n])?;
                Some(d)
            }
            None => None,
        };
        let mut q = vec![0.0; b * (t_len + 1) * n];
        let mut qd = vec![0.0; b * (t_len + 1) * n];
        let shared = &self.ws;
        py.detach(|| {
            let inp = Inputs { tau, z: zs, f_v, tau_e };
            if b == 1 {
                let mut ws = shared.lock().unwrap_or_else(|p| p.into_inner());
                if dz == 0 {
                    ws.set_z(m, &[])?;
                }
                m.rollout(&mut ws, q0, qd0, inp, dt, &mut q, &mut qd)
            } else {
                let mut wss: Vec<Workspace> = (0..b).map(|_| m.workspace()).collect();
                with_threads(threads, || m.rollout_batch(&mut wss, q0, qd0, inp, dt, &mut q, &mut qd))
                    .unwrap_or_else(|e| Err(Error::InputShape(e.to_string())))
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
            py.detach(|| {
                z.par_chunks_mut(t_len * dz).enumerate().try_for_each(|(bi, zb)| {
                    let mut st = m.encoder_state();
                    for t in 0..t_len {
                        let o = (bi * t_len + t) * c;
                        m.encode_step(&mut st, &x[o..o + c], &mut zb[t * dz..(t + 1) * dz])?;
                    }
                    Ok::<(), Error>(())
                })
            })
            .map_err(to_py)?;
        }
        Ok(PyArray1::from_vec(py, z))
    }

    /// Native per-call cost of a hot path, timed inside Rust (no Python in the loop): the minimum
    /// over `batches` batches of `per_batch` calls, in seconds. `op`: "inverse", "forward",
    /// "rollout_step" (a 200-step rollout / 200, constant z) or "encode_step".
    #[pyo3(signature = (op, per_batch=200, batches=100))]
    fn time_hot(&self, py: Python<'_>, op: &str, per_batch: usize, batches: usize) -> PyResult<f64> {
        use std::hint::black_box;
        use std::time::Instant;
        let m = &self.model;
        let n = m.n;
        let per_batch = per_batch.max(1);
        let mut ws = m.workspace();
        let z: Vec<f64> = (0..m.dz).map(|i| (i as f64 * 0.37).sin() * 0.5).collect();
        ws.set_z(m, &z).map_err(to_py)?;
        let q: Vec<f64> = (0..n).map(|i| 0.3 + 0.2 * i as f64).collect();
        let qd: Vec<f64> = (0..n).map(|i| 1.0 - 0.5 * i as f64).collect();
        let mut out = vec![0.0; n];
        let t_len = 200;
        let tau = vec![1.0; t_len * n];
        let f_v = vec![200.0; t_len];
        let (mut qo, mut qdo) = (vec![0.0; (t_len + 1) * n], vec![0.0; (t_len + 1) * n]);
        let mut st = m.encoder_state();
        let x = vec![0.5; m.context_dim()];
        let mut zo = vec![0.0; m.dz];
        let op = op.to_string();
        let best = py.detach(|| -> Result<f64, Error> {
            let mut best = f64::INFINITY;
            for _ in 0..batches.max(1) {
                let t = Instant::now();
                let mut calls = per_batch;
                match op.as_str() {
                    "inverse" => {
                        for _ in 0..per_batch {
                            m.inverse_dynamics(&mut ws, black_box(&q), black_box(&qd), black_box(&qd), 100.0, None, &mut out)?;
                        }
                    }
                    "forward" => {
                        for _ in 0..per_batch {
                            m.forward_dynamics(&mut ws, black_box(&q), black_box(&qd), black_box(&qd), 100.0, None, &mut out)?;
                        }
                    }
                    "rollout_step" => {
                        let zs = if m.dz > 0 { ZSeq::Const(&z) } else { ZSeq::Keep };
                        m.rollout(&mut ws, &q, &qd, Inputs { tau: &tau, z: zs, f_v: Some(&f_v), tau_e: None }, 0.005, &mut qo, &mut qdo)?;
                        calls = t_len;
                    }
                    "encode_step" => {
                        for _ in 0..per_batch {
                            m.encode_step(&mut st, black_box(&x), &mut zo)?;
                        }
                    }
                    other => return Err(Error::InputShape(format!("unknown op {other:?}"))),
                }
                best = best.min(t.elapsed().as_secs_f64() / calls as f64);
            }
            Ok(best)
        });
        best.map_err(to_py)
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
    Ok(())
}
