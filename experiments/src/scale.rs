//! Experiment sizes: the paper's, and a stated reduced size that fits a small machine.
//!
//! A scale fixes the default number of seeds and episodes and the preset overrides every run of
//! an experiment sends when it attaches. The overrides are one [`PlannerOverrides`] value, so the
//! launcher (which passes them to `sim-bridge run` as flags) and the in-process figures (which
//! apply them to a [`planner_service::config::Preset`]) cannot disagree about what "small" means.

use planner_service::config::{Preset, PresetError};
use planner_service::plan::Optimizer;
use proto::{Builtin, PlannerOverrides};
use serde::{Deserialize, Serialize};

/// How large an experiment is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Scale {
    /// The paper's Table 2 sizes and 5 seeds (a large machine: hours per task).
    Paper,
    /// Fewer seeds and episodes, a smaller CEM search and shorter training, sized so that one
    /// task's three-method comparison finishes in about an hour on a 2-core machine.
    Small,
}

impl Scale {
    pub fn name(self) -> &'static str {
        match self {
            Scale::Paper => "paper",
            Scale::Small => "small",
        }
    }

    /// Seeds per method when the command line names no number.
    pub fn default_seeds(self) -> u32 {
        match self {
            Scale::Paper => 5,
            Scale::Small => 2,
        }
    }

    /// Episodes per run when the command line names no number: the paper's Figure 4 reports
    /// about 15 cartpole/reacher episodes and 20,000 half-cheetah and ant steps.
    pub fn default_episodes(self, task: Builtin) -> u32 {
        match (self, task) {
            (Scale::Paper, Builtin::HalfCheetah | Builtin::Ant) => 20,
            (Scale::Paper, _) => 15,
            (Scale::Small, Builtin::HalfCheetah | Builtin::Ant) => 5,
            (Scale::Small, _) => 8,
        }
    }

    /// The preset overrides of this scale for `method` on `task` (none at the paper's scale).
    ///
    /// The small scale shrinks a sampling search (CEM, iCEM) by its population and iterations;
    /// a gradient search (`adam+dae`: 16 candidates) is small already, so it keeps its
    /// candidates and takes fewer steps instead. Sizing from the method's own preset keeps a
    /// "small" Adam from growing to a CEM-sized population.
    pub fn overrides(self, task: Builtin, method: &str) -> Result<PlannerOverrides, PresetError> {
        let paper = Preset::new(task.task(), Some(method))?;
        let sampling = paper.cem.optimizer != Optimizer::Adam;
        let count = |n: usize| Some(n.max(1) as u32);
        Ok(match (self, task) {
            (Scale::Paper, _) => PlannerOverrides::default(),
            // 1000-step episodes: a fifth of the population, a shorter
            // horizon, three CEM iterations (three fifths of Adam's steps) and one exploration
            // episode make a planned step ~10× cheaper; the networks keep their depth but train
            // for fewer epochs on a smaller energy model.
            (Scale::Small, Builtin::HalfCheetah | Builtin::Ant) => PlannerOverrides {
                population: if sampling { Some(100) } else { None },
                elites: if sampling { Some(10) } else { None },
                cem_iterations: if sampling {
                    Some(3)
                } else {
                    count(paper.cem.iterations * 3 / 5)
                },
                horizon: Some(20),
                exploration_episodes: Some(1),
                dynamics_epochs: Some(50),
                energy_epochs: Some(30),
                energy_hidden_layers: Some(3),
                energy_hidden_size: Some(200),
                ..PlannerOverrides::default()
            },
            // 150–200-step episodes: half the population and elites, a fifth of Table 2's
            // training epochs.
            (Scale::Small, _) => PlannerOverrides {
                population: if sampling {
                    count(paper.cem.population / 2)
                } else {
                    None
                },
                elites: if sampling {
                    count(paper.cem.elites / 2)
                } else {
                    None
                },
                cem_iterations: if sampling {
                    None
                } else {
                    count(paper.cem.iterations / 2)
                },
                dynamics_epochs: count(paper.dynamics.epochs / 5),
                energy_epochs: count(paper.energy.epochs / 5),
                ..PlannerOverrides::default()
            },
        })
    }
}

/// The `sim-bridge run` flags that send `o` as the run spec's overrides (regulariser and
/// energy weight come from the method's preset, so they are not spelled here).
pub fn bridge_flags(o: &PlannerOverrides) -> Vec<String> {
    let numbers = [
        ("--ensemble-size", o.ensemble_size),
        ("--particles", o.particles),
        ("--horizon", o.horizon),
        ("--population", o.population),
        ("--elites", o.elites),
        ("--cem-iterations", o.cem_iterations),
        ("--exploration-episodes", o.exploration_episodes),
        ("--dynamics-epochs", o.dynamics_epochs),
        ("--dynamics-hidden-layers", o.dynamics_hidden_layers),
        ("--dynamics-hidden-size", o.dynamics_hidden_size),
        ("--energy-epochs", o.energy_epochs),
        ("--energy-hidden-layers", o.energy_hidden_layers),
        ("--energy-hidden-size", o.energy_hidden_size),
    ];
    let mut flags = Vec::new();
    for (flag, value) in numbers {
        if let Some(v) = value {
            flags.push(flag.to_string());
            flags.push(v.to_string());
        }
    }
    if let Some(w) = o.energy_weight {
        flags.push("--energy-weight".into());
        flags.push(w.to_string());
    }
    flags
}

#[cfg(test)]
mod tests {
    use super::*;
    use planner_service::config::METHODS;

    #[test]
    fn paper_scale_changes_nothing() {
        for &task in Builtin::ALL {
            for method in METHODS {
                let paper = Scale::Paper.overrides(task, method).unwrap();
                assert_eq!(paper, PlannerOverrides::default());
                assert!(bridge_flags(&paper).is_empty());
            }
        }
    }

    #[test]
    fn small_scale_is_a_valid_smaller_preset_for_every_method() {
        for &task in Builtin::ALL {
            for method in METHODS {
                let paper = Preset::new(task.task(), Some(method)).unwrap();
                let mut small = paper.clone();
                small
                    .apply(&Scale::Small.overrides(task, method).unwrap())
                    .unwrap();
                let paper_work = paper.cem.population * paper.cem.iterations;
                let small_work = small.cem.population * small.cem.iterations;
                assert!(small_work < paper_work, "{task} {method}");
                assert!(
                    small.cem.population <= paper.cem.population,
                    "{task} {method}: a small search never grows"
                );
                if paper.cem.optimizer == Optimizer::Adam {
                    assert_eq!(
                        small.cem.population, paper.cem.population,
                        "{task}: Adam keeps its candidates at the small scale"
                    );
                }
                assert!(
                    small.dynamics.epochs < paper.dynamics.epochs,
                    "{task} {method}"
                );
                assert_eq!(small.regularizer, paper.regularizer);
            }
        }
    }

    #[test]
    fn flags_spell_every_override() {
        let flags = bridge_flags(
            &Scale::Small
                .overrides(Builtin::HalfCheetah, "cem+deen")
                .unwrap(),
        );
        let pairs: Vec<(&str, &str)> = flags
            .chunks(2)
            .map(|p| (p[0].as_str(), p[1].as_str()))
            .collect();
        assert!(pairs.contains(&("--population", "100")), "{pairs:?}");
        assert!(
            pairs.contains(&("--energy-hidden-size", "200")),
            "{pairs:?}"
        );
        assert!(
            pairs.contains(&("--exploration-episodes", "1")),
            "{pairs:?}"
        );
        assert_eq!(pairs.len(), 9);
    }
}
