//! What the two regularisers share: a softplus MLP on standardised vectors, trained with Adam
//! to undo Gaussian corruption `y = x + σε` of its training data.
//!
//! **Noise units.** With [`NoiseUnits::Standardised`] `σ` is applied to every dimension after
//! it has been scaled to unit variance. With [`NoiseUnits::Raw`] it is in the data's own
//! units, as the paper corrupts its replay buffer: dimension `f` with standard deviation `s_f`
//! gets `σ_f = σ / s_f` in standardised coordinates, and each dimension's residual is weighted
//! by `s_f²` (over their mean), which makes the loss the raw-coordinate one up to a constant
//! factor. A dimension that varies less than `σ` is scaled by `σ` instead of `s_f` (so
//! `σ_f ≤ 1` and the network never sees inputs blown up by a tiny scale): the noise smooths it
//! out either way. The energy is a log-density up to a constant in any affine coordinates, so
//! planning reads it in the model's own standardised coordinates whatever the units.
//!
//! Both estimate the score of the smoothed data density (Miyasawa: the optimal denoiser is
//! `y + σ² ∇ log p_σ(y)`); they differ only in what the network outputs and so in their loss.
//! A [`DenoisingLoss`] names that difference — the DAE's network outputs the clean vector, the
//! DEEN's a scalar energy whose input gradient is the score — and [`Denoiser`] does everything
//! else once: construction, stored parts, the normaliser, the epoch loop and the Adam step.

use super::config::{EnergyConfig, EnergyParts, NoiseUnits, layer_sizes};
use crate::nn::aligned::AlignedBuf;
use crate::nn::train::{FitBudget, run_epochs};
use crate::nn::{
    Activation, Adam, FitReport, FlushDenormals, Mlp, Normalizer, ShapeError, TrainPath,
};
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
    /// A tape for minibatches of up to `batch_size` vectors, its products on `path`.
    fn tape(mlp: &Mlp, batch_size: usize, path: TrainPath) -> Self::Tape;
    /// Row stride of the tape's feature-major buffers.
    fn ld(tape: &Self::Tape) -> usize;
    /// The kernels the tape's products run on.
    fn path(tape: &Self::Tape) -> TrainPath;
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
    units: NoiseUnits,
    /// The noise's standard deviation per dimension, in standardised coordinates.
    noise: Vec<f32>,
    /// Each dimension's weight in the loss (1 in standardised units).
    weights: Vec<f32>,
    batch_size: usize,
    /// The training path its fits use; `None`: the one measured fastest for its shape.
    train_path: Option<TrainPath>,
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
    /// Buffers for batches of up to `batch_size` vectors, on the model's pinned training path
    /// or else the one measured fastest for its network (see [`TrainPath::measured`]).
    pub fn new(model: &Denoiser<L>, batch_size: usize) -> Self {
        let mlp = &model.mlp;
        let path = model
            .train_path
            .unwrap_or_else(|| TrainPath::measured(mlp.sizes(), mlp.activation(), batch_size));
        Self::with_path(model, batch_size, path)
    }

    /// Buffers for batches of up to `batch_size` vectors, multiplying on `path`.
    pub fn with_path(model: &Denoiser<L>, batch_size: usize, path: TrainPath) -> Self {
        let tape = L::tape(&model.mlp, batch_size, path);
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

    /// The kernels this workspace's products run on.
    pub fn path(&self) -> TrainPath {
        L::path(&self.tape)
    }
}

impl<L: DenoisingLoss> Denoiser<L> {
    /// Pins the training path of its fits (`None`: measured, the default).
    pub fn pin_train_path(&mut self, path: Option<TrainPath>) {
        self.train_path = path;
    }

    /// An untrained model of the configured size (identity normaliser).
    pub fn new(dim: usize, config: &EnergyConfig, rng: &mut StdRng) -> Self {
        assert!(
            config.noise_sigma > 0.0,
            "{} needs a positive noise scale",
            L::NAME
        );
        let sizes = layer_sizes(dim, config, L::outputs(dim));
        let mlp = Mlp::new(&sizes, Activation::Softplus, rng);
        let mut model = Self {
            adam: Adam::new(mlp.params().len(), config.learning_rate),
            mlp,
            normalizer: Normalizer::identity(dim),
            sigma: config.noise_sigma,
            units: config.noise_units,
            noise: Vec::new(),
            weights: Vec::new(),
            batch_size: config.batch_size.max(1),
            train_path: None,
            loss: PhantomData,
        };
        model.derive_noise();
        model
    }

    /// Sets the per-dimension noise and loss weights from `σ`, the units and the normaliser.
    fn derive_noise(&mut self) {
        let std = self.normalizer.std();
        match self.units {
            NoiseUnits::Standardised => {
                self.noise = vec![self.sigma; std.len()];
                self.weights = vec![1.0; std.len()];
            }
            NoiseUnits::Raw => {
                self.noise = std.iter().map(|s| self.sigma / s).collect();
                let mean = std.iter().map(|s| s * s).sum::<f32>() / std.len().max(1) as f32;
                self.weights = std.iter().map(|s| s * s / mean).collect();
            }
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
        model.derive_noise();
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

    /// The noise scale `σ`, in [`Denoiser::noise_units`].
    pub fn sigma(&self) -> f32 {
        self.sigma
    }

    pub fn noise_units(&self) -> NoiseUnits {
        self.units
    }

    /// The noise's standard deviation per dimension in the model's standardised coordinates
    /// (`σ` everywhere in standardised units).
    pub fn noise_scales(&self) -> &[f32] {
        &self.noise
    }

    /// Each dimension's weight in the denoising loss (1 everywhere in standardised units).
    pub fn loss_weights(&self) -> &[f32] {
        &self.weights
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
        if self.units == NoiseUnits::Raw {
            self.normalizer = self.normalizer.clone().with_min_std(self.sigma);
        }
        self.derive_noise();
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
