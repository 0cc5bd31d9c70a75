//! Homogeneous edge functions with exact signs and the top-left tie rule.
//!
//! Screen-space vertices are `(X, Y, W)` with pixel centres at integer `(col, row, 1)` (see
//! [`super::clip::to_screen`]). The edge function of the edge `l -> h` is the Pineda (1988) edge
//! function in the homogeneous form of Olano and Greer (1997):
//! `e(p) = (v_l x v_h) . p = A col + B row + C`. It is always evaluated with the endpoints in a
//! canonical order (lower vertex index first) and the same floating-point expression, so two faces
//! sharing an edge see bit-identical values of opposite sign. The sign is made exact with a static
//! error bound (the filter) and, in the rare ambiguous cases, an exact expansion sum (Shewchuk
//! 1997); exact zeros are resolved by the top-left rule (Direct3D 10 / OpenGL), i.e. a symbolic
//! perturbation of the pixel centre by `(eps, eps^2)`. Together these make coverage watertight.

use autodiff::Real;

/// `x` as `T`, saturated to `T`'s finite range (NaN to zero).
#[inline(always)]
pub(crate) fn sat<T: Real>(x: f64) -> T {
    let m = T::max_value().to_f64c();
    if x.abs() <= m {
        T::from_f64c(x)
    } else if x.is_nan() {
        T::zero()
    } else {
        T::from_f64c(m.copysign(x))
    }
}

/// Unit roundoff of `f64`.
const U: f64 = f64::EPSILON * 0.5;
/// Relative error bound factor of the `f64` edge function and determinant (the true bound is
/// about `5 u` times the permanent, see [`Setup::new`]).
const ERR: f64 = 8.0 * U;
/// Absolute slack of the filter, for gradual underflow.
const ERR_ABS: f64 = 1e-300;

/// Exact `a + b = s + e`.
#[inline]
fn two_sum(a: f64, b: f64) -> (f64, f64) {
    let s = a + b;
    let bb = s - a;
    (s, (a - (s - bb)) + (b - bb))
}

/// Exact `a * b = p + e` (barring underflow); `mul_add` is a fused multiply-add by contract.
#[inline]
fn two_prod(a: f64, b: f64) -> (f64, f64) {
    let p = a * b;
    (p, a.mul_add(b, -p))
}

/// Collects the exact terms of a sum of products.
struct Terms {
    t: [f64; 24],
    n: usize,
}

impl Terms {
    fn new() -> Self {
        Self { t: [0.0; 24], n: 0 }
    }
    /// Adds `a * b` exactly (2 terms).
    fn prod2(&mut self, a: f64, b: f64) {
        let (p, e) = two_prod(a, b);
        self.t[self.n] = p;
        self.t[self.n + 1] = e;
        self.n += 2;
    }
    /// Adds `a * b * c` exactly (4 terms).
    fn prod3(&mut self, a: f64, b: f64, c: f64) {
        let (p, e) = two_prod(a, b);
        let (p1, p2) = two_prod(p, c);
        let (e1, e2) = two_prod(e, c);
        self.t[self.n..self.n + 4].copy_from_slice(&[p1, p2, e1, e2]);
        self.n += 4;
    }
    /// Exact sign of the sum: builds a nonoverlapping expansion with Shewchuk's
    /// GROW-EXPANSION-ZEROELIM and returns the sign of its largest component.
    fn sign(&self) -> i32 {
        let mut h = [0.0f64; 24];
        let mut n = 0;
        for &x in &self.t[..self.n] {
            let mut q = x;
            let mut k = 0;
            for i in 0..n {
                let (s, e) = two_sum(q, h[i]);
                if e != 0.0 {
                    h[k] = e;
                    k += 1;
                }
                q = s;
            }
            if q != 0.0 {
                h[k] = q;
                k += 1;
            }
            n = k;
        }
        if n == 0 {
            0
        } else if h[n - 1] > 0.0 {
            1
        } else {
            -1
        }
    }
}

/// Exact sign of `(l x h) . (col, row, 1)` over `(X, Y, W)`.
pub(crate) fn exact_edge_sign(l: &[f64; 4], h: &[f64; 4], col: f64, row: f64) -> i32 {
    let mut t = Terms::new();
    t.prod3(l[1], h[2], col);
    t.prod3(-l[2], h[1], col);
    t.prod3(l[2], h[0], row);
    t.prod3(-l[0], h[2], row);
    t.prod2(l[0], h[1]);
    t.prod2(-l[1], h[0]);
    t.sign()
}

/// Exact signs of the `col` and `row` coefficients `(A, B)` of the edge `l -> h`.
fn exact_normal_sign(l: &[f64; 4], h: &[f64; 4]) -> (i32, i32) {
    let mut a = Terms::new();
    a.prod2(l[1], h[2]);
    a.prod2(-l[2], h[1]);
    let mut b = Terms::new();
    b.prod2(l[2], h[0]);
    b.prod2(-l[0], h[2]);
    (a.sign(), b.sign())
}

/// Exact sign of `det [v0 v1 v2]` over `(X, Y, W)`.
fn exact_det_sign(v: &[[f64; 4]; 3]) -> i32 {
    let [a, b, c] = v;
    let mut t = Terms::new();
    t.prod3(a[0], b[1], c[2]);
    t.prod3(-a[0], b[2], c[1]);
    t.prod3(a[1], b[2], c[0]);
    t.prod3(-a[1], b[0], c[2]);
    t.prod3(a[2], b[0], c[1]);
    t.prod3(-a[2], b[1], c[0]);
    t.sign()
}

/// Canonical endpoints `(lo, hi)` of edge `i` (opposite vertex `i`) and the sign mapping the
/// canonical `lo x hi` to `v_{i+1} x v_{i+2}`.
#[inline(always)]
fn canonical(face: &[u32; 3], i: usize) -> (usize, usize, f64) {
    let (j, k) = ((i + 1) % 3, (i + 2) % 3);
    if face[j] <= face[k] {
        (j, k, 1.0)
    } else {
        (k, j, -1.0)
    }
}

/// Canonical edge function of the edge between vertex slots `j` and `k`: `(A, B, C)` of
/// `s (lo x hi)` with `s = +-1` such that it equals `v_j x v_k`, plus the permanents
/// `(|A|, |B|, |C|)`-bounds of its terms. Branch-free selection keeps it cheap.
#[inline(always)]
fn edge_coeffs(v: &[[f64; 4]; 3], face: &[u32; 3], j: usize, k: usize) -> ([f64; 3], [f64; 3]) {
    let swap = face[j] > face[k];
    let (l, h) = if swap { (&v[k], &v[j]) } else { (&v[j], &v[k]) };
    let s = if swap { -1.0 } else { 1.0 };
    // The same expression on the same operands for every face sharing the edge; the flip by
    // s is exact.
    let a1 = l[1] * h[2];
    let a2 = l[2] * h[1];
    let b1 = l[2] * h[0];
    let b2 = l[0] * h[2];
    let c1 = l[0] * h[1];
    let c2 = l[1] * h[0];
    (
        [s * (a1 - a2), s * (b1 - b2), s * (c1 - c2)],
        [
            a1.abs() + a2.abs(),
            b1.abs() + b2.abs(),
            c1.abs() + c2.abs(),
        ],
    )
}

/// Per-face data for coverage and interpolation, in the screen frame.
///
/// Edge `i` is opposite vertex `i`. Coefficients are oriented so that the inside of the triangle
/// is where all `e_i >= 0` (`e_i = a_i col + b_i row + c_i`), i.e. they are multiplied by the
/// orientation sign; `e_i / sum(e)` are the perspective-correct barycentrics.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Setup {
    pub a: [f64; 3],
    pub b: [f64; 3],
    pub c: [f64; 3],
    /// Filter bounds: `|e_i - exact e_i| <= bnd_i` over the pixel box given to [`Setup::new`].
    pub bnd: [f64; 3],
    /// `1 / |det M|` in the screen frame (`|det M| = sum_i e_i(p) w_i` for every `p`).
    pub inv_det: f64,
    /// Orientation sign of `det M`: negative for faces that are counter-clockwise in NDC (the
    /// viewport flips y).
    sign: f64,
    /// Vertex indices.
    pub face: [u32; 3],
    /// Clip `w` of the vertices.
    pub w: [f64; 3],
}

impl Setup {
    /// Builds the setup of `face` (screen vertices `v`) for pixels `col <= cmax`, `row <= rmax`.
    /// `None` for a back-facing face when `cull_back` (clockwise in NDC: `det M > 0` in the
    /// y-down screen frame), an exactly degenerate face (`det M == 0`), one whose edge
    /// functions overflow, or one whose `f64` determinant is too inaccurate to normalise with.
    #[inline]
    pub fn new(
        v: &[[f64; 4]; 3],
        face: [u32; 3],
        cmax: f64,
        rmax: f64,
        cull_back: bool,
    ) -> Option<Setup> {
        let (e0, p0) = edge_coeffs(v, &face, 1, 2);
        // det M = (v1 x v2) . v0, with its own error filter and exact fallback.
        let det = e0[0] * v[0][0] + e0[1] * v[0][1] + e0[2] * v[0][2];
        let perm = p0[0] * v[0][0].abs() + p0[1] * v[0][1].abs() + p0[2] * v[0][2].abs();
        let tol = ERR * perm + ERR_ABS;
        if cull_back && det > tol {
            // Certainly back-facing: culled before the rest of the setup.
            return None;
        }
        let (e1, p1) = edge_coeffs(v, &face, 2, 0);
        let (e2, p2) = edge_coeffs(v, &face, 0, 1);
        // e = fl(fl(a col) + fl(fl(b row) + c)) with a, b, c each within 2u of their
        // permanents: |error| <= ~5u (pa col + pb row + pc) <= ERR * (...).
        let bound = |p: &[f64; 3]| ERR * (p[0] * cmax + p[1] * rmax + p[2]) + ERR_ABS;
        let bnd = [bound(&p0), bound(&p1), bound(&p2)];
        if !(perm.is_finite() && (bnd[0] + bnd[1] + bnd[2]).is_finite()) {
            return None;
        }
        let sign = if det > tol {
            1.0
        } else if det < -tol {
            -1.0
        } else {
            match exact_det_sign(v) {
                0 => return None,
                s => s as f64,
            }
        };
        if cull_back && sign > 0.0 {
            return None;
        }
        let det = det * sign;
        if !(det > 0.0) {
            // Exactly nonzero but below the f64 rounding of its own terms: a sliver with no
            // usable barycentrics.
            return None;
        }
        Some(Setup {
            a: [e0[0] * sign, e1[0] * sign, e2[0] * sign],
            b: [e0[1] * sign, e1[1] * sign, e2[1] * sign],
            c: [e0[2] * sign, e1[2] * sign, e2[2] * sign],
            bnd,
            inv_det: 1.0 / det,
            sign,
            face,
            w: [v[0][2], v[1][2], v[2][2]],
        })
    }

    /// The NDC depth plane `(dza, dzb, dzc)`: `z/w = dza col + dzb row + dzc`, affine in
    /// screen space (`sum_i e_i z_i / sum_i e_i w_i` with `sum_i e_i w_i = det`). `v` are the
    /// face's screen vertices, `z` in slot 3.
    #[inline]
    pub fn depth_plane(&self, v: &[[f64; 4]; 3]) -> [f64; 3] {
        let z = [v[0][3], v[1][3], v[2][3]];
        [
            (self.a[0] * z[0] + self.a[1] * z[1] + self.a[2] * z[2]) * self.inv_det,
            (self.b[0] * z[0] + self.b[1] * z[1] + self.b[2] * z[2]) * self.inv_det,
            (self.c[0] * z[0] + self.c[1] * z[1] + self.c[2] * z[2]) * self.inv_det,
        ]
    }

    /// Row part `b_i row + c_i` of the edge functions.
    #[inline(always)]
    pub fn row(&self, row: f64) -> [f64; 3] {
        [
            self.b[0] * row + self.c[0],
            self.b[1] * row + self.c[1],
            self.b[2] * row + self.c[2],
        ]
    }

    /// Edge functions at `col` given the row part. This exact expression defines `e`.
    #[inline(always)]
    pub fn eval(&self, col: f64, t: &[f64; 3]) -> [f64; 3] {
        [
            self.a[0] * col + t[0],
            self.a[1] * col + t[1],
            self.a[2] * col + t[2],
        ]
    }

    /// Exact coverage of the pixel `(col, row)` whose `f64` edge values `e` were ambiguous for
    /// the filter (no `e_i < -bnd_i`).
    #[cold]
    #[inline(never)]
    pub fn covered_exact(&self, verts: &[[f64; 4]], e: &[f64; 3], col: f64, row: f64) -> bool {
        for (i, (&ei, &bi)) in e.iter().zip(&self.bnd).enumerate() {
            if ei > bi {
                continue;
            }
            let (lo, hi, fl) = canonical(&self.face, i);
            let (l, h) = (
                &verts[self.face[lo] as usize],
                &verts[self.face[hi] as usize],
            );
            let sigma = (fl * self.sign) as i32;
            let s = sigma * exact_edge_sign(l, h, col, row);
            if s < 0 {
                return false;
            }
            if s == 0 {
                // Top-left rule: an edge whose inward normal (a, b) points right (a > 0, a left
                // edge) or straight down (a == 0, b > 0: a top edge, rows grow downwards) owns
                // the pixels on it.
                let (sa, sb) = exact_normal_sign(l, h);
                let (sa, sb) = (sigma * sa, sigma * sb);
                if !(sa > 0 || (sa == 0 && sb > 0)) {
                    return false;
                }
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_sign_of_sums() {
        let mut t = Terms::new();
        t.prod2(1e16, 1.0);
        t.prod2(1.0, 1.0);
        t.prod2(-1e16, 1.0);
        assert_eq!(t.sign(), 1);
        let mut t = Terms::new();
        // (1 + 2^-52)^2 - 1 - 2^-51 = 2^-104 > 0, invisible to plain f64.
        let x = 1.0 + f64::EPSILON;
        t.prod2(x, x);
        t.prod2(-1.0, 1.0);
        t.prod2(-2.0 * f64::EPSILON, 1.0);
        assert_eq!(t.sign(), 1);
        assert_eq!(x * x - 1.0 - 2.0 * f64::EPSILON, 0.0);
        assert_eq!(Terms::new().sign(), 0);
    }

    #[test]
    fn exact_edge_on_pixel() {
        // Edge through (0.1, 0.1) and (0.3, 0.3) in homogeneous form with w = 1: pixel (7, 7) lies
        // on its line exactly although 0.1 and 0.3 are not representable.
        let l = [0.1, 0.1, 1.0, 0.0];
        let h = [0.3, 0.3, 1.0, 0.0];
        assert_eq!(exact_edge_sign(&l, &h, 7.0, 7.0), 0);
        assert_eq!(
            exact_edge_sign(&l, &h, 7.0, 8.0),
            -exact_edge_sign(&l, &h, 8.0, 7.0)
        );
        assert_eq!(exact_det_sign(&[l, h, [5.0, 5.0, 2.0, 0.0]]), 0);
    }
}
