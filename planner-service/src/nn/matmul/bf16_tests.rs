//! The bf16 encoding and the bf16 packed layers against plain f64 arithmetic.
//!
//! The kernels are exact up to f32 summation on bf16-rounded operands: a product of two bf16
//! numbers is exact in f32, so the reference rounds the operands the same way and sums in f64.

use super::packed::matmul_packed_at;
use super::{
    Encoding, MatMut, MatRef, PackedMatrix, bf16_bits, bf16_pair, bf16_value, write_bf16_pairs,
};
use crate::nn::activation::Activation;
use crate::nn::simd::{SimdLevel, bf16_dot_available};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};

fn round(x: f32) -> f32 {
    bf16_value(bf16_bits(x))
}

#[test]
fn bf16_rounding_is_to_nearest_even_and_keeps_special_values() {
    // 1 + 2⁻⁸ lies halfway between 1 and 1 + 2⁻⁷: ties go to the even significand (1).
    assert_eq!(round(1.0 + 2f32.powi(-8)), 1.0);
    // 1 + 3·2⁻⁸ lies halfway between 1 + 2⁻⁷ and 1 + 2⁻⁶: even is 1 + 2⁻⁶.
    assert_eq!(round(1.0 + 3.0 * 2f32.powi(-8)), 1.0 + 2f32.powi(-6));
    // Just above a tie rounds up.
    assert_eq!(
        round(1.0 + 2f32.powi(-8) + 2f32.powi(-20)),
        1.0 + 2f32.powi(-7)
    );
    assert_eq!(round(-3.0), -3.0);
    assert_eq!(round(f32::INFINITY), f32::INFINITY);
    assert!(round(f32::NAN).is_nan());
    // A NaN whose payload sits only in the low half must not round to infinity.
    assert!(round(f32::from_bits(0x7F80_0001)).is_nan());
    assert_eq!(round(1e-40).to_bits(), 0);
    assert_eq!(round(-1e-40).to_bits(), 0x8000_0000);
    // Relative rounding error is at most 2⁻⁸.
    let mut rng = StdRng::seed_from_u64(0);
    for _ in 0..10_000 {
        let x: f32 = rng.random_range(-1e6..1e6);
        assert!((round(x) - x).abs() <= x.abs() * 2f32.powi(-8), "{x}");
    }
    let pair = bf16_pair(1.5, -2.0).to_bits();
    assert_eq!((pair & 0xFFFF, pair >> 16), (0x3FC0, 0xC000));
}

/// `act(A · Y + b)` in f64 on bf16-rounded `A` and `Y` (f32 `Y` if `y_f32`), `A` row-major
/// `m × k`, `Y` row-major `k × n`.
fn reference(
    a: &[f32],
    y: &[f32],
    bias: &[f32],
    act: Option<Activation>,
    (m, n, k): (usize, usize, usize),
    y_f32: bool,
) -> Vec<f64> {
    let mut out = vec![0.0; m * n];
    for i in 0..m {
        for j in 0..n {
            let z = bias[i] as f64
                + (0..k)
                    .map(|d| {
                        let (w, v) = (a[i * k + d], y[d * n + j]);
                        if y_f32 {
                            w as f64 * v as f64
                        } else {
                            round(w) as f64 * round(v) as f64
                        }
                    })
                    .sum::<f64>();
            out[i * n + j] = crate::nn::reference::activate(act, z);
        }
    }
    out
}

/// `k × n` row-major values as bf16 pair rows of stride `ld`.
fn to_pairs(y: &[f32], k: usize, n: usize, ld: usize) -> Vec<f32> {
    let rows = Encoding::Bf16Pairs.storage_rows(k);
    let mut out = vec![f32::NAN; rows * ld];
    for p in 0..rows {
        for j in 0..n {
            let at = |d: usize| if d < k { y[d * n + j] } else { 0.0 };
            out[p * ld + j] = bf16_pair(at(2 * p), at(2 * p + 1));
        }
    }
    out
}

/// Element `(i, j)` of a matrix stored in `encoding` with row stride `ld`.
fn element(c: &[f32], encoding: Encoding, ld: usize, i: usize, j: usize) -> f32 {
    match encoding {
        Encoding::F32 => c[i * ld + j],
        Encoding::Bf16Pairs => {
            let word = c[i / 2 * ld + j].to_bits();
            bf16_value(if i.is_multiple_of(2) {
                word as u16
            } else {
                (word >> 16) as u16
            })
        }
    }
}

#[test]
fn bf16_layers_match_the_reference_on_ragged_shapes() {
    // A level without AVX-512 BF16 refuses a bf16 layer (the planner never asks for one there:
    // it falls back to f32).
    let a = PackedMatrix::pack_bf16(MatRef::new(&[1.0; 4], 2, 2));
    let refused = std::panic::catch_unwind(|| {
        let mut c = [0.0; 2];
        let y = [bf16_pair(1.0, 1.0)];
        matmul_packed_at(
            SimdLevel::Scalar,
            MatMut::new(&mut c, 2, 1),
            Encoding::F32,
            &a,
            MatRef::new(&y, 1, 1),
            &[0.0; 2],
            None,
        );
    });
    assert!(refused.is_err(), "a bf16 layer ran without AVX-512 BF16");
    if !bf16_dot_available() {
        return; // nothing else can run on this CPU
    }
    let mut rng = StdRng::seed_from_u64(7);
    let tiles = crate::nn::amx::available();
    if !tiles {
        eprintln!("no AMX-BF16 tiles on this CPU or kernel: the tile kernel is not tested");
    }
    // The AMX kernel's edges lie at 16 and 32 rows, columns and pairs and at groups of 128
    // columns: the extra shapes cross each (several row-block pairs and a lone block, whole
    // and ragged depth chunks, several column groups with a ragged last panel), the last two
    // at the depths of the presets' networks (256 and 517, every kind of block).
    let shapes = super::RAGGED_SHAPES.iter().chain(&[
        (17, 16, 32),
        (33, 145, 70),
        (64, 256, 64),
        (48, 129, 33),
        (80, 300, 130),
        (49, 150, 256),
        (33, 47, 517),
    ]);
    for &(m, n, k) in shapes {
        for (weights, amx, out) in [
            (Encoding::Bf16Pairs, false, Encoding::F32),
            (Encoding::Bf16Pairs, false, Encoding::Bf16Pairs),
            (Encoding::F32, false, Encoding::Bf16Pairs),
            (Encoding::Bf16Pairs, true, Encoding::F32),
            (Encoding::Bf16Pairs, true, Encoding::Bf16Pairs),
        ] {
            if amx && !tiles {
                continue;
            }
            for act in [None, Some(Activation::Swish), Some(Activation::Softplus)] {
                let a: Vec<f32> = (0..m * k).map(|_| rng.random_range(-2.0..2.0)).collect();
                let y: Vec<f32> = (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect();
                let bias: Vec<f32> = (0..m).map(|_| rng.random_range(-1.0..1.0)).collect();
                let ld = n + 5;
                let (packed, y_stored) = match weights {
                    Encoding::F32 => {
                        let mut y_ld = vec![f32::NAN; k * ld];
                        for d in 0..k {
                            y_ld[d * ld..d * ld + n].copy_from_slice(&y[d * n..(d + 1) * n]);
                        }
                        (PackedMatrix::pack(MatRef::new(&a, m, k)), y_ld)
                    }
                    Encoding::Bf16Pairs if amx => (
                        PackedMatrix::pack_bf16_tiles(MatRef::new(&a, m, k)),
                        to_pairs(&y, k, n, ld),
                    ),
                    Encoding::Bf16Pairs => (
                        PackedMatrix::pack_bf16(MatRef::new(&a, m, k)),
                        to_pairs(&y, k, n, ld),
                    ),
                };
                let ld_c = n + 3;
                let c_rows = out.storage_rows(m);
                let mut c = vec![f32::NAN; c_rows * ld_c];
                matmul_packed_at(
                    SimdLevel::Avx512,
                    MatMut::with_stride(&mut c, c_rows, n, ld_c),
                    out,
                    &packed,
                    MatRef::with_stride(&y_stored, weights.storage_rows(k), n, ld),
                    &bias,
                    act,
                );
                let want = reference(&a, &y, &bias, act, (m, n, k), weights == Encoding::F32);
                let what = format!("{weights:?} (tiles: {amx})→{out:?} {act:?} {m}×{n}×{k}");
                for i in 0..m {
                    for j in 0..n {
                        let (got, e) = (element(&c, out, ld_c, i, j) as f64, want[i * n + j]);
                        // f32 summation, plus the output's own rounding when it is bf16.
                        let mut tol = 3e-6 * (k as f64 + 1.0);
                        if out == Encoding::Bf16Pairs {
                            tol += e.abs() * 2f64.powi(-8);
                        }
                        assert!((got - e).abs() <= tol, "{what} ({i},{j}): {got} vs {e}");
                    }
                }
                // Padding columns are never written; an odd last output row pairs with zero.
                for row in c.chunks_exact(ld_c) {
                    assert!(row[n..].iter().all(|v| v.is_nan()), "{what}: padding");
                }
                if out == Encoding::Bf16Pairs && m % 2 == 1 {
                    for j in 0..n {
                        assert_eq!(element(&c, out, ld_c, m, j), 0.0, "{what}: pad row");
                    }
                }
            }
        }
    }
}

/// The conversion a bf16 first layer's input goes through rounds every element as
/// [`bf16_bits`] does (the AVX-512 BF16 path and the portable one alike), ties, subnormals,
/// infinities and NaN included; pairs rows in order, pads an odd last row with zero and writes
/// nothing past the `n` columns.
#[test]
fn input_conversion_to_pairs_rounds_each_element_like_bf16_bits() {
    let mut rng = StdRng::seed_from_u64(8);
    let special = [
        1.0 + 2f32.powi(-8),
        1.0 + 3.0 * 2f32.powi(-8),
        -0.0,
        1e-40,
        -1e-40,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        f32::from_bits(0x7F80_0001),
        f32::MAX,
    ];
    for (k, n) in [(1, 1), (5, 17), (24, 250), (42, 33), (7, 16)] {
        let (ld_src, ld) = (n + 4, n + 3);
        let mut src = vec![f32::NAN; k * ld_src];
        for d in 0..k {
            for j in 0..n {
                src[d * ld_src + j] = if (d * n + j) % 7 == 3 {
                    special[(d + j) % special.len()]
                } else {
                    rng.random_range(-50.0..50.0)
                };
            }
        }
        let rows = Encoding::Bf16Pairs.storage_rows(k);
        let mut dst = vec![f32::NAN; rows * ld];
        write_bf16_pairs(
            MatMut::with_stride(&mut dst, rows, n, ld),
            MatRef::with_stride(&src, k, n, ld_src),
        );
        for p in 0..rows {
            for j in 0..n {
                let at = |d: usize| if d < k { src[d * ld_src + j] } else { 0.0 };
                let word = dst[p * ld + j].to_bits();
                let (lo, hi) = (word as u16, (word >> 16) as u16);
                let (want_lo, want_hi) = (bf16_bits(at(2 * p)), bf16_bits(at(2 * p + 1)));
                assert!(
                    lo == want_lo || (bf16_value(lo).is_nan() && bf16_value(want_lo).is_nan()),
                    "{k}×{n} ({p},{j}) low: {lo:#06x} vs {want_lo:#06x}"
                );
                assert!(
                    hi == want_hi || (bf16_value(hi).is_nan() && bf16_value(want_hi).is_nan()),
                    "{k}×{n} ({p},{j}) high: {hi:#06x} vs {want_hi:#06x}"
                );
            }
            assert!(
                dst[p * ld + n..(p + 1) * ld].iter().all(|v| v.is_nan()),
                "{k}×{n}: padding of row {p} written"
            );
        }
    }
}
