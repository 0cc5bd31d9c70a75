//! Matrix products: matrix-matrix, matrix-vector, vector-vector and batched (with the batch
//! dimension broadcast). Matrix-vector products, the core of linear (3DMM) models, run in
//! parallel over fixed row blocks and reduce the transposed product block by block in a fixed
//! order, so they are deterministic for any thread count.

use ndarray::linalg::general_mat_mul;
use ndarray::{Array1, Array2, ArrayD, ArrayView1, ArrayView2, Axis, Ix1, Ix2, IxDyn};
use rayon::prelude::*;

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{scalar, Tensor};
use crate::Real;

const ROW_BLOCK: usize = 256;

/// `y = A x` for a row-major `A` [M, K], in parallel over fixed row blocks.
pub fn gemv<T: Real>(a: &ArrayView2<T>, x: &ArrayView1<T>) -> Array1<T> {
    let (m, k) = a.dim();
    let mut y = Array1::<T>::zeros(m);
    if let (Some(a_s), Some(x_s)) = (a.as_slice(), x.as_slice()) {
        y.as_slice_mut()
            .expect("fresh")
            .par_chunks_mut(ROW_BLOCK)
            .enumerate()
            .for_each(|(blk, ys)| {
                for (r, yv) in ys.iter_mut().enumerate() {
                    let row = &a_s[(blk * ROW_BLOCK + r) * k..(blk * ROW_BLOCK + r + 1) * k];
                    *yv = dot_slice(row, x_s);
                }
            });
    } else {
        for (yv, row) in y.iter_mut().zip(a.rows()) {
            *yv = row.dot(x);
        }
    }
    y
}

/// `y = A^T g` for a row-major `A` [M, K]: per fixed row block a partial K-vector in
/// parallel, then the partials added in block order.
pub fn gemv_t<T: Real>(a: &ArrayView2<T>, g: &ArrayView1<T>) -> Array1<T> {
    let (m, k) = a.dim();
    if let (Some(a_s), Some(g_s)) = (a.as_slice(), g.as_slice()) {
        let partials: Vec<Vec<T>> = (0..m.div_ceil(ROW_BLOCK))
            .into_par_iter()
            .map(|blk| {
                let mut acc = vec![T::zero(); k];
                let r1 = ((blk + 1) * ROW_BLOCK).min(m);
                for r in blk * ROW_BLOCK..r1 {
                    let gr = g_s[r];
                    let row = &a_s[r * k..(r + 1) * k];
                    for (o, &v) in acc.iter_mut().zip(row) {
                        *o += gr * v;
                    }
                }
                acc
            })
            .collect();
        let mut y = vec![T::zero(); k];
        for p in partials {
            for (o, v) in y.iter_mut().zip(p) {
                *o += v;
            }
        }
        Array1::from(y)
    } else {
        a.t().dot(g)
    }
}

#[inline]
fn dot_slice<T: Real>(a: &[T], b: &[T]) -> T {
    // Four independent accumulators let the compiler vectorise; fixed order, deterministic.
    let mut acc = [T::zero(); 4];
    let chunks = a.len() / 4;
    for i in 0..chunks {
        for j in 0..4 {
            acc[j] += a[4 * i + j] * b[4 * i + j];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for i in chunks * 4..a.len() {
        s += a[i] * b[i];
    }
    s
}

fn mm<T: Real>(a: &ArrayView2<T>, b: &ArrayView2<T>) -> Array2<T> {
    let mut c = Array2::<T>::zeros((a.nrows(), b.ncols()));
    general_mat_mul(T::one(), a, b, T::zero(), &mut c);
    c
}

/// Matrix product with NumPy `matmul` semantics for 1-, 2- and 3-dimensional inputs.
pub struct MatMulOp;

fn mm_err(a: &[usize], b: &[usize], why: &str) -> AutodiffError {
    AutodiffError::shape("matmul", &[a, b], why.to_string())
}

fn as2<T: Real>(t: &Tensor<T>) -> ArrayView2<'_, T> {
    t.view().into_dimensionality::<Ix2>().expect("2-d")
}
fn as1<T: Real>(t: &Tensor<T>) -> ArrayView1<'_, T> {
    t.view().into_dimensionality::<Ix1>().expect("1-d")
}

/// Output shape of a matmul, or a shape error.
pub fn matmul_shape(a: &[usize], b: &[usize]) -> Result<Vec<usize>> {
    match (a.len(), b.len()) {
        (1, 1) if a[0] == b[0] => Ok(vec![]),
        (2, 1) if a[1] == b[0] => Ok(vec![a[0]]),
        (1, 2) if a[0] == b[0] => Ok(vec![b[1]]),
        (2, 2) if a[1] == b[0] => Ok(vec![a[0], b[1]]),
        (3, 3) if a[2] == b[1] && (a[0] == b[0] || a[0] == 1 || b[0] == 1) => {
            Ok(vec![a[0].max(b[0]), a[1], b[2]])
        }
        (3, 2) if a[2] == b[0] => Ok(vec![a[0], a[1], b[1]]),
        (1..=3, 1..=3) => Err(mm_err(a, b, "inner dimensions differ or batch sizes do not broadcast")),
        _ => Err(mm_err(a, b, "matmul takes 1-, 2- or 3-dimensional inputs")),
    }
}

impl<T: Real> Op<T> for MatMulOp {
    fn name(&self) -> &'static str {
        "matmul"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (inputs[0], inputs[1]);
        let shape = matmul_shape(a.shape(), b.shape())?;
        let y: Tensor<T> = match (a.ndim(), b.ndim()) {
            (1, 1) => scalar(as1(a).dot(&as1(b))),
            (2, 1) => gemv(&as2(a), &as1(b)).into_dyn(),
            (1, 2) => gemv_t(&as2(b), &as1(a)).into_dyn(),
            (2, 2) => mm(&as2(a), &as2(b)).into_dyn(),
            _ => {
                let mut y = ArrayD::<T>::zeros(IxDyn(&shape));
                for i in 0..shape[0] {
                    let ai = a.index_axis(Axis(0), if a.shape()[0] == 1 { 0 } else { i });
                    let bi = if b.ndim() == 3 {
                        b.index_axis(Axis(0), if b.shape()[0] == 1 { 0 } else { i })
                    } else {
                        b.view()
                    };
                    let ai = ai.into_dimensionality::<Ix2>().expect("2-d");
                    let bi = bi.into_dimensionality::<Ix2>().expect("2-d");
                    let mut yi = y.index_axis_mut(Axis(0), i).into_dimensionality::<Ix2>().expect("2-d");
                    general_mat_mul(T::one(), &ai, &bi, T::zero(), &mut yi);
                }
                y
            }
        };
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let (a, b, g) = (ctx.inputs[0], ctx.inputs[1], ctx.grad_outputs[0]);
        let (na, nb) = (ctx.needs_grad[0], ctx.needs_grad[1]);
        let out = match (a.ndim(), b.ndim()) {
            (1, 1) => {
                let gs = *g.iter().next().expect("scalar");
                (
                    na.then(|| b.mapv(|v| v * gs)),
                    nb.then(|| a.mapv(|v| v * gs)),
                )
            }
            (2, 1) => {
                let g1 = as1(g);
                (
                    na.then(|| outer(&g1, &as1(b)).into_dyn()),
                    nb.then(|| gemv_t(&as2(a), &g1).into_dyn()),
                )
            }
            (1, 2) => {
                let g1 = as1(g);
                (
                    na.then(|| gemv(&as2(b), &g1).into_dyn()),
                    nb.then(|| outer(&as1(a), &g1).into_dyn()),
                )
            }
            (2, 2) => {
                let g2 = as2(g);
                (
                    na.then(|| mm(&g2, &as2(b).t()).into_dyn()),
                    nb.then(|| mm(&as2(a).t(), &g2).into_dyn()),
                )
            }
            _ => {
                let mut ga = na.then(|| ArrayD::<T>::zeros(a.raw_dim()));
                let mut gb = nb.then(|| ArrayD::<T>::zeros(b.raw_dim()));
                for i in 0..g.shape()[0] {
                    let ia = if a.shape()[0] == 1 { 0 } else { i };
                    let ib = if b.ndim() == 3 && b.shape()[0] != 1 { i } else { 0 };
                    let ai = a.index_axis(Axis(0), ia).into_dimensionality::<Ix2>().expect("2-d");
                    let bi = if b.ndim() == 3 {
                        b.index_axis(Axis(0), ib)
                    } else {
                        b.view()
                    }
                    .into_dimensionality::<Ix2>()
                    .expect("2-d");
                    let gi = g.index_axis(Axis(0), i).into_dimensionality::<Ix2>().expect("2-d");
                    if let Some(ga) = ga.as_mut() {
                        let mut t = ga.index_axis_mut(Axis(0), ia).into_dimensionality::<Ix2>().expect("2-d");
                        general_mat_mul(T::one(), &gi, &bi.t(), T::one(), &mut t);
                    }
                    if let Some(gb) = gb.as_mut() {
                        if b.ndim() == 3 {
                            let mut t = gb.index_axis_mut(Axis(0), ib).into_dimensionality::<Ix2>().expect("2-d");
                            general_mat_mul(T::one(), &ai.t(), &gi, T::one(), &mut t);
                        } else {
                            let mut t = gb.view_mut().into_dimensionality::<Ix2>().expect("2-d");
                            general_mat_mul(T::one(), &ai.t(), &gi, T::one(), &mut t);
                        }
                    }
                }
                (ga, gb)
            }
        };
        Ok(vec![out.0, out.1])
    }
}

fn outer<T: Real>(u: &ArrayView1<T>, v: &ArrayView1<T>) -> Array2<T> {
    let (m, n) = (u.len(), v.len());
    let mut o = Array2::<T>::zeros((m, n));
    o.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(u.axis_iter(Axis(0)).into_par_iter())
        .for_each(|(mut row, ui)| {
            let ui = ui.into_scalar();
            row.zip_mut_with(v, |o, &vv| *o = *ui * vv);
        });
    o
}
