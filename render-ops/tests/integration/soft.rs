#![allow(clippy::approx_constant)] // test coordinates chosen to avoid pixel-centre ties, not constants
//! SoftRas: gradient checks, the hard limit, agreement with the SoftRas reference, determinism
//! (speed: `render-ops/benches/soft.rs`).

use std::sync::Arc;

use autodiff::gradcheck::{gradcheck, GradcheckOptions};
use autodiff::{Tape, Tensor};
use ndarray::{ArrayD, IxDyn};
use render_ops::blend::blend_hard;
use render_ops::interpolate::interpolate;
use render_ops::io::read_npy_shape;
use render_ops::mesh::Mesh;
use render_ops::raster::RasterSettings;
use render_ops::rasterize::rasterize;
use render_ops::scene::Scene;
use render_ops::soft::{softras, SoftSettings};
use render_ops::transform::to_clip;

use crate::common;
use common::{clip_row, t2};

/// Two triangles overlapping in the middle whose depth order swaps across the image (the first
/// tilts in depth through the second), plus a small third one.
fn scene() -> (Tensor<f64>, Tensor<f64>, Arc<Vec<[u32; 3]>>) {
    let clip = t2(&[
        clip_row(-0.8113, -0.7057, 2.0),
        clip_row(0.7071, -0.6023, 3.0),
        clip_row(-0.1093, 0.8011, 2.5),
        clip_row(-0.6037, 0.5113, 2.6),
        clip_row(0.1049, -0.8021, 2.4),
        clip_row(0.8017, 0.6089, 2.5),
        clip_row(0.3029, 0.2963, 1.5),
        clip_row(0.6137, 0.3471, 1.5),
        clip_row(0.4523, 0.7038, 1.6),
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
    ]);
    (clip, attrs, Arc::new(vec![[0, 1, 2], [3, 4, 5], [6, 7, 8]]))
}

fn settings(n: usize, sigma: f64, gamma: f64) -> SoftSettings {
    let mut s = SoftSettings::new(n, n, 1.0, 10.0);
    s.sigma = sigma;
    s.gamma = gamma;
    s.background = vec![0.1, 0.2, 0.3];
    s
}

fn check(n: usize, sigma: f64, gamma: f64, perspective: bool, eps: f64, atol: f64) {
    let (clip, attrs, faces) = scene();
    let mut s = settings(n, sigma, gamma);
    s.perspective_correct = perspective;
    // The depth term needs eps inside the zn range to keep the background in play.
    s.eps = 0.5;
    let opts = GradcheckOptions {
        eps,
        atol,
        rtol: 1e-3,
        ..Default::default()
    };
    let rep = gradcheck(
        |_t, v| softras(v[0], v[1], faces.clone(), &s).unwrap(),
        &[clip.clone(), attrs.clone()],
        &opts,
    )
    .unwrap();
    println!("n {n} sigma {sigma:e} gamma {gamma:e} persp {perspective}: {rep}");
    assert!(rep.passed(), "{rep}");
    // The check is not vacuous: the image depends on the positions.
    let tape = Tape::new();
    let (c, a) = (tape.leaf(clip), tape.leaf(attrs));
    let img = softras(c, a, faces, &s).unwrap();
    let g = tape.backward(img.sum()).unwrap();
    assert!(g.wrt(c).iter().any(|&x| x.abs() > 1e-6));
}

#[test]
fn gradcheck_sigma_1e2() {
    check(16, 1e-2, 1e-2, false, 1e-6, 1e-5);
    check(16, 1e-2, 1e-2, true, 1e-6, 1e-5);
}

#[test]
fn gradcheck_sigma_1e3() {
    check(24, 1e-3, 1e-3, false, 1e-7, 1e-4);
    check(24, 1e-3, 1e-3, true, 1e-7, 1e-4);
}

#[test]
fn gradcheck_sigma_1e4() {
    check(32, 1e-4, 1e-4, false, 1e-8, 1e-3);
    check(32, 1e-4, 1e-4, true, 1e-8, 1e-3);
}

#[test]
fn hard_limit_matches_hard_render() {
    let (clip, attrs, faces) = scene();
    let n = 48;
    let mut s = settings(n, 1e-7, 1e-7);
    s.perspective_correct = true;
    let tape = Tape::new();
    let (c, a) = (tape.leaf(clip.clone()), tape.leaf(attrs.clone()));
    let soft = softras(c, a, faces.clone(), &s).unwrap();
    let g = tape.backward(soft.sum()).unwrap();
    assert!(g.wrt(c).iter().all(|x| x.is_finite()));
    assert!(g.wrt(a).iter().all(|x| x.is_finite()));
    let soft = soft.value().unwrap();
    assert!(soft.iter().all(|x| x.is_finite()));

    let tape = Tape::new();
    let c = tape.constant(clip.clone());
    let r = rasterize(c, faces.clone(), &RasterSettings::new(n, n)).unwrap();
    let cols = interpolate(tape.constant(attrs), &r).unwrap();
    let hard = blend_hard(cols, &r.fragments, &[0.1, 0.2, 0.3])
        .unwrap()
        .value()
        .unwrap();

    // Pixels farther than 2 px from every projected edge.
    let ndc: Vec<[f64; 2]> = clip
        .outer_iter()
        .map(|r| [r[0] / r[3], r[1] / r[3]])
        .collect();
    let mut max = 0.0f64;
    let mut counted = 0;
    for row in 0..n {
        for col in 0..n {
            let p = [
                2.0 * (col as f64 + 0.5) / n as f64 - 1.0,
                1.0 - 2.0 * (row as f64 + 0.5) / n as f64,
            ];
            let near_edge = faces.iter().any(|f| {
                (0..3).any(|k| {
                    let (a, b) = (ndc[f[k] as usize], ndc[f[(k + 1) % 3] as usize]);
                    let e = [b[0] - a[0], b[1] - a[1]];
                    let t = (((p[0] - a[0]) * e[0] + (p[1] - a[1]) * e[1])
                        / (e[0] * e[0] + e[1] * e[1]))
                        .clamp(0.0, 1.0);
                    let d = [
                        (p[0] - a[0] - t * e[0]) * n as f64 / 2.0,
                        (p[1] - a[1] - t * e[1]) * n as f64 / 2.0,
                    ];
                    d[0].hypot(d[1]) <= 2.0
                })
            });
            if near_edge {
                continue;
            }
            counted += 1;
            for ch in 0..4 {
                max = max.max((soft[[row, col, ch]] - hard[[row, col, ch]]).abs());
            }
        }
    }
    println!("hard limit: max diff {max:e} over {counted} pixels");
    assert!(counted > n * n / 2);
    assert!(max < 1e-3, "max diff {max}");
}

fn cosine(a: &ArrayD<f64>, b: &ArrayD<f64>) -> f64 {
    let dot: f64 = a.iter().zip(b.iter()).map(|(x, y)| x * y).sum();
    let na: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    let nb: f64 = b.iter().map(|x| x * x).sum::<f64>().sqrt();
    dot / (na * nb)
}

#[test]
fn matches_softras_reference() {
    let peers = common::peers();
    let reference = peers.join("reference");
    let scene = Scene::<f64>::load(peers.join("scenes/ico5k.json")).unwrap();
    let r = &scene.desc.raster;
    let mut s = SoftSettings::new(
        128,
        128,
        scene.camera.projection().near(),
        scene.camera.projection().far(),
    );
    s.sigma = r.sigma;
    s.gamma = r.gamma;
    s.eps = r.eps;
    s.threshold = r.threshold;
    s.background = vec![0.0; 3];
    let tape = Tape::new();
    let vars = scene.vars(
        &tape,
        render_ops::pipeline::Wrt {
            positions: true,
            colors: true,
            ..Default::default()
        },
    );
    let clip = to_clip(vars.positions, &scene.camera.view_proj());
    let faces = Arc::new(scene.mesh.faces.clone());
    let img = softras(clip, vars.colors, faces, &s).unwrap();
    let v = img.value().unwrap();
    let ref_img: ArrayD<f64> =
        read_npy_shape(reference.join("softras_image.npy"), &[128, 128, 3]).unwrap();
    let ref_alpha: ArrayD<f64> =
        read_npy_shape(reference.join("softras_alpha.npy"), &[128, 128, 1]).unwrap();
    let target: ArrayD<f64> =
        read_npy_shape(reference.join("softras_target.npy"), &[128, 128, 3]).unwrap();
    let mut dimg = 0.0f64;
    let mut dalpha = 0.0f64;
    for row in 0..128 {
        for col in 0..128 {
            for ch in 0..3 {
                dimg = dimg.max((v[[row, col, ch]] - ref_img[[row, col, ch]]).abs());
            }
            dalpha = dalpha.max((v[[row, col, 3]] - ref_alpha[[row, col, 0]]).abs());
        }
    }
    // Loss over RGB only.
    let rgb = img.slice(2, 0, 3);
    let diff = rgb - tape.constant(target);
    let loss = (diff * diff).sum();
    let lv = loss.item().unwrap();
    let g = tape.backward(loss).unwrap();
    let gv = g.wrt(vars.positions);
    let gc = g.wrt(vars.colors);
    let rv: ArrayD<f64> =
        read_npy_shape(reference.join("softras_grad_vertices.npy"), &[2562, 3]).unwrap();
    let rc: ArrayD<f64> =
        read_npy_shape(reference.join("softras_grad_colors.npy"), &[2562, 3]).unwrap();
    let (cv, cc) = (cosine(&gv, &rv), cosine(&gc, &rc));
    let rel = |a: &ArrayD<f64>, b: &ArrayD<f64>| {
        let n: f64 = a
            .iter()
            .zip(b.iter())
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt();
        n / b.iter().map(|x| x * x).sum::<f64>().sqrt()
    };
    println!(
        "softras vs reference: image max abs {dimg:e}, alpha max abs {dalpha:e}, loss {lv} (ref 1404.6762174599153), \
         dL/dV cosine {cv:.9} rel l2 {:e}, dL/dC cosine {cc:.9} rel l2 {:e}",
        rel(&gv, &rv),
        rel(&gc, &rc)
    );
    assert!(dimg < 1e-9, "image {dimg}");
    assert!(dalpha < 1e-9, "alpha {dalpha}");
    assert!(cv > 0.999999 && cc > 0.999999, "cosines {cv} {cc}");
}

#[test]
fn deterministic_across_thread_counts() {
    let mesh: Mesh<f64> = Mesh::icosphere(2, 1.0);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let (clip, cols) = ico_inputs(&mesh);
            let tape = Tape::new();
            let (c, a) = (tape.leaf(clip), tape.leaf(cols));
            let s = SoftSettings::new(64, 64, 1.0, 100.0);
            let img = softras(c, a, Arc::new(mesh.faces.clone()), &s).unwrap();
            let g = tape.backward((img * img).sum()).unwrap();
            (img.value().unwrap().as_ref().clone(), g.wrt(c), g.wrt(a))
        })
    };
    let (a, b) = (run(1), run(7));
    assert!(a
        .0
        .iter()
        .zip(b.0.iter())
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    assert!(a
        .1
        .iter()
        .zip(b.1.iter())
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    assert!(a
        .2
        .iter()
        .zip(b.2.iter())
        .all(|(x, y)| x.to_bits() == y.to_bits()));
}

fn ico_inputs(mesh: &Mesh<f64>) -> (Tensor<f64>, Tensor<f64>) {
    let cam = render_ops::camera::Camera::perspective_look_at(
        [0.0, 0.0, 3.0],
        [0.0; 3],
        [0.0, 1.0, 0.0],
        45f64.to_radians(),
        1.0,
        1.0,
        100.0,
    )
    .unwrap();
    let m = cam.view_proj();
    let mut clip = Vec::new();
    let mut cols = Vec::new();
    for p in &mesh.positions {
        for row in &m {
            clip.push(row[0] * p[0] + row[1] * p[1] + row[2] * p[2] + row[3]);
        }
        cols.extend([0.5 + 0.4 * p[0], 0.5 + 0.4 * p[1], 0.5 + 0.4 * p[2]]);
    }
    let v = mesh.positions.len();
    (
        ArrayD::from_shape_vec(IxDyn(&[v, 4]), clip).unwrap(),
        ArrayD::from_shape_vec(IxDyn(&[v, 3]), cols).unwrap(),
    )
}
