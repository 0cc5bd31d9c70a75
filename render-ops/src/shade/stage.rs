//! The shading stage of the scene pipeline ([`crate::pipeline`]): a scene's `material` and
//! `lights` (docs/CONVENTIONS.md) turned into one call that shades per fragment (hard methods,
//! after rasterization and interpolation) or per vertex (Gouraud shading, for methods that
//! take per-vertex attributes such as SoftRas).
//!
//! - `shading: none`: the albedo unlit;
//! - `lambert`, `phong`, `blinn_phong`: [`super::shade`] (fused) with the scene's ambient,
//!   directional and point lights; `ka` null means the albedo;
//! - `sh`: [`super::sh_shade`] with the scene's `sh` light (other lights are not used).
//!
//! The albedo is the material's `kd` times the vertex colours (white when the mesh has none)
//! times the texture sample when the scene has a texture.

use autodiff::{Real, Tape, Var};

use crate::error::RenderError;
use crate::scene::{self, Shading};
use crate::texture::{Filter, Sampler, Wrap};

use super::lights::{Lights, Material};
use super::phong::{shade, Surface};
use super::sh::sh_shade;

/// How a scene samples its texture: bilinear filtering of level 0 with repeat wrapping.
///
/// Not trilinear: the mip level of detail depends on the vertex positions and the camera
/// through the rasterizer's screen-space barycentric derivatives, which are fixed data of the
/// rasterization (see [`super::shader`]), so under minification trilinear gradients with
/// respect to positions and camera would miss that term. Bilinear keeps `tapestry grad`
/// exact; shaders that want mip-mapping call [`super::FragmentInputs::sample`] with a
/// trilinear [`crate::texture::Texture`].
pub const SCENE_SAMPLER: Sampler = Sampler {
    filter: Filter::Bilinear,
    wrap: Wrap::Repeat,
};

/// The constant lights and material of a scene, on a tape.
#[derive(Clone, Debug)]
pub struct SceneShading<'t, T: Real> {
    /// The shading model.
    pub shading: Shading,
    /// The scene's lights.
    pub lights: Lights<'t, T>,
    /// The reflection model (`lambert`, `phong`, `blinn_phong`; `None` otherwise).
    pub material: Option<Material<'t, T>>,
}

impl<'t, T: Real> SceneShading<'t, T> {
    /// The lights and material of a scene description, as constants on `tape`.
    pub fn new(tape: &'t Tape<T>, material: &scene::Material, lights: &[scene::Light]) -> Self {
        SceneShading {
            shading: material.shading,
            lights: Lights::from_scene(tape, lights),
            material: Material::from_scene(tape, material),
        }
    }

    /// The lights and material of a scene description with the light parameters taken from
    /// `rows` `[n, 3]` (layout of [`super::lights::scene_light_rows`]), on `rows`' tape.
    pub fn with_light_rows(
        material: &scene::Material,
        lights: &[scene::Light],
        rows: Var<'t, T>,
    ) -> Self {
        SceneShading {
            shading: material.shading,
            lights: Lights::from_scene_rows(lights, rows),
            material: Material::from_scene(rows.tape(), material),
        }
    }

    /// Whether the colour depends on normals and lights (`shading` other than `none`).
    pub fn is_lit(&self) -> bool {
        self.shading != Shading::None
    }

    /// Colours `[N, 3]` of `N` surface points (fragments or vertices): world positions
    /// `[N, 3]`, normals `[N, 3]` (any length, normalised inside), albedo `[N, 3]` or `[3]`,
    /// seen from `eye` `[3]`; `visibility` `[N, L]` shadows the directional and point lights
    /// ([`Surface::visibility`]; SH lighting is unshadowed).
    pub fn apply(
        &self,
        position: Var<'t, T>,
        normal: Var<'t, T>,
        albedo: Var<'t, T>,
        eye: Var<'t, T>,
        visibility: Option<Var<'t, T>>,
    ) -> Result<Var<'t, T>, RenderError> {
        let out = match self.shading {
            Shading::None => albedo,
            Shading::Lambert | Shading::Phong | Shading::BlinnPhong => {
                let m = self.material.as_ref().ok_or_else(|| {
                    RenderError::Unsupported(format!(
                        "material.shading '{:?}' has no reflection model",
                        self.shading
                    ))
                })?;
                let surface = Surface {
                    position,
                    normal,
                    albedo,
                    visibility,
                };
                shade(&surface, m, &self.lights, eye.reshape(&[3]))
            }
            Shading::Sh => {
                let sh = self.lights.sh.ok_or_else(|| {
                    RenderError::Unsupported(
                        "material.shading 'sh' needs a light of type 'sh'".into(),
                    )
                })?;
                sh_shade(normal, albedo, sh.coeffs)
            }
        };
        // Surface shape errors here, naming the op.
        out.value()?;
        Ok(out)
    }
}

/// The RGB albedo factor of a texture sample `[N, C]`: grey (`C = 1`, or grey + alpha) is
/// used for all three channels, RGB as is, the alpha of RGBA is ignored.
pub fn texture_rgb<'t, T: Real>(sample: Var<'t, T>) -> Result<Var<'t, T>, RenderError> {
    let s = sample.value()?.shape().to_vec();
    match s.get(1) {
        Some(1) | Some(3) => Ok(sample),
        Some(2) => Ok(sample.slice(1, 0, 1)),
        Some(4) => Ok(sample.slice(1, 0, 3)),
        _ => Err(RenderError::Unsupported(format!(
            "texture with shape {s:?}: 1 to 4 channels (grey, grey + alpha, RGB, RGBA) supported"
        ))),
    }
}
