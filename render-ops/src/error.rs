//! The crate's umbrella error: every failure of a rendering call, typed by where it arose.

use autodiff::Real;
use ndarray::Dimension;
use thiserror::Error;

/// Any error of a rendering op or pipeline.
#[derive(Debug, Error)]
pub enum RenderError {
    /// Tape errors (shapes, anomalies).
    #[error(transparent)]
    Autodiff(#[from] autodiff::AutodiffError),
    /// Rasterizer input errors.
    #[error(transparent)]
    Raster(#[from] crate::raster::RasterError),
    /// Invalid meshes.
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
    /// OBJ files.
    #[error(transparent)]
    Obj(#[from] crate::obj::ObjError),
    /// Scene JSON.
    #[error(transparent)]
    Scene(#[from] crate::scene::SceneError),
    /// Camera parameters.
    #[error(transparent)]
    Camera(#[from] crate::camera::CameraError),
    /// PNG and .npy files.
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    /// A NaN or infinite value in a differentiable input of a render, found before rendering:
    /// `input` names it (`positions`, `colors`, `texture`, `camera` for a scene's inputs,
    /// `attributes` for the per-vertex attributes of an op), `index` is the element's
    /// multi-index in it. (Clip positions of the raster ops give
    /// [`crate::raster::RasterError::NonFiniteVertex`].)
    #[error("{input}{index:?} = {value} is not finite")]
    NonFiniteInput {
        /// Which input.
        input: &'static str,
        /// The element's multi-index, e.g. `[vertex, channel]`.
        index: Vec<usize>,
        /// Its value.
        value: f64,
    },
    /// A request this build does not support (e.g. a shading model with a raster method that
    /// cannot carry it); the message says what is supported.
    #[error("unsupported: {0}")]
    Unsupported(String),
    /// An input that does not fit the scene (a target of another size, an input the scene
    /// lacks), with its message.
    #[error("{0}")]
    InvalidInput(String),
}

impl RenderError {
    /// `Ok` when every value of `t` is finite, else [`RenderError::NonFiniteInput`] naming
    /// `input` and the first bad element.
    pub fn check_finite<T: Real, S: ndarray::Data<Elem = T>>(
        input: &'static str,
        t: &ndarray::ArrayBase<S, ndarray::IxDyn>,
    ) -> Result<(), RenderError> {
        match t.indexed_iter().find(|(_, x)| !x.is_finite()) {
            None => Ok(()),
            Some((i, x)) => Err(RenderError::NonFiniteInput {
                input,
                index: i.slice().to_vec(),
                value: x.to_f64c(),
            }),
        }
    }
}
