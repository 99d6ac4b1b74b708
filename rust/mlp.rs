//! Dense layers with forward-mode tangents.
//!
//! A buffer of `nt` blocks holds a layer's value (block 0) and its derivative with respect to each
//! joint coordinate q_k (block k+1): the tangents ride along the value through every layer, so one
//! pass gives the network and its q-Jacobian (DESIGN.md section 2, hand-derived, no autodiff).
//!
//! Weights are stored transposed (`wt[j*out + i] = W[i, j]`) so that the inner loop runs over
//! outputs — independent accumulators, which vectorise without reassociating any sum; the order of
//! every floating-point operation is fixed, so results are bit-identical run to run.

use crate::math::tanh_slice_wide;
use crate::real::Real;

/// `y = W x + b` with W (out × inp); float64 (`Dense<f32>`: the copy for float32 lane rollouts).
#[derive(Debug, Clone)]
pub struct Dense<T = f64> {
    pub inp: usize,
    pub out: usize,
    /// Transposed weights, `inp * out`.
    pub wt: Vec<T>,
    /// Row-major weights, `out * inp` (for the narrow output layers).
    pub rows: Vec<T>,
    pub b: Vec<T>,
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
        Dense { inp, out, wt, rows: w.to_vec(), b: b.to_vec() }
    }

    /// The same layer rounded to float32.
    pub(crate) fn to_f32(&self) -> Dense<f32> {
        let f = |v: &[f64]| v.iter().map(|x| *x as f32).collect();
        Dense { inp: self.inp, out: self.out, wt: f(&self.wt), rows: f(&self.rows), b: f(&self.b) }
    }
}

/// A tanh MLP: tanh after every layer but the last.
#[derive(Debug, Clone)]
pub struct Mlp<T = f64> {
    pub layers: Vec<Dense<T>>,
    /// The first layer's z columns with its bias (`W0[:, split..]`, `b0`), for `z_bias`.
    pub(crate) z_part: Option<Dense<T>>,
    /// The first layer's φ columns (`W0[:, ..split]`, no bias), for the float32 lanes' φ part as a GEMM.
    pub(crate) phi_part: Option<Dense<T>>,
    /// For a reverse pass (`with_backward`; else empty): Wᵀ of the first layer's φ columns, then of
    /// the hidden layers 1..last (no bias).
    pub(crate) back: Vec<Dense<T>>,
}

impl<T> Dense<T> {
    /// Column j of W (all outputs' weights for input j).
    #[inline(always)]
    pub fn col(&self, j: usize) -> &[T] {
        &self.wt[j * self.out..(j + 1) * self.out]
    }
}

impl<T> Mlp<T> {
    pub fn d_out(&self) -> usize {
        self.layers.last().map(|l| l.out).unwrap_or(0)
    }
}

impl<T: Real> Mlp<T> {
    /// `b0 + W0[:, split..] z` with the SIMD kernel (bits may differ from `z_bias` in the last place).
    #[inline(always)]
    pub(crate) fn z_bias_fast<const FMA: bool, const WIDE: bool>(&self, z: &[T], zb: &mut [T]) {
        match &self.z_part {
            Some(d) => dense::<T, FMA, WIDE>(d, 1, z, zb),
            None => zb.copy_from_slice(&self.layers[0].b),
        }
    }
    /// Buffers for a pass with `nt` blocks: one per layer, `nt * out` each.
    pub fn buffers_t(&self, nt: usize) -> Vec<Vec<T>> {
        self.layers.iter().map(|l| vec![T::default(); nt * l.out]).collect()
    }
}

impl Mlp {
    /// The same network rounded to float32.
    pub(crate) fn to_f32(&self) -> Mlp<f32> {
        let f = |v: &[Dense]| v.iter().map(Dense::to_f32).collect();
        let g = |d: &Option<Dense>| d.as_ref().map(Dense::to_f32);
        Mlp { layers: f(&self.layers), z_part: g(&self.z_part), phi_part: g(&self.phi_part), back: f(&self.back) }
    }

    pub fn d_in(&self) -> usize {
        self.layers[0].inp
    }
    /// Buffers for a pass with `nt` blocks: one per layer, `nt * out` each.
    pub fn buffers(&self, nt: usize) -> Vec<Vec<f64>> {
        self.layers.iter().map(|l| vec![0.0; nt * l.out]).collect()
    }
    /// Split off the first layer's z columns (inputs `split..`) as their own dense map.
    pub(crate) fn with_z_part(mut self, split: usize) -> Mlp {
        let l0 = &self.layers[0];
        let dz = l0.inp - split;
        if dz > 0 {
            let mut rows = vec![0.0; l0.out * dz];
            for i in 0..l0.out {
                rows[i * dz..(i + 1) * dz].copy_from_slice(&l0.rows[i * l0.inp + split..(i + 1) * l0.inp]);
            }
            self.z_part = Some(Dense::from_rows(&rows, &l0.b, l0.out, dz));
        }
        let rows: Vec<f64> = (0..l0.out).flat_map(|i| l0.rows[i * l0.inp..i * l0.inp + split].iter().copied()).collect();
        self.phi_part = Some(Dense::from_rows(&rows, &vec![0.0; l0.out], l0.out, split));
        self
    }

    /// Add the transposed layers of a reverse pass (`back`), the first one restricted to inputs ..split.
    pub(crate) fn with_backward(mut self, split: usize) -> Mlp {
        let last = self.layers.len() - 1;
        self.back = self.layers[..last]
            .iter()
            .enumerate()
            .map(|(l, d)| {
                let inp = if l == 0 { split } else { d.inp };
                // Wᵀ (inp × out) from row-major W: its row-major rows are W's columns
                let rows: Vec<f64> = (0..inp).flat_map(|j| (0..d.out).map(move |i| (i, j))).map(|(i, j)| d.rows[i * d.inp + j]).collect();
                Dense::from_rows(&rows, &vec![0.0; inp], inp, d.out)
            })
            .collect();
        self
    }

    /// First layer's constant part for a fixed context: `b0 + W0[:, split..] z`.
    /// Computed once per z, not per step.
    pub fn z_bias(&self, split: usize, z: &[f64], zb: &mut [f64]) {
        let l0 = &self.layers[0];
        zb.copy_from_slice(&l0.b);
        for (j, &zj) in z.iter().enumerate() {
            for (zi, wi) in zb.iter_mut().zip(l0.col(split + j)) {
                *zi += wi * zj;
            }
        }
    }
}

/// Outputs `i0..i0+BW` of `y[k] = W x[k] (+ b for k = 0)` for `NT` blocks, accumulated in registers;
/// each output's sum runs over the inputs in order (b + w_0 x_0 + w_1 x_1 + …).
#[inline(always)]
fn block<T: Real, const NT: usize, const FMA: bool, const BW: usize>(d: &Dense<T>, x: &[T], y: &mut [T], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    assert!(x.len() >= NT * inp && y.len() >= NT * out && i0 + BW <= out);
    assert!(d.wt.len() >= inp * out && d.b.len() >= out);
    let mut acc = [[T::default(); BW]; NT];
    acc[0].copy_from_slice(&d.b[i0..i0 + BW]);
    let wt = d.wt.as_ptr();
    let xp = x.as_ptr();
    for j in 0..inp {
        // SAFETY: j < inp and i0 + BW <= out, so j*out + i0 + BW <= inp*out <= wt.len() (asserted);
        // k*inp + j < NT*inp <= x.len() (asserted). Unchecked reads keep bounds checks out of the
        // innermost loop, which is most of the engine's time.
        let w: &[T; BW] = unsafe { &*(wt.add(j * out + i0) as *const [T; BW]) };
        for k in 0..NT {
            let xk = unsafe { *xp.add(k * inp + j) };
            for i in 0..BW {
                acc[k][i] = T::madd::<FMA>(w[i], xk, acc[k][i]);
            }
        }
    }
    for k in 0..NT {
        y[k * out + i0..k * out + i0 + BW].copy_from_slice(&acc[k]);
    }
}

/// Small output layers (the 3 values of L, the 1 of V, …): dot products along the inputs with 8
/// partial sums (lane l takes inputs j ≡ l mod 8), reduced in a fixed tree — short dependency
/// chains instead of one 64-long chain. The order is fixed by the source, not by the vector width.
#[inline(always)]
fn narrow<T: Real, const NT: usize, const FMA: bool, const WIDE: bool>(d: &Dense<T>, x: &[T], y: &mut [T], i0: usize) {
    let (inp, out) = (d.inp, d.out);
    for i in i0..out {
        let wr = &d.rows[i * inp..(i + 1) * inp];
        for k in 0..NT {
            let s = T::dot8_wide::<FMA, WIDE>(wr, &x[k * inp..(k + 1) * inp]);
            y[k * out + i] = if k == 0 { d.b[i] + s } else { s };
        }
    }
}

/// `dot8`, in one zmm register with AVX-512 (LLVM left the 8 partial sums scalar): the same sums.
#[inline(always)]
pub(crate) fn dot8_wide<const FMA: bool, const WIDE: bool>(w: &[f64], x: &[f64]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if WIDE && w.len().is_multiple_of(8) {
        // SAFETY: WIDE is only instantiated inside `#[target_feature(enable = "avx512f")]` code.
        return unsafe { dot8_512(w, x) };
    }
    dot8::<f64, FMA>(w, x)
}

/// `dot8` for a multiple of 8 terms: partial sum l in lane l, then the tree by lane permutations
/// (adjacent lanes, then pairs within each half, then the halves), `dot8`'s order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn dot8_512(w: &[f64], x: &[f64]) -> f64 {
    use std::arch::x86_64::*;
    let n = w.len();
    assert!(n.is_multiple_of(8) && x.len() >= n);
    let mut acc = _mm512_setzero_pd();
    for c in (0..n).step_by(8) {
        // SAFETY: c + 8 <= n <= both lengths (asserted).
        acc = unsafe { _mm512_fmadd_pd(_mm512_loadu_pd(w.as_ptr().add(c)), _mm512_loadu_pd(x.as_ptr().add(c)), acc) };
    }
    let s1 = _mm512_add_pd(acc, _mm512_permute_pd::<0x55>(acc));
    let s2 = _mm512_add_pd(s1, _mm512_permutex_pd::<0x4E>(s1));
    _mm256_cvtsd_f64(_mm512_castpd512_pd256(s2)) + _mm256_cvtsd_f64(_mm512_extractf64x4_pd::<1>(s2))
}

/// Σ_i w[i] x[i] with 8 partial sums (term i into sum i mod 8, each in order) and a fixed tree:
/// `narrow`'s dot products (lane by lane in `lanes.rs`).
#[inline(always)]
pub(crate) fn dot8<T: Real, const FMA: bool>(w: &[T], x: &[T]) -> T {
    let mut acc = [T::default(); 8];
    let mut wc = w.chunks_exact(8);
    let mut xc = x[..w.len()].chunks_exact(8);
    for (w8, x8) in (&mut wc).zip(&mut xc) {
        for l in 0..8 {
            acc[l] = T::madd::<FMA>(w8[l], x8[l], acc[l]);
        }
    }
    for (l, (wi, xi)) in wc.remainder().iter().zip(xc.remainder()).enumerate() {
        acc[l] = T::madd::<FMA>(*wi, *xi, acc[l]);
    }
    ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
}

/// `y[k] = W x[k] (+ b for k = 0)` for `NT` blocks (value and tangents): register blocks of `BW`
/// outputs (`WIDE`: 32, 16 and 8 outputs in 512-bit registers), then of 4, then the narrow path.
#[inline(always)]
fn dense_nt<T: Real, const NT: usize, const FMA: bool, const WIDE: bool, const BW: usize>(d: &Dense<T>, x: &[T], y: &mut [T], rev: bool) {
    let out = d.out;
    let mut i0 = 0;
    #[cfg(target_arch = "x86_64")]
    if WIDE {
        // SAFETY: WIDE is only instantiated inside `#[target_feature(enable = "avx512f")]` code.
        unsafe {
            // rev: the same blocks last to first (independent outputs, so the same bits; see `eval`)
            // (f64: 32 and 8 outputs; f32: 64 and 16)
            let lw = T::LANES;
            let n32 = out / (4 * lw);
            for b in 0..n32 {
                block512::<T, NT, 4>(d, x, y, 4 * lw * if rev { n32 - 1 - b } else { b });
            }
            i0 = 4 * lw * n32;
            while i0 + lw <= out {
                block512::<T, NT, 1>(d, x, y, i0);
                i0 += lw;
            }
        }
    }
    while i0 + BW <= out {
        block::<T, NT, FMA, BW>(d, x, y, i0);
        i0 += BW;
    }
    while i0 + 4 <= out {
        block::<T, NT, FMA, 4>(d, x, y, i0);
        i0 += 4;
    }
    if i0 < out {
        narrow::<T, NT, FMA, WIDE>(d, x, y, i0);
    }
}

/// `block` for LANES·R outputs in R zmm registers per block, written with intrinsics: the compiler
/// does not vectorise the generic `block` at these widths (it spilled 96 accumulators to the stack).
/// The same fused operations in the same order as `block::<NT, true, _>`, so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(crate) unsafe fn block512<T: Real, const NT: usize, const R: usize>(d: &Dense<T>, x: &[T], y: &mut [T], i0: usize) {
    let (inp, out, lw) = (d.inp, d.out, T::LANES);
    assert!(x.len() >= NT * inp && y.len() >= NT * out && i0 + lw * R <= out);
    assert!(d.wt.len() >= inp * out && d.b.len() >= out);
    // SAFETY (all `T::z*` calls and pointer reads and writes): avx512f (the caller's target feature);
    // indices within the lengths asserted above.
    unsafe {
        let mut acc = [[T::zsplat(T::default()); R]; NT];
        for r in 0..R {
            acc[0][r] = T::zload(d.b.as_ptr().add(i0 + lw * r));
        }
        let (wt, xp) = (d.wt.as_ptr(), x.as_ptr());
        for j in 0..inp {
            let mut w = [T::zsplat(T::default()); R];
            for r in 0..R {
                w[r] = T::zload(wt.add(j * out + i0 + lw * r));
            }
            for k in 0..NT {
                let xk = T::zsplat(*xp.add(k * inp + j));
                for r in 0..R {
                    acc[k][r] = T::zfmadd(w[r], xk, acc[k][r]);
                }
            }
        }
        for k in 0..NT {
            for r in 0..R {
                T::zstore(y.as_mut_ptr().add(k * out + i0 + lw * r), acc[k][r]);
            }
        }
    }
}

/// Same as `dense_nt` for any block count (general n; not the 2-joint hot path).
#[inline(always)]
fn dense_dyn<T: Real, const FMA: bool>(d: &Dense<T>, nt: usize, x: &[T], y: &mut [T]) {
    let (inp, out) = (d.inp, d.out);
    for k in 0..nt {
        let yk = &mut y[k * out..(k + 1) * out];
        if k == 0 {
            yk.copy_from_slice(&d.b);
        } else {
            yk.fill(T::default());
        }
        for j in 0..inp {
            let xk = x[k * inp + j];
            for (yi, wi) in yk.iter_mut().zip(d.col(j)) {
                *yi = T::madd::<FMA>(*wi, xk, *yi);
            }
        }
    }
}

/// Dispatch on the tangent count. Register blocks are sized so the accumulators, the weight loads
/// and the broadcast fit the register file (AVX2: 3 x 3 ymm accumulators for value + 2 tangents;
/// AVX-512: 3 x 4 zmm, see `block512`; portable SSE2: 4 outputs). The block width only changes which outputs are
/// computed together, never the order of any sum, so AVX2 and AVX-512 agree bit for bit.
#[inline(always)]
pub(crate) fn dense<T: Real, const FMA: bool, const WIDE: bool>(d: &Dense<T>, nt: usize, x: &[T], y: &mut [T]) {
    dense_ordered::<T, FMA, WIDE>(d, nt, x, y, false)
}

/// `dense`, its register blocks visited last to first when `rev` (the same results).
#[inline(always)]
pub(crate) fn dense_ordered<T: Real, const FMA: bool, const WIDE: bool>(d: &Dense<T>, nt: usize, x: &[T], y: &mut [T], rev: bool) {
    match (FMA, WIDE) {
        (true, true) => match nt {
            1 => dense_nt::<T, 1, FMA, WIDE, 8>(d, x, y, rev),
            2 => dense_nt::<T, 2, FMA, WIDE, 8>(d, x, y, rev),
            3 => dense_nt::<T, 3, FMA, WIDE, 8>(d, x, y, rev),
            4 => dense_nt::<T, 4, FMA, WIDE, 8>(d, x, y, rev),
            _ => dense_dyn::<T, FMA>(d, nt, x, y),
        },
        (true, false) => match nt {
            1 => dense_nt::<T, 1, FMA, WIDE, 16>(d, x, y, rev),
            2 => dense_nt::<T, 2, FMA, WIDE, 12>(d, x, y, rev),
            3 => dense_nt::<T, 3, FMA, WIDE, 12>(d, x, y, rev),
            4 => dense_nt::<T, 4, FMA, WIDE, 8>(d, x, y, rev),
            _ => dense_dyn::<T, FMA>(d, nt, x, y),
        },
        _ => match nt {
            1 => dense_nt::<T, 1, FMA, WIDE, 8>(d, x, y, rev),
            2 => dense_nt::<T, 2, FMA, WIDE, 4>(d, x, y, rev),
            3 => dense_nt::<T, 3, FMA, WIDE, 4>(d, x, y, rev),
            4 => dense_nt::<T, 4, FMA, WIDE, 4>(d, x, y, rev),
            _ => dense_dyn::<T, FMA>(d, nt, x, y),
        },
    }
}

/// tanh on block 0 and the chain rule on the tangents: dh = (1 − h²) da.
#[inline(always)]
pub(crate) fn tanh_tangent<const FMA: bool, const WIDE: bool>(a: &mut [f64], width: usize, nt: usize) {
    let (h, rest) = a[..nt * width].split_at_mut(width);
    tanh_slice_wide::<FMA, WIDE>(h);
    for k in 0..nt - 1 {
        let dk = &mut rest[k * width..(k + 1) * width];
        for (di, hi) in dk.iter_mut().zip(h.iter()) {
            *di *= 1.0 - hi * hi;
        }
    }
}

/// Run layers 1.. of `mlp` given layer 0's pre-activations (with tangents) in `bufs[0]`.
/// The output layer's values and tangents end up in `bufs[last]`.
#[inline(always)]
pub(crate) fn mlp_rest<T: Real, const FMA: bool, const WIDE: bool>(mlp: &Mlp<T>, nt: usize, bufs: &mut [Vec<T>], rev: bool) {
    for l in 1..mlp.layers.len() {
        let (prev, next) = bufs.split_at_mut(l);
        let a = &mut prev[l - 1];
        T::tanh_tangent::<FMA, WIDE>(a, mlp.layers[l - 1].out, nt);
        dense_ordered::<T, FMA, WIDE>(&mlp.layers[l], nt, a, &mut next[0], rev);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dense_blocks_agree_with_naive() {
        for level in 0..3 {
            dense_check(level);
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    fn wide_avx512(d: &Dense, nt: usize, x: &[f64], y: &mut [f64]) {
        dense::<f64, true, true>(d, nt, x, y)
    }

    fn wide(d: &Dense, nt: usize, x: &[f64], y: &mut [f64]) {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has the features.
            return unsafe { wide_avx512(d, nt, x, y) };
        }
        dense::<f64, true, false>(d, nt, x, y)
    }

    fn dense_check(fma: u8) {
        let (out, inp) = (69, 7);
        let w: Vec<f64> = (0..out * inp).map(|i| ((i * 37 % 23) as f64 - 11.0) / 7.0).collect();
        let b: Vec<f64> = (0..out).map(|i| i as f64 * 0.1 - 0.5).collect();
        let d = Dense::from_rows(&w, &b, out, inp);
        for nt in 1..=6 {
            let x: Vec<f64> = (0..nt * inp).map(|i| (i as f64 * 0.37).sin()).collect();
            let mut y = vec![0.0; nt * out];
            match fma {
                0 => dense::<f64, false, false>(&d, nt, &x, &mut y),
                1 => dense::<f64, true, false>(&d, nt, &x, &mut y),
                _ => wide(&d, nt, &x, &mut y),
            }
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
