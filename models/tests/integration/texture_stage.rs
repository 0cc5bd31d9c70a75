//! The detail stage (`models::fit::fit_texture`): a known albedo texture is recovered from a
//! render with known geometry, pose and light, and the fitted face's OBJ + MTL + PNG read
//! back through Tapestry's own loaders.

use std::sync::Arc;

use models::fit::{self, FaceParams, FaceRenderer, RenderOptions, TextureOptions};
use models::Morphable;
use ndarray::{Array2, Array3};
use render_ops::io::write_png;
use render_ops::obj::parse_obj_str;
use render_ops::texture::load_png;

fn scratch(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-texture-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The shipped MediaPipe-mesh model (it has uvs), slightly turned and lit from the side.
fn scene() -> (Morphable<f64>, FaceParams) {
    let model = models::face::default_face::<f64>();
    let mut p = FaceParams::neutral(&model);
    p.rotation = fit::euler_to_axis_angle(0.25, -0.1, 0.0);
    p.translation[2] = -450.0;
    p.sh[1] = [0.3, 0.25, 0.2];
    p.sh[3] = [0.6, 0.5, 0.45];
    (model, p)
}

/// A 96 x 96 render with a known 48 x 48 texture (the mean albedo with a smooth colour
/// pattern) is fitted from the mean albedo: the masked RMSE drops by more than 10x, and over
/// the texels that the photo sees with a weight of at least a pixel, the mean absolute
/// texture error drops by more than 10x to under 0.005 (measured: RMSE 0.0564 -> 0.0016,
/// texture error 0.0452 -> 0.0006).
#[test]
fn known_texture_is_recovered() {
    let (model, p) = scene();
    let (size, tex) = (96, 48);
    let render = RenderOptions::new(size, size);
    let renderer = FaceRenderer::new(&model, render.clone()).unwrap();
    let textured = Arc::new(fit::textured_faces(&model));
    let o = TextureOptions {
        size: tex,
        iters: 60,
        step: 0.04,
        prior: 1e-4,
        smoothness: 0.02,
        ..TextureOptions::default()
    };
    // The prior (what the stage bakes) and a truth that departs from it smoothly.
    let prior = fit::fit_texture(
        &model,
        &render,
        &p,
        &Array3::zeros((size, size, 3)),
        &TextureOptions {
            iters: 0,
            ..o.clone()
        },
    )
    .unwrap()
    .prior;
    let truth = Array3::from_shape_fn((tex, tex, 3), |(r, c, k)| {
        let (u, v) = (c as f64 / tex as f64, r as f64 / tex as f64);
        let m = 1.0 + 0.3 * (6.0 * u + k as f64).sin() * (5.0 * v).cos();
        (prior[[r, c, k]] * m).clamp(0.0, 1.0)
    });
    let target = fit::render_textured(&renderer, &p, &truth.clone().into_dyn(), &textured)
        .unwrap()
        .slice(ndarray::s![.., .., 0..3])
        .to_owned();
    let r = fit::fit_texture(&model, &render, &p, &target, &o).unwrap();
    assert!(
        r.rmse_after < 0.1 * r.rmse_before,
        "RMSE {} -> {}",
        r.rmse_before,
        r.rmse_after
    );
    // Texels well seen: the bilinear weight that reaches them sums to at least one pixel.
    let weight = seen_weight(&model, &p, &render, tex);
    let (mut e0, mut e1, mut n) = (0.0, 0.0, 0.0);
    for ((rr, c), &wt) in weight.indexed_iter() {
        if wt >= 1.0 {
            for k in 0..3 {
                e0 += (r.prior[[rr, c, k]] - truth[[rr, c, k]]).abs();
                e1 += (r.texels[[rr, c, k]] - truth[[rr, c, k]]).abs();
            }
            n += 3.0;
        }
    }
    let (e0, e1) = (e0 / n, e1 / n);
    eprintln!(
        "RMSE {:.4} -> {:.4}; texture error {e0:.4} -> {e1:.4} over {n} channels; {} pixels",
        r.rmse_before, r.rmse_after, r.pixels
    );
    assert!(n > 300.0, "{n} texel channels seen");
    assert!(e1 < 0.005 && e1 < e0 / 10.0, "texture error {e0} -> {e1}");
    // Texels that no pixel reaches stay at the prior.
    for ((rr, c), &s) in r.seen.indexed_iter() {
        if !s {
            for k in 0..3 {
                assert_eq!(r.texels[[rr, c, k]], r.prior[[rr, c, k]]);
            }
        }
    }
}

/// Per texel, the sum over covered skin pixels of their bilinear weights on it.
fn seen_weight(
    model: &Morphable<f64>,
    p: &FaceParams,
    render: &RenderOptions,
    tex: usize,
) -> Array2<f64> {
    let renderer = FaceRenderer::new(model, render.clone()).unwrap();
    let s = renderer.surface_samples(p).unwrap();
    let textured = fit::textured_faces(model);
    let mut w = Array2::<f64>::zeros((tex, tex));
    let n = tex as f64;
    for (i, &f) in s.face.iter().enumerate() {
        if !textured[f as usize] {
            continue;
        }
        let x = s.uv[[i, 0]] * n - 0.5;
        let y = (1.0 - s.uv[[i, 1]]) * n - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        for (dy, wy) in [(0, 1.0 - fy), (1, fy)] {
            for (dx, wx) in [(0, 1.0 - fx), (1, fx)] {
                let rr = (y0 as i64 + dy).clamp(0, tex as i64 - 1) as usize;
                let cc = (x0 as i64 + dx).clamp(0, tex as i64 - 1) as usize;
                w[[rr, cc]] += wx * wy;
            }
        }
    }
    w
}

/// `face_obj` + the texture as PNG: Tapestry's OBJ loader reads back the positions (to the
/// file's 5 decimals), the uvs (6 decimals) and the model's triangles; the MTL names the PNG
/// by `map_Kd` and every material the OBJ uses; the PNG holds the texels to 8 bits.
#[test]
fn textured_obj_mtl_png_round_trip() {
    let (model, p) = scene();
    let shape = p.shape(&model).unwrap();
    let albedo = model.mean_albedo();
    let textured = fit::textured_faces(&model);
    let files = fit::face_obj(&model, &shape, &albedo, &textured, "fit.mtl", "albedo.png");
    let texels = Array3::from_shape_fn((16, 16, 3), |(r, c, k)| {
        ((r * 16 + c) * 3 + k) as f64 / (16.0 * 16.0 * 3.0)
    });
    let dir = scratch("obj");
    std::fs::write(dir.join("fit.obj"), &files.obj).unwrap();
    std::fs::write(dir.join("fit.mtl"), &files.mtl).unwrap();
    write_png(dir.join("albedo.png"), &texels).unwrap();

    let mesh = render_ops::obj::load_obj::<f64>(dir.join("fit.obj")).unwrap();
    assert_eq!(mesh.faces, model.faces());
    assert_eq!(mesh.uv_faces, model.faces());
    for (a, b) in mesh.positions.iter().zip(shape.rows()) {
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() <= 5e-6, "{a:?} vs {b}");
        }
    }
    let uvs = model.uvs().unwrap();
    assert_eq!(mesh.uvs.len(), uvs.nrows());
    for (a, b) in mesh.uvs.iter().zip(uvs.rows()) {
        assert!((a[0] - b[0]).abs() <= 5e-7 && (a[1] - b[1]).abs() <= 5e-7);
    }
    assert!(files.obj.lines().any(|l| l == "mtllib fit.mtl"));
    let map = files
        .mtl
        .lines()
        .find_map(|l| l.strip_prefix("map_Kd "))
        .unwrap();
    let png = load_png::<f64>(dir.join(map)).unwrap();
    assert_eq!(png.shape(), &[16, 16, 3]);
    for (a, b) in png.iter().zip(texels.iter()) {
        assert!((a - b).abs() <= 0.5 / 255.0 + 1e-12);
    }
    for used in files.obj.lines().filter_map(|l| l.strip_prefix("usemtl ")) {
        assert!(
            files.mtl.lines().any(|l| l == format!("newmtl {used}")),
            "material {used} is not in the MTL"
        );
    }
    // The untextured regions (mouth interior, eyes) have their own materials.
    assert!(files.mtl.contains("newmtl region_mouth_interior"));
    // The OBJ parses as a string too (no reliance on the file system).
    assert_eq!(
        parse_obj_str::<f64>(&files.obj).unwrap().faces.len(),
        model.n_faces()
    );
    std::fs::remove_dir_all(dir).unwrap();
}

/// The stage gives the same texture bits with 1 and 3 rayon threads.
#[test]
fn texture_stage_is_deterministic_across_thread_counts() {
    let (model, p) = scene();
    let render = RenderOptions::new(64, 64);
    let image = Array3::from_shape_fn((64, 64, 3), |(r, c, k)| {
        0.3 + 0.4 * (((r * 5 + c * 3 + k) % 17) as f64 / 17.0)
    });
    let o = TextureOptions {
        size: 32,
        iters: 4,
        ..TextureOptions::default()
    };
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| fit::fit_texture(&model, &render, &p, &image, &o).unwrap())
    };
    let (a, b) = (run(1), run(3));
    assert!(a
        .texels
        .iter()
        .zip(b.texels.iter())
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    assert_eq!(a.losses, b.losses);
}

/// Bad inputs are typed errors, and a face that covers no pixel leaves the texture at the
/// prior.
#[test]
fn bad_inputs_are_errors_and_an_unseen_face_keeps_the_prior() {
    let (model, p) = scene();
    let render = RenderOptions::new(16, 16);
    let img = Array3::from_elem((16, 16, 3), 0.5);
    let o = TextureOptions {
        size: 8,
        iters: 2,
        ..TextureOptions::default()
    };
    let err = |r: Result<fit::TextureFit, fit::FitError>| r.unwrap_err().to_string();
    let e = err(fit::fit_texture(
        &model,
        &render,
        &p,
        &Array3::zeros((8, 16, 3)),
        &o,
    ));
    assert!(e.contains("image"), "{e}");
    let mut nan = img.clone();
    nan[[3, 3, 1]] = f64::NAN;
    assert!(err(fit::fit_texture(&model, &render, &p, &nan, &o)).contains("non-finite"));
    let tiny = TextureOptions {
        size: 1,
        ..o.clone()
    };
    assert!(err(fit::fit_texture(&model, &render, &p, &img, &tiny)).contains("texture size"));
    let neg = TextureOptions {
        prior: -1.0,
        ..o.clone()
    };
    assert!(err(fit::fit_texture(&model, &render, &p, &img, &neg)).contains("weights"));
    let mut parts = model.to_parts();
    parts.uvs = None;
    let no_uv = Morphable::from_parts(parts).unwrap();
    assert!(err(fit::fit_texture(&no_uv, &render, &p, &img, &o)).contains("no uvs"));
    // Far to the side: nothing covered.
    let mut away = p.clone();
    away.translation[0] = 5000.0;
    let r = fit::fit_texture(&model, &render, &away, &img, &o).unwrap();
    assert_eq!(r.pixels, 0);
    assert_eq!(r.texels, r.prior);
    assert!(r.seen.iter().all(|&s| !s));
}
