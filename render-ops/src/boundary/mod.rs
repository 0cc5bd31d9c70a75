//! Boundary-gradient methods over any shaded image, after the `antialias` op of nvdiffrast
//! (S. Laine, J. Hellsten, T. Karras, Y. Seol, J. Lehtinen and T. Aila, "Modular Primitives for
//! High-Performance Differentiable Rendering", SIGGRAPH Asia 2020, section 3.4): the image is
//! shaded per fragment by any tape code (interpolated attributes, textures, lighting, a user's
//! closure), composited with [`crate::blend::blend_hard`], and one op then adds what the hard
//! render lacks, the dependence of the image on where the silhouette and occlusion edges lie.
//!
//! Each op takes the shaded image `[H, W, C]` (its last channel the coverage when it comes
//! from `blend_hard`, treated like any other channel), the output of [`crate::rasterize()`]
//! that drew it (the nearest fragment of each pixel: its face and depth) and the clip positions
//! `[V, 4]` of the vertices it rasterized, and returns an image `[H, W, C]`. Gradients go to the
//! shaded image (so on through the shader to texels, colours and lights, and through the
//! rasterizer's barycentrics to the positions: the exact interior part) and to `x`, `y`, `w` of
//! the clip positions of the edges' vertices (the boundary part):
//!
//! * [`deodr_antialias()`]: DEODR's discontinuity edge overdraw (M. de La Gorce, D. J. Fleet and
//!   N. Paragios, TPAMI 2011) of the shaded image: each silhouette edge is overdrawn on its outer
//!   side with a linear ramp `overdraw_px` wide, towards the colour the face shows just inside
//!   the edge (as nvdiffrast blends the two pixels of a pair across an edge); a forward of its
//!   own, differentiated exactly.
//! * [`opendr_antialias()`]: OpenDR's image-space derivative (M. M. Loper and M. J. Black, ECCV 2014) of
//!   the shaded image at occlusion boundaries: the forward is the image unchanged; across each
//!   boundary between neighbouring pixels half the jump of the image is chained to the vertices
//!   of the occluding face.
//! * [`nmr_antialias()`]: the Neural 3D Mesh Renderer's edge term (H. Kato, Y. Ushiku and T. Harada,
//!   CVPR 2018, section 3.3) over the shaded image: the forward is the image unchanged; the
//!   colour change a pixel sees when an edge sweeps over it, over the distance to the edge,
//!   gated by the incoming gradient, with the shaded colour of the face just inside the edge as
//!   the colour it would take.
//!
//! The fused ops of [`crate::approx`] over per-vertex attributes stay the fast path when the
//! shading is per vertex ([`crate::pipeline`] picks them for unlit, untextured scenes).
//!
//! Meshes split at uv seams ([`crate::mesh::Mesh::unified`]) have several vertices at one
//! position; the ops weld vertices with bit-identical clip coordinates before finding edges,
//! so a seam is not taken for a silhouette and its faces count as neighbours (the gradient of
//! a welded vertex goes to the first of its copies, which gathers to the same source vertex).
//!
//! All work is in `f64` whatever the scalar, in parallel over image rows (scanlines for `nmr`),
//! reduced in row order: the same result for any thread count.

pub mod deodr;
pub mod nmr;
pub mod opendr;

pub use deodr::deodr_antialias;
pub use nmr::nmr_antialias;
pub use opendr::opendr_antialias;

use std::collections::HashMap;
use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};

use crate::approx::{clip_tensor, Screen};
use crate::error::RenderError;
use crate::raster::Fragments;
use crate::rasterize::Rasterized;

/// Settings of the boundary ops.
#[derive(Clone, Debug, PartialEq)]
pub struct BoundarySettings {
    /// Width in pixels of [`deodr_antialias()`]'s overdraw ramp (default 1.0; 0 disables the overdraw).
    pub overdraw_px: f64,
}

impl Default for BoundarySettings {
    fn default() -> Self {
        Self { overdraw_px: 1.0 }
    }
}

/// What a boundary op keeps of its inputs: the fragments and faces of the rasterization, the
/// faces with welded vertex indices, and the channel count.
pub(crate) struct Geometry<T: Real> {
    pub fragments: Arc<Fragments<T>>,
    /// The rasterized faces with each vertex replaced by the first vertex of identical clip
    /// coordinates.
    pub welded: Vec<[u32; 3]>,
    /// Channels of the image.
    pub c: usize,
}

impl<T: Real> Geometry<T> {
    /// Checks that `color` is `[H, W, C]` at the rasterizer's size and `clip` `[V, 4]` with
    /// every face index below `V`; welds the vertices.
    pub fn new(
        op: &'static str,
        color: Var<'_, T>,
        raster: &Rasterized<'_, T>,
        clip: Var<'_, T>,
    ) -> Result<Self, RenderError> {
        let fr = &raster.fragments;
        let (cs, ks) = (color.shape(), clip.shape());
        if cs.len() != 3 || cs[0] != fr.height || cs[1] != fr.width || cs[2] == 0 {
            return Err(AutodiffError::shape(
                op,
                &[&cs],
                format!(
                    "the shaded image must be [{}, {}, C] (the rasterizer's size), C >= 1",
                    fr.height, fr.width
                ),
            )
            .into());
        }
        if ks.len() != 2 || ks[1] != 4 {
            return Err(AutodiffError::shape(op, &[&ks], "clip positions must be [V, 4]").into());
        }
        let nv = ks[0];
        if let Some(bad) = raster.faces.iter().flatten().find(|&&i| i as usize >= nv) {
            return Err(AutodiffError::index(
                op,
                &[&ks],
                format!("face vertex {bad} is out of range for {nv} clip positions"),
            )
            .into());
        }
        let canon = weld(&clip.value_ref()?.view());
        let welded = raster
            .faces
            .iter()
            .map(|f| f.map(|i| canon[i as usize]))
            .collect();
        Ok(Geometry {
            fragments: fr.clone(),
            welded,
            c: cs[2],
        })
    }

    /// The screen geometry of clip positions `clip` at the rasterizer's size.
    pub fn screen<S: ndarray::Data<Elem = T>>(
        &self,
        clip: &ndarray::ArrayBase<S, ndarray::IxDyn>,
    ) -> Screen {
        Screen::new(clip, self.fragments.width, self.fragments.height)
    }
}

/// The boundary term of an op whose forward is the identity on the shaded image ([`opendr_antialias()`],
/// [`nmr_antialias()`]): `dL/dclip` `[V, 4]` from the screen geometry, the image and `dL/dI` (in `f64`).
pub(crate) trait BoundaryTerm: 'static {
    /// The op's name.
    const NAME: &'static str;
    /// The gradient of the loss with respect to the clip positions.
    fn clip_gradient<T: Real>(
        &self,
        geo: &Geometry<T>,
        screen: &Screen,
        img: &[f64],
        g: &[f64],
    ) -> Vec<[f64; 4]>;
}

/// The op of a [`BoundaryTerm`]: the image passes through, `dL/dI` passes back to it unchanged
/// (the exact interior part), and the term adds the boundary part to the clip positions.
pub(crate) struct PassThrough<T: Real, B> {
    pub geo: Geometry<T>,
    pub term: B,
}

impl<T: Real, B: BoundaryTerm> PassThrough<T, B> {
    /// Applies the op to `[color, clip]`.
    pub fn apply<'t>(self, color: Var<'t, T>, clip: Var<'t, T>) -> Var<'t, T> {
        color.tape().apply(self, &[color, clip])
    }
}

impl<T: Real, B: BoundaryTerm> Op<T> for PassThrough<T, B> {
    fn name(&self) -> &'static str {
        B::NAME
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        Ok(vec![inputs[0].to_owned()])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let g_color = ctx.needs_grad[0].then(|| ctx.grad_outputs[0].clone());
        let g_clip = ctx.needs_grad[1].then(|| {
            let screen = self.geo.screen(&ctx.inputs[1]);
            let g = self.term.clip_gradient(
                &self.geo,
                &screen,
                &to_f64(&ctx.inputs[0]),
                &grad_out(ctx),
            );
            clip_tensor(g)
        });
        Ok(vec![g_color, g_clip])
    }
}

/// Per vertex, the first vertex with bit-identical clip coordinates (itself if none before).
pub(crate) fn weld<T: Real, S: ndarray::Data<Elem = T>>(
    clip: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> Vec<u32> {
    let mut first: HashMap<[u64; 4], u32> = HashMap::with_capacity(clip.shape()[0]);
    clip.outer_iter()
        .enumerate()
        .map(|(i, r)| {
            // +0 and -0 compare equal and weld together.
            let key = [r[0], r[1], r[2], r[3]].map(|x| (x.to_f64c() + 0.0).to_bits());
            *first.entry(key).or_insert(i as u32)
        })
        .collect()
}

/// The image values of a tensor in `f64`.
pub(crate) fn to_f64<T: Real, S: ndarray::Data<Elem = T>>(
    x: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> Vec<f64> {
    x.iter().map(|v| v.to_f64c()).collect()
}

/// `dL/dI` of the op's single output, in `f64`.
pub(crate) fn grad_out<T: Real>(ctx: &BackwardCtx<'_, '_, T>) -> Vec<f64> {
    to_f64(ctx.grad_outputs[0])
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{ArrayD, IxDyn};

    #[test]
    fn weld_joins_identical_rows_only() {
        let c = ArrayD::from_shape_vec(
            IxDyn(&[4, 4]),
            vec![
                0.0, 1.0, 2.0, 3.0, //
                0.0, 1.0, 2.0, 3.5, //
                -0.0, 1.0, 2.0, 3.0, //
                0.0, 1.0, 2.0, 3.5,
            ],
        )
        .unwrap();
        assert_eq!(weld::<f64, _>(&c), vec![0, 1, 0, 1]);
    }
}
