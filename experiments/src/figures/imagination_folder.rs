//! The output folder of a Figure 5 comparison over several seeds, kept so that the seeds can
//! accumulate over sittings, one whole seed at a time, as the Figure 4 launcher's runs do.
//!
//! At the paper's sizes one seed learns the task from scratch and compares 20 start states: an
//! hour or more on a 2-core machine, so three seeds rarely fit one sitting. The folder is the
//! record: `imagination.json` holds the settings every seed shares (a later command with other
//! settings is refused, so seeds of different experiments never mix), `imagination_states.csv`
//! every finished seed's per-state rows, and `imagination_seeds.csv` each finished seed's
//! training returns, wall time and machine. A command re-run into the folder skips the seeds it
//! already holds; a seed cut off before it finished left nothing behind (its rows are written
//! when it ends) and runs again from scratch.

use super::imagination::{
    ImaginationConfig, ImaginationResult, StateRow, read_csv, read_state_rows,
};
use crate::provenance::Machine;
use anyhow::{Context, Result, bail};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What every seed of one folder shares: the configuration without its seed.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Settings {
    pub task: String,
    pub scale: String,
    pub plan_scale: String,
    pub method: String,
    pub train_episodes: u32,
    pub mpc_steps: u32,
    pub inference_precision: String,
    pub states: u32,
}

impl Settings {
    pub fn of(config: &ImaginationConfig) -> Self {
        Self {
            task: config.task.name().to_string(),
            scale: config.scale.name().to_string(),
            plan_scale: config.plan_scale.name().to_string(),
            method: config.method.clone(),
            train_episodes: config.train_episodes,
            mpc_steps: config.mpc_steps,
            inference_precision: config.inference_precision.to_string(),
            states: config.states,
        }
    }
}

/// One finished seed's record (a row of `imagination_seeds.csv`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SeedRecord {
    pub seed: u64,
    /// Returns of its training episodes, `;`-separated (the last is the paper's "after 5
    /// episodes" model's own episode).
    pub training_returns: String,
    pub wall_seconds: f64,
    /// The binaries' commit, the machine and its CPU, as the Figure 4 records name them.
    pub commit: String,
    pub cpu: String,
    /// CPU family and model numbers, e.g. "25/17".
    pub cpu_family_model: String,
    pub logical_cpus: usize,
}

/// A folder of seeds of one comparison.
pub struct Folder {
    dir: PathBuf,
    rows: Vec<StateRow>,
    seeds: Vec<SeedRecord>,
}

impl Folder {
    /// Opens `dir` (created) for `settings`: records them in a new folder, refuses a folder
    /// whose recorded settings differ, and reads the seeds it holds.
    pub fn open(dir: &Path, settings: &Settings) -> Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join("imagination.json");
        match std::fs::read_to_string(&path) {
            Ok(text) => {
                let recorded: Settings = serde_json::from_str(&text)
                    .with_context(|| format!("reading {}", path.display()))?;
                if &recorded != settings {
                    bail!(
                        "{} holds another comparison ({recorded:?}); this command asks for \
                         {settings:?}: use another --out",
                        dir.display()
                    );
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                if dir.join("imagination_states.csv").exists() {
                    bail!(
                        "{} holds rows of a comparison whose settings were not recorded: use \
                         another --out",
                        dir.display()
                    );
                }
                std::fs::write(&path, serde_json::to_string_pretty(settings)? + "\n")
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
        }
        let states = dir.join("imagination_states.csv");
        let rows = if states.exists() {
            read_state_rows(&states)?
        } else {
            Vec::new()
        };
        let seeds_path = dir.join("imagination_seeds.csv");
        let seeds = if seeds_path.exists() {
            read_csv(&seeds_path)?
        } else {
            Vec::new()
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            rows,
            seeds,
        })
    }

    /// The seeds whose rows the folder holds.
    pub fn finished(&self) -> BTreeSet<u64> {
        self.rows.iter().map(|r| r.seed).collect()
    }

    /// Every finished seed's per-state rows.
    pub fn rows(&self) -> &[StateRow] {
        &self.rows
    }

    /// The mean wall time of the seeds recorded so far (`None`: none yet).
    pub fn seconds_per_seed(&self) -> Option<Duration> {
        let n = self.seeds.len();
        (n > 0).then(|| {
            Duration::from_secs_f64(
                self.seeds.iter().map(|s| s.wall_seconds).sum::<f64>() / n as f64,
            )
        })
    }

    /// Records a finished seed: appends its rows and its record, each file rewritten whole
    /// through a temporary file so that a reader never sees half of one.
    pub fn record(
        &mut self,
        seed: u64,
        result: &ImaginationResult,
        wall: Duration,
        commit: &str,
    ) -> Result<()> {
        if self.finished().contains(&seed) {
            bail!("seed {seed} is already recorded in {}", self.dir.display());
        }
        self.rows.extend(result.states.iter().cloned());
        let machine = Machine::this();
        self.seeds.push(SeedRecord {
            seed,
            training_returns: result
                .training_returns
                .iter()
                .map(|r| format!("{r:.2}"))
                .collect::<Vec<_>>()
                .join(";"),
            wall_seconds: wall.as_secs_f64(),
            commit: commit.to_string(),
            cpu: machine.cpu_model.clone(),
            cpu_family_model: machine.cpu_family_model.clone(),
            logical_cpus: machine.logical_cpus,
        });
        write_atomically(&self.dir.join("imagination_states.csv"), &self.rows)?;
        write_atomically(&self.dir.join("imagination_seeds.csv"), &self.seeds)
    }
}

fn write_atomically<T: serde::Serialize>(path: &Path, rows: &[T]) -> Result<()> {
    let tmp = path.with_extension("csv.tmp");
    super::imagination::write_csv(&tmp, rows)?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scale::Scale;
    use proto::{Builtin, InferencePrecision};

    fn config(seed: u64) -> ImaginationConfig {
        ImaginationConfig {
            task: Builtin::Cartpole,
            scale: Scale::Small,
            plan_scale: Scale::Paper,
            method: "cem+deen".into(),
            train_episodes: 2,
            mpc_steps: 5,
            inference_precision: InferencePrecision::Auto,
            seed,
            states: 2,
        }
    }

    fn result(seed: u64) -> ImaginationResult {
        let states = (0..2)
            .flat_map(|state| {
                ["none", "dae", "deen"].map(|regularizer| StateRow {
                    seed,
                    state,
                    regularizer: regularizer.into(),
                    alpha: 0.05,
                    steps: 30,
                    imagined_return: 1.0 + seed as f32,
                    real_return: 0.5,
                    gap: 0.5 + seed as f32,
                })
            })
            .collect();
        ImaginationResult {
            task: Builtin::Cartpole,
            train_episodes: 2,
            mpc_steps: 5,
            training_returns: vec![-3.0, 42.5],
            traces: Vec::new(),
            states,
        }
    }

    #[test]
    fn seeds_accumulate_across_openings_and_other_settings_are_refused() {
        let dir =
            std::env::temp_dir().join(format!("ebmpc-imagination-folder-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let settings = Settings::of(&config(0));
        let mut folder = Folder::open(&dir, &settings).unwrap();
        assert!(folder.finished().is_empty());
        assert_eq!(folder.seconds_per_seed(), None);
        folder
            .record(0, &result(0), Duration::from_secs(60), "abc")
            .unwrap();
        assert!(
            folder
                .record(0, &result(0), Duration::from_secs(60), "abc")
                .is_err()
        );

        // A later sitting sees seed 0 and adds seed 1.
        let mut again = Folder::open(&dir, &Settings::of(&config(1))).unwrap();
        assert_eq!(again.finished(), BTreeSet::from([0]));
        assert_eq!(again.rows(), folder.rows());
        again
            .record(1, &result(1), Duration::from_secs(120), "abc")
            .unwrap();
        let third = Folder::open(&dir, &settings).unwrap();
        assert_eq!(third.finished(), BTreeSet::from([0, 1]));
        assert_eq!(third.rows().len(), 12);
        assert_eq!(third.seconds_per_seed(), Some(Duration::from_secs(90)));
        assert_eq!(third.seeds[0].training_returns, "-3.00;42.50");

        // Another comparison in the same folder is refused, and the folder is left as it was.
        let mut other = config(0);
        other.mpc_steps = 50;
        let err = Folder::open(&dir, &Settings::of(&other)).err().unwrap();
        assert!(format!("{err:#}").contains("another comparison"), "{err:#}");
        assert_eq!(Folder::open(&dir, &settings).unwrap().rows().len(), 12);
        // So is a folder of rows whose settings nobody recorded (made by an older command).
        std::fs::remove_file(dir.join("imagination.json")).unwrap();
        let err = Folder::open(&dir, &settings).err().unwrap();
        assert!(format!("{err:#}").contains("not recorded"), "{err:#}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
