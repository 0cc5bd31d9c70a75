//! `tapestry fit-face` end to end: every output file, photos of any size and format, any
//! morphable model folder (here the shipped model re-saved with a 68-point iBUG map), and the
//! one-line errors that leave `--out` alone.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use models::fit::{self, SynthOptions, MEDIAPIPE_TO_IBUG68};
use models::{LandmarkScheme, Morphable, SurfacePoint};
use serde_json::Value;

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-ffcli-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn model() -> Morphable<f64> {
    models::face::default_face()
}

/// A synthetic `w x h` "photo" of the shipped model (PNG) and its 468 landmarks (text).
fn photo(d: &Path, w: usize, h: usize, seed: u64) -> (PathBuf, PathBuf, ndarray::Array2<f64>) {
    let s = fit::synthesize(&model(), &SynthOptions::new(w, h, seed)).unwrap();
    let img = d.join("face.png");
    render_ops::io::write_png(&img, &s.target.image).unwrap();
    let lm = d.join("lm.txt");
    std::fs::write(&lm, lines(&s.target.landmarks)).unwrap();
    (img, lm, s.target.landmarks)
}

fn lines(p: &ndarray::Array2<f64>) -> String {
    p.rows()
        .into_iter()
        .map(|r| format!("{} {}\n", r[0], r[1]))
        .collect()
}

fn read_points(p: &Path) -> Vec<[f64; 2]> {
    std::fs::read_to_string(p)
        .unwrap()
        .lines()
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            assert_eq!(v.len(), 2, "{l}");
            [v[0], v[1]]
        })
        .collect()
}

/// `tapestry fit-face ARGS` with a 128 x 128 albedo texture (test time).
fn fit_face(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_tapestry"))
        .args(["fit-face", "--texture-size", "128"])
        .args(args)
        .output()
        .unwrap()
}

fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

#[test]
fn a_resized_photo_gives_every_output_in_its_own_pixels() {
    let d = tmpdir("all");
    // 150 x 120 fitted at 64 x 51: a scale of 0.4267 / 0.425, no integer factor.
    let (img, lm, truth) = photo(&d, 150, 120, 4);
    let out = d.join("out");
    let o = fit_face(&[
        "--model".as_ref(),
        "mediapipe".as_ref(),
        "--target".as_ref(),
        img.as_os_str(),
        "--landmarks".as_ref(),
        lm.as_os_str(),
        "--size".as_ref(),
        "64".as_ref(),
        "--iters".as_ref(),
        "80".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    ok(&o);
    for f in [
        "fit.obj",
        "fit.mtl",
        "albedo.png",
        "landmarks.txt",
        "detected_landmarks.txt",
        "overlay.png",
        "compare.png",
        "fit.png",
        "params.json",
        "report.json",
        "loss_curve.svg",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let read = |f: &str| render_ops::io::read_png::<f64>(out.join(f)).unwrap();
    assert_eq!(read("fit.png").shape(), &[51, 64, 3]);
    assert_eq!(read("overlay.png").shape(), &[120, 150, 3]);
    assert_eq!(read("compare.png").shape(), &[120, 450, 3]);
    // The target landmarks used are the file's, in input pixels.
    let det = read_points(&out.join("detected_landmarks.txt"));
    assert_eq!(det.len(), 468);
    for (p, q) in det.iter().zip(truth.rows()) {
        assert!((p[0] - q[0]).abs() < 1e-3 && (p[1] - q[1]).abs() < 1e-3);
    }
    // The fitted landmarks, in input pixels: close to the truth.
    let fitted = read_points(&out.join("landmarks.txt"));
    assert_eq!(fitted.len(), 468);
    let mean: f64 = fitted
        .iter()
        .zip(truth.rows())
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt())
        .sum::<f64>()
        / 468.0;
    let report = json(&out.join("report.json"));
    let e = report["landmark_error_px"].as_f64().unwrap();
    assert!(
        (mean - e).abs() < 1e-3,
        "landmarks.txt {mean} vs report {e}"
    );
    // Measured 0.25 input px.
    assert!(e < 0.6, "landmark error {e} input px");
    assert_eq!(report["input_width"], 150);
    assert_eq!(report["width"], 64);
    let stages: Vec<&str> = report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            assert!(s["seconds"].as_f64().unwrap() >= 0.0);
            s["stage"].as_str().unwrap()
        })
        .collect();
    assert_eq!(
        stages,
        [
            "load",
            "landmarks",
            "pose_init",
            "stage1",
            "stage2",
            "texture",
            "outputs"
        ]
    );
    assert!(report["stages"][4]["landmark_error_px"].as_f64().is_some());
    // The mesh: 468 vertices with uvs, 898 triangles, the texture named by the material.
    let obj = std::fs::read_to_string(out.join("fit.obj")).unwrap();
    let count = |p: &str| obj.lines().filter(|l| l.starts_with(p)).count();
    assert_eq!((count("v "), count("vt "), count("f ")), (468, 468, 898));
    assert!(obj.contains("mtllib fit.mtl"));
    let mtl = std::fs::read_to_string(out.join("fit.mtl")).unwrap();
    assert!(mtl.contains("map_Kd albedo.png"));
    // The albedo texture, fitted at the input's resolution, lowers the photometric RMSE
    // there below that of the model's per-vertex albedo.
    assert_eq!(read("albedo.png").shape(), &[128, 128, 3]);
    let t = &report["texture"];
    assert_eq!(
        (t["image_width"].as_u64(), t["image_height"].as_u64()),
        (Some(150), Some(120))
    );
    let (before, after) = (
        t["photometric_rmse_before"].as_f64().unwrap(),
        t["photometric_rmse_after"].as_f64().unwrap(),
    );
    assert!(
        after < 0.8 * before,
        "texture stage RMSE {before} -> {after}"
    );
}

#[test]
fn gray_jpeg_photos_are_fitted() {
    let d = tmpdir("jpeg");
    let s = fit::synthesize(&model(), &SynthOptions::new(80, 72, 2)).unwrap();
    let (h, w) = (72u32, 80u32);
    let gray = image::GrayImage::from_fn(w, h, |x, y| {
        let p = s
            .target
            .image
            .slice(ndarray::s![y as usize, x as usize, ..]);
        image::Luma([(255.0 * (p[0] + p[1] + p[2]) / 3.0).round() as u8])
    });
    let img = d.join("face.JPG");
    gray.save_with_format(&img, image::ImageFormat::Jpeg)
        .unwrap();
    let lm = d.join("lm.txt");
    std::fs::write(&lm, lines(&s.target.landmarks)).unwrap();
    let out = d.join("out");
    let o = fit_face(&[
        "--model".as_ref(),
        "mediapipe".as_ref(),
        "--target".as_ref(),
        img.as_os_str(),
        "--landmarks".as_ref(),
        lm.as_os_str(),
        "--size".as_ref(),
        "48".as_ref(),
        "--iters".as_ref(),
        "60".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    ok(&o);
    let compare = render_ops::io::read_png::<f64>(out.join("compare.png")).unwrap();
    assert_eq!(compare.shape(), &[72, 240, 3]);
    // The input panel is gray: the channels agree.
    let p: Vec<f64> = (0..3).map(|k| compare[[36, 40, k]]).collect();
    assert!((p[0] - p[1]).abs() < 1e-9 && (p[1] - p[2]).abs() < 1e-9);
    let e = json(&out.join("report.json"))["landmark_error_px"]
        .as_f64()
        .unwrap();
    // Measured 0.26 px.
    assert!(e < 0.6, "landmark error {e} px");
}

/// The shipped model re-saved with the 68 iBUG landmarks as points on its triangles: a
/// landmark that the table makes the mean of two MediaPipe points is the middle of the edge
/// they share.
fn save_ibug68_model(dir: &Path) {
    let m = model();
    let mut parts = m.to_parts();
    let faces = m.faces();
    parts.landmarks = vec![];
    parts.landmark_points = MEDIAPIPE_TO_IBUG68
        .iter()
        .map(|&(a, b)| {
            let (face, tri) = faces
                .iter()
                .enumerate()
                .find(|(_, t)| t.contains(&(a as u32)) && t.contains(&(b as u32)))
                .unwrap_or_else(|| panic!("no triangle holds {a} and {b}"));
            let mut weights = [0.0; 3];
            for (k, &v) in tri.iter().enumerate() {
                if v as usize == a {
                    weights[k] += if a == b { 1.0 } else { 0.5 };
                }
                if v as usize == b && a != b {
                    weights[k] += 0.5;
                }
            }
            SurfacePoint { face, weights }
        })
        .collect();
    parts.landmark_scheme = Some(LandmarkScheme::Ibug68);
    parts.name = "face-ibug68".into();
    Morphable::from_parts(parts).unwrap().save(dir).unwrap();
}

#[test]
fn a_68_landmark_model_folder_fits_end_to_end() {
    let d = tmpdir("m68");
    let dir = d.join("model68");
    save_ibug68_model(&dir);
    let text = std::fs::read_to_string(dir.join("model.json")).unwrap();
    assert!(text.contains("\"landmark_scheme\": \"ibug68\""));
    // The photo's 468 MediaPipe points: the 68 are picked from them.
    let (img, lm, truth) = photo(&d, 96, 96, 11);
    let out = d.join("out");
    let o = fit_face(&[
        "--model".as_ref(),
        dir.as_os_str(),
        "--target".as_ref(),
        img.as_os_str(),
        "--landmarks".as_ref(),
        lm.as_os_str(),
        "--size".as_ref(),
        "96".as_ref(),
        "--iters".as_ref(),
        "160".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    ok(&o);
    let report = json(&out.join("report.json"));
    assert_eq!(report["model"], "face-ibug68");
    assert_eq!(report["landmarks"], 68);
    // Measured 0.11 px (initial 3.4 px).
    let e = report["landmark_error_px"].as_f64().unwrap();
    assert!(e < 0.5, "landmark error {e} px");
    let det = read_points(&out.join("detected_landmarks.txt"));
    assert_eq!(det.len(), 68);
    let (a, b) = MEDIAPIPE_TO_IBUG68[27];
    assert!((det[27][0] - 0.5 * (truth[[a, 0]] + truth[[b, 0]])).abs() < 1e-3);
    assert_eq!(read_points(&out.join("landmarks.txt")).len(), 68);
    // A synthetic target of the 68 model: its landmarks are its surface points.
    let out2 = d.join("out2");
    let o = fit_face(&[
        "--model".as_ref(),
        dir.as_os_str(),
        "--size".as_ref(),
        "48".as_ref(),
        "--iters".as_ref(),
        "10".as_ref(),
        "--out".as_ref(),
        out2.as_os_str(),
    ]);
    ok(&o);
    assert_eq!(json(&out2.join("report.json"))["landmarks"], 68);
}

#[test]
fn bad_inputs_are_one_line_errors_and_write_nothing() {
    let d = tmpdir("errors");
    let (img, lm, _) = photo(&d, 40, 40, 0);
    std::fs::write(d.join("short.txt"), "1 2\n3 4\n").unwrap();
    std::fs::write(d.join("garbage.png"), b"not a png at all").unwrap();
    std::fs::write(d.join("notes.txt"), b"hello").unwrap();
    let bad_model = d.join("badmodel");
    std::fs::create_dir_all(&bad_model).unwrap();
    std::fs::write(bad_model.join("model.json"), b"{\"n_vertices\": 3,").unwrap();
    let m68 = d.join("m68-sigma");
    save_ibug68_model(&m68);
    std::fs::write(m68.join("faces.npy"), b"\x93NUMPY garbage").unwrap();
    let blank = d.join("blank.png");
    render_ops::io::write_png(&blank, &ndarray::Array3::<f64>::from_elem((64, 64, 3), 0.5))
        .unwrap();
    let s = |p: &Path| p.display().to_string();
    let cases: Vec<(Vec<String>, Vec<String>)> = vec![
        (
            vec![
                "--target".into(),
                s(&d.join("missing.png")),
                "--landmarks".into(),
                s(&lm),
            ],
            vec!["missing.png".into()],
        ),
        (
            vec![
                "--target".into(),
                s(&d.join("garbage.png")),
                "--landmarks".into(),
                s(&lm),
            ],
            vec!["garbage.png".into()],
        ),
        (
            vec![
                "--target".into(),
                s(&d.join("notes.txt")),
                "--landmarks".into(),
                s(&lm),
            ],
            vec!["notes.txt".into(), "image".into()],
        ),
        (
            vec![
                "--target".into(),
                s(&img),
                "--landmarks".into(),
                s(&d.join("short.txt")),
            ],
            vec!["short.txt".into(), "2 landmarks".into(), "468".into()],
        ),
        (
            vec![
                "--target".into(),
                s(&img),
                "--landmarks".into(),
                s(&d.join("nolm.txt")),
            ],
            vec!["nolm.txt".into()],
        ),
        (
            vec!["--model".into(), s(&bad_model)],
            vec!["model.json".into(), "badmodel".into()],
        ),
        (
            vec!["--model".into(), s(&d.join("nomodel"))],
            vec!["nomodel".into(), "model.json".into()],
        ),
        (vec!["--model".into(), s(&m68)], vec!["faces.npy".into()]),
        (
            vec![
                "--target".into(),
                s(&img),
                "--landmarks".into(),
                s(&lm),
                "--face".into(),
                "1".into(),
            ],
            vec!["--face 1".into(), "lm.txt".into()],
        ),
        (vec!["--face".into(), "2".into()], vec!["--face 2".into()]),
        (
            vec!["--target".into(), s(&blank)],
            vec!["blank.png".into(), "no face found".into()],
        ),
        (
            vec!["--texture-size".into(), "1".into()],
            vec!["--texture-size 1".into(), "2 to 8192".into()],
        ),
    ];
    for (i, (args, needles)) in cases.iter().enumerate() {
        let out = d.join(format!("out{i}"));
        let o = Command::new(env!("CARGO_BIN_EXE_tapestry"))
            .arg("fit-face")
            .args(args)
            .args(["--iters", "2", "--size", "32", "--out"])
            .arg(&out)
            .output()
            .unwrap();
        assert!(!o.status.success(), "{args:?} succeeded");
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        for n in needles {
            assert!(err.contains(n.as_str()), "{args:?}: {err} lacks {n}");
        }
        assert!(!out.exists(), "{args:?}: {} was created", out.display());
    }
}

/// The main job with no landmark file: the photo's face and its 468 landmarks are detected
/// (`models::detect`), then fitted. On a 256 x 256 render of the shipped model the detector
/// lands 4-7 px from the model's own landmarks (`models/tests/detect.rs`), which bounds what the
/// fit can reach; asserted: fitted landmarks within 8 px of the true ones on average, the
/// detected ones likewise, and the photometric RMSE of the fit.
#[test]
fn a_photo_without_landmarks_is_detected_and_fitted() {
    let d = tmpdir("detect");
    let (img, _, truth) = photo(&d, 256, 256, 3);
    let out = d.join("out");
    ok(&fit_face(&[
        "--model".as_ref(),
        "mediapipe".as_ref(),
        "--target".as_ref(),
        img.as_os_str(),
        "--iters".as_ref(),
        "60".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]));
    let mean_err = |p: &[[f64; 2]]| {
        assert_eq!(p.len(), truth.nrows());
        p.iter()
            .zip(truth.rows())
            .map(|(a, b)| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt())
            .sum::<f64>()
            / p.len() as f64
    };
    let detected = mean_err(&read_points(&out.join("detected_landmarks.txt")));
    let fitted = mean_err(&read_points(&out.join("landmarks.txt")));
    let report = json(&out.join("report.json"));
    let rmse = report["photometric_rmse"].as_f64().unwrap();
    eprintln!("detected {detected:.2} px, fitted {fitted:.2} px from the truth, RMSE {rmse:.4}");
    assert!(
        detected < 8.0,
        "detected landmarks {detected} px from the truth"
    );
    assert!(fitted < 8.0, "fitted landmarks {fitted} px from the truth");
    assert!(rmse < 0.08, "photometric RMSE {rmse}");
}

/// A real portrait with the default model (ICT-FaceKit): `grace_hopper.jpg` (public domain,
/// 512 x 600, `models/tests/data/landmarker/README.md`), its face detected, fitted at 256 px
/// (100 iterations) and textured at the photo's own resolution. The goals: landmarks
/// within 2 px at 256 px of the detected ones, photometric RMSE inside the face mask under 0.05.
#[test]
fn a_real_portrait_is_fitted_with_the_ict_model() {
    let d = tmpdir("grace");
    let photo = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("models/tests/data/landmarker/grace_hopper.jpg");
    let out = d.join("out");
    // The default texture (512 texels; the other tests ask for 128).
    let o = Command::new(env!("CARGO_BIN_EXE_tapestry"))
        .arg("fit-face")
        .arg("--target")
        .arg(&photo)
        .args(["--iters", "100", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    ok(&o);
    let report = json(&out.join("report.json"));
    assert_eq!(report["model"], "ict-facekit-face");
    let lm_256 = report["landmark_error_px"].as_f64().unwrap() * 256.0 / 600.0;
    let rmse = report["texture"]["photometric_rmse_after"]
        .as_f64()
        .unwrap();
    let rmse_model = report["photometric_rmse"].as_f64().unwrap();
    eprintln!("landmarks {lm_256:.2} px at 256 px; RMSE in the mask {rmse_model:.4} (model fit), {rmse:.4} (textured)");
    // Measured (2026-11-29, dev profile): 0.87 px, RMSE 0.226 (model fit) -> 0.029.
    assert!(lm_256 < 2.0, "landmark error {lm_256} px at 256 px");
    assert!(rmse < 0.05, "photometric RMSE in the mask {rmse}");
    std::fs::remove_dir_all(&d).ok();
}
