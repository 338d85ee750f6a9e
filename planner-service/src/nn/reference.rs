//! Test-only `f64` reference implementations: a direct network evaluation, its input gradient
//! by explicit backpropagation, and central finite differences. The fast `f32` passes are
//! checked against these.

use super::activation::Activation;

fn act(a: Activation, z: f64) -> (f64, f64) {
    let s = 1.0 / (1.0 + (-z).exp());
    match a {
        Activation::Softplus => (z.max(0.0) + (-z.abs()).exp().ln_1p(), s),
        Activation::Swish => (z * s, s * (1.0 + z * (1.0 - s))),
    }
}

/// `act(z)` for a hidden layer, or `z` itself for a linear one (`None`).
pub fn activate(a: Option<Activation>, z: f64) -> f64 {
    a.map_or(z, |a| act(a, z).0)
}

/// Per-layer pre-activations `z` and activations `h` (`h[0] = x`) of one sample.
fn layers(
    sizes: &[usize],
    a: Activation,
    params: &[f64],
    x: &[f64],
) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let (mut zs, mut hs) = (vec![], vec![x.to_vec()]);
    let mut off = 0;
    for l in 0..sizes.len() - 1 {
        let (n_in, n_out) = (sizes[l], sizes[l + 1]);
        let (w, b) = (
            &params[off..off + n_in * n_out],
            &params[off + n_in * n_out..off + n_in * n_out + n_out],
        );
        off += n_in * n_out + n_out;
        let h = &hs[l];
        let z: Vec<f64> = (0..n_out)
            .map(|j| b[j] + (0..n_in).map(|i| h[i] * w[i * n_out + j]).sum::<f64>())
            .collect();
        let last = l + 2 == sizes.len();
        hs.push(if last {
            z.clone()
        } else {
            z.iter().map(|&v| act(a, v).0).collect()
        });
        zs.push(z);
    }
    (zs, hs)
}

/// The network's output for one sample.
pub fn forward(sizes: &[usize], a: Activation, params: &[f64], x: &[f64]) -> Vec<f64> {
    layers(sizes, a, params, x)
        .1
        .pop()
        .expect("at least one layer")
}

/// `∂out/∂x` of a scalar-output network at one sample, by backpropagation.
pub fn input_gradient(sizes: &[usize], a: Activation, params: &[f64], x: &[f64]) -> Vec<f64> {
    assert_eq!(sizes[sizes.len() - 1], 1);
    let (zs, _) = layers(sizes, a, params, x);
    let offsets: Vec<usize> = sizes
        .windows(2)
        .scan(0, |o, w| {
            let here = *o;
            *o += w[0] * w[1] + w[1];
            Some(here)
        })
        .collect();
    let mut g = vec![1.0];
    for l in (0..sizes.len() - 1).rev() {
        let (n_in, n_out) = (sizes[l], sizes[l + 1]);
        let w = &params[offsets[l]..offsets[l] + n_in * n_out];
        let mut below: Vec<f64> = (0..n_in)
            .map(|i| (0..n_out).map(|j| w[i * n_out + j] * g[j]).sum())
            .collect();
        if l > 0 {
            for (v, z) in below.iter_mut().zip(&zs[l - 1]) {
                *v *= act(a, *z).1;
            }
        }
        g = below;
    }
    g
}

/// Central differences of `f` at `p`, one coordinate at a time.
pub fn finite_difference(p: &[f64], f: impl Fn(&[f64]) -> f64) -> Vec<f64> {
    let mut q = p.to_vec();
    (0..p.len())
        .map(|i| {
            let h = 1e-5 * p[i].abs().max(1.0);
            q[i] = p[i] + h;
            let up = f(&q);
            q[i] = p[i] - h;
            let down = f(&q);
            q[i] = p[i];
            (up - down) / (2.0 * h)
        })
        .collect()
}

/// Asserts that a gradient computed on `path` matches the reference `want`: componentwise
/// within `f32_tolerance` ([`assert_close`]) for the f32 products; for the bf16 tiles, whose
/// factors are rounded to 8 significant bits (relative error up to 2⁻⁹ each, so a component
/// that is the difference of larger terms may lose most of its digits), in norm: the error
/// vector's length at most [`BF16_NORM_TOLERANCE`] of the reference's.
pub fn assert_gradient(
    path: super::TrainPath,
    got: &[f32],
    want: &[f64],
    f32_tolerance: f64,
    what: &str,
) {
    match path {
        super::TrainPath::F32 => assert_close(got, want, f32_tolerance, what),
        super::TrainPath::AmxBf16 => assert_close_in_norm(got, want, BF16_NORM_TOLERANCE, what),
    }
}

/// See [`assert_gradient`].
pub const BF16_NORM_TOLERANCE: f64 = 2e-2;

/// Asserts `‖got − want‖ ≤ tol · ‖want‖`.
pub fn assert_close_in_norm(got: &[f32], want: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let norm = want.iter().map(|w| w * w).sum::<f64>().sqrt();
    assert!(norm > 0.0, "{what}: reference gradient is identically zero");
    let err = got
        .iter()
        .zip(want)
        .map(|(&g, &w)| (g as f64 - w).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        err <= tol * norm,
        "{what}: error norm {err:e} against reference norm {norm:e} (relative {:e})",
        err / norm
    );
}

/// Asserts `got ≈ want` componentwise, relative to each component's size with a floor at 1 %
/// of the largest component (`f32` rounding makes tiny components noisy).
pub fn assert_close(got: &[f32], want: &[f64], tol: f64, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(
        scale > 0.0,
        "{what}: reference gradient is identically zero"
    );
    let mut worst = (0.0, 0);
    for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
        let err = (g as f64 - w).abs() / (w.abs() + 0.01 * scale);
        if err > worst.0 || err.is_nan() {
            worst = (err, i);
        }
    }
    let (err, i) = worst;
    assert!(
        err < tol,
        "{what}: component {i}: {} vs {} (relative error {err:e})",
        got[i],
        want[i]
    );
}

#[test]
fn reference_input_gradient_matches_finite_differences() {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    for a in [Activation::Swish, Activation::Softplus] {
        let sizes = [3, 6, 5, 1];
        let n: usize = sizes.windows(2).map(|w| w[0] * w[1] + w[1]).sum();
        let params: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let x = [0.3, -1.2, 0.7];
        let fd = finite_difference(&x, |x| forward(&sizes, a, &params, x)[0]);
        let g: Vec<f32> = input_gradient(&sizes, a, &params, &x)
            .iter()
            .map(|&v| v as f32)
            .collect();
        assert_close(&g, &fd, 1e-6, "reference input gradient");
    }
}

/// Checks a batch gradient against its samples: `grads_of(cols)` runs the pass on the samples
/// `cols` of a reused tape and returns the parameters' gradient. After a pass over `0..all` (as
/// a trainer reuses its tape), the gradient of the partial batch `0..batch` must be the sum of
/// its samples' gradients within 1e-6 of the terms' magnitude, and the first layer's bias
/// gradient must equal the gradient of the weights of input 0, which the caller sets to 1 in
/// every sample. Returns the batch's gradient for the caller's own checks.
pub fn assert_batch_gradient_sums_its_samples(
    mlp: &super::mlp::Mlp,
    (all, batch): (usize, usize),
    what: &str,
    mut grads_of: impl FnMut(std::ops::Range<usize>) -> Vec<f32>,
) -> Vec<f32> {
    grads_of(0..all);
    let batch_grads = grads_of(0..batch);
    let n = batch_grads.len();
    let (mut sum, mut magnitude) = (vec![0.0f64; n], vec![0.0f64; n]);
    for i in 0..batch {
        for (j, g) in grads_of(i..i + 1).into_iter().enumerate() {
            sum[j] += g as f64;
            magnitude[j] += (g as f64).abs();
        }
    }
    for j in 0..n {
        let err = (batch_grads[j] as f64 - sum[j]).abs();
        assert!(
            err <= 1e-6 * magnitude[j],
            "{what} parameter {j}: batch {} against the samples' sum {}",
            batch_grads[j],
            sum[j]
        );
    }
    let constant_input_row = &batch_grads[mlp.weight_range(0)][..mlp.sizes()[1]];
    let first_bias = &batch_grads[mlp.bias_range(0)];
    assert!(
        first_bias.iter().any(|&b| b != 0.0),
        "{what}: no bias gradient"
    );
    let scale = first_bias.iter().fold(0.0f32, |m, b| m.max(b.abs()));
    for (w, b) in constant_input_row.iter().zip(first_bias) {
        assert!((w - b).abs() <= 1e-6 * scale, "{what}: {w} ≠ {b}");
    }
    batch_grads
}
