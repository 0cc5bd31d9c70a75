use autodiff::gradcheck::{gradcheck, GradcheckOptions};
use autodiff::rng::Rng;
use autodiff::Tape;

#[test]
fn smoke_gradcheck_chain() {
    let mut r = Rng::new(1);
    let a = r.uniform_tensor::<f64>(&[3, 4], 0.5, 1.5);
    let b = r.uniform_tensor::<f64>(&[4], 0.5, 1.5);
    let rep = gradcheck(
        |_t: &Tape<f64>, x| ((x[0] * x[1] + 1.0).ln().sigmoid() / x[1]).matmul(x[1]).sum(),
        &[a, b],
        &GradcheckOptions::default(),
    )
    .unwrap();
    assert!(rep.passed(), "{rep}");
}
