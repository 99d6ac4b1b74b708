//! Per-call cost of the hot paths as the minimum over batches of repeated calls (the best estimate of
//! the engine's own cost on a machine shared with other jobs, where means include preemption), plus
//! the median for comparison.
//!
//!     cargo run --release --no-default-features --example timing [-- --all-levels]
//!
//! `--all-levels` times every code path this CPU runs (portable, AVX2, AVX-512) in the same run.
use std::hint::black_box;
use std::time::Instant;

use exolan::synth::{random_weights, SynthConfig};
use exolan::{Inputs, Model, ZSeq};

fn time<F: FnMut()>(name: &str, per_batch: usize, mut f: F) {
    let mut v = Vec::with_capacity(200);
    for _ in 0..200 {
        let t = Instant::now();
        for _ in 0..per_batch {
            f();
        }
        v.push(t.elapsed().as_secs_f64() * 1e6 / per_batch as f64);
    }
    v.sort_by(f64::total_cmp);
    println!("{name:<34} min {:>8.3} µs   median {:>8.3} µs", v[0], v[v.len() / 2]);
}

fn main() {
    let all = std::env::args().any(|a| a == "--all-levels");
    let best = Model::from_bytes(&random_weights(&SynthConfig::default())).unwrap().simd();
    let levels: Vec<exolan::Simd> = if all {
        [exolan::Simd::Portable, exolan::Simd::Avx2Fma, exolan::Simd::Avx512].into_iter().filter(|l| *l <= best).collect()
    } else {
        vec![best]
    };
    for (level, enc) in levels.iter().flat_map(|l| ["tcn", "lstm"].map(|e| (*l, e))) {
        let mut m = Model::from_bytes(&random_weights(&SynthConfig { encoder: enc, ..Default::default() })).unwrap();
        m.set_simd(Some(level));
        println!("-- model: DeLaN 2x64 + LIM 2x16 + {enc} encoder (simd: {:?})", m.simd());
        let mut ws = m.workspace();
        let mut st = m.encoder_state();
        let mut z = vec![0.0; 16];
        let x = [0.2, 0.8, 1.0, -2.0, 400.0, 0.1, 0.01];
        time("encoder step", 200, || m.encode_step(&mut st, black_box(&x), &mut z).unwrap());
        if enc == "lstm" {
            continue;
        }
        ws.set_z(&m, &z).unwrap();
        let z2: Vec<f64> = z.iter().map(|v| v + 1e-3).collect();
        let mut flip = false;
        time("set_z", 200, || {
            flip = !flip;
            ws.set_z(&m, if flip { &z } else { &z2 }).unwrap()
        });
        let (q, qd, qdd) = ([0.3, 0.9], [1.2, -2.0], [5.0, -3.0]);
        let mut out = [0.0; 2];
        time("inverse dynamics", 100, || {
            m.inverse_dynamics(&mut ws, black_box(&q), black_box(&qd), black_box(&qdd), 250.0, None, &mut out).unwrap()
        });
        time("forward dynamics", 100, || {
            m.forward_dynamics(&mut ws, black_box(&q), black_box(&qd), black_box(&qdd), 250.0, None, &mut out).unwrap()
        });
        let mut ws32 = m.workspace_f32();
        ws32.set_z(&m, &z).unwrap();
        time("inverse dynamics, f32", 100, || {
            m.inverse_dynamics_f32(&mut ws32, black_box(&q), black_box(&qd), black_box(&qdd), 250.0, &mut out).unwrap()
        });
        time("forward dynamics, f32", 100, || {
            m.forward_dynamics_f32(&mut ws32, black_box(&q), black_box(&qd), black_box(&qdd), 250.0, &mut out).unwrap()
        });
        let t_len = 200;
        let tau: Vec<f64> = (0..t_len * 2).map(|i| ((i as f64) * 0.05).sin() * 5.0).collect();
        let f_v = vec![300.0; t_len];
        let (mut qo, mut qdo) = (vec![0.0; (t_len + 1) * 2], vec![0.0; (t_len + 1) * 2]);
        let zc = z.clone();
        time("rollout, 200 steps (÷200 = per step)", 1, || {
            m.rollout(&mut ws, &[0.2, 0.5], &[0.0, 0.0], Inputs { tau: &tau, z: ZSeq::Const(&zc), f_v: Some(&f_v), tau_e: None }, 0.005, &mut qo, &mut qdo)
                .unwrap();
        });
        time("rollout, 200 steps, f32 (÷200)", 1, || {
            let inp = Inputs { tau: &tau, z: ZSeq::Const(&zc), f_v: Some(&f_v), tau_e: None };
            m.rollout_f32(&mut ws32, &[0.2, 0.5], &[0.0, 0.0], inp, 0.005, &mut qo, &mut qdo).unwrap();
        });
        let zs: Vec<f64> = (0..t_len * 16).map(|i| (i as f64 * 0.01).sin()).collect();
        time("rollout, 200 steps, per-step z (÷200)", 1, || {
            m.rollout(&mut ws, &[0.2, 0.5], &[0.0, 0.0], Inputs { tau: &tau, z: ZSeq::PerStep(&zs), f_v: Some(&f_v), tau_e: None }, 0.005, &mut qo, &mut qdo)
                .unwrap();
        });
        // batched: B = 256 rollouts of T = 20 steps, per-step z, on a 1-thread pool
        let (bsz, th) = (256, 20);
        let q0 = vec![0.1; bsz * 2];
        let taub = vec![1.0; bsz * th * 2];
        let zb: Vec<f64> = (0..bsz * th * 16).map(|i| (i as f64 * 0.01).sin()).collect();
        let fvb = vec![100.0; bsz * th];
        let mut wss: Vec<exolan::Workspace> = (0..bsz).map(|_| m.workspace()).collect();
        let (mut qb, mut qdb) = (vec![0.0; bsz * (th + 1) * 2], vec![0.0; bsz * (th + 1) * 2]);
        let mut lws = m.lane_workspaces(bsz);
        for threads in [1, 2] {
            let pool = exolan::Pool::new(threads).unwrap();
            let inp = Inputs { tau: &taub, z: ZSeq::PerStep(&zb), f_v: Some(&fvb), tau_e: None };
            time(&format!("batched 256x20, {threads} thr (÷5120)"), 1, || {
                m.rollout_batch(&pool, &mut wss, &q0, &q0, inp, 0.005, &mut qb, &mut qdb).unwrap()
            });
            time(&format!("batched 256x20 f32, {threads} thr (÷5120)"), 1, || {
                m.rollout_batch_f32(&pool, &mut lws, &q0, &q0, inp, 0.005, &mut qb, &mut qdb).unwrap()
            });
        }
    }
}
