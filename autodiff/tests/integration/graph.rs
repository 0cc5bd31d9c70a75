#![allow(
    clippy::err_expect,
    clippy::cloned_ref_to_slice_refs,
    clippy::needless_range_loop
)]
//! Graph semantics of the tape: accumulation, diamonds, no_grad, detach, vjp, multi-output
//! ops, skipped work for leaves without gradients, gradcheck modes, anomaly detection and NaN
//! propagation.

use std::cell::RefCell;
use std::rc::Rc;

use autodiff::gradcheck::{gradcheck, GradcheckOptions, Mode};
use autodiff::ndarray::{arr1, arr2, ArrayD, IxDyn};
use autodiff::rng::Rng;
use autodiff::tensor::{from_vec, sum_to_shape};
use autodiff::{AutodiffError, BackwardCtx, Op, Pass, Real, Result, Tape, Tensor, TensorView, Var};

fn t1(v: &[f64]) -> Tensor<f64> {
    arr1(v).into_dyn()
}

fn close(a: &Tensor<f64>, b: &Tensor<f64>, tol: f64) {
    assert_eq!(a.shape(), b.shape());
    for (x, y) in a.iter().zip(b.iter()) {
        assert!((x - y).abs() <= tol * (1.0 + y.abs()), "{a} vs {b}");
    }
}

#[test]
fn gradient_accumulates_over_three_uses() {
    let tape = Tape::<f64>::new();
    let xv = t1(&[0.3, -1.2, 2.0]);
    let x = tape.leaf(xv.clone());
    // x feeds exp, a scalar multiply and sin: three uses, three contributions.
    let loss = (x.exp() + x * 2.5 + x.sin()).sum();
    let g = tape.backward(loss).unwrap();
    let want = xv.mapv(|v| v.exp() + 2.5 + v.cos());
    close(g.get(x).unwrap(), &want, 1e-14);

    // The same variable three times in one expression.
    let tape = Tape::<f64>::new();
    let x = tape.leaf(xv.clone());
    let g = tape.backward((x * x * x).sum()).unwrap();
    close(g.get(x).unwrap(), &xv.mapv(|v| 3.0 * v * v), 1e-14);
}

#[test]
fn diamond_graph() {
    let tape = Tape::<f64>::new();
    let av = t1(&[0.1, 0.7, -0.4]);
    let a = tape.leaf(av.clone());
    let (b, c) = (a.exp(), a.sin());
    let d = (b * c).sum();
    let g = tape.backward(d).unwrap();
    close(
        g.get(a).unwrap(),
        &av.mapv(|v| v.exp() * (v.sin() + v.cos())),
        1e-14,
    );
    // A deeper diamond: two paths of different length meeting again.
    let tape = Tape::<f64>::new();
    let a = tape.leaf(av.clone());
    let top = a.square();
    let left = top.tanh() * 3.0;
    let right = top * top;
    let g = tape.backward((left + right).sum()).unwrap();
    let want = av.mapv(|v| {
        let s = v * v;
        (3.0 * (1.0 - s.tanh().powi(2)) + 2.0 * s) * 2.0 * v
    });
    close(g.get(a).unwrap(), &want, 1e-13);
}

#[test]
fn no_grad_regions_record_nothing_and_outside_still_works() {
    let tape = Tape::<f64>::new();
    let xv = t1(&[1.0, 2.0, 3.0]);
    let x = tape.leaf(xv.clone());
    let ops_before = tape.num_ops();
    let y = tape.no_grad(|| {
        assert!(tape.is_no_grad());
        let inner = tape.no_grad(|| x * 3.0);
        assert!(tape.is_no_grad(), "nested no_grad keeps the outer region");
        x * 2.0 + 1.0 + inner
    });
    assert!(!tape.is_no_grad());
    assert_eq!(
        tape.num_ops(),
        ops_before,
        "ops inside no_grad are not recorded"
    );
    assert!(!y.requires_grad());
    // Only the direct path counts: d/dx sum(y * x) = y with y constant.
    let g = tape.backward((y * x).sum()).unwrap();
    close(g.get(x).unwrap(), &xv.mapv(|v| 5.0 * v + 1.0), 1e-14);
    // After the region, recording works again.
    let g = tape.backward((x * x).sum()).unwrap();
    close(g.get(x).unwrap(), &xv.mapv(|v| 2.0 * v), 1e-14);
    // A panic inside no_grad does not leave the tape in no-grad mode.
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        tape.no_grad(|| panic!("boom"));
    }));
    assert!(r.is_err());
    assert!(!tape.is_no_grad());
    // A gradient of a no-grad result with respect to x does not exist.
    let g = tape.backward(y.sum()).unwrap();
    assert!(g.get(x).is_none());
}

#[test]
fn detach_stops_the_gradient() {
    let tape = Tape::<f64>::new();
    let xv = t1(&[0.5, -2.0]);
    let x = tape.leaf(xv.clone());
    let d = x.detach();
    assert!(!d.requires_grad());
    assert_eq!(*d.value().unwrap(), xv);
    let g = tape.backward((d * x).sum()).unwrap();
    close(g.get(x).unwrap(), &xv, 0.0);
    let g = tape.backward((x.exp().detach() * 3.0).sum()).unwrap();
    assert!(g.get(x).is_none());
}

#[test]
fn backward_from_a_non_scalar_is_an_error() {
    let tape = Tape::<f64>::new();
    let x = tape.leaf(t1(&[1.0, 2.0, 3.0]));
    let e = tape.backward(x * 2.0).err().expect("an error");
    assert!(
        matches!(e, AutodiffError::Shape { op: "backward", .. }),
        "{e:?}"
    );
    let m = e.to_string();
    assert!(
        m.contains("backward") && m.contains("[3]") && m.contains("vjp"),
        "{m}"
    );
    // One-element losses of any rank are fine.
    assert!(tape.backward(x.sum().reshape(&[1, 1])).is_ok());
    assert!(tape.backward(x.slice(0, 1, 2)).is_ok());
}

#[test]
fn vjp_with_a_given_output_gradient() {
    let tape = Tape::<f64>::new();
    let xv = arr2(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]).into_dyn();
    let wv = arr1(&[0.5, -1.0, 2.0]).into_dyn();
    let x = tape.leaf(xv.clone());
    let w = tape.constant(wv.clone());
    let y = (x * w).sin();
    let v = arr2(&[[1.0, 0.0, -2.0], [0.25, 3.0, 1.0]]).into_dyn();
    let g = tape.vjp(y, v.clone()).unwrap();
    let want = &v * &wv * &(&xv * &wv).mapv(f64::cos);
    close(g.get(x).unwrap(), &want, 1e-14);
    assert!(g.get(w).is_none());
    // The output gradient must have the output's shape.
    let e = tape.vjp(y, t1(&[1.0, 2.0])).err().expect("an error");
    assert!(
        e.to_string().contains("vjp") && e.to_string().contains("[2, 3]"),
        "{e}"
    );
    // vjp of a leaf is the given gradient.
    let g = tape.vjp(x, v.clone()).unwrap();
    assert_eq!(g.get(x).unwrap(), &v);
}

/// sin and cos of the input as two outputs; records the output gradients it is given.
struct SinCos {
    seen: Rc<RefCell<Vec<Vec<Tensor<f64>>>>>,
}

impl Op<f64> for SinCos {
    fn name(&self) -> &'static str {
        "sincos"
    }
    fn forward(&mut self, x: &[TensorView<'_, f64>]) -> Result<Vec<Tensor<f64>>> {
        Ok(vec![x[0].mapv(f64::sin), x[0].mapv(f64::cos)])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, f64>) -> Result<Vec<Option<Tensor<f64>>>> {
        self.seen
            .borrow_mut()
            .push(ctx.grad_outputs.iter().map(|g| (*g).clone()).collect());
        let x = &ctx.inputs[0];
        let g = ctx.grad_outputs[0] * &x.mapv(f64::cos) - ctx.grad_outputs[1] * &x.mapv(f64::sin);
        Ok(vec![Some(g)])
    }
}

#[test]
fn multi_output_op_unused_output_gets_zero_gradient() {
    let seen = Rc::new(RefCell::new(Vec::new()));
    let tape = Tape::<f64>::new();
    let xv = t1(&[0.2, 1.1, -0.7]);
    let x = tape.leaf(xv.clone());
    let out = tape.apply_multi(SinCos { seen: seen.clone() }, &[x], 2);
    assert_eq!(out.len(), 2);
    let g = tape.backward((out[0] * 2.0).sum()).unwrap();
    close(g.get(x).unwrap(), &xv.mapv(|v| 2.0 * v.cos()), 1e-14);
    {
        let s = seen.borrow();
        assert_eq!(s.len(), 1);
        assert!(s[0][0].iter().all(|&v| v == 2.0));
        assert_eq!(s[0][1].shape(), &[3]);
        assert!(
            s[0][1].iter().all(|&v| v == 0.0),
            "unused output gets zeros"
        );
    }
    // Both outputs used.
    let g = tape.backward((out[0] * 2.0 + out[1]).sum()).unwrap();
    close(
        g.get(x).unwrap(),
        &xv.mapv(|v| 2.0 * v.cos() - v.sin()),
        1e-14,
    );
    // Neither used: the op's backward never runs.
    let n = seen.borrow().len();
    tape.backward(x.sum()).unwrap();
    assert_eq!(seen.borrow().len(), n);
    // And it passes gradcheck through either output.
    for k in 0..2 {
        let rep = gradcheck(
            |t, v| {
                let o = t.apply_multi(SinCos { seen: seen.clone() }, &[v[0]], 2);
                o[k] * 3.0
            },
            &[xv.clone()],
            &GradcheckOptions::default(),
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
    }
}

/// `a * b`, recording the `needs_grad` flags it was given and whether it did work per input.
struct Probe {
    log: Rc<RefCell<Vec<Vec<bool>>>>,
    work: Rc<RefCell<[usize; 2]>>,
}

impl Op<f64> for Probe {
    fn name(&self) -> &'static str {
        "probe"
    }
    fn forward(&mut self, x: &[TensorView<'_, f64>]) -> Result<Vec<Tensor<f64>>> {
        Ok(vec![&x[0] * &x[1]])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, f64>) -> Result<Vec<Option<Tensor<f64>>>> {
        self.log.borrow_mut().push(ctx.needs_grad.to_vec());
        let g = ctx.grad_outputs[0];
        let mut out = vec![None, None];
        for k in 0..2 {
            if ctx.needs_grad[k] {
                self.work.borrow_mut()[k] += 1;
                out[k] = Some(g * &ctx.inputs[1 - k]);
            }
        }
        Ok(out)
    }
}

#[test]
fn leaves_without_requires_grad_get_nothing_and_their_work_is_skipped() {
    let log = Rc::new(RefCell::new(Vec::new()));
    let work = Rc::new(RefCell::new([0usize; 2]));
    let probe = || Probe {
        log: log.clone(),
        work: work.clone(),
    };
    let tape = Tape::<f64>::new();
    let av = t1(&[1.0, 2.0]);
    let bv = t1(&[3.0, -4.0]);
    let a = tape.leaf(av.clone());
    let b = tape.var(bv.clone(), false);
    let y = tape.apply(probe(), &[a, b]);
    let g = tape.backward(y.sum()).unwrap();
    assert_eq!(*log.borrow(), vec![vec![true, false]]);
    assert_eq!(
        *work.borrow(),
        [1, 0],
        "no gradient computed for the constant"
    );
    close(g.get(a).unwrap(), &bv, 0.0);
    assert!(g.get(b).is_none());
    // Order swapped: the flags follow the inputs.
    let y = tape.apply(probe(), &[b, a]);
    tape.backward(y.sum()).unwrap();
    assert_eq!(log.borrow()[1], vec![false, true]);
    assert_eq!(*work.borrow(), [1, 1]);

    // An op on constants only is not recorded and its backward never runs, even when its
    // output meets a parameter later.
    let n_ops = tape.num_ops();
    let c = tape.apply(probe(), &[b, b]);
    assert_eq!(tape.num_ops(), n_ops);
    assert!(!c.requires_grad());
    let g = tape.backward((c * a).sum()).unwrap();
    assert_eq!(log.borrow().len(), 2);
    close(g.get(a).unwrap(), &(&bv * &bv), 0.0);
    // A loss of constants only has no gradients.
    let g = tape.backward(c.sum()).unwrap();
    assert!(g.get(a).is_none() && g.get(b).is_none());
    // A parameter the loss does not reach: none, and zeros through `wrt`.
    let unused = tape.leaf(t1(&[1.0]));
    let g = tape.backward(a.sum()).unwrap();
    assert!(g.get(unused).is_none());
    assert_eq!(g.wrt(unused), t1(&[0.0]));
    // A recorded op whose output does not reach the loss is skipped.
    let before = log.borrow().len();
    let _dangling = tape.apply(probe(), &[a, a]);
    tape.backward(a.sum()).unwrap();
    assert_eq!(log.borrow().len(), before);
}

/// sin with a backward that is wrong by a factor (1 + bias) on one input.
struct WrongSin {
    bias: f64,
}

impl Op<f64> for WrongSin {
    fn name(&self) -> &'static str {
        "wrong_sin"
    }
    fn forward(&mut self, x: &[TensorView<'_, f64>]) -> Result<Vec<Tensor<f64>>> {
        Ok(vec![&x[0].mapv(f64::sin) * &x[1]])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, f64>) -> Result<Vec<Option<Tensor<f64>>>> {
        let (x, w, g) = (&ctx.inputs[0], &ctx.inputs[1], ctx.grad_outputs[0]);
        let gx = g * &x.mapv(f64::cos) * w * (1.0 + self.bias);
        let gw = sum_to_shape(g * &x.mapv(f64::sin), w.shape());
        Ok(vec![Some(gx), Some(gw)])
    }
}

fn good<'t>(t: &'t Tape<f64>, v: &[Var<'t, f64>]) -> Var<'t, f64> {
    t.apply(WrongSin { bias: 0.0 }, v)
        .tanh()
        .sum_axes(&[1], false)
}

fn bad<'t>(t: &'t Tape<f64>, v: &[Var<'t, f64>]) -> Var<'t, f64> {
    t.apply(WrongSin { bias: 0.01 }, v)
        .tanh()
        .sum_axes(&[1], false)
}

fn big_bad<'t>(t: &'t Tape<f64>, v: &[Var<'t, f64>]) -> Var<'t, f64> {
    let h = t.apply(
        WrongSin { bias: 0.01 },
        &[v[0].matmul(v[1]).reshape(&[3, 1]), v[1].slice(0, 0, 1)],
    );
    (h.exp() * 0.5).sum()
}

#[test]
fn gradcheck_fast_mode_agrees_with_full_and_both_catch_a_wrong_backward() {
    let mut rng = Rng::new(5);
    let xs = vec![
        rng.uniform_tensor::<f64>(&[3, 4], -1.0, 1.0),
        rng.uniform_tensor::<f64>(&[4], 0.5, 1.5),
    ];
    let full = GradcheckOptions::default();
    let fast = GradcheckOptions {
        mode: Mode::Fast { seed: 3 },
        ..Default::default()
    };
    let rf = gradcheck(good, &xs, &full).unwrap();
    let rq = gradcheck(good, &xs, &fast).unwrap();
    assert!(rf.passed(), "{rf}");
    assert!(rq.passed(), "{rq}");
    assert_eq!(rq.inputs.len(), 2);
    for r in &rq.inputs {
        assert!(
            (r.analytic - r.numeric).abs() < 1e-7 * (1.0 + r.numeric.abs()),
            "{rq}"
        );
        assert!(r.numeric.abs() > 1e-3, "a meaningful direction");
    }
    for (opts, name) in [(&full, "full"), (&fast, "fast")] {
        let r = gradcheck(bad, &xs, opts).unwrap();
        assert!(
            !r.passed(),
            "{name} mode must catch the wrong backward:\n{r}"
        );
        assert!(!r.inputs[0].passed, "{name}: input 0 is the wrong one\n{r}");
        assert!(r.inputs[1].passed, "{name}: input 1 is right\n{r}");
    }
    // Full mode points at the worst entry.
    let r = gradcheck(bad, &xs, &full).unwrap();
    assert_eq!(r.inputs[0].worst_index.len(), 2);
    assert!(r.to_string().contains("FAILED"));
    // A wrong gradient in a larger graph is still caught by both modes.
    for opts in [&full, &fast] {
        assert!(!gradcheck(big_bad, &xs, opts).unwrap().passed());
    }
}

/// Identity forward, NaN backward.
struct NanBackward;

impl<T: Real> Op<T> for NanBackward {
    fn name(&self) -> &'static str {
        "nan_backward"
    }
    fn forward(&mut self, x: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        Ok(vec![x[0].to_owned()])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        Ok(vec![Some(ctx.grad_outputs[0].mapv(|_| T::nan()))])
    }
}

#[test]
fn anomaly_detection_names_the_op_and_the_pass() {
    // Forward: log of a negative number.
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    let x = tape.leaf(t1(&[1.0, -1.0]));
    let y = (x * 2.0).ln().sum();
    let e = y.value().unwrap_err();
    match &e {
        AutodiffError::Anomaly {
            op,
            pass,
            input_shapes,
            ..
        } => {
            assert_eq!(*op, "log");
            assert_eq!(*pass, Pass::Forward);
            assert_eq!(input_shapes, &vec![vec![2]]);
        }
        other => panic!("expected an anomaly, got {other:?}"),
    }
    let m = e.to_string();
    assert!(m.contains("log") && m.contains("forward"), "{m}");
    assert_eq!(tape.backward(y).unwrap_err(), e);

    // Without detection the NaN just flows.
    let tape = Tape::<f64>::new();
    let x = tape.leaf(t1(&[1.0, -1.0]));
    let y = x.ln();
    assert!(y.value().unwrap()[1].is_nan());
    assert!(tape.error().is_none());

    // Backward: a custom op whose gradient is NaN.
    let tape = Tape::<f32>::new();
    tape.set_detect_anomaly(true);
    let x = tape.leaf(from_vec(&[2], vec![1.0f32, 2.0]).unwrap());
    let y = tape.apply(NanBackward, &[x.exp()]).sin().sum();
    assert!(y.value().is_ok(), "forward is finite");
    let e = tape.backward(y).err().expect("an anomaly");
    assert!(
        matches!(
            e,
            AutodiffError::Anomaly {
                op: "nan_backward",
                pass: Pass::Backward,
                ..
            }
        ),
        "{e:?}"
    );
    assert!(e.to_string().contains("nan_backward") && e.to_string().contains("backward pass"));

    // Backward: sqrt at zero has an infinite derivative.
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    let x = tape.leaf(t1(&[0.0, 4.0]));
    let e = tape.backward(x.sqrt().sum()).err().expect("an anomaly");
    assert!(
        matches!(
            e,
            AutodiffError::Anomaly {
                op: "sqrt",
                pass: Pass::Backward,
                ..
            }
        ),
        "{e:?}"
    );
    // Without detection the backward returns the infinite gradient.
    tape.set_detect_anomaly(false);
    let g = tape.backward(x.sqrt().sum()).unwrap();
    assert!(g.get(x).unwrap()[0].is_infinite());
}

type Build = for<'t> fn(Var<'t, f64>, Var<'t, f64>) -> Var<'t, f64>;

#[test]
fn nan_inputs_never_panic_and_propagate() {
    // Every op sees a NaN at [0, 1] of its first input and must output a NaN somewhere; the
    // backward runs without panicking.
    let cases: Vec<(&str, Build)> = vec![
        ("neg", |x, _| -x),
        ("exp", |x, _| x.exp()),
        ("log", |x, _| x.abs().ln()),
        ("sqrt", |x, _| x.abs().sqrt()),
        ("sin", |x, _| x.sin()),
        ("cos", |x, _| x.cos()),
        ("tanh", |x, _| x.tanh()),
        ("sigmoid", |x, _| x.sigmoid()),
        ("relu", |x, _| x.relu()),
        ("abs", |x, _| x.abs()),
        ("square", |x, _| x.square()),
        ("recip", |x, _| x.recip()),
        ("powf", |x, _| x.abs().powf(1.5)),
        ("clamp", |x, _| x.clamp(-0.5, 0.5)),
        ("add", |x, y| x + y),
        ("sub", |x, y| y - x),
        ("mul", |x, y| x * y),
        ("div", |x, y| y / x),
        ("pow", |x, y| y.abs().pow(x)),
        ("minimum", |x, y| x.minimum(y)),
        ("maximum", |x, y| y.maximum(x)),
        ("sum", |x, _| x.sum()),
        ("mean", |x, _| x.mean_axes(&[0], false)),
        ("max_axis", |x, _| x.max_axis(1, false)),
        ("logsumexp", |x, _| x.logsumexp(1, true)),
        ("matmul", |x, y| x.matmul(y.t())),
        ("matmul/vec", |x, y| {
            x.matmul(y.slice(0, 0, 1).reshape(&[3]))
        }),
        ("dot", |x, y| x.dot(y)),
        ("cross", |x, y| x.cross(y)),
        ("normalize", |x, _| x.normalize(1e-6)),
        ("reshape", |x, _| x.reshape(&[6])),
        ("permute", |x, _| x.t()),
        ("slice", |x, _| x.slice(1, 1, 3)),
        ("index_select", |x, _| x.index_select(1, &[1, 1])),
        ("gather", |x, _| {
            x.gather(1, ArrayD::from_elem(IxDyn(&[2, 1]), 1))
        }),
        ("scatter_add", |x, _| {
            x.scatter_add(1, ArrayD::zeros(IxDyn(&[2, 3])), 1)
        }),
        ("broadcast_to", |x, _| x.broadcast_to(&[4, 2, 3])),
    ];
    for (name, f) in cases {
        let tape = Tape::<f64>::new();
        let mut xv = arr2(&[[0.5, 0.0, -1.5], [2.0, 0.25, 1.0]]).into_dyn();
        xv[[0, 1]] = f64::NAN;
        let x = tape.leaf(xv);
        let y = tape.leaf(arr2(&[[1.5, -0.5, 0.75], [0.5, 1.25, -2.0]]).into_dyn());
        let out = f(x, y);
        let v = out.value().unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(v.iter().any(|v| v.is_nan()), "{name}: NaN dropped: {v}");
        let g = tape
            .backward(out.sum())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(g.wrt(x).shape(), &[2, 3], "{name}");
    }
    // `where` picks per element: the NaN survives where the mask takes it.
    let tape = Tape::<f64>::new();
    let x = tape.leaf(t1(&[f64::NAN, 1.0, 2.0]));
    let y = tape.leaf(t1(&[0.0, f64::NAN, 0.0]));
    let w = x
        .where_(arr1(&[true, true, false]).into_dyn(), y)
        .value()
        .unwrap();
    assert!(w[0].is_nan() && w[1] == 1.0 && w[2] == 0.0);
    // NaN as a parameter of scalar ops.
    let tape = Tape::<f64>::new();
    let x = tape.leaf(t1(&[1.0, 2.0]));
    assert!((x * f64::NAN).value().unwrap().iter().all(|v| v.is_nan()));
    assert!(
        x.clamp(f64::NAN, 1.0).value().is_err(),
        "NaN clamp bounds are an argument error"
    );
}
