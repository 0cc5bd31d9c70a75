//! The scene JSON of docs/CONVENTIONS.md: parsing (serde, unknown keys rejected everywhere), value
//! validation, and loading of the files it names.
//!
//! ```json
//! {
//!   "mesh": "sphere.obj",
//!   "texture": null,
//!   "camera": {"eye": [0, 0, 3], "at": [0, 0, 0], "up": [0, 1, 0],
//!              "fov_y_deg": 45, "near": 0.1, "far": 100},
//!   "image": {"width": 256, "height": 256, "background": [0, 0, 0]},
//!   "lights": [{"type": "directional", "direction": [0, 0, -1], "color": [1, 1, 1]},
//!              {"type": "ambient", "color": [0.2, 0.2, 0.2]}],
//!   "material": {"shading": "phong", "kd": [0.8, 0.8, 0.8], "ks": [0.2, 0.2, 0.2], "shininess": 32},
//!   "raster": {"method": "softras", "sigma": 1e-4, "gamma": 1e-4}
//! }
//! ```
//!
//! Required keys: `mesh`, `camera.eye`, `camera.at`, `camera.fov_y_deg`, `image.width`,
//! `image.height`. Everything else has a default (see each field's docs): `texture` null,
//! `camera.up` [0, 1, 0], `camera.near` 0.1, `camera.far` 100, `image.background` [0, 0, 0],
//! `lights` [], `material` {shading none, ka null, kd [1, 1, 1], ks [0.2, 0.2, 0.2],
//! shininess 32}, `raster` {method hard, faces_per_pixel null (1 for hard methods, every face
//! within the cut-off for soft ones), cull_backfaces false, perspective_correct true,
//! threshold 1e-4, sigma 1e-4, gamma 1e-4, eps 1e-3, delta 1/7000, overdraw_px 1.0}.
//!
//! Error messages name the key path, e.g.
//! ```text
//! scene.json: raster.method: unknown variant `soft`, expected one of `hard`, `tf_mesh`, ... at line 8 column 30
//! scene.json: lights[0].coeffs: expected 9 rows of [r, g, b] (bands l = 0, 1, 2), got 8
//! ```

use std::path::{Path, PathBuf};

use autodiff::Real;
use ndarray::Array3;
use serde::de::Error as _;
use serde::{Deserialize, Deserializer, Serialize};
use thiserror::Error;

use crate::camera::{Camera, CameraError};
use crate::io::{read_image, IoError};
use crate::mesh::Mesh;
use crate::obj::{load_obj, ObjError};

/// Errors of scene loading; `file` is the scene JSON (or `<string>`).
#[derive(Debug, Error)]
pub enum SceneError {
    /// The JSON file cannot be read.
    #[error("{}: cannot read scene file: {source}", .path.display())]
    Read {
        /// The JSON file.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// Malformed JSON, a wrong type, a missing or unknown key, an unknown enum value.
    #[error("{file}: {message}")]
    Json {
        /// The JSON file.
        file: String,
        /// serde's message prefixed with the key path, with line and column.
        message: String,
        /// 1-based line of the error (0 if unknown).
        line: usize,
        /// 1-based column of the error (0 if unknown).
        column: usize,
    },
    /// A well-typed but invalid value.
    #[error("{file}: {key}: {message}")]
    Invalid {
        /// The JSON file.
        file: String,
        /// Key path, e.g. `raster.sigma` or `lights[2].coeffs`.
        key: String,
        /// What is wrong and what is allowed.
        message: String,
    },
    /// The mesh file cannot be loaded.
    #[error("{file}: mesh: {source}")]
    Mesh {
        /// The JSON file.
        file: String,
        /// The OBJ error (naming the OBJ file and line).
        source: ObjError,
    },
    /// The texture file cannot be loaded.
    #[error("{file}: texture: {source}")]
    Texture {
        /// The JSON file.
        file: String,
        /// The image error (naming the image file).
        source: IoError,
    },
}

// ---------------------------------------------------------------------------------------------
// Key paths in serde messages.

/// Drops serde_json's trailing " at line L column C" (re-added once at the outermost level).
fn strip_position(msg: &str) -> &str {
    if let Some(i) = msg.rfind(" at line ") {
        let mut parts = msg[i + " at line ".len()..].split(" column ");
        let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
        if let (Some(l), Some(c), None) = (parts.next(), parts.next(), parts.next()) {
            if digits(l) && digits(c) {
                return &msg[..i];
            }
        }
    }
    msg
}

/// `key` + message: `camera` + `.eye: bad` = `camera.eye: bad`; `camera` + `bad` = `camera: bad`.
fn keyed(key: &str, msg: &str) -> String {
    let msg = strip_position(msg);
    if msg.starts_with('.') || msg.starts_with('[') {
        format!("{key}{msg}")
    } else {
        format!("{key}: {msg}")
    }
}

/// Defines `fn $name(d) -> Result<$ty, _>` that deserializes `$ty` and prefixes errors with
/// `$key` (nested keys start with a dot).
macro_rules! keyed_de {
    ($($name:ident: $ty:ty = $key:literal;)*) => {$(
        fn $name<'de, D: Deserializer<'de>>(d: D) -> Result<$ty, D::Error> {
            <$ty as Deserialize>::deserialize(d).map_err(|e| D::Error::custom(keyed($key, &e.to_string())))
        }
    )*};
}

keyed_de! {
    de_mesh: PathBuf = "mesh";
    de_texture: Option<PathBuf> = "texture";
    de_camera: CameraDesc = "camera";
    de_image: ImageDesc = "image";
    de_material: Material = "material";
    de_raster: Raster = "raster";
    de_eye: [f64; 3] = ".eye";
    de_at: [f64; 3] = ".at";
    de_up: [f64; 3] = ".up";
    de_fov: f64 = ".fov_y_deg";
    de_near: f64 = ".near";
    de_far: f64 = ".far";
    de_width: u32 = ".width";
    de_height: u32 = ".height";
    de_background: [f64; 3] = ".background";
    de_color: [f64; 3] = ".color";
    de_direction: [f64; 3] = ".direction";
    de_position: [f64; 3] = ".position";
    de_coeffs: Vec<[f64; 3]> = ".coeffs";
    de_shading: Shading = ".shading";
    de_ka: Option<[f64; 3]> = ".ka";
    de_kd: [f64; 3] = ".kd";
    de_ks: [f64; 3] = ".ks";
    de_shininess: f64 = ".shininess";
    de_method: Method = ".method";
    de_fpp: Option<u32> = ".faces_per_pixel";
    de_cull: bool = ".cull_backfaces";
    de_persp: bool = ".perspective_correct";
    de_threshold: f64 = ".threshold";
    de_sigma: f64 = ".sigma";
    de_gamma: f64 = ".gamma";
    de_eps: f64 = ".eps";
    de_delta: f64 = ".delta";
    de_overdraw: f64 = ".overdraw_px";
    de_spp: u32 = ".spp";
    de_seed: u64 = ".seed";
    de_edge_samples: Option<u32> = ".edge_samples";
    de_shadow_edge_samples: Option<u32> = ".shadow_edge_samples";
    de_area_edge_samples: u32 = ".area_edge_samples";
    de_corner: [f64; 3] = ".corner";
    de_edge_u: [f64; 3] = ".edge_u";
    de_edge_v: [f64; 3] = ".edge_v";
    de_radiance: [f64; 3] = ".radiance";
}

/// `lights`: each element on its own so that errors say which (`lights[2].color: ...`).
fn de_lights<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Light>, D::Error> {
    let values = Vec::<serde_json::Value>::deserialize(d)
        .map_err(|e| D::Error::custom(keyed("lights", &e.to_string())))?;
    values
        .into_iter()
        .enumerate()
        .map(|(i, v)| {
            serde_json::from_value::<Light>(v)
                .map_err(|e| D::Error::custom(keyed(&format!("lights[{i}]"), &e.to_string())))
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// The description.

/// A parsed scene JSON (paths as written, not yet resolved).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneDesc {
    /// OBJ file, relative to the JSON file's folder unless absolute.
    #[serde(deserialize_with = "de_mesh")]
    pub mesh: PathBuf,
    /// Texture image (`.png`, or `.npy` `[H, W, C]`), or null (default).
    #[serde(default, deserialize_with = "de_texture")]
    pub texture: Option<PathBuf>,
    /// The camera.
    #[serde(deserialize_with = "de_camera")]
    pub camera: CameraDesc,
    /// Output image size and background.
    #[serde(deserialize_with = "de_image")]
    pub image: ImageDesc,
    /// Lights (default none).
    #[serde(default, deserialize_with = "de_lights")]
    pub lights: Vec<Light>,
    /// Shading model and reflectances (default: shading none).
    #[serde(default, deserialize_with = "de_material")]
    pub material: Material,
    /// Rasterization method and its settings (default: hard).
    #[serde(default, deserialize_with = "de_raster")]
    pub raster: Raster,
}

fn default_up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}
fn default_near() -> f64 {
    0.1
}
fn default_far() -> f64 {
    100.0
}

/// `camera`: a look-at camera with an OpenGL perspective projection.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraDesc {
    /// Eye position (world).
    #[serde(deserialize_with = "de_eye")]
    pub eye: [f64; 3],
    /// Point looked at (world).
    #[serde(deserialize_with = "de_at")]
    pub at: [f64; 3],
    /// Up direction (default [0, 1, 0]); must not be parallel to `at - eye`.
    #[serde(default = "default_up", deserialize_with = "de_up")]
    pub up: [f64; 3],
    /// Vertical field of view in degrees, in (0, 180).
    #[serde(deserialize_with = "de_fov")]
    pub fov_y_deg: f64,
    /// Near plane distance, > 0 (default 0.1).
    #[serde(default = "default_near", deserialize_with = "de_near")]
    pub near: f64,
    /// Far plane distance, > near (default 100).
    #[serde(default = "default_far", deserialize_with = "de_far")]
    pub far: f64,
}

/// `image`: output size in pixels and background colour.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageDesc {
    /// Width in pixels, 1 to 65536.
    #[serde(deserialize_with = "de_width")]
    pub width: u32,
    /// Height in pixels, 1 to 65536.
    #[serde(deserialize_with = "de_height")]
    pub height: u32,
    /// Linear RGB background (default black).
    #[serde(default, deserialize_with = "de_background")]
    pub background: [f64; 3],
}

/// A light, tagged by `"type"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Light {
    /// Uniform ambient light.
    Ambient {
        /// Linear RGB intensity, >= 0.
        #[serde(deserialize_with = "de_color")]
        color: [f64; 3],
    },
    /// Light from infinitely far away.
    Directional {
        /// Direction the light travels (world, non-zero; need not be unit length).
        #[serde(deserialize_with = "de_direction")]
        direction: [f64; 3],
        /// Linear RGB intensity, >= 0.
        #[serde(deserialize_with = "de_color")]
        color: [f64; 3],
    },
    /// Point light.
    Point {
        /// Position (world).
        #[serde(deserialize_with = "de_position")]
        position: [f64; 3],
        /// Linear RGB intensity, >= 0.
        #[serde(deserialize_with = "de_color")]
        color: [f64; 3],
    },
    /// A parallelogram emitter `corner + a edge_u + b edge_v` (`a`, `b` in [0, 1]) of
    /// uniform radiance, emitting from the side of `edge_u x edge_v`; used by the `raytrace`
    /// method (sampled by area, soft shadows), refused by the raster methods. Falloff: see
    /// docs/CONVENTIONS.md.
    Area {
        /// One corner (world).
        #[serde(deserialize_with = "de_corner")]
        corner: [f64; 3],
        /// First edge from the corner (world).
        #[serde(deserialize_with = "de_edge_u")]
        edge_u: [f64; 3],
        /// Second edge from the corner (world), not parallel to `edge_u`.
        #[serde(deserialize_with = "de_edge_v")]
        edge_v: [f64; 3],
        /// Linear RGB radiance, >= 0.
        #[serde(deserialize_with = "de_radiance")]
        radiance: [f64; 3],
    },
    /// Order-2 spherical-harmonics lighting: 9 rows of [r, g, b] in the order and basis of
    /// docs/CONVENTIONS.md.
    Sh {
        /// Exactly 9 rows.
        #[serde(deserialize_with = "de_coeffs")]
        coeffs: Vec<[f64; 3]>,
    },
}

impl Light {
    /// The `type` tag.
    pub fn kind(&self) -> &'static str {
        match self {
            Light::Ambient { .. } => "ambient",
            Light::Directional { .. } => "directional",
            Light::Point { .. } => "point",
            Light::Area { .. } => "area",
            Light::Sh { .. } => "sh",
        }
    }
}

/// `material.shading`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Shading {
    /// Vertex colours or texture only, unlit (default).
    #[default]
    None,
    /// Diffuse.
    Lambert,
    /// Diffuse + Phong specular.
    Phong,
    /// Diffuse + Blinn-Phong specular.
    BlinnPhong,
    /// Spherical harmonics (needs a light of type `sh`).
    Sh,
}

fn default_kd() -> [f64; 3] {
    [1.0; 3]
}
fn default_ks() -> [f64; 3] {
    [0.2; 3]
}
fn default_shininess() -> f64 {
    32.0
}

/// `material`: reflectances (linear RGB, >= 0) and shading model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// Shading model (default `none`).
    #[serde(default, deserialize_with = "de_shading")]
    pub shading: Shading,
    /// Ambient reflectance; null (default) means "same as the diffuse albedo".
    #[serde(default, deserialize_with = "de_ka")]
    pub ka: Option<[f64; 3]>,
    /// Diffuse reflectance, multiplying the vertex colours / texture when present
    /// (default [1, 1, 1]).
    #[serde(default = "default_kd", deserialize_with = "de_kd")]
    pub kd: [f64; 3],
    /// Specular reflectance (default [0.2, 0.2, 0.2]).
    #[serde(default = "default_ks", deserialize_with = "de_ks")]
    pub ks: [f64; 3],
    /// Specular exponent, >= 0 (default 32).
    #[serde(default = "default_shininess", deserialize_with = "de_shininess")]
    pub shininess: f64,
}

impl Default for Material {
    fn default() -> Self {
        Material {
            shading: Shading::None,
            ka: None,
            kd: default_kd(),
            ks: default_ks(),
            shininess: default_shininess(),
        }
    }
}

/// `raster.method`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub enum Method {
    /// Z-buffer, gradients of interior barycentrics only (default).
    #[default]
    #[serde(rename = "hard")]
    Hard,
    /// TF Mesh Renderer: barycentric extrapolation.
    #[serde(rename = "tf_mesh")]
    TfMesh,
    /// OpenDR: image-space derivative approximation.
    #[serde(rename = "opendr")]
    OpenDr,
    /// Neural Mesh Renderer (Kato et al.).
    #[serde(rename = "nmr")]
    Nmr,
    /// Soft Rasterizer (Liu et al.).
    #[serde(rename = "softras")]
    SoftRas,
    /// DIB-R (Chen et al.).
    #[serde(rename = "dibr")]
    Dibr,
    /// DEODR: discontinuity edge overdraw (de La Gorce et al.).
    #[serde(rename = "deodr")]
    Deodr,
    /// Exact area sampling: the visible area of every face in each pixel (Catmull 1978).
    #[serde(rename = "analytic")]
    Analytic,

    /// Ray tracing with edge sampling (Li et al. 2018): shadows and their gradients.
    #[serde(rename = "raytrace")]
    Raytrace,
}

impl Method {
    /// The eight raster methods, in the order of docs/CONVENTIONS.md (the registry's tests,
    /// benches and face fits iterate these; [`Method::Raytrace`] renders whole scenes, see
    /// [`Method::RAY`]).
    pub const ALL: [Method; 8] = [
        Method::Hard,
        Method::TfMesh,
        Method::OpenDr,
        Method::Nmr,
        Method::SoftRas,
        Method::Dibr,
        Method::Deodr,
        Method::Analytic,
    ];

    /// The ray-traced methods.
    pub const RAY: [Method; 1] = [Method::Raytrace];

    /// The JSON name.
    pub fn name(self) -> &'static str {
        match self {
            Method::Hard => "hard",
            Method::TfMesh => "tf_mesh",
            Method::OpenDr => "opendr",
            Method::Nmr => "nmr",
            Method::SoftRas => "softras",
            Method::Dibr => "dibr",
            Method::Deodr => "deodr",
            Method::Raytrace => "raytrace",
            Method::Analytic => "analytic",
        }
    }

    /// Parses a JSON name (e.g. from a command line).
    pub fn from_name(name: &str) -> Option<Method> {
        Method::ALL
            .into_iter()
            .chain(Method::RAY)
            .find(|m| m.name() == name)
    }

    /// Soft methods (softras, dibr) aggregate every face within their cut-off per pixel; the
    /// others keep the front-most face.
    pub fn is_soft(self) -> bool {
        matches!(self, Method::SoftRas | Method::Dibr)
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Default DIB-R `delta` (squared NDC units): Kaolin's DIB-R default `sigmainv = 7000`
/// (recommended `1/sigmainv` in [3e-5, 3e-4]).
pub const DEFAULT_DIBR_DELTA: f64 = 1.0 / 7000.0;

/// `raster`: method and settings, each optional with the default shown (docs/CONVENTIONS.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Raster {
    /// Method (default `hard`).
    #[serde(deserialize_with = "de_method")]
    pub method: Method,
    /// Faces kept per pixel, >= 1; null (default) means 1 for hard methods and every face within
    /// the cut-off for soft ones (see [`Raster::effective_faces_per_pixel`]).
    #[serde(deserialize_with = "de_fpp")]
    pub faces_per_pixel: Option<u32>,
    /// Back-face culling (default false).
    #[serde(deserialize_with = "de_cull")]
    pub cull_backfaces: bool,
    /// Perspective-correct attribute interpolation (default true).
    #[serde(deserialize_with = "de_persp")]
    pub perspective_correct: bool,
    /// Coverage below which softras/dibr ignore a face (fixes the cut-off distance), in (0, 1),
    /// default 1e-4.
    #[serde(deserialize_with = "de_threshold")]
    pub threshold: f64,
    /// SoftRas sigma, squared NDC distance, > 0 (default 1e-4).
    #[serde(deserialize_with = "de_sigma")]
    pub sigma: f64,
    /// SoftRas gamma, `z01` units, > 0 (default 1e-4).
    #[serde(deserialize_with = "de_gamma")]
    pub gamma: f64,
    /// SoftRas background term epsilon (default 1e-3).
    #[serde(deserialize_with = "de_eps")]
    pub eps: f64,
    /// DIB-R delta, squared NDC distance, > 0 (default [`DEFAULT_DIBR_DELTA`] = 1/7000).
    #[serde(deserialize_with = "de_delta")]
    pub delta: f64,
    /// DEODR edge overdraw ramp width in pixels, >= 0 (default 1.0).
    #[serde(deserialize_with = "de_overdraw")]
    pub overdraw_px: f64,
    /// `raytrace`: samples per pixel, >= 1 (default 4).
    #[serde(deserialize_with = "de_spp")]
    pub spp: u32,
    /// `raytrace`: seed of the random numbers (default 0).
    #[serde(deserialize_with = "de_seed")]
    pub seed: u64,
    /// `raytrace`: primary (silhouette) edge samples per gradient; null (default): one per
    /// pixel.
    #[serde(deserialize_with = "de_edge_samples")]
    pub edge_samples: Option<u32>,
    /// `raytrace`: shadow-edge samples of point and directional lights per gradient; null
    /// (default): one per pixel.
    #[serde(deserialize_with = "de_shadow_edge_samples")]
    pub shadow_edge_samples: Option<u32>,
    /// `raytrace`: area-light edge samples per pixel sample and area light (default 1).
    #[serde(deserialize_with = "de_area_edge_samples")]
    pub area_edge_samples: u32,
}

impl Default for Raster {
    fn default() -> Self {
        Raster {
            method: Method::Hard,
            faces_per_pixel: None,
            cull_backfaces: false,
            perspective_correct: true,
            threshold: 1e-4,
            sigma: 1e-4,
            gamma: 1e-4,
            eps: 1e-3,
            delta: DEFAULT_DIBR_DELTA,
            overdraw_px: 1.0,
            spp: 4,
            seed: 0,
            edge_samples: None,
            shadow_edge_samples: None,
            area_edge_samples: 1,
        }
    }
}

impl Raster {
    /// Defaults with the given method.
    pub fn with_method(method: Method) -> Self {
        Raster {
            method,
            ..Default::default()
        }
    }

    /// Faces kept per pixel: the explicit value, else `Some(1)` for hard methods and `None`
    /// ("every face within the cut-off") for soft ones.
    pub fn effective_faces_per_pixel(&self) -> Option<u32> {
        match self.faces_per_pixel {
            Some(k) => Some(k),
            None if self.method.is_soft() => None,
            None => Some(1),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Validation.

struct Checker<'a> {
    file: &'a str,
}

impl Checker<'_> {
    fn fail(&self, key: impl Into<String>, message: impl Into<String>) -> SceneError {
        SceneError::Invalid {
            file: self.file.to_string(),
            key: key.into(),
            message: message.into(),
        }
    }

    fn finite(&self, key: &str, v: &[f64]) -> Result<(), SceneError> {
        if v.iter().all(|x| x.is_finite()) {
            Ok(())
        } else {
            Err(self.fail(key, format!("{v:?} must be finite")))
        }
    }

    fn non_negative(&self, key: &str, v: &[f64]) -> Result<(), SceneError> {
        if v.iter().all(|x| x.is_finite() && *x >= 0.0) {
            Ok(())
        } else {
            Err(self.fail(key, format!("{v:?} must be finite and >= 0")))
        }
    }

    fn positive(&self, key: &str, v: f64) -> Result<(), SceneError> {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(self.fail(key, format!("{v} must be finite and > 0")))
        }
    }
}

impl SceneDesc {
    /// Parses scene JSON text (no validation beyond types; see [`SceneDesc::validate`]).
    /// `file` names the source in errors.
    pub fn parse(text: &str, file: &str) -> Result<SceneDesc, SceneError> {
        serde_json::from_str(text).map_err(|e| {
            let msg = e.to_string();
            let msg = msg.strip_prefix('.').unwrap_or(&msg).to_string();
            SceneError::Json {
                file: file.to_string(),
                message: msg,
                line: e.line(),
                column: e.column(),
            }
        })
    }

    /// Serialises to pretty JSON (parses back to an equal description).
    pub fn to_json_pretty(&self) -> String {
        serde_json::to_string_pretty(self).expect("scene descriptions serialise")
    }

    /// Checks the values; errors name the key and what is allowed (`file` names the source):
    /// - `image`: width and height 1 to 65536, finite background;
    /// - `camera`: finite, `fov_y_deg` in (0, 180), `near > 0`, `far > near`, `eye != at`,
    ///   `up` not parallel to the view direction;
    /// - `lights`: colours finite and non-negative, directional directions non-zero, `sh`
    ///   coeffs exactly 9 rows of [r, g, b];
    /// - `material`: reflectances and shininess finite and non-negative, `shading: sh` only
    ///   with an `sh` light;
    /// - `raster`: `faces_per_pixel` at least 1 (or null), `threshold` in (0, 1), `sigma`,
    ///   `gamma` and `delta` positive, `eps` finite, `overdraw_px` non-negative.
    pub fn validate(&self, file: &str) -> Result<(), SceneError> {
        let c = Checker { file };
        for (key, v) in [
            ("image.width", self.image.width),
            ("image.height", self.image.height),
        ] {
            if !(1..=65536).contains(&v) {
                return Err(c.fail(key, format!("{v} must be between 1 and 65536")));
            }
        }
        c.finite("image.background", &self.image.background)?;

        let cam = &self.camera;
        c.finite("camera.eye", &cam.eye)?;
        c.finite("camera.at", &cam.at)?;
        c.finite("camera.up", &cam.up)?;
        if !(cam.fov_y_deg > 0.0 && cam.fov_y_deg < 180.0) {
            return Err(c.fail(
                "camera.fov_y_deg",
                format!(
                    "{} must lie strictly between 0 and 180 (degrees)",
                    cam.fov_y_deg
                ),
            ));
        }
        c.positive("camera.near", cam.near)?;
        if !(cam.far.is_finite() && cam.far > cam.near) {
            return Err(c.fail(
                "camera.far",
                format!(
                    "{} must be finite and greater than near = {}",
                    cam.far, cam.near
                ),
            ));
        }
        if let Err(e) = self.camera() {
            let key = match e {
                CameraError::EyeEqualsAt { .. } => "camera.at",
                CameraError::UpParallel { .. } => "camera.up",
                _ => "camera",
            };
            let msg = e.to_string();
            return Err(c.fail(key, msg.strip_prefix("camera: ").unwrap_or(&msg)));
        }

        let mut has_sh = false;
        for (i, light) in self.lights.iter().enumerate() {
            let key = |field: &str| format!("lights[{i}].{field}");
            match light {
                Light::Ambient { color } => c.non_negative(&key("color"), color)?,
                Light::Directional { direction, color } => {
                    c.finite(&key("direction"), direction)?;
                    if direction.iter().all(|&x| x == 0.0) {
                        return Err(c.fail(key("direction"), "must not be the zero vector"));
                    }
                    c.non_negative(&key("color"), color)?;
                }
                Light::Point { position, color } => {
                    c.finite(&key("position"), position)?;
                    c.non_negative(&key("color"), color)?;
                }
                Light::Area {
                    corner,
                    edge_u,
                    edge_v,
                    radiance,
                } => {
                    c.finite(&key("corner"), corner)?;
                    c.finite(&key("edge_u"), edge_u)?;
                    c.finite(&key("edge_v"), edge_v)?;
                    c.non_negative(&key("radiance"), radiance)?;
                    let n = [
                        edge_u[1] * edge_v[2] - edge_u[2] * edge_v[1],
                        edge_u[2] * edge_v[0] - edge_u[0] * edge_v[2],
                        edge_u[0] * edge_v[1] - edge_u[1] * edge_v[0],
                    ];
                    if n.iter().all(|&x| x == 0.0) {
                        return Err(c.fail(
                            key("edge_v"),
                            "must not be parallel to edge_u (the light has no area)",
                        ));
                    }
                }
                Light::Sh { coeffs } => {
                    has_sh = true;
                    if coeffs.len() != 9 {
                        return Err(c.fail(
                            key("coeffs"),
                            format!(
                                "expected 9 rows of [r, g, b] (bands l = 0, 1, 2), got {}",
                                coeffs.len()
                            ),
                        ));
                    }
                    for (k, row) in coeffs.iter().enumerate() {
                        c.finite(&format!("lights[{i}].coeffs[{k}]"), row)?;
                    }
                }
            }
        }

        let m = &self.material;
        if let Some(ka) = &m.ka {
            c.non_negative("material.ka", ka)?;
        }
        c.non_negative("material.kd", &m.kd)?;
        c.non_negative("material.ks", &m.ks)?;
        c.non_negative("material.shininess", &[m.shininess])?;
        if m.shading == Shading::Sh && !has_sh {
            return Err(c.fail(
                "material.shading",
                "'sh' needs a light {\"type\": \"sh\", \"coeffs\": [9 rows of [r, g, b]]}",
            ));
        }

        let r = &self.raster;
        if r.faces_per_pixel == Some(0) {
            return Err(c.fail(
                "raster.faces_per_pixel",
                "0 must be >= 1 (or null for the method's default)",
            ));
        }
        if !(r.threshold > 0.0 && r.threshold < 1.0) {
            return Err(c.fail(
                "raster.threshold",
                format!("{} must lie strictly between 0 and 1", r.threshold),
            ));
        }
        c.positive("raster.sigma", r.sigma)?;
        c.positive("raster.gamma", r.gamma)?;
        c.finite("raster.eps", &[r.eps])?;
        c.positive("raster.delta", r.delta)?;
        c.non_negative("raster.overdraw_px", &[r.overdraw_px])?;
        if r.spp == 0 || r.spp > 65536 {
            return Err(c.fail("raster.spp", format!("{} must be 1 to 65536", r.spp)));
        }
        if r.method != Method::Raytrace {
            if let Some(i) = self.lights.iter().position(|l| l.kind() == "area") {
                return Err(c.fail(
                    format!("lights[{i}]"),
                    format!(
                        "area lights need raster.method 'raytrace' (got '{}')",
                        r.method
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The camera: `look_at(eye, at, up)` and `perspective(fov_y_deg in radians,
    /// width / height, near, far)`.
    pub fn camera(&self) -> Result<Camera, CameraError> {
        let cam = &self.camera;
        Camera::perspective_look_at(
            cam.eye,
            cam.at,
            cam.up,
            cam.fov_y_deg.to_radians(),
            self.image.width as f64 / self.image.height as f64,
            cam.near,
            cam.far,
        )
    }

    /// The mesh path resolved against `base` (the JSON file's folder) unless absolute.
    pub fn mesh_path(&self, base: &Path) -> PathBuf {
        base.join(&self.mesh)
    }

    /// The texture path resolved against `base`, if any.
    pub fn texture_path(&self, base: &Path) -> Option<PathBuf> {
        self.texture.as_ref().map(|t| base.join(t))
    }
}

/// A loaded, validated scene.
#[derive(Debug, Clone)]
pub struct Scene<T: Real> {
    /// The JSON file (or `<string>`).
    pub source: String,
    /// The description as parsed.
    pub desc: SceneDesc,
    /// Resolved mesh path.
    pub mesh_path: PathBuf,
    /// Resolved texture path.
    pub texture_path: Option<PathBuf>,
    /// The mesh (vertex order of the OBJ file).
    pub mesh: Mesh<T>,
    /// The texture `[H, W, C]`, values in [0, 1] for PNG.
    pub texture: Option<Array3<T>>,
    /// The camera of `desc.camera` at the image's aspect ratio.
    pub camera: Camera,
}

impl<T: Real> Scene<T> {
    /// Reads, parses and validates a scene JSON, then loads its mesh (and texture) with paths
    /// resolved against the JSON file's folder.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, SceneError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new(""));
        Self::from_json(&text, base, &path.display().to_string())
    }

    /// [`Scene::load`] on JSON text; relative paths resolve against `base`; `file` names the
    /// source in errors.
    pub fn from_json(text: &str, base: &Path, file: &str) -> Result<Self, SceneError> {
        let desc = SceneDesc::parse(text, file)?;
        Self::from_desc(desc, base, file)
    }

    /// Validates a description and loads its files (relative paths against `base`).
    pub fn from_desc(desc: SceneDesc, base: &Path, file: &str) -> Result<Self, SceneError> {
        desc.validate(file)?;
        let camera = desc.camera().map_err(|e| SceneError::Invalid {
            file: file.to_string(),
            key: "camera".into(),
            message: e.to_string(),
        })?;
        let mesh_path = desc.mesh_path(base);
        let mesh = load_obj::<T>(&mesh_path).map_err(|source| SceneError::Mesh {
            file: file.to_string(),
            source,
        })?;
        let texture_path = desc.texture_path(base);
        let texture = match &texture_path {
            Some(p) => Some(read_image::<T>(p).map_err(|source| SceneError::Texture {
                file: file.to_string(),
                source,
            })?),
            None => None,
        };
        Ok(Scene {
            source: file.to_string(),
            desc,
            mesh_path,
            texture_path,
            mesh,
            texture,
            camera,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: &str = r#"{"mesh": "m.obj", "camera": {"eye": [0, 0, 3], "at": [0, 0, 0], "fov_y_deg": 45},
        "image": {"width": 4, "height": 2}}"#;

    fn parse_err(text: &str) -> String {
        match SceneDesc::parse(text, "s.json") {
            Err(e @ SceneError::Json { .. }) => e.to_string(),
            other => panic!("expected a JSON error, got {other:?}"),
        }
    }

    fn invalid(text: &str) -> (String, String) {
        let d = SceneDesc::parse(text, "s.json").unwrap();
        match d.validate("s.json") {
            Err(SceneError::Invalid { key, message, .. }) => (key, message),
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    /// `MIN` with `"key": value` set at the top level (`section` empty) or in a section.
    fn with(section: &str, entry: &str) -> String {
        let mut v: serde_json::Value = serde_json::from_str(MIN).unwrap();
        let add: serde_json::Map<String, serde_json::Value> =
            serde_json::from_str(&format!("{{{entry}}}")).unwrap();
        let top = v.as_object_mut().unwrap();
        let target = if section.is_empty() {
            top
        } else {
            top.entry(section)
                .or_insert_with(|| serde_json::json!({}))
                .as_object_mut()
                .unwrap()
        };
        target.extend(add);
        serde_json::to_string_pretty(&v).unwrap()
    }

    #[test]
    fn minimal_scene_gets_the_documented_defaults() {
        let d = SceneDesc::parse(MIN, "s.json").unwrap();
        d.validate("s.json").unwrap();
        assert_eq!(d.texture, None);
        assert_eq!(d.camera.up, [0.0, 1.0, 0.0]);
        assert_eq!((d.camera.near, d.camera.far), (0.1, 100.0));
        assert_eq!(d.image.background, [0.0; 3]);
        assert!(d.lights.is_empty());
        assert_eq!(d.material, Material::default());
        assert_eq!(d.material.shading, Shading::None);
        assert_eq!(d.raster, Raster::default());
        assert_eq!(d.raster.effective_faces_per_pixel(), Some(1));
        assert_eq!(
            Raster::with_method(Method::SoftRas).effective_faces_per_pixel(),
            None
        );
        assert_eq!(d.raster.delta, 1.0 / 7000.0);
        let cam = d.camera().unwrap();
        assert!((cam.proj_rows()[1][1] * 2.0 - cam.proj_rows()[0][0] * 4.0).abs() < 1e-12);
        // Round trip through serialisation.
        assert_eq!(SceneDesc::parse(&d.to_json_pretty(), "x").unwrap(), d);
    }

    #[test]
    fn full_scene_parses() {
        let text = r#"{
          "mesh": "sphere.obj", "texture": "tex.png",
          "camera": {"eye": [0, 0, 3], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 45, "near": 0.1, "far": 100},
          "image": {"width": 256, "height": 128, "background": [0.1, 0.2, 0.3]},
          "lights": [{"type": "directional", "direction": [0, 0, -1], "color": [1, 1, 1]},
                     {"type": "ambient", "color": [0.2, 0.2, 0.2]},
                     {"type": "point", "position": [1, 2, 3], "color": [5, 5, 5]},
                     {"type": "sh", "coeffs": [[1,1,1],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0.5,0.5,-0.5]]}],
          "material": {"shading": "blinn_phong", "ka": [0.1, 0.1, 0.1], "kd": [0.8, 0.8, 0.8], "ks": [0.2, 0.2, 0.2], "shininess": 32},
          "raster": {"method": "dibr", "faces_per_pixel": 8, "cull_backfaces": true, "perspective_correct": false,
                     "threshold": 1e-3, "sigma": 2e-4, "gamma": 3e-4, "eps": 1e-2, "delta": 5e-5, "overdraw_px": 0.5}
        }"#;
        let d = SceneDesc::parse(text, "s.json").unwrap();
        d.validate("s.json").unwrap();
        assert_eq!(
            d.texture_path(Path::new("/base")),
            Some(PathBuf::from("/base/tex.png"))
        );
        assert_eq!(d.lights.len(), 4);
        assert_eq!(
            d.lights[2],
            Light::Point {
                position: [1.0, 2.0, 3.0],
                color: [5.0; 3]
            }
        );
        assert_eq!(d.lights[3].kind(), "sh");
        assert_eq!(d.material.shading, Shading::BlinnPhong);
        assert_eq!(d.material.ka, Some([0.1; 3]));
        assert_eq!(
            d.raster,
            Raster {
                method: Method::Dibr,
                faces_per_pixel: Some(8),
                cull_backfaces: true,
                perspective_correct: false,
                threshold: 1e-3,
                sigma: 2e-4,
                gamma: 3e-4,
                eps: 1e-2,
                delta: 5e-5,
                overdraw_px: 0.5,
                ..Raster::default()
            }
        );
        assert_eq!(SceneDesc::parse(&d.to_json_pretty(), "x").unwrap(), d);
        for m in Method::ALL {
            assert_eq!(Method::from_name(m.name()), Some(m));
            let d =
                SceneDesc::parse(&with("raster", &format!("\"method\": \"{m}\"")), "s").unwrap();
            assert_eq!(d.raster.method, m);
        }
    }

    #[test]
    fn area_lights_and_the_ray_tracer_keys() {
        let area = |edge_v: &str| {
            with(
                "",
                &format!(
                    r#""lights": [{{"type": "area", "corner": [0, 2, 0], "edge_u": [1, 0, 0], "edge_v": {edge_v}, "radiance": [3, 3, 3]}}]"#
                ),
            )
        };
        let text = area("[0, 0, 1]");
        let rt = |t: &str| {
            let mut v: serde_json::Value = serde_json::from_str(t).unwrap();
            v["raster"] = serde_json::json!({"method": "raytrace", "spp": 16, "seed": 7,
                "edge_samples": 100, "shadow_edge_samples": 200, "area_edge_samples": 2});
            v.to_string()
        };
        let d = SceneDesc::parse(&rt(&text), "s.json").unwrap();
        d.validate("s.json").unwrap();
        assert_eq!(d.lights[0].kind(), "area");
        assert_eq!(d.raster.method, Method::Raytrace);
        assert_eq!(Method::from_name("raytrace"), Some(Method::Raytrace));
        assert_eq!(
            (d.raster.spp, d.raster.seed, d.raster.edge_samples),
            (16, 7, Some(100))
        );
        assert_eq!(
            (d.raster.shadow_edge_samples, d.raster.area_edge_samples),
            (Some(200), 2)
        );
        assert_eq!(SceneDesc::parse(&d.to_json_pretty(), "x").unwrap(), d);
        // Raster methods refuse area lights; a flat light is refused.
        let (k, m) = invalid(&text);
        assert_eq!(k, "lights[0]");
        assert!(m.contains("need raster.method 'raytrace'"), "{m}");
        let flat = rt(&area("[2, 0, 0]"));
        let (k, m) = invalid(&flat);
        assert_eq!(k, "lights[0].edge_v");
        assert!(m.contains("parallel"), "{m}");
        let (k, _) = invalid(&rt(&text).replace(r#""spp":16"#, r#""spp":0"#));
        assert_eq!(k, "raster.spp");
    }

    #[test]
    fn json_errors_name_the_key() {
        let e = parse_err(&with("raster", r#""method": "soft""#));
        assert!(e.starts_with("s.json: raster.method: unknown variant `soft`, expected one of `hard`, `tf_mesh`, `opendr`, `nmr`, `softras`, `dibr`, `deodr`, `analytic`"), "{e}");
        assert!(e.contains(" at line "), "{e}");
        let e = parse_err(&with("raster", r#""sigmaa": 1"#));
        assert!(
            e.contains("raster: unknown field `sigmaa`, expected one of `method`"),
            "{e}"
        );
        let e = parse_err(&with("", r#""extra": 1"#));
        assert!(
            e.contains("unknown field `extra`, expected one of `mesh`"),
            "{e}"
        );
        let e = parse_err(&with("camera", r#""fov": 1"#));
        assert!(e.contains("camera: unknown field `fov`"), "{e}");
        let e = parse_err(&with("image", r#""channels": 3"#));
        assert!(e.contains("image: unknown field `channels`"), "{e}");
        let e = parse_err(&with("material", r#""shading": "toon""#));
        assert!(e.contains("material.shading: unknown variant `toon`, expected one of `none`, `lambert`, `phong`, `blinn_phong`, `sh`"), "{e}");
        let e = parse_err(&with("material", r#""kd": "red""#));
        assert!(
            e.contains("material.kd: invalid type: string \"red\""),
            "{e}"
        );
        let e = parse_err(&with("raster", r#""sigma": "small""#));
        assert!(e.contains("raster.sigma: invalid type: string"), "{e}");
        let e = parse_err(&with("raster", r#""cull_backfaces": 1"#));
        assert!(
            e.contains("raster.cull_backfaces: invalid type: integer `1`, expected a boolean"),
            "{e}"
        );
        let e = parse_err(&with("raster", r#""faces_per_pixel": -2"#));
        assert!(
            e.contains("raster.faces_per_pixel: invalid value: integer `-2`"),
            "{e}"
        );
        let e = parse_err(r#"{"mesh": 3, "camera": {}, "image": {}}"#);
        assert!(e.contains("mesh: invalid type: integer `3`"), "{e}");
        let e = parse_err(
            r#"{"mesh": "m.obj", "camera": {"eye": [0, 0], "at": [0, 0, 0], "fov_y_deg": 45}, "image": {"width": 1, "height": 1}}"#,
        );
        assert!(
            e.contains("camera.eye: invalid length 2, expected an array of length 3"),
            "{e}"
        );
        let e = parse_err(
            r#"{"mesh": "m.obj", "camera": {"eye": [0, 0, 1], "at": [0, 0, 0]}, "image": {"width": 1, "height": 1}}"#,
        );
        assert!(e.contains("camera: missing field `fov_y_deg`"), "{e}");
        let e = parse_err(
            r#"{"mesh": "m.obj", "camera": {"eye": [0, 0, 1], "at": [0, 0, 0], "fov_y_deg": 4}}"#,
        );
        assert!(e.contains("missing field `image`"), "{e}");
        let e = parse_err(&with("image", r#""width": 2.5"#));
        assert!(
            e.contains("image.width: invalid type: floating point `2.5`"),
            "{e}"
        );
        let e = parse_err(&with(
            "",
            r#""lights": [{"type": "ambient", "color": [1, 1, 1]}, {"type": "spot", "color": [1, 1, 1]}]"#,
        ));
        assert!(e.contains("lights[1]: unknown variant `spot`, expected one of `ambient`, `directional`, `point`, `area`, `sh`"), "{e}");
        let e = parse_err(&with(
            "",
            r#""lights": [{"type": "ambient", "colour": [1, 1, 1]}]"#,
        ));
        assert!(
            e.contains("lights[0]: unknown field `colour`, expected `color`"),
            "{e}"
        );
        let e = parse_err(&with(
            "",
            r#""lights": [{"type": "directional", "direction": [0, 0, -1], "color": [1, 1]}]"#,
        ));
        assert!(e.contains("lights[0].color: invalid length 2"), "{e}");
        let e = parse_err(&with("", r#""lights": [{"color": [1, 1, 1]}]"#));
        assert!(e.contains("lights[0]: missing field `type`"), "{e}");
        let e = parse_err(&with("", r#""lights": {"type": "ambient"}"#));
        assert!(
            e.contains("lights: invalid type: map, expected a sequence"),
            "{e}"
        );
        let e = parse_err(&with(
            "",
            r#""lights": [{"type": "sh", "coeffs": [[1, 1]]}]"#,
        ));
        assert!(
            e.contains("lights[0].coeffs: invalid length 2, expected an array of length 3"),
            "{e}"
        );
        let e = parse_err("{\"mesh\": \"m.obj\",\n \"camera\": }");
        assert!(e.contains("line 2"), "{e}");
        match SceneDesc::parse(&with("raster", r#""method": "soft""#), "s.json") {
            Err(SceneError::Json { line, column, .. }) => assert!(line >= 1 && column >= 1),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn invalid_values_name_the_key_and_the_rule() {
        let cases: Vec<(String, &str, &str)> = vec![
            (with("image", r#""width": 0"#), "image.width", "between 1 and 65536"),
            (with("camera", r#""fov_y_deg": 180"#), "camera.fov_y_deg", "between 0 and 180"),
            (with("camera", r#""near": 0"#), "camera.near", "> 0"),
            (with("camera", r#""far": 0.05"#), "camera.far", "greater than near"),
            (with("camera", r#""up": [0, 0, 1]"#), "camera.up", "parallel"),
            (
                r#"{"mesh": "m.obj", "camera": {"eye": [0, 0, 0], "at": [0, 0, 0], "fov_y_deg": 45}, "image": {"width": 4, "height": 2}}"#.to_string(),
                "camera.at",
                "no view direction",
            ),
            (with("raster", r#""sigma": 0"#), "raster.sigma", "> 0"),
            (with("raster", r#""gamma": -1e-4"#), "raster.gamma", "> 0"),
            (with("raster", r#""delta": 0"#), "raster.delta", "> 0"),
            (with("raster", r#""threshold": 1"#), "raster.threshold", "between 0 and 1"),
            (with("raster", r#""faces_per_pixel": 0"#), "raster.faces_per_pixel", ">= 1"),
            (with("raster", r#""overdraw_px": -1"#), "raster.overdraw_px", ">= 0"),
            (with("material", r#""kd": [1, -1, 1]"#), "material.kd", ">= 0"),
            (with("material", r#""shininess": -2"#), "material.shininess", ">= 0"),
            (with("material", r#""shading": "sh""#), "material.shading", "needs a light"),
            (
                with("", r#""lights": [{"type": "sh", "coeffs": [[1,1,1],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0,0,0],[0,0,0]]}]"#),
                "lights[0].coeffs",
                "expected 9 rows of [r, g, b] (bands l = 0, 1, 2), got 8",
            ),
            (with("", r#""lights": [{"type": "directional", "direction": [0, 0, 0], "color": [1, 1, 1]}]"#), "lights[0].direction", "zero"),
            (with("", r#""lights": [{"type": "ambient", "color": [-1, 0, 0]}]"#), "lights[0].color", ">= 0"),
        ];
        for (text, key, rule) in cases {
            let (k, m) = invalid(&text);
            assert_eq!(k, key, "{text}");
            assert!(m.contains(rule), "{key}: {m}");
        }
        // The full message.
        let d = SceneDesc::parse(&with("raster", r#""sigma": -1"#), "s.json").unwrap();
        assert_eq!(
            d.validate("s.json").unwrap_err().to_string(),
            "s.json: raster.sigma: -1 must be finite and > 0"
        );
    }

    #[test]
    fn loading_resolves_paths_and_reports_missing_files() {
        let dir = std::env::temp_dir().join(format!("tapestry-scene-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("meshes")).unwrap();
        std::fs::write(
            dir.join("meshes/tri.obj"),
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        )
        .unwrap();
        let text = MIN.replace("m.obj", "meshes/tri.obj");
        std::fs::write(dir.join("s.json"), &text).unwrap();
        let s = Scene::<f32>::load(dir.join("s.json")).unwrap();
        assert_eq!(s.mesh.vertex_count(), 3);
        assert_eq!(s.mesh_path, dir.join("meshes/tri.obj"));
        assert!(s.texture.is_none());

        let e = Scene::<f32>::from_json(&text, Path::new("/nonexistent"), "s.json").unwrap_err();
        assert!(
            matches!(
                e,
                SceneError::Mesh {
                    source: ObjError::Open { .. },
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("/nonexistent/meshes/tri.obj"), "{e}");

        let with_tex = with("", r#""texture": "missing.png""#).replace("m.obj", "meshes/tri.obj");
        let e = Scene::<f32>::from_json(&with_tex, &dir, "s.json").unwrap_err();
        assert!(matches!(e, SceneError::Texture { .. }), "{e}");
        assert!(e.to_string().contains("missing.png"), "{e}");

        let e = Scene::<f32>::load(dir.join("nope.json")).unwrap_err();
        assert!(matches!(e, SceneError::Read { .. }));
        assert!(e.to_string().contains("nope.json"));
    }
}
