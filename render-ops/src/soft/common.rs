//! Machinery shared by the soft rasterizers (`softras`, `dibr`): projection of clip positions,
//! binning of faces into screen tiles by their boxes expanded by a cut-off distance, the
//! closest point of a projected triangle's boundary to a pixel centre with its gradient, and
//! the chain from NDC to clip coordinates.

use autodiff::{Real, Var};
use rayon::prelude::*;

use crate::raster::{RasterError, MAX_FRAGMENT_SLOTS};

/// Largest number of (tile, face) entries the soft methods' per-tile face lists may hold: a
/// face counts once for every 16 x 16 pixel tile its screen box, expanded by the coverage
/// cut-off, touches. Each entry is a 4-byte face id (64 MB at the limit); the backwards keep
/// one accumulator per face (`3 x (4 + C)` `f64` for SoftRas, `3 x 3` for DIB-R), not per
/// entry. The forwards' per-tile scratch holds the kept (face, pixel) pairs of one tile at a
/// time (48 bytes each for SoftRas; 8 for DIB-R) per thread, SoftRas's `f32` path those of one
/// band of 8 image rows (192 bytes per 8-pixel chunk). A fine mesh of small faces needs a few entries per face; a huge cut-off (e.g. SoftRas
/// `threshold` 0, which makes every face reach every pixel) multiplies faces by tiles and is
/// refused with [`RasterError::TooLarge`] before anything is allocated.
pub const MAX_SOFT_BIN_ENTRIES: usize = 1 << 24;

/// Tile edge in pixels.
pub(crate) const TILE: usize = 16;

#[inline]
pub(crate) fn cross(u: [f64; 2], v: [f64; 2]) -> f64 {
    u[0] * v[1] - u[1] * v[0]
}

/// NDC position of the centre of pixel (row, col) in a `width x height` image.
#[inline]
pub(crate) fn pixel_centre(row: usize, col: usize, width: usize, height: usize) -> [f64; 2] {
    [
        2.0 * (col as f64 + 0.5) / width as f64 - 1.0,
        1.0 - 2.0 * (row as f64 + 0.5) / height as f64,
    ]
}

/// NDC `(x, y)` and clip `w` (view depth) of every vertex of a [V, 4] clip tensor.
pub(crate) fn project<T: Real, S: ndarray::Data<Elem = T>>(
    clip: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> (Vec<[f64; 2]>, Vec<f64>) {
    let nv = clip.shape()[0];
    let mut ndc = Vec::with_capacity(nv);
    let mut depth = Vec::with_capacity(nv);
    for r in clip.outer_iter() {
        let w = r[3].to_f64c();
        ndc.push([r[0].to_f64c() / w, r[1].to_f64c() / w]);
        depth.push(w);
    }
    (ndc, depth)
}

/// Faces binned into `TILE x TILE` pixel tiles.
pub(crate) struct TileBins {
    /// Tiles per image row.
    pub tiles_x: usize,
    /// Faces per tile, in increasing face order.
    pub tiles: Vec<Vec<u32>>,
    /// Pixel box (c0, c1, r0, r1) per face, inclusive; c0 > c1 when skipped.
    pub rects: Vec<[i64; 4]>,
    /// Screen geometry per face (meaningful for faces that are not skipped).
    pub geoms: Vec<FaceGeom>,
    /// Row-span constraints per face ([`TileBins::span`]), set up once per binning.
    spans: Vec<FaceSpan>,
    /// NDC x of every pixel column's centre.
    pub px: Vec<f64>,
    /// NDC y of every pixel row's centre.
    pub py: Vec<f64>,
}

/// The pixel box of a skipped face (empty: `c0 > c1`).
pub(crate) const SKIPPED: [i64; 4] = [1, 0, 1, 0];

impl TileBins {
    /// Bins the faces whose vertices all have `w > 0` (in `[MIN_W, 1 / MIN_W]`), NDC within
    /// `MAX_NDC` and a non-zero projected area (and, with `cull_backfaces`, a positive one:
    /// counter-clockwise), by their NDC boxes expanded by `dmax` (NDC units).
    pub fn new(
        ndc: &[[f64; 2]],
        depth: &[f64],
        faces: &[[u32; 3]],
        width: usize,
        height: usize,
        dmax: f64,
        cull_backfaces: bool,
    ) -> Self {
        let rects = faces
            .par_iter()
            .with_min_len(1024)
            .map(|f| {
                face_rect(ndc, depth, f, width, height, dmax, cull_backfaces).unwrap_or(SKIPPED)
            })
            .collect();
        Self::with_rects(ndc, depth, faces, width, height, dmax, rects, true)
    }

    /// [`TileBins::new`] from the faces' pixel boxes as `face_rect` gives them (`SKIPPED`
    /// for skipped faces), e.g. those [`check_memory`] computed for its count; the per-tile
    /// face lists stay empty unless `bin_tiles` (for callers that walk faces, not tiles).
    #[allow(clippy::too_many_arguments)]
    pub fn with_rects(
        ndc: &[[f64; 2]],
        depth: &[f64],
        faces: &[[u32; 3]],
        width: usize,
        height: usize,
        dmax: f64,
        rects: Vec<[i64; 4]>,
        bin_tiles: bool,
    ) -> Self {
        let tiles_x = width.div_ceil(TILE);
        let tiles_y = height.div_ceil(TILE);
        let mut tiles = vec![Vec::new(); tiles_x * tiles_y];
        let (px0, dpx) = (1.0 / width as f64 - 1.0, 2.0 / width as f64);
        // Geometry and row-span constraints in parallel (per face, independent), binning in
        // face order.
        let (geoms, spans): (Vec<FaceGeom>, Vec<FaceSpan>) = faces
            .par_iter()
            .zip(&rects)
            .with_min_len(1024)
            .map(|(f, rect)| {
                if rect[0] > rect[1] {
                    return (FaceGeom::default(), FaceSpan::default());
                }
                let g = FaceGeom::new(ndc, depth, f);
                let sp = FaceSpan::new(&g, px0, dpx, dmax);
                (g, sp)
            })
            .unzip();
        for (fi, rect) in rects.iter().enumerate() {
            if rect[0] > rect[1] || !bin_tiles {
                continue;
            }
            for ty in rect[2] as usize / TILE..=rect[3] as usize / TILE {
                for tx in rect[0] as usize / TILE..=rect[1] as usize / TILE {
                    tiles[ty * tiles_x + tx].push(fi as u32);
                }
            }
        }
        let px = (0..width)
            .map(|c| pixel_centre(0, c, width, height)[0])
            .collect();
        let py = (0..height)
            .map(|r| pixel_centre(r, 0, width, height)[1])
            .collect();
        Self {
            tiles_x,
            tiles,
            rects,
            geoms,
            spans,
            px,
            py,
        }
    }

    /// The row spans of face `fi`'s cut-off region ([`FaceSpan`]).
    #[inline(always)]
    pub fn span(&self, fi: usize) -> FaceSpan {
        self.spans[fi]
    }

    /// Runs `face(fi, out)` for every face with a non-empty box, in parallel and in
    /// [`TileBins::spatial_order`] (the per-pixel data a face reads stays in cache), each face
    /// writing `stride` values. Callers then sum [`PerFace::get`] into vertices in face order,
    /// so the result does not depend on the thread count.
    pub fn per_face<F>(&self, stride: usize, face: F) -> PerFace
    where
        F: Fn(usize, &mut [f64]) + Sync,
    {
        let order = self.spatial_order();
        let mut vals = vec![0.0; order.len() * stride];
        vals.par_chunks_mut(stride)
            .zip(order.par_iter())
            .with_min_len(16)
            .for_each(|(acc, &fi)| face(fi as usize, acc));
        let mut slot = vec![u32::MAX; self.rects.len()];
        for (i, &fi) in order.iter().enumerate() {
            slot[fi as usize] = i as u32;
        }
        PerFace { vals, slot, stride }
    }

    /// Faces that have a box, in the order of the tile holding their box's first pixel
    /// (row-major tiles; face order within a tile), so that faces visited one after another
    /// touch nearby pixels.
    pub fn spatial_order(&self) -> Vec<u32> {
        let home = |r: &[i64; 4]| (r[2] as usize / TILE) * self.tiles_x + r[0] as usize / TILE;
        let mut start = vec![0usize; self.tiles.len() + 1];
        for r in self.rects.iter().filter(|r| r[0] <= r[1]) {
            start[home(r) + 1] += 1;
        }
        for t in 0..self.tiles.len() {
            start[t + 1] += start[t];
        }
        let mut order = vec![0u32; start[self.tiles.len()]];
        for (fi, r) in self.rects.iter().enumerate() {
            if r[0] <= r[1] {
                let h = home(r);
                order[start[h]] = fi as u32;
                start[h] += 1;
            }
        }
        order
    }

    /// The row spans of face `fi`'s cut-off region over its whole box, as `(row, py, a, b)`:
    /// image row, its NDC y and the first and last column that may pass the cut-off (what
    /// the per-face backward passes walk). Empty for a face that was not binned.
    #[inline(always)]
    pub fn face_rows(&self, fi: usize) -> FaceRows<'_> {
        let rc = self.rects[fi];
        let (row, end) = if rc[0] <= rc[1] {
            (rc[2] as usize, rc[3] as usize + 1)
        } else {
            (0, 0)
        };
        FaceRows {
            py: &self.py,
            span: self.span(fi),
            row,
            end,
            c0: rc[0].max(0) as usize,
            c1: rc[1].max(0) as usize,
        }
    }

    /// The part of face `fi`'s box inside tile `t` as (c0, c1, r0, r1), inclusive, in image
    /// pixels; `None` when they do not overlap.
    #[inline]
    pub fn face_in_tile(
        &self,
        fi: usize,
        t: usize,
        width: usize,
        height: usize,
    ) -> Option<[usize; 4]> {
        let rc = self.rects[fi];
        let (tx, ty) = (t % self.tiles_x, t / self.tiles_x);
        let c0 = (rc[0] as usize).max(tx * TILE);
        let c1 = (rc[1] as usize).min((tx * TILE + TILE).min(width) - 1);
        let r0 = (rc[2] as usize).max(ty * TILE);
        let r1 = (rc[3] as usize).min((ty * TILE + TILE).min(height) - 1);
        (rc[0] <= rc[1] && c0 <= c1 && r0 <= r1).then_some([c0, c1, r0, r1])
    }
}

/// The row spans of one face's cut-off region: the columns of a row that may pass the face's
/// outside bound ([`FaceGeom::outside_d2_bound`] `<= dmax^2`, `dmax` the cut-off the bins were
/// built with), i.e. the pixels no farther than `dmax` beyond any of the three edge lines,
/// `w_k >= -dmax / alt_k` for every `k`. Each `w_k` is affine along a row, so this is one
/// interval (the scanline of the triangle dilated along its edge normals). It is widened by a
/// relative margin and one column on each side, so the per-pixel test alone decides which
/// pixels are kept: the set of kept pairs is that of the whole box.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct FaceSpan {
    a: [f64; 3],
    by: [f64; 3],
    inv_s: [f64; 3],
}

impl FaceSpan {
    /// The constraints of face geometry `g` for cut-off `dmax` (NDC units), with column
    /// centres `px[col] = px0 + dpx col` up to rounding.
    fn new(g: &FaceGeom, px0: f64, dpx: f64, dmax: f64) -> Self {
        let ox = px0 - g.v[0][0];
        let mut sp = FaceSpan::default();
        for k in 0..3 {
            let b = g.bw[k];
            // w_k(col, row) = b0 + b1 (px0 + dpx col - v0x) + b2 (py - v0y), needed
            // >= lim = -dmax / alt_k; the margin covers the rounding of both evaluations.
            let lim = -dmax / g.alt[k];
            let err = 1e-10
                * (b[0].abs()
                    + b[1].abs() * (1.0 + g.v[0][0].abs())
                    + b[2].abs() * (1.0 + g.v[0][1].abs())
                    + lim.abs());
            let s = b[1] * dpx;
            // need(py) = lim - err - w_k(col 0) = a - by py; col >= need / s when s > 0.
            sp.a[k] = lim - err - (b[0] + b[1] * ox - b[2] * g.v[0][1]);
            sp.by[k] = b[2];
            sp.inv_s[k] = 1.0 / s;
        }
        sp
    }

    /// The columns within `[c0, c1]` of the row whose centres have NDC y `py`, or `None`.
    ///
    /// Per edge with `s > 0` the first column is `ceil(need / s) - 1`, with `s < 0` the last
    /// is `floor(need / s) + 1`. The quotient is first clamped to `[c0 - 2, c1 + 2]`, which
    /// changes no result (a bound beyond the box either leaves the box's end or empties the
    /// span either way), so `ceil` and `floor` are taken by truncation to an integer, without
    /// a libm call (the default x86-64 target has no rounding instruction).
    #[inline(always)]
    pub fn row(&self, py: f64, c0: usize, c1: usize) -> Option<(usize, usize)> {
        let (mut lo, mut hi) = (c0 as i64, c1 as i64);
        let (fmin, fmax) = (c0 as f64 - 2.0, c1 as f64 + 2.0);
        for k in 0..3 {
            let need = self.a[k] - self.by[k] * py;
            let inv_s = self.inv_s[k];
            if inv_s > 0.0 && inv_s.is_finite() {
                // NaN quotients (never expected) clamp to the box's end: no constraint.
                let x = (need * inv_s).max(fmin).min(fmax);
                let t = x as i64;
                // ceil(x) - 1.
                lo = lo.max(t + ((t as f64) < x) as i64 - 1);
            } else if inv_s < 0.0 && inv_s.is_finite() {
                let x = (need * inv_s).min(fmax).max(fmin);
                let t = x as i64;
                // floor(x) + 1.
                hi = hi.min(t - ((t as f64) > x) as i64 + 1);
            } else if need > 0.0 && !inv_s.is_finite() {
                // w_k does not change along the row (s = 0, 1 / s infinite).
                return None;
            }
        }
        (lo <= hi).then_some((lo as usize, hi as usize))
    }
}

/// Iterator of [`TileBins::face_rows`].
pub(crate) struct FaceRows<'a> {
    py: &'a [f64],
    span: FaceSpan,
    row: usize,
    end: usize,
    c0: usize,
    c1: usize,
}

impl FaceRows<'_> {
    /// Only the rows `lo..=hi` (the forwards' bands of rows).
    #[inline(always)]
    pub fn within(mut self, lo: usize, hi: usize) -> Self {
        self.row = self.row.max(lo);
        self.end = self.end.min(hi + 1);
        self
    }
}

impl Iterator for FaceRows<'_> {
    type Item = (usize, f64, usize, usize);

    #[inline(always)]
    fn next(&mut self) -> Option<Self::Item> {
        while self.row < self.end {
            let row = self.row;
            self.row += 1;
            let py = self.py[row];
            if let Some((a, b)) = self.span.row(py, self.c0, self.c1) {
                return Some((row, py, a, b));
            }
        }
        None
    }
}

/// Vertices with `w` outside `[MIN_W, 1 / MIN_W]` (at the eye plane, or at infinity), or
/// projected farther out than `MAX_NDC`, make their faces be skipped like faces behind the eye:
/// the products and quotients of the soft methods' per-pixel terms then stay finite.
const MIN_W: f64 = 1e-100;
const MAX_NDC: f64 = 1e100;

/// The inclusive pixel box (c0, c1, r0, r1) of face `f`'s NDC box expanded by `dmax`, or
/// `None` when the face is skipped (a vertex at `w <= 0`, or so near the eye plane or far out
/// that the soft terms would overflow: see [`MIN_W`]; zero or non-finite projected area;
/// back-facing under `cull_backfaces`; off screen).
fn face_rect(
    ndc: &[[f64; 2]],
    depth: &[f64],
    f: &[u32; 3],
    width: usize,
    height: usize,
    dmax: f64,
    cull_backfaces: bool,
) -> Option<[i64; 4]> {
    let (wf, hf) = (width as f64, height as f64);
    let p = f.map(|i| ndc[i as usize]);
    let ok = f
        .iter()
        .all(|&i| (MIN_W..=1.0 / MIN_W).contains(&depth[i as usize]))
        && p.iter()
            .all(|q| q[0].abs() <= MAX_NDC && q[1].abs() <= MAX_NDC);
    if !ok {
        return None;
    }
    let area = cross(
        [p[1][0] - p[0][0], p[1][1] - p[0][1]],
        [p[2][0] - p[0][0], p[2][1] - p[0][1]],
    );
    if area == 0.0 || !area.is_finite() || (cull_backfaces && area < 0.0) {
        return None;
    }
    let xmin = p.iter().map(|q| q[0]).fold(f64::INFINITY, f64::min) - dmax;
    let xmax = p.iter().map(|q| q[0]).fold(f64::NEG_INFINITY, f64::max) + dmax;
    let ymin = p.iter().map(|q| q[1]).fold(f64::INFINITY, f64::min) - dmax;
    let ymax = p.iter().map(|q| q[1]).fold(f64::NEG_INFINITY, f64::max) + dmax;
    let c0 = ((xmin + 1.0) * wf / 2.0 - 0.5).ceil().max(0.0);
    let c1 = ((xmax + 1.0) * wf / 2.0 - 0.5).floor().min(wf - 1.0);
    let r0 = ((1.0 - ymax) * hf / 2.0 - 0.5).ceil().max(0.0);
    let r1 = ((1.0 - ymin) * hf / 2.0 - 0.5).floor().min(hf - 1.0);
    if !(c0 <= c1 && r0 <= r1) {
        return None;
    }
    Some([c0 as i64, c1 as i64, r0 as i64, r1 as i64])
}

/// Refuses a vertex with a NaN or infinite clip coordinate
/// ([`RasterError::NonFiniteVertex`]) and, before anything is allocated, a soft render whose
/// image exceeds
/// [`MAX_FRAGMENT_SLOTS`] pixels or whose per-tile face lists would exceed
/// [`MAX_SOFT_BIN_ENTRIES`] entries (counted from the faces' expanded boxes, as
/// [`TileBins::new`] will bin them). Poisoned or non-2-D `clip` values are left to the op.
pub(crate) fn check_memory<T: Real>(
    op: &str,
    clip: &Var<'_, T>,
    faces: &[[u32; 3]],
    width: usize,
    height: usize,
    dmax: f64,
    cull_backfaces: bool,
) -> Result<(), RasterError> {
    check_memory_projected(op, clip, faces, width, height, dmax, cull_backfaces).map(|_| ())
}

/// What [`check_memory_projected`] computed for its count: the vertices' NDC and view depth
/// ([`project`]) and the faces' pixel boxes, for [`TileBins::with_rects`], so that the op's
/// forward need not redo them.
pub(crate) struct Projected {
    pub ndc: Vec<[f64; 2]>,
    pub depth: Vec<f64>,
    pub rects: Vec<[i64; 4]>,
}

/// [`check_memory`], returning its projection and face boxes when it computed them (`None`
/// where it left `clip` to the op).
pub(crate) fn check_memory_projected<T: Real>(
    op: &str,
    clip: &Var<'_, T>,
    faces: &[[u32; 3]],
    width: usize,
    height: usize,
    dmax: f64,
    cull_backfaces: bool,
) -> Result<Option<Projected>, RasterError> {
    let pixels = width.saturating_mul(height);
    if pixels > MAX_FRAGMENT_SLOTS {
        return Err(RasterError::TooLarge {
            request: format!("{op} at {width}x{height}"),
            what: "pixels",
            needed: pixels,
            limit: MAX_FRAGMENT_SLOTS,
        });
    }
    let Ok(clip) = clip.value_ref() else {
        return Ok(None);
    };
    let clip = clip.view();
    if clip.ndim() != 2 || clip.shape()[1] != 4 {
        return Ok(None);
    }
    // NaN or Inf coordinates are refused, as by the hard rasterizer.
    for (v, row) in clip.outer_iter().enumerate() {
        if !row.iter().all(|x| x.is_finite()) {
            return Err(RasterError::NonFiniteVertex {
                vertex: v,
                coords: [row[0], row[1], row[2], row[3]].map(|x| x.to_f64c()),
            });
        }
    }
    let (ndc, depth) = project(&clip);
    if faces
        .iter()
        .any(|f| f.iter().any(|&i| i as usize >= ndc.len()))
    {
        return Ok(None);
    }
    // Per-face boxes in parallel, their tile counts summed exactly (u128 cannot overflow
    // here).
    let rects: Vec<[i64; 4]> = faces
        .par_iter()
        .with_min_len(1024)
        .map(|f| face_rect(&ndc, &depth, f, width, height, dmax, cull_backfaces).unwrap_or(SKIPPED))
        .collect();
    let total: u128 = rects
        .iter()
        .filter(|r| r[0] <= r[1])
        .map(|r| {
            let tx = (r[1] as usize / TILE - r[0] as usize / TILE + 1) as u128;
            let ty = (r[3] as usize / TILE - r[2] as usize / TILE + 1) as u128;
            tx * ty
        })
        .sum();
    let entries = total.min(usize::MAX as u128) as usize;
    if entries > MAX_SOFT_BIN_ENTRIES {
        return Err(RasterError::TooLarge {
            request: format!(
                "{op} of {} faces at {width}x{height} with a cut-off of {dmax:.3e} NDC units",
                faces.len()
            ),
            what: "per-tile face list entries",
            needed: entries,
            limit: MAX_SOFT_BIN_ENTRIES,
        });
    }
    Ok(Some(Projected { ndc, depth, rects }))
}

/// The closest point of a triangle's boundary to a point `p`: on edge `edge` (from vertex
/// `edge` to vertex `edge + 1`) at parameter `t` in [0, 1], with `r = p - closest` and
/// `d2 = |r|^2`.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Closest {
    pub d2: f64,
    pub edge: u8,
    pub t: f64,
    pub r: [f64; 2],
}

/// Per-face values of [`TileBins::per_face`], stored in spatial order.
pub(crate) struct PerFace {
    vals: Vec<f64>,
    slot: Vec<u32>,
    stride: usize,
}

impl PerFace {
    /// Face `fi`'s values, `None` when its box was empty (it touched no pixel).
    pub fn get(&self, fi: usize) -> Option<&[f64]> {
        let i = self.slot[fi];
        (i != u32::MAX)
            .then(|| &self.vals[i as usize * self.stride..(i as usize + 1) * self.stride])
    }
}

/// Closest point of the boundary of triangle `v` to `p` (first edge wins ties): the plain
/// reference for [`FaceGeom`]'s tests.
#[cfg(test)]
pub(crate) fn closest_on_boundary(v: &[[f64; 2]; 3], p: [f64; 2]) -> Closest {
    let mut best = Closest {
        d2: f64::INFINITY,
        ..Default::default()
    };
    for k in 0..3 {
        let (a, b) = (v[k], v[(k + 1) % 3]);
        let e = [b[0] - a[0], b[1] - a[1]];
        let ee = e[0] * e[0] + e[1] * e[1];
        let t = if ee > 0.0 {
            (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / ee).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let r = [p[0] - a[0] - t * e[0], p[1] - a[1] - t * e[1]];
        let d2 = r[0] * r[0] + r[1] * r[1];
        if d2 < best.d2 {
            best = Closest {
                d2,
                edge: k as u8,
                t,
                r,
            };
        }
    }
    best
}

/// Screen geometry of one projected face, computed once per forward so that the work per
/// (face, pixel) pair is a few multiply-adds (SoftRas and DIB-R evaluate every face near every
/// pixel).
///
/// With `n_k(p) = cross(v_{k+1} - p, v_{k+2} - p)` (twice the signed area of the sub-triangle
/// opposite vertex `k`) and `area = sum_k n_k`, the screen-space barycentrics `w_k = n_k / area`
/// are affine in `p`; they are evaluated about `v0` for accuracy far from the origin. The
/// distance from `p` to the line of the edge opposite `k` is `|w_k| alt_k`; for a point inside
/// the triangle the nearest boundary point is the foot on the nearest edge line, so the
/// distance to the boundary is `min_k w_k alt_k`, and outside `max_k (-w_k alt_k)` is a lower
/// bound of the distance to the triangle (it is separated by that edge's line).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct FaceGeom {
    /// NDC vertices.
    pub v: [[f64; 2]; 3],
    /// `w_k(p) = bw[k][0] + bw[k][1] (p_x - v0_x) + bw[k][2] (p_y - v0_y)`.
    pub bw: [[f64; 3]; 3],
    /// `sum_k n_k = cross(v1 - v0, v2 - v0)`, twice the signed projected area.
    pub area: f64,
    /// `|area| / |v_{k+2} - v_{k+1}|`: distance to the edge line opposite `k` per unit `|w_k|`.
    pub alt: [f64; 3],
    /// `1 / |v_{k+1} - v_k|^2` of edge `k` (0 for a zero-length edge).
    pub inv_ee: [f64; 3],
    /// `1 / w_clip` of each vertex.
    pub inv_d: [f64; 3],
}

impl FaceGeom {
    /// Geometry of face `f` (its projected area must be non-zero and finite, as
    /// `face_rect` ensures for the faces it keeps).
    pub fn new(ndc: &[[f64; 2]], depth: &[f64], f: &[u32; 3]) -> Self {
        let v = f.map(|i| ndc[i as usize]);
        let o = v[0];
        let rel = v.map(|q| [q[0] - o[0], q[1] - o[1]]);
        let area = cross(rel[1], rel[2]);
        let inv_area = 1.0 / area;
        let mut bw = [[0.0; 3]; 3];
        let mut alt = [0.0; 3];
        let mut inv_ee = [0.0; 3];
        for k in 0..3 {
            let (a, b) = (rel[(k + 1) % 3], rel[(k + 2) % 3]);
            // n_k(q) = cross(a, b) + q_x (a_y - b_y) + q_y (b_x - a_x), q = p - v0.
            bw[k] = [
                cross(a, b) * inv_area,
                (a[1] - b[1]) * inv_area,
                (b[0] - a[0]) * inv_area,
            ];
            let len = (b[0] - a[0]).hypot(b[1] - a[1]);
            alt[k] = area.abs() / len;
            let e = [v[(k + 1) % 3][0] - v[k][0], v[(k + 1) % 3][1] - v[k][1]];
            let ee = e[0] * e[0] + e[1] * e[1];
            inv_ee[k] = if ee > 0.0 && (1.0 / ee).is_finite() {
                1.0 / ee
            } else {
                0.0
            };
        }
        Self {
            v,
            bw,
            area,
            alt,
            inv_ee,
            inv_d: f.map(|i| 1.0 / depth[i as usize]),
        }
    }

    /// Screen-space barycentrics of the point `p`.
    #[inline(always)]
    pub fn bary(&self, p: [f64; 2]) -> [f64; 3] {
        let (qx, qy) = (p[0] - self.v[0][0], p[1] - self.v[0][1]);
        self.bw.map(|b| b[0] + b[1] * qx + b[2] * qy)
    }

    /// Squared distance from an inside point with barycentrics `w` to the boundary.
    #[inline(always)]
    pub fn inside_d2(&self, w: &[f64; 3]) -> f64 {
        let d = (w[0] * self.alt[0])
            .min(w[1] * self.alt[1])
            .min(w[2] * self.alt[2]);
        d * d
    }

    /// A lower bound of the squared distance from an outside point with barycentrics `w` to the
    /// triangle: the largest distance beyond one of its edge lines.
    #[inline(always)]
    pub fn outside_d2_bound(&self, w: &[f64; 3]) -> f64 {
        let d = (-w[0] * self.alt[0])
            .max(-w[1] * self.alt[1])
            .max(-w[2] * self.alt[2]);
        d * d
    }

    /// Closest point of the boundary to an inside point `p` with barycentrics `w`: the foot on
    /// the nearest edge line (the edge opposite the smallest `w_k alt_k`), which for a point
    /// inside the triangle lies on that edge; as [`FaceGeom::closest`] up to ties.
    #[inline(always)]
    pub fn closest_inside(&self, p: [f64; 2], w: &[f64; 3]) -> Closest {
        let d = [w[0] * self.alt[0], w[1] * self.alt[1], w[2] * self.alt[2]];
        let k = if d[0] <= d[1] && d[0] <= d[2] {
            0
        } else if d[1] <= d[2] {
            1
        } else {
            2
        };
        // Edge `e` runs from vertex k + 1 to vertex k + 2.
        let e = (k + 1) % 3;
        let (a, b) = (self.v[e], self.v[(e + 1) % 3]);
        let ed = [b[0] - a[0], b[1] - a[1]];
        let ap = [p[0] - a[0], p[1] - a[1]];
        let t = ((ap[0] * ed[0] + ap[1] * ed[1]) * self.inv_ee[e]).clamp(0.0, 1.0);
        let r = [ap[0] - t * ed[0], ap[1] - t * ed[1]];
        Closest {
            d2: r[0] * r[0] + r[1] * r[1],
            edge: e as u8,
            t,
            r,
        }
    }

    /// Closest point of the triangle's boundary to `p`, as [`closest_on_boundary`] (first edge
    /// wins ties) with the edges' inverse squared lengths precomputed.
    #[inline]
    pub fn closest(&self, p: [f64; 2]) -> Closest {
        let v = &self.v;
        let mut best = Closest {
            d2: f64::INFINITY,
            ..Default::default()
        };
        for k in 0..3 {
            let (a, b) = (v[k], v[(k + 1) % 3]);
            let e = [b[0] - a[0], b[1] - a[1]];
            let ap = [p[0] - a[0], p[1] - a[1]];
            let t = ((ap[0] * e[0] + ap[1] * e[1]) * self.inv_ee[k]).clamp(0.0, 1.0);
            let r = [ap[0] - t * e[0], ap[1] - t * e[1]];
            let d2 = r[0] * r[0] + r[1] * r[1];
            if d2 < best.d2 {
                best = Closest {
                    d2,
                    edge: k as u8,
                    t,
                    r,
                };
            }
        }
        best
    }
}

/// `2^(j / 64)`, `j = 0..64`, correctly rounded (for [`exp`]).
const EXP2_64THS: [f64; 64] = [
    f64::from_bits(0x3ff0000000000000),
    f64::from_bits(0x3ff02c9a3e778061),
    f64::from_bits(0x3ff059b0d3158574),
    f64::from_bits(0x3ff0874518759bc8),
    f64::from_bits(0x3ff0b5586cf9890f),
    f64::from_bits(0x3ff0e3ec32d3d1a2),
    f64::from_bits(0x3ff11301d0125b51),
    f64::from_bits(0x3ff1429aaea92de0),
    f64::from_bits(0x3ff172b83c7d517b),
    f64::from_bits(0x3ff1a35beb6fcb75),
    f64::from_bits(0x3ff1d4873168b9aa),
    f64::from_bits(0x3ff2063b88628cd6),
    f64::from_bits(0x3ff2387a6e756238),
    f64::from_bits(0x3ff26b4565e27cdd),
    f64::from_bits(0x3ff29e9df51fdee1),
    f64::from_bits(0x3ff2d285a6e4030b),
    f64::from_bits(0x3ff306fe0a31b715),
    f64::from_bits(0x3ff33c08b26416ff),
    f64::from_bits(0x3ff371a7373aa9cb),
    f64::from_bits(0x3ff3a7db34e59ff7),
    f64::from_bits(0x3ff3dea64c123422),
    f64::from_bits(0x3ff4160a21f72e2a),
    f64::from_bits(0x3ff44e086061892d),
    f64::from_bits(0x3ff486a2b5c13cd0),
    f64::from_bits(0x3ff4bfdad5362a27),
    f64::from_bits(0x3ff4f9b2769d2ca7),
    f64::from_bits(0x3ff5342b569d4f82),
    f64::from_bits(0x3ff56f4736b527da),
    f64::from_bits(0x3ff5ab07dd485429),
    f64::from_bits(0x3ff5e76f15ad2148),
    f64::from_bits(0x3ff6247eb03a5585),
    f64::from_bits(0x3ff6623882552225),
    f64::from_bits(0x3ff6a09e667f3bcd),
    f64::from_bits(0x3ff6dfb23c651a2f),
    f64::from_bits(0x3ff71f75e8ec5f74),
    f64::from_bits(0x3ff75feb564267c9),
    f64::from_bits(0x3ff7a11473eb0187),
    f64::from_bits(0x3ff7e2f336cf4e62),
    f64::from_bits(0x3ff82589994cce13),
    f64::from_bits(0x3ff868d99b4492ed),
    f64::from_bits(0x3ff8ace5422aa0db),
    f64::from_bits(0x3ff8f1ae99157736),
    f64::from_bits(0x3ff93737b0cdc5e5),
    f64::from_bits(0x3ff97d829fde4e50),
    f64::from_bits(0x3ff9c49182a3f090),
    f64::from_bits(0x3ffa0c667b5de565),
    f64::from_bits(0x3ffa5503b23e255d),
    f64::from_bits(0x3ffa9e6b5579fdbf),
    f64::from_bits(0x3ffae89f995ad3ad),
    f64::from_bits(0x3ffb33a2b84f15fb),
    f64::from_bits(0x3ffb7f76f2fb5e47),
    f64::from_bits(0x3ffbcc1e904bc1d2),
    f64::from_bits(0x3ffc199bdd85529c),
    f64::from_bits(0x3ffc67f12e57d14b),
    f64::from_bits(0x3ffcb720dcef9069),
    f64::from_bits(0x3ffd072d4a07897c),
    f64::from_bits(0x3ffd5818dcfba487),
    f64::from_bits(0x3ffda9e603db3285),
    f64::from_bits(0x3ffdfc97337b9b5f),
    f64::from_bits(0x3ffe502ee78b3ff6),
    f64::from_bits(0x3ffea4afa2a490da),
    f64::from_bits(0x3ffefa1bee615a27),
    f64::from_bits(0x3fff50765b6e4540),
    f64::from_bits(0x3fffa7c1819e90d8),
];

/// `e^x` without a libm call, for the soft kernels' per-pair exponentials (the sigmoid of
/// SoftRas eq. (1), the depth weights of eq. (6), DIB-R's `e^{-x}`), inlined into their loops.
/// Table-driven: `x = (64 m + j) ln(2) / 64 + r` with `|r| <= ln(2) / 128` (the reduction
/// constant in two parts, the high one exact for every product that occurs), `e^x = 2^m
/// 2^(j/64) e^r`, `e^r - 1` by its Taylor polynomial of degree 5 (truncation below `4e-17`
/// relative); within 2 ulp of the exact value (tested against `f64::exp`). Outside `(-708,
/// 709)` (subnormal or overflowing results, NaN) it defers to `f64::exp`, except below `-746`,
/// where `e^x < 2^-1076` rounds to the `+0` that `f64::exp` returns (without its underflow
/// path: SoftRas's background weight `exp((eps - m) / gamma)` underflows at every pixel a face
/// covers when gamma is small).
#[inline(always)]
pub(crate) fn exp(x: f64) -> f64 {
    if !(x > -708.0 && x < 709.0) {
        if x < -746.0 {
            return 0.0;
        }
        return x.exp();
    }
    const SHIFT: f64 = 6755399441055744.0; // 1.5 * 2^52: adding it rounds to an integer.
    const INV_L: f64 = 92.332_482_616_893_66; // 64 / ln 2
    const L_HI: f64 = 0.010_830_424_689_629_58; // ln 2 / 64, 31 significant bits
    const L_LO: f64 = 6.619_564_634_077_006e-12;
    let n = (x * INV_L + SHIFT) - SHIFT;
    let r = (x - n * L_HI) - n * L_LO;
    let q = r + r * r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0))));
    let ni = n as i64;
    let t = EXP2_64THS[(ni & 63) as usize];
    // m = floor(n / 64) is in [-1022, 1023]: 2^m is a normal number.
    (t + t * q) * f64::from_bits((((ni >> 6) + 1023) as u64) << 52)
}

/// Adds `g`, the gradient of a pair's squared boundary distance behind its signed coverage
/// argument `x` (positive inside; SoftRas eq. 1, DIB-R eq. 4), to the projected corners `gv`:
/// the distance is to the foot on the nearest edge line for an inside point (barycentrics `w`),
/// to the pair's `closest` boundary point outside, to the closest point on the edge at `x = 0`.
#[inline]
pub(crate) fn signed_distance_backward(
    geom: &FaceGeom,
    p: [f64; 2],
    x: f64,
    w: &[f64; 3],
    closest: &Closest,
    g: f64,
    gv: &mut [[f64; 2]; 3],
) {
    let gd2 = if x >= 0.0 { g } else { -g };
    if gd2 != 0.0 {
        let cl = if x > 0.0 {
            geom.closest_inside(p, w)
        } else if x < 0.0 {
            *closest
        } else {
            geom.closest(p)
        };
        closest_backward(&cl, gd2, gv);
    }
}

/// Adds `gd2 * d(d2)/d(vertex NDC)` to `gv` (the closest parameter `t` is optimal or at a
/// clamp, so it does not move to first order).
#[inline]
pub(crate) fn closest_backward(q: &Closest, gd2: f64, gv: &mut [[f64; 2]; 3]) {
    if gd2 == 0.0 {
        return;
    }
    let (i, j) = (q.edge as usize, (q.edge as usize + 1) % 3);
    for ax in 0..2 {
        gv[i][ax] += gd2 * (-2.0 * q.r[ax] * (1.0 - q.t));
        gv[j][ax] += gd2 * (-2.0 * q.r[ax] * q.t);
    }
}

/// Chains a gradient `g` with respect to a vertex's NDC `(x, y) = (X / W, Y / W)` to its clip
/// coordinates: returns `(dX, dY, dW)`.
#[inline]
pub(crate) fn ndc_to_clip(g: [f64; 2], ndc: [f64; 2], w: f64) -> [f64; 3] {
    [g[0] / w, g[1] / w, -(g[0] * ndc[0] + g[1] * ndc[1]) / w]
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::rng::Rng;

    /// `FaceGeom`'s affine barycentrics, inside distance, outside bound and closest point
    /// against the plain formulas, on random triangles (both orientations, slivers included)
    /// and points around them.
    #[test]
    fn face_geom_matches_reference() {
        let mut rng = Rng::new(7);
        let mut inside_seen = 0;
        for case in 0..400 {
            let mut v = [[0.0f64; 2]; 3];
            for q in v.iter_mut() {
                *q = [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)];
            }
            if case % 10 == 0 {
                // A sliver: the third vertex near the first edge.
                let t = rng.uniform(0.0, 1.0);
                v[2] = [
                    v[0][0] + t * (v[1][0] - v[0][0]) + 1e-6,
                    v[0][1] + t * (v[1][1] - v[0][1]),
                ];
            }
            let ndc = v.to_vec();
            let depth = vec![1.0, 2.0, 3.0];
            let g = FaceGeom::new(&ndc, &depth, &[0, 1, 2]);
            let area = cross(
                [v[1][0] - v[0][0], v[1][1] - v[0][1]],
                [v[2][0] - v[0][0], v[2][1] - v[0][1]],
            );
            assert_eq!(g.area, area);
            for _ in 0..20 {
                let p = [rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5)];
                let w = g.bary(p);
                let mut n = [0.0; 3];
                for k in 0..3 {
                    let (a, b) = (v[(k + 1) % 3], v[(k + 2) % 3]);
                    n[k] = cross([a[0] - p[0], a[1] - p[1]], [b[0] - p[0], b[1] - p[1]]);
                }
                for k in 0..3 {
                    assert!(
                        (w[k] - n[k] / area).abs() <= 1e-9 * (1.0 + w[k].abs()),
                        "{w:?} {n:?}"
                    );
                }
                let exact = closest_on_boundary(&v, p);
                let fast = g.closest(p);
                assert!((fast.d2 - exact.d2).abs() <= 1e-12 * (1.0 + exact.d2));
                if w.iter().all(|&x| x >= 0.0) {
                    inside_seen += 1;
                    let d2 = g.inside_d2(&w);
                    assert!(
                        (d2 - exact.d2).abs() <= 1e-9 * (1e-6 + exact.d2),
                        "{d2} {}",
                        exact.d2
                    );
                } else {
                    assert!(g.outside_d2_bound(&w) <= exact.d2 * (1.0 + 1e-9) + 1e-15);
                }
            }
        }
        assert!(inside_seen > 100, "{inside_seen}");
    }

    /// [`exp`] within 2 ulp of `f64::exp` over the whole range, and exact at the edges.
    #[test]
    fn exp_matches_std() {
        let mut rng = Rng::new(3);
        for i in 0..200_000 {
            let x = match i % 4 {
                0 => rng.uniform(-750.0, 720.0),
                1 => rng.uniform(-40.0, 5.0),
                2 => rng.uniform(-1.0, 1.0),
                _ => rng.uniform(-1e-6, 1e-6),
            };
            let (a, b) = (exp(x), x.exp());
            assert!(
                a == b || (a - b).abs() <= 2.0 * f64::EPSILON * b,
                "exp({x}) = {a}, std {b}"
            );
        }
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-800.0), 0.0);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert!(exp(f64::NAN).is_nan());
    }

    /// [`FaceGeom::closest_inside`] against the exact closest point for inside points.
    #[test]
    fn closest_inside_matches_closest() {
        let mut rng = Rng::new(11);
        let mut seen = 0;
        while seen < 2000 {
            let v: Vec<[f64; 2]> = (0..3)
                .map(|_| [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)])
                .collect();
            let g = FaceGeom::new(&v, &[1.0, 1.0, 1.0], &[0, 1, 2]);
            let p = [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)];
            let w = g.bary(p);
            if !(w[0] >= 0.0 && w[1] >= 0.0 && w[2] >= 0.0) {
                continue;
            }
            seen += 1;
            let (a, b) = (g.closest_inside(p, &w), g.closest(p));
            assert!((a.d2 - b.d2).abs() <= 1e-12 * (1e-12 + b.d2), "{a:?} {b:?}");
            if (a.d2 - b.d2).abs() <= 1e-15 * b.d2 && a.edge == b.edge {
                assert!((a.t - b.t).abs() <= 1e-9, "{a:?} {b:?}");
            }
        }
    }

    /// [`FaceSpan::row`] (integer `ceil`/`floor` after clamping) gives the same spans as the
    /// plain `f64` formula, for random constraints including huge, infinite and NaN
    /// quotients and row-constant edges.
    #[test]
    fn row_span_matches_plain_formula() {
        fn plain(sp: &FaceSpan, py: f64, c0: usize, c1: usize) -> Option<(usize, usize)> {
            let (mut lo, mut hi) = (c0 as f64, c1 as f64);
            for k in 0..3 {
                let need = sp.a[k] - sp.by[k] * py;
                let inv_s = sp.inv_s[k];
                if inv_s > 0.0 && inv_s.is_finite() {
                    lo = lo.max((need * inv_s).ceil() - 1.0);
                } else if inv_s < 0.0 && inv_s.is_finite() {
                    hi = hi.min((need * inv_s).floor() + 1.0);
                } else if need > 0.0 && !inv_s.is_finite() {
                    return None;
                }
            }
            (lo <= hi).then(|| (lo.max(c0 as f64) as usize, hi.min(c1 as f64) as usize))
        }
        let mut rng = Rng::new(9);
        let mut nonempty = 0;
        for case in 0..200_000 {
            let pick = |rng: &mut Rng, i: usize| match (case + i) % 9 {
                0 => f64::INFINITY,
                1 => f64::NEG_INFINITY,
                2 => f64::NAN,
                3 => rng.uniform(-1e30, 1e30),
                4 => 0.0,
                _ => rng.uniform(-2.0, 2.0),
            };
            let mut sp = FaceSpan {
                a: [0.0; 3],
                by: [0.0; 3],
                inv_s: [0.0; 3],
            };
            for k in 0..3 {
                sp.a[k] = rng.uniform(-3.0, 3.0);
                sp.by[k] = rng.uniform(-2.0, 2.0);
                sp.inv_s[k] = if case % 5 == 0 {
                    pick(&mut rng, k)
                } else {
                    rng.uniform(-60.0, 60.0)
                };
            }
            let c0 = (rng.uniform(0.0, 40.0)) as usize;
            let c1 = c0 + (rng.uniform(0.0, 40.0)) as usize;
            let py = rng.uniform(-1.0, 1.0);
            let (a, b) = (sp.row(py, c0, c1), plain(&sp, py, c0, c1));
            assert_eq!(a, b, "{sp:?} py {py} {c0}..={c1}");
            nonempty += a.is_some() as usize;
        }
        assert!(nonempty > 20_000, "{nonempty}");
    }

    /// [`FaceSpan::row`] keeps every pixel of a face's box that passes the outside bound (or
    /// is inside), so the spans drop no pair the whole box would keep; and it is not much
    /// wider than those pixels.
    #[test]
    fn row_spans_cover_every_kept_pixel() {
        let mut rng = Rng::new(5);
        let (w, h) = (61, 47);
        let (mut kept, mut visited) = (0usize, 0usize);
        for case in 0..300 {
            let n = 4;
            let ndc: Vec<[f64; 2]> = (0..3 * n)
                .map(|_| [rng.uniform(-1.3, 1.3), rng.uniform(-1.3, 1.3)])
                .collect();
            let mut ndc = ndc;
            if case % 7 == 0 {
                // An axis-aligned edge (the row-constant case of the span).
                ndc[1][1] = ndc[0][1];
                ndc[4][0] = ndc[3][0];
            }
            let depth = vec![2.0; 3 * n];
            let faces: Vec<[u32; 3]> = (0..n as u32)
                .map(|i| [3 * i, 3 * i + 1, 3 * i + 2])
                .collect();
            let dmax = [0.0, 0.01, 0.05, 0.3][case % 4];
            let bins = TileBins::new(&ndc, &depth, &faces, w, h, dmax, false);
            for fi in 0..n {
                let r = bins.rects[fi];
                if r[0] > r[1] {
                    continue;
                }
                let g = &bins.geoms[fi];
                let span = bins.span(fi);
                let (c0, c1) = (r[0] as usize, r[1] as usize);
                for row in r[2] as usize..=r[3] as usize {
                    let sp = span.row(bins.py[row], c0, c1);
                    for col in c0..=c1 {
                        let wb = g.bary([bins.px[col], bins.py[row]]);
                        let inside = wb.iter().all(|&x| x >= 0.0);
                        if inside || g.outside_d2_bound(&wb) <= dmax * dmax {
                            kept += 1;
                            let (a, b) = sp.expect("a kept pixel in a row without a span");
                            assert!((a..=b).contains(&col), "{col} not in {a}..={b}");
                        }
                    }
                    if let Some((a, b)) = sp {
                        visited += b + 1 - a;
                    }
                }
            }
        }
        assert!(
            kept > 10_000 && visited < kept + kept / 2,
            "{kept} {visited}"
        );
    }
}
