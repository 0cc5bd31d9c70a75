//! The shipped ICT-FaceKit face model (USC ICT, MIT licence): the model folder
//! `models/data/ict` (face area, mouth socket and eyeballs; 100 identity modes, 53 expression
//! blendshapes), converted by `scripts/convert_ict.sh`; its README documents the arrays, the
//! landmark correspondence and the regions. It is `tapestry fit-face`'s default model.

use std::path::PathBuf;

use autodiff::Real;

use crate::error::Result;
use crate::morphable::Morphable;

/// ICT's "Narrow face area" (ICT-FaceKit README, "Face Area Details"): model vertices
/// `0..NARROW_FACE_VERTICES` (ICT's own indices), the region `skin`: the part of the face a
/// frontal photo shows, without forehead top, temples, ears, jaw underside and neck. The
/// photometric term uses only its pixels (`models/data/ict/README.md`).
pub const NARROW_FACE_VERTICES: usize = 6706;

/// The folder of the shipped ICT model, inside this crate's source tree.
pub fn ict_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/data/ict"))
}

/// Loads the shipped ICT model from [`ict_dir`] (14.6 MB; float16 bases widened to `T`).
pub fn load_ict<T: Real>() -> Result<Morphable<T>> {
    Morphable::load(ict_dir())
}
