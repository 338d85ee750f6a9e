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
    for &(m, n, k) in &[(130, 70, 200), (500, 32, 100), (30, 40, 1000)] {
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

/// Time of the transposes the weight gradients need (a 500-feature, 32-sample batch).
#[test]
#[ignore = "timing, prints numbers"]
fn transpose_timing() {
    let src: Vec<f32> = (0..500 * 32).map(|v| v as f32).collect();
    let mut dst = vec![0.0; 32 * 512];
    let reps = 20000;
    let t = std::time::Instant::now();
    for _ in 0..reps {
        transpose(std::hint::black_box(&src), 500, 32, 32, &mut dst, 512);
    }
    println!(
        "transpose 500×32: {:.2} µs",
        t.elapsed().as_secs_f64() * 1e6 / reps as f64
    );
}

/// Kernel throughput against the `gemm` crate on the networks' shapes.
/// `cargo test -p planner-service --lib matmul::tests::timing -- --ignored --nocapture`
/// (add `--release` for the figures that matter: the dev profile keeps debug assertions on).
#[test]
#[ignore = "timing, prints numbers"]
fn timing() {
    let mut rng = StdRng::seed_from_u64(1);
    // (m, n, k): C is m × n. Feature-major forward of a 500-wide layer on 32 samples is
    // (500, 32, 500); a weight gradient (500, 500, 32); planner chunks (500, 250, 500).
    for &(m, n, k) in &[
        (500, 32, 500),
        (500, 500, 32),
        (500, 250, 500),
        (200, 128, 200),
        (200, 200, 128),
        (200, 250, 200),
    ] {
        let x = random(&mut rng, m * k);
        let y = random(&mut rng, k * n);
        let mut c = vec![0.0; m * n];
        let reps = (4e9 / (2.0 * (m * n * k) as f64)) as usize + 1;
        let flops = 2.0 * (m * n * k) as f64 * reps as f64;
        let t = std::time::Instant::now();
        for _ in 0..reps {
            matmul(
                MatMut::new(&mut c, m, n),
                MatRef::new(&x, m, k),
                MatRef::new(&y, k, n),
                Init::Zero,
            );
        }
        let ours = flops / t.elapsed().as_secs_f64() / 1e9;
        let t = std::time::Instant::now();
        for _ in 0..reps {
            matmul_par(
                MatMut::new(&mut c, m, n),
                MatRef::new(&x, m, k),
                MatRef::new(&y, k, n),
                Init::Zero,
            );
        }
        let par = flops / t.elapsed().as_secs_f64() / 1e9;
        let t = std::time::Instant::now();
        for _ in 0..reps {
            // SAFETY: all three matrices are dense row-major with the given shapes.
            unsafe {
                gemm::gemm(
                    m,
                    n,
                    k,
                    c.as_mut_ptr(),
                    1,
                    n as isize,
                    false,
                    x.as_ptr(),
                    1,
                    k as isize,
                    y.as_ptr(),
                    1,
                    n as isize,
                    0.0,
                    1.0,
                    false,
                    false,
                    false,
                    gemm::Parallelism::None,
                );
            }
        }
        let theirs = flops / t.elapsed().as_secs_f64() / 1e9;
        println!(
            "{m}×{n}×{k}: ours {ours:.1} GFLOP/s (2 threads {par:.1}), gemm crate {theirs:.1} GFLOP/s"
        );
    }
}
