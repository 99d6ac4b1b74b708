//! The Python binding: `exolan._native`. Thin by design: argument checking and conversion only;
//! the work happens in the pure-Rust core.

use numpy::{PyReadonlyArray1, PyReadwriteArray1};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

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

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", crate::VERSION)?;
    m.add_function(wrap_pyfunction!(sum, m)?)?;
    m.add_function(wrap_pyfunction!(scale_in_place, m)?)?;
    Ok(())
}
