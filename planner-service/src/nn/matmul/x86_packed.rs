//! The AVX-512 kernel for packed layers (see [`packed`](super::packed)).
//!
//! A tile keeps a block of `C` in registers for the whole depth, starts it at the bias, and per
//! depth step loads one row segment of `Y` per 16-float panel and broadcasts the block's
//! adjacent packed weights — constant offsets from one pointer that advances by the block
//! height. The finished tile is activated in registers and stored with masks, so any width
//! works. As in `x86.rs`, rows are unrolled by a macro and pointer arithmetic is wrapping, for
//! the dev profile's sake.
//!
//! The two encodings use different tiles, each the faster of the two 24-accumulator shapes
//! for it (`bench kernel`, CPU time, best batches on the 200–500 wide layers):
//! - **f32: 12 rows × 2 panels** (one FMA per accumulator and depth step). 6 × 4 panels needs
//!   half the broadcasts but streams twice the `Y` cache lines per step (4 against 2 per 24
//!   FMAs, from L2 on these layers: a row of blocks passes over all of `Y` before the next
//!   block comes back to a panel). Measured: 6 × 64 ran the fused layers at 69–81 % of the f32
//!   peak (76–87 % in a local build with the activation switched off); 12 × 32 runs them at
//!   77–89 % (best batches of two runs, the second on a more loaded machine).
//! - **bf16: 6 rows × 4 panels** (one `VDPBF16PS` per accumulator and *pair* of depth steps,
//!   the `Y` panel and the broadcast weight each carrying two bf16 values per 32-bit lane), and
//!   6 rows × 3 panels where a row of panels does not divide by 4. With the activation switched
//!   off (a local build) its layers ran at 90–100 % of the bf16 peak; what the fused layers lose
//!   is the activation, which cost as much as in f32 against half the multiply time (73–91 %)
//!   until a tile stored as bf16 took the bf16-grade activations of `fastmath512` (82–96 %;
//!   without them 22 % of this tile's samples sat in the epilogue of a half-cheetah + DEEN
//!   plan, with them 9 %, `perf annotate`).
//!
//! Both tiles share the epilogue, which stores f32 rows or, for a next layer in bf16, converts
//! pairs of rows to bf16 pairs in registers. The two bodies differ only in their load and
//! multiply instructions; they stay two macros rather than one generic kernel because the
//! per-type helpers would need `#[target_feature]`, which rules out the forced inlining the
//! inner loop depends on.

use super::packed::Encoding;
use super::x86::{load_scalar, mask16};
use crate::nn::activation::Activation;
use crate::nn::aligned::LANES;
use crate::nn::fastmath512::{softplus_for_bf16, swish_for_bf16};
use crate::nn::lanes::{softplus, swish};
use std::arch::x86_64::*;

/// One packed product in pointer form; every extent was checked by `matmul_packed`.
pub(super) struct PackedRaw {
    pub m: usize,
    pub n: usize,
    /// Depth steps: `k` for f32 weights, `⌈k/2⌉` for bf16 pairs.
    pub steps: usize,
    pub a: *const f32,
    /// How `a` and `y` are stored: f32, or bf16 pairs (see `Encoding::Bf16Pairs`).
    pub encoding: Encoding,
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
pub(super) unsafe fn store_pairs(c: *mut f32, mask: __mmask16, lo: __m512, hi: __m512) {
    // SAFETY: the caller passes a row segment valid for the masked lanes.
    unsafe {
        let halves: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
        let idx = _mm512_loadu_si512(INTERLEAVE.as_ptr().cast());
        let pairs = _mm512_permutexvar_epi16(idx, halves);
        _mm512_mask_storeu_epi32(c.cast::<i32>(), mask, pairs);
    }
}

/// Rows `lo` and `hi` (zeros where `None`) as one row of bf16 pairs in `out`, 16 columns at a
/// time (see `packed::write_bf16_pairs`).
///
/// # Safety
/// The CPU must support AVX-512 BW and BF16; `lo`, `hi` and `out` have the same length.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
pub(super) unsafe fn pair_rows(out: &mut [f32], lo: &[f32], hi: Option<&[f32]>) {
    let n = out.len();
    debug_assert!(lo.len() == n && hi.is_none_or(|h| h.len() == n));
    for col in (0..n).step_by(LANES) {
        let mask = mask16(n, col);
        // SAFETY: the masked lanes lie inside the three rows of length `n`.
        unsafe {
            let low = _mm512_maskz_loadu_ps(mask, lo.as_ptr().wrapping_add(col));
            let high = match hi {
                Some(h) => _mm512_maskz_loadu_ps(mask, h.as_ptr().wrapping_add(col)),
                None => _mm512_setzero_ps(),
            };
            store_pairs(out.as_mut_ptr().wrapping_add(col), mask, low, high);
        }
    }
}

/// `src` rounded to bf16 (as `VCVTNEPS2BF16` rounds), consecutive elements paired into the
/// words of `out` (word `p` holds elements `2p` low and `2p + 1` high), zero past the end of
/// `src`: a row of a tile product's left factor (see `tiles.rs`).
///
/// # Safety
/// The CPU must support AVX-512 BW and BF16; `out` holds at least `⌈len/16⌉ · 8` words.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
pub(super) unsafe fn bf16_row(out: &mut [f32], src: &[f32]) {
    let n = src.len();
    let written = n.div_ceil(LANES) * LANES / 2;
    assert!(out.len() >= written, "{} words for {n} elements", out.len());
    for col in (0..n).step_by(LANES) {
        // SAFETY: the masked lanes lie inside `src`; words `col/2 .. col/2 + 8` inside `out`.
        unsafe {
            let v = _mm512_maskz_loadu_ps(mask16(n, col), src.as_ptr().wrapping_add(col));
            let halves: __m256i = std::mem::transmute(_mm512_cvtneps_pbh(v));
            _mm256_storeu_si256(out.as_mut_ptr().wrapping_add(col / 2).cast(), halves);
        }
    }
    out[written..].fill(0.0);
}

/// Activates a finished tile to the precision it is stored in (see
/// `fastmath512::swish_for_bf16`) and stores it as bf16 pairs: block rows `2q, 2q + 1` go to
/// storage row `i0/2 + q`. One call per tile: the f32 tiles (which lack the bf16 features and so
/// cannot inline the conversion) make one call here rather than one per pair of rows.
///
/// # Safety
/// The CPU must support AVX-512 BW and BF16 (`bf16_out` is set only then); the block and the
/// panels must be inside the extents of `raw`.
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn store_tile_as_pairs<const NP: usize, const MR: usize>(
    raw: &PackedRaw,
    tile: &mut [[__m512; NP]; MR],
    mask: &[__mmask16; NP],
    i0: usize,
    p0: usize,
) {
    match raw.act {
        None => {}
        Some(Activation::Swish) => {
            for v in tile.iter_mut().flatten() {
                *v = swish_for_bf16(*v);
            }
        }
        Some(Activation::Softplus) => {
            for v in tile.iter_mut().flatten() {
                *v = softplus_for_bf16(*v);
            }
        }
    }
    let ld_c = raw.ld_c;
    let c = raw.c.wrapping_add(i0 / 2 * ld_c + p0 * LANES);
    for q in (0..MR).step_by(2) {
        for j in 0..NP {
            let hi = if q + 1 < MR {
                tile[q + 1][j]
            } else {
                _mm512_setzero_ps()
            };
            // SAFETY: forwarded from the caller.
            unsafe {
                store_pairs(
                    c.wrapping_add(q / 2 * ld_c + j * LANES),
                    mask[j],
                    tile[q][j],
                    hi,
                )
            };
        }
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
        if $raw.bf16_out {
            // SAFETY: `bf16_out` is only set on CPUs with AVX-512 BW and BF16.
            store_tile_as_pairs::<$np, $mr>($raw, &mut tile, &$mask, $i0, $p0);
        } else {
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
            let c = $raw.c.wrapping_add($i0 * ld_c + $p0 * LANES);
            for (r, row) in tile.iter().enumerate() {
                for j in 0..$np {
                    _mm512_mask_storeu_ps(c.wrapping_add(r * ld_c + j * LANES), $mask[j], row[j]);
                }
            }
        }
    };
}

macro_rules! f32_tile {
    ($name:ident; $($r:literal)+) => {
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
    };
}

macro_rules! bf16_tile {
    ($name:ident; $($r:literal)+) => {
        /// The tile from bf16 pairs: one `VDPBF16PS` per accumulator does two depth steps.
        #[inline]
        #[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
        unsafe fn $name<const NP: usize>(raw: &PackedRaw, i0: usize, p0: usize) {
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

f32_tile!(f32_1; 0);
f32_tile!(f32_2; 0 1);
f32_tile!(f32_3; 0 1 2);
f32_tile!(f32_4; 0 1 2 3);
f32_tile!(f32_5; 0 1 2 3 4);
f32_tile!(f32_6; 0 1 2 3 4 5);
f32_tile!(f32_7; 0 1 2 3 4 5 6);
f32_tile!(f32_8; 0 1 2 3 4 5 6 7);
f32_tile!(f32_9; 0 1 2 3 4 5 6 7 8);
f32_tile!(f32_10; 0 1 2 3 4 5 6 7 8 9);
f32_tile!(f32_11; 0 1 2 3 4 5 6 7 8 9 10);
f32_tile!(f32_12; 0 1 2 3 4 5 6 7 8 9 10 11);
bf16_tile!(bf16_1; 0);
bf16_tile!(bf16_2; 0 1);
bf16_tile!(bf16_3; 0 1 2);
bf16_tile!(bf16_4; 0 1 2 3);
bf16_tile!(bf16_5; 0 1 2 3 4);
bf16_tile!(bf16_6; 0 1 2 3 4 5);

/// Runs the f32 tile for a block of `mr ≤ 12` rows and `NP` panels.
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn f32_block<const NP: usize>(mr: usize, raw: &PackedRaw, i0: usize, p: usize) {
    // SAFETY: forwarded from the caller.
    unsafe {
        match mr {
            1 => f32_1::<NP>(raw, i0, p),
            2 => f32_2::<NP>(raw, i0, p),
            3 => f32_3::<NP>(raw, i0, p),
            4 => f32_4::<NP>(raw, i0, p),
            5 => f32_5::<NP>(raw, i0, p),
            6 => f32_6::<NP>(raw, i0, p),
            7 => f32_7::<NP>(raw, i0, p),
            8 => f32_8::<NP>(raw, i0, p),
            9 => f32_9::<NP>(raw, i0, p),
            10 => f32_10::<NP>(raw, i0, p),
            11 => f32_11::<NP>(raw, i0, p),
            12 => f32_12::<NP>(raw, i0, p),
            _ => unreachable!("f32 row block of {mr}"),
        }
    }
}

/// Runs the bf16 tile for a block of `mr ≤ 6` rows and `NP` panels.
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn bf16_block<const NP: usize>(mr: usize, raw: &PackedRaw, i0: usize, p: usize) {
    // SAFETY: forwarded from the caller; the bf16 tiles run only when `matmul_packed` checked
    // for AVX-512 BF16.
    unsafe {
        match mr {
            1 => bf16_1::<NP>(raw, i0, p),
            2 => bf16_2::<NP>(raw, i0, p),
            3 => bf16_3::<NP>(raw, i0, p),
            4 => bf16_4::<NP>(raw, i0, p),
            5 => bf16_5::<NP>(raw, i0, p),
            6 => bf16_6::<NP>(raw, i0, p),
            _ => unreachable!("bf16 row block of {mr}"),
        }
    }
}

/// Block by block (each block's packed weights stay in L1 while every panel of `Y` passes
/// through): f32 weights in tiles of 12 rows × 2 panels and a lone last panel; bf16 pairs in
/// tiles of 6 rows × 4 and 3 panels (see [`bf16_tiling`]).
///
/// # Safety
/// The CPU must support AVX-512F and every extent of `raw` must be valid.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn drive(raw: &PackedRaw) {
    let panels = raw.n.div_ceil(LANES);
    let rows = raw.encoding.block_rows();
    for i0 in (0..raw.m).step_by(rows) {
        let mr = rows.min(raw.m - i0);
        // SAFETY (every call): the block and the panels named are inside the extents.
        match raw.encoding {
            Encoding::F32 => {
                let mut p = 0;
                while p + 2 <= panels {
                    unsafe { f32_block::<2>(mr, raw, i0, p) };
                    p += 2;
                }
                if p < panels {
                    unsafe { f32_block::<1>(mr, raw, i0, p) };
                }
            }
            Encoding::Bf16Pairs => {
                let (fours, threes) = bf16_tiling(panels);
                let mut p = 0;
                for _ in 0..fours {
                    unsafe { bf16_block::<4>(mr, raw, i0, p) };
                    p += 4;
                }
                for _ in 0..threes {
                    unsafe { bf16_block::<3>(mr, raw, i0, p) };
                    p += 3;
                }
                match panels - p {
                    0 => {}
                    1 => unsafe { bf16_block::<1>(mr, raw, i0, p) },
                    2 => unsafe { bf16_block::<2>(mr, raw, i0, p) },
                    left => unreachable!("{left} panels left"),
                }
            }
        }
    }
}

/// How a row of `panels` panels splits into bf16 tiles: `(fours, threes)` tiles of 4 and 3
/// panels, then 1 or 2 panels left only where fewer than six are (`5` is `3 + 2`). A 2-panel
/// tile does 12 multiply-adds per 6 broadcasts and 2 loads where a 4-panel one does 24 per 6
/// and 4: a 200-column row (13 panels) split 4 + 4 + 3 + 2 ran the 200×200×200 swish layer at
/// 360–376 GFLOP/s (best batches of three `bench kernel` runs), split 4 + 3 + 3 + 3 at 381–385
/// (two runs).
fn bf16_tiling(panels: usize) -> (usize, usize) {
    let threes = [0, 3, 2, 1][panels % 4];
    if panels >= 3 * threes {
        ((panels - 3 * threes) / 4, threes)
    } else {
        (0, usize::from(panels >= 3))
    }
}

#[cfg(test)]
mod tests {
    use super::bf16_tiling;

    #[test]
    fn bf16_rows_split_into_tiles_of_three_and_four_panels() {
        for panels in 0..40 {
            let (fours, threes) = bf16_tiling(panels);
            let left = panels - 4 * fours - 3 * threes;
            if panels >= 6 {
                assert_eq!(left, 0, "{panels}: {fours} × 4 + {threes} × 3");
                assert!(
                    threes < 4,
                    "{panels}: three 3-panel tiles make three 4-panel ones"
                );
            } else {
                assert!(left <= 2, "{panels}: {left} left");
            }
        }
        assert_eq!(bf16_tiling(13), (1, 3));
        assert_eq!(bf16_tiling(16), (4, 0));
        assert_eq!(bf16_tiling(5), (0, 1));
        assert_eq!(bf16_tiling(2), (0, 0));
    }
}
