//! Watertight ray-triangle intersection: S. Woop, C. Benthin, I. Wald, "Watertight
//! ray/triangle intersection", JCGT 2(1), 2013. The ray is sheared so that it runs along +z
//! through the origin; the triangle's 2D edge functions `U, V, W` then decide the hit, and a
//! ray through a shared edge or vertex hits at least one of the triangles that share it (edge
//! functions exactly zero count as inside). Everything is in `f64` (the paper's fallback
//! precision), so no second evaluation is needed.

use crate::simd::{arr3, lanes, LANES};

/// A vector of three `f64`.
pub type V3 = [f64; 3];

/// A ray `origin + t dir` prepared for the watertight test (the shear of section 3).
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    /// Origin.
    pub origin: V3,
    /// Direction (any length; `t` is in its units).
    pub dir: V3,
    /// `1 / dir` per axis (slab tests).
    pub inv_dir: V3,
    k: [usize; 3],
    shear: V3,
}

/// A hit: the distance along the ray and the barycentrics of the triangle's vertices.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter.
    pub t: f64,
    /// Barycentrics `(b0, b1, b2)`, summing to one; the hit is `sum b_i v_i`.
    pub bary: V3,
    /// Triangle (face) index.
    pub face: u32,
}

impl Hit {
    /// Puts `self` in `best` when it is nearer (`t`, then the lower face index: the closest-hit
    /// rule of every traversal) and below `t_max`; whether it did.
    #[inline]
    pub fn keep_if_nearer(self, best: &mut Option<Hit>, t_max: f64) -> bool {
        let nearer = match best {
            None => true,
            Some(b) => self.t < b.t || (self.t == b.t && self.face < b.face),
        };
        let keep = nearer && self.t < t_max;
        if keep {
            *best = Some(self);
        }
        keep
    }
}

impl Ray {
    /// A ray from `origin` along `dir` (non-zero).
    pub fn new(origin: V3, dir: V3) -> Self {
        let [kx, ky, kz] = axes(dir);
        let inv_dir = dir.map(|d| 1.0 / d);
        let sz = inv_dir[kz];
        Ray {
            origin,
            dir,
            inv_dir,
            k: [kx, ky, kz],
            shear: [dir[kx] * sz, dir[ky] * sz, sz],
        }
    }

    /// The point at `t`.
    pub fn at(&self, t: f64) -> V3 {
        [
            self.origin[0] + t * self.dir[0],
            self.origin[1] + t * self.dir[1],
            self.origin[2] + t * self.dir[2],
        ]
    }

    /// The watertight test against triangle `v`: `Some((t, bary))` when the ray hits it with
    /// `t_min < t < t_max`. Degenerate (zero-area in the ray's view) triangles never hit.
    #[inline]
    pub fn intersect(&self, v: &[V3; 3], t_min: f64, t_max: f64) -> Option<(f64, V3)> {
        let [kx, ky, kz] = self.k;
        let [sx, sy, sz] = self.shear;
        let rel = |p: &V3| {
            let a = [
                p[0] - self.origin[0],
                p[1] - self.origin[1],
                p[2] - self.origin[2],
            ];
            (a[kx] - sx * a[kz], a[ky] - sy * a[kz], sz * a[kz])
        };
        let (ax, ay, az) = rel(&v[0]);
        let (bx, by, bz) = rel(&v[1]);
        let (cx, cy, cz) = rel(&v[2]);
        let u = cx * by - cy * bx;
        let vv = ax * cy - ay * cx;
        let w = bx * ay - by * ax;
        if (u < 0.0 || vv < 0.0 || w < 0.0) && (u > 0.0 || vv > 0.0 || w > 0.0) {
            return None;
        }
        let det = u + vv + w;
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let t = (u * az + vv * bz + w * cz) / det;
        if !(t > t_min && t < t_max) {
            return None;
        }
        Some((t, [u / det, vv / det, w / det]))
    }
}

/// Eight `f64` lanes of a ray packet (one value per ray).
pub type D8 = [f64; LANES];
/// Eight lane flags.
pub type K8 = [bool; LANES];

/// Eight rays that share the axis permutation of the watertight test (camera rays through a
/// few neighbouring pixels, shadow rays towards one light), each lane the [`Ray`] of the same
/// origin and direction: the packet's tests are the scalar ones lane by lane, so they give the
/// same bits (the forward's packets, [`super::packet`]).
#[derive(Clone, Copy, Debug)]
pub struct Ray8 {
    /// Origins (x, y, z lanes).
    pub origin: [D8; 3],
    /// Directions.
    pub dir: [D8; 3],
    /// `1 / dir` per axis.
    pub inv_dir: [D8; 3],
    k: [usize; 3],
    shear: [D8; 3],
    /// The origins' coordinates in shear order `(kx, ky, kz)` (lanes indexed statically).
    o_k: [D8; 3],
}

/// The dominant axis of direction `d` and whether `d` runs towards its negative side.
#[inline(always)]
fn dominant(d: V3) -> (usize, bool) {
    let a = d.map(f64::abs);
    let kz = if a[0] >= a[1] && a[0] >= a[2] {
        0
    } else if a[1] >= a[2] {
        1
    } else {
        2
    };
    (kz, d[kz] < 0.0)
}

/// The axis permutation `[kx, ky, kz]` of the shear for direction `d`: `kz` the dominant axis,
/// `kx, ky` swapped where `d` runs towards `-kz` (keeps the triangles' winding).
#[inline(always)]
fn axes(d: V3) -> [usize; 3] {
    let (kz, neg) = dominant(d);
    let (kx, ky) = ((kz + 1) % 3, (kz + 2) % 3);
    if neg {
        [ky, kx, kz]
    } else {
        [kx, ky, kz]
    }
}

impl Ray8 {
    /// The rays of the `active` lanes (the others copy the first active one); `None` when
    /// their axis permutations differ (the caller takes the scalar rays) or no lane is active.
    #[inline(always)]
    pub fn new(origin: [D8; 3], dir: [D8; 3], active: K8) -> Option<Self> {
        let first = active.iter().position(|&a| a)?;
        let (origin, dir) = if active.contains(&false) {
            let pick = |v: &[D8; 3]| arr3(|a| lanes(|i| v[a][if active[i] { i } else { first }]));
            (pick(&origin), pick(&dir))
        } else {
            (origin, dir)
        };
        // The permutation of each lane, as one small code (dominant axis, sign).
        let code = lanes(|i| {
            let (kz, neg) = dominant([dir[0][i], dir[1][i], dir[2][i]]);
            2 * kz as u32 + neg as u32
        });
        if code.iter().any(|&c| c != code[0]) {
            return None;
        }
        let k = axes([dir[0][first], dir[1][first], dir[2][first]]);
        let inv_dir = arr3(|a| lanes(|i| 1.0 / dir[a][i]));
        let sz = inv_dir[k[2]];
        Some(Ray8 {
            origin,
            dir,
            inv_dir,
            o_k: k.map(|a| origin[a]),
            k,
            shear: [
                lanes(|i| dir[k[0]][i] * sz[i]),
                lanes(|i| dir[k[1]][i] * sz[i]),
                sz,
            ],
        })
    }

    /// Vertex `p` in each lane's sheared frame.
    #[inline(always)]
    fn rel(&self, p: &V3) -> (D8, D8, D8) {
        let [kx, ky, kz] = self.k;
        let [sx, sy, sz] = &self.shear;
        let [ox, oy, oz] = &self.o_k;
        let az = lanes(|i| p[kz] - oz[i]);
        (
            lanes(|i| (p[kx] - ox[i]) - sx[i] * az[i]),
            lanes(|i| (p[ky] - oy[i]) - sy[i] * az[i]),
            lanes(|i| sz[i] * az[i]),
        )
    }

    /// [`Ray::intersect`] lane by lane for the `active` lanes (`t_min >= 0`): which hit, their
    /// `t`, and the edge functions `(U, V, W)` and their sum `det` (the barycentrics are
    /// `U / det` ..., left to the caller: a closest-hit query divides once, for the winner);
    /// all unspecified in the other lanes.
    #[inline(always)]
    pub fn intersect(
        &self,
        v: &[V3; 3],
        t_min: f64,
        t_max: &D8,
        active: K8,
    ) -> (K8, D8, [D8; 3], D8) {
        let (ax, ay, az) = self.rel(&v[0]);
        let (bx, by, bz) = self.rel(&v[1]);
        let (cx, cy, cz) = self.rel(&v[2]);
        let u = lanes(|i| cx[i] * by[i] - cy[i] * bx[i]);
        let vv = lanes(|i| ax[i] * cy[i] - ay[i] * cx[i]);
        let w = lanes(|i| bx[i] * ay[i] - by[i] * ax[i]);
        let det = lanes(|i| u[i] + vv[i] + w[i]);
        let t = lanes(|i| (u[i] * az[i] + vv[i] * bz[i] + w[i] * cz[i]) / det[i]);
        // Branch-free lane masks (`&`, `|`: every operand is a plain comparison). The scalar
        // test's `det != 0` and finite `det` need no test of their own when `t_min >= 0`:
        // otherwise `t` is `+-inf`, `+-0` or NaN, which `t_min < t < t_max` rejects (and
        // `is_finite` would be lowered lane by lane, to integer code).
        debug_assert!(t_min >= 0.0);
        let hit = lanes(|i| {
            let out = ((u[i] < 0.0) | (vv[i] < 0.0) | (w[i] < 0.0))
                & ((u[i] > 0.0) | (vv[i] > 0.0) | (w[i] > 0.0));
            active[i] & !out & (t[i] > t_min) & (t[i] < t_max[i])
        });
        (hit, t, [u, vv, w], det)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hits_inside_misses_outside_and_reports_barycentrics() {
        let tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let r = Ray::new([0.25, 0.5, 1.0], [0.0, 0.0, -2.0]);
        let (t, b) = r.intersect(&tri, 0.0, f64::INFINITY).unwrap();
        assert!((t - 0.5).abs() < 1e-15);
        assert!((b[0] - 0.25).abs() < 1e-15 && (b[1] - 0.25).abs() < 1e-15);
        assert!((b[2] - 0.5).abs() < 1e-15);
        let p = r.at(t);
        for k in 0..3 {
            let q: f64 = (0..3).map(|i| b[i] * tri[i][k]).sum();
            assert!((p[k] - q).abs() < 1e-15);
        }
        assert!(Ray::new([0.8, 0.8, 1.0], [0.0, 0.0, -1.0])
            .intersect(&tri, 0.0, 9.0)
            .is_none());
        // Behind the origin, and beyond t_max.
        assert!(r.intersect(&tri, 0.6, 9.0).is_none());
        assert!(r.intersect(&tri, 0.0, 0.4).is_none());
    }

    #[test]
    fn shared_edges_are_watertight_and_degenerate_triangles_never_hit() {
        // Two triangles sharing the diagonal of the unit square; rays exactly on it, and at
        // the shared vertices, hit at least one of them.
        let a = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]];
        let b = [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]];
        // Interior points of the diagonal (its ends are corners of the square, where rounding
        // of the origin may put the ray just outside).
        for i in 1..64 {
            let x = i as f64 / 64.0;
            for dir in [[0.0, 0.0, -1.0], [0.3, -0.2, -1.0], [-1e-9, 2e-9, -1.0]] {
                let o = [x - 0.5 * dir[0], x - 0.5 * dir[1], 0.5];
                let r = Ray::new(o, dir);
                assert!(
                    r.intersect(&a, 0.0, 9.0).is_some() || r.intersect(&b, 0.0, 9.0).is_some(),
                    "{x} {dir:?}"
                );
            }
        }
        let sliver = [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0, 0.0]];
        let r = Ray::new([1.0, 1.0, 1.0], [0.0, 0.0, -1.0]);
        assert!(r.intersect(&sliver, 0.0, 9.0).is_none());
        let point = [[1.0, 1.0, 0.0]; 3];
        assert!(r.intersect(&point, 0.0, 9.0).is_none());
        // Grazing: a ray in the triangle's plane does not hit (det = 0) and gives no NaN.
        let g = Ray::new([-1.0, 0.2, 0.0], [1.0, 0.0, 0.0]);
        assert!(g.intersect(&a, 0.0, 9.0).is_none());
    }
}
