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

/// The folder of the shipped ICT model, inside this crate's source tree (for tools and tests;
/// [`load_ict`] reads the copy compiled into the binary).
pub fn ict_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/data/ict"))
}

/// The model folder's files, compiled in, so that the CLI and the Python wheel need no
/// checkout at run time.
const FILES: &[(&str, &[u8])] = &[
    ("model.json", include_bytes!("../data/ict/model.json")),
    (
        "mean_shape.npy",
        include_bytes!("../data/ict/mean_shape.npy"),
    ),
    ("id_basis.npy", include_bytes!("../data/ict/id_basis.npy")),
    ("exp_basis.npy", include_bytes!("../data/ict/exp_basis.npy")),
    (
        "mean_albedo.npy",
        include_bytes!("../data/ict/mean_albedo.npy"),
    ),
    (
        "albedo_basis.npy",
        include_bytes!("../data/ict/albedo_basis.npy"),
    ),
    ("faces.npy", include_bytes!("../data/ict/faces.npy")),
    (
        "face_regions.npy",
        include_bytes!("../data/ict/face_regions.npy"),
    ),
    ("uvs.npy", include_bytes!("../data/ict/uvs.npy")),
];

/// Loads the shipped ICT model (14.6 MB, compiled in; float16 bases widened to `T`): the same
/// model as `Morphable::load(ict_dir())`.
pub fn load_ict<T: Real>() -> Result<Morphable<T>> {
    Morphable::load_from_memory(FILES)
}
