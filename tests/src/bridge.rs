//! sim-bridge as the tests drive it: started against a planner with its episodes written to a
//! CSV file (`--out`), which is read back into typed rows and checked for what every bridge
//! run must show, before a test checks what is particular to it.

use crate::{Guarded, Planner, binaries, free_port};
use anyhow::{Context, Result, bail, ensure};
use std::path::Path;
use std::process::Command;
use std::time::Duration;

/// The columns of the bridge's episodes CSV, in order: a file format others read (learning
/// curves are joined on `episode`), so the tests name it rather than take it from sim-bridge.
pub const EPISODE_COLUMNS: [&str; 7] = [
    "episode",
    "return",
    "steps",
    "wall_seconds",
    "planned_steps",
    "plan_ms_mean",
    "train_seconds",
];

/// One row of the episodes CSV.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeRow {
    pub episode: u32,
    pub ret: f32,
    pub steps: u32,
    pub wall_seconds: f64,
    pub planned_steps: u32,
    pub plan_ms_mean: f64,
    pub train_seconds: f64,
}

/// Starts `sim-bridge run` with `args` against `endpoint`, logging to a file in `dir`.
pub fn spawn_bridge(dir: &Path, endpoint: &str, args: &[&str]) -> Result<Guarded> {
    let mut cmd = Command::new(&binaries().bridge);
    cmd.arg("run").args(args).args(["--connect", endpoint]);
    cmd.env("RUST_LOG", "info,zenoh=warn");
    let log = dir.join(format!("bridge-{}.log", free_port()));
    Guarded::spawn("sim-bridge", cmd, log)
}

/// What a finished bridge run left behind.
#[derive(Debug)]
pub struct BridgeRun {
    /// Everything the bridge logged.
    pub log: String,
    /// Its episodes, as [`read_episodes`] checked them.
    pub episodes: Vec<EpisodeRow>,
}

/// Runs `sim-bridge run` with `args` and `--episodes episodes` against `planner` to completion
/// (killed after `timeout`).
///
/// # Errors
/// Unless the bridge exits successfully (the error then holds its log and the planner's) and
/// its CSV passes [`read_episodes`] with one row per episode.
pub fn run_episodes(
    dir: &Path,
    planner: &Planner,
    args: &[&str],
    episodes: u32,
    timeout: Duration,
) -> Result<BridgeRun> {
    let csv = dir.join(format!("episodes-{}.csv", free_port()));
    let (episodes_arg, csv_arg) = (episodes.to_string(), csv.to_str().context("csv path")?);
    let mut all = args.to_vec();
    all.extend(["--episodes", &episodes_arg, "--out", csv_arg]);
    let mut bridge = spawn_bridge(dir, &planner.endpoint, &all)?;
    let status = bridge.wait(timeout)?;
    let log = bridge.log();
    if !status.success() {
        bail!(
            "sim-bridge failed: {status}\n{log}\nplanner:\n{}",
            planner.process.log()
        );
    }
    let episodes = read_episodes(&csv, episodes as usize)
        .with_context(|| format!("episodes of this bridge run:\n{log}"))?;
    Ok(BridgeRun { log, episodes })
}

/// Reads the bridge's episodes CSV at `path`.
///
/// # Errors
/// Unless the header is exactly [`EPISODE_COLUMNS`], there are `expected` rows (each
/// finished episode is written as it ends, so a missing row is a lost episode), every value
/// parses, episode numbers increase, and the values are possible: a finite return, no more
/// planned steps than steps, and finite, non-negative times (zero planning time when nothing
/// was planned).
pub fn read_episodes(path: &Path, expected: usize) -> Result<Vec<EpisodeRow>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("read {}", path.display()))?;
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let header = lines.next().context("empty episodes csv")?;
    ensure!(
        header == EPISODE_COLUMNS.join(","),
        "episodes csv header `{header}`, expected `{}`",
        EPISODE_COLUMNS.join(",")
    );
    let rows = lines.map(parse_row).collect::<Result<Vec<_>>>()?;
    ensure!(
        rows.len() == expected,
        "{} episodes in the csv, expected {expected}:\n{text}",
        rows.len()
    );
    for pair in rows.windows(2) {
        ensure!(
            pair[0].episode < pair[1].episode,
            "episode numbers do not increase: {pair:?}"
        );
    }
    for row in &rows {
        let times = [row.wall_seconds, row.plan_ms_mean, row.train_seconds];
        ensure!(
            row.ret.is_finite()
                && row.planned_steps <= row.steps
                && times.iter().all(|t| t.is_finite() && *t >= 0.0)
                && (row.planned_steps > 0 || row.plan_ms_mean == 0.0),
            "impossible episode row: {row:?}"
        );
    }
    Ok(rows)
}

fn parse_row(line: &str) -> Result<EpisodeRow> {
    let cells: Vec<&str> = line.split(',').collect();
    ensure!(
        cells.len() == EPISODE_COLUMNS.len(),
        "episodes csv row `{line}` has {} cells",
        cells.len()
    );
    let cell = |i: usize| cells[i].trim();
    let bad = |i: usize| format!("column {} of `{line}`", EPISODE_COLUMNS[i]);
    Ok(EpisodeRow {
        episode: cell(0).parse().with_context(|| bad(0))?,
        ret: cell(1).parse().with_context(|| bad(1))?,
        steps: cell(2).parse().with_context(|| bad(2))?,
        wall_seconds: cell(3).parse().with_context(|| bad(3))?,
        planned_steps: cell(4).parse().with_context(|| bad(4))?,
        plan_ms_mean: cell(5).parse().with_context(|| bad(5))?,
        train_seconds: cell(6).parse().with_context(|| bad(6))?,
    })
}

/// Checks a run of one random exploration episode followed by planned ones: the first has no
/// planned step, every step of the others is planned, and the planner timed those plans.
///
/// # Errors
/// Naming the first row that is otherwise.
pub fn check_random_then_planned(rows: &[EpisodeRow]) -> Result<()> {
    let (first, planned) = rows.split_first().context("no episodes")?;
    ensure!(
        first.planned_steps == 0,
        "the exploration episode is random: {first:?}"
    );
    for row in planned {
        ensure!(
            row.planned_steps == row.steps,
            "every action planned: {row:?}"
        );
        ensure!(
            row.plan_ms_mean > 0.0,
            "the planner timed its plans: {row:?}"
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TempDir;

    fn write(dir: &TempDir, text: &str) -> std::path::PathBuf {
        let path = dir.path().join("episodes.csv");
        std::fs::write(&path, text).unwrap();
        path
    }

    /// A file as sim-bridge writes it reads back typed; each way a file can be wrong is an
    /// error naming it.
    #[test]
    fn reads_the_bridge_csv_and_refuses_what_is_wrong() {
        let dir = TempDir::new("episodes-csv");
        let header = EPISODE_COLUMNS.join(",");
        let good = format!(
            "{header}\n0,12.5,200,1.235,0,0.000,0.000\n1,-3.25,200,1.235,200,50.000,2.500\n"
        );
        let rows = read_episodes(&write(&dir, &good), 2).unwrap();
        assert_eq!(
            rows[1],
            EpisodeRow {
                episode: 1,
                ret: -3.25,
                steps: 200,
                wall_seconds: 1.235,
                planned_steps: 200,
                plan_ms_mean: 50.0,
                train_seconds: 2.5,
            }
        );
        check_random_then_planned(&rows).unwrap();

        for (text, expected, why) in [
            (good.clone(), 3, "expected 3"),
            (good.replacen("plan_ms_mean", "plan_ms", 1), 2, "header"),
            (good.replace(",2.500", ""), 2, "has 6 cells"),
            (good.replace("-3.25", "NaN"), 2, "impossible"),
            (good.replace("-3.25", "x"), 2, "column return"),
            (good.replace(",200,50.000", ",201,50.000"), 2, "impossible"),
            (
                good.replace("0,0.000,0.000", "0,1.000,0.000"),
                2,
                "impossible",
            ),
            (good.replace("\n1,", "\n0,"), 2, "do not increase"),
        ] {
            let err = read_episodes(&write(&dir, &text), expected).unwrap_err();
            assert!(format!("{err:#}").contains(why), "{why}: {err:#}");
        }

        let mut all_random = rows.clone();
        all_random[1].planned_steps = 199;
        assert!(check_random_then_planned(&all_random).is_err());
        let mut untimed = rows.clone();
        untimed[1].plan_ms_mean = 0.0;
        assert!(check_random_then_planned(&untimed).is_err());
        let mut planned_first = rows;
        planned_first[0].planned_steps = 1;
        assert!(check_random_then_planned(&planned_first).is_err());
    }
}
