//! OpenDR's gradients (M. M. Loper and M. J. Black, "OpenDR: An Approximate Differentiable
//! Renderer", ECCV 2014, its derivatives of the image with respect to vertex positions;
//! section 4.1 of H. Kato et al., "Differentiable Rendering: A Survey", 2020).
//!
//! # Forward
//!
//! The hard render (z-buffer, perspective-correct interpolation of the per-vertex attributes,
//! background where nothing is covered, alpha = coverage), bit-identical to `rasterize` +
//! `interpolate` + `blend_hard`.
//!
//! # Backward
//!
//! OpenDR writes the derivative of pixel `p` with respect to the screen-space position `x_k` of a
//! vertex as the image-space gradient of the rendered image times the motion of the image
//! content under `p` (the chain rule through the 2D projection):
//!
//! `dI_p / dx_k = -(dI/dp)(p) w_k(p)`,
//!
//! i.e. moving the vertex by `delta` moves the image content near `p` by `w_k(p) delta`, where
//! `w_k(p)` is the screen-space barycentric weight of vertex `k` at `p` in the triangle that
//! carries the content (the barycentric chain), and `dI/dp` is estimated from the rendered image
//! by the central-difference filter `1/2 [-1, 0, 1]` along columns and rows. Each axis's central
//! difference is split into its two halves, `1/2 (I_p - I_l)` and `1/2 (I_r - I_p)` (`l`, `r`
//! the previous and next pixel), and each half is attributed to a triangle according to whether
//! an occlusion boundary separates the two pixels: a boundary where exactly one of them is
//! covered, or where their nearest triangles differ and share no vertex (the surface is not
//! continuous there). This gives the paper's three pixel classes, per axis:
//!
//! * **Interior** (no boundary on either side): the central difference, chained through the
//!   barycentric weights of the pixel's own triangle.
//! * **Single boundary** (a boundary on one side): the half on the smooth side is a one-sided
//!   difference chained through the pixel's own triangle; the half across the boundary (half the
//!   jump of the image at the edge) is chained to the occluding triangle (the covered one, or the
//!   nearer of the two), with its barycentric weights at the pixel clamped to the triangle and
//!   renormalised, i.e. to the vertices of its edge, weighted by the position along it (an
//!   edge-based gradient). The pixels on both sides of an edge each take half the jump, so moving
//!   the edge by one pixel accounts for one full jump, as for a box-filtered image.
//! * **Multi boundary** (boundaries on both sides, e.g. one-pixel-thin features): each half is
//!   the jump across its own boundary, chained to that boundary's occluding triangle.
//!
//! Pixels at the image border take a zero difference towards the outside. The alpha channel is
//! part of the image and gets its derivative in the same way. Gradients with respect to the
//! attributes are the exact ones of the forward. Screen positions are chained to clip `x`, `y`,
//! `w` through the perspective divide; triangles with a vertex at `w <= 0` get no position
//! gradient.
//!
//! This op takes per-vertex colours (interpolated attributes); over the image of any shader or
//! texture, [`crate::boundary::opendr_antialias()`] adds the boundary part of this derivative and leaves
//! the interior to the exact chain through the shader.
//!
//! Deterministic: contributions are computed per image row in parallel and summed in pixel
//! order.

use std::sync::Arc;

use autodiff::{BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use rayon::prelude::*;

use super::{
    clip_tensor, grad_f64, hard_render_grad, reduce_rows, screen_bary, tensor_f64, ApproxSettings,
    HardRender, Screen,
};
use crate::error::RenderError;

/// Renders per-vertex attributes `[V, C]` over the faces from clip positions `[V, 4]` with
/// OpenDR's image-gradient derivatives: an image `[H, W, C + 1]` (attributes over the
/// background, then the coverage). See the [module documentation](self).
///
/// # Errors
/// Clip positions not `[V, 4]`, attributes not `[V, C]`, a background of another length than
/// `C` or not finite, and the rasterizer's errors (image size, face indices, non-finite
/// vertices).
pub fn opendr<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &ApproxSettings,
) -> Result<Var<'t, T>, RenderError> {
    let op = OpenDrOp {
        hard: HardRender::new("opendr", clip, attrs, faces, settings)?,
    };
    Ok(clip.tape().apply(op, &[clip, attrs]))
}

struct OpenDrOp<T: Real> {
    hard: HardRender<T>,
}

/// What the backward needs per pixel: its nearest face and NDC depth.
#[derive(Clone, Copy)]
pub(crate) struct Px {
    pub face: Option<u32>,
    pub depth: f64,
}

impl Px {
    /// Per pixel of `fr`, its nearest face and depth.
    pub fn of<T: Real>(fr: &crate::raster::Fragments<T>) -> Vec<Px> {
        (0..fr.num_pixels())
            .map(|p| match fr.nearest(p) {
                Some(f) => Px {
                    face: Some(f.face),
                    depth: f.depth.to_f64c(),
                },
                None => Px {
                    face: None,
                    depth: f64::INFINITY,
                },
            })
            .collect()
    }
}

/// OpenDR's derivative over a rendered image: the faces drawn, and whether only the halves
/// across an occlusion boundary count (`boundary_only`: the interior, smooth part is left to
/// the exact chain through the shader, `crate::boundary::opendr_antialias`).
pub(crate) struct ImageGrad<'a> {
    pub faces: &'a [[u32; 3]],
    pub boundary_only: bool,
}

impl ImageGrad<'_> {
    /// Whether an occlusion boundary separates pixels `a` and `b`; if so, the occluding face.
    fn boundary(&self, a: Px, b: Px) -> Option<u32> {
        match (a.face, b.face) {
            (None, None) => None,
            (Some(f), None) | (None, Some(f)) => Some(f),
            (Some(fa), Some(fb)) => {
                let (va, vb) = (self.faces[fa as usize], self.faces[fb as usize]);
                if fa == fb || va.iter().any(|i| vb.contains(i)) {
                    None
                } else if b.depth < a.depth {
                    Some(fb)
                } else {
                    Some(fa)
                }
            }
        }
    }

    /// Contributions `(vertex, d/d(col, row))` of the pixels of one image row (`nc` values a
    /// pixel in `img` and `g`).
    #[allow(clippy::too_many_arguments)]
    pub fn row(
        &self,
        screen: &Screen,
        px: &[Px],
        img: &[f64],
        g: &[f64],
        nc: usize,
        row: usize,
        out: &mut Vec<(u32, [f64; 2])>,
    ) {
        let (w, h) = (screen.width, screen.height);
        for col in 0..w {
            let p = row * w + col;
            let gp = &g[p * nc..(p + 1) * nc];
            if gp.iter().all(|&x| x == 0.0) {
                continue;
            }
            let ip = &img[p * nc..(p + 1) * nc];
            // Axis 0: columns (x), axis 1: rows (y). Side -1: previous pixel, +1: next.
            for axis in 0..2 {
                for side in [-1isize, 1] {
                    let (r2, c2) = if axis == 0 {
                        (row as isize, col as isize + side)
                    } else {
                        (row as isize + side, col as isize)
                    };
                    if r2 < 0 || c2 < 0 || r2 >= h as isize || c2 >= w as isize {
                        continue;
                    }
                    let q = r2 as usize * w + c2 as usize;
                    let iq = &img[q * nc..(q + 1) * nc];
                    // Half of the central difference along +axis, projected on dL/dI_p.
                    let sgn = side as f64 * 0.5;
                    let s: f64 = (0..nc).map(|ch| gp[ch] * sgn * (iq[ch] - ip[ch])).sum();
                    if s == 0.0 {
                        continue;
                    }
                    let face = match self.boundary(px[p], px[q]) {
                        Some(f) => f,
                        None if self.boundary_only => continue,
                        None => match px[p].face {
                            Some(f) => f,
                            None => continue,
                        },
                    };
                    let f = self.faces[face as usize];
                    let Some((v, area2)) = screen.triangle(f) else {
                        continue;
                    };
                    let b = screen_bary(&v, area2, [col as f64, row as f64]).map(|x| x.max(0.0));
                    let sum = b[0] + b[1] + b[2];
                    if !(sum > 0.0) {
                        continue;
                    }
                    for k in 0..3 {
                        let wk = b[k] / sum;
                        if wk == 0.0 {
                            continue;
                        }
                        let mut gv = [0.0; 2];
                        gv[axis] = -wk * s;
                        out.push((f[k], gv));
                    }
                }
            }
        }
    }
}

impl<T: Real> Op<T> for OpenDrOp<T> {
    fn name(&self) -> &'static str {
        "opendr"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        self.hard.forward("opendr", inputs)
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let fr = &self.hard.fragments;
        let g_attr = if ctx.needs_grad[1] {
            let g = ctx.grad_outputs[0].as_standard_layout();
            let hg = hard_render_grad(
                "opendr",
                ctx,
                &self.hard.faces,
                fr,
                g.as_slice().expect("standard"),
                None,
                &self.hard.settings,
                false,
            )?;
            hg.attr.map(|a| tensor_f64(ctx.inputs[1].shape(), a))
        } else {
            None
        };
        if !ctx.needs_grad[0] {
            return Ok(vec![None, g_attr]);
        }
        let px = Px::of(fr);
        let img: Vec<f64> = ctx.outputs[0].iter().map(|x| x.to_f64c()).collect();
        let g = grad_f64(ctx);
        let screen = Screen::new(&ctx.inputs[0], fr.width, fr.height);
        let nc = self.hard.background.len() + 1;
        let ig = ImageGrad {
            faces: &self.hard.faces,
            boundary_only: false,
        };
        let rows: Vec<Vec<(u32, [f64; 2])>> = (0..fr.height)
            .into_par_iter()
            .map(|row| {
                let mut out = Vec::new();
                ig.row(&screen, &px, &img, &g, nc, row, &mut out);
                out
            })
            .collect();
        Ok(vec![Some(clip_tensor(reduce_rows(&screen, rows))), g_attr])
    }
}
