//! Retraining a run's models on its whole replay buffer (paper §2, Figure 1).
//!
//! Training starts from the current weights (the buffer only grows between two retrainings)
//! with the epochs the preset's schedule gives for the number of stored episodes.

use crate::config::Preset;
use crate::data::Transitions;
use crate::models::Models;
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::time::Instant;

/// What one retraining did.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainReport {
    pub models_version: u64,
    pub transitions: usize,
    pub dynamics_epochs: usize,
    pub energy_epochs: usize,
    pub dynamics_loss: f32,
    pub energy_loss: f32,
    pub seconds: f32,
}

/// Trains a copy of `current` on `data`, which holds the transitions of `episodes` finished
/// episodes, and returns the next version.
pub fn retrain(
    current: &Models,
    data: &Transitions,
    preset: &Preset,
    episodes: u32,
    seed: u64,
) -> (Models, TrainReport) {
    let started = Instant::now();
    let mut rng =
        StdRng::seed_from_u64(seed ^ (current.version + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let (dynamics_epochs, energy_epochs) = preset.epochs(episodes);
    let mut next = current.clone();
    let dynamics = next.dynamics.fit(data, dynamics_epochs, &mut rng);
    let energy = next.regularizer.fit(data, energy_epochs, &mut rng);
    next.version = current.version + 1;
    next.episodes_covered = episodes;
    next.pack_for_inference();
    let report = TrainReport {
        models_version: next.version,
        transitions: data.len(),
        dynamics_epochs,
        energy_epochs,
        dynamics_loss: dynamics.loss,
        energy_loss: energy.loss,
        seconds: started.elapsed().as_secs_f32(),
    };
    (next, report)
}
