//! `bench kernel`: throughput of the matrix kernels alone, on the shapes of the planner's layers
//! and of the training passes.
//!
//! The design of [`planner_service::nn::matmul`] rests on three speed claims, and this is where they are
//! checked on the machine at hand (a full planning call, `bench plan`, mixes the products with
//! everything else):
//! - **Packing and the fused epilogue**: a hidden layer `C = act(Wᵀ·H + b)` through the general
//!   strided kernel followed by a separate activation pass, against the same layer through
//!   [`matmul_packed`] on weights packed once with the activation fused into the kernel.
//! - **bf16 layers**: the same layer with weights and activations in bf16 pairs (f32 sums), as
//!   the planner runs inference by default where the CPU has AVX-512 BF16.
//! - **bf16 first layers**: a bf16 network's first layer (a few dozen input features, output
//!   as bf16 pairs) on its f32 input through f32 weights, as it ran before, against the input
//!   converted to bf16 pairs and the layer in bf16, as it runs now (conversion included).
//! - **Own kernel instead of the `gemm` crate**: the general kernel against `gemm` on dense
//!   products of the training passes' and planner's shapes. This comparison is why `gemm` is a
//!   normal dependency of the crate although nothing else calls it: the module docs justify the
//!   own kernel by it, and a claim nobody can re-measure rots.
//!
//! The weight-gradient transposes of the training passes are timed too. Every figure but the
//! `matmul_par` row runs on the calling thread and is timed in that thread's CPU time (the
//! `matmul_par` row in the process's, both threads' time summed), so a core lost to another
//! process does not lower a rate; the CPU share column says how much of the wall time the
//! measurement had the CPU. Inputs are uniform in `[-1, 1)`, so no product meets a denormal.

use super::BenchError;
use super::timing::{BATCHES, Clock, Timing, measure_for};
use planner_service::nn::Activation;
use planner_service::nn::aligned::AlignedBuf;
use planner_service::nn::matmul::{
    Encoding, Init, MatMut, MatRef, PackedMatrix, matmul, matmul_packed, matmul_par, transpose,
    write_bf16_pairs,
};
use planner_service::nn::peak::{Peak, TileOverlap, percent};
use planner_service::nn::simd::{SimdLevel, bf16_dot_available, level};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::fmt;
use std::hint::black_box;
use std::time::Duration;

/// A product's shape: `C` is `m × n`, the inner dimension `k`. For a feature-major layer: out
/// features × samples × in features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shape {
    pub m: usize,
    pub n: usize,
    pub k: usize,
}

impl Shape {
    pub const fn new(m: usize, n: usize, k: usize) -> Self {
        Self { m, n, k }
    }

    /// Floating-point operations of one product: a multiply and an add per `m·n·k`.
    pub fn flops(self) -> f64 {
        2.0 * (self.m * self.n * self.k) as f64
    }
}

impl fmt::Display for Shape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}×{}×{}", self.m, self.n, self.k)
    }
}

/// The hidden layers of the presets' networks, with a population chunk of 200–250 samples:
/// 200 wide (cartpole, reacher, half-cheetah dynamics), 400 (ant dynamics), 300 and 500
/// (softplus energy networks).
pub const PLANNER_LAYERS: [(Shape, Activation); 5] = [
    (Shape::new(200, 200, 200), Activation::Swish),
    (Shape::new(200, 250, 200), Activation::Swish),
    (Shape::new(400, 250, 400), Activation::Swish),
    (Shape::new(300, 250, 300), Activation::Softplus),
    (Shape::new(500, 250, 500), Activation::Softplus),
];

/// The first layers of the presets' bf16 networks (out × samples × in, 250-sample chunks):
/// half-cheetah's dynamics (18 + 6 inputs), its energy network (18 + 6 + 18) and ant's
/// dynamics (27 + 8).
pub const FIRST_LAYERS: [(Shape, Activation); 3] = [
    (Shape::new(200, 250, 24), Activation::Swish),
    (Shape::new(500, 250, 42), Activation::Softplus),
    (Shape::new(400, 250, 35), Activation::Swish),
];

/// Dense products of training and planning: a 500-wide layer's forward pass on a 32-sample
/// batch, its weight gradient, a planner chunk, and the same for 200-wide layers.
pub const PRODUCTS: [Shape; 6] = [
    Shape::new(500, 32, 500),
    Shape::new(500, 500, 32),
    Shape::new(500, 250, 500),
    Shape::new(200, 128, 200),
    Shape::new(200, 200, 128),
    Shape::new(200, 250, 200),
];

/// The transposes a weight gradient needs (`rows × cols`): a 500-feature layer's deltas on a
/// 32-sample batch.
pub const TRANSPOSES: [(usize, usize); 1] = [(500, 32)];

/// What `bench kernel` was asked to do.
pub(super) struct Settings {
    pub layers: Vec<(Shape, Activation)>,
    /// Timed only where bf16 layers can run.
    pub first_layers: Vec<(Shape, Activation)>,
    pub products: Vec<Shape>,
    pub transposes: Vec<(usize, usize)>,
    /// About how long each timed batch lasts.
    pub batch: Duration,
    pub seed: u64,
}

/// One kernel's CPU time per product.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Throughput {
    pub best_ms: f64,
    pub median_ms: f64,
    /// GFLOP/s per CPU second at the best and the median batch (`2·m·n·k` per product).
    pub best_gflops: f64,
    pub median_gflops: f64,
    /// CPU time over wall time of the timed batches (see [`Timing::cpu_share`]).
    pub cpu_share: Option<f64>,
}

impl Throughput {
    fn new(t: Timing, shape: Shape) -> Self {
        let gflops = |ms: f64| shape.flops() / (ms * 1e-3) / 1e9;
        Self {
            best_ms: t.min_ms,
            median_ms: t.median_ms,
            best_gflops: gflops(t.min_ms),
            median_gflops: gflops(t.median_ms),
            cpu_share: t.cpu_share,
        }
    }
}

/// One hidden layer through each inference path.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerTiming {
    pub shape: Shape,
    pub activation: Activation,
    /// [`matmul`] on the strided `Wᵀ` with the bias, then the activation over `C`.
    pub general: Throughput,
    /// [`matmul_packed`] on f32 weights, activation fused.
    pub packed_f32: Throughput,
    /// [`matmul_packed`] on bf16 weights, bf16-pair input and output; `None` without
    /// AVX-512 BF16.
    pub packed_bf16: Option<Throughput>,
    /// The same on weights packed as AMX tiles; `None` without AMX-BF16.
    pub packed_amx: Option<Throughput>,
    /// The AMX layer with its bias but no activation: the difference to `packed_amx` is what
    /// the activation in the epilogue costs.
    pub packed_amx_bare: Option<Throughput>,
}

/// A bf16 network's first layer, output written as bf16 pairs, both ways.
#[derive(Clone, Debug, PartialEq)]
pub struct FirstLayerTiming {
    pub shape: Shape,
    pub activation: Activation,
    /// f32 weights on the f32 input (how the first layer ran until the input was converted).
    pub f32_weights: Throughput,
    /// [`write_bf16_pairs`] on the f32 input, then the layer on bf16 weights.
    pub bf16_weights: Throughput,
}

/// One dense product through the own kernel and the `gemm` crate.
#[derive(Clone, Debug, PartialEq)]
pub struct ProductTiming {
    pub shape: Shape,
    /// [`matmul`] on the calling thread.
    pub ours: Throughput,
    /// [`matmul_par`]: the rows split across two rayon tasks (as the training passes run).
    pub ours_parallel: Throughput,
    /// the gemm family's f32 kernel (`gemm-f32`) with `Parallelism::None`.
    pub gemm: Throughput,
}

/// One transpose.
#[derive(Clone, Debug, PartialEq)]
pub struct TransposeTiming {
    pub rows: usize,
    pub cols: usize,
    /// CPU time per transpose.
    pub best_us: f64,
    pub median_us: f64,
}

/// Throughput of the matrix kernels.
#[derive(Clone, Debug, PartialEq)]
pub struct KernelReport {
    /// The instruction-set level the kernels dispatched to.
    pub simd: SimdLevel,
    /// Whether bf16 layers could run (AVX-512 BF16).
    pub bf16_available: bool,
    /// Threads `matmul_par` could use (it splits a product in two at most).
    pub parallel_threads: usize,
    pub layers: Vec<LayerTiming>,
    /// Empty without AVX-512 BF16.
    pub first_layers: Vec<FirstLayerTiming>,
    pub products: Vec<ProductTiming>,
    pub transposes: Vec<TransposeTiming>,
    /// Whether vector work runs beside the tile unit's products (`None` without AMX).
    pub tile_overlap: Option<TileOverlap>,
    /// This core's peak, measured before and after the kernels (the higher): every f32 row is
    /// a fraction of the f32 FMA peak, every bf16 row of the bf16 dot peak (per CPU second, so
    /// the two-thread `matmul_par` rows too).
    pub peak: Peak,
}

pub(super) fn run(s: &Settings) -> Result<KernelReport, BenchError> {
    if s.layers.is_empty()
        && s.first_layers.is_empty()
        && s.products.is_empty()
        && s.transposes.is_empty()
    {
        return Err(BenchError::Zero("shapes"));
    }
    let peak = Peak::measure();
    let mut rng = StdRng::seed_from_u64(s.seed);
    let bf16_available = bf16_dot_available();
    let layers = s
        .layers
        .iter()
        .map(|&(shape, act)| time_layer(shape, act, bf16_available, s.batch, &mut rng))
        .collect();
    let first_layers = if bf16_available {
        s.first_layers
            .iter()
            .map(|&(shape, act)| time_first_layer(shape, act, s.batch, &mut rng))
            .collect()
    } else {
        Vec::new()
    };
    let products = s
        .products
        .iter()
        .map(|&shape| time_product(shape, s.batch, &mut rng))
        .collect();
    let transposes = s
        .transposes
        .iter()
        .map(|&(rows, cols)| time_transpose(rows, cols, s.batch))
        .collect();
    Ok(KernelReport {
        simd: level(),
        bf16_available,
        parallel_threads: rayon::current_num_threads().min(2),
        layers,
        first_layers,
        products,
        transposes,
        tile_overlap: TileOverlap::measure(),
        peak: peak.max(Peak::measure()),
    })
}

/// `n` random floats in a 64-byte aligned buffer, as the networks hold their operands (a
/// plain `Vec` may start mid-line, so that every 64-byte row a kernel loads spans two cache
/// lines: the AMX layers then run at about half their speed in the networks).
fn random(rng: &mut StdRng, n: usize) -> AlignedBuf {
    let mut buf = AlignedBuf::zeros(n);
    for v in &mut buf.as_mut_slice()[..n] {
        *v = rng.random_range(-1.0..1.0);
    }
    buf
}

/// A layer's random operands as the networks hold them: `w` is `k × m` (in × out), `h`
/// feature-major `k × n` with rows padded to `ld`, a multiple of 16 floats, as the networks'
/// scratch is.
struct LayerOperands {
    w: AlignedBuf,
    h: AlignedBuf,
    bias: AlignedBuf,
    ld: usize,
}

impl LayerOperands {
    fn random(Shape { m, n, k }: Shape, rng: &mut StdRng) -> LayerOperands {
        let ld = n.div_ceil(16) * 16;
        let w = random(rng, k * m);
        let h = random(rng, k * ld);
        let bias = random(rng, m);
        LayerOperands { w, h, bias, ld }
    }
}

/// Times one hidden layer: `W` is `k × m` (in × out, as the networks store it), `H` feature-major
/// `k × n` with rows padded to a multiple of 16 floats, as the networks' scratch is.
fn time_layer(
    shape: Shape,
    act: Activation,
    bf16: bool,
    batch: Duration,
    rng: &mut StdRng,
) -> LayerTiming {
    let Shape { m, n, k } = shape;
    let LayerOperands { w, h, bias, ld } = LayerOperands::random(shape, rng);
    let wt = MatRef::new(&w, k, m).t();
    let mut c = AlignedBuf::zeros(m * ld);

    let general = measure_for(Clock::Thread, batch, || {
        matmul(
            MatMut::with_stride(&mut c, m, n, ld),
            wt,
            MatRef::with_stride(&h, k, n, ld),
            Init::RowBias(&bias),
        );
        for row in c.chunks_mut(ld) {
            act.apply(&mut row[..n]);
        }
        black_box(&mut c);
    });

    let packed = PackedMatrix::pack(wt);
    let packed_f32 = measure_for(Clock::Thread, batch, || {
        matmul_packed(
            MatMut::with_stride(&mut c, m, n, ld),
            Encoding::F32,
            &packed,
            MatRef::with_stride(&h, k, n, ld),
            &bias,
            Some(act),
        );
        black_box(&mut c);
    });

    let bf16_layer = |packed: &PackedMatrix, act: Option<Activation>| {
        let pairs = Encoding::Bf16Pairs;
        let (y_rows, c_rows) = (pairs.storage_rows(k), pairs.storage_rows(m));
        let y = to_bf16_pairs(&h, k, n, ld);
        let mut c = AlignedBuf::zeros(c_rows * ld);
        measure_for(Clock::Thread, batch, || {
            matmul_packed(
                MatMut::with_stride(&mut c, c_rows, n, ld),
                pairs,
                packed,
                MatRef::with_stride(&y, y_rows, n, ld),
                &bias,
                act,
            );
            black_box(&mut c);
        })
    };
    let packed_bf16 = bf16.then(|| bf16_layer(&PackedMatrix::pack_bf16(wt), Some(act)));
    let tiles =
        (bf16 && planner_service::nn::amx::available()).then(|| PackedMatrix::pack_bf16_tiles(wt));
    let packed_amx = tiles.as_ref().map(|t| bf16_layer(t, Some(act)));
    let packed_amx_bare = tiles.as_ref().map(|t| bf16_layer(t, None));

    LayerTiming {
        shape,
        activation: act,
        general: Throughput::new(general, shape),
        packed_f32: Throughput::new(packed_f32, shape),
        packed_bf16: packed_bf16.map(|t| Throughput::new(t, shape)),
        packed_amx: packed_amx.map(|t| Throughput::new(t, shape)),
        packed_amx_bare: packed_amx_bare.map(|t| Throughput::new(t, shape)),
    }
}

/// Feature-major `h` (`k` rows of `n` samples, row stride `ld`) in [`Encoding::Bf16Pairs`]:
/// feature rows `2p` and `2p + 1` share storage row `p`.
fn to_bf16_pairs(h: &[f32], k: usize, n: usize, ld: usize) -> AlignedBuf {
    let mut y = AlignedBuf::zeros(Encoding::Bf16Pairs.storage_rows(k) * ld);
    convert_to_pairs(&mut y, h, k, n, ld);
    y
}

fn convert_to_pairs(y: &mut [f32], h: &[f32], k: usize, n: usize, ld: usize) {
    write_bf16_pairs(
        MatMut::with_stride(y, Encoding::Bf16Pairs.storage_rows(k), n, ld),
        MatRef::with_stride(h, k, n, ld),
    );
}

/// Times a bf16 network's first layer both ways (see [`FirstLayerTiming`]); needs AVX-512
/// BF16.
fn time_first_layer(
    shape: Shape,
    act: Activation,
    batch: Duration,
    rng: &mut StdRng,
) -> FirstLayerTiming {
    let Shape { m, n, k } = shape;
    let LayerOperands { w, h: x, bias, ld } = LayerOperands::random(shape, rng);
    let wt = MatRef::new(&w, k, m).t();
    let pairs = Encoding::Bf16Pairs;
    let c_rows = pairs.storage_rows(m);
    let mut c = AlignedBuf::zeros(c_rows * ld);

    let packed = PackedMatrix::pack(wt);
    let f32_weights = measure_for(Clock::Thread, batch, || {
        matmul_packed(
            MatMut::with_stride(&mut c, c_rows, n, ld),
            pairs,
            &packed,
            MatRef::with_stride(&x, k, n, ld),
            &bias,
            Some(act),
        );
        black_box(&mut c);
    });

    let packed = PackedMatrix::pack_bf16(wt);
    let mut y = AlignedBuf::zeros(pairs.storage_rows(k) * ld);
    let bf16_weights = measure_for(Clock::Thread, batch, || {
        convert_to_pairs(&mut y, black_box(&x), k, n, ld);
        matmul_packed(
            MatMut::with_stride(&mut c, c_rows, n, ld),
            pairs,
            &packed,
            MatRef::with_stride(&y, pairs.storage_rows(k), n, ld),
            &bias,
            Some(act),
        );
        black_box(&mut c);
    });

    FirstLayerTiming {
        shape,
        activation: act,
        f32_weights: Throughput::new(f32_weights, shape),
        bf16_weights: Throughput::new(bf16_weights, shape),
    }
}

/// Times `C = X · Y` with all three dense and row-major.
fn time_product(shape: Shape, batch: Duration, rng: &mut StdRng) -> ProductTiming {
    let Shape { m, n, k } = shape;
    let x = random(rng, m * k);
    let y = random(rng, k * n);
    let mut c = AlignedBuf::zeros(m * n);
    let mut ours_with = |clock, product: fn(MatMut<'_>, MatRef<'_>, MatRef<'_>, Init<'_>)| {
        measure_for(clock, batch, || {
            product(
                MatMut::new(&mut c, m, n),
                MatRef::new(&x, m, k),
                MatRef::new(&y, k, n),
                Init::Zero,
            );
            black_box(&mut c);
        })
    };
    let ours = ours_with(Clock::Thread, matmul);
    let ours_parallel = ours_with(Clock::Process, matmul_par);
    let gemm = measure_for(Clock::Thread, batch, || {
        // SAFETY: `c` is m × n, `x` m × k and `y` k × n, all dense row-major (column stride 1,
        // row stride the width), and nothing else accesses them during the call.
        unsafe {
            gemm_f32::gemm::f32::get_gemm_fn()(
                m,
                n,
                k,
                c.as_mut_ptr(),
                1,
                n as isize,
                false,
                x.as_ptr(),
                1,
                k as isize,
                y.as_ptr(),
                1,
                n as isize,
                0.0,
                1.0,
                false,
                false,
                false,
                gemm_common::Parallelism::None,
            );
        }
        black_box(&mut c);
    });
    ProductTiming {
        shape,
        ours: Throughput::new(ours, shape),
        ours_parallel: Throughput::new(ours_parallel, shape),
        gemm: Throughput::new(gemm, shape),
    }
}

fn time_transpose(rows: usize, cols: usize, batch: Duration) -> TransposeTiming {
    let mut src = AlignedBuf::zeros(rows * cols);
    for (i, v) in src.iter_mut().enumerate() {
        *v = i as f32;
    }
    let ld_dst = rows.div_ceil(16) * 16;
    let mut dst = AlignedBuf::zeros(cols * ld_dst);
    let t = measure_for(Clock::Thread, batch, || {
        transpose(
            black_box(&src[..rows * cols]),
            rows,
            cols,
            cols,
            &mut dst,
            ld_dst,
        );
        black_box(&mut dst);
    });
    TransposeTiming {
        rows,
        cols,
        best_us: t.min_ms * 1e3,
        median_us: t.median_ms * 1e3,
    }
}

/// One table row: a kernel's name, its figures and their fractions of `peak`.
fn write_row(
    f: &mut fmt::Formatter<'_>,
    label: &str,
    kernel: &str,
    t: &Throughput,
    peak: Option<f64>,
) -> fmt::Result {
    write!(
        f,
        "\n  {label:<20} {kernel:<22} {:>9.3} {:>9.1} {:>6} {:>10.3} {:>9.1} {:>6} {:>6}",
        t.best_ms,
        t.best_gflops,
        percent(t.best_gflops, peak),
        t.median_ms,
        t.median_gflops,
        percent(t.median_gflops, peak),
        t.cpu_share
            .map_or("-".to_string(), |s| format!("{:.0}%", 100.0 * s))
    )
}

fn write_header(f: &mut fmt::Formatter<'_>, first: &str) -> fmt::Result {
    write!(
        f,
        "\n  {first:<20} {:<22} {:>9} {:>9} {:>6} {:>10} {:>9} {:>6} {:>6}",
        "kernel", "best ms", "GFLOP/s", "peak", "median ms", "GFLOP/s", "peak", "CPU"
    )
}

impl fmt::Display for KernelReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "bench kernel: {:?} kernels, per product the best and the median of {BATCHES} \
             batches in CPU time (ms per product; GFLOP/s count 2·m·n·k per CPU second; CPU: \
             the share of the wall time the batches were on a CPU)\n  {}",
            self.simd, self.peak
        )?;
        if let Some(o) = &self.tile_overlap {
            write!(f, "\n  {o}")?;
        }
        let (f32_peak, bf16_peak) = (self.peak.f32_at(self.simd), self.peak.bf16_gflops);
        if !self.layers.is_empty() {
            write!(
                f,
                "\n\n  hidden layers C = act(Wᵀ·H + b), one thread (m×n×k: out × samples × in)"
            )?;
            write_header(f, "layer")?;
            for l in &self.layers {
                let label = format!(
                    "{} {}",
                    l.shape,
                    format!("{:?}", l.activation).to_lowercase()
                );
                write_row(f, &label, "general + act. pass", &l.general, f32_peak)?;
                write_row(f, "", "packed f32, fused", &l.packed_f32, f32_peak)?;
                if let Some(t) = &l.packed_bf16 {
                    write_row(f, "", "packed bf16, fused", t, bf16_peak)?;
                }
                if let Some(t) = &l.packed_amx {
                    write_row(f, "", "AMX tiles bf16, fused", t, self.peak.amx_gflops)?;
                }
                if let Some(t) = &l.packed_amx_bare {
                    write_row(f, "", "AMX, bias only", t, self.peak.amx_gflops)?;
                }
            }
            if !self.bf16_available {
                write!(
                    f,
                    "\n  (packed bf16: unavailable on this CPU, which lacks AVX-512 BF16)"
                )?;
            }
        }
        if !self.first_layers.is_empty() {
            write!(
                f,
                "\n\n  first layers of bf16 networks, output as bf16 pairs, one thread: f32 \
                 input through f32 weights, or converted to bf16 pairs (timed) and through bf16 \
                 weights"
            )?;
            write_header(f, "layer")?;
            for l in &self.first_layers {
                let label = format!(
                    "{} {}",
                    l.shape,
                    format!("{:?}", l.activation).to_lowercase()
                );
                write_row(f, &label, "f32 weights", &l.f32_weights, f32_peak)?;
                write_row(f, "", "input → pairs, bf16", &l.bf16_weights, bf16_peak)?;
            }
        }
        if !self.products.is_empty() {
            write!(
                f,
                "\n\n  dense products C = X·Y against the gemm crate (m×n×k: C is m×n)"
            )?;
            write_header(f, "product")?;
            // Both threads' CPU time counts, so its rate is per core as well.
            let parallel = format!("ours, matmul_par ({}t)", self.parallel_threads);
            for p in &self.products {
                write_row(
                    f,
                    &p.shape.to_string(),
                    "ours, one thread",
                    &p.ours,
                    f32_peak,
                )?;
                write_row(f, "", &parallel, &p.ours_parallel, f32_peak)?;
                write_row(f, "", "gemm, one thread", &p.gemm, f32_peak)?;
            }
        }
        if !self.transposes.is_empty() {
            writeln!(f)?;
        }
        for t in &self.transposes {
            write!(
                f,
                "\n  transpose {}×{} (weight-gradient operand): {:.2} µs best, {:.2} µs median (CPU)",
                t.rows, t.cols, t.best_us, t.median_us
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finite_positive(t: &Throughput) -> bool {
        [t.best_ms, t.median_ms, t.best_gflops, t.median_gflops]
            .iter()
            .all(|v| v.is_finite() && *v > 0.0)
            && t.best_ms <= t.median_ms
            && t.best_gflops >= t.median_gflops
            && t.cpu_share.is_none_or(|s| s > 0.0 && s.is_finite())
    }

    #[test]
    fn times_every_kernel_on_every_shape() {
        // Odd sizes: ragged row blocks, a padded stride and an unpaired last bf16 row.
        let settings = Settings {
            layers: vec![
                (Shape::new(13, 20, 9), Activation::Swish),
                (Shape::new(8, 33, 16), Activation::Softplus),
            ],
            first_layers: vec![(Shape::new(14, 21, 5), Activation::Swish)],
            products: vec![Shape::new(7, 24, 5)],
            transposes: vec![(19, 6)],
            batch: Duration::ZERO,
            seed: 3,
        };
        let report = run(&settings).unwrap();
        assert_eq!(report.simd, level());
        assert_eq!(report.bf16_available, bf16_dot_available());
        assert!((1..=2).contains(&report.parallel_threads));
        assert_eq!(report.layers.len(), 2);
        for (l, (shape, act)) in report.layers.iter().zip(&settings.layers) {
            assert_eq!((l.shape, l.activation), (*shape, *act));
            assert!(finite_positive(&l.general), "{l:?}");
            assert!(finite_positive(&l.packed_f32), "{l:?}");
            assert_eq!(l.packed_bf16.is_some(), report.bf16_available);
            assert!(l.packed_bf16.as_ref().is_none_or(finite_positive), "{l:?}");
            let tiles = report.bf16_available && planner_service::nn::amx::available();
            assert_eq!(l.packed_amx.is_some(), tiles);
            assert_eq!(l.packed_amx_bare.is_some(), tiles);
            assert!(l.packed_amx.as_ref().is_none_or(finite_positive), "{l:?}");
            assert!(
                l.packed_amx_bare.as_ref().is_none_or(finite_positive),
                "{l:?}"
            );
        }
        assert_eq!(
            report.tile_overlap.is_some(),
            planner_service::nn::amx::available()
        );
        if report.bf16_available {
            let [l] = &report.first_layers[..] else {
                panic!("one first layer: {:?}", report.first_layers)
            };
            assert_eq!((l.shape, l.activation), settings.first_layers[0]);
            assert!(finite_positive(&l.f32_weights), "{l:?}");
            assert!(finite_positive(&l.bf16_weights), "{l:?}");
        } else {
            assert!(report.first_layers.is_empty());
        }
        let [p] = &report.products[..] else {
            panic!("one product: {:?}", report.products)
        };
        assert_eq!(p.shape, Shape::new(7, 24, 5));
        assert!(finite_positive(&p.ours) && finite_positive(&p.ours_parallel));
        assert!(finite_positive(&p.gemm), "{p:?}");
        let [t] = &report.transposes[..] else {
            panic!("one transpose: {:?}", report.transposes)
        };
        assert_eq!((t.rows, t.cols), (19, 6));
        assert!(t.best_us > 0.0 && t.best_us <= t.median_us && t.median_us.is_finite());

        let text = report.to_string();
        for needle in [
            "13×20×9 swish",
            "8×33×16 softplus",
            "7×24×5",
            "gemm, one thread",
            "transpose 19×6",
            "measured peak per core",
            "in CPU time",
        ] {
            assert!(text.contains(needle), "{needle} missing from\n{text}");
        }
        assert_eq!(
            text.contains("packed bf16, fused"),
            report.bf16_available,
            "{text}"
        );
        assert_eq!(
            text.contains("14×21×5 swish"),
            report.bf16_available,
            "{text}"
        );
        // (The peak line says "unavailable" of any path this CPU lacks, AMX tiles on a Zen.)
        assert_eq!(
            text.contains("packed bf16: unavailable"),
            !report.bf16_available
        );
    }

    #[test]
    fn the_bf16_operand_holds_the_layer_input() {
        // The bench times products nobody looks at: check that its bf16-pair input, fed to the
        // bf16 kernel, gives the layer the f32 kernel gives (to bf16 accuracy: each product
        // of two operands rounded to 8 significant bits is off by at most 2⁻⁷ of |w·h| ≤ 1).
        if !bf16_dot_available() {
            return; // the bench times no bf16 layer on this CPU
        }
        let mut rng = StdRng::seed_from_u64(4);
        let (m, n, k, ld) = (10, 5, 7, 16);
        let w = random(&mut rng, k * m);
        let h = random(&mut rng, k * ld);
        let bias = random(&mut rng, m);
        let wt = MatRef::new(&w, k, m).t();
        let mut want = vec![0.0; m * ld];
        matmul_packed(
            MatMut::with_stride(&mut want, m, n, ld),
            Encoding::F32,
            &PackedMatrix::pack(wt),
            MatRef::with_stride(&h, k, n, ld),
            &bias,
            None,
        );
        let y = to_bf16_pairs(&h, k, n, ld);
        let mut got = vec![0.0; m * ld];
        matmul_packed(
            MatMut::with_stride(&mut got, m, n, ld),
            Encoding::F32,
            &PackedMatrix::pack_bf16(wt),
            MatRef::with_stride(&y, k.div_ceil(2), n, ld),
            &bias,
            None,
        );
        for i in 0..m {
            for j in 0..n {
                let (g, e) = (got[i * ld + j], want[i * ld + j]);
                assert!((g - e).abs() <= k as f32 * 0.008, "({i},{j}): {g} vs {e}");
            }
        }
    }
}
