//! The float types the kernels run in, each chunk function compiled per SIMD level (`simd_dispatch!`). Every
//! function on the path below a dispatched one is `#[inline(always)]`: a function that is not inlined is compiled
//! without the level's target features, and each of its fused multiply-adds becomes a call to libm's `fma`.

use super::mlp::{self, MlpBwd, MlpFwd};
use super::terms::{self, BwdJob, FwdJob};
use crate::real::Real;
use crate::simd::Simd;

/// The float types the kernels run in (f32 for training, f64 for the tests against torch's float64).
pub trait KernelReal: Real {
    #[doc(hidden)]
    fn forward_chunk(simd: Simd, job: &FwdJob<Self>, ci: usize, tape: &mut [Self], outs: [&mut [Self]; 4]);
    #[doc(hidden)]
    fn backward_chunk(simd: Simd, job: &BwdJob<Self>, ci: usize, grad: &mut [Self], outs: [&mut [Self]; 3]);
    #[doc(hidden)]
    fn mlp_forward_chunk(simd: Simd, job: &MlpFwd<Self>, ci: usize, tape: &mut [Self], y: &mut [Self]);
    #[doc(hidden)]
    fn mlp_backward_chunk(simd: Simd, job: &MlpBwd<Self>, ci: usize, grad: &mut [Self], dx: &mut [Self]);
}

macro_rules! kernel_real {
    ($t:ty, $m:ident) => {
        mod $m {
            use super::*;
            use crate::simd::simd_dispatch;

            #[inline(always)]
            fn fwd<const FMA: bool, const WIDE: bool>(job: &FwdJob<$t>, ci: usize, tape: &mut [$t], outs: [&mut [$t]; 4]) {
                terms::forward_chunk::<$t, FMA, WIDE>(job, ci, tape, outs)
            }
            simd_dispatch!(pub(super) fn fwd_simd(job: &FwdJob<$t>, ci: usize, tape: &mut [$t], outs: [&mut [$t]; 4]) = fwd;);
            #[inline(always)]
            fn bwd<const FMA: bool, const WIDE: bool>(job: &BwdJob<$t>, ci: usize, grad: &mut [$t], outs: [&mut [$t]; 3]) {
                terms::backward_chunk::<$t, FMA, WIDE>(job, ci, grad, outs)
            }
            simd_dispatch!(pub(super) fn bwd_simd(job: &BwdJob<$t>, ci: usize, grad: &mut [$t], outs: [&mut [$t]; 3]) = bwd;);
            #[inline(always)]
            fn mfwd<const FMA: bool, const WIDE: bool>(job: &MlpFwd<$t>, ci: usize, tape: &mut [$t], y: &mut [$t]) {
                mlp::forward_chunk::<$t, FMA, WIDE>(job, ci, tape, y)
            }
            simd_dispatch!(pub(super) fn mfwd_simd(job: &MlpFwd<$t>, ci: usize, tape: &mut [$t], y: &mut [$t]) = mfwd;);
            #[inline(always)]
            fn mbwd<const FMA: bool, const WIDE: bool>(job: &MlpBwd<$t>, ci: usize, grad: &mut [$t], dx: &mut [$t]) {
                mlp::backward_chunk::<$t, FMA, WIDE>(job, ci, grad, dx)
            }
            simd_dispatch!(pub(super) fn mbwd_simd(job: &MlpBwd<$t>, ci: usize, grad: &mut [$t], dx: &mut [$t]) = mbwd;);
        }

        impl KernelReal for $t {
            fn forward_chunk(simd: Simd, job: &FwdJob<$t>, ci: usize, tape: &mut [$t], outs: [&mut [$t]; 4]) {
                $m::fwd_simd(simd, job, ci, tape, outs)
            }
            fn backward_chunk(simd: Simd, job: &BwdJob<$t>, ci: usize, grad: &mut [$t], outs: [&mut [$t]; 3]) {
                $m::bwd_simd(simd, job, ci, grad, outs)
            }
            fn mlp_forward_chunk(simd: Simd, job: &MlpFwd<$t>, ci: usize, tape: &mut [$t], y: &mut [$t]) {
                $m::mfwd_simd(simd, job, ci, tape, y)
            }
            fn mlp_backward_chunk(simd: Simd, job: &MlpBwd<$t>, ci: usize, grad: &mut [$t], dx: &mut [$t]) {
                $m::mbwd_simd(simd, job, ci, grad, dx)
            }
        }
    };
}
kernel_real!(f32, single);
kernel_real!(f64, double);
