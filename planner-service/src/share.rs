//! Sharing the cores between planning and retraining: plans come first.
//!
//! Every run's plans and retrainings draw on the same rayon pool. A plan has a deadline and a
//! retraining has minutes, so a retraining yields: before each minibatch it waits while any
//! plan is in flight, at most [`MAX_YIELD`] per minibatch so that a daemon planning without
//! pause still trains (then at the pace of one minibatch per [`MAX_YIELD`]). The wait is
//! between minibatches, never inside one: a minibatch already running finishes first, so a plan
//! may still share the cores with one minibatch's worth of training.

use std::sync::{Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// The longest a retraining waits for plans before one minibatch.
pub const MAX_YIELD: Duration = Duration::from_millis(200);

/// Counts the plans in flight, daemon-wide; retrainings wait on it.
#[derive(Debug, Default)]
pub struct PlanGate {
    in_flight: Mutex<usize>,
    idle: Condvar,
}

/// A plan in flight; dropping it ends the plan.
#[must_use = "the plan counts as in flight until the guard drops"]
pub struct Planning<'g> {
    gate: &'g PlanGate,
}

impl PlanGate {
    /// Marks a plan in flight until the returned guard drops.
    pub fn planning(&self) -> Planning<'_> {
        *self
            .in_flight
            .lock()
            .unwrap_or_else(PoisonError::into_inner) += 1;
        Planning { gate: self }
    }

    /// Plans in flight now.
    pub fn in_flight(&self) -> usize {
        *self
            .in_flight
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    /// Waits (blocking the calling thread) until no plan is in flight, or `max` has passed.
    /// Returns how long it waited.
    pub fn wait_for_plans(&self, max: Duration) -> Duration {
        let start = Instant::now();
        let guard = self
            .in_flight
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let _guard = self
            .idle
            .wait_timeout_while(guard, max, |n| *n > 0)
            .unwrap_or_else(PoisonError::into_inner);
        start.elapsed()
    }
}

impl Drop for Planning<'_> {
    fn drop(&mut self) {
        let mut n = self
            .gate
            .in_flight
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        *n = n.saturating_sub(1);
        if *n == 0 {
            self.gate.idle.notify_all();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    #[test]
    fn training_waits_while_a_plan_is_in_flight() {
        let gate = Arc::new(PlanGate::default());
        // Nothing in flight: the wait returns at once (else this test would hang 10 min).
        gate.wait_for_plans(Duration::from_secs(600));
        let ended = Arc::new(AtomicBool::new(false));
        let plan = gate.planning();
        assert_eq!(gate.in_flight(), 1);
        let waiter = std::thread::spawn({
            let (gate, ended) = (gate.clone(), ended.clone());
            move || {
                gate.wait_for_plans(Duration::from_secs(600));
                // The wait ends only after the plan did.
                assert!(ended.load(Ordering::SeqCst));
            }
        });
        std::thread::sleep(Duration::from_millis(50));
        ended.store(true, Ordering::SeqCst);
        drop(plan);
        waiter.join().unwrap();
        assert_eq!(gate.in_flight(), 0);
    }

    #[test]
    fn a_wait_is_bounded_while_plans_never_stop() {
        let gate = PlanGate::default();
        let _plan = gate.planning();
        // The plan never ends: the wait gives up after its bound.
        assert!(gate.wait_for_plans(Duration::from_millis(20)) >= Duration::from_millis(20));
    }
}
