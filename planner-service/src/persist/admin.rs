//! Managing the runs of a data directory from outside the daemon (`planner-service runs`),
//! and the lock that keeps a daemon and such changes apart.
//!
//! A daemon holds an exclusive advisory lock on `{data_dir}/daemon.lock` for as long as it
//! serves (the OS drops it when the process dies, SIGKILL included). Deleting or archiving a
//! run takes the same lock first, so it is refused while a daemon serves the directory: a
//! daemon keeps a run's files open and would go on writing to a deleted or moved log. Listing
//! only reads and works at any time. The lock also stops two daemons from serving one data
//! directory.

use super::{CHECKPOINT_PREFIX, CHECKPOINT_SUFFIX, PersistError, RunDir, io_error, stored_runs};
use proto::RunSpec;
use std::fs::{self, File, TryLockError};
use std::path::{Path, PathBuf};

const LOCK_FILE: &str = "daemon.lock";

/// Where archived runs are moved, under the data directory.
pub const ARCHIVE_DIR: &str = "archive";

/// Why a run could not be managed.
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    #[error(
        "a planner daemon is serving {data_dir} (it holds {LOCK_FILE}): stop it first, runs are only deleted or archived while no daemon uses them"
    )]
    DaemonRunning { data_dir: String },
    #[error("no run `{name}` in {data_dir}")]
    NoSuchRun { name: String, data_dir: String },
    #[error("invalid run name: {0}")]
    Name(#[from] proto::keys::InvalidName),
    #[error("{path} already exists")]
    Exists { path: String },
    #[error(transparent)]
    Persist(#[from] PersistError),
}

/// The exclusive lock on a data directory; released when dropped (or when the process dies).
#[derive(Debug)]
pub struct DataDirLock {
    _file: File,
}

impl DataDirLock {
    /// Takes the lock on `data_dir` (creating the directory), or fails if another process
    /// holds it.
    pub fn acquire(data_dir: &Path) -> Result<Self, AdminError> {
        fs::create_dir_all(data_dir).map_err(io_error(data_dir))?;
        let path = data_dir.join(LOCK_FILE);
        let file = fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .map_err(io_error(&path))?;
        match file.try_lock() {
            Ok(()) => Ok(Self { _file: file }),
            Err(TryLockError::WouldBlock) => Err(AdminError::DaemonRunning {
                data_dir: data_dir.display().to_string(),
            }),
            Err(TryLockError::Error(e)) => Err(io_error(&path)(e).into()),
        }
    }
}

/// What `runs list` shows of a stored run.
#[derive(Debug)]
pub struct RunEntry {
    pub name: String,
    /// `None` if the run has no readable `run.json`.
    pub spec: Option<RunSpec>,
    /// Bytes of its replay log.
    pub replay_bytes: u64,
    /// Its checkpoint files.
    pub checkpoints: usize,
}

/// The runs stored in `data_dir`, by name. Reads only, so it is safe while a daemon serves.
pub fn list_runs(data_dir: &Path) -> Result<Vec<RunEntry>, AdminError> {
    stored_runs(data_dir)?
        .into_iter()
        .map(|(name, dir)| {
            let spec = dir.read_spec().ok().flatten();
            let replay_bytes = fs::metadata(dir.replay_log()).map_or(0, |m| m.len());
            let checkpoints = fs::read_dir(dir.root())
                .map_err(io_error(dir.root()))?
                .filter_map(|e| e.ok()?.file_name().into_string().ok())
                .filter(|n| n.starts_with(CHECKPOINT_PREFIX) && n.ends_with(CHECKPOINT_SUFFIX))
                .count();
            Ok(RunEntry {
                name,
                spec,
                replay_bytes,
                checkpoints,
            })
        })
        .collect()
}

/// The directory of stored run `name`, checked to exist (the name cannot leave `runs/`).
fn existing_run(data_dir: &Path, name: &str) -> Result<RunDir, AdminError> {
    proto::validate_name(name)?;
    let dir = RunDir::new(data_dir, name);
    if !dir.root().is_dir() {
        return Err(AdminError::NoSuchRun {
            name: name.to_string(),
            data_dir: data_dir.display().to_string(),
        });
    }
    Ok(dir)
}

/// Deletes run `name` and everything it stored, unless a daemon serves `data_dir`.
pub fn delete_run(data_dir: &Path, name: &str) -> Result<(), AdminError> {
    let _lock = DataDirLock::acquire(data_dir)?;
    let dir = existing_run(data_dir, name)?;
    fs::remove_dir_all(dir.root()).map_err(io_error(dir.root()))?;
    Ok(())
}

/// Moves run `name` to `{data_dir}/archive/{name}` (kept whole, no longer served), unless a
/// daemon serves `data_dir`. Returns where it went.
pub fn archive_run(data_dir: &Path, name: &str) -> Result<PathBuf, AdminError> {
    let _lock = DataDirLock::acquire(data_dir)?;
    let dir = existing_run(data_dir, name)?;
    let archive = data_dir.join(ARCHIVE_DIR);
    fs::create_dir_all(&archive).map_err(io_error(&archive))?;
    let target = archive.join(name);
    if target.exists() {
        return Err(AdminError::Exists {
            path: target.display().to_string(),
        });
    }
    fs::rename(dir.root(), &target).map_err(io_error(&target))?;
    File::open(&archive)
        .and_then(|d| d.sync_all())
        .map_err(io_error(&archive))?;
    Ok(target)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::{PlannerOverrides, TaskId, TrainMode};

    fn store_run(data: &Path, name: &str) {
        let dir = RunDir::new(data, name);
        dir.write_spec(&RunSpec {
            task: TaskId::Cartpole,
            preset: None,
            overrides: PlannerOverrides::default(),
            mode: TrainMode::Sync,
            seed: 1,
        })
        .unwrap();
        fs::write(dir.replay_log(), [0u8; 100]).unwrap();
    }

    #[test]
    fn runs_are_listed_archived_and_deleted_only_while_no_daemon_holds_the_directory() {
        let data = tempfile::tempdir().unwrap();
        store_run(data.path(), "keep");
        store_run(data.path(), "old");
        store_run(data.path(), "gone");
        let listed = list_runs(data.path()).unwrap();
        let names: Vec<&str> = listed.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(names, ["gone", "keep", "old"]);
        assert_eq!(listed[0].replay_bytes, 100);
        assert_eq!(listed[0].spec.as_ref().unwrap().task, TaskId::Cartpole);

        // While a daemon holds the lock, listing works and changes are refused.
        let daemon = DataDirLock::acquire(data.path()).unwrap();
        assert!(matches!(
            DataDirLock::acquire(data.path()),
            Err(AdminError::DaemonRunning { .. })
        ));
        assert_eq!(list_runs(data.path()).unwrap().len(), 3);
        for err in [
            delete_run(data.path(), "gone").unwrap_err(),
            archive_run(data.path(), "old").unwrap_err(),
        ] {
            assert!(matches!(err, AdminError::DaemonRunning { .. }), "{err}");
        }
        drop(daemon);

        delete_run(data.path(), "gone").unwrap();
        let archived = archive_run(data.path(), "old").unwrap();
        assert_eq!(archived, data.path().join(ARCHIVE_DIR).join("old"));
        assert!(archived.join("replay.log").exists());
        let names: Vec<String> = stored_runs(data.path())
            .unwrap()
            .into_iter()
            .map(|(n, _)| n)
            .collect();
        assert_eq!(
            names,
            ["keep"],
            "a deleted or archived run is no longer served"
        );
        assert!(matches!(
            delete_run(data.path(), "gone"),
            Err(AdminError::NoSuchRun { .. })
        ));
        // Names cannot reach outside runs/.
        for hostile in ["..", "../keep", "a/b", ""] {
            assert!(delete_run(data.path(), hostile).is_err(), "{hostile:?}");
        }
        assert!(data.path().join("runs").join("keep").exists());
    }
}
