//! Whether one method beats another at an episode, with the uncertainty that a few seeds leave.
//!
//! Two views of the same returns. Each method's mean over its seeds with a Student-t interval
//! says where that method's expected return lies; the paper's curves are such per-method
//! means. But the methods of one experiment share each seed's random exploration (the same
//! first episodes, hence the same first models), and how fast a seed learns varies more between
//! seeds than between methods, so the per-method intervals can overlap while one method wins in
//! every seed. The seed-paired difference (method A's return minus method B's, seed by seed,
//! over the seeds both have) removes what a seed's luck adds to both; its Student-t interval
//! says whether the difference is distinguishable from 0.
//!
//! Episodes are counted as the learning curves count them: the `k`-th recorded episode of a
//! run (see [`runs_by_method`]). Runs budgeted in timesteps (the ant's 4,000) end after
//! different numbers of episodes; they are compared at each run's last episode.

use crate::results::{EpisodeRow, grouped, mean_and_std, runs_by_method};
use statrs::distribution::{ContinuousCDF, StudentsT};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// A mean over seeds and its two-sided Student-t confidence interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    pub seeds: usize,
    pub mean: f64,
    /// `None` with fewer than two seeds: one value says nothing about the spread.
    pub interval: Option<(f64, f64)>,
}

impl Estimate {
    /// The mean of `values` with a `level` (e.g. 0.95) Student-t interval.
    pub fn of(values: &[f64], level: f64) -> Self {
        let n = values.len();
        let (mean, std) = mean_and_std(values);
        let interval = (n >= 2).then(|| {
            let half = t_quantile(n - 1, 0.5 + level / 2.0) * std / (n as f64).sqrt();
            (mean - half, mean + half)
        });
        Estimate {
            seeds: n,
            mean,
            interval,
        }
    }

    /// Whether the two intervals share no point (false when either has none).
    pub fn separate_from(&self, other: &Estimate) -> bool {
        match (self.interval, other.interval) {
            (Some((lo, hi)), Some((other_lo, other_hi))) => hi < other_lo || other_hi < lo,
            _ => false,
        }
    }
}

/// The `p` quantile of Student's t distribution with `freedom` degrees of freedom.
fn t_quantile(freedom: usize, p: f64) -> f64 {
    StudentsT::new(0.0, 1.0, freedom as f64)
        .expect("location 0, scale 1 and at least one degree of freedom are valid")
        .inverse_cdf(p)
}

/// Which episode of each run is compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum At {
    /// The `k`-th recorded episode, from 0.
    Episode(u32),
    /// Each run's last recorded episode.
    Last,
}

impl std::str::FromStr for At {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        match text {
            "last" => Ok(At::Last),
            _ => text
                .parse()
                .map(At::Episode)
                .map_err(|_| format!("`{text}` is neither an episode number (from 0) nor `last`")),
        }
    }
}

impl std::fmt::Display for At {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            At::Episode(k) => write!(f, "episode {k} (from 0)"),
            At::Last => f.write_str("each run's last episode"),
        }
    }
}

/// One method's return at the compared episode.
#[derive(Clone, Debug, PartialEq)]
pub struct MethodReturn {
    pub method: String,
    pub estimate: Estimate,
}

/// Method `a`'s return minus method `b`'s, seed by seed; `a` is the method ahead on average.
#[derive(Clone, Debug, PartialEq)]
pub struct PairedDifference {
    pub a: String,
    pub b: String,
    pub estimate: Estimate,
    /// Seeds in which `a` earned more than `b`.
    pub a_ahead: usize,
    /// Whether the two methods' own intervals share no point.
    pub methods_separate: bool,
}

/// The comparison of an experiment's methods at one episode.
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    pub at: At,
    pub level: f64,
    /// Methods in first-seen order; a method without the episode in any seed is left out.
    pub methods: Vec<MethodReturn>,
    /// Every pair of methods that shares at least one seed, in the order of `methods`, each
    /// with the method ahead on average first.
    pub differences: Vec<PairedDifference>,
}

/// Compares the methods of `rows` at `at` with `level` intervals.
pub fn compare(rows: &[EpisodeRow], at: At, level: f64) -> Comparison {
    // Each method's return at the episode, by seed; methods without it in any seed left out.
    let by_method: Vec<(&str, BTreeMap<u64, f64>)> = runs_by_method(rows)
        .into_iter()
        .map(|(method, runs)| {
            let returns: BTreeMap<u64, f64> = runs
                .iter()
                .filter_map(|(seed, run)| {
                    let row = match at {
                        At::Episode(k) => run.get(k as usize),
                        At::Last => run.last(),
                    };
                    row.map(|r| (*seed, r.episode_return))
                })
                .collect();
            (method, returns)
        })
        .filter(|(_, returns)| !returns.is_empty())
        .collect();
    let methods: Vec<MethodReturn> = by_method
        .iter()
        .map(|(method, returns)| MethodReturn {
            method: method.to_string(),
            estimate: Estimate::of(&returns.values().copied().collect::<Vec<_>>(), level),
        })
        .collect();
    let mut differences = Vec::new();
    for (i, (a, a_returns)) in by_method.iter().enumerate() {
        for (j, (b, b_returns)) in by_method.iter().enumerate().skip(i + 1) {
            let mut diffs: Vec<f64> = a_returns
                .iter()
                .filter_map(|(seed, ra)| b_returns.get(seed).map(|rb| ra - rb))
                .collect();
            if diffs.is_empty() {
                continue;
            }
            // The method ahead on average first, so that a difference reads as a lead.
            let (mut a, mut b) = (a, b);
            if diffs.iter().sum::<f64>() < 0.0 {
                (a, b) = (b, a);
                diffs.iter_mut().for_each(|d| *d = -*d);
            }
            differences.push(PairedDifference {
                a: a.to_string(),
                b: b.to_string(),
                a_ahead: diffs.iter().filter(|d| **d > 0.0).count(),
                estimate: Estimate::of(&diffs, level),
                methods_separate: methods[i].estimate.separate_from(&methods[j].estimate),
            });
        }
    }
    Comparison {
        at,
        level,
        methods,
        differences,
    }
}

/// Which of the two tables to print.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Table {
    /// Each method's mean return with its interval.
    Methods,
    /// Every pair's seed-paired difference with its interval.
    Differences,
}

impl At {
    /// The episode as a table cell: its number from 0, or `last`.
    fn cell(self) -> String {
        match self {
            At::Episode(k) => k.to_string(),
            At::Last => "last".into(),
        }
    }
}

/// An estimate's three cells: seeds, mean and interval.
fn estimate_cells(e: &Estimate) -> String {
    let interval = match e.interval {
        Some((lo, hi)) => format!("[{}, {}]", grouped(lo), grouped(hi)),
        None => "— (one seed)".into(),
    };
    format!("{} | {} | {interval}", e.seeds, grouped(e.mean))
}

/// The comparisons at several episodes as one Markdown table, a row per episode and method (or
/// pair), with the numbers in the results tables' format (thousands grouped, a minus sign).
/// Comparisons at different levels cannot share a header: the first one's names it.
pub fn markdown(comparisons: &[Comparison], table: Table) -> String {
    let percent = comparisons.first().map_or(95.0, |c| c.level * 100.0);
    let mut out = String::new();
    match table {
        Table::Methods => {
            let _ = writeln!(
                out,
                "| episode | method | seeds | mean | {percent:.0} % interval |\n|---|---|---|---|---|"
            );
            for c in comparisons {
                for m in &c.methods {
                    let _ = writeln!(
                        out,
                        "| {} | `{}` | {} |",
                        c.at.cell(),
                        m.method,
                        estimate_cells(&m.estimate)
                    );
                }
            }
        }
        Table::Differences => {
            let _ = writeln!(
                out,
                "| episode | difference | seeds | mean | {percent:.0} % interval | first ahead in | \
                 methods' intervals |\n|---|---|---|---|---|---|---|"
            );
            for c in comparisons {
                for d in &c.differences {
                    let methods = if d.methods_separate {
                        "separate"
                    } else {
                        "overlap"
                    };
                    let _ = writeln!(
                        out,
                        "| {} | `{}` − `{}` | {} | {} of {} | {methods} |",
                        c.at.cell(),
                        d.a,
                        d.b,
                        estimate_cells(&d.estimate),
                        d.a_ahead,
                        d.estimate.seeds,
                    );
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::results::tests::row;

    #[test]
    fn student_t_intervals_match_published_quantiles() {
        // t(0.975) for 2, 4 and 9 degrees of freedom: 4.303, 2.776, 2.262 (any t table).
        for (freedom, quantile) in [(2, 4.3027), (4, 2.7764), (9, 2.2622)] {
            assert!(
                (t_quantile(freedom, 0.975) - quantile).abs() < 1e-3,
                "{freedom}"
            );
        }
        // Mean 2, sample std 1 over 3 values: 2 ± 4.303 / sqrt(3).
        let e = Estimate::of(&[1.0, 2.0, 3.0], 0.95);
        let (lo, hi) = e.interval.unwrap();
        assert_eq!(e.seeds, 3);
        assert!((e.mean - 2.0).abs() < 1e-12);
        assert!((hi - 2.0 - 4.3027 / 3f64.sqrt()).abs() < 1e-3);
        assert!((2.0 - lo - (hi - 2.0)).abs() < 1e-9);
        assert_eq!(Estimate::of(&[5.0], 0.95).interval, None);
    }

    #[test]
    fn a_method_ahead_in_every_seed_is_told_apart_by_pairing_though_its_interval_overlaps() {
        // Seeds differ by thousands, the methods by 100 in every seed (+-10).
        let mut rows = Vec::new();
        for (seed, base) in [(0, 1000.0), (1, 3000.0), (2, 5000.0), (3, 2000.0)] {
            let noise = if seed % 2 == 0 { 10.0 } else { -10.0 };
            rows.push(row("cem", seed, 0, -300.0));
            rows.push(row("cem", seed, 1, base));
            rows.push(row("cem+deen", seed, 0, -300.0));
            rows.push(row("cem+deen", seed, 1, base + 100.0 + noise));
        }
        let c = compare(&rows, At::Episode(1), 0.95);
        assert_eq!(c.methods.len(), 2);
        assert_eq!(c.methods[0].method, "cem");
        assert!((c.methods[1].estimate.mean - 2850.0).abs() < 1e-9);
        let d = &c.differences[0];
        assert_eq!((d.a.as_str(), d.b.as_str()), ("cem+deen", "cem"));
        assert!((d.estimate.mean - 100.0).abs() < 1e-9);
        assert_eq!(d.a_ahead, 4);
        let (lo, hi) = d.estimate.interval.unwrap();
        assert!(lo > 0.0 && hi < 200.0, "[{lo}, {hi}]");
        assert!(!d.methods_separate);
        let table = markdown(std::slice::from_ref(&c), Table::Differences);
        assert!(
            table.contains("| 1 | `cem+deen` − `cem` | 4 | 100 |"),
            "{table}"
        );
        assert!(table.contains("4 of 4 | overlap |"), "{table}");
    }

    #[test]
    fn methods_far_apart_in_every_seed_have_separate_intervals() {
        let mut rows = Vec::new();
        for seed in 0..3 {
            rows.push(row("cem", seed, 0, 100.0 + seed as f64));
            rows.push(row("cem+deen", seed, 0, 900.0 - seed as f64));
        }
        let c = compare(&rows, At::Episode(0), 0.95);
        assert!(c.differences[0].methods_separate);
        assert_eq!(c.differences[0].a, "cem+deen");
        assert_eq!(c.differences[0].a_ahead, 3);
        assert!(markdown(&[c], Table::Differences).contains("| separate |"));
    }

    #[test]
    fn pairs_use_shared_seeds_and_episodes_count_recorded_rows() {
        // cem has seeds 0-2, cem+dae seeds 1-3; seed 1 of cem+dae was resumed and numbers its
        // second recorded episode 2 (a cut-short episode skipped): it is still episode 1.
        let rows = vec![
            row("cem", 0, 0, 0.0),
            row("cem", 0, 1, 10.0),
            row("cem", 1, 0, 0.0),
            row("cem", 1, 1, 20.0),
            row("cem", 2, 0, 0.0),
            row("cem", 2, 1, 30.0),
            row("cem+dae", 1, 0, 0.0),
            row("cem+dae", 1, 2, 25.0),
            row("cem+dae", 2, 0, 0.0),
            row("cem+dae", 2, 1, 40.0),
            row("cem+dae", 3, 0, 0.0),
            row("pets", 0, 0, 0.0),
        ];
        let c = compare(&rows, At::Episode(1), 0.95);
        let names: Vec<&str> = c.methods.iter().map(|m| m.method.as_str()).collect();
        assert_eq!(names, ["cem", "cem+dae"], "pets has no episode 1");
        assert_eq!(c.methods[1].estimate.seeds, 2);
        let d = &c.differences[0];
        assert_eq!((d.a.as_str(), d.estimate.seeds), ("cem+dae", 2));
        assert!((d.estimate.mean - 7.5).abs() < 1e-9, "(5 + 10) / 2");
        assert_eq!(d.a_ahead, 2);
    }

    #[test]
    fn runs_of_different_lengths_are_compared_at_their_last_episodes() {
        // A timestep budget: cem's seed 0 took 3 episodes, seed 1 two; cem+deen's one each.
        let rows = vec![
            row("cem", 0, 0, 1.0),
            row("cem", 0, 1, 2.0),
            row("cem", 0, 2, 30.0),
            row("cem", 1, 0, 1.0),
            row("cem", 1, 1, 50.0),
            row("cem+deen", 0, 0, 70.0),
            row("cem+deen", 1, 0, 90.0),
        ];
        let c = compare(&rows, At::Last, 0.95);
        assert!((c.methods[0].estimate.mean - 40.0).abs() < 1e-9);
        assert!((c.methods[1].estimate.mean - 80.0).abs() < 1e-9);
        assert_eq!(c.differences[0].a_ahead, 2);
        let table = markdown(&[c], Table::Methods);
        assert!(table.starts_with("| episode | method | seeds | mean | 95 % interval |"));
        assert!(table.contains("| last | `cem+deen` | 2 | 80 |"), "{table}");
        assert_eq!("last".parse::<At>(), Ok(At::Last));
        assert_eq!("19".parse::<At>(), Ok(At::Episode(19)));
        assert!("-1".parse::<At>().unwrap_err().contains("neither"));
    }
}
