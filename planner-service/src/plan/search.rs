//! The planner's choice of optimiser ([`CemConfig::optimizer`]): one type that the MPC loop
//! drives the same way whichever search runs underneath.

use super::anytime::IterationClock;
use super::cem::{Cem, CemConfig, CemOutcome, ConfigError, Optimizer, PopulationObjective};
use super::icem::Icem;

/// CEM (the paper's) or iCEM, built from one [`CemConfig`].
#[derive(Debug)]
pub(super) enum Search {
    Cem(Cem),
    Icem(Icem),
}

impl Search {
    pub fn new(
        config: CemConfig,
        lower: &[f32],
        upper: &[f32],
        seed: u64,
    ) -> Result<Self, ConfigError> {
        Ok(match config.optimizer {
            Optimizer::Cem => Search::Cem(Cem::new(config, lower, upper, seed)?),
            Optimizer::Icem => Search::Icem(Icem::new(config, lower, upper, seed)?),
        })
    }

    pub fn config(&self) -> &CemConfig {
        match self {
            Search::Cem(s) => s.config(),
            Search::Icem(s) => s.config(),
        }
    }

    pub fn reset(&mut self) {
        match self {
            Search::Cem(s) => s.reset(),
            Search::Icem(s) => s.reset(),
        }
    }

    pub fn shift(&mut self) {
        match self {
            Search::Cem(s) => s.shift(),
            Search::Icem(s) => s.shift(),
        }
    }

    pub fn optimize<O: PopulationObjective + ?Sized>(
        &mut self,
        objective: &mut O,
        clock: &mut IterationClock,
    ) -> CemOutcome {
        match self {
            Search::Cem(s) => s.optimize(objective, clock),
            Search::Icem(s) => s.optimize(objective, clock),
        }
    }

    /// Indices of the last iteration's elites in the population it scored.
    pub fn elites(&self) -> &[usize] {
        match self {
            Search::Cem(s) => s.elites(),
            Search::Icem(s) => s.elites(),
        }
    }

    /// The plan of the last solve: CEM's mean, iCEM's best sequence.
    pub fn plan(&self) -> &[f32] {
        match self {
            Search::Cem(s) => s.mean(),
            Search::Icem(s) => s.best(),
        }
    }

    /// The first action of [`Search::plan`].
    pub fn first_action(&self) -> &[f32] {
        match self {
            Search::Cem(s) => s.first_action(),
            Search::Icem(s) => s.first_action(),
        }
    }

    /// The distribution's mean: the warm start of the next solve.
    pub fn mean(&self) -> &[f32] {
        match self {
            Search::Cem(s) => s.mean(),
            Search::Icem(s) => s.mean(),
        }
    }

    pub fn set_mean(&mut self, mean: &[f32]) {
        match self {
            Search::Cem(s) => s.set_mean(mean),
            Search::Icem(s) => s.set_mean(mean),
        }
    }
}
