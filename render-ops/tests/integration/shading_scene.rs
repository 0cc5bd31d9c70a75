#![allow(clippy::needless_range_loop)]
//! Shading and textures through the scene pipeline (`Scene::render`): the scene JSON's
//! `material`, `lights` and `texture` against the shader API, end-to-end gradient checks with
//! respect to positions, texels and camera, Gouraud shading of the soft methods, errors, and
//! the trilinear mip level chosen from the rasterizer's uv derivatives.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use autodiff::gradcheck::{gradcheck, GradcheckOptions};
use autodiff::rng::Rng;
use autodiff::{Tape, Tensor, Var};
use ndarray::{ArrayD, IxDyn};
use render_ops::mesh::Mesh;
use render_ops::obj::write_obj;
use render_ops::pipeline::{SceneVars, Wrt};
use render_ops::raster::RasterSettings;
use render_ops::rasterize::rasterize;
use render_ops::scene::Scene;
use render_ops::shade::{
    fragment_inputs, render_shader, sh_shade, shade, vertex_normals, FragmentInputs, Lights,
    Material, MeshAttributes,
};
use render_ops::soft::{
    soft_fragments, softras_aggregate, Coverage, SoftBlendSettings, SoftStageSettings,
};
use render_ops::texture::{mip_pyramid, sample, Filter, Sampler, Wrap};
use render_ops::transform::to_clip;

fn t(shape: &[usize], data: Vec<f64>) -> Tensor<f64> {
    ArrayD::from_shape_vec(IxDyn(shape), data).unwrap()
}

fn rows<const K: usize>(v: &[[f64; K]]) -> Tensor<f64> {
    t(&[v.len(), K], v.iter().flatten().copied().collect())
}

/// Pins a closure to the higher-ranked signature of a gradient-checked function.
fn hr<F: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>>(f: F) -> F {
    f
}

fn max_diff(a: &Tensor<f64>, b: &Tensor<f64>) -> f64 {
    assert_eq!(a.shape(), b.shape());
    a.iter()
        .zip(b.iter())
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
}

/// A fresh temporary folder for one test.
fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "tapestry-shading-scene-{name}-{}",
        std::process::id()
    ));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A latitude-longitude sphere of radius 1 whose seam vertices are shared positions with two
/// different uvs (separate `vt` indices, as OBJ files have them), poles included; per-vertex
/// colours. Counter-clockwise seen from outside.
fn seam_sphere(nlat: usize, nlon: usize) -> Mesh<f64> {
    let mut m = Mesh::uv_sphere(nlat, nlon, 1.0);
    m.colors = m
        .positions
        .iter()
        .map(|p| [0.7 + 0.2 * p[0], 0.6 + 0.3 * p[1], 0.8 - 0.2 * p[2]])
        .collect();
    m
}

const SH: &str = "[[0.8, 0.7, 0.6], [0.1, 0.05, 0.0], [0.3, 0.3, 0.25], [-0.1, 0.05, 0.1], \
                  [0.05, 0.0, -0.05], [0.02, 0.04, 0.0], [-0.1, -0.08, -0.05], [0.03, 0.0, 0.06], \
                  [-0.04, 0.02, 0.05]]";

/// Writes `mesh` (and `texture` as PNG) to `dir` and loads a scene with the given material,
/// method and image size.
fn scene_with(
    dir: &Path,
    mesh: &Mesh<f64>,
    texture: Option<&ndarray::Array3<f64>>,
    shading: &str,
    method: &str,
    size: usize,
) -> Scene<f64> {
    write_obj(dir.join("m.obj"), mesh).unwrap();
    let tex = match texture {
        Some(img) => {
            render_ops::io::write_png(dir.join("tex.png"), img).unwrap();
            "\"tex.png\""
        }
        None => "null",
    };
    let json = format!(
        r#"{{"mesh": "m.obj", "texture": {tex},
        "camera": {{"eye": [0.6, 0.8, 3.2], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 40,
                   "near": 0.5, "far": 10}},
        "image": {{"width": {size}, "height": {size}, "background": [0.1, 0.2, 0.3]}},
        "lights": [{{"type": "directional", "direction": [-0.4, -0.5, -1], "color": [1, 0.9, 0.8]}},
                   {{"type": "point", "position": [2, 1, 3], "color": [0.3, 0.3, 0.4]}},
                   {{"type": "ambient", "color": [0.15, 0.15, 0.15]}},
                   {{"type": "sh", "coeffs": {SH}}}],
        "material": {{"shading": "{shading}", "kd": [0.9, 0.8, 0.7], "ks": [0.4, 0.4, 0.4],
                     "shininess": 20}},
        "raster": {{"method": "{method}"}}}}"#
    );
    Scene::from_json(&json, dir, "test.json").unwrap()
}

fn texture_image(h: usize, w: usize, seed: u64) -> ndarray::Array3<f64> {
    let mut rng = Rng::new(seed);
    ndarray::Array3::from_shape_fn((h, w, 3), |_| {
        // Multiples of 1/255 survive the PNG round trip exactly.
        (rng.uniform(0.2, 1.0) * 255.0).round() / 255.0
    })
}

/// The image of a scene rendered through `Scene::render` (no gradients).
fn render_scene(scene: &Scene<f64>, camera_on_tape: bool) -> Tensor<f64> {
    let tape = Tape::new();
    let vars = scene.vars(
        &tape,
        Wrt {
            camera: camera_on_tape,
            ..Wrt::default()
        },
    );
    (*scene.render(&vars).unwrap().value().unwrap()).clone()
}

#[test]
fn scene_shading_models_match_the_shader_api() {
    let dir = temp_dir("models");
    let mesh = Mesh::<f64>::icosphere(2, 1.0).with_colors(
        Mesh::<f64>::icosphere(2, 1.0)
            .positions
            .iter()
            .map(|p| [0.6 + 0.3 * p[0], 0.7, 0.8 - 0.2 * p[1]])
            .collect(),
    );
    let size = 40;
    let unlit = render_scene(&scene_with(&dir, &mesh, None, "none", "hard", size), false);
    for shading in ["lambert", "phong", "blinn_phong", "sh"] {
        let scene = scene_with(&dir, &mesh, None, shading, "hard", size);
        let img = render_scene(&scene, false);
        // The same image from the shader API by hand.
        let tape = Tape::new();
        let pos = tape.constant(rows(&mesh.positions));
        let faces = Arc::new(mesh.faces.clone());
        let r = rasterize(
            to_clip(pos, &scene.camera.view_proj()),
            faces.clone(),
            &RasterSettings::new(size, size),
        )
        .unwrap();
        let attrs = MeshAttributes::new(pos)
            .with_normals(vertex_normals(pos, &faces))
            .with_attribute("c", tape.constant(rows(&mesh.colors)));
        let eye = tape.constant(t(&[3], scene.camera.eye().to_vec()));
        let kd = tape.constant(t(&[3], vec![0.9, 0.8, 0.7]));
        let lights = Lights::from_scene(&tape, &scene.desc.lights);
        let expect = render_shader(
            &r,
            &attrs,
            eye,
            |f: &FragmentInputs<'_, f64>| {
                let albedo = f.attribute("c").unwrap() * kd;
                match Material::from_scene(&tape, &scene.desc.material) {
                    Some(m) => shade(&f.surface(albedo), &m, &lights, f.eye),
                    None => sh_shade(f.normal, albedo, lights.sh.unwrap().coeffs),
                }
            },
            &[0.1, 0.2, 0.3],
        )
        .unwrap()
        .value()
        .unwrap();
        let d = max_diff(&img, &expect);
        assert!(d < 1e-12, "{shading}: differs from the shader API by {d:e}");
        // Lighting changes the image; background and alpha stay.
        let dl = max_diff(&img, &unlit);
        assert!(dl > 0.05, "{shading}: no visible lighting ({dl})");
        assert_eq!(img[[0, 0, 0]], 0.1);
        assert!(img.iter().all(|v| v.is_finite()));
        let alpha_diff = (0..size * size)
            .filter(|&p| img[[p / size, p % size, 3]] != unlit[[p / size, p % size, 3]])
            .count();
        assert_eq!(alpha_diff, 0, "{shading}: coverage changed");
    }
    // Phong has a highlight: some pixel brighter than the brightest Lambert pixel.
    let lam = render_scene(
        &scene_with(&dir, &mesh, None, "lambert", "hard", size),
        false,
    );
    let pho = render_scene(&scene_with(&dir, &mesh, None, "phong", "hard", size), false);
    let peak = |img: &Tensor<f64>| img.iter().fold(0.0f64, |m, &v| m.max(v));
    assert!(
        peak(&pho) > peak(&lam) + 0.1,
        "{} {}",
        peak(&pho),
        peak(&lam)
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn camera_on_the_tape_matches_the_constant_camera() {
    let dir = temp_dir("camera");
    let mesh = seam_sphere(8, 12);
    let tex = texture_image(6, 5, 3);
    for (shading, method) in [
        ("phong", "hard"),
        ("none", "hard"),
        ("blinn_phong", "softras"),
    ] {
        let texture = (method == "hard").then_some(&tex);
        let scene = scene_with(&dir, &mesh, texture, shading, method, 32);
        let a = render_scene(&scene, false);
        let b = render_scene(&scene, true);
        let d = max_diff(&a, &b);
        assert!(d < 1e-12, "{shading} {method}: {d:e}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// Pixel weights `[H, W, 4]`: random on pixels whose fragment lies at least `margin` (in
/// barycentric units) inside its face, zero elsewhere.
fn interior_weights(scene: &Scene<f64>, margin: f64, seed: u64) -> Tensor<f64> {
    let unified = scene.mesh.unified().unwrap();
    let tape = Tape::new();
    let r = rasterize(
        to_clip(
            tape.constant(rows(&unified.mesh.positions)),
            &scene.camera.view_proj(),
        ),
        Arc::new(unified.mesh.faces.clone()),
        &scene.raster_settings(),
    )
    .unwrap();
    let f = &r.fragments;
    let mut rng = Rng::new(seed);
    let mut w = ArrayD::zeros(IxDyn(&[f.height, f.width, 4]));
    for p in 0..f.num_pixels() {
        if let Some(fr) = f.nearest(p) {
            if fr.bary.iter().all(|&b| b > margin) {
                let (row, col) = f.pixel_coords(p);
                for k in 0..4 {
                    w[[row, col, k]] = rng.normal();
                }
            }
        }
    }
    w
}

#[test]
fn textured_scene_gradcheck_positions_texels_camera() {
    // A seam-split sphere with a 6 x 5 (non-power-of-two) texture, Phong and SH shading: the
    // scene pipeline's gradients with respect to positions, vertex colours, texels and
    // camera (eye, at) check against finite differences on interior pixels.
    let dir = temp_dir("gradcheck");
    let mesh = seam_sphere(6, 8);
    let tex = texture_image(6, 5, 11);
    let mut failures = Vec::new();
    for shading in ["none", "phong", "sh"] {
        let scene = scene_with(&dir, &mesh, Some(&tex), shading, "hard", 24);
        let weights = interior_weights(&scene, 0.04, 5);
        let inputs = {
            let tape = Tape::new();
            let v = scene.vars(&tape, Wrt::default());
            vec![
                (*v.positions.value().unwrap()).clone(),
                (*v.colors.value().unwrap()).clone(),
                (*v.texture.unwrap().value().unwrap()).clone(),
                (*v.camera.value().unwrap()).clone(),
            ]
        };
        assert_eq!(inputs[2].shape(), &[6, 5, 3]);
        assert_eq!(inputs[3].shape(), &[2, 3]);
        let f = hr(|tape, v| {
            let vars = SceneVars {
                positions: v[0],
                colors: v[1],
                texture: Some(v[2]),
                camera: v[3],
                lights: None,
            };
            (scene.render(&vars).unwrap() * tape.constant(weights.clone())).sum()
        });
        let rep = gradcheck(f, &inputs, &GradcheckOptions::default()).unwrap();
        if !rep.passed() {
            failures.push(format!("{shading}\n{rep}"));
        }
        // Every parameter really gets a gradient.
        let tape = Tape::new();
        let vars = scene.vars(
            &tape,
            Wrt {
                positions: true,
                colors: true,
                texture: true,
                camera: true,
                lights: false,
            },
        );
        let loss = (scene.render(&vars).unwrap() * tape.constant(weights.clone())).sum();
        let g = tape.backward(loss).unwrap();
        for (name, v) in [
            ("positions", vars.positions),
            ("colors", vars.colors),
            ("texture", vars.texture.unwrap()),
            ("camera", vars.camera),
        ] {
            let gv = g.wrt(v);
            assert!(
                gv.iter().all(|x| x.is_finite()) && gv.iter().any(|x| x.abs() > 1e-6),
                "{shading}: no gradient for {name}"
            );
        }
    }
    std::fs::remove_dir_all(&dir).ok();
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A lit softras scene is shaded per fragment through the soft stage
/// (`render_ops::soft::soft_fragments`, the built-in shading on the fragments,
/// `softras_aggregate`): the same image as those ops composed by hand. A textured softras scene
/// renders; a texture with the per-vertex method `tf_mesh` is a typed error naming the way out.
#[test]
fn soft_methods_shade_per_fragment_and_take_textures() {
    let dir = temp_dir("soft");
    let mesh = seam_sphere(8, 12);
    let scene = scene_with(&dir, &mesh, None, "phong", "softras", 32);
    let img = render_scene(&scene, false);
    let tape = Tape::new();
    let pos = tape.constant(rows(&mesh.positions));
    let faces = Arc::new(mesh.faces.clone());
    let r = &scene.desc.raster;
    let mut st = SoftStageSettings::new(32, 32, Coverage::Sigmoid { sigma: r.sigma });
    st.perspective_correct = r.perspective_correct;
    let clip = to_clip(pos, &scene.camera.view_proj());
    let sf = soft_fragments(clip, faces.clone(), &st).unwrap();
    let attrs = MeshAttributes::new(pos)
        .with_normals(vertex_normals(pos, &faces))
        .with_attribute("color", tape.constant(rows(&mesh.colors)));
    let eye = tape.constant(t(&[3], vec![0.6, 0.8, 3.2]));
    let f = fragment_inputs(&sf.raster, &attrs, eye).unwrap();
    let albedo = f.attribute("color").unwrap() * tape.constant(t(&[3], vec![0.9, 0.8, 0.7]));
    let lights = Lights::from_scene(&tape, &scene.desc.lights);
    let m = Material::from_scene(&tape, &scene.desc.material).unwrap();
    let colors = shade(&f.surface(albedo), &m, &lights, eye);
    let proj = scene.camera.projection();
    let mut bs = SoftBlendSettings::new(proj.near(), proj.far());
    bs.background = vec![0.1, 0.2, 0.3];
    let expect = softras_aggregate(&sf, colors, &bs)
        .unwrap()
        .value()
        .unwrap();
    let d = max_diff(&img, &expect);
    assert!(d < 1e-12, "softras + phong: {d:e}");
    let unlit = render_scene(&scene_with(&dir, &mesh, None, "none", "softras", 32), false);
    assert!(max_diff(&img, &unlit) > 0.05);
    let tex = texture_image(4, 4, 1);
    for method in ["softras", "dibr", "tf_mesh"] {
        let textured = render_scene(
            &scene_with(&dir, &mesh, Some(&tex), "none", method, 16),
            false,
        );
        assert!(textured.iter().all(|x| x.is_finite()), "{method}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn texture_without_uvs_is_an_error() {
    let dir = temp_dir("nouv");
    let mesh = Mesh::<f64>::icosphere(1, 1.0);
    let tex = texture_image(2, 3, 2);
    let scene = scene_with(&dir, &mesh, Some(&tex), "lambert", "hard", 8);
    let tape = Tape::new();
    let vars = scene.vars(&tape, Wrt::default());
    let err = scene.render(&vars).unwrap_err().to_string();
    assert!(err.contains("no uvs"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn scene_texture_one_texel_and_unlit_values() {
    // A 1 x 1 texture is a constant colour: the unlit textured render is kd * colour * texel.
    let dir = temp_dir("onetexel");
    let mesh = seam_sphere(6, 8);
    let tex = ndarray::Array3::from_shape_vec((1, 1, 3), vec![0.2, 0.4, 0.6]).unwrap();
    let scene = scene_with(&dir, &mesh, Some(&tex), "none", "hard", 24);
    let img = render_scene(&scene, false);
    let no_tex = render_scene(&scene_with(&dir, &mesh, None, "none", "hard", 24), false);
    let tv = scene.texture.as_ref().unwrap();
    let mut covered = 0;
    for r in 0..24 {
        for c in 0..24 {
            if img[[r, c, 3]] == 1.0 {
                covered += 1;
                for k in 0..3 {
                    let want = no_tex[[r, c, k]] * tv[[0, 0, k]];
                    assert!((img[[r, c, k]] - want).abs() < 1e-12);
                }
            }
        }
    }
    assert!(covered > 100);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn trilinear_level_follows_rasterizer_derivatives() {
    // The square [-1, 1]^2 seen frontally so that it fills the image exactly: uv is affine in
    // screen space with |d uv / d pixel| = 1 / size. A 64 x 64 texture over 24 pixels has
    // rho = 64 / 24 texels per pixel, lambda = log2(8 / 3) = 1.415: with trilinear filtering
    // and the rasterizer's uv derivatives every pixel must be the blend 0.585 * level 1 +
    // 0.415 * level 2 (bilinear in each) of the mip pyramid at the pixel centre's uv. The
    // scene pipeline samples bilinearly: level 0.
    let dir = temp_dir("trilinear");
    let plane = Mesh::<f64>::grid_plane(2);
    write_obj(dir.join("m.obj"), &plane).unwrap();
    let n = 64;
    let tex = texture_image(n, n, 4);
    render_ops::io::write_png(dir.join("tex.png"), &tex).unwrap();
    let size = 24;
    let fov = 2.0 * (1.0f64 / 3.0).atan();
    let json = format!(
        r#"{{"mesh": "m.obj", "texture": "tex.png",
        "camera": {{"eye": [0, 0, 3], "at": [0, 0, 0], "fov_y_deg": {}, "near": 0.5, "far": 10}},
        "image": {{"width": {size}, "height": {size}}}}}"#,
        fov.to_degrees()
    );
    let scene = Scene::<f64>::from_json(&json, &dir, "plane.json").unwrap();
    let texels = scene.texture.clone().unwrap().into_dyn();
    let scene_img = render_scene(&scene, false);
    // The same plane through the shader API with a trilinear texture.
    let tape = Tape::new();
    let pos = tape.constant(rows(&plane.positions));
    let r = rasterize(
        to_clip(pos, &scene.camera.view_proj()),
        Arc::new(plane.faces.clone()),
        &RasterSettings::new(size, size),
    )
    .unwrap();
    let mesh = MeshAttributes::new(pos).with_uvs(tape.constant(rows(&plane.uvs)));
    let trilinear = render_ops::texture::Texture::new(
        tape.constant(texels.clone()),
        Sampler::new(Filter::Trilinear, Wrap::Repeat),
    );
    let eye = tape.constant(t(&[3], vec![0.0, 0.0, 3.0]));
    let tri_img = render_shader(&r, &mesh, eye, |f| f.sample(&trilinear), &[0.0; 3])
        .unwrap()
        .value()
        .unwrap();
    let levels = mip_pyramid(&texels);
    let lam = (n as f64 / size as f64).log2();
    let f = lam - 1.0;
    let mut uv = Vec::new();
    for r in 0..size {
        for c in 0..size {
            uv.extend([
                (c as f64 + 0.5) / size as f64,
                1.0 - (r as f64 + 0.5) / size as f64,
            ]);
        }
    }
    let uv = tape.constant(t(&[size * size, 2], uv));
    let bil = |k: usize| {
        sample(
            tape.constant(levels[k].clone()),
            uv,
            None,
            Sampler::new(Filter::Bilinear, Wrap::Repeat),
        )
        .value()
        .unwrap()
    };
    let (l0, l1, l2) = (bil(0), bil(1), bil(2));
    let (mut worst, mut worst_scene, mut vs_level0) = (0.0f64, 0.0f64, 0.0f64);
    for p in 0..size * size {
        let (row, col) = (p / size, p % size);
        for k in 0..3 {
            let want = (1.0 - f) * l1[[p, k]] + f * l2[[p, k]];
            worst = worst.max((tri_img[[row, col, k]] - want).abs());
            vs_level0 = vs_level0.max((tri_img[[row, col, k]] - l0[[p, k]]).abs());
            worst_scene = worst_scene.max((scene_img[[row, col, k]] - l0[[p, k]]).abs());
        }
        assert_eq!(tri_img[[row, col, 3]], 1.0);
        assert_eq!(scene_img[[row, col, 3]], 1.0);
    }
    assert!(
        worst < 1e-9,
        "trilinear differs from the expected blend by {worst:e}"
    );
    assert!(
        vs_level0 > 0.05,
        "the trilinear render looks like level 0 ({vs_level0})"
    );
    assert!(
        worst_scene < 1e-9,
        "scene render vs level-0 bilinear: {worst_scene:e}"
    );
    std::fs::remove_dir_all(&dir).ok();
}
