//! How fast a task simulates: control steps per second on one thread.
//!
//! The planner waits on the simulator once per control step, and a whole training run is
//! thousands of episodes of simulated experience, so the step rate says whether the simulator
//! could ever be the bottleneck (it should be orders of magnitude faster than planning).

use crate::env::Env;
use crate::error::SimError;
use proto::Builtin;
use std::time::{Duration, Instant};

/// One measurement of a task's simulation speed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepRate {
    pub task: Builtin,
    /// Control steps taken (whole episodes, each ending by termination or time limit).
    pub steps: u64,
    /// Episodes those steps made up.
    pub episodes: u64,
    /// Wall-clock time they took, resets included.
    pub elapsed: Duration,
    /// Simulated seconds per control step.
    pub control_dt: f64,
}

impl StepRate {
    /// Control steps per wall-clock second.
    pub fn steps_per_second(&self) -> f64 {
        self.steps as f64 / self.elapsed.as_secs_f64()
    }

    /// Simulated seconds per wall-clock second.
    pub fn real_time_factor(&self) -> f64 {
        self.steps_per_second() * self.control_dt
    }
}

/// Runs whole episodes of `task` (seeds 0, 1, …) until at least `min_steps` control steps are
/// done, with a deterministic sweep of actions across the bounds, and times them.
///
/// # Errors
/// The task has no simulator, or its simulation failed (which a benchmark must not hide).
pub fn step_rate(task: Builtin, min_steps: u64) -> Result<StepRate, SimError> {
    let mut env = Env::new(task)?;
    let spec = env.spec();
    let mut action = vec![0.0; spec.act_dim];
    let (mut steps, mut episodes) = (0u64, 0u64);
    let started = Instant::now();
    while steps < min_steps {
        env.reset(episodes);
        episodes += 1;
        loop {
            // Each dimension sweeps its range at its own pace, so the actions are varied
            // without a random number generator in the timed loop.
            for (i, ((a, lo), hi)) in action
                .iter_mut()
                .zip(&spec.action_low)
                .zip(&spec.action_high)
                .enumerate()
            {
                let phase = (steps as f32 * (0.1 + 0.03 * i as f32)).sin();
                *a = lo + (hi - lo) * 0.5 * (phase + 1.0);
            }
            steps += 1;
            if env.step(&action)?.done() {
                break;
            }
        }
    }
    Ok(StepRate {
        task,
        steps,
        episodes,
        elapsed: started.elapsed(),
        control_dt: spec.control_dt,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_whole_episodes_of_the_task() {
        let rate = step_rate(Builtin::Cartpole, 250).unwrap();
        // Cartpole never terminates: two episodes of 200 steps cover 250.
        assert_eq!((rate.episodes, rate.steps), (2, 400));
        assert!(rate.steps_per_second() > 0.0 && rate.steps_per_second().is_finite());
        let factor = rate.real_time_factor() / rate.steps_per_second();
        assert!((factor - 0.04).abs() < 1e-12);
    }
}
