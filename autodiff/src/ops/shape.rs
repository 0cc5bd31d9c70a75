//! Shape ops: reshape, permute (transpose), slice, concat, stack, broadcast_to.

use ndarray::{ArrayD, Axis, IxDyn, Slice};

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{broadcast_shapes, into_standard, sum_to_shape, Tensor, TensorView};
use crate::Real;

/// Reshape to a new shape with the same number of elements (row-major order).
pub struct ReshapeOp(pub Vec<usize>);

impl<T: Real> Op<T> for ReshapeOp {
    fn name(&self) -> &'static str {
        "reshape"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        let n: usize = self.0.iter().product();
        if n != x.len() {
            return Err(AutodiffError::shape(
                "reshape",
                &[x.shape(), &self.0],
                format!("{} elements cannot take a shape of {} elements", x.len(), n),
            ));
        }
        let y = x
            .as_standard_layout()
            .into_owned()
            .into_shape_with_order(IxDyn(&self.0))
            .expect("count checked");
        Ok(vec![y])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        Ok(vec![ctx.needs_grad[0].then(|| {
            ctx.grad_outputs[0]
                .as_standard_layout()
                .into_owned()
                .into_shape_with_order(IxDyn(ctx.inputs[0].shape()))
                .expect("same count")
        })])
    }
}

/// Reorders the axes: output axis `i` is input axis `perm[i]`.
pub struct PermuteOp(pub Vec<usize>);

/// Checks that `perm` is a permutation of `0..n`.
pub fn check_perm(op: &'static str, shape: &[usize], perm: &[usize]) -> Result<()> {
    let mut seen = vec![false; shape.len()];
    if perm.len() != shape.len() {
        return Err(AutodiffError::index(
            op,
            &[shape],
            format!(
                "permutation {perm:?} has {} axes, the input {}",
                perm.len(),
                shape.len()
            ),
        ));
    }
    for &p in perm {
        if p >= shape.len() || seen[p] {
            return Err(AutodiffError::index(
                op,
                &[shape],
                format!("{perm:?} is not a permutation"),
            ));
        }
        seen[p] = true;
    }
    Ok(())
}

impl<T: Real> Op<T> for PermuteOp {
    fn name(&self) -> &'static str {
        "permute"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        check_perm("permute", x.shape(), &self.0)?;
        let y = x
            .view()
            .permuted_axes(IxDyn(&self.0))
            .as_standard_layout()
            .into_owned();
        Ok(vec![y])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let mut inv = vec![0; self.0.len()];
        for (i, &p) in self.0.iter().enumerate() {
            inv[p] = i;
        }
        Ok(vec![ctx.needs_grad[0].then(|| {
            ctx.grad_outputs[0]
                .view()
                .permuted_axes(IxDyn(&inv))
                .as_standard_layout()
                .into_owned()
        })])
    }
}

/// `x[.., start..end, ..]` along one axis.
pub struct SliceOp {
    /// Axis to slice.
    pub axis: usize,
    /// First index.
    pub start: usize,
    /// One past the last index.
    pub end: usize,
}

impl<T: Real> Op<T> for SliceOp {
    fn name(&self) -> &'static str {
        "slice"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        if self.axis >= x.ndim() || self.start > self.end || self.end > x.shape()[self.axis] {
            return Err(AutodiffError::index(
                "slice",
                &[x.shape()],
                format!("range {}..{} on axis {}", self.start, self.end, self.axis),
            ));
        }
        let y = x
            .slice_axis(Axis(self.axis), Slice::from(self.start..self.end))
            .to_owned();
        Ok(vec![y])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        Ok(vec![ctx.needs_grad[0].then(|| {
            let mut g = ArrayD::<T>::zeros(ctx.inputs[0].raw_dim());
            g.slice_axis_mut(Axis(self.axis), Slice::from(self.start..self.end))
                .assign(ctx.grad_outputs[0]);
            g
        })])
    }
}

/// Concatenation of several tensors along an existing axis.
pub struct ConcatOp(pub usize);

/// Concatenation of standard-layout tensors along `ax` as row copies: for each index of the
/// axes before `ax`, each input's contiguous block in turn. `None` when an input is not in
/// standard layout or the shapes differ off `ax` (the general path handles and reports those).
fn concat_standard<T: Real>(inputs: &[TensorView<'_, T>], ax: usize) -> Option<Tensor<T>> {
    let first = inputs[0].shape();
    let outer: usize = first[..ax].iter().product();
    let mut shape = first.to_vec();
    shape[ax] = 0;
    let mut inner = Vec::with_capacity(inputs.len());
    let mut slices = Vec::with_capacity(inputs.len());
    for t in inputs {
        let sh = t.shape();
        if sh.len() != first.len() || sh[..ax] != first[..ax] || sh[ax + 1..] != first[ax + 1..] {
            return None;
        }
        shape[ax] += sh[ax];
        inner.push(sh[ax..].iter().product::<usize>());
        slices.push(t.as_slice()?);
    }
    let row: usize = inner.iter().sum();
    let mut out = Vec::with_capacity(outer * row);
    for o in 0..outer {
        for (s, &n) in slices.iter().zip(&inner) {
            out.extend_from_slice(&s[o * n..(o + 1) * n]);
        }
    }
    ArrayD::from_shape_vec(IxDyn(&shape), out).ok()
}

impl<T: Real> Op<T> for ConcatOp {
    fn name(&self) -> &'static str {
        "concat"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let shapes: Vec<&[usize]> = inputs.iter().map(|t| t.shape()).collect();
        if inputs.is_empty() {
            return Err(AutodiffError::invalid("concat", "no inputs"));
        }
        let views: Vec<_> = inputs.iter().map(|t| t.view()).collect();
        if self.0 >= inputs[0].ndim() {
            return Err(AutodiffError::index(
                "concat",
                &shapes,
                format!("axis {} out of range", self.0),
            ));
        }
        if let Some(y) = concat_standard(inputs, self.0) {
            return Ok(vec![y]);
        }
        ndarray::concatenate(Axis(self.0), &views)
            .map(|y| vec![into_standard(y)])
            .map_err(|_| {
                AutodiffError::shape(
                    "concat",
                    &shapes,
                    format!("shapes differ off axis {}", self.0),
                )
            })
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let g = ctx.grad_outputs[0];
        let mut at = 0;
        Ok(ctx
            .inputs
            .iter()
            .zip(ctx.needs_grad)
            .map(|(x, &need)| {
                let n = x.shape()[self.0];
                let r = need.then(|| {
                    g.slice_axis(Axis(self.0), Slice::from(at..at + n))
                        .to_owned()
                });
                at += n;
                r
            })
            .collect())
    }
}

/// Stacking of equally shaped tensors along a new axis.
pub struct StackOp(pub usize);

impl<T: Real> Op<T> for StackOp {
    fn name(&self) -> &'static str {
        "stack"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let shapes: Vec<&[usize]> = inputs.iter().map(|t| t.shape()).collect();
        if inputs.is_empty() {
            return Err(AutodiffError::invalid("stack", "no inputs"));
        }
        if self.0 > inputs[0].ndim() {
            return Err(AutodiffError::index(
                "stack",
                &shapes,
                format!("axis {} out of range", self.0),
            ));
        }
        let views: Vec<_> = inputs.iter().map(|t| t.view()).collect();
        ndarray::stack(Axis(self.0), &views)
            .map(|y| vec![into_standard(y)])
            .map_err(|_| AutodiffError::shape("stack", &shapes, "stack needs equal shapes"))
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let g = ctx.grad_outputs[0];
        Ok(ctx
            .needs_grad
            .iter()
            .enumerate()
            .map(|(i, &need)| need.then(|| g.index_axis(Axis(self.0), i).to_owned()))
            .collect())
    }
}

/// Broadcast to a larger shape (NumPy rules); the gradient is summed back.
pub struct BroadcastToOp(pub Vec<usize>);

impl<T: Real> Op<T> for BroadcastToOp {
    fn name(&self) -> &'static str {
        "broadcast_to"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        let s = broadcast_shapes("broadcast_to", x.shape(), &self.0)?;
        if s != self.0 {
            return Err(AutodiffError::shape(
                "broadcast_to",
                &[x.shape(), &self.0],
                "input does not broadcast to the target shape",
            ));
        }
        Ok(vec![x
            .broadcast(IxDyn(&self.0))
            .expect("checked")
            .to_owned()])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        Ok(vec![ctx.needs_grad[0].then(|| {
            sum_to_shape(ctx.grad_outputs[0].clone(), ctx.inputs[0].shape())
        })])
    }
}
