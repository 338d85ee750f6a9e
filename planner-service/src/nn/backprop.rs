//! Training passes: a forward pass that records what backpropagation needs, and the backward
//! pass giving the parameter gradient and, on request, the input gradient.
//!
//! With layers `zₗ = Wₗᵀ hₗ₋₁ + bₗ`, `hₗ = σ(zₗ)` (feature-major, one column per sample) and
//! `Gₗ = ∂L/∂zₗ` given at the output, backpropagation is
//! `∂L/∂Wₗ = hₗ₋₁ Gₗᵀ`, `∂L/∂bₗ = Gₗ 1`, `Gₗ₋₁ = (Wₗ Gₗ) ⊙ σ'(zₗ₋₁)`, and `∂L/∂x = W₁ G₁`.
//!
//! The weight and bias gradients are one product: every recorded activation `hₗ₋₁` carries a
//! constant row of ones below its features, so `[hₗ₋₁; 1ᵀ] Gₗᵀ` is `[∂L/∂Wₗ; ∂L/∂bₗᵀ]`, the
//! layer's block of the parameter vector as it is laid out (see [`Mlp::layer_range`]). The
//! bias sums then cost one more row of the kernel instead of a reduction call per output
//! feature (on cartpole's 200-wide layers those calls took about 2.5 % of a dynamics step).

use super::Precision;
use super::aligned::{AlignedBuf, round_up};
use super::matmul::{Init, MatMut, MatRef};
use super::mlp::{Mlp, spans};
use super::train_path::{Products, TrainPath};

/// Buffers of one training pass for batches of up to `capacity` samples.
#[derive(Clone, Debug)]
pub struct Tape {
    sizes: Vec<usize>,
    ld: usize,
    samples: usize,
    /// `h[0]`: the input; `h[l]`: layer `l`'s activations; `h[L]`: the output. Each has one
    /// row more than its features, all ones, never written after [`Tape::new`]: the bias
    /// row of the gradient products (see the module docs).
    h: Vec<AlignedBuf>,
    /// `d1[l - 1] = σ'(zₗ)` for hidden layer `l`.
    d1: Vec<AlignedBuf>,
    out_grad: AlignedBuf,
    /// Ping-pong buffers for `Gₗ` below the output; the input gradient ends in one of them.
    g: [AlignedBuf; 2],
    input_grad_in: Option<usize>,
    /// `Gₗᵀ`, sample-major, the right factor of the weight gradient (f32 kernels).
    gt: AlignedBuf,
    products: Products,
}

impl Tape {
    /// Buffers for `mlp` on batches of up to `capacity` samples, multiplying in f32 (exact
    /// f32 gradients).
    pub fn new(mlp: &Mlp, capacity: usize) -> Self {
        Self::with_path(mlp, capacity, TrainPath::F32)
    }

    /// What planning by gradient differentiates a network through: its products in the number
    /// format its inference runs in. Exact f32 where inference is f32 (an explicit `f32`
    /// precision, or a CPU on which no bf16 path won); else the training path measured
    /// fastest for this network and batch (the AMX tiles where they win clearly: bf16 factors,
    /// f32 sums, as CEM's scoring rounds them), so that a gradient-planned run spends no more
    /// time per product than a trainer does.
    pub fn for_planning(mlp: &Mlp, capacity: usize) -> Self {
        // A packed network's path is resolved: its precision is f32 or bf16, never `Auto`.
        if mlp.inference_precision() == Precision::Bf16 {
            Self::for_training(mlp, capacity)
        } else {
            Self::new(mlp, capacity)
        }
    }

    /// [`Tape::new`] on the training path measured fastest for this network and batch (see
    /// [`TrainPath::measured`]): what a trainer uses.
    pub fn for_training(mlp: &Mlp, capacity: usize) -> Self {
        let path = TrainPath::measured(mlp.sizes(), mlp.activation(), capacity);
        Self::with_path(mlp, capacity, path)
    }

    /// [`Tape::new`] with its products on `path`. Panics if this CPU cannot run it.
    pub fn with_path(mlp: &Mlp, capacity: usize, path: TrainPath) -> Self {
        let ld = round_up(capacity.max(1));
        let sizes = mlp.sizes().to_vec();
        let width = mlp.max_width();
        Self {
            h: sizes.iter().map(|&s| with_ones_row(s, ld)).collect(),
            d1: sizes[1..sizes.len() - 1]
                .iter()
                .map(|&s| AlignedBuf::zeros(s * ld))
                .collect(),
            out_grad: AlignedBuf::zeros(mlp.out_dim() * ld),
            g: [AlignedBuf::zeros(width * ld), AlignedBuf::zeros(width * ld)],
            input_grad_in: None,
            gt: AlignedBuf::zeros(ld * round_up(width)),
            products: Products::new(path),
            sizes,
            ld,
            samples: 0,
        }
    }

    /// The kernels this tape's products run on.
    pub fn path(&self) -> TrainPath {
        self.products.path()
    }

    /// Whether this tape serves `mlp` on batches of `samples`.
    pub fn fits(&self, mlp: &Mlp, samples: usize) -> bool {
        self.sizes == mlp.sizes() && samples <= self.ld
    }

    /// Row stride of every feature-major buffer (and the batch capacity).
    pub fn ld(&self) -> usize {
        self.ld
    }

    /// The feature-major input to fill before [`Mlp::forward_train`]: `in_dim × ld`.
    pub fn input_mut(&mut self) -> &mut [f32] {
        let n = self.sizes[0] * self.ld;
        &mut self.h[0].as_mut_slice()[..n]
    }

    /// The output of the last forward pass (`out_dim × ld`) and the buffer for `∂L/∂output`
    /// (same shape) that [`Mlp::backward`] reads.
    pub fn output_and_grad_mut(&mut self) -> (&[f32], &mut [f32]) {
        let n = self.sizes[self.sizes.len() - 1] * self.ld;
        let out = &self.h[self.sizes.len() - 1].as_slice()[..n];
        (out, &mut self.out_grad.as_mut_slice()[..n])
    }

    /// `∂L/∂input` (`in_dim × ld`) from the last [`Mlp::backward`] that asked for it.
    pub fn input_grad(&self) -> &[f32] {
        let slot = self
            .input_grad_in
            .expect("backward was not asked for the input gradient");
        &self.g[slot].as_slice()[..self.sizes[0] * self.ld]
    }

    fn check(&self, mlp: &Mlp, samples: usize) {
        assert_eq!(
            self.sizes,
            mlp.sizes(),
            "tape built for another network shape"
        );
        assert!(
            samples <= self.ld,
            "batch of {samples} exceeds the tape's {}",
            self.ld
        );
    }
}

/// A feature-major buffer of `rows` zero rows and a last row of ones, `ld` floats each.
pub(super) fn with_ones_row(rows: usize, ld: usize) -> AlignedBuf {
    let mut buf = AlignedBuf::zeros((rows + 1) * ld);
    buf.as_mut_slice()[rows * ld..].fill(1.0);
    buf
}

impl Mlp {
    /// `Z = Wₗᵀ · H + bₗ` for training: large products are split across two threads.
    fn affine_train(
        &self,
        l: usize,
        (h, samples, ld): (&[f32], usize, usize),
        z: &mut [f32],
        products: &mut Products,
    ) {
        let (n_in, n_out) = (self.sizes()[l], self.sizes()[l + 1]);
        products.matmul_weights(
            MatMut::with_stride(z, n_out, samples, ld),
            (l, MatRef::new(self.weight(l), n_in, n_out), true),
            MatRef::with_stride(h, n_in, samples, ld),
            Init::RowBias(self.bias(l)),
        );
    }

    /// Forward pass over the first `samples` columns of [`Tape::input_mut`], recording the
    /// activations and their derivatives. Returns the output (`out_dim × ld`).
    pub fn forward_train<'t>(&self, tape: &'t mut Tape, samples: usize) -> &'t [f32] {
        tape.check(self, samples);
        tape.samples = samples;
        tape.products.new_weights();
        tape.input_grad_in = None;
        let ld = tape.ld;
        for l in 0..self.layers() {
            let (below, above) = tape.h.split_at_mut(l + 1);
            let z = above[0].as_mut_slice();
            let h = (below[l].as_slice(), samples, ld);
            self.affine_train(l, h, z, &mut tape.products);
            if l + 1 < self.layers() {
                let d1 = tape.d1[l].as_mut_slice();
                for span in spans(self.sizes()[l + 1], samples, ld) {
                    self.activation()
                        .apply_d1(&mut z[span.clone()], &mut d1[span]);
                }
            }
        }
        tape.output_and_grad_mut().0
    }

    /// Backpropagates the `∂L/∂output` written into the tape (see
    /// [`Tape::output_and_grad_mut`]) through the last forward pass: overwrites `grads`
    /// (laid out as [`Mlp::params`]) with `∂L/∂θ` and, if `input_grad`, computes `∂L/∂input`
    /// (read it with [`Tape::input_grad`]).
    pub fn backward(&self, tape: &mut Tape, grads: &mut [f32], input_grad: bool) {
        assert_eq!(grads.len(), self.params().len(), "gradient length");
        self.backward_through(tape, Some(grads), input_grad);
    }

    /// `∂L/∂input` alone (read it with [`Tape::input_grad`]), skipping the parameter gradient:
    /// what gradient-based planning needs, at about half the cost of [`Mlp::backward`].
    pub fn backward_input(&self, tape: &mut Tape) {
        self.backward_through(tape, None, true);
    }

    fn backward_through(&self, tape: &mut Tape, mut grads: Option<&mut [f32]>, input_grad: bool) {
        let (samples, ld) = (tape.samples, tape.ld);
        let layers = self.layers();
        // `None`: Gₗ is the output gradient; `Some(s)`: it is in `g[s]`.
        let mut current: Option<usize> = None;
        for l in (0..layers).rev() {
            let (n_in, n_out) = (self.sizes()[l], self.sizes()[l + 1]);
            let next_slot = current.map_or(0, |s| 1 - s);
            let [g0, g1] = &mut tape.g;
            let (g, g_next): (&[f32], &mut [f32]) = match current {
                None => (tape.out_grad.as_slice(), g0.as_mut_slice()),
                Some(0) => (g0.as_slice(), g1.as_mut_slice()),
                Some(_) => (g1.as_slice(), g0.as_mut_slice()),
            };
            if let Some(grads) = grads.as_deref_mut() {
                let h_ones = MatRef::with_stride(tape.h[l].as_slice(), n_in + 1, samples, ld);
                let g_view = MatRef::with_stride(g, n_out, samples, ld);
                let out = MatMut::new(&mut grads[self.layer_range(l)], n_in + 1, n_out);
                weight_and_bias_grad(out, h_ones, g_view, &mut tape.gt, &mut tape.products);
            }
            if l == 0 && !input_grad {
                break;
            }
            // Gₗ₋₁ = (Wₗ · Gₗ) ⊙ σ'(zₗ₋₁)
            tape.products.matmul_weights(
                MatMut::with_stride(g_next, n_in, samples, ld),
                (l, MatRef::new(self.weight(l), n_in, n_out), false),
                MatRef::with_stride(g, n_out, samples, ld),
                Init::Zero,
            );
            if l > 0 {
                let d1 = tape.d1[l - 1].as_slice();
                for span in spans(n_in, samples, ld) {
                    super::vecops::mul_inplace(&mut g_next[span.clone()], &d1[span]);
                }
            }
            current = Some(next_slot);
        }
        tape.input_grad_in = if input_grad { current } else { None };
    }
}

/// `[∂L/∂Wₗ; ∂L/∂bₗᵀ] = [hₗ₋₁; 1ᵀ] · Gₗᵀ` (overwriting `out`, `n_in + 1 × n_out`), given the
/// feature-major `h_ones` (`n_in + 1 × samples`, its last row ones) and `g` (`n_out ×
/// samples`). The f32 kernels need `Gᵀ` with unit column stride and get it copied into `gt`;
/// the tiles pack the transposed view directly.
fn weight_and_bias_grad(
    out: MatMut<'_>,
    h_ones: MatRef<'_>,
    g: MatRef<'_>,
    gt: &mut AlignedBuf,
    products: &mut Products,
) {
    if products.path() != TrainPath::F32 {
        return products.matmul(out, h_ones, g.t(), Init::Zero);
    }
    let (n_out, samples) = (g.rows(), g.cols());
    // Rows of Gᵀ start on cache lines, so the kernel's panel loads never straddle two.
    let ld_gt = round_up(n_out);
    let gt = gt.as_mut_slice();
    g.transpose_into(gt, ld_gt);
    products.matmul(
        out,
        h_ones,
        MatRef::with_stride(gt, samples, n_out, ld_gt),
        Init::Zero,
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::activation::Activation;
    use crate::nn::matmul::transpose;
    use crate::nn::reference;
    use crate::nn::train_path::tests::paths_and_activations;
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};

    /// Loss `Σ cᵢⱼ outᵢⱼ` with fixed random `c`: its output gradient is `c`, and the
    /// reference gradient is a central difference of the f64 reference network.
    #[test]
    fn parameter_and_input_gradients_match_finite_differences() {
        for path in TrainPath::available() {
            gradients_match_finite_differences_on(path);
        }
    }

    /// The bf16 tiles within the bounds of [`reference::assert_gradient`].
    fn gradients_match_finite_differences_on(path: TrainPath) {
        let mut rng = StdRng::seed_from_u64(5);
        for act in [Activation::Swish, Activation::Softplus] {
            let mlp = Mlp::new(&[4, 9, 7, 3], act, &mut rng);
            let samples = 6;
            let x: Vec<f32> = (0..samples * 4)
                .map(|_| rng.random_range(-2.0..2.0))
                .collect();
            let c: Vec<f32> = (0..samples * 3)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let loss = |params: &[f64], x: &[f64]| -> f64 {
                (0..samples)
                    .map(|i| {
                        let out =
                            reference::forward(mlp.sizes(), act, params, &x[i * 4..(i + 1) * 4]);
                        (0..3).map(|j| c[i * 3 + j] as f64 * out[j]).sum::<f64>()
                    })
                    .sum()
            };

            let mut tape = Tape::with_path(&mlp, samples, path);
            let ld = tape.ld();
            transpose(&x, samples, 4, 4, tape.input_mut(), ld);
            mlp.forward_train(&mut tape, samples);
            let (_, out_grad) = tape.output_and_grad_mut();
            transpose(&c, samples, 3, 3, out_grad, ld);
            let mut grads = vec![f32::NAN; mlp.params().len()];
            mlp.backward(&mut tape, &mut grads, true);

            let p64: Vec<f64> = mlp.params().iter().map(|&v| v as f64).collect();
            let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
            let fd_params = reference::finite_difference(&p64, |p| loss(p, &x64));
            reference::assert_gradient(
                path,
                &grads,
                &fd_params,
                1e-4,
                &format!("{act:?} parameter gradient on {path}"),
            );

            let fd_input = reference::finite_difference(&x64, |x| loss(&p64, x));
            let mut input_grad = vec![0.0; samples * 4];
            transpose(tape.input_grad(), 4, samples, ld, &mut input_grad, 4);
            reference::assert_gradient(
                path,
                &input_grad,
                &fd_input,
                1e-4,
                &format!("{act:?} input gradient on {path}"),
            );
            // The input gradient alone is the same numbers.
            let (_, out_grad) = tape.output_and_grad_mut();
            transpose(&c, samples, 3, 3, out_grad, ld);
            mlp.backward_input(&mut tape);
            let mut alone = vec![0.0; samples * 4];
            transpose(tape.input_grad(), 4, samples, ld, &mut alone, 4);
            assert_eq!(alone, input_grad, "{act:?} input gradient alone");
        }
    }

    /// The gradient of a batch is the sum of its samples' gradients, within float rounding
    /// (1e-6 of the terms' magnitude). The batch is a partial one on a tape that ran a fuller
    /// batch before, as a trainer reuses its tape. The output layer's bias gradient is also
    /// checked against the row sums of the output gradient, and the first layer's against the
    /// gradient of the weights of an input that is 1 in every sample. A bias row of the fused
    /// weight and bias product that is missing, scaled, stale or misplaced fails one of these.
    #[test]
    fn a_batch_gradient_is_the_sum_of_its_samples_gradients() {
        let mut rng = StdRng::seed_from_u64(11);
        let sizes = [5, 23, 17, 3];
        for (act, path) in paths_and_activations() {
            let mlp = Mlp::new(&sizes, act, &mut rng);
            let (all, batch) = (20, 7);
            // Input feature 0 is 1 for every sample: its weights' gradient is the first
            // layer's bias gradient.
            let x: Vec<f32> = (0..all * 5)
                .map(|i| match i % 5 {
                    0 => 1.0,
                    _ => rng.random_range(-2.0..2.0),
                })
                .collect();
            let c: Vec<f32> = (0..all * 3).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut tape = Tape::with_path(&mlp, all, path);
            let ld = tape.ld();
            let grads_of = |cols: std::ops::Range<usize>| -> Vec<f32> {
                let k = cols.len();
                transpose(
                    &x[cols.start * 5..cols.end * 5],
                    k,
                    5,
                    5,
                    tape.input_mut(),
                    ld,
                );
                mlp.forward_train(&mut tape, k);
                let (_, out_grad) = tape.output_and_grad_mut();
                transpose(&c[cols.start * 3..cols.end * 3], k, 3, 3, out_grad, ld);
                let mut grads = vec![f32::NAN; mlp.params().len()];
                mlp.backward(&mut tape, &mut grads, false);
                grads
            };
            let what = format!("{act:?} on {path}");
            let batch_grads = reference::assert_batch_gradient_sums_its_samples(
                &mlp,
                (all, batch),
                &what,
                grads_of,
            );
            for (k, &b) in batch_grads[mlp.bias_range(2)].iter().enumerate() {
                // The tiles multiply the output gradient rounded to bf16 by the ones row.
                let term = |v: f32| match path {
                    TrainPath::F32 => v as f64,
                    TrainPath::AmxBf16 => {
                        use crate::nn::matmul::{bf16_bits, bf16_value};
                        bf16_value(bf16_bits(v)) as f64
                    }
                };
                let terms = (0..batch).map(|i| term(c[i * 3 + k]));
                let (want, size) = terms.fold((0.0, 0.0), |(s, a), t| (s + t, a + t.abs()));
                assert!((b as f64 - want).abs() <= 1e-6 * size, "{act:?} bias {k}");
            }
        }
    }

    #[test]
    fn forward_train_agrees_with_inference() {
        let mut rng = StdRng::seed_from_u64(6);
        let mlp = Mlp::new(&[3, 20, 2], Activation::Swish, &mut rng);
        let x: Vec<f32> = (0..10 * 3).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut tape = Tape::new(&mlp, 12);
        let ld = tape.ld();
        transpose(&x, 10, 3, 3, tape.input_mut(), ld);
        let out = mlp.forward_train(&mut tape, 10).to_vec();
        let rows = mlp.forward_rows(&x);
        for i in 0..10 {
            for j in 0..2 {
                assert_eq!(out[j * ld + i], rows[i * 2 + j]);
            }
        }
    }
}
