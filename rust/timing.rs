//! Per-call cost of the hot paths, timed inside Rust (benchmark support for `benches/bench_engine.py`
//! through `Engine.time_hot`, and for `examples/timing.rs`): the minimum over batches of repeated
//! calls, the least disturbed figure on a machine shared with other jobs.

use std::hint::black_box;
use std::time::Instant;

use crate::error::{Error, Result};
use crate::model::Model;
use crate::rollout::{Inputs, ZSeq};

/// Seconds per call of `op`: "inverse", "forward", "rollout_step" (a 200-step rollout / 200,
/// constant z), their float32 versions "inverse_f32", "forward_f32", "rollout_step_f32" (models
/// without extension terms), or "encode_step"; the minimum over `batches` batches of `per_batch` calls.
pub fn time_hot(m: &Model, op: &str, per_batch: usize, batches: usize) -> Result<f64> {
    let n = m.n;
    let per_batch = per_batch.max(1);
    let mut ws = m.workspace();
    let z: Vec<f64> = (0..m.dz).map(|i| (i as f64 * 0.37).sin() * 0.5).collect();
    ws.set_z(m, &z)?;
    let mut ws32 = m.workspace_f32();
    ws32.set_z(m, &z)?;
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
    let mut best = f64::INFINITY;
    for _ in 0..batches.max(1) {
        let t = Instant::now();
        let mut calls = per_batch;
        match op {
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
            "inverse_f32" => {
                for _ in 0..per_batch {
                    m.inverse_dynamics_f32(&mut ws32, black_box(&q), black_box(&qd), black_box(&qd), 100.0, &mut out)?;
                }
            }
            "forward_f32" => {
                for _ in 0..per_batch {
                    m.forward_dynamics_f32(&mut ws32, black_box(&q), black_box(&qd), black_box(&qd), 100.0, &mut out)?;
                }
            }
            "rollout_step_f32" => {
                let zs = if m.dz > 0 { ZSeq::Const(&z) } else { ZSeq::Keep };
                m.rollout_f32(&mut ws32, &q, &qd, Inputs { tau: &tau, z: zs, f_v: Some(&f_v), tau_e: None }, 0.005, &mut qo, &mut qdo)?;
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
}
