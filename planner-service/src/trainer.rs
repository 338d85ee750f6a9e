//! Retraining a run's models on its whole replay buffer (paper §2, Figure 1).
//!
//! Training starts from the current weights (the buffer only grows between two retrainings)
//! with the epochs the preset's schedule gives for the stored episodes and transitions,
//! within the run's budget: the preset's cap on gradient steps, the daemon's seconds per
//! retraining, and a cancel flag the daemon raises when it stops. A retraining whose losses or parameters are
//! not all finite is discarded: the caller keeps serving the previous models.

use crate::config::Preset;
use crate::data::Transitions;
use crate::models::Models;
use crate::nn::train::{FitBudget, Stop};
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

/// What one retraining did.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainReport {
    pub models_version: u64,
    pub transitions: usize,
    pub dynamics_epochs: usize,
    pub energy_epochs: usize,
    /// Optimiser steps taken by the dynamics (summed over members) and the regulariser.
    pub dynamics_steps: usize,
    pub energy_steps: usize,
    pub dynamics_loss: f32,
    pub energy_loss: f32,
    /// The reward model's steps and last-epoch loss (`None`: the task's reward is not learned).
    pub reward_steps: usize,
    pub reward_loss: Option<f32>,
    /// The termination model's steps, and its accuracy on the transitions held out of its
    /// training (`None`: the task's termination is not learned, or no episode has ended as
    /// `terminated` yet).
    pub termination_steps: usize,
    pub termination_accuracy: Option<proto::TerminationAccuracy>,
    /// Why a model's training ended before its epochs (the step cap or the time budget).
    pub cut_short: Option<Stop>,
    pub seconds: f32,
}

/// The daemon's side of a retraining's budget.
#[derive(Clone, Debug)]
pub struct TrainLimits {
    /// Wall-clock budget of one retraining: the dynamics may use its first half, a reward
    /// model (for a learned reward) up to three quarters, the regulariser what is left.
    pub max_seconds: f64,
    /// Raised when the daemon stops: training ends before its next minibatch.
    pub cancel: Arc<AtomicBool>,
    /// The daemon's plan queue, which retraining yields to between minibatches.
    pub yield_to: Option<Arc<crate::sched::Scheduler>>,
}

impl TrainLimits {
    /// No time budget and a cancel flag nobody raises: for experiments and tests, which train
    /// the preset's full epochs.
    pub fn unbounded() -> Self {
        Self {
            max_seconds: f64::INFINITY,
            cancel: Arc::new(AtomicBool::new(false)),
            yield_to: None,
        }
    }

    /// The instant `fraction` of the time budget after `started` (`None`: no deadline).
    fn deadline(&self, started: Instant, fraction: f64) -> Option<Instant> {
        Duration::try_from_secs_f64(self.max_seconds * fraction)
            .ok()
            .and_then(|d| started.checked_add(d))
    }
}

/// Why a retraining produced no models.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrainError {
    #[error("training was cancelled")]
    Cancelled,
    #[error("training diverged: the {what} is not finite; the previous models stay in use")]
    NonFinite { what: String },
}

/// Trains a copy of `current` on `data`, which holds the transitions of `episodes` finished
/// episodes, and returns the next version.
pub fn retrain(
    current: &Models,
    data: &Transitions,
    preset: &Preset,
    episodes: u32,
    seed: u64,
    limits: &TrainLimits,
) -> Result<(Models, TrainReport), TrainError> {
    let started = Instant::now();
    let mut rng =
        StdRng::seed_from_u64(seed ^ (current.version + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let (dynamics_epochs, energy_epochs) = preset.epochs(episodes, data.len());
    let plan = |epochs: usize, deadline: Option<Instant>| FitBudget {
        epochs,
        max_steps: preset
            .max_gradient_steps
            .map(|s| usize::try_from(s).unwrap_or(usize::MAX)),
        deadline,
        cancel: Some(limits.cancel.clone()),
        yield_to: limits.yield_to.clone(),
    };
    let mut next = current.clone();
    let dynamics = next.dynamics.fit(
        data,
        plan(dynamics_epochs, limits.deadline(started, 0.5)),
        &mut rng,
    );
    // A learned reward trains on the same data with the dynamics' epochs: it is the other half
    // of the model of the system that imagination rolls out.
    let reward = next.reward.as_mut().map(|model| {
        model.fit(
            data,
            plan(dynamics_epochs, limits.deadline(started, 0.75)),
            &mut rng,
        )
    });
    // A learned termination trains on the same data with the dynamics' epochs, in the same
    // share of the time budget as a learned reward (the two are the system's other halves).
    let termination = next.termination.as_mut().map(|model| {
        model.fit(
            data,
            plan(dynamics_epochs, limits.deadline(started, 0.75)),
            &mut rng,
        )
    });
    let energy = next.regularizer.fit(
        data,
        plan(energy_epochs, limits.deadline(started, 1.0)),
        &mut rng,
    );
    let reports = [
        Some(("dynamics loss", &dynamics)),
        reward.as_ref().map(|r| ("reward model loss", r)),
        termination.as_ref().map(|r| ("termination model loss", r)),
        Some(("regulariser loss", &energy)),
    ];
    let reports = reports.iter().flatten();
    if reports
        .clone()
        .any(|(_, r)| r.stopped == Some(Stop::Cancelled))
    {
        return Err(TrainError::Cancelled);
    }
    for (what, report) in reports {
        if report.steps > 0 && !report.loss.is_finite() {
            return Err(TrainError::NonFinite {
                what: (*what).into(),
            });
        }
    }
    if let Some(what) = next.first_non_finite() {
        return Err(TrainError::NonFinite { what });
    }
    next.version = current.version + 1;
    next.episodes_covered = episodes;
    next.pack_for_inference();
    let report = TrainReport {
        models_version: next.version,
        transitions: data.len(),
        dynamics_epochs,
        energy_epochs,
        dynamics_steps: dynamics.steps,
        energy_steps: energy.steps,
        dynamics_loss: dynamics.loss,
        energy_loss: energy.loss,
        reward_steps: reward.as_ref().map_or(0, |r| r.steps),
        reward_loss: reward.as_ref().map(|r| r.loss),
        termination_steps: termination.as_ref().map_or(0, |r| r.steps),
        termination_accuracy: next.termination.as_ref().and_then(|t| t.held_out()),
        cut_short: dynamics
            .stopped
            .or(reward.as_ref().and_then(|r| r.stopped))
            .or(termination.as_ref().and_then(|r| r.stopped))
            .or(energy.stopped),
        seconds: started.elapsed().as_secs_f32(),
    };
    Ok((next, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::{Builtin, PlannerOverrides};
    use std::sync::atomic::Ordering;

    fn small_preset() -> Preset {
        let mut preset = Preset::new(Builtin::Cartpole.task(), Some("cem+deen")).unwrap();
        preset
            .apply(&PlannerOverrides {
                dynamics_hidden_layers: Some(1),
                dynamics_hidden_size: Some(8),
                energy_hidden_layers: Some(1),
                energy_hidden_size: Some(8),
                dynamics_epochs: Some(3),
                energy_epochs: Some(3),
                ..Default::default()
            })
            .unwrap();
        preset
    }

    /// Cartpole-shaped transitions whose observations are `scale` × a smooth pattern.
    fn data(n: usize, scale: f32) -> Transitions {
        let mut data = Transitions::new(4, 1);
        for i in 0..n {
            let x = i as f32 / n as f32;
            let obs = [x * scale, -x * scale, 0.5 * scale, (1.0 - x) * scale];
            let next = [-x * scale, x * scale, -0.5 * scale, x * scale];
            data.push(&obs, &[x], 0.0, &next);
        }
        data
    }

    fn untrained(preset: &Preset) -> Models {
        Models::untrained(Builtin::Cartpole.task(), preset, 7)
    }

    #[test]
    fn ordinary_data_trains_finite_models() {
        let preset = small_preset();
        let (models, report) = retrain(
            &untrained(&preset),
            &data(64, 1.0),
            &preset,
            1,
            0,
            &TrainLimits::unbounded(),
        )
        .unwrap();
        assert_eq!(models.version, 1);
        assert!(models.first_non_finite().is_none());
        assert!(report.dynamics_loss.is_finite() && report.energy_loss.is_finite());
        assert_eq!(report.cut_short, None);
    }

    /// A task whose reward is learned retrains its reward model with the dynamics (the same
    /// epochs), on the transitions' rewards; the models are trained only once it has.
    #[test]
    fn a_learned_reward_trains_its_model_with_the_dynamics() {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "trainer-learned-cartpole".into();
        spec.reward = proto::task::RewardKind::Learned;
        let task = proto::Task::intern(spec, &proto::task::SpecBounds::default()).unwrap();
        let mut preset = Preset::new(task, Some("cem")).unwrap();
        preset.dynamics.hidden_size = 8;
        preset.dynamics.epochs = 3;
        preset.reward.hidden_size = 8;
        let fresh = Models::untrained(task, &preset, 7);
        assert!(!fresh.reward.as_ref().unwrap().is_trained());
        let mut rewarded = Transitions::new(4, 1);
        let plain = data(64, 1.0);
        for i in 0..plain.len() {
            let (s, a, s1) = plain.row(i);
            rewarded.push(s, a, s1[0] - a[0], s1);
        }
        let (models, report) =
            retrain(&fresh, &rewarded, &preset, 1, 0, &TrainLimits::unbounded()).unwrap();
        assert!(models.is_trained() && models.reward.as_ref().unwrap().is_trained());
        // Three epochs of 64 transitions in batches of the dynamics' size.
        let batches = 64usize.div_ceil(preset.dynamics.batch_size);
        assert_eq!(report.reward_steps, 3 * batches);
        assert!(report.reward_loss.is_some_and(f32::is_finite), "{report:?}");
        // A task with a formula has no reward model and reports none.
        let small = small_preset();
        let (plain_models, plain_report) = retrain(
            &untrained(&small),
            &plain,
            &small,
            1,
            0,
            &TrainLimits::unbounded(),
        )
        .unwrap();
        assert!(plain_models.reward.is_none());
        assert_eq!(
            (plain_report.reward_steps, plain_report.reward_loss),
            (0, None)
        );
        // A retraining whose budget ran out before the reward model took a step leaves it
        // untrained: then the models are not trained, and the run keeps exploring instead of
        // planning with a reward model of random weights.
        let mut cut = models.clone();
        cut.reward = fresh.reward.clone();
        assert!(cut.version > 0 && !cut.is_trained());
    }

    /// Data at f32's limits (what a planner refuses at validation, here put straight into a
    /// buffer) makes the targets overflow: the retraining is refused, naming what diverged,
    /// and no model comes out to be served or checkpointed.
    #[test]
    fn extreme_data_yields_no_models() {
        let preset = small_preset();
        for scale in [3.4e38, f32::MAX] {
            let err = retrain(
                &untrained(&preset),
                &data(64, scale),
                &preset,
                1,
                0,
                &TrainLimits::unbounded(),
            )
            .unwrap_err();
            assert!(matches!(err, TrainError::NonFinite { .. }), "{err}");
            assert!(err.to_string().contains("not finite"), "{err}");
        }
    }

    /// The largest values a planner accepts by default (10⁴) train finite models.
    #[test]
    fn large_but_allowed_data_trains_finite_models() {
        let preset = small_preset();
        let bound = Builtin::Cartpole.task().magnitudes.observation;
        let (models, _) = retrain(
            &untrained(&preset),
            &data(64, bound),
            &preset,
            1,
            0,
            &TrainLimits::unbounded(),
        )
        .unwrap();
        assert!(models.first_non_finite().is_none());
    }

    #[test]
    fn the_step_cap_bounds_each_model_and_cancel_stops_training() {
        let mut preset = small_preset();
        preset.max_gradient_steps = Some(5);
        preset.dynamics.epochs = 1000;
        preset.energy.epochs = 1000;
        let (_, report) = retrain(
            &untrained(&preset),
            &data(256, 1.0),
            &preset,
            1,
            0,
            &TrainLimits::unbounded(),
        )
        .unwrap();
        assert_eq!((report.dynamics_steps, report.energy_steps), (5, 5));
        assert_eq!(report.cut_short, Some(Stop::StepCap));

        let limits = TrainLimits::unbounded();
        limits.cancel.store(true, Ordering::SeqCst);
        let err = retrain(&untrained(&preset), &data(256, 1.0), &preset, 1, 0, &limits);
        assert_eq!(err.unwrap_err(), TrainError::Cancelled);
    }

    #[test]
    fn the_time_budget_cuts_training_short_and_keeps_what_was_trained() {
        let mut preset = small_preset();
        preset.dynamics.epochs = 1_000_000;
        preset.energy.epochs = 1_000_000;
        let limits = TrainLimits {
            max_seconds: 1.0,
            ..TrainLimits::unbounded()
        };
        let (models, report) =
            retrain(&untrained(&preset), &data(64, 1.0), &preset, 1, 0, &limits).unwrap();
        assert_eq!(report.cut_short, Some(Stop::Deadline));
        assert!(report.dynamics_steps > 0 && models.is_trained());
    }
}
