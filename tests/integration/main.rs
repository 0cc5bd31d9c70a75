//! The integration tests of `tapestry`, one binary: each module was a test file of its own.
//! One binary links the crate graph once instead of once per file (CI time); run one
//! module with `cargo test -p tapestry --test integration MODULE::`.

mod bench;
mod cli;
mod cli_landmarks;
mod common;
mod determinism;
mod fit_face;
mod fit_face_cli;
mod gradcheck_cli;
mod hard_cases;
mod pipeline_hard;
mod readme_example;
