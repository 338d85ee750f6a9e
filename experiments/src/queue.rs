//! The run queue of an experiment sitting: which run to start next, longest first, and only
//! whole runs that fit the sitting's wall-clock budget.
//!
//! The queue itself is the experiment folder (see [`crate::launcher`]): every run of the
//! manifest that has no complete `runs/<stem>.csv` is pending, so the queue survives any
//! restart, and a later sitting on another machine continues it. What this module adds is the
//! order and the budget:
//!
//! - **Estimates.** A pending run's remaining cost is its remaining steps times its method's
//!   measured seconds per step: the median over the method's episodes that planned of their
//!   wall time (it includes the waits for retraining) over their steps, from every run of the
//!   method in this folder, finished or not, counting only the episodes recorded on a machine
//!   with this one's CPU when there are any ([`on_this_machine`]): a folder accumulates across
//!   machines whose planning speeds differ several times. Remaining steps are what the
//!   timestep budget still lacks, or the remaining episodes times the method's mean episode
//!   length (the task's episode length until one is recorded). A method with no planned
//!   episode yet has no estimate.
//! - **Longest first.** Runs without an estimate come first (nothing says they are short, and
//!   running one measures its method), then the others by decreasing estimate: the long runs
//!   start while the whole budget is ahead, the short ones fill what is left.
//! - **Whole runs only.** With a budget, a run whose estimate exceeds the time left is not
//!   started in this sitting (it waits for the next one), unless the sitting allows overruns:
//!   then it starts anyway if at least its next episode fits, is stopped before the deadline
//!   and keeps a resumable state ([`crate::resume_state`]), but only when no run that fits is
//!   waiting. A run without an estimate starts; if it is still running at the deadline it is
//!   stopped the same way.
//! - **Stops between episodes.** A running run's bridge is given the deadline and stops at the
//!   episode boundary after which its next episode would end past it, before it resets the
//!   simulator ([`sim_bridge::deadline`]), so a stopped run's data are its recorded episodes;
//!   the deadline itself stops only an episode the estimate did not foresee.

use crate::results::{EpisodeRow, median};
use std::collections::BTreeMap;
use std::time::Duration;

/// What a method's recorded episodes say about its cost.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MethodCost {
    /// Wall seconds per step of its planned episodes (`None`: none planned yet).
    pub seconds_per_step: Option<f64>,
    /// Mean steps per episode over all its episodes (`None`: none recorded).
    pub steps_per_episode: Option<f64>,
}

/// Per method, the cost its recorded episodes (`rows`: every run's, finished or not) measure.
///
/// The rate is the median of the planned episodes' own rates, not their pooled mean: an
/// episode recorded while the machine was shared (two runs of a sitting on two cores, a build
/// beside a `SCHED_IDLE` sitting) runs several times slower, and a few of them would otherwise
/// set the estimate of every run of the method and keep a run that fits out of the sitting.
pub fn method_costs(rows: &[EpisodeRow]) -> BTreeMap<String, MethodCost> {
    #[derive(Default)]
    struct Seen {
        planned_rates: Vec<f64>,
        steps: f64,
        episodes: f64,
    }
    let mut seen: BTreeMap<&str, Seen> = BTreeMap::new();
    for r in rows {
        let s = seen.entry(r.method.as_str()).or_default();
        if r.planned_steps > 0 && r.steps > 0 {
            s.planned_rates.push(r.wall_seconds / f64::from(r.steps));
        }
        s.steps += f64::from(r.steps);
        s.episodes += 1.0;
    }
    seen.into_iter()
        .map(|(m, s)| {
            let cost = MethodCost {
                seconds_per_step: median(s.planned_rates),
                steps_per_episode: (s.episodes > 0.0).then(|| s.steps / s.episodes),
            };
            (m.to_string(), cost)
        })
        .collect()
}

/// Per method, the costs `all` the folder's episodes measure, with the seconds per step of
/// those recorded on this machine's CPU (`here`) where it has planned any: the rate of another
/// CPU only stands in until this one has measured the method.
pub fn on_this_machine(
    all: BTreeMap<String, MethodCost>,
    here: &BTreeMap<String, MethodCost>,
) -> BTreeMap<String, MethodCost> {
    all.into_iter()
        .map(|(method, cost)| {
            let local = here.get(&method).and_then(|h| h.seconds_per_step);
            let cost = MethodCost {
                seconds_per_step: local.or(cost.seconds_per_step),
                ..cost
            };
            (method, cost)
        })
        .collect()
}

/// How much of a run is still to do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Remaining {
    pub episodes: u32,
    /// Steps the timestep budget still lacks (`None`: the run is budgeted in episodes only).
    pub steps: Option<u64>,
}

/// What is left of a run with `recorded_episodes` and `recorded_steps` of `episodes` episodes
/// and (optionally) `timesteps` steps; `None` when it is complete.
pub fn remaining(
    episodes: u32,
    timesteps: Option<u64>,
    recorded_episodes: usize,
    recorded_steps: u64,
) -> Option<Remaining> {
    let left = (episodes as usize).saturating_sub(recorded_episodes) as u32;
    let steps = timesteps.map(|t| t.saturating_sub(recorded_steps));
    (left > 0 && steps != Some(0)).then_some(Remaining {
        episodes: left,
        steps,
    })
}

/// The estimated wall time of what remains of a run of a method with `cost`, on a task whose
/// episodes last at most `episode_len` steps (`None`: the method has no measured rate).
pub fn estimate(left: Remaining, cost: MethodCost, episode_len: u32) -> Option<Duration> {
    let rate = cost.seconds_per_step?;
    let per_episode = cost.steps_per_episode.unwrap_or(f64::from(episode_len));
    let by_episodes = f64::from(left.episodes) * per_episode;
    // A run budgeted in steps ends after the episode in which it reaches them: the last
    // episode runs to its end, so the steps left count as the whole episodes they start.
    let steps = left.steps.map_or(by_episodes, |s| {
        ((s as f64 / per_episode).ceil() * per_episode).min(by_episodes)
    });
    Some(Duration::from_secs_f64((steps * rate).max(0.0)))
}

/// The estimated wall time of one planned episode of a method with `cost` on a task whose
/// episodes last at most `episode_len` steps (`None`: the method has no measured rate).
pub fn planned_episode(cost: Option<MethodCost>, episode_len: u32) -> Option<Duration> {
    let one = Remaining {
        episodes: 1,
        steps: None,
    };
    estimate(one, cost?, episode_len)
}

/// The estimated wall time of a resumed run's next episode at the start of a sitting: the
/// median wall time of the planned ones among the run's episodes this CPU recorded
/// (`recorded_here`), otherwise the method's [`planned_episode`] here. Not the last episode's
/// own time, the rule the bridge applies within a sitting
/// ([`sim_bridge::deadline::next_episode`]): the last
/// episode ran in an earlier sitting, perhaps beside a build or a second experiment that this
/// one does not have, and one such episode would keep the run out of a sitting it fits. `None`
/// when neither has been measured.
pub fn next_episode(
    recorded_here: &[&EpisodeRow],
    cost: Option<MethodCost>,
    episode_len: u32,
) -> Option<Duration> {
    let walls: Vec<f64> = recorded_here
        .iter()
        .filter(|r| r.planned_steps > 0)
        .map(|r| r.wall_seconds.max(0.0))
        .collect();
    median(walls)
        .map(|w| Duration::try_from_secs_f64(w).unwrap_or(Duration::MAX))
        .or_else(|| planned_episode(cost, episode_len))
}

/// A pending run and its estimated remaining cost.
#[derive(Clone, Debug, PartialEq)]
pub struct Pending<R> {
    pub run: R,
    pub estimate: Option<Duration>,
    /// Its next episode's estimate ([`next_episode`]); `None` for a run not started yet, whose
    /// first episode is random exploration.
    pub next_episode: Option<Duration>,
}

/// Sorts `pending` longest first: runs without an estimate first (in their given order), then
/// by decreasing estimate (ties in their given order).
pub fn longest_first<R>(pending: &mut [Pending<R>]) {
    pending.sort_by(|a, b| match (a.estimate, b.estimate) {
        (None, None) => std::cmp::Ordering::Equal,
        (None, Some(_)) => std::cmp::Ordering::Less,
        (Some(_), None) => std::cmp::Ordering::Greater,
        (Some(x), Some(y)) => y.cmp(&x),
    });
}

/// Why a run was started.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Start {
    /// It is expected to finish within the budget (or there is no budget).
    Whole,
    /// Its cost is unknown: it runs until it finishes or the deadline stops it.
    Unmeasured,
    /// It is not expected to finish in time; the sitting allows it to run until the deadline.
    Overrun,
}

/// Takes the next run to start from `queue` (sorted by [`longest_first`]): the first that
/// fits in `left` (no budget: the first), else, with `overrun`, the first whose next episode
/// fits (a run started with less would only be stopped again at its first boundary). A run
/// that can finish in this sitting goes before any overrun however long it is: a finished run
/// is a result to commit, while an overrun's episodes are as useful in the next sitting.
/// `None` when no run may start in this sitting.
pub fn next<R>(
    queue: &mut Vec<Pending<R>>,
    left: Option<Duration>,
    overrun: bool,
) -> Option<(Pending<R>, Start)> {
    if left.is_some_and(|l| l.is_zero()) {
        return None;
    }
    let fits = |p: &Pending<R>| match (p.estimate, left) {
        (_, None) => Some(Start::Whole),
        (None, Some(_)) => Some(Start::Unmeasured),
        (Some(e), Some(l)) if e <= l => Some(Start::Whole),
        (Some(_), Some(_)) => None,
    };
    let overruns = |p: &Pending<R>| {
        let next_fits = p.next_episode.is_none_or(|e| left.is_none_or(|l| e <= l));
        (overrun && next_fits).then_some(Start::Overrun)
    };
    let take = |rule: &dyn Fn(&Pending<R>) -> Option<Start>| {
        queue
            .iter()
            .enumerate()
            .find_map(|(i, p)| rule(p).map(|s| (i, s)))
    };
    let (index, start) = take(&fits).or_else(|| take(&overruns))?;
    Some((queue.remove(index), start))
}

/// Parses a duration such as `90s`, `45m`, `6h`, `1h30m` or a plain number of seconds.
pub fn parse_duration(text: &str) -> Result<Duration, String> {
    let text = text.trim();
    if text.is_empty() {
        return Err("an empty duration".into());
    }
    if let Ok(secs) = text.parse::<f64>() {
        return seconds(secs, text);
    }
    let (mut total, mut number) = (0.0f64, String::new());
    for c in text.chars() {
        match c {
            '0'..='9' | '.' => number.push(c),
            'h' | 'm' | 's' | 'd' => {
                let value: f64 = number
                    .parse()
                    .map_err(|_| format!("`{text}`: a unit without a number"))?;
                total += value
                    * match c {
                        'd' => 86_400.0,
                        'h' => 3600.0,
                        'm' => 60.0,
                        _ => 1.0,
                    };
                number.clear();
            }
            _ => return Err(format!("`{text}`: use e.g. 90s, 45m, 6h or 1h30m")),
        }
    }
    if !number.is_empty() {
        return Err(format!("`{text}`: a number without a unit at the end"));
    }
    seconds(total, text)
}

fn seconds(secs: f64, text: &str) -> Result<Duration, String> {
    if !(secs.is_finite() && secs > 0.0 && secs <= 365.0 * 86_400.0) {
        return Err(format!(
            "`{text}`: a duration must be positive and at most a year"
        ));
    }
    Ok(Duration::from_secs_f64(secs))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(method: &str, steps: u32, planned: u32, wall: f64) -> EpisodeRow {
        EpisodeRow {
            task: "ant".into(),
            method: method.into(),
            seed: 0,
            episode: 0,
            episode_return: 0.0,
            steps,
            planned_steps: planned,
            plan_ms_per_step: 0.0,
            train_seconds: 0.0,
            wall_seconds: wall,
        }
    }

    #[test]
    fn the_next_episode_costs_the_median_of_the_runs_planned_episodes_here() {
        let cost = Some(MethodCost {
            seconds_per_step: Some(0.5),
            steps_per_episode: Some(800.0),
        });
        // One episode beside a build (4,200 s) among three alone: the median, not the last.
        let episodes = [
            row("pets", 1000, 1000, 1600.0),
            row("pets", 1000, 0, 4.0),
            row("pets", 1000, 1000, 1500.0),
            row("pets", 1000, 1000, 4200.0),
        ];
        let here: Vec<&EpisodeRow> = episodes.iter().collect();
        assert_eq!(
            next_episode(&here, cost, 1000),
            Some(Duration::from_secs(1600))
        );
        // None planned here (random exploration only, or another CPU's episodes): the
        // method's planned rate over its mean episode length.
        assert_eq!(
            next_episode(&here[1..2], cost, 1000),
            Some(Duration::from_secs(400))
        );
        assert_eq!(next_episode(&[], None, 1000), None);
        let unplanned = Some(MethodCost {
            seconds_per_step: None,
            steps_per_episode: Some(1000.0),
        });
        assert_eq!(next_episode(&[], unplanned, 1000), None);
    }

    #[test]
    fn a_methods_rate_comes_from_its_planned_episodes_only() {
        let rows = [
            row("cem", 1000, 0, 5.0), // random exploration: not a planning cost
            row("cem", 500, 500, 100.0),
            row("cem", 300, 300, 60.0),
            row("pets", 1000, 0, 4.0),
        ];
        let costs = method_costs(&rows);
        assert_eq!(costs["cem"].seconds_per_step, Some(160.0 / 800.0));
        assert_eq!(costs["cem"].steps_per_episode, Some(600.0));
        assert_eq!(costs["pets"].seconds_per_step, None, "no planned episode");
        assert_eq!(costs["pets"].steps_per_episode, Some(1000.0));
    }

    #[test]
    fn a_few_episodes_slowed_by_a_shared_machine_do_not_set_the_rate() {
        // Six episodes alone on the machine, two beside another run (eight times slower).
        let mut rows: Vec<EpisodeRow> = [0.7, 0.8, 0.75, 0.65, 0.7, 0.8]
            .iter()
            .map(|rate| row("adam+dae", 1000, 1000, rate * 1000.0))
            .collect();
        rows.push(row("adam+dae", 1000, 1000, 6000.0));
        rows.push(row("adam+dae", 1000, 1000, 6200.0));
        let rate = method_costs(&rows)["adam+dae"].seconds_per_step.unwrap();
        assert!(
            (rate - 0.775).abs() < 1e-9,
            "median of the episodes' rates: {rate}"
        );
        // The pooled mean would have been 2.1 s per step, nearly three times a run's cost alone.
        let pooled: f64 = rows.iter().map(|r| r.wall_seconds).sum::<f64>() / 8000.0;
        assert!(pooled > 2.0 * rate);
    }

    #[test]
    fn this_machines_rate_replaces_the_folders_once_it_has_recorded_here() {
        let all = [
            row("cem", 1000, 0, 1.0),
            row("cem", 1000, 1000, 300.0), // another CPU, 3× faster
            row("cem", 1000, 1000, 900.0),
            row("cem+deen", 1000, 1000, 600.0),
            row("pets", 1000, 0, 1.0),
        ];
        // This CPU recorded the slow cem episode and pets' random one only.
        let here = [all[2].clone(), all[4].clone()];
        let costs = on_this_machine(method_costs(&all), &method_costs(&here));
        assert_eq!(costs["cem"].seconds_per_step, Some(0.9), "this CPU's rate");
        assert_eq!(
            costs["cem"].steps_per_episode,
            Some(1000.0),
            "episode lengths are every machine's"
        );
        assert_eq!(
            costs["cem+deen"].seconds_per_step,
            Some(0.6),
            "not measured here: the folder's rate stands in"
        );
        assert_eq!(costs["pets"].seconds_per_step, None, "planned nowhere");
        assert_eq!(costs.len(), 3);
    }

    #[test]
    fn what_remains_of_a_run_in_episodes_and_timesteps() {
        assert_eq!(
            remaining(10, None, 4, 4000),
            Some(Remaining {
                episodes: 6,
                steps: None
            })
        );
        assert_eq!(remaining(10, None, 10, 100), None);
        // Budgeted in steps: done once they are reached, whatever the episodes.
        assert_eq!(remaining(100, Some(4000), 7, 4000), None);
        assert_eq!(remaining(100, Some(4000), 7, 4100), None);
        assert_eq!(
            remaining(100, Some(4000), 7, 1500),
            Some(Remaining {
                episodes: 93,
                steps: Some(2500)
            })
        );
        // ... or once the episode cap is.
        assert_eq!(remaining(8, Some(4000), 8, 1500), None);
    }

    #[test]
    fn estimates_use_the_steps_left_at_the_methods_rate() {
        let cost = MethodCost {
            seconds_per_step: Some(0.2),
            steps_per_episode: Some(150.0),
        };
        let by_episodes = Remaining {
            episodes: 4,
            steps: None,
        };
        assert_eq!(
            estimate(by_episodes, cost, 1000),
            Some(Duration::from_secs(120))
        );
        // A step budget shorter than the episodes' steps is what remains, in the whole
        // episodes it starts: the last one runs to its end (100 steps left: one episode of
        // 150; 400 left: three).
        let by_steps = |steps| Remaining {
            episodes: 4,
            steps: Some(steps),
        };
        assert_eq!(
            estimate(by_steps(100), cost, 1000),
            Some(Duration::from_secs(30))
        );
        assert_eq!(
            estimate(by_steps(400), cost, 1000),
            Some(Duration::from_secs(90))
        );
        assert_eq!(
            estimate(by_steps(4000), cost, 1000),
            Some(Duration::from_secs(120)),
            "never more than the episodes left"
        );
        // Without a recorded episode the task's episode length stands in.
        let fresh = MethodCost {
            steps_per_episode: None,
            ..cost
        };
        assert_eq!(
            estimate(by_episodes, fresh, 1000),
            Some(Duration::from_secs(800))
        );
        let unmeasured = MethodCost {
            seconds_per_step: None,
            ..cost
        };
        assert_eq!(estimate(by_episodes, unmeasured, 1000), None);
    }

    fn pending(runs: &[(&'static str, Option<u64>)]) -> Vec<Pending<&'static str>> {
        runs.iter()
            .map(|&(run, mins)| Pending {
                run,
                estimate: mins.map(|m| Duration::from_secs(60 * m)),
                next_episode: None,
            })
            .collect()
    }

    fn names(queue: &[Pending<&'static str>]) -> Vec<&'static str> {
        queue.iter().map(|p| p.run).collect()
    }

    #[test]
    fn unmeasured_runs_come_first_then_the_longest() {
        let mut queue = pending(&[
            ("cem-s0", Some(10)),
            ("pets-s0", None),
            ("deen-s0", Some(60)),
            ("cem-s1", Some(10)),
            ("pets-s1", None),
        ]);
        longest_first(&mut queue);
        assert_eq!(
            names(&queue),
            ["pets-s0", "pets-s1", "deen-s0", "cem-s0", "cem-s1"]
        );
    }

    #[test]
    fn only_whole_runs_that_fit_the_time_left_start() {
        let mut queue = pending(&[("a", Some(120)), ("b", Some(50)), ("c", Some(20))]);
        let minutes = |m: u64| Some(Duration::from_secs(60 * m));
        // 60 minutes left: the longest run that fits is b, not a.
        let (p, start) = next(&mut queue, minutes(60), false).unwrap();
        assert_eq!((p.run, start), ("b", Start::Whole));
        // 10 minutes left: nothing fits; a waits for the next sitting.
        assert!(next(&mut queue, minutes(10), false).is_none());
        assert_eq!(names(&queue), ["a", "c"]);
        // Allowing overruns starts the longest, to be stopped at the deadline.
        let (p, start) = next(&mut queue, minutes(10), true).unwrap();
        assert_eq!((p.run, start), ("a", Start::Overrun));
        // Without a budget, everything runs in order.
        let (p, start) = next(&mut queue, None, false).unwrap();
        assert_eq!((p.run, start), ("c", Start::Whole));
        assert!(next(&mut queue, None, false).is_none());
    }

    /// The sitting that left a one-episode run waiting behind two that could not finish.
    #[test]
    fn a_run_that_finishes_in_the_sitting_goes_before_longer_overruns() {
        let minutes = |m: u64| Some(Duration::from_secs(60 * m));
        let mut queue = pending(&[("s2", Some(265)), ("s0", Some(141)), ("s1", Some(18))]);
        let (p, start) = next(&mut queue, minutes(120), true).unwrap();
        assert_eq!((p.run, start), ("s1", Start::Whole));
        let (p, start) = next(&mut queue, minutes(120), true).unwrap();
        assert_eq!((p.run, start), ("s2", Start::Overrun));
        let (p, start) = next(&mut queue, minutes(100), true).unwrap();
        assert_eq!((p.run, start), ("s0", Start::Overrun));
    }

    #[test]
    fn an_overrun_starts_only_a_run_whose_next_episode_fits() {
        let minutes = |m: u64| Some(Duration::from_secs(60 * m));
        let mut queue = pending(&[("resumed", Some(30)), ("new", Some(20))]);
        queue[0].next_episode = minutes(3);
        // 2 minutes left: the resumed run's next episode (3 min) would be stopped at once;
        // the new run starts with its random episode.
        let (p, start) = next(&mut queue, minutes(2), true).unwrap();
        assert_eq!((p.run, start), ("new", Start::Overrun));
        assert!(next(&mut queue, minutes(2), true).is_none());
        // With 5 minutes it starts.
        let (p, start) = next(&mut queue, minutes(5), true).unwrap();
        assert_eq!((p.run, start), ("resumed", Start::Overrun));
    }

    #[test]
    fn an_unmeasured_run_starts_while_time_is_left_and_nothing_after_the_deadline() {
        let mut queue = pending(&[("pets", None), ("cem", Some(1))]);
        let (p, start) = next(&mut queue, Some(Duration::from_secs(30)), false).unwrap();
        assert_eq!((p.run, start), ("pets", Start::Unmeasured));
        assert!(next(&mut queue, Some(Duration::ZERO), true).is_none());
        assert_eq!(names(&queue), ["cem"]);
    }

    #[test]
    fn durations_parse_in_common_units() {
        let s = |t| parse_duration(t).map(|d| d.as_secs());
        assert_eq!(s("90"), Ok(90));
        assert_eq!(s("90s"), Ok(90));
        assert_eq!(s("45m"), Ok(2700));
        assert_eq!(s("6h"), Ok(21_600));
        assert_eq!(s("1h30m"), Ok(5400));
        assert_eq!(s("1d"), Ok(86_400));
        for bad in ["", "h", "10x", "5h3", "-1", "0", "inf", "400d", "1e300"] {
            assert!(parse_duration(bad).is_err(), "{bad}");
        }
    }
}
