//! The scene pipeline: the common wiring of the stages for a scene JSON (vertex stage, raster
//! method, shading, blend), used by the `tapestry render` and `tapestry grad` commands. Every
//! stage stays callable on its own; this module only composes them.

use std::sync::Arc;

use autodiff::{Real, Tape, Var};
use ndarray::{ArrayD, IxDyn};

use crate::blend::blend_hard;
use crate::error::RenderError;
use crate::interpolate::interpolate;
use crate::raster::RasterSettings;
use crate::rasterize::rasterize;
use crate::scene::{Method, Scene, Shading};
use crate::soft::{softras, SoftSettings};
use crate::transform::to_clip;

/// The differentiable inputs of a scene render.
pub struct SceneVars<'t, T: Real> {
    /// Vertex positions [V, 3] (world space).
    pub positions: Var<'t, T>,
    /// Vertex colours [V, 3].
    pub colors: Var<'t, T>,
}

/// Which scene inputs should carry gradients.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Wrt {
    /// Vertex positions.
    pub positions: bool,
    /// Vertex colours.
    pub colors: bool,
}

impl<T: Real> Scene<T> {
    /// Raster settings of the scene (size, faces per pixel, culling, interpolation mode).
    pub fn raster_settings(&self) -> RasterSettings {
        let r = &self.desc.raster;
        let mut s = RasterSettings::new(
            self.desc.image.width as usize,
            self.desc.image.height as usize,
        );
        s.faces_per_pixel = r.effective_faces_per_pixel().unwrap_or(1) as usize;
        s.cull_backfaces = r.cull_backfaces;
        s.perspective_correct = r.perspective_correct;
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
        SceneVars {
            positions: tape.var(pos, wrt.positions),
            colors: tape.var(col, wrt.colors),
        }
    }

    /// Renders the scene: an RGBA image [H, W, 4] (RGB composited over the background, alpha =
    /// coverage) as a tape variable.
    pub fn render<'t>(&self, vars: &SceneVars<'t, T>) -> Result<Var<'t, T>, RenderError> {
        let method = self.desc.raster.method;
        if !matches!(method, Method::Hard | Method::SoftRas) {
            return Err(RenderError::Unsupported(format!(
                "raster.method '{}' is not available in this build; available: hard, softras",
                method.name()
            )));
        }
        if self.desc.material.shading != Shading::None {
            return Err(RenderError::Unsupported(format!(
                "material.shading '{:?}' is not available in this build; available: none",
                self.desc.material.shading
            )));
        }
        if self.texture.is_some() {
            return Err(RenderError::Unsupported(
                "textures are not available in this build; use vertex colours".into(),
            ));
        }
        let faces = Arc::new(self.mesh.faces.clone());
        let clip = to_clip(vars.positions, &self.camera.view_proj());
        let kd = self.desc.material.kd.map(T::from_f64c);
        let kd = vars
            .positions
            .tape()
            .constant(ArrayD::from_shape_vec(IxDyn(&[3]), kd.to_vec()).expect("3"));
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
            return softras(clip, vars.colors * kd, faces, &s);
        }
        let r = rasterize(clip, faces, &self.raster_settings())?;
        let colors = interpolate(vars.colors * kd, &r)?;
        blend_hard(colors, &r.fragments, &self.background())
    }
}
