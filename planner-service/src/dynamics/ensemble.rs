//! An ensemble of probabilistic models (PETS's "PE"); one member is the paper's single model.

use super::config::DynamicsConfig;
use super::model::{DynamicsScratch, ModelParts, ProbabilisticModel, TrainingSet};
use crate::data::Transitions;
use crate::nn::train::{FitBudget, Stop};
use crate::nn::{FitReport, FlushDenormals, Normalizer, ShapeError};
use proto::Task;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;
use std::time::Instant;

/// One member's fit: last-epoch loss, steps, NLL, MSE, and why it stopped early (if it did).
type MemberFit = (f32, usize, f32, f32, Option<Stop>);

/// `ensemble_size` probabilistic models of one task.
///
/// With several members each trains on its own bootstrap resample of the data (drawn anew at
/// every fit, as PETS does) so their disagreement reflects what the data leaves uncertain.
/// A single member trains on the data itself: resampling would only discard a third of it.
#[derive(Clone, Debug)]
pub struct Ensemble {
    config: DynamicsConfig,
    members: Vec<ProbabilisticModel>,
}

impl Ensemble {
    /// Untrained members of the configured size.
    pub fn new(task: &'static Task, config: &DynamicsConfig, rng: &mut StdRng) -> Self {
        assert!(config.ensemble_size > 0, "an ensemble needs a member");
        let members = (0..config.ensemble_size)
            .map(|_| ProbabilisticModel::new(task, config, rng))
            .collect();
        Self {
            config: config.clone(),
            members,
        }
    }

    /// An ensemble with stored members (see [`Ensemble::parts`]), one per part.
    pub fn from_parts(
        task: &'static Task,
        config: &DynamicsConfig,
        parts: Vec<ModelParts>,
    ) -> Result<Self, ShapeError> {
        ShapeError::check("ensemble members", config.ensemble_size, parts.len())?;
        let members = parts
            .into_iter()
            .map(|p| ProbabilisticModel::from_parts(task, config, p))
            .collect::<Result<_, _>>()?;
        Ok(Self {
            config: config.clone(),
            members,
        })
    }

    /// What determines every member's predictions — what persistence stores.
    pub fn parts(&self) -> Vec<ModelParts> {
        self.members.iter().map(ProbabilisticModel::parts).collect()
    }

    pub fn config(&self) -> &DynamicsConfig {
        &self.config
    }

    pub fn task(&self) -> &'static Task {
        self.members[0].task()
    }

    /// Number of members.
    pub fn members(&self) -> usize {
        self.members.len()
    }

    pub fn member(&self, i: usize) -> &ProbabilisticModel {
        &self.members[i]
    }

    pub fn member_mut(&mut self, i: usize) -> &mut ProbabilisticModel {
        &mut self.members[i]
    }

    /// Sets the number format of every member's planning-time inference.
    pub fn set_inference_precision(&mut self, precision: proto::InferencePrecision) {
        for member in &mut self.members {
            member.set_inference_precision(precision);
        }
    }

    /// Runs every member's inference on one kernel path, unmeasured.
    pub fn set_kernel_path(&mut self, path: crate::nn::KernelPath) {
        for member in &mut self.members {
            member.set_kernel_path(path);
        }
    }

    /// Trains every member for the budget's epochs on `data` (or until it says stop),
    /// continuing from the current weights after refitting the input and target statistics
    /// on `data`. Members train in parallel. Without data or epochs the ensemble is left
    /// exactly as it is.
    pub fn fit(
        &mut self,
        data: &Transitions,
        budget: impl Into<FitBudget>,
        rng: &mut StdRng,
    ) -> FitReport {
        let budget = budget.into();
        let epochs = budget.epochs;
        let started = Instant::now();
        let task = self.task();
        let n = data.len();
        if n == 0 || epochs == 0 {
            return FitReport::untrained(n, epochs);
        }
        let (inputs, targets) = TrainingSet::raw(task, data);
        let input_norm = Normalizer::fit(&inputs, task.state_feature_dim + task.act_dim);
        let target_norm = Normalizer::fit(&targets, task.obs_dim);
        for m in &mut self.members {
            m.set_normalizers(input_norm.clone(), target_norm.clone());
        }
        let set = TrainingSet::standardised(inputs, targets, &input_norm, &target_norm);
        let bootstrap = self.members.len() > 1;
        let plans: Vec<(Vec<usize>, u64)> = (0..self.members.len())
            .map(|_| {
                let order = if bootstrap && n > 0 {
                    (0..n).map(|_| rng.random_range(0..n)).collect()
                } else {
                    (0..n).collect()
                };
                (order, rng.random())
            })
            .collect();
        let train = |(member, (mut order, seed)): (&mut ProbabilisticModel, (Vec<usize>, u64))| {
            let _flush = FlushDenormals::new();
            let mut rng = StdRng::seed_from_u64(seed);
            let run = member.fit(&set, &mut order, &budget, &mut rng);
            let (nll, mse) = member.evaluate(&set);
            (run.loss, run.steps, nll, mse, run.stopped)
        };
        // In the daemon this runs on the background pool, so the members' threads are its
        // threads (they may wait for plans there; see `sched::background`).
        let results: Vec<MemberFit> = if bootstrap {
            self.members.par_iter_mut().zip(plans).map(train).collect()
        } else {
            self.members.iter_mut().zip(plans).map(train).collect()
        };
        let mean =
            |f: fn(&MemberFit) -> f32| results.iter().map(f).sum::<f32>() / results.len() as f32;
        let report = FitReport {
            samples: n,
            epochs,
            steps: results.iter().map(|r| r.1).sum(),
            loss: mean(|r| r.0),
            nll: (n > 0).then(|| mean(|r| r.2)),
            mse: (n > 0).then(|| mean(|r| r.3)),
            seconds: started.elapsed().as_secs_f32(),
            stopped: results.iter().find_map(|r| r.4),
        };
        tracing::debug!(?report, members = self.members.len(), "dynamics trained");
        report
    }

    /// Buffers for [`Ensemble::predict_next`] on up to `max_rows` rows (any member).
    pub fn scratch(&self, max_rows: usize) -> DynamicsScratch {
        self.members[0].scratch(max_rows)
    }

    /// [`ProbabilisticModel::predict_next`] with member `member`. Never allocates.
    #[allow(clippy::too_many_arguments)] // the planner's fixed hot-loop signature
    pub fn predict_next(
        &self,
        member: usize,
        obs: &[f32],
        act: &[f32],
        rows: usize,
        scratch: &mut DynamicsScratch,
        noise: Option<&[f32]>,
        next_obs: &mut [f32],
    ) {
        self.members[member].predict_next(obs, act, rows, scratch, noise, next_obs);
    }
}

impl DynamicsScratch {
    /// Whether these buffers serve `ensemble` on `rows` rows.
    pub fn fits(&self, ensemble: &Ensemble, rows: usize) -> bool {
        self.fits_model(&ensemble.members[0], rows)
    }
}
