//! Per-vertex colours through the fused ops of `render_ops::approx` against the composed path
//! of `render_ops::boundary` (rasterize + interpolate + blend_hard + the boundary op, which any
//! shader can feed; for `tf_mesh`: rasterize_extrapolated + interpolate on the hard and band
//! fragments + blend_band), forward + backward of `sum (I - 0.25)^2` over RGBA to positions and
//! colours, f32, on the peers' ico5k sphere at 256 x 256 (back-face culling), 1 and 2 threads.
//! `Scene::render` keeps the fused ops for unlit, untextured scenes; this bench measures what
//! the composed path costs there.
//!
//! 2026-11-28, shared 2-core machine (noisy), medians, fused / composed:
//!
//! | method | 1 thread | 2 threads |
//! |---|---|---|
//! | opendr | 24.0 / 16.9 ms | 12.5 / 11.5 ms |
//! | nmr | 65.0 / 58.2 ms | 47.5 / 58.6 ms |
//! | deodr | 5.4 / 8.6 ms | 5.2 / 9.1 ms |
//!
//! The composed `opendr` computes only the boundary term (the interior goes through the
//! rasterizer's barycentrics); composed `deodr` costs 1.6-1.75x the fused op and `nmr` up to
//! 1.23x, so the pipeline keeps the fused ops for per-vertex colours.
//!
//! ```text
//! cargo bench -p tapestry-render-ops --bench boundary -- --warm-up-time 1 --measurement-time 3
//! ```

mod common;

use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use common::{frame_in, peer_scene, peers_view_proj, pool, PeerScene};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use render_ops::approx::{self, ApproxSettings};
use render_ops::blend::blend_hard;
use render_ops::boundary::{self, BoundarySettings};
use render_ops::error::RenderError;
use render_ops::interpolate::interpolate;
use render_ops::rasterize::rasterize;
use render_ops::transform::to_clip;

fn bench_fused_vs_composed(c: &mut Criterion) {
    let mut g = c.benchmark_group("boundary_vs_fused_f32");
    g.sample_size(20);
    let m = peers_view_proj();
    let size = 256;
    let PeerScene { pos, col, faces } = peer_scene(4);
    let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
    let mut s = ApproxSettings::new(size, size);
    s.cull_backfaces = true;
    s.background = vec![0.0; 3];
    let rs = s.raster();
    for threads in [1, 2] {
        let pool = pool(threads);
        for method in ["tf_mesh", "opendr", "nmr", "deodr"] {
            for composed in [false, true] {
                let run = || {
                    let tape = Tape::<f32>::new();
                    let p = tape.var(pos.clone(), true);
                    let cv = tape.var(col.clone(), true);
                    let clip = to_clip(p, &m);
                    let img = if composed && method == "tf_mesh" {
                        let r = approx::tf_mesh::rasterize_extrapolated(clip, faces.clone(), &rs)?;
                        let (col, band) = (interpolate(cv, &r.raster)?, interpolate(cv, &r.band)?);
                        approx::tf_mesh::blend_band(col, band, &r, &[0.0; 3])?
                    } else if composed {
                        let r = rasterize(clip, faces.clone(), &rs)?;
                        let shaded = blend_hard(interpolate(cv, &r)?, &r.fragments, &[0.0; 3])?;
                        match method {
                            "opendr" => boundary::opendr_antialias(shaded, &r, clip)?,
                            "nmr" => boundary::nmr_antialias(shaded, &r, clip)?,
                            _ => boundary::deodr_antialias(
                                shaded,
                                &r,
                                clip,
                                &BoundarySettings::default(),
                            )?,
                        }
                    } else {
                        match method {
                            "tf_mesh" => approx::tf_mesh(clip, cv, faces.clone(), &s)?,
                            "opendr" => approx::opendr(clip, cv, faces.clone(), &s)?,
                            "nmr" => approx::nmr(clip, cv, faces.clone(), &s)?,
                            _ => approx::deodr(clip, cv, faces.clone(), &s)?,
                        }
                    };
                    let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
                    let gr = tape.backward(loss)?;
                    Ok::<_, RenderError>(gr.get(p).map(|t| t.len()))
                };
                let id = format!(
                    "{method}/{}/5k_faces/{size}px/{threads}thr",
                    if composed { "composed" } else { "fused" }
                );
                g.bench_function(BenchmarkId::new("forward_backward", id), |b| {
                    b.iter(|| frame_in(&pool, || run().unwrap()))
                });
            }
        }
    }
    g.finish();
}

criterion_group!(benches, bench_fused_vs_composed);
criterion_main!(benches);
