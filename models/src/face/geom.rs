//! Mesh tools for building the face basis, all in `f64` and deterministic: edge graphs,
//! geodesic (Dijkstra) distances, smooth compact kernels, harmonic interpolation, loop
//! flood fills and Gram-Schmidt.

use std::cmp::Ordering;
use std::collections::{BTreeSet, BinaryHeap};

pub type V3 = [f64; 3];

pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
pub fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
pub fn norm(a: V3) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}
pub fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Centroid of a set of vertices.
pub fn centroid(p: &[V3], set: &[usize]) -> V3 {
    let mut c = [0.0; 3];
    for &i in set {
        c = add(c, p[i]);
    }
    scale(c, 1.0 / set.len() as f64)
}

/// Weighted undirected edge graph: `adj[v]` = (neighbour, edge length), sorted by neighbour.
pub struct Graph {
    pub adj: Vec<Vec<(usize, f64)>>,
}

impl Graph {
    /// Edges of the triangles not excluded.
    pub fn new(p: &[V3], faces: &[[usize; 3]], exclude: &[bool]) -> Graph {
        let mut sets: Vec<BTreeSet<usize>> = vec![BTreeSet::new(); p.len()];
        for (f, t) in faces.iter().enumerate() {
            if exclude.get(f).copied().unwrap_or(false) {
                continue;
            }
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                sets[a].insert(b);
                sets[b].insert(a);
            }
        }
        let adj = sets
            .iter()
            .enumerate()
            .map(|(a, s)| s.iter().map(|&b| (b, norm(sub(p[a], p[b])))).collect())
            .collect();
        Graph { adj }
    }

    /// Shortest-path distance along edges from the nearest seed (0 on the seeds).
    pub fn geodesic(&self, seeds: &[usize]) -> Vec<f64> {
        #[derive(PartialEq)]
        struct Item(f64, usize);
        impl Eq for Item {}
        impl PartialOrd for Item {
            fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
                Some(self.cmp(o))
            }
        }
        impl Ord for Item {
            fn cmp(&self, o: &Self) -> Ordering {
                // Min-heap on distance, ties by vertex index: deterministic.
                o.0.total_cmp(&self.0).then(o.1.cmp(&self.1))
            }
        }
        let mut d = vec![f64::INFINITY; self.adj.len()];
        let mut heap = BinaryHeap::new();
        for &s in seeds {
            d[s] = 0.0;
            heap.push(Item(0.0, s));
        }
        while let Some(Item(dist, v)) = heap.pop() {
            if dist > d[v] {
                continue;
            }
            for &(w, len) in &self.adj[v] {
                let nd = dist + len;
                if nd < d[w] {
                    d[w] = nd;
                    heap.push(Item(nd, w));
                }
            }
        }
        d
    }

    /// Smooth compact kernel of the geodesic distance to `seeds`:
    /// `(1 - (d / radius)^2)^3` inside the radius, 0 outside (1 with zero slope on the seeds).
    pub fn kernel(&self, seeds: &[usize], radius: f64) -> Vec<f64> {
        self.geodesic(seeds)
            .iter()
            .map(|&d| falloff(d, radius))
            .collect()
    }

    /// Harmonic interpolation of `K`-vectors: vertices with `Some` keep their value, the
    /// others solve the graph Laplace equation with inverse-edge-length weights. Every
    /// connected part of the free vertices must touch a fixed vertex.
    pub fn harmonic<const K: usize>(&self, fixed: &[Option<[f64; K]>]) -> Vec<[f64; K]> {
        let n = self.adj.len();
        let free: Vec<usize> = (0..n).filter(|&v| fixed[v].is_none()).collect();
        let mut pos = vec![usize::MAX; n];
        for (i, &v) in free.iter().enumerate() {
            pos[v] = i;
        }
        let m = free.len();
        let mut a = vec![0.0; m * m];
        let mut rhs = vec![[0.0; K]; m];
        for (i, &v) in free.iter().enumerate() {
            for &(w, len) in &self.adj[v] {
                let wt = 1.0 / len.max(1e-9);
                a[i * m + i] += wt;
                match fixed[w] {
                    Some(x) => {
                        for k in 0..K {
                            rhs[i][k] += wt * x[k];
                        }
                    }
                    None => a[i * m + pos[w]] -= wt,
                }
            }
        }
        let sol = cholesky_solve(&mut a, m, rhs);
        let mut out: Vec<[f64; K]> = fixed.iter().map(|f| f.unwrap_or([0.0; K])).collect();
        for (i, &v) in free.iter().enumerate() {
            out[v] = sol[i];
        }
        out
    }
}

/// `(1 - (d / r)^2)^3` for `d < r`, else 0.
pub fn falloff(d: f64, r: f64) -> f64 {
    if d >= r {
        0.0
    } else {
        let t = 1.0 - (d / r) * (d / r);
        t * t * t
    }
}

/// `3 t^2 - 2 t^3` of `t` clamped to [0, 1].
pub fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Solves `A x = b` for a symmetric positive definite `A` (row-major `n x n`, overwritten).
fn cholesky_solve<const K: usize>(a: &mut [f64], n: usize, mut b: Vec<[f64; K]>) -> Vec<[f64; K]> {
    for j in 0..n {
        let mut s = a[j * n + j];
        for k in 0..j {
            s -= a[j * n + k] * a[j * n + k];
        }
        assert!(
            s > 0.0,
            "harmonic system is singular: a free part touches no fixed vertex"
        );
        let d = s.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    // Forward then backward substitution, K right-hand sides at once.
    for i in 0..n {
        let mut s = b[i];
        for j in 0..i {
            let l = a[i * n + j];
            for (sk, bk) in s.iter_mut().zip(b[j]) {
                *sk -= l * bk;
            }
        }
        b[i] = s.map(|x| x / a[i * n + i]);
    }
    for i in (0..n).rev() {
        let mut s = b[i];
        for j in i + 1..n {
            let l = a[j * n + i];
            for (sk, bk) in s.iter_mut().zip(b[j]) {
                *sk -= l * bk;
            }
        }
        b[i] = s.map(|x| x / a[i * n + i]);
    }
    b
}

/// Triangles reached from `seed` without crossing an edge of the closed vertex loop `lp`
/// (consecutive entries and last-first are the loop's edges).
pub fn inside_loop(faces: &[[usize; 3]], lp: &[usize], seed: usize) -> Vec<usize> {
    let mut cut = BTreeSet::new();
    for i in 0..lp.len() {
        let (a, b) = (lp[i], lp[(i + 1) % lp.len()]);
        cut.insert((a.min(b), a.max(b)));
    }
    // Edge -> faces.
    let mut edge_faces: std::collections::BTreeMap<(usize, usize), Vec<usize>> = Default::default();
    for (f, t) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            edge_faces.entry((a.min(b), a.max(b))).or_default().push(f);
        }
    }
    let mut seen = vec![false; faces.len()];
    let mut stack = vec![seed];
    seen[seed] = true;
    let mut out = vec![];
    while let Some(f) = stack.pop() {
        out.push(f);
        let t = faces[f];
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let e = (a.min(b), a.max(b));
            if cut.contains(&e) {
                continue;
            }
            for &g in &edge_faces[&e] {
                if !seen[g] {
                    seen[g] = true;
                    stack.push(g);
                }
            }
        }
    }
    out.sort_unstable();
    out
}

/// Modified Gram-Schmidt (twice, for accuracy) of `fields` in order. Returns the
/// orthonormal vectors and, for each, `r_kk`: the norm of the part of field `k` that the
/// earlier ones do not explain. `prefix` vectors (already orthonormal) are projected out
/// first and not returned.
/// Fails with the index of the first field that (numerically) lies in the span of the
/// earlier ones.
pub fn gram_schmidt(
    prefix: &[Vec<f64>],
    fields: &[Vec<f64>],
) -> Result<(Vec<Vec<f64>>, Vec<f64>), usize> {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut basis: Vec<Vec<f64>> = prefix.to_vec();
    let mut r = Vec::with_capacity(fields.len());
    for (k, f) in fields.iter().enumerate() {
        let mut v = f.clone();
        for _pass in 0..2 {
            for q in &basis {
                let c = dot(&v, q);
                for (x, y) in v.iter_mut().zip(q) {
                    *x -= c * y;
                }
            }
        }
        let n = dot(&v, &v).sqrt();
        // (Written so that a NaN norm also fails.)
        if n.is_nan() || n <= 1e-6 * dot(f, f).sqrt() {
            return Err(k);
        }
        for x in v.iter_mut() {
            *x /= n;
        }
        r.push(n);
        basis.push(v);
    }
    Ok((basis.split_off(prefix.len()), r))
}
