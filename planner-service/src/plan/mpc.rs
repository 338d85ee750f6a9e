//! The per-agent model-predictive controller: CEM over imagined returns, warm-started from
//! the previous step's plan, applying only the first action (PETS' `MPC.act`).

use super::Learned;
use crate::dynamics::Ensemble;
use crate::energy::Regularizer;
use crate::plan::anytime::IterationClock;
use crate::plan::imagine::Imagination;
use crate::plan::search::{Imagined, Search};
use crate::plan::settings::{CemConfig, ConfigError};
use crate::sched::Preempt;
use proto::Task;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// One agent's planner. Owns the optimiser's distribution (the warm start), the imagination's
/// buffers and the random state, so planning allocates nothing.
pub struct MpcPlanner {
    task: &'static Task,
    /// CEM, iCEM or Adam, as the configuration says.
    search: Search,
    imagination: Imagination,
    /// The action chosen by the last [`MpcPlanner::plan`] (the warm start has moved on since).
    action: Vec<f32>,
    /// This agent's iteration timings, which decide how many iterations fit a deadline.
    clock: IterationClock,
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

impl MpcPlanner {
    /// A planner for `task` that scores plans as `Σ reward − energy_weight · energy`, sampling
    /// the dynamics' predicted Gaussian when `sample` is set (PETS TS∞), else using its mean.
    /// The population is split across all rayon threads; `seed` fixes every random choice.
    pub fn new(
        task: &'static Task,
        config: CemConfig,
        energy_weight: f32,
        sample: bool,
        seed: u64,
    ) -> Result<Self, ConfigError> {
        Self::with_chunks(
            task,
            config,
            energy_weight,
            sample,
            seed,
            rayon::current_num_threads(),
        )
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
    /// runs (see [`crate::sched`]).
    pub fn plan_shared(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        deadline: Option<Instant>,
        preempt: Option<Arc<dyn Preempt>>,
    ) -> PlanOutcome<'_> {
        let mut objective = Imagined {
            imagination: &mut self.imagination,
            obs,
            dynamics,
            regularizer,
            learned,
            preempt: preempt.clone(),
        };
        self.clock.start_shared(deadline, preempt);
        let (outcome, mean_energy) = self.search.optimize(&mut objective, &mut self.clock);
        self.clock.end();
        if outcome.iterations == 0 {
            self.action
                .copy_from_slice(&self.search.mean()[..self.task.act_dim]);
        } else {
            self.action.copy_from_slice(self.search.first_action());
        }
        self.search.shift();
        PlanOutcome {
            action: &self.action,
            predicted_return: outcome.elite_return,
            mean_energy,
            iterations: outcome.iterations,
            cut: outcome.cut,
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
        let mut objective = Imagined {
            imagination: &mut self.imagination,
            obs,
            dynamics,
            regularizer,
            learned,
            preempt: None,
        };
        self.clock.start(None);
        let (outcome, _) = self.search.optimize(&mut objective, &mut self.clock);
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
            iterations: outcome.iterations,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Transitions;
    use crate::dynamics::DynamicsConfig;
    use crate::energy::{EnergyConfig, RegularizerKind};
    use crate::plan::{IcemConfig, Optimizer};
    use proto::Builtin;
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};
    use std::f32::consts::PI;

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
        let right = planner.plan(
            &[0.5, PI, 0.0, 0.0],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        );
        assert!(right.action[0] < -1.0, "{right:?}");
        assert!(
            right.predicted_return > 5.0 && right.predicted_return <= 8.0,
            "{right:?}"
        );
        assert_eq!((right.iterations, right.mean_energy), (5, 0.0));
        planner.reset();
        let left = planner.plan(
            &[-0.5, PI, 0.0, 0.0],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        );
        assert!(left.action[0] > 1.0, "{left:?}");
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
        let first = a
            .plan(
                &obs,
                &dynamics,
                &Regularizer::None,
                crate::plan::Learned::NONE,
                None,
            )
            .action[0];
        assert_eq!(
            first,
            b.plan(
                &obs,
                &dynamics,
                &Regularizer::None,
                crate::plan::Learned::NONE,
                None
            )
            .action[0]
        );
        // The warm start is the plan shifted by one step, with the neutral action appended.
        let plan = a.search.mean().to_vec();
        assert_eq!(plan[plan.len() - 1], 0.0);
        let second = a
            .plan(
                &obs,
                &dynamics,
                &Regularizer::None,
                crate::plan::Learned::NONE,
                None,
            )
            .action[0];
        b.reset();
        let fresh = b
            .plan(
                &obs,
                &dynamics,
                &Regularizer::None,
                crate::plan::Learned::NONE,
                None,
            )
            .action[0];
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
        planner.plan(
            &[0.5, PI, 0.0, 0.0],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        );
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
            let planned = planner
                .plan(
                    &obs,
                    &dynamics,
                    &Regularizer::None,
                    crate::plan::Learned::NONE,
                    None,
                )
                .action
                .to_vec();
            cem.optimize(
                &mut Imagined {
                    imagination: &mut imagination,
                    obs: &obs,
                    dynamics: &dynamics,
                    regularizer: &Regularizer::None,
                    learned: Learned::NONE,
                    preempt: None,
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
        let right = planner.plan(
            &[0.5, PI, 0.0, 0.0],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        );
        assert!(right.action[0] < -1.0, "{right:?}");
        planner.reset();
        let left = planner.plan(
            &[-0.5, PI, 0.0, 0.0],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        );
        assert!(left.action[0] > 1.0, "{left:?}");
    }

    #[test]
    fn a_plan_with_no_time_answers_the_previous_plan_shifted() {
        use std::time::{Duration, Instant};
        let dynamics = learned_cart();
        let task = Builtin::Cartpole.task();
        let obs = [0.5, PI, 0.0, 0.0];
        let mut planner = MpcPlanner::new(task, config(), 0.0, false, 4).unwrap();
        let first = planner.plan(
            &obs,
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            None,
        );
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
