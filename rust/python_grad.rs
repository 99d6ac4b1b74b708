//! The binding of the training kernels (`grad`): `terms_forward` and `TermsCall.backward`, `mlp_forward` and
//! `MlpCall.backward`, float32 or float64 throughout, every array C-contiguous and written in place (the
//! Python modules native_terms.py and native_mlp.py own the tensors). The GIL is released while a kernel runs.

use numpy::{Element, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArrayDyn, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyList;

use crate::grad::{KernelReal, LayerRef, MlpKernel, NetGrads, Tape, TermsKernel as Kernel};
use crate::python_conv::{bad, pool_for, to_py};
use crate::JointType;

enum Call {
    F32(Kernel<f32>, Tape<f32>),
    F64(Kernel<f64>, Tape<f64>),
}

/// A forward pass's prepared weights and tape, for its reverse pass.
#[pyclass(module = "exolan._native")]
pub(crate) struct TermsCall {
    call: Call,
}

fn slice<'a, T: Element>(name: &str, a: &'a PyReadonlyArrayDyn<'_, T>) -> PyResult<&'a [T]> {
    a.as_slice().map_err(|_| bad(format!("terms: {name} must be C-contiguous")))
}

fn slice_mut<'a, T: Element>(name: &str, a: &'a mut PyReadwriteArrayDyn<'_, T>) -> PyResult<&'a mut [T]> {
    a.as_slice_mut().map_err(|_| bad(format!("terms: {name} must be C-contiguous and writable")))
}

fn parse_joint_types(names: &[String]) -> PyResult<Vec<JointType>> {
    names.iter().map(|t| match t.as_str() {
        "revolute" => Ok(JointType::Revolute),
        "prismatic" => Ok(JointType::Prismatic),
        other => Err(bad(format!("terms: unknown joint type {other:?}"))),
    }).collect()
}

/// [W₀, b₀, W₁, b₁, …] as (W, b, out, in) per layer.
fn layers<'a, T: Element>(name: &str, arrays: &'a [PyReadonlyArrayDyn<'_, T>]) -> PyResult<Vec<LayerRef<'a, T>>> {
    if arrays.len() % 2 != 0 {
        return Err(bad(format!("terms: the {name} network's arrays must come as weight, bias pairs")));
    }
    arrays.chunks(2).enumerate().map(|(i, p)| {
        let shape = p[0].shape();
        if shape.len() != 2 || p[1].shape() != [shape[0]] {
            return Err(bad(format!("terms: {name} layer {i} has weight {shape:?} and bias {:?}", p[1].shape())));
        }
        Ok((slice("a weight", &p[0])?, slice("a bias", &p[1])?, shape[0], shape[1]))
    }).collect()
}

#[allow(clippy::too_many_arguments)]
fn forward<T: Element + KernelReal>(
    py: Python<'_>, types: &[JointType], dz: usize, offset: f64, v_scale: f64, lw: &[PyReadonlyArrayDyn<'_, T>],
    vw: &[PyReadonlyArrayDyn<'_, T>], inputs: [&PyReadonlyArrayDyn<'_, T>; 3], mut outs: [PyReadwriteArrayDyn<'_, T>; 4],
    keep: bool, threads: usize,
) -> PyResult<(Kernel<T>, Tape<T>)> {
    let kernel = Kernel::new(types, dz, offset, v_scale, &layers("inertia", lw)?, &layers("potential", vw)?).map_err(to_py)?;
    let [q, qd, z] = inputs;
    let (q, qd, z) = (slice("q", q)?, slice("qd", qd)?, slice("z", z)?);
    let [lo, ho, co, go] = &mut outs;
    let (lo, ho, co, go) = (slice_mut("L", lo)?, slice_mut("H", ho)?, slice_mut("c", co)?, slice_mut("g", go)?);
    let pool = pool_for(Some(threads.max(1)))?;
    let mut tape = Tape::new();
    py.detach(|| kernel.forward(q, qd, z, lo, ho, co, go, if keep { Some(&mut tape) } else { None }, &pool)).map_err(to_py)?;
    Ok((kernel, tape))
}

/// L, H (N, n, n), c, g (N, n) written into the given arrays from q, qd (N, n), z (N, dz) and the two
/// networks' [W, b, …] (float32 or float64, all alike). With `keep`, returns the call for `backward`.
#[pyfunction]
#[pyo3(signature = (joint_types, dz, softplus_offset, v_scale, l_weights, v_weights, q, qd, z, l_out, h_out, c_out, g_out, keep, threads))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn terms_forward(
    py: Python<'_>, joint_types: Vec<String>, dz: usize, softplus_offset: f64, v_scale: f64,
    l_weights: &Bound<'_, PyList>, v_weights: &Bound<'_, PyList>, q: &Bound<'_, PyAny>, qd: &Bound<'_, PyAny>,
    z: &Bound<'_, PyAny>, l_out: &Bound<'_, PyAny>, h_out: &Bound<'_, PyAny>, c_out: &Bound<'_, PyAny>,
    g_out: &Bound<'_, PyAny>, keep: bool, threads: usize,
) -> PyResult<Option<TermsCall>> {
    let types = parse_joint_types(&joint_types)?;
    macro_rules! run {
        ($t:ty, $variant:ident) => {{
            let lw: Vec<PyReadonlyArrayDyn<$t>> = l_weights.iter().map(|a| a.extract()).collect::<PyResult<_>>()?;
            let vw: Vec<PyReadonlyArrayDyn<$t>> = v_weights.iter().map(|a| a.extract()).collect::<PyResult<_>>()?;
            let ins: [PyReadonlyArrayDyn<$t>; 3] = [q.extract()?, qd.extract()?, z.extract()?];
            let outs: [PyReadwriteArrayDyn<$t>; 4] = [l_out.extract()?, h_out.extract()?, c_out.extract()?, g_out.extract()?];
            let (k, t) = forward::<$t>(py, &types, dz, softplus_offset, v_scale, &lw, &vw, [&ins[0], &ins[1], &ins[2]], outs, keep, threads)?;
            Ok(keep.then(|| TermsCall { call: Call::$variant(k, t) }))
        }};
    }
    if q.cast::<numpy::PyArrayDyn<f32>>().is_ok() {
        run!(f32, F32)
    } else if q.cast::<numpy::PyArrayDyn<f64>>().is_ok() {
        run!(f64, F64)
    } else {
        Err(bad("terms: q must be a float32 or float64 array".into()))
    }
}

type PyGrads<'py> = Vec<(Bound<'py, PyAny>, Bound<'py, PyAny>)>;

fn to_numpy<'py, T: Element>(py: Python<'py>, g: NetGrads<T>, shapes: &[(usize, usize)]) -> PyResult<PyGrads<'py>> {
    g.into_iter().zip(shapes).map(|((w, b), &(o, i))| {
        let w = PyArray1::from_vec(py, w).reshape([o, i])?;
        let w: Bound<'py, PyArray2<T>> = w;
        Ok((w.into_any(), PyArray1::from_vec(py, b).into_any()))
    }).collect()
}

#[allow(clippy::too_many_arguments)]
fn backward<'py, T: Element + KernelReal>(
    py: Python<'py>, kernel: &Kernel<T>, tape: &Tape<T>, ups: [&Bound<'py, PyAny>; 4], downs: [&Bound<'py, PyAny>; 3], threads: usize,
) -> PyResult<(PyGrads<'py>, PyGrads<'py>)> {
    let ups: [PyReadonlyArrayDyn<T>; 4] = [ups[0].extract()?, ups[1].extract()?, ups[2].extract()?, ups[3].extract()?];
    let mut downs: [PyReadwriteArrayDyn<T>; 3] = [downs[0].extract()?, downs[1].extract()?, downs[2].extract()?];
    let (dl, dh, dc, dg) = (slice("dL", &ups[0])?, slice("dH", &ups[1])?, slice("dc", &ups[2])?, slice("dg", &ups[3])?);
    let [dq, dqd, dz] = &mut downs;
    let (dq, dqd, dz) = (slice_mut("dq", dq)?, slice_mut("dqd", dqd)?, slice_mut("dz", dz)?);
    let pool = pool_for(Some(threads.max(1)))?;
    let (gl, gv) = py.detach(|| kernel.backward(tape, dl, dh, dc, dg, dq, dqd, dz, &pool)).map_err(to_py)?;
    let (sl, sv) = kernel.shapes();
    Ok((to_numpy(py, gl, &sl)?, to_numpy(py, gv, &sv)?))
}

#[pymethods]
impl TermsCall {
    /// Gradients of q, qd, z written into `dq`, `dqd`, `dz` from those of L, H, c, g; returns the weight
    /// gradients [(dW, db), …] of the inertia and the potential network.
    #[pyo3(signature = (dl, dh, dc, dg, dq, dqd, dz, threads))]
    #[allow(clippy::too_many_arguments)]
    fn backward<'py>(
        &self, py: Python<'py>, dl: &Bound<'py, PyAny>, dh: &Bound<'py, PyAny>, dc: &Bound<'py, PyAny>, dg: &Bound<'py, PyAny>,
        dq: &Bound<'py, PyAny>, dqd: &Bound<'py, PyAny>, dz: &Bound<'py, PyAny>, threads: usize,
    ) -> PyResult<(PyGrads<'py>, PyGrads<'py>)> {
        match &self.call {
            Call::F32(k, t) => backward(py, k, t, [dl, dh, dc, dg], [dq, dqd, dz], threads),
            Call::F64(k, t) => backward(py, k, t, [dl, dh, dc, dg], [dq, dqd, dz], threads),
        }
    }

    /// Samples of the forward pass.
    #[getter]
    fn samples(&self) -> usize {
        match &self.call {
            Call::F32(_, t) => t.samples(),
            Call::F64(_, t) => t.samples(),
        }
    }
}

enum Mlp {
    F32(MlpKernel<f32>, Tape<f32>),
    F64(MlpKernel<f64>, Tape<f64>),
}

/// A plain MLP's forward pass, for its reverse pass.
#[pyclass(module = "exolan._native")]
pub(crate) struct MlpCall {
    call: Mlp,
}

fn mlp_run<T: Element + KernelReal>(
    py: Python<'_>, ws: &[PyReadonlyArrayDyn<'_, T>], x: &PyReadonlyArrayDyn<'_, T>, mut y: PyReadwriteArrayDyn<'_, T>,
    keep: bool, threads: usize,
) -> PyResult<(MlpKernel<T>, Tape<T>)> {
    let kernel = MlpKernel::new(&layers("mlp", ws)?).map_err(to_py)?;
    let (x, y) = (slice("x", x)?, slice_mut("y", &mut y)?);
    let pool = pool_for(Some(threads.max(1)))?;
    let mut tape = Tape::new();
    py.detach(|| kernel.forward(x, y, if keep { Some(&mut tape) } else { None }, &pool)).map_err(to_py)?;
    Ok((kernel, tape))
}

/// y (N, d_out) written from x (N, d_in) through the tanh MLP [W₀, b₀, …] (float32 or float64, all alike); with
/// `keep`, returns the call for `backward`.
#[pyfunction]
#[pyo3(signature = (weights, x, y, keep, threads))]
pub(crate) fn mlp_forward(py: Python<'_>, weights: &Bound<'_, PyList>, x: &Bound<'_, PyAny>, y: &Bound<'_, PyAny>,
                          keep: bool, threads: usize) -> PyResult<Option<MlpCall>> {
    macro_rules! run {
        ($t:ty, $variant:ident) => {{
            let ws: Vec<PyReadonlyArrayDyn<$t>> = weights.iter().map(|a| a.extract()).collect::<PyResult<_>>()?;
            let (k, t) = mlp_run::<$t>(py, &ws, &x.extract()?, y.extract()?, keep, threads)?;
            Ok(keep.then(|| MlpCall { call: Mlp::$variant(k, t) }))
        }};
    }
    if x.cast::<numpy::PyArrayDyn<f32>>().is_ok() {
        run!(f32, F32)
    } else if x.cast::<numpy::PyArrayDyn<f64>>().is_ok() {
        run!(f64, F64)
    } else {
        Err(bad("mlp: x must be a float32 or float64 array".into()))
    }
}

fn mlp_back<'py, T: Element + KernelReal>(py: Python<'py>, k: &MlpKernel<T>, t: &Tape<T>, dy: &Bound<'py, PyAny>,
                                          dx: Option<&Bound<'py, PyAny>>, threads: usize) -> PyResult<PyGrads<'py>> {
    let dy: PyReadonlyArrayDyn<T> = dy.extract()?;
    let mut dx: Option<PyReadwriteArrayDyn<T>> = dx.map(|d| d.extract()).transpose()?;
    let dy = slice("dy", &dy)?;
    let dx = match dx.as_mut() {
        Some(d) => Some(slice_mut("dx", d)?),
        None => None,
    };
    let pool = pool_for(Some(threads.max(1)))?;
    let g = py.detach(|| k.backward(t, dy, dx, &pool)).map_err(to_py)?;
    to_numpy(py, g, &k.shapes())
}

#[pymethods]
impl MlpCall {
    /// The weight gradients [(dW, db), …] from dy (N, d_out); dx (N, d_in) written where given.
    #[pyo3(signature = (dy, dx, threads))]
    fn backward<'py>(&self, py: Python<'py>, dy: &Bound<'py, PyAny>, dx: Option<&Bound<'py, PyAny>>, threads: usize)
                     -> PyResult<PyGrads<'py>> {
        match &self.call {
            Mlp::F32(k, t) => mlp_back(py, k, t, dy, dx, threads),
            Mlp::F64(k, t) => mlp_back(py, k, t, dy, dx, threads),
        }
    }
}
