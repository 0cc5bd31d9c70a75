//! Hard-rasterizer methods with boundary gradients: the hard (z-buffer) image forward, with a
//! hand-written backward that approximates the derivative of the image at occlusion boundaries
//! (`tf_mesh`, `opendr`, `nmr`), or an antialiased forward with its exact derivative (`deodr`).
//!
//! * [`tf_mesh()`]: the TF Mesh Renderer (K. Genova, F. Cole, A. Maschinot, A. Sarna, D. Vlasic and
//!   W. T. Freeman, "Unsupervised Training for 3D Morphable Model Regression", CVPR 2018;
//!   section 4.4 of the survey of H. Kato et al., "Differentiable Rendering: A Survey", 2020):
//!   gradients through barycentrics of each pixel's nearest triangle, extrapolated past its
//!   edges, so the surface is treated as locally flat across occlusion boundaries; a one-pixel
//!   band along the silhouette gets the coverage change of the extended triangle.
//! * [`opendr()`]: OpenDR (M. M. Loper and M. J. Black, "OpenDR: An Approximate Differentiable
//!   Renderer", ECCV 2014; survey section 4.1): the derivative of the pixels with respect to the
//!   screen-space vertex positions from the image-space gradient of the rendered image (central
//!   differences `1/2 [-1, 0, 1]`), with interior, single-boundary and multi-boundary pixels.
//! * [`nmr()`]: the Neural 3D Mesh Renderer (H. Kato, Y. Ushiku and T. Harada, CVPR 2018, section
//!   3.3; survey section 4.2, eq. 1-2): per face, edge and scanline, the pixels an edge would
//!   sweep as a vertex moves along `x` (or `y`) get the colour change over the distance to the
//!   crossing, `delta_I / delta_x`, kept only where that change lowers the loss.
//!
//! * [`deodr()`]: DEODR (M. de La Gorce, D. J. Fleet and N. Paragios, TPAMI 2011; survey section
//!   4.4): the hard image with silhouette edges overdrawn by a linear ramp (discontinuity edge
//!   overdraw), a forward that is continuous in the vertex positions, and its exact derivative.
//!   Unlike the others, its forward differs from the hard render near silhouettes.
//!
//! The ops take clip positions `[V, 4]` and per-vertex attributes (colours) `[V, C]` and return
//! an image `[H, W, C + 1]`: the perspective-correct interpolated attributes of each pixel's
//! nearest fragment over the background, and the coverage (0 or 1) as the last channel. The
//! forward is the hard render of [`crate::rasterize`] + [`crate::interpolate`] +
//! [`crate::blend::blend_hard`], bit for bit. Attribute gradients are the exact ones of that
//! render (`dI_p / dA_k = b_k` on covered pixels). Position gradients go to `x`, `y` and `w` of
//! the clip coordinates (`z` only sets visibility and gets none).
//!
//! These fused ops take interpolated per-vertex attributes only: they are the fast path for
//! per-vertex colours. For textures and per-fragment shaders, [`crate::boundary`] has `deodr`,
//! `opendr` and `nmr` as ops over any shaded image, and [`tf_mesh::rasterize_extrapolated`]
//! with [`tf_mesh::blend_band`] is `tf_mesh`'s composed form (the paths
//! [`crate::methods::render_fragments`] takes for lit or textured scenes).
//!
//! All work is in `f64` whatever the scalar. The exact part shared by all four (attribute
//! gradients and the interior, barycentric position gradient of the hard render) is one pass
//! over the fragments (`hard_grad`: per face and fixed chunk of fragments). The
//! methods' boundary contributions are computed in parallel over image rows (for `nmr`, over
//! the rows and then the columns). Everything is reduced into the vertex gradients in a fixed
//! order (fragment, row and column order), so results are bit-identical for any number of
//! rayon threads.

pub mod deodr;
mod hard_grad;
pub mod nmr;
pub mod opendr;
pub mod tf_mesh;

pub use deodr::deodr;
pub use nmr::nmr;
pub use opendr::opendr;
pub use tf_mesh::tf_mesh;

use std::mem::MaybeUninit;
use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Real, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::raster::{Fragments, RasterSettings};
use crate::rasterize::{as_arrays, as_arrays_mut, clip_rows};
use crate::soft::common::ndc_to_clip;
use hard_grad::HardGrad;

/// Settings of [`tf_mesh()`], [`opendr()`], [`nmr()`] and [`deodr()`].
#[derive(Clone, Debug, PartialEq)]
pub struct ApproxSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Background value per attribute channel (empty: zeros).
    pub background: Vec<f64>,
    /// Perspective-correct interpolation (default `true`).
    pub perspective_correct: bool,
    /// Drop clockwise (back) faces (default `false`).
    pub cull_backfaces: bool,
    /// Width in pixels of [`deodr()`]'s overdraw ramp (default 1.0; 0 disables the overdraw).
    pub overdraw_px: f64,
}

impl ApproxSettings {
    /// Defaults for a `width x height` image.
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            background: Vec::new(),
            perspective_correct: true,
            cull_backfaces: false,
            overdraw_px: 1.0,
        }
    }

    /// The hard rasterizer's settings (one fragment per pixel, no barycentric derivatives).
    pub fn raster(&self) -> RasterSettings {
        let mut s = RasterSettings::new(self.width, self.height);
        s.barycentric_derivatives = false;
        s.perspective_correct = self.perspective_correct;
        s.cull_backfaces = self.cull_backfaces;
        s
    }
}

/// Checks shapes and settings; rasterizes. Returns the fragments and the background (`C`
/// values).
pub(crate) fn prepare<'t, T: Real>(
    op: &'static str,
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: &[[u32; 3]],
    s: &ApproxSettings,
) -> Result<(Arc<Fragments<T>>, Vec<T>), RenderError> {
    let (cs, as_) = (clip.shape(), attrs.shape());
    if cs.len() != 2 || cs[1] != 4 {
        return Err(AutodiffError::shape(op, &[&cs], "clip positions must be [V, 4]").into());
    }
    if as_.len() != 2 || as_[0] != cs[0] {
        return Err(AutodiffError::shape(
            op,
            &[&cs, &as_],
            "attributes must be [V, C] with V as the clip positions",
        )
        .into());
    }
    let c = as_[1];
    if !s.background.is_empty() && s.background.len() != c {
        return Err(AutodiffError::invalid(
            op,
            format!(
                "background has {} values for {c} attribute channels",
                s.background.len()
            ),
        )
        .into());
    }
    if s.background.iter().any(|b| !b.is_finite()) {
        return Err(AutodiffError::invalid(
            op,
            format!("background must be finite: {:?}", s.background),
        )
        .into());
    }
    let rows = clip_rows(&clip.value_ref()?.view())?;
    let frags = crate::raster::rasterize_fragments(&rows, faces, &s.raster())?;
    let bg = (0..c)
        .map(|ch| T::from_f64c(s.background.get(ch).copied().unwrap_or(0.0)))
        .collect();
    Ok((Arc::new(frags), bg))
}

/// The state of the ops whose forward is the hard render ([`tf_mesh`], [`opendr`], [`nmr`]):
/// the fragments of the forward's rasterization, the faces, the settings and the background.
pub(crate) struct HardRender<T: Real> {
    pub fragments: Arc<Fragments<T>>,
    pub faces: Arc<Vec<[u32; 3]>>,
    pub settings: ApproxSettings,
    pub background: Vec<T>,
}

impl<T: Real> HardRender<T> {
    /// Checks the inputs and rasterizes them ([`prepare`]).
    pub fn new(
        op: &'static str,
        clip: Var<'_, T>,
        attrs: Var<'_, T>,
        faces: Arc<Vec<[u32; 3]>>,
        settings: &ApproxSettings,
    ) -> Result<Self, RenderError> {
        let (fragments, background) = prepare(op, clip, attrs, &faces, settings)?;
        Ok(HardRender {
            fragments,
            faces,
            settings: settings.clone(),
            background,
        })
    }

    /// The op's forward: the hard render ([`render_hard`]) of the attributes `inputs[1]`.
    pub fn forward(
        &self,
        op: &'static str,
        inputs: &[TensorView<'_, T>],
    ) -> autodiff::Result<Vec<Tensor<T>>> {
        Ok(vec![render_hard(
            op,
            &self.fragments,
            &self.faces,
            &self.background,
            &inputs[1],
        )?])
    }
}

/// The hard render `[H, W, C + 1]`: per covered pixel `b0 A[f0] + b1 A[f1] + b2 A[f2]` (the
/// arithmetic of [`crate::interpolate`]) and alpha 1, the background and alpha 0 elsewhere.
pub(crate) fn render_hard<T: Real, S: ndarray::Data<Elem = T>>(
    op: &'static str,
    frags: &Fragments<T>,
    faces: &[[u32; 3]],
    bg: &[T],
    attrs: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> autodiff::Result<Tensor<T>> {
    let c = bg.len();
    if attrs.ndim() != 2 || attrs.shape()[1] != c {
        return Err(AutodiffError::shape(
            op,
            &[attrs.shape()],
            format!("attributes must be [V, {c}]"),
        ));
    }
    let a = attrs.as_standard_layout();
    let a = a.as_slice().expect("standard");
    let (h, w) = (frags.height, frags.width);
    let n = h * w * (c + 1);
    let mut img = Vec::with_capacity(n);
    let out = &mut img.spare_capacity_mut()[..n];
    match c {
        3 => render_hard_rows::<T, 3, 4>(frags, faces, bg, a, out),
        1 => render_hard_rows::<T, 1, 2>(frags, faces, bg, a, out),
        _ => render_hard_rows::<T, 0, 1>(frags, faces, bg, a, out),
    }
    // SAFETY: `render_hard_rows` wrote all `n` values.
    unsafe { img.set_len(n) };
    Ok(ArrayD::from_shape_vec(IxDyn(&[h, w, c + 1]), img).expect("h w c"))
}

/// The rows of [`render_hard`], for `C` channels (`C = 0`: `bg.len()`, known only at run
/// time; `P = C + 1` pixel values), in parallel over image rows, writing every value of the
/// (uninitialised) image. With `C > 0` a row starts as a copy of a background row and the
/// covered pixels are then written, each run of one face's fragments looking its corner
/// attributes up once.
fn render_hard_rows<T: Real, const C: usize, const P: usize>(
    frags: &Fragments<T>,
    faces: &[[u32; 3]],
    bg: &[T],
    a: &[T],
    img: &mut [MaybeUninit<T>],
) {
    let w = frags.width;
    if C > 0 {
        debug_assert_eq!(P, C + 1);
        let a = as_arrays::<T, C>(a);
        let mut empty = [T::zero(); P];
        empty[..C].copy_from_slice(bg);
        let empty_row = vec![empty.map(MaybeUninit::new); w];
        let pixels = as_arrays_mut::<MaybeUninit<T>, P>(img);
        pixels.par_chunks_mut(w).enumerate().for_each(|(row, out)| {
            let offs = &frags.offsets[row * w..=(row + 1) * w];
            out.copy_from_slice(&empty_row);
            let zero = [T::zero(); C];
            let (mut cur, mut a0, mut a1, mut a2) = (u32::MAX, &zero, &zero, &zero);
            let mut s = offs[0] as usize;
            for (px, &e) in out.iter_mut().zip(&offs[1..]) {
                let e = e as usize;
                if s < e {
                    let fi = frags.face[s];
                    if fi != cur {
                        let f = faces[fi as usize];
                        (a0, a1, a2) = (&a[f[0] as usize], &a[f[1] as usize], &a[f[2] as usize]);
                        cur = fi;
                    }
                    let b = frags.bary[s];
                    for ch in 0..C {
                        px[ch] = MaybeUninit::new(b[0] * a0[ch] + b[1] * a1[ch] + b[2] * a2[ch]);
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
            let offs = &frags.offsets[row * w..=(row + 1) * w];
            for (x, px) in out.chunks_exact_mut(c + 1).enumerate() {
                let (i, e) = (offs[x] as usize, offs[x + 1] as usize);
                if i == e {
                    for (o, &v) in px[..c].iter_mut().zip(&bg[..c]) {
                        o.write(v);
                    }
                    px[c].write(T::zero());
                    continue;
                }
                let f = faces[frags.face[i] as usize];
                let b = frags.bary[i];
                let (a0, a1, a2) = (
                    &a[f[0] as usize * c..][..c],
                    &a[f[1] as usize * c..][..c],
                    &a[f[2] as usize * c..][..c],
                );
                for ch in 0..c {
                    px[ch].write(b[0] * a0[ch] + b[1] * a1[ch] + b[2] * a2[ch]);
                }
                px[c].write(T::one());
            }
        });
}

/// The exact gradient of the hard render ([`hard_grad::hard_grad`]) for an op whose inputs
/// are the clip positions and the attributes: `g` is `dL/dI` (`[H * W * (C + 1)]`), replaced
/// at the pixels of `over` (`(pixels, values)`: increasing pixel indices, `C + 1` values each)
/// by those values.
#[allow(clippy::too_many_arguments)]
pub(crate) fn hard_render_grad<T: Real>(
    op: &'static str,
    ctx: &BackwardCtx<'_, '_, T>,
    faces: &[[u32; 3]],
    frags: &Fragments<T>,
    g: &[T],
    over: Option<(&[u32], &[f64])>,
    settings: &ApproxSettings,
    need_pos: bool,
) -> autodiff::Result<HardGrad> {
    let clip = clip_rows(&ctx.inputs[0]).map_err(|e| AutodiffError::Op {
        op,
        detail: e.to_string(),
    })?;
    let attrs = ctx.inputs[1].as_standard_layout();
    let c = ctx.inputs[1].shape()[1];
    Ok(hard_grad::hard_grad(
        &clip,
        faces,
        frags,
        attrs.as_slice().expect("standard"),
        c,
        g,
        over.unwrap_or((&[], &[])),
        settings.perspective_correct,
        need_pos,
        ctx.needs_grad[1],
    ))
}

/// A tensor of the given shape from `f64` values.
pub(crate) fn tensor_f64<T: Real>(shape: &[usize], v: Vec<f64>) -> Tensor<T> {
    ArrayD::from_shape_vec(IxDyn(shape), v.into_iter().map(T::from_f64c).collect())
        .expect("same shape")
}

/// Screen geometry of the vertices: pixel coordinates `(col, row)` (pixel centres are integers)
/// and NDC, with clip `w`.
pub(crate) struct Screen {
    pub width: usize,
    pub height: usize,
    /// `(col, row)` of every vertex.
    pub px: Vec<[f64; 2]>,
    /// NDC `(x, y)` of every vertex.
    pub ndc: Vec<[f64; 2]>,
    /// Clip `w` of every vertex.
    pub w: Vec<f64>,
    /// Clip `(x, y, z, w)` of every vertex in `f64`.
    pub clip: Vec<[f64; 4]>,
}

impl Screen {
    pub fn new<T: Real, S: ndarray::Data<Elem = T>>(
        clip: &ndarray::ArrayBase<S, ndarray::IxDyn>,
        width: usize,
        height: usize,
    ) -> Self {
        let (wf, hf) = (width as f64, height as f64);
        let mut s = Screen {
            width,
            height,
            px: Vec::new(),
            ndc: Vec::new(),
            w: Vec::new(),
            clip: Vec::new(),
        };
        for r in clip.outer_iter() {
            let c = [r[0], r[1], r[2], r[3]].map(|x| x.to_f64c());
            let ndc = [c[0] / c[3], c[1] / c[3]];
            s.px.push([
                (ndc[0] + 1.0) * wf / 2.0 - 0.5,
                (1.0 - ndc[1]) * hf / 2.0 - 0.5,
            ]);
            s.ndc.push(ndc);
            s.w.push(c[3]);
            s.clip.push(c);
        }
        s
    }

    /// The pixel positions of a face's vertices, `None` when a vertex is at or behind the eye
    /// plane (`w <= 0`), is not finite, or the projected triangle has no area.
    pub fn triangle(&self, f: [u32; 3]) -> Option<([[f64; 2]; 3], f64)> {
        if f.iter().any(|&i| !(self.w[i as usize] > 0.0)) {
            return None;
        }
        let v = f.map(|i| self.px[i as usize]);
        let area2 = cross2(sub(v[1], v[0]), sub(v[2], v[0]));
        (area2 != 0.0 && area2.is_finite()).then_some((v, area2))
    }

    /// Chains a gradient with respect to vertex `v`'s pixel position `(col, row)` to its clip
    /// coordinates `(x, y, z, w)`.
    pub fn px_to_clip(&self, v: usize, g: [f64; 2]) -> [f64; 4] {
        // col = (x_ndc + 1) W / 2 - 1/2, row = (1 - y_ndc) H / 2 - 1/2.
        let gn = [
            g[0] * self.width as f64 / 2.0,
            -g[1] * self.height as f64 / 2.0,
        ];
        let c = ndc_to_clip(gn, self.ndc[v], self.w[v]);
        [c[0], c[1], 0.0, c[2]]
    }

    /// Chains per-vertex gradients with respect to the pixel positions `(col, row)` to clip
    /// coordinates (vertices with a zero gradient get zeros).
    pub fn px_grads_to_clip(&self, acc: &[[f64; 2]]) -> Vec<[f64; 4]> {
        acc.iter()
            .enumerate()
            .map(|(v, &g)| {
                if g == [0.0, 0.0] {
                    [0.0; 4]
                } else {
                    self.px_to_clip(v, g)
                }
            })
            .collect()
    }
}

#[inline]
pub(crate) fn sub(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

#[inline]
pub(crate) fn cross2(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

/// Affine (screen-space) barycentrics of point `p` in triangle `v` with doubled signed area
/// `area2`; components are negative outside the triangle (extrapolation).
#[inline]
pub(crate) fn screen_bary(v: &[[f64; 2]; 3], area2: f64, p: [f64; 2]) -> [f64; 3] {
    let l = |k: usize| {
        let (a, b) = (v[(k + 1) % 3], v[(k + 2) % 3]);
        cross2(sub(b, a), sub(p, a)) / area2
    };
    [l(0), l(1), l(2)]
}

/// Per-row lists of `(vertex, d/d(col, row))` contributions, reduced in row order (the order
/// of pixels) into per-vertex pixel-space gradients, then chained to clip coordinates.
pub(crate) fn reduce_rows(screen: &Screen, rows: Vec<Vec<(u32, [f64; 2])>>) -> Vec<[f64; 4]> {
    let nv = screen.px.len();
    let mut acc = vec![[0.0f64; 2]; nv];
    for row in rows {
        for (v, g) in row {
            let a = &mut acc[v as usize];
            a[0] += g[0];
            a[1] += g[1];
        }
    }
    screen.px_grads_to_clip(&acc)
}

/// What a boundary term of [`HardRender::backward`] reads, in `f64`.
pub(crate) struct BoundaryInputs {
    /// Screen geometry of the vertices.
    pub screen: Screen,
    /// `dL/dI`, `[H * W * (C + 1)]`.
    pub g: Vec<f64>,
    /// The vertex attributes, `[V * C]`.
    pub attrs: Vec<f64>,
    /// The rendered image, `[H * W * (C + 1)]`.
    pub img: Vec<f64>,
}

impl<T: Real> HardRender<T> {
    /// The backward of the methods whose forward is the hard render and whose position
    /// gradient is the interior one plus a boundary term ([`tf_mesh`], [`nmr`]): exact
    /// attribute gradients and, for the positions, the interior (barycentric) part, both from
    /// [`hard_render_grad`], plus the method's `boundary` part (per-vertex clip coordinates,
    /// `f64`), each computed only where the input needs it.
    pub fn backward(
        &self,
        op: &'static str,
        ctx: &BackwardCtx<'_, '_, T>,
        boundary: impl FnOnce(&BoundaryInputs) -> Vec<[f64; 4]>,
    ) -> autodiff::Result<Vec<Option<Tensor<T>>>> {
        let (frags, faces) = (&*self.fragments, &self.faces[..]);
        let g_out = ctx.grad_outputs[0].as_standard_layout();
        let g_t = g_out.as_slice().expect("standard");
        let hg = hard_render_grad(
            op,
            ctx,
            faces,
            frags,
            g_t,
            None,
            &self.settings,
            ctx.needs_grad[0],
        )?;
        let g_attr = hg.attr.map(|a| tensor_f64(ctx.inputs[1].shape(), a));
        let Some(interior) = hg.pos else {
            return Ok(vec![None, g_attr]);
        };
        let inputs = BoundaryInputs {
            screen: Screen::new(&ctx.inputs[0], frags.width, frags.height),
            g: grad_f64(ctx),
            attrs: ctx.inputs[1].iter().map(|x| x.to_f64c()).collect(),
            img: ctx.outputs[0].iter().map(|x| x.to_f64c()).collect(),
        };
        let b = boundary(&inputs);
        let total = interior
            .iter()
            .zip(&b)
            .map(|(a, b)| [a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]])
            .collect();
        Ok(vec![Some(clip_tensor(total)), g_attr])
    }
}

/// NDC depth of each pixel's nearest fragment (infinity where nothing is covered): the
/// z-buffer that boundary terms test against.
pub(crate) fn depth_buffer<T: Real>(frags: &Fragments<T>) -> Vec<f64> {
    let mut z = vec![0.0; frags.num_pixels()];
    z.par_chunks_mut(4096).enumerate().for_each(|(ci, out)| {
        let p0 = ci * 4096;
        for (j, o) in out.iter_mut().enumerate() {
            let (s, e) = (frags.offsets[p0 + j], frags.offsets[p0 + j + 1]);
            *o = if s < e {
                frags.depth[s as usize].to_f64c()
            } else {
                f64::INFINITY
            };
        }
    });
    z
}

/// Bins items by the image lines (rows or columns) they reach: `ranges[i]` is the inclusive
/// range of lines of item `i` (`None`: none). Returns a CSR over the `n` lines, `(start,
/// items)`: the items reaching line `l` are `items[start[l]..start[l + 1]]`, in increasing
/// order.
pub(crate) fn bin_by_lines(ranges: &[Option<(usize, usize)>], n: usize) -> (Vec<usize>, Vec<u32>) {
    let mut start = vec![0usize; n + 1];
    for &(l0, l1) in ranges.iter().flatten() {
        for l in l0..=l1 {
            start[l + 1] += 1;
        }
    }
    for l in 0..n {
        start[l + 1] += start[l];
    }
    let mut fill = start.clone();
    let mut items = vec![0u32; start[n]];
    for (i, r) in ranges.iter().enumerate() {
        if let Some((l0, l1)) = *r {
            for l in l0..=l1 {
                items[fill[l]] = i as u32;
                fill[l] += 1;
            }
        }
    }
    (start, items)
}

/// Weights of the two endpoints of an edge at screen-space parameter `t` (0 at the first),
/// with `q = 1 / w` at the endpoints: perspective-correct, `((1 - t) q0, t q1) / den` with
/// `den = (1 - t) q0 + t q1`, or affine `(1 - t, t)` with `den = 1`. The attributes the face
/// shows at that point of its edge are `w0 A0 + w1 A1`.
#[inline]
pub(crate) fn edge_weights(q: [f64; 2], t: f64, persp: bool) -> ([f64; 2], f64) {
    if persp {
        let den = (1.0 - t) * q[0] + t * q[1];
        ([(1.0 - t) * q[0] / den, t * q[1] / den], den)
    } else {
        ([1.0 - t, t], 1.0)
    }
}

/// Gradient of the loss with respect to the output, `[H * W * (C + 1)]`, in `f64`.
pub(crate) fn grad_f64<T: Real>(ctx: &BackwardCtx<'_, '_, T>) -> Vec<f64> {
    ctx.grad_outputs[0].iter().map(|x| x.to_f64c()).collect()
}

/// A `[V, 4]` tensor from per-vertex clip gradients.
pub(crate) fn clip_tensor<T: Real>(g: Vec<[f64; 4]>) -> Tensor<T> {
    let v = g.len();
    ArrayD::from_shape_vec(
        IxDyn(&[v, 4]),
        g.into_iter().flatten().map(T::from_f64c).collect(),
    )
    .expect("v x 4")
}
