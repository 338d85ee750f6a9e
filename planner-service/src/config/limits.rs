//! What a client may ask of this daemon: `[limits]` in its TOML configuration.
//!
//! Every size an attaching agent chooses (through its preset and overrides) becomes memory or
//! CPU time in the daemon, so each has an upper bound here, and the sizes together have
//! budgets: the bytes the run's networks take, the multiply-adds of one plan, the seconds of
//! one retraining. An attach over a limit is refused with an error that names the field, its
//! value and the limit, before anything is allocated. The defaults admit every preset of the
//! paper (Table 2, at full size, with PETS's ensembles) with room to spare, and keep one run
//! to a fraction of a 24 GiB, 2-core machine.

use super::Preset;
use proto::Task;
use proto::task::{MAX_MAGNITUDE, Magnitudes, SpecBounds};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The daemon's limits (`[limits]`; every key optional).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// Most members of a dynamics ensemble (PETS uses 5).
    pub max_ensemble_size: u64,
    /// Most trajectory-sampling particles per CEM candidate (PETS uses 20).
    pub max_particles: u64,
    /// Longest planning horizon, in steps (Table 2: 25–30).
    pub max_horizon: u64,
    /// Largest CEM population (Table 2: 400–500); elites are bounded by the population.
    pub max_population: u64,
    /// Most CEM iterations per plan (Table 2: 5–7).
    pub max_cem_iterations: u64,
    /// Most episodes of random exploration (Table 2: 1–3).
    pub max_exploration_episodes: u64,
    /// Most transitions of random exploration (`exploration_steps`).
    pub max_exploration_steps: u64,
    /// Most training epochs per retraining, of either model, also in an epoch schedule
    /// (Table 2: up to 800).
    pub max_epochs: u64,
    /// Most hidden layers of either network (Table 2: up to 5).
    pub max_hidden_layers: u64,
    /// Most units per hidden layer (Table 2: up to 500).
    pub max_hidden_size: u64,
    /// Largest training minibatch (Table 2: up to 400).
    pub max_batch_size: u64,
    /// Budget of one run's networks in bytes: 20 bytes per parameter (the f32 weights, their
    /// packed copy for inference, the gradient and Adam's two moments). The replay buffer is
    /// not counted here.
    pub max_model_bytes: u64,
    /// Budget of one plan: multiply-adds of every network evaluation CEM makes (iterations ×
    /// population × particles × horizon × the networks' multiply-adds per transition).
    pub max_plan_multiply_adds: u64,
    /// Budget of one retraining in seconds: training stops after the minibatch that crosses
    /// it and the models trained so far are used.
    pub max_retrain_seconds: f64,
    /// Largest message accepted, in bytes, checked on the raw payload before decoding.
    pub max_payload_bytes: u64,
    /// Longest per-run deadline an agent may ask for (`deadline_ms`), in milliseconds: a plan
    /// holds the cores it plans on for up to that long.
    pub max_deadline_ms: u64,
    /// Seconds an agent's session waits for its next observation before it is closed if the
    /// agent has no liveliness token (it vanished without its token's deletion reaching us);
    /// its open episode is recorded as interrupted and its slot freed.
    pub agent_idle_seconds: u64,
    /// Longest observation of a task (a client's spec or a declared one).
    pub max_obs_dim: u64,
    /// Longest action of a task.
    pub max_act_dim: u64,
    /// Longest episode of a task, in steps.
    pub max_episode_len: u64,
    /// Per task (by name), the largest observation and reward magnitudes accepted instead of
    /// the catalog's (`[limits.magnitudes.cartpole] observation = 1e5, reward = 1e3`).
    pub magnitudes: BTreeMap<String, Magnitudes>,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_ensemble_size: 10,
            max_particles: 100,
            max_horizon: 200,
            max_population: 5_000,
            max_cem_iterations: 50,
            max_exploration_episodes: 1_000,
            max_exploration_steps: 1_000_000,
            max_epochs: 5_000,
            max_hidden_layers: 10,
            max_hidden_size: 2_048,
            max_batch_size: 4_096,
            max_model_bytes: 512 << 20,
            max_plan_multiply_adds: 4_000_000_000_000,
            max_retrain_seconds: 3_600.0,
            max_payload_bytes: 64 << 10,
            max_deadline_ms: 60_000,
            agent_idle_seconds: 3_600,
            max_obs_dim: SpecBounds::default().max_obs_dim as u64,
            max_act_dim: SpecBounds::default().max_act_dim as u64,
            max_episode_len: SpecBounds::default().max_episode_len.into(),
            magnitudes: BTreeMap::new(),
        }
    }
}

/// A request over one of the limits.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} = {value} is over this planner's limit of {limit} ([limits] {setting})")]
pub struct LimitExceeded {
    /// The override (or budget) that is too large.
    pub field: &'static str,
    pub value: u64,
    pub limit: u64,
    /// The `[limits]` key that sets the limit.
    pub setting: &'static str,
}

/// A `[limits]` section that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InvalidLimits {
    #[error("[limits] {0} must be positive")]
    NotPositive(&'static str),
    #[error("[limits.magnitudes] names an unknown task: {0}")]
    UnknownTask(#[from] proto::UnknownTask),
    #[error("[limits.magnitudes.{task}] bounds must be positive and at most {MAX_MAGNITUDE:e}")]
    Magnitude { task: String },
}

impl Limits {
    /// Checks the configuration itself: every limit positive, every magnitude in range (that
    /// each names a task of the catalog is the service configuration's check).
    pub fn validate(&self) -> Result<(), InvalidLimits> {
        let counts = [
            ("max_ensemble_size", self.max_ensemble_size),
            ("max_particles", self.max_particles),
            ("max_horizon", self.max_horizon),
            ("max_population", self.max_population),
            ("max_cem_iterations", self.max_cem_iterations),
            ("max_epochs", self.max_epochs),
            ("max_hidden_layers", self.max_hidden_layers),
            ("max_hidden_size", self.max_hidden_size),
            ("max_batch_size", self.max_batch_size),
            ("max_model_bytes", self.max_model_bytes),
            ("max_plan_multiply_adds", self.max_plan_multiply_adds),
            ("max_payload_bytes", self.max_payload_bytes),
            ("max_deadline_ms", self.max_deadline_ms),
            ("agent_idle_seconds", self.agent_idle_seconds),
            ("max_obs_dim", self.max_obs_dim),
            ("max_act_dim", self.max_act_dim),
            ("max_episode_len", self.max_episode_len),
        ];
        if let Some((name, _)) = counts.iter().find(|(_, v)| *v == 0) {
            return Err(InvalidLimits::NotPositive(name));
        }
        if !(self.max_retrain_seconds.is_finite() && self.max_retrain_seconds > 0.0) {
            return Err(InvalidLimits::NotPositive("max_retrain_seconds"));
        }
        for (task, m) in &self.magnitudes {
            if !m.is_valid() {
                return Err(InvalidLimits::Magnitude { task: task.clone() });
            }
        }
        Ok(())
    }

    /// The observation and reward bounds of `task`: the configured ones, or the catalog's.
    pub fn magnitudes(&self, task: &Task) -> Magnitudes {
        self.magnitudes
            .get(task.name())
            .copied()
            .unwrap_or(task.magnitudes)
    }

    /// The bounds of a task spec: its dimensions and episode length.
    pub fn spec_bounds(&self) -> SpecBounds {
        let clamp = |v: u64| usize::try_from(v).unwrap_or(usize::MAX);
        SpecBounds {
            max_obs_dim: clamp(self.max_obs_dim),
            max_act_dim: clamp(self.max_act_dim),
            max_episode_len: u32::try_from(self.max_episode_len).unwrap_or(u32::MAX),
        }
    }

    /// Checks every size of `preset` and then its budgets. Sizes come first, so an absurd
    /// size is named as itself, and the budgets are computed from bounded sizes only.
    pub fn check(&self, preset: &Preset) -> Result<(), LimitExceeded> {
        self.check_for(preset, preset.task)
    }

    /// As [`Limits::check`], for `preset` of `task` (a task not interned yet: see
    /// [`Preset::unshared`]).
    pub fn check_for(&self, preset: &Preset, task: &proto::Task) -> Result<(), LimitExceeded> {
        let (d, e, c) = (&preset.dynamics, &preset.energy, &preset.cem);
        let mut sizes = vec![
            (
                "ensemble_size",
                d.ensemble_size as u64,
                self.max_ensemble_size,
                "max_ensemble_size",
            ),
            (
                "particles",
                c.particles as u64,
                self.max_particles,
                "max_particles",
            ),
            ("horizon", c.horizon as u64, self.max_horizon, "max_horizon"),
            (
                "population",
                c.population as u64,
                self.max_population,
                "max_population",
            ),
            (
                "elites",
                c.elites as u64,
                self.max_population,
                "max_population",
            ),
            (
                "cem_iterations",
                c.iterations as u64,
                self.max_cem_iterations,
                "max_cem_iterations",
            ),
            (
                "exploration_episodes",
                preset.exploration_episodes as u64,
                self.max_exploration_episodes,
                "max_exploration_episodes",
            ),
            (
                "exploration_steps",
                preset.exploration_steps,
                self.max_exploration_steps,
                "max_exploration_steps",
            ),
            (
                "dynamics_epochs",
                d.epochs as u64,
                self.max_epochs,
                "max_epochs",
            ),
            (
                "energy_epochs",
                e.epochs as u64,
                self.max_epochs,
                "max_epochs",
            ),
            (
                "dynamics_hidden_layers",
                d.hidden_layers as u64,
                self.max_hidden_layers,
                "max_hidden_layers",
            ),
            (
                "energy_hidden_layers",
                e.hidden_layers as u64,
                self.max_hidden_layers,
                "max_hidden_layers",
            ),
            (
                "dynamics_hidden_size",
                d.hidden_size as u64,
                self.max_hidden_size,
                "max_hidden_size",
            ),
            (
                "energy_hidden_size",
                e.hidden_size as u64,
                self.max_hidden_size,
                "max_hidden_size",
            ),
            (
                "reward_hidden_layers",
                preset.reward.hidden_layers as u64,
                self.max_hidden_layers,
                "max_hidden_layers",
            ),
            (
                "reward_hidden_size",
                preset.reward.hidden_size as u64,
                self.max_hidden_size,
                "max_hidden_size",
            ),
            (
                "dynamics_batch_size",
                d.batch_size as u64,
                self.max_batch_size,
                "max_batch_size",
            ),
            (
                "energy_batch_size",
                e.batch_size as u64,
                self.max_batch_size,
                "max_batch_size",
            ),
        ];
        if let Some(ms) = preset.deadline_ms {
            sizes.push((
                "deadline_ms",
                u64::from(ms),
                self.max_deadline_ms,
                "max_deadline_ms",
            ));
        }
        match preset.schedule {
            proto::EpochSchedule::Constant => {}
            proto::EpochSchedule::DropAfter { epochs, .. } => sizes.push((
                "epoch_schedule.drop_after.epochs",
                epochs as u64,
                self.max_epochs,
                "max_epochs",
            )),
            proto::EpochSchedule::Geometric { min_epochs, .. } => sizes.push((
                "epoch_schedule.geometric.min_epochs",
                min_epochs as u64,
                self.max_epochs,
                "max_epochs",
            )),
        }
        for (field, value, limit, setting) in sizes {
            exceeds(field, value, limit, setting)?;
        }
        let cost = Cost::of_task(preset, task);
        exceeds(
            "model_bytes",
            cost.model_bytes,
            self.max_model_bytes,
            "max_model_bytes",
        )?;
        exceeds(
            "plan_multiply_adds",
            cost.plan_multiply_adds,
            self.max_plan_multiply_adds,
            "max_plan_multiply_adds",
        )
    }
}

fn exceeds(
    field: &'static str,
    value: u64,
    limit: u64,
    setting: &'static str,
) -> Result<(), LimitExceeded> {
    if value > limit {
        Err(LimitExceeded {
            field,
            value,
            limit,
            setting,
        })
    } else {
        Ok(())
    }
}

/// What a preset costs: the quantities the budgets bound.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cost {
    /// 20 bytes per network parameter (see [`Limits::max_model_bytes`]).
    pub model_bytes: u64,
    /// Multiply-adds of the network evaluations of one plan.
    pub plan_multiply_adds: u64,
}

/// Bytes a parameter costs: f32 weights, packed inference copy, gradient, Adam's m and v.
const BYTES_PER_PARAMETER: u64 = 5 * 4;

impl Cost {
    /// The cost of `preset`'s networks (saturating: an absurd preset costs `u64::MAX`).
    pub fn of(preset: &Preset) -> Self {
        Self::of_task(preset, preset.task)
    }

    /// The cost of `preset`'s networks for `task` (a task not interned yet: see
    /// [`Preset::unshared`]).
    pub fn of_task(preset: &Preset, task: &proto::Task) -> Self {
        let dynamics = crate::dynamics::config::layer_sizes(task, &preset.dynamics);
        let energy = preset
            .regularizer
            .layer_sizes(&preset.energy, task.obs_dim, task.act_dim)
            .unwrap_or_default();
        // Only a task whose reward is learned has a reward network.
        let reward = if task.reward_is_learned() {
            crate::reward::layer_sizes(task, &preset.reward)
        } else {
            Vec::new()
        };
        let members = preset.dynamics.ensemble_size as u64;
        let parameters = members
            .saturating_mul(parameters(&dynamics))
            .saturating_add(parameters(&energy))
            .saturating_add(parameters(&reward));
        // In imagination every particle steps one member, and every imagined transition is
        // scored by the regulariser (and by the reward model, where the reward is learned).
        let per_transition = multiply_adds(&dynamics)
            .saturating_add(multiply_adds(&energy))
            .saturating_add(multiply_adds(&reward));
        let c = &preset.cem;
        let transitions = [c.iterations, c.population, c.particles, c.horizon]
            .iter()
            .fold(1u64, |n, &k| n.saturating_mul(k as u64));
        // Adam runs one forward pass more than it has steps and back-propagates every step
        // (one product per layer, as a forward pass: the input gradient only), so a step costs
        // about two forward passes; counted as three, a bound with room for the extra pass.
        let transitions = match c.optimizer {
            crate::plan::Optimizer::Adam => transitions.saturating_mul(3),
            crate::plan::Optimizer::Cem | crate::plan::Optimizer::Icem => transitions,
        };
        Self {
            model_bytes: parameters.saturating_mul(BYTES_PER_PARAMETER),
            plan_multiply_adds: transitions.saturating_mul(per_transition),
        }
    }
}

/// Weights and biases of a network with layer sizes `sizes`.
fn parameters(sizes: &[usize]) -> u64 {
    sizes
        .windows(2)
        .map(|w| {
            (w[0] as u64)
                .saturating_mul(w[1] as u64)
                .saturating_add(w[1] as u64)
        })
        .fold(0, u64::saturating_add)
}

/// Multiply-adds of one forward pass of a network with layer sizes `sizes`.
fn multiply_adds(sizes: &[usize]) -> u64 {
    sizes
        .windows(2)
        .map(|w| (w[0] as u64).saturating_mul(w[1] as u64))
        .fold(0, u64::saturating_add)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::METHODS;
    use proto::{Builtin, PlannerOverrides};

    /// The defaults admit every preset of the paper at full size, with room to spare.
    #[test]
    fn every_paper_preset_fits_the_default_limits() {
        let limits = Limits::default();
        limits.validate().unwrap();
        for &task in Builtin::ALL {
            for method in METHODS {
                let preset = Preset::new(task.task(), Some(method)).unwrap();
                limits
                    .check(&preset)
                    .unwrap_or_else(|e| panic!("{task} {method}: {e}"));
                let cost = Cost::of(&preset);
                assert!(
                    cost.model_bytes * 4 <= limits.max_model_bytes
                        && cost.plan_multiply_adds * 2 <= limits.max_plan_multiply_adds,
                    "{task} {method}: {cost:?}"
                );
            }
        }
    }

    #[test]
    fn the_cost_counts_every_layer() {
        // Cartpole, cem+deen, 3 × 200 both; dynamics [5 + 1, 200, 200, 200, 8], energy
        // [4 + 1 + 4, 200, 200, 200, 1].
        let p = Preset::new(Builtin::Cartpole.task(), Some("cem+deen")).unwrap();
        let dyn_macs = 6 * 200 + 2 * 200 * 200 + 200 * 8;
        let energy_macs = 9 * 200 + 2 * 200 * 200 + 200;
        let dyn_params = dyn_macs + 3 * 200 + 8;
        let energy_params = energy_macs + 3 * 200 + 1;
        let cost = Cost::of(&p);
        assert_eq!(cost.model_bytes, 20 * (dyn_params + energy_params) as u64);
        // 5 iterations × 400 × 1 particle × 25 steps.
        assert_eq!(
            cost.plan_multiply_adds,
            5 * 400 * 25 * (dyn_macs + energy_macs) as u64
        );
    }

    /// Each oversized override is refused, naming the field, its value and the limit.
    #[test]
    fn every_oversized_size_is_named() {
        let limits = Limits::default();
        let cases: Vec<(PlannerOverrides, &str)> = vec![
            (
                PlannerOverrides {
                    dynamics_hidden_size: Some(4_000_000_000),
                    ..Default::default()
                },
                "dynamics_hidden_size = 4000000000 is over this planner's limit of 2048 ([limits] max_hidden_size)",
            ),
            (
                PlannerOverrides {
                    energy_hidden_size: Some(u32::MAX),
                    ..Default::default()
                },
                "energy_hidden_size",
            ),
            (
                PlannerOverrides {
                    dynamics_hidden_layers: Some(u32::MAX),
                    ..Default::default()
                },
                "dynamics_hidden_layers",
            ),
            (
                PlannerOverrides {
                    energy_hidden_layers: Some(11),
                    ..Default::default()
                },
                "energy_hidden_layers",
            ),
            (
                PlannerOverrides {
                    reward_hidden_layers: Some(11),
                    ..Default::default()
                },
                "reward_hidden_layers",
            ),
            (
                PlannerOverrides {
                    reward_hidden_size: Some(u32::MAX),
                    ..Default::default()
                },
                "reward_hidden_size",
            ),
            (
                PlannerOverrides {
                    ensemble_size: Some(u32::MAX),
                    ..Default::default()
                },
                "ensemble_size",
            ),
            (
                PlannerOverrides {
                    particles: Some(101),
                    ..Default::default()
                },
                "particles",
            ),
            (
                PlannerOverrides {
                    horizon: Some(u32::MAX),
                    ..Default::default()
                },
                "horizon",
            ),
            (
                PlannerOverrides {
                    population: Some(u32::MAX),
                    ..Default::default()
                },
                "population",
            ),
            (
                PlannerOverrides {
                    cem_iterations: Some(u32::MAX),
                    ..Default::default()
                },
                "cem_iterations",
            ),
            (
                PlannerOverrides {
                    exploration_episodes: Some(u32::MAX),
                    ..Default::default()
                },
                "exploration_episodes",
            ),
            (
                PlannerOverrides {
                    exploration_steps: Some(u64::MAX),
                    ..Default::default()
                },
                "exploration_steps",
            ),
            (
                PlannerOverrides {
                    dynamics_epochs: Some(u32::MAX),
                    ..Default::default()
                },
                "dynamics_epochs",
            ),
            (
                PlannerOverrides {
                    energy_epochs: Some(5_001),
                    ..Default::default()
                },
                "energy_epochs",
            ),
            (
                PlannerOverrides {
                    dynamics_batch_size: Some(u32::MAX),
                    ..Default::default()
                },
                "dynamics_batch_size",
            ),
            (
                PlannerOverrides {
                    energy_batch_size: Some(u32::MAX),
                    ..Default::default()
                },
                "energy_batch_size",
            ),
            (
                PlannerOverrides {
                    epoch_schedule: Some(proto::EpochSchedule::DropAfter {
                        after_episodes: 1,
                        epochs: u32::MAX,
                    }),
                    ..Default::default()
                },
                "epoch_schedule.drop_after.epochs",
            ),
            (
                PlannerOverrides {
                    epoch_schedule: Some(proto::EpochSchedule::Geometric {
                        dynamics_factor: 0.5,
                        energy_factor: 0.5,
                        min_epochs: u32::MAX,
                    }),
                    ..Default::default()
                },
                "epoch_schedule.geometric.min_epochs",
            ),
            // Each size within its limit, together over a budget.
            (
                PlannerOverrides {
                    ensemble_size: Some(10),
                    dynamics_hidden_size: Some(2048),
                    dynamics_hidden_layers: Some(10),
                    ..Default::default()
                },
                "model_bytes",
            ),
            (
                PlannerOverrides {
                    population: Some(5000),
                    elites: Some(50),
                    particles: Some(100),
                    horizon: Some(200),
                    cem_iterations: Some(50),
                    ..Default::default()
                },
                "plan_multiply_adds",
            ),
        ];
        for (overrides, expected) in cases {
            let mut preset = Preset::new(Builtin::HalfCheetah.task(), None).unwrap();
            preset.apply(&overrides).unwrap();
            let err = limits.check(&preset).unwrap_err().to_string();
            assert!(err.starts_with(expected), "{overrides:?}: {err}");
        }
    }

    #[test]
    fn limits_parse_and_invalid_ones_are_refused() {
        let limits: Limits = toml::from_str(
            "max_hidden_size = 64\n[magnitudes.cartpole]\nobservation = 1e6\nreward = 10.0\n",
        )
        .unwrap();
        limits.validate().unwrap();
        assert_eq!(limits.max_hidden_size, 64);
        let cartpole = Builtin::Cartpole.task();
        assert_eq!(limits.magnitudes(cartpole).observation, 1e6);
        assert_eq!(
            limits.magnitudes(Builtin::Ant.task()),
            Builtin::Ant.task().magnitudes
        );
        assert!(toml::from_str::<Limits>("max_hidden_sizes = 64").is_err());
        for bad in [
            "max_population = 0",
            "agent_idle_seconds = 0",
            "max_retrain_seconds = -1.0",
            "max_retrain_seconds = nan",
            "[magnitudes.ant]\nobservation = inf\nreward = 1.0",
            "[magnitudes.ant]\nobservation = 0.0\nreward = 1.0",
            "[magnitudes.ant]\nobservation = 3e38\nreward = 1.0",
            "[magnitudes.ant]\nobservation = 1.0\nreward = nan",
        ] {
            let limits: Limits = toml::from_str(bad).unwrap();
            assert!(limits.validate().is_err(), "{bad}");
        }
    }
}
