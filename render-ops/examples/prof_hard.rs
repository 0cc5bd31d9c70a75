//! Profiling driver for the hard f32 forward pipeline of `benches/raster.rs`'s
//! `render_hard_f32/forward` (positions -> clip -> `render_attributes`: rasterize, interpolate
//! colours, hard blend, in one pass when no gradient is asked for; back-face culling, one
//! thread), on the peers' icosphere and camera:
//!
//! ```text
//! cargo build --release -p tapestry-render-ops --example prof_hard
//! valgrind --tool=callgrind target/release/examples/prof_hard SIZE ITERS [SUBDIV]
//! ```
//!
//! `SUBDIV` 4 (default) is the 5k-face sphere. `THREADS=N` sets the pool size (default 1);
//! `HOT=0` turns the frame's `ActiveWait` off.
//! `GRAD=1` adds the backward of
//! `sum((image - 0.25)^2)` to positions and colours (`render_hard_f32/forward_backward`), and
//! the checksum then sums the gradients. `METHOD=deodr` renders with `render_ops::approx::deodr`
//! instead (DEODR's settings, as `benches/raster.rs`'s `deodr_f32`). Prints ms per iteration and a checksum of the
//! images (equal checksums: equal images up to summation order). Subtract a run with
//! `ITERS = 0` (scene setup) from the instruction counts; the checksum itself costs about
//! 10 instructions per image value.
#[path = "../benches/common/mod.rs"]
mod common;

use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use common::{driver_args, peer_scene, peers_view_proj, pool, PeerScene};
use render_ops::blend::blend_hard;
use render_ops::interpolate::interpolate;
use render_ops::raster::RasterSettings;
use render_ops::rasterize::render_attributes;
use render_ops::transform::to_clip;

fn main() {
    let (size, iters, subdiv) = driver_args();
    let m = peers_view_proj();
    let PeerScene { pos, col, faces } = peer_scene(subdiv);
    let s = RasterSettings {
        cull_backfaces: true,
        // The pipeline (vertex colours, hard blend) needs no barycentric derivatives;
        // `DERIVS=1` computes them anyway.
        barycentric_derivatives: std::env::var("DERIVS").is_ok_and(|v| v == "1"),
        ..RasterSettings::new(size, size)
    };
    let grad = std::env::var("GRAD").is_ok_and(|v| v == "1");
    let deodr = std::env::var("METHOD").is_ok_and(|v| v == "deodr");
    let mut approx = render_ops::approx::ApproxSettings::new(size, size);
    approx.cull_backfaces = true;
    approx.perspective_correct = false;
    approx.background = vec![0.0; 3];
    // Shared, not copied into each tape (as DEODR's bench reuses its target array).
    let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
    let pool = pool(std::env::var("THREADS").map_or(1, |t| t.parse().unwrap()));
    let mut acc = 0.0f64;
    let t0 = std::time::Instant::now();
    // `ONCE=1`: one `install` around the whole loop (as an application's loop runs inside
    // its pool), instead of one per iteration (as criterion's `b.iter(|| pool.install(..))`).
    let once = std::env::var("ONCE").is_ok_and(|v| v == "1");
    // The pool's other workers poll for work during each frame (`ActiveWait`, as the benches'
    // `frame_in`); `HOT=0` lets rayon park them between parallel regions.
    let hot = !std::env::var("HOT").is_ok_and(|v| v == "0");
    // `SPLIT=1`: rasterize + interpolate + blend_hard as three ops also for the forward
    // (by default `render_attributes`, which renders in one pass when no gradient is asked for).
    let split = std::env::var("SPLIT").is_ok_and(|v| v == "1");
    let nosum = std::env::var("NOSUM").is_ok_and(|v| v == "1");
    let mut frame = || {
        let _hot = hot.then(autodiff::ActiveWait::new);
        let tape = Tape::<f32>::new();
        let p = tape.var(pos.clone(), grad);
        let cv = tape.var(col.clone(), grad);
        let img = if deodr {
            render_ops::approx::deodr(to_clip(p, &m), cv, faces.clone(), &approx).unwrap()
        } else if split {
            let r = render_ops::rasterize::rasterize(to_clip(p, &m), faces.clone(), &s).unwrap();
            blend_hard(interpolate(cv, &r).unwrap(), &r.fragments, &[0.0; 3]).unwrap()
        } else {
            render_attributes(to_clip(p, &m), cv, faces.clone(), &s, &[0.0; 3]).unwrap()
        };
        if grad {
            let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
            let g = tape.backward(loss).unwrap();
            for v in [p, cv] {
                acc += g.get(v).unwrap().iter().map(|&x| x as f64).sum::<f64>();
            }
        } else {
            let im = img.value().unwrap();
            // `NOSUM=1`: no checksum of the images (it costs about as much as a 256^2 frame).
            if !nosum {
                acc += im.iter().map(|&x| x as f64).sum::<f64>();
            }
        }
    };
    if once {
        pool.install(|| (0..iters).for_each(|_| frame()));
    } else {
        (0..iters).for_each(|_| pool.install(&mut frame));
    }
    eprintln!(
        "{:.3} ms/iter checksum {acc:.6}",
        t0.elapsed().as_secs_f64() * 1e3 / iters as f64
    );
}
