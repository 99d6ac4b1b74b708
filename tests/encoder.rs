//! The streaming encoders against a plain whole-sequence implementation written here from the raw
//! tensors (causal dilated convs with left zero padding; the LSTM recursion): the ring buffers and the
//! per-step state must reproduce the batch computation exactly in structure and to rounding in value.

use safetensors::SafeTensors;

use exolan::synth::{random_weights, SynthConfig};
use exolan::Model;

fn tensor(st: &SafeTensors, name: &str) -> Vec<f64> {
    st.tensor(name).unwrap().data().chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect()
}

fn inputs(t_len: usize, c: usize) -> Vec<Vec<f64>> {
    (0..t_len)
        .map(|t| {
            (0..c)
                .map(|i| {
                    let v = ((t * 7 + i * 13) as f64 * 0.173).sin() * (1.0 + i as f64);
                    if t % 41 == 5 && i == 2 { f64::NAN } else { v }
                })
                .collect()
        })
        .collect()
}

fn normalise(st: &SafeTensors, x: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let (mean, std) = (tensor(st, "norm.ctx_mean"), tensor(st, "norm.ctx_std"));
    x.iter()
        .map(|r| r.iter().enumerate().map(|(i, v)| { let y = (v - mean[i]) / std[i]; if y.is_finite() { y } else { 0.0 } }).collect())
        .collect()
}

/// Causal dilated conv over a whole sequence (T × cin) → T × cout, kernel 2.
fn conv(x: &[Vec<f64>], w: &[f64], b: &[f64], cout: usize, cin: usize, k: usize, d: usize) -> Vec<Vec<f64>> {
    (0..x.len())
        .map(|t| {
            (0..cout)
                .map(|o| {
                    let mut s = b[o];
                    for tap in 0..k {
                        let lag = (k - 1 - tap) * d;
                        if t >= lag {
                            for i in 0..cin {
                                s += w[(o * cin + i) * k + tap] * x[t - lag][i];
                            }
                        }
                    }
                    s
                })
                .collect()
        })
        .collect()
}

fn close(a: &[f64], b: &[f64], what: &str) {
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= 1e-12 * (1.0 + y.abs()), "{what}: {x} vs {y}");
    }
}

#[test]
fn streaming_tcn_equals_whole_sequence_tcn() {
    let bytes = random_weights(&SynthConfig::default());
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let m = Model::from_bytes(&bytes).unwrap();
    let (t_len, c, h) = (150, 7, 16);
    let x = inputs(t_len, c);
    let mut seq = normalise(&st, &x);
    let mut cin = c;
    for i in 0..5 {
        let d = 1 << i;
        let p = format!("encoder.tcn.{i}");
        let relu = |v: Vec<Vec<f64>>| -> Vec<Vec<f64>> { v.into_iter().map(|r| r.into_iter().map(|a| a.max(0.0)).collect()).collect() };
        let h1 = relu(conv(&seq, &tensor(&st, &format!("{p}.conv1.weight")), &tensor(&st, &format!("{p}.conv1.bias")), h, cin, 2, d));
        let h2 = relu(conv(&h1, &tensor(&st, &format!("{p}.conv2.weight")), &tensor(&st, &format!("{p}.conv2.bias")), h, h, 2, d));
        let res = if cin != h {
            conv(&seq, &tensor(&st, &format!("{p}.res.weight")), &tensor(&st, &format!("{p}.res.bias")), h, cin, 1, 1)
        } else {
            seq.clone()
        };
        seq = h2.iter().zip(&res).map(|(a, r)| a.iter().zip(r).map(|(u, v)| (u + v).max(0.0)).collect()).collect();
        cin = h;
    }
    let mut state = m.encoder_state();
    let mut z = vec![0.0; h];
    for t in 0..t_len {
        m.encode_step(&mut state, &x[t], &mut z).unwrap();
        close(&z, &seq[t], &format!("tcn z at t={t}"));
    }
    // reset = a new trial: the first outputs repeat
    state.reset();
    m.encode_step(&mut state, &x[0], &mut z).unwrap();
    close(&z, &seq[0], "after reset");
    // receptive field 63: z_t depends on x_{t-62} but not on x_{t-63}
    let probe = |changed: usize| {
        let mut s = m.encoder_state();
        let mut zz = vec![0.0; h];
        for t in 0..=100 {
            let mut xt = x[t].clone();
            if t == changed {
                xt[0] += 5.0;
            }
            m.encode_step(&mut s, &xt, &mut zz).unwrap();
        }
        zz
    };
    let base = probe(usize::MAX);
    assert_ne!(probe(100 - 62), base, "x[t-62] must reach z_t");
    assert_eq!(probe(100 - 63), base, "x[t-63] is outside the receptive field");
}

#[test]
fn streaming_lstm_equals_the_recursion() {
    let bytes = random_weights(&SynthConfig { encoder: "lstm", ..Default::default() });
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let m = Model::from_bytes(&bytes).unwrap();
    let (t_len, c, h, layers) = (80, 7, 16, 5);
    let x = normalise(&st, &inputs(t_len, c));
    let sig = |v: f64| 1.0 / (1.0 + (-v).exp());
    let mut hs = vec![vec![0.0; h]; layers];
    let mut cs = vec![vec![0.0; h]; layers];
    let mut state = m.encoder_state();
    let mut z = vec![0.0; h];
    let raw = inputs(t_len, c);
    for t in 0..t_len {
        let mut inp = x[t].clone();
        for k in 0..layers {
            let wih = tensor(&st, &format!("encoder.lstm.weight_ih_l{k}"));
            let whh = tensor(&st, &format!("encoder.lstm.weight_hh_l{k}"));
            let bih = tensor(&st, &format!("encoder.lstm.bias_ih_l{k}"));
            let bhh = tensor(&st, &format!("encoder.lstm.bias_hh_l{k}"));
            let ni = inp.len();
            let g: Vec<f64> = (0..4 * h)
                .map(|r| {
                    bih[r] + bhh[r] + (0..ni).map(|j| wih[r * ni + j] * inp[j]).sum::<f64>() + (0..h).map(|j| whh[r * h + j] * hs[k][j]).sum::<f64>()
                })
                .collect();
            for i in 0..h {
                cs[k][i] = sig(g[h + i]) * cs[k][i] + sig(g[i]) * g[2 * h + i].tanh();
                hs[k][i] = sig(g[3 * h + i]) * cs[k][i].tanh();
            }
            inp = hs[k].clone();
        }
        m.encode_step(&mut state, &raw[t], &mut z).unwrap();
        close(&z, &hs[layers - 1], &format!("lstm z at t={t}"));
    }
}
