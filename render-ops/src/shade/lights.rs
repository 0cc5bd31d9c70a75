//! Lights and materials as small tape variables, so that their parameters (directions,
//! colours, positions, SH coefficients, reflectances, shininess) can be optimised.
//!
//! Conventions (docs/CONVENTIONS.md): colours are linear RGB; a directional light's `direction` is
//! the direction the light *travels* (the surface is lit from `-direction`); a point light
//! shines equally in all directions without distance attenuation (as PyTorch3D's
//! `PointLights`); ambient lights add up; an SH light holds 9 rows of RGB coefficients.

use autodiff::{tensor, Real, Tape, Tensor, Var};

use crate::scene;

fn vec3<T: Real>(x: [f64; 3]) -> Tensor<T> {
    tensor::from_vec(&[3], x.iter().map(|&v| T::from_f64c(v)).collect()).expect("3 values")
}

/// Uniform ambient light.
#[derive(Clone, Copy, Debug)]
pub struct AmbientLight<'t, T: Real> {
    /// Linear RGB intensity `[3]`.
    pub color: Var<'t, T>,
}

/// Light from infinitely far away.
#[derive(Clone, Copy, Debug)]
pub struct DirectionalLight<'t, T: Real> {
    /// Direction the light travels `[3]` (need not be unit length).
    pub direction: Var<'t, T>,
    /// Linear RGB intensity `[3]`.
    pub color: Var<'t, T>,
}

/// Point light (no distance attenuation).
#[derive(Clone, Copy, Debug)]
pub struct PointLight<'t, T: Real> {
    /// World position `[3]`.
    pub position: Var<'t, T>,
    /// Linear RGB intensity `[3]`.
    pub color: Var<'t, T>,
}

/// Order-2 spherical-harmonics environment light: `[9, 3]` coefficients in the order and basis
/// of docs/CONVENTIONS.md (see [`super::sh`]).
#[derive(Clone, Copy, Debug)]
pub struct ShLight<'t, T: Real> {
    /// Coefficients `[9, 3]`.
    pub coeffs: Var<'t, T>,
}

impl<'t, T: Real> AmbientLight<'t, T> {
    /// A constant (non-optimised) ambient light.
    pub fn constant(tape: &'t Tape<T>, color: [f64; 3]) -> Self {
        AmbientLight {
            color: tape.constant(vec3(color)),
        }
    }
}

impl<'t, T: Real> DirectionalLight<'t, T> {
    /// A constant directional light.
    pub fn constant(tape: &'t Tape<T>, direction: [f64; 3], color: [f64; 3]) -> Self {
        DirectionalLight {
            direction: tape.constant(vec3(direction)),
            color: tape.constant(vec3(color)),
        }
    }
}

impl<'t, T: Real> PointLight<'t, T> {
    /// A constant point light.
    pub fn constant(tape: &'t Tape<T>, position: [f64; 3], color: [f64; 3]) -> Self {
        PointLight {
            position: tape.constant(vec3(position)),
            color: tape.constant(vec3(color)),
        }
    }
}

impl<'t, T: Real> ShLight<'t, T> {
    /// A constant SH light from 9 rows of RGB.
    pub fn constant(tape: &'t Tape<T>, coeffs: &[[f64; 3]; 9]) -> Self {
        let data = coeffs.iter().flatten().map(|&v| T::from_f64c(v)).collect();
        ShLight {
            coeffs: tape.constant(tensor::from_vec(&[9, 3], data).expect("27 values")),
        }
    }
}

/// The lights of a scene, by kind.
#[derive(Clone, Debug, Default)]
pub struct Lights<'t, T: Real> {
    /// Ambient lights (their colours add up).
    pub ambient: Vec<AmbientLight<'t, T>>,
    /// Directional lights.
    pub directional: Vec<DirectionalLight<'t, T>>,
    /// Point lights.
    pub point: Vec<PointLight<'t, T>>,
    /// At most one SH light (used by the scene shading `sh`, through [`super::sh_shade`]).
    pub sh: Option<ShLight<'t, T>>,
}

impl<'t, T: Real> Lights<'t, T> {
    /// No lights.
    pub fn new() -> Self {
        Lights {
            ambient: Vec::new(),
            directional: Vec::new(),
            point: Vec::new(),
            sh: None,
        }
    }

    /// Adds an ambient light.
    pub fn with_ambient(mut self, l: AmbientLight<'t, T>) -> Self {
        self.ambient.push(l);
        self
    }

    /// Adds a directional light.
    pub fn with_directional(mut self, l: DirectionalLight<'t, T>) -> Self {
        self.directional.push(l);
        self
    }

    /// Adds a point light.
    pub fn with_point(mut self, l: PointLight<'t, T>) -> Self {
        self.point.push(l);
        self
    }

    /// Sets the SH light.
    pub fn with_sh(mut self, l: ShLight<'t, T>) -> Self {
        self.sh = Some(l);
        self
    }

    /// Constant lights from a scene description (`lights` of the scene JSON).
    pub fn from_scene(tape: &'t Tape<T>, lights: &[scene::Light]) -> Self {
        let mut out = Lights::new();
        for l in lights {
            match l {
                scene::Light::Ambient { color } => {
                    out.ambient.push(AmbientLight::constant(tape, *color))
                }
                scene::Light::Directional { direction, color } => out
                    .directional
                    .push(DirectionalLight::constant(tape, *direction, *color)),
                scene::Light::Point { position, color } => out
                    .point
                    .push(PointLight::constant(tape, *position, *color)),
                // Area lights are the ray tracer's (`crate::raytrace`); the scene refuses them
                // with the raster methods.
                scene::Light::Area { .. } => {}
                scene::Light::Sh { coeffs } => {
                    let mut c = [[0.0; 3]; 9];
                    for (dst, src) in c.iter_mut().zip(coeffs) {
                        *dst = *src;
                    }
                    out.sh = Some(ShLight::constant(tape, &c));
                }
            }
        }
        out
    }

    /// Lights of a scene description whose parameters are the rows of `rows` `[n, 3]`
    /// (see [`scene_light_rows`] for the row layout), so that gradients reach them.
    pub fn from_scene_rows(lights: &[scene::Light], rows: Var<'t, T>) -> Self {
        let mut out = Lights::new();
        let mut i = 0;
        let mut row = |n: usize| {
            let v = rows.slice(0, i, i + n);
            i += n;
            if n == 1 {
                v.reshape(&[3])
            } else {
                v
            }
        };
        for l in lights {
            match l {
                scene::Light::Ambient { .. } => out.ambient.push(AmbientLight { color: row(1) }),
                scene::Light::Directional { .. } => {
                    let direction = row(1);
                    out.directional.push(DirectionalLight {
                        direction,
                        color: row(1),
                    })
                }
                scene::Light::Point { .. } => {
                    let position = row(1);
                    out.point.push(PointLight {
                        position,
                        color: row(1),
                    })
                }
                scene::Light::Area { .. } => {
                    row(4);
                }
                scene::Light::Sh { .. } => out.sh = Some(ShLight { coeffs: row(9) }),
            }
        }
        out
    }
}

/// Every light parameter of a scene as rows of three numbers, in scene order: an ambient
/// light gives its `color`; a directional light its `direction`, then `color`; a point light
/// its `position`, then `color`; an area light its `corner`, `edge_u`, `edge_v`, `radiance`;
/// an SH light its 9 coefficient rows. This is the layout of the
/// scene input `lights` `[n, 3]` ([`crate::pipeline::SceneVars::lights`]).
pub fn scene_light_rows(lights: &[scene::Light]) -> Vec<[f64; 3]> {
    let mut out = Vec::new();
    for l in lights {
        match l {
            scene::Light::Ambient { color } => out.push(*color),
            scene::Light::Directional { direction, color } => {
                out.push(*direction);
                out.push(*color);
            }
            scene::Light::Point { position, color } => {
                out.push(*position);
                out.push(*color);
            }
            scene::Light::Area {
                corner,
                edge_u,
                edge_v,
                radiance,
            } => out.extend([*corner, *edge_u, *edge_v, *radiance]),
            scene::Light::Sh { coeffs } => out.extend(coeffs.iter().copied()),
        }
    }
    out
}

/// Which reflection model [`super::shade`] evaluates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Reflectance {
    /// Diffuse only (Lambert's cosine law).
    Lambert,
    /// Diffuse plus Phong (1975) specular, `(r . v)^s`.
    Phong,
    /// Diffuse plus Blinn (1977) specular, `(n . h)^s`.
    BlinnPhong,
}

/// Reflectances of a surface; the diffuse reflectance (albedo) is per fragment and given to
/// [`super::shade`] with the surface.
#[derive(Clone, Copy, Debug)]
pub struct Material<'t, T: Real> {
    /// Reflection model.
    pub model: Reflectance,
    /// Ambient reflectance `[3]` or `[N, 3]`; `None` means "the diffuse albedo" (the scene
    /// default).
    pub ka: Option<Var<'t, T>>,
    /// Specular reflectance `[3]` or `[N, 3]` (ignored by Lambert).
    pub ks: Var<'t, T>,
    /// Specular exponent, one element (ignored by Lambert). Values up to 1e4 are fine.
    pub shininess: Var<'t, T>,
}

impl<'t, T: Real> Material<'t, T> {
    /// A constant material: `ka = None` (albedo), the given `ks` and shininess.
    pub fn constant(tape: &'t Tape<T>, model: Reflectance, ks: [f64; 3], shininess: f64) -> Self {
        Material {
            model,
            ka: None,
            ks: tape.constant(vec3(ks)),
            shininess: tape.constant(tensor::scalar(T::from_f64c(shininess))),
        }
    }

    /// Lambert with the ambient reflectance equal to the albedo.
    pub fn lambert(tape: &'t Tape<T>) -> Self {
        Self::constant(tape, Reflectance::Lambert, [0.0; 3], 1.0)
    }

    /// Sets a separate ambient reflectance.
    pub fn with_ka(mut self, ka: Var<'t, T>) -> Self {
        self.ka = Some(ka);
        self
    }

    /// The constant material of a scene description; `None` for `shading` `none` and `sh`,
    /// which are not reflection models (use the albedo directly, or [`super::sh_shade`]).
    /// The scene's `kd` is not part of it: multiply it into the albedo.
    pub fn from_scene(tape: &'t Tape<T>, m: &scene::Material) -> Option<Self> {
        let model = match m.shading {
            scene::Shading::Lambert => Reflectance::Lambert,
            scene::Shading::Phong => Reflectance::Phong,
            scene::Shading::BlinnPhong => Reflectance::BlinnPhong,
            scene::Shading::None | scene::Shading::Sh => return None,
        };
        let mut out = Self::constant(tape, model, m.ks, m.shininess);
        out.ka = m.ka.map(|ka| tape.constant(vec3(ka)));
        Some(out)
    }
}
