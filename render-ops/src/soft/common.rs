//! Machinery shared by the soft rasterizers (`softras`, `dibr`): projection of clip positions,
//! binning of faces into screen tiles by their boxes expanded by a cut-off distance, the
//! closest point of a projected triangle's boundary to a pixel centre with its gradient, and
//! the chain from NDC to clip coordinates.

use autodiff::{Real, Tensor, Var};

use crate::raster::{RasterError, MAX_FRAGMENT_SLOTS};

/// Largest number of (tile, face) entries the soft methods' per-tile face lists may hold: a
/// face counts once for every 16 x 16 pixel tile its screen box, expanded by the coverage
/// cut-off, touches. Each entry is a 4-byte face id in the forward and a `3 x (4 + C)` `f64`
/// accumulator in the SoftRas backward (`3 x 4` for DIB-R), about 2.8 GB for RGB at the limit.
/// A fine mesh of small faces needs a few entries per face; a huge cut-off (e.g. SoftRas
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
pub(crate) fn project<T: Real>(clip: &Tensor<T>) -> (Vec<[f64; 2]>, Vec<f64>) {
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
}

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
        let tiles_x = width.div_ceil(TILE);
        let tiles_y = height.div_ceil(TILE);
        let mut tiles = vec![Vec::new(); tiles_x * tiles_y];
        let mut rects = vec![[1, 0, 1, 0]; faces.len()];
        for (fi, f) in faces.iter().enumerate() {
            let Some(rect) = face_rect(ndc, depth, f, width, height, dmax, cull_backfaces) else {
                continue;
            };
            rects[fi] = rect;
            for ty in rect[2] as usize / TILE..=rect[3] as usize / TILE {
                for tx in rect[0] as usize / TILE..=rect[1] as usize / TILE {
                    tiles[ty * tiles_x + tx].push(fi as u32);
                }
            }
        }
        Self {
            tiles_x,
            tiles,
            rects,
        }
    }

    /// Whether face `fi`'s expanded box holds pixel (row, col).
    #[inline]
    pub fn reaches(&self, fi: usize, row: usize, col: usize) -> bool {
        let rc = self.rects[fi];
        let (ci, ri) = (col as i64, row as i64);
        !(ci < rc[0] || ci > rc[1] || ri < rc[2] || ri > rc[3])
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
    let pixels = width.saturating_mul(height);
    if pixels > MAX_FRAGMENT_SLOTS {
        return Err(RasterError::TooLarge {
            request: format!("{op} at {width}x{height}"),
            what: "pixels",
            needed: pixels,
            limit: MAX_FRAGMENT_SLOTS,
        });
    }
    let Ok(clip) = clip.value() else {
        return Ok(());
    };
    if clip.ndim() != 2 || clip.shape()[1] != 4 {
        return Ok(());
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
        return Ok(());
    }
    let mut entries = 0usize;
    for f in faces {
        if let Some(r) = face_rect(&ndc, &depth, f, width, height, dmax, cull_backfaces) {
            let tx = (r[1] as usize / TILE - r[0] as usize / TILE + 1) as u128;
            let ty = (r[3] as usize / TILE - r[2] as usize / TILE + 1) as u128;
            entries = entries.saturating_add((tx * ty).min(usize::MAX as u128) as usize);
        }
    }
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
    Ok(())
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

/// Closest point of the boundary of triangle `v` to `p` (first edge wins ties).
#[inline]
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
