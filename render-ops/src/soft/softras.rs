//! SoftRas (Liu et al., ICCV 2019) as one tape op: clip positions [V, 4] and vertex attributes
//! [V, C] in, an RGBA-style image [H, W, C + 1] out (the last channel is the silhouette
//! `1 - prod_f (1 - D_f)`).
//!
//! Per face `f` and pixel centre `p` (NDC): `D_f = sigmoid(s d^2 / sigma)` with `d` the distance
//! from `p` to the projected triangle's boundary and `s = +1` inside, `-1` outside; pairs with
//! the centre outside and `D_f < threshold` are dropped, which bounds the distance by
//! `d_max^2 = sigma ln(1 / threshold - 1)`. Barycentrics are the screen-space barycentrics of `p`
//! clipped to `[0, 1]` and renormalised (as the reference does); attributes are interpolated with
//! them, or perspective-correctly when `perspective_correct` is set. Depth is `z = 1 / sum_k
//! (w_k / z_k)` with `z_k` the clip `w` (view depth), `z01 = (z - near) / (far - near)`,
//! `zn = 1 - z01`. Aggregation: `I = (sum_f D_f e_f c_f + e_b bg) / (sum_f D_f e_f + e_b)`,
//! `e_f = exp((zn_f - m) / gamma)`, `e_b = exp((eps - m) / gamma)`, `m = max(eps, max_f zn_f)`.
//! Faces with a vertex at `w <= 0` are skipped (no near clipping, as in SoftRas).
//!
//! Evaluation (forward): per 16 x 16 tile, each binned face is evaluated over the row spans
//! of its cut-off region within the tile (`common::FaceSpan`: the scanlines of the
//! triangle dilated by the cut-off along its edge normals), from per-face geometry precomputed
//! once (`common::FaceGeom`): affine barycentrics, the distance to the boundary of an
//! inside point as `min_k w_k alt_k`, and for an outside point a lower bound that rejects pairs
//! beyond the cut-off before the exact closest point. `D` and `1 - D` come from one
//! exponential. Two passes over the tile's faces with per-pixel accumulators (no per-pixel
//! lists): the first keeps each pair's `D`, `zn` and attribute weights and accumulates `m` and
//! `P`, the second the blend; each pixel's sums run in face order. The tiles' results are
//! then copied into the image and the per-pixel aggregate, image rows in parallel. The
//! backward runs in parallel over faces: each face re-evaluates its own pairs and reads what
//! it needs of the pixel's aggregate (`m`, `Z`, `P`, `I`) from the forward, so neither the
//! scatter into per-pixel lists nor the aggregate is redone; per-face sums are added to the
//! vertices in face order (bit-identical for any thread count). Silhouette stability: `P = prod (1 - D)`
//! is a plain product (each factor in `[0, 1]`, so it never overflows and is exactly 0 when
//! some `D = 1`); where `P >= 1/2` the silhouette is `-expm1(sum log1p(-D))` for full relative
//! precision of faint coverage. Its gradient is `d(1 - P)/dx_f = P D_f`, with no division by `1 - D_f`.
//!
//! `f32` tapes (the `fast` module): the same two-pass forward (over bands of 8 whole image rows
//! instead of tiles, so that row spans are not cut at tile columns, each band writing its
//! rows of the image and of the aggregate directly) and per-face backward, with each row
//! span evaluated 8 consecutive pixels at a time in single precision (eight-lane values the
//! compiler turns into AVX2 instructions in a build selected by runtime CPU detection, with a
//! portable build of the same source otherwise; both give the same bits). All three edges'
//! closest points are computed per lane and the nearest selected (no per-pixel branches);
//! occluded faces, whose depth weights `e_f` are exactly 0 in `f32`, skip the blend part of
//! the backward chain. `f64` tapes (gradient checks), `perspective_correct` and more than four
//! attribute channels keep the scalar `f64` evaluation above.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::common::{
    check_memory_projected, exp, ndc_to_clip, project, signed_distance_backward, Closest, FaceGeom,
    Projected, TileBins, TILE,
};
use super::lanes;
use crate::error::RenderError;

mod fast;

/// Settings of [`softras`].
#[derive(Clone, Debug, PartialEq)]
pub struct SoftSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Sharpness in squared NDC distance units (default 1e-4).
    pub sigma: f64,
    /// Depth blending temperature in `z01` units (default 1e-4).
    pub gamma: f64,
    /// Background depth term (default 1e-3).
    pub eps: f64,
    /// Coverage below which an outside face is ignored (default 1e-4).
    pub threshold: f64,
    /// Background value per attribute channel (empty: zeros).
    pub background: Vec<f64>,
    /// Near plane distance (for `z01`).
    pub near: f64,
    /// Far plane distance (for `z01`).
    pub far: f64,
    /// Interpolate attributes perspective-correctly (default `false`: screen space, as SoftRas).
    pub perspective_correct: bool,
}

impl SoftSettings {
    /// Defaults (sigma = gamma = 1e-4, eps = 1e-3, threshold = 1e-4) for a `width x height`
    /// image with the given near and far planes.
    pub fn new(width: usize, height: usize, near: f64, far: f64) -> Self {
        Self {
            width,
            height,
            sigma: 1e-4,
            gamma: 1e-4,
            eps: 1e-3,
            threshold: 1e-4,
            background: Vec::new(),
            near,
            far,
            perspective_correct: false,
        }
    }

    /// Squared cut-off distance `sigma ln(1 / threshold - 1)` (0 when threshold >= 0.5).
    pub fn cutoff_sq(&self) -> f64 {
        if self.threshold <= 0.0 {
            f64::INFINITY
        } else {
            (self.sigma * (1.0 / self.threshold - 1.0).ln()).max(0.0)
        }
    }

    fn validate(&self, channels: usize) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        if !(self.sigma > 0.0 && self.sigma.is_finite()) {
            return Err(format!("sigma must be finite and > 0, got {}", self.sigma));
        }
        if !(self.gamma > 0.0 && self.gamma.is_finite()) {
            return Err(format!("gamma must be finite and > 0, got {}", self.gamma));
        }
        if !self.eps.is_finite() {
            return Err(format!("eps must be finite, got {}", self.eps));
        }
        if !(0.0..1.0).contains(&self.threshold) {
            return Err(format!(
                "threshold must be in [0, 1), got {}",
                self.threshold
            ));
        }
        if !(self.far > self.near && self.near.is_finite() && self.far.is_finite()) {
            return Err(format!(
                "need near < far, got near {} far {}",
                self.near, self.far
            ));
        }
        if !self.background.is_empty() && self.background.len() != channels {
            return Err(format!(
                "background has {} values for {} attribute channels",
                self.background.len(),
                channels
            ));
        }
        Ok(())
    }
}

/// Renders `attrs` [V, C] over the faces with SoftRas from clip positions [V, 4]: an image
/// [H, W, C + 1] (the aggregated attributes, then the silhouette alpha), recorded on the tape.
pub fn softras<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &SoftSettings,
) -> Result<Var<'t, T>, RenderError> {
    let (cs, as_) = (clip.shape(), attrs.shape());
    if cs.len() != 2 || cs[1] != 4 {
        return Err(
            AutodiffError::shape("softras", &[&cs], "clip positions must be [V, 4]").into(),
        );
    }
    if as_.len() != 2 || as_[0] != cs[0] {
        return Err(AutodiffError::shape(
            "softras",
            &[&cs, &as_],
            "attributes must be [V, C] with V as clip",
        )
        .into());
    }
    settings
        .validate(as_[1])
        .map_err(|m| AutodiffError::invalid("softras", m))?;
    let v = cs[0] as u32;
    if let Some(f) = faces.iter().find(|f| f.iter().any(|&i| i >= v)) {
        return Err(AutodiffError::invalid(
            "softras",
            format!("face {f:?} indexes past {v} vertices"),
        )
        .into());
    }
    let pre = check_memory_projected(
        "softras",
        &clip,
        &faces,
        settings.width,
        settings.height,
        settings.cutoff_sq().sqrt(),
        false,
    )?;
    let op = SoftRasOp {
        faces,
        s: settings.clone(),
        prep: None,
        pre,
    };
    Ok(clip.tape().apply(op, &[clip, attrs]))
}

/// Projected vertices and the tile bins of one forward, and per pixel what the backward needs
/// of the forward's aggregate.
struct Prep {
    ndc: Vec<[f64; 2]>,
    depth: Vec<f64>,
    attrs: Vec<f64>,
    channels: usize,
    bins: TileBins,
    /// Per pixel (row-major), `PIX_STATS + C` values: `m` (the largest `zn`, at least `eps`),
    /// the blend's normaliser `Z = sum_f D_f e_f + e_b`, `P = prod_f (1 - D_f)`, then the C
    /// aggregated attributes `I`. Written by the forward.
    pix: Vec<f64>,
    /// Whether the `f32` fast path ([`fast`]) evaluates this render.
    fast: bool,
    /// Column centres padded for 8-lane chunks (fast path only).
    pxp: Vec<f64>,
    /// Per face, its `f32` geometry (fast path only).
    g32: Vec<lanes::Geom32>,
}

/// Leading per-pixel values of [`Prep::pix`] before the attributes.
const PIX_STATS: usize = 3;

/// One kept (face, pixel) pair of a tile, as the forward's first pass leaves it for the second.
#[derive(Clone, Copy, Default)]
struct Rec {
    /// Tile-local pixel index (row-major).
    lp: u32,
    /// `D = sigmoid(x)`, `x = s d^2 / sigma`.
    dd: f64,
    /// `1 - (z - near) / (far - near)`.
    zn: f64,
    /// Interpolation weights of the face's vertex attributes (`wn`, or `wn_k z / z_k`).
    wp: [f64; 3],
}

/// Per-thread scratch of the forward: the kept pairs of one tile in tile face order (`runs[li]
/// ..runs[li + 1]` are those of tile face `li`), and per tile pixel the running aggregate.
struct TileScratch {
    recs: Vec<Rec>,
    runs: Vec<usize>,
    /// Pairs per pixel.
    count: [u32; TILE * TILE],
    /// `m = max(eps, max_f zn_f)`.
    m: [f64; TILE * TILE],
    /// `P = prod (1 - D)`.
    prod: [f64; TILE * TILE],
    /// `Z = sum D e + e_b`.
    zsum: [f64; TILE * TILE],
    /// `sum log1p(-D)` (only where `P >= 1/2`).
    lsum: [f64; TILE * TILE],
    /// `sum D e c + e_b bg`, C per pixel.
    col: Vec<f64>,
    /// The current face's vertex attributes, `3 x C`.
    fa: Vec<f64>,
}

impl TileScratch {
    fn new(c: usize) -> Self {
        Self {
            recs: Vec::new(),
            runs: Vec::new(),
            count: [0; TILE * TILE],
            m: [0.0; TILE * TILE],
            prod: [0.0; TILE * TILE],
            zsum: [0.0; TILE * TILE],
            lsum: [0.0; TILE * TILE],
            col: vec![0.0; TILE * TILE * c],
            fa: vec![0.0; 3 * c],
        }
    }
}

pub(crate) struct SoftRasOp {
    faces: Arc<Vec<[u32; 3]>>,
    s: SoftSettings,
    prep: Option<Arc<Prep>>,
    /// The projection and face boxes of the clip positions the op was built for, from the
    /// memory check in [`softras`] (the tape runs the forward on those values right after):
    /// taken by the first forward instead of projecting and boxing the faces again.
    pre: Option<Projected>,
}

/// `(sigmoid(x), sigmoid(-x))` from one exponential `e = exp(-|x|)`, both to full relative
/// precision.
#[inline(always)]
fn sigmoid_from(x: f64, e: f64) -> (f64, f64) {
    let r = 1.0 / (1.0 + e);
    if x >= 0.0 {
        (r, e * r)
    } else {
        (e * r, r)
    }
}

/// Projection (or `pre`'s, computed from the same `clip` by the memory check) and binning
/// (faces into tiles only when not on the `fast` path, whose forward walks bands of rows).
fn prepare<T: Real, S: ndarray::Data<Elem = T>>(
    clip: &ndarray::ArrayBase<S, ndarray::IxDyn>,
    attrs: &ndarray::ArrayBase<S, ndarray::IxDyn>,
    faces: &[[u32; 3]],
    s: &SoftSettings,
    pre: Option<Projected>,
    fast: bool,
) -> Prep {
    let channels = attrs.shape()[1];
    let attrs: Vec<f64> = attrs.iter().map(|a| a.to_f64c()).collect();
    let dmax = s.cutoff_sq().sqrt();
    let (ndc, depth, bins) = match pre {
        Some(Projected { ndc, depth, rects }) if rects.len() == faces.len() => {
            let bins =
                TileBins::with_rects(&ndc, &depth, faces, s.width, s.height, dmax, rects, !fast);
            (ndc, depth, bins)
        }
        _ => {
            let (ndc, depth) = project(clip);
            let bins = TileBins::new(&ndc, &depth, faces, s.width, s.height, dmax, false);
            (ndc, depth, bins)
        }
    };
    Prep {
        ndc,
        depth,
        attrs,
        channels,
        bins,
        pix: Vec::new(),
        fast,
        pxp: Vec::new(),
        g32: Vec::new(),
    }
}

/// Pairs the backward evaluates together, stage by stage ([`SoftRasOp::face_gradient`]).
const BATCH: usize = 32;

/// Everything of one (face, pixel) pair that depends on the face's geometry and the pixel
/// only: the forward's first pass and the backward evaluate it with the same operations, so
/// they keep the same pairs and see the same values.
#[derive(Clone, Copy, Default)]
pub(crate) struct Pair {
    /// `x = s d^2 / sigma`.
    pub x: f64,
    /// Screen-space barycentrics of the pixel centre.
    pub w: [f64; 3],
    /// The same clipped to `[0, 1]` and renormalised.
    pub wn: [f64; 3],
    /// Sum of the clipped barycentrics.
    pub sumwc: f64,
    /// View depth `1 / sum_k wn_k / z_k`.
    pub z: f64,
    /// The closest boundary point, for a centre outside the triangle (inside, the backward
    /// takes the foot on the nearest edge, [`FaceGeom::closest_inside`]).
    pub closest: Closest,
}

impl SoftRasOp {
    /// The pair of face geometry `g` and pixel centre `p`, or `None` when it is dropped: the
    /// centre is outside the triangle and farther than the cut-off (a lower bound of the
    /// distance rejects most of those before the exact closest point, eq. (1)-(2) of the
    /// paper: `D = sigmoid(s d^2 / sigma)`), or its clipped barycentrics do not normalise.
    #[inline(always)]
    pub(crate) fn pair(g: &FaceGeom, p: [f64; 2], inv_sigma: f64, cut2: f64) -> Option<Pair> {
        let w = g.bary(p);
        let mut closest = Closest::default();
        let x = if w[0] >= 0.0 && w[1] >= 0.0 && w[2] >= 0.0 {
            g.inside_d2(&w) * inv_sigma
        } else {
            if g.outside_d2_bound(&w) > cut2 {
                return None;
            }
            closest = g.closest(p);
            if closest.d2 > cut2 {
                return None;
            }
            -closest.d2 * inv_sigma
        };
        let wc = w.map(|x| x.clamp(0.0, 1.0));
        let sumwc = wc[0] + wc[1] + wc[2];
        if !(sumwc > 0.0 && sumwc.is_finite()) {
            return None;
        }
        let inv = 1.0 / sumwc;
        let wn = wc.map(|x| x * inv);
        let z = 1.0 / (wn[0] * g.inv_d[0] + wn[1] * g.inv_d[1] + wn[2] * g.inv_d[2]);
        Some(Pair {
            x,
            w,
            wn,
            sumwc,
            z,
            closest,
        })
    }

    /// Interpolation weights of a pair's vertex attributes: `wn`, or perspective-correct
    /// `wn_k z / z_k`.
    #[inline(always)]
    fn attr_weights(&self, g: &FaceGeom, q: &Pair) -> [f64; 3] {
        attr_weights(g, q, self.s.perspective_correct)
    }

    /// Forward of tile `t` in two passes over its faces (in tile face order, each over the
    /// row spans of its cut-off region within the tile), with per-pixel accumulators instead
    /// of per-pixel sample lists. Pass 1 evaluates every pair (`D`, `zn`, attribute weights)
    /// into `sc.recs` and accumulates per pixel `m = max(eps, max_f zn_f)` and
    /// `P = prod_f (1 - D_f)`; pass 2 reads the pairs back and accumulates the blend of eq.
    /// (6) of the paper, `sum_f D_f e_f c_f + e_b bg` and `Z = sum_f D_f e_f + e_b` with
    /// `e_f = exp((zn_f - m) / gamma)`, and `sum log1p(-D_f)` where `P >= 1/2`. Writes
    /// `C + 1 + PIX_STATS` values per tile pixel (local row-major) to `out`: the attributes,
    /// the silhouette, then `m`, `Z`, `P`. Each pixel's sums run in face order, as a
    /// per-pixel list would, so the result does not depend on the thread count.
    fn tile_forward(&self, prep: &Prep, t: usize, sc: &mut TileScratch, out: &mut Vec<f64>) {
        let s = &self.s;
        let c = prep.channels;
        let bins = &prep.bins;
        let tf = &bins.tiles[t];
        let (c_base, r_base) = ((t % bins.tiles_x) * TILE, (t / bins.tiles_x) * TILE);
        let inv_sigma = 1.0 / s.sigma;
        let inv_gamma = 1.0 / s.gamma;
        let cut2 = s.cutoff_sq();
        let zscale = 1.0 / (s.far - s.near);
        sc.recs.clear();
        sc.runs.clear();
        sc.count.fill(0);
        sc.m.fill(s.eps);
        sc.prod.fill(1.0);
        // Pass 1: pairs, m and P.
        let mut qs = [Pair::default(); TILE];
        let mut lps = [0usize; TILE];
        let mut e_sig = [0.0f64; TILE];
        for &fi in tf.iter() {
            sc.runs.push(sc.recs.len());
            let Some([c0, c1, r0, r1]) = bins.face_in_tile(fi as usize, t, s.width, s.height)
            else {
                continue;
            };
            let g = &bins.geoms[fi as usize];
            let span = bins.span(fi as usize);
            for row in r0..=r1 {
                let py = bins.py[row];
                let Some((a, b)) = span.row(py, c0, c1) else {
                    continue;
                };
                let lbase = (row - r_base) * TILE;
                // The row's pairs (at most TILE) stage by stage, as in the backward: geometry,
                // exponentials, then the accumulation, so independent pairs overlap.
                let mut n = 0;
                for col in a..=b {
                    if let Some(q) = Self::pair(g, [bins.px[col], py], inv_sigma, cut2) {
                        qs[n] = q;
                        lps[n] = lbase + col - c_base;
                        n += 1;
                    }
                }
                for i in 0..n {
                    e_sig[i] = exp(-qs[i].x.abs());
                }
                for i in 0..n {
                    let (q, lp) = (&qs[i], lps[i]);
                    let (dd, omd) = sigmoid_from(q.x, e_sig[i]);
                    let zn = 1.0 - (q.z - s.near) * zscale;
                    sc.count[lp] += 1;
                    sc.m[lp] = sc.m[lp].max(zn);
                    sc.prod[lp] *= omd;
                    sc.recs.push(Rec {
                        lp: lp as u32,
                        dd,
                        zn,
                        wp: self.attr_weights(g, q),
                    });
                }
            }
        }
        sc.runs.push(sc.recs.len());
        // Background terms.
        for lp in 0..TILE * TILE {
            let eb = exp((s.eps - sc.m[lp]) * inv_gamma);
            sc.zsum[lp] = eb;
            sc.lsum[lp] = 0.0;
            for ch in 0..c {
                sc.col[lp * c + ch] = eb * s.background.get(ch).copied().unwrap_or(0.0);
            }
        }
        // Pass 2: the blend.
        for (li, &fi) in tf.iter().enumerate() {
            let recs = &sc.recs[sc.runs[li]..sc.runs[li + 1]];
            if recs.is_empty() {
                continue;
            }
            let f = self.faces[fi as usize];
            for k in 0..3 {
                let src = &prep.attrs[f[k] as usize * c..(f[k] as usize + 1) * c];
                sc.fa[k * c..(k + 1) * c].copy_from_slice(src);
            }
            for r in recs {
                let lp = r.lp as usize;
                if sc.prod[lp] >= 0.5 {
                    sc.lsum[lp] += (-r.dd).ln_1p();
                }
                // exp underflows to exactly 0 below -745.2: skip the call.
                let tt = (r.zn - sc.m[lp]) * inv_gamma;
                let ef = if tt < -746.0 { 0.0 } else { exp(tt) };
                let we = r.dd * ef;
                if we == 0.0 {
                    continue;
                }
                sc.zsum[lp] += we;
                let col = &mut sc.col[lp * c..(lp + 1) * c];
                for (ch, v) in col.iter_mut().enumerate() {
                    let a =
                        r.wp[0] * sc.fa[ch] + r.wp[1] * sc.fa[c + ch] + r.wp[2] * sc.fa[2 * c + ch];
                    *v += we * a;
                }
            }
        }
        out.clear();
        for lp in 0..TILE * TILE {
            if sc.count[lp] == 0 {
                out.extend((0..c).map(|ch| s.background.get(ch).copied().unwrap_or(0.0)));
                out.push(0.0);
            } else {
                let z = sc.zsum[lp];
                out.extend(sc.col[lp * c..(lp + 1) * c].iter().map(|&v| v / z));
                // Silhouette 1 - P. Where P is near 1 (faint coverage) the difference is taken
                // from the sum of logs, sum ln(1 - D) = sum log1p(-D), for full relative
                // precision.
                let p = sc.prod[lp];
                out.push(if p < 0.5 {
                    1.0 - p
                } else {
                    -sc.lsum[lp].exp_m1()
                });
            }
            out.extend([sc.m[lp], sc.zsum[lp], sc.prod[lp]]);
        }
    }
}

/// Interpolation weights of a pair's vertex attributes: the clipped, renormalised
/// barycentrics `wn`, or perspective-correct `wn_k z / z_k`.
#[inline(always)]
pub(crate) fn attr_weights(g: &FaceGeom, q: &Pair, perspective_correct: bool) -> [f64; 3] {
    if perspective_correct {
        [
            q.wn[0] * g.inv_d[0] * q.z,
            q.wn[1] * g.inv_d[1] * q.z,
            q.wn[2] * g.inv_d[2] * q.z,
        ]
    } else {
        q.wn
    }
}

/// Chains the gradients of a pair's clipped, renormalised barycentrics (`gwn`) and of its view
/// depth `z = 1 / sum_k wn_k / z_k` (`gz`) to the face's NDC vertices (`gv`) and vertex view
/// depths (`gdep`): through `z`, the clip-and-renormalise of the barycentrics, and the raw
/// screen-space barycentrics `w_k = n_k / sum n` at pixel centre `p` (`inv_area = 1 /
/// g.area`). Shared by SoftRas's fused backward and the soft fragment stage's.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn pair_backward(
    g: &FaceGeom,
    q: &Pair,
    p: [f64; 2],
    mut gwn: [f64; 3],
    gz: f64,
    inv_area: f64,
    gv: &mut [[f64; 2]; 3],
    gdep: &mut [f64; 3],
) {
    let (v, inv_d) = (&g.v, &g.inv_d);
    let gzinv = -q.z * q.z * gz;
    for k in 0..3 {
        gwn[k] += gzinv * inv_d[k];
        gdep[k] -= gzinv * q.wn[k] * inv_d[k] * inv_d[k];
    }
    // Clip-and-renormalise, then raw barycentrics w_k = n_k / sum n.
    let dot = gwn[0] * q.wn[0] + gwn[1] * q.wn[1] + gwn[2] * q.wn[2];
    let inv_sumwc = 1.0 / q.sumwc;
    let mut gw = [0.0; 3];
    for k in 0..3 {
        if q.w[k] > 0.0 && q.w[k] < 1.0 {
            gw[k] = (gwn[k] - dot) * inv_sumwc;
        }
    }
    let dot2 = gw[0] * q.w[0] + gw[1] * q.w[1] + gw[2] * q.w[2];
    for k in 0..3 {
        let gn = (gw[k] - dot2) * inv_area;
        if gn == 0.0 {
            continue;
        }
        let (i, j) = ((k + 1) % 3, (k + 2) % 3);
        let a = [v[i][0] - p[0], v[i][1] - p[1]];
        let b = [v[j][0] - p[0], v[j][1] - p[1]];
        // n_k = cross(a, b).
        gv[i][0] += gn * b[1];
        gv[i][1] -= gn * b[0];
        gv[j][0] -= gn * a[1];
        gv[j][1] += gn * a[0];
    }
}

/// `(sigmoid(x), sigmoid(-x))` of a pair's `x`, from one exponential.
#[inline(always)]
pub(crate) fn coverage_sigmoid(x: f64) -> (f64, f64) {
    sigmoid_from(x, exp(-x.abs()))
}

impl<T: Real> Op<T> for SoftRasOp {
    fn name(&self) -> &'static str {
        "softras"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let pre = self.pre.take();
        let fast = T::as_f32(&[]).is_some()
            && inputs[1].shape()[1] <= fast::FAST_MAX_C
            && !self.s.perspective_correct
            && fast::f32_range_ok(&self.s);
        let mut prep = prepare(&inputs[0], &inputs[1], &self.faces, &self.s, pre, fast);
        let (w, h, c) = (self.s.width, self.s.height, prep.channels);
        if prep.fast {
            prep.pxp = lanes::padded_px(&prep.bins.px);
            prep.g32 = lanes::geoms32(&prep.bins);
        }
        let this = &*self;
        let pstride = PIX_STATS + c;
        if prep.fast {
            // Bands of image rows in parallel, each straight into its rows of the image and
            // of `pix` (every pixel written).
            let rows = lanes::band_rows(w);
            let bands = lanes::band_faces(&prep.bins, h, rows);
            let mut img = vec![T::from_f64c(0.0); h * w * (c + 1)];
            // Every value of `pix` is written by its band (no image-sized zeroing first).
            let mut pix: Vec<f64> = Vec::with_capacity(h * w * pstride);
            {
                let prep = &prep;
                let img32 = T::as_f32_mut(&mut img).expect("the fast path runs on f32 tapes");
                img32
                    .par_chunks_mut(rows * w * (c + 1))
                    .zip(
                        pix.spare_capacity_mut()[..h * w * pstride]
                            .par_chunks_mut(rows * w * pstride),
                    )
                    .zip(bands.par_iter())
                    .enumerate()
                    .for_each_init(
                        || fast::Scratch32::new(c, w),
                        |sc, (band, ((irow, prow), tf))| {
                            this.band_forward32(prep, band, tf, sc, irow, prow)
                        },
                    );
            }
            // SAFETY: the capacity is h w pstride, and the bands (h / rows rounded up, each
            // over its rows of every column) wrote all `pstride` values of each of their
            // pixels (`band_forward32` writes them for covered and uncovered pixels alike).
            unsafe { pix.set_len(h * w * pstride) };
            prep.pix = pix;
            self.prep = Some(Arc::new(prep));
            return Ok(vec![
                ArrayD::from_shape_vec(IxDyn(&[h, w, c + 1]), img).expect("h w c+1")
            ]);
        }
        let bg: Vec<f64> = (0..c)
            .map(|ch| this.s.background.get(ch).copied().unwrap_or(0.0))
            .chain([0.0])
            .collect();
        // Parallel over tiles, each into its own buffer (local row-major, C + 1 + PIX_STATS
        // values a pixel).
        let per = c + 1 + PIX_STATS;
        let tiles: Vec<Vec<f64>> = {
            let prep = &prep;
            let bins = &prep.bins;
            (0..bins.tiles.len())
                .into_par_iter()
                .map_init(
                    || TileScratch::new(c),
                    |sc, t| {
                        let mut out = Vec::new();
                        if !bins.tiles[t].is_empty() {
                            out.reserve(TILE * TILE * per);
                            this.tile_forward(prep, t, sc, &mut out);
                        }
                        out
                    },
                )
                .collect()
        };
        // Rows in parallel, each from the tiles of its tile row into the image and `pix`.
        let bins = &prep.bins;
        let mut img = vec![T::from_f64c(0.0); h * w * (c + 1)];
        let mut pix = vec![0.0; h * w * pstride];
        img.par_chunks_mut(w * (c + 1))
            .zip(pix.par_chunks_mut(w * pstride))
            .enumerate()
            .with_min_len(8)
            .for_each(|(row, (irow, prow))| {
                for tx in 0..bins.tiles_x {
                    let tile = &tiles[(row / TILE) * bins.tiles_x + tx];
                    let cols = TILE.min(w - tx * TILE);
                    for j in 0..cols {
                        let col = tx * TILE + j;
                        let io = &mut irow[col * (c + 1)..(col + 1) * (c + 1)];
                        if tile.is_empty() {
                            for (d, &v) in io.iter_mut().zip(&bg) {
                                *d = T::from_f64c(v);
                            }
                            continue;
                        }
                        let o = ((row % TILE) * TILE + j) * per;
                        let v = &tile[o..o + per];
                        for (d, &v) in io.iter_mut().zip(&v[..c + 1]) {
                            *d = T::from_f64c(v);
                        }
                        let q = col * pstride;
                        prow[q..q + PIX_STATS].copy_from_slice(&v[c + 1..]);
                        prow[q + PIX_STATS..q + pstride].copy_from_slice(&v[..c]);
                    }
                }
            });
        prep.pix = pix;
        self.prep = Some(Arc::new(prep));
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[h, w, c + 1]), img).expect("h w c+1")
        ])
    }

    /// Parallel over faces: each face sums its pairs' gradients over its own cut-off region
    /// (row spans of its box, in row-major order) from the forward's per-pixel aggregate
    /// ([`Prep::pix`]), so no per-pixel lists are rebuilt; the per-face sums are then added to
    /// the vertices in face order, so results are bit-identical for any thread count.
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let prep = self
            .prep
            .as_ref()
            .ok_or_else(|| AutodiffError::invalid("softras", "backward before forward"))?;
        let c = prep.channels;
        let go = ctx.grad_outputs[0].as_standard_layout();
        let go = go.as_slice().expect("standard layout");
        let stride = 3 * (4 + c);
        let per_face = match T::as_f32(go) {
            Some(go32) if prep.fast => {
                let planes = fast::Planes::new(prep, go32);
                prep.bins.per_face(stride, |fi, acc| {
                    self.face_gradient32(prep, &prep.pxp, fi, &planes, acc)
                })
            }
            _ => {
                let go: Vec<f64> = go.iter().map(|x| x.to_f64c()).collect();
                self.per_face_f64(prep, &go)
            }
        };
        let nv = prep.ndc.len();
        let mut gclip = vec![0.0; nv * 4];
        let mut gattr = vec![0.0; nv * c];
        for (fi, f) in self.faces.iter().enumerate() {
            let Some(a) = per_face.get(fi) else {
                continue;
            };
            for k in 0..3 {
                let v = f[k] as usize;
                let ak = &a[k * (4 + c)..(k + 1) * (4 + c)];
                for j in 0..4 {
                    gclip[v * 4 + j] += ak[j];
                }
                for ch in 0..c {
                    gattr[v * c + ch] += ak[4 + ch];
                }
            }
        }
        let to_t = |v: Vec<f64>, shape: &[usize]| {
            ArrayD::from_shape_vec(IxDyn(shape), v.into_iter().map(T::from_f64c).collect())
                .expect("shape")
        };
        Ok(vec![
            ctx.needs_grad[0].then(|| to_t(gclip, &[nv, 4])),
            ctx.needs_grad[1].then(|| to_t(gattr, &[nv, c])),
        ])
    }
}

impl SoftRasOp {
    /// The `f64` backward's per-face sums ([`SoftRasOp::face_gradient`]).
    fn per_face_f64(&self, prep: &Prep, go: &[f64]) -> crate::soft::common::PerFace {
        let c = prep.channels;
        // Per pixel, what every pair there needs, packed (C + 4 values): the attribute
        // gradient g, then g_alpha P, g . I, 1 / Z and m (infinite where g is 0: skipped).
        let pstride = PIX_STATS + c;
        let bstride = c + 4;
        let mut pb = vec![0.0; (go.len() / (c + 1)) * bstride];
        pb.par_chunks_mut(bstride)
            .zip(go.par_chunks(c + 1))
            .zip(prep.pix.par_chunks(pstride))
            .with_min_len(1024)
            .for_each(|((b, g), st)| {
                if g.iter().all(|&x| x == 0.0) {
                    b[c + 3] = f64::INFINITY;
                    return;
                }
                b[..c].copy_from_slice(&g[..c]);
                b[c] = g[c] * st[2];
                b[c + 1] = (0..c).map(|ch| g[ch] * st[PIX_STATS + ch]).sum();
                b[c + 2] = 1.0 / st[1];
                b[c + 3] = st[0];
            });
        // Per face: [dX, dY, dZ, dW, dattr...] of each corner, summed into the vertices in
        // face order.
        prep.bins.per_face(3 * (4 + c), |fi, acc| {
            self.face_gradient(prep, fi, &pb, acc)
        })
    }
}

impl SoftRasOp {
    /// Gradient of the loss with respect to face `fi`'s three vertices, summed over its pairs
    /// (`pb`: per pixel, row-major, `C + 4` values: the attribute gradient `g`, `g_alpha P`,
    /// `g . I`, `1 / Z`, `m`, as the backward packs them): `acc[k * (4 + C)..]` gets
    /// [dX, dY, dZ, dW, dattr...] of corner k.
    ///
    /// Per pair, with `g` the pixel's output gradient, `I` its attributes, `a_f` the face's
    /// interpolated attributes, `e_f` its depth weight and `Z` the normaliser (eq. (6) of the
    /// paper): `dL/dx = (e_f (g . (a_f - I)) / Z) D (1 - D) + g_alpha P D` (the blend, and the
    /// silhouette `1 - P` with `d(1 - P)/dx_f = P D_f`), `dL/dzn = D e_f (g . (a_f - I)) /
    /// (Z gamma)`, `dL/da_f = g D e_f / Z`. These are chained through the distance (closest
    /// boundary point), the clipped barycentrics and the depth to the face's NDC vertices and
    /// view depths, accumulated per face, and taken to clip coordinates once at the end.
    fn face_gradient(&self, prep: &Prep, fi: usize, pb: &[f64], acc: &mut [f64]) {
        let s = &self.s;
        let bins = &prep.bins;
        let rc = bins.rects[fi];
        if rc[0] > rc[1] {
            return;
        }
        let c = prep.channels;
        let bstride = c + 4;
        let stride = 4 + c;
        let f = self.faces[fi];
        let geom = &bins.geoms[fi];
        let v = geom.v;
        let inv_d = geom.inv_d;
        let inv_area = 1.0 / geom.area;
        let inv_sigma = 1.0 / s.sigma;
        let inv_gamma = 1.0 / s.gamma;
        let cut2 = s.cutoff_sq();
        let zscale = 1.0 / (s.far - s.near);
        let fa = |k: usize, ch: usize| prep.attrs[f[k] as usize * c + ch];
        // NDC and view-depth gradients of the three vertices.
        let mut gv = [[0.0f64; 2]; 3];
        let mut gdep = [0.0f64; 3];
        let mut qs = [Pair::default(); BATCH];
        let mut cols = [0usize; BATCH];
        let (mut e_sig, mut e_f) = ([0.0f64; BATCH], [0.0f64; BATCH]);
        for (row, py, a, b) in bins.face_rows(fi) {
            // In batches of up to BATCH kept pairs: first their geometry, then their two
            // exponentials, then the chain rule, so that the long dependency chains of
            // independent pairs overlap instead of running one after another.
            let mut next = a;
            while next <= b {
                let mut n = 0;
                while next <= b && n < BATCH {
                    let col = next;
                    next += 1;
                    let pi = row * s.width + col;
                    if pb[pi * bstride + c + 3] == f64::INFINITY {
                        continue;
                    }
                    let p = [bins.px[col], py];
                    if let Some(q) = Self::pair(geom, p, inv_sigma, cut2) {
                        qs[n] = q;
                        cols[n] = col;
                        n += 1;
                    }
                }
                for i in 0..n {
                    let pi = row * s.width + cols[i];
                    let m = pb[pi * bstride + c + 3];
                    let zn = 1.0 - (qs[i].z - s.near) * zscale;
                    let tt = (zn - m) * inv_gamma;
                    e_sig[i] = exp(-qs[i].x.abs());
                    e_f[i] = if tt < -746.0 { 0.0 } else { exp(tt) };
                }
                for i in 0..n {
                    let (q, col) = (&qs[i], cols[i]);
                    let pi = row * s.width + col;
                    let pbx = &pb[pi * bstride..(pi + 1) * bstride];
                    let (g, ga_prod, g_img, inv_z) = (&pbx[..c], pbx[c], pbx[c + 1], pbx[c + 2]);
                    let p = [bins.px[col], py];
                    let (dd, omd) = sigmoid_from(q.x, e_sig[i]);
                    let ef = e_f[i];
                    let wp = self.attr_weights(geom, q);
                    // The blend's terms vanish with D e_f (as in the forward, which skips them).
                    let (gblend, gscale) = if dd * ef == 0.0 {
                        (0.0, 0.0)
                    } else {
                        // g . (a_f - I).
                        let mut cdiff = -g_img;
                        for ch in 0..c {
                            let a = wp[0] * fa(0, ch) + wp[1] * fa(1, ch) + wp[2] * fa(2, ch);
                            cdiff += g[ch] * a;
                        }
                        (ef * cdiff * inv_z, dd * ef * inv_z)
                    };
                    let gx = gblend * dd * omd + ga_prod * dd;
                    let g_zn = dd * gblend * inv_gamma;
                    // Coverage: x = s d2 / sigma, d2 the squared distance to the closest boundary
                    // point (for an inside point the foot on the nearest edge line).
                    signed_distance_backward(
                        geom,
                        p,
                        q.x,
                        &q.w,
                        &q.closest,
                        gx * inv_sigma,
                        &mut gv,
                    );
                    if gscale == 0.0 && g_zn == 0.0 {
                        continue;
                    }
                    // Depth and attributes.
                    let mut gz = -g_zn * zscale;
                    let mut gwn = [0.0f64; 3];
                    if s.perspective_correct {
                        // c = z u, u = sum_k wn_k C_k / z_k.
                        for ch in 0..c {
                            let gc = g[ch] * gscale;
                            if gc == 0.0 {
                                continue;
                            }
                            let ck = [fa(0, ch), fa(1, ch), fa(2, ch)];
                            let u = q.wn[0] * ck[0] * inv_d[0]
                                + q.wn[1] * ck[1] * inv_d[1]
                                + q.wn[2] * ck[2] * inv_d[2];
                            gz += gc * u;
                            let gu = q.z * gc;
                            for k in 0..3 {
                                gwn[k] += gu * ck[k] * inv_d[k];
                                acc[k * stride + 4 + ch] += gu * q.wn[k] * inv_d[k];
                                gdep[k] -= gu * ck[k] * q.wn[k] * inv_d[k] * inv_d[k];
                            }
                        }
                    } else {
                        for ch in 0..c {
                            let gc = g[ch] * gscale;
                            if gc == 0.0 {
                                continue;
                            }
                            for k in 0..3 {
                                gwn[k] += gc * fa(k, ch);
                                acc[k * stride + 4 + ch] += gc * q.wn[k];
                            }
                        }
                    }
                    pair_backward(geom, q, p, gwn, gz, inv_area, &mut gv, &mut gdep);
                }
            }
        }
        // NDC and view depth to clip coordinates (linear in the NDC gradient, so once per face).
        for k in 0..3 {
            let g = ndc_to_clip(gv[k], v[k], prep.depth[f[k] as usize]);
            let o = k * stride;
            acc[o] += g[0];
            acc[o + 1] += g[1];
            acc[o + 3] += g[2] + gdep[k];
        }
    }
}
