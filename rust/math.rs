//! Branch-free elementwise functions (tanh, sigmoid) that the compiler can vectorise.
//!
//! libm's `tanh` is a scalar call of ~50 cycles; the DeLaN pass needs ~300 of them per sample,
//! which alone would blow the 3 µs budget. These versions are accurate to a few ulp (tested
//! against libm) so parity with torch at 1e-9 is unaffected, and they are written without
//! branches so that loops over a slice compile to SIMD code.
//!
//! `FMA` selects fused multiply-add (only instantiated inside `#[target_feature(enable = "fma")]`
//! code). Results are deterministic for a given machine; the two variants may differ in the last bit.

#[inline(always)]
pub(crate) fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

// ln 2 split in two (fdlibm's constants: LN2_HI has trailing zero bits, so k·LN2_HI is exact).
const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
const INV_LN2: f64 = std::f64::consts::LOG2_E;
/// 1.5 * 2^52: adding it rounds to an integer held in the low mantissa bits.
const SHIFTER: f64 = 6_755_399_441_055_744.0;

/// Taylor coefficients 1/(i+1)! of expm1(r)/r.
const EXPM1_C: [f64; 13] = [
        1.0,
        1.0 / 2.0,
        1.0 / 6.0,
        1.0 / 24.0,
        1.0 / 120.0,
        1.0 / 720.0,
        1.0 / 5040.0,
        1.0 / 40320.0,
        1.0 / 362880.0,
        1.0 / 3628800.0,
        1.0 / 39916800.0,
        1.0 / 479001600.0,
        1.0 / 6227020800.0,
    ];
/// Bit-trick start of 1/d (`recip_tanh_den`).
const RECIP_MAGIC: u64 = 0x7FDE_6238_22FC_16E6;

/// expm1(r) for |r| ≤ ln2/2 by its Taylor series to r^13 (truncation < 1e-17 relative).
#[inline(always)]
fn expm1_reduced<const FMA: bool>(r: f64) -> f64 {
    const C: [f64; 13] = EXPM1_C;
    let mut p = C[12];
    let mut i = 11;
    loop {
        p = madd::<FMA>(p, r, C[i]);
        if i == 0 {
            break;
        }
        i -= 1;
    }
    p * r
}

/// expm1(y) for y in [-40, 40] (callers clamp). Written as 2^k (expm1(r) + 1) − 1 with
/// the (2^k − 1) part exact so there is no cancellation for small y.
#[inline(always)]
pub(crate) fn expm1_clamped<const FMA: bool>(y: f64) -> f64 {
    let kf = madd::<FMA>(y, INV_LN2, SHIFTER);
    let k_bits = kf.to_bits().wrapping_sub(SHIFTER.to_bits());
    let k = kf - SHIFTER;
    let r = madd::<FMA>(-k, LN2_LO, madd::<FMA>(-k, LN2_HI, y));
    let em = expm1_reduced::<FMA>(r);
    // 2^k as a double from the integer k in the low bits (k in [-58, 58], always normal).
    let two_k = f64::from_bits(k_bits.wrapping_add(1023) << 52);
    madd::<FMA>(two_k, em, two_k - 1.0)
}

/// exp(y) for y in [-700, 700] (callers clamp): 2^k (1 + expm1(r)), accurate in relative terms
/// also for large negative y (where expm1(y) + 1 would cancel).
#[inline(always)]
pub(crate) fn exp_clamped<const FMA: bool>(y: f64) -> f64 {
    let kf = madd::<FMA>(y, INV_LN2, SHIFTER);
    let k_bits = kf.to_bits().wrapping_sub(SHIFTER.to_bits());
    let k = kf - SHIFTER;
    let r = madd::<FMA>(-k, LN2_LO, madd::<FMA>(-k, LN2_HI, y));
    let em = expm1_reduced::<FMA>(r);
    let two_k = f64::from_bits(k_bits.wrapping_add(1023) << 52);
    two_k + two_k * em
}

/// 1/d for d in [2, 2^60] (tanh's denominator) by Newton–Raphson from the bit-trick estimate
/// (|1 − d y| ≤ 0.051): two cubic steps (error e → e³) and one quadratic leave < 1e-23 before rounding.
/// Nine fused operations instead of a division (16 cycles per 8 values at 512 bits, ~40 % of tanh),
/// the same bits at every vector width. NaN propagates.
#[inline(always)]
fn recip_tanh_den(d: f64) -> f64 {
    let mut y = f64::from_bits(RECIP_MAGIC.wrapping_sub(d.to_bits()));
    for _ in 0..2 {
        let e = (-d).mul_add(y, 1.0);
        y = y.mul_add(e.mul_add(e, e), y);
    }
    let e = (-d).mul_add(y, 1.0);
    y.mul_add(e, y)
}

/// tanh(x), a few ulp from libm.
#[inline(always)]
pub(crate) fn tanh<const FMA: bool>(x: f64) -> f64 {
    // |x| ≥ 20: tanh rounds to ±1 in f64; clamping keeps exp finite.
    let a = if x.abs() > 20.0 { 20.0 } else { x.abs() }; // NaN propagates (min() would drop it)
    tanh_of_em::<FMA>(expm1_clamped::<FMA>(2.0 * a), x)
}

/// Logistic sigmoid 1/(1+e^{−x}), accurate in both tails.
#[inline(always)]
pub(crate) fn sigmoid<const FMA: bool>(x: f64) -> f64 {
    // sigmoid(x) = ½ (1 + tanh(x/2)) loses relative accuracy for x ≪ 0; use e^{-|x|}
    // instead: s(|x|) = 1/(1+e^{-|x|}), s(−|x|) = e^{-|x|}/(1+e^{-|x|}).
    let a = if x.abs() > 40.0 { 40.0 } else { x.abs() };
    let e = exp_clamped::<FMA>(-a);
    let d = 1.0 / (1.0 + e);
    if x >= 0.0 {
        d
    } else {
        e * d
    }
}

/// `tanh::<true>` of 8·V values in V zmm registers, written with intrinsics (LLVM compiled the loop
/// over a slice to scalar code: one value per iteration); V independent chains hide the latency of
/// the ~40 dependent operations. The same operations in the same order (fnmadd(a, b, c) = fma(−a, b, c)
/// exactly), so the same bits as the scalar tanh.
/// SAFETY (caller): avx512f is available and `v` holds at least 8·V values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn tanh8<const V: usize>(v: &mut [f64]) {
    use std::arch::x86_64::*;
    const C: [f64; 13] = EXPM1_C;
    assert!(v.len() >= 8 * V);
    let set = _mm512_set1_pd;
    let (mut x, mut t) = ([_mm512_setzero_pd(); V], [_mm512_setzero_pd(); V]);
    for u in 0..V {
        // SAFETY: 8·V values (asserted).
        x[u] = unsafe { _mm512_loadu_pd(v.as_ptr().add(8 * u)) };
    }
    let (mut kf, mut r, mut p) = ([_mm512_setzero_pd(); V], [_mm512_setzero_pd(); V], [_mm512_setzero_pd(); V]);
    for u in 0..V {
        let ax = _mm512_abs_pd(x[u]);
        let a = _mm512_mask_blend_pd(_mm512_cmp_pd_mask::<_CMP_GT_OQ>(ax, set(20.0)), ax, set(20.0));
        let y = _mm512_mul_pd(set(2.0), a);
        // expm1_clamped
        kf[u] = _mm512_fmadd_pd(y, set(INV_LN2), set(SHIFTER));
        let k = _mm512_sub_pd(kf[u], set(SHIFTER));
        r[u] = _mm512_fnmadd_pd(k, set(LN2_LO), _mm512_fnmadd_pd(k, set(LN2_HI), y));
        p[u] = set(C[12]);
    }
    for i in (0..12).rev() {
        for u in 0..V {
            p[u] = _mm512_fmadd_pd(p[u], r[u], set(C[i]));
        }
    }
    for u in 0..V {
        let pr = _mm512_mul_pd(p[u], r[u]);
        let k_bits = _mm512_sub_epi64(_mm512_castpd_si512(kf[u]), _mm512_set1_epi64(SHIFTER.to_bits() as i64));
        let two_k = _mm512_castsi512_pd(_mm512_slli_epi64::<52>(_mm512_add_epi64(k_bits, _mm512_set1_epi64(1023))));
        let em = _mm512_fmadd_pd(two_k, pr, _mm512_sub_pd(two_k, set(1.0)));
        // tanh_of_em: Newton–Raphson reciprocal of em + 2
        let d = _mm512_add_pd(em, set(2.0));
        let mut q = _mm512_castsi512_pd(_mm512_sub_epi64(_mm512_set1_epi64(RECIP_MAGIC as i64), _mm512_castpd_si512(d)));
        for _ in 0..2 {
            let e = _mm512_fnmadd_pd(d, q, set(1.0));
            q = _mm512_fmadd_pd(q, _mm512_fmadd_pd(e, e, e), q);
        }
        let e = _mm512_fnmadd_pd(d, q, set(1.0));
        let tu = _mm512_mul_pd(em, _mm512_fmadd_pd(q, e, q));
        t[u] = _mm512_mask_blend_pd(_mm512_cmp_pd_mask::<_CMP_GT_OQ>(tu, set(1.0)), tu, set(1.0));
    }
    let sign = _mm512_set1_epi64(i64::MIN);
    for u in 0..V {
        // copysign(t, x)
        let bits = _mm512_or_si512(_mm512_andnot_si512(sign, _mm512_castpd_si512(t[u])), _mm512_and_si512(sign, _mm512_castpd_si512(x[u])));
        unsafe { _mm512_storeu_pd(v.as_mut_ptr().add(8 * u), _mm512_castsi512_pd(bits)) };
    }
}

/// The end of `tanh`: em = expm1(2|x|) → tanh(x).
#[inline(always)]
fn tanh_of_em<const FMA: bool>(em: f64, x: f64) -> f64 {
    // without FMA the Newton steps would lose their accuracy: divide there
    let t = if FMA { em * recip_tanh_den(em + 2.0) } else { em / (em + 2.0) };
    // the product may round above 1 where the quotient rounds to 1 (written so that NaN stays)
    let t = if t > 1.0 { 1.0 } else { t };
    t.copysign(x)
}

/// In-place tanh over a slice.
#[inline(always)]
pub(crate) fn tanh_slice<const FMA: bool>(xs: &mut [f64]) {
    for x in xs.iter_mut() {
        *x = tanh::<FMA>(*x);
    }
}

/// `tanh_slice`, 8 values per AVX-512 instruction when `WIDE` (the same bits).
#[inline(always)]
pub(crate) fn tanh_slice_wide<const FMA: bool, const WIDE: bool>(xs: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if WIDE {
        let mut i = 0;
        // SAFETY (both): WIDE is only instantiated inside `#[target_feature(enable = "avx512f")]` code.
        while i + 32 <= xs.len() {
            unsafe { tanh8::<4>(&mut xs[i..i + 32]) };
            i += 32;
        }
        while i + 8 <= xs.len() {
            unsafe { tanh8::<1>(&mut xs[i..i + 8]) };
            i += 8;
        }
        return tanh_slice::<FMA>(&mut xs[i..]);
    }
    tanh_slice::<FMA>(xs)
}

/// In-place logistic sigmoid over a slice (vectorised loop).
#[inline(always)]
pub(crate) fn sigmoid_slice<const FMA: bool>(xs: &mut [f64]) {
    for x in xs.iter_mut() {
        *x = sigmoid::<FMA>(*x);
    }
}

/// torch's softplus (beta 1, threshold 20): x for x > 20, else log(1 + e^x).
#[inline(always)]
pub(crate) fn softplus(x: f64) -> f64 {
    if x > 20.0 {
        x
    } else {
        x.exp().ln_1p()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rel(a: f64, b: f64) -> f64 {
        if a == b {
            0.0
        } else {
            (a - b).abs() / b.abs().max(1e-300)
        }
    }

    #[test]
    fn tanh_matches_libm() {
        let mut worst: f64 = 0.0;
        let mut x = -25.0;
        while x < 25.0 {
            for xx in [x, x * 1e-3, x * 1e-7] {
                worst = worst.max(rel(tanh::<false>(xx), xx.tanh()));
                worst = worst.max(rel(tanh::<true>(xx), xx.tanh()));
            }
            x += 0.000_731;
        }
        assert!(worst < 1e-15, "worst relative error {worst:e}");
        assert_eq!(tanh::<false>(0.0), 0.0);
        assert!(tanh::<false>(f64::NAN).is_nan());
    }

    #[test]
    fn tanh_slice_is_tanh_bit_for_bit() {
        let xs: Vec<f64> = (0..203).map(|i| ((i as f64) * 0.37 - 30.0) * if i % 3 == 0 { 1e-6 } else { 1.0 }).collect();
        let mut xs = [xs, vec![0.0, -0.0, 19.99, 20.01, -700.0, f64::INFINITY, f64::NAN]].concat();
        let want_t: Vec<u64> = xs.iter().map(|x| tanh::<true>(*x).to_bits()).collect();
        let want_f: Vec<u64> = xs.iter().map(|x| tanh::<false>(*x).to_bits()).collect();
        let (mut ys, mut zs) = (xs.clone(), xs.clone());
        tanh_slice::<false>(&mut ys);
        assert_eq!(ys.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), want_f);
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("fma") {
            #[target_feature(enable = "avx512f,avx2,fma")]
            fn wide(x: &mut [f64]) {
                tanh_slice_wide::<true, true>(x)
            }
            // SAFETY: the CPU has the features.
            unsafe { wide(&mut zs) };
            assert_eq!(zs.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), want_t);
        }
        tanh_slice_wide::<true, false>(&mut xs);
        assert_eq!(xs.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), want_t);
    }

    #[test]
    fn sigmoid_matches_reference() {
        let mut worst: f64 = 0.0;
        let mut x: f64 = -40.0;
        while x < 40.0 {
            let r = 1.0 / (1.0 + (-x).exp());
            worst = worst.max(rel(sigmoid::<false>(x), r));
            worst = worst.max(rel(sigmoid::<true>(x), r));
            x += 0.001_37;
        }
        assert!(worst < 2e-15, "worst relative error {worst:e}");
    }

    #[test]
    fn expm1_matches_libm() {
        let mut worst: f64 = 0.0;
        let mut y = -40.0;
        while y < 40.0 {
            worst = worst.max(rel(expm1_clamped::<false>(y), y.exp_m1()));
            y += 0.000_913;
        }
        assert!(worst < 4e-16, "worst relative error {worst:e}");
    }
}
