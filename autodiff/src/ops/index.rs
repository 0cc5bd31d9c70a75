//! Indexing ops: index_select, gather and scatter_add. Indices are data of the op (not
//! differentiable) and are validated against the input shape. Scatter-adds run sequentially
//! in index order, so accumulated sums are deterministic.

use ndarray::{ArrayD, Axis, IxDyn};

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{into_standard, Tensor, TensorView};
use crate::Real;

/// Rows (sub-tensors along `axis`) picked by `indices`, repeats allowed.
pub struct IndexSelectOp {
    /// Axis to index.
    pub axis: usize,
    /// Indices along that axis.
    pub indices: Vec<usize>,
}

impl<T: Real> Op<T> for IndexSelectOp {
    fn name(&self) -> &'static str {
        "index_select"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        if self.axis >= x.ndim() {
            return Err(AutodiffError::index(
                "index_select",
                &[x.shape()],
                format!("axis {} out of range", self.axis),
            ));
        }
        let n = x.shape()[self.axis];
        if let Some((k, &bad)) = self.indices.iter().enumerate().find(|(_, &i)| i >= n) {
            return Err(AutodiffError::index(
                "index_select",
                &[x.shape()],
                format!(
                    "index {bad} (position {k}) out of range for size {n} on axis {}",
                    self.axis
                ),
            ));
        }
        if self.axis == 0 {
            if let Some(xs) = x.as_slice() {
                // Whole contiguous rows: one copy per row, no per-row views.
                let row = xs.len().checked_div(n).unwrap_or(0);
                let mut out = Vec::with_capacity(self.indices.len() * row);
                for &i in &self.indices {
                    out.extend_from_slice(&xs[i * row..(i + 1) * row]);
                }
                let mut shape = x.shape().to_vec();
                shape[0] = self.indices.len();
                return Ok(vec![
                    ArrayD::from_shape_vec(IxDyn(&shape), out).expect("rows of the input")
                ]);
            }
        }
        Ok(vec![into_standard(
            x.select(Axis(self.axis), &self.indices),
        )])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let ax = Axis(self.axis);
        let mut gx = ArrayD::<T>::zeros(ctx.inputs[0].raw_dim());
        let g = ctx.grad_outputs[0];
        if let (0, Some(gs)) = (self.axis, g.as_slice()) {
            // Rows added in index order (the same order as the general path).
            let n = gx.shape()[0];
            let gxs = gx.as_slice_mut().expect("fresh");
            let row = gxs.len().checked_div(n).unwrap_or(0);
            for (&i, src) in self.indices.iter().zip(gs.chunks_exact(row.max(1))) {
                for (d, &v) in gxs[i * row..(i + 1) * row].iter_mut().zip(src) {
                    *d += v;
                }
            }
            return Ok(vec![Some(gx)]);
        }
        for (k, &i) in self.indices.iter().enumerate() {
            let src = ctx.grad_outputs[0].index_axis(ax, k);
            let mut dst = gx.index_axis_mut(ax, i);
            dst += &src;
        }
        Ok(vec![Some(gx)])
    }
}

fn check_index(
    op: &'static str,
    x: &[usize],
    index: &[usize],
    axis: usize,
    size_on_axis: usize,
    idx: &ArrayD<usize>,
) -> Result<()> {
    if axis >= x.len() || index.len() != x.len() {
        return Err(AutodiffError::index(
            op,
            &[x, index],
            format!("axis {axis} and an index of the input's number of dimensions needed"),
        ));
    }
    for (d, (&i, &s)) in index.iter().zip(x).enumerate() {
        if d != axis && i > s {
            return Err(AutodiffError::shape(
                op,
                &[x, index],
                format!("index larger than the input on dimension {d}"),
            ));
        }
    }
    if let Some(bad) = idx.iter().find(|&&i| i >= size_on_axis) {
        return Err(AutodiffError::index(
            op,
            &[x, index],
            format!("index {bad} out of range for size {size_on_axis} on axis {axis}"),
        ));
    }
    Ok(())
}

/// `out[i][j][k] = x[i][index[i][j][k]][k]` for `axis = 1` (as `torch.gather`).
pub struct GatherOp {
    /// Axis along which `index` picks.
    pub axis: usize,
    /// Index tensor, same number of dimensions as the input; the output has its shape.
    pub index: ArrayD<usize>,
}

impl<T: Real> Op<T> for GatherOp {
    fn name(&self) -> &'static str {
        "gather"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let x = &inputs[0];
        let size = *x.shape().get(self.axis).unwrap_or(&0);
        check_index(
            "gather",
            x.shape(),
            self.index.shape(),
            self.axis,
            size,
            &self.index,
        )?;
        let mut src = vec![0usize; x.ndim()];
        let y = ArrayD::from_shape_fn(self.index.raw_dim(), |pos| {
            for d in 0..src.len() {
                src[d] = pos[d];
            }
            src[self.axis] = self.index[&pos];
            x[IxDyn(&src)]
        });
        Ok(vec![y])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let mut gx = ArrayD::<T>::zeros(ctx.inputs[0].raw_dim());
        scatter_into(&mut gx, self.axis, &self.index, ctx.grad_outputs[0]);
        Ok(vec![Some(gx)])
    }
}

fn scatter_into<T: Real, S: ndarray::Data<Elem = T>>(
    dst: &mut Tensor<T>,
    axis: usize,
    index: &ArrayD<usize>,
    src: &ndarray::ArrayBase<S, IxDyn>,
) {
    let mut at = vec![0usize; dst.ndim()];
    for (pos, &i) in index.indexed_iter() {
        for d in 0..at.len() {
            at[d] = pos[d];
        }
        at[axis] = i;
        dst[IxDyn(&at)] += src[&pos];
    }
}

/// `out[i][index[i][j]] += src[i][j]` for `axis = 1` into a zero tensor whose size on `axis`
/// is `dim_size` (as `torch.zeros(..).scatter_add_`), e.g. face values summed to vertices.
pub struct ScatterAddOp {
    /// Axis along which `index` places.
    pub axis: usize,
    /// Index tensor with the source's shape.
    pub index: ArrayD<usize>,
    /// Size of the output along `axis`.
    pub dim_size: usize,
}

impl<T: Real> Op<T> for ScatterAddOp {
    fn name(&self) -> &'static str {
        "scatter_add"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let src = &inputs[0];
        if self.index.shape() != src.shape() {
            return Err(AutodiffError::shape(
                "scatter_add",
                &[src.shape(), self.index.shape()],
                "index must have the source's shape",
            ));
        }
        let mut shape = src.shape().to_vec();
        if self.axis >= shape.len() {
            return Err(AutodiffError::index(
                "scatter_add",
                &[src.shape()],
                format!("axis {} out of range", self.axis),
            ));
        }
        shape[self.axis] = self.dim_size;
        check_index(
            "scatter_add",
            &shape,
            self.index.shape(),
            self.axis,
            self.dim_size,
            &self.index,
        )?;
        let mut y = ArrayD::<T>::zeros(IxDyn(&shape));
        scatter_into(&mut y, self.axis, &self.index, src);
        Ok(vec![y])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let g = ctx.grad_outputs[0];
        let mut at = vec![0usize; g.ndim()];
        let gs = ArrayD::from_shape_fn(self.index.raw_dim(), |pos| {
            for d in 0..at.len() {
                at[d] = pos[d];
            }
            at[self.axis] = self.index[&pos];
            g[IxDyn(&at)]
        });
        Ok(vec![Some(gs)])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tape::Tape;

    /// The contiguous-row path of `index_select` (axis 0) against ndarray's `select` and the
    /// general backward, on a 3-d tensor with repeated indices.
    #[test]
    fn index_select_rows_match_the_general_path() {
        let x = ArrayD::from_shape_fn(IxDyn(&[5, 2, 3]), |i| (i[0] * 6 + i[1] * 3 + i[2]) as f64);
        let idx = [4usize, 0, 4, 2];
        let tape = Tape::<f64>::new();
        let v = tape.leaf(x.clone());
        let y = v.index_select(0, &idx);
        assert_eq!(*y.value().unwrap(), x.select(Axis(0), &idx));
        let w = ArrayD::from_shape_fn(IxDyn(&[4, 2, 3]), |i| (1 + i[0] + 10 * i[2]) as f64);
        let loss = (y * tape.constant(w.clone())).sum();
        let mut g = tape.backward(loss).unwrap();
        let gx = g.take(v).unwrap();
        let mut want = ArrayD::<f64>::zeros(IxDyn(&[5, 2, 3]));
        for (k, &i) in idx.iter().enumerate() {
            let mut d = want.index_axis_mut(Axis(0), i);
            d += &w.index_axis(Axis(0), k);
        }
        assert_eq!(gx, want);
    }
}
