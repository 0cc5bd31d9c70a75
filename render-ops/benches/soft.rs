//! Forward and forward + backward speed of the soft rasterizers (SoftRas and DIB-R) on the
//! peers' spheres (`Mesh::icosphere(4)` = ico5k, `Mesh::icosphere(6)` = ico80k) under the
//! peers' camera, f32, per-vertex colours, RGBA output; the backward is that of
//! `sum((image - target)^2)` (the fused `Var::sum_squared_diff`, the target shared by the
//! frames as the stand-in reuses its target tensor) with respect to positions and colours. SoftRas for
//! sigma in {1e-3, 1e-4, 1e-5} (gamma 1e-4, threshold 1e-4), DIB-R at its default delta.
//! `*_composed`: the same renders through the composed stages (`soft::soft_fragments`,
//! `interpolate`, `soft::softras_aggregate`; for DIB-R the registry's composed path, the hard
//! fragment pipeline under `soft::dibr_alpha`), against which the fused
//! ops (chosen automatically for per-vertex colours) are compared in `docs/performance.md`.
//! `scripts/bench-soft-peers.sh` runs this bench beside the PyTorch SoftRas stand-in.
//!
//! ```text
//! cargo bench -p tapestry-render-ops --bench soft -- --warm-up-time 1 --measurement-time 3
//! ```

mod common;

use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::{Tape, Tensor};
use common::{frame_in, peer_scene, peers_view_proj, pool, PeerScene};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use render_ops::interpolate::interpolate;
use render_ops::methods::{render_fragments, MethodSettings};
use render_ops::scene;
use render_ops::soft::{
    dibr, soft_fragments, softras, softras_aggregate, Coverage, DibrSettings, SoftBlendSettings,
    SoftSettings, SoftStageSettings,
};
use render_ops::transform::to_clip;

#[derive(Clone, Copy)]
enum Method {
    SoftRas(f64),
    Dibr,
    /// The composed path on the same per-vertex colours: `soft::soft_fragments`,
    /// `interpolate`, `soft::softras_aggregate` (sigma).
    SoftRasComposed(f64),
    /// `methods::render_fragments` with `interpolate` as the shader: rasterize, interpolate,
    /// `blend_hard`, `soft::dibr_alpha`.
    DibrComposed,
}

/// Renders (and optionally back-propagates) one frame; returns a value so the work is kept.
fn run(sc: &PeerScene, size: usize, method: Method, target: Option<&Arc<Tensor<f32>>>) -> usize {
    let m = peers_view_proj();
    let tape = Tape::<f32>::new();
    let grad = target.is_some();
    let p = tape.var(sc.pos.clone(), grad);
    let c = tape.var(sc.col.clone(), grad);
    let clip = to_clip(p, &m);
    let img = match method {
        Method::SoftRas(sigma) => {
            let mut s = SoftSettings::new(size, size, 1.0, 100.0);
            s.sigma = sigma;
            s.gamma = 1e-4;
            softras(clip, c, sc.faces.clone(), &s).unwrap()
        }
        Method::Dibr => dibr(clip, c, sc.faces.clone(), &DibrSettings::new(size, size)).unwrap(),
        Method::SoftRasComposed(sigma) => {
            let st = SoftStageSettings::new(size, size, Coverage::Sigmoid { sigma });
            let sf = soft_fragments(clip, sc.faces.clone(), &st).unwrap();
            let mut bs = SoftBlendSettings::new(1.0, 100.0);
            bs.gamma = 1e-4;
            softras_aggregate(&sf, interpolate(c, &sf.raster).unwrap(), &bs).unwrap()
        }
        Method::DibrComposed => {
            let s = MethodSettings::new(scene::Method::Dibr, size, size);
            render_fragments(clip, sc.faces.clone(), &s, &mut |r| interpolate(c, r)).unwrap()
        }
    };
    if let Some(target) = target {
        let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
        let g = tape.backward(loss).unwrap();
        g.get(p).map(|t| t.len()).unwrap_or(0)
    } else {
        img.value().unwrap().len()
    }
}

fn bench_soft(c: &mut Criterion) {
    let mut g = c.benchmark_group("soft_f32");
    g.sample_size(10);
    let threads = 2;
    let pool = pool(threads);
    for subdiv in [4u32, 6] {
        let sc = peer_scene(subdiv);
        for size in [256usize, 512] {
            let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
            let mut methods = vec![
                ("softras_sigma1e-3", Method::SoftRas(1e-3)),
                ("softras_sigma1e-4", Method::SoftRas(1e-4)),
                ("softras_sigma1e-5", Method::SoftRas(1e-5)),
                ("dibr", Method::Dibr),
                ("softras_sigma1e-4_composed", Method::SoftRasComposed(1e-4)),
                ("dibr_composed", Method::DibrComposed),
            ];
            if subdiv == 6 && size == 512 {
                // sigma 1e-3 at 512 x 512: the cut-off radius is 25 px, i.e. ~2000 pixels per
                // face; at 80k faces that is seconds per frame (see the note in the README).
                methods.remove(0);
            }
            for (name, method) in methods {
                let id = format!("{}k_faces/{size}px/{threads}thr", sc.faces.len() / 1000);
                g.bench_function(BenchmarkId::new(format!("{name}/forward"), &id), |b| {
                    b.iter(|| frame_in(&pool, || run(&sc, size, method, None)))
                });
                g.bench_function(
                    BenchmarkId::new(format!("{name}/forward_backward"), &id),
                    |b| b.iter(|| frame_in(&pool, || run(&sc, size, method, Some(&target)))),
                );
            }
        }
    }
    g.finish();
}

criterion_group!(benches, bench_soft);
criterion_main!(benches);
