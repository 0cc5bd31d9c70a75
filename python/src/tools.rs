//! `fit_face` (the library path of `tapestry fit-face`: `tapestry::cli::fit_face::fit_face`)
//! and `gradcheck` (`tapestry gradcheck`: the registered cases and the scene check).
//! Reports come back as JSON text, parsed by the Python wrapper.

use std::path::PathBuf;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use tapestry::cli::fit_face::{self, Args, GivenTarget};
use tapestry::cli::gradcheck::{self, SceneArgs, WORST};

use crate::array::{floats, to_numpy};
use crate::to_py;

/// _fit_face(image, landmarks, iters, method, size, seed, model, face)
/// -> (params_json, report_json, vertices, faces, albedo, image)
#[pyfunction]
#[pyo3(signature = (image = None, landmarks = None, iters = 200, method = "hard".to_string(), size = 256, seed = 0, model = None, face = 0))]
#[allow(clippy::too_many_arguments)]
fn _fit_face<'py>(
    py: Python<'py>,
    image: Option<&Bound<'py, PyAny>>,
    landmarks: Option<&Bound<'py, PyAny>>,
    iters: usize,
    method: String,
    size: usize,
    seed: u64,
    model: Option<PathBuf>,
    face: usize,
) -> PyResult<Vec<Bound<'py, PyAny>>> {
    let given = match image {
        Some(img) => {
            let photo = floats::<f64>(
                "image",
                img,
                &[None, None, None],
                "[H, W, C] float64, C of 1 to 4",
            )?
            .to_tensor();
            if !(1..=4).contains(&photo.shape()[2]) {
                return Err(PyValueError::new_err(format!(
                    "image: shape {:?}, expected [H, W, C] with C of 1 to 4",
                    photo.shape()
                )));
            }
            if photo.iter().any(|x| !x.is_finite()) {
                return Err(PyValueError::new_err("image: values must be finite"));
            }
            let lms = match landmarks {
                Some(l) => {
                    let l = floats::<f64>("landmarks", l, &[None, Some(2)], "[N, 2] float64")?
                        .to_tensor();
                    Some(l.into_dimensionality().expect("2-d"))
                }
                None => None,
            };
            Some(GivenTarget {
                photo: photo.into_dimensionality().expect("3-d"),
                landmarks: lms,
            })
        }
        None if landmarks.is_some() => {
            return Err(PyValueError::new_err(
                "landmarks need an image (the photo they belong to)",
            ))
        }
        None => None,
    };
    let args = Args {
        target: None,
        landmarks: None,
        model,
        face,
        out: PathBuf::new(),
        iters,
        seed,
        method,
        size,
        texture_size: 512,
        texture_iters: 30,
    };
    let fit = py
        .detach(|| fit_face::fit_face(&args, given).map_err(|e| e.to_string()))
        .map_err(to_py)?;
    let faces: Vec<i64> = fit.faces.iter().flatten().map(|&x| x as i64).collect();
    let nf = fit.faces.len();
    Ok(vec![
        fit.params_json.to_string().into_pyobject(py)?.into_any(),
        fit.report.to_string().into_pyobject(py)?.into_any(),
        to_numpy(py, fit.vertices.into_dyn()),
        to_numpy(
            py,
            ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&[nf, 3]), faces).expect("f x 3"),
        ),
        to_numpy(py, fit.albedo.into_dyn()),
        to_numpy(py, fit.image.into_dyn()),
    ])
}

/// _gradcheck(op=None) -> (json list of case records, all passed)
#[pyfunction]
#[pyo3(signature = (op = None))]
fn _gradcheck(py: Python<'_>, op: Option<String>) -> PyResult<(String, bool)> {
    let results = py.detach(|| render_ops::check::registry().run(op.as_deref()));
    if results.is_empty() {
        return Err(to_py(format!(
            "gradcheck: no op matches '{}'",
            op.unwrap_or_default()
        )));
    }
    let recs: Vec<serde_json::Value> = results.iter().map(gradcheck::case_json).collect();
    Ok((
        serde_json::Value::Array(recs).to_string(),
        results.iter().all(|r| r.passed),
    ))
}

/// _gradcheck_scene(path, wrt, target, method, samples, vertices) -> (json report, passed)
#[pyfunction]
#[pyo3(signature = (path, wrt, target = None, method = None, samples = 8, vertices = 48))]
fn _gradcheck_scene(
    py: Python<'_>,
    path: PathBuf,
    wrt: &str,
    target: Option<PathBuf>,
    method: Option<String>,
    samples: usize,
    vertices: usize,
) -> PyResult<(String, bool)> {
    let input = crate::scene::parse_wrt(wrt)?;
    let a = SceneArgs {
        scene: path,
        wrt: input,
        target,
        method,
        samples,
        vertices,
        out: None,
        backward_scale: None,
        json: true,
    };
    let check = py
        .detach(|| gradcheck::check_scene_args(&a).map_err(|e| e.to_string()))
        .map_err(to_py)?;
    Ok((check.to_json(WORST).to_string(), check.passed()))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_fit_face, m)?)?;
    m.add_function(wrap_pyfunction!(_gradcheck, m)?)?;
    m.add_function(wrap_pyfunction!(_gradcheck_scene, m)?)?;
    Ok(())
}
