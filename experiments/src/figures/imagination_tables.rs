//! Figure 5's tables, printed from an imagination folder's files as the results page shows
//! them: the summary over every (seed, state) with its bootstrap intervals, read from
//! `imagination_summary.csv` as the comparison wrote it (the intervals are not resampled
//! again), and the per-seed means from `imagination_states.csv`, with each seed's training
//! returns from `imagination_seeds.csv` where the folder has one (older folders do not).

use super::imagination::{StateRow, SummaryRow, read_csv, read_state_rows};
use super::imagination_folder::SeedRecord;
use crate::results::grouped;
use anyhow::{Context, Result, bail};
use std::fmt::Write as _;
use std::path::Path;

/// `value` with two decimals and a minus sign (`−1.26`), `+` too when `signed` (`+6.40`).
fn decimal(value: f64, signed: bool) -> String {
    let text = format!("{:.2}", value.abs());
    let zero = text.bytes().all(|b| b == b'0' || b == b'.');
    match (value < 0.0 && !zero, signed) {
        (true, _) => format!("−{text}"),
        (false, true) => format!("+{text}"),
        (false, false) => text,
    }
}

/// How the page names a regulariser: `none`, or its name in capitals with its weight.
fn label(regularizer: &str, alpha: f32) -> String {
    if regularizer == "none" {
        "none".to_string()
    } else {
        format!("{} (α = {alpha})", regularizer.to_uppercase())
    }
}

fn steps_of(rows: &[StateRow]) -> Result<usize> {
    let Some(first) = rows.first() else {
        bail!("no state rows");
    };
    if rows.iter().any(|r| r.steps != first.steps) {
        bail!("the rows compare plans over different numbers of steps");
    }
    Ok(first.steps)
}

/// Per regulariser: the mean gap (imagined − real) and the mean real return over every (seed,
/// state) pair, each with its 95 % interval.
pub fn summary_markdown(folder: &Path) -> Result<String> {
    let summary: Vec<SummaryRow> = read_csv(&folder.join("imagination_summary.csv"))?;
    let steps = steps_of(&read_state_rows(&folder.join("imagination_states.csv"))?)
        .with_context(|| format!("{}", folder.display()))?;
    let mut out =
        format!("| regulariser | imagined − real ({steps} steps) | real return |\n|---|---|---|\n");
    for row in &summary {
        let _ = writeln!(
            out,
            "| {} | {} [{}, {}] | {} [{}, {}] |",
            label(&row.regularizer, row.alpha),
            decimal(row.mean_gap, true),
            decimal(row.gap_ci_low, false),
            decimal(row.gap_ci_high, false),
            decimal(row.mean_real_return, false),
            decimal(row.real_ci_low, false),
            decimal(row.real_ci_high, false),
        );
    }
    Ok(out)
}

/// Per seed, per regulariser: the mean imagined return, real return and gap over its states;
/// the seed's training returns beside it when the folder recorded them.
pub fn per_seed_markdown(folder: &Path) -> Result<String> {
    let rows = read_state_rows(&folder.join("imagination_states.csv"))?;
    steps_of(&rows).with_context(|| format!("{}", folder.display()))?;
    let seeds_path = folder.join("imagination_seeds.csv");
    let records: Vec<SeedRecord> = if seeds_path.exists() {
        read_csv(&seeds_path)?
    } else {
        Vec::new()
    };
    let mut regularizers: Vec<&str> = Vec::new();
    let mut seeds: Vec<u64> = Vec::new();
    for r in &rows {
        if !regularizers.contains(&r.regularizer.as_str()) {
            regularizers.push(&r.regularizer);
        }
        if !seeds.contains(&r.seed) {
            seeds.push(r.seed);
        }
    }
    seeds.sort_unstable();

    let mut out = String::from(if records.is_empty() {
        "| seed |"
    } else {
        "| seed (training returns) |"
    });
    for (i, regularizer) in regularizers.iter().enumerate() {
        let name = if *regularizer == "none" {
            "none".to_string()
        } else {
            regularizer.to_uppercase()
        };
        if i == 0 {
            let _ = write!(out, " {name}: imagined / real / gap |");
        } else {
            let _ = write!(out, " {name} |");
        }
    }
    out.push_str("\n|---|");
    out.push_str(&"---|".repeat(regularizers.len()));
    out.push('\n');
    for seed in seeds {
        let _ = write!(out, "| {seed}");
        if let Some(record) = records.iter().find(|r| r.seed == seed) {
            let returns: Vec<String> = record
                .training_returns
                .split(';')
                .map(|r| {
                    r.trim()
                        .parse::<f64>()
                        .map(grouped)
                        .with_context(|| format!("seed {seed}'s training return {r:?}"))
                })
                .collect::<Result<_>>()?;
            let _ = write!(out, " ({})", returns.join(", "));
        }
        out.push_str(" |");
        for regularizer in &regularizers {
            let mine: Vec<&StateRow> = rows
                .iter()
                .filter(|r| r.seed == seed && r.regularizer == *regularizer)
                .collect();
            let mean = |f: fn(&StateRow) -> f32| {
                mine.iter().map(|r| f64::from(f(r))).sum::<f64>() / mine.len().max(1) as f64
            };
            if mine.is_empty() {
                out.push_str(" — |");
            } else {
                let _ = write!(
                    out,
                    " {} / {} / {} |",
                    decimal(mean(|r| r.imagined_return), false),
                    decimal(mean(|r| r.real_return), false),
                    decimal(mean(|r| r.gap), true),
                );
            }
        }
        out.push('\n');
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::figures::imagination::write_csv;

    fn state(seed: u64, regularizer: &str, imagined: f32, real: f32) -> StateRow {
        StateRow::for_test(seed, 0, regularizer, imagined, real)
    }

    #[test]
    fn decimals_carry_a_minus_sign_and_a_plus_where_signed() {
        assert_eq!(decimal(6.404, true), "+6.40");
        assert_eq!(decimal(-1.255_1, true), "−1.26");
        assert_eq!(decimal(-0.001, false), "0.00");
        assert_eq!(decimal(34.187, false), "34.19");
        assert_eq!(decimal(-5.26, false), "−5.26");
    }

    #[test]
    fn per_seed_means_and_training_returns() {
        let dir = tempfile::tempdir().unwrap();
        let mut rows = vec![
            state(1, "none", 10.0, 8.0),
            state(1, "deen", 6.0, 7.0),
            state(0, "none", 2.0, 1.0),
            state(0, "deen", 1.0, 1.0),
        ];
        rows.push(StateRow::for_test(0, 1, "none", 4.0, 1.0));
        write_csv(&dir.path().join("imagination_states.csv"), &rows).unwrap();
        let without = per_seed_markdown(dir.path()).unwrap();
        assert_eq!(
            without,
            "| seed | none: imagined / real / gap | DEEN |\n|---|---|---|\n\
             | 0 | 3.00 / 1.00 / +2.00 | 1.00 / 1.00 / +0.00 |\n\
             | 1 | 10.00 / 8.00 / +2.00 | 6.00 / 7.00 / −1.00 |\n"
        );
        let record = |seed, returns: &str| SeedRecord {
            seed,
            training_returns: returns.to_string(),
            wall_seconds: 1.0,
            commit: "c".into(),
            cpu: "cpu".into(),
            cpu_family_model: "25/17".into(),
            logical_cpus: 2,
        };
        write_csv(
            &dir.path().join("imagination_seeds.csv"),
            &[record(0, "-394.33;1459.94"), record(1, "12.5;-3.2")],
        )
        .unwrap();
        let with = per_seed_markdown(dir.path()).unwrap();
        assert!(
            with.starts_with("| seed (training returns) | none: imagined / real / gap | DEEN |"),
            "{with}"
        );
        assert!(
            with.contains("| 0 (−394, 1,460) | 3.00 / 1.00 / +2.00 |"),
            "{with}"
        );
        assert!(with.contains("| 1 (13, −3) | 10.00"), "{with}");
    }

    #[test]
    fn the_summary_prints_the_recorded_intervals() {
        let dir = tempfile::tempdir().unwrap();
        write_csv(
            &dir.path().join("imagination_states.csv"),
            &[state(0, "none", 2.0, 1.0)],
        )
        .unwrap();
        let row = SummaryRow {
            regularizer: "deen".into(),
            alpha: 0.05,
            seeds: 3,
            states: 60,
            mean_gap: -1.26,
            gap_ci_low: -2.72,
            gap_ci_high: 0.64,
            mean_real_return: 4.37,
            real_ci_low: 1.04,
            real_ci_high: 6.42,
        };
        write_csv(&dir.path().join("imagination_summary.csv"), &[row]).unwrap();
        assert_eq!(
            summary_markdown(dir.path()).unwrap(),
            "| regulariser | imagined − real (30 steps) | real return |\n|---|---|---|\n\
             | DEEN (α = 0.05) | −1.26 [−2.72, 0.64] | 4.37 [1.04, 6.42] |\n"
        );
    }

    #[test]
    fn a_folder_without_rows_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        assert!(per_seed_markdown(dir.path()).is_err());
        assert!(summary_markdown(dir.path()).is_err());
    }
}
