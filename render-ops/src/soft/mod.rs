//! Soft (probabilistic) rasterizers: SoftRas (Liu et al. 2019) and DIB-R (Chen et al. 2019),
//! each one tape op with an exact hand-derived backward to clip positions (and, for SoftRas,
//! vertex attributes).
//!
//! Only faces within the coverage cut-off of a pixel are visited: faces are binned into
//! 16 x 16 pixel tiles by their screen boxes expanded by the cut-off radius (the `common` module).
//! The forwards run in parallel over tiles, the backwards in parallel over faces; per-pixel
//! sums run in face order and per-face sums are added to the vertices in face order, so
//! results are bit-identical for any thread count. SoftRas and DIB-R on `f32` tapes evaluate
//! 8 pixels of a row span at a time in single precision (`simd`, `lanes`, `softras::fast`,
//! `dibr::fast`).
//!
//! The same methods also come as composable stages, so that any texture, lighting or shader
//! runs per fragment: [`stage::soft_fragments`] yields each pixel's fragments within the
//! cut-off (or its nearest K) with coverage probabilities, clipped barycentrics and depths as
//! a sparse list; interpolation, texturing and shaders run on it as on the hard rasterizer's
//! fragments; [`aggregate::softras_aggregate`] blends them. DIB-R's colour is the hard
//! foreground, so its composed form is the hard rasterizer's fragments, the shader, and
//! [`dibr::dibr_alpha`] as the alpha (`crate::methods::render_fragments`). The fused ops above
//! stay the fast path for per-vertex colours.

pub mod aggregate;
pub(crate) mod common;
pub mod dibr;
pub(crate) mod lanes;
pub mod softras;
pub mod stage;

pub use aggregate::{softras_aggregate, softras_blend, SoftBlendSettings};
pub use common::MAX_SOFT_BIN_ENTRIES;
pub use dibr::{dibr, dibr_alpha, DibrSettings};
pub use softras::{softras, SoftSettings};
pub use stage::{soft_fragments, Coverage, SoftFragments, SoftStageSettings, MAX_SOFT_FRAGMENTS};
