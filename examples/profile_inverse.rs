//! A loop of inverse-dynamics calls for profilers (`perf record`): nothing else runs.
//!
//!     cargo build --release --no-default-features --example profile_inverse
//!     perf record target/release/examples/profile_inverse && perf report
use std::hint::black_box;

use exolan::synth::{random_weights, SynthConfig};
use exolan::Model;

fn main() {
    let m = Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap();
    let mut ws = m.workspace();
    ws.set_z(&m, &[0.1; 16]).unwrap();
    let mut out = [0.0; 2];
    let calls: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(300_000);
    for i in 0..calls {
        let q = [0.3 + (i % 7) as f64 * 0.01, 0.9];
        m.inverse_dynamics(&mut ws, black_box(&q), &[1.2, -2.0], &[5.0, -3.0], 250.0, None, &mut out).unwrap();
    }
    println!("{out:?}");
}
