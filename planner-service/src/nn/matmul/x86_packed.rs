//! The AVX-512 kernel for packed layers (see [`packed`](super::packed)).
//!
//! A kernel owns up to 6 rows × `NP` 16-float panels of `C` in registers (24 accumulators and
//! four panel registers for `NP = 4`), starts them at the bias, and per depth step loads one row
//! segment of `Y` per panel and broadcasts the block's 6 adjacent packed weights — constant
//! offsets from one pointer that advances by the block height. 6 × 64 was measured against
//! 12 × 32 and 8 × 48 (same register budget): it needs half the broadcasts of 12 × 32 per
//! multiply-add and came out a few percent ahead on the 200–500 wide layers. The finished tile
//! is activated in registers and stored with masks, so any width works. As in `x86.rs`, rows
//! are unrolled by a macro and pointer arithmetic is wrapping, for the dev profile's sake.
//!
//! The macro makes each tile twice: in f32 (one FMA per accumulator and depth step) and in bf16
//! (one `VDPBF16PS` per accumulator and *pair* of depth steps, with the Y panel and the broadcast
//! weight each carrying two bf16 values per 32-bit lane). Both share the epilogue, which stores
//! f32 rows or, for a next layer in bf16, converts pairs of rows to bf16 pairs in registers. The
//! two bodies differ only in their load and multiply instructions; they stay two macro arms
//! rather than one generic kernel because the per-type helpers would need `#[target_feature]`,
//! which rules out the forced inlining the inner loop depends on.

use super::x86::{load_scalar, mask16};
use crate::nn::activation::Activation;
use crate::nn::aligned::LANES;
use crate::nn::fastmath512::{softplus, swish};
use std::arch::x86_64::*;

/// One packed product in pointer form; every extent was checked by `matmul_packed`.
pub(super) struct PackedRaw {
    pub m: usize,
    pub n: usize,
    /// Depth steps: `k` for f32 weights, `⌈k/2⌉` for bf16 pairs.
    pub steps: usize,
    pub a: *const f32,
    /// `a` and `y` hold bf16 pairs (see `Encoding::Bf16Pairs`).
    pub bf16_weights: bool,
    pub y: *const f32,
    pub ld_y: usize,
    pub c: *mut f32,
    pub ld_c: usize,
    /// Write `C` as bf16 pairs: block rows `2q, 2q + 1` go to storage row `i0/2 + q`.
    pub bf16_out: bool,
    pub bias: *const f32,
    pub act: Option<Activation>,
}

/// Word order that interleaves the two halves of `VCVTNE2PS2BF16(hi, lo)` (`lo₀…lo₁₅ hi₀…hi₁₅`)
/// into pairs `lo_j | hi_j << 16`.
const INTERLEAVE: [i16; 32] = {
    let mut idx = [0i16; 32];
    let mut j = 0;
    while j < 16 {
        idx[2 * j] = j as i16;
        idx[2 * j + 1] = 16 + j as i16;
        j += 1;
    }
    idx
};

/// Stores two finished rows of 16 lanes as one row of bf16 pairs.
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn store_pairs(c: *mut f32, mask: __mmask16, lo: __m512, hi: __m512) {
    // SAFETY: the caller passes a row segment valid for the masked lanes.
    unsafe {
        let halves: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
        let idx = _mm512_loadu_si512(INTERLEAVE.as_ptr().cast());
        let pairs = _mm512_permutexvar_epi16(idx, halves);
        _mm512_mask_storeu_epi32(c.cast::<i32>(), mask, pairs);
    }
}

/// Activates the finished accumulators and stores them, as f32 rows or as bf16 pairs.
///
/// The accumulators are first copied out whole row by row (constant indices only), and the
/// activation and stores loop over that copy. Indexing `acc` itself with a loop variable (the
/// pair loop, or an activation loop LLVM does not unroll at the dev profile's opt-level)
/// makes LLVM keep `acc` on the stack and store every accumulator after each FMA of the k
/// loop: that halved the kernel's rate (39 % of the f32 peak against 74 % for the general
/// kernel on 200-wide layers, `bench kernel`).
macro_rules! epilogue {
    ($raw:ident, $acc:ident, $mask:ident, $i0:ident, $p0:ident, $np:ident, $mr:ident; $($r:literal)+) => {
        let mut tile = [[_mm512_setzero_ps(); $np]; $mr];
        $( tile[$r] = $acc[$r]; )+
        match $raw.act {
            None => {}
            Some(Activation::Swish) => {
                for v in tile.iter_mut().flatten() { *v = swish(*v); }
            }
            Some(Activation::Softplus) => {
                for v in tile.iter_mut().flatten() { *v = softplus(*v); }
            }
        }
        let ld_c = $raw.ld_c;
        if $raw.bf16_out {
            // SAFETY: `bf16_out` is only set on CPUs with AVX-512 BW and BF16.
            let c = $raw.c.wrapping_add($i0 / 2 * ld_c + $p0 * LANES);
            for q in (0..$mr).step_by(2) {
                for j in 0..$np {
                    let hi = if q + 1 < $mr { tile[q + 1][j] } else { _mm512_setzero_ps() };
                    store_pairs(c.wrapping_add(q / 2 * ld_c + j * LANES), $mask[j], tile[q][j], hi);
                }
            }
        } else {
            let c = $raw.c.wrapping_add($i0 * ld_c + $p0 * LANES);
            for (r, row) in tile.iter().enumerate() {
                for j in 0..$np {
                    _mm512_mask_storeu_ps(c.wrapping_add(r * ld_c + j * LANES), $mask[j], row[j]);
                }
            }
        }
    };
}

macro_rules! packed512 {
    ($name:ident, $bf16:ident; $($r:literal)+) => {
        /// An f32 tile of the listed rows × `NP` panels of the block starting at row `i0`.
        #[inline]
        #[target_feature(enable = "avx512f")]
        unsafe fn $name<const NP: usize>(raw: &PackedRaw, i0: usize, p0: usize) {
            const MR: usize = [$($r),+].len();
            let PackedRaw { n, steps, ld_y, .. } = *raw;
            let mask: [__mmask16; NP] = std::array::from_fn(|j| mask16(n, (p0 + j) * LANES));
            let mut ap = raw.a.wrapping_add(i0 * steps);
            let mut yp = raw.y.wrapping_add(p0 * LANES);
            // SAFETY: the driver passes only blocks and panels inside the checked extents;
            // masked lanes are never touched.
            unsafe {
                let mut acc = [[_mm512_setzero_ps(); NP]; MR];
                $( acc[$r] = [_mm512_set1_ps(load_scalar(raw.bias.wrapping_add(i0 + $r))); NP]; )+
                for _ in 0..steps {
                    let w: [__m512; NP] = std::array::from_fn(|j| _mm512_maskz_loadu_ps(mask[j], yp.wrapping_add(j * LANES)));
                    $(
                        let xv = _mm512_set1_ps(load_scalar(ap.wrapping_add($r)));
                        for j in 0..NP {
                            acc[$r][j] = _mm512_fmadd_ps(xv, w[j], acc[$r][j]);
                        }
                    )+
                    ap = ap.wrapping_add(MR);
                    yp = yp.wrapping_add(ld_y);
                }
                epilogue!(raw, acc, mask, i0, p0, NP, MR; $($r)+);
            }
        }

        /// The same tile from bf16 pairs: one `VDPBF16PS` per accumulator does two depth steps.
        #[inline]
        #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
        unsafe fn $bf16<const NP: usize>(raw: &PackedRaw, i0: usize, p0: usize) {
            const MR: usize = [$($r),+].len();
            let PackedRaw { n, steps, ld_y, .. } = *raw;
            let mask: [__mmask16; NP] = std::array::from_fn(|j| mask16(n, (p0 + j) * LANES));
            let mut ap = raw.a.wrapping_add(i0 * steps);
            let mut yp = raw.y.wrapping_add(p0 * LANES);
            // SAFETY: as for the f32 tile; a pair word is loaded and broadcast as 32 raw bits.
            unsafe {
                let mut acc = [[_mm512_setzero_ps(); NP]; MR];
                $( acc[$r] = [_mm512_set1_ps(load_scalar(raw.bias.wrapping_add(i0 + $r))); NP]; )+
                for _ in 0..steps {
                    let w: [__m512bh; NP] = std::array::from_fn(|j| {
                        std::mem::transmute(_mm512_maskz_loadu_ps(mask[j], yp.wrapping_add(j * LANES)))
                    });
                    $(
                        let xv: __m512bh = std::mem::transmute(_mm512_set1_ps(load_scalar(ap.wrapping_add($r))));
                        for j in 0..NP {
                            acc[$r][j] = _mm512_dpbf16_ps(acc[$r][j], xv, w[j]);
                        }
                    )+
                    ap = ap.wrapping_add(MR);
                    yp = yp.wrapping_add(ld_y);
                }
                epilogue!(raw, acc, mask, i0, p0, NP, MR; $($r)+);
            }
        }
    };
}

packed512!(p512_1, bf16_1; 0);
packed512!(p512_2, bf16_2; 0 1);
packed512!(p512_3, bf16_3; 0 1 2);
packed512!(p512_4, bf16_4; 0 1 2 3);
packed512!(p512_5, bf16_5; 0 1 2 3 4);
packed512!(p512_6, bf16_6; 0 1 2 3 4 5);

/// Panels per full tile.
const TILE_PANELS: usize = 4;

/// Runs the tile kernel for a block of `mr ≤ 6` rows and `NP` panels.
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn tile<const NP: usize>(mr: usize, raw: &PackedRaw, i0: usize, p: usize) {
    // SAFETY: forwarded from the caller; the bf16 tiles run only when `matmul_packed` checked
    // for AVX-512 BF16.
    unsafe {
        match (raw.bf16_weights, mr) {
            (false, 1) => p512_1::<NP>(raw, i0, p),
            (false, 2) => p512_2::<NP>(raw, i0, p),
            (false, 3) => p512_3::<NP>(raw, i0, p),
            (false, 4) => p512_4::<NP>(raw, i0, p),
            (false, 5) => p512_5::<NP>(raw, i0, p),
            (false, 6) => p512_6::<NP>(raw, i0, p),
            (true, 1) => bf16_1::<NP>(raw, i0, p),
            (true, 2) => bf16_2::<NP>(raw, i0, p),
            (true, 3) => bf16_3::<NP>(raw, i0, p),
            (true, 4) => bf16_4::<NP>(raw, i0, p),
            (true, 5) => bf16_5::<NP>(raw, i0, p),
            (true, 6) => bf16_6::<NP>(raw, i0, p),
            _ => unreachable!("row block of {mr}"),
        }
    }
}

/// Block by block (each block's packed weights stay in L1 while every panel of `Y` passes
/// through), four panels per tile and narrower tiles for the rest.
///
/// # Safety
/// The CPU must support AVX-512F and every extent of `raw` must be valid.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn drive(raw: &PackedRaw) {
    let panels = raw.n.div_ceil(LANES);
    for i0 in (0..raw.m).step_by(super::packed::PACK_ROWS) {
        let mr = super::packed::PACK_ROWS.min(raw.m - i0);
        // A lone last panel would make a tile with one multiply-add per broadcast: end on
        // 3 + 2 panels instead of 4 + 1 where there are five or more.
        let full_tiles = match panels % TILE_PANELS {
            1 if panels > TILE_PANELS => panels / TILE_PANELS - 1,
            _ => panels / TILE_PANELS,
        };
        let mut p = 0;
        // SAFETY (every call): the block and the panels named are inside the extents.
        for _ in 0..full_tiles {
            unsafe { tile::<TILE_PANELS>(mr, raw, i0, p) };
            p += TILE_PANELS;
        }
        match panels - p {
            0 => {}
            1 => unsafe { tile::<1>(mr, raw, i0, p) },
            2 => unsafe { tile::<2>(mr, raw, i0, p) },
            3 => unsafe { tile::<3>(mr, raw, i0, p) },
            5 => unsafe {
                tile::<3>(mr, raw, i0, p);
                tile::<2>(mr, raw, i0, p + 3);
            },
            left => unreachable!("{left} panels left"),
        }
    }
}
