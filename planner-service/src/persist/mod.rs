//! What a run keeps on disk so that a restarted daemon resumes it where it stopped.
//!
//! ```text
//! {data_dir}/runs/{run}/run.json                     the run's spec (task, preset, overrides, mode, seed)
//! {data_dir}/runs/{run}/replay/{token}-{seq}.log     every transition, one file per ownership
//!                                                    term (see crate::replay::segments)
//! {data_dir}/runs/{run}/replay.log                   the replay of a run stored before segments
//! {data_dir}/runs/{run}/models-{version:08}.safetensors   model checkpoints, newest two kept
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
//! either the old file or the new one, never a mixture. Loading takes the newest checkpoint
//! that decodes and fits the run. A damaged one (its checksum or structure is wrong) is renamed
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

impl RunDir {
    /// The directory of run `name` under `data_dir` (not created until something is written).
    pub fn new(data_dir: &Path, name: &str) -> Self {
        Self {
            root: data_dir.join("runs").join(name),
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

    fn checkpoint_path(&self, version: u64) -> PathBuf {
        self.root.join(format!(
            "{CHECKPOINT_PREFIX}{version:08}{CHECKPOINT_SUFFIX}"
        ))
    }

    /// Stored checkpoint versions, newest first.
    fn checkpoint_versions(&self) -> Result<Vec<u64>, PersistError> {
        let entries = match fs::read_dir(&self.root) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_error(&self.root)(e)),
        };
        let mut versions: Vec<u64> = entries
            .filter_map(|entry| {
                let name = entry.ok()?.file_name().into_string().ok()?;
                name.strip_prefix(CHECKPOINT_PREFIX)?
                    .strip_suffix(CHECKPOINT_SUFFIX)?
                    .parse()
                    .ok()
            })
            .collect();
        versions.sort_unstable_by(|a, b| b.cmp(a));
        Ok(versions)
    }

    /// Writes a checkpoint of `models` and removes all but the newest `CHECKPOINTS_KEPT` (2).
    pub fn save_models(&self, models: &Models, task: &Task) -> Result<PathBuf, PersistError> {
        let path = self.checkpoint_path(models.version);
        let bytes =
            checkpoint::encode(models, task).map_err(|source| PersistError::Checkpoint {
                path: path.display().to_string(),
                source,
            })?;
        write_atomically(&path, &bytes)?;
        for old in self
            .checkpoint_versions()?
            .into_iter()
            .skip(CHECKPOINTS_KEPT)
        {
            let old = self.checkpoint_path(old);
            if let Err(e) = fs::remove_file(&old) {
                tracing::warn!(path = %old.display(), error = %e, "cannot remove an old checkpoint");
            }
        }
        Ok(path)
    }

    /// The newest stored checkpoint that decodes and fits `preset`; `None` if there is none.
    pub fn load_models(
        &self,
        task: &'static Task,
        preset: &Preset,
    ) -> Result<Option<Models>, PersistError> {
        for version in self.checkpoint_versions()? {
            let path = self.checkpoint_path(version);
            let loaded = fs::read(&path).map_err(io_error(&path)).and_then(|bytes| {
                checkpoint::decode(&bytes, task, preset).map_err(|source| {
                    PersistError::Checkpoint {
                        path: path.display().to_string(),
                        source,
                    }
                })
            });
            match loaded {
                Ok(models) => return Ok(Some(models)),
                Err(PersistError::Checkpoint { source, .. }) if source.is_damage() => {
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
                Err(e) => tracing::warn!(error = %e, "skipping a checkpoint that cannot be used"),
            }
        }
        Ok(None)
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
    let root = data_dir.join("runs");
    let entries = match fs::read_dir(&root) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io_error(&root)(e)),
    };
    let mut runs: Vec<(String, RunDir)> = entries
        .filter_map(|entry| {
            let entry = entry.ok()?;
            if !entry.file_type().ok()?.is_dir() {
                return None;
            }
            let name = entry.file_name().into_string().ok()?;
            Some((name.clone(), RunDir::new(data_dir, &name)))
        })
        .collect();
    runs.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(runs)
}

/// Writes `bytes` to `path` so that `path` holds either its old content or all of `bytes`,
/// whatever happens: a temporary sibling is written and synced, renamed over `path`, and the
/// directory is synced so the rename itself is durable.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), PersistError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    fs::create_dir_all(dir).map_err(io_error(dir))?;
    let mut tmp_name = path.file_name().unwrap_or_default().to_os_string();
    tmp_name.push(".tmp");
    let tmp = dir.join(tmp_name);
    let mut file = fs::File::create(&tmp).map_err(io_error(&tmp))?;
    file.write_all(bytes).map_err(io_error(&tmp))?;
    file.sync_all().map_err(io_error(&tmp))?;
    drop(file);
    fs::rename(&tmp, path).map_err(io_error(path))?;
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
            dir.save_models(&models, task).unwrap();
        }
        assert_eq!(dir.checkpoint_versions().unwrap(), vec![4, 3]);
        let loaded = dir.load_models(task, &preset).unwrap().unwrap();
        assert_eq!((loaded.version, loaded.episodes_covered), (4, 8));

        // A damaged newest checkpoint (a disk error: renames never leave half files), here
        // one flipped byte in its weights, is moved aside, and the one before it is used.
        let mut bytes = fs::read(dir.checkpoint_path(4)).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x01;
        fs::write(dir.checkpoint_path(4), &bytes).unwrap();
        let loaded = dir.load_models(task, &preset).unwrap().unwrap();
        assert_eq!(loaded.version, 3);
        assert!(!dir.checkpoint_path(4).exists());
        assert_eq!(
            fs::read(damaged_path(&dir.checkpoint_path(4))).unwrap(),
            bytes,
            "a damaged checkpoint is kept for inspection, under another name"
        );
        assert_eq!(dir.checkpoint_versions().unwrap(), vec![3]);
        // No leftovers of the temporary files.
        let names: Vec<String> = fs::read_dir(dir.root())
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
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
