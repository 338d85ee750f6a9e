//! The planning loop allocates nothing: a counting global allocator watches full `plan` calls
//! with real (tiny) networks, an ensemble with sampled particles, and a DEEN, for CEM, iCEM and
//! Adam (whose back-propagation through the horizon keeps one training tape per step), with the
//! task's own reward, with a learned reward and termination (a reward model scoring and a
//! termination model classifying every imagined step) and with a reward and a termination
//! written as formulas.
//!
//! The planner's own buffers and the networks' scratch are allocated when the planner is built
//! and on its first call with a model; rayon's pool and gemm-free kernels need nothing per call.
//! The networks' packed inference weights are made once per model (on its first forward pass,
//! or ahead of time with `Mlp::pack_for_inference`), so a newly trained model of the same
//! shapes, packed before it is handed over, plans without allocating from its first call.
//! The calls run inside a rayon pool, as the service runs them: a call from a thread outside
//! the pool goes through rayon's global job injector, a queue that allocates a block every 63
//! injected jobs. That allocation belongs to rayon, not to the planner, and is why the test
//! counts inside the pool.
//!
//! Only the pool's threads are watched: the planner runs on them and nowhere else, while other
//! threads of the process allocate for reasons of their own at any time — the test harness
//! prints a notice when a test runs over 60 seconds (it does on a loaded machine), and a
//! thread exiting hands its unreclaimed garbage to crossbeam-epoch's global queue. One pool
//! serves every case, so no thread of an earlier case's pool is still exiting.
//!
//! This file holds a single test so no other test's allocations can interleave with the count.

use planner_service::data::Transitions;
use planner_service::dynamics::{DynamicsConfig, Ensemble};
use planner_service::energy::{EnergyConfig, Regularizer, RegularizerKind};
use planner_service::nn::KernelPath;
use planner_service::plan::{CemConfig, IcemConfig, Learned, MpcPlanner, Optimizer, PlanRequest};
use planner_service::reward::{RewardConfig, RewardModel};
use planner_service::sched::Preempt;
use planner_service::termination::TerminationModel;
use proto::task::{RewardKind, SpecBounds, TerminationKind};
use proto::{Builtin, InferencePrecision, Task};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// Counts allocations (and reallocations) while `COUNTING` is on, on the watched threads.
struct CountingAllocator;

static COUNTING: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    /// Set on the planning pool's threads when they start (no destructor, so the allocator may
    /// read it at any point of a thread's life).
    static WATCHED: Cell<bool> = const { Cell::new(false) };
}

/// Whether an allocation now counts.
fn counted() -> bool {
    COUNTING.load(Ordering::Relaxed) && WATCHED.with(Cell::get)
}

// SAFETY: every method forwards to the system allocator unchanged; the counters are atomics.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if counted() {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if counted() {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        // SAFETY: forwarded with the caller's layout.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if counted() {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        // SAFETY: forwarded unchanged; the caller upholds `realloc`'s contract.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// Random transitions of the task: enough for the models' normalisers and a brief fit.
/// A scheduler with no rival plan: offered every pause, never takes one.
#[derive(Debug)]
struct NeverPaused;

impl Preempt for NeverPaused {
    fn step_back(&self) {}

    fn paused(&self) -> std::time::Duration {
        std::time::Duration::ZERO
    }
}

fn random_transitions(spec: &Task, n: usize, rng: &mut StdRng) -> Transitions {
    let mut data = Transitions::new(spec.obs_dim, spec.act_dim);
    for _ in 0..n {
        let obs: Vec<f32> = (0..spec.obs_dim)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let act: Vec<f32> = (0..spec.act_dim)
            .map(|d| rng.random_range(spec.action_low[d]..spec.action_high[d]))
            .collect();
        let next: Vec<f32> = obs
            .iter()
            .map(|o| o + 0.1 * rng.random_range(-1.0f32..1.0))
            .collect();
        let reward = next.iter().sum::<f32>() - act.iter().map(|a| a * a).sum::<f32>();
        data.push(&obs, &act, reward, &next);
        if next[0] < -0.5 {
            data.mark_terminated(data.len() - 1);
        }
    }
    data
}

/// Packs every network of the models ahead of planning (what a trainer does before publishing).
fn pack(dynamics: &Ensemble, regularizer: &Regularizer, learned: Learned<'_>) {
    if let Some(model) = learned.reward {
        model.mlp().pack_for_inference();
    }
    if let Some(model) = learned.termination {
        model.mlp().pack_for_inference();
    }
    for i in 0..dynamics.members() {
        dynamics.member(i).mlp().pack_for_inference();
    }
    match regularizer {
        Regularizer::None => {}
        Regularizer::Dae(m) => m.mlp().pack_for_inference(),
        Regularizer::Deen(m) => m.mlp().pack_for_inference(),
    }
}

/// Every number format (bf16 is f32 where the CPU lacks AVX-512 BF16; auto measures the
/// paths when the networks are packed, before the count) and every kernel path this CPU has
/// (AMX tiles, AVX-512 BF16, AVX-512 / AVX2 f32, scalar), one after the other: the
/// allocation counter is global, so no other test may run beside this one.
#[test]
fn planning_allocates_nothing_after_warm_up() {
    // Ant: the task with termination, so that path is exercised too; ant with its reward and
    // termination learned, planned with a reward and a termination model; and ant with its reward and termination written as
    // formulas, evaluated for the population by the expression language's block evaluator.
    let mut learned = Builtin::Ant.spec();
    learned.name = "ant-learned-reward-and-end".into();
    learned.reward = RewardKind::Learned;
    learned.termination = TerminationKind::Learned;
    let learned = Task::intern(learned, &SpecBounds::default()).unwrap();
    let mut formulas = Builtin::Ant.spec();
    formulas.name = "ant-formulas".into();
    formulas.reward = RewardKind::Expression("s_next[13] - 0.5*dot(a, a) + 1".into());
    formulas.termination =
        TerminationKind::Expression("!(s_next[0] >= 0.2 && s_next[0] <= 1)".into());
    let formulas = Task::intern(formulas, &SpecBounds::default()).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .start_handler(|_| WATCHED.with(|w| w.set(true)))
        .build()
        .unwrap();
    for spec in [Builtin::Ant.task(), learned, formulas] {
        for optimizer in [Optimizer::Cem, Optimizer::Icem, Optimizer::Adam] {
            let precisions = [
                InferencePrecision::F32,
                InferencePrecision::Bf16,
                InferencePrecision::Auto,
            ];
            let settings = precisions
                .into_iter()
                .map(Inference::Precision)
                .chain(KernelPath::available().into_iter().map(Inference::Path));
            for setting in settings {
                allocates_nothing_after_warm_up_in(&pool, spec, optimizer, setting);
            }
        }
    }
}

/// How the networks run inference: a number format (its path chosen, by measurement for
/// `auto`, when the networks are packed) or each kernel path this CPU has, forced.
#[derive(Clone, Copy, Debug)]
enum Inference {
    Precision(InferencePrecision),
    Path(KernelPath),
}

impl Inference {
    fn apply(self, dynamics: &mut Ensemble, regularizer: &mut Regularizer) {
        match self {
            Inference::Precision(p) => {
                dynamics.set_inference_precision(p);
                regularizer.set_inference_precision(p);
            }
            Inference::Path(p) => {
                dynamics.set_kernel_path(p);
                regularizer.set_kernel_path(p);
            }
        }
    }

    fn apply_to_reward(self, model: &mut RewardModel) {
        match self {
            Inference::Precision(p) => model.set_inference_precision(p),
            Inference::Path(p) => model.set_kernel_path(p),
        }
    }

    fn apply_to_termination(self, model: &mut TerminationModel) {
        match self {
            Inference::Precision(p) => model.set_inference_precision(p),
            Inference::Path(p) => model.set_kernel_path(p),
        }
    }
}

/// A termination model for `spec` trained briefly on `data` (`None` unless its termination is
/// learned); `data` has ends, so it predicts with its network.
fn termination_model(
    spec: &'static Task,
    data: &Transitions,
    inference: Inference,
    rng: &mut StdRng,
) -> Option<TerminationModel> {
    spec.termination_is_learned().then(|| {
        let mut model = TerminationModel::new(spec, &DynamicsConfig::default(), rng);
        model.fit(data, 1, rng);
        assert!(model.knows_ends());
        inference.apply_to_termination(&mut model);
        model
    })
}

/// A reward model for `spec` trained briefly on `data` (`None` unless its reward is learned).
fn reward_model(
    spec: &'static Task,
    data: &Transitions,
    inference: Inference,
    rng: &mut StdRng,
) -> Option<RewardModel> {
    spec.reward_is_learned().then(|| {
        let sizes = RewardConfig {
            hidden_layers: 2,
            hidden_size: 24,
        };
        let mut model = RewardModel::new(spec, &sizes, &DynamicsConfig::default(), rng);
        model.fit(data, 1, rng);
        inference.apply_to_reward(&mut model);
        model
    })
}

/// Every model a plan of `spec` may use, trained briefly (`epochs`) on `data`, running
/// `inference`: the dynamics ensemble, a DEEN, and the reward and termination models where
/// the task learns them.
struct Models {
    dynamics: Ensemble,
    deen: Regularizer,
    reward: Option<RewardModel>,
    termination: Option<TerminationModel>,
}

impl Models {
    fn trained(
        spec: &'static Task,
        data: &Transitions,
        epochs: usize,
        inference: Inference,
        rng: &mut StdRng,
    ) -> Self {
        let dynamics_config = DynamicsConfig {
            hidden_layers: 2,
            hidden_size: 32,
            ensemble_size: 3,
            ..Default::default()
        };
        let mut dynamics = Ensemble::new(spec, &dynamics_config, rng);
        dynamics.fit(data, epochs, rng);
        let energy_config = EnergyConfig {
            hidden_layers: 2,
            hidden_size: 24,
            ..Default::default()
        };
        let (obs_dim, act_dim) = (spec.obs_dim, spec.act_dim);
        let mut deen =
            Regularizer::new(RegularizerKind::Deen, &energy_config, obs_dim, act_dim, rng);
        deen.fit(data, epochs, rng);
        inference.apply(&mut dynamics, &mut deen);
        Self {
            dynamics,
            deen,
            reward: reward_model(spec, data, inference, rng),
            termination: termination_model(spec, data, inference, rng),
        }
    }
}

/// The learned parts of a plan: whichever of the two models exist.
fn learned_parts<'a>(
    reward: &'a Option<RewardModel>,
    termination: &'a Option<TerminationModel>,
) -> Learned<'a> {
    Learned {
        reward: reward.as_ref(),
        termination: termination.as_ref(),
    }
}

fn allocates_nothing_after_warm_up_in(
    pool: &rayon::ThreadPool,
    spec: &'static Task,
    optimizer: Optimizer,
    inference: Inference,
) {
    let mut rng = StdRng::seed_from_u64(0);
    let data = random_transitions(spec, 256, &mut rng);
    let Models {
        dynamics,
        deen,
        reward,
        termination,
    } = Models::trained(spec, &data, 1, inference, &mut rng);
    let learned = learned_parts(&reward, &termination);

    let cem = CemConfig {
        horizon: 7,
        population: 50,
        elites: 5,
        iterations: 3,
        smoothing: 0.1,
        min_variance: 1e-3,
        particles: 4,
        optimizer,
        icem: IcemConfig::default(),
        adam: planner_service::plan::AdamConfig::default(),
    };
    let mut planner = MpcPlanner::with_chunks(spec, cem, 0.05, true, 7, 2).unwrap();
    let obs: Vec<f32> = (0..spec.obs_dim)
        .map(|i| if i == 0 { 0.55 } else { 0.01 * i as f32 })
        .collect();

    let preempt: std::sync::Arc<dyn Preempt> = std::sync::Arc::new(NeverPaused);
    let (allocations, checksum) = pool.install(|| {
        // Warm-up: the first calls create the network scratch; every worker thread runs a
        // chunk at least once.
        for _ in 0..10 {
            planner.plan(&obs, &dynamics, &deen, learned, None);
        }
        planner.reset();
        ALLOCATIONS.store(0, Ordering::SeqCst);
        COUNTING.store(true, Ordering::SeqCst);
        let mut checksum = 0.0;
        // Planning against a deadline reads the clock and allocates nothing either (this one
        // is far enough away not to bind, so the checksum is the seed's alone).
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(3600);
        for _ in 0..5 {
            let outcome = planner.plan(&obs, &dynamics, &deen, learned, Some(deadline));
            checksum += outcome.action[0] + outcome.predicted_return + outcome.mean_energy;
        }
        // Nor does a plan sharing the cores, offered a pause between every imagined step.
        for _ in 0..2 {
            let shared = Some(preempt.clone());
            let outcome =
                planner.plan_shared(&obs, &dynamics, &deen, learned, Some(deadline), shared);
            checksum += outcome.action[0] + outcome.predicted_return + outcome.mean_energy;
        }
        COUNTING.store(false, Ordering::SeqCst);
        (ALLOCATIONS.load(Ordering::SeqCst), checksum)
    });
    assert!(checksum.is_finite(), "the plans were real: {checksum}");
    assert_eq!(
        allocations,
        0,
        "{}: allocations during 5 planning calls",
        spec.name()
    );

    // A batch of agents planning together in a shared workspace: once it has served a batch
    // of three, batches of three and of fewer allocate nothing either.
    let mut agents: Vec<MpcPlanner> = (0..3)
        .map(|k| MpcPlanner::with_chunks(spec, planner.config().clone(), 0.05, true, 20 + k, 2))
        .collect::<Result<_, _>>()
        .unwrap();
    let mut workspace = planner_service::plan::Workspace::new();
    let (allocations, checksum) = pool.install(|| {
        let mut batch_of = |agents: &mut [MpcPlanner]| -> f32 {
            let [a, b, c] = agents else {
                unreachable!("three agents")
            };
            let mut requests = [
                PlanRequest::new(a, &obs, None),
                PlanRequest::new(b, &obs, None),
                PlanRequest::new(c, &obs, None),
            ];
            let models = (&dynamics, &deen, learned);
            MpcPlanner::plan_batch(&mut requests, &mut workspace, models, None);
            let mut sum = 0.0;
            for r in &requests {
                sum += r.outcome().action[0] + r.outcome().predicted_return;
            }
            MpcPlanner::plan_batch(&mut requests[..2], &mut workspace, models, None);
            sum + requests[1].outcome().action[0]
        };
        for _ in 0..3 {
            batch_of(&mut agents);
        }
        ALLOCATIONS.store(0, Ordering::SeqCst);
        COUNTING.store(true, Ordering::SeqCst);
        let mut checksum = 0.0;
        for _ in 0..3 {
            checksum += batch_of(&mut agents);
        }
        COUNTING.store(false, Ordering::SeqCst);
        (ALLOCATIONS.load(Ordering::SeqCst), checksum)
    });
    assert!(checksum.is_finite(), "the batches were real: {checksum}");
    assert_eq!(
        allocations,
        0,
        "{}: allocations during batched planning calls",
        spec.name()
    );

    // A retrained model of the same shapes, packed before the swap, plans without allocating
    // from its very first call.
    let Models {
        dynamics,
        deen,
        reward,
        termination,
    } = Models::trained(spec, &data, 2, inference, &mut rng);
    let learned = learned_parts(&reward, &termination);
    pack(&dynamics, &deen, learned);
    let (allocations, outcome) = pool.install(|| {
        ALLOCATIONS.store(0, Ordering::SeqCst);
        COUNTING.store(true, Ordering::SeqCst);
        let outcome = planner
            .plan(&obs, &dynamics, &deen, learned, None)
            .predicted_return;
        COUNTING.store(false, Ordering::SeqCst);
        (ALLOCATIONS.load(Ordering::SeqCst), outcome)
    });
    assert!(outcome.is_finite());
    assert_eq!(
        allocations, 0,
        "allocations in the first call with new models"
    );

    // The counter does see allocations, so a zero above is meaningful.
    let (allocations, plan) = pool.install(|| {
        ALLOCATIONS.store(0, Ordering::SeqCst);
        COUNTING.store(true, Ordering::SeqCst);
        let plan = planner.imagine_plan(&obs, &dynamics, &deen, learned);
        COUNTING.store(false, Ordering::SeqCst);
        (ALLOCATIONS.load(Ordering::SeqCst), plan)
    });
    assert_eq!(plan.actions.len(), 7 * spec.act_dim);
    assert!(allocations > 0);
}
