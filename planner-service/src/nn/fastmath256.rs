//! AVX2 registers for the matrix kernel's epilogue and training's activation passes on CPUs
//! without AVX-512: the [`Lanes`] operations on `__m256`, so [`lanes`](super::lanes)' swish and
//! softplus run 8 lanes at a time there, as they run 16 on AVX-512.
//!
//! Why: on such CPUs the activation used to be a second pass over each stored block, compiled
//! from the scalar code, which multiplies and adds in separate roundings and divides for
//! `1 / (1 + t)`; a `perf record` of a half-cheetah PETS plan on an AMD Zen 3 (AVX2 only) put
//! 16 % of its samples in that pass against 73 % in the matrix kernel.

use super::fastmath::ROUND_MAGIC_BITS;
use super::lanes::Lanes;
use std::arch::x86_64::*;

// SAFETY (every intrinsic in this file): the functions are `inline(always)` into
// `#[target_feature(enable = "avx2,fma")]` code (the kernel's and passes' entry points check
// the CPU first), which covers each intrinsic's features.
impl Lanes for __m256 {
    const LANES: usize = 8;
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        // SAFETY: the caller guarantees `p` is valid for 8 floats.
        unsafe { _mm256_loadu_ps(p) }
    }
    #[inline(always)]
    unsafe fn store(self, p: *mut f32) {
        // SAFETY: the caller guarantees `p` is valid for 8 floats.
        unsafe { _mm256_storeu_ps(p, self) }
    }
    #[inline(always)]
    fn splat(v: f32) -> Self {
        unsafe { _mm256_set1_ps(v) }
    }
    #[inline(always)]
    fn add(self, b: Self) -> Self {
        unsafe { _mm256_add_ps(self, b) }
    }
    #[inline(always)]
    fn sub(self, b: Self) -> Self {
        unsafe { _mm256_sub_ps(self, b) }
    }
    #[inline(always)]
    fn mul(self, b: Self) -> Self {
        unsafe { _mm256_mul_ps(self, b) }
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        unsafe { _mm256_fmadd_ps(self, b, c) }
    }
    #[inline(always)]
    fn neg_mul_add(self, b: Self, c: Self) -> Self {
        unsafe { _mm256_fnmadd_ps(self, b, c) }
    }
    #[inline(always)]
    fn max(self, b: Self) -> Self {
        unsafe { _mm256_max_ps(self, b) }
    }
    #[inline(always)]
    fn neg_abs(self) -> Self {
        unsafe { _mm256_or_ps(self, _mm256_set1_ps(-0.0)) }
    }
    #[inline(always)]
    fn recip_estimate(self) -> Self {
        unsafe { _mm256_rcp_ps(self) }
    }
    #[inline(always)]
    fn exp2_of_rounded(self) -> Self {
        unsafe {
            let n = _mm256_sub_epi32(
                _mm256_castps_si256(self),
                _mm256_set1_epi32(ROUND_MAGIC_BITS as i32),
            );
            _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(
                n,
                _mm256_set1_epi32(127),
            )))
        }
    }
    #[inline(always)]
    fn where_negative(self, if_negative: Self, otherwise: Self) -> Self {
        unsafe {
            let negative = _mm256_cmp_ps::<_CMP_LT_OQ>(self, _mm256_setzero_ps());
            _mm256_blendv_ps(otherwise, if_negative, negative)
        }
    }
    #[inline(always)]
    fn where_above(self, bound: Self, if_above: Self, otherwise: Self) -> Self {
        unsafe {
            let above = _mm256_cmp_ps::<_CMP_GT_OQ>(self, bound);
            _mm256_blendv_ps(otherwise, if_above, above)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::fastmath;
    use crate::nn::lanes::{softplus, swish};
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
        let (sw, sp) = unsafe { (map(&xs, swish::<__m256>), map(&xs, softplus::<__m256>)) };
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
        let (sw, sp) = unsafe { (map(&xs, swish::<__m256>), map(&xs, softplus::<__m256>)) };
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
