//! Planning: the cross-entropy method over action sequences, scored by batched imagination.
//!
//! The arrows point one way: [`settings`] and [`sequence`] import no optimiser; [`cem`],
//! [`icem`] and [`adam`] each import only those two (and the models they plan through); the
//! dispatcher `search` picks one of the three from [`CemConfig::optimizer`], and [`mpc`] drives it.
//!
//! - [`settings`]: every optimiser's settings ([`CemConfig`], [`IcemConfig`], [`AdamConfig`])
//!   and their validation.
//! - [`sequence`]: what the searches share: the [`PopulationObjective`], the box of an action
//!   sequence, the [`CemOutcome`] of a solve.
//! - [`cem`]: CEM as PETS runs it, generic over a [`PopulationObjective`].
//! - [`icem`]: the improved CEM of Pinneri et al. (colored noise, kept elites, decaying
//!   population): fewer candidates per plan; on learned models it kept CEM's return on
//!   cartpole, not on half-cheetah or reacher3d (docs/results.md).
//! - [`adam`]: gradient-based planning through the learned models (the Adam + DAE baseline).
//! - [`imagine`]: the objective of the paper's eq. 5, rolling the learned dynamics forward for
//!   a whole population at once (particles, ensembles, energy, termination), in parallel chunks.
//! - [`anytime`]: the deadline of one solve, and when the next iteration would cross it.
//! - [`mpc`]: [`MpcPlanner`], one agent's model-predictive controller tying the two together.

pub mod adam;
pub mod anytime;
pub mod cem;
pub mod icem;
pub mod imagine;
pub mod mpc;
mod search;
pub mod sequence;
pub mod settings;

pub use adam::AdamPlanner;
pub use anytime::IterationClock;
pub use cem::Cem;
pub use icem::Icem;
pub use imagine::{Imagination, Rollout, Rollouts, Workspace, evaluate_batch};
pub use mpc::{ImaginedPlan, MpcPlanner, PlanOutcome, PlanRequest, default_chunks};
pub use sequence::{CemOutcome, PopulationObjective};
pub use settings::{AdamConfig, CemConfig, ConfigError, IcemConfig, Optimizer};

use crate::reward::RewardModel;
use crate::termination::TerminationModel;

/// The parts of a task that a run learns instead of being told, which imagination scores with
/// beside the dynamics and the regulariser: the reward model exactly when the task's reward is
/// learned, the termination model exactly when its termination is
/// ([`crate::models::Models::learned`]). The service builds it from the run's models, so a
/// mismatch with the task is a bug, not an input (checked by [`Learned::assert_matches`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct Learned<'a> {
    pub reward: Option<&'a RewardModel>,
    pub termination: Option<&'a TerminationModel>,
}

impl<'a> Learned<'a> {
    /// Nothing learned: the task's own reward and termination.
    pub const NONE: Learned<'static> = Learned {
        reward: None,
        termination: None,
    };

    /// A learned reward only.
    pub fn reward(reward: Option<&'a RewardModel>) -> Self {
        Self {
            reward,
            termination: None,
        }
    }

    /// Panics unless each model is given exactly when the task learns that part.
    pub fn assert_matches(&self, task: &proto::Task) {
        assert_eq!(
            self.reward.is_some(),
            task.reward_is_learned(),
            "task {}: a reward model is given exactly when the reward is learned",
            task.name()
        );
        assert_eq!(
            self.termination.is_some(),
            task.termination_is_learned(),
            "task {}: a termination model is given exactly when the termination is learned",
            task.name()
        );
    }
}
