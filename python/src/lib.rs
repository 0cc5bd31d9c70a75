//! Python bindings of Tapestry (`import tapestry`): the scene commands (`render_scene`,
//! `grad_scene`), the functional ops over numpy arrays with their vector-Jacobian products
//! ([`ops`]), `fit_face` and `gradcheck` ([`tools`]).
//!
//! Arrays: float inputs are `float32` or `float64` numpy arrays of any layout (strided and
//! non-contiguous ones included); C-contiguous aligned ones are read in place by the tape
//! (borrowed leaves, [`autodiff::Tape::var_borrowed`]), others are copied once. Outputs are
//! moved into numpy without a copy. The GIL is released while Rust works (`Python::detach`). Rust errors become
//! `tapestry.TapestryError` (a `ValueError`) with the same one-line message as the command
//! line; wrong shapes raise `ValueError`, wrong dtypes `TypeError`.

mod array;
mod ops;
mod scene;
mod tools;

use pyo3::prelude::*;

pyo3::create_exception!(
    _tapestry,
    TapestryError,
    pyo3::exceptions::PyValueError,
    "An error of the Tapestry library, with its one-line message (a ValueError)."
);

/// A Rust error as a Python exception with the same one-line message.
pub(crate) fn to_py(e: impl std::fmt::Display) -> PyErr {
    TapestryError::new_err(e.to_string())
}

#[pymodule]
fn _tapestry(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("TapestryError", m.py().get_type::<TapestryError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    scene::register(m)?;
    ops::register(m)?;
    tools::register(m)?;
    m.add_function(wrap_pyfunction!(array::_reads_in_place, m)?)?;
    Ok(())
}
