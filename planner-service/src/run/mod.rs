//! A run: one learning process with its task, preset, replay buffer and models, fed by one or
//! more agents and retrained by its own trainer task.

pub mod stats;

use crate::agent::{Accepted, AgentSession};
use crate::config::Preset;
use crate::models::Models;
use crate::persist::{PersistError, RunDir};
use crate::replay::{
    self, EpisodeSummary, LogFile, OwnerCheck, Record, ReplayBuffer, ReplayError, TransitionRecord,
};
use crate::sched::background::run_in_background;
use crate::trainer::{TrainError, TrainLimits, TrainReport, retrain};
use proto::{
    EpisodeEnd, ErrorCode, ErrorReport, Observation, RunEventKind, RunSpec, Task, TrainMode,
};
pub use stats::RunHistograms;
use stats::{LastRetraining, Latency, LatencyWindow, PlanRecord, PlanTally};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use tokio::sync::{Notify, watch};

/// Where a run reports what happens to it (the service publishes these on the run's events key).
pub type EventSink = Arc<dyn Fn(&str, RunEventKind) + Send + Sync>;

/// What the daemon hosting a run gives it: where its events go and how its training is
/// bounded (time per retraining, the cancel flag raised at shutdown).
#[derive(Clone)]
pub struct Hosting {
    pub events: EventSink,
    pub train_limits: TrainLimits,
    /// Most transitions the run's replay buffer keeps (`[storage] replay_capacity`).
    pub replay_capacity: Option<usize>,
    /// The replay byte budgets every run of the daemon shares (`[storage]`).
    pub replay_budget: Arc<ReplayBudget>,
    /// How the run's replay log reaches its file.
    pub log_disk: LogDisk,
    /// Where the run times its replay log's fsyncs and its retrainings (the daemon's metrics
    /// registry serves them).
    pub histograms: RunHistograms,
    /// Acknowledge a step only once it is on stable storage (`[storage] sync_every_step`):
    /// every store is followed by a group commit ([`crate::replay::LogSyncer::sync_through`]).
    pub sync_every_step: bool,
    /// Other planners share the run's directory (a fleet): a newer owner may read this
    /// term's replay segment, so nothing is ever cut from it (see
    /// [`crate::replay::ReplayLog::share`]).
    pub shared_dir: bool,
    /// Whether this planner still owns run `run` at fencing token `token` (its lease valid by
    /// its own clock): asked before a superseded replay segment is removed.
    pub still_owner: StillOwner,
}

/// Whether this planner still owns a run (by name) at a fencing token.
pub type StillOwner = Arc<dyn Fn(&str, u64) -> bool + Send + Sync>;

/// The daemon's replay byte budgets: each run's log at most `per_run` bytes, all runs' logs
/// together at most `total` (a run's replay in memory is about its log's size, so these bound
/// memory and disk alike). At a budget a run refuses every observation that would store
/// something, with an error naming the budget and its setting.
#[derive(Debug)]
pub struct ReplayBudget {
    pub per_run: u64,
    pub total: u64,
    /// Bytes of the logs of every open run.
    used: std::sync::atomic::AtomicU64,
}

impl ReplayBudget {
    pub fn new(per_run: u64, total: u64) -> Self {
        Self {
            per_run,
            total,
            used: std::sync::atomic::AtomicU64::new(0),
        }
    }

    /// No budget: for tests and experiments.
    pub fn unbounded() -> Self {
        Self::new(u64::MAX, u64::MAX)
    }

    /// Bytes of the logs of every open run.
    pub fn used(&self) -> u64 {
        self.used.load(Ordering::SeqCst)
    }

    /// A run's log went from `from` to `to` bytes.
    fn moved(&self, from: u64, to: u64) {
        if to >= from {
            self.used.fetch_add(to - from, Ordering::SeqCst);
        } else {
            self.used.fetch_sub(from - to, Ordering::SeqCst);
        }
    }

    /// Refuses a store into run `run`, whose log holds `run_bytes`, when a budget is reached.
    fn check(&self, run: &str, run_bytes: u64) -> Result<(), String> {
        if run_bytes >= self.per_run {
            return Err(format!(
                "run `{run}` holds {run_bytes} bytes of replay, its budget of {} bytes ([storage] max_run_replay_bytes): nothing more is stored; the operator raises the budget or sets [storage] replay_capacity (the oldest episodes are then evicted)",
                self.per_run
            ));
        }
        let used = self.used();
        if used >= self.total {
            return Err(format!(
                "this planner's runs hold {used} bytes of replay, its budget of {} bytes ([storage] max_total_replay_bytes): nothing more is stored; the operator raises the budget, sets [storage] replay_capacity, or archives runs",
                self.total
            ));
        }
        Ok(())
    }
}

/// How each run's replay log reaches the disk: straight to its file (the daemon), or through
/// a wrapper chosen per run name (tests give one run a disk that fails or blocks, and check
/// that the others are served meanwhile).
#[derive(Clone)]
pub struct LogDisk(Arc<OpenLog>);

/// Gives run `run`'s opened log file what its writes go through.
type OpenLog = dyn Fn(&str, std::fs::File) -> Box<dyn LogFile> + Send + Sync;

impl LogDisk {
    /// Every log writes straight to its file.
    pub fn direct() -> Self {
        Self(Arc::new(|_: &str, file| Box::new(file)))
    }

    /// Run `run`'s log writes through `wrap(run, file)`.
    pub fn wrapped(
        wrap: impl Fn(&str, std::fs::File) -> Box<dyn LogFile> + Send + Sync + 'static,
    ) -> Self {
        Self(Arc::new(wrap))
    }

    fn open(&self, run: &str, file: std::fs::File) -> Box<dyn LogFile> {
        (self.0)(run, file)
    }
}

impl Default for LogDisk {
    fn default() -> Self {
        Self::direct()
    }
}

impl std::fmt::Debug for LogDisk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LogDisk")
    }
}

/// One run.
pub struct Run {
    name: String,
    spec: RunSpec,
    preset: Preset,
    task: &'static Task,
    buffer: Mutex<ReplayBuffer>,
    models: RwLock<Arc<Models>>,
    /// Finished (not interrupted) episodes stored.
    episodes_stored: AtomicU32,
    /// Finished episodes the models in use were trained on; sync-mode agents wait on it.
    trained_through: watch::Sender<u32>,
    training: AtomicBool,
    wake_trainer: Notify,
    hosting: Hosting,
    latencies: Mutex<LatencyWindow>,
    plan_tally: Mutex<PlanTally>,
    /// The last retraining that produced models (`None` until one did here).
    last_retraining: Mutex<Option<LastRetraining>>,
    /// What `status` reports of the buffer, kept apart from it so a report never waits for a
    /// buffer busy writing to disk.
    tally: Mutex<Tally>,
    /// The next episode number of every agent that ended one, kept apart from the buffer for
    /// the same reason: attach asks for it while holding the service's table of runs.
    next_episodes: Mutex<HashMap<String, u32>>,
    /// Where checkpoints go (`None`: the run lives in memory only).
    dir: Option<RunDir>,
    /// The ownership epoch this planner holds the run at (see `crate::fleet`).
    epoch: u64,
    /// What could not be read from the replay log when the run was opened.
    replay_damage: Option<String>,
}

/// The counters of a run's buffer that `status` reports.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Tally {
    /// Finished (not interrupted) episodes.
    pub episodes: u32,
    pub transitions: usize,
    /// Bytes of the replay log file.
    pub log_bytes: u64,
    /// The last [`Tally::RETURNS`] finished episodes: agent, episode, return; oldest first.
    pub last_returns: Vec<(String, u32, f32)>,
}

impl Tally {
    /// Finished episodes whose returns are kept.
    pub const RETURNS: usize = 10;

    fn finished(&mut self, agent: &str, episode: u32, episode_return: f32) {
        self.episodes += 1;
        if self.last_returns.len() == Self::RETURNS {
            self.last_returns.remove(0);
        }
        self.last_returns
            .push((agent.to_string(), episode, episode_return));
    }
}

/// What storing an accepted observation leaves for the caller to do.
#[derive(Debug, Default)]
pub struct Stored {
    /// The episode finished: the number of finished episodes a sync-mode agent must see
    /// trained before its next episode.
    pub must_cover: Option<u32>,
}

/// Why a stored or new run could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("replay buffer: {0}")]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Persist(#[from] PersistError),
}

impl OpenError {
    /// Whether the failure may pass by itself (an I/O error: a disk or a mount briefly gone),
    /// so that opening is worth trying again; damaged or foreign data is not.
    pub fn is_transient(&self) -> bool {
        let transient = |e: &std::io::Error| {
            !matches!(
                e.kind(),
                std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof
            )
        };
        match self {
            OpenError::Replay(ReplayError::Log(replay::LogError::Io { source, .. })) => {
                transient(source)
            }
            OpenError::Persist(PersistError::Io { source, .. }) => transient(source),
            _ => false,
        }
    }
}

/// Why an observation's results could not be stored.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A replay budget is reached (the message names it): nothing was stored.
    #[error("{0}")]
    Budget(String),
    #[error("replay buffer: {0}")]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Fenced(#[from] Fenced),
    #[error("the storing task failed: {0}")]
    Task(String),
}

/// Why an agent's observation was refused.
#[derive(Debug)]
pub enum Refused {
    /// Out of order, or not stored (a full disk): the agent is told why and may send again.
    Step(ErrorReport),
    /// This planner lost the run to another: nothing was stored, the planner steps down and
    /// the agent must attach again (to the new owner).
    Fenced(Fenced),
}

/// This planner no longer owns the run: another took it over at a newer epoch (or its epoch
/// cannot be read, which is treated the same: never write without knowing).
#[derive(Debug, thiserror::Error)]
#[error(
    "run `{run}` was taken over by another planner (this planner holds epoch {held}, the run is at {})",
    .current.map_or_else(|| "an unreadable epoch".to_string(), |e| format!("epoch {e}"))
)]
pub struct Fenced {
    pub run: String,
    pub held: u64,
    /// The run's current epoch; `None` if it could not be read.
    pub current: Option<u64>,
}

/// Records in `next_episodes` that `agent` ended `episode` (its next one is numbered after).
fn ended(next_episodes: &mut HashMap<String, u32>, agent: &str, episode: u32) {
    let next = next_episodes.entry(agent.to_string()).or_default();
    *next = (*next).max(episode.saturating_add(1));
}

impl Drop for Run {
    /// A closed run's log no longer counts against the daemon's total replay budget.
    fn drop(&mut self) {
        let bytes = self
            .tally
            .get_mut()
            .unwrap_or_else(PoisonError::into_inner)
            .log_bytes;
        self.hosting.replay_budget.moved(bytes, 0);
    }
}

impl std::fmt::Debug for Run {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Run")
            .field("name", &self.name)
            .field("task", &self.task.name())
            .finish_non_exhaustive()
    }
}

impl Run {
    /// Opens the run stored in `dir`, or starts it there, as its owner at `epoch` (already
    /// claimed in `dir` by `planner`): recovers its replay buffer (cutting a torn tail,
    /// skipping records of fenced owners), records the claim in it, bounds it to
    /// `replay_capacity` transitions if given, loads the newest usable checkpoint and records
    /// its spec. If the buffer holds finished episodes the models were not trained on, the
    /// trainer is woken at once so the models catch up with the data.
    pub fn open(
        name: String,
        spec: RunSpec,
        preset: Preset,
        dir: RunDir,
        hosting: Hosting,
        (epoch, planner): (u64, &str),
    ) -> Result<Arc<Self>, OpenError> {
        let task = preset.task;
        let disk = hosting.log_disk.clone();
        let still_owner = {
            let (check, run) = (hosting.still_owner.clone(), name.clone());
            OwnerCheck(Arc::new(move || check(&run, epoch)))
        };
        let term = replay::Term {
            token: epoch,
            planner,
            still_owner,
        };
        let mut buffer =
            ReplayBuffer::open_with(dir.root(), task, term, |file| disk.open(&name, file))?;
        if hosting.shared_dir {
            buffer.share_log();
        }
        buffer.set_capacity(hosting.replay_capacity)?;
        buffer.compact_if_due()?;
        let mut models = match dir.load_models(task, &preset)? {
            Some(models) => models,
            None => Models::untrained(task, &preset, spec.seed),
        };
        models.set_inference_precision(preset.inference_precision);
        models.pack_for_inference();
        // Only a run whose models could be built is recorded: a stored spec is re-opened at
        // every start, so one that cannot be built must never reach the disk.
        dir.write_spec(&spec)?;
        tracing::info!(
            run = %name,
            transitions = buffer.len(),
            episodes = buffer.episodes().len(),
            models_version = models.version,
            epoch,
            path = %dir.root().display(),
            "run opened"
        );
        Ok(Self::with_state(
            name,
            spec,
            preset,
            buffer,
            models,
            Some(dir),
            hosting,
        ))
    }

    fn with_state(
        name: String,
        spec: RunSpec,
        preset: Preset,
        buffer: ReplayBuffer,
        models: Models,
        dir: Option<RunDir>,
        hosting: Hosting,
    ) -> Arc<Self> {
        let task = preset.task;
        let stored = buffer
            .episodes()
            .iter()
            .filter(|e| e.end != EpisodeEnd::Interrupted)
            .count() as u32;
        let covered = models.episodes_covered;
        let epoch = buffer.epoch();
        let replay_damage = buffer.damage().map(str::to_string);
        let mut tally = Tally {
            transitions: buffer.len(),
            log_bytes: buffer.log_bytes(),
            ..Tally::default()
        };
        hosting.replay_budget.moved(0, tally.log_bytes);
        let mut next_episodes = HashMap::new();
        for e in buffer.episodes() {
            if e.end != EpisodeEnd::Interrupted {
                tally.finished(&e.agent, e.episode, e.episode_return);
            }
            ended(&mut next_episodes, &e.agent, e.episode);
        }
        let run = Arc::new(Self {
            name,
            spec,
            preset,
            task,
            buffer: Mutex::new(buffer),
            models: RwLock::new(Arc::new(models)),
            episodes_stored: AtomicU32::new(stored),
            trained_through: watch::Sender::new(covered),
            training: AtomicBool::new(false),
            wake_trainer: Notify::new(),
            hosting,
            latencies: Mutex::new(LatencyWindow::default()),
            plan_tally: Mutex::new(PlanTally::default()),
            last_retraining: Mutex::new(None),
            tally: Mutex::new(tally),
            next_episodes: Mutex::new(next_episodes),
            dir,
            epoch,
            replay_damage,
        });
        if stored > covered {
            run.wake_trainer.notify_one();
        }
        run
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn spec(&self) -> &RunSpec {
        &self.spec
    }

    pub fn preset(&self) -> &Preset {
        &self.preset
    }

    pub fn task(&self) -> &'static Task {
        self.task
    }

    pub fn mode(&self) -> TrainMode {
        self.spec.mode
    }

    /// The ownership epoch this planner holds the run at.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Checks on disk that this planner still owns the run: no other planner has claimed a
    /// newer epoch. Done before anything is written at episode boundaries and before a
    /// checkpoint, so a planner that lost the run (partitioned, paused) stops writing at the
    /// next boundary at the latest. A run in memory only is never fenced.
    pub fn check_owner(&self) -> Result<(), Fenced> {
        let Some(dir) = &self.dir else { return Ok(()) };
        let fenced = |current| Fenced {
            run: self.name.clone(),
            held: self.epoch,
            current,
        };
        match dir.current_epoch() {
            Ok(current) if current == self.epoch => Ok(()),
            Ok(current) => Err(fenced(Some(current))),
            Err(e) => {
                tracing::error!(run = %self.name, error = %e, "cannot read the run's ownership epoch");
                Err(fenced(None))
            }
        }
    }

    /// The models in use now.
    pub fn models(&self) -> Arc<Models> {
        self.models
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    pub fn episodes_stored(&self) -> u32 {
        self.episodes_stored.load(Ordering::SeqCst)
    }

    /// What `status` reports of the buffer, without touching the buffer.
    pub fn tally(&self) -> Tally {
        self.tally
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    pub fn is_training(&self) -> bool {
        self.training.load(Ordering::SeqCst)
    }

    /// The next episode number for `agent` (runs resumed after a restart continue numbering),
    /// without touching the buffer.
    pub fn next_episode(&self, agent: &str) -> u32 {
        self.lock_next_episodes().get(agent).copied().unwrap_or(0)
    }

    fn lock_next_episodes(&self) -> std::sync::MutexGuard<'_, HashMap<String, u32>> {
        self.next_episodes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Records a planned action: how long it took, and what it adds to the plan tally.
    pub fn record_plan(&self, ms: f32, plan: PlanRecord) {
        self.latencies
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .record(ms);
        self.plan_tally
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .record(plan);
    }

    /// Records how long a sync of the run's log took (`None`: the run is in memory only).
    fn observe_fsync(&self, took: Option<std::time::Duration>) {
        if let Some(took) = took {
            self.hosting
                .histograms
                .fsync_seconds
                .observe(took.as_secs_f64());
        }
    }

    /// What could not be read from the replay log when the run was opened (`None`: nothing).
    pub fn replay_damage(&self) -> Option<&str> {
        self.replay_damage.as_deref()
    }

    /// The histograms this run records its fsyncs and retrainings in.
    pub fn histograms(&self) -> &RunHistograms {
        &self.hosting.histograms
    }

    /// The last retraining that produced models here, `None` before one did.
    pub fn last_retraining(&self) -> Option<LastRetraining> {
        *self
            .last_retraining
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// How this run's plans went against its deadline.
    pub fn plan_tally(&self) -> PlanTally {
        *self
            .plan_tally
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Planning latency percentiles of the recent planned actions.
    pub fn latency(&self) -> Option<Latency> {
        self.latencies
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .percentiles()
    }

    /// Whether actions are still uniformly random: during the exploration episodes and steps
    /// (both must be reached), and for as long as no model has been trained.
    pub fn exploring(&self) -> bool {
        self.episodes_stored() < self.preset.exploration_episodes
            || self.short_of_exploration_steps()
            || !self.models().is_trained()
    }

    /// Whether fewer transitions than the preset's `exploration_steps` are stored.
    fn short_of_exploration_steps(&self) -> bool {
        (self.lock_tally().transitions as u64) < self.preset.exploration_steps
    }

    /// Records the log's new size in the tally and in the daemon's replay budget.
    fn set_log_bytes(&self, tally: &mut Tally, bytes: u64) {
        self.hosting.replay_budget.moved(tally.log_bytes, bytes);
        tally.log_bytes = bytes;
    }

    fn lock_tally(&self) -> std::sync::MutexGuard<'_, Tally> {
        self.tally.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Compacts the replay log if evictions made it due, holding the buffer's lock only to
    /// start and to swap files (never across the copy or its fsyncs). A failure leaves the log
    /// as it was, every record in it: it is logged, and the next episode end tries again.
    /// Blocking: called on the blocking pool.
    fn compact_log(&self) {
        if let Err(e) = replay::compact_log(|| self.lock_buffer()) {
            tracing::warn!(run = %self.name, error = %e, "cannot compact the replay log; it keeps every record and is compacted later");
        }
        // A compaction shrinks the file: the reported size follows at once.
        let buffer = self.lock_buffer();
        self.set_log_bytes(&mut self.lock_tally(), buffer.log_bytes());
    }

    fn lock_buffer(&self) -> std::sync::MutexGuard<'_, ReplayBuffer> {
        self.buffer.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Takes a validated observation from `session`'s agent: checks that it follows on, stores
    /// what it completes (syncing an episode's end to disk), and only then moves the session
    /// on. The store and the sync run on the blocking pool, so a slow or stuck disk holds this
    /// run's agents only, never a thread that serves other runs; the caller acknowledges the
    /// observation (answers it) only once this returns. If the store fails (a full disk) the
    /// agent gets a [`ErrorCode::Storage`] error and its session stays where it was, so it can
    /// send the same observation again once the disk has room. If this planner lost the run,
    /// nothing is stored and [`Refused::Fenced`] says so.
    pub async fn accept(
        self: &Arc<Self>,
        session: &mut AgentSession,
        msg: &Observation,
    ) -> Result<(Accepted, Stored), Refused> {
        let mut next = session.clone();
        let accepted = next.observe(msg).map_err(Refused::Step)?;
        let run = self.clone();
        let agent = session.name().to_string();
        let (episode, step, next_obs) = (msg.episode, msg.step, msg.obs.clone());
        let joined = tokio::task::spawn_blocking(move || {
            let stored = run.store(&agent, episode, step, &next_obs, &accepted);
            (accepted, stored)
        })
        .await;
        let (accepted, stored) = joined.map_err(|e| {
            Refused::Step(
                ErrorReport::new(
                    ErrorCode::Internal,
                    format!("storing this step failed: {e}"),
                )
                .at(msg.episode, msg.step),
            )
        })?;
        let stored = stored.map_err(|e| match e {
            StoreError::Fenced(fenced) => Refused::Fenced(fenced),
            StoreError::Budget(message) => Refused::Step(
                ErrorReport::new(ErrorCode::Refused, message).at(msg.episode, msg.step),
            ),
            e => {
                tracing::error!(run = %self.name, agent = %session.name(), error = %e, "cannot store a transition; the step is refused");
                Refused::Step(
                    ErrorReport::new(
                        ErrorCode::Storage,
                        format!("the planner could not store this step, send it again later: {e}"),
                    )
                    .at(msg.episode, msg.step),
                )
            }
        })?;
        *session = next;
        Ok((accepted, stored))
    }

    /// Stores what an accepted observation produced — an episode it abandoned, its
    /// transition (with `next_obs`), the episode it finished — in one append, so that either
    /// all of it is stored or none, and syncs the log to disk when an episode ended (a failed
    /// sync stores none of it: [`ErrorCode::Storage`] to the agent). At episode boundaries (a start, an end) it first checks that this
    /// planner still owns the run, and stores nothing if not. Blocking: called on the
    /// blocking pool.
    fn store(
        &self,
        agent: &str,
        episode: u32,
        step: u32,
        next_obs: &[f32],
        accepted: &Accepted,
    ) -> Result<Stored, StoreError> {
        if accepted.transition.is_none() || accepted.finished.is_some() {
            self.check_owner()?;
        }

        let mut records = Vec::with_capacity(3);
        if let Some(abandoned) = &accepted.abandoned {
            records.push(Record::from(abandoned.clone()));
        }
        if let Some((obs, act, origin, reward)) = &accepted.transition {
            records.push(Record::Transition(TransitionRecord {
                epoch: self.epoch,
                agent: agent.to_string(),
                episode,
                step: step - 1,
                obs: obs.clone(),
                act: act.clone(),
                origin: *origin,
                next_obs: next_obs.to_vec(),
                reward: *reward,
            }));
        }
        if let Some(finished) = &accepted.finished {
            records.push(Record::from(finished.clone()));
        }
        if !records.is_empty() {
            let run_bytes = self.lock_tally().log_bytes;
            self.hosting
                .replay_budget
                .check(&self.name, run_bytes)
                .map_err(StoreError::Budget)?;
        }
        let mut buffer = self.lock_buffer();
        // With `sync_every_step`, this store is durable before it is acknowledged: the
        // appends so far (this one among them) are synced in a group commit below, after the
        // buffer's lock is released, so the agents storing at the same moment share one sync.
        // Otherwise every episode end, finished or abandoned, is synced to disk before it
        // counts, under the buffer's lock: a failed sync then takes back exactly this step's
        // records (no other agent of the run appended meanwhile), and the agent is refused
        // with a storage error and sends the step again. Only this run's agents wait for it.
        let episode_end = accepted.finished.is_some() || accepted.abandoned.is_some();
        if episode_end && !self.hosting.sync_every_step {
            let took = buffer.append_synced(records)?;
            self.observe_fsync(took);
        } else {
            buffer.append(records)?;
        }
        let durable = self
            .hosting
            .sync_every_step
            .then(|| buffer.syncer().map(|s| (s.appended(), s)))
            .flatten();
        // Capacity may have evicted old transitions: the tally follows the buffer's length,
        // set under the buffer's lock (the order is always buffer, then tally) so that two
        // agents' appends cannot leave it at the earlier one's length. A finished episode is
        // counted in the same step, so that `status` never shows an episode's last
        // transition without its end.
        {
            let mut tally = self.lock_tally();
            tally.transitions = buffer.len();
            self.set_log_bytes(&mut tally, buffer.log_bytes());
            if let Some(finished) = &accepted.finished {
                tally.finished(agent, finished.episode, finished.episode_return);
            }
        }
        drop(buffer);
        if let Some((appends, syncer)) = &durable {
            let started = std::time::Instant::now();
            let synced = syncer.sync_through(*appends);
            self.observe_fsync(Some(started.elapsed()));
            synced.map_err(ReplayError::from)?;
        }
        self.compact_log();
        for summary in [&accepted.abandoned, &accepted.finished]
            .into_iter()
            .flatten()
        {
            ended(&mut self.lock_next_episodes(), agent, summary.episode);
        }
        let Some(finished) = &accepted.finished else {
            return Ok(Stored { must_cover: None });
        };
        let stored = self.episodes_stored.fetch_add(1, Ordering::SeqCst) + 1;
        self.emit(RunEventKind::EpisodeFinished {
            agent: agent.to_string(),
            episode: finished.episode,
            episode_return: finished.episode_return,
            steps: finished.steps,
            end: finished.end,
        });
        self.wake_trainer.notify_one();
        Ok(Stored {
            must_cover: Some(stored),
        })
    }

    /// Records an episode that an agent left unfinished (it vanished or detached) and syncs
    /// it to disk, on the blocking pool, unless this planner no longer owns the run (the new
    /// owner records it when it reads the log).
    pub async fn store_interrupted(
        self: &Arc<Self>,
        summary: EpisodeSummary,
    ) -> Result<(), StoreError> {
        let run = self.clone();
        tokio::task::spawn_blocking(move || {
            run.check_owner()?;
            let (agent, episode) = (summary.agent.clone(), summary.episode);
            let mut buffer = run.lock_buffer();
            let took = buffer.append_synced(vec![Record::from(summary)])?;
            run.observe_fsync(took);
            run.set_log_bytes(&mut run.lock_tally(), buffer.log_bytes());
            drop(buffer);
            run.compact_log();
            ended(&mut run.lock_next_episodes(), &agent, episode);
            Ok(())
        })
        .await
        .map_err(|e| StoreError::Task(e.to_string()))?
    }

    /// Waits until the models in use were trained on at least `episodes` finished episodes.
    pub async fn wait_for_training(&self, episodes: u32) {
        let mut rx = self.trained_through.subscribe();
        // The sender lives as long as `self`, so this cannot fail while we hold `&self`.
        let _ = rx.wait_for(|&trained| trained >= episodes).await;
    }

    fn emit(&self, kind: RunEventKind) {
        (self.hosting.events)(&self.name, kind);
    }

    /// The trainer: retrains whenever episodes were stored since the last training, until the
    /// run is dropped by the service (the task is aborted then).
    pub async fn trainer_loop(self: Arc<Self>) {
        loop {
            self.wake_trainer.notified().await;
            let episodes = self.episodes_stored();
            if episodes <= *self.trained_through.borrow() {
                continue;
            }
            if self.short_of_exploration_steps() {
                // Models trained now would not be used: actions stay random until the
                // exploration steps are stored. Agents waiting for these episodes go on.
                self.trained_through.send_replace(episodes);
                continue;
            }
            self.training.store(true, Ordering::SeqCst);
            let current = self.models();
            let preset = self.preset.clone();
            let seed = self.spec.seed;
            let limits = self.hosting.train_limits.clone();
            // The snapshot waits for the buffer, which may be busy writing to a slow disk: on
            // the blocking pool that holds this run's trainer only. It and the checkpoint hold
            // locks the serving path takes, so they run at normal priority; only the fit runs
            // on the background pool, below every plan (see `sched::background`).
            let snapshot = {
                let run = self.clone();
                tokio::task::spawn_blocking(move || run.lock_buffer().transitions().clone())
            };
            let outcome = match snapshot.await {
                Err(e) => Err(format!("cannot take the buffer's snapshot: {e}")),
                Ok(data) => {
                    self.emit(RunEventKind::TrainingStarted {
                        transitions: data.len() as u64,
                    });
                    run_in_background(move || {
                        retrain(&current, &data, &preset, episodes, seed, &limits)
                    })
                    .await
                    .map_err(|e| format!("training failed: {e}"))
                }
            };
            let outcome = match outcome {
                // Checkpoint before the swap: models in use are always on disk too, so a
                // restart never plans with models older than the ones agents last saw. Only
                // finite models get here: `retrain` refuses the others.
                Ok(Ok((models, report))) => self
                    .clone()
                    .write_checkpoint(models)
                    .await
                    .map(|models| Ok((models, report))),
                other => other,
            };
            self.training.store(false, Ordering::SeqCst);
            let failure = match outcome {
                Ok(Ok((models, report))) => {
                    self.install(models, report, episodes);
                    None
                }
                Ok(Err(TrainError::Cancelled)) => {
                    tracing::info!(run = %self.name, "training cancelled");
                    return;
                }
                Ok(Err(e)) => Some(e.to_string()),
                Err(message) => Some(message),
            };
            if let Some(message) = failure {
                tracing::error!(run = %self.name, "training failed; keeping the previous models: {message}");
                self.emit(RunEventKind::TrainingFailed { message });
                // Do not leave sync-mode agents waiting forever on models that will not come.
                self.trained_through.send_replace(episodes);
            }
            if self.episodes_stored() > episodes {
                self.wake_trainer.notify_one();
            }
        }
    }

    /// Writes `models` as the run's newest checkpoint (when the run is durable and this planner
    /// still owns it: a planner that lost the run writes nothing over the new owner's), on the
    /// blocking pool, and hands them back. A failed write is logged; the models are used anyway.
    async fn write_checkpoint(self: Arc<Self>, models: Models) -> Result<Models, String> {
        tokio::task::spawn_blocking(move || {
            if let Some(dir) = &self.dir {
                match self.check_owner() {
                    Err(e) => tracing::warn!(error = %e, "no checkpoint written"),
                    Ok(()) => match dir.save_models(self.epoch, &models, self.task) {
                        Ok(path) => tracing::debug!(path = %path.display(), "checkpoint written"),
                        Err(e @ PersistError::NewerTerm { .. }) => {
                            tracing::warn!(error = %e, "no checkpoint written: a newer owner took the run")
                        }
                        Err(e) => tracing::error!(error = %e, "cannot write a checkpoint; the models are used anyway"),
                    },
                }
            }
            models
        })
        .await
        .map_err(|e| format!("cannot write the checkpoint: {e}"))
    }

    fn install(&self, models: Models, report: TrainReport, episodes: u32) {
        tracing::info!(
            run = %self.name,
            version = report.models_version,
            transitions = report.transitions,
            dynamics_epochs = report.dynamics_epochs,
            energy_epochs = report.energy_epochs,
            dynamics_steps = report.dynamics_steps,
            energy_steps = report.energy_steps,
            cut_short = ?report.cut_short,
            dynamics_loss = report.dynamics_loss,
            energy_loss = report.energy_loss,
            reward_steps = report.reward_steps,
            reward_loss = ?report.reward_loss,
            termination_steps = report.termination_steps,
            termination_accuracy = report.termination_accuracy.map(|a| a.accuracy),
            termination_recall = report.termination_accuracy.map(|a| a.recall),
            termination_held_out = report.termination_accuracy.map(|a| a.held_out),
            termination_held_out_ends = report.termination_accuracy.map(|a| a.terminations),
            seconds = report.seconds,
            "models updated"
        );
        *self.models.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(models);
        self.hosting
            .histograms
            .retraining_seconds
            .observe(f64::from(report.seconds));
        // A loss is `None` where the model took no step (nothing to report); a step's loss is
        // finite, or `retrain` refused the models.
        let loss = |steps: usize, loss: f32| (steps > 0 && loss.is_finite()).then_some(loss);
        *self
            .last_retraining
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(LastRetraining {
            models_version: report.models_version,
            seconds: report.seconds,
            dynamics_loss: loss(report.dynamics_steps, report.dynamics_loss),
            energy_loss: loss(report.energy_steps, report.energy_loss),
            termination_accuracy: report.termination_accuracy,
        });
        self.trained_through.send_replace(episodes);
        self.emit(RunEventKind::ModelsUpdated {
            models_version: report.models_version,
            dynamics_loss: report.dynamics_loss,
            energy_loss: report.energy_loss,
            reward_loss: report.reward_loss,
            seconds: report.seconds,
            termination_accuracy: report.termination_accuracy,
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::replay::log_tests::FillingDisk;
    use proto::{Builtin, PlannerOverrides};
    use std::sync::atomic::AtomicBool;

    fn small_preset() -> Preset {
        let mut preset = Preset::new(Builtin::Cartpole.task(), Some("cem")).unwrap();
        preset.dynamics.hidden_size = 8;
        preset
    }

    /// The spec every test run here has: cartpole, the `cem` preset, async, seed 1.
    fn cartpole_spec() -> RunSpec {
        RunSpec {
            task: Builtin::Cartpole.name().into(),
            preset: Some("cem".into()),
            overrides: PlannerOverrides::default(),
            mode: TrainMode::Async,
            seed: 1,
            task_spec: None,
        }
    }

    /// A cartpole run with untrained small models over `buffer`.
    fn run_on(buffer: ReplayBuffer) -> Arc<Run> {
        let preset = small_preset();
        let models = Models::untrained(Builtin::Cartpole.task(), &preset, 1);
        Run::with_state(
            "r".into(),
            cartpole_spec(),
            preset,
            buffer,
            models,
            None,
            quiet_hosting(),
        )
    }

    /// The term tests open their buffers at.
    fn test_term() -> replay::Term<'static> {
        replay::Term {
            token: 1,
            planner: "p",
            still_owner: OwnerCheck::alone(),
        }
    }

    /// A run whose replay log writes through a disk that fills up while `full` is set.
    fn run_on_a_filling_disk(path: &std::path::Path, full: Arc<AtomicBool>) -> Arc<Run> {
        run_on(
            ReplayBuffer::open_with(path, Builtin::Cartpole.task(), test_term(), |file| {
                Box::new(FillingDisk { file, full })
            })
            .unwrap(),
        )
    }

    /// Hosting that drops events and bounds nothing.
    fn quiet_hosting() -> Hosting {
        Hosting {
            events: Arc::new(|_: &str, _: RunEventKind| {}),
            train_limits: TrainLimits::unbounded(),
            replay_capacity: None,
            replay_budget: Arc::new(ReplayBudget::unbounded()),
            log_disk: LogDisk::direct(),
            histograms: RunHistograms::default(),
            sync_every_step: false,
            shared_dir: false,
            still_owner: Arc::new(|_: &str, _: u64| true),
        }
    }

    fn obs(episode: u32, step: u32, end: Option<EpisodeEnd>) -> Observation {
        let reward = (step > 0).then_some(step as f32);
        Observation::new(episode, step, vec![step as f32; 4], reward, end)
    }

    #[tokio::test]
    async fn a_full_disk_refuses_the_step_loses_nothing_acknowledged_and_the_agent_resends() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let full = Arc::new(AtomicBool::new(false));
        let run = run_on_a_filling_disk(&path, full.clone());
        let mut session = AgentSession::new("a", 200);
        // Steps 0..=3 are stored and acknowledged (the agent "receives" an action each).
        for step in 0..4 {
            run.accept(&mut session, &obs(0, step, None)).await.unwrap();
            session.acted(step, &[0.5]);
        }
        // The disk fills: step 4 (mid-episode) and the episode's last step are refused with a
        // storage error and the session stays at step 3.
        full.store(true, Ordering::SeqCst);
        for attempt in [obs(0, 4, None), obs(0, 4, Some(EpisodeEnd::TimeLimit))] {
            let Refused::Step(err) = run.accept(&mut session, &attempt).await.unwrap_err() else {
                panic!("a run in memory is never fenced");
            };
            assert_eq!(err.code, ErrorCode::Storage, "{err:?}");
            assert_eq!((err.episode, err.step), (Some(0), Some(4)));
            assert_eq!(session.position(), Some((0, 3)));
        }
        assert_eq!(run.tally().transitions, 3);
        assert_eq!(run.episodes_stored(), 0);
        // Space returns: the agent resends the same observation and the episode carries on.
        full.store(false, Ordering::SeqCst);
        let (_, stored) = run
            .accept(&mut session, &obs(0, 4, Some(EpisodeEnd::TimeLimit)))
            .await
            .unwrap();
        assert_eq!(stored.must_cover, Some(1));
        assert_eq!(run.next_episode("a"), 1);
        drop(run);
        // Every transition is on disk exactly once, and the episode ended once.
        let reopened = ReplayBuffer::read(&path, Builtin::Cartpole.task()).unwrap();
        assert_eq!(reopened.len(), 4);
        let states: Vec<f32> = (0..4).map(|i| reopened.transitions().row(i).0[0]).collect();
        assert_eq!(states, vec![0.0, 1.0, 2.0, 3.0]);
        assert_eq!(reopened.episodes().len(), 1);
        assert_eq!(reopened.episodes()[0].end, EpisodeEnd::TimeLimit);
        assert_eq!(reopened.episodes()[0].steps, 4);
    }

    /// A disk whose `fsync` fails while `failing` is set (as a device that lost the write):
    /// writes reach the file.
    #[derive(Debug)]
    struct FailingSync {
        file: std::fs::File,
        failing: Arc<AtomicBool>,
    }

    impl LogFile for FailingSync {
        fn append_bytes(&mut self, bytes: &[u8]) -> std::io::Result<()> {
            self.file.append_bytes(bytes)
        }

        fn truncate_to(&mut self, len: u64) -> std::io::Result<()> {
            self.file.truncate_to(len)
        }

        fn sync_data(&mut self) -> std::io::Result<()> {
            if self.failing.load(Ordering::SeqCst) {
                return Err(std::io::Error::from_raw_os_error(5)); // EIO
            }
            self.file.sync_data()
        }
    }

    /// A failed `fsync` of an episode's end is a storage error to the agent: nothing of the
    /// step counts (not in memory, not in the log), the episode stays open at the step before,
    /// and the agent's resend stores it once.
    #[tokio::test]
    async fn a_failed_fsync_refuses_the_step_as_storage_and_the_resend_stores_it_once() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let failing = Arc::new(AtomicBool::new(false));
        let buffer = {
            let failing = failing.clone();
            ReplayBuffer::open_with(&path, Builtin::Cartpole.task(), test_term(), |file| {
                Box::new(FailingSync { file, failing })
            })
            .unwrap()
        };
        let run = run_on(buffer);
        let mut session = AgentSession::new("a", 200);
        for step in 0..4 {
            run.accept(&mut session, &obs(0, step, None)).await.unwrap();
            session.acted(step, &[0.5]);
        }
        failing.store(true, Ordering::SeqCst);
        let last = obs(0, 4, Some(EpisodeEnd::TimeLimit));
        let Refused::Step(err) = run.accept(&mut session, &last).await.unwrap_err() else {
            panic!("a run in memory is never fenced");
        };
        assert_eq!(err.code, ErrorCode::Storage, "{err:?}");
        assert!(err.message.contains("send it again"), "{err}");
        assert_eq!((err.episode, err.step), (Some(0), Some(4)));
        assert_eq!(session.position(), Some((0, 3)), "the episode stays open");
        assert_eq!((run.tally().transitions, run.tally().episodes), (3, 0));
        assert_eq!(run.episodes_stored(), 0);
        assert_eq!(run.next_episode("a"), 0, "nothing ended");
        // The disk recovers: the same observation again ends the episode, once.
        failing.store(false, Ordering::SeqCst);
        let (_, stored) = run.accept(&mut session, &last).await.unwrap();
        assert_eq!(stored.must_cover, Some(1));
        assert_eq!((run.tally().transitions, run.tally().episodes), (4, 1));
        drop(run);
        let reopened = ReplayBuffer::read(&path, Builtin::Cartpole.task()).unwrap();
        assert_eq!(reopened.len(), 4);
        assert_eq!(reopened.episodes().len(), 1);
        assert_eq!(reopened.episodes()[0].steps, 4);
    }

    /// `status` reads the tally while agents store: an episode's last transition and its end
    /// appear together (the old code counted the end after syncing the log, and `status`
    /// could show every transition of a finished episode with the episode not yet counted).
    #[tokio::test]
    async fn the_tally_never_shows_an_episodes_last_transition_without_its_end() {
        const STEPS: u32 = 4;
        const EPISODES: u32 = 100;
        let dir = tempfile::tempdir().unwrap();
        let run = run_on_a_filling_disk(dir.path(), Default::default());
        let done = Arc::new(AtomicBool::new(false));
        let reader = {
            let (run, done) = (run.clone(), done.clone());
            std::thread::spawn(move || {
                let mut seen_ends = 0;
                // One look after the writer is done as well: the final tally (whole episodes
                // only) is always sampled, however the threads were scheduled.
                loop {
                    let last_look = done.load(Ordering::SeqCst);
                    let tally = run.tally();
                    if tally.transitions > 0 && tally.transitions % STEPS as usize == 0 {
                        assert_eq!(
                            tally.episodes as usize,
                            tally.transitions / STEPS as usize,
                            "{} transitions",
                            tally.transitions
                        );
                        seen_ends += 1;
                    }
                    if last_look {
                        break;
                    }
                }
                seen_ends
            })
        };
        let mut session = AgentSession::new("a", 200);
        for episode in 0..EPISODES {
            for step in 0..=STEPS {
                let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
                run.accept(&mut session, &obs(episode, step, end))
                    .await
                    .unwrap();
                session.acted(step, &[0.5]);
            }
        }
        done.store(true, Ordering::SeqCst);
        let seen_ends = reader.join().expect("the tally stayed consistent");
        assert!(seen_ends > 0, "the reader saw finished episodes");
        assert_eq!(run.tally().episodes, EPISODES);
    }

    /// An episode that an agent abandoned (it started the next one) is stored as interrupted,
    /// and its agent's next episode is numbered after it.
    #[tokio::test]
    async fn an_abandoned_episode_is_stored_as_interrupted_and_numbered_past() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let run = run_on_a_filling_disk(&path, Default::default());
        let mut session = AgentSession::new("a", 200);
        run.accept(&mut session, &obs(0, 0, None)).await.unwrap();
        session.acted(0, &[0.5]);
        run.accept(&mut session, &obs(0, 1, None)).await.unwrap();
        assert_eq!(run.next_episode("a"), 0, "nothing ended");
        // Episode 1 starts before 0 ended: 0 is abandoned, and stored as interrupted.
        let (accepted, stored) = run.accept(&mut session, &obs(1, 0, None)).await.unwrap();
        assert_eq!(accepted.abandoned.unwrap().end, EpisodeEnd::Interrupted);
        assert_eq!(stored.must_cover, None);
        assert_eq!(run.next_episode("a"), 1);
        assert_eq!(run.next_episode("b"), 0);
        drop(run);
        let reopened = ReplayBuffer::read(&path, Builtin::Cartpole.task()).unwrap();
        assert_eq!(reopened.len(), 1);
        assert_eq!(reopened.episodes().len(), 1);
        assert_eq!(reopened.episodes()[0].end, EpisodeEnd::Interrupted);
    }

    fn open(dir: &RunDir, planner: &str) -> Arc<Run> {
        let spec = cartpole_spec();
        let preset = small_preset();
        let epoch = dir
            .claim_epoch_after(dir.current_epoch().unwrap(), planner)
            .unwrap();
        Run::open(
            "r".into(),
            spec,
            preset,
            dir.clone(),
            quiet_hosting(),
            (epoch, planner),
        )
        .unwrap()
    }

    /// What the start of an episode asks to store: nothing but the boundary check.
    fn episode_start() -> Accepted {
        Accepted {
            transition: None,
            finished: None,
            abandoned: None,
        }
    }

    /// A planner whose run was taken over at a newer epoch stores nothing at the next episode
    /// boundary, and says so; the new owner stores on.
    #[test]
    fn an_owner_that_lost_the_run_is_fenced_at_the_next_boundary() {
        let data = tempfile::tempdir().unwrap();
        let dir = RunDir::new(data.path(), "r");
        let old = open(&dir, "pa");
        assert_eq!(old.epoch(), 1);
        old.store("a", 0, 0, &[0.0; 4], &episode_start()).unwrap();
        let new = open(&dir, "pb");
        assert_eq!(new.epoch(), 2);
        let err = old
            .store("a", 1, 0, &[0.0; 4], &episode_start())
            .unwrap_err();
        assert!(
            matches!(
                err,
                StoreError::Fenced(Fenced {
                    held: 1,
                    current: Some(2),
                    ..
                })
            ),
            "{err}"
        );
        assert!(old.check_owner().is_err());
        new.store("a", 1, 0, &[0.0; 4], &episode_start()).unwrap();
        new.check_owner().unwrap();
    }
}
