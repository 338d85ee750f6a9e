//! AVX-512 registers for the matrix kernels' epilogues and training's activation passes: the
//! [`Lanes`] operations on `__m512` (so [`lanes`](super::lanes)' swish and softplus run 16
//! lanes at a time), and the bf16-grade activations, which only the bf16 layers of AVX-512 BF16
//! CPUs use.
//!
//! A layer that stores its output as bf16 (8 significant bits, rounding error up to 2⁻⁹) has
//! no use for 24-bit activations: [`swish_for_bf16`] and [`softplus_for_bf16`] are accurate to
//! 2⁻¹³ and 2⁻¹⁶ relative (tested against f64) at half the instructions — `VSCALEFPS` in place
//! of the exponent's integer arithmetic, lower-degree polynomials, no Newton step. The
//! activation was what the bf16 layers lost against the bare product (a bf16 hidden layer
//! pays it once per output element against only `k/2` multiply instructions); with these
//! the half-cheetah + DEEN plan runs at 84–88 % of the bf16 peak per CPU second instead of
//! 72–76 % (README, Speed).

use super::fastmath::{LOG2E, ROUND_MAGIC_BITS};
use super::lanes::Lanes;
use std::arch::x86_64::*;

// SAFETY (every intrinsic in this file): the functions are `inline(always)` into
// `#[target_feature(enable = "avx512f")]` code (the kernels' and passes' entry points check
// the CPU first), which covers each intrinsic's features.
impl Lanes for __m512 {
    const LANES: usize = 16;
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        // SAFETY: the caller guarantees `p` is valid for 16 floats.
        unsafe { _mm512_loadu_ps(p) }
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        // SAFETY: the caller guarantees `p` is valid for 16 floats.
        unsafe { _mm512_storeu_ps(p, self) }
    }
    #[inline(always)]
    fn splat(v: f32) -> Self {
        unsafe { _mm512_set1_ps(v) }
    }
    #[inline(always)]
    fn add(self, b: Self) -> Self {
        unsafe { _mm512_add_ps(self, b) }
    }
    #[inline(always)]
    fn sub(self, b: Self) -> Self {
        unsafe { _mm512_sub_ps(self, b) }
    }
    #[inline(always)]
    fn mul(self, b: Self) -> Self {
        unsafe { _mm512_mul_ps(self, b) }
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        unsafe { _mm512_fmadd_ps(self, b, c) }
    }
    #[inline(always)]
    fn neg_mul_add(self, b: Self, c: Self) -> Self {
        unsafe { _mm512_fnmadd_ps(self, b, c) }
    }
    #[inline(always)]
    fn max(self, b: Self) -> Self {
        unsafe { _mm512_max_ps(self, b) }
    }
    #[inline(always)]
    fn neg_abs(self) -> Self {
        unsafe {
            _mm512_castsi512_ps(_mm512_or_si512(
                _mm512_castps_si512(self),
                _mm512_set1_epi32(i32::MIN),
            ))
        }
    }
    #[inline(always)]
    fn recip_estimate(self) -> Self {
        unsafe { _mm512_rcp14_ps(self) }
    }
    #[inline(always)]
    fn exp2_of_rounded(self) -> Self {
        unsafe {
            let n = _mm512_sub_epi32(
                _mm512_castps_si512(self),
                _mm512_set1_epi32(ROUND_MAGIC_BITS as i32),
            );
            _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(
                n,
                _mm512_set1_epi32(127),
            )))
        }
    }
    #[inline(always)]
    fn where_negative(self, if_negative: Self, otherwise: Self) -> Self {
        unsafe {
            let negative = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(self, _mm512_setzero_ps());
            _mm512_mask_blend_ps(negative, otherwise, if_negative)
        }
    }
    #[inline(always)]
    fn where_above(self, bound: Self, if_above: Self, otherwise: Self) -> Self {
        unsafe {
            let above = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(self, bound);
            _mm512_mask_blend_ps(above, otherwise, if_above)
        }
    }
}

/// `x · y + z` in one rounding.
#[inline(always)]
fn fma(x: __m512, y: __m512, z: __m512) -> __m512 {
    x.mul_add(y, z)
}

#[inline(always)]
fn splat(v: f32) -> __m512 {
    __m512::splat(v)
}

/// Bounds on `y` in [`exp2_for_bf16`]: `2^y` stays a normal float (no denormal results, which
/// x86 may handle in microcode) and finite.
const EXP2_Y_LO: f32 = -125.0;
const EXP2_Y_HI: f32 = 125.0;

/// `2^y` for `y ∈ [−125, 125]` (callers clamp) to within 2⁻¹⁸·⁶ relative: the exponent's
/// integer part goes into the result's exponent with `VSCALEFPS`, the fraction `f ∈ [−½, ½]`
/// through a degree-4 minimax polynomial (Remez, relative error).
#[inline(always)]
fn exp2_for_bf16(y: __m512) -> __m512 {
    // SAFETY: as for the `Lanes` impl above.
    unsafe {
        let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(y);
        let f = _mm512_sub_ps(y, n);
        let p = fma(splat(9.570_102e-3), f, splat(5.591_786e-2));
        let p = fma(p, f, splat(2.402_474_5e-1));
        let p = fma(p, f, splat(6.931_218e-1));
        let p = fma(p, f, splat(9.999_993e-1));
        _mm512_scalef_ps(p, n)
    }
}

/// Swish `x σ(x)` for a layer that stores its output as bf16: to within 2⁻¹³·⁸ relative
/// (the exponential above, and the 14-bit reciprocal estimate without a Newton step), where
/// the store that follows rounds by up to 2⁻⁹. Half the instructions of [`swish`](super::lanes::swish), which a
/// hidden bf16 layer pays once per output element against only `k/2` multiply instructions.
#[inline(always)]
pub fn swish_for_bf16(x: __m512) -> __m512 {
    // SAFETY: as for the `Lanes` impl above.
    unsafe {
        // e^{−x} = 2^y, y = −x·log₂e, clamped so that 1 + 2^y and its reciprocal stay normal.
        let y = _mm512_mul_ps(x, splat(-LOG2E));
        let y = _mm512_max_ps(_mm512_min_ps(y, splat(EXP2_Y_HI)), splat(EXP2_Y_LO));
        let sigma = _mm512_rcp14_ps(_mm512_add_ps(splat(1.0), exp2_for_bf16(y)));
        _mm512_mul_ps(x, sigma)
    }
}

/// `ln(1 + t) / t` for `t ∈ [0, 1]` to within 2⁻¹⁶·⁹ relative: a degree-5 minimax polynomial.
#[inline(always)]
fn ln_1p_over_t(t: __m512) -> __m512 {
    let q = fma(splat(-2.386_915_2e-2), t, splat(1.012_222_85e-1));
    let q = fma(q, t, splat(-2.100_486_9e-1));
    let q = fma(q, t, splat(3.252_066_8e-1));
    let q = fma(q, t, splat(-4.993_613_6e-1));
    fma(q, t, splat(9.999_916e-1))
}

/// Softplus `max(x, 0) + ln(1 + e^{−|x|})` for a layer that stores its output as bf16: to
/// within 2⁻¹⁶ relative, where the store rounds by up to 2⁻⁹; half the instructions of
/// [`softplus`](super::lanes::softplus). A NaN input gives NaN.
#[inline(always)]
pub fn softplus_for_bf16(x: __m512) -> __m512 {
    // SAFETY: as for the `Lanes` impl above.
    unsafe {
        let y = _mm512_mul_ps(x.neg_abs(), splat(LOG2E));
        // `max` returns its second operand when either is NaN: here the bound (a finite `t`),
        // and below `x`, so that NaN comes through.
        let t = exp2_for_bf16(_mm512_max_ps(y, splat(EXP2_Y_LO)));
        let pos = _mm512_max_ps(_mm512_setzero_ps(), x);
        fma(t, ln_1p_over_t(t), pos)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::activation::Activation;
    use crate::nn::fastmath;
    use crate::nn::lanes::{softplus, swish};
    use crate::nn::simd::{SimdLevel, level};

    /// Applies `f` to 16 floats at a time.
    #[target_feature(enable = "avx512f")]
    fn map(xs: &[f32], f: fn(__m512) -> __m512) -> Vec<f32> {
        xs.chunks(16)
            .flat_map(|c| {
                let mut lane = [0.0f32; 16];
                lane[..c.len()].copy_from_slice(c);
                // SAFETY: `lane` holds 16 floats; the CPU has AVX-512F (checked by the caller).
                let out = unsafe { f(_mm512_loadu_ps(lane.as_ptr())) };
                let mut back = [0.0f32; 16];
                // SAFETY: `back` holds 16 floats.
                unsafe { _mm512_storeu_ps(back.as_mut_ptr(), out) };
                back[..c.len()].to_vec()
            })
            .collect()
    }

    #[test]
    fn the_bf16_grade_activations_are_far_inside_the_bf16_rounding() {
        if level() < SimdLevel::Avx512 {
            return; // the bf16 layers that use them never run on this CPU
        }
        let xs: Vec<f32> = (0..=400_000).map(|i| -100.0 + i as f32 * 5e-4).collect();
        // SAFETY: the level check above guarantees AVX-512F.
        let (sw, sp) = unsafe { (map(&xs, swish_for_bf16), map(&xs, softplus_for_bf16)) };
        let (mut worst_sw, mut worst_sp) = (0.0f64, 0.0f64);
        for (i, &x) in xs.iter().enumerate() {
            let exact = |a| crate::nn::reference::activate(Some(a), f64::from(x));
            let (want_sw, want_sp) = (exact(Activation::Swish), exact(Activation::Softplus));
            // Relative to the value; below 1e-30 (|x| beyond about 65) the clamped tail only
            // has to stay as small (the clamp ends it near 2⁻¹²⁵·|x|).
            let err = |got: f32, want: f64| (f64::from(got) - want).abs() / want.abs().max(1e-30);
            worst_sw = worst_sw.max(err(sw[i], want_sw));
            worst_sp = worst_sp.max(err(sp[i], want_sp));
        }
        // The store that follows rounds by up to 2⁻⁹ relative.
        assert!(worst_sw <= 2f64.powi(-13), "swish: {worst_sw:e}");
        assert!(worst_sp <= 2f64.powi(-16), "softplus: {worst_sp:e}");
        let special = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.0];
        // SAFETY: as above.
        let (sw, sp) = unsafe {
            (
                map(&special, swish_for_bf16),
                map(&special, softplus_for_bf16),
            )
        };
        assert!(sw[0].is_nan() && sp[0].is_nan(), "NaN in, NaN out");
        assert_eq!([sw[1], sp[1]], [f32::INFINITY; 2]);
        assert!(sp[2] >= 0.0 && sp[2] < 1e-30, "softplus(−∞) = {}", sp[2]);
        assert_eq!([sw[3], sw[4]], [0.0; 2]);
        assert!(
            (sp[3] / std::f32::consts::LN_2 - 1.0).abs() < 2f32.powi(-16),
            "{}",
            sp[3]
        );
    }

    #[test]
    fn registers_agree_with_the_scalar_functions() {
        if level() < SimdLevel::Avx512 {
            return; // nothing to compare on this CPU; the scalar functions have their own tests
        }
        let mut xs: Vec<f32> = (0..=240_000).map(|i| -60.0 + i as f32 * 5e-4).collect();
        xs.extend([
            -1e30, -200.0, -88.0, -87.5, 0.0, -0.0, 1e-30, 88.0, 200.0, 1e30,
        ]);
        // SAFETY: the level check above guarantees AVX-512F.
        let (sw, sp) = unsafe { (map(&xs, swish::<__m512>), map(&xs, softplus::<__m512>)) };
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
}
