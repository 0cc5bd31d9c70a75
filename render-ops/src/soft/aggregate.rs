//! SoftRas's blend op over per-fragment colours of the soft rasterization stage
//! ([`super::stage`]): [`softras_blend`] takes colours `[N, C]` (interpolated, textured or
//! shaded per fragment), the fragments' coverage probabilities `D` `[N]` and normalised depths,
//! and gives an image `[H, W, C + 1]` whose last channel is the silhouette `alpha = 1 - prod_f
//! (1 - D_f)`. Liu et al. 2019, eq. 5-6: `I = (sum_f D_f e_f c_f + e_b bg) / (sum_f D_f e_f +
//! e_b)`, `e_f = exp((zn_f - m) / gamma)`, `e_b = exp((eps - m) / gamma)`, `m = max(eps, max_f
//! zn_f)`, with `zn` the normalised inverse depth (larger is nearer).
//!
//! DIB-R needs no blend over soft fragments: its colour is the hard foreground and only its
//! alpha is soft, so the registry composes it from the hard rasterizer's fragments and
//! [`super::dibr::dibr_alpha`] (`crate::methods::render_fragments`), shading each pixel once.
//!
//! Silhouette stability (as the fused ops): `P = prod (1 - D)` is a plain product; where `P >=
//! 1/2` the silhouette is `-expm1(sum log1p(-D))`. Its gradient is `prod_{j != f} (1 - D_j)`,
//! `P / (1 - D_f)` while both are normal numbers, the product of the others otherwise.
//!
//! The op runs forward in parallel over image rows and backward in parallel over fixed chunks
//! of fragments (each fragment's gradient depends only on its pixel's aggregate, written by
//! the forward): no sums across pixels, so results are bit-identical for any thread count.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::common::exp;
use super::stage::SoftFragments;
use crate::error::RenderError;
use crate::raster::{per_fragment, Fragments};

/// Settings of the SoftRas blend ([`softras_aggregate`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SoftBlendSettings {
    /// Depth blending temperature in `z01` units (default 1e-4).
    pub gamma: f64,
    /// Background depth term (default 1e-3).
    pub eps: f64,
    /// Near plane (for `zn = 1 - (z - near) / (far - near)`).
    pub near: f64,
    /// Far plane.
    pub far: f64,
    /// Background value per channel (empty: zeros).
    pub background: Vec<f64>,
}

impl SoftBlendSettings {
    /// Defaults (gamma 1e-4, eps 1e-3) with the given near and far planes.
    pub fn new(near: f64, far: f64) -> Self {
        Self {
            gamma: 1e-4,
            eps: 1e-3,
            near,
            far,
            background: Vec::new(),
        }
    }
}

/// The fragments' normalised inverse depth `zn = 1 - (z - near) / (far - near)` from their view
/// depth `z`, on the tape.
pub fn normalized_depth<'t, T: Real>(view_depth: Var<'t, T>, near: f64, far: f64) -> Var<'t, T> {
    (view_depth - T::from_f64c(near)) * T::from_f64c(-1.0 / (far - near)) + T::one()
}

/// SoftRas over the soft stage's fragments: colours `[N, C]` blended with the fragments'
/// probabilities and depths (see the module documentation): an image `[H, W, C + 1]`.
pub fn softras_aggregate<'t, T: Real>(
    frags: &SoftFragments<'t, T>,
    colors: Var<'t, T>,
    s: &SoftBlendSettings,
) -> Result<Var<'t, T>, RenderError> {
    if !(s.far > s.near && s.near.is_finite() && s.far.is_finite()) {
        return Err(AutodiffError::invalid(
            "softras_blend",
            format!("need near < far, got near {} far {}", s.near, s.far),
        )
        .into());
    }
    let zn = normalized_depth(frags.raster.view_depth, s.near, s.far);
    softras_blend(
        colors,
        frags.prob,
        zn,
        &frags.raster.fragments,
        s.gamma,
        s.eps,
        &s.background,
    )
}

fn check<T: Real>(
    op: &'static str,
    colors: &Var<'_, T>,
    per_fragment: &[&Var<'_, T>],
    f: &Fragments<T>,
    background: &[f64],
) -> Result<usize, RenderError> {
    let (cs, n) = (colors.shape(), f.len());
    if cs.len() != 2 || cs[0] != n {
        return Err(AutodiffError::shape(op, &[&cs], format!("colours must be [{n}, C]")).into());
    }
    for v in per_fragment {
        let s = v.shape();
        if s != [n] {
            return Err(AutodiffError::shape(
                op,
                &[&s],
                format!("per-fragment values must be [{n}]"),
            )
            .into());
        }
    }
    if !background.is_empty() && background.len() != cs[1] {
        return Err(AutodiffError::invalid(
            op,
            format!(
                "background has {} values for {} channels",
                background.len(),
                cs[1]
            ),
        )
        .into());
    }
    if background.iter().any(|b| !b.is_finite()) {
        return Err(AutodiffError::invalid(op, "background must be finite").into());
    }
    Ok(cs[1])
}

fn bg_of(background: &[f64], c: usize) -> Vec<f64> {
    (0..c)
        .map(|ch| background.get(ch).copied().unwrap_or(0.0))
        .collect()
}

/// The SoftRas blend op over per-fragment colours `[N, C]`, probabilities `D` `[N]` and
/// normalised inverse depths `zn` `[N]` of `fragments` (eq. 5-6 of Liu et al. 2019, see the
/// module documentation), with an exact backward to all three.
pub fn softras_blend<'t, T: Real>(
    colors: Var<'t, T>,
    prob: Var<'t, T>,
    zn: Var<'t, T>,
    fragments: &Arc<Fragments<T>>,
    gamma: f64,
    eps: f64,
    background: &[f64],
) -> Result<Var<'t, T>, RenderError> {
    let c = check(
        "softras_blend",
        &colors,
        &[&prob, &zn],
        fragments,
        background,
    )?;
    if !(gamma > 0.0 && gamma.is_finite() && eps.is_finite()) {
        return Err(AutodiffError::invalid(
            "softras_blend",
            format!("gamma must be finite and > 0 and eps finite, got {gamma}, {eps}"),
        )
        .into());
    }
    let op = SoftBlendOp {
        f: fragments.clone(),
        gamma,
        eps,
        bg: bg_of(background, c),
        pix: Vec::new(),
    };
    Ok(colors.tape().apply(op, &[colors, prob, zn]))
}

fn to_f64<T: Real, S: ndarray::Data<Elem = T>>(
    t: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> Vec<f64> {
    t.as_standard_layout().iter().map(|x| x.to_f64c()).collect()
}

/// The silhouette of probabilities `d`: `(alpha, P)` with `P = prod (1 - D)`.
#[inline]
fn silhouette(d: &[f64]) -> (f64, f64) {
    let p: f64 = d.iter().map(|&x| 1.0 - x).product();
    if p < 0.5 {
        (1.0 - p, p)
    } else {
        (-d.iter().map(|&x| (-x).ln_1p()).sum::<f64>().exp_m1(), p)
    }
}

/// `prod_{j != i} (1 - d_j)` given `P = prod_j (1 - d_j)`.
#[inline]
fn leave_one_out(d: &[f64], i: usize, p: f64) -> f64 {
    let omd = 1.0 - d[i];
    if p >= f64::MIN_POSITIVE && omd >= f64::MIN_POSITIVE {
        return p / omd;
    }
    d.iter()
        .enumerate()
        .filter(|&(j, _)| j != i)
        .map(|(_, &x)| 1.0 - x)
        .product()
}

/// Runs `pixel(p, range, out)` for every pixel, rows in parallel, each pixel writing `per`
/// values of an image `[H, W, per]`.
fn per_pixel<T: Real, F>(f: &Fragments<T>, per: usize, pixel: F) -> Vec<f64>
where
    F: Fn(usize, std::ops::Range<usize>, &mut [f64]) + Sync,
{
    let w = f.width;
    let mut out = vec![0.0; f.num_pixels() * per];
    out.par_chunks_mut(w * per)
        .enumerate()
        .for_each(|(row, o)| {
            for (col, px) in o.chunks_mut(per).enumerate() {
                let p = row * w + col;
                pixel(p, f.pixel_range(p), px);
            }
        });
    out
}

fn image<T: Real>(f: &Fragments<T>, per: usize, pix: &[f64], c1: usize) -> Tensor<T> {
    let data = pix
        .chunks(per)
        .flat_map(|px| px[..c1].iter().map(|&x| T::from_f64c(x)))
        .collect();
    ArrayD::from_shape_vec(IxDyn(&[f.height, f.width, c1]), data).expect("h x w x c1")
}

fn tensor<T: Real>(v: Vec<f64>, shape: &[usize]) -> Tensor<T> {
    ArrayD::from_shape_vec(IxDyn(shape), v.into_iter().map(T::from_f64c).collect()).expect("shape")
}

struct SoftBlendOp<T: Real> {
    f: Arc<Fragments<T>>,
    gamma: f64,
    eps: f64,
    bg: Vec<f64>,
    /// Per pixel: the `C` colours, alpha, then `m`, `Z`, `P` (the forward's aggregate).
    pix: Vec<f64>,
}

impl<T: Real> Op<T> for SoftBlendOp<T> {
    fn name(&self) -> &'static str {
        "softras_blend"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let c = inputs[0].shape()[1];
        let (col, d, zn) = (to_f64(&inputs[0]), to_f64(&inputs[1]), to_f64(&inputs[2]));
        let (f, bg) = (&*self.f, &self.bg);
        let (inv_gamma, eps) = (1.0 / self.gamma, self.eps);
        let per = c + 4;
        self.pix = per_pixel(f, per, |_, r, out| {
            if r.is_empty() {
                out[..c].copy_from_slice(bg);
                return;
            }
            let m = zn[r.clone()].iter().fold(eps, |a, &b| a.max(b));
            let eb = exp((eps - m) * inv_gamma);
            let mut z = eb;
            for (o, &b) in out[..c].iter_mut().zip(bg) {
                *o = eb * b;
            }
            for i in r.clone() {
                let we = d[i] * exp((zn[i] - m) * inv_gamma);
                z += we;
                for ch in 0..c {
                    out[ch] += we * col[i * c + ch];
                }
            }
            for o in &mut out[..c] {
                *o /= z;
            }
            let (alpha, p) = silhouette(&d[r]);
            out[c] = alpha;
            out[c + 1] = m;
            out[c + 2] = z;
            out[c + 3] = p;
        });
        Ok(vec![image(f, per, &self.pix, c + 1)])
    }

    /// Per fragment, with `g` its pixel's colour gradient, `I` the pixel's colour and `a`
    /// the alpha gradient: `dL/dc_f = g D e / Z`, `dL/dD_f = e (g . (c_f - I)) / Z + a
    /// prod_{j != f} (1 - D_j)`, `dL/dzn_f = D e (g . (c_f - I)) / (Z gamma)` (`I` does not
    /// depend on `m`).
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let c = ctx.inputs[0].shape()[1];
        let (col, d, zn) = (
            to_f64(&ctx.inputs[0]),
            to_f64(&ctx.inputs[1]),
            to_f64(&ctx.inputs[2]),
        );
        let go = to_f64(ctx.grad_outputs[0]);
        let f = &*self.f;
        let per = c + 4;
        let inv_gamma = 1.0 / self.gamma;
        let pix = &self.pix;
        // Per fragment: C colour gradients, then dD, dzn.
        let g = per_fragment(f, c + 2, |i, p, out| {
            let st = &pix[p * per..(p + 1) * per];
            let gp = &go[p * (c + 1)..(p + 1) * (c + 1)];
            let (m, z, pp) = (st[c + 1], st[c + 2], st[c + 3]);
            let e = exp((zn[i] - m) * inv_gamma);
            let scale = d[i] * e / z;
            let mut dot = 0.0;
            for ch in 0..c {
                out[ch] = gp[ch] * scale;
                dot += gp[ch] * (col[i * c + ch] - st[ch]);
            }
            let r = f.pixel_range(p);
            let loo = if gp[c] != 0.0 {
                leave_one_out(&d[r.clone()], i - r.start, pp)
            } else {
                0.0
            };
            out[c] = e * dot / z + gp[c] * loo;
            out[c + 1] = scale * dot * inv_gamma;
        });
        let n = f.len();
        let pick = |k: usize| -> Vec<f64> { g.chunks(c + 2).map(|r| r[k]).collect() };
        let gc = ctx.needs_grad[0].then(|| {
            tensor(
                g.chunks(c + 2)
                    .flat_map(|r| r[..c].iter().copied())
                    .collect(),
                &[n, c],
            )
        });
        Ok(vec![
            gc,
            ctx.needs_grad[1].then(|| tensor(pick(c), &[n])),
            ctx.needs_grad[2].then(|| tensor(pick(c + 1), &[n])),
        ])
    }
}
