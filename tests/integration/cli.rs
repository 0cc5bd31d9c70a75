//! The `tapestry` binary as a user runs it: outputs, exit codes, one-line errors.

use crate::common;

use std::process::Command;

fn tapestry() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tapestry"))
}

#[test]
fn render_and_grad_write_their_files() {
    let peers = common::peers_dir();
    let dir = std::env::temp_dir().join(format!("tapestry-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = peers.join("scenes/ico5k_hard.json");
    let out = tapestry()
        .arg("render")
        .arg(&scene)
        .arg("--out")
        .arg(dir.join("a.png"))
        .arg("--npy")
        .arg(dir.join("a.npy"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let img: tapestry::autodiff::Tensor<f64> =
        tapestry::render_ops::io::read_npy(dir.join("a.npy")).unwrap();
    assert_eq!(img.shape(), &[128, 128, 4]);
    let png = tapestry::render_ops::io::read_png::<f64>(dir.join("a.png")).unwrap();
    assert_eq!(png.shape(), &[128, 128, 3]);

    for wrt in ["positions", "colors"] {
        let g = dir.join(format!("g_{wrt}.npy"));
        let out = tapestry()
            .arg("grad")
            .arg(&scene)
            .arg("--target")
            .arg(peers.join("reference/deodr_target.npy"))
            .arg("--wrt")
            .arg(wrt)
            .arg("--out")
            .arg(&g)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(String::from_utf8_lossy(&out.stdout).starts_with("loss "));
        let g: tapestry::autodiff::Tensor<f64> = tapestry::render_ops::io::read_npy(&g).unwrap();
        assert_eq!(g.shape(), &[2562, 3]);
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|&v| v != 0.0));
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_inputs_give_one_line_errors_and_nonzero_exit() {
    let dir = std::env::temp_dir().join(format!("tapestry-cli-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bad = dir.join("bad.json");
    std::fs::write(
        &bad,
        r#"{"mesh": "x.obj", "camera": {}, "image": {"width": 4, "height": 4}, "oops": 1}"#,
    )
    .unwrap();
    for args in [
        vec![
            "render".to_string(),
            bad.display().to_string(),
            "--out".into(),
            "/tmp/never.png".into(),
        ],
        vec![
            "render".to_string(),
            "/nonexistent/scene.json".into(),
            "--out".into(),
            "/tmp/never.png".into(),
        ],
        vec!["gradcheck".to_string(), "--op".into(), "no_such_op".into()],
    ] {
        let out = tapestry().args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        assert!(
            err.starts_with("tapestry: error:") && !err.contains("panicked"),
            "{err}"
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn gradcheck_command_reports_json_records() {
    let out = tapestry()
        .args(["gradcheck", "--op", "exp", "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let recs = v.as_array().unwrap();
    assert!(!recs.is_empty());
    for r in recs {
        assert!(r["op"].as_str().unwrap().contains("exp"));
        assert!(r["passed"].as_bool().unwrap());
        assert!(r["max_abs_err"].as_f64().unwrap() < 1e-5);
    }
}

/// A textured, Phong-shaded plane scene in `dir` (mesh, 8 x 8 texture, JSON); returns the
/// scene path. `texture: false` leaves the texture out.
fn phong_scene(dir: &std::path::Path, texture: bool) -> std::path::PathBuf {
    use tapestry::render_ops::mesh::Mesh;
    let plane = Mesh::<f64>::grid_plane(4);
    tapestry::render_ops::obj::write_obj(dir.join("plane.obj"), &plane).unwrap();
    let tex = ndarray::Array3::from_shape_fn((8, 8, 3), |(r, c, k)| {
        (40 + 20 * r + 25 * c + 60 * k) as f64 % 256.0 / 255.0
    });
    tapestry::render_ops::io::write_png(dir.join("tex.png"), &tex).unwrap();
    let json = format!(
        r#"{{"mesh": "plane.obj", "texture": {},
        "camera": {{"eye": [0.3, 0.4, 3], "at": [0, 0, 0], "fov_y_deg": 50}},
        "image": {{"width": 32, "height": 32, "background": [0, 0, 0.2]}},
        "lights": [{{"type": "directional", "direction": [0.1, 0.2, -1], "color": [1, 1, 1]}},
                   {{"type": "ambient", "color": [0.1, 0.1, 0.1]}}],
        "material": {{"shading": "phong", "kd": [0.9, 0.9, 0.9], "ks": [0.5, 0.5, 0.5],
                     "shininess": 16}},
        "raster": {{"method": "hard"}}}}"#,
        if texture { "\"tex.png\"" } else { "null" }
    );
    let path = dir.join(if texture {
        "phong.json"
    } else {
        "phong_plain.json"
    });
    std::fs::write(&path, json).unwrap();
    path
}

#[test]
fn render_phong_and_grad_wrt_texture_and_camera() {
    let dir = std::env::temp_dir().join(format!("tapestry-cli-phong-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = phong_scene(&dir, true);
    let out = tapestry()
        .arg("render")
        .arg(&scene)
        .arg("--out")
        .arg(dir.join("phong.png"))
        .arg("--npy")
        .arg(dir.join("phong.npy"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let img: tapestry::autodiff::Tensor<f64> =
        tapestry::render_ops::io::read_npy(dir.join("phong.npy")).unwrap();
    assert_eq!(img.shape(), &[32, 32, 4]);
    assert!(img.iter().all(|v| v.is_finite()));
    // Lit: the centre is brighter than kd * texel (ambient + diffuse + highlight), and the
    // texture varies the colour across the plane.
    let centre: Vec<f64> = (0..3).map(|k| img[[16, 16, k]]).collect();
    assert!(
        img[[16, 16, 3]] == 1.0 && centre.iter().all(|&c| c > 0.3),
        "{centre:?}"
    );
    let spread = (0..32)
        .map(|c| img[[16, c, 0]])
        .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
    assert!(spread.1 - spread.0 > 0.1, "{spread:?}");
    // The target: the same scene rendered, shifted by 0.1, as a 3-channel .npy.
    let target = img.slice(ndarray::s![.., .., 0..3]).mapv(|v| v + 0.1);
    tapestry::render_ops::io::write_npy(dir.join("target.npy"), &target).unwrap();
    for (wrt, shape) in [("texture", vec![8, 8, 3]), ("camera", vec![2, 3])] {
        let g = dir.join(format!("g_{wrt}.npy"));
        let out = tapestry()
            .arg("grad")
            .arg(&scene)
            .arg("--target")
            .arg(dir.join("target.npy"))
            .arg("--wrt")
            .arg(wrt)
            .arg("--out")
            .arg(&g)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{wrt}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let stdout = String::from_utf8_lossy(&out.stdout).to_string();
        let loss: f64 = stdout
            .trim()
            .strip_prefix("loss ")
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("{stdout}"));
        // Every covered pixel is off by 0.1 in each channel, the background too.
        assert!((loss - 0.01 * 32.0 * 32.0 * 3.0).abs() < 1e-9, "{loss}");
        let g: tapestry::autodiff::Tensor<f64> = tapestry::render_ops::io::read_npy(&g).unwrap();
        assert_eq!(g.shape(), &shape[..], "{wrt}");
        assert!(g.iter().all(|v| v.is_finite()) && g.iter().any(|&v| v.abs() > 1e-6));
        if wrt == "texture" {
            // The render is 0.1 too dark everywhere: every visible texel should get brighter.
            assert!(g.iter().filter(|&&v| v < 0.0).count() > 150, "{g:?}");
        }
    }
    // The boundary and soft methods over the textured, Phong-lit scene: render, and every --wrt.
    let json = std::fs::read_to_string(&scene).unwrap();
    for method in ["opendr", "nmr", "deodr", "softras", "dibr"] {
        let sc = dir.join(format!("{method}.json"));
        std::fs::write(
            &sc,
            json.replace(r#""method": "hard""#, &format!(r#""method": "{method}""#)),
        )
        .unwrap();
        let out = tapestry()
            .arg("render")
            .arg(&sc)
            .arg("--out")
            .arg(dir.join(format!("{method}.png")))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{method}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        for wrt in ["positions", "colors", "texture", "camera", "lights"] {
            let g = dir.join(format!("g_{method}_{wrt}.npy"));
            let out = tapestry()
                .arg("grad")
                .arg(&sc)
                .arg("--target")
                .arg(dir.join("target.npy"))
                .args(["--wrt", wrt, "--out"])
                .arg(&g)
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{method} {wrt}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let g: tapestry::autodiff::Tensor<f64> =
                tapestry::render_ops::io::read_npy(&g).unwrap();
            assert!(
                g.iter().all(|v| v.is_finite()) && g.iter().any(|&v| v.abs() > 1e-6),
                "{method} {wrt}"
            );
        }
    }
    // --wrt texture on a scene without a texture: a one-line error.
    let plain = phong_scene(&dir, false);
    let out = tapestry()
        .arg("grad")
        .arg(&plain)
        .arg("--target")
        .arg(dir.join("target.npy"))
        .args(["--wrt", "texture", "--out"])
        .arg(dir.join("never.npy"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("no texture") && err.trim_end().lines().count() == 1,
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

/// Runs `tapestry ARGS` and checks that it failed the way a user should see it: exit code 2,
/// exactly one line on stderr starting with `tapestry: error:` and holding `expect`, and no
/// panic. Returns that line.
fn fails_with_one_line(args: &[&std::ffi::OsStr], expect: &str) -> String {
    let out = tapestry().args(args).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
    assert!(
        err.starts_with("tapestry: error:") && !err.contains("panicked"),
        "{args:?}: {err}"
    );
    assert!(err.contains(expect), "{args:?}: {err:?} lacks {expect:?}");
    err
}

#[test]
fn bad_files_and_oversized_requests_give_one_line_errors() {
    use std::ffi::OsStr;
    let dir = std::env::temp_dir().join(format!("tapestry-cli-robust-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tri = "v -1 -1 0\nv 1 -1 0\nv 0 1 0\nf 1 2 3\n";
    std::fs::write(dir.join("tri.obj"), tri).unwrap();
    std::fs::write(dir.join("bad_number.obj"), "v 0 0 zero\nf 1 2 3\n").unwrap();
    std::fs::write(dir.join("bad_index.obj"), tri.replace("f 1 2 3", "f 1 2 7")).unwrap();
    let scene = |name: &str, mesh: &str, image: &str, raster: &str| {
        let p = dir.join(name);
        std::fs::write(
            &p,
            format!(
                r#"{{"mesh": "{mesh}",
                "camera": {{"eye": [0, 0, 3], "at": [0, 0, 0], "fov_y_deg": 45}},
                "image": {image}, "raster": {raster}}}"#
            ),
        )
        .unwrap();
        p
    };
    let small = r#"{"width": 8, "height": 8}"#;
    let hard = r#"{"method": "hard"}"#;
    let good = scene("good.json", "tri.obj", small, hard);
    let png = dir.join("out.png");
    let o = |p: &std::path::Path| p.as_os_str().to_owned();
    let render = |s: &std::path::Path, expect: &str| {
        fails_with_one_line(
            &[OsStr::new("render"), &o(s), OsStr::new("--out"), &o(&png)],
            expect,
        )
    };
    // The good scene renders: the failures below are the inputs' fault.
    let ok = tapestry()
        .args([
            OsStr::new("render"),
            &o(&good),
            OsStr::new("--out"),
            &o(&png),
        ])
        .output()
        .unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );

    render(
        &scene("a.json", "bad_number.obj", small, hard),
        "bad_number.obj:1: bad number 'zero'",
    );
    render(
        &scene("b.json", "bad_index.obj", small, hard),
        "index 7 is out of range",
    );
    render(&scene("c.json", "none.obj", small, hard), "none.obj");
    render(
        &scene("d.json", "tri.obj", r#"{"width": "8", "height": 8}"#, hard),
        "image.width: invalid type",
    );
    render(
        &scene(
            "e.json",
            "tri.obj",
            small,
            r#"{"method": "hard", "sigmaa": 1}"#,
        ),
        "sigmaa",
    );
    // A texture needs uvs: a textured scene over a mesh without 'vt' lines names the mesh.
    tapestry::render_ops::io::write_png(
        dir.join("t.png"),
        &tapestry::autodiff::ndarray::Array3::<f64>::from_elem((2, 2, 3), 0.5),
    )
    .unwrap();
    render(
        &scene(
            "f.json",
            r#"tri.obj", "texture": "t.png"#,
            small,
            r#"{"method": "softras"}"#,
        ),
        "tri.obj has no uvs",
    );
    // Too large for memory: refused before allocating (a 4096^2 image at 16 faces per pixel is
    // 268M fragment slots; 65536^2 pixels is past the packed layout's pixel limit).
    render(
        &scene(
            "g.json",
            "tri.obj",
            r#"{"width": 4096, "height": 4096}"#,
            r#"{"method": "hard", "faces_per_pixel": 16}"#,
        ),
        "over the limit of 67108864",
    );
    render(
        &scene(
            "h.json",
            "tri.obj",
            r#"{"width": 65536, "height": 65536}"#,
            hard,
        ),
        "too large",
    );
    // SoftRas with a huge sigma reaches every pixel from every face: 5000 faces at 1024^2
    // would need 20M per-tile face list entries.
    std::fs::write(
        dir.join("many.obj"),
        format!("v -1 -1 0\nv 1 -1 0\nv 0 1 0\n{}", "f 1 2 3\n".repeat(5000)),
    )
    .unwrap();
    render(
        &scene(
            "i.json",
            "many.obj",
            r#"{"width": 1024, "height": 1024}"#,
            r#"{"method": "softras", "sigma": 10}"#,
        ),
        "per-tile face list entries",
    );
    // Output that cannot be written.
    fails_with_one_line(
        &[
            OsStr::new("render"),
            &o(&good),
            OsStr::new("--out"),
            OsStr::new("/nonexistent/dir/x.png"),
        ],
        "/nonexistent/dir/x.png",
    );

    // grad: corrupt PNG, 2-channel PNG, integer .npy and wrong-shape .npy targets.
    let grad = |target: &std::path::Path, expect: &str| {
        fails_with_one_line(
            &[
                OsStr::new("grad"),
                &o(&good),
                OsStr::new("--target"),
                &o(target),
                OsStr::new("--wrt"),
                OsStr::new("positions"),
                OsStr::new("--out"),
                &o(&dir.join("g.npy")),
            ],
            expect,
        )
    };
    let corrupt = dir.join("corrupt.png");
    std::fs::write(&corrupt, b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR").unwrap();
    grad(&corrupt, "cannot decode PNG");
    let gray = dir.join("gray.png");
    tapestry::render_ops::io::write_png(
        &gray,
        &tapestry::autodiff::ndarray::Array3::<f64>::zeros((8, 8, 1)),
    )
    .unwrap();
    grad(&gray, "does not match the scene's image");
    let ints = dir.join("ints.npy");
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    let mut header = "{'descr': '<i8', 'fortran_order': False, 'shape': (8, 8, 3), }".to_string();
    // Pad so that magic, version, length and header fill a multiple of 64 bytes.
    let pad = 63 - (10 + header.len()) % 64;
    header.push_str(&" ".repeat(pad));
    header.push('\n');
    npy.extend((header.len() as u16).to_le_bytes());
    npy.extend(header.as_bytes());
    npy.extend(vec![0u8; 8 * 8 * 3 * 8]);
    std::fs::write(&ints, npy).unwrap();
    grad(&ints, "dtype");
    let wrong = dir.join("wrong.npy");
    tapestry::render_ops::io::write_npy(
        &wrong,
        &tapestry::autodiff::ndarray::Array3::<f64>::zeros((4, 8, 3)),
    )
    .unwrap();
    grad(&wrong, "[4, 8, 3] does not match");
    grad(&dir.join("missing.npy"), "missing.npy");
    std::fs::remove_dir_all(&dir).ok();
}
