//! The scene commands: `render_scene` (`tapestry render --npy`) and `grad_scene`
//! (`tapestry grad`), through the same library calls as the command line
//! ([`Scene::render_image`], [`Scene::image_loss_grad`]), so the numbers are the same bit for bit.

use std::path::PathBuf;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use render_ops::io::read_image;
use render_ops::pipeline::SceneInput;
use render_ops::scene::Scene;

use crate::array::{dtype_of, floats, to_numpy, with_dtype, Dt};
use crate::to_py;

/// A scene input by its command-line name.
pub(crate) fn parse_wrt(wrt: &str) -> PyResult<SceneInput> {
    SceneInput::from_name(wrt).ok_or_else(|| {
        PyValueError::new_err(format!(
            "wrt '{wrt}': expected one of {}",
            SceneInput::ALL.map(|i| i.name()).join(", ")
        ))
    })
}

fn parse_dtype(dtype: &str) -> PyResult<Dt> {
    match dtype {
        "float64" | "f64" | "double" => Ok(Dt::F64),
        "float32" | "f32" | "float" => Ok(Dt::F32),
        _ => Err(PyValueError::new_err(format!(
            "dtype '{dtype}': expected 'float64' or 'float32'"
        ))),
    }
}

/// Renders a scene JSON: the RGBA image [H, W, 4] (RGB over the background, alpha = coverage).
/// With dtype="float64" (the default) this is, bit for bit, the array that
/// `tapestry render SCENE --npy` writes; "float32" renders in single precision.
#[pyfunction]
#[pyo3(signature = (path, dtype = "float64"))]
fn render_scene<'py>(py: Python<'py>, path: PathBuf, dtype: &str) -> PyResult<Bound<'py, PyAny>> {
    with_dtype!(parse_dtype(dtype)?, T => {
        let img = py
            .detach(|| Scene::<T>::load(&path).map_err(|e| e.to_string()).and_then(|s| s.render_image().map_err(|e| e.to_string())))
            .map_err(to_py)?;
        Ok(to_numpy(py, img))
    })
}

/// L = sum over pixels and channels of (render - target)^2 and dL/d(input), in float64:
/// `(loss, grad)`, exactly what `tapestry grad SCENE --target T --wrt INPUT` prints and writes.
/// `target` is a float64 array [H, W, 3] (compared with RGB) or [H, W, 4] (RGBA), or a path
/// (PNG or .npy, read as the command line reads it). `wrt`: "positions" [V, 3], "colors"
/// [V, 3], "texture" [H, W, C], "camera" [2, 3] (eye; at), "lights" [n, 3].
#[pyfunction]
#[pyo3(signature = (path, target, wrt = "positions"))]
fn grad_scene<'py>(
    py: Python<'py>,
    path: PathBuf,
    target: &Bound<'py, PyAny>,
    wrt: &str,
) -> PyResult<(f64, Bound<'py, PyAny>)> {
    let input = parse_wrt(wrt)?;
    let (target, name) = if let Ok(p) = target.extract::<PathBuf>() {
        let t = read_image::<f64>(&p).map_err(to_py)?.into_dyn();
        (t, p.display().to_string())
    } else {
        if dtype_of("target", target)? != Dt::F64 {
            return Err(pyo3::exceptions::PyTypeError::new_err(
                "target: dtype float32, expected float64 (the gradient is computed in float64, as the command line does)",
            ));
        }
        let t = floats::<f64>(
            "target",
            target,
            &[None, None, None],
            "[H, W, 3] or [H, W, 4]",
        )?;
        (t.to_tensor(), "array".to_string())
    };
    let (loss, g) = py
        .detach(|| {
            let scene = Scene::<f64>::load(&path).map_err(|e| e.to_string())?;
            scene
                .image_loss_grad(target, &name, input)
                .map_err(|e| e.to_string())
        })
        .map_err(to_py)?;
    Ok((loss, to_numpy(py, g)))
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(render_scene, m)?)?;
    m.add_function(wrap_pyfunction!(grad_scene, m)?)?;
    Ok(())
}
