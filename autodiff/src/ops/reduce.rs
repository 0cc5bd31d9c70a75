//! Reductions over axes: sum, mean, max, logsumexp. Sums run in a fixed order (see
//! [`crate::tensor`]) so results do not depend on the thread count.

use ndarray::{ArrayD, Axis, IxDyn, Zip};

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{full, scalar, sum_all_det, sum_axis_det, Tensor};
use crate::Real;

/// Validates reduction axes: in range, no repeats; returns them sorted.
pub fn check_axes(op: &'static str, shape: &[usize], axes: &[usize]) -> Result<Vec<usize>> {
    let mut a = axes.to_vec();
    a.sort_unstable();
    for w in a.windows(2) {
        if w[0] == w[1] && w[0] != usize::MAX {
            return Err(AutodiffError::index(
                op,
                &[shape],
                format!("axis {} repeated", w[0]),
            ));
        }
    }
    if let Some(&bad) = a.iter().find(|&&x| x >= shape.len()) {
        // Negative axes below -ndim arrive as usize::MAX (see var_ops).
        let which = if bad == usize::MAX {
            "a negative axis".to_string()
        } else {
            format!("axis {bad}")
        };
        return Err(AutodiffError::index(
            op,
            &[shape],
            format!("{which} out of range for {} dimensions", shape.len()),
        ));
    }
    Ok(a)
}

fn reduced_shape(shape: &[usize], axes: &[usize], keepdim: bool) -> Vec<usize> {
    let mut out = Vec::with_capacity(shape.len());
    for (i, &d) in shape.iter().enumerate() {
        if axes.contains(&i) {
            if keepdim {
                out.push(1);
            }
        } else {
            out.push(d);
        }
    }
    out
}

/// Shape with the reduced axes kept as size 1 (for broadcasting a gradient back).
fn keep_shape(shape: &[usize], axes: &[usize]) -> Vec<usize> {
    reduced_shape(shape, axes, true)
}

/// Sum (or mean) over `axes` (all axes when `axes` is `None`).
pub struct SumOp {
    /// Axes to reduce; `None` for all.
    pub axes: Option<Vec<usize>>,
    /// Keep reduced axes as size 1.
    pub keepdim: bool,
    /// Divide by the number of reduced elements.
    pub mean: bool,
    resolved: Vec<usize>,
}

impl SumOp {
    /// A sum or mean over the given axes.
    pub fn new(axes: Option<Vec<usize>>, keepdim: bool, mean: bool) -> Self {
        SumOp {
            axes,
            keepdim,
            mean,
            resolved: Vec::new(),
        }
    }
}

impl<T: Real> Op<T> for SumOp {
    fn name(&self) -> &'static str {
        if self.mean {
            "mean"
        } else {
            "sum"
        }
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let x = inputs[0];
        let name = <Self as Op<T>>::name(self);
        self.resolved = match &self.axes {
            Some(a) => check_axes(name, x.shape(), a)?,
            None => (0..x.ndim()).collect(),
        };
        let count: usize = self.resolved.iter().map(|&a| x.shape()[a]).product();
        let mut y = if self.resolved.len() == x.ndim() {
            let s = scalar(sum_all_det(x));
            s.into_shape_with_order(IxDyn(&reduced_shape(
                x.shape(),
                &self.resolved,
                self.keepdim,
            )))
            .expect("one element")
        } else {
            let mut y = x.clone();
            for &a in self.resolved.iter().rev() {
                y = sum_axis_det(&y.view(), a);
            }
            if self.keepdim {
                y.into_shape_with_order(IxDyn(&keep_shape(x.shape(), &self.resolved)))
                    .expect("same count")
            } else {
                y
            }
        };
        if self.mean {
            let inv = T::one() / T::from_usize_c(count.max(1));
            y.mapv_inplace(|v| v * inv);
        }
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let shape = ctx.inputs[0].shape();
        // A gradient in another memory layout is read in row-major order first.
        let g = ctx.grad_outputs[0].as_standard_layout();
        let g = g
            .view()
            .into_shape_with_order(IxDyn(&keep_shape(shape, &self.resolved)))
            .expect("same count, standard layout");
        let count: usize = self.resolved.iter().map(|&a| shape[a]).product();
        let scale = if self.mean {
            T::one() / T::from_usize_c(count.max(1))
        } else {
            T::one()
        };
        if g.len() == 1 {
            // A full reduction: the gradient is one value everywhere.
            let v = *g.iter().next().expect("one element") * scale;
            return Ok(vec![Some(full(shape, v))]);
        }
        let gb = g.broadcast(IxDyn(shape)).expect("keepdim broadcasts");
        Ok(vec![Some(gb.mapv(|v| v * scale))])
    }
}

/// Maximum over one axis; the gradient goes to the first maximal element.
pub struct MaxOp {
    /// Axis to reduce.
    pub axis: usize,
    /// Keep the reduced axis as size 1.
    pub keepdim: bool,
    argmax: ArrayD<usize>,
}

impl MaxOp {
    /// Max over `axis`.
    pub fn new(axis: usize, keepdim: bool) -> Self {
        MaxOp {
            axis,
            keepdim,
            argmax: ArrayD::zeros(IxDyn(&[])),
        }
    }
}

impl<T: Real> Op<T> for MaxOp {
    fn name(&self) -> &'static str {
        "max"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let x = inputs[0];
        check_axes("max", x.shape(), &[self.axis])?;
        if x.shape()[self.axis] == 0 {
            return Err(AutodiffError::shape(
                "max",
                &[x.shape()],
                "max over an empty axis",
            ));
        }
        let ax = Axis(self.axis);
        let mut idx = ArrayD::<usize>::zeros(IxDyn(&reduced_shape(x.shape(), &[self.axis], false)));
        let mut y = ArrayD::<T>::zeros(IxDyn(&reduced_shape(x.shape(), &[self.axis], false)));
        Zip::from(&mut y)
            .and(&mut idx)
            .and(x.lanes(ax))
            .for_each(|y, i, lane| {
                let mut best = lane[0];
                let mut bi = 0;
                for (k, &v) in lane.iter().enumerate().skip(1) {
                    // NaN wins, so that it propagates.
                    if v > best || (v.is_nan() && !best.is_nan()) {
                        best = v;
                        bi = k;
                    }
                }
                *y = best;
                *i = bi;
            });
        self.argmax = idx;
        if self.keepdim {
            y = y.insert_axis(ax);
        }
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let x = ctx.inputs[0];
        let ax = Axis(self.axis);
        let mut g_in = ArrayD::<T>::zeros(x.raw_dim());
        let g = if self.keepdim {
            ctx.grad_outputs[0].index_axis(ax, 0)
        } else {
            ctx.grad_outputs[0].view()
        };
        Zip::from(g_in.lanes_mut(ax))
            .and(&g)
            .and(&self.argmax)
            .for_each(|mut lane, &g, &i| lane[i] = g);
        Ok(vec![Some(g_in)])
    }
}

/// `log(sum(exp(x)))` over one axis, computed stably by subtracting the maximum.
pub struct LogSumExpOp {
    /// Axis to reduce.
    pub axis: usize,
    /// Keep the reduced axis as size 1.
    pub keepdim: bool,
}

impl<T: Real> Op<T> for LogSumExpOp {
    fn name(&self) -> &'static str {
        "logsumexp"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let x = inputs[0];
        check_axes("logsumexp", x.shape(), &[self.axis])?;
        let ax = Axis(self.axis);
        let mut y = ArrayD::<T>::zeros(IxDyn(&reduced_shape(x.shape(), &[self.axis], false)));
        Zip::from(&mut y).and(x.lanes(ax)).for_each(|y, lane| {
            // A NaN-propagating maximum (`T::max` would skip NaN and let +inf hide it).
            let m = lane.iter().copied().fold(T::neg_infinity(), |a, b| {
                if b > a || b.is_nan() {
                    b
                } else {
                    a
                }
            });
            *y = if m.is_infinite() {
                m
            } else {
                m + lane.iter().map(|&v| (v - m).exp()).sum::<T>().ln()
            };
        });
        if self.keepdim {
            y = y.insert_axis(ax);
        }
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let x = ctx.inputs[0];
        let ax = Axis(self.axis);
        let (y, g) = if self.keepdim {
            (
                ctx.outputs[0].index_axis(ax, 0),
                ctx.grad_outputs[0].index_axis(ax, 0),
            )
        } else {
            (ctx.outputs[0].view(), ctx.grad_outputs[0].view())
        };
        let mut gi = ArrayD::<T>::zeros(x.raw_dim());
        Zip::from(gi.lanes_mut(ax))
            .and(x.lanes(ax))
            .and(&y)
            .and(&g)
            .for_each(|mut out, lane, &y, &g| {
                for (o, &v) in out.iter_mut().zip(lane.iter()) {
                    // softmax weight; zero where y = -inf (all inputs -inf)
                    *o = if y.is_infinite() {
                        T::zero()
                    } else {
                        g * (v - y).exp()
                    };
                }
            });
        Ok(vec![Some(gi)])
    }
}
