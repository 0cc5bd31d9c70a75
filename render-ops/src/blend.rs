//! Compositing per-fragment colours into an image. The hard (z-buffer) blend takes each
//! pixel's nearest fragment and composites it over the background: output [H, W, C + 1] with
//! the coverage (0 or 1) as the last channel (alpha).

use std::mem::MaybeUninit;
use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::raster::{per_fragment, Fragments};
use crate::rasterize::as_arrays;

struct HardBlendOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    background: Vec<T>,
}

impl<T: Real> Op<T> for HardBlendOp<T> {
    fn name(&self) -> &'static str {
        "blend_hard"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let col = inputs[0].as_standard_layout();
        let f = &self.fragments;
        let (h, w) = (f.height, f.width);
        let c = self.background.len();
        if col.shape() != [f.face.len(), c] {
            return Err(AutodiffError::shape(
                "blend_hard",
                &[col.shape()],
                format!(
                    "fragment colours must be [{}, {c}] (fragments x background channels)",
                    f.face.len()
                ),
            ));
        }
        let cs = col.as_slice().expect("std");
        let n = h * w * (c + 1);
        let mut img = Vec::with_capacity(n);
        let out = &mut img.spare_capacity_mut()[..n];
        match c {
            3 => blend_rows::<T, 3, 4>(f, cs, &self.background, out),
            1 => blend_rows::<T, 1, 2>(f, cs, &self.background, out),
            2 => blend_rows::<T, 2, 3>(f, cs, &self.background, out),
            4 => blend_rows::<T, 4, 5>(f, cs, &self.background, out),
            _ => blend_rows::<T, 0, 1>(f, cs, &self.background, out),
        }
        // SAFETY: `blend_rows` wrote all `n` values of every pixel.
        unsafe { img.set_len(n) };
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[h, w, c + 1]), img).expect("h w c")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let f = &self.fragments;
        let c = self.background.len();
        let g = ctx.grad_outputs[0].as_standard_layout();
        let gs = g.as_slice().expect("std");
        let mut gc = vec![T::zero(); f.face.len() * c];
        // Each fragment is the first of at most one pixel: a direct write per pixel, in
        // parallel over image rows (each a contiguous run of fragments).
        let w = f.width;
        let mut rows: Vec<(usize, &mut [T])> = Vec::with_capacity(f.height);
        let mut rest = &mut gc[..];
        for r in 0..f.height {
            let n = (f.offsets[(r + 1) * w] - f.offsets[r * w]) as usize;
            let (a, b) = rest.split_at_mut(n * c);
            rows.push((r, a));
            rest = b;
        }
        rows.into_par_iter().with_min_len(8).for_each(|(r, out)| {
            let base = f.offsets[r * w] as usize;
            for x in 0..w {
                let p = r * w + x;
                let (s, e) = (f.offsets[p] as usize, f.offsets[p + 1] as usize);
                if s < e {
                    out[(s - base) * c..(s - base + 1) * c]
                        .copy_from_slice(&gs[p * (c + 1)..p * (c + 1) + c]);
                }
            }
        });
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(&[f.face.len(), c]), gc).expect("n c"),
        )])
    }
}

/// The image rows of the hard blend for `C` channels (`C = 0`: `bg.len()`, known only at run
/// time), in parallel over rows, writing every value of the (uninitialised) image.
/// `cs` holds `C` values per fragment (`bg.len()` when `C = 0`).
fn blend_rows<T: Real, const C: usize, const P: usize>(
    f: &Fragments<T>,
    cs: &[T],
    bg: &[T],
    img: &mut [MaybeUninit<T>],
) {
    let w = f.width;
    if C > 0 {
        debug_assert_eq!(P, C + 1);
        // Colour rows as `[T; C]` arrays, pixels as `[T; C + 1]`: each image row is first
        // the background (alpha 0), then each covered pixel gets its fragment's colour and
        // alpha 1; each pixel reads the offset where the next one starts once.
        let cs = as_arrays::<T, C>(cs);
        let mut empty = [T::zero(); P];
        empty[..C].copy_from_slice(bg);
        // Background first (a copy of one empty row), then the covered pixels.
        let empty_row = vec![empty.map(MaybeUninit::new); w];
        let pixels = crate::rasterize::as_arrays_mut::<MaybeUninit<T>, P>(img);
        pixels.par_chunks_mut(w).enumerate().for_each(|(row, out)| {
            let offs = &f.offsets[row * w..=(row + 1) * w];
            out.copy_from_slice(&empty_row);
            let mut s = offs[0] as usize;
            for (px, &e) in out.iter_mut().zip(&offs[1..]) {
                let e = e as usize;
                if s < e {
                    let c = &cs[s];
                    for ch in 0..C {
                        px[ch] = MaybeUninit::new(c[ch]);
                    }
                    px[C] = MaybeUninit::new(T::one());
                }
                s = e;
            }
        });
        return;
    }
    let c = bg.len();
    img.par_chunks_mut(w * (c + 1))
        .enumerate()
        .for_each(|(row, out)| {
            let offs = &f.offsets[row * w..=(row + 1) * w];
            for (x, px) in out.chunks_exact_mut(c + 1).enumerate() {
                let (s, e) = (offs[x] as usize, offs[x + 1] as usize);
                let (src, alpha) = if s < e {
                    (&cs[s * c..][..c], T::one())
                } else {
                    (&bg[..c], T::zero())
                };
                for (o, &v) in px[..c].iter_mut().zip(src) {
                    o.write(v);
                }
                px[c].write(alpha);
            }
        });
}

/// Hard z-buffer compositing of fragment colours [N, C] over `background` (C values):
/// an image [H, W, C + 1] whose last channel is the coverage.
pub fn blend_hard<'t, T: Real>(
    colors: Var<'t, T>,
    fragments: &Arc<Fragments<T>>,
    background: &[T],
) -> Result<Var<'t, T>, RenderError> {
    let op = HardBlendOp {
        fragments: fragments.clone(),
        background: background.to_vec(),
    };
    Ok(colors.tape().apply(op, &[colors]))
}

/// The area-weighted blend of [`crate::analytic`]: per pixel
/// `sum_i w_i c_i + (1 - sum_i w_i) background`, and the coverage `sum_i w_i` as the last
/// channel (the box-filtered image when `w_i` are the fragments' visible areas).
struct WeightedBlendOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    background: Vec<T>,
}

impl<T: Real> WeightedBlendOp<T> {
    fn check<S: ndarray::Data<Elem = T>>(
        &self,
        col: &ndarray::ArrayBase<S, ndarray::IxDyn>,
        weight: &ndarray::ArrayBase<S, ndarray::IxDyn>,
    ) -> AdResult<()> {
        let (n, c) = (self.fragments.len(), self.background.len());
        if col.shape() != [n, c] || weight.shape() != [n] {
            return Err(AutodiffError::shape(
                "blend_weighted",
                &[col.shape(), weight.shape()],
                format!("fragment colours must be [{n}, {c}] and weights [{n}]"),
            ));
        }
        Ok(())
    }
}

impl<T: Real> Op<T> for WeightedBlendOp<T> {
    fn name(&self) -> &'static str {
        "blend_weighted"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        self.check(&inputs[0], &inputs[1])?;
        let col = inputs[0].as_standard_layout();
        let wt = inputs[1].as_standard_layout();
        let (cs, ws) = (col.as_slice().expect("std"), wt.as_slice().expect("std"));
        let f = &self.fragments;
        let (h, w, c) = (f.height, f.width, self.background.len());
        let bg: Vec<f64> = self.background.iter().map(|x| x.to_f64c()).collect();
        let mut img = vec![T::zero(); h * w * (c + 1)];
        img.par_chunks_mut(w * (c + 1))
            .enumerate()
            .for_each(|(row, out)| {
                let mut acc = vec![0.0f64; c];
                for (x, px) in out.chunks_exact_mut(c + 1).enumerate() {
                    let p = row * w + x;
                    acc.iter_mut().for_each(|a| *a = 0.0);
                    let mut cov = 0.0f64;
                    for i in f.offsets[p] as usize..f.offsets[p + 1] as usize {
                        let wi = ws[i].to_f64c();
                        cov += wi;
                        for ch in 0..c {
                            acc[ch] += wi * cs[i * c + ch].to_f64c();
                        }
                    }
                    for ch in 0..c {
                        px[ch] = T::from_f64c(acc[ch] + (1.0 - cov) * bg[ch]);
                    }
                    px[c] = T::from_f64c(cov);
                }
            });
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[h, w, c + 1]), img).expect("h w c")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let f = &self.fragments;
        let (n, c) = (f.len(), self.background.len());
        let col = ctx.inputs[0].as_standard_layout();
        let wt = ctx.inputs[1].as_standard_layout();
        let (cs, ws) = (col.as_slice().expect("std"), wt.as_slice().expect("std"));
        let g = ctx.grad_outputs[0].as_standard_layout();
        let gs = g.as_slice().expect("std");
        let bg: Vec<f64> = self.background.iter().map(|x| x.to_f64c()).collect();
        // Per fragment: the colour gradient `w_i g_p` (C values) and the weight gradient
        // `g_p[C] + (c_i - bg) . g_p` (one), in one walk over the fragments.
        let (gc_on, gw_on) = (ctx.needs_grad[0], ctx.needs_grad[1]);
        let g = per_fragment(f, c + 1, |i, p, o| {
            let gp = &gs[p * (c + 1)..(p + 1) * (c + 1)];
            let wi = ws[i].to_f64c();
            let mut s = gp[c].to_f64c();
            for ch in 0..c {
                let gch = gp[ch].to_f64c();
                o[ch] = wi * gch;
                if gw_on {
                    s += (cs[i * c + ch].to_f64c() - bg[ch]) * gch;
                }
            }
            o[c] = s;
        });
        let gcol = gc_on.then(|| {
            let data = g
                .chunks_exact(c + 1)
                .flat_map(|o| o[..c].iter().map(|&x| T::from_f64c(x)))
                .collect();
            ArrayD::from_shape_vec(IxDyn(&[n, c]), data).expect("n c")
        });
        let gw = gw_on.then(|| {
            let data = g.chunks_exact(c + 1).map(|o| T::from_f64c(o[c])).collect();
            ArrayD::from_shape_vec(IxDyn(&[n]), data).expect("n")
        });
        Ok(vec![gcol, gw])
    }
}

/// Area-weighted compositing of fragment colours `[N, C]` with weights `[N]` (each pixel's
/// summing to at most 1: the visible areas of [`crate::analytic::analytic_fragments`]) over
/// `background` (`C` values): an image `[H, W, C + 1]`, per pixel
/// `sum_i w_i c_i + (1 - sum_i w_i) background`, last channel `sum_i w_i`.
///
/// # Errors
/// Shapes (colours not `[N, C]`, weights not `[N]`).
pub fn blend_weighted<'t, T: Real>(
    colors: Var<'t, T>,
    weights: Var<'t, T>,
    fragments: &Arc<Fragments<T>>,
    background: &[T],
) -> Result<Var<'t, T>, RenderError> {
    let op = WeightedBlendOp {
        fragments: fragments.clone(),
        background: background.to_vec(),
    };
    let (cv, wv) = (colors.value_ref()?, weights.value_ref()?);
    op.check(&cv.view(), &wv.view())?;
    Ok(colors.tape().apply(op, &[colors, weights]))
}
