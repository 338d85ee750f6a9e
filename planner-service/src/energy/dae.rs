//! The denoising autoencoder regulariser of Boney et al. (2019): a network `g` trained to map
//! corrupted vectors `x + σε` back to `x`.
//!
//! The optimal denoiser is `g(y) = y + σ² ∇ log p_σ(y)`, so `g(y) − y` estimates the score of the
//! smoothed data density directly, and `‖g(x) − x‖²` serves as a penalty that is small where
//! the data is dense. Unlike DEEN's energy it is not a log-density (the paper's point), but it
//! is the baseline the paper compares with. Works in standardised coordinates like
//! [`super::deen::Deen`].

use super::config::{EnergyConfig, EnergyParts, layer_sizes};
use crate::nn::aligned::AlignedBuf;
use crate::nn::train::run_epochs;
use crate::nn::vecops::add_squared_diff;
use crate::nn::{
    Activation, Adam, FitReport, FlushDenormals, ForwardScratch, Mlp, Normalizer, ShapeError, Tape,
};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use std::time::Instant;

/// A denoising autoencoder on `dim`-dimensional vectors.
#[derive(Clone, Debug)]
pub struct Dae {
    mlp: Mlp,
    normalizer: Normalizer,
    sigma: f32,
    batch_size: usize,
    adam: Adam,
}

/// Buffers of one training step, reused across steps.
#[derive(Clone, Debug)]
pub struct DaeWorkspace {
    tape: Tape,
    /// The batch's clean vectors and noise, feature-major.
    clean: AlignedBuf,
    eps: AlignedBuf,
    grads: Vec<f32>,
}

impl DaeWorkspace {
    /// Buffers for batches of up to `batch_size` vectors.
    pub fn new(dae: &Dae, batch_size: usize) -> Self {
        let tape = Tape::new(&dae.mlp, batch_size);
        let n = dae.dim() * tape.ld();
        Self {
            tape,
            clean: AlignedBuf::zeros(n),
            eps: AlignedBuf::zeros(n),
            grads: vec![0.0; dae.mlp.params().len()],
        }
    }

    /// The noise buffer (`dim × ld`, feature-major) that [`Dae::loss_and_grad`] reads.
    pub fn noise_mut(&mut self) -> &mut [f32] {
        self.eps.as_mut_slice()
    }

    /// The gradient left by the last [`Dae::loss_and_grad`].
    pub fn grads(&self) -> &[f32] {
        &self.grads
    }
}

impl Dae {
    /// An untrained DAE of the configured size (identity normaliser).
    pub fn new(dim: usize, config: &EnergyConfig, rng: &mut StdRng) -> Self {
        assert!(
            config.noise_sigma > 0.0,
            "a DAE needs a positive noise scale"
        );
        let mlp = Mlp::new(&layer_sizes(dim, config, dim), Activation::Softplus, rng);
        Self {
            adam: Adam::new(mlp.params().len(), config.learning_rate),
            mlp,
            normalizer: Normalizer::identity(dim),
            sigma: config.noise_sigma,
            batch_size: config.batch_size.max(1),
        }
    }

    /// A model of the configured size with stored parts (see [`Dae::parts`]).
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
        let mut ws = DaeWorkspace::new(self, self.batch_size.min(n.max(1)));
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
        ws: &mut DaeWorkspace,
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

    /// The loss `Σᵢ ‖g(xᵢ + σεᵢ) − xᵢ‖² / n` of a minibatch, the noise taken from
    /// [`DaeWorkspace::noise_mut`], and its parameter gradient (left in the workspace).
    pub fn loss_and_grad(&self, set: &[f32], batch: &[usize], ws: &mut DaeWorkspace) -> f32 {
        let (d, b, ld, sigma) = (self.dim(), batch.len(), ws.tape.ld(), self.sigma);
        assert!(b > 0 && b <= ld, "batch of {b} for a workspace of {ld}");
        let (eps, clean) = (ws.eps.as_slice(), ws.clean.as_mut_slice());
        let y = ws.tape.input_mut();
        for (col, &idx) in batch.iter().enumerate() {
            for (f, &x) in set[idx * d..(idx + 1) * d].iter().enumerate() {
                clean[f * ld + col] = x;
                y[f * ld + col] = x + sigma * eps[f * ld + col];
            }
        }
        self.mlp.forward_train(&mut ws.tape, b);
        let (out, grad) = ws.tape.output_and_grad_mut();
        let scale = 2.0 / b as f32;
        let mut total = 0.0f32;
        for f in 0..d {
            for i in f * ld..f * ld + b {
                let r = out[i] - clean[i];
                total += r * r;
                grad[i] = scale * r;
            }
        }
        self.mlp.backward(&mut ws.tape, &mut ws.grads, false);
        total / b as f32
    }

    /// Buffers for [`Dae::energy_standardised`] on up to `max_rows` vectors.
    pub fn scratch(&self, max_rows: usize) -> ForwardScratch {
        ForwardScratch::new(&self.mlp, max_rows)
    }

    /// Penalties `‖g(x) − x‖²` of `samples` *standardised* vectors already written
    /// feature-major into `scratch.input_mut()`, into `out[..samples]`. Never allocates.
    pub fn energy_standardised(
        &self,
        samples: usize,
        scratch: &mut ForwardScratch,
        out: &mut [f32],
    ) {
        let ld = scratch.ld();
        let (x, g) = self.mlp.forward_io(samples, scratch);
        let out = &mut out[..samples];
        out.fill(0.0);
        for f in 0..self.dim() {
            add_squared_diff(
                out,
                &g[f * ld..f * ld + samples],
                &x[f * ld..f * ld + samples],
            );
        }
    }

    /// The denoising displacement `g(x) − x` of raw vectors, in standardised units (it
    /// estimates `σ² ∇ log p_σ` there), sample-major. Allocates.
    pub fn displacement_rows(&self, rows: &[f32]) -> Vec<f32> {
        let mut x = rows.to_vec();
        self.normalizer.normalize_rows(&mut x);
        let mut g = self.mlp.forward_rows(&x);
        for (g, x) in g.iter_mut().zip(&x) {
            *g -= x;
        }
        g
    }
}
