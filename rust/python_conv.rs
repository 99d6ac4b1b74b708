//! Argument conversion for the binding (`python.rs`): numpy arrays to slices with their shapes
//! checked, engine errors to Python exceptions; and the two functions the build tests call.

use numpy::{PyArrayDyn, PyArrayMethods, PyReadonlyArray1, PyReadonlyArrayDyn, PyReadwriteArray1, PyUntypedArrayMethods};
use pyo3::exceptions::{PyArithmeticError, PyOSError, PyTypeError, PyValueError};
use pyo3::prelude::*;

use std::sync::{Mutex, MutexGuard};

use crate::{pool, Error};

/// Sum of a contiguous float64 array (read without copying).
#[pyfunction]
pub(crate) fn sum(xs: PyReadonlyArray1<'_, f64>) -> PyResult<f64> {
    let s = xs
        .as_slice()
        .map_err(|_| PyValueError::new_err("sum: array must be contiguous float64"))?;
    Ok(s.iter().sum())
}

/// Multiply a contiguous float64 array by `k` in place; returns the address of the data it
/// worked on so a test can check that it is numpy's own buffer (zero copy).
#[pyfunction]
pub(crate) fn scale_in_place(mut xs: PyReadwriteArray1<'_, f64>, k: f64) -> PyResult<usize> {
    let s = xs
        .as_slice_mut()
        .map_err(|_| PyValueError::new_err("scale_in_place: array must be contiguous float64"))?;
    let addr = s.as_ptr() as usize;
    s.iter_mut().for_each(|x| *x *= k);
    Ok(addr)
}

pub(crate) fn to_py(e: Error) -> PyErr {
    let msg = e.to_string();
    match e {
        Error::Io(_) => PyOSError::new_err(msg),
        Error::IllConditioned { .. } | Error::Diverged { .. } => PyArithmeticError::new_err(msg),
        _ => PyValueError::new_err(msg),
    }
}

pub(crate) fn bad(msg: String) -> PyErr {
    PyValueError::new_err(msg)
}

/// Shape and data of a contiguous array.
pub(crate) fn view<'a>(name: &str, a: &'a PyReadonlyArrayDyn<'_, f64>) -> PyResult<(Vec<usize>, &'a [f64])> {
    let s = a.as_slice().map_err(|_| bad(format!("{name} must be a C-contiguous float64 array")))?;
    Ok((a.shape().to_vec(), s))
}

pub(crate) fn expect_shape(name: &str, shape: &[usize], want: &[usize]) -> PyResult<()> {
    if shape != want {
        return Err(bad(format!("bad input shape: {name} has shape {shape:?}, expected {want:?}")));
    }
    Ok(())
}

/// The engine's pool for `threads` (None or 0: one thread per core).
pub(crate) fn pool_for(threads: Option<usize>) -> PyResult<std::sync::Arc<crate::Pool>> {
    pool::shared(threads.unwrap_or(0)).map_err(to_py)
}

pub(crate) fn samples(name: &str, shape: &[usize], n: usize) -> PyResult<usize> {
    match shape {
        [s, k] if *k == n => Ok(*s),
        _ => Err(bad(format!("bad input shape: {name} has shape {shape:?}, expected (N, {n})"))),
    }
}

/// An optional (N, width) array as a slice, or the error a missing required one gives.
pub(crate) fn rows<'a>(name: &str, a: &'a Option<PyReadonlyArrayDyn<'_, f64>>, want: &[usize]) -> PyResult<Option<&'a [f64]>> {
    match a {
        Some(a) => {
            let (s, d) = view(name, a)?;
            expect_shape(name, &s, want)?;
            Ok(Some(d))
        }
        None => Ok(None),
    }
}

/// A single sample's float64 vector of `len` values: shape (len,) or (1, len), C-contiguous.
/// Anything else is a `TypeError` (the wrapper then takes the general path).
pub(crate) fn one<'a>(a: &'a Bound<'_, PyAny>, len: usize) -> PyResult<PyReadonlyArrayDyn<'a, f64>> {
    let arr = a.cast::<PyArrayDyn<f64>>().map_err(|_| PyTypeError::new_err("not a float64 ndarray"))?;
    let ok = match arr.shape() {
        [k] | [1, k] => *k == len && arr.is_c_contiguous(),
        _ => false,
    };
    if !ok {
        return Err(PyTypeError::new_err("not one sample"));
    }
    arr.try_readonly().map_err(|_| PyTypeError::new_err("array is borrowed mutably"))
}

/// A scalar f_v: a Python or numpy number, or a one-element float64 array.
pub(crate) fn one_scalar(a: &Bound<'_, PyAny>) -> PyResult<f64> {
    if let Ok(v) = a.extract::<f64>() {
        return Ok(v);
    }
    let r = one(a, 1)?;
    Ok(r.as_slice().map_err(|_| PyTypeError::new_err("not contiguous"))?[0])
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// `precision`: "f64" (false) or "f32" (true); anything else is a `ValueError`.
pub(crate) fn is_f32(precision: &str) -> PyResult<bool> {
    match precision {
        "f64" => Ok(false),
        "f32" => Ok(true),
        other => Err(bad(format!("precision must be \"f64\" or \"f32\", got {other:?}"))),
    }
}
