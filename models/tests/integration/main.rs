//! The integration tests of `tapestry-models`, one binary: each module was a test file of its own.
//! One binary links the crate graph once instead of once per file (CI time); run one
//! module with `cargo test -p tapestry-models --test integration MODULE::`.

mod detect;
mod face_model;
mod ict_model;
mod model_io;
mod texture_stage;
