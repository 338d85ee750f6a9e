//! A run's replay buffer: every transition any of its agents produced, in memory for training
//! and in an append-only log on disk so that a restarted daemon resumes with all of it.

mod log;

pub use log::{ActionOrigin, LogError, Record, ReplayLog};

use crate::data::Transitions;
use proto::{EpisodeEnd, TaskSpec};
use std::collections::BTreeMap;
use std::path::Path;

/// A finished episode, as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeSummary {
    pub agent: String,
    pub episode: u32,
    pub steps: u32,
    pub episode_return: f32,
    pub end: EpisodeEnd,
}

/// Failures of the replay buffer.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Log(#[from] LogError),
    #[error("replay log {path} holds task {found}, this run is {expected}")]
    TaskMismatch {
        path: String,
        found: String,
        expected: String,
    },
    #[error("replay log {path} does not start with a header record")]
    MissingHeader { path: String },
}

/// Transitions in memory, mirrored to an optional log file.
#[derive(Debug)]
pub struct ReplayBuffer {
    transitions: Transitions,
    /// Which action each transition holds, in the order of `transitions`.
    origins: Vec<ActionOrigin>,
    episodes: Vec<EpisodeSummary>,
    log: Option<ReplayLog>,
    /// The ownership epoch of the newest claim: what this buffer writes under, and below which
    /// records are stale.
    epoch: u64,
    /// Records of an older epoch found after a newer claim when the log was opened (written by
    /// a planner that had lost the run); skipped.
    stale_skipped: usize,
}

impl ReplayBuffer {
    /// A buffer that lives in memory only (tests, benchmarks).
    pub fn in_memory(task: &TaskSpec) -> Self {
        Self {
            transitions: Transitions::new(task.obs_dim, task.act_dim),
            origins: Vec::new(),
            episodes: Vec::new(),
            log: None,
            epoch: 0,
            stale_skipped: 0,
        }
    }

    /// Opens the buffer stored at `path` (creating it), recovering every intact record except
    /// stale ones: an entry whose epoch is below that of a claim before it was written by a
    /// planner that had lost the run, and is skipped (with a warning).
    ///
    /// Episodes the log holds transitions of but no end (the daemon stopped in their middle)
    /// are recorded as interrupted here: their transitions stay (they were acknowledged), and
    /// their agents continue with the next episode number rather than resuming a stale one.
    pub fn open(path: &Path, task: &TaskSpec) -> Result<Self, ReplayError> {
        let (mut log, recovered) = ReplayLog::open(path)?;
        if recovered.truncated_bytes > 0 {
            tracing::warn!(path = %path.display(), bytes = recovered.truncated_bytes, "cut a torn tail off the replay log");
        }
        let mut buffer = Self::in_memory(task);
        let mut records = recovered.records.into_iter();
        match records.next() {
            None => log.append(&Record::Header {
                task: task.id,
                obs_dim: task.obs_dim as u32,
                act_dim: task.act_dim as u32,
            })?,
            Some(Record::Header { task: found, .. }) if found == task.id => {}
            Some(Record::Header { task: found, .. }) => {
                return Err(ReplayError::TaskMismatch {
                    path: path.display().to_string(),
                    found: found.to_string(),
                    expected: task.id.to_string(),
                });
            }
            Some(_) => {
                return Err(ReplayError::MissingHeader {
                    path: path.display().to_string(),
                });
            }
        }
        let mut open_episodes: BTreeMap<(String, u32), EpisodeSummary> = BTreeMap::new();
        for record in records {
            if let Record::Claim { epoch, .. } = &record {
                buffer.epoch = buffer.epoch.max(*epoch);
            }
            if record.epoch().is_some_and(|e| e < buffer.epoch) {
                buffer.stale_skipped += 1;
                continue;
            }
            match &record {
                Record::Transition {
                    agent,
                    episode,
                    step,
                    reward,
                    ..
                } => {
                    let open = open_episodes
                        .entry((agent.clone(), *episode))
                        .or_insert_with(|| EpisodeSummary {
                            agent: agent.clone(),
                            episode: *episode,
                            steps: 0,
                            episode_return: 0.0,
                            end: EpisodeEnd::Interrupted,
                        });
                    open.steps = open.steps.max(step + 1);
                    open.episode_return += reward;
                }
                Record::EpisodeEnd { agent, episode, .. } => {
                    open_episodes.remove(&(agent.clone(), *episode));
                }
                Record::Header { .. } | Record::Claim { .. } => {}
            }
            buffer.apply(&record);
        }
        if buffer.stale_skipped > 0 {
            tracing::warn!(path = %path.display(), records = buffer.stale_skipped, epoch = buffer.epoch, "skipped records a planner wrote after it had lost the run");
        }
        buffer.log = Some(log);
        for (_, summary) in open_episodes {
            tracing::warn!(path = %path.display(), agent = %summary.agent, episode = summary.episode, steps = summary.steps, "episode left open by a stopped daemon recorded as interrupted");
            buffer.end_episode(summary)?;
        }
        Ok(buffer)
    }

    fn apply(&mut self, record: &Record) {
        match record {
            Record::Header { .. } | Record::Claim { .. } => {}
            Record::Transition {
                obs,
                act,
                origin,
                next_obs,
                ..
            } => {
                self.transitions.push(obs, act, next_obs);
                self.origins.push(*origin);
            }
            Record::EpisodeEnd {
                agent,
                episode,
                steps,
                episode_return,
                end,
                ..
            } => self.episodes.push(EpisodeSummary {
                agent: agent.clone(),
                episode: *episode,
                steps: *steps,
                episode_return: *episode_return,
                end: *end,
            }),
        }
    }

    fn record(&mut self, record: Record) -> Result<(), ReplayError> {
        if let Some(log) = &mut self.log {
            log.append(&record)?;
        }
        self.apply(&record);
        Ok(())
    }

    /// Takes the buffer over for `planner` at ownership `epoch` (above every earlier claim):
    /// records the claim, synced, and writes everything after it under `epoch`.
    pub fn claim(&mut self, epoch: u64, planner: &str) -> Result<(), ReplayError> {
        self.record(Record::Claim {
            epoch,
            planner: planner.to_string(),
        })?;
        if let Some(log) = &mut self.log {
            log.sync()?;
        }
        self.epoch = epoch;
        Ok(())
    }

    /// The ownership epoch this buffer writes under.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Stale records skipped when the log was opened.
    pub fn stale_skipped(&self) -> usize {
        self.stale_skipped
    }

    /// Stores one transition. It is in the log (as far as the OS is concerned) when this returns.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        agent: &str,
        episode: u32,
        step: u32,
        obs: &[f32],
        act: &[f32],
        origin: ActionOrigin,
        next_obs: &[f32],
        reward: f32,
    ) -> Result<(), ReplayError> {
        self.record(Record::Transition {
            epoch: self.epoch,
            agent: agent.to_string(),
            episode,
            step,
            obs: obs.to_vec(),
            act: act.to_vec(),
            origin,
            next_obs: next_obs.to_vec(),
            reward,
        })
    }

    /// Marks the end of an episode and syncs the log to disk.
    pub fn end_episode(&mut self, summary: EpisodeSummary) -> Result<(), ReplayError> {
        let EpisodeSummary {
            agent,
            episode,
            steps,
            episode_return,
            end,
        } = summary;
        self.record(Record::EpisodeEnd {
            epoch: self.epoch,
            agent,
            episode,
            steps,
            episode_return,
            end,
        })?;
        if let Some(log) = &mut self.log {
            log.sync()?;
        }
        Ok(())
    }

    pub fn transitions(&self) -> &Transitions {
        &self.transitions
    }

    /// Which action each stored transition holds (in the order of [`Self::transitions`]).
    pub fn origins(&self) -> &[ActionOrigin] {
        &self.origins
    }

    pub fn episodes(&self) -> &[EpisodeSummary] {
        &self.episodes
    }

    pub fn len(&self) -> usize {
        self.transitions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.transitions.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::TaskId;

    const PLANNED: ActionOrigin = ActionOrigin::Planned;

    #[test]
    fn a_reopened_buffer_holds_everything_stored() {
        let dir = std::env::temp_dir().join(format!("ebmpc-replay-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("replay.log");
        let task = TaskId::Cartpole.spec();
        let mut buffer = ReplayBuffer::open(&path, task).unwrap();
        for step in 0..10 {
            let s = [step as f32; 4];
            buffer
                .push(
                    "a",
                    0,
                    step,
                    &s,
                    &[0.1],
                    ActionOrigin::Planned,
                    &[step as f32 + 1.0; 4],
                    0.5,
                )
                .unwrap();
        }
        let summary = EpisodeSummary {
            agent: "a".into(),
            episode: 0,
            steps: 10,
            episode_return: 5.0,
            end: EpisodeEnd::TimeLimit,
        };
        buffer.end_episode(summary.clone()).unwrap();
        let snapshot = buffer.transitions().clone();
        drop(buffer);

        let reopened = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(reopened.transitions(), &snapshot);
        assert_eq!(reopened.episodes(), &[summary]);
        let err = ReplayBuffer::open(&path, TaskId::Ant.spec()).unwrap_err();
        assert!(err.to_string().contains("holds task cartpole"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_episode_left_open_is_recorded_as_interrupted_on_reopening() {
        let dir = std::env::temp_dir().join(format!("ebmpc-replay-open-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("replay.log");
        let task = TaskId::Cartpole.spec();
        let mut buffer = ReplayBuffer::open(&path, task).unwrap();
        for step in 0..3 {
            buffer
                .push("a", 4, step, &[0.0; 4], &[0.1], PLANNED, &[1.0; 4], 0.5)
                .unwrap();
            buffer
                .push("b", 0, step, &[0.0; 4], &[0.1], PLANNED, &[1.0; 4], 1.0)
                .unwrap();
        }
        buffer
            .end_episode(EpisodeSummary {
                agent: "b".into(),
                episode: 0,
                steps: 3,
                episode_return: 3.0,
                end: EpisodeEnd::Terminated,
            })
            .unwrap();
        drop(buffer); // as if the daemon was killed: a's episode 4 never ended

        let reopened = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(reopened.len(), 6, "every stored transition is kept");
        let interrupted = EpisodeSummary {
            agent: "a".into(),
            episode: 4,
            steps: 3,
            episode_return: 1.5,
            end: EpisodeEnd::Interrupted,
        };
        assert_eq!(reopened.episodes().len(), 2);
        assert_eq!(reopened.episodes()[1], interrupted);
        drop(reopened);
        // Recorded once: opening again finds nothing left open.
        let again = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(again.episodes().len(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A planner that lost the run (a newer claim is in the log) and wrote on: its records are
    /// skipped on reading, the new owner's are kept, and the applied actions are kept as such.
    #[test]
    fn records_of_a_fenced_owner_are_skipped_and_origins_kept() {
        let dir = std::env::temp_dir().join(format!("ebmpc-replay-fence-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let path = dir.join("replay.log");
        let task = TaskId::Cartpole.spec();
        let mut old_owner = ReplayBuffer::open(&path, task).unwrap();
        old_owner.claim(1, "pa").unwrap();
        old_owner
            .push("a", 0, 0, &[0.0; 4], &[0.5], PLANNED, &[1.0; 4], 1.0)
            .unwrap();
        let mut new_owner = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!((new_owner.epoch(), new_owner.len()), (1, 1));
        new_owner.claim(2, "pb").unwrap();
        new_owner
            .push(
                "a",
                0,
                1,
                &[1.0; 4],
                &[-3.0],
                ActionOrigin::Applied,
                &[2.0; 4],
                1.0,
            )
            .unwrap();
        // The old owner, partitioned, still writes under epoch 1.
        old_owner
            .push("a", 0, 1, &[1.0; 4], &[0.7], PLANNED, &[9.0; 4], 1.0)
            .unwrap();
        drop((old_owner, new_owner));

        let reopened = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(reopened.epoch(), 2);
        assert_eq!(reopened.stale_skipped(), 1);
        assert_eq!(reopened.len(), 2);
        assert_eq!(
            reopened.origins(),
            &[ActionOrigin::Planned, ActionOrigin::Applied]
        );
        assert_eq!(reopened.transitions().row(1).1, &[-3.0]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
