//! The paper's Figure 5: imagination against reality.
//!
//! A run learns the task from scratch in-process for a few episodes (the same protocol as the
//! daemon: random exploration, then MPC, retraining after every episode, with the planner
//! library's [`MpcPlanner`] and [`retrain`] and the simulator's [`Env`]). From the state MPC
//! reaches after `mpc_steps` steps of the next episode, one plan is optimised from the initial
//! (uninformed) CEM distribution with each regulariser — none, DAE, DEEN — on the *same*
//! dynamics model and data, so the regulariser is the only difference. The figure plots, per
//! step of each plan, the reward the model imagines against the reward the simulator gives when
//! the plan is executed open-loop from the same state. The paper's point: without regularisation
//! the optimiser finds plans whose imagined reward the real system does not deliver.

use crate::plot::{FAMILY, Figure, XAxis, chart, padded_range, plot_err};
use crate::scale::Scale;
use anyhow::{Context, Result};
use planner_service::config::Preset;
use planner_service::data::Transitions;
use planner_service::energy::{Regularizer, RegularizerKind};
use planner_service::models::Models;
use planner_service::plan::MpcPlanner;
use planner_service::trainer::{TrainLimits, retrain};
use plotters::coord::Shift;
use plotters::prelude::*;
use proto::{InferencePrecision, TaskId};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use sim_bridge::Env;
use std::fmt::Write as _;

/// Settings of the imagination-vs-reality experiment.
#[derive(Clone, Debug)]
pub struct ImaginationConfig {
    pub task: TaskId,
    /// Sizes of the models and of the MPC that collects the data.
    pub scale: Scale,
    /// CEM sizes of the three compared plans. Exploiting a model takes a strong optimiser, so
    /// the paper's population and iterations can be used here even when training was small.
    pub plan_scale: Scale,
    /// The method whose MPC collects the training data (its dynamics model is the one used).
    pub method: String,
    /// Episodes of training before the comparison (the paper: 5).
    pub train_episodes: u32,
    /// MPC steps into the next episode before the plans are optimised (the paper: 50).
    pub mpc_steps: u32,
    /// Number format of the models' inference, in data collection and in the compared plans.
    pub inference_precision: InferencePrecision,
    pub seed: u64,
}

/// One regulariser's plan: what the model imagined and what the simulator delivered.
#[derive(Clone, Debug)]
pub struct PlanTrace {
    pub regularizer: RegularizerKind,
    /// The energy weight the plan was optimised with.
    pub alpha: f32,
    pub imagined: Vec<f32>,
    /// Real rewards, shorter than `imagined` if the episode ended inside the plan.
    pub real: Vec<f32>,
    pub energies: Vec<f32>,
}

/// Everything the figure shows.
#[derive(Clone, Debug)]
pub struct ImaginationResult {
    pub task: TaskId,
    pub train_episodes: u32,
    pub mpc_steps: u32,
    /// Returns of the training episodes.
    pub training_returns: Vec<f32>,
    pub traces: Vec<PlanTrace>,
}

/// Runs one episode with random actions (`planner` = None) or MPC; appends its transitions.
fn episode(
    env: &mut Env,
    seed: u64,
    planner: Option<(&mut MpcPlanner, &Models)>,
    data: &mut Transitions,
    rng: &mut StdRng,
) -> Result<f32> {
    let spec = env.spec();
    let mut obs = env.reset(seed).to_vec();
    let mut planner = planner;
    if let Some((p, _)) = planner.as_mut() {
        p.reset();
    }
    let mut action = vec![0.0; spec.act_dim];
    let mut total = 0.0;
    loop {
        match planner.as_mut() {
            Some((p, m)) => {
                action.copy_from_slice(p.plan(&obs, &m.dynamics, &m.regularizer, None).action);
            }
            None => {
                for (a, (lo, hi)) in action
                    .iter_mut()
                    .zip(spec.action_low.iter().zip(spec.action_high))
                {
                    *a = rng.random_range(*lo..*hi);
                }
            }
        }
        let out = env.step(&action)?;
        data.push(&obs, &action, &out.obs);
        total += out.reward;
        let done = out.done();
        obs = out.obs;
        if done {
            return Ok(total);
        }
    }
}

/// Trains, reaches a state by MPC and compares the three regularisers' plans there.
/// `on_episode(episode, return)` reports the training as it goes.
pub fn run(
    config: &ImaginationConfig,
    mut on_episode: impl FnMut(u32, f32),
) -> Result<ImaginationResult> {
    let task = config.task;
    let spec = task.spec();
    let mut preset = Preset::new(task, Some(&config.method))?;
    preset.apply(&config.scale.overrides(task))?;
    preset.inference_precision = config.inference_precision;
    let mut env = Env::new(task)?;
    let mut rng = StdRng::seed_from_u64(config.seed);
    let mut models = Models::untrained(spec, &preset, config.seed);
    let mut data = Transitions::new(spec.obs_dim, spec.act_dim);
    let mut planner = MpcPlanner::new(
        spec,
        preset.cem.clone(),
        preset.energy_weight,
        preset.sample_dynamics,
        config.seed,
    )?;
    let mut training_returns = Vec::new();
    for e in 0..config.train_episodes {
        let explore = e < preset.exploration_episodes || !models.is_trained();
        let seed = config.seed.wrapping_add(u64::from(e));
        let mpc = (!explore).then_some((&mut planner, &models));
        let ret = episode(&mut env, seed, mpc, &mut data, &mut rng)?;
        training_returns.push(ret);
        on_episode(e, ret);
        models = retrain(
            &models,
            &data,
            &preset,
            e + 1,
            config.seed,
            &TrainLimits::unbounded(),
        )?
        .0;
    }

    // The state: `mpc_steps` steps of MPC into the next episode.
    let start_seed = config.seed.wrapping_add(u64::from(config.train_episodes));
    let mut prefix = Vec::new();
    let mut obs = env.reset(start_seed).to_vec();
    planner.reset();
    for _ in 0..config.mpc_steps {
        let action = planner
            .plan(&obs, &models.dynamics, &models.regularizer, None)
            .action
            .to_vec();
        let out = env.step(&action)?;
        prefix.push(action);
        let done = out.done();
        obs = out.obs;
        if done {
            anyhow::bail!(
                "the episode ended within the first {} MPC steps: ask for fewer",
                config.mpc_steps
            );
        }
    }

    let (_, energy_epochs) = preset.epochs(config.train_episodes);
    let mut plan_preset = Preset::new(task, Some(&config.method))?;
    plan_preset.apply(&config.plan_scale.overrides(task))?;
    let mut traces = Vec::new();
    for kind in [
        RegularizerKind::None,
        RegularizerKind::Dae,
        RegularizerKind::Deen,
    ] {
        let regularizer = if kind == models.regularizer.kind() {
            models.regularizer.clone()
        } else {
            let mut r =
                Regularizer::new(kind, &preset.energy, spec.obs_dim, spec.act_dim, &mut rng);
            r.fit(&data, energy_epochs, &mut rng);
            r
        };
        let alpha = if kind == RegularizerKind::None {
            0.0
        } else {
            plan_preset.energy_weight
        };
        let mut fresh = MpcPlanner::new(
            spec,
            plan_preset.cem.clone(),
            alpha,
            false,
            config.seed.wrapping_add(1000),
        )?;
        let plan = fresh.imagine_plan(&obs, &models.dynamics, &regularizer);
        // Reality: the same state (replaying the same actions in a deterministic simulator),
        // then the plan open-loop.
        env.reset(start_seed);
        for a in &prefix {
            env.step(a)?;
        }
        let mut real = Vec::new();
        for a in plan.actions.chunks_exact(spec.act_dim) {
            match env.step(a) {
                Ok(out) => {
                    real.push(out.reward);
                    if out.done() {
                        break;
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, "the simulator stopped executing the plan");
                    break;
                }
            }
        }
        traces.push(PlanTrace {
            regularizer: kind,
            alpha,
            imagined: plan.rewards,
            real,
            energies: plan.energies,
        });
    }
    Ok(ImaginationResult {
        task,
        train_episodes: config.train_episodes,
        mpc_steps: config.mpc_steps,
        training_returns,
        traces,
    })
}

impl ImaginationResult {
    /// One row per (regulariser, plan step).
    pub fn to_csv(&self) -> String {
        let mut out =
            String::from("regularizer,alpha,step,imagined_reward,real_reward,imagined_energy\n");
        for t in &self.traces {
            for (i, imagined) in t.imagined.iter().enumerate() {
                let real = t.real.get(i).map(|r| r.to_string()).unwrap_or_default();
                let _ = writeln!(
                    out,
                    "{},{},{i},{imagined},{real},{}",
                    t.regularizer.name(),
                    t.alpha,
                    t.energies[i]
                );
            }
        }
        out
    }

    /// `(regulariser, Σ imagined, Σ real)` over the steps that were executed.
    pub fn totals(&self) -> Vec<(RegularizerKind, f32, f32)> {
        self.traces
            .iter()
            .map(|t| {
                let n = t.real.len();
                (
                    t.regularizer,
                    t.imagined[..n].iter().sum(),
                    t.real.iter().sum(),
                )
            })
            .collect()
    }
}

impl Figure for ImaginationResult {
    fn size(&self) -> (u32, u32) {
        (1200, 420)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, text: bool) -> Result<()> {
        let all = self
            .traces
            .iter()
            .flat_map(|t| t.imagined.iter().chain(&t.real))
            .map(|&v| f64::from(v));
        let yr = padded_range(all);
        let steps = self
            .traces
            .iter()
            .map(|t| t.imagined.len())
            .max()
            .unwrap_or(1);
        let xr = (0.0, (steps.max(2) - 1) as f64);
        let areas = root.split_evenly((1, self.traces.len().max(1)));
        let totals = self.totals();
        let imagined_style = RGBColor(200, 30, 30).stroke_width(2);
        let real_style = BLACK.stroke_width(2);
        for ((area, t), (_, imagined, real)) in areas.iter().zip(&self.traces).zip(totals) {
            let title = format!(
                "{}: imagined {imagined:.1}, real {real:.1}",
                match t.regularizer {
                    RegularizerKind::None => "no regulariser".to_string(),
                    k => format!("{} (α = {})", k.name().to_uppercase(), t.alpha),
                }
            );
            let mut c = chart(
                area,
                &title,
                (xr, XAxis::Steps),
                yr,
                ("plan step", "reward"),
                text,
            )?;
            let line = |v: &[f32]| -> Vec<(f64, f64)> {
                v.iter()
                    .enumerate()
                    .map(|(i, &r)| (i as f64, f64::from(r)))
                    .collect()
            };
            let s = c
                .draw_series(LineSeries::new(line(&t.imagined), imagined_style))
                .map_err(plot_err)?;
            if text {
                s.label("imagination")
                    .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], imagined_style));
            }
            let s = c
                .draw_series(LineSeries::new(line(&t.real), real_style))
                .map_err(plot_err)?;
            if text {
                s.label("reality")
                    .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], real_style));
                c.configure_series_labels()
                    .position(SeriesLabelPosition::LowerLeft)
                    .background_style(WHITE.mix(0.85))
                    .border_style(BLACK.mix(0.3))
                    .label_font((FAMILY, 12))
                    .draw()
                    .map_err(plot_err)?;
            }
        }
        Ok(())
    }
}

/// Checks that a task can be simulated before training for minutes.
pub fn check_task(task: TaskId) -> Result<()> {
    Env::new(task)
        .map(|_| ())
        .with_context(|| format!("{task} has no simulator"))
}
