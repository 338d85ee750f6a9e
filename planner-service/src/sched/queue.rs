//! The order plans get the cores in. Pure bookkeeping, no clocks and no threads, so the policy
//! is tested deterministically.
//!
//! Earliest deadline first is optimal while the deadlines can all be met, and the worst policy
//! when they cannot: a heavy plan that will be cut anyway (half-cheetah + DEEN at the paper's
//! sizes needs several times its 50 ms) would take the cores right up to its deadline, and a
//! light plan that arrived behind it with a slightly later deadline would miss too. So plans
//! come in [`Class`]es first: plans whose whole solve fits before their deadline (by their
//! planner's own estimate) go before plans that will be cut whatever happens, earliest deadline
//! first. The plans that will be cut share what is left, the shortest solve first: it holds
//! the cores the least time and keeps the largest share of its iterations, which matters on a
//! loaded machine, where a light plan's estimate can cross its deadline too and the light plan
//! would otherwise rank beside the heavy one. The heavy run's misses are then its own, counted
//! and reported, instead of being passed on to the light one.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

/// What a plan can still make of its deadline, as it arrives; earlier variants go first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Class {
    /// Its deadline has passed: it answers at once (its previous plan, counted as a miss), so
    /// running it first costs the others nothing.
    Overdue,
    /// Its whole solve fits before its deadline (or it has no estimate yet).
    Fits,
    /// Its solve cannot fit: it will be cut, and gets what the fitting plans leave.
    Cut,
    /// No deadline: after every plan that has one.
    Unbounded,
}

impl Class {
    /// The class of a plan arriving `now` that must end by `deadline` and whose whole solve is
    /// expected to take `estimate` on the cores alone (`None`: not timed yet).
    pub fn of(now: Instant, deadline: Option<Instant>, estimate: Option<Duration>) -> Self {
        match (deadline, estimate) {
            (None, _) => Class::Unbounded,
            (Some(deadline), _) if deadline <= now => Class::Overdue,
            (Some(deadline), Some(estimate)) if now + estimate > deadline => Class::Cut,
            (Some(_), _) => Class::Fits,
        }
    }
}

/// How urgent a plan is: its [`Class`], then (plans that will be cut) its estimated solve,
/// then its deadline, then its arrival (first come, first served among equals).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Urgency {
    class: Class,
    /// The estimated solve of a plan of class [`Class::Cut`]; `None` for the others.
    cut_solve: Option<Duration>,
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
    /// Queues a new plan arriving `now` that must end by `deadline`, whose whole solve its
    /// planner expects to take `estimate` (`None`: not timed yet); returns its urgency, which
    /// names it from now on.
    pub fn arrive(
        &mut self,
        now: Instant,
        deadline: Option<Instant>,
        estimate: Option<Duration>,
    ) -> Urgency {
        let class = Class::of(now, deadline, estimate);
        let urgency = Urgency {
            class,
            cut_solve: estimate.filter(|_| class == Class::Cut),
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

    /// Queues a plan arriving at `now` the way the scheduler does.
    fn arrive(
        queue: &mut PlanQueue,
        now: Instant,
        deadline: Option<Instant>,
        estimate: Option<Duration>,
    ) -> Urgency {
        queue.arrive(now, deadline, estimate)
    }

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
        let late = arrive(&mut queue, t0, at(500), None).ticket();
        let free = arrive(&mut queue, Instant::now(), None, None).ticket();
        let soon = arrive(&mut queue, t0, at(40), None).ticket();
        let free_later = arrive(&mut queue, Instant::now(), None, None).ticket();
        let soon_too = arrive(&mut queue, t0, at(40), None).ticket();
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
        let fresh = arrive(&mut queue, t0, Some(t0 + Duration::from_secs(1)), None).ticket();
        let overdue = arrive(&mut queue, t0, Some(t0 - Duration::from_millis(5)), None).ticket();
        assert_eq!(drain(&mut queue), [overdue, fresh]);
    }

    #[test]
    fn the_holder_keeps_the_cores_until_a_more_urgent_plan_arrives() {
        let t0 = Instant::now();
        let mut queue = PlanQueue::default();
        let heavy = arrive(&mut queue, Instant::now(), None, None).ticket();
        assert_eq!(queue.dispatch(), Some(heavy));
        // A later deadline or another plan without one does not outrank the holder.
        let other_heavy = arrive(&mut queue, Instant::now(), None, None).ticket();
        assert!(!queue.outranked());
        let light = arrive(&mut queue, t0, Some(t0 + Duration::from_millis(40)), None).ticket();
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
        let first = arrive(&mut queue, Instant::now(), None, None).ticket();
        let gone = arrive(&mut queue, Instant::now(), None, None).ticket();
        let last = arrive(&mut queue, Instant::now(), None, None).ticket();
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
        let only = arrive(&mut queue, Instant::now(), None, None).ticket();
        queue.dispatch();
        queue.preempt();
        assert!(queue.holds(only));
    }

    #[test]
    fn a_plan_that_will_be_cut_anyway_makes_way_for_one_that_fits() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut queue = PlanQueue::default();
        // Half-cheetah + DEEN: a 300 ms solve against a 50 ms deadline. It holds the cores.
        let heavy = arrive(&mut queue, t0, Some(t0 + ms(50)), Some(ms(300))).ticket();
        assert_eq!(queue.dispatch(), Some(heavy));
        // Cartpole arrives 20 ms later: a 30 ms solve due 40 ms later, after the heavy one's
        // deadline. Earliest deadline first would leave it 10 ms for 30 ms of work.
        let later = t0 + ms(20);
        let light = arrive(&mut queue, later, Some(later + ms(40)), Some(ms(30))).ticket();
        assert!(queue.outranked());
        queue.preempt();
        assert!(queue.holds(light));
        queue.leave(light);
        assert!(queue.holds(heavy));
        // Among plans that all fit (or all will be cut), the earliest deadline goes first.
        let fits_late = arrive(&mut queue, t0, Some(t0 + ms(90)), Some(ms(10))).ticket();
        let fits_soon = arrive(&mut queue, t0, Some(t0 + ms(60)), Some(ms(10))).ticket();
        let cut_soon = arrive(&mut queue, t0, Some(t0 + ms(45)), Some(ms(300))).ticket();
        let unbounded = arrive(&mut queue, t0, None, Some(ms(1))).ticket();
        let untimed = arrive(&mut queue, t0, Some(t0 + ms(70)), None).ticket();
        queue.leave(heavy);
        assert_eq!(
            drain(&mut queue),
            [fits_soon, untimed, fits_late, cut_soon, unbounded]
        );
    }

    #[test]
    fn among_plans_that_will_be_cut_the_shortest_solve_goes_first() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut queue = PlanQueue::default();
        // On a loaded machine the light plan's estimate crosses its deadline too: it still goes
        // before the heavy one, although the heavy one's deadline is earlier.
        let heavy = arrive(&mut queue, t0, Some(t0 + ms(50)), Some(ms(300))).ticket();
        let light = arrive(&mut queue, t0, Some(t0 + ms(60)), Some(ms(70))).ticket();
        let heavy_later = arrive(&mut queue, t0, Some(t0 + ms(80)), Some(ms(300))).ticket();
        assert_eq!(drain(&mut queue), [light, heavy, heavy_later]);
    }
}
