//! A run: one learning process with its task, preset, replay buffer and models, fed by one or
//! more agents and retrained by its own trainer task.

use crate::agent::Accepted;
use crate::config::Preset;
use crate::models::Models;
use crate::persist::{PersistError, RunDir};
use crate::replay::{EpisodeSummary, ReplayBuffer, ReplayError};
use crate::service::status::{Latency, LatencyWindow};
use crate::trainer::{TrainError, TrainLimits, TrainReport, retrain};
use proto::{EpisodeEnd, RunEventKind, RunSpec, TaskSpec, TrainMode};
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
}

/// One run.
pub struct Run {
    name: String,
    spec: RunSpec,
    preset: Preset,
    task: &'static TaskSpec,
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
    /// What `status` reports of the buffer, kept apart from it so a report never waits for a
    /// buffer busy writing to disk.
    tally: Mutex<Tally>,
    /// Where checkpoints go (`None`: the run lives in memory only).
    dir: Option<RunDir>,
}

/// The counters of a run's buffer that `status` reports.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Tally {
    /// Finished (not interrupted) episodes.
    pub episodes: u32,
    pub transitions: usize,
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

/// Why a stored or new run could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("replay buffer: {0}")]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Persist(#[from] PersistError),
}

impl std::fmt::Debug for Run {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Run")
            .field("name", &self.name)
            .field("task", &self.task.id)
            .finish_non_exhaustive()
    }
}

impl Run {
    /// Opens the run stored in `dir`, or starts it there: records its spec, recovers its replay
    /// buffer (cutting a torn tail) and loads the newest usable checkpoint. If the buffer holds
    /// finished episodes the models were not trained on, the trainer is woken at once so the
    /// models catch up with the data.
    pub fn open(
        name: String,
        spec: RunSpec,
        preset: Preset,
        dir: RunDir,
        hosting: Hosting,
    ) -> Result<Arc<Self>, OpenError> {
        let task = spec.task.spec();
        let buffer = ReplayBuffer::open(&dir.replay_log(), task)?;
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
        let task = spec.task.spec();
        let stored = buffer
            .episodes()
            .iter()
            .filter(|e| e.end != EpisodeEnd::Interrupted)
            .count() as u32;
        let covered = models.episodes_covered;
        let mut tally = Tally {
            transitions: buffer.len(),
            ..Tally::default()
        };
        for e in buffer.episodes() {
            if e.end != EpisodeEnd::Interrupted {
                tally.finished(&e.agent, e.episode, e.episode_return);
            }
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
            tally: Mutex::new(tally),
            dir,
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

    pub fn task(&self) -> &'static TaskSpec {
        self.task
    }

    pub fn mode(&self) -> TrainMode {
        self.spec.mode
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

    /// The next episode number for `agent` (runs resumed after a restart continue numbering).
    pub fn next_episode(&self, agent: &str) -> u32 {
        self.lock_buffer()
            .episodes()
            .iter()
            .filter(|e| e.agent == agent)
            .map(|e| e.episode + 1)
            .max()
            .unwrap_or(0)
    }

    /// Records how long a planned action took.
    pub fn record_latency(&self, ms: f32) {
        self.latencies
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .record(ms);
    }

    /// Planning latency percentiles of the recent planned actions.
    pub fn latency(&self) -> Option<Latency> {
        self.latencies
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .percentiles()
    }

    /// Whether actions are still uniformly random: during the exploration episodes, and for as
    /// long as no model has been trained.
    pub fn exploring(&self) -> bool {
        self.episodes_stored() < self.preset.exploration_episodes || !self.models().is_trained()
    }

    fn lock_tally(&self) -> std::sync::MutexGuard<'_, Tally> {
        self.tally.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn lock_buffer(&self) -> std::sync::MutexGuard<'_, ReplayBuffer> {
        self.buffer.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Stores what an accepted observation produced: its transition (with `next_obs`), the
    /// episode it finished, an episode it abandoned. Returns the number of finished episodes a
    /// sync-mode agent must see trained before its next episode (if this one finished).
    pub fn store(
        &self,
        agent: &str,
        episode: u32,
        step: u32,
        next_obs: &[f32],
        accepted: &Accepted,
    ) -> Result<Option<u32>, ReplayError> {
        let mut buffer = self.lock_buffer();
        if let Some(abandoned) = &accepted.abandoned {
            buffer.end_episode(abandoned.clone())?;
        }
        if let Some((obs, act, reward)) = &accepted.transition {
            buffer.push(agent, episode, step - 1, obs, act, next_obs, *reward)?;
            self.lock_tally().transitions += 1;
        }
        let Some(finished) = &accepted.finished else {
            return Ok(None);
        };
        buffer.end_episode(finished.clone())?;
        drop(buffer);
        self.lock_tally()
            .finished(agent, finished.episode, finished.episode_return);
        let stored = self.episodes_stored.fetch_add(1, Ordering::SeqCst) + 1;
        self.emit(RunEventKind::EpisodeFinished {
            agent: agent.to_string(),
            episode: finished.episode,
            episode_return: finished.episode_return,
            steps: finished.steps,
            end: finished.end,
        });
        self.wake_trainer.notify_one();
        Ok(Some(stored))
    }

    /// Records an episode that an agent left unfinished (it vanished or detached).
    pub fn store_interrupted(&self, summary: EpisodeSummary) -> Result<(), ReplayError> {
        self.lock_buffer().end_episode(summary)
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
            let data = self.lock_buffer().transitions().clone();
            self.training.store(true, Ordering::SeqCst);
            self.emit(RunEventKind::TrainingStarted {
                transitions: data.len() as u64,
            });
            let current = self.models();
            let preset = self.preset.clone();
            let seed = self.spec.seed;
            let dir = self.dir.clone();
            let task = self.task;
            let limits = self.hosting.train_limits.clone();
            let outcome = tokio::task::spawn_blocking(move || {
                let trained = retrain(&current, &data, &preset, episodes, seed, &limits)?;
                // Checkpoint before the swap: models in use are always on disk too, so a
                // restart never plans with models older than the ones agents last saw. Only
                // finite models get here: `retrain` refuses the others.
                if let Some(dir) = dir {
                    match dir.save_models(&trained.0, task) {
                        Ok(path) => tracing::debug!(path = %path.display(), "checkpoint written"),
                        Err(e) => tracing::error!(error = %e, "cannot write a checkpoint; the models are used anyway"),
                    }
                }
                Ok(trained)
            })
            .await;
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
                Err(e) => Some(format!("training panicked: {e}")),
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
            seconds = report.seconds,
            "models updated"
        );
        *self.models.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(models);
        self.trained_through.send_replace(episodes);
        self.emit(RunEventKind::ModelsUpdated {
            models_version: report.models_version,
            dynamics_loss: report.dynamics_loss,
            energy_loss: report.energy_loss,
            seconds: report.seconds,
        });
    }
}
