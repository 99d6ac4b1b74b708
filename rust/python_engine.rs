//! The binding's `Engine`: the loaded model with the workspaces its calls reuse, and the dispatch every method
//! shares (a per-sample call on this thread or over the pool, one sample with the GIL held). The methods
//! Python sees are in `python.rs`.

use std::sync::{Mutex, MutexGuard};

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;

use crate::python_conv::{bad, lock, one, one_scalar, pool_for, rows, to_py};
use crate::real::Real;
use crate::{LaneWorkspace, Model, Workspace};

pub(crate) type ArrayPair<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

/// Samples up to which a per-sample call runs on the calling thread in the engine's own workspace.
const CHUNK: usize = 64;

/// A loaded model. Methods take batched arrays (leading dimension N or B).
#[pyclass(module = "exolan._native", frozen)]
pub(crate) struct Engine {
    pub(crate) model: Model,
    /// Workspace for single-sample and small calls (no allocation per call).
    pub(crate) ws: Mutex<Workspace>,
    /// Workspace of the float32 single-sample calls and single rollouts (`precision="f32"`).
    pub(crate) ws32: Mutex<Workspace<f32>>,
    /// Workspaces of batch calls, kept between calls (a concurrent second call makes its own).
    pub(crate) batch: Mutex<Vec<Workspace>>,
    /// The float32 rollouts' lane workspaces, kept likewise.
    pub(crate) lanes: Mutex<Vec<LaneWorkspace>>,
}

impl Engine {
    pub(crate) fn with_model(model: Model) -> Engine {
        let (ws, ws32) = (Mutex::new(model.workspace()), Mutex::new(model.workspace_f32()));
        Engine { model, ws, ws32, batch: Mutex::new(vec![]), lanes: Mutex::new(vec![]) }
    }

    pub(crate) fn ws(&self) -> MutexGuard<'_, Workspace> {
        lock(&self.ws)
    }

    /// `f` on `count` workspaces: the kept ones (grown as needed) or, while another call holds
    /// them, fresh ones. Reuse cannot change a result: a workspace's z cache is exact.
    pub(crate) fn with_workspaces<T>(&self, count: usize, f: impl FnOnce(&mut [Workspace]) -> T) -> T {
        match self.batch.try_lock() {
            Ok(mut kept) => {
                while kept.len() < count {
                    kept.push(self.model.workspace());
                }
                f(&mut kept[..count])
            }
            Err(_) => f(&mut (0..count).map(|_| self.model.workspace()).collect::<Vec<_>>()),
        }
    }

    /// `f` on the lane workspaces of a float32 batch of `bsz` rollouts, kept or (while another call
    /// holds them) fresh, as `with_workspaces`.
    pub(crate) fn with_lanes<T>(&self, bsz: usize, f: impl FnOnce(&mut [LaneWorkspace]) -> T) -> T {
        match self.lanes.try_lock() {
            Ok(mut kept) => {
                let want = self.model.lane_workspaces(bsz).len();
                if kept.len() < want {
                    *kept = self.model.lane_workspaces(bsz);
                }
                f(&mut kept)
            }
            Err(_) => f(&mut self.model.lane_workspaces(bsz)),
        }
    }

    /// Run a per-sample core call over N samples with the GIL released: small N in the shared
    /// workspace on this thread, large N in chunks of CHUNK samples spread over all cores.
    pub(crate) fn per_sample<F>(&self, py: Python<'_>, ns: usize, width: usize, f: F) -> PyResult<Vec<f64>>
    where
        F: Fn(&crate::Pool, &mut [Workspace], &mut [f64]) -> crate::Result<()> + Send + Sync,
    {
        let mut out = vec![0.0; ns * width];
        let pool = pool_for(if ns <= CHUNK { Some(1) } else { None })?;
        py.detach(|| {
            if ns <= CHUNK {
                f(&pool, std::slice::from_mut(&mut *self.ws()), &mut out)
            } else {
                self.with_workspaces(ns.div_ceil(CHUNK), |wss| f(&pool, wss, &mut out))
            }
        })
        .map_err(to_py)?;
        Ok(out)
    }

    /// The z (N, dz) and f_v (N,) of a per-sample call, with the errors for missing ones.
    pub(crate) fn z_fv<'a>(
        &self,
        ns: usize,
        z: &'a Option<PyReadonlyArrayDyn<'_, f64>>,
        f_v: &'a Option<PyReadonlyArrayDyn<'_, f64>>,
    ) -> PyResult<[Option<&'a [f64]>; 2]> {
        let m = &self.model;
        let z = rows("z", z, &[ns, m.dz])?;
        if z.is_none() && m.dz > 0 {
            return Err(bad(format!("this model ({}) needs a context z of dimension {}", m.meta.method, m.dz)));
        }
        let f_v = rows("f_v", f_v, &[ns])?;
        if f_v.is_none() && m.meta.lim {
            return Err(bad("a model with LIM needs the insole force f_v".into()));
        }
        Ok([z, f_v])
    }

    /// One sample through `f` in the shared workspace `ws` (float64 or float32), GIL held; output shaped like `q`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn single<'py, T: Real>(
        &self,
        py: Python<'py>,
        args: [&Bound<'py, PyAny>; 3],
        z: Option<&Bound<'py, PyAny>>,
        f_v: Option<&Bound<'py, PyAny>>,
        ws: &Mutex<Workspace<T>>,
        f: impl Fn(&Model, &mut Workspace<T>, [&[f64]; 3], f64, &mut [f64]) -> crate::Result<()>,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let m = &self.model;
        let n = m.n;
        let (a, b, c) = (one(args[0], n)?, one(args[1], n)?, one(args[2], n)?);
        let shape = a.shape().to_vec();
        if b.shape() != shape.as_slice() || c.shape() != shape.as_slice() {
            return Err(PyTypeError::new_err("shapes differ"));
        }
        let zr = match z {
            Some(z) if !z.is_none() => Some(one(z, m.dz)?),
            _ if m.dz > 0 => return Err(PyTypeError::new_err("z missing")),
            _ => None,
        };
        let fv = match f_v {
            Some(f) if !f.is_none() => one_scalar(f)?,
            _ if m.meta.lim => return Err(PyTypeError::new_err("f_v missing")),
            _ => 0.0,
        };
        let mut out = [0.0f64; 64];
        {
            let mut ws = lock(ws);
            if let Some(zr) = &zr {
                ws.set_z(m, zr.as_slice()?).map_err(to_py)?;
            }
            f(m, &mut ws, [a.as_slice()?, b.as_slice()?, c.as_slice()?], fv, &mut out[..n]).map_err(to_py)?;
        }
        let res = unsafe { PyArrayDyn::<f64>::new(py, shape, false) };
        // SAFETY: a fresh array of n values that nothing else references yet.
        unsafe { res.as_slice_mut() }.map_err(|_| bad("output not contiguous".into()))?.copy_from_slice(&out[..n]);
        Ok(res)
    }
}
