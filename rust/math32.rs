//! Elementwise functions of the float32 lane rollouts, branch-free so loops over lanes vectorise,
//! accurate to float32 rounding (tested against libm in f64):
//!
//! - `tanh`: the odd rational minimax approximation of Eigen's `ptanh_float` (|x| clamped at 7.905,
//!   where tanh rounds to ±1), a few ulp;
//! - `sin_cos` (joint angles → φ), `softplus_sigmoid` (the diagonal of L): f32 polynomials with the
//!   argument reduced in parts, a few ulp.

// the published constants (Eigen, cephes) as written, rounded to f32 by the compiler
#![allow(clippy::excessive_precision)]

use crate::real::Real;

/// 1.5·2^23: adding it rounds an f32 to an integer (for |x| < 2^22), held in the low mantissa bits.
const SHIFTER32: f32 = 12_582_912.0;
/// π/2 in three parts (cephes' sinf DP1..3, doubled): k·PIO2_1 is exact for |k| < 2^16.
const PIO2_1: f32 = 1.570_312_5;
const PIO2_2: f32 = 4.837_512_969_970_703e-4;
const PIO2_3: f32 = 7.549_789_954_891_882e-8;
/// ln 2 in two parts (cephes' expf): k·LN2_HI32 is exact for the k here (≤ 126).
const LN2_HI32: f32 = 0.693_359_4;
const LN2_LO32: f32 = -2.121_944_4e-4;

const TANH_CLAMP: f32 = 7.905_311;
const TANH_P: [f32; 7] = [
    4.893_524_558_917_86e-3,
    6.372_619_288_754_36e-4,
    1.485_722_357_179_79e-5,
    5.122_297_090_371_14e-8,
    -8.604_671_522_137_35e-11,
    2.000_187_904_824_77e-13,
    -2.760_768_477_423_55e-16,
];
const TANH_Q: [f32; 4] = [4.893_525_185_543_85e-3, 2.268_434_632_439e-3, 1.185_347_056_866_54e-4, 1.198_258_394_667_02e-6];

#[inline(always)]
fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    <f32 as Real>::madd::<FMA>(a, b, c)
}

/// tanh(x) to a few ulp of f32; NaN propagates.
#[inline(always)]
pub(crate) fn tanh<const FMA: bool>(x: f32) -> f32 {
    let x = x.clamp(-TANH_CLAMP, TANH_CLAMP);
    let x2 = x * x;
    let mut p = TANH_P[6];
    for c in TANH_P[..6].iter().rev() {
        p = madd::<FMA>(p, x2, *c);
    }
    let mut q = TANH_Q[3];
    for c in TANH_Q[..3].iter().rev() {
        q = madd::<FMA>(q, x2, *c);
    }
    x * p / q
}

/// tanh on block 0 (`width` values) and dh = (1 − h²) da on the nt − 1 tangent blocks after it.
#[inline(always)]
pub(crate) fn tanh_tangent<const FMA: bool, const WIDE: bool>(a: &mut [f32], width: usize, nt: usize) {
    let (h, rest) = a[..nt * width].split_at_mut(width);
    let mut i = 0;
    #[cfg(target_arch = "x86_64")]
    if WIDE {
        i = width - width % 16;
        // SAFETY: WIDE is only instantiated inside `#[target_feature(enable = "avx512f")]` code.
        unsafe { tanh16(&mut h[..i]) };
    }
    for x in h[i..].iter_mut() {
        *x = tanh::<FMA>(*x);
    }
    for k in 0..nt - 1 {
        for (d, hi) in rest[k * width..(k + 1) * width].iter_mut().zip(h.iter()) {
            *d *= madd::<FMA>(-*hi, *hi, 1.0);
        }
    }
}

/// `tanh` 16 values per instruction, the division replaced by `rcp14` and one Newton step
/// (relative error 2^-14 → ~2^-28, below f32 rounding); within an ulp or two of `tanh` (tested).
/// SAFETY (caller): avx512f is available.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn tanh16(v: &mut [f32]) {
    use std::arch::x86_64::*;
    let set = _mm512_set1_ps;
    for c in v.chunks_exact_mut(16) {
        // SAFETY: 16 values per chunk.
        let x = unsafe { _mm512_loadu_ps(c.as_ptr()) };
        // max/min return their second operand when either is NaN: x second, so NaN propagates
        let x = _mm512_min_ps(set(TANH_CLAMP), _mm512_max_ps(set(-TANH_CLAMP), x));
        let x2 = _mm512_mul_ps(x, x);
        let mut p = set(TANH_P[6]);
        for k in (0..6).rev() {
            p = _mm512_fmadd_ps(p, x2, set(TANH_P[k]));
        }
        let mut q = set(TANH_Q[3]);
        for k in (0..3).rev() {
            q = _mm512_fmadd_ps(q, x2, set(TANH_Q[k]));
        }
        let r = _mm512_rcp14_ps(q);
        let r = _mm512_fmadd_ps(r, _mm512_fnmadd_ps(q, r, set(1.0)), r);
        unsafe { _mm512_storeu_ps(c.as_mut_ptr(), _mm512_mul_ps(_mm512_mul_ps(x, p), r)) };
    }
}

/// (sin x, cos x): x − k·π/2 in three parts (Cody–Waite; accurate for |x| < 1e5), Taylor polynomials
/// on [−π/4, π/4] (truncation < 2e-9); the quadrant from the low bits of the rounded k, selects
/// instead of branches. All f32/i32 operations, so lane loops vectorise 16 wide.
#[inline(always)]
pub(crate) fn sin_cos(x: f32) -> (f32, f32) {
    let kf = x * std::f32::consts::FRAC_2_PI + SHIFTER32;
    let k = kf - SHIFTER32;
    let r = ((x - k * PIO2_1) - k * PIO2_2) - k * PIO2_3;
    let r2 = r * r;
    let s = r + r * r2 * (-1.0 / 6.0 + r2 * (1.0 / 120.0 + r2 * (-1.0 / 5040.0 + r2 * (1.0 / 362_880.0))));
    let c = 1.0 + r2 * (-0.5 + r2 * (1.0 / 24.0 + r2 * (-1.0 / 720.0 + r2 * (1.0 / 40_320.0 + r2 * (-1.0 / 3_628_800.0)))));
    let quadrant = kf.to_bits() & 3; // k mod 4, also for negative k
    let (s, c) = if quadrant & 1 != 0 { (c, -s) } else { (s, c) };
    if quadrant & 2 != 0 {
        (-s, -c)
    } else {
        (s, c)
    }
}

/// torch's softplus (x for x > 20, else log(1 + e^x)) and sigmoid(x) = its derivative, from one
/// w = e^(−|x|) (2^(−k) e^r, Taylor to r^7): softplus = max(x, 0) + log1p(w), log1p(w) = 2 atanh(w / (2 + w))
/// by its series; f32/i32 operations only (vectorises).
#[inline(always)]
pub(crate) fn softplus_sigmoid(x: f32) -> (f32, f32) {
    let a = x.abs().min(87.0);
    let kf = a * std::f32::consts::LOG2_E + SHIFTER32;
    let k = kf - SHIFTER32;
    let r = (k * LN2_HI32 - a) + k * LN2_LO32;
    let mut p = 1.0 / 5040.0;
    for c in [1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
        p = p * r + c;
    }
    let ki = kf.to_bits().wrapping_sub(SHIFTER32.to_bits()); // k, 0..=126
    let w = f32::from_bits(127u32.wrapping_sub(ki) << 23) * p;
    let s = w / (2.0 + w);
    let s2 = s * s;
    let mut l = 1.0 / 13.0;
    for c in [1.0 / 11.0, 1.0 / 9.0, 1.0 / 7.0, 1.0 / 5.0, 1.0 / 3.0, 1.0] {
        l = l * s2 + c;
    }
    let sp = if x > 20.0 { x } else { x.max(0.0) + 2.0 * s * l };
    let d = 1.0 / (1.0 + w);
    (sp, if x >= 0.0 { d } else { w * d })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f32, b: f64) -> f64 {
        (a as f64 - b).abs() / (f32::EPSILON as f64 * b.abs().max(1e-30))
    }

    #[test]
    fn float32_functions_match_libm() {
        let (mut wt, mut ws, mut wp) = (0.0f64, 0.0f64, 0.0f64);
        let mut x = -30.0f64;
        while x < 30.0 {
            for xx in [x, x * 1e-3, x * 1e-6, x * 40.0] {
                let xf = xx as f32;
                let x64 = xf as f64;
                wt = wt.max(ulps(tanh::<true>(xf), x64.tanh())).max(ulps(tanh::<false>(xf), x64.tanh()));
                let (s, c) = sin_cos(xf);
                // absolute in units of f32 epsilon: sin/cos near their zeros have no relative scale
                ws = ws.max((s as f64 - x64.sin()).abs().max((c as f64 - x64.cos()).abs()) / f32::EPSILON as f64);
                let (sp, sg) = softplus_sigmoid(xf);
                let want = if x64 > 20.0 { x64 } else { x64.exp().ln_1p() };
                wp = wp.max(ulps(sp, want)).max(ulps(sg, 1.0 / (1.0 + (-x64).exp())));
            }
            x += 0.000_913;
        }
        assert!(wt < 4.0, "tanh: {wt} ulp");
        assert!(ws < 2.0, "sin/cos: {ws} eps absolute");
        assert!(wp < 4.0, "softplus/sigmoid: {wp} ulp");
        assert!(tanh::<true>(f32::NAN).is_nan());
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx512f") {
            let xs: Vec<f32> = (0..4000).map(|i| (i as f32 - 2000.0) * 0.0047).chain([f32::NAN, 9.0, -9.0, 0.0]).chain([0.0; 12]).collect();
            let mut ys = xs.clone();
            #[target_feature(enable = "avx512f,avx2,fma")]
            fn wide(a: &mut [f32]) {
                tanh_tangent::<true, true>(a, a.len(), 1)
            }
            // SAFETY: the CPU has the features.
            unsafe { wide(&mut ys) };
            for (x, y) in xs.iter().zip(&ys) {
                let want = (*x as f64).tanh();
                assert!(x.is_nan() && y.is_nan() || ulps(*y, want) < 4.0, "tanh16({x}) = {y}, want {want}");
            }
        }
        // saturated: within 4 ulp of ±1 (the rational form ends at 1 − 2.4e-7, not at 1)
        assert!((tanh::<true>(100.0) - 1.0).abs() <= 2.5e-7 && (tanh::<true>(-100.0) + 1.0).abs() <= 2.5e-7);
    }
}
