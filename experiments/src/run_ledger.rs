//! Every run of an experiment folder, one row each: the returns its planned episodes earned, in
//! the order recorded, and where it ran (CPUs, kernel paths, binaries, dates, planning time per
//! step), read from the run files the launcher keeps under `runs/` ([`RunId`]'s paths) and the
//! records of [`provenance`].
//!
//! The results pages print these tables instead of writing each run's numbers and sittings out
//! by hand: a folder committed run by run across days and machines then says itself which runs
//! it holds, how far each has got, and on what it ran.

use crate::launcher::RunId;
use crate::manifest::{Manifest, ManifestError};
use crate::provenance::{self, KeptSittings, Sitting};
use crate::results::{self, EpisodeRow, ResultsError, grouped};
use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// An experiment folder whose runs cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum LedgerError {
    #[error("{0} has no experiment.json: not an experiment folder")]
    NotAnExperiment(PathBuf),
    #[error(transparent)]
    Manifest(#[from] ManifestError),
    #[error(transparent)]
    Results(#[from] ResultsError),
    #[error("{path}: {source}")]
    Record {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// How far a run has got.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RunState {
    /// Its episodes are complete (`runs/<stem>.csv`).
    Finished,
    /// Some episodes are recorded and the run continues in a later sitting
    /// (`runs/<stem>.csv.partial`).
    UnderWay,
}

/// What the folder holds of one (method, seed) run.
#[derive(Clone, Debug, PartialEq)]
pub struct LedgerRun {
    pub run: RunId,
    pub state: RunState,
    /// Its recorded episodes, in the order recorded.
    pub episodes: Vec<EpisodeRow>,
    /// The sittings its record or sittings file names, oldest first.
    pub kept: KeptSittings,
}

/// Every run the folder's manifest asks for that has recorded at least one episode: methods in
/// the manifest's order, seeds ascending.
pub fn read_folder(dir: &Path) -> Result<(Manifest, Vec<LedgerRun>), LedgerError> {
    let manifest =
        Manifest::load(dir)?.ok_or_else(|| LedgerError::NotAnExperiment(dir.to_path_buf()))?;
    let mut runs = Vec::new();
    for method in &manifest.methods {
        for &seed in &manifest.seeds {
            let run = RunId {
                method: method.clone(),
                seed,
            };
            let (state, csv) = if run.csv(dir).exists() {
                (RunState::Finished, run.csv(dir))
            } else if run.partial_csv(dir).exists() {
                (RunState::UnderWay, run.partial_csv(dir))
            } else {
                continue;
            };
            let episodes = results::read_run_csv(&csv, manifest.task.name(), method, seed)?;
            if episodes.is_empty() {
                continue;
            }
            let file = run.sittings_file(dir);
            let kept = provenance::read_sittings(&file)
                .map_err(|source| LedgerError::Record { path: file, source })?;
            runs.push(LedgerRun {
                run,
                state,
                episodes,
                kept,
            });
        }
    }
    Ok((manifest, runs))
}

fn episodes_cell(run: &LedgerRun, episodes_per_run: u32) -> String {
    let recorded = run.episodes.len();
    match run.state {
        RunState::Finished => format!("{recorded}"),
        RunState::UnderWay => format!("{recorded} of {episodes_per_run}, under way"),
    }
}

/// The returns table: per run, its recorded episodes and the returns of its planned ones (the
/// random exploration's are the same for every method of a seed); a finished run's last in
/// bold.
pub fn returns_markdown(manifest: &Manifest, runs: &[LedgerRun]) -> String {
    let mut out = String::from(
        "| run | episodes | planned episodes' returns, in the order recorded |\n|---|---|---|\n",
    );
    for run in runs {
        let planned: Vec<&EpisodeRow> = run
            .episodes
            .iter()
            .filter(|e| e.planned_steps > 0)
            .collect();
        let cell = planned
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let value = grouped(e.episode_return);
                let last = i + 1 == planned.len();
                if last && run.state == RunState::Finished {
                    format!("**{value}**")
                } else {
                    value
                }
            })
            .collect::<Vec<_>>()
            .join(", ");
        let _ = writeln!(
            out,
            "| `{}` seed {} | {} | {} |",
            run.run.method,
            run.run.seed,
            episodes_cell(run, manifest.episodes),
            if cell.is_empty() { "—".into() } else { cell }
        );
    }
    out
}

/// The distinct values of `items`, in first-seen order, joined.
fn distinct<I: IntoIterator<Item = String>>(items: I) -> String {
    let mut seen = BTreeSet::new();
    let mut ordered = Vec::new();
    for item in items {
        if seen.insert(item.clone()) {
            ordered.push(item);
        }
    }
    if ordered.is_empty() {
        "—".into()
    } else {
        ordered.join("; ")
    }
}

/// Which episodes the listed sittings account for.
fn sittings_cell(run: &LedgerRun) -> String {
    if run.kept.sittings.is_empty() {
        return "none recorded".into();
    }
    if !run.kept.complete {
        return "the last only".into();
    }
    let listed: usize = run.kept.sittings.iter().map(|s| s.episodes.len()).sum();
    let n = run.kept.sittings.len();
    let noun = if n == 1 { "sitting" } else { "sittings" };
    if listed == run.episodes.len() {
        format!("{n} {noun}, every episode")
    } else {
        format!("{n} {noun}, {listed} of {} episodes", run.episodes.len())
    }
}

/// The milliseconds per planned step of a run's planned episodes: least, median and most.
fn planning_cell(run: &LedgerRun) -> String {
    let times: Vec<f64> = run
        .episodes
        .iter()
        .filter(|e| e.planned_steps > 0)
        .map(|e| e.plan_ms_per_step)
        .collect();
    let least = times.iter().copied().fold(f64::INFINITY, f64::min);
    let most = times.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    match results::median(times) {
        Some(median) => format!(
            "{} / {} / {}",
            grouped(least),
            grouped(median),
            grouped(most)
        ),
        None => "—".into(),
    }
}

/// The dates (UTC) of the listed sittings: the first one's start to the last one's end.
fn dates_cell(sittings: &[Sitting]) -> String {
    let day = |stamp: &str| stamp.get(..10).unwrap_or(stamp).to_string();
    let first = sittings.iter().map(|s| day(&s.started)).min();
    let last = sittings.iter().map(|s| day(&s.ended)).max();
    match (first, last) {
        (Some(a), Some(b)) if a == b => a,
        (Some(a), Some(b)) => format!("{a} to {b}"),
        _ => "—".into(),
    }
}

/// The provenance table: per run, the sittings its record lists, with their CPUs (model name,
/// family/model), the kernel paths the daemon chose for its networks, the binaries' commits and
/// the dates, beside the planning time per step over all its planned episodes.
pub fn provenance_markdown(runs: &[LedgerRun]) -> String {
    let mut out = String::from(
        "| run | sittings listed | CPU (family/model) | kernels | binaries | dates (UTC) \
         | ms per planned step (least / median / most) |\n|---|---|---|---|---|---|---|\n",
    );
    for run in runs {
        let cpus = distinct(
            run.kept
                .sittings
                .iter()
                .map(|s| format!("{} ({})", s.machine.cpu_model, s.machine.cpu_family_model)),
        );
        let kernels = distinct(run.kept.sittings.iter().filter_map(|s| {
            let k = s.kernels.as_ref()?;
            let paths: BTreeSet<&str> = [&k.dynamics, &k.energy, &k.reward]
                .into_iter()
                .filter_map(|p| p.as_deref())
                .collect();
            Some(paths.into_iter().collect::<Vec<_>>().join(", "))
        }));
        let binaries = distinct(run.kept.sittings.iter().map(|s| {
            let commit = &s.binaries_commit;
            format!("`{}`", commit.get(..7).unwrap_or(commit))
        }));
        let _ = writeln!(
            out,
            "| `{}` seed {} | {} | {} | {} | {} | {} | {} |",
            run.run.method,
            run.run.seed,
            sittings_cell(run),
            cpus,
            kernels,
            binaries,
            dates_cell(&run.kept.sittings),
            planning_cell(run)
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::provenance::{Load, Machine, RunKernels, RunRecord};
    use crate::scale::Scale;
    use proto::Builtin;

    const RUN_HEADER: &str =
        "episode,return,steps,wall_seconds,planned_steps,plan_ms_mean,train_seconds";

    fn machine(family_model: &str) -> Machine {
        Machine {
            hostname: "host".into(),
            cpu_model: "Some CPU".into(),
            cpu_family_model: family_model.into(),
            logical_cpus: 2,
            cpu_path: "avx2-f32 scalar-f32".into(),
        }
    }

    fn sitting(family_model: &str, commit: &str, day: &str, episodes: Vec<u32>) -> Sitting {
        let load = Load {
            load_average_1m: 1.0,
            sched_idle: true,
        };
        Sitting {
            machine: machine(family_model),
            binaries_commit: commit.into(),
            kernels: Some(RunKernels {
                precision: "auto".into(),
                dynamics: Some("avx2-f32".into()),
                energy: Some("avx512-bf16".into()),
                reward: None,
            }),
            started: format!("{day}T10:00:00Z"),
            ended: format!("{day}T11:00:00Z"),
            load_at_start: load.clone(),
            load_at_end: load,
            episodes,
        }
    }

    /// A folder with one finished run whose record keeps every sitting, one finished run with
    /// an older record, one under way and one asked for but never started.
    fn folder() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        let manifest = Manifest::new(
            Builtin::Cartpole,
            Scale::Small,
            3,
            vec!["cem+deen".into(), "cem".into()],
            vec![0, 1],
            None,
        )
        .unwrap();
        manifest.save(dir.path()).unwrap();
        std::fs::create_dir(dir.path().join("runs")).unwrap();
        let run = |method: &str, seed| RunId {
            method: method.into(),
            seed,
        };
        // cem+deen seed 0, finished, a resumed run whose CSV skips episode 2.
        std::fs::write(
            run("cem+deen", 0).csv(dir.path()),
            format!(
                "{RUN_HEADER}\n0,-12.4,10,1,0,0,0\n1,1234.5,10,1,10,40,1\n3,-7.5,10,1,10,60,1\n"
            ),
        )
        .unwrap();
        RunRecord {
            task: "cartpole".into(),
            method: "cem+deen".into(),
            seed: 0,
            scale: "small".into(),
            episodes: 3,
            steps: 30,
            spec: None,
            sittings: vec![
                sitting("6/167", "aaaaaaa1111", "2026-11-27", vec![0, 1]),
                sitting("25/17", "bbbbbbb2222", "2026-11-29", vec![3]),
            ],
            finished: "2026-11-29T11:00:00Z".into(),
            episode_wall_seconds: 3.0,
        }
        .save(&run("cem+deen", 0).record_json(dir.path()))
        .unwrap();
        // cem seed 0, finished, with a record from before records kept their sittings.
        std::fs::write(
            run("cem", 0).csv(dir.path()),
            format!("{RUN_HEADER}\n0,-12.4,10,1,0,0,0\n1,5,10,1,10,20,1\n2,6,10,1,10,30,1\n"),
        )
        .unwrap();
        let older = serde_json::json!({
            "task": "cartpole", "method": "cem", "seed": 0, "scale": "small",
            "episodes": 3, "steps": 30,
            "binaries_commit": "ccccccc3333",
            "machine": machine("25/1"),
            "kernels": null,
            "load_at_start": {"load_average_1m": 0.5, "sched_idle": true},
            "load_at_end": {"load_average_1m": 0.5, "sched_idle": true},
            "started": "2026-11-28T01:00:00Z", "finished": "2026-11-28T02:00:00Z",
            "episode_wall_seconds": 3.0
        });
        std::fs::write(
            run("cem", 0).record_json(dir.path()),
            serde_json::to_string(&older).unwrap(),
        )
        .unwrap();
        // cem seed 1, under way: two of three episodes, one sitting listed.
        std::fs::write(
            run("cem", 1).partial_csv(dir.path()),
            format!("{RUN_HEADER}\n0,-3,10,1,0,0,0\n1,999.6,10,1,10,25,1\n"),
        )
        .unwrap();
        provenance::append_sitting(
            &run("cem", 1).sittings_json(dir.path()),
            sitting("25/17", "ddddddd4444", "2026-12-03", vec![0]),
        )
        .unwrap();
        dir
    }

    #[test]
    fn every_started_run_in_manifest_order() {
        let dir = folder();
        let (_, runs) = read_folder(dir.path()).unwrap();
        let names: Vec<(String, u64, RunState)> = runs
            .iter()
            .map(|r| (r.run.method.clone(), r.run.seed, r.state))
            .collect();
        assert_eq!(
            names,
            vec![
                ("cem+deen".into(), 0, RunState::Finished),
                ("cem".into(), 0, RunState::Finished),
                ("cem".into(), 1, RunState::UnderWay),
            ]
        );
        assert!(runs[0].kept.complete);
        assert!(
            !runs[1].kept.complete,
            "an older record lists its last sitting only"
        );
        assert_eq!(runs[1].kept.sittings[0].binaries_commit, "ccccccc3333");
        assert_eq!(runs[2].kept.sittings.len(), 1);
    }

    #[test]
    fn returns_table_lists_planned_episodes_in_order() {
        let dir = folder();
        let (manifest, runs) = read_folder(dir.path()).unwrap();
        let table = returns_markdown(&manifest, &runs);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 2 + 3, "{table}");
        // The random episode (planned_steps 0) is left out; the finished run's last is bold.
        assert_eq!(lines[2], "| `cem+deen` seed 0 | 3 | 1,235, **−8** |");
        assert_eq!(lines[3], "| `cem` seed 0 | 3 | 5, **6** |");
        assert_eq!(lines[4], "| `cem` seed 1 | 2 of 3, under way | 1,000 |");
    }

    #[test]
    fn provenance_table_names_where_each_run_ran() {
        let dir = folder();
        let (_, runs) = read_folder(dir.path()).unwrap();
        let table = provenance_markdown(&runs);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(
            lines[2],
            "| `cem+deen` seed 0 | 2 sittings, every episode | Some CPU (6/167); Some CPU (25/17) \
             | avx2-f32, avx512-bf16 | `aaaaaaa`; `bbbbbbb` | 2026-11-27 to 2026-11-29 \
             | 40 / 50 / 60 |"
        );
        assert_eq!(
            lines[3],
            "| `cem` seed 0 | the last only | Some CPU (25/1) | — | `ccccccc` | 2026-11-28 \
             | 20 / 25 / 30 |"
        );
        assert_eq!(
            lines[4],
            "| `cem` seed 1 | 1 sitting, 1 of 2 episodes | Some CPU (25/17) \
             | avx2-f32, avx512-bf16 | `ddddddd` | 2026-12-03 | 25 / 25 / 25 |"
        );
    }

    #[test]
    fn a_folder_without_manifest_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let err = read_folder(dir.path()).unwrap_err();
        assert!(matches!(err, LedgerError::NotAnExperiment(_)), "{err}");
    }
}
