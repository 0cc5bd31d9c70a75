//! The peers' benchmark scene, shared by the benches and the profiling drivers
//! (`examples/prof_*.rs` include this file): the unit icosphere (`Mesh::icosphere(4)` = ico5k,
//! `(6)` = ico80k, as `peers/scene_gen.py`) under the peers' camera (eye (0, 0, -3), up (0, -1,
//! 0), fov_y 48.888 degrees, near 1, far 100), per-vertex colours `0.5 + 0.5 p`.
// Each bench or driver uses part of this module.
#![allow(dead_code)]

use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tensor;
use render_ops::camera::Camera;
use render_ops::mesh::Mesh;

/// The peers' camera: view-projection matrix (row-major).
pub fn peers_view_proj() -> [[f64; 4]; 4] {
    let fov = 2.0 * (0.5f64 / 1.1).atan();
    Camera::perspective_look_at(
        [0.0, 0.0, -3.0],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        fov,
        1.0,
        1.0,
        100.0,
    )
    .expect("valid camera")
    .view_proj()
}

/// The sphere's world positions `[V, 3]`, colours `[V, 3]` and faces, `f32`.
pub struct PeerScene {
    pub pos: Tensor<f32>,
    pub col: Tensor<f32>,
    pub faces: Arc<Vec<[u32; 3]>>,
}

/// The unit icosphere with `subdiv` subdivisions.
pub fn peer_scene(subdiv: u32) -> PeerScene {
    let mesh = Mesh::<f32>::icosphere(subdiv, 1.0);
    let v = mesh.positions.len();
    let pos = ArrayD::from_shape_vec(
        IxDyn(&[v, 3]),
        mesh.positions.iter().flatten().copied().collect(),
    )
    .expect("v x 3");
    let col = pos.mapv(|x| 0.5 + 0.5 * x);
    PeerScene {
        pos,
        col,
        faces: Arc::new(mesh.faces),
    }
}

/// A rayon pool of `threads` threads.
pub fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

/// Runs one frame `f` in `pool` with the pool's other workers polling for work meanwhile
/// (`autodiff::ActiveWait`, as an application's render or fitting loop would): the wake-up
/// latency of parked workers is not what these benches measure.
pub fn frame_in<R: Send>(pool: &rayon::ThreadPool, f: impl FnOnce() -> R + Send) -> R {
    pool.install(|| {
        let _hot = autodiff::ActiveWait::new();
        f()
    })
}

/// A profiling driver's command line, `SIZE ITERS [SUBDIV]`: image side, iterations, and the
/// icosphere's subdivisions (default 4, the 5k-face sphere).
pub fn driver_args() -> (usize, usize, u32) {
    let args: Vec<String> = std::env::args().collect();
    let size = args[1].parse().expect("SIZE: an image side in pixels");
    let iters = args[2].parse().expect("ITERS: a count");
    let subdiv = args
        .get(3)
        .map_or(4, |s| s.parse().expect("SUBDIV: a count"));
    (size, iters, subdiv)
}
