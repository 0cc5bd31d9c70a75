//! Loading and saving morphable models: a folder with `model.json` and `.npy` arrays.
//!
//! The layout is documented in `models/README.md` (section "Model folder layout"). In short:
//!
//! ```text
//! model.json          dimensions, units, file names, sigmas, landmarks, groups, regions
//! mean_shape.npy      float [V, 3] (or [3V])
//! id_basis.npy        float [3V, K_id] (row 3v+c = coordinate c of vertex v) or [V, 3, K_id]
//! exp_basis.npy       float [3V, K_exp] or [V, 3, K_exp]          (optional)
//! mean_albedo.npy     float [V, 3] (or [3V]), linear RGB          (optional)
//! albedo_basis.npy    float [3V, K_alb] or [V, 3, K_alb]          (optional)
//! faces.npy           integer [F, 3], counter-clockwise from outside
//! uvs.npy             float [V, 2]                                (optional)
//! face_regions.npy    integer [F], index into "regions"           (optional)
//! ```
//!
//! Floats may be float16, float32 or float64 (either byte order), integers any fixed-size
//! integer dtype. File names are whatever `model.json` says; the names above are what
//! [`Morphable::save`] writes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use autodiff::Real;
use ndarray::{Array1, Array2, ArrayD, Ix2, IxDyn};
use ndarray_npy::{ReadNpyError, ReadNpyExt, WriteNpyExt};
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::error::{ModelError, Result};
use crate::morphable::{Labels, LandmarkScheme, Morphable, MorphableParts, Region, SurfacePoint};

/// The `format` string of `model.json`.
pub const FORMAT: &str = "tapestry-morphable";
/// The `version` of `model.json` this crate writes and reads.
pub const VERSION: u32 = 1;

/// Where the files of a model come from.
pub(crate) enum Source<'a> {
    /// A folder on disk.
    Dir(&'a Path),
    /// Files in memory (`name`, bytes).
    Embedded(&'a [(&'a str, &'a [u8])]),
}

impl Source<'_> {
    fn label(&self, name: &str) -> String {
        match self {
            Source::Dir(d) => d.join(name).display().to_string(),
            Source::Embedded(_) => format!("<memory>/{name}"),
        }
    }
    fn path(&self, name: &str) -> PathBuf {
        match self {
            Source::Dir(d) => d.join(name),
            Source::Embedded(_) => PathBuf::from(format!("<memory>/{name}")),
        }
    }
    fn read(&self, name: &str) -> Result<Vec<u8>> {
        match self {
            Source::Dir(d) => {
                let p = d.join(name);
                std::fs::read(&p).map_err(|e| {
                    if e.kind() == std::io::ErrorKind::NotFound {
                        ModelError::MissingFile { path: p.clone() }
                    } else {
                        ModelError::Io {
                            path: p.clone(),
                            source: e,
                        }
                    }
                })
            }
            Source::Embedded(files) => files
                .iter()
                .find(|(n, _)| *n == name)
                .map(|(_, b)| b.to_vec())
                .ok_or_else(|| ModelError::MissingFile {
                    path: self.path(name),
                }),
        }
    }
}

// ------------------------------------------------------------------------ model.json schema

#[derive(Serialize, Deserialize, Debug, Clone)]
#[serde(untagged)]
enum Floats {
    Inline(Vec<f64>),
    File(String),
}

#[derive(Serialize, Deserialize, Debug, Clone)]
#[serde(untagged)]
enum Indices {
    Inline(Vec<i64>),
    File(String),
}

#[derive(Serialize, Deserialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct FilesJson {
    mean_shape: String,
    id_basis: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    exp_basis: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    mean_albedo: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    albedo_basis: Option<String>,
    faces: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    uvs: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    face_regions: Option<String>,
}

#[derive(Serialize, Deserialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct RegionJson {
    name: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    albedo: Option<[f64; 3]>,
    #[serde(default = "yes", skip_serializing_if = "is_yes")]
    photometric: bool,
}

fn yes() -> bool {
    true
}
fn is_yes(b: &bool) -> bool {
    *b
}

fn default_units() -> String {
    "mm".into()
}
fn one() -> f64 {
    1.0
}
fn is_one(x: &f64) -> bool {
    *x == 1.0
}
fn is_false(x: &bool) -> bool {
    !*x
}

#[derive(Serialize, Deserialize, Debug, Clone)]
#[serde(deny_unknown_fields)]
struct ModelJson {
    #[serde(default)]
    format: Option<String>,
    #[serde(default)]
    version: Option<u32>,
    #[serde(default)]
    name: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    description: Option<String>,
    #[serde(default = "default_units")]
    units: String,
    #[serde(default, skip_serializing_if = "is_false")]
    basis_scaled: bool,
    #[serde(default = "one", skip_serializing_if = "is_one")]
    albedo_scale: f64,
    n_vertices: usize,
    #[serde(default)]
    n_faces: Option<usize>,
    #[serde(default)]
    n_id: Option<usize>,
    #[serde(default)]
    n_exp: Option<usize>,
    #[serde(default)]
    n_albedo: Option<usize>,
    files: FilesJson,
    sigma_id: Floats,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    sigma_exp: Option<Floats>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    sigma_albedo: Option<Floats>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    landmarks: Option<Indices>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    landmark_points: Option<Vec<[f64; 4]>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    landmark_scheme: Option<String>,
    #[serde(default)]
    landmark_groups: BTreeMap<String, Vec<i64>>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    regions: Vec<RegionJson>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    id_names: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    exp_names: Vec<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    albedo_names: Vec<String>,
}

/// Length unit names accepted in `model.json` and their size in millimetres.
pub const UNITS: &[(&str, f64)] = &[("mm", 1.0), ("cm", 10.0), ("m", 1000.0), ("um", 1e-3)];

// ------------------------------------------------------------------------ .npy reading

const FLOAT_DTYPES: &str = "float16, float32 or float64";
const INT_DTYPES: &str = "a fixed-size integer dtype (int8..int64, uint8..uint64)";

fn npy_err(file: &str, e: ReadNpyError) -> ModelError {
    ModelError::Npy {
        file: file.to_string(),
        detail: e.to_string(),
    }
}

/// A float array (f16, f32 or f64 on disk) as f64.
fn read_floats(src: &Source<'_>, name: &str) -> Result<ArrayD<f64>> {
    let file = src.label(name);
    let bytes = src.read(name)?;
    match ArrayD::<f64>::read_npy(&bytes[..]) {
        Ok(a) => return Ok(a),
        Err(ReadNpyError::WrongDescriptor(_)) => {}
        Err(e) => return Err(npy_err(&file, e)),
    }
    let d = match ArrayD::<f32>::read_npy(&bytes[..]) {
        Ok(a) => return Ok(a.mapv(f64::from)),
        Err(ReadNpyError::WrongDescriptor(d)) => d,
        Err(e) => return Err(npy_err(&file, e)),
    };
    let descr = d.to_string();
    match swap_half_descr(bytes, "f2", "u2") {
        Some(bits) if descr.contains("f2") => match ArrayD::<u16>::read_npy(&bits[..]) {
            Ok(a) => Ok(a.mapv(|b| half::f16::from_bits(b).to_f64())),
            Err(e) => Err(npy_err(&file, e)),
        },
        _ => Err(ModelError::WrongDtype {
            file,
            found: descr,
            expected: FLOAT_DTYPES,
        }),
    }
}

/// The `.npy` bytes with the header's 2-byte dtype code `from` (`f2` or `u2`, either byte
/// order) replaced by `to`: ndarray-npy has no half-precision element, so float16 data are
/// read and written as their `u16` bit patterns under a header that says so. `None` when the
/// header has no such descriptor.
fn swap_half_descr(mut bytes: Vec<u8>, from: &str, to: &str) -> Option<Vec<u8>> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return None;
    }
    let (start, len) = match bytes[6] {
        1 => (10usize, u16::from_le_bytes([bytes[8], bytes[9]]) as usize),
        _ if bytes.len() >= 12 => (
            12,
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
        ),
        _ => return None,
    };
    let header = bytes.get(start..start.checked_add(len)?)?;
    let at = ["<", ">", "="].iter().find_map(|order| {
        let pat = format!("'descr': '{order}{from}'");
        let text = std::str::from_utf8(header).ok()?;
        text.find(&pat).map(|i| start + i + pat.len() - 3)
    })?;
    bytes[at..at + 2].copy_from_slice(to.as_bytes());
    Some(bytes)
}

/// Writes `a` as a float16 `.npy` file (NumPy dtype `<f2`), each value rounded to the nearest
/// half-precision number (IEEE 754 binary16: 11 significant bits, relative error at most
/// 2^-11 for normal numbers). For compact model files; [`Morphable::load`] reads them back.
pub fn write_f16_npy(path: &Path, a: &ArrayD<f64>) -> Result<()> {
    let mut buf = Vec::new();
    a.mapv(|x| half::f16::from_f64(x).to_bits())
        .write_npy(&mut buf)
        .map_err(|e| write_err(path, e))?;
    let bytes = swap_half_descr(buf, "u2", "f2")
        .ok_or_else(|| write_err(path, "no u2 descriptor in the npy header"))?;
    std::fs::write(path, bytes).map_err(|e| ModelError::Io {
        path: path.to_path_buf(),
        source: e,
    })
}

fn read_ints(src: &Source<'_>, name: &str) -> Result<ArrayD<i64>> {
    let file = src.label(name);
    let bytes = src.read(name)?;
    macro_rules! attempt {
        ($t:ty) => {
            match ArrayD::<$t>::read_npy(&bytes[..]) {
                Ok(a) => {
                    let mut out = ArrayD::<i64>::zeros(a.raw_dim());
                    for (o, &v) in out.iter_mut().zip(a.iter()) {
                        *o = i64::try_from(v).map_err(|_| ModelError::Invalid {
                            file: file.clone(),
                            detail: format!("value {v} does not fit an index"),
                        })?;
                    }
                    return Ok(out);
                }
                Err(ReadNpyError::WrongDescriptor(d)) => d,
                Err(e) => return Err(npy_err(&file, e)),
            }
        };
    }
    attempt!(i64);
    attempt!(i32);
    attempt!(u32);
    attempt!(u64);
    attempt!(i16);
    attempt!(u16);
    attempt!(u8);
    let d = attempt!(i8);
    Err(ModelError::WrongDtype {
        file,
        found: d.to_string(),
        expected: INT_DTYPES,
    })
}

fn to_t<T: Real>(a: ArrayD<f64>) -> ArrayD<T> {
    a.mapv(T::from_f64c)
}

/// `[V, 3]` or `[3V]` to `[V, 3]`.
fn per_vertex3<T: Real>(file: &str, a: ArrayD<f64>) -> Result<Array2<T>> {
    let shape = a.shape().to_vec();
    let a = match shape.len() {
        2 if shape[1] == 3 => a,
        1 if shape[0].rem_euclid(3) == 0 => a
            .into_shape_with_order(IxDyn(&[shape[0] / 3, 3]))
            .expect("3V"),
        _ => {
            return Err(ModelError::Shape {
                file: file.to_string(),
                shape,
                expected: "[V, 3] or [3V]".into(),
            })
        }
    };
    Ok(to_t(a).into_dimensionality::<Ix2>().expect("2-d"))
}

/// `[3V, K]` or `[V, 3, K]` to `[3V, K]` (same memory order).
fn basis<T: Real>(file: &str, a: ArrayD<f64>) -> Result<Array2<T>> {
    let shape = a.shape().to_vec();
    let a = match shape.len() {
        2 => a,
        3 if shape[1] == 3 => a
            .as_standard_layout()
            .into_owned()
            .into_shape_with_order(IxDyn(&[shape[0] * 3, shape[2]]))
            .expect("same size"),
        _ => {
            return Err(ModelError::Shape {
                file: file.to_string(),
                shape,
                expected: "[3V, K] or [V, 3, K]".into(),
            })
        }
    };
    Ok(to_t(a).into_dimensionality::<Ix2>().expect("2-d"))
}

fn vector<T: Real>(file: &str, a: ArrayD<f64>) -> Result<Array1<T>> {
    if a.ndim() != 1 {
        return Err(ModelError::Shape {
            file: file.to_string(),
            shape: a.shape().to_vec(),
            expected: "[K]".into(),
        });
    }
    Ok(to_t(a).into_dimensionality().expect("1-d"))
}

fn floats<T: Real>(
    src: &Source<'_>,
    json_label: &str,
    key: &str,
    f: &Floats,
) -> Result<(Array1<T>, String)> {
    match f {
        Floats::Inline(v) => Ok((
            Array1::from_iter(v.iter().map(|&x| T::from_f64c(x))),
            format!("{json_label}: {key}"),
        )),
        Floats::File(name) => {
            let label = src.label(name);
            let a = read_floats(src, name)?;
            Ok((vector(&label, a)?, label))
        }
    }
}

fn indices(label: &str, what: &str, v: &[i64], bound: usize) -> Result<Vec<usize>> {
    v.iter()
        .enumerate()
        .map(|(i, &x)| {
            if x < 0 || x as u64 >= bound as u64 {
                Err(ModelError::IndexOutOfRange {
                    file: label.to_string(),
                    what: what.to_string(),
                    position: i,
                    index: x,
                    bound,
                })
            } else {
                Ok(x as usize)
            }
        })
        .collect()
}

fn check_dim(file: &str, what: &str, expected: Option<usize>, found: usize) -> Result<()> {
    match expected {
        Some(e) if e != found => Err(ModelError::Dimension {
            file: file.to_string(),
            what: what.to_string(),
            expected: e,
            found,
        }),
        _ => Ok(()),
    }
}

fn scale_basis_or_sigma<T: Real>(
    b: &mut Array2<T>,
    s: &mut Array1<T>,
    factor: f64,
    basis_scaled: bool,
) {
    if factor == 1.0 {
        return;
    }
    let f = T::from_f64c(factor);
    if basis_scaled {
        b.mapv_inplace(|x| x * f);
    } else {
        s.mapv_inplace(|x| x * f);
    }
}

pub(crate) fn load_from<T: Real>(src: &Source<'_>) -> Result<Morphable<T>> {
    let json_name = "model.json";
    let json_path = src.path(json_name);
    let json_label = src.label(json_name);
    let text = src.read(json_name)?;
    let j: ModelJson = serde_json::from_slice(&text).map_err(|e| ModelError::Json {
        path: json_path.clone(),
        detail: e.to_string(),
    })?;
    let json_err = |detail: String| ModelError::Json {
        path: json_path.clone(),
        detail,
    };
    if let Some(f) = &j.format {
        if f != FORMAT {
            return Err(json_err(format!("format {f:?} is not {FORMAT:?}")));
        }
    }
    if let Some(v) = j.version {
        if v != VERSION {
            return Err(json_err(format!(
                "version {v} is not supported (this reader knows {VERSION})"
            )));
        }
    }
    let unit = UNITS
        .iter()
        .find(|(n, _)| *n == j.units)
        .map(|(_, s)| *s)
        .ok_or_else(|| {
            json_err(format!(
                "units {:?} unknown (one of {})",
                j.units,
                UNITS.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
            ))
        })?;
    if !(j.albedo_scale.is_finite() && j.albedo_scale > 0.0) {
        return Err(json_err(format!(
            "albedo_scale {} must be > 0",
            j.albedo_scale
        )));
    }
    let v = j.n_vertices;
    let mut labels = Labels::default();

    // Mean shape fixes V.
    let name = &j.files.mean_shape;
    labels.mean_shape = src.label(name);
    let mut mean_shape: Array2<T> = per_vertex3(&labels.mean_shape, read_floats(src, name)?)?;
    check_dim(
        &labels.mean_shape,
        "number of vertices (n_vertices in model.json)",
        Some(v),
        mean_shape.nrows(),
    )?;

    let load_basis = |name: &str, label: &str, k: Option<usize>, key: &str| -> Result<Array2<T>> {
        let b: Array2<T> = basis(label, read_floats(src, name)?)?;
        if b.nrows() != 3 * v {
            return Err(ModelError::Dimension {
                file: label.to_string(),
                what: "rows (3 * n_vertices)".into(),
                expected: 3 * v,
                found: b.nrows(),
            });
        }
        check_dim(
            label,
            &format!("columns ({key} in model.json)"),
            k,
            b.ncols(),
        )?;
        Ok(b)
    };

    labels.id_basis = src.label(&j.files.id_basis);
    let mut id_basis = load_basis(&j.files.id_basis, &labels.id_basis, j.n_id, "n_id")?;
    let (mut sigma_id, l) = floats::<T>(src, &json_label, "sigma_id", &j.sigma_id)?;
    labels.sigma_id = l;

    let (mut exp_basis, mut sigma_exp) = match &j.files.exp_basis {
        Some(name) => {
            labels.exp_basis = src.label(name);
            let b = load_basis(name, &labels.exp_basis, j.n_exp, "n_exp")?;
            let s = match &j.sigma_exp {
                Some(f) => {
                    let (s, l) = floats::<T>(src, &json_label, "sigma_exp", f)?;
                    labels.sigma_exp = l;
                    s
                }
                None => {
                    return Err(json_err(
                        "files.exp_basis is given but sigma_exp is not".into(),
                    ))
                }
            };
            (b, s)
        }
        None => {
            check_dim(&json_label, "n_exp (no files.exp_basis)", j.n_exp, 0)?;
            (Array2::zeros((3 * v, 0)), Array1::zeros(0))
        }
    };

    let mut mean_albedo: Array2<T> = match &j.files.mean_albedo {
        Some(name) => {
            labels.mean_albedo = src.label(name);
            per_vertex3(&labels.mean_albedo, read_floats(src, name)?)?
        }
        None => Array2::from_elem((v, 3), T::from_f64c(0.6 / j.albedo_scale)),
    };
    let (mut albedo_basis, mut sigma_albedo) = match &j.files.albedo_basis {
        Some(name) => {
            labels.albedo_basis = src.label(name);
            let b = load_basis(name, &labels.albedo_basis, j.n_albedo, "n_albedo")?;
            let s = match &j.sigma_albedo {
                Some(f) => {
                    let (s, l) = floats::<T>(src, &json_label, "sigma_albedo", f)?;
                    labels.sigma_albedo = l;
                    s
                }
                None => {
                    return Err(json_err(
                        "files.albedo_basis is given but sigma_albedo is not".into(),
                    ))
                }
            };
            (b, s)
        }
        None => {
            check_dim(
                &json_label,
                "n_albedo (no files.albedo_basis)",
                j.n_albedo,
                0,
            )?;
            (Array2::zeros((3 * v, 0)), Array1::zeros(0))
        }
    };

    // Units: lengths to millimetres, albedo by albedo_scale.
    if unit != 1.0 {
        let u = T::from_f64c(unit);
        mean_shape.mapv_inplace(|x| x * u);
    }
    scale_basis_or_sigma(&mut id_basis, &mut sigma_id, unit, j.basis_scaled);
    scale_basis_or_sigma(&mut exp_basis, &mut sigma_exp, unit, j.basis_scaled);
    if j.albedo_scale != 1.0 {
        let a = T::from_f64c(j.albedo_scale);
        mean_albedo.mapv_inplace(|x| x * a);
    }
    scale_basis_or_sigma(
        &mut albedo_basis,
        &mut sigma_albedo,
        j.albedo_scale,
        j.basis_scaled,
    );

    // Topology.
    labels.faces = src.label(&j.files.faces);
    let fa = read_ints(src, &j.files.faces)?;
    if fa.ndim() != 2 || fa.shape()[1] != 3 {
        return Err(ModelError::Shape {
            file: labels.faces.clone(),
            shape: fa.shape().to_vec(),
            expected: "[F, 3]".into(),
        });
    }
    check_dim(
        &labels.faces,
        "number of faces (n_faces in model.json)",
        j.n_faces,
        fa.shape()[0],
    )?;
    let flat: Vec<i64> = fa.iter().copied().collect();
    let idx = indices(&labels.faces, "vertex index", &flat, v)?;
    let faces: Vec<[u32; 3]> = idx
        .chunks(3)
        .map(|c| [c[0] as u32, c[1] as u32, c[2] as u32])
        .collect();

    let uvs = match &j.files.uvs {
        Some(name) => {
            labels.uvs = src.label(name);
            let a = read_floats(src, name)?;
            if a.ndim() != 2 || a.shape()[1] != 2 {
                return Err(ModelError::Shape {
                    file: labels.uvs.clone(),
                    shape: a.shape().to_vec(),
                    expected: "[V, 2]".into(),
                });
            }
            check_dim(&labels.uvs, "rows (n_vertices)", Some(v), a.shape()[0])?;
            Some(to_t::<T>(a).into_dimensionality::<Ix2>().expect("2-d"))
        }
        None => None,
    };

    let regions: Vec<Region> = j
        .regions
        .iter()
        .map(|r| Region {
            name: r.name.clone(),
            albedo: r.albedo,
            photometric: r.photometric,
        })
        .collect();
    let face_regions = match &j.files.face_regions {
        Some(name) => {
            labels.face_regions = src.label(name);
            let a = read_ints(src, name)?;
            if a.ndim() != 1 {
                return Err(ModelError::Shape {
                    file: labels.face_regions.clone(),
                    shape: a.shape().to_vec(),
                    expected: "[F]".into(),
                });
            }
            check_dim(
                &labels.face_regions,
                "length (n_faces)",
                Some(faces.len()),
                a.len(),
            )?;
            let flat: Vec<i64> = a.iter().copied().collect();
            let n_regions = regions.len().max(1);
            indices(&labels.face_regions, "region label", &flat, n_regions)?
                .into_iter()
                .map(|x| x as u16)
                .collect()
        }
        None => vec![],
    };

    labels.landmarks = format!("{json_label}: landmarks");
    labels.landmark_points = format!("{json_label}: landmark_points");
    let landmark_scheme = match &j.landmark_scheme {
        None => None,
        Some(name) => Some(LandmarkScheme::from_name(name).ok_or_else(|| {
            json_err(format!(
                "landmark_scheme {name:?} unknown (one of {})",
                LandmarkScheme::ALL.map(|s| s.name()).join(", ")
            ))
        })?),
    };
    let mut landmark_points = Vec::new();
    if let Some(rows) = &j.landmark_points {
        if j.landmarks.is_some() {
            return Err(json_err(
                "give either landmarks (vertices) or landmark_points (points on triangles), not both"
                    .into(),
            ));
        }
        for (i, r) in rows.iter().enumerate() {
            if !(r[0].is_finite() && r[0] >= 0.0 && r[0].fract() == 0.0) {
                return Err(ModelError::Invalid {
                    file: labels.landmark_points.clone(),
                    detail: format!("point {i}: triangle index {} is not an index", r[0]),
                });
            }
            landmark_points.push(SurfacePoint {
                face: r[0] as usize,
                weights: [r[1], r[2], r[3]],
            });
        }
    }
    let landmarks = match &j.landmarks {
        None if j.landmark_points.is_some() => vec![],
        None => (0..v).collect(),
        Some(Indices::Inline(l)) => indices(&labels.landmarks, "landmark vertex index", l, v)?,
        Some(Indices::File(name)) => {
            labels.landmarks = src.label(name);
            let a = read_ints(src, name)?;
            if a.ndim() != 1 {
                return Err(ModelError::Shape {
                    file: labels.landmarks.clone(),
                    shape: a.shape().to_vec(),
                    expected: "[L]".into(),
                });
            }
            let flat: Vec<i64> = a.iter().copied().collect();
            indices(&labels.landmarks, "landmark vertex index", &flat, v)?
        }
    };
    labels.groups = format!("{json_label}: landmark_groups");
    let mut groups = BTreeMap::new();
    for (name, g) in &j.landmark_groups {
        let l = format!("{json_label}: landmark_groups.{name}");
        groups.insert(name.clone(), indices(&l, "vertex index", g, v)?);
    }
    labels.names = json_label.clone();

    let parts = MorphableParts {
        name: j.name.clone().unwrap_or_default(),
        description: j.description.clone().unwrap_or_default(),
        mean_shape,
        id_basis,
        sigma_id,
        exp_basis,
        sigma_exp,
        mean_albedo,
        albedo_basis,
        sigma_albedo,
        basis_scaled: j.basis_scaled,
        faces,
        uvs,
        landmarks,
        landmark_points,
        landmark_scheme,
        landmark_groups: groups,
        regions,
        face_regions,
        id_names: j.id_names.clone(),
        exp_names: j.exp_names.clone(),
        albedo_names: j.albedo_names.clone(),
    };
    Morphable::from_parts_labelled(parts, &labels)
}

// ------------------------------------------------------------------------ writing

fn write_err(path: &Path, detail: impl std::fmt::Display) -> ModelError {
    ModelError::Io {
        path: path.to_path_buf(),
        source: std::io::Error::other(detail.to_string()),
    }
}

fn write_float<T: Real>(dir: &Path, name: &str, a: &ArrayD<T>) -> Result<()> {
    let path = dir.join(name);
    let file = std::fs::File::create(&path).map_err(|e| ModelError::Io {
        path: path.clone(),
        source: e,
    })?;
    let w = std::io::BufWriter::new(file);
    let r = if T::NAME == "f32" {
        a.mapv(|x| x.to_f64c() as f32).write_npy(w)
    } else {
        a.mapv(|x| x.to_f64c()).write_npy(w)
    };
    r.map_err(|e| write_err(&path, e))
}

fn write_int(dir: &Path, name: &str, a: &ArrayD<i32>) -> Result<()> {
    let path = dir.join(name);
    let file = std::fs::File::create(&path).map_err(|e| ModelError::Io {
        path: path.clone(),
        source: e,
    })?;
    a.write_npy(std::io::BufWriter::new(file))
        .map_err(|e| write_err(&path, e))
}

/// A JSON number that prints the shortest decimal that reads back as the same `T`.
fn json_number<T: Real>(x: T) -> f64 {
    if T::NAME == "f32" {
        format!("{x}")
            .parse::<f64>()
            .unwrap_or_else(|_| x.to_f64c())
    } else {
        x.to_f64c()
    }
}

const KEY_ORDER: &[&str] = &[
    "format",
    "version",
    "name",
    "description",
    "units",
    "basis_scaled",
    "albedo_scale",
    "n_vertices",
    "n_faces",
    "n_id",
    "n_exp",
    "n_albedo",
    "files",
    "mean_shape",
    "id_basis",
    "exp_basis",
    "mean_albedo",
    "albedo_basis",
    "faces",
    "uvs",
    "face_regions",
    "sigma_id",
    "sigma_exp",
    "sigma_albedo",
    "landmarks",
    "landmark_scheme",
    "landmark_points",
    "landmark_groups",
    "regions",
    "id_names",
    "exp_names",
    "albedo_names",
];

/// Pretty JSON with arrays of scalars kept on one line.
fn pretty(v: &Value, indent: usize, out: &mut String) {
    let pad = |n: usize| "  ".repeat(n);
    match v {
        Value::Object(m) if !m.is_empty() => {
            out.push_str("{\n");
            // Keys in the order of the schema (serde_json's map is sorted).
            let rank = |k: &str| KEY_ORDER.iter().position(|&o| o == k).unwrap_or(usize::MAX);
            let mut items: Vec<(&String, &Value)> = m.iter().collect();
            items.sort_by_key(|(k, _)| rank(k));
            for (i, (k, x)) in items.into_iter().enumerate() {
                out.push_str(&pad(indent + 1));
                out.push_str(&serde_json::to_string(k).expect("string"));
                out.push_str(": ");
                pretty(x, indent + 1, out);
                if i + 1 < m.len() {
                    out.push(',');
                }
                out.push('\n');
            }
            out.push_str(&pad(indent));
            out.push('}');
        }
        Value::Array(a) if a.iter().any(|x| x.is_object() || x.is_array()) => {
            out.push_str("[\n");
            for (i, x) in a.iter().enumerate() {
                out.push_str(&pad(indent + 1));
                pretty(x, indent + 1, out);
                if i + 1 < a.len() {
                    out.push(',');
                }
                out.push('\n');
            }
            out.push_str(&pad(indent));
            out.push(']');
        }
        Value::Array(a) => {
            out.push('[');
            for (i, x) in a.iter().enumerate() {
                if i > 0 {
                    out.push_str(", ");
                }
                out.push_str(&serde_json::to_string(x).expect("scalar"));
            }
            out.push(']');
        }
        _ => out.push_str(&serde_json::to_string(v).expect("scalar")),
    }
}

pub(crate) fn save_to<T: Real>(m: &Morphable<T>, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| ModelError::Io {
        path: dir.to_path_buf(),
        source: e,
    })?;
    let v = m.n_vertices();
    write_float(dir, "mean_shape.npy", &m.mean_shape().into_dyn())?;
    write_float(dir, "id_basis.npy", &m.id_basis().to_owned().into_dyn())?;
    let has_exp = m.n_exp() > 0;
    if has_exp {
        write_float(dir, "exp_basis.npy", &m.exp_basis().to_owned().into_dyn())?;
    }
    write_float(dir, "mean_albedo.npy", &m.mean_albedo().into_dyn())?;
    let has_alb = m.n_albedo() > 0;
    if has_alb {
        write_float(
            dir,
            "albedo_basis.npy",
            &m.albedo_basis().to_owned().into_dyn(),
        )?;
    }
    let faces = m.faces_array().mapv(|x| x as i32).into_dyn();
    write_int(dir, "faces.npy", &faces)?;
    if let Some(uv) = m.uvs() {
        write_float(dir, "uvs.npy", &uv.clone().into_dyn())?;
    }
    let labelled = m.regions().len() > 1;
    if labelled {
        let r = ArrayD::from_shape_vec(
            IxDyn(&[m.n_faces()]),
            m.face_regions().iter().map(|&x| x as i32).collect(),
        )
        .expect("F");
        write_int(dir, "face_regions.npy", &r)?;
    }
    let sig =
        |s: ndarray::ArrayView1<'_, T>| Floats::Inline(s.iter().map(|&x| json_number(x)).collect());
    let all: Vec<usize> = (0..v).collect();
    let j = ModelJson {
        format: Some(FORMAT.into()),
        version: Some(VERSION),
        name: Some(m.name().to_string()),
        description: (!m.description().is_empty()).then(|| m.description().to_string()),
        units: "mm".into(),
        basis_scaled: m.basis_scaled(),
        albedo_scale: 1.0,
        n_vertices: v,
        n_faces: Some(m.n_faces()),
        n_id: Some(m.n_id()),
        n_exp: Some(m.n_exp()),
        n_albedo: Some(m.n_albedo()),
        files: FilesJson {
            mean_shape: "mean_shape.npy".into(),
            id_basis: "id_basis.npy".into(),
            exp_basis: has_exp.then(|| "exp_basis.npy".into()),
            mean_albedo: Some("mean_albedo.npy".into()),
            albedo_basis: has_alb.then(|| "albedo_basis.npy".into()),
            faces: "faces.npy".into(),
            uvs: m.uvs().map(|_| "uvs.npy".into()),
            face_regions: labelled.then(|| "face_regions.npy".into()),
        },
        sigma_id: sig(m.sigma_id()),
        sigma_exp: has_exp.then(|| sig(m.sigma_exp())),
        sigma_albedo: has_alb.then(|| sig(m.sigma_albedo())),
        landmarks: (m.surface_landmarks().is_empty() && m.landmarks() != all.as_slice())
            .then(|| Indices::Inline(m.landmarks().iter().map(|&x| x as i64).collect())),
        landmark_points: (!m.surface_landmarks().is_empty()).then(|| {
            m.surface_landmarks()
                .iter()
                .map(|q| [q.face as f64, q.weights[0], q.weights[1], q.weights[2]])
                .collect()
        }),
        landmark_scheme: m.landmark_scheme().map(|s| s.name().to_string()),
        landmark_groups: m
            .landmark_groups()
            .iter()
            .map(|(k, g)| (k.clone(), g.iter().map(|&x| x as i64).collect()))
            .collect(),
        regions: if labelled || m.regions()[0].albedo.is_some() || !m.regions()[0].photometric {
            m.regions()
                .iter()
                .map(|r| RegionJson {
                    name: r.name.clone(),
                    albedo: r.albedo,
                    photometric: r.photometric,
                })
                .collect()
        } else {
            vec![]
        },
        id_names: m.id_names().to_vec(),
        exp_names: m.exp_names().to_vec(),
        albedo_names: m.albedo_names().to_vec(),
    };
    let value = serde_json::to_value(&j).map_err(|e| write_err(&dir.join("model.json"), e))?;
    let mut text = String::new();
    pretty(&value, 0, &mut text);
    text.push('\n');
    let path = dir.join("model.json");
    std::fs::write(&path, text).map_err(|e| ModelError::Io { path, source: e })
}

impl<T: Real> Morphable<T> {
    /// Loads a model folder (`model.json` plus `.npy` arrays; see the module docs and
    /// `models/README.md`). Lengths are converted to millimetres (`units`), albedo scaled by
    /// `albedo_scale`. Every dimension, index and value is checked; errors name the file.
    pub fn load(dir: impl AsRef<Path>) -> Result<Self> {
        load_from(&Source::Dir(dir.as_ref()))
    }

    /// Loads a model from files held in memory, `(file name, bytes)` pairs with the same
    /// names as in a folder (`model.json` and the files it names); e.g. `include_bytes!`.
    pub fn load_from_memory(files: &[(&str, &[u8])]) -> Result<Self> {
        load_from(&Source::Embedded(files))
    }

    /// Writes the model to `dir` (created if needed) in the layout [`Morphable::load`]
    /// reads, arrays in the model's precision, units millimetres.
    pub fn save(&self, dir: impl AsRef<Path>) -> Result<()> {
        save_to(self, dir.as_ref())
    }
}
