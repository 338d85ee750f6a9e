//! The multilayer perceptron: its parameters and its allocation-free inference pass.
//!
//! Parameters live in one flat vector — per layer the row-major `in × out` weight matrix, then
//! the bias — so the optimiser, the gradients and serialisation all see one slice.
//!
//! Activations are *feature-major*: a batch of `n` samples with `d` features is a `d × ld`
//! matrix whose column `i` is sample `i` (`ld ≥ n`, a multiple of 16). A layer is then
//! `Z = Wᵀ · H + b` with `Wᵀ` a free strided view (see [`matmul`](super::matmul)).
//!
//! Inference ([`Mlp::forward`]) instead reads each `Wᵀ` packed in the kernel's layout
//! ([`PackedMatrix`]), with the activation fused into the product. The packed copy is made on
//! the first inference after the network is built or its parameters were handed out mutably
//! ([`Mlp::params_mut`] drops it), so a planner packs once per model, never per call.
//!
//! The network's [`Precision`] picks the kernel path ([`KernelPath`], measured per network
//! shape for `Auto` and `Bf16`, see [`super::kernel_path`]) and so the packing:
//! an f32 path (the default for a bare network) packs every layer in f32; a bf16 path (AMX
//! tiles or AVX-512 BF16 dot products) packs every layer as bf16 pairs: the f32 input is
//! converted to pairs in one pass, hidden activations travel between layers as bf16, and the
//! output comes back in f32. The first layer was once kept in f32 for its raw input; with only
//! 24–62 input features its f32 tiles did half the multiply-adds per instruction for little
//! precision (the input is rounded to bf16 like every hidden activation, 2⁻⁹ relative), and a
//! `perf record` of a half-cheetah + DEEN plan put 6 % of its samples there for 2 % of its
//! multiply-adds.

use super::Precision;
use super::activation::Activation;
use super::aligned::{AlignedBuf, round_up};
use super::kernel_path::{self, KernelPath};
use super::matmul::{Encoding, MatMut, MatRef, PackedMatrix, matmul_packed_at, write_bf16_pairs};
use rand::RngExt;
use rand::rngs::StdRng;
use std::ops::Range;
use std::sync::OnceLock;

/// A dense feed-forward network: `sizes[0]` inputs, hidden layers of `sizes[1..L]` units with
/// `activation`, and a linear output layer of `sizes[L]` units.
#[derive(Clone, Debug, PartialEq)]
pub struct Mlp {
    sizes: Vec<usize>,
    activation: Activation,
    params: Vec<f32>,
    /// Each layer's `Wᵀ` packed for inference; derived from `params`, made on first use.
    packed: PackedCache,
}

/// The packed weights: a cache of `params` for the chosen kernel path, so it takes no part in
/// equality.
#[derive(Clone)]
struct PackedCache {
    request: Request,
    layers: OnceLock<Packed>,
}

/// What inference was asked to run in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Request {
    /// A number format; the path is chosen for it (see [`kernel_path::choose`]).
    Precision(Precision),
    /// One path (measurements and tests).
    Path(KernelPath),
}

#[derive(Clone)]
struct Packed {
    path: KernelPath,
    layers: Vec<PackedMatrix>,
}

impl PackedCache {
    fn empty(request: Request) -> Self {
        Self {
            request,
            layers: OnceLock::new(),
        }
    }
}

impl Default for PackedCache {
    fn default() -> Self {
        Self::empty(Request::Precision(Precision::F32))
    }
}

impl PartialEq for PackedCache {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for PackedCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let state = if self.layers.get().is_some() {
            "packed"
        } else {
            "not packed"
        };
        write!(f, "{state} ({:?})", self.request)
    }
}

impl Mlp {
    /// A network with the given layer sizes (at least input and output), initialised like
    /// PyTorch's `nn.Linear` (the reference implementations are PyTorch): weights and biases
    /// uniform in `±1/√fan_in`, which keeps activations of order one through smooth layers.
    pub fn new(sizes: &[usize], activation: Activation, rng: &mut StdRng) -> Self {
        assert!(
            sizes.len() >= 2 && sizes.iter().all(|&s| s > 0),
            "bad layer sizes {sizes:?}"
        );
        let mut params = Vec::with_capacity(param_count(sizes));
        for w in sizes.windows(2) {
            let bound = 1.0 / (w[0] as f32).sqrt();
            params.extend((0..w[0] * w[1] + w[1]).map(|_| rng.random_range(-bound..bound)));
        }
        Self {
            sizes: sizes.to_vec(),
            activation,
            params,
            packed: PackedCache::default(),
        }
    }

    /// A network with given parameters (e.g. loaded from disk), laid out as [`Mlp::params`].
    pub fn from_params(sizes: &[usize], activation: Activation, params: Vec<f32>) -> Self {
        assert!(
            sizes.len() >= 2 && sizes.iter().all(|&s| s > 0),
            "bad layer sizes {sizes:?}"
        );
        assert_eq!(
            params.len(),
            param_count(sizes),
            "parameter count for {sizes:?}"
        );
        Self {
            sizes: sizes.to_vec(),
            activation,
            params,
            packed: PackedCache::default(),
        }
    }

    /// `[inputs, hidden…, outputs]`.
    pub fn sizes(&self) -> &[usize] {
        &self.sizes
    }

    pub fn in_dim(&self) -> usize {
        self.sizes[0]
    }

    pub fn out_dim(&self) -> usize {
        self.sizes[self.sizes.len() - 1]
    }

    /// Number of weight layers (hidden layers + 1).
    pub fn layers(&self) -> usize {
        self.sizes.len() - 1
    }

    /// The widest layer (buffer sizing).
    pub fn max_width(&self) -> usize {
        self.sizes.iter().copied().max().unwrap_or(0)
    }

    pub fn activation(&self) -> Activation {
        self.activation
    }

    /// All parameters: for each layer, the row-major `in × out` weights, then the `out` biases.
    pub fn params(&self) -> &[f32] {
        &self.params
    }

    /// Mutable parameters (training). Drops the packed inference weights: the next
    /// [`Mlp::forward`] packs the new values.
    pub fn params_mut(&mut self) -> &mut [f32] {
        self.packed = PackedCache::empty(self.packed.request);
        &mut self.params
    }

    /// Sets the number format of inference (f32 until set); the next [`Mlp::forward`] chooses
    /// the kernel path for it and packs the weights. Training is unaffected: it always runs in
    /// f32.
    pub fn set_inference_precision(&mut self, precision: Precision) {
        self.request(Request::Precision(precision));
    }

    /// Runs inference on one kernel path (which must be available), unmeasured.
    pub fn set_kernel_path(&mut self, path: KernelPath) {
        assert!(path.is_available(), "{path} is not available on this CPU");
        self.request(Request::Path(path));
    }

    fn request(&mut self, request: Request) {
        if request != self.packed.request {
            self.packed = PackedCache::empty(request);
        }
    }

    /// The number format inference runs in: that of its kernel path (f32 where bf16 was asked
    /// on a CPU without AVX-512 BF16; `Auto` resolved by measurement).
    pub fn inference_precision(&self) -> Precision {
        self.kernel_path().precision()
    }

    /// The kernel path inference runs (chosen, and the weights packed, on first use).
    pub fn kernel_path(&self) -> KernelPath {
        self.packed().path
    }

    /// The kernel path, if the weights are packed already (never packs or measures).
    pub fn packed_kernel_path(&self) -> Option<KernelPath> {
        self.packed.layers.get().map(|p| p.path)
    }

    /// Packs the weights for inference now (what the first [`Mlp::forward`] would do), e.g.
    /// before a trained model is handed to planners, so no planning call pays for it.
    pub fn pack_for_inference(&self) {
        self.packed_weights();
    }

    /// Each layer's `Wᵀ` in the kernel path's layout, packed on first use.
    fn packed_weights(&self) -> &[PackedMatrix] {
        &self.packed().layers
    }

    fn packed(&self) -> &Packed {
        self.packed.layers.get_or_init(|| {
            let path = match self.packed.request {
                Request::Path(path) => path,
                Request::Precision(p) => kernel_path::choose(p, &self.sizes, self.activation),
            };
            let layers = (0..self.layers())
                .map(|l| {
                    let (n_in, n_out) = (self.sizes[l], self.sizes[l + 1]);
                    path.pack(MatRef::new(self.weight(l), n_in, n_out).t())
                })
                .collect();
            Packed { path, layers }
        })
    }

    /// Where layer `l`'s weights sit in [`Mlp::params`] (biases follow directly).
    pub fn weight_range(&self, l: usize) -> Range<usize> {
        let start: usize = self
            .sizes
            .windows(2)
            .take(l)
            .map(|w| w[0] * w[1] + w[1])
            .sum();
        start..start + self.sizes[l] * self.sizes[l + 1]
    }

    /// Where layer `l`'s biases sit in [`Mlp::params`].
    pub fn bias_range(&self, l: usize) -> Range<usize> {
        let w = self.weight_range(l);
        w.end..w.end + self.sizes[l + 1]
    }

    /// Where layer `l`'s weights and biases sit together in [`Mlp::params`]: a row-major
    /// `(sizes[l] + 1) × sizes[l + 1]` matrix whose last row is the biases. The training passes
    /// write a layer's whole gradient as this one block (see [`crate::nn::backprop`]).
    pub fn layer_range(&self, l: usize) -> Range<usize> {
        self.weight_range(l).start..self.bias_range(l).end
    }

    /// Layer `l`'s weights, row-major `sizes[l] × sizes[l + 1]`.
    pub fn weight(&self, l: usize) -> &[f32] {
        &self.params[self.weight_range(l)]
    }

    pub fn bias(&self, l: usize) -> &[f32] {
        &self.params[self.bias_range(l)]
    }

    /// The output for `samples` inputs written feature-major into [`ForwardScratch::input_mut`]:
    /// an `out_dim × scratch.ld()` matrix whose first `samples` columns are the outputs (the
    /// caller may transform it in place). Never allocates.
    pub fn forward<'s>(&self, samples: usize, scratch: &'s mut ForwardScratch) -> &'s mut [f32] {
        self.forward_io(samples, scratch).1
    }

    /// [`Mlp::forward`], also returning the (unchanged) input buffer, for callers that
    /// compare output with input (a denoising autoencoder). Never allocates.
    pub fn forward_io<'s>(
        &self,
        samples: usize,
        scratch: &'s mut ForwardScratch,
    ) -> (&'s [f32], &'s mut [f32]) {
        assert!(
            scratch.fits(self, samples),
            "scratch of {} samples / width {} too small",
            scratch.ld,
            scratch.width
        );
        let ld = scratch.ld;
        let Packed {
            path,
            layers: packed,
        } = self.packed();
        let lvl = path.level();
        let ForwardScratch {
            input,
            input_pairs,
            ping,
            pong,
            ..
        } = scratch;
        let layers = self.layers();
        let in_dim = self.in_dim();
        // Layer 0 reads the input in its weights' encoding.
        let first = match packed[0].encoding() {
            Encoding::F32 => input.as_slice(),
            Encoding::Bf16Pairs => {
                write_bf16_pairs(
                    MatMut::with_stride(
                        input_pairs.as_mut_slice(),
                        Encoding::Bf16Pairs.storage_rows(in_dim),
                        samples,
                        ld,
                    ),
                    MatRef::with_stride(input.as_slice(), in_dim, samples, ld),
                );
                input_pairs.as_slice()
            }
        };
        for (l, weights) in packed.iter().enumerate() {
            // Layer 0 reads the input; then `ping` and `pong` alternate (even layers write `ping`).
            let (src, dst) = match (l, l % 2) {
                (0, _) => (first, ping.as_mut_slice()),
                (_, 1) => (ping.as_slice(), pong.as_mut_slice()),
                _ => (pong.as_slice(), ping.as_mut_slice()),
            };
            let (n_in, n_out) = (self.sizes[l], self.sizes[l + 1]);
            let hidden = l + 1 < layers;
            // A layer writes its output in the encoding the next layer reads.
            let out = if hidden {
                packed[l + 1].encoding()
            } else {
                Encoding::F32
            };
            matmul_packed_at(
                lvl,
                MatMut::with_stride(dst, out.storage_rows(n_out), samples, ld),
                out,
                weights,
                MatRef::with_stride(src, weights.encoding().storage_rows(n_in), samples, ld),
                self.bias(l),
                hidden.then_some(self.activation),
            );
        }
        let out = if (layers - 1).is_multiple_of(2) {
            ping
        } else {
            pong
        };
        (
            &input.as_slice()[..in_dim * ld],
            &mut out.as_mut_slice()[..self.out_dim() * ld],
        )
    }

    /// Convenience for tests and tools: outputs for sample-major `x` (`samples × in_dim`),
    /// returned sample-major. Allocates.
    pub fn forward_rows(&self, x: &[f32]) -> Vec<f32> {
        let samples = x.len() / self.in_dim();
        let mut scratch = ForwardScratch::new(self, samples);
        let ld = scratch.ld();
        super::matmul::transpose(
            x,
            samples,
            self.in_dim(),
            self.in_dim(),
            scratch.input_mut(),
            ld,
        );
        let out = self.forward(samples, &mut scratch);
        let mut rows = vec![0.0; samples * self.out_dim()];
        super::matmul::transpose(out, self.out_dim(), samples, ld, &mut rows, self.out_dim());
        rows
    }
}

/// Stored numbers that do not fit the shape they are loaded into.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{what}: expected {expected} numbers, got {got}")]
pub struct ShapeError {
    pub what: &'static str,
    pub expected: usize,
    pub got: usize,
}

impl ShapeError {
    /// `Ok` when `got == expected`.
    pub fn check(what: &'static str, expected: usize, got: usize) -> Result<(), ShapeError> {
        if expected == got {
            Ok(())
        } else {
            Err(ShapeError {
                what,
                expected,
                got,
            })
        }
    }
}

/// Number of parameters of a network with these layer sizes.
pub fn param_count(sizes: &[usize]) -> usize {
    sizes.windows(2).map(|w| w[0] * w[1] + w[1]).sum()
}

/// The ranges of a `rows × cols` region of a buffer with row stride `ld` that elementwise
/// operations visit: one range when the rows are contiguous, else one per row.
pub(crate) fn spans(rows: usize, cols: usize, ld: usize) -> impl Iterator<Item = Range<usize>> {
    let whole = cols == ld;
    let count = if whole { usize::from(rows > 0) } else { rows };
    (0..count).map(move |r| {
        if whole {
            0..rows * ld
        } else {
            r * ld..r * ld + cols
        }
    })
}

/// Preallocated buffers for [`Mlp::forward`] on up to `capacity` samples.
#[derive(Clone, Debug)]
pub struct ForwardScratch {
    ld: usize,
    in_dim: usize,
    width: usize,
    input: AlignedBuf,
    /// The input as bf16 pairs, for a network whose first layer is packed in bf16.
    input_pairs: AlignedBuf,
    ping: AlignedBuf,
    pong: AlignedBuf,
}

impl ForwardScratch {
    /// Buffers for `mlp` on up to `max_samples` samples.
    pub fn new(mlp: &Mlp, max_samples: usize) -> Self {
        let ld = round_up(max_samples.max(1));
        let width = mlp.max_width();
        Self {
            ld,
            in_dim: mlp.in_dim(),
            width,
            input: AlignedBuf::zeros(mlp.in_dim() * ld),
            input_pairs: AlignedBuf::zeros(Encoding::Bf16Pairs.storage_rows(mlp.in_dim()) * ld),
            ping: AlignedBuf::zeros(width * ld),
            pong: AlignedBuf::zeros(width * ld),
        }
    }

    /// Row stride of every buffer, and the most samples one pass can take.
    pub fn ld(&self) -> usize {
        self.ld
    }

    /// Whether these buffers can run `mlp` on `samples` samples.
    pub fn fits(&self, mlp: &Mlp, samples: usize) -> bool {
        samples <= self.ld && self.in_dim == mlp.in_dim() && self.width >= mlp.max_width()
    }

    /// The feature-major input: `in_dim × ld`, sample `i`'s feature `f` at `f · ld + i`.
    pub fn input_mut(&mut self) -> &mut [f32] {
        let n = self.in_dim * self.ld;
        &mut self.input.as_mut_slice()[..n]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A direct, obviously correct evaluation in f64.
    fn reference_forward(mlp: &Mlp, x: &[f32]) -> Vec<f64> {
        let params: Vec<f64> = mlp.params().iter().map(|&v| f64::from(v)).collect();
        let x: Vec<f64> = x.iter().map(|&v| f64::from(v)).collect();
        crate::nn::reference::forward(mlp.sizes(), mlp.activation(), &params, &x)
    }

    #[test]
    fn forward_matches_reference_and_reuses_scratch() {
        let mut rng = StdRng::seed_from_u64(11);
        for act in [Activation::Swish, Activation::Softplus] {
            let mlp = Mlp::new(&[5, 37, 20, 3], act, &mut rng);
            let mut scratch = ForwardScratch::new(&mlp, 40);
            for samples in [1, 17, 40] {
                let x: Vec<f32> = (0..samples * 5)
                    .map(|_| rng.random_range(-2.0..2.0))
                    .collect();
                let ld = scratch.ld();
                crate::nn::matmul::transpose(&x, samples, 5, 5, scratch.input_mut(), ld);
                let out = mlp.forward(samples, &mut scratch).to_vec();
                let rows = mlp.forward_rows(&x);
                for i in 0..samples {
                    let want = reference_forward(&mlp, &x[i * 5..(i + 1) * 5]);
                    for j in 0..3 {
                        assert!(
                            (out[j * ld + i] as f64 - want[j]).abs() < 1e-5,
                            "{act:?} sample {i} out {j}"
                        );
                        assert_eq!(rows[i * 3 + j], out[j * ld + i]);
                    }
                }
            }
        }
    }

    /// bf16 inference of networks of the presets' shapes stays within 3 % of the outputs' RMS
    /// (measured at most 1.9 %; about 2⁻⁸ relative rounding per operand and layer), and
    /// switching back to f32 restores the exact outputs. The weights are scaled to unit gain
    /// per layer, so the signal neither vanishes nor explodes through the stack.
    #[test]
    fn bf16_inference_stays_close_to_f32() {
        let mut rng = StdRng::seed_from_u64(3);
        let shapes = [
            (vec![42, 500, 500, 500, 500, 500, 1], Activation::Softplus),
            (vec![24, 200, 200, 200, 200, 36], Activation::Swish),
            (vec![35, 400, 400, 400, 400, 54], Activation::Swish),
        ];
        for (sizes, act) in shapes {
            let mut mlp = Mlp::new(&sizes, act, &mut rng);
            for w in mlp.params_mut() {
                *w *= 3f32.sqrt();
            }
            let samples = 64;
            let x: Vec<f32> = (0..samples * sizes[0])
                .map(|_| rng.random_range(-2.0..2.0))
                .collect();
            let exact = mlp.forward_rows(&x);
            mlp.set_inference_precision(Precision::Bf16);
            if !crate::nn::simd::bf16_dot_available() {
                // Without AVX-512 BF16 the request falls back to f32, exactly.
                assert_eq!(mlp.inference_precision(), Precision::F32);
                assert_eq!(mlp.forward_rows(&x), exact);
                continue;
            }
            assert_eq!(mlp.inference_precision(), Precision::Bf16);
            let approx = mlp.forward_rows(&x);
            assert_ne!(approx, exact, "{sizes:?}: bf16 was not used");
            let rms =
                (exact.iter().map(|v| (v * v) as f64).sum::<f64>() / exact.len() as f64).sqrt();
            let worst = exact
                .iter()
                .zip(&approx)
                .map(|(e, a)| (e - a).abs() as f64)
                .fold(0.0, f64::max);
            eprintln!("{sizes:?}: bf16 error at most {worst:.2e}, output RMS {rms:.2e}");
            assert!(
                worst <= 0.03 * rms,
                "{sizes:?}: error {worst} against output RMS {rms}"
            );
            mlp.set_inference_precision(Precision::F32);
            assert_eq!(mlp.forward_rows(&x), exact);
        }
    }

    /// In bf16 the first layer too multiplies bf16 operands: a linear layer that copies its
    /// input returns the input rounded to bf16 (in f32, exactly the input).
    #[test]
    fn bf16_first_layer_reads_its_input_rounded_to_bf16() {
        // Output 0 = input 0, output 1 = input 2; inputs chosen between two bf16 numbers.
        let mut mlp = Mlp::from_params(
            &[3, 2],
            Activation::Swish,
            vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
        );
        let x = [
            1.0 + 2f32.powi(-10),
            5.0,
            -3.0 - 2f32.powi(-9) - 2f32.powi(-12),
        ];
        assert_eq!(mlp.forward_rows(&x), vec![x[0], x[2]]);
        mlp.set_inference_precision(Precision::Bf16);
        if mlp.inference_precision() != Precision::Bf16 {
            return; // no AVX-512 BF16: f32 it stays, checked above
        }
        let round = |v: f32| super::super::matmul::bf16_value(super::super::matmul::bf16_bits(v));
        assert_eq!(mlp.forward_rows(&x), vec![round(x[0]), round(x[2])]);
        assert_ne!(round(x[0]), x[0]);
        assert_ne!(round(x[2]), x[2]);
    }

    #[test]
    fn single_layer_network_is_affine() {
        let mut rng = StdRng::seed_from_u64(1);
        let mlp = Mlp::from_params(&[2, 1], Activation::Swish, vec![2.0, -1.0, 0.5]);
        assert_eq!(mlp.forward_rows(&[1.0, 3.0, 0.0, 0.0]), vec![-0.5, 0.5]);
        let big = Mlp::new(&[3, 4, 2], Activation::Softplus, &mut rng);
        assert_eq!(big.params().len(), param_count(&[3, 4, 2]));
        assert_eq!((big.weight_range(1), big.bias_range(1)), (16..24, 24..26));
    }

    #[test]
    fn spans_cover_exactly_the_valid_columns() {
        assert_eq!(spans(3, 16, 16).collect::<Vec<_>>(), vec![0..48]);
        assert_eq!(spans(2, 5, 16).collect::<Vec<_>>(), vec![0..5, 16..21]);
        assert_eq!(spans(0, 16, 16).count(), 0);
    }
}
