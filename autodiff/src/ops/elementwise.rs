//! Elementwise ops: unary math, scalar-parameter ops, and NumPy-broadcasting binary ops.
//!
//! Each op matches on its kind once and then runs a monomorphised kernel over the whole
//! tensor (no dispatch per element). Derivatives at kinks follow the usual subgradient
//! conventions: relu'(0) = abs'(0) = 0, clamp passes the gradient on the closed interval,
//! min/max split it equally on ties.

use ndarray::{ArrayD, Dimension, IxDyn};

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{
    broadcast_shapes, map1, map1_fast, map2, sum_to_shape, GradArg, Tensor, TensorView,
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
    /// 1 where x > 0, 0 where x <= 0 (`torch.heaviside(x, 0)`), NaN kept; no gradient (its
    /// derivative is 0 almost everywhere): a differentiable graph's mask, as `relu'`.
    Heaviside,
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
            Unary::Heaviside => "heaviside",
        }
    }

    /// False for a step, whose derivative is 0 almost everywhere: nothing flows back through
    /// it, so the tape records it as not requiring a gradient (eager and fused alike).
    pub fn has_gradient(&self) -> bool {
        !matches!(self, Unary::Heaviside)
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

/// The unit step `x > 0` as 1 or 0, NaN passed through.
#[inline(always)]
pub fn heaviside<T: Real>(x: T) -> T {
    if x > T::zero() {
        T::one()
    } else if x <= T::zero() {
        T::zero()
    } else {
        x
    }
}

/// The op recording a [`Unary`] kind.
pub struct UnaryOp<T>(pub Unary<T>);

impl<T: Real> Op<T> for UnaryOp<T> {
    fn name(&self) -> &'static str {
        self.0.name()
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
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
            Unary::Heaviside => map1(x, heaviside),
        };
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let g = GradArg::Borrowed(ctx.grad_outputs[0]);
        Ok(vec![Some(self.grad(g, &ctx.inputs[0], ctx.outputs[0]))])
    }

    fn backward_owned(
        &self,
        inputs: &[TensorView<'_, T>],
        outputs: &[&Tensor<T>],
        needs_grad: &[bool],
        grad_output: Tensor<T>,
    ) -> Result<Vec<Option<Tensor<T>>>> {
        if !needs_grad[0] {
            return Ok(vec![None]);
        }
        let g = GradArg::Owned(grad_output);
        Ok(vec![Some(self.grad(g, &inputs[0], outputs[0]))])
    }
}

impl<T: Real> UnaryOp<T> {
    /// The input's gradient from the output's gradient `g` (in `g`'s buffer when owned).
    fn grad(&self, g: GradArg<'_, T>, x: &TensorView<'_, T>, y: &Tensor<T>) -> Tensor<T> {
        let (x, y) = (x.view(), y.view());
        let (z, one, two) = (T::zero(), T::one(), T::one() + T::one());
        match self.0 {
            Unary::Neg => g.map1(|g| -g),
            Unary::Exp => g.map2(&y, |g, y| g * y),
            Unary::Log => g.map2(&x, |g, x| g / x),
            Unary::Sqrt => g.map2(&y, |g, y| g / (two * y)),
            Unary::Sin => g.map2_fast(
                &x,
                |g, x| g * x.k_cos(),
                |x| x.k_trig_ok(),
                |g, x| g * x.cos(),
            ),
            Unary::Cos => g.map2_fast(
                &x,
                |g, x| -g * x.k_sin(),
                |x| x.k_trig_ok(),
                |g, x| -g * x.sin(),
            ),
            Unary::Tanh => g.map2(&y, |g, y| g * (one - y * y)),
            Unary::Sigmoid => g.map2(&y, |g, y| g * y * (one - y)),
            Unary::Relu => g.map2(&x, |g, x| if x > z { g } else { z }),
            Unary::Abs => g.map2(&x, |g, x| {
                g * x.signum() * T::from_f64c((x != z) as u8 as f64)
            }),
            Unary::Square => g.map2(&x, |g, x| two * g * x),
            Unary::Recip => g.map2(&y, |g, y| -g * y * y),
            Unary::AddScalar(_) => g.into_owned(),
            Unary::MulScalar(c) => g.map1(|g| g * c),
            Unary::RSubScalar(_) => g.map1(|g| -g),
            Unary::RDivScalar(_) => g.map3(&x, &y, |g, x, y| -g * y / x),
            Unary::PowScalar(c) => {
                g.map2(&x, |g, x| if c == z { z } else { g * c * x.powf(c - one) })
            }
            Unary::ScalarPow(c) => g.map2(&y, |g, y| g * y * c.ln()),
            Unary::Clamp(lo, hi) => g.map2(&x, |g, x| if x >= lo && x <= hi { g } else { z }),
            Unary::Heaviside => g.map1(|_| z),
        }
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
fn bview<'a, T: Real>(x: &'a TensorView<'_, T>, shape: &[usize]) -> ndarray::ArrayViewD<'a, T> {
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

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (&inputs[0], &inputs[1]);
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

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let g = GradArg::Borrowed(ctx.grad_outputs[0]);
        Ok(self.grads(g, ctx.inputs, ctx.needs_grad))
    }

    fn backward_owned(
        &self,
        inputs: &[TensorView<'_, T>],
        _outputs: &[&Tensor<T>],
        needs_grad: &[bool],
        grad_output: Tensor<T>,
    ) -> Result<Vec<Option<Tensor<T>>>> {
        Ok(self.grads(GradArg::Owned(grad_output), inputs, needs_grad))
    }
}

impl BinaryOp {
    /// The inputs' gradients from the output's gradient `g`; the last input that needs one
    /// gets `g`'s buffer when it is owned.
    fn grads<T: Real>(
        &self,
        g: GradArg<'_, T>,
        inputs: &[TensorView<'_, T>],
        needs_grad: &[bool],
    ) -> Vec<Option<Tensor<T>>> {
        let (a, b) = (&inputs[0], &inputs[1]);
        let dim = g.get().raw_dim();
        let shape = dim.slice();
        let (av, bv) = (bview(a, shape), bview(b, shape));
        let (z, one, half) = (T::zero(), T::one(), T::from_f64c(0.5));
        let last = (0..2).rev().find(|&k| needs_grad[k]);
        let mut g = Some(g);
        let mut out = vec![None, None];
        for (k, slot) in out.iter_mut().enumerate() {
            if !needs_grad[k] {
                continue;
            }
            let held = g.as_ref().expect("taken only for the last input");
            let gk = if Some(k) == last {
                g.take().expect("taken once")
            } else {
                held.borrowed()
            };
            let full: Tensor<T> = match (self.0, k) {
                (Binary::Add, _) => gk.into_owned(),
                (Binary::Sub, 0) => gk.into_owned(),
                (Binary::Sub, _) => gk.map1(|v| -v),
                (Binary::Mul, 0) => gk.map2(&bv, |g, b| g * b),
                (Binary::Mul, _) => gk.map2(&av, |g, a| g * a),
                (Binary::Div, 0) => gk.map2(&bv, |g, b| g / b),
                (Binary::Div, _) => gk.map3(&av, &bv, |g, a, b| -g * a / (b * b)),
                (Binary::Pow, 0) => {
                    gk.map3(
                        &av,
                        &bv,
                        |g, a, b| {
                            if b == z {
                                z
                            } else {
                                g * b * a.powf(b - one)
                            }
                        },
                    )
                }
                (Binary::Pow, _) => {
                    gk.map3(
                        &av,
                        &bv,
                        |g, a, b| {
                            if a == z {
                                z
                            } else {
                                g * a.powf(b) * a.ln()
                            }
                        },
                    )
                }
                (Binary::Min | Binary::Max, _) => {
                    let want_less = (self.0 == Binary::Min) == (k == 0);
                    gk.map3(&av, &bv, |g, a, b| {
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
            *slot = Some(sum_to_shape(full, inputs[k].shape()));
        }
        out
    }
}

/// `x * x` for one variable used on both sides: its gradient `2 g x` is one tensor, computed
/// as `(g x) + (g x)`, the sum [`BinaryOp`] would accumulate from its two inputs, instead of
/// two (a pass over the gradient and one allocation fewer).
pub struct MulSelfOp;

impl<T: Real> Op<T> for MulSelfOp {
    fn name(&self) -> &'static str {
        "mul"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = inputs[0].view();
        Ok(vec![map2(&x, &x, |x, y| x * y)])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let g = GradArg::Borrowed(ctx.grad_outputs[0]);
        Ok(vec![
            ctx.needs_grad[0].then(|| mul_self_grad(g, &ctx.inputs[0]))
        ])
    }

    fn backward_owned(
        &self,
        inputs: &[TensorView<'_, T>],
        _outputs: &[&Tensor<T>],
        needs_grad: &[bool],
        grad_output: Tensor<T>,
    ) -> Result<Vec<Option<Tensor<T>>>> {
        let g = GradArg::Owned(grad_output);
        Ok(vec![needs_grad[0].then(|| mul_self_grad(g, &inputs[0]))])
    }
}

fn mul_self_grad<T: Real>(g: GradArg<'_, T>, x: &TensorView<'_, T>) -> Tensor<T> {
    g.map2(&x.view(), |g, x| {
        let t = g * x;
        t + t
    })
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

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (&inputs[0], &inputs[1]);
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

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use crate::Tape;

    fn bits(t: &Tensor<f32>) -> Vec<u32> {
        t.iter().map(|v| v.to_bits()).collect()
    }

    /// The in-place backward (owned gradient) gives the bits of the allocating one, on
    /// parallel-sized and small tensors, with values outside the fast kernels' range.
    #[test]
    fn owned_backward_matches_borrowed_backward() {
        let mut r = Rng::new(7);
        for n in [100_003usize, 37] {
            let mut x: Tensor<f32> = r.uniform_tensor(&[n], -3.0, 3.0);
            x[[1]] = 1e5; // outside the vectorised sin/cos range
            x[[2]] = 0.0;
            let x = x.mapv(|v| if v == 0.0 { v } else { v + 0.01 });
            let g: Tensor<f32> = r.normal_tensor(&[n]);
            let b: Tensor<f32> = r.uniform_tensor(&[n], 0.5, 2.0);
            let kinds = [
                Unary::Neg,
                Unary::Exp,
                Unary::Log,
                Unary::Sqrt,
                Unary::Sin,
                Unary::Cos,
                Unary::Tanh,
                Unary::Sigmoid,
                Unary::Relu,
                Unary::Abs,
                Unary::Square,
                Unary::Recip,
                Unary::AddScalar(0.5),
                Unary::MulScalar(1.01),
                Unary::RSubScalar(2.0),
                Unary::RDivScalar(3.0),
                Unary::PowScalar(1.5),
                Unary::ScalarPow(1.5),
                Unary::Clamp(-1.0, 1.0),
                Unary::Heaviside,
            ];
            for k in kinds {
                let mut op = UnaryOp(k);
                let y = op.forward(&[x.view()]).unwrap().remove(0);
                let ctx = BackwardCtx {
                    inputs: &[x.view()],
                    outputs: &[&y],
                    grad_outputs: &[&g],
                    needs_grad: &[true],
                };
                let want = op.backward(&ctx).unwrap().remove(0).unwrap();
                let got = op
                    .backward_owned(&[x.view()], &[&y], &[true], g.clone())
                    .unwrap()
                    .remove(0)
                    .unwrap();
                assert_eq!(bits(&got), bits(&want), "{}", k.name());
            }
            for k in [
                Binary::Add,
                Binary::Sub,
                Binary::Mul,
                Binary::Div,
                Binary::Pow,
                Binary::Min,
                Binary::Max,
            ] {
                let a = x.mapv(f32::abs);
                let mut op = BinaryOp(k);
                let y = Op::<f32>::forward(&mut op, &[a.view(), b.view()])
                    .unwrap()
                    .remove(0);
                for needs in [[true, true], [true, false], [false, true]] {
                    let ctx = BackwardCtx {
                        inputs: &[a.view(), b.view()],
                        outputs: &[&y],
                        grad_outputs: &[&g],
                        needs_grad: &needs,
                    };
                    let want = op.backward(&ctx).unwrap();
                    let got = op
                        .backward_owned(&[a.view(), b.view()], &[&y], &needs, g.clone())
                        .unwrap();
                    for (w, o) in want.iter().zip(&got) {
                        assert_eq!(w.as_ref().map(bits), o.as_ref().map(bits), "{}", k.name());
                    }
                }
            }
        }
    }

    /// `x * x` (one gradient `(g x) + (g x)`) gives the bits of the product of two inputs,
    /// whose two gradients the tape adds.
    #[test]
    fn mul_self_matches_binary_mul() {
        let x0: Tensor<f32> = Rng::new(3).normal_tensor(&[70_001]);
        let grad = |same: bool| {
            let tape = Tape::<f32>::new();
            let x = tape.leaf(x0.clone());
            let h = x.sin() * 1.3;
            let y = if same {
                h * h
            } else {
                tape.apply(BinaryOp(Binary::Mul), &[h, h])
            };
            let g = tape.backward(y.tanh().sum()).unwrap();
            (bits(&y.value().unwrap()), bits(g.get(x).unwrap()))
        };
        assert_eq!(grad(true), grad(false));
    }
}
