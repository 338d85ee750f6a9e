//! One run's plans, batched: the observations of several agents that wait at the same time
//! are planned in one solve ([`MpcPlanner::plan_batch`]), their CEM populations imagined as
//! one batch through the networks, and each agent is answered with its own action.
//!
//! A vector environment sends the observations of all its copies before it waits for their
//! actions, so they reach their workers within a millisecond or two of each other. Each
//! worker hands its planner and observation to the run's [`PlanBatcher`]; the first starts a
//! *drain* on the blocking pool, which takes every request waiting when it starts. Before it
//! does, it lingers while an agent that was answered mid-episode has not sent its next
//! observation yet (at most [`GATHER_QUIET`] after the latest arrival, [`GATHER_MAX`] in all,
//! and never more than a tenth of the time left to the earliest deadline), so that a vector
//! env's copies plan together instead of one first and the rest after it. Requests that
//! arrive while a batch plans make the next batch.
//!
//! A batch takes the cores as one plan ([`Scheduler::turn`]) with the urgency of its most
//! urgent request (the earliest deadline) and the sum of its members' estimated solves; it
//! steps back for more urgent plans between imagined steps as a single plan does, and each
//! request's deadline cuts its own iterations (see [`crate::plan::sequence::solve_lockstep`]).
//! An agent's plans waiting in a batcher count in its queue depth until its batch holds the
//! cores.

use crate::plan::{MpcPlanner, PlanRequest, Workspace};
use crate::run::Run;
use crate::sched::{Scheduler, Waiting};
use std::panic::AssertUnwindSafe;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};
use tokio::sync::oneshot;

/// A drain waits at most this long after the latest arrival for agents still expected.
pub(crate) const GATHER_QUIET: Duration = Duration::from_millis(4);

/// A drain waits at most this long in all for agents still expected.
pub(crate) const GATHER_MAX: Duration = Duration::from_millis(20);

/// The batched plans of one run's agents.
pub(crate) struct PlanBatcher {
    run: Arc<Run>,
    scheduler: Arc<Scheduler>,
    pending: Mutex<Pending>,
    /// Signalled when a request arrives or an expected agent turns out to need no plan.
    arrived: Condvar,
    /// Where batches imagine; only the drain uses it.
    workspace: Mutex<Workspace>,
}

#[derive(Default)]
struct Pending {
    requests: Vec<Request>,
    /// A drain is running (it takes every request that arrives until it finds none).
    draining: bool,
    /// Agents answered mid-episode whose next observation has not reached the batcher.
    expected: usize,
    last_arrival: Option<Instant>,
}

/// One agent's observation to plan: its planner travels with it and comes back in the answer.
pub(crate) struct Request {
    pub planner: MpcPlanner,
    pub obs: Vec<f32>,
    /// When the plan must have ended (the run's deadline less the answer's margin).
    pub deadline: Option<Instant>,
    /// The agent's count of plans waiting for the cores.
    pub waiting: Waiting,
    pub reply: oneshot::Sender<Planned>,
}

/// The answer to one [`Request`].
pub(crate) struct Planned {
    pub planner: MpcPlanner,
    pub action: Vec<f32>,
    pub predicted_return: f32,
    pub mean_energy: f32,
    pub iterations: u32,
    pub cut: bool,
    /// Times the batch stepped back for a more urgent plan.
    pub stepped_back: u32,
    pub models_version: u64,
}

/// Whether an agent's next observation is expected by its run's batcher (it was answered
/// mid-episode); dropping it (the worker ending) withdraws the expectation.
pub(crate) struct Expected {
    batcher: Arc<PlanBatcher>,
    marked: bool,
}

impl Expected {
    pub(crate) fn new(batcher: Arc<PlanBatcher>) -> Self {
        Self {
            batcher,
            marked: false,
        }
    }

    pub(crate) fn batcher(&self) -> &Arc<PlanBatcher> {
        &self.batcher
    }

    /// Says whether the agent will send another observation of its episode.
    pub(crate) fn set(&mut self, expected: bool) {
        if expected != self.marked {
            let batcher = self.batcher.clone();
            let mut pending = batcher.lock();
            self.mark(&mut pending, expected);
            drop(pending);
            batcher.arrived.notify_all();
        }
    }

    fn mark(&mut self, pending: &mut Pending, expected: bool) {
        if expected && !self.marked {
            pending.expected += 1;
        } else if !expected && self.marked {
            pending.expected -= 1;
        }
        self.marked = expected;
    }
}

impl Drop for Expected {
    fn drop(&mut self) {
        self.set(false);
    }
}

impl PlanBatcher {
    pub(crate) fn new(run: Arc<Run>, scheduler: Arc<Scheduler>) -> Self {
        Self {
            run,
            scheduler,
            pending: Mutex::default(),
            arrived: Condvar::new(),
            workspace: Mutex::new(Workspace::new()),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Pending> {
        self.pending.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues `request` (its agent no longer expected) and starts a drain if none runs.
    pub(crate) fn submit(self: &Arc<Self>, request: Request, expected: &mut Expected) {
        request.waiting.add();
        let mut pending = self.lock();
        expected.mark(&mut pending, false);
        pending.requests.push(request);
        pending.last_arrival = Some(Instant::now());
        let start = !std::mem::replace(&mut pending.draining, true);
        drop(pending);
        self.arrived.notify_all();
        if start {
            let batcher = self.clone();
            tokio::task::spawn_blocking(move || batcher.drain());
        }
    }

    /// Plans batches until none is waiting.
    fn drain(self: Arc<Self>) {
        /// Lets the next submission start a drain even if this one panics.
        struct Draining<'a>(&'a PlanBatcher);
        impl Drop for Draining<'_> {
            fn drop(&mut self) {
                if std::thread::panicking() {
                    self.0.lock().draining = false;
                }
            }
        }
        let _draining = Draining(&self);
        loop {
            let Some(mut batch) = self.gather() else {
                return;
            };
            let deadline = batch.iter().filter_map(|r| r.deadline).min();
            let estimate = batch
                .iter()
                .map(|r| r.planner.estimated_solve())
                .sum::<Option<Duration>>();
            let turn = Arc::new(self.scheduler.turn(deadline, estimate, &Waiting::default()));
            // Whoever arrived while the batch waited for the cores joins it.
            batch.append(&mut self.lock().requests);
            for request in &batch {
                request.waiting.sub();
            }
            self.plan(batch, turn);
        }
    }

    /// The requests waiting now, after lingering for the agents still expected; `None` (and
    /// the drain over) when there are none.
    fn gather(&self) -> Option<Vec<Request>> {
        let started = Instant::now();
        let mut pending = self.lock();
        loop {
            if pending.requests.is_empty() {
                pending.draining = false;
                return None;
            }
            let now = Instant::now();
            let mut until = started + GATHER_MAX;
            if let Some(last) = pending.last_arrival {
                until = until.min(last + GATHER_QUIET);
            }
            if let Some(deadline) = pending.requests.iter().filter_map(|r| r.deadline).min() {
                until = until.min(started + deadline.saturating_duration_since(started) / 10);
            }
            if pending.expected == 0 || now >= until {
                return Some(std::mem::take(&mut pending.requests));
            }
            pending = self
                .arrived
                .wait_timeout(pending, until - now)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }

    /// Plans `batch` holding `turn`, and answers every request. A panic loses the batch's
    /// planners: their workers see the answer dropped and start over with fresh ones.
    fn plan(&self, mut batch: Vec<Request>, turn: Arc<crate::sched::Turn>) {
        let models = self.run.models();
        let started = Instant::now();
        let mut workspace = self
            .workspace
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let planned = std::panic::catch_unwind(AssertUnwindSafe(|| {
            let mut requests: Vec<PlanRequest<'_>> = batch
                .iter_mut()
                .map(|r| PlanRequest::new(&mut r.planner, &r.obs, r.deadline))
                .collect();
            MpcPlanner::plan_batch(
                &mut requests,
                &mut workspace,
                (&models.dynamics, &models.regularizer, models.learned()),
                Some(turn.clone()),
            );
        }));
        if let Err(panic) = planned {
            *workspace = Workspace::new();
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            tracing::error!(run = %self.run.name(), agents = batch.len(), panic = %what, "a batch of plans panicked");
            return;
        }
        drop(workspace);
        tracing::debug!(run = %self.run.name(), agents = batch.len(), ms = started.elapsed().as_secs_f64() * 1e3, "planned a batch");
        let stepped_back = turn.stepped_back();
        // The cores go to the next plan before the answers are sent.
        drop(turn);
        for request in batch {
            let outcome = request.planner.outcome();
            let planned = Planned {
                action: outcome.action.to_vec(),
                predicted_return: outcome.predicted_return,
                mean_energy: outcome.mean_energy,
                iterations: outcome.iterations,
                cut: outcome.cut,
                stepped_back,
                models_version: models.version,
                planner: request.planner,
            };
            // A worker that is gone (its agent reattached) no longer wants its answer.
            let _ = request.reply.send(planned);
        }
    }
}
