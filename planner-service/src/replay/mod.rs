//! A run's replay buffer: every transition any of its agents produced, in memory for training
//! and in an append-only log on disk so that a restarted daemon resumes with all of it.

mod log;

#[cfg(test)]
pub(crate) use log::tests as log_tests;
pub use log::{LogError, LogFile, LogSyncer, Record, Recovered, ReplayLog};

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
    #[error("a replay record does not fit the run's dimensions: {record}")]
    Dimension { record: String },
}

/// Transitions in memory, mirrored to an optional log file.
#[derive(Debug)]
pub struct ReplayBuffer {
    task: &'static TaskSpec,
    transitions: Transitions,
    episodes: Vec<EpisodeSummary>,
    log: Option<ReplayLog>,
}

impl From<EpisodeSummary> for Record {
    fn from(summary: EpisodeSummary) -> Self {
        let EpisodeSummary {
            agent,
            episode,
            steps,
            episode_return,
            end,
        } = summary;
        Record::EpisodeEnd {
            agent,
            episode,
            steps,
            episode_return,
            end,
        }
    }
}

impl ReplayBuffer {
    /// A buffer that lives in memory only (tests, benchmarks).
    pub fn in_memory(task: &'static TaskSpec) -> Self {
        Self {
            task,
            transitions: Transitions::new(task.obs_dim, task.act_dim),
            episodes: Vec::new(),
            log: None,
        }
    }

    /// Opens the buffer stored at `path` (creating it), recovering every intact record.
    ///
    /// Episodes the log holds transitions of but no end (the daemon stopped in their middle)
    /// are recorded as interrupted here: their transitions stay (they were acknowledged), and
    /// their agents continue with the next episode number rather than resuming a stale one.
    pub fn open(path: &Path, task: &'static TaskSpec) -> Result<Self, ReplayError> {
        Self::from_log(ReplayLog::open(path)?, task)
    }

    /// As [`ReplayBuffer::open`], writing through `wrap(file)` (tests inject a failing disk).
    pub fn open_with(
        path: &Path,
        task: &'static TaskSpec,
        wrap: impl FnOnce(std::fs::File) -> Box<dyn LogFile>,
    ) -> Result<Self, ReplayError> {
        Self::from_log(ReplayLog::open_with(path, wrap)?, task)
    }

    fn from_log(
        (mut log, recovered): (ReplayLog, Recovered),
        task: &'static TaskSpec,
    ) -> Result<Self, ReplayError> {
        let path = log.path().to_path_buf();
        if recovered.truncated_bytes > 0 {
            tracing::warn!(path = %path.display(), bytes = recovered.truncated_bytes, "cut a torn tail off the replay log");
        }
        if recovered.damaged_regions > 0 {
            tracing::warn!(path = %path.display(), regions = recovered.damaged_regions, bytes = recovered.damaged_bytes, "skipped damaged records in the replay log; every intact record is kept");
        }
        let mut buffer = Self::in_memory(task);
        let mut records = recovered.records.into_iter();
        match records.next() {
            None => log.append(&[Record::Header {
                task: task.id,
                obs_dim: task.obs_dim as u32,
                act_dim: task.act_dim as u32,
            }])?,
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
            if !buffer.fits(&record) {
                tracing::warn!(path = %path.display(), "skipped a replay record whose dimensions do not fit the task");
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
                    open.steps = open.steps.max(step.saturating_add(1));
                    open.episode_return += reward;
                }
                Record::EpisodeEnd { agent, episode, .. } => {
                    open_episodes.remove(&(agent.clone(), *episode));
                }
                Record::Header { .. } => {}
            }
            buffer.apply(&record);
        }
        let left_open: Vec<Record> = open_episodes
            .into_values()
            .inspect(|summary| tracing::warn!(path = %path.display(), agent = %summary.agent, episode = summary.episode, steps = summary.steps, "episode left open by a stopped daemon recorded as interrupted"))
            .map(Record::from)
            .collect();
        buffer.log = Some(log);
        if !left_open.is_empty() {
            buffer.append(left_open)?;
            if let Some(syncer) = buffer.syncer() {
                syncer.sync()?;
            }
        }
        Ok(buffer)
    }

    /// Whether a record's vectors have the task's dimensions. The log's checksums catch
    /// damage; this catches a record that is intact but cannot belong to this run.
    fn fits(&self, record: &Record) -> bool {
        match record {
            Record::Transition {
                obs, act, next_obs, ..
            } => {
                obs.len() == self.task.obs_dim
                    && next_obs.len() == self.task.obs_dim
                    && act.len() == self.task.act_dim
            }
            Record::Header { .. } | Record::EpisodeEnd { .. } => true,
        }
    }

    fn apply(&mut self, record: &Record) {
        match record {
            Record::Header { .. } => {}
            Record::Transition {
                obs, act, next_obs, ..
            } => self.transitions.push(obs, act, next_obs),
            Record::EpisodeEnd {
                agent,
                episode,
                steps,
                episode_return,
                end,
            } => self.episodes.push(EpisodeSummary {
                agent: agent.clone(),
                episode: *episode,
                steps: *steps,
                episode_return: *episode_return,
                end: *end,
            }),
        }
    }

    /// Stores `records` together: when this returns `Ok` they are all in the log (as far as
    /// the OS is concerned) and in memory; on error none of them is in either, so the caller
    /// can refuse what they came from and accept it again later.
    pub fn append(&mut self, records: Vec<Record>) -> Result<(), ReplayError> {
        if let Some(record) = records.iter().find(|r| !self.fits(r)) {
            return Err(ReplayError::Dimension {
                record: format!("{record:?}"),
            });
        }
        if let Some(log) = &mut self.log {
            log.append(&records)?;
        }
        for record in &records {
            self.apply(record);
        }
        Ok(())
    }

    /// A handle that syncs the log to disk without holding the buffer (`None` in memory).
    pub fn syncer(&self) -> Option<LogSyncer> {
        self.log.as_ref().map(ReplayLog::syncer)
    }

    pub fn transitions(&self) -> &Transitions {
        &self.transitions
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

    /// A transition of `agent`'s `episode` at `step` with the cartpole's dimensions.
    fn transition(agent: &str, episode: u32, step: u32, reward: f32) -> Record {
        Record::Transition {
            agent: agent.into(),
            episode,
            step,
            obs: vec![step as f32; 4],
            act: vec![0.1],
            next_obs: vec![step as f32 + 1.0; 4],
            reward,
        }
    }

    #[test]
    fn a_reopened_buffer_holds_everything_stored() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.log");
        let task = TaskId::Cartpole.spec();
        let mut buffer = ReplayBuffer::open(&path, task).unwrap();
        for step in 0..10 {
            buffer.append(vec![transition("a", 0, step, 0.5)]).unwrap();
        }
        let summary = EpisodeSummary {
            agent: "a".into(),
            episode: 0,
            steps: 10,
            episode_return: 5.0,
            end: EpisodeEnd::TimeLimit,
        };
        buffer.append(vec![summary.clone().into()]).unwrap();
        let snapshot = buffer.transitions().clone();
        drop(buffer);

        let reopened = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(reopened.transitions(), &snapshot);
        assert_eq!(reopened.episodes(), &[summary]);
        let err = ReplayBuffer::open(&path, TaskId::Ant.spec()).unwrap_err();
        assert!(err.to_string().contains("holds task cartpole"), "{err}");
    }

    #[test]
    fn an_episode_left_open_is_recorded_as_interrupted_on_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.log");
        let task = TaskId::Cartpole.spec();
        let mut buffer = ReplayBuffer::open(&path, task).unwrap();
        for step in 0..3 {
            buffer
                .append(vec![
                    transition("a", 4, step, 0.5),
                    transition("b", 0, step, 1.0),
                ])
                .unwrap();
        }
        buffer
            .append(vec![
                EpisodeSummary {
                    agent: "b".into(),
                    episode: 0,
                    steps: 3,
                    episode_return: 3.0,
                    end: EpisodeEnd::Terminated,
                }
                .into(),
            ])
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
    }

    #[test]
    fn an_intact_record_of_the_wrong_dimension_is_skipped_on_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.log");
        let task = TaskId::Cartpole.spec();
        drop(ReplayBuffer::open(&path, task).unwrap());
        // Written straight to the log (as a buggy older build or a hand edit could): the
        // buffer itself refuses such a record.
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        let mut wrong = transition("a", 0, 1, 1.0);
        if let Record::Transition { obs, .. } = &mut wrong {
            obs.push(9.0);
        }
        log.append(&[
            transition("a", 0, 0, 1.0),
            wrong.clone(),
            transition("a", 0, 2, 1.0),
        ])
        .unwrap();
        drop(log);
        let mut reopened = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(reopened.len(), 2);
        let err = reopened.append(vec![wrong]).unwrap_err();
        assert!(matches!(err, ReplayError::Dimension { .. }), "{err}");
        assert_eq!(reopened.len(), 2);
    }

    #[test]
    fn an_episode_numbered_u32_max_resumes_without_overflow() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("replay.log");
        let task = TaskId::Cartpole.spec();
        let mut buffer = ReplayBuffer::open(&path, task).unwrap();
        buffer
            .append(vec![transition("a", u32::MAX, u32::MAX, 1.0)])
            .unwrap();
        drop(buffer);
        let reopened = ReplayBuffer::open(&path, task).unwrap();
        assert_eq!(reopened.episodes()[0].steps, u32::MAX);
    }
}
