//! Half-cheetah (PETS): a planar 9-link runner with 6 actuated joints.
//!
//! Observation (18): forward velocity of the root `Δx/dt`, then qpos without the root x (8:
//! root z, root pitch, 6 joints), then qvel (9). Actions ±1, 1000 steps of 0.05 s.

use super::{
    Builtin, BuiltinCode, TaskSpec, TerminationKind, catalog_entry, never_terminal, squared_norm,
    squared_norm_gradient,
};

pub(crate) const CODE: BuiltinCode = BuiltinCode {
    obs_dim: 18,
    act_dim: 6,
    state_feature_dim: 18,
    reward,
    reward_gradient,
    is_terminal: never_terminal,
    state_features,
    state_features_backward,
    target,
    next_obs_from_target,
    next_obs_from_target_backward,
};

/// The catalog entry.
pub(crate) fn spec() -> TaskSpec {
    catalog_entry(
        Builtin::HalfCheetah,
        vec![-1.0; 6],
        vec![1.0; 6],
        1000,
        0.05,
        TerminationKind::Never,
    )
}

/// Index of the root pitch in the observation.
const PITCH: usize = 2;

/// Index of the root's forward velocity `Δx/dt` in the observation.
pub const FORWARD_VELOCITY: usize = 0;

/// `obs[0] − 0.1 ‖a‖²`: the forward velocity reached by this step, minus the control cost.
fn reward(_obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
    next_obs[FORWARD_VELOCITY] - 0.1 * squared_norm(act)
}

/// `[obs[1], sin obs[2], cos obs[2], obs[3..]]`: the velocity is a target, not an input, and the
/// pitch wraps, so the model sees it on the circle.
/// [`reward`] and its gradient: 1 for the forward velocity, `−0.2a` for the action.
fn reward_gradient(
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    d_act: &mut [f32],
    d_next: &mut [f32],
) -> f32 {
    d_next.fill(0.0);
    d_next[FORWARD_VELOCITY] = 1.0;
    squared_norm_gradient(act, 0.1, d_act);
    reward(obs, act, next_obs)
}

/// Back-propagation through [`state_features`] (the velocity `obs[0]` is not a feature).
fn state_features_backward(obs: &[f32], d: &[f32], d_obs: &mut [f32]) {
    let (sin, cos) = obs[PITCH].sin_cos();
    d_obs[1] += d[0];
    d_obs[PITCH] += d[1] * cos - d[2] * sin;
    for (o, g) in d_obs[3..].iter_mut().zip(&d[3..]) {
        *o += g;
    }
}

/// Back-propagation through [`next_obs_from_target`]: the velocity is the target itself, the
/// rest are deltas.
fn next_obs_from_target_backward(
    obs: &[f32],
    d_next: &[f32],
    d_obs: &mut [f32],
    d_target: &mut [f32],
) {
    d_target[0] = d_next[0];
    super::apply_delta_backward(&obs[1..], &d_next[1..], &mut d_obs[1..], &mut d_target[1..]);
}

fn state_features(obs: &[f32], out: &mut [f32]) {
    out[0] = obs[1];
    out[1] = obs[PITCH].sin();
    out[2] = obs[PITCH].cos();
    out[3..].copy_from_slice(&obs[3..]);
}

/// The next velocity itself (it is not a state, so a delta means nothing), deltas for the rest.
fn target(obs: &[f32], next_obs: &[f32], out: &mut [f32]) {
    out[0] = next_obs[0];
    super::delta_target(&obs[1..], &next_obs[1..], &mut out[1..]);
}

fn next_obs_from_target(obs: &[f32], target: &[f32], next_obs: &mut [f32]) {
    next_obs[0] = target[0];
    super::apply_delta(&obs[1..], &target[1..], &mut next_obs[1..]);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn running_forward_pays() {
        let spec = Builtin::HalfCheetah.task();
        let still = [0.0; 18];
        let mut running = [0.0; 18];
        running[0] = 3.0;
        assert!(spec.reward(&still, &[0.0; 6], &running) > spec.reward(&still, &[0.0; 6], &still));
        assert!((spec.reward(&still, &[1.0; 6], &still) + 0.6).abs() < 1e-6);
    }

    #[test]
    fn features_drop_velocity_and_wrap_pitch() {
        let mut obs = [0.0f32; 18];
        obs[0] = 9.0;
        obs[1] = 0.5;
        obs[2] = std::f32::consts::FRAC_PI_2;
        obs[17] = 4.0;
        let mut f = [0.0; 18];
        state_features(&obs, &mut f);
        assert_eq!(f[0], 0.5);
        assert!((f[1] - 1.0).abs() < 1e-6 && f[2].abs() < 1e-6);
        assert_eq!(f[17], 4.0);
        assert!(!f.contains(&9.0));
    }
}
