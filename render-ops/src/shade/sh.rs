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

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};

use super::{chunked, grad_tensor, normalize3, normalize3_vjp, rows_of, Rows, SAFE_EPS, V3};

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

struct ShOp<T: Real> {
    eps: T,
}

fn read<'a, T: Real>(
    inputs: &'a [ndarray::CowArray<'_, T, ndarray::IxDyn>],
) -> AdResult<(usize, Rows<'a, T>, Rows<'a, T>, &'a [T])> {
    const OP: &str = "sh_shade";
    if inputs[0].ndim() != 2 {
        return Err(AutodiffError::shape(
            OP,
            &[inputs[0].shape()],
            "normals must be [N, 3]",
        ));
    }
    let n = inputs[0].shape()[0];
    let nrm = rows_of(OP, "normals", &inputs[0], n, false)?;
    let alb = rows_of(OP, "albedo", &inputs[1], n, true)?;
    if inputs[2].shape() != [9, 3] {
        return Err(AutodiffError::shape(
            OP,
            &[inputs[2].shape()],
            "SH coefficients must be [9, 3]",
        ));
    }
    Ok((n, nrm, alb, inputs[2].as_slice().expect("std")))
}

fn irradiance<T: Real>(y: &[T; 9], sh: &[T]) -> V3<T> {
    let mut e = [T::zero(); 3];
    for k in 0..9 {
        for c in 0..3 {
            e[c] += sh[3 * k + c] * y[k];
        }
    }
    e
}

impl<T: Real> Op<T> for ShOp<T> {
    fn name(&self) -> &'static str {
        "sh_shade"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let std = super::standard_inputs(inputs);
        let (n, nrm, alb, sh) = read(&std)?;
        let (out, _) = chunked::<T, _>(n, 3, 0, |start, o, _| {
            for (r, row) in o.chunks_mut(3).enumerate() {
                let i = start + r;
                let y = sh_eval(normalize3(nrm.get(i), self.eps).0);
                let e = irradiance(&y, sh);
                let a = alb.get(i);
                row.copy_from_slice(&[a[0] * e[0], a[1] * e[1], a[2] * e[2]]);
            }
        });
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[n, 3]), out).expect("n x 3")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let std = super::standard_inputs(ctx.inputs);
        let (n, nrm, alb, sh) = read(&std)?;
        let g = ctx.grad_outputs[0].as_standard_layout();
        let g = Rows {
            data: g.as_slice().expect("std"),
            per_row: true,
        };
        // Row: [gn (3), galbedo (3, when per row)]; shared: [gsh (27), galbedo (3)].
        let width = if alb.per_row { 6 } else { 3 };
        let (rows, shared) = chunked::<T, _>(n, width, 30, |start, o, acc| {
            for (r, row) in o.chunks_mut(width).enumerate() {
                let i = start + r;
                let gi = g.get(i);
                let (nh, len) = normalize3(nrm.get(i), self.eps);
                let y = sh_eval(nh);
                let e = irradiance(&y, sh);
                let a = alb.get(i);
                let ge = [a[0] * gi[0], a[1] * gi[1], a[2] * gi[2]];
                let mut gy = [T::zero(); 9];
                for k in 0..9 {
                    for c in 0..3 {
                        acc[3 * k + c] += y[k] * ge[c];
                        gy[k] += sh[3 * k + c] * ge[c];
                    }
                }
                let gn = normalize3_vjp(len, nh, sh_eval_vjp(nh, gy), self.eps);
                row[0..3].copy_from_slice(&gn);
                let ga = [e[0] * gi[0], e[1] * gi[1], e[2] * gi[2]];
                if alb.per_row {
                    row[3..6].copy_from_slice(&ga);
                } else {
                    for c in 0..3 {
                        acc[27 + c] += ga[c];
                    }
                }
            }
        });
        let column = |off: usize| -> Vec<T> {
            rows.chunks(width)
                .flat_map(|r| r[off..off + 3].to_vec())
                .collect()
        };
        Ok(vec![
            ctx.needs_grad[0].then(|| grad_tensor(&[n, 3], column(0))),
            ctx.needs_grad[1].then(|| {
                if alb.per_row {
                    grad_tensor(&[n, 3], column(3))
                } else {
                    grad_tensor(ctx.inputs[1].shape(), shared[27..30].to_vec())
                }
            }),
            ctx.needs_grad[2].then(|| grad_tensor(&[9, 3], shared[..27].to_vec())),
        ])
    }
}

/// SH-lit colours `[N, 3]` of normals `[N, 3]` (any length), albedo `[N, 3]` or `[3]` and
/// coefficients `[9, 3]` (fused op; see the module docs for the model).
pub fn sh_shade<'t, T: Real>(
    normal: Var<'t, T>,
    albedo: Var<'t, T>,
    coeffs: Var<'t, T>,
) -> Var<'t, T> {
    let op = ShOp {
        eps: T::from_f64c(SAFE_EPS),
    };
    normal.tape().apply(op, &[normal, albedo, coeffs])
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
