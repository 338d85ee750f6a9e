//! Training products on the AMX tile unit: `C = init + X · Y` with both factors rounded to
//! bf16 and every sum kept in f32 (`TDPBF16PS`), for CPUs whose tile unit multiplies several
//! times faster than their f32 FMA units (see `planner-service bench train`).
//!
//! A training step's products change both factors every step (the weights after each Adam
//! update, the activations with each minibatch), so unlike the inference layers nothing is
//! packed once per model: each product packs its two factors into the tile layouts, multiplies
//! whole 16 × 16 tiles of `C` (sums over 32 bf16 depth elements per instruction) into a padded
//! f32 scratch, and adds that to `C` with its [`Init`]. Packing reads each factor once (a few
//! percent of the multiply-adds at these sizes); the padding of ragged shapes to whole tiles
//! is zeros in the depth and discarded rows and columns of `C`.
//!
//! Layouts (words are 32 bits holding two bf16, the even depth element in the low half, the
//! same pairs as [`Encoding::Bf16Pairs`](super::Encoding::Bf16Pairs)):
//!
//! - the left factor `X` (`m × k`) as rows of pairs along the depth: word `p` of row `i` holds
//!   `X[i, 2p]` and `X[i, 2p + 1]` — a `tileloadd` of 16 rows of 64 bytes is one `A` tile;
//! - the right factor `Y` (`k × n`) as pair rows: word `j` of pair row `p` holds `Y[2p, j]`
//!   and `Y[2p + 1, j]` — 16 pair rows of 16 words are one `B` tile.
//!
//! Either layout is one conversion pass when the factor's rows run along the layout's words,
//! and a conversion followed by a 32-bit transpose when they run across (the training passes
//! multiply by `Wᵀ` and by `Gᵀ` as strided views; see [`MatRef::t`]): the pairs of a
//! transposed factor are the transpose of the other layout's pairs of the factor itself.
//!
//! The kernel keeps a 2 × 2 block of `C` tiles (4 of the 8 tile registers) for the whole depth,
//! with two `A` and two `B` tiles per depth step: four loads per four tile products.

use super::{Init, MatMut, MatRef, bf16_pair, transpose};
use crate::nn::aligned::AlignedBuf;
use crate::nn::amx::{self, TILE_BYTES as ROW_BYTES, TILE_ROWS as ROWS, TileConfig, tile};
use crate::nn::denormals;
use crate::nn::simd::{bf16_dot_available, multiversion};

/// Words (bf16 pairs, or f32 sums) per tile row.
const WORDS: usize = ROW_BYTES / 4;
/// Depth elements per tile product: 16 words of two bf16.
const DEPTH: usize = 2 * WORDS;

/// Every tile full size: four `C` tiles (0–3), two `A` tiles (4, 5), two `B` tiles (6, 7).
const CONFIG: TileConfig = {
    let mut c = TileConfig::new();
    let mut t = 0;
    while t < 8 {
        c = c.with_tile(t, ROWS, ROW_BYTES);
        t += 1;
    }
    c
};

/// Products with fewer multiply-adds than this run on one thread (see [`tile_matmul_par`]).
const PARALLEL_MIN_MACS: usize = 1 << 24;

/// Packed factors and the f32 tile sums of one product, grown to the largest product seen and
/// reused (a training tape owns one).
#[derive(Debug, Default)]
pub struct TileScratch {
    a: Buf,
    b: Buf,
    stage: Buf,
    c: Buf,
}

/// A buffer that only grows.
#[derive(Debug, Default)]
struct Buf(Option<AlignedBuf>);

impl Buf {
    fn at_least(&mut self, len: usize) -> &mut [f32] {
        if self.0.as_ref().is_none_or(|b| b.len() < len) {
            self.0 = Some(AlignedBuf::zeros(len));
        }
        &mut self.0.as_mut().expect("just allocated").as_mut_slice()[..len]
    }
}

/// The padded extents of one product, in tiles.
#[derive(Clone, Copy, Debug)]
struct Grid {
    /// Tile rows of `C` (even: the kernel's blocks are 2 × 2 tiles).
    mt: usize,
    /// Tile columns of `C` (even).
    nt: usize,
    /// Depth steps of 32.
    kt: usize,
}

impl Grid {
    fn new(m: usize, n: usize, k: usize) -> Self {
        Self {
            mt: m.div_ceil(2 * ROWS) * 2,
            nt: n.div_ceil(2 * WORDS) * 2,
            kt: k.div_ceil(DEPTH).max(1),
        }
    }

    /// Words per packed row of `X`.
    fn a_words(self) -> usize {
        self.kt * WORDS
    }

    /// Words per pair row of `Y` and floats per row of the sums.
    fn b_words(self) -> usize {
        self.nt * WORDS
    }
}

/// Whether this process can run the tile products: AMX-BF16 tiles, and AVX-512 BF16 for
/// packing the factors.
pub fn available() -> bool {
    bf16_dot_available() && amx::available()
}

/// `C = init + X · Y` with bf16 factors and f32 sums, on the calling thread. Panics on
/// mismatched shapes and if the tiles are not [`available`].
pub fn tile_matmul(
    c: MatMut<'_>,
    x: MatRef<'_>,
    y: MatRef<'_>,
    init: Init<'_>,
    scratch: &mut TileScratch,
) {
    tile_matmul_threads(c, Left::View(x), y, init, scratch, false)
}

/// [`tile_matmul`], with the rows of tiles of `C` split across two rayon tasks when the
/// product is large.
pub fn tile_matmul_par(
    c: MatMut<'_>,
    x: MatRef<'_>,
    y: MatRef<'_>,
    init: Init<'_>,
    scratch: &mut TileScratch,
) {
    tile_matmul_threads(c, Left::View(x), y, init, scratch, true)
}

/// A left factor packed once for several products (a layer's weights within one training
/// step: DEEN multiplies by each `Wᵀ` and each `W` twice).
#[derive(Debug, Default)]
pub struct PackedLeft {
    buf: Buf,
    stage: Buf,
    rows: usize,
    depth: usize,
}

impl PackedLeft {
    /// Packs `x` (any strides), replacing what was packed before.
    pub fn pack(&mut self, x: MatRef<'_>) {
        let grid = Grid::new(x.rows, 1, x.cols);
        pack_rows_of_pairs(&mut self.buf, &mut self.stage, x, grid);
        (self.rows, self.depth) = (x.rows, x.cols);
    }
}

/// [`tile_matmul_par`] with the left factor packed beforehand.
pub fn tile_matmul_packed_par(
    c: MatMut<'_>,
    x: &PackedLeft,
    y: MatRef<'_>,
    init: Init<'_>,
    scratch: &mut TileScratch,
) {
    tile_matmul_threads(c, Left::Packed(x), y, init, scratch, true)
}

/// The left factor of a product: a view to pack, or packed already.
#[derive(Clone, Copy)]
enum Left<'a> {
    View(MatRef<'a>),
    Packed(&'a PackedLeft),
}

impl Left<'_> {
    fn shape(self) -> (usize, usize) {
        match self {
            Left::View(x) => (x.rows, x.cols),
            Left::Packed(p) => (p.rows, p.depth),
        }
    }
}

fn tile_matmul_threads(
    c: MatMut<'_>,
    x: Left<'_>,
    y: MatRef<'_>,
    init: Init<'_>,
    scratch: &mut TileScratch,
    parallel: bool,
) {
    let ((x_rows, k), (m, n)) = (x.shape(), (c.rows, c.cols));
    assert_eq!(x_rows, m, "X has {x_rows} rows, C has {m}");
    assert_eq!(y.rows, k, "X has {k} columns, Y has {} rows", y.rows);
    assert_eq!(y.cols, n, "Y has {} columns, C has {n}", y.cols);
    match init {
        Init::RowBias(b) => assert!(b.len() >= m, "row bias too short"),
        Init::ColBias(b) => assert!(b.len() >= n, "column bias too short"),
        Init::Zero | Init::Accumulate => {}
    }
    assert!(available(), "AMX tiles are not available");
    if m == 0 || n == 0 {
        return;
    }
    let grid = Grid::new(m, n, k);
    let TileScratch {
        a,
        b,
        stage,
        c: sums,
    } = scratch;
    let a = match x {
        Left::View(x) => pack_rows_of_pairs(a, stage, x, grid),
        Left::Packed(p) => {
            let packed = p.buf.0.as_ref().expect("a packed factor").as_slice();
            &packed[..grid.mt * ROWS * grid.a_words()]
        }
    };
    let b = pack_pair_rows(b, stage, y, grid);
    let sums = sums.at_least(grid.mt * ROWS * grid.b_words());
    let job = Job {
        a: a.as_ptr(),
        b: b.as_ptr(),
        grid,
    };
    let split = parallel && m * n * k >= PARALLEL_MIN_MACS && rayon::current_num_threads() >= 2;
    if !split {
        // SAFETY: the tiles are available; the buffers hold the grid's extents.
        unsafe { job.multiply(0..grid.mt / 2, sums) };
        finish(c, sums, grid, init);
        return;
    }
    // Block rows (2 tiles, 32 rows of C) for the first task; C's own rows end at `m`.
    let half = grid.mt / 4;
    let rows_top = (2 * half * ROWS).min(m);
    let mode = denormals::current_mode();
    let (c_top, c_bottom) = c.split_rows(rows_top);
    let (sums_top, sums_bottom) = sums.split_at_mut(2 * half * ROWS * grid.b_words());
    let (init_top, init_bottom) = match init {
        Init::RowBias(bias) => (Init::RowBias(bias), Init::RowBias(&bias[rows_top..])),
        other => (other, other),
    };
    let job = &job;
    rayon::join(
        || {
            // SAFETY: as above; each task writes its own rows of the sums.
            unsafe { job.multiply(0..half, sums_top) };
            finish(c_top, sums_top, grid, init_top);
        },
        || {
            denormals::with_mode(mode, || {
                // SAFETY: as above.
                unsafe { job.multiply(half..grid.mt / 2, sums_bottom) };
                finish(c_bottom, sums_bottom, grid, init_bottom);
            })
        },
    );
}

/// The packed factors of one product, shared by the tasks of a split product.
struct Job {
    a: *const f32,
    b: *const f32,
    grid: Grid,
}

// SAFETY: the tasks of one product only read the factors.
unsafe impl Sync for Job {}

impl Job {
    /// The sums of the blocks (2 × 2 tiles) in block rows `blocks` of `C`, over the whole
    /// depth, on the calling thread, into `sums` (which starts at the first block's row).
    ///
    /// # Safety
    /// The tiles are available; `a` and `b` hold the extents of `grid`.
    unsafe fn multiply(&self, blocks: std::ops::Range<usize>, sums: &mut [f32]) {
        use tile::{dpbf16ps, load, store, zero};
        let Grid { nt, kt, .. } = self.grid;
        let (stride_a, stride_b) = (self.grid.a_words() * 4, self.grid.b_words() * 4);
        assert!(sums.len() >= blocks.len() * 2 * ROWS * self.grid.b_words());
        let first = blocks.start;
        let (a, b, sums) = (
            self.a.cast::<u8>(),
            self.b.cast::<u8>(),
            sums.as_mut_ptr().cast::<u8>(),
        );
        // SAFETY: every tile read or written below lies inside the grid's extents.
        unsafe {
            tile::load_config(&CONFIG);
            for bi in blocks {
                let a0 = a.wrapping_add(2 * bi * ROWS * stride_a);
                let a1 = a0.wrapping_add(ROWS * stride_a);
                for bj in 0..nt / 2 {
                    zero::<0>();
                    zero::<1>();
                    zero::<2>();
                    zero::<3>();
                    let b0 = b.wrapping_add(2 * bj * ROW_BYTES);
                    for kk in 0..kt {
                        let bk = b0.wrapping_add(kk * ROWS * stride_b);
                        load::<4>(a0.wrapping_add(kk * ROW_BYTES), stride_a);
                        load::<6>(bk, stride_b);
                        dpbf16ps::<0, 4, 6>();
                        load::<7>(bk.wrapping_add(ROW_BYTES), stride_b);
                        dpbf16ps::<1, 4, 7>();
                        load::<5>(a1.wrapping_add(kk * ROW_BYTES), stride_a);
                        dpbf16ps::<2, 5, 6>();
                        dpbf16ps::<3, 5, 7>();
                    }
                    let c0 =
                        sums.wrapping_add(2 * (bi - first) * ROWS * stride_b + 2 * bj * ROW_BYTES);
                    let c1 = c0.wrapping_add(ROWS * stride_b);
                    store::<0>(c0, stride_b);
                    store::<1>(c0.wrapping_add(ROW_BYTES), stride_b);
                    store::<2>(c1, stride_b);
                    store::<3>(c1.wrapping_add(ROW_BYTES), stride_b);
                }
            }
            tile::release();
        }
    }
}

/// Writes `C = init + sums` for the rows of `c` (the sums' rows `b_words` floats apart).
fn finish(c: MatMut<'_>, sums: &[f32], grid: Grid, init: Init<'_>) {
    let (n, ld_c, ld_s) = (c.cols, c.rs, grid.b_words());
    for i in 0..c.rows {
        let out = &mut c.data[i * ld_c..i * ld_c + n];
        let s = &sums[i * ld_s..i * ld_s + n];
        match init {
            Init::Zero => out.copy_from_slice(s),
            Init::Accumulate => add_into(out, s),
            Init::RowBias(b) => add_scalar(out, s, b[i]),
            Init::ColBias(b) => add2(out, s, &b[..n]),
        }
    }
}

multiversion! {
    /// `out += s`.
    fn add_into(out: &mut [f32], s: &[f32]) {
        let s = &s[..out.len()];
        for (o, v) in out.iter_mut().zip(s) {
            *o += *v;
        }
    }
}

multiversion! {
    /// `out = s + b`.
    fn add_scalar(out: &mut [f32], s: &[f32], b: f32) {
        let s = &s[..out.len()];
        for (o, v) in out.iter_mut().zip(s) {
            *o = *v + b;
        }
    }
}

multiversion! {
    /// `out = s + b` elementwise.
    fn add2(out: &mut [f32], s: &[f32], b: &[f32]) {
        let (s, b) = (&s[..out.len()], &b[..out.len()]);
        for ((o, v), w) in out.iter_mut().zip(s).zip(b) {
            *o = *v + *w;
        }
    }
}

/// Packs `x` (`m × k`) as rows of pairs along the depth (`mt · 16` rows of `kt · 16` words;
/// the words past `k` zero, the rows past `m` whatever they were: they only reach discarded
/// rows of the sums).
fn pack_rows_of_pairs<'s>(
    buf: &'s mut Buf,
    stage: &mut Buf,
    x: MatRef<'_>,
    grid: Grid,
) -> &'s [f32] {
    let (m, k, words) = (x.rows, x.cols, grid.a_words());
    let out = buf.at_least(grid.mt * ROWS * words);
    if x.cs == 1 {
        for i in 0..m {
            bf16_row(&mut out[i * words..(i + 1) * words], x.row(i));
        }
    } else if x.rs == 1 {
        // `x` is the transpose of the row-major `k × m` matrix `xᵀ`: pair its rows, then
        // transpose the words.
        let staged = stage.at_least(words * m);
        let xt = MatRef::strided(x.data, k, m, x.cs, 1);
        pair_rows_into(staged, m, xt, words);
        transpose(staged, words, m, m, out, words);
    } else {
        for i in 0..m {
            let row = &mut out[i * words..(i + 1) * words];
            for (p, w) in row.iter_mut().enumerate() {
                *w = bf16_pair(at(x, i, 2 * p), at(x, i, 2 * p + 1));
            }
        }
    }
    out
}

/// Packs `y` (`k × n`) as pair rows (`kt · 16` pair rows of `nt · 16` words; the pair rows
/// past `k` zero, the words past `n` whatever they were: they only reach discarded columns).
fn pack_pair_rows<'s>(buf: &'s mut Buf, stage: &mut Buf, y: MatRef<'_>, grid: Grid) -> &'s [f32] {
    let (k, n, words) = (y.rows, y.cols, grid.b_words());
    let pair_rows = grid.a_words();
    let out = buf.at_least(pair_rows * words);
    if y.cs == 1 || n == 1 {
        pair_rows_into(out, words, MatRef { cs: 1, ..y }, pair_rows);
    } else if y.rs == 1 {
        // `y` is the transpose of the row-major `n × k` matrix `yᵀ`: convert its rows, then
        // transpose the words.
        let staged = stage.at_least(n * pair_rows);
        let yt = MatRef::strided(y.data, n, k, y.cs, 1);
        for j in 0..n {
            bf16_row(&mut staged[j * pair_rows..(j + 1) * pair_rows], yt.row(j));
        }
        transpose(staged, n, pair_rows, pair_rows, out, words);
    } else {
        for p in 0..pair_rows {
            for j in 0..n {
                out[p * words + j] = bf16_pair(at(y, 2 * p, j), at(y, 2 * p + 1, j));
            }
        }
    }
    out
}

/// Element `(i, j)` of `x`, zero outside it.
fn at(x: MatRef<'_>, i: usize, j: usize) -> f32 {
    if i < x.rows && j < x.cols {
        x.data[i * x.rs + j * x.cs]
    } else {
        0.0
    }
}

/// Writes the rows of `src` (`k × n`, unit column stride) as `pair_rows` pair rows of `n`
/// words, `ld` words apart; pair rows past `⌈k/2⌉` are zero.
fn pair_rows_into(out: &mut [f32], ld: usize, src: MatRef<'_>, pair_rows: usize) {
    let (k, n) = (src.rows, src.cols);
    for p in 0..pair_rows {
        let row = &mut out[p * ld..p * ld + n];
        if 2 * p >= k {
            row.fill(0.0);
            continue;
        }
        let lo = src.row(2 * p);
        let hi = (2 * p + 1 < k).then(|| src.row(2 * p + 1));
        // SAFETY: the tiles are only used with AVX-512 BW and BF16 (see `available`);
        // the three rows hold `n` floats each.
        unsafe { super::x86_packed::pair_rows(row, lo, hi) };
    }
}

/// Writes `src` rounded to bf16 into `out` as consecutive pairs (word `p` holds elements `2p`
/// and `2p + 1`), zero past the end of `src`.
fn bf16_row(out: &mut [f32], src: &[f32]) {
    // SAFETY: the tiles are only used with AVX-512 BW and BF16 (see `available`).
    unsafe { super::x86_packed::bf16_row(out, src) };
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::matmul::{bf16_bits, bf16_value};
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};

    fn round(x: f32) -> f64 {
        bf16_value(bf16_bits(x)) as f64
    }

    /// Every product shape of [`super::super::RAGGED_SHAPES`] and the training shapes' edges,
    /// with `X` and `Y` each given row-major, transposed and (for `X`) with both strides
    /// non-unit, against f64 sums of the bf16-rounded factors: a product of two bf16 is exact
    /// in f32, so the only difference is the f32 summation.
    #[test]
    fn tile_products_match_rounded_f64_sums_at_ragged_shapes() {
        if !available() {
            eprintln!("SKIPPED on this CPU: no AMX-BF16 tiles (the f32 kernels are tested)");
            return;
        }
        let mut rng = StdRng::seed_from_u64(3);
        let mut scratch = TileScratch::default();
        let shapes = super::super::RAGGED_SHAPES.iter().copied().chain([
            (201, 200, 32),
            (200, 32, 201),
            (9, 33, 64),
            (65, 17, 97),
        ]);
        for (m, n, k) in shapes {
            for layout in 0..3 {
                for init_kind in 0..4 {
                    check(m, n, k, layout, init_kind, &mut scratch, &mut rng);
                }
            }
        }
    }

    fn check(
        m: usize,
        n: usize,
        k: usize,
        layout: usize,
        init_kind: usize,
        scratch: &mut TileScratch,
        rng: &mut StdRng,
    ) {
        let mut random =
            |len: usize| -> Vec<f32> { (0..len).map(|_| rng.random_range(-2.0..2.0)).collect() };
        // Layout 0: both row-major; 1: both stored transposed; 2: X with two non-unit
        // strides, Y row-major with a row stride.
        let (x_rs, x_cs) = match layout {
            0 => (k + 3, 1),
            1 => (1, m + 2),
            _ => (2 * k + 1, 2),
        };
        let (y_rs, y_cs) = match layout {
            1 => (1, k + 1),
            _ => (n + 5, 1),
        };
        let x_store = random(m * x_rs * x_cs + k * x_cs + m + k + 1);
        let y_store = random(k * y_rs * y_cs + n * y_cs + k + n + 1);
        let ld_c = n + 3;
        let c0 = random(m * ld_c);
        let bias = random(m.max(n));
        let x = MatRef::strided(&x_store, m, k, x_rs, x_cs);
        let y = MatRef::strided(&y_store, k, n, y_rs, y_cs);
        let init = match init_kind {
            0 => Init::Zero,
            1 => Init::Accumulate,
            2 => Init::RowBias(&bias),
            _ => Init::ColBias(&bias),
        };
        let mut c = c0.clone();
        tile_matmul_par(MatMut::with_stride(&mut c, m, n, ld_c), x, y, init, scratch);
        for i in 0..m {
            for j in 0..ld_c {
                let got = c[i * ld_c + j];
                if j >= n {
                    assert_eq!(got, c0[i * ld_c + j], "padding of C written");
                    continue;
                }
                let mut want = match init_kind {
                    0 => 0.0,
                    1 => c0[i * ld_c + j] as f64,
                    2 => bias[i] as f64,
                    _ => bias[j] as f64,
                };
                let mut size = want.abs();
                for d in 0..k {
                    let t = round(at(x, i, d)) * round(at(y, d, j));
                    want += t;
                    size += t.abs();
                }
                let err = (got as f64 - want).abs();
                assert!(
                    err <= 1e-6 * size + 1e-30,
                    "{m}×{n}×{k} layout {layout} init {init_kind} at ({i},{j}): {got} vs {want}"
                );
            }
        }
    }

    /// A left factor packed once gives the same numbers as packed by each product, also for
    /// a transposed view and after a larger factor was packed into the same buffer.
    #[test]
    fn a_packed_left_factor_gives_the_same_products() {
        if !available() {
            eprintln!("SKIPPED on this CPU: no AMX-BF16 tiles");
            return;
        }
        let mut rng = StdRng::seed_from_u64(5);
        let mut scratch = TileScratch::default();
        let mut packed = PackedLeft::default();
        for (m, n, k) in [(70, 40, 90), (37, 47, 13), (5, 3, 7)] {
            let w: Vec<f32> = (0..m * k).map(|_| rng.random_range(-1.0..1.0)).collect();
            let y: Vec<f32> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            // X given as the transpose of a row-major `k × m` matrix, as a layer's `Wᵀ`.
            let x = MatRef::new(&w, k, m).t();
            packed.pack(x);
            let (mut once, mut each) = (vec![0.0; m * n], vec![0.0; m * n]);
            let y = MatRef::new(&y, k, n);
            tile_matmul_packed_par(
                MatMut::new(&mut once, m, n),
                &packed,
                y,
                Init::Zero,
                &mut scratch,
            );
            tile_matmul_par(MatMut::new(&mut each, m, n), x, y, Init::Zero, &mut scratch);
            assert_eq!(once, each, "{m}×{n}×{k}");
        }
    }

    /// A product big enough to be split across two tasks gives the same numbers as on one.
    #[test]
    fn a_split_product_matches_the_unsplit_one() {
        if !available() {
            eprintln!("SKIPPED on this CPU: no AMX-BF16 tiles");
            return;
        }
        let (m, n, k) = (333, 270, 250);
        assert!(m * n * k >= PARALLEL_MIN_MACS);
        let mut rng = StdRng::seed_from_u64(4);
        let x: Vec<f32> = (0..m * k).map(|_| rng.random_range(-1.0..1.0)).collect();
        let y: Vec<f32> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let bias: Vec<f32> = (0..m).map(|_| rng.random_range(-1.0..1.0)).collect();
        let mut scratch = TileScratch::default();
        let mut run = |par: bool| {
            let mut c = vec![0.0; m * n];
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap();
            pool.install(|| {
                tile_matmul_threads(
                    MatMut::new(&mut c, m, n),
                    Left::View(MatRef::new(&x, m, k)),
                    MatRef::new(&y, k, n),
                    Init::RowBias(&bias),
                    &mut scratch,
                    par,
                )
            });
            c
        };
        assert_eq!(run(true), run(false));
    }
}
