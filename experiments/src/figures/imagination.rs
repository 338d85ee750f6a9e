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
//!
//! One state proves little, so the comparison is repeated from `states` start states (the
//! state `mpc_steps` MPC steps into each of `states` further episodes, reset from the seeds
//! after the training ones) with the same models; [`ImaginationResult::states`] holds each
//! state's imagined and real returns, and [`summary`] gives, over several seeds' results, the
//! mean gap and mean real return per regulariser with bootstrap confidence intervals. The
//! figure draws the first state.

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
use proto::{Builtin, InferencePrecision};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use sim_bridge::Env;
use std::fmt::Write as _;

/// Settings of the imagination-vs-reality experiment.
#[derive(Clone, Debug)]
pub struct ImaginationConfig {
    pub task: Builtin,
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
    /// Start states compared (at least 1; the paper shows 1).
    pub states: u32,
}

/// One regulariser's plan from one start state, summed over the steps that were executed.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StateRow {
    pub seed: u64,
    pub state: u32,
    pub regularizer: String,
    pub alpha: f32,
    pub steps: usize,
    pub imagined_return: f32,
    pub real_return: f32,
    /// `imagined_return − real_return`: how over-optimistic the plan was.
    pub gap: f32,
}

#[cfg(test)]
impl StateRow {
    /// A row for tests: α 0 for `none` and 0.05 otherwise, 30 steps, the gap from the returns.
    pub(crate) fn for_test(
        seed: u64,
        state: u32,
        regularizer: &str,
        imagined: f32,
        real: f32,
    ) -> Self {
        Self {
            seed,
            state,
            regularizer: regularizer.to_string(),
            alpha: if regularizer == "none" { 0.0 } else { 0.05 },
            steps: 30,
            imagined_return: imagined,
            real_return: real,
            gap: imagined - real,
        }
    }
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
    pub task: Builtin,
    pub train_episodes: u32,
    pub mpc_steps: u32,
    /// Returns of the training episodes.
    pub training_returns: Vec<f32>,
    /// The plans from the first start state (the figure).
    pub traces: Vec<PlanTrace>,
    /// Every start state's plans, summed.
    pub states: Vec<StateRow>,
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
                action.copy_from_slice(
                    p.plan(&obs, &m.dynamics, &m.regularizer, m.learned(), None)
                        .action,
                );
            }
            None => {
                for (a, (lo, hi)) in action
                    .iter_mut()
                    .zip(spec.action_low.iter().zip(&spec.action_high))
                {
                    *a = rng.random_range(*lo..*hi);
                }
            }
        }
        let out = env.step(&action)?;
        data.push(&obs, &action, out.reward, &out.obs);
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
    let spec = task.task();
    let mut preset = Preset::new(task.task(), Some(&config.method))?;
    preset.apply(&config.scale.overrides(task, &config.method, None)?)?;
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

    let (_, energy_epochs) = preset.epochs(config.train_episodes, data.len());
    let mut plan_preset = Preset::new(task.task(), Some(&config.method))?;
    plan_preset.apply(&config.plan_scale.overrides(task, &config.method, None)?)?;
    // The three regularisers, trained once on the same data, compared from every state.
    let mut regularizers = Vec::new();
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
        regularizers.push((kind, regularizer, alpha));
    }

    let mut first_traces = None;
    let mut states = Vec::new();
    for state in 0..config.states.max(1) {
        // The state: `mpc_steps` steps of MPC into a further episode.
        let start_seed = config
            .seed
            .wrapping_add(u64::from(config.train_episodes) + u64::from(state));
        let mut prefix = Vec::new();
        let mut obs = env.reset(start_seed).to_vec();
        planner.reset();
        let mut ended = false;
        for _ in 0..config.mpc_steps {
            let action = planner
                .plan(
                    &obs,
                    &models.dynamics,
                    &models.regularizer,
                    models.learned(),
                    None,
                )
                .action
                .to_vec();
            let out = env.step(&action)?;
            prefix.push(action);
            ended = out.done();
            obs = out.obs;
            if ended {
                break;
            }
        }
        if ended {
            tracing::warn!(
                state,
                "the episode ended within the first {} MPC steps: state left out",
                config.mpc_steps
            );
            continue;
        }
        let mut traces = Vec::new();
        for (kind, regularizer, alpha) in &regularizers {
            let mut fresh = MpcPlanner::new(
                spec,
                plan_preset.cem.clone(),
                *alpha,
                false,
                config.seed.wrapping_add(1000),
            )?;
            let plan = fresh.imagine_plan(&obs, &models.dynamics, regularizer, models.learned());
            // Reality: the same state (replaying the same actions in a deterministic
            // simulator), then the plan open-loop.
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
            let steps = real.len();
            let imagined_return: f32 = plan.rewards[..steps].iter().sum();
            let real_return: f32 = real.iter().sum();
            states.push(StateRow {
                seed: config.seed,
                state,
                regularizer: kind.name().to_string(),
                alpha: *alpha,
                steps,
                imagined_return,
                real_return,
                gap: imagined_return - real_return,
            });
            traces.push(PlanTrace {
                regularizer: *kind,
                alpha: *alpha,
                imagined: plan.rewards,
                real,
                energies: plan.energies,
            });
        }
        first_traces.get_or_insert(traces);
    }
    let Some(traces) = first_traces else {
        anyhow::bail!(
            "every episode ended within the first {} MPC steps: ask for fewer",
            config.mpc_steps
        );
    };
    Ok(ImaginationResult {
        task,
        train_episodes: config.train_episodes,
        mpc_steps: config.mpc_steps,
        training_returns,
        traces,
        states,
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

/// The mean of `values` over seeds and states, with a two-sided bootstrap confidence interval
/// at `level` (e.g. 0.95): `groups` holds one seed's values (its states) each, and every
/// resample draws seeds with replacement and then states with replacement within each drawn
/// seed (a two-level bootstrap: states of one seed share its models, so they are not
/// independent draws). Percentile interval over `resamples` resamples, seeded.
pub fn bootstrap_mean(groups: &[Vec<f64>], resamples: usize, level: f64, seed: u64) -> Interval {
    let groups: Vec<&Vec<f64>> = groups.iter().filter(|g| !g.is_empty()).collect();
    let all: Vec<f64> = groups.iter().flat_map(|g| g.iter().copied()).collect();
    let mean = all.iter().sum::<f64>() / all.len().max(1) as f64;
    if groups.is_empty() {
        return Interval {
            mean: f64::NAN,
            low: f64::NAN,
            high: f64::NAN,
        };
    }
    let mut rng = StdRng::seed_from_u64(seed);
    let mut means: Vec<f64> = (0..resamples.max(1))
        .map(|_| {
            let (mut sum, mut n) = (0.0, 0usize);
            for _ in 0..groups.len() {
                let g = groups[rng.random_range(0..groups.len())];
                for _ in 0..g.len() {
                    sum += g[rng.random_range(0..g.len())];
                    n += 1;
                }
            }
            sum / n as f64
        })
        .collect();
    means.sort_by(f64::total_cmp);
    let at = |q: f64| means[((q * (means.len() - 1) as f64).round() as usize).min(means.len() - 1)];
    let tail = (1.0 - level) / 2.0;
    Interval {
        mean,
        low: at(tail),
        high: at(1.0 - tail),
    }
}

/// A mean and its confidence interval.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Interval {
    pub mean: f64,
    pub low: f64,
    pub high: f64,
}

/// Per regulariser over every seed's states: the gap and the real return, each with a 95 %
/// two-level bootstrap interval (10,000 resamples).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SummaryRow {
    pub regularizer: String,
    pub alpha: f32,
    pub seeds: usize,
    pub states: usize,
    pub mean_gap: f64,
    pub gap_ci_low: f64,
    pub gap_ci_high: f64,
    pub mean_real_return: f64,
    pub real_ci_low: f64,
    pub real_ci_high: f64,
}

/// [`SummaryRow`]s of `rows` (any number of seeds and states), one per regulariser in the order
/// they first appear.
pub fn summary(rows: &[StateRow]) -> Vec<SummaryRow> {
    let mut kinds: Vec<(&str, f32)> = Vec::new();
    for r in rows {
        if !kinds.iter().any(|(k, _)| *k == r.regularizer) {
            kinds.push((&r.regularizer, r.alpha));
        }
    }
    kinds
        .into_iter()
        .map(|(kind, alpha)| {
            let mine: Vec<&StateRow> = rows.iter().filter(|r| r.regularizer == kind).collect();
            let mut seeds: Vec<u64> = mine.iter().map(|r| r.seed).collect();
            seeds.sort_unstable();
            seeds.dedup();
            let groups = |f: fn(&StateRow) -> f32| -> Vec<Vec<f64>> {
                seeds
                    .iter()
                    .map(|s| {
                        mine.iter()
                            .filter(|r| r.seed == *s)
                            .map(|r| f64::from(f(r)))
                            .collect()
                    })
                    .collect()
            };
            let gap = bootstrap_mean(&groups(|r| r.gap), 10_000, 0.95, 1);
            let real = bootstrap_mean(&groups(|r| r.real_return), 10_000, 0.95, 2);
            SummaryRow {
                regularizer: kind.to_string(),
                alpha,
                seeds: seeds.len(),
                states: mine.len(),
                mean_gap: gap.mean,
                gap_ci_low: gap.low,
                gap_ci_high: gap.high,
                mean_real_return: real.mean,
                real_ci_low: real.low,
                real_ci_high: real.high,
            }
        })
        .collect()
}

/// Writes serialisable rows as CSV (header from the field names).
pub fn write_csv<T: serde::Serialize>(path: &std::path::Path, rows: &[T]) -> Result<()> {
    let mut w =
        csv::Writer::from_path(path).with_context(|| format!("creating {}", path.display()))?;
    for r in rows {
        w.serialize(r)?;
    }
    w.flush()?;
    Ok(())
}

/// Reads rows that [`write_csv`] wrote.
pub fn read_csv<T: serde::de::DeserializeOwned>(path: &std::path::Path) -> Result<Vec<T>> {
    let mut r =
        csv::Reader::from_path(path).with_context(|| format!("reading {}", path.display()))?;
    Ok(r.deserialize().collect::<Result<_, _>>()?)
}

/// Reads the rows [`write_csv`] wrote of [`StateRow`]s.
pub fn read_state_rows(path: &std::path::Path) -> Result<Vec<StateRow>> {
    read_csv(path)
}

/// One statistic of a summary row: `(mean, interval low, interval high)`.
type Statistic = fn(&SummaryRow) -> (f64, f64, f64);

/// The summary as a figure: per regulariser, the mean gap and the mean real return with their
/// intervals (points with error bars, one panel each).
pub struct SummaryFigure<'a>(pub &'a [SummaryRow]);

impl Figure for SummaryFigure<'_> {
    fn size(&self) -> (u32, u32) {
        (900, 380)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>, text: bool) -> Result<()> {
        let rows = self.0;
        let areas = root.split_evenly((1, 2));
        let panels: [(&str, Statistic); 2] = [
            ("imagined − real return", |r| {
                (r.mean_gap, r.gap_ci_low, r.gap_ci_high)
            }),
            ("real return", |r| {
                (r.mean_real_return, r.real_ci_low, r.real_ci_high)
            }),
        ];
        for (area, (title, value)) in areas.iter().zip(panels) {
            let yr = padded_range(rows.iter().flat_map(|r| {
                let (_, lo, hi) = value(r);
                [lo, hi, 0.0]
            }));
            let xr = (-0.5, rows.len() as f64 - 0.5);
            let caption = format!(
                "{title} ({})",
                rows.iter()
                    .map(|r| r.regularizer.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            let mut c = chart(
                area,
                &caption,
                (xr, XAxis::Steps),
                yr,
                ("regulariser", "mean, 95 % CI"),
                text,
            )?;
            for (i, r) in rows.iter().enumerate() {
                let (mean, lo, hi) = value(r);
                let style = crate::plot::color(i).stroke_width(2);
                let x = i as f64;
                c.draw_series(std::iter::once(PathElement::new([(x, lo), (x, hi)], style)))
                    .map_err(plot_err)?;
                c.draw_series(std::iter::once(Circle::new((x, mean), 5, style.filled())))
                    .map_err(plot_err)?;
            }
        }
        Ok(())
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
pub fn check_task(task: Builtin) -> Result<()> {
    Env::new(task)
        .map(|_| ())
        .with_context(|| format!("{task} has no simulator"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn normal_groups(seeds: usize, states: usize, mean: f64, rng: &mut StdRng) -> Vec<Vec<f64>> {
        (0..seeds)
            .map(|_| {
                (0..states)
                    .map(|_| mean + rng.sample::<f64, _>(rand_distr::StandardNormal))
                    .collect()
            })
            .collect()
    }

    #[test]
    fn bootstrap_intervals_cover_the_mean_and_narrow_with_data() {
        let mut rng = StdRng::seed_from_u64(9);
        // Over 200 repeated experiments the 95 % interval covers the true mean about 95 % of
        // the time (a broad band: 85–100 %).
        let covered = (0..200)
            .filter(|&i| {
                let g = normal_groups(3, 20, 2.0, &mut rng);
                let ci = bootstrap_mean(&g, 500, 0.95, i);
                ci.low <= 2.0 && 2.0 <= ci.high
            })
            .count();
        assert!((170..=200).contains(&covered), "{covered}");
        let small = bootstrap_mean(&normal_groups(3, 5, 0.0, &mut rng), 2000, 0.95, 1);
        let large = bootstrap_mean(&normal_groups(3, 200, 0.0, &mut rng), 2000, 0.95, 1);
        assert!(
            large.high - large.low < 0.5 * (small.high - small.low),
            "{small:?} {large:?}"
        );
        // Constant data: a point.
        let flat = bootstrap_mean(&[vec![1.5; 4], vec![1.5; 4]], 100, 0.95, 0);
        assert_eq!((flat.mean, flat.low, flat.high), (1.5, 1.5, 1.5));
    }

    #[test]
    fn summary_per_regulariser_and_csv_round_trip() {
        let row = StateRow::for_test;
        let rows = vec![
            row(0, 0, "none", 10.0, 2.0),
            row(0, 0, "deen", 5.0, 4.0),
            row(1, 0, "none", 12.0, 2.0),
            row(1, 0, "deen", 6.0, 4.0),
        ];
        let s = summary(&rows);
        assert_eq!(s.len(), 2);
        assert_eq!(
            (s[0].regularizer.as_str(), s[0].seeds, s[0].states),
            ("none", 2, 2)
        );
        assert_eq!((s[0].mean_gap, s[1].mean_gap), (9.0, 1.5));
        assert!(s[0].gap_ci_low >= 8.0 && s[0].gap_ci_high <= 10.0, "{s:?}");
        assert_eq!((s[1].mean_real_return, s[1].real_ci_low), (4.0, 4.0));
        let dir = std::env::temp_dir().join(format!("ebmpc-states-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("states.csv");
        write_csv(&path, &rows).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.starts_with(
                "seed,state,regularizer,alpha,steps,imagined_return,real_return,gap\n"
            ),
            "{text}"
        );
        assert_eq!(read_state_rows(&path).unwrap(), rows);
        std::fs::remove_dir_all(&dir).unwrap();
        // The summary figure draws its points.
        let pixels = crate::plot::render_rgb(&SummaryFigure(&s), false).unwrap();
        assert!(pixels.chunks_exact(3).any(|p| p != [255, 255, 255]));
    }
}
