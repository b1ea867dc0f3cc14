//! Run-time choice of 256-bit vector code: the build stays generic (x86-64 baseline), and a kernel
//! written as plain loops over arrays is compiled a second time with AVX2 enabled and taken when the
//! CPU has it.
//!
//! A kernel is compiled the second time either through [`run_simd`] (a closure marked
//! `#[inline(always)]`: the structured-light triangulator's rows and the phase decoder's bands) or,
//! where the closure left the loop unvectorised, as a `#[target_feature(enable = "avx2")]` method of
//! its own (depth fusion's `SlabFusion::fuse_avx2`); both are taken on [`has_avx2`].
//!
//! Only AVX2 is enabled, not FMA: the compiler never fuses a multiply and an add on its own, so both
//! copies round every operation the same and a result does not depend on the CPU that computed it.

/// True when the CPU runs AVX2 (checked at run time).
pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f`, compiled with AVX2 enabled when `avx2` is set. `f` must be a closure marked
/// `#[inline(always)]` and the kernels it calls `#[inline(always)]` too, so that all of it is
/// compiled into the AVX2 copy (a large closure is otherwise left out of line, compiled for the
/// baseline); `avx2` must come from [`has_avx2`] (or be false).
#[inline(always)]
pub(crate) fn run_simd<T>(avx2: bool, f: impl FnOnce() -> T) -> T {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        #[target_feature(enable = "avx2")]
        unsafe fn with_avx2<T>(f: impl FnOnce() -> T) -> T {
            f()
        }
        // SAFETY: `avx2` is only set when the CPU runs AVX2 (`has_avx2`).
        return unsafe { with_avx2(f) };
    }
    let _ = avx2;
    f()
}
