//! The machine's peak multiply-add rate per core, measured at the start of a benchmark so that
//! every throughput can be printed as a fraction of what this CPU can do.
//!
//! The loop (`fma_chains`, `dpbf16_chains` below) keeps 12 independent
//! accumulators, each updated by a 512-bit `VFMADD` (f32) or `VDPBF16PS` (bf16 pairs) per
//! iteration, enough independent chains to hide the instruction's latency so that only the
//! FMA ports limit the rate. A loop with fewer chains measures latency, not throughput: the
//! project's earlier "85 % of the FMA peak" rested on such a loop and was half the real peak.
//!
//! The time is the calling thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), not wall time, so
//! another process taking the core away does not lower the measured peak; the best of several
//! trials is kept. Where the CPU lacks AVX-512 (or AVX-512 BF16) the corresponding peak is
//! `None`: the kernels then run a different instruction mix and no 512-bit peak applies.

use super::cputime::thread_cpu_time;

/// Independent accumulators: enough chains to hide the FMA's latency.
const CHAINS: usize = 12;
/// Loop iterations per trial: 12 · 16 lanes · 2 flops each, ≈ 1 ms at 230 GFLOP/s. Short
/// trials, because on a shared machine (or a virtual CPU whose physical core is shared) the best
/// of many short ones is the likeliest to have found an undisturbed stretch.
const ITERATIONS: u64 = 60_000;
/// Trials per instruction, f32 and bf16 alternating so that both see the same conditions; the
/// fastest of each is kept.
const TRIALS: usize = 150;

/// Measured peak GFLOP/s of one core (a multiply and an add count as two operations; a
/// `VDPBF16PS` does two multiply-adds per 32-bit lane).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Peak {
    /// 512-bit f32 FMA; `None` without AVX-512.
    pub f32_gflops: Option<f64>,
    /// 512-bit `VDPBF16PS`; `None` without AVX-512 BF16.
    pub bf16_gflops: Option<f64>,
}

impl Peak {
    /// Measures both peaks on the calling thread (about 0.3 s on an idle core).
    pub fn measure() -> Self {
        let f32_ok = avx512();
        let bf16_ok = crate::nn::simd::bf16_dot_available();
        // SAFETY (both closures): each runs only where its instructions were detected above.
        let mut f32_peak = Best::new(f32_ok);
        let mut bf16_peak = Best::new(bf16_ok);
        for trial in 0..=TRIALS {
            let warm_up = trial == 0; // clock ramp-up, the 512-bit units powering on
            f32_peak.run(warm_up, || unsafe { x86::fma_chains(ITERATIONS) });
            bf16_peak.run(warm_up, || unsafe { x86::dpbf16_chains(ITERATIONS) });
        }
        Self {
            f32_gflops: f32_peak.rate,
            bf16_gflops: bf16_peak.rate,
        }
    }

    /// The higher of two measurements of each peak (e.g. one before and one after the timed
    /// work: the less disturbed one is nearer the truth).
    pub fn max(self, other: Self) -> Self {
        let max = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        };
        Self {
            f32_gflops: max(self.f32_gflops, other.f32_gflops),
            bf16_gflops: max(self.bf16_gflops, other.bf16_gflops),
        }
    }

    /// The peak of one core for inference in `precision` (`None` where unmeasured).
    pub fn for_precision(&self, precision: proto::InferencePrecision) -> Option<f64> {
        match precision {
            proto::InferencePrecision::F32 => self.f32_gflops,
            proto::InferencePrecision::Bf16 => self.bf16_gflops,
        }
    }
}

impl std::fmt::Display for Peak {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let show = |g: Option<f64>| g.map_or("unavailable".to_string(), |g| format!("{g:.1}"));
        write!(
            f,
            "measured peak per core: f32 FMA {} GFLOP/s, bf16 dot {} GFLOP/s \
             ({CHAINS} independent 512-bit accumulators, thread CPU time)",
            show(self.f32_gflops),
            show(self.bf16_gflops)
        )
    }
}

/// Whether this CPU runs AVX-512 F (the kernels' widest level).
fn avx512() -> bool {
    crate::nn::simd::level() == crate::nn::simd::SimdLevel::Avx512
}

/// `part / whole` as a percentage for reports, `-` where the peak is unknown.
pub fn percent(part: f64, whole: Option<f64>) -> String {
    whole.map_or("-".to_string(), |w| format!("{:.0}%", 100.0 * part / w))
}

/// The fastest rate seen over trials of one instruction's loop.
struct Best {
    enabled: bool,
    rate: Option<f64>,
}

impl Best {
    fn new(enabled: bool) -> Self {
        Self {
            enabled,
            rate: None,
        }
    }

    /// Runs `trial` (which returns the flops it did) if enabled and keeps its rate unless this
    /// is the warm-up or the thread's CPU time cannot be read.
    fn run(&mut self, warm_up: bool, trial: impl FnOnce() -> f64) {
        if !self.enabled {
            return;
        }
        let before = thread_cpu_time();
        let flops = trial();
        let Some((before, after)) = before.zip(thread_cpu_time()) else {
            return;
        };
        let spent = after.saturating_sub(before).as_secs_f64();
        if !warm_up && spent > 0.0 {
            let rate = flops / spent / 1e9;
            self.rate = Some(self.rate.map_or(rate, |b| b.max(rate)));
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::CHAINS;
    use std::arch::x86_64::*;
    use std::hint::black_box;

    /// `iterations` rounds of one FMA on each of [`CHAINS`] accumulators; returns the flops.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn fma_chains(iterations: u64) -> f64 {
        let a = _mm512_set1_ps(black_box(1.000_000_1));
        let b = _mm512_set1_ps(black_box(0.999_999_9));
        let mut acc: [__m512; CHAINS] = std::array::from_fn(|i| _mm512_set1_ps(0.001 * i as f32));
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm512_fmadd_ps(*x, a, b);
            }
        }
        let sum: f32 = acc.iter().map(|&x| _mm512_reduce_add_ps(x)).sum();
        black_box(sum);
        (iterations * CHAINS as u64 * 16 * 2) as f64
    }

    /// `iterations` rounds of one `VDPBF16PS` on each of [`CHAINS`] accumulators; returns the
    /// flops (32 multiply-adds per instruction).
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
    pub(super) unsafe fn dpbf16_chains(iterations: u64) -> f64 {
        // bf16 1.0 in every half-word.
        let one: __m512bh = unsafe { std::mem::transmute(_mm512_set1_epi16(black_box(0x3f80))) };
        let mut acc = [_mm512_setzero_ps(); CHAINS];
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm512_dpbf16_ps(*x, one, one);
            }
        }
        let sum: f32 = acc.iter().map(|&x| _mm512_reduce_add_ps(x)).sum();
        black_box(sum);
        (iterations * CHAINS as u64 * 32 * 2) as f64
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod x86 {
    pub(super) unsafe fn fma_chains(_: u64) -> f64 {
        unreachable!("AVX-512 is never detected off x86-64")
    }
    pub(super) unsafe fn dpbf16_chains(_: u64) -> f64 {
        unreachable!("AVX-512 BF16 is never detected off x86-64")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measures_a_positive_peak_where_the_instructions_exist() {
        let peak = Peak::measure();
        assert_eq!(
            peak.f32_gflops.is_some(),
            avx512() && thread_cpu_time().is_some()
        );
        assert_eq!(
            peak.bf16_gflops.is_some(),
            crate::nn::simd::bf16_dot_available() && thread_cpu_time().is_some()
        );
        for g in [peak.f32_gflops, peak.bf16_gflops].into_iter().flatten() {
            assert!(g.is_finite() && g > 0.0, "{peak:?}");
        }
        assert_eq!(
            peak.for_precision(proto::InferencePrecision::Bf16),
            peak.bf16_gflops
        );
        assert!(peak.to_string().contains("measured peak per core"));
        let low = Peak {
            f32_gflops: Some(1.0),
            bf16_gflops: None,
        };
        let high = Peak {
            f32_gflops: Some(2.0),
            bf16_gflops: Some(3.0),
        };
        assert_eq!(low.max(high), high);
        assert_eq!(high.max(low), high);
        assert_eq!(percent(50.0, Some(200.0)), "25%");
        assert_eq!(percent(50.0, None), "-");
    }

    #[test]
    fn counts_the_flops_of_every_chain() {
        if avx512() {
            // SAFETY: AVX-512 F detected.
            assert_eq!(unsafe { x86::fma_chains(10) }, (10 * 12 * 16 * 2) as f64);
        }
        if crate::nn::simd::bf16_dot_available() {
            // SAFETY: AVX-512 BF16 detected.
            assert_eq!(unsafe { x86::dpbf16_chains(10) }, (10 * 12 * 32 * 2) as f64);
        }
        // A CPU without either instruction reports no peak for it (checked above).
        assert!(avx512() || Peak::measure().f32_gflops.is_none());
    }
}
