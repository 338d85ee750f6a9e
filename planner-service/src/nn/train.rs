//! What training loops share: minibatch schedules and the report of a fit.

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};

/// What one call to a model's `fit` did.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    /// Transitions in the training data.
    pub samples: usize,
    pub epochs: usize,
    /// Optimiser steps (minibatches) taken, summed over ensemble members.
    pub steps: usize,
    /// Mean training loss over the last epoch's minibatches (the model's own objective,
    /// without weight decay); averaged over ensemble members.
    pub loss: f32,
    /// Dynamics models: mean Gaussian negative log-likelihood per target dimension on the whole
    /// data after training (standardised targets, including `½ ln 2π`).
    pub nll: Option<f32>,
    /// Dynamics models: mean squared error of the predicted mean on the whole data after
    /// training, in units of each target dimension's variance (1 = no better than the mean).
    pub mse: Option<f32>,
    /// Wall-clock seconds.
    pub seconds: f32,
}

/// The minibatches of one epoch: `order` shuffled in place and cut into runs of `batch_size`
/// (the last one may be shorter), as PETS does.
pub fn shuffled_batches<'a>(
    order: &'a mut [usize],
    batch_size: usize,
    rng: &mut StdRng,
) -> impl Iterator<Item = &'a [usize]> {
    assert!(batch_size > 0, "batch size must be positive");
    order.shuffle(rng);
    order.chunks(batch_size)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn batches_cover_every_index_once_per_epoch() {
        let mut rng = StdRng::seed_from_u64(0);
        let mut order: Vec<usize> = (0..10).collect();
        let batches: Vec<Vec<usize>> = shuffled_batches(&mut order, 4, &mut rng)
            .map(|b| b.to_vec())
            .collect();
        assert_eq!(
            batches.iter().map(Vec::len).collect::<Vec<_>>(),
            vec![4, 4, 2]
        );
        let mut all: Vec<usize> = batches.concat();
        assert_ne!(all, (0..10).collect::<Vec<_>>(), "shuffled");
        all.sort();
        assert_eq!(all, (0..10).collect::<Vec<_>>());
    }
}
