//! Vectorised elementwise operations and sums over slices (one dispatched call per buffer).
//!
//! Sums accumulate in 16 independent lanes: LLVM may not reorder a plain floating-point sum,
//! so a one-accumulator loop stays scalar, while independent lanes vectorise.

use super::simd::multiversion;

multiversion! {
    /// `x ← x ⊙ y`.
    pub fn mul_inplace(x: &mut [f32], y: &[f32]) {
        let y = &y[..x.len()];
        for (a, b) in x.iter_mut().zip(y) {
            *a *= *b;
        }
    }
}

multiversion! {
    /// `x ← a ⊙ b`.
    pub fn product2(x: &mut [f32], a: &[f32], b: &[f32]) {
        let n = x.len();
        let (a, b) = (&a[..n], &b[..n]);
        for i in 0..n {
            x[i] = a[i] * b[i];
        }
    }
}

multiversion! {
    /// `x ← a ⊙ b ⊙ c`.
    pub fn product3(x: &mut [f32], a: &[f32], b: &[f32], c: &[f32]) {
        let n = x.len();
        let (a, b, c) = (&a[..n], &b[..n], &c[..n]);
        for i in 0..n {
            x[i] = a[i] * b[i] * c[i];
        }
    }
}

multiversion! {
    /// `x ← x ⊙ a + b ⊙ c ⊙ d`.
    pub fn mul_add3(x: &mut [f32], a: &[f32], b: &[f32], c: &[f32], d: &[f32]) {
        let n = x.len();
        let (a, b, c, d) = (&a[..n], &b[..n], &c[..n], &d[..n]);
        for i in 0..n {
            x[i] = x[i] * a[i] + b[i] * c[i] * d[i];
        }
    }
}

multiversion! {
    /// `x ← x · scale + shift`.
    pub fn scale_shift(x: &mut [f32], scale: f32, shift: f32) {
        for v in x.iter_mut() {
            *v = *v * scale + shift;
        }
    }
}

multiversion! {
    /// `acc ← acc + (a − b)²`.
    pub fn add_squared_diff(acc: &mut [f32], a: &[f32], b: &[f32]) {
        let n = acc.len();
        let (a, b) = (&a[..n], &b[..n]);
        for i in 0..n {
            let d = a[i] - b[i];
            acc[i] += d * d;
        }
    }
}

multiversion! {
    /// `Σ x`, accumulated in 16 lanes.
    pub fn sum(x: &[f32]) -> f32 {
        let mut lanes = [0.0f32; 16];
        let mut chunks = x.chunks_exact(16);
        for chunk in &mut chunks {
            for (l, v) in lanes.iter_mut().zip(chunk) {
                *l += *v;
            }
        }
        let tail: f32 = chunks.remainder().iter().sum();
        lanes.iter().sum::<f32>() + tail
    }
}

#[cfg(test)]
mod tests {
    use super::super::simd::{SimdLevel, with_level};
    use super::*;

    #[test]
    fn operations_match_scalar_definitions_at_every_level() {
        let a: Vec<f32> = (0..37).map(|i| i as f32 * 0.5 - 3.0).collect();
        let b: Vec<f32> = (0..37).map(|i| 1.0 + i as f32 * 0.25).collect();
        for level in SimdLevel::available() {
            with_level(level, || {
                let mut x = a.clone();
                mul_inplace(&mut x, &b);
                assert!(
                    x.iter()
                        .zip(a.iter().zip(&b))
                        .all(|(x, (a, b))| *x == a * b)
                );
                product2(&mut x, &b, &b);
                assert!(x.iter().zip(&b).all(|(x, b)| *x == b * b));
                product3(&mut x, &a, &b, &b);
                assert!(
                    x.iter()
                        .zip(a.iter().zip(&b))
                        .all(|(x, (a, b))| *x == a * b * b)
                );
                let mut y = a.clone();
                mul_add3(&mut y, &b, &a, &a, &b);
                assert!(
                    y.iter()
                        .zip(a.iter().zip(&b))
                        .all(|(y, (a, b))| (*y - (a * b + a * a * b)).abs() < 1e-4)
                );
                let mut acc = vec![1.0; 37];
                add_squared_diff(&mut acc, &a, &b);
                assert!(
                    acc.iter()
                        .zip(a.iter().zip(&b))
                        .all(|(s, (a, b))| *s == 1.0 + (a - b) * (a - b))
                );
                scale_shift(&mut y, 0.0, 2.0);
                assert!(y.iter().all(|v| *v == 2.0));
                let total = sum(&a);
                let want: f32 = (0..37).map(|i| i as f32 * 0.5 - 3.0).sum();
                assert!((total - want).abs() < 1e-4, "{level:?}: {total} vs {want}");
                assert_eq!(sum(&[]), 0.0);
            });
        }
    }
}
