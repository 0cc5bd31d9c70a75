//! The `raytrace` tape op: forward render and the backward of [`super`] (interior, primary
//! edges, shadow edges, area-light edges), parallel over fixed chunks of rows and edge samples
//! whose per-vertex accumulators are summed in chunk order (bit-identical on any pool).

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;
use smallvec::SmallVec;

use crate::error::RenderError;
use crate::shade::{acc3, add3, cross3, dot3, scale3, sub3};

use super::bvh::Bvh;
use super::edges::{face_normal, is_silhouette, mesh_edges, plane_hit, Cdf, Edge, Viewer};
use super::grid::ScreenGrid;
use super::intersect::{Hit, Ray, V3};
use super::rng::{stream_key, Counter, Stream};
use super::shading::{LightKind, LightSet, Reflection, ShadeGrad, Shadow};

/// Most pixels of one render (as the rasterizer's limit).
const MAX_PIXELS: usize = 1 << 26;
/// Side offset of edge evaluations, in pixels (primary and shadow edges) or in the light's
/// `(a, b)` units (area-light edges).
const SIDE_EPS_PX: f64 = 1e-3;
const SIDE_EPS_AB: f64 = 1e-5;

/// Settings of [`raytrace`].
#[derive(Clone, Debug, PartialEq)]
pub struct RaytraceSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Samples per pixel (stratified), >= 1.
    pub spp: usize,
    /// Seed of the counter-based random numbers.
    pub seed: u64,
    /// Background colour.
    pub background: [f64; 3],
    /// Near plane (view depth); primary hits nearer than it are clipped, as in the rasterizer.
    pub near: f64,
    /// Far plane (view depth).
    pub far: f64,
    /// The camera position in world space (view directions of specular terms, the shading
    /// point's motion for area-light edges).
    pub eye: [f64; 3],
    /// Reflection model and its constants.
    pub reflection: Reflection,
    /// Kinds of the lights, in the order of their rows.
    pub lights: Vec<LightKind>,
    /// Shadow rays (default true); off: every light is unshadowed.
    pub shadows: bool,
    /// Primary (silhouette) edge samples per backward, 0 for none (default: one per pixel).
    pub primary_edge_samples: usize,
    /// Shadow-edge samples of point and directional lights per backward (default: one per
    /// pixel).
    pub shadow_edge_samples: usize,
    /// Area-light edge samples per pixel sample and area light (default 1).
    pub area_edge_samples: usize,
}

impl RaytraceSettings {
    /// Defaults for a `width x height` image: 4 samples per pixel, seed 0, black background,
    /// near 0.1, far 100, eye at the origin, unlit (`shading: none`), no lights, shadows on,
    /// one primary and one shadow edge sample per pixel, one area edge sample per sample.
    pub fn new(width: usize, height: usize) -> Self {
        RaytraceSettings {
            width,
            height,
            spp: 4,
            seed: 0,
            background: [0.0; 3],
            near: 0.1,
            far: 100.0,
            eye: [0.0; 3],
            reflection: Reflection {
                shading: crate::scene::Shading::None,
                ks: [0.2; 3],
                shininess: 32.0,
                ka: None,
            },
            lights: Vec::new(),
            shadows: true,
            primary_edge_samples: width * height,
            shadow_edge_samples: width * height,
            area_edge_samples: 1,
        }
    }

    pub(super) fn validate(&self) -> Result<(), RenderError> {
        let bad = |m: String| Err(RenderError::Unsupported(format!("raytrace: {m}")));
        if self.width == 0 || self.height == 0 || self.width * self.height > MAX_PIXELS {
            return bad(format!(
                "image {} x {} must have 1 to {MAX_PIXELS} pixels",
                self.width, self.height
            ));
        }
        if self.spp == 0 || self.spp > 1 << 16 {
            return bad(format!("spp {} must be 1 to 65536", self.spp));
        }
        if !(self.near > 0.0 && self.far > self.near && self.far.is_finite()) {
            return bad(format!(
                "near {} and far {} must satisfy 0 < near < far < inf",
                self.near, self.far
            ));
        }
        let r = &self.reflection;
        let finite = self
            .background
            .iter()
            .chain(&self.eye)
            .chain(&r.ks)
            .chain(r.ka.iter().flatten())
            .all(|x| x.is_finite());
        if !(finite && r.shininess >= 0.0 && r.shininess.is_finite()) {
            return bad("background, eye, ks, ka and shininess must be finite".into());
        }
        Ok(())
    }

    /// Strata per row and per column of a pixel: the divisor pair of `spp` nearest a square.
    fn strata(&self) -> (usize, usize) {
        let mut sx = (self.spp as f64).sqrt() as usize;
        while sx > 1 && !self.spp.is_multiple_of(sx) {
            sx -= 1;
        }
        (sx.max(1), self.spp / sx.max(1))
    }
}

/// Renders `faces` by ray tracing: `clip` `[V, 4]` clip positions of a perspective camera,
/// `world` `[V, 3]` world positions, `normals` `[V, 3]` vertex normals (any length), `albedo`
/// `[V, 3]`, `lights` `[n, 3]` the light rows of `settings.lights` (ambient: colour;
/// directional: direction, colour; point: position, colour; area: corner, edge_u, edge_v,
/// radiance; sh: 9 rows). The image is `[H, W, 4]`: RGB over the background, then coverage.
///
/// # Errors
/// Shapes, face indices out of range, non-finite inputs, invalid settings.
#[allow(clippy::too_many_arguments)]
pub fn raytrace<'t, T: Real>(
    clip: Var<'t, T>,
    world: Var<'t, T>,
    normals: Var<'t, T>,
    albedo: Var<'t, T>,
    lights: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RaytraceSettings,
) -> Result<Var<'t, T>, RenderError> {
    settings.validate()?;
    let v = clip.shape().first().copied().unwrap_or(0);
    let n_rows: usize = settings.lights.iter().map(|k| k.rows()).sum();
    let want: [(&'static str, Var<'t, T>, [usize; 2]); 5] = [
        ("clip", clip, [v, 4]),
        ("world", world, [v, 3]),
        ("normals", normals, [v, 3]),
        ("albedo", albedo, [v, 3]),
        ("lights", lights, [n_rows, 3]),
    ];
    check_inputs("raytrace", &want)?;
    check_faces(&faces, v)?;
    let op = RaytraceOp {
        faces,
        s: settings.clone(),
    };
    Ok(clip
        .tape()
        .apply(op, &[clip, world, normals, albedo, lights]))
}

/// Each named input has its shape and finite values.
pub(super) fn check_inputs<T: Real, const N: usize>(
    op: &'static str,
    want: &[(&'static str, Var<'_, T>, [usize; N])],
) -> Result<(), RenderError> {
    for (name, var, shape) in want {
        let val = var.value_ref()?;
        if val.shape() != shape {
            return Err(AutodiffError::shape(
                op,
                &[val.shape()],
                format!("{name} must be {shape:?}"),
            )
            .into());
        }
        RenderError::check_finite(name, &val.view())?;
    }
    Ok(())
}

/// Every face index is below `v`.
pub(super) fn check_faces(faces: &[[u32; 3]], v: usize) -> Result<(), RenderError> {
    match faces
        .iter()
        .enumerate()
        .find(|(_, t)| t.iter().any(|&i| i as usize >= v))
    {
        Some((f, tri)) => Err(RenderError::Unsupported(format!(
            "raytrace: face {f} {tri:?} indexes past the {v} vertices"
        ))),
        None => Ok(()),
    }
}

struct RaytraceOp {
    faces: Arc<Vec<[u32; 3]>>,
    s: RaytraceSettings,
}

pub(super) fn rows<T: Real, const N: usize, S: ndarray::Data<Elem = T>>(
    t: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> Vec<[f64; N]> {
    let t = t.as_standard_layout();
    t.as_slice()
        .expect("standard")
        .chunks_exact(N)
        .map(|c| std::array::from_fn(|k| c[k].to_f64c()))
        .collect()
}

/// Everything one evaluation reads, built once per forward or backward.
pub(super) struct Scene<'a> {
    pub(super) s: &'a RaytraceSettings,
    pub(super) faces: &'a [[u32; 3]],
    pub(super) q: Vec<V3>,
    pub(super) clip: Vec<[f64; 4]>,
    pub(super) world: Vec<V3>,
    pub(super) normals: Vec<V3>,
    pub(super) albedo: Vec<V3>,
    pub(super) light_rows: Vec<V3>,
    pub(super) primary: ScreenGrid,
    pub(super) shadow: Option<Bvh>,
    /// Scale of the world coordinates (shadow-ray offsets).
    pub(super) scale: f64,
    /// Strata per pixel ([`RaytraceSettings::strata`]) and the pixel samples' stream key.
    pub(super) strata: (usize, usize),
    pixel_key: u64,
    /// `shading: none` and no lights: the colour is the albedo, and nothing reads a hit's
    /// point or normals.
    pub(super) unlit: bool,
}

/// Per-chunk gradient accumulators (dense per vertex; only the wanted inputs allocated): clip,
/// world, normals, albedo, light rows.
pub(super) struct Acc {
    pub(super) clip: Vec<[f64; 4]>,
    pub(super) world: Vec<V3>,
    normals: Vec<V3>,
    albedo: Vec<V3>,
    pub(super) rows: Vec<V3>,
}

impl Acc {
    /// Accumulators for the inputs `need` marks (clip, world, normals, albedo, light rows).
    pub(super) fn new(v: usize, n_rows: usize, need: &[bool]) -> Self {
        let n = |i: usize, len: usize| if need[i] { len } else { 0 };
        Acc {
            clip: vec![[0.0; 4]; n(0, v)],
            world: vec![[0.0; 3]; n(1, v)],
            normals: vec![[0.0; 3]; n(2, v)],
            albedo: vec![[0.0; 3]; n(3, v)],
            rows: vec![[0.0; 3]; n(4, n_rows)],
        }
    }

    /// Adds the gradients of primary-edge sample `ep` for a two-sided difference whose product
    /// with the output gradient is `g_delta`.
    pub(super) fn primary_edge(&mut self, ep: &EdgePoint, g_delta: f64) {
        if g_delta == 0.0 || self.clip.is_empty() {
            return;
        }
        let g = ep.clip_grads(g_delta);
        add_to(&mut self.clip, ep.v[0] as usize, g[0]);
        add_to(&mut self.clip, ep.v[1] as usize, g[1]);
    }

    /// Adds the gradients of shadow-edge sample `sp` (light row, world and clip positions) for
    /// a two-sided difference whose product with the output gradient is `g_delta`.
    pub(super) fn shadow_edge(&mut self, sp: &ShadowEdgePoint, g_delta: f64) {
        if g_delta == 0.0 {
            return;
        }
        let g = sp.grads(g_delta);
        add_to(&mut self.rows, g.row.0, g.row.1);
        for (v, x) in g.world {
            add_to(&mut self.world, v as usize, x);
        }
        for (v, x) in g.clip {
            add_to(&mut self.clip, v as usize, x);
        }
    }
}

fn add_to<const N: usize>(acc: &mut [[f64; N]], i: usize, g: [f64; N]) {
    if let Some(a) = acc.get_mut(i) {
        for k in 0..N {
            a[k] += g[k];
        }
    }
}

/// The hit of a primary sample, in world terms.
struct Surface {
    face: u32,
    bary: V3,
    x: V3,
    nraw: V3,
    albedo: V3,
    ng: V3,
    dir: V3,
}

impl<'a> Scene<'a> {
    fn new<T: Real>(op: &'a RaytraceOp, inputs: &[TensorView<'_, T>]) -> Self {
        Scene::build(
            &op.s,
            &op.faces,
            rows(&inputs[0]),
            rows(&inputs[1]),
            rows(&inputs[2]),
            rows(&inputs[3]),
            rows(&inputs[4]),
        )
    }

    /// The primary rays' scene alone (the fragment stage, [`super::stage`]): no shading inputs
    /// and no lights; the clip coordinates stand in for the world positions, which only weld
    /// the mesh's edges there.
    pub(super) fn primary_only(
        s: &'a RaytraceSettings,
        faces: &'a [[u32; 3]],
        clip: Vec<[f64; 4]>,
    ) -> Self {
        let world = clip.iter().map(|c| [c[0], c[1], c[2]]).collect();
        Scene::build(s, faces, clip, world, Vec::new(), Vec::new(), Vec::new())
    }

    /// The primary rays' and shadow rays' scene (the fragment stage with lights): no
    /// shading inputs.
    pub(super) fn with_lights(
        s: &'a RaytraceSettings,
        faces: &'a [[u32; 3]],
        clip: Vec<[f64; 4]>,
        world: Vec<V3>,
        light_rows: Vec<V3>,
    ) -> Self {
        Scene::build(s, faces, clip, world, Vec::new(), Vec::new(), light_rows)
    }

    pub(super) fn build(
        s: &'a RaytraceSettings,
        faces: &'a [[u32; 3]],
        clip: Vec<[f64; 4]>,
        world: Vec<V3>,
        normals: Vec<V3>,
        albedo: Vec<V3>,
        light_rows: Vec<V3>,
    ) -> Self {
        let q: Vec<V3> = clip.iter().map(|c| [c[0], c[1], c[3]]).collect();
        let lit = s.shadows
            && !light_rows.is_empty()
            && s.lights.iter().any(|k| {
                matches!(
                    k,
                    LightKind::Directional | LightKind::Point | LightKind::Area
                )
            });
        let (primary, shadow) = rayon::join(
            || ScreenGrid::new(&q, faces, s.width, s.height, s.near),
            || lit.then(|| Bvh::new(&world, faces)),
        );
        let scale = world.iter().flatten().fold(1.0f64, |m, x| m.max(x.abs()));
        Scene {
            s,
            faces,
            q,
            clip,
            world,
            normals,
            albedo,
            light_rows,
            primary,
            shadow,
            scale,
            strata: s.strata(),
            pixel_key: stream_key(s.seed, Stream::Pixel),
            unlit: s.reflection.shading == crate::scene::Shading::None && s.lights.is_empty(),
        }
    }

    /// Pixel point and random numbers of sample `k` of pixel `pix`: one jittered point in the
    /// sample's stratum (`sx x sy` strata per pixel), the counter left at the sample's next
    /// dimension (the area lights' samples).
    pub(super) fn sample(&self, pix: usize, k: usize) -> ([f64; 2], Counter) {
        let (sx, w) = (self.strata.0, self.s.width);
        self.sample_at(pix / w, pix % w, k, (k % sx, k / sx))
    }

    /// [`Scene::sample`] of sample `k` of the pixel in row `r`, column `c`, whose stratum
    /// `(k % sx, k / sx)` is given (the packets step through them without dividing).
    #[inline(always)]
    pub(super) fn sample_at(
        &self,
        r: usize,
        c: usize,
        k: usize,
        stratum: (usize, usize),
    ) -> ([f64; 2], Counter) {
        let (sx, sy) = self.strata;
        let pix = r * self.s.width + c;
        let mut ctr = Counter::at(self.pixel_key, (pix * self.s.spp + k) as u64);
        let u = [
            c as f64 + (stratum.0 as f64 + ctr.uniform()) / sx as f64,
            r as f64 + (stratum.1 as f64 + ctr.uniform()) / sy as f64,
        ];
        (u, ctr)
    }

    pub(super) fn lights(&self) -> LightSet<'_> {
        LightSet::new(&self.s.lights, &self.light_rows).expect("rows checked")
    }

    /// NDC of a point in pixel coordinates (x right, y down).
    fn ndc(&self, u: [f64; 2]) -> [f64; 2] {
        [
            2.0 * u[0] / self.s.width as f64 - 1.0,
            1.0 - 2.0 * u[1] / self.s.height as f64,
        ]
    }

    /// The nearest face on the primary ray through pixel point `u` (within the clip planes)
    /// and the ray's direction `(x, y, 1)` in `(clip.x, clip.y, clip.w)` (NDC `x, y`).
    pub(super) fn primary_hit(&self, u: [f64; 2]) -> Option<(Hit, V3)> {
        let [x, y] = self.ndc(u);
        let dir = [x, y, 1.0];
        let r = Ray::new([0.0; 3], dir);
        Some((self.primary.closest(&r, u, self.s.near, self.s.far)?, dir))
    }

    /// The primary hit through pixel point `u`.
    fn hit(&self, u: [f64; 2]) -> Option<Surface> {
        let (h, dir) = self.primary_hit(u)?;
        let tri = self.faces[h.face as usize];
        let lerp = |a: &[V3]| {
            let mut o = [0.0; 3];
            for (i, &vi) in tri.iter().enumerate() {
                acc3(&mut o, scale3(a[vi as usize], h.bary[i]));
            }
            o
        };
        let (x, nraw, ng) = if self.unlit {
            ([0.0; 3], [0.0; 3], [0.0; 3])
        } else {
            (
                lerp(&self.world),
                lerp(&self.normals),
                face_normal(&self.world, &tri),
            )
        };
        Some(Surface {
            face: h.face,
            bary: h.bary,
            x,
            nraw,
            albedo: lerp(&self.albedo),
            ng,
            dir,
        })
    }

    /// Shadow test from `x` (geometric normal `ng`): the origin is pushed off the surface
    /// towards the light by a small multiple of the scene's scale.
    pub(super) fn visible(&self, x: V3, ng: V3, q: Shadow) -> bool {
        let Some(bvh) = &self.shadow else {
            return true;
        };
        let (dir, t_max) = match q {
            Shadow::Toward(p) => (sub3(p, x), 1.0 - 1e-9),
            Shadow::Along(d) => (d, f64::INFINITY),
        };
        let len = dot3(ng, ng).sqrt();
        let side = if dot3(ng, dir) >= 0.0 { 1.0 } else { -1.0 };
        let off = if len > 0.0 {
            scale3(ng, side * 1e-9 * self.scale / len)
        } else {
            [0.0; 3]
        };
        let o = add3(x, off);
        let dir = match q {
            Shadow::Toward(p) => sub3(p, o),
            Shadow::Along(d) => d,
        };
        if dot3(dir, dir) == 0.0 {
            return true;
        }
        !bvh.occluded(&Ray::new(o, dir), 0.0, t_max)
    }

    fn area_samples(&self, ctr: &mut Counter, n: usize) -> SmallVec<[[f64; 2]; 4]> {
        (0..n).map(|_| [ctr.uniform(), ctr.uniform()]).collect()
    }

    /// The radiance (RGB, coverage) of the primary ray through `u`, with the area lights
    /// sampled from `ctr`; with `grad`, the gradient of `g . value` of the interior terms
    /// (and, for `area_edges`, the area-light edge terms of this sample) into `acc`.
    pub(super) fn radiance(
        &self,
        lights: &LightSet<'_>,
        u: [f64; 2],
        mut ctr: Counter,
        grad: Option<([f64; 4], &mut Acc)>,
        area_edges: Option<(&Edges, u64)>,
    ) -> [f64; 4] {
        let bg = self.s.background;
        let Some(hit) = self.hit(u) else {
            return [bg[0], bg[1], bg[2], 0.0];
        };
        let ab = self.area_samples(&mut ctr, lights.n_area);
        let mut vis = |q| self.visible(hit.x, hit.ng, q);
        let mut sg = ShadeGrad::default();
        let mut grad = grad.map(|(g, acc)| ([g[0], g[1], g[2]], acc));
        let c = lights.shade(
            &self.s.reflection,
            hit.x,
            hit.nraw,
            hit.albedo,
            self.s.eye,
            &ab,
            &mut vis,
            grad.as_mut()
                .map(|(g3, acc)| (*g3, &mut sg, acc.rows.as_mut_slice())),
        );
        if let Some((g3, acc)) = grad {
            if let Some((edges, index)) = area_edges {
                self.area_edge_terms(lights, &hit, g3, (edges, index), acc);
            }
            self.surface_backward(&hit, &sg, acc);
        }
        [c[0], c[1], c[2], 1.0]
    }

    /// Scatters the shading gradient of a hit onto its vertices: interpolation (world,
    /// normals, albedo) and the hit barycentrics (clip).
    fn surface_backward(&self, hit: &Surface, sg: &ShadeGrad, acc: &mut Acc) {
        let tri = self.faces[hit.face as usize];
        let b = hit.bary;
        let mut gb = [0.0; 3];
        for (i, &vi) in tri.iter().enumerate() {
            let vi = vi as usize;
            add_to(&mut acc.world, vi, scale3(sg.x, b[i]));
            add_to(&mut acc.normals, vi, scale3(sg.nraw, b[i]));
            add_to(&mut acc.albedo, vi, scale3(sg.albedo, b[i]));
            gb[i] = dot3(sg.x, self.world[vi])
                + dot3(sg.nraw, self.normals[vi])
                + dot3(sg.albedo, self.albedo[vi]);
        }
        if acc.clip.is_empty() {
            return;
        }
        let q = tri.map(|i| self.q[i as usize]);
        for (i, g) in bary_vjp(q, hit.dir, b, gb).into_iter().enumerate() {
            add_to(&mut acc.clip, tri[i] as usize, [g[0], g[1], 0.0, g[2]]);
        }
    }

    /// Pixel coordinates of clip point `c` and the rows of `d pixel / d clip`.
    fn project(&self, c: [f64; 4]) -> ([f64; 2], [[f64; 4]; 2]) {
        let (w, h) = (self.s.width as f64, self.s.height as f64);
        let iw = 1.0 / c[3];
        let u = [(c[0] * iw + 1.0) * 0.5 * w, (1.0 - c[1] * iw) * 0.5 * h];
        let d = [
            [0.5 * w * iw, 0.0, 0.0, -0.5 * w * c[0] * iw * iw],
            [0.0, -0.5 * h * iw, 0.0, 0.5 * h * c[1] * iw * iw],
        ];
        (u, d)
    }

    pub(super) fn pixel(&self, u: [f64; 2]) -> Option<usize> {
        let (c, r) = (u[0].floor(), u[1].floor());
        (c >= 0.0 && r >= 0.0 && (c as usize) < self.s.width && (r as usize) < self.s.height)
            .then(|| r as usize * self.s.width + c as usize)
    }

    /// The loss's change across an edge at image point `u` with image tangent `a`:
    /// `g_pixel . (f(u - eps n) - f(u + eps n))` (`n` = `perp(a) / |a|`, `g_pixel` the image
    /// gradient of `u`'s pixel); `None` off the image.
    fn across_edge(
        &self,
        lights: &LightSet<'_>,
        u: [f64; 2],
        a: [f64; 2],
        ctr: Counter,
        gimg: &[[f64; 4]],
    ) -> Option<f64> {
        let p = self.pixel(u)?;
        let [um, up] = side_points(u, a)?;
        let minus = self.radiance(lights, um, ctr, None, None);
        let plus = self.radiance(lights, up, ctr, None, None);
        Some(dot4(gimg[p], std::array::from_fn(|k| minus[k] - plus[k])))
    }

    /// Area-light edge terms of one pixel sample (module docs), into `acc`.
    fn area_edge_terms(
        &self,
        lights: &LightSet<'_>,
        hit: &Surface,
        g: V3,
        (edges, index): (&Edges, u64),
        acc: &mut Acc,
    ) {
        let m = self.s.area_edge_samples;
        if m == 0 {
            return;
        }
        let mut area_k = 0u64;
        for (li, kind) in self.s.lights.iter().enumerate() {
            if *kind != LightKind::Area {
                continue;
            }
            let o = lights.offsets[li];
            let one = LightSet::new(&[LightKind::Area], &self.light_rows[o..o + 4]).expect("4");
            let r = &self.light_rows;
            let quad = [r[o], add3(r[o], r[o + 1]), add3(r[o], r[o + 2])];
            let cdf = &edges.area[area_k as usize];
            for j in 0..m {
                if cdf.is_empty() {
                    break;
                }
                let idx = (index * lights.n_area as u64 + area_k) * m as u64 + j as u64;
                let mut ctr = Counter::new(self.s.seed, Stream::AreaEdge, idx);
                let (e, pe) = cdf.sample(ctr.uniform());
                let s = ctr.uniform();
                let edge = edges.list[e as usize];
                if !is_silhouette(&edge, &self.world, self.faces, Viewer::At(hit.x)) {
                    continue;
                }
                let (pa, pb) = (
                    self.world[edge.v[0] as usize],
                    self.world[edge.v[1] as usize],
                );
                let dp = sub3(pb, pa);
                let p = add3(pa, scale3(dp, s));
                let d = sub3(p, hit.x);
                let Some(ph) = plane_hit(hit.x, d, quad) else {
                    continue;
                };
                let (t, ab) = (ph.t, [ph.beta[1], ph.beta[2]]);
                if !(t > 1.0) || !(0.0..=1.0).contains(&ab[0]) || !(0.0..=1.0).contains(&ab[1]) {
                    continue;
                }
                let tan = [t * dot3(ph.j[0], dp), t * dot3(ph.j[1], dp)];
                let len = (tan[0] * tan[0] + tan[1] * tan[1]).sqrt();
                if !(len > 0.0 && len.is_finite()) {
                    continue;
                }
                let nrm = [-tan[1] / len * SIDE_EPS_AB, tan[0] / len * SIDE_EPS_AB];
                let mut vis = |q| self.visible(hit.x, hit.ng, q);
                let mut side = |sgn: f64| {
                    let at = [ab[0] + sgn * nrm[0], ab[1] + sgn * nrm[1]];
                    one.shade(
                        &self.s.reflection,
                        hit.x,
                        hit.nraw,
                        hit.albedo,
                        self.s.eye,
                        &[at],
                        &mut vis,
                        None,
                    )
                };
                let delta = sub3(side(-1.0), side(1.0));
                let scal = dot3(g, delta) / (m as f64 * pe);
                if scal == 0.0 {
                    continue;
                }
                let z = sub3(scale3(ph.j[1], tan[0]), scale3(ph.j[0], tan[1]));
                let zs = scale3(z, scal);
                add_to(&mut acc.rows, o, scale3(zs, -1.0));
                add_to(&mut acc.rows, o + 1, scale3(zs, -ab[0]));
                add_to(&mut acc.rows, o + 2, scale3(zs, -ab[1]));
                add_to(
                    &mut acc.world,
                    edge.v[0] as usize,
                    scale3(zs, t * (1.0 - s)),
                );
                add_to(&mut acc.world, edge.v[1] as usize, scale3(zs, t * s));
                // The shading point moves with its receiver along the camera ray.
                let gx = scale3(zs, 1.0 - t);
                let dc = sub3(hit.x, self.s.eye);
                let nd = dot3(hit.ng, dc);
                if nd != 0.0 && !acc.world.is_empty() {
                    let k = dot3(dc, gx) / nd;
                    let tri = self.faces[hit.face as usize];
                    for (i, &vi) in tri.iter().enumerate() {
                        add_to(&mut acc.world, vi as usize, scale3(hit.ng, k * hit.bary[i]));
                    }
                }
            }
            area_k += 1;
        }
    }

    /// Where primary-edge sample `j` falls (module docs), with its counter (the side
    /// evaluations' area-light samples); `None` behind the near plane.
    pub(super) fn primary_edge_point(
        &self,
        j: usize,
        edges: &Edges,
    ) -> Option<(EdgePoint, Counter)> {
        let mut ctr = Counter::new(self.s.seed, Stream::PrimaryEdge, j as u64);
        let (e, pe) = edges.primary.sample(ctr.uniform());
        // Uniform on the edge's part in front of the near plane (density 1 / (s1 - s0)).
        let [s0, s1] = edges.primary_part[e as usize];
        let s = s0 + ctr.uniform() * (s1 - s0);
        let edge = edges.list[e as usize];
        let (ca, cb) = (self.clip[edge.v[0] as usize], self.clip[edge.v[1] as usize]);
        let c: [f64; 4] = std::array::from_fn(|k| ca[k] + s * (cb[k] - ca[k]));
        if c[3] <= self.s.near {
            return None;
        }
        let (u, dpi) = self.project(c);
        let dc: [f64; 4] = std::array::from_fn(|k| cb[k] - ca[k]);
        let a = [dot4(dpi[0], dc), dot4(dpi[1], dc)];
        let point = EdgePoint {
            v: edge.v,
            s,
            u,
            a,
            dpi,
            weight: (s1 - s0) / (self.s.primary_edge_samples as f64 * pe),
        };
        Some((point, ctr))
    }

    /// Where shadow-edge sample `j` of a point or directional light falls in the image
    /// (module docs), with its counter; `None` when it casts no visible shadow edge.
    pub(super) fn shadow_edge_point(
        &self,
        lights: &LightSet<'_>,
        j: usize,
        edges: &Edges,
    ) -> Option<(ShadowEdgePoint, Counter)> {
        let bvh = self.shadow.as_ref()?;
        let mut ctr = Counter::new(self.s.seed, Stream::ShadowEdge, j as u64);
        let (pick, pe) = edges.shadow.sample(ctr.uniform());
        let s = ctr.uniform();
        let (li, e) = edges.shadow_items[pick as usize];
        let o = lights.offsets[li];
        let point = self.s.lights[li] == LightKind::Point;
        let edge = edges.list[e as usize];
        let (pa, pb) = (
            self.world[edge.v[0] as usize],
            self.world[edge.v[1] as usize],
        );
        let dp = sub3(pb, pa);
        let p = add3(pa, scale3(dp, s));
        let lrow = self.light_rows[o];
        let (origin, dir) = if point {
            (lrow, sub3(p, lrow))
        } else {
            (p, lrow)
        };
        if dot3(dir, dir) == 0.0 {
            return None;
        }
        // The receiver: the first surface beyond the edge point, away from the light.
        let h = bvh.closest(&Ray::new(p, dir), 1e-9, f64::INFINITY)?;
        if edge.faces.contains(&h.face) {
            return None;
        }
        let tri = self.faces[h.face as usize];
        let r = tri.map(|i| self.world[i as usize]);
        let ph = plane_hit(origin, dir, r)?;
        let beta = ph.beta;
        let cl = tri.map(|i| self.clip[i as usize]);
        let cy: [f64; 4] = std::array::from_fn(|k| (0..3).map(|i| beta[i] * cl[i][k]).sum());
        if cy[3] <= self.s.near {
            return None;
        }
        let (u, dpi) = self.project(cy);
        // d u / d beta_k (k = 1, 2), then d u / d (ray and triangle motion).
        let e1: [f64; 4] = std::array::from_fn(|k| cl[1][k] - cl[0][k]);
        let e2: [f64; 4] = std::array::from_fn(|k| cl[2][k] - cl[0][k]);
        let du_db = [
            [dot4(dpi[0], e1), dot4(dpi[1], e1)],
            [dot4(dpi[0], e2), dot4(dpi[1], e2)],
        ];
        let jw: [V3; 2] = std::array::from_fn(|row| {
            add3(
                scale3(ph.j[0], du_db[0][row]),
                scale3(ph.j[1], du_db[1][row]),
            )
        });
        let t = ph.t;
        let coef_p = if point { t } else { 1.0 };
        let a = [coef_p * dot3(jw[0], dp), coef_p * dot3(jw[1], dp)];
        let sp = ShadowEdgePoint {
            row: o,
            point,
            edge: edge.v,
            s,
            t,
            receiver: tri,
            beta,
            u,
            a,
            jw,
            dpi,
            weight: 1.0 / (self.s.shadow_edge_samples as f64 * pe),
        };
        Some((sp, ctr))
    }
}

/// A shadow-edge sample: the point `v0 + s (v1 - v0)` of occluder edge `edge`, whose ray from
/// the light (rows from `row`; `point` or directional) meets the receiver triangle at
/// barycentrics `beta` (ray parameter `t`), seen at image point `u`; `a` is the image tangent
/// of the shadow edge there, `jw` the rows of `d u / d (world motion)` through the receiver
/// plane, `dpi` those of `d u / d clip`; `weight` is `1 / (N p)`.
#[derive(Clone, Copy, Debug)]
pub(super) struct ShadowEdgePoint {
    row: usize,
    point: bool,
    edge: [u32; 2],
    s: f64,
    t: f64,
    receiver: [u32; 3],
    beta: V3,
    pub u: [f64; 2],
    pub a: [f64; 2],
    jw: [V3; 2],
    dpi: [[f64; 4]; 2],
    weight: f64,
}

/// The gradients of one shadow-edge sample: a light row, five world positions (the edge's
/// two vertices, the receiver's three) and the receiver's three clip positions.
pub(super) struct ShadowEdgeGrads {
    pub row: (usize, V3),
    pub world: [(u32, V3); 5],
    pub clip: [(u32, [f64; 4]); 3],
}

impl ShadowEdgePoint {
    /// The gradients for a two-sided difference whose product with the output gradient is
    /// `g_delta` (the difference times the normal velocity of the shadow edge's image, Li et
    /// al. 2018 eq. 7, as a function of the occluder edge, the light, the receiver and the
    /// camera).
    pub fn grads(&self, g_delta: f64) -> ShadowEdgeGrads {
        let scal = g_delta * self.weight;
        let (a, jw, dpi) = (self.a, self.jw, self.dpi);
        let z = scale3(sub3(scale3(jw[1], a[0]), scale3(jw[0], a[1])), scal);
        let z4: [f64; 4] = std::array::from_fn(|k| scal * (a[0] * dpi[1][k] - a[1] * dpi[0][k]));
        let (t, s) = (self.t, self.s);
        let coef_p = if self.point { t } else { 1.0 };
        let row = scale3(z, if self.point { 1.0 - t } else { t });
        let [r0, r1, r2] = self.receiver;
        let b = self.beta;
        ShadowEdgeGrads {
            row: (self.row, row),
            world: [
                (self.edge[0], scale3(z, coef_p * (1.0 - s))),
                (self.edge[1], scale3(z, coef_p * s)),
                (r0, scale3(z, -b[0])),
                (r1, scale3(z, -b[1])),
                (r2, scale3(z, -b[2])),
            ],
            clip: [
                (r0, z4.map(|x| x * b[0])),
                (r1, z4.map(|x| x * b[1])),
                (r2, z4.map(|x| x * b[2])),
            ],
        }
    }
}

/// The image points `u -+ eps n` on the two sides of an edge through `u` with image tangent
/// `a` (`n = perp(a) / |a|`), minus side first; `None` for a degenerate tangent.
pub(super) fn side_points(u: [f64; 2], a: [f64; 2]) -> Option<[[f64; 2]; 2]> {
    let len = (a[0] * a[0] + a[1] * a[1]).sqrt();
    if !(len > 0.0 && len.is_finite()) {
        return None;
    }
    let n = [-a[1] / len * SIDE_EPS_PX, a[0] / len * SIDE_EPS_PX];
    Some([[u[0] - n[0], u[1] - n[1]], [u[0] + n[0], u[1] + n[1]]])
}

/// A primary-edge sample: the point `v0 + s (v1 - v0)` of the edge between vertices `v`, seen
/// at image point `u` with image tangent `a` and `d u / d clip` rows `dpi`; `weight` is the
/// estimator's `1 / (N p(edge) p(s))`.
#[derive(Clone, Copy, Debug)]
pub(super) struct EdgePoint {
    pub v: [u32; 2],
    pub s: f64,
    pub u: [f64; 2],
    pub a: [f64; 2],
    pub dpi: [[f64; 4]; 2],
    pub weight: f64,
}

impl EdgePoint {
    /// The gradients of the clip positions of `v[0]` and `v[1]` for a two-sided difference
    /// whose product with the output gradient is `g_delta` (Li et al. 2018, eq. 7: the
    /// difference times the normal velocity `cross(a, d u / d theta)`, in pixel units).
    pub fn clip_grads(&self, g_delta: f64) -> [[f64; 4]; 2] {
        let scal = g_delta * self.weight;
        if scal == 0.0 {
            return [[0.0; 4]; 2];
        }
        let (a, dpi) = (self.a, self.dpi);
        let z4: [f64; 4] = std::array::from_fn(|k| scal * (a[0] * dpi[1][k] - a[1] * dpi[0][k]));
        [z4.map(|x| x * (1.0 - self.s)), z4.map(|x| x * self.s)]
    }
}

/// The part `[s0, s1]` of the clip-space segment from `a` to `b` in front of the near plane
/// (`w > near`); `None` when no part is.
fn near_part(a: [f64; 4], b: [f64; 4], near: f64) -> Option<[f64; 2]> {
    let (wa, wb) = (a[3] - near, b[3] - near);
    match (wa > 0.0, wb > 0.0) {
        (true, true) => Some([0.0, 1.0]),
        (false, false) => None,
        (true, false) => Some([0.0, wa / (wa - wb)]),
        (false, true) => Some([wa / (wa - wb), 1.0]),
    }
}

fn dot4(a: [f64; 4], b: [f64; 4]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
}

/// Gradient of the vertices `q` of a triangle hit by a ray along `d` at barycentrics `b`,
/// given the gradient `gb` of the barycentrics (module docs of [`super`]).
pub(crate) fn bary_vjp(q: [V3; 3], d: V3, b: V3, gb: V3) -> [V3; 3] {
    let e1 = sub3(q[1], q[0]);
    let e2 = sub3(q[2], q[0]);
    let n = cross3(e1, e2);
    let nn = dot3(n, n);
    let nd = dot3(n, d);
    if nn == 0.0 || nd == 0.0 {
        return [[0.0; 3]; 3];
    }
    let a = scale3(cross3(e2, n), 1.0 / nn);
    let bb = scale3(cross3(n, e1), 1.0 / nn);
    let g = add3(scale3(a, gb[1] - gb[0]), scale3(bb, gb[2] - gb[0]));
    let h = dot3(g, d) / nd;
    let w = sub3(scale3(n, h), g);
    [scale3(w, b[0]), scale3(w, b[1]), scale3(w, b[2])]
}

/// The edge tables of one backward.
pub(super) struct Edges {
    list: Vec<Edge>,
    /// Silhouette and boundary edges seen from the camera, by the projected length (pixels)
    /// of their part in front of the near plane.
    pub(super) primary: Cdf,
    /// That part `[s0, s1]` of each edge (edge points `v0 + s (v1 - v0)`).
    primary_part: Vec<[f64; 2]>,
    /// (light, edge) pairs of point and directional lights, silhouettes seen from the light,
    /// by world length; `shadow` samples indices into `shadow_items`.
    pub(super) shadow: Cdf,
    shadow_items: Vec<(usize, u32)>,
    /// Per area light, every edge by world length, times [`AREA_EDGE_BOOST`] where
    /// [`casts_shadow`] (the silhouette test is per shading point).
    area: Vec<Cdf>,
}

/// Weight factor of the edges that [`casts_shadow`] finds casting a shadow from an area
/// light. A defensive mixture (every edge keeps a positive weight, so the estimator stays
/// unbiased; only its variance depends on the test): the ground plane's own boundary edges,
/// long and never between a receiver and the light, no longer take most of the samples.
const AREA_EDGE_BOOST: f64 = 16.0;

/// Whether the ray from the centre or a corner of the area light `quad` (corner, edge_u,
/// edge_v) through the edge point `p` travels on to a surface other than the edge's faces:
/// the edge then casts a shadow edge somewhere (a heuristic for importance only).
fn casts_shadow(bvh: &Bvh, e: &Edge, p: V3, quad: &[V3]) -> bool {
    let n = cross3(quad[1], quad[2]);
    [[0.5, 0.5], [0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
        .iter()
        .any(|ab| {
            let l = add3(
                quad[0],
                add3(scale3(quad[1], ab[0]), scale3(quad[2], ab[1])),
            );
            let d = sub3(p, l);
            dot3(n, d) > 0.0
                && bvh
                    .closest(&Ray::new(p, d), 1e-9, f64::INFINITY)
                    .is_some_and(|h| !e.faces.contains(&h.face))
        })
}

impl Edges {
    pub(super) fn new(sc: &Scene<'_>) -> Self {
        let list = mesh_edges(&sc.world, sc.faces);
        let near = sc.s.near;
        let mut primary_part = vec![[0.0; 2]; list.len()];
        let primary = Cdf::new(list.iter().enumerate().map(|(i, e)| {
            let (ca, cb) = (sc.clip[e.v[0] as usize], sc.clip[e.v[1] as usize]);
            let part = near_part(ca, cb, near);
            let Some([s0, s1]) =
                part.filter(|_| is_silhouette(e, &sc.q, sc.faces, Viewer::At([0.0; 3])))
            else {
                return (i as u32, 0.0);
            };
            primary_part[i] = [s0, s1];
            let at = |s: f64| std::array::from_fn(|k| ca[k] + s * (cb[k] - ca[k]));
            let (ua, ub) = (sc.project(at(s0)).0, sc.project(at(s1)).0);
            (
                i as u32,
                ((ua[0] - ub[0]).powi(2) + (ua[1] - ub[1]).powi(2)).sqrt(),
            )
        }));
        let lights = sc.lights();
        let mut shadow_items = Vec::new();
        let mut weights = Vec::new();
        if sc.shadow.is_some() {
            for (li, kind) in sc.s.lights.iter().enumerate() {
                let o = lights.offsets[li];
                let viewer = match kind {
                    LightKind::Point => Viewer::At(sc.light_rows[o]),
                    LightKind::Directional => Viewer::Along(sc.light_rows[o]),
                    _ => continue,
                };
                for (i, e) in list.iter().enumerate() {
                    if is_silhouette(e, &sc.world, sc.faces, viewer) {
                        let d = sub3(sc.world[e.v[1] as usize], sc.world[e.v[0] as usize]);
                        weights.push((shadow_items.len() as u32, dot3(d, d).sqrt()));
                        shadow_items.push((li, i as u32));
                    }
                }
            }
        }
        let shadow = Cdf::new(weights.into_iter());
        let mut area = Vec::new();
        if let Some(bvh) = &sc.shadow {
            for (li, kind) in sc.s.lights.iter().enumerate() {
                if *kind == LightKind::Area {
                    let quad = &sc.light_rows[lights.offsets[li]..lights.offsets[li] + 3];
                    area.push(Cdf::new(
                        list.par_iter()
                            .enumerate()
                            .map(|(i, e)| {
                                let (a, b) = (sc.world[e.v[0] as usize], sc.world[e.v[1] as usize]);
                                let d = sub3(b, a);
                                let w = if casts_shadow(bvh, e, add3(a, scale3(d, 0.5)), quad) {
                                    AREA_EDGE_BOOST
                                } else {
                                    1.0
                                };
                                (i as u32, w * dot3(d, d).sqrt())
                            })
                            .collect::<Vec<_>>()
                            .into_iter(),
                    ));
                }
            }
        }
        Edges {
            list,
            primary,
            primary_part,
            shadow,
            shadow_items,
            area,
        }
    }
}

/// Fixed chunks of work (rows, edge samples): as many as the accumulators' memory allows, at
/// most 32; the count depends on the sizes only.
fn chunk_count(height: usize, v: usize, n_rows: usize) -> usize {
    let per = 13 * v + 3 * n_rows + 1;
    ((1usize << 23) / per).clamp(1, 32).min(height.max(1))
}

impl<T: Real> Op<T> for RaytraceOp {
    fn name(&self) -> &'static str {
        "raytrace"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let sc = Scene::new(self, inputs);
        let (w, h, spp) = (self.s.width, self.s.height, self.s.spp);
        let lights = sc.lights();
        let mut img = vec![T::zero(); h * w * 4];
        img.par_chunks_mut(w * 4).enumerate().for_each_init(
            || vec![[0.0; 4]; w],
            |sums, (r, row)| {
                sc.row_sums(&lights, r, sums);
                for (px, sum) in row.chunks_exact_mut(4).zip(sums.iter()) {
                    for ch in 0..4 {
                        px[ch] = T::from_f64c(sum[ch] / spp as f64);
                    }
                }
            },
        );
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[h, w, 4]), img).expect("h x w x 4")
        ])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let need = ctx.needs_grad;
        if !need.iter().any(|&b| b) {
            return Ok(vec![None; 5]);
        }
        let sc = Scene::new(self, ctx.inputs);
        let gimg: Vec<[f64; 4]> = rows(ctx.grad_outputs[0]);
        let edges = Edges::new(&sc);
        let lights = sc.lights();
        let (w, h, spp) = (self.s.width, self.s.height, self.s.spp);
        let v = sc.q.len();
        let n_rows = sc.light_rows.len();
        let chunks = chunk_count(h, v, n_rows);
        let rows_per = h.div_ceil(chunks);
        let block = |n: usize, c: usize| {
            let per = n.div_ceil(chunks);
            (c * per).min(n)..((c + 1) * per).min(n)
        };
        let area_edges = edges.area.iter().any(|c| !c.is_empty());
        let accs: Vec<Acc> = (0..chunks)
            .into_par_iter()
            .map(|c| {
                let mut acc = Acc::new(v, n_rows, need);
                for r in (c * rows_per).min(h)..((c + 1) * rows_per).min(h) {
                    for col in 0..w {
                        let pix = r * w + col;
                        let g = gimg[pix].map(|x| x / spp as f64);
                        if g.iter().all(|&x| x == 0.0) {
                            continue;
                        }
                        for k in 0..spp {
                            let index = (pix * spp + k) as u64;
                            let (u, ctr) = sc.sample(pix, k);
                            let ae = area_edges.then_some((&edges, index));
                            sc.radiance(&lights, u, ctr, Some((g, &mut acc)), ae);
                        }
                    }
                }
                if !edges.primary.is_empty() {
                    for j in block(self.s.primary_edge_samples, c) {
                        let Some((ep, ctr)) = sc.primary_edge_point(j, &edges) else {
                            continue;
                        };
                        if let Some(gd) = sc.across_edge(&lights, ep.u, ep.a, ctr, &gimg) {
                            acc.primary_edge(&ep, gd);
                        }
                    }
                }
                if !edges.shadow.is_empty() {
                    for j in block(self.s.shadow_edge_samples, c) {
                        let Some((sp, ctr)) = sc.shadow_edge_point(&lights, j, &edges) else {
                            continue;
                        };
                        if let Some(gd) = sc.across_edge(&lights, sp.u, sp.a, ctr, &gimg) {
                            acc.shadow_edge(&sp, gd);
                        }
                    }
                }
                acc
            })
            .collect();
        fn reduce<T: Real, const N: usize>(
            accs: &[Acc],
            get: impl Fn(&Acc) -> &Vec<[f64; N]> + Sync,
            shape: [usize; 2],
        ) -> Tensor<T> {
            let len = get(&accs[0]).len();
            let out: Vec<T> = (0..len)
                .into_par_iter()
                .flat_map_iter(|i| {
                    let mut s = [0.0; N];
                    for a in accs {
                        for k in 0..N {
                            s[k] += get(a)[i][k];
                        }
                    }
                    s.into_iter().map(T::from_f64c)
                })
                .collect();
            ArrayD::from_shape_vec(IxDyn(&shape), out).expect("shape")
        }
        Ok(vec![
            need[0].then(|| reduce::<T, 4>(&accs, |a| &a.clip, [v, 4])),
            need[1].then(|| reduce::<T, 3>(&accs, |a| &a.world, [v, 3])),
            need[2].then(|| reduce::<T, 3>(&accs, |a| &a.normals, [v, 3])),
            need[3].then(|| reduce::<T, 3>(&accs, |a| &a.albedo, [v, 3])),
            need[4].then(|| reduce::<T, 3>(&accs, |a| &a.rows, [n_rows, 3])),
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raytrace::intersect::Ray;

    #[test]
    fn bary_vjp_matches_finite_differences() {
        let q = [[0.1, -0.2, 2.0], [1.2, 0.1, 2.3], [-0.1, 0.9, 2.2]];
        let d = [0.15, 0.2, 1.0];
        let gb = [0.3, -1.2, 0.7];
        let f = |q: [V3; 3]| {
            let (_, b) = Ray::new([0.0; 3], d).intersect(&q, 0.0, 10.0).unwrap();
            dot3(b, gb)
        };
        let (_, b) = Ray::new([0.0; 3], d).intersect(&q, 0.0, 10.0).unwrap();
        let g = bary_vjp(q, d, b, gb);
        let h = 1e-6;
        for i in 0..3 {
            for k in 0..3 {
                let mut a = q;
                a[i][k] += h;
                let mut c = q;
                c[i][k] -= h;
                let num = (f(a) - f(c)) / (2.0 * h);
                assert!((num - g[i][k]).abs() < 1e-7, "{i} {k}: {num} {}", g[i][k]);
            }
        }
    }
}
