//! Determinism of whole scenes: for every raster method available in this build, the image
//! and the gradients of an image loss with respect to positions, colours and the camera are
//! bit-identical on rayon pools of 1, 2 and 8 threads (fixed-order reductions, no atomics).
//! Methods not available yet must be rejected with an error, identically on every pool.

use tapestry::autodiff::Tape;
use tapestry::render_ops::mesh::Mesh;
use tapestry::render_ops::obj::write_obj;
use tapestry::render_ops::pipeline::Wrt;
use tapestry::render_ops::scene::{Method, Scene};

/// Everything a run produces, as bits: image, then the gradients (positions, colours, camera).
type Bits = Vec<Vec<u64>>;

fn scene(method: Method, dir: &std::path::Path) -> Scene<f64> {
    // An icosphere (~320 faces: both layers overlap every covered pixel) and a second, smaller
    // one in front of it, so that occlusion, silhouettes and back faces all occur.
    let mut mesh: Mesh<f64> = Mesh::icosphere(2, 1.0);
    let small: Mesh<f64> = Mesh::icosphere(1, 0.4);
    let base = mesh.positions.len() as u32;
    mesh.positions.extend(
        small
            .positions
            .iter()
            .map(|p| [p[0] + 0.5, p[1] + 0.3, p[2] + 0.9]),
    );
    mesh.faces
        .extend(small.faces.iter().map(|f| f.map(|i| i + base)));
    mesh.colors = mesh
        .positions
        .iter()
        .map(|p| [0.5 + 0.4 * p[0], 0.5 + 0.4 * p[1], 0.5 + 0.4 * p[2]])
        .collect();
    write_obj(dir.join("m.obj"), &mesh).unwrap();
    let json = format!(
        r#"{{"mesh": "m.obj",
        "camera": {{"eye": [0.4, 0.6, 3.5], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 40,
                   "near": 0.5, "far": 10}},
        "image": {{"width": 64, "height": 64, "background": [0.1, 0.2, 0.3]}},
        "raster": {{"method": "{}", "sigma": 1e-4, "gamma": 1e-3}}}}"#,
        method.name()
    );
    Scene::from_json(&json, dir, "determinism.json").unwrap()
}

fn run(scene: &Scene<f64>) -> Result<Bits, String> {
    let tape = Tape::new();
    let vars = scene.vars(
        &tape,
        Wrt {
            positions: true,
            colors: true,
            camera: true,
            ..Wrt::default()
        },
    );
    let img = scene.render(&vars).map_err(|e| e.to_string())?;
    // A loss that weights every pixel and channel differently.
    let shape = img.value().unwrap().raw_dim();
    let w = tapestry::autodiff::ndarray::Array::from_shape_fn(shape, |i| {
        ((i[0] * 7 + i[1] * 13 + i[2] * 3) % 11) as f64 / 11.0
    });
    let loss = (img * tape.constant(w)).square().sum();
    let g = tape.backward(loss).unwrap();
    let bits = |t: &tapestry::autodiff::Tensor<f64>| t.iter().map(|v| v.to_bits()).collect();
    Ok(vec![
        bits(&img.value().unwrap()),
        bits(&g.wrt(vars.positions)),
        bits(&g.wrt(vars.colors)),
        bits(&g.wrt(vars.camera)),
    ])
}

#[test]
fn every_method_is_bit_identical_on_1_2_and_8_threads() {
    let dir = std::env::temp_dir().join(format!("tapestry-determinism-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut available = 0;
    for method in Method::ALL {
        let sc = scene(method, &dir);
        let runs: Vec<Result<Bits, String>> = [1, 2, 8]
            .iter()
            .map(|&n| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .build()
                    .unwrap()
                    .install(|| run(&sc))
            })
            .collect();
        match &runs[0] {
            Ok(bits) => {
                available += 1;
                assert!(
                    bits[1].iter().any(|&b| f64::from_bits(b) != 0.0),
                    "{method}: no position gradient"
                );
                for (n, r) in [2, 8].iter().zip(&runs[1..]) {
                    let other = r
                        .as_ref()
                        .unwrap_or_else(|e| panic!("{method}, {n} threads: {e}"));
                    for (k, what) in ["image", "positions", "colors", "camera"]
                        .iter()
                        .enumerate()
                    {
                        assert!(
                            bits[k] == other[k],
                            "{method}: {what} differs between 1 and {n} threads"
                        );
                    }
                }
            }
            Err(e) => {
                assert!(e.contains(method.name()), "{method}: {e}");
                assert!(runs.iter().all(|r| r.as_ref().err() == Some(e)), "{method}");
            }
        }
    }
    eprintln!(
        "{available} of {} methods available and deterministic",
        Method::ALL.len()
    );
    // hard, tf_mesh, opendr, nmr, deodr, softras, dibr and analytic: every method.
    assert!(available >= 8, "only {available} methods available");
    let _ = std::fs::remove_dir_all(&dir);
}
