//! Convex polygons bounded by labelled lines, clipped by half-planes (Sutherland and Hodgman
//! 1974), with their area and first moments and the exact backward of both to the lines.
//!
//! A polygon is a cycle of edges, each lying on a line `l = (a, b, c)` of the pixel's line
//! table ([`Lines`]), `a x + b y + c >= 0` inside. Vertex `k` starts edge `k` and is the
//! intersection of the lines of edges `k - 1` and `k`: `h = l_{k-1} x l_k`,
//! `p = (h_0 / h_2, h_1 / h_2)`, so every vertex is a smooth function of two lines and the
//! area and moments are smooth functions of the lines, whose derivatives this module chains
//! back (the discrete form of Reynolds transport: only the edges' motion moves the integral).
//!
//! Robustness: a vertex within a relative `1e-10` of a clip line counts as on it (exactly on
//! it when the line is one of its own two lines, which makes shared mesh edges, exact
//! negatives of each other, split pixels consistently), no vertex is made between nearly
//! parallel lines (such vertices are merged), and pieces below [`MIN_AREA`] are dropped.

/// Pieces with a smaller area (in pixels) are dropped as rounding debris.
pub(crate) const MIN_AREA: f64 = 1e-13;

/// Relative distance under which a vertex counts as on a line.
const ON_TOL: f64 = 1e-10;

/// Relative sine under which two lines count as parallel.
const PARALLEL_TOL: f64 = 1e-12;

/// What a line of a pixel's table is, for the backward.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum LineKind {
    /// A side of the pixel square (constant).
    Pixel,
    /// Edge `k` (opposite vertex `k`) of face slot `f`, times `sign`.
    Edge { f: u32, k: u8, sign: f64 },
    /// `sign * D_f` plus a constant, `D_f` the NDC-depth plane of face slot `f` (near:
    /// `D_f + (0, 0, 1)`, far: `-D_f + (0, 0, 1)`, and their complements).
    Depth { f: u32, sign: f64 },
    /// `sign * (D_f - D_g)` (positive where face `g` is nearer than face `f`).
    DepthDiff { f: u32, g: u32, sign: f64 },
}

/// A pixel's line table: values and kinds.
#[derive(Default)]
pub(crate) struct Lines {
    pub val: Vec<[f64; 3]>,
    pub kind: Vec<LineKind>,
}

impl Lines {
    pub fn clear(&mut self) {
        self.val.clear();
        self.kind.clear();
    }
    pub fn push(&mut self, l: [f64; 3], kind: LineKind) -> u32 {
        self.val.push(l);
        self.kind.push(kind);
        (self.val.len() - 1) as u32
    }
    /// The complement of line `id` (`-l`), as a new entry.
    pub fn negated(&mut self, id: u32) -> u32 {
        let l = self.val[id as usize].map(|x| -x);
        let kind = match self.kind[id as usize] {
            LineKind::Pixel => LineKind::Pixel,
            LineKind::Edge { f, k, sign } => LineKind::Edge { f, k, sign: -sign },
            LineKind::Depth { f, sign } => LineKind::Depth { f, sign: -sign },
            LineKind::DepthDiff { f, g, sign } => LineKind::DepthDiff { f, g, sign: -sign },
        };
        self.push(l, kind)
    }
}

/// Polygons stored back to back: per vertex its position and the line of the edge it starts.
#[derive(Default)]
pub(crate) struct Polys {
    pub vert: Vec<[f64; 2]>,
    pub line: Vec<u32>,
}

/// A polygon of a [`Polys`] arena: `start..start + len`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Poly {
    pub start: u32,
    pub len: u32,
}

impl Polys {
    pub fn clear(&mut self) {
        self.vert.clear();
        self.line.clear();
    }

    /// The pixel square `[c, c + 1] x [r, r + 1]` (lines 0..4 of a fresh table, counter-
    /// clockwise in the y-down frame: inside is to the left of each directed edge).
    pub fn square(&mut self, lines: &mut Lines, col: f64, row: f64) -> Poly {
        let start = self.vert.len() as u32;
        // x >= c, y <= r + 1, x <= c + 1, y >= r.
        let l = [
            lines.push([1.0, 0.0, -col], LineKind::Pixel),
            lines.push([0.0, -1.0, row + 1.0], LineKind::Pixel),
            lines.push([-1.0, 0.0, col + 1.0], LineKind::Pixel),
            lines.push([0.0, 1.0, -row], LineKind::Pixel),
        ];
        // Vertex k starts edge k and ends edge k - 1.
        let v = [
            [col, row],
            [col, row + 1.0],
            [col + 1.0, row + 1.0],
            [col + 1.0, row],
        ];
        for k in 0..4 {
            self.vert.push(v[k]);
            self.line.push(l[k]);
        }
        Poly { start, len: 4 }
    }

    /// `p` clipped by the half-plane of line `h` (`l . (x, y, 1) >= 0`), appended to the
    /// arena; `None` when nothing of area remains. The second value says whether the clip
    /// cut anything off.
    pub fn clip(&mut self, lines: &Lines, p: Poly, h: u32) -> (Option<Poly>, bool) {
        let l = lines.val[h as usize];
        let n = p.len as usize;
        let s0 = p.start as usize;
        if n > 64 {
            // (Polygons never exceed 64 vertices: each clip adds at most one.)
            return (Some(p), false);
        }
        // Which edges lie on `l` itself (a shared mesh edge, either orientation): their
        // vertices count as on it, exactly.
        let mut on_l = [false; 64];
        for (k, o) in on_l[..n].iter_mut().enumerate() {
            *o = same_line(&lines.val[self.line[s0 + k] as usize], &l);
        }
        let mut cls = [0i8; 64];
        let mut any_out = false;
        let mut any_in = false;
        for k in 0..n {
            let c = if on_l[(k + n - 1) % n] || on_l[k] {
                0
            } else {
                let v = self.vert[s0 + k];
                let d = l[0] * v[0] + l[1] * v[1] + l[2];
                let scale = (l[0] * v[0]).abs() + (l[1] * v[1]).abs() + l[2].abs();
                if d.abs() <= ON_TOL * scale {
                    0
                } else if d > 0.0 {
                    1
                } else {
                    -1
                }
            };
            cls[k] = c;
            any_out |= c < 0;
            any_in |= c > 0;
        }
        if !any_out {
            return (Some(p), false);
        }
        if !any_in {
            return (None, true);
        }
        let start = self.vert.len();
        for k in 0..n {
            let (a, b) = (cls[k], cls[(k + 1) % n]);
            let (v, le) = (self.vert[s0 + k], self.line[s0 + k]);
            match a {
                1 => {
                    self.vert.push(v);
                    self.line.push(le);
                    if b < 0 {
                        let w = self.vert[s0 + (k + 1) % n];
                        let i = intersect(&lines.val[le as usize], &l).unwrap_or(w);
                        self.vert.push(i);
                        self.line.push(h);
                    }
                }
                0 => {
                    self.vert.push(v);
                    self.line.push(if b < 0 { h } else { le });
                }
                _ => {
                    if b > 0 {
                        let i = intersect(&lines.val[le as usize], &l).unwrap_or(v);
                        self.vert.push(i);
                        self.line.push(le);
                    }
                }
            }
        }
        let out = self.finish(lines, start, h);
        (out, true)
    }

    /// Whether every vertex of `p` lies outside the half-plane of line `h` or on its line
    /// (within the on-line tolerance of [`Polys::clip`]): `p` keeps nothing of area there.
    pub fn outside(&self, lines: &Lines, p: Poly, h: u32) -> bool {
        let l = lines.val[h as usize];
        self.vert[p.start as usize..(p.start + p.len) as usize]
            .iter()
            .all(|v| {
                let d = l[0] * v[0] + l[1] * v[1] + l[2];
                let scale = (l[0] * v[0]).abs() + (l[1] * v[1]).abs() + l[2].abs();
                d <= ON_TOL * scale
            })
    }

    /// Merges vertices between (nearly) parallel lines in the polygon that starts at `start`
    /// and runs to the end of the arena, just clipped by line `h`; `None` (and the polygon
    /// removed) when fewer than three vertices or less than [`MIN_AREA`] remain. Only a vertex
    /// on `h` can sit between parallel lines at first (the clipped polygon's other vertices
    /// keep their two lines, which were checked when they were made), so the first scan looks
    /// at those; after a merge, every vertex is looked at again.
    fn finish(&mut self, lines: &Lines, start: usize, h: u32) -> Option<Poly> {
        let mut changed = true;
        let mut only_h = true;
        while changed && self.vert.len() - start >= 3 {
            changed = false;
            let n = self.vert.len() - start;
            for k in 0..n {
                let prev = self.line[start + (k + n - 1) % n];
                let next = self.line[start + k];
                if only_h && prev != h && next != h {
                    continue;
                }
                let (a, b) = (&lines.val[prev as usize], &lines.val[next as usize]);
                if parallel(a, b) {
                    // Drop vertex k: edge k - 1 runs on to vertex k + 1.
                    self.vert.remove(start + k);
                    self.line.remove(start + k);
                    // Edge k - 1 keeps its own line.
                    changed = true;
                    only_h = false;
                    break;
                }
            }
        }
        let n = self.vert.len() - start;
        let p = Poly {
            start: start as u32,
            len: n as u32,
        };
        if n < 3 || self.area(p) < MIN_AREA {
            self.vert.truncate(start);
            self.line.truncate(start);
            return None;
        }
        Some(p)
    }

    /// Signed area (positive for the square's orientation).
    pub fn area(&self, p: Poly) -> f64 {
        self.moments(p)[0]
    }

    /// Area and first moments `(A, int x, int y)` by the shoelace formula.
    pub fn moments(&self, p: Poly) -> [f64; 3] {
        let (s, n) = (p.start as usize, p.len as usize);
        let (mut a, mut mx, mut my) = (0.0, 0.0, 0.0);
        for k in 0..n {
            let (v, w) = (self.vert[s + k], self.vert[s + (k + 1) % n]);
            let c = w[0] * v[1] - v[0] * w[1];
            a += c;
            mx += (v[0] + w[0]) * c;
            my += (v[1] + w[1]) * c;
        }
        [0.5 * a, mx / 6.0, my / 6.0]
    }

    /// Bounding box `[x0, x1, y0, y1]`.
    pub fn bbox(&self, p: Poly) -> [f64; 4] {
        let mut b = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        for v in &self.vert[p.start as usize..(p.start + p.len) as usize] {
            b[0] = b[0].min(v[0]);
            b[1] = b[1].max(v[0]);
            b[2] = b[2].min(v[1]);
            b[3] = b[3].max(v[1]);
        }
        b
    }

    /// The backward of [`Polys::moments`] through the vertices to the lines (values `lines`,
    /// indexed by the vertices' line ids): adds to `gline[id]` the gradient of
    /// `g . (A, Mx, My)`.
    pub fn moments_backward(
        &self,
        lines: &[[f64; 3]],
        p: Poly,
        g: [f64; 3],
        gline: &mut [[f64; 3]],
    ) {
        let (s, n) = (p.start as usize, p.len as usize);
        let mut gv = [[0.0f64; 2]; 64];
        if n > 64 {
            return;
        }
        let (ga, gx, gy) = (g[0] * 0.5, g[1] / 6.0, g[2] / 6.0);
        for k in 0..n {
            let k1 = (k + 1) % n;
            let (v, w) = (self.vert[s + k], self.vert[s + k1]);
            let c = w[0] * v[1] - v[0] * w[1];
            let gc = ga + gx * (v[0] + w[0]) + gy * (v[1] + w[1]);
            // c = w0 v1 - v0 w1.
            gv[k][0] += -gc * w[1] + gx * c;
            gv[k][1] += gc * w[0] + gy * c;
            gv[k1][0] += gc * v[1] + gx * c;
            gv[k1][1] += -gc * v[0] + gy * c;
        }
        for k in 0..n {
            let la = self.line[s + (k + n - 1) % n] as usize;
            let lb = self.line[s + k] as usize;
            let (a, b) = (lines[la], lines[lb]);
            let h = cross(&a, &b);
            if h[2] == 0.0 {
                continue;
            }
            let v = self.vert[s + k];
            let g = gv[k];
            // p = (h0 / h2, h1 / h2).
            let gh = [
                g[0] / h[2],
                g[1] / h[2],
                -(g[0] * v[0] + g[1] * v[1]) / h[2],
            ];
            let (dga, dgb) = (cross(&b, &gh), cross(&gh, &a));
            for i in 0..3 {
                gline[la][i] += dga[i];
                gline[lb][i] += dgb[i];
            }
        }
    }
}

/// `a x b`.
#[inline]
pub(crate) fn cross(a: &[f64; 3], b: &[f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `a . b`.
#[inline]
pub(crate) fn dot(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The intersection of two lines, `None` when they are parallel.
#[inline]
fn intersect(a: &[f64; 3], b: &[f64; 3]) -> Option<[f64; 2]> {
    if parallel(a, b) {
        return None;
    }
    let h = cross(a, b);
    let p = [h[0] / h[2], h[1] / h[2]];
    (p[0].is_finite() && p[1].is_finite()).then_some(p)
}

/// Whether two lines are (nearly) parallel: `|a0 b1 - a1 b0| <= tol |a_xy| |b_xy|`, the
/// norms the largest components (within `sqrt 2` of the Euclidean ones, and no `hypot` on the
/// polygon clipper's hot path; no squares, which underflow for tiny lines).
#[inline]
fn parallel(a: &[f64; 3], b: &[f64; 3]) -> bool {
    let s = a[0] * b[1] - a[1] * b[0];
    let na = a[0].abs().max(a[1].abs());
    let nb = b[0].abs().max(b[1].abs());
    !(s.abs() > PARALLEL_TOL * na * nb)
}

/// The same line, with either orientation, bit for bit (a mesh edge shared by two faces).
#[inline]
fn same_line(a: &[f64; 3], b: &[f64; 3]) -> bool {
    (a[0] == b[0] && a[1] == b[1] && a[2] == b[2])
        || (a[0] == -b[0] && a[1] == -b[1] && a[2] == -b[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_diagonal_halves_the_square_and_its_gradient_is_the_edge() {
        let mut lines = Lines::default();
        let mut polys = Polys::default();
        let sq = polys.square(&mut lines, 0.0, 0.0);
        assert_eq!(polys.moments(sq), [1.0, 0.5, 0.5]);
        // x + y <= 1 + t: l = (-1, -1, 1 + t).
        let t = 0.1;
        let h = lines.push([-1.0, -1.0, 1.0 + t], LineKind::Pixel);
        let (p, cut) = polys.clip(&lines, sq, h);
        let p = p.unwrap();
        assert!(cut);
        let m = polys.moments(p);
        let exact = 1.0 - 0.5 * (1.0 - t) * (1.0 - t);
        assert!((m[0] - exact).abs() < 1e-15, "{m:?}");
        // dA/dc = length of the cut / |grad l| = (1 - t) sqrt(2) / sqrt(2).
        let mut g = vec![[0.0; 3]; lines.val.len()];
        polys.moments_backward(&lines.val, p, [1.0, 0.0, 0.0], &mut g);
        assert!(
            (g[h as usize][2] - (1.0 - t)).abs() < 1e-14,
            "{:?}",
            g[h as usize]
        );
        // Moments against central differences in c.
        let eps = 1e-6;
        let mom = |c: f64| {
            let mut lines = Lines::default();
            let mut polys = Polys::default();
            let sq = polys.square(&mut lines, 0.0, 0.0);
            let h = lines.push([-1.0, -1.0, c], LineKind::Pixel);
            let p = polys.clip(&lines, sq, h).0.unwrap();
            polys.moments(p)
        };
        let (a, b) = (mom(1.0 + t + eps), mom(1.0 + t - eps));
        for i in 0..3 {
            let mut g = vec![[0.0; 3]; lines.val.len()];
            let mut w = [0.0; 3];
            w[i] = 1.0;
            polys.moments_backward(&lines.val, p, w, &mut g);
            let fd = (a[i] - b[i]) / (2.0 * eps);
            assert!(
                (g[h as usize][2] - fd).abs() < 1e-8,
                "{i}: {} {fd}",
                g[h as usize][2]
            );
        }
    }

    #[test]
    fn a_shared_edge_splits_without_slivers() {
        let mut lines = Lines::default();
        let mut polys = Polys::default();
        let sq = polys.square(&mut lines, 0.0, 0.0);
        let l = [0.3, -1.0, 0.4];
        let a = lines.push(l, LineKind::Pixel);
        let b = lines.push(l.map(|x| -x), LineKind::Pixel);
        let pa = polys.clip(&lines, sq, a).0.unwrap();
        let pb = polys.clip(&lines, sq, b).0.unwrap();
        let total = polys.area(pa) + polys.area(pb);
        assert!((total - 1.0).abs() < 1e-15);
        // Clipping a piece by its own edge's complement leaves nothing.
        assert!(polys.clip(&lines, pa, b).0.is_none());
        assert!(!polys.clip(&lines, pa, a).1);
    }
}
