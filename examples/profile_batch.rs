//! A loop of batched rollouts (B = 256, T = 20, per-step z) on a 1-thread pool, for profilers.
//!
//!     cargo build --release --no-default-features --example profile_batch
//!     perf record target/release/examples/profile_batch && perf report
use exolan::synth::{random_weights, BatchSetup, SynthConfig};
use exolan::{Model, Pool};

fn main() {
    let m = Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap();
    let mut setup = BatchSetup::new(&m, 256, 20);
    let pool = Pool::new(1).unwrap();
    let reps: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(300);
    for _ in 0..reps {
        setup.run(&m, &pool).unwrap();
    }
    println!("{:?}", &setup.q[setup.q.len() - 2..]);
}
