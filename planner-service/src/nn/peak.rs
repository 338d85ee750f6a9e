//! The machine's peak multiply-add rate per core, measured at the start of a benchmark so that
//! every throughput can be printed as a fraction of what this CPU can do.
//!
//! The loop (`fma_chains`, `dpbf16_chains` below) keeps 12 independent
//! accumulators, each updated by a 512-bit `VFMADD` (f32) or `VDPBF16PS` (bf16 pairs) per
//! iteration, enough independent chains to hide the instruction's latency so that only the
//! FMA ports limit the rate; the same with 256-bit FMAs for the AVX2 path. The AMX loop
//! keeps four 16 × 16 f32 accumulator tiles and two operand tiles of each kind in registers
//! and issues `TDPBF16PS` on them round-robin (16 · 16 · 32 multiply-adds each), the matrix
//! unit's own limit. A loop with fewer chains measures latency, not throughput: the
//! project's earlier "85 % of the FMA peak" rested on such a loop and was half the real peak.
//!
//! The time is the calling thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), not wall time, so
//! another process taking the core away does not lower the measured peak; the best of several
//! trials is kept. Where the CPU lacks AVX-512 (or AVX-512 BF16) the corresponding peak is
//! `None`: the kernels then run a different instruction mix and no 512-bit peak applies.

use super::cputime::thread_cpu_time;
use crate::nn::KernelPath;

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
    /// AMX `TDPBF16PS`; `None` without AMX-BF16 tiles.
    pub amx_gflops: Option<f64>,
    /// 256-bit f32 FMA; `None` without AVX2 and FMA.
    pub avx2_gflops: Option<f64>,
}

impl Peak {
    /// Measures both peaks on the calling thread (about 0.3 s on an idle core).
    pub fn measure() -> Self {
        let f32_ok = avx512();
        let bf16_ok = crate::nn::simd::bf16_dot_available();
        // SAFETY (both closures): each runs only where its instructions were detected above.
        let mut f32_peak = Best::new(f32_ok);
        let mut bf16_peak = Best::new(bf16_ok);
        let mut amx_peak = Best::new(KernelPath::AmxBf16.is_available());
        let mut avx2_peak = Best::new(KernelPath::Avx2F32.is_available());
        for trial in 0..=TRIALS {
            let warm_up = trial == 0; // clock ramp-up, the 512-bit units powering on
            f32_peak.run(warm_up, || unsafe { x86::fma_chains(ITERATIONS) });
            bf16_peak.run(warm_up, || unsafe { x86::dpbf16_chains(ITERATIONS) });
            avx2_peak.run(warm_up, || unsafe { x86::fma256_chains(ITERATIONS) });
            // A tile product is 16 · 16 · 32 multiply-adds: a sixth of the loop's rounds
            // takes about as long as the vector loops.
            amx_peak.run(warm_up, || unsafe { x86::amx_tiles(ITERATIONS / 6) });
        }
        Self {
            f32_gflops: f32_peak.rate,
            bf16_gflops: bf16_peak.rate,
            amx_gflops: amx_peak.rate,
            avx2_gflops: avx2_peak.rate,
        }
    }

    /// The peak of one core on a kernel path (`None` where unmeasured; the scalar path has
    /// none).
    pub fn for_path(&self, path: KernelPath) -> Option<f64> {
        match path {
            KernelPath::AmxBf16 => self.amx_gflops,
            KernelPath::Avx512Bf16 => self.bf16_gflops,
            KernelPath::Avx512F32 => self.f32_gflops,
            KernelPath::Avx2F32 => self.avx2_gflops,
            KernelPath::ScalarF32 => None,
        }
    }

    /// The f32 FMA peak of the widest vectors the kernels use at `level` (AVX2's on a CPU
    /// without AVX-512; `None` for the portable loops).
    pub fn f32_at(&self, level: crate::nn::simd::SimdLevel) -> Option<f64> {
        use crate::nn::simd::SimdLevel;
        match level {
            SimdLevel::Avx512 => self.f32_gflops,
            SimdLevel::Avx2 => self.avx2_gflops,
            SimdLevel::Scalar => None,
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
            amx_gflops: max(self.amx_gflops, other.amx_gflops),
            avx2_gflops: max(self.avx2_gflops, other.avx2_gflops),
        }
    }
}

impl std::fmt::Display for Peak {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let show =
            |g: Option<f64>| g.map_or("unavailable".to_string(), |g| format!("{g:.1} GFLOP/s"));
        write!(
            f,
            "measured peak per core: AMX bf16 tiles {}, bf16 dot {}, f32 FMA {}, AVX2 f32 FMA \
             {} ({CHAINS} independent 512-bit or 256-bit accumulators, 4 accumulator tiles; \
             thread CPU time)",
            show(self.amx_gflops),
            show(self.bf16_gflops),
            show(self.f32_gflops),
            show(self.avx2_gflops)
        )
    }
}

/// Whether the vector units keep their rate while the AMX tile unit multiplies: a round of four
/// `TDPBF16PS` alone, and two amounts of independent 512-bit FMAs (one and two FMA ports' worth
/// for the round's 64 cycles where a tile product issues every 16) alone and interleaved with
/// the tile products (a quarter after each), in nanoseconds of thread CPU time per round, best
/// of several trials.
///
/// This is what decides whether a tile kernel can hide its epilogue (bias, activation, bf16
/// conversion: vector work on every output element) behind the next block's products: where
/// the vector work interleaved takes no longer than the tiles alone it is hidden; where it
/// takes its own time on top, the tile unit and the vectors share an execution port.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileOverlap {
    pub tiles_ns: f64,
    /// Per amount of FMAs ([`OVERLAP_FMAS`]): alone, and interleaved with the tiles.
    pub fmas: [(f64, f64); 2],
}

/// 512-bit FMAs per round in the two measurements of [`TileOverlap`].
pub const OVERLAP_FMAS: [usize; 2] = [64, 128];

impl TileOverlap {
    /// Measures the loops on the calling thread (about 0.1 s); `None` without AMX-BF16 tiles
    /// or a thread CPU clock.
    pub fn measure() -> Option<Self> {
        if !KernelPath::AmxBf16.is_available() || thread_cpu_time().is_none() {
            return None;
        }
        const ROUNDS: u64 = 20_000;
        let best = |f: &dyn Fn()| {
            let mut best = f64::INFINITY;
            for trial in 0..=30 {
                let before = thread_cpu_time()?;
                f();
                let spent = thread_cpu_time()?.saturating_sub(before).as_secs_f64();
                if trial > 0 {
                    best = best.min(spent * 1e9 / ROUNDS as f64);
                }
            }
            Some(best)
        };
        // SAFETY (every closure): AMX-BF16 tiles are available (checked above), and every CPU
        // with them has AVX-512 F.
        Some(Self {
            tiles_ns: best(&|| unsafe { x86::tiles_beside_fmas::<true, 0>(ROUNDS) })?,
            fmas: [
                (
                    best(&|| unsafe { x86::tiles_beside_fmas::<false, 2>(ROUNDS) })?,
                    best(&|| unsafe { x86::tiles_beside_fmas::<true, 2>(ROUNDS) })?,
                ),
                (
                    best(&|| unsafe { x86::tiles_beside_fmas::<false, 4>(ROUNDS) })?,
                    best(&|| unsafe { x86::tiles_beside_fmas::<true, 4>(ROUNDS) })?,
                ),
            ],
        })
    }

    /// The share of the `i`-th amount's vector time that the tile products hid: 1 where the two
    /// ran side by side, 0 where they took turns.
    pub fn hidden(&self, i: usize) -> f64 {
        let (alone, both) = self.fmas[i];
        ((self.tiles_ns + alone - both) / alone.min(self.tiles_ns)).clamp(0.0, 1.0)
    }
}

impl std::fmt::Display for TileOverlap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "tile unit beside vector work, ns per round: 4 TDPBF16PS {:.1}",
            self.tiles_ns
        )?;
        for (i, (count, (alone, both))) in OVERLAP_FMAS.iter().zip(self.fmas).enumerate() {
            write!(
                f,
                "; {count} 512-bit FMAs {alone:.1}, interleaved with the tiles {both:.1} ({:.0}% \
                 hidden)",
                100.0 * self.hidden(i)
            )?;
        }
        Ok(())
    }
}

static BACKGROUND: std::sync::OnceLock<Peak> = std::sync::OnceLock::new();

/// Measures the peaks once on a low-priority background thread (the daemon's start; about a
/// second of one core), for [`background_peak`]. Later calls do nothing.
pub fn measure_in_background() {
    static STARTED: std::sync::Once = std::sync::Once::new();
    STARTED.call_once(|| {
        let spawned = std::thread::Builder::new().name("peak".into()).spawn(|| {
            let _ = BACKGROUND.set(Peak::measure());
        });
        if let Err(e) = spawned {
            tracing::warn!("could not start the peak measurement: {e}");
        }
    });
}

/// The peaks [`measure_in_background`] measured, once it has.
pub fn background_peak() -> Option<Peak> {
    BACKGROUND.get().copied()
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

    /// `iterations` rounds of one 256-bit FMA on each of [`CHAINS`] accumulators.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn fma256_chains(iterations: u64) -> f64 {
        let a = _mm256_set1_ps(black_box(1.000_000_1));
        let b = _mm256_set1_ps(black_box(0.999_999_9));
        let mut acc: [__m256; CHAINS] = std::array::from_fn(|i| _mm256_set1_ps(0.001 * i as f32));
        for _ in 0..iterations {
            for x in &mut acc {
                *x = _mm256_fmadd_ps(*x, a, b);
            }
        }
        let mut lanes = [0.0f32; 8];
        for x in acc {
            let mut v = [0.0f32; 8];
            // SAFETY: 8 floats of stack memory.
            unsafe { _mm256_storeu_ps(v.as_mut_ptr(), x) };
            for (l, v) in lanes.iter_mut().zip(v) {
                *l += v;
            }
        }
        black_box(lanes);
        (iterations * CHAINS as u64 * 8 * 2) as f64
    }

    /// 64-byte aligned 1 KiB, a tile's worth.
    #[repr(align(64))]
    struct Operand([u32; 256]);

    /// Configures all eight tiles full (16 × 64 bytes), zeroes the accumulators 0–3 and loads
    /// the operand tiles 4–7 with bf16 1.0 pairs.
    ///
    /// # Safety
    /// AMX-BF16 tiles must be available (`amx::available`).
    unsafe fn start_tiles() {
        use crate::nn::amx::{TileConfig, tile};
        let mut config = TileConfig::new();
        for t in 0..8 {
            config = config.with_tile(t, 16, 64);
        }
        let ones = Operand([0x3f80_3f80; 256]);
        // SAFETY: tiles available (the caller's contract); each load covers the 1 KiB array.
        unsafe {
            tile::load_config(&config);
            tile::zero::<0>();
            tile::zero::<1>();
            tile::zero::<2>();
            tile::zero::<3>();
            tile::load::<4>(ones.0.as_ptr().cast(), 64);
            tile::load::<5>(ones.0.as_ptr().cast(), 64);
            tile::load::<6>(ones.0.as_ptr().cast(), 64);
            tile::load::<7>(ones.0.as_ptr().cast(), 64);
        }
    }

    /// `iterations` rounds of four `TDPBF16PS` on accumulator tiles 0–3 from operand tiles
    /// 4, 5 (`A`) and 6, 7 (`B`), every tile full (16 × 64 bytes); returns the flops.
    ///
    /// # Safety
    /// AMX-BF16 tiles must be available (`amx::available`).
    pub(super) unsafe fn amx_tiles(iterations: u64) -> f64 {
        use crate::nn::amx::tile;
        let mut out = Operand([0; 256]);
        // SAFETY: tiles available (the caller's contract); the store covers a 1 KiB array.
        unsafe {
            start_tiles();
            for _ in 0..black_box(iterations) {
                tile::dpbf16ps::<0, 4, 6>();
                tile::dpbf16ps::<1, 4, 7>();
                tile::dpbf16ps::<2, 5, 6>();
                tile::dpbf16ps::<3, 5, 7>();
            }
            tile::store::<0>(out.0.as_mut_ptr().cast(), 64);
            tile::release();
        }
        black_box(&out);
        (iterations * 4 * 16 * 16 * 32 * 2) as f64
    }

    /// `rounds` of four `TDPBF16PS` (when `TILES`), each followed by `DEPTH` FMAs on each of
    /// eight independent accumulators.
    ///
    /// # Safety
    /// AMX-BF16 tiles and AVX-512 F must be available.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn tiles_beside_fmas<const TILES: bool, const DEPTH: usize>(rounds: u64) {
        use crate::nn::amx::tile;
        let a = _mm512_set1_ps(black_box(1.000_000_1));
        let b = _mm512_set1_ps(black_box(0.999_999_9));
        let mut acc: [__m512; 8] = std::array::from_fn(|i| _mm512_set1_ps(0.001 * i as f32));
        let fmas = |acc: &mut [__m512; 8]| {
            for _ in 0..DEPTH {
                for x in acc.iter_mut() {
                    *x = _mm512_fmadd_ps(*x, a, b);
                }
            }
        };
        // SAFETY: the caller's contract.
        unsafe {
            start_tiles();
            for _ in 0..black_box(rounds) {
                if TILES {
                    tile::dpbf16ps::<0, 4, 6>();
                }
                fmas(&mut acc);
                if TILES {
                    tile::dpbf16ps::<1, 4, 7>();
                }
                fmas(&mut acc);
                if TILES {
                    tile::dpbf16ps::<2, 5, 6>();
                }
                fmas(&mut acc);
                if TILES {
                    tile::dpbf16ps::<3, 5, 7>();
                }
                fmas(&mut acc);
            }
            tile::release();
        }
        black_box(acc.iter().map(|&x| _mm512_reduce_add_ps(x)).sum::<f32>());
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
    pub(super) unsafe fn fma256_chains(_: u64) -> f64 {
        unreachable!("AVX2 is never detected off x86-64")
    }
    pub(super) unsafe fn amx_tiles(_: u64) -> f64 {
        unreachable!("AMX is never detected off x86-64")
    }
    pub(super) unsafe fn tiles_beside_fmas<const TILES: bool, const DEPTH: usize>(_: u64) {
        unreachable!("AMX is never detected off x86-64")
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
            peak.amx_gflops.is_some(),
            KernelPath::AmxBf16.is_available() && thread_cpu_time().is_some()
        );
        assert_eq!(peak.for_path(KernelPath::Avx512Bf16), peak.bf16_gflops);
        assert_eq!(peak.for_path(KernelPath::AmxBf16), peak.amx_gflops);
        assert!(peak.to_string().contains("measured peak per core"));
        let low = Peak {
            f32_gflops: Some(1.0),
            bf16_gflops: None,
            amx_gflops: None,
            avx2_gflops: Some(0.5),
        };
        let high = Peak {
            f32_gflops: Some(2.0),
            bf16_gflops: Some(3.0),
            amx_gflops: Some(30.0),
            avx2_gflops: Some(1.0),
        };
        assert_eq!(low.max(high), high);
        assert_eq!(high.max(low), high);
        assert_eq!(percent(50.0, Some(200.0)), "25%");
        assert_eq!(percent(50.0, None), "-");
    }

    #[test]
    fn the_tile_overlap_probe_runs_where_tiles_exist() {
        let overlap = TileOverlap::measure();
        assert_eq!(
            overlap.is_some(),
            KernelPath::AmxBf16.is_available() && thread_cpu_time().is_some()
        );
        if let Some(o) = overlap {
            assert!(o.tiles_ns.is_finite() && o.tiles_ns > 0.0, "{o:?}");
            // How the two loops overlap is the hardware's (and the build's) business, not a
            // property to assert: on a Xeon with AMX the test build's tile loop has run slower
            // alone than interleaved with FMAs. What the probe promises is finite times and a
            // share hidden between 0 and 1.
            for (i, (alone, both)) in o.fmas.into_iter().enumerate() {
                assert!(alone.is_finite() && alone > 0.0, "{o:?}");
                assert!(both.is_finite() && both > 0.0, "{o:?}");
                assert!((0.0..=1.0).contains(&o.hidden(i)));
            }
            // Twice the FMAs take longer alone (best of 30 trials each, so one preempted
            // trial does not decide it).
            assert!(o.fmas[1].0 > o.fmas[0].0, "{o:?}");
        }
        let measured = TileOverlap {
            tiles_ns: 17.0,
            fmas: [(8.5, 17.0), (17.0, 34.0)],
        };
        assert_eq!((measured.hidden(0), measured.hidden(1)), (1.0, 0.0));
        let text = measured.to_string();
        assert!(
            text.contains("64 512-bit FMAs 8.5, interleaved with the tiles 17.0 (100% hidden)"),
            "{text}"
        );
        assert!(text.contains("(0% hidden)"), "{text}");
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
        if KernelPath::AmxBf16.is_available() {
            // SAFETY: AMX detected.
            assert_eq!(unsafe { x86::amx_tiles(10) }, (10 * 4 * 8192 * 2) as f64);
        }
        // A CPU without either instruction reports no peak for it (checked above).
        assert!(avx512() || Peak::measure().f32_gflops.is_none());
    }
}
