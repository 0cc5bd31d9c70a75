//! `tapestry render`.

use std::path::Path;
use std::process::ExitCode;

use ndarray::{s, Ix3};
use render_ops::io::{write_npy, write_png};
use render_ops::scene::Scene;

use super::{timing, CliError};

/// Renders `scene` (f64 precision, no gradients: [`Scene::render_image`]) and writes the PNG
/// and optional .npy (`repeat`: [`timing::repeated`]).
pub fn run(
    scene: &Path,
    out: &Path,
    npy: Option<&Path>,
    repeat: usize,
) -> Result<ExitCode, CliError> {
    let scene = Scene::<f64>::load(scene)?;
    let img = timing::repeated(repeat, || Ok(scene.render_image()?))?;
    let img = img
        .view()
        .into_dimensionality::<Ix3>()
        .map_err(|e| CliError::Message(e.to_string()))?;
    write_png(out, &img.slice(s![.., .., 0..3]))?;
    if let Some(npy) = npy {
        write_npy(npy, &img)?;
    }
    Ok(ExitCode::SUCCESS)
}
