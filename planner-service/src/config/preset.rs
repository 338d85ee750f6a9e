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
use crate::plan::{CemConfig, IcemConfig, Optimizer};
use proto::{InferencePrecision, PlannerOverrides, RegularizerChoice, TaskId};
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
    /// Number format of planning-time inference: bf16 by default, which doubles the
    /// multiply-add rate on CPUs with AVX-512 BF16 (f32 is used where the CPU lacks it).
    #[serde(default = "default_precision")]
    pub inference_precision: InferencePrecision,
}

fn default_precision() -> InferencePrecision {
    InferencePrecision::Bf16
}

/// How training epochs decay with the number of finished episodes (the paper trains less as
/// the buffer grows, to avoid overfitting it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum EpochSchedule {
    /// The configured epochs after every episode.
    Constant,
    /// Half-cheetah: `epochs` for both models once `after_episodes` episodes are stored.
    DropAfter { after_episodes: u32, epochs: u32 },
    /// Ant: epochs multiplied by `dynamics_factor` / `energy_factor` after every episode
    /// beyond the exploration ones, never below `min_epochs`.
    Geometric {
        dynamics_factor: f32,
        energy_factor: f32,
        min_epochs: u32,
    },
}

impl EpochSchedule {
    /// `(dynamics epochs, energy epochs)` for a retraining after `episodes` stored episodes.
    pub fn epochs(&self, preset: &Preset, episodes: u32) -> (usize, usize) {
        let (dynamics, energy) = (preset.dynamics.epochs, preset.energy.epochs);
        match *self {
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
                let decays = episodes.saturating_sub(preset.exploration_episodes) as i32;
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
                optimizer: Optimizer::Cem,
                icem: IcemConfig::default(),
            },
            sample_dynamics: pets,
            exploration_episodes: t.exploration_episodes,
            schedule: t.schedule,
            inference_precision: default_precision(),
        })
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
        self.cem
            .icem
            .validate()
            .map_err(|e| PresetError::InvalidOverride(e.to_string()))
    }

    /// Applies `overrides` (fields that are `Some`), checking that the result still makes sense.
    pub fn apply(&mut self, o: &PlannerOverrides) -> Result<(), PresetError> {
        fn set(target: &mut usize, value: Option<u32>, name: &str) -> Result<(), PresetError> {
            match value {
                Some(0) => Err(PresetError::InvalidOverride(format!(
                    "{name} must be at least 1"
                ))),
                Some(v) => {
                    *target = v as usize;
                    Ok(())
                }
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
        if let Some(w) = o.energy_weight {
            if !(w.is_finite() && w >= 0.0) {
                return Err(PresetError::InvalidOverride(format!(
                    "energy_weight must be finite and ≥ 0, not {w}"
                )));
            }
            self.energy_weight = w;
        }
        set(
            &mut self.dynamics.ensemble_size,
            o.ensemble_size,
            "ensemble_size",
        )?;
        set(&mut self.cem.particles, o.particles, "particles")?;
        set(&mut self.cem.horizon, o.horizon, "horizon")?;
        set(&mut self.cem.population, o.population, "population")?;
        set(&mut self.cem.elites, o.elites, "elites")?;
        set(&mut self.cem.iterations, o.cem_iterations, "cem_iterations")?;
        set(
            &mut self.dynamics.epochs,
            o.dynamics_epochs,
            "dynamics_epochs",
        )?;
        set(
            &mut self.dynamics.hidden_layers,
            o.dynamics_hidden_layers,
            "dynamics_hidden_layers",
        )?;
        set(
            &mut self.dynamics.hidden_size,
            o.dynamics_hidden_size,
            "dynamics_hidden_size",
        )?;
        set(&mut self.energy.epochs, o.energy_epochs, "energy_epochs")?;
        set(
            &mut self.energy.hidden_layers,
            o.energy_hidden_layers,
            "energy_hidden_layers",
        )?;
        set(
            &mut self.energy.hidden_size,
            o.energy_hidden_size,
            "energy_hidden_size",
        )?;
        if let Some(e) = o.exploration_episodes {
            self.exploration_episodes = e;
        }
        if let Some(p) = o.inference_precision {
            self.inference_precision = p;
        }
        self.apply_optimizer(o)?;
        if self.cem.elites > self.cem.population {
            return Err(PresetError::InvalidOverride(format!(
                "elites ({}) cannot exceed population ({})",
                self.cem.elites, self.cem.population
            )));
        }
        Ok(())
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
        assert_eq!(hc.schedule.epochs(&hc, 5), (300, 100));
        assert_eq!(hc.schedule.epochs(&hc, 10), (8, 8));
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
        assert_eq!(ant.schedule.epochs(&ant, 1), (600, 800));
        assert_eq!(ant.schedule.epochs(&ant, 2), (360, 560));
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

    #[test]
    fn every_preset_plans_with_cem_unless_icem_is_asked_for() {
        for task in TaskId::ALL {
            for method in METHODS {
                let p = Preset::new(*task, Some(method)).unwrap();
                assert_eq!(p.cem.optimizer, Optimizer::Cem, "{task} {method}");
            }
        }
        let mut p = Preset::new(TaskId::HalfCheetah, None).unwrap();
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
            let mut p = Preset::new(TaskId::Cartpole, None).unwrap();
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
