//! Tests of the energy models: loss gradients against finite differences, the scores they
//! learn on a 1-D Gaussian mixture against the analytic answer (the paper's Figure 3
//! experiment), and the regulariser on transitions.

use super::mixture::{SIGMA, density_and_score, samples as mixture_samples};
use super::*;
use crate::nn::{Activation, TrainPath, reference};
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;

/// `∇ log p_σ(y)` of the mixture convolved with `N(0, σ²)`.
fn analytic_score(y: f64) -> f64 {
    density_and_score(y, SIGMA * SIGMA).1
}

/// Pearson correlation.
fn correlation(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
    let (va, vb): (f64, f64) = (
        a.iter().map(|x| (x - ma).powi(2)).sum(),
        b.iter().map(|y| (y - mb).powi(2)).sum(),
    );
    cov / (va * vb).sqrt()
}

/// Least-squares slope of `b` on `a` through the origin.
fn slope(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>() / a.iter().map(|x| x * x).sum::<f64>()
}

/// 1,000 mixture samples, the normaliser's standard deviation of them, and a grid over their
/// range.
fn mixture_problem(seed: u64) -> (Vec<f32>, f64, Vec<f32>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let data = mixture_samples(1000, &mut rng);
    let sd = Normalizer::fit(&data, 1).std()[0] as f64;
    let (lo, hi) = data
        .iter()
        .fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    let grid = (0..=200)
        .map(|i| lo + (hi - lo) * i as f32 / 200.0)
        .collect();
    (data, sd, grid)
}

fn toy_config(sd: f64) -> EnergyConfig {
    // σ is configured in standardised units: σ = 0.5 raw.
    EnergyConfig {
        hidden_layers: 2,
        hidden_size: 64,
        epochs: 1000,
        batch_size: 32,
        noise_sigma: (SIGMA / sd) as f32,
        noise_units: Default::default(),
        learning_rate: 1e-3,
    }
}

/// On every training path this CPU has: the bf16 tiles learn the same score.
#[test]
fn deen_learns_the_score_of_a_smoothed_gaussian_mixture() {
    for path in TrainPath::available() {
        deen_learns_the_score_on(path);
    }
}

fn deen_learns_the_score_on(path: TrainPath) {
    let (data, sd, grid) = mixture_problem(31);
    let mut rng = StdRng::seed_from_u64(32);
    let config = toy_config(sd);
    let mut deen = Deen::new(1, &config, &mut rng);
    deen.pin_train_path(Some(path));
    let report = deen.fit(&data, config.epochs, &mut rng);
    assert_eq!(
        (report.samples, report.steps),
        (1000, config.epochs * 1000usize.div_ceil(config.batch_size))
    );
    let model: Vec<f64> = deen.score_rows(&grid).iter().map(|&v| v as f64).collect();
    let truth: Vec<f64> = grid.iter().map(|&y| analytic_score(y as f64)).collect();
    let r = correlation(&model, &truth);
    let k = slope(&truth, &model);
    println!("DEEN on {path}: correlation {r:.4}, slope {k:.4}");
    assert!(
        r >= 0.95,
        "{path}: correlation of DEEN's score with the analytic score: {r}"
    );
    // Not only the shape: the magnitude is right too.
    assert!((0.8..1.25).contains(&k), "{path}: slope {k}");
    // The energy is low where the data is dense: the modes beat the gaps between them.
    let e = deen.energy_rows(&[-3.0, -1.5, 0.0, 1.5, 3.0, 6.0]);
    assert!(
        e[0] < e[1] && e[2] < e[1] && e[2] < e[3] && e[4] < e[3] && e[4] < e[5],
        "{e:?}"
    );
}

#[test]
fn dae_displacement_estimates_the_scaled_score() {
    let (data, sd, grid) = mixture_problem(33);
    let mut rng = StdRng::seed_from_u64(34);
    let config = toy_config(sd);
    let mut dae = Dae::new(1, &config, &mut rng);
    dae.fit(&data, config.epochs, &mut rng);
    // g(y) − y ≈ σ² ∇ log p_σ(y) in standardised units, i.e. σ_std² · sd · score_raw.
    let model: Vec<f64> = dae
        .displacement_rows(&grid)
        .iter()
        .map(|&v| v as f64)
        .collect();
    let sigma_std = config.noise_sigma as f64;
    let truth: Vec<f64> = grid
        .iter()
        .map(|&y| sigma_std * sigma_std * sd * analytic_score(y as f64))
        .collect();
    let r = correlation(&model, &truth);
    let k = slope(&truth, &model);
    assert!(
        r >= 0.9,
        "correlation of the DAE's displacement with σ²·score: {r}"
    );
    assert!((0.6..1.5).contains(&k), "slope {k}");
}

/// A small network, data and noise for the loss-gradient checks.
fn gradient_problem(rng: &mut StdRng) -> (EnergyConfig, Vec<f32>, Vec<usize>) {
    let config = EnergyConfig {
        hidden_layers: 2,
        hidden_size: 7,
        epochs: 1,
        batch_size: 8,
        noise_sigma: 0.4,
        noise_units: Default::default(),
        learning_rate: 1e-3,
    };
    let set: Vec<f32> = (0..10 * 3).map(|_| rng.random_range(-2.0..2.0)).collect();
    (config, set, vec![7, 2, 9, 4, 0])
}

fn fill_noise(noise: &mut [f32], ld: usize, d: usize, b: usize, rng: &mut StdRng) -> Vec<f32> {
    let mut eps = vec![0.0; b * d];
    for f in 0..d {
        for i in 0..b {
            let e: f32 = rng.sample(StandardNormal);
            noise[f * ld + i] = e;
            eps[i * d + f] = e;
        }
    }
    eps
}

/// The loss of one clean vector `x` and its corruption `y` with noise scale `σ`, in f64, for
/// parameters `p` of a network of `sizes`.
type SampleLoss = dyn Fn(&[usize], &[f64], &[f64], &[f64], f64) -> f64;

/// Checks a regulariser's minibatch loss against `per_sample` and its parameter gradient
/// against finite differences of it.
/// On every training path this CPU has; the bf16 tiles within the bounds of
/// [`reference::assert_gradient`].
fn check_loss_gradient<L: DenoisingLoss>(seed: u64, tolerance: f64, per_sample: &SampleLoss) {
    for path in TrainPath::available() {
        check_loss_gradient_on::<L>(seed, path, tolerance, per_sample);
    }
}

fn check_loss_gradient_on<L: DenoisingLoss>(
    seed: u64,
    path: TrainPath,
    tolerance: f64,
    per_sample: &SampleLoss,
) {
    let mut rng = StdRng::seed_from_u64(seed);
    let (config, set, batch) = gradient_problem(&mut rng);
    let model = Denoiser::<L>::new(3, &config, &mut rng);
    let mut ws = denoiser::Workspace::with_path(&model, 8, path);
    let ld = crate::nn::aligned::round_up(8);
    let eps = fill_noise(ws.noise_mut(), ld, 3, batch.len(), &mut rng);
    let loss = model.loss_and_grad(&set, &batch, &mut ws);
    let sizes = model.mlp().sizes().to_vec();
    let sigma = config.noise_sigma as f64;
    let reference_loss = |p: &[f64]| -> f64 {
        let mut total = 0.0;
        for (c, &idx) in batch.iter().enumerate() {
            let x: Vec<f64> = set[idx * 3..idx * 3 + 3]
                .iter()
                .map(|&v| v as f64)
                .collect();
            let y: Vec<f64> = (0..3)
                .map(|f| x[f] + sigma * eps[c * 3 + f] as f64)
                .collect();
            total += per_sample(&sizes, p, &x, &y, sigma);
        }
        total / batch.len() as f64
    };
    let p: Vec<f64> = model.mlp().params().iter().map(|&v| v as f64).collect();
    let loss_tolerance = match path {
        TrainPath::F32 => 1e-5,
        TrainPath::AmxBf16 => reference::BF16_NORM_TOLERANCE,
    };
    assert!(
        (loss as f64 - reference_loss(&p)).abs() < loss_tolerance * reference_loss(&p).max(1.0),
        "{path}: loss {loss} vs {}",
        reference_loss(&p)
    );
    let fd = reference::finite_difference(&p, reference_loss);
    let what = format!("{} loss gradient on {path}", L::NAME);
    reference::assert_gradient(path, ws.grads(), &fd, tolerance, &what);
}

#[test]
fn deen_loss_gradient_matches_finite_differences() {
    // ‖x − y + σ² ∂E/∂y‖² with the input gradient of the reference network.
    check_loss_gradient::<deen::DeenLoss>(35, 1e-3, &|sizes, p, x, y, sigma| {
        let s = reference::input_gradient(sizes, Activation::Softplus, p, y);
        (0..3)
            .map(|f| (x[f] - y[f] + sigma * sigma * s[f]).powi(2))
            .sum()
    });
}

#[test]
fn dae_loss_gradient_matches_finite_differences() {
    // ‖g(y) − x‖² with the reference network's output.
    check_loss_gradient::<dae::DaeLoss>(36, 1e-4, &|sizes, p, x, y, _| {
        let g = reference::forward(sizes, Activation::Softplus, p, y);
        (0..3).map(|f| (g[f] - x[f]).powi(2)).sum()
    });
}

/// Transitions of a damped oscillator `s = (q, p)`, `a` a force: a thin manifold in
/// `[s, a, s']` space.
fn oscillator(n: usize, rng: &mut StdRng) -> Transitions {
    let mut data = Transitions::new(2, 1);
    for _ in 0..n {
        let s = [
            rng.random_range(-1.0f32..1.0),
            rng.random_range(-1.0f32..1.0),
        ];
        let a = rng.random_range(-1.0f32..1.0);
        let next = [s[0] + 0.1 * s[1], s[1] + 0.1 * (-s[0] - 0.2 * s[1] + a)];
        data.push(&s, &[a], 0.0, &next);
    }
    data
}

#[test]
fn regularizers_score_real_transitions_as_more_familiar_than_impossible_ones() {
    let mut rng = StdRng::seed_from_u64(37);
    let data = oscillator(2000, &mut rng);
    let config = EnergyConfig {
        hidden_layers: 2,
        hidden_size: 64,
        epochs: 30,
        batch_size: 32,
        noise_sigma: 0.2,
        noise_units: Default::default(),
        learning_rate: 1e-3,
    };
    let test = oscillator(300, &mut rng);
    // The same states and actions, but next states that the dynamics cannot produce.
    let shifted: Vec<f32> = test
        .next_obs()
        .iter()
        .enumerate()
        .map(|(i, v)| v + if i % 2 == 0 { 0.3 } else { -0.3 })
        .collect();
    for kind in [RegularizerKind::Deen, RegularizerKind::Dae] {
        let mut reg = Regularizer::new(kind, &config, 2, 1, &mut rng);
        assert_eq!(reg.kind(), kind);
        let report = reg.fit(&data, config.epochs, &mut rng);
        assert!(report.loss.is_finite() && report.steps > 0, "{report:?}");
        let mut scratch = reg.scratch(300);
        assert!(scratch.fits(&reg, 300) && !scratch.fits(&reg, 301));
        let (mut real, mut fake) = (vec![0.0; 300], vec![0.0; 300]);
        reg.energy(
            test.obs(),
            test.act(),
            test.next_obs(),
            300,
            &mut scratch,
            &mut real,
        );
        reg.energy(
            test.obs(),
            test.act(),
            &shifted,
            300,
            &mut scratch,
            &mut fake,
        );
        let lower = real.iter().zip(&fake).filter(|(r, f)| r < f).count();
        assert!(
            lower >= 285,
            "{kind}: only {lower}/300 real transitions have lower energy than their impossible twins"
        );
        // The batched, allocation-free path agrees with the model's own evaluation.
        if let Regularizer::Deen(deen) = &reg {
            let direct = deen.energy_rows(&transition_rows(&test));
            for (a, b) in real.iter().zip(&direct) {
                assert!((a - b).abs() <= 1e-5 * a.abs().max(1.0), "{a} vs {b}");
            }
        }
    }
}

#[test]
fn parts_restore_identical_energies() {
    let mut rng = StdRng::seed_from_u64(40);
    let data = oscillator(200, &mut rng);
    let config = EnergyConfig {
        hidden_layers: 2,
        hidden_size: 16,
        epochs: 2,
        batch_size: 32,
        noise_sigma: 0.2,
        noise_units: Default::default(),
        learning_rate: 1e-3,
    };
    for kind in RegularizerKind::ALL.iter().copied() {
        let mut reg = Regularizer::new(kind, &config, 2, 1, &mut rng);
        reg.fit(&data, 2, &mut rng);
        let json = serde_json::to_string(&reg.parts()).unwrap();
        let restored =
            Regularizer::from_parts(kind, &config, 2, 1, serde_json::from_str(&json).unwrap())
                .unwrap();
        let (mut a, mut b) = (vec![0.0; 200], vec![1.0; 200]);
        reg.energy(
            data.obs(),
            data.act(),
            data.next_obs(),
            200,
            &mut reg.scratch(200),
            &mut a,
        );
        restored.energy(
            data.obs(),
            data.act(),
            data.next_obs(),
            200,
            &mut restored.scratch(200),
            &mut b,
        );
        assert_eq!(a, b, "{kind}");
    }
    let deen = Regularizer::new(RegularizerKind::Deen, &config, 2, 1, &mut rng);
    assert!(
        Regularizer::from_parts(RegularizerKind::Dae, &config, 2, 1, deen.parts()).is_err(),
        "a DAE has another shape"
    );
    assert!(Regularizer::from_parts(RegularizerKind::None, &config, 2, 1, deen.parts()).is_err());
    assert!(Regularizer::from_parts(RegularizerKind::Deen, &config, 3, 1, deen.parts()).is_err());
}

#[test]
fn fitting_nothing_changes_nothing() {
    let mut rng = StdRng::seed_from_u64(41);
    let config = EnergyConfig {
        hidden_layers: 1,
        hidden_size: 8,
        epochs: 1,
        batch_size: 16,
        noise_sigma: 0.2,
        noise_units: Default::default(),
        learning_rate: 1e-3,
    };
    for kind in [RegularizerKind::Dae, RegularizerKind::Deen] {
        let mut reg = Regularizer::new(kind, &config, 2, 1, &mut rng);
        reg.fit(&oscillator(50, &mut rng), 1, &mut rng);
        let before = reg.parts();
        let report = reg.fit(&Transitions::new(2, 1), 3, &mut rng);
        assert_eq!((report.samples, report.steps), (0, 0));
        reg.fit(&oscillator(50, &mut rng), 0, &mut rng);
        assert_eq!(
            reg.parts(),
            before,
            "{kind}: weights and statistics unchanged"
        );
    }
}

#[test]
fn the_none_regularizer_is_free() {
    let mut rng = StdRng::seed_from_u64(38);
    let mut reg = Regularizer::new(
        RegularizerKind::None,
        &EnergyConfig::default(),
        2,
        1,
        &mut rng,
    );
    let data = oscillator(10, &mut rng);
    assert_eq!(reg.fit(&data, 5, &mut rng).samples, 10);
    let mut scratch = reg.scratch(10);
    let mut out = vec![f32::NAN; 10];
    reg.energy(
        data.obs(),
        data.act(),
        data.next_obs(),
        10,
        &mut scratch,
        &mut out,
    );
    assert!(out.iter().all(|v| *v == 0.0));
}

#[test]
fn kinds_parse_and_serialise_lowercase() {
    for &kind in RegularizerKind::ALL {
        assert_eq!(kind.name().parse::<RegularizerKind>().unwrap(), kind);
        assert_eq!(serde_json::to_string(&kind).unwrap(), format!("\"{kind}\""));
    }
    assert_eq!(
        "DEEN".parse::<RegularizerKind>().unwrap(),
        RegularizerKind::Deen
    );
    let err = "vae".parse::<RegularizerKind>().unwrap_err();
    assert!(err.to_string().contains("none, dae, deen"), "{err}");
    fn assert_traits<T: Clone + Send + Sync + 'static>() {}
    assert_traits::<Regularizer>();
    assert_traits::<EnergyScratch>();
}

/// The gradient planning follows, against central differences: DEEN's exact input gradient,
/// and the DAE penalty's with the autoencoder's output held at its value (the stopped
/// gradient); the energies are those [`Regularizer::energy`] reports.
#[test]
fn planning_gradients_match_finite_differences() {
    let (o, a, rows) = (3, 2, 4);
    let mut rng = StdRng::seed_from_u64(41);
    let data_rows: Vec<f32> = (0..60 * (2 * o + a))
        .map(|_| rng.random_range(-2.0..2.0))
        .collect();
    let mut data = Transitions::new(o, a);
    for r in data_rows.chunks_exact(2 * o + a) {
        data.push(&r[..o], &r[o..o + a], 0.0, &r[o + a..]);
    }
    let config = EnergyConfig {
        hidden_layers: 2,
        hidden_size: 16,
        noise_sigma: 0.3,
        noise_units: Default::default(),
        ..Default::default()
    };
    let random = |n: usize, rng: &mut StdRng| -> Vec<f32> {
        (0..n).map(|_| rng.random_range(-1.5..1.5)).collect()
    };
    let (obs, act, next) = (
        random(rows * o, &mut rng),
        random(rows * a, &mut rng),
        random(rows * o, &mut rng),
    );
    for kind in [RegularizerKind::Dae, RegularizerKind::Deen] {
        let mut model = Regularizer::new(kind, &config, o, a, &mut rng);
        model.fit(&data, 2, &mut rng);
        let mut scratch = model.grad_scratch(rows);
        let mut energy = vec![0.0; rows];
        let (mut d_obs, mut d_act, mut d_next) = (
            vec![0.0; rows * o],
            vec![0.0; rows * a],
            vec![0.0; rows * o],
        );
        model.energy_and_gradient(
            &obs,
            &act,
            &next,
            rows,
            &mut scratch,
            &mut energy,
            &mut d_obs,
            &mut d_act,
            &mut d_next,
        );
        let mut plain = vec![0.0; rows];
        model.energy(
            &obs,
            &act,
            &next,
            rows,
            &mut model.scratch(rows),
            &mut plain,
        );
        for (e, p) in energy.iter().zip(&plain) {
            assert!(
                (e - p).abs() <= 1e-4 * (1.0 + p.abs()),
                "{kind}: {e} vs {p}"
            );
        }
        // The energy of row `i` as a function of its raw vector `[s, a, s']`.
        let rows_of = |i: usize| -> Vec<f32> {
            [
                &obs[i * o..(i + 1) * o],
                &act[i * a..(i + 1) * a],
                &next[i * o..(i + 1) * o],
            ]
            .concat()
        };
        for i in 0..rows {
            let x0 = rows_of(i);
            let energy_of = |x: &[f32]| -> f64 {
                match &model {
                    Regularizer::Deen(m) => m.energy_rows(x)[0] as f64,
                    Regularizer::Dae(m) => {
                        // ‖g(x̃₀) − x̃‖² with the output frozen at x₀.
                        let n = m.normalizer();
                        let g0: Vec<f32> = m
                            .displacement_rows(&x0)
                            .iter()
                            .enumerate()
                            .map(|(f, d)| d + n.normalize(f, x0[f]))
                            .collect();
                        x.iter()
                            .enumerate()
                            .map(|(f, &v)| ((g0[f] - n.normalize(f, v)) as f64).powi(2))
                            .sum()
                    }
                    Regularizer::None => unreachable!(),
                }
            };
            let got = [
                &d_obs[i * o..(i + 1) * o],
                &d_act[i * a..(i + 1) * a],
                &d_next[i * o..(i + 1) * o],
            ]
            .concat();
            let h = 1e-2f32;
            for f in 0..x0.len() {
                let (mut up, mut down) = (x0.clone(), x0.clone());
                up[f] += h;
                down[f] -= h;
                let fd = ((energy_of(&up) - energy_of(&down)) / (2.0 * h as f64)) as f32;
                assert!(
                    (got[f] - fd).abs() <= 2e-2 * (1.0 + fd.abs()),
                    "{kind} row {i} coordinate {f}: {} vs {fd}",
                    got[f]
                );
            }
        }
    }
    // Without a regulariser: zero energy and zero gradient.
    let none = Regularizer::None;
    let mut energy = vec![1.0; rows];
    let (mut d_obs, mut d_act, mut d_next) = (
        vec![1.0; rows * o],
        vec![1.0; rows * a],
        vec![1.0; rows * o],
    );
    none.energy_and_gradient(
        &obs,
        &act,
        &next,
        rows,
        &mut none.grad_scratch(rows),
        &mut energy,
        &mut d_obs,
        &mut d_act,
        &mut d_next,
    );
    assert!(
        energy
            .iter()
            .chain(&d_obs)
            .chain(&d_act)
            .chain(&d_next)
            .all(|&v| v == 0.0)
    );
}
