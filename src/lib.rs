//! Tapestry: differentiable rendering in Rust.
//!
//! - [`autodiff`]: the reverse-mode tape, the op trait, the gradient checker, optimisers;
//! - [`render_ops`]: cameras, meshes, rasterization methods, interpolation, shading, blending;
//! - [`models`]: parametric (3DMM-style) models and analysis-by-synthesis fitting;
//! - [`mod@bench`]: `tapestry bench`, speed against error and scaling of the raster methods;
//! - [`cli`]: the `tapestry` command line.
pub use autodiff;
pub use models;
pub use render_ops;

pub mod bench;
pub mod cli;
