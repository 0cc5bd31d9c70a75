//! Loading and saving: round trips and every loader error path.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use models::{ModelError, Morphable, MorphableParts, Region};
use ndarray::{Array1, Array2, Array3, ArrayD};
use ndarray_npy::WriteNpyExt;
use serde_json::Value;

fn scratch(name: &str) -> PathBuf {
    static N: AtomicUsize = AtomicUsize::new(0);
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!(
        "model_io_{}_{}_{}",
        name,
        std::process::id(),
        N.fetch_add(1, Ordering::SeqCst)
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A small valid model: a square pyramid (5 vertices, 6 triangles), 3 identity, 2
/// expression, 2 albedo components, two regions, uvs, groups and names.
fn tiny() -> MorphableParts<f64> {
    let v = 5;
    let mean_shape = Array2::from_shape_vec(
        (v, 3),
        vec![
            -1., -1., 0., 1., -1., 0., 1., 1., 0., -1., 1., 0., 0., 0., 1.,
        ],
    )
    .unwrap();
    let basis = |k: usize, seed: f64| {
        Array2::from_shape_fn((3 * v, k), |(r, c)| ((r * 7 + c * 3) as f64 * seed).sin())
    };
    MorphableParts {
        name: "tiny".into(),
        description: "a pyramid".into(),
        mean_shape,
        id_basis: basis(3, 0.37),
        sigma_id: Array1::from(vec![3.0, 2.0, 1.0]),
        exp_basis: basis(2, 0.53),
        sigma_exp: Array1::from(vec![4.0, 0.5]),
        mean_albedo: Array2::from_elem((v, 3), 0.5),
        albedo_basis: basis(2, 0.71),
        sigma_albedo: Array1::from(vec![0.1, 0.05]),
        basis_scaled: false,
        faces: vec![
            [0, 1, 4],
            [1, 2, 4],
            [2, 3, 4],
            [3, 0, 4],
            [0, 2, 1],
            [0, 3, 2],
        ],
        uvs: Some(Array2::from_shape_fn((v, 2), |(i, c)| {
            (i + c) as f64 / 10.0
        })),
        landmarks: vec![4, 0, 2],
        landmark_points: vec![],
        landmark_scheme: None,
        landmark_groups: [("base".to_string(), vec![0, 1, 2, 3])]
            .into_iter()
            .collect(),
        regions: vec![
            Region::new("skin"),
            Region {
                name: "bottom".into(),
                albedo: Some([0.1, 0.0, 0.0]),
                photometric: false,
            },
        ],
        face_regions: vec![0, 0, 0, 0, 1, 1],
        id_names: vec!["a".into(), "b".into(), "c".into()],
        exp_names: vec![],
        albedo_names: vec!["x".into(), "y".into()],
    }
}

fn saved(name: &str) -> PathBuf {
    let d = scratch(name);
    Morphable::from_parts(tiny()).unwrap().save(&d).unwrap();
    d
}

fn write<A: WriteNpyExt>(path: PathBuf, a: &A) {
    a.write_npy(std::fs::File::create(path).unwrap()).unwrap();
}

fn edit_json(dir: &Path, f: impl FnOnce(&mut Value)) {
    let p = dir.join("model.json");
    let mut j: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut j);
    std::fs::write(&p, serde_json::to_string_pretty(&j).unwrap()).unwrap();
}

fn load_err(dir: &Path) -> ModelError {
    match Morphable::<f64>::load(dir) {
        Ok(_) => panic!("loading {} should fail", dir.display()),
        Err(e) => e,
    }
}

fn assert_same(a: &Morphable<f64>, b: &Morphable<f64>, tol: f64) {
    let close = |x: &[f64], y: &[f64]| {
        x.len() == y.len()
            && x.iter()
                .zip(y)
                .all(|(p, q)| (p - q).abs() <= tol * q.abs().max(1.0))
    };
    let v = |a: ndarray::ArrayView2<'_, f64>| a.iter().copied().collect::<Vec<_>>();
    assert!(close(&v(a.mean_shape().view()), &v(b.mean_shape().view())));
    assert!(close(&v(a.id_basis()), &v(b.id_basis())));
    assert!(close(&v(a.exp_basis()), &v(b.exp_basis())));
    assert!(close(&v(a.albedo_basis()), &v(b.albedo_basis())));
    assert!(close(
        &v(a.mean_albedo().view()),
        &v(b.mean_albedo().view())
    ));
    assert!(close(&a.sigma_id().to_vec(), &b.sigma_id().to_vec()));
    assert!(close(&a.sigma_exp().to_vec(), &b.sigma_exp().to_vec()));
    assert!(close(
        &a.sigma_albedo().to_vec(),
        &b.sigma_albedo().to_vec()
    ));
    assert_eq!(a.faces(), b.faces());
    assert_eq!(a.face_regions(), b.face_regions());
    assert_eq!(a.regions(), b.regions());
    assert_eq!(a.landmarks(), b.landmarks());
    assert_eq!(a.landmark_groups(), b.landmark_groups());
    assert_eq!(a.id_names(), b.id_names());
    assert_eq!(a.exp_names(), b.exp_names());
    assert_eq!(a.albedo_names(), b.albedo_names());
    assert_eq!(a.name(), b.name());
    assert_eq!(a.description(), b.description());
    assert_eq!(a.uvs().is_some(), b.uvs().is_some());
}

#[test]
fn round_trip_f64_is_exact() {
    let m = Morphable::from_parts(tiny()).unwrap();
    let d = scratch("rt64");
    m.save(&d).unwrap();
    let back = Morphable::<f64>::load(&d).unwrap();
    assert_same(&m, &back, 0.0);
    // Saving again gives the same bytes.
    let d2 = scratch("rt64b");
    back.save(&d2).unwrap();
    for f in [
        "model.json",
        "mean_shape.npy",
        "id_basis.npy",
        "faces.npy",
        "face_regions.npy",
    ] {
        assert_eq!(
            std::fs::read(d.join(f)).unwrap(),
            std::fs::read(d2.join(f)).unwrap(),
            "{f}"
        );
    }
}

#[test]
fn round_trip_f32_and_the_face_model() {
    let m = models::face::default_face::<f32>();
    let d = scratch("rt32");
    m.save(&d).unwrap();
    let back = Morphable::<f32>::load(&d).unwrap();
    assert_eq!(back.id_basis(), m.id_basis());
    assert_eq!(back.sigma_id(), m.sigma_id());
    assert_eq!(back.sigma_exp(), m.sigma_exp());
    assert_eq!(back.mean_shape(), m.mean_shape());
    assert_eq!(back.faces(), m.faces());
    assert_eq!(back.face_regions(), m.face_regions());
    assert_eq!(back.regions(), m.regions());
    assert_eq!(back.landmarks().len(), 468);
    // f32 files load into an f64 model too.
    let wide = Morphable::<f64>::load(&d).unwrap();
    assert_eq!(wide.id_basis()[[5, 3]], m.id_basis()[[5, 3]] as f64);
    // And from memory.
    let names = [
        "model.json",
        "mean_shape.npy",
        "id_basis.npy",
        "exp_basis.npy",
        "mean_albedo.npy",
        "albedo_basis.npy",
        "faces.npy",
        "uvs.npy",
        "face_regions.npy",
    ];
    let bytes: Vec<(String, Vec<u8>)> = names
        .iter()
        .map(|n| (n.to_string(), std::fs::read(d.join(n)).unwrap()))
        .collect();
    let refs: Vec<(&str, &[u8])> = bytes
        .iter()
        .map(|(n, b)| (n.as_str(), b.as_slice()))
        .collect();
    let mem = Morphable::<f32>::load_from_memory(&refs).unwrap();
    assert_eq!(mem.exp_basis(), m.exp_basis());
}

#[test]
fn a_v3k_basis_an_npy_sigma_and_units_are_accepted() {
    let d = saved("layouts");
    let m = Morphable::<f64>::load(&d).unwrap();
    // Fortran-order arrays read as their logical values.
    let fortran = m
        .exp_basis()
        .t()
        .as_standard_layout()
        .into_owned()
        .reversed_axes();
    assert!(fortran.t().is_standard_layout());
    write(d.join("exp_basis.npy"), &fortran);
    let f = Morphable::<f64>::load(&d).unwrap();
    assert_eq!(f.exp_basis(), m.exp_basis());
    // FLAME-style [V, 3, K] basis, sigma from a file, centimetres.
    let b = m
        .id_basis()
        .to_owned()
        .into_shape_with_order((5, 3, 3))
        .unwrap();
    write(d.join("id_basis.npy"), &b);
    write(
        d.join("sigma_id.npy"),
        &Array1::from(vec![0.3f32, 0.2, 0.1]),
    );
    let mean_cm = m.mean_shape() / 10.0;
    write(d.join("mean_shape.npy"), &mean_cm);
    edit_json(&d, |j| {
        j["sigma_id"] = "sigma_id.npy".into();
        j["units"] = "cm".into();
        j["sigma_exp"] = serde_json::json!([0.4, 0.05]);
    });
    let l = Morphable::<f64>::load(&d).unwrap();
    assert_eq!(l.id_basis(), m.id_basis());
    for (a, b) in l.mean_shape().iter().zip(m.mean_shape().iter()) {
        assert!((a - b).abs() < 1e-12);
    }
    // Orthonormal convention: the unit goes to the coefficients.
    for (a, b) in l.sigma_id().iter().zip([3.0, 2.0, 1.0]) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
    for (a, b) in l.sigma_exp().iter().zip([4.0, 0.5]) {
        assert!((a - b).abs() < 1e-12);
    }
    // Scaled-basis convention: the unit goes to the basis, sigma stays.
    edit_json(&d, |j| {
        j["basis_scaled"] = true.into();
        j["units"] = "m".into();
    });
    let s = Morphable::<f64>::load(&d).unwrap();
    assert!(s.basis_scaled());
    assert!((s.id_basis()[[0, 0]] - 1000.0 * m.id_basis()[[0, 0]]).abs() < 1e-9);
    assert!((s.sigma_exp()[0] - 0.4).abs() < 1e-12);
    // Optional parts may be left out: no expressions, no albedo, no regions, no uvs.
    edit_json(&d, |j| {
        let files = j["files"].as_object_mut().unwrap();
        for k in [
            "exp_basis",
            "albedo_basis",
            "mean_albedo",
            "uvs",
            "face_regions",
        ] {
            files.remove(k);
        }
        let o = j.as_object_mut().unwrap();
        for k in [
            "sigma_exp",
            "sigma_albedo",
            "n_exp",
            "n_albedo",
            "regions",
            "albedo_names",
            "landmarks",
        ] {
            o.remove(k);
        }
    });
    let bare = Morphable::<f64>::load(&d).unwrap();
    assert_eq!((bare.n_exp(), bare.n_albedo()), (0, 0));
    assert_eq!(bare.landmarks(), &[0, 1, 2, 3, 4]);
    assert!(bare.uvs().is_none());
    assert_eq!(bare.regions().len(), 1);
    let tape = autodiff::Tape::<f64>::new();
    let a = tape.leaf(ndarray::ArrayD::zeros(ndarray::IxDyn(&[3])));
    let b = tape.leaf(ndarray::ArrayD::zeros(ndarray::IxDyn(&[0])));
    assert_eq!(bare.shape(&tape, a, b).value().unwrap().shape(), &[5, 3]);
}

#[test]
fn missing_files_are_named() {
    let d = saved("missing");
    std::fs::remove_file(d.join("exp_basis.npy")).unwrap();
    match load_err(&d) {
        ModelError::MissingFile { path } => {
            assert!(path.ends_with("exp_basis.npy"), "{}", path.display())
        }
        e => panic!("{e}"),
    }
    let d = scratch("missing_json");
    match load_err(&d) {
        ModelError::MissingFile { path } => assert!(path.ends_with("model.json")),
        e => panic!("{e}"),
    }
}

#[test]
fn basis_rows_must_be_3v() {
    let d = saved("rows");
    write(d.join("id_basis.npy"), &Array2::<f64>::zeros((12, 3)));
    let e = load_err(&d);
    let msg = e.to_string();
    match e {
        ModelError::Dimension {
            file,
            expected,
            found,
            ..
        } => {
            assert!(file.ends_with("id_basis.npy"));
            assert_eq!((expected, found), (15, 12));
        }
        e => panic!("{e}"),
    }
    assert!(
        msg.contains("id_basis.npy") && msg.contains("15") && msg.contains("12"),
        "{msg}"
    );
    // Columns must match n_id of model.json.
    let d = saved("cols");
    write(d.join("exp_basis.npy"), &Array2::<f64>::zeros((15, 3)));
    match load_err(&d) {
        ModelError::Dimension {
            file,
            what,
            expected,
            found,
        } => {
            assert!(
                file.ends_with("exp_basis.npy") && what.contains("n_exp"),
                "{what}"
            );
            assert_eq!((expected, found), (2, 3));
        }
        e => panic!("{e}"),
    }
    // A 3-d basis whose middle axis is not 3 is a shape error.
    let d = saved("shape3");
    write(d.join("id_basis.npy"), &Array3::<f64>::zeros((5, 2, 3)));
    assert!(
        matches!(load_err(&d), ModelError::Shape { file, .. } if file.ends_with("id_basis.npy"))
    );
}

#[test]
fn vertex_count_must_match_model_json() {
    let d = saved("nverts");
    edit_json(&d, |j| j["n_vertices"] = 6.into());
    match load_err(&d) {
        ModelError::Dimension {
            file,
            expected,
            found,
            ..
        } => {
            assert!(file.ends_with("mean_shape.npy"));
            assert_eq!((expected, found), (6, 5));
        }
        e => panic!("{e}"),
    }
}

#[test]
fn face_indices_must_be_vertices() {
    let d = saved("faces");
    let mut f = Array2::<i64>::zeros((6, 3));
    f[[4, 2]] = 5;
    write(d.join("faces.npy"), &f);
    match load_err(&d) {
        ModelError::IndexOutOfRange {
            file,
            index,
            position,
            bound,
            ..
        } => {
            assert!(file.ends_with("faces.npy"));
            assert_eq!((index, position, bound), (5, 14, 5));
        }
        e => panic!("{e}"),
    }
    let mut f = Array2::<i32>::zeros((6, 3));
    f[[0, 0]] = -1;
    write(d.join("faces.npy"), &f);
    assert!(matches!(
        load_err(&d),
        ModelError::IndexOutOfRange { index: -1, .. }
    ));
    // Wrong face count.
    write(d.join("faces.npy"), &Array2::<u32>::zeros((5, 3)));
    assert!(matches!(
        load_err(&d),
        ModelError::Dimension {
            expected: 6,
            found: 5,
            ..
        }
    ));
    // uint16 faces are fine.
    write(d.join("faces.npy"), &Array2::<u16>::zeros((6, 3)));
    assert!(Morphable::<f64>::load(&d).is_ok());
}

#[test]
fn sigma_length_must_match_the_basis() {
    let d = saved("sigma");
    edit_json(&d, |j| j["sigma_id"] = serde_json::json!([1.0, 2.0]));
    match load_err(&d) {
        ModelError::Dimension {
            file,
            expected,
            found,
            ..
        } => {
            assert!(
                file.contains("model.json") && file.contains("sigma_id"),
                "{file}"
            );
            assert_eq!((expected, found), (3, 2));
        }
        e => panic!("{e}"),
    }
    write(d.join("s.npy"), &Array1::from(vec![1.0f64; 4]));
    edit_json(&d, |j| j["sigma_id"] = "s.npy".into());
    assert!(
        matches!(load_err(&d), ModelError::Dimension { file, expected: 3, found: 4, .. } if file.ends_with("s.npy"))
    );
    edit_json(&d, |j| j["sigma_id"] = serde_json::json!([1.0, 0.0, 2.0]));
    assert!(matches!(
        load_err(&d),
        ModelError::BadSigma { index: 1, .. }
    ));
    // A basis without sigmas.
    let d = saved("nosigma");
    edit_json(&d, |j| {
        j.as_object_mut().unwrap().remove("sigma_exp");
    });
    assert!(matches!(load_err(&d), ModelError::Json { .. }));
}

#[test]
fn nan_values_are_reported_with_their_position() {
    let d = saved("nan");
    let m = Morphable::<f64>::load(&d).unwrap();
    let mut mean = m.mean_shape();
    mean[[2, 1]] = f64::NAN;
    write(d.join("mean_shape.npy"), &mean);
    match load_err(&d) {
        ModelError::NonFinite { file, index, .. } => {
            assert!(file.ends_with("mean_shape.npy"));
            assert_eq!(index, 7);
        }
        e => panic!("{e}"),
    }
    let d = saved("nan2");
    let mut b = m.albedo_basis().to_owned().mapv(|x| x as f32);
    b[[3, 1]] = f32::INFINITY;
    write(d.join("albedo_basis.npy"), &b);
    assert!(
        matches!(load_err(&d), ModelError::NonFinite { file, index: 7, .. } if file.ends_with("albedo_basis.npy"))
    );
    let d = saved("nan3");
    write(d.join("s.npy"), &Array1::from(vec![1.0, f64::NAN, 1.0]));
    edit_json(&d, |j| j["sigma_id"] = "s.npy".into());
    assert!(
        matches!(load_err(&d), ModelError::NonFinite { file, index: 1, .. } if file.ends_with("s.npy"))
    );
}

#[test]
fn wrong_dtypes_are_rejected() {
    let d = saved("dtype");
    write(d.join("faces.npy"), &Array2::<f32>::zeros((6, 3)));
    match load_err(&d) {
        ModelError::WrongDtype { file, found, .. } => {
            assert!(file.ends_with("faces.npy"));
            assert!(found.contains("f4"), "{found}");
        }
        e => panic!("{e}"),
    }
    let d = saved("dtype2");
    write(d.join("id_basis.npy"), &Array2::<i32>::zeros((15, 3)));
    match load_err(&d) {
        ModelError::WrongDtype {
            file,
            found,
            expected,
        } => {
            assert!(file.ends_with("id_basis.npy"));
            assert!(
                found.contains("i4") && expected.contains("float"),
                "{found}"
            );
        }
        e => panic!("{e}"),
    }
    let d = saved("dtype3");
    write(
        d.join("mean_shape.npy"),
        &ArrayD::<bool>::from_elem(ndarray::IxDyn(&[5, 3]), true),
    );
    assert!(matches!(load_err(&d), ModelError::WrongDtype { .. }));
}

#[test]
fn corrupt_files_and_bad_json_are_errors() {
    let d = saved("corrupt");
    let bytes = std::fs::read(d.join("id_basis.npy")).unwrap();
    std::fs::write(d.join("id_basis.npy"), &bytes[..bytes.len() - 8]).unwrap();
    assert!(matches!(load_err(&d), ModelError::Npy { file, .. } if file.ends_with("id_basis.npy")));
    let d = saved("json");
    edit_json(&d, |j| j["colour"] = "blue".into());
    let e = load_err(&d);
    assert!(
        matches!(&e, ModelError::Json { .. }) && e.to_string().contains("colour"),
        "{e}"
    );
    let d = saved("units");
    edit_json(&d, |j| j["units"] = "furlong".into());
    assert!(matches!(load_err(&d), ModelError::Json { detail, .. } if detail.contains("furlong")));
    let d = saved("version");
    edit_json(&d, |j| j["version"] = 99.into());
    assert!(matches!(load_err(&d), ModelError::Json { .. }));
    let d = saved("syntax");
    std::fs::write(d.join("model.json"), "{ not json").unwrap();
    assert!(matches!(load_err(&d), ModelError::Json { .. }));
}

#[test]
fn landmarks_groups_regions_and_names_are_checked() {
    let d = saved("landmarks");
    edit_json(&d, |j| j["landmarks"] = serde_json::json!([0, 9]));
    assert!(matches!(
        load_err(&d),
        ModelError::IndexOutOfRange {
            index: 9,
            position: 1,
            bound: 5,
            ..
        }
    ));
    let d = saved("groups");
    edit_json(&d, |j| {
        j["landmark_groups"]["base"] = serde_json::json!([0, 1, 7])
    });
    assert!(
        matches!(load_err(&d), ModelError::IndexOutOfRange { file, index: 7, .. } if file.contains("base"))
    );
    let d = saved("regions");
    write(
        d.join("face_regions.npy"),
        &Array1::from(vec![0i32, 0, 0, 0, 2, 1]),
    );
    assert!(
        matches!(load_err(&d), ModelError::IndexOutOfRange { file, index: 2, bound: 2, .. } if file.ends_with("face_regions.npy"))
    );
    let d = saved("names");
    edit_json(&d, |j| j["id_names"] = serde_json::json!(["only one"]));
    assert!(matches!(
        load_err(&d),
        ModelError::Dimension {
            expected: 3,
            found: 1,
            ..
        }
    ));
    let d = saved("uvs");
    write(d.join("uvs.npy"), &Array2::<f64>::zeros((4, 2)));
    assert!(
        matches!(load_err(&d), ModelError::Dimension { file, expected: 5, found: 4, .. } if file.ends_with("uvs.npy"))
    );
}

#[test]
fn from_parts_checks_in_memory_models_too() {
    let mut p = tiny();
    p.faces[2] = [0, 1, 9];
    assert!(matches!(
        Morphable::from_parts(p),
        Err(ModelError::IndexOutOfRange { index: 9, .. })
    ));
    let mut p = tiny();
    p.sigma_exp = Array1::from(vec![1.0]);
    assert!(matches!(
        Morphable::from_parts(p),
        Err(ModelError::Dimension {
            expected: 2,
            found: 1,
            ..
        })
    ));
    let mut p = tiny();
    p.id_basis[[0, 0]] = f64::NAN;
    assert!(matches!(
        Morphable::from_parts(p),
        Err(ModelError::NonFinite { index: 0, .. })
    ));
    let mut p = tiny();
    p.regions.push(Region::new("skin"));
    assert!(matches!(
        Morphable::from_parts(p),
        Err(ModelError::Invalid { .. })
    ));
    // Truncation and casting keep a valid model.
    let m = Morphable::from_parts(tiny()).unwrap();
    let t = m.truncated(2, 9, 0);
    assert_eq!((t.n_id(), t.n_exp(), t.n_albedo()), (2, 2, 0));
    assert_eq!(t.id_names(), &["a", "b"]);
    let c = m.cast::<f32>().cast::<f64>();
    assert!((c.id_basis()[[3, 1]] - m.id_basis()[[3, 1]]).abs() < 1e-6);
}

#[test]
fn landmark_points_and_scheme_round_trip_and_are_checked() {
    use models::{LandmarkPoint, LandmarkScheme, SurfacePoint};
    // Surface landmarks: a point inside triangle 1 and a corner of triangle 0.
    let mut p = tiny();
    p.landmarks = vec![];
    p.landmark_points = vec![
        SurfacePoint {
            face: 1,
            weights: [0.25, 0.5, 0.25],
        },
        SurfacePoint {
            face: 0,
            weights: [1.0, 0.0, 0.0],
        },
    ];
    let m = Morphable::from_parts(p.clone()).unwrap();
    assert_eq!(m.n_landmarks(), 2);
    assert_eq!(
        m.landmark_points(),
        vec![
            LandmarkPoint {
                vertices: [1, 2, 4],
                weights: [0.25, 0.5, 0.25],
            },
            LandmarkPoint {
                vertices: [0, 1, 4],
                weights: [1.0, 0.0, 0.0],
            },
        ]
    );
    let d = scratch("lmpoints");
    m.save(&d).unwrap();
    let text = std::fs::read_to_string(d.join("model.json")).unwrap();
    assert!(text.contains("\"landmark_points\"") && !text.contains("\"landmarks\""));
    let back = Morphable::<f64>::load(&d).unwrap();
    assert_eq!(back.surface_landmarks(), m.surface_landmarks());
    assert!(back.landmarks().is_empty());
    // On the tape: the weighted sum of the corners.
    let tape = autodiff::Tape::<f64>::new();
    let shape = tape.constant(m.mean_shape().into_dyn());
    let got = back.landmark_positions(shape).value().unwrap();
    let mean = m.mean_shape();
    for (i, q) in m.landmark_points().iter().enumerate() {
        let want = q.eval(mean.view());
        for k in 0..3 {
            assert!((got[[i, k]] - want[k]).abs() < 1e-12);
        }
    }

    // The scheme round-trips and must match the landmark count.
    let mut q = tiny();
    q.landmark_scheme = Some(LandmarkScheme::Ibug68);
    let e = Morphable::from_parts(q).unwrap_err();
    assert!(e.to_string().contains("ibug68"), "{e}");
    let d = saved("scheme");
    edit_json(&d, |j| j["landmark_scheme"] = "dlib5".into());
    let e = load_err(&d);
    assert!(matches!(e, ModelError::Json { .. }), "{e}");
    assert!(e.to_string().contains("dlib5") && e.to_string().contains("mediapipe468"));
    // The shipped model is MediaPipe-numbered, in memory and on disk.
    assert_eq!(
        models::face::load_default_face::<f64>()
            .unwrap()
            .landmark_scheme(),
        Some(LandmarkScheme::MediaPipe468)
    );
    assert_eq!(
        models::face::default_face::<f64>().landmark_scheme(),
        Some(LandmarkScheme::MediaPipe468)
    );

    // Bad rows: both keys, a triangle out of range, a fractional index, weights not summing to 1.
    let d = saved("both");
    edit_json(&d, |j| {
        j["landmark_points"] = serde_json::json!([[0, 1.0, 0.0, 0.0]])
    });
    let e = load_err(&d);
    assert!(e.to_string().contains("not both"), "{e}");
    for (row, needle) in [
        (serde_json::json!([[6, 1.0, 0.0, 0.0]]), "triangle index 6"),
        (serde_json::json!([[1.5, 1.0, 0.0, 0.0]]), "1.5"),
        (serde_json::json!([[1, 0.5, 0.0, 0.0]]), "sum to 1"),
    ] {
        let d = saved("badrow");
        edit_json(&d, |j| {
            j.as_object_mut().unwrap().remove("landmarks");
            j["landmark_points"] = row.clone();
        });
        let e = load_err(&d);
        let msg = e.to_string();
        assert!(
            msg.contains(needle) && msg.contains("landmark_points"),
            "{msg}"
        );
        assert_eq!(msg.lines().count(), 1, "{msg}");
    }
}
