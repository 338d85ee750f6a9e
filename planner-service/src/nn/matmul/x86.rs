//! Register-blocked AVX-512 and AVX2 kernels.
//!
//! A kernel owns a block of `C` — up to 12 rows (AVX-512) or 6 rows (AVX2) by two 16-float
//! panels (one on AVX2) — in registers for the whole depth: per step it loads one row segment of
//! `Y` per panel and broadcasts one element of `X` per row, then does one fused multiply-add per
//! accumulator. 24 accumulators + 2 panel registers fit AVX-512's 32 registers; 12 + 2 fit
//! AVX2's 16. Partial panels use masked loads and stores, so no shape needs padding.
//!
//! The AVX2 kernel also serves the packed inference layers on CPUs without AVX-512 (see
//! `packed.rs`): it then activates the finished registers before storing them (`Raw::act`,
//! [`lanes`]), and since a packed block's weights for one depth step are adjacent
//! (`rs_x = 1`) it is compiled a second time with that stride a constant, so the row
//! broadcasts take constant offsets instead of one pointer addition each (5 of the 28
//! instructions of a depth step in the compiled loop).
//!
//! The row loop is unrolled by a macro (one statement per row) rather than left to LLVM: at the
//! dev profile's opt-level 2 it does not unroll 12 iterations and the accumulators then live in
//! memory (3× slower). Pointer arithmetic is wrapping and every load is an intrinsic because
//! the dev profile keeps debug assertions on, whose overflow and dereference checks would
//! cost more than the arithmetic.

use super::{Raw, RawInit};
use crate::nn::Activation;
use crate::nn::aligned::LANES;
use crate::nn::lanes;
use std::arch::x86_64::*;

/// Rows per AVX-512 block.
const MR512: usize = 12;
/// Rows per AVX2 block.
const MR256: usize = 6;

/// One element, loaded without the dev profile's raw-pointer dereference checks.
#[inline(always)]
pub(super) unsafe fn load_scalar(p: *const f32) -> f32 {
    // SAFETY: the caller guarantees `p` is valid for reads.
    unsafe { _mm_cvtss_f32(_mm_load_ss(p)) }
}

/// Mask of the valid lanes of the panel starting at column `col` of an `n`-column matrix.
#[inline(always)]
pub(super) fn mask16(n: usize, col: usize) -> __mmask16 {
    let left = n.saturating_sub(col);
    if left >= LANES {
        0xFFFF
    } else {
        ((1u32 << left) - 1) as __mmask16
    }
}

macro_rules! kernel512 {
    ($name:ident; $($r:literal)+) => {
        /// A block of the listed rows × `NP` panels (see the module docs).
        #[inline]
        #[target_feature(enable = "avx512f")]
        unsafe fn $name<const NP: usize>(raw: &Raw, i0: usize, p0: usize) {
            let Raw { n, k, rs_x, cs_x, ld_y, ld_c, .. } = *raw;
            let mask: [__mmask16; NP] = std::array::from_fn(|j| mask16(n, (p0 + j) * LANES));
            let mut xp = raw.x.wrapping_add(i0.wrapping_mul(rs_x));
            let mut yp = raw.y.wrapping_add(p0 * LANES);
            let c = raw.c.wrapping_add(i0.wrapping_mul(ld_c).wrapping_add(p0 * LANES));
            // SAFETY: the driver passes only rows and panels inside the checked extents, and
            // masked lanes are never touched.
            unsafe {
                let mut acc = [[_mm512_setzero_ps(); NP]; [$($r),+].len()];
                match raw.init {
                    RawInit::Zero => {}
                    RawInit::Accumulate => {
                        $( for j in 0..NP {
                            acc[$r][j] = _mm512_maskz_loadu_ps(mask[j], c.wrapping_add(($r as usize).wrapping_mul(ld_c) + j * LANES));
                        } )+
                    }
                    RawInit::RowBias(b) => {
                        $( acc[$r] = [_mm512_set1_ps(load_scalar(b.wrapping_add(i0 + $r))); NP]; )+
                    }
                    RawInit::ColBias(b) => {
                        let bias: [__m512; NP] = std::array::from_fn(|j| _mm512_maskz_loadu_ps(mask[j], b.wrapping_add((p0 + j) * LANES)));
                        $( acc[$r] = bias; )+
                    }
                }
                for _ in 0..k {
                    let w: [__m512; NP] = std::array::from_fn(|j| _mm512_maskz_loadu_ps(mask[j], yp.wrapping_add(j * LANES)));
                    $(
                        let xv = _mm512_set1_ps(load_scalar(xp.wrapping_add(($r as usize).wrapping_mul(rs_x))));
                        for j in 0..NP {
                            acc[$r][j] = _mm512_fmadd_ps(xv, w[j], acc[$r][j]);
                        }
                    )+
                    xp = xp.wrapping_add(cs_x);
                    yp = yp.wrapping_add(ld_y);
                }
                $( for j in 0..NP {
                    _mm512_mask_storeu_ps(c.wrapping_add(($r as usize).wrapping_mul(ld_c) + j * LANES), mask[j], acc[$r][j]);
                } )+
            }
        }
    };
}

kernel512!(k512_1; 0);
kernel512!(k512_2; 0 1);
kernel512!(k512_3; 0 1 2);
kernel512!(k512_4; 0 1 2 3);
kernel512!(k512_5; 0 1 2 3 4);
kernel512!(k512_6; 0 1 2 3 4 5);
kernel512!(k512_7; 0 1 2 3 4 5 6);
kernel512!(k512_8; 0 1 2 3 4 5 6 7);
kernel512!(k512_9; 0 1 2 3 4 5 6 7 8);
kernel512!(k512_10; 0 1 2 3 4 5 6 7 8 9);
kernel512!(k512_11; 0 1 2 3 4 5 6 7 8 9 10);
kernel512!(k512_12; 0 1 2 3 4 5 6 7 8 9 10 11);

/// Runs the AVX-512 kernel for a block of `mr ≤ 12` rows and `NP` panels.
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn block512<const NP: usize>(mr: usize, raw: &Raw, i: usize, p: usize) {
    // SAFETY: forwarded from the caller.
    unsafe {
        match mr {
            1 => k512_1::<NP>(raw, i, p),
            2 => k512_2::<NP>(raw, i, p),
            3 => k512_3::<NP>(raw, i, p),
            4 => k512_4::<NP>(raw, i, p),
            5 => k512_5::<NP>(raw, i, p),
            6 => k512_6::<NP>(raw, i, p),
            7 => k512_7::<NP>(raw, i, p),
            8 => k512_8::<NP>(raw, i, p),
            9 => k512_9::<NP>(raw, i, p),
            10 => k512_10::<NP>(raw, i, p),
            11 => k512_11::<NP>(raw, i, p),
            12 => k512_12::<NP>(raw, i, p),
            _ => unreachable!("row block of {mr}"),
        }
    }
}

/// # Safety
/// The CPU must support AVX-512F and every extent of `raw` must be valid.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn drive_avx512(raw: &Raw) {
    assert!(
        raw.act.is_none(),
        "the AVX-512 general kernel has no activation epilogue"
    );
    let panels = raw.n.div_ceil(LANES);
    let mut i = 0;
    while i < raw.m {
        let mr = MR512.min(raw.m - i);
        let mut p = 0;
        // SAFETY (both calls): rows `i..i + mr` and the panels named are inside the extents.
        while p + 2 <= panels {
            unsafe { block512::<2>(mr, raw, i, p) };
            p += 2;
        }
        if p < panels {
            unsafe { block512::<1>(mr, raw, i, p) };
        }
        i += mr;
    }
}

/// Lane mask of the 8-float half starting at column `col` (`maskload`/`maskstore` form).
#[inline]
#[target_feature(enable = "avx2")]
fn mask8(n: usize, col: usize) -> __m256i {
    let left = n.saturating_sub(col).min(8) as i32;
    _mm256_cmpgt_epi32(
        _mm256_set1_epi32(left),
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
    )
}

macro_rules! kernel256 {
    ($name:ident; $($r:literal)+) => {
        /// A block of the listed rows × one panel; `MASKED` for the last, partial panel.
        #[inline]
        #[target_feature(enable = "avx2,fma")]
        unsafe fn $name<const MASKED: bool, const UNIT_RS: bool>(raw: &Raw, i0: usize, p0: usize) {
            let Raw { n, k, rs_x, cs_x, ld_y, ld_c, .. } = *raw;
            let rs_x = if UNIT_RS { 1 } else { rs_x };
            let col = p0 * LANES;
            let (m0, m1) = (mask8(n, col), mask8(n, col + 8));
            let mut xp = raw.x.wrapping_add(i0.wrapping_mul(rs_x));
            let mut yp = raw.y.wrapping_add(col);
            let c = raw.c.wrapping_add(i0.wrapping_mul(ld_c).wrapping_add(col));
            // SAFETY: the driver passes only rows and panels inside the checked extents, and
            // masked lanes are never touched.
            unsafe {
                let load = |p: *const f32, m: __m256i| if MASKED { _mm256_maskload_ps(p, m) } else { _mm256_loadu_ps(p) };
                let mut acc = [[_mm256_setzero_ps(); 2]; [$($r),+].len()];
                match raw.init {
                    RawInit::Zero => {}
                    RawInit::Accumulate => {
                        $(
                            let row = c.wrapping_add(($r as usize).wrapping_mul(ld_c));
                            acc[$r] = [load(row, m0), load(row.wrapping_add(8), m1)];
                        )+
                    }
                    RawInit::RowBias(b) => {
                        $( acc[$r] = [_mm256_set1_ps(load_scalar(b.wrapping_add(i0 + $r))); 2]; )+
                    }
                    RawInit::ColBias(b) => {
                        let bias = [load(b.wrapping_add(col), m0), load(b.wrapping_add(col + 8), m1)];
                        $( acc[$r] = bias; )+
                    }
                }
                for _ in 0..k {
                    let (w0, w1) = (load(yp, m0), load(yp.wrapping_add(8), m1));
                    $(
                        let xv = _mm256_set1_ps(load_scalar(xp.wrapping_add(($r as usize).wrapping_mul(rs_x))));
                        acc[$r][0] = _mm256_fmadd_ps(xv, w0, acc[$r][0]);
                        acc[$r][1] = _mm256_fmadd_ps(xv, w1, acc[$r][1]);
                    )+
                    xp = xp.wrapping_add(cs_x);
                    yp = yp.wrapping_add(ld_y);
                }
                if let Some(act) = raw.act {
                    $( acc[$r] = [activate(act, acc[$r][0]), activate(act, acc[$r][1])]; )+
                }
                $(
                    let row = c.wrapping_add(($r as usize).wrapping_mul(ld_c));
                    if MASKED {
                        _mm256_maskstore_ps(row, m0, acc[$r][0]);
                        _mm256_maskstore_ps(row.wrapping_add(8), m1, acc[$r][1]);
                    } else {
                        _mm256_storeu_ps(row, acc[$r][0]);
                        _mm256_storeu_ps(row.wrapping_add(8), acc[$r][1]);
                    }
                )+
            }
        }
    };
}

kernel256!(k256_1; 0);
kernel256!(k256_2; 0 1);
kernel256!(k256_3; 0 1 2);
kernel256!(k256_4; 0 1 2 3);
kernel256!(k256_5; 0 1 2 3 4);
kernel256!(k256_6; 0 1 2 3 4 5);

/// A hidden layer's activation of one register ([`lanes`]' on `__m256`; masked-off lanes hold
/// zeros, which activate to finite values that are never stored).
#[inline(always)]
fn activate(act: Activation, v: __m256) -> __m256 {
    match act {
        Activation::Swish => lanes::swish(v),
        Activation::Softplus => lanes::softplus(v),
    }
}

/// Runs the AVX2 kernel for a block of `mr ≤ 6` rows and one panel.
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn block256<const MASKED: bool, const UNIT_RS: bool>(
    mr: usize,
    raw: &Raw,
    i: usize,
    p: usize,
) {
    // SAFETY: forwarded from the caller.
    unsafe {
        match mr {
            1 => k256_1::<MASKED, UNIT_RS>(raw, i, p),
            2 => k256_2::<MASKED, UNIT_RS>(raw, i, p),
            3 => k256_3::<MASKED, UNIT_RS>(raw, i, p),
            4 => k256_4::<MASKED, UNIT_RS>(raw, i, p),
            5 => k256_5::<MASKED, UNIT_RS>(raw, i, p),
            6 => k256_6::<MASKED, UNIT_RS>(raw, i, p),
            _ => unreachable!("row block of {mr}"),
        }
    }
}

/// # Safety
/// The CPU must support AVX2 and FMA and every extent of `raw` must be valid.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn drive_avx2(raw: &Raw) {
    let full = raw.n / LANES;
    let mut i = 0;
    while i < raw.m {
        let mr = MR256.min(raw.m - i);
        // SAFETY (both calls): rows `i..i + mr` and the panels named are inside the extents.
        if raw.rs_x == 1 {
            for p in 0..full {
                unsafe { block256::<false, true>(mr, raw, i, p) };
            }
            if !raw.n.is_multiple_of(LANES) {
                unsafe { block256::<true, true>(mr, raw, i, full) };
            }
        } else {
            for p in 0..full {
                unsafe { block256::<false, false>(mr, raw, i, p) };
            }
            if !raw.n.is_multiple_of(LANES) {
                unsafe { block256::<true, false>(mr, raw, i, full) };
            }
        }
        i += mr;
    }
}

/// Transposes the 8 × 8 block at `src` (row stride `ld_src`) into `dst` (row stride `ld_dst`).
///
/// # Safety
/// The CPU must support AVX; both blocks must be inside their buffers.
#[inline]
#[target_feature(enable = "avx")]
unsafe fn transpose8x8(src: *const f32, ld_src: usize, dst: *mut f32, ld_dst: usize) {
    // SAFETY: the caller guarantees both 8 × 8 blocks are in bounds.
    unsafe {
        let r: [__m256; 8] = std::array::from_fn(|k| _mm256_loadu_ps(src.wrapping_add(k * ld_src)));
        // Interleave pairs of rows, then pairs of pairs, then swap 128-bit halves.
        let t = [
            _mm256_unpacklo_ps(r[0], r[1]),
            _mm256_unpackhi_ps(r[0], r[1]),
            _mm256_unpacklo_ps(r[2], r[3]),
            _mm256_unpackhi_ps(r[2], r[3]),
            _mm256_unpacklo_ps(r[4], r[5]),
            _mm256_unpackhi_ps(r[4], r[5]),
            _mm256_unpacklo_ps(r[6], r[7]),
            _mm256_unpackhi_ps(r[6], r[7]),
        ];
        let u = [
            _mm256_shuffle_ps::<0x44>(t[0], t[2]),
            _mm256_shuffle_ps::<0xEE>(t[0], t[2]),
            _mm256_shuffle_ps::<0x44>(t[1], t[3]),
            _mm256_shuffle_ps::<0xEE>(t[1], t[3]),
            _mm256_shuffle_ps::<0x44>(t[4], t[6]),
            _mm256_shuffle_ps::<0xEE>(t[4], t[6]),
            _mm256_shuffle_ps::<0x44>(t[5], t[7]),
            _mm256_shuffle_ps::<0xEE>(t[5], t[7]),
        ];
        let out = [
            _mm256_permute2f128_ps::<0x20>(u[0], u[4]),
            _mm256_permute2f128_ps::<0x20>(u[1], u[5]),
            _mm256_permute2f128_ps::<0x20>(u[2], u[6]),
            _mm256_permute2f128_ps::<0x20>(u[3], u[7]),
            _mm256_permute2f128_ps::<0x31>(u[0], u[4]),
            _mm256_permute2f128_ps::<0x31>(u[1], u[5]),
            _mm256_permute2f128_ps::<0x31>(u[2], u[6]),
            _mm256_permute2f128_ps::<0x31>(u[3], u[7]),
        ];
        for (k, v) in out.iter().enumerate() {
            _mm256_storeu_ps(dst.wrapping_add(k * ld_dst), *v);
        }
    }
}

/// The whole 8 × 8 blocks of a transpose (`rows8 × cols8` of them); the caller does the
/// ragged edges.
///
/// # Safety
/// The CPU must support AVX; the extents must have been checked by `transpose`.
#[target_feature(enable = "avx")]
pub(super) unsafe fn transpose_blocks(
    src: *const f32,
    ld_src: usize,
    dst: *mut f32,
    ld_dst: usize,
    rows8: usize,
    cols8: usize,
) {
    for bi in 0..rows8 {
        for bj in 0..cols8 {
            let (i, j) = (bi * 8, bj * 8);
            // SAFETY: block (i, j) of the source and (j, i) of the destination are in bounds.
            unsafe {
                transpose8x8(
                    src.wrapping_add(i * ld_src + j),
                    ld_src,
                    dst.wrapping_add(j * ld_dst + i),
                    ld_dst,
                )
            };
        }
    }
}
