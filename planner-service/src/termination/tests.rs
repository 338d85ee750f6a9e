//! The termination classifier learns a real termination rule from episodes (held-out accuracy
//! and recall of ends), its loss gradient matches finite differences, it predicts no end
//! before it has seen one, and its stored parts restore it exactly.

use super::*;
use proto::task::{DeclaredTransforms, ModelTransforms, RewardKind, SpecBounds, TerminationKind};
use rand::RngExt;

/// An inverted pendulum on a cart whose termination is learned: `[x, θ, ẋ, θ̇]`, one action.
fn task() -> &'static Task {
    let mut spec = proto::Builtin::Cartpole.spec();
    spec.name = "termination-model-test".into();
    spec.obs_dim = 4;
    spec.act_dim = 1;
    spec.action_low = vec![-3.0];
    spec.action_high = vec![3.0];
    spec.reward = RewardKind::Expression("1".into());
    spec.termination = TerminationKind::Learned;
    spec.model = ModelTransforms::Declared(DeclaredTransforms::default());
    Task::intern(spec, &SpecBounds::default()).unwrap()
}

/// Gymnasium's InvertedPendulum rule: the episode ends once the pole leans more than 0.2 rad.
fn falls(s1: &[f32]) -> bool {
    s1[1].abs() > 0.2
}

/// Episodes of a pendulum that drifts under random pushes until it falls (or 60 steps pass:
/// a time limit, not an end), as an agent reports them.
fn episodes(count: usize, rng: &mut StdRng) -> Transitions {
    let mut data = Transitions::new(4, 1);
    for _ in 0..count {
        let mut s = [
            rng.random_range(-0.1f32..0.1),
            rng.random_range(-0.05f32..0.05),
            rng.random_range(-0.1f32..0.1),
            rng.random_range(-0.1f32..0.1),
        ];
        for _ in 0..60 {
            let a = [rng.random_range(-3.0f32..3.0)];
            let s1 = [
                s[0] + 0.04 * s[2],
                s[1] + 0.04 * s[3],
                s[2] + 0.04 * a[0],
                s[3] + 0.04 * (9.8 * s[1] - a[0]) + rng.random_range(-0.05f32..0.05),
            ];
            data.push(&s, &a, 1.0, &s1);
            if falls(&s1) {
                let last = data.len() - 1;
                data.mark_terminated(last);
                break;
            }
            s = s1;
        }
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

#[test]
fn learns_a_real_termination_rule_on_held_out_transitions() {
    let mut rng = StdRng::seed_from_u64(3);
    let data = episodes(300, &mut rng);
    let ends = data.terminated().iter().filter(|&&t| t).count();
    assert!(
        ends > 100 && ends * 5 < data.len(),
        "most episodes fall, and ends are a minority: {ends} of {}",
        data.len()
    );
    let mut model = TerminationModel::new(task(), &training(), &mut rng);
    assert!(!model.knows_ends() && model.held_out().is_none());
    let report = model.fit(&data, 40, &mut rng);
    assert!(report.steps > 0 && report.loss.is_finite(), "{report:?}");
    assert!(model.knows_ends());
    let held = model.held_out().expect("measured on the held-out fifth");
    let expected = (data.len() as f32 / HOLD_OUT_EVERY as f32) as u32;
    assert!(
        held.held_out.abs_diff(expected) < expected / 5 && held.terminations > 10,
        "{held:?} of {} transitions",
        data.len()
    );
    assert!(
        held.accuracy > 0.95 && held.recall > 0.9,
        "held-out accuracy {held:?}"
    );
    // Fresh episodes of the same system: the rule, not the training rows, was learned. The
    // never-ending classifier would score the ends' share below 1, and recall 0.
    let fresh = episodes(100, &mut StdRng::seed_from_u64(99));
    let all: Vec<usize> = (0..fresh.len()).collect();
    let scored = model.accuracy(&fresh, &all).unwrap();
    assert!(
        scored.accuracy > 0.95 && scored.recall > 0.9,
        "fresh episodes: {scored:?}"
    );
    // States well inside and well beyond the boundary, with the planner's batched inference.
    let next = [
        0.0, 0.0, 0.0, 0.0, // upright
        0.0, 0.35, 0.0, 1.0, // fallen to one side
        0.0, -0.35, 0.0, -1.0, // and to the other
        0.1, 0.05, 0.1, 0.1, // leaning a little
    ];
    let mut scratch = model.scratch(4);
    let mut ended = [false; 4];
    model.predict(&next, 4, &mut scratch, &mut ended);
    assert_eq!(ended, [false, true, true, false]);
}

#[test]
fn before_any_end_it_predicts_none_and_takes_no_step() {
    let mut rng = StdRng::seed_from_u64(5);
    let data = episodes(20, &mut rng);
    let never = {
        let mut t = Transitions::new(4, 1);
        for i in 0..data.len() {
            let (s, a, s1) = data.row(i);
            t.push(s, a, 1.0, s1);
        }
        t
    };
    let mut model = TerminationModel::new(task(), &training(), &mut rng);
    let report = model.fit(&never, 10, &mut rng);
    assert_eq!(report.steps, 0, "nothing ended: nothing to learn");
    assert!(!model.knows_ends() && model.held_out().is_none());
    let fallen = [0.0, 1.0, 0.0, 0.0];
    let mut out = [true];
    model.predict(&fallen, 1, &mut model.scratch(1), &mut out);
    assert_eq!(out, [false], "a model that saw no end predicts none");
    // The parts round-trip exactly, trained or not.
    model.fit(&data, 5, &mut rng);
    assert!(model.knows_ends());
    let restored = TerminationModel::from_parts(task(), &training(), model.parts()).unwrap();
    assert_eq!(restored.parts(), model.parts());
    let shorter = TerminationParts {
        params: vec![0.0; 3],
        ..model.parts()
    };
    assert!(TerminationModel::from_parts(task(), &training(), shorter).is_err());
}

/// The class-weighted logistic loss's hand-written gradient, through the network to every
/// parameter, against central finite differences of the loss.
#[test]
fn the_loss_gradient_matches_finite_differences() {
    let mut rng = StdRng::seed_from_u64(11);
    let mlp = Mlp::new(&[3, 5, 1], Activation::Swish, &mut rng);
    let n = 7;
    let inputs: Vec<f32> = (0..n * 3).map(|_| rng.random_range(-1.5f32..1.5)).collect();
    let labels: Vec<f32> = (0..n).map(|i| f32::from(u8::from(i % 3 == 0))).collect();
    let weights = class_weights(3, n);
    let batch: Vec<usize> = (0..n).collect();
    let mut tape = Tape::for_training(&mlp, n);
    let mut grads = vec![0.0; mlp.params().len()];
    logistic_loss_and_grad(&mlp, &inputs, &labels, weights, &batch, &mut tape);
    mlp.backward(&mut tape, &mut grads, false);
    let loss_at = |params: &[f32]| {
        let mut m = mlp.clone();
        m.params_mut().copy_from_slice(params);
        let mut t = Tape::for_training(&m, n);
        f64::from(logistic_loss_and_grad(
            &m, &inputs, &labels, weights, &batch, &mut t,
        ))
    };
    let params = mlp.params().to_vec();
    let h = 1e-2f32;
    for (k, &g) in grads.iter().enumerate() {
        let (mut up, mut down) = (params.clone(), params.clone());
        up[k] += h;
        down[k] -= h;
        let numeric = (loss_at(&up) - loss_at(&down)) / (2.0 * f64::from(h));
        let err = (numeric - f64::from(g)).abs();
        assert!(
            err < 2e-3 + 2e-2 * numeric.abs(),
            "parameter {k}: analytic {g}, numeric {numeric}"
        );
    }
    // Both classes weigh the same in all: 3 negatives × 2/3 = 1 end × 2.
    assert_eq!(class_weights(1, 4), (4.0 / 6.0, 2.0));
}
