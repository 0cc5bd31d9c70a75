//! Face fitting (`models::fit`) and the `tapestry fit-face` command.
//!
//! What a synthetic fit can recover. The target has 468 exact 2D landmarks (one per vertex)
//! and a shaded image. Two things are not identifiable from one view with a known focal
//! length: (1) the size/distance ambiguity: scaling the posed face about the camera centre by
//! `s` (shape times `s`, translation times `s`) leaves every pixel unchanged, and the identity
//! basis holds near-uniform scalings (face width, height, depth), so only the priors pick the
//! size; (2) depth detail under a near-frontal, weak-perspective view (at 600 mm a 1 mm depth
//! change moves a landmark by well under a pixel at 80 px), which only the pose variation and
//! the shading constrain. So the bound on the shape error is relative: the fit must remove at
//! least half of the error of the mean shape (the prior's guess), and the error after removing
//! the best uniform scale must be below 1.5 mm. Measured at 80 x 80, 600 iterations, hard
//! method: seed 1 1.35 mm (mean shape 2.92, scale-aligned 1.34), seed 2 0.75 mm (4.08, 0.62);
//! 1500 iterations only reach 1.22 / 0.83 mm, the plateau of what one view determines.
//!
//! Where the rest of the error lies (seed 1, measured by rotating the error into the true
//! camera frame): 1.08 of the 1.35 mm is along the viewing axis (x 0.24, y 0.60), with a
//! 1 degree pitch error, the rotation/depth (bas-relief) trade-off: 1 mm of depth moves a
//! landmark by ~0.02 px here, below the 0.08 px landmark residual. The default priors
//! (`w_id = w_exp = 1e-4` against `w_lmk = 100`) amount to ~0.9 px landmark noise, right for
//! detected landmarks but a bias on these exact ones: with `1e-6` a landmark-only fit of seed
//! 1 reaches 0.44 mm (scale-aligned) after 2000 iterations, but seed 2 then drifts in size
//! (1.67 mm, 0.93 aligned), and `1e-5` / `3e-5` with the default schedule give no better
//! scale-aligned errors over seeds 0, 1, 2, 4 (1.14-1.37 mm). So the defaults stay, and 1 mm
//! is not a bound that one view at 80 px supports for every seed.

use std::path::PathBuf;
use std::process::Command;

use models::fit::{self, FaceParams, FitOptions, LandmarkFileError, SynthOptions};
use models::Morphable;
use render_ops::scene::Method;

fn model() -> Morphable<f64> {
    models::face::default_face()
}

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-fit-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

struct Outcome {
    params: FaceParams,
    landmark_px: f64,
    shape_mm: f64,
    shape_aligned_mm: f64,
    mean_shape_mm: f64,
    rmse: f64,
}

fn run_fit(size: usize, seed: u64, iters: usize, method: Method) -> Outcome {
    let m = model();
    let s = fit::synthesize(&m, &SynthOptions::new(size, size, seed)).unwrap();
    let mut o = FitOptions::new(size, size, iters);
    o.render.method = method;
    let r = fit::fit(&m, &s.target, None, &o, &mut |_| {}).unwrap();
    let renderer = fit::FaceRenderer::new(&m, o.render.clone()).unwrap();
    let (img, _) = renderer.render(&r.params).unwrap();
    let lm = renderer.landmarks_px(&r.params, &s.target.points).unwrap();
    let truth = s.truth.shape(&m).unwrap();
    let shape = r.params.shape(&m).unwrap();
    Outcome {
        landmark_px: fit::landmark_error_px(&lm, &s.target.landmarks),
        shape_mm: fit::shape_error_mm(&shape, &truth),
        shape_aligned_mm: fit::shape_error_scale_aligned_mm(&shape, &truth),
        mean_shape_mm: fit::shape_error_mm(&m.mean_shape(), &truth),
        rmse: fit::photometric_rmse(&img, &s.target.image),
        params: r.params,
    }
}

#[test]
fn synthetic_fit_converges_hard() {
    let t = std::time::Instant::now();
    for seed in [1, 2] {
        let o = run_fit(80, seed, 600, Method::Hard);
        eprintln!(
            "seed {seed}: landmarks {:.3} px, shape {:.3} mm (scale-aligned {:.3}, mean shape {:.3}), rmse {:.4}",
            o.landmark_px, o.shape_mm, o.shape_aligned_mm, o.mean_shape_mm, o.rmse
        );
        assert!(o.landmark_px < 1.0, "landmark error {} px", o.landmark_px);
        assert!(
            o.shape_mm < 0.5 * o.mean_shape_mm,
            "shape error {} mm vs mean shape {} mm",
            o.shape_mm,
            o.mean_shape_mm
        );
        assert!(
            o.shape_aligned_mm < 1.5,
            "scale-aligned shape error {} mm",
            o.shape_aligned_mm
        );
        // Noise 0.01 plus edge pixels: the fit explains the image.
        assert!(o.rmse < 0.05, "photometric RMSE {}", o.rmse);
    }
    eprintln!("two fits: {:.1} s", t.elapsed().as_secs_f64());
}

#[test]
fn synthetic_fit_converges_softras() {
    let o = run_fit(64, 3, 160, Method::SoftRas);
    eprintln!(
        "softras: landmarks {:.3} px, shape {:.3} mm (scale-aligned {:.3}, mean shape {:.3}), rmse {:.4}",
        o.landmark_px, o.shape_mm, o.shape_aligned_mm, o.mean_shape_mm, o.rmse
    );
    assert!(o.landmark_px < 1.0, "landmark error {} px", o.landmark_px);
    assert!(o.shape_mm < 0.5 * o.mean_shape_mm);
    // Blurred edges at 64 px pin the depth less than the hard fit: measured 1.71 mm aligned.
    assert!(
        o.shape_aligned_mm < 2.0,
        "scale-aligned shape error {} mm",
        o.shape_aligned_mm
    );
    assert!(o.rmse < 0.06, "photometric RMSE {}", o.rmse);
}

fn bits(p: &FaceParams) -> Vec<u64> {
    p.tensors()
        .iter()
        .flat_map(|t| t.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
        .collect()
}

#[test]
fn fit_is_deterministic_across_thread_counts() {
    for method in [Method::Hard, Method::SoftRas] {
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| run_fit(64, 5, 24, method).params)
        };
        let (a, b) = (run(1), run(2));
        assert_eq!(bits(&a), bits(&b), "{method}: 1 vs 2 threads differ");
        assert_ne!(a, FaceParams::neutral(&model()), "the fit moved nothing");
    }
}

#[test]
fn every_method_fits_a_few_steps_and_lowers_the_loss() {
    // Stage 2 only (landmarks and the photometric term, every parameter), 4 steps at 32 px:
    // each method's render and gradient run, and the loss falls; for both shipped models (ICT's
    // photometric term carries the photometric-weight channel through every method), the ray
    // tracer included (through its fragment stages).
    for m in [model(), models::ict::load_ict().unwrap()] {
        let s = fit::synthesize(&m, &SynthOptions::new(32, 32, 0)).unwrap();
        for method in Method::ALL.into_iter().chain(Method::RAY) {
            let mut o = FitOptions::new(32, 32, 4);
            o.render.method = method;
            (o.landmark_iters, o.full_iters) = (0, 4);
            let r = fit::fit(&m, &s.target, None, &o, &mut |_| {}).unwrap();
            let (first, last) = (&r.history[0], r.history.last().unwrap());
            let name = m.name();
            assert!(
                first.photo_term > 0.0,
                "{name} {method}: no photometric term"
            );
            assert!(
                last.loss < first.loss,
                "{name} {method}: loss {} -> {}",
                first.loss,
                last.loss
            );
        }
    }
}

#[test]
fn bad_targets_are_errors() {
    let m = model();
    let s = fit::synthesize(&m, &SynthOptions::new(32, 32, 0)).unwrap();
    // Image size that does not match the render size.
    let o = FitOptions::new(40, 32, 4);
    let e = fit::fit(&m, &s.target, None, &o, &mut |_| {}).unwrap_err();
    assert!(matches!(e, fit::FitError::Invalid(_)), "{e}");
    // Non-finite landmark.
    let mut t = s.target.clone();
    t.landmarks[[3, 1]] = f64::NAN;
    let e = fit::fit(&m, &t, None, &FitOptions::new(32, 32, 4), &mut |_| {}).unwrap_err();
    assert!(matches!(e, fit::FitError::Invalid(_)), "{e}");
}

#[test]
fn landmark_file_errors_are_typed() {
    let d = tmpdir("lm");
    let m = model();
    let write = |name: &str, text: &str| {
        let p = d.join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    // Good file with comments, blank lines and a comma separator.
    let p = write("ok.txt", "# x y\n1.5 2.5\n\n3,4\n");
    let a = fit::read_landmarks(&p).unwrap();
    assert_eq!(a.shape(), &[2, 2]);
    assert_eq!(a[[1, 0]], 3.0);
    // Wrong count for the model.
    let e = fit::correspondence(&m, a.nrows(), &p).unwrap_err();
    assert!(
        matches!(e, LandmarkFileError::Count { found: 2, .. }),
        "{e}"
    );
    assert!(
        e.to_string().contains("468") && e.to_string().contains("68"),
        "{e}"
    );
    let c = fit::correspondence(&m, 468, &p).unwrap();
    assert_eq!(
        c.points,
        (0..468)
            .map(models::LandmarkPoint::vertex)
            .collect::<Vec<_>>()
    );
    assert_eq!(c.rows, (0..468).map(|i| [i, i]).collect::<Vec<_>>());
    // A line with three fields, a non-number, a non-finite value.
    for (name, text, line) in [
        ("three.txt", "1 2\n1 2 3\n", 2),
        ("word.txt", "1 2\n3 4\nfoo 5\n", 3),
        ("nan.txt", "inf 2\n", 1),
        ("one.txt", "7\n", 1),
    ] {
        let e = fit::read_landmarks(write(name, text)).unwrap_err();
        match &e {
            LandmarkFileError::Parse { line: l, .. } => assert_eq!(*l, line, "{name}: {e}"),
            other => panic!("{name}: {other}"),
        }
        assert!(e.to_string().contains(name), "{e}");
    }
    let e = fit::read_landmarks(write("empty.txt", "\n# nothing\n")).unwrap_err();
    assert!(
        matches!(e, LandmarkFileError::Count { found: 0, .. }),
        "{e}"
    );
    let e = fit::read_landmarks(d.join("missing.txt")).unwrap_err();
    assert!(matches!(e, LandmarkFileError::Io { .. }), "{e}");
}

fn tapestry() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tapestry"))
}

#[test]
fn cli_fit_face_writes_its_files() {
    let d = tmpdir("cli");
    let out = tapestry()
        .args([
            "fit-face",
            "--iters",
            "8",
            "--size",
            "64",
            "--seed",
            "3",
            "--texture-size",
            "64",
            "--out",
        ])
        .arg(&d)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    for what in ["landmark error", "photometric RMSE", "shape error", "time"] {
        assert!(stdout.contains(what), "{stdout}");
    }
    for f in [
        "params.json",
        "fit.png",
        "overlay.png",
        "loss_curve.svg",
        "report.json",
    ] {
        assert!(d.join(f).is_file(), "{f} missing");
    }
    let png = render_ops::io::read_png::<f64>(d.join("fit.png")).unwrap();
    assert_eq!(png.shape(), &[64, 64, 3]);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("report.json")).unwrap()).unwrap();
    for key in [
        "landmark_error_px",
        "photometric_rmse",
        "seconds",
        "iterations",
        "method",
        "shape_error_mm",
    ] {
        assert!(
            report.get(key).is_some(),
            "report.json lacks {key}: {report}"
        );
    }
    // The default model is ICT-FaceKit's; the synthetic target's exact landmarks get
    // `EXACT_LANDMARK_ITERS` landmark steps, then the 4 of stage 2.
    assert_eq!(report["iterations"], fit::EXACT_LANDMARK_ITERS + 4);
    assert_eq!(report["method"], "hard");
    assert!(report["landmark_error_px"].as_f64().unwrap().is_finite());
    let params: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("params.json")).unwrap()).unwrap();
    assert_eq!(params["sh"].as_array().unwrap().len(), 9);
    let ict: Morphable<f64> = models::ict::load_ict().unwrap();
    assert_eq!(params["z_id"].as_array().unwrap().len(), ict.n_id());
    let svg = std::fs::read_to_string(d.join("loss_curve.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("<polyline"));
}

#[test]
fn cli_fits_a_photo_with_landmarks() {
    // A "photo": a synthetic target written as PNG with its 468 landmarks as text.
    let d = tmpdir("photo");
    let m = model();
    let s = fit::synthesize(&m, &SynthOptions::new(96, 96, 11)).unwrap();
    render_ops::io::write_png(d.join("face.png"), &s.target.image).unwrap();
    let lines: Vec<String> = s
        .target
        .landmarks
        .outer_iter()
        .map(|p| format!("{} {}", p[0], p[1]))
        .collect();
    std::fs::write(d.join("lm.txt"), lines.join("\n")).unwrap();
    let out = tapestry()
        .args(["fit-face", "--iters", "160", "--size", "96"])
        .arg("--target")
        .arg(d.join("face.png"))
        .arg("--landmarks")
        .arg(d.join("lm.txt"))
        .arg("--out")
        .arg(d.join("out"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("out/report.json")).unwrap()).unwrap();
    assert!(report.get("shape_error_mm").is_none());
    let e = report["landmark_error_px"].as_f64().unwrap();
    assert!(e < 1.0, "landmark error {e} px");
}

#[test]
fn cli_fit_face_errors_are_one_line() {
    let d = tmpdir("clierr");
    std::fs::write(d.join("bad.txt"), "1 2\nx y\n").unwrap();
    std::fs::write(d.join("short.txt"), "1 2\n3 4\n").unwrap();
    std::fs::write(d.join("img.png"), b"not a png").unwrap();
    let m = model();
    let s = fit::synthesize(&m, &SynthOptions::new(32, 32, 0)).unwrap();
    render_ops::io::write_png(d.join("face.png"), &s.target.image).unwrap();
    // A well-formed landmark file (one `x y` line per model vertex), so that the corrupt image
    // is what fails.
    let good: String = s
        .target
        .landmarks
        .rows()
        .into_iter()
        .map(|r| format!("{} {}\n", r[0], r[1]))
        .collect();
    assert_eq!(good.lines().count(), m.n_vertices());
    std::fs::write(d.join("good.txt"), good).unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "--target".into(),
                d.join("face.png").display().to_string(),
                "--landmarks".into(),
                d.join("bad.txt").display().to_string(),
            ],
            "bad.txt:2",
        ),
        (
            vec![
                "--target".into(),
                d.join("face.png").display().to_string(),
                "--landmarks".into(),
                d.join("short.txt").display().to_string(),
            ],
            "2 landmarks",
        ),
        (
            vec![
                "--target".into(),
                d.join("face.png").display().to_string(),
                "--landmarks".into(),
                d.join("missing.txt").display().to_string(),
            ],
            "missing.txt",
        ),
        (
            vec![
                "--target".into(),
                d.join("img.png").display().to_string(),
                "--landmarks".into(),
                d.join("good.txt").display().to_string(),
            ],
            "img.png",
        ),
        (vec!["--method".into(), "bogus".into()], "bogus"),
    ];
    for (args, needle) in cases {
        let out = tapestry()
            .arg("fit-face")
            .args(&args)
            .args(["--iters", "2", "--size", "32", "--out"])
            .arg(d.join("o"))
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?} succeeded");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {err}");
    }
    // clap: --target without --landmarks.
    let out = tapestry()
        .args(["fit-face", "--target", "x.png"])
        .output()
        .unwrap();
    assert!(!out.status.success());
}
