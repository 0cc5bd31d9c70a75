#![allow(
    clippy::err_expect,
    clippy::cloned_ref_to_slice_refs,
    clippy::needless_range_loop
)]
//! Every built-in op passes a full-Jacobian gradient check in f64, and its f32 run agrees with
//! the f64 run to 1e-4 (normwise relative, values and gradients).

use std::time::Instant;

use autodiff::gradcheck::{GradcheckOptions, Mode};
use autodiff::suite::{builtin_cases, render_table, run_all, F32_REL_TOL};

#[test]
fn every_builtin_case_passes_gradcheck_and_f32_agrees() {
    let t0 = Instant::now();
    let results = run_all(None);
    let secs = t0.elapsed().as_secs_f64();
    let table = render_table(&results);
    println!("{table}\n{secs:.3} s");
    assert_eq!(results.len(), builtin_cases().len());
    let failed: Vec<_> = results.iter().filter(|r| !r.passed).map(|r| r.op).collect();
    assert!(failed.is_empty(), "failed cases {failed:?}\n{table}");
    for r in &results {
        assert!(r.error.is_none(), "{}: {:?}", r.op, r.error);
        assert!(
            r.f32_rel <= F32_REL_TOL,
            "{}: f32 vs f64 {:.3e}\n{table}",
            r.op,
            r.f32_rel
        );
        assert!(
            r.max_abs_err.is_finite() && r.max_rel_err.is_finite(),
            "{}",
            r.op
        );
    }
}

#[test]
fn suite_covers_every_builtin_op() {
    let cases = builtin_cases();
    let names: Vec<&str> = cases.iter().map(|c| c.base()).collect();
    for op in [
        "add",
        "sub",
        "mul",
        "div",
        "neg",
        "exp",
        "log",
        "sqrt",
        "pow",
        "pow_scalar",
        "scalar_pow",
        "add_scalar",
        "sub_scalar",
        "mul_scalar",
        "div_scalar",
        "rsub_scalar",
        "rdiv_scalar",
        "sin",
        "cos",
        "tanh",
        "sigmoid",
        "relu",
        "abs",
        "square",
        "recip",
        "clamp",
        "minimum",
        "maximum",
        "where",
        "sum",
        "mean",
        "sum_axes",
        "mean_axes",
        "max_axis",
        "logsumexp",
        "matmul",
        "reshape",
        "permute",
        "t",
        "slice",
        "concat",
        "stack",
        "broadcast_to",
        "gather",
        "scatter_add",
        "index_select",
        "dot",
        "cross",
        "normalize",
        "norm",
    ] {
        assert!(names.contains(&op), "no suite case for {op}");
    }
    for v in [
        "matmul/mat-mat",
        "matmul/mat-vec",
        "matmul/vec-mat",
        "matmul/vec-vec",
        "matmul/batched",
        "matmul/batch-bcast-rhs",
        "matmul/3d-2d",
        "add/bcast-1dims",
        "add/0d",
        "sum_axes/keepdim",
    ] {
        assert!(cases.iter().any(|c| c.op == v), "no suite case {v}");
    }
    // Shapes with size-1 dimensions and 0-d scalars are covered.
    assert!(cases.iter().any(|c| c.shapes.iter().any(|s| s.is_empty())));
    assert!(cases
        .iter()
        .any(|c| c.shapes.iter().any(|s| s.len() > 1 && s.contains(&1))));
}

#[test]
fn fast_mode_passes_on_every_case() {
    let opts = GradcheckOptions {
        mode: Mode::Fast { seed: 11 },
        ..Default::default()
    };
    for case in builtin_cases() {
        let r = case.run(&opts).unwrap();
        assert!(r.passed, "{} in fast mode: {r:?}", case.op);
    }
}

#[test]
fn a_case_with_a_wrong_gradient_fails_in_the_table() {
    // The suite's verdict must be able to fail: run a case with a tolerance no real check
    // meets, and a finite-difference step so large that the error is visible.
    let case = builtin_cases().into_iter().find(|c| c.op == "exp").unwrap();
    let opts = GradcheckOptions {
        eps: 0.3,
        atol: 1e-9,
        rtol: 1e-9,
        ..Default::default()
    };
    let r = case.run(&opts).unwrap();
    assert!(!r.passed && r.max_abs_err > 1e-3, "{r:?}");
    assert!(render_table(&[r]).contains("FAIL"));
}
