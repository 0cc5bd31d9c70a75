//! The shipped face model: committed files vs a fresh build, orthonormality, expressions
//! (mouth opening, eye closing), regions, differentiable evaluation in f32 and f64.

use autodiff::gradcheck::{gradcheck, GradcheckOptions, Mode};
use autodiff::{tensor, Real, Tape};
use models::face::{self, exp};
use models::Morphable;
use ndarray::{Array2, ArrayView1, ArrayView2};

fn model() -> Morphable<f64> {
    face::default_face::<f64>()
}

fn zeros(n: usize) -> Vec<f64> {
    vec![0.0; n]
}

fn dist(s: &Array2<f64>, a: usize, b: usize) -> f64 {
    (0..3)
        .map(|c| (s[[a, c]] - s[[b, c]]).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn normal(s: &Array2<f64>, t: [u32; 3]) -> [f64; 3] {
    let p = |i: u32| [s[[i as usize, 0]], s[[i as usize, 1]], s[[i as usize, 2]]];
    let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ]
}

/// (triangles clearly facing the viewer at +z in `s0` that face away in `s1`,
/// triangles whose normal reverses).
fn flips(m: &Morphable<f64>, s0: &Array2<f64>, s1: &Array2<f64>) -> (usize, usize) {
    let mut front_to_back = 0;
    let mut folds = 0;
    for &t in m.faces() {
        let n0 = normal(s0, t);
        let n1 = normal(s1, t);
        let l0 = (n0[0] * n0[0] + n0[1] * n0[1] + n0[2] * n0[2]).sqrt();
        if n0[2] / l0 > 0.2 && n1[2] < 0.0 {
            front_to_back += 1;
        }
        if n0[0] * n1[0] + n0[1] * n1[1] + n0[2] * n1[2] < 0.0 {
            folds += 1;
        }
    }
    (front_to_back, folds)
}

fn with_exp(m: &Morphable<f64>, k: usize, z: f64) -> Array2<f64> {
    let mut b = zeros(m.n_exp());
    b[k] = z * m.sigma_exp()[k];
    m.eval_shape(&zeros(m.n_id()), &b).unwrap()
}

fn max_orthonormality_error(b: ArrayView2<'_, f64>) -> f64 {
    let g = b.t().dot(&b);
    let mut worst = 0.0f64;
    for ((i, j), &v) in g.indexed_iter() {
        let want = if i == j { 1.0 } else { 0.0 };
        worst = worst.max((v - want).abs());
    }
    worst
}

#[test]
fn committed_files_match_a_fresh_build() {
    let built = face::build_face_model().unwrap();
    let stored = face::load_default_face::<f64>().unwrap();
    let close2 = |what: &str, a: ArrayView2<'_, f64>, b: ArrayView2<'_, f64>| {
        assert_eq!(a.shape(), b.shape(), "{what}: shapes differ");
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for ((ix, &x), &y) in a.indexed_iter().zip(b.iter()) {
            assert!(
                (x - y).abs() <= 1e-6 * y.abs() + 1e-9 * scale,
                "{what}{ix:?}: built {x} vs committed {y} (regenerate with `cargo run -p tapestry-models --example build_face_model --release`)"
            );
        }
    };
    let close1 = |what: &str, a: ArrayView1<'_, f64>, b: ArrayView1<'_, f64>| {
        assert_eq!(a.len(), b.len(), "{what}: lengths differ");
        for (k, (&x, &y)) in a.iter().zip(b.iter()).enumerate() {
            assert!(
                (x - y).abs() <= 1e-6 * y.abs(),
                "{what}[{k}]: built {x} vs committed {y}"
            );
        }
    };
    close2(
        "mean_shape",
        built.mean_shape().view(),
        stored.mean_shape().view(),
    );
    close2("id_basis", built.id_basis(), stored.id_basis());
    close2("exp_basis", built.exp_basis(), stored.exp_basis());
    close2(
        "mean_albedo",
        built.mean_albedo().view(),
        stored.mean_albedo().view(),
    );
    close2("albedo_basis", built.albedo_basis(), stored.albedo_basis());
    close2(
        "uvs",
        built.uvs().unwrap().view(),
        stored.uvs().unwrap().view(),
    );
    close1("sigma_id", built.sigma_id(), stored.sigma_id());
    close1("sigma_exp", built.sigma_exp(), stored.sigma_exp());
    close1("sigma_albedo", built.sigma_albedo(), stored.sigma_albedo());
    assert_eq!(built.faces(), stored.faces());
    assert_eq!(built.face_regions(), stored.face_regions());
    assert_eq!(built.regions(), stored.regions());
    assert_eq!(built.landmarks(), stored.landmarks());
    assert_eq!(built.landmark_groups(), stored.landmark_groups());
    assert_eq!(built.id_names(), stored.id_names());
    assert_eq!(built.exp_names(), stored.exp_names());
    assert_eq!(built.albedo_names(), stored.albedo_names());
    assert_eq!(built.name(), stored.name());
}

#[test]
fn shipped_model_has_the_promised_size() {
    let m = model();
    assert_eq!(m.n_vertices(), 468);
    assert_eq!(m.n_faces(), 898);
    assert!(m.n_id() >= 40, "{} identity components", m.n_id());
    assert!(m.n_exp() >= 10, "{} expression components", m.n_exp());
    assert!(m.n_albedo() >= 10, "{} albedo components", m.n_albedo());
    assert_eq!(m.landmarks(), (0..468).collect::<Vec<_>>().as_slice());
    for g in [
        "lips",
        "left_eye",
        "right_eye",
        "left_eyebrow",
        "right_eyebrow",
        "face_oval",
    ] {
        assert!(m.group(g).is_some_and(|g| !g.is_empty()), "group {g}");
    }
    assert_eq!(m.exp_names()[exp::JAW_OPEN], "jaw_open");
    assert_eq!(m.exp_names()[exp::EYE_CLOSE_LEFT], "eye_close_left");
    assert_eq!(m.exp_names()[exp::EYE_CLOSE_RIGHT], "eye_close_right");
    assert_eq!(m.exp_names()[exp::SMILE], "smile");
    assert_eq!(m.exp_names()[exp::JAW_FORWARD], "jaw_forward");
    // Mean shape in millimetres: the OBJ (centimetres) times ten, about 15 cm wide.
    let s = m.mean_shape();
    let width =
        s.column(0).fold(0.0f64, |a, &b| a.max(b)) - s.column(0).fold(0.0f64, |a, &b| a.min(b));
    assert!((140.0..170.0).contains(&width), "face width {width} mm");
    // Standard deviations: plausible millimetres per vertex at one sigma.
    let table = face::component_table(&m);
    for c in &table {
        match c.kind {
            "identity" => assert!((0.5..8.0).contains(&c.peak), "{} peak {}", c.name, c.peak),
            "expression" => assert!((1.0..10.0).contains(&c.peak), "{} peak {}", c.name, c.peak),
            _ => assert!((0.005..0.3).contains(&c.peak), "{} peak {}", c.name, c.peak),
        }
    }
}

#[test]
fn stored_bases_are_orthonormal() {
    let m = face::load_default_face::<f64>().unwrap();
    for (what, b) in [
        ("id", m.id_basis()),
        ("exp", m.exp_basis()),
        ("albedo", m.albedo_basis()),
    ] {
        let e = max_orthonormality_error(b);
        assert!(e < 1e-5, "{what}: |B^T B - I| = {e}");
    }
    // The identity basis is also orthogonal to rigid motions (pose is not identity).
    let s = m.mean_shape();
    let n = m.n_vertices();
    let c = [
        0.0,
        s.column(1).mean().unwrap(),
        s.column(2).mean().unwrap(),
    ];
    for axis in 0..3 {
        let t = Array2::from_shape_fn((3 * n, 1), |(r, _)| if r % 3 == axis { 1.0 } else { 0.0 });
        let mut w = [0.0; 3];
        w[axis] = 1.0;
        let rot = Array2::from_shape_fn((3 * n, 1), |(r, _)| {
            let p = [
                s[[r / 3, 0]] - c[0],
                s[[r / 3, 1]] - c[1],
                s[[r / 3, 2]] - c[2],
            ];
            let x = [
                w[1] * p[2] - w[2] * p[1],
                w[2] * p[0] - w[0] * p[2],
                w[0] * p[1] - w[1] * p[0],
            ];
            x[r % 3]
        });
        for (what, v) in [("translation", t), ("rotation", rot)] {
            let v = &v / v.iter().map(|x| x * x).sum::<f64>().sqrt();
            let proj = m.id_basis().t().dot(&v);
            let worst = proj.iter().fold(0.0f64, |a, b| a.max(b.abs()));
            assert!(
                worst < 1e-5,
                "identity basis not orthogonal to {what} {axis}: {worst}"
            );
        }
    }
}

#[test]
fn mouth_opens_at_plus_two_sigma() {
    let m = model();
    let s0 = m.mean_shape();
    let d0 = dist(&s0, 13, 14);
    let s1 = with_exp(&m, exp::JAW_OPEN, 1.0);
    let s2 = with_exp(&m, exp::JAW_OPEN, 2.0);
    assert!(s2.iter().all(|v| v.is_finite()));
    let (d1, d2) = (dist(&s1, 13, 14), dist(&s2, 13, 14));
    assert!(
        d2 - d0 >= 10.0 && (10.0..=25.0).contains(&d2),
        "13-14: {d0:.1} mm at the mean, {d2:.1} mm at +2 sigma"
    );
    assert!(d0 < d1 && d1 < d2);
    // The lower lip goes down, the upper lip slightly up, the chin down.
    assert!(s2[[14, 1]] < s0[[14, 1]] - 7.0);
    assert!(s2[[13, 1]] > s0[[13, 1]]);
    assert!(s2[[152, 1]] < s0[[152, 1]] - 7.0);
    // The upper face stays.
    for v in [1usize, 4, 6, 10, 33, 133, 159, 263] {
        let moved = (0..3)
            .map(|c| (s2[[v, c]] - s0[[v, c]]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!(moved < 0.5, "vertex {v} moved {moved} mm");
    }
    let (ftb, folds) = flips(&m, &s0, &s2);
    assert!(
        ftb <= 2 && folds <= 2,
        "{ftb} triangles turned away, {folds} folded"
    );
}

#[test]
fn eyes_close_at_plus_two_sigma() {
    let m = model();
    let s0 = m.mean_shape();
    for (k, side, other) in [
        (exp::EYE_CLOSE_LEFT, "left", "right"),
        (exp::EYE_CLOSE_RIGHT, "right", "left"),
    ] {
        let s = with_exp(&m, k, 2.0);
        let up = m.group(&format!("{side}_eye_upper")).unwrap();
        let lo = m.group(&format!("{side}_eye_lower")).unwrap();
        for (&u, &l) in up.iter().zip(lo).skip(1).take(up.len() - 2) {
            let (g0, g) = (dist(&s0, u, l), dist(&s, u, l));
            assert!(
                g < 0.15 * g0 && g < 1.0,
                "{side} lid pair {u}/{l}: {g0:.2} -> {g:.2} mm"
            );
            // The upper lid came down onto the lower lid, not the other way.
            assert!((s[[l, 1]] - s0[[l, 1]]).abs() < 1e-9);
        }
        let up = m.group(&format!("{other}_eye_upper")).unwrap();
        for &u in up {
            assert!(
                (s[[u, 1]] - s0[[u, 1]]).abs() < 1e-9,
                "the {other} eye moved"
            );
        }
        let (ftb, folds) = flips(&m, &s0, &s);
        assert!(
            ftb <= 1 && folds <= 1,
            "{side}: {ftb} turned away, {folds} folded"
        );
    }
}

#[test]
fn every_expression_is_a_valid_mesh_at_plus_two_sigma() {
    let m = model();
    let s0 = m.mean_shape();
    for k in 0..m.n_exp() {
        let s = with_exp(&m, k, 2.0);
        assert!(s.iter().all(|v| v.is_finite()));
        let (ftb, folds) = flips(&m, &s0, &s);
        assert!(
            ftb <= 2 && folds <= 2,
            "{}: {ftb} turned away, {folds} folded",
            m.exp_names()[k]
        );
    }
}

#[test]
fn regions_label_the_openings() {
    let m = model();
    let interior = m.region_label("mouth_interior").unwrap();
    let both: Vec<usize> = (0..m.n_faces())
        .filter(|&f| m.faces()[f].contains(&13) && m.faces()[f].contains(&14))
        .collect();
    assert!(!both.is_empty());
    for f in both {
        assert_eq!(
            m.face_regions()[f],
            interior,
            "triangle {f} holds 13 and 14"
        );
    }
    let s = m.mean_shape();
    for (name, sign) in [("eye_left", 1.0), ("eye_right", -1.0)] {
        let faces = m.faces_in_region(name);
        assert!(
            (8..40).contains(&faces.len()),
            "{name}: {} triangles",
            faces.len()
        );
        let group = m
            .group(if sign > 0.0 { "left_eye" } else { "right_eye" })
            .unwrap();
        for f in faces {
            for &v in &m.faces()[f] {
                assert!(s[[v as usize, 0]] * sign > 0.0);
                assert!(
                    group.contains(&(v as usize)),
                    "eye triangle {f} has a vertex off the lid contour"
                );
            }
        }
    }
    let lips = m.faces_in_region("lips");
    assert!(lips.len() > 40);
    let lip_group = m.group("lips").unwrap();
    for f in m.faces_in_region("mouth_interior") {
        for &v in &m.faces()[f] {
            assert!(lip_group.contains(&(v as usize)));
        }
    }
    assert!(!m.faces_in_region("brows").is_empty());
    // Regions with their own albedo: the mouth interior is dark.
    let a = m.regions()[interior as usize].albedo.unwrap();
    assert!(a.iter().all(|&c| c < 0.15));
    // Lips are redder than skin, brows darker.
    let alb = m.mean_albedo();
    let lip_v = 0usize; // upper-lip midpoint
    let cheek_v = 205usize;
    let brow_v = 105usize;
    assert!(alb[[lip_v, 0]] / alb[[lip_v, 1]] > alb[[cheek_v, 0]] / alb[[cheek_v, 1]]);
    assert!(alb[[brow_v, 0]] < 0.5 * alb[[cheek_v, 0]]);
}

#[test]
fn region_split_gives_openings_their_own_colour() {
    let m = model();
    let split = m.region_split();
    assert!(split.n_vertices() > m.n_vertices());
    assert_eq!(split.faces.len(), m.n_faces());
    assert_eq!(
        &split.vertex_map[..m.n_vertices()],
        (0..m.n_vertices()).collect::<Vec<_>>().as_slice()
    );
    let interior = m.region_label("mouth_interior").unwrap();
    let colour = m.regions()[interior as usize].albedo.unwrap();
    let tape = Tape::<f64>::new();
    let gamma = tape.leaf(tensor::from_vec(&[m.n_albedo()], zeros(m.n_albedo())).unwrap());
    let alb = split.albedo(m.albedo(&tape, gamma));
    let a = alb.value().unwrap();
    for (f, t) in split.faces.iter().enumerate() {
        let copies = t.iter().all(|&v| v as usize >= m.n_vertices());
        if m.face_regions()[f] == interior {
            assert!(copies);
            for &v in t {
                for c in 0..3 {
                    assert_eq!(a[[v as usize, c]], colour[c]);
                }
            }
        } else if m.regions()[m.face_regions()[f] as usize].albedo.is_none() {
            assert_eq!(t, &m.faces()[f]);
        }
    }
    // Gradients flow to gamma only through the skin copies.
    let g = tape.backward(alb.sum()).unwrap().wrt(gamma);
    assert!(g.iter().any(|&x| x != 0.0));
    let plain = split.albedo_plain(&m.eval_albedo(&zeros(m.n_albedo())).unwrap());
    assert!(plain
        .iter()
        .zip(a.iter())
        .all(|(x, y)| (x - y).abs() < 1e-12));
}

#[test]
fn tape_and_plain_evaluation_agree() {
    let m = model();
    let mut rng = autodiff::rng::Rng::new(7);
    let a: Vec<f64> = (0..m.n_id())
        .map(|k| rng.normal() * m.sigma_id()[k])
        .collect();
    let b: Vec<f64> = (0..m.n_exp())
        .map(|k| rng.normal() * m.sigma_exp()[k])
        .collect();
    let g: Vec<f64> = (0..m.n_albedo())
        .map(|k| rng.normal() * m.sigma_albedo()[k])
        .collect();
    let tape = Tape::new();
    let av = tape.leaf(tensor::from_vec(&[a.len()], a.clone()).unwrap());
    let bv = tape.leaf(tensor::from_vec(&[b.len()], b.clone()).unwrap());
    let gv = tape.leaf(tensor::from_vec(&[g.len()], g.clone()).unwrap());
    let s = m.shape(&tape, av, bv).value().unwrap();
    let p = m.eval_shape(&a, &b).unwrap();
    assert_eq!(s.shape(), &[468, 3]);
    assert!(s.iter().zip(p.iter()).all(|(x, y)| (x - y).abs() < 1e-9));
    let al = m.albedo(&tape, gv).value().unwrap();
    let ap = m.eval_albedo(&g).unwrap();
    assert!(al.iter().zip(ap.iter()).all(|(x, y)| (x - y).abs() < 1e-12));
    // Priors: tape and plain agree; alpha = sigma gives K.
    let (pi, pe, pa) = m.eval_priors(&a, &b, &g).unwrap();
    assert!((m.id_prior(&tape, av).item().unwrap() - pi).abs() < 1e-9);
    assert!((m.exp_prior(&tape, bv).item().unwrap() - pe).abs() < 1e-9);
    assert!((m.albedo_prior(&tape, gv).item().unwrap() - pa).abs() < 1e-9);
    let sig: Vec<f64> = m.sigma_id().to_vec();
    let (k, _, _) = m
        .eval_priors(&sig, &zeros(m.n_exp()), &zeros(m.n_albedo()))
        .unwrap();
    assert!((k - m.n_id() as f64).abs() < 1e-9);
    // Standardised parametrisation.
    let z: Vec<f64> = a.iter().zip(m.sigma_id()).map(|(x, s)| x / s).collect();
    let w: Vec<f64> = b.iter().zip(m.sigma_exp()).map(|(x, s)| x / s).collect();
    let zs = m.eval_shape_standardized(&z, &w).unwrap();
    assert!(zs.iter().zip(p.iter()).all(|(x, y)| (x - y).abs() < 1e-9));
    let zv = tape.leaf(tensor::from_vec(&[z.len()], z).unwrap());
    let wv = tape.leaf(tensor::from_vec(&[w.len()], w).unwrap());
    let st = m.shape_standardized(&tape, zv, wv).value().unwrap();
    assert!(st.iter().zip(p.iter()).all(|(x, y)| (x - y).abs() < 1e-9));
    // Landmarks are vertices.
    let lm = m
        .landmark_positions(m.shape(&tape, av, bv))
        .value()
        .unwrap();
    assert_eq!(lm.shape(), &[468, 3]);
    assert_eq!(lm[[14, 1]], s[[14, 1]]);
    // Wrong lengths are errors, not panics.
    assert!(m.eval_shape(&a[1..], &b).is_err());
    let short = tape.leaf(tensor::from_vec(&[3], vec![0.0; 3]).unwrap());
    assert!(m.shape(&tape, short, bv).value().is_err());
}

fn sub_input(n: usize, seed: u64, scale: f64) -> ndarray::ArrayD<f64> {
    let mut rng = autodiff::rng::Rng::new(seed);
    tensor::from_vec(&[n], (0..n).map(|_| rng.normal() * scale).collect()).unwrap()
}

#[test]
fn gradcheck_shape_and_albedo_in_f64() {
    let m = model();
    // Full Jacobian on a truncated model and a subset of vertices (fast)...
    let t = m.truncated(6, 4, 3);
    let pick: Vec<usize> = vec![0, 13, 14, 33, 61, 152, 263, 291, 386, 454];
    let opts = GradcheckOptions {
        eps: 1e-4,
        ..GradcheckOptions::default()
    };
    let inputs = [
        sub_input(6, 1, 10.0),
        sub_input(4, 2, 10.0),
        sub_input(3, 3, 0.3),
    ];
    let r = gradcheck(
        |tape, v| {
            let s = t.shape(tape, v[0], v[1]).index_select(0, &pick);
            let a = t.albedo(tape, v[2]).index_select(0, &pick);
            tape.concat(&[s, a], 1) * (s.sum() * 1e-3).sin()
        },
        &inputs,
        &opts,
    )
    .unwrap();
    assert!(r.passed(), "{r}");
    // ... and random directional checks of the whole model, priors included.
    let inputs = [
        sub_input(m.n_id(), 4, 5.0),
        sub_input(m.n_exp(), 5, 5.0),
        sub_input(m.n_albedo(), 6, 0.2),
        sub_input(m.n_id(), 7, 1.0),
    ];
    let opts = GradcheckOptions {
        eps: 1e-4,
        mode: Mode::Fast { seed: 11 },
        ..GradcheckOptions::default()
    };
    let r = gradcheck(
        |tape, v| {
            let s = m.shape(tape, v[0], v[1]);
            let a = m.albedo(tape, v[2]);
            let z = m.shape_standardized(tape, v[3], v[1]);
            (s * a).square().sum() * 1e-6
                + z.sin().sum()
                + m.id_prior(tape, v[0])
                + m.exp_prior(tape, v[1])
                + m.albedo_prior(tape, v[2])
        },
        &inputs,
        &opts,
    )
    .unwrap();
    assert!(r.passed(), "{r}");
}

fn eval_in<T: Real>(m: &Morphable<T>, z: f64) -> (Vec<f64>, Vec<f64>) {
    let tape = Tape::<T>::new();
    let mut a = vec![T::zero(); m.n_id()];
    a[0] = T::from_f64c(z * m.sigma_id()[0].to_f64c());
    let mut b = vec![T::zero(); m.n_exp()];
    b[exp::JAW_OPEN] = T::from_f64c(z * m.sigma_exp()[exp::JAW_OPEN].to_f64c());
    let av = tape.leaf(tensor::from_vec(&[a.len()], a).unwrap());
    let bv = tape.leaf(tensor::from_vec(&[b.len()], b).unwrap());
    let s = m.shape(&tape, av, bv);
    let loss = s.square().sum() + m.id_prior(&tape, av);
    let g = tape.backward(loss).unwrap();
    let vals = s.value().unwrap().iter().map(|v| v.to_f64c()).collect();
    let grads = g.wrt(av).iter().map(|v| v.to_f64c()).collect();
    (vals, grads)
}

#[test]
fn f32_and_f64_agree() {
    let m64 = model();
    let m32 = face::default_face::<f32>();
    let (v64, g64) = eval_in(&m64, 1.5);
    let (v32, g32) = eval_in(&m32, 1.5);
    let rel = |a: &[f64], b: &[f64]| {
        let s = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        a.iter()
            .zip(b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
            / s
    };
    assert!(rel(&v32, &v64) < 1e-5, "values {}", rel(&v32, &v64));
    assert!(rel(&g32, &g64) < 1e-4, "gradients {}", rel(&g32, &g64));
}
