//! DEODR: discontinuity edge overdraw (M. de La Gorce, D. J. Fleet and N. Paragios,
//! "Model-Based 3D Hand Pose Estimation from Monocular Video", TPAMI 2011, section 4; the
//! antialiasing of P. V. Sander et al., "Discontinuity Edge Overdraw", I3D 2001; section 4.4 of
//! H. Kato et al., "Differentiable Rendering: A Survey", 2020).
//!
//! # Forward
//!
//! 1. The hard render of the per-vertex attributes (z-buffer, one fragment per pixel, alpha =
//!    coverage), bit-identical to `rasterize` + `interpolate` + `blend_hard`.
//! 2. Every *silhouette edge* is overdrawn with a linear ramp `overdraw_px` pixels wide on its
//!    outer side. An edge is a silhouette edge when exactly one of the faces that share it is
//!    front-facing (counter-clockwise in NDC): mesh boundary edges of front faces, and edges
//!    between a front and a back face. Faces with a vertex at `w <= 0` make their edges
//!    ineligible (the near plane is not a silhouette).
//!
//!    For an edge from `p0` to `p1` (pixel coordinates, pixel centres at integers) with unit
//!    normal `n` pointing away from the face's third vertex, a pixel centre `p` has the edge
//!    coordinates `t = e . (p - p0) / |e|^2` (`e = p1 - p0`) and `s = n . (p - p0)`. Where
//!    `0 <= t <= 1`, `0 <= s < overdraw_px`, and the edge's NDC depth `z(t)` (affine in screen
//!    space) is nearer than the z-buffer, the pixel is blended
//!
//!    `I <- T I + (1 - T) A(t)`, `T = s / overdraw_px`,
//!
//!    with `A(t)` the edge's attributes at `t` (perspective-correct along the edge when the
//!    settings say so, as the face's own interpolation at the edge, so that the image does not
//!    jump when a pixel centre crosses the edge), and the alpha channel blended towards 1. Edges
//!    are drawn in the order of DEODR: faces from the farthest to the nearest by the sum of
//!    their vertices' depths (ties by face index), each face's edges in order; the overdraw does
//!    not write the z-buffer.
//!
//! The result is continuous in the vertex positions wherever a pixel centre crosses a
//! silhouette edge (the ramp starts at the edge's own colour) and where it leaves the ramp
//! (`T = 1`), so its derivative carries the silhouette gradient. As in DEODR, the ramps are
//! rectangles: in the wedge outside a silhouette vertex where two ramps meet, a pixel centre
//! entering a ramp's end cap (`t = 0` or `1`) still jumps (tested: away from silhouette
//! vertices, a sweep in steps of 1e-4 px changes no value by more than 1e-4).
//!
//! # Backward
//!
//! The exact derivative of that forward (the method is exact, not approximate): per image row,
//! the overdraw layers of each pixel are replayed in reverse, giving `dL/dT`, `dL/dA` per layer
//! and the gradient reaching the hard image; `T` and `A(t)` are differentiated with respect to
//! the edge's screen positions (and `w` for the perspective-correct weights), the hard image
//! through the rasterizer's barycentric backward ([`crate::raster::rasterize_backward`]'s
//! factored per-run form, one pass over the fragments with the attribute gradients) and the
//! attributes exactly. Depth tests, coverage and the edge set are piecewise constant and carry
//! no gradient.
//!
//! Only the pixels a ramp touches are converted to `f64`: the forward overdraws the hard render
//! in place and keeps the touched pixels' previous values (a few per silhouette crossing of a
//! row), from which the backward replays the layers; the gradient reaching the hard render is
//! passed on as `dL/dI` with those pixels replaced, so no image-sized copy is made.
//!
//! Differences from DEODR 0.2.3: DEODR requires back-face culling and differentiates only
//! screen-space (affine) interpolation; here both follow the settings (set
//! `cull_backfaces = true`, `perspective_correct = false` to match it). DEODR's scanline
//! fill rule and ours (top-left) can differ on pixel centres exactly on an edge.
//!
//! Deterministic: rows are processed in parallel, each row's edges in the global order, and
//! contributions are reduced in row order.

use std::cmp::Ordering;
use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::{
    bin_by_lines, cross2, edge_weights, hard_render_grad, prepare, render_hard, sub, tensor_f64,
    ApproxSettings, Screen,
};
use crate::error::RenderError;
use crate::raster::Fragments;

/// Renders per-vertex attributes `[V, C]` over the faces from clip positions `[V, 4]` with
/// DEODR's discontinuity edge overdraw: an image `[H, W, C + 1]` (attributes over the
/// background, then the coverage, both antialiased along silhouette edges). See the
/// [module documentation](self).
///
/// # Errors
/// Clip positions not `[V, 4]`, attributes not `[V, C]`, a background of another length than
/// `C` or not finite, `overdraw_px` negative or not finite, and the rasterizer's errors.
pub fn deodr<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &ApproxSettings,
) -> Result<Var<'t, T>, RenderError> {
    if !(settings.overdraw_px.is_finite() && settings.overdraw_px >= 0.0) {
        return Err(AutodiffError::invalid(
            "deodr",
            format!(
                "overdraw_px must be finite and >= 0, got {}",
                settings.overdraw_px
            ),
        )
        .into());
    }
    let (fragments, background) = prepare("deodr", clip, attrs, &faces, settings)?;
    let screen = Screen::new(&*clip.value()?, settings.width, settings.height);
    let edges = if settings.overdraw_px > 0.0 {
        silhouette_edges(&screen, &faces, settings.overdraw_px)
    } else {
        EdgeSet::empty(settings.height)
    };
    let op = DeodrOp {
        fragments,
        faces,
        settings: settings.clone(),
        background,
        screen,
        edges,
        hard_px: Vec::new(),
    };
    Ok(clip.tape().apply(op, &[clip, attrs]))
}

/// One silhouette edge in screen space.
#[derive(Clone, Debug)]
pub(crate) struct Edge {
    /// Vertex indices of its endpoints.
    pub v: [u32; 2],
    /// The (front) face it belongs to.
    pub face: u32,
    /// Endpoints `(col, row)`.
    pub p0: [f64; 2],
    pub e: [f64; 2],
    /// `|e|^2` and `|e|`.
    pub len2: f64,
    pub len: f64,
    /// Unit normal pointing away from the face (the side that is overdrawn).
    pub n: [f64; 2],
    /// `+1` or `-1`: `n = sgn (-e_y, e_x) / |e|`.
    pub sgn: f64,
    /// NDC depth at the endpoints.
    pub z: [f64; 2],
    /// `1 / w` at the endpoints.
    pub q: [f64; 2],
}

/// The silhouette edges in drawing order, and for each image row the edges whose ramp may
/// reach it (in drawing order).
pub(crate) struct EdgeSet {
    pub edges: Vec<Edge>,
    /// CSR over rows: `row_edges[row_start[r]..row_start[r + 1]]`.
    row_start: Vec<usize>,
    row_edges: Vec<u32>,
}

impl EdgeSet {
    pub fn empty(height: usize) -> Self {
        EdgeSet {
            edges: Vec::new(),
            row_start: vec![0; height + 1],
            row_edges: Vec::new(),
        }
    }

    pub fn row(&self, r: usize) -> &[u32] {
        &self.row_edges[self.row_start[r]..self.row_start[r + 1]]
    }
}

/// Finds the silhouette edges (exactly one front-facing face among those sharing the edge, no
/// face with a vertex at `w <= 0`), orders them as DEODR draws them and bins them by row.
pub(crate) fn silhouette_edges(screen: &Screen, faces: &[[u32; 3]], sigma: f64) -> EdgeSet {
    // Per face: front-facing (counter-clockwise in NDC, i.e. clockwise in pixel coordinates
    // whose rows go down), or invalid (a vertex at w <= 0 or not finite).
    #[derive(Clone, Copy, PartialEq)]
    enum Kind {
        Front,
        Other,
        Invalid,
    }
    // A vertex is usable when it is in front of the eye (w > 0) with a finite position.
    let usable: Vec<bool> = (0..screen.px.len())
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| screen.w[i] > 0.0 && screen.px[i].iter().all(|x| x.is_finite()))
        .collect();
    let kind: Vec<Kind> = faces
        .par_iter()
        .with_min_len(4096)
        .map(|&f| {
            if !f.iter().all(|&i| usable[i as usize]) {
                return Kind::Invalid;
            }
            let v = f.map(|i| screen.px[i as usize]);
            if cross2(sub(v[1], v[0]), sub(v[2], v[0])) < 0.0 {
                Kind::Front
            } else {
                Kind::Other
            }
        })
        .collect();
    let face_depth = |fk: u32| -> f64 {
        faces[fk as usize / 3]
            .iter()
            .map(|&v| screen.clip[v as usize][2] / screen.w[v as usize])
            .sum()
    };
    // The undirected edges of front and invalid faces, listed under their lower vertex (`(higher
    // vertex, face * 3 + k)` per entry): an edge of a front face is a silhouette edge when no
    // other entry of its lower vertex has the same higher vertex. Each block of lower vertices
    // scans all faces for its own entries, in parallel; the edges found are sorted below, so
    // their order here does not matter.
    let nv = screen.px.len();
    let listed = kind.iter().filter(|&&k| k != Kind::Other).count();
    let blocks = rayon::current_num_threads().min(nv / 1024).max(1);
    let per = nv.div_ceil(blocks).max(1);
    let mut sil: Vec<(f64, u32)> = (0..blocks)
        .into_par_iter()
        .flat_map_iter(|b| {
            let vr = b * per..((b + 1) * per).min(nv);
            // Per vertex of the block its last entry, and per entry its higher vertex, face
            // edge and the previous entry of the same lower vertex (`u32::MAX`: none).
            let mut head = vec![u32::MAX; vr.len()];
            let mut ent: Vec<(u32, u32, u32)> = Vec::with_capacity(3 * listed / blocks + 64);
            for (fi, f) in faces.iter().enumerate() {
                if kind[fi] == Kind::Other {
                    continue;
                }
                for k in 0..3 {
                    let (a, b) = (f[k], f[(k + 1) % 3]);
                    let lo = a.min(b) as usize;
                    if vr.contains(&lo) {
                        let h = &mut head[lo - vr.start];
                        ent.push((a.max(b), (fi * 3 + k) as u32, *h));
                        *h = (ent.len() - 1) as u32;
                    }
                }
            }
            let mut out = Vec::new();
            let mut list: Vec<(u32, u32)> = Vec::new();
            for &h in &head {
                list.clear();
                let mut j = h;
                while j != u32::MAX {
                    let (hi, fk, next) = ent[j as usize];
                    list.push((hi, fk));
                    j = next;
                }
                for (m, &(hi, fk)) in list.iter().enumerate() {
                    if kind[fk as usize / 3] == Kind::Front
                        && !list
                            .iter()
                            .enumerate()
                            .any(|(l, &(h2, _))| l != m && h2 == hi)
                    {
                        out.push((face_depth(fk), fk));
                    }
                }
            }
            out
        })
        .collect();
    // DEODR's order: farthest face first (sum of depths), then face index and edge.
    sil.sort_unstable_by(|a, b| match b.0.total_cmp(&a.0) {
        Ordering::Equal => a.1.cmp(&b.1),
        o => o,
    });
    let height = screen.height;
    let mut edges = Vec::with_capacity(sil.len());
    let mut rows: Vec<Option<(usize, usize)>> = Vec::with_capacity(sil.len());
    for &(_, fk) in &sil {
        let f = faces[fk as usize / 3];
        let k = fk as usize % 3;
        let (a, b, c) = (f[k], f[(k + 1) % 3], f[(k + 2) % 3]);
        let (p0, p1, pc) = (
            screen.px[a as usize],
            screen.px[b as usize],
            screen.px[c as usize],
        );
        let e = sub(p1, p0);
        let len2 = e[0] * e[0] + e[1] * e[1];
        if !(len2 > 0.0 && len2.is_finite()) {
            continue;
        }
        let len = len2.sqrt();
        // Away from the third vertex.
        let sgn = if cross2(e, sub(pc, p0)) > 0.0 {
            -1.0
        } else {
            1.0
        };
        let n = [-sgn * e[1] / len, sgn * e[0] / len];
        let ys = [p0[1], p1[1], p0[1] + sigma * n[1], p1[1] + sigma * n[1]];
        let ymin = ys.iter().copied().fold(f64::INFINITY, f64::min).ceil();
        let ymax = ys.iter().copied().fold(f64::NEG_INFINITY, f64::max).floor();
        let r0 = ymin.max(0.0);
        let r1 = ymax.min(height as f64 - 1.0);
        if !(r0 <= r1) {
            continue;
        }
        rows.push(Some((r0 as usize, r1 as usize)));
        edges.push(Edge {
            v: [a, b],
            face: fk / 3,
            p0,
            e,
            len2,
            len,
            n,
            sgn,
            z: [a, b].map(|v| screen.clip[v as usize][2] / screen.w[v as usize]),
            q: [a, b].map(|v| 1.0 / screen.w[v as usize]),
        });
    }
    let (row_start, row_edges) = bin_by_lines(&rows, height);
    EdgeSet {
        edges,
        row_start,
        row_edges,
    }
}

/// Where an edge's ramp covers pixel centre `(x, row)`: its coordinates `t` along the edge and
/// `s` across it.
#[inline]
pub(crate) fn edge_coords(e: &Edge, x: f64, row: f64) -> (f64, f64) {
    let d = [x - e.p0[0], row - e.p0[1]];
    let t = (e.e[0] * d[0] + e.e[1] * d[1]) / e.len2;
    let s = e.n[0] * d[0] + e.n[1] * d[1];
    (t, s)
}

/// The columns of row `row` whose centres may lie in the ramp of `e` (`0 <= t <= 1`,
/// `0 <= s <= sigma`), clamped to the image; the exact test is made per pixel.
pub(crate) fn column_range(e: &Edge, row: f64, sigma: f64, width: usize) -> Option<(usize, usize)> {
    let (mut lo, mut hi) = (0.0f64, width as f64 - 1.0);
    // t(x) = (e_x (x - x0) + e_y (row - y0)) / len2 and s(x) = n_x (x - x0) + n_y (row - y0):
    // each is affine in x; keep the x where it lies in its interval.
    let dy = row - e.p0[1];
    for (slope, base, a, b) in [
        (e.e[0] / e.len2, e.e[1] * dy / e.len2, 0.0, 1.0),
        (e.n[0], e.n[1] * dy, 0.0, sigma),
    ] {
        if slope == 0.0 {
            if !(base >= a - 1e-12 && base <= b + 1e-12) {
                return None;
            }
            continue;
        }
        let x1 = e.p0[0] + (a - base) / slope;
        let x2 = e.p0[0] + (b - base) / slope;
        let (l, h) = if x1 < x2 { (x1, x2) } else { (x2, x1) };
        lo = lo.max(l.floor());
        hi = hi.min(h.ceil());
    }
    (lo <= hi).then_some((lo as usize, hi as usize))
}

/// `f64` copies of the pixels of one image row that the overdraw touches, made on first touch
/// from the row's values (`C + 1` per pixel) and written back at the end: rows are converted
/// only where a ramp reaches.
struct Touched {
    /// Per column: index into `xs` of its copy, or `u32::MAX`.
    slot: Vec<u32>,
    /// Touched columns, in order of first touch.
    xs: Vec<u32>,
    /// Their values, `C + 1` each.
    vals: Vec<f64>,
    /// Their values at first touch, when `keep` is set.
    orig: Vec<f64>,
    keep: bool,
    c1: usize,
}

/// The pixels of one row that the overdraw touched: columns in order of first touch, and
/// `C + 1` values each (the hard render's, kept by the forward for the backward's replay; or
/// `dL/dI` of the hard render, from the backward).
#[derive(Default)]
struct RowPixels {
    xs: Vec<u32>,
    vals: Vec<f64>,
}

impl RowPixels {
    /// The same pixels in increasing column order (`c1` values each).
    fn sorted(self, c1: usize) -> Self {
        if self.xs.is_sorted() {
            return self;
        }
        let mut order: Vec<usize> = (0..self.xs.len()).collect();
        order.sort_unstable_by_key(|&k| self.xs[k]);
        RowPixels {
            xs: order.iter().map(|&k| self.xs[k]).collect(),
            vals: order
                .iter()
                .flat_map(|&k| &self.vals[k * c1..(k + 1) * c1])
                .copied()
                .collect(),
        }
    }
}

impl Touched {
    fn new(width: usize, c1: usize, keep: bool) -> Self {
        Touched {
            slot: vec![u32::MAX; width],
            xs: Vec::new(),
            vals: Vec::new(),
            orig: Vec::new(),
            keep,
            c1,
        }
    }

    /// Starts from the pixels of `pre` (their values as copies), so that `get` never reads
    /// the row for them.
    fn preload(&mut self, pre: &RowPixels) {
        for (k, &x) in pre.xs.iter().enumerate() {
            self.slot[x as usize] = k as u32;
        }
        self.xs.extend_from_slice(&pre.xs);
        self.vals.extend_from_slice(&pre.vals);
    }

    /// The copy of column `x` of `src` (the row's values), made on first touch (`src` is not
    /// read for preloaded columns).
    #[inline]
    fn get<T: Real>(&mut self, src: &[T], x: usize) -> &mut [f64] {
        let c1 = self.c1;
        let k = if self.slot[x] == u32::MAX {
            let k = self.xs.len();
            self.slot[x] = k as u32;
            self.xs.push(x as u32);
            let v = &src[x * c1..(x + 1) * c1];
            self.vals.extend(v.iter().map(|v| v.to_f64c()));
            if self.keep {
                self.orig.extend(v.iter().map(|v| v.to_f64c()));
            }
            k
        } else {
            self.slot[x] as usize
        };
        &mut self.vals[k * c1..(k + 1) * c1]
    }

    /// Writes the copies into `dst` (the row) when `dst` is given, and forgets them. Returns
    /// the touched pixels with their values at first touch when `keep` is set, else with
    /// their current values.
    fn finish<T: Real>(&mut self, dst: Option<&mut [T]>) -> RowPixels {
        let c1 = self.c1;
        if let Some(dst) = dst {
            for (k, &x) in self.xs.iter().enumerate() {
                let x = x as usize;
                for (o, &v) in dst[x * c1..(x + 1) * c1]
                    .iter_mut()
                    .zip(&self.vals[k * c1..(k + 1) * c1])
                {
                    *o = T::from_f64c(v);
                }
            }
        }
        self.unmark();
        // Exact-size copies: the buffers stay with the scratch for the next row (handing them
        // over would regrow them from empty on every row).
        let out = RowPixels {
            xs: self.xs.clone(),
            vals: if self.keep {
                self.orig.clone()
            } else {
                self.vals.clone()
            },
        };
        self.xs.clear();
        self.vals.clear();
        self.orig.clear();
        out
    }

    /// Forgets the copies, keeping the buffers for the next row.
    fn reset(&mut self) {
        self.unmark();
        self.xs.clear();
        self.vals.clear();
        self.orig.clear();
    }

    fn unmark(&mut self) {
        for &x in &self.xs {
            self.slot[x as usize] = u32::MAX;
        }
    }
}

/// Per-thread scratch of the backward's rows.
struct RowScratch {
    hard: Touched,
    grad: Touched,
    layers: Vec<Layer>,
    saved: Vec<f64>,
}

/// One overdraw layer of a pixel, recorded for the backward.
struct Layer {
    x: usize,
    edge: u32,
    t: f64,
    tr: f64,
    /// Offset of the pixel's value before this layer in the row's `before` buffer.
    before: usize,
}

/// A row's gradient contributions: `(vertex, d/d(col, row), d/dw)` for positions, and for
/// attributes the vertex of each entry with its `C` values `dL/dA[vertex, ..]`.
#[derive(Default)]
struct RowGrad {
    pos: Vec<(u32, [f64; 3])>,
    attr_vertex: Vec<u32>,
    attr_grad: Vec<f64>,
}

struct DeodrOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: ApproxSettings,
    background: Vec<T>,
    screen: Screen,
    edges: EdgeSet,
    /// Per image row, the hard render's values at the pixels the overdraw touched, kept by
    /// the forward for the backward's replay.
    hard_px: Vec<RowPixels>,
}

impl<T: Real> DeodrOp<T> {
    /// NDC depth of pixel `p`'s nearest fragment (infinity where uncovered): the z-buffer the
    /// overdraw tests against.
    #[inline]
    fn depth(&self, p: usize) -> f64 {
        let fr = &self.fragments;
        let (s, e) = (fr.offsets[p], fr.offsets[p + 1]);
        if s < e {
            fr.depth[s as usize].to_f64c()
        } else {
            f64::INFINITY
        }
    }

    /// Overdraws row `row` of the image (`src`: that row, `W * (C + 1)` values, the hard render)
    /// into the `f64` copies `out` of the pixels it touches, calling `layer` after each blend
    /// with the pixel value it replaced.
    fn overdraw_row(
        &self,
        attrs: &[f64],
        row: usize,
        src: &[T],
        out: &mut Touched,
        mut layer: impl FnMut(Layer, &[f64]),
    ) {
        let c = self.background.len();
        let w = self.settings.width;
        let sigma = self.settings.overdraw_px;
        let persp = self.settings.perspective_correct;
        let rf = row as f64;
        let mut before = vec![0.0; c + 1];
        for &ei in self.edges.row(row) {
            let e = &self.edges.edges[ei as usize];
            let Some((x0, x1)) = column_range(e, rf, sigma, w) else {
                continue;
            };
            for x in x0..=x1 {
                let (t, s) = edge_coords(e, x as f64, rf);
                if !((0.0..=1.0).contains(&t) && s >= 0.0 && s < sigma) {
                    continue;
                }
                let z = e.z[0] + t * (e.z[1] - e.z[0]);
                if !(z < self.depth(row * w + x)) {
                    continue;
                }
                let tr = s / sigma;
                let (wt, _) = edge_weights(e.q, t, persp);
                let px = out.get(src, x);
                before.copy_from_slice(px);
                for ch in 0..c {
                    let a = wt[0] * attrs[e.v[0] as usize * c + ch]
                        + wt[1] * attrs[e.v[1] as usize * c + ch];
                    px[ch] = tr * px[ch] + (1.0 - tr) * a;
                }
                px[c] = tr * px[c] + (1.0 - tr);
                layer(
                    Layer {
                        x,
                        edge: ei,
                        t,
                        tr,
                        before: 0,
                    },
                    &before,
                );
            }
        }
    }

    /// The backward of one row: from `g` (`dL/dI` of the row's final values) to the per-edge
    /// contributions and `dL/dI` of the hard render at the pixels the overdraw touched (the
    /// others pass `g` through unchanged). `hard` holds the hard render's values at those
    /// pixels, kept by the forward.
    fn backward_row(
        &self,
        attrs: &[f64],
        hard_px: &RowPixels,
        row: usize,
        g: &[T],
        sc: &mut RowScratch,
    ) -> (RowGrad, RowPixels) {
        let c = self.background.len();
        let sigma = self.settings.overdraw_px;
        let persp = self.settings.perspective_correct;
        let RowScratch {
            hard,
            grad,
            layers,
            saved,
        } = sc;
        layers.clear();
        saved.clear();
        // The replay touches exactly the forward's pixels, all preloaded: the row itself is
        // not read.
        hard.preload(hard_px);
        self.overdraw_row(attrs, row, &[] as &[T], hard, |mut l, before| {
            l.before = saved.len();
            saved.extend_from_slice(before);
            layers.push(l);
        });
        hard.reset();
        // At most two entries per layer: sized once, no regrowth.
        let n = 2 * layers.len();
        let mut out = RowGrad {
            pos: Vec::with_capacity(n),
            attr_vertex: Vec::with_capacity(n),
            attr_grad: Vec::with_capacity(n * c),
        };
        let rf = row as f64;
        let mut ga = vec![0.0; c];
        for l in layers.iter().rev() {
            let e = &self.edges.edges[l.edge as usize];
            let gp = grad.get(g, l.x);
            let before = &saved[l.before..l.before + c + 1];
            let (wt, den) = edge_weights(e.q, l.t, persp);
            // I = T before + (1 - T) A: dL/dA = (1 - T) g, dL/dT = g . (before - A).
            let mut gtr = gp[c] * (before[c] - 1.0);
            let (mut gt, mut gq0, mut gq1) = (0.0, 0.0, 0.0);
            for ch in 0..c {
                let a0 = attrs[e.v[0] as usize * c + ch];
                let a1 = attrs[e.v[1] as usize * c + ch];
                let a = wt[0] * a0 + wt[1] * a1;
                gtr += gp[ch] * (before[ch] - a);
                ga[ch] = (1.0 - l.tr) * gp[ch];
                if persp {
                    // A = ((1 - t) q0 A0 + t q1 A1) / den, den = (1 - t) q0 + t q1.
                    gt += ga[ch] * (e.q[1] * (a1 - a) + e.q[0] * (a - a0)) / den;
                    gq0 += ga[ch] * (1.0 - l.t) * (a0 - a) / den;
                    gq1 += ga[ch] * l.t * (a1 - a) / den;
                } else {
                    gt += ga[ch] * (a1 - a0);
                }
            }
            for v in gp.iter_mut() {
                *v *= l.tr;
            }
            if ga.iter().any(|&x| x != 0.0) {
                for k in 0..2 {
                    out.attr_vertex.push(e.v[k]);
                    out.attr_grad.extend(ga.iter().map(|g| g * wt[k]));
                }
            }
            let gs = gtr / sigma;
            if gs == 0.0 && gt == 0.0 && gq0 == 0.0 && gq1 == 0.0 {
                continue;
            }
            // s = sgn cross(e, d) / |e|, t = e . d / |e|^2 with e = p1 - p0, d = p - p0.
            let d = [l.x as f64 - e.p0[0], rf - e.p0[1]];
            let (s, t) = (
                e.sgn * cross2(e.e, d) / e.len,
                (e.e[0] * d[0] + e.e[1] * d[1]) / e.len2,
            );
            let ds_de = [
                e.sgn * d[1] / e.len - s * e.e[0] / e.len2,
                -e.sgn * d[0] / e.len - s * e.e[1] / e.len2,
            ];
            let dt_de = [
                d[0] / e.len2 - 2.0 * t * e.e[0] / e.len2,
                d[1] / e.len2 - 2.0 * t * e.e[1] / e.len2,
            ];
            let g1 = [gs * ds_de[0] + gt * dt_de[0], gs * ds_de[1] + gt * dt_de[1]];
            let g0 = [
                -g1[0] - gs * e.n[0] - gt * e.e[0] / e.len2,
                -g1[1] - gs * e.n[1] - gt * e.e[1] / e.len2,
            ];
            // q = 1 / w: dq/dw = -q^2.
            out.pos
                .push((e.v[0], [g0[0], g0[1], -gq0 * e.q[0] * e.q[0]]));
            out.pos
                .push((e.v[1], [g1[0], g1[1], -gq1 * e.q[1] * e.q[1]]));
        }
        (out, grad.finish::<T>(None).sorted(c + 1))
    }
}

impl<T: Real> Op<T> for DeodrOp<T> {
    fn name(&self) -> &'static str {
        "deodr"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let hard = render_hard(
            "deodr",
            &self.fragments,
            &self.faces,
            &self.background,
            &inputs[1],
        )?;
        if self.edges.edges.is_empty() {
            return Ok(vec![hard]);
        }
        let c = self.background.len();
        let w = self.settings.width;
        let attrs: Vec<f64> = inputs[1].iter().map(|x| x.to_f64c()).collect();
        // Only rows that some ramp reaches change, and only their touched pixels, in f64 (their
        // previous values are kept for the backward).
        let mut img = hard;
        let rw = w * (c + 1);
        self.hard_px = img
            .as_slice_mut()
            .expect("standard")
            .par_chunks_mut(rw)
            .enumerate()
            .map_init(
                || Touched::new(w, c + 1, true),
                |t, (row, out)| {
                    if self.edges.row(row).is_empty() {
                        return RowPixels::default();
                    }
                    self.overdraw_row(&attrs, row, out, t, |_, _| {});
                    t.finish(Some(out))
                },
            )
            .collect();
        Ok(vec![img])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let fr = &self.fragments;
        let c = self.background.len();
        let w = self.settings.width;
        let attrs: Vec<f64> = ctx.inputs[1].iter().map(|x| x.to_f64c()).collect();
        // dL/dI, replayed through each row's overdraw layers (in f64) to dL/dI_hard at the
        // touched pixels; the others pass through unchanged.
        let g_in = ctx.grad_outputs[0].as_standard_layout();
        let g_in = g_in.as_slice().expect("standard");
        let rw = w * (c + 1);
        let rows: Vec<(RowGrad, RowPixels)> = (0..self.hard_px.len())
            .into_par_iter()
            .map_init(
                || RowScratch {
                    hard: Touched::new(w, c + 1, false),
                    grad: Touched::new(w, c + 1, false),
                    layers: Vec::new(),
                    saved: Vec::new(),
                },
                |sc, row| {
                    if self.edges.row(row).is_empty() {
                        return Default::default();
                    }
                    let g_row = &g_in[row * rw..(row + 1) * rw];
                    self.backward_row(&attrs, &self.hard_px[row], row, g_row, sc)
                },
            )
            .collect();
        // The touched pixels' dL/dI_hard in pixel order (each row's already sorted).
        let n_ov: usize = rows.iter().map(|(_, px)| px.xs.len()).sum();
        let (mut ov_pix, mut ov_val) =
            (Vec::with_capacity(n_ov), Vec::with_capacity(n_ov * (c + 1)));
        for (row, (_, px)) in rows.iter().enumerate() {
            ov_pix.extend(px.xs.iter().map(|&x| (row * w + x as usize) as u32));
            ov_val.extend_from_slice(&px.vals);
        }
        let contrib: Vec<RowGrad> = rows.into_iter().map(|(r, _)| r).collect();
        let hg = hard_render_grad(
            "deodr",
            ctx,
            &self.faces,
            fr,
            g_in,
            Some((&ov_pix, &ov_val)),
            &self.settings,
            ctx.needs_grad[0],
        )?;
        let g_attr = hg.attr.map(|mut ga| {
            for r in &contrib {
                for (v, vals) in r.attr_vertex.iter().zip(r.attr_grad.chunks(c.max(1))) {
                    for (ch, x) in vals.iter().enumerate() {
                        ga[*v as usize * c + ch] += *x;
                    }
                }
            }
            tensor_f64(ctx.inputs[1].shape(), ga)
        });
        let Some(interior) = hg.pos else {
            return Ok(vec![None, g_attr]);
        };
        // Edges: pixel-space and w gradients per vertex, summed in row order.
        let nv = self.screen.px.len();
        let mut acc = vec![[0.0f64; 3]; nv];
        for r in &contrib {
            for (v, gv) in &r.pos {
                let a = &mut acc[*v as usize];
                a[0] += gv[0];
                a[1] += gv[1];
                a[2] += gv[2];
            }
        }
        let total: Vec<T> = interior
            .iter()
            .zip(&acc)
            .enumerate()
            .flat_map(|(v, (a, e))| {
                let mut out = *a;
                if e[0] != 0.0 || e[1] != 0.0 {
                    let ce = self.screen.px_to_clip(v, [e[0], e[1]]);
                    for k in 0..4 {
                        out[k] += ce[k];
                    }
                }
                out[3] += e[2];
                out.map(T::from_f64c)
            })
            .collect();
        Ok(vec![
            Some(ArrayD::from_shape_vec(IxDyn(&[nv, 4]), total).expect("v x 4")),
            g_attr,
        ])
    }
}
