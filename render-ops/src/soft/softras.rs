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
//! Evaluation: per 16 x 16 tile, each binned face is evaluated over its cut-off box within the
//! tile (a scatter into per-pixel sample lists, in face order), from per-face geometry
//! precomputed once ([`super::common::FaceGeom`]): affine barycentrics, the distance to the
//! boundary of an inside point as `min_k w_k alt_k`, and for an outside point a lower bound
//! that rejects pairs beyond the cut-off before the exact closest point. `D` and `1 - D` come
//! from one exponential. Silhouette stability: `P = prod (1 - D)` is a plain product (each
//! factor in `[0, 1]`, so it never overflows and is exactly 0 when some `D = 1`); where
//! `P >= 1/2` the silhouette is `-expm1(sum log1p(-D))` for full relative precision of faint
//! coverage. Its gradient is `d(1 - P)/dx_f = P D_f`, with no division by `1 - D_f`.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::common::{
    check_memory, closest_backward, ndc_to_clip, project, FaceGeom, TileBins, TILE,
};
use crate::error::RenderError;

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
    check_memory(
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
    };
    Ok(clip.tape().apply(op, &[clip, attrs]))
}

/// Projected vertices and the tile bins of one forward.
struct Prep {
    ndc: Vec<[f64; 2]>,
    depth: Vec<f64>,
    attrs: Vec<f64>,
    channels: usize,
    bins: TileBins,
}

/// One face at one pixel: the face is kept if the pixel centre is inside it, or outside within
/// the cut-off.
#[derive(Clone, Copy, Default)]
struct Sample {
    /// Index into the tile's face list.
    li: u32,
    /// `x = s d^2 / sigma`.
    x: f64,
    /// `D = sigmoid(x)`.
    dd: f64,
    /// `1 - D = sigmoid(-x)`.
    omd: f64,
    /// Screen-space barycentrics of the pixel centre.
    w: [f64; 3],
    /// The same clipped to `[0, 1]` and renormalised.
    wn: [f64; 3],
    /// Sum of the clipped barycentrics.
    sumwc: f64,
    /// View depth `1 / sum_k wn_k / d_k`.
    z: f64,
    /// `1 - (z - near) / (far - near)`.
    zn: f64,
    /// `exp((zn - m) / gamma)`, set by [`SoftRasOp::aggregate`].
    ef: f64,
}

/// Per-thread scratch: the samples of every pixel of one tile (local row-major order), each
/// list in tile face order.
struct TileScratch {
    lists: Vec<Vec<Sample>>,
}

impl TileScratch {
    fn new() -> Self {
        Self {
            lists: (0..TILE * TILE).map(|_| Vec::new()).collect(),
        }
    }
}

struct SoftRasOp {
    faces: Arc<Vec<[u32; 3]>>,
    s: SoftSettings,
    prep: Option<Arc<Prep>>,
}

/// `(sigmoid(x), sigmoid(-x))` from one exponential, both to full relative precision.
#[inline(always)]
fn sigmoid_pair(x: f64) -> (f64, f64) {
    let e = (-x.abs()).exp();
    let r = 1.0 / (1.0 + e);
    if x >= 0.0 {
        (r, e * r)
    } else {
        (e * r, r)
    }
}

fn prepare<T: Real>(
    clip: &Tensor<T>,
    attrs: &Tensor<T>,
    faces: &[[u32; 3]],
    s: &SoftSettings,
) -> Prep {
    let channels = attrs.shape()[1];
    let (ndc, depth) = project(clip);
    let attrs: Vec<f64> = attrs.iter().map(|a| a.to_f64c()).collect();
    let bins = TileBins::new(
        &ndc,
        &depth,
        faces,
        s.width,
        s.height,
        s.cutoff_sq().sqrt(),
        false,
    );
    Prep {
        ndc,
        depth,
        attrs,
        channels,
        bins,
    }
}

impl SoftRasOp {
    /// Evaluates every face of tile `t` over its (cut-off expanded) box within the tile: the
    /// samples of each pixel go to `sc.lists` (local row-major), each list in tile face order.
    /// Pairs outside the triangle beyond the cut-off are rejected by a lower bound of their
    /// distance before the exact closest point is computed.
    fn tile_samples(&self, prep: &Prep, t: usize, sc: &mut TileScratch) {
        let s = &self.s;
        let bins = &prep.bins;
        for l in sc.lists.iter_mut() {
            l.clear();
        }
        let (c_base, r_base) = ((t % bins.tiles_x) * TILE, (t / bins.tiles_x) * TILE);
        let inv_sigma = 1.0 / s.sigma;
        let cut2 = s.cutoff_sq();
        let zscale = 1.0 / (s.far - s.near);
        for (li, &fi) in bins.tiles[t].iter().enumerate() {
            let Some([c0, c1, r0, r1]) = bins.face_in_tile(fi as usize, t, s.width, s.height)
            else {
                continue;
            };
            let g = &bins.geoms[fi as usize];
            for row in r0..=r1 {
                let py = bins.py[row];
                let lbase = (row - r_base) * TILE;
                for col in c0..=c1 {
                    let p = [bins.px[col], py];
                    let w = g.bary(p);
                    let x = if w[0] >= 0.0 && w[1] >= 0.0 && w[2] >= 0.0 {
                        g.inside_d2(&w) * inv_sigma
                    } else {
                        if g.outside_d2_bound(&w) > cut2 {
                            continue;
                        }
                        let d2 = g.closest(p).d2;
                        if d2 > cut2 {
                            continue;
                        }
                        -d2 * inv_sigma
                    };
                    let wc = w.map(|x| x.clamp(0.0, 1.0));
                    let sumwc = wc[0] + wc[1] + wc[2];
                    if !(sumwc > 0.0 && sumwc.is_finite()) {
                        continue;
                    }
                    let wn = wc.map(|x| x / sumwc);
                    let z = 1.0 / (wn[0] * g.inv_d[0] + wn[1] * g.inv_d[1] + wn[2] * g.inv_d[2]);
                    let (dd, omd) = sigmoid_pair(x);
                    sc.lists[lbase + col - c_base].push(Sample {
                        li: li as u32,
                        x,
                        dd,
                        omd,
                        w,
                        wn,
                        sumwc,
                        z,
                        zn: 1.0 - (z - s.near) * zscale,
                        ef: 0.0,
                    });
                }
            }
        }
    }

    /// Interpolation weights of a sample's vertex attributes: `wn`, or perspective-correct
    /// `wn_k z / d_k`.
    #[inline]
    fn attr_weights(&self, g: &FaceGeom, q: &Sample) -> [f64; 3] {
        if self.s.perspective_correct {
            [
                q.wn[0] * g.inv_d[0] * q.z,
                q.wn[1] * g.inv_d[1] * q.z,
                q.wn[2] * g.inv_d[2] * q.z,
            ]
        } else {
            q.wn
        }
    }

    /// Aggregates the samples of one pixel (of a tile with face list `tf`): writes the C
    /// attributes and alpha into `px`, sets each sample's `ef`, keeps each sample's
    /// interpolated attributes in `cols` (C per sample; zeros where its blend weight is 0, as
    /// the backward then multiplies them by 0), returns `(Z, P)`: the blend's normaliser and
    /// `P = prod (1 - D)`.
    fn aggregate(
        &self,
        prep: &Prep,
        tf: &[u32],
        samples: &mut [Sample],
        px: &mut [f64],
        cols: &mut Vec<f64>,
    ) -> (f64, f64) {
        let s = &self.s;
        let c = prep.channels;
        let m = samples.iter().fold(s.eps, |m, q| m.max(q.zn));
        let inv_gamma = 1.0 / s.gamma;
        let eb = ((s.eps - m) * inv_gamma).exp();
        let mut zsum = eb;
        for (ch, v) in px[..c].iter_mut().enumerate() {
            *v = eb * s.background.get(ch).copied().unwrap_or(0.0);
        }
        let mut prod = 1.0;
        cols.clear();
        cols.resize(samples.len() * c, 0.0);
        for (j, q) in samples.iter_mut().enumerate() {
            // exp underflows to exactly 0 below -745.2: skip the call.
            let t = (q.zn - m) * inv_gamma;
            q.ef = if t < -746.0 { 0.0 } else { t.exp() };
            prod *= q.omd;
            let we = q.dd * q.ef;
            if we == 0.0 {
                continue;
            }
            zsum += we;
            let fi = tf[q.li as usize] as usize;
            let f = self.faces[fi];
            let wp = self.attr_weights(&prep.bins.geoms[fi], q);
            let col = &mut cols[j * c..(j + 1) * c];
            for (ch, (v, cv)) in px[..c].iter_mut().zip(col.iter_mut()).enumerate() {
                let a = wp[0] * prep.attrs[f[0] as usize * c + ch]
                    + wp[1] * prep.attrs[f[1] as usize * c + ch]
                    + wp[2] * prep.attrs[f[2] as usize * c + ch];
                *cv = a;
                *v += we * a;
            }
        }
        for v in px[..c].iter_mut() {
            *v /= zsum;
        }
        // Silhouette 1 - P. Where P is near 1 (faint coverage) the difference is taken from
        // the sum of logs, sum ln(1 - D) = sum log1p(-D), for full relative precision.
        px[c] = if prod < 0.5 {
            1.0 - prod
        } else {
            -samples
                .iter()
                .map(|q| (-q.dd).ln_1p())
                .sum::<f64>()
                .exp_m1()
        };
        (zsum, prod)
    }
}

impl<T: Real> Op<T> for SoftRasOp {
    fn name(&self) -> &'static str {
        "softras"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> AdResult<Vec<Tensor<T>>> {
        let prep = Arc::new(prepare(inputs[0], inputs[1], &self.faces, &self.s));
        let (w, h, c) = (self.s.width, self.s.height, prep.channels);
        let this = &*self;
        let bins = &prep.bins;
        let bg: Vec<f64> = (0..c)
            .map(|ch| this.s.background.get(ch).copied().unwrap_or(0.0))
            .chain([0.0])
            .collect();
        // Parallel over tiles, each into its own buffer (local row-major, C + 1 values a pixel).
        let tiles: Vec<Vec<f64>> = (0..bins.tiles.len())
            .into_par_iter()
            .map_init(
                || (TileScratch::new(), vec![0.0; c + 1], Vec::new()),
                |(sc, px, colbuf), t| {
                    if bins.tiles[t].is_empty() {
                        return Vec::new();
                    }
                    this.tile_samples(&prep, t, sc);
                    let tf = &bins.tiles[t];
                    let mut out = Vec::with_capacity(TILE * TILE * (c + 1));
                    for samples in sc.lists.iter_mut() {
                        if samples.is_empty() {
                            out.extend_from_slice(&bg);
                        } else {
                            this.aggregate(&prep, tf, samples, px, colbuf);
                            out.extend_from_slice(px);
                        }
                    }
                    out
                },
            )
            .collect();
        let mut img = Vec::with_capacity(h * w * (c + 1));
        for row in 0..h {
            for tx in 0..bins.tiles_x {
                let tile = &tiles[(row / TILE) * bins.tiles_x + tx];
                let cols = TILE.min(w - tx * TILE);
                if tile.is_empty() {
                    for _ in 0..cols {
                        img.extend(bg.iter().map(|&v| T::from_f64c(v)));
                    }
                } else {
                    let o = (row % TILE) * TILE * (c + 1);
                    img.extend(tile[o..o + cols * (c + 1)].iter().map(|&v| T::from_f64c(v)));
                }
            }
        }
        self.prep = Some(prep);
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[h, w, c + 1]), img).expect("h w c+1")
        ])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let prep = self
            .prep
            .as_ref()
            .ok_or_else(|| AutodiffError::invalid("softras", "backward before forward"))?;
        let s = &self.s;
        let (w, h, c) = (s.width, s.height, prep.channels);
        let go = ctx.grad_outputs[0].as_standard_layout();
        let go: Vec<f64> = go.iter().map(|x| x.to_f64c()).collect();
        let stride = 3 * (4 + c);
        let bins = &prep.bins;
        let inv_gamma = 1.0 / s.gamma;
        // Per tile: accumulators per (tile face, corner) of [dX, dY, dZ, dW, dattr...].
        let accs: Vec<Vec<f64>> = (0..bins.tiles.len())
            .into_par_iter()
            .map_init(
                || (TileScratch::new(), vec![0.0; c + 1], Vec::new()),
                |(sc, px, colbuf), t| {
                    let tf = &bins.tiles[t];
                    let mut acc = vec![0.0; tf.len() * stride];
                    if tf.is_empty() {
                        return acc;
                    }
                    let (tx, ty) = (t % bins.tiles_x, t / bins.tiles_x);
                    let grad_at = |row: usize, col: usize| {
                        &go[(row * w + col) * (c + 1)..(row * w + col + 1) * (c + 1)]
                    };
                    let rows = ty * TILE..(ty * TILE + TILE).min(h);
                    let cols = tx * TILE..(tx * TILE + TILE).min(w);
                    if rows.clone().all(|r| {
                        cols.clone()
                            .all(|cc| grad_at(r, cc).iter().all(|&x| x == 0.0))
                    }) {
                        return acc;
                    }
                    self.tile_samples(prep, t, sc);
                    for row in rows {
                        for col in cols.clone() {
                            let g = grad_at(row, col);
                            let samples = &mut sc.lists[(row - ty * TILE) * TILE + col - tx * TILE];
                            if samples.is_empty() || g.iter().all(|&x| x == 0.0) {
                                continue;
                            }
                            let (zsum, prod) = self.aggregate(prep, tf, samples, px, colbuf);
                            let p = [bins.px[col], bins.py[row]];
                            for (j, q) in samples.iter().enumerate() {
                                let fi = tf[q.li as usize] as usize;
                                let colq = &colbuf[j * c..(j + 1) * c];
                                let cdiff: f64 = (0..c).map(|ch| g[ch] * (colq[ch] - px[ch])).sum();
                                // dL/dx through D in the blend (dD/dx = D (1 - D)) and in the
                                // silhouette (d(1 - P)/dx_f = P D_f).
                                let gblend = q.ef * cdiff / zsum;
                                let gx = gblend * q.dd * q.omd + g[c] * prod * q.dd;
                                let g_zn = q.dd * gblend * inv_gamma;
                                let gscale = q.dd * q.ef / zsum;
                                let li = q.li as usize;
                                let a = &mut acc[li * stride..(li + 1) * stride];
                                self.face_backward(prep, fi, p, q, gx, g_zn, &g[..c], gscale, a);
                            }
                        }
                    }
                    acc
                },
            )
            .collect();
        let nv = prep.ndc.len();
        let mut gclip = vec![0.0; nv * 4];
        let mut gattr = vec![0.0; nv * c];
        for (t, acc) in accs.iter().enumerate() {
            for (li, &fi) in bins.tiles[t].iter().enumerate() {
                let f = self.faces[fi as usize];
                let a = &acc[li * stride..(li + 1) * stride];
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
    /// Chains dL/dx (x = s d^2 / sigma), dL/dzn and dL/d(interpolated attribute)
    /// (= `g_col * gscale`) of one sample at pixel `p` down to its three vertices:
    /// `acc[k * (4 + C)..]` gets [dX, dY, dZ, dW, dattr...] of corner k.
    #[allow(clippy::too_many_arguments)]
    fn face_backward(
        &self,
        prep: &Prep,
        fi: usize,
        p: [f64; 2],
        q: &Sample,
        gx: f64,
        g_zn: f64,
        g_col: &[f64],
        gscale: f64,
        acc: &mut [f64],
    ) {
        let s = &self.s;
        let c = prep.channels;
        let f = self.faces[fi];
        let geom = &prep.bins.geoms[fi];
        let v = geom.v;
        let d = f.map(|i| prep.depth[i as usize]);
        let mut gv = [[0.0f64; 2]; 3];
        let mut gdep = [0.0f64; 3];
        let mut gwn = [0.0f64; 3];
        // Coverage: x = s d2 / sigma, d2 the squared distance to the closest boundary point
        // (for an inside point the foot on the nearest edge line).
        let sign = if q.x >= 0.0 { 1.0 } else { -1.0 };
        let gd2 = gx * sign / s.sigma;
        if gd2 != 0.0 {
            closest_backward(&geom.closest(p), gd2, &mut gv);
        }
        // Depth and attributes.
        let mut gz = -g_zn / (s.far - s.near);
        let stride = 4 + c;
        if s.perspective_correct {
            // c = z u, u = sum_k wn_k C_k / d_k.
            for ch in 0..c {
                let gc = g_col[ch] * gscale;
                if gc == 0.0 {
                    continue;
                }
                let mut u = 0.0;
                for k in 0..3 {
                    let ck = prep.attrs[f[k] as usize * c + ch];
                    u += q.wn[k] * ck / d[k];
                }
                gz += gc * u;
                let gu = q.z * gc;
                for k in 0..3 {
                    let ck = prep.attrs[f[k] as usize * c + ch];
                    gwn[k] += gu * ck / d[k];
                    acc[k * stride + 4 + ch] += gu * q.wn[k] / d[k];
                    gdep[k] -= gu * ck * q.wn[k] / (d[k] * d[k]);
                }
            }
        } else {
            for ch in 0..c {
                let gc = g_col[ch] * gscale;
                if gc == 0.0 {
                    continue;
                }
                for k in 0..3 {
                    gwn[k] += gc * prep.attrs[f[k] as usize * c + ch];
                    acc[k * stride + 4 + ch] += gc * q.wn[k];
                }
            }
        }
        let gzinv = -q.z * q.z * gz;
        for k in 0..3 {
            gwn[k] += gzinv / d[k];
            gdep[k] -= gzinv * q.wn[k] / (d[k] * d[k]);
        }
        // Clip-and-renormalise, then raw barycentrics w_k = n_k / sum n.
        let dot = gwn[0] * q.wn[0] + gwn[1] * q.wn[1] + gwn[2] * q.wn[2];
        let mut gw = [0.0; 3];
        for k in 0..3 {
            if q.w[k] > 0.0 && q.w[k] < 1.0 {
                gw[k] = (gwn[k] - dot) / q.sumwc;
            }
        }
        let dot2 = gw[0] * q.w[0] + gw[1] * q.w[1] + gw[2] * q.w[2];
        for k in 0..3 {
            let gn = (gw[k] - dot2) / geom.area;
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
        // NDC and view depth to clip coordinates.
        for k in 0..3 {
            let g = ndc_to_clip(gv[k], v[k], d[k]);
            let o = k * stride;
            acc[o] += g[0];
            acc[o + 1] += g[1];
            acc[o + 3] += g[2] + gdep[k];
        }
    }
}
