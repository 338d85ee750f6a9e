use super::*;
use crate::nn::simd::SimdLevel;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};

fn random(rng: &mut StdRng, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-1.0..1.0)).collect()
}

/// One product checked against an `f64` reference, with `X` given transposed in memory and
/// strided `Y`/`C`, so every stride path is exercised.
fn check(lvl: Option<SimdLevel>, m: usize, n: usize, k: usize, init_kind: usize, rng: &mut StdRng) {
    // X stored as its transpose (k × m, row stride m + 1): element (i, d) at d (m + 1) + i.
    let x_rs = m + 1;
    let x_store = random(rng, k.max(1) * x_rs);
    let ld_y = n + 5;
    let y_store = random(rng, k * ld_y);
    let ld_c = n + 3;
    let c0 = random(rng, m * ld_c);
    let bias = random(rng, m.max(n));
    let mut want = vec![0.0f64; m * n];
    for i in 0..m {
        for j in 0..n {
            let mut s = match init_kind {
                0 => 0.0,
                1 => c0[i * ld_c + j] as f64,
                2 => bias[i] as f64,
                _ => bias[j] as f64,
            };
            for d in 0..k {
                s += x_store[d * x_rs + i] as f64 * y_store[d * ld_y + j] as f64;
            }
            want[i * n + j] = s;
        }
    }
    let init = match init_kind {
        0 => Init::Zero,
        1 => Init::Accumulate,
        2 => Init::RowBias(&bias),
        _ => Init::ColBias(&bias),
    };
    let mut c = c0.clone();
    let x = MatRef::strided(&x_store, k, m, x_rs, 1).t();
    let y = MatRef::with_stride(&y_store, k, n, ld_y);
    let cm = MatMut::with_stride(&mut c, m, n, ld_c);
    match lvl {
        Some(l) => matmul_at(l, cm, x, y, init),
        None => matmul_par(cm, x, y, init),
    }
    for i in 0..m {
        for j in 0..ld_c {
            let got = c[i * ld_c + j];
            if j < n {
                let err = (got as f64 - want[i * n + j]).abs();
                assert!(
                    err < 2e-6 * (k as f64 + 1.0),
                    "{lvl:?} {m}×{n}×{k} init {init_kind} at ({i},{j}): {got} vs {}",
                    want[i * n + j]
                );
            } else {
                assert_eq!(
                    got,
                    c0[i * ld_c + j],
                    "{lvl:?}: padding column {j} of row {i} was written"
                );
            }
        }
    }
}

#[test]
fn products_match_reference_for_ragged_shapes_every_init_and_level() {
    let mut rng = StdRng::seed_from_u64(3);
    let shapes = [
        (1, 1, 1),
        (5, 3, 15),
        (12, 17, 16),
        (13, 8, 17),
        (25, 64, 33),
        (40, 5, 48),
        (31, 100, 50),
        (7, 9, 0),
        (24, 31, 2),
    ];
    for lvl in SimdLevel::available() {
        for &(m, n, k) in &shapes {
            for init in 0..4 {
                check(Some(lvl), m, n, k, init, &mut rng);
            }
        }
    }
}

#[test]
fn parallel_product_matches_reference() {
    let mut rng = StdRng::seed_from_u64(4);
    for &(m, n, k) in &[(130, 70, 500), (500, 32, 300), (30, 150, 1000)] {
        // Large enough to be split across the two tasks (and an odd split: 130 = 72 + 58).
        assert!(m * n * k >= super::PARALLEL_MIN_MACS && m >= 24);
        for init in 0..4 {
            check(None, m, n, k, init, &mut rng);
        }
    }
}

#[test]
#[should_panic(expected = "Y has 3 rows")]
fn mismatched_shapes_panic() {
    let a = [0.0; 6];
    let mut c = [0.0; 4];
    matmul(
        MatMut::new(&mut c, 2, 2),
        MatRef::new(&a, 2, 2),
        MatRef::new(&a, 3, 2),
        Init::Zero,
    );
}

#[test]
fn transpose_round_trips_at_every_level() {
    for lvl in SimdLevel::available() {
        for &(rows, cols) in &[(37, 23), (8, 8), (16, 40), (5, 3), (1, 17)] {
            let (ld_src, ld_dst) = (cols + 2, rows + 3);
            let src: Vec<f32> = (0..rows * ld_src).map(|v| v as f32).collect();
            let mut t = vec![f32::NAN; cols * ld_dst];
            transpose_at(lvl, &src, rows, cols, ld_src, &mut t, ld_dst);
            for i in 0..rows {
                for j in 0..cols {
                    assert_eq!(
                        t[j * ld_dst + i],
                        src[i * ld_src + j],
                        "{lvl:?} {rows}×{cols} ({i}, {j})"
                    );
                }
            }
            assert!(t[rows].is_nan(), "{lvl:?}: wrote past the row");
            let mut back = vec![0.0; rows * ld_src];
            transpose_at(lvl, &t, cols, rows, ld_dst, &mut back, ld_src);
            for i in 0..rows {
                assert_eq!(
                    back[i * ld_src..i * ld_src + cols],
                    src[i * ld_src..i * ld_src + cols]
                );
            }
        }
    }
}
