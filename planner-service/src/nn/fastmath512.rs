//! [`fastmath`](super::fastmath)'s swish and softplus on whole AVX-512 registers, for the matrix
//! kernel's epilogue: a finished tile of `Z = Wᵀ·H + b` is activated in registers before it is
//! stored, so the activation costs no extra pass over memory.
//!
//! The polynomials, constants and range reductions are `fastmath`'s; two things differ, both
//! for speed: every `a·b + c` is one fused multiply-add, and `1 / (1 + t)` is a 14-bit
//! reciprocal estimate refined by one Newton step (a division costs as much as the rest of the
//! swish put together). Results agree with `fastmath` to within a few ulps (tested).

use std::arch::x86_64::*;

const LOG2E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const ROUND_MAGIC: f32 = 12_582_912.0;
const ROUND_MAGIC_BITS: i32 = 0x4B40_0000;
const EXP_LO: f32 = -87.0;

/// `x · y + z` in one rounding.
#[inline(always)]
fn fma(x: __m512, y: __m512, z: __m512) -> __m512 {
    // SAFETY: callers are compiled with AVX-512F (every function here is `inline(always)`
    // into `#[target_feature(enable = "avx512f")]` code).
    unsafe { _mm512_fmadd_ps(x, y, z) }
}

#[inline(always)]
fn splat(v: f32) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe { _mm512_set1_ps(v) }
}

/// `-|x|` (the sign bit set).
#[inline(always)]
fn neg_abs(x: __m512) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe {
        _mm512_castsi512_ps(_mm512_or_si512(
            _mm512_castps_si512(x),
            _mm512_set1_epi32(i32::MIN),
        ))
    }
}

/// `eˣ` for `x ≤ 0` (clamped below at −87, as [`super::fastmath::exp`]).
#[inline(always)]
fn exp_nonpositive(x: __m512) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe {
        let x = _mm512_max_ps(x, splat(EXP_LO));
        let shifted = fma(x, splat(LOG2E), splat(ROUND_MAGIC));
        let n = _mm512_sub_ps(shifted, splat(ROUND_MAGIC));
        let r = _mm512_fnmadd_ps(n, splat(LN2_HI), x);
        let r = _mm512_fnmadd_ps(n, splat(LN2_LO), r);
        let p = fma(splat(1.987_569_2e-4), r, splat(1.398_2e-3));
        let p = fma(p, r, splat(8.333_452e-3));
        let p = fma(p, r, splat(4.166_579_6e-2));
        let p = fma(p, r, splat(1.666_666_5e-1));
        let p = fma(p, r, splat(0.5));
        let er = _mm512_add_ps(fma(p, _mm512_mul_ps(r, r), r), splat(1.0));
        let n_int = _mm512_sub_epi32(
            _mm512_castps_si512(shifted),
            _mm512_set1_epi32(ROUND_MAGIC_BITS),
        );
        let scale = _mm512_slli_epi32::<23>(_mm512_add_epi32(n_int, _mm512_set1_epi32(127)));
        _mm512_mul_ps(er, _mm512_castsi512_ps(scale))
    }
}

/// `1 / d` for `d ∈ [1, 2]`: the 14-bit estimate and one Newton step (error below 2⁻²³).
#[inline(always)]
fn recip_1_2(d: __m512) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe {
        let r = _mm512_rcp14_ps(d);
        fma(_mm512_fnmadd_ps(d, r, splat(1.0)), r, r)
    }
}

/// Swish `x σ(x)`.
#[inline(always)]
pub fn swish(x: __m512) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe {
        let t = exp_nonpositive(neg_abs(x));
        let a = recip_1_2(_mm512_add_ps(splat(1.0), t));
        // σ(x) is a = 1/(1 + e^{-|x|}) for x ≥ 0 and t·a for x < 0.
        let negative = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(x, _mm512_setzero_ps());
        let s = _mm512_mask_mul_ps(a, negative, t, a);
        _mm512_mul_ps(x, s)
    }
}

/// `ln(1 + t)` for `t ∈ [0, 1]` ([`super::fastmath::ln_1p_unit`]).
#[inline(always)]
fn ln_1p_unit(t: __m512) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe {
        let big = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(t, splat(std::f32::consts::SQRT_2 - 1.0));
        let half_tm1 = _mm512_mul_ps(_mm512_sub_ps(t, splat(1.0)), splat(0.5));
        let f = _mm512_mask_blend_ps(big, t, half_tm1);
        let e = _mm512_maskz_mov_ps(big, splat(std::f32::consts::LN_2));
        let z = _mm512_mul_ps(f, f);
        let p = fma(splat(7.037_683_6e-2), f, splat(-1.151_461e-1));
        let p = fma(p, f, splat(1.167_699_9e-1));
        let p = fma(p, f, splat(-1.242_014_1e-1));
        let p = fma(p, f, splat(1.424_932_3e-1));
        let p = fma(p, f, splat(-1.666_805_8e-1));
        let p = fma(p, f, splat(2.000_071_4e-1));
        let p = fma(p, f, splat(-2.499_999_4e-1));
        let p = fma(p, f, splat(0.333_333_3));
        let y = fma(_mm512_mul_ps(f, z), p, _mm512_mul_ps(splat(-0.5), z));
        _mm512_add_ps(_mm512_add_ps(f, y), e)
    }
}

/// Softplus `ln(1 + eˣ) = max(x, 0) + ln(1 + e^{-|x|})`.
#[inline(always)]
pub fn softplus(x: __m512) -> __m512 {
    // SAFETY: as in `fma`.
    unsafe {
        let t = exp_nonpositive(neg_abs(x));
        let pos = _mm512_max_ps(x, _mm512_setzero_ps());
        _mm512_add_ps(pos, ln_1p_unit(t))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::fastmath;
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
    fn registers_agree_with_the_scalar_functions() {
        if level() < SimdLevel::Avx512 {
            return; // nothing to compare on this CPU; the scalar functions have their own tests
        }
        let mut xs: Vec<f32> = (0..=240_000).map(|i| -60.0 + i as f32 * 5e-4).collect();
        xs.extend([
            -1e30, -200.0, -88.0, -87.5, 0.0, -0.0, 1e-30, 88.0, 200.0, 1e30,
        ]);
        // SAFETY: the level check above guarantees AVX-512F.
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
}
