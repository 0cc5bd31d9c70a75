//! Ops on 3-vectors and other vectors stored along the last axis: cross product and
//! normalisation (dot is `(a * b).sum_axes(&[-1])`, composed).

use ndarray::{Axis, IxDyn, Zip};

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{broadcast_shapes, sum_to_shape, Tensor, TensorView};
use crate::Real;

/// Cross product along the last axis (size 3), with broadcasting of the other axes.
pub struct CrossOp;

fn cross3<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn lanes_cross<T: Real, A: ndarray::Data<Elem = T>, B: ndarray::Data<Elem = T>>(
    a: &ndarray::ArrayBase<A, IxDyn>,
    b: &ndarray::ArrayBase<B, IxDyn>,
    shape: &[usize],
) -> Tensor<T> {
    let av = a.broadcast(IxDyn(shape)).expect("checked");
    let bv = b.broadcast(IxDyn(shape)).expect("checked");
    let mut y = Tensor::<T>::zeros(IxDyn(shape));
    let ax = Axis(shape.len() - 1);
    Zip::from(y.lanes_mut(ax))
        .and(av.lanes(ax))
        .and(bv.lanes(ax))
        .for_each(|mut o, x, y| {
            let c = cross3([x[0], x[1], x[2]], [y[0], y[1], y[2]]);
            o[0] = c[0];
            o[1] = c[1];
            o[2] = c[2];
        });
    y
}

impl<T: Real> Op<T> for CrossOp {
    fn name(&self) -> &'static str {
        "cross"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (&inputs[0], &inputs[1]);
        if a.shape().last() != Some(&3) || b.shape().last() != Some(&3) {
            return Err(AutodiffError::shape(
                "cross",
                &[a.shape(), b.shape()],
                "last axis must have size 3",
            ));
        }
        let shape = broadcast_shapes("cross", a.shape(), b.shape())?;
        Ok(vec![lanes_cross(a, b, &shape)])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let (a, b, g) = (&ctx.inputs[0], &ctx.inputs[1], ctx.grad_outputs[0]);
        let shape = g.shape();
        // d(a x b) with upstream g: ga = b x g, gb = g x a.
        Ok(vec![
            ctx.needs_grad[0].then(|| sum_to_shape(lanes_cross(b, g, shape), a.shape())),
            ctx.needs_grad[1].then(|| sum_to_shape(lanes_cross(g, a, shape), b.shape())),
        ])
    }
}

/// `x / max(|x|, eps)` along the last axis. Safe at zero length: a zero vector maps to zero
/// with gradient `g / eps` (finite), never NaN.
pub struct NormalizeOp<T> {
    /// Length floor (must be > 0).
    pub eps: T,
}

impl<T: Real> Op<T> for NormalizeOp<T> {
    fn name(&self) -> &'static str {
        "normalize"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        if self.eps.is_nan() || self.eps <= T::zero() {
            return Err(AutodiffError::invalid(
                "normalize",
                format!(
                    "eps must be > 0, got {} (input shape {:?})",
                    self.eps,
                    x.shape()
                ),
            ));
        }
        if x.ndim() == 0 {
            return Err(AutodiffError::shape(
                "normalize",
                &[x.shape()],
                "needs at least one axis",
            ));
        }
        let ax = Axis(x.ndim() - 1);
        let mut y = x.to_owned();
        for mut lane in y.lanes_mut(ax) {
            let len = lane.iter().map(|&v| v * v).sum::<T>().sqrt();
            // Not `len.max(eps)`, which would turn a NaN length into eps.
            let n = if len < self.eps { self.eps } else { len };
            lane.mapv_inplace(|v| v / n);
        }
        Ok(vec![y])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let (x, y, g) = (&ctx.inputs[0], ctx.outputs[0], ctx.grad_outputs[0]);
        let ax = Axis(x.ndim() - 1);
        let mut gx = Tensor::<T>::zeros(x.raw_dim());
        Zip::from(gx.lanes_mut(ax))
            .and(x.lanes(ax))
            .and(y.lanes(ax))
            .and(g.lanes(ax))
            .for_each(|mut o, x, y, g| {
                let len = x.iter().map(|&v| v * v).sum::<T>().sqrt();
                if len > self.eps {
                    let yg: T = y.iter().zip(g.iter()).map(|(&a, &b)| a * b).sum();
                    for ((o, &yv), &gv) in o.iter_mut().zip(y.iter()).zip(g.iter()) {
                        *o = (gv - yv * yg) / len;
                    }
                } else {
                    for (o, &gv) in o.iter_mut().zip(g.iter()) {
                        *o = gv / self.eps;
                    }
                }
            });
        Ok(vec![Some(gx)])
    }
}
