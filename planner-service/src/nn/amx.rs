//! Intel AMX tile primitives: detection, the Linux permission, tile configuration and the
//! instructions the bf16 kernels use (`ldtilecfg`, `tilezero`, `tileloadd`, `tdpbf16ps`,
//! `tilestored`, `tilerelease`).
//!
//! AMX adds eight tile registers (`tmm0`–`tmm7`, up to 16 rows × 64 bytes each) and a matrix
//! unit that multiplies them: one `TDPBF16PS` adds a 16 × 32 bf16 tile times a 32 × 16 one
//! into a 16 × 16 f32 tile (8192 multiply-adds). On the Xeon this project measures on, one
//! core runs it at ~2.7–3.0 TFLOP/s against ~170 GFLOP/s of 512-bit f32 FMA (measured with a
//! register-only loop and with tile loads from L1, see `nn::peak`).
//!
//! Rust has no stable AMX intrinsics, so the instructions are `asm!` with the tile register
//! named by a const generic. The tile state is not preserved across function calls by any
//! ABI, so a kernel configures, uses and releases the tiles within one call on one thread.
//!
//! **Using AMX needs three things:** the CPU (CPUID leaf 7: AMX-TILE and AMX-BF16), the
//! operating system saving the tile state (XCR0 bits 17 and 18, read with `xgetbv`), and on
//! Linux (5.16 and later) the permission `arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`:
//! without it the first tile instruction kills the process with `SIGILL`. The permission is
//! **per process**: measured here, a thread created *before* the request uses the tiles
//! after it, and `ARCH_GET_XCOMP_PERM` reads the same bits on every thread, so one request
//! covers rayon's pool and every later thread. [`available`] makes that request once per
//! process; where any of the three is missing it logs the reason once and reports `false`,
//! and the kernels fall back to AVX-512 (see `bench::kernel`'s path selection).
//!
//! `LDTILECFG` zeroes every tile (measured), so a configuration is loaded only between tiles'
//! accumulations, never in the middle of one.

use std::sync::OnceLock;

/// Rows of a tile register at most.
pub const TILE_ROWS: usize = 16;
/// Bytes of a tile row at most (16 f32, or 16 pairs of bf16).
pub const TILE_BYTES: usize = 64;

/// Whether AMX-BF16 tiles can be used by this process. Detects once: CPUID, the operating
/// system's state saving (XCR0) and, on Linux, the permission request. Logs once why not.
pub fn available() -> bool {
    static AVAILABLE: OnceLock<bool> = OnceLock::new();
    *AVAILABLE.get_or_init(|| match enable() {
        Ok(()) => {
            tracing::debug!("AMX-BF16 tiles enabled");
            true
        }
        Err(why) => {
            tracing::info!("AMX tiles unavailable, kernels use AVX-512 or lower: {why}");
            false
        }
    })
}

/// Why AMX cannot be used, or `Ok` once the permission is granted.
fn enable() -> Result<(), String> {
    #[cfg(target_arch = "x86_64")]
    {
        cpu_has_amx()?;
        os_saves_tiles()?;
        request_permission()
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        Err("not an x86-64 CPU".into())
    }
}

/// CPUID leaf 7: EDX bit 24 AMX-TILE, bit 22 AMX-BF16.
#[cfg(target_arch = "x86_64")]
fn cpu_has_amx() -> Result<(), String> {
    use std::arch::x86_64::{__cpuid, __cpuid_count};
    if __cpuid(0).eax < 7 {
        return Err("CPUID has no leaf 7".into());
    }
    let edx = __cpuid_count(7, 0).edx;
    let tile = edx & (1 << 24) != 0;
    let bf16 = edx & (1 << 22) != 0;
    match (tile, bf16) {
        (true, true) => Ok(()),
        (false, _) => Err("the CPU has no AMX-TILE".into()),
        (true, false) => Err("the CPU has AMX-TILE but no AMX-BF16".into()),
    }
}

/// XCR0 bits 17 (XTILECFG) and 18 (XTILEDATA): the OS enabled the tile state in XSAVE.
#[cfg(target_arch = "x86_64")]
fn os_saves_tiles() -> Result<(), String> {
    use std::arch::x86_64::__cpuid;
    // CPUID.1:ECX.OSXSAVE[27]: `xgetbv` may be executed.
    if __cpuid(1).ecx & (1 << 27) == 0 {
        return Err("the operating system has not enabled XSAVE".into());
    }
    let (lo, _hi): (u32, u32);
    // SAFETY: OSXSAVE is set, so XGETBV with ECX = 0 is defined; it reads a register only.
    unsafe {
        std::arch::asm!("xgetbv", in("ecx") 0u32, out("eax") lo, out("edx") _hi,
            options(nomem, nostack, preserves_flags));
    }
    const TILE_STATE: u32 = (1 << 17) | (1 << 18);
    if lo & TILE_STATE != TILE_STATE {
        return Err(format!(
            "the operating system does not save the tile state (XCR0 = {lo:#x})"
        ));
    }
    Ok(())
}

/// `arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`: once per process (see the module
/// documentation). Kernels before 5.16 lack the call (`EINVAL`) and also do not enable the
/// tile state in XCR0, which [`os_saves_tiles`] already checked.
#[cfg(all(target_arch = "x86_64", target_os = "linux"))]
fn request_permission() -> Result<(), String> {
    const ARCH_GET_XCOMP_PERM: libc::c_long = 0x1022;
    const ARCH_REQ_XCOMP_PERM: libc::c_long = 0x1023;
    const XFEATURE_XTILEDATA: libc::c_long = 18;
    // SAFETY: arch_prctl with an integer argument; the kernel reads nothing from our memory.
    let r = unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_REQ_XCOMP_PERM,
            XFEATURE_XTILEDATA,
        )
    };
    if r != 0 {
        return Err(format!(
            "arch_prctl(ARCH_REQ_XCOMP_PERM, XTILEDATA) refused: {}",
            std::io::Error::last_os_error()
        ));
    }
    let mut granted: u64 = 0;
    // SAFETY: the kernel writes one u64 to the pointer we pass.
    let r = unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_GET_XCOMP_PERM,
            &mut granted as *mut u64,
        )
    };
    if r != 0 || granted & (1 << XFEATURE_XTILEDATA) == 0 {
        return Err(format!(
            "arch_prctl granted the permissions {granted:#x} without XTILEDATA"
        ));
    }
    Ok(())
}

/// Other operating systems enable the tile state for every process when they support it
/// (XCR0, checked above).
#[cfg(all(target_arch = "x86_64", not(target_os = "linux")))]
fn request_permission() -> Result<(), String> {
    Ok(())
}

/// The 64-byte operand of `LDTILECFG` (palette 1): rows and bytes per row of each tile.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileConfig {
    palette: u8,
    start_row: u8,
    reserved: [u8; 14],
    colsb: [u16; 16],
    rows: [u8; 16],
}

impl TileConfig {
    /// Every tile unused (a tile must be configured before an instruction names it).
    pub const fn new() -> Self {
        Self {
            palette: 1,
            start_row: 0,
            reserved: [0; 14],
            colsb: [0; 16],
            rows: [0; 16],
        }
    }

    /// Tile `t` as `rows` rows of `bytes` bytes (`rows ≤ 16`, `bytes ≤ 64`, `bytes` a multiple
    /// of 4 for the tiles `TDPBF16PS` reads or writes).
    pub const fn with_tile(mut self, t: usize, rows: usize, bytes: usize) -> Self {
        assert!(t < 8 && rows <= TILE_ROWS && bytes <= TILE_BYTES);
        self.rows[t] = rows as u8;
        self.colsb[t] = bytes as u16;
        self
    }

    /// Rows and bytes per row of tile `t`.
    pub fn tile(&self, t: usize) -> (usize, usize) {
        (usize::from(self.rows[t]), usize::from(self.colsb[t]))
    }
}

impl Default for TileConfig {
    fn default() -> Self {
        Self::new()
    }
}

/// The tile instructions. Every one is `unsafe`: the caller guarantees [`available`] returned
/// `true`, that a configuration naming every tile used is loaded on this thread, and for loads
/// and stores that each of the tile's rows (`rows × bytes` of its configuration, `stride` bytes
/// apart) lies in memory it may read or write.
#[cfg(target_arch = "x86_64")]
pub mod tile {
    use super::TileConfig;
    use std::arch::asm;

    /// `LDTILECFG`: loads a configuration (and zeroes every tile).
    ///
    /// # Safety
    /// [`available`](super::available) returned `true`; the configuration is valid (palette
    /// 1, rows ≤ 16, bytes ≤ 64), or the instruction faults.
    #[inline(always)]
    pub unsafe fn load_config(config: &TileConfig) {
        // SAFETY: forwarded from the caller; the operand is 64 readable bytes.
        unsafe {
            asm!("ldtilecfg [{}]", in(reg) config as *const TileConfig,
                options(nostack, readonly, preserves_flags))
        }
    }

    /// `TILERELEASE`: returns the tiles to their initial state (unconfigured), so the OS need
    /// not save them on a context switch and the core leaves its AMX power state.
    ///
    /// # Safety
    /// [`available`](super::available) returned `true`.
    #[inline(always)]
    pub unsafe fn release() {
        // SAFETY: forwarded from the caller.
        unsafe { asm!("tilerelease", options(nostack, nomem, preserves_flags)) }
    }

    /// `TILEZERO tmmT`.
    ///
    /// # Safety
    /// See the module documentation.
    #[inline(always)]
    pub unsafe fn zero<const T: u8>() {
        // SAFETY: forwarded from the caller.
        unsafe { asm!("tilezero tmm{t}", t = const T, options(nostack, nomem, preserves_flags)) }
    }

    /// `TILELOADD tmmT, [base + stride]`: the tile's rows from `base`, `stride` bytes apart.
    ///
    /// # Safety
    /// See the module documentation.
    #[inline(always)]
    pub unsafe fn load<const T: u8>(base: *const u8, stride: usize) {
        // SAFETY: forwarded from the caller.
        unsafe {
            asm!("tileloadd tmm{t}, [{b} + {s} * 1]", t = const T, b = in(reg) base,
                s = in(reg) stride, options(nostack, readonly, preserves_flags))
        }
    }

    /// `TILESTORED [base + stride], tmmT`.
    ///
    /// # Safety
    /// See the module documentation.
    #[inline(always)]
    pub unsafe fn store<const T: u8>(base: *mut u8, stride: usize) {
        // SAFETY: forwarded from the caller.
        unsafe {
            asm!("tilestored [{b} + {s} * 1], tmm{t}", t = const T, b = in(reg) base,
                s = in(reg) stride, options(nostack, preserves_flags))
        }
    }

    /// `TDPBF16PS tmmC, tmmA, tmmB`: `C[m][n] += Σₚ A[m].pair(p) · B[p].pair(n)` with f32 sums,
    /// where row `m` of `A` holds bf16 pairs along the depth and row `p` of `B` holds, per
    /// column `n`, the pair of depth elements `2p, 2p + 1` (the project's `Bf16Pairs`
    /// encoding of feature-major activations).
    ///
    /// # Safety
    /// See the module documentation; the tiles' shapes must agree (`A`: M × 4K bytes, `B`:
    /// K × 4N, `C`: M × 4N), or the instruction faults.
    #[inline(always)]
    pub unsafe fn dpbf16ps<const C: u8, const A: u8, const B: u8>() {
        // SAFETY: forwarded from the caller.
        unsafe {
            asm!("tdpbf16ps tmm{c}, tmm{a}, tmm{b}", c = const C, a = const A, b = const B,
                options(nostack, nomem, preserves_flags))
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use crate::nn::matmul::{bf16_bits, bf16_value};

    /// Tiles on this CPU, or a line saying why the test checks nothing more.
    fn tiles_or_skip(test: &str) -> bool {
        if !available() {
            eprintln!("{test}: this CPU or kernel offers no AMX-BF16 tiles; nothing to check");
        }
        available()
    }

    #[test]
    fn detection_agrees_with_the_cpu_flags_and_is_stable() {
        let cpu = cpu_has_amx().is_ok();
        assert_eq!(available(), available());
        if available() {
            assert!(cpu && os_saves_tiles().is_ok());
        }
        if !cpu {
            assert!(!available());
        }
    }

    #[test]
    fn config_layout_is_the_instruction_operand() {
        let c = TileConfig::new().with_tile(2, 16, 64).with_tile(7, 3, 12);
        assert_eq!(std::mem::size_of::<TileConfig>(), 64);
        // SAFETY: TileConfig is 64 plain bytes.
        let bytes: [u8; 64] = unsafe { std::mem::transmute(c) };
        assert_eq!(bytes[0], 1, "palette");
        assert_eq!(u16::from_le_bytes([bytes[16 + 4], bytes[16 + 5]]), 64);
        assert_eq!(u16::from_le_bytes([bytes[16 + 14], bytes[16 + 15]]), 12);
        assert_eq!((bytes[48 + 2], bytes[48 + 7]), (16, 3));
        assert_eq!(c.tile(7), (3, 12));
    }

    /// One 16 × 32 by 32 × 16 product with ragged tiles (`M`, `K`, `N` below the maximum),
    /// against f64 sums of the bf16-rounded operands.
    #[test]
    fn a_tile_product_matches_the_reference_at_ragged_shapes() {
        if !tiles_or_skip("a_tile_product_matches_the_reference_at_ragged_shapes") {
            return;
        }
        for &(m, pairs, n) in &[
            (16, 16, 16),
            (5, 7, 3),
            (16, 1, 9),
            (1, 16, 16),
            (13, 11, 15),
        ] {
            let value = |i: usize, j: usize, s: usize| {
                bf16_value(bf16_bits(((i * 7 + j * 13 + s) % 23) as f32 / 8.0 - 1.3))
            };
            // A: m rows of `pairs` pairs; B: `pairs` rows of n pairs (depth 2p, 2p + 1).
            let mut a = [0u32; 16 * 16];
            let mut b = [0u32; 16 * 16];
            let pair =
                |lo: f32, hi: f32| u32::from(bf16_bits(lo)) | (u32::from(bf16_bits(hi)) << 16);
            for i in 0..m {
                for p in 0..pairs {
                    a[i * 16 + p] = pair(value(i, 2 * p, 1), value(i, 2 * p + 1, 1));
                }
            }
            for p in 0..pairs {
                for j in 0..n {
                    b[p * 16 + j] = pair(value(2 * p, j, 2), value(2 * p + 1, j, 2));
                }
            }
            let mut c = [f32::NAN; 16 * 16];
            let config = TileConfig::new()
                .with_tile(0, m, 4 * n)
                .with_tile(1, m, 4 * pairs)
                .with_tile(2, pairs, 4 * n);
            // SAFETY: tiles are available; each load and store stays inside its 1 KiB array.
            unsafe {
                tile::load_config(&config);
                tile::zero::<0>();
                tile::load::<1>(a.as_ptr().cast(), 64);
                tile::load::<2>(b.as_ptr().cast(), 64);
                tile::dpbf16ps::<0, 1, 2>();
                tile::dpbf16ps::<0, 1, 2>();
                tile::store::<0>(c.as_mut_ptr().cast(), 64);
                tile::release();
            }
            for i in 0..16 {
                for j in 0..16 {
                    let got = c[i * 16 + j];
                    if i < m && j < n {
                        let want: f64 = 2.0
                            * (0..2 * pairs)
                                .map(|d| value(i, d, 1) as f64 * value(d, j, 2) as f64)
                                .sum::<f64>();
                        assert!(
                            (got as f64 - want).abs() < 1e-4 * (1.0 + want.abs()),
                            "{m}×{pairs}×{n} ({i},{j}): {got} vs {want}"
                        );
                    } else {
                        assert!(got.is_nan(), "{m}×{pairs}×{n}: wrote ({i},{j}) outside");
                    }
                }
            }
        }
    }

    #[test]
    fn threads_started_before_and_after_detection_use_the_tiles() {
        if !tiles_or_skip("threads_started_before_and_after_detection_use_the_tiles") {
            return;
        }
        // The permission is per process: a pool thread (started whenever rayon started it) and
        // a fresh thread both run a tile instruction without faulting.
        let run = || {
            let config = TileConfig::new().with_tile(0, 16, 64);
            let mut out = [1.0f32; 256];
            // SAFETY: tiles are available; the store covers exactly `out`.
            unsafe {
                tile::load_config(&config);
                tile::zero::<0>();
                tile::store::<0>(out.as_mut_ptr().cast(), 64);
                tile::release();
            }
            out.iter().all(|&v| v == 0.0)
        };
        assert!(rayon::join(run, run) == (true, true));
        assert!(std::thread::spawn(run).join().unwrap());
    }
}
