//! Face detection and the 468 landmarks end to end (`models::detect`): the kit's two photos
//! against MediaPipe 0.10.21's own landmarks, images without a face, bad images, and renders
//! of the shipped face model against their true landmark positions.

use std::path::PathBuf;
use std::sync::OnceLock;

use autodiff::rng::Rng;
use models::detect::{self, DetectError, FaceDetection, Landmarker, NUM_LANDMARKS};
use models::fit::{self, FaceParams, FaceRenderer, RenderOptions, SynthOptions};
use models::Morphable;
use ndarray::{Array2, Array3};
use serde_json::Value;

fn data(name: &str) -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/landmarker"
    ))
    .join(name)
}

fn landmarker() -> &'static Landmarker {
    static L: OnceLock<Landmarker> = OnceLock::new();
    L.get_or_init(|| Landmarker::new().unwrap())
}

/// A photo as `[H, W, 3]` (a gray one replicated, as MediaPipe was given it).
fn photo(file: &str) -> Array3<f64> {
    let a: Array3<f64> = render_ops::io::read_image(data(file)).unwrap();
    let (h, w, c) = a.dim();
    Array3::from_shape_fn((h, w, 3), |(r, col, k)| {
        a[[r, col, if c == 1 { 0 } else { k }]]
    })
}

fn expected(name: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(data(&format!("{name}_expected.json"))).unwrap())
        .unwrap()
}

/// Mean and largest 2D distance between `[N, >=2]` point sets.
fn distances(a: &Array2<f64>, b: &Array2<f64>) -> (f64, f64) {
    assert_eq!(a.nrows(), b.nrows());
    let d: Vec<f64> = (0..a.nrows())
        .map(|i| (a[[i, 0]] - b[[i, 0]]).hypot(a[[i, 1]] - b[[i, 1]]))
        .collect();
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    (mean, d.iter().fold(0.0, |m, &x| m.max(x)))
}

#[test]
fn photos_reproduce_mediapipe_landmarks() {
    for (name, file) in [
        ("camera", "camera.png"),
        ("grace_hopper", "grace_hopper.jpg"),
    ] {
        let img = photo(file);
        let (h, w) = (img.shape()[0] as f64, img.shape()[1] as f64);
        let faces = landmarker().detect_landmarks(img.view()).unwrap();
        assert_eq!(faces.len(), 1, "{name}");
        let f = &faces[0];
        assert_eq!(f.points.dim(), (NUM_LANDMARKS, 3));
        assert!(f.presence > 0.99, "{name}: presence {}", f.presence);
        // MediaPipe's file: X = x_norm W (integer = pixel centre); ours: centres at +0.5.
        let mp = fit::read_landmarks(data(&format!("{name}_landmarks_px.txt"))).unwrap() + 0.5;
        let (mean, max) = distances(&f.points, &mp);
        eprintln!(
            "{name}: mean {mean:.4} px, max {max:.4} px from MediaPipe; score {:.6}",
            f.detection.score
        );
        assert!(mean <= 0.25 && max <= 1.0, "{name}: mean {mean} max {max}");
        // z: MediaPipe's normalised z times the width.
        let e = expected(name);
        let xyz = &e["expected_landmarks"]["landmarks_norm_xyz"];
        let zerr = (0..NUM_LANDMARKS)
            .map(|i| (f.points[[i, 2]] - xyz[i][2].as_f64().unwrap() * w).abs())
            .sum::<f64>()
            / NUM_LANDMARKS as f64;
        assert!(zerr <= 0.25, "{name}: mean |z| error {zerr}");
        // The detection against MediaPipe's face detector on the same image.
        let md = &e["mediapipe_detection"];
        let s = md["score"].as_f64().unwrap();
        assert!(
            (f.detection.score - s).abs() < 2e-3,
            "{name}: score {} vs {s}",
            f.detection.score
        );
        let b = &md["relative_bbox_xmin_ymin_w_h"];
        let v = |i: usize| b[i].as_f64().unwrap();
        let want = [v(0) * w, v(1) * h, (v(0) + v(2)) * w, (v(1) + v(3)) * h];
        for k in 0..4 {
            assert!(
                (f.detection.bbox[k] - 0.5 - want[k]).abs() < 0.5,
                "{name}: box {:?} vs {want:?}",
                f.detection.bbox
            );
        }
        let kp = &md["relative_keypoints_xy"];
        for k in 0..6 {
            let (x, y) = (
                kp[k][0].as_f64().unwrap() * w + 0.5,
                kp[k][1].as_f64().unwrap() * h + 0.5,
            );
            let [gx, gy] = f.detection.keypoints[k];
            assert!((gx - x).hypot(gy - y) < 0.5, "{name}: keypoint {k}");
        }
        // The same through detect + landmarks, and through the cached convenience function.
        let dets = landmarker().detect(img.view()).unwrap();
        assert_eq!(dets.len(), 1);
        assert_eq!(dets[0], f.detection);
        let again = landmarker().landmarks(img.view(), &dets[0]).unwrap();
        assert_eq!(&again, f);
        assert_eq!(&detect::detect_landmarks(img.view()).unwrap()[0], f);
    }
}

#[test]
fn images_without_a_face_give_no_face() {
    let grey = Array3::from_elem((240, 320, 3), 0.5);
    assert!(landmarker().detect(grey.view()).unwrap().is_empty());
    assert!(matches!(
        landmarker().detect_landmarks(grey.view()),
        Err(DetectError::NoFace)
    ));
    assert!(matches!(
        detect::detect_landmarks(grey.view()),
        Err(DetectError::NoFace)
    ));
    // The kit's synthetic pattern (README "Fixtures"), as an image.
    let n = 192;
    let pattern = Array3::from_shape_fn((n, n, 3), |(y, x, c)| {
        let (xf, yf, nf) = (x as f64, y as f64, n as f64);
        match c {
            0 => {
                0.5 + 0.5
                    * (6.0 * std::f64::consts::PI * xf / nf).sin()
                    * (4.0 * std::f64::consts::PI * yf / nf).cos()
            }
            1 => ((x + 2 * y) % 32) as f64 / 31.0,
            _ => (if (x / 16 + y / 16) % 2 == 0 { 0.8 } else { 0.2 }) * yf / (nf - 1.0),
        }
    });
    assert!(matches!(
        landmarker().detect_landmarks(pattern.view()),
        Err(DetectError::NoFace)
    ));
    // Asked for landmarks anyway (a made-up detection), the crop of the pattern has no face.
    let det = FaceDetection {
        score: 0.9,
        bbox: [40.0, 40.0, 140.0, 140.0],
        keypoints: [
            [70.0, 70.0],
            [110.0, 70.0],
            [90.0, 90.0],
            [90.0, 115.0],
            [45.0, 80.0],
            [135.0, 80.0],
        ],
    };
    let f = landmarker().landmarks(pattern.view(), &det).unwrap();
    assert!(f.presence < 0.5, "presence {}", f.presence);
    assert!(f.points.iter().all(|v| v.is_finite()));
}

#[test]
fn bad_images_and_detections_are_refused() {
    let l = landmarker();
    let msg = |r: Result<Vec<FaceDetection>, DetectError>| match r {
        Err(DetectError::BadImage(m)) => m,
        other => panic!("{other:?}"),
    };
    assert!(msg(l.detect(Array3::zeros((64, 64, 1)).view())).contains("1 channel"));
    assert!(msg(l.detect(Array3::zeros((64, 64, 4)).view())).contains("4 channel"));
    assert!(msg(l.detect(Array3::zeros((8, 64, 3)).view())).contains("too small"));
    let mut nan = Array3::from_elem((64, 64, 3), 0.5);
    nan[[10, 20, 1]] = f64::NAN;
    assert!(msg(l.detect(nan.view())).contains("not finite"));
    assert!(matches!(
        l.detect_landmarks(nan.view()),
        Err(DetectError::BadImage(_))
    ));
    assert!(matches!(
        detect::detect_landmarks(nan.view()),
        Err(DetectError::BadImage(_))
    ));
    let img = Array3::from_elem((64, 64, 3), 0.5);
    let mut det = FaceDetection {
        score: 0.9,
        bbox: [10.0, 10.0, 50.0, 50.0],
        keypoints: [[20.0, 20.0]; 6],
    };
    assert!(matches!(
        l.landmarks(nan.view(), &det),
        Err(DetectError::BadImage(_))
    ));
    det.bbox[2] = f64::INFINITY;
    assert!(
        matches!(l.landmarks(img.view(), &det), Err(DetectError::BadImage(m)) if m.contains("non-finite"))
    );
    // Values outside [0, 1] are clamped like an 8-bit image, not refused.
    assert!(l
        .detect(Array3::from_elem((64, 64, 3), 3.0).view())
        .unwrap()
        .is_empty());
}

/// A 256 x 256 render of the shipped face model (`fit::synthesize`'s random identity,
/// expression, light and pose, here with yaw, pitch and roll within +-30 degrees) composited
/// over a textured background, and the true positions of all 468 vertices.
fn render(seed: u64) -> (Array3<f64>, Array2<f64>) {
    let model = models::face::default_face::<f64>();
    let mut o = SynthOptions::new(256, 256, seed);
    (o.max_yaw_deg, o.max_pitch_deg, o.max_roll_deg) = (30.0, 30.0, 30.0);
    let truth = fit::synthesize(&model, &o).unwrap().truth;
    render_over_background(&model, &truth, o.supersample, seed)
}

/// `model` posed by `truth`, rendered at 256 x 256 (`ss`^2 samples per pixel) over a
/// textured background, and the projections of the model's landmarks (pixels).
fn render_over_background(
    model: &Morphable<f64>,
    truth: &FaceParams,
    ss: usize,
    seed: u64,
) -> (Array3<f64>, Array2<f64>) {
    let renderer = FaceRenderer::new(model, RenderOptions::new(256 * ss, 256 * ss)).unwrap();
    let (big, _) = renderer.render(truth).unwrap();
    let px = renderer
        .landmarks_px(truth, &model.landmark_points())
        .unwrap();
    // Background: smooth colour gradients plus blocky value noise (a cluttered wall).
    let mut rng = Rng::new(seed ^ 0xB6);
    let cells: Vec<f64> = (0..16 * 16 * 3).map(|_| rng.uniform(0.0, 1.0)).collect();
    let mut img = Array3::zeros((256, 256, 3));
    for r in 0..256 {
        for c in 0..256 {
            for k in 0..3 {
                let mut s = 0.0;
                for i in 0..ss {
                    for j in 0..ss {
                        let (y, x) = (r * ss + i, c * ss + j);
                        let a = big[[y, x, 3]];
                        let g = 0.25 + 0.3 * ((x + 2 * k * y) as f64 / (256 * ss) as f64);
                        let bg = 0.6 * g + 0.4 * cells[((r / 16) * 16 + c / 16) * 3 + k];
                        s += big[[y, x, k]] + (1.0 - a) * bg;
                    }
                }
                img[[r, c, k]] = (s / (ss * ss) as f64 + 0.01 * rng.normal()).clamp(0.0, 1.0);
            }
        }
    }
    (img, px / ss as f64)
}

#[test]
fn renders_of_the_shipped_face_model_are_found() {
    let mut means = Vec::new();
    for seed in 0..6 {
        let (img, truth) = render(seed);
        let faces = match landmarker().detect_landmarks(img.view()) {
            Ok(f) => f,
            Err(e) => {
                let dets = landmarker().detect(img.view()).unwrap();
                panic!("seed {seed}: {e}; detections {dets:?}");
            }
        };
        let (mean, max) = distances(&faces[0].points, &truth);
        eprintln!(
            "seed {seed}: score {:.3}, presence {:.3}, landmark error mean {mean:.2} px, max {max:.2} px",
            faces[0].detection.score, faces[0].presence
        );
        means.push(mean);
    }
    let avg = means.iter().sum::<f64>() / means.len() as f64;
    eprintln!(
        "mean landmark error over {} renders: {avg:.2} px",
        means.len()
    );
    // Measured (2026-11-28): 5.22 px on average (4.0 to 7.0 px per render). The shipped model
    // is hand-designed, not a scan: its vertices are not exactly where MediaPipe's network
    // places the landmarks (face oval, lids), so this is a bound, not the 3 px aim.
    assert!(avg < 6.0, "{means:?}");
    assert!(means.iter().all(|&m| m < 9.0), "{means:?}");
}

/// Renders of the ICT-FaceKit model (`models/data/ict`) at random identity (N(0, 1)),
/// expression (each blendshape on with probability 0.25, weight in [0, 0.6]), SH light and
/// pose (yaw +-25, pitch +-15, roll +-15 degrees): the detector's 468 landmarks against the
/// projections of the model's MediaPipe correspondence points.
#[test]
fn renders_of_the_ict_model_are_found_at_its_correspondence_points() {
    let model: Morphable<f64> = models::ict::load_ict().unwrap();
    let mut means = Vec::new();
    for seed in 0..4 {
        let mut o = SynthOptions::new(256, 256, 100 + seed);
        (o.max_yaw_deg, o.max_pitch_deg, o.max_roll_deg) = (25.0, 15.0, 15.0);
        o.supersample = 1;
        let mut truth = fit::synthesize(&model, &o).unwrap().truth;
        let mut rng = Rng::new(seed);
        let sigma = model.sigma_exp();
        for (k, z) in truth.z_exp.iter_mut().enumerate() {
            let on = rng.next_f64() < 0.25;
            *z = if on {
                rng.uniform(0.0, 0.6) / sigma[k]
            } else {
                0.0
            };
        }
        let (img, lms) = render_over_background(&model, &truth, 2, seed);
        let faces = landmarker().detect_landmarks(img.view()).unwrap();
        assert_eq!(faces.len(), 1, "seed {seed}");
        let (mean, max) = distances(&faces[0].points, &lms);
        eprintln!(
            "ICT seed {seed}: score {:.3}, presence {:.3}, landmark error mean {mean:.2} px, max {max:.2} px",
            faces[0].detection.score, faces[0].presence
        );
        means.push(mean);
    }
    let avg = means.iter().sum::<f64>() / means.len() as f64;
    eprintln!(
        "ICT: mean landmark error over {} renders: {avg:.2} px",
        means.len()
    );
    // Measured (2026-11-28): 3.45 px on average (3.0 to 3.9 px per render; the shipped
    // model's own vertices: 5.22 px above). The correspondence was refined on frontal renders
    // of the mean and four identities (models/data/ict/README.md); these renders have other
    // identities, blendshapes, light and poses. Geometric alone it gave 4.40 px.
    assert!(avg < 4.5, "{means:?}");
    assert!(means.iter().all(|&m| m < 6.0), "{means:?}");
}
