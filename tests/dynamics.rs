//! Self-consistency of the Rust dynamics on random-weight models in the export format:
//! derivatives against finite differences, inverse ∘ forward = identity, H symmetric positive
//! definite, energy conservation, bit-identical batches across thread counts, clear errors.

use exolan::synth::{pseudo, random_weights, shapes, SynthConfig};
use exolan::{Error, Inputs, Model, Workspace, ZSeq};

fn model(cfg: &SynthConfig) -> Model {
    Model::from_bytes(&random_weights(cfg)).expect("synthetic model loads")
}

fn configs() -> Vec<SynthConfig> {
    shapes()
}

fn ws_with_z(m: &Model, seed: u64) -> Workspace {
    let mut ws = m.workspace();
    ws.set_z(m, &pseudo(seed, m.dz, 1.0)).unwrap();
    ws
}

fn h_at(m: &Model, ws: &mut Workspace, q: &[f64]) -> Vec<f64> {
    let zeros = vec![0.0; m.n];
    m.terms(ws, q, &zeros).unwrap();
    ws.h().to_vec()
}

#[test]
fn h_is_symmetric_positive_definite_and_forward_inverts_inverse() {
    for cfg in configs() {
        let m = model(&cfg);
        let n = m.n;
        let mut ws = ws_with_z(&m, 7);
        for trial in 0..20u64 {
            let q = pseudo(100 + trial, n, 2.0);
            let qd = pseudo(200 + trial, n, 3.0);
            let qdd = pseudo(300 + trial, n, 10.0);
            let f_v = 400.0 * trial as f64 / 20.0;
            m.terms(&mut ws, &q, &qd).unwrap();
            let h = ws.h().to_vec();
            for i in 0..n {
                assert!(h[i * n + i] > 0.0);
                for j in 0..n {
                    assert_eq!(h[i * n + j], h[j * n + i], "H symmetric");
                }
            }
            // xᵀHx > 0 for a few directions
            for s in 0..5 {
                let x = pseudo(900 + s, n, 1.0);
                let quad: f64 = (0..n).map(|i| (0..n).map(|j| x[i] * h[i * n + j] * x[j]).sum::<f64>()).sum();
                assert!(quad > 0.0);
            }
            let mut tau = vec![0.0; n];
            m.inverse_dynamics(&mut ws, &q, &qd, &qdd, f_v, None, &mut tau).unwrap();
            let mut back = vec![0.0; n];
            m.forward_dynamics(&mut ws, &q, &qd, &tau, f_v, None, &mut back).unwrap();
            for i in 0..n {
                let tol = 1e-9 * (1.0 + qdd[i].abs());
                assert!((back[i] - qdd[i]).abs() < tol, "{}: qdd {} vs {}", cfg.encoder, back[i], qdd[i]);
            }
            // inverse = H q̈ + c + g − B f_v with the terms the engine reports
            m.terms(&mut ws, &q, &qd).unwrap();
            for i in 0..n {
                let hq: f64 = (0..n).map(|j| ws.h()[i * n + j] * qdd[j]).sum();
                let want = hq + ws.c()[i] + ws.g()[i] - ws.b()[i] * f_v;
                assert!((tau[i] - want).abs() < 1e-12 * (1.0 + want.abs()));
            }
            if !cfg.lim {
                assert!(ws.b().iter().all(|b| *b == 0.0));
            }
        }
    }
}

#[test]
fn g_is_the_gradient_of_v() {
    for cfg in configs() {
        let m = model(&cfg);
        let n = m.n;
        let mut ws = ws_with_z(&m, 8);
        for trial in 0..10u64 {
            let q = pseudo(10 + trial, n, 2.0);
            let zeros = vec![0.0; n];
            m.terms(&mut ws, &q, &zeros).unwrap();
            let g = ws.g().to_vec();
            let eps = 1e-5;
            for k in 0..n {
                let (mut qp, mut qm) = (q.clone(), q.clone());
                qp[k] += eps;
                qm[k] -= eps;
                let vp = m.energy(&mut ws, &qp, &zeros).unwrap().1;
                let vm = m.energy(&mut ws, &qm, &zeros).unwrap().1;
                let fd = (vp - vm) / (2.0 * eps);
                assert!((fd - g[k]).abs() < 1e-6 * (1.0 + g[k].abs()), "g[{k}] {} vs fd {fd}", g[k]);
            }
        }
    }
}

#[test]
fn c_matches_finite_differences_of_h() {
    for cfg in configs() {
        let m = model(&cfg);
        let n = m.n;
        let mut ws = ws_with_z(&m, 9);
        for trial in 0..10u64 {
            let q = pseudo(20 + trial, n, 2.0);
            let qd = pseudo(30 + trial, n, 3.0);
            m.terms(&mut ws, &q, &qd).unwrap();
            let c = ws.c().to_vec();
            let eps = 1e-5;
            // dH[k] = ∂H/∂q_k by central differences
            let dh: Vec<Vec<f64>> = (0..n)
                .map(|k| {
                    let (mut qp, mut qm) = (q.clone(), q.clone());
                    qp[k] += eps;
                    qm[k] -= eps;
                    let hp = h_at(&m, &mut ws, &qp);
                    let hm = h_at(&m, &mut ws, &qm);
                    hp.iter().zip(&hm).map(|(a, b)| (a - b) / (2.0 * eps)).collect()
                })
                .collect();
            let mut scale = 1.0;
            for i in 0..n {
                // (Ḣ q̇)_i − ½ q̇ᵀ ∂H/∂q_i q̇
                let mut hd_qd = 0.0;
                for j in 0..n {
                    let hd_ij: f64 = (0..n).map(|k| dh[k][i * n + j] * qd[k]).sum();
                    hd_qd += hd_ij * qd[j];
                }
                let quad: f64 = (0..n).map(|a| (0..n).map(|b| qd[a] * dh[i][a * n + b] * qd[b]).sum::<f64>()).sum();
                let want = hd_qd - 0.5 * quad;
                scale = f64::max(scale, want.abs());
                assert!((c[i] - want).abs() < 1e-6 * scale, "c[{i}] {} vs fd {want}", c[i]);
            }
            // passivity identity q̇ᵀ c = ½ q̇ᵀ Ḣ q̇ (c does no net work beyond the kinetic energy change)
            let qc: f64 = (0..n).map(|i| qd[i] * c[i]).sum();
            let mut qhq = 0.0;
            for i in 0..n {
                for j in 0..n {
                    let hd_ij: f64 = (0..n).map(|k| dh[k][i * n + j] * qd[k]).sum();
                    qhq += qd[i] * hd_ij * qd[j];
                }
            }
            assert!((qc - 0.5 * qhq).abs() < 1e-6 * (1.0 + qc.abs()));
        }
    }
}

#[test]
fn unforced_motion_conserves_energy() {
    // τ = 0, f_v = 0: dE/dt = 0 exactly; semi-implicit Euler keeps the drift O(dt).
    let m = model(&SynthConfig { seed: 11, ..Default::default() });
    let n = m.n;
    let mut ws = ws_with_z(&m, 12);
    let t_len = 4000;
    let dt = 2e-5;
    let tau = vec![0.0; t_len * n];
    let (mut q, mut qd) = (vec![0.0; (t_len + 1) * n], vec![0.0; (t_len + 1) * n]);
    let q0 = [0.3, -0.8];
    let qd0 = [1.5, -2.0];
    m.rollout(&mut ws, &q0, &qd0, Inputs { tau: &tau, z: ZSeq::Keep, f_v: None, tau_e: None }, dt, &mut q, &mut qd)
        .unwrap();
    let e = |ws: &mut Workspace, k: usize| {
        let (t, v) = m.energy(ws, &q[k * n..(k + 1) * n], &qd[k * n..(k + 1) * n]).unwrap();
        t + v
    };
    let e0 = e(&mut ws, 0);
    let (t0, _) = m.energy(&mut ws, &q0, &qd0).unwrap();
    let moved: f64 = (0..n).map(|i| (q[t_len * n + i] - q0[i]).abs()).sum();
    assert!(moved > 1e-3, "the state must actually move");
    let mut worst: f64 = 0.0;
    for k in (0..=t_len).step_by(100) {
        worst = worst.max((e(&mut ws, k) - e0).abs());
    }
    assert!(worst < 1e-3 * t0.max(1e-3), "energy drift {worst:e} (kinetic {t0:e})");
}

#[test]
fn simd_levels_agree() {
    // AVX-512 and AVX2+FMA agree bit for bit, the portable path to rounding; forcing a level works.
    use exolan::Simd;
    for cfg in configs() {
        let mut m = model(&cfg);
        let n = m.n;
        let q = pseudo(1, n, 1.0);
        let qd = pseudo(2, n, 2.0);
        let qdd = pseudo(3, n, 5.0);
        let run = |m: &Model| {
            let mut ws = ws_with_z(m, 5);
            let mut tau = vec![0.0; n];
            m.inverse_dynamics(&mut ws, &q, &qd, &qdd, 300.0, None, &mut tau).unwrap();
            let mut z = vec![0.0; m.dz];
            if m.dz > 0 {
                let mut st = m.encoder_state();
                for k in 0..70 {
                    let x: Vec<f64> = pseudo(k, m.context_dim(), 2.0);
                    m.encode_step(&mut st, &x, &mut z).unwrap();
                }
            }
            (tau, z)
        };
        let best = m.simd();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let (a, za) = run(&m);
        let (b, zb) = run(&m);
        assert_eq!(bits(&a), bits(&b));
        assert_eq!(bits(&za), bits(&zb));
        if best == Simd::Avx512 {
            // the same sums in the same order with the same fused operations: the same bits
            m.set_simd(Some(Simd::Avx2Fma));
            assert_eq!(m.simd(), Simd::Avx2Fma);
            let (c, zc) = run(&m);
            assert_eq!(bits(&a), bits(&c), "AVX-512 vs AVX2");
            assert_eq!(bits(&za), bits(&zc), "AVX-512 vs AVX2, encoder");
        }
        m.set_simd(Some(Simd::Portable));
        assert_eq!(m.simd(), Simd::Portable);
        let (c, zc) = run(&m);
        for i in 0..n {
            assert!((a[i] - c[i]).abs() < 1e-12 * (1.0 + a[i].abs()), "{best:?}: {} vs {}", a[i], c[i]);
        }
        for i in 0..zc.len() {
            assert!((za[i] - zc[i]).abs() < 1e-12 * (1.0 + za[i].abs()));
        }
    }
}

#[test]
fn z_is_cached_and_switching_back_reproduces_bits() {
    let m = model(&SynthConfig::default());
    let mut ws = m.workspace();
    let (z1, z2) = (pseudo(1, 16, 1.0), pseudo(2, 16, 1.0));
    let q = [0.1, 0.5];
    let qd = [0.2, 0.3];
    let qdd = [1.0, 2.0];
    let mut t1 = [0.0; 2];
    let mut t2 = [0.0; 2];
    let mut t3 = [0.0; 2];
    ws.set_z(&m, &z1).unwrap();
    m.inverse_dynamics(&mut ws, &q, &qd, &qdd, 0.0, None, &mut t1).unwrap();
    ws.set_z(&m, &z2).unwrap();
    m.inverse_dynamics(&mut ws, &q, &qd, &qdd, 0.0, None, &mut t2).unwrap();
    ws.set_z(&m, &z1).unwrap();
    m.inverse_dynamics(&mut ws, &q, &qd, &qdd, 0.0, None, &mut t3).unwrap();
    assert_ne!(t1, t2, "z must matter");
    assert_eq!(t1.map(f64::to_bits), t3.map(f64::to_bits));
}

#[test]
fn batched_rollouts_are_bit_identical_across_thread_counts() {
    let m = model(&SynthConfig::default());
    let n = m.n;
    let (bsz, t_len) = (13, 20);
    let q0 = pseudo(1, bsz * n, 1.0);
    let qd0 = pseudo(2, bsz * n, 1.0);
    let tau = pseudo(3, bsz * t_len * n, 20.0);
    let z = pseudo(4, bsz * t_len * m.dz, 1.0);
    let f_v = pseudo(5, bsz * t_len, 300.0).iter().map(|f| f.abs()).collect::<Vec<_>>();
    let run = |threads: usize| {
        let pool = exolan::Pool::new(threads).unwrap();
        let mut wss: Vec<Workspace> = (0..bsz).map(|_| m.workspace()).collect();
        let mut q = vec![0.0; bsz * (t_len + 1) * n];
        let mut qd = q.clone();
        m.rollout_batch(
                &pool,
                &mut wss,
                &q0,
                &qd0,
                Inputs { tau: &tau, z: ZSeq::PerStep(&z), f_v: Some(&f_v), tau_e: None },
                0.005,
                &mut q,
                &mut qd,
            )
        .unwrap();
        (q, qd)
    };
    let (q1, qd1) = run(1);
    for threads in [2, 3, 4] {
        let (q, qd) = run(threads);
        assert!(q.iter().zip(&q1).all(|(a, b)| a.to_bits() == b.to_bits()), "{threads} threads");
        assert!(qd.iter().zip(&qd1).all(|(a, b)| a.to_bits() == b.to_bits()));
    }
    // and equal to one-by-one single rollouts
    let mut ws = m.workspace();
    let b = 7;
    let mut q = vec![0.0; (t_len + 1) * n];
    let mut qd = q.clone();
    m.rollout(
        &mut ws,
        &q0[b * n..(b + 1) * n],
        &qd0[b * n..(b + 1) * n],
        Inputs {
            tau: &tau[b * t_len * n..(b + 1) * t_len * n],
            z: ZSeq::PerStep(&z[b * t_len * m.dz..(b + 1) * t_len * m.dz]),
            f_v: Some(&f_v[b * t_len..(b + 1) * t_len]),
            tau_e: None,
        },
        0.005,
        &mut q,
        &mut qd,
    )
    .unwrap();
    let off = b * (t_len + 1) * n;
    assert!(q.iter().zip(&q1[off..]).all(|(a, b)| a.to_bits() == b.to_bits()));
}

#[test]
fn batched_lanes_equal_single_rollouts_at_every_level() {
    // the lanes of a group (full and partial) run each element's own operations: the same bits as its
    // single rollout, for every model shape, context kind and code path
    use exolan::Simd;
    for cfg in configs() {
        let mut m = model(&cfg);
        let (n, dz, best) = (m.n, m.dz, m.simd());
        let (bsz, t_len) = (11, 6);
        let q0 = pseudo(11, bsz * n, 1.0);
        let qd0 = pseudo(12, bsz * n, 1.0);
        let tau = pseudo(13, bsz * t_len * n, 5.0);
        let zs = pseudo(14, bsz * t_len * dz, 1.0);
        let zc = pseudo(15, bsz * dz, 1.0);
        let f_v = pseudo(16, bsz * t_len, 300.0).iter().map(|f| f.abs()).collect::<Vec<_>>();
        for level in [Simd::Portable, Simd::Avx2Fma, Simd::Avx512].into_iter().filter(|l| *l <= best) {
            m.set_simd(Some(level));
            for per_step in [true, false] {
                let zb = |b: usize| match (dz, per_step) {
                    (0, _) => ZSeq::Keep,
                    (_, true) => ZSeq::PerStep(&zs[b * t_len * dz..(b + 1) * t_len * dz]),
                    _ => ZSeq::Const(&zc[b * dz..(b + 1) * dz]),
                };
                let all = match (dz, per_step) {
                    (0, _) => ZSeq::Keep,
                    (_, true) => ZSeq::PerStep(&zs),
                    _ => ZSeq::Const(&zc),
                };
                let pool = exolan::Pool::new(2).unwrap();
                let mut wss: Vec<Workspace> = (0..bsz).map(|_| m.workspace()).collect();
                let (mut q, mut qd) = (vec![0.0; bsz * (t_len + 1) * n], vec![0.0; bsz * (t_len + 1) * n]);
                let inp = Inputs { tau: &tau, z: all, f_v: Some(&f_v), tau_e: None };
                m.rollout_batch(&pool, &mut wss, &q0, &qd0, inp, 0.005, &mut q, &mut qd).unwrap();
                let mut ws = m.workspace();
                for b in 0..bsz {
                    let (mut q1, mut qd1) = (vec![0.0; (t_len + 1) * n], vec![0.0; (t_len + 1) * n]);
                    let tb = &tau[b * t_len * n..(b + 1) * t_len * n];
                    let inp = Inputs { tau: tb, z: zb(b), f_v: Some(&f_v[b * t_len..(b + 1) * t_len]), tau_e: None };
                    m.rollout(&mut ws, &q0[b * n..(b + 1) * n], &qd0[b * n..(b + 1) * n], inp, 0.005, &mut q1, &mut qd1).unwrap();
                    let off = b * (t_len + 1) * n;
                    let same = |a: &[f64], c: &[f64]| a.iter().zip(c).all(|(x, y)| x.to_bits() == y.to_bits());
                    assert!(same(&q1, &q[off..]) && same(&qd1, &qd[off..]), "{:?} {level:?} per_step {per_step} element {b}", cfg.joint_types);
                }
            }
        }
    }
}

#[test]
fn ill_conditioned_inertia_is_reported() {
    // softplus_offset 0 and a very negative diagonal pre-activation: L_11 ≈ e^{-60}, cond(H) ~ 1e50.
    let d = SynthConfig::default();
    let mut bias = vec![0.0; 3];
    bias[1] = -60.0;
    let cfg = SynthConfig {
        extra: vec![
            ("delan.L.2.weight".into(), vec![3, 64], vec![0.0; 3 * 64]),
            ("delan.L.2.bias".into(), vec![3], bias),
        ],
        meta: vec![("softplus_offset".into(), "0.0".into())],
        ..d
    };
    let m = model(&cfg);
    let mut ws = ws_with_z(&m, 1);
    let mut qdd = [0.0; 2];
    let r = m.forward_dynamics(&mut ws, &[0.1, 0.2], &[0.0, 0.0], &[1.0, 1.0], 0.0, None, &mut qdd);
    match r {
        Err(Error::IllConditioned { cond, .. }) => assert!(cond > exolan::COND_MAX),
        other => panic!("expected IllConditioned, got {other:?}"),
    }
    let msg = r.unwrap_err().to_string();
    assert!(msg.contains("ill-conditioned"), "{msg}");
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let m = model(&SynthConfig::default());
    let mut ws = m.workspace();
    let mut tau = [0.0; 2];
    // z never set
    let r = m.inverse_dynamics(&mut ws, &[0.0, 0.0], &[0.0, 0.0], &[0.0, 0.0], 0.0, None, &mut tau);
    assert!(matches!(r, Err(Error::InputShape(_))), "{r:?}");
    assert!(matches!(ws.set_z(&m, &[0.0; 3]), Err(Error::InputShape(_))));
    let mut z = vec![0.0; 16];
    z[3] = f64::NAN;
    assert!(matches!(ws.set_z(&m, &z), Err(Error::NonFiniteInput(_))));
    ws.set_z(&m, &[0.0; 16]).unwrap();
    let r = m.inverse_dynamics(&mut ws, &[0.0], &[0.0, 0.0], &[0.0, 0.0], 0.0, None, &mut tau);
    assert!(matches!(r, Err(Error::InputShape(_))));
    let r = m.inverse_dynamics(&mut ws, &[0.0, f64::INFINITY], &[0.0, 0.0], &[0.0, 0.0], 0.0, None, &mut tau);
    assert!(matches!(r, Err(Error::NonFiniteInput(ref s)) if s == "q"), "{r:?}");
    let r = m.inverse_dynamics(&mut ws, &[0.0, 0.0], &[0.0, 0.0], &[0.0, 0.0], f64::NAN, None, &mut tau);
    assert!(matches!(r, Err(Error::NonFiniteInput(_))));
    let mut q = vec![0.0; 6];
    let mut qd = vec![0.0; 6];
    let r = m.rollout(&mut ws, &[0.0, 0.0], &[0.0, 0.0], Inputs { tau: &[0.0; 5], z: ZSeq::Keep, f_v: None, tau_e: None }, 0.005, &mut q, &mut qd);
    assert!(matches!(r, Err(Error::InputShape(_))));
    let r = m.rollout(&mut ws, &[0.0, 0.0], &[0.0, 0.0], Inputs { tau: &[0.0; 4], z: ZSeq::Keep, f_v: None, tau_e: None }, -1.0, &mut q, &mut qd);
    assert!(matches!(r, Err(Error::NonFiniteInput(_))));
}
