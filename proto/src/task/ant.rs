//! Ant (gym Ant with MBPO's truncated observation): a quadruped with 8 actuated joints.
//!
//! Observation (27): qpos without the root x, y (13: torso height, orientation quaternion,
//! 8 joints), then qvel (14, starting with the root's x velocity). Actions ±1, 1000 steps of
//! 0.05 s. The episode terminates when the torso height leaves [0.2, 1.0].

use super::{
    Builtin, BuiltinCode, TaskSpec, TerminationKind, apply_delta, apply_delta_backward,
    catalog_entry, delta_target, identity_features, identity_features_backward, squared_norm,
    squared_norm_gradient,
};

pub(crate) const CODE: BuiltinCode = BuiltinCode {
    obs_dim: 27,
    act_dim: 8,
    state_feature_dim: 27,
    reward,
    reward_gradient,
    is_terminal,
    state_features: identity_features,
    state_features_backward: identity_features_backward,
    target: delta_target,
    next_obs_from_target: apply_delta,
    next_obs_from_target_backward: apply_delta_backward,
};

/// The catalog entry.
pub(crate) fn spec() -> TaskSpec {
    catalog_entry(
        Builtin::Ant,
        vec![-1.0; 8],
        vec![1.0; 8],
        1000,
        0.05,
        TerminationKind::Builtin(Builtin::Ant),
    )
}

/// Index of the torso height in the observation.
pub const TORSO_HEIGHT: usize = 0;
/// Index of the root's forward (x) velocity in the observation.
pub const FORWARD_VELOCITY: usize = 13;
/// Healthy torso heights.
pub const HEALTHY_HEIGHT: (f32, f32) = (0.2, 1.0);

/// `forward velocity − 0.5 ‖a‖² + 1` (the survive bonus).
fn reward(_obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
    next_obs[FORWARD_VELOCITY] - 0.5 * squared_norm(act) + 1.0
}

/// [`reward`] and its gradient: 1 for the forward velocity, `−a` for the action.
fn reward_gradient(
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    d_act: &mut [f32],
    d_next: &mut [f32],
) -> f32 {
    d_next.fill(0.0);
    d_next[FORWARD_VELOCITY] = 1.0;
    squared_norm_gradient(act, 0.5, d_act);
    reward(obs, act, next_obs)
}

/// The torso left the healthy height range: the ant fell (or jumped off).
fn is_terminal(next_obs: &[f32]) -> bool {
    let z = next_obs[TORSO_HEIGHT];
    !(HEALTHY_HEIGHT.0..=HEALTHY_HEIGHT.1).contains(&z)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn falling_terminates_and_walking_pays() {
        let spec = Builtin::Ant.task();
        let mut standing = [0.0f32; 27];
        standing[TORSO_HEIGHT] = 0.55;
        assert!(!spec.is_terminal(&standing));
        let mut fallen = standing;
        fallen[TORSO_HEIGHT] = 0.1;
        assert!(spec.is_terminal(&fallen));
        let mut walking = standing;
        walking[FORWARD_VELOCITY] = 1.5;
        assert!((spec.reward(&standing, &[0.0; 8], &walking) - 2.5).abs() < 1e-6);
        assert!((spec.reward(&standing, &[1.0; 8], &standing) + 3.0).abs() < 1e-6);
    }
}
