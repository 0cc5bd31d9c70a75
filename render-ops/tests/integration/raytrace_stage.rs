//! The ray tracer as fragment stages (`render_ops::raytrace::stage`): with per-vertex colours
//! the composed render and its gradients equal the fused `raytrace` op's; a textured custom
//! shader through `render_fragments` converges to the supersampled hard render of the same
//! shader, and its position and texture gradients agree with that reference; f32, threads.

use std::sync::Arc;

use autodiff::{Real, Tape, Tensor};
use ndarray::{ArrayD, IxDyn};
use render_ops::camera::Camera;
use render_ops::methods::{render_fragments, render_fragments_lit, MethodSettings};
use render_ops::raytrace::{
    blend_traced, raytrace, raytrace_fragments, LightKind, RaytraceSettings, ShadowInputs,
};
use render_ops::shade::{fragment_inputs, MeshAttributes};
use render_ops::texture::{Filter, Sampler, Texture, Wrap};
use render_ops::Method;
use render_ops::{interpolate, to_clip, Mesh};

use crate::common::scenes::cosine;
use crate::common::weights;

fn tensor<T: Real>(rows: &[[f64; 3]]) -> Tensor<T> {
    ArrayD::from_shape_vec(
        IxDyn(&[rows.len(), 3]),
        rows.iter().flatten().map(|&x| T::from_f64c(x)).collect(),
    )
    .unwrap()
}

fn camera() -> Camera {
    Camera::perspective_look_at(
        [0.3, 0.4, 3.0],
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        45f64.to_radians(),
        1.0,
        0.1,
        100.0,
    )
    .unwrap()
}

/// Positions, faces, colours.
type Soup = (Vec<[f64; 3]>, Vec<[u32; 3]>, Vec<[f64; 3]>);

/// Two spheres in one mesh, the front one covering part of the back one (silhouettes and an
/// occlusion contour), with colours varying over them.
fn two_spheres() -> Soup {
    let a = Mesh::<f64>::icosphere(1, 0.8);
    let mut pos: Vec<[f64; 3]> = a
        .positions
        .iter()
        .map(|p| [p[0] - 0.4, p[1], p[2] - 0.5])
        .collect();
    let mut faces = a.faces.clone();
    let n = pos.len() as u32;
    pos.extend(
        a.positions
            .iter()
            .map(|p| [0.5 * p[0] + 0.3, 0.5 * p[1], 0.5 * p[2] + 0.6]),
    );
    faces.extend(a.faces.iter().map(|f| f.map(|i| i + n)));
    let colors = pos
        .iter()
        .map(|p| [0.5 + 0.4 * p[0], 0.5 + 0.4 * p[1], 0.5 + 0.3 * p[2]])
        .collect();
    (pos, faces, colors)
}

fn settings(size: usize, spp: usize) -> RaytraceSettings {
    let mut s = RaytraceSettings::new(size, size);
    s.spp = spp;
    s.seed = 5;
    s.background = [0.2, 0.3, 0.4];
    s.primary_edge_samples = 4 * size * size;
    s
}

/// Image and the gradients of `sum(w * image)` with respect to positions and colours, by the
/// fused op (`fused`) or by the stages with `interpolate` as the shader.
fn vertex_colours<T: Real>(fused: bool, s: &RaytraceSettings, w: &[f64]) -> [Vec<f64>; 3] {
    let (pos, faces, colors) = two_spheres();
    let tape = Tape::<T>::new();
    let p = tape.var(tensor::<T>(&pos), true);
    let col = tape.var(tensor::<T>(&colors), true);
    let faces = Arc::new(faces);
    let clip = to_clip(p, &camera().view_proj());
    let img = if fused {
        let v = pos.len();
        let normals = tape.constant(ArrayD::zeros(IxDyn(&[v, 3])));
        let lights = tape.constant(ArrayD::zeros(IxDyn(&[0, 3])));
        raytrace(clip, p, normals, col, lights, faces, s).unwrap()
    } else {
        let t = raytrace_fragments(clip, faces, s, None).unwrap();
        let c = interpolate(col, &t.raster).unwrap();
        let band = interpolate(col, &t.band).unwrap();
        let bg = s.background.map(T::from_f64c);
        blend_traced(c, band, &t, clip, &bg).unwrap()
    };
    let vals: Vec<f64> = img.value().unwrap().iter().map(|x| x.to_f64c()).collect();
    let wt = tape.constant(
        ArrayD::from_shape_vec(
            IxDyn(img.shape().as_slice()),
            w.iter().map(|&x| T::from_f64c(x)).collect(),
        )
        .unwrap(),
    );
    let g = tape.backward((img * wt).sum()).unwrap();
    let f = |v| g.wrt(v).iter().map(|x: &T| x.to_f64c()).collect();
    [vals, f(p), f(col)]
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

fn max_abs(a: &[f64]) -> f64 {
    a.iter().map(|x| x.abs()).fold(0.0, f64::max)
}

#[test]
fn composed_vertex_colours_equal_the_fused_op() {
    let s = settings(16, 4);
    let w = weights(16 * 16 * 4);
    let fused = vertex_colours::<f64>(true, &s, &w);
    let composed = vertex_colours::<f64>(false, &s, &w);
    // The same samples, hits and edge samples; only the order of the sums differs.
    assert!(max_abs_diff(&fused[0], &composed[0]) <= 1e-14, "image");
    for (k, name) in [(1, "positions"), (2, "colours")] {
        let scale = max_abs(&fused[k]);
        assert!(scale > 0.0, "{name}: no gradient");
        let d = max_abs_diff(&fused[k], &composed[k]);
        assert!(d <= 1e-10 * scale, "{name}: {d} against {scale}");
    }
    // f32 within its rounding of f64.
    let f32 = vertex_colours::<f32>(false, &s, &w);
    assert!(max_abs_diff(&f32[0], &composed[0]) <= 1e-5, "f32 image");
    let d = max_abs_diff(&f32[1], &composed[1]);
    assert!(d <= 1e-3 * max_abs(&composed[1]), "f32 positions: {d}");
    // Bit-identical on any pool.
    let on = |n: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
            .install(|| vertex_colours::<f64>(false, &s, &w))
    };
    assert_eq!(on(1), on(3));
}

/// A sphere with uvs from its positions, a texture, and a custom shader (texture times a
/// wrapped diffuse term plus a rim), rendered by `method` through `render_fragments`: the
/// image and, with `w`, the gradients of `sum(w * image)` with respect to positions and texels.
struct Textured {
    pos: Vec<[f64; 3]>,
    faces: Vec<[u32; 3]>,
    uvs: Vec<[f64; 2]>,
    texels: Vec<f64>,
}

const TEX: usize = 8;

impl Textured {
    fn new() -> Self {
        let m = Mesh::<f64>::icosphere(1, 1.0);
        let uvs = m
            .positions
            .iter()
            .map(|p| [0.5 + 0.45 * p[0], 0.5 - 0.45 * p[1]])
            .collect();
        let texels = (0..TEX * TEX * 3)
            .map(|i| {
                let (r, c, ch) = (i / (TEX * 3), (i / 3) % TEX, i % 3);
                0.5 + 0.4 * ((r as f64 * 0.9 + c as f64 * 1.7 + ch as f64).sin())
            })
            .collect();
        Textured {
            pos: m.positions,
            faces: m.faces,
            uvs,
            texels,
        }
    }

    fn render(
        &self,
        pos: &[[f64; 3]],
        method: Method,
        size: usize,
        tune: impl Fn(&mut MethodSettings),
        w: Option<&[f64]>,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let tape = Tape::<f64>::new();
        let want = w.is_some();
        let p = tape.var(tensor::<f64>(pos), want);
        let tex = tape.var(
            ArrayD::from_shape_vec(IxDyn(&[TEX, TEX, 3]), self.texels.clone()).unwrap(),
            want,
        );
        let uv = tape.constant(
            ArrayD::from_shape_vec(
                IxDyn(&[self.uvs.len(), 2]),
                self.uvs.iter().flatten().copied().collect(),
            )
            .unwrap(),
        );
        let faces = Arc::new(self.faces.clone());
        let clip = to_clip(p, &camera().view_proj());
        let normals = render_ops::shade::vertex_normals(p, &faces);
        let mesh = MeshAttributes::new(p).with_normals(normals).with_uvs(uv);
        let texture = Texture::new(tex, Sampler::new(Filter::Bilinear, Wrap::Clamp));
        let mut s = MethodSettings::new(method, size, size);
        s.view.background = vec![0.2, 0.3, 0.4];
        s.barycentric_derivatives = true;
        tune(&mut s);
        let eye = tape.constant(ArrayD::from_shape_vec(IxDyn(&[3]), vec![0.3, 0.4, 3.0]).unwrap());
        let l = tape.constant(ArrayD::from_shape_vec(IxDyn(&[3]), vec![-0.4, 0.6, 0.7]).unwrap());
        let img = render_fragments(clip, faces, &s, &mut |r| {
            let f = fragment_inputs(r, &mesh, eye)?;
            let ndl = (f.normal * l.normalize(1e-12)).sum_axes(&[-1], true);
            let diffuse = (ndl * 0.5 + 0.5) * texture.sample(f.uv.expect("uvs"), None);
            let ndv = (f.normal * f.view_dir).sum_axes(&[-1], true);
            let rim = (-ndv + 1.0).relu().powf(3.0) * 0.5;
            Ok(diffuse + rim)
        })
        .unwrap();
        let vals: Vec<f64> = img.value().unwrap().iter().copied().collect();
        let Some(w) = w else {
            return (vals, Vec::new(), Vec::new());
        };
        let wt = tape
            .constant(ArrayD::from_shape_vec(IxDyn(img.shape().as_slice()), w.to_vec()).unwrap());
        let g = tape.backward((img * wt).sum()).unwrap();
        (
            vals,
            g.wrt(p).iter().copied().collect(),
            g.wrt(tex).iter().copied().collect(),
        )
    }

    /// The hard render of `size * ss` pixels, box-filtered to `size` (CONVENTIONS), with the
    /// texture gradient of `sum(w * image)` when `w` is given.
    fn supersampled(
        &self,
        pos: &[[f64; 3]],
        size: usize,
        ss: usize,
        w: Option<&[f64]>,
    ) -> (Vec<f64>, Vec<f64>) {
        let big_w = w.map(|w| {
            let mut b = vec![0.0; size * size * ss * ss * 4];
            for r in 0..size * ss {
                for c in 0..size * ss {
                    for ch in 0..4 {
                        b[(r * size * ss + c) * 4 + ch] =
                            w[((r / ss) * size + c / ss) * 4 + ch] / (ss * ss) as f64;
                    }
                }
            }
            b
        });
        let (img, _, gt) = self.render(pos, Method::Hard, size * ss, |_| {}, big_w.as_deref());
        let mut out = vec![0.0; size * size * 4];
        for r in 0..size * ss {
            for c in 0..size * ss {
                for ch in 0..4 {
                    out[((r / ss) * size + c / ss) * 4 + ch] +=
                        img[(r * size * ss + c) * 4 + ch] / (ss * ss) as f64;
                }
            }
        }
        (out, gt)
    }
}

fn rmse(a: &[f64], b: &[f64]) -> f64 {
    (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len() as f64).sqrt()
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[test]
fn a_textured_custom_shader_through_the_ray_tracer() {
    let sc = Textured::new();
    let size = 16;
    let spp = |n: usize| {
        move |s: &mut MethodSettings| {
            s.spp = n;
            s.seed = 3;
            s.edge_samples = Some(64 * size * size);
        }
    };
    // The image converges to the area-integrated image of the same shader.
    let (reference, _) = sc.supersampled(&sc.pos, size, 16, None);
    let errs: Vec<f64> = [1, 16, 64]
        .iter()
        .map(|&n| {
            rmse(
                &sc.render(&sc.pos, Method::Raytrace, size, spp(n), None).0,
                &reference,
            )
        })
        .collect();
    eprintln!("textured shader, rmse by spp 1, 16, 64: {errs:?}");
    assert!(
        errs[1] < errs[0] * 0.5 && errs[2] < errs[1] * 0.7,
        "{errs:?}"
    );
    assert!(errs[2] < 0.01, "{errs:?}");

    // Gradients of sum(w * image) at 64 spp (at 16 the interior estimate's noise leaves the
    // position cosine at 0.84; 0.98 at 64 and 256): texels against the reference's own (exact for it: the
    // texture moves no edge), positions against its central differences.
    let w = weights(size * size * 4);
    let (_, gp, gt) = sc.render(&sc.pos, Method::Raytrace, size, spp(64), Some(&w));
    let (_, gt_ref) = sc.supersampled(&sc.pos, size, 16, Some(&w));
    let ct = cosine(&gt, &gt_ref);
    let items: Vec<usize> = (0..sc.pos.len()).step_by(3).collect();
    let h = 0.02;
    let mut fd = Vec::new();
    let mut an = Vec::new();
    for &v in &items {
        for k in 0..3 {
            let mut a = sc.pos.clone();
            a[v][k] += h;
            let mut b = sc.pos.clone();
            b[v][k] -= h;
            let fa = dot(&sc.supersampled(&a, size, 16, None).0, &w);
            let fb = dot(&sc.supersampled(&b, size, 16, None).0, &w);
            fd.push((fa - fb) / (2.0 * h));
            an.push(gp[3 * v + k]);
        }
    }
    let cp = cosine(&an, &fd);
    eprintln!("textured shader: texel gradient cosine {ct:.4}, position gradient cosine {cp:.4}");
    assert!(ct >= 0.99, "texels: {ct}");
    assert!(cp >= 0.9, "positions: {cp}");
}

#[test]
fn traced_fragments_reject_bad_inputs() {
    let tape = Tape::<f64>::new();
    let s = settings(8, 1);
    let clip3 = tape.constant(ArrayD::zeros(IxDyn(&[3, 3])));
    assert!(raytrace_fragments(clip3, Arc::new(vec![[0, 1, 2]]), &s, None).is_err());
    let mut c = ArrayD::zeros(IxDyn(&[3, 4]));
    c[[0, 3]] = f64::NAN;
    let e = raytrace_fragments(tape.constant(c), Arc::new(vec![[0, 1, 2]]), &s, None)
        .err()
        .unwrap();
    assert!(e.to_string().contains("clip"), "{e}");
    let ok = tape.constant(ArrayD::ones(IxDyn(&[3, 4])));
    assert!(raytrace_fragments(ok, Arc::new(vec![[0, 1, 3]]), &s, None).is_err());
    // Shadow inputs: world and light rows of the kinds' shapes; no area lights; only the
    // ray tracer casts shadows.
    let faces = Arc::new(vec![[0, 1, 2]]);
    let world = tape.constant(ArrayD::ones(IxDyn(&[3, 3])));
    let shadows = |kinds: Vec<LightKind>, rows: usize| ShadowInputs {
        world,
        lights: tape.constant(ArrayD::ones(IxDyn(&[rows, 3]))),
        kinds,
    };
    let dir = vec![LightKind::Directional];
    assert!(raytrace_fragments(ok, faces.clone(), &s, Some(shadows(dir.clone(), 2))).is_ok());
    let e = raytrace_fragments(ok, faces.clone(), &s, Some(shadows(dir.clone(), 3)));
    assert!(e.err().unwrap().to_string().contains("lights"));
    let area = vec![LightKind::Area];
    let e = raytrace_fragments(ok, faces.clone(), &s, Some(shadows(area, 4)));
    assert!(e.err().unwrap().to_string().contains("area"));
    let hard = MethodSettings::new(Method::Hard, 8, 8);
    let e = render_fragments_lit(ok, faces, &hard, Some(shadows(dir, 2)), &mut |r| Ok(r.bary));
    assert!(e.err().unwrap().to_string().contains("shadow"));
    let t = raytrace_fragments(ok, Arc::new(vec![[0, 1, 2]]), &s, None).unwrap();
    // Edge samples only when the geometry asks for a gradient.
    let tri = ArrayD::from_shape_vec(
        IxDyn(&[3, 4]),
        vec![
            -0.5, -0.5, 0.5, 1.0, 0.5, -0.5, 0.5, 1.0, 0.0, 0.5, 0.5, 1.0,
        ],
    )
    .unwrap();
    for wants in [false, true] {
        let c = tape.var(tri.clone(), wants);
        let b = raytrace_fragments(c, Arc::new(vec![[0, 1, 2]]), &s, None).unwrap();
        assert_eq!(!b.band.fragments.is_empty(), wants);
    }
    let band = tape.constant(ArrayD::zeros(IxDyn(&[t.band.fragments.len() + 1, 3])));
    let col = tape.constant(ArrayD::zeros(IxDyn(&[t.raster.fragments.len(), 3])));
    assert!(blend_traced(col, band, &t, ok, &[0.0; 3]).is_err());
}

/// A textured plane scene with `lights` (JSON) rendered by `method` at `size`.
fn textured_scene(
    dir: &std::path::Path,
    lights: &str,
    method: &str,
    size: usize,
    spp: usize,
) -> render_ops::Scene<f64> {
    let plane = Mesh::<f64>::grid_plane(3);
    render_ops::obj::write_obj(dir.join("m.obj"), &plane).unwrap();
    let tex = ndarray::Array3::from_shape_fn((8, 8, 3), |(r, c, ch)| {
        ((0.5 + 0.4 * (r as f64 * 0.9 + c as f64 * 1.7 + ch as f64).sin()) * 255.0).round() / 255.0
    });
    render_ops::io::write_png(dir.join("tex.png"), &tex).unwrap();
    let json = format!(
        r#"{{"mesh": "m.obj", "texture": "tex.png",
        "camera": {{"eye": [0.4, -1.2, 2.6], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 40,
                   "near": 0.5, "far": 10}},
        "image": {{"width": {size}, "height": {size}, "background": [0.1, 0.2, 0.3]}},
        "lights": {lights}, "material": {{"shading": "lambert", "kd": [0.9, 0.8, 0.7]}},
        "raster": {{"method": "{method}", "spp": {spp}, "seed": 2}}}}"#
    );
    render_ops::Scene::from_json(&json, dir, "scene.json").unwrap()
}

#[test]
fn textured_scenes_render_through_the_stages() {
    use render_ops::pipeline::{SceneInput, Wrt};
    let dir = crate::common::scenes::temp_dir("raytrace-textured");
    let lights = r#"[{"type": "ambient", "color": [0.3, 0.3, 0.3]},
        {"type": "sh", "coeffs": [[0.8, 0.8, 0.8], [0.1, 0.1, 0.1], [0.3, 0.3, 0.3],
         [0.1, 0.1, 0.1], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]}]"#;
    let size = 16;
    // The ray-traced scene converges to the 16 x 16-supersampled hard render of the same scene.
    let rt = textured_scene(&dir, lights, "raytrace", size, 64)
        .render_image()
        .unwrap();
    let big = textured_scene(&dir, lights, "hard", size * 16, 1)
        .render_image()
        .unwrap();
    let mut reference = vec![0.0; size * size * 4];
    for ((r, c, ch), v) in big
        .view()
        .into_dimensionality::<ndarray::Ix3>()
        .unwrap()
        .indexed_iter()
    {
        reference[((r / 16) * size + c / 16) * 4 + ch] += v / 256.0;
    }
    let e = rmse(&rt.iter().copied().collect::<Vec<_>>(), &reference);
    eprintln!("textured scene: rmse {e:.4} at 64 spp");
    assert!(e < 0.01, "{e}");
    // Gradients reach the texels and the positions.
    let sc = textured_scene(&dir, lights, "raytrace", size, 4);
    let target = ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.5);
    for input in [SceneInput::Texture, SceneInput::Positions] {
        let (loss, g) = sc.image_loss_grad(target.clone(), "target", input).unwrap();
        assert!(loss.is_finite() && g.iter().all(|x| x.is_finite()));
        assert!(g.iter().any(|x| x.abs() > 1e-6), "{input:?}");
    }
    // An area light with a texture: a typed error naming the method.
    let area = r#"[{"type": "area", "corner": [-0.3, 2, -0.3], "edge_u": [0.6, 0, 0],
        "edge_v": [0, 0, 0.6], "radiance": [1, 1, 1]}]"#;
    let sc = textured_scene(&dir, area, "raytrace", size, 4);
    let tape = Tape::new();
    let e = sc.render(&sc.vars(&tape, Wrt::default())).unwrap_err();
    assert!(e.to_string().contains("raytrace"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A ground plane and a quad occluder above it (in view), with uvs; `texture` names a white
/// texture or none; Lambert under an ambient, a directional and a point light.
fn shadow_scene(dir: &std::path::Path, texture: bool) -> render_ops::Scene<f64> {
    let mut m = Mesh::new(
        vec![
            [-2.0, 0.0, -2.0],
            [2.0, 0.0, -2.0],
            [2.0, 0.0, 2.0],
            [-2.0, 0.0, 2.0],
            [-0.6, 0.9, -0.3],
            [0.1, 0.9, -0.25],
            [0.05, 0.9, 0.3],
            [-0.55, 0.95, 0.25],
        ],
        vec![[0, 2, 1], [0, 3, 2], [4, 6, 5], [4, 7, 6]],
    );
    m.uvs = m
        .positions
        .iter()
        .map(|p| [0.5 + 0.2 * p[0], 0.5 + 0.2 * p[2]])
        .collect();
    m.uv_faces = m.faces.clone();
    m.colors = m
        .positions
        .iter()
        .map(|p| [0.8, 0.6 + 0.1 * p[1], 0.5])
        .collect();
    render_ops::obj::write_obj(dir.join("m.obj"), &m).unwrap();
    render_ops::io::write_png(
        dir.join("white.png"),
        &ndarray::Array3::from_elem((2, 2, 3), 1.0),
    )
    .unwrap();
    let json = format!(
        r#"{{"mesh": "m.obj", "texture": {},
        "camera": {{"eye": [0.3, 3, 2.2], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 45,
                   "near": 0.1, "far": 100}},
        "image": {{"width": 16, "height": 16, "background": [0.1, 0.1, 0.1]}},
        "lights": [{{"type": "ambient", "color": [0.2, 0.2, 0.2]}},
                   {{"type": "directional", "direction": [0.3, -1, -0.2], "color": [0.8, 0.8, 0.8]}},
                   {{"type": "point", "position": [0.4, 2.5, 0.6], "color": [0.5, 0.4, 0.3]}}],
        "material": {{"shading": "lambert", "kd": [0.9, 0.8, 0.7]}},
        "raster": {{"method": "raytrace", "spp": 4, "seed": 3, "edge_samples": 1024,
                   "shadow_edge_samples": 4096}}}}"#,
        if texture { "\"white.png\"" } else { "null" }
    );
    render_ops::Scene::from_json(&json, dir, "scene.json").unwrap()
}

/// With a white texture, a lit scene through the fragment stages (shadows by the stage's
/// visibility, shadow-edge terms in `blend_traced`) equals the fused op on the same scene
/// with vertex colours: the image, and the gradients with respect to positions and lights.
#[test]
fn composed_shadows_equal_the_fused_op() {
    use render_ops::pipeline::SceneInput;
    let dir = crate::common::scenes::temp_dir("raytrace-shadows");
    let fused = shadow_scene(&dir, false);
    let composed = shadow_scene(&dir, true);
    let (a, b) = (
        fused.render_image().unwrap(),
        composed.render_image().unwrap(),
    );
    let (a, b): (Vec<f64>, Vec<f64>) = (a.iter().copied().collect(), b.iter().copied().collect());
    assert!(
        max_abs_diff(&a, &b) <= 1e-12,
        "image {}",
        max_abs_diff(&a, &b)
    );
    // Some pixels in shadow: the plane's lit and shadowed values differ.
    let target = ArrayD::from_elem(IxDyn(&[16, 16, 4]), 0.3);
    for input in [SceneInput::Positions, SceneInput::Lights] {
        let (la, ga) = fused.image_loss_grad(target.clone(), "t", input).unwrap();
        let (lb, gb) = composed
            .image_loss_grad(target.clone(), "t", input)
            .unwrap();
        assert!(
            (la - lb).abs() <= 1e-10 * la.abs(),
            "{input:?}: loss {la} {lb}"
        );
        let (ga, gb): (Vec<f64>, Vec<f64>) =
            (ga.iter().copied().collect(), gb.iter().copied().collect());
        let scale = max_abs(&ga);
        assert!(scale > 0.0, "{input:?}: no gradient");
        let d = max_abs_diff(&ga, &gb);
        assert!(d <= 1e-9 * scale, "{input:?}: {d} against {scale}");
    }
    std::fs::remove_dir_all(&dir).ok();
}
