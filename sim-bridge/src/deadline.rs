//! A wall-clock deadline for a run of episodes: the bridge starts an episode only when it is
//! expected to end before the deadline, and otherwise stops between episodes.
//!
//! Why the bridge decides and not whoever started it: the bridge resets the simulator and sends
//! the next episode's first observation the moment an episode ends. A supervisor that watched
//! the episodes file and sent SIGTERM "between episodes" would usually land after that first
//! observation, and the planner would then record an interrupted episode with no transitions,
//! spending an episode number (later episodes would start from other states than in an
//! uninterrupted run). Deciding before the reset leaves nothing half-begun.

use crate::bridge::EpisodeRecord;
use std::time::{Duration, SystemTime};

/// No episode should still be running at `at`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EpisodeDeadline {
    /// The deadline (wall-clock time, so that another process can set it).
    pub at: SystemTime,
    /// The expected wall time of a planned episode, for the episode after one that planned
    /// nothing (random exploration is far faster than planning, so it predicts nothing).
    /// `None`: such an episode always starts.
    pub planned_episode: Option<Duration>,
}

impl EpisodeDeadline {
    /// The next episode's expected wall time after `last`: `last`'s own when it planned (a
    /// run's planning cost drifts slowly, so its latest episode predicts the next best, and it
    /// includes the wait for retraining), otherwise [`Self::planned_episode`].
    pub fn next_episode(&self, last: &EpisodeRecord) -> Option<Duration> {
        next_episode(
            last.actions.planned,
            last.wall_seconds,
            self.planned_episode,
        )
    }

    /// Whether an episode following `last` may start at `now`: unless it is expected to end
    /// after the deadline. An episode with no estimate starts (the supervisor's own stop at the
    /// deadline bounds it).
    pub fn admits(&self, last: &EpisodeRecord, now: SystemTime) -> bool {
        let left = self.at.duration_since(now).unwrap_or(Duration::ZERO);
        self.next_episode(last).is_none_or(|next| next <= left)
    }
}

/// The expected wall time of the episode after one that planned `planned_steps` steps in
/// `wall_seconds`: that episode's own time when it planned, else `planned_episode` (the one
/// rule for the bridge at its deadline and for the experiment queue's estimates).
pub fn next_episode(
    planned_steps: u32,
    wall_seconds: f64,
    planned_episode: Option<Duration>,
) -> Option<Duration> {
    if planned_steps > 0 {
        // NaN counts as no time, a time too long for a Duration as the longest.
        Some(Duration::try_from_secs_f64(wall_seconds.max(0.0)).unwrap_or(Duration::MAX))
    } else {
        planned_episode
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bridge::ActionTally;
    use proto::EpisodeEnd;

    fn episode(planned: u32, wall_seconds: f64) -> EpisodeRecord {
        EpisodeRecord {
            episode: 3,
            episode_return: 1.0,
            steps: 100,
            end: EpisodeEnd::TimeLimit,
            wall_seconds,
            actions: ActionTally {
                planned,
                random: 100 - planned,
                planning_ms: 0.0,
                models_version: 1,
            },
            train_seconds: 0.0,
        }
    }

    #[test]
    fn a_planned_episode_predicts_the_next_and_stops_it_when_it_would_end_late() {
        let now = SystemTime::UNIX_EPOCH + Duration::from_secs(1_000_000);
        let deadline = EpisodeDeadline {
            at: now + Duration::from_secs(60),
            planned_episode: Some(Duration::from_secs(3_600)),
        };
        assert!(deadline.admits(&episode(100, 59.0), now));
        assert!(deadline.admits(&episode(100, 60.0), now));
        assert!(!deadline.admits(&episode(100, 61.0), now));
        // Past the deadline nothing with a cost starts.
        let later = now + Duration::from_secs(120);
        assert!(!deadline.admits(&episode(100, 0.5), later));
    }

    #[test]
    fn after_exploration_the_planned_estimate_decides_and_without_one_the_episode_starts() {
        let now = SystemTime::UNIX_EPOCH + Duration::from_secs(1_000_000);
        let mut deadline = EpisodeDeadline {
            at: now + Duration::from_secs(60),
            planned_episode: Some(Duration::from_secs(90)),
        };
        let random = episode(0, 1.0);
        assert_eq!(
            deadline.next_episode(&random),
            Some(Duration::from_secs(90))
        );
        assert!(!deadline.admits(&random, now));
        deadline.planned_episode = Some(Duration::from_secs(30));
        assert!(deadline.admits(&random, now));
        deadline.planned_episode = None;
        assert!(deadline.admits(&random, now + Duration::from_secs(3_600)));
    }
}
