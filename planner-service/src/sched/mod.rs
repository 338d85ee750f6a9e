//! Sharing the cores between every run's plans and retrainings.
//!
//! Every plan spreads its population over the whole rayon pool, so plans take the cores one at
//! a time, in order of urgency (see [`queue`]): plans whose whole solve fits before their
//! deadline first, earliest deadline first; then plans that will be cut anyway, shortest solve
//! first; plans without a deadline last; first come, first served among equals. The plan holding the cores checks
//! between its optimiser's iterations, and between two imagined time steps within one, whether
//! a more urgent plan waits, and if so steps back into the queue until that one is done: a
//! light run's plan waits at most one imagined step of a heavy run's plan (about 2 ms for
//! half-cheetah + DEEN at the paper's sizes), never the whole plan. The time a plan spends
//! stepped back is not counted in its iteration timings (see [`crate::plan::anytime`]), but it
//! does count against its own deadline, which then cuts it.
//!
//! Retraining has minutes where a plan has milliseconds, so it yields: before each minibatch a
//! fit waits while any plan holds or waits for the cores, and runs in the idle time plans
//! leave. Its threads run at `SCHED_IDLE` (see [`background`]), so while plans never stop they
//! would get no core at all and a sync run would wait forever for its models. So the wait is
//! bounded by the retraining's guaranteed share of the cores ([`Scheduler::training_share`],
//! `retraining_share` in the configuration): after waiting `(1 − share) / share` times as long
//! as its last minibatch took (at most [`MAX_YIELD`]), a fit that still finds plans running
//! takes one minibatch's *slice*: it queues as the most urgent plan, the plan holding the
//! cores steps back at its next imagined step, and the minibatch runs while every plan waits.
//! Under continuous planning a retraining therefore gets about `share` of the time, and plans
//! the rest; `status` counts the slices and says while a retraining is starving (it needed a
//! slice within [`STARVING_WINDOW`]). The wait is between minibatches, never inside one.
//!
//! A minibatch holding a slice may wait inside it, in a rayon join of its products, and rayon
//! runs other jobs of the pool on a waiting thread: another run's retraining, or another
//! member of an ensemble. That fit's next minibatch then runs *on top of* the slice's own
//! stack, so it must not queue behind the slice (the slice could never end: a deadlock seen
//! with two ant runs retraining at once). A thread therefore knows the slice it holds
//! ([`Slice`]), and a minibatch started on top of it hands the slice back to any waiting plan
//! and takes it again, instead of waiting for itself.
//!
//! Limits: preemption happens only between imagined steps (Adam + DAE: between its gradient
//! steps), so a waiting plan can lose up to one of those, and a minibatch already running
//! finishes first (retraining runs on a pool of its own whose threads the OS runs only when no
//! plan wants a core, so that minibatch takes next to nothing from the plan: see
//! [`background`]). No
//! schedule makes an overloaded machine fit: when the deadlines ask for more than the cores
//! give (two half-cheetah + DEEN runs at 50 ms each on two cores), the deadlines decide how
//! much each plan gets, and the anytime planner cuts and reports the rest.

pub mod background;
mod preempt;
pub mod queue;

pub use preempt::Preempt;
use queue::PlanQueue;
use std::cell::RefCell;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// The longest a retraining waits for plans before one minibatch.
pub const MAX_YIELD: Duration = Duration::from_millis(200);

/// The share of the cores a retraining is guaranteed while plans leave it no idle time,
/// unless configured (`retraining_share`).
pub const DEFAULT_TRAINING_SHARE: f64 = 0.2;

/// A retraining counts as starving while it needed a slice this recently.
pub const STARVING_WINDOW: Duration = Duration::from_secs(5);

/// The daemon's plan queue; every run's plans and retrainings share one.
#[derive(Debug)]
pub struct Scheduler {
    queue: Mutex<PlanQueue>,
    /// Signalled whenever the holder changes or the queue empties.
    changed: Condvar,
    /// The share of the cores a retraining gets while plans never stop, in (0, 1].
    training_share: f64,
    /// Minibatches retrainings ran in a slice taken from plans (plans left no idle time).
    slices: AtomicU64,
    /// Nanoseconds retrainings waited for plans before their minibatches.
    training_waited_ns: AtomicU64,
    /// When a retraining last needed a slice.
    last_slice: Mutex<Option<Instant>>,
}

impl Default for Scheduler {
    fn default() -> Self {
        Self::new(DEFAULT_TRAINING_SHARE)
    }
}

/// How retrainings fared against the plans, for `status`.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
pub struct TrainingShare {
    /// The share of the cores a retraining is guaranteed while plans never stop.
    pub share: f64,
    /// Minibatches run in a slice taken from the plans, since the daemon started.
    pub slices: u64,
    /// Seconds retrainings waited for plans before their minibatches, since the daemon started.
    pub waited_seconds: f64,
    /// A retraining needed a slice within the last few seconds: plans leave it no idle time,
    /// and it advances at its guaranteed share only.
    pub starving: bool,
}

/// How many of one owner's plans (an agent's) wait for the cores now: queued, or stepped back
/// for a more urgent plan. The status report and the metrics read it as the agent's queue depth;
/// the scheduler keeps it, so it counts exactly the time a plan spends waiting in the queue.
#[derive(Clone, Debug, Default)]
pub struct Waiting(Arc<AtomicUsize>);

impl Waiting {
    pub fn get(&self) -> usize {
        self.0.load(Ordering::SeqCst)
    }

    pub(crate) fn add(&self) {
        self.0.fetch_add(1, Ordering::SeqCst);
    }

    pub(crate) fn sub(&self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

/// A plan's hold on the cores; dropping it ends the plan and hands them on.
#[must_use = "the plan holds the cores until the turn drops"]
#[derive(Debug)]
pub struct Turn {
    scheduler: Arc<Scheduler>,
    /// Its place in the queue; a retraining's slice renews it ([`Scheduler::renew_slice`]).
    ticket: Arc<AtomicU64>,
    /// Its owner's count of plans waiting, raised while this plan steps back.
    waiting: Waiting,
    /// Nanoseconds this plan has spent stepped back (see [`Preempt::paused`]).
    paused_ns: AtomicU64,
    /// Times this plan stepped back.
    step_backs: AtomicU32,
}

impl Scheduler {
    /// A scheduler that guarantees retraining `training_share` of the cores while plans never
    /// stop (clamped into [0.01, 1]).
    pub fn new(training_share: f64) -> Self {
        let share = if training_share.is_finite() {
            training_share.clamp(0.01, 1.0)
        } else {
            DEFAULT_TRAINING_SHARE
        };
        Self {
            queue: Mutex::default(),
            changed: Condvar::new(),
            training_share: share,
            slices: AtomicU64::new(0),
            training_waited_ns: AtomicU64::new(0),
            last_slice: Mutex::new(None),
        }
    }

    /// The share of the cores a retraining is guaranteed while plans never stop.
    pub fn training_share(&self) -> f64 {
        self.training_share
    }

    /// Before a retraining's minibatch, whose previous one took `last`: waits while plans hold
    /// or wait for the cores, at most `(1 − share) / share` times `last` (within 1 ms and
    /// [`MAX_YIELD`]); if plans still want the cores then, blocks until the minibatch holds
    /// them as the most urgent plan and returns that turn, to be held for the minibatch
    /// (`None`: the plans left idle time, and the minibatch runs in it, or the minibatch runs
    /// on top of a slice its thread already holds, which it renews: see the module doc).
    pub fn before_minibatch(self: &Arc<Self>, last: Duration) -> Option<Slice> {
        let patience = last
            .mul_f64((1.0 - self.training_share) / self.training_share)
            .clamp(Duration::from_millis(1), MAX_YIELD);
        if let Some(held) = HeldSlice::on_this_thread(self) {
            self.renew_slice(&held.ticket, patience);
            return None;
        }
        self.wait_for_plans_counted(patience);
        if self.lock().is_idle() {
            return None;
        }
        self.count_slice();
        // A deadline of now is overdue: the most urgent class, so the holder steps back.
        let turn = self.turn(Some(Instant::now()), None, &Waiting::default());
        Some(Slice::hold(self, turn))
    }

    /// A minibatch starts on top of the slice `ticket` its own thread holds: if plans wait,
    /// hands the cores to them, waits for them as a minibatch of its own would (at most
    /// `patience`) and queues again as the most urgent, storing the new place in `ticket`. It
    /// never waits behind `ticket` itself, which cannot end before this minibatch does.
    fn renew_slice(&self, ticket: &AtomicU64, patience: Duration) {
        {
            let mut queue = self.lock();
            if queue.waiting() == 0 {
                return;
            }
            queue.leave(ticket.load(Ordering::SeqCst));
        }
        self.changed.notify_all();
        self.wait_for_plans_counted(patience);
        self.count_slice();
        let mut queue = self.lock();
        let now = Instant::now();
        let renewed = queue.arrive(now, Some(now), None).ticket();
        // Stored before the wait: a panic unwinding from here still leaves the right ticket.
        ticket.store(renewed, Ordering::SeqCst);
        queue.dispatch();
        self.changed.notify_all();
        self.wait_to_hold(queue, renewed);
    }

    /// [`Scheduler::wait_for_plans`] for a retraining, counted in its waiting time.
    fn wait_for_plans_counted(&self, patience: Duration) {
        let waited = self.wait_for_plans(patience);
        self.training_waited_ns.fetch_add(
            u64::try_from(waited.as_nanos()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
    }

    /// Counts a slice a retraining takes from the plans.
    fn count_slice(&self) {
        self.slices.fetch_add(1, Ordering::Relaxed);
        *self
            .last_slice
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(Instant::now());
    }

    /// How retrainings fared against the plans.
    pub fn training(&self) -> TrainingShare {
        let last = *self
            .last_slice
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        TrainingShare {
            share: self.training_share,
            slices: self.slices.load(Ordering::Relaxed),
            waited_seconds: self.training_waited_ns.load(Ordering::Relaxed) as f64 * 1e-9,
            starving: last.is_some_and(|at| at.elapsed() < STARVING_WINDOW),
        }
    }

    fn lock(&self) -> MutexGuard<'_, PlanQueue> {
        self.queue.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Blocks until `queue` says `ticket` holds the cores.
    fn wait_to_hold<'q>(&'q self, mut queue: MutexGuard<'q, PlanQueue>, ticket: u64) {
        while !queue.holds(ticket) {
            queue = self
                .changed
                .wait(queue)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }

    /// Queues a plan that must end by `deadline`, whose whole solve its planner expects to take
    /// `estimate` on the cores alone (`None`: not timed yet), and blocks the calling thread until
    /// the plan holds the cores; `waiting` (its owner's count) counts it meanwhile.
    pub fn turn(
        self: &Arc<Self>,
        deadline: Option<Instant>,
        estimate: Option<Duration>,
        waiting: &Waiting,
    ) -> Turn {
        let mut queue = self.lock();
        let ticket = queue.arrive(Instant::now(), deadline, estimate).ticket();
        queue.dispatch();
        self.changed.notify_all();
        waiting.add();
        self.wait_to_hold(queue, ticket);
        waiting.sub();
        Turn {
            scheduler: self.clone(),
            ticket: Arc::new(AtomicU64::new(ticket)),
            waiting: waiting.clone(),
            paused_ns: AtomicU64::new(0),
            step_backs: AtomicU32::new(0),
        }
    }

    /// Plans waiting for the cores now (not counting the one holding them).
    pub fn waiting(&self) -> usize {
        self.lock().waiting()
    }

    /// Waits (blocking the calling thread) until no plan holds or waits for the cores, or
    /// `max` has passed. Returns how long it waited.
    pub fn wait_for_plans(&self, max: Duration) -> Duration {
        let start = Instant::now();
        let queue = self.lock();
        let _queue = self
            .changed
            .wait_timeout_while(queue, max, |q| !q.is_idle())
            .unwrap_or_else(PoisonError::into_inner);
        start.elapsed()
    }
}

impl Turn {
    /// Between two iterations or two imagined steps: if a more urgent plan waits, steps back
    /// until it is done and this plan is the most urgent again. Returns whether it stepped back.
    pub fn yield_to_earlier(&self) -> bool {
        let scheduler = &self.scheduler;
        let mut queue = scheduler.lock();
        if !queue.outranked() {
            return false;
        }
        let since = Instant::now();
        queue.preempt();
        scheduler.changed.notify_all();
        self.waiting.add();
        scheduler.wait_to_hold(queue, self.ticket.load(Ordering::SeqCst));
        self.waiting.sub();
        let paused = u64::try_from(since.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.paused_ns.fetch_add(paused, Ordering::SeqCst);
        self.step_backs.fetch_add(1, Ordering::SeqCst);
        true
    }

    /// Times this plan stepped back for a more urgent one so far.
    pub fn stepped_back(&self) -> u32 {
        self.step_backs.load(Ordering::SeqCst)
    }
}

impl Preempt for Turn {
    fn step_back(&self) {
        self.yield_to_earlier();
    }

    fn outranked(&self) -> bool {
        self.scheduler.lock().outranked()
    }

    fn paused(&self) -> Duration {
        Duration::from_nanos(self.paused_ns.load(Ordering::SeqCst))
    }
}

impl Drop for Turn {
    fn drop(&mut self) {
        self.scheduler
            .lock()
            .leave(self.ticket.load(Ordering::SeqCst));
        self.scheduler.changed.notify_all();
    }
}

thread_local! {
    /// The retraining slice this thread holds, if any.
    static HELD: RefCell<Option<HeldSlice>> = const { RefCell::new(None) };
}

/// Which slice a thread holds: its scheduler and its (renewable) place in the queue.
#[derive(Clone, Debug)]
struct HeldSlice {
    scheduler: Arc<Scheduler>,
    ticket: Arc<AtomicU64>,
}

impl HeldSlice {
    /// The slice of `scheduler` this thread holds, if any.
    fn on_this_thread(scheduler: &Arc<Scheduler>) -> Option<Self> {
        HELD.with(|held| {
            held.borrow()
                .as_ref()
                .filter(|h| Arc::ptr_eq(&h.scheduler, scheduler))
                .cloned()
        })
    }
}

/// A retraining minibatch's hold on the cores, taken from plans that left it no idle time.
/// While it lives its thread is marked as holding it, so that a fit rayon runs on this thread
/// meanwhile renews it rather than queueing behind it (see the module doc); dropping it hands
/// the cores on and restores the mark of any slice beneath it.
#[must_use = "the minibatch holds the cores until the slice drops"]
#[derive(Debug)]
pub struct Slice {
    /// Held until the slice drops (after [`Slice`]'s own `drop`, which restores the mark).
    _turn: Turn,
    beneath: Option<HeldSlice>,
}

impl Slice {
    fn hold(scheduler: &Arc<Scheduler>, turn: Turn) -> Self {
        let mine = HeldSlice {
            scheduler: scheduler.clone(),
            ticket: turn.ticket.clone(),
        };
        let beneath = HELD.with(|held| held.borrow_mut().replace(mine));
        Self {
            _turn: turn,
            beneath,
        }
    }
}

impl Drop for Slice {
    fn drop(&mut self) {
        let beneath = self.beneath.take();
        HELD.with(|held| *held.borrow_mut() = beneath);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

    /// Spins (without timing anything) until `n` plans wait.
    fn until_waiting(scheduler: &Scheduler, n: usize) {
        while scheduler.waiting() != n {
            std::thread::yield_now();
        }
    }

    #[test]
    fn waiting_plans_get_the_cores_by_earliest_deadline() {
        let scheduler = Arc::new(Scheduler::default());
        let t0 = Instant::now();
        let holder = scheduler.turn(None, None, &Waiting::default());
        let order = Arc::new(Mutex::new(vec![]));
        let mut threads = vec![];
        // Queued one after the other, latest deadline first.
        for (i, deadline) in [Some(900), None, Some(300), Some(100)]
            .into_iter()
            .enumerate()
        {
            let (queued, order) = (scheduler.clone(), order.clone());
            threads.push(std::thread::spawn(move || {
                let _turn = queued.turn(
                    deadline.map(|ms| t0 + Duration::from_millis(ms)),
                    None,
                    &Waiting::default(),
                );
                order.lock().unwrap().push(deadline);
            }));
            until_waiting(&scheduler, i + 1);
        }
        drop(holder);
        threads.into_iter().for_each(|t| t.join().unwrap());
        assert_eq!(
            *order.lock().unwrap(),
            [Some(100), Some(300), Some(900), None]
        );
    }

    #[test]
    fn the_holder_steps_back_for_a_more_urgent_plan() {
        let scheduler = Arc::new(Scheduler::default());
        let heavy_waiting = Waiting::default();
        let heavy = scheduler.turn(None, None, &heavy_waiting);
        assert!(!heavy.yield_to_earlier(), "nobody waits");
        assert_eq!(heavy_waiting.get(), 0, "the holder does not wait");
        let light_done = Arc::new(AtomicBool::new(false));
        let light_waiting = Waiting::default();
        let light = std::thread::spawn({
            let (scheduler, light_done) = (scheduler.clone(), light_done.clone());
            let light_waiting = light_waiting.clone();
            move || {
                let _turn = scheduler.turn(
                    Some(Instant::now() + Duration::from_millis(40)),
                    None,
                    &light_waiting,
                );
                light_done.store(true, Ordering::SeqCst);
            }
        });
        until_waiting(&scheduler, 1);
        // The light plan waits behind the holder, and its owner's count says so.
        while light_waiting.get() != 1 {
            std::thread::yield_now();
        }
        // The heavy plan's next iteration boundary: it resumes only after the light plan ran.
        assert!(heavy.yield_to_earlier());
        assert!(light_done.load(Ordering::SeqCst));
        assert_eq!(heavy.stepped_back(), 1);
        light.join().unwrap();
        assert_eq!((light_waiting.get(), heavy_waiting.get()), (0, 0));
        assert!(!heavy.yield_to_earlier());
    }

    #[test]
    fn training_waits_while_a_plan_holds_or_waits() {
        let scheduler = Arc::new(Scheduler::default());
        // Nothing queued: the wait returns at once (else this test would hang 10 min).
        scheduler.wait_for_plans(Duration::from_secs(600));
        let ended = Arc::new(AtomicBool::new(false));
        let plan = scheduler.turn(None, None, &Waiting::default());
        let waiter = std::thread::spawn({
            let (scheduler, ended) = (scheduler.clone(), ended.clone());
            move || {
                scheduler.wait_for_plans(Duration::from_secs(600));
                // The wait ends only after the plan did.
                assert!(ended.load(Ordering::SeqCst));
            }
        });
        std::thread::sleep(Duration::from_millis(20));
        ended.store(true, Ordering::SeqCst);
        drop(plan);
        waiter.join().unwrap();
    }

    /// While plans never stop, a retraining's minibatch still runs: after a wait bounded by
    /// its share it takes the cores from the plans (the holder steps back at its next step),
    /// and `training` says it is starving.
    #[test]
    fn a_retraining_takes_its_share_from_plans_that_never_stop() {
        let scheduler = Arc::new(Scheduler::new(0.5));
        assert_eq!(
            scheduler
                .before_minibatch(Duration::from_millis(5))
                .map(|_| ()),
            None
        );
        assert!(
            !scheduler.training().starving,
            "idle plans: no slice needed"
        );
        let stop = Arc::new(AtomicBool::new(false));
        let planner = std::thread::spawn({
            let (scheduler, stop) = (scheduler.clone(), stop.clone());
            move || {
                // A plan holding the cores for ever, stepping back when outranked.
                let turn = scheduler.turn(None, None, &Waiting::default());
                let mut stepped_back = 0;
                while !stop.load(Ordering::SeqCst) {
                    stepped_back += u32::from(turn.yield_to_earlier());
                    std::thread::yield_now();
                }
                stepped_back
            }
        });
        while scheduler.lock().is_idle() {
            std::thread::yield_now();
        }
        let started = Instant::now();
        let slice = scheduler.before_minibatch(Duration::from_millis(5));
        assert!(slice.is_some(), "the minibatch holds the cores");
        // It waited about as long as the minibatch takes (share 0.5), far from for ever.
        assert!(started.elapsed() < Duration::from_secs(5));
        let training = scheduler.training();
        assert_eq!(training.slices, 1);
        assert!(training.starving);
        assert!(training.waited_seconds >= 0.004, "{training:?}");
        drop(slice);
        stop.store(true, Ordering::SeqCst);
        assert!(planner.join().unwrap() >= 1, "the plan stepped back");
    }

    #[test]
    fn a_wait_is_bounded_while_plans_never_stop() {
        let scheduler = Arc::new(Scheduler::default());
        let _plan = scheduler.turn(None, None, &Waiting::default());
        // The plan never ends: the wait gives up after its bound.
        assert!(scheduler.wait_for_plans(Duration::from_millis(20)) >= Duration::from_millis(20));
    }

    /// What rayon does to a retraining holding a slice: while its minibatch waits in a join,
    /// its thread runs another fit's job, whose next minibatch starts on top of the slice.
    /// That minibatch must neither wait behind the slice beneath it (which cannot end first:
    /// the daemon hung so, two ant runs retraining at once) nor keep the cores from a plan
    /// that waits: it hands them to the plan and takes them back.
    #[test]
    fn a_minibatch_on_top_of_its_threads_slice_renews_it_instead_of_waiting_behind_it() {
        let scheduler = Arc::new(Scheduler::new(0.5));
        let stop = Arc::new(AtomicBool::new(false));
        // Imagined steps the plans took, counted while they hold the cores.
        let plan_steps = Arc::new(AtomicUsize::new(0));
        // Plans that never stop, each stepping back whenever something more urgent waits.
        let planner = std::thread::spawn({
            let (scheduler, stop, steps) = (scheduler.clone(), stop.clone(), plan_steps.clone());
            move || {
                while !stop.load(Ordering::SeqCst) {
                    let turn = scheduler.turn(
                        Some(Instant::now() + Duration::from_millis(50)),
                        None,
                        &Waiting::default(),
                    );
                    for _ in 0..5 {
                        steps.fetch_add(1, Ordering::SeqCst);
                        std::thread::sleep(Duration::from_millis(1));
                        turn.yield_to_earlier();
                    }
                }
            }
        });
        while plan_steps.load(Ordering::SeqCst) == 0 {
            std::thread::yield_now();
        }
        let (done, finished) = std::sync::mpsc::channel();
        std::thread::spawn({
            let (scheduler, steps) = (scheduler.clone(), plan_steps.clone());
            move || {
                let slice = scheduler.before_minibatch(Duration::from_millis(1));
                assert!(
                    slice.is_some(),
                    "plans never stop: the minibatch takes a slice"
                );
                // The plan stepped back for the slice and waits.
                assert_eq!(scheduler.waiting(), 1);
                let before = steps.load(Ordering::SeqCst);
                // The nested fit's minibatch.
                let nested = scheduler.before_minibatch(Duration::from_millis(1));
                assert!(nested.is_none(), "it runs under the renewed slice");
                let after = steps.load(Ordering::SeqCst);
                drop(slice);
                assert!(HeldSlice::on_this_thread(&scheduler).is_none());
                done.send(after > before).unwrap();
            }
        });
        let plan_ran_between = finished
            .recv_timeout(Duration::from_secs(60))
            .expect("the nested minibatch waited behind its own thread's slice");
        assert!(
            plan_ran_between,
            "the waiting plan got the cores in between"
        );
        stop.store(true, Ordering::SeqCst);
        planner.join().unwrap();
        assert!(scheduler.training().slices >= 2);
    }
}
