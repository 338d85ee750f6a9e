//! What the two regularisers share: a softplus MLP on standardised vectors, trained with Adam
//! to undo Gaussian corruption `y = x + σε` of its training data.
//!
//! Both estimate the score of the smoothed data density (Miyasawa: the optimal denoiser is
//! `y + σ² ∇ log p_σ(y)`); they differ only in what the network outputs and so in their loss.
//! A [`DenoisingLoss`] names that difference — the DAE's network outputs the clean vector, the
//! DEEN's a scalar energy whose input gradient is the score — and [`Denoiser`] does everything
//! else once: construction, stored parts, the normaliser, the epoch loop and the Adam step.

use super::config::{EnergyConfig, EnergyParts, layer_sizes};
use crate::nn::aligned::AlignedBuf;
use crate::nn::train::{FitBudget, run_epochs};
use crate::nn::{Activation, Adam, FitReport, FlushDenormals, Mlp, Normalizer, ShapeError};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use std::marker::PhantomData;
use std::time::Instant;

/// The loss that makes a [`Denoiser`] a particular regulariser.
pub trait DenoisingLoss {
    /// The regulariser's name in messages ("DEEN", "DAE").
    const NAME: &'static str;
    /// Training buffers of one minibatch besides the noise and the gradient.
    type Tape: Clone + std::fmt::Debug;
    /// Outputs of the network for `dim`-dimensional inputs.
    fn outputs(dim: usize) -> usize;
    /// A tape for minibatches of up to `batch_size` vectors.
    fn tape(mlp: &Mlp, batch_size: usize) -> Self::Tape;
    /// Row stride of the tape's feature-major buffers.
    fn ld(tape: &Self::Tape) -> usize;
    /// The loss of a minibatch (`batch`: indices into the standardised, sample-major `set`)
    /// corrupted by the noise `eps` (feature-major, [`DenoisingLoss::ld`] columns), and its
    /// parameter gradient into `grads`.
    fn loss_and_grad(
        model: &Denoiser<Self>,
        set: &[f32],
        batch: &[usize],
        tape: &mut Self::Tape,
        eps: &[f32],
        grads: &mut [f32],
    ) -> f32
    where
        Self: Sized;
}

/// A network trained to denoise `dim`-dimensional vectors, with the loss `L`.
#[derive(Clone, Debug)]
pub struct Denoiser<L> {
    mlp: Mlp,
    normalizer: Normalizer,
    sigma: f32,
    batch_size: usize,
    adam: Adam,
    loss: PhantomData<L>,
}

/// Buffers of one training step, reused across steps.
#[derive(Clone, Debug)]
pub struct Workspace<L: DenoisingLoss> {
    tape: L::Tape,
    /// The batch's noise `ε`, feature-major.
    eps: AlignedBuf,
    grads: Vec<f32>,
}

impl<L: DenoisingLoss> Workspace<L> {
    /// Buffers for batches of up to `batch_size` vectors.
    pub fn new(model: &Denoiser<L>, batch_size: usize) -> Self {
        let tape = L::tape(&model.mlp, batch_size);
        let eps = AlignedBuf::zeros(model.dim() * L::ld(&tape));
        Self {
            tape,
            eps,
            grads: vec![0.0; model.mlp.params().len()],
        }
    }

    /// The noise buffer (`dim × ld`, feature-major) that [`Denoiser::loss_and_grad`] reads.
    pub fn noise_mut(&mut self) -> &mut [f32] {
        self.eps.as_mut_slice()
    }

    /// The gradient left by the last [`Denoiser::loss_and_grad`].
    pub fn grads(&self) -> &[f32] {
        &self.grads
    }
}

impl<L: DenoisingLoss> Denoiser<L> {
    /// An untrained model of the configured size (identity normaliser).
    pub fn new(dim: usize, config: &EnergyConfig, rng: &mut StdRng) -> Self {
        assert!(
            config.noise_sigma > 0.0,
            "{} needs a positive noise scale",
            L::NAME
        );
        let sizes = layer_sizes(dim, config, L::outputs(dim));
        let mlp = Mlp::new(&sizes, Activation::Softplus, rng);
        Self {
            adam: Adam::new(mlp.params().len(), config.learning_rate),
            mlp,
            normalizer: Normalizer::identity(dim),
            sigma: config.noise_sigma,
            batch_size: config.batch_size.max(1),
            loss: PhantomData,
        }
    }

    /// A model of the configured size with stored parts (see [`Denoiser::parts`]).
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

    /// Runs inference on one kernel path, unmeasured (benchmarks and tests of every path).
    pub fn set_kernel_path(&mut self, path: crate::nn::KernelPath) {
        self.mlp.set_kernel_path(path);
    }

    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    pub fn normalizer(&self) -> &Normalizer {
        &self.normalizer
    }

    /// Refits the normaliser on `rows` (raw, sample-major, `dim` columns) and trains the
    /// budget's epochs over them (or until it says stop), continuing from the current weights.
    /// Without data or epochs the model is left exactly as it is.
    pub fn fit(
        &mut self,
        rows: &[f32],
        budget: impl Into<FitBudget>,
        rng: &mut StdRng,
    ) -> FitReport {
        let budget = budget.into();
        let epochs = budget.epochs;
        let started = Instant::now();
        let n = rows.len() / self.dim();
        if n == 0 || epochs == 0 {
            return FitReport::untrained(n, epochs);
        }
        let _flush = FlushDenormals::new();
        self.normalizer = Normalizer::fit(rows, self.dim());
        let mut set = rows.to_vec();
        self.normalizer.normalize_rows(&mut set);
        let mut order: Vec<usize> = (0..n).collect();
        let mut ws = Workspace::new(self, self.batch_size.min(n.max(1)));
        let batch_size = self.batch_size;
        let run = run_epochs(&mut order, batch_size, &budget, rng, |batch, rng| {
            self.train_step(&set, batch, &mut ws, rng)
        });
        FitReport {
            samples: n,
            epochs,
            steps: run.steps,
            loss: run.loss,
            stopped: run.stopped,
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
        ws: &mut Workspace<L>,
        rng: &mut StdRng,
    ) -> f32 {
        let ld = L::ld(&ws.tape);
        for row in ws.eps.as_mut_slice()[..self.dim() * ld].chunks_mut(ld) {
            for e in &mut row[..batch.len()] {
                *e = rng.sample(StandardNormal);
            }
        }
        let loss = self.loss_and_grad(set, batch, ws);
        self.adam.step(self.mlp.params_mut(), &ws.grads);
        loss
    }

    /// The minibatch loss with the noise in [`Workspace::noise_mut`], and its parameter
    /// gradient (left in the workspace).
    pub fn loss_and_grad(&self, set: &[f32], batch: &[usize], ws: &mut Workspace<L>) -> f32 {
        let ld = L::ld(&ws.tape);
        let b = batch.len();
        assert!(b > 0 && b <= ld, "batch of {b} for a workspace of {ld}");
        L::loss_and_grad(
            self,
            set,
            batch,
            &mut ws.tape,
            ws.eps.as_slice(),
            &mut ws.grads,
        )
    }
}
