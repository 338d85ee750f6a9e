//! Pusher (PETS): a 7-joint arm without gravity pushes a cylinder across a table to a fixed goal.
//!
//! Observation (20): the 7 joint angles, the 7 joint velocities, the arm's tip position (3) and
//! the object's position (3), both in the world frame. Actions are joint torques in ±2 N·m,
//! 150 steps of 0.04 s. Unlike Reacher3D the tip is observed, so the reward needs no forward
//! kinematics; the goal never moves, so it is a constant here ([`GOAL`]) rather than part of
//! the observation (sim-bridge's `assets/pusher.xml` marks it with a site, and its tests check
//! the two agree).

use super::{
    Builtin, BuiltinCode, TaskSpec, TerminationKind, apply_delta, apply_delta_backward,
    catalog_entry, delta_target, identity_features, identity_features_backward, never_terminal,
    squared_norm_gradient,
};

pub(crate) const CODE: BuiltinCode = BuiltinCode {
    obs_dim: 20,
    act_dim: 7,
    state_feature_dim: 20,
    reward,
    reward_gradient,
    is_terminal: never_terminal,
    state_features: identity_features,
    state_features_backward: identity_features_backward,
    target: delta_target,
    next_obs_from_target: apply_delta,
    next_obs_from_target_backward: apply_delta_backward,
};

/// The catalog entry.
pub(crate) fn spec() -> TaskSpec {
    catalog_entry(
        Builtin::Pusher,
        vec![-2.0; 7],
        vec![2.0; 7],
        150,
        0.04,
        TerminationKind::Never,
    )
}

/// Joints of the arm.
pub const JOINTS: usize = 7;
/// Index of the first joint velocity in the observation.
pub const QVEL: usize = JOINTS;
/// Index of the tip's x coordinate in the observation (y and z follow).
pub const TIP: usize = 2 * JOINTS;
/// Index of the object's x coordinate in the observation (y and z follow).
pub const OBJECT: usize = TIP + 3;

/// Where the object's centre must go, in the world frame: on the table, at the height of the
/// object's centre, so that a perfect push scores a zero distance.
pub const GOAL: [f32; 3] = [0.45, -0.05, -0.25];

/// Weight of the object–goal distance in the cost.
pub const GOAL_WEIGHT: f32 = 1.25;
/// Weight of the object–tip distance in the cost (it draws the arm to the object first).
pub const TIP_WEIGHT: f32 = 0.5;
/// Weight of the squared action in the cost.
pub const ACTION_WEIGHT: f32 = 0.1;

/// `−(1.25 ‖object − goal‖₁ + 0.5 ‖object − tip‖₁ + 0.1 ‖a‖²)`, on the state the action led to.
fn reward(_obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
    let object = &next_obs[OBJECT..OBJECT + 3];
    let tip = &next_obs[TIP..TIP + 3];
    let to_goal = l1(object, &GOAL);
    let to_tip = l1(object, tip);
    -(GOAL_WEIGHT * to_goal + TIP_WEIGHT * to_tip + ACTION_WEIGHT * super::squared_norm(act))
}

/// [`reward`] and its gradient: the L1 distances give signs (0 exactly at a kink).
fn reward_gradient(
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    d_act: &mut [f32],
    d_next: &mut [f32],
) -> f32 {
    let sign = |x: f32| if x == 0.0 { 0.0 } else { x.signum() };
    d_next.fill(0.0);
    for k in 0..3 {
        let (object, tip) = (next_obs[OBJECT + k], next_obs[TIP + k]);
        let to_tip = sign(object - tip);
        d_next[OBJECT + k] = -(GOAL_WEIGHT * sign(object - GOAL[k]) + TIP_WEIGHT * to_tip);
        d_next[TIP + k] = TIP_WEIGHT * to_tip;
    }
    squared_norm_gradient(act, ACTION_WEIGHT, d_act);
    reward(obs, act, next_obs)
}

/// `‖a − b‖₁`.
fn l1(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An observation with the object at `object` and the tip at `tip`.
    fn state(object: [f32; 3], tip: [f32; 3]) -> [f32; 20] {
        let mut obs = [0.0; 20];
        obs[TIP..TIP + 3].copy_from_slice(&tip);
        obs[OBJECT..OBJECT + 3].copy_from_slice(&object);
        obs
    }

    #[test]
    fn reward_is_the_weighted_l1_cost() {
        let spec = Builtin::Pusher.task();
        let on_goal = state(GOAL, GOAL);
        assert_eq!(spec.reward(&on_goal, &[0.0; 7], &on_goal), 0.0);

        // Object 0.1 off in x and 0.2 in y; the tip touching it.
        let object = [GOAL[0] + 0.1, GOAL[1] - 0.2, GOAL[2]];
        let off = state(object, object);
        assert!((spec.reward(&on_goal, &[0.0; 7], &off) + 1.25 * 0.3).abs() < 1e-6);

        // The tip 0.2 from the object in z: L1, not Euclidean.
        let away = state(GOAL, [GOAL[0] + 0.1, GOAL[1], GOAL[2] + 0.2]);
        assert!((spec.reward(&on_goal, &[0.0; 7], &away) + 0.5 * 0.3).abs() < 1e-6);

        let act = [1.0, -1.0, 0.0, 0.0, 0.0, 0.0, 2.0];
        assert!((spec.reward(&on_goal, &act, &on_goal) + 0.1 * 6.0).abs() < 1e-6);
    }

    #[test]
    fn reward_rises_as_the_object_nears_the_goal() {
        let spec = Builtin::Pusher.task();
        let rewards: Vec<f32> = [0.4f32, 0.2, 0.1, 0.05, 0.0]
            .iter()
            .map(|d| {
                let object = [GOAL[0] - d, GOAL[1] + d, GOAL[2]];
                let next = state(object, [object[0] - 0.06, object[1], object[2]]);
                spec.reward(&next, &[0.0; 7], &next)
            })
            .collect();
        assert!(rewards.windows(2).all(|w| w[0] < w[1]), "{rewards:?}");
    }
}
