//! 2D landmark files: one `x y` line per landmark, in pixels (origin at the image's top-left
//! corner, pixel centres at +0.5; CONVENTIONS). Blank lines and lines starting with `#` are
//! skipped; the two numbers may be separated by spaces, tabs or a comma.

use std::path::{Path, PathBuf};

use ndarray::Array2;
use thiserror::Error;

use crate::morphable::Morphable;

/// A landmark file that cannot be used; every variant names the file.
#[derive(Debug, Error)]
pub enum LandmarkFileError {
    /// The file cannot be read.
    #[error("{}: cannot read landmark file: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// A line that is not two finite numbers.
    #[error("{}:{line}: {detail}", .path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        detail: String,
    },
    /// A number of landmarks that does not fit the model.
    #[error("{}: {found} landmarks, expected {expected}", .path.display())]
    Count {
        /// The file.
        path: PathBuf,
        /// Landmarks found.
        found: usize,
        /// The accepted counts, in words.
        expected: String,
    },
}

/// Reads a landmark file into `[L, 2]` pixel positions.
pub fn read_landmarks(path: impl AsRef<Path>) -> Result<Array2<f64>, LandmarkFileError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|source| LandmarkFileError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut data = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let parse_err = |detail: String| LandmarkFileError::Parse {
            path: path.to_path_buf(),
            line: i + 1,
            detail,
        };
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|s| !s.is_empty())
            .collect();
        if fields.len() != 2 {
            return Err(parse_err(format!(
                "expected two numbers `x y`, found {} field(s) in {line:?}",
                fields.len()
            )));
        }
        for f in fields {
            let v: f64 = f
                .parse()
                .map_err(|_| parse_err(format!("{f:?} is not a number")))?;
            if !v.is_finite() {
                return Err(parse_err(format!("{f:?} is not finite")));
            }
            data.push(v);
        }
    }
    if data.is_empty() {
        return Err(LandmarkFileError::Count {
            path: path.to_path_buf(),
            found: 0,
            expected: "at least one `x y` line".into(),
        });
    }
    let n = data.len() / 2;
    Ok(Array2::from_shape_vec((n, 2), data).expect("two values per line"))
}

/// The model vertex of each of `n` landmarks read from `path`: with as many lines as the model
/// has vertices (468 for the shipped model: MediaPipe's face mesh) one per vertex in vertex
/// order, else the model's landmark list when the count matches it.
pub fn landmark_vertices(
    model: &Morphable<f64>,
    n: usize,
    path: impl AsRef<Path>,
) -> Result<Vec<usize>, LandmarkFileError> {
    if n == model.n_vertices() {
        Ok((0..n).collect())
    } else if n == model.landmarks().len() {
        Ok(model.landmarks().to_vec())
    } else {
        let nl = model.landmarks().len();
        let nv = model.n_vertices();
        Err(LandmarkFileError::Count {
            path: path.as_ref().to_path_buf(),
            found: n,
            expected: if nl == nv {
                format!("{nv} (one per model vertex)")
            } else {
                format!("{nv} (one per model vertex) or {nl} (the model's landmarks)")
            },
        })
    }
}
