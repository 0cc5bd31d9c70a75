//! The `raytrace` method: convergence to the area-integrated image, shadow and visibility
//! gradients against finite differences, an inverse task through a shadow, hard cases,
//! precision and determinism.

use crate::common;

use std::sync::Arc;

use autodiff::{Real, Tape, Tensor};
use ndarray::{ArrayD, IxDyn};
use render_ops::camera::Camera;
use render_ops::raytrace::{raytrace, LightKind, RaytraceSettings, Reflection};
use render_ops::scene::Shading;
use render_ops::shade::vertex_normals;
use render_ops::{render_attributes, to_clip, Mesh, RasterSettings};

use common::scenes::cosine;
use common::weights;

/// A scene for the ray tracer: world positions, faces, colours, camera, light rows.
#[derive(Clone)]
struct Setup {
    pos: Vec<[f64; 3]>,
    faces: Vec<[u32; 3]>,
    colors: Vec<[f64; 3]>,
    camera: Camera,
    rows: Vec<[f64; 3]>,
    s: RaytraceSettings,
}

fn tensor<T: Real>(rows: &[[f64; 3]]) -> Tensor<T> {
    ArrayD::from_shape_vec(
        IxDyn(&[rows.len(), 3]),
        rows.iter().flatten().map(|&x| T::from_f64c(x)).collect(),
    )
    .unwrap()
}

fn camera(eye: [f64; 3], at: [f64; 3], fov: f64) -> Camera {
    Camera::perspective_look_at(eye, at, [0.0, 1.0, 0.0], fov.to_radians(), 1.0, 0.1, 100.0)
        .unwrap()
}

/// Gradients with respect to positions and light rows, flattened.
type Grads = (Vec<f64>, Vec<f64>);

/// Image `[H, W, 4]` and, with `loss_w`, the gradients of `sum(loss_w * image)` with respect
/// to positions and light rows.
fn run<T: Real>(
    su: &Setup,
    pos: &[[f64; 3]],
    rows: &[[f64; 3]],
    loss_w: Option<&[f64]>,
) -> (Vec<f64>, Option<Grads>) {
    let tape = Tape::<T>::new();
    let want = loss_w.is_some();
    let p = tape.var(tensor::<T>(pos), want);
    let l = tape.var(tensor::<T>(rows), want);
    let faces = Arc::new(su.faces.clone());
    let clip = to_clip(p, &su.camera.view_proj());
    let normals = vertex_normals(p, &faces);
    let albedo = tape.constant(tensor::<T>(&su.colors));
    let img = raytrace(clip, p, normals, albedo, l, faces, &su.s).unwrap();
    let vals: Vec<f64> = img.value().unwrap().iter().map(|x| x.to_f64c()).collect();
    let grads = loss_w.map(|w| {
        let wt = tape.constant(
            ArrayD::from_shape_vec(
                IxDyn(img.shape().as_slice()),
                w.iter().map(|&x| T::from_f64c(x)).collect(),
            )
            .unwrap(),
        );
        let loss = (img * wt).sum();
        let g = tape.backward(loss).unwrap();
        let f = |v| {
            g.get(v)
                .map(|t: &Tensor<T>| t.iter().map(|x| x.to_f64c()).collect())
                .unwrap_or_default()
        };
        (f(p), f(l))
    });
    (vals, grads)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// A ground plane (y = 0, 4 x 4) and a small quad occluder at height `h` over (cx, cz),
/// lit by `lights`; the camera looks down at the plane so that the occluder is outside the
/// view (every pixel sees the plane only).
fn shadow_setup(size: usize, spp: usize, kinds: Vec<LightKind>, rows: Vec<[f64; 3]>) -> Setup {
    let mut pos = vec![
        [-2.0, 0.0, -2.0],
        [2.0, 0.0, -2.0],
        [2.0, 0.0, 2.0],
        [-2.0, 0.0, 2.0],
    ];
    let mut faces = vec![[0, 2, 1], [0, 3, 2]];
    let (h, cx, cz, r) = (1.0, -0.6, 0.0, 0.25);
    pos.extend([
        [cx - r, h, cz - r],
        [cx + r, h, cz - r * 0.6],
        [cx + r * 0.8, h, cz + r],
        [cx - r, h + 0.05, cz + r],
    ]);
    faces.extend([[4, 6, 5], [4, 7, 6]]);
    let colors = vec![[0.8, 0.7, 0.6]; pos.len()];
    let mut s = RaytraceSettings::new(size, size);
    s.spp = spp;
    s.seed = 5;
    s.eye = [0.0, 2.0, 0.3];
    s.background = [0.1, 0.1, 0.1];
    s.reflection = Reflection {
        shading: Shading::Lambert,
        ks: [0.0; 3],
        shininess: 1.0,
        ka: None,
    };
    s.lights = kinds;
    s.primary_edge_samples = size * size;
    s.shadow_edge_samples = 16 * size * size;
    s.area_edge_samples = 4;
    Setup {
        pos,
        faces,
        colors,
        camera: camera([0.0, 2.0, 0.3], [0.15, 0.0, 0.0], 40.0),
        rows,
        s,
    }
}

/// Central differences of `sum(w * image)` over the occluder's vertex coordinates (vertices
/// 4..8), at high sample counts with the same random numbers on both sides.
fn occluder_fd(su: &Setup, w: &[f64], h: f64) -> Vec<f64> {
    let mut out = Vec::new();
    for v in 4..8 {
        for k in 0..3 {
            let mut a = su.pos.clone();
            a[v][k] += h;
            let mut b = su.pos.clone();
            b[v][k] -= h;
            let fa = dot(&run::<f64>(su, &a, &su.rows, None).0, w);
            let fb = dot(&run::<f64>(su, &b, &su.rows, None).0, w);
            out.push((fa - fb) / (2.0 * h));
        }
    }
    out
}

fn occluder_check(su: &Setup, name: &str) {
    let n = su.s.width * su.s.height * 4;
    let w: Vec<f64> = weights(n).iter().map(|x| x + 0.7).collect();
    let (_, g) = run::<f64>(su, &su.pos, &su.rows, Some(&w));
    let (gp, _) = g.unwrap();
    let analytic: Vec<f64> = gp[12..24].to_vec();
    let mut fd_su = su.clone();
    fd_su.s.spp = 256;
    let fd = occluder_fd(&fd_su, &w, 0.01);
    let c = cosine(&analytic, &fd);
    let norm = dot(&analytic, &analytic).sqrt();
    eprintln!(
        "{name}: cosine {c:.4}, |analytic| {norm:.4e}, |fd| {:.4e}",
        dot(&fd, &fd).sqrt()
    );
    assert!(norm > 1e-3, "{name}: occluder gradient is zero");
    assert!(
        c >= 0.9,
        "{name}: cosine {c} analytic {analytic:?} fd {fd:?}"
    );
}

#[test]
fn point_light_shadow_moves_with_the_occluder() {
    let su = shadow_setup(
        16,
        4,
        vec![LightKind::Ambient, LightKind::Point],
        vec![[0.1; 3], [-1.2, 3.0, 0.2], [1.0, 1.0, 1.0]],
    );
    occluder_check(&su, "point");
}

#[test]
fn area_light_soft_shadow_moves_with_the_occluder() {
    // Soft shadows need more samples per pixel for the same noise (each pixel sample draws
    // `area_edge_samples` edges).
    let mut su = shadow_setup(
        16,
        16,
        vec![LightKind::Area],
        vec![
            [-1.5, 3.0, -0.2],
            [0.5, 0.0, 0.0],
            [0.0, 0.0, 0.5],
            [4.0, 4.0, 4.0],
        ],
    );
    su.s.area_edge_samples = 16;
    occluder_check(&su, "area");
}

/// Unlit render of `mesh` (vertex colours) by the ray tracer and by the hard rasterizer
/// supersampled `ss x ss` per pixel (the area-integrated reference of docs/CONVENTIONS.md).
fn unlit(mesh: &Mesh<f64>, size: usize, spp: usize) -> Setup {
    let mut s = RaytraceSettings::new(size, size);
    s.spp = spp;
    s.seed = 11;
    s.background = [0.2, 0.3, 0.4];
    Setup {
        pos: mesh.positions.clone(),
        faces: mesh.faces.clone(),
        colors: mesh
            .positions
            .iter()
            .map(|p| [0.5 + 0.4 * p[0], 0.5 + 0.4 * p[1], 0.5 + 0.3 * p[2]])
            .collect(),
        camera: camera([0.3, 0.4, 3.0], [0.0, 0.0, 0.0], 45.0),
        rows: Vec::new(),
        s,
    }
}

fn supersampled_hard(su: &Setup, pos: &[[f64; 3]], ss: usize) -> Vec<f64> {
    let tape = Tape::<f64>::new();
    let p = tape.constant(tensor::<f64>(pos));
    let clip = to_clip(p, &su.camera.view_proj());
    let col = tape.constant(tensor::<f64>(&su.colors));
    let (w, h) = (su.s.width, su.s.height);
    let rs = RasterSettings::new(w * ss, h * ss);
    let img = render_attributes(clip, col, Arc::new(su.faces.clone()), &rs, &su.s.background)
        .unwrap()
        .value()
        .unwrap();
    let mut out = vec![0.0; h * w * 4];
    for r in 0..h * ss {
        for c in 0..w * ss {
            for ch in 0..4 {
                out[((r / ss) * w + c / ss) * 4 + ch] += img[[r, c, ch]] / (ss * ss) as f64;
            }
        }
    }
    out
}

fn rmse(a: &[f64], b: &[f64]) -> f64 {
    (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len() as f64).sqrt()
}

#[test]
fn converges_to_the_supersampled_hard_render() {
    let mesh = Mesh::<f64>::icosphere(2, 1.0);
    let su = unlit(&mesh, 24, 1);
    let reference = supersampled_hard(&su, &su.pos, 16);
    let mut errs = Vec::new();
    for spp in [1, 4, 16, 64] {
        let mut s = su.clone();
        s.s.spp = spp;
        errs.push(rmse(&run::<f64>(&s, &s.pos, &[], None).0, &reference));
    }
    eprintln!("rmse by spp 1, 4, 16, 64: {errs:?}");
    // Stratified sampling: the error falls at least as 1/sqrt(spp) (edge pixels: faster).
    for k in 1..4 {
        assert!(errs[k] < errs[k - 1] * 0.6, "{errs:?}");
    }
    assert!(errs[3] < 0.01, "{errs:?}");
}

/// Per-vertex gradient of `sum(w * image)` against central differences of the supersampled
/// hard render, over every third vertex (the test's time); the cosine.
fn visibility_cosine(mesh: &Mesh<f64>) -> f64 {
    let items: Vec<usize> = (0..mesh.positions.len()).step_by(3).collect();
    visibility_cosine_of(mesh, &items)
}

fn visibility_cosine_of(mesh: &Mesh<f64>, items: &[usize]) -> f64 {
    let su = unlit(mesh, 16, 16);
    let mut su = su;
    su.s.primary_edge_samples = 64 * 16 * 16;
    let w: Vec<f64> = weights(16 * 16 * 4);
    let (_, g) = run::<f64>(&su, &su.pos, &[], Some(&w));
    let analytic = g.unwrap().0;
    let h = 0.02;
    let analytic: Vec<f64> = items
        .iter()
        .flat_map(|&v| analytic[3 * v..3 * v + 3].to_vec())
        .collect();
    let mut fd = Vec::new();
    for &v in items {
        for k in 0..3 {
            let mut a = su.pos.clone();
            a[v][k] += h;
            let mut b = su.pos.clone();
            b[v][k] -= h;
            let fa = dot(&supersampled_hard(&su, &a, 16), &w);
            let fb = dot(&supersampled_hard(&su, &b, 16), &w);
            fd.push((fa - fb) / (2.0 * h));
        }
    }
    cosine(&analytic, &fd)
}

fn visibility_check(mesh: &Mesh<f64>, name: &str) {
    let c = visibility_cosine(mesh);
    eprintln!("{name}: cosine {c:.4}");
    assert!(c >= 0.9, "{name}: cosine {c}");
}

/// A floor strip from behind the eye to in front of it: its long edges cross the near plane
/// and only their parts in front of it are in the image (the cut by the near plane itself
/// projects far below the image). The gradient of the strip's four vertices, two behind the
/// eye, against the supersampled reference.
#[test]
fn primary_edges_crossing_the_near_plane() {
    let pos = vec![
        [-0.7, -0.5, 3.6],
        [-0.1, -0.5, 3.6],
        [-0.1, -0.5, -1.0],
        [-0.7, -0.5, -1.0],
    ];
    let mesh = Mesh::new(pos, vec![[0, 2, 1], [0, 3, 2]]);
    let c = visibility_cosine_of(&mesh, &[0, 1, 2, 3]);
    eprintln!("strip across the near plane: cosine {c:.4}");
    assert!(c >= 0.9, "cosine {c}");
}

#[test]
fn primary_visibility_gradient_of_a_sphere() {
    visibility_check(&Mesh::<f64>::icosphere(1, 1.0), "sphere");
}

#[test]
fn primary_visibility_gradient_of_a_self_occluding_mesh() {
    // Two spheres in one mesh, the front one covering part of the back one.
    let a = Mesh::<f64>::icosphere(1, 0.7);
    let n = a.positions.len() as u32;
    let mut pos: Vec<[f64; 3]> = a
        .positions
        .iter()
        .map(|p| [p[0] - 0.35, p[1], p[2]])
        .collect();
    pos.extend(
        a.positions
            .iter()
            .map(|p| [p[0] + 0.45, p[1] + 0.1, p[2] - 0.9]),
    );
    let mut faces = a.faces.clone();
    faces.extend(a.faces.iter().map(|f| f.map(|i| i + n)));
    visibility_check(&Mesh::new(pos, faces), "two spheres");
}

/// Occluder vertices moved by `d`.
fn translated(pos: &[[f64; 3]], d: [f64; 3]) -> Vec<[f64; 3]> {
    pos.iter()
        .enumerate()
        .map(|(i, p)| {
            if i >= 4 {
                [p[0] + d[0], p[1] + d[1], p[2] + d[2]]
            } else {
                *p
            }
        })
        .collect()
}

#[test]
fn inverse_task_recovers_the_occluder_from_its_shadow_alone() {
    // The occluder is outside the view: only its shadow on the plane is seen.
    let su = shadow_setup(
        16,
        4,
        vec![LightKind::Ambient, LightKind::Point],
        vec![[0.1; 3], [-1.2, 3.0, 0.2], [1.0, 1.0, 1.0]],
    );
    let target = run::<f64>(&su, &su.pos, &su.rows, None).0;
    let start = [0.2, 0.1, -0.15];
    let mut d = start;
    let (mut m, mut v) = ([0.0; 3], [0.0; 3]);
    let (lr, b1, b2) = (0.02, 0.9, 0.999);
    for it in 1..=60 {
        let pos = translated(&su.pos, d);
        let img = run::<f64>(&su, &pos, &su.rows, None).0;
        // L = sum (img - target)^2: the linear loss's weights are 2 (img - target).
        let w: Vec<f64> = img
            .iter()
            .zip(&target)
            .map(|(a, b)| 2.0 * (a - b))
            .collect();
        let (gp, _) = run::<f64>(&su, &pos, &su.rows, Some(&w)).1.unwrap();
        for k in 0..3 {
            let g: f64 = (4..8).map(|i| gp[3 * i + k]).sum();
            m[k] = b1 * m[k] + (1.0 - b1) * g;
            v[k] = b2 * v[k] + (1.0 - b2) * g * g;
            let mh = m[k] / (1.0 - b1.powi(it));
            let vh = v[k] / (1.0 - b2.powi(it));
            d[k] -= lr * mh / (vh.sqrt() + 1e-12);
        }
    }
    let err = dot(&d, &d).sqrt();
    let err0 = dot(&start, &start).sqrt();
    eprintln!("occluder position error {err0:.3} -> {err:.4} ({d:?})");
    assert!(err < 0.25 * err0, "{err0} -> {err}: {d:?}");
}

fn all_finite(su: &Setup) {
    let n = su.s.width * su.s.height * 4;
    let w = weights(n);
    let (img, g) = run::<f64>(su, &su.pos, &su.rows, Some(&w));
    let (gp, gl) = g.unwrap();
    assert!(img.iter().all(|x| x.is_finite()));
    assert!(gp.iter().chain(&gl).all(|x| x.is_finite()));
}

#[test]
fn hard_cases_give_finite_images_and_gradients() {
    let point = || {
        shadow_setup(
            12,
            2,
            vec![LightKind::Ambient, LightKind::Point, LightKind::Area],
            vec![
                [0.1; 3],
                [-1.2, 3.0, 0.2],
                [1.0, 1.0, 1.0],
                [-1.5, 3.0, -0.2],
                [0.5, 0.0, 0.0],
                [0.0, 0.0, 0.5],
                [4.0, 4.0, 4.0],
            ],
        )
    };
    // Grazing: the camera in the ground plane's plane, looking along it.
    let mut g = point();
    g.camera = camera([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], 40.0);
    g.s.eye = [0.0, 0.0, 3.0];
    all_finite(&g);
    // Degenerate triangles (a repeated vertex, collinear vertices) added to the mesh.
    let mut d = point();
    d.faces.extend([[4, 4, 5], [0, 1, 1]]);
    d.pos.push([0.0, 0.5, 0.0]);
    d.pos.push([0.5, 0.5, 0.0]);
    d.pos.push([1.0, 0.5, 0.0]);
    d.colors.extend([[1.0; 3]; 3]);
    d.faces.push([8, 9, 10]);
    all_finite(&d);
    // A point light inside a closed mesh (everything outside it is in shadow).
    let mut inside = point();
    let sphere = Mesh::<f64>::icosphere(1, 0.3);
    let base = inside.pos.len() as u32;
    inside
        .pos
        .extend(sphere.positions.iter().map(|p| [p[0], p[1] + 0.5, p[2]]));
    inside.colors.extend(vec![[0.5; 3]; sphere.positions.len()]);
    inside
        .faces
        .extend(sphere.faces.iter().map(|f| f.map(|i| i + base)));
    inside.rows[1] = [0.0, 0.5, 0.0];
    let (img, _) = run::<f64>(&inside, &inside.pos, &inside.rows, None);
    all_finite(&inside);
    // Many tiny triangles over the plane.
    let mut tiny = point();
    for i in 0..20000u32 {
        let (x, z) = ((i % 200) as f64 * 0.01 - 1.0, (i / 200) as f64 * 0.01 - 0.5);
        let b = tiny.pos.len() as u32;
        tiny.pos
            .extend([[x, 0.3, z], [x + 1e-4, 0.3, z], [x, 0.3, z + 1e-4]]);
        tiny.colors.extend([[0.9; 3]; 3]);
        tiny.faces.push([b, b + 1, b + 2]);
    }
    all_finite(&tiny);
    // The enclosed point light reaches nothing the camera sees: the image is that of the
    // same scene with the point light switched off.
    let mut off = inside.clone();
    off.rows[2] = [0.0; 3];
    let (img_off, _) = run::<f64>(&off, &off.pos, &off.rows, None);
    let d = img
        .iter()
        .zip(&img_off)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(d < 1e-12, "{d}");
}

#[test]
fn an_edge_exactly_on_a_pixel_boundary() {
    // A square whose left edge projects onto NDC x = 0, the boundary between the two middle
    // columns of an even-width image.
    let mut s = RaytraceSettings::new(8, 8);
    s.spp = 4;
    let su = Setup {
        pos: vec![
            [0.0, -0.5, 0.0],
            [0.6, -0.5, 0.0],
            [0.6, 0.5, 0.0],
            [0.0, 0.5, 0.0],
        ],
        faces: vec![[0, 1, 2], [0, 2, 3]],
        colors: vec![[1.0; 3]; 4],
        camera: camera([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], 45.0),
        rows: Vec::new(),
        s,
    };
    let (img, g) = run::<f64>(&su, &su.pos, &[], Some(&weights(8 * 8 * 4)));
    for r in 0..8 {
        for c in 0..4 {
            assert_eq!(img[(r * 8 + c) * 4 + 3], 0.0, "left half uncovered");
        }
    }
    let (gp, _) = g.unwrap();
    assert!(gp.iter().all(|x| x.is_finite()));
    // The edge's vertices get a horizontal gradient (the edge sample's two sides differ).
    assert!(gp[0].abs() > 0.0 && gp[9].abs() > 0.0, "{gp:?}");
}

#[test]
fn f32_agrees_with_f64_and_results_do_not_depend_on_threads() {
    let su = shadow_setup(
        12,
        2,
        vec![LightKind::Ambient, LightKind::Point, LightKind::Area],
        vec![
            [0.1; 3],
            [-1.2, 3.0, 0.2],
            [1.0, 1.0, 1.0],
            [-1.5, 3.0, -0.2],
            [0.5, 0.0, 0.0],
            [0.0, 0.0, 0.5],
            [4.0, 4.0, 4.0],
        ],
    );
    let w = weights(12 * 12 * 4);
    let (i64_, g64) = run::<f64>(&su, &su.pos, &su.rows, Some(&w));
    let (i32_, g32) = run::<f32>(&su, &su.pos, &su.rows, Some(&w));
    let diff = i64_
        .iter()
        .zip(&i32_)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(diff < 1e-3, "image {diff}");
    let (a, b) = (g64.unwrap(), g32.unwrap());
    let c = cosine(&[a.0.clone(), a.1.clone()].concat(), &[b.0, b.1].concat());
    assert!(c > 0.999, "gradient cosine f32 / f64 {c}");
    let mut runs = Vec::new();
    for threads in [1, 2, 3] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        runs.push(pool.install(|| run::<f64>(&su, &su.pos, &su.rows, Some(&w))));
    }
    for r in &runs[1..] {
        assert_eq!(r.0, runs[0].0);
        assert_eq!(r.1, runs[0].1);
    }
    assert_eq!(runs[0].0, i64_);
}

#[test]
fn bad_inputs_are_typed_errors() {
    let tape = Tape::<f64>::new();
    let su = unlit(&Mesh::<f64>::icosphere(0, 1.0), 4, 1);
    let p = tape.var(tensor::<f64>(&su.pos), true);
    let clip = to_clip(p, &su.camera.view_proj());
    let faces = Arc::new(su.faces.clone());
    let n = tape.constant(tensor::<f64>(&su.pos));
    let lights = tape.constant(ArrayD::zeros(IxDyn(&[0, 3])));
    let ok = |s: &RaytraceSettings, world, albedo, faces: Arc<Vec<[u32; 3]>>| {
        raytrace(clip, world, n, albedo, lights, faces, s).map(|_| ())
    };
    assert!(ok(&su.s, p, n, faces.clone()).is_ok());
    // Wrong shape, NaN, a face past the vertices, zero samples, a light with missing rows.
    let short = tape.constant(tensor::<f64>(&su.pos[..3]));
    assert!(ok(&su.s, short, n, faces.clone()).is_err());
    let mut bad = su.pos.clone();
    bad[1][2] = f64::NAN;
    let nan = tape.constant(tensor::<f64>(&bad));
    let e = ok(&su.s, p, nan, faces.clone()).unwrap_err();
    assert!(e.to_string().contains("albedo"), "{e}");
    let e = ok(&su.s, p, n, Arc::new(vec![[0, 1, 99]])).unwrap_err();
    assert!(e.to_string().contains("face 0"), "{e}");
    let mut s = su.s.clone();
    s.spp = 0;
    assert!(ok(&s, p, n, faces.clone()).is_err());
    let mut s = su.s.clone();
    s.lights = vec![LightKind::Point];
    assert!(ok(&s, p, n, faces).is_err());
}

#[test]
fn constant_lights_need_no_gradient() {
    // Light rows as constants (the scene's default): the position gradient is the same.
    let su = shadow_setup(
        8,
        2,
        vec![LightKind::Ambient, LightKind::Point, LightKind::Area],
        vec![
            [0.1; 3],
            [-1.2, 3.0, 0.2],
            [1.0, 1.0, 1.0],
            [-1.5, 3.0, -0.2],
            [0.5, 0.0, 0.0],
            [0.0, 0.0, 0.5],
            [4.0, 4.0, 4.0],
        ],
    );
    let w = weights(8 * 8 * 4);
    let (_, g) = run::<f64>(&su, &su.pos, &su.rows, Some(&w));
    let tape = Tape::<f64>::new();
    let p = tape.var(tensor::<f64>(&su.pos), true);
    let faces = Arc::new(su.faces.clone());
    let clip = to_clip(p, &su.camera.view_proj());
    let img = raytrace(
        clip,
        p,
        vertex_normals(p, &faces),
        tape.constant(tensor::<f64>(&su.colors)),
        tape.constant(tensor::<f64>(&su.rows)),
        faces,
        &su.s,
    )
    .unwrap();
    let wt = tape.constant(ArrayD::from_shape_vec(IxDyn(&[8, 8, 4]), w).unwrap());
    let grads = tape.backward((img * wt).sum()).unwrap();
    let gp: Vec<f64> = grads.get(p).unwrap().iter().copied().collect();
    assert_eq!(gp, g.unwrap().0);
}

/// Gradients of the op's own image with respect to albedo and light rows (smooth at fixed
/// samples when nothing changes visibility: no shadows, lights moved a little) against f64
/// central differences of the same render (same seed).
#[test]
fn appearance_gradients_match_finite_differences_of_the_own_image() {
    let mut su = shadow_setup(
        8,
        2,
        vec![
            LightKind::Ambient,
            LightKind::Directional,
            LightKind::Point,
            LightKind::Area,
        ],
        vec![
            [0.1; 3],
            [0.3, -1.0, -0.2],
            [0.5, 0.4, 0.3],
            [-1.2, 3.0, 0.2],
            [1.0, 1.0, 1.0],
            [-1.5, 3.0, -0.2],
            [0.5, 0.0, 0.0],
            [0.0, 0.0, 0.5],
            [4.0, 4.0, 4.0],
        ],
    );
    su.s.shadows = false;
    su.s.reflection.shading = Shading::BlinnPhong;
    su.s.reflection.ks = [0.3; 3];
    su.s.reflection.shininess = 8.0;
    let w = weights(8 * 8 * 4);
    let eval = |alb: &[[f64; 3]], rows: &[[f64; 3]], grad: bool| {
        let tape = Tape::<f64>::new();
        let p = tape.constant(tensor::<f64>(&su.pos));
        let a = tape.var(tensor::<f64>(alb), grad);
        let l = tape.var(tensor::<f64>(rows), grad);
        let faces = Arc::new(su.faces.clone());
        let clip = to_clip(p, &su.camera.view_proj());
        let img = raytrace(clip, p, vertex_normals(p, &faces), a, l, faces, &su.s).unwrap();
        let wt = tape.constant(ArrayD::from_shape_vec(IxDyn(&[8, 8, 4]), w.clone()).unwrap());
        let loss = (img * wt).sum();
        let v = loss.value().unwrap().iter().sum::<f64>();
        let g = grad.then(|| {
            let g = tape.backward(loss).unwrap();
            let f = |x| g.get(x).unwrap().iter().copied().collect::<Vec<f64>>();
            (f(a), f(l))
        });
        (v, g)
    };
    let (_, g) = eval(&su.colors, &su.rows, true);
    let (ga, gl) = g.unwrap();
    let h = 1e-6;
    let mut checked = 0;
    for (which, base) in [(0, su.colors.clone()), (1, su.rows.clone())] {
        for i in 0..base.len() {
            for k in 0..3 {
                let mut p = base.clone();
                p[i][k] += h;
                let mut m = base.clone();
                m[i][k] -= h;
                let (fp, fm) = if which == 0 {
                    (eval(&p, &su.rows, false).0, eval(&m, &su.rows, false).0)
                } else {
                    (eval(&su.colors, &p, false).0, eval(&su.colors, &m, false).0)
                };
                let num = (fp - fm) / (2.0 * h);
                let ana = if which == 0 {
                    ga[3 * i + k]
                } else {
                    gl[3 * i + k]
                };
                assert!(
                    (num - ana).abs() <= 1e-5 * (1.0 + num.abs()),
                    "{} [{i}][{k}]: analytic {ana} numeric {num}",
                    ["albedo", "light rows"][which]
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 40);
}
