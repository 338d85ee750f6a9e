//! Anytime planning: a solve stops iterating when its next iteration would finish after the
//! plan's deadline, and answers with the best plan found so far.
//!
//! The cost of the next iteration is estimated from the iterations already timed, per scored
//! candidate (iCEM's population shrinks from one iteration to the next): the latest iteration
//! of this solve, or for a solve's first iteration the latest of an earlier solve. Without a
//! deadline nothing is cut, so a seeded planner takes exactly the actions it always did; the
//! iterations are still timed (two clock reads each), for the scheduler's estimate of a whole
//! solve ([`IterationClock::estimate`]).
//!
//! A solve that shares the cores (the daemon's plans, see [`crate::sched`]) may be paused
//! before an iteration, and between two imagined time steps within one, while a more urgent
//! plan runs; the pause counts against the deadline but not in the iteration timings, which
//! describe this planner's own work.

use crate::sched::Preempt;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The time budget of one solve, and the iteration timings that outlive it. Owned by one
/// planner (one agent): its timings describe its models and population on this machine.
#[derive(Clone, Debug, Default)]
pub struct IterationClock {
    /// When the solve in hand must have ended; `None`: never cut.
    deadline: Option<Instant>,
    /// Seconds per scored candidate of the latest timed iteration; `None` before any.
    per_candidate: Option<f64>,
    /// The same before any halving by a refused first iteration: what the scheduler ranks the
    /// next solve by, so that a heavy plan refused again and again does not come to look light.
    measured_per_candidate: Option<f64>,
    /// When the iteration in hand started, and [`Preempt::paused`] then.
    started: Option<(Instant, Duration)>,
    /// Who may pause the solve in hand between iterations; `None`: it has the cores alone.
    preempt: Option<Arc<dyn Preempt>>,
}

impl IterationClock {
    /// Starts a solve that must end by `deadline` (`None`: runs every configured iteration).
    pub fn start(&mut self, deadline: Option<Instant>) {
        self.start_shared(deadline, None);
    }

    /// Starts a solve like [`IterationClock::start`] that `preempt` may pause before each
    /// iteration (released again by the next start).
    pub fn start_shared(&mut self, deadline: Option<Instant>, preempt: Option<Arc<dyn Preempt>>) {
        self.deadline = deadline;
        self.started = None;
        self.preempt = preempt;
    }

    /// Whether an iteration scoring `candidates` may start now: always without a deadline,
    /// otherwise when the estimate says it ends by the deadline (or nothing is timed yet). A
    /// first iteration refused halves the estimate, so a planner whose estimate came from a
    /// slow moment (a burst of load) tries again soon instead of answering unplanned for ever.
    pub fn may_start(&mut self, candidates: usize, first: bool) -> bool {
        if let Some(preempt) = &self.preempt {
            preempt.step_back();
        }
        let now = Instant::now();
        let fits = match (self.deadline, self.per_candidate) {
            (None, _) => true,
            (Some(deadline), None) => now < deadline,
            (Some(deadline), Some(per)) => {
                now + Duration::from_secs_f64(per * candidates as f64) <= deadline
            }
        };
        if fits {
            self.started = Some((now, self.paused()));
        } else if first && let Some(per) = self.per_candidate.as_mut() {
            *per *= 0.5;
        }
        fits
    }

    /// Who may pause the solve in hand inside an iteration (between imagined steps).
    pub fn preempt(&self) -> Option<&dyn Preempt> {
        self.preempt.as_deref()
    }

    fn paused(&self) -> Duration {
        self.preempt.as_ref().map_or(Duration::ZERO, |p| p.paused())
    }

    /// How long a whole solve of `candidates` (summed over its iterations) is expected to
    /// take on the cores alone, from the latest timed iteration; `None` before any.
    pub fn estimate(&self, candidates: usize) -> Option<Duration> {
        self.measured_per_candidate
            .map(|per| Duration::from_secs_f64(per * candidates as f64))
    }

    /// Ends the solve in hand: whoever could pause it is let go.
    pub fn end(&mut self) {
        self.preempt = None;
    }

    /// Records the end of the iteration that [`IterationClock::may_start`] let start.
    pub fn finished(&mut self, candidates: usize) {
        if let Some((started, paused_before)) = self.started.take() {
            let paused = self.paused().saturating_sub(paused_before);
            let seconds = started.elapsed().saturating_sub(paused).as_secs_f64();
            self.per_candidate = Some(seconds / candidates.max(1) as f64);
            self.measured_per_candidate = self.per_candidate;
        }
    }

    /// Whether the solve in hand has a deadline.
    pub fn has_deadline(&self) -> bool {
        self.deadline.is_some()
    }
}

/// Counts the pauses a solve is offered and takes none (for tests here and in `imagine`).
#[cfg(test)]
#[derive(Debug, Default)]
pub(crate) struct CountingPreempt(pub std::sync::atomic::AtomicUsize);

#[cfg(test)]
impl Preempt for CountingPreempt {
    fn step_back(&self) {
        self.0.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    }

    fn paused(&self) -> Duration {
        Duration::ZERO
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_a_deadline_every_iteration_starts() {
        let mut clock = IterationClock::default();
        clock.start(None);
        for _ in 0..3 {
            assert!(clock.may_start(1_000_000, false));
            clock.finished(1);
        }
        assert!(!clock.has_deadline());
    }

    #[test]
    fn a_passed_deadline_refuses_and_an_estimate_over_it_refuses() {
        let mut clock = IterationClock::default();
        clock.start(Some(Instant::now() - Duration::from_millis(1)));
        assert!(!clock.may_start(10, true), "the deadline has passed");
        // One candidate took at least 20 ms: 10 of them cannot fit in 100 ms.
        clock.start(Some(Instant::now() + Duration::from_secs(3600)));
        assert!(clock.may_start(1, true));
        std::thread::sleep(Duration::from_millis(20));
        clock.finished(1);
        clock.start(Some(Instant::now() + Duration::from_millis(100)));
        assert!(!clock.may_start(10, false));
        // They fit in an hour.
        clock.start(Some(Instant::now() + Duration::from_secs(3600)));
        assert!(clock.may_start(10, false));
    }

    #[test]
    fn a_refused_first_iteration_halves_the_estimate() {
        let mut clock = IterationClock {
            per_candidate: Some(1.0),
            ..Default::default()
        };
        clock.start(Some(Instant::now() + Duration::from_secs(3600)));
        // 8000 candidates at 1 s each cannot fit in an hour; at 0.25 s (after two halvings)
        // 8000 × 0.25 = 2000 s can.
        assert!(!clock.may_start(8000, true));
        assert!(!clock.may_start(8000, true));
        assert!(clock.may_start(8000, true));
        // What the scheduler ranks the plan by is still the last measurement (none here).
        assert_eq!(clock.estimate(1), None);
        clock.finished(8000);
        let measured = clock.estimate(8000).expect("timed");
        clock.start(Some(Instant::now()));
        assert!(!clock.may_start(8000, true), "the deadline has passed");
        assert_eq!(clock.estimate(8000), Some(measured), "not halved");
    }

    /// Pauses `pause` in the middle of every iteration (as the scheduler does between two
    /// imagined steps), and says so.
    #[derive(Debug)]
    struct PausingPreempt {
        pause: Duration,
        paused: std::sync::Mutex<Duration>,
    }

    impl Preempt for PausingPreempt {
        fn step_back(&self) {
            std::thread::sleep(self.pause);
            *self.paused.lock().unwrap() += self.pause;
        }

        fn paused(&self) -> Duration {
            *self.paused.lock().unwrap()
        }
    }

    #[test]
    fn time_stepped_back_inside_an_iteration_is_left_out_of_its_timing() {
        let preempt = Arc::new(PausingPreempt {
            pause: Duration::from_millis(300),
            paused: Default::default(),
        });
        let mut clock = IterationClock::default();
        clock.start_shared(None, Some(preempt.clone()));
        assert!(clock.may_start(1, true));
        // The iteration's own work takes no measurable time; a more urgent plan takes 300 ms
        // of the cores in its middle.
        clock.preempt().expect("shared").step_back();
        clock.finished(1);
        let estimate = clock.estimate(1).expect("timed");
        assert!(estimate < Duration::from_millis(300), "{estimate:?}");
        assert!(preempt.paused() >= Duration::from_millis(600), "two pauses");
    }

    #[test]
    fn a_shared_solve_may_be_paused_before_every_iteration_and_lets_go_at_its_end() {
        let preempt = Arc::new(CountingPreempt::default());
        let mut clock = IterationClock::default();
        clock.start_shared(None, Some(preempt.clone()));
        for _ in 0..3 {
            assert!(clock.may_start(10, false));
            clock.finished(10);
        }
        assert_eq!(preempt.0.load(std::sync::atomic::Ordering::SeqCst), 3);
        // The scheduler's turn is released when the solve ends, not when the next one starts.
        clock.end();
        assert_eq!(Arc::strong_count(&preempt), 1);
    }
}
