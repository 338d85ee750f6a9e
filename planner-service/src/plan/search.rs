//! The planner's choice of optimiser ([`CemConfig::optimizer`]): one type that the MPC loop
//! drives the same way whichever search runs underneath.

use super::Learned;
use super::adam::AdamPlanner;
use super::anytime::IterationClock;
use super::cem::Cem;
use super::icem::Icem;
use super::imagine::Imagination;
use super::sequence::{CemOutcome, SteppedSearch};
use super::settings::{CemConfig, ConfigError, Optimizer};
use crate::dynamics::Ensemble;
use crate::energy::Regularizer;
use proto::Task;

/// CEM (the paper's), iCEM or Adam, built from one [`CemConfig`].
#[derive(Debug)]
pub(super) enum Search {
    // Each boxed: their sizes differ by hundreds of bytes (iCEM's random stream and
    // colored-noise state, Adam's rollout memory), and a planner holds exactly one.
    Cem(Box<Cem>),
    Icem(Box<Icem>),
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
            Optimizer::Cem => Search::Cem(Box::new(Cem::new(config, lower, upper, seed)?)),
            Optimizer::Icem => Search::Icem(Box::new(Icem::new(config, lower, upper, seed)?)),
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

    /// CEM and iCEM, run iteration by iteration (several agents' solves in lockstep, see
    /// [`super::sequence::solve_lockstep`]); `None` for Adam, which solves alone
    /// ([`Search::solve_gradient`]).
    pub fn stepped(&mut self) -> Option<&mut dyn SteppedSearch> {
        match self {
            Search::Cem(s) => Some(s.as_mut()),
            Search::Icem(s) => Some(s.as_mut()),
            Search::Adam(_) => None,
        }
    }

    /// Adam's solve from `obs` within the clock's deadline, and the mean energy per imagined
    /// step of its best sequence (0 when the deadline left no time for an iteration); `None`
    /// for CEM and iCEM.
    pub fn solve_gradient(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        clock: &mut IterationClock,
    ) -> Option<(CemOutcome, f32)> {
        let Search::Adam(s) = self else {
            return None;
        };
        let outcome = s.optimize(obs, dynamics, regularizer, learned, clock);
        let energy = if outcome.iterations == 0 {
            0.0
        } else {
            s.best_energy()
        };
        Some((outcome, energy))
    }

    /// After a CEM or iCEM solve that ran an iteration: the mean energy per imagined step of
    /// its last elites, as `imagination` scored them.
    pub fn elite_energy(&self, imagination: &Imagination) -> f32 {
        let elites = match self {
            Search::Cem(s) => s.elites(),
            Search::Icem(s) => s.elites(),
            Search::Adam(s) => return s.best_energy(),
        };
        elites
            .iter()
            .map(|&e| imagination.candidate_energy(e))
            .sum::<f32>()
            / elites.len() as f32
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
