//! The task catalog: everything both processes must agree on about a task.
//!
//! A task's reward, termination and model transforms live here, once, so the simulator computes
//! the real reward with the very function the planner uses on imagined transitions.

pub mod ant;
pub mod cartpole;
pub mod expression;
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
    pub reward_gradient: RewardGradient,
    pub is_terminal: fn(next_obs: &[f32]) -> bool,
    pub state_features: fn(obs: &[f32], out: &mut [f32]),
    pub state_features_backward: fn(obs: &[f32], d_features: &[f32], d_obs: &mut [f32]),
    pub target: fn(obs: &[f32], next_obs: &[f32], out: &mut [f32]),
    pub next_obs_from_target: fn(obs: &[f32], target: &[f32], next_obs: &mut [f32]),
    pub next_obs_from_target_backward: TargetBackward,
}

/// A reward with its gradient: `(obs, act, next_obs, ∂r/∂act, ∂r/∂next_obs) → r`.
pub(crate) type RewardGradient =
    fn(obs: &[f32], act: &[f32], next_obs: &[f32], d_act: &mut [f32], d_next: &mut [f32]) -> f32;

/// Back-propagation through `next_obs_from_target`: `(obs, ∂L/∂next_obs, ∂L/∂obs (added to),
/// ∂L/∂target)`.
pub(crate) type TargetBackward =
    fn(obs: &[f32], d_next_obs: &[f32], d_obs: &mut [f32], d_target: &mut [f32]);

impl TaskSpec {
    /// Reward of the transition `obs --act--> next_obs`. The simulator reports exactly this.
    pub fn reward(&self, obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
        (self.functions.reward)(obs, act, next_obs)
    }

    /// The reward of `obs --act--> next_obs` (exactly [`TaskSpec::reward`]) and its gradient:
    /// `∂r/∂act` into `d_act` and `∂r/∂next_obs` into `d_next_obs` (both overwritten). Every
    /// catalog reward reads only the action and the new observation, so there is no `∂r/∂obs`
    /// (the finite-difference tests check that too). Where a reward has a kink (pusher's L1
    /// distances) the gradient is the one-sided one of `signum`, 0 exactly at the kink.
    /// Gradient-based planning (Adam + DAE) back-propagates through it.
    pub fn reward_gradient(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        d_act: &mut [f32],
        d_next_obs: &mut [f32],
    ) -> f32 {
        (self.functions.reward_gradient)(obs, act, next_obs, d_act, d_next_obs)
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

    /// The transpose of [`TaskSpec::state_features`]' Jacobian at `obs` applied to
    /// `d_features`, *added* to `d_obs`: back-propagation from the model's input to `obs`.
    pub fn state_features_backward(&self, obs: &[f32], d_features: &[f32], d_obs: &mut [f32]) {
        (self.functions.state_features_backward)(obs, d_features, d_obs)
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

    /// Back-propagation through [`TaskSpec::next_obs_from_target`]: given `∂L/∂next_obs`, adds
    /// `∂L/∂obs` to `d_obs` and writes `∂L/∂target` into `d_target`.
    pub fn next_obs_from_target_backward(
        &self,
        obs: &[f32],
        d_next_obs: &[f32],
        d_obs: &mut [f32],
        d_target: &mut [f32],
    ) {
        (self.functions.next_obs_from_target_backward)(obs, d_next_obs, d_obs, d_target)
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

/// Back-propagation through [`apply_delta`]: `next = obs + delta` passes its gradient to both.
pub(crate) fn apply_delta_backward(
    _obs: &[f32],
    d_next_obs: &[f32],
    d_obs: &mut [f32],
    d_target: &mut [f32],
) {
    d_target.copy_from_slice(d_next_obs);
    for (o, d) in d_obs.iter_mut().zip(d_next_obs) {
        *o += d;
    }
}

/// Features that are the observation itself.
pub(crate) fn identity_features(obs: &[f32], out: &mut [f32]) {
    out.copy_from_slice(obs);
}

/// Back-propagation through [`identity_features`].
pub(crate) fn identity_features_backward(_obs: &[f32], d_features: &[f32], d_obs: &mut [f32]) {
    for (o, d) in d_obs.iter_mut().zip(d_features) {
        *o += d;
    }
}

/// `∂(−w‖a‖²)/∂a = −2w·a` into `d_act`.
pub(crate) fn squared_norm_gradient(act: &[f32], weight: f32, d_act: &mut [f32]) {
    for (d, a) in d_act.iter_mut().zip(act) {
        *d = -2.0 * weight * a;
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

    /// A deterministic pseudo-random number in [-1, 1) for test inputs.
    fn wiggle(i: usize, salt: u32) -> f32 {
        let x = ((i as u32).wrapping_mul(2_654_435_761) ^ salt.wrapping_mul(40_503)) % 10_007;
        x as f32 / 5003.5 - 1.0
    }

    /// Central differences in f64 of `f` around `x` (f32 inputs), one coordinate at a time.
    fn finite_difference(x: &[f32], f: impl Fn(&[f32]) -> f32) -> Vec<f32> {
        let h = 1e-3f32;
        (0..x.len())
            .map(|i| {
                let (mut up, mut down) = (x.to_vec(), x.to_vec());
                up[i] += h;
                down[i] -= h;
                ((f(&up) as f64 - f(&down) as f64) / (2.0 * h as f64)) as f32
            })
            .collect()
    }

    fn assert_close(got: &[f32], want: &[f32], what: &str) {
        for (i, (g, w)) in got.iter().zip(want).enumerate() {
            let tol = 2e-2 * (1.0 + w.abs());
            assert!(
                (g - w).abs() <= tol,
                "{what}[{i}]: {g} vs {w}\n{got:?}\n{want:?}"
            );
        }
    }

    /// A transition for `spec` with every coordinate away from zero (pusher's L1 kinks lie at
    /// equal coordinates, which these never are).
    fn transition(spec: &TaskSpec, salt: u32) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let obs: Vec<f32> = (0..spec.obs_dim).map(|i| 0.7 * wiggle(i, salt)).collect();
        let next: Vec<f32> = (0..spec.obs_dim)
            .map(|i| 0.7 * wiggle(i + 100, salt))
            .collect();
        let act: Vec<f32> = (0..spec.act_dim)
            .map(|i| 0.5 * spec.action_high[i] * wiggle(i + 200, salt))
            .collect();
        (obs, act, next)
    }

    #[test]
    fn reward_gradients_match_finite_differences() {
        for &t in TaskId::ALL {
            let spec = t.spec();
            for salt in 1..4 {
                let (obs, act, next) = transition(spec, salt);
                let (mut d_act, mut d_next) =
                    (vec![f32::NAN; spec.act_dim], vec![0.0; spec.obs_dim]);
                let r = spec.reward_gradient(&obs, &act, &next, &mut d_act, &mut d_next);
                assert_eq!(r, spec.reward(&obs, &act, &next), "{t}: the same reward");
                let fd_act = finite_difference(&act, |a| spec.reward(&obs, a, &next));
                assert_close(&d_act, &fd_act, &format!("{t} ∂r/∂a"));
                let fd_next = finite_difference(&next, |n| spec.reward(&obs, &act, n));
                assert_close(&d_next, &fd_next, &format!("{t} ∂r/∂s'"));
                let fd_obs = finite_difference(&obs, |o| spec.reward(o, &act, &next));
                assert!(fd_obs.iter().all(|&g| g == 0.0), "{t}: the reward reads s");
                assert!(d_next.iter().any(|&g| g != 0.0), "{t}: a reward of s'");
            }
        }
    }

    #[test]
    fn feature_and_target_backward_match_finite_differences() {
        for &t in TaskId::ALL {
            let spec = t.spec();
            let (obs, _, next) = transition(spec, 7);
            let f = spec.state_feature_dim;
            // L = c · features(obs): its gradient is the Jacobian's transpose applied to c.
            let c: Vec<f32> = (0..f).map(|i| wiggle(i + 300, 7)).collect();
            let mut d_obs = vec![0.5; spec.obs_dim];
            spec.state_features_backward(&obs, &c, &mut d_obs);
            let fd = finite_difference(&obs, |o| {
                let mut out = vec![0.0; f];
                spec.state_features(o, &mut out);
                out.iter().zip(&c).map(|(x, c)| x * c).sum()
            });
            let added: Vec<f32> = fd.iter().map(|g| g + 0.5).collect();
            assert_close(&d_obs, &added, &format!("{t} features"));

            // L = c · next_obs_from_target(obs, target).
            let mut target = vec![0.0; spec.obs_dim];
            spec.target(&obs, &next, &mut target);
            let c: Vec<f32> = (0..spec.obs_dim).map(|i| wiggle(i + 400, 7)).collect();
            let loss = |o: &[f32], tg: &[f32]| {
                let mut n = vec![0.0; spec.obs_dim];
                spec.next_obs_from_target(o, tg, &mut n);
                n.iter().zip(&c).map(|(x, c)| x * c).sum::<f32>()
            };
            let (mut d_obs, mut d_target) = (vec![0.0; spec.obs_dim], vec![f32::NAN; spec.obs_dim]);
            spec.next_obs_from_target_backward(&obs, &c, &mut d_obs, &mut d_target);
            assert_close(
                &d_obs,
                &finite_difference(&obs, |o| loss(o, &target)),
                &format!("{t} ∂s'/∂s"),
            );
            assert_close(
                &d_target,
                &finite_difference(&target, |tg| loss(&obs, tg)),
                &format!("{t} ∂s'/∂target"),
            );
        }
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
