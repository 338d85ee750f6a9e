//! A recursive-descent parser that compiles a formula straight into a [`Program`], checking
//! every index, length and arity against the task's dimensions as it goes.
//!
//! There is no syntax tree: each grammar rule returns the [`Value`] it computed (a scalar
//! operation, a list of them for a vector, or a whole input not yet loaded), so a long chain
//! like `a[0] + a[1] + … ` is built in a loop and never becomes a deep structure that a later
//! recursive pass (or drop) could overflow the stack on. Recursion happens only through
//! [`Parser::unary`], which counts it against [`MAX_NESTING`].

use super::error::{ErrorKind, ExpressionError};
use super::lexer::{self, Tok, Token};
use super::program::{Binary, Builder, Op, Program, Reg, Unary};
use super::{Dims, Input, MAX_NESTING, MAX_OPERATIONS, MAX_SOURCE_BYTES};

/// The functions a formula may call.
pub(super) const FUNCTIONS: &[&str] = &[
    "sin", "cos", "exp", "log", "tanh", "abs", "sqrt", "sum", "norm", "norm1", "dot", "min", "max",
    "if",
];

/// Largest `|n|` of an integer power computed by repeated multiplication (`x^2` is `x·x`
/// exactly, as the catalog's rewards write it); other exponents go through `powf`.
const MAX_INTEGER_POWER: f32 = 64.0;

/// What a piece of a formula evaluates to.
#[derive(Clone, Debug)]
enum Value {
    Scalar(Reg),
    Vector(Vec<Reg>),
    /// A whole input row (`s`, `a`, `s_next`), loaded only where it is used as a vector, so
    /// that `s[3]` costs one load even for a large observation.
    Input(Input),
}

/// A value and the byte range of the source it came from.
#[derive(Clone, Debug)]
struct Spanned {
    value: Value,
    start: usize,
    end: usize,
}

/// Compiles `source` for inputs of `dims`; the formula must be a scalar.
pub(super) fn compile(source: &str, dims: Dims) -> Result<Program, ExpressionError> {
    if source.len() > MAX_SOURCE_BYTES {
        return Err(ExpressionError::too_long(source.len(), MAX_SOURCE_BYTES));
    }
    let mut parser = Parser {
        source,
        tokens: lexer::tokens(source)?,
        pos: 0,
        depth: 0,
        dims,
        builder: Builder::new(MAX_OPERATIONS),
    };
    let formula = parser.expr()?;
    if parser.peek().tok != Tok::End {
        return Err(parser.error_here(ErrorKind::Expected("an operator or the end of the formula")));
    }
    let output = parser.scalar(&formula)?;
    Ok(parser.builder.finish(output))
}

struct Parser<'s> {
    source: &'s str,
    tokens: Vec<Token<'s>>,
    pos: usize,
    /// Current nesting, counted in [`Parser::unary`].
    depth: usize,
    dims: Dims,
    builder: Builder,
}

impl<'s> Parser<'s> {
    // ---- tokens ----

    fn peek(&self) -> Token<'s> {
        self.tokens[self.pos]
    }

    fn advance(&mut self) -> Token<'s> {
        let t = self.tokens[self.pos];
        if t.tok != Tok::End {
            self.pos += 1;
        }
        t
    }

    /// Consumes the punctuation `p` if it comes next.
    fn eat(&mut self, p: &str) -> Option<Token<'s>> {
        match self.peek().tok {
            Tok::Punct(q) if q == p => Some(self.advance()),
            _ => None,
        }
    }

    /// Consumes the punctuation `p`, which must come next.
    fn expect(&mut self, p: &str, what: &'static str) -> Result<Token<'s>, ExpressionError> {
        self.eat(p)
            .ok_or_else(|| self.error_here(ErrorKind::Expected(what)))
    }

    fn error(&self, start: usize, end: usize, kind: ErrorKind) -> ExpressionError {
        ExpressionError::new(self.source, start, end, kind)
    }

    fn error_here(&self, kind: ErrorKind) -> ExpressionError {
        let t = self.peek();
        self.error(t.start, t.end, kind)
    }

    // ---- grammar, loosest binding first ----

    fn expr(&mut self) -> Result<Spanned, ExpressionError> {
        self.or()
    }

    fn or(&mut self) -> Result<Spanned, ExpressionError> {
        let mut left = self.and()?;
        while self.eat("||").is_some() {
            let right = self.and()?;
            left = self.binary(Binary::Or, left, right)?;
        }
        Ok(left)
    }

    fn and(&mut self) -> Result<Spanned, ExpressionError> {
        let mut left = self.comparison()?;
        while self.eat("&&").is_some() {
            let right = self.comparison()?;
            left = self.binary(Binary::And, left, right)?;
        }
        Ok(left)
    }

    fn comparison_operator(&self) -> Option<Binary> {
        match self.peek().tok {
            Tok::Punct("<") => Some(Binary::Lt),
            Tok::Punct("<=") => Some(Binary::Le),
            Tok::Punct(">") => Some(Binary::Gt),
            Tok::Punct(">=") => Some(Binary::Ge),
            Tok::Punct("==") => Some(Binary::Eq),
            Tok::Punct("!=") => Some(Binary::Ne),
            _ => None,
        }
    }

    fn comparison(&mut self) -> Result<Spanned, ExpressionError> {
        let left = self.sum()?;
        let Some(op) = self.comparison_operator() else {
            return Ok(left);
        };
        self.advance();
        let right = self.sum()?;
        if self.comparison_operator().is_some() {
            return Err(self.error_here(ErrorKind::ChainedComparison));
        }
        self.binary(op, left, right)
    }

    fn sum(&mut self) -> Result<Spanned, ExpressionError> {
        let mut left = self.product()?;
        loop {
            let op = if self.eat("+").is_some() {
                Binary::Add
            } else if self.eat("-").is_some() {
                Binary::Sub
            } else {
                return Ok(left);
            };
            let right = self.product()?;
            left = self.binary(op, left, right)?;
        }
    }

    fn product(&mut self) -> Result<Spanned, ExpressionError> {
        let mut left = self.unary()?;
        loop {
            let op = if self.eat("*").is_some() {
                Binary::Mul
            } else if self.eat("/").is_some() {
                Binary::Div
            } else {
                return Ok(left);
            };
            let right = self.unary()?;
            left = self.binary(op, left, right)?;
        }
    }

    /// `-x`, `!x` or a power. Every recursion of the grammar passes through here, so this is
    /// where nesting is bounded.
    fn unary(&mut self) -> Result<Spanned, ExpressionError> {
        if self.depth >= MAX_NESTING {
            return Err(self.error_here(ErrorKind::TooDeep { max: MAX_NESTING }));
        }
        self.depth += 1;
        let result = self.unary_inner();
        self.depth -= 1;
        result
    }

    fn unary_inner(&mut self) -> Result<Spanned, ExpressionError> {
        let op = match self.peek().tok {
            Tok::Punct("-") => Unary::Neg,
            Tok::Punct("!") => Unary::Not,
            _ => return self.power(),
        };
        let start = self.advance().start;
        let x = self.unary()?;
        let end = x.end;
        self.elementwise(vec![x], start, end, |r| Op::Unary(op, r[0]))
    }

    /// `x ^ y`, right-associative and binding tighter than a sign: `-x^2` is `-(x^2)`.
    fn power(&mut self) -> Result<Spanned, ExpressionError> {
        let base = self.postfix()?;
        if self.eat("^").is_none() {
            return Ok(base);
        }
        let exponent = self.unary()?;
        let (start, end) = (base.start, exponent.end);
        let whole = match exponent.value {
            Value::Scalar(r) => self
                .builder
                .constant_value(r)
                .filter(|n| n.fract() == 0.0 && n.abs() <= MAX_INTEGER_POWER),
            _ => None,
        };
        match whole {
            Some(n) => self.elementwise(vec![base], start, end, |r| {
                Op::Unary(Unary::PowI(n as i32), r[0])
            }),
            None => self.elementwise(vec![base, exponent], start, end, |r| {
                Op::Binary(Binary::Pow, r[0], r[1])
            }),
        }
    }

    /// A primary followed by any number of `[i]` or `[i:j]`.
    fn postfix(&mut self) -> Result<Spanned, ExpressionError> {
        let mut value = self.primary()?;
        while self.eat("[").is_some() {
            value = self.index(value)?;
        }
        Ok(value)
    }

    fn primary(&mut self) -> Result<Spanned, ExpressionError> {
        let t = self.peek();
        match t.tok {
            Tok::Number(v) => {
                self.advance();
                let r = self.constant(v, t.start, t.end)?;
                Ok(spanned(Value::Scalar(r), t.start, t.end))
            }
            Tok::Ident(name) => {
                self.advance();
                if self.eat("(").is_some() {
                    return self.call(name, t);
                }
                let value = match name {
                    "s" => Value::Input(Input::S),
                    "a" => Value::Input(Input::A),
                    "s_next" => Value::Input(Input::SNext),
                    "pi" => Value::Scalar(self.constant(std::f32::consts::PI, t.start, t.end)?),
                    "e" => Value::Scalar(self.constant(std::f32::consts::E, t.start, t.end)?),
                    _ => return Err(self.error(t.start, t.end, ErrorKind::UnknownName)),
                };
                Ok(spanned(value, t.start, t.end))
            }
            Tok::Punct("(") => {
                self.advance();
                let inner = self.expr()?;
                let close = self.expect(")", "`)`")?;
                Ok(spanned(inner.value, t.start, close.end))
            }
            Tok::Punct("[") => {
                self.advance();
                let mut elements = Vec::new();
                loop {
                    let element = self.expr()?;
                    elements.push(self.scalar(&element)?);
                    if self.eat(",").is_none() {
                        break;
                    }
                }
                let close = self.expect("]", "`,` or `]`")?;
                Ok(spanned(Value::Vector(elements), t.start, close.end))
            }
            _ => Err(self.error_here(ErrorKind::Expected("a number, a name, `(` or `[`"))),
        }
    }

    /// `value[i]` or `value[i:j]` (either bound may be left out), after the `[`.
    fn index(&mut self, value: Spanned) -> Result<Spanned, ExpressionError> {
        let first = self.whole_number()?;
        let slice = self.eat(":").is_some();
        let second = if slice { self.whole_number()? } else { None };
        let close = self.expect("]", if slice { "`]`" } else { "`:` or `]`" })?;
        let (start, end) = (value.start, close.end);
        let (len, of) = match &value.value {
            Value::Scalar(_) => return Err(self.error(start, end, ErrorKind::NotAVector)),
            Value::Vector(v) => (v.len(), format!("a vector of length {}", v.len())),
            Value::Input(input) => {
                let (name, dim_name, dim) = self.describe(*input);
                (dim, format!("{name} ({dim_name} {dim})"))
            }
        };
        if !slice {
            let Some(index) = first else {
                return Err(self.error(close.start, close.end, ErrorKind::BadIndex));
            };
            if index >= len {
                return Err(self.error(start, end, ErrorKind::IndexOutOfRange { index, of }));
            }
            let reg = self.element(&value.value, index, start, end)?;
            return Ok(spanned(Value::Scalar(reg), start, end));
        }
        let (from, to) = (first.unwrap_or(0), second.unwrap_or(len));
        if from >= to || to > len {
            let kind = ErrorKind::BadSlice {
                start: from,
                end: to,
                of,
            };
            return Err(self.error(start, end, kind));
        }
        let regs = (from..to)
            .map(|i| self.element(&value.value, i, start, end))
            .collect::<Result<_, _>>()?;
        Ok(spanned(Value::Vector(regs), start, end))
    }

    /// A whole-number literal index if one comes next (`None` before `:` or `]`).
    fn whole_number(&mut self) -> Result<Option<usize>, ExpressionError> {
        let t = self.peek();
        match t.tok {
            Tok::Punct(":" | "]") => Ok(None),
            Tok::Number(v) if v.fract() == 0.0 && v >= 0.0 && v <= (1u32 << 24) as f32 => {
                self.advance();
                Ok(Some(v as usize))
            }
            _ => Err(self.error(t.start, t.end, ErrorKind::BadIndex)),
        }
    }

    /// `name(args)`, after the `(`.
    fn call(&mut self, name: &'s str, name_token: Token<'s>) -> Result<Spanned, ExpressionError> {
        let Some(&function) = FUNCTIONS.iter().find(|f| **f == name) else {
            return Err(self.error(name_token.start, name_token.end, ErrorKind::UnknownFunction));
        };
        let mut args = Vec::new();
        if self.eat(")").is_none() {
            loop {
                args.push(self.expr()?);
                if self.eat(",").is_none() {
                    break;
                }
            }
            self.expect(")", "`,` or `)`")?;
        }
        let (start, end) = (name_token.start, self.tokens[self.pos - 1].end);
        let arity = |expected: &'static str, ok: bool| {
            if ok {
                Ok(())
            } else {
                Err(ExpressionError::new(
                    self.source,
                    start,
                    end,
                    ErrorKind::Arity {
                        function,
                        expected,
                        got: args.len(),
                    },
                ))
            }
        };
        let elementwise = match function {
            "sin" => Some(Unary::Sin),
            "cos" => Some(Unary::Cos),
            "exp" => Some(Unary::Exp),
            "log" => Some(Unary::Log),
            "tanh" => Some(Unary::Tanh),
            "abs" => Some(Unary::Abs),
            "sqrt" => Some(Unary::Sqrt),
            _ => None,
        };
        if let Some(op) = elementwise {
            arity("1", args.len() == 1)?;
            return self.elementwise(args, start, end, |r| Op::Unary(op, r[0]));
        }
        match function {
            "sum" | "norm" | "norm1" => {
                arity("1", args.len() == 1)?;
                let x = args.pop().expect("one argument");
                let terms = match function {
                    "sum" => x,
                    "norm" => self.elementwise(vec![x.clone(), x], start, end, |r| {
                        Op::Binary(Binary::Mul, r[0], r[1])
                    })?,
                    _ => self.elementwise(vec![x], start, end, |r| Op::Unary(Unary::Abs, r[0]))?,
                };
                let total = self.reduce(vec![terms], Binary::Add, start, end)?;
                let result = if function == "norm" {
                    self.op(Op::Unary(Unary::Sqrt, total), start, end)?
                } else {
                    total
                };
                Ok(spanned(Value::Scalar(result), start, end))
            }
            "dot" => {
                arity("2", args.len() == 2)?;
                let products =
                    self.elementwise(args, start, end, |r| Op::Binary(Binary::Mul, r[0], r[1]))?;
                let total = self.reduce(vec![products], Binary::Add, start, end)?;
                Ok(spanned(Value::Scalar(total), start, end))
            }
            "min" | "max" => {
                arity("1 or more", !args.is_empty())?;
                let op = if function == "min" {
                    Binary::Min
                } else {
                    Binary::Max
                };
                let result = self.reduce(args, op, start, end)?;
                Ok(spanned(Value::Scalar(result), start, end))
            }
            "if" => {
                arity("3", args.len() == 3)?;
                self.elementwise(args, start, end, |r| Op::Select(r[0], r[1], r[2]))
            }
            _ => unreachable!("every function in FUNCTIONS is handled"),
        }
    }

    // ---- building ----

    fn op(&mut self, op: Op, start: usize, end: usize) -> Result<Reg, ExpressionError> {
        self.builder.push(op).map_err(|_| {
            self.error(
                start,
                end,
                ErrorKind::TooLarge {
                    max: MAX_OPERATIONS,
                },
            )
        })
    }

    fn constant(&mut self, v: f32, start: usize, end: usize) -> Result<Reg, ExpressionError> {
        self.builder.constant(v).map_err(|_| {
            self.error(
                start,
                end,
                ErrorKind::TooLarge {
                    max: MAX_OPERATIONS,
                },
            )
        })
    }

    /// `(name, dimension name, dimension)` of an input, for messages and bounds.
    fn describe(&self, input: Input) -> (&'static str, &'static str, usize) {
        match input {
            Input::S => ("s", "obs_dim", self.dims.obs_dim),
            Input::A => ("a", "act_dim", self.dims.act_dim),
            Input::SNext => ("s_next", "obs_dim", self.dims.obs_dim),
        }
    }

    /// Element `i` (in range) of a vector or an input.
    fn element(
        &mut self,
        v: &Value,
        i: usize,
        start: usize,
        end: usize,
    ) -> Result<Reg, ExpressionError> {
        match v {
            Value::Vector(regs) => Ok(regs[i]),
            Value::Input(input) => self.op(Op::Load(*input, i as u32), start, end),
            Value::Scalar(r) => Ok(*r),
        }
    }

    /// The elements of a value: one for a scalar, and whether it was a vector.
    fn elements(&mut self, v: &Spanned) -> Result<(Vec<Reg>, bool), ExpressionError> {
        match &v.value {
            Value::Scalar(r) => Ok((vec![*r], false)),
            Value::Vector(regs) => Ok((regs.clone(), true)),
            Value::Input(input) => {
                let dim = self.describe(*input).2;
                let regs = (0..dim)
                    .map(|i| self.element(&v.value, i, v.start, v.end))
                    .collect::<Result<_, _>>()?;
                Ok((regs, true))
            }
        }
    }

    /// The scalar a value must be.
    fn scalar(&self, v: &Spanned) -> Result<Reg, ExpressionError> {
        let len = match &v.value {
            Value::Scalar(r) => return Ok(*r),
            Value::Vector(regs) => regs.len(),
            Value::Input(input) => self.describe(*input).2,
        };
        Err(self.error(v.start, v.end, ErrorKind::NotAScalar(len)))
    }

    /// `build` applied element by element: scalars are repeated against vectors, vectors must
    /// have one length. A scalar result if every argument is a scalar.
    fn elementwise(
        &mut self,
        args: Vec<Spanned>,
        start: usize,
        end: usize,
        build: impl Fn(&[Reg]) -> Op,
    ) -> Result<Spanned, ExpressionError> {
        let mut columns = Vec::with_capacity(args.len());
        let mut len: Option<usize> = None;
        for arg in &args {
            let (regs, vector) = self.elements(arg)?;
            if vector {
                match len {
                    Some(n) if n != regs.len() => {
                        let kind = ErrorKind::LengthMismatch(n, regs.len());
                        return Err(self.error(start, end, kind));
                    }
                    _ => len = Some(regs.len()),
                }
            }
            columns.push(regs);
        }
        let mut operands = vec![0; columns.len()];
        let mut results = Vec::with_capacity(len.unwrap_or(1));
        for k in 0..len.unwrap_or(1) {
            for (o, column) in operands.iter_mut().zip(&columns) {
                *o = if column.len() == 1 {
                    column[0]
                } else {
                    column[k]
                };
            }
            results.push(self.op(build(&operands), start, end)?);
        }
        let value = match len {
            Some(_) => Value::Vector(results),
            None => Value::Scalar(results[0]),
        };
        Ok(spanned(value, start, end))
    }

    /// Every element of every argument combined with `op`, left to right.
    fn reduce(
        &mut self,
        args: Vec<Spanned>,
        op: Binary,
        start: usize,
        end: usize,
    ) -> Result<Reg, ExpressionError> {
        let mut acc: Option<Reg> = None;
        for arg in &args {
            for r in self.elements(arg)?.0 {
                acc = Some(match acc {
                    None => r,
                    Some(a) => self.op(Op::Binary(op, a, r), start, end)?,
                });
            }
        }
        acc.ok_or_else(|| self.error(start, end, ErrorKind::EmptyVector))
    }

    /// `left op right`, element by element.
    fn binary(
        &mut self,
        op: Binary,
        left: Spanned,
        right: Spanned,
    ) -> Result<Spanned, ExpressionError> {
        let (start, end) = (left.start, right.end);
        self.elementwise(vec![left, right], start, end, |r| {
            Op::Binary(op, r[0], r[1])
        })
    }
}

fn spanned(value: Value, start: usize, end: usize) -> Spanned {
    Spanned { value, start, end }
}
