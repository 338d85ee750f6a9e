//! The compiled form of a formula: a flat list of scalar operations in evaluation order.
//!
//! Vectors exist only while parsing: `norm(s[0:3])` becomes three loads, three products, two
//! sums and a square root. Each operation reads earlier operations' results (by index) and
//! produces one number per row, so a program is evaluated for a whole batch one operation at a
//! time (see `eval.rs`), and its reverse-mode gradient walks the same list backwards. The
//! builder folds operations on constants with the very functions evaluation uses, shares
//! repeated operations (`sin(s_next[1])` written twice is computed once), and drops operations
//! the result does not use.

use super::Input;
use std::collections::HashMap;

/// Index of an operation, whose result it names.
pub(super) type Reg = u32;

/// One scalar operation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Op {
    /// A constant (its `f32` bits, so that operations can be hashed).
    Const(u32),
    /// Coordinate `index` of an input row.
    Load(Input, u32),
    Unary(Unary, Reg),
    Binary(Binary, Reg, Reg),
    /// `if(c, x, y)`: `x` where `c ≠ 0` (NaN counts as true), else `y`.
    Select(Reg, Reg, Reg),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Unary {
    Neg,
    /// Logical not: 1 where the operand is 0, else 0.
    Not,
    Sin,
    Cos,
    Exp,
    Log,
    Tanh,
    Abs,
    Sqrt,
    /// An integer power `x^n` with `n` written as a whole-number literal.
    PowI(i32),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Binary {
    Add,
    Sub,
    Mul,
    Div,
    Pow,
    Min,
    Max,
    Lt,
    Le,
    Gt,
    Ge,
    Eq,
    Ne,
    And,
    Or,
}

/// A compiled formula: its operations and which one is the result.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Program {
    pub ops: Vec<Op>,
    pub output: Reg,
}

/// 1 for true, 0 for false.
fn flag(b: bool) -> f32 {
    if b { 1.0 } else { 0.0 }
}

/// Whether a number counts as true: anything but ±0 (NaN included).
pub(super) fn truthy(x: f32) -> bool {
    x != 0.0
}

impl Unary {
    /// The operation on one number.
    #[inline(always)]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Unary::Neg => -x,
            Unary::Not => flag(!truthy(x)),
            Unary::Sin => x.sin(),
            Unary::Cos => x.cos(),
            Unary::Exp => x.exp(),
            Unary::Log => x.ln(),
            Unary::Tanh => x.tanh(),
            Unary::Abs => x.abs(),
            Unary::Sqrt => x.sqrt(),
            Unary::PowI(2) => x * x,
            Unary::PowI(n) => x.powi(n),
        }
    }

    /// `∂y/∂x` at `x`, where `y = self.apply(x)`. Kinks take one-sided conventions that keep a
    /// gradient finite and follow the catalog's rewards: `abs` has 0 at 0, `sqrt` has 0 at 0
    /// (so `norm` of a zero vector has a zero gradient rather than NaN).
    #[inline(always)]
    pub fn derivative(self, x: f32, y: f32) -> f32 {
        match self {
            Unary::Neg => -1.0,
            Unary::Not => 0.0,
            Unary::Sin => x.cos(),
            Unary::Cos => -x.sin(),
            Unary::Exp => y,
            Unary::Log => 1.0 / x,
            Unary::Tanh => 1.0 - y * y,
            Unary::Abs => {
                if x == 0.0 {
                    0.0
                } else {
                    x.signum()
                }
            }
            Unary::Sqrt => {
                if y > 0.0 {
                    0.5 / y
                } else {
                    0.0
                }
            }
            Unary::PowI(0) => 0.0,
            Unary::PowI(n) => n as f32 * x.powi(n - 1),
        }
    }
}

impl Binary {
    /// The operation on two numbers. `min`/`max` ignore a NaN operand (as `f32::min` does).
    #[inline(always)]
    pub fn apply(self, x: f32, y: f32) -> f32 {
        match self {
            Binary::Add => x + y,
            Binary::Sub => x - y,
            Binary::Mul => x * y,
            Binary::Div => x / y,
            Binary::Pow => x.powf(y),
            Binary::Min => x.min(y),
            Binary::Max => x.max(y),
            Binary::Lt => flag(x < y),
            Binary::Le => flag(x <= y),
            Binary::Gt => flag(x > y),
            Binary::Ge => flag(x >= y),
            Binary::Eq => flag(x == y),
            Binary::Ne => flag(x != y),
            Binary::And => flag(truthy(x) && truthy(y)),
            Binary::Or => flag(truthy(x) || truthy(y)),
        }
    }

    /// `(∂z/∂x, ∂z/∂y)` at `(x, y)`, where `z = self.apply(x, y)`. Comparisons and logic have
    /// zero gradients; `min`/`max` pass it to the operand they chose (the first on a tie);
    /// `x^y` has no gradient in `y` where `x ≤ 0` (`ln x` is undefined there).
    #[inline(always)]
    pub fn derivatives(self, x: f32, y: f32, z: f32) -> (f32, f32) {
        match self {
            Binary::Add => (1.0, 1.0),
            Binary::Sub => (1.0, -1.0),
            Binary::Mul => (y, x),
            Binary::Div => (1.0 / y, -z / y),
            Binary::Pow => (y * x.powf(y - 1.0), if x > 0.0 { z * x.ln() } else { 0.0 }),
            Binary::Min | Binary::Max => {
                if z == x {
                    (1.0, 0.0)
                } else {
                    (0.0, 1.0)
                }
            }
            Binary::Lt
            | Binary::Le
            | Binary::Gt
            | Binary::Ge
            | Binary::Eq
            | Binary::Ne
            | Binary::And
            | Binary::Or => (0.0, 0.0),
        }
    }
}

/// The program grew past its bound.
#[derive(Debug)]
pub(super) struct TooLarge;

/// Builds a [`Program`] operation by operation.
pub(super) struct Builder {
    ops: Vec<Op>,
    /// Each operation already built, so that a repeated one is shared.
    known: HashMap<Op, Reg>,
    max_ops: usize,
}

impl Builder {
    pub fn new(max_ops: usize) -> Self {
        Self {
            ops: Vec::new(),
            known: HashMap::new(),
            max_ops,
        }
    }

    /// The constant `value`.
    pub fn constant(&mut self, value: f32) -> Result<Reg, TooLarge> {
        self.push(Op::Const(value.to_bits()))
    }

    /// The result of `op`: folded if its operands are constants, shared if built before.
    pub fn push(&mut self, op: Op) -> Result<Reg, TooLarge> {
        let op = match op {
            Op::Unary(u, x) => match self.constant_value(x) {
                Some(x) => Op::Const(u.apply(x).to_bits()),
                None => op,
            },
            Op::Binary(b, x, y) => match (self.constant_value(x), self.constant_value(y)) {
                (Some(x), Some(y)) => Op::Const(b.apply(x, y).to_bits()),
                _ => op,
            },
            Op::Select(c, x, y) => match self.constant_value(c) {
                Some(c) => return Ok(if truthy(c) { x } else { y }),
                None => op,
            },
            Op::Const(_) | Op::Load(..) => op,
        };
        if let Some(&reg) = self.known.get(&op) {
            return Ok(reg);
        }
        if self.ops.len() >= self.max_ops {
            return Err(TooLarge);
        }
        let reg = self.ops.len() as Reg;
        self.ops.push(op);
        self.known.insert(op, reg);
        Ok(reg)
    }

    /// The value of `reg` if it is a constant.
    pub fn constant_value(&self, reg: Reg) -> Option<f32> {
        match self.ops[reg as usize] {
            Op::Const(bits) => Some(f32::from_bits(bits)),
            _ => None,
        }
    }

    /// The program computing `output`, without the operations it does not use.
    pub fn finish(self, output: Reg) -> Program {
        let mut live = vec![false; self.ops.len()];
        live[output as usize] = true;
        for (i, op) in self.ops.iter().enumerate().rev() {
            if !live[i] {
                continue;
            }
            match *op {
                Op::Const(_) | Op::Load(..) => {}
                Op::Unary(_, x) => live[x as usize] = true,
                Op::Binary(_, x, y) => {
                    live[x as usize] = true;
                    live[y as usize] = true;
                }
                Op::Select(c, x, y) => {
                    for r in [c, x, y] {
                        live[r as usize] = true;
                    }
                }
            }
        }
        let mut renamed = vec![0; self.ops.len()];
        let mut ops = Vec::with_capacity(live.iter().filter(|l| **l).count());
        for (i, op) in self.ops.iter().enumerate() {
            if !live[i] {
                continue;
            }
            let r = |x: Reg| renamed[x as usize];
            let op = match *op {
                Op::Unary(u, x) => Op::Unary(u, r(x)),
                Op::Binary(b, x, y) => Op::Binary(b, r(x), r(y)),
                Op::Select(c, x, y) => Op::Select(r(c), r(x), r(y)),
                other => other,
            };
            renamed[i] = ops.len() as Reg;
            ops.push(op);
        }
        Program {
            output: renamed[output as usize],
            ops,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folds_constants_shares_repeats_and_drops_dead_operations() {
        let mut b = Builder::new(100);
        let x = b.push(Op::Load(Input::SNext, 1)).unwrap();
        let unused = b.push(Op::Load(Input::S, 0)).unwrap();
        let _dead = b.push(Op::Unary(Unary::Exp, unused)).unwrap();
        let sin1 = b.push(Op::Unary(Unary::Sin, x)).unwrap();
        let sin2 = b.push(Op::Unary(Unary::Sin, x)).unwrap();
        assert_eq!(sin1, sin2, "a repeated operation is shared");
        let two = b.constant(2.0).unwrap();
        let three = b.constant(3.0).unwrap();
        let six = b.push(Op::Binary(Binary::Mul, two, three)).unwrap();
        let y = b.push(Op::Binary(Binary::Mul, six, sin1)).unwrap();
        let one = b.constant(1.0).unwrap();
        assert_eq!(
            b.push(Op::Select(one, y, x)).unwrap(),
            y,
            "a constant condition"
        );
        let p = b.finish(y);
        assert_eq!(
            p.ops,
            [
                Op::Load(Input::SNext, 1),
                Op::Unary(Unary::Sin, 0),
                Op::Const(6.0f32.to_bits()),
                Op::Binary(Binary::Mul, 2, 1),
            ]
        );
        assert_eq!(p.output, 3);
    }

    #[test]
    fn stops_at_its_bound() {
        let mut b = Builder::new(2);
        let x = b.push(Op::Load(Input::A, 0)).unwrap();
        let y = b.push(Op::Unary(Unary::Neg, x)).unwrap();
        assert_eq!(
            b.push(Op::Unary(Unary::Neg, x)).unwrap(),
            y,
            "shared: no new operation"
        );
        assert!(b.push(Op::Unary(Unary::Sin, y)).is_err());
    }

    /// Each derivative against central differences in f64 at a point away from kinks.
    #[test]
    fn derivatives_match_finite_differences() {
        let h = 1e-3f64;
        let unary = [
            Unary::Neg,
            Unary::Sin,
            Unary::Cos,
            Unary::Exp,
            Unary::Log,
            Unary::Tanh,
            Unary::Abs,
            Unary::Sqrt,
            Unary::PowI(2),
            Unary::PowI(3),
            Unary::PowI(-2),
            Unary::PowI(0),
        ];
        for u in unary {
            for x in [0.7f32, 1.9, -0.4] {
                if matches!(u, Unary::Log | Unary::Sqrt) && x < 0.0 {
                    continue;
                }
                let f = |x: f64| u.apply(x as f32) as f64;
                let fd = (f(x as f64 + h) - f(x as f64 - h)) / (2.0 * h);
                let d = u.derivative(x, u.apply(x)) as f64;
                assert!(
                    (d - fd).abs() < 1e-2 * (1.0 + fd.abs()),
                    "{u:?} at {x}: {d} vs {fd}"
                );
            }
        }
        let binary = [
            Binary::Add,
            Binary::Sub,
            Binary::Mul,
            Binary::Div,
            Binary::Pow,
            Binary::Min,
            Binary::Max,
        ];
        for b in binary {
            for (x, y) in [(0.7f32, 1.3f32), (1.9, -0.6), (2.5, 0.4)] {
                let z = b.apply(x, y);
                let (dx, dy) = b.derivatives(x, y, z);
                let f = |x: f64, y: f64| b.apply(x as f32, y as f32) as f64;
                let (x, y) = (x as f64, y as f64);
                let fdx = (f(x + h, y) - f(x - h, y)) / (2.0 * h);
                let fdy = (f(x, y + h) - f(x, y - h)) / (2.0 * h);
                assert!(
                    (dx as f64 - fdx).abs() < 1e-2 * (1.0 + fdx.abs()),
                    "{b:?} ∂x at {x},{y}"
                );
                assert!(
                    (dy as f64 - fdy).abs() < 1e-2 * (1.0 + fdy.abs()),
                    "{b:?} ∂y at {x},{y}"
                );
            }
        }
    }

    #[test]
    fn kinks_take_finite_conventions() {
        assert_eq!(Unary::Abs.derivative(0.0, 0.0), 0.0);
        assert_eq!(Unary::Sqrt.derivative(0.0, 0.0), 0.0);
        assert_eq!(Binary::Min.derivatives(1.0, 1.0, 1.0), (1.0, 0.0));
        assert_eq!(Binary::Pow.derivatives(-2.0, 2.0, 4.0), (-4.0, 0.0));
        assert_eq!(Binary::Lt.derivatives(1.0, 2.0, 1.0), (0.0, 0.0));
        assert!(truthy(f32::NAN) && !truthy(-0.0));
    }
}
