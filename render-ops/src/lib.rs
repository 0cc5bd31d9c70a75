//! Rendering ops.
// Index loops mirror the papers' per-vertex/per-channel equations; the backward closures'
// types are spelled out where they are built.
#![allow(
    clippy::needless_range_loop,
    clippy::type_complexity,
    clippy::neg_cmp_op_on_partial_ord,
    clippy::manual_contains
)]
pub mod approx;
pub mod blend;
pub mod boundary;
pub mod camera;
pub mod check;
pub mod error;
pub mod interpolate;
pub mod io;
pub mod mesh;
pub mod methods;
pub mod obj;
pub mod pipeline;
pub mod raster;
pub mod rasterize;
mod scatter;
pub mod scene;
pub mod shade;
pub mod soft;
pub mod texture;
pub mod transform;
