//! Profiling driver for the `f32` SoftRas forward + backward of `benches/soft.rs`
//! (`softras_sigma*/forward_backward`: positions -> clip -> SoftRas (Liu et al. 2019) RGBA ->
//! `sum((image - 0.25)^2)` -> gradients of positions and colours), on the peers' icosphere and
//! camera:
//!
//! ```text
//! cargo build --release -p tapestry-render-ops --example prof_soft
//! valgrind --tool=callgrind target/release/examples/prof_soft SIZE ITERS SIGMA [SUBDIV] [THREADS]
//! ```
//!
//! `SUBDIV` 4 (default) is the 5k-face sphere, `THREADS` 1 by default. Prints ms per
//! iteration and checksums of the image and the gradients (equal checksums: equal results up
//! to summation order). Subtract a run with `ITERS = 0` (scene setup) from the instruction
//! counts.
use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use render_ops::camera::Camera;
use render_ops::mesh::Mesh;
use render_ops::soft::{softras, SoftSettings};
use render_ops::transform::to_clip;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args[1].parse().unwrap();
    let iters: usize = args[2].parse().unwrap();
    let sigma: f64 = args[3].parse().unwrap();
    let subdiv: u32 = args.get(4).map_or(4, |s| s.parse().unwrap());
    let threads: usize = args.get(5).map_or(1, |s| s.parse().unwrap());
    let fov = 2.0 * (0.5f64 / 1.1).atan();
    let m = Camera::perspective_look_at(
        [0.0, 0.0, -3.0],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        fov,
        1.0,
        1.0,
        100.0,
    )
    .unwrap()
    .view_proj();
    let mesh = Mesh::<f32>::icosphere(subdiv, 1.0);
    let v = mesh.positions.len();
    let pos = ArrayD::from_shape_vec(
        IxDyn(&[v, 3]),
        mesh.positions.iter().flatten().copied().collect(),
    )
    .unwrap();
    let col = pos.mapv(|x| 0.5 + 0.5 * x);
    let faces = Arc::new(mesh.faces.clone());
    let mut s = SoftSettings::new(size, size, 1.0, 100.0);
    s.sigma = sigma;
    s.gamma = 1e-4;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let (mut ci, mut cp, mut cc) = (0.0f64, 0.0f64, 0.0f64);
    let t0 = std::time::Instant::now();
    for _ in 0..iters {
        pool.install(|| {
            let tape = Tape::<f32>::new();
            let p = tape.var(pos.clone(), true);
            let c = tape.var(col.clone(), true);
            let img = softras(to_clip(p, &m), c, faces.clone(), &s).unwrap();
            let target = tape.constant(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
            let g = tape.backward((img - target).square().sum()).unwrap();
            ci += img.value().unwrap().iter().map(|&x| x as f64).sum::<f64>();
            cp += g.get(p).unwrap().iter().map(|&x| x as f64).sum::<f64>();
            cc += g.get(c).unwrap().iter().map(|&x| x as f64).sum::<f64>();
        });
    }
    eprintln!(
        "{:.3} ms/iter checksum image {ci:.9e} pos {cp:.9e} col {cc:.9e}",
        t0.elapsed().as_secs_f64() * 1e3 / iters as f64
    );
}
