//! Local reflection models: Lambert, Phong and Blinn-Phong under ambient, directional and
//! point lights, evaluated per fragment.
//!
//! With `n` the unit normal, `v = normalize(eye - x)` the unit view direction, and for every
//! light `j` of colour `C_j` the unit direction towards it `l_j` (`-normalize(direction)` for
//! a directional light, `normalize(position - x)` for a point light):
//!
//! ```text
//! colour = ka ⊙ sum(ambient) + sum_j C_j ⊙ (albedo * max(n . l_j, 0) + ks * spec_j)
//! Phong (1975):       spec_j = max(r_j . v, 0)^s,  r_j = 2 (n . l_j) n - l_j
//! Blinn-Phong (1977): spec_j = max(n . h_j, 0)^s,  h_j = normalize(l_j + v)
//! Lambert:            spec_j = 0
//! ```
//!
//! `spec_j` is taken as 0 where `n . l_j <= 0` (no highlight on surfaces facing away from the
//! light). `ka` defaults to the albedo. B. T. Phong, "Illumination for computer generated
//! pictures", CACM 18(6), 1975; J. F. Blinn, "Models of light reflection for computer
//! synthesized pictures", SIGGRAPH 1977.
//!
//! Derivatives at the kinks follow the tape's conventions (`relu'(0) = 0`); where the
//! specular base is 0 the highlight and all its gradients are 0 (also with respect to `s`,
//! whose derivative `spec ln(base)` would be `0 * -inf` there). All normalisations are the
//! safe `x / max(|x|, eps)` of the [module docs](super).

use autodiff::{AutodiffError, Real, Result as AdResult, Var};
use ndarray::{ArrayD, IxDyn};

use super::lights::{Lights, Material, Reflectance};
use super::{check_rows, SAFE_EPS};

/// Per-fragment inputs of a reflection model.
#[derive(Clone, Copy, Debug)]
pub struct Surface<'t, T: Real> {
    /// World positions `[N, 3]` (used by point lights and the view direction).
    pub position: Var<'t, T>,
    /// Normals `[N, 3]`, any length (normalised inside).
    pub normal: Var<'t, T>,
    /// Diffuse reflectance `[N, 3]` or `[3]` (the material's `kd` times texture or vertex
    /// colour).
    pub albedo: Var<'t, T>,
    /// Visibility of the directional lights, then the point lights `[N, L]` (shadows: each
    /// light's term is scaled by its column), or `None` for unshadowed lights.
    pub visibility: Option<Var<'t, T>>,
}

/// The reflection model of `material` (Lambert, Phong or Blinn-Phong, see the module docs)
/// at every fragment of `surface`, seen from `eye` (`[3]`): colours `[N, 3]`.
///
/// [`shade_composed`] run inside [`autodiff::Tape::fused`]: one fused op, evaluated chunk by
/// chunk in cache with the chain rule derived from the graph (no hand-written backward), and
/// fused further with the caller's elementwise ops when called inside a fused region.
/// Gradients reach the positions, normals, albedo, `ka`, `ks`, shininess, the eye and every
/// light's parameters. Inputs of the wrong shape poison the result with an error naming them
/// (see [`autodiff::Tape`]).
pub fn shade<'t, T: Real>(
    surface: &Surface<'t, T>,
    material: &Material<'t, T>,
    lights: &Lights<'t, T>,
    eye: Var<'t, T>,
) -> Var<'t, T> {
    let t = surface.position.tape();
    match check_inputs(surface, material, lights, eye) {
        Ok(()) => t.fused(|| shade_composed(surface, material, lights, eye)),
        Err(e) => t.poisoned(e),
    }
}

/// The shapes [`shade`] takes.
fn check_inputs<'t, T: Real>(
    surface: &Surface<'t, T>,
    material: &Material<'t, T>,
    lights: &Lights<'t, T>,
    eye: Var<'t, T>,
) -> AdResult<()> {
    const OP: &str = "shade";
    let ps = surface.position.shape();
    if ps.len() != 2 || ps[1] != 3 {
        return Err(AutodiffError::shape(OP, &[&ps], "positions must be [N, 3]"));
    }
    let n = ps[0];
    check_rows(OP, "normals", surface.normal, n, false)?;
    check_rows(OP, "albedo", surface.albedo, n, true)?;
    if let Some(ka) = material.ka {
        check_rows(OP, "ka", ka, n, true)?;
    }
    check_rows(OP, "ks", material.ks, n, true)?;
    let len = |v: Var<'t, T>| v.shape().iter().product::<usize>();
    if len(material.shininess) != 1 {
        let s = material.shininess.shape();
        return Err(AutodiffError::shape(
            OP,
            &[&s],
            "shininess must have one element",
        ));
    }
    let three = |what: &str, v: Var<'t, T>| {
        if len(v) == 3 {
            Ok(())
        } else {
            let s = v.shape();
            Err(AutodiffError::shape(
                OP,
                &[&s],
                format!("{what} must be [3]"),
            ))
        }
    };
    three("eye", eye)?;
    for a in &lights.ambient {
        three("an ambient colour", a.color)?;
    }
    for d in &lights.directional {
        three("a light direction", d.direction)?;
        three("a directional colour", d.color)?;
    }
    for p in &lights.point {
        three("a light position", p.position)?;
        three("a point colour", p.color)?;
    }
    if let Some(v) = surface.visibility {
        let l = lights.directional.len() + lights.point.len();
        let s = v.shape();
        if s != [n, l] {
            return Err(AutodiffError::shape(
                OP,
                &[&s],
                format!("visibility must be [{n}, {l}] (fragments, directional and point lights)"),
            ));
        }
    }
    Ok(())
}

/// [`shade`] composed from tape ops: the reference, and a template for custom shaders.
///
/// Written with ops the tape's fused evaluation handles (the "facing the light" mask is
/// [`Var::heaviside`], not a mask read from a value), so that inside [`autodiff::Tape::fused`]
/// the whole model is one fused op.
pub fn shade_composed<'t, T: Real>(
    surface: &Surface<'t, T>,
    material: &Material<'t, T>,
    lights: &Lights<'t, T>,
    eye: Var<'t, T>,
) -> Var<'t, T> {
    let t = surface.position.tape();
    let eps = T::from_f64c(SAFE_EPS);
    let n = surface.normal.normalize(eps);
    let ka = material.ka.unwrap_or(surface.albedo);
    let mut col: Option<Var<'t, T>> = None;
    let mut add = |term: Var<'t, T>| col = Some(col.map_or(term, |c| c + term));
    for a in &lights.ambient {
        add(ka * a.color.reshape(&[3]));
    }
    let specular = material.model != Reflectance::Lambert;
    let v = (eye.reshape(&[3]) - surface.position).normalize(eps);
    let mut add_light = |l: Var<'t, T>, color: Var<'t, T>, k: usize| {
        // l: [3] or [N, 3], unit, towards the light.
        let ndl = (n * l).sum_axes(&[-1], true);
        let mut refl = surface.albedo * ndl.relu();
        if specular {
            let base = match material.model {
                Reflectance::Phong => {
                    let r = n * (ndl * T::from_f64c(2.0)) - l;
                    (r * v).sum_axes(&[-1], true)
                }
                _ => (n * (l + v).normalize(eps)).sum_axes(&[-1], true),
            };
            // No highlight where the surface faces away from the light.
            // `[]` or `[1]`: either broadcasts over the fragments, no reshape op recorded.
            let spec = base.relu().pow(material.shininess) * ndl.heaviside();
            refl = refl + material.ks * spec;
        }
        let term = refl * color.reshape(&[3]);
        add(match surface.visibility {
            Some(vis) => term * vis.slice(-1, k, k + 1),
            None => term,
        });
    };
    for (k, d) in lights.directional.iter().enumerate() {
        let l = (-d.direction.reshape(&[3])).normalize(eps);
        add_light(l, d.color, k);
    }
    let nd = lights.directional.len();
    for (k, p) in lights.point.iter().enumerate() {
        let l = (p.position.reshape(&[3]) - surface.position).normalize(eps);
        add_light(l, p.color, nd + k);
    }
    // `[N, 3]` also when no term varies by fragment (ambient light only, constant `ka`).
    let nrows = surface.position.shape().first().copied().unwrap_or(0);
    match col {
        Some(c) if c.shape() == [nrows, 3] => c,
        c => {
            let zero = t.constant(ArrayD::zeros(IxDyn(&[nrows, 3])));
            c.map_or(zero, |c| zero + c)
        }
    }
}
