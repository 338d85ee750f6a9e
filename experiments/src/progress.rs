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

    /// Records a finished episode of a run.
    pub fn episode(&self, bar: &ProgressBar, name: &str, row: &EpisodeRow, episodes: u32) {
        let line = format!(
            "episode {}/{} return {:.2} ({} planned steps, {:.1} ms/plan, {:.1} s training)",
            row.episode + 1,
            episodes,
            row.episode_return,
            row.planned_steps,
            row.plan_ms_per_step,
            row.train_seconds
        );
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
