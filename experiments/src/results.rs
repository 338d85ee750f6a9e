//! The results of an experiment: one row per (method, seed, episode).
//!
//! Each (method, seed) run's bridge writes its own file under `runs/` (sim-bridge's episode CSV,
//! flushed after every episode); the experiment's `episodes.csv` is the union of the runs with
//! the method and seed prepended, rebuilt from the run files whenever a run finishes. A run file
//! is renamed from `*.csv.partial` to `*.csv` only when its bridge exits successfully, so a
//! `.csv` file is a complete run: that is what resuming relies on.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The columns of `episodes.csv`, in order.
pub const HEADER: &str = "task,method,seed,episode,return,steps,planned_steps,plan_ms_per_step,train_seconds,wall_seconds";

/// One episode of one run.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeRow {
    pub task: String,
    pub method: String,
    pub seed: u64,
    /// The run's episode number, from 0.
    pub episode: u32,
    /// Sum of the simulator's rewards.
    pub episode_return: f64,
    pub steps: u32,
    /// Steps whose action was planned (the others were random exploration).
    pub planned_steps: u32,
    /// Mean planning time per planned step, as the planner reported it (0 without planning).
    pub plan_ms_per_step: f64,
    /// Retraining seconds the planner reported before this episode (0 for the first).
    pub train_seconds: f64,
    /// Wall time of the episode, including waits for the planner.
    pub wall_seconds: f64,
}

/// A results file that cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: missing column `{column}`")]
    MissingColumn { path: PathBuf, column: String },
    #[error("{path} line {line}: {reason}")]
    BadRow {
        path: PathBuf,
        line: usize,
        reason: String,
    },
}

/// A parsed CSV: header names to column index, and the data rows.
struct Table {
    columns: BTreeMap<String, usize>,
    rows: Vec<(usize, Vec<String>)>,
}

impl Table {
    fn read(path: &Path) -> Result<Self, ResultsError> {
        let text = std::fs::read_to_string(path).map_err(|source| ResultsError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self::parse(&text))
    }

    fn parse(text: &str) -> Self {
        let mut lines = text.lines().enumerate();
        let columns = lines
            .next()
            .map(|(_, h)| {
                h.split(',')
                    .enumerate()
                    .map(|(i, c)| (c.trim().to_string(), i))
                    .collect()
            })
            .unwrap_or_default();
        let rows = lines
            .filter(|(_, l)| !l.trim().is_empty())
            .map(|(i, l)| (i + 1, l.split(',').map(|c| c.trim().to_string()).collect()))
            .collect();
        Self { columns, rows }
    }

    fn index(&self, path: &Path, column: &str) -> Result<usize, ResultsError> {
        self.columns
            .get(column)
            .copied()
            .ok_or_else(|| ResultsError::MissingColumn {
                path: path.to_path_buf(),
                column: column.to_string(),
            })
    }
}

/// Reads `column` of a row as a `T`, with the file and line in the error.
fn field<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    row: &[String],
    index: usize,
    column: &str,
) -> Result<T, ResultsError> {
    let text = row.get(index).ok_or_else(|| ResultsError::BadRow {
        path: path.to_path_buf(),
        line,
        reason: format!("no `{column}` value"),
    })?;
    text.parse().map_err(|_| ResultsError::BadRow {
        path: path.to_path_buf(),
        line,
        reason: format!("`{column}` is `{text}`"),
    })
}

/// Reads a bridge's episode CSV (`sim_bridge::csv::HEADER`) as the rows of one run. Rows from
/// a bridge that predates the planning and training columns read those as 0.
pub fn read_run_csv(
    path: &Path,
    task: &str,
    method: &str,
    seed: u64,
) -> Result<Vec<EpisodeRow>, ResultsError> {
    let table = Table::read(path)?;
    let required = ["episode", "return", "steps", "wall_seconds"].map(|c| table.index(path, c));
    let [episode, ret, steps, wall] = required;
    let (episode, ret, steps, wall) = (episode?, ret?, steps?, wall?);
    let optional = |c: &str| table.columns.get(c).copied();
    let (planned, plan_ms, train) = (
        optional("planned_steps"),
        optional("plan_ms_mean"),
        optional("train_seconds"),
    );
    let mut out = Vec::with_capacity(table.rows.len());
    for (line, row) in &table.rows {
        let get_f = |i: Option<usize>, c: &str| match i {
            Some(i) => field::<f64>(path, *line, row, i, c),
            None => Ok(0.0),
        };
        out.push(EpisodeRow {
            task: task.to_string(),
            method: method.to_string(),
            seed,
            episode: field(path, *line, row, episode, "episode")?,
            episode_return: field(path, *line, row, ret, "return")?,
            steps: field(path, *line, row, steps, "steps")?,
            planned_steps: match planned {
                Some(i) => field(path, *line, row, i, "planned_steps")?,
                None => 0,
            },
            plan_ms_per_step: get_f(plan_ms, "plan_ms_mean")?,
            train_seconds: get_f(train, "train_seconds")?,
            wall_seconds: field(path, *line, row, wall, "wall_seconds")?,
        });
    }
    Ok(out)
}

/// The number of finished episodes in a run file (0 if it does not exist or cannot be read):
/// the progress display polls this while a bridge runs.
pub fn count_rows(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .map(|t| t.lines().skip(1).filter(|l| !l.trim().is_empty()).count())
        .unwrap_or(0)
}

/// The episodes a run file records (none if it does not exist or cannot be read), with its
/// own columns only (task, method and seed left empty).
pub fn recorded(path: &Path) -> Vec<EpisodeRow> {
    read_run_csv(path, "", "", 0).unwrap_or_default()
}

/// Formats rows as `episodes.csv` (header included).
pub fn to_csv(rows: &[EpisodeRow]) -> String {
    let mut out = String::with_capacity(64 * (rows.len() + 1));
    out.push_str(HEADER);
    out.push('\n');
    for r in rows {
        // Writing to a String cannot fail.
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{:.3},{:.3},{:.3}",
            r.task,
            r.method,
            r.seed,
            r.episode,
            r.episode_return,
            r.steps,
            r.planned_steps,
            r.plan_ms_per_step,
            r.train_seconds,
            r.wall_seconds
        );
    }
    out
}

/// Reads an `episodes.csv`.
pub fn read_episodes(path: &Path) -> Result<Vec<EpisodeRow>, ResultsError> {
    let table = Table::read(path)?;
    let mut idx = BTreeMap::new();
    for column in HEADER.split(',') {
        idx.insert(column, table.index(path, column)?);
    }
    let mut out = Vec::with_capacity(table.rows.len());
    for (line, row) in &table.rows {
        let get = |c: &str| {
            row.get(idx[c])
                .cloned()
                .ok_or_else(|| ResultsError::BadRow {
                    path: path.to_path_buf(),
                    line: *line,
                    reason: format!("no `{c}` value"),
                })
        };
        let num = |c: &str| field::<f64>(path, *line, row, idx[c], c);
        out.push(EpisodeRow {
            task: get("task")?,
            method: get("method")?,
            seed: field(path, *line, row, idx["seed"], "seed")?,
            episode: field(path, *line, row, idx["episode"], "episode")?,
            episode_return: num("return")?,
            steps: field(path, *line, row, idx["steps"], "steps")?,
            planned_steps: field(path, *line, row, idx["planned_steps"], "planned_steps")?,
            plan_ms_per_step: num("plan_ms_per_step")?,
            train_seconds: num("train_seconds")?,
            wall_seconds: num("wall_seconds")?,
        });
    }
    Ok(out)
}

/// Writes `episodes.csv` atomically (temporary file, then rename), so a reader never sees half
/// a file.
pub fn write_episodes(path: &Path, rows: &[EpisodeRow]) -> Result<(), ResultsError> {
    let tmp = path.with_extension("csv.tmp");
    let io = |source| ResultsError::Io {
        path: path.to_path_buf(),
        source,
    };
    std::fs::write(&tmp, to_csv(rows)).map_err(io)?;
    std::fs::rename(&tmp, path).map_err(io)
}

/// The mean of `values` and their sample standard deviation (`n − 1` in the denominator; 0 for
/// a single value; the mean is NaN for none).
pub fn mean_and_std(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let variance = if values.len() > 1 {
        values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    (mean, variance.sqrt())
}

/// The median of `values` (the mean of the middle two for an even count; `None` for none).
pub fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(values[n / 2]),
        _ => Some((values[n / 2 - 1] + values[n / 2]) / 2.0),
    }
}

/// Each method's runs, methods in first-seen order, a method's runs by seed, each run's rows
/// in episode order: a row's index in its run is the run's *recorded* episode count, the
/// episode number that curves, tables and comparisons use. The two differ only in a resumed
/// run, whose daemon numbers episodes by the data it holds, including an episode cut short by
/// the interruption (see the launcher), so its CSV's episode numbers skip one; counting
/// recorded episodes keeps every seed at every point.
pub fn runs_by_method(rows: &[EpisodeRow]) -> Vec<(&str, BTreeMap<u64, Vec<&EpisodeRow>>)> {
    let mut methods: Vec<(&str, BTreeMap<u64, Vec<&EpisodeRow>>)> = Vec::new();
    for r in rows {
        let index = match methods.iter().position(|(m, _)| *m == r.method) {
            Some(i) => i,
            None => {
                methods.push((&r.method, BTreeMap::new()));
                methods.len() - 1
            }
        };
        methods[index].1.entry(r.seed).or_default().push(r);
    }
    for (_, runs) in &mut methods {
        for run in runs.values_mut() {
            run.sort_by_key(|r| r.episode);
        }
    }
    methods
}

/// Mean and sample standard deviation (over seeds, `n − 1` in the denominator; 0 for a single
/// seed) of the return per method and recorded episode (see [`runs_by_method`]): the numbers
/// behind a learning curve and a results table. Methods are in first-seen order.
pub fn curves(rows: &[EpisodeRow]) -> Vec<Curve> {
    runs_by_method(rows)
        .into_iter()
        .map(|(method, runs)| {
            let mut by: BTreeMap<u32, Vec<f64>> = BTreeMap::new();
            for run in runs.values() {
                for (k, r) in run.iter().enumerate() {
                    by.entry(k as u32).or_default().push(r.episode_return);
                }
            }
            let points = by
                .into_iter()
                .map(|(episode, values)| {
                    let (mean, std) = mean_and_std(&values);
                    CurvePoint {
                        episode,
                        mean,
                        std,
                        seeds: values.len(),
                    }
                })
                .collect();
            Curve {
                method: method.to_string(),
                points,
            }
        })
        .collect()
}

/// A number as the results pages print it: rounded, thousands separated, with a minus sign.
pub fn grouped(value: f64) -> String {
    let rounded = value.round();
    let digits = format!("{:.0}", rounded.abs());
    let mut grouped = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            grouped.push(',');
        }
        grouped.push(c);
    }
    if rounded < 0.0 {
        format!("−{grouped}")
    } else {
        grouped
    }
}

/// A Markdown table of the return at `episodes` (every episode when empty), mean ± sample std
/// over seeds per method, with the seeds behind each method, its mean planning time per planned
/// step and its mean wall time per run: what the results tables of docs/results.md print.
pub fn markdown_table(rows: &[EpisodeRow], episodes: &[u32]) -> String {
    let curves = curves(rows);
    let episodes: Vec<u32> = if episodes.is_empty() {
        let mut all: Vec<u32> = curves
            .iter()
            .flat_map(|c| c.points.iter().map(|p| p.episode))
            .collect();
        all.sort_unstable();
        all.dedup();
        all
    } else {
        episodes.to_vec()
    };
    let mut out = String::from("| method | seeds |");
    for e in &episodes {
        let _ = write!(out, " {e} |");
    }
    out.push_str(" ms per planned step | minutes per run |\n|---|---|");
    out.push_str(&"---|".repeat(episodes.len() + 2));
    out.push('\n');
    for curve in &curves {
        let mine: Vec<&EpisodeRow> = rows.iter().filter(|r| r.method == curve.method).collect();
        let mut seeds: Vec<u64> = mine.iter().map(|r| r.seed).collect();
        seeds.sort_unstable();
        seeds.dedup();
        let _ = write!(out, "| `{}` | {} |", curve.method, seeds.len());
        for e in &episodes {
            match curve.points.iter().find(|p| p.episode == *e) {
                Some(p) if p.seeds == seeds.len() => {
                    let _ = write!(out, " {} ± {} |", grouped(p.mean), grouped(p.std));
                }
                Some(p) => {
                    let _ = write!(
                        out,
                        " {} ± {} ({} seeds) |",
                        grouped(p.mean),
                        grouped(p.std),
                        p.seeds
                    );
                }
                None => out.push_str(" — |"),
            }
        }
        let (planned_ms, planned_steps) = mine.iter().fold((0.0, 0u64), |(ms, n), r| {
            (
                ms + r.plan_ms_per_step * f64::from(r.planned_steps),
                n + u64::from(r.planned_steps),
            )
        });
        let wall: f64 = mine.iter().map(|r| r.wall_seconds).sum();
        let _ = writeln!(
            out,
            " {:.1} | {:.1} |",
            planned_ms / planned_steps.max(1) as f64,
            wall / 60.0 / seeds.len().max(1) as f64
        );
    }
    out
}

/// One method's learning curve.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve {
    pub method: String,
    pub points: Vec<CurvePoint>,
}

/// The return at one episode, over seeds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CurvePoint {
    pub episode: u32,
    pub mean: f64,
    pub std: f64,
    /// Seeds that reached this episode.
    pub seeds: usize,
}

/// The rows of several experiments, each given as (its name, its rows), in one list: a method
/// found in more than one of them is labelled `method (name)` in each, so that two folders'
/// runs of one method (say iCEM at two populations) stay two curves instead of one curve that
/// counts each seed twice.
pub fn combine_experiments(experiments: Vec<(String, Vec<EpisodeRow>)>) -> Vec<EpisodeRow> {
    let mut folders_of: BTreeMap<String, usize> = BTreeMap::new();
    for (_, rows) in &experiments {
        let methods: BTreeSet<&str> = rows.iter().map(|r| r.method.as_str()).collect();
        for method in methods {
            *folders_of.entry(method.to_string()).or_default() += 1;
        }
    }
    let mut combined = Vec::new();
    for (name, rows) in experiments {
        for mut row in rows {
            if folders_of[&row.method] > 1 {
                row.method = format!("{} ({name})", row.method);
            }
            combined.push(row);
        }
    }
    combined
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn a_method_in_two_experiments_stays_two_curves_labelled_by_folder() {
        let icem150 = vec![row("cem+deen", 0, 0, 1.0), row("icem+deen", 0, 0, 2.0)];
        let icem250 = vec![row("icem+deen", 0, 0, 3.0), row("icem+deen", 1, 0, 5.0)];
        let rows = combine_experiments(vec![
            ("small-learning".into(), icem150),
            ("icem250".into(), icem250),
        ]);
        let methods: Vec<&str> = rows.iter().map(|r| r.method.as_str()).collect();
        assert_eq!(
            methods,
            [
                "cem+deen",
                "icem+deen (small-learning)",
                "icem+deen (icem250)",
                "icem+deen (icem250)"
            ]
        );
        let curves = curves(&rows);
        let icem250 = curves
            .iter()
            .find(|c| c.method == "icem+deen (icem250)")
            .unwrap();
        assert_eq!((icem250.points[0].seeds, icem250.points[0].mean), (2, 4.0));
    }

    /// A cartpole episode row with the given return (episode 0 unplanned).
    pub(crate) fn row(method: &str, seed: u64, episode: u32, ret: f64) -> EpisodeRow {
        EpisodeRow {
            task: "cartpole".into(),
            method: method.into(),
            seed,
            episode,
            episode_return: ret,
            steps: 200,
            planned_steps: if episode == 0 { 0 } else { 200 },
            plan_ms_per_step: if episode == 0 { 0.0 } else { 12.5 },
            train_seconds: f64::from(episode) * 1.5,
            wall_seconds: 3.25,
        }
    }

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("ebmpc-results-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn episodes_csv_has_the_documented_columns_and_round_trips() {
        let rows = vec![row("cem", 0, 0, 12.5), row("cem+deen", 1, 1, -3.25)];
        let text = to_csv(&rows);
        let mut lines = text.lines();
        assert_eq!(
            lines.next().unwrap(),
            "task,method,seed,episode,return,steps,planned_steps,plan_ms_per_step,train_seconds,wall_seconds"
        );
        assert_eq!(
            lines.next().unwrap(),
            "cartpole,cem,0,0,12.5,200,0,0.000,0.000,3.250"
        );
        assert_eq!(
            lines.next().unwrap(),
            "cartpole,cem+deen,1,1,-3.25,200,200,12.500,1.500,3.250"
        );
        let dir = temp("roundtrip");
        let path = dir.join("episodes.csv");
        write_episodes(&path, &rows).unwrap();
        assert_eq!(read_episodes(&path).unwrap(), rows);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn reads_the_bridge_csv_by_column_name() {
        let dir = temp("bridge");
        let path = dir.join("run.csv");
        std::fs::write(
            &path,
            format!(
                "{}\n0,10.5,200,1.000,0,0.000,0.000\n1,150,200,9.000,200,31.250,4.500\n",
                sim_bridge::csv::HEADER
            ),
        )
        .unwrap();
        let rows = read_run_csv(&path, "cartpole", "cem+dae", 7).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(count_rows(&path), 2);
        assert_eq!(
            rows[1],
            EpisodeRow {
                task: "cartpole".into(),
                method: "cem+dae".into(),
                seed: 7,
                episode: 1,
                episode_return: 150.0,
                steps: 200,
                planned_steps: 200,
                plan_ms_per_step: 31.25,
                train_seconds: 4.5,
                wall_seconds: 9.0,
            }
        );
        // A file without the return column is refused with its name.
        std::fs::write(&path, "episode,steps,wall_seconds\n0,200,1.0\n").unwrap();
        let err = read_run_csv(&path, "cartpole", "cem", 0).unwrap_err();
        assert!(err.to_string().contains("`return`"), "{err}");
        std::fs::write(
            &path,
            format!("{}\n0,oops,200,1,0,0,0\n", sim_bridge::csv::HEADER),
        )
        .unwrap();
        let err = read_run_csv(&path, "cartpole", "cem", 0).unwrap_err();
        assert!(err.to_string().contains("line 2"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(count_rows(&path), 0);
    }

    #[test]
    fn the_median_of_an_even_count_is_the_mean_of_the_middle_two() {
        assert_eq!(median(vec![]), None);
        assert_eq!(median(vec![3.0]), Some(3.0));
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(vec![5.0, 1.0, 3.0]), Some(3.0));
    }

    #[test]
    fn curves_are_mean_and_std_over_seeds_per_episode() {
        let rows = vec![
            row("cem", 0, 0, 10.0),
            row("cem", 1, 0, 20.0),
            row("cem", 0, 1, 100.0),
            row("cem+deen", 0, 0, 5.0),
            row("cem", 1, 1, 100.0),
        ];
        let c = curves(&rows);
        assert_eq!(c.len(), 2);
        assert_eq!(c[0].method, "cem");
        assert_eq!(
            c[0].points,
            vec![
                CurvePoint {
                    episode: 0,
                    mean: 15.0,
                    std: 50f64.sqrt(),
                    seeds: 2
                },
                CurvePoint {
                    episode: 1,
                    mean: 100.0,
                    std: 0.0,
                    seeds: 2
                }
            ]
        );
        assert_eq!(c[1].points.len(), 1);
    }

    #[test]
    fn a_results_table_gives_mean_and_sample_std_per_episode_and_says_when_seeds_are_missing() {
        let mut rows = vec![
            row("cem", 0, 0, 10.0),
            row("cem", 1, 0, 20.0),
            row("cem", 2, 0, 30.0),
            row("cem", 0, 1, 40.0),
            row("cem", 1, 1, 60.0),
            row("pets", 0, 0, 5.0),
        ];
        for r in &mut rows {
            r.planned_steps = 100;
            r.plan_ms_per_step = if r.method == "cem" { 2.0 } else { 8.0 };
            r.wall_seconds = 60.0;
        }
        let table = markdown_table(&rows, &[0, 1]);
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(
            lines[0],
            "| method | seeds | 0 | 1 | ms per planned step | minutes per run |"
        );
        assert_eq!(lines[1], "|---|---|---|---|---|---|");
        // Episode 0 over 3 seeds: mean 20, sample std 10; episode 1 reached by 2 of them.
        assert_eq!(
            lines[2],
            "| `cem` | 3 | 20 ± 10 | 50 ± 14 (2 seeds) | 2.0 | 1.7 |"
        );
        assert_eq!(lines[3], "| `pets` | 1 | 5 ± 0 | — | 8.0 | 1.0 |");
    }

    #[test]
    fn a_resumed_runs_skipped_episode_number_does_not_split_its_curve() {
        // Seed 1 was resumed: its daemon numbered the episode after the interruption 3.
        let rows = vec![
            row("cem", 0, 0, 1.0),
            row("cem", 0, 1, 2.0),
            row("cem", 0, 2, 3.0),
            row("cem", 1, 0, 1.0),
            row("cem", 1, 1, 2.0),
            row("cem", 1, 3, 5.0),
        ];
        let points = &curves(&rows)[0].points;
        assert_eq!(points.len(), 3);
        assert_eq!(
            (points[2].episode, points[2].seeds, points[2].mean),
            (2, 2, 4.0)
        );
    }

    #[test]
    fn returns_are_rounded_grouped_and_signed() {
        assert_eq!(grouped(0.4), "0");
        assert_eq!(grouped(999.5), "1,000");
        assert_eq!(grouped(-1234567.0), "−1,234,567");
        assert_eq!(grouped(-0.4), "0");
        assert_eq!(grouped(123.0), "123");
    }
}
