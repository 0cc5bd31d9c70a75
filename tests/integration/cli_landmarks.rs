//! `tapestry landmarks` as a user runs it: a photo gives 468 landmark lines, an overlay and
//! the faces' scores; no face, a missing file and a non-image give one-line errors.

use std::path::PathBuf;
use std::process::Command;

fn tapestry() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tapestry"))
}

fn kit(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("models/tests/data/landmarker")
        .join(name)
}

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-cli-lm-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn photo_gives_468_landmark_lines_and_an_overlay() {
    let dir = tmpdir("ok");
    let (txt, png) = (dir.join("l.txt"), dir.join("o.png"));
    let out = tapestry()
        .arg("landmarks")
        .arg(kit("grace_hopper.jpg"))
        .arg("--out")
        .arg(&txt)
        .arg("--overlay")
        .arg(&png)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.starts_with("1 face(s) in "), "{stdout}");
    assert!(stdout.contains("face 0: score 0.93"), "{stdout}");
    // The file reads back as fit-face reads it, and agrees with MediaPipe (centres +0.5).
    let got = tapestry::models::fit::read_landmarks(&txt).unwrap();
    assert_eq!(got.dim(), (468, 2));
    let mp = tapestry::models::fit::read_landmarks(kit("grace_hopper_landmarks_px.txt")).unwrap();
    let mean = (0..468)
        .map(|i| (got[[i, 0]] - mp[[i, 0]] - 0.5).hypot(got[[i, 1]] - mp[[i, 1]] - 0.5))
        .sum::<f64>()
        / 468.0;
    assert!(mean < 0.25, "{mean}");
    let overlay = tapestry::render_ops::io::read_png::<f64>(&png).unwrap();
    assert_eq!(overlay.shape(), &[600, 512, 3]);
    // JSON: every face with its landmarks; a gray photo works too.
    let out = tapestry()
        .arg("landmarks")
        .arg(kit("camera.png"))
        .arg("--json")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let faces = v["faces"].as_array().unwrap();
    assert_eq!(faces.len(), 1);
    assert!(faces[0]["score"].as_f64().unwrap() > 0.7);
    assert_eq!(faces[0]["landmarks"].as_array().unwrap().len(), 468);
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(512), Some(512))
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn no_face_missing_file_and_non_image_are_one_line_errors() {
    let dir = tmpdir("bad");
    let grey = dir.join("grey.png");
    let img = ndarray::Array3::<f64>::from_elem((64, 80, 3), 0.5);
    tapestry::render_ops::io::write_png(&grey, &img).unwrap();
    let text = dir.join("notes.jpg");
    std::fs::write(&text, "not an image").unwrap();
    let missing = dir.join("missing.jpg");
    let cases = [
        (vec![grey.clone()], "grey.png: no face found".to_string()),
        (vec![missing.clone()], format!("{}", missing.display())),
        (vec![text.clone()], "notes.jpg: cannot decode".to_string()),
    ];
    for (args, want) in cases {
        let out = tapestry().arg("landmarks").args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        assert!(
            err.contains(&want) && !err.contains("panicked"),
            "{args:?}: {err}"
        );
    }
    // A face index past the faces found.
    let out = tapestry()
        .arg("landmarks")
        .arg(kit("grace_hopper.jpg"))
        .args(["--face", "3"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--face 3"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}
