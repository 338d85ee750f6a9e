//! `ebmpc-experiment`: reproduces the paper's comparisons and figures.

// Flag docs are `--help` text, where `results/<task>/…` reads as a path pattern, not HTML.
#![allow(rustdoc::invalid_html_tags)]

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use ebmpc_experiments::figures::imagination_folder::{self, Folder};
use ebmpc_experiments::figures::{imagination, imagination_tables, toy};
use ebmpc_experiments::launcher::{self, Experiment};
use ebmpc_experiments::plot::{self, curves::LearningCurves, fonts};
use ebmpc_experiments::scale::Scale;
use ebmpc_experiments::{compare, distance, model_error, provenance, replan, results, run_ledger};
use proto::Builtin;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Instant, SystemTime, UNIX_EPOCH};
use tracing_subscriber::EnvFilter;

/// Reproduces the paper's experiments: learning curves through the real planner daemon and
/// sim-bridges (Figure 4), imagination against reality (Figure 5), DEEN against DAE on a 1-D
/// mixture (Figure 3).
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Learn a task from scratch with several methods and seeds: one planner daemon, one
    /// sim-bridge per (method, seed) run over Zenoh. Re-running into the same --out folder
    /// skips the runs already complete; a sitting works only on the runs its command names.
    /// Ctrl-C stops the sitting cleanly (bridges, daemon, then the unfinished runs' resumable
    /// states); a second Ctrl-C ends it at once.
    Experiment(ExperimentArgs),
    /// Draw the learning curves (mean ± std over seeds per method) of an experiment folder.
    Plot(PlotArgs),
    /// Print a Markdown table of the returns (mean ± sample std over seeds) at chosen episodes,
    /// per method, with the planning time per step and the wall time per run.
    Table(TableArgs),
    /// Whether one method beats another at some episodes: each method's mean return over seeds
    /// with a Student-t interval, and every pair's seed-paired difference with its interval
    /// (the methods of an experiment share each seed's random exploration).
    Compare(CompareArgs),
    /// Every run of an experiment folder, one Markdown row each: its planned episodes'
    /// returns in the order recorded (finished or under way), or with --provenance where it
    /// ran: the CPUs, kernel paths, binaries and dates its records list, and its planning time
    /// per step.
    Runs(RunsArgs),
    /// How far the body travelled forward in each episode of a locomotion experiment's runs
    /// (half-cheetah, ant), read from the planner's stored replay logs: a return mixes
    /// progress with survival bonuses and control costs, the distance does not.
    Distance(DistanceArgs),
    /// Figure 5: after some episodes of training, optimise one plan from a random population
    /// with each regulariser and compare its imagined rewards with the real ones.
    Imagination(ImaginationArgs),
    /// Figure 5's tables of an imagination folder, in Markdown: per regulariser the mean gap
    /// (imagined − real return) and real return over every (seed, state) with their 95 %
    /// intervals, or with --per-seed each seed's means and its training returns.
    ImaginationTable(ImaginationTableArgs),
    /// Figure 3: DEEN and DAE score estimates on a 1-D Gaussian mixture against the truth.
    Toy(ToyArgs),
    /// Plan with a stored run's frozen models in the simulator for one episode: real return
    /// and milliseconds per plan, to compare optimisers (CEM, iCEM) on the same model.
    Replan(ReplanArgs),
    /// How wrong a stored run's newest models are on its own stored transitions, per episode
    /// and per interval of one observation: next-observation error, the reward the planner
    /// would imagine against the real one, and the regulariser's energy of both transitions.
    ModelError(ModelErrorArgs),
}

#[derive(Args, Debug)]
struct ExperimentArgs {
    /// Task to learn.
    #[arg(long)]
    task: Builtin,
    /// Methods to compare (comma-separated): cem, cem+dae, cem+deen, pets, pets+deen, adam+dae,
    /// and icem, icem+dae, icem+deen: the cem… preset planned by iCEM with 30 % of the scale's
    /// CEM population, a tenth of that as elites and 3 iterations.
    #[arg(long, value_delimiter = ',', default_value = "cem,cem+dae,cem+deen")]
    methods: Vec<String>,
    /// Sizes: `paper` (Table 2), `small` (fits a 2-core machine; see docs/experiments.md) or
    /// `small-learning` (small's seeds, episodes and training, Table 2's planning search).
    #[arg(long, value_enum, default_value_t = Scale::Paper)]
    scale: Scale,
    /// Seeds per method (0, 1, …; default: 5 at paper scale, 2 at small).
    #[arg(long)]
    seeds: Option<u32>,
    /// Episodes per run (default: the scale's for the task; with --timesteps, as many as the
    /// steps need).
    #[arg(long)]
    episodes: Option<u32>,
    /// Environment steps per run: a run is complete after the episode in which its steps
    /// reach this many (or after --episodes episodes, if given, whichever comes first). The
    /// paper counts ant and half-cheetah in timesteps ("walks within 4,000 timesteps").
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=100_000_000))]
    timesteps: Option<u64>,
    /// Noise σ of the energy model (DEEN, DAE) instead of Table 2's, for the methods that
    /// have one.
    #[arg(long)]
    energy_noise_sigma: Option<f32>,
    /// Units of the energy model's σ: standardised (each dimension of the transitions scaled
    /// to unit variance) or raw (the transitions' own units, as the paper corrupts its replay
    /// buffer); by default the task's preset decides (raw for pusher, standardised for the
    /// others).
    #[arg(long)]
    energy_noise_units: Option<proto::NoiseUnits>,
    /// Episodes of random actions before planning starts, for every method, instead of the
    /// preset's (the paper's: 3 for half-cheetah, 1 for the other tasks). More random data
    /// before the first plan, e.g. for a task whose first models see too little movement.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1000))]
    exploration_episodes: Option<u32>,
    /// Wall-clock budget of this sitting (e.g. 90m, 6h, 1h30m): runs start longest first and
    /// only when their estimated remaining time fits what is left; a run stops between two
    /// episodes when its next would end after the deadline (what still runs at the deadline is
    /// stopped there), and every unfinished run keeps a resumable state under runs/. Re-run the
    /// same command (on any machine, from a clone with the folder) to continue.
    #[arg(long, value_parser = ebmpc_experiments::queue::parse_duration)]
    budget: Option<std::time::Duration>,
    /// With --budget, start runs that are not expected to finish in the time left too (runs
    /// longer than any one sitting, e.g. PETS on half-cheetah on a small machine) while their
    /// next episode fits and no run that can finish is waiting; they are stopped by the
    /// deadline (between episodes where possible) and resume in the next sitting.
    #[arg(long, requires = "budget")]
    overrun: bool,
    /// Candidates per iteration of every sampling method, instead of the scale's search: a
    /// CEM method's population (elites a tenth of it, its iterations kept), an icem… method's
    /// first iteration (elites a tenth, 3 iterations). To find the smallest search that keeps
    /// a task's return (not for adam+dae, which has no population).
    #[arg(long, value_parser = clap::value_parser!(u32).range(4..=5000))]
    population: Option<u32>,
    /// Runs at the same time.
    #[arg(long, default_value_t = 2)]
    jobs: usize,
    /// Experiment folder (default: results/<task>/<UTC stamp>); an existing one is resumed.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Folder of the planner-service and sim-bridge binaries (default: this binary's folder).
    #[arg(long)]
    bin_dir: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct PlotArgs {
    /// Experiment folders (their episodes.csv) or episodes.csv files, all of one task: several
    /// draw their methods in one figure.
    #[arg(required = true)]
    paths: Vec<PathBuf>,
    /// Output stem (default: learning_curves next to the first CSV); .png and .svg are written.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct TableArgs {
    /// Experiment folders (their episodes.csv) or episodes.csv files, all of one task: several
    /// put their methods in one table.
    #[arg(required = true)]
    paths: Vec<PathBuf>,
    /// Episodes to show (comma-separated; default: every episode).
    #[arg(long, value_delimiter = ',')]
    episodes: Vec<u32>,
}

#[derive(Args, Debug)]
struct ImaginationTableArgs {
    /// The folder an `imagination` command wrote (imagination_states.csv, imagination_summary.csv).
    folder: PathBuf,
    /// One row per seed (its mean imagined return, real return and gap per regulariser)
    /// instead of the summary over seeds.
    #[arg(long)]
    per_seed: bool,
}

#[derive(Args, Debug)]
struct CompareArgs {
    /// Experiment folders (their episodes.csv) or episodes.csv files, all of one task.
    #[arg(required = true)]
    paths: Vec<PathBuf>,
    /// The episodes to compare at (comma-separated), each its number from 0 (the 20th episode
    /// is 19) or `last`: each run's last episode (runs budgeted in timesteps end after
    /// different numbers of episodes).
    #[arg(long, required = true, value_delimiter = ',')]
    episode: Vec<compare::At>,
    /// Confidence level of the intervals, between 0 and 1.
    #[arg(long, default_value_t = 0.95, value_parser = confidence_level)]
    level: f64,
    /// Compare only these methods (comma-separated, as the experiment names them; several
    /// folders' methods carry their folder's name in parentheses). Default: every method.
    #[arg(long, value_delimiter = ',')]
    methods: Vec<String>,
    /// Print only this table, without captions (as the results page's checked tables hold it).
    #[arg(long, value_enum)]
    only: Option<compare::Table>,
}

#[derive(Args, Debug)]
struct RunsArgs {
    /// The experiment folder (the one holding experiment.json and runs/).
    folder: PathBuf,
    /// Print where each run ran instead of its returns.
    #[arg(long)]
    provenance: bool,
}

/// A confidence level strictly between 0 and 1.
fn confidence_level(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(level) if level > 0.0 && level < 1.0 => Ok(level),
        _ => Err(format!(
            "`{text}` is not a level between 0 and 1 (e.g. 0.95)"
        )),
    }
}

#[derive(Args, Debug)]
struct DistanceArgs {
    /// Experiment folder (the --out of `experiment`), whose planner/ holds the runs.
    folder: PathBuf,
    /// The task whose runs to read (half-cheetah or ant).
    #[arg(long)]
    task: Builtin,
    /// Episodes shown per run, the most recent.
    #[arg(long, default_value_t = 3)]
    last: usize,
    /// Only episodes at least this long (default: whole episodes of the task).
    #[arg(long)]
    min_steps: Option<u32>,
}

#[derive(Args, Debug)]
struct ImaginationArgs {
    #[arg(long, default_value = "halfcheetah")]
    task: Builtin,
    /// Sizes of the models and of the MPC that collects the training data.
    #[arg(long, value_enum, default_value_t = Scale::Paper)]
    scale: Scale,
    /// CEM sizes of the three compared plans (default: --scale).
    #[arg(long, value_enum)]
    plan_scale: Option<Scale>,
    /// Method whose MPC collects the training data.
    #[arg(long, default_value = "cem+deen")]
    method: String,
    /// Training episodes before the comparison.
    #[arg(long, default_value_t = 5)]
    episodes: u32,
    /// MPC steps into the next episode before the plans are optimised.
    #[arg(long, default_value_t = 50)]
    mpc_steps: u32,
    /// Number format of the models' inference: auto (the service's default: the path measured
    /// fastest on this CPU, see the performance page), bf16 or f32. The Figure 5 results of
    /// 2026-11-23/24 were made with bf16, this flag's default then.
    #[arg(long, default_value = "auto")]
    inference_precision: proto::InferencePrecision,
    /// Seed of the first run (the others follow: seed + 1, …).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Runs, each learning from scratch with its own seed (≥ 3 for a confidence interval
    /// worth the name). Seeds the output folder already holds are skipped: re-run the same
    /// command to add the ones a sitting left.
    #[arg(long, default_value_t = 1)]
    seeds: u32,
    /// Start states compared per run (the paper shows 1).
    #[arg(long, default_value_t = 1)]
    states: u32,
    /// Wall-clock budget of this sitting (e.g. 90m, 1h30m): a seed starts only while the mean
    /// time of the seeds recorded in the folder fits what is left (the first one always).
    #[arg(long, value_parser = ebmpc_experiments::queue::parse_duration)]
    budget: Option<std::time::Duration>,
    /// Output folder (default: results/<task>/imagination-<scale>). It keeps every finished
    /// seed; one with other settings is refused.
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct ToyArgs {
    /// Training epochs of both estimators.
    #[arg(long, default_value_t = 1000)]
    epochs: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Output folder.
    #[arg(long, default_value = "results/figures")]
    out: PathBuf,
}

#[derive(Args, Debug)]
struct ModelErrorArgs {
    /// A run's directory (`run.json`, `models-*.safetensors`, `replay/`), e.g. a copy of
    /// `<experiment>/planner/archive/<run>`; a damaged checkpoint in it is moved aside. Its
    /// newest checkpoint is measured: remove newer ones from the copy to measure an older one.
    #[arg(long)]
    run: PathBuf,
    /// Group each episode's transitions by this observation of the state (an index; e.g. 2,
    /// the half-cheetah's pitch). Without it, one group per episode.
    #[arg(long)]
    by_obs: Option<usize>,
    /// Ascending edges of the groups on that observation (comma-separated): n edges make
    /// n + 1 intervals, a value on an edge belonging to the interval above.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    edges: Vec<f32>,
    /// Only these episodes (comma-separated episode numbers as the replay stores them; default:
    /// all).
    #[arg(long, value_delimiter = ',')]
    episodes: Option<Vec<u32>>,
}

#[derive(Args, Debug)]
struct ReplanArgs {
    /// A run's directory (`run.json` and `models-*.safetensors`), e.g. a copy of
    /// `<experiment>/planner/runs/<run>`; a damaged checkpoint in it is moved aside.
    #[arg(long)]
    run: PathBuf,
    /// Simulator steps of the episode (at most the task's episode length).
    #[arg(long, default_value_t = 1000)]
    steps: u32,
    /// Seed of the start state and of the planner.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Optimiser: cem, icem or adam (default: the run's).
    #[arg(long)]
    optimizer: Option<proto::Optimizer>,
    /// Planning horizon in steps (default: the run's): a shorter one buys more candidates in
    /// the same time.
    #[arg(long)]
    horizon: Option<u32>,
    /// Weight α of the regulariser's penalty (default: the run's; 0 plans on the same models
    /// without it: what the penalty costs or earns on them).
    #[arg(long)]
    energy_weight: Option<f32>,
    /// Candidates per iteration (iCEM: of its first iteration; default: the run's).
    #[arg(long)]
    population: Option<u32>,
    /// Elites per iteration (default: the run's).
    #[arg(long)]
    elites: Option<u32>,
    /// Iterations per plan (default: the run's).
    #[arg(long)]
    iterations: Option<u32>,
    /// iCEM's colored-noise exponent β (default: the preset's for the task).
    #[arg(long)]
    noise_beta: Option<f32>,
    /// iCEM's fraction of elites kept across iterations and steps.
    #[arg(long)]
    keep_elites: Option<f32>,
    /// iCEM's population decay per iteration (≥ 1).
    #[arg(long)]
    population_decay: Option<f32>,
}

/// `YYYYMMDD-HHMMSS` in UTC, for experiment folders.
fn stamp() -> String {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    let (year, month, day) = ebmpc_experiments::provenance::civil_from_days(days);
    format!(
        "{year:04}{month:02}{day:02}-{:02}{:02}{:02}",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

fn experiment(args: ExperimentArgs) -> Result<()> {
    let seeds = args.seeds.unwrap_or(args.scale.default_seeds());
    let exp = Experiment {
        task: args.task,
        methods: args.methods,
        seeds: (0..u64::from(seeds)).collect(),
        episodes: match (args.episodes, args.timesteps) {
            (Some(e), _) => e,
            // Every episode has at least one step: the step budget bounds the count.
            (None, Some(t)) => u32::try_from(t).unwrap_or(u32::MAX),
            (None, None) => args.scale.default_episodes(args.task),
        },
        timesteps: args.timesteps,
        energy_noise_sigma: args.energy_noise_sigma,
        energy_noise_units: args.energy_noise_units,
        exploration_episodes: args.exploration_episodes,
        budget: args.budget,
        overrun: args.overrun,
        scale: args.scale,
        out: args
            .out
            .unwrap_or_else(|| Path::new("results").join(args.task.name()).join(stamp())),
        jobs: args.jobs,
        population: args.population,
        bin_dir: match args.bin_dir {
            Some(dir) => dir,
            None => launcher::default_bin_dir()?,
        },
    };
    // The first SIGINT or SIGTERM asks the sitting to stop cleanly (its bridges, then its
    // daemon, then packing the unfinished runs' states); a second one ends the launcher at
    // once (its children are told to stop by the kernel).
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(signal, 130, Arc::clone(&stop))
            .context("installing the stop handler")?;
        signal_hook::flag::register(signal, Arc::clone(&stop))
            .context("installing the stop handler")?;
    }
    let started = Instant::now();
    let outcome = launcher::run(&exp, &stop);
    // Whatever finished is worth a figure, also when some run failed.
    let csv = exp.out.join("episodes.csv");
    if csv.exists() {
        plot_curves(&csv, &exp.out.join("learning_curves"))?;
    }
    let rows = outcome?;
    println!(
        "{} ({} scale): {} episodes in {} in {:.1} min",
        exp.task,
        exp.scale.name(),
        rows.len(),
        exp.out.display(),
        started.elapsed().as_secs_f64() / 60.0
    );
    print_summary(&rows);
    Ok(())
}

/// Per method: the mean ± std return of the last episode, the mean planning time per step and
/// the training time per retraining.
fn print_summary(rows: &[results::EpisodeRow]) {
    println!(
        "{:<10} {:>5} {:>18} {:>14} {:>14}",
        "method", "seeds", "last-episode return", "ms/plan step", "s/retraining"
    );
    for curve in results::curves(rows) {
        let Some(last) = curve.points.last() else {
            continue;
        };
        let mine: Vec<_> = rows.iter().filter(|r| r.method == curve.method).collect();
        let planned: Vec<_> = mine.iter().filter(|r| r.planned_steps > 0).collect();
        let plan_ms =
            planned.iter().map(|r| r.plan_ms_per_step).sum::<f64>() / planned.len().max(1) as f64;
        let trained: Vec<_> = mine.iter().filter(|r| r.train_seconds > 0.0).collect();
        let train_s =
            trained.iter().map(|r| r.train_seconds).sum::<f64>() / trained.len().max(1) as f64;
        println!(
            "{:<10} {:>5} {:>11.1} ± {:<6.1} {:>13.1} {:>14.1}",
            curve.method, last.seeds, last.mean, last.std, plan_ms, train_s
        );
    }
}

fn plot_curves(csv: &Path, stem: &Path) -> Result<()> {
    draw_curves(&results::read_episodes(csv)?, stem)
}

fn draw_curves(rows: &[results::EpisodeRow], stem: &Path) -> Result<()> {
    let task = rows.first().map(|r| r.task.clone()).unwrap_or_default();
    let figure = LearningCurves {
        title: format!("{task}: return per episode, mean ± std over seeds"),
        curves: results::curves(rows),
    };
    let [png, svg] = plot::save(&figure, stem, fonts::ensure())?;
    println!("wrote {} and {}", png.display(), svg.display());
    Ok(())
}

/// The `episodes.csv` a folder or file argument names.
fn episodes_csv(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join("episodes.csv")
    } else {
        path.to_path_buf()
    }
}

/// The rows of several experiments of one task, in argument order (a method found in several is
/// labelled with its folder's name in each).
fn read_experiments(paths: &[PathBuf]) -> Result<Vec<results::EpisodeRow>> {
    let mut experiments = Vec::new();
    for path in paths {
        let csv = episodes_csv(path);
        let name = csv.parent().and_then(Path::file_name).map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into(),
        );
        experiments.push((name, results::read_episodes(&csv)?));
    }
    let rows = results::combine_experiments(experiments);
    let mut tasks: Vec<&str> = rows.iter().map(|r| r.task.as_str()).collect();
    tasks.dedup();
    if tasks.len() > 1 {
        anyhow::bail!(
            "the experiments are of different tasks ({}): compare one task at a time",
            tasks.join(", ")
        );
    }
    Ok(rows)
}

fn plot_command(args: PlotArgs) -> Result<()> {
    let rows = read_experiments(&args.paths)?;
    let stem = args.out.unwrap_or_else(|| {
        episodes_csv(&args.paths[0])
            .parent()
            .unwrap_or(Path::new("."))
            .join("learning_curves")
    });
    draw_curves(&rows, &stem)
}

fn distance_command(args: DistanceArgs) -> Result<()> {
    let rows = distance::experiment_distances(&args.folder, args.task)?;
    let min_steps = args
        .min_steps
        .unwrap_or_else(|| args.task.spec().episode_len);
    print!("{}", distance::markdown(&rows, args.last, min_steps));
    Ok(())
}

fn table_command(args: TableArgs) -> Result<()> {
    let rows = read_experiments(&args.paths)?;
    print!("{}", results::markdown_table(&rows, &args.episodes));
    Ok(())
}

fn imagination_table_command(args: ImaginationTableArgs) -> Result<()> {
    let table = if args.per_seed {
        imagination_tables::per_seed_markdown(&args.folder)?
    } else {
        imagination_tables::summary_markdown(&args.folder)?
    };
    print!("{table}");
    Ok(())
}

fn runs_command(args: RunsArgs) -> Result<()> {
    let (manifest, runs) = run_ledger::read_folder(&args.folder)?;
    if args.provenance {
        print!("{}", run_ledger::provenance_markdown(&runs));
    } else {
        print!("{}", run_ledger::returns_markdown(&manifest, &runs));
    }
    Ok(())
}

fn compare_command(args: CompareArgs) -> Result<()> {
    let mut rows = read_experiments(&args.paths)?;
    if !args.methods.is_empty() {
        let mut present: Vec<&str> = rows.iter().map(|r| r.method.as_str()).collect();
        present.sort_unstable();
        present.dedup();
        if let Some(missing) = args.methods.iter().find(|m| !present.contains(&m.as_str())) {
            anyhow::bail!(
                "no run of method `{missing}`: the experiments hold {}",
                present.join(", ")
            );
        }
        rows.retain(|r| args.methods.contains(&r.method));
    }
    let mut comparisons = Vec::new();
    for at in args.episode {
        let comparison = compare::compare(&rows, at, args.level);
        if comparison.methods.is_empty() {
            anyhow::bail!("no run has {at}");
        }
        comparisons.push(comparison);
    }
    let percent = args.level * 100.0;
    match args.only {
        Some(table) => print!("{}", compare::markdown(&comparisons, table)),
        None => print!(
            "Return at each episode, the mean over seeds with a {percent:.0} % Student-t \
             interval:\n\n{}\nSeed-paired differences, over the seeds both methods have (the \
             method ahead on average first):\n\n{}",
            compare::markdown(&comparisons, compare::Table::Methods),
            compare::markdown(&comparisons, compare::Table::Differences)
        ),
    }
    Ok(())
}

fn imagination_command(args: ImaginationArgs) -> Result<()> {
    imagination::check_task(args.task)?;
    let out = args.out.unwrap_or_else(|| {
        Path::new("results")
            .join(args.task.name())
            .join(format!("imagination-{}", args.scale.name()))
    });
    let config = |seed: u64| imagination::ImaginationConfig {
        task: args.task,
        scale: args.scale,
        plan_scale: args.plan_scale.unwrap_or(args.scale),
        method: args.method.clone(),
        train_episodes: args.episodes,
        mpc_steps: args.mpc_steps,
        inference_precision: args.inference_precision,
        seed,
        states: args.states,
    };
    let mut folder = Folder::open(&out, &imagination_folder::Settings::of(&config(args.seed)))?;
    let exe_dir = std::env::current_exe()?
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default();
    let commit = provenance::binaries_commit(&exe_dir);
    let started = Instant::now();
    let seeds: Vec<u64> = (0..args.seeds.max(1))
        .map(|s| args.seed.wrapping_add(u64::from(s)))
        .collect();
    let mut left_for_later = Vec::new();
    for &seed in &seeds {
        if folder.finished().contains(&seed) {
            tracing::info!("seed {seed}: already in {}, skipped", out.display());
            continue;
        }
        let time_left = args.budget.map(|b| b.saturating_sub(started.elapsed()));
        if let (Some(left), Some(per_seed)) = (time_left, folder.seconds_per_seed())
            && per_seed > left
        {
            left_for_later.push(seed);
            continue;
        }
        let seed_started = Instant::now();
        let config = config(seed);
        let result = imagination::run(&config, |e, ret| {
            tracing::info!(
                "seed {seed}: training episode {}/{}: return {ret:.2} ({:.0} s so far)",
                e + 1,
                config.train_episodes,
                started.elapsed().as_secs_f64()
            );
        })?;
        folder.record(seed, &result, seed_started.elapsed(), &commit)?;
        // The per-step figure shows the first seed's first state.
        if seed == args.seed {
            std::fs::write(out.join("imagination.csv"), result.to_csv())?;
            plot::save(&result, &out.join("imagination"), fonts::ensure())?;
        }
    }
    if !left_for_later.is_empty() {
        println!(
            "seeds {left_for_later:?} do not fit the budget's remaining time (about {} each): \
             re-run the same command to add them",
            folder
                .seconds_per_seed()
                .map_or_else(String::new, |d| format!(
                    "{:.0} min",
                    d.as_secs_f64() / 60.0
                ))
        );
    }
    let rows = folder.rows();
    if rows.is_empty() {
        return Ok(());
    }
    let summary = imagination::summary(rows);
    imagination::write_csv(&out.join("imagination_summary.csv"), &summary)?;
    plot::save(
        &imagination::SummaryFigure(&summary),
        &out.join("imagination_summary"),
        fonts::ensure(),
    )?;
    println!(
        "over {} seed(s) and their start states (95 % bootstrap intervals):",
        folder.finished().len()
    );
    for r in &summary {
        println!(
            "{:<5} {} states: gap {:>8.2} [{:.2}, {:.2}]  real {:>8.2} [{:.2}, {:.2}]",
            r.regularizer,
            r.states,
            r.mean_gap,
            r.gap_ci_low,
            r.gap_ci_high,
            r.mean_real_return,
            r.real_ci_low,
            r.real_ci_high
        );
    }
    println!(
        "wrote {} (imagination_states.csv, imagination_seeds.csv, imagination_summary.{{csv,png,svg}}, \
         and the first seed's imagination.{{csv,png,svg}}) in {:.1} min",
        out.display(),
        started.elapsed().as_secs_f64() / 60.0
    );
    Ok(())
}

fn toy_command(args: ToyArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let config = toy::ToyConfig {
        epochs: args.epochs,
        seed: args.seed,
        ..toy::ToyConfig::default()
    };
    let result = toy::run(&config);
    std::fs::write(args.out.join("toy.csv"), result.to_csv())?;
    let [png, svg] = plot::save(&result, &args.out.join("toy"), fonts::ensure())?;
    let (deen, dae) = result.score_rmse();
    println!("score RMSE against the smoothed truth (|x| ≤ 4): DEEN {deen:.3}, DAE {dae:.3}");
    println!("wrote {}, {}", png.display(), svg.display());
    Ok(())
}

fn replan_command(args: ReplanArgs) -> Result<()> {
    let config = replan::ReplanConfig {
        run_dir: args.run,
        overrides: proto::PlannerOverrides {
            optimizer: args.optimizer,
            horizon: args.horizon,
            energy_weight: args.energy_weight,
            population: args.population,
            elites: args.elites,
            cem_iterations: args.iterations,
            icem_noise_beta: args.noise_beta,
            icem_keep_elites: args.keep_elites,
            icem_population_decay: args.population_decay,
            ..Default::default()
        },
        steps: args.steps,
        seed: args.seed,
    };
    println!("{}", replan::run(&config)?);
    Ok(())
}

fn model_error_command(args: ModelErrorArgs) -> Result<()> {
    let report = model_error::run(&model_error::ModelErrorConfig {
        run_dir: args.run,
        by_obs: args.by_obs,
        edges: args.edges,
        episodes: args.episodes,
    })?;
    print!("{}", report.markdown());
    Ok(())
}

fn main() -> Result<()> {
    // MuJoCo's compile-time report and zenoh's chatter are noise here; colours only on a
    // terminal, so that a run under nohup leaves a readable log.
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| EnvFilter::new("info,zenoh=warn,mujoco=warn")),
        )
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Experiment(args) => experiment(args),
        Command::Plot(args) => plot_command(args),
        Command::Table(args) => table_command(args),
        Command::Compare(args) => compare_command(args),
        Command::Runs(args) => runs_command(args),
        Command::Distance(args) => distance_command(args),
        Command::Imagination(args) => imagination_command(args),
        Command::ImaginationTable(args) => imagination_table_command(args),
        Command::Toy(args) => toy_command(args),
        Command::Replan(args) => replan_command(args),
        Command::ModelError(args) => model_error_command(args),
    }
}
