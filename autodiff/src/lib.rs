//! Reverse-mode automatic differentiation on a tape, generic over `f32` and `f64`.
pub mod real;
pub use real::{c, Real};
