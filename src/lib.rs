//! Tapestry: differentiable rendering in Rust.
pub use autodiff;
pub use models;
pub use render_ops;
