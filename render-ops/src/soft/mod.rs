//! Soft (probabilistic) rasterizers: SoftRas (Liu et al. 2019) and DIB-R (Chen et al. 2019),
//! each one tape op with an exact hand-derived backward to clip positions (and, for SoftRas,
//! vertex attributes).
//!
//! Only faces within the coverage cut-off of a pixel are visited: faces are binned into
//! 16 x 16 pixel tiles by their screen boxes expanded by the cut-off radius ([`common`]).
//! Work is parallel over tiles; the backward keeps per-tile, per-face accumulators and reduces
//! them into the vertex gradients in tile order, so results are bit-identical for any thread
//! count.

pub(crate) mod common;
pub mod dibr;
pub(crate) mod simd;
pub mod softras;

pub use common::MAX_SOFT_BIN_ENTRIES;
pub use dibr::{dibr, dibr_alpha, DibrSettings};
pub use softras::{softras, SoftSettings};
