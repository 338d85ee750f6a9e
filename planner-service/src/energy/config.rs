//! Sizes and training settings of an energy model (the paper's Table 2, "DEEN" rows; the DAE
//! uses the same).

pub use proto::NoiseUnits;
use serde::{Deserialize, Serialize};

/// How a DEEN or DAE is built and trained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnergyConfig {
    /// Hidden layers (softplus activations).
    pub hidden_layers: usize,
    /// Units per hidden layer.
    pub hidden_size: usize,
    /// Passes over the data per retraining (the trainer's schedule may override it per call).
    pub epochs: usize,
    pub batch_size: usize,
    /// Standard deviation `σ` of the corrupting noise, in `noise_units`.
    pub noise_sigma: f32,
    /// What `σ` is measured in: standard deviations of each dimension (every dimension of the
    /// transition scaled to unit variance first, so one `σ` fits all), or the transitions' own
    /// units, as the paper corrupts its replay buffer (see [`NoiseUnits`]).
    #[serde(default)]
    pub noise_units: NoiseUnits,
    /// Adam's step size.
    pub learning_rate: f32,
}

impl Default for EnergyConfig {
    /// The paper's cartpole DEEN: 3 × 200, σ = 0.1, batch 32, Adam at 1e-3.
    fn default() -> Self {
        Self {
            hidden_layers: 3,
            hidden_size: 200,
            epochs: 500,
            batch_size: 32,
            noise_sigma: 0.1,
            noise_units: NoiseUnits::Standardised,
            learning_rate: 1e-3,
        }
    }
}

/// Everything that determines an energy model's outputs — what persistence stores. (Adam's
/// moments are not included: a restored model's optimiser starts afresh.)
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnergyParts {
    /// The network's parameters, laid out as [`crate::nn::Mlp::params`].
    pub params: Vec<f32>,
    pub normalizer: crate::nn::Normalizer,
}

/// Layer sizes `[dim, hidden…, out]` of an energy network.
pub fn layer_sizes(dim: usize, config: &EnergyConfig, out: usize) -> Vec<usize> {
    let mut sizes = vec![dim];
    sizes.extend(std::iter::repeat_n(
        config.hidden_size,
        config.hidden_layers,
    ));
    sizes.push(out);
    sizes
}
