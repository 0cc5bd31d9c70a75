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

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};

use super::lights::{Lights, Material, Reflectance};
use super::{
    add3, chunked, dot3, grad_tensor, light_rows, mul3, normalize3, normalize3_vjp, rows_of,
    scale3, sub3, Rows, SAFE_EPS, V3,
};

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
}

struct PhongOp<T: Real> {
    model: Reflectance,
    eps: T,
}

/// Everything a fragment's evaluation reads.
struct Inputs<'a, T: Real> {
    model: Reflectance,
    eps: T,
    pos: Rows<'a, T>,
    nrm: Rows<'a, T>,
    alb: Rows<'a, T>,
    ka: Rows<'a, T>,
    ks: Rows<'a, T>,
    s: T,
    eye: V3<T>,
    ambient: V3<T>,
    /// Directional lights: unit direction towards the light, its pre-normalisation length,
    /// the normalised travel direction, colour.
    dirs: Vec<(V3<T>, T, V3<T>, V3<T>)>,
    /// Point lights: position, colour.
    points: Vec<(V3<T>, V3<T>)>,
}

/// One light's contribution at a fragment, with what the backward needs.
struct LightEval<T> {
    l: V3<T>,
    /// `q - x` and its length (point lights).
    raw_len: T,
    ndl: T,
    diff: T,
    /// Specular active (`n . l > 0`, base > 0, not Lambert).
    spec_on: bool,
    base: T,
    spec: T,
    /// Phong: the reflected direction; Blinn: the half vector.
    rh: V3<T>,
    /// Blinn: `|l + v|`.
    h_len: T,
}

impl<T: Real> Inputs<'_, T> {
    fn specular(&self) -> bool {
        self.model != Reflectance::Lambert
    }

    fn light(&self, n: V3<T>, v: V3<T>, l: V3<T>, raw_len: T) -> LightEval<T> {
        let ndl = dot3(n, l);
        let z = T::zero();
        let diff = if ndl > z { ndl } else { z };
        let mut e = LightEval {
            l,
            raw_len,
            ndl,
            diff,
            spec_on: false,
            base: z,
            spec: z,
            rh: [z; 3],
            h_len: z,
        };
        if self.specular() && ndl > z {
            match self.model {
                Reflectance::Phong => {
                    let r = sub3(scale3(n, ndl + ndl), l);
                    e.rh = r;
                    e.base = dot3(r, v);
                }
                _ => {
                    let (h, hl) = normalize3(add3(l, v), self.eps);
                    e.rh = h;
                    e.h_len = hl;
                    e.base = dot3(n, h);
                }
            }
            if e.base > z {
                e.spec_on = true;
                e.spec = e.base.powf(self.s);
            }
        }
        e
    }

    /// `(n̂, |n|, v, |eye - x|)` of fragment `i`.
    fn frame(&self, i: usize) -> (V3<T>, T, V3<T>, T) {
        let (n, nl) = normalize3(self.nrm.get(i), self.eps);
        if self.specular() {
            let (v, vl) = normalize3(sub3(self.eye, self.pos.get(i)), self.eps);
            (n, nl, v, vl)
        } else {
            (n, nl, [T::zero(); 3], T::zero())
        }
    }

    fn lights_at(
        &self,
        i: usize,
        n: V3<T>,
        v: V3<T>,
    ) -> impl Iterator<Item = (LightEval<T>, V3<T>)> + '_ {
        let x = self.pos.get(i);
        let d = self
            .dirs
            .iter()
            .map(move |&(l, _, _, c)| (self.light(n, v, l, T::zero()), c));
        let p = self.points.iter().map(move |&(q, c)| {
            let (l, len) = normalize3(sub3(q, x), self.eps);
            (self.light(n, v, l, len), c)
        });
        d.chain(p)
    }

    fn color(&self, i: usize) -> V3<T> {
        let (n, _, v, _) = self.frame(i);
        let a = self.alb.get(i);
        let ks = self.ks.get(i);
        let mut col = mul3(self.ka.get(i), self.ambient);
        for (e, c) in self.lights_at(i, n, v) {
            let refl = add3(scale3(a, e.diff), scale3(ks, e.spec));
            col = add3(col, mul3(c, refl));
        }
        col
    }
}

/// Layout of the per-fragment gradient rows and of the shared accumulator.
struct Layout {
    /// Offsets in the per-fragment row (None: shared or not per row).
    alb: Option<usize>,
    ka: Option<usize>,
    ks: Option<usize>,
    width: usize,
    // Shared accumulator offsets.
    s_amb: usize,
    s_s: usize,
    s_eye: usize,
    s_alb: usize,
    s_ka: usize,
    s_ks: usize,
    s_dir: usize,
    s_pt: usize,
    n_shared: usize,
}

impl Layout {
    fn new<T: Real>(k: &Inputs<'_, T>) -> Self {
        let mut width = 6;
        let mut slot = |per_row: bool| {
            per_row.then(|| {
                width += 3;
                width - 3
            })
        };
        let alb = slot(k.alb.per_row);
        let ka = slot(k.ka.per_row);
        let ks = slot(k.ks.per_row);
        // Shared: ambient 0..3, shininess 3, eye 4..7, albedo 7..10, ka 10..13, ks 13..16,
        // then (colour, direction) per directional light and (colour, position) per point light.
        let s_dir = 16;
        let s_pt = s_dir + 6 * k.dirs.len();
        Layout {
            alb,
            ka,
            ks,
            width,
            s_amb: 0,
            s_s: 3,
            s_eye: 4,
            s_alb: 7,
            s_ka: 10,
            s_ks: 13,
            s_dir,
            s_pt,
            n_shared: s_pt + 6 * k.points.len(),
        }
    }
}

fn add_at<T: Real>(buf: &mut [T], at: usize, v: V3<T>) {
    buf[at] += v[0];
    buf[at + 1] += v[1];
    buf[at + 2] += v[2];
}

fn read_inputs<'a, T: Real>(
    model: Reflectance,
    eps: T,
    inputs: &'a [ndarray::CowArray<'_, T, ndarray::IxDyn>],
) -> AdResult<Inputs<'a, T>> {
    const OP: &str = "shade";
    if inputs[0].ndim() != 2 {
        return Err(AutodiffError::shape(
            OP,
            &[inputs[0].shape()],
            "positions must be [N, 3]",
        ));
    }
    let n = inputs[0].shape()[0];
    let pos = rows_of(OP, "positions", &inputs[0], n, false)?;
    let nrm = rows_of(OP, "normals", &inputs[1], n, false)?;
    let alb = rows_of(OP, "albedo", &inputs[2], n, true)?;
    let ka = rows_of(OP, "ka", &inputs[3], n, true)?;
    let ks = rows_of(OP, "ks", &inputs[4], n, true)?;
    if inputs[5].len() != 1 {
        return Err(AutodiffError::shape(
            OP,
            &[inputs[5].shape()],
            "shininess must have one element",
        ));
    }
    let s = *inputs[5].iter().next().expect("one element");
    if inputs[6].len() != 3 {
        return Err(AutodiffError::shape(
            OP,
            &[inputs[6].shape()],
            "eye must be [3]",
        ));
    }
    let e: Vec<T> = inputs[6].iter().copied().collect();
    let eye = [e[0], e[1], e[2]];
    let mut ambient = [T::zero(); 3];
    for a in light_rows(OP, "ambient colours", &inputs[7])? {
        ambient = add3(ambient, a);
    }
    let dd = light_rows(OP, "light directions", &inputs[8])?;
    let dc = light_rows(OP, "directional colours", &inputs[9])?;
    let pq = light_rows(OP, "light positions", &inputs[10])?;
    let pc = light_rows(OP, "point colours", &inputs[11])?;
    if dd.len() != dc.len() || pq.len() != pc.len() {
        return Err(AutodiffError::shape(
            OP,
            &[
                inputs[8].shape(),
                inputs[9].shape(),
                inputs[10].shape(),
                inputs[11].shape(),
            ],
            "one colour per light",
        ));
    }
    let dirs = dd
        .iter()
        .zip(&dc)
        .map(|(&d, &c)| {
            let (dh, len) = normalize3(d, eps);
            (scale3(dh, -T::one()), len, dh, c)
        })
        .collect();
    let points = pq.into_iter().zip(pc).collect();
    Ok(Inputs {
        model,
        eps,
        pos,
        nrm,
        alb,
        ka,
        ks,
        s,
        eye,
        ambient,
        dirs,
        points,
    })
}

impl<T: Real> Op<T> for PhongOp<T> {
    fn name(&self) -> &'static str {
        match self.model {
            Reflectance::Lambert => "lambert",
            Reflectance::Phong => "phong",
            Reflectance::BlinnPhong => "blinn_phong",
        }
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let std = super::standard_inputs(inputs);
        let k = read_inputs(self.model, self.eps, &std)?;
        let n = std[0].shape()[0];
        let (out, _) = chunked::<T, _>(n, 3, 0, |start, o, _| {
            for (r, row) in o.chunks_mut(3).enumerate() {
                row.copy_from_slice(&k.color(start + r));
            }
        });
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[n, 3]), out).expect("n x 3")
        ])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let std = super::standard_inputs(ctx.inputs);
        let k = read_inputs(self.model, self.eps, &std)?;
        let n = std[0].shape()[0];
        let lay = Layout::new(&k);
        let g = ctx.grad_outputs[0].as_standard_layout();
        let g = Rows {
            data: g.as_slice().expect("std"),
            per_row: true,
        };
        let z = T::zero();
        let two = T::one() + T::one();
        let (rows, shared) = chunked::<T, _>(n, lay.width, lay.n_shared, |start, o, acc| {
            for (r, row) in o.chunks_mut(lay.width).enumerate() {
                let i = start + r;
                let gi = g.get(i);
                let (nh, nl, v, vl) = k.frame(i);
                let a = k.alb.get(i);
                let ka = k.ka.get(i);
                let ks = k.ks.get(i);
                let (mut gn, mut gv, mut gx) = ([z; 3], [z; 3], [z; 3]);
                let (mut ga, mut gks) = ([z; 3], [z; 3]);
                // Ambient.
                let gka = mul3(k.ambient, gi);
                add_at(acc, lay.s_amb, mul3(ka, gi));
                for (j, (e, c)) in k.lights_at(i, nh, v).enumerate() {
                    let w = mul3(c, gi);
                    let refl = add3(scale3(a, e.diff), scale3(ks, e.spec));
                    let mut gl = [z; 3];
                    ga = add3(ga, scale3(w, e.diff));
                    let gdiff = dot3(w, a);
                    if e.spec_on {
                        gks = add3(gks, scale3(w, e.spec));
                        let gspec = dot3(w, ks);
                        let gbase = if k.s == z {
                            z
                        } else {
                            gspec * k.s * e.base.powf(k.s - T::one())
                        };
                        acc[lay.s_s] += gspec * e.spec * e.base.ln();
                        if k.model == Reflectance::Phong {
                            let gr = scale3(v, gbase);
                            gv = add3(gv, scale3(e.rh, gbase));
                            let grn = dot3(gr, nh);
                            gn = add3(gn, add3(scale3(e.l, two * grn), scale3(gr, two * e.ndl)));
                            gl = add3(gl, sub3(scale3(nh, two * grn), gr));
                        } else {
                            gn = add3(gn, scale3(e.rh, gbase));
                            let ghh = normalize3_vjp(e.h_len, e.rh, scale3(nh, gbase), k.eps);
                            gl = add3(gl, ghh);
                            gv = add3(gv, ghh);
                        }
                    }
                    if e.ndl > z {
                        gn = add3(gn, scale3(e.l, gdiff));
                        gl = add3(gl, scale3(nh, gdiff));
                    }
                    if j < k.dirs.len() {
                        let at = lay.s_dir + 6 * j;
                        add_at(acc, at, mul3(refl, gi));
                        add_at(acc, at + 3, gl);
                    } else {
                        let p = j - k.dirs.len();
                        let at = lay.s_pt + 6 * p;
                        add_at(acc, at, mul3(refl, gi));
                        let graw = normalize3_vjp(e.raw_len, e.l, gl, k.eps);
                        add_at(acc, at + 3, graw);
                        gx = sub3(gx, graw);
                    }
                }
                if k.specular() {
                    let gvraw = normalize3_vjp(vl, v, gv, k.eps);
                    add_at(acc, lay.s_eye, gvraw);
                    gx = sub3(gx, gvraw);
                }
                let gnraw = normalize3_vjp(nl, nh, gn, k.eps);
                row[0..3].copy_from_slice(&gx);
                row[3..6].copy_from_slice(&gnraw);
                match lay.alb {
                    Some(o) => row[o..o + 3].copy_from_slice(&ga),
                    None => add_at(acc, lay.s_alb, ga),
                }
                match lay.ka {
                    Some(o) => row[o..o + 3].copy_from_slice(&gka),
                    None => add_at(acc, lay.s_ka, gka),
                }
                match lay.ks {
                    Some(o) => row[o..o + 3].copy_from_slice(&gks),
                    None => add_at(acc, lay.s_ks, gks),
                }
            }
        });
        let column = |off: usize| -> Vec<T> {
            let mut v = Vec::with_capacity(3 * n);
            for r in rows.chunks(lay.width) {
                v.extend_from_slice(&r[off..off + 3]);
            }
            v
        };
        let per_row_or_shared = |idx: usize, off: Option<usize>, s_off: usize| -> Tensor<T> {
            match off {
                Some(o) => grad_tensor(ctx.inputs[idx].shape(), column(o)),
                None => grad_tensor(ctx.inputs[idx].shape(), shared[s_off..s_off + 3].to_vec()),
            }
        };
        let nd = k.dirs.len();
        let np = k.points.len();
        let need = |i: usize| ctx.needs_grad[i];
        let mut out: Vec<Option<Tensor<T>>> = vec![None; 12];
        if need(0) {
            out[0] = Some(grad_tensor(&[n, 3], column(0)));
        }
        if need(1) {
            out[1] = Some(grad_tensor(&[n, 3], column(3)));
        }
        if need(2) {
            out[2] = Some(per_row_or_shared(2, lay.alb, lay.s_alb));
        }
        if need(3) {
            out[3] = Some(per_row_or_shared(3, lay.ka, lay.s_ka));
        }
        if need(4) {
            out[4] = Some(per_row_or_shared(4, lay.ks, lay.s_ks));
        }
        if need(5) {
            out[5] = Some(grad_tensor(ctx.inputs[5].shape(), vec![shared[lay.s_s]]));
        }
        if need(6) {
            out[6] = Some(grad_tensor(
                ctx.inputs[6].shape(),
                shared[lay.s_eye..lay.s_eye + 3].to_vec(),
            ));
        }
        if need(7) {
            // Every ambient light gets the gradient of their sum.
            let la = ctx.inputs[7].len() / 3;
            let gs: Vec<T> = (0..la)
                .flat_map(|_| shared[lay.s_amb..lay.s_amb + 3].to_vec())
                .collect();
            out[7] = Some(grad_tensor(ctx.inputs[7].shape(), gs));
        }
        if need(8) {
            // l = -normalize(d): dL/dd = normalize_vjp(-sum of dL/dl).
            let gd: Vec<T> = (0..nd)
                .flat_map(|j| {
                    let (_, len, dh, _) = k.dirs[j];
                    let at = lay.s_dir + 6 * j + 3;
                    let gl = [shared[at], shared[at + 1], shared[at + 2]];
                    normalize3_vjp(len, dh, scale3(gl, -T::one()), k.eps)
                })
                .collect();
            out[8] = Some(grad_tensor(ctx.inputs[8].shape(), gd));
        }
        if need(9) {
            let gc: Vec<T> = (0..nd)
                .flat_map(|j| shared[lay.s_dir + 6 * j..lay.s_dir + 6 * j + 3].to_vec())
                .collect();
            out[9] = Some(grad_tensor(ctx.inputs[9].shape(), gc));
        }
        if need(10) {
            let gq: Vec<T> = (0..np)
                .flat_map(|j| shared[lay.s_pt + 6 * j + 3..lay.s_pt + 6 * j + 6].to_vec())
                .collect();
            out[10] = Some(grad_tensor(ctx.inputs[10].shape(), gq));
        }
        if need(11) {
            let gc: Vec<T> = (0..np)
                .flat_map(|j| shared[lay.s_pt + 6 * j..lay.s_pt + 6 * j + 3].to_vec())
                .collect();
            out[11] = Some(grad_tensor(ctx.inputs[11].shape(), gc));
        }
        Ok(out)
    }
}

/// The fused reflection model of `material` (Lambert, Phong or Blinn-Phong, see the module
/// docs) at every fragment of `surface`, seen from `eye` (`[3]`): colours `[N, 3]`.
///
/// One tape op with a hand-written backward, parallel over fragments. Gradients reach the
/// positions, normals, albedo, `ka`, `ks`, shininess, the eye and every light's parameters.
/// Shape errors poison the result (see [`autodiff::Tape`]).
pub fn shade<'t, T: Real>(
    surface: &Surface<'t, T>,
    material: &Material<'t, T>,
    lights: &Lights<'t, T>,
    eye: Var<'t, T>,
) -> Var<'t, T> {
    let t = surface.position.tape();
    let ins = [
        surface.position,
        surface.normal,
        surface.albedo,
        material.ka.unwrap_or(surface.albedo),
        material.ks,
        material.shininess,
        eye,
        Lights::stacked(t, &lights.ambient, |l| l.color),
        Lights::stacked(t, &lights.directional, |l| l.direction),
        Lights::stacked(t, &lights.directional, |l| l.color),
        Lights::stacked(t, &lights.point, |l| l.position),
        Lights::stacked(t, &lights.point, |l| l.color),
    ];
    let op = PhongOp {
        model: material.model,
        eps: T::from_f64c(SAFE_EPS),
    };
    t.apply(op, &ins)
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
    let mut add_light = |l: Var<'t, T>, color: Var<'t, T>| {
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
        add(refl * color.reshape(&[3]));
    };
    for d in &lights.directional {
        let l = (-d.direction.reshape(&[3])).normalize(eps);
        add_light(l, d.color);
    }
    for p in &lights.point {
        let l = (p.position.reshape(&[3]) - surface.position).normalize(eps);
        add_light(l, p.color);
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
