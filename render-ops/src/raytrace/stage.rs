//! The ray tracer as stages of the fragment pipeline, so that textures and any per-fragment
//! shader compose with it, shadows included (ARCHITECTURE.md, "The ray tracer"):
//!
//! ```text
//! clip [V, 4] (+ world [V, 3], light rows) ─► raytrace_fragments(clip, faces, settings, shadows)
//!    │  raster: one fragment per pixel sample that hits a face (the fused op's samples:
//!    │          same strata, jitter and seed), in sample order per pixel
//!    │  band:   the hits of the two side points `u -+ eps n` of every edge sample: primary
//!    │          (silhouette and occlusion) edges, and shadow boundaries of the directional
//!    │          and point lights
//!    │  with shadows, each fragment's `visibility` [N, L]: shadow rays from its surface point
//!    ▼
//! the shader on `raster` and on `band` (any tape code, as on a rasterization; the built-in
//! shading scales each light by its visibility column)
//!    ▼
//! blend_traced(colours, band colours, traced, clip, background) -> image [H, W, C + 1]
//!       forward: the box filter, `sum_s c_s / spp + (1 - hits / spp) background`
//!       backward: the samples' colours get `g / spp`; the edge terms (Li et al. 2018,
//!       eq. 5-7) from the shaded sides reach the clip positions, and for shadow boundaries
//!       the world positions and the light rows
//! ```
//!
//! A fragment's barycentrics are those of the ray's hit, which are the perspective-correct
//! barycentrics of the rasterizer at the sample's image point, so the fragments are recorded
//! as a rasterization whose backward takes the rasterizer's product at each fragment's own
//! point instead of its pixel centre (`rasterize::record_at`). The edge samples, their
//! placement and their normal velocities are the fused op's (`EdgePoint`, `ShadowEdgePoint`),
//! and so are the shadow rays, so for the built-in shading with vertex colours the composed
//! render and its gradients equal the fused op's (tested).
//!
//! The visibility is a constant: its derivative is the shadow-edge terms, whose two sides are
//! shaded by the same shader with the visibility their own shadow rays give. Area lights are
//! the fused op's only (their samples and edge terms live inside its shading). A band fragment
//! is listed under the pixel of its edge point; its side point lies within `1e-3` pixel of it.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::blend::blend_weighted;
use crate::error::RenderError;
use crate::raster::{Fragments, RasterSettings};
use crate::rasterize::{record_at, Rasterized};
use crate::shade::{acc3, cross3, scale3};

use super::edges::face_normal;
use super::op::{
    check_faces, check_inputs, rows, side_points, Acc, EdgePoint, Edges, Scene, ShadowEdgePoint,
};
use super::shading::{LightKind, Shadow};
use super::RaytraceSettings;

/// The fragments of a ray-traced render ([`raytrace_fragments`]).
pub struct TracedFragments<'t, T: Real> {
    /// One fragment per pixel sample that hits a face, in sample order within each pixel.
    pub raster: Rasterized<'t, T>,
    /// The hits of the edge samples' side points (primary edges, shadow boundaries), under the
    /// pixel of each edge point.
    pub band: Rasterized<'t, T>,
    /// Each sample fragment's weight in its pixel, `1 / spp` (a constant).
    pub weight: Var<'t, T>,
    edges: Arc<Vec<EdgeSample>>,
    shadows: Option<ShadowInputs<'t, T>>,
}

/// An edge sample: its point, its pixel, and the band fragment of each side (`None`: the side
/// sees the background).
#[derive(Clone, Copy, Debug)]
struct EdgeSample {
    kind: EdgeKind,
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

/// The inputs of [`raytrace_fragments`]' shadow rays: world positions `[V, 3]` and the light
/// rows `[n, 3]` of `kinds` (layout of [`super::raytrace`]'s `lights`). The visibility they
/// give is a constant; its derivative is [`blend_traced`]'s shadow-edge terms, which reach
/// these two inputs and the clip positions.
#[derive(Clone, Debug)]
pub struct ShadowInputs<'t, T: Real> {
    /// World positions `[V, 3]`, the clip positions' vertices.
    pub world: Var<'t, T>,
    /// Light rows `[n, 3]`.
    pub lights: Var<'t, T>,
    /// The lights' kinds, in the order of their rows (ambient, directional, point, sh; area
    /// lights are sampled by the fused op only).
    pub kinds: Vec<LightKind>,
}

/// An edge sample of the stage: where it falls, and the clip gradients it gives.
#[derive(Clone, Copy, Debug)]
enum EdgeKind {
    /// A silhouette or occlusion edge seen from the camera.
    Primary(EdgePoint),
    /// An occluder edge's shadow boundary, from a directional or point light.
    Shadow(ShadowEdgePoint),
}

/// The visibility columns (directional lights, then point lights, each in scene order) and
/// their shadow queries from a point: indices into `kinds`.
fn visibility_columns(kinds: &[LightKind]) -> Vec<usize> {
    let of = |k| {
        kinds
            .iter()
            .enumerate()
            .filter(move |(_, x)| **x == k)
            .map(|(i, _)| i)
    };
    of(LightKind::Directional)
        .chain(of(LightKind::Point))
        .collect()
}

/// Casts the primary rays of `settings`' pixel samples and of the two sides of its edge
/// samples (module docs): primary edges, and with `shadows` the shadow boundaries of its
/// directional and point lights, whose visibility each fragment then carries
/// ([`Rasterized::visibility`], by shadow rays as the fused op casts them). `width`, `height`,
/// `spp`, `seed`, `near`, `far`, `shadows` and the edge sample counts are read; the settings'
/// own `lights` are replaced by `shadows.kinds`; shading belongs to the shader. The band is
/// empty when neither `clip` nor the shadow inputs need a gradient (a forward-only render).
///
/// # Errors
/// `clip` not `[V, 4]`, `world` not `[V, 3]`, light rows not those of `kinds`, non-finite
/// values, face indices out of range, an area light (`Unsupported`), invalid settings.
pub fn raytrace_fragments<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RaytraceSettings,
    shadows: Option<ShadowInputs<'t, T>>,
) -> Result<TracedFragments<'t, T>, RenderError> {
    settings.validate()?;
    let kinds = shadows.as_ref().map_or(Vec::new(), |x| x.kinds.clone());
    if kinds.contains(&LightKind::Area) {
        return Err(RenderError::Unsupported(
            "raytrace fragments: area lights are sampled by the fused raytrace op only (built-in \
             shading with vertex colours)"
                .into(),
        ));
    }
    let s = RaytraceSettings {
        lights: kinds.clone(),
        ..settings.clone()
    };
    let v = clip.shape().first().copied().unwrap_or(0);
    let n_rows: usize = kinds.iter().map(|k| k.rows()).sum();
    check_inputs("raytrace_fragments", &[("clip", clip, [v, 4])])?;
    if let Some(sh) = &shadows {
        let want = [
            ("world", sh.world, [v, 3]),
            ("lights", sh.lights, [n_rows, 3]),
        ];
        check_inputs("raytrace_fragments", &want)?;
    }
    check_faces(&faces, v)?;
    let clip_f64: Vec<[f64; 4]> = rows(&clip.value_ref()?.view());
    let sc = match &shadows {
        Some(sh) => Scene::with_lights(
            &s,
            &faces,
            clip_f64.clone(),
            rows(&sh.world.value_ref()?.view()),
            rows(&sh.lights.value_ref()?.view()),
        ),
        None => Scene::primary_only(&s, &faces, clip_f64.clone()),
    };
    let columns = if shadows.is_some() && s.shadows {
        visibility_columns(&kinds)
    } else {
        Vec::new()
    };
    let lights = sc.lights();
    // The visibility of each column's light from the surface point of a fragment.
    // The shadow query of each column's light (the same from every point).
    let queries: Vec<Shadow> = columns
        .iter()
        .map(|&li| {
            let r = sc.light_rows[lights.offsets[li]];
            match kinds[li] {
                LightKind::Directional => Shadow::Along(scale3(r, -1.0)),
                _ => Shadow::Toward(r),
            }
        })
        .collect();
    // The visibility of each column's light from the surface point of a fragment, into `out`.
    let visibility = |fr: &Frag, out: &mut [T]| {
        let tri = faces[fr.1 as usize];
        let mut x = [0.0; 3];
        for (i, &vi) in tri.iter().enumerate() {
            acc3(&mut x, scale3(sc.world[vi as usize], fr.2[i]));
        }
        let ng = face_normal(&sc.world, &tri);
        for (o, &q) in out.iter_mut().zip(&queries) {
            *o = if sc.visible(x, ng, q) {
                T::one()
            } else {
                T::zero()
            };
        }
    };
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
    // The edge samples only serve gradients: none when no geometry input asks for one.
    let wants = clip.requires_grad()
        || shadows
            .as_ref()
            .is_some_and(|sh| sh.world.requires_grad() || sh.lights.requires_grad());
    let edges = wants.then(|| Edges::new(&sc));
    let count = |cdf_empty: fn(&Edges) -> bool, n: usize| match &edges {
        Some(e) if !cdf_empty(e) => n,
        _ => 0,
    };
    let n_primary = count(|e| e.primary.is_empty(), s.primary_edge_samples);
    let n_shadow = count(|e| e.shadow.is_empty(), s.shadow_edge_samples);
    // Per edge sample (primary, then shadow): its point, pixel and side hits; then the band in
    // pixel order (stable in the sample index, so the order is fixed).
    let placed: Vec<Option<(EdgeKind, usize, [Option<Frag>; 2])>> = (0..n_primary + n_shadow)
        .into_par_iter()
        .map(|j| {
            let edges = edges.as_ref()?;
            let (kind, u, a) = if j < n_primary {
                let (ep, _) = sc.primary_edge_point(j, edges)?;
                (EdgeKind::Primary(ep), ep.u, ep.a)
            } else {
                let (sp, _) = sc.shadow_edge_point(&lights, j - n_primary, edges)?;
                (EdgeKind::Shadow(sp), sp.u, sp.a)
            };
            let p = sc.pixel(u)?;
            let sides = side_points(u, a)?;
            Some((kind, p, sides.map(|u| fragment(&sc, &clip_f64, p, u))))
        })
        .collect();
    let mut order: Vec<usize> = (0..placed.len()).filter(|&j| placed[j].is_some()).collect();
    order.sort_by_key(|&j| placed[j].as_ref().map_or(0, |x| x.1));
    let mut band_frags = Vec::new();
    let mut edge_list = Vec::with_capacity(order.len());
    for j in order {
        let (kind, p, sides) = placed[j].expect("kept");
        let mut idx = [None; 2];
        for (k, side) in sides.into_iter().enumerate() {
            if let Some(fr) = side {
                idx[k] = Some(band_frags.len() as u32);
                band_frags.push(fr);
            }
        }
        edge_list.push(EdgeSample {
            kind,
            pixel: p as u32,
            sides: idx,
        });
    }
    let tape = clip.tape();
    let rs = RasterSettings::new(w, h);
    let make = |frags: &[Frag]| {
        let (f, ndc) = pack::<T>(frags, w, h);
        let mut r = record_at(clip, Arc::new(f), faces.clone(), &rs, Some(ndc));
        if !columns.is_empty() {
            let l = columns.len();
            let mut vis = vec![T::zero(); frags.len() * l];
            vis.par_chunks_mut(l)
                .zip(frags.par_iter())
                .for_each(|(out, fr)| visibility(fr, out));
            let vis = ArrayD::from_shape_vec(IxDyn(&[frags.len(), l]), vis).expect("n x l");
            r.visibility = Some(tape.constant(vis));
        }
        r
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
        shadows: shadows.filter(|_| s.shadows),
    })
}

/// The box-filtered image of traced fragments shaded `colors` `[N, C]`, with the edge terms
/// of the side fragments shaded `band` `[M, C]` in its backward (module docs): `[H, W, C + 1]`,
/// the last channel the covered fraction of the samples. The primary-edge terms reach `clip`;
/// the shadow-edge terms reach `clip` and the world positions and light rows of the stage's
/// [`ShadowInputs`].
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
    let mut inputs = vec![image, band, clip];
    if let Some(sh) = &traced.shadows {
        inputs.extend([sh.world, sh.lights]);
    }
    Ok(image.tape().apply(op, &inputs))
}

/// Passes the image through; its backward adds the edge terms: primary edges to the clip
/// positions, shadow boundaries to the clip and world positions and the light rows.
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
        let need = ctx.needs_grad;
        let g = ctx.grad_outputs[0];
        let mut out: Vec<Option<Tensor<T>>> = vec![None; need.len()];
        out[0] = need[0].then(|| g.to_owned());
        if !need[2..].iter().any(|&b| b) {
            return Ok(out);
        }
        let c = self.background.len();
        let g = g.as_standard_layout();
        let g = g.as_slice().expect("standard");
        let band = ctx.inputs[1].as_standard_layout();
        let band = band.as_slice().expect("standard");
        // The colour and coverage of a side: its band fragment's, or the background's.
        let side = |s: Option<u32>, k: usize| match s {
            Some(i) if k < c => band[i as usize * c + k].to_f64c(),
            Some(_) => 1.0,
            None if k < c => self.background[k],
            None => 0.0,
        };
        let g_delta: Vec<f64> = self
            .edges
            .par_iter()
            .map(|e| {
                let gp = &g[e.pixel as usize * (c + 1)..][..c + 1];
                (0..=c)
                    .map(|k| gp[k].to_f64c() * (side(e.sides[0], k) - side(e.sides[1], k)))
                    .sum()
            })
            .collect();
        // Dense accumulators, added in edge order (the same on any pool).
        let v = ctx.inputs[2].shape()[0];
        let n_rows = ctx.inputs.get(4).map_or(0, |l| l.shape()[0]);
        let wants = |i: usize| need.get(i) == Some(&true);
        let mut acc = Acc::new(v, n_rows, &[wants(2), wants(3), false, false, wants(4)]);
        for (e, &gd) in self.edges.iter().zip(&g_delta) {
            match &e.kind {
                EdgeKind::Primary(ep) => acc.primary_edge(ep, gd),
                EdgeKind::Shadow(sp) => acc.shadow_edge(sp, gd),
            }
        }
        let tensor = |a: Vec<f64>, shape: [usize; 2]| {
            ArrayD::from_shape_vec(IxDyn(&shape), a.into_iter().map(T::from_f64c).collect())
                .expect("shape")
        };
        if wants(2) {
            out[2] = Some(tensor(acc.clip.into_flattened(), [v, 4]));
        }
        if wants(3) {
            out[3] = Some(tensor(acc.world.into_flattened(), [v, 3]));
        }
        if wants(4) {
            out[4] = Some(tensor(acc.rows.into_flattened(), [n_rows, 3]));
        }
        Ok(out)
    }
}
