//! The Neural 3D Mesh Renderer's edge term over a shaded image (H. Kato, Y. Ushiku and
//! T. Harada, "Neural 3D Mesh Renderer", CVPR 2018, section 3.3; section 4.2 of H. Kato et al.,
//! "Differentiable Rendering: A Survey", 2020, eq. 1-2), composed as nvdiffrast composes
//! `antialias` (S. Laine et al., SIGGRAPH Asia 2020, section 3.4).
//!
//! # Forward
//!
//! The shaded image, unchanged.
//!
//! # Backward
//!
//! `dL/dI` passes to the shaded image unchanged (the interior part, exact through the shader
//! and the rasterizer's barycentrics). To the positions it adds the edge term of the fused
//! [`crate::approx::nmr()`] (see there: per face, scanline and edge, the pixels the edge would
//! sweep or uncover, `dI_j / dx_i = delta_I / delta_x` gated by `delta_I . dL/dI_j < 0`, with a
//! half-pixel floor on the distance), with one change: the colour a pixel would take when the
//! edge sweeps outward over it is the shaded colour of the face's own pixel just inside the
//! edge (what NMR's reference implementation does), since a shader's colour is known only where
//! it ran. The colour a pixel shows once uncovered is, as there, that of the pixel just across
//! the edge.
//!
//! Deterministic: per scanline in parallel, reduced in scanline order.

use std::sync::Arc;

use autodiff::{Real, Var};

use super::{BoundaryTerm, Geometry, PassThrough};
use crate::approx::nmr::Sweeper;
use crate::approx::Screen;
use crate::error::RenderError;
use crate::rasterize::Rasterized;

/// NMR's edge gradient over the shaded image `color` `[H, W, C]` drawn from `raster` (of clip
/// positions `clip` `[V, 4]`): returns the image unchanged, with the gradient described in the
/// [module documentation](self).
///
/// # Errors
/// `color` not `[H, W, C]` at the rasterizer's size, `clip` not `[V, 4]` or too short for the
/// rasterized faces.
pub fn nmr_antialias<'t, T: Real>(
    color: Var<'t, T>,
    raster: &Rasterized<'t, T>,
    clip: Var<'t, T>,
) -> Result<Var<'t, T>, RenderError> {
    let geo = Geometry::new(NmrTerm::NAME, color, raster, clip)?;
    let term = NmrTerm {
        faces: raster.faces.clone(),
    };
    Ok(PassThrough { geo, term }.apply(color, clip))
}

/// NMR's edge sweeps over the rasterized faces (not welded: the sweeps follow each face).
struct NmrTerm {
    faces: Arc<Vec<[u32; 3]>>,
}

impl BoundaryTerm for NmrTerm {
    const NAME: &'static str = "boundary::nmr_antialias";

    fn clip_gradient<T: Real>(
        &self,
        geo: &Geometry<T>,
        screen: &Screen,
        img: &[f64],
        g: &[f64],
    ) -> Vec<[f64; 4]> {
        let sw = Sweeper {
            faces: &self.faces,
            // Only the outward colours from vertex attributes are interpolated.
            persp: true,
        };
        sw.boundary(&geo.fragments, screen, img, g, None)
    }
}
