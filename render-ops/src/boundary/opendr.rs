//! OpenDR's boundary derivative over a shaded image (M. M. Loper and M. J. Black, "OpenDR: An
//! Approximate Differentiable Renderer", ECCV 2014; section 4.1 of H. Kato et al.,
//! "Differentiable Rendering: A Survey", 2020), composed as nvdiffrast composes `antialias`
//! (S. Laine et al., SIGGRAPH Asia 2020, section 3.4).
//!
//! # Forward
//!
//! The shaded image, unchanged.
//!
//! # Backward
//!
//! `dL/dI` passes to the shaded image unchanged (the interior, smooth dependence of the image on
//! the geometry is there, exact, through the shader and the rasterizer's barycentrics). To the
//! positions it adds OpenDR's boundary term: for each pair of neighbouring pixels `p`, `q`
//! along a row or a column separated by an occlusion boundary (exactly one of them covered, or
//! their nearest faces different and sharing no vertex), half of the image's jump
//! `1/2 (I_q - I_p)` projected on `dL/dI_p` is chained to the vertices of the occluding face
//! (the covered one, or the nearer) with its screen-space barycentric weights at `p` clamped to
//! the face and renormalised: `dL/dx_k -= w_k 1/2 (I_q - I_p) . dL/dI_p` (the image content
//! moves with the edge). This is the single- and multi-boundary part of the fused
//! [`crate::approx::opendr()`], whose interior part (the image's central differences) is
//! replaced here by the exact chain through the shader.
//!
//! Deterministic: per image row in parallel, reduced in row order.

use autodiff::{Real, Var};
use rayon::prelude::*;

use super::{BoundaryTerm, Geometry, PassThrough};
use crate::approx::opendr::{ImageGrad, Px};
use crate::approx::{reduce_rows, Screen};
use crate::error::RenderError;
use crate::rasterize::Rasterized;

/// OpenDR's boundary gradient over the shaded image `color` `[H, W, C]` drawn from `raster`
/// (of clip positions `clip` `[V, 4]`): returns the image unchanged, with the gradient
/// described in the [module documentation](self).
///
/// # Errors
/// `color` not `[H, W, C]` at the rasterizer's size, `clip` not `[V, 4]` or too short for the
/// rasterized faces.
pub fn opendr_antialias<'t, T: Real>(
    color: Var<'t, T>,
    raster: &Rasterized<'t, T>,
    clip: Var<'t, T>,
) -> Result<Var<'t, T>, RenderError> {
    let geo = Geometry::new(OpenDrTerm::NAME, color, raster, clip)?;
    Ok(PassThrough {
        geo,
        term: OpenDrTerm,
    }
    .apply(color, clip))
}

/// OpenDR's single- and multi-boundary terms, per image row.
struct OpenDrTerm;

impl BoundaryTerm for OpenDrTerm {
    const NAME: &'static str = "boundary::opendr_antialias";

    fn clip_gradient<T: Real>(
        &self,
        geo: &Geometry<T>,
        screen: &Screen,
        img: &[f64],
        g: &[f64],
    ) -> Vec<[f64; 4]> {
        let fr = &*geo.fragments;
        let px = Px::of(fr);
        let ig = ImageGrad {
            faces: &geo.welded,
            boundary_only: true,
        };
        let rows: Vec<Vec<(u32, [f64; 2])>> = (0..fr.height)
            .into_par_iter()
            .map(|row| {
                let mut out = Vec::new();
                ig.row(screen, &px, img, g, geo.c, row, &mut out);
                out
            })
            .collect();
        reduce_rows(screen, rows)
    }
}
