//! Planning: the cross-entropy method over action sequences, scored by batched imagination.
//!
//! - [`cem`]: CEM as PETS runs it, generic over a [`PopulationObjective`].
//! - [`icem`]: the improved CEM of Pinneri et al. (colored noise, kept elites, decaying
//!   population): fewer candidates per plan; on learned models it kept CEM's return on
//!   cartpole, not on half-cheetah or reacher3d (docs/results.md).
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

pub use adam::{AdamConfig, AdamPlanner};
pub use anytime::IterationClock;
pub use cem::{Cem, CemConfig, CemOutcome, ConfigError, Optimizer, PopulationObjective};
pub use icem::{Icem, IcemConfig};
pub use imagine::Imagination;
pub use mpc::{ImaginedPlan, MpcPlanner, PlanOutcome};
