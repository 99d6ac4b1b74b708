//! A loop of batched rollouts (B = 256, T = 20, per-step z) on a 1-thread pool, for profilers; with
//! `f32` as the second argument the float32 lane path (`rollout_batch_f32`).
//!
//!     cargo build --release --no-default-features --example profile_batch
//!     perf record target/release/examples/profile_batch [REPS] [f32] && perf report
use exolan::synth::{random_weights, BatchSetup, SynthConfig};
use exolan::{Model, Pool};

fn main() {
    let m = Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap();
    let mut setup = BatchSetup::new(&m, 256, 20);
    let pool = Pool::new(1).unwrap();
    let reps: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(300);
    let f32 = std::env::args().nth(2).is_some_and(|a| a == "f32");
    let mut best = f64::INFINITY;
    for _ in 0..reps {
        let t = std::time::Instant::now();
        if f32 {
            setup.run_f32(&m, &pool).unwrap();
        } else {
            setup.run(&m, &pool).unwrap();
        }
        best = best.min(t.elapsed().as_secs_f64());
    }
    println!("{:?}  ({:.3} µs per element-step, minimum over batches)", &setup.q[setup.q.len() - 2..], best / (256.0 * 20.0) * 1e6);
}
