//! Planners compared on a fixed model: `ebmpc-experiment replan`.
//!
//! A learning curve mixes two things: how well a planner plans and what data its plans
//! collected for the next model. To compare optimisers (the paper's CEM against iCEM) on the
//! first alone, this loads one stored run's newest checkpoint — the run directory a daemon
//! wrote, with its `run.json` — and drives the simulator with MPC over those frozen models from
//! a seeded start state: the real return the planner earns, and the wall time of every planning
//! call. Same run, same seed and same models for every optimiser, so the optimiser is the only
//! difference.
//!
//! The run's spec fixes the models (their shapes must match the checkpoint; see
//! [`crate::stored_run`]); the overrides given here change how it plans (optimiser,
//! population, iterations, iCEM parameters, …) and are applied after the run's own, with the
//! same checks as an attaching agent's.

use crate::stored_run::{self, StoredRun};
use anyhow::{Result, bail};
use planner_service::plan::MpcPlanner;
use proto::{Builtin, Optimizer, PlannerOverrides};
use sim_bridge::Env;
use std::fmt;
use std::path::PathBuf;
use std::time::Instant;

/// What to replan.
#[derive(Clone, Debug)]
pub struct ReplanConfig {
    /// A run's directory: `run.json` and its `models-*.safetensors` checkpoints. The newest
    /// checkpoint that decodes is used; a damaged one is moved aside (as the daemon does), so
    /// point this at a copy of a run you want to keep untouched.
    pub run_dir: PathBuf,
    /// Planning settings on top of the run's own.
    pub overrides: PlannerOverrides,
    /// Simulator steps (at most the task's episode length).
    pub steps: u32,
    /// Seed of the start state and of the planner.
    pub seed: u64,
}

/// The outcome of one replanned episode.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplanReport {
    pub task: Builtin,
    /// The models' version (retrainings behind the checkpoint).
    pub models_version: u64,
    pub optimizer: Optimizer,
    /// Weight α of the regulariser's penalty the plans used.
    pub energy_weight: f32,
    pub horizon: usize,
    pub population: usize,
    pub elites: usize,
    pub iterations: usize,
    /// iCEM's colored-noise exponent (reported for iCEM only).
    pub noise_beta: Option<f32>,
    pub steps: u32,
    /// Sum of the simulator's rewards.
    pub real_return: f64,
    /// Mean candidate sequences scored per planning call.
    pub candidates_per_plan: f64,
    /// Wall time of each planning call, in milliseconds, in order.
    pub plan_ms: Vec<f64>,
}

impl ReplanReport {
    /// Fastest planning call.
    pub fn best_ms(&self) -> f64 {
        self.plan_ms.iter().copied().fold(f64::INFINITY, f64::min)
    }

    /// Median planning call (NaN when none was made).
    pub fn median_ms(&self) -> f64 {
        crate::results::median(self.plan_ms.clone()).unwrap_or(f64::NAN)
    }
}

impl fmt::Display for ReplanReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let beta = self
            .noise_beta
            .map(|b| format!(", β {b}"))
            .unwrap_or_default();
        write!(
            f,
            "{} models v{}: {} (α {}, horizon {}, population {}, elites {}, {} iterations{beta}): \
             real return {:.1} over {} steps; {:.0} candidates per plan; \
             ms per plan best {:.1}, median {:.1}",
            self.task,
            self.models_version,
            self.optimizer,
            self.energy_weight,
            self.horizon,
            self.population,
            self.elites,
            self.iterations,
            self.real_return,
            self.steps,
            self.candidates_per_plan,
            self.best_ms(),
            self.median_ms()
        )
    }
}

/// Loads the run's models and runs one MPC episode of `config.steps` steps with them.
pub fn run(config: &ReplanConfig) -> Result<ReplanReport> {
    let StoredRun {
        task,
        mut preset,
        mut models,
        ..
    } = stored_run::load(&config.run_dir)?;
    preset.apply(&config.overrides)?;
    preset.cem.validate()?;
    models.set_inference_precision(preset.inference_precision);
    models.pack_for_inference();

    let mut env = Env::new(task)?;
    env.cap_episode_length(Some(config.steps));
    let mut obs = env.reset(config.seed).to_vec();
    let mut planner = MpcPlanner::new(
        task.task(),
        preset.cem.clone(),
        preset.energy_weight,
        preset.sample_dynamics,
        config.seed,
    )?;
    let (mut real_return, mut steps, mut candidates) = (0.0f64, 0u32, 0usize);
    let mut plan_ms = Vec::with_capacity(config.steps as usize);
    loop {
        let started = Instant::now();
        let outcome = planner.plan(
            &obs,
            &models.dynamics,
            &models.regularizer,
            models.learned(),
            None,
        );
        plan_ms.push(started.elapsed().as_secs_f64() * 1e3);
        candidates += preset.cem.candidates_scored(outcome.iterations as usize);
        let step = env.step(outcome.action)?;
        real_return += f64::from(step.reward);
        steps += 1;
        let done = step.done();
        obs = step.obs;
        if done {
            break;
        }
    }
    if steps == 0 {
        bail!("the episode took no step");
    }
    Ok(ReplanReport {
        task,
        models_version: models.version,
        optimizer: preset.cem.optimizer,
        energy_weight: preset.energy_weight,
        horizon: preset.cem.horizon,
        population: preset.cem.population,
        elites: preset.cem.elites,
        iterations: preset.cem.iterations,
        noise_beta: (preset.cem.optimizer == Optimizer::Icem).then_some(preset.cem.icem.noise_beta),
        steps,
        real_return,
        candidates_per_plan: candidates as f64 / f64::from(steps),
        plan_ms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stored_run::store_tiny_cartpole_run;
    use planner_service::config::Preset;
    use std::path::Path;

    fn replan(dir: &Path, overrides: PlannerOverrides) -> Result<ReplanReport> {
        run(&ReplanConfig {
            run_dir: dir.to_path_buf(),
            overrides,
            steps: 12,
            seed: 3,
        })
    }

    #[test]
    fn replans_a_stored_run_with_each_optimiser_and_the_same_seed_repeats() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("cartpole-run");
        store_tiny_cartpole_run(&dir);
        let cem = replan(&dir, PlannerOverrides::default()).unwrap();
        assert_eq!((cem.task, cem.models_version), (Builtin::Cartpole, 1));
        assert_eq!(
            (cem.optimizer, cem.population, cem.iterations),
            (Optimizer::Cem, 20, 2)
        );
        assert_eq!((cem.steps, cem.plan_ms.len()), (12, 12));
        assert!(cem.real_return.is_finite(), "{cem:?}");
        assert!(cem.candidates_per_plan > 0.0 && cem.candidates_per_plan <= 40.0);
        assert!(cem.best_ms() <= cem.median_ms(), "{cem:?}");
        assert_eq!(cem.noise_beta, None);
        let again = replan(&dir, PlannerOverrides::default()).unwrap();
        assert_eq!(again.real_return, cem.real_return);

        let icem = replan(
            &dir,
            PlannerOverrides {
                optimizer: Some(Optimizer::Icem),
                population: Some(30),
                icem_noise_beta: Some(0.5),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(
            (icem.optimizer, icem.noise_beta),
            (Optimizer::Icem, Some(0.5))
        );
        // 30 candidates, then 24 (decay 1.25), never more.
        assert!(icem.candidates_per_plan <= 54.0, "{icem:?}");
        assert_eq!(icem.steps, 12);

        // Without the penalty on the same models: the report says which α planned.
        let paper_alpha = Preset::new(Builtin::Cartpole.task(), Some("cem+deen"))
            .unwrap()
            .energy_weight;
        assert!(paper_alpha > 0.0);
        assert_eq!(cem.energy_weight, paper_alpha);
        let unpenalised = replan(
            &dir,
            PlannerOverrides {
                energy_weight: Some(0.0),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(unpenalised.energy_weight, 0.0);
        assert!(unpenalised.to_string().contains("(α 0,"), "{unpenalised}");
    }

    #[test]
    fn refuses_a_directory_without_a_run_and_overrides_that_do_not_fit() {
        let tmp = tempfile::tempdir().unwrap();
        let err = replan(tmp.path(), PlannerOverrides::default()).unwrap_err();
        assert!(err.to_string().contains("run.json"), "{err}");
        let dir = tmp.path().join("run");
        store_tiny_cartpole_run(&dir);
        for bad in [
            PlannerOverrides {
                icem_noise_beta: Some(0.5),
                ..Default::default()
            },
            PlannerOverrides {
                elites: Some(1000),
                ..Default::default()
            },
            PlannerOverrides {
                optimizer: Some(Optimizer::Icem),
                icem_noise_beta: Some(f32::NAN),
                ..Default::default()
            },
        ] {
            assert!(replan(&dir, bad.clone()).is_err(), "{bad:?}");
        }
    }
}
