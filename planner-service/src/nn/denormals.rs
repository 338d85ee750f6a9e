//! Flush-to-zero for training threads.
//!
//! Softplus networks trained with the DEEN double backprop produce denormal numbers: products
//! of `σ''(z) = σ(z)(1 − σ(z))` at saturated units with small upstream gradients underflow
//! into the denormal range, and x86 handles every denormal operand or result in microcode,
//! up to 100× slower per instruction. Such values are far below anything that can change an
//! `f32` weight, so training threads set MXCSR's flush-to-zero (bit 15: denormal results become
//! 0) and denormals-are-zero (bit 6: denormal inputs read as 0) for the duration of a fit,
//! through [`FlushDenormals`], and restore the previous mode afterwards.

/// MXCSR bits: flush-to-zero (15) and denormals-are-zero (6).
#[cfg(target_arch = "x86_64")]
const FTZ_DAZ: u32 = (1 << 15) | (1 << 6);

/// The calling thread's floating-point control word (MXCSR; 0 on other architectures).
pub fn current_mode() -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        let mut csr: u32 = 0;
        // SAFETY: `stmxcsr` stores the 32-bit control register to the given, valid address.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack, preserves_flags))
        };
        csr
    }
    #[cfg(not(target_arch = "x86_64"))]
    0
}

fn set_mode(csr: u32) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: `ldmxcsr` loads a control word previously read from MXCSR (possibly with the
    // FTZ/DAZ bits, which every x86-64 CPU supports), so no reserved bit is set.
    unsafe {
        std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack, preserves_flags, readonly))
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = csr;
}

/// Runs `f` with the floating-point control word `mode`, then restores this thread's own.
/// Used to carry a training thread's mode to the rayon helpers it hands work to.
pub fn with_mode<R>(mode: u32, f: impl FnOnce() -> R) -> R {
    let saved = current_mode();
    set_mode(mode);
    let out = f();
    set_mode(saved);
    out
}

/// While alive, denormal results and inputs are flushed to zero on this thread.
#[derive(Debug)]
#[must_use = "the mode is restored when the guard drops"]
pub struct FlushDenormals {
    saved: u32,
}

impl FlushDenormals {
    pub fn new() -> Self {
        let saved = current_mode();
        #[cfg(target_arch = "x86_64")]
        set_mode(saved | FTZ_DAZ);
        Self { saved }
    }
}

impl Default for FlushDenormals {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for FlushDenormals {
    fn drop(&mut self) {
        set_mode(self.saved);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn guard_flushes_denormals_and_restores() {
        let tiny = std::hint::black_box(f32::MIN_POSITIVE);
        let half = std::hint::black_box(0.5f32);
        assert!((tiny * half).is_subnormal());
        let before = current_mode();
        {
            let _guard = FlushDenormals::new();
            assert_eq!(std::hint::black_box(tiny) * std::hint::black_box(half), 0.0);
            let inner = with_mode(before, || {
                std::hint::black_box(tiny) * std::hint::black_box(half)
            });
            assert!(inner.is_subnormal(), "with_mode applies the given mode");
            assert_eq!(
                std::hint::black_box(tiny) * std::hint::black_box(half),
                0.0,
                "and restores"
            );
        }
        assert_eq!(current_mode(), before);
        assert!((std::hint::black_box(tiny) * half).is_subnormal());
    }
}
