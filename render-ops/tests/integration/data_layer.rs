//! The data layer against the peer kit's scenes and reference arrays (vendored in
//! `tests/data/peers`, see `common::peers`) and the other files in `tests/data`.

use std::path::{Path, PathBuf};

use ndarray::{Array3, ArrayD, Ix2};
use render_ops::camera::{ndc_to_pixel, Camera};
use render_ops::io::{read_npy, read_npy_shape, read_png, write_npy, write_png, IoError};
use render_ops::mesh::Mesh;
use render_ops::obj::{load_obj, ObjError};
use render_ops::scene::{Method, Scene, SceneError, Shading};

use crate::common;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("tapestry-data-layer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// The `v` lines of an OBJ, parsed independently of obj.rs.
fn v_lines(path: &Path) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| l.split_whitespace().map(|t| t.parse().unwrap()).collect())
        .collect()
}

fn f_lines(path: &Path) -> Vec<[u32; 3]> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter_map(|l| l.strip_prefix("f "))
        .map(|l| {
            let v: Vec<u32> = l
                .split_whitespace()
                .map(|t| t.parse::<u32>().unwrap() - 1)
                .collect();
            [v[0], v[1], v[2]]
        })
        .collect()
}

#[test]
fn ico5k_obj_loads_in_file_order_with_colours() {
    let peers = common::peers();
    for name in ["ico5k.obj", "ico5k_target.obj"] {
        let path = peers.join("scenes").join(name);
        let m: Mesh<f64> = load_obj(&path).unwrap();
        assert_eq!(m.vertex_count(), 2562, "{name}");
        assert_eq!(m.face_count(), 5120, "{name}");
        assert_eq!(m.colors.len(), 2562, "{name}");
        assert!(m.uvs.is_empty() && m.normals.is_empty());
        let vs = v_lines(&path);
        assert_eq!(vs.len(), 2562);
        for (i, v) in vs.iter().enumerate() {
            // Bit-exact: the file carries 17 significant digits.
            assert_eq!(m.positions[i], [v[0], v[1], v[2]], "{name} vertex {i}");
            assert_eq!(m.colors[i], [v[3], v[4], v[5]], "{name} colour {i}");
        }
        assert_eq!(m.faces, f_lines(&path), "{name}");
        m.validate().unwrap();
        assert!(m.degenerate_faces().is_empty());
        // f32 loading rounds each value once.
        let m32: Mesh<f32> = load_obj(&path).unwrap();
        assert_eq!(m32.positions[5][1], vs[5][1] as f32);
        assert_eq!(m32.faces, m.faces);
    }
}

#[test]
fn procedural_icosphere_reproduces_ico5k_bit_for_bit() {
    let peers = common::peers();
    let file: Mesh<f64> = load_obj(peers.join("scenes/ico5k.obj")).unwrap();
    let ico = Mesh::<f64>::icosphere(4, 1.0);
    assert_eq!(ico.faces, file.faces);
    assert_eq!(ico.positions, file.positions);
}

#[test]
fn every_peer_scene_json_loads() {
    let peers = common::peers();
    let mut count = 0;
    let mut entries: Vec<PathBuf> = std::fs::read_dir(peers.join("scenes"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    entries.sort();
    for path in entries {
        let s = Scene::<f64>::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!((s.desc.image.width, s.desc.image.height), (128, 128));
        assert_eq!(s.mesh.vertex_count(), 2562);
        assert_eq!(s.mesh.face_count(), 5120);
        assert!(s.mesh.has_colors());
        assert_eq!(s.desc.material.shading, Shading::None);
        assert!(s.desc.lights.is_empty() && s.texture.is_none());
        let stem = path.file_stem().unwrap().to_str().unwrap();
        let method = if stem.ends_with("_deodr") {
            Method::Deodr
        } else if stem.ends_with("_hard") {
            Method::Hard
        } else {
            Method::SoftRas
        };
        assert_eq!(s.desc.raster.method, method, "{stem}");
        assert_eq!(
            (s.desc.raster.sigma, s.desc.raster.gamma, s.desc.raster.eps),
            (1e-4, 1e-4, 1e-3)
        );
        count += 1;
    }
    assert!(count >= 6, "only {count} scene JSONs");
}

/// Tapestry's camera (look-at + OpenGL perspective, pixel u = (ndc.x + 1) W / 2,
/// v = (1 - ndc.y) H / 2) projects like the peers' OpenCV camera K, R = I, t = (0, 0, 3).
#[test]
fn reference_camera_matches_opencv_k() {
    let peers = common::peers();
    let k = read_npy_shape::<f64>(peers.join("reference/camera_K.npy"), &[3, 3])
        .unwrap()
        .into_dimensionality::<Ix2>()
        .unwrap();
    assert!((k[[0, 0]] - 140.8).abs() < 1e-12 && k[[0, 2]] == 64.0 && k[[1, 2]] == 64.0);
    let rt = read_npy_shape::<f64>(peers.join("reference/camera_Rt.npy"), &[3, 4])
        .unwrap()
        .into_dimensionality::<Ix2>()
        .unwrap();
    let t = [0.0, 0.0, 3.0];
    for i in 0..3 {
        for j in 0..3 {
            assert_eq!(rt[[i, j]], if i == j { 1.0 } else { 0.0 });
        }
        assert_eq!(rt[[i, 3]], t[i]);
    }

    let scene = Scene::<f64>::load(peers.join("scenes/ico5k.json")).unwrap();
    let cam: &Camera = &scene.camera;
    let (w, h) = (scene.desc.image.width, scene.desc.image.height);

    // The OpenCV form Tapestry derives equals the peers' files.
    let cv = cam.opencv(w, h).unwrap();
    for i in 0..3 {
        for j in 0..3 {
            assert!(
                (cv.k[i][j] - k[[i, j]]).abs() < 1e-12,
                "K[{i}][{j}] {} vs {}",
                cv.k[i][j],
                k[[i, j]]
            );
            assert!((cv.r[i][j] - rt[[i, j]]).abs() < 1e-15);
        }
        assert!((cv.t[i] - rt[[i, 3]]).abs() < 1e-15);
    }

    let mut worst: f64 = 0.0;
    for name in ["ico5k.obj", "ico5k_target.obj"] {
        let mesh: Mesh<f64> = load_obj(peers.join("scenes").join(name)).unwrap();
        for p in &mesh.positions {
            let pc = [p[0] + t[0], p[1] + t[1], p[2] + t[2]];
            let z = pc[2];
            let u_cv = (k[[0, 0]] * pc[0] + k[[0, 1]] * pc[1] + k[[0, 2]] * pc[2]) / z;
            let v_cv = (k[[1, 0]] * pc[0] + k[[1, 1]] * pc[1] + k[[1, 2]] * pc[2]) / z;
            let clip = cam.project(*p);
            let ndc = [clip[0] / clip[3], clip[1] / clip[3]];
            let [u, v] = ndc_to_pixel(ndc, w, h);
            worst = worst.max((u - u_cv).abs()).max((v - v_cv).abs());
            // clip.w is the view depth, equal to OpenCV's z.
            assert!((clip[3] - z).abs() < 1e-12);
            assert!((cam.view_depth(*p) - z).abs() < 1e-12);
            assert_eq!(cam.project_pixel(*p, w, h), Some([u, v]));
        }
    }
    assert!(worst < 1e-9, "max pixel discrepancy {worst}");
}

#[test]
fn reference_arrays_read_and_round_trip() {
    let peers = common::peers();
    let img: ArrayD<f64> =
        read_npy_shape(peers.join("reference/hard_image.npy"), &[128, 128, 3]).unwrap();
    assert!(img.iter().all(|&x| (0.0..=1.0).contains(&x)));
    assert!(img.iter().any(|&x| x > 0.1));
    let alpha: ArrayD<f64> =
        read_npy_shape(peers.join("reference/hard_alpha.npy"), &[128, 128, 1]).unwrap();
    assert_eq!(alpha.iter().filter(|&&a| a == 1.0).count(), 7788);
    let img32: ArrayD<f32> = read_npy(peers.join("reference/hard_image.npy")).unwrap();
    assert_eq!(img32, img.mapv(|x| x as f32));

    let e =
        read_npy_shape::<f64>(peers.join("reference/hard_image.npy"), &[128, 128, 4]).unwrap_err();
    assert!(matches!(e, IoError::Shape { .. }));
    assert!(e.to_string().contains("hard_image.npy"), "{e}");

    // .npy round trip is exact; PNG within half a quantisation step.
    let p = tmp("hard_image.npy");
    write_npy(&p, &img).unwrap();
    assert_eq!(read_npy::<f64>(&p).unwrap(), img);
    let img3: Array3<f64> = img.into_dimensionality().unwrap();
    let q = tmp("hard_image.png");
    write_png(&q, &img3).unwrap();
    let back: Array3<f64> = read_png(&q).unwrap();
    assert_eq!(back.shape(), &[128, 128, 3]);
    let err = back
        .iter()
        .zip(img3.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(err <= 0.5 / 255.0 + 1e-12, "{err}");
}

#[test]
fn scene_with_every_section_loads_and_unifies() {
    let s = Scene::<f32>::load(data("scene_full.json")).unwrap();
    assert_eq!(s.mesh_path, data("two_quads_uv.obj"));
    assert_eq!(s.desc.lights.len(), 3);
    assert_eq!(s.desc.material.shading, Shading::Sh);
    assert_eq!(s.desc.raster.method, Method::SoftRas);
    assert_eq!(s.desc.raster.effective_faces_per_pixel(), None);
    let m = &s.mesh;
    assert_eq!((m.vertex_count(), m.face_count()), (6, 4));
    assert_eq!(m.uv_faces.len(), 4);
    // The seam along x = 1 splits vertices 2 and 3 (1-based) into two copies each.
    let u = m.unified().unwrap();
    assert_eq!(u.mesh.vertex_count(), 8);
    assert_eq!(&u.position_index[6..], &[1, 2]);
    u.mesh.validate().unwrap();
    // The camera looks at the quads' centre: it projects to the image centre.
    let c = s.camera.project_pixel([1.0, 0.5, 0.0], 64, 32).unwrap();
    assert!((c[0] - 32.0).abs() < 1e-9 && (c[1] - 16.0).abs() < 1e-9);
}

#[test]
fn bad_scene_files_give_messages_naming_the_problem() {
    let cases: [(&str, &str); 7] = [
        ("unknown_key.json", "raster: unknown field `sigmaa`, expected one of `method`"),
        ("wrong_type.json", "raster.sigma: invalid type: string \"tiny\", expected f64"),
        ("missing_mesh.json", "missing.obj: cannot open OBJ file"),
        (
            "bad_enum.json",
            "raster.method: unknown variant `soft`, expected one of `hard`, `tf_mesh`, `opendr`, `nmr`, `softras`, `dibr`, `deodr`",
        ),
        ("sh_rows.json", "lights[0].coeffs: expected 9 rows of [r, g, b] (bands l = 0, 1, 2), got 3"),
        ("bad_value.json", "raster.sigma: 0 must be finite and > 0"),
        ("bad_mesh.json", "bad_number.obj:3: bad number '1.5.2' in a 'v' statement"),
    ];
    for (name, expected) in cases {
        let path = data("bad").join(name);
        let e = Scene::<f64>::load(&path).unwrap_err();
        let msg = e.to_string();
        assert!(msg.starts_with(&path.display().to_string()), "{msg}");
        assert!(msg.contains(expected), "{name}: {msg}");
        match name {
            "missing_mesh.json" => assert!(matches!(
                e,
                SceneError::Mesh {
                    source: ObjError::Open { .. },
                    ..
                }
            )),
            "bad_mesh.json" => assert!(matches!(
                e,
                SceneError::Mesh {
                    source: ObjError::BadNumber { line: 3, .. },
                    ..
                }
            )),
            "sh_rows.json" | "bad_value.json" => assert!(matches!(e, SceneError::Invalid { .. })),
            _ => assert!(matches!(e, SceneError::Json { .. })),
        }
    }
}
