//! Managing the runs of a data directory from outside the daemon (`planner-service runs`),
//! and the locks that keep daemons and such changes apart.
//!
//! A daemon holds two advisory locks for as long as it serves (the OS drops them when the
//! process dies, SIGKILL included):
//!
//! - an exclusive one on `{data_dir}/daemon-{planner_id}.lock`: two daemons with the same id on
//!   one data directory would take each other's runs (ids name the run leases of a fleet);
//! - a shared one on `{data_dir}/daemon.lock`: the planners of a fleet share one data
//!   directory (see `crate::fleet`), and all of them hold it at once.
//!
//! Deleting or archiving a run takes `daemon.lock` exclusively first, so it is refused while
//! any daemon serves the directory (a daemon keeps a run's files open and would go on writing
//! to a deleted or moved log, and in a fleet any planner may take any run over), and a daemon
//! cannot start while a run is being changed. The refusal names the planners serving and, if
//! one of them holds the run's newest ownership epoch, its owner. Listing only reads and works
//! at any time.

use super::{
    CHECKPOINT_PREFIX, CHECKPOINT_SUFFIX, PersistError, RUNS_DIR, RunDir, io_error, run_dirs_under,
};
use proto::RunSpec;
use std::fs::{self, File, TryLockError};
use std::path::{Path, PathBuf};

/// Held shared by every serving daemon, exclusively by `runs delete|archive`.
const SHARED_LOCK: &str = "daemon.lock";
/// `daemon-{planner_id}.lock`: held exclusively by the daemon with that id.
const DAEMON_LOCK_PREFIX: &str = "daemon-";
const DAEMON_LOCK_SUFFIX: &str = ".lock";

/// Where archived runs are moved, under the data directory.
pub const ARCHIVE_DIR: &str = "archive";

/// Which runs of a data directory: those a daemon serves (`runs/`), or those moved out of its
/// way by `runs archive` (`archive/`), which keep their files for reading (export, analysis).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shelf {
    Served,
    Archived,
}

impl Shelf {
    /// The folder of this shelf's runs under `data_dir`.
    pub fn root(self, data_dir: &Path) -> PathBuf {
        data_dir.join(match self {
            Shelf::Served => RUNS_DIR,
            Shelf::Archived => ARCHIVE_DIR,
        })
    }
}

/// Why a run could not be managed, or a daemon not start.
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    #[error(
        "planner daemons are serving {data_dir} ({}){}: stop them first, runs are only deleted or archived while no daemon uses the directory",
        if .planners.is_empty() { "they hold daemon.lock".to_string() } else { format!("planners {}", .planners.join(", ")) },
        .owner.as_ref().map_or_else(String::new, |o| format!("; planner `{o}` owns the run"))
    )]
    DaemonRunning {
        data_dir: String,
        /// The planners whose daemon lock is held (empty if none could be told apart).
        planners: Vec<String>,
        /// The serving planner that holds the run's newest ownership epoch, if one does.
        owner: Option<String>,
    },
    #[error(
        "a planner daemon with id `{planner_id}` already serves {data_dir} (it holds daemon-{planner_id}.lock): give every planner its own id"
    )]
    SameId {
        planner_id: String,
        data_dir: String,
    },
    #[error(
        "runs of {data_dir} are being deleted or archived right now (daemon.lock is held): start the daemon again when that is done"
    )]
    Managing { data_dir: String },
    #[error("no run `{name}` in {data_dir}")]
    NoSuchRun { name: String, data_dir: String },
    #[error("invalid name: {0}")]
    Name(#[from] proto::keys::InvalidName),
    #[error("{path} already exists")]
    Exists { path: String },
    #[error(transparent)]
    Persist(#[from] PersistError),
    #[error(transparent)]
    Replay(#[from] crate::replay::LogError),
}

/// A serving daemon's locks on its data directory; released when dropped (or when the
/// process dies).
#[derive(Debug)]
pub struct DaemonLock {
    _own: File,
    _shared: File,
}

impl DaemonLock {
    /// Takes planner `planner_id`'s locks on `data_dir` (creating the directory): fails if a
    /// daemon with the same id serves it, or if runs are being deleted or archived.
    pub fn acquire(data_dir: &Path, planner_id: &str) -> Result<Self, AdminError> {
        proto::validate_name(planner_id)?;
        fs::create_dir_all(data_dir).map_err(io_error(data_dir))?;
        let own = open_lock_file(&daemon_lock_path(data_dir, planner_id))?;
        match own.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                return Err(AdminError::SameId {
                    planner_id: planner_id.to_string(),
                    data_dir: data_dir.display().to_string(),
                });
            }
            Err(TryLockError::Error(e)) => {
                return Err(io_error(&daemon_lock_path(data_dir, planner_id))(e).into());
            }
        }
        let path = data_dir.join(SHARED_LOCK);
        let shared = open_lock_file(&path)?;
        match shared.try_lock_shared() {
            Ok(()) => Ok(Self {
                _own: own,
                _shared: shared,
            }),
            Err(TryLockError::WouldBlock) => Err(AdminError::Managing {
                data_dir: data_dir.display().to_string(),
            }),
            Err(TryLockError::Error(e)) => Err(io_error(&path)(e).into()),
        }
    }
}

fn daemon_lock_path(data_dir: &Path, planner_id: &str) -> PathBuf {
    data_dir.join(format!(
        "{DAEMON_LOCK_PREFIX}{planner_id}{DAEMON_LOCK_SUFFIX}"
    ))
}

fn open_lock_file(path: &Path) -> Result<File, AdminError> {
    Ok(fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(path)
        .map_err(io_error(path))?)
}

/// The exclusive hold on a data directory that deleting or archiving a run needs: no daemon
/// serves it meanwhile, and none can start.
struct ManageLock {
    _file: File,
}

impl ManageLock {
    /// Takes the hold for changing `run`, or says who serves `data_dir`.
    fn acquire(data_dir: &Path, run: &RunDir) -> Result<Self, AdminError> {
        fs::create_dir_all(data_dir).map_err(io_error(data_dir))?;
        let path = data_dir.join(SHARED_LOCK);
        let file = open_lock_file(&path)?;
        match file.try_lock() {
            Ok(()) => Ok(Self { _file: file }),
            Err(TryLockError::WouldBlock) => {
                let planners = serving_planners(data_dir);
                let owner = run
                    .current_epoch()
                    .ok()
                    .and_then(|epoch| run.epoch_holder(epoch))
                    .filter(|holder| planners.contains(holder));
                Err(AdminError::DaemonRunning {
                    data_dir: data_dir.display().to_string(),
                    planners,
                    owner,
                })
            }
            Err(TryLockError::Error(e)) => Err(io_error(&path)(e).into()),
        }
    }
}

/// The planners whose `daemon-{id}.lock` is held now, by id. Probing takes a lock that is
/// free for an instant (a shared one, released at once), so this is for messages only.
fn serving_planners(data_dir: &Path) -> Vec<String> {
    let Ok(entries) = fs::read_dir(data_dir) else {
        return Vec::new();
    };
    let mut planners: Vec<String> = entries
        .filter_map(|entry| {
            let name = entry.ok()?.file_name().into_string().ok()?;
            let id = name
                .strip_prefix(DAEMON_LOCK_PREFIX)?
                .strip_suffix(DAEMON_LOCK_SUFFIX)?
                .to_string();
            let file = File::open(daemon_lock_path(data_dir, &id)).ok()?;
            matches!(file.try_lock_shared(), Err(TryLockError::WouldBlock)).then_some(id)
        })
        .collect();
    planners.sort();
    planners
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

/// The runs on `shelf` of `data_dir`, by name. Reads only, so it is safe while a daemon serves.
pub fn list_runs(data_dir: &Path, shelf: Shelf) -> Result<Vec<RunEntry>, AdminError> {
    run_dirs_under(&shelf.root(data_dir))?
        .into_iter()
        .map(|(name, dir)| {
            let spec = dir.read_spec().ok().flatten();
            let replay_bytes = dir.replay_bytes();
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

/// The directory of run `name` on `shelf`, checked to exist (the name cannot leave the shelf).
fn existing_run(data_dir: &Path, shelf: Shelf, name: &str) -> Result<RunDir, AdminError> {
    proto::validate_name(name)?;
    let root = shelf.root(data_dir);
    let dir = RunDir::at(root.join(name));
    if !dir.root().is_dir() {
        return Err(AdminError::NoSuchRun {
            name: name.to_string(),
            data_dir: root.display().to_string(),
        });
    }
    Ok(dir)
}

/// Every intact record of run `name`'s replay, in order, as its owner would read it (see
/// `crate::replay::segments`), without writing anything, so it is safe while a daemon serves
/// (records appended meanwhile may be missing, never half-read).
pub fn read_replay(
    data_dir: &Path,
    shelf: Shelf,
    name: &str,
) -> Result<crate::replay::Recovered, AdminError> {
    let dir = existing_run(data_dir, shelf, name)?;
    Ok(crate::replay::segments::read(dir.root())?.recovered)
}

/// Deletes run `name` and everything it stored, unless a daemon serves `data_dir`.
pub fn delete_run(data_dir: &Path, name: &str) -> Result<(), AdminError> {
    let dir = existing_run(data_dir, Shelf::Served, name)?;
    let _lock = ManageLock::acquire(data_dir, &dir)?;
    fs::remove_dir_all(dir.root()).map_err(io_error(dir.root()))?;
    Ok(())
}

/// Moves run `name` to `{data_dir}/archive/{name}` (kept whole, no longer served), unless a
/// daemon serves `data_dir`. Returns where it went.
pub fn archive_run(data_dir: &Path, name: &str) -> Result<PathBuf, AdminError> {
    let dir = existing_run(data_dir, Shelf::Served, name)?;
    let _lock = ManageLock::acquire(data_dir, &dir)?;
    let archive = Shelf::Archived.root(data_dir);
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
    use proto::{Builtin, PlannerOverrides, TrainMode};

    fn store_run(data: &Path, name: &str) {
        let dir = RunDir::new(data, name);
        dir.write_spec(&RunSpec {
            task: Builtin::Cartpole.name().into(),
            preset: None,
            overrides: PlannerOverrides::default(),
            mode: TrainMode::Sync,
            seed: 1,
            task_spec: None,
        })
        .unwrap();
        fs::write(dir.root().join(crate::replay::segments::LEGACY), [0u8; 100]).unwrap();
    }

    #[test]
    fn runs_are_listed_archived_and_deleted_only_while_no_daemon_holds_the_directory() {
        let data = tempfile::tempdir().unwrap();
        store_run(data.path(), "keep");
        store_run(data.path(), "old");
        store_run(data.path(), "gone");
        let listed = list_runs(data.path(), Shelf::Served).unwrap();
        let names: Vec<&str> = listed.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(names, ["gone", "keep", "old"]);
        assert_eq!(listed[0].replay_bytes, 100);
        assert_eq!(listed[0].spec.as_ref().unwrap().task, "cartpole");

        // While a daemon holds its locks, listing works and changes are refused.
        let daemon = DaemonLock::acquire(data.path(), "pa").unwrap();
        assert_eq!(list_runs(data.path(), Shelf::Served).unwrap().len(), 3);
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
        let names: Vec<String> = crate::persist::stored_runs(data.path())
            .unwrap()
            .into_iter()
            .map(|(n, _)| n)
            .collect();
        assert_eq!(
            names,
            ["keep"],
            "a deleted or archived run is no longer served"
        );
        // The archived run is still listed and read on its own shelf, and only there.
        let archived: Vec<String> = list_runs(data.path(), Shelf::Archived)
            .unwrap()
            .into_iter()
            .map(|r| r.name)
            .collect();
        assert_eq!(archived, ["old"]);
        assert_eq!(
            list_runs(data.path(), Shelf::Archived).unwrap()[0]
                .spec
                .as_ref()
                .unwrap()
                .task,
            "cartpole"
        );
        assert!(read_replay(data.path(), Shelf::Archived, "old").is_ok());
        assert!(matches!(
            read_replay(data.path(), Shelf::Served, "old"),
            Err(AdminError::NoSuchRun { .. })
        ));
        // Archiving a run whose name the archive already holds is refused, the run kept.
        store_run(data.path(), "old");
        assert!(matches!(
            archive_run(data.path(), "old"),
            Err(AdminError::Exists { .. })
        ));
        assert!(data.path().join("runs").join("old").exists());
        delete_run(data.path(), "old").unwrap();
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

    /// Planners of a fleet share a data directory, each under its own id; a second daemon
    /// with an id already serving is refused, and so is a daemon starting while runs change.
    #[test]
    fn daemons_share_a_data_directory_under_distinct_ids_only() {
        let data = tempfile::tempdir().unwrap();
        let pa = DaemonLock::acquire(data.path(), "pa").unwrap();
        let pb = DaemonLock::acquire(data.path(), "pb").unwrap();
        let err = DaemonLock::acquire(data.path(), "pa").unwrap_err();
        assert!(
            matches!(&err, AdminError::SameId { planner_id, .. } if planner_id == "pa"),
            "{err}"
        );
        // The id names a file: one that is not a key chunk is refused before any file is made.
        for hostile in ["../pa", "a/b", "", "p*", "pa\0"] {
            assert!(
                matches!(
                    DaemonLock::acquire(data.path(), hostile),
                    Err(AdminError::Name(_))
                ),
                "{hostile:?}"
            );
        }
        drop((pa, pb));
        // The id is free again once its daemon stops (or dies: the OS drops the lock).
        let pa = DaemonLock::acquire(data.path(), "pa").unwrap();
        drop(pa);
        // While a run is being deleted, no daemon starts.
        let run = RunDir::new(data.path(), "r");
        let managing = ManageLock::acquire(data.path(), &run).unwrap();
        assert!(matches!(
            DaemonLock::acquire(data.path(), "pc"),
            Err(AdminError::Managing { .. })
        ));
        drop(managing);
        DaemonLock::acquire(data.path(), "pc").unwrap();
    }

    /// `runs delete|archive` are refused while any planner of a fleet serves the directory,
    /// whether or not it owns the run, and the refusal names the serving planners and the
    /// run's owner.
    #[test]
    fn runs_are_changed_only_while_no_planner_of_the_fleet_serves() {
        let data = tempfile::tempdir().unwrap();
        store_run(data.path(), "r");
        let dir = RunDir::new(data.path(), "r");
        assert_eq!(dir.claim_epoch_after(0, "pa").unwrap(), 1);
        // pb serves, pa (the run's owner on disk) does not: refused, and no owner named.
        let pb = DaemonLock::acquire(data.path(), "pb").unwrap();
        let err = delete_run(data.path(), "r").unwrap_err();
        match &err {
            AdminError::DaemonRunning {
                planners, owner, ..
            } => {
                assert_eq!(planners, &["pb"]);
                assert_eq!(owner, &None);
            }
            other => panic!("{other}"),
        }
        // pa serves too: the run is owned now, and the refusal says by whom.
        let pa = DaemonLock::acquire(data.path(), "pa").unwrap();
        let err = archive_run(data.path(), "r").unwrap_err();
        match &err {
            AdminError::DaemonRunning {
                planners, owner, ..
            } => {
                assert_eq!(planners, &["pa", "pb"]);
                assert_eq!(owner.as_deref(), Some("pa"));
            }
            other => panic!("{other}"),
        }
        assert!(
            err.to_string().contains("planner `pa` owns the run"),
            "{err}"
        );
        // Only the owner left serving: still refused.
        drop(pb);
        assert!(matches!(
            delete_run(data.path(), "r"),
            Err(AdminError::DaemonRunning { .. })
        ));
        drop(pa);
        delete_run(data.path(), "r").unwrap();
        assert!(!dir.root().exists());
    }

    #[test]
    fn a_replay_is_read_beside_a_serving_daemon_without_changing_its_file() {
        use crate::replay::{ActionOrigin, HeaderRecord, Record, ReplayLog, TransitionRecord};
        let data = tempfile::tempdir().unwrap();
        store_run(data.path(), "r");
        let path = RunDir::new(data.path(), "r")
            .root()
            .join(crate::replay::segments::LEGACY);
        fs::remove_file(&path).unwrap();
        let transition = Record::Transition(TransitionRecord {
            epoch: 1,
            agent: "a".into(),
            episode: 0,
            step: 0,
            obs: vec![0.5; 4],
            act: vec![1.0],
            origin: ActionOrigin::Planned,
            next_obs: vec![0.25; 4],
            reward: 2.0,
        });
        let (mut log, _) = ReplayLog::open(&path).unwrap();
        log.append(&[
            Record::Header(HeaderRecord {
                task: "cartpole".into(),
                obs_dim: 4,
                act_dim: 1,
            }),
            transition.clone(),
        ])
        .unwrap();
        // A daemon in the middle of a write: a torn record at the end.
        fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .and_then(|mut f| std::io::Write::write_all(&mut f, &[7u8; 5]))
            .unwrap();
        let _daemon = DaemonLock::acquire(data.path(), "pa").unwrap();
        let before = fs::read(&path).unwrap();
        let read = read_replay(data.path(), Shelf::Served, "r").unwrap();
        assert_eq!(read.records.len(), 2);
        assert_eq!(read.records[1], transition);
        assert_eq!(read.truncated_bytes, 5);
        assert_eq!(fs::read(&path).unwrap(), before, "reading wrote nothing");
        assert!(matches!(
            read_replay(data.path(), Shelf::Served, "none"),
            Err(AdminError::NoSuchRun { .. })
        ));
        assert!(matches!(
            read_replay(data.path(), Shelf::Served, "../r"),
            Err(AdminError::Name(_))
        ));
        assert!(matches!(
            read_replay(data.path(), Shelf::Archived, "../runs/r"),
            Err(AdminError::Name(_))
        ));
    }
}
