//! `tapestry grad`: L = sum over pixels and channels of (render - target)^2 and its gradient
//! with respect to the vertex positions `[V, 3]`, vertex colours `[V, 3]`, texture texels
//! `[H, W, C]`, camera (eye and look-at point, `[2, 3]`) or light parameters (`[n, 3]`),
//! computed by [`Scene::image_loss_grad`].

use std::path::Path;
use std::process::ExitCode;

use render_ops::io::{read_image, write_npy};
use render_ops::scene::Scene;

use super::{CliError, WrtArg};

/// Computes the loss against `target`, prints it, and writes the gradient in the input's shape.
pub fn run(scene: &Path, target: &Path, wrt: WrtArg, out: &Path) -> Result<ExitCode, CliError> {
    let scene = Scene::<f64>::load(scene)?;
    let target_img = read_image::<f64>(target)?;
    let (loss, g) = scene.image_loss_grad(
        target_img.into_dyn(),
        &target.display().to_string(),
        wrt.into(),
    )?;
    println!("loss {loss:.17e}");
    write_npy(out, &g)?;
    Ok(ExitCode::SUCCESS)
}
