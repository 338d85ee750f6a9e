//! [`fastmath`](super::fastmath)'s swish and softplus (and their derivatives) on whole vector
//! registers, written once for every register type ([`Lanes`]: AVX-512's `__m512` in
//! [`fastmath512`](super::fastmath512), AVX2's `__m256` in [`fastmath256`](super::fastmath256)).
//!
//! The matrix kernels call these in their epilogues (a finished tile of `Z = Wᵀ·H + b` is
//! activated in registers before it is stored, so the activation costs no extra pass over
//! memory), and training's activation passes call the derivative forms, so on one CPU a forward
//! pass in training gives bit for bit what inference gives.
//!
//! The polynomials, constants and range reductions are `fastmath`'s; two things differ, both
//! for speed: every `a·b + c` is one fused multiply-add, and `1 / (1 + t)` is the CPU's
//! reciprocal estimate (14 bits on AVX-512, 12 on AVX2) refined by one Newton step (a division
//! costs as much as the rest of the swish put together). Results agree with `fastmath` to
//! within a few ulps (tested per register type).

use super::fastmath::{EXP_COEFFS, EXP_LO, LN_1P_COEFFS, LN2_HI, LN2_LO, LOG2E, ROUND_MAGIC};

/// The widest register's lanes (AVX-512's 16): buffers for a partial register hold this many.
pub const MAX_LANES: usize = 16;

/// The operations the activations need, on one register of `f32` lanes.
///
/// Implementations are `#[inline(always)]` wrappers of one or two intrinsics each, with no
/// `#[target_feature]` of their own: they inline into the kernels' and passes'
/// `#[target_feature]` functions, whose features cover the intrinsics (as every caller's
/// SAFETY comment states).
pub trait Lanes: Copy {
    /// Floats per register.
    const LANES: usize;
    /// The register at `p` (unaligned).
    ///
    /// # Safety
    /// `p` must be valid for reads of [`Lanes::LANES`] floats.
    unsafe fn load(p: *const f32) -> Self;
    /// Writes the register to `p` (unaligned).
    ///
    /// # Safety
    /// `p` must be valid for writes of [`Lanes::LANES`] floats.
    unsafe fn store(self, p: *mut f32);
    /// Every lane `v`.
    fn splat(v: f32) -> Self;
    fn add(self, b: Self) -> Self;
    fn sub(self, b: Self) -> Self;
    fn mul(self, b: Self) -> Self;
    /// `self · b + c` in one rounding.
    fn mul_add(self, b: Self, c: Self) -> Self;
    /// `c − self · b` in one rounding.
    fn neg_mul_add(self, b: Self, c: Self) -> Self;
    /// Lane-wise maximum; where either lane is NaN, `b`'s lane.
    fn max(self, b: Self) -> Self;
    /// `-|x|` (the sign bit set).
    fn neg_abs(self) -> Self;
    /// The reciprocal estimate (`rcp14` or `rcp`).
    fn recip_estimate(self) -> Self;
    /// `2ⁿ` for the integer `n` that `x · log₂e + ROUND_MAGIC` holds in its low mantissa bits
    /// (`self` is that sum).
    fn exp2_of_rounded(self) -> Self;
    /// `if_negative` where `self < 0`, else `otherwise` (NaN is not negative).
    fn where_negative(self, if_negative: Self, otherwise: Self) -> Self;
    /// `if_above` where `self > bound`, else `otherwise`.
    fn where_above(self, bound: Self, if_above: Self, otherwise: Self) -> Self;
}

/// `eˣ` for `x ≤ 0` (clamped below at −87, as [`super::fastmath::exp`]).
#[inline(always)]
fn exp_nonpositive<V: Lanes>(x: V) -> V {
    let x = x.max(V::splat(EXP_LO));
    let shifted = x.mul_add(V::splat(LOG2E), V::splat(ROUND_MAGIC));
    let n = shifted.sub(V::splat(ROUND_MAGIC));
    let r = n.neg_mul_add(V::splat(LN2_HI), x);
    let r = n.neg_mul_add(V::splat(LN2_LO), r);
    let [c0, rest @ ..] = EXP_COEFFS;
    let p = rest
        .iter()
        .fold(V::splat(c0), |p, &c| p.mul_add(r, V::splat(c)));
    let er = p.mul_add(r.mul(r), r).add(V::splat(1.0));
    er.mul(shifted.exp2_of_rounded())
}

/// `1 / d` for `d ∈ [1, 2]`: the estimate and one Newton step.
#[inline(always)]
fn recip_1_2<V: Lanes>(d: V) -> V {
    let r = d.recip_estimate();
    d.neg_mul_add(r, V::splat(1.0)).mul_add(r, r)
}

/// `(σ(x), σ(−x))` given `t = e^{−|x|}` ([`super::fastmath`]'s pair): the complement is computed
/// directly, not as `1 − σ`, which would cancel for large `x`.
#[inline(always)]
fn sigmoid_pair<V: Lanes>(x: V, t: V) -> (V, V) {
    let a = recip_1_2(V::splat(1.0).add(t));
    let b = t.mul(a);
    (x.where_negative(b, a), x.where_negative(a, b))
}

/// Swish `x σ(x)`.
#[inline(always)]
pub fn swish<V: Lanes>(x: V) -> V {
    swish_d2(x).0
}

/// `ln(1 + t)` for `t ∈ [0, 1]` ([`super::fastmath::ln_1p_unit`]).
#[inline(always)]
fn ln_1p_unit<V: Lanes>(t: V) -> V {
    let bound = V::splat(std::f32::consts::SQRT_2 - 1.0);
    let half_tm1 = t.sub(V::splat(1.0)).mul(V::splat(0.5));
    let f = t.where_above(bound, half_tm1, t);
    let e = t.where_above(bound, V::splat(std::f32::consts::LN_2), V::splat(0.0));
    let z = f.mul(f);
    let [c0, rest @ ..] = LN_1P_COEFFS;
    let p = rest
        .iter()
        .fold(V::splat(c0), |p, &c| p.mul_add(f, V::splat(c)));
    let y = f.mul(z).mul_add(p, V::splat(-0.5).mul(z));
    f.add(y).add(e)
}

/// Softplus `ln(1 + eˣ) = max(x, 0) + ln(1 + e^{-|x|})`. A NaN input gives NaN.
#[inline(always)]
pub fn softplus<V: Lanes>(x: V) -> V {
    softplus_d2(x).0
}

/// Swish and its first two derivatives, as [`super::fastmath::swish_d2`]: `(x σ, σ (1 + x (1 −
/// σ)), σ (1 − σ) (2 + x (1 − 2σ)))`.
#[inline(always)]
pub fn swish_d2<V: Lanes>(x: V) -> (V, V, V) {
    let (s, c) = sigmoid_pair(x, exp_nonpositive(x.neg_abs()));
    let d1 = s.mul(x.mul_add(c, V::splat(1.0)));
    let d2 = s.mul(c).mul(x.mul_add(c.sub(s), V::splat(2.0)));
    (x.mul(s), d1, d2)
}

/// Softplus and its first two derivatives, as [`super::fastmath::softplus_d2`]: `(ln(1 + eˣ),
/// σ(x), σ(x) σ(−x))`. A NaN input gives a NaN value, so that a diverging training step shows
/// in its loss.
#[inline(always)]
pub fn softplus_d2<V: Lanes>(x: V) -> (V, V, V) {
    let t = exp_nonpositive(x.neg_abs());
    // `max` returns its second operand when either is NaN.
    let pos = V::splat(0.0).max(x);
    let (s, c) = sigmoid_pair(x, t);
    (pos.add(ln_1p_unit(t)), s, s.mul(c))
}
