//! The detail stage: a per-pixel albedo texture in the model's uv space, fitted to the photo
//! by analysis-by-synthesis after the model fit, with the geometry, pose and SH light of that
//! fit held fixed (illumination-corrected texture extraction, Blanz and Vetter, "A morphable
//! model for the synthesis of 3D faces", SIGGRAPH 1999, sec. 5; here with a smoothness prior
//! and a prior towards the model's albedo instead of a direct inversion).
//!
//! Model: the colour of a covered pixel `p` is `I_p = A(uv_p) * E(n_p)`, with `A` the albedo
//! texture `[S, S, 3]` sampled bilinearly ([`TEXTURE_SAMPLER`], the texture op with its
//! backward) at the interpolated uv and `E` the order-2 SH irradiance of the interpolated,
//! normalised vertex normal (per-pixel shading, [`render_ops::shade::sh::sh_shade`]). Because
//! the geometry and the light are fixed, rasterization, interpolation and the irradiance
//! `E(n_p)` (`sh_shade` of a white albedo: the shading is linear in the albedo) run once
//! ([`FaceRenderer::surface_samples`]); each step puts the texture on a fresh tape, samples
//! it, multiplies by `E` and evaluates
//!
//! ```text
//! E(A) = sum_p w_p rho(I_p - T_p) / (3 sum_p w_p)                       rho: Charbonnier
//!      + (w_prior sum_t |A_t - A0_t|^2 + w_smooth sum_{t~t'} |A_t - A_t'|^2) / n_chart
//! ```
//!
//! over the pixels `p` of textured, photometric faces ([`textured_faces`]: the skin; the eyes
//! and the mouth interior keep the model's albedo and do not enter the data term, so they
//! cannot bias the skin; regions that are not photometric, such as ICT's `face_outer` with the
//! hair line, ears and neck, are textured but see no pixel: they keep the baked prior), with `w_p = max(0, n_p . v_p)` (`v_p` the unit vector to the camera): grazing pixels,
//! whose texels are stretched over many texels and whose colour mixes with the background,
//! count little, and pixels that face away count nothing. Occlusion is the rasterizer's: a
//! texel hidden behind the nose gets no pixel. `A0` is the model fit's per-vertex albedo baked
//! into uv space ([`bake_albedo`]) and is also the initial value; `t ~ t'` are the
//! horizontally and vertically adjacent texel pairs inside the uv charts (`n_chart` texels).
//! Texels that no pixel's bilinear footprint reaches get no update: they stay at the prior.
//! Cast shadows are not modelled; the Charbonnier penalty keeps their pull on the texture
//! bounded. Optimiser: Adam with a cosine step decay (as [`super::fit`]), the texels clamped
//! to `[0, 1]` after each step. The light is not refined (the albedo-light scale ambiguity is
//! the model fit's to settle).
//!
//! Both shipped models have uvs (ICT's own; the MediaPipe mesh's canonical uvs, whose `v`
//! runs down the face, so its `albedo.png` shows the face upside down while every OBJ viewer
//! maps it right). A model without uvs is an error here, and `fit-face` skips the stage for
//! it (`report.json`: `texture.skipped`), writing vertex colours instead.

use std::sync::Arc;
use std::time::Instant;

use autodiff::optim::Adam;
use autodiff::{AutodiffError, BackwardCtx, Op, Real, Tape, Tensor, TensorView, Var};
use ndarray::{Array2, Array3, ArrayD, IxDyn};
use rayon::prelude::*;
use render_ops::shade::sh::sh_shade;
use render_ops::texture::sample;
use serde::Serialize;

use super::render::to3;
use super::{lr_at, photometric_rmse, Active, FaceParams, FaceRenderer, FitError, PhotoLossOp};
use super::{RenderOptions, TEXTURE_SAMPLER};
use crate::morphable::Morphable;

/// Regions that are never textured: they keep the model's albedo (their own constants or
/// per-vertex colours), so that eyes and mouth interior do not bias the skin texture.
pub const UNTEXTURED_REGIONS: &[&str] = &[
    "mouth_interior",
    "eyes",
    "eye_left",
    "eye_right",
    "teeth",
    "gums",
];

/// One flag per model face: textured by the detail stage (a region without a constant colour
/// whose name is not in [`UNTEXTURED_REGIONS`]; ICT: `skin`; the MediaPipe model: `skin`,
/// `lips`, `brows`).
pub fn textured_faces(model: &Morphable<f64>) -> Vec<bool> {
    let on: Vec<bool> = model
        .regions()
        .iter()
        .map(|r| r.albedo.is_none() && !UNTEXTURED_REGIONS.contains(&r.name.as_str()))
        .collect();
    model
        .face_regions()
        .iter()
        .map(|&r| on.get(r as usize).copied().unwrap_or(false))
        .collect()
}

/// Per-vertex `albedo` `[V, 3]` of the faces flagged in `textured` ([`textured_faces`])
/// baked into a `size x size` texture in the model's uv space ([`bake_albedo`]). Only those
/// faces: other parts (ICT's eyeballs) may share their uv space. Errors when the model has no
/// uvs.
pub fn bake_textured(
    model: &Morphable<f64>,
    textured: &[bool],
    albedo: &Array2<f64>,
    size: usize,
) -> Result<BakedTexture, FitError> {
    let uvs = model.uvs().ok_or_else(|| {
        FitError::Invalid(format!(
            "model {} has no uvs: it cannot be textured",
            model.name()
        ))
    })?;
    let faces: Vec<[u32; 3]> = model
        .faces()
        .iter()
        .zip(textured)
        .filter_map(|(f, &t)| t.then_some(*f))
        .collect();
    Ok(bake_albedo(uvs, &faces, albedo, &[], size))
}

/// A texture baked from per-vertex values ([`bake_albedo`]).
#[derive(Clone, Debug)]
pub struct BakedTexture {
    /// Texels `[S, S, 3]`, row 0 at the top (`v = 1`).
    pub texels: Array3<f64>,
    /// Texels whose centre lies in a baked triangle (`[S, S]`): the uv charts.
    pub chart: Array2<bool>,
}

/// Per-vertex `albedo` `[V, 3]` baked into a `size x size` texture: every triangle drawn in
/// uv space (`u` right, `v` up, OBJ convention) with its corners' albedo interpolated
/// barycentrically at texel centres (or its region's constant colour), later triangles over
/// earlier ones; then four rounds of dilation (each empty texel next to drawn ones gets their
/// mean) so that bilinear lookups at the seams do not pick up the background.
pub fn bake_albedo(
    uvs: &Array2<f64>,
    faces: &[[u32; 3]],
    albedo: &Array2<f64>,
    region_colour: &[Option<[f64; 3]>],
    size: usize,
) -> BakedTexture {
    let n = size as f64;
    let mut tex = Array3::<f64>::zeros((size, size, 3));
    let mut filled = Array2::<bool>::from_elem((size, size), false);
    for (fi, f) in faces.iter().enumerate() {
        let v = f.map(|x| x as usize);
        let p = v.map(|i| [uvs[[i, 0]] * n, (1.0 - uvs[[i, 1]]) * n]);
        let area =
            (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[2][0] - p[0][0]) * (p[1][1] - p[0][1]);
        if !area.is_finite() || area.abs() < 1e-12 {
            continue;
        }
        // Texels whose centres lie in the triangle's bounding box.
        let span = |k: usize| {
            let lo = p.iter().map(|q| q[k]).fold(f64::INFINITY, f64::min);
            let hi = p.iter().map(|q| q[k]).fold(f64::NEG_INFINITY, f64::max);
            let a = (lo - 0.5).ceil().clamp(0.0, n);
            let b = ((hi - 0.5).floor() + 1.0).clamp(a, n);
            a as usize..b as usize
        };
        let colour = region_colour.get(fi).copied().flatten();
        for r in span(1) {
            for c in span(0) {
                let (x, y) = (c as f64 + 0.5, r as f64 + 0.5);
                let edge = |a: [f64; 2], b: [f64; 2]| {
                    (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0])
                };
                let b = [
                    edge(p[1], p[2]) / area,
                    edge(p[2], p[0]) / area,
                    edge(p[0], p[1]) / area,
                ];
                if b.iter().any(|&w| w < -1e-9) {
                    continue;
                }
                for k in 0..3 {
                    tex[[r, c, k]] = match colour {
                        Some(col) => col[k],
                        None => (0..3).map(|j| b[j] * albedo[[v[j], k]]).sum(),
                    };
                }
                filled[[r, c]] = true;
            }
        }
    }
    let chart = filled.clone();
    for _ in 0..4 {
        let prev = filled.clone();
        let src = tex.clone();
        for r in 0..size {
            for c in 0..size {
                if prev[[r, c]] {
                    continue;
                }
                let mut sum = [0.0; 3];
                let mut cnt = 0.0;
                for (dr, dc) in [(-1isize, 0isize), (1, 0), (0, -1), (0, 1)] {
                    let (rr, cc) = (r as isize + dr, c as isize + dc);
                    if rr < 0 || cc < 0 || rr >= size as isize || cc >= size as isize {
                        continue;
                    }
                    let (rr, cc) = (rr as usize, cc as usize);
                    if prev[[rr, cc]] {
                        for (k, s) in sum.iter_mut().enumerate() {
                            *s += src[[rr, cc, k]];
                        }
                        cnt += 1.0;
                    }
                }
                if cnt > 0.0 {
                    for (k, s) in sum.iter().enumerate() {
                        tex[[r, c, k]] = s / cnt;
                    }
                    filled[[r, c]] = true;
                }
            }
        }
    }
    BakedTexture { texels: tex, chart }
}

/// Settings of [`fit_texture`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TextureOptions {
    /// Texture side in texels.
    pub size: usize,
    /// Adam iterations.
    pub iters: usize,
    /// Initial Adam step (albedo units), decayed by a cosine to `final_step_fraction` of it.
    pub step: f64,
    /// Final step as a fraction of `step`.
    pub final_step_fraction: f64,
    /// `w_prior` (see the module docs).
    pub prior: f64,
    /// `w_smooth` (see the module docs).
    pub smoothness: f64,
    /// Charbonnier `eps` of the data term (colour units).
    pub charbonnier_eps: f64,
}

impl Default for TextureOptions {
    fn default() -> Self {
        TextureOptions {
            size: 512,
            iters: 30,
            step: 0.03,
            final_step_fraction: 0.1,
            prior: 0.01,
            smoothness: 0.5,
            charbonnier_eps: 0.02,
        }
    }
}

/// The result of [`fit_texture`].
#[derive(Clone, Debug)]
pub struct TextureFit {
    /// The fitted albedo texture `[S, S, 3]` (row 0 at the top, values in `[0, 1]`).
    pub texels: Array3<f64>,
    /// The prior and initial value: the model fit's albedo baked into uv space.
    pub prior: Array3<f64>,
    /// Texels that some pixel's bilinear footprint reaches `[S, S]`.
    pub seen: Array2<bool>,
    /// One flag per model face: textured.
    pub textured: Arc<Vec<bool>>,
    /// The render with the texture `[H, W, 4]`.
    pub image: Array3<f64>,
    /// Photometric RMSE inside the photometric mask ([`photometric_rmse`] of
    /// [`FaceRenderer::render_photo`]: the visible pixels of photometric regions) of the model
    /// fit's render (per-vertex albedo) and of the textured render.
    pub rmse_before: f64,
    /// See `rmse_before`.
    pub rmse_after: f64,
    /// Total loss per step.
    pub losses: Vec<f64>,
    /// Pixels in the data term.
    pub pixels: usize,
    /// Seconds of the whole stage (baking, rasterization, steps, final render).
    pub seconds: f64,
}

/// Fits the albedo texture of the face posed and lit by `params` (the model fit's result) to
/// `image` `[H, W, 3]`, rendered with `render` (its size is the image's; its method is not
/// used: the stage rasterizes hard). See the module docs.
///
/// # Errors
/// A model without uvs, an image of the wrong size or with non-finite values, an empty or
/// huge texture, non-finite or negative weights, and the ops' errors.
pub fn fit_texture(
    model: &Morphable<f64>,
    render: &RenderOptions,
    params: &FaceParams,
    image: &Array3<f64>,
    o: &TextureOptions,
) -> Result<TextureFit, FitError> {
    let start = Instant::now();
    let (h, w) = (render.height, render.width);
    if image.dim() != (h, w, 3) {
        return Err(FitError::Invalid(format!(
            "texture stage: image is {:?}, the render is [{h}, {w}, 3]",
            image.shape()
        )));
    }
    if image.iter().any(|v| !v.is_finite()) {
        return Err(FitError::Invalid(
            "texture stage: the image holds non-finite values".into(),
        ));
    }
    if !(2..=8192).contains(&o.size) {
        return Err(FitError::Invalid(format!(
            "texture size {}: must be 2 to 8192 texels",
            o.size
        )));
    }
    let weights = [o.step, o.final_step_fraction, o.prior, o.smoothness];
    if weights.iter().any(|v| !v.is_finite() || *v < 0.0)
        || o.charbonnier_eps.is_nan()
        || o.charbonnier_eps <= 0.0
    {
        return Err(FitError::Invalid(format!(
            "texture stage: step, weights and eps must be finite and >= 0 (eps > 0): {o:?}"
        )));
    }
    params.check(model)?;
    let textured = Arc::new(textured_faces(model));
    // The prior: the fitted per-vertex albedo of the textured faces, baked.
    let baked = bake_textured(model, &textured, &params.albedo(model)?, o.size)?;
    let renderer = FaceRenderer::new(model, render.clone())?;
    let prior = Arc::new(baked.texels.clone().into_dyn());
    let chart = Arc::new(baked.chart.iter().copied().collect::<Vec<bool>>());

    // The data: covered pixels of textured, photometric faces, weighted by n . v.
    let photometric = model.photometric_faces();
    let s = renderer.surface_samples(params)?;
    let mut keep = Vec::new();
    for (i, &f) in s.face.iter().enumerate() {
        if !(textured[f as usize] && photometric[f as usize]) {
            continue;
        }
        let (n, p) = (s.normal.row(i), s.position.row(i));
        let (ln, lp) = (n.dot(&n).sqrt(), p.dot(&p).sqrt());
        let cos = if ln > 0.0 && lp > 0.0 {
            -n.dot(&p) / (ln * lp)
        } else {
            0.0
        };
        if cos > 0.0 {
            keep.push((i, cos));
        }
    }
    let m = keep.len();
    let rows = |a: &Array2<f64>, c: usize| {
        ArrayD::from_shape_fn(IxDyn(&[m, c]), |j| a[[keep[j[0]].0, j[1]]])
    };
    let uv = rows(&s.uv, 2);
    let normal = rows(&s.normal, 3);
    let weight = ArrayD::from_shape_fn(IxDyn(&[m, 1]), |j| keep[j[0]].1);
    let target = ArrayD::from_shape_fn(IxDyn(&[m, 1, 3]), |j| {
        let px = s.pixel[keep[j[0]].0];
        image[[px / w, px % w, j[2]]]
    });
    let sh = ArrayD::from_shape_vec(
        IxDyn(&[9, 3]),
        params.sh.iter().flatten().copied().collect(),
    )
    .expect("9 x 3");

    // Texels that some pixel reaches: the gradient of the weighted sample sum.
    let seen: Vec<bool> = {
        let tape = Tape::new();
        let tex = tape.var_shared(prior.clone(), true);
        let a = sample(tex, tape.constant(uv.clone()), None, TEXTURE_SAMPLER);
        let total = (a * tape.constant(weight.clone())).sum();
        let mut g = tape.backward(total)?;
        match g.take(tex) {
            Some(g) => g.iter().step_by(3).map(|&x| x > 1e-6).collect(),
            None => vec![false; o.size * o.size],
        }
    };

    let data = TextureData::new(
        uv,
        normal,
        weight,
        target,
        sh,
        prior.clone(),
        chart,
        o.clone(),
    )?;
    let mut texels = baked.texels.into_dyn();
    let mut adam = Adam::new(o.step);
    let mut losses = Vec::with_capacity(o.iters);
    let _hot = autodiff::ActiveWait::new();
    for i in 0..o.iters {
        let tape = Tape::with_capacity(16);
        let tex = tape.var(texels.clone(), true);
        let loss = data.loss(tex)?;
        losses.push(loss.item()?);
        let mut g = tape.backward(loss)?;
        let Some(mut grad) = g.take(tex) else { break };
        for (gt, &on) in grad
            .exact_chunks_mut(IxDyn(&[1, 1, 3]))
            .into_iter()
            .zip(&seen)
        {
            if !on {
                gt.into_iter().for_each(|x| *x = 0.0);
            }
        }
        adam.lr = lr_at(o.step, i, o.iters, o.final_step_fraction);
        adam.step([(&mut texels, &grad)])?;
        texels.mapv_inplace(|x| x.clamp(0.0, 1.0));
    }

    // Both RMSEs inside the photometric mask: the model fit's render as the photometric term
    // sees it, and the textured render (the same geometry, so the same coverage) with its
    // alpha replaced by that mask.
    let before = renderer.render_photo(params)?;
    let after = render_textured(&renderer, params, &texels, &textured)?;
    let mut after_masked = after.clone();
    after_masked
        .slice_mut(ndarray::s![.., .., 3])
        .assign(&before.slice(ndarray::s![.., .., 3]));
    let texels = to3(&texels);
    let seen = Array2::from_shape_vec((o.size, o.size), seen).expect("S x S");
    Ok(TextureFit {
        rmse_before: photometric_rmse(&before, image),
        rmse_after: photometric_rmse(&after_masked, image),
        image: after,
        texels,
        prior: to3(&prior),
        seen,
        textured,
        losses,
        pixels: m,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The fixed data of the stage's loss: the `M` pixels of textured faces.
struct TextureData {
    /// Texture coordinates `[M, 2]`.
    uv: Arc<Tensor<f64>>,
    /// SH irradiance `E(n_p)` `[M, 3]`: the shading of each pixel, fixed with the geometry
    /// and the light (`sh_shade` of the normals with a white albedo).
    irradiance: Arc<Tensor<f64>>,
    /// `w_p = n . v` `[M, 1]`.
    weight: Arc<Tensor<f64>>,
    /// The photo at the pixels `[M, 1, 3]`.
    target: Arc<Tensor<f64>>,
    /// The prior texture `[S, S, 3]`.
    prior: Arc<Tensor<f64>>,
    /// Texels in the uv charts.
    chart: Arc<Vec<bool>>,
    options: TextureOptions,
}

impl TextureData {
    /// The data of pixels with `uv` `[M, 2]`, `normal` `[M, 3]`, weight `[M, 1]`, photo
    /// colours `target` `[M, 1, 3]`, lit by `sh` `[9, 3]`.
    #[allow(clippy::too_many_arguments)]
    fn new(
        uv: Tensor<f64>,
        normal: Tensor<f64>,
        weight: Tensor<f64>,
        target: Tensor<f64>,
        sh: Tensor<f64>,
        prior: Arc<Tensor<f64>>,
        chart: Arc<Vec<bool>>,
        options: TextureOptions,
    ) -> Result<Self, FitError> {
        let tape = Tape::new();
        let white = tape.constant(ArrayD::from_elem(IxDyn(&[3]), 1.0));
        let irradiance = sh_shade(tape.constant(normal), white, tape.constant(sh)).value()?;
        Ok(TextureData {
            uv: Arc::new(uv),
            irradiance,
            weight: Arc::new(weight),
            target: Arc::new(target),
            prior,
            chart,
            options,
        })
    }

    /// The loss of the module docs for texels `tex` `[S, S, 3]`: the texture sampled at the
    /// pixels, times their irradiance (`sh_shade` is linear in the albedo), against the photo.
    fn loss<'t>(&self, tex: Var<'t, f64>) -> Result<Var<'t, f64>, FitError> {
        let tape = tex.tape();
        let o = &self.options;
        let m = self.uv.shape()[0];
        let c = |x: &Arc<Tensor<f64>>| tape.var_shared(x.clone(), false);
        let a = sample(tex, c(&self.uv), None, TEXTURE_SAMPLER);
        let col = a * c(&self.irradiance);
        let weighted = tape.concat(&[col, c(&self.weight)], 1).reshape(&[m, 1, 4]);
        let data = tape.apply(
            PhotoLossOp::new(self.target.clone(), o.charbonnier_eps),
            &[weighted],
        );
        Ok(data + texture_prior(tex, &self.prior, &self.chart, o.prior, o.smoothness)?)
    }
}

/// Plain render `[H, W, 4]` of the face posed by `params` with the albedo of the `textured`
/// faces from `texels` `[S, S, 3]` ([`FaceRenderer::image_textured`]).
pub fn render_textured(
    renderer: &FaceRenderer<'_>,
    params: &FaceParams,
    texels: &Tensor<f64>,
    textured: &Arc<Vec<bool>>,
) -> Result<Array3<f64>, FitError> {
    let tape = Tape::new();
    let v = renderer.vars(&tape, params, Active::NONE);
    let tex = tape.constant(texels.clone());
    let img = renderer.image_textured(renderer.posed(&v), &v, tex, textured)?;
    Ok(to3(&*img.value()?))
}

/// The priors of the texture as one fused op on texels `[S, S, C]` (see the module docs):
/// `(w_prior sum_t |A_t - A0_t|^2 + w_smooth sum_{t~t'} |A_t - A_t'|^2) / n_chart` over the
/// texels `t` with `chart[t]` and the adjacent pairs with both in the chart. Errors on shapes.
pub fn texture_prior<'t, T: Real>(
    texels: Var<'t, T>,
    prior: &Arc<Tensor<T>>,
    chart: &Arc<Vec<bool>>,
    w_prior: f64,
    w_smooth: f64,
) -> Result<Var<'t, T>, FitError> {
    let s = texels.shape();
    if s.len() != 3 || prior.shape() != s.as_slice() || chart.len() != s[0] * s[1] {
        return Err(AutodiffError::shape(
            "texture_prior",
            &[&s, prior.shape(), &[chart.len()]],
            "expected texels and prior [S, S, C] and one chart flag per texel",
        )
        .into());
    }
    let n = chart.iter().filter(|&&c| c).count().max(1) as f64;
    let op = TexturePriorOp {
        prior: prior.clone(),
        chart: chart.clone(),
        w_prior: T::from_f64c(w_prior / n),
        w_smooth: T::from_f64c(w_smooth / n),
    };
    Ok(texels.tape().apply(op, &[texels]))
}

struct TexturePriorOp<T: Real> {
    prior: Arc<Tensor<T>>,
    chart: Arc<Vec<bool>>,
    /// `w_prior / n_chart`.
    w_prior: T,
    /// `w_smooth / n_chart`.
    w_smooth: T,
}

impl<T: Real> TexturePriorOp<T> {
    /// Calls `f(texel, neighbour)` for the right and lower neighbours of texel `i` in the
    /// chart (each adjacent pair once).
    #[inline(always)]
    fn pairs_from(&self, i: usize, (h, w): (usize, usize), mut f: impl FnMut(usize)) {
        let (r, c) = (i / w, i % w);
        if c + 1 < w && self.chart[i + 1] {
            f(i + 1);
        }
        if r + 1 < h && self.chart[i + w] {
            f(i + w);
        }
    }
}

impl<T: Real> Op<T> for TexturePriorOp<T> {
    fn name(&self) -> &'static str {
        "texture_prior"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> autodiff::Result<Vec<Tensor<T>>> {
        let x = inputs[0].as_standard_layout();
        let p = self.prior.as_standard_layout();
        let (h, w, c) = (x.shape()[0], x.shape()[1], x.shape()[2]);
        let (xs, ps) = (x.as_slice().expect("std"), p.as_slice().expect("std"));
        // One partial sum per texel row, added in row order: any thread count, same bits.
        let rows: Vec<T> = (0..h)
            .into_par_iter()
            .map(|r| {
                let mut acc = T::zero();
                for i in r * w..(r + 1) * w {
                    if !self.chart[i] {
                        continue;
                    }
                    for k in 0..c {
                        let d = xs[i * c + k] - ps[i * c + k];
                        acc += self.w_prior * d * d;
                    }
                    self.pairs_from(i, (h, w), |j| {
                        for k in 0..c {
                            let d = xs[i * c + k] - xs[j * c + k];
                            acc += self.w_smooth * d * d;
                        }
                    });
                }
                acc
            })
            .collect();
        let total = rows.into_iter().fold(T::zero(), |a, b| a + b);
        Ok(vec![autodiff::tensor::scalar(total)])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> autodiff::Result<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let x = ctx.inputs[0].as_standard_layout();
        let p = self.prior.as_standard_layout();
        let (h, w, c) = (x.shape()[0], x.shape()[1], x.shape()[2]);
        let (xs, ps) = (x.as_slice().expect("std"), p.as_slice().expect("std"));
        let g = ctx.grad_outputs[0]
            .iter()
            .next()
            .copied()
            .unwrap_or(T::zero());
        let two = T::from_f64c(2.0);
        let mut out = vec![T::zero(); xs.len()];
        // Each texel gathers from its four neighbours: no scatter, rows in parallel.
        out.par_chunks_mut(w * c).enumerate().for_each(|(r, row)| {
            for cc in 0..w {
                let i = r * w + cc;
                if !self.chart[i] {
                    continue;
                }
                let mut nb = [usize::MAX; 4];
                if cc > 0 {
                    nb[0] = i - 1;
                }
                if cc + 1 < w {
                    nb[1] = i + 1;
                }
                if r > 0 {
                    nb[2] = i - w;
                }
                if r + 1 < h {
                    nb[3] = i + w;
                }
                for k in 0..c {
                    let mut d = self.w_prior * (xs[i * c + k] - ps[i * c + k]);
                    for &j in nb.iter().filter(|&&j| j != usize::MAX && self.chart[j]) {
                        d += self.w_smooth * (xs[i * c + k] - xs[j * c + k]);
                    }
                    row[cc * c + k] = g * two * d;
                }
            }
        });
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(x.shape()), out).expect("same shape"),
        )])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::gradcheck::{gradcheck, GradcheckOptions};
    use autodiff::rng::Rng;

    /// The fused prior against the same sums of tape ops (f64 and f32), and its gradient
    /// against finite differences (f64).
    #[test]
    fn texture_prior_matches_composed_ops_and_gradcheck() {
        let mut rng = Rng::new(7);
        let (h, w, c) = (5, 6, 3);
        let x: Tensor<f64> = rng.uniform_tensor(&[h, w, c], 0.0, 1.0);
        let p = Arc::new(rng.uniform_tensor::<f64>(&[h, w, c], 0.0, 1.0));
        let chart: Arc<Vec<bool>> = Arc::new((0..h * w).map(|i| (i * 7) % 5 != 0).collect());
        let (wp, ws) = (0.3, 0.7);
        let n = chart.iter().filter(|&&b| b).count() as f64;
        // Composed: masks on the texels and on the pairs.
        let m = |f: &dyn Fn(usize, usize) -> bool, hh: usize, ww: usize| {
            ArrayD::from_shape_fn(
                IxDyn(&[hh, ww, c]),
                |i| {
                    if f(i[0], i[1]) {
                        1.0
                    } else {
                        0.0
                    }
                },
            )
        };
        let at = |r: usize, col: usize| chart[r * w + col];
        let tape = Tape::new();
        let v = tape.leaf(x.clone());
        let want = {
            let t = &tape;
            let p = t.constant((*p).clone());
            let d = v - p;
            let prior = (d.square() * t.constant(m(&|r, cc| at(r, cc), h, w))).sum();
            let dx = v.slice(1, 1, w) - v.slice(1, 0, w - 1);
            let dy = v.slice(0, 1, h) - v.slice(0, 0, h - 1);
            let mx = m(&|r, cc| at(r, cc) && at(r, cc + 1), h, w - 1);
            let my = m(&|r, cc| at(r, cc) && at(r + 1, cc), h - 1, w);
            let smooth =
                (dx.square() * t.constant(mx)).sum() + (dy.square() * t.constant(my)).sum();
            ((prior * wp + smooth * ws) * (1.0 / n)).item().unwrap()
        };
        let fused = texture_prior(v, &p, &chart, wp, ws)
            .unwrap()
            .item()
            .unwrap();
        assert!(
            (fused - want).abs() < 1e-12 * want.abs().max(1.0),
            "{fused} vs {want}"
        );
        let t32 = Tape::<f32>::new();
        let p32 = Arc::new(p.mapv(|a| a as f32));
        let v32 = t32.leaf(x.mapv(|a| a as f32));
        let f32v = texture_prior(v32, &p32, &chart, wp, ws)
            .unwrap()
            .item()
            .unwrap();
        assert!(
            (f32v as f64 - want).abs() < 1e-5 * want.abs().max(1.0),
            "{f32v} vs {want}"
        );
        let rep = gradcheck(
            |_t: &Tape<f64>, v| texture_prior(v[0], &p, &chart, wp, ws).unwrap(),
            &[x],
            &GradcheckOptions::default(),
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
    }

    /// The stage's whole loss (texture sampling, per-pixel SH shading, the weighted
    /// Charbonnier data term and the priors) against finite differences on a tiny case.
    #[test]
    fn texture_loss_gradcheck() {
        let mut rng = Rng::new(11);
        let (m, size) = (9, 4);
        let mut normal: Tensor<f64> = rng.uniform_tensor(&[m, 3], -0.5, 0.5);
        normal
            .index_axis_mut(ndarray::Axis(1), 2)
            .mapv_inplace(|z| z + 1.0);
        let sh = {
            let mut s: Tensor<f64> = rng.uniform_tensor(&[9, 3], -0.3, 0.3);
            s.index_axis_mut(ndarray::Axis(0), 0).fill(2.5);
            s
        };
        let data = TextureData::new(
            rng.uniform_tensor(&[m, 2], 0.05, 0.95),
            normal,
            rng.uniform_tensor(&[m, 1], 0.1, 1.0),
            rng.uniform_tensor(&[m, 1, 3], 0.0, 1.0),
            sh,
            Arc::new(rng.uniform_tensor(&[size, size, 3], 0.2, 0.8)),
            Arc::new((0..size * size).map(|i| i % 5 != 3).collect()),
            TextureOptions {
                prior: 0.2,
                smoothness: 0.3,
                ..TextureOptions::default()
            },
        )
        .unwrap();
        let x: Tensor<f64> = rng.uniform_tensor(&[size, size, 3], 0.0, 1.0);
        let rep = gradcheck(
            |_t: &Tape<f64>, v| data.loss(v[0]).unwrap(),
            &[x],
            &GradcheckOptions::default(),
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
    }

    #[test]
    fn baked_albedo_interpolates_the_corners() {
        let uvs = Array2::from_shape_vec((3, 2), vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0]).unwrap();
        let albedo =
            Array2::from_shape_vec((3, 3), vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
                .unwrap();
        let n = 16;
        let b = bake_albedo(&uvs, &[[0, 1, 2]], &albedo, &[None], n);
        // Texel (row 12, col 2): centre (2.5, 12.5) = uv (2.5 / 16, 1 - 12.5 / 16).
        let (u, v) = (2.5 / 16.0, 1.0 - 12.5 / 16.0);
        let want = [1.0 - u - v, u, v];
        for (k, w) in want.iter().enumerate() {
            assert!((b.texels[[12, 2, k]] - w).abs() < 1e-12);
        }
        assert!(b.chart[[12, 2]] && !b.chart[[0, 15]] && !b.chart[[1, 14]]);
        // Beyond the diagonal: four dilation rounds fill texels next to the triangle, the far
        // corner stays empty.
        assert!(b
            .texels
            .slice(ndarray::s![0, 15, ..])
            .iter()
            .all(|&x| x == 0.0));
        assert!(b
            .texels
            .slice(ndarray::s![0, 0, ..])
            .iter()
            .any(|&x| x > 0.0));
        // A region colour replaces the interpolation.
        let b = bake_albedo(&uvs, &[[0, 1, 2]], &albedo, &[Some([0.1, 0.2, 0.3])], n);
        assert_eq!(b.texels[[12, 2, 1]], 0.2);
    }
}
