//! The integration tests of `tapestry-render-ops`, one binary: each module was a test file of its own.
//! One binary links the crate graph once instead of once per file (CI time); run one
//! module with `cargo test -p tapestry-render-ops --test integration MODULE::`.

mod approx;
mod boundary;
mod common;
mod data_layer;
mod deodr;
mod dibr;
mod inverse_silhouette;
mod large;
mod nmr;
mod proptest_robust;
mod raytrace;
mod raytrace_stage;
mod shader_fused;
mod shading;
mod shading_scene;
mod soft;
mod soft_stage;
mod typed_errors;
