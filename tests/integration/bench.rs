//! `tapestry bench`: the reference machinery (pose, supersampled reference, finite
//! differences) and the command's JSON records on the tiny configuration.

use std::process::Command;

use tapestry::bench::{
    self, fd_gradient, image_at, method_gradient, reference_image, sq_loss, BenchScene, Pose,
    SceneKind, FD_STEP_PX, TARGET_POSE,
};
use tapestry::render_ops::scene::{Method, Raster};

fn softras(sigma: f64) -> Raster {
    let mut r = Raster::with_method(Method::SoftRas);
    r.sigma = sigma;
    r.gamma = 1e-4;
    r
}

/// The pose on the tape gives the same positions as the plain function.
#[test]
fn pose_on_the_tape_matches_the_plain_pose() {
    let b = BenchScene::build(SceneKind::Occlusion);
    let scene = b.scene(32, 32, Raster::default()).unwrap();
    let pose = Pose::new(&b, &scene).unwrap();
    let u = [0.3, -1.0, 2.0, 0.5, 1.5, -0.7];
    let tape = tapestry::autodiff::Tape::<f64>::new();
    let leaf = tape.var(
        ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&[6]), u.to_vec()).unwrap(),
        false,
    );
    let v = pose.positions_var(&tape, leaf).value().unwrap();
    let p = pose.positions(&u);
    for (i, q) in p.iter().enumerate() {
        for k in 0..3 {
            assert!((v[[i, k]] - q[k]).abs() < 1e-12);
        }
    }
    // Only the front sphere moves.
    let p0 = pose.positions(&[0.0; 6]);
    assert_eq!(p0[0], p[0]);
    assert_ne!(p0[p.len() - 1], p[p.len() - 1]);
}

/// The finite-difference machinery against a method with an exact gradient: SoftRas at a
/// moderate sigma, its tape gradient against central differences of its own loss.
#[test]
fn finite_differences_match_softras_own_gradient() {
    let b = BenchScene::build(SceneKind::Ico(2));
    let scene = b.scene(24, 24, softras(1e-3)).unwrap();
    let pose = Pose::new(&b, &scene).unwrap();
    let target = image_at(&scene, &pose, &TARGET_POSE).unwrap();
    let (g, _) = method_gradient(&scene, &pose, &[0.0; 6], &target).unwrap();
    let fd = fd_gradient(
        |u| Ok(sq_loss(&image_at(&scene, &pose, u)?, &target)),
        &[0.0; 6],
        1e-3,
    )
    .unwrap();
    let (cos, rel) = bench::compare(&g, &fd);
    assert!(
        cos > 0.9999 && rel < 1e-2,
        "cos {cos} rel {rel}: {g:?} vs {fd:?}"
    );
}

/// The supersampled reference gradient agrees with SoftRas at a small sigma (which tends to
/// the box-filtered image as sigma -> 0).
#[test]
fn reference_gradient_matches_softras_at_small_sigma() {
    // 48 px: sigma 1e-4 puts the soft edge at about a tenth of a pixel; the SoftRas
    // gradient's direction follows the box-filtered one (its size differs: rel < 0.7).
    let b = BenchScene::build(SceneKind::Ico(3));
    let scene = b.scene(48, 48, softras(1e-4)).unwrap();
    let pose = Pose::new(&b, &scene).unwrap();
    let s = 8;
    let target = reference_image(&scene, &pose, &TARGET_POSE, s).unwrap();
    let g_ref = fd_gradient(
        |u| Ok(sq_loss(&reference_image(&scene, &pose, u, s)?, &target)),
        &[0.0; 6],
        FD_STEP_PX,
    )
    .unwrap();
    let (g, img) = method_gradient(&scene, &pose, &[0.0; 6], &target).unwrap();
    let (cos, rel) = bench::compare(&g, &g_ref);
    assert!(
        cos > 0.98 && rel < 0.7,
        "cos {cos} rel {rel}: {g:?} vs {g_ref:?}"
    );
    let reference = reference_image(&scene, &pose, &[0.0; 6], s).unwrap();
    let err = bench::mean_abs(&img, &reference);
    assert!(err < 0.04, "image error {err}");
}

/// `tapestry bench --tiny`: exit 0, the JSON list with the docs/CONVENTIONS.md fields, the charts.
#[test]
fn bench_command_writes_records_and_charts() {
    let dir = std::env::temp_dir().join(format!("tapestry-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("bench.json");
    let out = Command::new(env!("CARGO_BIN_EXE_tapestry"))
        .args(["bench", "--tiny", "--json"])
        .arg(&json)
        .arg("--out")
        .arg(dir.join("charts"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("| scene | method |"), "{stdout}");
    // Progress only on a terminal.
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let records: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let records = records.as_array().unwrap();
    assert!(!records.is_empty());
    let mut methods = std::collections::BTreeSet::new();
    for r in records {
        for key in [
            "method",
            "scene",
            "params",
            "width",
            "height",
            "faces",
            "threads",
            "forward_s",
            "forward_backward_s",
            "peak_bytes",
            "image_error",
            "grad_cosine",
            "grad_rel_l2",
        ] {
            assert!(r.get(key).is_some(), "{key} missing in {r}");
        }
        assert!(r["params"].is_object());
        assert!(r["forward_s"].as_f64().unwrap() > 0.0);
        assert!(r["forward_backward_s"].as_f64().unwrap() > 0.0);
        // The binary counts its allocations.
        assert!(r["peak_bytes"].as_u64().unwrap() > 0, "{r}");
        if r["kind"] == "accuracy" {
            methods.insert(r["method"].as_str().unwrap().to_string());
            let cos = r["grad_cosine"].as_f64().unwrap();
            assert!((-1.0..=1.0 + 1e-12).contains(&cos), "{r}");
            assert!(r["image_error"].as_f64().unwrap() >= 0.0);
            assert!(r["grad_rel_l2"].as_f64().unwrap() >= 0.0);
        }
    }
    for m in ["hard", "tf_mesh", "opendr", "softras", "dibr", "raytrace"] {
        assert!(methods.contains(m), "{m} missing: {methods:?}");
    }
    // The ray tracer's speed against error at several sample counts.
    let spps: std::collections::BTreeSet<u64> = records
        .iter()
        .filter(|r| r["kind"] == "accuracy" && r["method"] == "raytrace")
        .map(|r| r["params"]["spp"].as_u64().unwrap())
        .collect();
    assert_eq!(spps, [1, 4, 16].into(), "{spps:?}");
    for kind in ["faces", "pixels", "threads"] {
        assert!(records.iter().any(|r| r["kind"] == kind), "{kind}");
    }
    for chart in ["pareto.svg", "faces.svg", "pixels.svg", "threads.svg"] {
        let text = std::fs::read_to_string(dir.join("charts").join(chart)).unwrap();
        assert!(text.starts_with("<svg"), "{chart}");
    }
    std::fs::remove_dir_all(&dir).ok();
}
