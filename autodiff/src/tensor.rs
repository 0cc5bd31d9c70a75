//! Tensors are ndarray's dynamic-dimensional arrays; this module holds the shape algebra
//! (NumPy broadcasting, reducing a broadcast gradient back to its input's shape) and the
//! parallel elementwise kernels every op shares.
//!
//! Parallel kernels split work into chunks whose boundaries do not depend on the number of
//! threads, and reduce partial results in chunk order, so results are bit-identical for any
//! rayon pool size.

use std::mem::MaybeUninit;

use ndarray::{ArrayBase, ArrayD, ArrayViewD, Axis, Data, Dimension, IxDyn, Zip};
use rayon::prelude::*;

use crate::error::{AutodiffError, Result};
use crate::Real;

/// An n-dimensional array of scalars (row-major by default).
pub type Tensor<T> = ArrayD<T>;

/// A borrowed tensor: how ops see their input values.
pub type TensorView<'a, T> = ArrayViewD<'a, T>;

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
        let da = if i + a.len() >= n {
            a[i + a.len() - n]
        } else {
            1
        };
        let db = if i + b.len() >= n {
            b[i + b.len() - n]
        } else {
            1
        };
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

/// Sum of a slice in a fixed order: 16 interleaved partial sums (vectorisable), added
/// pairwise, then the tail.
pub fn sum_slice<T: Real>(s: &[T]) -> T {
    let mut acc = [T::zero(); 16];
    let mut it = s.chunks_exact(16);
    for c in &mut it {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a += v;
        }
    }
    let mut w = 16;
    while w > 1 {
        w /= 2;
        for k in 0..w {
            acc[k] += acc[k + w];
        }
    }
    it.remainder().iter().fold(acc[0], |a, &v| a + v)
}

/// Sum of all elements: fixed-size chunks summed in parallel, partial sums added in order.
pub fn sum_all_det<T: Real, S: Data<Elem = T>>(x: &ArrayBase<S, IxDyn>) -> T {
    match x.as_slice() {
        Some(s) if s.len() >= PAR_MIN_LEN => {
            let parts: Vec<T> = s.par_chunks(REDUCE_CHUNK).map(sum_slice).collect();
            parts.into_iter().fold(T::zero(), |a, v| a + v)
        }
        Some(s) => sum_slice(s),
        None => x.iter().copied().sum(),
    }
}

/// Elements per task of the parallel elementwise kernels (fixed, so results never depend on
/// the number of threads).
pub const EW_CHUNK: usize = 1 << 14;

/// A vector of `n` elements, each chunk of [`EW_CHUNK`] filled by `fill(chunk, offset)` (in
/// parallel from [`PAR_MIN_LEN`] elements). `fill` must write every element of its chunk.
fn build<T: Real>(n: usize, fill: impl Fn(&mut [MaybeUninit<T>], usize) + Sync) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    let spare = &mut v.spare_capacity_mut()[..n];
    if n >= PAR_MIN_LEN {
        spare
            .par_chunks_mut(EW_CHUNK)
            .enumerate()
            .for_each(|(i, c)| fill(c, i * EW_CHUNK));
    } else {
        fill(spare, 0);
    }
    // SAFETY: every caller's `fill` writes each element of the chunk it is given (they zip the
    // chunk with input slices of the same length), so all `n` elements are initialised. If
    // `fill` panics we never get here and the vector is dropped empty.
    unsafe { v.set_len(n) };
    v
}

/// Elementwise loop bodies, compiled three times on x86-64: for the baseline target, with AVX2 +
/// FMA and with AVX-512, picked at run time (the same IEEE operations in each, so the results
/// are bit-identical whichever runs: Rust never contracts a multiply and an add into an FMA,
/// and the explicit `mul_add` and `floor` of [`crate::vmath`] are exact operations on every
/// target, one instruction in the wide variants and libm calls in the baseline one). The
/// closures are inlined into each, so that their arithmetic (and
/// the polynomials of [`crate::vmath`]) vectorises at the wider width where available.
macro_rules! multiversion_dispatch {
    ($name:ident, $body:ident, $out:ty, ($($a:ident: $ta:ty),*), $f:ident: [$($tf:tt)+]) => {
        fn $name<T: Real, F: $($tf)+>(o: $out, $($a: $ta,)* $f: &F) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
                unsafe fn wide512<T: Real, F: $($tf)+>(o: $out, $($a: $ta,)* $f: &F) {
                    $body(o, $($a,)* $f)
                }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide<T: Real, F: $($tf)+>(o: $out, $($a: $ta,)* $f: &F) {
                    $body(o, $($a,)* $f)
                }
                if std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512vl")
                    && std::arch::is_x86_feature_detected!("avx512dq")
                    && std::arch::is_x86_feature_detected!("avx512bw")
                {
                    // SAFETY: the CPU has the features `wide512` is compiled for (AVX-512 implies
                    // AVX2 and FMA).
                    return unsafe { wide512(o, $($a,)* $f) };
                }
                if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU has the features `wide` is compiled for.
                    return unsafe { wide(o, $($a,)* $f) };
                }
            }
            $body(o, $($a,)* $f)
        }
    };
}

/// Writing loop bodies, `o[i] = f(a[i], ...)`, multiversioned by [`multiversion_dispatch!`].
macro_rules! multiversion {
    ($name:ident, $body:ident, ($($a:ident: $ta:ty),*), $f:ident: [$($tf:tt)+]) => {
        #[inline(always)]
        fn $body<T: Real, F: $($tf)+>(o: &mut [MaybeUninit<T>], $($a: $ta,)* $f: &F) {
            let n = o.len();
            $(let $a = &$a[..n];)*
            for (i, o) in o.iter_mut().enumerate() {
                o.write($f($($a[i]),*));
            }
        }
        multiversion_dispatch!($name, $body, &mut [MaybeUninit<T>], ($($a: $ta),*), $f: [$($tf)+]);
    };
}

multiversion!(fill1, fill1_body, (a: &[T]), f: [Fn(T) -> T]);
multiversion!(fill2, fill2_body, (a: &[T], b: &[T]), f: [Fn(T, T) -> T]);
multiversion!(fill3, fill3_body, (a: &[T], b: &[T], c: &[T]), f: [Fn(T, T, T) -> T]);

/// In-place elementwise loop bodies, `o[i] = f(o[i], a[i], ...)`, multiversioned as
/// [`multiversion!`] (the same IEEE operations in each variant).
macro_rules! multiversion_inplace {
    ($name:ident, $body:ident, ($($a:ident: $ta:ty),*), $f:ident: [$($tf:tt)+]) => {
        #[inline(always)]
        #[allow(unused_variables)] // `n` and `i` in the one-argument variant
        fn $body<T: Real, F: $($tf)+>(o: &mut [T], $($a: $ta,)* $f: &F) {
            let n = o.len();
            $(let $a = &$a[..n];)*
            for (i, o) in o.iter_mut().enumerate() {
                *o = $f(*o, $($a[i]),*);
            }
        }
        multiversion_dispatch!($name, $body, &mut [T], ($($a: $ta),*), $f: [$($tf)+]);
    };
}

multiversion_inplace!(upd1, upd1_body, (), f: [Fn(T) -> T]);
multiversion_inplace!(upd2, upd2_body, (a: &[T]), f: [Fn(T, T) -> T]);
multiversion_inplace!(upd3, upd3_body, (a: &[T], b: &[T]), f: [Fn(T, T, T) -> T]);

/// Runs `f(chunk, offset)` over fixed [`EW_CHUNK`] chunks of `o` (in parallel from
/// [`PAR_MIN_LEN`] elements).
fn par_update<T: Real>(o: &mut [T], f: impl Fn(&mut [T], usize) + Sync) {
    if o.len() >= PAR_MIN_LEN {
        o.par_chunks_mut(EW_CHUNK)
            .enumerate()
            .for_each(|(i, c)| f(c, i * EW_CHUNK));
    } else {
        f(o, 0);
    }
}

/// An output gradient handed to an elementwise backward: owned (the tape no longer needs it, so
/// the input's gradient is computed in its buffer when the layouts allow) or borrowed (a new
/// tensor is allocated). Either way each element gets the same value.
pub enum GradArg<'a, T: Real> {
    /// The gradient by value: updated in place.
    Owned(Tensor<T>),
    /// A borrowed gradient: results go to a new tensor.
    Borrowed(&'a Tensor<T>),
}

impl<T: Real> GradArg<'_, T> {
    /// The gradient, read-only.
    pub fn get(&self) -> &Tensor<T> {
        match self {
            GradArg::Owned(t) => t,
            GradArg::Borrowed(t) => t,
        }
    }

    /// A borrowed handle to the same gradient (for all but the last use).
    pub fn borrowed(&self) -> GradArg<'_, T> {
        GradArg::Borrowed(self.get())
    }

    /// The gradient itself (moved when owned, copied when borrowed).
    pub fn into_owned(self) -> Tensor<T> {
        match self {
            GradArg::Owned(t) => t,
            GradArg::Borrowed(t) => t.clone(),
        }
    }

    /// The owned gradient when it is row-major and has `shape`, for an in-place update.
    fn inplace(self, shape: &[usize]) -> std::result::Result<Tensor<T>, Self> {
        match self {
            GradArg::Owned(t) if t.shape() == shape && t.is_standard_layout() => Ok(t),
            other => Err(other),
        }
    }

    /// `f(g)` for every element.
    pub fn map1<F>(self, f: F) -> Tensor<T>
    where
        F: Fn(T) -> T + Sync + Send,
    {
        let shape = self.get().raw_dim();
        match self.inplace(shape.slice()) {
            Ok(mut g) => {
                let s = g.as_slice_mut().expect("standard layout");
                par_update(s, |o, _| upd1(o, &f));
                g
            }
            Err(g) => map1(g.get(), f),
        }
    }

    /// `f(g, x)` for every element (`x` has the gradient's shape).
    pub fn map2<F>(self, x: &ArrayViewD<T>, f: F) -> Tensor<T>
    where
        F: Fn(T, T) -> T + Sync + Send,
    {
        match (x.as_slice(), self.inplace(x.shape())) {
            (Some(a), Ok(mut g)) => {
                let s = g.as_slice_mut().expect("standard layout");
                par_update(s, |o, at| upd2(o, &a[at..at + o.len()], &f));
                g
            }
            (_, Ok(g)) => map2(&g.view(), x, f),
            (_, Err(g)) => map2(&g.get().view(), x, f),
        }
    }

    /// [`map2`]'s fast variant: `fast(g, x)`, and `exact(g, x)` where `ok(x)` fails (the
    /// vectorised `f32` transcendentals, see [`map2_fast`]).
    pub fn map2_fast<F, P, E>(self, x: &ArrayViewD<T>, fast: F, ok: P, exact: E) -> Tensor<T>
    where
        F: Fn(T, T) -> T + Sync + Send,
        P: Fn(T) -> bool + Sync + Send,
        E: Fn(T, T) -> T + Sync + Send,
    {
        match (x.as_slice(), T::FAST_MATH, self.inplace(x.shape())) {
            (Some(a), true, Ok(mut g)) => {
                let s = g.as_slice_mut().expect("standard layout");
                par_update(s, |o, at| {
                    let a = &a[at..at + o.len()];
                    // One pass: the fast kernel where `ok`, the gradient kept elsewhere; then
                    // (the chunk now in cache) `exact` on the gradient kept, if any.
                    upd2(o, a, &|g, x| if ok(x) { fast(g, x) } else { g });
                    if !a.iter().fold(true, |acc, &v| acc & ok(v)) {
                        for (o, &v) in o.iter_mut().zip(a) {
                            if !ok(v) {
                                *o = exact(*o, v);
                            }
                        }
                    }
                });
                g
            }
            (_, _, Ok(g)) => map2_fast(&g.view(), x, fast, |_, v| ok(v), exact),
            (_, _, Err(g)) => map2_fast(&g.get().view(), x, fast, |_, v| ok(v), exact),
        }
    }

    /// `f(g, x, y)` for every element (`x` and `y` have the gradient's shape).
    pub fn map3<F>(self, x: &ArrayViewD<T>, y: &ArrayViewD<T>, f: F) -> Tensor<T>
    where
        F: Fn(T, T, T) -> T + Sync + Send,
    {
        let same = x.shape() == y.shape();
        match (x.as_slice(), y.as_slice(), same, self.inplace(x.shape())) {
            (Some(a), Some(b), true, Ok(mut g)) => {
                let s = g.as_slice_mut().expect("standard layout");
                par_update(s, |o, at| {
                    let r = at..at + o.len();
                    upd3(o, &a[r.clone()], &b[r], &f)
                });
                g
            }
            (_, _, _, Ok(g)) => map3(&g.view(), x, y, f),
            (_, _, _, Err(g)) => map3(&g.get().view(), x, y, f),
        }
    }
}

/// A tensor of `shape` filled with `v` (in parallel for large tensors).
pub fn full<T: Real>(shape: &[usize], v: T) -> Tensor<T> {
    let n = shape.iter().product();
    let data = build(n, |o, _| {
        for o in o {
            o.write(v);
        }
    });
    from_parts(shape, data)
}

/// `acc += g` elementwise (same shape), in place and in parallel for large tensors.
pub fn add_assign<T: Real, S: Data<Elem = T>>(acc: &mut Tensor<T>, g: &ArrayBase<S, IxDyn>) {
    if acc.shape() == g.shape() {
        if let (Some(a), Some(b)) = (acc.as_slice_mut(), g.as_slice()) {
            par_update(a, |o, at| upd2(o, &b[at..at + o.len()], &|x, y| x + y));
            return;
        }
    }
    *acc += g;
}

/// Row-major slice of a view, if it has one.
fn std_slice<'a, T: Real>(x: &'a ArrayViewD<'_, T>) -> Option<&'a [T]> {
    x.as_slice()
}

fn from_parts<T: Real>(shape: &[usize], v: Vec<T>) -> Tensor<T> {
    ArrayD::from_shape_vec(IxDyn(shape), v).expect("length matches the shape")
}

/// `f` applied to every element (parallel for large tensors).
pub fn map1<T: Real, S: Data<Elem = T>, F>(x: &ArrayBase<S, IxDyn>, f: F) -> Tensor<T>
where
    F: Fn(T) -> T + Sync + Send,
{
    if let Some(a) = x.as_slice() {
        let v = build(a.len(), |o, at| fill1(o, &a[at..at + o.len()], &f));
        return from_parts(x.shape(), v);
    }
    if x.len() >= PAR_MIN_LEN {
        Zip::from(x).par_map_collect(|&a| f(a))
    } else {
        x.mapv(f)
    }
}

/// `fast` applied to every element, and `exact` where `ok` fails (the vectorised `f32`
/// transcendentals and their range: see the `vmath` module).
pub fn map1_fast<T: Real, S: Data<Elem = T>, F, P, E>(
    x: &ArrayBase<S, IxDyn>,
    fast: F,
    ok: P,
    exact: E,
) -> Tensor<T>
where
    F: Fn(T) -> T + Sync + Send,
    P: Fn(T) -> bool + Sync + Send,
    E: Fn(T) -> T + Sync + Send,
{
    match x.as_slice() {
        Some(a) if T::FAST_MATH => {
            let v = build(a.len(), |o, at| {
                let a = &a[at..at + o.len()];
                fill1(o, a, &fast);
                if !a.iter().fold(true, |acc, &v| acc & ok(v)) {
                    for (o, &v) in o.iter_mut().zip(a) {
                        if !ok(v) {
                            o.write(exact(v));
                        }
                    }
                }
            });
            from_parts(x.shape(), v)
        }
        _ => map1(x, exact),
    }
}

/// `f` over two tensors of the same shape.
pub fn map2<T: Real, F>(x: &ArrayViewD<T>, y: &ArrayViewD<T>, f: F) -> Tensor<T>
where
    F: Fn(T, T) -> T + Sync + Send,
{
    if let (Some(a), Some(b)) = (std_slice(x), std_slice(y)) {
        if x.shape() == y.shape() {
            let v = build(a.len(), |o, at| {
                let r = at..at + o.len();
                fill2(o, &a[r.clone()], &b[r], &f)
            });
            return from_parts(x.shape(), v);
        }
    }
    if x.len() >= PAR_MIN_LEN {
        Zip::from(x).and(y).par_map_collect(|&a, &b| f(a, b))
    } else {
        Zip::from(x).and(y).map_collect(|&a, &b| f(a, b))
    }
}

/// [`map2`] with a fast function, and `exact` where `ok` fails.
pub fn map2_fast<T: Real, F, P, E>(
    x: &ArrayViewD<T>,
    y: &ArrayViewD<T>,
    fast: F,
    ok: P,
    exact: E,
) -> Tensor<T>
where
    F: Fn(T, T) -> T + Sync + Send,
    P: Fn(T, T) -> bool + Sync + Send,
    E: Fn(T, T) -> T + Sync + Send,
{
    if let (Some(a), Some(b), true) = (std_slice(x), std_slice(y), T::FAST_MATH) {
        if x.shape() == y.shape() {
            let v = build(a.len(), |o, at| {
                let r = at..at + o.len();
                let (a, b) = (&a[r.clone()], &b[r]);
                fill2(o, a, b, &fast);
                if !a.iter().zip(b).fold(true, |acc, (&u, &v)| acc & ok(u, v)) {
                    for ((o, &u), &v) in o.iter_mut().zip(a).zip(b) {
                        if !ok(u, v) {
                            o.write(exact(u, v));
                        }
                    }
                }
            });
            return from_parts(x.shape(), v);
        }
    }
    map2(x, y, exact)
}

/// `f` over three tensors of the same shape.
pub fn map3<T: Real, F>(x: &ArrayViewD<T>, y: &ArrayViewD<T>, z: &ArrayViewD<T>, f: F) -> Tensor<T>
where
    F: Fn(T, T, T) -> T + Sync + Send,
{
    if let (Some(a), Some(b), Some(c)) = (std_slice(x), std_slice(y), std_slice(z)) {
        if x.shape() == y.shape() && x.shape() == z.shape() {
            let v = build(a.len(), |o, at| {
                let r = at..at + o.len();
                fill3(o, &a[r.clone()], &b[r.clone()], &c[r], &f)
            });
            return from_parts(x.shape(), v);
        }
    }
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

/// Checks that every element is finite (contiguous data: branch-free per chunk, so it
/// vectorises; in parallel for large tensors).
pub fn all_finite<T: Real, S: Data<Elem = T>>(x: &ArrayBase<S, IxDyn>) -> bool {
    match x.as_slice() {
        Some(s) if s.len() >= PAR_MIN_LEN => s.par_chunks(REDUCE_CHUNK).all(all_finite_slice),
        Some(s) => all_finite_slice(s),
        None => x.iter().all(|v| v.is_finite()),
    }
}

/// Every element of `s` finite, without an early exit (so the loop vectorises).
pub fn all_finite_slice<T: Real>(s: &[T]) -> bool {
    s.iter().fold(true, |ok, v| ok & v.is_finite())
}

/// Casts a tensor to another scalar type.
pub fn cast<T: Real, U: Real, S: Data<Elem = T>>(x: &ArrayBase<S, IxDyn>) -> Tensor<U> {
    x.mapv(|v| U::from_f64c(v.to_f64c()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broadcasting_follows_numpy() {
        assert_eq!(
            broadcast_shapes("t", &[3, 1, 5], &[4, 1]).unwrap(),
            vec![3, 4, 5]
        );
        assert_eq!(broadcast_shapes("t", &[], &[2, 2]).unwrap(), vec![2, 2]);
        let e = broadcast_shapes("add", &[3, 2], &[4, 2]).unwrap_err();
        let msg = e.to_string();
        assert!(
            msg.contains("add") && msg.contains("[3, 2]") && msg.contains("[4, 2]"),
            "{msg}"
        );
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

    #[test]
    fn every_kernel_variant_gives_the_same_bits() {
        // The dispatched kernels (AVX-512 or AVX2 + FMA where the CPU has them) against the
        // baseline-compiled loop body, for the vectorised transcendentals.
        let a: Vec<f32> = (0..40_000)
            .map(|i| ((i as f32) * 0.731).sin() * 30.0)
            .collect();
        type Fill<'a> = &'a dyn Fn(&mut [MaybeUninit<f32>], &[f32]);
        let run = |f: Fill<'_>| -> Vec<u32> {
            let mut o = vec![MaybeUninit::<f32>::uninit(); a.len()];
            f(&mut o, &a);
            // SAFETY: both fill functions write every element.
            o.iter()
                .map(|v| unsafe { v.assume_init() }.to_bits())
                .collect()
        };
        let kernels: [fn(f32) -> f32; 4] = [
            crate::vmath::sin,
            crate::vmath::cos,
            crate::vmath::exp,
            crate::vmath::tanh,
        ];
        for k in kernels {
            let fast = run(&|o, a| fill1(o, a, &k));
            let base = run(&|o, a| fill1_body(o, a, &k));
            assert_eq!(fast, base);
        }
    }
}
