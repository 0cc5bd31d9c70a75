//! Shading: geometry normals, lights and materials, spherical-harmonics lighting, programmable
//! fragment shaders and the auxiliary outputs of inverse rendering.
//!
//! Every reflection model is written once, composed from tape ops (`*_composed`: the
//! reference, and the template for users' own shaders). The entry points [`shade`] and
//! [`sh_shade`] check the inputs' shapes and run that same code inside
//! [`autodiff::Tape::fused`], so a model is one fused op with the chain rule derived from its
//! graph: evaluated chunk by chunk in cache, in parallel, bit-identical for any number of
//! threads (see `autodiff::fused`), and faster than the hand-fused ops with hand-written
//! backwards it replaced (docs/performance.md). A user's shader gets the same speed by running
//! inside `Tape::fused`, as [`render_shader`] does.
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

use autodiff::{AutodiffError, Real, Result as AdResult, Var};

/// Length floor of every normalisation in the shading models and normals: `x / max(|x|, eps)`.
pub const SAFE_EPS: f64 = 1e-12;

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

/// Checks that `v` is `[n, 3]` or, when `shared_ok`, `[3]` / `[1, 3]` (one row shared by all
/// `n` fragments).
pub(crate) fn check_rows<T: Real>(
    op: &'static str,
    what: &str,
    v: Var<'_, T>,
    n: usize,
    shared_ok: bool,
) -> AdResult<()> {
    let s = v.shape();
    if s == [n, 3] || (shared_ok && (s == [3] || s == [1, 3])) {
        return Ok(());
    }
    Err(AutodiffError::shape(
        op,
        &[&s],
        if shared_ok {
            format!("{what} must be [{n}, 3] or [3]")
        } else {
            format!("{what} must be [{n}, 3]")
        },
    ))
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
}
