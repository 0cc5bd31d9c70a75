//! Matrix products: matrix-matrix, matrix-vector, vector-vector and batched (with the batch
//! dimension broadcast). Matrix-vector products, the core of linear (3DMM) models, run in
//! parallel over fixed row blocks and reduce the transposed product block by block in a fixed
//! order, so they are deterministic for any thread count.

use ndarray::linalg::general_mat_mul;
use ndarray::{Array1, Array2, ArrayD, ArrayView1, ArrayView2, Axis, Ix1, Ix2, IxDyn};
use rayon::prelude::*;

use crate::error::{AutodiffError, Result};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{scalar, Tensor, TensorView};
use crate::Real;

const ROW_BLOCK: usize = 256;

/// `y = A x` for a row-major `A` [M, K], in parallel over fixed row blocks.
pub fn gemv<T: Real>(a: &ArrayView2<T>, x: &ArrayView1<T>) -> Array1<T> {
    let (m, k) = a.dim();
    let mut y = Array1::<T>::zeros(m);
    if let (Some(a_s), Some(x_s)) = (a.as_slice(), x.as_slice()) {
        if k == 0 {
            return y;
        }
        y.as_slice_mut()
            .expect("fresh")
            .par_chunks_mut(ROW_BLOCK)
            .enumerate()
            .for_each(|(blk, ys)| {
                let rows = &a_s[blk * ROW_BLOCK * k..(blk * ROW_BLOCK + ys.len()) * k];
                gemv_block(rows, x_s, ys);
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
///
/// The blocks are visited from the last to the first: a backward pass runs right after the
/// forward [`gemv`] over the same matrix, which read it from the first row to the last, so
/// the rows it read last (still in the last-level cache when `A` is larger than it) are read
/// again first. The order of the visits does not change the result.
pub fn gemv_t<T: Real>(a: &ArrayView2<T>, g: &ArrayView1<T>) -> Array1<T> {
    let (m, k) = a.dim();
    if let (Some(a_s), Some(g_s)) = (a.as_slice(), g.as_slice()) {
        if k == 0 {
            return Array1::zeros(0);
        }
        let mut partials = vec![T::zero(); m.div_ceil(ROW_BLOCK) * k];
        partials
            .par_chunks_mut(k)
            .enumerate()
            .rev()
            .for_each(|(blk, acc)| {
                let r1 = ((blk + 1) * ROW_BLOCK).min(m);
                axpy_block(
                    &a_s[blk * ROW_BLOCK * k..r1 * k],
                    &g_s[blk * ROW_BLOCK..r1],
                    acc,
                );
            });
        let mut y = vec![T::zero(); k];
        for p in partials.chunks_exact(k) {
            for (o, &v) in y.iter_mut().zip(p) {
                *o += v;
            }
        }
        Array1::from(y)
    } else {
        a.t().dot(g)
    }
}

/// Dot product in a fixed order: 16 interleaved partial sums (vectorisable), added pairwise,
/// then the tail.
#[inline(always)]
fn dot_slice<T: Real>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::zero(); 16];
    let (ca, cb) = (a.chunks_exact(16), b.chunks_exact(16));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for j in 0..16 {
            acc[j] += x[j] * y[j];
        }
    }
    let mut w = 16;
    while w > 1 {
        w /= 2;
        for j in 0..w {
            acc[j] += acc[j + w];
        }
    }
    ra.iter().zip(rb).fold(acc[0], |s, (&x, &y)| s + x * y)
}

/// `ys[r] = rows[r] . x` for consecutive rows of length `x.len()`.
#[inline(always)]
fn gemv_rows<T: Real>(rows: &[T], x: &[T], ys: &mut [T]) {
    for (yv, row) in ys.iter_mut().zip(rows.chunks_exact(x.len())) {
        *yv = dot_slice(row, x);
    }
}

/// `acc += sum_r g[r] rows[r]`, row by row (one sequential stream through the rows, see
/// [`super::stream_f32`]).
#[inline(always)]
fn axpy_rows<T: Real>(rows: &[T], g: &[T], acc: &mut [T]) {
    for (row, &gr) in rows.chunks_exact(acc.len()).zip(g) {
        for (o, &v) in acc.iter_mut().zip(row) {
            *o += gr * v;
        }
    }
}

/// One row block of [`gemv`]: the explicit AVX2 kernel for `f32` where the CPU has it, else
/// the generic one.
fn gemv_block<T: Real>(rows: &[T], x: &[T], ys: &mut [T]) {
    if let (Some(r), Some(x), Some(y)) = (T::as_f32(rows), T::as_f32(x), T::as_f32_mut(ys)) {
        if super::stream_f32::gemv_rows(r, x, y) {
            return;
        }
    }
    dispatch_gemv_rows(rows, x, ys);
}

/// One row block of [`gemv_t`], dispatched as [`gemv_block`].
fn axpy_block<T: Real>(rows: &[T], g: &[T], acc: &mut [T]) {
    if let (Some(r), Some(g), Some(a)) = (T::as_f32(rows), T::as_f32(g), T::as_f32_mut(acc)) {
        if super::stream_f32::axpy_rows(r, g, a) {
            return;
        }
    }
    dispatch_axpy_rows(rows, g, acc);
}

/// Runs `f` compiled for AVX2 + FMA when the CPU has them (the generic loops above are
/// inlined into it and vectorise at that width), else for the baseline target.
macro_rules! dispatch {
    ($name:ident, $body:ident, ($($a:ident: $ta:ty),*)) => {
        fn $name<T: Real>($($a: $ta),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide<T: Real>($($a: $ta),*) {
                    $body($($a),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU has the features `wide` is compiled for.
                    return unsafe { wide($($a),*) };
                }
            }
            $body($($a),*)
        }
    };
}

dispatch!(dispatch_gemv_rows, gemv_rows, (rows: &[T], x: &[T], ys: &mut [T]));
dispatch!(dispatch_axpy_rows, axpy_rows, (rows: &[T], g: &[T], acc: &mut [T]));

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

fn as2<T: Real, S: ndarray::Data<Elem = T>>(t: &ndarray::ArrayBase<S, IxDyn>) -> ArrayView2<'_, T> {
    t.view().into_dimensionality::<Ix2>().expect("2-d")
}
fn as1<T: Real, S: ndarray::Data<Elem = T>>(t: &ndarray::ArrayBase<S, IxDyn>) -> ArrayView1<'_, T> {
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
        (1..=3, 1..=3) => Err(mm_err(
            a,
            b,
            "inner dimensions differ or batch sizes do not broadcast",
        )),
        _ => Err(mm_err(a, b, "matmul takes 1-, 2- or 3-dimensional inputs")),
    }
}

impl<T: Real> Op<T> for MatMulOp {
    fn name(&self) -> &'static str {
        "matmul"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let (a, b) = (&inputs[0], &inputs[1]);
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
                    let mut yi = y
                        .index_axis_mut(Axis(0), i)
                        .into_dimensionality::<Ix2>()
                        .expect("2-d");
                    general_mat_mul(T::one(), &ai, &bi, T::zero(), &mut yi);
                }
                y
            }
        };
        Ok(vec![y])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let (a, b, g) = (&ctx.inputs[0], &ctx.inputs[1], ctx.grad_outputs[0]);
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
                    let ib = if b.ndim() == 3 && b.shape()[0] != 1 {
                        i
                    } else {
                        0
                    };
                    let ai = a
                        .index_axis(Axis(0), ia)
                        .into_dimensionality::<Ix2>()
                        .expect("2-d");
                    let bi = if b.ndim() == 3 {
                        b.index_axis(Axis(0), ib)
                    } else {
                        b.view()
                    }
                    .into_dimensionality::<Ix2>()
                    .expect("2-d");
                    let gi = g
                        .index_axis(Axis(0), i)
                        .into_dimensionality::<Ix2>()
                        .expect("2-d");
                    if let Some(ga) = ga.as_mut() {
                        let mut t = ga
                            .index_axis_mut(Axis(0), ia)
                            .into_dimensionality::<Ix2>()
                            .expect("2-d");
                        general_mat_mul(T::one(), &gi, &bi.t(), T::one(), &mut t);
                    }
                    if let Some(gb) = gb.as_mut() {
                        if b.ndim() == 3 {
                            let mut t = gb
                                .index_axis_mut(Axis(0), ib)
                                .into_dimensionality::<Ix2>()
                                .expect("2-d");
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Generic path (f64): each row is summed as `dot_slice` does, whatever the block split.
    #[test]
    fn gemv_rows_match_dot_slice() {
        let mut r = Rng::new(11);
        for (m, k) in [(1031usize, 199usize), (7, 16), (5, 3), (13, 35)] {
            let a: Tensor<f64> = r.normal_tensor(&[m, k]);
            let x: Tensor<f64> = r.normal_tensor(&[k]);
            let a2 = as2(&a);
            let x1 = as1(&x);
            let y = gemv(&a2, &x1);
            for (i, row) in a2.rows().into_iter().enumerate() {
                let want = dot_slice(row.as_slice().unwrap(), x1.as_slice().unwrap());
                assert_eq!(y[i].to_bits(), want.to_bits(), "m {m} k {k} row {i}");
            }
        }
    }

    /// f32 (explicit kernels where the CPU has them): bit-identical on 1 and 3 threads, and
    /// within f32 rounding of the f64 products.
    #[test]
    fn gemv_f32_deterministic_and_accurate() {
        let mut r = Rng::new(12);
        let (m, k) = (3000usize, 199usize);
        let a: Tensor<f64> = r.normal_tensor(&[m, k]);
        let x: Tensor<f64> = r.normal_tensor(&[k]);
        let g: Tensor<f64> = r.normal_tensor(&[m]);
        let (af, xf, gf) = (
            a.mapv(|v| v as f32),
            x.mapv(|v| v as f32),
            g.mapv(|v| v as f32),
        );
        let run = |n: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap();
            pool.install(|| (gemv(&as2(&af), &as1(&xf)), gemv_t(&as2(&af), &as1(&gf))))
        };
        let (y1, t1) = run(1);
        let (y3, t3) = run(3);
        assert!(y1.iter().zip(&y3).all(|(p, q)| p.to_bits() == q.to_bits()));
        assert!(t1.iter().zip(&t3).all(|(p, q)| p.to_bits() == q.to_bits()));
        let (y64, t64) = (gemv(&as2(&a), &as1(&x)), gemv_t(&as2(&a), &as1(&g)));
        for (p, q) in y1.iter().zip(&y64) {
            assert!((*p as f64 - q).abs() < 1e-4 * (1.0 + q.abs()), "{p} {q}");
        }
        for (p, q) in t1.iter().zip(&t64) {
            assert!((*p as f64 - q).abs() < 1e-3 * (1.0 + q.abs()), "{p} {q}");
        }
    }
}
