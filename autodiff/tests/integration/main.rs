//! The integration tests of `tapestry-autodiff`, one binary: each module was a test file of its own.
//! One binary links the crate graph once instead of once per file (CI time); run one
//! module with `cargo test -p tapestry-autodiff --test integration MODULE::`.

mod anomaly;
mod custom_op;
mod determinism;
mod errors;
mod fused;
mod graph;
mod ops;
mod optim;
