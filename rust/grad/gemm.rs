//! The one matrix product of the training kernel: C (+)= A·B for small, cache-resident operands.
//!
//! C is m × w row-major (row stride `ldc`), B is k × w row-major (row stride `ldb`), and A is read
//! element by element through two strides (`a[r·ars + j·acs]`), so the same kernel computes a layer's
//! forward pass (A = the inputs, B = Wᵀ), its input gradient (A = the output gradient, B = W) and its
//! weight gradient (A = the output gradient read transposed, B = the inputs). Widths are multiples of
//! the lane count (the kernel's callers pad with zeros). Every C element's sum runs over j in order with
//! fused operations, whatever the blocking, so the result does not depend on the instruction-set level
//! beyond FMA vs separate multiply-add.

use crate::real::Real;

/// Register block: `MR` rows × `NV` vectors of `V` lanes accumulated over the whole k loop.
/// SAFETY (caller): every index below lies inside the slices (checked once by `gemm`).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn block<T: Real, const FMA: bool, const V: usize, const NV: usize, const MR: usize>(
    k: usize, a: &[T], ars: usize, acs: usize, b: &[T], ldb: usize, c: &mut [T], ldc: usize, acc_in: bool,
) {
    let mut acc = [[[T::default(); V]; NV]; MR];
    if acc_in {
        for r in 0..MR {
            for v in 0..NV {
                for l in 0..V {
                    acc[r][v][l] = unsafe { *c.get_unchecked(r * ldc + v * V + l) };
                }
            }
        }
    }
    for j in 0..k {
        let mut bv = [[T::default(); V]; NV];
        for v in 0..NV {
            for l in 0..V {
                bv[v][l] = unsafe { *b.get_unchecked(j * ldb + v * V + l) };
            }
        }
        for r in 0..MR {
            let x = unsafe { *a.get_unchecked(r * ars + j * acs) };
            for v in 0..NV {
                for l in 0..V {
                    acc[r][v][l] = T::madd::<FMA>(x, bv[v][l], acc[r][v][l]);
                }
            }
        }
    }
    for r in 0..MR {
        for v in 0..NV {
            for l in 0..V {
                unsafe { *c.get_unchecked_mut(r * ldc + v * V + l) = acc[r][v][l] };
            }
        }
    }
}

/// Rows 0..m of one column panel (`NV` vectors wide) in blocks of `MR`, the last rows in smaller blocks.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn panel<T: Real, const FMA: bool, const V: usize, const NV: usize, const MR: usize>(
    m: usize, k: usize, a: &[T], ars: usize, acs: usize, b: &[T], ldb: usize, c: &mut [T], ldc: usize, acc_in: bool,
) {
    let mut r = 0;
    unsafe {
        while r + MR <= m {
            block::<T, FMA, V, NV, MR>(k, &a[r * ars..], ars, acs, b, ldb, &mut c[r * ldc..], ldc, acc_in);
            r += MR;
        }
        while r < m {
            block::<T, FMA, V, NV, 1>(k, &a[r * ars..], ars, acs, b, ldb, &mut c[r * ldc..], ldc, acc_in);
            r += 1;
        }
    }
}

/// C (+)= A·B over column panels of `NV·V` lanes, then the narrower rest.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn panels<T: Real, const FMA: bool, const V: usize, const NV: usize, const MR: usize>(
    m: usize, k: usize, w: usize, a: &[T], ars: usize, acs: usize, b: &[T], ldb: usize, c: &mut [T], ldc: usize, acc_in: bool,
) {
    let mut col = 0;
    // SAFETY: `gemm` checked the extents of a, b and c for all m rows, k terms and w columns.
    unsafe {
        while col + NV * V <= w {
            panel::<T, FMA, V, NV, MR>(m, k, a, ars, acs, &b[col..], ldb, &mut c[col..], ldc, acc_in);
            col += NV * V;
        }
        while col < w {
            panel::<T, FMA, V, 1, MR>(m, k, a, ars, acs, &b[col..], ldb, &mut c[col..], ldc, acc_in);
            col += V;
        }
    }
}

/// C[r][0..w] = (C[r][0..w] if `acc_in`) + Σ_j a[r·ars + j·acs] · B[j][0..w] for r < m.
/// `w` is a multiple of `T::LANES`; the register blocking follows the SIMD level (`WIDE`: 512-bit).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn gemm<T: Real, const FMA: bool, const WIDE: bool>(
    m: usize, k: usize, w: usize, a: &[T], ars: usize, acs: usize, b: &[T], ldb: usize, c: &mut [T], ldc: usize, acc_in: bool,
) {
    if m == 0 || w == 0 {
        return;
    }
    assert!(w % T::LANES == 0, "gemm: width {w} is not a multiple of {}", T::LANES);
    assert!(k == 0 || (m - 1) * ars + (k - 1) * acs < a.len(), "gemm: A too short");
    assert!(k == 0 || (k - 1) * ldb + w <= b.len(), "gemm: B too short");
    assert!((m - 1) * ldc + w <= c.len(), "gemm: C too short");
    // f32: 16 lanes per 512-bit register (8 per 256-bit), f64: 8 (4)
    match (T::LANES, WIDE) {
        (16, true) => panels::<T, FMA, 16, 4, 6>(m, k, w, a, ars, acs, b, ldb, c, ldc, acc_in),
        (8, true) => panels::<T, FMA, 8, 4, 6>(m, k, w, a, ars, acs, b, ldb, c, ldc, acc_in),
        (16, false) => panels::<T, FMA, 8, 2, 6>(m, k, w, a, ars, acs, b, ldb, c, ldc, acc_in),
        _ => panels::<T, FMA, 4, 2, 6>(m, k, w, a, ars, acs, b, ldb, c, ldc, acc_in),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(m: usize, k: usize, w: usize, a: &[f64], ars: usize, acs: usize, b: &[f64], ldb: usize, c: &mut [f64], ldc: usize, acc: bool) {
        for r in 0..m {
            for col in 0..w {
                let mut s = if acc { c[r * ldc + col] } else { 0.0 };
                for j in 0..k {
                    s += a[r * ars + j * acs] * b[j * ldb + col];
                }
                c[r * ldc + col] = s;
            }
        }
    }

    #[test]
    fn every_blocking_computes_the_product() {
        let mut seed = 1u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 33) as f64) / (1u64 << 31) as f64 - 0.5
        };
        for &(m, k, w) in &[(1, 1, 8), (7, 5, 8), (13, 64, 64), (20, 3, 32), (6, 0, 16), (97, 33, 80)] {
            for transposed in [false, true] {
                let (ars, acs) = if transposed { (1, m) } else { (k, 1) };
                let a: Vec<f64> = (0..m * k.max(1)).map(|_| rnd()).collect();
                let b: Vec<f64> = (0..k.max(1) * (w + 3)).map(|_| rnd()).collect();
                let c0: Vec<f64> = (0..m * (w + 5)).map(|_| rnd()).collect();
                for acc in [false, true] {
                    let mut want = c0.clone();
                    naive(m, k, w, &a, ars, acs, &b, w + 3, &mut want, w + 5, acc);
                    for (fma, wide) in [(false, false), (true, false), (true, true)] {
                        let mut got = c0.clone();
                        match (fma, wide) {
                            (false, _) => gemm::<f64, false, false>(m, k, w, &a, ars, acs, &b, w + 3, &mut got, w + 5, acc),
                            (true, false) => gemm::<f64, true, false>(m, k, w, &a, ars, acs, &b, w + 3, &mut got, w + 5, acc),
                            (true, true) => gemm::<f64, true, true>(m, k, w, &a, ars, acs, &b, w + 3, &mut got, w + 5, acc),
                        }
                        for (g, e) in got.iter().zip(&want) {
                            assert!((g - e).abs() < 1e-12, "m {m} k {k} w {w} t {transposed} acc {acc}: {g} vs {e}");
                        }
                    }
                }
            }
        }
    }
}
