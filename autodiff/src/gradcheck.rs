//! Finite-difference gradient checking in `f64`.
//!
//! [`gradcheck`] compares the tape's gradients of any function of variables with central
//! differences `(f(x + h e_j) - f(x - h e_j)) / 2h`:
//! - [`Mode::Full`] builds the whole Jacobian both ways (one vector-Jacobian product per
//!   output element, two evaluations per input element) and reports, per input, the largest
//!   absolute and relative error and where it occurs;
//! - [`Mode::Fast`] checks one random directional derivative per input, `v^T J u`, as
//!   PyTorch's `fast_mode` does: two evaluations and one backward per input.
//!
//! An element passes when `|analytic - numeric| <= atol + rtol |numeric|`. The relative error
//! reported is `|analytic - numeric| / max(|numeric|, atol)`.
//!
//! [`compare_precision`] runs the same function in `f32` and `f64` and reports the normwise
//! relative difference of values and gradients, so an `f32` pipeline is checked by its `f64`
//! twin.

use crate::error::{AutodiffError, Result};
use crate::rng::Rng;
use crate::tape::{Tape, Var};
use crate::tensor::{cast, Tensor};
use crate::Real;
use ndarray::{ArrayD, IxDyn};

/// Full Jacobian or a random directional check.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Mode {
    /// Every Jacobian entry.
    Full,
    /// `v^T J u` with random `u`, `v` from the seed.
    Fast {
        /// Seed of the random directions.
        seed: u64,
    },
}

/// Settings of [`gradcheck`].
#[derive(Clone, Debug)]
pub struct GradcheckOptions {
    /// Finite-difference step.
    pub eps: f64,
    /// Absolute tolerance.
    pub atol: f64,
    /// Relative tolerance.
    pub rtol: f64,
    /// Full or fast.
    pub mode: Mode,
    /// Which inputs to check (default: all). Unchecked inputs are constants.
    pub wrt: Option<Vec<bool>>,
}

impl Default for GradcheckOptions {
    fn default() -> Self {
        GradcheckOptions {
            eps: 1e-6,
            atol: 1e-5,
            rtol: 1e-3,
            mode: Mode::Full,
            wrt: None,
        }
    }
}

/// Result of checking one input.
#[derive(Clone, Debug)]
pub struct InputReport {
    /// Position of the input.
    pub input: usize,
    /// Its shape.
    pub shape: Vec<usize>,
    /// Largest absolute error.
    pub max_abs_err: f64,
    /// Largest relative error (`|a - n| / max(|n|, atol)`).
    pub max_rel_err: f64,
    /// (output index, input index) of the largest absolute error; empty in fast mode.
    pub worst_index: Vec<usize>,
    /// Analytic value at the worst entry.
    pub analytic: f64,
    /// Numeric value at the worst entry.
    pub numeric: f64,
    /// All entries within tolerance.
    pub passed: bool,
}

/// Result of a gradient check.
#[derive(Clone, Debug)]
pub struct GradcheckReport {
    /// One report per checked input.
    pub inputs: Vec<InputReport>,
    /// Shape of the function's output.
    pub output_shape: Vec<usize>,
}

impl GradcheckReport {
    /// True when every checked input passed.
    pub fn passed(&self) -> bool {
        self.inputs.iter().all(|r| r.passed)
    }
    /// Largest absolute error over inputs.
    pub fn max_abs_err(&self) -> f64 {
        self.inputs
            .iter()
            .map(|r| r.max_abs_err)
            .fold(0.0, f64::max)
    }
    /// Largest relative error over inputs.
    pub fn max_rel_err(&self) -> f64 {
        self.inputs
            .iter()
            .map(|r| r.max_rel_err)
            .fold(0.0, f64::max)
    }
}

impl std::fmt::Display for GradcheckReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for r in &self.inputs {
            // worst_index is (flat output index, flat input index): show the input entry as a
            // multi-index in the input's shape.
            let at = match r.worst_index.as_slice() {
                [k, j] if r.shape.iter().product::<usize>() > *j => {
                    format!("output[{k}] / input{:?}", unravel(*j, &r.shape))
                }
                _ => "-".to_string(),
            };
            writeln!(
                f,
                "input {} {:?}: max abs {:.3e}, max rel {:.3e} at {} (analytic {:.6e}, numeric {:.6e}) {}",
                r.input,
                r.shape,
                r.max_abs_err,
                r.max_rel_err,
                at,
                r.analytic,
                r.numeric,
                if r.passed { "ok" } else { "FAILED" }
            )?;
        }
        Ok(())
    }
}

fn eval<F>(f: &F, xs: &[Tensor<f64>], wrt: &[bool]) -> Result<Tensor<f64>>
where
    F: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    let tape = Tape::new();
    let vars: Vec<_> = xs
        .iter()
        .zip(wrt)
        .map(|(x, &w)| tape.var(x.clone(), w))
        .collect();
    let y = f(&tape, &vars);
    // Read outputs as flat row-major slices below, whatever layout the function returned.
    let v = y.value()?;
    Ok(v.as_standard_layout().into_owned())
}

fn analytic_vjp<F>(
    f: &F,
    xs: &[Tensor<f64>],
    wrt: &[bool],
    v: Tensor<f64>,
) -> Result<Vec<Tensor<f64>>>
where
    F: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    let tape = Tape::new();
    let vars: Vec<_> = xs
        .iter()
        .zip(wrt)
        .map(|(x, &w)| tape.var(x.clone(), w))
        .collect();
    let y = f(&tape, &vars);
    let g = tape.vjp(y, v)?;
    Ok(vars.iter().map(|&x| g.wrt(x)).collect())
}

fn tol_ok(a: f64, n: f64, o: &GradcheckOptions) -> bool {
    // NaN never passes.
    (a - n).abs() <= o.atol + o.rtol * n.abs()
}

/// Checks the gradients of `f` at `inputs` against central finite differences.
pub fn gradcheck<F>(
    f: F,
    inputs: &[Tensor<f64>],
    opts: &GradcheckOptions,
) -> Result<GradcheckReport>
where
    F: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    if opts.eps.is_nan() || opts.eps <= 0.0 {
        return Err(AutodiffError::invalid("gradcheck", "eps must be > 0"));
    }
    let wrt = opts.wrt.clone().unwrap_or_else(|| vec![true; inputs.len()]);
    if wrt.len() != inputs.len() {
        return Err(AutodiffError::invalid(
            "gradcheck",
            "wrt must have one flag per input",
        ));
    }
    let y0 = eval(&f, inputs, &wrt)?;
    let m = y0.len();
    let mut xs: Vec<Tensor<f64>> = inputs
        .iter()
        .map(|x| x.as_standard_layout().into_owned())
        .collect();
    let mut reports = Vec::new();
    match opts.mode {
        Mode::Full => {
            // Analytic Jacobian rows: one VJP per output element.
            let mut rows: Vec<Vec<Tensor<f64>>> = Vec::with_capacity(m);
            for k in 0..m {
                let mut v = ArrayD::<f64>::zeros(y0.raw_dim());
                v.as_slice_mut().expect("fresh")[k] = 1.0;
                rows.push(analytic_vjp(&f, &xs, &wrt, v)?);
            }
            for i in 0..xs.len() {
                if !wrt[i] {
                    continue;
                }
                let mut rep = InputReport {
                    input: i,
                    shape: xs[i].shape().to_vec(),
                    max_abs_err: 0.0,
                    max_rel_err: 0.0,
                    worst_index: vec![],
                    analytic: 0.0,
                    numeric: 0.0,
                    passed: true,
                };
                for j in 0..xs[i].len() {
                    let x0 = xs[i].as_slice().expect("standard")[j];
                    xs[i].as_slice_mut().expect("standard")[j] = x0 + opts.eps;
                    let yp = eval(&f, &xs, &wrt)?;
                    xs[i].as_slice_mut().expect("standard")[j] = x0 - opts.eps;
                    let ym = eval(&f, &xs, &wrt)?;
                    xs[i].as_slice_mut().expect("standard")[j] = x0;
                    for (k, row) in rows.iter().enumerate() {
                        let n = (yp.as_slice().expect("std")[k] - ym.as_slice().expect("std")[k])
                            / (2.0 * opts.eps);
                        let a = row[i].as_standard_layout()[IxDyn(&unravel(j, xs[i].shape()))];
                        let abs = (a - n).abs();
                        let rel = abs / n.abs().max(opts.atol);
                        let bad = !tol_ok(a, n, opts);
                        if abs > rep.max_abs_err || abs.is_nan() || (bad && rep.passed) {
                            rep.max_abs_err = if abs.is_nan() {
                                f64::INFINITY
                            } else {
                                abs.max(rep.max_abs_err)
                            };
                            rep.worst_index = vec![k, j];
                            rep.analytic = a;
                            rep.numeric = n;
                        }
                        rep.max_rel_err =
                            rep.max_rel_err
                                .max(if rel.is_nan() { f64::INFINITY } else { rel });
                        rep.passed &= !bad;
                    }
                }
                reports.push(rep);
            }
        }
        Mode::Fast { seed } => {
            let mut rng = Rng::new(seed);
            let v = rng.normal_tensor(y0.shape());
            let g = analytic_vjp(&f, &xs, &wrt, v.clone())?;
            for i in 0..xs.len() {
                if !wrt[i] {
                    continue;
                }
                let u: Tensor<f64> = rng.normal_tensor(xs[i].shape());
                let a: f64 = (&g[i] * &u).sum();
                let x0 = xs[i].clone();
                xs[i] = &x0 + &(&u * opts.eps);
                let yp = eval(&f, &xs, &wrt)?;
                xs[i] = &x0 - &(&u * opts.eps);
                let ym = eval(&f, &xs, &wrt)?;
                xs[i] = x0;
                let n: f64 = ((&yp - &ym) * &v).sum() / (2.0 * opts.eps);
                let abs = (a - n).abs();
                let rel = abs / n.abs().max(opts.atol);
                reports.push(InputReport {
                    input: i,
                    shape: xs[i].shape().to_vec(),
                    max_abs_err: if abs.is_nan() { f64::INFINITY } else { abs },
                    max_rel_err: if rel.is_nan() { f64::INFINITY } else { rel },
                    worst_index: vec![],
                    analytic: a,
                    numeric: n,
                    passed: tol_ok(a, n, opts),
                });
            }
        }
    }
    Ok(GradcheckReport {
        inputs: reports,
        output_shape: y0.shape().to_vec(),
    })
}

fn unravel(mut j: usize, shape: &[usize]) -> Vec<usize> {
    let mut idx = vec![0; shape.len()];
    for d in (0..shape.len()).rev() {
        idx[d] = j % shape[d];
        j /= shape[d];
    }
    idx
}

/// Normwise relative differences between an `f32` run and an `f64` run of the same function.
#[derive(Clone, Debug)]
pub struct PrecisionReport {
    /// `max |y32 - y64| / max |y64|` over the output.
    pub value_rel: f64,
    /// The same for each input's gradient of `sum(y * v)` (fixed random `v`).
    pub grad_rel: Vec<f64>,
}

impl PrecisionReport {
    /// Worst of the value and gradient differences.
    pub fn max_rel(&self) -> f64 {
        self.grad_rel.iter().copied().fold(self.value_rel, f64::max)
    }
}

fn normwise<T: Real>(a: &Tensor<T>, b: &Tensor<f64>) -> f64 {
    // `f64::max` ignores NaN, so a NaN on either side is reported as an infinite difference.
    if a.iter().any(|x| x.is_nan()) || b.iter().any(|y| y.is_nan()) {
        return f64::INFINITY;
    }
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = a
        .iter()
        .zip(b.iter())
        .fold(0.0f64, |m, (x, y)| m.max((x.to_f64c() - y).abs()));
    if scale == 0.0 {
        diff
    } else {
        diff / scale
    }
}

/// Runs `f32f` and `f64f` (the same function instantiated at both precisions) on `inputs` and
/// reports the normwise relative difference of their values and gradients.
pub fn compare_precision<F32, F64>(
    f32f: F32,
    f64f: F64,
    inputs: &[Tensor<f64>],
    seed: u64,
) -> Result<PrecisionReport>
where
    F32: for<'t> Fn(&'t Tape<f32>, &[Var<'t, f32>]) -> Var<'t, f32>,
    F64: for<'t> Fn(&'t Tape<f64>, &[Var<'t, f64>]) -> Var<'t, f64>,
{
    let t64 = Tape::<f64>::new();
    let v64: Vec<_> = inputs.iter().map(|x| t64.leaf(x.clone())).collect();
    let y64 = f64f(&t64, &v64);
    let y64v = (*y64.value()?).clone();
    let w = Rng::new(seed).normal_tensor(y64v.shape());
    let g64 = t64.vjp(y64, w.clone())?;

    let t32 = Tape::<f32>::new();
    let v32: Vec<_> = inputs
        .iter()
        .map(|x| t32.leaf(cast::<f64, f32, _>(x)))
        .collect();
    let y32 = f32f(&t32, &v32);
    let y32v = (*y32.value()?).clone();
    if y32v.shape() != y64v.shape() {
        return Err(AutodiffError::shape(
            "compare_precision",
            &[y32v.shape(), y64v.shape()],
            "f32 and f64 outputs differ in shape",
        ));
    }
    let g32 = t32.vjp(y32, cast::<f64, f32, _>(&w))?;
    Ok(PrecisionReport {
        value_rel: normwise(&y32v, &y64v),
        grad_rel: v32
            .iter()
            .zip(&v64)
            .map(|(&a, &b)| normwise(&g32.wrt(a), &g64.wrt(b)))
            .collect(),
    })
}
