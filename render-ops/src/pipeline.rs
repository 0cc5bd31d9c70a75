//! The scene pipeline: the common wiring of the stages for a scene JSON (vertex stage, raster
//! method, shading, blend), used by the `tapestry render` and `tapestry grad` commands. Every
//! stage stays callable on its own; this module only composes them.

use std::sync::Arc;

use autodiff::{Real, Tape, Var};
use ndarray::{ArrayD, IxDyn};

use crate::approx::{deodr, nmr, opendr, tf_mesh, ApproxSettings};
use crate::blend::blend_hard;
use crate::boundary::{self, BoundarySettings};
use crate::error::RenderError;
use crate::raster::RasterSettings;
use crate::rasterize::{rasterize, render_attributes, Rasterized};
use crate::scene::{Method, Scene};
use crate::shade::stage::{texture_rgb, SceneShading, SCENE_SAMPLER};
use crate::shade::{fragment_inputs, vertex_normals, MeshAttributes};
use crate::soft::{
    dibr, dibr_aggregate, soft_fragments, softras, softras_aggregate, Coverage, DibrSettings,
    SoftBlendSettings, SoftFragments, SoftSettings, SoftStageSettings,
};
use crate::texture::Texture;
use crate::transform::to_clip;

/// The differentiable inputs of a scene render.
pub struct SceneVars<'t, T: Real> {
    /// Vertex positions [V, 3] (world space).
    pub positions: Var<'t, T>,
    /// Vertex colours [V, 3].
    pub colors: Var<'t, T>,
    /// The scene's texture [H, W, C] (values in [0, 1] for PNG); `None` without a texture.
    pub texture: Option<Var<'t, T>>,
    /// The camera's eye and look-at point, rows `[2, 3]` = [eye; at] (world space). The up
    /// vector, field of view and clip planes stay those of the scene. When this variable
    /// requires a gradient the view matrix is built on the tape ([`Scene::clip`]).
    pub camera: Var<'t, T>,
    /// The light parameters `[n, 3]`, every light of the scene in order (an ambient light:
    /// its colour; directional: direction, colour; point: position, colour; SH: 9 rows; see
    /// [`crate::shade::lights::scene_light_rows`]); `None` (the scene's constant lights) unless
    /// asked for with [`Wrt::lights`] or set.
    pub lights: Option<Var<'t, T>>,
}

/// Which scene inputs should carry gradients.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Wrt {
    /// Vertex positions.
    pub positions: bool,
    /// Vertex colours.
    pub colors: bool,
    /// The texture texels (`[H, W, C]`; ignored when the scene has no texture).
    pub texture: bool,
    /// The camera's eye and look-at point (`[2, 3]`).
    pub camera: bool,
    /// The light parameters (`[n, 3]`, [`SceneVars::lights`]).
    pub lights: bool,
}

impl<T: Real> Scene<T> {
    /// Raster settings of the scene (size, faces per pixel, culling, interpolation mode;
    /// barycentric derivatives for textured scenes).
    pub fn raster_settings(&self) -> RasterSettings {
        let r = &self.desc.raster;
        let mut s = RasterSettings::new(
            self.desc.image.width as usize,
            self.desc.image.height as usize,
        );
        s.faces_per_pixel = r.effective_faces_per_pixel().unwrap_or(1) as usize;
        s.cull_backfaces = r.cull_backfaces;
        s.perspective_correct = r.perspective_correct;
        // Only texturing reads the screen-space uv derivatives.
        s.barycentric_derivatives = self.texture.is_some();
        s
    }

    /// Background colour of the image.
    pub fn background(&self) -> [T; 3] {
        self.desc.image.background.map(T::from_f64c)
    }

    /// Creates the scene's inputs on `tape` (vertex colours default to white when the mesh
    /// has none).
    pub fn vars<'t>(&self, tape: &'t Tape<T>, wrt: Wrt) -> SceneVars<'t, T> {
        let v = self.mesh.positions.len();
        let pos = ArrayD::from_shape_vec(
            IxDyn(&[v, 3]),
            self.mesh.positions.iter().flatten().copied().collect(),
        )
        .expect("v x 3");
        let col: Vec<T> = if self.mesh.colors.is_empty() {
            vec![T::one(); 3 * v]
        } else {
            self.mesh.colors.iter().flatten().copied().collect()
        };
        let col = ArrayD::from_shape_vec(IxDyn(&[v, 3]), col).expect("v x 3");
        let texture = self
            .texture
            .as_ref()
            .map(|t| tape.var(t.clone().into_dyn(), wrt.texture));
        let c = &self.desc.camera;
        let cam = ArrayD::from_shape_vec(
            IxDyn(&[2, 3]),
            c.eye
                .iter()
                .chain(&c.at)
                .map(|&x| T::from_f64c(x))
                .collect(),
        )
        .expect("2 x 3");
        let lights = wrt.lights.then(|| {
            let rows = crate::shade::lights::scene_light_rows(&self.desc.lights);
            let data = rows.iter().flatten().map(|&x| T::from_f64c(x)).collect();
            tape.var(
                ArrayD::from_shape_vec(IxDyn(&[rows.len(), 3]), data).expect("n x 3"),
                true,
            )
        });
        SceneVars {
            positions: tape.var(pos, wrt.positions),
            colors: tape.var(col, wrt.colors),
            texture,
            camera: tape.var(cam, wrt.camera),
            lights,
        }
    }

    /// The scene's shading on the tape: its constant lights, or those of `vars.lights`.
    pub fn shading<'t>(&self, vars: &SceneVars<'t, T>) -> SceneShading<'t, T> {
        match vars.lights {
            Some(rows) => {
                SceneShading::with_light_rows(&self.desc.material, &self.desc.lights, rows)
            }
            None => SceneShading::new(
                vars.positions.tape(),
                &self.desc.material,
                &self.desc.lights,
            ),
        }
    }

    /// Renders the scene: an RGBA image [H, W, 4] (RGB composited over the background, alpha =
    /// coverage) as a tape variable.
    ///
    /// Methods `opendr`, `nmr` and `deodr` over unlit, untextured scenes use the fused ops of
    /// [`crate::approx`] over the vertex colours (the image of method `hard` with approximate
    /// boundary gradients, or for `deodr` that image's silhouette edges overdrawn with a ramp
    /// `overdraw_px` wide, differentiated exactly). Lit or textured scenes are shaded per
    /// fragment as by method `hard` and then go through the method's op of
    /// [`crate::boundary`] over the shaded image. Methods `softras` and `dibr` over unlit,
    /// untextured scenes use their fused ops of [`crate::soft`]; lit or textured scenes go
    /// through the soft stage, per-fragment shading and the method's blend
    /// ([`crate::soft::stage`]). `tf_mesh` renders per-vertex colours only
    /// (lighting evaluated at the vertices, see [`Scene::vertex_colors`]). Every method of
    /// [`Method::ALL`] is available.
    pub fn render<'t>(&self, vars: &SceneVars<'t, T>) -> Result<Var<'t, T>, RenderError> {
        let method = self.desc.raster.method;
        // NaN or Inf in an input would otherwise reach the image silently (colours), be
        // skipped (soft methods) or be reported as a clip coordinate: name the input.
        RenderError::check_finite("positions", &*vars.positions.value()?)?;
        RenderError::check_finite("colors", &*vars.colors.value()?)?;
        RenderError::check_finite("camera", &*vars.camera.value()?)?;
        if let Some(t) = vars.texture {
            RenderError::check_finite("texture", &*t.value()?)?;
        }
        if let Some(l) = vars.lights {
            let n = crate::shade::lights::scene_light_rows(&self.desc.lights).len();
            let v = l.value()?;
            if v.shape() != [n, 3] {
                return Err(autodiff::AutodiffError::shape(
                    "scene lights",
                    &[v.shape()],
                    format!("the scene's light parameters are [{n}, 3]"),
                )
                .into());
            }
            RenderError::check_finite("lights", &v)?;
        }
        let faces = Arc::new(self.mesh.faces.clone());
        let clip = self.clip(vars.positions, vars);
        let kd = self.desc.material.kd.map(T::from_f64c);
        let kd = vars
            .positions
            .tape()
            .constant(ArrayD::from_shape_vec(IxDyn(&[3]), kd.to_vec()).expect("3"));
        if method.is_soft() && (self.shading(vars).is_lit() || vars.texture.is_some()) {
            // Lit or textured: the soft stage, per-fragment shading, the method's blend.
            return self.render_soft(vars, clip, kd);
        }
        if method == Method::SoftRas {
            let r = &self.desc.raster;
            let proj = self.camera.projection();
            let (w, h) = (
                self.desc.image.width as usize,
                self.desc.image.height as usize,
            );
            let mut s = SoftSettings::new(w, h, proj.near(), proj.far());
            s.sigma = r.sigma;
            s.gamma = r.gamma;
            s.eps = r.eps;
            s.threshold = r.threshold;
            s.perspective_correct = r.perspective_correct;
            s.background = self.desc.image.background.to_vec();
            return softras(clip, self.vertex_colors(vars, kd)?, faces, &s);
        }
        if method == Method::Dibr {
            // DIB-R over vertex colours: the hard render's RGB with the soft silhouette as
            // alpha (render_ops::soft::dibr).
            let r = &self.desc.raster;
            let mut s = DibrSettings::new(
                self.desc.image.width as usize,
                self.desc.image.height as usize,
            );
            s.delta = r.delta;
            s.threshold = r.threshold;
            s.cull_backfaces = r.cull_backfaces;
            let alpha = dibr::dibr_alpha(clip, faces, &s)?;
            return dibr::composite(self.render_hard(vars, clip, kd)?, alpha);
        }
        if matches!(
            method,
            Method::TfMesh | Method::OpenDr | Method::Nmr | Method::Deodr
        ) {
            let r = &self.desc.raster;
            let lit = SceneShading::new(
                vars.positions.tape(),
                &self.desc.material,
                &self.desc.lights,
            )
            .is_lit();
            if method != Method::TfMesh && (lit || vars.texture.is_some()) {
                // Shaded per fragment as by method `hard` (texture, per-pixel lighting), then
                // the method's boundary op over the shaded image (render_ops::boundary).
                let shaded = self.shade_fragments(vars, clip, kd)?;
                let Some((raster, rclip)) = shaded.raster else {
                    return Err(RenderError::Unsupported(
                        "a lit or textured scene is shaded after rasterization".into(),
                    ));
                };
                return match method {
                    Method::OpenDr => boundary::opendr(shaded.image, &raster, rclip),
                    Method::Nmr => boundary::nmr(shaded.image, &raster, rclip),
                    _ => boundary::deodr(
                        shaded.image,
                        &raster,
                        rclip,
                        &BoundarySettings {
                            overdraw_px: r.overdraw_px,
                        },
                    ),
                };
            }
            // The fast path: the hard forward over per-vertex colours with approximate boundary
            // gradients, or DEODR's edge overdraw and its exact gradient, fused
            // (render_ops::approx); for tf_mesh also over Gouraud-shaded colours. Textures are
            // rejected by vertex_colors.
            let mut s = ApproxSettings::new(
                self.desc.image.width as usize,
                self.desc.image.height as usize,
            );
            s.perspective_correct = r.perspective_correct;
            s.cull_backfaces = r.cull_backfaces;
            s.background = self.desc.image.background.to_vec();
            s.overdraw_px = r.overdraw_px;
            let colors = self.vertex_colors(vars, kd)?;
            return match method {
                Method::TfMesh => tf_mesh(clip, colors, faces, &s),
                Method::OpenDr => opendr(clip, colors, faces, &s),
                Method::Nmr => nmr(clip, colors, faces, &s),
                _ => deodr(clip, colors, faces, &s),
            };
        }
        self.render_hard(vars, clip, kd)
    }
}

/// The stages shared by the raster methods: camera, per-vertex (Gouraud) shading for methods
/// that take per-vertex attributes, and the per-fragment path of the hard method.
impl<T: Real> Scene<T> {
    /// Homogeneous clip coordinates `[N, 4]` of world points `[N, 3]` under the scene's camera.
    /// When `vars.camera` requires a gradient, the view matrix is built on the tape from its
    /// eye and look-at rows (`look_at` of [`crate::camera`], the scene's `up`), so gradients
    /// reach the camera; otherwise the camera's constant matrix is used.
    pub fn clip<'t>(&self, points: Var<'t, T>, vars: &SceneVars<'t, T>) -> Var<'t, T> {
        if !vars.camera.requires_grad() {
            return to_clip(points, &self.camera.view_proj());
        }
        let t = points.tape();
        let eps = T::from_f64c(1e-12);
        let eye = vars.camera.slice(0, 0, 1).reshape(&[3]);
        let at = vars.camera.slice(0, 1, 2).reshape(&[3]);
        let up = t.constant(
            ArrayD::from_shape_vec(
                IxDyn(&[3]),
                self.desc
                    .camera
                    .up
                    .iter()
                    .map(|&x| T::from_f64c(x))
                    .collect(),
            )
            .expect("3"),
        );
        let f = (at - eye).normalize(eps);
        let s = f.cross(up).normalize(eps);
        let u = s.cross(f);
        // Rows of the view rotation: s, u, -f; view point = R (p - eye).
        let rot = t.stack(&[s, u, -f], 0);
        let view = (points - eye).matmul(rot.t());
        let n = points.shape().first().copied().unwrap_or(0);
        let ones = t.constant(ArrayD::from_elem(IxDyn(&[n, 1]), T::one()));
        let p = self.camera.proj_rows();
        let pt = ArrayD::from_shape_fn(IxDyn(&[4, 4]), |i| T::from_f64c(p[i[1]][i[0]]));
        t.concat(&[view, ones], 1).matmul(t.constant(pt))
    }

    /// The eye `[3]` (row 0 of `vars.camera`).
    pub fn eye<'t>(&self, vars: &SceneVars<'t, T>) -> Var<'t, T> {
        vars.camera.slice(0, 0, 1).reshape(&[3])
    }

    /// Per-vertex colours `[V, 3]` for raster methods that take per-vertex attributes (the
    /// soft methods and those of [`crate::approx`]: `tf_mesh`, `opendr`, `nmr`, `deodr`): the
    /// albedo `kd` times the vertex colours, shaded per vertex with the scene's material and
    /// lights (Gouraud shading: the lighting is evaluated at the vertices, with area-weighted
    /// vertex normals, and interpolated by the raster method).
    /// Textures need per-fragment uvs and are not supported here: an `Unsupported` error.
    pub fn vertex_colors<'t>(
        &self,
        vars: &SceneVars<'t, T>,
        kd: Var<'t, T>,
    ) -> Result<Var<'t, T>, RenderError> {
        if vars.texture.is_some() {
            return Err(RenderError::Unsupported(format!(
                "textures are sampled per fragment: raster.method '{}' takes per-vertex \
                 colours; use method 'hard', 'opendr', 'nmr', 'deodr', 'softras' or 'dibr' for \
                 textured scenes",
                self.desc.raster.method.name()
            )));
        }
        let albedo = vars.colors * kd;
        let shading = self.shading(vars);
        if !shading.is_lit() {
            return Ok(albedo);
        }
        let faces = Arc::new(self.mesh.faces.clone());
        let normals = vertex_normals(vars.positions, &faces);
        shading.apply(vars.positions, normals, albedo, self.eye(vars))
    }

    /// The hard method: rasterize `clip` (`[V, 4]`, of `vars.positions`), then per fragment
    /// interpolate, texture, shade (Phong shading: lighting per fragment with interpolated
    /// area-weighted vertex normals), and composite with the z-buffer blend.
    ///
    /// A textured scene splits the mesh at uv seams ([`crate::mesh::Mesh::unified`]): the
    /// split vertices gather the clip coordinates, colours and normals of their source
    /// vertices, so gradients sum back onto `vars.positions` / `vars.colors`. The texture is
    /// sampled with [`SCENE_SAMPLER`] (bilinear, repeat).
    fn render_hard<'t>(
        &self,
        vars: &SceneVars<'t, T>,
        clip: Var<'t, T>,
        kd: Var<'t, T>,
    ) -> Result<Var<'t, T>, RenderError> {
        Ok(self.shade_fragments(vars, clip, kd)?.image)
    }

    /// The image of [`Scene::render_hard`], with the rasterization it was drawn from and the
    /// clip positions of the vertices it rasterized (those of the uv-split mesh for a textured
    /// scene); no rasterization for unlit, untextured scenes drawn by
    /// [`render_attributes`].
    fn shade_fragments<'t>(
        &self,
        vars: &SceneVars<'t, T>,
        clip: Var<'t, T>,
        kd: Var<'t, T>,
    ) -> Result<Shaded<'t, T>, RenderError> {
        let settings = self.raster_settings();
        let bg = self.background();
        if vars.texture.is_none() && !self.shading(vars).is_lit() {
            // Vertex colours: in one pass when no gradient is asked for.
            let faces = Arc::new(self.mesh.faces.clone());
            let image = render_attributes(clip, vars.colors * kd, faces, &settings, &bg)?;
            return Ok(Shaded {
                image,
                raster: None,
            });
        }
        let (color, r, rclip) =
            self.shade_with(vars, clip, kd, |c, faces| rasterize(c, faces, &settings))?;
        let image = blend_hard(color, &r.fragments, &bg)?;
        Ok(Shaded {
            image,
            raster: Some((r, rclip)),
        })
    }

    /// Per-fragment colours `[N, 3]` of the scene (texture, lighting with interpolated
    /// area-weighted vertex normals) over the fragments that `draw` gives for clip positions
    /// and faces (the hard rasterizer, or the soft stage [`crate::soft::soft_fragments`]),
    /// with those fragments and the clip positions drawn (those of the uv-split mesh for a
    /// textured scene, see [`Scene::render_hard`]).
    fn shade_with<'t, D>(
        &self,
        vars: &SceneVars<'t, T>,
        clip: Var<'t, T>,
        kd: Var<'t, T>,
        draw: D,
    ) -> Result<(Var<'t, T>, Rasterized<'t, T>, Var<'t, T>), RenderError>
    where
        D: FnOnce(Var<'t, T>, Arc<Vec<[u32; 3]>>) -> Result<Rasterized<'t, T>, RenderError>,
    {
        let t = vars.positions.tape();
        let shading = self.shading(vars);
        let Some(texels) = vars.texture else {
            let faces = Arc::new(self.mesh.faces.clone());
            let r = draw(clip, faces.clone())?;
            let mesh = MeshAttributes::new(vars.positions)
                .with_normals(vertex_normals(vars.positions, &faces))
                .with_attribute("color", vars.colors);
            let f = fragment_inputs(&r, &mesh, self.eye(vars))?;
            let albedo = f.attribute("color").expect("set above") * kd;
            let color = shading.apply(f.position, f.normal, albedo, f.eye)?;
            return Ok((color, r, clip));
        };
        if !self.mesh.has_uvs() {
            return Err(RenderError::Unsupported(format!(
                "the scene has a texture but the mesh {} has no uvs ('vt' lines)",
                self.mesh_path.display()
            )));
        }
        let unified = self.mesh.unified()?;
        let index: Vec<usize> = unified.position_index.iter().map(|&i| i as usize).collect();
        let faces = Arc::new(unified.mesh.faces.clone());
        let uvs = ArrayD::from_shape_vec(
            IxDyn(&[unified.mesh.uvs.len(), 2]),
            unified.mesh.uvs.iter().flatten().copied().collect(),
        )
        .expect("v x 2");
        let rclip = clip.index_select(0, &index);
        let r = draw(rclip, faces)?;
        let normals = vertex_normals(vars.positions, &Arc::new(self.mesh.faces.clone()));
        let mesh = MeshAttributes::new(vars.positions.index_select(0, &index))
            .with_normals(normals.index_select(0, &index))
            .with_uvs(t.constant(uvs))
            .with_attribute("color", vars.colors.index_select(0, &index));
        let f = fragment_inputs(&r, &mesh, self.eye(vars))?;
        let tex = texture_rgb(f.sample(&Texture::new(texels, SCENE_SAMPLER)))?;
        let albedo = f.attribute("color").expect("set above") * kd * tex;
        let color = shading.apply(f.position, f.normal, albedo, f.eye)?;
        Ok((color, r, rclip))
    }

    /// The composed soft methods (`softras`, `dibr`) for lit or textured scenes: the soft
    /// rasterization stage ([`crate::soft::soft_fragments`]: every face within the cut-off of a
    /// pixel, or its `faces_per_pixel` nearest), the scene's texture and shading per fragment
    /// ([`Scene::shade_with`]), then the method's blend ([`crate::soft::softras_aggregate`]:
    /// softmax over depth; [`crate::soft::dibr_aggregate`]: hard foreground, soft alpha).
    fn render_soft<'t>(
        &self,
        vars: &SceneVars<'t, T>,
        clip: Var<'t, T>,
        kd: Var<'t, T>,
    ) -> Result<Var<'t, T>, RenderError> {
        let r = &self.desc.raster;
        let (w, h) = (
            self.desc.image.width as usize,
            self.desc.image.height as usize,
        );
        let softras = r.method == Method::SoftRas;
        let coverage = if softras {
            Coverage::Sigmoid { sigma: r.sigma }
        } else {
            Coverage::Exp { delta: r.delta }
        };
        let mut st = SoftStageSettings::new(w, h, coverage);
        st.threshold = r.threshold;
        st.max_faces = r.faces_per_pixel.map(|k| k as usize);
        st.perspective_correct = r.perspective_correct;
        // SoftRas draws back faces too (as its fused op); DIB-R culls when asked.
        st.cull_backfaces = !softras && r.cull_backfaces;
        st.barycentric_derivatives = vars.texture.is_some();
        let mut soft = None;
        let (color, raster, _) = self.shade_with(vars, clip, kd, |c, faces| {
            let sf = soft_fragments(c, faces, &st)?;
            soft = Some((sf.prob, sf.inside));
            Ok(sf.raster)
        })?;
        let (prob, inside) = soft.expect("drawn by the soft stage");
        let sf = SoftFragments {
            raster,
            prob,
            inside,
        };
        let bg = self.desc.image.background.to_vec();
        if softras {
            let proj = self.camera.projection();
            let mut bs = SoftBlendSettings::new(proj.near(), proj.far());
            bs.gamma = r.gamma;
            bs.eps = r.eps;
            bs.background = bg;
            softras_aggregate(&sf, color, &bs)
        } else {
            dibr_aggregate(&sf, color, &bg)
        }
    }
}

/// A hard render shaded per fragment: the image `[H, W, 4]`, and when drawn through
/// [`rasterize`], the rasterization and the clip positions `[V, 4]` it was drawn from.
struct Shaded<'t, T: Real> {
    image: Var<'t, T>,
    raster: Option<(Rasterized<'t, T>, Var<'t, T>)>,
}
