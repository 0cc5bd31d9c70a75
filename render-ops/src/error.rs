//! The crate's umbrella error: every failure of a rendering call, typed by where it arose.

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
    /// A request this build does not support (e.g. a shading model with a raster method that
    /// cannot carry it); the message says what is supported.
    #[error("unsupported: {0}")]
    Unsupported(String),
}
