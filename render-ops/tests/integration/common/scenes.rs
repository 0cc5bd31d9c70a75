//! Scenes shared by the tests of composed methods (`boundary.rs`, `soft_stage.rs`): a
//! uv-seamed sphere, a smooth texture, scene JSON of three kinds (vertex colours, textured,
//! Phong-lit), supersampled hard renders and directional position gradients.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use autodiff::optim::Adam;
use autodiff::{Tape, Tensor, Var};
use ndarray::{ArrayD, IxDyn};

use super::weights;
use render_ops::camera::Camera;
use render_ops::mesh::Mesh;
use render_ops::obj::write_obj;
use render_ops::pipeline::Wrt;
use render_ops::scene::Scene;
use render_ops::shade::FragmentInputs;

pub fn max_diff(a: &Tensor<f64>, b: &Tensor<f64>) -> f64 {
    a.iter()
        .zip(b.iter())
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
}

pub fn cosine(a: &[f64], b: &[f64]) -> f64 {
    let dot: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let na: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| x * x).sum::<f64>().sqrt();
    dot / (na * nb)
}

pub fn flat(t: &Tensor<f64>) -> Vec<f64> {
    t.iter().copied().collect()
}

/// A fresh temporary folder `tapestry-{name}-{pid}`.
pub fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A latitude-longitude sphere of radius `r` with a uv seam (seam vertices share positions and
/// have two uvs), per-vertex colours; counter-clockwise seen from outside.
pub fn seam_sphere(nlat: usize, nlon: usize, r: f64) -> Mesh<f64> {
    let mut m = Mesh::uv_sphere(nlat, nlon, r);
    m.colors = m
        .positions
        .iter()
        .map(|p| [0.7 + 0.2 * p[0], 0.6 + 0.3 * p[1], 0.8 - 0.2 * p[2]])
        .collect();
    m
}

/// A smooth texture (stripes and a checker of low frequency, values on the 8-bit grid).
pub fn texture_image(h: usize, w: usize) -> ndarray::Array3<f64> {
    ndarray::Array3::from_shape_fn((h, w, 3), |(r, c, ch)| {
        let (u, v) = (c as f64 / w as f64, r as f64 / h as f64);
        let x = 0.55
            + 0.35
                * (std::f64::consts::TAU * (2.0 * u + ch as f64 * 0.3)).sin()
                * (std::f64::consts::PI * (3.0 * v)).cos();
        (x * 255.0).round() / 255.0
    })
}

/// The kinds of scene of the tests: per-vertex colours (the fused path), textured, per-pixel
/// Phong-lit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Kind {
    VertexColours,
    Textured,
    Phong,
}

/// Writes the mesh (and texture) to `dir` and loads a scene.
pub fn scene(dir: &Path, mesh: &Mesh<f64>, kind: Kind, method: &str, size: usize) -> Scene<f64> {
    scene_with(dir, mesh, kind, method, size, "")
}

/// [`scene`] with further `raster` fields (`extra`: JSON members, each preceded by a comma).
pub fn scene_with(
    dir: &Path,
    mesh: &Mesh<f64>,
    kind: Kind,
    method: &str,
    size: usize,
    extra: &str,
) -> Scene<f64> {
    write_obj(dir.join("m.obj"), mesh).unwrap();
    let tex = if kind == Kind::Textured {
        let p = dir.join("tex.png");
        if !p.exists() {
            render_ops::io::write_png(&p, &texture_image(32, 64)).unwrap();
        }
        "\"tex.png\""
    } else {
        "null"
    };
    let shading = if kind == Kind::Phong { "phong" } else { "none" };
    let json = format!(
        r#"{{"mesh": "m.obj", "texture": {tex},
        "camera": {{"eye": [0.6, 0.8, 3.2], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 40,
                   "near": 0.5, "far": 10}},
        "image": {{"width": {size}, "height": {size}, "background": [0.1, 0.2, 0.3]}},
        "lights": [{{"type": "directional", "direction": [-0.4, -0.5, -1], "color": [1, 0.9, 0.8]}},
                   {{"type": "point", "position": [2, 1, 3], "color": [0.3, 0.3, 0.4]}},
                   {{"type": "ambient", "color": [0.15, 0.15, 0.15]}}],
        "material": {{"shading": "{shading}", "kd": [0.9, 0.8, 0.7], "ks": [0.4, 0.4, 0.4],
                     "shininess": 20}},
        "raster": {{"method": "{method}"{extra}}}}}"#
    );
    Scene::from_json(&json, dir, "test.json").unwrap()
}

pub fn positions_tensor(p: &[[f64; 3]]) -> Tensor<f64> {
    ArrayD::from_shape_vec(IxDyn(&[p.len(), 3]), p.iter().flatten().copied().collect()).unwrap()
}

/// The scene's image at vertex positions `pos`.
pub fn image_at(sc: &Scene<f64>, pos: &Tensor<f64>) -> Tensor<f64> {
    let tape = Tape::new();
    let mut vars = sc.vars(&tape, Wrt::default());
    vars.positions = tape.constant(pos.clone());
    sc.render(&vars).unwrap().value().unwrap().as_ref().clone()
}

/// The hard render of `big` (the scene at `n * ss` pixels) box-filtered to `n x n`.
pub fn supersampled(big: &Scene<f64>, pos: &Tensor<f64>, n: usize, ss: usize) -> Vec<f64> {
    let img = image_at(big, pos);
    let mut out = vec![0.0; n * n * 4];
    let scale = 1.0 / (ss * ss) as f64;
    for (i, v) in img.iter().enumerate() {
        let (p, ch) = (i / 4, i % 4);
        let (row, col) = (p / (n * ss), p % (n * ss));
        out[((row / ss) * n + col / ss) * 4 + ch] += scale * v;
    }
    out
}

/// `d/dpositions` of `sum (render - target)^2`.
pub fn position_grad(sc: &Scene<f64>, pos: &Tensor<f64>, target: &[f64]) -> Tensor<f64> {
    let tape = Tape::new();
    let mut vars = sc.vars(&tape, Wrt::default());
    vars.positions = tape.leaf(pos.clone());
    let img = sc.render(&vars).unwrap();
    let t = ArrayD::from_shape_vec(IxDyn(img.shape().as_slice()), target.to_vec()).unwrap();
    let loss = (img - tape.constant(t)).square().sum();
    tape.backward(loss).unwrap().wrt(vars.positions)
}

/// Directions of vertex motion `[V, 3]`: the six rigid motions (translations, rotations about
/// the axes through the origin) and two smooth deformations.
pub fn directions(pts: &[[f64; 3]]) -> Vec<Vec<f64>> {
    let mut out = Vec::new();
    for k in 0..3 {
        out.push(
            pts.iter()
                .flat_map(|_| {
                    let mut d = [0.0; 3];
                    d[k] = 1.0;
                    d
                })
                .collect(),
        );
        out.push(
            pts.iter()
                .flat_map(|p| {
                    let mut a = [0.0; 3];
                    a[k] = 1.0;
                    [
                        a[1] * p[2] - a[2] * p[1],
                        a[2] * p[0] - a[0] * p[2],
                        a[0] * p[1] - a[1] * p[0],
                    ]
                })
                .collect(),
        );
    }
    for ph in [0.3, 1.7] {
        out.push(
            pts.iter()
                .flat_map(|p| {
                    let s = 0.5 * (2.0 * p[0] + 3.0 * p[1] + ph).sin();
                    [s * p[0], s * p[1], s * p[2]]
                })
                .collect(),
        );
    }
    out
}

/// The vertices of the edges between a face turned towards `eye` and one turned away.
pub fn silhouette_vertices(mesh: &Mesh<f64>, eye: [f64; 3]) -> Vec<usize> {
    let p = &mesh.positions;
    let towards: Vec<bool> = mesh
        .faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| p[i as usize]);
            let (u, v) = (
                [0, 1, 2].map(|k| b[k] - a[k]),
                [0, 1, 2].map(|k| c[k] - a[k]),
            );
            let n = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            (0..3).map(|k| n[k] * (eye[k] - a[k])).sum::<f64>() > 0.0
        })
        .collect();
    let mut edges: std::collections::BTreeMap<(u32, u32), Vec<bool>> = Default::default();
    for (f, &t) in mesh.faces.iter().zip(&towards) {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            edges.entry((a.min(b), a.max(b))).or_default().push(t);
        }
    }
    let mut out: Vec<usize> = edges
        .iter()
        .filter(|(_, t)| t.iter().any(|&x| x) && t.iter().any(|&x| !x))
        .flat_map(|(&(a, b), _)| [a as usize, b as usize])
        .collect();
    out.sort_unstable();
    out.dedup();
    out
}

pub fn moved(pos: &Tensor<f64>, d: &[f64], h: f64) -> Tensor<f64> {
    let mut p = pos.clone();
    for (x, dx) in p.iter_mut().zip(d) {
        *x += h * dx;
    }
    p
}

/// The toon / rim shader of `examples/custom_shader.rs`: a two-tone diffuse term (a soft
/// step at `threshold`) and a Fresnel rim of strength `rim`.
pub fn toon_rim<'t>(
    f: &FragmentInputs<'t, f64>,
    threshold: Var<'t, f64>,
    rim: Var<'t, f64>,
) -> Var<'t, f64> {
    let t = f.position.tape();
    let vec3 = |a: [f64; 3]| t.constant(ArrayD::from_shape_vec(IxDyn(&[3]), a.to_vec()).unwrap());
    let to_light = vec3([-0.4, 0.6, 0.7]).normalize(1e-12);
    let ndl = (f.normal * to_light).sum_axes(&[-1], true);
    let step = ((ndl - threshold) * (1.0 / 0.08)).sigmoid();
    let diffuse = vec3([0.9, 0.45, 0.3]) * (step * 0.75 + 0.2);
    let ndv = (f.normal * f.view_dir).sum_axes(&[-1], true);
    let fresnel = (-ndv + 1.0).relu().powf(5.0) * 0.96 + 0.04;
    diffuse + fresnel * rim * vec3([0.3, 0.6, 1.0])
}

/// The closure-shader tests' scene: a level-2 icosphere seen from `[0, 0.2, 3]` (45 degree
/// field of view) at `size` x `size`, and fixed loss weights over its RGBA image.
pub struct ToonScene {
    pub cam: Camera,
    pub mesh: Mesh<f64>,
    pub faces: Arc<Vec<[u32; 3]>>,
    pub pos: Tensor<f64>,
    pub size: usize,
    pub wts: Tensor<f64>,
}

impl ToonScene {
    /// The camera alone (for tests of other sizes or scalars).
    pub fn camera() -> Camera {
        Camera::perspective_look_at(
            [0.0, 0.2, 3.0],
            [0.0; 3],
            [0.0, 1.0, 0.0],
            45f64.to_radians(),
            1.0,
            0.5,
            10.0,
        )
        .unwrap()
    }

    pub fn new() -> Self {
        let cam = Self::camera();
        let mesh = Mesh::<f64>::icosphere(2, 1.0);
        let faces = Arc::new(mesh.faces.clone());
        let pos = positions_tensor(&mesh.positions);
        let size = 24;
        let wts =
            ArrayD::from_shape_vec(IxDyn(&[size, size, 4]), weights(size * size * 4)).unwrap();
        ToonScene {
            cam,
            mesh,
            faces,
            pos,
            size,
            wts,
        }
    }
}

/// A `[1]` tensor holding `x` (a shader parameter).
pub fn scalar(x: f64) -> Tensor<f64> {
    ArrayD::from_elem(IxDyn(&[1]), x)
}

/// The result of [`fit_pose`]: the loss before the first and after the last step, and the
/// largest error of a pose component.
pub struct PoseFit {
    pub first: f64,
    pub last: f64,
    pub err: f64,
}

/// An inverse task: the pose `[tx, ty, angle about y]` of `mesh` in `sc` recovered from the
/// image rendered at `truth`, starting at `[-0.1, 0.1, 0]`, with `steps` Adam steps (rate
/// 0.02) on the squared image difference.
pub fn fit_pose(sc: &Scene<f64>, mesh: &Mesh<f64>, truth: [f64; 3], steps: usize) -> PoseFit {
    let (s, c) = truth[2].sin_cos();
    let posed: Vec<[f64; 3]> = mesh
        .positions
        .iter()
        .map(|p| {
            [
                c * p[0] + s * p[2] + truth[0],
                p[1] + truth[1],
                -s * p[0] + c * p[2],
            ]
        })
        .collect();
    let target = image_at(sc, &positions_tensor(&posed));
    let mut pose = ArrayD::from_shape_vec(IxDyn(&[3]), vec![-0.1, 0.1, 0.0]).unwrap();
    let mut adam = Adam::new(0.02);
    let mut first = None;
    let mut last = 0.0;
    for _ in 0..steps {
        let tape = Tape::new();
        let pv = tape.leaf(pose.clone());
        // Points as a function of the pose on the tape.
        let base = tape.constant(positions_tensor(&mesh.positions));
        let ang = pv.slice(0, 2, 3);
        let (s, c) = (ang.sin(), ang.cos());
        let x = base.slice(1, 0, 1);
        let y = base.slice(1, 1, 2);
        let z = base.slice(1, 2, 3);
        let pts = tape.concat(
            &[
                x * c + z * s + pv.slice(0, 0, 1),
                y + pv.slice(0, 1, 2),
                z * c - x * s,
            ],
            1,
        );
        let mut vars = sc.vars(&tape, Wrt::default());
        vars.positions = pts;
        let img = sc.render(&vars).unwrap();
        let loss = (img - tape.constant(target.clone())).square().sum();
        last = loss.item().unwrap();
        first.get_or_insert(last);
        let g = tape.backward(loss).unwrap().wrt(pv);
        adam.step([(&mut pose, &g)]).unwrap();
    }
    let err = (0..3)
        .map(|k| (pose[k] - truth[k]).abs())
        .fold(0.0, f64::max);
    println!(
        "pose fit: loss {:.3} -> {last:.3}, pose {:?} (truth {truth:?})",
        first.unwrap(),
        pose.as_slice().unwrap()
    );
    PoseFit {
        first: first.unwrap(),
        last,
        err,
    }
}
