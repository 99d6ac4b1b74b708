//! A loop of inverse-dynamics calls for profilers (`perf record`): nothing else runs. `f32` as the
//! second argument: the float32 single-sample path (`inverse_dynamics_f32`).
//!
//!     cargo build --release --no-default-features --example profile_inverse
//!     perf record target/release/examples/profile_inverse [CALLS] [f32] && perf report
use std::hint::black_box;

use exolan::synth::{random_weights, SynthConfig};
use exolan::Model;

fn main() {
    let m = Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap();
    let mut ws = m.workspace();
    ws.set_z(&m, &[0.1; 16]).unwrap();
    let mut ws32 = m.workspace_f32();
    ws32.set_z(&m, &[0.1; 16]).unwrap();
    let mut out = [0.0; 2];
    let calls: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(300_000);
    let f32 = std::env::args().nth(2).is_some_and(|a| a == "f32");
    for i in 0..calls {
        let q = [0.3 + (i % 7) as f64 * 0.01, 0.9];
        if f32 {
            m.inverse_dynamics_f32(&mut ws32, black_box(&q), &[1.2, -2.0], &[5.0, -3.0], 250.0, &mut out).unwrap();
        } else {
            m.inverse_dynamics(&mut ws, black_box(&q), &[1.2, -2.0], &[5.0, -3.0], 250.0, None, &mut out).unwrap();
        }
    }
    println!("{out:?}");
}
