//! `tapestry gradcheck` on scenes and on the registry, and the library check it calls.

use std::path::{Path, PathBuf};
use std::process::Command;

use tapestry::autodiff::{BackwardCtx, Op, Result as AdResult, Tape, Tensor, TensorView};
use tapestry::render_ops::check::scene::{check_scene, SceneCheckOptions, SceneInput};
use tapestry::render_ops::check::{check_image_gradient, cosine_rel_l2, pipeline, CheckOptions};
use tapestry::render_ops::mesh::Mesh;
use tapestry::render_ops::pipeline::Wrt;
use tapestry::render_ops::scene::Scene;

fn tapestry() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tapestry"))
}

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-gradcheck-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
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

/// Writes `mesh` and a 32 x 32 scene JSON with `extra` (lights, material, raster) into
/// `dir`; returns the JSON path.
fn write_scene(dir: &Path, name: &str, mesh: &Mesh<f64>, extra: &str) -> PathBuf {
    let obj = format!("{name}.obj");
    tapestry::render_ops::obj::write_obj(dir.join(&obj), mesh).unwrap();
    let json = format!(
        r#"{{"mesh": "{obj}",
        "camera": {{"eye": [0.3, 0.2, 3.5], "at": [0, 0, 0], "fov_y_deg": 45, "near": 1, "far": 10}},
        "image": {{"width": 32, "height": 32, "background": [0.1, 0.1, 0.1]}}{extra}}}"#
    );
    let p = dir.join(format!("{name}.json"));
    std::fs::write(&p, json).unwrap();
    p
}

/// One mesh of two spheres, the front one hiding part of the back one (self-occlusion).
fn occlusion_mesh() -> Mesh<f64> {
    let back = colored_sphere(2, 0.7, [-0.3, -0.1, -0.4], [0.4, 0.6, 1.0]);
    let front = colored_sphere(2, 0.45, [0.35, 0.15, 0.5], [1.0, 0.6, 0.4]);
    let n = back.positions.len() as u32;
    let mut positions = back.positions;
    positions.extend(front.positions);
    let mut colors = back.colors;
    colors.extend(front.colors);
    let mut faces = back.faces;
    faces.extend(front.faces.iter().map(|f| f.map(|i| i + n)));
    Mesh::new(positions, faces).with_colors(colors)
}

fn json_of(out: &std::process::Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{e}: {}\n{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
    })
}

#[test]
fn colors_pass_on_hard_softras_and_deodr_scenes() {
    let dir = temp_dir("colors");
    let scene = write_scene(
        &dir,
        "sphere",
        &colored_sphere(2, 0.9, [0.0; 3], [1.0; 3]),
        "",
    );
    for method in ["hard", "softras", "deodr"] {
        let out = tapestry()
            .arg("gradcheck")
            .arg(&scene)
            .args([
                "--wrt",
                "colors",
                "--method",
                method,
                "--vertices",
                "24",
                "--json",
            ])
            .output()
            .unwrap();
        let v = json_of(&out);
        assert_eq!(out.status.code(), Some(0), "{method}: {v}");
        assert_eq!(v["passed"], true, "{method}");
        assert_eq!(v["method"], method);
        assert!(
            v["own"]["cosine"].as_f64().unwrap() > 1.0 - 1e-9,
            "{method}: {v}"
        );
        assert_eq!(v["items"].as_array().unwrap().len(), 24);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_wrong_backward_fails_with_exit_1_naming_the_worst_vertices() {
    let dir = temp_dir("wrong");
    let scene = write_scene(
        &dir,
        "sphere",
        &colored_sphere(2, 0.9, [0.0; 3], [1.0; 3]),
        "",
    );
    let out = tapestry()
        .arg("gradcheck")
        .arg(&scene)
        .args(["--wrt", "colors", "--vertices", "12"])
        .args(["--self-test-backward-scale", "1.5"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1), "{text}");
    assert!(text.contains("FAILED: "), "{text}");
    let worst: Vec<&str> = text
        .lines()
        .filter(|l| l.trim_start().starts_with("vertex "))
        .collect();
    assert_eq!(worst.len(), 10, "{text}");
    assert!(worst[0].contains(" at pixel ("), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A test op, "scale colours": forward `0.8 x`, backward `1.2 g` (1.5 times the right one).
struct ScaleColors;

impl Op<f64> for ScaleColors {
    fn name(&self) -> &'static str {
        "scale_colors (wrong backward)"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, f64>]) -> AdResult<Vec<Tensor<f64>>> {
        Ok(vec![inputs[0].mapv(|x| 0.8 * x)])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, f64>) -> AdResult<Vec<Option<Tensor<f64>>>> {
        Ok(vec![Some(ctx.grad_outputs[0].mapv(|g| 1.2 * g))])
    }
}

#[test]
fn the_library_check_catches_a_user_op_with_a_wrong_backward() {
    let dir = temp_dir("userop");
    let path = write_scene(
        &dir,
        "sphere",
        &colored_sphere(2, 0.9, [0.0; 3], [1.0; 3]),
        "",
    );
    let scene = Scene::<f64>::load(&path).unwrap();
    let tape = Tape::new();
    let colors = (*scene.vars(&tape, Wrt::default()).colors.value().unwrap()).clone();
    let target = tapestry::render_ops::check::scene::default_target(&scene).unwrap();
    let with_op = |wrong: bool| {
        let scene = &scene;
        pipeline(move |t, x| {
            let mut vars = scene.vars(t, Wrt::default());
            vars.colors = if wrong {
                t.apply(ScaleColors, &[x])
            } else {
                x * 0.8
            };
            scene.render(&vars)
        })
    };
    let opts = CheckOptions {
        items: tapestry::render_ops::check::Items::Random(30),
        ..Default::default()
    };
    let good = check_image_gradient(with_op(false), &colors, &target, &opts).unwrap();
    assert!(good.passed && good.cosine > 1.0 - 1e-9, "{good:?}");
    let bad = check_image_gradient(with_op(true), &colors, &target, &opts).unwrap();
    assert!(!bad.passed);
    // Every vertex with a gradient is off by exactly the factor; the worst are named.
    let worst = bad.worst(3);
    assert!(worst.iter().all(|w| !w.passed && w.abs_err > 0.0));
    for i in bad
        .items
        .iter()
        .filter(|i| i.numeric.iter().any(|n| n.abs() > 1e-3))
    {
        for (a, n) in i.analytic.iter().zip(&i.numeric) {
            if n.abs() > 1e-3 {
                assert!((a / n - 1.5).abs() < 1e-4, "{i:?}");
            }
        }
    }
    // The scene check (what the CLI runs) fails the same way.
    let mut o = SceneCheckOptions::new(SceneInput::Colors);
    o.items = 12;
    o.backward_scale = Some(1.5);
    let c = check_scene(&scene, None, &o).unwrap();
    assert!(!c.passed() && !c.worst(1)[0].own_passed);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn positions_report_per_category_cosines_on_a_self_occluding_scene() {
    let dir = temp_dir("positions");
    let scene = write_scene(&dir, "occlusion", &occlusion_mesh(), "");
    let out_dir = dir.join("out");
    let out = tapestry()
        .arg("gradcheck")
        .arg(&scene)
        .args(["--wrt", "positions", "--method", "deodr", "--samples", "4"])
        .args(["--vertices", "30", "--json", "--out"])
        .arg(&out_dir)
        .output()
        .unwrap();
    let v = json_of(&out);
    assert_eq!(out.status.code(), Some(0), "{v}");
    assert!(out_dir.join("disagreement.png").is_file());
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(report["categories"], v["categories"]);
    let items = v["items"].as_array().unwrap();
    assert_eq!(items.len(), 30);
    let cats = v["categories"].as_array().unwrap();
    let names: Vec<&str> = cats
        .iter()
        .map(|c| c["category"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["silhouette", "occlusion_contour", "interior"]);
    // Independently: the cosine and relative L2 of each category from the item records.
    let vec_of = |x: &serde_json::Value| -> Vec<f64> {
        x.as_array()
            .unwrap()
            .iter()
            .map(|a| a.as_f64().unwrap())
            .collect()
    };
    for c in cats {
        let sel: Vec<&serde_json::Value> = items
            .iter()
            .filter(|i| i["category"] == c["category"])
            .collect();
        assert_eq!(sel.len() as u64, c["count"].as_u64().unwrap());
        assert!(sel.len() >= 5, "{c}");
        let a: Vec<f64> = sel.iter().flat_map(|i| vec_of(&i["analytic"])).collect();
        let r: Vec<f64> = sel.iter().flat_map(|i| vec_of(&i["reference"])).collect();
        let n: Vec<f64> = sel.iter().flat_map(|i| vec_of(&i["numeric"])).collect();
        let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>();
        let cos = |x: &[f64], y: &[f64]| dot(x, y) / (dot(x, x).sqrt() * dot(y, y).sqrt());
        let want_ref = cos(&a, &r);
        let want_own = cos(&a, &n);
        assert!(
            (c["cosine_reference"].as_f64().unwrap() - want_ref).abs() < 1e-9,
            "{c}"
        );
        assert!(
            (c["cosine_own"].as_f64().unwrap() - want_own).abs() < 1e-9,
            "{c}"
        );
        let (_, rel) = cosine_rel_l2(a.iter().copied(), r.iter().copied());
        assert!((c["rel_l2_reference"].as_f64().unwrap() - rel).abs() < 1e-9 * rel.max(1.0));
        // DEODR differentiates its own image exactly, in every category.
        assert!(want_own > 1.0 - 1e-6, "{c}");
    }
    // The worst items carry screen positions inside the image.
    for w in v["worst"].as_array().unwrap() {
        let p = vec_of(&w["pixel"]);
        assert!(p.iter().all(|&x| (0.0..=32.0).contains(&x)), "{w}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn lights_and_camera_inputs_and_errors() {
    let dir = temp_dir("lights");
    let lit = r#", "lights": [{"type": "directional", "direction": [0.2, -0.3, -1], "color": [0.9, 0.8, 0.7]},
                   {"type": "point", "position": [1, 1, 3], "color": [0.3, 0.3, 0.3]},
                   {"type": "ambient", "color": [0.1, 0.1, 0.1]}],
        "material": {"shading": "phong", "kd": [0.9, 0.9, 0.9], "ks": [0.3, 0.3, 0.3], "shininess": 8}"#;
    let scene = write_scene(
        &dir,
        "lit",
        &colored_sphere(2, 0.9, [0.0; 3], [1.0; 3]),
        lit,
    );
    let out = tapestry()
        .arg("gradcheck")
        .arg(&scene)
        .args(["--wrt", "lights", "--json"])
        .output()
        .unwrap();
    let v = json_of(&out);
    assert_eq!(out.status.code(), Some(0), "{v}");
    // direction, colour; position, colour; colour.
    assert_eq!(v["items"].as_array().unwrap().len(), 5);
    // The texture of a scene without one: a one-line error, exit 2.
    let out = tapestry()
        .arg("gradcheck")
        .arg(&scene)
        .args(["--wrt", "texture"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("has no texture") && err.trim_end().lines().count() == 1,
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn all_runs_every_category_and_every_case_passes() {
    let out = tapestry()
        .args(["gradcheck", "--all", "--json"])
        .output()
        .unwrap();
    let v = json_of(&out);
    let recs = v.as_array().unwrap();
    let failed: Vec<&serde_json::Value> = recs.iter().filter(|r| r["passed"] != true).collect();
    assert!(failed.is_empty(), "{failed:?}");
    assert_eq!(out.status.code(), Some(0));
    for cat in ["autodiff", "shade", "texture", "raster", "method"] {
        assert!(recs.iter().any(|r| r["category"] == cat), "no {cat} case");
    }
    for m in [
        "hard", "tf_mesh", "opendr", "nmr", "softras", "dibr", "deodr",
    ] {
        let name = format!("method/{m}");
        assert!(
            recs.iter()
                .any(|r| r["op"].as_str().unwrap().starts_with(&name)),
            "no case of {m}"
        );
    }
    // --op selects by category.
    let out = tapestry()
        .args(["gradcheck", "--op", "raster", "--json"])
        .output()
        .unwrap();
    let v = json_of(&out);
    assert!(v
        .as_array()
        .unwrap()
        .iter()
        .all(|r| r["category"] == "raster"));
}
