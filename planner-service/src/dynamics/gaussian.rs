//! The probabilistic output head of PETS: a Gaussian with a softly bounded log-variance.
//!
//! The network's raw log-variance output `ρ` is squashed between learnable per-dimension
//! bounds (Chua et al. 2018, appendix A.1):
//! `ℓ₁ = max − softplus(max − ρ)`, `lv = min + softplus(ℓ₁ − min)`,
//! so the variance can neither collapse on points the model has memorised nor explode far
//! from the data. The loss per target dimension and sample is PETS's
//! `(μ − t)² e^{−lv} + lv` (twice the Gaussian negative log-likelihood, without the constant),
//! averaged over batch and dimensions, plus `0.01 (Σ max − Σ min)`, which keeps the bounds tight.

use crate::nn::fastmath::{exp, softplus_sigmoid};
use crate::nn::simd::multiversion;
use crate::nn::vecops::sum;

/// Weight of the penalty `Σ max − Σ min` on the log-variance bounds (PETS's value).
pub const BOUND_PENALTY: f32 = 0.01;
/// Initial upper bound of the log-variance (PETS's value, in standardised target units).
pub const INITIAL_MAX_LOGVAR: f32 = 0.5;
/// Initial lower bound of the log-variance (PETS's value).
pub const INITIAL_MIN_LOGVAR: f32 = -10.0;

/// The bounded log-variance for raw output `raw` and bounds `(max, min)`, with its partial
/// derivatives with respect to `raw`, `max` and `min`.
#[inline(always)]
pub fn bounded_logvar(raw: f32, max: f32, min: f32) -> [f32; 4] {
    let (sp_a, sig_a, sig_neg_a) = softplus_sigmoid(max - raw);
    let upper = max - sp_a;
    let (sp_b, sig_b, sig_neg_b) = softplus_sigmoid(upper - min);
    [min + sp_b, sig_b * sig_a, sig_b * sig_neg_a, sig_neg_b]
}

/// One element of [`nll_row`]: `([∂ℓ/∂mean, ∂ℓ/∂raw], [ℓ, ∂ℓ/∂max, ∂ℓ/∂min, (mean − target)²])`.
#[inline(always)]
fn nll_element(mean: f32, raw: f32, target: f32, max: f32, min: f32) -> ([f32; 2], [f32; 4]) {
    let [lv, d_raw_lv, d_max_lv, d_min_lv] = bounded_logvar(raw, max, min);
    let inv_var = exp(-lv);
    let err = mean - target;
    let weighted = err * err * inv_var;
    let d_lv = 1.0 - weighted;
    (
        [2.0 * err * inv_var, d_lv * d_raw_lv],
        [weighted + lv, d_lv * d_max_lv, d_lv * d_min_lv, err * err],
    )
}

multiversion! {
    /// The elementwise part of [`nll_row`]: gradients into `grad`, and `ℓ`, `∂ℓ/∂max`,
    /// `∂ℓ/∂min` and `(mean − target)²` into the four quarters of `terms`. A pure map, so it
    /// vectorises; the sums are taken separately.
    fn nll_terms(mean: &[f32], raw: &[f32], target: &[f32], bounds: [f32; 3], grad: (&mut [f32], &mut [f32]), terms: &mut [f32]) {
        let [max, min, scale] = bounds;
        let n = mean.len();
        let (raw, target) = (&raw[..n], &target[..n]);
        let (d_mean, d_raw) = (&mut grad.0[..n], &mut grad.1[..n]);
        let (loss, rest) = terms[..4 * n].split_at_mut(n);
        let (d_max, rest) = rest.split_at_mut(n);
        let (d_min, sq) = rest.split_at_mut(n);
        for i in 0..n {
            let (g, s) = nll_element(mean[i], raw[i], target[i], max, min);
            d_mean[i] = scale * g[0];
            d_raw[i] = scale * g[1];
            loss[i] = s[0];
            d_max[i] = s[1];
            d_min[i] = s[2];
            sq[i] = s[3];
        }
    }
}

/// One target dimension of a batch (feature-major rows of `mean`, `raw` log-variance and
/// `target`): writes `scale · ∂ℓ/∂mean` and `scale · ∂ℓ/∂raw` into `grad` and returns
/// `[Σ ℓ, Σ ∂ℓ/∂max, Σ ∂ℓ/∂min, Σ (mean − target)²]` over the batch. `terms` is scratch of at
/// least four times the batch.
pub fn nll_row(
    mean: &[f32],
    raw: &[f32],
    target: &[f32],
    bounds: [f32; 3],
    grad: (&mut [f32], &mut [f32]),
    terms: &mut [f32],
) -> [f32; 4] {
    let n = mean.len();
    nll_terms(mean, raw, target, bounds, grad, terms);
    std::array::from_fn(|k| sum(&terms[k * n..(k + 1) * n]))
}

multiversion! {
    /// `mean ← mean + e^{lv/2} ε` per sample: a draw from the predicted Gaussian (PETS TS∞).
    pub fn sample_row(mean: &mut [f32], raw: &[f32], noise: &[f32], max: f32, min: f32) {
        let n = mean.len();
        let (raw, noise) = (&raw[..n], &noise[..n]);
        for i in 0..n {
            let lv = bounded_logvar(raw[i], max, min)[0];
            mean[i] += exp(0.5 * lv) * noise[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::reference;

    fn softplus64(x: f64) -> f64 {
        x.max(0.0) + (-x.abs()).exp().ln_1p()
    }

    /// The head's loss in f64: mean over elements of `(μ − t)² e^{−lv} + lv` plus the penalty.
    fn loss64(p: &[f64], target: &[f64]) -> f64 {
        let n = target.len();
        let (mean, raw, max, min) = (&p[..n], &p[n..2 * n], p[2 * n], p[2 * n + 1]);
        let mut total = 0.0;
        for i in 0..n {
            let upper = max - softplus64(max - raw[i]);
            let lv = min + softplus64(upper - min);
            total += (mean[i] - target[i]).powi(2) * (-lv).exp() + lv;
        }
        total / n as f64 + BOUND_PENALTY as f64 * (max - min)
    }

    #[test]
    fn nll_gradient_matches_finite_differences() {
        let n = 21;
        let mean: Vec<f32> = (0..n).map(|i| (i as f32 * 0.37).sin()).collect();
        // Raw log-variances from far below the lower bound to far above the upper one.
        let raw: Vec<f32> = (0..n).map(|i| -14.0 + i as f32 * 0.8).collect();
        let target: Vec<f32> = (0..n).map(|i| (i as f32 * 0.11).cos()).collect();
        let (max, min) = (0.3f32, -9.0f32);
        let scale = 1.0 / n as f32;
        let (mut d_mean, mut d_raw) = (vec![0.0; n], vec![0.0; n]);
        let mut terms = vec![0.0; 4 * n];
        let [total, d_max, d_min, sq] = nll_row(
            &mean,
            &raw,
            &target,
            [max, min, scale],
            (&mut d_mean, &mut d_raw),
            &mut terms,
        );
        let mut got = d_mean.clone();
        got.extend(&d_raw);
        got.push(scale * d_max + BOUND_PENALTY);
        got.push(scale * d_min - BOUND_PENALTY);

        let p: Vec<f64> = mean
            .iter()
            .chain(&raw)
            .map(|&v| v as f64)
            .chain([max as f64, min as f64])
            .collect();
        let t64: Vec<f64> = target.iter().map(|&v| v as f64).collect();
        let fd = reference::finite_difference(&p, |p| loss64(p, &t64));
        reference::assert_close(&got, &fd, 1e-4, "Gaussian NLL gradient");
        let want = loss64(&p, &t64) - BOUND_PENALTY as f64 * (max - min) as f64;
        assert!((total as f64 * scale as f64 - want).abs() < 1e-5 * want.abs().max(1.0));
        let want_sq: f64 = (0..n)
            .map(|i| (mean[i] as f64 - target[i] as f64).powi(2))
            .sum();
        assert!((sq as f64 - want_sq).abs() < 1e-5);
    }

    #[test]
    fn log_variance_stays_within_its_bounds() {
        // The bounds are soft: the upper one can be exceeded by ln(1 + e^{−(max − min)}).
        for raw in [-1e6f32, -50.0, -10.0, 0.0, 0.5, 50.0, 1e6] {
            let lv = bounded_logvar(raw, 0.5, -10.0)[0];
            assert!((-10.0..=0.5 + 3e-5).contains(&lv), "{raw} → {lv}");
        }
        // Well inside the bounds it is (nearly) the identity.
        assert!((bounded_logvar(-4.0, 0.5, -10.0)[0] + 4.0).abs() < 0.02);
    }
}
