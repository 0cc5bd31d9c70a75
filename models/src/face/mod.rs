//! The shipped face model: a 3DMM-style basis built on the MediaPipe canonical face mesh
//! (468 vertices, 898 triangles; Apache-2.0, see `models/data/face/NOTICE`).
//!
//! No statistical basis with a permissive licence exists for this mesh, so the basis is
//! *designed*: every component is a smooth displacement (or colour) field defined from the
//! mesh's landmark contours, with a chosen size at one standard deviation, and the fields
//! are orthonormalised (Gram-Schmidt, in order) in the `3V` space. The construction is
//! documented in `models/data/face/README.md`; [`build_face_model`] is deterministic, and
//! `cargo run -p tapestry-models --example build_face_model --release` writes its output to
//! `models/data/face/` (a test checks the committed files against a fresh build).
//!
//! Coordinates: millimetres (the OBJ's centimetres times 10), y up, the face looks towards
//! +z; "left"/"right" are the subject's (the subject's left is +x).

mod construct;
pub(crate) mod geom;

use std::path::PathBuf;
use std::sync::OnceLock;

use autodiff::Real;

use crate::error::Result;
use crate::morphable::Morphable;

pub use construct::{build_face_model, component_table, ComponentInfo};

/// The folder of the committed model files (`model.json`, `.npy` arrays, OBJ, licence),
/// inside this crate's source tree.
pub fn face_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/data/face"))
}

/// The MediaPipe canonical face mesh (centimetres), compiled in.
pub const CANONICAL_OBJ: &str = include_str!("../../data/face/canonical_face.obj");
/// The MediaPipe contour index lists, compiled in.
pub const CONTOURS_JSON: &str = include_str!("../../data/face/landmark_contours.json");

/// The shipped face model in precision `T`. Built once per process from the compiled-in
/// mesh (a few milliseconds) and cached; identical (to `f32` rounding, checked by a test)
/// to the committed files in [`face_dir`].
pub fn default_face<T: Real>() -> Morphable<T> {
    static CACHE: OnceLock<Morphable<f64>> = OnceLock::new();
    CACHE
        .get_or_init(|| build_face_model().expect("the shipped face data builds"))
        .cast::<T>()
}

/// Loads the committed model files from [`face_dir`] (the same model as [`default_face`],
/// read through the general loader).
pub fn load_default_face<T: Real>() -> Result<Morphable<T>> {
    Morphable::load(face_dir())
}

/// Indices of the shipped model's expression components (see `exp_names`).
pub mod exp {
    /// Jaw drop: lower lip, chin and jaw move down (and back), upper lip slightly up.
    pub const JAW_OPEN: usize = 0;
    /// Subject's left upper eyelid down onto the lower lid (closed at +2 sigma).
    pub const EYE_CLOSE_LEFT: usize = 1;
    /// Subject's right upper eyelid down onto the lower lid (closed at +2 sigma).
    pub const EYE_CLOSE_RIGHT: usize = 2;
    /// Mouth corners up, out and back; cheeks up.
    pub const SMILE: usize = 3;
    /// Both brows (and the forehead skin) up.
    pub const BROW_RAISE: usize = 4;
    /// Inner brows down and together.
    pub const BROW_FROWN: usize = 5;
    /// Lips forward, corners in.
    pub const MOUTH_PUCKER: usize = 6;
    /// Mouth corners down.
    pub const MOUTH_FROWN: usize = 7;
    /// Upper lip and nostrils up.
    pub const UPPER_LIP_RAISE: usize = 8;
    /// Cheeks out.
    pub const CHEEK_PUFF: usize = 9;
    /// Lower jaw towards the subject's left (+x).
    pub const JAW_LEFT: usize = 10;
    /// Subject's left mouth corner up, right corner down.
    pub const SMILE_ASYM: usize = 11;
    /// Subject's left brow up, right brow down.
    pub const BROW_RAISE_ASYM: usize = 12;
    /// Lower eyelids up.
    pub const EYE_SQUINT: usize = 13;
    /// Mouth corners outwards and back.
    pub const MOUTH_STRETCH: usize = 14;
    /// Lower jaw forward.
    pub const JAW_FORWARD: usize = 15;
}
