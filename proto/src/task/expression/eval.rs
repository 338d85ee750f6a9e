//! Evaluation of a [`Program`] for a batch of rows, and its reverse-mode gradient.
//!
//! Rows are processed in blocks of [`BLOCK`]: each operation is one tight loop over the block
//! (a column of numbers), reading the columns of earlier operations from the scratch. A block's
//! columns stay in cache whatever the batch size, and the scratch holds one block per operation,
//! so it never grows with the batch. The gradient runs the block forward, keeping every
//! column, then walks the operations backwards accumulating adjoints (`∂result/∂column`), and
//! scatters the adjoints of loads into the input gradients.

use super::program::{Binary, Op, Program, Reg, Unary, truthy};
use super::{Dims, Gradients, Input, Inputs};

/// Rows evaluated together.
pub(super) const BLOCK: usize = 64;

/// Working memory for evaluating one expression: a column per operation for the values and,
/// for gradients, for the adjoints. Made by [`Expression::scratch`](super::Expression::scratch);
/// one per thread evaluating at once.
#[derive(Clone, Debug, Default)]
pub struct Scratch {
    values: Vec<f32>,
    adjoints: Vec<f32>,
}

impl Scratch {
    /// Room for a program of `ops` operations (and their adjoints if `gradient`).
    pub(super) fn for_ops(ops: usize, gradient: bool) -> Self {
        let mut s = Self::default();
        s.reserve(ops, gradient);
        s
    }

    /// Grows to fit `ops` operations; allocates only if this scratch was made for a smaller
    /// program.
    fn reserve(&mut self, ops: usize, gradient: bool) {
        if self.values.len() < ops * BLOCK {
            self.values.resize(ops * BLOCK, 0.0);
        }
        if gradient && self.adjoints.len() < ops * BLOCK {
            self.adjoints.resize(ops * BLOCK, 0.0);
        }
    }
}

impl Inputs<'_> {
    fn get(&self, input: Input) -> &[f32] {
        match input {
            Input::S => self.s,
            Input::A => self.a,
            Input::SNext => self.s_next,
        }
    }
}

impl Gradients<'_> {
    fn get(&mut self, input: Input) -> &mut [f32] {
        match input {
            Input::S => self.s,
            Input::A => self.a,
            Input::SNext => self.s_next,
        }
    }
}

impl Dims {
    pub(super) fn of(&self, input: Input) -> usize {
        match input {
            Input::S | Input::SNext => self.obs_dim,
            Input::A => self.act_dim,
        }
    }
}

impl Program {
    /// Writes each row's result into `out` (one per row).
    pub(super) fn eval_batch(
        &self,
        dims: Dims,
        inputs: &Inputs,
        out: &mut [f32],
        scratch: &mut Scratch,
    ) {
        scratch.reserve(self.ops.len(), false);
        let values = &mut scratch.values[..self.ops.len() * BLOCK];
        self.fill_constants(values);
        for first in (0..out.len()).step_by(BLOCK) {
            let rows = BLOCK.min(out.len() - first);
            self.forward(dims, inputs, first, rows, values);
            out[first..first + rows].copy_from_slice(&column(values, self.output)[..rows]);
        }
    }

    /// [`Program::eval_batch`], and each row's gradient into `grads` (overwritten; an empty
    /// slice is skipped).
    pub(super) fn eval_grad(
        &self,
        dims: Dims,
        inputs: &Inputs,
        out: &mut [f32],
        grads: &mut Gradients,
        scratch: &mut Scratch,
    ) {
        let n = self.ops.len();
        scratch.reserve(n, true);
        let values = &mut scratch.values[..n * BLOCK];
        let adjoints = &mut scratch.adjoints[..n * BLOCK];
        self.fill_constants(values);
        for input in [Input::S, Input::A, Input::SNext] {
            grads.get(input).fill(0.0);
        }
        for first in (0..out.len()).step_by(BLOCK) {
            let rows = BLOCK.min(out.len() - first);
            self.forward(dims, inputs, first, rows, values);
            out[first..first + rows].copy_from_slice(&column(values, self.output)[..rows]);
            self.backward(dims, grads, first, rows, values, adjoints);
        }
    }

    /// Constants do not change from block to block: their columns are filled once per call.
    fn fill_constants(&self, values: &mut [f32]) {
        for (op, col) in self.ops.iter().zip(values.chunks_exact_mut(BLOCK)) {
            if let Op::Const(bits) = *op {
                col.fill(f32::from_bits(bits));
            }
        }
    }

    /// Every operation's column for rows `first..first + rows`.
    fn forward(&self, dims: Dims, inputs: &Inputs, first: usize, rows: usize, values: &mut [f32]) {
        for (i, op) in self.ops.iter().enumerate() {
            let (done, rest) = values.split_at_mut(i * BLOCK);
            let out = &mut rest[..rows];
            let col = |r: Reg| &column(done, r)[..rows];
            match *op {
                Op::Const(_) => {}
                Op::Load(input, index) => {
                    let dim = dims.of(input);
                    let data = &inputs.get(input)[first * dim..];
                    for (k, o) in out.iter_mut().enumerate() {
                        *o = data[k * dim + index as usize];
                    }
                }
                Op::Unary(u, x) => unary(u, col(x), out),
                Op::Binary(b, x, y) => binary(b, col(x), col(y), out),
                Op::Select(c, x, y) => {
                    for (((o, &c), &x), &y) in out.iter_mut().zip(col(c)).zip(col(x)).zip(col(y)) {
                        *o = if truthy(c) { x } else { y };
                    }
                }
            }
        }
    }

    /// Adjoints from the result back to the loads, added into `grads`.
    fn backward(
        &self,
        dims: Dims,
        grads: &mut Gradients,
        first: usize,
        rows: usize,
        values: &[f32],
        adjoints: &mut [f32],
    ) {
        adjoints.fill(0.0);
        adjoints[self.output as usize * BLOCK..][..rows].fill(1.0);
        for (i, op) in self.ops.iter().enumerate().rev() {
            let (earlier, rest) = adjoints.split_at_mut(i * BLOCK);
            let g = &rest[..rows];
            let val = |r: Reg| &column(values, r)[..rows];
            match *op {
                Op::Const(_) => {}
                Op::Load(input, index) => {
                    let dim = dims.of(input);
                    let d = grads.get(input);
                    if !d.is_empty() {
                        let d = &mut d[first * dim..];
                        for (k, g) in g.iter().enumerate() {
                            d[k * dim + index as usize] += g;
                        }
                    }
                }
                Op::Unary(u, x) => {
                    let (xs, ys) = (val(x), val(i as Reg));
                    let dx = &mut column_mut(earlier, x)[..rows];
                    for (((d, &g), &x), &y) in dx.iter_mut().zip(g).zip(xs).zip(ys) {
                        *d += chain(g, u.derivative(x, y));
                    }
                }
                Op::Binary(b, x, y) if x != y => {
                    let (xs, ys, zs) = (val(x), val(y), val(i as Reg));
                    let (dx, dy) = two_columns_mut(earlier, x, y);
                    binary_backward(b, g, xs, ys, zs, &mut dx[..rows], &mut dy[..rows]);
                }
                Op::Binary(b, x, _) => {
                    // `x op x` (a square written `x*x`): both partials go to one column.
                    let (xs, zs) = (val(x), val(i as Reg));
                    let dx = &mut column_mut(earlier, x)[..rows];
                    for (((d, &g), &x), &z) in dx.iter_mut().zip(g).zip(xs).zip(zs) {
                        let (px, py) = b.derivatives(x, x, z);
                        *d += chain(g, px) + chain(g, py);
                    }
                }
                Op::Select(c, x, y) => {
                    let cs = val(c);
                    let (xo, yo) = (x as usize * BLOCK, y as usize * BLOCK);
                    for k in 0..rows {
                        let to = if truthy(cs[k]) { xo } else { yo };
                        earlier[to + k] += g[k];
                    }
                }
            }
        }
    }
}

/// `g · d`, but 0 where `g` is 0: a branch `if` did not take, or a factor with a zero
/// gradient, passes nothing on even where its own derivative is infinite (`log` at 0).
#[inline(always)]
fn chain(g: f32, d: f32) -> f32 {
    if g == 0.0 { 0.0 } else { g * d }
}

fn column(values: &[f32], r: Reg) -> &[f32] {
    &values[r as usize * BLOCK..][..BLOCK]
}

fn column_mut(values: &mut [f32], r: Reg) -> &mut [f32] {
    &mut values[r as usize * BLOCK..][..BLOCK]
}

/// The columns of two different operations, both mutable.
fn two_columns_mut(values: &mut [f32], x: Reg, y: Reg) -> (&mut [f32], &mut [f32]) {
    let (lo, hi) = (x.min(y) as usize, x.max(y) as usize);
    let (head, tail) = values.split_at_mut(hi * BLOCK);
    let (low, high) = (&mut head[lo * BLOCK..][..BLOCK], &mut tail[..BLOCK]);
    if x < y { (low, high) } else { (high, low) }
}

/// Adds `g·∂z/∂x` to `dx` and `g·∂z/∂y` to `dy` for `z = b(x, y)`; sums, differences and
/// products get loops of their own so that they vectorise.
fn binary_backward(
    b: Binary,
    g: &[f32],
    xs: &[f32],
    ys: &[f32],
    zs: &[f32],
    dx: &mut [f32],
    dy: &mut [f32],
) {
    let pairs = dx.iter_mut().zip(dy.iter_mut()).zip(g);
    match b {
        Binary::Add => pairs.for_each(|((dx, dy), &g)| {
            *dx += g;
            *dy += g;
        }),
        Binary::Sub => pairs.for_each(|((dx, dy), &g)| {
            *dx += g;
            *dy -= g;
        }),
        Binary::Mul => pairs
            .zip(xs.iter().zip(ys))
            .for_each(|(((dx, dy), &g), (&x, &y))| {
                *dx += chain(g, y);
                *dy += chain(g, x);
            }),
        _ => pairs
            .zip(xs.iter().zip(ys).zip(zs))
            .for_each(|(((dx, dy), &g), ((&x, &y), &z))| {
                let (px, py) = b.derivatives(x, y, z);
                *dx += chain(g, px);
                *dy += chain(g, py);
            }),
    }
}

/// `out = u(x)`; the common operations get loops of their own so that they vectorise.
fn unary(u: Unary, x: &[f32], out: &mut [f32]) {
    fn map(x: &[f32], out: &mut [f32], f: impl Fn(f32) -> f32) {
        for (o, &x) in out.iter_mut().zip(x) {
            *o = f(x);
        }
    }
    match u {
        Unary::Neg => map(x, out, |x| -x),
        Unary::Abs => map(x, out, f32::abs),
        Unary::PowI(2) => map(x, out, |x| x * x),
        _ => map(x, out, |x| u.apply(x)),
    }
}

/// `out = b(x, y)`; the common operations get loops of their own so that they vectorise.
fn binary(b: Binary, x: &[f32], y: &[f32], out: &mut [f32]) {
    fn map(x: &[f32], y: &[f32], out: &mut [f32], f: impl Fn(f32, f32) -> f32) {
        for ((o, &x), &y) in out.iter_mut().zip(x).zip(y) {
            *o = f(x, y);
        }
    }
    match b {
        Binary::Add => map(x, y, out, |x, y| x + y),
        Binary::Sub => map(x, y, out, |x, y| x - y),
        Binary::Mul => map(x, y, out, |x, y| x * y),
        Binary::Div => map(x, y, out, |x, y| x / y),
        _ => map(x, y, out, |x, y| b.apply(x, y)),
    }
}
