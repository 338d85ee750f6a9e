//! Reacher3D (PETS): a 7-joint arm without gravity reaching a goal point resampled every episode.
//!
//! Observation (17): the 7 joint angles, the goal's 3 coordinates, the 7 joint velocities.
//! Actions are joint torques in ±20 N·m, 150 steps of 0.02 s. The reward needs the arm's tip,
//! which is not observed: [`tip`] computes it from the joint angles by the forward kinematics of
//! ebmpc's arm (sim-bridge's `assets/reacher3d.xml` is built from the constants here, and its
//! tests check the two agree), so the simulator and the planner share one definition.

use super::{
    Builtin, BuiltinCode, TaskSpec, TerminationKind, apply_delta, apply_delta_backward,
    catalog_entry, delta_target, identity_features, identity_features_backward, never_terminal,
    squared_norm_gradient,
};

pub(crate) const CODE: BuiltinCode = BuiltinCode {
    obs_dim: 17,
    act_dim: 7,
    state_feature_dim: 17,
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
        Builtin::Reacher3d,
        vec![-20.0; 7],
        vec![20.0; 7],
        150,
        0.02,
        TerminationKind::Never,
    )
}

/// Joints of the arm.
pub const JOINTS: usize = 7;
/// Index of the goal's x coordinate in the observation (y and z follow).
pub const GOAL: usize = JOINTS;
/// Length of the upper arm: shoulder to elbow, along the link's x axis.
pub const UPPER_ARM: f32 = 0.4;
/// Length of the forearm: elbow to wrist.
pub const FOREARM: f32 = 0.321;
/// Wrist to tip.
pub const HAND: f32 = 0.15;

/// The axis of each joint in its link's frame, from the shoulder outwards: shoulder pan (z),
/// shoulder lift (y), upper-arm roll (x), elbow flex (y), forearm roll (x), wrist flex (y),
/// wrist roll (x). All links point along their x axis when the joints are at 0.
pub const AXES: [Axis; JOINTS] = [
    Axis::Z,
    Axis::Y,
    Axis::X,
    Axis::Y,
    Axis::X,
    Axis::Y,
    Axis::X,
];

/// A coordinate axis a joint turns about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    X,
    Y,
    Z,
}

/// Link length after each joint (the offset to the next joint, or to the tip after the last).
const OFFSETS: [f32; JOINTS] = [0.0, 0.0, UPPER_ARM, 0.0, FOREARM, 0.0, HAND];

/// The tip's position in the world frame (the shoulder at the origin) for the joint angles
/// `q` (the first [`JOINTS`] numbers of an observation).
pub fn tip(q: &[f32]) -> [f32; 3] {
    // Walk the chain: `rot` is the current link's orientation, `pos` its origin.
    let mut rot = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let mut pos = [0.0f32; 3];
    for ((&angle, &axis), &offset) in q[..JOINTS].iter().zip(&AXES).zip(&OFFSETS) {
        rot = mul(&rot, &rotation(axis, angle));
        for (p, row) in pos.iter_mut().zip(&rot) {
            *p += row[0] * offset;
        }
    }
    pos
}

/// `−‖tip − goal‖² − 0.01 ‖a‖²`, with the tip and the goal of the new observation.
fn reward(_obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
    let tip = tip(next_obs);
    let distance: f32 = tip
        .iter()
        .zip(&next_obs[GOAL..GOAL + 3])
        .map(|(t, g)| (t - g) * (t - g))
        .sum();
    -distance - 0.01 * super::squared_norm(act)
}

/// [`reward`] and its gradient. With `e = tip − goal`, `∂r/∂goal = 2e` and, since joint `j`
/// turns the tip about its world axis `w_j` through its position `p_j`,
/// `∂tip/∂q_j = w_j × (tip − p_j)` and `∂r/∂q_j = −2 e · (w_j × (tip − p_j))`.
fn reward_gradient(
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    d_act: &mut [f32],
    d_next: &mut [f32],
) -> f32 {
    // The forward kinematics again, keeping each joint's world axis and position.
    let mut rot = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let mut pos = [0.0f32; 3];
    let mut joints = [([0.0f32; 3], [0.0f32; 3]); JOINTS];
    for (j, ((&angle, &axis), &offset)) in next_obs[..JOINTS]
        .iter()
        .zip(&AXES)
        .zip(&OFFSETS)
        .enumerate()
    {
        rot = mul(&rot, &rotation(axis, angle));
        let k = match axis {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        };
        joints[j] = ([rot[0][k], rot[1][k], rot[2][k]], pos);
        for (p, row) in pos.iter_mut().zip(&rot) {
            *p += row[0] * offset;
        }
    }
    let e: [f32; 3] = std::array::from_fn(|i| pos[i] - next_obs[GOAL + i]);
    d_next.fill(0.0);
    for (d, (w, p)) in d_next[..JOINTS].iter_mut().zip(&joints) {
        let arm = [pos[0] - p[0], pos[1] - p[1], pos[2] - p[2]];
        let dtip = [
            w[1] * arm[2] - w[2] * arm[1],
            w[2] * arm[0] - w[0] * arm[2],
            w[0] * arm[1] - w[1] * arm[0],
        ];
        *d = -2.0 * (e[0] * dtip[0] + e[1] * dtip[1] + e[2] * dtip[2]);
    }
    for (d, e) in d_next[GOAL..GOAL + 3].iter_mut().zip(&e) {
        *d = 2.0 * e;
    }
    squared_norm_gradient(act, 0.01, d_act);
    reward(obs, act, next_obs)
}

fn rotation(axis: Axis, angle: f32) -> [[f32; 3]; 3] {
    let (s, c) = angle.sin_cos();
    match axis {
        Axis::X => [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]],
        Axis::Y => [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]],
        Axis::Z => [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
    }
}

fn mul(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::FRAC_PI_2;

    fn close(a: [f32; 3], b: [f32; 3]) -> bool {
        a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-5)
    }

    #[test]
    fn forward_kinematics_of_simple_poses() {
        let reach = UPPER_ARM + FOREARM + HAND;
        assert!(close(tip(&[0.0; 7]), [reach, 0.0, 0.0]));
        // Panning a quarter turn points the straight arm along +y.
        assert!(close(
            tip(&[FRAC_PI_2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
            [0.0, reach, 0.0]
        ));
        // Lifting by +π/2 about y turns +x into −z; the elbow at +π/2 turns the forearm back.
        assert!(close(
            tip(&[0.0, FRAC_PI_2, 0.0, 0.0, 0.0, 0.0, 0.0]),
            [0.0, 0.0, -reach]
        ));
        assert!(close(
            tip(&[0.0, 0.0, 0.0, FRAC_PI_2, 0.0, 0.0, 0.0]),
            [UPPER_ARM, 0.0, -FOREARM - HAND]
        ));
        // Rolls along a straight arm move nothing; the wrist roll never moves the tip.
        assert!(close(
            tip(&[0.0, 0.0, 1.0, 0.0, -2.0, 0.0, 3.0]),
            [reach, 0.0, 0.0]
        ));
    }

    #[test]
    fn reward_peaks_at_the_goal() {
        let spec = Builtin::Reacher3d.task();
        let mut obs = [0.0f32; 17];
        obs[..7].copy_from_slice(&[0.3, 0.4, 0.1, -1.0, 0.2, -0.5, 0.0]);
        let t = tip(&obs);
        obs[GOAL..GOAL + 3].copy_from_slice(&t);
        let at_goal = spec.reward(&obs, &[0.0; 7], &obs);
        assert!(at_goal.abs() < 1e-10);
        let mut off = obs;
        off[GOAL] += 0.3;
        assert!((spec.reward(&obs, &[0.0; 7], &off) + 0.09).abs() < 1e-5);
        assert!((spec.reward(&obs, &[1.0; 7], &obs) + 0.07).abs() < 1e-5);
    }
}
