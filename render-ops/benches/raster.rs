//! Forward (and forward + backward) speed of the hard rasterizer on icospheres.
//!
//! Scenes: unit icosphere (icosahedron subdivided 4 and 6 times: 5120 and 81920 faces) at distance
//! 3, fov_y 48.9 degrees, 256x256 and 512x512, f32, K = 1, on rayon pools of 1 and 2 threads,
//! without and with back-face culling.

use std::collections::HashMap;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use glam::{DMat4, DVec3, DVec4};
use render_ops::raster::{rasterize, rasterize_backward, RasterSettings};

/// Unit icosphere with outward counter-clockwise faces (20 * 4^n faces).
fn icosphere(n: usize) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<DVec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| DVec3::from_array(*p).normalize())
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..n {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut nf = Vec::with_capacity(f.len() * 4);
        for &[a, b, c] in &f {
            let mut m = |x: u32, y: u32| {
                *mid.entry((x.min(y), x.max(y))).or_insert_with(|| {
                    v.push((v[x as usize] + v[y as usize]).normalize());
                    (v.len() - 1) as u32
                })
            };
            let (ab, bc, ca) = (m(a, b), m(b, c), m(c, a));
            nf.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    for face in &mut f {
        let [a, b, c] = face.map(|i| v[i as usize]);
        if (b - a).cross(c - a).dot(a) < 0.0 {
            face.swap(1, 2);
        }
    }
    (v, f)
}

fn scene(subdiv: usize) -> (Vec<[f32; 4]>, Vec<[u32; 3]>) {
    let (v, f) = icosphere(subdiv);
    let view = DMat4::look_at_rh(DVec3::new(0.0, 0.0, 3.0), DVec3::ZERO, DVec3::Y);
    let proj = DMat4::perspective_rh_gl(48.9f64.to_radians(), 1.0, 0.1, 100.0);
    let m = proj * view;
    let clip = v
        .iter()
        .map(|p| (m * DVec4::new(p.x, p.y, p.z, 1.0)).as_vec4().to_array())
        .collect();
    (clip, f)
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("raster_forward_f32");
    for subdiv in [4, 6] {
        let (clip, faces) = scene(subdiv);
        for size in [256, 512] {
            // Default settings (both layers of the sphere rasterized), then back-face culling as
            // in DEODR's peer setting.
            for (cull, threads) in [(false, 1), (false, 2), (true, 2)] {
                let s = RasterSettings {
                    cull_backfaces: cull,
                    ..RasterSettings::new(size, size)
                };
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let id = format!(
                    "{}k_faces/{size}px/{threads}thr{}",
                    faces.len() / 1000,
                    if cull { "/cull" } else { "" }
                );
                g.bench_function(BenchmarkId::from_parameter(id), |b| {
                    b.iter(|| pool.install(|| rasterize(&clip, &faces, &s).unwrap()))
                });
            }
        }
    }
    g.finish();
    let mut g = c.benchmark_group("raster_backward_f32");
    for subdiv in [4, 6] {
        let (clip, faces) = scene(subdiv);
        let s = RasterSettings::new(512, 512);
        let fr = rasterize(&clip, &faces, &s).unwrap();
        let gb = vec![[1.0f32, -0.5, 0.25]; fr.len()];
        let gd = vec![1.0f32; fr.len()];
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let id = format!("{}k_faces/512px/2thr", faces.len() / 1000);
        g.bench_function(BenchmarkId::from_parameter(id), |b| {
            b.iter(|| {
                pool.install(|| {
                    rasterize_backward(&clip, &faces, &fr, &gb, Some(&gd), Some(&gd), &s).unwrap()
                })
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
