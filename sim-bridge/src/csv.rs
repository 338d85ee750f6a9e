//! The per-episode results file, one row per episode:
//! `episode,return,steps,wall_seconds,planned_steps,plan_ms_mean,train_seconds` — the return,
//! the time the episode took, how many of its actions were planned (the rest were random
//! exploration), the planner's mean planning time per planned action, and the retraining time
//! the planner reported before the episode (see [`EpisodeRecord::train_seconds`]).
//!
//! Rows are written and flushed as episodes end, so an interrupted run keeps every finished
//! episode; learning curves across seeds are then a join on `episode`.

use crate::bridge::EpisodeRecord;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// The header line, naming the columns in order.
pub const HEADER: &str =
    "episode,return,steps,wall_seconds,planned_steps,plan_ms_mean,train_seconds";

/// A CSV file of episode results.
#[derive(Debug)]
pub struct EpisodeCsv<W: Write> {
    out: W,
}

impl EpisodeCsv<BufWriter<File>> {
    /// Creates (or truncates) `path`, creating its folder if needed, and writes the header.
    pub fn create(path: &Path) -> io::Result<Self> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        Self::new(BufWriter::new(File::create(path)?))
    }
}

impl<W: Write> EpisodeCsv<W> {
    /// Writes the header to `out`.
    pub fn new(mut out: W) -> io::Result<Self> {
        writeln!(out, "{HEADER}")?;
        out.flush()?;
        Ok(Self { out })
    }

    /// Appends one episode's row and flushes it.
    pub fn append(&mut self, r: &EpisodeRecord) -> io::Result<()> {
        writeln!(
            self.out,
            "{},{},{},{:.3},{},{:.3},{:.3}",
            r.episode,
            r.episode_return,
            r.steps,
            r.wall_seconds,
            r.actions.planned,
            r.actions.mean_planning_ms(),
            r.train_seconds
        )?;
        self.out.flush()
    }

    /// The underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bridge::ActionTally;
    use proto::EpisodeEnd;

    #[test]
    fn writes_a_header_then_one_row_per_episode() {
        let mut csv = EpisodeCsv::new(Vec::new()).unwrap();
        for (episode, ret, planned) in [(0, 12.5f32, 0), (1, -3.25, 200)] {
            let actions = ActionTally {
                planned,
                random: 200 - planned,
                planning_ms: 50.0 * f64::from(planned),
                models_version: u64::from(episode),
            };
            let record = EpisodeRecord {
                episode,
                episode_return: ret,
                steps: 200,
                end: EpisodeEnd::TimeLimit,
                wall_seconds: 1.23456,
                actions,
                train_seconds: 2.5 * f64::from(episode),
            };
            csv.append(&record).unwrap();
        }
        let text = String::from_utf8(csv.into_inner()).unwrap();
        assert_eq!(
            text,
            format!(
                "{HEADER}\n0,12.5,200,1.235,0,0.000,0.000\n1,-3.25,200,1.235,200,50.000,2.500\n"
            )
        );
    }

    #[test]
    fn create_makes_the_folder_and_the_header() {
        let dir = std::env::temp_dir().join(format!("sim-bridge-csv-{}", std::process::id()));
        let path = dir.join("nested").join("episodes.csv");
        let csv = EpisodeCsv::create(&path).unwrap();
        drop(csv);
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            format!("{HEADER}\n")
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
