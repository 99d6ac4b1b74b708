//! The float type of the lane kernels (`lanes.rs`), lane rollouts (`lane_rollout.rs`) and the
//! single-sample pass (`mlp.rs`, `delan.rs`, `single_f32.rs`): f64, the engine's precision (bit-exact
//! with torch float64), or f32 (opt-in batched rollouts, 16 samples per AVX-512 register, and
//! single-sample calls; `pub` only to bound `LaneWorkspace<T>`, in a private
//! module, so not part of the API). Everything generic over [`Real`] monomorphises to
//! the code it was written as for f64: the trait's methods are `#[inline(always)]` wrappers.

use std::fmt::Debug;
use std::ops::{Add, Div, Mul, Neg, Sub};

use crate::delan::Workspace;
use crate::math32;
use crate::mlp::{tanh_tangent, Mlp};
use crate::model::Model;

#[allow(dead_code)]
pub trait Real:
    Copy + Default + PartialOrd + Debug + Send + Sync + 'static
    + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self> + Neg<Output = Self>
{
    /// Samples per AVX-512 register: the lanes of one group.
    const LANES: usize;
    /// Largest condition number of H a lane rollout accepts (beyond it q̈ has no correct digit).
    const COND_MAX: f64;
    fn of(x: f64) -> Self;
    fn to_f64(self) -> f64;
    fn madd<const FMA: bool>(a: Self, b: Self, c: Self) -> Self;
    fn sqrt(self) -> Self;
    fn sin_cos(self) -> (Self, Self);
    /// torch's softplus (beta 1, threshold 20) and its derivative, the logistic sigmoid.
    fn softplus_sigmoid(self) -> (Self, Self);
    /// tanh on block 0 of a [block][unit·lane] buffer and the chain rule on the tangent blocks.
    fn tanh_tangent<const FMA: bool, const WIDE: bool>(a: &mut [Self], width: usize, nt: usize);
    /// `mlp::dot8` (8 partial sums, fixed tree) of the narrow output layers; f64 in one zmm when WIDE.
    fn dot8_wide<const FMA: bool, const WIDE: bool>(w: &[Self], x: &[Self]) -> Self;
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    /// The first layers' z parts of `ws.zt` at the model's SIMD level (`Workspace::set_z`).
    fn z_bias(m: &Model, ws: &mut Workspace<Self>);
    /// L, V and LIM (if any) in this precision.
    fn nets(m: &Model) -> [Option<&Mlp<Self>>; 3];

    /// One AVX-512 register of LANES values.
    #[cfg(target_arch = "x86_64")]
    type Zmm: Copy;
    /// SAFETY (all `z*`): avx512f is available; pointers are valid for LANES values.
    #[cfg(target_arch = "x86_64")]
    unsafe fn zsplat(x: Self) -> Self::Zmm;
    #[cfg(target_arch = "x86_64")]
    unsafe fn zload(p: *const Self) -> Self::Zmm;
    #[cfg(target_arch = "x86_64")]
    unsafe fn zstore(p: *mut Self, v: Self::Zmm);
    /// a·b + c, fused.
    #[cfg(target_arch = "x86_64")]
    unsafe fn zfmadd(a: Self::Zmm, b: Self::Zmm, c: Self::Zmm) -> Self::Zmm;
}

impl Real for f64 {
    const LANES: usize = 8;
    const COND_MAX: f64 = crate::delan::COND_MAX;
    #[inline(always)]
    fn of(x: f64) -> f64 {
        x
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
        crate::math::madd::<FMA>(a, b, c)
    }
    #[inline(always)]
    fn sqrt(self) -> f64 {
        f64::sqrt(self)
    }
    #[inline(always)]
    fn sin_cos(self) -> (f64, f64) {
        f64::sin_cos(self)
    }
    #[inline(always)]
    fn softplus_sigmoid(self) -> (f64, f64) {
        (crate::math::softplus(self), 1.0 / (1.0 + (-self).exp()))
    }
    #[inline(always)]
    fn tanh_tangent<const FMA: bool, const WIDE: bool>(a: &mut [f64], width: usize, nt: usize) {
        tanh_tangent::<FMA, WIDE>(a, width, nt)
    }
    #[inline(always)]
    fn dot8_wide<const FMA: bool, const WIDE: bool>(w: &[f64], x: &[f64]) -> f64 {
        crate::mlp::dot8_wide::<FMA, WIDE>(w, x)
    }
    #[inline(always)]
    fn min(self, o: f64) -> f64 {
        f64::min(self, o)
    }
    #[inline(always)]
    fn max(self, o: f64) -> f64 {
        f64::max(self, o)
    }
    fn z_bias(m: &Model, ws: &mut Workspace<f64>) {
        crate::delan::z_bias_dispatch64(m.simd, m, ws)
    }
    fn nets(m: &Model) -> [Option<&Mlp<f64>>; 3] {
        [Some(&m.net_l), Some(&m.net_v), m.net_lim.as_ref()]
    }

    #[cfg(target_arch = "x86_64")]
    type Zmm = std::arch::x86_64::__m512d;
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zsplat(x: f64) -> Self::Zmm {
        unsafe { std::arch::x86_64::_mm512_set1_pd(x) }
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zload(p: *const f64) -> Self::Zmm {
        unsafe { std::arch::x86_64::_mm512_loadu_pd(p) }
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zstore(p: *mut f64, v: Self::Zmm) {
        unsafe { std::arch::x86_64::_mm512_storeu_pd(p, v) }
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zfmadd(a: Self::Zmm, b: Self::Zmm, c: Self::Zmm) -> Self::Zmm {
        unsafe { std::arch::x86_64::_mm512_fmadd_pd(a, b, c) }
    }
}

impl Real for f32 {
    const LANES: usize = 16;
    /// f32 rounding (6e-8) times 1e6 leaves q̈ about one correct digit.
    const COND_MAX: f64 = 1e6;
    #[inline(always)]
    fn of(x: f64) -> f32 {
        x as f32
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
        if FMA {
            a.mul_add(b, c)
        } else {
            a * b + c
        }
    }
    #[inline(always)]
    fn sqrt(self) -> f32 {
        f32::sqrt(self)
    }
    #[inline(always)]
    fn sin_cos(self) -> (f32, f32) {
        math32::sin_cos(self)
    }
    #[inline(always)]
    fn softplus_sigmoid(self) -> (f32, f32) {
        math32::softplus_sigmoid(self)
    }
    #[inline(always)]
    fn tanh_tangent<const FMA: bool, const WIDE: bool>(a: &mut [f32], width: usize, nt: usize) {
        math32::tanh_tangent::<FMA, WIDE>(a, width, nt)
    }
    #[inline(always)]
    fn dot8_wide<const FMA: bool, const WIDE: bool>(w: &[f32], x: &[f32]) -> f32 {
        crate::mlp::dot8::<f32, FMA>(w, x)
    }
    #[inline(always)]
    fn min(self, o: f32) -> f32 {
        f32::min(self, o)
    }
    #[inline(always)]
    fn max(self, o: f32) -> f32 {
        f32::max(self, o)
    }
    fn z_bias(m: &Model, ws: &mut Workspace<f32>) {
        crate::delan::z_bias_dispatch32(m.simd, m, ws)
    }
    fn nets(m: &Model) -> [Option<&Mlp<f32>>; 3] {
        m.nets_f32.each_ref().map(|n| n.as_ref())
    }

    #[cfg(target_arch = "x86_64")]
    type Zmm = std::arch::x86_64::__m512;
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zsplat(x: f32) -> Self::Zmm {
        unsafe { std::arch::x86_64::_mm512_set1_ps(x) }
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zload(p: *const f32) -> Self::Zmm {
        unsafe { std::arch::x86_64::_mm512_loadu_ps(p) }
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zstore(p: *mut f32, v: Self::Zmm) {
        unsafe { std::arch::x86_64::_mm512_storeu_ps(p, v) }
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn zfmadd(a: Self::Zmm, b: Self::Zmm, c: Self::Zmm) -> Self::Zmm {
        unsafe { std::arch::x86_64::_mm512_fmadd_ps(a, b, c) }
    }
}
