#![allow(
    clippy::err_expect,
    clippy::cloned_ref_to_slice_refs,
    clippy::needless_range_loop
)]
//! Every shape or argument error is returned (never a panic), names the op and the shapes
//! involved, and a poisoned loss returns the first error from backward.

use autodiff::ndarray::{arr1, ArrayD, IxDyn};
use autodiff::optim::{Adam, Sgd};
use autodiff::rng::Rng;
use autodiff::{AutodiffError, BackwardCtx, Op, Result, Tape, Tensor, TensorView, Var};

fn zeros(shape: &[usize]) -> Tensor<f64> {
    ArrayD::zeros(IxDyn(shape))
}

/// The error of a poisoned variable; checks that its message names `op` and every string in
/// `parts` (shapes, details).
fn expect_err(v: Var<'_, f64>, op: &str, parts: &[&str]) -> AutodiffError {
    let e = v
        .value()
        .err()
        .unwrap_or_else(|| panic!("{op}: expected an error"));
    let m = e.to_string();
    assert!(
        m.starts_with(op) || m.contains(&format!("{op}:")),
        "{op}: {m}"
    );
    for p in parts {
        assert!(m.contains(p), "{op}: message {m:?} lacks {p:?}");
    }
    // The tape keeps it as its first error.
    assert_eq!(v.tape().error().as_ref(), Some(&e));
    e
}

fn with_tape(f: impl for<'t> FnOnce(&'t Tape<f64>) -> AutodiffError) -> AutodiffError {
    let tape = Tape::<f64>::new();
    f(&tape)
}

#[test]
fn add_with_incompatible_broadcast() {
    let e = with_tape(|t| {
        let a = t.leaf(zeros(&[3, 2]));
        let b = t.leaf(zeros(&[4, 2]));
        expect_err(a + b, "add", &["[3, 2]", "[4, 2]"])
    });
    assert!(matches!(e, AutodiffError::Shape { op: "add", .. }));
    for (name, f) in [
        (
            "sub",
            (|a, b| a - b) as for<'t> fn(Var<'t, f64>, Var<'t, f64>) -> Var<'t, f64>,
        ),
        ("mul", |a, b| a * b),
        ("div", |a, b| a / b),
        ("pow", |a, b| a.pow(b)),
        ("min", |a, b| a.minimum(b)),
        ("max", |a, b| a.maximum(b)),
        ("cross", |a, b| a.cross(b)),
    ] {
        with_tape(|t| {
            let a = t.leaf(zeros(&[2, 3]));
            let b = t.leaf(zeros(&[4, 3]));
            expect_err(f(a, b), name, &["[2, 3]", "[4, 3]"])
        });
    }
}

#[test]
fn where_and_broadcast_to_mismatch() {
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        let mask = ArrayD::from_elem(IxDyn(&[4, 1]), true);
        expect_err(a.where_(mask, a), "where", &["[4, 1]", "[2, 3]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        expect_err(
            a.broadcast_to(&[4, 3]),
            "broadcast_to",
            &["[2, 3]", "[4, 3]"],
        )
    });
    with_tape(|t| {
        // Broadcasting "down" to fewer dimensions is not allowed either.
        let a = t.leaf(zeros(&[2, 3]));
        expect_err(a.broadcast_to(&[3]), "broadcast_to", &["[2, 3]", "[3]"])
    });
}

#[test]
fn matmul_mismatch() {
    for (sa, sb) in [
        (vec![3, 4], vec![5, 2]),
        (vec![3, 4], vec![5]),
        (vec![4], vec![5, 2]),
        (vec![4], vec![5]),
        (vec![2, 3, 4], vec![3, 4, 2]),
        (vec![2, 3, 4], vec![5, 2]),
        (vec![2, 2, 2, 2], vec![2, 2]),
        (vec![], vec![3]),
    ] {
        with_tape(|t| {
            let a = t.leaf(zeros(&sa));
            let b = t.leaf(zeros(&sb));
            let e = expect_err(
                a.matmul(b),
                "matmul",
                &[&format!("{sa:?}"), &format!("{sb:?}")],
            );
            assert!(matches!(e, AutodiffError::Shape { op: "matmul", .. }));
            e
        });
    }
}

#[test]
fn shape_op_errors() {
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(
            a.reshape(&[5, 2]),
            "reshape",
            &["[3, 4]", "[5, 2]", "12", "10"],
        )
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        expect_err(a.permute(&[0, 0]), "permute", &["[2, 3]", "[0, 0]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        expect_err(a.permute(&[1, 0, 2]), "permute", &["[2, 3]", "[1, 0, 2]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(a.slice(1, 2, 6), "slice", &["[3, 4]", "2..6"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(a.slice(0, 2, 1), "slice", &["[3, 4]", "2..1"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(a.slice(2, 0, 1), "slice", &["[3, 4]", "axis 2"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        let b = t.leaf(zeros(&[2, 4]));
        expect_err(t.concat(&[a, b], 0), "concat", &["[2, 3]", "[2, 4]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        expect_err(t.concat(&[a, a], 2), "concat", &["[2, 3]", "axis 2"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[2, 3]));
        let b = t.leaf(zeros(&[3, 2]));
        expect_err(t.stack(&[a, b], 0), "stack", &["[2, 3]", "[3, 2]"])
    });
    with_tape(|t| expect_err(t.concat(&[], 0), "concat", &["no inputs"]));
}

#[test]
fn index_errors() {
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        let e = expect_err(
            a.index_select(0, &[0, 3]),
            "index_select",
            &["[3, 4]", "index 3"],
        );
        assert!(matches!(e, AutodiffError::Index { .. }));
        e
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(
            a.index_select(2, &[0]),
            "index_select",
            &["[3, 4]", "axis 2"],
        )
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        let idx = ArrayD::from_elem(IxDyn(&[3, 2]), 4usize);
        expect_err(a.gather(1, idx), "gather", &["[3, 4]", "[3, 2]", "index 4"])
    });
    with_tape(|t| {
        // Index larger than the input off the gather axis.
        let a = t.leaf(zeros(&[3, 4]));
        let idx = ArrayD::from_elem(IxDyn(&[5, 2]), 0usize);
        expect_err(a.gather(1, idx), "gather", &["[3, 4]", "[5, 2]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        let idx = ArrayD::from_elem(IxDyn(&[3]), 0usize);
        expect_err(a.gather(0, idx), "gather", &["[3, 4]", "[3]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        let idx = ArrayD::from_elem(IxDyn(&[3, 4]), 2usize);
        expect_err(
            a.scatter_add(1, idx, 2),
            "scatter_add",
            &["[3, 2]", "[3, 4]", "index 2"],
        )
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        let idx = ArrayD::from_elem(IxDyn(&[3, 3]), 0usize);
        expect_err(
            a.scatter_add(1, idx, 2),
            "scatter_add",
            &["[3, 4]", "[3, 3]"],
        )
    });
}

#[test]
fn vector_op_errors() {
    with_tape(|t| {
        let a = t.leaf(zeros(&[4, 2]));
        expect_err(a.cross(a), "cross", &["[4, 2]", "size 3"])
    });
    for eps in [0.0, -1.0, f64::NAN] {
        with_tape(|t| {
            let a = t.leaf(zeros(&[4, 3]));
            let e = expect_err(a.normalize(eps), "normalize", &["eps", "[4, 3]"]);
            assert!(matches!(e, AutodiffError::InvalidArgument { .. }));
            e
        });
    }
    with_tape(|t| {
        let a = t.leaf(zeros(&[]));
        expect_err(a.normalize(1e-6), "normalize", &["[]"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[4]));
        expect_err(a.clamp(1.0, -1.0), "clamp", &["lo 1 > hi -1"])
    });
}

#[test]
fn reduction_axis_errors() {
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        let e = expect_err(
            a.max_axis(2, false),
            "max",
            &["[3, 4]", "axis 2 out of range"],
        );
        assert!(matches!(e, AutodiffError::Index { op: "max", .. }));
        e
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(a.max_axis(-3, false), "max", &["[3, 4]", "negative axis"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 0]));
        expect_err(a.max_axis(1, false), "max", &["[3, 0]", "empty"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(a.logsumexp(5, true), "logsumexp", &["[3, 4]", "axis 5"])
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(
            a.sum_axes(&[1, -1], false),
            "sum",
            &["[3, 4]", "axis 1 repeated"],
        )
    });
    with_tape(|t| {
        let a = t.leaf(zeros(&[3, 4]));
        expect_err(a.mean_axes(&[0, 2], true), "mean", &["[3, 4]", "axis 2"])
    });
}

#[test]
fn backward_of_a_poisoned_loss_returns_the_first_error() {
    let tape = Tape::<f64>::new();
    let a = tape.leaf(zeros(&[3, 4]));
    let bad = a.reshape(&[5]); // first error
    let worse = bad.matmul(a).exp(); // fed a poisoned variable: no new error
    let unrelated = a.slice(0, 0, 9); // a second, later error
    let loss = (worse + unrelated).sum();
    let first = tape.error().expect("recorded");
    assert!(
        matches!(first, AutodiffError::Shape { op: "reshape", .. }),
        "{first:?}"
    );
    let e = tape.backward(loss).err().expect("an error");
    assert_eq!(e, first);
    assert!(e.to_string().contains("reshape") && e.to_string().contains("[3, 4]"));
    assert_eq!(tape.vjp(loss, zeros(&[])).err(), Some(first.clone()));
    assert_eq!(loss.item().err(), Some(first.clone()));
    // The first error stays the first.
    let _ = a.permute(&[7]);
    assert_eq!(tape.error(), Some(first));
    // Variables not touched by the error still work.
    assert!(tape.backward(a.sum()).is_ok());
}

#[test]
fn tape_misuse_errors() {
    let t1 = Tape::<f64>::new();
    let t2 = Tape::<f64>::new();
    let a = t1.leaf(zeros(&[2]));
    let b = t2.leaf(zeros(&[2]));
    let e = (a + b).value().err().expect("another tape");
    assert!(
        e.to_string().contains("add") && e.to_string().contains("another tape"),
        "{e}"
    );
    let e = a.value().unwrap().len();
    assert_eq!(e, 2);
    let e = a.item().err().expect("two elements");
    assert!(
        e.to_string().contains("item") && e.to_string().contains("[2]"),
        "{e}"
    );
}

/// A custom op that returns the wrong number of outputs or gradients, or a gradient of the
/// wrong shape.
struct Broken {
    outputs: usize,
    grads: usize,
    grad_shape: Vec<usize>,
}

impl Op<f64> for Broken {
    fn name(&self) -> &'static str {
        "broken"
    }
    fn forward(&mut self, x: &[TensorView<'_, f64>]) -> Result<Vec<Tensor<f64>>> {
        Ok(vec![x[0].to_owned(); self.outputs])
    }
    fn backward(&self, _: &BackwardCtx<'_, '_, f64>) -> Result<Vec<Option<Tensor<f64>>>> {
        Ok(vec![Some(zeros(&self.grad_shape)); self.grads])
    }
}

#[test]
fn custom_op_contract_errors() {
    let tape = Tape::<f64>::new();
    let a = tape.leaf(zeros(&[2, 3]));
    let op = |outputs, grads, grad_shape: &[usize]| Broken {
        outputs,
        grads,
        grad_shape: grad_shape.to_vec(),
    };
    // Forward returning no output: an error, not a panic.
    let e = tape
        .apply(op(0, 1, &[2, 3]), &[a])
        .value()
        .err()
        .expect("an error");
    assert!(
        e.to_string().contains("broken") && e.to_string().contains("0 outputs"),
        "{e}"
    );
    let tape = Tape::<f64>::new();
    let a = tape.leaf(zeros(&[2, 3]));
    let e = tape
        .backward(tape.apply(op(1, 2, &[2, 3]), &[a]).sum())
        .err()
        .expect("an error");
    assert!(
        e.to_string().contains("broken") && e.to_string().contains("2 gradients for 1 inputs"),
        "{e}"
    );
    let e = tape
        .backward(tape.apply(op(1, 1, &[3, 2]), &[a]).sum())
        .err()
        .expect("an error");
    let m = e.to_string();
    assert!(
        m.contains("broken") && m.contains("[2, 3]") && m.contains("[3, 2]"),
        "{m}"
    );
}

#[test]
fn optimiser_shape_mismatch() {
    let mut adam = Adam::<f64>::new(0.1);
    let mut p = arr1(&[1.0, 2.0, 3.0]).into_dyn();
    let g = arr1(&[1.0, 1.0, 1.0, 1.0]).into_dyn();
    let e = adam.step([(&mut p, &g)]).err().expect("an error");
    let m = e.to_string();
    assert!(
        m.contains("adam") && m.contains("[3]") && m.contains("[4]"),
        "{m}"
    );
    assert_eq!(adam.steps(), 0, "a failed step is not counted");
    assert_eq!(
        p,
        arr1(&[1.0, 2.0, 3.0]).into_dyn(),
        "a failed step changes nothing"
    );
    // A parameter that changes shape between steps.
    let g3 = arr1(&[1.0, 1.0, 1.0]).into_dyn();
    adam.step([(&mut p, &g3)]).unwrap();
    let mut p2 = arr1(&[1.0, 2.0]).into_dyn();
    let g2 = arr1(&[1.0, 1.0]).into_dyn();
    let e = adam.step([(&mut p2, &g2)]).err().expect("an error");
    let m = e.to_string();
    assert!(
        m.contains("adam") && m.contains("[3]") && m.contains("[2]") && m.contains("changed shape"),
        "{m}"
    );
    assert_eq!(adam.steps(), 1);

    let mut sgd = Sgd::<f64>::new(0.1, 0.9);
    let mut q = Rng::new(1).uniform_tensor::<f64>(&[2, 2], -1.0, 1.0);
    let before = q.clone();
    let gq = zeros(&[4]);
    // The first pair is fine, the second is not: nothing is updated.
    let mut r = zeros(&[3]);
    let ones2 = ArrayD::from_elem(IxDyn(&[2, 2]), 1.0);
    let e = sgd
        .step([(&mut r, &g3), (&mut q, &gq)])
        .err()
        .expect("an error");
    let m = e.to_string();
    assert!(
        m.contains("sgd") && m.contains("[2, 2]") && m.contains("[4]"),
        "{m}"
    );
    assert_eq!(q, before);
    assert_eq!(r, zeros(&[3]));
    sgd.step([(&mut r, &g3), (&mut q, &ones2)]).unwrap();
    assert!(r.iter().all(|&v| (v + 0.1).abs() < 1e-15));
}
