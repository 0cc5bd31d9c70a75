#![allow(
    clippy::err_expect,
    clippy::cloned_ref_to_slice_refs,
    clippy::needless_range_loop
)]
#![allow(clippy::neg_cmp_op_on_partial_ord)]
//! A user-defined op, written as a crate outside `autodiff` would write it: a fused softplus
//! with a learnable temperature, `y = tau * ln(1 + exp(x / tau))`, with two inputs, an
//! optional second output `sigmoid(x / tau)`, and a cache filled in the forward.

use autodiff::gradcheck::{compare_precision, gradcheck, GradcheckOptions, Mode};
use autodiff::ndarray::{arr1, ArrayD, IxDyn, Zip};
use autodiff::rng::Rng;
use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result, Tape, Tensor, TensorView, Var};

/// `softplus_t(x, tau)`: `x` any shape, `tau` a 0-d positive temperature.
struct SoftplusT<T: Real> {
    /// Also output `sigmoid(x / tau)` (the derivative of `y` by `x`).
    with_sigmoid: bool,
    /// `sigmoid(x / tau)`, filled in the forward and reused by the backward.
    cache: Option<Tensor<T>>,
}

fn stable_softplus<T: Real>(z: T) -> T {
    // max(z, 0) + ln(1 + exp(-|z|)): no overflow for large |z|.
    z.max(T::zero()) + (-z.abs()).exp().ln_1p()
}

fn sigmoid<T: Real>(z: T) -> T {
    if z >= T::zero() {
        T::one() / (T::one() + (-z).exp())
    } else {
        let e = z.exp();
        e / (T::one() + e)
    }
}

impl<T: Real> Op<T> for SoftplusT<T> {
    fn name(&self) -> &'static str {
        "softplus_t"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let (x, tau) = (&inputs[0], &inputs[1]);
        if tau.ndim() != 0 {
            return Err(AutodiffError::shape(
                "softplus_t",
                &[x.shape(), tau.shape()],
                "the temperature must be 0-dimensional",
            ));
        }
        let tau = tau[[]];
        if !(tau > T::zero()) {
            return Err(AutodiffError::invalid(
                "softplus_t",
                format!("temperature must be > 0, got {tau}"),
            ));
        }
        let s = x.mapv(|v| sigmoid(v / tau));
        let y = x.mapv(|v| tau * stable_softplus(v / tau));
        let mut out = vec![y];
        if self.with_sigmoid {
            out.push(s.clone());
        }
        self.cache = Some(s);
        Ok(out)
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let s = self.cache.as_ref().ok_or(AutodiffError::Op {
            op: "softplus_t",
            detail: "backward before forward".into(),
        })?;
        let (x, tau) = (&ctx.inputs[0], ctx.inputs[1][[]]);
        let (y, gy) = (ctx.outputs[0], ctx.grad_outputs[0]);
        let gs = self.with_sigmoid.then(|| ctx.grad_outputs[1]);
        let one = T::one();
        // y = tau sp(z), z = x / tau:  dy/dx = s,  dy/dtau = sp(z) - z s.
        // s = sigmoid(z):              ds/dx = s (1 - s) / tau,  ds/dtau = -s (1 - s) z / tau.
        let mut gx = ctx.needs_grad[0].then(|| ArrayD::<T>::zeros(x.raw_dim()));
        let mut gtau = T::zero();
        let need_tau = ctx.needs_grad[1];
        let mut k = 0usize;
        Zip::from(x)
            .and(y)
            .and(s)
            .and(gy)
            .for_each(|&x, &y, &s, &g| {
                let z = x / tau;
                let ds = s * (one - s);
                let g2 = gs.map_or(T::zero(), |gs| gs.as_slice().expect("standard")[k]);
                if let Some(gx) = gx.as_mut() {
                    gx.as_slice_mut().expect("fresh")[k] = g * s + g2 * ds / tau;
                }
                if need_tau {
                    gtau += g * (y / tau - z * s) - g2 * ds * z / tau;
                }
                k += 1;
            });
        Ok(vec![
            gx,
            need_tau.then(|| ArrayD::from_elem(IxDyn(&[]), gtau)),
        ])
    }
}

fn softplus_t<'t, T: Real>(x: Var<'t, T>, tau: Var<'t, T>) -> Var<'t, T> {
    x.tape().apply(
        SoftplusT {
            with_sigmoid: false,
            cache: None,
        },
        &[x, tau],
    )
}

fn softplus_t2<'t, T: Real>(x: Var<'t, T>, tau: Var<'t, T>) -> (Var<'t, T>, Var<'t, T>) {
    let o = x.tape().apply_multi(
        SoftplusT {
            with_sigmoid: true,
            cache: None,
        },
        &[x, tau],
        2,
    );
    (o[0], o[1])
}

/// The same function from built-in ops.
fn softplus_composed<'t, T: Real>(x: Var<'t, T>, tau: Var<'t, T>) -> Var<'t, T> {
    ((x / tau).exp() + T::one()).ln() * tau
}

fn inputs(seed: u64) -> Vec<Tensor<f64>> {
    let mut r = Rng::new(seed);
    vec![
        r.uniform_tensor(&[2, 3], -2.0, 2.0),
        ArrayD::from_elem(IxDyn(&[]), r.uniform(0.5, 1.5)),
    ]
}

fn modes() -> [GradcheckOptions; 2] {
    [
        GradcheckOptions::default(),
        GradcheckOptions {
            mode: Mode::Fast { seed: 9 },
            ..Default::default()
        },
    ]
}

#[test]
fn single_output_passes_gradcheck_in_full_and_fast_mode() {
    for opts in modes() {
        let rep = gradcheck(|_, v| softplus_t(v[0], v[1]), &inputs(1), &opts).unwrap();
        assert!(rep.passed(), "{:?}\n{rep}", opts.mode);
        assert_eq!(rep.inputs.len(), 2);
        assert_eq!(rep.output_shape, vec![2, 3]);
    }
}

#[test]
fn multi_output_variant_passes_gradcheck_through_each_output() {
    for opts in modes() {
        // Both outputs, only the second (the first gets a zero gradient), only the first.
        let both = gradcheck(
            |_, v| {
                let (y, s) = softplus_t2(v[0], v[1]);
                y * 0.5 + s.square()
            },
            &inputs(2),
            &opts,
        )
        .unwrap();
        assert!(both.passed(), "{both}");
        let second = gradcheck(|_, v| softplus_t2(v[0], v[1]).1, &inputs(3), &opts).unwrap();
        assert!(second.passed(), "{second}");
        let first = gradcheck(|_, v| softplus_t2(v[0], v[1]).0.sum(), &inputs(4), &opts).unwrap();
        assert!(first.passed(), "{first}");
    }
}

#[test]
fn matches_the_composed_builtin_version() {
    let xs = inputs(5);
    let tape = Tape::<f64>::new();
    let (x, tau) = (tape.leaf(xs[0].clone()), tape.leaf(xs[1].clone()));
    let w = tape.constant(Rng::new(6).normal_tensor(&[2, 3]));
    let fused = softplus_t(x, tau);
    let composed = softplus_composed(x, tau);
    let (gf, gc) = (
        tape.backward((fused * w).sum()).unwrap(),
        tape.backward((composed * w).sum()).unwrap(),
    );
    for (a, b) in fused
        .value()
        .unwrap()
        .iter()
        .zip(composed.value().unwrap().iter())
    {
        assert!((a - b).abs() < 1e-13, "{a} vs {b}");
    }
    for v in [x, tau] {
        for (a, b) in gf.get(v).unwrap().iter().zip(gc.get(v).unwrap().iter()) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
    }
    // Where the composed version overflows, the fused one stays finite.
    let big = tape.leaf(arr1(&[800.0, -800.0]).into_dyn());
    let one = tape.scalar(1.0);
    assert!(softplus_composed(big, one).value().unwrap()[0].is_infinite());
    let y = softplus_t(big, one).value().unwrap();
    assert_eq!(y[0], 800.0);
    assert!(y[1] >= 0.0 && y[1] < 1e-300);
}

#[test]
fn inside_a_larger_graph() {
    // A two-layer network with the fused activation: x [4, 3], W1 [3, 5], b1 [5], tau, w2 [5].
    let mut r = Rng::new(7);
    let xs = vec![
        r.uniform_tensor::<f64>(&[4, 3], -1.0, 1.0),
        r.uniform_tensor::<f64>(&[3, 5], -1.0, 1.0),
        r.uniform_tensor::<f64>(&[5], -0.5, 0.5),
        ArrayD::from_elem(IxDyn(&[]), 0.7),
        r.uniform_tensor::<f64>(&[5], -1.0, 1.0),
    ];
    fn net<'t, T: Real>(_: &'t Tape<T>, v: &[Var<'t, T>]) -> Var<'t, T> {
        let h = softplus_t(v[0].matmul(v[1]) + v[2], v[3]);
        let (_, gate) = softplus_t2(h, v[3]);
        (h * gate).matmul(v[4]).logsumexp(0, false)
    }
    for opts in modes() {
        let rep = gradcheck(net, &xs, &opts).unwrap();
        assert!(rep.passed(), "{:?}\n{rep}", opts.mode);
        assert_eq!(rep.inputs.len(), 5);
    }
    let prec = compare_precision(net::<f32>, net::<f64>, &xs, 1).unwrap();
    assert!(prec.max_rel() < 1e-5, "{prec:?}");
    // The temperature is learnable: a few SGD steps on it lower a loss.
    let mut tau = ArrayD::from_elem(IxDyn(&[]), 2.0f64);
    let loss_at = |tau: &Tensor<f64>| {
        let t = Tape::<f64>::new();
        let tv = t.leaf(tau.clone());
        let v: Vec<_> = xs.iter().map(|x| t.constant(x.clone())).collect();
        let l = (softplus_t(v[0].matmul(v[1]) + v[2], tv) - 0.3)
            .square()
            .sum();
        (l.item().unwrap(), t.backward(l).unwrap().wrt(tv))
    };
    let (l0, _) = loss_at(&tau);
    let mut opt = autodiff::optim::Sgd::new(0.05, 0.0);
    for _ in 0..20 {
        let (_, g) = loss_at(&tau);
        opt.step([(&mut tau, &g)]).unwrap();
    }
    assert!(loss_at(&tau).0 < l0);
}

#[test]
fn argument_errors_name_the_custom_op() {
    let tape = Tape::<f64>::new();
    let x = tape.leaf(ArrayD::zeros(IxDyn(&[2, 3])));
    let tau = tape.leaf(ArrayD::from_elem(IxDyn(&[1]), 1.0));
    let e = softplus_t(x, tau).value().unwrap_err();
    let m = e.to_string();
    assert!(
        m.contains("softplus_t") && m.contains("[2, 3]") && m.contains("[1]"),
        "{m}"
    );
    let tape = Tape::<f64>::new();
    let x = tape.leaf(ArrayD::zeros(IxDyn(&[2])));
    let e = softplus_t(x, tape.scalar(-1.0)).value().unwrap_err();
    assert!(
        e.to_string().contains("softplus_t") && e.to_string().contains("-1"),
        "{e}"
    );
    // The sticky error flows through the multi-output variant too.
    let (a, b) = softplus_t2(x, tape.scalar(-1.0));
    assert!(a.value().is_err() && b.value().is_err());
}
