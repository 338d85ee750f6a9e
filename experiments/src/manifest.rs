//! `experiment.json`: what an experiment folder holds, so that re-running a command into the
//! same folder resumes the same experiment rather than mixing two different ones.

use crate::scale::Scale;
use planner_service::config::PresetError;
use proto::{Builtin, PlannerOverrides};
use serde::{Deserialize, Deserializer, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// File name of the manifest inside an experiment folder.
pub const FILE: &str = "experiment.json";

/// The settings every run of an experiment shares.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub task: Builtin,
    pub scale: Scale,
    pub episodes: u32,
    /// A run is also complete once it has this many environment steps (whole episodes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timesteps: Option<u64>,
    /// The preset overrides each method's runs sent (the scale's, which depend on the method).
    /// Manifests written before overrides depended on the method hold one value for all.
    #[serde(deserialize_with = "overrides_per_method")]
    pub overrides: BTreeMap<String, PlannerOverrides>,
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

/// `overrides` as stored: one value per method, or (older manifests) one value for every
/// method. An empty map stands for "no overrides" for every method.
#[derive(Deserialize)]
#[serde(untagged)]
enum StoredOverrides {
    PerMethod(BTreeMap<String, PlannerOverrides>),
    Shared(Box<PlannerOverrides>),
}

fn overrides_per_method<'de, D: Deserializer<'de>>(
    d: D,
) -> Result<BTreeMap<String, PlannerOverrides>, D::Error> {
    Ok(match StoredOverrides::deserialize(d)? {
        StoredOverrides::PerMethod(map) => map,
        // The methods are not known here; `Manifest::overrides_for` falls back to the value
        // under the empty name.
        StoredOverrides::Shared(o) => BTreeMap::from([(String::new(), *o)]),
    })
}

impl Manifest {
    /// The manifest of an experiment: the scale's overrides for each method.
    pub fn new(
        task: Builtin,
        scale: Scale,
        episodes: u32,
        methods: Vec<String>,
        seeds: Vec<u64>,
        population: Option<u32>,
    ) -> Result<Self, PresetError> {
        let overrides = methods
            .iter()
            .map(|m| Ok((m.clone(), scale.overrides(task, m, population)?)))
            .collect::<Result<_, PresetError>>()?;
        Ok(Manifest {
            task,
            scale,
            episodes,
            timesteps: None,
            overrides,
            methods,
            seeds,
        })
    }

    /// The overrides `method`'s runs send: its own, or an older manifest's shared value.
    pub fn overrides_for(&self, method: &str) -> PlannerOverrides {
        self.overrides
            .get(method)
            .or_else(|| self.overrides.get(""))
            .cloned()
            .unwrap_or_default()
    }

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
        if existing.timesteps != self.timesteps {
            let show = |t: Option<u64>| t.map_or_else(|| "none".to_string(), |t| t.to_string());
            return Err(mismatch(
                "timesteps",
                show(existing.timesteps),
                show(self.timesteps),
            ));
        }
        for m in self.methods.iter().filter(|m| existing.methods.contains(m)) {
            let (found, wanted) = (existing.overrides_for(m), self.overrides_for(m));
            if found != wanted {
                return Err(mismatch(
                    "overrides",
                    format!("{m}: {found:?}"),
                    format!("{m}: {wanted:?}"),
                ));
            }
        }
        let mut merged = existing.clone();
        for m in &self.methods {
            if !merged.methods.contains(m) {
                merged.methods.push(m.clone());
            }
        }
        // Every method's overrides spelled out from now on: what its runs were started with,
        // or the scale's for a method this resume adds.
        merged.overrides = merged
            .methods
            .iter()
            .map(|m| {
                let o = if existing.methods.contains(m) {
                    existing.overrides_for(m)
                } else {
                    self.overrides_for(m)
                };
                (m.clone(), o)
            })
            .collect();
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
        Manifest::new(
            Builtin::Cartpole,
            Scale::Small,
            episodes,
            methods.iter().map(|m| m.to_string()).collect(),
            seeds.to_vec(),
            None,
        )
        .unwrap()
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
        // A step budget is part of what the experiment is.
        let mut budgeted = manifest(10, &["cem"], &[0]);
        budgeted.timesteps = Some(4000);
        let err = budgeted.resume(&loaded, &dir).unwrap_err();
        assert!(
            err.to_string().contains("timesteps: none there, 4000"),
            "{err}"
        );
        budgeted.save(&dir).unwrap();
        let text = std::fs::read_to_string(dir.join(FILE)).unwrap();
        assert!(text.contains("\"timesteps\": 4000"), "{text}");
        assert_eq!(Manifest::load(&dir).unwrap().unwrap(), budgeted);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn each_method_keeps_its_own_overrides() {
        let m = manifest(8, &["cem", "adam+dae"], &[0]);
        assert_ne!(m.overrides_for("cem"), m.overrides_for("adam+dae"));
        assert_eq!(m.overrides_for("adam+dae").population, None);
        assert_eq!(m.overrides_for("cem").population, Some(200), "half of 400");
    }

    /// A folder written before overrides depended on the method (one shared value) still
    /// resumes, and keeps what its runs were started with.
    #[test]
    fn a_manifest_with_one_shared_overrides_value_still_resumes() {
        let dir = tempfile::tempdir().unwrap();
        let shared = Scale::Small
            .overrides(Builtin::Cartpole, "cem", None)
            .unwrap();
        let old = serde_json::json!({
            "task": "cartpole", "scale": "small", "episodes": 8,
            "overrides": shared, "methods": ["cem", "cem+deen"], "seeds": [0, 1],
        });
        std::fs::write(dir.path().join(FILE), old.to_string()).unwrap();
        let existing = Manifest::load(dir.path()).unwrap().unwrap();
        assert_eq!(existing.overrides_for("cem+deen"), shared);
        let merged = manifest(8, &["cem", "cem+deen", "adam+dae"], &[0])
            .resume(&existing, dir.path())
            .unwrap();
        assert_eq!(merged.overrides_for("cem"), shared);
        assert_eq!(merged.overrides_for("adam+dae").population, None);
        assert_eq!(merged.overrides.len(), 3);
    }
}
