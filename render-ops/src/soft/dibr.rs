//! DIB-R (Chen et al., "Learning to Predict 3D Objects with an Interpolation-based
//! Differentiable Renderer", NeurIPS 2019): foreground pixels are hard-rasterized and their
//! attributes interpolated with barycentrics (exact interior gradients, through
//! [`crate::rasterize`] and [`crate::interpolate`]); the alpha channel of every pixel is the soft
//! silhouette
//!
//! `A = 1 - prod_j (1 - exp(-d_j^2 / delta))`
//!
//! over the faces `j` near the pixel, with `d_j` the Euclidean distance in NDC from the pixel
//! centre to the projected triangle `j` (0 inside it), as a tape op with an exact backward to
//! the clip positions of every nearby vertex.
//!
//! Cut-off: a face whose term `exp(-d^2 / delta)` is below `threshold` is dropped, i.e. faces
//! farther than `d_max = sqrt(delta ln(1 / threshold))`; faces are binned into 16 x 16 pixel
//! tiles by their boxes expanded by `d_max` (shared with `softras`, the `common` module). Dropping
//! a face changes `A` by at most `threshold * (1 - A)` per dropped face.
//!
//! Stability: the product is a sum of logs, `L = sum_j ln(1 - e^{-x_j})` with `x_j = d_j^2 /
//! delta`, each term computed as `ln(-expm1(-x_j))`, and `A = -expm1(L)`. A pixel centre inside
//! (or on the boundary of) a face has `A = 1` exactly and no gradient (the distance is
//! identically 0 there). Elsewhere `dA/dx_j = -exp(L - ln(1 - e^{-x_j}) - x_j)`, finite for
//! every `x_j > 0`.
//!
//! Compositing ([`dibr`], and `Method::Dibr` of the scene pipeline): the output is RGBA
//! `[H, W, C + 1]`. The colour channels are the hard render: the interpolated attributes of the
//! front face where a face covers the pixel centre, the background elsewhere. This is exactly
//! `A * F + (1 - A) * B` with `F` the hard foreground taken as transparent (equal to the
//! background `B`) off the faces, since `A = 1` wherever a face covers the pixel centre. The
//! silhouette gradient therefore flows through the alpha channel only; losses on silhouettes
//! use alpha.
//!
//! The forward runs in parallel over tiles (each face over the row spans of its cut-off region,
//! `common::FaceSpan`) and keeps each pixel's `P = prod_j f_j`; the backward runs in
//! parallel over faces, each summing its own pairs with `prod_{k != j} f_k = P / f_j` (recomputed
//! from the other faces where `P` is subnormal or 0), and adds the per-face sums to the vertices
//! in face order, so results are bit-identical for any thread count.
//!
//! `f32` tapes take a fast path (the `fast` module, as SoftRas's): the same forward and
//! backward over bands of whole image rows and per face, eight pixels of a row span at a time
//! in single precision, with `P` kept in `f64` (an `f32` product underflows where a few dozen
//! faces are near a pixel); `f64` tapes (gradient checks) keep the evaluation above.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::common::{
    check_memory, closest_backward, exp, ndc_to_clip, project, Closest, FaceGeom, TileBins, TILE,
};
use super::lanes::{band_faces, band_rows, geoms32, padded_px, Geom32};
use crate::blend::blend_hard;
use crate::error::RenderError;
use crate::interpolate::interpolate;
use crate::raster::RasterSettings;
use crate::rasterize::rasterize;
use crate::scene::DEFAULT_DIBR_DELTA;
use crate::simd::LANES;

mod fast;

/// Settings of [`dibr`] and [`dibr_alpha`].
#[derive(Clone, Debug, PartialEq)]
pub struct DibrSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Silhouette sharpness in squared NDC distance units (default [`DEFAULT_DIBR_DELTA`]).
    pub delta: f64,
    /// A face whose term `exp(-d^2 / delta)` falls below this is ignored (default 1e-4).
    pub threshold: f64,
    /// Background value per attribute channel (empty: zeros).
    pub background: Vec<f64>,
    /// Perspective-correct interpolation of the foreground (default `true`).
    pub perspective_correct: bool,
    /// Drop clockwise (back) faces, in the foreground and in the silhouette (default `false`).
    pub cull_backfaces: bool,
}

impl DibrSettings {
    /// Defaults (delta = [`DEFAULT_DIBR_DELTA`], threshold = 1e-4) for a `width x height` image.
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            delta: DEFAULT_DIBR_DELTA,
            threshold: 1e-4,
            background: Vec::new(),
            perspective_correct: true,
            cull_backfaces: false,
        }
    }

    /// Largest `x = d^2 / delta` a face may have and still count: `ln(1 / threshold)`.
    pub fn cutoff_x(&self) -> f64 {
        if self.threshold <= 0.0 {
            f64::INFINITY
        } else {
            -self.threshold.ln()
        }
    }

    /// Squared cut-off distance `delta ln(1 / threshold)` (NDC units).
    pub fn cutoff_sq(&self) -> f64 {
        self.delta * self.cutoff_x()
    }

    fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        if !(self.delta > 0.0 && self.delta.is_finite()) {
            return Err(format!("delta must be finite and > 0, got {}", self.delta));
        }
        if !(self.threshold > 0.0 && self.threshold < 1.0) {
            return Err(format!(
                "threshold must lie strictly between 0 and 1, got {}",
                self.threshold
            ));
        }
        if self.background.iter().any(|b| !b.is_finite()) {
            return Err(format!(
                "background must be finite, got {:?}",
                self.background
            ));
        }
        Ok(())
    }
}

fn check_inputs(
    op: &'static str,
    cs: &[usize],
    faces: &[[u32; 3]],
    s: &DibrSettings,
) -> Result<(), RenderError> {
    if cs.len() != 2 || cs[1] != 4 {
        return Err(AutodiffError::shape(op, &[cs], "clip positions must be [V, 4]").into());
    }
    s.validate().map_err(|m| AutodiffError::invalid(op, m))?;
    let v = cs[0] as u32;
    if let Some(f) = faces.iter().find(|f| f.iter().any(|&i| i >= v)) {
        return Err(
            AutodiffError::invalid(op, format!("face {f:?} indexes past {v} vertices")).into(),
        );
    }
    Ok(())
}

/// The DIB-R soft silhouette `[H, W]` of the faces under clip positions `[V, 4]`, recorded on
/// the tape (see the module documentation). Faces with a vertex at `w <= 0` are skipped.
pub fn dibr_alpha<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &DibrSettings,
) -> Result<Var<'t, T>, RenderError> {
    check_inputs("dibr_alpha", &clip.shape(), &faces, settings)?;
    check_memory(
        "dibr_alpha",
        &clip,
        &faces,
        settings.width,
        settings.height,
        settings.cutoff_sq().sqrt(),
        settings.cull_backfaces,
    )?;
    let op = DibrAlphaOp {
        faces,
        s: settings.clone(),
        prep: None,
    };
    Ok(clip.tape().apply(op, &[clip]))
}

/// Joins the RGB(…) channels of a hard render `[H, W, C + 1]` (its last channel, the hard
/// coverage, is dropped) with a DIB-R alpha `[H, W]`: an image `[H, W, C + 1]`.
pub fn composite<'t, T: Real>(
    hard: Var<'t, T>,
    alpha: Var<'t, T>,
) -> Result<Var<'t, T>, RenderError> {
    let (hs, as_) = (hard.shape(), alpha.shape());
    if hs.len() != 3 || as_.len() != 2 || hs[0] != as_[0] || hs[1] != as_[1] || hs[2] < 1 {
        return Err(AutodiffError::shape(
            "dibr",
            &[&hs, &as_],
            "need a hard render [H, W, C + 1] and an alpha [H, W]",
        )
        .into());
    }
    Ok(hard.tape().apply(ReplaceAlpha, &[hard, alpha]))
}

/// `[H, W, C + 1]` and `[H, W]` to `[H, W, C + 1]`: the first `C` channels of the first input
/// and the second as the last channel, in one pass (a slice and a concat would copy the image
/// element by element through strided views twice, forward and backward).
struct ReplaceAlpha;

impl<T: Real> Op<T> for ReplaceAlpha {
    fn name(&self) -> &'static str {
        "dibr_composite"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let mut out = inputs[0].as_standard_layout().into_owned();
        let alpha = inputs[1].as_standard_layout();
        let c1 = out.shape()[2];
        for (px, a) in out
            .as_slice_mut()
            .expect("standard")
            .chunks_mut(c1)
            .zip(alpha.iter())
        {
            px[c1 - 1] = *a;
        }
        Ok(vec![out])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let g = ctx.grad_outputs[0].as_standard_layout();
        let c1 = g.shape()[2];
        let gs = g.as_slice().expect("standard");
        let g_alpha = ctx.needs_grad[1].then(|| {
            let (h, w) = (g.shape()[0], g.shape()[1]);
            ArrayD::from_shape_vec(IxDyn(&[h, w]), gs.chunks(c1).map(|px| px[c1 - 1]).collect())
                .expect("h x w")
        });
        let g_hard = ctx.needs_grad[0].then(|| {
            let mut gh = g.to_owned();
            for px in gh.as_slice_mut().expect("standard").chunks_mut(c1) {
                px[c1 - 1] = T::zero();
            }
            gh
        });
        Ok(vec![g_hard, g_alpha])
    }
}

/// DIB-R: renders vertex attributes `[V, C]` over the faces from clip positions `[V, 4]`: an
/// image `[H, W, C + 1]`, the hard-rasterized, barycentrically interpolated attributes over
/// the background, then the soft silhouette alpha (see the module documentation).
pub fn dibr<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &DibrSettings,
) -> Result<Var<'t, T>, RenderError> {
    let (cs, as_) = (clip.shape(), attrs.shape());
    check_inputs("dibr", &cs, &faces, settings)?;
    if as_.len() != 2 || as_[0] != cs[0] {
        return Err(AutodiffError::shape(
            "dibr",
            &[&cs, &as_],
            "attributes must be [V, C] with V as clip",
        )
        .into());
    }
    let c = as_[1];
    if !settings.background.is_empty() && settings.background.len() != c {
        return Err(AutodiffError::invalid(
            "dibr",
            format!(
                "background has {} values for {c} attribute channels",
                settings.background.len()
            ),
        )
        .into());
    }
    let mut rs = RasterSettings::new(settings.width, settings.height);
    rs.perspective_correct = settings.perspective_correct;
    rs.cull_backfaces = settings.cull_backfaces;
    rs.barycentric_derivatives = false;
    let r = rasterize(clip, faces.clone(), &rs)?;
    let cols = interpolate(attrs, &r)?;
    let bg: Vec<T> = (0..c)
        .map(|ch| T::from_f64c(settings.background.get(ch).copied().unwrap_or(0.0)))
        .collect();
    let hard = blend_hard(cols, &r.fragments, &bg)?;
    let alpha = dibr_alpha(clip, faces, settings)?;
    composite(hard, alpha)
}

struct Prep {
    ndc: Vec<[f64; 2]>,
    depth: Vec<f64>,
    bins: TileBins,
    /// Per pixel (row-major): `P = prod_j f_j` over the nearby faces, or [`COVERED`] where a
    /// face covers the pixel centre (alpha 1, no gradient). Written by the `f64` forward.
    prod: Vec<f64>,
    /// Whether the `f32` fast path ([`fast`]) evaluates this render.
    fast: bool,
    /// Column centres padded for 8-lane chunks (fast path only).
    pxp: Vec<f64>,
    /// Per face, its `f32` geometry (fast path only).
    g32: Vec<Geom32>,
    /// [`Prep::prod`] of the fast path ([`fast::COVERED64`] for covered centres), padded by
    /// [`LANES`].
    p64: Vec<f64>,
}

/// [`Prep::prod`] of a pixel whose centre a face covers.
const COVERED: f64 = -1.0;

/// Per-thread scratch of one tile (local row-major pixels): each pixel's factors
/// `f_j = 1 - exp(-x_j)` in tile face order, and whether a face covers its centre.
struct TileScratch {
    lists: Vec<Vec<f64>>,
    covered: Vec<bool>,
}

impl TileScratch {
    fn new() -> Self {
        Self {
            lists: (0..TILE * TILE).map(|_| Vec::new()).collect(),
            covered: vec![false; TILE * TILE],
        }
    }
}

struct DibrAlphaOp {
    faces: Arc<Vec<[u32; 3]>>,
    s: DibrSettings,
    prep: Option<Arc<Prep>>,
}

/// What a face contributes at a pixel centre: nothing (beyond the cut-off), coverage (the
/// centre is in or on the triangle), or the factor of a nearby face.
enum Term {
    None,
    Covered,
    Near { x: f64, q: Closest },
}

impl DibrAlphaOp {
    /// The term of face geometry `g` at pixel centre `p`. Pairs beyond the cut-off are
    /// rejected by a lower bound of their distance before the exact closest point is computed.
    #[inline(always)]
    fn term(&self, g: &FaceGeom, p: [f64; 2], cut2: f64, xmax: f64) -> Term {
        let w = g.bary(p);
        if w[0] >= 0.0 && w[1] >= 0.0 && w[2] >= 0.0 {
            return Term::Covered;
        }
        if g.outside_d2_bound(&w) > cut2 {
            return Term::None;
        }
        let q = g.closest(p);
        let x = q.d2 / self.s.delta;
        if x <= 0.0 {
            Term::Covered
        } else if x > xmax {
            Term::None
        } else {
            Term::Near { x, q }
        }
    }

    /// Evaluates every face of tile `t` over the row spans of its cut-off region within the
    /// tile: marks the pixels whose centre lies in (or on) a face, and collects for the others
    /// the factors of the faces within the cut-off, in tile face order.
    fn tile_samples(&self, prep: &Prep, t: usize, sc: &mut TileScratch) {
        let s = &self.s;
        let bins = &prep.bins;
        for l in sc.lists.iter_mut() {
            l.clear();
        }
        sc.covered.fill(false);
        let (c_base, r_base) = ((t % bins.tiles_x) * TILE, (t / bins.tiles_x) * TILE);
        let xmax = s.cutoff_x();
        let cut2 = s.cutoff_sq();
        for &fi in bins.tiles[t].iter() {
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
                for col in a..=b {
                    let lp = lbase + col - c_base;
                    if sc.covered[lp] {
                        continue;
                    }
                    match self.term(g, [bins.px[col], py], cut2, xmax) {
                        Term::None => {}
                        Term::Covered => sc.covered[lp] = true,
                        Term::Near { x, .. } => sc.lists[lp].push(-(-x).exp_m1()),
                    }
                }
            }
        }
    }

    /// `prod_{k != j} f_k` at pixel (row, col) for face `fi`, by multiplying the other faces'
    /// factors afresh (in tile face order): used where the pixel's `P` is subnormal or 0, so
    /// that `P / f_j` would lose precision.
    fn leave_one_out(&self, prep: &Prep, fi: usize, row: usize, col: usize) -> f64 {
        let s = &self.s;
        let bins = &prep.bins;
        let t = (row / TILE) * bins.tiles_x + col / TILE;
        let p = [bins.px[col], bins.py[row]];
        let (xmax, cut2) = (s.cutoff_x(), s.cutoff_sq());
        let mut prod = 1.0;
        for &fj in bins.tiles[t].iter() {
            let fj = fj as usize;
            if fj == fi {
                continue;
            }
            let Some([c0, c1, r0, r1]) = bins.face_in_tile(fj, t, s.width, s.height) else {
                continue;
            };
            if !(c0..=c1).contains(&col) || !(r0..=r1).contains(&row) {
                continue;
            }
            if let Term::Near { x, .. } = self.term(&bins.geoms[fj], p, cut2, xmax) {
                prod *= -(-x).exp_m1();
            }
        }
        prod
    }

    /// Gradient of the loss with respect to face `fi`'s clip positions, summed over the
    /// uncovered pixels within its cut-off (`go`: the alpha gradient `[H, W]`): `acc[k * 3..]`
    /// gets [dX, dY, dW] of corner k. Per pair `dA/dx_j = -prod_{k != j} f_k e^{-x_j}` with
    /// `prod_{k != j} f_k = P / f_j` from the forward's `P` (exact to rounding while `P` is a
    /// normal number, since every `f_k <= 1`; recomputed otherwise), chained through the
    /// closest boundary point to the NDC vertices, then to clip coordinates once per face.
    fn face_gradient(&self, prep: &Prep, fi: usize, go: &[f64], acc: &mut [f64]) {
        let s = &self.s;
        let bins = &prep.bins;
        let rc = bins.rects[fi];
        if rc[0] > rc[1] {
            return;
        }
        let g = &bins.geoms[fi];
        let (xmax, cut2) = (s.cutoff_x(), s.cutoff_sq());
        let mut gv = [[0.0f64; 2]; 3];
        for (row, py, a, b) in bins.face_rows(fi) {
            for col in a..=b {
                let pi = row * s.width + col;
                let (gp, prod) = (go[pi], prep.prod[pi]);
                if gp == 0.0 || prod == COVERED {
                    continue;
                }
                let Term::Near { x, q } = self.term(g, [bins.px[col], py], cut2, xmax) else {
                    continue;
                };
                let excl = if prod >= f64::MIN_POSITIVE {
                    prod / -(-x).exp_m1()
                } else {
                    self.leave_one_out(prep, fi, row, col)
                };
                // dA/dx_j = -prod_{k != j} (1 - e^{-x_k}) e^{-x_j}.
                let gx = -gp * excl * exp(-x);
                closest_backward(&q, gx / s.delta, &mut gv);
            }
        }
        self.store_face_gradient(prep, fi, gv, acc);
    }

    /// Writes face `fi`'s NDC vertex gradients `gv`, chained to clip coordinates, into `acc`
    /// ([dX, dY, dW] of corner k at `acc[k * 3..]`).
    fn store_face_gradient(&self, prep: &Prep, fi: usize, gv: [[f64; 2]; 3], acc: &mut [f64]) {
        let f = self.faces[fi];
        for k in 0..3 {
            let vi = f[k] as usize;
            let gc = ndc_to_clip(gv[k], prep.ndc[vi], prep.depth[vi]);
            acc[k * 3..k * 3 + 3].copy_from_slice(&gc);
        }
    }
}

/// `A = 1 - prod_j f_j` of one uncovered pixel, and `P = prod_j f_j`. Where the product is near
/// 1 (faint coverage) the difference is taken from the sum of logs for full relative precision.
#[inline]
fn alpha_of(f: &[f64]) -> (f64, f64) {
    let prod: f64 = f.iter().product();
    let a = if prod < 0.5 {
        1.0 - prod
    } else {
        -f.iter().map(|f| f.ln()).sum::<f64>().exp_m1()
    };
    (a, prod)
}

impl<T: Real> Op<T> for DibrAlphaOp {
    fn name(&self) -> &'static str {
        "dibr_alpha"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let s = &self.s;
        let (ndc, depth) = project(&inputs[0]);
        let bins = TileBins::new(
            &ndc,
            &depth,
            &self.faces,
            s.width,
            s.height,
            s.cutoff_sq().sqrt(),
            s.cull_backfaces,
        );
        let fast = T::as_f32(&[]).is_some() && fast::f32_range_ok(s);
        let mut prep = Prep {
            ndc,
            depth,
            bins,
            prod: Vec::new(),
            fast,
            pxp: Vec::new(),
            g32: Vec::new(),
            p64: Vec::new(),
        };
        let (w, h) = (s.width, s.height);
        let this = &*self;
        if fast {
            prep.pxp = padded_px(&prep.bins.px);
            prep.g32 = geoms32(&prep.bins);
            // Bands of image rows in parallel, each straight into its rows of the alpha and of
            // `p64` (every pixel written).
            let rows = band_rows(w);
            let bands = band_faces(&prep.bins, h, rows);
            let mut img = vec![T::zero(); h * w];
            let mut p64: Vec<f64> = Vec::with_capacity(h * w + LANES);
            {
                let prep = &prep;
                let img32 = T::as_f32_mut(&mut img).expect("the fast path runs on f32 tapes");
                let spare = &mut p64.spare_capacity_mut()[..h * w + LANES];
                for x in &mut spare[h * w..] {
                    x.write(1.0);
                }
                img32
                    .par_chunks_mut(rows * w)
                    .zip(spare[..h * w].par_chunks_mut(rows * w))
                    .zip(bands.par_iter())
                    .enumerate()
                    .for_each_init(
                        || fast::Scratch32::new(w),
                        |sc, (band, ((irow, prow), tf))| {
                            this.band_forward32(prep, band, tf, sc, irow, prow)
                        },
                    );
            }
            // SAFETY: the capacity is h w + LANES; the padding was written above and each
            // band (h / rows rounded up, over its rows of every column) wrote all its pixels.
            unsafe { p64.set_len(h * w + LANES) };
            prep.p64 = p64;
            self.prep = Some(Arc::new(prep));
            return Ok(vec![
                ArrayD::from_shape_vec(IxDyn(&[h, w]), img).expect("h w")
            ]);
        }
        // Parallel over tiles, each into its own buffer (local row-major): (alpha, P) a pixel.
        let tiles: Vec<Vec<(f64, f64)>> = {
            let prep = &prep;
            let bins = &prep.bins;
            (0..bins.tiles.len())
                .into_par_iter()
                .map_init(TileScratch::new, |sc, t| {
                    if bins.tiles[t].is_empty() {
                        return Vec::new();
                    }
                    this.tile_samples(prep, t, sc);
                    sc.lists
                        .iter()
                        .zip(&sc.covered)
                        .map(|(l, &cov)| if cov { (1.0, COVERED) } else { alpha_of(l) })
                        .collect()
                })
                .collect()
        };
        let bins = &prep.bins;
        let mut img = Vec::with_capacity(h * w);
        let mut prod = Vec::with_capacity(h * w);
        for row in 0..h {
            for tx in 0..bins.tiles_x {
                let tile = &tiles[(row / TILE) * bins.tiles_x + tx];
                let cols = TILE.min(w - tx * TILE);
                if tile.is_empty() {
                    img.extend(std::iter::repeat_n(T::zero(), cols));
                    prod.extend(std::iter::repeat_n(1.0, cols));
                } else {
                    let o = (row % TILE) * TILE;
                    img.extend(tile[o..o + cols].iter().map(|&(a, _)| T::from_f64c(a)));
                    prod.extend(tile[o..o + cols].iter().map(|&(_, p)| p));
                }
            }
        }
        prep.prod = prod;
        self.prep = Some(Arc::new(prep));
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[h, w]), img).expect("h w")
        ])
    }

    /// Parallel over faces, each summing its own pairs (row-major over its cut-off region);
    /// the per-face sums are added to the vertices in face order, so results are
    /// bit-identical for any thread count.
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let prep = self
            .prep
            .as_ref()
            .ok_or_else(|| AutodiffError::invalid("dibr_alpha", "backward before forward"))?;
        let go = ctx.grad_outputs[0].as_standard_layout();
        let go = go.as_slice().expect("standard layout");
        // Per face: [dX, dY, dW] of each corner.
        const STRIDE: usize = 9;
        let per_face = match T::as_f32(go) {
            Some(go32) if prep.fast => {
                // The alpha gradient, 0 at covered centres (skipped), padded for 8 lanes.
                let gp: Vec<f32> = go32
                    .iter()
                    .zip(&prep.p64)
                    .map(|(&g, &p)| if p == fast::COVERED64 { 0.0 } else { g })
                    .chain(std::iter::repeat_n(0.0, LANES))
                    .collect();
                prep.bins
                    .per_face(STRIDE, |fi, acc| self.face_gradient32(prep, fi, &gp, acc))
            }
            _ => {
                let go: Vec<f64> = go.iter().map(|x| x.to_f64c()).collect();
                prep.bins
                    .per_face(STRIDE, |fi, acc| self.face_gradient(prep, fi, &go, acc))
            }
        };
        let nv = prep.ndc.len();
        let mut gclip = vec![0.0; nv * 4];
        for (fi, f) in self.faces.iter().enumerate() {
            let Some(a) = per_face.get(fi) else {
                continue;
            };
            for k in 0..3 {
                let v = f[k] as usize;
                gclip[v * 4] += a[k * 3];
                gclip[v * 4 + 1] += a[k * 3 + 1];
                gclip[v * 4 + 3] += a[k * 3 + 2];
            }
        }
        Ok(vec![Some(
            ArrayD::from_shape_vec(
                IxDyn(&[nv, 4]),
                gclip.into_iter().map(T::from_f64c).collect(),
            )
            .expect("v x 4"),
        )])
    }
}
