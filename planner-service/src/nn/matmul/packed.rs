//! Inference layers `C = act(A · Y + b)` with `A` packed once in the kernel's own layout.
//!
//! During a planning call the weights never change, while each layer's product runs tens of
//! thousands of times. A layer's `Wᵀ` is therefore packed once per model into blocks of output
//! features ([`Encoding::block_rows`]: 12 in f32, 6 in bf16): within a block, the weights the
//! kernel broadcasts at one depth step are adjacent, and the depth steps follow each other. The
//! kernel then reads its broadcast operand as one sequential stream instead of one
//! line per step strided through the whole weight matrix, and addresses it with constant
//! offsets rather than a runtime stride (packing alone measured 1–6 % faster; the fused
//! activation below gives the rest).
//!
//! The activation is the kernel's epilogue: on AVX-512 and AVX2 it runs on the finished tile in
//! registers (see [`lanes`](crate::nn::lanes)), so a hidden layer costs one pass over memory; the
//! portable kernel's rows are activated right after they are stored, while they are still in L1.
//!
//! **bf16 layers** ([`Encoding::Bf16Pairs`]). On CPUs with AVX-512 BF16 one `VDPBF16PS` does
//! 32 multiply-adds (bf16 products, f32 sums) where an f32 FMA does 16, but its rate depends on
//! the CPU: measured 230 against 117 GFLOP/s per core on an AMD Zen 5, and 85 against
//! 162 GFLOP/s — half the f32 rate — on an Intel Xeon with AMX, whose tile unit
//! (`TDPBF16PS`, `amx_packed.rs`, [`PackedMatrix::pack_bf16_tiles`]) does 2.7–3.0 TFLOP/s.
//! Which kernel a network runs is therefore measured, not assumed
//! ([`kernel_path`](crate::nn::kernel_path)). A matrix packed with
//! [`PackedMatrix::pack_bf16`] holds its weights rounded to bf16, two consecutive depth
//! elements per 32-bit word, and multiplies activations stored the same way: feature rows
//! `2p` and `2p + 1` of a sample share word `p` of its column, the even one in the low half.
//! Any layer can *write* that encoding from its epilogue (round to nearest even, interleave),
//! so a network runs f32 input → bf16 hidden activations → f32 output with no separate
//! conversion pass. Sums stay f32; only the operands lose precision (8 significant bits,
//! relative rounding ≤ 2⁻⁸), see [`Precision`](crate::nn::Precision) for where that is used.
//!
//! Why not the `gemm` crate: it allocates on every call (the planner allocates nothing per
//! call), and on these shapes (200–500 wide layers, 200–250 samples per population chunk) it
//! is no faster than this kernel before packing (`planner-service bench kernel`), and cannot
//! fuse the bias and the activation into its stores.

use super::{MatMut, MatRef, Raw, RawInit};
use crate::nn::activation::Activation;
use crate::nn::aligned::{AlignedBuf, LANES};
use crate::nn::simd::{SimdLevel, bf16_dot_available, level};

/// How the elements of a packed matrix, and of the feature-major activations it multiplies or
/// writes, are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// One `f32` per element.
    F32,
    /// Two consecutive feature rows per storage row, each element rounded to bf16: word `p`
    /// of a column holds rows `2p` (low half) and `2p + 1` (high half; zero past the last row).
    /// Stored in `f32` buffers as raw bits.
    Bf16Pairs,
}

impl Encoding {
    /// Storage rows of a matrix of `features` feature rows in this encoding.
    pub fn storage_rows(self, features: usize) -> usize {
        match self {
            Encoding::F32 => features,
            Encoding::Bf16Pairs => features.div_ceil(2),
        }
    }

    /// Output features per packed block of weights in this encoding: the row block of the
    /// AVX-512 tile, 12 rows × 32 columns of accumulators in f32 and 6 rows × 64 in bf16 (see
    /// `x86_packed.rs` for why they differ). Both even, so a block's rows pair up exactly
    /// when it writes [`Encoding::Bf16Pairs`]; both multiples of the AVX2 kernel's 6 rows.
    pub const fn block_rows(self) -> usize {
        match self {
            Encoding::F32 => 12,
            Encoding::Bf16Pairs => 6,
        }
    }
}

/// `x` rounded to the nearest bf16 (ties to even), as its 16 bits. Subnormals flush to a signed
/// zero and NaN stays NaN, as in the hardware conversion (`VCVTNE2PS2BF16`).
pub fn bf16_bits(x: f32) -> u16 {
    let bits = x.to_bits();
    if x.is_nan() {
        return ((bits >> 16) | 0x0040) as u16;
    }
    if x.is_subnormal() {
        return ((bits >> 16) & 0x8000) as u16;
    }
    let rounded = bits.wrapping_add(0x7FFF + ((bits >> 16) & 1));
    (rounded >> 16) as u16
}

/// The value of a bf16 given by its bits.
pub fn bf16_value(bits: u16) -> f32 {
    f32::from_bits(u32::from(bits) << 16)
}

/// Two values as one [`Encoding::Bf16Pairs`] word, carried in an `f32` slot.
pub fn bf16_pair(low: f32, high: f32) -> f32 {
    f32::from_bits(u32::from(bf16_bits(low)) | (u32::from(bf16_bits(high)) << 16))
}

/// Writes the rows of an f32 matrix `src` (`k × n`, unit column stride) into `dst` as
/// [`Encoding::Bf16Pairs`] (`⌈k/2⌉ × n`): rows `2p` and `2p + 1` rounded to bf16 and
/// interleaved into storage row `p`, the high half of the last word zero when `k` is odd.
///
/// This is how a bf16 first layer gets its input: the caller fills the normalised input in f32
/// and one pass over it (`k · n` reads, a few dozen features) makes the pairs, where converting
/// inside the kernel would redo it for every block of output rows. Rounds as [`bf16_bits`] does
/// (the hardware conversion on CPUs with AVX-512 BF16). Never allocates.
pub fn write_bf16_pairs(dst: MatMut<'_>, src: MatRef<'_>) {
    let (k, n) = (src.rows, src.cols);
    assert_eq!(
        dst.rows,
        Encoding::Bf16Pairs.storage_rows(k),
        "{k} rows make {} pair rows, not {}",
        Encoding::Bf16Pairs.storage_rows(k),
        dst.rows
    );
    assert_eq!(
        dst.cols, n,
        "source has {n} columns, destination {}",
        dst.cols
    );
    assert!(src.cs == 1 || n <= 1, "the source needs unit column stride");
    #[cfg(target_arch = "x86_64")]
    if bf16_dot_available() {
        for p in 0..dst.rows {
            let lo = src.row(2 * p);
            let hi = (2 * p + 1 < k).then(|| src.row(2 * p + 1));
            let out = &mut dst.data[p * dst.rs..p * dst.rs + n];
            // SAFETY: the CPU has AVX-512 BW and BF16; the three rows hold `n` floats each.
            unsafe { super::x86_packed::pair_rows(out, lo, hi) };
        }
        return;
    }
    for p in 0..dst.rows {
        for j in 0..n {
            let at = |r: usize| {
                if r < k {
                    src.data[r * src.rs + j * src.cs]
                } else {
                    0.0
                }
            };
            dst.data[p * dst.rs + j] = bf16_pair(at(2 * p), at(2 * p + 1));
        }
    }
}

/// An `m × k` matrix packed for [`matmul_packed`]: with `R` its encoding's
/// [`block_rows`](Encoding::block_rows) and `s` its depth
/// steps (`k` in f32, `⌈k/2⌉` bf16 pairs), block `b` holds rows `Rb..Rb + mr`
/// (`mr = min(R, m − Rb)`) at offset `Rb·s`, step `d` of row `Rb + r` at `Rb·s + d·mr + r`.
#[derive(Clone)]
pub struct PackedMatrix {
    rows: usize,
    depth: usize,
    encoding: Encoding,
    /// Packed as AMX tiles (bf16 only, see [`PackedMatrix::pack_bf16_tiles`]) rather than in
    /// the vector kernels' row blocks.
    tiles: bool,
    data: AlignedBuf,
}

impl std::fmt::Debug for PackedMatrix {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "PackedMatrix({}×{}, {:?}{})",
            self.rows,
            self.depth,
            self.encoding,
            if self.tiles { ", AMX tiles" } else { "" }
        )
    }
}

impl PackedMatrix {
    /// Packs any `m × k` view in f32 (for a layer: `MatRef::new(weights, in, out).t()`).
    pub fn pack(a: MatRef<'_>) -> Self {
        Self::pack_with(a, Encoding::F32, |a, i, d| a.data[i * a.rs + d * a.cs])
    }

    /// Packs any `m × k` view as bf16 pairs along the depth (see [`Encoding::Bf16Pairs`]).
    pub fn pack_bf16(a: MatRef<'_>) -> Self {
        Self::pack_with(a, Encoding::Bf16Pairs, |a, i, p| {
            let at = |d: usize| {
                if d < a.cols {
                    a.data[i * a.rs + d * a.cs]
                } else {
                    0.0
                }
            };
            bf16_pair(at(2 * p), at(2 * p + 1))
        })
    }

    /// Packs any `m × k` view as bf16 pairs in AMX tiles: blocks of 16 output rows, depth
    /// chunks of 16 pairs, each a zero-padded 16 × 16-word tile (see `amx_packed.rs`).
    /// Multiplied by [`matmul_packed`] only where [`amx::available`](crate::nn::amx::available).
    pub fn pack_bf16_tiles(a: MatRef<'_>) -> Self {
        let (m, k) = (a.rows, a.cols);
        let steps = Encoding::Bf16Pairs.storage_rows(k);
        let (blocks, chunks) = (m.div_ceil(16), steps.div_ceil(16));
        let mut data = AlignedBuf::zeros(blocks * chunks * 256);
        let out = data.as_mut_slice();
        let at = |i: usize, d: usize| {
            if d < k {
                a.data[i * a.rs + d * a.cs]
            } else {
                0.0
            }
        };
        for i in 0..m {
            for p in 0..steps {
                let (b, r, c, q) = (i / 16, i % 16, p / 16, p % 16);
                out[(b * chunks + c) * 256 + r * 16 + q] =
                    bf16_pair(at(i, 2 * p), at(i, 2 * p + 1));
            }
        }
        Self {
            rows: m,
            depth: k,
            encoding: Encoding::Bf16Pairs,
            tiles: true,
            data,
        }
    }

    /// Whether this matrix is packed as AMX tiles.
    pub fn is_tiles(&self) -> bool {
        self.tiles
    }

    fn pack_with(
        a: MatRef<'_>,
        encoding: Encoding,
        element: impl Fn(&MatRef<'_>, usize, usize) -> f32,
    ) -> Self {
        let (m, k) = (a.rows, a.cols);
        let (steps, rows) = (encoding.storage_rows(k), encoding.block_rows());
        let mut data = AlignedBuf::zeros(m * steps);
        let out = data.as_mut_slice();
        for i0 in (0..m).step_by(rows) {
            let mr = rows.min(m - i0);
            let block = &mut out[i0 * steps..(i0 + mr) * steps];
            for d in 0..steps {
                for r in 0..mr {
                    block[d * mr + r] = element(&a, i0 + r, d);
                }
            }
        }
        Self {
            rows: m,
            depth: k,
            encoding,
            tiles: false,
            data,
        }
    }

    /// `m`: rows of the product (output features).
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// `k`: the inner dimension (input features).
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// How the weights, and the input this matrix multiplies, are stored.
    pub fn encoding(&self) -> Encoding {
        self.encoding
    }

    /// Depth steps of the kernel: storage rows of the input.
    fn steps(&self) -> usize {
        self.encoding.storage_rows(self.depth)
    }

    /// Rows `i0..i0 + mr` as a strided view (f32 only; `i0` a multiple of its block rows).
    fn block(&self, i0: usize) -> MatRef<'_> {
        let mr = Encoding::F32.block_rows().min(self.rows - i0);
        let data = &self.data.as_slice()[i0 * self.depth..];
        MatRef::strided(data, mr, self.depth, 1, mr)
    }
}

/// `C = act(A · Y + b)` (bias per row of `C`; `act` = `None` for a linear layer) on the
/// calling thread. `Y` is stored in `A`'s encoding and `C` is written in `out`'s: their views'
/// rows are storage rows (`Encoding::storage_rows`). `Y` must have unit column stride. Any bf16
/// operand needs [`bf16_dot_available`]. Never allocates.
pub fn matmul_packed(
    c: MatMut<'_>,
    out: Encoding,
    a: &PackedMatrix,
    y: MatRef<'_>,
    bias: &[f32],
    act: Option<Activation>,
) {
    matmul_packed_at(level(), c, out, a, y, bias, act)
}

pub(crate) fn matmul_packed_at(
    lvl: SimdLevel,
    c: MatMut<'_>,
    out: Encoding,
    a: &PackedMatrix,
    y: MatRef<'_>,
    bias: &[f32],
    act: Option<Activation>,
) {
    let (m, n, steps) = (a.rows, c.cols, a.steps());
    assert_eq!(
        out.storage_rows(m),
        c.rows,
        "A has {m} rows, C has {} storage rows in {out:?}",
        c.rows
    );
    assert_eq!(
        y.rows, steps,
        "A has {} columns ({steps} steps in {:?}), Y has {} rows",
        a.depth, a.encoding, y.rows
    );
    assert_eq!(y.cols, n, "Y has {} columns, C has {n}", y.cols);
    assert!(y.cs == 1 || n <= 1, "Y needs unit column stride");
    assert!(bias.len() >= m, "bias too short");
    let bf16 = a.encoding == Encoding::Bf16Pairs || out == Encoding::Bf16Pairs;
    assert!(
        !bf16 || (lvl == SimdLevel::Avx512 && bf16_dot_available()),
        "bf16 layers need AVX-512 BF16"
    );
    assert!(
        !a.tiles || crate::nn::amx::available(),
        "a matrix packed as AMX tiles needs AMX-BF16"
    );
    if m == 0 || n == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if lvl == SimdLevel::Avx512 {
        let raw = super::x86_packed::PackedRaw {
            m,
            n,
            steps,
            a: a.data.as_slice().as_ptr(),
            encoding: a.encoding,
            y: y.data.as_ptr(),
            ld_y: y.rs,
            c: c.data.as_mut_ptr(),
            ld_c: c.rs,
            bf16_out: out == Encoding::Bf16Pairs,
            bias: bias.as_ptr(),
            act,
        };
        if a.tiles {
            // SAFETY: AMX and AVX-512 BF16 were asserted above; the views and the packing
            // checked every extent.
            unsafe { super::amx_packed::drive(&raw) };
        } else {
            // SAFETY: the level guarantees AVX-512F (and BF16 where a bf16 operand is
            // involved, asserted above); the views and the packing checked every extent.
            unsafe { super::x86_packed::drive(&raw) };
        }
        return;
    }
    // Other levels: the general kernel, one 16-column panel of `Y` at a time through every
    // block of `A`. The panel (`k` rows of one cache line) then stays in L1 while the blocks
    // pass, and `A`, read once per panel, in L2; block by block over the whole width instead,
    // every block streamed all of `Y` again, from L3 once a call's samples outgrow L2 (a
    // half-cheetah PETS plan on a Zen 3: 1,000 samples a call, `Y` 800 KB), and the plan
    // took about a tenth longer (one thread, four rounds in turns). The AVX2 kernel activates
    // the finished registers ([`lanes`](crate::nn::lanes)); the portable kernel's rows are
    // activated right after they are stored, while they are in L1.
    let k = a.depth;
    let ld_c = c.rs;
    let c_data = c.data;
    for p0 in (0..n).step_by(LANES) {
        let w = LANES.min(n - p0);
        for i0 in (0..m).step_by(Encoding::F32.block_rows()) {
            let block = a.block(i0);
            let mr = block.rows;
            let mut raw = Raw {
                m: mr,
                n: w,
                k,
                x: block.data.as_ptr(),
                rs_x: block.rs,
                cs_x: block.cs,
                y: y.data[p0..].as_ptr(),
                ld_y: y.rs,
                c: c_data[i0 * ld_c + p0..].as_mut_ptr(),
                ld_c,
                init: RawInit::RowBias(bias[i0..].as_ptr()),
                act: None,
            };
            match lvl {
                #[cfg(target_arch = "x86_64")]
                SimdLevel::Avx2 | SimdLevel::Avx512 => {
                    raw.act = act;
                    // SAFETY: the level guarantees AVX2+FMA; every extent was checked above
                    // (rows `i0..i0 + mr`, columns `p0..p0 + w`).
                    unsafe { super::x86::drive_avx2(&raw) }
                }
                _ => {
                    // SAFETY: every extent was checked above.
                    unsafe { super::scalar::drive(&raw) };
                    if let Some(act) = act {
                        for r in i0..i0 + mr {
                            act.apply(&mut c_data[r * ld_c + p0..r * ld_c + p0 + w]);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::matmul::matmul;
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};

    fn random(rng: &mut StdRng, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.random_range(-2.0..2.0)).collect()
    }

    /// `act(Wᵀ·H + b)` in f64, for a row-major `k × m` weight matrix and `k × n` `H`.
    #[allow(clippy::too_many_arguments)]
    fn reference(
        w: &[f32],
        h: &[f32],
        ld: usize,
        bias: &[f32],
        act: Option<Activation>,
        (m, n, k): (usize, usize, usize),
    ) -> Vec<f64> {
        let mut out = vec![0.0; m * n];
        for i in 0..m {
            for j in 0..n {
                let z = bias[i] as f64
                    + (0..k)
                        .map(|d| w[d * m + i] as f64 * h[d * ld + j] as f64)
                        .sum::<f64>();
                out[i * n + j] = crate::nn::reference::activate(act, z);
            }
        }
        out
    }

    #[test]
    fn packing_lays_out_blocks_of_the_encodings_height() {
        // Two full blocks and a ragged one of 2 rows, 4 columns (2 bf16 pairs).
        for encoding in [Encoding::F32, Encoding::Bf16Pairs] {
            let rows = encoding.block_rows();
            let (m, k) = (2 * rows + 2, 4);
            let a: Vec<f32> = (0..m * k).map(|v| v as f32).collect();
            let view = MatRef::new(&a, m, k);
            let (p, steps) = match encoding {
                Encoding::F32 => (PackedMatrix::pack(view), k),
                Encoding::Bf16Pairs => (PackedMatrix::pack_bf16(view), k / 2),
            };
            let element = |i: usize, d: usize| match encoding {
                Encoding::F32 => a[i * k + d],
                Encoding::Bf16Pairs => bf16_pair(a[i * k + 2 * d], a[i * k + 2 * d + 1]),
            };
            let data = p.data.as_slice();
            for i in 0..m {
                let i0 = i / rows * rows;
                let mr = rows.min(m - i0);
                for d in 0..steps {
                    let got = data[i0 * steps + d * mr + (i - i0)];
                    assert_eq!(
                        got.to_bits(),
                        element(i, d).to_bits(),
                        "{encoding:?} ({i}, {d})"
                    );
                }
            }
            // The last block is packed at its own height: its rows are adjacent.
            let last = 2 * rows;
            assert_eq!(
                [
                    data[last * steps].to_bits(),
                    data[last * steps + 1].to_bits()
                ],
                [element(last, 0).to_bits(), element(last + 1, 0).to_bits()],
                "{encoding:?}"
            );
            assert_eq!((p.rows(), p.depth(), p.encoding()), (m, k, encoding));
        }
    }

    #[test]
    fn packed_layers_match_the_reference_on_ragged_shapes_at_every_level() {
        let mut rng = StdRng::seed_from_u64(5);
        for lvl in SimdLevel::available() {
            for &(m, n, k) in &super::super::RAGGED_SHAPES {
                for act in [None, Some(Activation::Swish), Some(Activation::Softplus)] {
                    let ld = n + 7;
                    let w = random(&mut rng, k * m);
                    let h = random(&mut rng, k * ld);
                    let bias = random(&mut rng, m);
                    let packed = PackedMatrix::pack(MatRef::new(&w, k, m).t());
                    let ld_c = n + 3;
                    let mut c = vec![f32::NAN; m * ld_c];
                    matmul_packed_at(
                        lvl,
                        MatMut::with_stride(&mut c, m, n, ld_c),
                        Encoding::F32,
                        &packed,
                        MatRef::with_stride(&h, k, n, ld),
                        &bias,
                        act,
                    );
                    let want = reference(&w, &h, ld, &bias, act, (m, n, k));
                    for i in 0..m {
                        for j in 0..ld_c {
                            let got = c[i * ld_c + j];
                            if j < n {
                                let e = want[i * n + j];
                                assert!(
                                    (got as f64 - e).abs() < 3e-6 * (k as f64 + 1.0),
                                    "{lvl:?} {act:?} {m}×{n}×{k} ({i},{j}): {got} vs {e}"
                                );
                            } else {
                                assert!(got.is_nan(), "{lvl:?}: padding ({i},{j}) written");
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn linear_packed_layer_equals_the_general_kernel() {
        // Same operands and the same summation order: the packed product is bit-identical to
        // the strided one on every level.
        let mut rng = StdRng::seed_from_u64(6);
        let (m, n, k) = (29, 40, 33);
        let w = random(&mut rng, k * m);
        let h = random(&mut rng, k * n);
        let bias = random(&mut rng, m);
        let packed = PackedMatrix::pack(MatRef::new(&w, k, m).t());
        for lvl in SimdLevel::available() {
            let (mut a, mut b) = (vec![0.0; m * n], vec![0.0; m * n]);
            crate::nn::simd::with_level(lvl, || {
                matmul(
                    MatMut::new(&mut a, m, n),
                    MatRef::new(&w, k, m).t(),
                    MatRef::new(&h, k, n),
                    super::super::Init::RowBias(&bias),
                );
                matmul_packed(
                    MatMut::new(&mut b, m, n),
                    Encoding::F32,
                    &packed,
                    MatRef::new(&h, k, n),
                    &bias,
                    None,
                );
            });
            assert_eq!(a, b, "{lvl:?}");
        }
    }
}
