//! Profiling driver for the `f32` SoftRas forward + backward of `benches/soft.rs`
//! (`softras_sigma*/forward_backward`: positions -> clip -> SoftRas (Liu et al. 2019) RGBA ->
//! `sum((image - 0.25)^2)` (fused, shared target) -> gradients of positions and colours), on the peers' icosphere and
//! camera:
//!
//! ```text
//! cargo build --release -p tapestry-render-ops --example prof_soft
//! valgrind --tool=callgrind target/release/examples/prof_soft SIZE ITERS SIGMA [SUBDIV] [THREADS]
//! ```
//!
//! `SUBDIV` 4 (default) is the 5k-face sphere, `THREADS` 1 by default (each frame runs under
//! `ActiveWait`, as the bench's `frame_in`; `HOT=0` turns that off). Prints ms per
//! iteration and checksums of the image and the gradients (equal checksums: equal results up
//! to summation order). Subtract a run with `ITERS = 0` (scene setup) from the instruction
//! counts.
#[path = "../benches/common/mod.rs"]
mod common;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use common::{frame_in, peer_scene, peers_view_proj, pool, PeerScene};
use render_ops::soft::{softras, SoftSettings};
use render_ops::transform::to_clip;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args[1].parse().unwrap();
    let iters: usize = args[2].parse().unwrap();
    let sigma: f64 = args[3].parse().unwrap();
    let subdiv: u32 = args.get(4).map_or(4, |s| s.parse().unwrap());
    let threads: usize = args.get(5).map_or(1, |s| s.parse().unwrap());
    let m = peers_view_proj();
    let PeerScene { pos, col, faces } = peer_scene(subdiv);
    let mut s = SoftSettings::new(size, size, 1.0, 100.0);
    s.sigma = sigma;
    s.gamma = 1e-4;
    let pool = pool(threads);
    let target = std::sync::Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
    let (mut ci, mut cp, mut cc) = (0.0f64, 0.0f64, 0.0f64);
    let t0 = std::time::Instant::now();
    let hot = !std::env::var("HOT").is_ok_and(|v| v == "0");
    for _ in 0..iters {
        let frame = || {
            let tape = Tape::<f32>::new();
            let p = tape.var(pos.clone(), true);
            let c = tape.var(col.clone(), true);
            let img = softras(to_clip(p, &m), c, faces.clone(), &s).unwrap();
            let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
            let g = tape.backward(loss).unwrap();
            ci += img.value().unwrap().iter().map(|&x| x as f64).sum::<f64>();
            cp += g.get(p).unwrap().iter().map(|&x| x as f64).sum::<f64>();
            cc += g.get(c).unwrap().iter().map(|&x| x as f64).sum::<f64>();
        };
        if hot {
            frame_in(&pool, frame);
        } else {
            pool.install(frame);
        }
    }
    eprintln!(
        "{:.3} ms/iter checksum image {ci:.9e} pos {cp:.9e} col {cc:.9e}",
        t0.elapsed().as_secs_f64() * 1e3 / iters as f64
    );
}
