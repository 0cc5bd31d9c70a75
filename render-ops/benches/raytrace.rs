//! Speed of the `raytrace` method (f64, as `tapestry render` / `tapestry grad` run it), forward
//! and forward + backward (`L = sum (I - 0)^2` with respect to positions), on the two scenes of
//! the side-by-side with Mitsuba 3 (`scripts/bench-raytrace-peers.sh`): the peers' ico5k sphere
//! (5120 faces, unlit vertex colours) and the shadow scene (a ground quad and a quad occluder
//! under a 0.6 x 0.6 area light, Lambert), 256 x 256, 4 spp, on rayon pools of 1 and 2 threads;
//! and the fragment stages against the fused op: the shadow scene under a directional light
//! with vertex colours (`shadow_dir`, the fused op) and with a white texture
//! (`shadow_dir_textured`, `raytrace_fragments` + the scene's shader + `blend_traced`: the same
//! image).
//!
//! ```text
//! cargo bench -p tapestry-render-ops --bench raytrace -- --warm-up-time 1 --measurement-time 3
//! ```

mod common;

use std::path::Path;

use autodiff::ndarray::{ArrayD, IxDyn};
use common::{frame_in, pool};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use render_ops::pipeline::SceneInput;
use render_ops::Scene;

const ICO5K: &str = r#"{
  "mesh": "ico5k.obj",
  "camera": {"eye": [0, 0, -3], "at": [0, 0, 0], "up": [0, -1, 0],
             "fov_y_deg": 48.88790956083307, "near": 1, "far": 100},
  "image": {"width": 256, "height": 256, "background": [0, 0, 0]},
  "lights": [], "material": {"shading": "none"},
  "raster": {"method": "raytrace", "spp": 4, "seed": 1, "area_edge_samples": 4}
}"#;

/// The shadow scene under a directional light; `TEXTURE` is replaced by a texture or null.
const SHADOW_DIR: &str = r#"{
  "mesh": "shadow_uv.obj", "texture": TEXTURE,
  "camera": {"eye": [0, 3, 2.5], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 45,
             "near": 0.1, "far": 100},
  "image": {"width": 256, "height": 256, "background": [0, 0, 0]},
  "lights": [{"type": "directional", "direction": [0.2, -1, 0.1], "color": [1, 1, 1]}],
  "material": {"shading": "lambert"},
  "raster": {"method": "raytrace", "spp": 4, "seed": 1}
}"#;

const SHADOW_AREA: &str = r#"{
  "mesh": "shadow.obj",
  "camera": {"eye": [0, 3, 2.5], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 45,
             "near": 0.1, "far": 100},
  "image": {"width": 256, "height": 256, "background": [0, 0, 0]},
  "lights": [{"type": "area", "corner": [-0.9, 3, -0.3], "edge_u": [0.6, 0, 0],
              "edge_v": [0, 0, 0.6], "radiance": [3, 3, 3]}],
  "material": {"shading": "lambert"},
  "raster": {"method": "raytrace", "spp": 4, "seed": 1, "area_edge_samples": 4}
}"#;

/// The ground quad and the occluder of `scripts/compare_raytrace_mitsuba.py`.
const SHADOW_OBJ: &str = "v -2 0 -2 0.8 0.8 0.8\nv 2 0 -2 0.8 0.8 0.8\nv 2 0 2 0.8 0.8 0.8\n\
v -2 0 2 0.8 0.8 0.8\nv -0.45 0.8 -0.25 0.9 0.3 0.2\nv 0.15 0.8 -0.2 0.9 0.3 0.2\n\
v 0.1 0.8 0.25 0.9 0.3 0.2\nv -0.4 0.85 0.25 0.9 0.3 0.2\nf 1 3 2\nf 1 4 3\nf 5 7 6\nf 5 8 7\n";

fn bench_raytrace(c: &mut Criterion) {
    let peers = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/peers/scenes");
    let tmp = std::env::temp_dir().join(format!("tapestry-bench-raytrace-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("temp dir");
    std::fs::write(tmp.join("shadow.obj"), SHADOW_OBJ).expect("shadow.obj");
    // The same mesh with uvs, and a white texture (the textured image equals the untextured).
    let uv: String = (0..8)
        .map(|i| format!("vt {} {}\n", (i % 4) as f64 / 4.0, (i / 4) as f64))
        .collect();
    let faces = SHADOW_OBJ
        .lines()
        .filter(|l| l.starts_with('f'))
        .map(|l| {
            let ix: Vec<&str> = l.split_whitespace().skip(1).collect();
            format!(
                "f {}\n",
                ix.iter()
                    .map(|i| format!("{i}/{i}"))
                    .collect::<Vec<_>>()
                    .join(" ")
            )
        })
        .collect::<String>();
    let verts: String = SHADOW_OBJ
        .lines()
        .filter(|l| l.starts_with('v'))
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(tmp.join("shadow_uv.obj"), format!("{verts}{uv}{faces}")).expect("obj");
    let white = ndarray::Array3::<f64>::from_elem((2, 2, 3), 1.0);
    render_ops::io::write_png(tmp.join("white.png"), &white).expect("white.png");
    let scenes = [
        ("ico5k", Scene::<f64>::from_json(ICO5K, &peers, "ico5k")),
        (
            "shadow_area",
            Scene::<f64>::from_json(SHADOW_AREA, &tmp, "shadow_area"),
        ),
        (
            "shadow_dir",
            Scene::<f64>::from_json(&SHADOW_DIR.replace("TEXTURE", "null"), &tmp, "shadow_dir"),
        ),
        (
            "shadow_dir_textured",
            Scene::<f64>::from_json(
                &SHADOW_DIR.replace("TEXTURE", "\"white.png\""),
                &tmp,
                "shadow_dir_textured",
            ),
        ),
    ];
    let mut g = c.benchmark_group("raytrace_f64");
    g.sample_size(10);
    for (name, scene) in scenes {
        let scene = scene.expect("bench scene");
        let target = ArrayD::<f64>::zeros(IxDyn(&[256, 256, 4]));
        for threads in [1, 2] {
            let pool = pool(threads);
            g.bench_function(
                BenchmarkId::from_parameter(format!("{name}/forward/{threads}thr")),
                |b| b.iter(|| frame_in(&pool, || scene.render_image().unwrap())),
            );
            g.bench_function(
                BenchmarkId::from_parameter(format!("{name}/forward_backward/{threads}thr")),
                |b| {
                    b.iter(|| {
                        frame_in(&pool, || {
                            scene
                                .image_loss_grad(target.clone(), "zeros", SceneInput::Positions)
                                .unwrap()
                        })
                    })
                },
            );
        }
    }
    g.finish();
    let _ = std::fs::remove_dir_all(&tmp);
}

criterion_group!(benches, bench_raytrace);
criterion_main!(benches);
