//! The reward model learns a known reward to a small error on held-out transitions, its
//! gradient matches finite differences through the angle transforms, and its stored parts
//! restore it exactly.

use super::*;
use proto::task::{DeclaredTransforms, ModelTransforms, RewardKind, SpecBounds, TerminationKind};
use rand::RngExt;

/// A pendulum-like task with a learned reward: `[θ, θ̇, x]`, one action; θ is an angle (the
/// models see `sin θ`, `cos θ`).
fn task() -> &'static Task {
    let mut spec = proto::Builtin::Cartpole.spec();
    spec.name = "reward-model-test".into();
    spec.obs_dim = 3;
    spec.act_dim = 1;
    spec.action_low = vec![-2.0];
    spec.action_high = vec![2.0];
    spec.reward = RewardKind::Learned;
    spec.termination = TerminationKind::Never;
    spec.model = ModelTransforms::Declared(DeclaredTransforms {
        angles: vec![0],
        absolute: vec![],
    });
    Task::intern(spec, &SpecBounds::default()).unwrap()
}

/// The reward to learn: upright (θ' = 0 or 2π: the same angle) is best, effort costs.
fn known_reward(s: &[f32], a: &[f32], s1: &[f32]) -> f32 {
    s1[0].cos() - 0.1 * s1[1] * s1[1] - 0.1 * a[0] * a[0] + 0.05 * s[2]
}

fn transitions(n: usize, rng: &mut StdRng) -> Transitions {
    let mut data = Transitions::new(3, 1);
    for _ in 0..n {
        let s = [
            rng.random_range(-3.0f32..9.0), // angles beyond one turn: only sin/cos matter
            rng.random_range(-2.0f32..2.0),
            rng.random_range(-1.0f32..1.0),
        ];
        let a = [rng.random_range(-2.0f32..2.0)];
        let s1 = [s[0] + 0.1 * s[1], s[1] + 0.1 * a[0], s[2]];
        data.push(&s, &a, known_reward(&s, &a, &s1), &s1);
    }
    data
}

fn training() -> DynamicsConfig {
    DynamicsConfig {
        batch_size: 32,
        learning_rate: 3e-3,
        weight_decay: 0.0,
        ..DynamicsConfig::default()
    }
}

fn small() -> RewardConfig {
    RewardConfig {
        hidden_layers: 2,
        hidden_size: 32,
    }
}

#[test]
fn learns_a_known_reward_to_a_small_error_on_held_out_transitions() {
    let mut rng = StdRng::seed_from_u64(1);
    let (train, held_out) = (transitions(2000, &mut rng), transitions(500, &mut rng));
    let mut model = RewardModel::new(task(), &small(), &training(), &mut rng);
    assert!(!model.is_trained());
    let before = model.mean_squared_error(&held_out);
    let report = model.fit(&train, 60, &mut rng);
    assert!(model.is_trained());
    assert!(report.steps > 0 && report.loss.is_finite(), "{report:?}");
    let after = model.mean_squared_error(&held_out);
    // In units of the reward's variance: 1 is no better than its mean.
    assert!(
        after < 0.01,
        "held-out MSE {after} (before training {before})"
    );
    assert!(before > 0.3, "an untrained model knows nothing: {before}");
    // Batched inference (the planner's path, bf16 where the CPU has it) agrees.
    let mut bf16 = model.clone();
    bf16.set_inference_precision(proto::InferencePrecision::Bf16);
    assert!(bf16.mean_squared_error(&held_out) < 0.02);
}

/// Central differences of `f` in each coordinate of `x`.
fn finite_difference(x: &[f32], f: impl Fn(&[f32]) -> f32) -> Vec<f32> {
    let h = 1e-2f32;
    (0..x.len())
        .map(|i| {
            let (mut up, mut down) = (x.to_vec(), x.to_vec());
            up[i] += h;
            down[i] -= h;
            (f(&up) - f(&down)) / (2.0 * h)
        })
        .collect()
}

#[test]
fn gradient_matches_finite_differences() {
    let mut rng = StdRng::seed_from_u64(2);
    let data = transitions(300, &mut rng);
    let mut model = RewardModel::new(task(), &small(), &training(), &mut rng);
    model.fit(&data, 3, &mut rng);
    let rows = 5;
    let (obs, act, next) = (
        &data.obs()[..rows * 3],
        &data.act()[..rows],
        &data.next_obs()[..rows * 3],
    );
    let mut tape = model.tape(rows);
    let (mut out, mut d_obs, mut d_act, mut d_next) = (
        vec![0.0; rows],
        vec![0.0; rows * 3],
        vec![0.0; rows],
        vec![0.0; rows * 3],
    );
    model.predict_with_gradient(
        obs,
        act,
        next,
        rows,
        &mut tape,
        &mut out,
        &mut d_obs,
        &mut d_act,
        &mut d_next,
    );
    let value = |s: &[f32], a: &[f32], s1: &[f32]| {
        let mut r = [0.0];
        model.predict(s, a, s1, 1, &mut model.scratch(1), &mut r);
        r[0]
    };
    let mut scratch = model.scratch(1);
    let mut one = [0.0];
    for i in 0..rows {
        let (s, a, s1) = data.row(i);
        model.predict(s, a, s1, 1, &mut scratch, &mut one);
        assert!(
            (one[0] - out[i]).abs() < 1e-4,
            "row {i}: {} vs {}",
            one[0],
            out[i]
        );
        let checks = [
            (
                "s",
                finite_difference(s, |x| value(x, a, s1)),
                &d_obs[i * 3..(i + 1) * 3],
            ),
            (
                "a",
                finite_difference(a, |x| value(s, x, s1)),
                &d_act[i..i + 1],
            ),
            (
                "s'",
                finite_difference(s1, |x| value(s, a, x)),
                &d_next[i * 3..(i + 1) * 3],
            ),
        ];
        for (what, fd, analytic) in checks {
            for (k, (f, g)) in fd.iter().zip(analytic).enumerate() {
                assert!(
                    (f - g).abs() <= 2e-3 + 2e-2 * f.abs(),
                    "row {i} ∂r/∂{what}[{k}]: finite difference {f}, analytic {g}"
                );
            }
        }
        // The angle's gradient is real: θ enters through sin and cos, not as a plain input.
        assert!(d_obs[i * 3].abs() + d_next[i * 3].abs() > 0.0);
    }
}

#[test]
fn parts_restore_the_model_exactly_and_wrong_shapes_are_refused() {
    let mut rng = StdRng::seed_from_u64(3);
    let data = transitions(200, &mut rng);
    let mut model = RewardModel::new(task(), &small(), &training(), &mut rng);
    model.fit(&data, 2, &mut rng);
    let restored = RewardModel::from_parts(task(), &small(), &training(), model.parts()).unwrap();
    assert!(restored.is_trained());
    assert_eq!(restored.parts(), model.parts());
    assert_eq!(
        restored.mean_squared_error(&data),
        model.mean_squared_error(&data)
    );
    let wider = RewardConfig {
        hidden_size: 33,
        ..small()
    };
    let err = RewardModel::from_parts(task(), &wider, &training(), model.parts()).unwrap_err();
    assert!(err.to_string().contains("reward parameters"), "{err}");
}

#[test]
fn no_data_or_no_epochs_leave_the_model_untrained() {
    let mut rng = StdRng::seed_from_u64(4);
    let mut model = RewardModel::new(task(), &small(), &training(), &mut rng);
    let before = model.parts();
    model.fit(&Transitions::new(3, 1), 5, &mut rng);
    model.fit(&transitions(10, &mut rng), 0, &mut rng);
    assert!(!model.is_trained());
    assert_eq!(model.parts(), before);
}
