//! Criterion benchmarks of the engine on the paper's ExoLaN size (hip + knee, DeLaN 2x64, LIM 2x16,
//! TCN 5x16 or LSTM 5x16), random weights in the export format:
//! inverse dynamics and forward dynamics (float64 and float32), rollout step, encoder step, batched rollouts
//! (float64 and float32).
//!
//!     cargo bench --no-default-features --bench engine
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use std::hint::black_box;

use exolan::synth::{random_weights, BatchSetup, SynthConfig};
use exolan::{Inputs, Model, ZSeq};

fn model(encoder: &'static str) -> Model {
    Model::from_bytes(&random_weights(&SynthConfig { encoder, ..Default::default() })).unwrap()
}

fn bench_dynamics(c: &mut Criterion) {
    let m = model("tcn");
    let mut ws = m.workspace();
    let z: Vec<f64> = (0..16).map(|i| (i as f64 * 0.3).sin()).collect();
    ws.set_z(&m, &z).unwrap();
    let (q, qd, qdd) = ([0.3, 0.9], [1.2, -2.0], [5.0, -3.0]);
    let mut out = [0.0; 2];
    c.bench_function("inverse_dynamics", |b| {
        b.iter(|| m.inverse_dynamics(&mut ws, black_box(&q), black_box(&qd), black_box(&qdd), black_box(250.0), None, &mut out).unwrap())
    });
    let tau = [10.0, -4.0];
    c.bench_function("forward_dynamics", |b| {
        b.iter(|| m.forward_dynamics(&mut ws, black_box(&q), black_box(&qd), black_box(&tau), black_box(250.0), None, &mut out).unwrap())
    });
    c.bench_function("terms", |b| b.iter(|| m.terms(&mut ws, black_box(&q), black_box(&qd)).unwrap()));
    let mut ws32 = m.workspace_f32();
    ws32.set_z(&m, &z).unwrap();
    c.bench_function("inverse_dynamics_f32", |b| {
        b.iter(|| m.inverse_dynamics_f32(&mut ws32, black_box(&q), black_box(&qd), black_box(&qdd), black_box(250.0), &mut out).unwrap())
    });
    c.bench_function("forward_dynamics_f32", |b| {
        b.iter(|| m.forward_dynamics_f32(&mut ws32, black_box(&q), black_box(&qd), black_box(&tau), black_box(250.0), &mut out).unwrap())
    });
    let z2: Vec<f64> = z.iter().map(|v| v + 1e-3).collect();
    let mut flip = false;
    c.bench_function("set_z (first-layer z contribution)", |b| {
        b.iter(|| {
            flip = !flip;
            ws.set_z(&m, if flip { &z } else { &z2 }).unwrap()
        })
    });
}

fn bench_rollout(c: &mut Criterion) {
    let m = model("tcn");
    let mut ws = m.workspace();
    let t_len = 200;
    let tau: Vec<f64> = (0..t_len * 2).map(|i| ((i as f64) * 0.05).sin() * 5.0).collect();
    let f_v: Vec<f64> = (0..t_len).map(|i| 300.0 + 200.0 * (i as f64 * 0.03).sin()).collect();
    let z_const: Vec<f64> = (0..16).map(|i| (i as f64 * 0.3).sin()).collect();
    let z_step: Vec<f64> = (0..t_len * 16).map(|i| (i as f64 * 0.01).sin()).collect();
    let (mut q, mut qd) = (vec![0.0; (t_len + 1) * 2], vec![0.0; (t_len + 1) * 2]);
    let mut g = c.benchmark_group("rollout_step");
    g.throughput(Throughput::Elements(t_len as u64));
    for (name, zs) in [("const z", ZSeq::Const(&z_const)), ("per-step z", ZSeq::PerStep(&z_step))] {
        g.bench_function(BenchmarkId::new("200 steps", name), |b| {
            b.iter(|| {
                m.rollout(&mut ws, &[0.2, 0.5], &[0.0, 0.0], Inputs { tau: &tau, z: zs, f_v: Some(&f_v), tau_e: None }, 0.005, &mut q, &mut qd)
                    .unwrap()
            })
        });
    }
    let mut ws32 = m.workspace_f32();
    g.bench_function(BenchmarkId::new("200 steps, f32", "const z"), |b| {
        b.iter(|| {
            let inp = Inputs { tau: &tau, z: ZSeq::Const(&z_const), f_v: Some(&f_v), tau_e: None };
            m.rollout_f32(&mut ws32, &[0.2, 0.5], &[0.0, 0.0], inp, 0.005, &mut q, &mut qd).unwrap()
        })
    });
    g.finish();
}

fn bench_encoder(c: &mut Criterion) {
    let mut g = c.benchmark_group("encoder_step");
    for enc in ["tcn", "lstm"] {
        let m = model(enc);
        let mut st = m.encoder_state();
        let mut z = vec![0.0; 16];
        let x = [0.2, 0.8, 1.0, -2.0, 400.0, 0.1, 0.01];
        g.bench_function(enc, |b| b.iter(|| m.encode_step(&mut st, black_box(&x), &mut z).unwrap()));
    }
    g.finish();
}

fn bench_batched(c: &mut Criterion) {
    let m = model("tcn");
    let (bsz, t_len) = (256, 20);
    let mut setup = BatchSetup::new(&m, bsz, t_len);
    let mut g = c.benchmark_group("batched_rollout");
    g.throughput(Throughput::Elements((bsz * t_len) as u64));
    for threads in [1, 2] {
        let pool = exolan::Pool::new(threads).unwrap();
        g.bench_function(BenchmarkId::new("B256 x T20 per-step z", format!("{threads} threads")), |b| {
            b.iter(|| setup.run(&m, &pool).unwrap())
        });
        g.bench_function(BenchmarkId::new("B256 x T20 per-step z, f32", format!("{threads} threads")), |b| {
            b.iter(|| setup.run_f32(&m, &pool).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, bench_dynamics, bench_rollout, bench_encoder, bench_batched);
criterion_main!(benches);
