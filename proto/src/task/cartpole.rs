//! Cartpole swing-up (PETS): a cart on a rail with a 0.6 m pole, θ = 0 hanging down.
//!
//! Observation `[x, θ, ẋ, θ̇]`; action: the force on the cart, ±3. 200 steps of 0.04 s.

use super::{
    Builtin, BuiltinCode, TaskSpec, TerminationKind, apply_delta, apply_delta_backward,
    catalog_entry, delta_target, never_terminal, squared_norm, squared_norm_gradient,
};

/// Pole length in metres (the reward's target is the tip straight above the rail's origin).
pub const POLE_LENGTH: f32 = 0.6;

pub(crate) const CODE: BuiltinCode = BuiltinCode {
    obs_dim: 4,
    act_dim: 1,
    state_feature_dim: 5,
    reward,
    reward_gradient,
    is_terminal: never_terminal,
    state_features,
    state_features_backward,
    target: delta_target,
    next_obs_from_target: apply_delta,
    next_obs_from_target_backward: apply_delta_backward,
};

/// The catalog entry.
pub(crate) fn spec() -> TaskSpec {
    catalog_entry(
        Builtin::Cartpole,
        vec![-3.0],
        vec![3.0],
        200,
        0.04,
        TerminationKind::Never,
    )
}

/// Position of the pole's tip for observation `[x, θ, …]`.
pub fn tip(obs: &[f32]) -> (f32, f32) {
    let (x, theta) = (obs[0], obs[1]);
    (x - POLE_LENGTH * theta.sin(), -POLE_LENGTH * theta.cos())
}

/// `exp(−‖tip − (0, 0.6)‖² / 0.6²) − 0.01 ‖a‖²`, on the state the action led to.
fn reward(_obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
    let (tx, ty) = tip(next_obs);
    let d2 = tx * tx + (ty - POLE_LENGTH) * (ty - POLE_LENGTH);
    (-d2 / (POLE_LENGTH * POLE_LENGTH)).exp() - 0.01 * squared_norm(act)
}

/// `[sin θ, cos θ, x, ẋ, θ̇]`: the angle wraps, so the model sees it on the circle.
/// [`reward`] and its gradient: with `e = exp(−d²/L²)`, `∂r/∂d² = −e/L²`, and
/// `d² = tx² + (ty − L)²` with `tx = x − L sin θ`, `ty = −L cos θ`.
fn reward_gradient(
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    d_act: &mut [f32],
    d_next: &mut [f32],
) -> f32 {
    let (tx, ty) = tip(next_obs);
    let (sin, cos) = next_obs[1].sin_cos();
    let l2 = POLE_LENGTH * POLE_LENGTH;
    let d2 = tx * tx + (ty - POLE_LENGTH) * (ty - POLE_LENGTH);
    let e = (-d2 / l2).exp();
    let dr_dd2 = -e / l2;
    d_next.fill(0.0);
    d_next[0] = dr_dd2 * 2.0 * tx;
    d_next[1] =
        dr_dd2 * (2.0 * tx * (-POLE_LENGTH * cos) + 2.0 * (ty - POLE_LENGTH) * POLE_LENGTH * sin);
    squared_norm_gradient(act, 0.01, d_act);
    reward(obs, act, next_obs)
}

/// Back-propagation through [`state_features`].
fn state_features_backward(obs: &[f32], d: &[f32], d_obs: &mut [f32]) {
    let (sin, cos) = obs[1].sin_cos();
    d_obs[1] += d[0] * cos - d[1] * sin;
    d_obs[0] += d[2];
    d_obs[2] += d[3];
    d_obs[3] += d[4];
}

fn state_features(obs: &[f32], out: &mut [f32]) {
    let theta = obs[1];
    out[0] = theta.sin();
    out[1] = theta.cos();
    out[2] = obs[0];
    out[3] = obs[2];
    out[4] = obs[3];
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::PI;

    #[test]
    fn reward_peaks_upright_at_the_origin() {
        let spec = Builtin::Cartpole.task();
        let upright = spec.reward(&[0.0; 4], &[0.0], &[0.0, PI, 0.0, 0.0]);
        assert!((upright - 1.0).abs() < 1e-6, "{upright}");
        let hanging = spec.reward(&[0.0; 4], &[0.0], &[0.0, 0.0, 0.0, 0.0]);
        assert!(hanging < 0.02, "{hanging}");
        let shifted = spec.reward(&[0.0; 4], &[0.0], &[0.5, PI, 0.0, 0.0]);
        assert!(hanging < shifted && shifted < upright);
        let pushing = spec.reward(&[0.0; 4], &[3.0], &[0.0, PI, 0.0, 0.0]);
        assert!((upright - pushing - 0.09).abs() < 1e-6);
    }

    #[test]
    fn features_put_the_angle_on_the_circle() {
        let mut f = [0.0; 5];
        state_features(&[1.0, PI / 2.0, 2.0, 3.0], &mut f);
        assert!((f[0] - 1.0).abs() < 1e-6 && f[1].abs() < 1e-6);
        assert_eq!(&f[2..], &[1.0, 2.0, 3.0]);
    }
}
