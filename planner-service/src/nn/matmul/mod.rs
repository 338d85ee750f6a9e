//! Dense products `C = init + X · Y`: the only matrix operation the networks need.
//!
//! Why a kernel of our own rather than the `gemm` crate: every general `gemm` call allocates
//! (a bookkeeping `Vec` and packing buffers), and the planner promises zero allocations per
//! planning step; and on the shapes of these networks (a few dozen to a few hundred samples,
//! 200–500 wide layers) a register-blocked kernel without packing is as fast or faster (see
//! `planner-service bench kernel`). The kernel broadcasts single elements of `X` — so `X` may
//! have any strides, which makes `Wᵀ` free — and streams rows of `Y` in 16-float panels, so `Y`
//! and `C` need unit column stride. The last panel of a row is masked, so any width works.
//!
//! Inference layers take a second entry, [`matmul_packed`]: the weights packed once per model
//! into the kernel's layout, and bias plus activation fused into the kernel (see `packed.rs`).
//!
//! The networks keep their activations *feature-major* (feature `f` of sample `i` at
//! `f · ld + i`): then the forward pass is `Z = Wᵀ · H`, the backward pass `G' = W · G`, and only
//! the weight gradient needs a (small) transpose of its right factor.

#[cfg(target_arch = "x86_64")]
mod amx_packed;
#[cfg(test)]
mod bf16_tests;
mod packed;
mod scalar;
#[cfg(target_arch = "x86_64")]
pub mod tiles;
#[cfg(target_arch = "x86_64")]
mod x86;
#[cfg(target_arch = "x86_64")]
mod x86_packed;

pub(crate) use packed::matmul_packed_at;
pub use packed::{
    Encoding, PackedMatrix, bf16_bits, bf16_pair, bf16_value, matmul_packed, write_bf16_pairs,
};

use super::Activation;
use super::denormals;
use super::simd::{SimdLevel, level};

/// A read-only matrix view with arbitrary strides (element `(i, j)` at `i · rs + j · cs`).
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a> {
    data: &'a [f32],
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

impl<'a> MatRef<'a> {
    /// A dense row-major `rows × cols` matrix.
    pub fn new(data: &'a [f32], rows: usize, cols: usize) -> Self {
        Self::strided(data, rows, cols, cols, 1)
    }

    /// A row-major matrix whose rows are `rs` floats apart.
    pub fn with_stride(data: &'a [f32], rows: usize, cols: usize, rs: usize) -> Self {
        Self::strided(data, rows, cols, rs, 1)
    }

    /// Any strides. Panics if `data` is too short for the extent.
    pub fn strided(data: &'a [f32], rows: usize, cols: usize, rs: usize, cs: usize) -> Self {
        if rows > 0 && cols > 0 {
            let last = (rows - 1) * rs + (cols - 1) * cs;
            assert!(
                last < data.len(),
                "matrix view {rows}×{cols} (strides {rs}, {cs}) exceeds {} floats",
                data.len()
            );
        }
        Self {
            data,
            rows,
            cols,
            rs,
            cs,
        }
    }

    /// The transpose (a view, nothing is copied).
    pub fn t(self) -> Self {
        Self {
            rows: self.cols,
            cols: self.rows,
            rs: self.cs,
            cs: self.rs,
            ..self
        }
    }

    pub fn rows(&self) -> usize {
        self.rows
    }

    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Row `i` (for views with unit column stride).
    pub fn row(&self, i: usize) -> &'a [f32] {
        assert!(
            self.cs == 1 && i < self.rows,
            "row {i} of a {}-row view with column stride {}",
            self.rows,
            self.cs
        );
        &self.data[i * self.rs..i * self.rs + self.cols]
    }

    /// Writes this matrix transposed into `dst` (`cols × rows`, row stride `ld_dst`).
    pub fn transpose_into(&self, dst: &mut [f32], ld_dst: usize) {
        assert_eq!(self.cs, 1, "transpose_into reads rows");
        transpose(self.data, self.rows, self.cols, self.rs, dst, ld_dst);
    }

    /// Rows `start..start + count`.
    fn row_range(self, start: usize, count: usize) -> Self {
        let data = if count == 0 || self.cols == 0 {
            &self.data[..0]
        } else {
            &self.data[start * self.rs..]
        };
        Self {
            data,
            rows: count,
            ..self
        }
    }
}

/// A mutable row-major matrix view with unit column stride and row stride `rs`.
#[derive(Debug)]
pub struct MatMut<'a> {
    data: &'a mut [f32],
    rows: usize,
    cols: usize,
    rs: usize,
}

impl<'a> MatMut<'a> {
    /// A dense row-major `rows × cols` matrix.
    pub fn new(data: &'a mut [f32], rows: usize, cols: usize) -> Self {
        Self::with_stride(data, rows, cols, cols)
    }

    /// A row-major matrix whose rows are `rs ≥ cols` floats apart.
    pub fn with_stride(data: &'a mut [f32], rows: usize, cols: usize, rs: usize) -> Self {
        assert!(rs >= cols, "row stride {rs} < {cols} columns");
        if rows > 0 && cols > 0 {
            assert!(
                (rows - 1) * rs + cols <= data.len(),
                "matrix view {rows}×{cols} (stride {rs}) exceeds {} floats",
                data.len()
            );
        }
        Self {
            data,
            rows,
            cols,
            rs,
        }
    }

    /// Splits after row `at`.
    fn split_rows(self, at: usize) -> (MatMut<'a>, MatMut<'a>) {
        let (rows, cols, rs) = (self.rows, self.cols, self.rs);
        let cut = (at * rs).min(self.data.len());
        let (top, bottom) = self.data.split_at_mut(cut);
        (
            MatMut {
                data: top,
                rows: at,
                cols,
                rs,
            },
            MatMut {
                data: bottom,
                rows: rows - at,
                cols,
                rs,
            },
        )
    }
}

/// What `C` starts from before `X · Y` is added.
#[derive(Clone, Copy, Debug)]
pub enum Init<'a> {
    /// `C = X · Y`.
    Zero,
    /// `C += X · Y`.
    Accumulate,
    /// `C[i, j] = b[i] + (X · Y)[i, j]` (a bias per row: feature-major layers).
    RowBias(&'a [f32]),
    /// `C[i, j] = b[j] + (X · Y)[i, j]` (a bias per column: sample-major layers).
    ColBias(&'a [f32]),
}

/// The pointer form of one product, shared with the kernels. Every access the kernels make
/// is inside the extents [`matmul`] checked.
#[derive(Clone, Copy)]
struct Raw {
    m: usize,
    n: usize,
    k: usize,
    x: *const f32,
    rs_x: usize,
    cs_x: usize,
    y: *const f32,
    ld_y: usize,
    c: *mut f32,
    ld_c: usize,
    init: RawInit,
    /// A hidden layer's activation, applied to each finished block in registers before it is
    /// stored; only the AVX2 kernel takes one (the packed AVX2 layers, see
    /// [`packed`]), every other caller passes `None`.
    act: Option<Activation>,
}

#[derive(Clone, Copy)]
enum RawInit {
    Zero,
    Accumulate,
    RowBias(*const f32),
    ColBias(*const f32),
}

/// `C = init + X · Y` on the calling thread. `Y` must have unit column stride.
/// Panics on mismatched shapes. Never allocates.
pub fn matmul(c: MatMut<'_>, x: MatRef<'_>, y: MatRef<'_>, init: Init<'_>) {
    matmul_at(level(), c, x, y, init)
}

fn matmul_at(lvl: SimdLevel, c: MatMut<'_>, x: MatRef<'_>, y: MatRef<'_>, init: Init<'_>) {
    let (m, n, k) = (c.rows, c.cols, x.cols);
    assert_eq!(x.rows, m, "X has {} rows, C has {m}", x.rows);
    assert_eq!(y.rows, k, "X has {k} columns, Y has {} rows", y.rows);
    assert_eq!(y.cols, n, "Y has {} columns, C has {n}", y.cols);
    assert!(y.cs == 1 || n <= 1, "Y needs unit column stride");
    let init = match init {
        Init::Zero => RawInit::Zero,
        Init::Accumulate => RawInit::Accumulate,
        Init::RowBias(b) => {
            assert!(b.len() >= m, "row bias too short");
            RawInit::RowBias(b.as_ptr())
        }
        Init::ColBias(b) => {
            assert!(b.len() >= n, "column bias too short");
            RawInit::ColBias(b.as_ptr())
        }
    };
    if m == 0 || n == 0 {
        return;
    }
    let raw = Raw {
        m,
        n,
        k,
        x: x.data.as_ptr(),
        rs_x: x.rs,
        cs_x: x.cs,
        y: y.data.as_ptr(),
        ld_y: y.rs,
        c: c.data.as_mut_ptr(),
        ld_c: c.rs,
        init,
        act: None,
    };
    match lvl {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the level guarantees AVX-512F; the views checked every extent.
        SimdLevel::Avx512 => unsafe { x86::drive_avx512(&raw) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the level guarantees AVX2+FMA; the views checked every extent.
        SimdLevel::Avx2 => unsafe { x86::drive_avx2(&raw) },
        // SAFETY: the views checked every extent.
        _ => unsafe { scalar::drive(&raw) },
    }
}

/// Products smaller than this many multiply-adds run on one thread: below it, handing half
/// to another thread costs more than it saves. Measured with `bench train` (CPU time): at the
/// former 2²⁰ the cartpole steps (200-wide layers, batch 32: 1.3 M multiply-adds a product)
/// were split, and a dynamics step cost 0.57 ms of CPU (both threads, the helper's waiting
/// included) and about 1 ms of wall time on the loaded 2-core machine; unsplit it costs
/// 0.10 ms of CPU.
const PARALLEL_MIN_MACS: usize = 1 << 22;

/// [`matmul`], with the rows of `C` split across two rayon tasks when the product is large.
/// The floating-point mode (flush-to-zero) of the calling thread is carried to the helper.
pub fn matmul_par(c: MatMut<'_>, x: MatRef<'_>, y: MatRef<'_>, init: Init<'_>) {
    let (m, n, k) = (c.rows, c.cols, x.cols);
    if m < 24 || m * n * k < PARALLEL_MIN_MACS || rayon::current_num_threads() < 2 {
        return matmul(c, x, y, init);
    }
    assert_eq!(x.rows, m, "X has {} rows, C has {m}", x.rows);
    // Split on a multiple of the AVX-512 row block so neither half gets a ragged block.
    let half = (m / 2).div_ceil(12) * 12;
    let (c_top, c_bottom) = c.split_rows(half);
    let (x_top, x_bottom) = (x.row_range(0, half), x.row_range(half, m - half));
    let (init_top, init_bottom) = match init {
        Init::RowBias(b) => (Init::RowBias(&b[..half]), Init::RowBias(&b[half..])),
        other => (other, other),
    };
    let mode = denormals::current_mode();
    rayon::join(
        || matmul(c_top, x_top, y, init_top),
        || denormals::with_mode(mode, || matmul(c_bottom, x_bottom, y, init_bottom)),
    );
}

/// Writes the transpose of `src` (`rows × cols`, row stride `ld_src`) into `dst`
/// (`cols × rows`, row stride `ld_dst`). Never allocates.
pub fn transpose(
    src: &[f32],
    rows: usize,
    cols: usize,
    ld_src: usize,
    dst: &mut [f32],
    ld_dst: usize,
) {
    transpose_at(level(), src, rows, cols, ld_src, dst, ld_dst)
}

fn transpose_at(
    lvl: SimdLevel,
    src: &[f32],
    rows: usize,
    cols: usize,
    ld_src: usize,
    dst: &mut [f32],
    ld_dst: usize,
) {
    if rows == 0 || cols == 0 {
        return;
    }
    assert!(
        ld_src >= cols && ld_dst >= rows,
        "strides shorter than rows"
    );
    assert!(
        (rows - 1) * ld_src + cols <= src.len() && (cols - 1) * ld_dst + rows <= dst.len(),
        "transpose out of bounds"
    );
    // Whole 8 × 8 blocks with register shuffles where the CPU has AVX; the rest element-wise.
    let (rows8, cols8) = match lvl {
        #[cfg(target_arch = "x86_64")]
        SimdLevel::Avx2 | SimdLevel::Avx512 => {
            let (r8, c8) = (rows / 8, cols / 8);
            // SAFETY: AVX is part of both levels; the extents were checked above.
            unsafe {
                x86::transpose_blocks(src.as_ptr(), ld_src, dst.as_mut_ptr(), ld_dst, r8, c8)
            };
            (r8 * 8, c8 * 8)
        }
        _ => (0, 0),
    };
    for i in 0..rows {
        let row = &src[i * ld_src..i * ld_src + cols];
        let start = if i < rows8 { cols8 } else { 0 };
        for (j, &v) in row.iter().enumerate().skip(start) {
            dst[j * ld_dst + i] = v;
        }
    }
}

#[cfg(test)]
mod tests;

/// Product shapes `(m, n, k)` that exercise every edge of the packed kernels: `m` not a
/// multiple of the row block (every count of leftover rows of the f32 kernel's 12-row block
/// and of the bf16 kernel's 6-row one), `n` not a multiple of the 16-float panel or of the
/// tile (1 panel after the f32 kernel's 2-panel tiles; every bf16 tiling: 1, 2, 3, 4 and
/// 3 + 2 panels, 3 + 3, 4 + 3, 4 + 3 + 3 + 3 and 4 × 4), and odd and even `k` (an odd one
/// leaves the last bf16 pair half empty).
#[cfg(test)]
const RAGGED_SHAPES: [(usize, usize, usize); 17] = [
    (1, 1, 1),
    (5, 3, 7),
    (12, 16, 12),
    (13, 17, 9),
    (25, 33, 31),
    (37, 47, 1),
    (37, 47, 2),
    (24, 64, 50),
    (50, 100, 23),
    (7, 80, 5),
    (11, 96, 3),
    (6, 200, 4),
    (27, 40, 13),
    (28, 48, 6),
    (32, 21, 17),
    (33, 65, 8),
    (34, 250, 11),
];
