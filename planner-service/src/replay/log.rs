//! The replay buffer's file: an append-only sequence of length-prefixed, checksummed records.
//!
//! ```text
//! record := len: u32 LE | crc32(payload): u32 LE | payload: postcard(Record)
//! ```
//!
//! Every record is written (to the OS, not yet to disk) before the planner acknowledges the
//! transition it holds by answering with an action, so a killed daemon loses nothing it
//! acknowledged; the file is fsynced at every episode end for power loss. A record cut short by
//! a crash (a *torn tail*) fails its length or checksum test when the file is opened and is cut
//! off, with a warning, so the log is always a clean prefix of what was written.

use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Largest record accepted when reading; anything larger is corruption.
const MAX_RECORD: u32 = 16 << 20;

/// One entry of the log.
///
/// Every entry an owner writes carries its ownership `epoch` (see `crate::fleet`): when a
/// planner takes a run over it writes a [`Record::Claim`] with a higher epoch, and from then on
/// entries of older epochs (written by a planner that lost the run and did not know yet) are
/// stale and skipped when the log is read.
#[derive(Clone, Debug, PartialEq)]
pub enum Record {
    /// First record of every file: what the buffer holds.
    Header {
        task: proto::TaskId,
        obs_dim: u32,
        act_dim: u32,
    },
    /// Planner `planner` took the run over at `epoch`.
    Claim { epoch: u64, planner: String },
    /// One transition `(s, a, s')` with its reward, from `agent`'s `episode` at `step`; `act`
    /// is the action the agent applied if it said so, else the one planned (`origin` says which).
    Transition {
        epoch: u64,
        agent: String,
        episode: u32,
        step: u32,
        obs: Vec<f32>,
        act: Vec<f32>,
        origin: ActionOrigin,
        next_obs: Vec<f32>,
        reward: f32,
    },
    /// `agent` finished `episode`.
    EpisodeEnd {
        epoch: u64,
        agent: String,
        episode: u32,
        steps: u32,
        episode_return: f32,
        end: proto::EpisodeEnd,
    },
}

impl Record {
    /// The ownership epoch an entry was written under (`None` for the header and claims, which
    /// are never stale).
    pub fn epoch(&self) -> Option<u64> {
        match self {
            Record::Header { .. } | Record::Claim { .. } => None,
            Record::Transition { epoch, .. } | Record::EpisodeEnd { epoch, .. } => Some(*epoch),
        }
    }
}

/// Which action a stored transition holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum ActionOrigin {
    /// The action the planner sent (the agent did not say it applied another).
    Planned,
    /// The action the agent said it applied (clipped, overridden, teleoperated).
    Applied,
}

/// The records as postcard writes them: the variant index is the on-disk tag, so variants are
/// only ever added at the end. Logs written before ownership epochs hold `TransitionV1` and
/// `EpisodeEndV1`; they are read as epoch 0 with the planned action and never written again.
#[derive(Serialize, Deserialize)]
enum OnDisk {
    Header {
        task: proto::TaskId,
        obs_dim: u32,
        act_dim: u32,
    },
    TransitionV1 {
        agent: String,
        episode: u32,
        step: u32,
        obs: Vec<f32>,
        act: Vec<f32>,
        next_obs: Vec<f32>,
        reward: f32,
    },
    EpisodeEndV1 {
        agent: String,
        episode: u32,
        steps: u32,
        episode_return: f32,
        end: proto::EpisodeEnd,
    },
    Claim {
        epoch: u64,
        planner: String,
    },
    Transition {
        epoch: u64,
        agent: String,
        episode: u32,
        step: u32,
        obs: Vec<f32>,
        act: Vec<f32>,
        origin: ActionOrigin,
        next_obs: Vec<f32>,
        reward: f32,
    },
    EpisodeEnd {
        epoch: u64,
        agent: String,
        episode: u32,
        steps: u32,
        episode_return: f32,
        end: proto::EpisodeEnd,
    },
}

impl From<OnDisk> for Record {
    fn from(stored: OnDisk) -> Self {
        match stored {
            OnDisk::Header {
                task,
                obs_dim,
                act_dim,
            } => Record::Header {
                task,
                obs_dim,
                act_dim,
            },
            OnDisk::TransitionV1 {
                agent,
                episode,
                step,
                obs,
                act,
                next_obs,
                reward,
            } => Record::Transition {
                epoch: 0,
                agent,
                episode,
                step,
                obs,
                act,
                origin: ActionOrigin::Planned,
                next_obs,
                reward,
            },
            OnDisk::EpisodeEndV1 {
                agent,
                episode,
                steps,
                episode_return,
                end,
            } => Record::EpisodeEnd {
                epoch: 0,
                agent,
                episode,
                steps,
                episode_return,
                end,
            },
            OnDisk::Claim { epoch, planner } => Record::Claim { epoch, planner },
            OnDisk::Transition {
                epoch,
                agent,
                episode,
                step,
                obs,
                act,
                origin,
                next_obs,
                reward,
            } => Record::Transition {
                epoch,
                agent,
                episode,
                step,
                obs,
                act,
                origin,
                next_obs,
                reward,
            },
            OnDisk::EpisodeEnd {
                epoch,
                agent,
                episode,
                steps,
                episode_return,
                end,
            } => Record::EpisodeEnd {
                epoch,
                agent,
                episode,
                steps,
                episode_return,
                end,
            },
        }
    }
}

impl From<Record> for OnDisk {
    fn from(record: Record) -> Self {
        match record {
            Record::Header {
                task,
                obs_dim,
                act_dim,
            } => OnDisk::Header {
                task,
                obs_dim,
                act_dim,
            },
            Record::Claim { epoch, planner } => OnDisk::Claim { epoch, planner },
            Record::Transition {
                epoch,
                agent,
                episode,
                step,
                obs,
                act,
                origin,
                next_obs,
                reward,
            } => OnDisk::Transition {
                epoch,
                agent,
                episode,
                step,
                obs,
                act,
                origin,
                next_obs,
                reward,
            },
            Record::EpisodeEnd {
                epoch,
                agent,
                episode,
                steps,
                episode_return,
                end,
            } => OnDisk::EpisodeEnd {
                epoch,
                agent,
                episode,
                steps,
                episode_return,
                end,
            },
        }
    }
}

/// Failures of the log file.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    #[error("replay log {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("replay log {path}: cannot encode record: {reason}")]
    Encode { path: PathBuf, reason: String },
}

/// What opening a log found.
#[derive(Debug)]
pub struct Recovered {
    pub records: Vec<Record>,
    /// Bytes cut off a torn or corrupt tail (0 for a clean file).
    pub truncated_bytes: u64,
}

/// An open log, positioned at its end.
#[derive(Debug)]
pub struct ReplayLog {
    path: PathBuf,
    writer: BufWriter<File>,
}

impl ReplayLog {
    /// Opens (creating if needed) the log at `path`, reads every intact record and cuts off a
    /// torn tail.
    pub fn open(path: &Path) -> Result<(Self, Recovered), LogError> {
        let io = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        // Append mode: every write lands at the end of the file as it is then, so a planner that
        // lost the run (and does not know it yet) cannot overwrite the new owner's records.
        let mut file = OpenOptions::new()
            .read(true)
            .append(true)
            .create(true)
            .open(path)
            .map_err(io)?;
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes).map_err(io)?;
        let (records, good_len) = parse(&bytes);
        let truncated_bytes = bytes.len() as u64 - good_len;
        if truncated_bytes > 0 {
            file.set_len(good_len).map_err(io)?;
            file.sync_all().map_err(io)?;
        }
        file.seek(SeekFrom::Start(good_len)).map_err(io)?;
        Ok((
            Self {
                path: path.to_path_buf(),
                writer: BufWriter::new(file),
            },
            Recovered {
                records,
                truncated_bytes,
            },
        ))
    }

    /// Appends a record and hands it to the OS (survives the process being killed).
    pub fn append(&mut self, record: &Record) -> Result<(), LogError> {
        let payload =
            postcard::to_stdvec(&OnDisk::from(record.clone())).map_err(|e| LogError::Encode {
                path: self.path.clone(),
                reason: e.to_string(),
            })?;
        let io = |source| LogError::Io {
            path: self.path.clone(),
            source,
        };
        self.writer
            .write_all(&(payload.len() as u32).to_le_bytes())
            .map_err(io)?;
        self.writer
            .write_all(&crc32fast::hash(&payload).to_le_bytes())
            .map_err(io)?;
        self.writer.write_all(&payload).map_err(io)?;
        self.writer.flush().map_err(io)
    }

    /// Forces everything written so far to disk (survives power loss).
    pub fn sync(&mut self) -> Result<(), LogError> {
        let io = |source| LogError::Io {
            path: self.path.clone(),
            source,
        };
        self.writer.flush().map_err(io)?;
        self.writer.get_ref().sync_data().map_err(io)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// The intact records at the start of `bytes`, and how many bytes they span.
fn parse(bytes: &[u8]) -> (Vec<Record>, u64) {
    let mut records = Vec::new();
    let mut at = 0usize;
    while bytes.len() - at >= 8 {
        let len = u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
        let crc = u32::from_le_bytes(bytes[at + 4..at + 8].try_into().expect("4 bytes"));
        if len > MAX_RECORD || bytes.len() - at - 8 < len as usize {
            break;
        }
        let payload = &bytes[at + 8..at + 8 + len as usize];
        if crc32fast::hash(payload) != crc {
            break;
        }
        match postcard::from_bytes::<OnDisk>(payload) {
            Ok(record) => records.push(record.into()),
            Err(_) => break,
        }
        at += 8 + len as usize;
    }
    (records, at as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn transition(step: u32) -> Record {
        Record::Transition {
            epoch: 1,
            agent: "a".into(),
            episode: 0,
            step,
            obs: vec![step as f32; 4],
            act: vec![0.5],
            origin: ActionOrigin::Planned,
            next_obs: vec![step as f32 + 1.0; 4],
            reward: 0.1,
        }
    }

    fn temp_path(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("ebmpc-log-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        dir.join("replay.log")
    }

    #[test]
    fn records_survive_reopening() {
        let path = temp_path("reopen");
        let (mut log, rec) = ReplayLog::open(&path).unwrap();
        assert!(rec.records.is_empty());
        for step in 0..5 {
            log.append(&transition(step)).unwrap();
        }
        log.sync().unwrap();
        drop(log);
        let (_, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(rec.records, (0..5).map(transition).collect::<Vec<_>>());
        assert_eq!(rec.truncated_bytes, 0);
    }

    #[test]
    fn a_torn_tail_is_cut_off_at_every_cut_point() {
        let path = temp_path("torn");
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        for step in 0..3 {
            log.append(&transition(step)).unwrap();
        }
        drop(log);
        let full = std::fs::read(&path).unwrap();
        let (_, two_len) = parse(&full);
        let record_len = full.len() / 3;
        assert_eq!(two_len as usize, full.len());
        // Cut the file at every byte inside the last record: the first two always survive.
        for cut in (2 * record_len)..full.len() {
            std::fs::write(&path, &full[..cut]).unwrap();
            let (mut log, rec) = ReplayLog::open(&path).unwrap();
            assert_eq!(rec.records.len(), 2, "cut at {cut}");
            assert_eq!(rec.truncated_bytes as usize, cut - 2 * record_len);
            // Appending after recovery yields a clean log again.
            log.append(&transition(9)).unwrap();
            drop(log);
            let (_, rec) = ReplayLog::open(&path).unwrap();
            assert_eq!(rec.records.last(), Some(&transition(9)));
            assert_eq!(rec.truncated_bytes, 0);
        }
    }

    #[test]
    fn a_corrupt_byte_stops_the_log_there() {
        let path = temp_path("corrupt");
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        for step in 0..3 {
            log.append(&transition(step)).unwrap();
        }
        drop(log);
        let mut bytes = std::fs::read(&path).unwrap();
        let record_len = bytes.len() / 3;
        bytes[record_len + 12] ^= 0xff;
        std::fs::write(&path, &bytes).unwrap();
        let (_, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(rec.records, vec![transition(0)]);
    }

    /// A log written before ownership epochs (its records encoded as that release did) reads
    /// as epoch 0 with the planned actions, and new records append after it.
    #[test]
    fn a_log_from_before_epochs_is_read_and_extended() {
        /// The record type of the release before epochs, as it was.
        #[derive(Serialize)]
        enum OldRecord {
            Header {
                task: proto::TaskId,
                obs_dim: u32,
                act_dim: u32,
            },
            Transition {
                agent: String,
                episode: u32,
                step: u32,
                obs: Vec<f32>,
                act: Vec<f32>,
                next_obs: Vec<f32>,
                reward: f32,
            },
            EpisodeEnd {
                agent: String,
                episode: u32,
                steps: u32,
                episode_return: f32,
                end: proto::EpisodeEnd,
            },
        }
        let old = [
            OldRecord::Header {
                task: proto::TaskId::Cartpole,
                obs_dim: 4,
                act_dim: 1,
            },
            OldRecord::Transition {
                agent: "a".into(),
                episode: 0,
                step: 0,
                obs: vec![0.0; 4],
                act: vec![0.5],
                next_obs: vec![1.0; 4],
                reward: 0.1,
            },
            OldRecord::EpisodeEnd {
                agent: "a".into(),
                episode: 0,
                steps: 1,
                episode_return: 0.1,
                end: proto::EpisodeEnd::TimeLimit,
            },
        ];
        let mut bytes = Vec::new();
        for record in &old {
            let payload = postcard::to_stdvec(record).unwrap();
            bytes.extend_from_slice(&(payload.len() as u32).to_le_bytes());
            bytes.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
            bytes.extend_from_slice(&payload);
        }
        let path = temp_path("v1");
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, &bytes).unwrap();
        let (mut log, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(rec.truncated_bytes, 0);
        assert_eq!(
            rec.records[1],
            Record::Transition {
                epoch: 0,
                agent: "a".into(),
                episode: 0,
                step: 0,
                obs: vec![0.0; 4],
                act: vec![0.5],
                origin: ActionOrigin::Planned,
                next_obs: vec![1.0; 4],
                reward: 0.1,
            }
        );
        assert_eq!(rec.records[2].epoch(), Some(0));
        let claim = Record::Claim {
            epoch: 1,
            planner: "p".into(),
        };
        log.append(&claim).unwrap();
        log.append(&transition(1)).unwrap();
        drop(log);
        let (_, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(rec.records.len(), 5);
        assert_eq!(rec.records[3..], [claim, transition(1)]);
    }
}
