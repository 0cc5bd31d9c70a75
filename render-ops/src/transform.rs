//! Differentiable rigid transforms and projections as tape functions: rotations from
//! axis-angle (Rodrigues), unit quaternions and Euler angles; points moved by `R p + t`;
//! points taken to clip space by a projection matrix (constant, or a perspective camera with a
//! learnable focal length).
//!
//! The axis-angle map is a fused op with a hand-written backward that uses series expansions
//! near zero, so the identity rotation (where face fitting starts) has exact, finite
//! gradients; composing it from `sqrt`, `sin`, `/` would give NaN at zero.

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result, Tape, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

/// Coefficients of Rodrigues' formula `R = I + a(θ) K + b(θ) K²` (K the cross-product matrix
/// of the unnormalised axis-angle vector r, θ = |r|), and `a'(θ)/θ`, `b'(θ)/θ`; series for
/// small θ.
fn rodrigues_coeffs(theta2: f64) -> (f64, f64, f64, f64) {
    if theta2 < 1e-6 {
        let t2 = theta2;
        (
            1.0 - t2 / 6.0 + t2 * t2 / 120.0,
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            -1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0,
            -1.0 / 12.0 + t2 / 180.0 - t2 * t2 / 6720.0,
        )
    } else {
        let t = theta2.sqrt();
        let (s, c) = t.sin_cos();
        let a = s / t;
        let b = (1.0 - c) / theta2;
        (
            a,
            b,
            (t * c - s) / (theta2 * t),
            (t * s - 2.0 * (1.0 - c)) / (theta2 * theta2),
        )
    }
}

fn skew(r: [f64; 3]) -> [[f64; 3]; 3] {
    [[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]]
}

fn mat_mul3(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut o = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    o
}

/// Axis-angle vector `[3]` to rotation matrix `[3, 3]` (Rodrigues' formula).
pub struct AxisAngleOp;

impl<T: Real> Op<T> for AxisAngleOp {
    fn name(&self) -> &'static str {
        "axis_angle_to_matrix"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let r = &inputs[0];
        if r.shape() != [3] {
            return Err(AutodiffError::shape(
                "axis_angle_to_matrix",
                &[r.shape()],
                "expected [3]",
            ));
        }
        let rv = [r[0].to_f64c(), r[1].to_f64c(), r[2].to_f64c()];
        let t2 = rv.iter().map(|v| v * v).sum::<f64>();
        let (a, b, _, _) = rodrigues_coeffs(t2);
        let k = skew(rv);
        let k2 = mat_mul3(&k, &k);
        let m = ArrayD::from_shape_fn(IxDyn(&[3, 3]), |ix| {
            let (i, j) = (ix[0], ix[1]);
            T::from_f64c(if i == j { 1.0 } else { 0.0 } + a * k[i][j] + b * k2[i][j])
        });
        Ok(vec![m])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let r = &ctx.inputs[0];
        let g = ctx.grad_outputs[0];
        let rv = [r[0].to_f64c(), r[1].to_f64c(), r[2].to_f64c()];
        let t2 = rv.iter().map(|v| v * v).sum::<f64>();
        let (a, b, a1, b1) = rodrigues_coeffs(t2);
        let k = skew(rv);
        let k2 = mat_mul3(&k, &k);
        let mut out = [0.0f64; 3];
        for (i, o) in out.iter_mut().enumerate() {
            let mut e = [0.0; 3];
            e[i] = 1.0;
            let ei = skew(e);
            let ek = mat_mul3(&ei, &k);
            let ke = mat_mul3(&k, &ei);
            // dR/dr_i = a1 r_i K + a E_i + b1 r_i K² + b (E_i K + K E_i)
            let mut s = 0.0;
            for p in 0..3 {
                for q in 0..3 {
                    let d = a1 * rv[i] * k[p][q]
                        + a * ei[p][q]
                        + b1 * rv[i] * k2[p][q]
                        + b * (ek[p][q] + ke[p][q]);
                    s += d * g[[p, q]].to_f64c();
                }
            }
            *o = s;
        }
        Ok(vec![Some(ArrayD::from_shape_fn(IxDyn(&[3]), |ix| {
            T::from_f64c(out[ix[0]])
        }))])
    }
}

/// Rotation matrix `[3, 3]` from an axis-angle vector `[3]` (direction = axis, norm = angle in
/// radians), exact and finite at zero.
pub fn axis_angle_to_matrix<'t, T: Real>(r: Var<'t, T>) -> Var<'t, T> {
    r.tape().apply(AxisAngleOp, &[r])
}

/// Rotation matrix `[3, 3]` from a quaternion `[4]` `(w, x, y, z)`, normalised first (so any
/// non-zero quaternion is valid and the gradient is tangent to the unit sphere).
pub fn quaternion_to_matrix<'t, T: Real>(q: Var<'t, T>) -> Var<'t, T> {
    let t = q.tape();
    let q = q.normalize(T::from_f64c(1e-12));
    let (w, x, y, z) = (
        q.slice(0, 0, 1),
        q.slice(0, 1, 2),
        q.slice(0, 2, 3),
        q.slice(0, 3, 4),
    );
    let one = T::one();
    let two = one + one;
    let m2 = -two;
    let rows = [
        [
            (y * y + z * z) * m2 + one,
            (x * y - w * z) * two,
            (x * z + w * y) * two,
        ],
        [
            (x * y + w * z) * two,
            (x * x + z * z) * m2 + one,
            (y * z - w * x) * two,
        ],
        [
            (x * z - w * y) * two,
            (y * z + w * x) * two,
            (x * x + y * y) * m2 + one,
        ],
    ];
    let flat: Vec<Var<'t, T>> = rows.iter().flatten().copied().collect();
    t.concat(&flat, 0).reshape(&[3, 3])
}

/// Euler angles `[3]` (radians) to a rotation matrix `R = Rz(c) Ry(b) Rx(a)` for angles
/// `(a, b, c)` about x, y and z (rotation about x first).
pub fn euler_xyz_to_matrix<'t, T: Real>(angles: Var<'t, T>) -> Var<'t, T> {
    let t = angles.tape();
    let (s, c) = (angles.sin(), angles.cos());
    let (sa, sb, sc) = (s.slice(0, 0, 1), s.slice(0, 1, 2), s.slice(0, 2, 3));
    let (ca, cb, cc) = (c.slice(0, 0, 1), c.slice(0, 1, 2), c.slice(0, 2, 3));
    let entries = [
        cc * cb,
        cc * sb * sa - sc * ca,
        cc * sb * ca + sc * sa,
        sc * cb,
        sc * sb * sa + cc * ca,
        sc * sb * ca - cc * sa,
        -sb,
        cb * sa,
        cb * ca,
    ];
    t.concat(&entries, 0).reshape(&[3, 3])
}

/// `R p + t` for points `[N, 3]`, rotation `[3, 3]` and translation `[3]`.
pub fn rigid_transform<'t, T: Real>(
    points: Var<'t, T>,
    rot: Var<'t, T>,
    trans: Var<'t, T>,
) -> Var<'t, T> {
    points.matmul(rot.t()) + trans
}

/// `p -> M [p, 1]` for points [N, 3] and a constant 4x4 row-major matrix `M`, one fused op
/// (no homogeneous copy of the points, no matrix product op): each output row is computed in
/// `f64` and rounded once; the backward is `dL/dp = (dL/dclip) M[:, :3]`.
struct ClipOp {
    matrix: [[f64; 4]; 4],
}

/// Rows per parallel task of [`ClipOp`].
const CLIP_ROWS: usize = 4096;

impl<T: Real> Op<T> for ClipOp {
    fn name(&self) -> &'static str {
        "to_clip"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let p = inputs[0].as_standard_layout();
        if p.ndim() != 2 || p.shape()[1] != 3 {
            return Err(AutodiffError::shape(
                "to_clip",
                &[p.shape()],
                "points must be [N, 3]",
            ));
        }
        let n = p.shape()[0];
        let ps = p.as_slice().expect("standard");
        let m = &self.matrix;
        let mut out = vec![T::zero(); 4 * n];
        out.par_chunks_mut(4 * CLIP_ROWS)
            .zip(ps.par_chunks(3 * CLIP_ROWS))
            .for_each(|(o, p)| {
                for (o, p) in o.chunks_exact_mut(4).zip(p.chunks_exact(3)) {
                    let (x, y, z) = (p[0].to_f64c(), p[1].to_f64c(), p[2].to_f64c());
                    for (o, r) in o.iter_mut().zip(m) {
                        *o = T::from_f64c(r[0] * x + r[1] * y + r[2] * z + r[3]);
                    }
                }
            });
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[n, 4]), out).expect("n x 4")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let g = ctx.grad_outputs[0].as_standard_layout();
        let gs = g.as_slice().expect("standard");
        let n = gs.len() / 4;
        let m = &self.matrix;
        let mut out = vec![T::zero(); 3 * n];
        out.par_chunks_mut(3 * CLIP_ROWS)
            .zip(gs.par_chunks(4 * CLIP_ROWS))
            .for_each(|(o, g)| {
                for (o, g) in o.chunks_exact_mut(3).zip(g.chunks_exact(4)) {
                    let g = [g[0], g[1], g[2], g[3]].map(|v| v.to_f64c());
                    for (i, o) in o.iter_mut().enumerate() {
                        *o = T::from_f64c(
                            g[0] * m[0][i] + g[1] * m[1][i] + g[2] * m[2][i] + g[3] * m[3][i],
                        );
                    }
                }
            });
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(&[n, 3]), out).expect("n x 3"),
        )])
    }
}

/// Homogeneous clip coordinates [N, 4] of points [N, 3] under a constant 4x4 row-major matrix
/// (e.g. `projection * view * model`): `clip = M [p, 1]`.
pub fn to_clip<'t, T: Real>(points: Var<'t, T>, matrix: &[[f64; 4]; 4]) -> Var<'t, T> {
    points.tape().apply(ClipOp { matrix: *matrix }, &[points])
}

/// Clip coordinates [N, 4] of view-space points [N, 3] (camera looking down -z) under an
/// OpenGL perspective projection whose focal length `focal` (a `[1]` variable: `cot(fov_y/2)`)
/// can be optimised: `clip = (f/aspect x, f y, A z + B, -z)` with `A = -(far+near)/(far-near)`,
/// `B = -2 far near/(far-near)` (the gluPerspective matrix).
pub fn perspective_clip<'t, T: Real>(
    view_points: Var<'t, T>,
    focal: Var<'t, T>,
    aspect: f64,
    near: f64,
    far: f64,
) -> Result<Var<'t, T>> {
    if !(near > 0.0 && far > near && aspect > 0.0) {
        return Err(AutodiffError::invalid(
            "perspective_clip",
            format!("need 0 < near < far and aspect > 0 (near {near}, far {far}, aspect {aspect})"),
        ));
    }
    let t: &Tape<T> = view_points.tape();
    let x = view_points.slice(1, 0, 1);
    let y = view_points.slice(1, 1, 2);
    let z = view_points.slice(1, 2, 3);
    let a = T::from_f64c(-(far + near) / (far - near));
    let b = T::from_f64c(-2.0 * far * near / (far - near));
    let cx = x * focal * T::from_f64c(1.0 / aspect);
    let cy = y * focal;
    let cz = z * a + b;
    let cw = -z;
    Ok(t.concat(&[cx, cy, cz, cw], 1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::gradcheck::{gradcheck, GradcheckOptions};
    use autodiff::rng::Rng;

    fn orthonormal(m: &Tensor<f64>) -> f64 {
        let m2 = m.clone().into_dimensionality::<ndarray::Ix2>().unwrap();
        let e = m2.t().dot(&m2) - ndarray::Array2::<f64>::eye(3);
        e.iter().fold(0.0f64, |a, v| a.max(v.abs()))
    }

    #[test]
    fn rotations_are_orthonormal_and_agree() {
        let tape = Tape::<f64>::new();
        let r = tape.leaf(ArrayD::from_shape_vec(IxDyn(&[3]), vec![0.3, -0.2, 0.5]).unwrap());
        let m = axis_angle_to_matrix(r).value().unwrap();
        assert!(orthonormal(&m) < 1e-14);
        // The same rotation as a quaternion.
        let th = (0.09f64 + 0.04 + 0.25).sqrt();
        let (s, c) = (th / 2.0).sin_cos();
        let q = tape.leaf(
            ArrayD::from_shape_vec(
                IxDyn(&[4]),
                vec![c, s * 0.3 / th, s * -0.2 / th, s * 0.5 / th],
            )
            .unwrap(),
        );
        let mq = quaternion_to_matrix(q).value().unwrap();
        let d = (&*m - &*mq).iter().fold(0.0f64, |a, v| a.max(v.abs()));
        assert!(d < 1e-14, "{d}");
        let e = euler_xyz_to_matrix(
            tape.leaf(ArrayD::from_shape_vec(IxDyn(&[3]), vec![0.1, 0.2, 0.3]).unwrap()),
        );
        assert!(orthonormal(&e.value().unwrap()) < 1e-14);
    }

    #[test]
    fn rotation_gradients_check_including_zero() {
        let opts = GradcheckOptions::default();
        let mut rng = Rng::new(7);
        let w: Tensor<f64> = rng.normal_tensor(&[3, 3]);
        for r in [
            vec![0.0, 0.0, 0.0],
            vec![1e-5, -2e-5, 3e-6],
            vec![0.3, -1.2, 0.7],
            vec![2.0, 1.0, -2.5],
        ] {
            let x = ArrayD::from_shape_vec(IxDyn(&[3]), r).unwrap();
            let w = w.clone();
            let rep = gradcheck(
                move |t: &Tape<f64>, v| (axis_angle_to_matrix(v[0]) * t.constant(w.clone())).sum(),
                &[x],
                &opts,
            )
            .unwrap();
            assert!(rep.passed(), "{rep}");
        }
        let q = ArrayD::from_shape_vec(IxDyn(&[4]), vec![0.9, 0.1, -0.3, 0.2]).unwrap();
        let w2 = w.clone();
        let rep = gradcheck(
            move |t: &Tape<f64>, v| (quaternion_to_matrix(v[0]) * t.constant(w2.clone())).sum(),
            &[q],
            &opts,
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
        let e = ArrayD::from_shape_vec(IxDyn(&[3]), vec![0.4, -0.3, 1.1]).unwrap();
        let rep = gradcheck(
            move |t: &Tape<f64>, v| (euler_xyz_to_matrix(v[0]) * t.constant(w.clone())).sum(),
            &[e],
            &opts,
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
    }

    #[test]
    fn to_clip_matches_homogeneous_product_and_gradients_check() {
        let mut rng = Rng::new(7);
        let p: Tensor<f64> = rng.uniform_tensor(&[9, 3], -2.0, 2.0);
        let m = [
            [1.2, -0.3, 0.5, 0.1],
            [0.2, 1.7, -0.4, -0.6],
            [0.3, 0.1, -1.1, 2.5],
            [0.05, -0.2, -1.0, 3.0],
        ];
        let tape = Tape::<f64>::new();
        let c = to_clip(tape.var(p.clone(), false), &m).value().unwrap();
        assert_eq!(c.shape(), [9, 4]);
        for n in 0..9 {
            for j in 0..4 {
                let want =
                    m[j][0] * p[[n, 0]] + m[j][1] * p[[n, 1]] + m[j][2] * p[[n, 2]] + m[j][3];
                assert!((c[[n, j]] - want).abs() <= 1e-14 * (1.0 + want.abs()));
            }
        }
        let rep = gradcheck(
            |_t: &Tape<f64>, v| {
                let c = to_clip(v[0], &m);
                (c.slice(1, 0, 3) / c.slice(1, 3, 4)).square().sum()
            },
            std::slice::from_ref(&p),
            &GradcheckOptions::default(),
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
        // Wrong shapes are typed errors.
        let bad = to_clip(tape.var(ArrayD::zeros(IxDyn(&[4, 2])), false), &m);
        assert!(bad.value().is_err());
        // f32 rounds the f64 result once.
        let t32 = Tape::<f32>::new();
        let c32 = to_clip(t32.var(p.mapv(|x| x as f32), false), &m)
            .value()
            .unwrap();
        for (a, b) in c32.iter().zip(
            to_clip(tape.var(p.mapv(|x| x as f32 as f64), false), &m)
                .value()
                .unwrap()
                .iter(),
        ) {
            assert_eq!(*a, *b as f32);
        }
    }

    #[test]
    fn projection_gradients_check() {
        let mut rng = Rng::new(3);
        let mut p: Tensor<f64> = rng.uniform_tensor(&[5, 3], -1.0, 1.0);
        p.index_axis_mut(ndarray::Axis(1), 2)
            .mapv_inplace(|z| z - 4.0);
        let f = ArrayD::from_elem(IxDyn(&[1]), 1.7);
        let rep = gradcheck(
            |_t: &Tape<f64>, v| {
                let c = perspective_clip(v[0], v[1], 1.3, 0.1, 50.0).unwrap();
                (c.slice(1, 0, 3) / c.slice(1, 3, 4)).square().sum()
            },
            &[p, f],
            &GradcheckOptions::default(),
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
    }
}
