//! The task catalog: everything both processes must agree on about a task.
//!
//! A task is data ([`TaskSpec`], `spec.rs`): a TOML/JSON file on the daemon or a spec in an
//! agent's attach. [`Task`] (`compiled.rs`) is a spec with its code: the reward, termination and
//! model transforms its kinds name. The five tasks of the paper are catalog entries of the same
//! type whose reward, termination and transforms are Rust code ([`Builtin`], one module each),
//! so the simulator computes the real reward with the very function the planner uses on
//! imagined transitions. [`TaskCatalog`] (`catalog.rs`) answers lookups by name.

pub mod ant;
pub mod cartpole;
mod catalog;
mod compiled;
pub mod expression;
pub mod halfcheetah;
pub mod pusher;
pub mod reacher3d;
mod spec;
mod transforms;

pub use catalog::{CatalogError, TaskCatalog, UnknownTask};
pub use compiled::{
    Formula, FormulaScratch, MAX_DISTINCT_TASKS, Task, TaskError, compile_expression,
};
pub use spec::{
    DeclaredTransforms, MAX_ACTION_BOUND, MAX_CONTROL_DT, MAX_EXPRESSION_BYTES, MAX_MAGNITUDE,
    MIN_CONTROL_DT, Magnitudes, ModelTransforms, ObservationBounds, RewardKind, SpecBounds,
    SpecError, TaskSpec, TerminationKind,
};

use serde::{Deserialize, Serialize};
use std::fmt;

/// The tasks whose reward, termination and model transforms are Rust code: the paper's five.
///
/// This names code, not a task: tasks are named by their name string on the wire and on disk.
/// A spec names a builtin kind by its lowercase name (`reward = { builtin = "cartpole" }`);
/// postcard (a spec in an attach) by the variant's index, so new variants go at the end.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Builtin {
    Cartpole,
    Reacher3d,
    HalfCheetah,
    Ant,
    Pusher,
}

impl Builtin {
    /// Every builtin task, in the paper's order.
    pub const ALL: &'static [Builtin] = &[
        Builtin::Cartpole,
        Builtin::Reacher3d,
        Builtin::Pusher,
        Builtin::HalfCheetah,
        Builtin::Ant,
    ];

    /// The lowercase name: of the catalog entry and of the kind in a spec.
    pub fn name(self) -> &'static str {
        match self {
            Builtin::Cartpole => "cartpole",
            Builtin::Reacher3d => "reacher3d",
            Builtin::HalfCheetah => "halfcheetah",
            Builtin::Ant => "ant",
            Builtin::Pusher => "pusher",
        }
    }

    /// The builtin of that name (ASCII case ignored), if there is one.
    pub fn from_name(name: &str) -> Option<Builtin> {
        Builtin::ALL
            .iter()
            .copied()
            .find(|b| b.name().eq_ignore_ascii_case(name))
    }

    /// The catalog entry: this builtin's dimensions, bounds, timing and its code as every kind.
    pub fn spec(self) -> TaskSpec {
        match self {
            Builtin::Cartpole => cartpole::spec(),
            Builtin::Reacher3d => reacher3d::spec(),
            Builtin::HalfCheetah => halfcheetah::spec(),
            Builtin::Ant => ant::spec(),
            Builtin::Pusher => pusher::spec(),
        }
    }

    /// The catalog entry as a task (compiled once per process).
    pub fn task(self) -> &'static Task {
        Task::intern(self.spec(), &SpecBounds::default())
            .expect("every catalog entry is a valid task (tested)")
    }

    /// This builtin's reward written in the expression language (the same numbers as its Rust
    /// code, to within rounding; `expression::tests` checks the values and gradients), for
    /// comparing the two on the planner's path (`planner-service bench plan --rewards`).
    /// Reacher3d's has none here: the forward kinematics of its arm's tip, written out as a
    /// formula, was never checked against its code.
    pub fn reward_formula(self) -> Option<&'static str> {
        match self {
            Builtin::Cartpole => Some(
                "exp(-((s_next[0] - 0.6*sin(s_next[1]))^2 + (-0.6*cos(s_next[1]) - 0.6)^2) \
                 / (0.6*0.6)) - 0.01*dot(a, a)",
            ),
            Builtin::HalfCheetah => Some("s_next[0] - 0.1*dot(a, a)"),
            Builtin::Ant => Some("s_next[13] - 0.5*dot(a, a) + 1"),
            Builtin::Pusher => Some(
                "-(1.25*norm1(s_next[17:20] - [0.45, -0.05, -0.25]) \
                  + 0.5*norm1(s_next[17:20] - s_next[14:17]) + 0.1*dot(a, a))",
            ),
            Builtin::Reacher3d => None,
        }
    }

    /// Where a locomotion task's observation holds the root's forward (x) velocity, whose
    /// integral over an episode is how far the body travelled; `None` for the tasks that do
    /// not move a body forward.
    pub fn forward_velocity(self) -> Option<usize> {
        match self {
            Builtin::HalfCheetah => Some(halfcheetah::FORWARD_VELOCITY),
            Builtin::Ant => Some(ant::FORWARD_VELOCITY),
            Builtin::Cartpole | Builtin::Reacher3d | Builtin::Pusher => None,
        }
    }

    /// The observation and action dimensions the code indexes.
    pub fn dims(self) -> (usize, usize) {
        let code = self.code();
        (code.obs_dim, code.act_dim)
    }

    pub(crate) fn code(self) -> &'static BuiltinCode {
        match self {
            Builtin::Cartpole => &cartpole::CODE,
            Builtin::Reacher3d => &reacher3d::CODE,
            Builtin::HalfCheetah => &halfcheetah::CODE,
            Builtin::Ant => &ant::CODE,
            Builtin::Pusher => &pusher::CODE,
        }
    }

    /// The base preset of a spec that names none: the smallest task's sizes.
    pub(crate) fn default_base() -> Builtin {
        Builtin::Cartpole
    }
}

/// Command lines (benchmarks, sim-bridge) name a builtin by its name.
impl std::str::FromStr for Builtin {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        Builtin::from_name(s).ok_or_else(|| {
            let known: Vec<&str> = Builtin::ALL.iter().map(|b| b.name()).collect();
            format!("unknown built-in task `{s}` (known: {})", known.join(", "))
        })
    }
}

impl fmt::Display for Builtin {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A builtin's catalog entry: every kind is its own code.
fn catalog_entry(
    builtin: Builtin,
    action_low: Vec<f32>,
    action_high: Vec<f32>,
    episode_len: u32,
    control_dt: f64,
    termination: TerminationKind,
) -> TaskSpec {
    let (obs_dim, act_dim) = builtin.dims();
    TaskSpec {
        name: builtin.name().to_string(),
        obs_dim,
        act_dim,
        action_low,
        action_high,
        episode_len,
        control_dt,
        observation_bounds: None,
        magnitudes: Magnitudes::GENEROUS,
        model: ModelTransforms::Builtin(builtin),
        termination,
        reward: RewardKind::Builtin(builtin),
        base_preset: builtin,
    }
}

/// The Rust code of one builtin task. All functions take one transition as slices of the
/// builtin's dimensions.
#[derive(Debug)]
pub(crate) struct BuiltinCode {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Length of the model's state input ([`BuiltinCode::state_features`]).
    pub state_feature_dim: usize,
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
    fn builtin_names_round_trip_and_entries_name_their_code() {
        for &b in Builtin::ALL {
            assert_eq!(Builtin::from_name(b.name()), Some(b));
            let task = b.task();
            assert_eq!(task.name, b.name());
            assert_eq!(task.reward, RewardKind::Builtin(b));
            assert_eq!(task.action_low.len(), task.act_dim);
            assert_eq!(task.action_high.len(), task.act_dim);
        }
        assert_eq!(Builtin::from_name("walker"), None);
    }

    /// A spec in an attach names a builtin kind by postcard's variant index.
    #[test]
    fn variant_indices_are_stable() {
        let indices: Vec<Vec<u8>> = [
            Builtin::Cartpole,
            Builtin::Reacher3d,
            Builtin::HalfCheetah,
            Builtin::Ant,
            Builtin::Pusher,
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
    fn transition(spec: &Task, salt: u32) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
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
        for &t in Builtin::ALL {
            let spec = t.task();
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
        // The builtins' code, and transforms declared per dimension (angles, absolute targets).
        let mut declared = Builtin::Cartpole.spec();
        declared.name = "declared-transforms".into();
        declared.model = ModelTransforms::Declared(DeclaredTransforms {
            angles: vec![1, 3],
            absolute: vec![0, 3],
        });
        let declared = Task::intern(declared, &SpecBounds::default()).unwrap();
        let tasks = Builtin::ALL.iter().map(|b| b.task()).chain([declared]);
        for spec in tasks {
            let t = spec.name();
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
        for &t in Builtin::ALL {
            let spec = t.task();
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
