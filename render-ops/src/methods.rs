//! The method registry: what each of the eight raster methods and the ray tracer is (its
//! [`MethodInfo`]: name, [`Kind`], which gradients are exact, its paper),
//! the settings every method shares ([`ViewSettings`]) and those of one method
//! ([`MethodSettings`], from which each op's own settings struct is built), and the two entry
//! points every caller goes through:
//!
//! * [`render_vertex_colors`]: per-vertex colours `[V, C]` (Gouraud shading), the fused fast
//!   path of each method (one op, or the direct render for `hard`);
//! * [`render_fragments`]: any per-fragment shader (interpolated attributes, textures,
//!   lighting, a user's closure) composed with the method's visibility stage: rasterize (for
//!   `tf_mesh` with its silhouette band of extrapolated fragments), the shader, the hard blend,
//!   then the method's boundary op; for `softras` the soft stage's fragments within the
//!   cut-off ([`soft::soft_fragments`]), the shader, and SoftRas's blend; for `dibr` the hard
//!   image with DIB-R's soft alpha.
//!
//! The scene pipeline ([`crate::pipeline`]), `models::fit` and `tapestry bench` dispatch on the
//! method only here. To add a method: a [`Method`] variant (scene.rs), its [`MethodInfo`] in
//! [`Method::info`], and its arms in the two entry points.
//!
//! Every method composes with any shader (a new one must give both entry points). The ray
//! tracer composes through its fragment stages ([`crate::raytrace::stage`]: visibility, light
//! visibility by shadow rays with [`render_fragments_lit`], and the edge terms); its fused op
//! is the built-in shading's path for vertex colours.

use std::sync::Arc;

use autodiff::{Real, Var};

use crate::analytic::analytic_fragments;
use crate::approx::{self, ApproxSettings};
use crate::blend::{blend_hard, blend_weighted};
use crate::boundary::{self, BoundarySettings};
use crate::error::RenderError;
use crate::interpolate::interpolate;
use crate::raster::RasterSettings;
use crate::rasterize::{rasterize, render_attributes, Rasterized};
use crate::raytrace::{blend_traced, raytrace, raytrace_fragments, RaytraceSettings, ShadowInputs};
use crate::scene::{Method, Raster};
use crate::soft::{
    self, Coverage, DibrSettings, SoftBlendSettings, SoftSettings, SoftStageSettings,
};

/// How a method decides visibility and where its position gradients come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// The z-buffer image; gradients through the barycentrics of covered pixels only.
    Hard,
    /// The hard image (or DEODR's overdrawn one) plus a boundary term at silhouette and
    /// occlusion edges.
    Boundary,
    /// Probabilistic coverage of every face within a cut-off distance.
    Soft,
    /// Monte Carlo ray tracing of the box-filtered image with shadows; boundary terms by edge
    /// sampling.
    RayTraced,
    /// The exact visible area of every face in each pixel (box filter).
    Area,
}

/// Which gradients of a method are those of its own forward (exact), and which approximate
/// the box-filtered image's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Exactness {
    /// Gradients with respect to colours, texels and lights.
    pub appearance: bool,
    /// Position gradients of the forward the method computes (for `hard`, `deodr`,
    /// `softras` and `dibr` the derivative of their image; for the others a surrogate).
    pub positions: bool,
    /// Whether silhouette vertices get a gradient at all.
    pub silhouette: bool,
}

/// What the registry knows about a method.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MethodInfo {
    /// The method.
    pub method: Method,
    /// The scene JSON name.
    pub name: &'static str,
    /// Visibility kind.
    pub kind: Kind,
    /// Which gradients are exact.
    pub exact: Exactness,
    /// The paper.
    pub paper: &'static str,
}

impl Method {
    /// The registry entry of the method.
    pub fn info(self) -> MethodInfo {
        let e = |appearance, positions, silhouette| Exactness {
            appearance,
            positions,
            silhouette,
        };
        let (kind, exact, paper) = match self {
            Method::Hard => (Kind::Hard, e(true, true, false), "z-buffer rasterization"),
            Method::TfMesh => (
                Kind::Boundary,
                e(true, false, true),
                "Genova et al., CVPR 2018 (TF Mesh Renderer)",
            ),
            Method::OpenDr => (
                Kind::Boundary,
                e(true, false, true),
                "Loper and Black, ECCV 2014 (OpenDR)",
            ),
            Method::Nmr => (
                Kind::Boundary,
                e(true, false, true),
                "Kato et al., CVPR 2018 (Neural 3D Mesh Renderer)",
            ),
            Method::SoftRas => (
                Kind::Soft,
                e(true, true, true),
                "Liu et al., ICCV 2019 (Soft Rasterizer)",
            ),
            Method::Dibr => (
                Kind::Soft,
                e(true, true, true),
                "Chen et al., NeurIPS 2019 (DIB-R)",
            ),
            Method::Deodr => (
                Kind::Boundary,
                e(true, true, true),
                "de La Gorce et al., TPAMI 2011 (DEODR)",
            ),
            Method::Raytrace => (
                Kind::RayTraced,
                e(true, true, true),
                "Li et al., SIGGRAPH Asia 2018 (edge sampling, redner)",
            ),
            Method::Analytic => (
                Kind::Area,
                e(true, true, true),
                "Catmull, SIGGRAPH 1978 (analytic area sampling), differentiated",
            ),
        };
        MethodInfo {
            method: self,
            name: self.name(),
            kind,
            exact,
            paper,
        }
    }
}

/// The settings every method shares: image size, background, culling and interpolation.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Background value per colour channel (empty: zeros).
    pub background: Vec<f64>,
    /// Drop faces that are clockwise in NDC (default `false`; SoftRas ignores it).
    pub cull_backfaces: bool,
    /// Perspective-correct interpolation (default `true`).
    pub perspective_correct: bool,
}

impl ViewSettings {
    /// Defaults for a `width x height` image: zero background, no culling, perspective-correct.
    pub fn new(width: usize, height: usize) -> Self {
        ViewSettings {
            width,
            height,
            background: Vec::new(),
            cull_backfaces: false,
            perspective_correct: true,
        }
    }

    /// The background as `C` scalars (zeros past its end).
    pub fn background_of<T: Real>(&self, c: usize) -> Vec<T> {
        (0..c)
            .map(|ch| T::from_f64c(self.background.get(ch).copied().unwrap_or(0.0)))
            .collect()
    }
}

/// One method with all its settings: the view, and the parameters each op reads (defaults
/// as in docs/CONVENTIONS.md). The op settings structs ([`RasterSettings`],
/// [`ApproxSettings`], [`BoundarySettings`], [`SoftSettings`], [`DibrSettings`]) are built
/// from it by the methods below, so the shared fields are set in one place.
#[derive(Clone, Debug, PartialEq)]
pub struct MethodSettings {
    /// The method.
    pub method: Method,
    /// Size, background, culling, interpolation.
    pub view: ViewSettings,
    /// Fragments kept per pixel by the hard rasterizer (`hard`; the others draw the nearest).
    pub faces_per_pixel: usize,
    /// Fragments the soft stage keeps per pixel, nearest first (`None`: every face within the
    /// cut-off; the scene's `faces_per_pixel` for `softras` and `dibr`).
    pub soft_faces_per_pixel: Option<usize>,
    /// Screen-space barycentric derivatives (for texture filtering).
    pub barycentric_derivatives: bool,
    /// SoftRas sigma (squared NDC units).
    pub sigma: f64,
    /// SoftRas gamma (`z01` units).
    pub gamma: f64,
    /// SoftRas background term.
    pub eps: f64,
    /// Coverage below which softras and dibr ignore a face.
    pub threshold: f64,
    /// DIB-R delta (squared NDC units).
    pub delta: f64,
    /// DEODR's overdraw ramp width in pixels.
    pub overdraw_px: f64,
    /// Near plane distance (SoftRas's `z01`).
    pub near: f64,
    /// Far plane distance (SoftRas's `z01`).
    pub far: f64,
    /// `raytrace`: samples per pixel.
    pub spp: usize,
    /// `raytrace`: seed.
    pub seed: u64,
    /// `raytrace`: primary edge samples (`None`: one per pixel).
    pub edge_samples: Option<usize>,
    /// `raytrace`: shadow-edge samples (`None`: one per pixel).
    pub shadow_edge_samples: Option<usize>,
    /// `raytrace`: area-light edge samples per pixel sample.
    pub area_edge_samples: usize,
}

impl MethodSettings {
    /// `method` with its ops' defaults for a `width x height` image (near 0.1, far 100;
    /// SoftRas interpolates in screen space, as SoftRas does, the others perspective-correctly).
    pub fn new(method: Method, width: usize, height: usize) -> Self {
        let r = Raster {
            perspective_correct: method != Method::SoftRas,
            ..Raster::with_method(method)
        };
        Self::from_raster(&r, ViewSettings::new(width, height), 0.1, 100.0)
    }

    /// The settings of a scene's `raster` block over `view` (its `cull_backfaces` and
    /// `perspective_correct` are the raster block's) with the camera's clip planes.
    pub fn from_raster(r: &Raster, view: ViewSettings, near: f64, far: f64) -> Self {
        MethodSettings {
            method: r.method,
            view: ViewSettings {
                cull_backfaces: r.cull_backfaces,
                perspective_correct: r.perspective_correct,
                ..view
            },
            faces_per_pixel: r.effective_faces_per_pixel().unwrap_or(1) as usize,
            soft_faces_per_pixel: r.faces_per_pixel.map(|k| k as usize),
            barycentric_derivatives: false,
            sigma: r.sigma,
            gamma: r.gamma,
            eps: r.eps,
            threshold: r.threshold,
            delta: r.delta,
            overdraw_px: r.overdraw_px,
            near,
            far,
            spp: r.spp as usize,
            seed: r.seed,
            edge_samples: r.edge_samples.map(|n| n as usize),
            shadow_edge_samples: r.shadow_edge_samples.map(|n| n as usize),
            area_edge_samples: r.area_edge_samples as usize,
        }
    }

    /// The ray tracer's settings (unlit, no lights: the caller sets the eye, reflection and
    /// lights for a lit scene).
    pub fn raytrace(&self) -> RaytraceSettings {
        let v = &self.view;
        let bg = v.background_of::<f64>(3);
        let px = v.width * v.height;
        RaytraceSettings {
            spp: self.spp,
            seed: self.seed,
            background: [bg[0], bg[1], bg[2]],
            near: self.near,
            far: self.far,
            primary_edge_samples: self.edge_samples.unwrap_or(px),
            shadow_edge_samples: self.shadow_edge_samples.unwrap_or(px),
            area_edge_samples: self.area_edge_samples,
            ..RaytraceSettings::new(v.width, v.height)
        }
    }

    /// The hard rasterizer's settings.
    pub fn raster(&self) -> RasterSettings {
        let v = &self.view;
        RasterSettings {
            faces_per_pixel: self.faces_per_pixel,
            cull_backfaces: v.cull_backfaces,
            perspective_correct: v.perspective_correct,
            barycentric_derivatives: self.barycentric_derivatives,
            ..RasterSettings::new(v.width, v.height)
        }
    }

    /// The settings of the fused ops of [`crate::approx`].
    pub fn approx(&self) -> ApproxSettings {
        let v = &self.view;
        ApproxSettings {
            background: v.background.clone(),
            perspective_correct: v.perspective_correct,
            cull_backfaces: v.cull_backfaces,
            overdraw_px: self.overdraw_px,
            ..ApproxSettings::new(v.width, v.height)
        }
    }

    /// The settings of the boundary ops of [`crate::boundary`].
    pub fn boundary(&self) -> BoundarySettings {
        BoundarySettings {
            overdraw_px: self.overdraw_px,
        }
    }

    /// SoftRas's settings (SoftRas does not cull).
    pub fn softras(&self) -> SoftSettings {
        let v = &self.view;
        SoftSettings {
            sigma: self.sigma,
            gamma: self.gamma,
            eps: self.eps,
            threshold: self.threshold,
            background: v.background.clone(),
            perspective_correct: v.perspective_correct,
            ..SoftSettings::new(v.width, v.height, self.near, self.far)
        }
    }

    /// The soft stage's settings for `softras` (sigmoid coverage, no culling, as SoftRas) or
    /// `dibr` (exponential coverage, culling as set).
    pub fn soft_stage(&self) -> SoftStageSettings {
        let v = &self.view;
        let softras = self.method == Method::SoftRas;
        let coverage = if softras {
            Coverage::Sigmoid { sigma: self.sigma }
        } else {
            Coverage::Exp { delta: self.delta }
        };
        SoftStageSettings {
            threshold: self.threshold,
            max_faces: self.soft_faces_per_pixel,
            perspective_correct: v.perspective_correct,
            cull_backfaces: !softras && v.cull_backfaces,
            barycentric_derivatives: self.barycentric_derivatives,
            ..SoftStageSettings::new(v.width, v.height, coverage)
        }
    }

    /// SoftRas's blend over the soft stage's fragments.
    pub fn soft_blend(&self) -> SoftBlendSettings {
        SoftBlendSettings {
            gamma: self.gamma,
            eps: self.eps,
            background: self.view.background.clone(),
            ..SoftBlendSettings::new(self.near, self.far)
        }
    }

    /// DIB-R's settings.
    pub fn dibr(&self) -> DibrSettings {
        let v = &self.view;
        DibrSettings {
            delta: self.delta,
            threshold: self.threshold,
            background: v.background.clone(),
            perspective_correct: v.perspective_correct,
            cull_backfaces: v.cull_backfaces,
            ..DibrSettings::new(v.width, v.height)
        }
    }
}

/// Renders per-vertex colours `colors` `[V, C]` over `faces` from clip positions `[V, 4]`
/// with the method of `s`: an image `[H, W, C + 1]` (colours over the background, then the
/// coverage or soft alpha). The fused fast path of each method: `hard` draws in one pass when
/// nothing needs a gradient ([`render_attributes`]); `tf_mesh`, `opendr`, `nmr`, `deodr` are
/// the ops of [`crate::approx`]; `softras` is [`soft::softras`]; `dibr` the hard render with
/// DIB-R's alpha ([`soft::dibr::composite`]); `analytic` is its stage
/// ([`analytic_fragments`]), the colours interpolated at each fragment's centroid and
/// [`blend_weighted`] (exact for screen-space interpolation, `perspective_correct = false`).
///
/// # Errors
/// The ops' errors (shapes, settings, background length).
pub fn render_vertex_colors<'t, T: Real>(
    clip: Var<'t, T>,
    colors: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    s: &MethodSettings,
) -> Result<Var<'t, T>, RenderError> {
    let c = colors.shape().get(1).copied().unwrap_or(0);
    match s.method {
        Method::Hard => {
            render_attributes(clip, colors, faces, &s.raster(), &s.view.background_of(c))
        }
        Method::TfMesh => approx::tf_mesh(clip, colors, faces, &s.approx()),
        Method::OpenDr => approx::opendr(clip, colors, faces, &s.approx()),
        Method::Nmr => approx::nmr(clip, colors, faces, &s.approx()),
        Method::Deodr => approx::deodr(clip, colors, faces, &s.approx()),
        Method::SoftRas => soft::softras(clip, colors, faces, &s.softras()),
        Method::Analytic => {
            let a = analytic_fragments(clip, faces, &s.raster())?;
            let col = interpolate(colors, &a.raster)?;
            blend_weighted(col, a.weight, &a.raster.fragments, &s.view.background_of(c))
        }
        Method::Dibr => {
            let hard = render_attributes(
                clip,
                colors,
                faces.clone(),
                &s.raster(),
                &s.view.background_of(c),
            )?;
            let alpha = soft::dibr_alpha(clip, faces, &s.dibr())?;
            soft::dibr::composite(hard, alpha)
        }
        Method::Raytrace => {
            // Unlit: the world positions only feed shadows and area lights (none here).
            let t = clip.tape();
            let v = clip.shape().first().copied().unwrap_or(0);
            let world = clip.slice(1, 0, 3);
            let normals = t.constant(ndarray::ArrayD::zeros(ndarray::IxDyn(&[v, 3])));
            let lights = t.constant(ndarray::ArrayD::zeros(ndarray::IxDyn(&[0, 3])));
            raytrace(clip, world, normals, colors, lights, faces, &s.raytrace())
        }
    }
}

/// A per-fragment shader: the colours `[N, C]` of the fragments of a rasterization (any tape
/// code: [`crate::interpolate`], [`crate::texture`], [`crate::shade`], a user's closure).
/// `tf_mesh` calls it twice, for the hard fragments and for its silhouette band.
pub type FragmentShader<'a, 't, T> =
    dyn FnMut(&Rasterized<'t, T>) -> Result<Var<'t, T>, RenderError> + 'a;

/// Renders `faces` from clip positions `[V, 4]` with the method of `s`, shading each fragment
/// with `shader` (colours `[N, C]`; the background `s.view.background` has `C` values): an
/// image `[H, W, C + 1]`.
///
/// * `hard`: rasterize, shade, [`blend_hard`].
/// * `tf_mesh`: [`approx::tf_mesh::rasterize_extrapolated`], the shader on the hard
///   fragments and on the silhouette band, [`approx::tf_mesh::blend_band`].
/// * `opendr`, `nmr`, `deodr`: the hard image, then the method's op of [`crate::boundary`].
/// * `softras`: the soft stage ([`soft::soft_fragments`]: every face within the cut-off, or
///   the nearest K, with coverage probabilities and clipped barycentrics), the shader on those
///   fragments, and SoftRas's softmax over depth ([`soft::softras_aggregate`]).
/// * `dibr`: the hard image (the nearest covering fragment of each pixel, shaded once) with
///   DIB-R's soft silhouette ([`soft::dibr_alpha`]) as its alpha, as the fused path does.
/// * `analytic`: [`analytic_fragments`] (every visible face part of each pixel, its area and
///   its values at the area centroid), the shader on those fragments, [`blend_weighted`].
/// * `raytrace`: [`raytrace_fragments`] (one fragment per pixel sample that hits, and the
///   side points of the edge samples as a band), the shader on both, and [`blend_traced`]
///   (the box filter, with the edge terms in its backward). Lights in the shader are
///   unshadowed here; [`render_fragments_lit`] gives the fragments their visibility.
///
/// # Errors
/// The ops' and the shader's errors.
pub fn render_fragments<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    s: &MethodSettings,
    shader: &mut FragmentShader<'_, 't, T>,
) -> Result<Var<'t, T>, RenderError> {
    render_fragments_lit(clip, faces, s, None, shader)
}

/// [`render_fragments`] with the inputs of shadow rays: for `raytrace`, every fragment then
/// carries the visibility of the directional and point lights ([`Rasterized::visibility`],
/// which [`crate::shade::Surface::visibility`] takes), and the shadow boundaries' edge terms
/// reach `shadows.world` and `shadows.lights`.
///
/// # Errors
/// As [`render_fragments`]; `shadows` with a raster method (`Unsupported`: only the ray
/// tracer casts shadows).
pub fn render_fragments_lit<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    s: &MethodSettings,
    shadows: Option<ShadowInputs<'t, T>>,
    shader: &mut FragmentShader<'_, 't, T>,
) -> Result<Var<'t, T>, RenderError> {
    if shadows.is_some() && s.method != Method::Raytrace {
        return Err(RenderError::Unsupported(format!(
            "'{}' casts no shadows: shadow rays are the ray tracer's ('raytrace')",
            s.method.name()
        )));
    }
    let hard = |shader: &mut FragmentShader<'_, 't, T>| -> Result<_, RenderError> {
        let r = rasterize(clip, faces.clone(), &s.raster())?;
        let col = shader(&r)?;
        let bg = s
            .view
            .background_of(col.shape().get(1).copied().unwrap_or(0));
        let image = blend_hard(col, &r.fragments, &bg)?;
        Ok((image, r))
    };
    match s.method {
        Method::Hard => Ok(hard(shader)?.0),
        Method::TfMesh => {
            let r = approx::tf_mesh::rasterize_extrapolated(clip, faces, &s.raster())?;
            let col = shader(&r.raster)?;
            let band = shader(&r.band)?;
            let bg = s
                .view
                .background_of(col.shape().get(1).copied().unwrap_or(0));
            approx::tf_mesh::blend_band(col, band, &r, &bg)
        }
        Method::OpenDr => {
            let (image, r) = hard(shader)?;
            boundary::opendr_antialias(image, &r, clip)
        }
        Method::Nmr => {
            let (image, r) = hard(shader)?;
            boundary::nmr_antialias(image, &r, clip)
        }
        Method::Deodr => {
            let (image, r) = hard(shader)?;
            boundary::deodr_antialias(image, &r, clip, &s.boundary())
        }
        Method::Raytrace => {
            let t = raytrace_fragments(clip, faces, &s.raytrace(), shadows)?;
            let col = shader(&t.raster)?;
            let band = shader(&t.band)?;
            let bg = s
                .view
                .background_of(col.shape().get(1).copied().unwrap_or(0));
            blend_traced(col, band, &t, clip, &bg)
        }
        Method::Analytic => {
            let a = analytic_fragments(clip, faces, &s.raster())?;
            let col = shader(&a.raster)?;
            let bg = s
                .view
                .background_of(col.shape().get(1).copied().unwrap_or(0));
            blend_weighted(col, a.weight, &a.raster.fragments, &bg)
        }
        Method::SoftRas => {
            let frags = soft::soft_fragments(clip, faces, &s.soft_stage())?;
            let col = shader(&frags.raster)?;
            soft::softras_aggregate(&frags, col, &s.soft_blend())
        }
        Method::Dibr => {
            let (image, _) = hard(shader)?;
            soft::dibr::composite(image, soft::dibr_alpha(clip, faces, &s.dibr())?)
        }
    }
}
