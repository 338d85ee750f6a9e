//! Sizes and training settings of a dynamics model (the paper's Table 2, "Model" rows).

use serde::{Deserialize, Serialize};

/// How a dynamics model (or ensemble) is built and trained.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DynamicsConfig {
    /// Hidden layers of each network (Swish activations).
    pub hidden_layers: usize,
    /// Units per hidden layer.
    pub hidden_size: usize,
    /// Members of the ensemble; 1 is the paper's single model (trained on all the data),
    /// more is PETS (each member on its own bootstrap resample).
    pub ensemble_size: usize,
    /// Passes over the data per retraining (the trainer's schedule may override it per call).
    pub epochs: usize,
    pub batch_size: usize,
    /// Adam's step size.
    pub learning_rate: f32,
    /// L2 penalty `λ/2 ‖W‖²` on every weight matrix (PETS's weight decay; biases excluded).
    pub weight_decay: f32,
}

impl Default for DynamicsConfig {
    /// The paper's cartpole model: 3 × 200, one network, batch 32, Adam at 1e-3.
    fn default() -> Self {
        Self {
            hidden_layers: 3,
            hidden_size: 200,
            ensemble_size: 1,
            epochs: 500,
            batch_size: 32,
            learning_rate: 1e-3,
            weight_decay: 5e-5,
        }
    }
}

/// Layer sizes `[state features + action, hidden…, 2 × obs]` of one member's network: it
/// predicts a mean and a log-variance per observation dimension.
pub fn layer_sizes(task: &proto::Task, config: &DynamicsConfig) -> Vec<usize> {
    let mut sizes = vec![task.state_feature_dim + task.act_dim];
    sizes.extend(std::iter::repeat_n(
        config.hidden_size,
        config.hidden_layers,
    ));
    sizes.push(2 * task.obs_dim);
    sizes
}
