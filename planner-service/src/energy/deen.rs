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
//! The model works in standardised coordinates (its [`Normalizer`] is fitted on the training
//! data at every fit); [`Deen::energy_rows`] and [`Deen::score_rows`] take raw vectors.

use super::config::{EnergyConfig, EnergyParts, layer_sizes};
use crate::nn::aligned::AlignedBuf;
use crate::nn::matmul::transpose;
use crate::nn::train::run_epochs;
use crate::nn::{
    Activation, Adam, FitReport, FlushDenormals, ForwardScratch, InputGradTape, Mlp, Normalizer,
    ShapeError,
};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use std::time::Instant;

/// A DEEN on `dim`-dimensional vectors.
#[derive(Clone, Debug)]
pub struct Deen {
    mlp: Mlp,
    normalizer: Normalizer,
    sigma: f32,
    batch_size: usize,
    adam: Adam,
}

/// Buffers of one training step, reused across steps.
#[derive(Clone, Debug)]
pub struct DeenWorkspace {
    tape: InputGradTape,
    /// The batch's noise `ε`, feature-major.
    eps: AlignedBuf,
    grads: Vec<f32>,
}

impl DeenWorkspace {
    /// Buffers for batches of up to `batch_size` vectors.
    pub fn new(deen: &Deen, batch_size: usize) -> Self {
        let tape = InputGradTape::new(&deen.mlp, batch_size);
        let eps = AlignedBuf::zeros(deen.dim() * tape.ld());
        Self {
            tape,
            eps,
            grads: vec![0.0; deen.mlp.params().len()],
        }
    }

    /// The noise buffer (`dim × ld`, feature-major) that [`Deen::loss_and_grad`] reads.
    pub fn noise_mut(&mut self) -> &mut [f32] {
        self.eps.as_mut_slice()
    }

    /// The gradient left by the last [`Deen::loss_and_grad`].
    pub fn grads(&self) -> &[f32] {
        &self.grads
    }
}

impl Deen {
    /// An untrained DEEN of the configured size (identity normaliser).
    pub fn new(dim: usize, config: &EnergyConfig, rng: &mut StdRng) -> Self {
        assert!(
            config.noise_sigma > 0.0,
            "DEEN needs a positive noise scale"
        );
        let mlp = Mlp::new(&layer_sizes(dim, config, 1), Activation::Softplus, rng);
        Self {
            adam: Adam::new(mlp.params().len(), config.learning_rate),
            mlp,
            normalizer: Normalizer::identity(dim),
            sigma: config.noise_sigma,
            batch_size: config.batch_size.max(1),
        }
    }

    /// A model of the configured size with stored parts (see [`Deen::parts`]).
    pub fn from_parts(
        dim: usize,
        config: &EnergyConfig,
        parts: EnergyParts,
    ) -> Result<Self, ShapeError> {
        let mut model = Self::new(dim, config, &mut StdRng::seed_from_u64(0)); // weights replaced
        ShapeError::check(
            "energy parameters",
            model.mlp.params().len(),
            parts.params.len(),
        )?;
        ShapeError::check("energy statistics", dim, parts.normalizer.dim())?;
        model.mlp.params_mut().copy_from_slice(&parts.params);
        model.normalizer = parts.normalizer;
        Ok(model)
    }

    /// A copy of what determines this model's outputs.
    pub fn parts(&self) -> EnergyParts {
        EnergyParts {
            params: self.mlp.params().to_vec(),
            normalizer: self.normalizer.clone(),
        }
    }

    pub fn dim(&self) -> usize {
        self.mlp.in_dim()
    }

    /// The noise scale, in standardised units.
    pub fn sigma(&self) -> f32 {
        self.sigma
    }

    /// Sets the number format of planning-time inference (see [`Mlp::set_inference_precision`]).
    pub fn set_inference_precision(&mut self, precision: proto::InferencePrecision) {
        self.mlp.set_inference_precision(precision);
    }

    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    pub fn normalizer(&self) -> &Normalizer {
        &self.normalizer
    }

    /// Refits the normaliser on `rows` (raw, sample-major, `dim` columns) and trains `epochs`
    /// passes over them, continuing from the current weights. Without data or epochs the model
    /// is left exactly as it is.
    pub fn fit(&mut self, rows: &[f32], epochs: usize, rng: &mut StdRng) -> FitReport {
        let started = Instant::now();
        let n = rows.len() / self.dim();
        if n == 0 || epochs == 0 {
            // Nothing to learn from: keep the statistics as well as the weights.
            return FitReport {
                samples: n,
                epochs,
                loss: f32::NAN,
                ..FitReport::default()
            };
        }
        let _flush = FlushDenormals::new();
        self.normalizer = Normalizer::fit(rows, self.dim());
        let mut set = rows.to_vec();
        self.normalizer.normalize_rows(&mut set);
        let mut order: Vec<usize> = (0..n).collect();
        let mut ws = DeenWorkspace::new(self, self.batch_size.min(n.max(1)));
        let batch_size = self.batch_size;
        let (loss, steps) = run_epochs(&mut order, batch_size, epochs, rng, |batch, rng| {
            self.train_step(&set, batch, &mut ws, rng)
        });
        FitReport {
            samples: n,
            epochs,
            steps,
            loss,
            seconds: started.elapsed().as_secs_f32(),
            ..FitReport::default()
        }
    }

    /// One Adam step on a minibatch (`batch`: indices into the standardised, sample-major
    /// `set`), with fresh noise. Returns the minibatch's loss before the step.
    pub fn train_step(
        &mut self,
        set: &[f32],
        batch: &[usize],
        ws: &mut DeenWorkspace,
        rng: &mut StdRng,
    ) -> f32 {
        let ld = ws.tape.ld();
        for row in ws.eps.as_mut_slice()[..self.dim() * ld].chunks_mut(ld) {
            for e in &mut row[..batch.len()] {
                *e = rng.sample(StandardNormal);
            }
        }
        let loss = self.loss_and_grad(set, batch, ws);
        self.adam.step(self.mlp.params_mut(), &ws.grads);
        loss
    }

    /// The DEEN loss `Σᵢ ‖xᵢ − yᵢ + σ² ∂E/∂yᵢ‖² / n` of a minibatch with `yᵢ = xᵢ + σεᵢ`, the
    /// noise taken from [`DeenWorkspace::noise_mut`], and its parameter gradient (left in the
    /// workspace).
    pub fn loss_and_grad(&self, set: &[f32], batch: &[usize], ws: &mut DeenWorkspace) -> f32 {
        let (d, b, ld, sigma) = (self.dim(), batch.len(), ws.tape.ld(), self.sigma);
        assert!(b > 0 && b <= ld, "batch of {b} for a workspace of {ld}");
        let eps = ws.eps.as_slice();
        let y = ws.tape.input_mut();
        for (col, &idx) in batch.iter().enumerate() {
            for (f, &x) in set[idx * d..(idx + 1) * d].iter().enumerate() {
                y[f * ld + col] = x + sigma * eps[f * ld + col];
            }
        }
        self.mlp.input_gradient_train(&mut ws.tape, b);
        let (_, score, v) = ws.tape.input_score_and_grad_mut();
        // r = x − y + σ² s = σ² s − σ ε;  ∂L/∂s = 2 σ² r / n.
        let (sigma2, scale) = (sigma * sigma, 2.0 * sigma * sigma / b as f32);
        let mut total = 0.0f32;
        for f in 0..d {
            for i in f * ld..f * ld + b {
                let r = sigma2 * score[i] - sigma * eps[i];
                total += r * r;
                v[i] = scale * r;
            }
        }
        self.mlp
            .input_gradient_backward(&mut ws.tape, &mut ws.grads);
        total / b as f32
    }

    /// Buffers for [`Deen::energy_standardised`] on up to `max_rows` vectors.
    pub fn scratch(&self, max_rows: usize) -> ForwardScratch {
        ForwardScratch::new(&self.mlp, max_rows)
    }

    /// Energies of `samples` *standardised* vectors already written feature-major into
    /// `scratch.input_mut()`: the first `samples` entries of the result. Never allocates.
    pub fn energy_standardised<'s>(
        &self,
        samples: usize,
        scratch: &'s mut ForwardScratch,
    ) -> &'s [f32] {
        &self.mlp.forward(samples, scratch)[..samples]
    }

    /// Energies of raw vectors (`rows`: sample-major, `dim` columns). Allocates.
    pub fn energy_rows(&self, rows: &[f32]) -> Vec<f32> {
        let mut x = rows.to_vec();
        self.normalizer.normalize_rows(&mut x);
        self.mlp.forward_rows(&x)
    }

    /// The model's score `−∂E/∂x` in raw coordinates (the chain rule through the normaliser
    /// divides by each dimension's standard deviation), sample-major like `rows`. Allocates.
    pub fn score_rows(&self, rows: &[f32]) -> Vec<f32> {
        let (d, n) = (self.dim(), rows.len() / self.dim());
        let mut x = rows.to_vec();
        self.normalizer.normalize_rows(&mut x);
        let mut tape = InputGradTape::new(&self.mlp, n);
        let ld = tape.ld();
        transpose(&x, n, d, d, tape.input_mut(), ld);
        let grad = self.mlp.input_gradient_train(&mut tape, n);
        let mut out = vec![0.0; n * d];
        transpose(grad, d, n, ld, &mut out, d);
        for row in out.chunks_exact_mut(d) {
            for (f, v) in row.iter_mut().enumerate() {
                *v = -*v / self.normalizer.std()[f];
            }
        }
        out
    }
}
