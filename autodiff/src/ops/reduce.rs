//! Reductions over axes: sum, mean, max, logsumexp, and the fused squared-error loss. Sums run
//! in a fixed order (see [`crate::tensor`]) so results do not depend on the thread count.

use ndarray::{ArrayD, Axis, IxDyn, Zip};
use rayon::prelude::*;

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{
    full, map1, map2, scalar, sum_all_det, sum_axis_det, Tensor, TensorView, PAR_MIN_LEN,
    REDUCE_CHUNK,
};
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

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
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
            let mut y = x.to_owned();
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

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
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

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
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

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let x = &ctx.inputs[0];
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

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
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

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let x = &ctx.inputs[0];
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

/// `sum((a - b)^2)` over all elements of two tensors of one shape, fused: the forward reads both
/// once and stores nothing image-sized, the backward writes `2 (a - b) g` (and its negative for
/// `b`) in one pass. The same value as `(a - b).square().sum()` (same operations in the same
/// order: fixed chunks, [`crate::tensor::sum_slice`]'s partial sums), without
/// the difference, square and gradient-broadcast tensors of the composed form (the photometric
/// loss of analysis-by-synthesis over a whole image).
pub struct SumSquaredDiffOp;

/// `sum((a - b)^2)` of two slices of one length, in the fixed order of
/// [`crate::tensor::sum_slice`] (16 partial sums folded pairwise, then the tail).
fn sum_sq_diff_slice<T: Real>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::zero(); 16];
    let (ca, cb) = (a.chunks_exact(16), b.chunks_exact(16));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for ((s, &u), &v) in acc.iter_mut().zip(x).zip(y) {
            let d = u - v;
            *s += d * d;
        }
    }
    let mut w = 16;
    while w > 1 {
        w /= 2;
        for k in 0..w {
            acc[k] += acc[k + w];
        }
    }
    ra.iter().zip(rb).fold(acc[0], |s, (&u, &v)| {
        let d = u - v;
        s + d * d
    })
}

impl<T: Real> Op<T> for SumSquaredDiffOp {
    fn name(&self) -> &'static str {
        "sum_squared_diff"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (&inputs[0], &inputs[1]);
        if a.shape() != b.shape() {
            return Err(AutodiffError::shape(
                "sum_squared_diff",
                &[a.shape(), b.shape()],
                "both tensors must have the same shape",
            ));
        }
        let (a, b) = (a.as_standard_layout(), b.as_standard_layout());
        let (a, b) = (a.as_slice().expect("std"), b.as_slice().expect("std"));
        let s = if a.len() >= PAR_MIN_LEN {
            // Fixed chunks summed in parallel, partial sums added in chunk order.
            let parts: Vec<T> = a
                .par_chunks(REDUCE_CHUNK)
                .zip(b.par_chunks(REDUCE_CHUNK))
                .map(|(x, y)| sum_sq_diff_slice(x, y))
                .collect();
            parts.into_iter().fold(T::zero(), |s, v| s + v)
        } else {
            sum_sq_diff_slice(a, b)
        };
        Ok(vec![scalar(s)])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] && !ctx.needs_grad[1] {
            return Ok(vec![None, None]);
        }
        let g2 = *ctx.grad_outputs[0].iter().next().expect("scalar") * T::from_f64c(2.0);
        let ga = map2(&ctx.inputs[0].view(), &ctx.inputs[1].view(), |u, v| {
            (u - v) * g2
        });
        let gb = ctx.needs_grad[1].then(|| map1(&ga, |v| -v));
        Ok(vec![ctx.needs_grad[0].then_some(ga), gb])
    }
}

#[cfg(test)]
mod tests {
    use crate::tape::Tape;
    use ndarray::{ArrayD, IxDyn};

    /// The fused loss equals the composed `(a - b).square().sum()` bit for bit, gives
    /// the composed gradients to both inputs, is bit-identical for any thread count, and
    /// rejects mismatched shapes with a typed error.
    #[test]
    fn sum_squared_diff_matches_composed_form_and_is_deterministic() {
        let n = 100_003;
        let a = ArrayD::from_shape_fn(IxDyn(&[n]), |i| ((i[0] as f64) * 0.37).sin());
        let b = ArrayD::from_shape_fn(IxDyn(&[n]), |i| ((i[0] as f64) * 0.11).cos() * 0.5);
        let tape = Tape::<f64>::new();
        let (va, vb) = (tape.var(a.clone(), true), tape.var(b.clone(), true));
        let fused = va.sum_squared_diff(vb);
        let composed = (va - vb).square().sum();
        let (f, c) = (fused.item().unwrap(), composed.item().unwrap());
        // The same operations in the same order (fixed chunks, 16 partial sums): the same bits.
        assert_eq!(f.to_bits(), c.to_bits(), "{f} vs {c}");
        let (gf, gc) = (
            tape.backward(fused).unwrap(),
            tape.backward(composed).unwrap(),
        );
        for v in [va, vb] {
            let (x, y) = (gf.get(v).unwrap(), gc.get(v).unwrap());
            assert!(x.iter().zip(y.iter()).all(|(p, q)| (p - q).abs() <= 1e-15));
        }
        // f32, pools of 1, 2 and 5 threads: the same bits.
        let (a32, b32) = (a.mapv(|v| v as f32), b.mapv(|v| v as f32));
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    let t = Tape::<f32>::new();
                    let (x, y) = (t.var(a32.clone(), true), t.var(b32.clone(), false));
                    let l = x.sum_squared_diff(y);
                    let g = t.backward(l).unwrap();
                    let gx: Vec<u32> = g.get(x).unwrap().iter().map(|v| v.to_bits()).collect();
                    assert!(g.get(y).is_none());
                    (l.item().unwrap().to_bits(), gx)
                })
        };
        let r1 = run(1);
        assert_eq!(r1, run(2));
        assert_eq!(r1, run(5));
        // Shapes must match.
        let t = Tape::<f64>::new();
        let bad = t
            .var(ArrayD::zeros(IxDyn(&[2, 3])), true)
            .sum_squared_diff(t.var(ArrayD::zeros(IxDyn(&[3, 2])), true));
        assert!(bad.value().is_err());
    }
}
