//! Built-in ops. Every one implements [`crate::Op`], the same trait user ops implement.
pub mod elementwise;
pub mod index;
pub mod linalg;
pub mod reduce;
pub mod shape;
mod stream_f32;
pub mod vector;
