//! The task catalog: everything both processes must agree on about a task.
//!
//! A task's reward, termination and model transforms live here, once, so the simulator computes
//! the real reward with the very function the planner uses on imagined transitions.

pub mod ant;
pub mod cartpole;
pub mod halfcheetah;
pub mod pusher;
pub mod reacher3d;

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// The tasks ebmpc knows. The wire name is the lowercase identifier (`"cartpole"`).
///
/// New variants go at the end: postcard encodes a variant by its index, and replay logs and run
/// records store it, so reordering would make stored runs name the wrong task.
/// [`TaskId::ALL`] gives the paper's order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TaskId {
    Cartpole,
    Reacher3d,
    HalfCheetah,
    Ant,
    Pusher,
}

impl TaskId {
    /// Every task in the catalog, in the paper's order.
    pub const ALL: &'static [TaskId] = &[
        TaskId::Cartpole,
        TaskId::Reacher3d,
        TaskId::Pusher,
        TaskId::HalfCheetah,
        TaskId::Ant,
    ];

    /// The lowercase wire and command-line name.
    pub fn name(self) -> &'static str {
        match self {
            TaskId::Cartpole => "cartpole",
            TaskId::Reacher3d => "reacher3d",
            TaskId::HalfCheetah => "halfcheetah",
            TaskId::Ant => "ant",
            TaskId::Pusher => "pusher",
        }
    }

    /// The task's static description.
    pub fn spec(self) -> &'static TaskSpec {
        match self {
            TaskId::Cartpole => &cartpole::SPEC,
            TaskId::Reacher3d => &reacher3d::SPEC,
            TaskId::HalfCheetah => &halfcheetah::SPEC,
            TaskId::Ant => &ant::SPEC,
            TaskId::Pusher => &pusher::SPEC,
        }
    }
}

impl fmt::Display for TaskId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A task name that is not in the catalog.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown task `{0}` (known: {known})", known = TaskId::ALL.iter().map(|t| t.name()).collect::<Vec<_>>().join(", "))]
pub struct UnknownTask(pub String);

impl FromStr for TaskId {
    type Err = UnknownTask;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        TaskId::ALL
            .iter()
            .copied()
            .find(|t| t.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| UnknownTask(s.to_string()))
    }
}

/// Dimensions, bounds, timing, and the functions of one task.
///
/// All functions take one transition as slices; the planner calls them row by row over its
/// population (they are cheap next to the networks). Slices must have the task's dimensions.
#[derive(Debug)]
pub struct TaskSpec {
    pub id: TaskId,
    /// Observation length.
    pub obs_dim: usize,
    /// Action length.
    pub act_dim: usize,
    /// Lower action bound per dimension.
    pub action_low: &'static [f32],
    /// Upper action bound per dimension.
    pub action_high: &'static [f32],
    /// Steps per episode (time limit).
    pub episode_len: u32,
    /// Seconds of simulated time between two actions.
    pub control_dt: f64,
    /// Length of [`TaskSpec::state_features`]: the observation as the dynamics model sees it.
    pub state_feature_dim: usize,
    /// The largest observation and reward magnitudes an agent may send for this task.
    pub magnitudes: Magnitudes,
    pub(crate) functions: TaskFunctions,
}

/// The largest magnitudes a task's observations and rewards may take. Finite is not enough: a
/// value like 3.4e38 is finite, but the difference of two of them (the dynamics model's
/// target) overflows to infinity and poisons training. A planner refuses larger values, and
/// its operator can change them per task (`[limits.magnitudes.<task>]`) for a custom robot.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
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
}

/// The per-task functions behind [`TaskSpec`]'s methods.
#[derive(Debug)]
pub(crate) struct TaskFunctions {
    pub reward: fn(obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32,
    pub is_terminal: fn(next_obs: &[f32]) -> bool,
    pub state_features: fn(obs: &[f32], out: &mut [f32]),
    pub target: fn(obs: &[f32], next_obs: &[f32], out: &mut [f32]),
    pub next_obs_from_target: fn(obs: &[f32], target: &[f32], next_obs: &mut [f32]),
}

impl TaskSpec {
    /// Reward of the transition `obs --act--> next_obs`. The simulator reports exactly this.
    pub fn reward(&self, obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
        (self.functions.reward)(obs, act, next_obs)
    }

    /// Whether `next_obs` ends the episode (no reward accrues after it, in reality or imagination).
    pub fn is_terminal(&self, next_obs: &[f32]) -> bool {
        (self.functions.is_terminal)(next_obs)
    }

    /// The observation as the dynamics model's input sees it (e.g. angles as sin/cos),
    /// `state_feature_dim` numbers written to `out`. The action is appended by the model.
    pub fn state_features(&self, obs: &[f32], out: &mut [f32]) {
        (self.functions.state_features)(obs, out)
    }

    /// What the dynamics model learns to predict for a transition (`obs_dim` numbers):
    /// usually the delta `next_obs − obs`.
    pub fn target(&self, obs: &[f32], next_obs: &[f32], out: &mut [f32]) {
        (self.functions.target)(obs, next_obs, out)
    }

    /// The inverse of [`TaskSpec::target`]: the next observation from `obs` and a predicted target.
    pub fn next_obs_from_target(&self, obs: &[f32], target: &[f32], next_obs: &mut [f32]) {
        (self.functions.next_obs_from_target)(obs, target, next_obs)
    }

    /// Clamps an action into the task's bounds, in place.
    pub fn clamp_action(&self, act: &mut [f32]) {
        for ((a, lo), hi) in act.iter_mut().zip(self.action_low).zip(self.action_high) {
            *a = a.clamp(*lo, *hi);
        }
    }
}

/// Targets that are plain deltas: `next_obs − obs`.
pub(crate) fn delta_target(obs: &[f32], next_obs: &[f32], out: &mut [f32]) {
    for ((o, s), n) in out.iter_mut().zip(obs).zip(next_obs) {
        *o = n - s;
    }
}

/// Inverse of [`delta_target`].
pub(crate) fn apply_delta(obs: &[f32], delta: &[f32], next_obs: &mut [f32]) {
    for ((o, s), d) in next_obs.iter_mut().zip(obs).zip(delta) {
        *o = s + d;
    }
}

/// Never terminates: the episode runs to its time limit.
pub(crate) fn never_terminal(_next_obs: &[f32]) -> bool {
    false
}

/// `‖a‖²`.
pub(crate) fn squared_norm(a: &[f32]) -> f32 {
    a.iter().map(|x| x * x).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for &t in TaskId::ALL {
            assert_eq!(t.name().parse::<TaskId>().unwrap(), t);
            assert_eq!(t.spec().id, t);
            assert_eq!(t.spec().action_low.len(), t.spec().act_dim);
            assert_eq!(t.spec().action_high.len(), t.spec().act_dim);
        }
        let err = "walker".parse::<TaskId>().unwrap_err();
        assert!(err.to_string().contains("cartpole"), "{err}");
    }

    /// Stored replay logs and run records name their task by postcard's variant index.
    #[test]
    fn variant_indices_are_stable() {
        let indices: Vec<Vec<u8>> = [
            TaskId::Cartpole,
            TaskId::Reacher3d,
            TaskId::HalfCheetah,
            TaskId::Ant,
            TaskId::Pusher,
        ]
        .iter()
        .map(|t| postcard::to_stdvec(t).unwrap())
        .collect();
        assert_eq!(indices, [[0], [1], [2], [3], [4]]);
    }

    #[test]
    fn targets_invert() {
        for &t in TaskId::ALL {
            let spec = t.spec();
            let obs: Vec<f32> = (0..spec.obs_dim).map(|i| 0.1 * i as f32 - 0.3).collect();
            let next: Vec<f32> = (0..spec.obs_dim).map(|i| 0.05 * i as f32 + 0.2).collect();
            let mut target = vec![0.0; spec.obs_dim];
            let mut back = vec![0.0; spec.obs_dim];
            spec.target(&obs, &next, &mut target);
            spec.next_obs_from_target(&obs, &target, &mut back);
            for (a, b) in back.iter().zip(&next) {
                assert!((a - b).abs() < 1e-5, "{t}: {back:?} vs {next:?}");
            }
        }
    }
}
