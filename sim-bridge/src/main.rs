//! `sim-bridge`: runs a MuJoCo task as an ebmpc agent, with actions from a planner over Zenoh.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
use proto::session::Endpoints;
use proto::{Builtin, InferencePrecision, PlannerOverrides, RegularizerChoice, RunSpec, TrainMode};
use sim_bridge::bridge::{self, BridgeConfig};
use sim_bridge::csv::EpisodeCsv;
use sim_bridge::deadline::EpisodeDeadline;
use std::path::PathBuf;
use std::time::{Duration, SystemTime};
use tracing_subscriber::EnvFilter;

/// Runs a simulated task (MuJoCo) as an agent of an ebmpc planner: sends observations and
/// rewards over Zenoh and applies the actions the planner answers with.
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Attach to a run on a planner and run episodes of a task (Ctrl-C stops; the planner
    /// records the open episode as interrupted).
    Run(Box<RunArgs>),
    /// List the tasks of the catalog: dimensions, action bounds, episode length, control rate.
    Tasks,
    /// Measure how fast each simulated task steps (control steps per second, one thread).
    Bench(BenchArgs),
}

#[derive(Args, Debug)]
struct BenchArgs {
    /// Only this task (default: every simulated task).
    #[arg(long)]
    task: Option<Builtin>,
    /// Control steps to time per task, at least (whole episodes are run).
    #[arg(long, default_value_t = 20_000)]
    steps: u64,
}

#[derive(Args, Debug)]
struct RunArgs {
    /// Task to simulate (see `sim-bridge tasks`).
    #[arg(long, env = "EBMPC_TASK")]
    task: Builtin,
    /// Run to attach to: the planner creates it on first attach; other agents may join it.
    #[arg(long, env = "EBMPC_RUN")]
    run: String,
    /// This agent's name within the run (attaching again under the same name resumes it).
    #[arg(long, env = "EBMPC_AGENT")]
    agent: String,
    /// Number of episodes to run.
    #[arg(long, env = "EBMPC_EPISODES")]
    episodes: u32,
    /// Stop after the episode in which this many control steps have been run (whole episodes;
    /// --episodes still bounds the count): budgets in timesteps, like the paper's "4,000
    /// timesteps".
    #[arg(long, env = "EBMPC_TIMESTEPS", value_parser = clap::value_parser!(u64).range(1..))]
    timesteps: Option<u64>,
    /// Start no episode expected to end after this time (seconds since the Unix epoch): stop
    /// between episodes instead, before the simulator resets, so the planner's data hold only
    /// whole episodes. The next episode is expected to take as long as the last one when it
    /// planned, else --planned-episode-seconds. Stopping after a planned episode (sync mode),
    /// the bridge first waits, until the deadline at most, for the planner's retraining on it,
    /// which the planner checkpoints, so a resumed run need not redo it. Experiment sittings
    /// with a budget set it.
    #[arg(long, env = "EBMPC_DEADLINE", value_name = "UNIX_SECONDS")]
    deadline: Option<u64>,
    /// With --deadline: the expected wall time of a planned episode, for the episode after one
    /// that planned nothing (random exploration predicts nothing); without it such an episode
    /// always starts.
    #[arg(long, env = "EBMPC_PLANNED_EPISODE_SECONDS", requires = "deadline")]
    planned_episode_seconds: Option<f64>,
    /// Seed: episode e starts from the state drawn with seed + e; also the run's model seed
    /// unless --planner-seed is given.
    #[arg(long, env = "EBMPC_SEED", default_value_t = 0)]
    seed: u64,
    /// End every episode after at most this many steps, reported to the planner as a time
    /// limit (default: the task's episode length). For quick tests and demos.
    #[arg(long, env = "EBMPC_MAX_STEPS")]
    max_steps: Option<u32>,
    /// Write a PNG frame of every step here, one folder per episode (needs an offscreen OpenGL
    /// context through EGL; without one the bridge says so and runs without frames).
    #[cfg(feature = "render")]
    #[arg(long, value_name = "DIR")]
    render: Option<PathBuf>,
    /// Write one CSV row per episode here (columns: see sim_bridge::csv::HEADER: return, steps,
    /// wall seconds, planned steps, mean planning ms, training seconds).
    #[arg(long)]
    out: Option<PathBuf>,

    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable, or comma-separated).
    #[arg(long, env = "EBMPC_LISTEN", value_delimiter = ',')]
    listen: Vec<String>,
    /// Zenoh endpoint of the planner or a router, e.g. tcp/127.0.0.1:7447 (repeatable, or
    /// comma-separated). Multicast scouting is off: give at least one of --connect / --listen.
    #[arg(long, env = "EBMPC_CONNECT", value_delimiter = ',')]
    connect: Vec<String>,
    /// Zenoh configuration file to start from (JSON5); endpoints above still apply.
    #[arg(long, env = "EBMPC_ZENOH_CONFIG")]
    zenoh_config: Option<PathBuf>,
    /// Key prefix shared with the planner.
    #[arg(long, env = "EBMPC_PREFIX", default_value = proto::keys::DEFAULT_PREFIX)]
    prefix: String,

    /// Seconds to keep asking for a planner to attach to.
    #[arg(long, env = "EBMPC_ATTACH_TIMEOUT", default_value_t = 60.0)]
    attach_timeout: f64,
    /// Seconds to wait for each action.
    #[arg(long, env = "EBMPC_ACTION_TIMEOUT", default_value_t = 60.0)]
    action_timeout: f64,
    /// Seconds to wait for the first action of each later episode, which in sync mode comes
    /// only after the planner has retrained on the episodes so far.
    #[arg(long, env = "EBMPC_TRAIN_TIMEOUT", default_value_t = 3600.0)]
    train_timeout: f64,

    #[command(flatten)]
    spec: SpecArgs,
}

/// The run spec sent when attaching. It creates the run if it is new; a run that exists keeps
/// its own configuration (only the task must match).
#[derive(Args, Debug)]
#[command(next_help_heading = "Run spec (used when the run is created)")]
struct SpecArgs {
    /// Planner preset: cem, cem+dae, cem+deen (the paper's default), pets, pets+deen, adam+dae.
    #[arg(long)]
    preset: Option<String>,
    /// sync: the next episode starts once the models are retrained (the paper's protocol);
    /// async: keep acting with the previous models while training.
    #[arg(long, value_enum, default_value_t = Mode::Sync)]
    mode: Mode,
    /// Seed of the run's models and planner (default: --seed).
    #[arg(long)]
    planner_seed: Option<u64>,
    /// Energy regulariser of the planning objective.
    #[arg(long, value_enum)]
    regularizer: Option<Regularizer>,
    /// Weight alpha of the energy in the planning objective.
    #[arg(long)]
    energy_weight: Option<f32>,
    /// Members of the dynamics ensemble.
    #[arg(long)]
    ensemble_size: Option<u32>,
    /// Trajectory-sampling particles per candidate action sequence.
    #[arg(long)]
    particles: Option<u32>,
    /// Planning horizon in control steps.
    #[arg(long)]
    horizon: Option<u32>,
    /// CEM population size.
    #[arg(long)]
    population: Option<u32>,
    /// CEM elites.
    #[arg(long)]
    elites: Option<u32>,
    /// CEM iterations per action.
    #[arg(long)]
    cem_iterations: Option<u32>,
    /// Episodes of uniformly random actions before planning starts.
    #[arg(long)]
    exploration_episodes: Option<u32>,
    /// Training epochs of the dynamics model after each episode.
    #[arg(long)]
    dynamics_epochs: Option<u32>,
    /// Hidden layers of the dynamics model.
    #[arg(long)]
    dynamics_hidden_layers: Option<u32>,
    /// Width of the dynamics model's hidden layers.
    #[arg(long)]
    dynamics_hidden_size: Option<u32>,
    /// Training epochs of the energy model after each episode.
    #[arg(long)]
    energy_epochs: Option<u32>,
    /// Hidden layers of the energy model.
    #[arg(long)]
    energy_hidden_layers: Option<u32>,
    /// Width of the energy model's hidden layers.
    #[arg(long)]
    energy_hidden_size: Option<u32>,
    /// Standard deviation σ of the energy model's training noise (Table 2's per task by
    /// default), in --energy-noise-units.
    #[arg(long)]
    energy_noise_sigma: Option<f32>,
    /// Units of σ: standardised (each dimension of the transitions scaled to unit variance) or
    /// raw (the transitions' own units, as the paper corrupts its buffer); by default the
    /// task's preset decides (raw for pusher, standardised for the others).
    #[arg(long)]
    energy_noise_units: Option<proto::NoiseUnits>,
    /// Number format of the planner's network inference: auto (the default: the kernel path
    /// measured fastest on the planner's CPU), bf16 or f32.
    #[arg(long)]
    inference_precision: Option<InferencePrecision>,
    /// Planning optimiser: cem (the paper's, the default), icem (Pinneri et al. 2020:
    /// colored noise, kept elites, decaying population: fewer candidates per plan, which
    /// kept CEM's return on cartpole but not on half-cheetah or reacher3d) or adam
    /// (gradient-based, the adam+dae preset's).
    #[arg(long)]
    optimizer: Option<proto::Optimizer>,
    /// iCEM: exponent β of the colored noise (0 = white; the task's default: 2 for cartpole,
    /// reacher3d and pusher, 0.25 for half-cheetah and ant).
    #[arg(long)]
    icem_noise_beta: Option<f32>,
    /// iCEM: fraction of the elites kept for the next iteration and step (the task's default:
    /// 0.3 for cartpole, reacher3d and pusher, 0 for half-cheetah and ant).
    #[arg(long)]
    icem_keep_elites: Option<f32>,
    /// iCEM: population decay factor per iteration (default 1.25).
    #[arg(long)]
    icem_population_decay: Option<f32>,
    /// Milliseconds from each observation to its action; planning stops iterating before it
    /// would cross it. 0 (the default here) turns it off: a simulator waits for its action,
    /// so its plans run every configured iteration, as the paper's did. A controller that
    /// omits it gets the task's control period.
    #[arg(long, default_value_t = 0)]
    deadline_ms: u32,
}

/// Command-line spelling of [`TrainMode`].
#[derive(Clone, Copy, Debug, ValueEnum)]
enum Mode {
    Sync,
    Async,
}

/// Command-line spelling of [`RegularizerChoice`].
#[derive(Clone, Copy, Debug, ValueEnum)]
enum Regularizer {
    None,
    Dae,
    Deen,
}

impl SpecArgs {
    fn into_spec(self, task: Builtin, seed: u64) -> RunSpec {
        RunSpec {
            task: task.name().to_string(),
            preset: self.preset,
            overrides: PlannerOverrides {
                regularizer: self.regularizer.map(|r| match r {
                    Regularizer::None => RegularizerChoice::None,
                    Regularizer::Dae => RegularizerChoice::Dae,
                    Regularizer::Deen => RegularizerChoice::Deen,
                }),
                energy_weight: self.energy_weight,
                ensemble_size: self.ensemble_size,
                particles: self.particles,
                horizon: self.horizon,
                population: self.population,
                elites: self.elites,
                cem_iterations: self.cem_iterations,
                exploration_episodes: self.exploration_episodes,
                dynamics_epochs: self.dynamics_epochs,
                dynamics_hidden_layers: self.dynamics_hidden_layers,
                dynamics_hidden_size: self.dynamics_hidden_size,
                energy_epochs: self.energy_epochs,
                energy_hidden_layers: self.energy_hidden_layers,
                energy_hidden_size: self.energy_hidden_size,
                energy_noise_sigma: self.energy_noise_sigma,
                energy_noise_units: self.energy_noise_units,
                inference_precision: self.inference_precision,
                optimizer: self.optimizer,
                icem_noise_beta: self.icem_noise_beta,
                icem_keep_elites: self.icem_keep_elites,
                icem_population_decay: self.icem_population_decay,
                deadline_ms: Some(self.deadline_ms),
                // The other overrides (batch sizes, learning rates, CEM smoothing, the
                // epoch schedule, the gradient-step cap) have no flag here: the planner's
                // `[overrides]` or a controller's attach message sets them.
                ..PlannerOverrides::default()
            },
            mode: match self.mode {
                Mode::Sync => TrainMode::Sync,
                Mode::Async => TrainMode::Async,
            },
            seed: self.planner_seed.unwrap_or(seed),
            task_spec: None,
        }
    }
}

fn seconds(name: &str, value: f64) -> Result<Duration> {
    Duration::try_from_secs_f64(value)
        .with_context(|| format!("--{name} {value}: not a number of seconds"))
}

/// The episode deadline of `--deadline at` and `--planned-episode-seconds planned`.
fn deadline(at: u64, planned: Option<f64>) -> Result<EpisodeDeadline> {
    let at = SystemTime::UNIX_EPOCH
        .checked_add(Duration::from_secs(at))
        .with_context(|| format!("--deadline {at}: not a time this system can represent"))?;
    let planned_episode = planned
        .map(|s| seconds("planned-episode-seconds", s))
        .transpose()?;
    Ok(EpisodeDeadline {
        at,
        planned_episode,
    })
}

impl RunArgs {
    fn into_config(self) -> Result<(BridgeConfig, Option<PathBuf>)> {
        if self.listen.is_empty() && self.connect.is_empty() && self.zenoh_config.is_none() {
            bail!(
                "no Zenoh endpoints: multicast scouting is off, so give --connect ENDPOINT (the planner's \
                 --listen address or a router), --listen ENDPOINT, or --zenoh-config FILE"
            );
        }
        if self.episodes == 0 {
            bail!("--episodes must be at least 1");
        }
        if self.max_steps == Some(0) {
            bail!("--max-steps must be at least 1");
        }
        let config = BridgeConfig {
            prefix: self.prefix,
            endpoints: Endpoints {
                listen: self.listen,
                connect: self.connect,
            },
            zenoh_config: self.zenoh_config,
            run: self.run,
            agent: self.agent,
            episodes: self.episodes,
            timesteps: self.timesteps,
            deadline: self
                .deadline
                .map(|at| deadline(at, self.planned_episode_seconds))
                .transpose()?,
            seed: self.seed,
            attach_timeout: seconds("attach-timeout", self.attach_timeout)?,
            action_timeout: seconds("action-timeout", self.action_timeout)?,
            train_timeout: seconds("train-timeout", self.train_timeout)?,
            max_steps: self.max_steps,
            #[cfg(feature = "render")]
            render: self.render,
            spec: self.spec.into_spec(self.task, self.seed),
        };
        Ok((config, self.out))
    }
}

async fn run(args: RunArgs) -> Result<()> {
    let (config, out) = args.into_config()?;
    let mut csv = match &out {
        Some(path) => {
            Some(EpisodeCsv::create(path).with_context(|| format!("creating {}", path.display()))?)
        }
        None => None,
    };
    let mut write_error = None;
    let on_episode = |record: &bridge::EpisodeRecord| {
        println!(
            "episode {} return {:.3} ({} steps)",
            record.episode, record.episode_return, record.steps
        );
        if let Some(csv) = csv.as_mut()
            && let Err(e) = csv.append(record)
            && write_error.is_none()
        {
            tracing::error!(error = %e, "cannot write the episode to the CSV file");
            write_error = Some(e);
        }
    };
    let records = tokio::select! {
        result = bridge::run(&config, on_episode) => result.context("sim-bridge stopped")?,
        signal = proto::shutdown::shutdown_signal() => {
            let signal = signal.context("listening for stop signals")?;
            bail!("stopped by {signal}; the planner records the open episode as interrupted");
        }
    };
    if let (Some(e), Some(path)) = (write_error, &out) {
        return Err(e).with_context(|| format!("writing {}", path.display()));
    }
    let returns: Vec<f32> = records.iter().map(|r| r.episode_return).collect();
    let mean = returns.iter().sum::<f32>() / returns.len() as f32;
    let best = returns.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    tracing::info!(
        episodes = records.len(),
        mean_return = mean,
        best_return = best,
        "done"
    );
    Ok(())
}

fn list_tasks() {
    println!(
        "{:<12} {:>4} {:>4}  {:<16} {:>8} {:>10} {:>8}  simulator",
        "task", "obs", "act", "action bounds", "episode", "control dt", "rate"
    );
    for &task in Builtin::ALL {
        let spec = task.task();
        let bounds = bounds_text(&spec.action_low, &spec.action_high);
        let simulated = if sim_bridge::SIMULATED.contains(&task) {
            "yes"
        } else {
            "not yet"
        };
        println!(
            "{:<12} {:>4} {:>4}  {:<16} {:>8} {:>9}s {:>6.1}Hz  {simulated}",
            task.name(),
            spec.obs_dim,
            spec.act_dim,
            bounds,
            spec.episode_len,
            spec.control_dt,
            1.0 / spec.control_dt,
        );
    }
}

/// `±3` when every dimension has the same symmetric bounds, `[lo, hi]` otherwise.
fn bounds_text(low: &[f32], high: &[f32]) -> String {
    let symmetric = low
        .iter()
        .zip(high)
        .all(|(l, h)| *l == -*h && *h == high[0]);
    if symmetric {
        format!("±{}", high[0])
    } else if low.iter().all(|l| *l == low[0]) && high.iter().all(|h| *h == high[0]) {
        format!("[{}, {}]", low[0], high[0])
    } else {
        "per dimension".to_string()
    }
}

fn bench(args: &BenchArgs) -> Result<()> {
    let tasks = match args.task {
        Some(task) => vec![task],
        None => sim_bridge::SIMULATED.to_vec(),
    };
    println!(
        "{:<12} {:>8} {:>8} {:>12} {:>10} {:>10}",
        "task", "steps", "episodes", "steps/s", "µs/step", "real time"
    );
    for task in tasks {
        let rate = sim_bridge::bench::step_rate(task, args.steps)
            .with_context(|| format!("benchmarking {task}"))?;
        println!(
            "{:<12} {:>8} {:>8} {:>12.0} {:>10.1} {:>9.0}×",
            task.name(),
            rate.steps,
            rate.episodes,
            rate.steps_per_second(),
            1e6 / rate.steps_per_second(),
            rate.real_time_factor()
        );
    }
    Ok(())
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| EnvFilter::new("info,zenoh=warn,mujoco=warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Tasks => {
            list_tasks();
            Ok(())
        }
        Command::Bench(args) => bench(&args),
        Command::Run(args) => {
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()
                .context("starting the tokio runtime")?;
            runtime.block_on(run(*args))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--deadline` and `--planned-episode-seconds` as a user (or a launcher) gives them: the
    /// deadline in Unix seconds, the estimate in seconds; values no time can hold are refused
    /// with the flag's name, not a panic.
    #[test]
    fn the_deadline_flags_parse_and_refuse_what_no_time_can_hold() {
        let ok = deadline(1_800_000_000, Some(90.5)).unwrap();
        assert_eq!(
            ok.at,
            SystemTime::UNIX_EPOCH + Duration::from_secs(1_800_000_000)
        );
        assert_eq!(ok.planned_episode, Some(Duration::from_secs_f64(90.5)));
        assert_eq!(deadline(0, None).unwrap().planned_episode, None);
        let far = deadline(u64::MAX, None).unwrap_err();
        assert!(format!("{far:#}").contains("--deadline"), "{far:#}");
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            let err = deadline(1, Some(bad)).unwrap_err();
            assert!(
                format!("{err:#}").contains("--planned-episode-seconds"),
                "{err:#}"
            );
        }
        // The estimate needs a deadline to mean anything.
        let cli = Cli::try_parse_from([
            "sim-bridge",
            "run",
            "--task",
            "cartpole",
            "--run",
            "r",
            "--agent",
            "a",
            "--episodes",
            "1",
            "--planned-episode-seconds",
            "5",
        ]);
        assert!(cli.is_err());
    }
}
