//! The planner's choice of optimiser ([`CemConfig::optimizer`]): one type that the MPC loop
//! drives the same way whichever search runs underneath.

use super::Learned;
use super::adam::AdamPlanner;
use super::anytime::IterationClock;
use super::cem::Cem;
use super::icem::Icem;
use super::imagine::Imagination;
use super::sequence::{CemOutcome, PopulationObjective};
use super::settings::{CemConfig, ConfigError, Optimizer};
use crate::dynamics::Ensemble;
use crate::energy::Regularizer;
use crate::sched::Preempt;
use proto::Task;
use std::sync::Arc;

/// The planning problem of one step: imagination from one observation with fixed models.
/// CEM and iCEM see it as a [`PopulationObjective`]; Adam differentiates the same objective.
pub(super) struct Imagined<'a> {
    pub imagination: &'a mut Imagination,
    pub obs: &'a [f32],
    pub dynamics: &'a Ensemble,
    pub regularizer: &'a Regularizer,
    /// The run's reward and termination models, each exactly when the task learns it.
    pub learned: Learned<'a>,
    /// Who may pause the solve between imagined steps (a plan sharing the cores).
    pub preempt: Option<Arc<dyn Preempt>>,
}

impl PopulationObjective for Imagined<'_> {
    fn evaluate(&mut self, actions: &[f32], returns: &mut [f32]) {
        self.imagination.evaluate(
            self.obs,
            actions,
            self.dynamics,
            self.regularizer,
            self.learned,
            returns,
            self.preempt.as_deref(),
        );
    }
}

/// CEM (the paper's), iCEM or Adam, built from one [`CemConfig`].
#[derive(Debug)]
pub(super) enum Search {
    Cem(Cem),
    Icem(Icem),
    /// Boxed: its rollout memory and Adam state make it twice the size of the others.
    Adam(Box<AdamPlanner>),
}

impl Search {
    pub fn new(
        task: &'static Task,
        config: CemConfig,
        energy_weight: f32,
        seed: u64,
    ) -> Result<Self, ConfigError> {
        let (lower, upper) = (&task.action_low[..], &task.action_high[..]);
        Ok(match config.optimizer {
            Optimizer::Cem => Search::Cem(Cem::new(config, lower, upper, seed)?),
            Optimizer::Icem => Search::Icem(Icem::new(config, lower, upper, seed)?),
            Optimizer::Adam => Search::Adam(Box::new(AdamPlanner::new(
                task,
                config,
                energy_weight,
                seed,
            )?)),
        })
    }

    pub fn config(&self) -> &CemConfig {
        match self {
            Search::Cem(s) => s.config(),
            Search::Icem(s) => s.config(),
            Search::Adam(s) => s.config(),
        }
    }

    pub fn reset(&mut self) {
        match self {
            Search::Cem(s) => s.reset(),
            Search::Icem(s) => s.reset(),
            Search::Adam(s) => s.reset(),
        }
    }

    pub fn shift(&mut self) {
        match self {
            Search::Cem(s) => s.shift(),
            Search::Icem(s) => s.shift(),
            Search::Adam(s) => s.shift(),
        }
    }

    /// One solve within the clock's deadline, and the mean energy per imagined step of what
    /// it settled on (CEM and iCEM: their last elites; Adam: its best sequence; 0 when the
    /// deadline left no time for an iteration).
    pub fn optimize(
        &mut self,
        problem: &mut Imagined<'_>,
        clock: &mut IterationClock,
    ) -> (CemOutcome, f32) {
        let (outcome, elites) = match self {
            Search::Cem(s) => (s.optimize(problem, clock), s.elites()),
            Search::Icem(s) => (s.optimize(problem, clock), s.elites()),
            Search::Adam(s) => {
                let outcome = s.optimize(
                    problem.obs,
                    problem.dynamics,
                    problem.regularizer,
                    problem.learned,
                    clock,
                );
                let energy = if outcome.iterations == 0 {
                    0.0
                } else {
                    s.best_energy()
                };
                return (outcome, energy);
            }
        };
        if outcome.iterations == 0 {
            return (outcome, 0.0);
        }
        let energy = elites
            .iter()
            .map(|&e| problem.imagination.candidate_energy(e))
            .sum::<f32>()
            / elites.len() as f32;
        (outcome, energy)
    }

    /// The plan of the last solve: CEM's mean, iCEM's and Adam's best sequence.
    pub fn plan(&self) -> &[f32] {
        match self {
            Search::Cem(s) => s.mean(),
            Search::Icem(s) => s.best(),
            Search::Adam(s) => s.best(),
        }
    }

    /// The first action of [`Search::plan`].
    pub fn first_action(&self) -> &[f32] {
        match self {
            Search::Cem(s) => s.first_action(),
            Search::Icem(s) => s.first_action(),
            Search::Adam(s) => s.first_action(),
        }
    }

    /// The warm start of the next solve (CEM's and iCEM's distribution mean).
    pub fn mean(&self) -> &[f32] {
        match self {
            Search::Cem(s) => s.mean(),
            Search::Icem(s) => s.mean(),
            Search::Adam(s) => s.mean(),
        }
    }

    pub fn set_mean(&mut self, mean: &[f32]) {
        match self {
            Search::Cem(s) => s.set_mean(mean),
            Search::Icem(s) => s.set_mean(mean),
            Search::Adam(s) => s.set_mean(mean),
        }
    }
}
