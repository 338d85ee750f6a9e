//! The Deep Energy Estimator Network (Saremi et al. 2018): a scalar network `E(y)` whose input
//! gradient is trained to denoise.
//!
//! For data `x` corrupted as `y = x + σε`, the least-squares denoiser is
//! `E[x | y] = y + σ² ∇ log p_σ(y)` (Miyasawa), where `p_σ` is the data density smoothed by
//! `N(0, σ²)`. DEEN parameterises the score as `−∂E/∂y` and minimises
//! `‖x − y + σ² ∂E/∂y‖²` (mean over the batch), so `E` learns `−log p_σ` up to a constant:
//! an energy that is low on familiar transitions and grows away from them. The gradient of this
//! loss needs double backpropagation ([`crate::nn::double_backprop`]).
//!
//! The model works in standardised coordinates (its [`Normalizer`](crate::nn::Normalizer) is
//! fitted on the training data at every fit); [`Deen::energy_rows`] and [`Deen::score_rows`]
//! take raw vectors.

use super::denoiser::{Denoiser, DenoisingLoss, Workspace};
use crate::nn::matmul::transpose;
use crate::nn::{ForwardScratch, InputGradTape, Mlp, TrainPath};

/// DEEN's loss: the network outputs a scalar energy whose input gradient denoises.
#[derive(Clone, Copy, Debug)]
pub struct DeenLoss;

/// A DEEN on `dim`-dimensional vectors.
pub type Deen = Denoiser<DeenLoss>;

/// Buffers of one DEEN training step, reused across steps.
pub type DeenWorkspace = Workspace<DeenLoss>;

impl DenoisingLoss for DeenLoss {
    const NAME: &'static str = "DEEN";
    type Tape = InputGradTape;

    fn outputs(_dim: usize) -> usize {
        1
    }

    fn tape(mlp: &Mlp, batch_size: usize, path: TrainPath) -> InputGradTape {
        InputGradTape::with_path(mlp, batch_size, path)
    }

    fn ld(tape: &InputGradTape) -> usize {
        tape.ld()
    }

    fn path(tape: &InputGradTape) -> TrainPath {
        tape.path()
    }

    /// `Σᵢ ‖xᵢ − yᵢ + σ² ∂E/∂yᵢ‖² / n` with `yᵢ = xᵢ + σεᵢ`, per dimension with its own `σ_f`
    /// and weight (see [`Denoiser`]'s noise units; `σ` and 1 in standardised units).
    fn loss_and_grad(
        deen: &Deen,
        set: &[f32],
        batch: &[usize],
        tape: &mut InputGradTape,
        eps: &[f32],
        grads: &mut [f32],
    ) -> f32 {
        let (d, b, ld) = (deen.dim(), batch.len(), tape.ld());
        let (noise, weights) = (deen.noise_scales(), deen.loss_weights());
        let y = tape.input_mut();
        for (col, &idx) in batch.iter().enumerate() {
            for (f, &x) in set[idx * d..(idx + 1) * d].iter().enumerate() {
                y[f * ld + col] = x + noise[f] * eps[f * ld + col];
            }
        }
        deen.mlp().input_gradient_train(tape, b);
        let (_, score, v) = tape.input_score_and_grad_mut();
        // r = x − y + σ² s = σ² s − σ ε;  L = Σ w r² / n;  ∂L/∂s = 2 w σ² r / n.
        let mut total = 0.0f32;
        for (f, (&sigma, &w)) in noise.iter().zip(weights).enumerate().take(d) {
            let (sigma2, scale) = (sigma * sigma, 2.0 * w * sigma * sigma / b as f32);
            for i in f * ld..f * ld + b {
                let r = sigma2 * score[i] - sigma * eps[i];
                total += w * r * r;
                v[i] = scale * r;
            }
        }
        deen.mlp().input_gradient_backward(tape, grads);
        total / b as f32
    }
}

impl Deen {
    /// Buffers for [`Deen::energy_standardised`] on up to `max_rows` vectors.
    pub fn scratch(&self, max_rows: usize) -> ForwardScratch {
        ForwardScratch::new(self.mlp(), max_rows)
    }

    /// Energies of `samples` *standardised* vectors already written feature-major into
    /// `scratch.input_mut()`: the first `samples` entries of the result. Never allocates.
    pub fn energy_standardised<'s>(
        &self,
        samples: usize,
        scratch: &'s mut ForwardScratch,
    ) -> &'s [f32] {
        &self.mlp().forward(samples, scratch)[..samples]
    }

    /// Energies of raw vectors (`rows`: sample-major, `dim` columns). Allocates.
    pub fn energy_rows(&self, rows: &[f32]) -> Vec<f32> {
        let mut x = rows.to_vec();
        self.normalizer().normalize_rows(&mut x);
        self.mlp().forward_rows(&x)
    }

    /// The model's score `−∂E/∂x` in raw coordinates (the chain rule through the normaliser
    /// divides by each dimension's standard deviation), sample-major like `rows`. Allocates.
    pub fn score_rows(&self, rows: &[f32]) -> Vec<f32> {
        let (d, n) = (self.dim(), rows.len() / self.dim());
        let mut x = rows.to_vec();
        self.normalizer().normalize_rows(&mut x);
        let mut tape = InputGradTape::new(self.mlp(), n);
        let ld = tape.ld();
        transpose(&x, n, d, d, tape.input_mut(), ld);
        let grad = self.mlp().input_gradient_train(&mut tape, n);
        let mut out = vec![0.0; n * d];
        transpose(grad, d, n, ld, &mut out, d);
        for row in out.chunks_exact_mut(d) {
            for (f, v) in row.iter_mut().enumerate() {
                *v = -*v / self.normalizer().std()[f];
            }
        }
        out
    }
}
