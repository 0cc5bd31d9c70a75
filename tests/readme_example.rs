//! The custom-op example of the README, compiled and checked: a user op with a hand-written
//! backward, run through the finite-difference gradient checker.

use tapestry::autodiff::gradcheck::{gradcheck, GradcheckOptions};
use tapestry::autodiff::{BackwardCtx, Op, Real, Result, Tape, Tensor, Var};

/// `y = softplus(x) = ln(1 + e^x)`, computed stably, with its own backward `g * sigmoid(x)`.
struct Softplus;

impl<T: Real> Op<T> for Softplus {
    fn name(&self) -> &'static str {
        "softplus"
    }
    fn forward(&mut self, x: &[&Tensor<T>]) -> Result<Vec<Tensor<T>>> {
        Ok(vec![
            x[0].mapv(|v| v.max(T::zero()) + (-v.abs()).exp().ln_1p())
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> Result<Vec<Option<Tensor<T>>>> {
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
