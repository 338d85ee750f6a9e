//! The per-agent model-predictive controller: CEM over imagined returns, warm-started from
//! the previous step's plan, applying only the first action (PETS' `MPC.act`).

use super::Learned;
use crate::dynamics::Ensemble;
use crate::energy::Regularizer;
use crate::plan::anytime::IterationClock;
use crate::plan::imagine::{Imagination, Rollout, Rollouts, Workspace, evaluate_batch};
use crate::plan::search::Search;
use crate::plan::sequence::{Lockstep, LockstepMember, SteppedSearch, solve_lockstep};
use crate::plan::settings::{CemConfig, ConfigError};
use crate::sched::Preempt;
use proto::Task;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// One agent's planner. Owns the optimiser's distribution (the warm start), its random state
/// and (for its solo plans) the imagination's buffers, so planning allocates nothing.
///
/// Several agents of one run plan together with [`MpcPlanner::plan_batch`]: their CEM (or
/// iCEM) solves run in lockstep, and each iteration imagines all their populations as one
/// batch through the networks. [`MpcPlanner::plan`] is the batch of one.
pub struct MpcPlanner {
    task: &'static Task,
    /// CEM, iCEM or Adam, as the configuration says.
    search: Search,
    imagination: Imagination,
    /// The action chosen by the last [`MpcPlanner::plan`] (the warm start has moved on since).
    action: Vec<f32>,
    /// This agent's iteration timings, which decide how many iterations fit a deadline.
    clock: IterationClock,
    /// What the last solve did.
    solved: Solved,
}

/// The statistics of the last solve (see [`PlanOutcome`]).
#[derive(Clone, Copy, Debug)]
struct Solved {
    predicted_return: f32,
    mean_energy: f32,
    iterations: u32,
    cut: bool,
}

/// One agent's observation in a batch of plans ([`MpcPlanner::plan_batch`]): its planner, the
/// observation and when the answer is due.
pub struct PlanRequest<'a> {
    planner: &'a mut MpcPlanner,
    obs: &'a [f32],
    deadline: Option<Instant>,
    step: Lockstep,
}

impl<'a> PlanRequest<'a> {
    pub fn new(planner: &'a mut MpcPlanner, obs: &'a [f32], deadline: Option<Instant>) -> Self {
        Self {
            planner,
            obs,
            deadline,
            step: Lockstep::default(),
        }
    }

    /// The planner's answer, after [`MpcPlanner::plan_batch`].
    pub fn outcome(&self) -> PlanOutcome<'_> {
        self.planner.outcome()
    }
}

impl LockstepMember for PlanRequest<'_> {
    fn parts(
        &mut self,
    ) -> (
        Option<&mut dyn SteppedSearch>,
        &mut IterationClock,
        &mut Lockstep,
    ) {
        let planner = &mut *self.planner;
        (planner.search.stepped(), &mut planner.clock, &mut self.step)
    }
}

impl Rollout for PlanRequest<'_> {
    fn rollouts(&mut self) -> Option<Rollouts<'_>> {
        if !self.step.joined {
            return None;
        }
        let planner = &mut *self.planner;
        let (actions, returns) = planner.search.stepped()?.drawn();
        Some(Rollouts {
            imagination: &mut planner.imagination,
            obs: self.obs,
            actions,
            returns,
        })
    }
}

/// The answer to one observation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanOutcome<'a> {
    /// The action to apply (`act_dim`, within the task's bounds).
    pub action: &'a [f32],
    /// Mean imagined regularised return of the last iteration's elites (`-inf` only if the
    /// model diverged on every elite).
    pub predicted_return: f32,
    /// Mean energy per imagined transition of those elites (0 without a regulariser).
    pub mean_energy: f32,
    /// Optimiser iterations run (fewer than configured after an early stop); 0 when the
    /// deadline left no time for one, and the action is the previous plan's next one.
    pub iterations: u32,
    /// Iterations were left out because the next one would have crossed the deadline.
    pub cut: bool,
}

/// A plan optimised from scratch, with what the model imagines it will earn step by step: the
/// material of the paper's Figure 5 (imagination against reality).
#[derive(Clone, Debug, PartialEq)]
pub struct ImaginedPlan {
    /// The planned actions, `horizon × act_dim`.
    pub actions: Vec<f32>,
    /// Imagined reward per step (mean over particles).
    pub rewards: Vec<f32>,
    /// Imagined energy per step (mean over particles; 0 without a regulariser).
    pub energies: Vec<f32>,
    /// The plan's regularised return `Σ (reward − α·energy)`.
    pub predicted_return: f32,
    /// CEM iterations run.
    pub iterations: u32,
}

/// Candidates a chunk keeps at least before [`default_chunks`] gives a thread a second chunk.
const MIN_SPLIT_CHUNK: usize = 12;

/// Threads from which [`default_chunks`] gives each thread two chunks.
const MIN_SPLIT_THREADS: usize = 4;

/// Population chunks planned in parallel by `threads` threads for `population` candidates:
/// two per thread from 4 threads up (`MIN_SPLIT_THREADS`) where each chunk still holds 12
/// candidates (`MIN_SPLIT_CHUNK`), else one.
///
/// A plan's CEM iteration ends when its slowest chunk does. The cores of a shared or virtual
/// machine do not run at one speed: on a 16-core Xeon (model 207, a virtual machine with nothing
/// else running) sixteen one-thread processes planning the same half-cheetah + DEEN call took
/// 326–898 ms each, against 324 ms for one alone. With one chunk per thread the join waits for
/// the slowest core; with two, rayon's work stealing hands the second chunks to the cores that
/// finished first: 16-thread plans were faster in 23 of 24 paired comparisons there (by up to
/// 37 %; half-cheetah, ant and cartpole + DEEN at Table 2's sizes, 12–16 candidates per
/// chunk). Chunks of 3 candidates (a population of 100 on 16 threads) made the products so
/// small that plans took 1.6–1.8× as long, hence the floor; and on 2 threads a second chunk's
/// effect on that Xeon was mixed and it cost cartpole + DEEN 3–7 % of its CPU time on a Zen 4,
/// hence the thread floor. See the performance page's "Sixteen cores".
pub fn default_chunks(threads: usize, population: usize) -> usize {
    if threads >= MIN_SPLIT_THREADS && population >= 2 * threads * MIN_SPLIT_CHUNK {
        2 * threads
    } else {
        threads.max(1)
    }
}

impl MpcPlanner {
    /// A planner for `task` that scores plans as `Σ reward − energy_weight · energy`, sampling
    /// the dynamics' predicted Gaussian when `sample` is set (PETS TS∞), else using its mean.
    /// The population is split into [`default_chunks`] of the rayon threads; `seed` fixes every
    /// random choice.
    pub fn new(
        task: &'static Task,
        config: CemConfig,
        energy_weight: f32,
        sample: bool,
        seed: u64,
    ) -> Result<Self, ConfigError> {
        let chunks = default_chunks(rayon::current_num_threads(), config.population);
        Self::with_chunks(task, config, energy_weight, sample, seed, chunks)
    }

    /// As [`MpcPlanner::new`], with the population split into `chunks` parallel chunks.
    /// Results depend on the seed and the chunk count, not on the thread that runs a chunk.
    pub fn with_chunks(
        task: &'static Task,
        config: CemConfig,
        energy_weight: f32,
        sample: bool,
        seed: u64,
        chunks: usize,
    ) -> Result<Self, ConfigError> {
        if !(energy_weight.is_finite() && energy_weight >= 0.0) {
            return Err(ConfigError::EnergyWeight(energy_weight));
        }
        let search = Search::new(task, config, energy_weight, seed)?;
        let imagination = Imagination::new(
            task,
            search.config(),
            energy_weight,
            sample,
            chunks,
            seed.wrapping_add(1),
        );
        Ok(Self {
            task,
            search,
            imagination,
            action: vec![0.0; task.act_dim],
            clock: IterationClock::default(),
            solved: Solved {
                predicted_return: f32::NEG_INFINITY,
                mean_energy: 0.0,
                iterations: 0,
                cut: false,
            },
        })
    }

    pub fn task(&self) -> &'static Task {
        self.task
    }

    pub fn config(&self) -> &CemConfig {
        self.search.config()
    }

    /// Forgets the warm start; call at the start of an episode.
    pub fn reset(&mut self) {
        self.search.reset();
    }

    /// Plans from `obs` and returns the first action of the best plan found. The rest of the
    /// plan, shifted by one step, warm-starts the next call.
    ///
    /// With a `deadline`, iterations stop when the next one would end after it (see
    /// [`IterationClock`]) and the best plan so far answers; when not even one fits, the
    /// answer is the previous plan's next action (the warm start), with no elites scored
    /// (`predicted_return` is `-inf`, `mean_energy` 0). Without one, every configured
    /// iteration runs, exactly as the seed dictates.
    ///
    /// `learned` holds the run's reward and termination models, each given exactly when the
    /// task learns that part (a planner of such a task has no other way to score a transition
    /// or to see an episode end).
    pub fn plan(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        deadline: Option<Instant>,
    ) -> PlanOutcome<'_> {
        self.plan_shared(obs, dynamics, regularizer, learned, deadline, None)
    }

    /// How long a whole solve is expected to take on the cores alone, from this planner's
    /// latest timed iteration (`None` before its first): the scheduler ranks plans that fit
    /// their deadline before plans that will be cut (see [`crate::sched::queue`]).
    pub fn estimated_solve(&self) -> Option<Duration> {
        let config = self.search.config();
        self.clock
            .estimate(config.candidates_scored(config.iterations))
    }

    /// [`MpcPlanner::plan`] on cores shared with other plans: `preempt` may pause the solve
    /// before each iteration, and between imagined steps within one, while a more urgent plan
    /// runs (see [`crate::sched`]). The batch of one, in this planner's own workspace.
    pub fn plan_shared(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        deadline: Option<Instant>,
        preempt: Option<Arc<dyn Preempt>>,
    ) -> PlanOutcome<'_> {
        let mut workspace = self.imagination.take_workspace();
        Self::plan_batch(
            &mut [PlanRequest::new(self, obs, deadline)],
            &mut workspace,
            (dynamics, regularizer, learned),
            preempt,
        );
        self.imagination.keep_workspace(workspace);
        self.outcome()
    }

    /// Plans every request of `batch` as [`MpcPlanner::plan_shared`] plans one, together:
    /// their CEM or iCEM solves run in lockstep, and each iteration imagines every agent's
    /// candidates in one pass through `workspace` (one matrix product per layer for them all;
    /// see [`crate::plan::imagine::evaluate_batch`]). Each agent's answer
    /// ([`PlanRequest::outcome`]) is exactly what planning it alone with the same random state
    /// gives, unless a deadline cut it. A request's iteration starts only when its deadline
    /// leaves room for the whole batch's iteration; one whose deadline does not is cut there,
    /// and the others go on. Adam (a gradient planner, no population to stack) solves each of
    /// its requests in turn.
    ///
    /// The requests must come from planners of one task and configuration (one run's agents).
    /// Allocates nothing once `workspace` has served a batch as large.
    pub fn plan_batch(
        batch: &mut [PlanRequest<'_>],
        workspace: &mut Workspace,
        models: (&Ensemble, &Regularizer, Learned<'_>),
        preempt: Option<Arc<dyn Preempt>>,
    ) {
        for request in batch.iter_mut() {
            request
                .planner
                .clock
                .start_shared(request.deadline, preempt.clone());
        }
        Self::solve(batch, workspace, models, preempt.as_deref());
        for request in batch.iter_mut() {
            let planner = &mut *request.planner;
            planner.clock.end();
            let act_dim = planner.task.act_dim;
            if planner.solved.iterations == 0 {
                planner
                    .action
                    .copy_from_slice(&planner.search.mean()[..act_dim]);
            } else {
                planner
                    .action
                    .copy_from_slice(planner.search.first_action());
            }
            planner.search.shift();
        }
    }

    /// One solve per request from its warm start (the clocks started), its statistics left in
    /// each planner.
    fn solve(
        batch: &mut [PlanRequest<'_>],
        workspace: &mut Workspace,
        (dynamics, regularizer, learned): (&Ensemble, &Regularizer, Learned<'_>),
        preempt: Option<&dyn Preempt>,
    ) {
        for request in batch.iter_mut() {
            let planner = &mut *request.planner;
            if let Some((outcome, mean_energy)) = planner.search.solve_gradient(
                request.obs,
                dynamics,
                regularizer,
                learned,
                &mut planner.clock,
            ) {
                planner.solved = Solved {
                    predicted_return: outcome.elite_return,
                    mean_energy,
                    iterations: outcome.iterations,
                    cut: outcome.cut,
                };
            }
        }
        solve_lockstep(batch, |members| {
            evaluate_batch(workspace, members, dynamics, regularizer, learned, preempt)
        });
        for request in batch.iter_mut() {
            let planner = &mut *request.planner;
            let Some((iterations, elite_return)) = planner.search.stepped().map(|s| s.progress())
            else {
                continue;
            };
            let mean_energy = if iterations == 0 {
                0.0
            } else {
                planner.search.elite_energy(&planner.imagination)
            };
            planner.solved = Solved {
                predicted_return: elite_return,
                mean_energy,
                iterations,
                cut: request.step.cut,
            };
        }
    }

    /// The answer of the last plan: its action and what the solve did.
    pub fn outcome(&self) -> PlanOutcome<'_> {
        PlanOutcome {
            action: &self.action,
            predicted_return: self.solved.predicted_return,
            mean_energy: self.solved.mean_energy,
            iterations: self.solved.iterations,
            cut: self.solved.cut,
        }
    }

    /// Optimises one plan from `obs` starting from the initial (uninformed) distribution, as
    /// the paper's Figure 5 does, and imagines it step by step. The warm start of
    /// [`MpcPlanner::plan`] is left as it was. Allocates its result (not for the control loop).
    pub fn imagine_plan(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
    ) -> ImaginedPlan {
        let warm_start = self.search.mean().to_vec();
        self.search.reset();
        self.clock.start(None);
        let mut workspace = self.imagination.take_workspace();
        Self::solve(
            &mut [PlanRequest::new(self, obs, None)],
            &mut workspace,
            (dynamics, regularizer, learned),
            None,
        );
        self.imagination.keep_workspace(workspace);
        self.clock.end();
        let actions = self.search.plan().to_vec();
        self.search.set_mean(&warm_start);
        let horizon = self.search.config().horizon;
        let (mut rewards, mut energies) = (vec![0.0; horizon], vec![0.0; horizon]);
        let predicted_return = self.imagination.rollout(
            obs,
            &actions,
            dynamics,
            regularizer,
            learned,
            &mut rewards,
            &mut energies,
        );
        ImaginedPlan {
            actions,
            rewards,
            energies,
            predicted_return,
            iterations: self.solved.iterations,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Transitions;
    use crate::dynamics::DynamicsConfig;
    use crate::energy::{EnergyConfig, RegularizerKind};
    use crate::plan::imagine::Workspace;
    use crate::plan::{IcemConfig, Optimizer};
    use proto::Builtin;
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};
    use std::f32::consts::PI;

    #[test]
    fn a_thread_gets_a_second_chunk_only_where_chunks_keep_their_floor() {
        // Table 2's populations on 4 and 16 threads: two chunks per thread.
        assert_eq!(default_chunks(4, 400), 8);
        assert_eq!(default_chunks(16, 500), 32);
        assert_eq!(default_chunks(16, 2 * 16 * MIN_SPLIT_CHUNK), 32);
        // One candidate short of the floor, and a small search: one per thread.
        assert_eq!(default_chunks(16, 2 * 16 * MIN_SPLIT_CHUNK - 1), 16);
        assert_eq!(default_chunks(16, 100), 16);
        // Below the thread floor: one chunk per thread; zero threads is read as one.
        assert_eq!(default_chunks(2, 500), 2);
        assert_eq!(default_chunks(1, 500), 1);
        assert_eq!(default_chunks(0, 500), 1);
    }

    /// A cart that the action pushes directly, `x' = x + 0.1·a`, everything else constant.
    /// With the pole upright (θ = π) cartpole's reward `exp(−x²/0.36) − 0.01a²` is best at
    /// x = 0, so from x = 0.5 the right first action is a hard push to the left.
    fn pushed_cart(n: usize, actions: (f32, f32), seed: u64) -> Transitions {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut data = Transitions::new(4, 1);
        for _ in 0..n {
            let obs = [
                rng.random_range(-1.0..1.0),
                PI + rng.random_range(-0.5..0.5),
                0.0,
                0.0,
            ];
            let a = rng.random_range(actions.0..actions.1);
            data.push(&obs, &[a], 0.0, &[obs[0] + 0.1 * a, obs[1], obs[2], obs[3]]);
        }
        data
    }

    fn learned_cart() -> Ensemble {
        let config = DynamicsConfig {
            hidden_layers: 2,
            hidden_size: 32,
            ..Default::default()
        };
        let mut rng = StdRng::seed_from_u64(0);
        let mut dynamics = Ensemble::new(Builtin::Cartpole.task(), &config, &mut rng);
        let report = dynamics.fit(&pushed_cart(2000, (-3.0, 3.0), 1), 40, &mut rng);
        assert!(report.mse.unwrap() < 0.05, "{report:?}");
        dynamics
    }

    /// One plan from `obs` with no regulariser, no learned parts and no deadline.
    fn plan_alone<'p>(
        planner: &'p mut MpcPlanner,
        obs: &[f32],
        dynamics: &Ensemble,
    ) -> PlanOutcome<'p> {
        planner.plan(
            obs,
            dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        )
    }

    /// Pushes the cart left from the right of the centre and right from the left (the reward
    /// is at the centre), with the warm start forgotten in between.
    fn assert_plans_towards_the_reward(planner: &mut MpcPlanner, dynamics: &Ensemble) {
        let right = plan_alone(planner, &[0.5, PI, 0.0, 0.0], dynamics);
        assert!(right.action[0] < -1.0, "{right:?}");
        planner.reset();
        let left = plan_alone(planner, &[-0.5, PI, 0.0, 0.0], dynamics);
        assert!(left.action[0] > 1.0, "{left:?}");
    }

    fn config() -> CemConfig {
        CemConfig {
            horizon: 8,
            population: 200,
            elites: 20,
            iterations: 5,
            smoothing: 0.1,
            min_variance: 1e-3,
            particles: 1,
            optimizer: Optimizer::Cem,
            icem: IcemConfig::default(),
            adam: crate::plan::AdamConfig::default(),
        }
    }

    #[test]
    fn plans_towards_the_reward_through_a_learned_model() {
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let mut planner = MpcPlanner::new(task, config(), 0.0, false, 3).unwrap();
        let right = plan_alone(&mut planner, &[0.5, PI, 0.0, 0.0], &dynamics);
        assert!(
            right.predicted_return > 5.0 && right.predicted_return <= 8.0,
            "{right:?}"
        );
        assert_eq!((right.iterations, right.mean_energy), (5, 0.0));
        planner.reset();
        assert_plans_towards_the_reward(&mut planner, &dynamics);
    }

    #[test]
    fn the_energy_keeps_plans_near_the_data() {
        // The DEEN has only seen pushes to the right (a ≥ 0). Unregularised, the planner pushes
        // left from x = 0.5 (towards the reward); with a heavy energy weight its plan pushes
        // right on average, as the data did. (Over a ∈ [−3, 3] this DEEN's energy varies by
        // ~10 per step, so the weight must be large next to rewards of at most 1 per step.)
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let energy_config = EnergyConfig {
            hidden_layers: 2,
            hidden_size: 64,
            noise_sigma: 0.2,
            noise_units: Default::default(),
            ..Default::default()
        };
        let mut rng = StdRng::seed_from_u64(5);
        let mut deen = Regularizer::new(RegularizerKind::Deen, &energy_config, 4, 1, &mut rng);
        deen.fit(&pushed_cart(2000, (0.0, 3.0), 6), 30, &mut rng);
        let obs = [0.5, PI, 0.0, 0.0];
        let mean_push =
            |plan: &ImaginedPlan| plan.actions.iter().sum::<f32>() / plan.actions.len() as f32;

        let mut free = MpcPlanner::new(task, config(), 0.0, false, 3).unwrap();
        let unregularised = free.imagine_plan(&obs, &dynamics, &deen, crate::plan::Learned::NONE);
        let mut careful = MpcPlanner::new(task, config(), 10.0, false, 3).unwrap();
        let regularised = careful.imagine_plan(&obs, &dynamics, &deen, crate::plan::Learned::NONE);
        assert!(mean_push(&unregularised) < -0.4, "{unregularised:?}");
        assert!(mean_push(&regularised) > 0.1, "{regularised:?}");
        assert!(regularised.actions[0] > unregularised.actions[0] + 1.0);
        // The regularised plan is the more familiar one, step for step on average.
        let mean_energy = |plan: &ImaginedPlan| plan.energies.iter().sum::<f32>();
        assert!(mean_energy(&regularised) < mean_energy(&unregularised));
        let outcome = careful.plan(&obs, &dynamics, &deen, crate::plan::Learned::NONE, None);
        assert!(
            outcome.mean_energy.is_finite() && outcome.mean_energy > 0.0,
            "{outcome:?}"
        );
    }

    #[test]
    fn warm_starts_reset_and_reproducibility() {
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let obs = [0.5, PI, 0.0, 0.0];
        let mut a = MpcPlanner::new(task, config(), 0.0, false, 9).unwrap();
        let mut b = MpcPlanner::new(task, config(), 0.0, false, 9).unwrap();
        let first = plan_alone(&mut a, &obs, &dynamics).action[0];
        assert_eq!(first, plan_alone(&mut b, &obs, &dynamics).action[0]);
        // The warm start is the plan shifted by one step, with the neutral action appended.
        let plan = a.search.mean().to_vec();
        assert_eq!(plan[plan.len() - 1], 0.0);
        let second = plan_alone(&mut a, &obs, &dynamics).action[0];
        b.reset();
        let fresh = plan_alone(&mut b, &obs, &dynamics).action[0];
        assert_ne!(
            second, fresh,
            "warm and cold starts drew from different distributions"
        );
    }

    #[test]
    fn imagined_plans_report_their_steps_and_leave_the_warm_start_alone() {
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let mut planner = MpcPlanner::new(task, config(), 0.0, false, 2).unwrap();
        plan_alone(&mut planner, &[0.5, PI, 0.0, 0.0], &dynamics);
        let warm = planner.search.mean().to_vec();
        let imagined = planner.imagine_plan(
            &[0.5, PI, 0.0, 0.0],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
        );
        assert_eq!(planner.search.mean(), &warm[..]);
        assert_eq!((imagined.actions.len(), imagined.rewards.len()), (8, 8));
        let total: f32 = imagined.rewards.iter().sum();
        assert!(
            (total - imagined.predicted_return).abs() < 1e-4,
            "{imagined:?}"
        );
        // Pushing left brings the tip over the origin: imagined rewards climb towards 1.
        assert!(
            imagined.rewards[7] > 0.9 && imagined.rewards[0] < imagined.rewards[7],
            "{imagined:?}"
        );
    }

    /// Imagination from one observation as a plain [`crate::plan::PopulationObjective`].
    struct Imagined<'a> {
        imagination: &'a mut Imagination,
        obs: &'a [f32],
        dynamics: &'a Ensemble,
    }

    impl crate::plan::PopulationObjective for Imagined<'_> {
        fn evaluate(&mut self, actions: &[f32], returns: &mut [f32]) {
            self.imagination.evaluate(
                self.obs,
                actions,
                self.dynamics,
                &Regularizer::None,
                Learned::NONE,
                returns,
                None,
            );
        }
    }

    #[test]
    fn the_default_preset_plans_exactly_as_plain_cem() {
        // The optimiser dispatch changes nothing for the paper's method: the default preset's
        // planner takes, step after step, the actions that `Cem` itself picks with the same
        // seed over the same imagination.
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let preset = crate::config::Preset::new(Builtin::Cartpole.task(), None).unwrap();
        assert_eq!(preset.cem.optimizer, Optimizer::Cem);
        let mut planner =
            MpcPlanner::with_chunks(task, preset.cem.clone(), 0.0, false, 5, 2).unwrap();
        let mut cem =
            crate::plan::Cem::new(preset.cem.clone(), &task.action_low, &task.action_high, 5)
                .unwrap();
        let mut imagination = Imagination::new(task, &preset.cem, 0.0, false, 2, 6);
        let mut obs = [0.5, PI, 0.0, 0.0];
        for _ in 0..3 {
            let planned = plan_alone(&mut planner, &obs, &dynamics).action.to_vec();
            cem.optimize(
                &mut Imagined {
                    imagination: &mut imagination,
                    obs: &obs,
                    dynamics: &dynamics,
                },
                &mut IterationClock::default(),
            );
            assert_eq!(planned, cem.first_action());
            cem.shift();
            obs[0] += 0.1 * planned[0];
        }
    }

    #[test]
    fn icem_plans_towards_the_reward_with_a_fraction_of_the_samples() {
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let mut cfg = config();
        cfg.optimizer = Optimizer::Icem;
        cfg.population = 50;
        cfg.elites = 10;
        let mut planner = MpcPlanner::new(task, cfg, 0.0, false, 3).unwrap();
        assert_plans_towards_the_reward(&mut planner, &dynamics);
    }

    #[test]
    fn a_plan_with_no_time_answers_the_previous_plan_shifted() {
        use std::time::{Duration, Instant};
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let obs = [0.5, PI, 0.0, 0.0];
        let mut planner = MpcPlanner::new(task, config(), 0.0, false, 4).unwrap();
        let first = plan_alone(&mut planner, &obs, &dynamics);
        assert!(first.iterations > 0 && !first.cut, "{first:?}");
        // The warm start is the plan shifted by one step: its first action is what a plan
        // that cannot run one iteration answers.
        let shifted = planner.search.mean()[0];
        let passed = Some(Instant::now() - Duration::from_millis(1));
        let late = planner.plan(
            &obs,
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            passed,
        );
        assert_eq!((late.iterations, late.cut), (0, true));
        assert_eq!(late.action, &[shifted]);
        assert_eq!(late.mean_energy, 0.0);
    }

    #[test]
    fn a_deadline_that_does_not_bind_plans_as_without_one() {
        // Same seed, same observations: no deadline and a deadline an hour away take the same
        // actions, every iteration run, nothing cut.
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let later = std::time::Instant::now() + std::time::Duration::from_secs(3600);
        let actions = |deadline| {
            let mut planner = MpcPlanner::new(task, config(), 0.0, false, 8).unwrap();
            let mut obs = [0.5, PI, 0.0, 0.0];
            let mut taken = Vec::new();
            for _ in 0..4 {
                let outcome = planner.plan(
                    &obs,
                    &dynamics,
                    &Regularizer::None,
                    crate::plan::Learned::NONE,
                    deadline,
                );
                assert!(outcome.iterations > 0 && !outcome.cut, "{outcome:?}");
                taken.push(outcome.action[0]);
                obs[0] += 0.1 * outcome.action[0];
            }
            taken
        };
        assert_eq!(actions(None), actions(Some(later)));
    }

    /// Each agent of a batch gets exactly the answer it gets alone with the same random state:
    /// CEM and iCEM, ragged batches (1, 3, 8 agents, one workspace serving them all in turn),
    /// an ensemble with sampled particles, a DEEN, warm starts over several steps, and an
    /// early stop that ends some agents' solves before others'.
    #[test]
    fn a_batch_plans_each_agent_exactly_as_alone() {
        let task = Builtin::Cartpole.task();
        let mut rng = StdRng::seed_from_u64(11);
        let dynamics = Ensemble::new(
            task,
            &DynamicsConfig {
                hidden_layers: 2,
                hidden_size: 24,
                ensemble_size: 3,
                ..Default::default()
            },
            &mut rng,
        );
        let deen = Regularizer::new(
            RegularizerKind::Deen,
            &EnergyConfig {
                hidden_layers: 2,
                hidden_size: 16,
                ..Default::default()
            },
            4,
            1,
            &mut rng,
        );
        let models = (&dynamics, &deen, Learned::NONE);
        let mut workspace = Workspace::new();
        for optimizer in [Optimizer::Cem, Optimizer::Icem] {
            let mut cfg = config();
            cfg.optimizer = optimizer;
            cfg.population = 37;
            cfg.elites = 5;
            cfg.particles = 4;
            // Loose enough that some solves converge before their last iteration.
            cfg.min_variance = match optimizer {
                Optimizer::Icem => 1.2,
                _ => 0.3,
            };
            let planner = |k: u64| {
                MpcPlanner::with_chunks(task, cfg.clone(), 0.05, true, 100 + k, 2).unwrap()
            };
            for n in [1usize, 3, 8] {
                let mut alone: Vec<MpcPlanner> = (0..n as u64).map(planner).collect();
                let mut batched: Vec<MpcPlanner> = (0..n as u64).map(planner).collect();
                let mut obs: Vec<[f32; 4]> = (0..n)
                    .map(|k| {
                        [
                            0.1 * k as f32 - 0.3,
                            PI - 0.05 * k as f32,
                            0.0,
                            0.01 * k as f32,
                        ]
                    })
                    .collect();
                let mut iterations = std::collections::BTreeSet::new();
                for step in 0..3 {
                    let expected: Vec<(Vec<f32>, f32, f32, u32, bool)> = alone
                        .iter_mut()
                        .zip(&obs)
                        .map(|(p, o)| {
                            let out = p.plan(o, &dynamics, &deen, Learned::NONE, None);
                            let (a, r, e) =
                                (out.action.to_vec(), out.predicted_return, out.mean_energy);
                            (a, r, e, out.iterations, out.cut)
                        })
                        .collect();
                    let mut requests: Vec<PlanRequest> = batched
                        .iter_mut()
                        .zip(&obs)
                        .map(|(p, o)| PlanRequest::new(p, o, None))
                        .collect();
                    MpcPlanner::plan_batch(&mut requests, &mut workspace, models, None);
                    for (k, (request, want)) in requests.iter().zip(&expected).enumerate() {
                        let got = request.outcome();
                        let got = (
                            got.action.to_vec(),
                            got.predicted_return,
                            got.mean_energy,
                            got.iterations,
                            got.cut,
                        );
                        assert_eq!(
                            &got, want,
                            "{optimizer:?}, {n} agents, agent {k}, step {step}"
                        );
                        assert!(want.1.is_finite() && want.2 > 0.0, "{want:?}");
                        iterations.insert(want.3);
                    }
                    for (o, (a, ..)) in obs.iter_mut().zip(&expected) {
                        o[0] += 0.1 * a[0];
                    }
                }
                if n == 8 {
                    assert!(
                        iterations.len() > 1,
                        "{optimizer:?}: every solve ran {iterations:?} iterations"
                    );
                }
            }
        }
    }

    /// A deadline cuts only its own request: the agent whose deadline has passed answers its
    /// warm start (no iteration, cut), and the others of the batch plan exactly as alone.
    #[test]
    fn a_passed_deadline_in_a_batch_cuts_that_agent_only() {
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let models = (&dynamics, &Regularizer::None, Learned::NONE);
        let obs = [
            [0.5, PI, 0.0, 0.0],
            [-0.5, PI, 0.0, 0.0],
            [0.2, PI, 0.0, 0.0],
        ];
        let make = |k: u64| MpcPlanner::with_chunks(task, config(), 0.0, false, k, 2).unwrap();
        let mut alone: Vec<MpcPlanner> = (0..3).map(make).collect();
        let mut batched: Vec<MpcPlanner> = (0..3).map(make).collect();
        let expected: Vec<Vec<f32>> = alone
            .iter_mut()
            .zip(&obs)
            .map(|(p, o)| {
                p.plan(o, models.0, models.1, models.2, None)
                    .action
                    .to_vec()
            })
            .collect();
        let warm_start = batched[1].search.mean()[0];
        let passed = Some(Instant::now() - Duration::from_millis(1));
        let later = Some(Instant::now() + Duration::from_secs(3600));
        let mut workspace = Workspace::new();
        let [a, b, c] = &mut batched[..] else {
            unreachable!()
        };
        let mut requests = [
            PlanRequest::new(a, &obs[0], later),
            PlanRequest::new(b, &obs[1], passed),
            PlanRequest::new(c, &obs[2], None),
        ];
        MpcPlanner::plan_batch(&mut requests, &mut workspace, models, None);
        let late = requests[1].outcome();
        assert_eq!((late.iterations, late.cut), (0, true));
        assert_eq!(late.action, &[warm_start]);
        for k in [0, 2] {
            let outcome = requests[k].outcome();
            assert_eq!((outcome.iterations, outcome.cut), (5, false), "agent {k}");
            assert_eq!(outcome.action, &expected[k][..], "agent {k}");
        }
    }

    #[test]
    fn refuses_a_bad_energy_weight() {
        let task = Builtin::Cartpole.task();
        assert!(matches!(
            MpcPlanner::new(task, config(), f32::NAN, false, 0),
            Err(ConfigError::EnergyWeight(_))
        ));
        assert!(MpcPlanner::new(task, config(), -1.0, false, 0).is_err());
    }
}
