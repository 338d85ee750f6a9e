//! Planning: the cross-entropy method over action sequences, scored by batched imagination.
//!
//! - [`cem`]: CEM as PETS runs it, generic over a [`PopulationObjective`].
//! - [`icem`]: the improved CEM of Pinneri et al. (colored noise, kept elites, decaying
//!   population), the real-time option.
//! - [`imagine`]: the objective of the paper's eq. 5, rolling the learned dynamics forward for
//!   a whole population at once (particles, ensembles, energy, termination), in parallel chunks.
//! - [`mpc`]: [`MpcPlanner`], one agent's model-predictive controller tying the two together.

pub mod adam;
pub mod cem;
pub mod icem;
pub mod imagine;
pub mod mpc;
mod search;

pub use adam::{AdamConfig, AdamPlanner};
pub use cem::{Cem, CemConfig, CemOutcome, ConfigError, Optimizer, PopulationObjective};
pub use icem::{Icem, IcemConfig};
pub use imagine::Imagination;
pub use mpc::{ImaginedPlan, MpcPlanner, PlanOutcome};
