//! The binding of the TCN encoder's training kernel (`tcn`): `tcn_forward` and `TcnCall.backward`, float32 or
//! float64 throughout, every array C-contiguous and written in place (python/exolan/native_tcn.py owns the
//! tensors). The GIL is released while the kernel runs.

use numpy::{Element, PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyReadwriteArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyList;

use crate::python_conv::{bad, pool_for, to_py};
use crate::tcn::{ConvRef, Tcn, TcnReal, TcnTape};

enum Call {
    F32(Tcn<f32>, TcnTape<f32>),
    F64(Tcn<f64>, TcnTape<f64>),
}

/// A forward pass's prepared weights and tape, for its reverse pass.
#[pyclass(module = "exolan._native")]
pub(crate) struct TcnCall {
    call: Call,
}

fn slice<'a, T: Element>(name: &str, a: &'a PyReadonlyArrayDyn<'_, T>) -> PyResult<&'a [T]> {
    a.as_slice().map_err(|_| bad(format!("tcn: {name} must be C-contiguous")))
}

fn slice_mut<'a, T: Element>(name: &str, a: &'a mut PyReadwriteArrayDyn<'_, T>) -> PyResult<&'a mut [T]> {
    a.as_slice_mut().map_err(|_| bad(format!("tcn: {name} must be C-contiguous and writable")))
}

/// [W₀, b₀, W₁, b₁, …] (W out × in × taps, b out) as slices.
fn convs<'a, T: Element>(arrays: &'a [PyReadonlyArrayDyn<'_, T>]) -> PyResult<Vec<ConvRef<'a, T>>> {
    if !arrays.len().is_multiple_of(2) {
        return Err(bad("tcn: the convs' arrays must come as weight, bias pairs".into()));
    }
    arrays.chunks(2).enumerate().map(|(i, p)| {
        let shape = p[0].shape();
        if shape.len() != 3 || p[1].shape() != [shape[0]] {
            return Err(bad(format!("tcn: conv {i} has weight {shape:?} and bias {:?}", p[1].shape())));
        }
        Ok((slice("a weight", &p[0])?, slice("a bias", &p[1])?))
    }).collect()
}

#[allow(clippy::too_many_arguments)]
fn forward<T: Element + TcnReal>(
    py: Python<'_>, shape: [usize; 4], weights: &[PyReadonlyArrayDyn<'_, T>], x: &PyReadonlyArrayDyn<'_, T>,
    keep: &PyReadonlyArrayDyn<'_, T>, mut z: PyReadwriteArrayDyn<'_, T>, want_tape: bool, threads: usize,
) -> PyResult<(Tcn<T>, TcnTape<T>)> {
    let [c_in, hidden, levels, kernel] = shape;
    let tcn = Tcn::new(c_in, hidden, levels, kernel, &convs(weights)?).map_err(to_py)?;
    let (batch, t_len) = match *x.shape() {
        [b, t, c] if c == c_in => (b, t),
        ref s => return Err(bad(format!("tcn: x has shape {s:?}, expected (B, T, {c_in})"))),
    };
    if keep.shape() != [batch, t_len] || z.shape() != [batch, t_len, hidden] {
        return Err(bad(format!("tcn: keep {:?} and z {:?} for x {:?}", keep.shape(), z.shape(), x.shape())));
    }
    let (xs, ks, zs) = (slice("x", x)?, slice("keep", keep)?, slice_mut("z", &mut z)?);
    let pool = pool_for(Some(threads.max(1)))?;
    let mut tape = TcnTape::new();
    py.detach(|| tcn.forward(xs, ks, batch, t_len, zs, want_tape.then_some(&mut tape), &pool)).map_err(to_py)?;
    Ok((tcn, tape))
}

/// z (B, T, hidden) written into `z` from x (B, T, c_in), keep (B, T) and the convs' [W, b, …] in module order
/// (float32 or float64, all alike). With `tape`, returns the call for `backward`.
#[pyfunction]
#[pyo3(signature = (c_in, hidden, levels, kernel, weights, x, keep, z, tape, threads))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn tcn_forward(
    py: Python<'_>, c_in: usize, hidden: usize, levels: usize, kernel: usize, weights: &Bound<'_, PyList>,
    x: &Bound<'_, PyAny>, keep: &Bound<'_, PyAny>, z: &Bound<'_, PyAny>, tape: bool, threads: usize,
) -> PyResult<Option<TcnCall>> {
    let shape = [c_in, hidden, levels, kernel];
    macro_rules! run {
        ($t:ty, $variant:ident) => {{
            let ws: Vec<PyReadonlyArrayDyn<$t>> = weights.iter().map(|a| a.extract()).collect::<PyResult<_>>()?;
            let (k, t) = forward::<$t>(py, shape, &ws, &x.extract()?, &keep.extract()?, z.extract()?, tape, threads)?;
            Ok(tape.then(|| TcnCall { call: Call::$variant(k, t) }))
        }};
    }
    if x.cast::<numpy::PyArrayDyn<f32>>().is_ok() {
        run!(f32, F32)
    } else if x.cast::<numpy::PyArrayDyn<f64>>().is_ok() {
        run!(f64, F64)
    } else {
        Err(bad("tcn: x must be a float32 or float64 array".into()))
    }
}

type PyGrads<'py> = Vec<(Bound<'py, PyAny>, Bound<'py, PyAny>)>;

fn backward<'py, T: Element + TcnReal>(
    py: Python<'py>, tcn: &Tcn<T>, tape: &TcnTape<T>, gz: &Bound<'py, PyAny>, dx: Option<&Bound<'py, PyAny>>, threads: usize,
) -> PyResult<PyGrads<'py>> {
    let gz: PyReadonlyArrayDyn<T> = gz.extract()?;
    let mut dx: Option<PyReadwriteArrayDyn<T>> = dx.map(|d| d.extract()).transpose()?;
    let gzs = slice("dz", &gz)?;
    let dxs = match dx.as_mut() {
        Some(d) => Some(slice_mut("dx", d)?),
        None => None,
    };
    let pool = pool_for(Some(threads.max(1)))?;
    let grads = py.detach(|| tcn.backward(tape, gzs, dxs, &pool)).map_err(to_py)?;
    grads.into_iter().zip(tcn.shapes()).map(|((w, b), (o, i, k))| {
        Ok((PyArray1::from_vec(py, w).reshape([o, i, k])?.into_any(), PyArray1::from_vec(py, b).into_any()))
    }).collect()
}

#[pymethods]
impl TcnCall {
    /// The gradient of x written into `dx` where given, from that of z (`dz`); returns the convs' weight
    /// gradients [(dW, db), …] in the order the forward pass took them.
    #[pyo3(signature = (dz, dx, threads))]
    fn backward<'py>(
        &self, py: Python<'py>, dz: &Bound<'py, PyAny>, dx: Option<&Bound<'py, PyAny>>, threads: usize,
    ) -> PyResult<PyGrads<'py>> {
        match &self.call {
            Call::F32(k, t) => backward(py, k, t, dz, dx, threads),
            Call::F64(k, t) => backward(py, k, t, dz, dx, threads),
        }
    }

    /// Sequences of the forward pass.
    #[getter]
    fn batch(&self) -> usize {
        match &self.call {
            Call::F32(_, t) => t.batch(),
            Call::F64(_, t) => t.batch(),
        }
    }
}
