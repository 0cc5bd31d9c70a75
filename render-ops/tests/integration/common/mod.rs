//! Shared helpers of the render-ops integration tests.
#![allow(dead_code)]

pub mod scenes;

use autodiff::Tensor;
use ndarray::{ArrayD, IxDyn};

/// A `[N, C]` tensor from its rows.
pub fn t2(rows: &[Vec<f64>]) -> Tensor<f64> {
    let c = rows[0].len();
    ArrayD::from_shape_vec(
        IxDyn(&[rows.len(), c]),
        rows.iter().flatten().copied().collect(),
    )
    .unwrap()
}

/// Clip row from NDC (x, y) and view depth w (OpenGL depth with near 1, far 10).
pub fn clip_row(x: f64, y: f64, w: f64) -> Vec<f64> {
    vec![x * w, y * w, (11.0 * w - 20.0) / 9.0, w]
}

/// Fixed pseudo-random weights in [-0.5, 0.5), so that a loss `sum(weights * image)` sees
/// every pixel.
pub fn weights(n: usize) -> Vec<f64> {
    let mut x = 0x9e37_79b9_7f4a_7c15u64;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        })
        .collect()
}

/// Clip coordinates `[V, 4]` of world points seen from `eye` (looking at (0.02, -0.03, 0), y
/// up, 42 degrees, near 1, far 50).
pub fn perspective_clip(points: &[[f64; 3]], eye: [f64; 3]) -> Tensor<f64> {
    let cam = render_ops::camera::Camera::perspective_look_at(
        eye,
        [0.02, -0.03, 0.0],
        [0.0, 1.0, 0.0],
        42f64.to_radians(),
        1.0,
        1.0,
        50.0,
    )
    .unwrap();
    let m = cam.view_proj();
    ArrayD::from_shape_fn(IxDyn(&[points.len(), 4]), |i| {
        let p = points[i[0]];
        (0..4)
            .map(|k| m[i[1]][k] * if k < 3 { p[k] } else { 1.0 })
            .sum()
    })
}

/// Smooth per-vertex colours `[V, 3]` from the positions.
pub fn smooth_colours(points: &[[f64; 3]]) -> Tensor<f64> {
    ArrayD::from_shape_fn(IxDyn(&[points.len(), 3]), |i| {
        let p = points[i[0]];
        0.5 + 0.4 * (3.0 * p[i[1]] + i[1] as f64).sin()
    })
}

/// The peer kit's scenes and reference arrays, vendored in `tests/data/peers/` (`scenes/`,
/// `reference/`; made by the kit's `make_reference.py`, see `reference/README.md`). A
/// different copy can be named with `$TAPESTRY_PEERS`; a missing folder fails the test.
pub fn peers() -> std::path::PathBuf {
    let dir = std::env::var_os("TAPESTRY_PEERS")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/peers")
        });
    assert!(
        dir.join("reference/hard_image.npy").is_file() && dir.join("scenes/ico5k.obj").is_file(),
        "peer reference data missing at {}",
        dir.display()
    );
    dir
}
