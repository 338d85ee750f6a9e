//! What training loops share: minibatch schedules, what may cut a fit short, and the report
//! of a fit.

use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// How long a fit may run: its epochs, and what may end it sooner. Checked before every
/// minibatch, so a fit stops within one optimiser step of being asked to. A bare number of
/// epochs converts into a budget with nothing else.
#[derive(Clone, Debug, Default)]
pub struct FitBudget {
    pub epochs: usize,
    /// Most optimiser steps (per ensemble member).
    pub max_steps: Option<usize>,
    /// No minibatch starts after this instant.
    pub deadline: Option<Instant>,
    /// Set from outside (the daemon shutting down): no further minibatch starts.
    pub cancel: Option<Arc<AtomicBool>>,
    /// Plans to yield to: before each minibatch the fit waits while any holds or waits for the
    /// cores, for a time bounded by its guaranteed share, and then takes a slice from them
    /// ([`crate::sched::Scheduler::before_minibatch`]). Never on the planning pool's threads: a
    /// fit running on one would hold the very thread a plan needs (the daemon fits on the
    /// background pool, see [`crate::sched::background`]).
    pub yield_to: Option<Arc<crate::sched::Scheduler>>,
}

impl From<usize> for FitBudget {
    fn from(epochs: usize) -> Self {
        Self {
            epochs,
            ..Self::default()
        }
    }
}

/// Why a fit ended before its epochs were done.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stop {
    /// It took its [`FitBudget::max_steps`].
    StepCap,
    /// Its [`FitBudget::deadline`] passed.
    Deadline,
    /// It was cancelled.
    Cancelled,
}

impl FitBudget {
    /// Why no further step may start after `steps` steps (`None`: it may).
    fn stop(&self, steps: usize) -> Option<Stop> {
        if self
            .cancel
            .as_ref()
            .is_some_and(|c| c.load(Ordering::Relaxed))
        {
            Some(Stop::Cancelled)
        } else if self.max_steps.is_some_and(|max| steps >= max) {
            Some(Stop::StepCap)
        } else if self.deadline.is_some_and(|d| Instant::now() >= d) {
            Some(Stop::Deadline)
        } else {
            None
        }
    }
}

/// What [`run_epochs`] did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpochsRun {
    /// Mean loss of the last (possibly partial) epoch's minibatches; NaN if none ran.
    pub loss: f32,
    pub steps: usize,
    pub stopped: Option<Stop>,
}

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
    /// Why the fit ended before its epochs were done, if it did.
    #[serde(default)]
    pub stopped: Option<Stop>,
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

/// `budget.epochs` passes over `order` (indices of training samples, e.g. a bootstrap
/// resample), each in freshly shuffled minibatches of `batch_size`, until the budget says
/// stop; `step` takes one optimiser step on a minibatch and returns its mean loss.
pub fn run_epochs(
    order: &mut [usize],
    batch_size: usize,
    budget: &FitBudget,
    rng: &mut StdRng,
    mut step: impl FnMut(&[usize], &mut StdRng) -> f32,
) -> EpochsRun {
    let mut run = EpochsRun {
        loss: f32::NAN,
        steps: 0,
        stopped: None,
    };
    if order.is_empty() {
        return run;
    }
    // How long the last minibatch took: a retraining beside plans that never stop waits a
    // multiple of it before it takes a slice (see `crate::sched`).
    let mut last_minibatch = std::time::Duration::ZERO;
    'epochs: for _ in 0..budget.epochs {
        let (mut total, mut count) = (0.0f64, 0usize);
        order.shuffle(rng);
        for batch in order.chunks(batch_size.max(1)) {
            if let Some(stop) = budget.stop(run.steps) {
                run.stopped = Some(stop);
                if count > 0 {
                    run.loss = (total / count as f64) as f32;
                }
                break 'epochs;
            }
            let _slice = match &budget.yield_to {
                Some(plans) if crate::sched::background::may_wait_for_plans() => {
                    plans.before_minibatch(last_minibatch)
                }
                _ => None,
            };
            let started = Instant::now();
            total += step(batch, rng) as f64 * batch.len() as f64;
            last_minibatch = started.elapsed();
            count += batch.len();
            run.steps += 1;
        }
        run.loss = (total / count as f64) as f32;
    }
    run
}

/// How a small network is trained on its own: minibatches of `batch_size`, and `weight_decay`
/// added to each weight's gradient at every Adam step (see [`super::Adam::step_decaying`]).
#[derive(Clone, Copy, Debug)]
pub struct Minibatches {
    pub batch_size: usize,
    pub weight_decay: f32,
}

/// Trains `mlp` with `adam` on samples `0..n` for the budget's epochs in shuffled minibatches
/// (see [`run_epochs`]): for each minibatch `loss_and_grad` runs the forward pass on the tape,
/// seeds its output gradient and returns the minibatch's mean loss; the gradient of the
/// weights is then taken and one Adam step applied. The learned reward and the learned
/// termination train this way; only their inputs and losses differ.
pub fn fit_minibatches(
    mlp: &mut super::Mlp,
    adam: &mut super::Adam,
    settings: Minibatches,
    n: usize,
    budget: &FitBudget,
    rng: &mut StdRng,
    mut loss_and_grad: impl FnMut(&super::Mlp, &[usize], &mut super::Tape) -> f32,
) -> EpochsRun {
    let mut tape = super::Tape::for_training(mlp, settings.batch_size.min(n).max(1));
    let mut grads = vec![0.0; mlp.params().len()];
    let mut order: Vec<usize> = (0..n).collect();
    run_epochs(&mut order, settings.batch_size, budget, rng, |batch, _| {
        let loss = loss_and_grad(mlp, batch, &mut tape);
        mlp.backward(&mut tape, &mut grads, false);
        adam.step_decaying(mlp, &grads, settings.weight_decay);
        loss
    })
}

/// Copies the minibatch `batch` of the sample-major `inputs` (one row of `mlp.in_dim()` values
/// per sample) into the tape's inputs, one column per sample, and runs the training forward
/// pass; the loss then reads the outputs and seeds their gradient in the tape.
pub fn forward_minibatch(
    mlp: &super::Mlp,
    inputs: &[f32],
    batch: &[usize],
    tape: &mut super::Tape,
) {
    let (dim, ld) = (mlp.in_dim(), tape.ld());
    let input = tape.input_mut();
    for (col, &idx) in batch.iter().enumerate() {
        for (k, &v) in inputs[idx * dim..(idx + 1) * dim].iter().enumerate() {
            input[k * ld + col] = v;
        }
    }
    mlp.forward_train(tape, batch.len());
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
        let run = run_epochs(&mut order, 4, &2.into(), &mut rng, |batch, _| {
            batches.push(batch.to_vec());
            batch.iter().map(|&i| i as f32).sum::<f32>() / batch.len() as f32
        });
        let (loss, steps) = (run.loss, run.steps);
        assert_eq!(run.stopped, None);
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
        assert!(
            run_epochs(&mut [], 2, &3.into(), &mut rng, |_, _| 1.0)
                .loss
                .is_nan()
        );
    }

    /// A step cap, a passed deadline and a cancel flag each stop the loop before the next
    /// minibatch, and say which did.
    #[test]
    fn a_budget_stops_the_epochs_between_minibatches() {
        let mut rng = StdRng::seed_from_u64(1);
        let mut order: Vec<usize> = (0..10).collect();
        let capped = FitBudget {
            epochs: 100,
            max_steps: Some(7),
            ..FitBudget::default()
        };
        let run = run_epochs(&mut order, 4, &capped, &mut rng, |_, _| 2.0);
        assert_eq!(
            (run.steps, run.stopped, run.loss),
            (7, Some(Stop::StepCap), 2.0)
        );

        let past = FitBudget {
            epochs: 100,
            deadline: Some(Instant::now()),
            ..FitBudget::default()
        };
        let run = run_epochs(&mut order, 4, &past, &mut rng, |_, _| 1.0);
        assert_eq!((run.steps, run.stopped), (0, Some(Stop::Deadline)));
        assert!(run.loss.is_nan());

        let cancel = Arc::new(AtomicBool::new(false));
        let cancellable = FitBudget {
            epochs: 100,
            cancel: Some(cancel.clone()),
            ..FitBudget::default()
        };
        let run = run_epochs(&mut order, 4, &cancellable, &mut rng, |_, _| {
            cancel.store(true, Ordering::Relaxed);
            1.0
        });
        assert_eq!((run.steps, run.stopped), (1, Some(Stop::Cancelled)));
    }
}
