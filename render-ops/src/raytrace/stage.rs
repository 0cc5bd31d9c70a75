//! The ray tracer as stages of the fragment pipeline, so that textures and any per-fragment
//! shader compose with it (ARCHITECTURE.md, "The ray tracer"):
//!
//! ```text
//! clip [V, 4] ─► raytrace_fragments(clip, faces, RaytraceSettings)
//!    │  raster: one fragment per pixel sample that hits a face (the fused op's samples:
//!    │          same strata, jitter and seed), in sample order per pixel
//!    │  band:   the hits of the two side points `u -+ eps n` of every primary-edge sample
//!    ▼
//! the shader on `raster` and on `band` (any tape code, as on a rasterization)
//!    ▼
//! blend_traced(colours, band colours, traced, clip, background) -> image [H, W, C + 1]
//!       forward: the box filter, `sum_s c_s / spp + (1 - hits / spp) background`
//!       backward: the samples' colours get `g / spp`; the clip positions get the
//!       primary-edge terms (Li et al. 2018, eq. 5-7) from the shaded sides
//! ```
//!
//! A fragment's barycentrics are those of the ray's hit, which are the perspective-correct
//! barycentrics of the rasterizer at the sample's image point, so the fragments are recorded
//! as a rasterization whose backward takes the rasterizer's product at each fragment's own
//! point instead of its pixel centre (`rasterize::record_at`). The edge
//! samples are the fused op's (the same edges, positions and weights for a seed), so for
//! per-vertex colours the composed render and its gradient equal the fused op's (tested).
//!
//! Lights in a composed shader are unshadowed, as in the rasterizers: shadow rays, and the
//! shadow and area-light edge terms, are the fused op's ([`super::raytrace`]), which
//! `Scene::render` uses for its built-in shading. A band fragment is listed under the pixel of
//! its edge point; its side point lies within `1e-3` pixel of it.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::blend::blend_weighted;
use crate::error::RenderError;
use crate::raster::{Fragments, RasterSettings};
use crate::rasterize::{record_at, Rasterized};
use crate::shade::cross3;

use super::op::{check_faces, rows, side_points, EdgePoint, Edges, Scene};
use super::RaytraceSettings;

/// The fragments of a ray-traced render ([`raytrace_fragments`]).
pub struct TracedFragments<'t, T: Real> {
    /// One fragment per pixel sample that hits a face, in sample order within each pixel.
    pub raster: Rasterized<'t, T>,
    /// The hits of the primary-edge samples' side points, under the pixel of each edge point.
    pub band: Rasterized<'t, T>,
    /// Each sample fragment's weight in its pixel, `1 / spp` (a constant).
    pub weight: Var<'t, T>,
    edges: Arc<Vec<EdgeSample>>,
}

/// A primary-edge sample: its point, its pixel, and the band fragment of each side (`None`:
/// the side sees the background).
#[derive(Clone, Copy, Debug)]
struct EdgeSample {
    point: EdgePoint,
    pixel: u32,
    sides: [Option<u32>; 2],
}

/// One hit: pixel, face, barycentrics, NDC depth, view depth, NDC point of the ray, and the
/// barycentrics' derivatives per pixel step right and down.
type Frag = (u32, u32, [f64; 3], f64, f64, [f64; 2], [[f64; 3]; 2]);

/// `d bary / d col` and `d bary / d row` of the perspective-correct barycentrics at NDC point
/// `p` of the triangle with clip vertices `v` in a `width x height` image: `b_i = e_i / sum e`
/// with `e_i = (q_{i+1} x q_{i+2}) . (x, y, 1)`, `q = (clip.x, clip.y, clip.w)`.
fn bary_derivatives(v: [[f64; 4]; 3], p: [f64; 2], width: usize, height: usize) -> [[f64; 3]; 2] {
    let q = v.map(|c| [c[0], c[1], c[3]]);
    let c: [[f64; 3]; 3] = std::array::from_fn(|i| cross3(q[(i + 1) % 3], q[(i + 2) % 3]));
    let e = c.map(|ci| ci[0] * p[0] + ci[1] * p[1] + ci[2]);
    let sum = e[0] + e[1] + e[2];
    if sum == 0.0 {
        return [[0.0; 3]; 2];
    }
    // Per pixel step: d ndc.x / d col = 2 / width, d ndc.y / d row = -2 / height.
    let steps = [(0, 2.0 / width as f64), (1, -2.0 / height as f64)];
    steps.map(|(axis, step)| {
        let ds: f64 = c.iter().map(|ci| ci[axis]).sum();
        std::array::from_fn(|i| step * (c[i][axis] * sum - e[i] * ds) / (sum * sum))
    })
}

/// The fragment of the primary ray through pixel point `u` of pixel `pixel`, if it hits.
fn fragment(sc: &Scene<'_>, clip: &[[f64; 4]], pixel: usize, u: [f64; 2]) -> Option<Frag> {
    let (h, dir) = sc.primary_hit(u)?;
    let tri = sc.faces[h.face as usize];
    let (mut z, mut w) = (0.0, 0.0);
    for (i, &vi) in tri.iter().enumerate() {
        z += h.bary[i] * clip[vi as usize][2];
        w += h.bary[i] * clip[vi as usize][3];
    }
    let v = tri.map(|vi| clip[vi as usize]);
    let ndc = [dir[0], dir[1]];
    let (wd, ht) = (sc.s.width, sc.s.height);
    let d = bary_derivatives(v, ndc, wd, ht);
    Some((pixel as u32, h.face, h.bary, z / w, w, ndc, d))
}

/// Packs fragments listed in pixel order into [`Fragments`] (CSR per pixel) and their NDC
/// points.
fn pack<T: Real>(frags: &[Frag], width: usize, height: usize) -> (Fragments<T>, Vec<[f64; 2]>) {
    let mut f = Fragments::empty(width, height, 1);
    let mut counts = vec![0u32; width * height];
    for fr in frags {
        counts[fr.0 as usize] += 1;
    }
    f.k = counts.iter().copied().max().unwrap_or(0).max(1) as usize;
    let mut at = 0u32;
    for (p, c) in counts.iter().enumerate() {
        f.offsets[p] = at;
        at += c;
    }
    f.offsets[width * height] = at;
    let t = |x: f64| T::from_f64c(x);
    f.face = frags.iter().map(|fr| fr.1).collect();
    f.bary = frags.iter().map(|fr| fr.2.map(t)).collect();
    f.depth = frags.iter().map(|fr| t(fr.3)).collect();
    f.view_depth = frags.iter().map(|fr| t(fr.4)).collect();
    f.dbary_dx = frags.iter().map(|fr| fr.6[0].map(t)).collect();
    f.dbary_dy = frags.iter().map(|fr| fr.6[1].map(t)).collect();
    (f, frags.iter().map(|fr| fr.5).collect())
}

/// Casts the primary rays of `settings`' pixel samples and of its primary-edge samples' sides
/// (module docs). Only `width`, `height`, `spp`, `seed`, `near`, `far` and
/// `primary_edge_samples` are read; lights and shading belong to the shader.
///
/// # Errors
/// `clip` not `[V, 4]` or not finite, face indices out of range, invalid settings.
pub fn raytrace_fragments<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RaytraceSettings,
) -> Result<TracedFragments<'t, T>, RenderError> {
    settings.validate()?;
    let s = RaytraceSettings {
        lights: Vec::new(),
        shadows: false,
        ..settings.clone()
    };
    let cv = clip.value_ref()?;
    let v = cv.shape().first().copied().unwrap_or(0);
    if cv.shape() != [v, 4] {
        return Err(AutodiffError::shape(
            "raytrace_fragments",
            &[cv.shape()],
            "clip must be [V, 4]",
        )
        .into());
    }
    RenderError::check_finite("clip", &cv.view())?;
    check_faces(&faces, v)?;
    let clip_f64: Vec<[f64; 4]> = rows(&cv.view());
    drop(cv);
    let sc = Scene::primary_only(&s, &faces, clip_f64.clone());
    let (w, h, spp) = (s.width, s.height, s.spp);
    let samples: Vec<Frag> = (0..h)
        .into_par_iter()
        .flat_map_iter(|r| {
            let sc = &sc;
            let clip = &clip_f64;
            (r * w..(r + 1) * w).flat_map(move |pix| {
                (0..spp).filter_map(move |k| fragment(sc, clip, pix, sc.sample(pix, k).0))
            })
        })
        .collect();
    let edges = Edges::new(&sc);
    let n_edge = if edges.primary.is_empty() {
        0
    } else {
        s.primary_edge_samples
    };
    // Per edge sample: its point, pixel and side hits; then the band in pixel order (stable in
    // the sample index, so the order is fixed).
    let placed: Vec<Option<(EdgePoint, usize, [Option<Frag>; 2])>> = (0..n_edge)
        .into_par_iter()
        .map(|j| {
            let (ep, _) = sc.primary_edge_point(j, &edges)?;
            let p = sc.pixel(ep.u)?;
            let sides = side_points(ep.u, ep.a)?;
            Some((ep, p, sides.map(|u| fragment(&sc, &clip_f64, p, u))))
        })
        .collect();
    let mut order: Vec<usize> = (0..placed.len()).filter(|&j| placed[j].is_some()).collect();
    order.sort_by_key(|&j| placed[j].as_ref().map_or(0, |x| x.1));
    let mut band_frags = Vec::new();
    let mut edge_list = Vec::with_capacity(order.len());
    for j in order {
        let (ep, p, sides) = placed[j].expect("kept");
        let mut idx = [None; 2];
        for (k, side) in sides.into_iter().enumerate() {
            if let Some(fr) = side {
                idx[k] = Some(band_frags.len() as u32);
                band_frags.push(fr);
            }
        }
        edge_list.push(EdgeSample {
            point: ep,
            pixel: p as u32,
            sides: idx,
        });
    }
    let tape = clip.tape();
    let rs = RasterSettings::new(w, h);
    let make = |frags: &[Frag]| {
        let (f, ndc) = pack::<T>(frags, w, h);
        record_at(clip, Arc::new(f), faces.clone(), &rs, Some(ndc))
    };
    let raster = make(&samples);
    let band = make(&band_frags);
    let weight = tape.constant(ArrayD::from_elem(
        IxDyn(&[samples.len()]),
        T::from_f64c(1.0 / spp as f64),
    ));
    Ok(TracedFragments {
        raster,
        band,
        weight,
        edges: Arc::new(edge_list),
    })
}

/// The box-filtered image of traced fragments shaded `colors` `[N, C]`, with the primary-edge
/// terms of the side fragments shaded `band` `[M, C]` in its backward (module docs):
/// `[H, W, C + 1]`, the last channel the covered fraction of the samples.
///
/// # Errors
/// Shapes (colours not `[N, C]`, band not `[M, C]`, background not `C` values).
pub fn blend_traced<'t, T: Real>(
    colors: Var<'t, T>,
    band: Var<'t, T>,
    traced: &TracedFragments<'t, T>,
    clip: Var<'t, T>,
    background: &[T],
) -> Result<Var<'t, T>, RenderError> {
    let c = background.len();
    let m = traced.band.fragments.len();
    let bs = band.shape();
    if bs != [m, c] {
        return Err(AutodiffError::shape(
            "blend_traced",
            &[&bs],
            format!(
                "band colours must be [{m}, {c}] (the band's fragments, the background's channels)"
            ),
        )
        .into());
    }
    let image = blend_weighted(colors, traced.weight, &traced.raster.fragments, background)?;
    let op = EdgeTermsOp {
        edges: traced.edges.clone(),
        background: background.iter().map(|x| x.to_f64c()).collect(),
    };
    Ok(image.tape().apply(op, &[image, band, clip]))
}

/// Passes the image through; its backward adds the primary-edge terms to the clip positions.
struct EdgeTermsOp {
    edges: Arc<Vec<EdgeSample>>,
    background: Vec<f64>,
}

impl<T: Real> Op<T> for EdgeTermsOp {
    fn name(&self) -> &'static str {
        "raytrace_edges"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        Ok(vec![inputs[0].to_owned()])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let g = ctx.grad_outputs[0];
        let g_image = ctx.needs_grad[0].then(|| g.to_owned());
        if !ctx.needs_grad[2] {
            return Ok(vec![g_image, None, None]);
        }
        let c = self.background.len();
        let g = g.as_standard_layout();
        let g = g.as_slice().expect("standard");
        let band = ctx.inputs[1].as_standard_layout();
        let band = band.as_slice().expect("standard");
        let v = ctx.inputs[2].shape()[0];
        // The colour and coverage of a side: its band fragment's, or the background's.
        let side = |s: Option<u32>, k: usize| match s {
            Some(i) if k < c => band[i as usize * c + k].to_f64c(),
            Some(_) => 1.0,
            None if k < c => self.background[k],
            None => 0.0,
        };
        let grads: Vec<[[f64; 4]; 2]> = self
            .edges
            .par_iter()
            .map(|e| {
                let gp = &g[e.pixel as usize * (c + 1)..][..c + 1];
                let g_delta: f64 = (0..=c)
                    .map(|k| gp[k].to_f64c() * (side(e.sides[0], k) - side(e.sides[1], k)))
                    .sum();
                e.point.clip_grads(g_delta)
            })
            .collect();
        let mut acc = vec![[0.0f64; 4]; v];
        for (e, gr) in self.edges.iter().zip(&grads) {
            for (k, &vi) in e.point.v.iter().enumerate() {
                for (a, x) in acc[vi as usize].iter_mut().zip(gr[k]) {
                    *a += x;
                }
            }
        }
        let out = acc.into_iter().flatten().map(T::from_f64c).collect();
        Ok(vec![
            g_image,
            None,
            Some(ArrayD::from_shape_vec(IxDyn(&[v, 4]), out).expect("v x 4")),
        ])
    }
}
