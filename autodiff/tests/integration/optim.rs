#![allow(
    clippy::err_expect,
    clippy::cloned_ref_to_slice_refs,
    clippy::needless_range_loop
)]
//! Adam and SGD with momentum recover the solution of a small least-squares problem, with a
//! fresh tape every step (define-by-run).

use autodiff::ndarray::{Array2, ArrayD, IxDyn};
use autodiff::optim::{Adam, Sgd};
use autodiff::rng::Rng;
use autodiff::{Tape, Tensor};

/// A well-conditioned `A` [8, 5], the true `x` [5] and `b = A x`.
fn problem() -> (Tensor<f64>, Tensor<f64>, Tensor<f64>) {
    let mut r = Rng::new(42);
    let mut a = Array2::<f64>::from_shape_fn((8, 5), |_| 0.3 * r.normal());
    for i in 0..5 {
        a[[i, i]] += 1.5;
    }
    let x = r.uniform_tensor::<f64>(&[5], -2.0, 2.0);
    let b = a.dot(
        &x.view()
            .into_dimensionality::<autodiff::ndarray::Ix1>()
            .unwrap(),
    );
    (a.into_dyn(), x, b.into_dyn())
}

/// Loss `sum((A x - b)^2)` and its gradient on a fresh tape.
fn loss_and_grad(a: &Tensor<f64>, b: &Tensor<f64>, x: &Tensor<f64>) -> (f64, Tensor<f64>) {
    let tape = Tape::<f64>::new();
    let xv = tape.leaf(x.clone());
    let loss = (tape.constant(a.clone()).matmul(xv) - tape.constant(b.clone()))
        .square()
        .sum();
    let l = loss.item().unwrap();
    let mut g = tape.backward(loss).unwrap();
    (l, g.take(xv).unwrap())
}

fn max_err(x: &Tensor<f64>, want: &Tensor<f64>) -> f64 {
    x.iter()
        .zip(want.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
}

#[test]
fn adam_recovers_x_from_a_x_eq_b() {
    let (a, want, b) = problem();
    let mut x: Tensor<f64> = ArrayD::zeros(IxDyn(&[5]));
    let mut opt = Adam::new(0.05);
    let (l0, _) = loss_and_grad(&a, &b, &x);
    let mut steps = 0;
    while max_err(&x, &want) > 1e-6 && steps < 5000 {
        let (_, g) = loss_and_grad(&a, &b, &x);
        opt.step([(&mut x, &g)]).unwrap();
        steps += 1;
    }
    let (l, _) = loss_and_grad(&a, &b, &x);
    assert!(
        max_err(&x, &want) <= 1e-6,
        "after {steps} steps: {x} vs {want}"
    );
    assert!(l < 1e-10 * l0, "{l} vs {l0}");
    assert_eq!(opt.steps(), steps);
    println!("adam: {steps} steps");
}

#[test]
fn sgd_with_momentum_recovers_x_from_a_x_eq_b() {
    let (a, want, b) = problem();
    let mut x: Tensor<f64> = ArrayD::zeros(IxDyn(&[5]));
    let mut opt = Sgd::new(0.05, 0.9);
    let mut steps = 0;
    while max_err(&x, &want) > 1e-6 && steps < 5000 {
        let (_, g) = loss_and_grad(&a, &b, &x);
        opt.step([(&mut x, &g)]).unwrap();
        steps += 1;
    }
    assert!(
        max_err(&x, &want) <= 1e-6,
        "after {steps} steps: {x} vs {want}"
    );
    println!("sgd+momentum: {steps} steps");
    // The heavy-ball rule itself: with a constant gradient the second step is (1 + mu) times
    // the first.
    let mut p = ArrayD::from_elem(IxDyn(&[2]), 1.0f64);
    let g = ArrayD::from_elem(IxDyn(&[2]), 2.0f64);
    let mut opt = Sgd::new(0.1, 0.9);
    opt.step([(&mut p, &g)]).unwrap();
    assert!(p.iter().all(|&v| (v - 0.8).abs() < 1e-15));
    opt.step([(&mut p, &g)]).unwrap();
    assert!(p
        .iter()
        .all(|&v| (v - (0.8 - 0.1 * 1.9 * 2.0)).abs() < 1e-15));
}

#[test]
fn optimisers_in_f32_converge_to_f32_precision() {
    let (a, want, b) = problem();
    let cast = |t: &Tensor<f64>| t.mapv(|v| v as f32);
    let (a, b) = (cast(&a), cast(&b));
    let mut x: Tensor<f32> = ArrayD::zeros(IxDyn(&[5]));
    let mut opt = Adam::new(0.02f32);
    for _ in 0..3000 {
        let tape = Tape::<f32>::new();
        let xv = tape.leaf(x.clone());
        let loss = (tape.constant(a.clone()).matmul(xv) - tape.constant(b.clone()))
            .square()
            .sum();
        let g = tape.backward(loss).unwrap().wrt(xv);
        opt.step([(&mut x, &g)]).unwrap();
    }
    let err = x
        .iter()
        .zip(want.iter())
        .map(|(&a, &b)| (a as f64 - b).abs())
        .fold(0.0, f64::max);
    assert!(err < 1e-4, "{err}");
}
