//! Planning: the cross-entropy method over action sequences, scored by batched imagination.
//!
//! - [`cem`]: CEM as PETS runs it, generic over a [`PopulationObjective`].
//! - [`imagine`]: the objective of the paper's eq. 5, rolling the learned dynamics forward for
//!   a whole population at once (particles, ensembles, energy, termination), in parallel chunks.
//! - [`mpc`]: [`MpcPlanner`], one agent's model-predictive controller tying the two together.

pub mod cem;
pub mod imagine;
pub mod mpc;

pub use cem::{Cem, CemConfig, CemOutcome, ConfigError, PopulationObjective};
pub use imagine::Imagination;
pub use mpc::{ImaginedPlan, MpcPlanner, PlanOutcome};
