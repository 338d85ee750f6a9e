//! The language's semantics, its errors, hostile inputs, the gradient against finite
//! differences, and agreement with the catalog's Rust rewards written as formulas.

use super::*;
use crate::Builtin;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};

const SMALL: Dims = Dims {
    obs_dim: 4,
    act_dim: 2,
};

fn parse(source: &str) -> Expression {
    Expression::parse(source, SMALL).unwrap_or_else(|e| panic!("{source}: {e}"))
}

fn error(source: &str, dims: Dims) -> ExpressionError {
    match Expression::parse(source, dims) {
        Ok(_) => panic!("{source} parsed"),
        Err(e) => e,
    }
}

/// The formula on one transition.
fn eval1(e: &Expression, s: &[f32], a: &[f32], s_next: &[f32]) -> f32 {
    let mut out = [0.0];
    e.eval_batch(Inputs { s, a, s_next }, &mut out, &mut e.scratch());
    out[0]
}

/// A formula of constants (any dimensions).
fn value(source: &str) -> f32 {
    eval1(&parse(source), &[0.0; 4], &[0.0; 2], &[0.0; 4])
}

/// `rows` random rows of each input, uniform in `[-range, range)`.
fn random_batch(dims: Dims, rows: usize, range: f32, seed: u64) -> [Vec<f32>; 3] {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut draw =
        |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-range..range)).collect() };
    [
        draw(rows * dims.obs_dim),
        draw(rows * dims.act_dim),
        draw(rows * dims.obs_dim),
    ]
}

#[test]
fn arithmetic_follows_the_documented_precedence() {
    assert_eq!(value("1 + 2 * 3"), 7.0);
    assert_eq!(value("(1 + 2) * 3"), 9.0);
    assert_eq!(value("-2^2"), -4.0);
    assert_eq!(value("2^3^2"), 512.0);
    assert_eq!(value("2^-1"), 0.5);
    assert_eq!(value("8 / 2 / 2"), 2.0);
    assert_eq!(value("7 - 2 - 1"), 4.0);
    assert_eq!(value("1 < 2 && 3 > 4"), 0.0);
    assert_eq!(value("1 < 2 || 3 > 4"), 1.0);
    assert_eq!(value("!(1 == 1) + (2 != 2) + (2 <= 2) + (3 >= 4)"), 1.0);
    assert_eq!(value("if(0, 5, 6) + if(-0.5, 10, 20)"), 16.0);
    assert!((value("pi") - std::f32::consts::PI).abs() < 1e-7);
    assert!((value("log(e)") - 1.0).abs() < 1e-6);
    assert_eq!(value("min(3, [4, -1], 2) + max([1, 5, 2])"), 4.0);
    assert_eq!(value("sum([1, 2, 3] * 2 + 1)"), 15.0);
    assert_eq!(
        value("norm([3, 4]) + norm1([-1, 2]) + dot([1, 2], [3, 4])"),
        5.0 + 3.0 + 11.0
    );
    assert_eq!(
        value("[5, 6, 7, 8][1:3][1] + [1, 2, 3][:2][0] + [1, 2, 3][2:][0]"),
        11.0
    );
    assert_eq!(
        value("abs(-3) + sqrt(16) + tanh(0) + exp(0) + sin(0) + cos(0)"),
        9.0
    );
    assert_eq!(value("2.5e1 + .5 + 1."), 26.5);
    // NaN is true; `min` ignores a NaN.
    assert_eq!(value("if(0/0, 1, 2)"), 1.0);
    assert_eq!(value("min(0/0, 3)"), 3.0);
}

#[test]
fn reads_inputs_by_index_and_slice() {
    let e = parse("s[0] + 10*a[1] + 100*s_next[3] + sum(s_next[1:3]) + norm1(s - s_next)");
    let (s, a, n) = ([1.0, 2.0, 3.0, 4.0], [5.0, 6.0], [7.0, 8.0, 9.0, 10.0]);
    assert_eq!(eval1(&e, &s, &a, &n), 1.0 + 60.0 + 1000.0 + 17.0 + 24.0);
    assert!(e.reads(Input::S) && e.reads(Input::A) && e.reads(Input::SNext));

    // Inputs the formula does not read may be left empty; simplified-away ones do not count.
    let e = parse("s_next[2] + 0 * s[0] * 3 - if(1, 0, a[0])");
    assert!(!e.reads(Input::A) && e.reads(Input::S) && e.reads(Input::SNext));
    let e = parse("2 * s_next[2]");
    assert!(!e.reads(Input::S) && !e.reads(Input::A));
    assert_eq!(eval1(&e, &[], &[], &n), 18.0);
}

#[test]
fn repeated_work_is_shared_and_constants_folded() {
    let once = parse("sin(s_next[1])");
    let twice = parse("sin(s_next[1]) * sin(s_next[1]) + 2 * 3");
    // load, sin, product, constant 6, sum.
    assert_eq!((once.operations(), twice.operations()), (2, 5));
    assert_eq!(parse("norm(s)").operations(), 4 + 4 + 3 + 1);
}

#[test]
fn errors_name_the_offending_text_and_its_offset() {
    let e = error("exp(-s[0]^2)+s[7]", SMALL);
    assert_eq!(
        e.to_string().lines().next().unwrap(),
        "s[7]: index 7 out of range for s (obs_dim 4) at 13"
    );
    assert_eq!(e.to_string().lines().nth(2).unwrap(), "               ^^^^");

    let cases: &[(&str, usize, &str, ErrorKind)] = &[
        (
            "a[2]",
            0,
            "a[2]",
            ErrorKind::IndexOutOfRange {
                index: 2,
                of: "a (act_dim 2)".into(),
            },
        ),
        (
            "[1, 2][5]",
            0,
            "[1, 2][5]",
            ErrorKind::IndexOutOfRange {
                index: 5,
                of: "a vector of length 2".into(),
            },
        ),
        (
            "s[1:9]",
            0,
            "s[1:9]",
            ErrorKind::BadSlice {
                start: 1,
                end: 9,
                of: "s (obs_dim 4)".into(),
            },
        ),
        (
            "s[3:3]",
            0,
            "s[3:3]",
            ErrorKind::BadSlice {
                start: 3,
                end: 3,
                of: "s (obs_dim 4)".into(),
            },
        ),
        ("s[1.5]", 2, "1.5", ErrorKind::BadIndex),
        ("s[-1]", 2, "-", ErrorKind::BadIndex),
        ("s[]", 2, "]", ErrorKind::BadIndex),
        ("s[0][0]", 0, "s[0][0]", ErrorKind::NotAVector),
        ("1 + obs[0]", 4, "obs", ErrorKind::UnknownName),
        ("sn[0]", 0, "sn", ErrorKind::UnknownName),
        ("2 * sinh(a[0])", 4, "sinh", ErrorKind::UnknownFunction),
        ("s(0)", 0, "s", ErrorKind::UnknownFunction),
        (
            "1 + dot(a)",
            4,
            "dot(a)",
            ErrorKind::Arity {
                function: "dot",
                expected: "2",
                got: 1,
            },
        ),
        (
            "sin(1, 2)",
            0,
            "sin(1, 2)",
            ErrorKind::Arity {
                function: "sin",
                expected: "1",
                got: 2,
            },
        ),
        (
            "max()",
            0,
            "max()",
            ErrorKind::Arity {
                function: "max",
                expected: "1 or more",
                got: 0,
            },
        ),
        ("s", 0, "s", ErrorKind::NotAScalar(4)),
        ("1 + a * 2", 0, "1 + a * 2", ErrorKind::NotAScalar(2)),
        ("s_next[0:3]", 0, "s_next[0:3]", ErrorKind::NotAScalar(3)),
        ("[1, s]", 4, "s", ErrorKind::NotAScalar(4)),
        ("dot(s, a)", 0, "dot(s, a)", ErrorKind::LengthMismatch(4, 2)),
        ("norm(s + a)", 5, "s + a", ErrorKind::LengthMismatch(4, 2)),
        ("0 < a[0] < 1", 9, "<", ErrorKind::ChainedComparison),
        ("(a[0] + 1", 9, "end of input", ErrorKind::Expected("`)`")),
        (
            "a[0] a[1]",
            5,
            "a",
            ErrorKind::Expected("an operator or the end of the formula"),
        ),
        (
            "2x",
            1,
            "x",
            ErrorKind::Expected("an operator or the end of the formula"),
        ),
        (
            "",
            0,
            "end of input",
            ErrorKind::Expected("a number, a name, `(` or `[`"),
        ),
        (
            "1 + * 2",
            4,
            "*",
            ErrorKind::Expected("a number, a name, `(` or `[`"),
        ),
        ("a[0] # 2", 5, "#", ErrorKind::UnexpectedCharacter),
        ("1e39 * a[0]", 0, "1e39", ErrorKind::BadNumber),
    ];
    for (source, offset, token, kind) in cases {
        let e = error(source, SMALL);
        assert_eq!(
            (e.offset, e.token.as_str(), &e.kind),
            (*offset, *token, kind),
            "{source}: {e}"
        );
        assert!(e.to_string().contains(&format!("at {offset}")), "{e}");
    }
}

#[test]
fn hostile_sources_get_clear_errors() {
    let megabyte = "a[0]+".repeat(200_000) + "1";
    let e = error(&megabyte, SMALL);
    assert_eq!(
        e.kind,
        ErrorKind::TooLong {
            len: megabyte.len(),
            max: MAX_SOURCE_BYTES
        }
    );

    let parens = "(".repeat(8000) + "a[0]" + &")".repeat(8000);
    assert_eq!(
        error(&parens, SMALL).kind,
        ErrorKind::TooDeep { max: MAX_NESTING }
    );
    let signs = "-".repeat(10_000) + "a[0]";
    assert_eq!(
        error(&signs, SMALL).kind,
        ErrorKind::TooDeep { max: MAX_NESTING }
    );
    let calls = "sin(".repeat(3000) + "1" + &")".repeat(3000);
    assert_eq!(
        error(&calls, SMALL).kind,
        ErrorKind::TooDeep { max: MAX_NESTING }
    );
    let powers = "a[0]^".repeat(3000) + "2";
    assert_eq!(
        error(&powers, SMALL).kind,
        ErrorKind::TooDeep { max: MAX_NESTING }
    );
    let literals = "[".repeat(3000) + "1" + &"]".repeat(3000);
    assert_eq!(
        error(&literals, SMALL).kind,
        ErrorKind::TooDeep { max: MAX_NESTING }
    );
    // Nesting just inside the bound is fine.
    let ok = "(".repeat(MAX_NESTING - 1) + "a[0]" + &")".repeat(MAX_NESTING - 1);
    assert_eq!(eval1(&parse(&ok), &[0.0; 4], &[3.0, 0.0], &[0.0; 4]), 3.0);

    let wide = Dims {
        obs_dim: 5000,
        act_dim: 1,
    };
    assert_eq!(
        error("norm(s)", wide).kind,
        ErrorKind::TooLarge {
            max: MAX_OPERATIONS
        }
    );
    assert!(
        Expression::parse("s[4999] - s_next[0]", wide).is_ok(),
        "one load, not 5000"
    );
    let mid = Dims {
        obs_dim: 100,
        act_dim: 1,
    };
    let products = format!("sum(s{})", "*s".repeat(50));
    assert_eq!(
        error(&products, mid).kind,
        ErrorKind::TooLarge {
            max: MAX_OPERATIONS
        }
    );
    // A long flat chain compiles in a loop: no stack depth, just operations.
    let chain = "a[0]*a[1]+".repeat(1500) + "0";
    assert!(Expression::parse(&chain, SMALL).is_ok());

    let empty = Dims {
        obs_dim: 0,
        act_dim: 0,
    };
    for source in ["sum(a)", "norm(s)", "max(s_next)", "dot(a, a)"] {
        assert_eq!(
            error(source, empty).kind,
            ErrorKind::EmptyVector,
            "{source}"
        );
    }
    assert_eq!(
        error("s[0]", empty).kind,
        ErrorKind::IndexOutOfRange {
            index: 0,
            of: "s (obs_dim 0)".into()
        }
    );
    assert!(Expression::parse("1 + 2", empty).is_ok());
    let digits = "9".repeat(1000);
    assert_eq!(error(&digits, SMALL).kind, ErrorKind::BadNumber);
    assert_eq!(error("s[99999999999]", SMALL).kind, ErrorKind::BadIndex);
    assert_eq!(
        error("s[16777216]", SMALL).kind,
        ErrorKind::IndexOutOfRange {
            index: 1 << 24,
            of: "s (obs_dim 4)".into()
        }
    );
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2000))]

    /// Any string made of the language's pieces (and some that are not) parses or is refused
    /// with an error pointing into the source; one that parses evaluates, and its gradient
    /// pass gives the same values.
    #[test]
    fn any_token_soup_parses_or_fails_cleanly(pieces in proptest::collection::vec(
        proptest::sample::select(vec![
            "s", "a", "s_next", "[", "]", "(", ")", ",", ":", "0", "1", "3", "7", "2.5", "1e30",
            "+", "-", "*", "/", "^", "<", "<=", "==", "&&", "||", "!", "sin", "norm", "dot",
            "min", "if", "sum", "pi", "é", " ", "#",
        ]),
        0..40,
    )) {
        let source: String = pieces.concat();
        // Zero dimensions too: every reduction and index must be refused, never panic.
        let _ = Expression::parse(&source, Dims { obs_dim: 0, act_dim: 0 });
        match Expression::parse(&source, SMALL) {
            Err(e) => {
                proptest::prop_assert!(e.offset <= source.len(), "{source}: {e}");
                proptest::prop_assert!(source.is_char_boundary(e.offset), "{source}: {e}");
                let _ = e.to_string();
            }
            Ok(e) => {
                let [s, a, n] = random_batch(SMALL, 3, 2.0, 1);
                let inputs = Inputs { s: &s, a: &a, s_next: &n };
                let (mut plain, mut with_grad) = ([0.0; 3], [0.0; 3]);
                let mut scratch = e.scratch();
                e.eval_batch(inputs, &mut plain, &mut scratch);
                let (mut ds, mut da, mut dn) = (vec![0.0; 12], vec![0.0; 6], vec![0.0; 12]);
                let grads = Gradients { s: &mut ds, a: &mut da, s_next: &mut dn };
                e.eval_grad(inputs, &mut with_grad, grads, &mut scratch);
                for (p, g) in plain.iter().zip(&with_grad) {
                    proptest::prop_assert!(p.to_bits() == g.to_bits() || (p.is_nan() && g.is_nan()), "{source}");
                }
            }
        }
    }
}

/// Formulas exercising every operation, differentiated on a batch longer than a block (so
/// block boundaries are crossed) and checked against central differences. A central
/// difference means nothing where a kink or a jump (`max`, `abs`, `if`, a comparison) lies
/// within the step of the point: such points are recognised by their one-sided differences
/// disagreeing, and may be at most a few percent of the rows.
#[test]
fn gradients_match_finite_differences() {
    let formulas = [
        "exp(-((s_next[0] - 0.6*sin(s_next[1]))^2 + (-0.6*cos(s_next[1]) - 0.6)^2)/0.36) - 0.01*dot(a, a)",
        "tanh(s[0]*a[1]) + log(2 + s_next[2]) * sqrt(3 + s[3]) - abs(a[0] - s[1])^3 / (2 + s_next[3]^2)",
        "norm(s_next - s) + norm1(s_next[1:3] - [0.1, -0.2]) + max(a) - min(s_next, a[1])",
        "if(s[0] > 0, (2 + s_next[1])^-2, 3*a[0]) + (2 + sin(a[1]))^(1 + 0.5*cos(s[2])) + sum(a*s[0:2])",
        "(s[0] < 0.5 && a[0] > -0.5) * s_next[0]^2 + !(s[1] >= 0) * s_next[2] - (1 || 0)",
    ];
    let rows = 150;
    let mut kinks_seen = 0;
    for (f, source) in formulas.iter().enumerate() {
        let e = parse(source);
        let [s, a, n] = random_batch(SMALL, rows, 0.9, f as u64);
        let mut out = vec![0.0; rows];
        let (mut ds, mut da, mut dn) = (
            vec![f32::NAN; rows * 4],
            vec![f32::NAN; rows * 2],
            vec![f32::NAN; rows * 4],
        );
        let mut scratch = e.scratch();
        let grads = Gradients {
            s: &mut ds,
            a: &mut da,
            s_next: &mut dn,
        };
        e.eval_grad(
            Inputs {
                s: &s,
                a: &a,
                s_next: &n,
            },
            &mut out,
            grads,
            &mut scratch,
        );

        let h = 1e-3f32;
        let mut fd_out = vec![0.0; rows];
        let mut eval_at = |s: &[f32], a: &[f32], n: &[f32]| -> Vec<f32> {
            e.eval_batch(Inputs { s, a, s_next: n }, &mut fd_out, &mut scratch);
            fd_out.clone()
        };
        for (which, (x, dx, dim)) in [(&s, &ds, 4), (&a, &da, 2), (&n, &dn, 4)]
            .into_iter()
            .enumerate()
        {
            for j in 0..dim {
                // Move coordinate j of every row at once: rows are independent.
                let shifted = |delta: f32| -> Vec<f32> {
                    let mut x = x.clone();
                    for r in 0..rows {
                        x[r * dim + j] += delta;
                    }
                    x
                };
                let (up, down) = (shifted(h), shifted(-h));
                let (fu, fd) = match which {
                    0 => (eval_at(&up, &a, &n), eval_at(&down, &a, &n)),
                    1 => (eval_at(&s, &up, &n), eval_at(&s, &down, &n)),
                    _ => (eval_at(&s, &a, &up), eval_at(&s, &a, &down)),
                };
                let mut kinks = 0;
                for r in 0..rows {
                    let want = (fu[r] as f64 - fd[r] as f64) / (2.0 * h as f64);
                    let forward = (fu[r] as f64 - out[r] as f64) / h as f64;
                    let backward = (out[r] as f64 - fd[r] as f64) / h as f64;
                    if (forward - backward).abs() > 0.1 * (1.0 + want.abs()) {
                        kinks += 1;
                        continue;
                    }
                    let got = dx[r * dim + j] as f64;
                    assert!(
                        (got - want).abs() <= 1e-2 * (1.0 + want.abs()),
                        "{source}: input {which}, row {r}, coordinate {j}: {got} vs {want}"
                    );
                }
                assert!(
                    kinks <= rows / 20,
                    "{source}: input {which}, coordinate {j}: {kinks} kinks"
                );
                kinks_seen += kinks;
            }
        }
    }
    assert!(kinks_seen < 20, "{kinks_seen} points next to a kink");
}

#[test]
fn batches_agree_with_single_rows_and_need_no_full_inputs_for_gradients() {
    let e = parse("sin(s[0]) * a[1] + s_next[3]^2");
    let rows = 3 * eval::BLOCK + 5;
    let [s, a, n] = random_batch(SMALL, rows, 1.0, 9);
    let mut out = vec![0.0; rows];
    e.eval_batch(
        Inputs {
            s: &s,
            a: &a,
            s_next: &n,
        },
        &mut out,
        &mut e.scratch(),
    );
    for r in 0..rows {
        let one = eval1(&e, &s[r * 4..][..4], &a[r * 2..][..2], &n[r * 4..][..4]);
        assert_eq!(out[r], one, "row {r}");
    }
    // Only the action's gradient asked for.
    let mut da = vec![0.0; rows * 2];
    let mut grad_out = vec![0.0; rows];
    let grads = Gradients {
        s: &mut [],
        a: &mut da,
        s_next: &mut [],
    };
    e.eval_grad(
        Inputs {
            s: &s,
            a: &a,
            s_next: &n,
        },
        &mut grad_out,
        grads,
        &mut e.scratch(),
    );
    assert_eq!(grad_out, out);
    for r in 0..rows {
        assert_eq!(da[r * 2], 0.0);
        assert_eq!(da[r * 2 + 1], s[r * 4].sin());
    }
}

#[test]
fn untaken_branches_pass_no_gradient() {
    // log(a[0]) is -inf with an infinite slope at 0, in the branch not taken.
    let e = parse("if(a[0] > 0, log(a[0]), 2*a[0]) + sqrt(a[1]^2) + norm([a[1], 0])");
    let (mut out, mut da) = ([0.0], [0.0; 2]);
    let grads = Gradients {
        s: &mut [],
        a: &mut da,
        s_next: &mut [],
    };
    e.eval_grad(
        Inputs {
            s: &[],
            a: &[0.0, 0.0],
            s_next: &[],
        },
        &mut out,
        grads,
        &mut e.scratch(),
    );
    assert_eq!((out[0], da), (0.0, [2.0, 0.0]));
}

#[test]
#[should_panic(expected = "s: 3 numbers for 1 rows of 4")]
fn short_inputs_are_refused() {
    let e = parse("s[0]");
    e.eval_batch(
        Inputs {
            s: &[0.0; 3],
            a: &[],
            s_next: &[],
        },
        &mut [0.0],
        &mut e.scratch(),
    );
}

/// The catalog's rewards written as formulas, with the functions they must agree with.
fn catalog_formulas() -> Vec<(Builtin, &'static str)> {
    let formulas: Vec<_> = Builtin::ALL
        .iter()
        .filter_map(|&b| b.reward_formula().map(|f| (b, f)))
        .collect();
    assert_eq!(formulas.len(), 4, "every catalog reward but reacher3d's");
    formulas
}

fn dims_of(task: Builtin) -> Dims {
    Dims {
        obs_dim: task.task().obs_dim,
        act_dim: task.task().act_dim,
    }
}

#[test]
fn catalog_rewards_written_as_formulas_agree_with_the_rust_ones() {
    let rows = 500;
    for (task, source) in catalog_formulas() {
        let spec = task.task();
        let dims = dims_of(task);
        let e = Expression::parse(source, dims).unwrap_or_else(|err| panic!("{task}: {err}"));
        assert!(
            !e.reads(Input::S),
            "{task}: the catalog's rewards do not read s"
        );
        let [s, a, n] = random_batch(dims, rows, 2.0, 17);
        let (o, u) = (dims.obs_dim, dims.act_dim);
        let mut out = vec![0.0; rows];
        let (mut da, mut dn) = (vec![0.0; rows * u], vec![0.0; rows * o]);
        let grads = Gradients {
            s: &mut [],
            a: &mut da,
            s_next: &mut dn,
        };
        e.eval_grad(
            Inputs {
                s: &s,
                a: &a,
                s_next: &n,
            },
            &mut out,
            grads,
            &mut e.scratch(),
        );
        let (mut want_da, mut want_dn) = (vec![0.0; u], vec![0.0; o]);
        for r in 0..rows {
            let (s, a, n) = (&s[r * o..][..o], &a[r * u..][..u], &n[r * o..][..o]);
            let want = spec.reward_gradient(s, a, n, &mut want_da, &mut want_dn);
            let close = |x: f32, y: f32| (x - y).abs() <= 1e-5 * (1.0 + y.abs());
            assert!(close(out[r], want), "{task} row {r}: {} vs {want}", out[r]);
            for (k, (g, w)) in da[r * u..][..u].iter().zip(&want_da).enumerate() {
                assert!(close(*g, *w), "{task} row {r}: ∂r/∂a[{k}] {g} vs {w}");
            }
            for (k, (g, w)) in dn[r * o..][..o].iter().zip(&want_dn).enumerate() {
                assert!(close(*g, *w), "{task} row {r}: ∂r/∂s_next[{k}] {g} vs {w}");
            }
        }
    }
}

#[test]
fn ants_termination_written_as_a_formula_agrees_with_the_rust_one() {
    let spec = Builtin::Ant.task();
    let e = Expression::parse(
        "!(s_next[0] >= 0.2 && s_next[0] <= 1)",
        dims_of(Builtin::Ant),
    )
    .unwrap();
    let rows = 400;
    let [_, _, mut n] = random_batch(dims_of(Builtin::Ant), rows, 1.5, 5);
    // The edges of the healthy range exactly, and a NaN height (not healthy).
    n[0] = 0.2;
    n[27] = 1.0;
    n[54] = f32::NAN;
    let mut out = vec![0.0; rows];
    e.eval_batch(
        Inputs {
            s: &[],
            a: &[],
            s_next: &n,
        },
        &mut out,
        &mut e.scratch(),
    );
    let mut ended = 0;
    for r in 0..rows {
        let want = spec.is_terminal(&n[r * 27..][..27]);
        assert_eq!(out[r] != 0.0, want, "row {r}: height {}", n[r * 27]);
        ended += usize::from(want);
    }
    assert!(
        ended > 50 && ended < rows - 50,
        "both outcomes occur: {ended}"
    );
}
