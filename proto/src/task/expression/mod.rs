//! Rewards and terminations written as formulas over a transition `s --a--> s_next`, for
//! systems that are not in the catalog.
//!
//! A formula is parsed and checked against the task's dimensions once ([`Expression::parse`]),
//! compiled into a flat list of scalar operations, and then evaluated for a whole population
//! of rows at once without allocating ([`Expression::eval_batch`]), with a reverse-mode
//! gradient for gradient-based planning ([`Expression::eval_grad`]). No maintained crate fits:
//! `evalexpr`, `meval` and `fasteval` evaluate one scalar `f64` formula at a time with no
//! vectors and no derivatives, and `exmex`, which differentiates, builds a separate symbolic
//! expression per partial derivative of named scalar variables (one per coordinate, evaluated
//! one row at a time); none batches rows or checks vector indices against dimensions.
//!
//! # The language
//!
//! ```text
//! formula    := or
//! or         := and ( "||" and )*
//! and        := comparison ( "&&" comparison )*
//! comparison := sum ( ("<" | "<=" | ">" | ">=" | "==" | "!=") sum )?
//! sum        := product ( ("+" | "-") product )*
//! product    := unary ( ("*" | "/") unary )*
//! unary      := ("-" | "!") unary | power
//! power      := postfix ( "^" unary )?          right-associative: -x^2 is -(x^2)
//! postfix    := primary ( "[" index "]" )*
//! index      := N | N? ":" N?                   whole-number literals, slices half-open
//! primary    := number | name | name "(" args? ")" | "(" formula ")" | "[" formula ("," formula)* "]"
//! ```
//!
//! - **Inputs** are the vectors `s` (the observation, `obs_dim` long), `a` (the action,
//!   `act_dim`) and `s_next` (the observation the action led to, `obs_dim`). There are no
//!   aliases: one spelling each, the ones the catalog's documentation uses. `s[3]` is a
//!   coordinate (from 0), `s[0:3]` the vector of coordinates 0, 1, 2, `s[:3]` and `s[14:]` leave
//!   a bound out. Any vector can be indexed, including `[0.45, -0.05, -0.25]`, a vector literal.
//! - **Constants**: numbers (`2`, `0.5`, `.5`, `1e-3`, finite in `f32`), `pi`, `e`.
//! - **Arithmetic** `+ - * / ^`, unary `-`, and the functions `sin cos exp log tanh abs sqrt`
//!   apply element by element to vectors; a scalar combines with every element of a vector,
//!   two vectors must have the same length. `x^n` with a whole-number literal `n` is repeated
//!   multiplication (`x^2` is exactly `x*x`), any other power is `powf`.
//! - **Reductions** give scalars: `sum(v)`, `norm(v)` (L2, `sqrt(sum(v*v))`), `norm1(v)`
//!   (`sum(abs(v))`), `dot(u, v)` (`sum(u*v)`), and `min(…)`/`max(…)` over every element of
//!   every argument (`min(x, 0)`, `max(s_next[0:3])`). Sums run left to right from the first
//!   element, as the catalog's Rust rewards do, so a built-in reward written as a formula gives
//!   the same numbers.
//! - **Conditions**: comparisons give 1 (true) or 0 (false) and do not chain (`0 < x < 1` is
//!   an error; write `0 < x && x < 1`); `&&`, `||` and `!` treat every number but 0 as true
//!   (NaN included); `if(c, x, y)` is `x` where `c` is true, else `y`.
//!
//! The formula must be a scalar: a reward, or for a termination a number that is true (not 0)
//! where the episode ends, e.g. `!(s_next[0] >= 0.2 && s_next[0] <= 1)`.
//!
//! Evaluation follows IEEE `f32` arithmetic: `log(0)` is `-inf`, `0/0` NaN; the caller decides
//! what a non-finite reward means. Gradients are exact derivatives of what is computed, with
//! these conventions at kinks: `abs` and `sqrt` have slope 0 at 0 (so `norm` of a zero vector
//! has a zero gradient), `min`/`max` pass the gradient to the element they chose (the first on
//! a tie), comparisons and logic pass none, `if` passes it to the branch it took only (the
//! other branch contributes 0 even where its derivative is infinite), and `x^y` has no
//! gradient in `y` where `x ≤ 0`.
//!
//! # Bounds
//!
//! A formula is at most [`MAX_SOURCE_BYTES`] long, nests at most [`MAX_NESTING`] levels
//! (parentheses, calls, signs, powers), and compiles to at most [`MAX_OPERATIONS`] scalar
//! operations once vectors are expanded (`norm(s)` is `3·obs_dim` of them: loads, squares,
//! sums and a root). Beyond any of these, and for any mistake, [`Expression::parse`] returns
//! an [`ExpressionError`] naming the offending text and its byte offset; it never panics or
//! overflows the stack.

mod error;
mod eval;
mod lexer;
mod parser;
mod program;

pub use error::{ErrorKind, ExpressionError};
pub use eval::Scratch;

use program::{Op, Program};

/// Longest formula accepted, in bytes. A reward is a line or two; this leaves room for long
/// sums written out coordinate by coordinate.
pub const MAX_SOURCE_BYTES: usize = 16 * 1024;
/// Deepest nesting of parentheses, calls, signs and powers.
pub const MAX_NESTING: usize = 64;
/// Most scalar operations a formula may compile to (after sharing repeated ones).
pub const MAX_OPERATIONS: usize = 4096;

/// The dimensions a formula is checked against.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Dims {
    pub obs_dim: usize,
    pub act_dim: usize,
}

/// The three inputs of a formula.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Input {
    /// `s`: the observation before the action.
    S,
    /// `a`: the action.
    A,
    /// `s_next`: the observation after it.
    SNext,
}

/// A batch of transitions, row-major: row `i` of `s` is `s[i*obs_dim..(i+1)*obs_dim]`.
/// An input the formula does not read ([`Expression::reads`]) may be empty.
#[derive(Clone, Copy, Debug)]
pub struct Inputs<'a> {
    pub s: &'a [f32],
    pub a: &'a [f32],
    pub s_next: &'a [f32],
}

/// Where [`Expression::eval_grad`] writes each row's gradient, laid out like [`Inputs`]. Each
/// slice is overwritten (zeros for an input the formula does not read), or skipped if empty.
#[derive(Debug)]
pub struct Gradients<'a> {
    pub s: &'a mut [f32],
    pub a: &'a mut [f32],
    pub s_next: &'a mut [f32],
}

/// A checked, compiled formula. Immutable and `Sync`: threads share one and each evaluates
/// with a [`Scratch`] of its own.
#[derive(Clone, Debug, PartialEq)]
pub struct Expression {
    source: String,
    dims: Dims,
    program: Program,
    /// Whether the program loads `s`, `a`, `s_next` (in [`Input`] order).
    reads: [bool; 3],
}

impl Expression {
    /// Parses `source` and checks it against `dims`: every index in range, every vector where a
    /// vector may be, known names and functions with the right number of arguments, a scalar
    /// result, and the bounds on size.
    pub fn parse(source: &str, dims: Dims) -> Result<Self, ExpressionError> {
        let program = parser::compile(source, dims)?;
        let reads = [Input::S, Input::A, Input::SNext].map(|input| {
            program
                .ops
                .iter()
                .any(|op| matches!(op, Op::Load(i, _) if *i == input))
        });
        Ok(Self {
            program,
            source: source.to_string(),
            dims,
            reads,
        })
    }

    /// The formula as written.
    pub fn source(&self) -> &str {
        &self.source
    }

    /// The dimensions it was checked against.
    pub fn dims(&self) -> Dims {
        self.dims
    }

    /// Whether the formula reads `input` at all (after simplification: `0*s[0]` does not).
    pub fn reads(&self, input: Input) -> bool {
        self.reads[input as usize]
    }

    /// Scalar operations per row.
    pub fn operations(&self) -> usize {
        self.program.ops.len()
    }

    /// Working memory for [`Expression::eval_batch`] and [`Expression::eval_grad`] on any number
    /// of rows. With it, neither allocates.
    pub fn scratch(&self) -> Scratch {
        Scratch::for_ops(self.program.ops.len(), true)
    }

    /// The formula for every row of `inputs`, into `out` (its length is the number of rows).
    ///
    /// # Panics
    /// If an input the formula reads does not hold `out.len()` rows, or one it does not read
    /// is neither empty nor that size.
    pub fn eval_batch(&self, inputs: Inputs, out: &mut [f32], scratch: &mut Scratch) {
        self.check(&inputs, None, out.len());
        self.program.eval_batch(self.dims, &inputs, out, scratch);
    }

    /// [`Expression::eval_batch`], and the gradient of each row's result with respect to that
    /// row's `s`, `a` and `s_next` into `grads`.
    ///
    /// # Panics
    /// As [`Expression::eval_batch`], and if a non-empty gradient slice does not hold
    /// `out.len()` rows.
    pub fn eval_grad(
        &self,
        inputs: Inputs,
        out: &mut [f32],
        mut grads: Gradients,
        scratch: &mut Scratch,
    ) {
        self.check(&inputs, Some(&grads), out.len());
        self.program
            .eval_grad(self.dims, &inputs, out, &mut grads, scratch);
    }

    fn check(&self, inputs: &Inputs, grads: Option<&Gradients>, rows: usize) {
        let named = [
            (Input::S, "s", inputs.s.len(), grads.map(|g| g.s.len())),
            (Input::A, "a", inputs.a.len(), grads.map(|g| g.a.len())),
            (
                Input::SNext,
                "s_next",
                inputs.s_next.len(),
                grads.map(|g| g.s_next.len()),
            ),
        ];
        for (input, name, len, grad_len) in named {
            let want = rows * self.dims.of(input);
            assert!(
                len == want || (len == 0 && !self.reads(input)),
                "{name}: {len} numbers for {rows} rows of {}",
                self.dims.of(input)
            );
            if let Some(g) = grad_len {
                assert!(
                    g == want || g == 0,
                    "gradient of {name}: {g} numbers for {rows} rows"
                );
            }
        }
    }
}

#[cfg(test)]
mod tests;
