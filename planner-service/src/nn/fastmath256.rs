//! [`fastmath`](super::fastmath)'s swish and softplus on whole AVX2 registers, for the AVX2
//! matrix kernel's epilogue: a finished block of `Z = Wᵀ·H + b` is activated in registers
//! before it is stored, as [`fastmath512`](super::fastmath512) does for AVX-512.
//!
//! Why: on CPUs without AVX-512 the activation used to be a second pass over each stored block,
//! compiled from the scalar code, which multiplies and adds in separate roundings and divides
//! for `1 / (1 + t)`; a `perf record` of a half-cheetah PETS plan on an AMD Zen 3 (AVX2 only)
//! put 16 % of its samples in that pass against 73 % in the matrix kernel. Here, as in
//! `fastmath512`, every `a·b + c` is one fused multiply-add and the division is the 12-bit
//! reciprocal estimate refined by one Newton step. Results agree with `fastmath` to within a
//! few ulps (tested).

use std::arch::x86_64::*;

const LOG2E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const ROUND_MAGIC: f32 = 12_582_912.0;
const ROUND_MAGIC_BITS: i32 = 0x4B40_0000;
const EXP_LO: f32 = -87.0;

/// `x · y + z` in one rounding.
#[inline(always)]
fn fma(x: __m256, y: __m256, z: __m256) -> __m256 {
    // SAFETY: callers are compiled with AVX2 and FMA (every function here is `inline(always)`
    // into `#[target_feature(enable = "avx2,fma")]` code).
    unsafe { _mm256_fmadd_ps(x, y, z) }
}

#[inline(always)]
fn splat(v: f32) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe { _mm256_set1_ps(v) }
}

/// `-|x|` (the sign bit set).
#[inline(always)]
fn neg_abs(x: __m256) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe { _mm256_or_ps(x, splat(-0.0)) }
}

/// `eˣ` for `x ≤ 0` (clamped below at −87, as [`super::fastmath::exp`]).
#[inline(always)]
fn exp_nonpositive(x: __m256) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe {
        let x = _mm256_max_ps(x, splat(EXP_LO));
        let shifted = fma(x, splat(LOG2E), splat(ROUND_MAGIC));
        let n = _mm256_sub_ps(shifted, splat(ROUND_MAGIC));
        let r = _mm256_fnmadd_ps(n, splat(LN2_HI), x);
        let r = _mm256_fnmadd_ps(n, splat(LN2_LO), r);
        let p = fma(splat(1.987_569_2e-4), r, splat(1.398_2e-3));
        let p = fma(p, r, splat(8.333_452e-3));
        let p = fma(p, r, splat(4.166_579_6e-2));
        let p = fma(p, r, splat(1.666_666_5e-1));
        let p = fma(p, r, splat(0.5));
        let er = _mm256_add_ps(fma(p, _mm256_mul_ps(r, r), r), splat(1.0));
        let n_int = _mm256_sub_epi32(
            _mm256_castps_si256(shifted),
            _mm256_set1_epi32(ROUND_MAGIC_BITS),
        );
        let scale = _mm256_slli_epi32::<23>(_mm256_add_epi32(n_int, _mm256_set1_epi32(127)));
        _mm256_mul_ps(er, _mm256_castsi256_ps(scale))
    }
}

/// `1 / d` for `d ∈ [1, 2]`: the 12-bit estimate and one Newton step (error about 2⁻²²).
#[inline(always)]
fn recip_1_2(d: __m256) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe {
        let r = _mm256_rcp_ps(d);
        fma(_mm256_fnmadd_ps(d, r, splat(1.0)), r, r)
    }
}

/// Swish `x σ(x)`.
#[inline(always)]
pub fn swish(x: __m256) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe {
        let t = exp_nonpositive(neg_abs(x));
        let a = recip_1_2(_mm256_add_ps(splat(1.0), t));
        // σ(x) is a = 1/(1 + e^{-|x|}) for x ≥ 0 and t·a for x < 0.
        let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(x, _mm256_setzero_ps());
        let s = _mm256_blendv_ps(a, _mm256_mul_ps(t, a), negative);
        _mm256_mul_ps(x, s)
    }
}

/// `ln(1 + t)` for `t ∈ [0, 1]` ([`super::fastmath::ln_1p_unit`]).
#[inline(always)]
fn ln_1p_unit(t: __m256) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe {
        let big = _mm256_cmp_ps::<_CMP_GT_OQ>(t, splat(std::f32::consts::SQRT_2 - 1.0));
        let half_tm1 = _mm256_mul_ps(_mm256_sub_ps(t, splat(1.0)), splat(0.5));
        let f = _mm256_blendv_ps(t, half_tm1, big);
        let e = _mm256_and_ps(big, splat(std::f32::consts::LN_2));
        let z = _mm256_mul_ps(f, f);
        let p = fma(splat(7.037_683_6e-2), f, splat(-1.151_461e-1));
        let p = fma(p, f, splat(1.167_699_9e-1));
        let p = fma(p, f, splat(-1.242_014_1e-1));
        let p = fma(p, f, splat(1.424_932_3e-1));
        let p = fma(p, f, splat(-1.666_805_8e-1));
        let p = fma(p, f, splat(2.000_071_4e-1));
        let p = fma(p, f, splat(-2.499_999_4e-1));
        let p = fma(p, f, splat(0.333_333_3));
        let y = fma(_mm256_mul_ps(f, z), p, _mm256_mul_ps(splat(-0.5), z));
        _mm256_add_ps(_mm256_add_ps(f, y), e)
    }
}

/// Softplus `ln(1 + eˣ) = max(x, 0) + ln(1 + e^{-|x|})`.
#[inline(always)]
pub fn softplus(x: __m256) -> __m256 {
    // SAFETY: as in `fma`.
    unsafe {
        let t = exp_nonpositive(neg_abs(x));
        let pos = _mm256_max_ps(x, _mm256_setzero_ps());
        _mm256_add_ps(pos, ln_1p_unit(t))
    }
}

/// `(σ(x), σ(−x))` given `t = e^{−|x|}` ([`super::fastmath`]'s pair, with the reciprocal
/// estimate refined by one Newton step in place of the division).
#[inline(always)]
fn sigmoid_pair(x: __m256, t: __m256) -> (__m256, __m256) {
    // SAFETY: as in `fma`.
    unsafe {
        let a = recip_1_2(_mm256_add_ps(splat(1.0), t));
        let b = _mm256_mul_ps(t, a);
        let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(x, _mm256_setzero_ps());
        (
            _mm256_blendv_ps(a, b, negative),
            _mm256_blendv_ps(b, a, negative),
        )
    }
}

/// Swish and its first two derivatives, as [`super::fastmath::swish_d2`], for training's
/// activation passes: the value is bit for bit [`swish`]'s, so a network trained on this CPU
/// sees in its forward pass exactly what inference computes.
#[inline(always)]
pub fn swish_d2(x: __m256) -> (__m256, __m256, __m256) {
    // SAFETY: as in `fma`.
    unsafe {
        let (s, c) = sigmoid_pair(x, exp_nonpositive(neg_abs(x)));
        let d1 = _mm256_mul_ps(s, fma(x, c, splat(1.0)));
        let d2 = _mm256_mul_ps(_mm256_mul_ps(s, c), fma(x, _mm256_sub_ps(c, s), splat(2.0)));
        (_mm256_mul_ps(x, s), d1, d2)
    }
}

/// Softplus and its first two derivatives, as [`super::fastmath::softplus_d2`]. A NaN input
/// gives a NaN value, so that a diverging training step shows in its loss.
#[inline(always)]
pub fn softplus_d2(x: __m256) -> (__m256, __m256, __m256) {
    // SAFETY: as in `fma`.
    unsafe {
        let t = exp_nonpositive(neg_abs(x));
        // `max` returns its second operand when either is NaN.
        let pos = _mm256_max_ps(_mm256_setzero_ps(), x);
        let (s, c) = sigmoid_pair(x, t);
        (_mm256_add_ps(pos, ln_1p_unit(t)), s, _mm256_mul_ps(s, c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::fastmath;
    use crate::nn::simd::{SimdLevel, level};

    /// Applies `f` to 8 floats at a time.
    #[target_feature(enable = "avx2,fma")]
    fn map(xs: &[f32], f: fn(__m256) -> __m256) -> Vec<f32> {
        xs.chunks(8)
            .flat_map(|c| {
                let mut lane = [0.0f32; 8];
                lane[..c.len()].copy_from_slice(c);
                // SAFETY: `lane` holds 8 floats; the CPU has AVX2 and FMA (checked by the caller).
                let out = unsafe { f(_mm256_loadu_ps(lane.as_ptr())) };
                let mut back = [0.0f32; 8];
                // SAFETY: `back` holds 8 floats.
                unsafe { _mm256_storeu_ps(back.as_mut_ptr(), out) };
                back[..c.len()].to_vec()
            })
            .collect()
    }

    #[test]
    fn registers_agree_with_the_scalar_functions() {
        if level() < SimdLevel::Avx2 {
            return; // nothing to compare on this CPU; the scalar functions have their own tests
        }
        let mut xs: Vec<f32> = (0..=240_000).map(|i| -60.0 + i as f32 * 5e-4).collect();
        xs.extend([
            -1e30, -200.0, -88.0, -87.5, 0.0, -0.0, 1e-30, 88.0, 200.0, 1e30,
        ]);
        // SAFETY: the level check above guarantees AVX2 and FMA.
        let (sw, sp) = unsafe { (map(&xs, swish), map(&xs, softplus)) };
        for (i, &x) in xs.iter().enumerate() {
            let want_sw = fastmath::swish_d2(x).0;
            let want_sp = fastmath::softplus(x);
            // A few ulps of the value, or of 1 near zero (fastmath's own accuracy is 3e-7).
            let close = |u: f32, v: f32| (u - v).abs() <= 4e-7 * v.abs().max(1.0);
            assert!(close(sw[i], want_sw), "swish({x}) = {} vs {want_sw}", sw[i]);
            assert!(
                close(sp[i], want_sp),
                "softplus({x}) = {} vs {want_sp}",
                sp[i]
            );
            assert!(sw[i].is_finite() && sp[i].is_finite(), "{x}");
        }
    }

    #[test]
    fn registers_are_exact_to_a_few_ulps_of_the_true_functions() {
        if level() < SimdLevel::Avx2 {
            return;
        }
        let xs: Vec<f32> = (0..=200_000).map(|i| -50.0 + i as f32 * 5e-4).collect();
        // SAFETY: the level check above guarantees AVX2 and FMA.
        let (sw, sp) = unsafe { (map(&xs, swish), map(&xs, softplus)) };
        let (mut worst_sw, mut worst_sp) = (0.0f64, 0.0f64);
        for (i, &x) in xs.iter().enumerate() {
            let exact = |a| crate::nn::reference::activate(Some(a), f64::from(x));
            let err = |got: f32, want: f64| (f64::from(got) - want).abs() / want.abs().max(1e-30);
            worst_sw = worst_sw.max(err(sw[i], exact(crate::nn::Activation::Swish)));
            worst_sp = worst_sp.max(err(sp[i], exact(crate::nn::Activation::Softplus)));
        }
        // f32's own rounding is 2⁻²⁴; a handful of roundings through the polynomials.
        assert!(worst_sw <= 2f64.powi(-20), "swish: {worst_sw:e}");
        assert!(worst_sp <= 2f64.powi(-20), "softplus: {worst_sp:e}");
    }
}
