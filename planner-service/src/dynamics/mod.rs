//! Learned dynamics models: a probabilistic MLP and PETS-style bootstrapped ensembles.
//!
//! - [`config`]: sizes and training settings (Table 2's "Model" rows).
//! - [`gaussian`]: the output head, a Gaussian with softly bounded log-variance, and its loss.
//! - [`model`]: one [`ProbabilisticModel`]: training on minibatches, allocation-free prediction.
//! - [`ensemble`]: [`Ensemble`] of bootstrapped members trained in parallel.
//!
//! The planner's interface (all on [`Ensemble`]; never allocating once the scratch exists):
//!
//! ```text
//! fn scratch(&self, max_rows: usize) -> DynamicsScratch
//! fn members(&self) -> usize
//! fn predict_next(&self, member: usize, obs: &[f32], act: &[f32], rows: usize,
//!                 scratch: &mut DynamicsScratch, noise: Option<&[f32]>, next_obs: &mut [f32])
//! DynamicsScratch::fits(&self, ensemble: &Ensemble, rows: usize) -> bool
//! ```
//!
//! and the trainer's: `Ensemble::new(task, &config, &mut rng)`,
//! `Ensemble::fit(&mut self, &Transitions, epochs, &mut rng) -> FitReport`.

pub mod config;
pub mod ensemble;
pub mod gaussian;
pub mod model;

pub use config::DynamicsConfig;
pub use ensemble::Ensemble;
pub use model::{
    DynamicsScratch, MeanTape, ModelParts, ProbabilisticModel, TrainWorkspace, TrainingSet,
};

#[cfg(test)]
mod tests;
