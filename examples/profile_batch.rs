//! A loop of batched rollouts (B = 256, T = 20, per-step z) on a 1-thread pool, for profilers.
//!
//!     cargo build --release --no-default-features --example profile_batch
//!     perf record target/release/examples/profile_batch && perf report
use exolan::synth::{random_weights, SynthConfig};
use exolan::{Inputs, Model, Pool, Workspace, ZSeq};

fn main() {
    let m = Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap();
    let (bsz, t_len) = (256, 20);
    let q0: Vec<f64> = (0..bsz * 2).map(|i| (i as f64 * 0.1).sin()).collect();
    let tau: Vec<f64> = (0..bsz * t_len * 2).map(|i| (i as f64 * 0.07).sin() * 5.0).collect();
    let z: Vec<f64> = (0..bsz * t_len * 16).map(|i| (i as f64 * 0.013).sin()).collect();
    let f_v: Vec<f64> = (0..bsz * t_len).map(|i| 200.0 + (i as f64).sin()).collect();
    let mut wss: Vec<Workspace> = (0..bsz).map(|_| m.workspace()).collect();
    let (mut q, mut qd) = (vec![0.0; bsz * (t_len + 1) * 2], vec![0.0; bsz * (t_len + 1) * 2]);
    let pool = Pool::new(1).unwrap();
    let reps: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(300);
    for _ in 0..reps {
        let inp = Inputs { tau: &tau, z: ZSeq::PerStep(&z), f_v: Some(&f_v), tau_e: None };
        m.rollout_batch(&pool, &mut wss, &q0, &q0, inp, 0.005, &mut q, &mut qd).unwrap();
    }
    println!("{:?}", &q[q.len() - 2..]);
}
