//! A run: one learning process with its task, preset, replay buffer and models, fed by one or
//! more agents and retrained by its own trainer task.

use crate::agent::Accepted;
use crate::config::Preset;
use crate::models::Models;
use crate::persist::{PersistError, RunDir};
use crate::replay::{EpisodeSummary, ReplayBuffer, ReplayError};
use crate::service::status::{Latency, LatencyWindow};
use crate::trainer::{TrainReport, retrain};
use proto::{EpisodeEnd, RunEventKind, RunSpec, TaskSpec, TrainMode};
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use tokio::sync::{Notify, watch};

/// Where a run reports what happens to it (the service publishes these on the run's events key).
pub type EventSink = Arc<dyn Fn(&str, RunEventKind) + Send + Sync>;

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
    events: EventSink,
    latencies: Mutex<LatencyWindow>,
    /// Where checkpoints go (`None`: the run lives in memory only).
    dir: Option<RunDir>,
    /// The ownership epoch this planner holds the run at (see `crate::fleet`).
    epoch: u64,
}

/// Why a stored or new run could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("replay buffer: {0}")]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Persist(#[from] PersistError),
}

/// Why an observation's results could not be stored.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("replay buffer: {0}")]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Fenced(#[from] Fenced),
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

impl std::fmt::Debug for Run {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Run")
            .field("name", &self.name)
            .field("task", &self.task.id)
            .finish_non_exhaustive()
    }
}

impl Run {
    /// Opens the run stored in `dir`, or starts it there, as its owner at `epoch` (already
    /// claimed in `dir` by `planner`): records its spec, recovers its replay buffer (cutting a
    /// torn tail, skipping records of fenced owners), records the claim in it, and loads the
    /// newest usable checkpoint. If the buffer holds finished episodes the models were not
    /// trained on, the trainer is woken at once so the models catch up with the data.
    pub fn open(
        name: String,
        spec: RunSpec,
        preset: Preset,
        dir: RunDir,
        events: EventSink,
        (epoch, planner): (u64, &str),
    ) -> Result<Arc<Self>, OpenError> {
        let task = spec.task.spec();
        dir.write_spec(&spec)?;
        let mut buffer = ReplayBuffer::open(&dir.replay_log(), task)?;
        buffer.claim(epoch, planner)?;
        let mut models = match dir.load_models(task, &preset)? {
            Some(models) => models,
            None => Models::untrained(task, &preset, spec.seed),
        };
        models.set_inference_precision(preset.inference_precision);
        models.pack_for_inference();
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
            events,
        ))
    }

    fn with_state(
        name: String,
        spec: RunSpec,
        preset: Preset,
        buffer: ReplayBuffer,
        models: Models,
        dir: Option<RunDir>,
        events: EventSink,
    ) -> Arc<Self> {
        let task = spec.task.spec();
        let stored = buffer
            .episodes()
            .iter()
            .filter(|e| e.end != EpisodeEnd::Interrupted)
            .count() as u32;
        let covered = models.episodes_covered;
        let epoch = buffer.epoch();
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
            events,
            latencies: Mutex::new(LatencyWindow::default()),
            dir,
            epoch,
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

    pub fn transitions_stored(&self) -> usize {
        self.lock_buffer().len()
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

    /// Returns of the finished episodes, oldest first.
    pub fn returns(&self) -> Vec<(String, u32, f32)> {
        self.lock_buffer()
            .episodes()
            .iter()
            .filter(|e| e.end != EpisodeEnd::Interrupted)
            .map(|e| (e.agent.clone(), e.episode, e.episode_return))
            .collect()
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

    fn lock_buffer(&self) -> std::sync::MutexGuard<'_, ReplayBuffer> {
        self.buffer.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Stores what an accepted observation produced: its transition (with `next_obs`), the
    /// episode it finished, an episode it abandoned. Returns the number of finished episodes a
    /// sync-mode agent must see trained before its next episode (if this one finished).
    /// At episode boundaries (a start, an end) it first checks that this planner still owns
    /// the run, and stores nothing if not.
    pub fn store(
        &self,
        agent: &str,
        episode: u32,
        step: u32,
        next_obs: &[f32],
        accepted: &Accepted,
    ) -> Result<Option<u32>, StoreError> {
        if accepted.transition.is_none() || accepted.finished.is_some() {
            self.check_owner()?;
        }
        let mut buffer = self.lock_buffer();
        if let Some(abandoned) = &accepted.abandoned {
            buffer.end_episode(abandoned.clone())?;
        }
        if let Some((obs, act, origin, reward)) = &accepted.transition {
            buffer.push(
                agent,
                episode,
                step - 1,
                obs,
                act,
                *origin,
                next_obs,
                *reward,
            )?;
        }
        let Some(finished) = &accepted.finished else {
            return Ok(None);
        };
        buffer.end_episode(finished.clone())?;
        drop(buffer);
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

    /// Records an episode that an agent left unfinished (it vanished or detached), unless
    /// this planner no longer owns the run (the new owner records it when it reads the log).
    pub fn store_interrupted(&self, summary: EpisodeSummary) -> Result<(), StoreError> {
        self.check_owner()?;
        Ok(self.lock_buffer().end_episode(summary)?)
    }

    /// Waits until the models in use were trained on at least `episodes` finished episodes.
    pub async fn wait_for_training(&self, episodes: u32) {
        let mut rx = self.trained_through.subscribe();
        // The sender lives as long as `self`, so this cannot fail while we hold `&self`.
        let _ = rx.wait_for(|&trained| trained >= episodes).await;
    }

    fn emit(&self, kind: RunEventKind) {
        (self.events)(&self.name, kind);
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
            let run = self.clone();
            let task = self.task;
            let outcome = tokio::task::spawn_blocking(move || {
                let (models, report) = retrain(&current, &data, &preset, episodes, seed);
                // Checkpoint before the swap: models in use are always on disk too, so a
                // restart never plans with models older than the ones agents last saw. A
                // planner that lost the run writes no checkpoint over the new owner's.
                if let Some(dir) = &run.dir {
                    match run.check_owner() {
                        Err(e) => tracing::warn!(error = %e, "no checkpoint written"),
                        Ok(()) => match dir.save_models(&models, task) {
                            Ok(path) => tracing::debug!(path = %path.display(), "checkpoint written"),
                            Err(e) => tracing::error!(error = %e, "cannot write a checkpoint; the models are used anyway"),
                        },
                    }
                }
                (models, report)
            })
            .await;
            self.training.store(false, Ordering::SeqCst);
            match outcome {
                Ok((models, report)) => self.install(models, report, episodes),
                Err(e) => {
                    tracing::error!(run = %self.name, error = %e, "training failed; keeping the previous models");
                    self.emit(RunEventKind::TrainingFailed {
                        message: e.to_string(),
                    });
                    // Do not leave sync-mode agents waiting forever on models that will not come.
                    self.trained_through.send_replace(episodes);
                }
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

#[cfg(test)]
mod tests {
    use super::*;
    use proto::TaskId;

    fn temp_dir(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("ebmpc-run-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir
    }

    fn open(dir: &RunDir, planner: &str) -> Arc<Run> {
        let spec = RunSpec {
            task: TaskId::Cartpole,
            preset: Some("cem".into()),
            overrides: Default::default(),
            mode: TrainMode::Async,
            seed: 1,
        };
        let mut preset = Preset::new(TaskId::Cartpole, Some("cem")).unwrap();
        preset.dynamics.hidden_size = 8;
        let epoch = dir
            .claim_epoch_after(dir.current_epoch().unwrap(), planner)
            .unwrap();
        let events: EventSink = Arc::new(|_: &str, _: RunEventKind| {});
        Run::open(
            "r".into(),
            spec,
            preset,
            dir.clone(),
            events,
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
        let data = temp_dir("fence");
        let dir = RunDir::new(&data, "r");
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
        std::fs::remove_dir_all(&data).unwrap();
    }
}
