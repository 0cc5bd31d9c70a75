//! Fixtures of the unit tests: `models/tests/data/landmarker/` (see its README).

use std::path::PathBuf;

use ndarray::{Array3, ArrayD};
use serde_json::Value;

use super::crop::Roi;
use super::decode::RawDetection;

/// A fixture file.
pub fn path(name: &str) -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/landmarker"
    ))
    .join(name)
}

/// A float32 `.npy` fixture, flattened.
pub fn npy(name: &str) -> Vec<f32> {
    let a: ArrayD<f32> = render_ops::io::read_npy(path(name)).unwrap();
    a.iter().copied().collect()
}

/// An 8-bit RGB PNG fixture (a model input stored as its 8-bit samples), flattened.
pub fn png_u8(name: &str) -> Vec<u8> {
    let a: Array3<f64> = render_ops::io::read_png(path(name)).unwrap();
    assert_eq!(a.shape()[2], 3);
    a.iter().map(|&v| (v * 255.0).round() as u8).collect()
}

/// A photo as `[H, W, 3]` (gray replicated).
pub fn photo(name: &str) -> Array3<f64> {
    let file = if name == "camera" {
        "camera.png"
    } else {
        "grace_hopper.jpg"
    };
    let a: Array3<f64> = render_ops::io::read_image(path(file)).unwrap();
    let (h, w, c) = a.dim();
    Array3::from_shape_fn((h, w, 3), |(r, col, k)| {
        a[[r, col, if c == 1 { 0 } else { k }]]
    })
}

/// `NAME_expected.json`.
pub fn expected(name: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path(&format!("{name}_expected.json"))).unwrap())
        .unwrap()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

/// The reference pipeline's detection (normalised image coordinates).
pub fn reference_detection(name: &str) -> RawDetection {
    let r = &expected(name)["reference_pipeline"];
    let b = &r["detection_relative_bbox_xmin_ymin_w_h"];
    let (x, y, w, h) = (f(&b[0]), f(&b[1]), f(&b[2]), f(&b[3]));
    let k = &r["detection_relative_keypoints_xy"];
    RawDetection {
        score: f(&r["detection_score"]),
        bbox: [x, y, x + w, y + h],
        keypoints: std::array::from_fn(|i| [f(&k[i][0]), f(&k[i][1])]),
    }
}

/// The reference pipeline's crop, in pixels.
pub fn reference_roi(name: &str) -> Roi {
    let r = &expected(name)["reference_pipeline"]["roi_pixels"];
    Roi {
        cx: f(&r["x_center"]),
        cy: f(&r["y_center"]),
        size: f(&r["size"]),
        rotation: f(&r["rotation_rad"]),
    }
}

/// The kit's synthetic model input `[n, n, 3]` with values in `[lo, hi]` (formula of
/// `tools/make_fixtures.py`, `pattern()`): float64, then float32.
pub fn pattern(n: usize, lo: f64, hi: f64) -> Vec<f32> {
    use std::f64::consts::PI;
    let nf = n as f64;
    let mut out = Vec::with_capacity(n * n * 3);
    for yi in 0..n {
        for xi in 0..n {
            let (x, y) = (xi as f64, yi as f64);
            let c0 = 0.5 + 0.5 * (2.0 * PI * x / nf * 3.0).sin() * (2.0 * PI * y / nf * 2.0).cos();
            let c1 = ((x + 2.0 * y) % 32.0) / 31.0;
            let even = ((xi / 16) + (yi / 16)) % 2 == 0;
            let c2 = if even { 0.8 } else { 0.2 } * (y / (nf - 1.0));
            for c in [c0, c1, c2] {
                out.push((lo + (hi - lo) * c) as f32);
            }
        }
    }
    out
}

/// Elementwise `|got - want| <= 1e-3 + 1e-5 |want|` (the kit's model tolerance); returns the
/// largest absolute difference.
pub fn assert_close_model(got: &[f32], want: &[f32], what: &str) -> f32 {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let mut worst = 0f32;
    for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
        let d = (g - w).abs();
        assert!(d <= 1e-3 + 1e-5 * w.abs(), "{what}[{i}]: {g} vs {w}");
        worst = worst.max(d);
    }
    worst
}

/// Samples that differ from the fixture: (count, largest difference in grey levels).
pub fn sample_diff(got: &[u8], want: &[u8]) -> (usize, u8) {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .filter(|(a, b)| a != b)
        .fold((0, 0), |(n, m), (a, b)| (n + 1, m.max(a.abs_diff(*b))))
}

/// Checks 8-bit samples against the reference pipeline's. From the lossless `camera.png`
/// at most 0.1% of the samples may differ, by one grey level (a float sum landing on .5);
/// `grace_hopper.jpg` was decoded by libjpeg (PIL) for the fixture and by zune-jpeg here,
/// whose pixels differ by a few grey levels (IDCT, chroma upsampling), so there up to a
/// quarter of the samples may differ, by at most 4.
pub fn assert_samples_match(name: &str, got: &[u8], want: &[u8]) {
    let (n, worst) = sample_diff(got, want);
    let (frac, max) = if name == "camera" {
        (0.001, 1)
    } else {
        (0.25, 4)
    };
    assert!(
        n as f64 <= frac * want.len() as f64 && worst <= max,
        "{name}: {n} of {} samples differ, by up to {worst}",
        want.len()
    );
}
