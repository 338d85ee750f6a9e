//! Which kernel runs a network's inference, chosen by measuring every kernel this CPU has on
//! the network's own layer shapes.
//!
//! What is fastest depends on the CPU far more than on the code: on AMD Zen 5 a 512-bit
//! `VDPBF16PS` does twice the multiply-adds of an f32 FMA per cycle, on the Intel Xeon with
//! AMX this project also runs on it does *half* (85 against 162 GFLOP/s per core), while the
//! AMX tile unit does ~2.7–3.0 TFLOP/s. Nothing here assumes any of that: [`choose`] times a
//! forward pass of the network through each available path for a fraction of a second and
//! keeps the fastest ([`Precision::Auto`], the default), unless a path of more exact numbers
//! comes within [`CLEAR_WIN`] of it (see [`Measurement::fastest`]). An explicit `f32` runs the widest f32
//! vector level unmeasured (exact f32 planning is a choice of numbers, not of speed); an
//! explicit `bf16` runs the faster, measured, of the bf16 paths.
//!
//! Measurements are cached per network shape for the life of the process, so an ensemble's
//! members and every retrained model of the same shape reuse the first one.

use super::Precision;
use super::activation::Activation;
use super::amx;
use super::matmul::{MatRef, PackedMatrix};
use super::mlp::{ForwardScratch, Mlp};
use super::simd::{SimdLevel, bf16_dot_available, level};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// One way to run a packed inference layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum KernelPath {
    /// AMX tiles, `TDPBF16PS` (bf16 operands, f32 sums).
    AmxBf16,
    /// 512-bit `VDPBF16PS` dot products (AVX-512 BF16).
    Avx512Bf16,
    /// 512-bit f32 FMA (AVX-512 F).
    Avx512F32,
    /// 256-bit f32 FMA (AVX2 + FMA).
    Avx2F32,
    /// Whatever the compiler makes of baseline x86-64 (or another architecture).
    ScalarF32,
}

impl KernelPath {
    /// Every path, fastest-looking first (the order is only for display).
    pub const ALL: [KernelPath; 5] = [
        KernelPath::AmxBf16,
        KernelPath::Avx512Bf16,
        KernelPath::Avx512F32,
        KernelPath::Avx2F32,
        KernelPath::ScalarF32,
    ];

    /// The name printed by benchmarks and `status`.
    pub fn name(self) -> &'static str {
        match self {
            KernelPath::AmxBf16 => "amx-bf16",
            KernelPath::Avx512Bf16 => "avx512-bf16",
            KernelPath::Avx512F32 => "avx512-f32",
            KernelPath::Avx2F32 => "avx2-f32",
            KernelPath::ScalarF32 => "scalar-f32",
        }
    }

    /// Whether this CPU (and operating system) can run the path.
    pub fn is_available(self) -> bool {
        match self {
            KernelPath::AmxBf16 => bf16_dot_available() && amx::available(),
            KernelPath::Avx512Bf16 => bf16_dot_available(),
            KernelPath::Avx512F32 => level() >= SimdLevel::Avx512,
            KernelPath::Avx2F32 => level() >= SimdLevel::Avx2,
            KernelPath::ScalarF32 => true,
        }
    }

    /// The paths this CPU can run.
    pub fn available() -> Vec<KernelPath> {
        Self::ALL.into_iter().filter(|p| p.is_available()).collect()
    }

    /// The number format of the path's operands.
    pub fn precision(self) -> Precision {
        match self {
            KernelPath::AmxBf16 | KernelPath::Avx512Bf16 => Precision::Bf16,
            _ => Precision::F32,
        }
    }

    /// The vector level the path's kernels (and its f32 fallback code) run at.
    pub(crate) fn level(self) -> SimdLevel {
        match self {
            KernelPath::AmxBf16 | KernelPath::Avx512Bf16 | KernelPath::Avx512F32 => {
                SimdLevel::Avx512
            }
            KernelPath::Avx2F32 => SimdLevel::Avx2,
            KernelPath::ScalarF32 => SimdLevel::Scalar,
        }
    }

    /// A layer's `Wᵀ` packed for this path.
    pub(crate) fn pack(self, wt: MatRef<'_>) -> PackedMatrix {
        match self {
            KernelPath::AmxBf16 => PackedMatrix::pack_bf16_tiles(wt),
            KernelPath::Avx512Bf16 => PackedMatrix::pack_bf16(wt),
            _ => PackedMatrix::pack(wt),
        }
    }

    /// The f32 path of the widest vector level this CPU has.
    fn widest_f32() -> KernelPath {
        match level() {
            SimdLevel::Avx512 => KernelPath::Avx512F32,
            SimdLevel::Avx2 => KernelPath::Avx2F32,
            SimdLevel::Scalar => KernelPath::ScalarF32,
        }
    }
}

impl std::fmt::Display for KernelPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A path's measured time for one forward pass of a network on [`BATCH`] samples.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Timing {
    pub path: KernelPath,
    /// Best time of one forward pass, in seconds.
    pub seconds: f64,
}

/// The measurement behind a choice: every candidate's best time, fastest first.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Measurement {
    pub sizes: Vec<usize>,
    pub timings: Vec<Timing>,
}

/// How much faster than a path of more exact numbers a path must be to be chosen over it.
/// Within this margin two paths are a tie that timing noise decides, and a run's numbers
/// (bf16-rounded operands or exact f32 products; or only another order of summation) would then
/// depend on the machine's load at start; a tie goes to the path [`PREFERENCE`] lists first.
/// Training's choice ([`train_path`](super::train_path)) follows the same rule.
pub const CLEAR_WIN: f64 = 0.15;

/// The order in which tied paths are preferred: exact f32 products before bf16 operands, and
/// within each number format the wider vectors first.
pub const PREFERENCE: [KernelPath; 5] = [
    KernelPath::Avx512F32,
    KernelPath::Avx2F32,
    KernelPath::ScalarF32,
    KernelPath::AmxBf16,
    KernelPath::Avx512Bf16,
];

impl Measurement {
    /// The path to run: the first in [`PREFERENCE`] that is no more than [`CLEAR_WIN`] slower
    /// than the fastest measured. Where one path is clearly fastest (AMX tiles 3–4× the f32
    /// kernels, `VDPBF16PS` twice them on Zen 5) that is the fastest.
    pub fn fastest(&self) -> KernelPath {
        let best = self.timings[0].seconds;
        PREFERENCE
            .iter()
            .filter_map(|&p| self.timings.iter().find(|t| t.path == p))
            .find(|t| t.seconds * (1.0 - CLEAR_WIN) <= best)
            .map_or(self.timings[0].path, |t| t.path)
    }
}

/// Samples per measured forward pass: a population chunk of the presets' size (200–250
/// candidates) rounded to the 16-sample panels.
pub const BATCH: usize = 256;

/// Time spent measuring one network shape, over all its candidate paths.
const BUDGET: Duration = Duration::from_millis(150);

/// The path a network of `sizes` with `activation` runs for `precision` (see the module
/// documentation): measured and cached for `Auto` and for `Bf16` with more than one bf16
/// path, the widest f32 level for `F32` and wherever bf16 is asked but missing.
pub fn choose(precision: Precision, sizes: &[usize], activation: Activation) -> KernelPath {
    let candidates: Vec<KernelPath> = match precision {
        Precision::F32 => return KernelPath::widest_f32(),
        Precision::Bf16 => KernelPath::available()
            .into_iter()
            .filter(|p| p.precision() == Precision::Bf16)
            .collect(),
        Precision::Auto => KernelPath::available(),
    };
    match candidates.len() {
        0 => KernelPath::widest_f32(),
        1 => candidates[0],
        _ => measured(sizes, activation, &candidates).fastest(),
    }
}

type Key = (Vec<usize>, Activation, Vec<KernelPath>);

/// Every measurement made in this process, by network shape and candidates.
static MEASURED: Mutex<Vec<(Key, Measurement)>> = Mutex::new(Vec::new());

/// The cached measurement of `candidates` on a network of `sizes`, made now if new.
pub fn measured(sizes: &[usize], activation: Activation, candidates: &[KernelPath]) -> Measurement {
    let key = (sizes.to_vec(), activation, candidates.to_vec());
    if let Some((_, m)) = lock().iter().find(|(k, _)| *k == key) {
        return m.clone();
    }
    let m = measure(sizes, activation, candidates, BUDGET);
    tracing::info!(
        "kernel paths for a {sizes:?} network: {} (chosen: {})",
        m.timings
            .iter()
            .map(|t| format!("{} {:.0} µs", t.path, t.seconds * 1e6))
            .collect::<Vec<_>>()
            .join(", "),
        m.fastest()
    );
    lock().push((key, m.clone()));
    m
}

/// Every measurement made so far in this process (for `status` and benchmarks).
pub fn measurements() -> Vec<Measurement> {
    lock().iter().map(|(_, m)| m.clone()).collect()
}

fn lock() -> std::sync::MutexGuard<'static, Vec<(Key, Measurement)>> {
    MEASURED.lock().unwrap_or_else(|e| e.into_inner())
}

/// Times one forward pass of a random network of `sizes` through each of `candidates`, in
/// rounds that visit every path in turn (so that all see the same conditions), until `budget`
/// is spent; keeps each path's best time.
pub fn measure(
    sizes: &[usize],
    activation: Activation,
    candidates: &[KernelPath],
    budget: Duration,
) -> Measurement {
    let mut rng = StdRng::seed_from_u64(0);
    let mut mlp = Mlp::new(sizes, activation, &mut rng);
    let mut scratch = ForwardScratch::new(&mlp, BATCH);
    for v in scratch.input_mut() {
        *v = rng.random_range(-1.0..1.0);
    }
    let nets: Vec<Mlp> = candidates
        .iter()
        .map(|&p| {
            mlp.set_kernel_path(p);
            mlp.pack_for_inference();
            mlp.clone()
        })
        .collect();
    let mut best = vec![f64::INFINITY; candidates.len()];
    let start = Instant::now();
    let mut rounds = 0;
    while rounds < 3 || (start.elapsed() < budget && rounds < 10_000) {
        for (net, best) in nets.iter().zip(&mut best) {
            let t = Instant::now();
            std::hint::black_box(net.forward(BATCH, &mut scratch));
            // The first round warms caches and clocks up.
            if rounds > 0 {
                *best = best.min(t.elapsed().as_secs_f64());
            }
        }
        rounds += 1;
    }
    let mut timings: Vec<Timing> = candidates
        .iter()
        .zip(best)
        .map(|(&path, seconds)| Timing { path, seconds })
        .collect();
    timings.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
    Measurement {
        sizes: sizes.to_vec(),
        timings,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_available_path_is_measured_and_the_fastest_is_chosen() {
        let sizes = [12, 64, 64, 7];
        let all = KernelPath::available();
        assert!(all.contains(&KernelPath::ScalarF32));
        let m = measure(&sizes, Activation::Swish, &all, Duration::from_millis(20));
        assert_eq!(m.timings.len(), all.len());
        for w in m.timings.windows(2) {
            assert!(w[0].seconds <= w[1].seconds);
        }
        assert!(
            m.timings
                .iter()
                .all(|t| t.seconds.is_finite() && t.seconds > 0.0)
        );
        println!("{m:?}");
        let auto = choose(Precision::Auto, &sizes, Activation::Swish);
        assert!(auto.is_available());
        let cached = measured(&sizes, Activation::Swish, &all);
        assert_eq!(auto, cached.fastest());
        // The cache answers the same shape with the same measurement.
        assert_eq!(measured(&sizes, Activation::Swish, &all), cached);
    }

    #[test]
    fn a_path_is_chosen_over_more_exact_ones_only_when_clearly_faster() {
        let m = |times: &[(KernelPath, f64)]| {
            let mut timings: Vec<Timing> = times
                .iter()
                .map(|&(path, seconds)| Timing { path, seconds })
                .collect();
            timings.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
            Measurement {
                sizes: vec![6, 200, 200, 8],
                timings,
            }
        };
        use KernelPath::*;
        // The tiles 3.6 times faster (as measured on a Xeon with AMX): the tiles.
        let xeon = [(AmxBf16, 77e-6), (Avx512F32, 280e-6), (Avx512Bf16, 409e-6)];
        assert_eq!(m(&xeon).fastest(), AmxBf16);
        // A tie of the tiles and the f32 kernels: the exact products, whichever timed faster.
        assert_eq!(
            m(&[(AmxBf16, 56e-6), (Avx512F32, 57e-6)]).fastest(),
            Avx512F32
        );
        assert_eq!(
            m(&[(AmxBf16, 58e-6), (Avx512F32, 57e-6)]).fastest(),
            Avx512F32
        );
        // Two bf16 paths within the margin, both clearly ahead of f32: the first preferred.
        let close = [(Avx512Bf16, 50e-6), (AmxBf16, 55e-6), (Avx512F32, 100e-6)];
        assert_eq!(m(&close).fastest(), AmxBf16);
        // Only the first wins clearly: it runs.
        let clear = [(Avx512Bf16, 50e-6), (AmxBf16, 80e-6), (Avx512F32, 100e-6)];
        assert_eq!(m(&clear).fastest(), Avx512Bf16);
        // A single measured path is the one chosen.
        assert_eq!(m(&[(Avx2F32, 1e-6)]).fastest(), Avx2F32);
    }

    #[test]
    fn explicit_precisions_stay_in_their_number_format() {
        let sizes = [5, 40, 3];
        let f32 = choose(Precision::F32, &sizes, Activation::Softplus);
        assert_eq!(f32.precision(), Precision::F32);
        assert!(f32.is_available());
        let bf16 = choose(Precision::Bf16, &sizes, Activation::Softplus);
        if bf16_dot_available() {
            assert_eq!(bf16.precision(), Precision::Bf16);
        } else {
            assert_eq!(bf16, f32, "bf16 falls back to f32 without AVX-512 BF16");
        }
    }
}
