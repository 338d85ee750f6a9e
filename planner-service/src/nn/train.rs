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

impl FitReport {
    /// The report of a fit that had no data or no epochs: nothing was trained, so the loss is
    /// undefined (the model keeps its statistics as well as its weights).
    pub fn untrained(samples: usize, epochs: usize) -> Self {
        Self {
            samples,
            epochs,
            loss: f32::NAN,
            ..Self::default()
        }
    }
}

/// `epochs` passes over `order` (indices of training samples, e.g. a bootstrap resample), each
/// in freshly shuffled minibatches of `batch_size`; `step` takes one optimiser step on a
/// minibatch and returns its mean loss. Returns the mean loss of the last epoch (NaN if
/// nothing ran) and the number of steps.
pub fn run_epochs(
    order: &mut [usize],
    batch_size: usize,
    epochs: usize,
    rng: &mut StdRng,
    mut step: impl FnMut(&[usize], &mut StdRng) -> f32,
) -> (f32, usize) {
    let (mut last, mut steps) = (f32::NAN, 0);
    if order.is_empty() {
        return (last, steps);
    }
    for _ in 0..epochs {
        let (mut total, mut count) = (0.0f64, 0usize);
        order.shuffle(rng);
        for batch in order.chunks(batch_size.max(1)) {
            total += step(batch, rng) as f64 * batch.len() as f64;
            count += batch.len();
            steps += 1;
        }
        last = (total / count as f64) as f32;
    }
    (last, steps)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn every_epoch_visits_every_index_once_in_shuffled_batches() {
        let mut rng = StdRng::seed_from_u64(0);
        let mut order: Vec<usize> = (0..10).collect();
        let mut batches: Vec<Vec<usize>> = vec![];
        let (loss, steps) = run_epochs(&mut order, 4, 2, &mut rng, |batch, _| {
            batches.push(batch.to_vec());
            batch.iter().map(|&i| i as f32).sum::<f32>() / batch.len() as f32
        });
        assert_eq!(
            batches.iter().map(Vec::len).collect::<Vec<_>>(),
            vec![4, 4, 2, 4, 4, 2]
        );
        for epoch in batches.chunks(3) {
            let mut all = epoch.concat();
            assert_ne!(all, (0..10).collect::<Vec<_>>(), "shuffled");
            all.sort();
            assert_eq!(all, (0..10).collect::<Vec<_>>());
        }
        // The last epoch's per-batch means weighted by batch size: the mean index, 4.5.
        assert!((loss - 4.5).abs() < 1e-6 && steps == 6, "{loss} {steps}");
        assert!(run_epochs(&mut [], 2, 3, &mut rng, |_, _| 1.0).0.is_nan());
    }
}
