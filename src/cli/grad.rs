//! `tapestry grad`: L = sum over pixels and channels of (render - target)^2 and its gradient
//! with respect to the vertex positions `[V, 3]`, vertex colours `[V, 3]`, texture texels
//! `[H, W, C]`, camera (eye and look-at point, `[2, 3]`) or light parameters (`[n, 3]`).

use std::path::Path;
use std::process::ExitCode;

use autodiff::Tape;
use render_ops::io::{read_image, write_npy};
use render_ops::pipeline::Wrt;
use render_ops::scene::Scene;

use super::{CliError, WrtArg};

/// Computes the loss against `target`, prints it, and writes the gradient in the input's shape.
pub fn run(scene: &Path, target: &Path, wrt: WrtArg, out: &Path) -> Result<ExitCode, CliError> {
    let scene = Scene::<f64>::load(scene)?;
    let target_img = read_image::<f64>(target)?;
    let (w, h) = (
        scene.desc.image.width as usize,
        scene.desc.image.height as usize,
    );
    let ts = target_img.shape().to_vec();
    if ts[0] != h || ts[1] != w || !(ts[2] == 3 || ts[2] == 4) {
        return Err(CliError::Message(format!(
            "target {}: shape {:?} does not match the scene's image [{h}, {w}, 3 or 4]",
            target.display(),
            ts
        )));
    }
    let tape = Tape::new();
    let vars = scene.vars(
        &tape,
        Wrt {
            positions: wrt == WrtArg::Positions,
            colors: wrt == WrtArg::Colors,
            texture: wrt == WrtArg::Texture,
            camera: wrt == WrtArg::Camera,
            lights: wrt == WrtArg::Lights,
        },
    );
    let texture = match (wrt, vars.texture) {
        (WrtArg::Texture, None) => {
            return Err(CliError::Message(format!(
                "--wrt texture: the scene {} has no texture",
                scene.source
            )))
        }
        (_, t) => t,
    };
    let img = scene.render(&vars)?;
    let img = if ts[2] == 3 { img.slice(2, 0, 3) } else { img };
    let loss = img.sum_squared_diff(tape.constant(target_img.into_dyn()));
    let grads = tape.backward(loss)?;
    println!("loss {:.17e}", loss.item()?);
    let g = match wrt {
        WrtArg::Positions => grads.wrt(vars.positions),
        WrtArg::Colors => grads.wrt(vars.colors),
        WrtArg::Texture => grads.wrt(texture.expect("checked above")),
        WrtArg::Camera => grads.wrt(vars.camera),
        WrtArg::Lights => match vars.lights {
            Some(l) if !l.is_empty() => grads.wrt(l),
            _ => {
                return Err(CliError::Message(format!(
                    "--wrt lights: the scene {} has no lights",
                    scene.source
                )))
            }
        },
    };
    write_npy(out, &g)?;
    Ok(ExitCode::SUCCESS)
}
