//! The face renderer used by the fitting: model coefficients and pose to landmarks and images
//! on the tape.
//!
//! Camera: at the origin, looking down `-z` (the view matrix is the identity), OpenGL
//! perspective with focal length `focal = cot(fov_y / 2)`, `aspect = width / height`. The face
//! (model coordinates in millimetres, facing `+z`) is placed by `world = R(rotation) p +
//! translation`, so a face in front of the camera has `translation.z < 0`.
//!
//! Shading: per-vertex albedo ([`Morphable::albedo_standardized`], with the constant region
//! colours of the mouth interior and eye openings from [`Morphable::region_split`]) lit by
//! order-2 SH ([`render_ops::shade::sh::sh_shade`], CONVENTIONS) with area-weighted vertex
//! normals of the posed mesh (world = view space). Every method goes through the method
//! registry (`render_ops::methods`): methods with a composed path (all but `softras`)
//! interpolate normals and albedo per fragment and shade per fragment, composed with the
//! method's visibility stage (`render_fragments`); `softras` shades per vertex and lets its op
//! interpolate and aggregate the colours (Gouraud shading, as in SoftRas's own face-fitting
//! examples), until the composed soft stage exists. The photometric loss weights pixels by the
//! render's alpha held constant, so DIB-R's silhouette gradient (which flows through alpha only)
//! is not used: the outline is driven by the landmarks, and DIB-R's colours carry its interior
//! (hard) gradients.

use std::sync::Arc;

use autodiff::{Tape, Var};
use ndarray::{Array2, Array3, ArrayD, IxDyn};
use render_ops::error::RenderError;
use render_ops::interpolate::interpolate;
use render_ops::methods::{render_fragments, MethodSettings};
use render_ops::scene::Method;
use render_ops::shade::normals::vertex_normals;
use render_ops::shade::sh::sh_shade;
use render_ops::texture::{sample, Filter, Sampler, Wrap};
use render_ops::transform::{axis_angle_to_matrix, perspective_clip, rigid_transform};

use super::{FaceParams, FitError};
use crate::morphable::{landmark_combination, LandmarkPoint, Morphable, PointShape, RegionSplit};

/// Near plane of the fitting camera, millimetres.
pub const NEAR_MM: f64 = 50.0;
/// Far plane of the fitting camera, millimetres.
pub const FAR_MM: f64 = 2000.0;

/// Parameter variables of one evaluation (see [`FaceParams`] for the meaning).
#[derive(Clone, Copy, Debug)]
pub struct ParamVars<'t> {
    /// Axis-angle rotation `[3]`.
    pub rotation: Var<'t, f64>,
    /// Translation `[3]`, millimetres.
    pub translation: Var<'t, f64>,
    /// Focal length `[1]` (`cot(fov_y / 2)`).
    pub focal: Var<'t, f64>,
    /// Standardised identity coefficients `[K_id]`.
    pub z_id: Var<'t, f64>,
    /// Standardised expression coefficients `[K_exp]`.
    pub z_exp: Var<'t, f64>,
    /// Standardised albedo coefficients `[K_alb]`.
    pub z_albedo: Var<'t, f64>,
    /// SH coefficients `[9, 3]`.
    pub sh: Var<'t, f64>,
}

/// Settings of the face renderer.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Raster method.
    pub method: Method,
    /// Background colour.
    pub background: [f64; 3],
    /// SoftRas `sigma` (squared NDC units).
    pub sigma: f64,
    /// SoftRas `gamma` (`z01` units).
    pub gamma: f64,
    /// DIB-R `delta` (squared NDC units).
    pub delta: f64,
    /// Aspect ratio of the projection; `None`: `width / height`. A photo resized to the fit's
    /// size keeps its own aspect here, so that the fit's pixels map back to the photo's by a
    /// scale per axis.
    pub aspect: Option<f64>,
}

impl RenderOptions {
    /// Defaults for a `width x height` image: `hard`, black background, SoftRas defaults.
    pub fn new(width: usize, height: usize) -> Self {
        RenderOptions {
            width,
            height,
            method: Method::Hard,
            background: [0.0; 3],
            sigma: 1e-4,
            gamma: 1e-4,
            delta: render_ops::scene::DEFAULT_DIBR_DELTA,
            aspect: None,
        }
    }
}

/// Renders a [`Morphable`] face: holds the render topology and the settings.
pub struct FaceRenderer<'m> {
    model: &'m Morphable<f64>,
    split: RegionSplit<f64>,
    model_faces: Arc<Vec<[u32; 3]>>,
    render_faces: Arc<Vec<[u32; 3]>>,
    /// Texture coordinates of the render vertices `[V', 2]`, when the model has uvs.
    uvs: Option<Arc<ArrayD<f64>>>,
    /// The settings.
    pub options: RenderOptions,
}

impl<'m> FaceRenderer<'m> {
    /// A renderer of `model` with `options`; errors for unsupported methods or empty images.
    pub fn new(model: &'m Morphable<f64>, options: RenderOptions) -> Result<Self, FitError> {
        if options.width == 0 || options.height == 0 {
            return Err(FitError::Invalid(format!(
                "image size {}x{} is empty",
                options.width, options.height
            )));
        }
        let split = model.region_split();
        let render_faces = Arc::new(split.faces.clone());
        let uvs = model
            .uvs()
            .map(|uv| Arc::new(split.gather_plain(uv).into_dyn()));
        Ok(FaceRenderer {
            model,
            uvs,
            split,
            model_faces: Arc::new(model.faces().to_vec()),
            render_faces,
            options,
        })
    }

    /// The model.
    pub fn model(&self) -> &'m Morphable<f64> {
        self.model
    }

    /// Parameter variables on `tape` from plain parameters; `grad` says which of (pose,
    /// focal, shape, appearance) require gradients.
    pub fn vars<'t>(&self, tape: &'t Tape<f64>, p: &FaceParams, grad: Active) -> ParamVars<'t> {
        let t = p.tensors();
        ParamVars {
            rotation: tape.var(t[0].clone(), grad.pose),
            translation: tape.var(t[1].clone(), grad.pose),
            focal: tape.var(t[2].clone(), grad.focal),
            z_id: tape.var(t[3].clone(), grad.shape),
            z_exp: tape.var(t[4].clone(), grad.shape),
            z_albedo: tape.var(t[5].clone(), grad.appearance),
            sh: tape.var(t[6].clone(), grad.appearance),
        }
    }

    /// Model-space shape `[V, 3]` (millimetres).
    pub fn shape<'t>(&self, v: &ParamVars<'t>) -> Var<'t, f64> {
        self.model
            .shape_standardized(v.rotation.tape(), v.z_id, v.z_exp)
    }

    /// Posed (world = view space) vertex positions `[V, 3]`.
    pub fn posed<'t>(&self, v: &ParamVars<'t>) -> Var<'t, f64> {
        pose(self.shape(v), v)
    }

    /// Pixel positions `[N, 2]` (as [`FaceRenderer::project_px`]) of the points of a
    /// [`PointShape`] (the model at the landmark points): the landmark term without the other
    /// vertices' shape.
    pub fn project_points_px<'t>(
        &self,
        points: &PointShape<f64>,
        v: &ParamVars<'t>,
    ) -> Result<Var<'t, f64>, FitError> {
        let shape = points.shape_standardized(v.rotation.tape(), v.z_id, v.z_exp);
        self.project_rows(pose(shape, v), v.focal)
    }

    fn clip<'t>(&self, world: Var<'t, f64>, focal: Var<'t, f64>) -> Result<Var<'t, f64>, FitError> {
        let aspect = self
            .options
            .aspect
            .unwrap_or(self.options.width as f64 / self.options.height as f64);
        Ok(perspective_clip(world, focal, aspect, NEAR_MM, FAR_MM)?)
    }

    /// Pixel positions `[N, 2]` (x right, y down, origin at the image's top-left corner, pixel
    /// centres at +0.5) of landmark `points` of the posed vertices `world` (each point the
    /// weighted sum of its vertices' posed positions, then projected).
    pub fn project_px<'t>(
        &self,
        world: Var<'t, f64>,
        focal: Var<'t, f64>,
        points: &[LandmarkPoint],
    ) -> Result<Var<'t, f64>, FitError> {
        self.project_rows(landmark_combination(world, points), focal)
    }

    fn project_rows<'t>(
        &self,
        positions: Var<'t, f64>,
        focal: Var<'t, f64>,
    ) -> Result<Var<'t, f64>, FitError> {
        let c = self.clip(positions, focal)?;
        let w = c.slice(1, 3, 4);
        let (wd, ht) = (self.options.width as f64, self.options.height as f64);
        let x = (c.slice(1, 0, 1) / w + 1.0) * (0.5 * wd);
        let y = (1.0 - c.slice(1, 1, 2) / w) * (0.5 * ht);
        Ok(positions.tape().concat(&[x, y], 1))
    }

    /// The rendered image `[H, W, 4]` (RGB over the background, alpha = coverage) of posed
    /// vertices `world` with the appearance in `v`.
    pub fn image<'t>(
        &self,
        world: Var<'t, f64>,
        v: &ParamVars<'t>,
    ) -> Result<Var<'t, f64>, FitError> {
        self.shaded(world, v, None, false)
    }

    /// [`FaceRenderer::image`] with the albedo of the faces marked in `textured` (one flag
    /// per model face) sampled from an albedo texture `texels` `[S, S, 3]` in the model's uv
    /// space ([`TEXTURE_SAMPLER`]) instead of interpolated from the vertices: per-pixel
    /// albedo, shaded per pixel. Errors when the model has no uvs.
    pub fn image_textured<'t>(
        &self,
        world: Var<'t, f64>,
        v: &ParamVars<'t>,
        texels: Var<'t, f64>,
        textured: &Arc<Vec<bool>>,
    ) -> Result<Var<'t, f64>, FitError> {
        if textured.len() != self.render_faces.len() {
            return Err(FitError::Invalid(format!(
                "{} texture flags for {} faces",
                textured.len(),
                self.render_faces.len()
            )));
        }
        self.shaded(world, v, Some((texels, textured)), false)
    }

    /// The image the photometric term compares: as [`FaceRenderer::image`] when every region
    /// of the model is photometric, else `[H, W, 5]`: RGB, the photometric weight (1 where a
    /// photometric triangle is visible, 0 where another one is: [`Region::photometric`],
    /// [`RegionSplit::photo_weight`]) and coverage. A pixel's weight in the term is the
    /// product of the channels after RGB.
    ///
    /// [`Region::photometric`]: crate::morphable::Region::photometric
    pub fn photo_image<'t>(
        &self,
        world: Var<'t, f64>,
        v: &ParamVars<'t>,
    ) -> Result<Var<'t, f64>, FitError> {
        self.shaded(world, v, None, true)
    }

    fn shaded<'t>(
        &self,
        world: Var<'t, f64>,
        v: &ParamVars<'t>,
        texture: Option<(Var<'t, f64>, &Arc<Vec<bool>>)>,
        photo: bool,
    ) -> Result<Var<'t, f64>, FitError> {
        let tape = world.tape();
        let weight = match self.split.photo_weight() {
            Some(w) if photo => Some(tape.var_shared(w.clone(), false)),
            _ => None,
        };
        let normals = self.split.gather(vertex_normals(world, &self.model_faces));
        let albedo = self
            .split
            .albedo(self.model.albedo_standardized(tape, v.z_albedo));
        let uvs = match (texture.is_some(), &self.uvs) {
            (false, _) => None,
            (true, Some(uv)) => Some(tape.var_shared(uv.clone(), false)),
            (true, None) => {
                return Err(FitError::Invalid(format!(
                    "model {} has no uvs: it cannot be textured",
                    self.model.name()
                )))
            }
        };
        let pos = self.split.gather(world);
        let clip = self.clip(pos, v.focal)?;
        let mut s = self.method_settings();
        if weight.is_some() {
            // The photometric weight's channel: 0 on the background.
            s.view.background.push(0.0);
        }
        let faces = self.render_faces.clone();
        Ok(render_fragments(clip, faces, &s, &mut |r| {
            let n = interpolate(normals, r)?;
            let mut a = interpolate(albedo, r)?;
            if let (Some((texels, textured)), Some(uvs)) = (texture, uvs) {
                let t = sample(texels, interpolate(uvs, r)?, None, TEXTURE_SAMPLER);
                let face = &r.fragments.face;
                let mask = ArrayD::from_shape_fn(IxDyn(&[face.len(), 3]), |i| {
                    textured[face[i[0]] as usize]
                });
                a = t.where_(mask, a);
            }
            let rgb = sh_shade(n, a, v.sh);
            Ok(match weight {
                Some(w) => tape.concat(&[rgb, interpolate(w, r)?], 1),
                None => rgb,
            })
        })?)
    }

    fn method_settings(&self) -> MethodSettings {
        let o = &self.options;
        let mut s = MethodSettings::new(o.method, o.width, o.height);
        s.view.background = o.background.to_vec();
        (s.sigma, s.gamma, s.delta) = (o.sigma, o.gamma, o.delta);
        (s.near, s.far) = (NEAR_MM, FAR_MM);
        s
    }

    /// The surface seen at every covered pixel of the face posed by `p` (hard rasterization
    /// through the method registry, whatever the renderer's method): what a stage that keeps
    /// the geometry fixed needs, computed once.
    pub fn surface_samples(&self, p: &FaceParams) -> Result<SurfaceSamples, FitError> {
        let uvs = self.uvs.as_ref().ok_or_else(|| {
            FitError::Invalid(format!(
                "model {} has no uvs: it cannot be textured",
                self.model.name()
            ))
        })?;
        let tape = Tape::new();
        let v = self.vars(&tape, p, Active::NONE);
        let world = self.posed(&v);
        let normals = self.split.gather(vertex_normals(world, &self.model_faces));
        let albedo = self
            .split
            .albedo(self.model.albedo_standardized(&tape, v.z_albedo));
        let pos = self.split.gather(world);
        let uv = tape.var_shared(uvs.clone(), false);
        let clip = self.clip(pos, v.focal)?;
        let mut s = self.method_settings();
        s.method = Method::Hard;
        let mut out = None;
        render_fragments(clip, self.render_faces.clone(), &s, &mut |r| {
            let col = interpolate(albedo, r)?;
            let [position, normal, uv] = [pos, normals, uv].map(|x| interpolate(x, r));
            let plain =
                |x: Var<'_, f64>| -> Result<Array2<f64>, RenderError> { Ok(to2(&*x.value()?)) };
            let f = &r.fragments;
            let mut pixel = vec![0; f.face.len()];
            for (px, w) in f.offsets.windows(2).enumerate() {
                pixel[w[0] as usize..w[1] as usize].fill(px);
            }
            out = Some(SurfaceSamples {
                pixel,
                face: f.face.clone(),
                position: plain(position?)?,
                normal: plain(normal?)?,
                uv: plain(uv?)?,
                albedo: plain(col)?,
            });
            Ok(col)
        })?;
        out.ok_or_else(|| FitError::Invalid("the rasterizer called no shader".into()))
    }

    /// Plain render of `p`: the image `[H, W, 4]` and all vertices' pixel positions `[V, 2]`.
    pub fn render(&self, p: &FaceParams) -> Result<(Array3<f64>, Array2<f64>), FitError> {
        let tape = Tape::new();
        let v = self.vars(&tape, p, Active::NONE);
        let world = self.posed(&v);
        let img = self.image(world, &v)?.value()?;
        let px = self.project_rows(world, v.focal)?.value()?;
        Ok((to3(&img), to2(&px)))
    }

    /// Plain render of `p` as the photometric term sees it: `[H, W, 4]`, RGB and alpha =
    /// coverage times the photometric weight ([`FaceRenderer::photo_image`]); with it
    /// [`super::photometric_rmse`] is the RMSE inside the photometric mask.
    pub fn render_photo(&self, p: &FaceParams) -> Result<Array3<f64>, FitError> {
        let tape = Tape::new();
        let v = self.vars(&tape, p, Active::NONE);
        let img = self.photo_image(self.posed(&v), &v)?.value()?;
        let img = to3(&img);
        if img.shape()[2] == 4 {
            return Ok(img);
        }
        let mut out = img.slice(ndarray::s![.., .., 0..4]).to_owned();
        for ((o, &w), &a) in out
            .slice_mut(ndarray::s![.., .., 3])
            .iter_mut()
            .zip(img.slice(ndarray::s![.., .., 3]))
            .zip(img.slice(ndarray::s![.., .., 4]))
        {
            *o = w * a;
        }
        Ok(out)
    }

    /// Plain pixel positions `[N, 2]` of landmark `points` of the face posed by `p`.
    pub fn landmarks_px(
        &self,
        p: &FaceParams,
        points: &[LandmarkPoint],
    ) -> Result<Array2<f64>, FitError> {
        let tape = Tape::new();
        let v = self.vars(&tape, p, Active::NONE);
        let world = self.posed(&v);
        let px = self.project_px(world, v.focal, points)?.value()?;
        Ok(to2(&px))
    }
}

/// How the albedo texture is sampled: bilinear, clamped to the edge (uvs outside `[0, 1]`
/// belong to untextured regions).
pub const TEXTURE_SAMPLER: Sampler = Sampler {
    filter: Filter::Bilinear,
    wrap: Wrap::Clamp,
};

/// The surface seen at the `N` covered pixels of a hard rasterization
/// ([`FaceRenderer::surface_samples`]): one row per pixel, values interpolated
/// perspective-correctly from the render vertices.
#[derive(Clone, Debug)]
pub struct SurfaceSamples {
    /// Row-major pixel index `row * width + col`.
    pub pixel: Vec<usize>,
    /// The model face seen.
    pub face: Vec<u32>,
    /// View-space position `[N, 3]` (millimetres; the camera at the origin).
    pub position: Array2<f64>,
    /// Interpolated vertex normal `[N, 3]` (not normalised).
    pub normal: Array2<f64>,
    /// Texture coordinates `[N, 2]`.
    pub uv: Array2<f64>,
    /// Interpolated vertex albedo `[N, 3]` (region colours included).
    pub albedo: Array2<f64>,
}

/// Model-space positions `[N, 3]` posed by `v`'s rotation and translation.
fn pose<'t>(shape: Var<'t, f64>, v: &ParamVars<'t>) -> Var<'t, f64> {
    rigid_transform(shape, axis_angle_to_matrix(v.rotation), v.translation)
}

/// Which parameter groups require gradients.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Active {
    /// Rotation and translation.
    pub pose: bool,
    /// Focal length.
    pub focal: bool,
    /// Identity and expression.
    pub shape: bool,
    /// Albedo and SH lighting.
    pub appearance: bool,
}

impl Active {
    /// Nothing requires gradients (plain evaluation).
    pub const NONE: Active = Active {
        pose: false,
        focal: false,
        shape: false,
        appearance: false,
    };
}

pub(crate) fn to3(a: &ArrayD<f64>) -> Array3<f64> {
    a.clone()
        .into_dimensionality()
        .expect("renderer images are 3-D")
}

pub(crate) fn to2(a: &ArrayD<f64>) -> Array2<f64> {
    a.clone().into_dimensionality().expect("2-D")
}
