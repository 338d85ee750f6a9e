//! Hidden-layer activations and the vectorised slice operations built on them.
//!
//! Both activations are smooth (the DEEN loss needs second derivatives). Every operation here
//! is a loop over a slice: one call per layer, branch-free inside. [`Activation::apply`] is a
//! [`multiversion!`](super::simd) loop (the portable kernel's inference pass). On AVX-512 and
//! AVX2, training's passes (the activation with its derivatives,
//! [`Activation::apply_d1`] and [`Activation::apply_d2`]) run [`lanes`](super::lanes)' register
//! functions instead: the same polynomials with fused multiply-adds and a refined reciprocal
//! estimate in place of the division, which the scalar code spends most of its time on. They
//! agree with the scalar functions to a few ulps (tested), and their values are bit for bit
//! those of the inference kernels' epilogues on the same CPU; a cartpole training step spent
//! 8–12 % of its time in these passes (README, Speed).

use super::fastmath::{softplus, softplus_d2, swish_d2};
use super::simd::multiversion;
#[cfg(target_arch = "x86_64")]
use super::simd::{SimdLevel, level};
use serde::{Deserialize, Serialize};

/// The nonlinearity applied after every hidden layer (the output layer is linear).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
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
        if self.on_registers(z, d1, None) {
            return;
        }
        match self {
            Activation::Swish => swish_d1_inplace(z, d1),
            Activation::Softplus => softplus_d1_inplace(z, d1),
        }
    }

    /// Applies the activation in place and writes its first and second derivatives at the old
    /// values to `d1` and `d2` (the DEEN double backprop needs both).
    pub fn apply_d2(self, z: &mut [f32], d1: &mut [f32], d2: &mut [f32]) {
        assert!(z.len() == d1.len() && z.len() == d2.len());
        if self.on_registers(z, d1, Some(&mut *d2)) {
            return;
        }
        match self {
            Activation::Swish => swish_d2_inplace(z, d1, d2),
            Activation::Softplus => softplus_d2_inplace(z, d1, d2),
        }
    }

    /// Runs a training pass on whole registers where the CPU has AVX-512 or AVX2
    /// ([`registers`]); `false` (nothing done) on the portable level.
    fn on_registers(self, z: &mut [f32], d1: &mut [f32], d2: Option<&mut [f32]>) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            match level() {
                // SAFETY: `level()` reports AVX-512 only when the CPU has every enabled feature.
                SimdLevel::Avx512 => unsafe { registers::avx512(self, z, d1, d2) },
                // SAFETY: `level()` reports AVX2 only when the CPU has AVX2 and FMA.
                SimdLevel::Avx2 => unsafe { registers::avx2(self, z, d1, d2) },
                SimdLevel::Scalar => return false,
            }
            true
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (z, d1, d2);
            false
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

// Training's passes on the portable level only: AVX2 and AVX-512 run [`registers`], so these
// need no per-level copies.

fn swish_d1_inplace(z: &mut [f32], d1: &mut [f32]) {
    for (v, g) in z.iter_mut().zip(d1.iter_mut()) {
        let (a, b, _) = swish_d2(*v);
        *v = a;
        *g = b;
    }
}

fn softplus_d1_inplace(z: &mut [f32], d1: &mut [f32]) {
    for (v, g) in z.iter_mut().zip(d1.iter_mut()) {
        let (a, b, _) = softplus_d2(*v);
        *v = a;
        *g = b;
    }
}

fn swish_d2_inplace(z: &mut [f32], d1: &mut [f32], d2: &mut [f32]) {
    for ((v, g), h) in z.iter_mut().zip(d1.iter_mut()).zip(d2.iter_mut()) {
        let (a, b, c) = swish_d2(*v);
        *v = a;
        *g = b;
        *h = c;
    }
}

fn softplus_d2_inplace(z: &mut [f32], d1: &mut [f32], d2: &mut [f32]) {
    for ((v, g), h) in z.iter_mut().zip(d1.iter_mut()).zip(d2.iter_mut()) {
        let (a, b, c) = softplus_d2(*v);
        *v = a;
        *g = b;
        *h = c;
    }
}

/// Training's activation passes on whole registers: [`lanes`](crate::nn::lanes)' functions,
/// 16 lanes at a time on AVX-512 and 8 on AVX2.
#[cfg(target_arch = "x86_64")]
mod registers {
    use super::Activation;
    use crate::nn::lanes::{self, Lanes};
    use std::arch::x86_64::*;

    /// Activates `z` in place, writing the first derivative to `d1` and, when given, the second
    /// to `d2` (all of `z`'s length), on AVX-512 registers.
    #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
    pub fn avx512(act: Activation, z: &mut [f32], d1: &mut [f32], d2: Option<&mut [f32]>) {
        // Closures, not the functions themselves: a closure inherits this function's target
        // features, so the intrinsics inline into the loop (a function item passed as `Fn` was
        // called through a shim without them, four times slower than the scalar code).
        let swish = |x| lanes::swish_d2::<__m512>(x);
        let softplus = |x| lanes::softplus_d2::<__m512>(x);
        match act {
            Activation::Swish => map(z, d1, d2, swish),
            Activation::Softplus => map(z, d1, d2, softplus),
        }
    }

    /// [`avx512`] on AVX2 registers.
    #[target_feature(enable = "avx2,fma")]
    pub fn avx2(act: Activation, z: &mut [f32], d1: &mut [f32], d2: Option<&mut [f32]>) {
        let swish = |x| lanes::swish_d2::<__m256>(x);
        let softplus = |x| lanes::softplus_d2::<__m256>(x);
        match act {
            Activation::Swish => map(z, d1, d2, swish),
            Activation::Softplus => map(z, d1, d2, softplus),
        }
    }

    /// One pass of `f` over `z`, a register at a time, the last partial register through a
    /// zero-padded copy (the tail only; AMD's masked stores are slow). Generic over `f` (a
    /// closure of the entry points above) and inlined, so that each activation and register
    /// type gets a loop of its own.
    #[inline(always)]
    fn map<V: Lanes>(
        z: &mut [f32],
        d1: &mut [f32],
        mut d2: Option<&mut [f32]>,
        f: impl Fn(V) -> (V, V, V),
    ) {
        let n = z.len();
        assert!(d1.len() == n && d2.as_ref().is_none_or(|d2| d2.len() == n));
        let whole = n / V::LANES * V::LANES;
        for i in (0..whole).step_by(V::LANES) {
            // SAFETY: i + LANES ≤ n, inside every slice (same length n, checked above).
            unsafe {
                let (a, b, c) = f(V::load(z.as_ptr().add(i)));
                a.store(z.as_mut_ptr().add(i));
                b.store(d1.as_mut_ptr().add(i));
                if let Some(d2) = d2.as_deref_mut() {
                    c.store(d2.as_mut_ptr().add(i));
                }
            }
        }
        if whole < n {
            let tail = n - whole;
            let mut lanes = [[0.0f32; lanes::MAX_LANES]; 3];
            lanes[0][..tail].copy_from_slice(&z[whole..]);
            // SAFETY: each of `lanes` holds MAX_LANES ≥ V::LANES floats.
            unsafe {
                let (a, b, c) = f(V::load(lanes[0].as_ptr()));
                a.store(lanes[0].as_mut_ptr());
                b.store(lanes[1].as_mut_ptr());
                c.store(lanes[2].as_mut_ptr());
            }
            z[whole..].copy_from_slice(&lanes[0][..tail]);
            d1[whole..].copy_from_slice(&lanes[1][..tail]);
            if let Some(d2) = d2 {
                d2[whole..].copy_from_slice(&lanes[2][..tail]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::simd::{SimdLevel, with_level};
    use super::*;

    #[test]
    fn slice_ops_match_scalar_reference_at_every_level() {
        let mut xs: Vec<f32> = (0..1003).map(|i| (i as f32 - 501.0) * 0.037).collect();
        xs.extend([
            -1e30, -200.0, -88.0, -87.5, 0.0, -0.0, 1e-30, 88.0, 200.0, 1e30,
        ]);
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

    /// A diverging step must show in the loss: NaN in, NaN out, at every level.
    #[test]
    fn a_nan_input_gives_a_nan_value_at_every_level() {
        for level in SimdLevel::available() {
            for act in [Activation::Swish, Activation::Softplus] {
                let mut z = vec![0.5; 37];
                z[3] = f32::NAN;
                z[36] = f32::NAN;
                let (mut d1, mut d2) = (vec![0.0; 37], vec![0.0; 37]);
                with_level(level, || act.apply_d2(&mut z, &mut d1, &mut d2));
                assert!(z[3].is_nan() && z[36].is_nan(), "{level:?} {act:?}");
                assert!(z[4].is_finite() && z[35].is_finite(), "{level:?} {act:?}");
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
