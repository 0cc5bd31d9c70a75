//! Forward (and forward + backward) speed of the hard rasterizer on icospheres.
//!
//! Scenes: the peers' benchmark spheres (`Mesh::icosphere`, identical to `peers/scene_gen.py`'s
//! ico5k and ico80k: 5120 and 81920 faces) and a 1.3M-face sphere (8 subdivisions), seen with
//! the peers' camera (eye (0, 0, -3), up (0, -1, 0), fov_y 48.888 degrees, near 1, far 100),
//! f32, K = 1, on rayon pools of 1 and 2 threads, with the default settings and with DEODR's
//! (back-face culling, no barycentric derivatives). `scripts/bench-raster-peers.sh` runs this
//! bench and DEODR's forward side by side.
//! Groups `deodr_f32` and `nmr_f32` time those methods of `render_ops::approx`, forward and
//! forward + backward, on the 5k and 80k spheres at 256 and 512 pixels; group `analytic_f32`
//! the `analytic` method (through `render_vertex_colors`) on the same.
//!
//! ```text
//! cargo bench -p tapestry-render-ops --bench raster -- --warm-up-time 1 --measurement-time 3
//! ```

mod common;

use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use common::{frame_in, peer_scene, peers_view_proj, pool, PeerScene};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use render_ops::mesh::Mesh;
use render_ops::raster::{rasterize_backward, rasterize_fragments, RasterSettings};
use render_ops::rasterize::render_attributes;
use render_ops::transform::to_clip;

/// Clip-space positions and faces of the unit icosphere with `subdiv` subdivisions under the
/// peers' camera.
fn scene(subdiv: u32) -> (Vec<[f32; 4]>, Vec<[u32; 3]>) {
    let mesh = Mesh::<f64>::icosphere(subdiv, 1.0);
    let m = peers_view_proj();
    let clip = mesh
        .positions
        .iter()
        .map(|p| {
            let mut c = [0f32; 4];
            for (r, ci) in c.iter_mut().enumerate() {
                *ci = (m[r][0] * p[0] + m[r][1] * p[1] + m[r][2] * p[2] + m[r][3]) as f32;
            }
            c
        })
        .collect();
    (clip, mesh.faces)
}

fn bench_forward(c: &mut Criterion) {
    let mut g = c.benchmark_group("raster_forward_f32");
    g.sample_size(20);
    let cases: [(u32, &[usize]); 3] = [(4, &[256, 512]), (6, &[256, 512]), (8, &[1024])];
    for (subdiv, sizes) in cases {
        let (clip, faces) = scene(subdiv);
        for &size in sizes {
            // Default settings (both layers of the sphere rasterized, barycentric
            // derivatives), then DEODR's peer setting: back-face culling, and no derivatives
            // (DEODR computes none).
            for (cull, threads) in [(false, 1), (false, 2), (true, 1), (true, 2)] {
                let s = RasterSettings {
                    cull_backfaces: cull,
                    barycentric_derivatives: !cull,
                    ..RasterSettings::new(size, size)
                };
                let pool = pool(threads);
                let id = format!(
                    "{}k_faces/{size}px/{threads}thr{}",
                    faces.len() / 1000,
                    if cull { "/cull" } else { "" }
                );
                g.bench_function(BenchmarkId::from_parameter(id), |b| {
                    b.iter(|| frame_in(&pool, || rasterize_fragments(&clip, &faces, &s).unwrap()))
                });
            }
        }
    }
    g.finish();
}

fn bench_backward(c: &mut Criterion) {
    let mut g = c.benchmark_group("raster_backward_f32");
    for subdiv in [4, 6] {
        let (clip, faces) = scene(subdiv);
        let s = RasterSettings::new(512, 512);
        let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
        let gb = vec![[1.0f32, -0.5, 0.25]; fr.len()];
        let gd = vec![1.0f32; fr.len()];
        let pool = pool(2);
        let id = format!("{}k_faces/512px/2thr", faces.len() / 1000);
        g.bench_function(BenchmarkId::from_parameter(id), |b| {
            b.iter(|| {
                frame_in(&pool, || {
                    rasterize_backward(&clip, &faces, &fr, &gb, Some(&gd), Some(&gd), &s).unwrap()
                })
            })
        });
    }
    g.finish();
}

/// The whole hard pipeline as DEODR's `render` does it (world positions -> clip space ->
/// rasterize -> interpolate vertex colours -> composite over the background, through
/// `render_attributes`: in one pass without a fragment list for the forward), and the same
/// plus the backward of `sum((image - target)^2)` (the fused `Var::sum_squared_diff`) to
/// positions and colours (DEODR's `render_backward`), f32, with culling (DEODR's setting) and
/// without barycentric derivatives (nothing reads them) on 1 and 2 threads.
fn bench_pipeline(c: &mut Criterion) {
    let mut g = c.benchmark_group("render_hard_f32");
    g.sample_size(20);
    let m = peers_view_proj();
    for (subdiv, size) in [(4u32, 256usize), (4, 512), (6, 256), (6, 512)] {
        let PeerScene { pos, col, faces } = peer_scene(subdiv);
        // Shared, not copied into each tape (as DEODR's bench reuses its target array).
        let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
        // Vertex colours need no barycentric derivatives.
        let s = RasterSettings {
            cull_backfaces: true,
            barycentric_derivatives: false,
            ..RasterSettings::new(size, size)
        };
        for threads in [1, 2] {
            let pool = pool(threads);
            let id = format!("{}k_faces/{size}px/{threads}thr", faces.len() / 1000);
            let run = |grad: bool| {
                let tape = Tape::<f32>::new();
                let p = tape.var(pos.clone(), grad);
                let cv = tape.var(col.clone(), grad);
                // One pass without a fragment list when no gradient is asked for.
                let img = render_attributes(to_clip(p, &m), cv, faces.clone(), &s, &[0.0; 3])?;
                if grad {
                    let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
                    let gr = tape.backward(loss)?;
                    Ok::<_, render_ops::error::RenderError>(gr.get(p).map(|t| t.len()))
                } else {
                    Ok(Some(img.value()?.len()))
                }
            };
            g.bench_function(BenchmarkId::new("forward", &id), |b| {
                b.iter(|| frame_in(&pool, || run(false).unwrap()))
            });
            g.bench_function(BenchmarkId::new("forward_backward", &id), |b| {
                b.iter(|| frame_in(&pool, || run(true).unwrap()))
            });
        }
    }
    g.finish();
}

/// An approximate-gradient method of `render_ops::approx`.
type ApproxFn = for<'t> fn(
    autodiff::Var<'t, f32>,
    autodiff::Var<'t, f32>,
    Arc<Vec<[u32; 3]>>,
    &render_ops::approx::ApproxSettings,
) -> Result<autodiff::Var<'t, f32>, render_ops::error::RenderError>;

/// Method `method` of `render_ops::approx` with DEODR's settings (back-face culling,
/// screen-space colours, for `deodr` a 1 px ramp) on the same scenes, loss `sum (I - 0.25)^2`
/// over RGBA, gradients to positions and colours, as criterion group `group`.
fn bench_approx(c: &mut Criterion, group: &str, method: ApproxFn) {
    let mut g = c.benchmark_group(group);
    g.sample_size(20);
    let m = peers_view_proj();
    for (subdiv, size) in [(4u32, 256usize), (4, 512), (6, 256), (6, 512)] {
        let PeerScene { pos, col, faces } = peer_scene(subdiv);
        // Shared, not copied into each tape (as DEODR's bench reuses its target array).
        let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
        let mut s = render_ops::approx::ApproxSettings::new(size, size);
        s.cull_backfaces = true;
        s.perspective_correct = false;
        s.background = vec![0.0; 3];
        for threads in [1, 2] {
            let pool = pool(threads);
            let id = format!("{}k_faces/{size}px/{threads}thr", faces.len() / 1000);
            let run = |grad: bool| {
                let tape = Tape::<f32>::new();
                let p = tape.var(pos.clone(), grad);
                let cv = tape.var(col.clone(), grad);
                let img = method(to_clip(p, &m), cv, faces.clone(), &s)?;
                if grad {
                    let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
                    let gr = tape.backward(loss)?;
                    Ok::<_, render_ops::error::RenderError>(gr.get(p).map(|t| t.len()))
                } else {
                    Ok(Some(img.value()?.len()))
                }
            };
            g.bench_function(BenchmarkId::new("forward", &id), |b| {
                b.iter(|| frame_in(&pool, || run(false).unwrap()))
            });
            g.bench_function(BenchmarkId::new("forward_backward", &id), |b| {
                b.iter(|| frame_in(&pool, || run(true).unwrap()))
            });
        }
    }
    g.finish();
}

/// The `deodr` method: the Tapestry side of `scripts/bench-raster-peers.sh`'s DEODR comparison.
fn bench_deodr(c: &mut Criterion) {
    bench_approx(c, "deodr_f32", render_ops::approx::deodr::<f32>);
}

/// The `nmr` method (Kato et al. 2018), on DEODR's settings and scenes for comparison.
fn bench_nmr(c: &mut Criterion) {
    bench_approx(c, "nmr_f32", render_ops::approx::nmr::<f32>);
}

/// The `analytic` method (exact area sampling) through the registry's vertex-colour path, on
/// DEODR's settings and scenes, beside `deodr_f32` (the issue's target: within 3x).
fn analytic_vertex_colors<'t>(
    clip: autodiff::Var<'t, f32>,
    col: autodiff::Var<'t, f32>,
    faces: Arc<Vec<[u32; 3]>>,
    s: &render_ops::approx::ApproxSettings,
) -> Result<autodiff::Var<'t, f32>, render_ops::error::RenderError> {
    let mut ms = render_ops::MethodSettings::new(render_ops::Method::Analytic, s.width, s.height);
    ms.view.cull_backfaces = s.cull_backfaces;
    ms.view.perspective_correct = s.perspective_correct;
    ms.view.background = s.background.clone();
    render_ops::render_vertex_colors(clip, col, faces, &ms)
}

fn bench_analytic(c: &mut Criterion) {
    bench_approx(c, "analytic_f32", analytic_vertex_colors);
}

criterion_group!(
    benches,
    bench_forward,
    bench_backward,
    bench_pipeline,
    bench_deodr,
    bench_nmr,
    bench_analytic
);
criterion_main!(benches);
