//! What an experiment shows while it runs: an overall bar over all pending runs (with the
//! ETA), one bar per active run (episode, last return), and a log line per finished episode so
//! that a run under `nohup` (no terminal: the bars are hidden) still records its progress.
//!
//! Progress is counted in what a run's length is counted in: episodes, or environment steps
//! for a run budgeted in timesteps (whose episode count is only an upper bound, as long as
//! the budget: an ant run of 4,000 steps may take 5 episodes or 18).

use crate::results::EpisodeRow;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};

/// How long each run of an experiment is: `episodes` episodes, or, with `timesteps`, the
/// episode in which its steps reach that many.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RunLength {
    pub episodes: u32,
    pub timesteps: Option<u64>,
}

impl RunLength {
    /// One run's length in the unit progress is counted in.
    fn units(self) -> u64 {
        self.timesteps.unwrap_or(u64::from(self.episodes))
    }

    /// The unit's name, for the overall bar.
    fn unit(self) -> &'static str {
        if self.timesteps.is_some() {
            "steps"
        } else {
            "episodes"
        }
    }

    /// The progress of a run that has recorded `episodes` episodes of `steps` steps in all.
    fn done(self, episodes: usize, steps: u64) -> u64 {
        if self.timesteps.is_some() {
            steps
        } else {
            episodes as u64
        }
    }
}

impl std::fmt::Display for RunLength {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.timesteps {
            Some(t) if u64::from(self.episodes) < t => {
                write!(f, "{t} steps or {} episodes per run", self.episodes)
            }
            Some(t) => write!(f, "{t} steps per run"),
            None => write!(f, "{} episodes per run", self.episodes),
        }
    }
}

/// The progress display of one experiment invocation.
pub struct Progress {
    multi: MultiProgress,
    overall: ProgressBar,
    length: RunLength,
}

impl Progress {
    /// A display for `runs` runs of `length` each.
    pub fn new(runs: usize, length: RunLength) -> Self {
        let multi = MultiProgress::new();
        let overall = multi.add(ProgressBar::new(runs as u64 * length.units()));
        let template = format!(
            "{{prefix:>10}} [{{elapsed_precise}}] {{wide_bar}} {{pos}}/{{len}} {}, ETA {{eta}}",
            length.unit()
        );
        overall.set_style(
            ProgressStyle::with_template(&template)
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        overall.set_prefix("all runs");
        Self {
            multi,
            overall,
            length,
        }
    }

    /// Counts what a resumed run recorded before this sitting (`episodes` episodes of `steps`
    /// steps in all) as done, so that the overall bar's ETA is of what is left.
    pub fn resumed(&self, episodes: usize, steps: u64) {
        self.overall.inc(self.length.done(episodes, steps));
    }

    /// A bar for a run that starts now.
    pub fn start_run(&self, name: &str) -> ProgressBar {
        let bar = self.multi.add(ProgressBar::new(0));
        bar.set_style(
            ProgressStyle::with_template("{prefix:>14} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_spinner()),
        );
        bar.set_prefix(name.to_string());
        bar.set_message("starting");
        self.log(&format!("run {name} started"));
        bar
    }

    /// Records a run's `recorded`-th finished episode (counted from 1), after which the run
    /// holds `steps` steps in all. It is shown by that count, like the learning curves
    /// (`results::curves`): a resumed run's daemon numbers episodes by the data it holds,
    /// including the one the interruption cut short, so its own number is shown beside the
    /// count only where the two differ.
    pub fn episode(
        &self,
        bar: &ProgressBar,
        name: &str,
        recorded: usize,
        steps: u64,
        row: &EpisodeRow,
    ) {
        let line = episode_line(recorded, steps, row, self.length);
        bar.set_message(line.clone());
        self.overall.inc(self.length.done(1, u64::from(row.steps)));
        self.log(&format!("{name}: {line}"));
    }

    /// Removes a finished run's bar.
    pub fn end_run(&self, bar: ProgressBar) {
        bar.finish_and_clear();
        self.multi.remove(&bar);
    }

    /// A log line that does not tear the bars.
    pub fn log(&self, line: &str) {
        self.multi.suspend(|| tracing::info!("{line}"));
    }

    /// Leaves the overall bar in place with its final count.
    pub fn finish(&self) {
        self.overall.finish();
    }
}

/// The line shown for a run's `recorded`-th finished episode, after which the run holds
/// `steps` steps, in a run of `length`.
fn episode_line(recorded: usize, steps: u64, row: &EpisodeRow, length: RunLength) -> String {
    let numbered = if row.episode as usize + 1 == recorded {
        String::new()
    } else {
        format!(" (daemon's episode {})", row.episode)
    };
    let count = match length.timesteps {
        Some(t) => format!("episode {recorded}{numbered}, {steps}/{t} steps,"),
        None => format!("episode {recorded}/{}{numbered}", length.episodes),
    };
    format!(
        "{count} return {:.2} ({} planned steps, {:.1} ms/plan, {:.1} s training)",
        row.episode_return, row.planned_steps, row.plan_ms_per_step, row.train_seconds
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(episode: u32) -> EpisodeRow {
        EpisodeRow {
            task: "pusher".into(),
            method: "cem".into(),
            seed: 1,
            episode,
            episode_return: -117.05,
            steps: 150,
            planned_steps: 150,
            plan_ms_per_step: 49.2,
            train_seconds: 0.0,
            wall_seconds: 7.6,
        }
    }

    const FIFTEEN_EPISODES: RunLength = RunLength {
        episodes: 15,
        timesteps: None,
    };

    #[test]
    fn a_resumed_runs_episode_is_counted_by_recorded_episodes_with_the_daemons_number_beside() {
        // An uninterrupted run: the daemon's numbers are the counts.
        assert_eq!(
            episode_line(14, 2100, &row(13), FIFTEEN_EPISODES),
            "episode 14/15 return -117.05 (150 planned steps, 49.2 ms/plan, 0.0 s training)"
        );
        // Resumed after an interruption cut one episode short: the 13th recorded episode is the
        // daemon's 14th (number 13), shown beside the count; the count never passes the total
        // (the log used to say "episode 17/15" for the last of such a run).
        assert_eq!(
            episode_line(13, 1950, &row(13), FIFTEEN_EPISODES),
            "episode 13/15 (daemon's episode 13) return -117.05 (150 planned steps, 49.2 ms/plan, 0.0 s training)"
        );
    }

    #[test]
    fn a_run_budgeted_in_timesteps_counts_its_steps_not_an_episode_total_it_has_not_got() {
        // `--timesteps 10000` bounds the episodes by the steps (each has at least one), so
        // "episode 2/10000" would be true and useless; the steps against the budget are not.
        let steps = RunLength {
            episodes: 10_000,
            timesteps: Some(10_000),
        };
        assert_eq!(
            episode_line(2, 261, &row(1), steps),
            "episode 2, 261/10000 steps, return -117.05 (150 planned steps, 49.2 ms/plan, 0.0 s training)"
        );
        assert_eq!(steps.to_string(), "10000 steps per run");
        assert_eq!(
            (steps.units(), steps.unit(), steps.done(2, 261)),
            (10_000, "steps", 261)
        );
        let both = RunLength {
            episodes: 20,
            timesteps: Some(10_000),
        };
        assert_eq!(both.to_string(), "10000 steps or 20 episodes per run");
        assert_eq!(FIFTEEN_EPISODES.to_string(), "15 episodes per run");
        assert_eq!(
            (
                FIFTEEN_EPISODES.units(),
                FIFTEEN_EPISODES.unit(),
                FIFTEEN_EPISODES.done(2, 261)
            ),
            (15, "episodes", 2)
        );
    }
}
