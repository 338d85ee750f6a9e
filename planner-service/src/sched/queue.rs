//! The order plans get the cores in: earliest deadline first. Pure bookkeeping, no clocks and
//! no threads, so the policy is tested deterministically.

use std::collections::BTreeSet;
use std::time::Instant;

/// How urgent a plan is: its deadline (`None`: no deadline, after every plan that has one),
/// then its arrival (first come, first served among equals).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Urgency {
    /// `false` sorts first: a plan with a deadline goes before every plan without one.
    unbounded: bool,
    deadline: Option<Instant>,
    /// Arrival order, unique per plan; also the plan's identity in the queue.
    arrival: u64,
}

impl Urgency {
    /// The plan's identity, unique for the life of its [`PlanQueue`].
    pub fn ticket(&self) -> u64 {
        self.arrival
    }
}

/// The plans waiting for the cores and the one that holds them.
#[derive(Debug, Default)]
pub struct PlanQueue {
    waiting: BTreeSet<Urgency>,
    running: Option<Urgency>,
    arrivals: u64,
}

impl PlanQueue {
    /// Queues a new plan that must end by `deadline`; returns its urgency, which names it
    /// from now on.
    pub fn arrive(&mut self, deadline: Option<Instant>) -> Urgency {
        let urgency = Urgency {
            unbounded: deadline.is_none(),
            deadline,
            arrival: self.arrivals,
        };
        self.arrivals += 1;
        self.waiting.insert(urgency);
        urgency
    }

    /// Gives the cores to the most urgent waiting plan if nobody holds them; returns the
    /// holder's ticket after the call.
    pub fn dispatch(&mut self) -> Option<u64> {
        if self.running.is_none() {
            self.running = self.waiting.pop_first();
        }
        self.running.map(|u| u.ticket())
    }

    /// Whether `ticket` holds the cores.
    pub fn holds(&self, ticket: u64) -> bool {
        self.running.is_some_and(|u| u.ticket() == ticket)
    }

    /// Whether a waiting plan is more urgent than the one holding the cores: then the holder
    /// should [`PlanQueue::preempt`] itself at its next iteration boundary.
    pub fn outranked(&self) -> bool {
        match (self.running, self.waiting.first()) {
            (Some(running), Some(first)) => first < &running,
            _ => false,
        }
    }

    /// The holder steps back into the queue (keeping its urgency) and the most urgent plan
    /// takes the cores.
    pub fn preempt(&mut self) {
        if let Some(running) = self.running.take() {
            self.waiting.insert(running);
        }
        self.dispatch();
    }

    /// `ticket` is done, whether it held the cores or still waited; the next plan gets them.
    pub fn leave(&mut self, ticket: u64) {
        if self.holds(ticket) {
            self.running = None;
        } else {
            self.waiting.retain(|u| u.ticket() != ticket);
        }
        self.dispatch();
    }

    /// Plans waiting for the cores (not counting the holder).
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }

    /// Whether no plan holds or waits for the cores.
    pub fn is_idle(&self) -> bool {
        self.running.is_none() && self.waiting.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Tickets in the order the queue hands out the cores, each plan running to its end.
    fn drain(queue: &mut PlanQueue) -> Vec<u64> {
        let mut order = vec![];
        while let Some(ticket) = queue.dispatch() {
            order.push(ticket);
            queue.leave(ticket);
        }
        order
    }

    #[test]
    fn earliest_deadline_first_then_arrival_then_plans_without_a_deadline() {
        let t0 = Instant::now();
        let at = |ms| Some(t0 + Duration::from_millis(ms));
        let mut queue = PlanQueue::default();
        let late = queue.arrive(at(500)).ticket();
        let free = queue.arrive(None).ticket();
        let soon = queue.arrive(at(40)).ticket();
        let free_later = queue.arrive(None).ticket();
        let soon_too = queue.arrive(at(40)).ticket();
        assert_eq!(queue.waiting(), 5);
        assert_eq!(drain(&mut queue), [soon, soon_too, late, free, free_later]);
        assert!(queue.is_idle());
    }

    #[test]
    fn an_overdue_plan_goes_first() {
        // A plan whose deadline passed while it queued answers at once (its previous plan,
        // counted as a miss), so running it first costs the others nothing.
        let t0 = Instant::now();
        let mut queue = PlanQueue::default();
        let fresh = queue.arrive(Some(t0 + Duration::from_secs(1))).ticket();
        let overdue = queue.arrive(Some(t0 - Duration::from_millis(5))).ticket();
        assert_eq!(drain(&mut queue), [overdue, fresh]);
    }

    #[test]
    fn the_holder_keeps_the_cores_until_a_more_urgent_plan_arrives() {
        let t0 = Instant::now();
        let mut queue = PlanQueue::default();
        let heavy = queue.arrive(None).ticket();
        assert_eq!(queue.dispatch(), Some(heavy));
        // A later deadline or another plan without one does not outrank the holder.
        let other_heavy = queue.arrive(None).ticket();
        assert!(!queue.outranked());
        let light = queue.arrive(Some(t0 + Duration::from_millis(40))).ticket();
        assert!(queue.outranked());
        queue.preempt();
        assert!(queue.holds(light));
        assert!(
            !queue.outranked(),
            "the heavy plans rank below the light one"
        );
        queue.leave(light);
        // The preempted plan kept its place ahead of the one that arrived after it.
        assert_eq!(queue.dispatch(), Some(heavy));
        queue.leave(heavy);
        assert_eq!(drain(&mut queue), [other_heavy]);
    }

    #[test]
    fn a_plan_that_leaves_while_waiting_is_forgotten() {
        let mut queue = PlanQueue::default();
        let first = queue.arrive(None).ticket();
        let gone = queue.arrive(None).ticket();
        let last = queue.arrive(None).ticket();
        assert_eq!(queue.dispatch(), Some(first));
        queue.leave(gone);
        assert_eq!(queue.waiting(), 1);
        queue.leave(first);
        assert!(queue.holds(last));
        queue.leave(last);
        assert!(queue.is_idle());
    }

    #[test]
    fn preempting_without_a_rival_keeps_the_holder() {
        let mut queue = PlanQueue::default();
        let only = queue.arrive(None).ticket();
        queue.dispatch();
        queue.preempt();
        assert!(queue.holds(only));
    }
}
