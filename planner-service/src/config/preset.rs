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
//!
//! A run's preset is then adjusted by the daemon's configured overrides and the attaching
//! agent's own overrides, in that order.

use crate::dynamics::DynamicsConfig;
use crate::energy::{EnergyConfig, RegularizerKind};
use crate::plan::CemConfig;
use proto::{EpochSchedule, InferencePrecision, PlannerOverrides, RegularizerChoice, TaskId};
use serde::{Deserialize, Serialize};

/// The methods a preset can be built for (see the module docs).
pub const METHODS: &[&str] = &["cem", "cem+dae", "cem+deen", "pets", "pets+deen"];

/// The method a run uses when it names none: the paper's.
pub const DEFAULT_METHOD: &str = "cem+deen";

/// Everything a run needs to know to learn and plan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Preset {
    /// The method name (one of [`METHODS`]).
    pub method: String,
    pub task: TaskId,
    pub dynamics: DynamicsConfig,
    pub regularizer: RegularizerKind,
    pub energy: EnergyConfig,
    /// `alpha`: weight of the energy in the planning objective (Table 2's cost multiplier).
    pub energy_weight: f32,
    pub cem: CemConfig,
    /// Sample the dynamics' predicted Gaussian in imagination (PETS TS∞) instead of its mean.
    pub sample_dynamics: bool,
    /// Episodes of uniformly random actions before planning starts.
    pub exploration_episodes: u32,
    /// How the number of training epochs changes as episodes accumulate.
    pub schedule: EpochSchedule,
    /// Most gradient steps per model in one retraining; `None` (the paper's presets) trains
    /// the schedule's full epochs however large the buffer has grown.
    #[serde(default)]
    pub max_gradient_steps: Option<u64>,
    /// Number format of planning-time inference: bf16 by default, which doubles the
    /// multiply-add rate on CPUs with AVX-512 BF16 (f32 is used where the CPU lacks it).
    #[serde(default = "default_precision")]
    pub inference_precision: InferencePrecision,
}

fn default_precision() -> InferencePrecision {
    InferencePrecision::Bf16
}

impl Preset {
    /// `(dynamics epochs, energy epochs)` for a retraining after `episodes` stored episodes,
    /// by the preset's [`EpochSchedule`].
    pub fn epochs(&self, episodes: u32) -> (usize, usize) {
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
                let decays = episodes.saturating_sub(self.exploration_episodes) as i32;
                let decay = |epochs: usize, factor: f32| {
                    ((epochs as f32 * factor.powi(decays)).round() as usize)
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
    alpha: f32,
    horizon: usize,
    population: usize,
    elites: usize,
    iterations: usize,
    exploration_episodes: u32,
    schedule: EpochSchedule,
}

fn table(task: TaskId) -> TaskTable {
    match task {
        TaskId::Cartpole => TaskTable {
            model_layers: 3,
            model_size: 200,
            model_epochs: 500,
            model_batch: 32,
            energy_layers: 3,
            energy_size: 200,
            energy_epochs: 500,
            energy_batch: 32,
            sigma: 0.1,
            alpha: 0.001,
            horizon: 25,
            population: 400,
            elites: 40,
            iterations: 5,
            exploration_episodes: 1,
            schedule: EpochSchedule::Constant,
        },
        TaskId::Reacher3d => TaskTable {
            model_layers: 3,
            model_size: 200,
            model_epochs: 500,
            model_batch: 32,
            energy_layers: 3,
            energy_size: 200,
            energy_epochs: 500,
            energy_batch: 32,
            sigma: 0.1,
            alpha: 0.001,
            horizon: 25,
            population: 400,
            elites: 40,
            iterations: 5,
            exploration_episodes: 1,
            schedule: EpochSchedule::Constant,
        },
        TaskId::Pusher => TaskTable {
            model_layers: 3,
            model_size: 200,
            model_epochs: 100,
            model_batch: 32,
            energy_layers: 3,
            energy_size: 200,
            energy_epochs: 100,
            energy_batch: 32,
            sigma: 0.1,
            alpha: 0.01,
            horizon: 25,
            population: 500,
            elites: 50,
            iterations: 5,
            exploration_episodes: 1,
            schedule: EpochSchedule::Constant,
        },
        TaskId::HalfCheetah => TaskTable {
            model_layers: 4,
            model_size: 200,
            model_epochs: 300,
            model_batch: 128,
            energy_layers: 5,
            energy_size: 500,
            energy_epochs: 100,
            energy_batch: 32,
            sigma: 0.37,
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
        TaskId::Ant => TaskTable {
            model_layers: 4,
            model_size: 400,
            model_epochs: 600,
            model_batch: 400,
            energy_layers: 3,
            energy_size: 300,
            energy_epochs: 800,
            energy_batch: 64,
            sigma: 0.9,
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
    /// The preset for `task` and `method` (`None`: [`DEFAULT_METHOD`]).
    pub fn new(task: TaskId, method: Option<&str>) -> Result<Self, PresetError> {
        let method = method.unwrap_or(DEFAULT_METHOD);
        let (pets, regularizer) = match method {
            "cem" => (false, RegularizerKind::None),
            "cem+dae" => (false, RegularizerKind::Dae),
            "cem+deen" => (false, RegularizerKind::Deen),
            "pets" => (true, RegularizerKind::None),
            "pets+deen" => (true, RegularizerKind::Deen),
            other => return Err(PresetError::UnknownMethod(other.to_string())),
        };
        let t = table(task);
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
                learning_rate: 1e-3,
            },
            energy_weight: t.alpha,
            cem: CemConfig {
                horizon: t.horizon,
                population: t.population,
                elites: t.elites,
                iterations: t.iterations,
                smoothing: 0.1,
                min_variance: 1e-3,
                particles: if pets { 20 } else { 1 },
            },
            sample_dynamics: pets,
            exploration_episodes: t.exploration_episodes,
            schedule: t.schedule,
            max_gradient_steps: None,
            inference_precision: default_precision(),
        })
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
        count(&mut d.batch_size, o.dynamics_batch_size, "dynamics_batch_size")?;
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
        count(&mut e.epochs, o.energy_epochs, "energy_epochs")?;
        count(
            &mut e.hidden_layers,
            o.energy_hidden_layers,
            "energy_hidden_layers",
        )?;
        count(&mut e.hidden_size, o.energy_hidden_size, "energy_hidden_size")?;
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
        if let Some(sample) = o.sample_dynamics {
            self.sample_dynamics = sample;
        }
        if let Some(e) = o.exploration_episodes {
            self.exploration_episodes = e;
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

    #[test]
    fn table_two_numbers() {
        let hc = Preset::new(TaskId::HalfCheetah, None).unwrap();
        assert_eq!(hc.method, "cem+deen");
        assert_eq!((hc.energy.hidden_layers, hc.energy.hidden_size), (5, 500));
        assert_eq!(hc.energy_weight, 0.05);
        assert_eq!(hc.exploration_episodes, 3);
        assert_eq!(hc.epochs(5), (300, 100));
        assert_eq!(hc.epochs(10), (8, 8));
        let ant = Preset::new(TaskId::Ant, Some("pets")).unwrap();
        assert_eq!(
            (
                ant.dynamics.ensemble_size,
                ant.cem.particles,
                ant.cem.iterations
            ),
            (5, 20, 7)
        );
        assert_eq!(ant.regularizer, RegularizerKind::None);
        assert_eq!(ant.epochs(1), (600, 800));
        assert_eq!(ant.epochs(2), (360, 560));
        let pusher = Preset::new(TaskId::Pusher, None).unwrap();
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
        assert!(Preset::new(TaskId::Cartpole, Some("sac")).is_err());
    }

    #[test]
    fn overrides_apply_and_are_checked() {
        let mut p = Preset::new(TaskId::Cartpole, None).unwrap();
        assert_eq!(p.inference_precision, InferencePrecision::Bf16);
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
}
