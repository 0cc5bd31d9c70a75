//! Order-2 spherical-harmonics lighting (R. Ramamoorthi and P. Hanrahan, "An efficient
//! representation for irradiance environment maps", SIGGRAPH 2001).
//!
//! The basis, its order and its constants are exactly those of docs/CONVENTIONS.md: for the unit
//! world-space normal `(x, y, z)`, in the order (l, m) = (0,0), (1,-1), (1,0), (1,1), (2,-2),
//! (2,-1), (2,0), (2,1), (2,2),
//!
//! ```text
//! Y = [0.282095, 0.488603 y, 0.488603 z, 0.488603 x, 1.092548 xy, 1.092548 yz,
//!      0.315392 (3z^2 - 1), 1.092548 xz, 0.546274 (x^2 - y^2)]
//! colour = albedo ⊙ sum_k sh_k Y_k(n)          (sh: [9, 3], row k = RGB of Y_k)
//! ```
//!
//! The coefficients already hold any irradiance convolution factors (the `A_l` of Ramamoorthi
//! and Hanrahan); the shaded colour is linear in them. Normals are normalised first with the
//! safe `x / max(|x|, eps)`: a zero normal gives `Y = (0.282095, 0, ..., 0, -0.315392, 0, 0)`.

use autodiff::{AutodiffError, Real, Result as AdResult, Tensor, Var};
use ndarray::{ArrayD, IxDyn};

use super::{check_rows, normalize3, SAFE_EPS};

/// `Y_00` constant.
pub const SH_C0: f64 = 0.282095;
/// Constant of the three `l = 1` functions.
pub const SH_C1: f64 = 0.488603;
/// Constant of `xy`, `yz`, `xz`.
pub const SH_C2: f64 = 1.092548;
/// Constant of `3z^2 - 1`.
pub const SH_C3: f64 = 0.315392;
/// Constant of `x^2 - y^2`.
pub const SH_C4: f64 = 0.546274;

/// The 9 basis values at a unit normal.
#[inline(always)]
pub fn sh_eval<T: Real>(n: [T; 3]) -> [T; 9] {
    let (x, y, z) = (n[0], n[1], n[2]);
    let c = |v: f64| T::from_f64c(v);
    [
        c(SH_C0),
        c(SH_C1) * y,
        c(SH_C1) * z,
        c(SH_C1) * x,
        c(SH_C2) * x * y,
        c(SH_C2) * y * z,
        c(SH_C3) * (c(3.0) * z * z - T::one()),
        c(SH_C2) * x * z,
        c(SH_C4) * (x * x - y * y),
    ]
}

/// Vector-Jacobian product of [`sh_eval`]: `dL/dn` from `dL/dY`.
#[inline(always)]
pub(crate) fn sh_eval_vjp<T: Real>(n: [T; 3], g: [T; 9]) -> [T; 3] {
    let (x, y, z) = (n[0], n[1], n[2]);
    let c = |v: f64| T::from_f64c(v);
    let (c1, c2, c3, c4) = (c(SH_C1), c(SH_C2), c(SH_C3), c(SH_C4));
    let two = c(2.0);
    [
        c1 * g[3] + c2 * y * g[4] + c2 * z * g[7] + two * c4 * x * g[8],
        c1 * g[1] + c2 * x * g[4] + c2 * z * g[5] - two * c4 * y * g[8],
        c1 * g[2] + c2 * y * g[5] + c(6.0) * c3 * z * g[6] + c2 * x * g[7],
    ]
}

/// SH-lit colours `[N, 3]` of normals `[N, 3]` (any length), albedo `[N, 3]` or `[3]` and
/// coefficients `[9, 3]` (see the module docs for the model).
///
/// [`sh_shade_composed`] run inside [`autodiff::Tape::fused`]: the per-fragment work is one
/// fused op, evaluated chunk by chunk in cache with the chain rule derived from the graph.
/// Inputs of the wrong shape poison the result with an error naming them.
pub fn sh_shade<'t, T: Real>(
    normal: Var<'t, T>,
    albedo: Var<'t, T>,
    coeffs: Var<'t, T>,
) -> Var<'t, T> {
    const OP: &str = "sh_shade";
    let t = normal.tape();
    let check = || -> AdResult<()> {
        let ns = normal.shape();
        if ns.len() != 2 || ns[1] != 3 {
            return Err(AutodiffError::shape(OP, &[&ns], "normals must be [N, 3]"));
        }
        check_rows(OP, "albedo", albedo, ns[0], true)?;
        let cs = coeffs.shape();
        if cs != [9, 3] {
            return Err(AutodiffError::shape(
                OP,
                &[&cs],
                "SH coefficients must be [9, 3]",
            ));
        }
        Ok(())
    };
    match check() {
        Ok(()) => t.fused(|| sh_shade_composed(normal, albedo, coeffs)),
        Err(e) => t.poisoned(e),
    }
}

/// The 9 basis functions at the (normalised) normals `[N, 3]`: `[N, 9]` (plain values).
pub fn sh_basis<T: Real>(normals: &Tensor<T>) -> Tensor<T> {
    let n = normals.shape().first().copied().unwrap_or(0);
    let eps = T::from_f64c(SAFE_EPS);
    let data: Vec<T> = normals
        .outer_iter()
        .flat_map(|r| sh_eval(normalize3([r[0], r[1], r[2]], eps).0))
        .collect();
    ArrayD::from_shape_vec(IxDyn(&[n, 9]), data).expect("n x 9")
}

/// The 9 basis values `[N, 1]` each at normals `[N, 3]` (normalised inside), composed from
/// tape ops (differentiable); `Y_00`, a constant, is `None`.
fn sh_basis_terms<'t, T: Real>(normal: Var<'t, T>) -> [Option<Var<'t, T>>; 9] {
    let n = normal.normalize(T::from_f64c(SAFE_EPS));
    let (x, y, z) = (n.slice(1, 0, 1), n.slice(1, 1, 2), n.slice(1, 2, 3));
    let c = |v: f64| T::from_f64c(v);
    [
        None,
        Some(y * c(SH_C1)),
        Some(z * c(SH_C1)),
        Some(x * c(SH_C1)),
        Some(x * y * c(SH_C2)),
        Some(y * z * c(SH_C2)),
        Some((z * z * c(3.0) - c(1.0)) * c(SH_C3)),
        Some(x * z * c(SH_C2)),
        Some((x * x - y * y) * c(SH_C4)),
    ]
}

/// The basis `[N, 9]` at normals `[N, 3]`, composed from tape ops (differentiable).
pub fn sh_basis_composed<'t, T: Real>(normal: Var<'t, T>) -> Var<'t, T> {
    let t = normal.tape();
    let nrows = normal.shape().first().copied().unwrap_or(0);
    let y0 = t.constant(ArrayD::from_elem(IxDyn(&[nrows, 1]), T::from_f64c(SH_C0)));
    let terms: Vec<Var<'t, T>> = sh_basis_terms(normal)
        .into_iter()
        .map(|y| y.unwrap_or(y0))
        .collect();
    t.concat(&terms, 1)
}

/// [`sh_shade`] composed from tape ops: `albedo * sum_k Y_k(n) sh_k`, the product with the
/// coefficients written as a sum of broadcast products (no `[N, 9]` basis, no matrix
/// product), so that inside [`autodiff::Tape::fused`] the whole model is one fused op.
pub fn sh_shade_composed<'t, T: Real>(
    normal: Var<'t, T>,
    albedo: Var<'t, T>,
    coeffs: Var<'t, T>,
) -> Var<'t, T> {
    let row = |k: usize| coeffs.slice(0, k, k + 1).reshape(&[3]);
    let mut e = row(0) * T::from_f64c(SH_C0);
    for (k, y) in sh_basis_terms(normal).into_iter().enumerate() {
        if let Some(y) = y {
            e = e + y * row(k);
        }
    }
    albedo * e
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_matches_conventions_at_axes() {
        let b = sh_eval([0.0f64, 0.0, 1.0]);
        assert_eq!(
            b,
            [
                0.282095,
                0.0,
                0.488603,
                0.0,
                0.0,
                0.0,
                0.315392 * 2.0,
                0.0,
                0.0
            ]
        );
        let s = 0.5f64.sqrt();
        let b = sh_eval([s, s, 0.0]);
        assert!((b[4] - 1.092548 * 0.5).abs() < 1e-15);
        assert!((b[3] - 0.488603 * s).abs() < 1e-15 && (b[1] - 0.488603 * s).abs() < 1e-15);
        assert!(b[8].abs() < 1e-15);
        let b = sh_eval([1.0f64, 0.0, 0.0]);
        assert_eq!(b[8], 0.546274);
        assert_eq!(b[6], -0.315392);
    }
}
