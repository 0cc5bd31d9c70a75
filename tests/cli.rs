//! The `tapestry` binary as a user runs it: outputs, exit codes, one-line errors.

mod common;

use std::process::Command;

fn tapestry() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tapestry"))
}

#[test]
fn render_and_grad_write_their_files() {
    let Some(peers) = common::peers_dir() else {
        eprintln!("peer kit not found: skipped");
        return;
    };
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
