//! Which kernels a training pass multiplies with, chosen by timing them on the network's own
//! training step.
//!
//! A training step's time is its matrix products: the forward pass, the backward pass and the
//! weight gradient (and DEEN's double backprop, the same shapes again). They run either on
//! the f32 kernels ([`matmul_par`]: exact f32, AVX-512 or AVX2 FMA) or, on CPUs with AMX, on
//! the tile unit with both factors rounded to bf16 and every sum in f32 ([`tile_matmul_par`]).
//! The weights, the Adam moments and every elementwise step stay f32: only the products'
//! operands are rounded, as in the usual mixed-precision training. Which is faster depends on
//! the CPU and on the shapes (tiny networks lose more to packing than the tiles win), so
//! [`TrainPath::measured`] times one forward and backward pass of a network of the same sizes
//! and batch through each path and keeps the faster; the answer is cached per shape for the
//! life of the process, so an ensemble's members and every retraining reuse it.

use super::kernel_path::CLEAR_WIN;
#[cfg(target_arch = "x86_64")]
use super::matmul::tiles::{
    self, PackedLeft, TileScratch, tile_matmul_packed_par, tile_matmul_par,
};
use super::matmul::{Init, MatMut, MatRef, matmul_par};
use super::mlp::Mlp;
use super::{Activation, Tape};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The kernels of a training pass's products.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TrainPath {
    /// The f32 kernels at the CPU's widest vector level (exact f32 products).
    F32,
    /// AMX tiles: bf16 factors, f32 sums.
    AmxBf16,
}

impl TrainPath {
    /// The name benchmarks print.
    pub fn name(self) -> &'static str {
        match self {
            TrainPath::F32 => "f32",
            TrainPath::AmxBf16 => "amx-bf16",
        }
    }

    /// Whether this CPU (and operating system) can run the path.
    pub fn is_available(self) -> bool {
        match self {
            TrainPath::F32 => true,
            #[cfg(target_arch = "x86_64")]
            TrainPath::AmxBf16 => tiles::available(),
            #[cfg(not(target_arch = "x86_64"))]
            TrainPath::AmxBf16 => false,
        }
    }

    /// Every path this CPU can run.
    pub fn available() -> Vec<TrainPath> {
        [TrainPath::F32, TrainPath::AmxBf16]
            .into_iter()
            .filter(|p| p.is_available())
            .collect()
    }

    /// The faster path for training a network of `sizes` with `activation` on batches of
    /// `batch` (measured once per shape per process; see the module documentation).
    pub fn measured(sizes: &[usize], activation: Activation, batch: usize) -> TrainPath {
        let candidates = TrainPath::available();
        if candidates.len() == 1 {
            return candidates[0];
        }
        measurement(sizes, activation, batch).fastest()
    }
}

impl std::fmt::Display for TrainPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Each path's best time for one forward and backward pass of a network, fastest first.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Measurement {
    pub sizes: Vec<usize>,
    pub batch: usize,
    /// `(path, seconds)` of every available path.
    pub timings: Vec<(TrainPath, f64)>,
}

impl Measurement {
    /// The path to train with: the fastest, except that the tiles must beat the f32 kernels
    /// by [`CLEAR_WIN`]: within it the two are a tie that timing noise decides, and a learning
    /// run's numerics (bf16-rounded factors or exact f32 products) would then depend on the
    /// machine's load at start; a tie goes to the exact products.
    pub fn fastest(&self) -> TrainPath {
        let time = |path| self.timings.iter().find(|(p, _)| *p == path).map(|t| t.1);
        match (self.timings[0].0, time(TrainPath::F32)) {
            (TrainPath::AmxBf16, Some(f32_time))
                if self.timings[0].1 > f32_time * (1.0 - CLEAR_WIN) =>
            {
                TrainPath::F32
            }
            (fastest, _) => fastest,
        }
    }
}

/// Time spent measuring one network shape, over all its paths.
const BUDGET: Duration = Duration::from_millis(120);

type Key = (Vec<usize>, Activation, usize);

static MEASURED: Mutex<Vec<(Key, Measurement)>> = Mutex::new(Vec::new());

fn lock() -> std::sync::MutexGuard<'static, Vec<(Key, Measurement)>> {
    MEASURED.lock().unwrap_or_else(|e| e.into_inner())
}

/// The cached measurement of every available path on a network of `sizes`, made now if new.
pub fn measurement(sizes: &[usize], activation: Activation, batch: usize) -> Measurement {
    let key = (sizes.to_vec(), activation, batch);
    if let Some((_, m)) = lock().iter().find(|(k, _)| *k == key) {
        return m.clone();
    }
    let m = measure(sizes, activation, batch, &TrainPath::available(), BUDGET);
    tracing::info!(
        "training paths for a {sizes:?} network, batch {batch}: {} (chosen: {})",
        m.timings
            .iter()
            .map(|(p, s)| format!("{p} {:.0} µs", s * 1e6))
            .collect::<Vec<_>>()
            .join(", "),
        m.fastest()
    );
    lock().push((key, m.clone()));
    m
}

/// Times one forward pass and one backward pass (parameter gradient) of a random network of
/// `sizes` on `batch` samples through each of `paths`, in rounds that visit every path in turn
/// so that all see the same conditions, until `budget` is spent; keeps each path's best.
pub fn measure(
    sizes: &[usize],
    activation: Activation,
    batch: usize,
    paths: &[TrainPath],
    budget: Duration,
) -> Measurement {
    let mut rng = StdRng::seed_from_u64(0);
    let mlp = Mlp::new(sizes, activation, &mut rng);
    let batch = batch.max(1);
    let mut tapes: Vec<Tape> = paths
        .iter()
        .map(|&p| {
            let mut tape = Tape::with_path(&mlp, batch, p);
            for v in tape.input_mut() {
                *v = rng.random_range(-1.0..1.0);
            }
            tape
        })
        .collect();
    let mut grads = vec![0.0; mlp.params().len()];
    let mut best = vec![f64::INFINITY; paths.len()];
    let start = Instant::now();
    let mut rounds = 0;
    while rounds < 3 || (start.elapsed() < budget && rounds < 10_000) {
        for (tape, best) in tapes.iter_mut().zip(&mut best) {
            let t = Instant::now();
            mlp.forward_train(tape, batch);
            tape.output_and_grad_mut().1.fill(1e-3);
            mlp.backward(tape, &mut grads, false);
            // The first round warms caches and clocks up.
            if rounds > 0 {
                *best = best.min(t.elapsed().as_secs_f64());
            }
        }
        rounds += 1;
    }
    let mut timings: Vec<(TrainPath, f64)> = paths.iter().copied().zip(best).collect();
    timings.sort_by(|a, b| a.1.total_cmp(&b.1));
    Measurement {
        sizes: sizes.to_vec(),
        batch,
        timings,
    }
}

/// The products of one training tape on its path, with the scratch the tiles pack into.
#[derive(Debug)]
pub struct Products {
    path: TrainPath,
    #[cfg(target_arch = "x86_64")]
    tiles: TileScratch,
    /// Per layer, its weights packed as the left factor `W` (index 0) and `Wᵀ` (index 1),
    /// and whether that packing is of the current weights (see [`Products::new_weights`]).
    #[cfg(target_arch = "x86_64")]
    weights: Vec<[(PackedLeft, bool); 2]>,
}

impl Clone for Products {
    /// The same path with scratch of its own.
    fn clone(&self) -> Self {
        Self::new(self.path)
    }
}

impl Products {
    /// Products on `path`. Panics if this CPU cannot run it.
    pub fn new(path: TrainPath) -> Self {
        assert!(path.is_available(), "training path {path} is not available");
        Self {
            path,
            #[cfg(target_arch = "x86_64")]
            tiles: TileScratch::default(),
            #[cfg(target_arch = "x86_64")]
            weights: Vec::new(),
        }
    }

    /// Forgets the packed weights: a pass over new weights starts (a forward pass). Between
    /// two calls every [`Products::matmul_weights`] of a layer must pass the same weights.
    pub fn new_weights(&mut self) {
        #[cfg(target_arch = "x86_64")]
        for forms in &mut self.weights {
            forms[0].1 = false;
            forms[1].1 = false;
        }
    }

    /// `C = init + W · Y` (or `Wᵀ · Y` if `transposed`) for the weights `w` of layer `layer`,
    /// which the tiles pack once per [`Products::new_weights`] for each of the two forms.
    pub fn matmul_weights(
        &mut self,
        c: MatMut<'_>,
        (layer, w, transposed): (usize, MatRef<'_>, bool),
        y: MatRef<'_>,
        init: Init<'_>,
    ) {
        let x = if transposed { w.t() } else { w };
        match self.path {
            TrainPath::F32 => matmul_par(c, x, y, init),
            #[cfg(target_arch = "x86_64")]
            TrainPath::AmxBf16 => {
                if self.weights.len() <= layer {
                    self.weights.resize_with(layer + 1, Default::default);
                }
                let (packed, fresh) = &mut self.weights[layer][usize::from(transposed)];
                if !*fresh {
                    packed.pack(x);
                    *fresh = true;
                }
                tile_matmul_packed_par(c, packed, y, init, &mut self.tiles)
            }
            #[cfg(not(target_arch = "x86_64"))]
            TrainPath::AmxBf16 => unreachable!("checked in Products::new"),
        }
    }

    pub fn path(&self) -> TrainPath {
        self.path
    }

    /// `C = init + X · Y`, split across two threads when large. On [`TrainPath::F32`] `Y`
    /// needs unit column stride; the tiles take any strides (see `tiles.rs`).
    pub fn matmul(&mut self, c: MatMut<'_>, x: MatRef<'_>, y: MatRef<'_>, init: Init<'_>) {
        match self.path {
            TrainPath::F32 => matmul_par(c, x, y, init),
            #[cfg(target_arch = "x86_64")]
            TrainPath::AmxBf16 => tile_matmul_par(c, x, y, init, &mut self.tiles),
            #[cfg(not(target_arch = "x86_64"))]
            TrainPath::AmxBf16 => unreachable!("checked in Products::new"),
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Every training path this CPU has with both activations: what the gradient tests run.
    pub(crate) fn paths_and_activations() -> Vec<(Activation, TrainPath)> {
        let paths = TrainPath::available();
        if !paths.contains(&TrainPath::AmxBf16) {
            eprintln!("no AMX-BF16 tiles on this CPU: the gradients are checked in f32 only");
        }
        [Activation::Swish, Activation::Softplus]
            .into_iter()
            .flat_map(|a| paths.iter().map(move |&p| (a, p)))
            .collect()
    }

    #[test]
    fn the_tiles_train_only_when_clearly_faster_than_f32() {
        let m = |amx: f64, f32_time: f64| {
            let mut timings = vec![(TrainPath::AmxBf16, amx), (TrainPath::F32, f32_time)];
            timings.sort_by(|a, b| a.1.total_cmp(&b.1));
            Measurement {
                sizes: vec![5, 200, 200, 8],
                batch: 32,
                timings,
            }
        };
        // 56 against 57 µs (a measured tie): the exact products.
        assert_eq!(m(56e-6, 57e-6).fastest(), TrainPath::F32);
        assert_eq!(m(60e-6, 57e-6).fastest(), TrainPath::F32);
        // Three times faster: the tiles.
        assert_eq!(m(20e-6, 60e-6).fastest(), TrainPath::AmxBf16);
        assert_eq!(m(80e-6, 100e-6).fastest(), TrainPath::AmxBf16);
    }

    #[test]
    fn every_available_path_is_timed_and_the_fastest_chosen() {
        let sizes = [9, 64, 64, 1];
        let all = TrainPath::available();
        assert!(all.contains(&TrainPath::F32));
        let m = measure(
            &sizes,
            Activation::Swish,
            32,
            &all,
            Duration::from_millis(20),
        );
        assert_eq!(m.timings.len(), all.len());
        assert!(m.timings.windows(2).all(|w| w[0].1 <= w[1].1));
        assert!(m.timings.iter().all(|t| t.1.is_finite() && t.1 > 0.0));
        let chosen = TrainPath::measured(&sizes, Activation::Swish, 32);
        assert!(chosen.is_available());
        assert_eq!(chosen, measurement(&sizes, Activation::Swish, 32).fastest());
        // Cached: the same shape gets the same measurement.
        assert_eq!(
            measurement(&sizes, Activation::Swish, 32),
            measurement(&sizes, Activation::Swish, 32)
        );
        if !TrainPath::AmxBf16.is_available() {
            eprintln!("no AMX-BF16 tiles on this CPU: only the f32 path was timed");
        }
    }
}
