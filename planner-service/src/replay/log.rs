//! The replay buffer's file: an append-only sequence of self-delimiting, checksummed records
//! that can be found again after damage.
//!
//! ```text
//! file   := MAGIC (8 bytes) | FORMAT_VERSION: u32 LE | record*
//! record := SYNC (4 bytes) | len: u32 LE | crc32(len LE ‖ payload): u32 LE | payload: postcard(Record)
//! ```
//!
//! Every record is written whole, in one `write`, straight to the OS (no user-space buffer
//! that could flush half a record later) before the planner acknowledges the transition it
//! holds by answering with an action, so a killed daemon loses nothing it acknowledged. A
//! failed write (a full disk) is undone by truncating the file back to the end of the last
//! good record, so the file never holds a record the caller was told failed; if even that
//! truncation fails, the next append retries it first.
//!
//! On opening, a record that fails its length or checksum test is skipped and the scan
//! resynchronises on the next [`SYNC`] marker that starts an intact record: damage in the
//! middle of the file costs the damaged records only. Damage with no intact record after it is
//! a *torn tail* (a crash during a write) and is cut off, with a warning, so appends continue
//! from a clean end.
//!
//! Logs written before the format carried a header (`len | crc32(payload) | payload`, no
//! marker) are read and rewritten in this format once, on opening (new file, fsync, rename).
//!
//! Format 3 added ownership epochs and the applied action to the records (claims, and the
//! `epoch`/`origin` fields; see [`Record`]). The payloads of format 2 are valid format-3
//! payloads (the old record variants keep their tags), so a format-2 log is upgraded on opening
//! by rewriting it whole under the new version (new file, fsync, rename): from then on a build
//! that reads only format 2 refuses the file rather than taking the new records for damage and
//! cutting them off.
//!
//! Format 4 names the task in the header by its name string (tasks became data: any name a
//! catalog or an agent's spec gives). A header of formats 1–3 (the task as an index of the old
//! closed enum) is read as that task's name; such a log is upgraded like a format-2 one.
//!
//! Format 5 is one file per ownership term (a *segment*, see `super::segments`): it is created
//! whole holding its header and a [`Record::Term`] naming the earlier segments it continues
//! from, and only its term's owner ever appends to it. A file of an older format is read as it
//! is (the oldest segment of its run) and never written again.

use serde::{Deserialize, Serialize};
use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// Largest record accepted when reading; anything larger is corruption.
const MAX_RECORD: u32 = 16 << 20;

/// The first bytes of a log file in this format.
const MAGIC: &[u8; 8] = b"EBMPCRL\0";

/// The format version written after [`MAGIC`] (3: ownership epochs and applied actions; 4: the
/// header names its task by name; 5: one file per ownership term, each starting with a
/// [`Record::Term`]).
const FORMAT_VERSION: u32 = 5;

/// Bytes of the file header: magic and version.
const FILE_HEADER_LEN: usize = MAGIC.len() + 4;

/// Marks the start of every record, so a scan can find the next record after damage.
const SYNC: [u8; 4] = [0xEB, 0x5C, 0xA1, 0x7E];

/// Bytes of a record before its payload: marker, length, checksum.
const RECORD_HEADER_LEN: usize = SYNC.len() + 8;

/// One entry of the log.
///
/// Every entry an owner writes carries its ownership `epoch` (see `crate::fleet`): when a
/// planner takes a run over it writes a [`Record::Claim`] with a higher epoch, and from then on
/// entries of older epochs (written by a planner that lost the run and did not know yet) are
/// stale and skipped when the log is read.
///
/// Each variant holds a struct that is also what the file stores for it (the private `OnDisk`), so
/// the fields of an entry are declared once.
#[derive(Clone, Debug, PartialEq)]
pub enum Record {
    Header(HeaderRecord),
    Claim(ClaimRecord),
    Term(TermRecord),
    Transition(TransitionRecord),
    EpisodeEnd(EpisodeEndRecord),
}

/// First record of every file: what the buffer holds (the task by name).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeaderRecord {
    pub task: String,
    pub obs_dim: u32,
    pub act_dim: u32,
}

/// Planner `planner` took the run over at `epoch`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClaimRecord {
    pub epoch: u64,
    pub planner: String,
}

/// The second record of every segment file (see `super::segments`): the ownership term it
/// belongs to (`epoch`, the fencing token, and the `planner`), and the earlier segments the
/// run's data continues from, each up to the length this term found it at. Never part of the
/// records a buffer holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TermRecord {
    pub epoch: u64,
    pub planner: String,
    pub reads: Vec<SegmentRead>,
}

/// One transition `(s, a, s')` with its reward, from `agent`'s `episode` at `step`; `act` is
/// the action the agent applied if it said so, else the one planned (`origin` says which).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TransitionRecord {
    pub epoch: u64,
    pub agent: String,
    pub episode: u32,
    pub step: u32,
    pub obs: Vec<f32>,
    pub act: Vec<f32>,
    pub origin: ActionOrigin,
    pub next_obs: Vec<f32>,
    pub reward: f32,
}

/// `agent` finished `episode`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeEndRecord {
    pub epoch: u64,
    pub agent: String,
    pub episode: u32,
    pub steps: u32,
    pub episode_return: f32,
    pub end: proto::EpisodeEnd,
}

impl Record {
    /// The ownership epoch an entry was written under (`None` for the header and claims, which
    /// are never stale).
    pub fn epoch(&self) -> Option<u64> {
        match self {
            Record::Header(_) | Record::Claim(_) | Record::Term(_) => None,
            Record::Transition(TransitionRecord { epoch, .. })
            | Record::EpisodeEnd(EpisodeEndRecord { epoch, .. }) => Some(*epoch),
        }
    }

    /// Puts the entry under ownership epoch `to` (the header and claims carry none).
    pub fn set_epoch(&mut self, to: u64) {
        match self {
            Record::Header(_) | Record::Claim(_) | Record::Term(_) => {}
            Record::Transition(TransitionRecord { epoch, .. })
            | Record::EpisodeEnd(EpisodeEndRecord { epoch, .. }) => *epoch = to,
        }
    }
}

/// An earlier segment a term continues from, and how many of its bytes count: what a stale
/// writer appended to it after this term read it lies beyond `len` and is never read.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SegmentRead {
    /// The file, relative to the run's directory (`replay.log` or `replay/{token}-{seq}.log`).
    pub name: String,
    /// Bytes of it that count: the end of its last intact record when this term read it.
    pub len: u64,
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
/// only ever added at the end. A newtype variant of a struct is encoded exactly as a struct
/// variant with the same fields (tag, then the fields in order), so the current variants share
/// [`Record`]'s structs. Logs written before ownership epochs hold `TransitionV1` and
/// `EpisodeEndV1`; they are read as epoch 0 with the planned action and never written again.
/// Logs of formats 1–3 name their task in `HeaderV3` by the index of the closed task enum of
/// those builds; it is read as that task's name and never written again (`Header` names it).
#[derive(Serialize, Deserialize)]
enum OnDisk {
    HeaderV3 {
        task: CatalogIndexV3,
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
    Claim(ClaimRecord),
    Transition(TransitionRecord),
    EpisodeEnd(EpisodeEndRecord),
    Header(HeaderRecord),
    Term(TermRecord),
}

/// How logs of formats 1–3 named their task: postcard's index of the task enum of those
/// builds, in its declaration order (not the paper's).
#[derive(Clone, Copy, Serialize, Deserialize)]
enum CatalogIndexV3 {
    Cartpole,
    Reacher3d,
    HalfCheetah,
    Ant,
    Pusher,
}

impl CatalogIndexV3 {
    fn name(self) -> &'static str {
        match self {
            Self::Cartpole => "cartpole",
            Self::Reacher3d => "reacher3d",
            Self::HalfCheetah => "halfcheetah",
            Self::Ant => "ant",
            Self::Pusher => "pusher",
        }
    }
}

impl From<OnDisk> for Record {
    fn from(stored: OnDisk) -> Self {
        match stored {
            OnDisk::HeaderV3 {
                task,
                obs_dim,
                act_dim,
            } => Record::Header(HeaderRecord {
                task: task.name().to_string(),
                obs_dim,
                act_dim,
            }),
            OnDisk::TransitionV1 {
                agent,
                episode,
                step,
                obs,
                act,
                next_obs,
                reward,
            } => Record::Transition(TransitionRecord {
                epoch: 0,
                agent,
                episode,
                step,
                obs,
                act,
                origin: ActionOrigin::Planned,
                next_obs,
                reward,
            }),
            OnDisk::EpisodeEndV1 {
                agent,
                episode,
                steps,
                episode_return,
                end,
            } => Record::EpisodeEnd(EpisodeEndRecord {
                epoch: 0,
                agent,
                episode,
                steps,
                episode_return,
                end,
            }),
            OnDisk::Header(header) => Record::Header(header),
            OnDisk::Claim(claim) => Record::Claim(claim),
            OnDisk::Term(term) => Record::Term(term),
            OnDisk::Transition(transition) => Record::Transition(transition),
            OnDisk::EpisodeEnd(end) => Record::EpisodeEnd(end),
        }
    }
}

impl From<Record> for OnDisk {
    fn from(record: Record) -> Self {
        match record {
            Record::Header(header) => OnDisk::Header(header),
            Record::Claim(claim) => OnDisk::Claim(claim),
            Record::Term(term) => OnDisk::Term(term),
            Record::Transition(transition) => OnDisk::Transition(transition),
            Record::EpisodeEnd(end) => OnDisk::EpisodeEnd(end),
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
    #[error(
        "replay log {path}: format version {found} is newer than this build reads ({FORMAT_VERSION})"
    )]
    Format { path: PathBuf, found: u32 },
    #[error(
        "replay log {path}: claimed by another planner at epoch {found} (this one holds {held}); not rewritten"
    )]
    Fenced {
        path: PathBuf,
        held: u64,
        found: u64,
    },
}

/// What opening a log found.
#[derive(Debug, Default)]
pub struct Recovered {
    pub records: Vec<Record>,
    /// Bytes of a torn tail (0 for a clean file): ignored when a run is read (its segments
    /// are read only, so nothing is cut).
    pub truncated_bytes: u64,
    /// Damaged stretches in the middle of the file that were skipped.
    pub damaged_regions: u32,
    /// Bytes in those stretches (they stay in the file; every open skips them again).
    pub damaged_bytes: u64,
}

/// Where the log's bytes go: the file itself, or (in tests) a wrapper that fails like a full
/// disk. Writes go straight to the OS: there is no user-space buffer to hold half a record.
pub trait LogFile: Send + std::fmt::Debug {
    /// Writes all of `bytes` at the current end, or fails (possibly after writing a prefix).
    fn append_bytes(&mut self, bytes: &[u8]) -> std::io::Result<()>;
    /// Cuts the file to `len` bytes and positions the next write there.
    fn truncate_to(&mut self, len: u64) -> std::io::Result<()>;
    /// Forces the bytes written so far to disk (`fdatasync`), or fails as a device that lost
    /// them does.
    fn sync_data(&mut self) -> std::io::Result<()>;
}

impl LogFile for File {
    fn append_bytes(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.write_all(bytes)
    }

    fn truncate_to(&mut self, len: u64) -> std::io::Result<()> {
        self.set_len(len)?;
        self.seek(SeekFrom::Start(len)).map(|_| ())
    }

    fn sync_data(&mut self) -> std::io::Result<()> {
        File::sync_data(self)
    }
}

/// A handle that forces the log's written bytes to disk. It is separate from the writer so
/// that fsync runs on the blocking pool without holding the replay buffer's lock.
///
/// Every clone syncs the log's *current* file: a compaction moves writing to a new file (see
/// [`ReplayLog::finish_rewrite`]), and a store that appended to the old file and syncs after
/// the swap must make the new file durable, since the new file is the one that counts from
/// then on (it holds a copy of what the old one held). After a swap the directory entry is
/// synced once too, by the first sync that comes, before anything written to the new file is
/// acknowledged.
#[derive(Clone, Debug)]
pub struct LogSyncer {
    path: PathBuf,
    target: Arc<Mutex<SyncTarget>>,
    /// Appends made to the log so far (a sequence number, not bytes).
    appended: Arc<std::sync::atomic::AtomicU64>,
    /// The appends known durable; held across a group commit's fsync, so that the callers
    /// waiting behind it find their appends covered and sync nothing more.
    durable: Arc<Mutex<u64>>,
}

/// The file a [`LogSyncer`] syncs, and whether its name in the directory is not yet durable.
#[derive(Debug)]
struct SyncTarget {
    file: Arc<File>,
    directory_unsynced: bool,
}

impl LogSyncer {
    fn new(path: &Path, file: &File) -> std::io::Result<Self> {
        Ok(Self {
            path: path.to_path_buf(),
            target: Arc::new(Mutex::new(SyncTarget {
                file: Arc::new(file.try_clone()?),
                directory_unsynced: false,
            })),
            appended: Arc::default(),
            durable: Arc::default(),
        })
    }

    /// The number of appends made so far: what [`LogSyncer::sync_through`] is given to make
    /// one's own appends durable.
    pub fn appended(&self) -> u64 {
        self.appended.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// Group commit: returns once the first `appends` appends are on stable storage, with one
    /// fsync for every batch of callers. A caller that finds an fsync under way waits for it,
    /// and the next fsync covers every append made until it starts, so agents that store at
    /// the same moment share one fsync instead of queueing one each.
    pub fn sync_through(&self, appends: u64) -> Result<(), LogError> {
        let mut durable = self.durable.lock().unwrap_or_else(PoisonError::into_inner);
        if *durable >= appends {
            return Ok(());
        }
        let covered = self.appended();
        self.sync()?;
        *durable = covered;
        Ok(())
    }

    fn target(&self) -> std::sync::MutexGuard<'_, SyncTarget> {
        self.target.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Forces everything written so far to disk (survives power loss). The target's lock is
    /// held only to read which file to sync, never across the fsync.
    pub fn sync(&self) -> Result<(), LogError> {
        let io = |source| LogError::Io {
            path: self.path.clone(),
            source,
        };
        let (file, directory_unsynced) = {
            let target = self.target();
            (target.file.clone(), target.directory_unsynced)
        };
        file.sync_data().map_err(io)?;
        if directory_unsynced {
            sync_directory(&self.path).map_err(io)?;
            let mut target = self.target();
            if Arc::ptr_eq(&target.file, &file) {
                target.directory_unsynced = false;
            }
        }
        Ok(())
    }

    /// Syncs the log's directory entry if a compaction renamed a new file over the log and no
    /// sync has made the new name durable yet (see [`LogSyncer::sync`]).
    fn sync_directory_if_swapped(&self) -> Result<(), LogError> {
        let mut target = self.target();
        if target.directory_unsynced {
            sync_directory(&self.path).map_err(|source| LogError::Io {
                path: self.path.clone(),
                source,
            })?;
            target.directory_unsynced = false;
        }
        Ok(())
    }

    /// Points every clone at `file`, newly renamed over the log's path.
    fn swap(&self, file: &File) -> std::io::Result<()> {
        let file = Arc::new(file.try_clone()?);
        let mut target = self.target();
        target.file = file;
        target.directory_unsynced = true;
        Ok(())
    }
}

/// An open log, positioned at its end.
#[derive(Debug)]
pub struct ReplayLog {
    path: PathBuf,
    file: Box<dyn LogFile>,
    syncer: LogSyncer,
    /// End of the last record known to be whole in the file.
    end: u64,
    /// A failed write may have left bytes after `end` that could not be cut yet.
    dirty: bool,
    /// Other planners may read this file while it is written (a fleet: a newer owner records
    /// how far it read this segment, and its data continues from there). Then nothing here
    /// ever cuts the file: a failed write's partial bytes stay (readers skip them as a damaged
    /// record) rather than being cut off, since records written after a cut could land
    /// inside the length a newer owner recorded.
    shared: bool,
}

impl ReplayLog {
    /// Opens (creating if needed) the log at `path` in the current format, reads every intact
    /// record, skips damaged ones and cuts off a torn tail. Tests only: the
    /// service never reopens a file for writing (a term writes only the segment it created,
    /// [`ReplayLog::create_with`], and reads the others with [`ReplayLog::read_prefix`]), since
    /// cutting or rewriting a file another planner may have read would break the fence.
    #[cfg(test)]
    pub fn open(path: &Path) -> Result<(Self, Recovered), LogError> {
        Self::open_with(path, |file| Box::new(file))
    }

    /// As [`ReplayLog::open`], writing through `wrap(file)` (tests inject a failing disk).
    #[cfg(test)]
    pub fn open_with(
        path: &Path,
        wrap: impl FnOnce(File) -> Box<dyn LogFile>,
    ) -> Result<(Self, Recovered), LogError> {
        let io = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        let mut bytes = Vec::new();
        open_rw(path)
            .and_then(|mut f| f.read_to_end(&mut bytes))
            .map_err(io)?;
        let recovered = if let Some(version) = current_version(path, &bytes)? {
            assert_eq!(
                version, FORMAT_VERSION,
                "older logs are read (ReplayLog::read), never written again"
            );
            let (recovered, good_len) = scan(&bytes);
            if recovered.truncated_bytes > 0 {
                let file = open_rw(path).map_err(io)?;
                file.set_len(good_len).map_err(io)?;
                file.sync_all().map_err(io)?;
            }
            recovered
        } else if bytes.len() < FILE_HEADER_LEN
            && MAGIC.starts_with(&bytes[..bytes.len().min(MAGIC.len())])
        {
            // New, or a crash while its header was written: start it afresh.
            write_file(path, &[]).map_err(io)?;
            Recovered::default()
        } else {
            panic!(
                "{}: a log of the first format is read, never written again",
                path.display()
            )
        };
        let file = open_append(path).map_err(io)?;
        let end = file.metadata().map_err(io)?.len();
        let syncer = LogSyncer::new(path, &file).map_err(io)?;
        let mut file = wrap(file);
        file.truncate_to(end).map_err(io)?;
        Ok((
            Self {
                path: path.to_path_buf(),
                file,
                syncer,
                end,
                dirty: false,
                shared: false,
            },
            recovered,
        ))
    }

    /// Reads every intact record of the log at `path` without writing anything: a torn tail
    /// and damaged stretches are skipped, but nothing
    /// is cut or rewritten, so this is safe beside a daemon that is appending. A log in the
    /// format before the current one is read as well; an empty or missing file holds nothing.
    pub fn read(path: &Path) -> Result<Recovered, LogError> {
        Ok(Self::read_prefix(path, None)?.0)
    }

    /// As [`ReplayLog::read`], reading only the first `limit` bytes of the file (all of it for
    /// `None`); also returns the end of the last intact record read (the file's length that
    /// counts). A missing file holds nothing.
    pub fn read_prefix(path: &Path, limit: Option<u64>) -> Result<(Recovered, u64), LogError> {
        let io = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        let mut bytes = Vec::new();
        match File::open(path) {
            Ok(file) => {
                file.take(limit.unwrap_or(u64::MAX))
                    .read_to_end(&mut bytes)
                    .map_err(io)?;
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok((Recovered::default(), 0));
            }
            Err(e) => return Err(io(e)),
        }
        if current_version(path, &bytes)?.is_some() {
            Ok(scan(&bytes))
        } else if bytes.len() < FILE_HEADER_LEN
            && MAGIC.starts_with(&bytes[..bytes.len().min(MAGIC.len())])
        {
            Ok((Recovered::default(), 0))
        } else {
            let (records, parsed) = parse_legacy(&bytes);
            Ok((
                Recovered {
                    records,
                    truncated_bytes: (bytes.len() - parsed) as u64,
                    ..Recovered::default()
                },
                parsed as u64,
            ))
        }
    }

    /// Creates the new file at `path` holding `records` (a segment's header and term) and
    /// opens it for appending, writing through `wrap(file)`. The file appears whole or not at
    /// all: it is written to a temporary file, synced, linked to `path` (which fails if `path`
    /// exists: no file is ever replaced) and the directory synced, so it is durable before
    /// anything appended to it is acknowledged.
    pub fn create_with(
        path: &Path,
        records: &[Record],
        wrap: impl FnOnce(File) -> Box<dyn LogFile>,
    ) -> Result<Self, LogError> {
        let io = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        if let Some(dir) = path.parent()
            && !dir.is_dir()
        {
            // A new directory: its own entry must be durable too.
            std::fs::create_dir_all(dir).map_err(io)?;
            sync_directory(dir).map_err(io)?;
        }
        let mut framed = Vec::new();
        for record in records {
            encode_record(path, record, &mut framed)?;
        }
        let tmp = path.with_extension("log.tmp");
        let mut file = File::create(&tmp).map_err(io)?;
        file.write_all(MAGIC).map_err(io)?;
        file.write_all(&FORMAT_VERSION.to_le_bytes()).map_err(io)?;
        file.write_all(&framed).map_err(io)?;
        file.sync_all().map_err(io)?;
        drop(file);
        publish(&tmp, path).map_err(io)?;
        let file = open_append(path).map_err(io)?;
        let end = file.metadata().map_err(io)?.len();
        let syncer = LogSyncer::new(path, &file).map_err(io)?;
        Ok(Self {
            path: path.to_path_buf(),
            file: wrap(file),
            syncer,
            end,
            dirty: false,
            shared: false,
        })
    }

    /// Appends `records` in one write and hands them to the OS (they survive the process
    /// being killed). On failure none of them is in the log: the file is cut back to where it
    /// ended before, and the caller can try again later.
    pub fn append(&mut self, records: &[Record]) -> Result<(), LogError> {
        let mut bytes = Vec::new();
        for record in records {
            encode_record(&self.path, record, &mut bytes)?;
        }
        let io = |source| LogError::Io {
            path: self.path.clone(),
            source,
        };
        if self.dirty && !self.shared {
            self.file.truncate_to(self.end).map_err(io)?;
            self.dirty = false;
        }
        if let Err(e) = self.file.append_bytes(&bytes) {
            if self.shared {
                tracing::warn!(path = %self.path.display(), error = %e, "a write to the shared replay log failed; its partial bytes stay (readers skip them)");
                return Err(io(e));
            }
            self.dirty = true;
            match self.file.truncate_to(self.end) {
                Ok(()) => self.dirty = false,
                Err(cut) => {
                    tracing::error!(path = %self.path.display(), error = %cut, "cannot cut a failed write off the replay log; retrying before the next write")
                }
            }
            return Err(io(e));
        }
        self.end += bytes.len() as u64;
        self.syncer
            .appended
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        Ok(())
    }

    /// Appends `records` as [`ReplayLog::append`] does and forces them to disk through the
    /// log's writer before returning. If the sync fails they are taken back (cut off the file,
    /// as a failed write is): after a failed `fsync` Linux may drop the pages it could not
    /// write and report a later `fsync` of them as a success, so records whose sync failed
    /// are never counted as stored; the caller refuses what they came from, and the records
    /// are written afresh when it is sent again. A shared file ([`ReplayLog::share`]) is never
    /// cut: a newer owner may have read past these records, so they stay (unacknowledged, and
    /// stored again when the step is sent again). Returns the time the sync took.
    pub fn append_synced(&mut self, records: &[Record]) -> Result<Duration, LogError> {
        let before = self.end;
        self.append(records)?;
        let started = Instant::now();
        let synced = self
            .file
            .sync_data()
            .map_err(|source| LogError::Io {
                path: self.path.clone(),
                source,
            })
            .and_then(|()| self.syncer.sync_directory_if_swapped());
        let took = started.elapsed();
        if let Err(e) = synced {
            if self.shared {
                tracing::warn!(path = %self.path.display(), error = %e, "syncing the shared replay log failed; its records stay (a shared file is never cut)");
                return Err(e);
            }
            self.end = before;
            self.dirty = true;
            match self.file.truncate_to(before) {
                Ok(()) => self.dirty = false,
                Err(cut) => {
                    tracing::error!(path = %self.path.display(), error = %cut, "cannot cut records whose sync failed off the replay log; retrying before the next write")
                }
            }
            return Err(e);
        }
        Ok(took)
    }

    /// Marks the file as read by other planners while it is written: from now on it is
    /// never cut (a failed write leaves its partial bytes).
    pub fn share(&mut self) {
        self.shared = true;
    }

    /// Starts rewriting the run's data without the records `keep` refuses (a compaction)
    /// into a new segment `target` of this term, in three steps so that the caller holds its
    /// buffer's lock only for the first and the last, and never across an fsync:
    ///
    /// 1. this call (lock held): cuts the bytes of a failed write, if any, and names the job;
    /// 2. [`Rewrite::copy`] (no lock): copies the kept records of the `earlier` segments (each
    ///    up to its length that counts) and of this log into a temporary file, starting with
    ///    `head` (the new segment's header and term), and fsyncs it; called again, it copies
    ///    what was appended to this log since (the *catch-up*);
    /// 3. [`ReplayLog::finish_rewrite`] (lock held): if this log has not grown since the last
    ///    copy, gives the new file its name `target` (never replacing a file) and writes on
    ///    there; otherwise it hands the job back for another catch-up.
    ///
    /// No file is changed: the old segments stay until the caller removes them once the new
    /// one is durable, and a crash at any moment leaves the old segments (the new one is not
    /// there, or not yet named by a durable directory entry) or the new one, each holding
    /// every record acknowledged. Writing continues on the new file through the plain file: a
    /// wrapper given to [`ReplayLog::create_with`] is not carried over.
    ///
    /// A copy fails with [`LogError::Fenced`] if `newer_term` names a term newer than
    /// `held_epoch`, the one the caller owns the run at: the run has moved on, and the caller's
    /// compaction must not become part of it.
    pub fn start_rewrite(
        &mut self,
        plan: RewritePlan,
        keep: impl FnMut(&Record) -> bool + Send + 'static,
    ) -> Result<Rewrite, LogError> {
        if self.dirty {
            self.file
                .truncate_to(self.end)
                .map_err(|source| LogError::Io {
                    path: self.path.clone(),
                    source,
                })?;
            self.dirty = false;
        }
        Ok(Rewrite {
            path: self.path.clone(),
            tmp: plan.target.with_extension("log.compacting"),
            plan,
            out: None,
            copied_to: 0,
            keep: Box::new(keep),
        })
    }

    /// Ends a rewrite whose last [`Rewrite::copy`] reached the end of the log: the new file
    /// gets its name and writing continues there (`Ok(None)`; this log's path is the new
    /// segment's from then on). If records were appended since that copy, nothing changes
    /// and the job comes back (`Ok(Some(job))`) for another copy. The directory entry is
    /// synced by the next [`LogSyncer::sync`], outside any lock.
    pub fn finish_rewrite(&mut self, job: Rewrite) -> Result<Option<Rewrite>, LogError> {
        let io = |source| LogError::Io {
            path: self.path.clone(),
            source,
        };
        if self.dirty {
            self.file.truncate_to(self.end).map_err(io)?;
            self.dirty = false;
        }
        let on_disk = std::fs::metadata(&self.path).map_err(io)?.len();
        if on_disk != job.copied_to || job.out.is_none() {
            return Ok(Some(job));
        }
        if let Some(found) = (job.plan.newer_term)().filter(|&t| t > job.plan.held_epoch) {
            let held = job.plan.held_epoch;
            job.abandon();
            return Err(LogError::Fenced {
                path: self.path.clone(),
                held,
                found,
            });
        }
        let target = job.plan.target.clone();
        std::fs::hard_link(&job.tmp, &target).map_err(io)?;
        if let Err(e) = std::fs::remove_file(&job.tmp) {
            tracing::warn!(path = %job.tmp.display(), error = %e, "cannot remove a compaction's temporary name");
        }
        let mut file = open_append(&target).map_err(io)?;
        let end = file.metadata().map_err(io)?.len();
        file.truncate_to(end).map_err(io)?;
        self.syncer.swap(&file).map_err(io)?;
        self.file = Box::new(file);
        self.path = target;
        self.end = end;
        Ok(None)
    }

    /// A handle that syncs this log to disk, usable without holding the log.
    pub fn syncer(&self) -> LogSyncer {
        self.syncer.clone()
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes of the log file up to its last whole record: its size on disk (once synced).
    pub fn len_bytes(&self) -> u64 {
        self.end
    }
}

/// What a compaction writes (see [`ReplayLog::start_rewrite`]).
pub struct RewritePlan {
    /// The new segment.
    pub target: PathBuf,
    /// Its first records: the header and its term.
    pub head: Vec<Record>,
    /// The earlier segments the log continues from, each with its length that counts.
    pub earlier: Vec<(PathBuf, u64)>,
    /// The ownership term the caller holds.
    pub held_epoch: u64,
    /// The newest term that has a segment, if any is newer than the caller's.
    pub newer_term: Box<dyn Fn() -> Option<u64> + Send>,
}

/// A compaction in progress (see [`ReplayLog::start_rewrite`]): the new file being written
/// beside the log and how far into the log it has copied.
pub struct Rewrite {
    /// The segment being compacted (the one its term appends to).
    path: PathBuf,
    tmp: PathBuf,
    plan: RewritePlan,
    out: Option<File>,
    /// Bytes of the log copied (or skipped as refused) so far.
    copied_to: u64,
    keep: Box<dyn FnMut(&Record) -> bool + Send>,
}

impl std::fmt::Debug for Rewrite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Rewrite")
            .field("path", &self.path)
            .field("target", &self.plan.target)
            .field("copied_to", &self.copied_to)
            .field("held_epoch", &self.plan.held_epoch)
            .finish_non_exhaustive()
    }
}

impl Rewrite {
    /// Copies the records after the last copy into the new file, keeping those `keep`
    /// accepts, and fsyncs it. The first call reads the earlier segments (up to their lengths
    /// that count) and the whole log (skipping damaged stretches, as reading does); later calls
    /// read only what was appended to the log since, up to the last whole record (a write
    /// still under way is copied next time). Headers and terms are not copied: the new file
    /// has its own. Takes no lock: the buffer keeps storing meanwhile.
    pub fn copy(&mut self) -> Result<(), LogError> {
        let io = |source| LogError::Io {
            path: self.path.clone(),
            source,
        };
        if let Some(found) = (self.plan.newer_term)().filter(|&t| t > self.plan.held_epoch) {
            return Err(LogError::Fenced {
                path: self.path.clone(),
                held: self.plan.held_epoch,
                found,
            });
        }
        let mut source = File::open(&self.path).map_err(io)?;
        source.seek(SeekFrom::Start(self.copied_to)).map_err(io)?;
        let mut bytes = Vec::new();
        source.read_to_end(&mut bytes).map_err(io)?;
        let (records, consumed) = if self.out.is_none() {
            let mut records = Vec::new();
            for (earlier, len) in &self.plan.earlier {
                records.extend(ReplayLog::read_prefix(earlier, Some(*len))?.0.records);
            }
            let (recovered, good_end) = scan(&bytes);
            records.extend(recovered.records);
            (records, good_end)
        } else {
            let (mut records, mut at) = (Vec::new(), 0);
            while let Some((record, next)) = read_record(&bytes, at) {
                records.push(record);
                at = next;
            }
            (records, at as u64)
        };
        let mut framed = Vec::new();
        for record in records
            .iter()
            .filter(|r| !matches!(r, Record::Header(_) | Record::Term(_)))
            .filter(|r| (self.keep)(r))
        {
            encode_record(&self.path, record, &mut framed)?;
        }
        let out = match &mut self.out {
            Some(out) => out,
            None => {
                let mut out = File::create(&self.tmp).map_err(io)?;
                out.write_all(MAGIC).map_err(io)?;
                out.write_all(&FORMAT_VERSION.to_le_bytes()).map_err(io)?;
                let mut head = Vec::new();
                for record in &self.plan.head {
                    encode_record(&self.path, record, &mut head)?;
                }
                out.write_all(&head).map_err(io)?;
                self.out.insert(out)
            }
        };
        out.write_all(&framed).map_err(io)?;
        out.sync_data().map_err(io)?;
        self.copied_to += consumed;
        Ok(())
    }

    /// Gives the rewrite up, removing its half-written file; the log is untouched.
    pub fn abandon(self) {
        if self.out.is_some()
            && let Err(e) = std::fs::remove_file(&self.tmp)
        {
            tracing::warn!(path = %self.tmp.display(), error = %e, "cannot remove an abandoned compaction's file");
        }
    }
}

/// Makes the entries of `path`'s directory durable (a rename or a new file).
fn sync_directory(path: &Path) -> std::io::Result<()> {
    match path.parent() {
        Some(dir) => File::open(dir)?.sync_all(),
        None => Ok(()),
    }
}

/// Gives the finished file `tmp` its final name `path` without ever replacing a file there (a
/// hard link fails if `path` exists), removes the temporary name and syncs the directory.
fn publish(tmp: &Path, path: &Path) -> std::io::Result<()> {
    std::fs::hard_link(tmp, path)?;
    std::fs::remove_file(tmp)?;
    sync_directory(path)
}

#[cfg(test)]
fn open_rw(path: &Path) -> std::io::Result<File> {
    OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)
}

/// The writer's handle: in append mode, every write lands at the end of the file as it is
/// then, so a planner that lost the run (and does not know it yet) cannot overwrite the new
/// owner's records (see `crate::fleet`).
fn open_append(path: &Path) -> std::io::Result<File> {
    OpenOptions::new()
        .read(true)
        .append(true)
        .create(true)
        .open(path)
}

/// The format version of a file in the current format (`None`: empty, a torn header, or the
/// old format), refusing a version newer than this build reads.
fn current_version(path: &Path, bytes: &[u8]) -> Result<Option<u32>, LogError> {
    if !is_current_format(bytes) {
        return Ok(None);
    }
    let version = u32::from_le_bytes(
        bytes[MAGIC.len()..FILE_HEADER_LEN]
            .try_into()
            .expect("4 bytes"),
    );
    if version > FORMAT_VERSION {
        return Err(LogError::Format {
            path: path.to_path_buf(),
            found: version,
        });
    }
    Ok(Some(version))
}

fn is_current_format(bytes: &[u8]) -> bool {
    bytes.len() >= FILE_HEADER_LEN && bytes.starts_with(MAGIC)
}

/// Appends `record`, encoded as it is stored ([`OnDisk`]) and framed, to `out`.
fn encode_record(path: &Path, record: &Record, out: &mut Vec<u8>) -> Result<(), LogError> {
    let payload =
        postcard::to_stdvec(&OnDisk::from(record.clone())).map_err(|e| LogError::Encode {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
    frame(&payload, out);
    Ok(())
}

/// Appends one framed record holding `payload` to `out`.
fn frame(payload: &[u8], out: &mut Vec<u8>) {
    let len = (payload.len() as u32).to_le_bytes();
    let mut crc = crc32fast::Hasher::new();
    crc.update(&len);
    crc.update(payload);
    out.extend_from_slice(&SYNC);
    out.extend_from_slice(&len);
    out.extend_from_slice(&crc.finalize().to_le_bytes());
    out.extend_from_slice(payload);
}

/// The record that starts at `at`, and where the next one starts, if the bytes there are an
/// intact record.
fn read_record(bytes: &[u8], at: usize) -> Option<(Record, usize)> {
    let head = bytes.get(at..at + RECORD_HEADER_LEN)?;
    if head[..4] != SYNC {
        return None;
    }
    let len_bytes: [u8; 4] = head[4..8].try_into().expect("4 bytes");
    let len = u32::from_le_bytes(len_bytes);
    let crc = u32::from_le_bytes(head[8..12].try_into().expect("4 bytes"));
    if len > MAX_RECORD {
        return None;
    }
    let start = at + RECORD_HEADER_LEN;
    let payload = bytes.get(start..start + len as usize)?;
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&len_bytes);
    hasher.update(payload);
    if hasher.finalize() != crc {
        return None;
    }
    let record = postcard::from_bytes::<OnDisk>(payload).ok()?;
    Some((record.into(), start + len as usize))
}

/// Every intact record of a current-format file, and the length of the file up to the end of
/// the last one (what follows is a torn tail).
fn scan(bytes: &[u8]) -> (Recovered, u64) {
    let mut recovered = Recovered::default();
    let mut at = FILE_HEADER_LEN;
    let mut good_end = at;
    loop {
        if let Some((record, next)) = read_record(bytes, at) {
            recovered.records.push(record);
            at = next;
            good_end = next;
            continue;
        }
        let resync = (at + 1..bytes.len().saturating_sub(RECORD_HEADER_LEN - 1))
            .filter(|&q| bytes[q..q + SYNC.len()] == SYNC)
            .find(|&q| read_record(bytes, q).is_some());
        match resync {
            Some(q) => {
                recovered.damaged_regions += 1;
                recovered.damaged_bytes += (q - at) as u64;
                at = q;
            }
            None => break,
        }
    }
    recovered.truncated_bytes = (bytes.len() - good_end) as u64;
    (recovered, good_end as u64)
}

/// The intact records at the start of a log in the old format (`len | crc32(payload) |
/// payload`, no marker: nothing after the first damaged record can be found again).
fn parse_legacy(bytes: &[u8]) -> (Vec<Record>, usize) {
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
    (records, at)
}

/// Writes a current-format file holding the already framed `records` atomically: a temporary
/// file, fsynced, renamed over `path`, and the directory fsynced (for [`ReplayLog::open`]).
#[cfg(test)]
fn write_file(path: &Path, records: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension("log.tmp");
    let mut file = File::create(&tmp)?;
    file.write_all(MAGIC)?;
    file.write_all(&FORMAT_VERSION.to_le_bytes())?;
    file.write_all(records)?;
    file.sync_all()?;
    drop(file);
    std::fs::rename(&tmp, path)?;
    sync_directory(path)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};

    fn transition(step: u32) -> Record {
        Record::Transition(TransitionRecord {
            epoch: 1,
            agent: "a".into(),
            episode: 0,
            step,
            obs: vec![step as f32; 4],
            act: vec![0.5],
            origin: ActionOrigin::Planned,
            next_obs: vec![step as f32 + 1.0; 4],
            reward: 0.1,
        })
    }

    fn temp_path(dir: &tempfile::TempDir) -> PathBuf {
        dir.path().join("replay.log")
    }

    /// Transition `step` as the releases before ownership epochs encoded it (formats 1 and 2),
    /// and what reading it gives: epoch 0, the planned action.
    fn old_transition(step: u32) -> (Vec<u8>, Record) {
        let payload = postcard::to_stdvec(&OnDisk::TransitionV1 {
            agent: "a".into(),
            episode: 0,
            step,
            obs: vec![step as f32; 4],
            act: vec![0.5],
            next_obs: vec![step as f32 + 1.0; 4],
            reward: 0.1,
        })
        .unwrap();
        let mut read = transition(step);
        read.set_epoch(0);
        (payload, read)
    }

    /// A disk that fills up on demand: while `full` is set, every write puts a prefix of its
    /// bytes in the file (as a real `ENOSPC` after a partial write does) and fails.
    #[derive(Debug)]
    pub(crate) struct FillingDisk {
        pub(crate) file: File,
        pub(crate) full: Arc<AtomicBool>,
    }

    impl LogFile for FillingDisk {
        fn append_bytes(&mut self, bytes: &[u8]) -> std::io::Result<()> {
            if self.full.load(Ordering::SeqCst) {
                Write::write_all(&mut self.file, &bytes[..bytes.len() / 2])?;
                return Err(std::io::Error::from_raw_os_error(28)); // ENOSPC
            }
            Write::write_all(&mut self.file, bytes)
        }

        fn truncate_to(&mut self, len: u64) -> std::io::Result<()> {
            self.file.truncate_to(len)
        }

        fn sync_data(&mut self) -> std::io::Result<()> {
            self.file.sync_data()
        }
    }

    #[test]
    fn records_survive_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let (mut log, rec) = ReplayLog::open(&path).unwrap();
        assert!(rec.records.is_empty());
        for step in 0..5 {
            log.append(&[transition(step)]).unwrap();
        }
        log.syncer().sync().unwrap();
        drop(log);
        let (_, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(rec.records, (0..5).map(transition).collect::<Vec<_>>());
        assert_eq!((rec.truncated_bytes, rec.damaged_regions), (0, 0));
    }

    /// A syncer handed out before a compaction swapped the file syncs the new file afterwards
    /// (the one the path names), and the first sync after the swap makes the rename durable.
    #[test]
    fn a_syncer_taken_before_a_compaction_syncs_the_file_that_replaced_the_log() {
        use std::os::unix::fs::MetadataExt;
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        for step in 0..6 {
            log.append(&[transition(step)]).unwrap();
        }
        let early = log.syncer();
        let target = dir.path().join("compacted.log");
        let plan = RewritePlan {
            target: target.clone(),
            head: Vec::new(),
            earlier: Vec::new(),
            held_epoch: 1,
            newer_term: Box::new(|| None),
        };
        let mut job = log
            .start_rewrite(
                plan,
                |r| !matches!(r, Record::Transition(TransitionRecord { step, .. }) if *step < 3),
            )
            .unwrap();
        job.copy().unwrap();
        assert!(log.finish_rewrite(job).unwrap().is_none());
        let synced_inode = early.target().file.metadata().unwrap().ino();
        assert_eq!(synced_inode, std::fs::metadata(&target).unwrap().ino());
        assert_eq!(log.path(), target, "writing goes on in the new file");
        assert!(
            path.exists(),
            "the old file is left for its owner to remove"
        );
        assert!(early.target().directory_unsynced);
        early.sync().unwrap();
        assert!(
            !log.syncer().target().directory_unsynced,
            "one sync for all clones"
        );
        log.append(&[transition(6)]).unwrap();
        drop(log);
        let (_, rec) = ReplayLog::open(&target).unwrap();
        assert_eq!(rec.records, (3..7).map(transition).collect::<Vec<_>>());
    }

    #[test]
    fn a_torn_tail_is_cut_off_at_every_cut_point() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        for step in 0..3 {
            log.append(&[transition(step)]).unwrap();
        }
        drop(log);
        let full = std::fs::read(&path).unwrap();
        let record_len = (full.len() - FILE_HEADER_LEN) / 3;
        let two_end = FILE_HEADER_LEN + 2 * record_len;
        // Cut the file at every byte inside the last record: the first two always survive.
        for cut in two_end..full.len() {
            std::fs::write(&path, &full[..cut]).unwrap();
            let (mut log, rec) = ReplayLog::open(&path).unwrap();
            assert_eq!(rec.records.len(), 2, "cut at {cut}");
            assert_eq!(rec.truncated_bytes as usize, cut - two_end);
            assert_eq!(rec.damaged_regions, 0);
            // Appending after recovery yields a clean log again.
            log.append(&[transition(9)]).unwrap();
            drop(log);
            let (_, rec) = ReplayLog::open(&path).unwrap();
            assert_eq!(rec.records.last(), Some(&transition(9)));
            assert_eq!(rec.truncated_bytes, 0);
        }
    }

    #[test]
    fn a_damaged_record_in_the_middle_costs_that_record_only() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        for step in 0..5 {
            log.append(&[transition(step)]).unwrap();
        }
        drop(log);
        let clean = std::fs::read(&path).unwrap();
        let record_len = (clean.len() - FILE_HEADER_LEN) / 5;
        // Damage every byte of record 1 in turn (marker, length, checksum, payload): records
        // 0, 2, 3 and 4 are always found, and nothing is cut off the end.
        for offset in 0..record_len {
            let mut bytes = clean.clone();
            bytes[FILE_HEADER_LEN + record_len + offset] ^= 0xff;
            std::fs::write(&path, &bytes).unwrap();
            let (mut log, rec) = ReplayLog::open(&path).unwrap();
            let expected: Vec<_> = [0, 2, 3, 4].into_iter().map(transition).collect();
            assert_eq!(rec.records, expected, "byte {offset} of record 1 damaged");
            assert_eq!(rec.damaged_regions, 1);
            assert_eq!(rec.damaged_bytes as usize, record_len);
            assert_eq!(rec.truncated_bytes, 0);
            // New records go after the intact ones and are found again.
            log.append(&[transition(5)]).unwrap();
            drop(log);
            let (_, rec) = ReplayLog::open(&path).unwrap();
            assert_eq!(rec.records.len(), 5);
            assert_eq!(rec.records.last(), Some(&transition(5)));
        }
    }

    #[test]
    fn a_log_in_the_first_format_reads_every_record_and_stays_as_it_is() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        // The format written before this one: len | crc32(payload) | payload.
        let mut old = Vec::new();
        let mut expected = Vec::new();
        for step in 0..4 {
            let (payload, read) = old_transition(step);
            old.extend_from_slice(&(payload.len() as u32).to_le_bytes());
            old.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
            old.extend_from_slice(&payload);
            expected.push(read);
        }
        std::fs::write(&path, &old).unwrap();
        let rec = ReplayLog::read(&path).unwrap();
        assert_eq!(rec.records, expected);
        assert_eq!(rec.truncated_bytes, 0);
        assert_eq!(std::fs::read(&path).unwrap(), old);
    }

    #[test]
    fn a_first_format_log_with_a_torn_tail_reads_up_to_it_and_stays_as_it_is() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let (payload, read) = old_transition(0);
        let mut old = (payload.len() as u32).to_le_bytes().to_vec();
        old.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        old.extend_from_slice(&payload);
        old.extend_from_slice(&[7, 0, 0]);
        std::fs::write(&path, &old).unwrap();
        let rec = ReplayLog::read(&path).unwrap();
        assert_eq!(rec.records, vec![read]);
        assert_eq!(rec.truncated_bytes, 3);
        assert_eq!(std::fs::read(&path).unwrap(), old);
    }

    #[test]
    fn a_failed_write_leaves_nothing_behind_and_writing_resumes_when_space_returns() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let full = Arc::new(AtomicBool::new(false));
        let disk = full.clone();
        let (mut log, _) =
            ReplayLog::open_with(&path, |file| Box::new(FillingDisk { file, full: disk })).unwrap();
        log.append(&[transition(0)]).unwrap();
        let before = std::fs::read(&path).unwrap();
        full.store(true, Ordering::SeqCst);
        let err = log.append(&[transition(1), transition(2)]).unwrap_err();
        assert!(err.to_string().contains("os error 28"), "{err}");
        assert_eq!(
            std::fs::read(&path).unwrap(),
            before,
            "the half write is cut"
        );
        full.store(false, Ordering::SeqCst);
        log.append(&[transition(1)]).unwrap();
        drop(log);
        let (_, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(rec.records, vec![transition(0), transition(1)]);
        assert_eq!((rec.truncated_bytes, rec.damaged_regions), (0, 0));
    }

    /// Two handles on one file marked shared: one write fails half-way (a full disk) after
    /// the other appended records. Nothing the other wrote is cut: the half record stays, a
    /// damaged region readers skip. (A fleet's segment has one writer, but a newer owner may
    /// have recorded a length of it that a cut would put new records under.)
    #[test]
    fn a_fenced_owners_failed_write_deletes_nothing_of_the_new_owners() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let full = Arc::new(AtomicBool::new(false));
        let disk = full.clone();
        let (mut stale, _) =
            ReplayLog::open_with(&path, |file| Box::new(FillingDisk { file, full: disk })).unwrap();
        stale.share();
        stale.append(&[transition(0)]).unwrap();
        let (mut owner, rec) = ReplayLog::open(&path).unwrap();
        owner.share();
        assert_eq!(rec.records, vec![transition(0)]);
        let claim = Record::Claim(ClaimRecord {
            epoch: 9,
            planner: "new".into(),
        });
        owner
            .append(&[claim.clone(), transition(1), transition(2)])
            .unwrap();
        full.store(true, Ordering::SeqCst);
        assert!(stale.append(&[transition(3)]).is_err());
        // The fenced owner tries again (its next step): still failing, still cutting nothing.
        assert!(stale.append(&[transition(4)]).is_err());
        owner.append(&[transition(5)]).unwrap();
        drop((stale, owner));
        let (_, rec) = ReplayLog::open(&path).unwrap();
        assert_eq!(
            rec.records,
            vec![
                transition(0),
                claim,
                transition(1),
                transition(2),
                transition(5)
            ]
        );
        assert!(rec.damaged_regions >= 1);
    }

    /// Group commit: appends are counted, and a sync through a count covers every append up
    /// to it; a caller whose appends are covered syncs nothing more.
    #[test]
    fn a_group_commit_covers_every_append_made_before_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        let syncer = log.syncer();
        assert_eq!(syncer.appended(), 0);
        log.append(&[transition(0)]).unwrap();
        let mine = syncer.appended();
        log.append(&[transition(1)]).unwrap();
        assert_eq!(syncer.appended(), 2);
        syncer.sync_through(mine).unwrap();
        assert_eq!(
            *syncer.durable.lock().unwrap(),
            2,
            "the sync covered both appends"
        );
        syncer.sync_through(2).unwrap();
        assert_eq!(*syncer.durable.lock().unwrap(), 2);
    }

    #[test]
    fn a_log_from_a_newer_format_is_refused_not_rewritten() {
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
        std::fs::write(&path, &bytes).unwrap();
        let err = ReplayLog::open(&path).unwrap_err();
        assert!(err.to_string().contains("newer"), "{err}");
        assert_eq!(std::fs::read(&path).unwrap(), bytes);
    }

    /// A format-3 log names its task by the old closed enum's index: it reads as the task's
    /// name, and headers written from now on carry the name.
    #[test]
    fn a_format_3_log_reads_its_task_index_as_a_name() {
        let old_header = OnDisk::HeaderV3 {
            task: CatalogIndexV3::HalfCheetah,
            obs_dim: 18,
            act_dim: 6,
        };
        let encoded = postcard::to_stdvec(&old_header).unwrap();
        assert_eq!(encoded[..2], [0, 2], "format 3's tag and the task's index");
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&3u32.to_le_bytes());
        frame(&encoded, &mut bytes);
        frame(
            &postcard::to_stdvec(&OnDisk::from(transition(0))).unwrap(),
            &mut bytes,
        );
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        std::fs::write(&path, &bytes).unwrap();
        let header = Record::Header(HeaderRecord {
            task: "halfcheetah".into(),
            obs_dim: 18,
            act_dim: 6,
        });
        let rec = ReplayLog::read(&path).unwrap();
        assert_eq!(rec.records, [header.clone(), transition(0)]);
        assert_eq!(std::fs::read(&path).unwrap(), bytes);
        let written = postcard::to_stdvec(&OnDisk::from(header)).unwrap();
        assert_eq!(written[0], 6, "a new header is the appended variant");
    }

    /// Builds up to format 5's first release declared the current variants as struct variants;
    /// the newtype variants over [`Record`]'s structs must encode to the same bytes, so both
    /// read each other's logs.
    #[test]
    fn the_record_structs_encode_as_the_struct_variants_earlier_builds_wrote() {
        /// The current variants as earlier builds declared them (tags 3–7).
        #[derive(Serialize)]
        enum Earlier {
            _HeaderV3,
            _TransitionV1,
            _EpisodeEndV1,
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
            Header {
                task: String,
                obs_dim: u32,
                act_dim: u32,
            },
            Term {
                epoch: u64,
                planner: String,
                reads: Vec<SegmentRead>,
            },
        }
        let pairs = [
            (
                Record::Claim(ClaimRecord {
                    epoch: 7,
                    planner: "p".into(),
                }),
                Earlier::Claim {
                    epoch: 7,
                    planner: "p".into(),
                },
            ),
            (
                Record::Transition(TransitionRecord {
                    epoch: 3,
                    agent: "a".into(),
                    episode: 2,
                    step: 9,
                    obs: vec![0.5, -1.0],
                    act: vec![0.25],
                    origin: ActionOrigin::Applied,
                    next_obs: vec![0.75, -2.0],
                    reward: 1.5,
                }),
                Earlier::Transition {
                    epoch: 3,
                    agent: "a".into(),
                    episode: 2,
                    step: 9,
                    obs: vec![0.5, -1.0],
                    act: vec![0.25],
                    origin: ActionOrigin::Applied,
                    next_obs: vec![0.75, -2.0],
                    reward: 1.5,
                },
            ),
            (
                Record::EpisodeEnd(EpisodeEndRecord {
                    epoch: 3,
                    agent: "a".into(),
                    episode: 2,
                    steps: 10,
                    episode_return: -4.0,
                    end: proto::EpisodeEnd::Terminated,
                }),
                Earlier::EpisodeEnd {
                    epoch: 3,
                    agent: "a".into(),
                    episode: 2,
                    steps: 10,
                    episode_return: -4.0,
                    end: proto::EpisodeEnd::Terminated,
                },
            ),
            (
                Record::Header(HeaderRecord {
                    task: "ant".into(),
                    obs_dim: 27,
                    act_dim: 8,
                }),
                Earlier::Header {
                    task: "ant".into(),
                    obs_dim: 27,
                    act_dim: 8,
                },
            ),
            (
                Record::Term(TermRecord {
                    epoch: 4,
                    planner: "q".into(),
                    reads: vec![SegmentRead {
                        name: "replay.log".into(),
                        len: 1234,
                    }],
                }),
                Earlier::Term {
                    epoch: 4,
                    planner: "q".into(),
                    reads: vec![SegmentRead {
                        name: "replay.log".into(),
                        len: 1234,
                    }],
                },
            ),
        ];
        for (record, earlier) in pairs {
            let earlier = postcard::to_stdvec(&earlier).unwrap();
            let now = postcard::to_stdvec(&OnDisk::from(record.clone())).unwrap();
            assert_eq!(now, earlier, "{record:?}");
            let read = Record::from(postcard::from_bytes::<OnDisk>(&earlier).unwrap());
            assert_eq!(read, record);
        }
    }

    /// A format-2 log (written before ownership epochs, its records encoded as that release
    /// did) reads as it is: every record as epoch 0 with the planned action, and a damaged
    /// record in it is still skipped.
    #[test]
    fn a_format_2_log_reads_as_epoch_0_with_the_planned_action() {
        /// The record type of the release before epochs, as it was.
        #[derive(Serialize)]
        enum OldRecord {
            Header {
                task: CatalogIndexV3,
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
                task: CatalogIndexV3::Cartpole,
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
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&2u32.to_le_bytes());
        for record in &old {
            frame(&postcard::to_stdvec(record).unwrap(), &mut bytes);
        }
        // A damaged record between the last two: format 2 resynchronised on it, so does 3.
        frame(&[0xff; 9], &mut bytes);
        let at = bytes.len() - 9;
        bytes[at] ^= 0x01;
        let mut tail = Vec::new();
        frame(&postcard::to_stdvec(&old[2]).unwrap(), &mut tail);
        bytes.extend_from_slice(&tail);
        let dir = tempfile::tempdir().unwrap();
        let path = temp_path(&dir);
        std::fs::write(&path, &bytes).unwrap();
        let rec = ReplayLog::read(&path).unwrap();
        assert_eq!((rec.truncated_bytes, rec.damaged_regions), (0, 1));
        assert_eq!(rec.records.len(), 4);
        assert_eq!(std::fs::read(&path).unwrap(), bytes, "read, not rewritten");
        assert_eq!(
            rec.records[0],
            Record::Header(HeaderRecord {
                task: "cartpole".into(),
                obs_dim: 4,
                act_dim: 1,
            }),
            "the old header's task index reads as the task's name"
        );
        assert_eq!(
            rec.records[1],
            Record::Transition(TransitionRecord {
                epoch: 0,
                agent: "a".into(),
                episode: 0,
                step: 0,
                obs: vec![0.0; 4],
                act: vec![0.5],
                origin: ActionOrigin::Planned,
                next_obs: vec![1.0; 4],
                reward: 0.1,
            })
        );
        assert_eq!(rec.records[2].epoch(), Some(0));
        assert_eq!(
            rec.records[3], rec.records[2],
            "both episode ends read alike"
        );
    }
}
