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
use nalgebra::{Rotation3, Unit, Vector3};

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

impl Axis {
    /// The axis as a unit vector of its link's frame.
    fn unit(self) -> Unit<Vector3<f32>> {
        match self {
            Axis::X => Vector3::x_axis(),
            Axis::Y => Vector3::y_axis(),
            Axis::Z => Vector3::z_axis(),
        }
    }
}

/// The arm's forward kinematics for one pose: each joint's axis and position in the world frame
/// (the shoulder at the origin), and the tip's position.
struct Chain {
    axes: [Vector3<f32>; JOINTS],
    origins: [Vector3<f32>; JOINTS],
    tip: Vector3<f32>,
}

impl Chain {
    /// Walks the chain from the shoulder for the joint angles `q` (at least [`JOINTS`]).
    fn new(q: &[f32]) -> Self {
        let mut rot = Rotation3::<f32>::identity();
        let mut pos = Vector3::zeros();
        let mut axes = [Vector3::zeros(); JOINTS];
        let mut origins = [Vector3::zeros(); JOINTS];
        for (j, ((&angle, &axis), &offset)) in
            q[..JOINTS].iter().zip(&AXES).zip(&OFFSETS).enumerate()
        {
            rot *= Rotation3::from_axis_angle(&axis.unit(), angle);
            axes[j] = rot * axis.unit().into_inner();
            origins[j] = pos;
            pos += rot * Vector3::x() * offset;
        }
        Self {
            axes,
            origins,
            tip: pos,
        }
    }
}

/// The tip's position in the world frame (the shoulder at the origin) for the joint angles
/// `q` (the first [`JOINTS`] numbers of an observation).
pub fn tip(q: &[f32]) -> [f32; 3] {
    Chain::new(q).tip.into()
}

/// `−‖tip − goal‖² − 0.01 ‖a‖²`, with the tip and the goal of the new observation.
fn reward(_obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
    let distance = (Chain::new(next_obs).tip - goal(next_obs)).norm_squared();
    -distance - 0.01 * super::squared_norm(act)
}

/// The goal point of an observation.
fn goal(obs: &[f32]) -> Vector3<f32> {
    Vector3::from_column_slice(&obs[GOAL..GOAL + 3])
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
    let chain = Chain::new(next_obs);
    let e = chain.tip - goal(next_obs);
    d_next.fill(0.0);
    for ((d, w), p) in d_next[..JOINTS]
        .iter_mut()
        .zip(&chain.axes)
        .zip(&chain.origins)
    {
        *d = -2.0 * e.dot(&w.cross(&(chain.tip - p)));
    }
    for (d, e) in d_next[GOAL..GOAL + 3].iter_mut().zip(e.iter()) {
        *d = 2.0 * e;
    }
    squared_norm_gradient(act, 0.01, d_act);
    reward(obs, act, next_obs)
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

    /// The kinematics as first written, with hand-written 3×3 products: the reference the
    /// nalgebra version must reproduce.
    mod hand_written {
        use super::super::{AXES, Axis, GOAL, JOINTS, OFFSETS};

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

        /// The tip, and `∂‖tip − goal‖²/∂q` for the observation `obs`.
        pub fn tip_and_distance_gradient(obs: &[f32]) -> ([f32; 3], [f32; JOINTS]) {
            let mut rot = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            let mut pos = [0.0f32; 3];
            let mut joints = [([0.0f32; 3], [0.0f32; 3]); JOINTS];
            for (j, ((&angle, &axis), &offset)) in
                obs[..JOINTS].iter().zip(&AXES).zip(&OFFSETS).enumerate()
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
            let e: [f32; 3] = std::array::from_fn(|i| pos[i] - obs[GOAL + i]);
            let mut grad = [0.0; JOINTS];
            for (d, (w, p)) in grad.iter_mut().zip(&joints) {
                let arm = [pos[0] - p[0], pos[1] - p[1], pos[2] - p[2]];
                let dtip = [
                    w[1] * arm[2] - w[2] * arm[1],
                    w[2] * arm[0] - w[0] * arm[2],
                    w[0] * arm[1] - w[1] * arm[0],
                ];
                *d = 2.0 * (e[0] * dtip[0] + e[1] * dtip[1] + e[2] * dtip[2]);
            }
            (pos, grad)
        }
    }

    /// On random poses and goals, the tip and the reward's gradient are the hand-written
    /// kinematics' to f32 rounding.
    #[test]
    fn kinematics_match_the_hand_written_products() {
        use rand::{RngExt, SeedableRng};
        let spec = Builtin::Reacher3d.task();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for _ in 0..500 {
            let mut obs = [0.0f32; 17];
            for v in &mut obs[..JOINTS] {
                *v = rng.random_range(-3.2..3.2);
            }
            for v in &mut obs[GOAL..GOAL + 3] {
                *v = rng.random_range(-0.9..0.9);
            }
            let (want_tip, want_grad) = hand_written::tip_and_distance_gradient(&obs);
            assert!(close(tip(&obs), want_tip), "{obs:?}");
            let (mut d_act, mut d_next) = ([0.0f32; 7], [0.0f32; 17]);
            spec.reward_gradient(&obs, &[0.0; 7], &obs, &mut d_act, &mut d_next);
            for (got, want) in d_next[..JOINTS].iter().zip(&want_grad) {
                assert!((got + want).abs() < 1e-5, "{got} vs {}", -want);
            }
        }
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
