#![allow(clippy::cloned_ref_to_slice_refs, clippy::needless_range_loop)]
//! Shading and texturing: gradient checks of every op, fused against composed forms, hard
//! cases, and inverse tasks (texture and SH recovery).

use std::sync::Arc;

use autodiff::gradcheck::{gradcheck, GradcheckOptions, GradcheckReport};
use autodiff::rng::Rng;
use autodiff::{Tape, Tensor, Var};
use ndarray::{ArrayD, IxDyn};
use render_ops::camera::Camera;
use render_ops::raster::RasterSettings;
use render_ops::rasterize::{rasterize, Rasterized};
use render_ops::shade::{
    depth_map, ncc, normal_map, pncc, render_shader, run_shader, uv_derivatives, FragmentInputs,
    MeshAttributes, ShLight,
};
use render_ops::shade::{
    face_normals, face_normals_composed, sh_shade, sh_shade_composed, shade, shade_composed,
    vertex_normals, vertex_normals_composed, AmbientLight, DirectionalLight, Lights, Material,
    PointLight, Reflectance, Surface,
};
use render_ops::texture::{sample, sample_composed, Filter, Sampler, Texture, Wrap};
use render_ops::transform::to_clip;

type Build = for<'t> fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>;

fn t(shape: &[usize], data: Vec<f64>) -> Tensor<f64> {
    ArrayD::from_shape_vec(IxDyn(shape), data).unwrap()
}

/// Pins a closure to the higher-ranked signature of a gradient-checked function.
fn hr<F: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>>(f: F) -> F {
    f
}

fn check(name: &str, rep: GradcheckReport) {
    assert!(rep.passed(), "{name}: gradcheck failed\n{rep}");
}

fn max_diff(a: &Tensor<f64>, b: &Tensor<f64>) -> f64 {
    assert_eq!(a.shape(), b.shape());
    a.iter()
        .zip(b.iter())
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
}

/// Fused and composed agree in value and in the gradient of a random projection of the
/// output, with respect to every input, to `tol`.
fn agree(name: &str, fused: Build, composed: Build, inputs: &[Tensor<f64>], tol: f64) {
    let run = |f: Build| {
        let tape = Tape::new();
        let vars: Vec<_> = inputs.iter().map(|x| tape.leaf(x.clone())).collect();
        let y = f(&tape, &vars);
        let yv = (*y.value().unwrap()).clone();
        let w = Rng::new(99).normal_tensor::<f64>(yv.shape());
        let g = tape.vjp(y, w).unwrap();
        let gs: Vec<Tensor<f64>> = vars.iter().map(|&v| g.wrt(v)).collect();
        (yv, gs)
    };
    let (ya, ga) = run(fused);
    let (yb, gb) = run(composed);
    let dv = max_diff(&ya, &yb);
    assert!(dv <= tol, "{name}: values differ by {dv:e}");
    assert!(ya.iter().all(|v| v.is_finite()), "{name}: non-finite value");
    for (k, (a, b)) in ga.iter().zip(&gb).enumerate() {
        let d = max_diff(a, b);
        let scale = b.iter().fold(1.0f64, |m, v| m.max(v.abs()));
        assert!(
            d <= tol * scale,
            "{name}: gradient of input {k} differs by {d:e} (scale {scale:e})"
        );
        assert!(
            a.iter().all(|v| v.is_finite()),
            "{name}: non-finite gradient of input {k}"
        );
    }
}

// ---------------------------------------------------------------- normals

fn mesh_inputs() -> (Tensor<f64>, Arc<Vec<[u32; 3]>>) {
    // A perturbed octahedron plus one isolated vertex (index 6).
    let mut rng = Rng::new(5);
    let base = [
        [1.0, 0.0, 0.0],
        [-1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
        [3.0, 3.0, 3.0],
    ];
    let p: Vec<f64> = base
        .iter()
        .flatten()
        .map(|&x| x + rng.uniform(-0.2, 0.2))
        .collect();
    let faces = vec![
        [0, 2, 4],
        [2, 1, 4],
        [1, 3, 4],
        [3, 0, 4],
        [2, 0, 5],
        [1, 2, 5],
        [3, 1, 5],
        [0, 3, 5],
    ];
    (t(&[7, 3], p), Arc::new(faces))
}

thread_local! {
    static FACES: Arc<Vec<[u32; 3]>> = mesh_inputs().1;
}

fn faces() -> Arc<Vec<[u32; 3]>> {
    FACES.with(|f| f.clone())
}

#[test]
fn normals_gradcheck_and_agree() {
    let (p, _) = mesh_inputs();
    let opts = GradcheckOptions::default();
    check(
        "face_normals",
        gradcheck(
            |_t: &Tape<f64>, v| face_normals(v[0], &faces()),
            &[p.clone()],
            &opts,
        )
        .unwrap(),
    );
    check(
        "vertex_normals",
        gradcheck(
            |_t: &Tape<f64>, v| vertex_normals(v[0], &faces()),
            &[p.clone()],
            &opts,
        )
        .unwrap(),
    );
    agree(
        "face_normals",
        |_t, v| face_normals(v[0], &faces()),
        |_t, v| face_normals_composed(v[0], &faces()),
        &[p.clone()],
        1e-10,
    );
    agree(
        "vertex_normals",
        |_t, v| vertex_normals(v[0], &faces()),
        |_t, v| vertex_normals_composed(v[0], &faces()),
        &[p.clone()],
        1e-10,
    );
    // Outward, unit, and the isolated vertex is (0, 0, 0).
    let tape = Tape::<f64>::new();
    let n = vertex_normals(tape.constant(p.clone()), &faces())
        .value()
        .unwrap();
    for v in 0..6 {
        let row: Vec<f64> = (0..3).map(|k| n[[v, k]]).collect();
        let len = row.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!((len - 1.0).abs() < 1e-12);
        let dot: f64 = (0..3).map(|k| row[k] * p[[v, k]]).sum();
        assert!(dot > 0.5, "vertex {v} normal points inwards");
    }
    assert_eq!((0..3).map(|k| n[[6, k]]).collect::<Vec<_>>(), vec![0.0; 3]);
}

#[test]
fn zero_length_normals_are_safe() {
    // A degenerate face (collinear points) and a repeated vertex.
    let p = t(
        &[4, 3],
        vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    let faces = Arc::new(vec![[0u32, 1, 2], [0, 3, 1]]);
    let tape = Tape::<f64>::new();
    let pv = tape.leaf(p);
    let fnrm = face_normals(pv, &faces);
    let vnrm = vertex_normals(pv, &faces);
    for v in [fnrm, vnrm] {
        let val = v.value().unwrap();
        assert!(
            val.iter().all(|&x| x == 0.0),
            "degenerate normals must be zero: {val:?}"
        );
    }
    let loss = (fnrm.sum() + vnrm.sum()) * 1.0;
    let g = tape.backward(loss).unwrap().wrt(pv);
    assert!(g.iter().all(|x| x.is_finite()));
    // Shading with zero normals: finite values and gradients in every model.
    let n = 4;
    let tape = Tape::<f64>::new();
    let normal = tape.leaf(ArrayD::zeros(IxDyn(&[n, 3])));
    let pos = tape.leaf(Rng::new(1).uniform_tensor(&[n, 3], -1.0, 1.0));
    let albedo = tape.leaf(ArrayD::from_elem(IxDyn(&[n, 3]), 0.5));
    let eye = tape.leaf(t(&[3], vec![0.0, 0.0, 4.0]));
    let lights = Lights::new()
        .with_directional(DirectionalLight::constant(
            &tape,
            [0.0, 0.0, -1.0],
            [1.0, 1.0, 1.0],
        ))
        .with_point(PointLight::constant(
            &tape,
            [1.0, 2.0, 3.0],
            [1.0, 0.5, 0.2],
        ))
        .with_ambient(AmbientLight::constant(&tape, [0.1, 0.1, 0.1]));
    let surf = Surface {
        position: pos,
        normal,
        albedo,
        visibility: None,
    };
    let coeffs = tape.leaf(Rng::new(2).normal_tensor(&[9, 3]));
    let mut total = sh_shade(normal, albedo, coeffs).sum();
    for model in [
        Reflectance::Lambert,
        Reflectance::Phong,
        Reflectance::BlinnPhong,
    ] {
        let m = Material::constant(&tape, model, [0.3; 3], 20.0);
        total = total
            + shade(&surf, &m, &lights, eye).sum()
            + shade_composed(&surf, &m, &lights, eye).sum();
    }
    let val = total.item().unwrap();
    assert!(val.is_finite());
    let g = tape.backward(total).unwrap();
    for v in [normal, pos, albedo, eye, coeffs] {
        assert!(g.wrt(v).iter().all(|x| x.is_finite()));
    }
}

// ---------------------------------------------------------------- reflection models

const NF: usize = 12;

/// Positions, normals and albedo of `NF` fragments, with every light at least 0.05 away from
/// the kinks (`n . l = 0`, specular base = 0), plus the shared parameters.
fn phong_inputs() -> Vec<Tensor<f64>> {
    let mut rng = Rng::new(11);
    let eye = [0.3, -0.2, 4.0];
    let dirs = [[0.2, -0.3, -1.0], [-1.0, 0.4, -0.3]];
    let q = [1.5, 2.0, 2.5];
    let unit = |v: [f64; 3]| {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / l, v[1] / l, v[2] / l]
    };
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (mut pos, mut nrm) = (Vec::new(), Vec::new());
    while pos.len() < 3 * NF {
        let x = [
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-1.0, 1.0),
        ];
        let nr = [rng.normal(), rng.normal(), rng.normal() + 1.0];
        let n = unit(nr);
        let v = unit([eye[0] - x[0], eye[1] - x[1], eye[2] - x[2]]);
        let mut ls: Vec<[f64; 3]> = dirs.iter().map(|d| unit([-d[0], -d[1], -d[2]])).collect();
        ls.push(unit([q[0] - x[0], q[1] - x[1], q[2] - x[2]]));
        let ok = ls.iter().all(|&l| {
            let ndl = dot(n, l);
            let r = [
                2.0 * ndl * n[0] - l[0],
                2.0 * ndl * n[1] - l[1],
                2.0 * ndl * n[2] - l[2],
            ];
            let h = unit([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
            ndl.abs() > 0.05 && (ndl < 0.0 || (dot(r, v).abs() > 0.05 && dot(n, h).abs() > 0.05))
        });
        if ok {
            pos.extend(x);
            // Not unit length: the models normalise.
            nrm.extend(nr.map(|c| c * 1.7));
        }
    }
    let albedo = rng.uniform_tensor(&[NF, 3], 0.2, 1.0);
    vec![
        t(&[NF, 3], pos),
        t(&[NF, 3], nrm),
        albedo,
        t(&[3], vec![0.3, 0.2, 0.25]), // ka
        t(&[3], vec![0.5, 0.4, 0.3]),  // ks
        t(&[], vec![6.0]),             // shininess
        t(&[3], eye.to_vec()),         // eye
        t(&[3], vec![0.1, 0.15, 0.2]), // ambient
        t(&[3], dirs[0].to_vec()),
        t(&[3], vec![0.9, 0.8, 0.7]),
        t(&[3], dirs[1].to_vec()),
        t(&[3], vec![0.3, 0.5, 0.6]),
        t(&[3], q.to_vec()),
        t(&[3], vec![0.6, 0.6, 0.4]),
    ]
}

/// The reflection model on `phong_inputs` (ka from the inputs when `own_ka`).
fn phong_with<'t>(
    model: Reflectance,
    fused: bool,
    own_ka: bool,
    v: &[Var<'t, f64>],
) -> Var<'t, f64> {
    let surf = Surface {
        position: v[0],
        normal: v[1],
        albedo: v[2],
        visibility: None,
    };
    let mat = Material {
        model,
        ka: own_ka.then_some(v[3]),
        ks: v[4],
        shininess: v[5],
    };
    let lights = Lights::new()
        .with_ambient(AmbientLight { color: v[7] })
        .with_directional(DirectionalLight {
            direction: v[8],
            color: v[9],
        })
        .with_directional(DirectionalLight {
            direction: v[10],
            color: v[11],
        })
        .with_point(PointLight {
            position: v[12],
            color: v[13],
        });
    if fused {
        shade(&surf, &mat, &lights, v[6])
    } else {
        shade_composed(&surf, &mat, &lights, v[6])
    }
}

#[test]
fn reflection_models_gradcheck() {
    let inputs = phong_inputs();
    let opts = GradcheckOptions::default();
    let cases: [(&str, Build); 4] = [
        ("lambert", |_t, v| {
            phong_with(Reflectance::Lambert, true, true, v)
        }),
        ("phong", |_t, v| {
            phong_with(Reflectance::Phong, true, true, v)
        }),
        ("blinn_phong", |_t, v| {
            phong_with(Reflectance::BlinnPhong, true, true, v)
        }),
        ("blinn_phong/ka=albedo", |_t, v| {
            phong_with(Reflectance::BlinnPhong, true, false, v)
        }),
    ];
    for (name, f) in cases {
        let rep = gradcheck(f, &inputs, &opts).unwrap();
        check(name, rep);
    }
    // The specular parameters really get gradients.
    let tape = Tape::new();
    let vars: Vec<_> = inputs.iter().map(|x| tape.leaf(x.clone())).collect();
    let g = tape
        .backward(phong_with(Reflectance::Phong, true, true, &vars).sum())
        .unwrap();
    assert!(g.wrt(vars[5])[[]].abs() > 1e-6, "no shininess gradient");
    assert!(
        g.wrt(vars[4]).iter().all(|x| x.abs() > 1e-6),
        "no ks gradient"
    );
}

#[test]
fn reflection_models_fused_equal_composed() {
    let inputs = phong_inputs();
    let cases: [(&str, Build, Build); 6] = [
        (
            "lambert",
            |_t, v| phong_with(Reflectance::Lambert, true, true, v),
            |_t, v| phong_with(Reflectance::Lambert, false, true, v),
        ),
        (
            "phong",
            |_t, v| phong_with(Reflectance::Phong, true, true, v),
            |_t, v| phong_with(Reflectance::Phong, false, true, v),
        ),
        (
            "blinn",
            |_t, v| phong_with(Reflectance::BlinnPhong, true, true, v),
            |_t, v| phong_with(Reflectance::BlinnPhong, false, true, v),
        ),
        (
            "lambert/ka=albedo",
            |_t, v| phong_with(Reflectance::Lambert, true, false, v),
            |_t, v| phong_with(Reflectance::Lambert, false, false, v),
        ),
        (
            "phong/ka=albedo",
            |_t, v| phong_with(Reflectance::Phong, true, false, v),
            |_t, v| phong_with(Reflectance::Phong, false, false, v),
        ),
        (
            "blinn/ka=albedo",
            |_t, v| phong_with(Reflectance::BlinnPhong, true, false, v),
            |_t, v| phong_with(Reflectance::BlinnPhong, false, false, v),
        ),
    ];
    for (name, a, b) in cases {
        agree(name, a, b, &inputs, 1e-10);
    }
    // Shared albedo [3] and per-fragment ks [N, 3].
    let mut swapped = inputs.clone();
    swapped[2] = t(&[3], vec![0.7, 0.6, 0.5]);
    swapped[4] = Rng::new(3).uniform_tensor(&[NF, 3], 0.1, 0.6);
    agree(
        "phong/shared albedo",
        |_t, v| phong_with(Reflectance::Phong, true, true, v),
        |_t, v| phong_with(Reflectance::Phong, false, true, v),
        &swapped,
        1e-10,
    );
    agree(
        "blinn/shared albedo",
        |_t, v| phong_with(Reflectance::BlinnPhong, true, false, v),
        |_t, v| phong_with(Reflectance::BlinnPhong, false, false, v),
        &swapped,
        1e-10,
    );
}

/// The composed Phong family and SH use only ops the tape fuses, so the entry points `shade`
/// and `sh_shade` (the composed code inside `Tape::fused`) record ONE fused op for a model's
/// per-fragment work (no mask read from a value, no concat or matrix product ending the
/// region), which agrees with the eager composed graph and passes gradcheck. (SH's coefficient
/// rows are sliced on the tape before the region: ops on 27 numbers, not recorded when the
/// coefficients are constants, as in the count below.)
#[test]
fn shading_models_are_one_fused_op() {
    /// Ops recorded by `f`, with the inputs numbered in `constant` as constants.
    fn ops_of(f: Build, inputs: &[Tensor<f64>], constant: &[usize]) -> usize {
        let tape = Tape::new();
        let vars: Vec<_> = inputs
            .iter()
            .enumerate()
            .map(|(i, x)| tape.var(x.clone(), !constant.contains(&i)))
            .collect();
        let before = tape.num_ops();
        let y = f(&tape, &vars);
        tape.materialize(&[y]);
        tape.num_ops() - before
    }
    let inputs = phong_inputs();
    let cases: [(&str, Build, Build); 3] = [
        (
            "lambert",
            |_t, v| phong_with(Reflectance::Lambert, true, true, v),
            |_t, v| phong_with(Reflectance::Lambert, false, true, v),
        ),
        (
            "phong",
            |_t, v| phong_with(Reflectance::Phong, true, true, v),
            |_t, v| phong_with(Reflectance::Phong, false, true, v),
        ),
        (
            "blinn/ka=albedo",
            |_t, v| phong_with(Reflectance::BlinnPhong, true, false, v),
            |_t, v| phong_with(Reflectance::BlinnPhong, false, false, v),
        ),
    ];
    let opts = GradcheckOptions::default();
    for (name, entry, eager) in cases {
        let n_fused = ops_of(entry, &inputs, &[]);
        assert_eq!(n_fused, 1, "{name}: {n_fused} ops in the fused region");
        agree(name, entry, eager, &inputs, 1e-10);
        check(name, gradcheck(entry, &inputs, &opts).unwrap());
    }
    let sh: (Build, Build) = (
        |_t, v| sh_shade(v[0], v[1], v[2]),
        |_t, v| sh_shade_composed(v[0], v[1], v[2]),
    );
    for shared in [false, true] {
        let inputs = sh_inputs(shared);
        assert_eq!(
            ops_of(sh.0, &inputs, &[2]),
            1,
            "sh (shared albedo {shared})"
        );
        agree("sh", sh.0, sh.1, &inputs, 1e-10);
        check("sh", gradcheck(sh.0, &inputs, &opts).unwrap());
    }
}

/// Inputs of the wrong shape give an error naming them (not a broadcast that happens to fit).
#[test]
fn shading_rejects_bad_shapes() {
    let tape = Tape::<f64>::new();
    let rows = |n: usize| tape.constant(ArrayD::zeros(IxDyn(&[n, 3])));
    let err = |y: Var<'_, f64>| y.value().unwrap_err().to_string();
    let lights = Lights::new().with_directional(DirectionalLight::constant(
        &tape,
        [0.0, 0.0, -1.0],
        [1.0; 3],
    ));
    let m = Material::constant(&tape, Reflectance::Phong, [0.3; 3], 8.0);
    let eye = tape.constant(ArrayD::zeros(IxDyn(&[3])));
    let surf = |p, n, a| Surface {
        position: p,
        normal: n,
        albedo: a,
        visibility: None,
    };
    let e = err(shade(
        &surf(tape.constant(ArrayD::zeros(IxDyn(&[3]))), rows(4), rows(4)),
        &m,
        &lights,
        eye,
    ));
    assert!(e.contains("positions must be [N, 3]"), "{e}");
    let tape = Tape::<f64>::new();
    let rows = |n: usize| tape.constant(ArrayD::zeros(IxDyn(&[n, 3])));
    let m = Material::constant(&tape, Reflectance::Phong, [0.3; 3], 8.0);
    let eye = tape.constant(ArrayD::zeros(IxDyn(&[3])));
    let lights = Lights::new();
    let e = err(shade(&surf(rows(4), rows(5), rows(4)), &m, &lights, eye));
    assert!(e.contains("normals must be [4, 3]"), "{e}");
    let tape = Tape::<f64>::new();
    let rows = |n: usize| tape.constant(ArrayD::zeros(IxDyn(&[n, 3])));
    let m = Material::constant(&tape, Reflectance::Phong, [0.3; 3], 8.0);
    let eye = tape.constant(ArrayD::zeros(IxDyn(&[2])));
    let e = err(shade(
        &surf(rows(4), rows(4), rows(4)),
        &m,
        &Lights::new(),
        eye,
    ));
    assert!(e.contains("eye must be [3]"), "{e}");
    let tape = Tape::<f64>::new();
    let rows = |n: usize| tape.constant(ArrayD::zeros(IxDyn(&[n, 3])));
    let e = err(sh_shade(
        rows(4),
        rows(4),
        tape.constant(ArrayD::zeros(IxDyn(&[9, 2]))),
    ));
    assert!(e.contains("SH coefficients must be [9, 3]"), "{e}");
    let tape = Tape::<f64>::new();
    let rows = |n: usize| tape.constant(ArrayD::zeros(IxDyn(&[n, 3])));
    let e = err(sh_shade(rows(4), rows(2), rows(9)));
    assert!(e.contains("albedo must be [4, 3] or [3]"), "{e}");
}

#[test]
fn grazing_light_and_huge_shininess() {
    // Light exactly and nearly tangent to the surface: finite values and gradients, diffuse
    // term exactly 0 at tangency, fused and composed agree.
    let mut inputs = phong_inputs();
    let n = 4;
    inputs[0] = t(&[n, 3], vec![0.0; 3 * n]);
    inputs[1] = t(
        &[n, 3],
        vec![
            0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 1e-9, 1.0, 0.0, -1e-3, 1.0,
        ],
    );
    inputs[2] = t(&[n, 3], vec![0.5; 3 * n]);
    inputs[8] = t(&[3], vec![-1.0, 0.0, 0.0]); // travels along -x: grazing for normal +z
    inputs[10] = t(&[3], vec![0.0, -1.0, 1e-6]);
    inputs[12] = t(&[3], vec![5.0, 0.0, 0.0]);
    for s in [1.0, 100.0, 1e4] {
        inputs[5] = t(&[], vec![s]);
        for model in [
            Reflectance::Lambert,
            Reflectance::Phong,
            Reflectance::BlinnPhong,
        ] {
            let tape = Tape::new();
            let vars: Vec<_> = inputs.iter().map(|x| tape.leaf(x.clone())).collect();
            let (fu, co) = (
                phong_with(model, true, true, &vars),
                phong_with(model, false, true, &vars),
            );
            let (a, b) = (fu.value().unwrap(), co.value().unwrap());
            assert!(max_diff(&a, &b) < 1e-12, "{model:?} s={s}");
            assert!(a.iter().all(|x| x.is_finite()));
            let g = tape.backward(fu.sum() + co.sum()).unwrap();
            for (k, v) in vars.iter().enumerate() {
                assert!(
                    g.wrt(*v).iter().all(|x| x.is_finite()),
                    "{model:?} s={s}: input {k}"
                );
            }
        }
    }
    // Shininess 1e4 near the mirror direction: the highlight is a narrow, finite peak, and its
    // gradients check (a tiny shininess step: the exponent amplifies it).
    let eye = [0.0, 0.0, 5.0];
    let mk = |tilt: f64| {
        let mut inp = phong_inputs();
        inp[0] = t(&[2, 3], vec![0.0; 6]);
        inp[1] = t(&[2, 3], vec![0.0, tilt, 1.0, tilt * 0.5, 0.0, 1.0]);
        inp[2] = t(&[2, 3], vec![0.5; 6]);
        inp[5] = t(&[], vec![1e4]);
        inp[6] = t(&[3], eye.to_vec());
        inp[8] = t(&[3], vec![0.0, 0.0, -1.0]);
        inp[10] = t(&[3], vec![0.0, 0.01, -1.0]);
        inp[12] = t(&[3], vec![0.0, 0.0, 50.0]);
        inp
    };
    let inputs = mk(3e-3);
    let opts = GradcheckOptions {
        eps: 1e-8,
        atol: 1e-4,
        rtol: 1e-3,
        ..GradcheckOptions::default()
    };
    check(
        "phong/s=1e4",
        gradcheck(
            |_t: &Tape<f64>, v| phong_with(Reflectance::Phong, true, true, v),
            &inputs,
            &opts,
        )
        .unwrap(),
    );
    check(
        "blinn/s=1e4",
        gradcheck(
            |_t: &Tape<f64>, v| phong_with(Reflectance::BlinnPhong, true, true, v),
            &inputs,
            &opts,
        )
        .unwrap(),
    );
    agree(
        "phong/s=1e4",
        |_t, v| phong_with(Reflectance::Phong, true, true, v),
        |_t, v| phong_with(Reflectance::Phong, false, true, v),
        &inputs,
        1e-10,
    );
    agree(
        "blinn/s=1e4",
        |_t, v| phong_with(Reflectance::BlinnPhong, true, true, v),
        |_t, v| phong_with(Reflectance::BlinnPhong, false, true, v),
        &inputs,
        1e-10,
    );
}

// ---------------------------------------------------------------- spherical harmonics

fn sh_inputs(shared_albedo: bool) -> Vec<Tensor<f64>> {
    let mut rng = Rng::new(21);
    vec![
        rng.normal_tensor(&[NF, 3]),
        if shared_albedo {
            t(&[3], vec![0.8, 0.6, 0.4])
        } else {
            rng.uniform_tensor(&[NF, 3], 0.2, 1.0)
        },
        rng.normal_tensor(&[9, 3]),
    ]
}

#[test]
fn sh_gradcheck_and_agree() {
    let opts = GradcheckOptions::default();
    for shared in [false, true] {
        let inputs = sh_inputs(shared);
        check(
            "sh_shade",
            gradcheck(
                |_t: &Tape<f64>, v| sh_shade(v[0], v[1], v[2]),
                &inputs,
                &opts,
            )
            .unwrap(),
        );
        agree(
            "sh_shade",
            |_t, v| sh_shade(v[0], v[1], v[2]),
            |_t, v| sh_shade_composed(v[0], v[1], v[2]),
            &inputs,
            1e-10,
        );
    }
    // The basis as in docs/CONVENTIONS.md: n = +z with only coefficient 6 (Y_20) set to 1 gives
    // 0.315392 * 2 times the albedo.
    let tape = Tape::<f64>::new();
    let mut c = ArrayD::zeros(IxDyn(&[9, 3]));
    c[[6, 0]] = 1.0;
    c[[2, 1]] = 1.0;
    c[[0, 2]] = 1.0;
    let y = sh_shade(
        tape.constant(t(&[1, 3], vec![0.0, 0.0, 2.0])),
        tape.constant(t(&[3], vec![1.0, 1.0, 1.0])),
        tape.constant(c),
    )
    .value()
    .unwrap();
    assert_eq!(
        y.iter().copied().collect::<Vec<_>>(),
        vec![0.315392 * 2.0, 0.488603, 0.282095]
    );
}

// ---------------------------------------------------------------- textures

/// uv in `[-3, 4)` with every level's bilinear fractions at least 0.02 from a kink, and uv
/// derivatives giving LODs with fractional parts in [0.2, 0.8] (rx > 2 ry: no max tie).
fn tex_inputs(h: usize, w: usize, c: usize, n: usize, seed: u64) -> Vec<Tensor<f64>> {
    let mut rng = Rng::new(seed);
    let texels = rng.uniform_tensor(&[h, w, c], 0.0, 1.0);
    let sizes = render_ops::texture::mip_sizes(h, w);
    let frac = |x: f64| x - x.floor();
    let mut uv = Vec::new();
    while uv.len() < 2 * n {
        let (u, v) = (rng.uniform(-3.0, 4.0), rng.uniform(-3.0, 4.0));
        let ok = sizes.iter().all(|&(hh, ww)| {
            let fx = frac(u * ww as f64 - 0.5);
            let fy = frac((1.0 - v) * hh as f64 - 0.5);
            let fnx = frac(u * ww as f64);
            let fny = frac((1.0 - v) * hh as f64);
            [fx, fy, fnx, fny].iter().all(|&f| f > 0.02 && f < 0.98)
        });
        if ok {
            uv.extend([u, v]);
        }
    }
    let top = (sizes.len() - 1) as f64;
    let mut da = Vec::new();
    for i in 0..n {
        // Spread the LODs over magnification, every level and beyond the coarsest.
        let lam = if top == 0.0 {
            0.3
        } else {
            (i % (sizes.len() + 1)) as f64 - 0.5 + rng.uniform(0.2, 0.8)
        };
        let rho = 2f64.powf(lam);
        let a = rng.uniform(0.0, std::f64::consts::TAU);
        let b = a + 1.3;
        da.extend([
            rho * a.cos() / w as f64,
            rho * a.sin() / h as f64,
            0.6 * rho * b.cos() / w as f64,
            0.6 * rho * b.sin() / h as f64,
        ]);
    }
    vec![texels, t(&[n, 2], uv), t(&[n, 4], da)]
}

fn sampler_cases() -> Vec<Sampler> {
    let mut v = Vec::new();
    for filter in [Filter::Nearest, Filter::Bilinear, Filter::Trilinear] {
        for wrap in [Wrap::Repeat, Wrap::Clamp, Wrap::Mirror] {
            v.push(Sampler::new(filter, wrap));
        }
    }
    v
}

thread_local! {
    static SAMPLER: std::cell::Cell<Sampler> = std::cell::Cell::new(Sampler::default());
}

fn tex_fused<'t>(_t: &'t Tape<f64>, v: &[Var<'t, f64>]) -> Var<'t, f64> {
    sample(v[0], v[1], Some(v[2]), SAMPLER.with(|s| s.get()))
}

fn tex_composed<'t>(_t: &'t Tape<f64>, v: &[Var<'t, f64>]) -> Var<'t, f64> {
    sample_composed(v[0], v[1], Some(v[2]), SAMPLER.with(|s| s.get()))
}

#[test]
fn texture_gradcheck_and_agree() {
    let opts = GradcheckOptions::default();
    for (h, w, c) in [(6, 7, 2), (8, 8, 1), (1, 1, 3), (1, 5, 2), (12, 10, 3)] {
        let inputs = tex_inputs(h, w, c, 14, (h * 31 + w) as u64);
        for s in sampler_cases() {
            SAMPLER.with(|c| c.set(s));
            let name = format!("texture {s:?} {h}x{w}x{c}");
            let rep = gradcheck(tex_fused, &inputs, &opts).unwrap();
            assert!(rep.passed(), "{name}\n{rep}");
            agree(&name, tex_fused, tex_composed, &inputs, 1e-10);
        }
    }
    // Trilinear really uses several levels and passes gradients to the uv derivatives.
    let inputs = tex_inputs(12, 10, 3, 14, 7);
    SAMPLER.with(|c| c.set(Sampler::new(Filter::Trilinear, Wrap::Repeat)));
    let tape = Tape::new();
    let v: Vec<_> = inputs.iter().map(|x| tape.leaf(x.clone())).collect();
    let g = tape.backward(tex_fused(&tape, &v).sum()).unwrap();
    let gda = g.wrt(v[2]);
    assert!(
        gda.iter().filter(|x| x.abs() > 1e-8).count() >= 10,
        "{gda:?}"
    );
}

#[test]
fn texture_texel_gradient_is_deterministic() {
    let inputs = tex_inputs(32, 24, 3, 5000, 9);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let tape = Tape::<f32>::new();
                let cast = |x: &Tensor<f64>| x.mapv(|v| v as f32);
                let tex = tape.leaf(cast(&inputs[0]));
                let uv = tape.leaf(cast(&inputs[1]));
                let da = tape.leaf(cast(&inputs[2]));
                let w = tape.constant(Rng::new(4).normal_tensor(&[5000, 3]));
                let y = sample(
                    tex,
                    uv,
                    Some(da),
                    Sampler::new(Filter::Trilinear, Wrap::Mirror),
                );
                let g = tape.backward((y * w).sum()).unwrap();
                (g.wrt(tex), g.wrt(uv), g.wrt(da))
            })
    };
    let (a, b) = (run(1), run(3));
    let bits = |x: &Tensor<f32>| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.0), bits(&b.0));
    assert_eq!(bits(&a.1), bits(&b.1));
    assert_eq!(bits(&a.2), bits(&b.2));
}

#[test]
fn uv_far_outside_the_unit_square() {
    let mut rng = Rng::new(8);
    let texels: Tensor<f64> = rng.uniform_tensor(&[5, 6, 3], 0.0, 1.0);
    let base = [0.3125, 0.6875, 0.1, 0.45];
    for wrap in [Wrap::Repeat, Wrap::Mirror, Wrap::Clamp] {
        for filter in [Filter::Nearest, Filter::Bilinear] {
            let s = Sampler::new(filter, wrap);
            let at = |uv: Vec<f64>| {
                let tape = Tape::<f64>::new();
                let y = sample(
                    tape.constant(texels.clone()),
                    tape.constant(t(&[uv.len() / 2, 2], uv)),
                    None,
                    s,
                );
                (*y.value().unwrap()).clone()
            };
            let reference = at(base.to_vec());
            for k in [2.0, -4.0, 1000.0, -1.0e5] {
                let shifted = at(base.iter().map(|x| x + k).collect());
                let expect = match wrap {
                    // Period 1 (repeat) and 2 (mirror): even shifts reproduce the sample.
                    Wrap::Repeat | Wrap::Mirror => reference.clone(),
                    // Clamp: the edge texels.
                    Wrap::Clamp => {
                        let e = if k > 0.0 { 10.0 } else { -10.0 };
                        at(base.iter().map(|_| e).collect())
                    }
                };
                let d = max_diff(&shifted, &expect);
                assert!(d < 1e-8, "{s:?} shift {k}: {d}");
            }
            // Mirror: an odd shift reflects.
            if wrap == Wrap::Mirror {
                let reflected = at(vec![
                    1.0 - base[0] + 1.0,
                    1.0 - base[1] + 1.0,
                    1.0 - base[2] - 1.0,
                    1.0 - base[3] + 3.0,
                ]);
                assert!(max_diff(&reflected, &reference) < 1e-9);
            }
        }
    }
    // f32 at |uv| ~ 1e3 still samples the right texel neighbourhood.
    let tape = Tape::<f32>::new();
    let tex32 = tape.constant(texels.mapv(|v| v as f32));
    let s = Sampler::new(Filter::Bilinear, Wrap::Repeat);
    let near = sample(
        tex32,
        tape.constant(ArrayD::from_shape_vec(IxDyn(&[1, 2]), vec![0.3125f32, 0.6875]).unwrap()),
        None,
        s,
    );
    let far = sample(
        tex32,
        tape.constant(
            ArrayD::from_shape_vec(IxDyn(&[1, 2]), vec![1000.3125f32, -999.3125]).unwrap(),
        ),
        None,
        s,
    );
    let (a, b) = (near.value().unwrap(), far.value().unwrap());
    assert!(
        a.iter().zip(b.iter()).all(|(x, y)| (x - y).abs() < 1e-3),
        "{a:?} {b:?}"
    );
}

#[test]
fn texture_from_png_roundtrip() {
    let dir = std::env::temp_dir().join(format!("tapestry-shading-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("tex.png");
    // A 3 x 5 (non-power-of-two) RGB texture.
    let img =
        ndarray::Array3::from_shape_fn((3, 5, 3), |(r, c, k)| ((r * 5 + c) * 3 + k) as f64 / 64.0);
    render_ops::io::write_png(&path, &img).unwrap();
    let tape = Tape::<f64>::new();
    let tex = render_ops::texture::Texture::from_png(
        &tape,
        &path,
        Sampler::new(Filter::Nearest, Wrap::Clamp),
        true,
    )
    .unwrap();
    assert_eq!(tex.texels.shape(), vec![3, 5, 3]);
    // Texel (row 1, col 3) centre: u = 3.5 / 5, v = 1 - 1.5 / 3.
    let y = tex
        .sample(tape.constant(t(&[1, 2], vec![0.7, 0.5])), None)
        .value()
        .unwrap();
    for k in 0..3 {
        assert!((y[[0, k]] - img[[1, 3, k]]).abs() <= 0.5 / 255.0 + 1e-12);
    }
    std::fs::remove_dir_all(&dir).ok();
}

// ---------------------------------------------------------------- shaders on rasterized meshes

/// A latitude-longitude sphere of radius 1 (y up) with uvs `(lon, lat)` in [0, 1]^2 and a uv
/// seam (duplicated vertices at longitude 0 / 1, facing -z); counter-clockwise seen from outside, no
/// degenerate faces.
struct UvSphere {
    positions: Vec<[f64; 3]>,
    uvs: Vec<[f64; 2]>,
    faces: Arc<Vec<[u32; 3]>>,
}

fn uv_sphere(nlat: usize, nlon: usize) -> UvSphere {
    let (mut positions, mut uvs) = (Vec::new(), Vec::new());
    for i in 0..=nlat {
        let th = std::f64::consts::PI * i as f64 / nlat as f64;
        for j in 0..=nlon {
            let ph = std::f64::consts::TAU * j as f64 / nlon as f64;
            positions.push([th.sin() * ph.sin(), th.cos(), -th.sin() * ph.cos()]);
            uvs.push([j as f64 / nlon as f64, 1.0 - i as f64 / nlat as f64]);
        }
    }
    let id = |i: usize, j: usize| (i * (nlon + 1) + j) as u32;
    let mut faces = Vec::new();
    for i in 0..nlat {
        for j in 0..nlon {
            for tri in [
                [id(i, j), id(i + 1, j), id(i + 1, j + 1)],
                [id(i, j), id(i + 1, j + 1), id(i, j + 1)],
            ] {
                let p = |k: usize| positions[tri[k] as usize];
                let (a, b, c) = (p(0), p(1), p(2));
                let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                let n = [
                    e1[1] * e2[2] - e1[2] * e2[1],
                    e1[2] * e2[0] - e1[0] * e2[2],
                    e1[0] * e2[1] - e1[1] * e2[0],
                ];
                let area = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                if area < 1e-12 {
                    continue;
                }
                let centre = [a[0] + b[0] + c[0], a[1] + b[1] + c[1], a[2] + b[2] + c[2]];
                let outward = n[0] * centre[0] + n[1] * centre[1] + n[2] * centre[2] > 0.0;
                faces.push(if outward {
                    tri
                } else {
                    [tri[0], tri[2], tri[1]]
                });
            }
        }
    }
    UvSphere {
        positions,
        uvs,
        faces: Arc::new(faces),
    }
}

fn rows<const K: usize>(v: &[[f64; K]]) -> Tensor<f64> {
    t(&[v.len(), K], v.iter().flatten().copied().collect())
}

fn camera(eye: [f64; 3]) -> Camera {
    Camera::perspective_look_at(
        eye,
        [0.0; 3],
        [0.0, 1.0, 0.0],
        40f64.to_radians(),
        1.0,
        0.5,
        10.0,
    )
    .unwrap()
}

fn raster<'t>(
    positions: Var<'t, f64>,
    faces: &Arc<Vec<[u32; 3]>>,
    cam: &Camera,
    size: usize,
) -> Rasterized<'t, f64> {
    let clip = to_clip(positions, &cam.view_proj());
    rasterize(clip, faces.clone(), &RasterSettings::new(size, size)).unwrap()
}

/// Pixel weights `[H, W, 4]`: random on pixels whose fragment lies at least `margin` (in
/// barycentric units) inside its face, zero elsewhere (silhouettes and edges).
fn interior_weights(r: &Rasterized<'_, f64>, margin: f64, seed: u64) -> Tensor<f64> {
    let f = &r.fragments;
    let mut rng = Rng::new(seed);
    let mut w = ArrayD::zeros(IxDyn(&[f.height, f.width, 4]));
    for p in 0..f.num_pixels() {
        if let Some(fr) = f.nearest(p) {
            if fr.bary.iter().all(|&b| b > margin) {
                let (row, col) = f.pixel_coords(p);
                for k in 0..4 {
                    w[[row, col, k]] = rng.normal();
                }
            }
        }
    }
    w
}

#[test]
fn shader_pipeline_gradcheck_end_to_end() {
    // rasterize + interpolate + (vertex normals, texture, Blinn-Phong | SH) + hard blend, in
    // f64, gradients of interior pixels with respect to positions, texels, lights and eye.
    let s = uv_sphere(5, 8);
    let cam = camera([0.4, 0.5, 3.2]);
    let eye = [0.4, 0.5, 3.2];
    let size = 20;
    let p0 = rows(&s.positions);
    let weights = {
        let tape = Tape::new();
        interior_weights(
            &raster(tape.constant(p0.clone()), &s.faces, &cam, size),
            0.03,
            17,
        )
    };
    let uvs = rows(&s.uvs);
    let mut rng = Rng::new(3);
    let inputs = vec![
        p0,
        rng.uniform_tensor(&[3, 5, 3], 0.2, 1.0),
        t(&[3], vec![-0.3, -0.5, -1.0]),
        t(&[3], eye.to_vec()),
        rng.normal_tensor(&[9, 3]),
    ];
    let opts = GradcheckOptions::default();
    for sh in [false, true] {
        let f = hr(|tape, v| {
            let r = raster(v[0], &s.faces, &cam, size);
            let mesh = MeshAttributes::new(v[0]).with_uvs(tape.constant(uvs.clone()));
            let tex = Texture::new(v[1], Sampler::new(Filter::Bilinear, Wrap::Repeat));
            let img = render_shader(
                &r,
                &mesh,
                v[3],
                |fi: &FragmentInputs<'_, f64>| {
                    let albedo = fi.sample(&tex);
                    if sh {
                        sh_shade(fi.normal, albedo, v[4])
                    } else {
                        let lights = Lights::new()
                            .with_directional(DirectionalLight {
                                direction: v[2],
                                color: tape.constant(t(&[3], vec![1.0, 0.9, 0.8])),
                            })
                            .with_ambient(AmbientLight::constant(tape, [0.1, 0.1, 0.1]));
                        let m = Material::constant(
                            tape,
                            Reflectance::BlinnPhong,
                            [0.3, 0.3, 0.3],
                            12.0,
                        );
                        shade(&fi.surface(albedo), &m, &lights, fi.eye)
                    }
                },
                &[0.1, 0.2, 0.3],
            )
            .unwrap();
            (img * tape.constant(weights.clone())).sum()
        });
        let rep = gradcheck(f, &inputs, &opts).unwrap();
        assert!(rep.passed(), "sh={sh}\n{rep}");
        // The positions really receive interior gradients.
        assert!(rep.inputs[0].max_abs_err < 1e-5);
    }
}

#[test]
fn uv_derivatives_match_pixel_differences_and_gradcheck() {
    // A plane parallel to the image plane: uv is affine in screen space, so d uv / d col is
    // the difference of the interpolated uvs of neighbouring pixels.
    let plane = render_ops::mesh::Mesh::<f64>::grid_plane(3);
    let faces = Arc::new(plane.faces.clone());
    let cam = camera([0.0, 0.0, 3.0]);
    let tape = Tape::new();
    let r = raster(tape.constant(rows(&plane.positions)), &faces, &cam, 32);
    let uvv = tape.leaf(rows(&plane.uvs));
    let uv = render_ops::interpolate::interpolate(uvv, &r)
        .unwrap()
        .value()
        .unwrap();
    let da = uv_derivatives(uvv, &r).value().unwrap();
    let f = &r.fragments;
    let mut checked = 0;
    for p in 0..f.num_pixels() {
        let (row, col) = f.pixel_coords(p);
        if col + 1 >= f.width || row + 1 >= f.height {
            continue;
        }
        let (Some(a), Some(b), Some(c)) = (f.nearest(p), f.nearest(p + 1), f.nearest(p + f.width))
        else {
            continue;
        };
        for k in 0..2 {
            assert!((uv[[b.index, k]] - uv[[a.index, k]] - da[[a.index, k]]).abs() < 1e-9);
            assert!((uv[[c.index, k]] - uv[[a.index, k]] - da[[a.index, 2 + k]]).abs() < 1e-9);
        }
        checked += 1;
    }
    assert!(checked > 100);
    // du/dx > 0, dv/dy < 0 (v grows upwards, rows downwards).
    assert!(da[[0, 0]] > 0.0 && da[[0, 3]] < 0.0);
    let uv0 = rows(&plane.uvs);
    let rep = gradcheck(
        |tp: &Tape<f64>, v| {
            let r = raster(tp.constant(rows(&plane.positions)), &faces, &cam, 12);
            let w = tp.constant(Rng::new(1).normal_tensor(&[r.fragments.len(), 4]));
            (uv_derivatives(v[0], &r) * w).sum()
        },
        &[uv0],
        &GradcheckOptions::default(),
    )
    .unwrap();
    check("uv_derivatives", rep);
    // Fragments rasterized without barycentric derivatives: a typed error, not zeros.
    let tape = Tape::new();
    let clip = to_clip(tape.constant(rows(&plane.positions)), &cam.view_proj());
    let s = RasterSettings {
        barycentric_derivatives: false,
        ..RasterSettings::new(32, 32)
    };
    let r = rasterize(clip, faces.clone(), &s).unwrap();
    assert!(!r.fragments.is_empty() && !r.fragments.has_derivatives());
    let err = uv_derivatives(tape.leaf(rows(&plane.uvs)), &r)
        .value()
        .unwrap_err();
    assert!(err.to_string().contains("barycentric_derivatives"), "{err}");
}

#[test]
fn auxiliary_outputs_and_alpha() {
    let s = uv_sphere(16, 32);
    let cam = camera([0.0, 0.0, 3.0]);
    let tape = Tape::new();
    let pos = tape.leaf(rows(&s.positions));
    let r = raster(pos, &s.faces, &cam, 33);
    let code = tape.constant(ncc(&s.positions));
    let mesh = MeshAttributes::new(pos).with_attribute("ncc", code);
    let eye = tape.constant(t(&[3], vec![0.0, 0.0, 3.0]));
    let centre = |img: &Tensor<f64>| {
        (0..img.shape()[2])
            .map(|k| img[[16, 16, k]])
            .collect::<Vec<_>>()
    };
    // Normal map: the point facing the camera is +z.
    let nm = render_shader(&r, &mesh, eye, |f| normal_map(f.normal), &[0.0; 3])
        .unwrap()
        .value()
        .unwrap();
    let c = centre(&nm);
    assert!(
        (c[0] - 0.5).abs() < 0.02
            && (c[1] - 0.5).abs() < 0.02
            && (c[2] - 1.0).abs() < 1e-3
            && c[3] == 1.0,
        "{c:?}"
    );
    // Depth: view depth 2 at the front point.
    let dm = render_shader(
        &r,
        &mesh,
        eye,
        |f| depth_map(f.view_depth, 0.5, 10.0),
        &[1.0],
    )
    .unwrap()
    .value()
    .unwrap();
    let c = centre(&dm);
    assert!((c[0] - (2.0 - 0.5) / 9.5).abs() < 2e-3, "{c:?}");
    assert_eq!(dm[[0, 0, 0]], 1.0);
    // PNCC: the bounding box of the sphere is [-1, 1]^3, the front point (0, 0, 1) maps to
    // (0.5, 0.5, 1); the attribute and the pncc function agree.
    let pc = render_shader(&r, &mesh, eye, |f| f.attribute("ncc").unwrap(), &[0.0; 3])
        .unwrap()
        .value()
        .unwrap();
    let c = centre(&pc);
    assert!(
        (c[0] - 0.5).abs() < 0.02 && (c[1] - 0.5).abs() < 0.02 && (c[2] - 1.0).abs() < 2e-3,
        "{c:?}"
    );
    let direct = pncc(code, &r).unwrap().value().unwrap();
    let via = run_shader(&r, &mesh, eye, |f| f.attribute("ncc").unwrap())
        .unwrap()
        .color
        .value()
        .unwrap();
    assert_eq!(max_diff(&direct, &via), 0.0);
    // A shader alpha: colour a c + (1 - a) bg, last channel coverage * a.
    let img = render_shader(
        &r,
        &mesh,
        eye,
        |f: &FragmentInputs<'_, f64>| {
            let n = f.len();
            let c = tape.constant(ArrayD::from_elem(IxDyn(&[n, 3]), 1.0));
            let a = tape.constant(ArrayD::from_elem(IxDyn(&[n, 1]), 0.25));
            (c, a)
        },
        &[0.0, 0.0, 1.0],
    )
    .unwrap()
    .value()
    .unwrap();
    assert_eq!(centre(&img), vec![0.25, 0.25, 1.0, 0.25]);
    assert_eq!(
        (0..4).map(|k| img[[0, 0, k]]).collect::<Vec<_>>(),
        vec![0.0, 0.0, 1.0, 0.0]
    );
    // Sampling without uvs is an error naming the problem, not a panic.
    let err = render_shader(
        &r,
        &mesh,
        eye,
        |f: &FragmentInputs<'_, f64>| {
            f.sample(&Texture::new(
                tape.constant(ArrayD::zeros(IxDyn(&[2, 2, 3]))),
                Sampler::default(),
            ))
        },
        &[0.0; 3],
    )
    .unwrap_err();
    assert!(err.to_string().contains("no uvs"), "{err}");
}

// ---------------------------------------------------------------- inverse tasks

/// Conjugate gradients on a quadratic `f` given by its gradient `grad` (called with the
/// current point; `grad(0)` is evaluated once): returns the minimiser reached after `iters`
/// steps from `x`.
fn conjugate_gradients(
    mut x: Vec<f64>,
    iters: usize,
    grad: &dyn Fn(&[f64]) -> Vec<f64>,
) -> Vec<f64> {
    let g0 = grad(&vec![0.0; x.len()]);
    let hess = |p: &[f64]| -> Vec<f64> { grad(p).iter().zip(&g0).map(|(a, b)| a - b).collect() };
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut r: Vec<f64> = grad(&x).iter().map(|v| -v).collect();
    let mut p = r.clone();
    let mut rr = dot(&r, &r);
    for _ in 0..iters {
        if rr < 1e-28 {
            break;
        }
        let hp = hess(&p);
        let alpha = rr / dot(&p, &hp);
        for i in 0..x.len() {
            x[i] += alpha * p[i];
            r[i] -= alpha * hp[i];
        }
        let rr2 = dot(&r, &r);
        for i in 0..x.len() {
            p[i] = r[i] + rr2 / rr * p[i];
        }
        rr = rr2;
    }
    x
}

#[test]
fn inverse_texture_from_six_views() {
    // Truth: a smooth colourful 64 x 64 pattern. Six views (+-x, +-y, +-z) of a textured
    // sphere at 80 x 80, unlit bilinear texture; the texture is recovered by conjugate
    // gradients on the squared image error (linear in the texels), gradients from the tape.
    let n = 64;
    let truth = ArrayD::from_shape_fn(IxDyn(&[n, n, 3]), |i| {
        let (y, x, c) = (i[0] as f64 / n as f64, i[1] as f64 / n as f64, i[2] as f64);
        0.5 + 0.2
            * (std::f64::consts::TAU * (2.0 * x + c * 0.3)).sin()
            * (std::f64::consts::TAU * (1.5 * y)).cos()
            + 0.15 * (std::f64::consts::TAU * (5.0 * x + 3.0 * y + c)).sin()
    });
    let s = uv_sphere(24, 48);
    let eyes = [
        [3.0, 0.0, 0.0],
        [-3.0, 0.0, 0.0],
        [0.0, 3.0, 0.01],
        [0.0, -3.0, 0.01],
        [0.0, 0.0, 3.0],
        [0.0, 0.0, -3.0],
    ];
    let cams: Vec<Camera> = eyes
        .iter()
        .map(|&e| {
            Camera::perspective_look_at(
                e,
                [0.0; 3],
                [0.0, 1.0, 0.0],
                45f64.to_radians(),
                1.0,
                0.5,
                10.0,
            )
            .unwrap()
        })
        .collect();
    let size = 80;
    fn render_all<'t>(
        tape: &'t Tape<f64>,
        tex: Var<'t, f64>,
        s: &UvSphere,
        cams: &[Camera],
        eyes: &[[f64; 3]],
        size: usize,
    ) -> Vec<Var<'t, f64>> {
        let pos = tape.constant(rows(&s.positions));
        let mesh = MeshAttributes::new(pos).with_uvs(tape.constant(rows(&s.uvs)));
        let texture = Texture::new(tex, Sampler::new(Filter::Bilinear, Wrap::Repeat));
        cams.iter()
            .zip(eyes)
            .map(|(cam, e)| {
                let r = raster(pos, &s.faces, cam, size);
                render_shader(
                    &r,
                    &mesh,
                    tape.constant(t(&[3], e.to_vec())),
                    |f| f.sample(&texture),
                    &[0.0; 3],
                )
                .unwrap()
            })
            .collect()
    }
    let targets: Vec<Tensor<f64>> = {
        let tape = Tape::new();
        render_all(&tape, tape.constant(truth.clone()), &s, &cams, &eyes, size)
            .iter()
            .map(|v| (*v.value().unwrap()).clone())
            .collect()
    };
    let grad = |x: &[f64]| -> Vec<f64> {
        let tape = Tape::new();
        let tex = tape.leaf(t(&[n, n, 3], x.to_vec()));
        let mut loss = tape.scalar(0.0);
        for (img, target) in render_all(&tape, tex, &s, &cams, &eyes, size)
            .into_iter()
            .zip(&targets)
        {
            loss = loss + (img - tape.constant(target.clone())).square().sum();
        }
        tape.backward(loss)
            .unwrap()
            .wrt(tex)
            .iter()
            .copied()
            .collect()
    };
    // Visible texels: total bilinear weight of the samples reading them (A^T 1) >= 1.
    let coverage: Vec<f64> = {
        let tape = Tape::new();
        let tex = tape.leaf(ArrayD::zeros(IxDyn(&[n, n, 3])));
        let mut total = tape.scalar(0.0);
        for img in render_all(&tape, tex, &s, &cams, &eyes, size) {
            total = total + img.slice(2, 0, 3).sum();
        }
        tape.backward(total)
            .unwrap()
            .wrt(tex)
            .iter()
            .copied()
            .collect()
    };
    let x = conjugate_gradients(vec![0.5; n * n * 3], 20, &grad);
    let (mut se, mut count) = (0.0, 0usize);
    for (i, (&xi, &ti)) in x.iter().zip(truth.iter()).enumerate() {
        if coverage[i] >= 1.0 {
            se += (xi - ti) * (xi - ti);
            count += 1;
        }
    }
    let psnr = 10.0 * (1.0 / (se / count as f64)).log10();
    let visible = count as f64 / (n * n * 3) as f64;
    eprintln!(
        "texture recovery: PSNR {psnr:.1} dB over {:.0}% of the texels",
        100.0 * visible
    );
    assert!(visible > 0.8, "only {visible} of the texels visible");
    assert!(psnr >= 30.0, "PSNR {psnr} dB");
}

/// Solves `a x = b` (dense, Gaussian elimination with partial pivoting).
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for col in 0..n {
        let piv = (col..n)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap();
        a.swap(col, piv);
        b.swap(col, piv);
        for row in col + 1..n {
            let f = a[row][col] / a[col][col];
            for k in col..n {
                a[row][k] -= f * a[col][k];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x
}

#[test]
fn inverse_sh_coefficients_from_one_image() {
    // A known sphere with spatially varying albedo, lit by 27 SH coefficients, one noise-free
    // 64 x 64 image. The image is linear in the coefficients: the normal equations are
    // assembled from 28 tape gradients and solved.
    let truth: [[f64; 3]; 9] = [
        [0.9, 0.8, 0.7],
        [0.15, 0.1, -0.05],
        [0.4, 0.35, 0.3],
        [-0.2, 0.1, 0.05],
        [0.05, -0.08, 0.1],
        [0.1, 0.05, -0.1],
        [-0.12, -0.1, -0.05],
        [0.08, 0.12, 0.02],
        [-0.06, 0.04, 0.09],
    ];
    let mesh = render_ops::mesh::Mesh::<f64>::icosphere(3, 1.0);
    let cam = camera([0.0, 0.3, 3.0]);
    let albedo: Vec<[f64; 3]> = mesh
        .positions
        .iter()
        .map(|p| [0.6 + 0.3 * p[0], 0.5 + 0.2 * p[1], 0.7 - 0.2 * p[2]])
        .collect();
    fn render<'t>(
        tape: &'t Tape<f64>,
        coeffs: Var<'t, f64>,
        mesh: &render_ops::mesh::Mesh<f64>,
        albedo: &[[f64; 3]],
        cam: &Camera,
    ) -> Var<'t, f64> {
        let faces = Arc::new(mesh.faces.clone());
        let pos = tape.constant(rows(&mesh.positions));
        let r = raster(pos, &faces, cam, 64);
        let attrs = MeshAttributes::new(pos).with_attribute("albedo", tape.constant(rows(albedo)));
        let light = ShLight { coeffs };
        let eye = tape.constant(t(&[3], vec![0.0, 0.3, 3.0]));
        render_shader(
            &r,
            &attrs,
            eye,
            |f| sh_shade(f.normal, f.attribute("albedo").unwrap(), light.coeffs),
            &[0.0; 3],
        )
        .unwrap()
    }
    let target = {
        let tape = Tape::new();
        (*render(&tape, tape.constant(rows(&truth)), &mesh, &albedo, &cam)
            .value()
            .unwrap())
        .clone()
    };
    let grad = |c: &[f64]| -> Vec<f64> {
        let tape = Tape::new();
        let cv = tape.leaf(t(&[9, 3], c.to_vec()));
        let loss = (render(&tape, cv, &mesh, &albedo, &cam) - tape.constant(target.clone()))
            .square()
            .sum();
        tape.backward(loss)
            .unwrap()
            .wrt(cv)
            .iter()
            .copied()
            .collect()
    };
    let g0 = grad(&[0.0; 27]);
    let cols: Vec<Vec<f64>> = (0..27)
        .map(|k| {
            let mut e = [0.0; 27];
            e[k] = 1.0;
            grad(&e).iter().zip(&g0).map(|(a, b)| a - b).collect()
        })
        .collect();
    // H = [cols] (symmetric); H c = -g0.
    let h: Vec<Vec<f64>> = (0..27)
        .map(|i| (0..27).map(|k| cols[k][i]).collect())
        .collect();
    let c = solve(h, g0.iter().map(|v| -v).collect());
    let tv: Vec<f64> = truth.iter().flatten().copied().collect();
    let err = c
        .iter()
        .zip(&tv)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    let norm = tv.iter().map(|v| v * v).sum::<f64>().sqrt();
    eprintln!("SH recovery: relative error {:.2e}", err / norm);
    assert!(err / norm <= 1e-3, "relative error {}", err / norm);
}
