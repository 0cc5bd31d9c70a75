//! Elementwise ops: unary math, scalar-parameter ops, and NumPy-broadcasting binary ops.
//!
//! Each op matches on its kind once and then runs a monomorphised kernel over the whole
//! tensor (no dispatch per element). Derivatives at kinks follow the usual subgradient
//! conventions: relu'(0) = abs'(0) = 0, clamp passes the gradient on the closed interval,
//! min/max split it equally on ties.

use ndarray::{ArrayD, IxDyn};

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{
    broadcast_shapes, map1, map1_fast, map2, map2_fast, map3, sum_to_shape, Tensor,
};
use crate::Real;

/// Unary elementwise kinds; some carry a scalar parameter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Unary<T> {
    /// -x
    Neg,
    /// e^x
    Exp,
    /// ln x
    Log,
    /// sqrt x
    Sqrt,
    /// sin x
    Sin,
    /// cos x
    Cos,
    /// tanh x
    Tanh,
    /// 1 / (1 + e^-x)
    Sigmoid,
    /// max(x, 0)
    Relu,
    /// |x|
    Abs,
    /// x^2
    Square,
    /// 1 / x
    Recip,
    /// x + c
    AddScalar(T),
    /// x * c
    MulScalar(T),
    /// c - x
    RSubScalar(T),
    /// c / x
    RDivScalar(T),
    /// x^c
    PowScalar(T),
    /// c^x
    ScalarPow(T),
    /// min(max(x, lo), hi)
    Clamp(T, T),
}

impl<T: Real> Unary<T> {
    /// Name of the op.
    pub fn name(&self) -> &'static str {
        match self {
            Unary::Neg => "neg",
            Unary::Exp => "exp",
            Unary::Log => "log",
            Unary::Sqrt => "sqrt",
            Unary::Sin => "sin",
            Unary::Cos => "cos",
            Unary::Tanh => "tanh",
            Unary::Sigmoid => "sigmoid",
            Unary::Relu => "relu",
            Unary::Abs => "abs",
            Unary::Square => "square",
            Unary::Recip => "recip",
            Unary::AddScalar(_) => "add_scalar",
            Unary::MulScalar(_) => "mul_scalar",
            Unary::RSubScalar(_) => "rsub_scalar",
            Unary::RDivScalar(_) => "rdiv_scalar",
            Unary::PowScalar(_) => "pow_scalar",
            Unary::ScalarPow(_) => "scalar_pow",
            Unary::Clamp(..) => "clamp",
        }
    }
}

/// A numerically stable logistic function.
#[inline(always)]
pub fn sigmoid<T: Real>(x: T) -> T {
    if x >= T::zero() {
        T::one() / (T::one() + (-x).exp())
    } else {
        let e = x.exp();
        e / (T::one() + e)
    }
}

/// The op recording a [`Unary`] kind.
pub struct UnaryOp<T>(pub Unary<T>);

impl<T: Real> Op<T> for UnaryOp<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let x = inputs[0];
        let z = T::zero();
        let y = match self.0 {
            Unary::Neg => map1(x, |v| -v),
            // exp, sin, cos, tanh, sigmoid: vectorised polynomials for f32 (see `vmath`),
            // libm outside their range and for f64.
            Unary::Exp => map1_fast(x, T::k_exp, T::k_exp_ok, T::exp),
            Unary::Log => map1(x, |v| v.ln()),
            Unary::Sqrt => map1(x, |v| v.sqrt()),
            Unary::Sin => map1_fast(x, T::k_sin, T::k_trig_ok, T::sin),
            Unary::Cos => map1_fast(x, T::k_cos, T::k_trig_ok, T::cos),
            Unary::Tanh => map1_fast(x, T::k_tanh, |v| !v.is_nan(), T::tanh),
            Unary::Sigmoid => map1_fast(x, T::k_sigmoid, |v| (-v.abs()).k_exp_ok(), sigmoid),
            // Written so that NaN passes through (`f32::max` would drop it).
            Unary::Relu => map1(x, |v| if v < z { z } else { v }),
            Unary::Abs => map1(x, |v| v.abs()),
            Unary::Square => map1(x, |v| v * v),
            Unary::Recip => map1(x, |v| v.recip()),
            Unary::AddScalar(c) => map1(x, |v| v + c),
            Unary::MulScalar(c) => map1(x, |v| v * c),
            Unary::RSubScalar(c) => map1(x, |v| c - v),
            Unary::RDivScalar(c) => map1(x, |v| c / v),
            Unary::PowScalar(c) => map1(x, |v| v.powf(c)),
            Unary::ScalarPow(c) => map1(x, |v| c.powf(v)),
            Unary::Clamp(lo, hi) => {
                if lo.is_nan() || hi.is_nan() || lo > hi {
                    return Err(AutodiffError::invalid(
                        "clamp",
                        format!("lo {lo} > hi {hi}"),
                    ));
                }
                map1(x, |v| {
                    if v < lo {
                        lo
                    } else if v > hi {
                        hi
                    } else {
                        v
                    }
                })
            }
        };
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let g0 = ctx.grad_outputs[0];
        let (g, x, y) = (g0.view(), ctx.inputs[0].view(), ctx.outputs[0].view());
        let (z, one, two) = (T::zero(), T::one(), T::one() + T::one());
        let gx = match self.0 {
            Unary::Neg => map1(g0, |g| -g),
            Unary::Exp => map2(&g, &y, |g, y| g * y),
            Unary::Log => map2(&g, &x, |g, x| g / x),
            Unary::Sqrt => map2(&g, &y, |g, y| g / (two * y)),
            Unary::Sin => map2_fast(
                &g,
                &x,
                |g, x| g * x.k_cos(),
                |_, x| x.k_trig_ok(),
                |g, x| g * x.cos(),
            ),
            Unary::Cos => map2_fast(
                &g,
                &x,
                |g, x| -g * x.k_sin(),
                |_, x| x.k_trig_ok(),
                |g, x| -g * x.sin(),
            ),
            Unary::Tanh => map2(&g, &y, |g, y| g * (one - y * y)),
            Unary::Sigmoid => map2(&g, &y, |g, y| g * y * (one - y)),
            Unary::Relu => map2(&g, &x, |g, x| if x > z { g } else { z }),
            Unary::Abs => map2(&g, &x, |g, x| {
                g * x.signum() * T::from_f64c((x != z) as u8 as f64)
            }),
            Unary::Square => map2(&g, &x, |g, x| two * g * x),
            Unary::Recip => map2(&g, &y, |g, y| -g * y * y),
            Unary::AddScalar(_) => ctx.grad_outputs[0].clone(),
            Unary::MulScalar(c) => map1(g0, |g| g * c),
            Unary::RSubScalar(_) => map1(g0, |g| -g),
            Unary::RDivScalar(_) => map3(&g, &x, &y, |g, x, y| -g * y / x),
            Unary::PowScalar(c) => map2(
                &g,
                &x,
                |g, x| {
                    if c == z {
                        z
                    } else {
                        g * c * x.powf(c - one)
                    }
                },
            ),
            Unary::ScalarPow(c) => map2(&g, &y, |g, y| g * y * c.ln()),
            Unary::Clamp(lo, hi) => map2(&g, &x, |g, x| if x >= lo && x <= hi { g } else { z }),
        };
        Ok(vec![Some(gx)])
    }
}

/// Binary elementwise kinds (NumPy broadcasting).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Binary {
    /// a + b
    Add,
    /// a - b
    Sub,
    /// a * b
    Mul,
    /// a / b
    Div,
    /// a^b
    Pow,
    /// min(a, b)
    Min,
    /// max(a, b)
    Max,
}

impl Binary {
    /// Name of the op.
    pub fn name(&self) -> &'static str {
        match self {
            Binary::Add => "add",
            Binary::Sub => "sub",
            Binary::Mul => "mul",
            Binary::Div => "div",
            Binary::Pow => "pow",
            Binary::Min => "min",
            Binary::Max => "max",
        }
    }
}

/// `x` broadcast to `shape` (a plain view when it already has that shape).
fn bview<'a, T: Real>(x: &'a Tensor<T>, shape: &[usize]) -> ndarray::ArrayViewD<'a, T> {
    if x.shape() == shape {
        x.view()
    } else {
        x.broadcast(IxDyn(shape)).expect("forward checked")
    }
}

/// The op recording a [`Binary`] kind.
pub struct BinaryOp(pub Binary);

impl<T: Real> Op<T> for BinaryOp {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (inputs[0], inputs[1]);
        let (av, bv) = if a.shape() == b.shape() {
            (a.view(), b.view())
        } else {
            let shape = broadcast_shapes(self.0.name(), a.shape(), b.shape())?;
            (
                a.broadcast(IxDyn(&shape)).expect("broadcast checked"),
                b.broadcast(IxDyn(&shape)).expect("broadcast checked"),
            )
        };
        let half = T::from_f64c(0.5);
        let y = match self.0 {
            Binary::Add => map2(&av, &bv, |x, y| x + y),
            Binary::Sub => map2(&av, &bv, |x, y| x - y),
            Binary::Mul => map2(&av, &bv, |x, y| x * y),
            Binary::Div => map2(&av, &bv, |x, y| x / y),
            Binary::Pow => map2(&av, &bv, |x, y| x.powf(y)),
            // Ties (and NaN, which `f32::min`/`max` would drop) give the mean: NaN propagates.
            Binary::Min => map2(&av, &bv, |x, y| {
                if x < y {
                    x
                } else if y < x {
                    y
                } else {
                    half * (x + y)
                }
            }),
            Binary::Max => map2(&av, &bv, |x, y| {
                if x > y {
                    x
                } else if y > x {
                    y
                } else {
                    half * (x + y)
                }
            }),
        };
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let (a, b) = (ctx.inputs[0], ctx.inputs[1]);
        let g = ctx.grad_outputs[0];
        let shape = g.shape();
        let (av, bv) = (bview(a, shape), bview(b, shape));
        let gv = g.view();
        let (z, one, half) = (T::zero(), T::one(), T::from_f64c(0.5));
        let mut out = vec![None, None];
        for (k, slot) in out.iter_mut().enumerate() {
            if !ctx.needs_grad[k] {
                continue;
            }
            let full: Tensor<T> = match (self.0, k) {
                (Binary::Add, _) => g.clone(),
                (Binary::Sub, 0) => g.clone(),
                (Binary::Sub, _) => map1(g, |v| -v),
                (Binary::Mul, 0) => map2(&gv, &bv, |g, b| g * b),
                (Binary::Mul, _) => map2(&gv, &av, |g, a| g * a),
                (Binary::Div, 0) => map2(&gv, &bv, |g, b| g / b),
                (Binary::Div, _) => map3(&gv, &av, &bv, |g, a, b| -g * a / (b * b)),
                (Binary::Pow, 0) => map3(&gv, &av, &bv, |g, a, b| {
                    if b == z {
                        z
                    } else {
                        g * b * a.powf(b - one)
                    }
                }),
                (Binary::Pow, _) => map3(&gv, &av, &bv, |g, a, b| {
                    if a == z {
                        z
                    } else {
                        g * a.powf(b) * a.ln()
                    }
                }),
                (Binary::Min | Binary::Max, _) => {
                    let want_less = (self.0 == Binary::Min) == (k == 0);
                    map3(&gv, &av, &bv, |g, a, b| {
                        if a == b {
                            g * half
                        } else if (a < b) == want_less {
                            g
                        } else {
                            z
                        }
                    })
                }
            };
            *slot = Some(sum_to_shape(full, ctx.inputs[k].shape()));
        }
        Ok(out)
    }
}

/// `where(mask, a, b)`: `a` where the mask is true, `b` elsewhere; mask, a and b broadcast.
pub struct WhereOp {
    /// The condition (not differentiable, held in the op).
    pub mask: ArrayD<bool>,
}

impl<T: Real> Op<T> for WhereOp {
    fn name(&self) -> &'static str {
        "where"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (inputs[0], inputs[1]);
        let s = broadcast_shapes("where", a.shape(), b.shape())?;
        let s = broadcast_shapes("where", &s, self.mask.shape()).map_err(|_| {
            AutodiffError::shape(
                "where",
                &[self.mask.shape(), a.shape(), b.shape()],
                "mask does not broadcast with the values",
            )
        })?;
        let m = self.mask.broadcast(IxDyn(&s)).expect("checked");
        let av = a.broadcast(IxDyn(&s)).expect("checked");
        let bv = b.broadcast(IxDyn(&s)).expect("checked");
        let y = ndarray::Zip::from(&m)
            .and(&av)
            .and(&bv)
            .map_collect(|&m, &x, &y| if m { x } else { y });
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let g = ctx.grad_outputs[0];
        let m = self.mask.broadcast(IxDyn(g.shape())).expect("checked");
        let z = T::zero();
        let mut out = vec![None, None];
        for (k, slot) in out.iter_mut().enumerate() {
            if ctx.needs_grad[k] {
                let take = k == 0;
                let full = ndarray::Zip::from(g)
                    .and(&m)
                    .map_collect(|&g, &m| if m == take { g } else { z });
                *slot = Some(sum_to_shape(full, ctx.inputs[k].shape()));
            }
        }
        Ok(out)
    }
}
