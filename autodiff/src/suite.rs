//! The built-in op check suite: a registry of named gradient-check cases covering every
//! built-in op (elementwise, broadcasting, reductions, matrix products, shape, indexing and
//! vector ops), each run as a full-Jacobian [`gradcheck`] in `f64` plus a
//! [`compare_precision`] of the same function instantiated at `f32`.
//!
//! Every case is one generic function `fn<'t, T: Real>(&'t Tape<T>, &[Var<'t, T>]) -> Var<'t, T>`
//! stored twice (at `f32` and `f64`), the input shapes, and one [`Gen`] per input that draws
//! values from [`Rng`] with a seed derived from the case name, away from kinks and
//! singularities by far more than the finite-difference step.
//!
//! ```
//! let results = autodiff::suite::run_all(Some("matmul"));
//! assert!(results.len() >= 6 && results.iter().all(|r| r.passed));
//! println!("{}", autodiff::suite::render_table(&results));
//! ```
//!
//! [`Registry`] is the one list that `tapestry gradcheck --all` runs: the built-in cases
//! (category `autodiff`), the crates' cases (`render_ops::check::register` adds `shade`,
//! `texture`, `raster` and `method`) and whatever user code adds, as a [`Case`] or as any
//! check function ([`Registry::add_check`]).
//!
//! ```
//! use autodiff::suite::{Case, Gen, Registry};
//! use autodiff::{Real, Tape, Var};
//! fn cube<'t, T: Real>(_t: &'t Tape<T>, x: &[Var<'t, T>]) -> Var<'t, T> {
//!     x[0] * x[0] * x[0]
//! }
//! let mut reg = Registry::builtin();
//! reg.add(Case::new("my/cube", vec![vec![4]], vec![Gen::Uniform(-1.0, 1.0)], cube::<f32>, cube::<f64>)
//!     .in_category("mine"));
//! let results = reg.run(Some("mine"));
//! assert_eq!(results.len(), 1);
//! assert!(results[0].passed && results[0].category == "mine");
//! ```

use std::sync::Arc;

use ndarray::{ArrayD, Dimension, IxDyn};
use rayon::prelude::*;

use crate::error::Result;
use crate::gradcheck::{compare_precision, gradcheck, GradcheckOptions};
use crate::ops::elementwise::{Unary, UnaryOp};
use crate::rng::Rng;
use crate::tape::{Tape, Var};
use crate::tensor::Tensor;
use crate::{c, Real};

/// Largest normwise relative difference allowed between the `f32` and `f64` runs of a case.
pub const F32_REL_TOL: f64 = 1e-4;

/// A case function at one precision.
pub type CaseFn<T> = for<'t> fn(&'t Tape<T>, &[Var<'t, T>]) -> Var<'t, T>;

/// How the values of one input are drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Gen {
    /// Uniform in `[lo, hi)`.
    Uniform(f64, f64),
    /// Random sign, magnitude uniform in `[lo, hi)`: away from zero (relu, abs, recip, division).
    Signed(f64, f64),
    /// `m + offset + u` with `m` a random integer in `[-2, 2]` and `u` uniform in
    /// `[-0.2, 0.2]`: at least 0.3 away from every `k + offset + 0.5` (clamp bounds), and two
    /// inputs whose offsets differ by 0.5 are never closer than 0.1 (minimum, maximum).
    Lattice(f64),
    /// Pairwise distinct values: a random permutation of `n` evenly spaced points in
    /// `[lo, hi]`, jittered by a quarter of the spacing, so no two are closer than half the
    /// spacing (max over an axis).
    Distinct(f64, f64),
}

impl Gen {
    /// Draws a tensor of the given shape.
    pub fn sample(&self, rng: &mut Rng, shape: &[usize]) -> Tensor<f64> {
        let n: usize = shape.iter().product();
        let data: Vec<f64> = match *self {
            Gen::Uniform(lo, hi) => (0..n).map(|_| rng.uniform(lo, hi)).collect(),
            Gen::Signed(lo, hi) => (0..n)
                .map(|_| {
                    let m = rng.uniform(lo, hi);
                    if rng.next_u64() & 1 == 0 {
                        m
                    } else {
                        -m
                    }
                })
                .collect(),
            Gen::Lattice(offset) => (0..n)
                .map(|_| (rng.below(5) as f64 - 2.0) + offset + rng.uniform(-0.2, 0.2))
                .collect(),
            Gen::Distinct(lo, hi) => {
                // Fisher-Yates shuffle of the slots.
                let mut perm: Vec<usize> = (0..n).collect();
                for i in (1..n).rev() {
                    perm.swap(i, rng.below(i + 1));
                }
                let step = (hi - lo) / n.max(1) as f64;
                perm.iter()
                    .map(|&p| lo + (p as f64 + 0.5 + rng.uniform(-0.25, 0.25)) * step)
                    .collect()
            }
        };
        ArrayD::from_shape_vec(IxDyn(shape), data).expect("count matches the shape")
    }
}

/// One named gradient-check case.
#[derive(Clone)]
pub struct Case {
    /// Name: the op, then `/variant` where an op has several cases (e.g. `matmul/mat-vec`).
    pub op: &'static str,
    /// Shapes of the inputs.
    pub shapes: Vec<Vec<usize>>,
    /// How each input is drawn.
    pub gens: Vec<Gen>,
    /// Seed of the input values (derived from the name).
    pub seed: u64,
    /// The case at `f32`.
    pub f_f32: CaseFn<f32>,
    /// The case at `f64`.
    pub f_f64: CaseFn<f64>,
    /// Category in a [`Registry`] (`autodiff` unless set with [`Case::in_category`]).
    pub category: &'static str,
    /// Gradcheck settings of this case (`None`: those given to [`Case::run`]).
    pub options: Option<GradcheckOptions>,
    /// Largest `f32`/`f64` difference allowed ([`F32_REL_TOL`] unless set).
    pub f32_tol: f64,
}

impl std::fmt::Debug for Case {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Case")
            .field("op", &self.op)
            .field("shapes", &self.shapes)
            .field("gens", &self.gens)
            .field("seed", &self.seed)
            .field("category", &self.category)
            .field("f32_tol", &self.f32_tol)
            .finish_non_exhaustive()
    }
}

/// Outcome of one case (plain fields, ready for a table or JSON).
#[derive(Clone, Debug, PartialEq)]
pub struct CaseResult {
    /// Name of the case.
    pub op: &'static str,
    /// Its category (`autodiff`, `shade`, `texture`, `raster`, `method`, or a user's).
    pub category: &'static str,
    /// Shapes of its inputs.
    pub shapes: Vec<Vec<usize>>,
    /// Largest absolute error of the analytic Jacobian against central differences (`f64`).
    pub max_abs_err: f64,
    /// Largest relative error, `|a - n| / max(|n|, atol)`.
    pub max_rel_err: f64,
    /// Largest normwise relative difference between the `f32` and `f64` runs (value and
    /// gradients).
    pub f32_rel: f64,
    /// Gradcheck passed and `f32_rel <= F32_REL_TOL`.
    pub passed: bool,
    /// The error, when the case could not be run at all (then `passed` is false and the
    /// errors are infinite).
    pub error: Option<String>,
}

fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

impl Case {
    /// A case; the seed is derived from the name.
    pub fn new(
        op: &'static str,
        shapes: Vec<Vec<usize>>,
        gens: Vec<Gen>,
        f_f32: CaseFn<f32>,
        f_f64: CaseFn<f64>,
    ) -> Self {
        assert_eq!(shapes.len(), gens.len(), "{op}: one generator per input");
        Case {
            op,
            shapes,
            gens,
            seed: fnv1a(op),
            f_f32,
            f_f64,
            category: "autodiff",
            options: None,
            f32_tol: F32_REL_TOL,
        }
    }

    /// The case in another category.
    pub fn in_category(mut self, category: &'static str) -> Self {
        self.category = category;
        self
    }

    /// The case with its own gradcheck settings (e.g. a larger step or tolerance).
    pub fn with_options(mut self, options: GradcheckOptions) -> Self {
        self.options = Some(options);
        self
    }

    /// The case with its own `f32`/`f64` tolerance (ops whose `f32` path rounds differently
    /// by design, e.g. a rasterizer's `f32` edge tests).
    pub fn with_f32_tol(mut self, tol: f64) -> Self {
        self.f32_tol = tol;
        self
    }

    /// The base op name (the part before `/`).
    pub fn base(&self) -> &'static str {
        self.op.split('/').next().unwrap_or(self.op)
    }

    /// Whether `filter` selects this case: the full name or the base op name.
    pub fn matches(&self, filter: &str) -> bool {
        self.op == filter || self.base() == filter
    }

    /// The input values (`f64`; the `f32` run rounds them).
    pub fn inputs(&self) -> Vec<Tensor<f64>> {
        let mut rng = Rng::new(self.seed);
        self.shapes
            .iter()
            .zip(&self.gens)
            .map(|(s, g)| g.sample(&mut rng, s))
            .collect()
    }

    /// Runs the gradient check (the case's own options, else `opts`, normally full mode) in
    /// `f64` and the `f32`/`f64` comparison.
    pub fn run(&self, opts: &GradcheckOptions) -> Result<CaseResult> {
        let inputs = self.inputs();
        let opts = self.options.as_ref().unwrap_or(opts);
        let rep = gradcheck(self.f_f64, &inputs, opts)?;
        let prec = compare_precision(self.f_f32, self.f_f64, &inputs, self.seed.rotate_left(17))?;
        let f32_rel = match prec.max_rel() {
            r if r.is_nan() => f64::INFINITY,
            r => r,
        };
        Ok(CaseResult {
            op: self.op,
            category: self.category,
            shapes: self.shapes.clone(),
            max_abs_err: rep.max_abs_err(),
            max_rel_err: rep.max_rel_err(),
            f32_rel,
            passed: rep.passed() && f32_rel <= self.f32_tol,
            error: None,
        })
    }

    /// Like [`Case::run`], with an error turned into a failed result.
    pub fn run_or_fail(&self, opts: &GradcheckOptions) -> CaseResult {
        self.run(opts)
            .unwrap_or_else(|e| CaseResult::error(self.op, self.category, &self.shapes, e))
    }
}

impl CaseResult {
    /// A failed result for a check that could not run (`error` holds its message).
    pub fn error(
        op: &'static str,
        category: &'static str,
        shapes: &[Vec<usize>],
        e: impl std::fmt::Display,
    ) -> Self {
        CaseResult {
            op,
            category,
            shapes: shapes.to_vec(),
            max_abs_err: f64::INFINITY,
            max_rel_err: f64::INFINITY,
            f32_rel: f64::INFINITY,
            passed: false,
            error: Some(e.to_string()),
        }
    }
}

/// A check that is not a [`Case`]: any function returning a [`CaseResult`] (e.g. a comparison
/// with a reference gradient by cosine, or a check over a whole scene).
pub type CheckFn = Arc<dyn Fn() -> CaseResult + Send + Sync>;

/// One entry of a [`Registry`].
#[derive(Clone)]
pub enum Entry {
    /// A full-Jacobian gradcheck plus `f32`/`f64` comparison.
    Case(Case),
    /// Any other check.
    Check {
        /// Name (shown in tables, matched by filters).
        op: &'static str,
        /// Category.
        category: &'static str,
        /// The check.
        run: CheckFn,
    },
}

impl Entry {
    /// Name of the entry.
    pub fn op(&self) -> &'static str {
        match self {
            Entry::Case(c) => c.op,
            Entry::Check { op, .. } => op,
        }
    }

    /// Category of the entry.
    pub fn category(&self) -> &'static str {
        match self {
            Entry::Case(c) => c.category,
            Entry::Check { category, .. } => category,
        }
    }

    /// Whether `filter` selects this entry: its full name, its base name (before `/`), its
    /// category, or a substring of its name.
    pub fn matches(&self, filter: &str) -> bool {
        let op = self.op();
        op == filter
            || op.split('/').next() == Some(filter)
            || self.category() == filter
            || op.contains(filter)
    }

    /// Runs the entry (`opts`: the default settings of cases without their own).
    pub fn run(&self, opts: &GradcheckOptions) -> CaseResult {
        match self {
            Entry::Case(c) => c.run_or_fail(opts),
            Entry::Check { run, .. } => run(),
        }
    }
}

impl std::fmt::Debug for Entry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Entry::Case(c) => c.fmt(f),
            Entry::Check { op, category, .. } => f
                .debug_struct("Check")
                .field("op", op)
                .field("category", category)
                .finish_non_exhaustive(),
        }
    }
}

/// The list of gradient checks that `tapestry gradcheck` runs; user code adds its own cases.
#[derive(Clone, Debug, Default)]
pub struct Registry {
    entries: Vec<Entry>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// The built-in op cases ([`builtin_cases`], category `autodiff`).
    pub fn builtin() -> Self {
        let mut r = Self::new();
        for c in builtin_cases() {
            r.add(c);
        }
        r
    }

    /// Adds a case.
    pub fn add(&mut self, case: Case) -> &mut Self {
        self.entries.push(Entry::Case(case));
        self
    }

    /// Adds a check function under a name and category.
    pub fn add_check(
        &mut self,
        op: &'static str,
        category: &'static str,
        run: impl Fn() -> CaseResult + Send + Sync + 'static,
    ) -> &mut Self {
        self.entries.push(Entry::Check {
            op,
            category,
            run: Arc::new(run),
        });
        self
    }

    /// Every entry, in the order added.
    pub fn entries(&self) -> &[Entry] {
        &self.entries
    }

    /// The distinct categories, in the order first added.
    pub fn categories(&self) -> Vec<&'static str> {
        let mut out: Vec<&'static str> = Vec::new();
        for e in &self.entries {
            if !out.contains(&e.category()) {
                out.push(e.category());
            }
        }
        out
    }

    /// Runs the entries that `filter` selects ([`Entry::matches`]; all for `None`) with the
    /// default gradcheck options, in parallel, results in registry order. An empty result
    /// means that nothing matched.
    pub fn run(&self, filter: Option<&str>) -> Vec<CaseResult> {
        let opts = GradcheckOptions::default();
        let selected: Vec<&Entry> = self
            .entries
            .iter()
            .filter(|e| match filter {
                None => true,
                Some(f) => e.matches(f),
            })
            .collect();
        selected.par_iter().map(|e| e.run(&opts)).collect()
    }
}

/// Runs every built-in case whose name or base op name equals `filter` (all cases for
/// `None`) with the default gradcheck options (full mode). An empty result means that
/// nothing matched.
pub fn run_all(filter: Option<&str>) -> Vec<CaseResult> {
    let opts = GradcheckOptions::default();
    builtin_cases()
        .iter()
        .filter(|c| match filter {
            None => true,
            Some(f) => c.matches(f),
        })
        .map(|c| c.run_or_fail(&opts))
        .collect()
}

/// `[3, 4], [4]`: the input shapes of a case as one string.
pub fn shapes_str(shapes: &[Vec<usize>]) -> String {
    shapes
        .iter()
        .map(|s| format!("{s:?}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// An aligned text table: op, input shapes, max abs err, max rel err, f32 rel, pass.
pub fn render_table(results: &[CaseResult]) -> String {
    let head = [
        "op",
        "inputs",
        "max abs err",
        "max rel err",
        "f32 rel",
        "pass",
    ];
    let rows: Vec<[String; 6]> = results
        .iter()
        .map(|r| {
            [
                r.op.to_string(),
                shapes_str(&r.shapes),
                format!("{:.2e}", r.max_abs_err),
                format!("{:.2e}", r.max_rel_err),
                format!("{:.2e}", r.f32_rel),
                match (&r.error, r.passed) {
                    (Some(e), _) => format!("ERROR: {e}"),
                    (None, true) => "ok".to_string(),
                    (None, false) => "FAIL".to_string(),
                },
            ]
        })
        .collect();
    let mut w = head.map(str::len);
    for r in &rows {
        for (k, cell) in r.iter().enumerate() {
            w[k] = w[k].max(cell.len());
        }
    }
    let mut out = String::new();
    let line = |out: &mut String, cells: [&str; 6]| {
        // Text columns left-aligned, numbers right-aligned; no trailing spaces.
        let s = format!(
            "{:<w0$}  {:<w1$}  {:>w2$}  {:>w3$}  {:>w4$}  {}",
            cells[0],
            cells[1],
            cells[2],
            cells[3],
            cells[4],
            cells[5],
            w0 = w[0],
            w1 = w[1],
            w2 = w[2],
            w3 = w[3],
            w4 = w[4],
        );
        out.push_str(s.trim_end());
        out.push('\n');
    };
    line(&mut out, head);
    let rule: Vec<String> = w.iter().map(|&n| "-".repeat(n)).collect();
    line(&mut out, std::array::from_fn(|k| rule[k].as_str()));
    for r in &rows {
        line(&mut out, std::array::from_fn(|k| r[k].as_str()));
    }
    let failed = results.iter().filter(|r| !r.passed).count();
    out.push_str(&format!(
        "{} cases, {} passed, {} failed\n",
        results.len(),
        results.len() - failed,
        failed
    ));
    out
}

/// An index tensor from a shape and row-major values.
fn idx(shape: &[usize], v: &[usize]) -> ArrayD<usize> {
    ArrayD::from_shape_vec(IxDyn(shape), v.to_vec()).expect("index count matches its shape")
}

/// A checkerboard mask (true where the index sum is even).
fn checker(shape: &[usize]) -> ArrayD<bool> {
    ArrayD::from_shape_fn(IxDyn(shape), |i| i.slice().iter().sum::<usize>() % 2 == 0)
}

fn unary<'t, T: Real>(x: Var<'t, T>, k: Unary<T>) -> Var<'t, T> {
    x.tape().apply(UnaryOp(k), &[x])
}

/// Defines one case from a generic body, instantiated at `f32` and `f64`.
macro_rules! case {
    ($op:expr, [$($shape:expr),* $(,)?], [$($gen:expr),* $(,)?], |$t:ident, $x:ident| $body:expr) => {{
        #[allow(unused_variables)]
        fn f<'t, T: Real>($t: &'t Tape<T>, $x: &[Var<'t, T>]) -> Var<'t, T> {
            $body
        }
        Case::new(
            $op,
            vec![$({ let s: &[usize] = &$shape; s.to_vec() }),*],
            vec![$($gen),*],
            f::<f32>,
            f::<f64>,
        )
    }};
}

/// Every built-in case.
pub fn builtin_cases() -> Vec<Case> {
    use Gen::*;
    const U: Gen = Uniform(-1.0, 1.0);
    const POS: Gen = Uniform(0.5, 2.0);
    const AWAY: Gen = Signed(0.2, 2.0);
    vec![
        // ---- elementwise binary, with NumPy broadcasting (size-1 dims and 0-d scalars) ----
        case!("add", [[3, 4], [3, 4]], [U, U], |t, x| x[0] + x[1]),
        case!("add/bcast-1dims", [[3, 1], [1, 4]], [U, U], |t, x| x[0]
            + x[1]),
        case!("add/bcast-rank", [[2, 3, 4], [4]], [U, U], |t, x| x[0]
            + x[1]),
        case!("add/0d", [[], [2, 3]], [U, U], |t, x| x[0] + x[1]),
        case!("sub", [[3, 4], [3, 4]], [U, U], |t, x| x[0] - x[1]),
        case!("sub/bcast", [[2, 1, 3], [4, 1]], [U, U], |t, x| x[0] - x[1]),
        case!("sub/0d-0d", [[], []], [U, U], |t, x| x[0] - x[1]),
        case!("mul", [[3, 4], [3, 4]], [U, U], |t, x| x[0] * x[1]),
        case!("mul/bcast-1dims", [[2, 3, 1], [3, 4]], [U, U], |t, x| x[0]
            * x[1]),
        case!("mul/0d", [[2, 3], []], [U, U], |t, x| x[0] * x[1]),
        case!("div", [[3, 4], [3, 4]], [U, AWAY], |t, x| x[0] / x[1]),
        case!("div/bcast", [[3, 4], [3, 1]], [U, AWAY], |t, x| x[0] / x[1]),
        case!("div/0d", [[], [2, 3]], [U, AWAY], |t, x| x[0] / x[1]),
        case!(
            "pow",
            [[3, 4], [3, 4]],
            [POS, Uniform(-1.5, 1.5)],
            |t, x| x[0].pow(x[1])
        ),
        case!(
            "pow/0d-exponent",
            [[3, 4], []],
            [POS, Uniform(-1.5, 1.5)],
            |t, x| x[0].pow(x[1])
        ),
        case!(
            "pow/bcast-base",
            [[4], [3, 4]],
            [POS, Uniform(-1.5, 1.5)],
            |t, x| x[0].pow(x[1])
        ),
        case!(
            "minimum",
            [[3, 4], [3, 4]],
            [Lattice(0.0), Lattice(0.5)],
            |t, x| x[0].minimum(x[1])
        ),
        case!(
            "minimum/bcast",
            [[3, 4], [4]],
            [Lattice(0.0), Lattice(0.5)],
            |t, x| x[0].minimum(x[1])
        ),
        case!(
            "maximum",
            [[3, 4], [3, 4]],
            [Lattice(0.0), Lattice(0.5)],
            |t, x| x[0].maximum(x[1])
        ),
        case!(
            "maximum/0d",
            [[3, 4], []],
            [Lattice(0.0), Lattice(0.5)],
            |t, x| x[0].maximum(x[1])
        ),
        case!("where", [[3, 4], [3, 4]], [U, U], |t, x| x[0]
            .where_(checker(&[3, 4]), x[1])),
        case!("where/bcast", [[3, 1], [4]], [U, U], |t, x| x[0]
            .where_(checker(&[3, 4]), x[1])),
        // ---- elementwise unary ----
        case!("neg", [[3, 4]], [U], |t, x| -x[0]),
        case!("exp", [[3, 4]], [U], |t, x| x[0].exp()),
        case!("log", [[3, 4]], [POS], |t, x| x[0].ln()),
        case!("sqrt", [[3, 4]], [POS], |t, x| x[0].sqrt()),
        case!("sin", [[3, 4]], [Uniform(-3.0, 3.0)], |t, x| x[0].sin()),
        case!("cos", [[3, 4]], [Uniform(-3.0, 3.0)], |t, x| x[0].cos()),
        case!("tanh", [[3, 4]], [Uniform(-2.0, 2.0)], |t, x| x[0].tanh()),
        case!("sigmoid", [[3, 4]], [Uniform(-4.0, 4.0)], |t, x| x[0]
            .sigmoid()),
        case!("relu", [[3, 4]], [AWAY], |t, x| x[0].relu()),
        case!("abs", [[3, 4]], [AWAY], |t, x| x[0].abs()),
        case!("square", [[3, 4]], [U], |t, x| x[0].square()),
        case!("recip", [[3, 4]], [AWAY], |t, x| x[0].recip()),
        case!("clamp", [[3, 4]], [Lattice(0.0)], |t, x| x[0]
            .clamp(c(-0.5), c(0.5))),
        case!("pow_scalar", [[3, 4]], [POS], |t, x| x[0].powf(c(2.5))),
        case!("pow_scalar/negative", [[3, 4]], [POS], |t, x| x[0]
            .powf(c(-1.5))),
        case!("scalar_pow", [[3, 4]], [U], |t, x| unary(
            x[0],
            Unary::ScalarPow(c(2.5))
        )),
        // ---- scalar operands ----
        case!("add_scalar", [[3, 4]], [U], |t, x| x[0] + c::<T>(0.75)),
        case!("sub_scalar", [[3, 4]], [U], |t, x| x[0] - c::<T>(0.75)),
        case!("mul_scalar", [[3, 4]], [U], |t, x| x[0] * c::<T>(-1.5)),
        case!("div_scalar", [[3, 4]], [U], |t, x| x[0] / c::<T>(4.0)),
        case!("rsub_scalar", [[3, 4]], [U], |t, x| unary(
            x[0],
            Unary::RSubScalar(c(2.0))
        )),
        case!("rdiv_scalar", [[3, 4]], [AWAY], |t, x| unary(
            x[0],
            Unary::RDivScalar(c(2.0))
        )),
        // ---- reductions ----
        case!("sum", [[3, 4]], [U], |t, x| x[0].sum()),
        case!("sum/0d", [[]], [U], |t, x| x[0].sum()),
        case!("sum_axes", [[2, 3, 4]], [U], |t, x| x[0]
            .sum_axes(&[0, 2], false)),
        case!("sum_axes/keepdim", [[2, 3, 4]], [U], |t, x| x[0]
            .sum_axes(&[1], true)),
        case!("sum_axes/neg-axis", [[2, 3, 4]], [U], |t, x| x[0]
            .sum_axes(&[-1, 0], true)),
        case!("mean", [[3, 4]], [U], |t, x| x[0].mean()),
        case!("sum_squared_diff", [[3, 4], [3, 4]], [U, U], |t, x| x[0]
            .sum_squared_diff(x[1])),
        case!("mean_axes/keepdim", [[2, 3, 4]], [U], |t, x| x[0]
            .mean_axes(&[1], true)),
        case!("max_axis", [[3, 5]], [Distinct(-2.0, 2.0)], |t, x| x[0]
            .max_axis(1, false)),
        case!(
            "max_axis/keepdim",
            [[4, 3]],
            [Distinct(-2.0, 2.0)],
            |t, x| x[0].max_axis(0, true)
        ),
        case!("max_axis/3d", [[2, 3, 4]], [Distinct(-2.0, 2.0)], |t, x| x
            [0]
        .max_axis(-2, false)),
        case!("logsumexp", [[3, 5]], [Uniform(-2.0, 2.0)], |t, x| x[0]
            .logsumexp(1, false)),
        case!(
            "logsumexp/keepdim",
            [[4, 3]],
            [Uniform(-2.0, 2.0)],
            |t, x| x[0].logsumexp(0, true)
        ),
        // ---- matrix products ----
        case!("matmul/mat-mat", [[3, 4], [4, 2]], [U, U], |t, x| x[0]
            .matmul(x[1])),
        case!("matmul/mat-vec", [[3, 4], [4]], [U, U], |t, x| x[0]
            .matmul(x[1])),
        case!("matmul/vec-mat", [[4], [4, 3]], [U, U], |t, x| x[0]
            .matmul(x[1])),
        case!("matmul/vec-vec", [[5], [5]], [U, U], |t, x| x[0]
            .matmul(x[1])),
        case!("matmul/batched", [[2, 3, 4], [2, 4, 2]], [U, U], |t, x| x
            [0]
        .matmul(x[1])),
        case!(
            "matmul/batch-bcast-rhs",
            [[2, 3, 4], [1, 4, 2]],
            [U, U],
            |t, x| x[0].matmul(x[1])
        ),
        case!(
            "matmul/batch-bcast-lhs",
            [[1, 3, 4], [3, 4, 2]],
            [U, U],
            |t, x| x[0].matmul(x[1])
        ),
        case!("matmul/3d-2d", [[2, 3, 4], [4, 2]], [U, U], |t, x| x[0]
            .matmul(x[1])),
        // ---- shape ops ----
        case!("reshape", [[3, 4]], [U], |t, x| x[0].reshape(&[2, 6])),
        case!("reshape/flatten", [[2, 3, 2]], [U], |t, x| (x[0]
            .permute(&[2, 0, 1])
            * c::<T>(2.0))
        .reshape(&[12])),
        case!("permute", [[2, 3, 4]], [U], |t, x| x[0].permute(&[2, 0, 1])),
        case!("t", [[3, 4]], [U], |t, x| x[0].t()),
        case!("t/3d", [[2, 3, 4]], [U], |t, x| x[0].t()),
        case!("slice", [[4, 5]], [U], |t, x| x[0].slice(1, 1, 4)),
        case!("slice/axis0", [[4, 5]], [U], |t, x| x[0].slice(0, 2, 3)),
        case!("concat", [[2, 3], [1, 3], [3, 3]], [U, U, U], |t, x| t
            .concat(x, 0)),
        case!("concat/last-axis", [[2, 3], [2, 2]], [U, U], |t, x| t
            .concat(x, -1)),
        case!("stack", [[2, 3], [2, 3], [2, 3]], [U, U, U], |t, x| t
            .stack(x, 0)),
        case!("stack/new-last-axis", [[2, 3], [2, 3]], [U, U], |t, x| t
            .stack(x, -1)),
        case!("broadcast_to", [[3, 1]], [U], |t, x| x[0]
            .broadcast_to(&[2, 3, 4])),
        case!("broadcast_to/0d", [[]], [U], |t, x| x[0]
            .broadcast_to(&[2, 2])),
        // ---- indexing (repeated indices accumulate) ----
        case!("index_select", [[5, 3]], [U], |t, x| x[0]
            .index_select(0, &[4, 0, 4, 2, 0])),
        case!("index_select/axis1", [[3, 4]], [U], |t, x| x[0]
            .index_select(-1, &[3, 3, 1])),
        case!("gather", [[3, 4]], [U], |t, x| {
            x[0].gather(
                1,
                idx(&[3, 5], &[0, 3, 3, 1, 0, 2, 2, 2, 0, 1, 3, 1, 0, 1, 3]),
            )
        }),
        case!("gather/axis0", [[3, 2]], [U], |t, x| x[0]
            .gather(0, idx(&[4, 2], &[2, 0, 2, 2, 0, 1, 1, 0]))),
        case!("scatter_add", [[3, 4]], [U], |t, x| {
            x[0].scatter_add(1, idx(&[3, 4], &[0, 2, 0, 0, 1, 1, 2, 1, 2, 0, 0, 2]), 3)
        }),
        case!("scatter_add/axis0", [[4, 2]], [U], |t, x| {
            x[0].scatter_add(0, idx(&[4, 2], &[1, 0, 1, 1, 0, 2, 1, 2]), 3)
        }),
        // ---- vector ops along the last axis ----
        case!("dot", [[4, 3], [4, 3]], [U, U], |t, x| x[0].dot(x[1])),
        case!("dot/bcast", [[4, 3], [3]], [U, U], |t, x| x[0].dot(x[1])),
        case!("cross", [[4, 3], [4, 3]], [U, U], |t, x| x[0].cross(x[1])),
        case!("cross/bcast", [[3], [2, 3]], [U, U], |t, x| x[0]
            .cross(x[1])),
        case!("normalize", [[4, 3]], [Signed(0.3, 1.0)], |t, x| x[0]
            .normalize(c(1e-6))),
        case!(
            "normalize/below-eps",
            [[2, 3]],
            [Signed(0.01, 0.02)],
            |t, x| x[0].normalize(c(0.5))
        ),
        case!("norm", [[4, 3]], [Signed(0.3, 1.0)], |t, x| x[0].norm()),
        // ---- small composite graphs ----
        case!("composite/mlp", [[4, 3], [3, 5], [5]], [U, U, U], |t, x| {
            (x[0].matmul(x[1]) + x[2]).tanh().logsumexp(-1, false)
        }),
        case!(
            "composite/face-normal",
            [[3, 3], [3]],
            [U, Signed(0.5, 1.0)],
            |t, x| {
                let (v0, v1, v2) = (
                    x[0].slice(0, 0, 1),
                    x[0].slice(0, 1, 2),
                    x[0].slice(0, 2, 3),
                );
                let n = (v1 - v0).cross(v2 - v0).normalize(c(1e-9));
                n.dot(x[1].normalize(c(1e-9))).sigmoid()
            }
        ),
        case!(
            "composite/chain",
            [[3, 4], [4]],
            [Uniform(0.5, 1.5), Uniform(0.5, 1.5)],
            |t, x| ((x[0] * x[1] + c::<T>(1.0)).ln().sigmoid() / x[1]).matmul(x[1])
        ),
        // ---- fused regions (`Tape::fused`), both backward strategies, several chunks ----
        case!(
            "fused/recompute",
            [[5, 3], [5, 1], [3]],
            [U, POS, U],
            |t, x| fused_case(t, x[0], x[1], x[2], crate::fused::FusedBackward::Recompute)
        ),
        case!("fused/preaccumulate", [[5, 3], [5, 1]], [U, POS], |t, x| {
            let light =
                t.constant(crate::tensor::from_vec(&[3], vec![c(0.3), c(-0.6), c(0.9)]).unwrap());
            fused_case(
                t,
                x[0],
                x[1],
                light,
                crate::fused::FusedBackward::Preaccumulate,
            )
        }),
        case!(
            "fused/preaccumulate_forward",
            [[5, 3], [5, 1]],
            [U, POS],
            |t, x| {
                let light = t.constant(
                    crate::tensor::from_vec(&[3], vec![c(0.3), c(-0.6), c(0.9)]).unwrap(),
                );
                fused_case(
                    t,
                    x[0],
                    x[1],
                    light,
                    crate::fused::FusedBackward::PreaccumulateForward,
                )
            }
        ),
    ]
}

/// A shader-like fused region over rows (`[N, 3]`, `[N, 1]` and a broadcast `[3]`) in chunks
/// of two rows, its backward prepared by `mode` (preaccumulation needs the broadcast input
/// to be a constant).
fn fused_case<'t, T: Real>(
    t: &'t Tape<T>,
    normal: Var<'t, T>,
    scale: Var<'t, T>,
    light: Var<'t, T>,
    mode: crate::fused::FusedBackward,
) -> Var<'t, T> {
    t.set_fused_chunk(6);
    t.set_fused_backward(mode);
    let y = t.fused(|| {
        let n = normal.normalize(c(1e-9));
        let d = (n * light).sum_axes(&[-1], true);
        (d.sin() * scale.sqrt() + n.tanh()).sum_axes(&[-1], false)
    });
    (y * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_and_generators_match_inputs() {
        let cases = builtin_cases();
        let mut names: Vec<_> = cases.iter().map(|c| c.op).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), cases.len());
        for c in &cases {
            let xs = c.inputs();
            assert_eq!(xs.len(), c.shapes.len());
            for (x, s) in xs.iter().zip(&c.shapes) {
                assert_eq!(x.shape(), &s[..]);
            }
        }
    }

    #[test]
    fn generators_keep_their_margins() {
        let mut rng = Rng::new(3);
        let d = Gen::Distinct(-2.0, 2.0).sample(&mut rng, &[5, 4]);
        let mut v: Vec<f64> = d.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        assert!(v
            .windows(2)
            .all(|w| w[1] - w[0] >= 0.5 * 4.0 / 20.0 - 1e-12));
        let a = Gen::Lattice(0.0).sample(&mut rng, &[200]);
        let b = Gen::Lattice(0.5).sample(&mut rng, &[200]);
        assert!(a.iter().all(|&x| (x.abs() - 0.5).abs() >= 0.3 - 1e-12));
        assert!(a
            .iter()
            .zip(b.iter())
            .all(|(x, y)| (x - y).abs() >= 0.1 - 1e-12));
        let s = Gen::Signed(0.2, 2.0).sample(&mut rng, &[200]);
        assert!(s.iter().all(|&x| x.abs() >= 0.2) && s.iter().any(|&x| x < 0.0));
    }

    #[test]
    fn filter_selects_by_base_or_full_name() {
        let all = builtin_cases();
        let mm: Vec<_> = all.iter().filter(|c| c.matches("matmul")).collect();
        assert_eq!(mm.len(), 8);
        assert_eq!(
            all.iter().filter(|c| c.matches("matmul/mat-vec")).count(),
            1
        );
        assert_eq!(all.iter().filter(|c| c.matches("max")).count(), 0);
        assert!(run_all(Some("no-such-op")).is_empty());
    }

    #[test]
    fn registry_adds_filters_and_reports_categories() {
        let mut reg = Registry::builtin();
        let n = reg.entries().len();
        assert_eq!(n, builtin_cases().len());
        reg.add(
            case!("user/square", [[3]], [Gen::Uniform(-1.0, 1.0)], |t, x| x[0]
                * x[0])
            .in_category("user"),
        );
        reg.add_check("user/broken", "user", || CaseResult {
            op: "user/broken",
            category: "user",
            shapes: vec![],
            max_abs_err: 1.0,
            max_rel_err: 1.0,
            f32_rel: 0.0,
            passed: false,
            error: None,
        });
        assert_eq!(reg.categories(), vec!["autodiff", "user"]);
        let r = reg.run(Some("user"));
        assert_eq!(r.len(), 2);
        assert!(r[0].passed && r[0].op == "user/square" && r[0].category == "user");
        assert!(!r[1].passed);
        // Full name, base name, substring.
        assert_eq!(reg.run(Some("user/square")).len(), 1);
        assert!(reg.run(Some("matmul")).len() >= 8);
        assert!(reg.run(Some("no-such-op")).is_empty());
        // A case's own tolerances replace the defaults.
        let strict = case!("strict", [[3]], [Gen::Uniform(0.5, 1.0)], |t, x| x[0].exp())
            .with_options(GradcheckOptions {
                eps: 1e-2,
                atol: 0.0,
                rtol: 1e-12,
                ..Default::default()
            });
        assert!(!strict.run_or_fail(&GradcheckOptions::default()).passed);
    }

    #[test]
    fn table_is_aligned() {
        let r = run_all(Some("add"));
        let t = render_table(&r);
        let lines: Vec<&str> = t.lines().collect();
        assert!(lines[0].starts_with("op") && lines[0].contains("f32 rel"));
        let col = lines[0].find("max abs err").unwrap();
        assert!(lines[2..2 + r.len()].iter().all(|l| l.len() > col));
        assert!(t.contains("[3, 1], [1, 4]"));
    }
}
