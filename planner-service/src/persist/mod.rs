//! What a run keeps on disk so that a restarted daemon resumes it where it stopped.
//!
//! ```text
//! {data_dir}/runs/{run}/run.json                     the run's spec (task, preset, overrides, mode, seed)
//! {data_dir}/runs/{run}/replay/{token}-{seq}.log     every transition, one file per ownership
//!                                                    term (see crate::replay::segments)
//! {data_dir}/runs/{run}/replay.log                   the replay of a run stored before segments
//! {data_dir}/runs/{run}/models-{token:020}-{version:08}.safetensors
//!                                                    model checkpoints, one file per term and
//!                                                    models version (see [`CheckpointId`])
//! {data_dir}/runs/{run}/epochs/{epoch:020}           ownership epochs (the planner id inside)
//! ```
//!
//! The ownership epoch fences planners that share one data directory (see `crate::fleet`): a
//! planner takes a run over by creating the file of the next epoch with `O_CREAT | O_EXCL`, so
//! of two planners racing for the same epoch exactly one succeeds, and a planner whose epoch is
//! no longer the newest file knows it has lost the run.
//!
//! Every file but the append-only replay log is written whole to a temporary file, synced, and
//! renamed over its final name (then the directory is synced), so a crash at any moment leaves
//! either the old file or the new one, never a mixture.
//!
//! Checkpoints follow the replay segments' rule, one writer per file: each is named by the
//! fencing token of the term that wrote it, a term writes only while no newer term has written
//! to the run, and a term's pruning removes only its own or older terms' files. So a stale
//! owner (one that lost the run and has not noticed) never writes over, nor prunes, a
//! checkpoint of the owner that followed it. Loading takes the newest checkpoint of the newest
//! term that decodes and fits the run; a file named by version only (from before terms) is of
//! term 0, so it is read by the same code and replaced by the first term that writes one. A
//! damaged one (its checksum or structure is wrong) is renamed
//! `*.damaged` with an error in the log, so it is never tried again and never deleted; one that
//! is intact but does not fit the run (another preset, an older format) is skipped.

pub mod admin;
pub mod checkpoint;

use crate::config::Preset;
use crate::models::Models;
use checkpoint::CheckpointError;
use proto::{RunSpec, Task};
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Checkpoints kept per run: the newest and one fallback.
const CHECKPOINTS_KEPT: usize = 2;

const SPEC_FILE: &str = "run.json";
const EPOCHS_DIR: &str = "epochs";
/// Epoch files kept per run (older ones are removed after a claim; only the newest counts).
const EPOCHS_KEPT: usize = 4;
const CHECKPOINT_PREFIX: &str = "models-";
const CHECKPOINT_SUFFIX: &str = ".safetensors";

/// Failures of run persistence.
#[derive(Debug, thiserror::Error)]
pub enum PersistError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Spec {
        path: String,
        source: serde_json::Error,
    },
    #[error("{path}: {source}")]
    Checkpoint {
        path: String,
        source: CheckpointError,
    },
    #[error("ownership epoch {epoch} of {path} was taken by another planner at the same moment")]
    EpochTaken { path: String, epoch: u64 },
    #[error("{path}: not written: term {token} was followed by term {newer}")]
    NewerTerm {
        path: String,
        token: u64,
        newer: u64,
    },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> PersistError + '_ {
    move |source| PersistError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// The directory of one run.
#[derive(Clone, Debug)]
pub struct RunDir {
    root: PathBuf,
}

/// The folder of the served runs under a data directory: `{data_dir}/runs/{run}`.
pub(crate) const RUNS_DIR: &str = "runs";

impl RunDir {
    /// The directory of run `name` under `data_dir` (not created until something is written).
    pub fn new(data_dir: &Path, name: &str) -> Self {
        Self {
            root: data_dir.join(RUNS_DIR).join(name),
        }
    }

    /// The run directory at `root` itself (e.g. a copy of a run's directory, read by tools).
    pub fn at(root: impl Into<PathBuf>) -> Self {
        Self { root: root.into() }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Whether the run has stored replay (a segment, or the log from before segments).
    pub fn has_replay(&self) -> bool {
        crate::replay::segments::list(&self.root).is_ok_and(|found| !found.is_empty())
    }

    /// Bytes of the run's replay files on disk.
    pub fn replay_bytes(&self) -> u64 {
        crate::replay::segments::bytes_on_disk(&self.root)
    }

    /// When the run last stored a transition (its newest replay segment's last write).
    pub fn replay_last_written(&self) -> Option<std::time::SystemTime> {
        crate::replay::segments::last_written(&self.root)
    }

    fn spec_path(&self) -> PathBuf {
        self.root.join(SPEC_FILE)
    }

    /// Records the run's spec, so a restarted daemon can re-create the run without its agents.
    pub fn write_spec(&self, spec: &RunSpec) -> Result<(), PersistError> {
        let path = self.spec_path();
        let json = serde_json::to_vec_pretty(spec).map_err(|source| PersistError::Spec {
            path: path.display().to_string(),
            source,
        })?;
        write_atomically(&path, &json)
    }

    /// The recorded spec, `None` if this directory never got one (a run from before specs
    /// were recorded, or one whose creation was interrupted).
    pub fn read_spec(&self) -> Result<Option<RunSpec>, PersistError> {
        let path = self.spec_path();
        let bytes = match fs::read(&path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io_error(&path)(e)),
        };
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|source| PersistError::Spec {
                path: path.display().to_string(),
                source,
            })
    }

    fn epochs_dir(&self) -> PathBuf {
        self.root.join(EPOCHS_DIR)
    }

    /// Claimed epochs, newest first.
    fn epochs(&self) -> Result<Vec<u64>, PersistError> {
        let dir = self.epochs_dir();
        let entries = match fs::read_dir(&dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_error(&dir)(e)),
        };
        let mut epochs: Vec<u64> = entries
            .filter_map(|entry| entry.ok()?.file_name().into_string().ok()?.parse().ok())
            .collect();
        epochs.sort_unstable_by(|a, b| b.cmp(a));
        Ok(epochs)
    }

    /// The run's current ownership epoch (0: never claimed).
    pub fn current_epoch(&self) -> Result<u64, PersistError> {
        Ok(self.epochs()?.first().copied().unwrap_or(0))
    }

    /// The planner that claimed `epoch`, if its file is there and readable.
    pub fn epoch_holder(&self, epoch: u64) -> Option<String> {
        fs::read_to_string(self.epochs_dir().join(format!("{epoch:020}"))).ok()
    }

    /// Takes the epoch after `seen` (the newest the caller found) for `planner`: creates its
    /// file exclusively (synced, and the directory synced), so no two planners ever hold the
    /// same epoch. Fails with [`PersistError::EpochTaken`] if another planner created it first.
    pub fn claim_epoch_after(&self, seen: u64, planner: &str) -> Result<u64, PersistError> {
        self.claim_epoch(seen + 1, planner)
    }

    /// Records that `planner` took the run at fencing token `token` (granted by etcd, so no
    /// other planner ever records the same one): the newest token on disk is the floor of
    /// the next one, and the fence that [`RunDir::current_epoch`] readers check.
    /// Recording a token this planner recorded already (it took the run again under the same
    /// owner key) is not an error.
    pub fn record_token(&self, token: u64, planner: &str) -> Result<u64, PersistError> {
        match self.claim_epoch(token, planner) {
            Err(PersistError::EpochTaken { .. })
                if self.epoch_holder(token).as_deref() == Some(planner) =>
            {
                Ok(token)
            }
            claimed => claimed,
        }
    }

    fn claim_epoch(&self, epoch: u64, planner: &str) -> Result<u64, PersistError> {
        let dir = self.epochs_dir();
        fs::create_dir_all(&dir).map_err(io_error(&dir))?;
        let path = dir.join(format!("{epoch:020}"));
        let mut file = match fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&path)
        {
            Ok(file) => file,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(PersistError::EpochTaken {
                    path: self.root.display().to_string(),
                    epoch,
                });
            }
            Err(e) => return Err(io_error(&path)(e)),
        };
        file.write_all(planner.as_bytes())
            .and_then(|()| file.sync_all())
            .map_err(io_error(&path))?;
        fs::File::open(&dir)
            .and_then(|d| d.sync_all())
            .map_err(io_error(&dir))?;
        for old in self.epochs()?.into_iter().skip(EPOCHS_KEPT) {
            let old = dir.join(format!("{old:020}"));
            if let Err(e) = fs::remove_file(&old) {
                tracing::warn!(path = %old.display(), error = %e, "cannot remove an old epoch file");
            }
        }
        Ok(epoch)
    }

    fn checkpoint_path(&self, id: CheckpointId) -> PathBuf {
        self.root.join(id.file_name())
    }

    /// Stored checkpoints, newest first: by term, then by models version (the order loading
    /// tries them in).
    pub fn checkpoints(&self) -> Result<Vec<CheckpointId>, PersistError> {
        let entries = match fs::read_dir(&self.root) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_error(&self.root)(e)),
        };
        let mut found: Vec<CheckpointId> = entries
            .filter_map(|entry| CheckpointId::parse(entry.ok()?.file_name().to_str()?))
            .collect();
        found.sort_unstable_by(|a, b| b.cmp(a));
        Ok(found)
    }

    /// The newest term newer than `token` that has written to the run: a checkpoint or a
    /// replay segment of its own (a new owner creates its segment before it acknowledges).
    fn newer_term_than(&self, token: u64) -> Result<Option<u64>, PersistError> {
        let newest_checkpoint = self.checkpoints()?.first().map(|id| id.token);
        let newest_segment = crate::replay::segments::newest_token(&self.root);
        Ok(newest_checkpoint
            .max(newest_segment)
            .filter(|&newest| newest > token))
    }

    /// Writes a checkpoint of `models` as the term of fencing token `token`, then removes all
    /// but the newest `CHECKPOINTS_KEPT` (2) of this term's and older terms' checkpoints.
    ///
    /// One writer per file: the file is named by the term, so two planners never write the
    /// same one. A term that is no longer the newest (a newer term has a checkpoint or a
    /// replay segment) writes nothing: that is checked before the write and again before the
    /// file gets its name. Pruning never touches a newer term's file, whatever it finds.
    ///
    /// # Errors
    /// [`PersistError::NewerTerm`] when fenced; I/O errors (a full disk) leave no file of
    /// this term behind but the checkpoints that were there.
    pub fn save_models(
        &self,
        token: u64,
        models: &Models,
        task: &Task,
    ) -> Result<PathBuf, PersistError> {
        let id = CheckpointId {
            token,
            version: models.version,
        };
        let path = self.checkpoint_path(id);
        let fence = || match self.newer_term_than(token)? {
            Some(newer) => Err(PersistError::NewerTerm {
                path: path.display().to_string(),
                token,
                newer,
            }),
            None => Ok(()),
        };
        fence()?;
        let bytes =
            checkpoint::encode(models, task).map_err(|source| PersistError::Checkpoint {
                path: path.display().to_string(),
                source,
            })?;
        write_atomically_if(&path, &bytes, fence)?;
        self.prune_checkpoints(token);
        Ok(path)
    }

    /// Removes all but the newest `CHECKPOINTS_KEPT` of the checkpoints of term `token` and
    /// older terms; a newer term's files are never among those considered.
    fn prune_checkpoints(&self, token: u64) {
        let found = match self.checkpoints() {
            Ok(found) => found,
            Err(e) => {
                tracing::warn!(error = %e, "cannot list the checkpoints to prune them");
                return;
            }
        };
        let own_or_older = found.into_iter().filter(|c| c.token <= token);
        for old in own_or_older.skip(CHECKPOINTS_KEPT) {
            let old = self.checkpoint_path(old);
            if let Err(e) = fs::remove_file(&old) {
                tracing::warn!(path = %old.display(), error = %e, "cannot remove an old checkpoint");
            }
        }
    }

    /// The newest stored checkpoint that decodes and fits `preset` (of the newest term that
    /// has one that does); `None` if there is none. A file that disappears while it is read
    /// (its term pruned it after writing a newer one) sends the search back to a fresh
    /// listing, so a concurrent prune never makes a run start untrained.
    pub fn load_models(
        &self,
        task: &'static Task,
        preset: &Preset,
    ) -> Result<Option<Models>, PersistError> {
        /// Listings tried before files that keep vanishing are taken as gone.
        const LISTINGS: usize = 4;
        'listing: for _ in 0..LISTINGS {
            for id in self.checkpoints()? {
                let path = self.checkpoint_path(id);
                let bytes = match fs::read(&path) {
                    Ok(bytes) => bytes,
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue 'listing,
                    Err(e) => {
                        tracing::warn!(path = %path.display(), error = %e, "skipping a checkpoint that cannot be read");
                        continue;
                    }
                };
                match checkpoint::decode(&bytes, task, preset) {
                    Ok(models) => return Ok(Some(models)),
                    Err(source) if source.is_damage() => {
                        let aside = damaged_path(&path);
                        match fs::rename(&path, &aside) {
                            Ok(()) => {
                                tracing::error!(path = %path.display(), moved_to = %aside.display(), error = %source, "damaged checkpoint moved aside")
                            }
                            Err(e) => {
                                tracing::error!(path = %path.display(), error = %source, rename_error = %e, "damaged checkpoint skipped; it could not be moved aside")
                            }
                        }
                    }
                    Err(source) => {
                        tracing::warn!(path = %path.display(), error = %source, "skipping a checkpoint that cannot be used")
                    }
                }
            }
            return Ok(None);
        }
        Ok(None)
    }
}

/// Where a checkpoint stands in its run's order: the term (fencing token) that wrote it, then
/// its models version. A file from before terms (`models-{version:08}.safetensors`, written
/// by builds that named checkpoints by version only) is of term 0, older than every term, so
/// it loads while no term has written one and the first term's pruning removes it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct CheckpointId {
    pub token: u64,
    pub version: u64,
}

impl CheckpointId {
    /// The file's name in the run's directory: `models-{token:020}-{version:08}.safetensors`
    /// (term 0: the name from before terms).
    pub fn file_name(self) -> String {
        let Self { token, version } = self;
        if token == 0 {
            format!("{CHECKPOINT_PREFIX}{version:08}{CHECKPOINT_SUFFIX}")
        } else {
            format!("{CHECKPOINT_PREFIX}{token:020}-{version:08}{CHECKPOINT_SUFFIX}")
        }
    }

    /// The checkpoint a file name stands for (`None`: not a checkpoint's name).
    pub fn parse(name: &str) -> Option<Self> {
        let stem = name
            .strip_prefix(CHECKPOINT_PREFIX)?
            .strip_suffix(CHECKPOINT_SUFFIX)?;
        let id = match stem.split_once('-') {
            Some((token, version)) => Self {
                token: token.parse().ok()?,
                version: version.parse().ok()?,
            },
            None => Self {
                token: 0,
                version: stem.parse().ok()?,
            },
        };
        // One name per checkpoint: `models-5.safetensors` or a token of 0 are not ours.
        (id.file_name() == name).then_some(id)
    }
}

/// Where a damaged file is moved: its name with `.damaged` appended.
fn damaged_path(path: &Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(".damaged");
    path.with_file_name(name)
}

/// The runs stored under `data_dir`, by name (sorted).
pub fn stored_runs(data_dir: &Path) -> Result<Vec<(String, RunDir)>, PersistError> {
    run_dirs_under(&data_dir.join(RUNS_DIR))
}

/// The run directories directly under `root` (`runs/`, or a data directory's `archive/`), by
/// name (sorted); none if `root` does not exist.
pub(crate) fn run_dirs_under(root: &Path) -> Result<Vec<(String, RunDir)>, PersistError> {
    let entries = match fs::read_dir(root) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io_error(root)(e)),
    };
    let mut runs: Vec<(String, RunDir)> = entries
        .filter_map(|entry| {
            let entry = entry.ok()?;
            if !entry.file_type().ok()?.is_dir() {
                return None;
            }
            let name = entry.file_name().into_string().ok()?;
            Some((name.clone(), RunDir::at(root.join(&name))))
        })
        .collect();
    runs.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(runs)
}

/// Writes `bytes` to `path` so that `path` holds either its old content or all of `bytes`,
/// whatever happens: a temporary sibling is written and synced, renamed over `path`, and the
/// directory is synced so the rename itself is durable.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), PersistError> {
    write_atomically_if(path, bytes, || Ok(()))
}

/// As [`write_atomically`], giving the file its name only if `still` passes once the bytes
/// are durable. On any failure (a full disk, `still` refusing) the temporary file is removed
/// and `path` is left as it was.
fn write_atomically_if(
    path: &Path,
    bytes: &[u8],
    still: impl FnOnce() -> Result<(), PersistError>,
) -> Result<(), PersistError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir).map_err(io_error(dir))?;
    let mut tmp_name = path.file_name().unwrap_or_default().to_os_string();
    tmp_name.push(".tmp");
    let tmp = dir.join(tmp_name);
    let written = (|| {
        let mut file = fs::File::create(&tmp).map_err(io_error(&tmp))?;
        file.write_all(bytes).map_err(io_error(&tmp))?;
        file.sync_all().map_err(io_error(&tmp))?;
        drop(file);
        still()?;
        fs::rename(&tmp, path).map_err(io_error(path))
    })();
    if let Err(e) = written {
        if let Err(removal) = fs::remove_file(&tmp)
            && removal.kind() != std::io::ErrorKind::NotFound
        {
            tracing::warn!(path = %tmp.display(), error = %removal, "cannot remove a temporary file");
        }
        return Err(e);
    }
    fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io_error(dir))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::{Builtin, PlannerOverrides, TrainMode};

    fn temp_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("ebmpc-persist-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    fn small_preset() -> Preset {
        let mut preset = Preset::new(Builtin::Cartpole.task(), Some("cem+deen")).unwrap();
        preset.dynamics.hidden_size = 8;
        preset.energy.hidden_size = 8;
        preset
    }

    /// A run stored by protocol 3 builds (`task` the closed enum's JSON name, no `task_spec`)
    /// reads as the same task by name.
    #[test]
    fn a_run_spec_of_the_previous_format_reads_by_name() {
        let data = temp_dir("old-spec");
        let dir = RunDir::new(&data, "old");
        fs::create_dir_all(dir.root()).unwrap();
        fs::write(
            dir.spec_path(),
            br#"{"task": "halfcheetah", "preset": "cem+deen", "overrides": {}, "mode": "sync", "seed": 3}"#,
        )
        .unwrap();
        let spec = dir.read_spec().unwrap().unwrap();
        assert_eq!((spec.task.as_str(), spec.seed), ("halfcheetah", 3));
        assert_eq!(spec.task_spec, None);
    }

    /// A run of a task given in full stores the whole spec, so a restarted daemon rebuilds it.
    #[test]
    fn a_custom_task_spec_is_stored_with_the_run() {
        let data = temp_dir("custom-spec");
        let dir = RunDir::new(&data, "custom");
        let mut task = Builtin::Cartpole.spec();
        task.name = "my-cartpole".into();
        task.episode_len = 40;
        let spec = RunSpec {
            task: "my-cartpole".into(),
            preset: None,
            overrides: PlannerOverrides::default(),
            mode: TrainMode::Sync,
            seed: 2,
            task_spec: Some(task),
        };
        dir.write_spec(&spec).unwrap();
        assert_eq!(dir.read_spec().unwrap(), Some(spec));
    }

    #[test]
    fn the_spec_round_trips_and_a_missing_one_is_none() {
        let data = temp_dir("spec");
        let dir = RunDir::new(&data, "r1");
        assert_eq!(dir.read_spec().unwrap(), None);
        let spec = RunSpec {
            task: Builtin::Ant.name().into(),
            preset: Some("pets+deen".into()),
            overrides: PlannerOverrides::default(),
            mode: TrainMode::Async,
            seed: 9,
            task_spec: None,
        };
        dir.write_spec(&spec).unwrap();
        assert_eq!(dir.read_spec().unwrap(), Some(spec));
        let runs = stored_runs(&data).unwrap();
        assert_eq!(runs.len(), 1);
        assert_eq!(runs[0].0, "r1");
        fs::write(dir.spec_path(), b"{not json").unwrap();
        assert!(dir.read_spec().is_err());
        fs::remove_dir_all(&data).unwrap();
    }

    /// The checkpoints stored, newest first, as `(token, version)`.
    fn stored(dir: &RunDir) -> Vec<(u64, u64)> {
        let ids = dir.checkpoints().unwrap();
        ids.into_iter().map(|c| (c.token, c.version)).collect()
    }

    fn id(token: u64, version: u64) -> CheckpointId {
        CheckpointId { token, version }
    }

    #[test]
    fn the_newest_usable_checkpoint_is_loaded_and_only_two_are_kept() {
        let data = temp_dir("checkpoints");
        let dir = RunDir::new(&data, "r");
        let task = Builtin::Cartpole.task();
        let preset = small_preset();
        assert!(dir.load_models(task, &preset).unwrap().is_none());
        let mut models = Models::untrained(task, &preset, 1);
        for version in 1..=4 {
            models.version = version;
            models.episodes_covered = version as u32 * 2;
            dir.save_models(7, &models, task).unwrap();
        }
        assert_eq!(stored(&dir), vec![(7, 4), (7, 3)]);
        let loaded = dir.load_models(task, &preset).unwrap().unwrap();
        assert_eq!((loaded.version, loaded.episodes_covered), (4, 8));

        // A damaged newest checkpoint (a disk error: renames never leave half files), here
        // one flipped byte in its weights, is moved aside, and the one before it is used.
        let newest = dir.checkpoint_path(id(7, 4));
        let mut bytes = fs::read(&newest).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x01;
        fs::write(&newest, &bytes).unwrap();
        let loaded = dir.load_models(task, &preset).unwrap().unwrap();
        assert_eq!(loaded.version, 3);
        assert!(!newest.exists());
        assert_eq!(
            fs::read(damaged_path(&newest)).unwrap(),
            bytes,
            "a damaged checkpoint is kept for inspection, under another name"
        );
        assert_eq!(stored(&dir), vec![(7, 3)]);
        // No leftovers of the temporary files.
        let names: Vec<String> = fs::read_dir(dir.root())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
        fs::remove_dir_all(&data).unwrap();
    }

    #[test]
    fn checkpoint_names_round_trip_and_strangers_are_ignored() {
        for c in [id(0, 3), id(1, 0), id(12, 7), id(u64::MAX, u64::MAX)] {
            assert_eq!(CheckpointId::parse(&c.file_name()), Some(c), "{c:?}");
        }
        assert_eq!(
            CheckpointId::parse("models-00000003.safetensors"),
            Some(id(0, 3))
        );
        assert_eq!(
            id(5, 2).file_name(),
            "models-00000000000000000005-00000002.safetensors"
        );
        for stranger in [
            "models-3.safetensors",
            "models-00000000000000000000-00000003.safetensors",
            "models-00000000000000000005-00000002.safetensors.tmp",
            "models-00000000000000000005-00000002.safetensors.damaged",
            "models-x-00000002.safetensors",
            "replay.log",
        ] {
            assert_eq!(CheckpointId::parse(stranger), None, "{stranger}");
        }
        // Newer terms order first whatever their versions; the old layout is oldest.
        let mut ids = vec![id(0, 9), id(5, 2), id(3, 8), id(5, 1)];
        ids.sort_unstable_by(|a, b| b.cmp(a));
        assert_eq!(ids, vec![id(5, 2), id(5, 1), id(3, 8), id(0, 9)]);
    }

    /// A stale term (one a newer owner followed) that keeps training: its saves write nothing
    /// and remove nothing, neither while only the newer term's replay segment exists nor once
    /// it has checkpoints; pruning by a term only removes its own or older terms' files.
    #[test]
    fn a_stale_terms_save_and_prune_leave_the_newer_terms_checkpoints_intact() {
        let data = temp_dir("stale-checkpoints");
        let dir = RunDir::new(&data, "r");
        let task = Builtin::Cartpole.task();
        let preset = small_preset();
        let mut models = Models::untrained(task, &preset, 1);
        let save = |token: u64, version: u64, models: &mut Models| {
            models.version = version;
            dir.save_models(token, models, task)
        };
        // Term 3 writes versions 1..=3 (keeps 2, 3).
        for version in 1..=3 {
            save(3, version, &mut models).unwrap();
        }
        // Term 5 takes over: its replay segment exists before it acknowledges anything.
        let segment = dir
            .root()
            .join(crate::replay::segments::SegmentId::Term { token: 5, seq: 0 }.name());
        fs::create_dir_all(segment.parent().unwrap()).unwrap();
        fs::write(&segment, b"").unwrap();
        let err = save(3, 4, &mut models).unwrap_err();
        assert!(
            matches!(
                err,
                PersistError::NewerTerm {
                    token: 3,
                    newer: 5,
                    ..
                }
            ),
            "{err}"
        );
        assert_eq!(
            stored(&dir),
            vec![(3, 3), (3, 2)],
            "the stale save wrote nothing"
        );
        // Term 5 trains on from version 3 and saves 4 and 5: its pruning removes term 3's.
        save(5, 4, &mut models).unwrap();
        let files_of_5: Vec<Vec<u8>> = {
            save(5, 5, &mut models).unwrap();
            [id(5, 5), id(5, 4)]
                .iter()
                .map(|c| fs::read(dir.checkpoint_path(*c)).unwrap())
                .collect()
        };
        assert_eq!(stored(&dir), vec![(5, 5), (5, 4)]);
        // The stale term saves again, many versions further: refused every time, and the
        // newer term's files are untouched, byte for byte.
        for version in 6..=9 {
            let err = save(3, version, &mut models).unwrap_err();
            assert!(matches!(err, PersistError::NewerTerm { .. }), "{err}");
        }
        assert_eq!(stored(&dir), vec![(5, 5), (5, 4)]);
        for (c, bytes) in [id(5, 5), id(5, 4)].iter().zip(&files_of_5) {
            assert_eq!(&fs::read(dir.checkpoint_path(*c)).unwrap(), bytes);
        }
        let loaded = dir.load_models(task, &preset).unwrap().unwrap();
        assert_eq!(loaded.version, 5);

        // A stale term whose save got past the fence just before the takeover (the newer
        // term wrote its files meanwhile) prunes only its own and older terms' files.
        fs::remove_file(&segment).unwrap();
        for version in 1..=4 {
            models.version = version;
            let path = dir.checkpoint_path(id(3, version));
            write_atomically(&path, &checkpoint::encode(&models, task).unwrap()).unwrap();
        }
        dir.prune_checkpoints(3);
        assert_eq!(stored(&dir), vec![(5, 5), (5, 4), (3, 4), (3, 3)]);
        for (c, bytes) in [id(5, 5), id(5, 4)].iter().zip(&files_of_5) {
            assert_eq!(&fs::read(dir.checkpoint_path(*c)).unwrap(), bytes);
        }
        // The newer term's own pruning then removes the stale files.
        dir.prune_checkpoints(5);
        assert_eq!(stored(&dir), vec![(5, 5), (5, 4)]);
        fs::remove_dir_all(&data).unwrap();
    }

    /// Loading picks the newest term's newest checkpoint, even when an older term has a
    /// higher models version; a data directory of the layout from before terms loads, and
    /// its files are pruned by the first term that saves.
    #[test]
    fn loading_picks_the_newest_terms_newest_checkpoint_and_the_old_layout_loads() {
        let data = temp_dir("load-terms");
        let dir = RunDir::new(&data, "r");
        let task = Builtin::Cartpole.task();
        let preset = small_preset();
        let mut models = Models::untrained(task, &preset, 1);
        // The layout from before terms: `models-{version:08}.safetensors`.
        for version in [6, 7] {
            models.version = version;
            let path = dir.root().join(format!("models-{version:08}.safetensors"));
            write_atomically(&path, &checkpoint::encode(&models, task).unwrap()).unwrap();
        }
        assert_eq!(stored(&dir), vec![(0, 7), (0, 6)]);
        assert_eq!(dir.load_models(task, &preset).unwrap().unwrap().version, 7);
        // Term 4 resumes from version 7 and writes 8: the old files are kept beside it
        // (newest two), then pruned as it writes more.
        models.version = 8;
        dir.save_models(4, &models, task).unwrap();
        assert_eq!(stored(&dir), vec![(4, 8), (0, 7)]);
        models.version = 9;
        dir.save_models(4, &models, task).unwrap();
        assert_eq!(stored(&dir), vec![(4, 9), (4, 8)]);
        // A stale term 2 that wrote version 30 before term 4 took over (the check passed
        // just before): term 4's newest is still what loads, and term 4 never prunes a file
        // of its own to keep an older term's.
        models.version = 30;
        let late = dir.root().join(id(2, 30).file_name());
        write_atomically(&late, &checkpoint::encode(&models, task).unwrap()).unwrap();
        assert_eq!(dir.load_models(task, &preset).unwrap().unwrap().version, 9);
        models.version = 10;
        dir.save_models(4, &models, task).unwrap();
        assert_eq!(stored(&dir), vec![(4, 10), (4, 9)]);
        // The newest term's checkpoint that does not fit the run (another preset) is skipped
        // for the next newest.
        let mut other = preset.clone();
        other.dynamics.hidden_size = 16;
        let mut wide = Models::untrained(task, &other, 1);
        wide.version = 11;
        dir.save_models(6, &wide, task).unwrap();
        assert_eq!(stored(&dir)[0], (6, 11));
        assert_eq!(dir.load_models(task, &preset).unwrap().unwrap().version, 10);
        fs::remove_dir_all(&data).unwrap();
    }

    #[test]
    fn epochs_are_claimed_once_each_and_grow() {
        let data = temp_dir("epochs");
        let dir = RunDir::new(&data, "r");
        assert_eq!(dir.current_epoch().unwrap(), 0);
        assert_eq!(dir.claim_epoch_after(0, "pa").unwrap(), 1);
        assert_eq!(dir.claim_epoch_after(1, "pb").unwrap(), 2);
        assert_eq!(dir.current_epoch().unwrap(), 2);
        // Two planners that both found epoch 2 the newest race for 3: exactly one gets it.
        assert_eq!(dir.claim_epoch_after(2, "pc").unwrap(), 3);
        let err = dir.claim_epoch_after(2, "pd").unwrap_err();
        assert!(
            matches!(err, PersistError::EpochTaken { epoch: 3, .. }),
            "{err}"
        );
        assert_eq!(
            fs::read_to_string(dir.epochs_dir().join(format!("{:020}", 3))).unwrap(),
            "pc"
        );
        for (seen, planner) in [(3, "pa"), (4, "pb"), (5, "pc"), (6, "pd")] {
            dir.claim_epoch_after(seen, planner).unwrap();
        }
        assert_eq!(dir.current_epoch().unwrap(), 7);
        assert_eq!(
            dir.epochs().unwrap(),
            vec![7, 6, 5, 4],
            "only the newest are kept"
        );
        fs::remove_dir_all(&data).unwrap();
    }
}
