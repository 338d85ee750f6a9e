//! The ebmpc planner: learned dynamics, energy regularisers, CEM model-predictive control, the
//! replay buffer and trainer, and the Zenoh service that serves many runs and agents.
//!
//! Layout (one concept per module):
//! - [`data`]: transitions `(s, a, s')` as dense matrices, the currency between the parts below.
//! - [`nn`]: plain MLPs with hand-written forward, input-gradient and parameter-gradient passes.
//! - [`dynamics`]: probabilistic dynamics models and PETS-style ensembles.
//! - [`energy`]: the regularisers scoring how familiar a transition is: DEEN and DAE.
//! - [`plan`]: CEM over action sequences and the batched imagination that scores them.

pub mod agent;
pub mod config;
pub mod data;
pub mod dynamics;
pub mod energy;
pub mod fleet;
pub mod models;
pub mod nn;
pub mod persist;
pub mod plan;
pub mod replay;
pub mod reward;
pub mod run;
pub mod sched;
pub mod service;
pub mod termination;
pub mod trainer;
