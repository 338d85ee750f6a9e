//! `experiment.json`: what an experiment folder holds, so that re-running a command into the
//! same folder resumes the same experiment rather than mixing two different ones.

use crate::scale::Scale;
use proto::{PlannerOverrides, Builtin};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// File name of the manifest inside an experiment folder.
pub const FILE: &str = "experiment.json";

/// The settings every run of an experiment shares.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub task: Builtin,
    pub scale: Scale,
    pub episodes: u32,
    /// The preset overrides every run sent (the scale's).
    pub overrides: PlannerOverrides,
    /// Methods and seeds asked for so far (a resumed experiment may add more).
    pub methods: Vec<String>,
    pub seeds: Vec<u64>,
}

/// A folder that holds a different experiment.
#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    #[error("{0}")]
    Io(#[from] std::io::Error),
    #[error("{path}: {source}")]
    Parse {
        path: String,
        #[source]
        source: serde_json::Error,
    },
    #[error(
        "{path} holds a different experiment ({what}: {found} there, {wanted} asked for); \
         give another --out folder"
    )]
    Mismatch {
        path: String,
        what: &'static str,
        found: String,
        wanted: String,
    },
}

impl Manifest {
    /// Loads the folder's manifest if it has one.
    pub fn load(dir: &Path) -> Result<Option<Self>, ManifestError> {
        let path = dir.join(FILE);
        match std::fs::read_to_string(&path) {
            Ok(text) => {
                serde_json::from_str(&text)
                    .map(Some)
                    .map_err(|source| ManifestError::Parse {
                        path: path.display().to_string(),
                        source,
                    })
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    /// Checks that `self` (what the command line asks for) continues `existing`, and returns
    /// the merged manifest: the union of methods and seeds.
    pub fn resume(&self, existing: &Manifest, dir: &Path) -> Result<Manifest, ManifestError> {
        let mismatch = |what, found: String, wanted: String| ManifestError::Mismatch {
            path: dir.join(FILE).display().to_string(),
            what,
            found,
            wanted,
        };
        if existing.task != self.task {
            return Err(mismatch(
                "task",
                existing.task.to_string(),
                self.task.to_string(),
            ));
        }
        if existing.scale != self.scale {
            return Err(mismatch(
                "scale",
                existing.scale.name().into(),
                self.scale.name().into(),
            ));
        }
        if existing.episodes != self.episodes {
            return Err(mismatch(
                "episodes",
                existing.episodes.to_string(),
                self.episodes.to_string(),
            ));
        }
        if existing.overrides != self.overrides {
            return Err(mismatch(
                "overrides",
                format!("{:?}", existing.overrides),
                format!("{:?}", self.overrides),
            ));
        }
        let mut merged = existing.clone();
        for m in &self.methods {
            if !merged.methods.contains(m) {
                merged.methods.push(m.clone());
            }
        }
        for s in &self.seeds {
            if !merged.seeds.contains(s) {
                merged.seeds.push(*s);
            }
        }
        Ok(merged)
    }

    /// Writes the manifest into `dir`.
    pub fn save(&self, dir: &Path) -> Result<(), ManifestError> {
        let text = serde_json::to_string_pretty(self).map_err(|source| ManifestError::Parse {
            path: dir.join(FILE).display().to_string(),
            source,
        })?;
        std::fs::write(dir.join(FILE), text + "\n")?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest(episodes: u32, methods: &[&str], seeds: &[u64]) -> Manifest {
        Manifest {
            task: Builtin::Cartpole.name().into(),
            scale: Scale::Small,
            episodes,
            overrides: Scale::Small.overrides(Builtin::Cartpole),
            methods: methods.iter().map(|m| m.to_string()).collect(),
            seeds: seeds.to_vec(),
        }
    }

    #[test]
    fn resuming_merges_methods_and_seeds_and_refuses_other_experiments() {
        let dir = std::env::temp_dir().join(format!("ebmpc-manifest-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        assert_eq!(Manifest::load(&dir).unwrap(), None);
        let first = manifest(10, &["cem"], &[0, 1]);
        first.save(&dir).unwrap();
        let loaded = Manifest::load(&dir).unwrap().unwrap();
        assert_eq!(loaded, first);
        let merged = manifest(10, &["cem", "cem+deen"], &[1, 2])
            .resume(&loaded, &dir)
            .unwrap();
        assert_eq!(merged.methods, vec!["cem", "cem+deen"]);
        assert_eq!(merged.seeds, vec![0, 1, 2]);
        let err = manifest(12, &["cem"], &[0])
            .resume(&loaded, &dir)
            .unwrap_err();
        assert!(err.to_string().contains("episodes: 10 there, 12"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
