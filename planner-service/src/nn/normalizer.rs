//! Per-dimension standardisation of network inputs and targets.

use serde::{Deserialize, Serialize};

/// A dimension whose standard deviation in the data is below this is treated as constant.
pub const MIN_STD: f32 = 1e-6;

/// The largest scale a normaliser uses. Data spread wider than this (possible only with
/// values near f32's limits) is scaled by it instead, so the statistics stay finite: the
/// spread of two values near ±3.4e38 does not fit in an f32.
pub const MAX_STD: f32 = 1e30;

/// `x ↦ (x − mean) / std` per dimension, fitted from data.
///
/// A dimension that does not vary in the data (`std < MIN_STD`) gets `std = 1`: it is only
/// centred, as PETS does, so a later variation is not amplified by an enormous factor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Normalizer {
    mean: Vec<f32>,
    std: Vec<f32>,
}

impl Normalizer {
    /// The identity on `dim` dimensions (what an untrained model uses).
    pub fn identity(dim: usize) -> Self {
        Self {
            mean: vec![0.0; dim],
            std: vec![1.0; dim],
        }
    }

    /// Mean and standard deviation of each column of `rows` (sample-major, `dim` columns),
    /// accumulated in `f64`, the scale clamped to [`MAX_STD`]. Empty data gives the identity.
    /// Every statistic is finite for any finite data.
    pub fn fit(rows: &[f32], dim: usize) -> Self {
        assert!(
            dim > 0 && rows.len().is_multiple_of(dim),
            "{} floats are not rows of {dim}",
            rows.len()
        );
        let n = rows.len() / dim;
        if n == 0 {
            return Self::identity(dim);
        }
        let mut sum = vec![0.0f64; dim];
        for row in rows.chunks_exact(dim) {
            for (s, &v) in sum.iter_mut().zip(row) {
                *s += v as f64;
            }
        }
        let mean: Vec<f64> = sum.iter().map(|s| s / n as f64).collect();
        let mut var = vec![0.0f64; dim];
        for row in rows.chunks_exact(dim) {
            for ((s, &v), m) in var.iter_mut().zip(row).zip(&mean) {
                *s += (v as f64 - m).powi(2);
            }
        }
        let std = var
            .iter()
            .map(|v| {
                let s = (v / n as f64).sqrt().min(MAX_STD as f64) as f32;
                if s < MIN_STD { 1.0 } else { s }
            })
            .collect();
        Self {
            mean: mean.iter().map(|&m| m as f32).collect(),
            std,
        }
    }

    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    pub fn mean(&self) -> &[f32] {
        &self.mean
    }

    pub fn std(&self) -> &[f32] {
        &self.std
    }

    /// The same normaliser with every scale raised to at least `floor`: a dimension that
    /// varies less than `floor` in the data is then only centred and divided by `floor`.
    pub fn with_min_std(mut self, floor: f32) -> Self {
        for s in &mut self.std {
            *s = s.max(floor);
        }
        self
    }

    /// Dimension `d` of `x`, standardised.
    #[inline]
    pub fn normalize(&self, d: usize, x: f32) -> f32 {
        (x - self.mean[d]) / self.std[d]
    }

    /// Dimension `d` of a standardised value, mapped back.
    #[inline]
    pub fn denormalize(&self, d: usize, z: f32) -> f32 {
        z * self.std[d] + self.mean[d]
    }

    /// Standardises every row of `rows` (sample-major) in place.
    pub fn normalize_rows(&self, rows: &mut [f32]) {
        for row in rows.chunks_exact_mut(self.dim()) {
            for (d, v) in row.iter_mut().enumerate() {
                *v = self.normalize(d, *v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fitted_data_is_standardised_and_constant_columns_only_centred() {
        let rows = [1.0, 5.0, 2.0, 5.0, 3.0, 5.0, 6.0, 5.0];
        let norm = Normalizer::fit(&rows, 2);
        assert_eq!(norm.mean(), &[3.0, 5.0]);
        assert!((norm.std()[0] - 3.5f32.sqrt()).abs() < 1e-6);
        assert_eq!(norm.std()[1], 1.0);
        let mut z = rows;
        norm.normalize_rows(&mut z);
        let col: Vec<f32> = z.iter().step_by(2).copied().collect();
        let mean = col.iter().sum::<f32>() / 4.0;
        let var = col.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / 4.0;
        assert!(mean.abs() < 1e-6 && (var - 1.0).abs() < 1e-5);
        assert!(z.iter().skip(1).step_by(2).all(|v| *v == 0.0));
        assert_eq!(norm.denormalize(0, norm.normalize(0, 4.25)), 4.25);
        assert_eq!(Normalizer::fit(&[], 3), Normalizer::identity(3));
    }

    /// Extreme but finite data (values at f32's limits, whose spread overflows an f32) gives
    /// finite statistics; data within the largest magnitude a planner accepts (1e18)
    /// standardises to finite values.
    #[test]
    fn extreme_finite_data_gives_finite_statistics() {
        let rows = [
            f32::MAX,
            -3.4e38,
            f32::MIN,
            1.0,
            3.4e38,
            f32::MAX,
            -f32::MAX,
            0.0,
        ];
        let norm = Normalizer::fit(&rows, 2);
        assert!(norm.mean().iter().all(|m| m.is_finite()), "{norm:?}");
        assert!(
            norm.std().iter().all(|s| s.is_finite() && *s <= MAX_STD),
            "{norm:?}"
        );
        let mut rows = [1e18, -1e18, -1e18, 3.0, 1e18, 1e18, -1e18, 0.0];
        let norm = Normalizer::fit(&rows, 2);
        norm.normalize_rows(&mut rows);
        assert!(rows.iter().all(|v| v.is_finite()), "{rows:?}");
    }
}
