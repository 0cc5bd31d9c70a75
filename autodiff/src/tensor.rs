//! Tensors are ndarray's dynamic-dimensional arrays; this module holds the shape algebra
//! (NumPy broadcasting, reducing a broadcast gradient back to its input's shape) and the
//! parallel elementwise kernels every op shares.
//!
//! Parallel kernels split work into chunks whose boundaries do not depend on the number of
//! threads, and reduce partial results in chunk order, so results are bit-identical for any
//! rayon pool size.

use ndarray::{ArrayD, ArrayViewD, Axis, IxDyn, Zip};
use rayon::prelude::*;

use crate::error::{AutodiffError, Result};
use crate::Real;

/// An n-dimensional array of scalars (row-major by default).
pub type Tensor<T> = ArrayD<T>;

/// Elements from which elementwise kernels go parallel.
pub const PAR_MIN_LEN: usize = 1 << 15;
/// Fixed chunk length of deterministic parallel reductions.
pub const REDUCE_CHUNK: usize = 1 << 14;

/// A tensor of the given shape from a flat row-major vector.
pub fn from_vec<T: Real>(shape: &[usize], data: Vec<T>) -> Result<Tensor<T>> {
    let n: usize = shape.iter().product();
    if n != data.len() {
        return Err(AutodiffError::shape(
            "from_vec",
            &[shape],
            format!("{} values given for {} elements", data.len(), n),
        ));
    }
    Ok(ArrayD::from_shape_vec(IxDyn(shape), data).expect("length checked"))
}

/// `x` in row-major (standard) layout, copied only when it is not already. Ops return their
/// outputs in this layout, so that code reading a tensor as a flat row-major slice works on
/// any op's output.
pub fn into_standard<T: Real>(x: Tensor<T>) -> Tensor<T> {
    if x.is_standard_layout() {
        x
    } else {
        x.as_standard_layout().into_owned()
    }
}

/// A 0-dimensional tensor holding `x`.
pub fn scalar<T: Real>(x: T) -> Tensor<T> {
    ArrayD::from_elem(IxDyn(&[]), x)
}

/// NumPy broadcasting of two shapes.
pub fn broadcast_shapes(op: &'static str, a: &[usize], b: &[usize]) -> Result<Vec<usize>> {
    let n = a.len().max(b.len());
    let mut out = vec![0; n];
    for i in 0..n {
        let da = if i + a.len() >= n { a[i + a.len() - n] } else { 1 };
        let db = if i + b.len() >= n { b[i + b.len() - n] } else { 1 };
        out[i] = if da == db || db == 1 {
            da
        } else if da == 1 {
            db
        } else {
            return Err(AutodiffError::shape(
                op,
                &[a, b],
                format!("dimension {i} of the broadcast: {da} vs {db}"),
            ));
        };
    }
    Ok(out)
}

/// Sums `g` over the axes along which `shape` was broadcast to `g`'s shape (the adjoint of
/// broadcasting).
pub fn sum_to_shape<T: Real>(g: Tensor<T>, shape: &[usize]) -> Tensor<T> {
    if g.shape() == shape {
        return g;
    }
    let mut g = g;
    while g.ndim() > shape.len() {
        g = sum_axis_det(&g.view(), 0);
    }
    for (i, &d) in shape.iter().enumerate() {
        if d == 1 && g.shape()[i] != 1 {
            g = sum_axis_det(&g.view(), i).insert_axis(Axis(i));
        }
    }
    g
}

/// Sum over one axis, in index order along that axis (deterministic).
pub fn sum_axis_det<T: Real>(x: &ArrayViewD<T>, axis: usize) -> Tensor<T> {
    let mut shape = x.shape().to_vec();
    let n = shape.remove(axis);
    let mut out = ArrayD::<T>::zeros(IxDyn(&shape));
    for k in 0..n {
        let lane = x.index_axis(Axis(axis), k);
        if out.len() >= PAR_MIN_LEN {
            Zip::from(&mut out).and(&lane).par_for_each(|o, &v| *o += v);
        } else {
            Zip::from(&mut out).and(&lane).for_each(|o, &v| *o += v);
        }
    }
    out
}

/// Sum of all elements: fixed-size chunks summed in parallel, partial sums added in order.
pub fn sum_all_det<T: Real>(x: &Tensor<T>) -> T {
    match x.as_slice() {
        Some(s) if s.len() >= PAR_MIN_LEN => {
            let parts: Vec<T> = s
                .par_chunks(REDUCE_CHUNK)
                .map(|c| c.iter().copied().sum())
                .collect();
            parts.into_iter().sum()
        }
        Some(s) => s.iter().copied().sum(),
        None => x.iter().copied().sum(),
    }
}

/// `f` applied to every element (parallel for large tensors).
pub fn map1<T: Real, F>(x: &Tensor<T>, f: F) -> Tensor<T>
where
    F: Fn(T) -> T + Sync + Send,
{
    if x.len() >= PAR_MIN_LEN {
        Zip::from(x).par_map_collect(|&a| f(a))
    } else {
        x.mapv(f)
    }
}

/// `f` over two tensors of the same shape.
pub fn map2<T: Real, F>(x: &ArrayViewD<T>, y: &ArrayViewD<T>, f: F) -> Tensor<T>
where
    F: Fn(T, T) -> T + Sync + Send,
{
    if x.len() >= PAR_MIN_LEN {
        Zip::from(x).and(y).par_map_collect(|&a, &b| f(a, b))
    } else {
        Zip::from(x).and(y).map_collect(|&a, &b| f(a, b))
    }
}

/// `f` over three tensors of the same shape.
pub fn map3<T: Real, F>(x: &ArrayViewD<T>, y: &ArrayViewD<T>, z: &ArrayViewD<T>, f: F) -> Tensor<T>
where
    F: Fn(T, T, T) -> T + Sync + Send,
{
    if x.len() >= PAR_MIN_LEN {
        Zip::from(x)
            .and(y)
            .and(z)
            .par_map_collect(|&a, &b, &c| f(a, b, c))
    } else {
        Zip::from(x)
            .and(y)
            .and(z)
            .map_collect(|&a, &b, &c| f(a, b, c))
    }
}

/// Checks that every element is finite.
pub fn all_finite<T: Real>(x: &Tensor<T>) -> bool {
    match x.as_slice() {
        Some(s) if s.len() >= PAR_MIN_LEN => s.par_chunks(REDUCE_CHUNK).all(|c| c.iter().all(|v| v.is_finite())),
        _ => x.iter().all(|v| v.is_finite()),
    }
}

/// Casts a tensor to another scalar type.
pub fn cast<T: Real, U: Real>(x: &Tensor<T>) -> Tensor<U> {
    x.mapv(|v| U::from_f64c(v.to_f64c()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broadcasting_follows_numpy() {
        assert_eq!(broadcast_shapes("t", &[3, 1, 5], &[4, 1]).unwrap(), vec![3, 4, 5]);
        assert_eq!(broadcast_shapes("t", &[], &[2, 2]).unwrap(), vec![2, 2]);
        let e = broadcast_shapes("add", &[3, 2], &[4, 2]).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("add") && msg.contains("[3, 2]") && msg.contains("[4, 2]"), "{msg}");
    }

    #[test]
    fn sum_to_shape_is_the_adjoint_of_broadcasting() {
        let g = ArrayD::<f64>::ones(IxDyn(&[2, 3, 4]));
        let r = sum_to_shape(g, &[3, 1]);
        assert_eq!(r.shape(), &[3, 1]);
        assert!(r.iter().all(|&v| v == 8.0));
    }

    #[test]
    fn parallel_sum_is_independent_of_thread_count() {
        let x = ArrayD::from_shape_fn(IxDyn(&[100_003]), |i| ((i[0] as f32) * 0.37).sin());
        let sums: Vec<f32> = [1, 2, 8]
            .iter()
            .map(|&n| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .unwrap()
                    .install(|| sum_all_det(&x))
            })
            .collect();
        assert_eq!(sums[0].to_bits(), sums[1].to_bits());
        assert_eq!(sums[0].to_bits(), sums[2].to_bits());
    }
}
