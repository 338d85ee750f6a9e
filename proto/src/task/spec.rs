//! A task as data: what an operator writes in a TOML/JSON file or an agent sends in its attach.
//!
//! A [`TaskSpec`] says everything the planner must know about a system with a vector state and a
//! box action space: dimensions, bounds, timing, how the dynamics model sees the state, when an
//! episode ends and what it is rewarded for. It is plain data (serde), so it travels in messages
//! and is stored with a run; [`crate::task::Task`] is the same spec with its code attached.
//!
//! Reward and termination are *kinds*: `builtin` (Rust code of one of the five catalog tasks),
//! `expression` (a formula over `s`, `a`, `s_next`) or `learned` (a model trained on the rewards
//! agents send, or on the episodes they end as `terminated`). Serde writes them externally tagged (`reward = { builtin = "cartpole" }`,
//! `reward = "learned"`), the one enum form that postcard, JSON and TOML all read.

use super::Builtin;
use serde::{Deserialize, Serialize};

/// The largest magnitude bound a task may declare: differences and squares of values up to it
/// stay within f32's range (10³⁶ < 3.4·10³⁸).
pub const MAX_MAGNITUDE: f32 = 1e18;

/// The largest action bound a spec may declare: actions are sampled and summed in f32.
pub const MAX_ACTION_BOUND: f32 = 1e6;

/// Longest expression source accepted in a spec, in bytes.
pub const MAX_EXPRESSION_BYTES: usize = 4096;

/// One task: dimensions, bounds, timing, model transforms, termination and reward.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TaskSpec {
    /// The task's name: 1–64 characters from letters, digits, `-`, `_`, `.`. In a daemon's
    /// `[tasks.NAME]` table it may be left out (the table's key is the name).
    #[serde(default)]
    pub name: String,
    /// Observation length.
    pub obs_dim: usize,
    /// Action length.
    pub act_dim: usize,
    /// Lower action bound per dimension.
    pub action_low: Vec<f32>,
    /// Upper action bound per dimension.
    pub action_high: Vec<f32>,
    /// Steps per episode (time limit).
    pub episode_len: u32,
    /// Seconds between two actions: the default planning deadline.
    pub control_dt: f64,
    /// The range each observation coordinate may take, when the system knows it: an
    /// observation outside it is refused (`out_of_range`) and never trains the models.
    #[serde(default)]
    pub observation_bounds: Option<ObservationBounds>,
    /// The largest observation and reward magnitudes an agent may send (10⁴ if absent).
    #[serde(default = "Magnitudes::generous")]
    pub magnitudes: Magnitudes,
    /// How the dynamics model sees the state and what it predicts.
    #[serde(default)]
    pub model: ModelTransforms,
    /// When an episode ends before its time limit.
    #[serde(default)]
    pub termination: TerminationKind,
    /// What a transition `(s, a, s')` earns.
    pub reward: RewardKind,
    /// The catalog task whose preset sizes (paper Table 2: networks, CEM, epochs) a run of this
    /// task starts from before its overrides (`cartpole` if absent: the smallest).
    #[serde(default = "Builtin::default_base")]
    pub base_preset: Builtin,
}

/// Per-coordinate observation range: `low[i] ≤ obs[i] ≤ high[i]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ObservationBounds {
    pub low: Vec<f32>,
    pub high: Vec<f32>,
}

/// The largest magnitudes a task's observations and rewards may take. Finite is not enough: a
/// value like 3.4e38 is finite, but the difference of two of them (the dynamics model's
/// target) overflows to infinity and poisons training. A planner refuses larger values, and
/// its operator can change them per task (`[limits.magnitudes.<task>]`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Magnitudes {
    /// Largest `|x|` of any observation coordinate.
    pub observation: f32,
    /// Largest `|r|` of one step's reward.
    pub reward: f32,
}

impl Magnitudes {
    /// The catalog's bound for every task: 10⁴ for both, far above the positions, velocities
    /// and per-step rewards of the catalog's tasks, and far below where a difference or a
    /// square leaves f32's range (10⁸ ≪ 3.4·10³⁸).
    pub const GENEROUS: Magnitudes = Magnitudes {
        observation: 1e4,
        reward: 1e4,
    };

    fn generous() -> Self {
        Self::GENEROUS
    }

    /// Both bounds positive and at most [`MAX_MAGNITUDE`].
    pub fn is_valid(&self) -> bool {
        let ok = |v: f32| v > 0.0 && v <= MAX_MAGNITUDE;
        ok(self.observation) && ok(self.reward)
    }
}

/// How the dynamics model sees a state and what it learns to predict.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ModelTransforms {
    /// A catalog task's own transforms (Rust code).
    Builtin(Builtin),
    /// Transforms declared per observation dimension.
    Declared(DeclaredTransforms),
}

impl Default for ModelTransforms {
    fn default() -> Self {
        Self::Declared(DeclaredTransforms::default())
    }
}

/// Per-dimension model transforms. Every other dimension is a plain input and a delta target.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct DeclaredTransforms {
    /// Observation dimensions that are angles: the model sees `sin` and `cos` of each (in its
    /// place), so that it does not learn a jump where the angle wraps.
    pub angles: Vec<usize>,
    /// Observation dimensions the model predicts as the next value itself rather than a delta
    /// (a velocity or a reading that is no state to add to).
    pub absolute: Vec<usize>,
}

/// When an episode ends before its time limit.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum TerminationKind {
    /// Never: the episode runs to its time limit.
    #[default]
    Never,
    /// A catalog task's own rule (Rust code).
    Builtin(Builtin),
    /// A formula over `s_next`; the episode ends where it is positive.
    Expression(String),
    /// Observed only: a classifier learns it from the episodes agents end as `terminated`,
    /// and imagination stops a particle's returns where it predicts an end.
    Learned,
}

/// What a transition earns.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum RewardKind {
    /// A catalog task's own reward and its gradient (Rust code).
    Builtin(Builtin),
    /// A formula over `s`, `a`, `s_next`.
    Expression(String),
    /// Observed only: a model learns it from the rewards agents send.
    Learned,
}

/// The bounds a spec must keep: the daemon's `[limits]` for the client-chosen sizes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpecBounds {
    /// Longest observation.
    pub max_obs_dim: usize,
    /// Longest action.
    pub max_act_dim: usize,
    /// Longest episode, in steps.
    pub max_episode_len: u32,
}

impl Default for SpecBounds {
    /// Far above the catalog's tasks (27 observations, 8 actions, 1,000 steps) and far below
    /// what would make one transition or one episode a memory problem.
    fn default() -> Self {
        Self {
            max_obs_dim: 1024,
            max_act_dim: 256,
            max_episode_len: 100_000,
        }
    }
}

/// Shortest control period accepted, in seconds: 0.1 ms.
pub const MIN_CONTROL_DT: f64 = 1e-4;
/// Longest control period accepted, in seconds: an hour.
pub const MAX_CONTROL_DT: f64 = 3_600.0;

/// Why a spec cannot be used. Each names the field and the offending value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpecError {
    #[error("task name: {0}")]
    Name(#[from] crate::keys::InvalidName),
    #[error("task {task}: {field} = {value} must be between 1 and {limit}")]
    Size {
        task: String,
        field: &'static str,
        value: u64,
        limit: u64,
    },
    #[error("task {task}: {field} has {found} numbers, it needs {expected}")]
    Length {
        task: String,
        field: &'static str,
        found: usize,
        expected: usize,
    },
    #[error(
        "task {task}: {field}[{index}] = [{low}, {high}] must be finite, low < high, within ±{bound:e}"
    )]
    Bound {
        task: String,
        field: &'static str,
        index: usize,
        low: f32,
        high: f32,
        bound: f32,
    },
    #[error(
        "task {task}: control_dt = {value} s must be between {MIN_CONTROL_DT} and {MAX_CONTROL_DT}"
    )]
    ControlPeriod { task: String, value: f64 },
    #[error(
        "task {task}: magnitudes must be positive and at most {MAX_MAGNITUDE:e}, got {found:?}"
    )]
    Magnitudes { task: String, found: Magnitudes },
    #[error(
        "task {task}: model.{field} index {index} is repeated or not below obs_dim = {obs_dim}"
    )]
    Index {
        task: String,
        field: &'static str,
        index: usize,
        obs_dim: usize,
    },
    #[error(
        "task {task}: builtin {part} `{builtin}` needs obs_dim = {obs_dim} and act_dim = {act_dim}"
    )]
    BuiltinDims {
        task: String,
        part: &'static str,
        builtin: Builtin,
        obs_dim: usize,
        act_dim: usize,
    },
    #[error("task {task}: {part} expression is {len} bytes, over {MAX_EXPRESSION_BYTES}")]
    ExpressionTooLong {
        task: String,
        part: &'static str,
        len: usize,
    },
}

impl TaskSpec {
    /// Checks every field: the name, dimensions within `bounds`, finite ordered bounds, timing,
    /// magnitudes, model indices, and that a builtin kind's code fits the dimensions (it indexes
    /// them). A spec that passes cannot make any task function index out of range.
    pub fn validate(&self, bounds: &SpecBounds) -> Result<(), SpecError> {
        crate::keys::validate_name(&self.name)?;
        let task = || self.name.clone();
        let size = |field, value: u64, limit: u64| {
            if value == 0 || value > limit {
                Err(SpecError::Size {
                    task: task(),
                    field,
                    value,
                    limit,
                })
            } else {
                Ok(())
            }
        };
        size("obs_dim", self.obs_dim as u64, bounds.max_obs_dim as u64)?;
        size("act_dim", self.act_dim as u64, bounds.max_act_dim as u64)?;
        size(
            "episode_len",
            self.episode_len.into(),
            bounds.max_episode_len.into(),
        )?;
        let length = |field, found: usize, expected: usize| {
            if found == expected {
                Ok(())
            } else {
                Err(SpecError::Length {
                    task: task(),
                    field,
                    found,
                    expected,
                })
            }
        };
        length("action_low", self.action_low.len(), self.act_dim)?;
        length("action_high", self.action_high.len(), self.act_dim)?;
        check_ranges(
            &self.name,
            "action",
            &self.action_low,
            &self.action_high,
            MAX_ACTION_BOUND,
        )?;
        if !(MIN_CONTROL_DT..=MAX_CONTROL_DT).contains(&self.control_dt) {
            return Err(SpecError::ControlPeriod {
                task: task(),
                value: self.control_dt,
            });
        }
        if !self.magnitudes.is_valid() {
            return Err(SpecError::Magnitudes {
                task: task(),
                found: self.magnitudes,
            });
        }
        if let Some(b) = &self.observation_bounds {
            length("observation_bounds.low", b.low.len(), self.obs_dim)?;
            length("observation_bounds.high", b.high.len(), self.obs_dim)?;
            check_ranges(
                &self.name,
                "observation_bounds",
                &b.low,
                &b.high,
                self.magnitudes.observation,
            )?;
        }
        match &self.model {
            ModelTransforms::Builtin(b) => self.check_builtin("model", *b)?,
            ModelTransforms::Declared(d) => {
                self.check_indices("angles", &d.angles)?;
                self.check_indices("absolute", &d.absolute)?;
            }
        }
        match &self.termination {
            TerminationKind::Never => {}
            TerminationKind::Builtin(b) => self.check_builtin("termination", *b)?,
            TerminationKind::Expression(e) => self.check_expression("termination", e)?,
            TerminationKind::Learned => {}
        }
        match &self.reward {
            RewardKind::Learned => {}
            RewardKind::Builtin(b) => self.check_builtin("reward", *b)?,
            RewardKind::Expression(e) => self.check_expression("reward", e)?,
        }
        Ok(())
    }

    fn check_builtin(&self, part: &'static str, builtin: Builtin) -> Result<(), SpecError> {
        let (obs_dim, act_dim) = builtin.dims();
        if (self.obs_dim, self.act_dim) == (obs_dim, act_dim) {
            Ok(())
        } else {
            Err(SpecError::BuiltinDims {
                task: self.name.clone(),
                part,
                builtin,
                obs_dim,
                act_dim,
            })
        }
    }

    fn check_indices(&self, field: &'static str, indices: &[usize]) -> Result<(), SpecError> {
        let mut seen = vec![false; self.obs_dim];
        for &index in indices {
            if index >= self.obs_dim || std::mem::replace(&mut seen[index], true) {
                return Err(SpecError::Index {
                    task: self.name.clone(),
                    field,
                    index,
                    obs_dim: self.obs_dim,
                });
            }
        }
        Ok(())
    }

    fn check_expression(&self, part: &'static str, source: &str) -> Result<(), SpecError> {
        if source.len() > MAX_EXPRESSION_BYTES {
            return Err(SpecError::ExpressionTooLong {
                task: self.name.clone(),
                part,
                len: source.len(),
            });
        }
        Ok(())
    }
}

/// Every `low[i] < high[i]`, both finite and within `±bound`.
fn check_ranges(
    task: &str,
    field: &'static str,
    low: &[f32],
    high: &[f32],
    bound: f32,
) -> Result<(), SpecError> {
    for (index, (&lo, &hi)) in low.iter().zip(high).enumerate() {
        let ok = lo.is_finite() && hi.is_finite() && lo < hi && lo >= -bound && hi <= bound;
        if !ok {
            return Err(SpecError::Bound {
                task: task.to_string(),
                field,
                index,
                low: lo,
                high: hi,
                bound,
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pendulum as a user would write it: one angle, a learned reward.
    pub(crate) fn pendulum() -> TaskSpec {
        TaskSpec {
            name: "pendulum".into(),
            obs_dim: 2,
            act_dim: 1,
            action_low: vec![-2.0],
            action_high: vec![2.0],
            episode_len: 200,
            control_dt: 0.05,
            observation_bounds: None,
            magnitudes: Magnitudes::GENEROUS,
            model: ModelTransforms::Declared(DeclaredTransforms {
                angles: vec![0],
                absolute: vec![],
            }),
            termination: TerminationKind::Never,
            reward: RewardKind::Learned,
            base_preset: Builtin::Cartpole,
        }
    }

    #[test]
    fn a_spec_reads_from_toml_and_json_with_defaults() {
        let toml_spec: TaskSpec = toml::from_str(
            r#"
            name = "pendulum"
            obs_dim = 2
            act_dim = 1
            action_low = [-2.0]
            action_high = [2.0]
            episode_len = 200
            control_dt = 0.05
            reward = "learned"
            model = { declared = { angles = [0] } }
            "#,
        )
        .unwrap();
        assert_eq!(toml_spec, pendulum());
        let json = serde_json::to_string(&pendulum()).unwrap();
        assert_eq!(serde_json::from_str::<TaskSpec>(&json).unwrap(), pendulum());
        let bytes = postcard::to_stdvec(&pendulum()).unwrap();
        assert_eq!(
            postcard::from_bytes::<TaskSpec>(&bytes).unwrap(),
            pendulum()
        );
        let builtin: TaskSpec = serde_json::from_str(
            r#"{"name":"c","obs_dim":4,"act_dim":1,"action_low":[-3],"action_high":[3],
                "episode_len":200,"control_dt":0.04,"reward":{"builtin":"cartpole"},
                "termination":"never","model":{"builtin":"cartpole"}}"#,
        )
        .unwrap();
        assert_eq!(builtin.reward, RewardKind::Builtin(Builtin::Cartpole));
        builtin.validate(&SpecBounds::default()).unwrap();
        let unknown = serde_json::from_str::<TaskSpec>(
            r#"{"name":"c","obs_dim":4,"act_dim":1,"action_low":[-3],"action_high":[3],
                "episode_len":200,"control_dt":0.04,"reward":"learned","gravity":9.8}"#,
        );
        assert!(unknown.unwrap_err().to_string().contains("gravity"));
    }

    #[test]
    fn every_catalog_spec_is_valid() {
        for &b in Builtin::ALL {
            b.spec().validate(&SpecBounds::default()).unwrap();
        }
        pendulum().validate(&SpecBounds::default()).unwrap();
    }

    /// Every hostile value a client could send is refused with the field it is in.
    #[test]
    fn hostile_specs_are_refused_naming_the_field() {
        let bounds = SpecBounds::default();
        let refused = |change: &dyn Fn(&mut TaskSpec), expect: &str| {
            let mut spec = pendulum();
            change(&mut spec);
            let err = spec.validate(&bounds).unwrap_err().to_string();
            assert!(err.contains(expect), "{expect}: {err}");
        };
        refused(&|s| s.name = "a/b".into(), "invalid name");
        refused(&|s| s.name = "x".repeat(65), "invalid name");
        refused(&|s| s.name = String::new(), "invalid name");
        refused(&|s| s.obs_dim = 0, "obs_dim = 0");
        refused(&|s| s.obs_dim = usize::MAX, "obs_dim");
        refused(&|s| s.obs_dim = 1025, "between 1 and 1024");
        refused(&|s| s.act_dim = 4_000_000_000, "act_dim");
        refused(&|s| s.episode_len = 0, "episode_len");
        refused(&|s| s.episode_len = u32::MAX, "episode_len");
        refused(&|s| s.action_low = vec![], "action_low has 0 numbers");
        refused(&|s| s.action_high = vec![1.0, 2.0], "action_high has 2");
        refused(&|s| s.action_low = vec![f32::NAN], "action[0]");
        refused(&|s| s.action_high = vec![f32::INFINITY], "action[0]");
        refused(&|s| s.action_low = vec![3.0], "low < high");
        refused(&|s| s.action_low = vec![2.0], "low < high");
        refused(&|s| s.action_high = vec![1e30], "action[0]");
        refused(&|s| s.control_dt = 0.0, "control_dt");
        refused(&|s| s.control_dt = f64::NAN, "control_dt");
        refused(&|s| s.control_dt = -1.0, "control_dt");
        refused(&|s| s.control_dt = 1e9, "control_dt");
        refused(
            &|s| s.magnitudes.observation = f32::INFINITY,
            "magnitudes must be positive",
        );
        refused(&|s| s.magnitudes.reward = 0.0, "magnitudes");
        refused(
            &|s| {
                s.observation_bounds = Some(ObservationBounds {
                    low: vec![-1.0],
                    high: vec![1.0],
                })
            },
            "observation_bounds.low has 1",
        );
        refused(
            &|s| {
                s.observation_bounds = Some(ObservationBounds {
                    low: vec![-1.0, -1e9],
                    high: vec![1.0, 1.0],
                })
            },
            "observation_bounds[1]",
        );
        refused(
            &|s| {
                s.model = ModelTransforms::Declared(DeclaredTransforms {
                    angles: vec![2],
                    absolute: vec![],
                })
            },
            "model.angles index 2",
        );
        refused(
            &|s| {
                s.model = ModelTransforms::Declared(DeclaredTransforms {
                    angles: vec![],
                    absolute: vec![1, 1],
                })
            },
            "model.absolute index 1 is repeated",
        );
        // Builtin code indexes its own dimensions: another task's must not reach it.
        refused(
            &|s| s.reward = RewardKind::Builtin(Builtin::Ant),
            "builtin reward `ant` needs obs_dim = 27",
        );
        refused(
            &|s| s.termination = TerminationKind::Builtin(Builtin::Ant),
            "builtin termination",
        );
        refused(
            &|s| s.model = ModelTransforms::Builtin(Builtin::HalfCheetah),
            "builtin model",
        );
        refused(
            &|s| s.reward = RewardKind::Expression("s[0]+".repeat(2000)),
            "over 4096",
        );
    }
}
