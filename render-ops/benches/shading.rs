//! Shading and texturing speed, f32:
//! - Phong (one directional, one point and one ambient light) and SH lighting on 512 x 512
//!   fragments, forward + backward (gradients for every input): the entry points `shade` and
//!   `sh_shade` (the composed models inside `Tape::fused`, entries `fused`) against the same
//!   composed code run op by op (`composed`);
//! - the toon/rim custom shader of `examples/custom_shader.rs` on the 256 x 256 fragments of a
//!   full-frame render, forward + backward, eager against fused (the shader stage alone: the
//!   rasterization is the same either way);
//! - texture sampling throughput (samples per second), bilinear and trilinear, forward and
//!   forward + backward, 512 x 512 samples from a 512 x 512 RGB texture.
//!
//! `cargo bench -p tapestry-render-ops --bench shading`.

use std::sync::Arc;
use std::time::Duration;

use autodiff::rng::Rng;
use autodiff::{Tape, Tensor, Var};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use render_ops::shade::{
    sh_shade, sh_shade_composed, shade, shade_composed, AmbientLight, DirectionalLight, Lights,
    Material, PointLight, Reflectance, Surface,
};
use render_ops::texture::{sample, Filter, Sampler, Wrap};

const N: usize = 512 * 512;

fn config() -> Criterion {
    Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
}

struct Data {
    pos: Arc<Tensor<f32>>,
    nrm: Arc<Tensor<f32>>,
    alb: Arc<Tensor<f32>>,
    sh: Tensor<f32>,
    grad: Tensor<f32>,
}

fn data() -> Data {
    let mut rng = Rng::new(1);
    Data {
        pos: Arc::new(rng.uniform_tensor(&[N, 3], -1.0, 1.0)),
        nrm: Arc::new(rng.normal_tensor(&[N, 3])),
        alb: Arc::new(rng.uniform_tensor(&[N, 3], 0.2, 1.0)),
        sh: rng.normal_tensor(&[9, 3]),
        grad: rng.normal_tensor(&[N, 3]),
    }
}

/// Which evaluation of a lighting model to run.
#[derive(Clone, Copy, PartialEq)]
enum Path {
    /// The entry point: the composed model inside `Tape::fused`.
    Fused,
    /// The composed tape code, op by op.
    Composed,
}

impl Path {
    fn name(self) -> &'static str {
        match self {
            Path::Fused => "fused",
            Path::Composed => "composed",
        }
    }
}

fn phong<'t>(tape: &'t Tape<f32>, d: &Data, path: Path) -> (Var<'t, f32>, Vec<Var<'t, f32>>) {
    let pos = tape.var_shared(d.pos.clone(), true);
    let nrm = tape.var_shared(d.nrm.clone(), true);
    let alb = tape.var_shared(d.alb.clone(), true);
    let dir = tape.leaf(ndarray::arr1(&[0.2f32, -0.3, -1.0]).into_dyn());
    let eye = tape.leaf(ndarray::arr1(&[0.0f32, 0.0, 4.0]).into_dyn());
    let lights = Lights::new()
        .with_ambient(AmbientLight::constant(tape, [0.1, 0.1, 0.1]))
        .with_directional(DirectionalLight {
            direction: dir,
            color: tape.constant(ndarray::arr1(&[1.0f32, 0.9, 0.8]).into_dyn()),
        })
        .with_point(PointLight::constant(tape, [2.0, 2.0, 3.0], [0.5, 0.5, 0.5]));
    let m = Material::constant(tape, Reflectance::Phong, [0.3, 0.3, 0.3], 32.0);
    let surf = Surface {
        position: pos,
        normal: nrm,
        albedo: alb,
        visibility: None,
    };
    let y = match path {
        Path::Fused => shade(&surf, &m, &lights, eye),
        Path::Composed => shade_composed(&surf, &m, &lights, eye),
    };
    (y, vec![pos, nrm, alb, dir, eye])
}

fn bench_shading(c: &mut Criterion) {
    let d = data();
    let mut g = c.benchmark_group("phong_512x512_fwd_bwd");
    g.throughput(Throughput::Elements(N as u64));
    for path in [Path::Fused, Path::Composed] {
        g.bench_function(path.name(), |b| {
            b.iter(|| {
                let tape = Tape::new();
                let (y, vars) = phong(&tape, &d, path);
                let gr = tape.vjp(y, d.grad.clone()).unwrap();
                vars.iter()
                    .filter_map(|&v| gr.get(v))
                    .map(|g| g.len())
                    .sum::<usize>()
            })
        });
    }
    g.finish();
    let mut g = c.benchmark_group("sh_512x512_fwd_bwd");
    g.throughput(Throughput::Elements(N as u64));
    for path in [Path::Fused, Path::Composed] {
        g.bench_function(path.name(), |b| {
            b.iter(|| {
                let tape = Tape::new();
                let (n, a) = (
                    tape.var_shared(d.nrm.clone(), true),
                    tape.var_shared(d.alb.clone(), true),
                );
                let s = tape.leaf(d.sh.clone());
                let y = match path {
                    Path::Fused => sh_shade(n, a, s),
                    Path::Composed => sh_shade_composed(n, a, s),
                };
                let gr = tape.vjp(y, d.grad.clone()).unwrap();
                gr.get(s).map(|g| g.len()).unwrap_or(0) + gr.get(n).map(|g| g.len()).unwrap_or(0)
            })
        });
    }
    g.finish();
}

/// The toon/rim shader of `examples/custom_shader.rs` (same ops, same constants) on
/// per-fragment normals and view directions.
fn toon_rim<'t>(
    normal: Var<'t, f32>,
    view_dir: Var<'t, f32>,
    threshold: Var<'t, f32>,
    rim: Var<'t, f32>,
) -> Var<'t, f32> {
    let t = normal.tape();
    let vec3 = |a: [f32; 3]| t.constant(ndarray::arr1(&a).into_dyn());
    let to_light = vec3([-0.4, 0.6, 0.7]).normalize(1e-12);
    let ndl = (normal * to_light).sum_axes(&[-1], true);
    let step = ((ndl - threshold) * (1.0 / 0.08)).sigmoid();
    let albedo = vec3([0.9, 0.45, 0.3]);
    let diffuse = albedo * (step * 0.75 + 0.2);
    let ndv = (normal * view_dir).sum_axes(&[-1], true);
    let fresnel = (-ndv + 1.0).relu().powf(5.0) * 0.96 + 0.04;
    diffuse + fresnel * rim * vec3([0.3, 0.6, 1.0])
}

fn bench_custom_shader(c: &mut Criterion) {
    const F: usize = 256 * 256;
    let mut rng = Rng::new(2);
    let unit = |t: Tensor<f32>| {
        let mut t = t;
        for mut row in t.rows_mut() {
            let l = row.dot(&row).sqrt().max(1e-6);
            row.mapv_inplace(|v| v / l);
        }
        Arc::new(t)
    };
    let nrm = unit(rng.normal_tensor(&[F, 3]));
    let view = unit(rng.normal_tensor(&[F, 3]));
    let grad: Tensor<f32> = rng.normal_tensor(&[F, 3]);
    let mut g = c.benchmark_group("toon_rim_256x256_fwd_bwd");
    g.throughput(Throughput::Elements(F as u64));
    for fused in [false, true] {
        g.bench_function(if fused { "fused" } else { "eager" }, |b| {
            b.iter(|| {
                let tape = Tape::new();
                let n = tape.var_shared(nrm.clone(), true);
                let v = tape.var_shared(view.clone(), true);
                let th = tape.leaf(ndarray::arr1(&[0.3f32]).into_dyn());
                let rim = tape.leaf(ndarray::arr1(&[0.8f32]).into_dyn());
                let y = if fused {
                    tape.fused(|| toon_rim(n, v, th, rim))
                } else {
                    toon_rim(n, v, th, rim)
                };
                let gr = tape.vjp(y, grad.clone()).unwrap();
                gr.get(n).map(|g| g.len()).unwrap_or(0) + gr.get(th).map(|g| g.len()).unwrap_or(0)
            })
        });
    }
    g.finish();
}

fn bench_texture(c: &mut Criterion) {
    let mut rng = Rng::new(2);
    let tex: Arc<Tensor<f32>> = Arc::new(rng.uniform_tensor(&[512, 512, 3], 0.0, 1.0));
    let uv: Arc<Tensor<f32>> = Arc::new(rng.uniform_tensor(&[N, 2], -0.5, 1.5));
    // Footprints of 0.5 to 8 texels per pixel: mip levels 0 to 3.
    let da: Arc<Tensor<f32>> = Arc::new(Tensor::from_shape_fn(ndarray::IxDyn(&[N, 4]), |i| {
        let rho = 2f32.powf((i[0] % 97) as f32 / 96.0 * 4.0 - 1.0) / 512.0;
        if i[1] % 2 == 0 {
            rho
        } else {
            0.3 * rho
        }
    }));
    let grad: Tensor<f32> = rng.normal_tensor(&[N, 3]);
    let mut g = c.benchmark_group("texture_512x512_samples");
    g.throughput(Throughput::Elements(N as u64));
    for filter in [Filter::Bilinear, Filter::Trilinear] {
        let s = Sampler::new(filter, Wrap::Repeat);
        g.bench_with_input(
            BenchmarkId::new("forward", format!("{filter:?}")),
            &s,
            |b, &s| {
                b.iter(|| {
                    let tape = Tape::new();
                    let (t, u, dd) = (
                        tape.var_shared(tex.clone(), false),
                        tape.var_shared(uv.clone(), false),
                        tape.var_shared(da.clone(), false),
                    );
                    let y = sample(t, u, Some(dd), s);
                    y.value().unwrap()[[0, 0]]
                })
            },
        );
        g.bench_with_input(
            BenchmarkId::new("forward_backward", format!("{filter:?}")),
            &s,
            |b, &s| {
                b.iter(|| {
                    let tape = Tape::new();
                    let (t, u, dd) = (
                        tape.var_shared(tex.clone(), true),
                        tape.var_shared(uv.clone(), true),
                        tape.var_shared(da.clone(), true),
                    );
                    let y = sample(t, u, Some(dd), s);
                    let gr = tape.vjp(y, grad.clone()).unwrap();
                    gr.get(t).map(|g| g.len()).unwrap_or(0)
                        + gr.get(u).map(|g| g.len()).unwrap_or(0)
                })
            },
        );
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = config();
    targets = bench_shading, bench_custom_shader, bench_texture
}
criterion_main!(benches);
