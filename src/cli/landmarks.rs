//! `tapestry landmarks`: face detection and the 468 MediaPipe face-mesh landmarks of a photo
//! (`models::detect`), written as a landmark file (`x y` per line, pixels, centres at +0.5:
//! what `fit-face --landmarks` reads) and drawn over the photo.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use models::detect::{self, DetectError, FaceLandmarks};
use ndarray::Array3;
use render_ops::io::{read_image, write_png};
use serde_json::json;

use super::CliError;

/// Arguments of `landmarks`.
#[derive(Debug, Clone)]
pub struct Args {
    /// The photo (PNG, JPEG or .npy `[H, W, C]`).
    pub photo: PathBuf,
    /// Landmark file to write.
    pub out: Option<PathBuf>,
    /// Overlay PNG to write.
    pub overlay: Option<PathBuf>,
    /// Which face (0 = largest box) the landmark file and overlay points are of.
    pub face: usize,
    /// Print JSON instead of the summary.
    pub json: bool,
}

/// `[H, W, 3]` RGB of a gray, RGB or RGBA image (gray replicated, alpha dropped).
fn to_rgb(img: &Array3<f64>) -> Array3<f64> {
    let (h, w, c) = img.dim();
    Array3::from_shape_fn((h, w, 3), |(r, col, k)| {
        img[[r, col, if c < 3 { 0 } else { k }]]
    })
}

/// The landmark file: a comment line, then one `x y` line per landmark.
fn landmark_text(photo: &Path, index: usize, f: &FaceLandmarks) -> String {
    let mut s = format!(
        "# {} MediaPipe face-mesh landmarks of {} (face {index}, score {:.4}, presence {:.4}): x y in pixels, pixel centres at +0.5\n",
        f.points.nrows(),
        photo.display(),
        f.detection.score,
        f.presence
    );
    for p in f.points.rows() {
        let _ = writeln!(s, "{:.4} {:.4}", p[0], p[1]);
    }
    s
}

/// Sets the pixels of a filled disc of radius `r` around `(x, y)` (pixel centres at +0.5).
fn dot(img: &mut Array3<f64>, x: f64, y: f64, r: f64, color: [f64; 3]) {
    let (h, w, _) = img.dim();
    let (r0, r1) = ((y - r).floor().max(0.0), (y + r).ceil().min(h as f64));
    let (c0, c1) = ((x - r).floor().max(0.0), (x + r).ceil().min(w as f64));
    if !(r0 < r1 && c0 < c1) {
        return;
    }
    for row in r0 as usize..r1 as usize {
        for col in c0 as usize..c1 as usize {
            let (dx, dy) = (col as f64 + 0.5 - x, row as f64 + 0.5 - y);
            if dx * dx + dy * dy <= r * r {
                for (k, &v) in color.iter().enumerate() {
                    img[[row, col, k]] = v;
                }
            }
        }
    }
}

/// The outline of a box, `t` pixels thick.
fn rect(img: &mut Array3<f64>, b: [f64; 4], t: f64, color: [f64; 3]) {
    let steps = |a: f64, z: f64| {
        let n = ((z - a).abs().ceil() as usize).clamp(1, 100_000);
        (0..=n).map(move |i| a + (z - a) * i as f64 / n as f64)
    };
    for x in steps(b[0], b[2]) {
        dot(img, x, b[1], t, color);
        dot(img, x, b[3], t, color);
    }
    for y in steps(b[1], b[3]) {
        dot(img, b[0], y, t, color);
        dot(img, b[2], y, t, color);
    }
}

/// The photo with every face's box and the chosen face's landmarks.
fn overlay(rgb: &Array3<f64>, faces: &[FaceLandmarks], chosen: usize) -> Array3<f64> {
    let mut img = rgb.clone();
    let (h, w, _) = img.dim();
    let r = (w.min(h) as f64 / 300.0).max(1.0);
    let (green, orange) = ([0.1, 1.0, 0.2], [1.0, 0.55, 0.0]);
    for (i, f) in faces.iter().enumerate() {
        let c = if i == chosen { green } else { orange };
        rect(&mut img, f.detection.bbox, 0.6 * r, c);
    }
    for p in faces[chosen].points.rows() {
        dot(&mut img, p[0], p[1], r, green);
    }
    img
}

/// Runs `landmarks`.
pub fn run(a: &Args) -> Result<ExitCode, CliError> {
    let img = read_image::<f64>(&a.photo)?;
    let rgb = to_rgb(&img);
    let name = a.photo.display();
    let faces = detect::detect_landmarks(rgb.view()).map_err(|e| match e {
        DetectError::NoFace => CliError::Message(format!("{name}: no face found")),
        e => CliError::Message(format!("{name}: {e}")),
    })?;
    let chosen = faces.get(a.face).ok_or_else(|| {
        CliError::Message(format!(
            "--face {}: {name} has {} face(s) (numbered from 0, largest first)",
            a.face,
            faces.len()
        ))
    })?;
    if let Some(out) = &a.out {
        std::fs::write(out, landmark_text(&a.photo, a.face, chosen))
            .map_err(|e| CliError::Message(format!("{}: cannot write: {e}", out.display())))?;
    }
    if let Some(path) = &a.overlay {
        write_png(path, &overlay(&rgb, &faces, a.face))?;
    }
    if a.json {
        let list: Vec<_> = faces
            .iter()
            .map(|f| {
                json!({
                    "score": f.detection.score,
                    "presence": f.presence,
                    "bbox": f.detection.bbox,
                    "keypoints": f.detection.keypoints,
                    "landmarks": f.points.rows().into_iter().map(|p| [p[0], p[1], p[2]]).collect::<Vec<_>>(),
                })
            })
            .collect();
        let doc = json!({
            "photo": a.photo.display().to_string(),
            "width": rgb.shape()[1],
            "height": rgb.shape()[0],
            "face": a.face,
            "faces": list,
        });
        println!("{doc}");
    } else {
        println!("{} face(s) in {name}", faces.len());
        for (i, f) in faces.iter().enumerate() {
            let b = f.detection.bbox;
            println!(
                "face {i}: score {:.4}, presence {:.4}, box {:.1} {:.1} {:.1} {:.1}{}",
                f.detection.score,
                f.presence,
                b[0],
                b[1],
                b[2],
                b[3],
                if i == a.face && (a.out.is_some() || a.overlay.is_some()) {
                    " (written)"
                } else {
                    ""
                }
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
