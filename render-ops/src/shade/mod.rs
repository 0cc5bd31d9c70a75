//! Shading: geometry normals, lights and materials, spherical-harmonics lighting, programmable
//! fragment shaders and the auxiliary outputs of inverse rendering.
//!
//! Every built-in model exists twice:
//! - **composed** from tape ops (`*_composed`): the reference implementation, and the template
//!   for users' own shaders (copy it and change the formula);
//! - **fused** into one [`autodiff::Op`] with a hand-written backward: the fast path. It runs
//!   in parallel over fixed chunks of [`CHUNK`] fragments with rayon; gradients of parameters
//!   shared by all fragments (light colours and directions, material constants, SH
//!   coefficients) are summed per chunk and the partial sums added in chunk order, so results
//!   are bit-identical for any number of threads.
//!
//! The two forms compute the same formulas (tests hold them to 1e-10 in `f64`, values and
//! gradients).
//!
//! Per-fragment inputs are tensors `[N, 3]` (positions, normals, albedo); a reflectance given
//! as `[3]` (or `[1, 3]`) is shared by all fragments. Normals and directions are normalised
//! inside every model with `x / max(|x|, eps)` ([`SAFE_EPS`]): a zero-length vector becomes the
//! zero vector (no NaN), and its gradient is `g / eps` (finite), exactly as
//! [`autodiff::Var::normalize`].
//!
//! Modules:
//! - [`normals`]: differentiable face normals and area-weighted vertex normals;
//! - [`lights`]: ambient, directional, point and SH lights, materials;
//! - [`phong`]: Lambert, Phong (1975) and Blinn-Phong (1977) reflection;
//! - [`sh`]: order-2 real spherical-harmonics irradiance (Ramamoorthi and Hanrahan 2001);
//! - [`shader`]: programmable shaders: [`FragmentInputs`] and [`run_shader`] / [`render_shader`];
//! - [`outputs`]: normal maps, depth and PNCC;
//! - [`stage`]: the shading stage of the scene pipeline (scene material and lights);
//! - [`suite`]: gradient-check cases of these ops and of [`crate::texture`] for
//!   `tapestry gradcheck`.

pub mod lights;
pub mod normals;
pub mod outputs;
pub mod phong;
pub mod sh;
pub mod shader;
pub mod stage;
pub mod suite;

pub use lights::{
    AmbientLight, DirectionalLight, Lights, Material, PointLight, Reflectance, ShLight,
};
pub use normals::{face_normals, face_normals_composed, vertex_normals, vertex_normals_composed};
pub use outputs::{depth_map, ncc, normal_map, normal_map_view, pncc};
pub use phong::{shade, shade_composed, Surface};
pub use sh::{
    sh_basis, sh_basis_composed, sh_shade, sh_shade_composed, SH_C0, SH_C1, SH_C2, SH_C3, SH_C4,
};
pub use shader::{
    fragment_inputs, render_shader, run_shader, uv_derivatives, FragmentInputs, MeshAttributes,
    ShaderOutput,
};

use autodiff::{AutodiffError, Real, Result as AdResult, Tensor, TensorView};
use rayon::prelude::*;

/// Length floor of every normalisation in the shading models and normals: `x / max(|x|, eps)`.
pub const SAFE_EPS: f64 = 1e-12;

/// Fragments per parallel task of the fused ops (fixed, so results do not depend on the
/// number of threads).
pub const CHUNK: usize = 1024;

pub(crate) type V3<T> = [T; 3];

#[inline(always)]
pub(crate) fn dot3<T: Real>(a: V3<T>, b: V3<T>) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline(always)]
pub(crate) fn add3<T: Real>(a: V3<T>, b: V3<T>) -> V3<T> {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline(always)]
pub(crate) fn sub3<T: Real>(a: V3<T>, b: V3<T>) -> V3<T> {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline(always)]
pub(crate) fn scale3<T: Real>(a: V3<T>, s: T) -> V3<T> {
    [a[0] * s, a[1] * s, a[2] * s]
}

#[inline(always)]
pub(crate) fn mul3<T: Real>(a: V3<T>, b: V3<T>) -> V3<T> {
    [a[0] * b[0], a[1] * b[1], a[2] * b[2]]
}

#[inline(always)]
pub(crate) fn cross3<T: Real>(a: V3<T>, b: V3<T>) -> V3<T> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline(always)]
pub(crate) fn acc3<T: Real>(acc: &mut V3<T>, a: V3<T>) {
    acc[0] += a[0];
    acc[1] += a[1];
    acc[2] += a[2];
}

/// `(x / max(|x|, eps), |x|)`, the same arithmetic as [`autodiff::Var::normalize`].
#[inline(always)]
pub(crate) fn normalize3<T: Real>(x: V3<T>, eps: T) -> (V3<T>, T) {
    let len = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
    let d = len.max(eps);
    ([x[0] / d, x[1] / d, x[2] / d], len)
}

/// Vector-Jacobian product of [`normalize3`]: `(g - y (y . g)) / |x|` above the floor,
/// `g / eps` below it.
#[inline(always)]
pub(crate) fn normalize3_vjp<T: Real>(len: T, y: V3<T>, g: V3<T>, eps: T) -> V3<T> {
    if len > eps {
        let yg = dot3(y, g);
        [
            (g[0] - y[0] * yg) / len,
            (g[1] - y[1] * yg) / len,
            (g[2] - y[2] * yg) / len,
        ]
    } else {
        [g[0] / eps, g[1] / eps, g[2] / eps]
    }
}

/// Rows of a `[N, 3]` tensor, or one `[3]` / `[1, 3]` row shared by all `N`.
#[derive(Clone, Copy)]
pub(crate) struct Rows<'a, T> {
    pub data: &'a [T],
    pub per_row: bool,
}

impl<T: Real> Rows<'_, T> {
    #[inline(always)]
    pub fn get(&self, i: usize) -> V3<T> {
        let o = if self.per_row { 3 * i } else { 0 };
        [self.data[o], self.data[o + 1], self.data[o + 2]]
    }
}

/// Checks that `t` is `[n, 3]` (`per_row`) or, when `shared_ok`, `[3]` / `[1, 3]`.
pub(crate) fn rows_of<'a, T: Real, S: ndarray::Data<Elem = T>>(
    op: &'static str,
    what: &str,
    t: &'a ndarray::ArrayBase<S, ndarray::IxDyn>,
    n: usize,
    shared_ok: bool,
) -> AdResult<Rows<'a, T>> {
    let s = t.shape();
    let data = t.as_slice().ok_or_else(|| AutodiffError::Op {
        op,
        detail: format!("{what} is not contiguous"),
    })?;
    if s == [n, 3] {
        return Ok(Rows {
            data,
            per_row: true,
        });
    }
    if shared_ok && (s == [3] || s == [1, 3]) {
        return Ok(Rows {
            data,
            per_row: false,
        });
    }
    Err(AutodiffError::shape(
        op,
        &[s],
        if shared_ok {
            format!("{what} must be [{n}, 3] or [3]")
        } else {
            format!("{what} must be [{n}, 3]")
        },
    ))
}

/// `[k, 3]` rows of a small tensor (lights); `[3]` counts as one row.
pub(crate) fn light_rows<T: Real, S: ndarray::Data<Elem = T>>(
    op: &'static str,
    what: &str,
    t: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> AdResult<Vec<V3<T>>> {
    let s = t.shape();
    let ok = (s.len() == 2 && s[1] == 3) || s == [3];
    if !ok {
        return Err(AutodiffError::shape(
            op,
            &[s],
            format!("{what} must be [L, 3]"),
        ));
    }
    Ok(t.iter()
        .copied()
        .collect::<Vec<T>>()
        .chunks(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect())
}

/// Runs `f(first_fragment, out, shared)` over fixed chunks of [`CHUNK`] fragments in parallel.
/// `out` holds `width` values per fragment of the chunk (zeros on entry), `shared` a zeroed
/// accumulator of `n_shared` values; the accumulators are summed in chunk order. Deterministic
/// for any number of threads.
pub(crate) fn chunked<T: Real, F>(n: usize, width: usize, n_shared: usize, f: F) -> (Vec<T>, Vec<T>)
where
    F: Fn(usize, &mut [T], &mut [T]) + Sync + Send,
{
    let mut out = vec![T::zero(); n * width];
    let partials: Vec<Vec<T>> = if width > 0 {
        out.par_chunks_mut(CHUNK * width)
            .enumerate()
            .map(|(c, o)| {
                let mut acc = vec![T::zero(); n_shared];
                f(c * CHUNK, o, &mut acc);
                acc
            })
            .collect()
    } else {
        (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .map(|c| {
                let mut acc = vec![T::zero(); n_shared];
                f(c * CHUNK, &mut [], &mut acc);
                acc
            })
            .collect()
    };
    let mut shared = vec![T::zero(); n_shared];
    for p in partials {
        for (s, v) in shared.iter_mut().zip(p) {
            *s += v;
        }
    }
    (out, shared)
}

/// The tensor `[n, 3]` (per row) or `[3]`-like (shared) gradient for an input of `shape`.
/// The op inputs in standard (row-major contiguous) layout: borrowed when they already are
/// (the usual case), copied only otherwise, so that a fused op does not copy its inputs per call.
pub(crate) fn standard_inputs<'a, T: Real>(
    inputs: &'a [TensorView<'_, T>],
) -> Vec<ndarray::CowArray<'a, T, ndarray::IxDyn>> {
    inputs.iter().map(|t| t.as_standard_layout()).collect()
}

pub(crate) fn grad_tensor<T: Real>(shape: &[usize], data: Vec<T>) -> Tensor<T> {
    Tensor::from_shape_vec(ndarray::IxDyn(shape), data).expect("gradient has the input's size")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normalize_helpers_are_safe_at_zero() {
        let (y, len) = normalize3([0.0f64; 3], 1e-12);
        assert_eq!(y, [0.0; 3]);
        assert_eq!(len, 0.0);
        let g = normalize3_vjp(len, y, [1.0, 2.0, 3.0], 1e-12);
        assert!(g.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn chunked_is_independent_of_thread_count() {
        let n = 5000;
        let run = || {
            chunked::<f32, _>(n, 1, 1, |s, o, acc| {
                for (k, v) in o.iter_mut().enumerate() {
                    let x = ((s + k) as f32 * 0.37).sin();
                    *v = x;
                    acc[0] += x;
                }
            })
        };
        let results: Vec<_> = [1, 3]
            .iter()
            .map(|&t| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(t)
                    .build()
                    .unwrap()
                    .install(run)
            })
            .collect();
        assert_eq!(results[0].1[0].to_bits(), results[1].1[0].to_bits());
        assert_eq!(results[0].0, results[1].0);
    }
}
