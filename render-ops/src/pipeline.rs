//! The scene pipeline: the common wiring of the stages for a scene JSON (vertex stage, raster
//! method, shading, blend), used by the `tapestry render` and `tapestry grad` commands. Every
//! stage stays callable on its own; this module only composes them.

use std::sync::Arc;

use autodiff::{Real, Tape, Tensor, Var};
use ndarray::{ArrayD, IxDyn};

use crate::error::RenderError;
use crate::methods::{render_fragments_lit, render_vertex_colors, MethodSettings, ViewSettings};
use crate::raster::RasterSettings;
use crate::raytrace::{raytrace, LightKind, RaytraceSettings, Reflection, ShadowInputs};
use crate::scene::{Light, Scene};
use crate::shade::stage::{texture_rgb, SceneShading, SCENE_SAMPLER};
use crate::shade::{fragment_inputs, vertex_normals, MeshAttributes};
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

impl<'t, T: Real> SceneVars<'t, T> {
    /// The variable of `input`. `InvalidInput` (named after `--wrt`, with the scene's
    /// `source`) when the scene has no texture, no lights, or the input is empty.
    pub fn input(&self, input: SceneInput, source: &str) -> Result<Var<'t, T>, RenderError> {
        let missing = |what: &str| {
            RenderError::InvalidInput(format!(
                "--wrt {}: the scene {source} has no {what}",
                input.name()
            ))
        };
        let v = match input {
            SceneInput::Positions => self.positions,
            SceneInput::Colors => self.colors,
            SceneInput::Camera => self.camera,
            SceneInput::Texture => self.texture.ok_or_else(|| missing("texture"))?,
            SceneInput::Lights => self.lights.ok_or_else(|| missing("lights"))?,
        };
        if v.is_empty() {
            return Err(missing(input.name()));
        }
        Ok(v)
    }
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

/// A differentiable scene input.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SceneInput {
    /// Vertex positions `[V, 3]`.
    Positions,
    /// Vertex colours `[V, 3]`.
    Colors,
    /// Texture texels `[H, W, C]`.
    Texture,
    /// Camera eye and look-at point `[2, 3]`.
    Camera,
    /// Light parameters `[n, 3]` ([`crate::pipeline::SceneVars::lights`]).
    Lights,
}

impl SceneInput {
    /// Every input.
    pub const ALL: [SceneInput; 5] = [
        SceneInput::Positions,
        SceneInput::Colors,
        SceneInput::Texture,
        SceneInput::Camera,
        SceneInput::Lights,
    ];

    /// The command-line name.
    pub fn name(self) -> &'static str {
        match self {
            SceneInput::Positions => "positions",
            SceneInput::Colors => "colors",
            SceneInput::Texture => "texture",
            SceneInput::Camera => "camera",
            SceneInput::Lights => "lights",
        }
    }

    /// Parses a command-line name.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|i| i.name() == name)
    }

    /// Positions and camera move edges: the image is not smooth in them.
    pub fn is_geometric(self) -> bool {
        matches!(self, SceneInput::Positions | SceneInput::Camera)
    }

    /// One item per mesh vertex.
    pub fn is_per_vertex(self) -> bool {
        matches!(self, SceneInput::Positions | SceneInput::Colors)
    }

    /// The [`Wrt`] flags that make this input require a gradient.
    pub fn wrt(self) -> Wrt {
        Wrt {
            positions: self == SceneInput::Positions,
            colors: self == SceneInput::Colors,
            texture: self == SceneInput::Texture,
            camera: self == SceneInput::Camera,
            lights: self == SceneInput::Lights,
        }
    }
}

impl<T: Real> Scene<T> {
    /// Raster settings of the scene (size, faces per pixel, culling, interpolation mode;
    /// barycentric derivatives for textured scenes).
    pub fn raster_settings(&self) -> RasterSettings {
        self.method_settings().raster()
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

    /// The scene's method settings for the registry ([`crate::methods`]): the `raster` block,
    /// the image's size and background, the camera's clip planes; barycentric derivatives for
    /// textured scenes.
    pub fn method_settings(&self) -> MethodSettings {
        let proj = self.camera.projection();
        let view = ViewSettings {
            background: self.desc.image.background.to_vec(),
            ..ViewSettings::new(
                self.desc.image.width as usize,
                self.desc.image.height as usize,
            )
        };
        MethodSettings {
            // Only texturing reads the screen-space uv derivatives.
            barycentric_derivatives: self.texture.is_some(),
            ..MethodSettings::from_raster(&self.desc.raster, view, proj.near(), proj.far())
        }
    }

    /// Renders the scene: an RGBA image [H, W, 4] (RGB composited over the background, alpha =
    /// coverage) as a tape variable, through the method registry ([`crate::methods`]).
    ///
    /// Unlit, untextured scenes take the fused per-vertex-colour path of the method
    /// ([`render_vertex_colors`]). Lit or textured scenes are shaded per fragment (texture,
    /// per-pixel lighting) and composed with the method's visibility stage
    /// ([`render_fragments`]: the hard blend, `tf_mesh`'s extrapolated silhouette band, the
    /// boundary ops of [`crate::boundary`], the soft stage's fragments within the cut-off and
    /// SoftRas's blend, or DIB-R's soft alpha). Every method of
    /// [`crate::scene::Method::ALL`] is available.
    pub fn render<'t>(&self, vars: &SceneVars<'t, T>) -> Result<Var<'t, T>, RenderError> {
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
        let s = self.method_settings();
        if s.method == crate::scene::Method::Raytrace {
            return self.render_raytrace(vars, clip, kd, &s);
        }
        let per_vertex = !self.shading(vars).is_lit() && vars.texture.is_none();
        if per_vertex {
            return render_vertex_colors(clip, self.vertex_colors(vars, kd)?, faces, &s);
        }
        self.render_shaded(vars, clip, kd, &s, None)
    }
}

/// The scene commands as library calls (`tapestry render --npy`, `tapestry grad`), so that the
/// command line and the Python bindings compute the same numbers.
impl<T: Real> Scene<T> {
    /// The RGBA image `[H, W, 4]` of [`Scene::render`] without gradients (what
    /// `tapestry render --npy` writes, with `T = f64`).
    ///
    /// # Errors
    /// The render's errors.
    pub fn render_image(&self) -> Result<Tensor<T>, RenderError> {
        let tape = Tape::new();
        let vars = self.vars(&tape, Wrt::default());
        let img = self.render(&vars)?.value()?;
        Ok(Arc::unwrap_or_clone(img))
    }

    /// `L = sum over pixels and channels of (render - target)^2` and `dL/d input` in the
    /// input's shape (`tapestry grad`). A 3-channel `target` `[H, W, 3]` is compared with the
    /// RGB channels, a 4-channel one with RGBA. `target_name` names the target in errors.
    ///
    /// # Errors
    /// `InvalidInput` for a target of another size, a texture or lights asked of a scene
    /// without them; the render's errors.
    pub fn image_loss_grad(
        &self,
        target: Tensor<T>,
        target_name: &str,
        input: SceneInput,
    ) -> Result<(T, Tensor<T>), RenderError> {
        let (w, h) = (
            self.desc.image.width as usize,
            self.desc.image.height as usize,
        );
        let ts = target.shape().to_vec();
        if ts.len() != 3 || ts[0] != h || ts[1] != w || !(ts[2] == 3 || ts[2] == 4) {
            return Err(RenderError::InvalidInput(format!(
                "target {target_name}: shape {ts:?} does not match the scene's image [{h}, {w}, 3 or 4]"
            )));
        }
        let tape = Tape::new();
        let vars = self.vars(&tape, input.wrt());
        let x = vars.input(input, &self.source)?;
        let img = self.render(&vars)?;
        let img = if ts[2] == 3 { img.slice(2, 0, 3) } else { img };
        let loss = img.sum_squared_diff(tape.constant(target));
        let grads = tape.backward(loss)?;
        Ok((loss.item()?, grads.wrt(x)))
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
                "textures are sampled per fragment: per-vertex colours of raster.method '{}' \
                 cannot carry one (render the scene, which shades textured scenes per fragment)",
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
        shading.apply(vars.positions, normals, albedo, self.eye(vars), None)
    }

    /// Per-fragment shading composed with the method of `s` ([`render_fragments`]): per
    /// fragment interpolate, texture, shade (Phong shading: lighting per fragment with
    /// interpolated area-weighted vertex normals).
    ///
    /// A textured scene splits the mesh at uv seams ([`crate::mesh::Mesh::unified`]): the
    /// split vertices gather the clip coordinates, colours and normals of their source
    /// vertices, so gradients sum back onto `vars.positions` / `vars.colors`. The texture is
    /// sampled with [`SCENE_SAMPLER`] (bilinear, repeat). With `shadow_rows` (the scene's
    /// light rows, `raytrace` only) the fragments carry the lights' visibility by shadow rays
    /// ([`render_fragments_lit`]).
    fn render_shaded<'t>(
        &self,
        vars: &SceneVars<'t, T>,
        clip: Var<'t, T>,
        kd: Var<'t, T>,
        s: &MethodSettings,
        shadow_rows: Option<Var<'t, T>>,
    ) -> Result<Var<'t, T>, RenderError> {
        let t = vars.positions.tape();
        let shading = self.shading(vars);
        let eye = self.eye(vars);
        let faces = Arc::new(self.mesh.faces.clone());
        let normals = vertex_normals(vars.positions, &faces);
        let Some(texels) = vars.texture else {
            let mesh = MeshAttributes::new(vars.positions)
                .with_normals(normals)
                .with_attribute("color", vars.colors);
            let shadows = self.shadow_inputs(vars.positions, shadow_rows);
            return render_fragments_lit(clip, faces, s, shadows, &mut |r| {
                let f = fragment_inputs(r, &mesh, eye)?;
                let albedo = f.attribute("color").expect("set above") * kd;
                shading.apply(f.position, f.normal, albedo, f.eye, f.visibility)
            });
        };
        if !self.mesh.has_uvs() {
            return Err(RenderError::Unsupported(format!(
                "the scene has a texture but the mesh {} has no uvs ('vt' lines)",
                self.mesh_path.display()
            )));
        }
        let unified = self.mesh.unified()?;
        let index: Vec<usize> = unified.position_index.iter().map(|&i| i as usize).collect();
        let ufaces = Arc::new(unified.mesh.faces.clone());
        let uvs = ArrayD::from_shape_vec(
            IxDyn(&[unified.mesh.uvs.len(), 2]),
            unified.mesh.uvs.iter().flatten().copied().collect(),
        )
        .expect("v x 2");
        let rclip = clip.index_select(0, &index);
        let upos = vars.positions.index_select(0, &index);
        let shadows = self.shadow_inputs(upos, shadow_rows);
        let mesh = MeshAttributes::new(upos)
            .with_normals(normals.index_select(0, &index))
            .with_uvs(t.constant(uvs))
            .with_attribute("color", vars.colors.index_select(0, &index));
        let texture = Texture::new(texels, SCENE_SAMPLER);
        render_fragments_lit(rclip, ufaces, s, shadows, &mut |r| {
            let f = fragment_inputs(r, &mesh, eye)?;
            let tex = texture_rgb(f.sample(&texture))?;
            let albedo = f.attribute("color").expect("set above") * kd * tex;
            shading.apply(f.position, f.normal, albedo, f.eye, f.visibility)
        })
    }
}

/// The `raytrace` method on a scene.
impl<T: Real> Scene<T> {
    /// The inputs of the ray tracer's shadow rays: world positions and the scene's light rows.
    fn shadow_inputs<'t>(
        &self,
        world: Var<'t, T>,
        rows: Option<Var<'t, T>>,
    ) -> Option<ShadowInputs<'t, T>> {
        rows.map(|lights| ShadowInputs {
            world,
            lights,
            kinds: self.raytrace_settings().lights,
        })
    }

    /// The ray tracer's settings for this scene: the registry's (`raster` block, size,
    /// background, clip planes) with the scene's eye, material and light kinds.
    pub fn raytrace_settings(&self) -> RaytraceSettings {
        let m = &self.desc.material;
        RaytraceSettings {
            eye: self.desc.camera.eye,
            reflection: Reflection {
                shading: m.shading,
                ks: m.ks,
                shininess: m.shininess,
                ka: m.ka,
            },
            lights: self
                .desc
                .lights
                .iter()
                .map(|l| match l {
                    Light::Ambient { .. } => LightKind::Ambient,
                    Light::Directional { .. } => LightKind::Directional,
                    Light::Point { .. } => LightKind::Point,
                    Light::Area { .. } => LightKind::Area,
                    Light::Sh { .. } => LightKind::Sh,
                })
                .collect(),
            ..self.method_settings().raytrace()
        }
    }

    /// Ray-traced render ([`crate::raytrace`]): albedo `kd` times the vertex colours,
    /// area-weighted vertex normals, the scene's lights (or `vars.lights`) with shadows. A
    /// textured scene goes through the fragment stages ([`crate::raytrace::stage`]) with the
    /// scene's shader and the shadows of its directional and point lights; an area light with
    /// a texture is `Unsupported`.
    fn render_raytrace<'t>(
        &self,
        vars: &SceneVars<'t, T>,
        clip: Var<'t, T>,
        kd: Var<'t, T>,
        s: &MethodSettings,
    ) -> Result<Var<'t, T>, RenderError> {
        let t = vars.positions.tape();
        let lights = match vars.lights {
            Some(l) => l,
            None => {
                let rows = crate::shade::lights::scene_light_rows(&self.desc.lights);
                let data = rows.iter().flatten().map(|&x| T::from_f64c(x)).collect();
                t.constant(ArrayD::from_shape_vec(IxDyn(&[rows.len(), 3]), data).expect("n x 3"))
            }
        };
        if vars.texture.is_some() {
            if self
                .desc
                .lights
                .iter()
                .any(|l| matches!(l, Light::Area { .. }))
            {
                return Err(RenderError::Unsupported(
                    "raster.method 'raytrace' shades a textured scene through its fragment \
                     stages, which cast shadows of directional and point lights: area lights \
                     need vertex colours"
                        .into(),
                ));
            }
            return self.render_shaded(vars, clip, kd, s, Some(lights));
        }
        let faces = Arc::new(self.mesh.faces.clone());
        let normals = vertex_normals(vars.positions, &faces);
        let albedo = vars.colors * kd;
        raytrace(
            clip,
            vars.positions,
            normals,
            albedo,
            lights,
            faces,
            &self.raytrace_settings(),
        )
    }
}
