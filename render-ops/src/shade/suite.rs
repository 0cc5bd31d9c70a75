//! Gradient-check cases of the shading and texture ops, in the form of
//! [`autodiff::suite::Case`] (full-Jacobian `f64` gradcheck plus an `f32`/`f64` comparison),
//! for `tapestry gradcheck`. Inputs are drawn away from the models' kinks: normals near +z
//! lit from the front, uvs at random (a bilinear kink is hit with probability ~1e-5).

use autodiff::suite::{Case, CaseResult, Gen};
use autodiff::{tensor, Real, Tape, Var};
use ndarray::{ArrayD, IxDyn};
use std::sync::Arc;

use super::lights::{AmbientLight, DirectionalLight, Lights, Material, PointLight, Reflectance};
use super::normals::{face_normals, vertex_normals};
use super::phong::{shade, Surface};
use super::sh::sh_shade;
use crate::texture::{sample, Filter, Sampler, Wrap};

const OCTA: [[f64; 3]; 6] = [
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 0.0, -1.0],
];
/// The octahedron's faces, counter-clockwise seen from outside (also the raster cases' mesh).
pub(crate) const OCTA_FACES: [[u32; 3]; 8] = [
    [0, 2, 4],
    [2, 1, 4],
    [1, 3, 4],
    [3, 0, 4],
    [2, 0, 5],
    [1, 2, 5],
    [3, 1, 5],
    [0, 3, 5],
];

fn octahedron<'t, T: Real>(t: &'t Tape<T>, delta: Var<'t, T>) -> (Var<'t, T>, Arc<Vec<[u32; 3]>>) {
    let base = ArrayD::from_shape_vec(
        IxDyn(&[6, 3]),
        OCTA.iter().flatten().map(|&x| T::from_f64c(x)).collect(),
    )
    .expect("6 x 3");
    (t.constant(base) + delta, Arc::new(OCTA_FACES.to_vec()))
}

fn face_normals_case<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    let (p, f) = octahedron(t, v[0]);
    face_normals(p, &f)
}

fn vertex_normals_case<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    let (p, f) = octahedron(t, v[0]);
    vertex_normals(p, &f)
}

fn vec3<'t, T: Real>(t: &'t Tape<T>, x: [f64; 3]) -> Var<'t, T> {
    t.constant(tensor::from_vec(&[3], x.iter().map(|&c| T::from_f64c(c)).collect()).expect("3"))
}

/// Inputs: positions [8, 3], normal perturbations [8, 3] (around +z), albedo [8, 3],
/// ks [3], light direction [3] (around -z), point light position [3].
fn reflection<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>], model: Reflectance) -> Var<'t, T> {
    let normal = v[1] + vec3(t, [0.0, 0.0, 1.0]);
    let surf = Surface {
        position: v[0],
        normal,
        albedo: v[2],
        visibility: None,
    };
    let mut m = Material::constant(t, model, [0.0; 3], 8.0);
    m.ks = v[3];
    let lights = Lights::new()
        .with_ambient(AmbientLight::constant(t, [0.1, 0.1, 0.1]))
        .with_directional(DirectionalLight {
            direction: v[4] + vec3(t, [0.0, 0.0, -1.0]),
            color: vec3(t, [1.0, 0.9, 0.8]),
        })
        .with_point(PointLight {
            position: v[5] + vec3(t, [0.0, 0.0, 6.0]),
            color: vec3(t, [0.5, 0.5, 0.5]),
        });
    shade(&surf, &m, &lights, vec3(t, [0.1, -0.1, 8.0]))
}

fn lambert_case<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    reflection(t, v, Reflectance::Lambert)
}

fn phong_case<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    reflection(t, v, Reflectance::Phong)
}

fn blinn_phong_case<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    reflection(t, v, Reflectance::BlinnPhong)
}

fn sh_case<'t, T: Real>(_t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    sh_shade(v[0], v[1], v[2])
}

fn texture_case<'t, T: Real>(v: &[Var<'t, T>], filter: Filter, wrap: Wrap) -> Var<'t, T> {
    sample(v[0], v[1], Some(v[2]), Sampler::new(filter, wrap))
}

fn nearest_case<'t, T: Real>(_t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    sample(
        v[0],
        v[1],
        None,
        Sampler::new(Filter::Nearest, Wrap::Repeat),
    )
}

fn bilinear_case<'t, T: Real>(_t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    texture_case(v, Filter::Bilinear, Wrap::Mirror)
}

/// uv derivatives of 2^lambda texels per pixel on an 8 x 8 texture, lambda = 1.5 + 0.2 x for
/// lattice values x (so lambda is 1.1, 1.3, ..., 1.9 +- 0.04: away from integers), and
/// |d/dy| = 0.4 |d/dx| (no tie in the max).
fn trilinear_case<'t, T: Real>(t: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
    let lam = v[2].slice(1, 0, 1) * T::from_f64c(0.2) + T::from_f64c(1.5);
    let rho = (lam * T::from_f64c(std::f64::consts::LN_2)).exp() * T::from_f64c(1.0 / 8.0);
    let a = v[2].slice(1, 1, 2);
    let da = t.concat(
        &[
            rho * a.cos(),
            rho * a.sin(),
            rho * a.sin() * T::from_f64c(0.4),
            rho * a.cos() * T::from_f64c(-0.4),
        ],
        1,
    );
    sample(
        v[0],
        v[1],
        Some(da),
        Sampler::new(Filter::Trilinear, Wrap::Clamp),
    )
}

/// The shading and texture cases (names `shade/...`, `texture/...`).
pub fn cases() -> Vec<Case> {
    let frag = vec![
        vec![8, 3],
        vec![8, 3],
        vec![8, 3],
        vec![3],
        vec![3],
        vec![3],
    ];
    let frag_gens = vec![
        Gen::Uniform(-1.0, 1.0),
        Gen::Uniform(-0.3, 0.3),
        Gen::Uniform(0.2, 1.0),
        Gen::Uniform(0.1, 0.6),
        Gen::Uniform(-0.3, 0.3),
        Gen::Uniform(-1.0, 1.0),
    ];
    let tex = vec![vec![8, 8, 3], vec![10, 2], vec![10, 2]];
    let cases = vec![
        Case::new(
            "shade/face_normals",
            vec![vec![6, 3]],
            vec![Gen::Uniform(-0.2, 0.2)],
            face_normals_case::<f32>,
            face_normals_case::<f64>,
        ),
        Case::new(
            "shade/vertex_normals",
            vec![vec![6, 3]],
            vec![Gen::Uniform(-0.2, 0.2)],
            vertex_normals_case::<f32>,
            vertex_normals_case::<f64>,
        ),
        Case::new(
            "shade/lambert",
            frag.clone(),
            frag_gens.clone(),
            lambert_case::<f32>,
            lambert_case::<f64>,
        ),
        Case::new(
            "shade/phong",
            frag.clone(),
            frag_gens.clone(),
            phong_case::<f32>,
            phong_case::<f64>,
        ),
        Case::new(
            "shade/blinn_phong",
            frag,
            frag_gens,
            blinn_phong_case::<f32>,
            blinn_phong_case::<f64>,
        ),
        Case::new(
            "shade/sh",
            vec![vec![8, 3], vec![8, 3], vec![9, 3]],
            vec![
                Gen::Signed(0.3, 1.0),
                Gen::Uniform(0.2, 1.0),
                Gen::Uniform(-1.0, 1.0),
            ],
            sh_case::<f32>,
            sh_case::<f64>,
        ),
        Case::new(
            "texture/nearest",
            vec![vec![5, 7, 3], vec![10, 2]],
            vec![Gen::Uniform(0.0, 1.0), Gen::Uniform(-2.0, 3.0)],
            nearest_case::<f32>,
            nearest_case::<f64>,
        ),
        Case::new(
            "texture/bilinear",
            vec![vec![5, 7, 3], vec![10, 2], vec![10, 4]],
            vec![
                Gen::Uniform(0.0, 1.0),
                Gen::Uniform(-2.0, 3.0),
                Gen::Uniform(0.0, 0.1),
            ],
            bilinear_case::<f32>,
            bilinear_case::<f64>,
        ),
        Case::new(
            "texture/trilinear",
            tex,
            vec![
                Gen::Uniform(0.0, 1.0),
                Gen::Uniform(-2.0, 3.0),
                Gen::Lattice(0.0),
            ],
            trilinear_case::<f32>,
            trilinear_case::<f64>,
        ),
    ];
    // Categories of the gradcheck registry: the name's prefix.
    cases
        .into_iter()
        .map(|c| {
            let cat = if c.op.starts_with("texture/") {
                "texture"
            } else {
                "shade"
            };
            c.in_category(cat)
        })
        .collect()
}

/// Runs every case matching `filter` (full name or base, e.g. `shade/phong` or `shade`), all
/// for `None`, with the default gradcheck options.
pub fn run_all(filter: Option<&str>) -> Vec<CaseResult> {
    let opts = autodiff::gradcheck::GradcheckOptions::default();
    cases()
        .iter()
        .filter(|c| match filter {
            None => true,
            Some(f) => c.matches(f),
        })
        .map(|c| c.run_or_fail(&opts))
        .collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn every_case_passes() {
        let results = super::run_all(None);
        assert_eq!(results.len(), 9);
        for r in &results {
            assert!(r.passed, "{r:?}");
        }
    }
}
