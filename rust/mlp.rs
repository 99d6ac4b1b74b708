//! Dense layers with forward-mode tangents.
//!
//! A buffer of `nt` blocks holds a layer's value (block 0) and its derivative with respect to each
//! joint coordinate q_k (block k+1): the tangents ride along the value through every layer, so one
//! pass gives the network and its q-Jacobian (DESIGN.md section 2, hand-derived, no autodiff).
//!
//! Weights are stored transposed (`wt[j*out + i] = W[i, j]`) so that the inner loop runs over
//! outputs — independent accumulators, which vectorise without reassociating any sum; the order of
//! every floating-point operation is fixed, so results are bit-identical run to run.

use crate::math::{madd, tanh_slice};

/// `y = W x + b` with W (out × inp).
#[derive(Debug, Clone)]
pub struct Dense {
    pub inp: usize,
    pub out: usize,
    /// Transposed weights, `inp * out`.
    pub wt: Vec<f64>,
    pub b: Vec<f64>,
}

impl Dense {
    /// From torch's row-major (out, inp) weight.
    pub fn from_rows(w: &[f64], b: &[f64], out: usize, inp: usize) -> Dense {
        debug_assert_eq!(w.len(), out * inp);
        let mut wt = vec![0.0; out * inp];
        for i in 0..out {
            for j in 0..inp {
                wt[j * out + i] = w[i * inp + j];
            }
        }
        Dense { inp, out, wt, b: b.to_vec() }
    }

    /// Column j of W (all outputs' weights for input j).
    #[inline(always)]
    pub fn col(&self, j: usize) -> &[f64] {
        &self.wt[j * self.out..(j + 1) * self.out]
    }
}

/// A tanh MLP: tanh after every layer but the last.
#[derive(Debug, Clone)]
pub struct Mlp {
    pub layers: Vec<Dense>,
}

impl Mlp {
    pub fn d_in(&self) -> usize {
        self.layers[0].inp
    }
    pub fn d_out(&self) -> usize {
        self.layers.last().map(|l| l.out).unwrap_or(0)
    }
    /// Buffers for a pass with `nt` blocks: one per layer, `nt * out` each.
    pub fn buffers(&self, nt: usize) -> Vec<Vec<f64>> {
        self.layers.iter().map(|l| vec![0.0; nt * l.out]).collect()
    }
    /// First layer's constant part for a fixed context: `b0 + W0[:, split..] z`.
    /// Computed once per z, not per step.
    pub fn z_bias(&self, split: usize, z: &[f64], zb: &mut [f64]) {
        let l0 = &self.layers[0];
        zb.copy_from_slice(&l0.b);
        for (j, &zj) in z.iter().enumerate() {
            let w = l0.col(split + j);
            for i in 0..l0.out {
                zb[i] += w[i] * zj;
            }
        }
    }
}

/// `y[k] = W x[k] (+ b for k = 0)` for `NT` blocks, outputs in register blocks of 8.
#[inline(always)]
fn dense_nt<const NT: usize, const FMA: bool>(d: &Dense, x: &[f64], y: &mut [f64]) {
    let (inp, out) = (d.inp, d.out);
    let x = &x[..NT * inp];
    let y = &mut y[..NT * out];
    let wt = &d.wt[..inp * out];
    let b = &d.b[..out];
    let mut i0 = 0;
    while i0 + 8 <= out {
        let mut acc = [[0.0f64; 8]; NT];
        acc[0].copy_from_slice(&b[i0..i0 + 8]);
        for j in 0..inp {
            let w: &[f64; 8] = wt[j * out + i0..j * out + i0 + 8].try_into().unwrap();
            for k in 0..NT {
                let xk = x[k * inp + j];
                for i in 0..8 {
                    acc[k][i] = madd::<FMA>(w[i], xk, acc[k][i]);
                }
            }
        }
        for k in 0..NT {
            y[k * out + i0..k * out + i0 + 8].copy_from_slice(&acc[k]);
        }
        i0 += 8;
    }
    for i in i0..out {
        for k in 0..NT {
            let mut s = if k == 0 { b[i] } else { 0.0 };
            for j in 0..inp {
                s = madd::<FMA>(wt[j * out + i], x[k * inp + j], s);
            }
            y[k * out + i] = s;
        }
    }
}

/// Same as `dense_nt` for any block count (general n; not the 2-joint hot path).
#[inline(always)]
fn dense_dyn<const FMA: bool>(d: &Dense, nt: usize, x: &[f64], y: &mut [f64]) {
    let (inp, out) = (d.inp, d.out);
    for k in 0..nt {
        let yk = &mut y[k * out..(k + 1) * out];
        if k == 0 {
            yk.copy_from_slice(&d.b);
        } else {
            yk.fill(0.0);
        }
        for j in 0..inp {
            let xk = x[k * inp + j];
            let w = d.col(j);
            for i in 0..out {
                yk[i] = madd::<FMA>(w[i], xk, yk[i]);
            }
        }
    }
}

#[inline(always)]
pub(crate) fn dense<const FMA: bool>(d: &Dense, nt: usize, x: &[f64], y: &mut [f64]) {
    match nt {
        1 => dense_nt::<1, FMA>(d, x, y),
        2 => dense_nt::<2, FMA>(d, x, y),
        3 => dense_nt::<3, FMA>(d, x, y),
        4 => dense_nt::<4, FMA>(d, x, y),
        _ => dense_dyn::<FMA>(d, nt, x, y),
    }
}

/// tanh on block 0 and the chain rule on the tangents: dh = (1 − h²) da.
#[inline(always)]
pub(crate) fn tanh_tangent<const FMA: bool>(a: &mut [f64], width: usize, nt: usize) {
    let (h, rest) = a[..nt * width].split_at_mut(width);
    tanh_slice::<FMA>(h);
    for k in 0..nt - 1 {
        let dk = &mut rest[k * width..(k + 1) * width];
        for i in 0..width {
            dk[i] *= 1.0 - h[i] * h[i];
        }
    }
}

/// Run layers 1.. of `mlp` given layer 0's pre-activations (with tangents) in `bufs[0]`.
/// The output layer's values and tangents end up in `bufs[last]`.
#[inline(always)]
pub(crate) fn mlp_rest<const FMA: bool>(mlp: &Mlp, nt: usize, bufs: &mut [Vec<f64>]) {
    for l in 1..mlp.layers.len() {
        let (prev, next) = bufs.split_at_mut(l);
        let a = &mut prev[l - 1];
        tanh_tangent::<FMA>(a, mlp.layers[l - 1].out, nt);
        dense::<FMA>(&mlp.layers[l], nt, a, &mut next[0]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_blocks_agree_with_naive() {
        let (out, inp) = (19, 7);
        let w: Vec<f64> = (0..out * inp).map(|i| ((i * 37 % 23) as f64 - 11.0) / 7.0).collect();
        let b: Vec<f64> = (0..out).map(|i| i as f64 * 0.1 - 0.5).collect();
        let d = Dense::from_rows(&w, &b, out, inp);
        for nt in 1..=6 {
            let x: Vec<f64> = (0..nt * inp).map(|i| (i as f64 * 0.37).sin()).collect();
            let mut y = vec![0.0; nt * out];
            dense::<false>(&d, nt, &x, &mut y);
            for k in 0..nt {
                for i in 0..out {
                    let mut s = if k == 0 { b[i] } else { 0.0 };
                    for j in 0..inp {
                        s += w[i * inp + j] * x[k * inp + j];
                    }
                    assert!((y[k * out + i] - s).abs() < 1e-13, "nt {nt} k {k} i {i}");
                }
            }
        }
    }
}
