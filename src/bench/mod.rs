//! `tapestry bench`: speed against error for every raster method, and scaling in faces,
//! pixels and threads (issue 8, docs/CONVENTIONS.md "The tapestry command line").
//!
//! # References
//! - **Reference image** ([`reference_image`]): the box-filtered image (docs/CONVENTIONS.md) by
//!   supersampling the hard rasterizer: the scene is rendered with method `hard` at
//!   `S W x S H` pixels and each `S x S` block is averaged (block averaging, no jitter; the
//!   sub-samples sit at the centres of an `S x S` grid in the pixel square). `S = 16` in the
//!   full and quick runs (4 in the test-only tiny run); the output states it.
//! - **Pose** ([`Pose`]): six numbers `u = (tx, ty, tz, rx, ry, rz)` moving the scene's moving
//!   vertices `p` (all of them, or the front object of the occlusion scene) to
//!   `p + t + r x (p - c)` with `c` their centroid: a translation and a linearised (small
//!   angle) rotation. Each component is scaled so that a unit change moves the farthest moving
//!   vertex by one pixel of the benchmark image ("pixel-normalised" units), so the six
//!   gradient components are comparable and the cosine is not dominated by one of them.
//! - **Loss**: `L(u) = sum over pixels and RGBA channels of (I(u) - T)^2` with the target `T`
//!   the reference image at the pose [`TARGET_POSE`] (a few pixels away).
//! - **Reference gradient** ([`fd_gradient`]): central finite differences of `L` of the
//!   reference image, `(L(u + h e_k) - L(u - h e_k)) / 2h` at `u = 0`, with a step of
//!   `h = 0.75` px (crossing pixel boundaries, so that the supersampled image moves by whole
//!   sub-samples and the difference measures the box-filtered derivative).
//! - **Method gradient**: each method renders through the tape with `u` as the leaf (the
//!   vertex positions are `p0 + J u` on the tape) and is compared with the reference gradient:
//!   cosine similarity and relative L2 error `|g - g_ref| / |g_ref|`. Image error: mean
//!   absolute difference of the method's RGBA at `u = 0` to the reference image.
//! - **Inverse task** ([`pose_fit`]): Adam on `u` (step 0.5 px) from a wrong pose
//!   ([`FIT_START`]) towards the reference image at `u = 0`; the number of steps until the IoU
//!   of the hard silhouette (alpha > 0.5) with the reference's (coverage > 0.5) reaches 0.95,
//!   `None` when not reached within the cap.
//!
//! Timings: the median of a few repetitions after one warm-up, each in a rayon pool of the
//! record's thread count (1 for the accuracy records; its other workers poll for work between
//! a frame's parallel regions, [`autodiff::ActiveWait`]). Peak memory: the counting allocator
//! ([`alloc`]) over one forward+backward pass.

pub mod alloc;
pub mod plot;

use std::path::PathBuf;
use std::time::Instant;

use autodiff::optim::Adam;
use autodiff::{AutodiffError, Tape, Var};
use ndarray::{Array2, Array3, ArrayD, IxDyn};
use render_ops::error::RenderError;
use render_ops::mesh::Mesh;
use render_ops::pipeline::Wrt;
use render_ops::scene::{
    CameraDesc, ImageDesc, Light, Material, Method, Raster, Scene, SceneDesc, SceneError, Shading,
    DEFAULT_DIBR_DELTA,
};
use serde::Serialize;
use serde_json::{json, Value};
use thiserror::Error;

/// Errors of the bench.
#[derive(Debug, Error)]
pub enum BenchError {
    /// A rendering error.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// A tape error.
    #[error(transparent)]
    Autodiff(#[from] AutodiffError),
    /// A built-in scene failed validation (boxed: scene errors are large).
    #[error(transparent)]
    Scene(Box<SceneError>),
    /// Anything else, with its message.
    #[error("bench: {0}")]
    Message(String),
}

impl From<SceneError> for BenchError {
    fn from(e: SceneError) -> Self {
        BenchError::Scene(Box::new(e))
    }
}

type Result<T> = std::result::Result<T, BenchError>;

/// Finite-difference step of the reference gradient, in pixels of the benchmark image.
pub const FD_STEP_PX: f64 = 0.75;

/// Pose of the loss target (pixel-normalised units, see the module docs).
pub const TARGET_POSE: [f64; 6] = [2.0, -1.5, 1.0, 1.5, -2.0, 1.0];

/// Start of the pose fit (pixel-normalised units); the fit's target is `u = 0`.
pub const FIT_START: [f64; 6] = [5.0, -4.0, 3.0, 3.0, -4.0, 3.0];

/// Adam step of the pose fit (pixel-normalised units).
pub const FIT_LR: f64 = 0.5;

/// IoU that ends the pose fit.
pub const FIT_IOU: f64 = 0.95;

/// The built-in scenes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneKind {
    /// Icosphere with `s` subdivisions (`20 * 4^s` faces; s = 4: 5120, s = 6: 81920).
    Ico(u32),
    /// The cube with sharp edges, turned so that three faces show.
    Cube,
    /// The mean shape and albedo of the shipped face model.
    Face,
    /// Two spheres, the front one (which the pose moves) partly hiding the back one.
    Occlusion,
    /// A latitude-longitude sphere (24 x 48, 2208 faces) with a procedural texture, lit per
    /// pixel (Phong: a directional, a point and an ambient light): every method through its
    /// composed (per-fragment) path, where it has one.
    TexturedLit,
}

impl SceneKind {
    /// The name in the table and JSON.
    pub fn name(self) -> String {
        match self {
            SceneKind::Ico(s) => format!("ico{}", 20 * 4usize.pow(s)),
            SceneKind::Cube => "cube".into(),
            SceneKind::Face => "face".into(),
            SceneKind::Occlusion => "occlusion".into(),
            SceneKind::TexturedLit => "textured-lit".into(),
        }
    }
}

/// What a run covers.
#[derive(Clone, Debug)]
pub struct BenchConfig {
    /// `quick`, `full` or `tiny` (tests).
    pub name: &'static str,
    /// Image size (square) of the accuracy records and pose fits.
    pub size: usize,
    /// Reference samples per pixel along each axis (`S`).
    pub samples: usize,
    /// Scenes of the accuracy records.
    pub scenes: Vec<SceneKind>,
    /// Timed repetitions (after one warm-up).
    pub reps: usize,
    /// Scenes with a pose fit.
    pub fit_scenes: Vec<SceneKind>,
    /// Step cap of the pose fit.
    pub fit_cap: usize,
    /// Icosphere subdivisions of the faces scaling.
    pub face_levels: Vec<u32>,
    /// Image sizes of the pixel scaling (ico5k).
    pub pixel_sizes: Vec<usize>,
    /// Image size of the thread scaling (ico5k).
    pub thread_size: usize,
    /// Thread counts of the thread scaling.
    pub threads: Vec<usize>,
    /// Icosphere subdivision of the pixel and thread scaling scenes.
    pub scaling_level: u32,
}

impl BenchConfig {
    /// `tapestry bench --quick`: under 2 minutes on 2 cores.
    pub fn quick() -> Self {
        BenchConfig {
            name: "quick",
            size: 64,
            samples: 16,
            scenes: vec![
                SceneKind::Ico(4),
                SceneKind::Cube,
                SceneKind::Face,
                SceneKind::Occlusion,
                SceneKind::TexturedLit,
            ],
            reps: 3,
            fit_scenes: vec![SceneKind::Ico(4), SceneKind::Cube, SceneKind::Occlusion],
            fit_cap: 100,
            face_levels: vec![2, 3, 4, 5],
            pixel_sizes: vec![32, 64, 128, 256],
            thread_size: 128,
            threads: vec![1, 2],
            scaling_level: 4,
        }
    }

    /// `tapestry bench`: under 20 minutes on 2 cores.
    pub fn full() -> Self {
        BenchConfig {
            name: "full",
            size: 128,
            samples: 16,
            scenes: vec![
                SceneKind::Ico(4),
                SceneKind::Ico(6),
                SceneKind::Cube,
                SceneKind::Face,
                SceneKind::Occlusion,
                SceneKind::TexturedLit,
            ],
            reps: 5,
            fit_scenes: vec![
                SceneKind::Ico(4),
                SceneKind::Cube,
                SceneKind::Face,
                SceneKind::Occlusion,
            ],
            fit_cap: 100,
            face_levels: vec![2, 3, 4, 5, 6],
            pixel_sizes: vec![32, 64, 128, 256, 512],
            thread_size: 256,
            threads: vec![1, 2],
            scaling_level: 4,
        }
    }

    /// A configuration of a few seconds in the test profile (hidden `--tiny` flag).
    pub fn tiny() -> Self {
        BenchConfig {
            name: "tiny",
            size: 24,
            samples: 4,
            scenes: vec![
                SceneKind::Ico(2),
                SceneKind::Occlusion,
                SceneKind::TexturedLit,
            ],
            reps: 1,
            fit_scenes: vec![SceneKind::Ico(2)],
            fit_cap: 10,
            face_levels: vec![1, 2],
            pixel_sizes: vec![16, 24],
            thread_size: 24,
            threads: vec![1, 2],
            scaling_level: 2,
        }
    }
}

/// One raster method with settings.
#[derive(Clone, Debug)]
pub struct MethodConfig {
    /// The scene `raster` block.
    pub raster: Raster,
    /// The settings that differ between configurations, as a JSON object.
    pub params: Value,
    /// Whether this is the method's default configuration (used in the scaling runs).
    pub default: bool,
}

impl MethodConfig {
    /// `method` and its parameters, e.g. `softras sigma=1e-4 gamma=1e-4`.
    pub fn label(&self) -> String {
        let mut s = self.raster.method.name().to_string();
        if let Some(o) = self.params.as_object() {
            for (k, v) in o {
                s.push_str(&format!(" {k}={}", value_text(v)));
            }
        }
        s
    }
}

/// Every method of [`Method::ALL`] with its parameter sweep: softras sigma in {1e-3, 1e-4,
/// 1e-5} (gamma 1e-4), gamma in {1e-2, 1e-3} (sigma 1e-4) and the cut-off threshold 1e-2
/// (default 1e-4); dibr delta in {3e-5, 1/7000, 3e-4} (Kaolin's recommended range); hard with
/// K = 1 and 4 faces per pixel; tf_mesh, opendr and nmr with one; deodr with overdraw ramps of
/// 0.5, 1 and 2 px; analytic with no parameter; and the ray tracer of [`Method::RAY`] at 1, 4
/// and 16 samples per pixel (its speed against gradient error; the textured scene is noted as
/// not available to it, as to any method without a texture path).
pub fn method_configs() -> Vec<MethodConfig> {
    let mut out = Vec::new();
    for m in Method::ALL.into_iter().chain(Method::RAY) {
        let mut r = Raster::with_method(m);
        match m {
            Method::Analytic => out.push(MethodConfig {
                raster: r,
                params: json!({}),
                default: true,
            }),
            Method::Hard | Method::TfMesh | Method::OpenDr | Method::Nmr => {
                let ks: &[u32] = if m == Method::Hard { &[1, 4] } else { &[1] };
                for &k in ks {
                    r.faces_per_pixel = Some(k);
                    out.push(MethodConfig {
                        raster: r,
                        params: json!({ "faces_per_pixel": k }),
                        default: k == 1,
                    });
                }
            }
            Method::SoftRas => {
                let sweep = [
                    (1e-3, 1e-4, 1e-4),
                    (1e-4, 1e-4, 1e-4),
                    (1e-5, 1e-4, 1e-4),
                    (1e-4, 1e-2, 1e-4),
                    (1e-4, 1e-3, 1e-4),
                    (1e-4, 1e-4, 1e-2),
                ];
                for (sigma, gamma, threshold) in sweep {
                    r.sigma = sigma;
                    r.gamma = gamma;
                    r.threshold = threshold;
                    let mut params = json!({"sigma": sigma, "gamma": gamma});
                    if threshold != 1e-4 {
                        params["threshold"] = json!(threshold);
                    }
                    out.push(MethodConfig {
                        raster: r,
                        params,
                        default: (sigma, gamma, threshold) == (1e-4, 1e-4, 1e-4),
                    });
                }
            }
            Method::Dibr => {
                for delta in [3e-5, DEFAULT_DIBR_DELTA, 3e-4] {
                    r.delta = delta;
                    out.push(MethodConfig {
                        raster: r,
                        params: json!({"delta": delta}),
                        default: delta == DEFAULT_DIBR_DELTA,
                    });
                }
            }
            Method::Raytrace => {
                for spp in [1, 4, 16] {
                    r.spp = spp;
                    out.push(MethodConfig {
                        raster: r,
                        params: json!({ "spp": spp }),
                        default: spp == 4,
                    });
                }
            }
            Method::Deodr => {
                for px in [0.5, 1.0, 2.0] {
                    r.overdraw_px = px;
                    out.push(MethodConfig {
                        raster: r,
                        params: json!({ "overdraw_px": px }),
                        default: px == 1.0,
                    });
                }
            }
        }
    }
    out
}

/// A built-in scene: mesh with vertex colours (shading none), or a textured, Phong-lit one;
/// which vertices the pose moves.
#[derive(Clone, Debug)]
pub struct BenchScene {
    /// Name in the table.
    pub name: String,
    /// The mesh, with per-vertex colours.
    pub mesh: Mesh<f64>,
    /// Vertices moved by the pose.
    pub moving: Vec<usize>,
    /// The texture `[H, W, 3]` of a textured scene (the mesh has uvs).
    pub texture: Option<Array3<f64>>,
}

/// The textured, lit scene's mesh (white vertex colours) and texture: stripes and a smooth
/// checker of low frequency, 64 x 128 texels on the 8-bit grid.
fn textured_sphere() -> (Mesh<f64>, Array3<f64>) {
    let mut m = Mesh::<f64>::uv_sphere(24, 48, 1.0);
    m.colors = vec![[1.0; 3]; m.positions.len()];
    let (h, w) = (64, 128);
    let tex = Array3::from_shape_fn((h, w, 3), |(r, c, ch)| {
        let (u, v) = (c as f64 / w as f64, r as f64 / h as f64);
        let x = 0.55
            + 0.35
                * (std::f64::consts::TAU * (4.0 * u + ch as f64 * 0.3)).sin()
                * (std::f64::consts::PI * (5.0 * v)).cos();
        (x * 255.0).round() / 255.0
    });
    (m, tex)
}

fn colored_sphere(level: u32, radius: f64, offset: [f64; 3], tint: [f64; 3]) -> Mesh<f64> {
    let m = Mesh::<f64>::icosphere(level, radius);
    let colors = m
        .positions
        .iter()
        .map(|p| std::array::from_fn(|k| tint[k] * (0.55 + 0.4 * p[k] / radius)))
        .collect();
    let positions = m
        .positions
        .iter()
        .map(|p| std::array::from_fn(|k| p[k] + offset[k]))
        .collect();
    Mesh::new(positions, m.faces).with_colors(colors)
}

fn merge(a: Mesh<f64>, b: Mesh<f64>) -> Mesh<f64> {
    let n = a.positions.len() as u32;
    let mut positions = a.positions;
    positions.extend(b.positions);
    let mut colors = a.colors;
    colors.extend(b.colors);
    let mut faces = a.faces;
    faces.extend(b.faces.iter().map(|f| f.map(|i| i + n)));
    Mesh::new(positions, faces).with_colors(colors)
}

impl BenchScene {
    /// Builds a built-in scene (all fit in the unit ball about the origin).
    pub fn build(kind: SceneKind) -> Self {
        let mut texture = None;
        let (mesh, moving) = match kind {
            SceneKind::TexturedLit => {
                let (m, tex) = textured_sphere();
                texture = Some(tex);
                let all = (0..m.positions.len()).collect();
                (m, all)
            }
            SceneKind::Ico(s) => {
                let m = colored_sphere(s, 1.0, [0.0; 3], [1.0; 3]);
                let all = (0..m.positions.len()).collect();
                (m, all)
            }
            SceneKind::Cube => {
                let c = Mesh::<f64>::cube();
                let (a, b) = (35f64.to_radians(), 25f64.to_radians());
                let positions: Vec<[f64; 3]> = c
                    .positions
                    .iter()
                    .map(|p| {
                        // Ry(a) then Rx(b), scaled by 0.6.
                        let x = p[0] * a.cos() + p[2] * a.sin();
                        let z = -p[0] * a.sin() + p[2] * a.cos();
                        let y = p[1] * b.cos() - z * b.sin();
                        let z = p[1] * b.sin() + z * b.cos();
                        [0.6 * x, 0.6 * y, 0.6 * z]
                    })
                    .collect();
                let colors = c
                    .positions
                    .iter()
                    .map(|p| p.map(|x| 0.5 + 0.35 * x))
                    .collect();
                let m = Mesh::new(positions, c.faces).with_colors(colors);
                let all = (0..8).collect();
                (m, all)
            }
            SceneKind::Face => {
                let model: models::Morphable<f64> = models::face::default_face();
                let shape = model.mean_shape();
                let albedo = model.mean_albedo();
                let v = shape.nrows();
                let mut lo = [f64::INFINITY; 3];
                let mut hi = [f64::NEG_INFINITY; 3];
                for r in 0..v {
                    for k in 0..3 {
                        lo[k] = lo[k].min(shape[[r, k]]);
                        hi[k] = hi[k].max(shape[[r, k]]);
                    }
                }
                let c: [f64; 3] = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
                let radius = (0..v)
                    .map(|r| {
                        (0..3)
                            .map(|k| (shape[[r, k]] - c[k]).powi(2))
                            .sum::<f64>()
                            .sqrt()
                    })
                    .fold(0.0, f64::max)
                    .max(1e-12);
                let positions = (0..v)
                    .map(|r| std::array::from_fn(|k| (shape[[r, k]] - c[k]) / radius))
                    .collect();
                let colors = (0..v)
                    .map(|r| std::array::from_fn(|k| albedo[[r, k]]))
                    .collect();
                let m = Mesh::new(positions, model.faces().to_vec()).with_colors(colors);
                (m, (0..v).collect())
            }
            SceneKind::Occlusion => {
                let back = colored_sphere(3, 0.7, [-0.3, -0.1, -0.4], [0.4, 0.6, 1.0]);
                let front = colored_sphere(3, 0.45, [0.35, 0.15, 0.5], [1.0, 0.6, 0.4]);
                let nb = back.positions.len();
                let nf = front.positions.len();
                (merge(back, front), (nb..nb + nf).collect())
            }
        };
        BenchScene {
            name: kind.name(),
            mesh,
            moving,
            texture,
        }
    }

    /// The scene at `width x height` with the given raster block: camera at (0, 0, 3.5)
    /// looking at the origin, fov 45 degrees, near 1, far 10, black background, shading none
    /// (a textured scene: Phong, kd 0.9, ks 0.3, shininess 20, a directional, a point and an
    /// ambient light).
    pub fn scene(&self, width: usize, height: usize, raster: Raster) -> Result<Scene<f64>> {
        let (lights, material) = if self.texture.is_some() {
            let lights = vec![
                Light::Directional {
                    direction: [-0.4, -0.5, -1.0],
                    color: [1.0, 0.95, 0.9],
                },
                Light::Point {
                    position: [2.0, 1.0, 3.0],
                    color: [0.3, 0.3, 0.35],
                },
                Light::Ambient { color: [0.15; 3] },
            ];
            let material = Material {
                shading: Shading::Phong,
                kd: [0.9; 3],
                ks: [0.3; 3],
                shininess: 20.0,
                ..Material::default()
            };
            (lights, material)
        } else {
            (Vec::new(), Material::default())
        };
        let desc = SceneDesc {
            mesh: PathBuf::from(format!("<{}>", self.name)),
            texture: self
                .texture
                .as_ref()
                .map(|_| PathBuf::from(format!("<{} texture>", self.name))),
            camera: CameraDesc {
                eye: [0.0, 0.0, 3.5],
                at: [0.0; 3],
                up: [0.0, 1.0, 0.0],
                fov_y_deg: 45.0,
                near: 1.0,
                far: 10.0,
            },
            image: ImageDesc {
                width: width as u32,
                height: height as u32,
                background: [0.0; 3],
            },
            lights,
            material,
            raster,
        };
        let file = format!("<bench {}>", self.name);
        desc.validate(&file)?;
        let camera = desc
            .camera()
            .map_err(|e| BenchError::Message(e.to_string()))?;
        Ok(Scene {
            source: file,
            desc,
            mesh_path: PathBuf::from(format!("<{}>", self.name)),
            texture_path: None,
            mesh: self.mesh.clone(),
            texture: self.texture.clone(),
            camera,
        })
    }
}

/// The pose of a scene: vertex positions `p0 + J u` (see the module docs).
#[derive(Clone, Debug)]
pub struct Pose {
    base: Vec<f64>,
    /// `[6, 3V]`, rows pixel-normalised.
    jac: Array2<f64>,
}

impl Pose {
    /// The pose of `bench`'s moving vertices, normalised in pixels of `scene`'s image.
    pub fn new(bench: &BenchScene, scene: &Scene<f64>) -> Result<Self> {
        let pos = &bench.mesh.positions;
        let v = pos.len();
        if bench.moving.is_empty() {
            return Err(BenchError::Message(format!(
                "scene {}: nothing moves",
                bench.name
            )));
        }
        let mut c = [0.0; 3];
        for &i in &bench.moving {
            for k in 0..3 {
                c[k] += pos[i][k] / bench.moving.len() as f64;
            }
        }
        let mut jac = Array2::<f64>::zeros((6, 3 * v));
        for &i in &bench.moving {
            let q: [f64; 3] = std::array::from_fn(|k| pos[i][k] - c[k]);
            for k in 0..3 {
                jac[[k, 3 * i + k]] = 1.0;
            }
            // e_x x q, e_y x q, e_z x q.
            let rows = [[0.0, -q[2], q[1]], [q[2], 0.0, -q[0]], [-q[1], q[0], 0.0]];
            for (r, d) in rows.iter().enumerate() {
                for k in 0..3 {
                    jac[[3 + r, 3 * i + k]] = d[k];
                }
            }
        }
        // Pixel normalisation: the largest screen motion of a moving vertex per unit change.
        let (w, h) = (scene.desc.image.width, scene.desc.image.height);
        let eps = 1e-6;
        for r in 0..6 {
            let mut most = 0.0f64;
            for &i in &bench.moving {
                let p = pos[i];
                let d: [f64; 3] = std::array::from_fn(|k| jac[[r, 3 * i + k]]);
                let q = [p[0] + eps * d[0], p[1] + eps * d[1], p[2] + eps * d[2]];
                if let (Some(a), Some(b)) = (
                    scene.camera.project_pixel(p, w, h),
                    scene.camera.project_pixel(q, w, h),
                ) {
                    most = most.max(((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt() / eps);
                }
            }
            if !(most.is_finite() && most > 0.0) {
                return Err(BenchError::Message(format!(
                    "scene {}: pose component {r} does not move the image",
                    bench.name
                )));
            }
            jac.row_mut(r).mapv_inplace(|x| x / most);
        }
        Ok(Pose {
            base: pos.iter().flatten().copied().collect(),
            jac,
        })
    }

    /// Positions at pose `u`.
    pub fn positions(&self, u: &[f64; 6]) -> Vec<[f64; 3]> {
        let mut p = self.base.clone();
        for (r, &ur) in u.iter().enumerate() {
            if ur != 0.0 {
                for (x, &j) in p.iter_mut().zip(self.jac.row(r)) {
                    *x += ur * j;
                }
            }
        }
        p.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
    }

    /// Positions `[V, 3]` on the tape as a function of the pose leaf `u` `[6]`.
    pub fn positions_var<'t>(&self, tape: &'t Tape<f64>, u: Var<'t, f64>) -> Var<'t, f64> {
        let v = self.base.len() / 3;
        let base = tape
            .constant(ArrayD::from_shape_vec(IxDyn(&[v, 3]), self.base.clone()).expect("v x 3"));
        let jac = tape.constant(self.jac.clone().into_dyn());
        base + u.reshape(&[1, 6]).matmul(jac).reshape(&[v, 3])
    }
}

/// Renders `scene` (its method) at pose `u` on `tape` (`u` a `[6]` variable).
pub fn render_pose<'t>(
    scene: &Scene<f64>,
    pose: &Pose,
    tape: &'t Tape<f64>,
    u: Var<'t, f64>,
) -> Result<Var<'t, f64>> {
    let mut vars = scene.vars(tape, Wrt::default());
    vars.positions = pose.positions_var(tape, u);
    Ok(scene.render(&vars)?)
}

fn pose_leaf<'t>(tape: &'t Tape<f64>, u: &[f64; 6], grad: bool) -> Var<'t, f64> {
    tape.var(
        ArrayD::from_shape_vec(IxDyn(&[6]), u.to_vec()).expect("6"),
        grad,
    )
}

fn to_array3(img: &ArrayD<f64>) -> Result<Array3<f64>> {
    img.clone()
        .into_dimensionality()
        .map_err(|e| BenchError::Message(format!("image is not [H, W, C]: {e}")))
}

/// The image of `scene`'s method at pose `u` (no gradient).
pub fn image_at(scene: &Scene<f64>, pose: &Pose, u: &[f64; 6]) -> Result<Array3<f64>> {
    let tape = Tape::new();
    let img = render_pose(scene, pose, &tape, pose_leaf(&tape, u, false))?;
    to_array3(&*img.value()?)
}

/// The reference image of `scene` at pose `u`: method `hard` at `S W x S H`, `S x S` blocks
/// averaged (see the module docs). RGBA `[H, W, 4]`.
pub fn reference_image(
    scene: &Scene<f64>,
    pose: &Pose,
    u: &[f64; 6],
    samples: usize,
) -> Result<Array3<f64>> {
    let big = render_ops::check::scene::supersampled_scene(scene, samples)?;
    let img = image_at(&big, pose, u)?;
    Ok(render_ops::check::scene::box_downsample(&img, samples))
}

/// `sum (a - b)^2`.
pub fn sq_loss(a: &Array3<f64>, b: &Array3<f64>) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Central finite differences of `loss` at `u` with step `h` in each pose component.
pub fn fd_gradient(
    mut loss: impl FnMut(&[f64; 6]) -> Result<f64>,
    u: &[f64; 6],
    h: f64,
) -> Result<[f64; 6]> {
    let mut g = [0.0; 6];
    for k in 0..6 {
        let mut a = *u;
        let mut b = *u;
        a[k] += h;
        b[k] -= h;
        g[k] = (loss(&a)? - loss(&b)?) / (2.0 * h);
    }
    Ok(g)
}

/// The tape gradient of `sum (I(u) - target)^2` with respect to `u`, and the image.
pub fn method_gradient(
    scene: &Scene<f64>,
    pose: &Pose,
    u: &[f64; 6],
    target: &Array3<f64>,
) -> Result<([f64; 6], Array3<f64>)> {
    let tape = Tape::new();
    let leaf = pose_leaf(&tape, u, true);
    let img = render_pose(scene, pose, &tape, leaf)?;
    let loss = img.sum_squared_diff(tape.constant(target.clone().into_dyn()));
    let grads = tape.backward(loss)?;
    let g = grads.wrt(leaf);
    let out = std::array::from_fn(|k| g[k]);
    Ok((out, to_array3(&*img.value()?)?))
}

/// Cosine similarity and relative L2 error of `g` against `reference`.
pub fn compare(g: &[f64; 6], reference: &[f64; 6]) -> (f64, f64) {
    let dot: f64 = g.iter().zip(reference).map(|(a, b)| a * b).sum();
    let ng = g.iter().map(|a| a * a).sum::<f64>().sqrt();
    let nr = reference.iter().map(|a| a * a).sum::<f64>().sqrt();
    let diff = g
        .iter()
        .zip(reference)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    let cos = if ng > 0.0 && nr > 0.0 {
        dot / (ng * nr)
    } else {
        0.0
    };
    (cos, if nr > 0.0 { diff / nr } else { f64::NAN })
}

/// Mean absolute difference.
pub fn mean_abs(a: &Array3<f64>, b: &Array3<f64>) -> f64 {
    let n = a.len().max(1) as f64;
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f64>() / n
}

fn silhouette(img: &Array3<f64>) -> Vec<bool> {
    let c = img.dim().2;
    img.outer_iter()
        .flat_map(|row| {
            row.outer_iter()
                .map(|px| px[c - 1] > 0.5)
                .collect::<Vec<_>>()
        })
        .collect()
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

/// The inverse task: Adam (step [`FIT_LR`]) on the pose from [`FIT_START`] towards `target`
/// (the reference image at `u = 0`). Returns the steps taken until the IoU of the hard
/// silhouette with `target`'s reaches [`FIT_IOU`] (`None` if not within `cap`) and the last
/// IoU.
pub fn pose_fit(
    scene: &Scene<f64>,
    pose: &Pose,
    target: &Array3<f64>,
    cap: usize,
) -> Result<(Option<usize>, f64)> {
    let mut hard = scene.clone();
    hard.desc.raster = Raster::with_method(Method::Hard);
    let want = silhouette(target);
    let mut u = ArrayD::from_shape_vec(IxDyn(&[6]), FIT_START.to_vec()).expect("6");
    let mut adam = Adam::new(FIT_LR);
    let mut last = 0.0;
    for step in 0..=cap {
        let cur: [f64; 6] = std::array::from_fn(|k| u[k]);
        last = iou(&silhouette(&image_at(&hard, pose, &cur)?), &want);
        if last >= FIT_IOU {
            return Ok((Some(step), last));
        }
        if step == cap {
            break;
        }
        let (g, _) = method_gradient(scene, pose, &cur, target)?;
        let g = ArrayD::from_shape_vec(IxDyn(&[6]), g.to_vec()).expect("6");
        adam.step([(&mut u, &g)])?;
    }
    Ok((None, last))
}

/// One row of the report (docs/CONVENTIONS.md fields, plus `kind`, `samples` and the pose fit).
#[derive(Clone, Debug, Serialize)]
pub struct Record {
    /// `accuracy`, `faces`, `pixels` or `threads`.
    pub kind: String,
    /// Raster method name.
    pub method: String,
    /// Scene name.
    pub scene: String,
    /// The method's settings.
    pub params: Value,
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Triangles.
    pub faces: usize,
    /// Threads of the rayon pool the timings ran in.
    pub threads: usize,
    /// Median forward time, seconds.
    pub forward_s: f64,
    /// Median forward + backward time, seconds.
    pub forward_backward_s: f64,
    /// Peak bytes allocated during one forward + backward (null without the counting
    /// allocator).
    pub peak_bytes: Option<u64>,
    /// Mean absolute RGBA difference to the reference image (accuracy records).
    pub image_error: Option<f64>,
    /// Cosine similarity of the pose gradient with the reference gradient.
    pub grad_cosine: Option<f64>,
    /// Relative L2 error of the pose gradient.
    pub grad_rel_l2: Option<f64>,
    /// Pose-fit steps until IoU >= 0.95 (null: not reached, or no fit on this scene).
    pub iters_to_iou95: Option<usize>,
    /// IoU at the end of the pose fit (null: no fit).
    pub fit_final_iou: Option<f64>,
    /// Reference samples per pixel along each axis.
    pub samples: usize,
}

/// A finished run: records and notes (skipped methods).
#[derive(Clone, Debug, Default)]
pub struct Report {
    /// Every record.
    pub records: Vec<Record>,
    /// Skipped methods and why.
    pub notes: Vec<String>,
    /// Wall time of the run, seconds.
    pub seconds: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

struct Timing {
    forward_s: f64,
    forward_backward_s: f64,
    peak_bytes: Option<u64>,
}

fn time_method(
    scene: &Scene<f64>,
    pose: &Pose,
    target: &Array3<f64>,
    reps: usize,
) -> Result<Timing> {
    let u = [0.0; 6];
    // The pool's other workers poll between the frame's parallel regions (as in `fit`).
    let _hot = autodiff::ActiveWait::new();
    let fwd = || -> Result<f64> {
        let t0 = Instant::now();
        let tape = Tape::new();
        let img = render_pose(scene, pose, &tape, pose_leaf(&tape, &u, true))?;
        img.value()?;
        Ok(t0.elapsed().as_secs_f64())
    };
    let fwdbwd = || -> Result<f64> {
        let t0 = Instant::now();
        method_gradient(scene, pose, &u, target)?;
        Ok(t0.elapsed().as_secs_f64())
    };
    fwd()?;
    let (r, peak_bytes) = alloc::measure_peak(fwdbwd);
    r?;
    let reps = reps.max(1);
    let forward_s = median((0..reps).map(|_| fwd()).collect::<Result<_>>()?);
    let forward_backward_s = median((0..reps).map(|_| fwdbwd()).collect::<Result<_>>()?);
    Ok(Timing {
        forward_s,
        forward_backward_s,
        peak_bytes,
    })
}

fn pool(threads: usize) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| BenchError::Message(format!("thread pool: {e}")))
}

/// Whether a method is available in this build: `Err(message)` when its render is
/// `Unsupported`.
fn probe(bench: &BenchScene, cfg: &MethodConfig) -> Result<std::result::Result<(), String>> {
    let scene = bench.scene(8, 8, cfg.raster)?;
    let pose = Pose::new(bench, &scene)?;
    match image_at(&scene, &pose, &[0.0; 6]) {
        Ok(_) => Ok(Ok(())),
        Err(BenchError::Render(RenderError::Unsupported(m))) => Ok(Err(m)),
        Err(e) => Err(e),
    }
}

/// Runs the bench. `progress` receives one line per step.
pub fn run(config: &BenchConfig, progress: &mut dyn FnMut(&str)) -> Result<Report> {
    let start = Instant::now();
    let mut report = Report::default();
    let probe_scene = BenchScene::build(SceneKind::Ico(1));
    let mut configs = Vec::new();
    for cfg in method_configs() {
        match probe(&probe_scene, &cfg)? {
            Ok(()) => configs.push(cfg),
            Err(m) => {
                let note = format!("{}: skipped ({m})", cfg.label());
                if !report.notes.contains(&note) {
                    report.notes.push(note);
                }
            }
        }
    }
    let one = pool(1)?;
    let all = pool(config.threads.iter().copied().max().unwrap_or(1))?;
    let (size, s) = (config.size, config.samples);

    // Accuracy against the references.
    for &kind in &config.scenes {
        let bench = BenchScene::build(kind);
        let base = bench.scene(size, size, Raster::with_method(Method::Hard))?;
        let pose = Pose::new(&bench, &base)?;
        progress(&format!(
            "{}: reference ({}x{} samples a pixel, finite differences)",
            bench.name, s, s
        ));
        let (reference, g_ref) = all.install(|| -> Result<_> {
            let target = reference_image(&base, &pose, &TARGET_POSE, s)?;
            let reference = reference_image(&base, &pose, &[0.0; 6], s)?;
            let g = fd_gradient(
                |u| Ok(sq_loss(&reference_image(&base, &pose, u, s)?, &target)),
                &[0.0; 6],
                FD_STEP_PX,
            )?;
            Ok(((reference, target), g))
        })?;
        let (reference, target) = reference;
        for cfg in &configs {
            progress(&format!("{}: {}", bench.name, cfg.label()));
            if bench.texture.is_some() {
                // Said explicitly: a method without a composed (per-fragment) path cannot
                // texture or light per pixel, and is not timed on this scene.
                if let Err(m) = probe(&bench, cfg)? {
                    let note = format!("{} on {}: not available ({m})", cfg.label(), bench.name);
                    if !report.notes.contains(&note) {
                        report.notes.push(note);
                    }
                    continue;
                }
            }
            let scene = bench.scene(size, size, cfg.raster)?;
            let rec = one.install(|| -> Result<Record> {
                let timing = time_method(&scene, &pose, &target, config.reps)?;
                let (g, img) = method_gradient(&scene, &pose, &[0.0; 6], &target)?;
                let (cos, rel) = compare(&g, &g_ref);
                let (iters, fit_iou) = if config.fit_scenes.contains(&kind) {
                    let (i, f) = pose_fit(&scene, &pose, &reference, config.fit_cap)?;
                    (i, Some(f))
                } else {
                    (None, None)
                };
                Ok(Record {
                    kind: "accuracy".into(),
                    method: cfg.raster.method.name().into(),
                    scene: bench.name.clone(),
                    params: cfg.params.clone(),
                    width: size,
                    height: size,
                    faces: bench.mesh.faces.len(),
                    threads: 1,
                    forward_s: timing.forward_s,
                    forward_backward_s: timing.forward_backward_s,
                    peak_bytes: timing.peak_bytes,
                    image_error: Some(mean_abs(&img, &reference)),
                    grad_cosine: Some(cos),
                    grad_rel_l2: Some(rel),
                    iters_to_iou95: iters,
                    fit_final_iou: fit_iou,
                    samples: s,
                })
            })?;
            report.records.push(rec);
        }
    }

    // Scaling: default configuration of each method, timings only.
    let defaults: Vec<&MethodConfig> = configs.iter().filter(|c| c.default).collect();
    let mut runs: Vec<(&str, SceneKind, usize, usize)> = Vec::new();
    for &l in &config.face_levels {
        runs.push(("faces", SceneKind::Ico(l), size, 1));
    }
    for &p in &config.pixel_sizes {
        runs.push(("pixels", SceneKind::Ico(config.scaling_level), p, 1));
    }
    for &t in &config.threads {
        runs.push((
            "threads",
            SceneKind::Ico(config.scaling_level),
            config.thread_size,
            t,
        ));
    }
    for (what, kind, px, threads) in runs {
        let bench = BenchScene::build(kind);
        let p = pool(threads)?;
        for cfg in &defaults {
            progress(&format!(
                "scaling {what}: {} {px}x{px} {threads} thread(s) {}",
                bench.name,
                cfg.label()
            ));
            let scene = bench.scene(px, px, cfg.raster)?;
            let pose = Pose::new(&bench, &scene)?;
            let target = p.install(|| image_at(&scene, &pose, &TARGET_POSE))?;
            let timing = p.install(|| time_method(&scene, &pose, &target, config.reps))?;
            report.records.push(Record {
                kind: what.into(),
                method: cfg.raster.method.name().into(),
                scene: bench.name.clone(),
                params: cfg.params.clone(),
                width: px,
                height: px,
                faces: bench.mesh.faces.len(),
                threads,
                forward_s: timing.forward_s,
                forward_backward_s: timing.forward_backward_s,
                peak_bytes: timing.peak_bytes,
                image_error: None,
                grad_cosine: None,
                grad_rel_l2: None,
                iters_to_iou95: None,
                fit_final_iou: None,
                samples: s,
            });
        }
    }
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}

/// A parameter value for the table: floats as short scientific numbers (`1e-4`, `1.43e-4`).
fn value_text(v: &Value) -> String {
    match v.as_f64() {
        Some(x) if v.is_f64() && x != 0.0 && (x.abs() < 1e-2 || x.abs() >= 1e4) => {
            let s = format!("{x:.2e}");
            match s.split_once('e') {
                Some((m, e)) => {
                    let m = if m.contains('.') {
                        m.trim_end_matches('0').trim_end_matches('.')
                    } else {
                        m
                    };
                    format!("{m}e{e}")
                }
                None => s,
            }
        }
        _ => v.to_string(),
    }
}

fn params_text(v: &Value) -> String {
    match v.as_object() {
        Some(o) => o
            .iter()
            .map(|(k, v)| format!("{k}={}", value_text(v)))
            .collect::<Vec<_>>()
            .join(" "),
        None => v.to_string(),
    }
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("-".into(), |x| format!("{x:.digits$}"))
}

/// The Markdown tables: accuracy records, then scaling records.
pub fn markdown(report: &Report, config: &BenchConfig) -> String {
    let mut s = format!(
        "Reference: hard rasterizer at {0}x{0} samples a pixel (block average); gradient: \
         central differences of the pose (6 pixel-normalised numbers), step {FD_STEP_PX} px. \
         Timings: median of {1} after a warm-up, 1 thread unless stated.\n\n",
        config.samples, config.reps
    );
    s.push_str(
        "| scene | method | params | faces | size | fwd ms | fwd+bwd ms | peak MiB | image err \
         | grad cos | grad rel L2 | IoU 0.95 iters |\n|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in report.records.iter().filter(|r| r.kind == "accuracy") {
        let fit = match (r.iters_to_iou95, r.fit_final_iou) {
            (Some(i), _) => i.to_string(),
            (None, Some(f)) => format!("not reached (IoU {f:.3})"),
            (None, None) => "-".into(),
        };
        s.push_str(&format!(
            "| {} | {} | {} | {} | {}x{} | {:.2} | {:.2} | {} | {} | {} | {} | {} |\n",
            r.scene,
            r.method,
            params_text(&r.params),
            r.faces,
            r.width,
            r.height,
            1e3 * r.forward_s,
            1e3 * r.forward_backward_s,
            r.peak_bytes
                .map_or("-".into(), |b| format!("{:.1}", b as f64 / 1048576.0)),
            opt(r.image_error, 4),
            opt(r.grad_cosine, 3),
            opt(r.grad_rel_l2, 3),
            fit
        ));
    }
    s.push_str(
        "\n| scaling | method | scene | size | faces | threads | fwd ms | fwd+bwd ms | peak MiB |\n\
         |---|---|---|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in report.records.iter().filter(|r| r.kind != "accuracy") {
        s.push_str(&format!(
            "| {} | {} | {} | {}x{} | {} | {} | {:.2} | {:.2} | {} |\n",
            r.kind,
            r.method,
            r.scene,
            r.width,
            r.height,
            r.faces,
            r.threads,
            1e3 * r.forward_s,
            1e3 * r.forward_backward_s,
            r.peak_bytes
                .map_or("-".into(), |b| format!("{:.1}", b as f64 / 1048576.0)),
        ));
    }
    for n in &report.notes {
        s.push_str(&format!("\nNote: {n}"));
    }
    s.push_str(&format!(
        "\n\n{} run: {:.1} s.\n",
        config.name, report.seconds
    ));
    s
}
