//! Where the `analytic` method's time goes, on `benches/raster.rs`'s `analytic_f32` scenes
//! (the peers' icosphere and camera, back-face culling, screen-space colours, `f32`, one
//! thread): the fragments' forward alone, the whole pipeline's forward (fragments,
//! interpolated colours, `blend_weighted`), forward + backward with gradients to the colours
//! only (the fragments' backward skipped), and with gradients to positions too. The
//! differences give the downstream stages' and the fragments' backward's shares.
//!
//! ```text
//! cargo build --release -p tapestry-render-ops --example prof_analytic
//! target/release/examples/prof_analytic SIZE ITERS [SUBDIV]
//! ```
//!
//! `SUBDIV` 4 (default) is the 5k-face sphere, 6 the 80k one. Prints the fragment count, the
//! covered pixels, checksums of the fragments' areas and barycentrics and of the position
//! gradient (equal checksums: the same results), and the best of `ITERS` times of each part.
//! `CULL=0` renders back faces too (every pixel then solves occlusion); `ONLY=fwd` loops over
//! the fragments' forward alone (for `perf record`).
#[path = "../benches/common/mod.rs"]
mod common;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use common::{driver_args, peer_scene, peers_view_proj, pool, PeerScene};
use render_ops::analytic::analytic_fragments;
use render_ops::blend::blend_weighted;
use render_ops::interpolate::interpolate;
use render_ops::raster::RasterSettings;
use render_ops::transform::to_clip;
use std::sync::Arc;
use std::time::Instant;

fn main() {
    let (size, iters, subdiv) = driver_args();
    let PeerScene { pos, col, faces } = peer_scene(subdiv);
    let m = peers_view_proj();
    let s = RasterSettings {
        // `CULL=0`: back faces too (every pixel solves occlusion).
        cull_backfaces: !std::env::var("CULL").is_ok_and(|v| v == "0"),
        perspective_correct: false,
        ..RasterSettings::new(size, size)
    };
    let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
    let pool = pool(1);
    let run = |gpos: bool, gcol: bool, stop: u8| -> f64 {
        let t0 = Instant::now();
        let tape = Tape::<f32>::new();
        let p = tape.var(pos.clone(), gpos);
        let cv = tape.var(col.clone(), gcol);
        let a = analytic_fragments(to_clip(p, &m), faces.clone(), &s).unwrap();
        if stop == 0 {
            return t0.elapsed().as_secs_f64();
        }
        let c = interpolate(cv, &a.raster).unwrap();
        let img = blend_weighted(c, a.weight, &a.raster.fragments, &[0.0; 3]).unwrap();
        if stop == 1 {
            img.value().unwrap();
            return t0.elapsed().as_secs_f64();
        }
        let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
        tape.backward(loss).unwrap();
        t0.elapsed().as_secs_f64()
    };
    if std::env::var("ONLY").is_ok_and(|v| v == "fwd") {
        pool.install(|| {
            let t: f64 = (0..iters).map(|_| run(false, false, 0)).sum();
            println!("fragments fwd mean {:.2} ms", t / iters as f64 * 1e3);
        });
        return;
    }
    pool.install(|| {
        let tape = Tape::<f32>::new();
        let p = tape.var(pos.clone(), false);
        let a = analytic_fragments(to_clip(p, &m), faces.clone(), &s).unwrap();
        let f = &a.raster.fragments;
        let n = f.offsets[f.offsets.len() - 1];
        let covered = f.offsets.windows(2).filter(|w| w[1] > w[0]).count();
        println!(
            "fragments {n}, covered pixels {covered}, max per pixel {}",
            f.k
        );
        // Checksums: equal ones mean the same fragments and gradients to the bit (almost).
        let w = a.weight.value().unwrap();
        let b = a.raster.bary.value().unwrap();
        let cs: f64 = w
            .iter()
            .enumerate()
            .map(|(i, &x)| x as f64 * (1 + i % 7) as f64)
            .sum();
        let cb: f64 = b
            .iter()
            .enumerate()
            .map(|(i, &x)| x as f64 * (1 + i % 5) as f64)
            .sum();
        let tape2 = Tape::<f32>::new();
        let p2 = tape2.var(pos.clone(), true);
        let a2 = analytic_fragments(to_clip(p2, &m), faces.clone(), &s).unwrap();
        let c2 = interpolate(tape2.var(col.clone(), false), &a2.raster).unwrap();
        let img = blend_weighted(c2, a2.weight, &a2.raster.fragments, &[0.0; 3]).unwrap();
        let loss = img.sum_squared_diff(tape2.var_shared(target.clone(), false));
        let g = tape2.backward(loss).unwrap();
        let gp = g.get(p2).unwrap();
        let cg: f64 = gp
            .iter()
            .enumerate()
            .map(|(i, &x)| x as f64 * (1 + i % 3) as f64)
            .sum();
        println!("checksums {cs:.9e} {cb:.9e} {cg:.9e}");
        for (name, gp, gc, stop) in [
            ("fragments fwd", false, false, 0u8),
            ("pipeline fwd", false, false, 1),
            ("fwd+bwd colours only", false, true, 2),
            ("fwd+bwd all", true, true, 2),
        ] {
            let mut best = f64::INFINITY;
            for _ in 0..iters {
                best = best.min(run(gp, gc, stop));
            }
            println!("{name}: {:.2} ms", best * 1e3);
        }
    });
}
