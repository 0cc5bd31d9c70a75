//! Writes a photo-like 1024 x 1024 fitting target: a synthetic face of the shipped model over
//! a textured background, as `face.png` and `face.jpg`, with its 468 landmarks as `lm.txt`
//! (the input of `benches/fit_face.rs`, for timing `tapestry fit-face` by hand):
//!
//! ```sh
//! cargo run --example fit_face_photo -- DIR [SIZE] [SEED]
//! target/release/tapestry fit-face --target DIR/face.jpg --landmarks DIR/lm.txt --out DIR/out
//! ```

use std::path::PathBuf;

use models::fit::{self, SynthOptions};

fn main() {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(args.next().unwrap_or_else(|| "fit-face-photo".into()));
    let size: usize = args.next().map_or(1024, |s| s.parse().expect("SIZE"));
    let seed: u64 = args.next().map_or(5, |s| s.parse().expect("SEED"));
    std::fs::create_dir_all(&dir).expect("output folder");
    let m = models::face::default_face::<f64>();
    let mut o = SynthOptions::new(size, size, seed);
    o.supersample = 1;
    let s = fit::synthesize(&m, &o).expect("synthesize");
    let r = fit::FaceRenderer::new(&m, fit::RenderOptions::new(size, size)).expect("renderer");
    let (face, _) = r.render(&s.truth).expect("render");
    let n = size as f64;
    let mut img = s.target.image.clone();
    for ((r, c, k), v) in img.indexed_iter_mut() {
        let (x, y) = (c as f64 / n, r as f64 / n);
        let t = ((c * 7 + r * 13 + k * 5) % 17) as f64 / 17.0;
        let bg = 0.25 + 0.3 * x * (k as f64 + 1.0) / 3.0 + 0.2 * y + 0.05 * t;
        let a = face[[r, c, 3]];
        *v = a * *v + (1.0 - a) * bg;
    }
    render_ops::io::write_png(dir.join("face.png"), &img).expect("face.png");
    let rgb = image::RgbImage::from_fn(size as u32, size as u32, |x, y| {
        let p = |k: usize| (255.0 * img[[y as usize, x as usize, k]]).round() as u8;
        image::Rgb([p(0), p(1), p(2)])
    });
    rgb.save_with_format(dir.join("face.jpg"), image::ImageFormat::Jpeg)
        .expect("face.jpg");
    let lines: String = s
        .target
        .landmarks
        .rows()
        .into_iter()
        .map(|r| format!("{} {}\n", r[0], r[1]))
        .collect();
    std::fs::write(dir.join("lm.txt"), lines).expect("lm.txt");
    println!("wrote {}/{{face.png, face.jpg, lm.txt}}", dir.display());
}
