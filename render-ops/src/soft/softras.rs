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

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::common::{
    check_memory, closest_backward, closest_on_boundary, cross, ndc_to_clip, pixel_centre, project,
    Closest, TileBins, TILE,
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

/// One face at one pixel.
#[derive(Clone, Copy, Default)]
struct Sample {
    /// Index into the tile's face list.
    li: u32,
    x: f64,
    dd: f64,
    closest: Closest,
    w: [f64; 3],
    wn: [f64; 3],
    sumwc: f64,
    area: f64,
    z: f64,
    zn: f64,
}

struct SoftRasOp {
    faces: Arc<Vec<[u32; 3]>>,
    s: SoftSettings,
    prep: Option<Arc<Prep>>,
}

#[inline]
fn sigmoid(x: f64) -> f64 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// `ln(1 + e^x)`, stable.
#[inline]
fn softplus(x: f64) -> f64 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
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
    /// The faces of tile `t` that matter at pixel (row, col): samples into `out`, their
    /// interpolated attributes into `cols` (C per sample).
    #[allow(clippy::too_many_arguments)]
    fn pixel_samples(
        &self,
        prep: &Prep,
        tile_faces: &[u32],
        row: usize,
        col: usize,
        out: &mut Vec<Sample>,
        cols: &mut Vec<f64>,
    ) {
        let s = &self.s;
        out.clear();
        cols.clear();
        let c = prep.channels;
        let p = pixel_centre(row, col, s.width, s.height);
        for (li, &fi) in tile_faces.iter().enumerate() {
            if !prep.bins.reaches(fi as usize, row, col) {
                continue;
            }
            let f = self.faces[fi as usize];
            let v = f.map(|i| prep.ndc[i as usize]);
            let mut n = [0.0; 3];
            for k in 0..3 {
                let (a, b) = (v[(k + 1) % 3], v[(k + 2) % 3]);
                n[k] = cross([a[0] - p[0], a[1] - p[1]], [b[0] - p[0], b[1] - p[1]]);
            }
            let area = n[0] + n[1] + n[2];
            // A sliver whose area rounds to zero (or overflows) at this pixel has no
            // barycentrics here: skipped, in the forward and the backward alike.
            if area == 0.0 || !area.is_finite() {
                continue;
            }
            let w = n.map(|x| x / area);
            let inside = w.iter().all(|&x| x >= 0.0);
            let best = closest_on_boundary(&v, p);
            let x = if inside {
                best.d2 / s.sigma
            } else {
                -best.d2 / s.sigma
            };
            let dd = sigmoid(x);
            if !inside && dd < s.threshold {
                continue;
            }
            let wc = w.map(|x| x.clamp(0.0, 1.0));
            let sumwc = wc[0] + wc[1] + wc[2];
            if !(sumwc > 0.0 && sumwc.is_finite()) {
                continue;
            }
            let wn = wc.map(|x| x / sumwc);
            let d = f.map(|i| prep.depth[i as usize]);
            let zinv = wn[0] / d[0] + wn[1] / d[1] + wn[2] / d[2];
            let z = 1.0 / zinv;
            let zn = 1.0 - (z - s.near) / (s.far - s.near);
            let wp = if s.perspective_correct {
                [wn[0] / d[0] * z, wn[1] / d[1] * z, wn[2] / d[2] * z]
            } else {
                wn
            };
            for ch in 0..c {
                let mut acc = 0.0;
                for k in 0..3 {
                    acc += wp[k] * prep.attrs[f[k] as usize * c + ch];
                }
                cols.push(acc);
            }
            out.push(Sample {
                li: li as u32,
                x,
                dd,
                closest: best,
                w,
                wn,
                sumwc,
                area,
                z,
                zn,
            });
        }
    }

    /// Aggregates the samples of one pixel: writes the C attributes and alpha into `px`;
    /// returns (m, Z, S = sum ln(1 - D)).
    fn aggregate(
        &self,
        samples: &[Sample],
        cols: &[f64],
        c: usize,
        px: &mut [f64],
    ) -> (f64, f64, f64) {
        let s = &self.s;
        let m = samples.iter().fold(s.eps, |m, q| m.max(q.zn));
        let eb = ((s.eps - m) / s.gamma).exp();
        let mut zsum = eb;
        for (ch, v) in px[..c].iter_mut().enumerate() {
            *v = eb * s.background.get(ch).copied().unwrap_or(0.0);
        }
        let mut lsum = 0.0;
        for (q, col) in samples.iter().zip(cols.chunks_exact(c.max(1))) {
            let we = q.dd * ((q.zn - m) / s.gamma).exp();
            zsum += we;
            for ch in 0..c {
                px[ch] += we * col[ch];
            }
            lsum -= softplus(q.x);
        }
        for v in px[..c].iter_mut() {
            *v /= zsum;
        }
        px[c] = -lsum.exp_m1();
        (m, zsum, lsum)
    }
}

impl<T: Real> Op<T> for SoftRasOp {
    fn name(&self) -> &'static str {
        "softras"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> AdResult<Vec<Tensor<T>>> {
        let prep = Arc::new(prepare(inputs[0], inputs[1], &self.faces, &self.s));
        let (w, h, c) = (self.s.width, self.s.height, prep.channels);
        let mut img = vec![0.0f64; h * w * (c + 1)];
        let this = &*self;
        let tiles_y = h.div_ceil(TILE);
        // Parallel over bands of tile rows; each band writes its own image rows.
        img.par_chunks_mut(TILE * w * (c + 1))
            .enumerate()
            .for_each(|(ty, band)| {
                debug_assert!(ty < tiles_y);
                let mut samples = Vec::new();
                let mut cols = Vec::new();
                for tx in 0..prep.bins.tiles_x {
                    let tf = &prep.bins.tiles[ty * prep.bins.tiles_x + tx];
                    for lr in 0..TILE.min(h - ty * TILE) {
                        for col in tx * TILE..(tx * TILE + TILE).min(w) {
                            this.pixel_samples(
                                &prep,
                                tf,
                                ty * TILE + lr,
                                col,
                                &mut samples,
                                &mut cols,
                            );
                            let o = (lr * w + col) * (c + 1);
                            let px = &mut band[o..o + c + 1];
                            if samples.is_empty() {
                                for (ch, v) in px[..c].iter_mut().enumerate() {
                                    *v = this.s.background.get(ch).copied().unwrap_or(0.0);
                                }
                                px[c] = 0.0;
                            } else {
                                this.aggregate(&samples, &cols, c, px);
                            }
                        }
                    }
                }
            });
        self.prep = Some(prep);
        let out = ArrayD::from_shape_vec(
            IxDyn(&[h, w, c + 1]),
            img.into_iter().map(T::from_f64c).collect(),
        )
        .expect("h w c+1");
        Ok(vec![out])
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
        let ntiles = prep.bins.tiles.len();
        // Per tile: accumulators per (tile face, corner) of [dX, dY, dZ, dW, dattr...].
        let accs: Vec<Vec<f64>> = (0..ntiles)
            .into_par_iter()
            .map(|t| {
                let tf = &prep.bins.tiles[t];
                let mut acc = vec![0.0; tf.len() * stride];
                if tf.is_empty() {
                    return acc;
                }
                let (tx, ty) = (t % prep.bins.tiles_x, t / prep.bins.tiles_x);
                let mut samples = Vec::new();
                let mut cols = Vec::new();
                let mut px = vec![0.0; c + 1];
                for row in ty * TILE..(ty * TILE + TILE).min(h) {
                    for col in tx * TILE..(tx * TILE + TILE).min(w) {
                        let g = &go[(row * w + col) * (c + 1)..(row * w + col + 1) * (c + 1)];
                        if g.iter().all(|&x| x == 0.0) {
                            continue;
                        }
                        self.pixel_samples(prep, tf, row, col, &mut samples, &mut cols);
                        if samples.is_empty() {
                            continue;
                        }
                        let (m, zsum, lsum) = self.aggregate(&samples, &cols, c, &mut px);
                        let p = pixel_centre(row, col, w, h);
                        for (q, colv) in samples.iter().zip(cols.chunks_exact(c.max(1))) {
                            let ef = ((q.zn - m) / s.gamma).exp();
                            let mut cdiff = 0.0;
                            for ch in 0..c {
                                cdiff += g[ch] * (colv[ch] - px[ch]);
                            }
                            let g_d = ef * cdiff / zsum + g[c] * (lsum + softplus(q.x)).exp();
                            let g_zn = q.dd * ef * cdiff / (s.gamma * zsum);
                            let gscale = q.dd * ef / zsum;
                            let fi = tf[q.li as usize] as usize;
                            let a = &mut acc[q.li as usize * stride..(q.li as usize + 1) * stride];
                            self.face_backward(prep, fi, p, q, g_d, g_zn, &g[..c], gscale, a);
                        }
                    }
                }
                acc
            })
            .collect();
        let nv = prep.ndc.len();
        let mut gclip = vec![0.0; nv * 4];
        let mut gattr = vec![0.0; nv * c];
        for (t, acc) in accs.iter().enumerate() {
            for (li, &fi) in prep.bins.tiles[t].iter().enumerate() {
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
    /// Chains dL/dD, dL/dzn and dL/d(interpolated attribute) (= `g_col * gscale`) of one sample
    /// down to its three vertices: `acc[k * (4 + C)..]` gets [dX, dY, dZ, dW, dattr...] of corner k.
    #[allow(clippy::too_many_arguments)]
    fn face_backward(
        &self,
        prep: &Prep,
        fi: usize,
        p: [f64; 2],
        q: &Sample,
        g_d: f64,
        g_zn: f64,
        g_col: &[f64],
        gscale: f64,
        acc: &mut [f64],
    ) {
        let s = &self.s;
        let c = prep.channels;
        let f = self.faces[fi];
        let v = f.map(|i| prep.ndc[i as usize]);
        let d = f.map(|i| prep.depth[i as usize]);
        let mut gv = [[0.0f64; 2]; 3];
        let mut gdep = [0.0f64; 3];
        let mut gwn = [0.0f64; 3];
        // Coverage: x = s d2 / sigma.
        let gx = g_d * q.dd * sigmoid(-q.x);
        let sign = if q.x >= 0.0 { 1.0 } else { -1.0 };
        let gd2 = gx * sign / s.sigma;
        closest_backward(&q.closest, gd2, &mut gv);
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
            let gn = (gw[k] - dot2) / q.area;
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
