//! Hidden-layer activations and the vectorised slice operations built on them.
//!
//! Both activations are smooth (the DEEN loss needs second derivatives). Every operation here
//! is a [`multiversion!`](super::simd) loop over a slice: one call per layer, branch-free inside.

use super::fastmath::{softplus, softplus_d2, swish_d2};
use super::simd::multiversion;
use serde::{Deserialize, Serialize};

/// The nonlinearity applied after every hidden layer (the output layer is linear).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Activation {
    /// `x σ(x)` (SiLU), as in the PETS dynamics models.
    Swish,
    /// `ln(1 + eˣ)`, as in DEEN: smooth and convex, so the energy's input gradient is well behaved.
    Softplus,
}

impl Activation {
    /// Applies the activation in place.
    pub fn apply(self, z: &mut [f32]) {
        match self {
            Activation::Swish => swish_inplace(z),
            Activation::Softplus => softplus_inplace(z),
        }
    }

    /// Applies the activation in place and writes its derivative at the old values to `d1`.
    pub fn apply_d1(self, z: &mut [f32], d1: &mut [f32]) {
        assert_eq!(z.len(), d1.len());
        match self {
            Activation::Swish => swish_d1_inplace(z, d1),
            Activation::Softplus => softplus_d1_inplace(z, d1),
        }
    }

    /// Applies the activation in place and writes its first and second derivatives at the old
    /// values to `d1` and `d2` (the DEEN double backprop needs both).
    pub fn apply_d2(self, z: &mut [f32], d1: &mut [f32], d2: &mut [f32]) {
        assert!(z.len() == d1.len() && z.len() == d2.len());
        match self {
            Activation::Swish => swish_d2_inplace(z, d1, d2),
            Activation::Softplus => softplus_d2_inplace(z, d1, d2),
        }
    }

    /// The activation of one number (reference for tests and scalar paths).
    pub fn eval_d2(self, x: f32) -> (f32, f32, f32) {
        match self {
            Activation::Swish => swish_d2(x),
            Activation::Softplus => softplus_d2(x),
        }
    }
}

multiversion! {
    fn swish_inplace(z: &mut [f32]) {
        for v in z.iter_mut() {
            *v = swish_d2(*v).0;
        }
    }
}

multiversion! {
    fn softplus_inplace(z: &mut [f32]) {
        for v in z.iter_mut() {
            *v = softplus(*v);
        }
    }
}

multiversion! {
    fn swish_d1_inplace(z: &mut [f32], d1: &mut [f32]) {
        for (v, g) in z.iter_mut().zip(d1.iter_mut()) {
            let (a, b, _) = swish_d2(*v);
            *v = a;
            *g = b;
        }
    }
}

multiversion! {
    fn softplus_d1_inplace(z: &mut [f32], d1: &mut [f32]) {
        for (v, g) in z.iter_mut().zip(d1.iter_mut()) {
            let (a, b, _) = softplus_d2(*v);
            *v = a;
            *g = b;
        }
    }
}

multiversion! {
    fn swish_d2_inplace(z: &mut [f32], d1: &mut [f32], d2: &mut [f32]) {
        for ((v, g), h) in z.iter_mut().zip(d1.iter_mut()).zip(d2.iter_mut()) {
            let (a, b, c) = swish_d2(*v);
            *v = a;
            *g = b;
            *h = c;
        }
    }
}

multiversion! {
    fn softplus_d2_inplace(z: &mut [f32], d1: &mut [f32], d2: &mut [f32]) {
        for ((v, g), h) in z.iter_mut().zip(d1.iter_mut()).zip(d2.iter_mut()) {
            let (a, b, c) = softplus_d2(*v);
            *v = a;
            *g = b;
            *h = c;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::simd::{SimdLevel, with_level};
    use super::*;

    #[test]
    fn slice_ops_match_scalar_reference_at_every_level() {
        let xs: Vec<f32> = (0..1003).map(|i| (i as f32 - 501.0) * 0.037).collect();
        for level in SimdLevel::available() {
            for act in [Activation::Swish, Activation::Softplus] {
                let (mut a, mut b, mut c) = (xs.clone(), xs.clone(), xs.clone());
                let (mut b1, mut c1, mut c2) = (
                    vec![0.0; xs.len()],
                    vec![0.0; xs.len()],
                    vec![0.0; xs.len()],
                );
                with_level(level, || {
                    act.apply(&mut a);
                    act.apply_d1(&mut b, &mut b1);
                    act.apply_d2(&mut c, &mut c1, &mut c2);
                });
                for (i, &x) in xs.iter().enumerate() {
                    let (f, d1, d2) = act.eval_d2(x);
                    // Vectorised code may contract differently; allow a couple of ulps.
                    let close = |u: f32, v: f32| (u - v).abs() <= 1e-6 * v.abs().max(1.0);
                    assert!(
                        close(a[i], f) && close(b[i], f) && close(c[i], f),
                        "{level:?} {act:?} {x}"
                    );
                    assert!(
                        close(b1[i], d1) && close(c1[i], d1),
                        "{level:?} {act:?} {x}"
                    );
                    assert!(close(c2[i], d2), "{level:?} {act:?} {x}");
                }
            }
        }
    }

    #[test]
    fn serde_names_are_lowercase() {
        assert_eq!(
            serde_json::to_string(&Activation::Softplus).unwrap(),
            "\"softplus\""
        );
        let a: Activation = serde_json::from_str("\"swish\"").unwrap();
        assert_eq!(a, Activation::Swish);
    }
}
