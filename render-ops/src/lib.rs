//! Rendering ops.
