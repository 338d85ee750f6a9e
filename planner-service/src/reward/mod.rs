//! A learned reward: for systems whose reward is only observed (`reward = "learned"`), an MLP
//! `r̂(s, a, s')` trained on the rewards agents send, so that imagination can score transitions
//! no formula describes.
//!
//! **Inputs.** `[features(s), a, features(s')]`: each state goes through the task's own model
//! transforms ([`proto::Task::state_features`], angles as `sin`/`cos`), the transforms the
//! dynamics model sees its input through, so an angle that wraps is one place to this model as
//! it is to the dynamics. Inputs and the reward are standardised with statistics of the whole
//! training data (refitted at every fit, as the dynamics' are).
//!
//! **Training.** Mean squared error of the standardised reward, Adam with the dynamics' step
//! size, batch size and weight decay, for the dynamics' epochs of each retraining (the same
//! schedule, [`crate::trainer::retrain`]); the epoch loop is [`crate::nn::train::run_epochs`].
//!
//! **Planning.** [`RewardModel::predict`] scores a whole population's transitions in one
//! batched forward pass (in the run's inference precision) without allocating;
//! [`RewardModel::predict_with_gradient`] also gives `∂r̂/∂s`, `∂r̂/∂a`, `∂r̂/∂s'` for Adam
//! (f32, through the training pass; checked against finite differences in the tests).
//!
//! **Before training.** An untrained model's predictions mean nothing: [`RewardModel::is_trained`]
//! is false until a fit has taken an optimiser step, and a run plans only with models that are
//! all trained ([`crate::models::Models::is_trained`]).

use crate::data::Transitions;
use crate::dynamics::DynamicsConfig;
use crate::nn::train::{FitBudget, Minibatches, fit_minibatches, forward_minibatch};
use crate::nn::{
    Activation, Adam, FitReport, FlushDenormals, ForwardScratch, Mlp, Normalizer, ShapeError, Tape,
};
use proto::Task;
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// The reward model's sizes (its training settings are the dynamics model's).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RewardConfig {
    /// Hidden layers (Swish activations, as the dynamics model's).
    pub hidden_layers: usize,
    /// Units per hidden layer.
    pub hidden_size: usize,
}

impl Default for RewardConfig {
    /// 2 × 200: a reward is one number of the transition, a smaller function to learn than
    /// the dynamics' whole next state (3 × 200 in the paper's smallest preset).
    fn default() -> Self {
        Self {
            hidden_layers: 2,
            hidden_size: 200,
        }
    }
}

/// Layer sizes `[2 · state features + action, hidden…, 1]` of `task`'s reward network.
pub fn layer_sizes(task: &Task, config: &RewardConfig) -> Vec<usize> {
    let mut sizes = vec![input_dim(task)];
    sizes.extend(std::iter::repeat_n(
        config.hidden_size,
        config.hidden_layers,
    ));
    sizes.push(1);
    sizes
}

fn input_dim(task: &Task) -> usize {
    2 * task.state_feature_dim + task.act_dim
}

/// Everything that determines the model's predictions — what persistence stores. (Adam's
/// moments are not included: a restored model's optimiser starts afresh.)
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RewardParts {
    /// The network's parameters, laid out as [`Mlp::params`].
    pub params: Vec<f32>,
    pub input_norm: Normalizer,
    /// Mean and scale of the reward (one dimension).
    pub target_norm: Normalizer,
    /// Whether a fit has taken an optimiser step (see [`RewardModel::is_trained`]).
    pub trained: bool,
}

/// A reward model for one task (see the module docs).
#[derive(Clone, Debug)]
pub struct RewardModel {
    task: &'static Task,
    mlp: Mlp,
    input_norm: Normalizer,
    target_norm: Normalizer,
    adam: Adam,
    batch_size: usize,
    weight_decay: f32,
    trained: bool,
}

/// Preallocated buffers for [`RewardModel::predict`] on up to `capacity` rows.
#[derive(Clone, Debug)]
pub struct RewardScratch {
    forward: ForwardScratch,
    features: Vec<f32>,
}

impl RewardScratch {
    /// Whether these buffers serve `model` on `rows` rows.
    pub fn fits(&self, model: &RewardModel, rows: usize) -> bool {
        self.forward.fits(&model.mlp, rows) && self.features.len() == model.task.state_feature_dim
    }
}

/// Preallocated buffers for [`RewardModel::predict_with_gradient`] on up to `capacity` rows.
#[derive(Clone, Debug)]
pub struct RewardTape {
    tape: Tape,
    features: Vec<f32>,
    d_features: Vec<f32>,
}

impl RewardTape {
    /// Whether these buffers serve `model` on `rows` rows.
    pub fn fits(&self, model: &RewardModel, rows: usize) -> bool {
        self.tape.fits(&model.mlp, rows) && self.features.len() == model.task.state_feature_dim
    }
}

impl RewardModel {
    /// An untrained model of `config`'s sizes for `task`, trained with `training`'s step size,
    /// batch size and weight decay (identity normalisers).
    pub fn new(
        task: &'static Task,
        config: &RewardConfig,
        training: &DynamicsConfig,
        rng: &mut StdRng,
    ) -> Self {
        let mlp = Mlp::new(&layer_sizes(task, config), Activation::Swish, rng);
        Self {
            task,
            adam: Adam::new(mlp.params().len(), training.learning_rate),
            input_norm: Normalizer::identity(mlp.in_dim()),
            target_norm: Normalizer::identity(1),
            mlp,
            batch_size: training.batch_size.max(1),
            weight_decay: training.weight_decay,
            trained: false,
        }
    }

    /// A model of `config`'s sizes with stored parts (see [`RewardModel::parts`]).
    pub fn from_parts(
        task: &'static Task,
        config: &RewardConfig,
        training: &DynamicsConfig,
        parts: RewardParts,
    ) -> Result<Self, ShapeError> {
        // The weights are replaced below.
        let mut model = Self::new(task, config, training, &mut StdRng::seed_from_u64(0));
        ShapeError::check(
            "reward parameters",
            model.mlp.params().len(),
            parts.params.len(),
        )?;
        ShapeError::check(
            "reward input statistics",
            model.mlp.in_dim(),
            parts.input_norm.dim(),
        )?;
        ShapeError::check("reward statistics", 1, parts.target_norm.dim())?;
        model.mlp.params_mut().copy_from_slice(&parts.params);
        model.input_norm = parts.input_norm;
        model.target_norm = parts.target_norm;
        model.trained = parts.trained;
        Ok(model)
    }

    /// A copy of what determines this model's predictions.
    pub fn parts(&self) -> RewardParts {
        RewardParts {
            params: self.mlp.params().to_vec(),
            input_norm: self.input_norm.clone(),
            target_norm: self.target_norm.clone(),
            trained: self.trained,
        }
    }

    /// Whether a fit has taken at least one optimiser step: before that the model's
    /// predictions are those of random weights, and nothing may plan with them.
    pub fn is_trained(&self) -> bool {
        self.trained
    }

    /// The network: `2 · state_feature_dim + act_dim` inputs, one output.
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    /// Sets the number format of planning-time inference (see [`Mlp::set_inference_precision`]).
    pub fn set_inference_precision(&mut self, precision: proto::InferencePrecision) {
        self.mlp.set_inference_precision(precision);
    }

    /// Runs inference on one kernel path, unmeasured (benchmarks and tests of every path).
    pub fn set_kernel_path(&mut self, path: crate::nn::KernelPath) {
        self.mlp.set_kernel_path(path);
    }

    /// The raw model inputs `[features(s), a, features(s')]` of every transition, sample-major.
    fn raw_inputs(&self, data: &Transitions) -> Vec<f32> {
        let (f, a) = (self.task.state_feature_dim, self.task.act_dim);
        let mut inputs = vec![0.0; data.len() * (2 * f + a)];
        for (i, row) in inputs.chunks_exact_mut(2 * f + a).enumerate() {
            let (s, u, s1) = data.row(i);
            self.task.state_features(s, &mut row[..f]);
            row[f..f + a].copy_from_slice(u);
            self.task.state_features(s1, &mut row[f + a..]);
        }
        inputs
    }

    /// Refits the statistics on `data` and trains the budget's epochs over it (or until it
    /// says stop) on the rewards its agents reported, continuing from the current weights.
    /// Without data or epochs the model is left exactly as it is.
    pub fn fit(
        &mut self,
        data: &Transitions,
        budget: impl Into<FitBudget>,
        rng: &mut StdRng,
    ) -> FitReport {
        let budget = budget.into();
        let (epochs, n, started) = (budget.epochs, data.len(), Instant::now());
        if n == 0 || epochs == 0 {
            return FitReport::untrained(n, epochs);
        }
        let _flush = FlushDenormals::new();
        let dim = self.mlp.in_dim();
        let mut inputs = self.raw_inputs(data);
        let mut targets = data.rewards().to_vec();
        self.input_norm = Normalizer::fit(&inputs, dim);
        self.target_norm = Normalizer::fit(&targets, 1);
        self.input_norm.normalize_rows(&mut inputs);
        self.target_norm.normalize_rows(&mut targets);
        let settings = Minibatches {
            batch_size: self.batch_size,
            weight_decay: self.weight_decay,
        };
        let run = fit_minibatches(
            &mut self.mlp,
            &mut self.adam,
            settings,
            n,
            &budget,
            rng,
            |mlp, batch, tape| squared_error_and_grad(mlp, &inputs, &targets, batch, tape),
        );
        self.trained |= run.steps > 0;
        let mse = self.mean_squared_error(data);
        tracing::debug!(
            steps = run.steps,
            loss = run.loss,
            mse,
            "reward model trained"
        );
        FitReport {
            samples: n,
            epochs,
            steps: run.steps,
            loss: run.loss,
            mse: Some(mse),
            stopped: run.stopped,
            seconds: started.elapsed().as_secs_f32(),
            ..FitReport::default()
        }
    }

    /// Mean squared error of the predicted rewards of `data` in units of the reward's variance
    /// in the last fit's data (1 = no better than predicting the mean). Allocates.
    pub fn mean_squared_error(&self, data: &Transitions) -> f32 {
        let n = data.len();
        if n == 0 {
            return f32::NAN;
        }
        let mut scratch = self.scratch(n);
        let mut predicted = vec![0.0; n];
        self.predict(
            data.obs(),
            data.act(),
            data.next_obs(),
            n,
            &mut scratch,
            &mut predicted,
        );
        let scale = self.target_norm.std()[0];
        let sum: f64 = predicted
            .iter()
            .zip(data.rewards())
            .map(|(p, r)| (((p - r) / scale) as f64).powi(2))
            .sum();
        (sum / n as f64) as f32
    }

    /// Buffers for [`RewardModel::predict`] on up to `max_rows` rows.
    pub fn scratch(&self, max_rows: usize) -> RewardScratch {
        RewardScratch {
            forward: ForwardScratch::new(&self.mlp, max_rows),
            features: vec![0.0; self.task.state_feature_dim],
        }
    }

    /// Buffers for [`RewardModel::predict_with_gradient`] on up to `max_rows` rows.
    pub fn tape(&self, max_rows: usize) -> RewardTape {
        let f = self.task.state_feature_dim;
        RewardTape {
            tape: Tape::for_planning(&self.mlp, max_rows),
            features: vec![0.0; f],
            d_features: vec![0.0; f],
        }
    }

    /// Writes the standardised inputs of `rows` transitions feature-major (row stride `ld`).
    fn fill_inputs(
        &self,
        (obs, act, next_obs): (&[f32], &[f32], &[f32]),
        rows: usize,
        features: &mut [f32],
        input: &mut [f32],
        ld: usize,
    ) {
        let (o, a, f) = (
            self.task.obs_dim,
            self.task.act_dim,
            self.task.state_feature_dim,
        );
        assert!(
            obs.len() >= rows * o && act.len() >= rows * a && next_obs.len() >= rows * o,
            "buffers shorter than {rows} rows"
        );
        for i in 0..rows {
            self.task.state_features(&obs[i * o..(i + 1) * o], features);
            for (k, &v) in features.iter().chain(&act[i * a..(i + 1) * a]).enumerate() {
                input[k * ld + i] = self.input_norm.normalize(k, v);
            }
            self.task
                .state_features(&next_obs[i * o..(i + 1) * o], features);
            for (j, &v) in features.iter().enumerate() {
                let k = f + a + j;
                input[k * ld + i] = self.input_norm.normalize(k, v);
            }
        }
    }

    /// The predicted reward of each of `rows` transitions into `out[..rows]` (`obs`, `act`,
    /// `next_obs`: `rows` rows each, sample-major). One batched forward pass; never allocates.
    pub fn predict(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        rows: usize,
        scratch: &mut RewardScratch,
        out: &mut [f32],
    ) {
        assert!(
            scratch.fits(self, rows),
            "reward scratch does not fit {rows} rows of this model"
        );
        let ld = scratch.forward.ld();
        let RewardScratch { forward, features } = scratch;
        self.fill_inputs(
            (obs, act, next_obs),
            rows,
            features,
            forward.input_mut(),
            ld,
        );
        let predicted = self.mlp.forward(rows, forward);
        let (mean, std) = (self.target_norm.mean()[0], self.target_norm.std()[0]);
        for (r, &z) in out[..rows].iter_mut().zip(&predicted[..rows]) {
            *r = mean + std * z;
        }
    }

    /// [`RewardModel::predict`] in f32 through the training pass, with the gradient of each
    /// row's reward: `∂r̂/∂s` into `d_obs`, `∂r̂/∂a` into `d_act`, `∂r̂/∂s'` into `d_next`
    /// (sample-major, overwritten). The chain rule runs through the reward's scale, the input
    /// normaliser and the task's state transforms. Never allocates.
    #[allow(clippy::too_many_arguments)]
    pub fn predict_with_gradient(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        rows: usize,
        tape: &mut RewardTape,
        out: &mut [f32],
        d_obs: &mut [f32],
        d_act: &mut [f32],
        d_next: &mut [f32],
    ) {
        assert!(
            tape.fits(self, rows),
            "reward tape does not fit {rows} rows of this model"
        );
        let (o, a, f) = (
            self.task.obs_dim,
            self.task.act_dim,
            self.task.state_feature_dim,
        );
        let RewardTape {
            tape,
            features,
            d_features,
        } = tape;
        let ld = tape.ld();
        self.fill_inputs((obs, act, next_obs), rows, features, tape.input_mut(), ld);
        let (mean, std) = (self.target_norm.mean()[0], self.target_norm.std()[0]);
        let predicted = self.mlp.forward_train(tape, rows);
        for (r, &z) in out[..rows].iter_mut().zip(&predicted[..rows]) {
            *r = mean + std * z;
        }
        let (_, out_grad) = tape.output_and_grad_mut();
        out_grad[..rows].fill(std);
        self.mlp.backward_input(tape);
        let grad = tape.input_grad();
        let scale = self.input_norm.std();
        d_obs[..rows * o].fill(0.0);
        d_next[..rows * o].fill(0.0);
        for i in 0..rows {
            for (k, d) in d_features.iter_mut().enumerate() {
                *d = grad[k * ld + i] / scale[k];
            }
            self.task.state_features_backward(
                &obs[i * o..(i + 1) * o],
                d_features,
                &mut d_obs[i * o..(i + 1) * o],
            );
            for j in 0..a {
                let k = f + j;
                d_act[i * a + j] = grad[k * ld + i] / scale[k];
            }
            for (j, d) in d_features.iter_mut().enumerate() {
                let k = f + a + j;
                *d = grad[k * ld + i] / scale[k];
            }
            self.task.state_features_backward(
                &next_obs[i * o..(i + 1) * o],
                d_features,
                &mut d_next[i * o..(i + 1) * o],
            );
        }
    }
}

/// The mean squared error of the network's output on the minibatch `batch` (indices into the
/// standardised, sample-major `inputs` and `targets`) after a training forward pass, with
/// `∂L/∂output` left in the tape for the backward pass.
fn squared_error_and_grad(
    mlp: &Mlp,
    inputs: &[f32],
    targets: &[f32],
    batch: &[usize],
    tape: &mut Tape,
) -> f32 {
    let b = batch.len();
    forward_minibatch(mlp, inputs, batch, tape);
    let (out, grad) = tape.output_and_grad_mut();
    let mut total = 0.0f32;
    for (col, &idx) in batch.iter().enumerate() {
        let err = out[col] - targets[idx];
        total += err * err;
        grad[col] = 2.0 * err / b as f32;
    }
    total / b as f32
}

#[cfg(test)]
mod tests;
