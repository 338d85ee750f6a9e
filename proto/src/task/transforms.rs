//! Model transforms declared per dimension (a spec's `model = { declared = … }`): angles seen as
//! `sin`/`cos` in their place, targets that are the next value itself instead of a delta.

use super::spec::DeclaredTransforms;

/// [`DeclaredTransforms`] as per-dimension flags, so the per-row functions look nothing up.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Declared {
    angle: Vec<bool>,
    absolute: Vec<bool>,
}

impl Declared {
    /// The flags of a validated spec's transforms (indices below `obs_dim`, none repeated).
    pub fn new(obs_dim: usize, declared: &DeclaredTransforms) -> Self {
        let flags = |indices: &[usize]| {
            let mut flags = vec![false; obs_dim];
            for &i in indices {
                flags[i] = true;
            }
            flags
        };
        Self {
            angle: flags(&declared.angles),
            absolute: flags(&declared.absolute),
        }
    }

    /// Length of the model's state input: one per dimension, two per angle.
    pub fn feature_dim(&self) -> usize {
        self.angle.len() + self.angle.iter().filter(|&&a| a).count()
    }

    pub fn state_features(&self, obs: &[f32], out: &mut [f32]) {
        let mut k = 0;
        for (&x, &angle) in obs.iter().zip(&self.angle) {
            if angle {
                let (sin, cos) = x.sin_cos();
                out[k] = sin;
                out[k + 1] = cos;
                k += 2;
            } else {
                out[k] = x;
                k += 1;
            }
        }
    }

    pub fn state_features_backward(&self, obs: &[f32], d: &[f32], d_obs: &mut [f32]) {
        let mut k = 0;
        for ((g, &x), &angle) in d_obs.iter_mut().zip(obs).zip(&self.angle) {
            if angle {
                let (sin, cos) = x.sin_cos();
                *g += d[k] * cos - d[k + 1] * sin;
                k += 2;
            } else {
                *g += d[k];
                k += 1;
            }
        }
    }

    pub fn target(&self, obs: &[f32], next_obs: &[f32], out: &mut [f32]) {
        for (((o, &s), &n), &absolute) in out.iter_mut().zip(obs).zip(next_obs).zip(&self.absolute)
        {
            *o = if absolute { n } else { n - s };
        }
    }

    pub fn next_obs_from_target(&self, obs: &[f32], target: &[f32], next_obs: &mut [f32]) {
        for (((n, &s), &t), &absolute) in
            next_obs.iter_mut().zip(obs).zip(target).zip(&self.absolute)
        {
            *n = if absolute { t } else { s + t };
        }
    }

    pub fn next_obs_from_target_backward(
        &self,
        d_next: &[f32],
        d_obs: &mut [f32],
        d_target: &mut [f32],
    ) {
        d_target.copy_from_slice(d_next);
        for ((o, &d), &absolute) in d_obs.iter_mut().zip(d_next).zip(&self.absolute) {
            if !absolute {
                *o += d;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angles_expand_in_place_and_absolute_targets_are_the_value() {
        let t = Declared::new(
            3,
            &DeclaredTransforms {
                angles: vec![1],
                absolute: vec![2],
            },
        );
        assert_eq!(t.feature_dim(), 4);
        let mut f = [0.0; 4];
        t.state_features(&[5.0, std::f32::consts::FRAC_PI_2, 7.0], &mut f);
        assert!((f[1] - 1.0).abs() < 1e-6 && f[2].abs() < 1e-6, "{f:?}");
        assert_eq!((f[0], f[3]), (5.0, 7.0));
        let mut target = [0.0; 3];
        t.target(&[1.0, 1.0, 1.0], &[2.0, 3.0, 4.0], &mut target);
        assert_eq!(target, [1.0, 2.0, 4.0]);
    }
}
