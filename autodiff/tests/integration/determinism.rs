#![allow(
    clippy::err_expect,
    clippy::cloned_ref_to_slice_refs,
    clippy::needless_range_loop
)]
//! A large graph (>= 100k elements, parallel kernels) gives bit-identical values and gradients
//! in rayon pools of 1, 2 and 8 threads.

use autodiff::rng::Rng;
use autodiff::tensor::PAR_MIN_LEN;
use autodiff::{Tape, Tensor};

struct Data {
    x: Tensor<f32>,
    basis: Tensor<f32>,
    coef: Tensor<f32>,
    mean: Tensor<f32>,
    w: Tensor<f32>,
}

fn data() -> Data {
    let mut r = Rng::new(2024);
    Data {
        x: r.uniform_tensor(&[400, 500], -1.0, 1.0),
        basis: r.normal_tensor(&[6000, 40]),
        coef: r.normal_tensor(&[40]),
        mean: r.normal_tensor(&[6000]),
        w: r.normal_tensor(&[6000]),
    }
}

/// Loss value and the bit patterns of every gradient.
fn run(d: &Data) -> (u32, Vec<Vec<u32>>) {
    let tape = Tape::<f32>::new();
    let x = tape.leaf(d.x.clone());
    let basis = tape.leaf(d.basis.clone());
    let coef = tape.leaf(d.coef.clone());
    let mean = tape.constant(d.mean.clone());
    let w = tape.leaf(d.w.clone());
    // Elementwise chains and full sums over 200k elements.
    let a = (x.sin() * x + 0.25).square().sum();
    // Sums over axes of a large tensor, a mean, a logsumexp.
    let b = x.exp().sum_axes(&[0], false).logsumexp(0, false);
    let c = x.tanh().mean_axes(&[1], true).square().sum();
    // A 3DMM-like mat-vec (240k-element basis, both gradients) and a vec-mat product.
    let y = basis.matmul(coef) + mean;
    let e = (y.square() * 1e-3).sum() + w.matmul(basis).square().sum() * 1e-4;
    let loss = a + b * 0.5 + c + e;
    let g = tape.backward(loss).unwrap();
    let bits = |t: &Tensor<f32>| t.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    (
        loss.item().unwrap().to_bits(),
        [x, basis, coef, w]
            .iter()
            .map(|&v| bits(g.get(v).unwrap()))
            .collect(),
    )
}

#[test]
fn values_and_gradients_are_bit_identical_across_thread_counts() {
    let d = data();
    assert!(d.x.len() >= 100_000 && d.x.len() >= 4 * PAR_MIN_LEN);
    let results: Vec<_> = [1, 2, 8]
        .iter()
        .map(|&n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
                .install(|| run(&d))
        })
        .collect();
    assert!(f32::from_bits(results[0].0).is_finite());
    for (k, r) in results.iter().enumerate().skip(1) {
        assert_eq!(r.0, results[0].0, "loss differs with pool {k}");
        for (i, (a, b)) in r.1.iter().zip(&results[0].1).enumerate() {
            let diff = a.iter().zip(b).filter(|(x, y)| x != y).count();
            assert_eq!(
                diff, 0,
                "gradient {i}: {diff} elements differ with pool {k}"
            );
        }
    }
    // And the same pool gives the same result twice.
    assert_eq!(run(&d).0, results[0].0);
}
