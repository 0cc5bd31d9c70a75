//! Methods and operators on [`Var`]: the user-facing vocabulary of the tape.
//!
//! Axes may be negative (counted from the end, as in NumPy). Scalars mix with variables on
//! either side of `+ - * /`.

use std::ops::{Add, Div, Mul, Neg, Sub};

use ndarray::ArrayD;

use crate::fused::Kind;
use crate::ops::elementwise::{Binary, BinaryOp, MulSelfOp, Unary, UnaryOp, WhereOp};
use crate::ops::index::{GatherOp, IndexSelectOp, ScatterAddOp};
use crate::ops::linalg::MatMulOp;
use crate::ops::reduce::{LogSumExpOp, MaxOp, SumOp, SumSquaredDiffOp};
use crate::ops::shape::{BroadcastToOp, ConcatOp, PermuteOp, ReshapeOp, SliceOp, StackOp};
use crate::ops::vector::{CrossOp, NormalizeOp};
use crate::tape::{Tape, Var};
use crate::Real;

/// Resolves a possibly negative axis; out-of-range axes map to `usize::MAX` so that the op
/// reports them with the input's shape.
fn axis(ndim: usize, a: isize) -> usize {
    let r = if a < 0 { ndim as isize + a } else { a };
    if r < 0 {
        usize::MAX
    } else {
        r as usize
    }
}

impl<'t, T: Real> Var<'t, T> {
    /// Inside [`Tape::fused`]: `kind` recorded as a pending node, when it fits.
    #[inline]
    fn lazy(self, kind: Kind<T>, args: &[Self], mask: Option<&ArrayD<bool>>) -> Option<Self> {
        if self.tape().is_fusing() {
            self.tape().record_lazy(kind, args, mask)
        } else {
            None
        }
    }
    fn unary(self, k: Unary<T>) -> Self {
        if let Some(v) = self.lazy(Kind::Unary(k), &[self], None) {
            return v;
        }
        let x = if k.has_gradient() {
            self
        } else {
            self.detach()
        };
        self.tape().apply(UnaryOp(k), &[x])
    }
    fn binary(self, k: Binary, o: Self) -> Self {
        if k == Binary::Mul && self.id() == o.id() && std::ptr::eq(self.tape(), o.tape()) {
            // `x * x`: one gradient tensor instead of two added together.
            if let Some(v) = self.lazy(Kind::MulSelf, &[self], None) {
                return v;
            }
            return self.tape().apply(MulSelfOp, &[self]);
        }
        if let Some(v) = self.lazy(Kind::Binary(k), &[self, o], None) {
            return v;
        }
        self.tape().apply(BinaryOp(k), &[self, o])
    }
    /// e^x
    pub fn exp(self) -> Self {
        self.unary(Unary::Exp)
    }
    /// Natural logarithm.
    pub fn ln(self) -> Self {
        self.unary(Unary::Log)
    }
    /// Natural logarithm (alias of [`Var::ln`]).
    pub fn log(self) -> Self {
        self.ln()
    }
    /// Square root.
    pub fn sqrt(self) -> Self {
        self.unary(Unary::Sqrt)
    }
    /// Sine.
    pub fn sin(self) -> Self {
        self.unary(Unary::Sin)
    }
    /// Cosine.
    pub fn cos(self) -> Self {
        self.unary(Unary::Cos)
    }
    /// Hyperbolic tangent.
    pub fn tanh(self) -> Self {
        self.unary(Unary::Tanh)
    }
    /// Logistic sigmoid (stable for large |x|).
    pub fn sigmoid(self) -> Self {
        self.unary(Unary::Sigmoid)
    }
    /// max(x, 0)
    pub fn relu(self) -> Self {
        self.unary(Unary::Relu)
    }
    /// |x|
    pub fn abs(self) -> Self {
        self.unary(Unary::Abs)
    }
    /// x^2
    pub fn square(self) -> Self {
        self.unary(Unary::Square)
    }
    /// 1 / x
    pub fn recip(self) -> Self {
        self.unary(Unary::Recip)
    }
    /// x^p for a scalar p.
    pub fn powf(self, p: T) -> Self {
        self.unary(Unary::PowScalar(p))
    }
    /// x^y elementwise with broadcasting.
    pub fn pow(self, y: Self) -> Self {
        self.binary(Binary::Pow, y)
    }
    /// 1 where x > 0, 0 where x <= 0 (`torch.heaviside(x, 0)`); no gradient flows through it.
    /// Inside [`crate::Tape::fused`] it keeps a mask such as "facing the light" in the fused
    /// region, where a mask read from a value would end the region there.
    pub fn heaviside(self) -> Self {
        self.unary(Unary::Heaviside)
    }
    /// min(max(x, lo), hi)
    pub fn clamp(self, lo: T, hi: T) -> Self {
        self.unary(Unary::Clamp(lo, hi))
    }
    /// Elementwise minimum with broadcasting.
    pub fn minimum(self, y: Self) -> Self {
        self.binary(Binary::Min, y)
    }
    /// Elementwise maximum with broadcasting.
    pub fn maximum(self, y: Self) -> Self {
        self.binary(Binary::Max, y)
    }
    /// `self` where `mask` is true, `other` elsewhere (all three broadcast).
    pub fn where_(self, mask: ArrayD<bool>, other: Self) -> Self {
        if let Some(v) = self.lazy(Kind::Select, &[self, other], Some(&mask)) {
            return v;
        }
        self.tape().apply(WhereOp { mask }, &[self, other])
    }

    /// Sum of all elements (0-dimensional result).
    pub fn sum(self) -> Self {
        self.tape().apply(SumOp::new(None, false, false), &[self])
    }
    /// `sum((self - other)^2)` over all elements (0-dimensional result), one fused op: the
    /// squared-error loss without the difference and square tensors of
    /// `(self - other).square().sum()`. Both must have the same shape (no broadcasting).
    pub fn sum_squared_diff(self, other: Self) -> Self {
        self.tape().apply(SumSquaredDiffOp, &[self, other])
    }
    /// Mean of all elements.
    pub fn mean(self) -> Self {
        self.tape().apply(SumOp::new(None, false, true), &[self])
    }
    /// Sum over the given axes.
    pub fn sum_axes(self, axes: &[isize], keepdim: bool) -> Self {
        let n = self.ndim();
        if n > 0 && axes.len() == 1 && axis(n, axes[0]) == n - 1 {
            if let Some(v) = self.lazy(Kind::SumLast(keepdim), &[self], None) {
                return v;
            }
        }
        let a = axes.iter().map(|&a| axis(n, a)).collect();
        self.tape()
            .apply(SumOp::new(Some(a), keepdim, false), &[self])
    }
    /// Mean over the given axes.
    pub fn mean_axes(self, axes: &[isize], keepdim: bool) -> Self {
        let n = self.ndim();
        let a = axes.iter().map(|&a| axis(n, a)).collect();
        self.tape()
            .apply(SumOp::new(Some(a), keepdim, true), &[self])
    }
    /// Maximum over one axis.
    pub fn max_axis(self, ax: isize, keepdim: bool) -> Self {
        let a = axis(self.ndim(), ax);
        self.tape().apply(MaxOp::new(a, keepdim), &[self])
    }
    /// Stable `log(sum(exp(x)))` over one axis.
    pub fn logsumexp(self, ax: isize, keepdim: bool) -> Self {
        let a = axis(self.ndim(), ax);
        self.tape().apply(LogSumExpOp { axis: a, keepdim }, &[self])
    }

    /// Matrix product (NumPy `matmul` for 1-, 2- and 3-dimensional inputs).
    pub fn matmul(self, o: Self) -> Self {
        self.tape().apply(MatMulOp, &[self, o])
    }
    /// Dot product along the last axis.
    pub fn dot(self, o: Self) -> Self {
        (self * o).sum_axes(&[-1], false)
    }
    /// Cross product along the last axis (size 3).
    pub fn cross(self, o: Self) -> Self {
        self.tape().apply(CrossOp, &[self, o])
    }
    /// Unit vectors along the last axis: `x / max(|x|, eps)`.
    pub fn normalize(self, eps: T) -> Self {
        if let Some(v) = self.lazy(Kind::Normalize(eps), &[self], None) {
            return v;
        }
        self.tape().apply(NormalizeOp { eps }, &[self])
    }
    /// Euclidean norm along the last axis.
    pub fn norm(self) -> Self {
        self.square().sum_axes(&[-1], false).sqrt()
    }

    /// Same elements, new shape.
    ///
    /// To its own shape it is `self`, with nothing recorded (as a view in PyTorch): a shader
    /// that reshapes a light's `[3]` colour to `[3]` keeps its fused region whole.
    pub fn reshape(self, shape: &[usize]) -> Self {
        if self.shape() == shape {
            return self;
        }
        self.tape().apply(ReshapeOp(shape.to_vec()), &[self])
    }
    /// Axes reordered: output axis `i` is input axis `perm[i]`.
    pub fn permute(self, perm: &[usize]) -> Self {
        self.tape().apply(PermuteOp(perm.to_vec()), &[self])
    }
    /// Swaps the last two axes.
    pub fn t(self) -> Self {
        let n = self.ndim();
        let mut p: Vec<usize> = (0..n).collect();
        if n >= 2 {
            p.swap(n - 1, n - 2);
        }
        self.permute(&p)
    }
    /// `start..end` along `axis`.
    pub fn slice(self, ax: isize, start: usize, end: usize) -> Self {
        let a = axis(self.ndim(), ax);
        if self.ndim() > 0 && a == self.ndim() - 1 {
            if let Some(v) = self.lazy(Kind::SliceLast(start, end), &[self], None) {
                return v;
            }
        }
        self.tape().apply(
            SliceOp {
                axis: a,
                start,
                end,
            },
            &[self],
        )
    }
    /// Broadcast to `shape`.
    pub fn broadcast_to(self, shape: &[usize]) -> Self {
        self.tape().apply(BroadcastToOp(shape.to_vec()), &[self])
    }
    /// Rows picked along `axis` (repeats allowed).
    pub fn index_select(self, ax: isize, indices: &[usize]) -> Self {
        let a = axis(self.ndim(), ax);
        self.tape().apply(
            IndexSelectOp {
                axis: a,
                indices: indices.to_vec(),
            },
            &[self],
        )
    }
    /// `torch.gather` along `axis`.
    pub fn gather(self, ax: isize, index: ArrayD<usize>) -> Self {
        let a = axis(self.ndim(), ax);
        self.tape().apply(GatherOp { axis: a, index }, &[self])
    }
    /// Scatter-add along `axis` into a zero tensor whose size on `axis` is `dim_size`.
    pub fn scatter_add(self, ax: isize, index: ArrayD<usize>, dim_size: usize) -> Self {
        let a = axis(self.ndim(), ax);
        self.tape().apply(
            ScatterAddOp {
                axis: a,
                index,
                dim_size,
            },
            &[self],
        )
    }
}

impl<T: Real> Tape<T> {
    /// Concatenation along an existing axis.
    pub fn concat<'t>(&'t self, vars: &[Var<'t, T>], ax: isize) -> Var<'t, T> {
        let n = vars.first().map(|v| v.ndim()).unwrap_or(0);
        self.apply(ConcatOp(axis(n, ax)), vars)
    }
    /// Stacking along a new axis.
    pub fn stack<'t>(&'t self, vars: &[Var<'t, T>], ax: isize) -> Var<'t, T> {
        let n = vars.first().map(|v| v.ndim() + 1).unwrap_or(0);
        self.apply(StackOp(axis(n, ax)), vars)
    }
}

macro_rules! var_binop {
    ($tr:ident, $m:ident, $kind:ident, $scalar_kind:expr, $rscalar:expr) => {
        impl<'t, T: Real> $tr<Var<'t, T>> for Var<'t, T> {
            type Output = Var<'t, T>;
            fn $m(self, o: Var<'t, T>) -> Var<'t, T> {
                self.binary(Binary::$kind, o)
            }
        }
        impl<'t, T: Real> $tr<T> for Var<'t, T> {
            type Output = Var<'t, T>;
            fn $m(self, c: T) -> Var<'t, T> {
                let f: fn(T) -> Unary<T> = $scalar_kind;
                self.unary(f(c))
            }
        }
        impl<'t> $tr<Var<'t, f64>> for f64 {
            type Output = Var<'t, f64>;
            fn $m(self, v: Var<'t, f64>) -> Var<'t, f64> {
                let f: fn(f64) -> Unary<f64> = $rscalar;
                v.unary(f(self))
            }
        }
        impl<'t> $tr<Var<'t, f32>> for f32 {
            type Output = Var<'t, f32>;
            fn $m(self, v: Var<'t, f32>) -> Var<'t, f32> {
                let f: fn(f32) -> Unary<f32> = $rscalar;
                v.unary(f(self))
            }
        }
    };
}

var_binop!(Add, add, Add, Unary::AddScalar, Unary::AddScalar);
var_binop!(Mul, mul, Mul, Unary::MulScalar, Unary::MulScalar);
var_binop!(
    Sub,
    sub,
    Sub,
    |c: T| Unary::AddScalar(-c),
    Unary::RSubScalar
);
var_binop!(
    Div,
    div,
    Div,
    |c: T| Unary::MulScalar(c.recip()),
    Unary::RDivScalar
);

impl<'t, T: Real> Neg for Var<'t, T> {
    type Output = Var<'t, T>;
    fn neg(self) -> Var<'t, T> {
        self.unary(Unary::Neg)
    }
}
