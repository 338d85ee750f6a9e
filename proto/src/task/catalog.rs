//! The tasks a process knows by name: the five built-ins plus those its operator declared (a
//! daemon's `[tasks.NAME]` tables and its tasks folder).

use super::Builtin;
use super::compiled::{Task, TaskError};
use super::spec::{SpecBounds, TaskSpec};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A task name that is not in the catalog.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown task `{name}` (known: {known})")]
pub struct UnknownTask {
    /// The name asked for, cut to [`crate::keys::SHOWN_NAME_CHARS`] characters.
    pub name: String,
    /// The catalog's names, comma-separated.
    pub known: String,
}

/// A declared task that cannot join the catalog.
#[derive(Debug, thiserror::Error)]
pub enum CatalogError {
    #[error("task {name}: {source}")]
    Task { name: String, source: TaskError },
    #[error("task {0} is declared twice (or is a built-in task's name)")]
    Duplicate(String),
    #[error("[tasks.{key}] names its task `{name}`: leave the name out or make them agree")]
    NameMismatch { key: String, name: String },
    #[error("tasks folder {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("task file {path}: {message}")]
    Parse { path: PathBuf, message: String },
}

/// Tasks by name.
#[derive(Debug, Clone)]
pub struct TaskCatalog {
    tasks: BTreeMap<String, &'static Task>,
}

impl Default for TaskCatalog {
    fn default() -> Self {
        Self::builtin()
    }
}

impl TaskCatalog {
    /// The five built-in tasks.
    pub fn builtin() -> Self {
        Self {
            tasks: Builtin::ALL
                .iter()
                .map(|b| (b.name().to_string(), b.task()))
                .collect(),
        }
    }

    /// Adds a declared task, named by `key` (a `[tasks.NAME]` table's key or a file's stem)
    /// unless its spec names itself the same. Validated against `bounds`.
    pub fn declare(
        &mut self,
        key: &str,
        mut spec: TaskSpec,
        bounds: &SpecBounds,
    ) -> Result<&'static Task, CatalogError> {
        if spec.name.is_empty() {
            spec.name = key.to_string();
        } else if spec.name != key {
            return Err(CatalogError::NameMismatch {
                key: key.to_string(),
                name: spec.name,
            });
        }
        if self.tasks.contains_key(key) {
            return Err(CatalogError::Duplicate(key.to_string()));
        }
        let task = Task::intern(spec, bounds).map_err(|source| CatalogError::Task {
            name: key.to_string(),
            source,
        })?;
        self.tasks.insert(key.to_string(), task);
        Ok(task)
    }

    /// Adds every `*.toml` and `*.json` file of `dir` as a task named by its file stem.
    pub fn declare_folder(&mut self, dir: &Path, bounds: &SpecBounds) -> Result<(), CatalogError> {
        let io = |source| CatalogError::Io {
            path: dir.to_path_buf(),
            source,
        };
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(io)?
            .map(|e| e.map(|e| e.path()))
            .collect::<Result<_, _>>()
            .map_err(io)?;
        files.sort();
        for path in files {
            let (Some(stem), Some(ext)) = (
                path.file_stem().and_then(|s| s.to_str()),
                path.extension().and_then(|s| s.to_str()),
            ) else {
                continue;
            };
            let parse = |message: String| CatalogError::Parse {
                path: path.clone(),
                message,
            };
            let text = std::fs::read_to_string(&path).map_err(|source| CatalogError::Io {
                path: path.clone(),
                source,
            })?;
            let spec: TaskSpec = match ext {
                "toml" => toml::from_str(&text).map_err(|e| parse(e.to_string()))?,
                "json" => serde_json::from_str(&text).map_err(|e| parse(e.to_string()))?,
                _ => continue,
            };
            self.declare(stem, spec, bounds)?;
        }
        Ok(())
    }

    /// The task of that name.
    pub fn get(&self, name: &str) -> Result<&'static Task, UnknownTask> {
        self.tasks.get(name).copied().ok_or_else(|| UnknownTask {
            name: name.chars().take(crate::keys::SHOWN_NAME_CHARS).collect(),
            known: self.tasks.keys().cloned().collect::<Vec<_>>().join(", "),
        })
    }

    /// Every task, by name.
    pub fn tasks(&self) -> impl Iterator<Item = &'static Task> + '_ {
        self.tasks.values().copied()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::RewardKind;

    fn small(name: &str) -> TaskSpec {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = name.into();
        spec.episode_len = 50;
        spec
    }

    #[test]
    fn the_catalog_holds_the_builtins_and_declared_tasks() {
        let mut catalog = TaskCatalog::builtin();
        assert_eq!(catalog.get("ant").unwrap().name(), "ant");
        let err = catalog.get("walker").unwrap_err().to_string();
        assert!(
            err.contains("unknown task `walker`") && err.contains("cartpole"),
            "{err}"
        );
        let mut unnamed = small("");
        unnamed.episode_len = 60;
        let task = catalog
            .declare("short-cartpole", unnamed, &SpecBounds::default())
            .unwrap();
        assert_eq!(task.name(), "short-cartpole");
        assert_eq!(catalog.get("short-cartpole").unwrap().episode_len, 60);
        assert!(matches!(
            catalog.declare("cartpole", small("cartpole"), &SpecBounds::default()),
            Err(CatalogError::Duplicate(_))
        ));
        assert!(matches!(
            catalog.declare("x", small("y"), &SpecBounds::default()),
            Err(CatalogError::NameMismatch { .. })
        ));
    }

    #[test]
    fn a_tasks_folder_is_read_by_file_stem() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("short.json"),
            serde_json::to_string(&small("")).unwrap(),
        )
        .unwrap();
        let mut toml_spec = small("");
        toml_spec.episode_len = 70;
        std::fs::write(
            dir.path().join("shorter.toml"),
            toml::to_string(&toml_spec).unwrap(),
        )
        .unwrap();
        std::fs::write(dir.path().join("README"), "not a task").unwrap();
        let mut catalog = TaskCatalog::builtin();
        catalog
            .declare_folder(dir.path(), &SpecBounds::default())
            .unwrap();
        assert_eq!(catalog.get("short").unwrap().episode_len, 50);
        assert_eq!(catalog.get("shorter").unwrap().episode_len, 70);

        std::fs::write(dir.path().join("broken.toml"), "obs_dim = \"four\"").unwrap();
        let err = TaskCatalog::builtin()
            .declare_folder(dir.path(), &SpecBounds::default())
            .unwrap_err();
        assert!(err.to_string().contains("broken.toml"), "{err}");
        // A task whose reward is learned is declared like any other.
        let mut learned = small("");
        learned.reward = RewardKind::Learned;
        let mut catalog = TaskCatalog::builtin();
        catalog
            .declare("l", learned, &SpecBounds::default())
            .unwrap();
        assert!(catalog.get("l").unwrap().reward_is_learned());
    }
}
