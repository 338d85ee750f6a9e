//! A run's compact resumable state: what a later sitting, on this machine or another, needs to
//! continue an unfinished run.
//!
//! The daemon keeps a run in `<out>/planner/runs/<run>/` (see `planner_service::persist`):
//! its spec (`run.json`), its replay (one segment file per ownership term under `replay/`, and
//! `replay.log` for a run stored before segments) and its newest two model checkpoints, plus
//! the ownership epochs it was taken at (`epochs/`). The resumable state is the spec, the replay
//! files and the newest checkpoint, in one gzip-compressed tar file beside the run's
//! episode file, `runs/<stem>.state.tar.gz` (a few MB for the paper's largest runs), so that
//! it can be committed with the experiment folder while `planner/` is not. A sitting packs it
//! for every run it leaves unfinished, unpacks it before the daemon starts when the daemon's
//! folder lacks the run (a fresh clone), and removes it when the run completes.
//!
//! The epochs are not packed but restored from the replay: a daemon takes a run at the epoch
//! after the newest in `epochs/`, and refuses a replay that holds a newer term than the one it
//! took (another planner's, as far as it can tell). So unpacking records the newest replay
//! segment's term as the run's epoch: a run resumed over several sittings (one term each) opens
//! on a fresh clone at the term after its newest.
//!
//! What the episodes already recorded say stays in `runs/<stem>.csv.partial`, which the
//! launcher merges as for any resumed run.

use flate2::Compression;
use flate2::read::GzDecoder;
use flate2::write::GzEncoder;
use planner_service::persist::RunDir;
use planner_service::replay::segments::{self, SegmentId};
use std::fs::File;
use std::io;
use std::path::{Path, PathBuf};

/// File name suffix of a run's packed state.
pub const SUFFIX: &str = ".state.tar.gz";

/// The files of the run directory `run_dir` that make up its resumable state, relative to
/// it: the spec, the replay files and the newest checkpoint (the one loading tries first: the
/// newest term's newest version), whichever exist.
pub fn state_files(run_dir: &Path) -> io::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    if run_dir.join("run.json").is_file() {
        files.push(PathBuf::from("run.json"));
    }
    files.extend(
        segments::list(run_dir)?
            .into_iter()
            .map(|id| PathBuf::from(id.name())),
    );
    let checkpoints = RunDir::at(run_dir)
        .checkpoints()
        .map_err(io::Error::other)?;
    if let Some(newest) = checkpoints.first() {
        files.push(PathBuf::from(newest.file_name()));
    }
    Ok(files)
}

/// Packs the resumable state of `run_dir` into `archive` (written to a temporary file and
/// renamed, so an interrupted pack leaves the previous archive). Returns the archive's size in
/// bytes, or `None` when the run directory holds no replay (nothing to resume from).
pub fn pack(run_dir: &Path, archive: &Path) -> io::Result<Option<u64>> {
    if segments::list(run_dir)?.is_empty() {
        return Ok(None);
    }
    let tmp = archive.with_extension("tmp");
    {
        let file = File::create(&tmp)?;
        let mut tar = tar::Builder::new(GzEncoder::new(file, Compression::default()));
        for name in state_files(run_dir)? {
            tar.append_path_with_name(run_dir.join(&name), &name)?;
        }
        let file = tar.into_inner()?.finish()?;
        file.sync_all()?;
    }
    std::fs::rename(&tmp, archive)?;
    Ok(Some(std::fs::metadata(archive)?.len()))
}

/// Unpacks `archive` into `run_dir` (created) unless `run_dir` already holds replay: the
/// daemon's own copy is at least as new as any archive it was packed from. Returns whether it
/// unpacked. Only plain files directly in the run directory and replay segments are accepted.
/// The newest segment's term is recorded as the run's epoch (see the module doc).
pub fn unpack(archive: &Path, run_dir: &Path) -> io::Result<bool> {
    if !segments::list(run_dir)?.is_empty() {
        return Ok(false);
    }
    std::fs::create_dir_all(run_dir)?;
    let mut tar = tar::Archive::new(GzDecoder::new(File::open(archive)?));
    for entry in tar.entries()? {
        let mut entry = entry?;
        let path = entry.path()?.into_owned();
        let in_run = path.components().count() == 1
            && matches!(
                path.components().next(),
                Some(std::path::Component::Normal(_))
            );
        let segment = path
            .to_str()
            .and_then(SegmentId::parse)
            .is_some_and(|id| id != SegmentId::Legacy);
        let plain = entry.header().entry_type().is_file() && (in_run || segment);
        if !plain {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!(
                    "{}: unexpected entry `{}` (a run's state holds plain files only)",
                    archive.display(),
                    path.display()
                ),
            ));
        }
        if segment {
            std::fs::create_dir_all(run_dir.join(segments::DIR))?;
        }
        entry.unpack(run_dir.join(&path))?;
    }
    if let Some(term) = segments::newest_token(run_dir) {
        RunDir::at(run_dir)
            .record_token(term, RESTORED)
            .map_err(io::Error::other)?;
    }
    Ok(true)
}

/// The holder named in the epoch file that unpacking writes.
const RESTORED: &str = "restored from a resumable state";

#[cfg(test)]
mod tests {
    use super::*;

    fn write(path: &Path, bytes: &[u8]) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }

    #[test]
    fn the_state_is_the_spec_the_log_and_the_newest_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("planner/runs/ant-cem-s0");
        write(&run.join("run.json"), b"{\"task\":\"ant\"}");
        let log: Vec<u8> = (0..200_000u32)
            .flat_map(|i| (i % 97).to_le_bytes())
            .collect();
        write(&run.join("replay.log"), &log);
        let segment = run.join("replay/00000000000000000004-000000.log");
        write(&segment, b"the newer term");
        // Checkpoints of the layout from before terms, and a newer term's (of a lower
        // version): the newer term's is the newest.
        write(&run.join("models-00000009.safetensors"), b"older");
        write(&run.join("models-00000010.safetensors"), b"old layout");
        let newest = "models-00000000000000000004-00000003.safetensors";
        write(&run.join(newest), b"newest");
        write(&run.join("epochs/00000000000000000003"), b"planner-1");
        let archive = dir.path().join("runs/ant-cem-s0.state.tar.gz");
        std::fs::create_dir_all(archive.parent().unwrap()).unwrap();
        let size = pack(&run, &archive).unwrap().unwrap();
        assert!(size < log.len() as u64 / 4, "compressed: {size} bytes");

        // A fresh clone: no daemon folder. The state comes back without the old checkpoint;
        // the epoch is the newest replay term's, not the old folder's 3.
        let fresh = dir.path().join("clone/planner/runs/ant-cem-s0");
        assert!(unpack(&archive, &fresh).unwrap());
        let mut names: Vec<String> = std::fs::read_dir(&fresh)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        assert_eq!(
            names,
            ["epochs", newest, "replay", "replay.log", "run.json"]
        );
        let restored = RunDir::at(&fresh);
        assert_eq!(restored.current_epoch().unwrap(), 4);
        assert_eq!(restored.epoch_holder(4).as_deref(), Some(RESTORED));
        assert_eq!(std::fs::read(fresh.join("replay.log")).unwrap(), log);
        assert_eq!(
            std::fs::read(fresh.join("replay/00000000000000000004-000000.log")).unwrap(),
            b"the newer term"
        );
        assert_eq!(std::fs::read(fresh.join(newest)).unwrap(), b"newest");
        // The daemon's own copy is never overwritten by an archive.
        write(&fresh.join("replay.log"), b"newer");
        assert!(!unpack(&archive, &fresh).unwrap());
        assert_eq!(std::fs::read(fresh.join("replay.log")).unwrap(), b"newer");
    }

    /// A run resumed over two sittings holds replay segments of terms 1 and 2; unpacked on a
    /// fresh clone, the next daemon takes it at term 3, so its replay (term 2 the newest) is its
    /// own to append to. Without the restored epoch it took term 1 and refused the replay as
    /// claimed by another planner at epoch 2.
    #[test]
    fn a_run_of_two_sittings_unpacks_to_be_taken_after_its_newest_term() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("planner/runs/halfcheetah-adam-dae-s1");
        write(&run.join("run.json"), b"{}");
        write(
            &run.join("replay/00000000000000000001-000000.log"),
            b"first sitting",
        );
        write(
            &run.join("replay/00000000000000000002-000000.log"),
            b"second sitting",
        );
        let archive = dir.path().join("adam-dae-s1.state.tar.gz");
        pack(&run, &archive).unwrap().unwrap();
        let fresh = dir
            .path()
            .join("clone/planner/runs/halfcheetah-adam-dae-s1");
        assert!(unpack(&archive, &fresh).unwrap());
        let restored = RunDir::at(&fresh);
        let seen = restored.current_epoch().unwrap();
        assert_eq!(restored.claim_epoch_after(seen, "daemon").unwrap(), 3);
    }

    #[test]
    fn a_run_without_a_replay_log_has_no_state() {
        let dir = tempfile::tempdir().unwrap();
        write(&dir.path().join("run/run.json"), b"{}");
        let archive = dir.path().join("x.state.tar.gz");
        assert_eq!(pack(&dir.path().join("run"), &archive).unwrap(), None);
        assert!(!archive.exists());
    }

    #[test]
    fn an_archive_with_paths_outside_the_run_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let archive = dir.path().join("evil.state.tar.gz");
        {
            let file = File::create(&archive).unwrap();
            let mut tar = tar::Builder::new(GzEncoder::new(file, Compression::default()));
            let mut header = tar::Header::new_gnu();
            header.set_size(3);
            header.set_mode(0o644);
            header.set_cksum();
            tar.append_data(&mut header, "sub/escape", &b"bad"[..])
                .unwrap();
            tar.into_inner().unwrap().finish().unwrap();
        }
        let err = unpack(&archive, &dir.path().join("run")).unwrap_err();
        assert!(err.to_string().contains("plain files only"), "{err}");
        assert!(!dir.path().join("run/sub").exists());
    }
}
