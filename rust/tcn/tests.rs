//! The encoder's kernel against central finite differences of its own forward pass (float64), and against
//! itself at any thread count. (The comparison with torch's autograd lives in tests/test_native_tcn.py.)

use super::*;
use crate::synth::Rng;

#[derive(Clone)]
struct Setup {
    c_in: usize,
    hidden: usize,
    levels: usize,
    kernel: usize,
    convs: Vec<(Vec<f64>, Vec<f64>)>,
}

fn setup(c_in: usize, hidden: usize, levels: usize, kernel: usize, rng: &mut Rng) -> Setup {
    let mut convs = Vec::new();
    for l in 0..levels {
        let cin = if l == 0 { c_in } else { hidden };
        convs.push((rng.uniform(hidden * cin * kernel, 0.6), rng.uniform(hidden, 0.4)));
        convs.push((rng.uniform(hidden * hidden * kernel, 0.6), rng.uniform(hidden, 0.4)));
        if cin != hidden {
            convs.push((rng.uniform(hidden * cin, 0.6), rng.uniform(hidden, 0.4)));
        }
    }
    Setup { c_in, hidden, levels, kernel, convs }
}

fn tcn(s: &Setup) -> Tcn<f64> {
    let refs: Vec<ConvRef<f64>> = s.convs.iter().map(|(w, b)| (&w[..], &b[..])).collect();
    Tcn::new(s.c_in, s.hidden, s.levels, s.kernel, &refs).unwrap()
}

/// Sequence b starts its trial after 3·b positions (all of them when that is beyond the end).
fn keep(batch: usize, t: usize) -> Vec<f64> {
    (0..batch * t).map(|i| if i % t < 3 * (i / t) { 0.0 } else { 1.0 }).collect()
}

/// The scalar loss Σ w·z of a forward pass.
fn loss(k: &Tcn<f64>, x: &[f64], kp: &[f64], batch: usize, t: usize, w: &[f64], pool: &Pool) -> f64 {
    let mut z = vec![0.0; w.len()];
    k.forward(x, kp, batch, t, &mut z, None, pool).unwrap();
    z.iter().zip(w).map(|(a, b)| a * b).sum()
}

#[test]
fn gradients_match_finite_differences() {
    let pool = Pool::new(1).unwrap();
    // (c_in, hidden, levels, kernel, t, batch): weight gradients of fewer rows than gemm's block, of a block and
    // a part, of whole blocks and a recomputed part (16); an identity residual; taps that reach before t = 0
    let cases = [(3, 5, 3, 2, 23, 3), (3, 7, 2, 2, 12, 2), (4, 4, 3, 3, 6, 2), (7, 16, 2, 2, 9, 2)];
    for (c_in, hidden, levels, kernel, t, batch) in cases {
        let mut rng = Rng(11);
        let s = setup(c_in, hidden, levels, kernel, &mut rng);
        let k = tcn(&s);
        let x = rng.uniform(batch * t * c_in, 1.5);
        let kp = keep(batch, t);
        let w = rng.uniform(batch * t * hidden, 1.0);
        let mut tape = TcnTape::new();
        let mut z = vec![0.0; w.len()];
        k.forward(&x, &kp, batch, t, &mut z, Some(&mut tape), &pool).unwrap();
        assert!(z.iter().any(|v| *v > 0.1), "a dead encoder tests nothing");
        let mut dx = vec![0.0; x.len()];
        let grads = k.backward(&tape, &w, Some(&mut dx), &pool).unwrap();
        let eps = 1e-6;
        let fd = |f: &dyn Fn(f64) -> f64| (f(eps) - f(-eps)) / (2.0 * eps);
        let close = |a: f64, b: f64, what: &str| assert!((a - b).abs() < 1e-6 * (1.0 + b.abs()), "{what}: {a} vs {b}");
        for i in 0..x.len() {
            close(dx[i], fd(&|e| { let mut x2 = x.clone(); x2[i] += e; loss(&k, &x2, &kp, batch, t, &w, &pool) }), "x");
        }
        assert_eq!(grads.len(), s.convs.len());
        for (ci, (dw, db)) in grads.iter().enumerate() {
            let perturbed = |bias: bool, i: usize, e: f64| {
                let mut s2 = s.clone();
                if bias { s2.convs[ci].1[i] += e } else { s2.convs[ci].0[i] += e }
                loss(&tcn(&s2), &x, &kp, batch, t, &w, &pool)
            };
            for i in 0..dw.len() {
                close(dw[i], fd(&|e| perturbed(false, i, e)), &format!("case {c_in}/{hidden} conv {ci} W[{i}]"));
            }
            for i in 0..db.len() {
                close(db[i], fd(&|e| perturbed(true, i, e)), &format!("case {c_in}/{hidden} conv {ci} b[{i}]"));
            }
        }
    }
}

#[test]
fn any_thread_count_gives_the_same_bits() {
    let mut rng = Rng(3);
    let s = setup(7, 16, 5, 2, &mut rng);
    let k = tcn(&s);
    // 100 positions: 5 sequences per chunk, 4 chunks
    let (batch, t) = (17, 100);
    let x = rng.uniform(batch * t * 7, 1.0);
    let kp = keep(batch, t);
    let gz = rng.uniform(batch * t * 16, 1.0);
    let mut results = Vec::new();
    for threads in [1, 2, 3] {
        let pool = Pool::new(threads).unwrap();
        let mut tape = TcnTape::new();
        let (mut z, mut z_plain) = (vec![0.0; gz.len()], vec![0.0; gz.len()]);
        // a second pass over the same tape, and a pass without one, change nothing
        for _ in 0..2 {
            k.forward(&x, &kp, batch, t, &mut z, Some(&mut tape), &pool).unwrap();
        }
        k.forward(&x, &kp, batch, t, &mut z_plain, None, &pool).unwrap();
        assert_eq!(z, z_plain);
        let mut dx = vec![0.0; x.len()];
        let grads = k.backward(&tape, &gz, Some(&mut dx), &pool).unwrap();
        assert_eq!(grads, k.backward(&tape, &gz, None, &pool).unwrap());
        results.push((z, dx, grads));
    }
    assert!(results.windows(2).all(|w| w[0] == w[1]));
}

#[test]
fn shapes_are_checked() {
    let mut rng = Rng(5);
    let s = setup(3, 4, 2, 2, &mut rng);
    let refs: Vec<ConvRef<f64>> = s.convs.iter().map(|(w, b)| (&w[..], &b[..])).collect();
    assert!(Tcn::new(3, 4, 2, 2, &refs[1..]).is_err());
    assert!(Tcn::new(3, 4, 2, 3, &refs).is_err());
    let k = tcn(&s);
    assert_eq!(k.shapes(), vec![(4, 3, 2), (4, 4, 2), (4, 3, 1), (4, 4, 2), (4, 4, 2)]);
    let pool = Pool::new(1).unwrap();
    let mut z = vec![0.0; 2 * 5 * 4];
    assert!(k.forward(&[0.0; 29], &[1.0; 10], 2, 5, &mut z, None, &pool).is_err());
    let mut tape = TcnTape::new();
    k.forward(&[0.0; 30], &[1.0; 10], 2, 5, &mut z, Some(&mut tape), &pool).unwrap();
    assert!(k.backward(&tape, &[0.0; 39], None, &pool).is_err());
}

/// The training shape in float32: `cargo test --release --lib tcn::tests::speed -- --ignored --nocapture`
/// (THREADS=n for a pool of n threads).
#[test]
#[ignore]
fn speed_f32() {
    let mut rng = Rng(5);
    let s = setup(7, 16, 5, 2, &mut rng);
    let convs: Vec<(Vec<f32>, Vec<f32>)> = s.convs.iter()
        .map(|(w, b)| (w.iter().map(|v| *v as f32).collect(), b.iter().map(|v| *v as f32).collect())).collect();
    let refs: Vec<ConvRef<f32>> = convs.iter().map(|(w, b)| (&w[..], &b[..])).collect();
    let k = Tcn::<f32>::new(7, 16, 5, 2, &refs).unwrap();
    let (batch, t) = (32, 318);
    let x: Vec<f32> = rng.uniform(batch * t * 7, 1.0).iter().map(|v| *v as f32).collect();
    let kp: Vec<f32> = keep(batch, t).iter().map(|v| *v as f32).collect();
    let gz: Vec<f32> = rng.uniform(batch * t * 16, 1.0).iter().map(|v| *v as f32).collect();
    let threads = std::env::var("THREADS").map_or(1, |v| v.parse().unwrap());
    let pool = Pool::new(threads).unwrap();
    let mut z = vec![0f32; gz.len()];
    let (mut best_f, mut best_b, mut best_n) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
    for _ in 0..40 {
        let mut tape = TcnTape::new();
        let t0 = std::time::Instant::now();
        k.forward(&x, &kp, batch, t, &mut z, Some(&mut tape), &pool).unwrap();
        best_f = best_f.min(t0.elapsed().as_secs_f64());
        let t0 = std::time::Instant::now();
        k.backward(&tape, &gz, None, &pool).unwrap();
        best_b = best_b.min(t0.elapsed().as_secs_f64());
        let t0 = std::time::Instant::now();
        k.forward(&x, &kp, batch, t, &mut z, None, &pool).unwrap();
        best_n = best_n.min(t0.elapsed().as_secs_f64());
    }
    println!("best of 40: forward {:.3} ms, backward {:.3} ms, forward without a tape {:.3} ms, simd {:?}, {threads} thread(s)",
             best_f * 1e3, best_b * 1e3, best_n * 1e3, k.simd);
}
