//! One probabilistic dynamics model: an ensemble member of PETS, or the paper's single model.
//!
//! Input: the task's state features of `s` followed by the action, standardised per dimension
//! (statistics of the whole training data). Output: mean and bounded log-variance of the
//! task's target for the transition (usually the delta `s' − s`), in *standardised* target
//! units. Standardising the targets as well as the inputs gives every target dimension the
//! same weight in the loss and puts the log-variance bounds on one scale, whatever the
//! physical units (a joint angle changes by 1e-3 per step while a velocity changes by 1); the
//! prediction is mapped back before `next_obs_from_target`.

use super::config::DynamicsConfig;
use super::gaussian::{
    BOUND_PENALTY, INITIAL_MAX_LOGVAR, INITIAL_MIN_LOGVAR, bounded_logvar, nll_row, sample_row,
};
use crate::data::Transitions;
use crate::nn::aligned::AlignedBuf;
use crate::nn::matmul::transpose;
use crate::nn::train::{EpochsRun, FitBudget, run_epochs};
use crate::nn::vecops::scale_shift;
use crate::nn::{Activation, Adam, ForwardScratch, Mlp, Normalizer, ShapeError, Tape, TrainPath};
use proto::Task;
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};

/// Model inputs and targets of a set of transitions, standardised, sample-major.
#[derive(Clone, Debug)]
pub struct TrainingSet {
    inputs: Vec<f32>,
    targets: Vec<f32>,
    in_dim: usize,
    out_dim: usize,
}

impl TrainingSet {
    /// The raw (unstandardised) model inputs `[features(s), a]` and targets of every
    /// transition, sample-major.
    pub fn raw(task: &Task, data: &Transitions) -> (Vec<f32>, Vec<f32>) {
        let (f, a, o) = (task.state_feature_dim, task.act_dim, task.obs_dim);
        let mut inputs = vec![0.0; data.len() * (f + a)];
        let mut targets = vec![0.0; data.len() * o];
        for (i, (row, target)) in inputs
            .chunks_exact_mut(f + a)
            .zip(targets.chunks_exact_mut(o))
            .enumerate()
        {
            let (s, u, s1) = data.row(i);
            task.state_features(s, &mut row[..f]);
            row[f..].copy_from_slice(u);
            task.target(s, s1, target);
        }
        (inputs, targets)
    }

    /// Standardises raw inputs and targets with the given statistics.
    pub fn standardised(
        mut inputs: Vec<f32>,
        mut targets: Vec<f32>,
        input_norm: &Normalizer,
        target_norm: &Normalizer,
    ) -> Self {
        let (in_dim, out_dim) = (input_norm.dim(), target_norm.dim());
        assert_eq!(
            inputs.len() / in_dim,
            targets.len() / out_dim,
            "inputs and targets of different lengths"
        );
        input_norm.normalize_rows(&mut inputs);
        target_norm.normalize_rows(&mut targets);
        Self {
            inputs,
            targets,
            in_dim,
            out_dim,
        }
    }

    pub fn len(&self) -> usize {
        self.targets.len() / self.out_dim
    }

    pub fn is_empty(&self) -> bool {
        self.targets.is_empty()
    }
}

/// Buffers of one training step, reused across steps.
#[derive(Clone, Debug)]
pub struct TrainWorkspace {
    tape: Tape,
    /// Feature-major standardised targets of the batch.
    targets: AlignedBuf,
    grads: Vec<f32>,
    /// `∂L/∂[max; min]` of the log-variance bounds.
    bound_grads: Vec<f32>,
    /// Per-sample terms of the loss, summed per target dimension.
    terms: Vec<f32>,
}

impl TrainWorkspace {
    /// Buffers for batches of up to `batch_size` transitions, on the model's pinned training
    /// path or else the one measured fastest for its network (see [`TrainPath::measured`]).
    pub fn new(model: &ProbabilisticModel, batch_size: usize) -> Self {
        let mlp = &model.mlp;
        let path = model
            .train_path
            .unwrap_or_else(|| TrainPath::measured(mlp.sizes(), mlp.activation(), batch_size));
        Self::with_path(model, batch_size, path)
    }

    /// Buffers for batches of up to `batch_size` transitions, multiplying on `path`.
    pub fn with_path(model: &ProbabilisticModel, batch_size: usize, path: TrainPath) -> Self {
        let tape = Tape::with_path(&model.mlp, batch_size, path);
        Self {
            targets: AlignedBuf::zeros(model.task.obs_dim * tape.ld()),
            grads: vec![0.0; model.mlp.params().len()],
            bound_grads: vec![0.0; 2 * model.task.obs_dim],
            terms: vec![0.0; 4 * tape.ld()],
            tape,
        }
    }
}

impl TrainWorkspace {
    /// The kernels this workspace's products run on.
    pub fn path(&self) -> TrainPath {
        self.tape.path()
    }
}

#[cfg(test)]
impl TrainWorkspace {
    pub(crate) fn grads_for_test(&self) -> &[f32] {
        &self.grads
    }

    pub(crate) fn bound_grads_for_test(&self) -> &[f32] {
        &self.bound_grads
    }
}

/// Preallocated buffers for [`ProbabilisticModel::predict_next`] on up to `capacity` rows.
#[derive(Clone, Debug)]
pub struct DynamicsScratch {
    forward: ForwardScratch,
    features: Vec<f32>,
    target: Vec<f32>,
    /// The noise, feature-major.
    noise: AlignedBuf,
}

impl DynamicsScratch {
    /// The most rows one prediction can take.
    pub fn capacity(&self) -> usize {
        self.forward.ld()
    }

    pub(crate) fn fits_model(&self, model: &ProbabilisticModel, rows: usize) -> bool {
        self.forward.fits(&model.mlp, rows)
            && self.features.len() == model.task.state_feature_dim
            && self.target.len() == model.task.obs_dim
    }
}

/// Buffers for differentiating the mean prediction on up to `capacity` rows: the training tape
/// (it keeps the activations the backward pass needs) and one row's worth of task transforms.
/// See [`ProbabilisticModel::predict_mean_recorded`] and [`ProbabilisticModel::mean_backward`].
#[derive(Clone, Debug)]
pub struct MeanTape {
    tape: Tape,
    features: Vec<f32>,
    target: Vec<f32>,
    d_features: Vec<f32>,
    d_target: Vec<f32>,
}

impl MeanTape {
    /// Whether these buffers serve `model` on `rows` rows.
    pub fn fits(&self, model: &ProbabilisticModel, rows: usize) -> bool {
        self.tape.fits(&model.mlp, rows)
            && self.features.len() == model.task.state_feature_dim
            && self.target.len() == model.task.obs_dim
    }
}

/// Everything that determines a model's predictions — what persistence stores. (Adam's
/// moments are not included: a restored model's optimiser starts afresh.)
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelParts {
    /// The network's parameters, laid out as [`Mlp::params`].
    pub params: Vec<f32>,
    pub input_norm: Normalizer,
    pub target_norm: Normalizer,
    pub max_logvar: Vec<f32>,
    pub min_logvar: Vec<f32>,
}

/// A Gaussian dynamics model `p(target | s, a)` (see the module docs).
#[derive(Clone, Debug)]
pub struct ProbabilisticModel {
    task: &'static Task,
    mlp: Mlp,
    input_norm: Normalizer,
    target_norm: Normalizer,
    /// `[max log-variance (obs_dim); min log-variance (obs_dim)]`, learned.
    logvar_bounds: Vec<f32>,
    adam: Adam,
    bounds_adam: Adam,
    batch_size: usize,
    /// The training path its fits use; `None`: the one measured fastest for its shape.
    train_path: Option<TrainPath>,
    weight_decay: f32,
}

impl ProbabilisticModel {
    /// An untrained model of the configured size for `task` (identity normalisers).
    pub fn new(task: &'static Task, config: &DynamicsConfig, rng: &mut StdRng) -> Self {
        let sizes = super::config::layer_sizes(task, config);
        let in_dim = sizes[0];
        let mlp = Mlp::new(&sizes, Activation::Swish, rng);
        let mut logvar_bounds = vec![INITIAL_MAX_LOGVAR; task.obs_dim];
        logvar_bounds.extend(std::iter::repeat_n(INITIAL_MIN_LOGVAR, task.obs_dim));
        Self {
            task,
            adam: Adam::new(mlp.params().len(), config.learning_rate),
            bounds_adam: Adam::new(2 * task.obs_dim, config.learning_rate),
            mlp,
            input_norm: Normalizer::identity(in_dim),
            target_norm: Normalizer::identity(task.obs_dim),
            logvar_bounds,
            batch_size: config.batch_size.max(1),
            train_path: None,
            weight_decay: config.weight_decay,
        }
    }

    /// A model of the configured size with stored parts (see [`ProbabilisticModel::parts`]).
    pub fn from_parts(
        task: &'static Task,
        config: &DynamicsConfig,
        parts: ModelParts,
    ) -> Result<Self, ShapeError> {
        let mut rng = StdRng::seed_from_u64(0); // the weights are replaced below
        let mut model = Self::new(task, config, &mut rng);
        let o = task.obs_dim;
        ShapeError::check(
            "dynamics parameters",
            model.mlp.params().len(),
            parts.params.len(),
        )?;
        ShapeError::check(
            "dynamics input statistics",
            model.mlp.in_dim(),
            parts.input_norm.dim(),
        )?;
        ShapeError::check("dynamics target statistics", o, parts.target_norm.dim())?;
        ShapeError::check("maximum log-variances", o, parts.max_logvar.len())?;
        ShapeError::check("minimum log-variances", o, parts.min_logvar.len())?;
        model.mlp.params_mut().copy_from_slice(&parts.params);
        model.input_norm = parts.input_norm;
        model.target_norm = parts.target_norm;
        model.logvar_bounds = [parts.max_logvar, parts.min_logvar].concat();
        Ok(model)
    }

    /// A copy of what determines this model's predictions.
    pub fn parts(&self) -> ModelParts {
        ModelParts {
            params: self.mlp.params().to_vec(),
            input_norm: self.input_norm.clone(),
            target_norm: self.target_norm.clone(),
            max_logvar: self.max_logvar().to_vec(),
            min_logvar: self.min_logvar().to_vec(),
        }
    }

    pub fn task(&self) -> &'static Task {
        self.task
    }

    /// Pins the path of the products of its fits and of planning by gradient through it
    /// (`None`: measured, the default; see [`Tape::for_planning`]).
    pub fn pin_train_path(&mut self, path: Option<TrainPath>) {
        self.train_path = path;
    }

    /// Sets the number format of planning-time inference (see [`Mlp::set_inference_precision`]).
    pub fn set_inference_precision(&mut self, precision: proto::InferencePrecision) {
        self.mlp.set_inference_precision(precision);
    }

    /// Runs inference on one kernel path, unmeasured (benchmarks and tests of every path).
    pub fn set_kernel_path(&mut self, path: crate::nn::KernelPath) {
        self.mlp.set_kernel_path(path);
    }

    /// The network: `state_feature_dim + act_dim` inputs, `2 · obs_dim` outputs (means, then
    /// raw log-variances).
    pub fn mlp(&self) -> &Mlp {
        &self.mlp
    }

    pub fn input_normalizer(&self) -> &Normalizer {
        &self.input_norm
    }

    pub fn target_normalizer(&self) -> &Normalizer {
        &self.target_norm
    }

    /// Learned upper bounds of the standardised log-variance, per target dimension.
    pub fn max_logvar(&self) -> &[f32] {
        &self.logvar_bounds[..self.task.obs_dim]
    }

    /// Learned lower bounds of the standardised log-variance, per target dimension.
    pub fn min_logvar(&self) -> &[f32] {
        &self.logvar_bounds[self.task.obs_dim..]
    }

    #[cfg(test)]
    pub(crate) fn member_bounds_mut(&mut self) -> &mut [f32] {
        &mut self.logvar_bounds
    }

    /// Replaces the standardisation statistics (the ensemble fits them once for all members).
    pub fn set_normalizers(&mut self, input: Normalizer, target: Normalizer) {
        assert_eq!(
            (input.dim(), target.dim()),
            (self.mlp.in_dim(), self.task.obs_dim),
            "normaliser dimensions"
        );
        self.input_norm = input;
        self.target_norm = target;
    }

    /// The loss of one minibatch (`batch`: indices into `set`) and its gradient, left in the
    /// workspace: PETS's Gaussian objective (see [`super::gaussian`]) without weight decay.
    pub fn loss_and_grad(
        &self,
        set: &TrainingSet,
        batch: &[usize],
        ws: &mut TrainWorkspace,
    ) -> f32 {
        let (n_in, d, b) = (set.in_dim, set.out_dim, batch.len());
        let ld = ws.tape.ld();
        assert!(b > 0 && b <= ld, "batch of {b} for a workspace of {ld}");
        let input = ws.tape.input_mut();
        let targets = ws.targets.as_mut_slice();
        for (col, &idx) in batch.iter().enumerate() {
            for (f, &v) in set.inputs[idx * n_in..(idx + 1) * n_in].iter().enumerate() {
                input[f * ld + col] = v;
            }
            for (f, &v) in set.targets[idx * d..(idx + 1) * d].iter().enumerate() {
                targets[f * ld + col] = v;
            }
        }
        self.mlp.forward_train(&mut ws.tape, b);
        let (out, grad) = ws.tape.output_and_grad_mut();
        let (g_mean, g_raw) = grad.split_at_mut(d * ld);
        let scale = 1.0 / (b * d) as f32;
        let (max, min) = self.logvar_bounds.split_at(d);
        let mut total = 0.0;
        for k in 0..d {
            let row = k * ld..k * ld + b;
            let raw = (d + k) * ld..(d + k) * ld + b;
            let [loss, d_max, d_min, _] = nll_row(
                &out[row.clone()],
                &out[raw],
                &targets[row.clone()],
                [max[k], min[k], scale],
                (&mut g_mean[row.clone()], &mut g_raw[row]),
                &mut ws.terms,
            );
            total += loss;
            ws.bound_grads[k] = scale * d_max + BOUND_PENALTY;
            ws.bound_grads[d + k] = scale * d_min - BOUND_PENALTY;
        }
        self.mlp.backward(&mut ws.tape, &mut ws.grads, false);
        total * scale + BOUND_PENALTY * (max.iter().sum::<f32>() - min.iter().sum::<f32>())
    }

    /// One Adam step on one minibatch; returns the minibatch's loss before the step.
    pub fn train_step(
        &mut self,
        set: &TrainingSet,
        batch: &[usize],
        ws: &mut TrainWorkspace,
    ) -> f32 {
        let loss = self.loss_and_grad(set, batch, ws);
        self.adam
            .step_decaying(&mut self.mlp, &ws.grads, self.weight_decay);
        self.bounds_adam
            .step(&mut self.logvar_bounds, &ws.bound_grads);
        loss
    }

    /// `budget.epochs` passes over `order` (indices into `set`, e.g. a bootstrap resample),
    /// each in freshly shuffled minibatches, continuing from the current weights, until the
    /// budget says stop.
    pub fn fit(
        &mut self,
        set: &TrainingSet,
        order: &mut [usize],
        budget: &FitBudget,
        rng: &mut StdRng,
    ) -> EpochsRun {
        let mut ws = TrainWorkspace::new(self, self.batch_size.min(order.len().max(1)));
        run_epochs(order, self.batch_size, budget, rng, |batch, _| {
            self.train_step(set, batch, &mut ws)
        })
    }

    /// Mean Gaussian negative log-likelihood per target dimension (standardised units,
    /// with `½ ln 2π`) and mean squared error of the mean (in units of the target variance)
    /// over every transition of `set`.
    pub fn evaluate(&self, set: &TrainingSet) -> (f32, f32) {
        const CHUNK: usize = 512;
        let (n_in, d) = (set.in_dim, set.out_dim);
        let mut scratch = ForwardScratch::new(&self.mlp, CHUNK.min(set.len().max(1)));
        let ld = scratch.ld();
        let (max, min) = self.logvar_bounds.split_at(d);
        let (mut nll, mut sq) = (0.0f64, 0.0f64);
        for start in (0..set.len()).step_by(ld) {
            let cols = ld.min(set.len() - start);
            let rows = &set.inputs[start * n_in..(start + cols) * n_in];
            transpose(rows, cols, n_in, n_in, scratch.input_mut(), ld);
            let out = self.mlp.forward(cols, &mut scratch);
            for i in 0..cols {
                for k in 0..d {
                    let err = out[k * ld + i] - set.targets[(start + i) * d + k];
                    let lv = bounded_logvar(out[(d + k) * ld + i], max[k], min[k])[0];
                    nll += 0.5
                        * ((err * err) as f64 * (-lv as f64).exp()
                            + lv as f64
                            + (2.0 * std::f64::consts::PI).ln());
                    sq += (err * err) as f64;
                }
            }
        }
        let count = (set.len() * d).max(1) as f64;
        ((nll / count) as f32, (sq / count) as f32)
    }

    /// Buffers for [`ProbabilisticModel::predict_next`] on up to `max_rows` rows.
    pub fn scratch(&self, max_rows: usize) -> DynamicsScratch {
        let forward = ForwardScratch::new(&self.mlp, max_rows);
        let ld = forward.ld();
        DynamicsScratch {
            forward,
            features: vec![0.0; self.task.state_feature_dim],
            target: vec![0.0; self.task.obs_dim],
            noise: AlignedBuf::zeros(self.task.obs_dim * ld),
        }
    }

    /// Buffers for differentiating the mean prediction on up to `max_rows` rows.
    pub fn mean_tape(&self, max_rows: usize) -> MeanTape {
        let (f, o) = (self.task.state_feature_dim, self.task.obs_dim);
        MeanTape {
            tape: match self.train_path {
                Some(path) => Tape::with_path(&self.mlp, max_rows, path),
                None => Tape::for_planning(&self.mlp, max_rows),
            },
            features: vec![0.0; f],
            target: vec![0.0; o],
            d_features: vec![0.0; f],
            d_target: vec![0.0; o],
        }
    }

    /// The predicted mean next observations of `rows` transitions (as
    /// [`ProbabilisticModel::predict_next`] without noise, but in f32 through the training
    /// pass), recording in `tape` what [`ProbabilisticModel::mean_backward`] needs. Never
    /// allocates.
    pub fn predict_mean_recorded(
        &self,
        obs: &[f32],
        act: &[f32],
        rows: usize,
        tape: &mut MeanTape,
        next_obs: &mut [f32],
    ) {
        let task = self.task;
        let (o, a) = (task.obs_dim, task.act_dim);
        assert!(tape.fits(self, rows), "mean tape does not fit {rows} rows");
        let ld = tape.tape.ld();
        let input = tape.tape.input_mut();
        for i in 0..rows {
            task.state_features(&obs[i * o..(i + 1) * o], &mut tape.features);
            for (k, &v) in tape
                .features
                .iter()
                .chain(&act[i * a..(i + 1) * a])
                .enumerate()
            {
                input[k * ld + i] = self.input_norm.normalize(k, v);
            }
        }
        let out = self.mlp.forward_train(&mut tape.tape, rows);
        for i in 0..rows {
            for (k, t) in tape.target.iter_mut().enumerate() {
                *t = self.target_norm.denormalize(k, out[k * ld + i]);
            }
            task.next_obs_from_target(
                &obs[i * o..(i + 1) * o],
                &tape.target,
                &mut next_obs[i * o..(i + 1) * o],
            );
        }
    }

    /// Back-propagates `∂L/∂next_obs` (`d_next`, `rows × obs_dim`) through the last
    /// [`ProbabilisticModel::predict_mean_recorded`] on `obs`: writes `∂L/∂obs` into `d_obs`
    /// and `∂L/∂act` into `d_act` (both overwritten, sample-major). Never allocates.
    pub fn mean_backward(
        &self,
        obs: &[f32],
        rows: usize,
        tape: &mut MeanTape,
        d_next: &[f32],
        d_obs: &mut [f32],
        d_act: &mut [f32],
    ) {
        let task = self.task;
        let (o, a, f) = (task.obs_dim, task.act_dim, task.state_feature_dim);
        let ld = tape.tape.ld();
        let MeanTape {
            tape: mlp_tape,
            features: _,
            target: _,
            d_features,
            d_target,
        } = tape;
        let (_, out_grad) = mlp_tape.output_and_grad_mut();
        // The log-variance outputs do not reach the mean: their gradient is zero.
        for k in o..2 * o {
            out_grad[k * ld..k * ld + rows].fill(0.0);
        }
        d_obs[..rows * o].fill(0.0);
        for i in 0..rows {
            let row = i * o..(i + 1) * o;
            task.next_obs_from_target_backward(
                &obs[row.clone()],
                &d_next[row.clone()],
                &mut d_obs[row],
                d_target,
            );
            for (k, d) in d_target.iter().enumerate() {
                out_grad[k * ld + i] = d * self.target_norm.std()[k];
            }
        }
        self.mlp.backward_input(mlp_tape);
        let input_grad = mlp_tape.input_grad();
        let std = self.input_norm.std();
        for i in 0..rows {
            for (k, d) in d_features.iter_mut().enumerate() {
                *d = input_grad[k * ld + i] / std[k];
            }
            for j in 0..a {
                d_act[i * a + j] = input_grad[(f + j) * ld + i] / std[f + j];
            }
            task.state_features_backward(
                &obs[i * o..(i + 1) * o],
                d_features,
                &mut d_obs[i * o..(i + 1) * o],
            );
        }
    }

    /// Next observations for `rows` transitions (`obs`: `rows × obs_dim`, `act`:
    /// `rows × act_dim`, `next_obs`: `rows × obs_dim`, sample-major). With `noise`
    /// (`rows × obs_dim` standard normals) the target is drawn from the predicted Gaussian
    /// (PETS TS∞); without, it is the predicted mean. Never allocates.
    pub fn predict_next(
        &self,
        obs: &[f32],
        act: &[f32],
        rows: usize,
        scratch: &mut DynamicsScratch,
        noise: Option<&[f32]>,
        next_obs: &mut [f32],
    ) {
        let task = self.task;
        let (o, a) = (task.obs_dim, task.act_dim);
        assert!(
            scratch.fits_model(self, rows),
            "scratch of {} rows does not fit {rows} rows of this model",
            scratch.capacity()
        );
        assert!(
            obs.len() >= rows * o && act.len() >= rows * a && next_obs.len() >= rows * o,
            "buffers shorter than {rows} rows"
        );
        let ld = scratch.forward.ld();
        let DynamicsScratch {
            forward,
            features,
            target,
            noise: noise_fm,
        } = scratch;
        let input = forward.input_mut();
        for i in 0..rows {
            task.state_features(&obs[i * o..(i + 1) * o], features);
            for (k, &v) in features.iter().chain(&act[i * a..(i + 1) * a]).enumerate() {
                input[k * ld + i] = self.input_norm.normalize(k, v);
            }
        }
        let out = self.mlp.forward(rows, forward);
        let (means, raws) = out.split_at_mut(o * ld);
        if let Some(eps) = noise {
            assert!(eps.len() >= rows * o, "noise shorter than {rows} rows");
            let noise_fm = noise_fm.as_mut_slice();
            transpose(&eps[..rows * o], rows, o, o, noise_fm, ld);
            let (max, min) = self.logvar_bounds.split_at(o);
            for k in 0..o {
                let row = k * ld..k * ld + rows;
                sample_row(
                    &mut means[row.clone()],
                    &raws[row.clone()],
                    &noise_fm[row],
                    max[k],
                    min[k],
                );
            }
        }
        for k in 0..o {
            scale_shift(
                &mut means[k * ld..k * ld + rows],
                self.target_norm.std()[k],
                self.target_norm.mean()[k],
            );
        }
        for i in 0..rows {
            for (k, t) in target.iter_mut().enumerate() {
                *t = means[k * ld + i];
            }
            task.next_obs_from_target(
                &obs[i * o..(i + 1) * o],
                target,
                &mut next_obs[i * o..(i + 1) * o],
            );
        }
    }
}
