//! Typed errors of the model crate: every loader error names the file (or, for in-memory
//! models, the array) and the value or dimension that does not fit.

use std::path::PathBuf;

use thiserror::Error;

/// Everything that can go wrong building, loading, saving or evaluating a model.
#[derive(Debug, Error)]
pub enum ModelError {
    /// A file the model needs does not exist.
    #[error("{path}: file not found")]
    MissingFile {
        /// The path looked for.
        path: PathBuf,
    },
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// `model.json` is not valid JSON or does not follow the schema (unknown keys are errors).
    #[error("{path}: {detail}")]
    Json {
        /// The JSON file.
        path: PathBuf,
        /// What serde (or the schema check) said.
        detail: String,
    },
    /// An `.npy` file that cannot be parsed (bad header, truncated data, ...).
    #[error("{file}: cannot read .npy: {detail}")]
    Npy {
        /// The file.
        file: String,
        /// What went wrong.
        detail: String,
    },
    /// An array stored with an element type the loader does not accept.
    #[error("{file}: dtype {found}, expected {expected}")]
    WrongDtype {
        /// The file.
        file: String,
        /// The dtype descriptor found in the header (e.g. `'<f4'`).
        found: String,
        /// What is accepted.
        expected: &'static str,
    },
    /// An array with the wrong number of dimensions or an impossible shape.
    #[error("{file}: shape {shape:?}, expected {expected}")]
    Shape {
        /// The file or array.
        file: String,
        /// Its shape.
        shape: Vec<usize>,
        /// The accepted shapes.
        expected: String,
    },
    /// One dimension that disagrees with the rest of the model.
    #[error("{file}: {what} is {found}, expected {expected}")]
    Dimension {
        /// The file or array.
        file: String,
        /// Which dimension (e.g. `rows (3 * n_vertices)`).
        what: String,
        /// The value the rest of the model implies.
        expected: usize,
        /// The value found.
        found: usize,
    },
    /// An index (vertex index of a face, landmark, region label) out of range.
    #[error(
        "{file}: {what} {index} at position {position} is out of range (must be in 0..{bound})"
    )]
    IndexOutOfRange {
        /// The file or array.
        file: String,
        /// What the index refers to (e.g. `vertex index`).
        what: String,
        /// Flat position of the bad entry.
        position: usize,
        /// The bad value.
        index: i64,
        /// The exclusive upper bound.
        bound: usize,
    },
    /// A NaN or infinite value in a float array.
    #[error("{file}: non-finite value {value} at flat index {index}")]
    NonFinite {
        /// The file or array.
        file: String,
        /// Flat (row-major) index of the first bad entry.
        index: usize,
        /// The value.
        value: f64,
    },
    /// A standard deviation that is not strictly positive.
    #[error("{file}: standard deviation {value} at index {index} must be > 0")]
    BadSigma {
        /// The file or array.
        file: String,
        /// Index of the component.
        index: usize,
        /// The value.
        value: f64,
    },
    /// Anything else that makes the model inconsistent (unknown unit, duplicate name, ...).
    #[error("{file}: {detail}")]
    Invalid {
        /// The file or array.
        file: String,
        /// What is wrong.
        detail: String,
    },
    /// A coefficient vector of the wrong length given to a plain (tape-free) evaluation.
    #[error("{what}: {found} coefficients given, the model has {expected}")]
    Coefficients {
        /// Which coefficients (`alpha`, `beta`, `gamma`).
        what: &'static str,
        /// The model's number of components.
        expected: usize,
        /// The length given.
        found: usize,
    },
}

/// Result alias of the crate.
pub type Result<T, E = ModelError> = std::result::Result<T, E>;
