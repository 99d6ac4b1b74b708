//! The instruction-set level of the hot loops, chosen once per model from the CPU.
//!
//! Every kernel is written once, generic over `FMA` (fused multiply-add) and `WIDE` (512-bit
//! registers: wider register blocks), and compiled per level inside a `#[target_feature]` function
//! by [`simd_dispatch!`]. The AVX-512 and AVX2 paths compute every sum in the same order with the
//! same fused operations, so they agree bit for bit; the portable path (separate multiply and add)
//! may differ from them in the last bits.

/// Instruction-set level of the hot loops.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Simd {
    /// Plain SSE2, separate multiply and add.
    Portable,
    /// AVX2 with fused multiply-add.
    Avx2Fma,
    /// AVX-512 (F) with fused multiply-add: the AVX2 arithmetic in 8-wide registers.
    Avx512,
}

impl Simd {
    /// The name Python sees (`Engine.simd`).
    pub fn name(self) -> &'static str {
        match self {
            Simd::Portable => "portable",
            Simd::Avx2Fma => "avx2-fma",
            Simd::Avx512 => "avx512",
        }
    }
}

/// The best level this CPU runs. `EXOLAN_PORTABLE=1` forces the portable path, `EXOLAN_NO_AVX512=1`
/// caps it at AVX2.
pub fn detect() -> Simd {
    #[cfg(target_arch = "x86_64")]
    {
        if std::env::var_os("EXOLAN_PORTABLE").is_some() {
            return Simd::Portable;
        }
        if !(std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")) {
            return Simd::Portable;
        }
        if std::is_x86_feature_detected!("avx512f") && std::env::var_os("EXOLAN_NO_AVX512").is_none() {
            return Simd::Avx512;
        }
        return Simd::Avx2Fma;
    }
    #[allow(unreachable_code)]
    Simd::Portable
}

/// `simd_dispatch!(vis fn name(args) -> ret = generic);` defines `name(simd: Simd, args) -> ret`,
/// which runs `generic::<FMA, WIDE>(args)` compiled for the level's target features.
macro_rules! simd_dispatch {
    ($vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? = $generic:ident;) => {
        $vis fn $name(simd: $crate::simd::Simd, $($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn avx2($($arg: $ty),*) $(-> $ret)? {
                    $generic::<true, false>($($arg),*)
                }
                #[target_feature(enable = "avx512f,avx2,fma")]
                unsafe fn avx512($($arg: $ty),*) $(-> $ret)? {
                    $generic::<true, true>($($arg),*)
                }
                match simd {
                    // SAFETY: a level above Portable is only chosen when the CPU reports its
                    // features (`simd::detect`, and `Model::set_simd` clamps to it).
                    $crate::simd::Simd::Avx512 => return unsafe { avx512($($arg),*) },
                    $crate::simd::Simd::Avx2Fma => return unsafe { avx2($($arg),*) },
                    $crate::simd::Simd::Portable => {}
                }
            }
            #[allow(unreachable_code)]
            $generic::<false, false>($($arg),*)
        }
    };
}
pub(crate) use simd_dispatch;
