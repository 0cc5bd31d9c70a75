//! The mesh's edges and what edge sampling needs of them: adjacency (vertices with identical
//! positions welded, so uv or normal seams are not edges), silhouette tests seen from a point
//! or along a direction, a length-proportional sampling table, and the derivative of where a
//! ray meets a triangle's plane. T.-M. Li, M. Aittala, F. Durand, J. Lehtinen,
//! "Differentiable Monte Carlo ray tracing through edge sampling", SIGGRAPH Asia 2018,
//! sections 4-5 (primary and secondary visibility, edge selection by importance).

use std::collections::HashMap;

use crate::shade::{cross3, dot3, scale3, sub3};

use super::intersect::V3;

/// An edge with the faces on either side (`faces[1] == u32::MAX`: a boundary edge; more than
/// two faces: treated as a boundary, always a candidate).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Edge {
    /// End vertices (as indexed by the first face that has the edge).
    pub v: [u32; 2],
    /// Adjacent faces.
    pub faces: [u32; 2],
}

/// No face on this side.
pub const NONE: u32 = u32::MAX;

/// The edges of `faces`, in the order of first appearance (face by face, corner by corner):
/// deterministic. Vertices at bitwise equal positions are one vertex for adjacency.
pub fn mesh_edges(positions: &[V3], faces: &[[u32; 3]]) -> Vec<Edge> {
    let mut weld: HashMap<[u64; 3], u32> = HashMap::with_capacity(positions.len());
    let canon: Vec<u32> = positions
        .iter()
        .enumerate()
        .map(|(i, p)| *weld.entry(p.map(f64::to_bits)).or_insert(i as u32))
        .collect();
    let mut index: HashMap<(u32, u32), usize> = HashMap::with_capacity(faces.len() * 2);
    let mut edges: Vec<Edge> = Vec::with_capacity(faces.len() * 3 / 2 + 1);
    let mut extra: Vec<bool> = Vec::new();
    for (f, tri) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let (ca, cb) = (canon[a as usize], canon[b as usize]);
            if ca == cb {
                continue;
            }
            let key = (ca.min(cb), ca.max(cb));
            match index.get(&key) {
                None => {
                    index.insert(key, edges.len());
                    edges.push(Edge {
                        v: [a, b],
                        faces: [f as u32, NONE],
                    });
                    extra.push(false);
                }
                Some(&e) => {
                    if edges[e].faces[1] == NONE && !extra[e] {
                        edges[e].faces[1] = f as u32;
                    } else {
                        extra[e] = true;
                    }
                }
            }
        }
    }
    for (e, x) in edges.iter_mut().zip(extra) {
        if x {
            e.faces[1] = NONE;
        }
    }
    edges
}

/// Unnormalised face normal `(v1 - v0) x (v2 - v0)`.
pub fn face_normal(p: &[V3], tri: &[u32; 3]) -> V3 {
    let v = tri.map(|i| p[i as usize]);
    cross3(sub3(v[1], v[0]), sub3(v[2], v[0]))
}

/// Where a silhouette is seen from.
#[derive(Clone, Copy, Debug)]
pub enum Viewer {
    /// A point (camera, point light, shading point).
    At(V3),
    /// A direction of travel (directional light).
    Along(V3),
}

/// Whether `e` is a silhouette (or boundary) edge seen from `viewer`: its two faces face
/// opposite ways.
pub fn is_silhouette(e: &Edge, p: &[V3], faces: &[[u32; 3]], viewer: Viewer) -> bool {
    if e.faces[1] == NONE {
        return true;
    }
    let side = |f: u32| {
        let n = face_normal(p, &faces[f as usize]);
        match viewer {
            Viewer::At(o) => dot3(n, sub3(o, p[e.v[0] as usize])),
            Viewer::Along(d) => -dot3(n, d),
        }
    };
    let (a, b) = (side(e.faces[0]), side(e.faces[1]));
    (a > 0.0) != (b > 0.0)
}

/// A discrete distribution over items proportional to non-negative weights.
#[derive(Clone, Debug, Default)]
pub struct Cdf {
    items: Vec<u32>,
    cum: Vec<f64>,
}

impl Cdf {
    /// Items with positive finite weight.
    pub fn new(weights: impl Iterator<Item = (u32, f64)>) -> Self {
        let mut c = Cdf::default();
        let mut total = 0.0;
        for (i, w) in weights {
            if w > 0.0 && w.is_finite() {
                total += w;
                c.items.push(i);
                c.cum.push(total);
            }
        }
        c
    }

    /// No item has weight.
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// The item at `u` in `[0, 1)` and its probability.
    pub fn sample(&self, u: f64) -> (u32, f64) {
        let total = *self.cum.last().expect("non-empty");
        let x = u * total;
        let k = self
            .cum
            .partition_point(|&c| c <= x)
            .min(self.items.len() - 1);
        let prev = if k == 0 { 0.0 } else { self.cum[k - 1] };
        (self.items[k], (self.cum[k] - prev) / total)
    }
}

/// Where the ray `o + t D` meets the plane of triangle `r`: `t`, the barycentrics `beta` and
/// their derivative rows: for a first-order change of the ray and the triangle,
/// `d beta_k = j[k] . (do + t dD - sum_i beta_i dr_i)` (`k = 1, 2`; `d beta_0 = -d beta_1 -
/// d beta_2`). With `N = e1 x e2` and `P = I - D N^T / (N . D)` (the projection onto the plane
/// along `D`), `j[1] = P^T (e2 x N) / |N|^2`, `j[2] = P^T (N x e1) / |N|^2`.
#[derive(Clone, Copy, Debug)]
pub struct PlaneHit {
    /// Ray parameter.
    pub t: f64,
    /// Barycentrics.
    pub beta: V3,
    /// Derivative rows of `beta_1`, `beta_2`.
    pub j: [V3; 2],
}

/// [`PlaneHit`] of `o + t D` with the plane of `r`; `None` when the ray is parallel to it or
/// the triangle is degenerate.
pub fn plane_hit(o: V3, d: V3, r: [V3; 3]) -> Option<PlaneHit> {
    let e1 = sub3(r[1], r[0]);
    let e2 = sub3(r[2], r[0]);
    let n = cross3(e1, e2);
    let nn = dot3(n, n);
    let nd = dot3(n, d);
    if nn == 0.0 || nd == 0.0 || !(nd / nn.sqrt()).is_normal() {
        return None;
    }
    let t = dot3(n, sub3(r[0], o)) / nd;
    let x = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    let a = scale3(cross3(e2, n), 1.0 / nn);
    let b = scale3(cross3(n, e1), 1.0 / nn);
    let w = sub3(x, r[0]);
    let (b1, b2) = (dot3(a, w), dot3(b, w));
    let pt = |m: V3| {
        let s = dot3(d, m) / nd;
        sub3(m, scale3(n, s))
    };
    Some(PlaneHit {
        t,
        beta: [1.0 - b1 - b2, b1, b2],
        j: [pt(a), pt(b)],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edges_weld_seams_and_find_silhouettes() {
        // A quad split in two, with the shared diagonal's vertices duplicated (a seam).
        let p = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
        ];
        let faces = vec![[0, 1, 2], [4, 5, 3]];
        let e = mesh_edges(&p, &faces);
        assert_eq!(e.len(), 5);
        let inner: Vec<_> = e.iter().filter(|e| e.faces[1] != NONE).collect();
        assert_eq!(inner.len(), 1);
        assert!(!is_silhouette(
            inner[0],
            &p,
            &faces,
            Viewer::At([0.5, 0.5, 1.0])
        ));
        // Folded: the second face turned over; seen from above, the crease is a silhouette.
        let faces2 = vec![[0, 1, 2], [4, 3, 5]];
        let e2 = mesh_edges(&p, &faces2);
        let inner2 = e2.iter().find(|e| e.faces[1] != NONE).unwrap();
        assert!(is_silhouette(
            inner2,
            &p,
            &faces2,
            Viewer::At([0.5, 0.5, 1.0])
        ));
        assert!(is_silhouette(
            inner2,
            &p,
            &faces2,
            Viewer::Along([0.0, 0.0, -1.0])
        ));
    }

    #[test]
    fn cdf_samples_in_proportion() {
        let c = Cdf::new([(3, 1.0), (5, 0.0), (7, 3.0)].into_iter());
        assert_eq!(c.sample(0.1), (3, 0.25));
        assert_eq!(c.sample(0.26), (7, 0.75));
        assert_eq!(c.sample(0.999).0, 7);
        assert!(Cdf::new([(1, 0.0)].into_iter()).is_empty());
    }

    #[test]
    fn plane_hit_derivative_matches_finite_differences() {
        let r = [[0.1, -0.2, 0.0], [1.2, 0.1, 0.3], [-0.1, 0.9, 0.2]];
        let o = [0.3, 0.2, 2.0];
        let d = [0.05, 0.1, -1.0];
        let h0 = plane_hit(o, d, r).unwrap();
        let eps = 1e-6;
        for k in 0..3 {
            // Perturb o along axis k: d beta = j . do.
            let mut o2 = o;
            o2[k] += eps;
            let mut o1 = o;
            o1[k] -= eps;
            let (a, b) = (plane_hit(o2, d, r).unwrap(), plane_hit(o1, d, r).unwrap());
            for m in 1..3 {
                let num = (a.beta[m] - b.beta[m]) / (2.0 * eps);
                assert!((num - h0.j[m - 1][k]).abs() < 1e-7, "o {k} {m}");
            }
            // Perturb vertex 1: d beta = -beta_1 j . dr_1.
            let mut r2 = r;
            r2[1][k] += eps;
            let mut r1 = r;
            r1[1][k] -= eps;
            let (a, b) = (plane_hit(o, d, r2).unwrap(), plane_hit(o, d, r1).unwrap());
            for m in 1..3 {
                let num = (a.beta[m] - b.beta[m]) / (2.0 * eps);
                assert!(
                    (num + h0.beta[1] * h0.j[m - 1][k]).abs() < 1e-7,
                    "r {k} {m}"
                );
            }
            // Perturb the direction: d beta = t j . dD.
            let mut d2 = d;
            d2[k] += eps;
            let mut d1 = d;
            d1[k] -= eps;
            let (a, b) = (plane_hit(o, d2, r).unwrap(), plane_hit(o, d1, r).unwrap());
            for m in 1..3 {
                let num = (a.beta[m] - b.beta[m]) / (2.0 * eps);
                assert!((num - h0.t * h0.j[m - 1][k]).abs() < 1e-7, "d {k} {m}");
            }
        }
    }
}
