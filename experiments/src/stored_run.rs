//! One stored run's frozen models, loaded as the daemon would load them: the commands that
//! study a run after the fact ([`crate::replan`], [`crate::model_error`]) start here.
//!
//! The run's spec (`run.json`) fixes the task and the models' shapes (its preset and
//! overrides); the newest checkpoint that decodes holds the weights. A damaged checkpoint is
//! moved aside, as the daemon does, so point these commands at a copy of a run you want to keep
//! untouched.

use anyhow::{Context, Result};
use planner_service::config::Preset;
use planner_service::models::Models;
use planner_service::persist::RunDir;
use proto::Builtin;
use std::path::Path;

/// A stored run's task, its preset (the run's overrides applied) and newest models.
pub struct StoredRun {
    pub dir: RunDir,
    pub task: Builtin,
    pub preset: Preset,
    pub models: Models,
}

/// Loads the run stored in `run_dir` (`run.json` and `models-*.safetensors`).
pub fn load(run_dir: &Path) -> Result<StoredRun> {
    let dir = RunDir::at(run_dir);
    let spec = dir
        .read_spec()?
        .with_context(|| format!("{} has no run.json", run_dir.display()))?;
    let task: Builtin = spec
        .task
        .parse()
        .map_err(|e| anyhow::anyhow!("task `{}`: {e}", spec.task))?;
    let mut preset = Preset::new(task.task(), spec.preset.as_deref())?;
    preset.apply(&spec.overrides)?;
    let models = dir
        .load_models(task.task(), &preset)?
        .with_context(|| format!("{} holds no usable checkpoint", run_dir.display()))?;
    Ok(StoredRun {
        dir,
        task,
        preset,
        models,
    })
}

/// A cartpole `cem+deen` run with tiny models and a small search, stored as the daemon stores
/// one (its spec and one checkpoint, version 1, untrained weights): the fixture of the tests of
/// the commands that read stored runs.
#[cfg(test)]
pub(crate) fn store_tiny_cartpole_run(dir: &Path) {
    use proto::{PlannerOverrides, RunSpec};
    let task = Builtin::Cartpole.task();
    let spec = RunSpec {
        task: "cartpole".into(),
        preset: Some("cem+deen".into()),
        overrides: PlannerOverrides {
            dynamics_hidden_layers: Some(1),
            dynamics_hidden_size: Some(8),
            energy_hidden_layers: Some(1),
            energy_hidden_size: Some(8),
            horizon: Some(5),
            population: Some(20),
            elites: Some(4),
            cem_iterations: Some(2),
            ..Default::default()
        },
        mode: Default::default(),
        seed: 0,
        task_spec: None,
    };
    let mut preset = Preset::new(task, spec.preset.as_deref()).unwrap();
    preset.apply(&spec.overrides).unwrap();
    let mut models = Models::untrained(task, &preset, 0);
    models.version = 1;
    std::fs::create_dir_all(dir).unwrap();
    let run = RunDir::at(dir);
    run.write_spec(&spec).unwrap();
    run.save_models(1, &models, task).unwrap();
}
