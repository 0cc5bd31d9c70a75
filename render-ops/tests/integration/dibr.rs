#![allow(clippy::needless_range_loop)]
//! DIB-R: gradient checks of the soft silhouette, the foreground against the hard render (op
//! level and through `Scene::render`), the threshold truncation bound, stability for tiny
//! delta, determinism across thread counts, and typed errors.

use std::path::PathBuf;
use std::sync::Arc;

use autodiff::gradcheck::{gradcheck, GradcheckOptions};
use autodiff::{Tape, Tensor};
use ndarray::{ArrayD, IxDyn};
use render_ops::blend::blend_hard;
use render_ops::interpolate::interpolate;
use render_ops::mesh::Mesh;
use render_ops::obj::write_obj;
use render_ops::pipeline::Wrt;
use render_ops::raster::RasterSettings;
use render_ops::rasterize::rasterize;
use render_ops::scene::Scene;
use render_ops::soft::{dibr, dibr_alpha, DibrSettings};

use crate::common;
use common::{clip_row, t2};

/// Two overlapping triangles (depth order swapping across the image), a small third one
/// (clockwise) and a sliver, at coordinates that avoid pixel-centre ties.
fn scene() -> (Tensor<f64>, Tensor<f64>, Arc<Vec<[u32; 3]>>) {
    let clip = t2(&[
        clip_row(-0.8113, -0.7057, 2.0),
        clip_row(0.7073, -0.6023, 3.0),
        clip_row(-0.1093, 0.8011, 2.5),
        clip_row(-0.6037, 0.5113, 2.6),
        clip_row(0.1049, -0.8021, 2.4),
        clip_row(0.8017, 0.6089, 2.5),
        clip_row(0.3029, 0.2963, 1.5),
        clip_row(0.4523, 0.7038, 1.6),
        clip_row(0.6137, 0.3471, 1.5),
        clip_row(-0.9031, 0.8517, 2.0),
        clip_row(-0.8543, 0.7021, 2.1),
        clip_row(-0.8999, 0.7039, 2.2),
    ]);
    let attrs = t2(&[
        vec![1.0, 0.2, 0.1],
        vec![0.1, 0.9, 0.3],
        vec![0.2, 0.3, 1.0],
        vec![0.8, 0.8, 0.1],
        vec![0.1, 0.7, 0.7],
        vec![0.6, 0.1, 0.6],
        vec![0.3, 0.3, 0.3],
        vec![0.9, 0.5, 0.2],
        vec![0.4, 0.9, 0.6],
        vec![0.5, 0.5, 0.9],
        vec![0.2, 0.8, 0.4],
        vec![0.7, 0.1, 0.3],
    ]);
    (
        clip,
        attrs,
        Arc::new(vec![[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]]),
    )
}

fn settings(n: usize, delta: f64) -> DibrSettings {
    let mut s = DibrSettings::new(n, n);
    s.delta = delta;
    s.background = vec![0.1, 0.2, 0.3];
    s
}

fn check_alpha(n: usize, delta: f64, eps: f64, atol: f64) {
    let (clip, _, faces) = scene();
    let mut s = settings(n, delta);
    // A tiny threshold keeps the cut-off far from every pixel (no jump inside the stencil).
    s.threshold = 1e-30;
    let opts = GradcheckOptions {
        eps,
        atol,
        rtol: 1e-3,
        ..Default::default()
    };
    let rep = gradcheck(
        |_t, v| dibr_alpha(v[0], faces.clone(), &s).unwrap(),
        std::slice::from_ref(&clip),
        &opts,
    )
    .unwrap();
    println!("dibr alpha n {n} delta {delta:e}: {rep}");
    assert!(rep.passed(), "{rep}");
    // Not vacuous: alpha depends on the positions, and on x, y and w of several vertices.
    let tape = Tape::new();
    let c = tape.leaf(clip);
    let a = dibr_alpha(c, faces, &s).unwrap();
    let g = tape.backward(a.sum()).unwrap().wrt(c);
    let moved = (0..g.shape()[0])
        .filter(|&v| g[[v, 0]].abs() > 1e-6 && g[[v, 3]].abs() > 1e-6)
        .count();
    assert!(moved >= 9, "{moved} vertices with x and w gradients");
    assert!((0..g.shape()[0]).all(|v| g[[v, 2]] == 0.0));
}

#[test]
fn gradcheck_alpha_delta_1e2() {
    check_alpha(16, 1e-2, 1e-6, 1e-5);
}

#[test]
fn gradcheck_alpha_delta_1e3() {
    check_alpha(24, 1e-3, 1e-7, 1e-4);
}

#[test]
fn gradcheck_alpha_delta_1e4() {
    check_alpha(32, 1e-4, 1e-8, 1e-3);
}

/// The same check through the full `dibr` op (hard foreground + soft alpha), with respect to
/// positions and attributes, with a loss weighted away from edges where the hard foreground
/// is discontinuous: the interior barycentric gradients and the alpha gradients together.
#[test]
fn gradcheck_full_dibr_interior() {
    let (clip, attrs, faces) = scene();
    let n = 16;
    let s = settings(n, 1e-2);
    // Weights: zero on the RGB of pixels within 1.5 px of an edge, one elsewhere.
    let ndc: Vec<[f64; 2]> = clip
        .outer_iter()
        .map(|r| [r[0] / r[3], r[1] / r[3]])
        .collect();
    let mut wts = ArrayD::<f64>::ones(IxDyn(&[n, n, 4]));
    for row in 0..n {
        for col in 0..n {
            if near_edge(&ndc, &faces, row, col, n, 1.5) {
                for ch in 0..3 {
                    wts[[row, col, ch]] = 0.0;
                }
            }
        }
    }
    let rep = gradcheck(
        |t, v| {
            let img = dibr(v[0], v[1], faces.clone(), &s).unwrap();
            (img * t.constant(wts.clone())).sum()
        },
        &[clip, attrs],
        &GradcheckOptions::default(),
    )
    .unwrap();
    println!("dibr full: {rep}");
    assert!(rep.passed(), "{rep}");
}

/// Whether pixel (row, col) lies within `px` pixels of a projected edge.
fn near_edge(
    ndc: &[[f64; 2]],
    faces: &[[u32; 3]],
    row: usize,
    col: usize,
    n: usize,
    px: f64,
) -> bool {
    let p = [
        2.0 * (col as f64 + 0.5) / n as f64 - 1.0,
        1.0 - 2.0 * (row as f64 + 0.5) / n as f64,
    ];
    faces.iter().any(|f| {
        (0..3).any(|k| {
            let (a, b) = (ndc[f[k] as usize], ndc[f[(k + 1) % 3] as usize]);
            let e = [b[0] - a[0], b[1] - a[1]];
            let t = (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1]) / (e[0] * e[0] + e[1] * e[1]))
                .clamp(0.0, 1.0);
            let d = [
                (p[0] - a[0] - t * e[0]) * n as f64 / 2.0,
                (p[1] - a[1] - t * e[1]) * n as f64 / 2.0,
            ];
            d[0].hypot(d[1]) <= px
        })
    })
}

#[test]
fn foreground_equals_hard_render() {
    let (clip, attrs, faces) = scene();
    let n = 48;
    let s = settings(n, 1e-3);
    let tape = Tape::new();
    let (c, a) = (tape.leaf(clip.clone()), tape.leaf(attrs.clone()));
    let img = dibr(c, a, faces.clone(), &s).unwrap();
    let soft = img.value().unwrap();
    let tape2 = Tape::new();
    let r = rasterize(tape2.constant(clip), faces, &RasterSettings::new(n, n)).unwrap();
    let cols = interpolate(tape2.constant(attrs), &r).unwrap();
    let hard = blend_hard(cols, &r.fragments, &[0.1, 0.2, 0.3])
        .unwrap()
        .value()
        .unwrap();
    let (mut covered, mut halo) = (0, 0);
    for row in 0..n {
        for col in 0..n {
            for ch in 0..3 {
                // RGB is the hard render everywhere (background off the faces).
                assert_eq!(soft[[row, col, ch]], hard[[row, col, ch]]);
            }
            let alpha = soft[[row, col, 3]];
            assert!((0.0..=1.0).contains(&alpha));
            if hard[[row, col, 3]] == 1.0 {
                covered += 1;
                assert_eq!(alpha, 1.0, "covered pixel ({row}, {col})");
            } else if alpha > 1e-3 {
                halo += 1;
            }
        }
    }
    assert!(covered > n * n / 4, "{covered}");
    assert!(halo > n, "soft halo of {halo} pixels");
    // Gradients reach the positions through both the interior and the halo.
    let g = tape.backward(img.sum()).unwrap();
    assert!(g.wrt(c).iter().all(|x| x.is_finite()));
    assert!(g.wrt(c).iter().any(|x| x.abs() > 1e-6));
}

/// The threshold drops faces whose term is below it: each dropped face changes alpha by at
/// most `threshold * (1 - alpha)`.
#[test]
fn threshold_truncation_error_is_bounded() {
    let (clip, _, faces) = scene();
    let n = 64;
    for &delta in &[1e-3, 1e-4] {
        let render = |threshold: f64| {
            let mut s = settings(n, delta);
            s.threshold = threshold;
            let tape = Tape::new();
            (*dibr_alpha(tape.constant(clip.clone()), faces.clone(), &s)
                .unwrap()
                .value()
                .unwrap())
            .clone()
        };
        let exact = render(1e-300);
        for &th in &[1e-2, 1e-4, 1e-6] {
            let cut = render(th);
            let err = exact
                .iter()
                .zip(cut.iter())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            println!("dibr delta {delta:e} threshold {th:e}: max alpha truncation error {err:e}");
            assert!(err <= faces.len() as f64 * th, "{err}");
            assert!(cut.iter().zip(exact.iter()).all(|(c, e)| c <= e));
        }
    }
}

#[test]
fn tiny_delta_is_finite_and_hard() {
    let (clip, _, faces) = scene();
    let n = 32;
    let s = settings(n, 1e-9);
    let tape = Tape::new();
    let c = tape.leaf(clip.clone());
    let a = dibr_alpha(c, faces.clone(), &s).unwrap();
    let g = tape.backward((a * a).sum()).unwrap().wrt(c);
    assert!(g.iter().all(|x| x.is_finite()));
    let a = a.value().unwrap();
    let tape2 = Tape::new();
    let r = rasterize(tape2.constant(clip), faces, &RasterSettings::new(n, n)).unwrap();
    let mut diff = 0;
    for row in 0..n {
        for col in 0..n {
            let hard = if r.fragments.count(row * n + col) > 0 {
                1.0
            } else {
                0.0
            };
            assert!(a[[row, col]].is_finite());
            if (a[[row, col]] - hard).abs() > 1e-3 {
                diff += 1;
            }
        }
    }
    assert_eq!(diff, 0);
}

#[test]
fn deterministic_across_thread_counts() {
    let mesh: Mesh<f64> = Mesh::icosphere(3, 1.0);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let m = render_ops::camera::Camera::perspective_look_at(
                [0.3, 0.2, 3.0],
                [0.0; 3],
                [0.0, 1.0, 0.0],
                45f64.to_radians(),
                1.0,
                1.0,
                100.0,
            )
            .unwrap()
            .view_proj();
            let clip: Vec<f64> = mesh
                .positions
                .iter()
                .flat_map(|p| m.map(|r| r[0] * p[0] + r[1] * p[1] + r[2] * p[2] + r[3]))
                .collect();
            let v = mesh.positions.len();
            let tape = Tape::new();
            let c = tape.leaf(ArrayD::from_shape_vec(IxDyn(&[v, 4]), clip).unwrap());
            let mut s = DibrSettings::new(80, 72);
            s.delta = 1e-4;
            let a = dibr_alpha(c, Arc::new(mesh.faces.clone()), &s).unwrap();
            let g = tape.backward((a * a).sum()).unwrap();
            (a.value().unwrap().as_ref().clone(), g.wrt(c))
        })
    };
    let (a, b) = (run(1), run(5));
    let same = |x: &ArrayD<f64>, y: &ArrayD<f64>| {
        x.iter()
            .zip(y.iter())
            .all(|(p, q)| p.to_bits() == q.to_bits())
    };
    assert!(same(&a.0, &b.0) && same(&a.1, &b.1));
    assert!(a.1.iter().any(|x| x.abs() > 1e-6));
}

#[test]
fn bad_inputs_are_typed_errors() {
    let (clip, attrs, faces) = scene();
    let tape = Tape::new();
    let (c, a) = (tape.leaf(clip), tape.leaf(attrs));
    for s in [
        settings(16, 0.0),
        settings(16, f64::NAN),
        DibrSettings {
            threshold: 1.0,
            ..settings(16, 1e-3)
        },
        settings(0, 1e-3),
    ] {
        assert!(dibr_alpha(c, faces.clone(), &s).is_err());
        assert!(dibr(c, a, faces.clone(), &s).is_err());
    }
    let s = settings(16, 1e-3);
    assert!(dibr_alpha(c, Arc::new(vec![[0, 1, 99]]), &s).is_err());
    assert!(dibr_alpha(c.slice(1, 0, 3), faces.clone(), &s).is_err());
    assert!(dibr(c, a.slice(0, 0, 5), faces.clone(), &s).is_err());
    let mut s4 = s.clone();
    s4.background = vec![0.0; 4];
    assert!(dibr(c, a, faces, &s4).is_err());
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-dibr-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Through `Scene::render`: method `dibr` gives the RGB of method `hard` (Phong shading per
/// fragment, through the composed soft stage; to rounding) and an alpha that is 1 on covered pixels and soft around them, with finite,
/// non-zero position gradients.
#[test]
fn scene_dibr_matches_scene_hard() {
    let dir = temp_dir("scene");
    let mesh: Mesh<f64> = Mesh::icosphere(2, 0.8);
    write_obj(dir.join("m.obj"), &mesh).unwrap();
    let load = |method: &str| {
        let json = format!(
            r#"{{"mesh": "m.obj",
            "camera": {{"eye": [0.6, 0.8, 3.2], "at": [0, 0, 0], "up": [0, 1, 0],
                       "fov_y_deg": 40, "near": 0.5, "far": 10}},
            "image": {{"width": 40, "height": 36, "background": [0.1, 0.2, 0.3]}},
            "lights": [{{"type": "directional", "direction": [-0.4, -0.5, -1],
                         "color": [1, 0.9, 0.8]}}, {{"type": "ambient", "color": [0.2, 0.2, 0.2]}}],
            "material": {{"shading": "phong", "kd": [0.9, 0.8, 0.7], "ks": [0.4, 0.4, 0.4],
                         "shininess": 20}},
            "raster": {{"method": "{method}", "delta": 1e-3}}}}"#
        );
        Scene::<f64>::from_json(&json, &dir, "s.json").unwrap()
    };
    let (hard, soft) = (load("hard"), load("dibr"));
    let tape = Tape::new();
    let hv = hard.vars(&tape, Wrt::default());
    let hi = hard.render(&hv).unwrap().value().unwrap();
    let sv = soft.vars(
        &tape,
        Wrt {
            positions: true,
            ..Wrt::default()
        },
    );
    let img = soft.render(&sv).unwrap();
    let si = img.value().unwrap();
    assert_eq!(si.shape(), &[36, 40, 4]);
    let mut halo = 0;
    for row in 0..36 {
        for col in 0..40 {
            // The lit scene goes through the soft stage, whose perspective-correct
            // barycentrics are computed in another order than the hard rasterizer's.
            for ch in 0..3 {
                let d = (si[[row, col, ch]] - hi[[row, col, ch]]).abs();
                assert!(d < 1e-12, "({row}, {col}, {ch}): {d:e}");
            }
            if hi[[row, col, 3]] == 1.0 {
                assert_eq!(si[[row, col, 3]], 1.0);
            } else if si[[row, col, 3]] > 1e-3 {
                halo += 1;
            }
        }
    }
    assert!(halo > 20, "{halo}");
    let alpha = img.slice(2, 3, 4);
    let g = tape.backward(alpha.sum()).unwrap().wrt(sv.positions);
    assert!(g.iter().all(|x| x.is_finite()));
    assert!(g.iter().any(|x| x.abs() > 1e-6));
    std::fs::remove_dir_all(&dir).ok();
}
