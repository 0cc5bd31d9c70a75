//! Face detection and the 468 landmarks on a photo (issue 27's goal: under 100 ms per photo
//! on 2 cores): `cargo bench -p tapestry-models --bench detect`.
//!
//! `detect_landmarks` is the whole pipeline (letterbox, detector, decoding, crop, face
//! mesh); `detect` the detector stage alone; `new` building both models from the embedded
//! ONNX files (once per process in practice).

use criterion::{criterion_group, criterion_main, Criterion};
use models::detect::Landmarker;
use ndarray::Array3;

fn photo() -> Array3<f64> {
    render_ops::io::read_image(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/landmarker/grace_hopper.jpg"
    ))
    .expect("the fixture photo")
}

fn bench(c: &mut Criterion) {
    let img = photo();
    let lm = Landmarker::new().expect("the embedded models build");
    let mut g = c.benchmark_group("grace_hopper_512x600");
    g.sample_size(20);
    g.bench_function("detect_landmarks", |b| {
        b.iter(|| lm.detect_landmarks(img.view()).expect("one face"))
    });
    g.bench_function("detect", |b| {
        b.iter(|| lm.detect(img.view()).expect("runs"))
    });
    g.sample_size(10);
    g.bench_function("new", |b| b.iter(|| Landmarker::new().expect("builds")));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
