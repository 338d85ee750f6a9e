//! The 1-D Gaussian mixture of the paper's Figure 3 experiment, with its exact density and score.
//!
//! A problem whose answer is known in closed form: DEEN trained on samples corrupted by
//! `N(0, σ²)` should learn the score of the mixture *smoothed* by that noise, which is again a
//! mixture with every component's variance increased by `σ²`. The energy tests check DEEN and
//! the DAE against it and the experiments crate draws the figure from it, so it lives here once.

use rand::RngExt;
use rand::rngs::StdRng;
use rand_distr::StandardNormal;

/// Weight, mean and standard deviation of each component.
pub const MIXTURE: [(f64, f64, f64); 3] = [(0.3, -3.0, 0.4), (0.4, 0.0, 0.6), (0.3, 3.0, 0.5)];

/// The corruption noise of the paper's toy experiment, in raw units.
pub const SIGMA: f64 = 0.5;

/// `n` samples of the mixture.
pub fn samples(n: usize, rng: &mut StdRng) -> Vec<f32> {
    (0..n)
        .map(|_| {
            let mut u: f64 = rng.random();
            let &(_, m, s) = MIXTURE
                .iter()
                .find(|c| {
                    u -= c.0;
                    u < 0.0
                })
                .unwrap_or(&MIXTURE[2]);
            (m + s * rng.sample::<f64, _>(StandardNormal)) as f32
        })
        .collect()
}

/// Density and score `∇ log p` at `y` of the mixture with every component's variance
/// increased by `extra_variance` (`0`: the mixture itself; `σ²`: it convolved with `N(0, σ²)`).
pub fn density_and_score(y: f64, extra_variance: f64) -> (f64, f64) {
    let (mut p, mut num) = (0.0, 0.0);
    for (w, m, s) in MIXTURE {
        let v = s * s + extra_variance;
        let density =
            w * (-(y - m).powi(2) / (2.0 * v)).exp() / (2.0 * std::f64::consts::PI * v).sqrt();
        p += density;
        num += density * (m - y) / v;
    }
    (p, num / p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn the_score_is_the_derivative_of_the_log_density() {
        for extra in [0.0, SIGMA * SIGMA] {
            for y in [-4.0, -1.3, 0.2, 2.9] {
                let h = 1e-5;
                let log_p = |y| density_and_score(y, extra).0.ln();
                let fd = (log_p(y + h) - log_p(y - h)) / (2.0 * h);
                let (_, score) = density_and_score(y, extra);
                assert!(
                    (fd - score).abs() < 1e-6 * (1.0 + score.abs()),
                    "{y}: {fd} vs {score}"
                );
            }
        }
    }

    #[test]
    fn samples_follow_the_mixture_weights() {
        let x = samples(20_000, &mut StdRng::seed_from_u64(1));
        let share = |lo: f32, hi: f32| x.iter().filter(|&&v| lo < v && v < hi).count() as f64 / 2e4;
        // Each component lies within ±1.5 of its mean with probability ≥ 0.99.
        for (w, m, _) in MIXTURE {
            let got = share(m as f32 - 1.5, m as f32 + 1.5);
            assert!((got - w).abs() < 0.02, "component at {m}: {got} vs {w}");
        }
    }
}
