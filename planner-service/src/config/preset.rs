//! Per-task presets: the paper's Table 2 (model, DEEN and CEM sizes) and `tasks.md` (horizon,
//! population, elites, exploration), combined with a *method* — the preset's name:
//!
//! | preset      | dynamics                        | regulariser |
//! |-------------|---------------------------------|-------------|
//! | `cem`       | one probabilistic model, mean   | none        |
//! | `cem+dae`   | one probabilistic model, mean   | DAE         |
//! | `cem+deen`  | one probabilistic model, mean   | DEEN (default: the paper) |
//! | `pets`      | 5-member ensemble, TS∞, 20 particles, sampled | none |
//! | `pets+deen` | as `pets`                       | DEEN (the paper's §4.1 setting) |
//! | `adam+dae`  | one probabilistic model, mean   | DAE, planned by Adam (Boney et al. 2019) |
//!
//! `adam+dae` is the paper's gradient-based baseline ([`crate::plan::adam`]). The paper gives
//! no Adam settings (it reports only that Adam "requires much more computation" than CEM);
//! its horizon, model, DAE and `α` are the task's Table 2 values as for `cem+dae`, and the
//! rest are this project's choices: [`ADAM_CANDIDATES`] sequences optimised together (the
//! warm start and noisy copies of it), [`ADAM_ITERATIONS`] Adam steps of
//! [`crate::plan::AdamConfig::default`]'s learning rate (0.1 of each action's half-range).
//! With them one plan back-propagates `31 × 16` rollouts against CEM's `5 × 400–500` forward
//! ones.
//!
//! A run's preset is then adjusted by the daemon's configured overrides and the attaching
//! agent's own overrides, in that order.

use crate::dynamics::DynamicsConfig;
use crate::energy::{EnergyConfig, NoiseUnits, RegularizerKind};
use crate::plan::{AdamConfig, CemConfig, IcemConfig, Optimizer};
use crate::reward::RewardConfig;
use proto::{
    Builtin, EpochSchedule, InferencePrecision, PlannerOverrides, RegularizerChoice, Task,
};

/// The methods a preset can be built for (see the module docs).
pub const METHODS: &[&str] = &[
    "cem",
    "cem+dae",
    "cem+deen",
    "pets",
    "pets+deen",
    "adam+dae",
];

/// Sequences the `adam+dae` preset optimises together (a documented choice, see above).
pub const ADAM_CANDIDATES: usize = 16;
/// Adam steps per plan in the `adam+dae` preset (a documented choice, see above).
pub const ADAM_ITERATIONS: usize = 30;

/// The method a run uses when it names none: the paper's.
pub const DEFAULT_METHOD: &str = "cem+deen";

/// Everything a run needs to know to learn and plan.
#[derive(Clone, Debug, PartialEq)]
pub struct Preset {
    /// The method name (one of [`METHODS`]).
    pub method: String,
    /// The task the run learns.
    pub task: &'static Task,
    pub dynamics: DynamicsConfig,
    pub regularizer: RegularizerKind,
    pub energy: EnergyConfig,
    /// Sizes of the reward model, trained and used only for a task whose reward is learned
    /// (its training settings are the dynamics').
    pub reward: RewardConfig,
    /// `alpha`: weight of the energy in the planning objective (Table 2's cost multiplier).
    pub energy_weight: f32,
    pub cem: CemConfig,
    /// Sample the dynamics' predicted Gaussian in imagination (PETS TS∞) instead of its mean.
    pub sample_dynamics: bool,
    /// Episodes of uniformly random actions before planning starts.
    pub exploration_episodes: u32,
    /// Transitions of uniformly random actions before planning starts, on top of the
    /// episodes (both must be reached; 0: the episodes alone, as the paper's presets).
    pub exploration_steps: u64,
    /// How the number of training epochs changes as episodes accumulate.
    pub schedule: EpochSchedule,
    /// Most gradient steps per model in one retraining; `None` (the paper's presets) trains
    /// the schedule's full epochs however large the buffer has grown.
    pub max_gradient_steps: Option<u64>,
    /// Number format of planning-time inference: `auto` by default (each network runs the
    /// kernel path measured fastest for its shapes on this CPU, see `crate::nn::kernel_path`);
    /// `f32` or `bf16` when a run asks for one.
    pub inference_precision: InferencePrecision,
    /// Milliseconds from an observation's arrival to its action (`None`: no deadline). The
    /// task's control period unless overridden: a robot needs its action within it.
    pub deadline_ms: Option<u32>,
}

/// The shortest deadline a run may ask for: below it a plan cannot even be answered in time
/// (decoding, storing and publishing take a millisecond or so).
pub const MIN_DEADLINE_MS: u32 = 5;

/// A task's control period in whole milliseconds (at least 1): its default deadline.
fn control_period_ms(task: &Task) -> u32 {
    ((task.control_dt * 1e3).round() as u32).max(1)
}

/// iCEM's parameters for a task's runs that plan with `optimizer = "icem"` (overridable per
/// run). The colored-noise exponent `β` must suit the task's motion: Pinneri et al. tune it per
/// environment, 0.25 for HalfCheetah Running and 2–3.5 for their humanoid and manipulation
/// tasks. Smooth noise (`β = 2`) has almost no power at the few-step period at which a running
/// gait reverses each joint, so on half-cheetah iCEM then plans about as well as standing
/// still. Keeping elites across iterations and steps, which the paper measured with the true
/// simulator as its model, makes iCEM on a *learned* half-cheetah model keep re-selecting the
/// sequences that exploit the model's errors; without it the real return is higher. Both
/// half-cheetah values are measured with `ebmpc-experiment replan` (see docs/performance.md, iCEM
/// section). Ant walks with a gait too and takes the same values by analogy (not measured);
/// the other tasks keep [`IcemConfig::default`] (the paper's general values).
fn icem_for(task: Builtin) -> IcemConfig {
    match task {
        Builtin::HalfCheetah | Builtin::Ant => IcemConfig {
            noise_beta: 0.25,
            keep_elites: 0.0,
            ..IcemConfig::default()
        },
        Builtin::Cartpole | Builtin::Reacher3d | Builtin::Pusher => IcemConfig::default(),
    }
}

fn default_precision() -> InferencePrecision {
    InferencePrecision::Auto
}

impl Preset {
    /// `(dynamics epochs, energy epochs)` for a retraining on `transitions` stored transitions
    /// from `episodes` finished episodes, by the preset's [`EpochSchedule`].
    pub fn epochs(&self, episodes: u32, transitions: usize) -> (usize, usize) {
        let (dynamics, energy) = (self.dynamics.epochs, self.energy.epochs);
        match self.schedule {
            EpochSchedule::Constant => (dynamics, energy),
            EpochSchedule::DropAfter {
                after_episodes,
                epochs,
            } if episodes >= after_episodes => (epochs as usize, epochs as usize),
            EpochSchedule::DropAfter { .. } => (dynamics, energy),
            EpochSchedule::Geometric {
                dynamics_factor,
                energy_factor,
                min_epochs,
            } => {
                // The decay makes up for an epoch's growing length as the buffer fills, so it
                // counts the data gathered after exploration in time limits' worth of
                // transitions, at most one per planned episode: a planned episode cut short
                // by a fall counts for the share of the time limit it lasted. Counting
                // episodes alone, a run of early falls (an ant flipping within 20 steps, ten
                // times) would cut the epochs to the floor before the buffer held one
                // episode's worth, and the models would then barely learn from what came next.
                let planned = episodes.saturating_sub(self.exploration_episodes) as f32;
                let gathered = transitions as f32 / self.task.episode_len.max(1) as f32
                    - self.exploration_episodes as f32;
                let decays = gathered.clamp(0.0, planned);
                let decay = |epochs: usize, factor: f32| {
                    ((epochs as f32 * factor.powf(decays)).round() as usize)
                        .max(min_epochs as usize)
                };
                (
                    decay(dynamics, dynamics_factor),
                    decay(energy, energy_factor),
                )
            }
        }
    }
}

/// A preset that cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PresetError {
    #[error("unknown preset `{0}` (known: {known})", known = METHODS.join(", "))]
    UnknownMethod(String),
    #[error("invalid override: {0}")]
    InvalidOverride(String),
}

/// Table 2's numbers for one task.
struct TaskTable {
    model_layers: usize,
    model_size: usize,
    model_epochs: usize,
    model_batch: usize,
    energy_layers: usize,
    energy_size: usize,
    energy_epochs: usize,
    energy_batch: usize,
    sigma: f32,
    /// The units `sigma` corrupts transitions in. The paper corrupts the replay buffer's raw
    /// transitions; standardised units were this planner's first reading and stay where they
    /// were measured to match the paper. Pusher needs raw: with σ on standardised transitions
    /// the energy is steep in the object's few-centimetre directions and CEM + DEEN ends at
    /// −219 ± 26 against CEM's −112 ± 9, with raw σ at −119 ± 15 (docs/results.md, "Pusher:
    /// DEEN's penalty").
    noise_units: NoiseUnits,
    alpha: f32,
    horizon: usize,
    population: usize,
    elites: usize,
    iterations: usize,
    exploration_episodes: u32,
    schedule: EpochSchedule,
}

fn table(task: Builtin) -> TaskTable {
    match task {
        Builtin::Cartpole => TaskTable {
            model_layers: 3,
            model_size: 200,
            model_epochs: 500,
            model_batch: 32,
            energy_layers: 3,
            energy_size: 200,
            energy_epochs: 500,
            energy_batch: 32,
            sigma: 0.1,
            noise_units: NoiseUnits::Standardised,
            alpha: 0.001,
            horizon: 25,
            population: 400,
            elites: 40,
            iterations: 5,
            exploration_episodes: 1,
            schedule: EpochSchedule::Constant,
        },
        Builtin::Reacher3d => TaskTable {
            model_layers: 3,
            model_size: 200,
            model_epochs: 500,
            model_batch: 32,
            energy_layers: 3,
            energy_size: 200,
            energy_epochs: 500,
            energy_batch: 32,
            sigma: 0.1,
            noise_units: NoiseUnits::Standardised,
            alpha: 0.001,
            horizon: 25,
            population: 400,
            elites: 40,
            iterations: 5,
            exploration_episodes: 1,
            schedule: EpochSchedule::Constant,
        },
        Builtin::Pusher => TaskTable {
            model_layers: 3,
            model_size: 200,
            model_epochs: 100,
            model_batch: 32,
            energy_layers: 3,
            energy_size: 200,
            energy_epochs: 100,
            energy_batch: 32,
            sigma: 0.1,
            noise_units: NoiseUnits::Raw,
            alpha: 0.01,
            horizon: 25,
            population: 500,
            elites: 50,
            iterations: 5,
            exploration_episodes: 1,
            schedule: EpochSchedule::Constant,
        },
        Builtin::HalfCheetah => TaskTable {
            model_layers: 4,
            model_size: 200,
            model_epochs: 300,
            model_batch: 128,
            energy_layers: 5,
            energy_size: 500,
            energy_epochs: 100,
            energy_batch: 32,
            sigma: 0.37,
            noise_units: NoiseUnits::Standardised,
            alpha: 0.05,
            horizon: 30,
            population: 500,
            elites: 50,
            iterations: 5,
            exploration_episodes: 3,
            schedule: EpochSchedule::DropAfter {
                after_episodes: 10,
                epochs: 8,
            },
        },
        Builtin::Ant => TaskTable {
            model_layers: 4,
            model_size: 400,
            model_epochs: 600,
            model_batch: 400,
            energy_layers: 3,
            energy_size: 300,
            energy_epochs: 800,
            energy_batch: 64,
            sigma: 0.9,
            noise_units: NoiseUnits::Standardised,
            alpha: 0.035,
            horizon: 30,
            population: 500,
            elites: 50,
            iterations: 7,
            exploration_episodes: 1,
            schedule: EpochSchedule::Geometric {
                dynamics_factor: 0.6,
                energy_factor: 0.7,
                min_epochs: 5,
            },
        },
    }
}

impl Preset {
    /// The preset for `task` and `method` (`None`: [`DEFAULT_METHOD`]): the sizes of the task's
    /// base preset (a catalog task's own Table 2 row; a custom task names the row it starts
    /// from, its `base_preset`), the deadline of its control period.
    pub fn new(task: &'static Task, method: Option<&str>) -> Result<Self, PresetError> {
        let method = method.unwrap_or(DEFAULT_METHOD);
        let adam = method == "adam+dae";
        let (pets, regularizer) = match method {
            "cem" => (false, RegularizerKind::None),
            "adam+dae" => (false, RegularizerKind::Dae),
            "cem+dae" => (false, RegularizerKind::Dae),
            "cem+deen" => (false, RegularizerKind::Deen),
            "pets" => (true, RegularizerKind::None),
            "pets+deen" => (true, RegularizerKind::Deen),
            other => return Err(PresetError::UnknownMethod(other.to_string())),
        };
        let t = table(task.base_preset);
        Ok(Preset {
            method: method.to_string(),
            task,
            dynamics: DynamicsConfig {
                hidden_layers: t.model_layers,
                hidden_size: t.model_size,
                ensemble_size: if pets { 5 } else { 1 },
                epochs: t.model_epochs,
                batch_size: t.model_batch,
                learning_rate: 1e-3,
                weight_decay: 5e-5,
            },
            regularizer,
            energy: EnergyConfig {
                hidden_layers: t.energy_layers,
                hidden_size: t.energy_size,
                epochs: t.energy_epochs,
                batch_size: t.energy_batch,
                noise_sigma: t.sigma,
                noise_units: t.noise_units,
                learning_rate: 1e-3,
            },
            reward: RewardConfig::default(),
            energy_weight: t.alpha,
            cem: CemConfig {
                horizon: t.horizon,
                population: if adam { ADAM_CANDIDATES } else { t.population },
                elites: if adam { 1 } else { t.elites },
                iterations: if adam { ADAM_ITERATIONS } else { t.iterations },
                smoothing: 0.1,
                min_variance: 1e-3,
                particles: if pets { 20 } else { 1 },
                optimizer: if adam {
                    Optimizer::Adam
                } else {
                    Optimizer::Cem
                },
                icem: icem_for(task.base_preset),
                adam: AdamConfig::default(),
            },
            sample_dynamics: pets,
            exploration_episodes: t.exploration_episodes,
            exploration_steps: 0,
            schedule: t.schedule,
            max_gradient_steps: None,
            inference_precision: default_precision(),
            deadline_ms: Some(control_period_ms(task)),
        })
    }

    /// The preset of `method` for `task`, a task compiled but not interned yet (a client's
    /// spec, checked before anything is kept for it: see [`proto::Task::compile_unshared`]):
    /// as [`Preset::new`], sized from the task's base preset and with its control period as
    /// deadline. Its `task` is the base preset's catalog task until the caller, having checked
    /// it ([`crate::config::Limits::check_for`] with `task`), interns `task` and puts it there.
    pub fn unshared(task: &Task, method: Option<&str>) -> Result<Self, PresetError> {
        let mut preset = Self::new(task.base_preset.task(), method)?;
        preset.deadline_ms = Some(control_period_ms(task));
        Ok(preset)
    }

    /// The optimiser overrides: the choice and iCEM's parameters, each checked against its
    /// range ([`IcemConfig::validate`]); iCEM parameters without iCEM are refused rather than
    /// silently ignored.
    fn apply_optimizer(&mut self, o: &PlannerOverrides) -> Result<(), PresetError> {
        if let Some(optimizer) = o.optimizer {
            self.cem.optimizer = optimizer;
        }
        let icem = [
            o.icem_noise_beta
                .map(|v| (&mut self.cem.icem.noise_beta, v)),
            o.icem_keep_elites
                .map(|v| (&mut self.cem.icem.keep_elites, v)),
            o.icem_population_decay
                .map(|v| (&mut self.cem.icem.population_decay, v)),
        ];
        let mut any = false;
        for (field, value) in icem.into_iter().flatten() {
            *field = value;
            any = true;
        }
        if any && self.cem.optimizer != Optimizer::Icem {
            return Err(PresetError::InvalidOverride(
                "icem_* overrides need optimizer = \"icem\"".to_string(),
            ));
        }
        if let Some(lr) = o.adam_learning_rate {
            if self.cem.optimizer != Optimizer::Adam {
                return Err(PresetError::InvalidOverride(
                    "adam_learning_rate needs optimizer = \"adam\"".to_string(),
                ));
            }
            self.cem.adam.learning_rate = lr;
        }
        self.cem
            .adam
            .validate()
            .map_err(|e| PresetError::InvalidOverride(e.to_string()))?;
        self.cem
            .icem
            .validate()
            .map_err(|e| PresetError::InvalidOverride(e.to_string()))
    }

    /// Applies `overrides` (fields that are `Some`), checking that each value and the result
    /// make sense. Sizes are only checked to be at least 1 here: their upper bounds are the
    /// daemon's [`super::Limits`], checked on the finished preset.
    pub fn apply(&mut self, o: &PlannerOverrides) -> Result<(), PresetError> {
        fn count(target: &mut usize, value: Option<u32>, name: &str) -> Result<(), PresetError> {
            match value {
                Some(0) => Err(invalid(format!("{name} must be at least 1"))),
                Some(v) => {
                    *target = v as usize;
                    Ok(())
                }
                None => Ok(()),
            }
        }
        /// A real number within `range` (its ends as the range says).
        fn real(
            target: &mut f32,
            value: Option<f32>,
            name: &str,
            range: impl std::ops::RangeBounds<f32> + std::fmt::Debug,
        ) -> Result<(), PresetError> {
            match value {
                Some(v) if v.is_finite() && range.contains(&v) => {
                    *target = v;
                    Ok(())
                }
                Some(v) => Err(invalid(format!("{name} must be in {range:?}, not {v}"))),
                None => Ok(()),
            }
        }
        if let Some(r) = o.regularizer {
            self.regularizer = match r {
                RegularizerChoice::None => RegularizerKind::None,
                RegularizerChoice::Dae => RegularizerKind::Dae,
                RegularizerChoice::Deen => RegularizerKind::Deen,
            };
        }
        real(
            &mut self.energy_weight,
            o.energy_weight,
            "energy_weight",
            0.0..=MAX_ENERGY_WEIGHT,
        )?;
        let (d, e, c) = (&mut self.dynamics, &mut self.energy, &mut self.cem);
        count(&mut d.ensemble_size, o.ensemble_size, "ensemble_size")?;
        count(&mut c.particles, o.particles, "particles")?;
        count(&mut c.horizon, o.horizon, "horizon")?;
        count(&mut c.population, o.population, "population")?;
        count(&mut c.elites, o.elites, "elites")?;
        count(&mut c.iterations, o.cem_iterations, "cem_iterations")?;
        real(&mut c.smoothing, o.cem_smoothing, "cem_smoothing", 0.0..1.0)?;
        real(
            &mut c.min_variance,
            o.cem_min_variance,
            "cem_min_variance",
            0.0..=MAX_CEM_MIN_VARIANCE,
        )?;
        count(&mut d.epochs, o.dynamics_epochs, "dynamics_epochs")?;
        count(
            &mut d.hidden_layers,
            o.dynamics_hidden_layers,
            "dynamics_hidden_layers",
        )?;
        count(
            &mut d.hidden_size,
            o.dynamics_hidden_size,
            "dynamics_hidden_size",
        )?;
        count(
            &mut d.batch_size,
            o.dynamics_batch_size,
            "dynamics_batch_size",
        )?;
        real(
            &mut d.learning_rate,
            o.dynamics_learning_rate,
            "dynamics_learning_rate",
            LEARNING_RATES,
        )?;
        real(
            &mut d.weight_decay,
            o.dynamics_weight_decay,
            "dynamics_weight_decay",
            0.0..=1.0,
        )?;
        count(
            &mut self.reward.hidden_layers,
            o.reward_hidden_layers,
            "reward_hidden_layers",
        )?;
        count(
            &mut self.reward.hidden_size,
            o.reward_hidden_size,
            "reward_hidden_size",
        )?;
        count(&mut e.epochs, o.energy_epochs, "energy_epochs")?;
        count(
            &mut e.hidden_layers,
            o.energy_hidden_layers,
            "energy_hidden_layers",
        )?;
        count(
            &mut e.hidden_size,
            o.energy_hidden_size,
            "energy_hidden_size",
        )?;
        count(&mut e.batch_size, o.energy_batch_size, "energy_batch_size")?;
        real(
            &mut e.learning_rate,
            o.energy_learning_rate,
            "energy_learning_rate",
            LEARNING_RATES,
        )?;
        real(
            &mut e.noise_sigma,
            o.energy_noise_sigma,
            "energy_noise_sigma",
            MIN_NOISE_SIGMA..=MAX_NOISE_SIGMA,
        )?;
        if let Some(units) = o.energy_noise_units {
            e.noise_units = units;
        }
        if let Some(sample) = o.sample_dynamics {
            self.sample_dynamics = sample;
        }
        if let Some(e) = o.exploration_episodes {
            self.exploration_episodes = e;
        }
        if let Some(steps) = o.exploration_steps {
            self.exploration_steps = steps;
        }
        if let Some(schedule) = &o.epoch_schedule {
            check_schedule(schedule)?;
            self.schedule = schedule.clone();
        }
        match o.max_gradient_steps {
            Some(0) => return Err(invalid("max_gradient_steps must be at least 1".into())),
            Some(steps) => self.max_gradient_steps = Some(steps),
            None => {}
        }
        if let Some(p) = o.inference_precision {
            self.inference_precision = p;
        }
        match o.deadline_ms {
            Some(0) => self.deadline_ms = None,
            Some(ms) if ms < MIN_DEADLINE_MS => {
                return Err(invalid(format!(
                    "deadline_ms must be 0 (off) or at least {MIN_DEADLINE_MS}, not {ms}"
                )));
            }
            Some(ms) => self.deadline_ms = Some(ms),
            None => {}
        }
        self.apply_optimizer(o)?;
        if self.cem.elites > self.cem.population {
            return Err(invalid(format!(
                "elites ({}) cannot exceed population ({})",
                self.cem.elites, self.cem.population
            )));
        }
        Ok(())
    }
}

/// Adam step sizes a run may ask for: above 1 every step overshoots.
const LEARNING_RATES: std::ops::RangeInclusive<f32> = 1e-7..=1.0;
/// The energy weight's upper end: far above Table 2's 0.001–0.05, where the energy drowns
/// out the reward entirely.
const MAX_ENERGY_WEIGHT: f32 = 1e3;
/// CEM's variance floor, in squared action units (actions are bounded, so more is no search).
const MAX_CEM_MIN_VARIANCE: f32 = 1e3;
/// The denoisers' noise scale, in standardised units (Table 2 uses 0.1–0.9).
const MIN_NOISE_SIGMA: f32 = 1e-4;
const MAX_NOISE_SIGMA: f32 = 10.0;

fn invalid(message: String) -> PresetError {
    PresetError::InvalidOverride(message)
}

/// An epoch schedule's own numbers make sense (its epochs' upper bound is a limit).
fn check_schedule(schedule: &EpochSchedule) -> Result<(), PresetError> {
    match *schedule {
        EpochSchedule::Constant => Ok(()),
        EpochSchedule::DropAfter { epochs: 0, .. } => Err(invalid(
            "epoch_schedule.drop_after.epochs must be at least 1".into(),
        )),
        EpochSchedule::DropAfter { .. } => Ok(()),
        EpochSchedule::Geometric {
            dynamics_factor,
            energy_factor,
            min_epochs,
        } => {
            for (name, f) in [
                ("dynamics_factor", dynamics_factor),
                ("energy_factor", energy_factor),
            ] {
                if !(f.is_finite() && f > 0.0 && f <= 1.0) {
                    return Err(invalid(format!(
                        "epoch_schedule.geometric.{name} must be in (0, 1], not {f}"
                    )));
                }
            }
            if min_epochs == 0 {
                return Err(invalid(
                    "epoch_schedule.geometric.min_epochs must be at least 1".into(),
                ));
            }
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every number of the paper's Table 2, task by task, as every preset carries it (PETS
    /// adds its ensemble and particles on top; Adam + DAE replaces the CEM search).
    #[test]
    fn every_preset_carries_all_of_table_two() {
        // model (layers, size, epochs, batch), DEEN (layers, size, epochs, batch, σ, α),
        // CEM iterations — the paper's columns Cartpole, Reacher, Pusher, Half-cheetah, Ant.
        type Row = (Builtin, [usize; 4], [usize; 4], f32, f32, usize);
        #[rustfmt::skip]
        let table: [Row; 5] = [
            (Builtin::Cartpole,    [3, 200, 500, 32],  [3, 200, 500, 32], 0.1,  0.001, 5),
            (Builtin::Reacher3d,   [3, 200, 500, 32],  [3, 200, 500, 32], 0.1,  0.001, 5),
            (Builtin::Pusher,      [3, 200, 100, 32],  [3, 200, 100, 32], 0.1,  0.01,  5),
            (Builtin::HalfCheetah, [4, 200, 300, 128], [5, 500, 100, 32], 0.37, 0.05,  5),
            (Builtin::Ant,         [4, 400, 600, 400], [3, 300, 800, 64], 0.9,  0.035, 7),
        ];
        for (task, model, deen, sigma, alpha, iterations) in table {
            for method in METHODS {
                let p = Preset::new(task.task(), Some(method)).unwrap();
                let d = &p.dynamics;
                let e = &p.energy;
                assert_eq!(
                    [d.hidden_layers, d.hidden_size, d.epochs, d.batch_size],
                    model,
                    "{task} {method} model"
                );
                assert_eq!(
                    [e.hidden_layers, e.hidden_size, e.epochs, e.batch_size],
                    deen,
                    "{task} {method} energy network"
                );
                assert_eq!(
                    (e.noise_sigma, p.energy_weight),
                    (sigma, alpha),
                    "{task} {method}"
                );
                let pets = method.starts_with("pets");
                assert_eq!(
                    (d.ensemble_size, p.cem.particles, p.sample_dynamics),
                    if pets { (5, 20, true) } else { (1, 1, false) },
                    "{task} {method} dynamics"
                );
                if *method != "adam+dae" {
                    assert_eq!(
                        p.cem.iterations, iterations,
                        "{task} {method} CEM iterations"
                    );
                }
            }
        }
    }

    #[test]
    fn table_two_numbers() {
        let hc = Preset::new(Builtin::HalfCheetah.task(), None).unwrap();
        assert_eq!(hc.method, "cem+deen");
        assert_eq!((hc.energy.hidden_layers, hc.energy.hidden_size), (5, 500));
        assert_eq!(hc.energy_weight, 0.05);
        assert_eq!(hc.exploration_episodes, 3);
        assert_eq!(hc.epochs(5, 5000), (300, 100));
        assert_eq!(hc.epochs(10, 10_000), (8, 8));
        let ant = Preset::new(Builtin::Ant.task(), Some("pets")).unwrap();
        assert_eq!(
            (
                ant.dynamics.ensemble_size,
                ant.cem.particles,
                ant.cem.iterations
            ),
            (5, 20, 7)
        );
        assert_eq!(ant.regularizer, RegularizerKind::None);
        assert_eq!(ant.epochs(1, 1000), (600, 800));
        assert_eq!(ant.epochs(2, 2000), (360, 560));
        let pusher = Preset::new(Builtin::Pusher.task(), None).unwrap();
        assert_eq!(
            (
                pusher.dynamics.epochs,
                pusher.energy.epochs,
                pusher.energy_weight
            ),
            (100, 100, 0.01)
        );
        assert_eq!(
            (pusher.cem.population, pusher.cem.elites, pusher.cem.horizon),
            (500, 50, 25)
        );
        // Pusher's σ corrupts raw transitions, as the paper's does; the tasks whose results
        // were measured with standardised σ keep it.
        assert_eq!(pusher.energy.noise_units, NoiseUnits::Raw);
        assert_eq!(ant.energy.noise_units, NoiseUnits::Standardised);
        assert!(Preset::new(Builtin::Cartpole.task(), Some("sac")).is_err());
    }

    /// The ant's geometric decay counts data, not resets: ten planned episodes that fell
    /// within 20 steps leave the epochs near Table 2's, while full-length episodes decay once
    /// each, and no more than once per planned episode however long the exploration ran.
    #[test]
    fn geometric_decay_counts_time_limits_of_data() {
        let ant = Preset::new(Builtin::Ant.task(), None).unwrap();
        assert_eq!(ant.exploration_episodes, 1);
        // One exploration episode of 1,000 steps, then ten falls of 20 steps: 0.2 decays.
        let (dynamics, energy) = ant.epochs(11, 1200);
        assert_eq!(
            (dynamics, energy),
            (
                (600.0 * 0.6f32.powf(0.2)).round() as usize,
                (800.0 * 0.7f32.powf(0.2)).round() as usize
            )
        );
        assert!(dynamics > 500, "{dynamics}");
        // Five whole planned episodes: five decays, as the paper's per-episode schedule.
        assert_eq!(
            ant.epochs(6, 6000),
            (
                (600.0 * 0.6f32.powi(5)).round() as usize,
                (800.0 * 0.7f32.powi(5)).round() as usize
            )
        );
        // A short exploration episode does not make the first planned one count twice.
        assert_eq!(ant.epochs(2, 2000), (360, 560));
        // The floor.
        assert_eq!(ant.epochs(40, 40_000), (5, 5));
        // No decay before the data outgrow the exploration episodes' time limits.
        assert_eq!(ant.epochs(4, 400), (600, 800));
    }

    #[test]
    fn overrides_apply_and_are_checked() {
        let mut p = Preset::new(Builtin::Cartpole.task(), None).unwrap();
        assert_eq!(p.inference_precision, InferencePrecision::Auto);
        let o = PlannerOverrides {
            regularizer: Some(RegularizerChoice::Dae),
            population: Some(50),
            elites: Some(5),
            inference_precision: Some(InferencePrecision::F32),
            ..Default::default()
        };
        p.apply(&o).unwrap();
        assert_eq!(
            (
                p.regularizer,
                p.cem.population,
                p.cem.elites,
                p.inference_precision
            ),
            (RegularizerKind::Dae, 50, 5, InferencePrecision::F32)
        );
        let bad = PlannerOverrides {
            elites: Some(500),
            ..Default::default()
        };
        assert!(p.apply(&bad).is_err());
        let zero = PlannerOverrides {
            horizon: Some(0),
            ..Default::default()
        };
        assert!(p.apply(&zero).is_err());
        let nan = PlannerOverrides {
            energy_weight: Some(f32::NAN),
            ..Default::default()
        };
        assert!(p.apply(&nan).is_err());
    }

    /// `adam+dae`: one model, the DAE, Adam with the documented settings and the task's
    /// Table 2 horizon and `α`; its learning rate is overridable within its range, and only
    /// with Adam.
    #[test]
    fn adam_dae_preset_and_its_learning_rate_override() {
        for &task in Builtin::ALL {
            let p = Preset::new(task.task(), Some("adam+dae")).unwrap();
            let dae = Preset::new(task.task(), Some("cem+dae")).unwrap();
            assert_eq!(p.cem.optimizer, Optimizer::Adam);
            assert_eq!(p.regularizer, RegularizerKind::Dae);
            assert_eq!(
                (p.dynamics.clone(), p.energy.clone()),
                (dae.dynamics, dae.energy)
            );
            assert_eq!(
                (p.energy_weight, p.cem.horizon),
                (dae.energy_weight, dae.cem.horizon)
            );
            assert_eq!(
                (p.cem.population, p.cem.iterations, p.cem.particles),
                (ADAM_CANDIDATES, ADAM_ITERATIONS, 1)
            );
            assert!(!p.sample_dynamics);
            p.cem.validate().unwrap();
        }
        let mut p = Preset::new(Builtin::Cartpole.task(), Some("adam+dae")).unwrap();
        p.apply(&PlannerOverrides {
            adam_learning_rate: Some(0.3),
            ..Default::default()
        })
        .unwrap();
        assert_eq!(p.cem.adam.learning_rate, 0.3);
        for hostile in [0.0, -1.0, f32::NAN, f32::INFINITY, 1e30] {
            let mut p = Preset::new(Builtin::Cartpole.task(), Some("adam+dae")).unwrap();
            let err = p
                .apply(&PlannerOverrides {
                    adam_learning_rate: Some(hostile),
                    ..Default::default()
                })
                .unwrap_err();
            assert!(
                err.to_string().contains("learning_rate"),
                "{hostile}: {err}"
            );
        }
        let mut cem = Preset::new(Builtin::Cartpole.task(), Some("cem")).unwrap();
        let err = cem
            .apply(&PlannerOverrides {
                adam_learning_rate: Some(0.3),
                ..Default::default()
            })
            .unwrap_err();
        assert!(err.to_string().contains("optimizer"), "{err}");
    }

    /// Every preset field can be overridden, each to a value that then lands in the preset.
    #[test]
    fn every_preset_field_can_be_overridden() {
        let mut p = Preset::new(Builtin::Cartpole.task(), Some("cem")).unwrap();
        let schedule = EpochSchedule::Geometric {
            dynamics_factor: 0.5,
            energy_factor: 0.25,
            min_epochs: 3,
        };
        let o = PlannerOverrides {
            regularizer: Some(RegularizerChoice::Deen),
            energy_weight: Some(0.5),
            ensemble_size: Some(3),
            particles: Some(4),
            horizon: Some(6),
            population: Some(70),
            elites: Some(7),
            cem_iterations: Some(2),
            cem_smoothing: Some(0.3),
            cem_min_variance: Some(0.01),
            sample_dynamics: Some(true),
            exploration_episodes: Some(2),
            exploration_steps: Some(500),
            dynamics_epochs: Some(11),
            dynamics_hidden_layers: Some(2),
            dynamics_hidden_size: Some(12),
            dynamics_batch_size: Some(13),
            dynamics_learning_rate: Some(2e-3),
            dynamics_weight_decay: Some(1e-4),
            reward_hidden_layers: Some(3),
            reward_hidden_size: Some(17),
            energy_epochs: Some(14),
            energy_hidden_layers: Some(1),
            energy_hidden_size: Some(15),
            energy_batch_size: Some(16),
            energy_learning_rate: Some(3e-3),
            energy_noise_sigma: Some(0.2),
            energy_noise_units: Some(proto::NoiseUnits::Raw),
            epoch_schedule: Some(schedule.clone()),
            max_gradient_steps: Some(1000),
            inference_precision: Some(InferencePrecision::F32),
            optimizer: Some(Optimizer::Icem),
            icem_noise_beta: Some(1.5),
            icem_keep_elites: Some(0.2),
            icem_population_decay: Some(1.5),
            adam_learning_rate: None,
            deadline_ms: Some(25),
        };
        p.apply(&o).unwrap();
        assert_eq!(p.deadline_ms, Some(25));
        assert_eq!(p.cem.optimizer, Optimizer::Icem);
        assert_eq!(
            (
                p.cem.icem.noise_beta,
                p.cem.icem.keep_elites,
                p.cem.icem.population_decay
            ),
            (1.5, 0.2, 1.5)
        );
        let d = &p.dynamics;
        let e = &p.energy;
        let c = &p.cem;
        assert_eq!(p.regularizer, RegularizerKind::Deen);
        assert_eq!(p.energy_weight, 0.5);
        assert_eq!(
            (
                d.ensemble_size,
                d.epochs,
                d.hidden_layers,
                d.hidden_size,
                d.batch_size
            ),
            (3, 11, 2, 12, 13)
        );
        assert_eq!((d.learning_rate, d.weight_decay), (2e-3, 1e-4));
        assert_eq!(
            (e.epochs, e.hidden_layers, e.hidden_size, e.batch_size),
            (14, 1, 15, 16)
        );
        assert_eq!((e.learning_rate, e.noise_sigma), (3e-3, 0.2));
        assert_eq!(e.noise_units, proto::NoiseUnits::Raw);
        assert_eq!((p.reward.hidden_layers, p.reward.hidden_size), (3, 17));
        assert_eq!(
            (c.particles, c.horizon, c.population, c.elites, c.iterations),
            (4, 6, 70, 7, 2)
        );
        assert_eq!((c.smoothing, c.min_variance), (0.3, 0.01));
        assert!(p.sample_dynamics);
        assert_eq!((p.exploration_episodes, p.exploration_steps), (2, 500));
        assert_eq!(p.schedule, schedule);
        assert_eq!(p.max_gradient_steps, Some(1000));
        assert_eq!(p.inference_precision, InferencePrecision::F32);
        // Every field of the preset is reached: a preset field added without an override
        // makes this list (and so this test) fail to compile.
        let Preset {
            method: _,
            task: _,
            dynamics: _,
            regularizer: _,
            energy: _,
            reward: _,
            energy_weight: _,
            cem: _,
            sample_dynamics: _,
            exploration_episodes: _,
            exploration_steps: _,
            schedule: _,
            max_gradient_steps: _,
            inference_precision: _,
            deadline_ms: _,
        } = p;
    }

    /// A custom task's preset is its base preset's Table 2 row, with the deadline of its own
    /// control period; overrides apply on top as for any task.
    #[test]
    fn a_custom_task_starts_from_its_base_preset() {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "slow-arm".into();
        spec.control_dt = 0.1;
        spec.base_preset = Builtin::Reacher3d;
        spec.model = proto::task::ModelTransforms::default();
        let task = Task::intern(spec, &Default::default()).unwrap();
        let custom = Preset::new(task, Some("cem+deen")).unwrap();
        let reacher = Preset::new(Builtin::Reacher3d.task(), Some("cem+deen")).unwrap();
        assert_eq!(custom.dynamics, reacher.dynamics);
        assert_eq!(custom.energy, reacher.energy);
        assert_eq!(custom.cem, reacher.cem);
        assert_eq!(custom.deadline_ms, Some(100));
        assert_eq!(custom.task.name(), "slow-arm");
    }

    /// A run's deadline is its task's control period unless overridden; 0 turns it off, and
    /// a deadline too short to answer in is refused.
    #[test]
    fn the_deadline_defaults_to_the_control_period() {
        let period = |task: Builtin| Preset::new(task.task(), None).unwrap().deadline_ms;
        assert_eq!(period(Builtin::Cartpole), Some(40));
        assert_eq!(period(Builtin::Reacher3d), Some(20));
        assert_eq!(period(Builtin::HalfCheetah), Some(50));
        let mut p = Preset::new(Builtin::Cartpole.task(), None).unwrap();
        let deadline = |ms| PlannerOverrides {
            deadline_ms: Some(ms),
            ..Default::default()
        };
        p.apply(&deadline(0)).unwrap();
        assert_eq!(p.deadline_ms, None);
        p.apply(&deadline(200)).unwrap();
        assert_eq!(p.deadline_ms, Some(200));
        for hostile in [1, MIN_DEADLINE_MS - 1] {
            let err = p.apply(&deadline(hostile)).unwrap_err().to_string();
            assert!(err.contains("deadline_ms"), "{err}");
        }
        // The upper bound is a limit: u32::MAX is over it.
        p.apply(&deadline(u32::MAX)).unwrap();
        let err = crate::config::Limits::default().check(&p).unwrap_err();
        assert_eq!((err.field, err.setting), ("deadline_ms", "max_deadline_ms"));
    }

    /// Hostile values of every real-valued and scheduled override are refused, naming the field.
    #[test]
    fn hostile_overrides_are_refused_by_name() {
        let base = Preset::new(Builtin::Cartpole.task(), None).unwrap();
        let o = PlannerOverrides::default;
        let cases: Vec<(PlannerOverrides, &str)> = vec![
            (
                PlannerOverrides {
                    energy_weight: Some(-1.0),
                    ..o()
                },
                "energy_weight",
            ),
            (
                PlannerOverrides {
                    energy_weight: Some(f32::INFINITY),
                    ..o()
                },
                "energy_weight",
            ),
            (
                PlannerOverrides {
                    energy_weight: Some(1e30),
                    ..o()
                },
                "energy_weight",
            ),
            (
                PlannerOverrides {
                    cem_smoothing: Some(1.0),
                    ..o()
                },
                "cem_smoothing",
            ),
            (
                PlannerOverrides {
                    cem_smoothing: Some(f32::NAN),
                    ..o()
                },
                "cem_smoothing",
            ),
            (
                PlannerOverrides {
                    cem_min_variance: Some(-0.1),
                    ..o()
                },
                "cem_min_variance",
            ),
            (
                PlannerOverrides {
                    cem_min_variance: Some(f32::MAX),
                    ..o()
                },
                "cem_min_variance",
            ),
            (
                PlannerOverrides {
                    dynamics_learning_rate: Some(0.0),
                    ..o()
                },
                "dynamics_learning_rate",
            ),
            (
                PlannerOverrides {
                    dynamics_learning_rate: Some(1e9),
                    ..o()
                },
                "dynamics_learning_rate",
            ),
            (
                PlannerOverrides {
                    dynamics_weight_decay: Some(-1e-3),
                    ..o()
                },
                "dynamics_weight_decay",
            ),
            (
                PlannerOverrides {
                    energy_learning_rate: Some(f32::NAN),
                    ..o()
                },
                "energy_learning_rate",
            ),
            (
                PlannerOverrides {
                    energy_noise_sigma: Some(0.0),
                    ..o()
                },
                "energy_noise_sigma",
            ),
            (
                PlannerOverrides {
                    energy_noise_sigma: Some(1e20),
                    ..o()
                },
                "energy_noise_sigma",
            ),
            (
                PlannerOverrides {
                    dynamics_batch_size: Some(0),
                    ..o()
                },
                "dynamics_batch_size",
            ),
            (
                PlannerOverrides {
                    energy_batch_size: Some(0),
                    ..o()
                },
                "energy_batch_size",
            ),
            (
                PlannerOverrides {
                    max_gradient_steps: Some(0),
                    ..o()
                },
                "max_gradient_steps",
            ),
            (
                PlannerOverrides {
                    epoch_schedule: Some(EpochSchedule::DropAfter {
                        after_episodes: 0,
                        epochs: 0,
                    }),
                    ..o()
                },
                "epoch_schedule.drop_after.epochs",
            ),
            (
                PlannerOverrides {
                    epoch_schedule: Some(EpochSchedule::Geometric {
                        dynamics_factor: 2.0,
                        energy_factor: 0.5,
                        min_epochs: 1,
                    }),
                    ..o()
                },
                "epoch_schedule.geometric.dynamics_factor",
            ),
            (
                PlannerOverrides {
                    epoch_schedule: Some(EpochSchedule::Geometric {
                        dynamics_factor: 0.5,
                        energy_factor: f32::NAN,
                        min_epochs: 1,
                    }),
                    ..o()
                },
                "epoch_schedule.geometric.energy_factor",
            ),
        ];
        for (overrides, field) in cases {
            let err = base.clone().apply(&overrides).unwrap_err().to_string();
            assert!(err.contains(field), "{overrides:?}: {err}");
        }
    }

    /// A mistyped override is refused in JSON and TOML; postcard names no fields, and bytes
    /// beyond the fields it knows are refused as trailing bytes.
    #[test]
    fn unknown_override_fields_are_refused() {
        let err = serde_json::from_str::<PlannerOverrides>(r#"{"populaton": 50}"#).unwrap_err();
        assert!(err.to_string().contains("populaton"), "{err}");
        assert!(toml::from_str::<PlannerOverrides>("horizn = 3").is_err());
        let spec = proto::RunSpec {
            task: Builtin::Cartpole.name().into(),
            preset: None,
            overrides: PlannerOverrides::default(),
            mode: Default::default(),
            seed: 0,
            task_spec: None,
        };
        let request = proto::AttachRequest {
            version: proto::PROTOCOL_VERSION,
            agent: "a".into(),
            spec,
            session: None,
        };
        let mut bytes = proto::encode(&request, proto::Encoding::Postcard).unwrap();
        bytes.push(1);
        assert!(proto::decode::<proto::AttachRequest>(&bytes, proto::Encoding::Postcard).is_err());
        let json = format!(
            r#"{{"version":{},"agent":"a","spec":{{"task":"cartpole","overrides":{{"dynamics_hidden_size":64,"hidden_size":64}}}}}}"#,
            proto::PROTOCOL_VERSION
        );
        let err = proto::decode::<proto::AttachRequest>(json.as_bytes(), proto::Encoding::Json)
            .unwrap_err();
        assert!(err.to_string().contains("hidden_size"), "{err}");
    }

    #[test]
    fn every_preset_plans_with_cem_unless_icem_is_asked_for() {
        for task in Builtin::ALL {
            for method in METHODS {
                let p = Preset::new(task.task(), Some(method)).unwrap();
                let expected = if *method == "adam+dae" {
                    Optimizer::Adam
                } else {
                    Optimizer::Cem
                };
                assert_eq!(p.cem.optimizer, expected, "{task} {method}");
            }
        }
        let mut p = Preset::new(Builtin::HalfCheetah.task(), None).unwrap();
        let icem = PlannerOverrides {
            optimizer: Some(Optimizer::Icem),
            icem_noise_beta: Some(2.5),
            icem_keep_elites: Some(0.2),
            icem_population_decay: Some(1.5),
            ..Default::default()
        };
        p.apply(&icem).unwrap();
        assert_eq!(p.cem.optimizer, Optimizer::Icem);
        assert_eq!(
            p.cem.icem,
            IcemConfig {
                noise_beta: 2.5,
                keep_elites: 0.2,
                population_decay: 1.5
            }
        );
    }

    #[test]
    fn hostile_optimizer_overrides_are_refused() {
        let icem = |o: PlannerOverrides| PlannerOverrides {
            optimizer: Some(Optimizer::Icem),
            ..o
        };
        for bad in [
            icem(PlannerOverrides {
                icem_noise_beta: Some(f32::NAN),
                ..Default::default()
            }),
            icem(PlannerOverrides {
                icem_noise_beta: Some(1e9),
                ..Default::default()
            }),
            icem(PlannerOverrides {
                icem_keep_elites: Some(-0.5),
                ..Default::default()
            }),
            icem(PlannerOverrides {
                icem_population_decay: Some(0.0),
                ..Default::default()
            }),
            icem(PlannerOverrides {
                icem_population_decay: Some(f32::INFINITY),
                ..Default::default()
            }),
            // iCEM parameters for CEM would be silently ignored: refused instead.
            PlannerOverrides {
                icem_noise_beta: Some(1.0),
                ..Default::default()
            },
        ] {
            let mut p = Preset::new(Builtin::Cartpole.task(), None).unwrap();
            let err = p.apply(&bad).unwrap_err();
            assert!(matches!(err, PresetError::InvalidOverride(_)), "{bad:?}");
        }
        // The TOML/JSON spelling.
        let o: PlannerOverrides =
            serde_json::from_str(r#"{"optimizer": "icem", "icem_noise_beta": 1.5}"#).unwrap();
        assert_eq!(
            (o.optimizer, o.icem_noise_beta),
            (Some(Optimizer::Icem), Some(1.5))
        );
        assert!(serde_json::from_str::<PlannerOverrides>(r#"{"optimizer": "mppi"}"#).is_err());
    }
}
