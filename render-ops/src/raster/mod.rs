//! Hard (z-buffer) rasterization of clip-space triangles into packed per-pixel fragments.
//!
//! # Method
//!
//! * **2D homogeneous rasterization** (M. Olano and T. Greer, "Triangle Scan Conversion using 2D
//!   Homogeneous Coordinates", Graphics Hardware 1997). With `M = [v0 v1 v2]` the matrix whose
//!   columns are the clip-space `(x, y, w)` of a triangle and `p = (px, py, 1)` a pixel centre,
//!   the edge functions are `e_i(p) = (v_j x v_k) . p` (Pineda 1988 edge functions, in homogeneous
//!   form) and the perspective-correct barycentrics of the *original* triangle are
//!   `b = M^-1 p / (1^T M^-1 p) = e(p) / sum(e(p))`. A pixel is covered iff all `e_i(p)` have the
//!   sign of `det M`; this is exact also for vertices behind the eye (`w <= 0`), so no vertex is
//!   ever divided by its `w`.
//! * **Clipping.** The near plane `z_clip >= -w_clip` (and the far plane `z_clip <= w_clip`, as in
//!   OpenGL) is a per-fragment test on the interpolated NDC depth `z/w in [-1, 1]`, which is affine
//!   in screen space. Polygon clipping (Sutherland-Hodgman, against near/far only) is used just to
//!   find the screen bounding box of triangles that cross those planes; triangles wholly outside one
//!   frustum plane are culled from their vertex outcodes. Barycentrics therefore always refer to
//!   the original triangle.
//! * **Watertightness.** Edge functions are evaluated in `f64` on pixel coordinates (pixel centres
//!   are integers after a per-vertex viewport transform), with the two endpoints of every edge in a
//!   canonical order (lower vertex index first), so an edge shared by two faces gives bit-identical
//!   values of opposite sign. Signs are exact: a forward error bound filters the `f64` value and
//!   the rare ambiguous cases fall back to an exact expansion sum (Shewchuk 1997, "Adaptive
//!   Precision Floating-Point Arithmetic and Fast Robust Geometric Predicates"). Pixels exactly on
//!   an edge are resolved with the top-left rule of Direct3D 10 / OpenGL (equivalently a symbolic
//!   perturbation of the pixel centre), so on a closed mesh no pixel centre is covered twice by
//!   adjacent faces nor missed between them. Zero-area triangles (exactly `det M == 0`) produce no
//!   fragments.
//! * **Tiles.** Faces are binned by their (clipped) screen bounding boxes, rounded inwards to
//!   the pixel centres they can contain, into `32 x 32` pixel tiles; the binning pass also
//!   culls and sets up each surviving face once (edge functions with error bounds valid over
//!   its whole box, depth plane), stored in face order so that the tile pass reads them
//!   contiguously instead of gathering vertices per tile. Tiles are rasterized in
//!   parallel with rayon. Within a tile each face walks conservative per-row column spans (from
//!   the edge functions and their error bounds) and only pixels in a span get the exact test, so
//!   cost grows with covered pixels and faces. Each tile keeps the `K` nearest fragments per pixel
//!   in a fixed-size per-thread K-buffer (which records, per row, the column span it tested
//!   and how many slots it filled, so that packing reads and resets only those spans) and
//!   packs their face records and depths; assembly then
//!   finds where every tile row starts in the packed pixel-order output (prefix sums) and,
//!   in parallel over tiles (whose face records are a small working set), computes each
//!   fragment's barycentrics, depths and derivatives straight into the output arrays
//!   (allocated uninitialised and written once), per run of consecutive fragments of one
//!   face in a tile row (the record, the row part of its edge functions and its per-face
//!   constants taken once per run; each fragment's values are the same expressions as
//!   computed alone). With `K = 1` the coverage and depth test of a span and the values of a
//!   run are computed four pixels at a time with AVX2 where the CPU has it (runtime
//!   detection; the same IEEE operations in the same order, so the output is bit-identical to
//!   the portable code, which a test checks). The barycentric derivatives are computed only
//!   when [`RasterSettings::barycentric_derivatives`] asks for them (texturing); the
//!   approximate-gradient methods, DIB-R, untextured scene pipelines and `fit-face` skip them.
//!   Input validation (face indices, finite vertices) runs in parallel and
//!   reports the first offender in index order. Bins list faces in increasing index order
//!   and depth ties go to the lower face index, so the result is bit-identical for any number
//!   of threads.
//! * **Direct render.** A forward that needs only the hard image of per-vertex attributes
//!   ([`render_attributes_direct`]: vertex colours, no gradients) skips the fragment list: each tile
//!   task runs the same z-test with `K = 1` and writes its pixels of the image itself, bit for
//!   bit the image of `rasterize` + `interpolate` + `blend_hard`. For `f32` RGB each fragment is
//!   shaded in the z-test when it wins its pixel (a hook compiled out of the rasterizer).
//! * **Degenerate input.** Fragments whose `f64` `sum(e)` is not positive (slivers at the limit
//!   of `f64` precision) are dropped; output values beyond the range of `T` are saturated, so
//!   every fragment value is finite.
//!
//! Conventions (see `docs/CONVENTIONS.md`): OpenGL clip space, pixel `(row r, col c)` centred at
//! `ndc = (2 (c + 0.5) / W - 1, 1 - 2 (r + 0.5) / H)`, row 0 at the top, front faces
//! counter-clockwise in NDC.

// `!(a <= b)` is used deliberately throughout: it is true for NaN, which must take the
// conservative branch.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use rayon::prelude::*;

mod bin;
mod clip;
mod direct;
mod edge;
mod fragments;
mod hard;

pub(crate) use clip::clip_plane;
pub use direct::render_attributes_direct;
pub(crate) use fragments::{per_fragment, PixelCursor};
pub use fragments::{Fragment, Fragments};
pub(crate) use hard::rasterize_backward_at;
pub use hard::{rasterize_backward, rasterize_fragments};
pub(crate) use hard::{FaceVjp, RunSetup, RunVjp};

/// Side of the square screen tiles that faces are binned into and that are rasterized in parallel.
pub const TILE_SIZE: usize = 32;

/// Largest image accepted, in pixels (`width * height`).
pub const MAX_PIXELS: usize = 1 << 31;

/// Largest `faces_per_pixel` accepted.
pub const MAX_FACES_PER_PIXEL: usize = 1024;

/// Largest `width * height * faces_per_pixel` accepted: the worst-case number of fragments,
/// checked before anything is allocated. A fragment takes 92 bytes in [`Fragments`] for `f64`
/// (48 for `f32`) and about as much again in the tape ops downstream, so a request at the
/// limit (2^26: 8192 x 8192 with one face per pixel, 2048 x 2048 with 16) may need some 12 GB
/// when every slot is filled. The soft methods, which keep one image row of values per pixel,
/// take the same limit on `width * height`.
pub const MAX_FRAGMENT_SLOTS: usize = 1 << 26;

/// Settings of the hard rasterizer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RasterSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// `K >= 1`: how many of the nearest fragments each pixel keeps (default 1).
    pub faces_per_pixel: usize,
    /// Drop faces that are clockwise in NDC (seen from behind). Default `false`.
    pub cull_backfaces: bool,
    /// Perspective-correct barycentrics (default `true`); `false` gives barycentrics affine in
    /// screen space (DEODR's mode). Depth is interpolated perspective-correctly either way.
    pub perspective_correct: bool,
    /// Compute the screen-space barycentric derivatives [`Fragments::dbary_dx`] and
    /// [`Fragments::dbary_dy`] (default `true`). Only texture filtering and attribute
    /// derivatives ([`crate::shade::uv_derivatives`]) read them; without them both arrays are
    /// left empty, which halves the per-fragment output (nvdiffrast likewise outputs its
    /// `rast_db` only for filtering).
    pub barycentric_derivatives: bool,
}

impl Default for RasterSettings {
    fn default() -> Self {
        Self {
            width: 256,
            height: 256,
            faces_per_pixel: 1,
            cull_backfaces: false,
            perspective_correct: true,
            barycentric_derivatives: true,
        }
    }
}

impl RasterSettings {
    /// Default settings for a `width x height` image.
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            ..Self::default()
        }
    }

    /// Checks the image size, `faces_per_pixel` and the worst-case fragment count
    /// ([`MAX_FRAGMENT_SLOTS`]).
    pub fn validate(&self) -> Result<(), RasterError> {
        let (width, height) = (self.width, self.height);
        if width == 0 || height == 0 {
            return Err(RasterError::EmptyImage { width, height });
        }
        match width.checked_mul(height) {
            Some(n) if n <= MAX_PIXELS => {}
            _ => {
                return Err(RasterError::ImageTooLarge {
                    width,
                    height,
                    max_pixels: MAX_PIXELS,
                })
            }
        }
        if self.faces_per_pixel == 0 || self.faces_per_pixel > MAX_FACES_PER_PIXEL {
            return Err(RasterError::BadFacesPerPixel {
                k: self.faces_per_pixel,
                max: MAX_FACES_PER_PIXEL,
            });
        }
        let slots = width
            .saturating_mul(height)
            .saturating_mul(self.faces_per_pixel);
        if slots > MAX_FRAGMENT_SLOTS {
            return Err(RasterError::TooLarge {
                request: format!(
                    "a {width}x{height} image with faces_per_pixel {}",
                    self.faces_per_pixel
                ),
                what: "fragment slots (width x height x faces_per_pixel)",
                needed: slots,
                limit: MAX_FRAGMENT_SLOTS,
            });
        }
        Ok(())
    }
}

/// Errors of the rasterizer, each naming the offending input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RasterError {
    /// Width or height is zero.
    #[error("image size {width}x{height} is empty")]
    EmptyImage {
        /// Requested width.
        width: usize,
        /// Requested height.
        height: usize,
    },
    /// The image has more pixels than the packed fragment layout supports.
    #[error("image size {width}x{height} is too large (at most {max_pixels} pixels)")]
    ImageTooLarge {
        /// Requested width.
        width: usize,
        /// Requested height.
        height: usize,
        /// Limit on `width * height`.
        max_pixels: usize,
    },
    /// The request would need more memory than a documented limit ([`MAX_FRAGMENT_SLOTS`],
    /// [`crate::soft::MAX_SOFT_BIN_ENTRIES`]); refused before anything is allocated.
    #[error("{request} needs {needed} {what}, over the limit of {limit}: lower the image size, faces_per_pixel or the soft cut-off")]
    TooLarge {
        /// What was asked for, e.g. `a 2048x2048 image with faces_per_pixel 32`.
        request: String,
        /// The resource counted, e.g. `fragment slots (width x height x faces_per_pixel)`.
        what: &'static str,
        /// How many the request needs (saturated at `usize::MAX`).
        needed: usize,
        /// The limit.
        limit: usize,
    },
    /// `faces_per_pixel` is zero or too large.
    #[error("faces_per_pixel must be between 1 and {max}, got {k}")]
    BadFacesPerPixel {
        /// Requested K.
        k: usize,
        /// Largest accepted K.
        max: usize,
    },
    /// A face refers to a vertex that does not exist.
    #[error("face {face} refers to vertex {index}, but there are only {num_vertices} vertices")]
    FaceIndexOutOfRange {
        /// Face number.
        face: usize,
        /// The bad vertex index.
        index: u32,
        /// Number of vertices given.
        num_vertices: usize,
    },
    /// A vertex has a NaN or infinite clip coordinate.
    #[error("vertex {vertex} has a non-finite clip coordinate {coords:?}")]
    NonFiniteVertex {
        /// Vertex number.
        vertex: usize,
        /// Its clip coordinates (as f64).
        coords: [f64; 4],
    },
    /// More faces than fit the `u32` face ids of [`Fragments`].
    #[error("{faces} faces is too many (at most {max})")]
    TooManyFaces {
        /// Number of faces given.
        faces: usize,
        /// Limit.
        max: usize,
    },
    /// More fragments than fit the `u32` offsets of [`Fragments`].
    #[error("{fragments} fragments is too many for u32 offsets (lower faces_per_pixel or the image size)")]
    TooManyFragments {
        /// Number of fragments produced.
        fragments: usize,
    },
    /// An array given to the backward pass has the wrong length.
    #[error("{what} has length {got}, expected {expected}")]
    LengthMismatch {
        /// Which argument.
        what: &'static str,
        /// Its length.
        got: usize,
        /// The expected length.
        expected: usize,
    },
    /// The fragments do not belong to these settings or faces.
    #[error("fragments do not match the inputs: {0}")]
    FragmentsMismatch(String),
}

/// The first `i < n` (in index order) with `bad(i)`: blocks of indices are scanned in
/// parallel, each with a plain loop, and the first block that has one wins.
pub(crate) fn par_first_index(n: usize, bad: impl Fn(usize) -> bool + Sync) -> Option<usize> {
    const BLOCK: usize = 1 << 14;
    (0..n.div_ceil(BLOCK))
        .into_par_iter()
        .find_map_first(|b| (b * BLOCK..((b + 1) * BLOCK).min(n)).find(|&i| bad(i)))
}

/// Checks settings, face indices and vertex finiteness.
pub(crate) fn validate_inputs<T: autodiff::Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    s: &RasterSettings,
) -> Result<(), RasterError> {
    s.validate()?;
    let max = u32::MAX as usize;
    if faces.len() > max {
        return Err(RasterError::TooManyFaces {
            faces: faces.len(),
            max,
        });
    }
    // In parallel over large blocks; the first offender (in index order) is reported.
    let nv = clip.len();
    let bad_face = par_first_index(faces.len(), |f| faces[f].iter().any(|&i| i as usize >= nv));
    if let Some(f) = bad_face {
        let index = *faces[f].iter().find(|&&i| i as usize >= nv).expect("found");
        return Err(RasterError::FaceIndexOutOfRange {
            face: f,
            index,
            num_vertices: nv,
        });
    }
    let bad_vertex = par_first_index(clip.len(), |v| !clip[v].iter().all(|x| x.is_finite()));
    if let Some(v) = bad_vertex {
        return Err(RasterError::NonFiniteVertex {
            vertex: v,
            coords: clip[v].map(|x| x.to_f64c()),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests;
