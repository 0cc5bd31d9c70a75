//! Shaders for the auxiliary outputs of inverse rendering: normal maps, depth and PNCC.
//!
//! Each is a differentiable function of per-fragment variables, usable directly as (or
//! inside) a shader of [`super::render_shader`]:
//!
//! ```ignore
//! let nrm = render_shader(&r, &mesh, eye, |f| normal_map(f.normal), &[0.5, 0.5, 0.5])?;
//! let dep = render_shader(&r, &mesh, eye, |f| depth_map(f.view_depth, 0.1, 10.0), &[1.0])?;
//! let mesh = mesh.with_attribute("ncc", tape.constant(ncc(&mean_shape)));
//! let pncc = render_shader(&r, &mesh, eye, |f| f.attribute("ncc").unwrap(), &[0.0; 3])?;
//! ```

use autodiff::{Real, Tensor, Var};
use ndarray::{Array2, ArrayD, IxDyn};

use crate::error::RenderError;
use crate::interpolate::interpolate;
use crate::rasterize::Rasterized;

use super::SAFE_EPS;

/// Normal map colours `[N, 3]`: `0.5 n + 0.5` of the normalised normals `[N, 3]` (world
/// space: +x red, +y green, +z blue).
pub fn normal_map<'t, T: Real>(normal: Var<'t, T>) -> Var<'t, T> {
    normal.normalize(T::from_f64c(SAFE_EPS)) * T::from_f64c(0.5) + T::from_f64c(0.5)
}

/// Normal map in view space: the normals rotated by the upper-left 3 x 3 of a row-major
/// world-to-view matrix (e.g. [`crate::camera::Camera::view_rows`]), then `0.5 n + 0.5`
/// (a surface facing the camera is (0.5, 0.5, 1)).
pub fn normal_map_view<'t, T: Real>(normal: Var<'t, T>, view: &[[f64; 4]; 4]) -> Var<'t, T> {
    // n_view = R n for row vectors: n @ R^T.
    let rt = Array2::from_shape_fn((3, 3), |(i, j)| T::from_f64c(view[j][i])).into_dyn();
    let n = normal
        .normalize(T::from_f64c(SAFE_EPS))
        .matmul(normal.tape().constant(rt));
    normal_map(n)
}

/// Depth output `[N, 1]`: `(d - near) / (far - near)` of view depths `d` `[N]` (or `[N, 1]`),
/// linear in view depth as docs/CONVENTIONS.md's `z01`: 0 at the near plane, 1 at the far plane.
pub fn depth_map<'t, T: Real>(view_depth: Var<'t, T>, near: f64, far: f64) -> Var<'t, T> {
    let n = view_depth.len();
    let s = 1.0 / (far - near);
    view_depth.reshape(&[n, 1]) * T::from_f64c(s) - T::from_f64c(near * s)
}

/// Normalised coordinate code of a mean shape (Zhu et al., "Face alignment across large
/// poses: a 3D solution", CVPR 2016): every coordinate mapped to [0, 1] by the shape's
/// bounding box, `(p - min) / (max - min)` per axis; `[V, 3]`, constant data (an axis of zero
/// extent maps to 0).
pub fn ncc<T: Real>(mean_shape: &[[T; 3]]) -> Tensor<T> {
    let mut lo = [T::infinity(); 3];
    let mut hi = [T::neg_infinity(); 3];
    for p in mean_shape {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let data = mean_shape
        .iter()
        .flat_map(|p| {
            (0..3).map(move |k| {
                let ext = hi[k] - lo[k];
                if ext > T::zero() {
                    (p[k] - lo[k]) / ext
                } else {
                    T::zero()
                }
            })
        })
        .collect();
    ArrayD::from_shape_vec(IxDyn(&[mean_shape.len(), 3]), data).expect("v x 3")
}

/// PNCC (projected NCC) fragment colours `[N, 3]`: the code `[V, 3]` of [`ncc`] (as a tape
/// variable) interpolated at the fragments of `r`. Gradients reach the positions through the
/// barycentrics.
pub fn pncc<'t, T: Real>(
    code: Var<'t, T>,
    r: &Rasterized<'t, T>,
) -> Result<Var<'t, T>, RenderError> {
    interpolate(code, r)
}
