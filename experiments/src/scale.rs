//! Experiment sizes: the paper's, and a stated reduced size that fits a small machine.
//!
//! A scale fixes the default number of seeds and episodes and the preset overrides every run of
//! an experiment sends when it attaches. The overrides are one [`PlannerOverrides`] value, so the
//! launcher (which passes them to `sim-bridge run` as flags) and the in-process figures (which
//! apply them to a [`planner_service::config::Preset`]) cannot disagree about what "small" means.

use planner_service::config::Preset;
use proto::{PlannerOverrides, Builtin};
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

    /// The preset overrides of this scale for `task` (none at the paper's scale).
    pub fn overrides(self, task: Builtin) -> PlannerOverrides {
        match (self, task) {
            (Scale::Paper, _) => PlannerOverrides::default(),
            // 1000-step episodes: a quarter of the population, a shorter horizon, three CEM
            // iterations and one exploration episode make a planned step ~10× cheaper; the
            // networks keep their depth but train for fewer epochs on a smaller energy model.
            (Scale::Small, Builtin::HalfCheetah | Builtin::Ant) => PlannerOverrides {
                population: Some(100),
                elites: Some(10),
                cem_iterations: Some(3),
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
            (Scale::Small, _) => {
                // Preset::new fails only for an unknown method, and the default method is known.
                let paper = Preset::new(task.task(), None).expect("the default method has a preset");
                let half = |n: usize| Some((n / 2).max(1) as u32);
                let fifth = |n: usize| Some((n / 5).max(1) as u32);
                PlannerOverrides {
                    population: half(paper.cem.population),
                    elites: half(paper.cem.elites),
                    dynamics_epochs: fifth(paper.dynamics.epochs),
                    energy_epochs: fifth(paper.energy.epochs),
                    ..PlannerOverrides::default()
                }
            }
        }
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

    #[test]
    fn paper_scale_changes_nothing() {
        for &task in Builtin::ALL {
            assert_eq!(Scale::Paper.overrides(task), PlannerOverrides::default());
            assert!(bridge_flags(&Scale::Paper.overrides(task)).is_empty());
        }
    }

    #[test]
    fn small_scale_is_a_valid_smaller_preset_for_every_method() {
        for &task in Builtin::ALL {
            for method in crate::METHODS {
                let paper = Preset::new(task, Some(method)).unwrap();
                let mut small = paper.clone();
                small.apply(&Scale::Small.overrides(task)).unwrap();
                assert!(
                    small.cem.population < paper.cem.population,
                    "{task} {method}"
                );
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
        let flags = bridge_flags(&Scale::Small.overrides(Builtin::HalfCheetah));
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
