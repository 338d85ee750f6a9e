//! Tests of the dynamics models: the loss gradient against finite differences, and learning a
//! known system — its mean, its noise level, and sampling from it.

use super::*;
use crate::data::Transitions;
use crate::nn::{Activation, Normalizer, TrainPath, reference};
use proto::{Builtin, Task};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;

fn cartpole() -> &'static Task {
    Builtin::Cartpole.task()
}

const DT: f32 = 0.05;

/// A pendulum on a cart with the cartpole task's observation `[x, θ, ẋ, θ̇]`: Euler steps of
/// `ẍ = a − 0.1 ẋ`, `θ̈ = −16 sin θ − 0.8 a cos θ − 0.05 θ̇`, plus Gaussian noise of standard
/// deviation `noise` on the angular velocity.
fn step(s: &[f32], a: f32, noise: f32, rng: &mut StdRng) -> [f32; 4] {
    let (x, th, xd, thd) = (s[0], s[1], s[2], s[3]);
    let xdd = a - 0.1 * xd;
    let thdd = -16.0 * th.sin() - 0.8 * a * th.cos() - 0.05 * thd;
    let eps: f32 = rng.sample(StandardNormal);
    [
        x + DT * xd,
        th + DT * thd,
        xd + DT * xdd,
        thd + DT * thdd + noise * eps,
    ]
}

fn random_state(rng: &mut StdRng) -> ([f32; 4], f32) {
    let s = [
        rng.random_range(-1.0..1.0),
        rng.random_range(-3.1..3.1),
        rng.random_range(-2.0..2.0),
        rng.random_range(-4.0..4.0),
    ];
    (s, rng.random_range(-3.0..3.0))
}

fn dataset(n: usize, noise: f32, rng: &mut StdRng) -> Transitions {
    let mut data = Transitions::new(4, 1);
    for _ in 0..n {
        let (s, a) = random_state(rng);
        data.push(&s, &[a], 0.0, &step(&s, a, noise, rng));
    }
    data
}

fn small_config(epochs: usize) -> DynamicsConfig {
    DynamicsConfig {
        hidden_layers: 2,
        hidden_size: 64,
        ensemble_size: 1,
        epochs,
        batch_size: 32,
        learning_rate: 2e-3,
        weight_decay: 1e-5,
    }
}

/// On every training path this CPU has; the bf16 tiles within the bounds of
/// [`reference::assert_gradient`].
#[test]
fn loss_gradient_matches_finite_differences() {
    for path in TrainPath::available() {
        loss_gradient_matches_finite_differences_on(path);
    }
}

fn loss_gradient_matches_finite_differences_on(path: TrainPath) {
    let mut rng = StdRng::seed_from_u64(21);
    let task = cartpole();
    let config = DynamicsConfig {
        hidden_layers: 1,
        hidden_size: 6,
        ..small_config(1)
    };
    let mut model = ProbabilisticModel::new(task, &config, &mut rng);
    let data = dataset(7, 0.3, &mut rng);
    let (inputs, targets) = TrainingSet::raw(task, &data);
    let (ni, no) = (
        Normalizer::fit(&inputs, 5 + 1),
        Normalizer::fit(&targets, 4),
    );
    model.set_normalizers(ni.clone(), no.clone());
    let set = TrainingSet::standardised(inputs.clone(), targets.clone(), &ni, &no);
    // Bounds near the data so both soft bounds are active somewhere.
    model
        .member_bounds_mut()
        .copy_from_slice(&[0.2, -0.1, 0.3, 0.0, -1.5, -2.0, -1.0, -3.0]);
    let batch = [0, 3, 4, 6, 1];
    let mut ws = TrainWorkspace::with_path(&model, 8, path);
    let loss = model.loss_and_grad(&set, &batch, &mut ws);
    let mut got = ws.grads_for_test().to_vec();
    got.extend(ws.bound_grads_for_test());

    let sizes = model.mlp().sizes().to_vec();
    let n_params = model.mlp().params().len();
    let reference_loss = |p: &[f64]| -> f64 {
        let (params, bounds) = p.split_at(n_params);
        let softplus = |x: f64| x.max(0.0) + (-x.abs()).exp().ln_1p();
        let mut total = 0.0;
        for &i in &batch {
            let x: Vec<f64> = (0..6)
                .map(|f| ni.normalize(f, inputs[i * 6 + f]) as f64)
                .collect();
            let out = reference::forward(&sizes, Activation::Swish, params, &x);
            for k in 0..4 {
                let t = no.normalize(k, targets[i * 4 + k]) as f64;
                let upper = bounds[k] - softplus(bounds[k] - out[4 + k]);
                let lv = bounds[4 + k] + softplus(upper - bounds[4 + k]);
                total += (out[k] - t).powi(2) * (-lv).exp() + lv;
            }
        }
        total / (batch.len() * 4) as f64
            + 0.01 * (bounds[..4].iter().sum::<f64>() - bounds[4..].iter().sum::<f64>())
    };
    let p: Vec<f64> = model
        .mlp()
        .params()
        .iter()
        .chain(model.max_logvar())
        .chain(model.min_logvar())
        .map(|&v| v as f64)
        .collect();
    let loss_tolerance = match path {
        TrainPath::F32 => 1e-4,
        TrainPath::AmxBf16 => reference::BF16_NORM_TOLERANCE,
    };
    assert!(
        (loss as f64 - reference_loss(&p)).abs() < loss_tolerance * reference_loss(&p).abs(),
        "{path}: loss {loss} vs {}",
        reference_loss(&p)
    );
    let fd = reference::finite_difference(&p, reference_loss);
    let what = format!("dynamics loss gradient on {path}");
    reference::assert_gradient(path, &got, &fd, 1e-3, &what);
}

/// Squared error of the mean prediction on fresh noise-free transitions, per observation
/// dimension, relative to the variance of that dimension's change.
fn held_out_error(ensemble: &Ensemble, member: usize, rng: &mut StdRng) -> [f32; 4] {
    let n = 400;
    let (mut obs, mut act, mut truth) = (vec![], vec![], vec![]);
    for _ in 0..n {
        let (s, a) = random_state(rng);
        obs.extend(s);
        act.push(a);
        truth.extend(step(&s, a, 0.0, rng));
    }
    let mut scratch = ensemble.scratch(n);
    let mut next = vec![0.0; n * 4];
    ensemble.predict_next(member, &obs, &act, n, &mut scratch, None, &mut next);
    let mut out = [0.0; 4];
    for (k, o) in out.iter_mut().enumerate() {
        let deltas: Vec<f32> = (0..n).map(|i| truth[i * 4 + k] - obs[i * 4 + k]).collect();
        let mean = deltas.iter().sum::<f32>() / n as f32;
        let var = deltas.iter().map(|d| (d - mean).powi(2)).sum::<f32>() / n as f32;
        let mse = (0..n)
            .map(|i| (next[i * 4 + k] - truth[i * 4 + k]).powi(2))
            .sum::<f32>()
            / n as f32;
        *o = mse / var;
    }
    out
}

/// On every training path this CPU has: the bf16 tiles learn the same system.
#[test]
fn learns_a_known_system_and_its_noise() {
    for path in TrainPath::available() {
        learns_a_known_system_and_its_noise_on(path);
    }
}

fn learns_a_known_system_and_its_noise_on(path: TrainPath) {
    // The whole-data NLL after a fit moves with the fit's last minibatches: over seeds 22–39
    // one seed in 18 (23 before the fused bias gradient of session 11, 22 after it) ends the
    // second fit above the first. This seed is clear of that on both.
    let mut rng = StdRng::seed_from_u64(27);
    let task = cartpole();
    let noise = 0.2;
    let data = dataset(3000, noise, &mut rng);
    let mut ensemble = Ensemble::new(task, &small_config(0), &mut rng);
    ensemble.member_mut(0).pin_train_path(Some(path));
    let before = held_out_error(&ensemble, 0, &mut rng);
    let first = ensemble.fit(&data, 10, &mut rng);
    // Training continues from the current weights: a second call improves on the first.
    let second = ensemble.fit(&data, 30, &mut rng);
    assert!(
        second.nll.unwrap() < first.nll.unwrap(),
        "{first:?} then {second:?}"
    );
    assert_eq!(
        (second.samples, second.epochs, second.steps),
        (3000, 30, 30 * 3000usize.div_ceil(32))
    );
    let after = held_out_error(&ensemble, 0, &mut rng);
    println!("dynamics on {path}: held-out relative error {after:?}, {second:?}");
    for k in 0..4 {
        assert!(before[k] > 0.3, "untrained error {before:?}");
        assert!(
            after[k] < 0.02,
            "dimension {k}: relative error {} (untrained {})",
            after[k],
            before[k]
        );
    }
    // The angular velocity carries noise of std 0.2: the predicted variance finds it.
    let model = ensemble.member(0);
    let (s, a) = ([0.3f32, 1.0, -0.5, 2.0], [1.5f32]);
    let mut scratch = model.scratch(1);
    let mut input = [0.0; 6];
    task.state_features(&s, &mut input[..5]);
    input[5] = a[0];
    let x: Vec<f32> = input
        .iter()
        .enumerate()
        .map(|(k, &v)| model.input_normalizer().normalize(k, v))
        .collect();
    let out = model.mlp().forward_rows(&x);
    let lv = gaussian::bounded_logvar(out[4 + 3], model.max_logvar()[3], model.min_logvar()[3])[0];
    let std = (0.5 * lv).exp() * model.target_normalizer().std()[3];
    assert!(
        (0.85 * noise..1.15 * noise).contains(&std),
        "predicted std {std}, true {noise}"
    );
    // Drawing with noise (TS∞) spreads the next angular velocity by that std around the mean.
    let draws = 4000;
    let obs: Vec<f32> = s.repeat(draws);
    let act: Vec<f32> = a.repeat(draws);
    let eps: Vec<f32> = (0..draws * 4).map(|_| rng.sample(StandardNormal)).collect();
    let mut scratch_many = model.scratch(draws);
    let (mut mean_next, mut sampled) = (vec![0.0; 4], vec![0.0; draws * 4]);
    model.predict_next(&s, &a, 1, &mut scratch, None, &mut mean_next);
    model.predict_next(
        &obs,
        &act,
        draws,
        &mut scratch_many,
        Some(&eps),
        &mut sampled,
    );
    let thd: Vec<f32> = sampled.iter().skip(3).step_by(4).copied().collect();
    let m = thd.iter().sum::<f32>() / draws as f32;
    let sd = (thd.iter().map(|v| (v - m).powi(2)).sum::<f32>() / draws as f32).sqrt();
    assert!(
        (m - mean_next[3]).abs() < 0.05 * std + 4.0 * std / (draws as f32).sqrt(),
        "sample mean {m} vs {}",
        mean_next[3]
    );
    assert!(
        (sd / std - 1.0).abs() < 0.08,
        "sample std {sd} vs predicted {std}"
    );
}

#[test]
fn ensemble_members_differ_and_all_learn() {
    let mut rng = StdRng::seed_from_u64(23);
    let data = dataset(1500, 0.05, &mut rng);
    let config = DynamicsConfig {
        ensemble_size: 3,
        ..small_config(25)
    };
    let mut ensemble = Ensemble::new(cartpole(), &config, &mut rng);
    let report = ensemble.fit(&data, config.epochs, &mut rng);
    assert_eq!(ensemble.members(), 3);
    assert!(
        report.mse.unwrap() < 0.05 && report.nll.unwrap() < 0.0,
        "{report:?}"
    );
    let mut predictions = vec![];
    for member in 0..3 {
        let err = held_out_error(&ensemble, member, &mut rng);
        assert!(err.iter().all(|e| *e < 0.1), "member {member}: {err:?}");
        let mut scratch = ensemble.scratch(1);
        let mut next = [0.0; 4];
        // Far outside the data (θ̇ = 30) the bootstrapped members disagree.
        ensemble.predict_next(
            member,
            &[0.0, 0.5, 0.0, 30.0],
            &[2.0],
            1,
            &mut scratch,
            None,
            &mut next,
        );
        predictions.push(next[3]);
    }
    assert!(
        predictions[0] != predictions[1] && predictions[1] != predictions[2],
        "{predictions:?}"
    );
}

#[test]
fn parts_restore_identical_predictions_and_reject_wrong_shapes() {
    let mut rng = StdRng::seed_from_u64(26);
    let data = dataset(300, 0.05, &mut rng);
    let config = DynamicsConfig {
        ensemble_size: 2,
        ..small_config(2)
    };
    let mut ensemble = Ensemble::new(cartpole(), &config, &mut rng);
    ensemble.fit(&data, 2, &mut rng);
    let parts = ensemble.parts();
    let json = serde_json::to_string(&parts).unwrap();
    let restored =
        Ensemble::from_parts(cartpole(), &config, serde_json::from_str(&json).unwrap()).unwrap();
    let (mut a, mut b) = ([0.0; 8], [0.0; 8]);
    let eps = [0.5, -1.0, 0.2, 1.5, -0.3, 0.0, 0.8, -2.0];
    for member in 0..2 {
        let mut scratch = ensemble.scratch(2);
        ensemble.predict_next(
            member,
            &data.obs()[..8],
            &data.act()[..2],
            2,
            &mut scratch,
            Some(&eps),
            &mut a,
        );
        restored.predict_next(
            member,
            &data.obs()[..8],
            &data.act()[..2],
            2,
            &mut scratch,
            Some(&eps),
            &mut b,
        );
        assert_eq!(a, b);
    }
    let mut short = parts.clone();
    short[1].max_logvar.pop();
    let err = Ensemble::from_parts(cartpole(), &config, short).unwrap_err();
    assert_eq!(
        (err.what, err.expected, err.got),
        ("maximum log-variances", 4, 3)
    );
    let err = Ensemble::from_parts(cartpole(), &config, parts[..1].to_vec()).unwrap_err();
    assert_eq!(err.what, "ensemble members");
}

#[test]
fn models_are_shareable_across_threads() {
    fn assert_traits<T: Clone + Send + Sync + 'static>() {}
    assert_traits::<Ensemble>();
    assert_traits::<DynamicsScratch>();
}

#[test]
fn empty_data_leaves_the_model_untouched() {
    let mut rng = StdRng::seed_from_u64(24);
    let mut ensemble = Ensemble::new(cartpole(), &small_config(3), &mut rng);
    ensemble.fit(&dataset(100, 0.1, &mut rng), 1, &mut rng);
    let before = ensemble.member(0).parts();
    let report = ensemble.fit(&Transitions::new(4, 1), 3, &mut rng);
    assert_eq!((report.samples, report.steps, report.mse), (0, 0, None));
    let report = ensemble.fit(&dataset(100, 0.1, &mut rng), 0, &mut rng);
    assert_eq!((report.samples, report.steps), (100, 0));
    assert_eq!(
        ensemble.member(0).parts(),
        before,
        "weights and statistics unchanged"
    );
}

/// The mean prediction's input gradient (through the task's features, both normalisers, the
/// network and `next_obs_from_target`) against central differences, on the two tasks whose
/// transforms are not plain identities and deltas, with non-trivial statistics.
#[test]
fn mean_prediction_gradient_matches_finite_differences() {
    for task in [Builtin::Cartpole, Builtin::HalfCheetah] {
        let spec = task.task();
        let (o, a, f) = (spec.obs_dim, spec.act_dim, spec.state_feature_dim);
        let mut rng = StdRng::seed_from_u64(31);
        let config = DynamicsConfig {
            hidden_layers: 2,
            hidden_size: 16,
            ..small_config(1)
        };
        let mut model = ProbabilisticModel::new(spec, &config, &mut rng);
        let rows_of = |n: usize, d: usize, rng: &mut StdRng| -> Vec<f32> {
            (0..n * d).map(|_| rng.random_range(-1.5..1.5)).collect()
        };
        model.set_normalizers(
            Normalizer::fit(&rows_of(50, f + a, &mut rng), f + a),
            Normalizer::fit(&rows_of(50, o, &mut rng), o),
        );
        let rows = 3;
        let obs = rows_of(rows, o, &mut rng);
        let act = rows_of(rows, a, &mut rng);
        let c = rows_of(rows, o, &mut rng);
        let mut tape = model.mean_tape(rows);
        let mut next = vec![0.0; rows * o];
        model.predict_mean_recorded(&obs, &act, rows, &mut tape, &mut next);
        // The recorded prediction is the planner's mean prediction.
        let mut scratch = model.scratch(rows);
        let mut inferred = vec![0.0; rows * o];
        model.predict_next(&obs, &act, rows, &mut scratch, None, &mut inferred);
        for (x, y) in next.iter().zip(&inferred) {
            assert!(
                (x - y).abs() <= 1e-4 * (1.0 + y.abs()),
                "{task}: {x} vs {y}"
            );
        }
        let (mut d_obs, mut d_act) = (vec![f32::NAN; rows * o], vec![f32::NAN; rows * a]);
        model.mean_backward(&obs, rows, &mut tape, &c, &mut d_obs, &mut d_act);

        let loss = |obs: &[f32], act: &[f32]| -> f64 {
            let mut tape = model.mean_tape(rows);
            let mut next = vec![0.0; rows * o];
            model.predict_mean_recorded(obs, act, rows, &mut tape, &mut next);
            next.iter().zip(&c).map(|(x, c)| (x * c) as f64).sum()
        };
        let h = 1e-2f32;
        let central = |x: &[f32], i: usize, eval: &dyn Fn(&[f32]) -> f64| -> f32 {
            let (mut up, mut down) = (x.to_vec(), x.to_vec());
            up[i] += h;
            down[i] -= h;
            ((eval(&up) - eval(&down)) / (2.0 * h as f64)) as f32
        };
        for (i, &g) in d_obs.iter().enumerate() {
            let fd = central(&obs, i, &|x| loss(x, &act));
            assert!(
                (g - fd).abs() <= 2e-2 * (1.0 + fd.abs()),
                "{task} ∂/∂s[{i}]: {g} vs {fd}"
            );
        }
        for (i, &g) in d_act.iter().enumerate() {
            let fd = central(&act, i, &|x| loss(&obs, x));
            assert!(
                (g - fd).abs() <= 2e-2 * (1.0 + fd.abs()),
                "{task} ∂/∂a[{i}]: {g} vs {fd}"
            );
        }
    }
}
