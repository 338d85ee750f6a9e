//! The experiment launcher: one planner daemon, one sim-bridge process per (method, seed) run,
//! all talking over Zenoh on loopback exactly as in a deployment (`deploy/demo.sh` does the same
//! by hand: a free port, multicast scouting off, the bridges `--connect` to the daemon).
//!
//! ```text
//! <out>/experiment.json        task, scale, episodes, overrides, methods, seeds (resume check)
//! <out>/runs/<method>-s<seed>.csv   one run's episodes; `.csv.partial` while it runs
//! <out>/runs/<method>-s<seed>.csv.attempt   the episodes of the bridge now running
//! <out>/runs/<method>-s<seed>.json  a finished run's record: spec, and per sitting the episodes
//!                              it recorded, binaries' commit, machine, kernel paths and
//!                              precision, load (provenance::RunRecord)
//! <out>/runs/<method>-s<seed>.sittings.json  an unfinished run's sittings so far
//! <out>/runs/<method>-s<seed>.state.tar.gz  an unfinished run's resumable state (resume_state)
//! <out>/episodes.csv           every run's rows with method and seed (results::HEADER)
//! <out>/learning_curves.{png,svg}
//! <out>/logs/, <out>/planner/  process logs and the daemon's data (not committed)
//! <out>/planner/archive/       finished runs' daemon data, moved out of the daemon's way
//! ```
//!
//! A run counts as done when its `.csv` exists with all its episodes (or, for an experiment
//! budgeted in timesteps, with at least that many steps), so re-running the same command into
//! the same folder skips the finished runs and **resumes** the unfinished ones: the folder is
//! the run queue, and it survives restarts. Everything a finished run leaves under `runs/` is
//! ready to commit the moment it finishes; `logs/` and `planner/` are not meant to be.
//!
//! **Budgets.** A sitting may have a wall-clock budget: then it starts runs longest first and only
//! those whose estimated remaining cost fits the time left ([`crate::queue`]), has each bridge stop
//! between two episodes, before it resets the simulator, when its next one would end after the
//! deadline (`sim-bridge run --deadline`; so that the run's buffer holds exactly its recorded
//! episodes), stops what still runs at the deadline itself (an episode the
//! estimate did not foresee), and packs the replay log and newest checkpoint of every
//! unfinished run it started into `runs/<stem>.state.tar.gz` ([`crate::resume_state`]), from
//! which a later sitting — on a fresh clone too — continues it.
//!
//! **Stopping a sitting by hand.** Asked to stop ([`run`]'s `stop` flag: the binary sets it on
//! the first SIGINT or SIGTERM), a sitting ends as at a deadline reached now: it starts no
//! further run, stops the running bridges (each records its open episode as interrupted), stops
//! the daemon, which syncs its data, and then packs the states of the unfinished runs it
//! started, so a Ctrl-C
//! loses no recorded episode and the same command continues. The bridges and the daemon run in
//! process groups of their own, so a terminal's Ctrl-C reaches the launcher alone and the
//! processes stop in that order.
//!
//! **Resuming a half-finished run.** A run keeps one daemon run name for its whole life
//! (`<task>-<method>-s<seed>`), and the daemon's data lives in `<out>/planner/`, so a restarted
//! experiment's daemon reopens the run from its stored replay buffer and newest model
//! checkpoint. The episodes already recorded in `.csv.partial` (k of N) are kept and the
//! bridge is asked for the remaining `N − k` only; it numbers them from the daemon's next
//! episode and resets episode `e` from the seed `seed + e`, as an uninterrupted run does. Each
//! attempt's bridge writes its own `.csv.attempt`, whose complete lines are appended to
//! `.csv.partial` when the bridge ends (and, after a crash of the launcher itself, when the
//! run is next started), so no recorded episode is lost or counted twice.
//!
//! What is identical to an uninterrupted run: the recorded episodes, the training data and every
//! episode's start state. What is not: an episode cut short (a killed launcher, or a deadline the
//! estimate did not foresee; a budget otherwise stops runs between episodes) stays in the daemon's
//! buffer as an interrupted episode (it is trained on), a retraining still under way when the
//! daemon stops is redone from the newest checkpoint (a bridge stopping between episodes waits
//! for the retraining on its last one, up to the deadline), the planner's random stream
//! restarts from the run's seed when the daemon reopens the run, and an episode the daemon
//! finished whose row the killed bridge had not yet written is played once more (the daemon
//! then holds one episode more than the CSV, and the CSV's episode numbers skip one).

use crate::manifest::Manifest;
use crate::method::Method;
use crate::progress::{Progress, RunLength};
use crate::provenance::{self, Load, Machine, RunRecord, Sitting};
use crate::queue::{self, Pending};
use crate::results::{self, EpisodeRow};
use crate::resume_state;
use crate::scale::{self, Scale};
use anyhow::{Context, Result, bail};
use planner_service::config::ServiceConfig;
use planner_service::persist::admin;
use planner_service::plan::Optimizer;
use proto::Builtin;
use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime};

/// What to run.
#[derive(Clone, Debug)]
pub struct Experiment {
    pub task: Builtin,
    pub methods: Vec<String>,
    pub seeds: Vec<u64>,
    pub episodes: u32,
    pub scale: Scale,
    /// The experiment folder (created, or resumed if it holds the same experiment).
    pub out: PathBuf,
    /// Runs at the same time (each is one bridge; they share the daemon and the cores).
    pub jobs: usize,
    /// Folder holding the `planner-service` and `sim-bridge` binaries.
    pub bin_dir: PathBuf,
    /// Candidates per iteration of every sampling method (CEM's population, iCEM's first
    /// iteration; default: the scale's, see [`crate::scale::Scale::overrides`]).
    pub population: Option<u32>,
    /// A run is complete after this many environment steps (whole episodes), or after
    /// `episodes` episodes, whichever comes first (`None`: episodes only).
    pub timesteps: Option<u64>,
    /// The energy model's noise σ and its units for the methods with a regulariser (`None`:
    /// the preset's, Table 2's σ in standardised units).
    pub energy_noise_sigma: Option<f32>,
    pub energy_noise_units: Option<proto::NoiseUnits>,
    /// Episodes of random actions before planning starts, for every method (`None`: the
    /// preset's, paper §4.2: 3 for half-cheetah, 1 for the other tasks).
    pub exploration_episodes: Option<u32>,
    /// This sitting's wall-clock budget (`None`: run everything pending).
    pub budget: Option<Duration>,
    /// Start runs that are not expected to finish within the budget too (they are stopped at
    /// the deadline and keep a resumable state).
    pub overrun: bool,
}

/// One (method, seed) run of an experiment.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunId {
    pub method: String,
    pub seed: u64,
}

impl RunId {
    /// File stem of the run's files: the method with `+` spelled `-` (file and key friendly).
    pub fn stem(&self) -> String {
        format!("{}-s{}", self.method.replace('+', "-"), self.seed)
    }

    /// The finished run's episode file.
    pub fn csv(&self, dir: &Path) -> PathBuf {
        dir.join("runs").join(format!("{}.csv", self.stem()))
    }

    /// The episodes recorded so far while the run is unfinished (over all its attempts).
    pub fn partial_csv(&self, dir: &Path) -> PathBuf {
        dir.join("runs")
            .join(format!("{}.csv.partial", self.stem()))
    }

    /// The file the running bridge writes (merged into [`RunId::partial_csv`] when it ends).
    pub fn attempt_csv(&self, dir: &Path) -> PathBuf {
        dir.join("runs")
            .join(format!("{}.csv.attempt", self.stem()))
    }

    /// The run's name in the daemon: the same for every attempt, so that a resumed attempt
    /// continues the stored run.
    pub fn daemon_run(&self, task: Builtin) -> String {
        format!("{}-{}", task.name(), self.stem())
    }

    /// The record of the finished run ([`RunRecord`]).
    pub fn record_json(&self, dir: &Path) -> PathBuf {
        dir.join("runs").join(format!("{}.json", self.stem()))
    }

    /// The unfinished run's sittings so far ([`Sitting`]), moved into its record when it
    /// finishes.
    pub fn sittings_json(&self, dir: &Path) -> PathBuf {
        dir.join("runs")
            .join(format!("{}.sittings.json", self.stem()))
    }

    /// Where the run's sittings are kept ([`provenance::read_sittings`]): its record once it
    /// is finished, else its sittings file.
    pub fn sittings_file(&self, dir: &Path) -> PathBuf {
        if self.record_json(dir).exists() {
            self.record_json(dir)
        } else {
            self.sittings_json(dir)
        }
    }

    /// The unfinished run's packed resumable state.
    pub fn state_archive(&self, dir: &Path) -> PathBuf {
        dir.join("runs")
            .join(format!("{}{}", self.stem(), resume_state::SUFFIX))
    }

    /// The daemon's folder of this run under the experiment's `planner/` data directory.
    pub fn daemon_dir(&self, dir: &Path, task: Builtin) -> PathBuf {
        dir.join("planner").join("runs").join(self.daemon_run(task))
    }
}

/// How long each of the manifest's runs is.
fn run_length(manifest: &Manifest) -> RunLength {
    RunLength {
        episodes: manifest.episodes,
        timesteps: manifest.timesteps,
    }
}

/// What remains of a run given the episodes its file records (`None`: it is complete).
fn remaining_of(file: &Path, manifest: &Manifest) -> Option<queue::Remaining> {
    remaining_after(&results::recorded(file), manifest)
}

/// What remains of a run after its recorded episodes `rows` (`None`: it is complete).
fn remaining_after(rows: &[EpisodeRow], manifest: &Manifest) -> Option<queue::Remaining> {
    let steps = rows.iter().map(|r| u64::from(r.steps)).sum();
    queue::remaining(manifest.episodes, manifest.timesteps, rows.len(), steps)
}

/// Every run of the manifest, methods first then seeds, with whether it is already complete.
pub fn runs(dir: &Path, manifest: &Manifest) -> Vec<(RunId, bool)> {
    let mut out = Vec::new();
    for method in &manifest.methods {
        for &seed in &manifest.seeds {
            let run = RunId {
                method: method.clone(),
                seed,
            };
            let done = run.csv(dir).exists() && remaining_of(&run.csv(dir), manifest).is_none();
            out.push((run, done));
        }
    }
    out
}

/// The unfinished runs this command asks for: its methods × its seeds. A folder's manifest
/// holds every run any command asked for, and `episodes.csv` all the finished ones, but a
/// sitting works only on what its own command names, so that a shorter command can finish
/// one run first (`--methods cem+deen --seeds 1`) and the full one continues the rest.
pub fn asked_and_unfinished(all: &[(RunId, bool)], exp: &Experiment) -> Vec<RunId> {
    all.iter()
        .filter(|(run, done)| {
            !done && exp.methods.contains(&run.method) && exp.seeds.contains(&run.seed)
        })
        .map(|(run, _)| run.clone())
        .collect()
}

/// The rows of every complete run of the manifest, in manifest order.
pub fn collect_rows(dir: &Path, manifest: &Manifest) -> Result<Vec<EpisodeRow>> {
    let task = manifest.task.name();
    let mut rows = Vec::new();
    for (run, done) in runs(dir, manifest) {
        if done {
            rows.extend(results::read_run_csv(
                &run.csv(dir),
                task,
                &run.method,
                run.seed,
            )?);
        }
    }
    Ok(rows)
}

/// Prepares the folder: checks or writes the manifest and returns it (merged with an existing
/// one when resuming).
pub fn prepare(exp: &Experiment) -> Result<Manifest> {
    for method in &exp.methods {
        let parsed =
            Method::parse(exp.task, method).with_context(|| format!("method `{method}`"))?;
        if exp.population.is_some() && parsed.optimizer == Optimizer::Adam {
            bail!(
                "--population sizes sampling searches (CEM, iCEM); method `{method}` optimises \
                 by gradient and has no population: run it in an experiment of its own"
            );
        }
    }
    std::fs::create_dir_all(exp.out.join("runs"))
        .with_context(|| format!("creating {}", exp.out.display()))?;
    std::fs::create_dir_all(exp.out.join("logs"))?;
    let mut wanted = Manifest::new(
        exp.task,
        exp.scale,
        exp.episodes,
        exp.methods.clone(),
        exp.seeds.clone(),
        exp.population,
    )?;
    wanted.timesteps = exp.timesteps;
    for (method, overrides) in &mut wanted.overrides {
        overrides.exploration_episodes =
            exp.exploration_episodes.or(overrides.exploration_episodes);
        let preset = Method::parse(exp.task, method)?.preset;
        if preset.contains("dae") || preset.contains("deen") {
            overrides.energy_noise_sigma = exp.energy_noise_sigma.or(overrides.energy_noise_sigma);
            overrides.energy_noise_units = exp.energy_noise_units.or(overrides.energy_noise_units);
        }
    }
    let manifest = match Manifest::load(&exp.out)? {
        Some(existing) => wanted.resume(&existing, &exp.out)?,
        None => wanted,
    };
    manifest.save(&exp.out)?;
    Ok(manifest)
}

/// Every episode recorded so far by the runs of the manifest, finished or not, and those of
/// them that a sitting on a machine with `machine`'s CPU recorded (for the queue's cost
/// estimates).
fn recorded_rows(
    dir: &Path,
    manifest: &Manifest,
    machine: &Machine,
) -> (Vec<EpisodeRow>, Vec<EpisodeRow>) {
    let task = manifest.task.name();
    let (mut all, mut here) = (Vec::new(), Vec::new());
    for (run, _) in runs(dir, manifest) {
        let file = run.sittings_file(dir);
        let sittings = provenance::read_sittings(&file).unwrap_or_else(|e| {
            tracing::warn!(run = %run.stem(), "{}: {e}", file.display());
            provenance::KeptSittings::default()
        });
        let recorded_here: BTreeSet<u32> = sittings
            .sittings
            .into_iter()
            .filter(|s| s.machine.same_cpu(machine))
            .flat_map(|s| s.episodes)
            .collect();
        for file in [run.csv(dir), run.partial_csv(dir), run.attempt_csv(dir)] {
            if let Ok(rows) = results::read_run_csv(&file, task, &run.method, run.seed) {
                here.extend(
                    rows.iter()
                        .filter(|r| recorded_here.contains(&r.episode))
                        .cloned(),
                );
                all.extend(rows);
            }
        }
    }
    (all, here)
}

/// Per method, what its recorded episodes measure, with the planning rate of this machine's
/// CPU where it has been measured here ([`queue::on_this_machine`]).
fn method_costs(
    dir: &Path,
    manifest: &Manifest,
    machine: &Machine,
) -> BTreeMap<String, queue::MethodCost> {
    let (all, here) = recorded_rows(dir, manifest, machine);
    costs_here(&all, &here)
}

/// [`method_costs`] from the rows [`recorded_rows`] returned.
fn costs_here(all: &[EpisodeRow], here: &[EpisodeRow]) -> BTreeMap<String, queue::MethodCost> {
    queue::on_this_machine(queue::method_costs(all), &queue::method_costs(here))
}

/// The pending runs with their estimated remaining cost on `machine`, longest first.
fn plan_queue(
    dir: &Path,
    manifest: &Manifest,
    machine: &Machine,
    pending: &[RunId],
) -> Vec<Pending<RunId>> {
    let (all, here) = recorded_rows(dir, manifest, machine);
    let costs = costs_here(&all, &here);
    let episode_len = manifest.task.task().spec().episode_len;
    let mut out: Vec<Pending<RunId>> = pending
        .iter()
        .map(|run| {
            let cost = costs.get(&run.method).copied();
            let rows = results::recorded(&run.partial_csv(dir));
            let estimate = remaining_after(&rows, manifest)
                .and_then(|left| queue::estimate(left, cost?, episode_len));
            // A resumed run's next episode costs what its planned episodes on this CPU took
            // (their median); episodes of another CPU (or of no recorded sitting) say nothing
            // about this one, so without any the method's rate here stands in. A new run's
            // first episode is random exploration (cheap), left unestimated.
            let recorded_here: Vec<&EpisodeRow> = here
                .iter()
                .filter(|r| r.method == run.method && r.seed == run.seed)
                .collect();
            let next_episode = rows
                .last()
                .and_then(|_| queue::next_episode(&recorded_here, cost, episode_len));
            Pending {
                run: run.clone(),
                estimate,
                next_episode,
            }
        })
        .collect();
    queue::longest_first(&mut out);
    out
}

/// Minutes, for log lines.
fn minutes(d: Duration) -> String {
    format!("{:.1} min", d.as_secs_f64() / 60.0)
}

/// How a run's bridge ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum RunEnd {
    Finished,
    /// Stopped at the sitting's deadline or on request; its state is packed when the daemon
    /// has stopped.
    Stopped,
}

/// Runs the experiment's unfinished runs, `jobs` at a time, longest first and within the
/// budget if there is one, and rebuilds `episodes.csv`. Returns the rows of all complete
/// runs. Fails (after the other runs finished) if any run failed; its log is named in the
/// error. Runs left for a later sitting are not failures. Once `stop` is set (from a signal
/// handler, say) the sitting ends as at its deadline, at once (see the module's doc).
pub fn run(exp: &Experiment, stop: &AtomicBool) -> Result<Vec<EpisodeRow>> {
    let started = Instant::now();
    let deadline = exp.budget.map(|b| started + b);
    let manifest = prepare(exp)?;
    let _sitting = lock_sitting(&exp.out)?;
    let all = runs(&exp.out, &manifest);
    let pending = asked_and_unfinished(&all, exp);
    let skipped = all.iter().filter(|(_, done)| *done).count();
    let not_asked = all.len() - skipped - pending.len();
    tracing::info!(
        dir = %exp.out.display(),
        runs = all.len(),
        skipped,
        pending = pending.len(),
        not_asked,
        budget = ?exp.budget,
        "experiment {} ({} scale): {}",
        exp.task,
        exp.scale.name(),
        run_length(&manifest),
    );
    archive_finished_runs(&exp.out, &manifest);
    let episodes_csv = exp.out.join("episodes.csv");
    if pending.is_empty() {
        let rows = collect_rows(&exp.out, &manifest)?;
        results::write_episodes(&episodes_csv, &rows)?;
        remove_finished_states(&exp.out, &manifest)?;
        return Ok(rows);
    }
    // A fresh clone has the unfinished runs' packed states but no daemon folder.
    for run in &pending {
        let archive = run.state_archive(&exp.out);
        if archive.exists()
            && resume_state::unpack(&archive, &run.daemon_dir(&exp.out, exp.task))
                .with_context(|| format!("unpacking {}", archive.display()))?
        {
            tracing::info!(run = %run.stem(), "resuming from {}", archive.display());
        }
    }

    let planner = Daemon::start(
        &exp.bin_dir.join("planner-service"),
        &exp.out.join("planner"),
        &exp.out.join("logs"),
    )?;
    let machine = Machine::this();
    let commit = provenance::binaries_commit(&exp.bin_dir);
    if commit == provenance::UNKNOWN_COMMIT {
        // Said at the start, not found in the records afterwards: a sitting whose binaries'
        // commit is unknown leaves its episodes without the provenance a result must name.
        tracing::warn!(
            bin_dir = %exp.bin_dir.display(),
            "the binaries' commit is unknown and this sitting's records will say so: write \
             `git rev-parse HEAD` of the tree they were built from to COMMIT in --bin-dir \
             (experiments/figure4.sh does)"
        );
    }
    let progress = Progress::new(pending.len(), run_length(&manifest));
    let queue = Mutex::new(plan_queue(&exp.out, &manifest, &machine, &pending));
    let failures = Mutex::new(Vec::new());
    let csv_lock = Mutex::new(());
    std::thread::scope(|scope| {
        for _ in 0..exp.jobs.max(1) {
            scope.spawn(|| {
                loop {
                    if stop.load(Ordering::Relaxed) {
                        break;
                    }
                    let next = {
                        let mut q = queue
                            .lock()
                            .unwrap_or_else(std::sync::PoisonError::into_inner);
                        let left = deadline.map(|d| d.saturating_duration_since(Instant::now()));
                        queue::next(&mut q, left, exp.overrun)
                    };
                    let Some((pending, start)) = next else { break };
                    let run = pending.run;
                    let estimate = pending
                        .estimate
                        .map_or_else(|| "not yet measured".to_string(), minutes);
                    progress.log(&format!(
                        "run {} starts ({start:?}; estimated {estimate})",
                        run.stem()
                    ));
                    let context = RunContext {
                        exp,
                        manifest: &manifest,
                        machine: &machine,
                        commit: &commit,
                        endpoint: &planner.endpoint,
                        zenoh_config: &planner.zenoh_config,
                        progress: &progress,
                        deadline,
                        stop,
                    };
                    let outcome = run_one(&context, &run);
                    match outcome {
                        Ok(RunEnd::Finished) => {
                            let _guard = csv_lock.lock();
                            if let Err(e) = write_record(exp, &manifest, &run) {
                                progress
                                    .log(&format!("cannot write {}'s record: {e:#}", run.stem()));
                            }
                            if let Err(e) = collect_rows(&exp.out, &manifest)
                                .and_then(|rows| Ok(results::write_episodes(&episodes_csv, &rows)?))
                            {
                                progress.log(&format!("cannot update episodes.csv: {e:#}"));
                            }
                            // The finished run measured its method: re-estimate what is left.
                            let mut q = queue
                                .lock()
                                .unwrap_or_else(std::sync::PoisonError::into_inner);
                            let left: Vec<RunId> = q.iter().map(|p| p.run.clone()).collect();
                            *q = plan_queue(&exp.out, &manifest, &machine, &left);
                        }
                        Ok(RunEnd::Stopped) => {
                            let why = if stop.load(Ordering::Relaxed) {
                                "on request"
                            } else {
                                "at the budget's deadline"
                            };
                            progress.log(&format!(
                                "run {} stopped {why}; it resumes in a later sitting",
                                run.stem()
                            ));
                        }
                        Err(e) => {
                            progress.log(&format!("run {} failed: {e:#}", run.stem()));
                            failures
                                .lock()
                                .unwrap_or_else(std::sync::PoisonError::into_inner)
                                .push(format!("{}: {e:#}", run.stem()));
                        }
                    }
                }
            });
        }
    });
    progress.finish();
    let stopped = stop.load(Ordering::Relaxed);
    let left = queue
        .into_inner()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    // The queue hands out every run it starts: what it still holds never started.
    let started: Vec<RunId> = pending
        .iter()
        .filter(|run| !left.iter().any(|l| &l.run == *run))
        .cloned()
        .collect();
    for left in left {
        tracing::info!(
            run = %left.run.stem(),
            estimate = %left.estimate.map_or_else(|| "unknown".into(), minutes),
            "left for a later sitting: {}",
            if stopped {
                "the sitting was stopped"
            } else {
                "it does not fit the budget's remaining time"
            }
        );
    }
    // The daemon syncs its data when it stops; only then are the runs' folders complete.
    drop(planner);
    pack_unfinished_states(&exp.out, &manifest, &started)?;
    remove_finished_states(&exp.out, &manifest)?;
    let rows = collect_rows(&exp.out, &manifest)?;
    results::write_episodes(&episodes_csv, &rows)?;
    if stopped {
        tracing::info!(
            "stopped on request: every unfinished run kept its recorded episodes and a \
             resumable state; re-run the same command to continue"
        );
    }
    let failures = failures.into_inner().unwrap_or_default();
    if !failures.is_empty() {
        bail!(
            "{} run(s) failed (re-run the same command to retry them):\n  {}",
            failures.len(),
            failures.join("\n  ")
        );
    }
    Ok(rows)
}

/// Takes `<out>/logs/sitting.lock` exclusively for the sitting's life (the OS drops it when the
/// launcher dies, however it dies): two launchers on one folder would each start a bridge for
/// the same run and append to the same files. Fails at once, before anything is touched, if
/// another sitting holds it.
fn lock_sitting(out: &Path) -> Result<std::fs::File> {
    let logs = out.join("logs");
    std::fs::create_dir_all(&logs).with_context(|| format!("creating {}", logs.display()))?;
    let path = logs.join("sitting.lock");
    let file =
        std::fs::File::create(&path).with_context(|| format!("opening {}", path.display()))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => bail!(
            "another sitting is running in {} (it holds {}): wait for it to end, or stop it \
             with Ctrl-C or SIGTERM",
            out.display(),
            path.display()
        ),
        Err(std::fs::TryLockError::Error(e)) => {
            Err(e).with_context(|| format!("locking {}", path.display()))
        }
    }
}

/// Packs the resumable state of the unfinished runs this sitting `started`, and of any
/// unfinished run the daemon holds data for that has no packed state yet (a sitting that was
/// killed before it could pack). The daemon opens every run in its folder, and each opening
/// adds an ownership segment to the run's replay; repacking a run the sitting did not work on
/// would only rewrite its committed archive with nothing learnt.
fn pack_unfinished_states(dir: &Path, manifest: &Manifest, started: &[RunId]) -> Result<()> {
    for (run, done) in runs(dir, manifest) {
        if done {
            continue;
        }
        let archive = run.state_archive(dir);
        let daemon_dir = run.daemon_dir(dir, manifest.task);
        if (started.contains(&run) || !archive.exists())
            && daemon_dir.is_dir()
            && let Some(bytes) = resume_state::pack(&daemon_dir, &archive)
                .with_context(|| format!("packing {}", archive.display()))?
        {
            tracing::info!(
                run = %run.stem(),
                "resumable state: {} ({:.1} MB)",
                archive.display(),
                bytes as f64 / 1e6
            );
        }
    }
    Ok(())
}

/// Moves every finished run's daemon data to the data directory's archive before a sitting's
/// daemon starts: a daemon opens every run it finds under `runs/` (memory, and a retraining
/// for any whose last one a stop cut short), and a finished run has nothing left to learn.
/// The archive keeps the files whole for reading (`distance`, `planner-service runs export
/// --archived`). Called while no daemon serves the folder (the sitting's lock is held).
fn archive_finished_runs(dir: &Path, manifest: &Manifest) {
    let data_dir = dir.join("planner");
    for (run, done) in runs(dir, manifest) {
        if done && run.daemon_dir(dir, manifest.task).is_dir() {
            match admin::archive_run(&data_dir, &run.daemon_run(manifest.task)) {
                Ok(to) => tracing::info!(
                    run = %run.stem(),
                    "finished: its daemon data moved to {}",
                    to.display()
                ),
                // Only costs the daemon's memory and time: the sitting goes on.
                Err(e) => tracing::warn!(
                    run = %run.stem(),
                    "finished run's daemon data left served: {e}"
                ),
            }
        }
    }
}

/// Removes the packed state of every finished run (its episodes and record are what remain).
fn remove_finished_states(dir: &Path, manifest: &Manifest) -> Result<()> {
    for (run, done) in runs(dir, manifest) {
        let archive = run.state_archive(dir);
        if done && archive.exists() {
            std::fs::remove_file(&archive)
                .with_context(|| format!("removing {}", archive.display()))?;
        }
    }
    Ok(())
}

/// Writes a finished run's record beside its episodes, with the sittings its sittings file
/// kept (the file is then removed: the record holds them).
fn write_record(exp: &Experiment, manifest: &Manifest, run: &RunId) -> Result<()> {
    let rows = results::read_run_csv(&run.csv(&exp.out), exp.task.name(), &run.method, run.seed)?;
    let spec = std::fs::read_to_string(run.daemon_dir(&exp.out, exp.task).join("run.json"))
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok());
    let sittings_json = run.sittings_json(&exp.out);
    let record = RunRecord {
        task: exp.task.name().into(),
        method: run.method.clone(),
        seed: run.seed,
        scale: manifest.scale.name().into(),
        episodes: rows.len(),
        steps: rows.iter().map(|r| u64::from(r.steps)).sum(),
        spec,
        sittings: provenance::read_sittings(&sittings_json)
            .with_context(|| format!("reading {}", sittings_json.display()))?
            .sittings,
        finished: provenance::utc_now(),
        episode_wall_seconds: rows.iter().map(|r| r.wall_seconds).sum(),
    };
    record.save(&run.record_json(&exp.out))?;
    if sittings_json.exists() {
        std::fs::remove_file(&sittings_json)?;
    }
    Ok(())
}

/// What every run of a sitting shares.
struct RunContext<'a> {
    exp: &'a Experiment,
    manifest: &'a Manifest,
    /// Where the sitting runs, and the commit of its binaries (for each run's [`Sitting`]).
    machine: &'a Machine,
    commit: &'a str,
    endpoint: &'a str,
    /// The sitting's Zenoh file ([`write_sitting_config`]), for the bridges too.
    zenoh_config: &'a Path,
    progress: &'a Progress,
    deadline: Option<Instant>,
    /// Set when the sitting is asked to stop now.
    stop: &'a AtomicBool,
}

/// Runs one bridge to completion (or to the deadline), showing its episodes as they finish.
fn run_one(ctx: &RunContext<'_>, run: &RunId) -> Result<RunEnd> {
    let (exp, manifest, progress) = (ctx.exp, ctx.manifest, ctx.progress);
    let partial = run.partial_csv(&exp.out);
    let attempt = run.attempt_csv(&exp.out);
    // A launcher killed while a bridge ran left that bridge's rows unmerged.
    merge_attempt(&attempt, &partial)?;
    let before = results::recorded(&partial);
    let recorded = before.len();
    let recorded_steps: u64 = before.iter().map(|r| u64::from(r.steps)).sum();
    let log_path = exp.out.join("logs").join(format!("{}.log", run.stem()));
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .with_context(|| format!("opening {}", log_path.display()))?;
    let run_name = run.daemon_run(exp.task);
    // An `icem…` label attaches with its CEM preset; the optimiser is among the overrides.
    let preset = Method::parse(exp.task, &run.method)?.preset;
    let Some(left) = remaining_after(&before, manifest) else {
        // Every episode was recorded before the last launcher stopped.
        std::fs::rename(&partial, run.csv(&exp.out))?;
        return Ok(RunEnd::Finished);
    };
    if recorded > 0 {
        progress.log(&format!(
            "run {} resumes after {recorded} recorded episodes: {} to go",
            run.stem(),
            left.steps.map_or_else(
                || format!("{} episodes", left.episodes),
                |s| format!("{s} steps (at most {} episodes)", left.episodes)
            )
        ));
    }
    let (started, load_at_start) = (provenance::utc_now(), Load::now());
    let mut cmd = Command::new(exp.bin_dir.join("sim-bridge"));
    cmd.arg("run")
        .args([
            "--task",
            exp.task.name(),
            "--run",
            &run_name,
            "--agent",
            "bridge",
        ])
        .args(["--episodes", &left.episodes.to_string()])
        .args(["--seed", &run.seed.to_string()])
        .args(["--preset", &preset])
        .args(["--connect", ctx.endpoint])
        .arg("--zenoh-config")
        .arg(ctx.zenoh_config)
        // Sittings run at SCHED_IDLE beside other work, where a plan (or a retraining) can
        // wait minutes for a core: a slow answer is no failure here. A planner that dies is
        // still seen at once (the bridge watches its liveliness, and a dead process's loopback
        // link closes at once), and the budget bounds a sitting.
        .args(["--action-timeout", "3600"])
        .arg("--train-timeout")
        .arg(SITTING_RETRAIN.as_secs().to_string())
        .arg("--out")
        .arg(&attempt)
        .args(scale::bridge_flags(&manifest.overrides_for(&run.method)))
        .env("RUST_LOG", "info,zenoh=warn,mujoco=warn")
        .stdin(Stdio::null())
        .stdout(log.try_clone()?)
        .stderr(log);
    if let Some(steps) = left.steps {
        cmd.args(["--timesteps", &steps.to_string()]);
    }
    if let Some(deadline) = ctx.deadline {
        // The bridge stops between episodes by itself, before it resets the simulator, when
        // its next episode would end after the deadline (sim_bridge::deadline): a signal sent
        // on seeing an episode's row would usually arrive after the next episode had begun.
        let at = SystemTime::now() + deadline.saturating_duration_since(Instant::now());
        let at = at.duration_since(SystemTime::UNIX_EPOCH)?.as_secs();
        cmd.args(["--deadline", &at.to_string()]);
        // What the run's method has measured so far, for a planned episode after exploration.
        let cost = method_costs(&exp.out, manifest, ctx.machine)
            .get(&run.method)
            .copied();
        let episode_len = manifest.task.task().spec().episode_len;
        if let Some(planned) = queue::planned_episode(cost, episode_len) {
            cmd.args([
                "--planned-episode-seconds",
                &format!("{:.3}", planned.as_secs_f64()),
            ]);
        }
    }
    stop_with_launcher(&mut cmd);
    let mut child = Guard(
        cmd.spawn()
            .with_context(|| format!("starting {}", exp.bin_dir.join("sim-bridge").display()))?,
    );
    let bar = progress.start_run(&run.stem());
    progress.resumed(recorded, recorded_steps);
    let mut seen = 0;
    let mut steps = recorded_steps;
    let mut stopped = false;
    let status = loop {
        let status = child.0.try_wait()?;
        let done = results::count_rows(&attempt);
        if done > seen {
            let rows = results::read_run_csv(&attempt, exp.task.name(), &run.method, run.seed)
                .unwrap_or_default();
            for (index, row) in rows.iter().enumerate().skip(seen) {
                let count = recorded + index + 1;
                steps += u64::from(row.steps);
                progress.episode(&bar, &run.stem(), count, steps, row);
            }
            seen = done;
        }
        if let Some(status) = status {
            break status;
        }
        let asked = ctx.stop.load(Ordering::Relaxed);
        if !stopped && (asked || ctx.deadline.is_some_and(|d| Instant::now() >= d)) {
            // Asked to stop, or an episode the estimate did not foresee. SIGTERM: the bridge
            // tells the planner the open episode was interrupted.
            stopped = true;
            terminate(&child.0);
        }
        std::thread::sleep(Duration::from_millis(500));
    };
    progress.end_run(bar);
    let recorded_now =
        results::read_run_csv(&attempt, exp.task.name(), &run.method, run.seed).unwrap_or_default();
    if !recorded_now.is_empty() {
        // While the daemon still holds the run: what its networks ran on.
        let kernels = provenance::run_kernels(
            &exp.bin_dir.join("planner-service"),
            ctx.endpoint,
            &run_name,
        );
        let sitting = Sitting {
            machine: ctx.machine.clone(),
            binaries_commit: ctx.commit.to_string(),
            kernels,
            started,
            ended: provenance::utc_now(),
            load_at_start,
            load_at_end: Load::now(),
            episodes: recorded_now.iter().map(|r| r.episode).collect(),
        };
        let file = run.sittings_json(&exp.out);
        if let Err(e) = provenance::append_sitting(&file, sitting) {
            // The episodes are safe; only where they were recorded goes unsaid.
            progress.log(&format!("cannot add to {}: {e}", file.display()));
        }
    }
    merge_attempt(&attempt, &partial)?;
    let left = remaining_of(&partial, manifest);
    if stopped && left.is_some() {
        return Ok(RunEnd::Stopped);
    }
    if status.success() && left.is_some() && ctx.deadline.is_some() {
        // The bridge's only early stop: its next episode would have ended after the deadline.
        progress.log(&format!(
            "run {} stopped after this episode: its next would end after the budget's deadline",
            run.stem()
        ));
        return Ok(RunEnd::Stopped);
    }
    if !status.success() && left.is_some() {
        bail!(
            "sim-bridge exited with {status}; see {}",
            log_path.display()
        );
    }
    if left.is_some() {
        bail!(
            "sim-bridge finished with {} of {} episodes; see {}",
            results::count_rows(&partial),
            manifest.episodes,
            log_path.display()
        );
    }
    std::fs::rename(&partial, run.csv(&exp.out))?;
    Ok(RunEnd::Finished)
}

/// Sends SIGTERM to `child` (its clean stop).
fn terminate(child: &Child) {
    if let Ok(pid) = libc::pid_t::try_from(child.id()) {
        // SAFETY: kill with a pid of our own child and a valid signal touches no memory.
        unsafe {
            libc::kill(pid, libc::SIGTERM);
        }
    }
}

/// Appends the complete rows of a bridge's `attempt` file to the run's `partial` file (which
/// gets the attempt's header if it has none yet) and removes the attempt. A line the bridge
/// was cut off writing (no newline yet) is dropped.
fn merge_attempt(attempt: &Path, partial: &Path) -> Result<()> {
    let Ok(text) = std::fs::read_to_string(attempt) else {
        return Ok(());
    };
    let mut lines = text.split_inclusive('\n').filter(|l| l.ends_with('\n'));
    let Some(header) = lines.next() else {
        std::fs::remove_file(attempt)?;
        return Ok(());
    };
    let mut out = std::fs::read_to_string(partial).unwrap_or_default();
    if out.trim().is_empty() {
        out = header.to_string();
    }
    for line in lines.filter(|l| !l.trim().is_empty()) {
        out.push_str(line);
    }
    let tmp = partial.with_extension("partial.tmp");
    std::fs::write(&tmp, out).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, partial)?;
    std::fs::remove_file(attempt)?;
    Ok(())
}

/// Asks the kernel to send the child SIGTERM when the launcher dies, however it dies: a
/// launcher killed with SIGKILL runs no destructor, and an orphaned daemon would keep the lock
/// on `<out>/planner/` that the resumed experiment's daemon needs (SIGTERM is its clean
/// shutdown, which syncs the run's data). The child gets a process group of its own, so a
/// terminal's Ctrl-C reaches the launcher alone, which stops the bridges before the daemon.
fn stop_with_launcher(cmd: &mut Command) {
    use std::os::unix::process::CommandExt;
    cmd.process_group(0);
    // SAFETY: the closure runs in the forked child before exec and only makes one
    // async-signal-safe system call.
    unsafe {
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) == -1 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
}

/// A child process killed when dropped (a bridge whose launcher is going away).
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// The planner id of every sitting's daemon.
const PLANNER_ID: &str = "experiment";

/// The planner daemon of an experiment, stopped with SIGTERM (a clean shutdown that syncs its
/// data) when dropped.
pub struct Daemon {
    child: Child,
    pub endpoint: String,
    /// The Zenoh file the daemon started from, with the sitting's link lease.
    pub zenoh_config: PathBuf,
}

/// How long a silent peer of a sitting counts as alive: Zenoh's link lease (its default is
/// 10 s). Sittings run at `SCHED_IDLE` beside other work, and beside a build or a test run an
/// idle-priority process can go longer than 10 s without a core; with the default lease its
/// peers then close the link, the daemon's liveliness token vanishes and every bridge starts
/// the episode under way over (a cut-short episode in the run's training data). Every process
/// of a sitting is on loopback, where a process that dies closes its sockets at once, so the
/// long lease delays nothing but the verdict on a process that is alive and starved.
pub const SITTING_LINK_LEASE: Duration = Duration::from_secs(3600);

/// How long one retraining of a sitting may take, and how long a bridge waits for it. The
/// daemon's default budget (an hour) ends training early and plans with what it has, which
/// serves a live agent; an experiment must train the preset's full epochs however slow its
/// machine, or its results would depend on the load beside it (a PETS retraining on
/// half-cheetah can take hours on 2 starved cores).
pub const SITTING_RETRAIN: Duration = Duration::from_secs(86_400);

/// Writes the configuration every process of a sitting starts from into `dir`: the Zenoh file
/// (`zenoh.json5`, link lease [`SITTING_LINK_LEASE`]) for the daemon and the bridges, and the
/// daemon's `planner.toml` (that Zenoh file, retraining budget [`SITTING_RETRAIN`]). Returns
/// their paths, Zenoh file first.
///
/// # Errors
/// If a file cannot be written.
pub fn write_sitting_config(dir: &Path) -> Result<(PathBuf, PathBuf)> {
    let zenoh = dir.join("zenoh.json5");
    let lease_ms = SITTING_LINK_LEASE.as_millis();
    let link = serde_json::json!({ "transport": { "link": { "tx": { "lease": lease_ms } } } });
    std::fs::write(&zenoh, serde_json::to_string_pretty(&link)?)
        .with_context(|| format!("writing {}", zenoh.display()))?;
    let mut daemon = ServiceConfig {
        zenoh_config: Some(zenoh.clone()),
        ..ServiceConfig::default()
    };
    daemon.limits.max_retrain_seconds = SITTING_RETRAIN.as_secs_f64();
    let planner = dir.join("planner.toml");
    let text = toml::to_string(&daemon).context("writing the sitting's planner configuration")?;
    std::fs::write(&planner, text).with_context(|| format!("writing {}", planner.display()))?;
    Ok((zenoh, planner))
}

impl Daemon {
    /// Starts `planner-service serve` on a free loopback port, with the sitting's configuration
    /// ([`write_sitting_config`]) and its log written into `logs`, and waits until it serves.
    pub fn start(bin: &Path, data_dir: &Path, logs: &Path) -> Result<Self> {
        if !bin.exists() {
            bail!(
                "{} not found: build the binaries first (`cargo build --release --bins`), or point \
                 --bin-dir at them",
                bin.display()
            );
        }
        let log_path = &logs.join("planner.log");
        let (zenoh_config, config) = write_sitting_config(logs)?;
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .context("finding a free loopback port")?
            .port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let log = std::fs::File::create(log_path)
            .with_context(|| format!("creating {}", log_path.display()))?;
        let mut cmd = Command::new(bin);
        cmd.args(["serve", "--config"])
            .arg(&config)
            .args(["--listen", &endpoint, "--planner-id"])
            // One id for every sitting: the sitting lock keeps a folder to one daemon at a
            // time, and each id leaves its own `daemon-<id>.lock` in the data directory.
            .arg(PLANNER_ID)
            .arg("--data-dir")
            .arg(data_dir)
            .env("RUST_LOG", "info,zenoh=warn")
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log);
        stop_with_launcher(&mut cmd);
        let child = cmd
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        let mut daemon = Self {
            child,
            endpoint,
            zenoh_config,
        };
        daemon.wait_until_serving(log_path, Duration::from_secs(120))?;
        tracing::info!(endpoint = %daemon.endpoint, log = %log_path.display(), "planner daemon serving");
        Ok(daemon)
    }

    fn wait_until_serving(&mut self, log_path: &Path, timeout: Duration) -> Result<()> {
        let started = Instant::now();
        loop {
            let mut text = String::new();
            if let Ok(mut f) = std::fs::File::open(log_path) {
                let _ = f.read_to_string(&mut text);
            }
            if text.contains("planner serving") {
                return Ok(());
            }
            if let Some(status) = self.child.try_wait()? {
                bail!(
                    "the planner daemon exited ({status}) before serving; see {}",
                    log_path.display()
                );
            }
            if started.elapsed() > timeout {
                bail!(
                    "the planner daemon did not serve within {timeout:?}; see {}",
                    log_path.display()
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Ok(Some(_)) = self.child.try_wait() {
            return;
        }
        terminate(&self.child);
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(20) {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The folder of the running executable: where `cargo build` puts the sibling binaries.
pub fn default_bin_dir() -> Result<PathBuf> {
    let exe = std::env::current_exe().context("locating this executable")?;
    Ok(exe
        .parent()
        .context("the executable has no folder")?
        .to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A temporary experiment folder (with its `runs/`) of `cem` runs of `seeds`, 3 episodes.
    fn cem_folder(seeds: &[u64]) -> (tempfile::TempDir, Manifest) {
        let folder = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(folder.path().join("runs")).unwrap();
        (folder, manifest(&["cem"], seeds, 3))
    }

    fn cem_run(seed: u64) -> RunId {
        RunId {
            method: "cem".into(),
            seed,
        }
    }

    fn manifest(methods: &[&str], seeds: &[u64], episodes: u32) -> Manifest {
        Manifest::new(
            Builtin::Cartpole,
            Scale::Small,
            episodes,
            methods.iter().map(|m| m.to_string()).collect(),
            seeds.to_vec(),
            None,
        )
        .unwrap()
    }

    fn bridge_csv(returns: &[f64]) -> String {
        let mut text = format!("{}\n", sim_bridge::csv::HEADER);
        for (e, r) in returns.iter().enumerate() {
            text.push_str(&format!("{e},{r},200,1.0,200,10.0,2.0\n"));
        }
        text
    }

    fn machine(cpu_family_model: &str) -> Machine {
        Machine {
            hostname: "vm".into(),
            cpu_model: "AMD EPYC".into(),
            cpu_family_model: cpu_family_model.into(),
            logical_cpus: 2,
            cpu_path: "avx2-f32 scalar-f32".into(),
        }
    }

    fn sitting(on: &Machine, episodes: &[u32]) -> Sitting {
        let load = Load {
            load_average_1m: 1.0,
            sched_idle: true,
        };
        Sitting {
            machine: on.clone(),
            binaries_commit: "c0ffee".into(),
            kernels: None,
            started: "2026-11-29T08:00:00Z".into(),
            ended: "2026-11-29T09:00:00Z".into(),
            load_at_start: load.clone(),
            load_at_end: load,
            episodes: episodes.to_vec(),
        }
    }

    #[test]
    fn estimates_use_the_rate_this_cpu_measured_once_it_has() {
        let id = cem_run;
        let (folder, m) = cem_folder(&[0, 1, 2]);
        let dir = folder.path();
        let (fast, slow) = (machine("25/17"), machine("25/1"));
        // 200 planned steps per episode: 10 s each on the fast CPU, 40 s on the slow one.
        let csv = |wall: f64, n: u32| {
            let mut text = format!("{}\n", sim_bridge::csv::HEADER);
            for e in 0..n {
                text.push_str(&format!("{e},1.0,200,{wall},200,10.0,2.0\n"));
            }
            text
        };
        // Seed 0 finished on the fast CPU (its record keeps the sitting); seed 1 recorded two
        // episodes on the slow one (its sittings file); seed 2 has not started.
        std::fs::write(id(0).csv(dir), csv(10.0, 3)).unwrap();
        let record = serde_json::json!({ "sittings": [sitting(&fast, &[0, 1, 2])] });
        std::fs::write(id(0).record_json(dir), record.to_string()).unwrap();
        std::fs::write(id(1).partial_csv(dir), csv(40.0, 2)).unwrap();
        provenance::append_sitting(&id(1).sittings_json(dir), sitting(&slow, &[0, 1])).unwrap();

        let estimate_of_seed_2 = |on: &Machine| {
            plan_queue(dir, &m, on, &[id(1), id(2)])
                .into_iter()
                .find(|p| p.run.seed == 2)
                .and_then(|p| p.estimate)
                .map(|d| d.as_secs_f64())
                .unwrap()
        };
        // Three episodes of 200 steps at each CPU's own rate...
        assert!((estimate_of_seed_2(&slow) - 120.0).abs() < 1e-6);
        assert!((estimate_of_seed_2(&fast) - 30.0).abs() < 1e-6);
        // ...and on a CPU that has not run the method, every episode's: the median of three
        // episodes at 50 s per 1,000 steps and two at 200 s.
        let unseen = machine("6/143");
        assert!((estimate_of_seed_2(&unseen) - 30.0).abs() < 1e-6);
        // Seed 1's next episode is as long as its planned episodes took on the CPU that ran
        // them; on another CPU, one episode at the method's rate there.
        let seed_1 = |on: &Machine| plan_queue(dir, &m, on, &[id(1)]).remove(0);
        assert_eq!(seed_1(&slow).next_episode, Some(Duration::from_secs(40)));
        assert_eq!(seed_1(&fast).next_episode, Some(Duration::from_secs(10)));
        assert_eq!(seed_1(&unseen).next_episode, Some(Duration::from_secs(10)));
        assert!((seed_1(&fast).estimate.unwrap().as_secs_f64() - 10.0).abs() < 1e-6);
    }

    #[test]
    fn resume_skips_complete_runs_only() {
        let dir =
            std::env::temp_dir().join(format!("ebmpc-launcher-resume-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("runs")).unwrap();
        let m = manifest(&["cem", "cem+deen"], &[0, 1], 3);
        let id = |method: &str, seed| RunId {
            method: method.into(),
            seed,
        };
        // cem s0: complete. cem s1: only a partial file (interrupted). cem+deen s0: a .csv
        // with too few episodes (e.g. written by hand). cem+deen s1: nothing.
        std::fs::write(id("cem", 0).csv(&dir), bridge_csv(&[1.0, 2.0, 3.0])).unwrap();
        std::fs::write(id("cem", 1).partial_csv(&dir), bridge_csv(&[1.0, 2.0])).unwrap();
        std::fs::write(id("cem+deen", 0).csv(&dir), bridge_csv(&[5.0])).unwrap();
        let status: Vec<(String, bool)> = runs(&dir, &m)
            .into_iter()
            .map(|(r, done)| (r.stem(), done))
            .collect();
        assert_eq!(
            status,
            vec![
                ("cem-s0".to_string(), true),
                ("cem-s1".to_string(), false),
                ("cem-deen-s0".to_string(), false),
                ("cem-deen-s1".to_string(), false),
            ]
        );
        // Only complete runs reach episodes.csv.
        let rows = collect_rows(&dir, &m).unwrap();
        assert_eq!(rows.len(), 3);
        assert!(rows.iter().all(|r| r.method == "cem" && r.seed == 0));
        assert_eq!(rows[2].episode_return, 3.0);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A sitting's daemon should not open finished runs: their daemon data moves to the
    /// archive (kept whole), the unfinished runs' stays served, and a refusal to archive
    /// (a daemon still serving) leaves the data where it was without failing the sitting.
    #[test]
    fn finished_runs_daemon_data_is_archived_and_unfinished_runs_stay_served() {
        let id = cem_run;
        let (folder, m) = cem_folder(&[0, 1]);
        let dir = folder.path();
        std::fs::write(id(0).csv(dir), bridge_csv(&[1.0, 2.0, 3.0])).unwrap();
        std::fs::write(id(1).partial_csv(dir), bridge_csv(&[1.0])).unwrap();
        for seed in [0, 1] {
            let daemon_dir = id(seed).daemon_dir(dir, m.task);
            std::fs::create_dir_all(&daemon_dir).unwrap();
            std::fs::write(daemon_dir.join("replay.log"), [seed as u8; 10]).unwrap();
        }
        let data_dir = dir.join("planner");

        // A daemon serving the folder: nothing moves, and the sitting is not failed.
        let serving = admin::DaemonLock::acquire(&data_dir, "other").unwrap();
        archive_finished_runs(dir, &m);
        assert!(id(0).daemon_dir(dir, m.task).is_dir());
        drop(serving);

        archive_finished_runs(dir, &m);
        assert!(!id(0).daemon_dir(dir, m.task).exists());
        let archived = data_dir.join("archive").join(id(0).daemon_run(m.task));
        assert_eq!(
            std::fs::read(archived.join("replay.log")).unwrap(),
            [0u8; 10],
            "kept whole"
        );
        assert!(id(1).daemon_dir(dir, m.task).is_dir(), "unfinished: served");
        // A second sitting has nothing more to move.
        archive_finished_runs(dir, &m);
        assert!(archived.is_dir() && id(1).daemon_dir(dir, m.task).is_dir());
    }

    /// A sitting repacks the runs it worked on and packs a run that has daemon data but no
    /// packed state; a run it did not start keeps its packed state byte for byte, although
    /// the sitting's daemon opened it (and added to its replay).
    #[test]
    fn a_sitting_repacks_only_the_runs_it_started() {
        let id = cem_run;
        let (folder, m) = cem_folder(&[0, 1, 2]);
        let dir = folder.path();
        let replay = |seed| id(seed).daemon_dir(dir, m.task).join("replay.log");
        for seed in [0, 1, 2] {
            std::fs::write(id(seed).partial_csv(dir), bridge_csv(&[1.0])).unwrap();
            std::fs::create_dir_all(id(seed).daemon_dir(dir, m.task)).unwrap();
            std::fs::write(replay(seed), [seed as u8; 10]).unwrap();
        }
        // An earlier sitting packed seeds 0 and 1 (seed 2's state was never packed).
        for seed in [0, 1] {
            resume_state::pack(
                &id(seed).daemon_dir(dir, m.task),
                &id(seed).state_archive(dir),
            )
            .unwrap();
        }
        let packed = |seed: u64| std::fs::read(id(seed).state_archive(dir)).unwrap();
        let before = [packed(0), packed(1)];
        // This sitting's daemon opened all three; only seed 0 ran.
        for seed in [0, 1, 2] {
            let mut bytes = std::fs::read(replay(seed)).unwrap();
            bytes.extend([9u8; 4]);
            std::fs::write(replay(seed), bytes).unwrap();
        }
        pack_unfinished_states(dir, &m, &[id(0)]).unwrap();
        assert_ne!(packed(0), before[0], "the run it worked on is repacked");
        assert_eq!(
            packed(1),
            before[1],
            "a run it did not start is left as it was"
        );
        assert!(
            id(2).state_archive(dir).is_file(),
            "a run with data and no packed state is packed"
        );
    }

    #[test]
    fn prepare_refuses_unknown_methods_and_a_different_experiment() {
        let dir =
            std::env::temp_dir().join(format!("ebmpc-launcher-prepare-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut exp = Experiment {
            task: Builtin::Cartpole,
            methods: vec!["cem".into()],
            seeds: vec![0],
            episodes: 2,
            scale: Scale::Small,
            out: dir.clone(),
            jobs: 1,
            bin_dir: dir.clone(),
            population: None,
            timesteps: None,
            energy_noise_sigma: None,
            energy_noise_units: None,
            exploration_episodes: None,
            budget: None,
            overrun: false,
        };
        let first = prepare(&exp).unwrap();
        assert_eq!(first.methods, vec!["cem"]);
        // Other settings of the same runs are another experiment.
        exp.exploration_episodes = Some(2);
        let err = prepare(&exp).unwrap_err();
        assert!(format!("{err:#}").contains("overrides"), "{err:#}");
        exp.exploration_episodes = None;
        exp.methods = vec!["cem+deen".into()];
        exp.seeds = vec![1];
        let merged = prepare(&exp).unwrap();
        assert_eq!((merged.methods.len(), merged.seeds.len()), (2, 2));
        // The folder holds four runs now; this command asks for one of them, and a finished
        // run is never asked for again.
        let mut all = runs(&exp.out, &merged);
        assert_eq!(all.len(), 4);
        let asked = asked_and_unfinished(&all, &exp);
        assert_eq!(asked.len(), 1);
        assert_eq!((asked[0].method.as_str(), asked[0].seed), ("cem+deen", 1));
        for (run, done) in &mut all {
            *done = run.method == "cem+deen";
        }
        assert!(asked_and_unfinished(&all, &exp).is_empty());
        exp.methods = vec!["cem".into(), "cem+deen".into()];
        exp.seeds = vec![0, 1];
        assert_eq!(asked_and_unfinished(&all, &exp).len(), 2, "both cem runs");
        exp.seeds = vec![1];
        exp.methods = vec!["sgd".into()];
        assert!(prepare(&exp).is_err());
        exp.methods = vec!["cem".into(), "adam+dae".into()];
        exp.population = Some(250);
        let err = prepare(&exp).unwrap_err();
        assert!(format!("{err:#}").contains("adam+dae"), "{err:#}");
        exp.population = None;
        exp.methods = vec!["cem".into()];
        exp.scale = Scale::Paper;
        let err = prepare(&exp).unwrap_err();
        assert!(format!("{err:#}").contains("scale"), "{err:#}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
