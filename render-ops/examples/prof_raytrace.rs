//! Times the `raytrace` forward of a scene file (`Scene::render_image`, `f64`, the pool of
//! `RAYON_NUM_THREADS`) and prints a checksum of the image (equal checksums: the same bits),
//! for A/B runs of the forward and for `perf record`:
//!
//! ```text
//! cargo build --release -p tapestry-render-ops --example prof_raytrace
//! target/release/examples/prof_raytrace SCENE.json ITERS
//! ```

use std::time::Instant;

use render_ops::scene::Scene;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (Some(path), Some(iters)) = (args.get(1), args.get(2).and_then(|n| n.parse().ok())) else {
        eprintln!("usage: prof_raytrace SCENE.json ITERS");
        std::process::exit(2);
    };
    let scene = Scene::<f64>::load(path).unwrap_or_else(|e| {
        eprintln!("{path}: {e}");
        std::process::exit(1);
    });
    let mut best = f64::INFINITY;
    let mut sum = 0.0;
    for _ in 0..iters {
        let t = Instant::now();
        let img = scene.render_image().expect("render");
        best = best.min(t.elapsed().as_secs_f64() * 1e3);
        sum = img
            .iter()
            .enumerate()
            .map(|(i, x)| x * (1 + i % 7) as f64)
            .sum();
    }
    println!("forward best of {iters}: {best:.2} ms  checksum {sum:.17e}");
}
