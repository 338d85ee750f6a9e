//! What an experiment shows while it runs: an overall bar over all pending episodes (with the
//! ETA), one bar per active run (episode, last return), and a log line per finished episode so
//! that a run under `nohup` (no terminal: the bars are hidden) still records its progress.

use crate::results::EpisodeRow;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};

/// The progress display of one experiment invocation.
pub struct Progress {
    multi: MultiProgress,
    overall: ProgressBar,
}

impl Progress {
    /// A display for `runs` runs of `episodes` episodes each.
    pub fn new(runs: usize, episodes: u32) -> Self {
        let multi = MultiProgress::new();
        let overall = multi.add(ProgressBar::new(runs as u64 * u64::from(episodes)));
        overall.set_style(
            ProgressStyle::with_template(
                "{prefix:>10} [{elapsed_precise}] {wide_bar} {pos}/{len} episodes, ETA {eta}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        overall.set_prefix("all runs");
        Self { multi, overall }
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

    /// Records a run's `recorded`-th finished episode (counted from 1). It is shown by that
    /// count, like the learning curves (`results::curves`): a resumed run's daemon numbers
    /// episodes by the data it holds, including the one the interruption cut short, so its own
    /// number is shown beside the count only where the two differ.
    pub fn episode(
        &self,
        bar: &ProgressBar,
        name: &str,
        recorded: usize,
        row: &EpisodeRow,
        episodes: u32,
    ) {
        let line = episode_line(recorded, row, episodes);
        bar.set_message(line.clone());
        self.overall.inc(1);
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

/// The line shown for a run's `recorded`-th finished episode of `episodes`.
fn episode_line(recorded: usize, row: &EpisodeRow, episodes: u32) -> String {
    let numbered = if row.episode as usize + 1 == recorded {
        String::new()
    } else {
        format!(" (daemon's episode {})", row.episode)
    };
    format!(
        "episode {recorded}/{episodes}{numbered} return {:.2} ({} planned steps, {:.1} ms/plan, {:.1} s training)",
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

    #[test]
    fn a_resumed_runs_episode_is_counted_by_recorded_episodes_with_the_daemons_number_beside() {
        // An uninterrupted run: the daemon's numbers are the counts.
        assert_eq!(
            episode_line(14, &row(13), 15),
            "episode 14/15 return -117.05 (150 planned steps, 49.2 ms/plan, 0.0 s training)"
        );
        // Resumed after an interruption cut one episode short: the 13th recorded episode is the
        // daemon's 14th (number 13), shown beside the count; the count never passes the total
        // (the log used to say "episode 17/15" for the last of such a run).
        assert_eq!(
            episode_line(13, &row(13), 15),
            "episode 13/15 (daemon's episode 13) return -117.05 (150 planned steps, 49.2 ms/plan, 0.0 s training)"
        );
    }
}
