//! Anomaly mode (`Tape::set_detect_anomaly`): the first op whose forward output or backward
//! gradient holds a NaN or Inf is reported as `AutodiffError::Anomaly`, naming the op, its node
//! id on the tape and its input shapes, in the variant's fields and in the message. It is off by
//! default: then NaN and Inf simply propagate.

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::{AutodiffError, Pass, Tape, Tensor};

fn t(shape: &[usize], v: &[f64]) -> Tensor<f64> {
    ArrayD::from_shape_vec(IxDyn(shape), v.to_vec()).unwrap()
}

#[test]
fn forward_nan_names_op_node_and_input_shapes() {
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    // Node 0: the leaf; node 1: log of a negative entry; node 2: exp downstream of it.
    let x = tape.leaf(t(&[2, 3], &[1.0, 2.0, -3.0, 4.0, 5.0, 6.0]));
    let y = x.ln();
    let z = y.exp().sum();
    let e = z.value().unwrap_err();
    assert_eq!(
        e,
        AutodiffError::Anomaly {
            op: "log",
            node: 1,
            pass: Pass::Forward,
            input_shapes: vec![vec![2, 3]],
        }
    );
    let m = e.to_string();
    for part in ["log", "node 1", "forward", "[[2, 3]]"] {
        assert!(m.contains(part), "message {m:?} lacks {part:?}");
    }
    // The first anomaly is sticky: downstream ops (exp, sum) report it, and so does backward.
    assert_eq!(y.value().unwrap_err(), e);
    assert_eq!(tape.error(), Some(e.clone()));
    assert_eq!(tape.backward(z).unwrap_err(), e);

    // Two inputs: the shapes of both are reported (0 / 0 in div).
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    let a = tape.leaf(t(&[3], &[1.0, 0.0, 2.0]));
    let b = tape.leaf(t(&[1], &[0.0]));
    let e = (a / b).value().unwrap_err();
    assert!(
        matches!(
            &e,
            AutodiffError::Anomaly { op: "div", node: 2, pass: Pass::Forward, input_shapes }
                if input_shapes == &vec![vec![3], vec![1]]
        ),
        "{e:?}"
    );
}

#[test]
fn backward_inf_and_nan_name_op_node_and_input_shapes() {
    // Inf: d sqrt(x) / dx at x = 0. The forward is finite, so only the backward reports.
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    let x = tape.leaf(t(&[4], &[0.0, 1.0, 4.0, 9.0]));
    let s = x.sqrt(); // node 1
    let loss = s.sum();
    assert!(loss.value().is_ok());
    let e = tape.backward(loss).unwrap_err();
    assert_eq!(
        e,
        AutodiffError::Anomaly {
            op: "sqrt",
            node: 1,
            pass: Pass::Backward,
            input_shapes: vec![vec![4]],
        }
    );
    let m = e.to_string();
    for part in ["sqrt", "node 1", "backward", "[[4]]"] {
        assert!(m.contains(part), "message {m:?} lacks {part:?}");
    }

    // NaN: the incoming gradient of sqrt at 0 is 0 (the output is scaled by 0), and 0 / 0 in
    // its backward is NaN, while every forward value is finite.
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    let x = tape.leaf(t(&[2, 2], &[0.0, 1.0, 4.0, 9.0]));
    let s = x.sqrt(); // node 1
    let loss = (s * 0.0).sum();
    assert_eq!(loss.value().unwrap()[[]], 0.0);
    match tape.backward(loss).unwrap_err() {
        AutodiffError::Anomaly {
            op,
            node,
            pass,
            input_shapes,
        } => {
            assert_eq!((op, node, pass), ("sqrt", 1, Pass::Backward));
            assert_eq!(input_shapes, vec![vec![2, 2]]);
        }
        other => panic!("expected an anomaly, got {other:?}"),
    }
}

#[test]
fn off_by_default_nan_and_inf_propagate() {
    let tape = Tape::<f64>::new();
    let x = tape.leaf(t(&[3], &[-1.0, 0.0, 4.0]));
    // Forward: log(-1) is NaN and flows on through exp and sum without an error.
    let y = x.ln();
    let v = y.value().unwrap();
    assert!(v[0].is_nan() && v[1] == f64::NEG_INFINITY);
    assert!(y.exp().sum().value().unwrap()[[]].is_nan());
    assert!(tape.error().is_none());
    // Backward: sqrt at 0 gives an infinite gradient, NaN at -1, returned as they are.
    let g = tape.backward(x.sqrt().sum()).unwrap();
    let gx = g.get(x).unwrap();
    assert!(gx[0].is_nan(), "{gx}");
    assert_eq!(gx[1], f64::INFINITY);
    assert_eq!(gx[2], 0.25);
    assert!(tape.error().is_none());

    // Turning detection on, then off again, restores the default.
    tape.set_detect_anomaly(true);
    assert!(tape.backward(x.sqrt().sum()).is_err());
    tape.set_detect_anomaly(false);
    assert!(tape.backward(x.sqrt().sum()).is_ok());
}
