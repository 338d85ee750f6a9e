//! The AMX kernel for packed bf16 layers (see [`packed`](super::packed) and
//! [`amx`](crate::nn::amx)).
//!
//! `TDPBF16PS` multiplies an `A` tile of 16 rows × 16 bf16 pairs (16 output features × 32
//! depth elements) by a `B` tile of 16 pair rows × 16 columns, where row `p` of `B` holds, per
//! column, the pair of depth elements `2p, 2p + 1`: exactly the
//! [`Bf16Pairs`](super::Encoding::Bf16Pairs) encoding of feature-major activations. So `B`
//! tiles load straight from the activations (16 rows, `ld_y` apart), and only the weights are
//! packed, once per model, as whole zero-padded 1 KiB tiles ([`PackedMatrix::pack_bf16_tiles`](
//! super::PackedMatrix::pack_bf16_tiles)): block `b` of 16 output rows, depth chunk `c` of 16
//! pairs at word `(b · chunks + c) · 256`, row `r` and pair `q` at `r · 16 + q`.
//!
//! The register blocking is 2 × 2: four 16 × 16 f32 accumulators (`tmm0`–`tmm3`) for 32
//! output features × 32 samples, two `A` tiles (`tmm4`, `tmm5`) and two `B` tiles (`tmm6`,
//! `tmm7`): four tile loads per four products. Ragged edges:
//! - **rows** (`m` not a multiple of 16): the weights are zero-padded; the epilogue stores only
//!   the valid rows;
//! - **depth** (`⌈k/2⌉` pairs not a multiple of 16): the weights are zero-padded, and the last
//!   chunk's `B` tiles are copied, zero-padded, to a stack buffer (reading past the last pair
//!   row could meet an infinity or NaN, and `0 · ∞` is NaN);
//! - **columns** (`n` not a multiple of 16): the last panel runs under a second configuration
//!   whose `B` and accumulator tiles are `n mod 16` columns wide, so no load reads past `n`.
//!
//! The epilogue stores the accumulators to a stack buffer and runs the same AVX-512 code as
//! the vector kernels on each 16-wide row: bias, activation (the bf16-grade one when the
//! output is stored as bf16), and an f32 or bf16-pair store.

use super::packed::Encoding;
use super::x86::{load_scalar, mask16};
use super::x86_packed::{PackedRaw, store_pairs};
use crate::nn::activation::Activation;
use crate::nn::amx::{TILE_BYTES, TILE_ROWS, TileConfig, tile};
use crate::nn::fastmath512::{softplus_for_bf16, swish_for_bf16};
use crate::nn::lanes::{softplus, swish};
use std::arch::x86_64::*;

/// Words (bf16 pairs or f32) of one full tile.
pub(super) const TILE_WORDS: usize = TILE_ROWS * TILE_BYTES / 4;
/// Columns per panel (one tile's width).
const PANEL: usize = 16;
/// Panels whose depth tails are staged at once (the stack buffer: 8 KiB).
const GROUP: usize = 8;

/// Depth chunks (of 16 pairs) of a matrix with `steps` pair rows.
pub(super) fn chunks(steps: usize) -> usize {
    steps.div_ceil(TILE_ROWS)
}

/// 64-byte aligned tiles on the stack.
#[repr(C, align(64))]
struct Tiles<const N: usize>([[f32; TILE_WORDS]; N]);

/// The configuration for panels `cols ≤ 16` wide: accumulators `tmm0`–`tmm3` and `B` tiles
/// `tmm6`, `tmm7` of `cols` columns, `A` tiles `tmm4`, `tmm5` of 16 rows × 16 pairs.
fn config(cols: usize) -> TileConfig {
    let mut c = TileConfig::new();
    for t in 0..4 {
        c = c.with_tile(t, TILE_ROWS, 4 * cols);
    }
    c.with_tile(4, TILE_ROWS, TILE_BYTES)
        .with_tile(5, TILE_ROWS, TILE_BYTES)
        .with_tile(6, TILE_ROWS, 4 * cols)
        .with_tile(7, TILE_ROWS, 4 * cols)
}

/// Where one block of up to 2 × 2 accumulator tiles reads its operands.
struct Block {
    /// The packed weights of row block `b` (and `b + 1` at `+ chunks · 256` words).
    a: *const f32,
    /// Row `0` of `Y` at the block's first column.
    y: *const f32,
    /// The staged depth tail of the block's first panel (the next panel's at `+ 256` words).
    tail: *const f32,
}

/// Accumulates a block of `R` row blocks × `P` panels (`R, P ∈ {1, 2}`) over the whole depth
/// and stores the accumulators to `acc` (tile `2r + p` for row block `r`, panel `p`).
///
/// # Safety
/// Tiles are available and configured by [`config`]; `blk` points inside the operands as
/// `drive` computes it; `full` depth chunks of `Y` are readable, and the tail is staged when
/// `tail_chunk` is set.
#[inline(always)]
unsafe fn accumulate<const R: usize, const P: usize>(
    blk: &Block,
    chunks: usize,
    full: usize,
    tail_chunk: bool,
    ld_y_bytes: usize,
    acc: &mut Tiles<4>,
) {
    const A_TILE: usize = TILE_WORDS;
    let a1 = blk.a.wrapping_add(chunks * A_TILE);
    // SAFETY: forwarded from the caller.
    unsafe {
        tile::zero::<0>();
        if P == 2 {
            tile::zero::<1>();
        }
        if R == 2 {
            tile::zero::<2>();
            if P == 2 {
                tile::zero::<3>();
            }
        }
        let step = |c: usize, b: *const u8, stride: usize| {
            tile::load::<4>(blk.a.wrapping_add(c * A_TILE).cast(), TILE_BYTES);
            tile::load::<6>(b, stride);
            if P == 2 {
                tile::load::<7>(b.wrapping_add(TILE_BYTES), stride);
            }
            tile::dpbf16ps::<0, 4, 6>();
            if P == 2 {
                tile::dpbf16ps::<1, 4, 7>();
            }
            if R == 2 {
                tile::load::<5>(a1.wrapping_add(c * A_TILE).cast(), TILE_BYTES);
                tile::dpbf16ps::<2, 5, 6>();
                if P == 2 {
                    tile::dpbf16ps::<3, 5, 7>();
                }
            }
        };
        for c in 0..full {
            step(
                c,
                blk.y.cast::<u8>().wrapping_add(c * TILE_ROWS * ld_y_bytes),
                ld_y_bytes,
            );
        }
        if tail_chunk {
            // The staged tiles are 16 rows of 64 bytes; panel 2's follows panel 1's.
            let b = blk.tail.cast::<u8>();
            tile::load::<4>(blk.a.wrapping_add(full * A_TILE).cast(), TILE_BYTES);
            tile::load::<6>(b, TILE_BYTES);
            if P == 2 {
                tile::load::<7>(b.wrapping_add(TILE_ROWS * TILE_BYTES), TILE_BYTES);
            }
            tile::dpbf16ps::<0, 4, 6>();
            if P == 2 {
                tile::dpbf16ps::<1, 4, 7>();
            }
            if R == 2 {
                tile::load::<5>(a1.wrapping_add(full * A_TILE).cast(), TILE_BYTES);
                tile::dpbf16ps::<2, 5, 6>();
                if P == 2 {
                    tile::dpbf16ps::<3, 5, 7>();
                }
            }
        }
        let mut out = |t: usize| acc.0[t].as_mut_ptr().cast::<u8>();
        tile::store::<0>(out(0), TILE_BYTES);
        if P == 2 {
            tile::store::<1>(out(1), TILE_BYTES);
        }
        if R == 2 {
            tile::store::<2>(out(2), TILE_BYTES);
            if P == 2 {
                tile::store::<3>(out(3), TILE_BYTES);
            }
        }
    }
}

/// Bias, activation and store of one accumulator tile: rows `i0..i0 + 16` (those below `m`),
/// columns `j0..j0 + cols`.
///
/// # Safety
/// AVX-512 F, BW and BF16; the rows and columns named are inside the extents of `raw`.
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn epilogue(raw: &PackedRaw, acc: &[f32; TILE_WORDS], i0: usize, j0: usize, cols: usize) {
    let mask = mask16(cols, 0);
    let rows = TILE_ROWS.min(raw.m - i0);
    let ld_c = raw.ld_c;
    if raw.bf16_out {
        let c = raw.c.wrapping_add(i0 / 2 * ld_c + j0);
        for q in 0..rows.div_ceil(2) {
            // SAFETY: forwarded from the caller.
            let (lo, hi) = unsafe {
                (
                    finish(raw, acc, i0, rows, 2 * q),
                    finish(raw, acc, i0, rows, 2 * q + 1),
                )
            };
            // SAFETY: storage row `i0/2 + q` exists (rows pair up from the even `i0`).
            unsafe { store_pairs(c.wrapping_add(q * ld_c), mask, lo, hi) };
        }
    } else {
        let c = raw.c.wrapping_add(i0 * ld_c + j0);
        for r in 0..rows {
            // SAFETY: forwarded from the caller.
            let v = unsafe { finish(raw, acc, i0, rows, r) };
            // SAFETY: row `i0 + r < m`, the masked columns `< n`.
            unsafe { _mm512_mask_storeu_ps(c.wrapping_add(r * ld_c), mask, v) };
        }
    }
}

/// Row `r` of an accumulator tile plus its bias, activated (zero for rows past the last).
///
/// # Safety
/// As for [`epilogue`].
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
unsafe fn finish(
    raw: &PackedRaw,
    acc: &[f32; TILE_WORDS],
    i0: usize,
    rows: usize,
    r: usize,
) -> __m512 {
    if r >= rows {
        return _mm512_setzero_ps();
    }
    // SAFETY: row `r` of the 1 KiB buffer; the bias has `m > i0 + r` entries.
    let z = unsafe {
        _mm512_add_ps(
            _mm512_load_ps(acc.as_ptr().add(r * PANEL)),
            _mm512_set1_ps(load_scalar(raw.bias.add(i0 + r))),
        )
    };
    match (raw.act, raw.bf16_out) {
        (None, _) => z,
        (Some(Activation::Swish), false) => swish(z),
        (Some(Activation::Softplus), false) => softplus(z),
        (Some(Activation::Swish), true) => swish_for_bf16(z),
        (Some(Activation::Softplus), true) => softplus_for_bf16(z),
    }
}

/// Copies pair rows `row0..steps` of panels `p0..p0 + count` of `Y` into zero-padded tiles.
fn stage_tail(raw: &PackedRaw, row0: usize, p0: usize, count: usize, tail: &mut Tiles<GROUP>) {
    let rows = raw.steps - row0;
    for (g, t) in tail.0.iter_mut().take(count).enumerate() {
        t.fill(0.0);
        let j0 = (p0 + g) * PANEL;
        let cols = PANEL.min(raw.n - j0);
        for r in 0..rows {
            let src = raw.y.wrapping_add((row0 + r) * raw.ld_y + j0);
            // SAFETY: row `row0 + r < steps` and columns `j0..j0 + cols ≤ n` of `Y`.
            let src = unsafe { std::slice::from_raw_parts(src, cols) };
            t[r * PANEL..r * PANEL + cols].copy_from_slice(src);
        }
    }
}

/// `C = act(A · Y + b)` with `A` packed as tiles; see the module documentation.
///
/// # Safety
/// [`amx::available`](crate::nn::amx::available) returned `true`, the CPU has AVX-512 F, BW
/// and BF16, `raw.a` holds `⌈m/16⌉ · chunks(steps)` packed tiles and every extent of `raw`
/// is valid.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
pub(super) unsafe fn drive(raw: &PackedRaw) {
    debug_assert!(raw.encoding == Encoding::Bf16Pairs);
    let chunks = chunks(raw.steps);
    let full = raw.steps / TILE_ROWS;
    let tail_chunk = full < chunks;
    let blocks = raw.m.div_ceil(TILE_ROWS);
    let panels = raw.n.div_ceil(PANEL);
    let whole = raw.n / PANEL; // full-width panels
    let ld_y_bytes = raw.ld_y * 4;
    let mut tail = Tiles::<GROUP>([[0.0; TILE_WORDS]; GROUP]);
    let mut acc = Tiles::<4>([[0.0; TILE_WORDS]; 4]);
    let main = config(PANEL);
    let ragged = config(raw.n % PANEL);
    // SAFETY: tiles are available (the caller's contract); `config` is valid.
    unsafe { tile::load_config(&main) };
    let mut configured_ragged = false;
    for g0 in (0..panels).step_by(GROUP) {
        let count = GROUP.min(panels - g0);
        if tail_chunk {
            stage_tail(raw, full * TILE_ROWS, g0, count, &mut tail);
        }
        for b in (0..blocks).step_by(2) {
            let two_rows = b + 1 < blocks;
            let mut p = g0;
            while p < g0 + count {
                let two_cols = p + 1 < whole.min(g0 + count);
                let ragged_panel = p >= whole;
                if ragged_panel != configured_ragged {
                    // SAFETY: as above; between blocks, where zeroing the tiles loses nothing.
                    unsafe { tile::load_config(if ragged_panel { &ragged } else { &main }) };
                    configured_ragged = ragged_panel;
                }
                let blk = Block {
                    a: raw.a.wrapping_add(b * chunks * TILE_WORDS),
                    y: raw.y.wrapping_add(p * PANEL),
                    tail: tail.0[p - g0].as_ptr(),
                };
                // SAFETY: the block's rows, panels and depth are inside the operands.
                unsafe {
                    match (two_rows, two_cols) {
                        (true, true) => {
                            accumulate::<2, 2>(&blk, chunks, full, tail_chunk, ld_y_bytes, &mut acc)
                        }
                        (true, false) => {
                            accumulate::<2, 1>(&blk, chunks, full, tail_chunk, ld_y_bytes, &mut acc)
                        }
                        (false, true) => {
                            accumulate::<1, 2>(&blk, chunks, full, tail_chunk, ld_y_bytes, &mut acc)
                        }
                        (false, false) => {
                            accumulate::<1, 1>(&blk, chunks, full, tail_chunk, ld_y_bytes, &mut acc)
                        }
                    }
                }
                let cols_of = |q: usize| PANEL.min(raw.n - q * PANEL);
                for r in 0..1 + usize::from(two_rows) {
                    for c in 0..1 + usize::from(two_cols) {
                        // SAFETY: row block `b + r` and panel `p + c` are inside `C`.
                        unsafe {
                            epilogue(
                                raw,
                                &acc.0[2 * r + c],
                                (b + r) * TILE_ROWS,
                                (p + c) * PANEL,
                                cols_of(p + c),
                            )
                        };
                    }
                }
                p += 1 + usize::from(two_cols);
            }
        }
    }
    // SAFETY: tiles are available.
    unsafe { tile::release() };
}
