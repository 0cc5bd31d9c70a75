//! Direct lighting at a ray hit, with its hand-written reverse-mode derivative: the Lambert,
//! Phong and Blinn-Phong terms of [`crate::shade::phong`] (the same formulas, conventions and
//! kinks: no highlight where `n . l <= 0`, `relu'(0) = 0`), each light's term multiplied by
//! its shadow-ray visibility, plus an area light sampled by area and SH lighting (unshadowed).
//!
//! An area light is a parallelogram `corner + a edge_u + b edge_v`, `(a, b)` in `[0, 1]^2`,
//! emitting radiance `L` from the side of `N_l = edge_u x edge_v`. One sample at `(a, b)`
//! estimates `integral L brdf cos_s cos_l / r^2 dA` as a point light of colour
//! `L A cos_l / r^2 = L max(-N_l . (l - x), 0) / |l - x|^3` at `l` (the density of a uniform
//! area sample is `1 / A`). Like point lights ([`crate::shade::lights`]) the diffuse term is
//! `albedo (n . l)` without a `1 / pi`: a light of colour `C` seen head-on gives `albedo C`.
//! The gradient of a shading sample with respect to the light's rows (corner, edges,
//! radiance) is that of this estimator at fixed `(a, b)`.

use smallvec::SmallVec;

use crate::scene::Shading;
use crate::shade::sh::{sh_eval, sh_eval_vjp};
use crate::shade::{
    acc3, add3, cross3, dot3, mul3, normalize3, normalize3_vjp, scale3, sub3, SAFE_EPS,
};

use super::intersect::V3;

/// What a scene light is, in the order of its rows in the light-rows input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightKind {
    /// `color` (1 row).
    Ambient,
    /// `direction` (travel), `color` (2 rows).
    Directional,
    /// `position`, `color` (2 rows).
    Point,
    /// `corner`, `edge_u`, `edge_v`, `radiance` (4 rows).
    Area,
    /// 9 coefficient rows (used when the shading is `sh`; unshadowed).
    Sh,
}

impl LightKind {
    /// Rows of the light in the light-rows input.
    pub fn rows(self) -> usize {
        match self {
            LightKind::Ambient => 1,
            LightKind::Directional | LightKind::Point => 2,
            LightKind::Area => 4,
            LightKind::Sh => 9,
        }
    }
}

/// A shadow query: is the segment from the shading point towards a point, or along a
/// direction, blocked?
#[derive(Clone, Copy, Debug)]
pub enum Shadow {
    /// Towards a point (point and area lights).
    Toward(V3),
    /// Along a direction to infinity (directional lights).
    Along(V3),
}

/// The reflection model's constants.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reflection {
    /// Shading model.
    pub shading: Shading,
    /// Specular reflectance.
    pub ks: V3,
    /// Specular exponent.
    pub shininess: f64,
    /// Ambient reflectance (`None`: the albedo).
    pub ka: Option<V3>,
}

/// Gradients of one shading evaluation.
#[derive(Clone, Copy, Debug, Default)]
pub struct ShadeGrad {
    /// Shading point.
    pub x: V3,
    /// Interpolated (unnormalised) normal.
    pub nraw: V3,
    /// Albedo.
    pub albedo: V3,
}

/// One light's term `C (albedo max(n.l, 0) + ks spec)` and, given the output gradient, its
/// gradients (accumulated into `gn`, `gv`, `gl`, `galb`; returned: `g_C`).
#[allow(clippy::too_many_arguments)]
fn term(
    m: &Reflection,
    n: V3,
    v: V3,
    l: V3,
    alb: V3,
    c: V3,
    g: Option<(V3, &mut [V3; 4])>,
) -> (V3, V3) {
    let z = [0.0; 3];
    let ndl = dot3(n, l);
    if ndl <= 0.0 {
        return (z, z);
    }
    let (mut base, mut rh, mut hl) = (0.0, z, 0.0);
    match m.shading {
        Shading::Phong => {
            rh = sub3(scale3(n, ndl + ndl), l);
            base = dot3(rh, v);
        }
        Shading::BlinnPhong => {
            let (h, len) = normalize3(add3(l, v), SAFE_EPS);
            rh = h;
            hl = len;
            base = dot3(n, h);
        }
        _ => {}
    }
    let spec = if base > 0.0 {
        base.powf(m.shininess)
    } else {
        0.0
    };
    let refl = add3(scale3(alb, ndl), scale3(m.ks, spec));
    let out = mul3(c, refl);
    let Some((gc, acc)) = g else {
        return (out, z);
    };
    // acc = [gn, gv, gl, galb]
    let g_c = mul3(gc, refl);
    let gcc = mul3(gc, c);
    acc3(&mut acc[3], scale3(gcc, ndl));
    let mut g_ndl = dot3(gcc, alb);
    if spec > 0.0 {
        let g_base = dot3(gcc, m.ks) * m.shininess * base.powf(m.shininess - 1.0);
        match m.shading {
            Shading::Phong => {
                let g_r = scale3(v, g_base);
                acc3(&mut acc[1], scale3(rh, g_base));
                g_ndl += 2.0 * dot3(g_r, n);
                acc3(&mut acc[0], scale3(g_r, 2.0 * ndl));
                acc3(&mut acc[2], scale3(g_r, -1.0));
            }
            Shading::BlinnPhong => {
                acc3(&mut acc[0], scale3(rh, g_base));
                let g_sum = normalize3_vjp(hl, rh, scale3(n, g_base), SAFE_EPS);
                acc3(&mut acc[2], g_sum);
                acc3(&mut acc[1], g_sum);
            }
            _ => {}
        }
    }
    acc3(&mut acc[0], scale3(l, g_ndl));
    acc3(&mut acc[2], scale3(n, g_ndl));
    (out, g_c)
}

/// Adds `v` to row `i` of a light-rows gradient (empty when the rows need none).
fn add_row(gr: &mut [V3], i: usize, v: V3) {
    if let Some(r) = gr.get_mut(i) {
        acc3(r, v);
    }
}

/// The scene's lights with their parameter rows (values of the light-rows input).
#[derive(Clone, Debug)]
pub struct LightSet<'a> {
    /// Kinds in scene order.
    pub kinds: &'a [LightKind],
    /// Parameter rows, `sum kinds.rows()` of them.
    pub rows: &'a [V3],
    /// Where each light's rows start (inline up to 8 lights: a set is built per sample).
    pub offsets: SmallVec<[usize; 8]>,
    /// Number of area lights.
    pub n_area: usize,
    /// Per light, for directional ones: the unit direction towards the light and the row's
    /// length (the same for every shading point, so normalised once per set).
    pub(super) toward: SmallVec<[(V3, f64); 8]>,
}

impl<'a> LightSet<'a> {
    /// Lights of `kinds` with parameters `rows`; `None` when the row count does not fit.
    pub fn new(kinds: &'a [LightKind], rows: &'a [V3]) -> Option<Self> {
        let mut offsets = SmallVec::new();
        let mut at = 0;
        for k in kinds {
            offsets.push(at);
            at += k.rows();
        }
        (at == rows.len()).then(|| LightSet {
            kinds,
            rows,
            n_area: kinds.iter().filter(|k| **k == LightKind::Area).count(),
            toward: kinds
                .iter()
                .zip(&offsets)
                .map(|(k, &o)| match k {
                    LightKind::Directional => normalize3(scale3(rows[o], -1.0), SAFE_EPS),
                    _ => ([0.0; 3], 0.0),
                })
                .collect(),
            offsets,
        })
    }

    /// The point of area light `i` (rows from `o`) at `(a, b)`.
    pub fn area_point(&self, o: usize, ab: [f64; 2]) -> V3 {
        let r = self.rows;
        add3(r[o], add3(scale3(r[o + 1], ab[0]), scale3(r[o + 2], ab[1])))
    }

    /// Shades the point `x` with interpolated normal `nraw` and `albedo`, seen from `eye`;
    /// `area_ab[k]` is the sample of the `k`-th area light; `visible` answers shadow queries.
    /// With `grad = Some((g, out, g_rows))` also accumulates the gradient of `g . colour`
    /// into `out` and `g_rows`.
    #[allow(clippy::too_many_arguments)]
    pub fn shade(
        &self,
        m: &Reflection,
        x: V3,
        nraw: V3,
        albedo: V3,
        eye: V3,
        area_ab: &[[f64; 2]],
        visible: &mut impl FnMut(Shadow) -> bool,
        grad: Option<(V3, &mut ShadeGrad, &mut [V3])>,
    ) -> V3 {
        let (n, nlen) = normalize3(nraw, SAFE_EPS);
        let z = [0.0; 3];
        let mut col = z;
        let (g, mut sg, mut grow) = match grad {
            Some((g, sg, gr)) => (Some(g), Some(sg), Some(gr)),
            None => (None, None, None),
        };
        // [gn, gv, gl, galb]
        let mut acc = [z; 4];
        match m.shading {
            Shading::None => {
                if let (Some(g), Some(sg)) = (g, sg.as_deref_mut()) {
                    acc3(&mut sg.albedo, g);
                }
                return albedo;
            }
            Shading::Sh => {
                let Some(k) = self.kinds.iter().position(|k| *k == LightKind::Sh) else {
                    return z;
                };
                let o = self.offsets[k];
                let y = sh_eval(n);
                let mut e = z;
                for j in 0..9 {
                    e = add3(e, scale3(self.rows[o + j], y[j]));
                }
                if let (Some(g), Some(sg), Some(gr)) = (g, sg, grow) {
                    acc3(&mut sg.albedo, mul3(g, e));
                    let ge = mul3(g, albedo);
                    let mut gy = [0.0; 9];
                    for j in 0..9 {
                        add_row(gr, o + j, scale3(ge, y[j]));
                        gy[j] = dot3(ge, self.rows[o + j]);
                    }
                    let gn = sh_eval_vjp(n, gy);
                    acc3(&mut sg.nraw, normalize3_vjp(nlen, n, gn, SAFE_EPS));
                }
                return mul3(albedo, e);
            }
            _ => {}
        }
        // The view direction: only the specular terms read it.
        let (v, vlen) = if matches!(m.shading, Shading::Phong | Shading::BlinnPhong) {
            normalize3(sub3(eye, x), SAFE_EPS)
        } else {
            (z, 0.0)
        };
        let ka = m.ka.unwrap_or(albedo);
        let mut area_k = 0;
        for (i, kind) in self.kinds.iter().enumerate() {
            let o = self.offsets[i];
            let r = self.rows;
            match kind {
                LightKind::Ambient => {
                    col = add3(col, mul3(ka, r[o]));
                    if let (Some(g), Some(gr)) = (g, grow.as_deref_mut()) {
                        add_row(gr, o, mul3(g, ka));
                        if m.ka.is_none() {
                            acc3(&mut acc[3], mul3(g, r[o]));
                        }
                    }
                }
                LightKind::Directional | LightKind::Point => {
                    let ((l, llen), shadow) = if *kind == LightKind::Directional {
                        (self.toward[i], Shadow::Along(scale3(r[o], -1.0)))
                    } else {
                        (normalize3(sub3(r[o], x), SAFE_EPS), Shadow::Toward(r[o]))
                    };
                    if dot3(n, l) <= 0.0 || !visible(shadow) {
                        continue;
                    }
                    let before = acc[2];
                    acc[2] = z;
                    let (t, g_c) = term(m, n, v, l, albedo, r[o + 1], g.map(|g| (g, &mut acc)));
                    col = add3(col, t);
                    if let (Some(_), Some(gr), Some(sg)) =
                        (g, grow.as_deref_mut(), sg.as_deref_mut())
                    {
                        add_row(gr, o + 1, g_c);
                        let g_raw = normalize3_vjp(llen, l, acc[2], SAFE_EPS);
                        if *kind == LightKind::Directional {
                            add_row(gr, o, scale3(g_raw, -1.0));
                        } else {
                            add_row(gr, o, g_raw);
                            acc3(&mut sg.x, scale3(g_raw, -1.0));
                        }
                    }
                    acc[2] = before;
                }
                LightKind::Area => {
                    let ab = area_ab[area_k];
                    area_k += 1;
                    let lp = self.area_point(o, ab);
                    let lraw = sub3(lp, x);
                    let (l, rl) = normalize3(lraw, SAFE_EPS);
                    let nl = cross3(r[o + 1], r[o + 2]);
                    let k = -dot3(nl, lraw);
                    if k <= 0.0 || rl <= SAFE_EPS || dot3(n, l) <= 0.0 {
                        continue;
                    }
                    if !visible(Shadow::Toward(lp)) {
                        continue;
                    }
                    let r3 = rl * rl * rl;
                    let f = k / r3;
                    let c = scale3(r[o + 3], f);
                    let before = acc[2];
                    acc[2] = z;
                    let (t, g_c) = term(m, n, v, l, albedo, c, g.map(|g| (g, &mut acc)));
                    col = add3(col, t);
                    if let (Some(_), Some(gr), Some(sg)) =
                        (g, grow.as_deref_mut(), sg.as_deref_mut())
                    {
                        add_row(gr, o + 3, scale3(g_c, f));
                        let g_f = dot3(g_c, r[o + 3]);
                        let mut g_raw = normalize3_vjp(rl, l, acc[2], SAFE_EPS);
                        let r5 = r3 * rl * rl;
                        g_raw = add3(
                            g_raw,
                            add3(scale3(nl, -g_f / r3), scale3(lraw, -3.0 * g_f * k / r5)),
                        );
                        let g_nl = scale3(lraw, -g_f / r3);
                        add_row(gr, o, g_raw);
                        add_row(
                            gr,
                            o + 1,
                            add3(cross3(r[o + 2], g_nl), scale3(g_raw, ab[0])),
                        );
                        add_row(
                            gr,
                            o + 2,
                            add3(cross3(g_nl, r[o + 1]), scale3(g_raw, ab[1])),
                        );
                        acc3(&mut sg.x, scale3(g_raw, -1.0));
                    }
                    acc[2] = before;
                }
                LightKind::Sh => {}
            }
        }
        if let Some(sg) = sg {
            acc3(&mut sg.albedo, acc[3]);
            acc3(&mut sg.nraw, normalize3_vjp(nlen, n, acc[0], SAFE_EPS));
            let g_vraw = normalize3_vjp(vlen, v, acc[1], SAFE_EPS);
            acc3(&mut sg.x, scale3(g_vraw, -1.0));
        }
        col
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hand-written gradient of `g . shade(...)` against central differences, for every
    /// model and light kind (visibility true).
    #[test]
    fn shading_gradient_matches_finite_differences() {
        let kinds = [
            LightKind::Ambient,
            LightKind::Directional,
            LightKind::Point,
            LightKind::Area,
        ];
        let rows0: Vec<V3> = vec![
            [0.1, 0.2, 0.05],
            [0.3, -1.0, -0.4],
            [0.9, 0.8, 0.7],
            [1.0, 2.0, 1.5],
            [0.6, 0.5, 0.9],
            [-0.5, 3.0, -0.5],
            [1.0, 0.1, 0.0],
            [0.0, 0.2, 1.0],
            [2.0, 1.5, 1.0],
        ];
        let x0 = [0.1, 0.2, -0.1];
        let n0 = [0.2, 1.0, 0.3];
        let a0 = [0.7, 0.5, 0.3];
        let eye = [0.5, 1.0, 3.0];
        let g = [0.3, -0.7, 1.1];
        let ab = [[0.3, 0.6]];
        for shading in [Shading::Lambert, Shading::Phong, Shading::BlinnPhong] {
            let m = Reflection {
                shading,
                ks: [0.3, 0.2, 0.4],
                shininess: 7.0,
                ka: None,
            };
            let f = |x: V3, nr: V3, a: V3, rows: &[V3]| {
                let ls = LightSet::new(&kinds, rows).unwrap();
                let c = ls.shade(&m, x, nr, a, eye, &ab, &mut |_| true, None);
                dot3(c, g)
            };
            let ls = LightSet::new(&kinds, &rows0).unwrap();
            let mut sg = ShadeGrad::default();
            let mut gr = vec![[0.0; 3]; rows0.len()];
            let _ = ls.shade(
                &m,
                x0,
                n0,
                a0,
                eye,
                &ab,
                &mut |_| true,
                Some((g, &mut sg, &mut gr)),
            );
            let h = 1e-6;
            for k in 0..3 {
                let d = |v: V3, s: f64| {
                    let mut v = v;
                    v[k] += s;
                    v
                };
                let nx = (f(d(x0, h), n0, a0, &rows0) - f(d(x0, -h), n0, a0, &rows0)) / (2.0 * h);
                let nn = (f(x0, d(n0, h), a0, &rows0) - f(x0, d(n0, -h), a0, &rows0)) / (2.0 * h);
                let na = (f(x0, n0, d(a0, h), &rows0) - f(x0, n0, d(a0, -h), &rows0)) / (2.0 * h);
                assert!(
                    (nx - sg.x[k]).abs() < 1e-6,
                    "{shading:?} x{k}: {nx} {}",
                    sg.x[k]
                );
                assert!(
                    (nn - sg.nraw[k]).abs() < 1e-6,
                    "{shading:?} n{k}: {nn} {}",
                    sg.nraw[k]
                );
                assert!((na - sg.albedo[k]).abs() < 1e-6, "{shading:?} a{k}");
                for r in 0..rows0.len() {
                    let mut p = rows0.clone();
                    p[r][k] += h;
                    let mut q = rows0.clone();
                    q[r][k] -= h;
                    let nr = (f(x0, n0, a0, &p) - f(x0, n0, a0, &q)) / (2.0 * h);
                    assert!(
                        (nr - gr[r][k]).abs() < 1e-6 * (1.0 + nr.abs()),
                        "{shading:?} row {r}.{k}: {nr} {}",
                        gr[r][k]
                    );
                }
            }
        }
    }
}
