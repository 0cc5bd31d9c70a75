//! 2D landmark files: one `x y` line per landmark, in pixels (origin at the image's top-left
//! corner, pixel centres at +0.5; CONVENTIONS). Blank lines and lines starting with `#` are
//! skipped; the two numbers may be separated by spaces, tabs or a comma.

use std::path::{Path, PathBuf};

use ndarray::Array2;
use thiserror::Error;

use crate::morphable::{LandmarkPoint, LandmarkScheme, Morphable};

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

/// The MediaPipe face-mesh point(s) of each of the 68 iBUG 300-W / Multi-PIE landmarks (dlib's
/// 68, in their order, 0-based): one index, or two whose mean is the landmark (`(a, a)` for
/// one). The table of Peizhi Yan's "Mediapipe_2_Dlib_Landmarks"
/// (<https://github.com/PeizhiYan/Mediapipe_2_Dlib_Landmarks>, as used in flame-head-tracker),
/// written out here: jaw 0-16, brows 17-26, nose 27-35, eyes 36-47, outer lips 48-59, inner
/// lips 60-67.
pub const MEDIAPIPE_TO_IBUG68: [(usize, usize); 68] = [
    // Jaw, subject's right ear to left ear.
    (127, 127),
    (234, 234),
    (93, 93),
    (132, 58),
    (58, 172),
    (136, 136),
    (150, 150),
    (176, 176),
    (152, 152),
    (400, 400),
    (379, 379),
    (365, 365),
    (397, 288),
    (361, 361),
    (323, 323),
    (454, 454),
    (356, 356),
    // Right brow, left brow.
    (70, 70),
    (63, 63),
    (105, 105),
    (66, 66),
    (107, 107),
    (336, 336),
    (296, 296),
    (334, 334),
    (293, 293),
    (300, 300),
    // Nose ridge, then the nostrils' lower edge.
    (168, 6),
    (197, 195),
    (5, 5),
    (4, 4),
    (75, 75),
    (97, 97),
    (2, 2),
    (326, 326),
    (305, 305),
    // Right eye, left eye (from the outer corner, upper lid first).
    (33, 33),
    (160, 160),
    (158, 158),
    (133, 133),
    (153, 153),
    (144, 144),
    (362, 362),
    (385, 385),
    (387, 387),
    (263, 263),
    (373, 373),
    (380, 380),
    // Outer lips from the right corner, upper first.
    (61, 61),
    (39, 39),
    (37, 37),
    (0, 0),
    (267, 267),
    (269, 269),
    (291, 291),
    (321, 321),
    (314, 314),
    (17, 17),
    (84, 84),
    (91, 91),
    // Inner lips.
    (78, 78),
    (82, 82),
    (13, 13),
    (312, 312),
    (308, 308),
    (317, 317),
    (14, 14),
    (87, 87),
];

/// How the landmarks of a photo meet the model: photo landmark `i` of the fit is the weighted
/// sum of the photo's rows `rows[i]` (weights `row_weights[i]`), matched with model point
/// `points[i]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Correspondence {
    /// Rows of the photo's landmark array behind each fitted landmark (two; the same row
    /// twice for one).
    pub rows: Vec<[usize; 2]>,
    /// Weights of the two rows (`[1, 0]` for one row, `[0.5, 0.5]` for a mean).
    pub row_weights: Vec<[f64; 2]>,
    /// The model point of each fitted landmark.
    pub points: Vec<LandmarkPoint>,
    /// In words, e.g. `68 of the 468 MediaPipe points (iBUG-68 model)`.
    pub description: String,
}

impl Correspondence {
    /// The fitted landmarks `[L, 2]` picked (or averaged) from the photo's `[N, 2]`.
    pub fn select(&self, photo: &Array2<f64>) -> Array2<f64> {
        Array2::from_shape_fn((self.rows.len(), photo.ncols()), |(i, k)| {
            let [a, b] = self.rows[i];
            let [wa, wb] = self.row_weights[i];
            wa * photo[[a, k]] + wb * photo[[b, k]]
        })
    }

    fn identity(points: Vec<LandmarkPoint>, description: String) -> Self {
        let n = points.len();
        Correspondence {
            rows: (0..n).map(|i| [i, i]).collect(),
            row_weights: vec![[1.0, 0.0]; n],
            points,
            description,
        }
    }
}

fn pair_weights(a: usize, b: usize) -> [f64; 2] {
    if a == b {
        [1.0, 0.0]
    } else {
        [0.5, 0.5]
    }
}

/// Matches `n` photo landmarks (from `source`, named in errors) with `model`'s landmarks:
///
/// - `n` = the model's landmark count: one to one, in order;
/// - 468 MediaPipe points and an `ibug68` model: the 68 picked from the 468
///   ([`MEDIAPIPE_TO_IBUG68`]);
/// - 68 iBUG points and a `mediapipe468` model: each matched with the model point(s) of the
///   table (the mean of two model points where the table has two);
/// - `n` = the model's vertex count: one per vertex, in vertex order.
pub fn correspondence(
    model: &Morphable<f64>,
    n: usize,
    source: impl AsRef<Path>,
) -> Result<Correspondence, LandmarkFileError> {
    let nl = model.n_landmarks();
    let nv = model.n_vertices();
    let scheme = model.landmark_scheme();
    let model_points = model.landmark_points();
    if n == nl {
        return Ok(Correspondence::identity(
            model_points,
            format!("{n} landmarks, one per model landmark"),
        ));
    }
    if n == LandmarkScheme::MediaPipe468.count() && scheme == Some(LandmarkScheme::Ibug68) {
        return Ok(Correspondence {
            rows: MEDIAPIPE_TO_IBUG68.iter().map(|&(a, b)| [a, b]).collect(),
            row_weights: MEDIAPIPE_TO_IBUG68
                .iter()
                .map(|&(a, b)| pair_weights(a, b))
                .collect(),
            points: model_points,
            description: "68 iBUG points from the 468 MediaPipe points".into(),
        });
    }
    if n == LandmarkScheme::Ibug68.count() && scheme == Some(LandmarkScheme::MediaPipe468) {
        let points = MEDIAPIPE_TO_IBUG68
            .iter()
            .map(|&(a, b)| {
                let (pa, pb) = (model_points[a], model_points[b]);
                let [wa, wb] = pair_weights(a, b);
                match (pa.as_vertex(), pb.as_vertex()) {
                    (Some(va), Some(vb)) => LandmarkPoint {
                        vertices: [va, vb, va],
                        weights: [wa, wb, 0.0],
                    },
                    // Surface points: the first one (a mean of two points on different
                    // triangles needs six vertices).
                    _ => pa,
                }
            })
            .collect();
        return Ok(Correspondence::identity(
            points,
            "68 iBUG points, matched through the MediaPipe mesh".into(),
        ));
    }
    if n == nv {
        return Ok(Correspondence::identity(
            (0..nv).map(LandmarkPoint::vertex).collect(),
            format!("{n} landmarks, one per model vertex"),
        ));
    }
    let mut accepted = vec![format!("{nl} (the model's landmarks)")];
    if nv != nl {
        accepted.push(format!("{nv} (one per model vertex)"));
    }
    match scheme {
        Some(LandmarkScheme::Ibug68) => accepted.push("468 (MediaPipe face mesh)".into()),
        Some(LandmarkScheme::MediaPipe468) => accepted.push("68 (iBUG 300-W)".into()),
        None => {}
    }
    Err(LandmarkFileError::Count {
        path: source.as_ref().to_path_buf(),
        found: n,
        expected: accepted.join(" or "),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ibug_table_is_68_distinct_mediapipe_points() {
        let mut seen = std::collections::BTreeSet::new();
        for &(a, b) in &MEDIAPIPE_TO_IBUG68 {
            assert!(a < 468 && b < 468);
            assert!(seen.insert((a, b)), "({a}, {b}) twice");
        }
        // Symmetric pairs: outer eye corners 36/45, mouth corners 48/54, chin 8 on the midline.
        let shipped = crate::face::default_face::<f64>();
        let m = shipped.mean_shape();
        let x = |i: usize| {
            let (a, b) = MEDIAPIPE_TO_IBUG68[i];
            0.5 * (m[[a, 0]] + m[[b, 0]])
        };
        assert!((x(36) + x(45)).abs() < 1e-3 && x(36) < 0.0, "eye corners");
        assert!((x(48) + x(54)).abs() < 1e-3 && x(48) < 0.0, "mouth corners");
        assert!(x(8).abs() < 1e-3 && x(30).abs() < 1e-3, "chin, nose tip");
    }

    #[test]
    fn correspondence_picks_the_68_from_the_468_and_back() {
        let shipped = crate::face::default_face::<f64>();
        // 68 photo points, a MediaPipe model: model points from the table.
        let c = correspondence(&shipped, 68, "lm68.txt").unwrap();
        assert_eq!(c.rows.len(), 68);
        assert_eq!(c.points[8], LandmarkPoint::vertex(152));
        assert_eq!(
            c.points[3],
            LandmarkPoint {
                vertices: [132, 58, 132],
                weights: [0.5, 0.5, 0.0],
            }
        );
        // 468 photo points, an iBUG-68 model: rows picked and averaged from the photo.
        let mut parts = shipped.to_parts();
        parts.landmarks = MEDIAPIPE_TO_IBUG68.iter().map(|&(a, _)| a).collect();
        parts.landmark_scheme = Some(LandmarkScheme::Ibug68);
        let m68 = Morphable::from_parts(parts).unwrap();
        let c = correspondence(&m68, 468, "lm.txt").unwrap();
        let photo = Array2::from_shape_fn((468, 2), |(i, k)| (i * 2 + k) as f64);
        let sel = c.select(&photo);
        assert_eq!(sel.shape(), &[68, 2]);
        assert_eq!(sel[[8, 0]], photo[[152, 0]]);
        assert_eq!(sel[[3, 1]], 0.5 * (photo[[132, 1]] + photo[[58, 1]]));
        // 68 lines for the 68 model: one to one.
        assert_eq!(correspondence(&m68, 68, "x").unwrap().rows[5], [5, 5]);
        let e = correspondence(&m68, 100, "bad.txt").unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("bad.txt") && msg.contains("100"), "{msg}");
        assert!(msg.contains("68") && msg.contains("468"), "{msg}");
    }
}
