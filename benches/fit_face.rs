//! The whole `tapestry fit-face` command (process start, photo decode and resize, fit, every
//! output) on a 1024 x 1024 photo-like target with its 468 landmarks: a synthetic face of the
//! shipped model rendered at 1024 x 1024 over a textured background, saved as PNG and JPEG.
//! The issue's goal is under 5 s on 2 cores (release).
//!
//! ```sh
//! cargo bench --bench fit_face
//! ```

use std::path::{Path, PathBuf};
use std::process::Command;

use criterion::{criterion_group, criterion_main, Criterion};
use models::fit::{self, SynthOptions};

/// Writes `face.png`, `face.jpg` and `lm.txt` into `dir`.
fn photo(dir: &Path) {
    let m = models::face::default_face::<f64>();
    let mut o = SynthOptions::new(1024, 1024, 5);
    o.supersample = 1;
    let s = fit::synthesize(&m, &o).unwrap();
    // Photo-like: a smooth coloured background with fine texture where the face is not.
    let r = fit::FaceRenderer::new(&m, fit::RenderOptions::new(1024, 1024)).unwrap();
    let (face, _) = r.render(&s.truth).unwrap();
    let mut img = s.target.image.clone();
    for ((r, c, k), v) in img.indexed_iter_mut() {
        let (x, y) = (c as f64 / 1024.0, r as f64 / 1024.0);
        let t = ((c * 7 + r * 13 + k * 5) % 17) as f64 / 17.0;
        let bg = 0.25 + 0.3 * x * (k as f64 + 1.0) / 3.0 + 0.2 * y + 0.05 * t;
        let a = face[[r, c, 3]];
        *v = a * *v + (1.0 - a) * bg;
    }
    render_ops::io::write_png(dir.join("face.png"), &img).unwrap();
    let rgb = image::RgbImage::from_fn(1024, 1024, |x, y| {
        let p = |k: usize| (255.0 * img[[y as usize, x as usize, k]]).round() as u8;
        image::Rgb([p(0), p(1), p(2)])
    });
    rgb.save_with_format(dir.join("face.jpg"), image::ImageFormat::Jpeg)
        .unwrap();
    let lines: String = s
        .target
        .landmarks
        .rows()
        .into_iter()
        .map(|r| format!("{} {}\n", r[0], r[1]))
        .collect();
    std::fs::write(dir.join("lm.txt"), lines).unwrap();
}

fn bench(c: &mut Criterion) {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("fit_face_bench");
    std::fs::create_dir_all(&dir).unwrap();
    photo(&dir);
    let mut g = c.benchmark_group("fit_face_1024");
    g.sample_size(10);
    for name in ["face.png", "face.jpg"] {
        g.bench_function(name, |b| {
            b.iter(|| {
                let out = Command::new(env!("CARGO_BIN_EXE_tapestry"))
                    .args(["fit-face", "--target"])
                    .arg(dir.join(name))
                    .arg("--landmarks")
                    .arg(dir.join("lm.txt"))
                    .arg("--out")
                    .arg(dir.join("out"))
                    .output()
                    .unwrap();
                assert!(
                    out.status.success(),
                    "{}",
                    String::from_utf8_lossy(&out.stderr)
                );
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
