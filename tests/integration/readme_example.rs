//! The custom-op example of the README, compiled and checked: a user op with a hand-written
//! backward, run through the finite-difference gradient checker.

use tapestry::autodiff::gradcheck::{gradcheck, GradcheckOptions};
use tapestry::autodiff::{BackwardCtx, Op, Real, Result, Tape, Tensor, TensorView, Var};

/// `y = softplus(x) = ln(1 + e^x)`, computed stably, with its own backward `g * sigmoid(x)`.
struct Softplus;

impl<T: Real> Op<T> for Softplus {
    fn name(&self) -> &'static str {
        "softplus"
    }
    fn forward(&mut self, x: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        Ok(vec![
            x[0].mapv(|v| v.max(T::zero()) + (-v.abs()).exp().ln_1p())
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let g = ctx.grad_outputs[0] * &ctx.inputs[0].mapv(|v| T::one() / (T::one() + (-v).exp()));
        Ok(vec![ctx.needs_grad[0].then_some(g)])
    }
}

fn softplus<'t, T: Real>(x: Var<'t, T>) -> Var<'t, T> {
    x.tape().apply(Softplus, &[x])
}

#[test]
fn readme_custom_op_passes_gradcheck() {
    let x = Tensor::from_shape_vec(vec![4], vec![-3.0, -0.5, 0.2, 4.0]).unwrap();
    let report = gradcheck(
        |_t: &Tape<f64>, v| (softplus(v[0]) * v[0]).sum(),
        &[x],
        &GradcheckOptions::default(),
    )
    .unwrap();
    assert!(report.passed(), "{report}");
}

/// The README's "pipeline in ten lines", line for line: a sphere rasterized, interpolated and
/// blended, and the gradient of an image loss with respect to its vertex positions.
#[test]
fn readme_pipeline_runs() -> std::result::Result<(), Box<dyn std::error::Error>> {
    use std::sync::Arc;
    use tapestry::render_ops::{
        blend::blend_hard, camera::Camera, interpolate::interpolate, mesh::Mesh,
    };
    use tapestry::render_ops::{raster::RasterSettings, rasterize::rasterize, transform::to_clip};

    let mesh = Mesh::<f64>::icosphere(3, 1.0); // 1280 faces
    let cam = Camera::perspective_look_at(
        [0.0, 0.0, 3.0],
        [0.0; 3],
        [0.0, 1.0, 0.0],
        0.8,
        1.0,
        0.1,
        100.0,
    )?;
    let tape = Tape::new();
    let pos = tape.leaf(Tensor::from_shape_vec(
        vec![mesh.positions.len(), 3],
        mesh.positions.concat(),
    )?);
    let col = tape.constant(pos.value()?.mapv(|x| 0.5 + 0.5 * x)); // colour from position
    let frags = rasterize(
        to_clip(pos, &cam.view_proj()),
        Arc::new(mesh.faces.clone()),
        &RasterSettings::new(64, 64),
    )?;
    let image = blend_hard(interpolate(col, &frags)?, &frags.fragments, &[0.0; 3])?; // [64, 64, 4] RGBA
    let target = tape.constant(Tensor::zeros(vec![64, 64, 4])); // your [H, W, 4] target
    let grads = tape.backward(image.sum_squared_diff(target))?; // sum((image - target)^2)
    let d_pos = grads.wrt(pos); // [V, 3]

    assert_eq!(image.shape(), vec![64, 64, 4]);
    assert_eq!(d_pos.shape(), &[mesh.positions.len(), 3]);
    // The sphere covers the image centre, and the loss pulls its visible colours to zero.
    let img = image.value()?;
    assert_eq!(img[[32, 32, 3]], 1.0);
    assert!(d_pos.iter().all(|g| g.is_finite()));
    assert!(d_pos.iter().any(|&g| g != 0.0));
    Ok(())
}
