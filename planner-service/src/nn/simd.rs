//! Runtime CPU dispatch for the hot numeric loops.
//!
//! The crate is built for baseline x86-64 (SSE2) so the binary runs anywhere, but the networks
//! spend their time in activations, elementwise products and matrix kernels that are 4–8× faster
//! with AVX2/AVX-512. Each hot loop is written once as an `#[inline(always)]` body of plain
//! loops that LLVM vectorises; `multiversion!` compiles that body three times (AVX-512, AVX2+FMA,
//! baseline) and picks one at run time from [`level`], detected once per process.

use std::sync::atomic::{AtomicU8, Ordering};

/// The instruction-set level a dispatched function runs at.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum SimdLevel {
    /// Baseline x86-64 (or another architecture): whatever the compiler does with SSE2.
    Scalar,
    /// AVX2 with FMA: 8 lanes, 16 vector registers.
    Avx2,
    /// AVX-512 F/VL: 16 lanes, 32 vector registers.
    Avx512,
}

impl SimdLevel {
    /// Every level this CPU can run, lowest first (tests exercise each one).
    pub fn available() -> Vec<SimdLevel> {
        let best = detect();
        [SimdLevel::Scalar, SimdLevel::Avx2, SimdLevel::Avx512]
            .into_iter()
            .filter(|l| *l <= best)
            .collect()
    }
}

const UNKNOWN: u8 = u8::MAX;
static DETECTED: AtomicU8 = AtomicU8::new(UNKNOWN);

fn detect() -> SimdLevel {
    #[cfg(target_arch = "x86_64")]
    {
        if is_x86_feature_detected!("avx512f")
            && is_x86_feature_detected!("avx512vl")
            && is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("fma")
        {
            return SimdLevel::Avx512;
        }
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            return SimdLevel::Avx2;
        }
    }
    SimdLevel::Scalar
}

fn from_u8(v: u8) -> SimdLevel {
    match v {
        2 => SimdLevel::Avx512,
        1 => SimdLevel::Avx2,
        _ => SimdLevel::Scalar,
    }
}

#[cfg(test)]
thread_local! {
    /// Tests force a lower level on their own thread to check every code path on one machine.
    static FORCED: std::cell::Cell<Option<SimdLevel>> = const { std::cell::Cell::new(None) };
}

/// Runs `f` with dispatch forced to `level` on this thread (tests only).
#[cfg(test)]
pub(crate) fn with_level<R>(level: SimdLevel, f: impl FnOnce() -> R) -> R {
    assert!(level <= detect(), "{level:?} is not supported by this CPU");
    FORCED.with(|c| c.set(Some(level)));
    let out = f();
    FORCED.with(|c| c.set(None));
    out
}

/// The level dispatched functions use: the best this CPU supports, detected once.
#[inline]
pub fn level() -> SimdLevel {
    #[cfg(test)]
    if let Some(forced) = FORCED.with(|c| c.get()) {
        return forced;
    }
    let v = DETECTED.load(Ordering::Relaxed);
    if v != UNKNOWN {
        return from_u8(v);
    }
    let l = detect();
    DETECTED.store(l as u8, Ordering::Relaxed);
    l
}

/// Whether this CPU multiplies bf16 pairs into f32 (`VDPBF16PS`, AVX-512 BF16) at the level
/// in use: then packed inference layers may run in bf16. Whether that is faster than f32 is
/// the CPU's business (twice the f32 rate on AMD Zen 5, half of it on Intel's AMX Xeons):
/// [`kernel_path`](crate::nn::kernel_path) measures it rather than assuming.
#[inline]
pub fn bf16_dot_available() -> bool {
    static BF16: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    level() == SimdLevel::Avx512
        && *BF16.get_or_init(|| {
            #[cfg(target_arch = "x86_64")]
            {
                is_x86_feature_detected!("avx512bf16") && is_x86_feature_detected!("avx512bw")
            }
            #[cfg(not(target_arch = "x86_64"))]
            {
                false
            }
        })
}

/// Defines a function whose body is compiled for AVX-512, AVX2+FMA and baseline x86-64, and
/// dispatched at run time on [`level`]. The body must be safe code; it is inlined into each
/// `#[target_feature]` wrapper so LLVM vectorises it with the wider registers.
macro_rules! multiversion {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body($($arg: $ty),*) $(-> $ret)? $body

            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            fn avx512($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }

            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            fn avx2($($arg: $ty),*) $(-> $ret)? { body($($arg),*) }

            match $crate::nn::simd::level() {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `level()` reports AVX-512 only when the CPU has every enabled feature.
                $crate::nn::simd::SimdLevel::Avx512 => unsafe { avx512($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `level()` reports AVX2 only when the CPU has AVX2 and FMA.
                $crate::nn::simd::SimdLevel::Avx2 => unsafe { avx2($($arg),*) },
                _ => body($($arg),*),
            }
        }
    };
}
pub(crate) use multiversion;

#[cfg(test)]
mod tests {
    use super::*;

    multiversion! {
        fn double_all(x: &mut [f32]) -> usize {
            for v in x.iter_mut() {
                *v *= 2.0;
            }
            x.len()
        }
    }

    #[test]
    fn every_level_runs_the_same_body() {
        for l in SimdLevel::available() {
            let mut x = [1.0, -2.0, 3.5];
            let n = with_level(l, || double_all(&mut x));
            assert_eq!((n, x), (3, [2.0, -4.0, 7.0]), "{l:?}");
        }
        assert_eq!(SimdLevel::available()[0], SimdLevel::Scalar);
    }
}
