//! The kernel against central finite differences of its own forward pass (float64), and against itself
//! at any thread count. (The comparison with torch's autograd lives in tests/test_native_terms.py.)

use super::*;
use crate::synth::Rng;
use crate::model::JointType;
use crate::pool::Pool;

struct Setup {
    types: Vec<JointType>,
    dz: usize,
    l: Vec<(Vec<f64>, Vec<f64>, usize, usize)>,
    v: Vec<(Vec<f64>, Vec<f64>, usize, usize)>,
}

fn setup(types: Vec<JointType>, dz: usize, hidden: usize, rng: &mut Rng) -> Setup {
    let n = types.len();
    let dphi: usize = types.iter().map(|t| if *t == JointType::Revolute { 2 } else { 1 }).sum();
    let mk = |rng: &mut Rng, out_last: usize| {
        let dims = [dphi + dz, hidden, hidden, out_last];
        (0..3).map(|i| (rng.uniform(dims[i + 1] * dims[i], 0.6), rng.uniform(dims[i + 1], 0.3), dims[i + 1], dims[i])).collect::<Vec<_>>()
    };
    let l = mk(rng, n * (n + 1) / 2);
    let v = mk(rng, 1);
    Setup { types, dz, l, v }
}

fn refs(ls: &[(Vec<f64>, Vec<f64>, usize, usize)]) -> Vec<LayerRef<'_, f64>> {
    ls.iter().map(|(w, b, o, i)| (&w[..], &b[..], *o, *i)).collect()
}

fn kernel(s: &Setup) -> TermsKernel<f64> {
    TermsKernel::new(&s.types, s.dz, 1e-2, 3.0, &refs(&s.l), &refs(&s.v)).unwrap()
}

/// The scalar loss Σ wL·L + wH·H + wc·c + wg·g of a forward pass.
fn loss(k: &TermsKernel<f64>, q: &[f64], qd: &[f64], z: &[f64], w: &[Vec<f64>; 4], pool: &Pool) -> f64 {
    let (nn, n) = (q.len() / k.n() * k.n() * k.n(), q.len());
    let (mut l, mut h, mut c, mut g) = (vec![0.0; nn], vec![0.0; nn], vec![0.0; n], vec![0.0; n]);
    k.forward(q, qd, z, &mut l, &mut h, &mut c, &mut g, None, pool).unwrap();
    [l, h, c, g].iter().zip(w).map(|(a, b)| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>()).sum()
}

#[test]
fn gradients_match_finite_differences() {
    let pool = Pool::new(1).unwrap();
    let cases = [
        (vec![JointType::Revolute, JointType::Revolute], 3),
        (vec![JointType::Prismatic], 0),
        (vec![JointType::Revolute, JointType::Prismatic, JointType::Revolute], 2),
    ];
    for (types, dz) in cases {
        let mut rng = Rng(7);
        let s = setup(types, dz, 10, &mut rng);
        let k = kernel(&s);
        let (n, ns) = (k.n(), 5);
        let q = rng.uniform(ns * n, 2.0);
        let qd = rng.uniform(ns * n, 1.5);
        let z = rng.uniform(ns * dz, 1.0);
        let w = [rng.uniform(ns * n * n, 1.0), rng.uniform(ns * n * n, 1.0), rng.uniform(ns * n, 1.0), rng.uniform(ns * n, 1.0)];
        let mut tape = Tape::new();
        let (mut l, mut h, mut c, mut g) = (vec![0.0; ns * n * n], vec![0.0; ns * n * n], vec![0.0; ns * n], vec![0.0; ns * n]);
        k.forward(&q, &qd, &z, &mut l, &mut h, &mut c, &mut g, Some(&mut tape), &pool).unwrap();
        let (mut dq, mut dqd, mut dzv) = (vec![0.0; ns * n], vec![0.0; ns * n], vec![0.0; ns * dz]);
        let (gl, gv) = k.backward(&tape, &w[0], &w[1], &w[2], &w[3], &mut dq, &mut dqd, &mut dzv, &pool).unwrap();
        let eps = 1e-6;
        let fd = |f: &dyn Fn(f64) -> f64| (f(eps) - f(-eps)) / (2.0 * eps);
        let close = |a: f64, b: f64, what: &str| assert!((a - b).abs() < 1e-6 * (1.0 + b.abs()), "{what}: {a} vs {b}");
        for i in 0..ns * n {
            close(dq[i], fd(&|e| { let mut x = q.clone(); x[i] += e; loss(&k, &x, &qd, &z, &w, &pool) }), "q");
            close(dqd[i], fd(&|e| { let mut x = qd.clone(); x[i] += e; loss(&k, &q, &x, &z, &w, &pool) }), "qd");
        }
        for i in 0..ns * dz {
            close(dzv[i], fd(&|e| { let mut x = z.clone(); x[i] += e; loss(&k, &q, &qd, &x, &w, &pool) }), "z");
        }
        for (net, grads) in [(0, &gl), (1, &gv)] {
            for (li, (dw, db)) in grads.iter().enumerate() {
                for i in (0..dw.len()).step_by(7) {
                    let num = fd(&|e| {
                        let mut s2 = Setup { types: s.types.clone(), dz, l: s.l.clone(), v: s.v.clone() };
                        let layers = if net == 0 { &mut s2.l } else { &mut s2.v };
                        layers[li].0[i] += e;
                        loss(&kernel(&s2), &q, &qd, &z, &w, &pool)
                    });
                    close(dw[i], num, &format!("net {net} layer {li} W[{i}]"));
                }
                for i in 0..db.len() {
                    let num = fd(&|e| {
                        let mut s2 = Setup { types: s.types.clone(), dz, l: s.l.clone(), v: s.v.clone() };
                        let layers = if net == 0 { &mut s2.l } else { &mut s2.v };
                        layers[li].1[i] += e;
                        loss(&kernel(&s2), &q, &qd, &z, &w, &pool)
                    });
                    close(db[i], num, &format!("net {net} layer {li} b[{i}]"));
                }
            }
        }
    }
}

#[test]
fn any_thread_count_gives_the_same_bits() {
    let mut rng = Rng(3);
    let s = setup(vec![JointType::Revolute, JointType::Revolute], 4, 16, &mut rng);
    let k = kernel(&s);
    let ns = 3 * CHUNK_TILES * TILE + 17;
    let q = rng.uniform(ns * 2, 2.0);
    let qd = rng.uniform(ns * 2, 1.0);
    let z = rng.uniform(ns * 4, 1.0);
    let up: Vec<Vec<f64>> = [4, 4, 2, 2].iter().map(|m| rng.uniform(ns * m, 1.0)).collect();
    let mut results = Vec::new();
    for threads in [1, 2, 3] {
        let pool = Pool::new(threads).unwrap();
        let mut tape = Tape::new();
        let (mut l, mut h, mut c, mut g) = (vec![0.0; ns * 4], vec![0.0; ns * 4], vec![0.0; ns * 2], vec![0.0; ns * 2]);
        k.forward(&q, &qd, &z, &mut l, &mut h, &mut c, &mut g, Some(&mut tape), &pool).unwrap();
        let (mut dq, mut dqd, mut dz) = (vec![0.0; ns * 2], vec![0.0; ns * 2], vec![0.0; ns * 4]);
        let (gl, gv) = k.backward(&tape, &up[0], &up[1], &up[2], &up[3], &mut dq, &mut dqd, &mut dz, &pool).unwrap();
        results.push((l, h, c, g, dq, dqd, dz, gl, gv));
    }
    assert!(results.windows(2).all(|w| w[0] == w[1]));
}

#[test]
#[ignore]
fn speed_f32() {
    let mut rng = Rng(5);
    let s = setup(vec![JointType::Revolute, JointType::Revolute], 16, 64, &mut rng);
    let l: Vec<(Vec<f32>, Vec<f32>, usize, usize)> = s.l.iter().map(|(w, b, o, i)| (w.iter().map(|x| *x as f32).collect(), b.iter().map(|x| *x as f32).collect(), *o, *i)).collect();
    let v: Vec<(Vec<f32>, Vec<f32>, usize, usize)> = s.v.iter().map(|(w, b, o, i)| (w.iter().map(|x| *x as f32).collect(), b.iter().map(|x| *x as f32).collect(), *o, *i)).collect();
    let r = |ls: &[(Vec<f32>, Vec<f32>, usize, usize)]| -> Vec<(Vec<f32>, Vec<f32>, usize, usize)> { ls.to_vec() };
    let (l, v) = (r(&l), r(&v));
    let lr: Vec<LayerRef<f32>> = l.iter().map(|(w, b, o, i)| (&w[..], &b[..], *o, *i)).collect();
    let vr: Vec<LayerRef<f32>> = v.iter().map(|(w, b, o, i)| (&w[..], &b[..], *o, *i)).collect();
    let k = TermsKernel::<f32>::new(&s.types, 16, 1e-2, 3.0, &lr, &vr).unwrap();
    let ns = 8192;
    let q: Vec<f32> = rng.uniform(ns * 2, 2.0).iter().map(|x| *x as f32).collect();
    let qd: Vec<f32> = rng.uniform(ns * 2, 1.0).iter().map(|x| *x as f32).collect();
    let z: Vec<f32> = rng.uniform(ns * 16, 1.0).iter().map(|x| *x as f32).collect();
    let pool = Pool::new(1).unwrap();
    let (mut lo, mut h, mut c, mut g) = (vec![0f32; ns * 4], vec![0f32; ns * 4], vec![0f32; ns * 2], vec![0f32; ns * 2]);
    let mut tape = Tape::new();
    for _ in 0..3 {
        let t = std::time::Instant::now();
        k.forward(&q, &qd, &z, &mut lo, &mut h, &mut c, &mut g, Some(&mut tape), &pool).unwrap();
        let t1 = t.elapsed();
        let (mut dq, mut dqd, mut dz) = (vec![0f32; ns * 2], vec![0f32; ns * 2], vec![0f32; ns * 16]);
        let t = std::time::Instant::now();
        k.backward(&tape, &lo, &h, &c, &g, &mut dq, &mut dqd, &mut dz, &pool).unwrap();
        println!("forward {:?} backward {:?} simd {:?}", t1, t.elapsed(), crate::simd::detect());
    }
}

#[test]
fn mlp_gradients_match_finite_differences_and_threads_agree() {
    let mut rng = Rng(11);
    let dims = [9usize, 20, 20, 3];
    let layers: Vec<(Vec<f64>, Vec<f64>, usize, usize)> =
        (0..3).map(|i| (rng.uniform(dims[i + 1] * dims[i], 0.5), rng.uniform(dims[i + 1], 0.3), dims[i + 1], dims[i])).collect();
    let ns = 2 * CHUNK_TILES * TILE + 5;
    let x = rng.uniform(ns * 9, 1.5);
    let w = rng.uniform(ns * 3, 1.0);
    let k = MlpKernel::new(&refs(&layers)).unwrap();
    let loss = |k: &MlpKernel<f64>, x: &[f64]| {
        let mut y = vec![0.0; ns * 3];
        k.forward(x, &mut y, None, &Pool::new(1).unwrap()).unwrap();
        y.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
    };
    let mut runs = Vec::new();
    for threads in [1, 2] {
        let pool = Pool::new(threads).unwrap();
        let (mut y, mut tape) = (vec![0.0; ns * 3], Tape::new());
        k.forward(&x, &mut y, Some(&mut tape), &pool).unwrap();
        let mut dx = vec![0.0; ns * 9];
        let g = k.backward(&tape, &w, Some(&mut dx), &pool).unwrap();
        runs.push((y, dx, g));
    }
    assert!(runs[0] == runs[1], "thread counts disagree");
    let (_, dx, g) = &runs[0];
    let eps = 1e-6;
    for i in (0..ns * 9).step_by(97) {
        let (mut a, mut b) = (x.clone(), x.clone());
        a[i] += eps;
        b[i] -= eps;
        let num = (loss(&k, &a) - loss(&k, &b)) / (2.0 * eps);
        assert!((dx[i] - num).abs() < 1e-6 * (1.0 + num.abs()), "dx[{i}]: {} vs {num}", dx[i]);
    }
    for (li, (dw, db)) in g.iter().enumerate() {
        for (i, grad) in dw.iter().enumerate().step_by(13).chain(db.iter().enumerate().map(|(i, v)| (i + usize::MAX / 2, v))) {
            let bump = |e: f64| {
                let mut l2 = layers.clone();
                if i >= usize::MAX / 2 { l2[li].1[i - usize::MAX / 2] += e } else { l2[li].0[i] += e }
                loss(&MlpKernel::new(&refs(&l2)).unwrap(), &x)
            };
            let num = (bump(eps) - bump(-eps)) / (2.0 * eps);
            assert!((grad - num).abs() < 1e-6 * (1.0 + num.abs()), "layer {li} entry {i}: {grad} vs {num}");
        }
    }
}
