//! `tapestry grad`: L = sum over pixels and channels of (render - target)^2 and its gradient
//! with respect to the vertex positions `[V, 3]`, vertex colours `[V, 3]`, texture texels
//! `[H, W, C]`, camera (eye and look-at point, `[2, 3]`) or light parameters (`[n, 3]`),
//! computed by [`Scene::image_loss_grad`].

use std::path::Path;
use std::process::ExitCode;

use render_ops::io::{read_image, write_npy};
use render_ops::scene::Scene;

use super::{timing, CliError, WrtArg};

/// Computes the loss against `target`, prints it, and writes the gradient in the input's shape
/// (`repeat`: [`timing::repeated`]).
pub fn run(
    scene: &Path,
    target: &Path,
    wrt: WrtArg,
    out: &Path,
    repeat: usize,
) -> Result<ExitCode, CliError> {
    let scene = Scene::<f64>::load(scene)?;
    let target_img = read_image::<f64>(target)?;
    let target_img = target_img.into_dyn();
    let (loss, g) = timing::repeated(repeat, || {
        Ok(scene.image_loss_grad(
            target_img.clone(),
            &target.display().to_string(),
            wrt.into(),
        )?)
    })?;
    println!("loss {loss:.17e}");
    write_npy(out, &g)?;
    Ok(ExitCode::SUCCESS)
}
