//! The float32 single-sample calls (`inverse_dynamics_f32`, `forward_dynamics_f32`, `rollout_f32`)
//! against the float64 ones: agreement to float32 rounding on every synthetic model shape and code
//! path, determinism, consistency of a rollout with its steps, refusals.

use exolan::synth::{pseudo, random_weights, shapes, SynthConfig};
use exolan::{Error, Inputs, Model, Simd, ZSeq};

fn model(cfg: &SynthConfig) -> Model {
    Model::from_bytes(&random_weights(cfg)).expect("synthetic model loads")
}

/// max |a − b| over max |b| (normwise relative).
fn rel(a: &[f64], b: &[f64]) -> f64 {
    let scale = b.iter().fold(0.0f64, |s, v| s.max(v.abs()));
    a.iter().zip(b).fold(0.0f64, |s, (u, v)| s.max((u - v).abs())) / scale
}

fn configs() -> Vec<SynthConfig> {
    let d = SynthConfig::default();
    let mut v = shapes();
    // widths that are not multiples of 16: the f32 register blocks' remainders
    v.push(SynthConfig { hidden: 40, lim_hidden: 12, seed: 7, ..d.clone() });
    v.push(SynthConfig { joint_types: vec!["revolute", "revolute", "revolute", "revolute"], hidden: 24, seed: 8, ..d });
    v
}

/// Worst normwise relative differences f32 vs f64 (inverse τ, forward q̈) over `count` samples.
fn single_errors(m: &Model, count: usize) -> (f64, f64) {
    let n = m.n;
    let (mut w64, mut w32) = (m.workspace(), m.workspace_f32());
    let (mut e_inv, mut e_fwd) = (0.0f64, 0.0f64);
    for s in 0..count as u64 {
        let z = pseudo(100 + s, m.dz, 1.0);
        let (q, qd, qdd, tau) = (pseudo(200 + s, n, 1.5), pseudo(300 + s, n, 2.0), pseudo(400 + s, n, 5.0), pseudo(500 + s, n, 5.0));
        let f_v = 150.0 + 100.0 * s as f64 / count as f64;
        w64.set_z(m, &z).unwrap();
        w32.set_z(m, &z).unwrap();
        let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
        m.inverse_dynamics(&mut w64, &q, &qd, &qdd, f_v, None, &mut a).unwrap();
        m.inverse_dynamics_f32(&mut w32, &q, &qd, &qdd, f_v, &mut b).unwrap();
        e_inv = e_inv.max(rel(&b, &a));
        m.forward_dynamics(&mut w64, &q, &qd, &tau, f_v, None, &mut a).unwrap();
        m.forward_dynamics_f32(&mut w32, &q, &qd, &tau, f_v, &mut b).unwrap();
        e_fwd = e_fwd.max(rel(&b, &a));
    }
    (e_inv, e_fwd)
}

#[test]
fn f32_single_calls_agree_with_f64() {
    for cfg in configs() {
        for level in [Simd::Portable, Simd::Avx2Fma, Simd::Avx512] {
            let mut m = model(&cfg);
            m.set_simd(Some(level));
            let (e_inv, e_fwd) = single_errors(&m, 40);
            println!("{:?} n={} hidden {} {:?}: inverse {e_inv:.1e}, forward {e_fwd:.1e}", cfg.encoder, m.n, cfg.hidden, m.simd());
            assert!(e_inv < 1e-4 && e_fwd < 1e-4, "{cfg:?} {level:?}: inverse {e_inv:e}, forward {e_fwd:e}");
        }
    }
}

/// A 20-step rollout's inputs for `m`.
#[allow(clippy::type_complexity)]
fn rollout_inputs(m: &Model) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let (t_len, n) = (20, m.n);
    let f_v = pseudo(5, t_len, 300.0).iter().map(|f| f.abs()).collect();
    (pseudo(1, n, 1.0), pseudo(2, n, 1.0), pseudo(3, t_len * n, 5.0), pseudo(4, t_len * m.dz, 1.0), f_v)
}

#[test]
fn f32_single_rollouts_agree_with_f64_and_with_their_steps() {
    for cfg in configs() {
        for level in [Simd::Portable, Simd::Avx512] {
            let mut m = model(&cfg);
            m.set_simd(Some(level));
            let n = m.n;
            let (q0, qd0, tau, z, f_v) = rollout_inputs(&m);
            let t_len = tau.len() / n;
            let zs = if m.dz > 0 { ZSeq::PerStep(&z) } else { ZSeq::Keep };
            let inp = Inputs { tau: &tau, z: zs, f_v: Some(&f_v), tau_e: None };
            let len = (t_len + 1) * n;
            let (mut q64, mut qd64, mut q32, mut qd32) = (vec![0.0; len], vec![0.0; len], vec![0.0; len], vec![0.0; len]);
            let (mut w64, mut w32) = (m.workspace(), m.workspace_f32());
            m.rollout(&mut w64, &q0, &qd0, inp, 0.005, &mut q64, &mut qd64).unwrap();
            m.rollout_f32(&mut w32, &q0, &qd0, inp, 0.005, &mut q32, &mut qd32).unwrap();
            let (eq, eqd) = (rel(&q32, &q64), rel(&qd32, &qd64));
            println!("{:?} n={} {:?} rollout: q {eq:.1e}, qd {eqd:.1e}", cfg.encoder, n, m.simd());
            assert!(eq < 1e-4 && eqd < 1e-4, "{cfg:?} {level:?}: q {eq:e}, qd {eqd:e}");
            // the same rollout step by step through forward_dynamics_f32: the same bits
            let mut ws = m.workspace_f32();
            let (mut q, mut qd, mut qdd) = (q0.clone(), qd0.clone(), vec![0.0; n]);
            for k in 0..t_len {
                ws.set_z(&m, &z[k * m.dz..(k + 1) * m.dz]).unwrap();
                m.forward_dynamics_f32(&mut ws, &q, &qd, &tau[k * n..(k + 1) * n], f_v[k], &mut qdd).unwrap();
                for i in 0..n {
                    qd[i] += 0.005 * qdd[i];
                    q[i] += 0.005 * qd[i];
                }
                let at = (k + 1) * n..(k + 2) * n;
                assert!(q.iter().chain(&qd).zip(q32[at.clone()].iter().chain(&qd32[at])).all(|(a, b)| a.to_bits() == b.to_bits()), "step {k}");
            }
        }
    }
}

#[test]
fn f32_single_calls_are_deterministic() {
    let m = model(&SynthConfig::default());
    let n = m.n;
    let (z, q, qd, qdd) = (pseudo(1, m.dz, 1.0), pseudo(2, n, 1.0), pseudo(3, n, 1.0), pseudo(4, n, 1.0));
    let mut first = vec![0.0; n];
    let mut ws = m.workspace_f32();
    ws.set_z(&m, &z).unwrap();
    m.inverse_dynamics_f32(&mut ws, &q, &qd, &qdd, 200.0, &mut first).unwrap();
    // repeated calls (the hidden layers alternate their order), other inputs between, fresh workspaces
    for rep in 0..5 {
        let mut fresh = m.workspace_f32();
        let w = if rep % 2 == 0 { &mut ws } else { &mut fresh };
        w.set_z(&m, &z).unwrap();
        let mut other = vec![0.0; n];
        m.inverse_dynamics_f32(w, &qd, &q, &qdd, 10.0, &mut other).unwrap();
        let mut again = vec![0.0; n];
        m.inverse_dynamics_f32(w, &q, &qd, &qdd, 200.0, &mut again).unwrap();
        assert!(again.iter().zip(&first).all(|(a, b)| a.to_bits() == b.to_bits()), "rep {rep}");
    }
}

#[test]
fn f32_single_calls_refuse_what_they_do_not_run() {
    let ext = SynthConfig { extra: vec![("ext.damping".into(), vec![2, 2], vec![1.0, 0.2, 0.2, 0.5])], ..Default::default() };
    let m = model(&ext);
    let mut ws = m.workspace_f32();
    ws.set_z(&m, &vec![0.0; m.dz]).unwrap();
    let mut out = [0.0; 2];
    let err = m.inverse_dynamics_f32(&mut ws, &[0.1, 0.2], &[0.0; 2], &[0.0; 2], 0.0, &mut out).unwrap_err();
    assert!(matches!(err, Error::Unsupported(ref msg) if msg.contains("extension terms")), "{err}");
    let m = model(&SynthConfig::default());
    let mut ws = m.workspace_f32();
    let err = m.forward_dynamics_f32(&mut ws, &[0.1, 0.2], &[0.0; 2], &[0.0; 2], 0.0, &mut out).unwrap_err();
    assert!(matches!(err, Error::InputShape(ref msg) if msg.contains("not set")), "{err}");
    ws.set_z(&m, &vec![0.0; m.dz]).unwrap();
    let err = m.inverse_dynamics_f32(&mut ws, &[0.1, f64::NAN], &[0.0; 2], &[0.0; 2], 0.0, &mut out).unwrap_err();
    assert_eq!(err, Error::NonFiniteInput("q".into()));
    let err = m.forward_dynamics_f32(&mut ws, &[0.1, 0.2], &[0.0; 2], &[0.0; 2], 0.0, &mut out[..1]).unwrap_err();
    assert!(matches!(err, Error::InputShape(_)), "{err}");
    let other = model(&SynthConfig { joint_types: vec!["prismatic"], encoder: "none", ..Default::default() });
    let err = other.inverse_dynamics_f32(&mut ws, &[0.1], &[0.0], &[0.0], 0.0, &mut out[..1]).unwrap_err();
    assert!(matches!(err, Error::InputShape(ref msg) if msg.contains("different model")), "{err}");
}
