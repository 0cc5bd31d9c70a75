//! Least-squares alignment of corresponding 3-D point sets: the similarity (or rigid)
//! transform `x -> s R x + t` minimising `sum |s R x_i + t - y_i|^2` (Umeyama 1991, "Least-
//! squares estimation of transformation parameters between two point patterns", eqs. 40-42).
//! `R` is the orthogonal polar factor of the cross-covariance (`U V^T` of its SVD), computed by
//! Higham's iteration `R <- (R + R^-T) / 2`; for the near-aligned shapes it is used on (a fit
//! against its truth, two face meshes) this is the rotation of Umeyama's eq. 40 (no
//! reflection case).

use crate::face::geom::{cross, sub, V3};

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `x -> scale * rotation (x - from) + to`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    /// Rotation (row-major).
    pub rotation: [[f64; 3]; 3],
    /// Scale (1 for a rigid transform).
    pub scale: f64,
    /// Centroid of the source points.
    pub from: [f64; 3],
    /// Centroid of the destination points.
    pub to: [f64; 3],
}

impl Similarity {
    /// The transformed point.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let q = sub(p, self.from);
        std::array::from_fn(|i| self.scale * dot(self.rotation[i], q) + self.to[i])
    }
}

/// The least-squares transform taking `src` onto `dst` (same length, corresponding points):
/// with a scale when `with_scale`, else rigid.
pub fn umeyama(src: &[[f64; 3]], dst: &[[f64; 3]], with_scale: bool) -> Similarity {
    let n = src.len().max(1) as f64;
    let mean = |p: &[[f64; 3]]| -> [f64; 3] {
        std::array::from_fn(|i| p.iter().map(|q| q[i]).sum::<f64>() / n)
    };
    let (ms, md) = (mean(src), mean(dst));
    let mut cov = [[0.0; 3]; 3];
    let mut var = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let (s, d) = (sub(*s, ms), sub(*d, md));
        var += dot(s, s);
        for i in 0..3 {
            for j in 0..3 {
                cov[i][j] += d[i] * s[j];
            }
        }
    }
    let mut r = cov;
    for _ in 0..100 {
        let inv_t = inverse_transpose(r);
        if inv_t.iter().flatten().any(|x| !x.is_finite()) {
            break;
        }
        for i in 0..3 {
            for j in 0..3 {
                r[i][j] = 0.5 * (r[i][j] + inv_t[i][j]);
            }
        }
    }
    let mut tr = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            tr += r[i][j] * cov[i][j];
        }
    }
    let scale = if with_scale && var > 0.0 {
        tr / var
    } else {
        1.0
    };
    Similarity {
        rotation: r,
        scale,
        from: ms,
        to: md,
    }
}

/// `(M^-1)^T`: the cofactor matrix over the determinant.
fn inverse_transpose(m: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let c0 = cross(m[1], m[2]);
    let c1 = cross(m[2], m[0]);
    let c2 = cross(m[0], m[1]);
    let det = dot(m[0], c0);
    [c0, c1, c2].map(|r| r.map(|x| x / det))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::euler_to_axis_angle;

    /// A known similarity is recovered from 10 points, rigid and with scale.
    #[test]
    fn recovers_a_known_transform() {
        let mut rng = autodiff::rng::Rng::new(7);
        let src: Vec<[f64; 3]> = (0..10)
            .map(|_| std::array::from_fn(|_| rng.uniform(-50.0, 50.0)))
            .collect();
        let r = euler_to_axis_angle(0.4, -0.2, 0.3);
        let tape = autodiff::Tape::<f64>::new();
        let v = tape
            .constant(ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&[3]), r.to_vec()).unwrap());
        let m = render_ops::transform::axis_angle_to_matrix(v)
            .value()
            .unwrap();
        for s in [1.0, 1.3] {
            let dst: Vec<[f64; 3]> = src
                .iter()
                .map(|p| {
                    std::array::from_fn(|i| {
                        s * (0..3).map(|j| m[[i, j]] * p[j]).sum::<f64>() + [5.0, -2.0, 9.0][i]
                    })
                })
                .collect();
            let t = umeyama(&src, &dst, s != 1.0);
            assert!((t.scale - s).abs() < 1e-12, "{}", t.scale);
            for (p, q) in src.iter().zip(&dst) {
                let a = t.apply(*p);
                assert!((0..3).all(|i| (a[i] - q[i]).abs() < 1e-9), "{a:?} {q:?}");
            }
        }
    }
}
