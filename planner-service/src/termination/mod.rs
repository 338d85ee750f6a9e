//! A learned termination: for systems that end their own episodes by a rule nobody wrote down
//! (`termination = "learned"`), a classifier `p̂(end | s')` trained on the episodes agents end
//! as `terminated`, so that imagination stops a particle's returns where the system would
//! have ended the episode (falling costs the rest of the horizon's rewards).
//!
//! **Inputs.** `features(s')`: the next state through the task's own model transforms
//! ([`proto::Task::state_features`]), standardised with statistics of the training data. A
//! termination is a property of the state an episode ends in, as a termination formula is
//! (one reads only `s_next`).
//!
//! **Labels.** A transition is positive when its agent ended the episode with it as
//! `terminated` ([`Transitions::terminated`]); every other transition, the last step of a
//! time-limited episode included, is negative.
//!
//! **Training.** Logistic loss with the classes weighted to equal total weight (an episode
//! has one end and many steps: unweighted, "never" would be 90–99 % right and useless), Adam
//! with the dynamics' step size, batch size and weight decay for the dynamics' epochs. One
//! transition in [`HOLD_OUT_EVERY`] (by a fixed hash of its position, so the split is stable
//! as the buffer grows) is held out of training; the model's accuracy and recall of ends on
//! it are reported with every retraining ([`TerminationModel::held_out`]).
//!
//! **Before any end.** A model that has seen no terminated episode in its training data has
//! nothing to learn from: it predicts no end ([`TerminationModel::knows_ends`] is false), the
//! same as a task without a termination. So a run whose system never ends an episode plans as
//! one without a termination rule, and is never held back waiting for one.
//!
//! **Planning.** [`TerminationModel::predict`] classifies a whole population's next states in
//! one batched forward pass (the run's inference precision), without allocating: an end where
//! the logit is positive (`p̂ > ½`).

#[cfg(test)]
mod tests;

use crate::data::Transitions;
use crate::dynamics::DynamicsConfig;
use crate::nn::train::{FitBudget, Minibatches, fit_minibatches, forward_minibatch};
use crate::nn::{
    Activation, Adam, FitReport, FlushDenormals, ForwardScratch, Mlp, Normalizer, ShapeError, Tape,
};
use proto::{Task, TerminationAccuracy};
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Hidden layers of the classifier (Swish, as the other models).
pub const HIDDEN_LAYERS: usize = 2;
/// Units per hidden layer: the boundary of a region of state space is a smaller function than
/// the dynamics' next state, and the classifier runs at every imagined step.
pub const HIDDEN_SIZE: usize = 64;
/// One transition in this many is held out of training to measure the model's accuracy.
pub const HOLD_OUT_EVERY: u64 = 5;

/// Layer sizes `[state features, hidden…, 1]` of `task`'s termination classifier.
pub fn layer_sizes(task: &Task) -> Vec<usize> {
    let mut sizes = vec![task.state_feature_dim];
    sizes.extend(std::iter::repeat_n(HIDDEN_SIZE, HIDDEN_LAYERS));
    sizes.push(1);
    sizes
}

/// Whether transition `i` of a buffer is held out of training (a fixed hash of its position:
/// spread evenly, unrelated to step numbers, and the same at every retraining).
pub fn is_held_out(i: usize) -> bool {
    let mut z = (i as u64).wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    (z ^ (z >> 31)).is_multiple_of(HOLD_OUT_EVERY)
}

/// Everything that determines the model's predictions — what persistence stores.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TerminationParts {
    /// The network's parameters, laid out as [`Mlp::params`].
    pub params: Vec<f32>,
    pub input_norm: Normalizer,
    /// Whether a fit has trained on at least one end (see [`TerminationModel::knows_ends`]).
    pub knows_ends: bool,
}

/// A termination classifier for one task (see the module docs).
#[derive(Clone, Debug)]
pub struct TerminationModel {
    task: &'static Task,
    mlp: Mlp,
    input_norm: Normalizer,
    adam: Adam,
    batch_size: usize,
    weight_decay: f32,
    knows_ends: bool,
    /// The accuracy measured at the last fit (not stored: a restored model reports it again
    /// after its next retraining).
    held_out: Option<TerminationAccuracy>,
}

/// Preallocated buffers for [`TerminationModel::predict`] on up to `capacity` rows.
#[derive(Clone, Debug)]
pub struct TerminationScratch {
    forward: ForwardScratch,
    features: Vec<f32>,
}

impl TerminationScratch {
    /// Whether these buffers serve `model` on `rows` rows.
    pub fn fits(&self, model: &TerminationModel, rows: usize) -> bool {
        self.forward.fits(&model.mlp, rows) && self.features.len() == model.task.state_feature_dim
    }
}

impl TerminationModel {
    /// An untrained model for `task`, trained with `training`'s step size, batch size and
    /// weight decay (an identity normaliser).
    pub fn new(task: &'static Task, training: &DynamicsConfig, rng: &mut StdRng) -> Self {
        let mlp = Mlp::new(&layer_sizes(task), Activation::Swish, rng);
        Self {
            task,
            adam: Adam::new(mlp.params().len(), training.learning_rate),
            input_norm: Normalizer::identity(mlp.in_dim()),
            mlp,
            batch_size: training.batch_size.max(1),
            weight_decay: training.weight_decay,
            knows_ends: false,
            held_out: None,
        }
    }

    /// A model with stored parts (see [`TerminationModel::parts`]).
    pub fn from_parts(
        task: &'static Task,
        training: &DynamicsConfig,
        parts: TerminationParts,
    ) -> Result<Self, ShapeError> {
        // The weights are replaced below.
        let mut model = Self::new(task, training, &mut StdRng::seed_from_u64(0));
        ShapeError::check(
            "termination parameters",
            model.mlp.params().len(),
            parts.params.len(),
        )?;
        ShapeError::check(
            "termination input statistics",
            model.mlp.in_dim(),
            parts.input_norm.dim(),
        )?;
        model.mlp.params_mut().copy_from_slice(&parts.params);
        model.input_norm = parts.input_norm;
        model.knows_ends = parts.knows_ends;
        Ok(model)
    }

    /// A copy of what determines this model's predictions.
    pub fn parts(&self) -> TerminationParts {
        TerminationParts {
            params: self.mlp.params().to_vec(),
            input_norm: self.input_norm.clone(),
            knows_ends: self.knows_ends,
        }
    }

    /// Whether a fit has trained on at least one terminated episode: before that the model
    /// predicts no end anywhere (nothing was seen to end).
    pub fn knows_ends(&self) -> bool {
        self.knows_ends
    }

    /// The accuracy on held-out transitions measured by the last fit (`None` before one that
    /// had an end to learn from, and after a restore until the next).
    pub fn held_out(&self) -> Option<TerminationAccuracy> {
        self.held_out
    }

    /// The network: `state_feature_dim` inputs, one logit out.
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

    /// The raw inputs `features(s')` of the transitions `rows` of `data`, sample-major.
    fn raw_inputs(&self, data: &Transitions, rows: &[usize]) -> Vec<f32> {
        let f = self.task.state_feature_dim;
        let mut inputs = vec![0.0; rows.len() * f];
        for (row, &i) in inputs.chunks_exact_mut(f).zip(rows) {
            self.task.state_features(data.row(i).2, row);
        }
        inputs
    }

    /// Trains on `data`'s terminated flags, all but the held-out transitions (see
    /// [`is_held_out`]), for the budget's epochs continuing from the current weights, then
    /// measures the held-out accuracy. Training data with no end leaves the model as it is
    /// (predicting no end until it has seen one).
    pub fn fit(
        &mut self,
        data: &Transitions,
        budget: impl Into<FitBudget>,
        rng: &mut StdRng,
    ) -> FitReport {
        let budget = budget.into();
        let started = Instant::now();
        let (train, held): (Vec<usize>, Vec<usize>) =
            (0..data.len()).partition(|&i| !is_held_out(i));
        let labels: Vec<f32> = train
            .iter()
            .map(|&i| f32::from(u8::from(data.terminated()[i])))
            .collect();
        let ends = labels.iter().filter(|&&y| y > 0.5).count();
        let n = train.len();
        if n == 0 || budget.epochs == 0 || ends == 0 {
            return FitReport::untrained(n, budget.epochs);
        }
        let _flush = FlushDenormals::new();
        let dim = self.mlp.in_dim();
        let mut inputs = self.raw_inputs(data, &train);
        self.input_norm = Normalizer::fit(&inputs, dim);
        self.input_norm.normalize_rows(&mut inputs);
        let weights = class_weights(ends, n);
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
            |mlp, batch, tape| logistic_loss_and_grad(mlp, &inputs, &labels, weights, batch, tape),
        );
        self.knows_ends |= run.steps > 0;
        self.held_out = self.accuracy(data, &held);
        tracing::debug!(steps = run.steps, loss = run.loss, held_out = ?self.held_out, "termination model trained");
        FitReport {
            samples: n,
            epochs: budget.epochs,
            steps: run.steps,
            loss: run.loss,
            stopped: run.stopped,
            seconds: started.elapsed().as_secs_f32(),
            ..FitReport::default()
        }
    }

    /// Accuracy and recall of ends on the transitions `rows` of `data` (`None` for no rows).
    /// Allocates.
    pub fn accuracy(&self, data: &Transitions, rows: &[usize]) -> Option<TerminationAccuracy> {
        if rows.is_empty() {
            return None;
        }
        let o = self.task.obs_dim;
        let mut next = Vec::with_capacity(rows.len() * o);
        for &i in rows {
            next.extend_from_slice(data.row(i).2);
        }
        let mut predicted = vec![false; rows.len()];
        let mut scratch = self.scratch(rows.len());
        self.predict(&next, rows.len(), &mut scratch, &mut predicted);
        let truth = rows.iter().map(|&i| data.terminated()[i]);
        let (mut right, mut ends, mut found) = (0u32, 0u32, 0u32);
        for (p, t) in predicted.iter().zip(truth) {
            right += u32::from(*p == t);
            ends += u32::from(t);
            found += u32::from(t && *p);
        }
        Some(TerminationAccuracy {
            held_out: rows.len() as u32,
            terminations: ends,
            accuracy: right as f32 / rows.len() as f32,
            recall: if ends == 0 {
                1.0
            } else {
                found as f32 / ends as f32
            },
        })
    }

    /// Buffers for [`TerminationModel::predict`] on up to `max_rows` rows.
    pub fn scratch(&self, max_rows: usize) -> TerminationScratch {
        TerminationScratch {
            forward: ForwardScratch::new(&self.mlp, max_rows),
            features: vec![0.0; self.task.state_feature_dim],
        }
    }

    /// Whether each of `rows` next states (`next_obs`, sample-major) ends its episode, into
    /// `out[..rows]`: one batched forward pass; never allocates. A model that knows no end
    /// predicts none.
    pub fn predict(
        &self,
        next_obs: &[f32],
        rows: usize,
        scratch: &mut TerminationScratch,
        out: &mut [bool],
    ) {
        if !self.knows_ends {
            out[..rows].fill(false);
            return;
        }
        assert!(
            scratch.fits(self, rows),
            "termination scratch does not fit {rows} rows of this model"
        );
        let o = self.task.obs_dim;
        assert!(
            next_obs.len() >= rows * o,
            "buffers shorter than {rows} rows"
        );
        let ld = scratch.forward.ld();
        let TerminationScratch { forward, features } = scratch;
        let input = forward.input_mut();
        for i in 0..rows {
            self.task
                .state_features(&next_obs[i * o..(i + 1) * o], features);
            for (k, &v) in features.iter().enumerate() {
                input[k * ld + i] = self.input_norm.normalize(k, v);
            }
        }
        let logits = self.mlp.forward(rows, forward);
        for (end, &z) in out[..rows].iter_mut().zip(&logits[..rows]) {
            // A NaN logit (a diverging imagined state) is no end: the return is `-inf` anyway.
            *end = z > 0.0;
        }
    }
}

/// Per-sample weights `(negative, positive)` that give both classes the same total weight and
/// the whole set a mean weight of 1: `n / (2·negatives)` and `n / (2·ends)`.
pub fn class_weights(ends: usize, n: usize) -> (f32, f32) {
    let negatives = n.saturating_sub(ends).max(1);
    (
        n as f32 / (2 * negatives) as f32,
        n as f32 / (2 * ends.max(1)) as f32,
    )
}

/// The class-weighted logistic loss of the network's logits `z` on the minibatch `batch`
/// (indices into the standardised, sample-major `inputs` and the 0/1 `labels`),
///
/// `L = (1/B) Σ w_y · (softplus(z) − y·z)`, `∂L/∂z = w_y · (σ(z) − y) / B`,
///
/// after a training forward pass, with `∂L/∂z` left in the tape for the backward pass
/// (softplus and σ in their overflow-free forms).
pub fn logistic_loss_and_grad(
    mlp: &Mlp,
    inputs: &[f32],
    labels: &[f32],
    (negative, positive): (f32, f32),
    batch: &[usize],
    tape: &mut Tape,
) -> f32 {
    let b = batch.len();
    forward_minibatch(mlp, inputs, batch, tape);
    let (out, grad) = tape.output_and_grad_mut();
    let mut total = 0.0f32;
    for (col, &idx) in batch.iter().enumerate() {
        let (z, y) = (out[col], labels[idx]);
        let w = if y > 0.5 { positive } else { negative };
        // softplus(z) = max(z, 0) + ln(1 + e^−|z|); σ(z) likewise from e^−|z|.
        let e = (-z.abs()).exp();
        let softplus = z.max(0.0) + e.ln_1p();
        let sigmoid = if z >= 0.0 {
            1.0 / (1.0 + e)
        } else {
            e / (1.0 + e)
        };
        total += w * (softplus - y * z);
        grad[col] = w * (sigmoid - y) / b as f32;
    }
    total / b as f32
}
