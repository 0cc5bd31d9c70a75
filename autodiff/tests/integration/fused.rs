//! Fused evaluation (`Tape::fused`) against the eager tape: values and gradients on fixed and
//! random graphs of the supported ops, in f32 and f64; determinism across thread counts and
//! chunk sizes; NaN propagation, anomaly mode naming the op inside the region; fallback to the
//! eager op for ops the fuser does not handle; finite-difference checks of fused ops.
//!
//! Bounds: values are bit-identical (every node applies the eager formula in the eager order),
//! and so are the gradients of row-varying inputs when no row-invariant tensor's gradient flows
//! back into them (the fixed shader graph). Gradients of inputs broadcast over the rows are
//! summed per chunk, then over chunks: within `rtol * N * (1 + |g|)` of eager (1e-15 in f64,
//! 1e-6 in f32), and a row-varying gradient downstream of such a sum (random graphs: `x9 =
//! sum(x6)` over all rows, eager, then `max(x6, x9)` fused) inherits that rounding and is held
//! to the same bound. Gradient contributions from different ops are added in tape order, and a
//! fused op is recorded when it is materialised, so a shared input may receive them in another
//! order than eager: the difference is rounding of the terms' size (see the `Normalize` step).

use autodiff::fused::FusedBackward;
use autodiff::gradcheck::{gradcheck, GradcheckOptions};
use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::rng::Rng;
use autodiff::{AutodiffError, Pass, Real, Tape, Tensor, Var};
use proptest::prelude::*;

/// Rows of the test graphs: several chunks of the default size.
const N: usize = 3001;

/// One step of a random program over a growing list of variables.
#[derive(Clone, Debug)]
enum Step {
    Unary(u8, usize),
    Binary(u8, usize, usize),
    Square(usize),
    Where(usize, usize, u64),
    SumLast(usize, bool),
    Normalize(usize),
    /// Lanes of the last axis, chosen by the second field.
    Slice(usize, usize),
}

/// The inputs: row-varying `[N, 3]`, `[N, 1]`, `[N, 3]`, and row-invariant `[3]`, `[1]`, `[]`.
fn input_shapes() -> Vec<Vec<usize>> {
    vec![vec![N, 3], vec![N, 1], vec![N, 3], vec![3], vec![1], vec![]]
}

fn inputs<T: Real>(seed: u64) -> Vec<Tensor<T>> {
    let mut r = Rng::new(seed);
    input_shapes()
        .iter()
        .map(|s| r.uniform_tensor(s, 0.2, 1.5))
        .collect()
}

/// Applies a step (unary kinds keep values in a range where every op is finite).
fn apply<'t, T: Real>(vars: &mut Vec<Var<'t, T>>, st: &Step) {
    let c = |x: f64| T::from_f64c(x);
    let pick = |i: usize| vars[i % vars.len()];
    let v = match *st {
        Step::Unary(k, i) => {
            let x = pick(i);
            match k % 17 {
                0 => -x,
                1 => (x * c(0.3)).exp(),
                2 => (x.abs() + c(0.5)).ln(),
                3 => (x.abs() + c(0.1)).sqrt(),
                4 => x.sin(),
                5 => x.cos(),
                6 => x.tanh(),
                7 => x.sigmoid(),
                8 => (x - c(0.7)).relu(),
                9 => x.square(),
                10 => (x.abs() + c(0.5)).recip(),
                11 => -x + c(2.0),
                12 => (x.abs() + c(0.5)).powf(c(1.7)),
                13 => x.clamp(c(0.4), c(0.9)),
                14 => x / c(3.0),
                15 => (x.abs() + c(1.0)).recip() * c(1.5),
                _ => (x - c(0.7)).heaviside(),
            }
        }
        Step::Binary(k, i, j) => {
            let (a, b) = (pick(i), pick(j));
            if !small_broadcast(&a.shape(), &b.shape()) {
                return;
            }
            match k % 7 {
                0 => a + b,
                1 => a - b,
                2 => a * b,
                3 => a / (b.abs() + c(0.5)),
                4 => (a.abs() + c(0.1)).pow(b.tanh()),
                5 => a.minimum(b),
                _ => a.maximum(b),
            }
        }
        Step::Square(i) => {
            let x = pick(i);
            x * x
        }
        Step::Where(i, j, seed) => {
            let (a, b) = (pick(i), pick(j));
            let sa = a.shape();
            let sb = b.shape();
            if !small_broadcast(&sa, &sb) {
                return;
            }
            let s = broadcast(&sa, &sb).unwrap();
            let mut r = Rng::new(seed);
            let n: usize = s.iter().product();
            let m: Vec<bool> = (0..n).map(|_| r.below(2) == 1).collect();
            a.where_(ArrayD::from_shape_vec(IxDyn(&s), m).unwrap(), b)
        }
        Step::SumLast(i, keep) => {
            let x = pick(i);
            if x.ndim() == 0 {
                return;
            }
            x.sum_axes(&[-1], keep)
        }
        Step::Normalize(i) => {
            let x = pick(i);
            if x.ndim() == 0 {
                return;
            }
            // eps 1e-3, not 1e-9: at a zero vector (`x - x`) the gradient is `g / eps`, and
            // terms of that size that cancel leave rounding of that size in whichever order
            // they are added (a fused op is recorded when it is materialised, so its
            // contributions reach a shared input in another order than eager's).
            x.normalize(c(1e-3))
        }
        Step::Slice(i, s) => {
            let x = pick(i);
            let Some(&k) = x.shape().last() else {
                return;
            };
            let start = s % k;
            x.slice(-1, start, start + 1 + (s / k) % (k - start))
        }
    };
    vars.push(v);
}

/// The two shapes broadcast to at most `[N, 3]` elements and two axes.
fn small_broadcast(a: &[usize], b: &[usize]) -> bool {
    matches!(broadcast(a, b), Ok(s) if s.len() <= 2 && s.iter().product::<usize>() <= 3 * N)
}

fn broadcast(a: &[usize], b: &[usize]) -> Result<Vec<usize>, ()> {
    autodiff::tensor::broadcast_shapes("t", a, b).map_err(|_| ())
}

/// The program's loss, evaluated eagerly or fused: `sum(w * out)` over the last few
/// variables, plus their values.
struct Run<T: Real> {
    values: Vec<Tensor<T>>,
    grads: Vec<Tensor<T>>,
}

fn run<T: Real>(xs: &[Tensor<T>], prog: &[Step], fused: bool, chunk: usize) -> Run<T> {
    run_with(xs, prog, fused, chunk, FusedBackward::Auto, false)
}

/// [`run`] with the fused ops' backward strategy, and with the row-invariant inputs as
/// constants when `const_inv` (so that preaccumulation applies to every fused op).
fn run_with<T: Real>(
    xs: &[Tensor<T>],
    prog: &[Step],
    fused: bool,
    chunk: usize,
    mode: FusedBackward,
    const_inv: bool,
) -> Run<T> {
    let tape = Tape::<T>::new();
    tape.set_fused_chunk(chunk);
    tape.set_fused_backward(mode);
    let leaves: Vec<Var<'_, T>> = xs
        .iter()
        .map(|x| {
            if const_inv && x.shape().first() != Some(&N) {
                tape.constant(x.clone())
            } else {
                tape.leaf(x.clone())
            }
        })
        .collect();
    let body = || {
        let mut vars = leaves.clone();
        for st in prog {
            apply(&mut vars, st);
        }
        vars
    };
    let vars = if fused { tape.fused(body) } else { body() };
    let outs: Vec<Var<'_, T>> = vars[leaves.len()..].iter().rev().take(3).copied().collect();
    tape.materialize(&outs);
    let mut r = Rng::new(99);
    let mut loss = tape.scalar(T::zero());
    let mut values = Vec::new();
    for o in &outs {
        values.push((*o.value().unwrap()).clone());
        let w = tape.constant(r.normal_tensor(&o.shape()));
        loss = loss + (*o * w).sum();
    }
    let g = tape.backward(loss).unwrap();
    Run {
        values,
        grads: leaves.iter().map(|v| g.wrt(*v)).collect(),
    }
}

fn bits<T: Real>(t: &Tensor<T>) -> Vec<u64> {
    t.iter().map(|v| v.to_f64c().to_bits()).collect()
}

/// Asserts equal bits, reporting the first difference.
fn same_bits<T: Real>(a: &Tensor<T>, b: &Tensor<T>, what: &str) {
    assert_eq!(a.shape(), b.shape(), "{what}");
    if let Some((i, (x, y))) = a
        .iter()
        .zip(b.iter())
        .enumerate()
        .find(|(_, (x, y))| x.to_f64c().to_bits() != y.to_f64c().to_bits())
    {
        panic!("{what} ({}): element {i}: {x:?} vs {y:?}", T::NAME);
    }
}

/// Values bit for bit; gradients of row-varying inputs bit for bit where `row_bits`, all other
/// gradients within `rtol * N * (1 + |g|)` (the rounding of a sum over `N` rows).
fn compare<T: Real>(a: &Run<T>, b: &Run<T>, rtol: f64, row_bits: bool) {
    assert_eq!(a.values.len(), b.values.len());
    for (x, y) in a.values.iter().zip(&b.values) {
        same_bits(x, y, "values");
    }
    for (k, (x, y)) in a.grads.iter().zip(&b.grads).enumerate() {
        if row_bits && input_shapes()[k].first() == Some(&N) {
            same_bits(x, y, &format!("gradient of row input {k}"));
        } else {
            for (&u, &v) in x.iter().zip(y.iter()) {
                let (u, v) = (u.to_f64c(), v.to_f64c());
                assert!(
                    u.to_bits() == v.to_bits()
                        || (u - v).abs() <= rtol * (1.0 + u.abs().max(v.abs())) * N as f64,
                    "gradient of input {k}: {u} vs {v}"
                );
            }
        }
    }
}

/// Preaccumulated against eager: values bit for bit; gradients within
/// `rtol * (1 + max(|u|, |v|))` (see [`preaccumulated_random_graphs_match_eager`]), NaN where
/// eager has NaN.
fn compare_preaccumulated<T: Real>(pre: &Run<T>, eager: &Run<T>, rtol: f64) {
    for (x, y) in pre.values.iter().zip(&eager.values) {
        same_bits(x, y, "values");
    }
    for (k, (x, y)) in pre.grads.iter().zip(&eager.grads).enumerate() {
        for (&u, &v) in x.iter().zip(y.iter()) {
            let (u, v) = (u.to_f64c(), v.to_f64c());
            assert!(
                u.to_bits() == v.to_bits()
                    || (u.is_nan() && v.is_nan())
                    || (u - v).abs() <= rtol * (1.0 + u.abs().max(v.abs())),
                "gradient of input {k} ({}): {u} vs {v}",
                T::NAME
            );
        }
    }
}

fn step() -> impl Strategy<Value = Step> {
    prop_oneof![
        (any::<u8>(), any::<usize>()).prop_map(|(k, i)| Step::Unary(k, i)),
        (any::<u8>(), any::<usize>(), any::<usize>()).prop_map(|(k, i, j)| Step::Binary(k, i, j)),
        any::<usize>().prop_map(Step::Square),
        (any::<usize>(), any::<usize>(), any::<u64>()).prop_map(|(i, j, s)| Step::Where(i, j, s)),
        (any::<usize>(), any::<bool>()).prop_map(|(i, k)| Step::SumLast(i, k)),
        any::<usize>().prop_map(Step::Normalize),
        (any::<usize>(), any::<usize>()).prop_map(|(i, s)| Step::Slice(i, s)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Random graphs: fused equals eager (f64 and f32).
    #[test]
    fn random_graphs_match_eager(prog in prop::collection::vec(step(), 1..14), seed in 0u64..1000) {
        let x64 = inputs::<f64>(seed);
        compare(&run(&x64, &prog, true, 1024), &run(&x64, &prog, false, 1024), 1e-15, false);
        let x32 = inputs::<f32>(seed);
        compare(&run(&x32, &prog, true, 1024), &run(&x32, &prog, false, 1024), 1e-6, false);
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Random graphs with the row-invariant inputs as constants, every fused op preaccumulated
    /// (up to 3 outputs of up to 3 channels: several sweeps per chunk), by forward tangents and
    /// by reverse sweeps: values equal eager's bit for bit. Gradients differ from eager's by
    /// the rounding of `g * (d_L * ... * d_1)` (in either order) against eager's
    /// `((g * d_L) * ...) * d_1` along each path and of the sums where paths join against
    /// eager's one sweep: a few ulp of the largest adjoint inside the graph, which `normalize`
    /// near a zero vector makes up to `1 / eps` = 1e3 times `|g|` (its gradient
    /// `g / max(len, eps)` and the projection that cancels it). Held to `16 u / eps` of
    /// `1 + |g|` (`u` the unit roundoff).
    #[test]
    fn preaccumulated_random_graphs_match_eager(
        prog in prop::collection::vec(step(), 1..14),
        seed in 0u64..1000,
    ) {
        for pre in [FusedBackward::PreaccumulateForward, FusedBackward::PreaccumulateReverse] {
            let x64 = inputs::<f64>(seed);
            compare_preaccumulated(
                &run_with(&x64, &prog, true, 1024, pre, true),
                &run_with(&x64, &prog, false, 1024, pre, true),
                16.0 * f64::EPSILON / 2.0 * 1e3,
            );
            let x32 = inputs::<f32>(seed);
            compare_preaccumulated(
                &run_with(&x32, &prog, true, 1024, pre, true),
                &run_with(&x32, &prog, false, 1024, pre, true),
                16.0 * f64::from(f32::EPSILON) / 2.0 * 1e3,
            );
        }
    }
}

/// A fixed graph with every kind of node and broadcast (a shader-like sum of terms).
fn shader_prog() -> Vec<Step> {
    vec![
        Step::Normalize(0),       // 6: normalize [N,3]
        Step::Normalize(3),       // 7: normalize [3]
        Step::Binary(2, 6, 7),    // 8: [N,3] * [3]
        Step::SumLast(8, true),   // 9: [N,1]
        Step::Binary(1, 9, 4),    // 10: [N,1] - [1]
        Step::Unary(7, 10),       // 11: sigmoid
        Step::Binary(2, 3, 11),   // 12: [3] * [N,1]
        Step::Unary(8, 1),        // 13: relu [N,1]
        Step::Unary(12, 13),      // 14: powf
        Step::Binary(2, 14, 5),   // 15: [N,1] * []
        Step::Binary(0, 12, 15),  // 16: [N,3] + [N,1]
        Step::Where(16, 2, 5),    // 17
        Step::Square(17),         // 18
        Step::Binary(6, 18, 2),   // 19: max
        Step::SumLast(19, false), // 20: [N]
        Step::Unary(4, 20),       // 21: sin
        Step::Slice(16, 4),       // 22: lanes 1..3 of [N,3]
        Step::Unary(16, 10),      // 23: heaviside [N,1]
        Step::Binary(2, 22, 23),  // 24: [N,2] * [N,1]
    ]
}

#[test]
fn shader_graph_matches_eager_in_f64_and_f32() {
    let prog = shader_prog();
    let x = inputs::<f64>(1);
    compare(
        &run(&x, &prog, true, 1024),
        &run(&x, &prog, false, 1024),
        1e-15,
        true,
    );
    let x = inputs::<f32>(1);
    compare(
        &run(&x, &prog, true, 1024),
        &run(&x, &prog, false, 1024),
        1e-6,
        true,
    );
}

/// The 50-op chain of the benchmark (`x * 1.01`, `x + 0.5`, `sin`, `tanh`, `x * x`, ten times).
fn chain50<'t, T: Real>(x: Var<'t, T>) -> Var<'t, T> {
    let mut h = x;
    for i in 0..50 {
        h = match i % 5 {
            0 => h * T::from_f64c(1.01),
            1 => h + T::from_f64c(0.5),
            2 => h.sin(),
            3 => h.tanh(),
            _ => h * h,
        };
    }
    h
}

/// The 50-op chain of the benchmark, 1-D (one element per row), bit for bit in f32 (the
/// vectorised sin/tanh kernels) and f64, with the backward that recomputes and sweeps in
/// reverse as eager does (the default preaccumulates in forward mode: values bit for bit,
/// gradients within the bound of the next test).
#[test]
fn chain_is_bit_identical() {
    fn go<T: Real>(fused: bool) -> (Vec<u64>, Vec<u64>) {
        let mut x0: Tensor<T> = Rng::new(3).normal_tensor(&[70_001]);
        x0[[5]] = T::from_f64c(1e5); // outside the f32 polynomial range
        let tape = Tape::<T>::new();
        tape.set_fused_backward(FusedBackward::Recompute);
        let x = tape.leaf(x0);
        let y = if fused {
            tape.fused(|| chain50(x))
        } else {
            chain50(x)
        };
        assert_eq!(y.is_pending(), fused);
        let loss = y.sum();
        if fused {
            assert_eq!(tape.num_ops(), 2, "one fused op and the sum");
        }
        let g = tape.backward(loss).unwrap();
        (bits(&y.value().unwrap()), bits(g.get(x).unwrap()))
    }
    assert_eq!(go::<f32>(true), go::<f32>(false));
    assert_eq!(go::<f64>(true), go::<f64>(false));
}

/// The chain with a random output gradient `g` (the default strategy preaccumulates it, in
/// forward mode for one input and one output channel): the values bit for bit; the gradient
/// `g * ((d_1 * d_2) * ... * d_50)` against eager's `((g * d_50) * ...) * d_1` with the same
/// factors `d_k`: each within `(1 + u)^51` of the exact product, so within `102 u` of eager's
/// relative to it (u the unit roundoff).
#[test]
fn chain_with_any_output_gradient_is_within_the_bound() {
    fn go<T: Real>(fused: bool) -> (Vec<u64>, Vec<f64>) {
        let x0: Tensor<T> = Rng::new(3).normal_tensor(&[20_001]);
        let w0: Tensor<T> = Rng::new(4).normal_tensor(&[20_001]);
        let tape = Tape::<T>::new();
        let x = tape.leaf(x0);
        let w = tape.constant(w0);
        let y = if fused {
            tape.fused(|| chain50(x))
        } else {
            chain50(x)
        };
        let g = tape.backward((y * w).sum()).unwrap();
        let g = g.get(x).unwrap().iter().map(|v| v.to_f64c()).collect();
        (bits(&y.value().unwrap()), g)
    }
    fn check<T: Real>() {
        let (fused, eager) = (go::<T>(true), go::<T>(false));
        assert_eq!(fused.0, eager.0, "values");
        let u = T::EPS.to_f64c() / 2.0;
        let worst = fused
            .1
            .iter()
            .zip(&eager.1)
            .map(|(&a, &b)| {
                if a == b {
                    0.0
                } else {
                    (a - b).abs() / (b.abs() * u)
                }
            })
            .fold(0.0, f64::max);
        assert!(worst <= 102.0, "{}: {worst} u", T::NAME);
    }
    check::<f32>();
    check::<f64>();
}

/// `tanh` over chunks whose arguments are all small, all large, mixed, and mixed with a NaN
/// (the interpreter's one-sided `tanh` paths): the eager values and gradients, bit for bit.
#[test]
fn tanh_paths_match_eager() {
    let mut x0: Tensor<f32> = Rng::new(9).normal_tensor(&[4096]);
    for (i, v) in x0.iter_mut().enumerate() {
        *v = match i / 1024 {
            0 => *v * 0.1,
            1 => v.signum() * (0.7 + v.abs()),
            _ => *v,
        };
    }
    x0[[3000]] = f32::NAN;
    let go = |fused: bool| {
        let tape = Tape::<f32>::new();
        tape.set_fused_chunk(1024);
        let x = tape.leaf(x0.clone());
        let y = if fused {
            tape.fused(|| x.tanh())
        } else {
            x.tanh()
        };
        let g = tape.backward(y.sum()).unwrap();
        (bits(&y.value().unwrap()), bits(g.get(x).unwrap()))
    };
    assert_eq!(go(true), go(false));
}

/// Same bits with 1, 2 and 3 threads; same bits across chunk sizes except the gradients of
/// row-invariant inputs (their summation order follows the chunks), which stay within bound.
#[test]
fn deterministic_across_threads_and_chunk_sizes() {
    let prog = shader_prog();
    let x = inputs::<f64>(4);
    let go = |n: usize, chunk: usize| in_pool(n, || run(&x, &prog, true, chunk));
    for chunk in [1, 7, 1024, 1 << 20] {
        let one = go(1, chunk);
        for n in [2, 3] {
            assert_eq!(all_bits(&one), all_bits(&go(n, chunk)));
        }
        compare(&one, &go(1, 1024), 1e-15, true);
    }
}

/// Runs `f` in a pool of `n` threads.
fn in_pool<R: Send>(n: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(n)
        .build()
        .unwrap()
        .install(f)
}

/// The bits of a run's values and gradients.
fn all_bits<T: Real>(r: &Run<T>) -> (Vec<Vec<u64>>, Vec<Vec<u64>>) {
    (
        r.values.iter().map(bits).collect(),
        r.grads.iter().map(bits).collect(),
    )
}

/// Preaccumulated fused ops (the shader graph with constant broadcast inputs: five output
/// channels), by forward tangents and by reverse sweeps, give the same bits with 1, 2 and 3
/// threads and with every chunk size (each row's Jacobian comes from its own elements), and
/// the values and gradients of a single-channel op swept in reverse equal eager's bit for bit
/// when the output gradient is 1 (`sum`).
#[test]
fn preaccumulated_is_deterministic_across_threads_and_chunk_sizes() {
    let prog = shader_prog();
    let x = inputs::<f32>(4);
    for pre in [
        FusedBackward::PreaccumulateForward,
        FusedBackward::PreaccumulateReverse,
    ] {
        let go =
            |n: usize, chunk: usize| in_pool(n, || run_with(&x, &prog, true, chunk, pre, true));
        let reference = all_bits(&go(1, 1024));
        for chunk in [1, 7, 1024, 1 << 20] {
            for n in [1, 2, 3] {
                let got = all_bits(&go(n, chunk));
                assert_eq!(got, reference, "{pre:?}: {n} threads, chunk {chunk}");
            }
        }
    }
    // One output channel, seed 1: eager's sweep, bit for bit.
    let go = |fused: bool| {
        let tape = Tape::<f32>::new();
        tape.set_fused_backward(FusedBackward::PreaccumulateReverse);
        let a = tape.leaf(x[0].clone());
        let b = tape.leaf(x[1].clone());
        let body = || ((a * b).sin().sum_axes(&[-1], false) * 1.5).tanh();
        let y = if fused { tape.fused(body) } else { body() };
        let g = tape.backward(y.sum()).unwrap();
        (
            bits(&y.value().unwrap()),
            bits(g.get(a).unwrap()),
            bits(g.get(b).unwrap()),
        )
    };
    assert_eq!(go(true), go(false));
}

#[test]
fn nan_and_inf_propagate() {
    let tape = Tape::<f64>::new();
    let x = tape.leaf(ArrayD::from_shape_vec(IxDyn(&[4]), vec![1.0, -1.0, 0.0, 2.0]).unwrap());
    let y = tape.fused(|| (x.ln() + 1.0) * 2.0);
    let v = y.value().unwrap();
    assert_eq!(v[[0]], 2.0);
    assert!(v[[1]].is_nan());
    assert_eq!(v[[2]], f64::NEG_INFINITY);
    let g = tape.backward(y.sum()).unwrap();
    let g = g.get(x).unwrap();
    assert_eq!(g[[0]], 2.0);
    assert_eq!(g[[2]], f64::INFINITY);
}

/// Anomaly mode names the op inside the region that made the first non-finite value, with the
/// node id and input shapes the eager tape reports.
#[test]
fn anomaly_names_the_op_inside_a_region() {
    let report = |fused: bool, backward: bool| {
        let tape = Tape::<f64>::new();
        tape.set_detect_anomaly(true);
        let x = tape.leaf(
            ArrayD::from_shape_vec(IxDyn(&[2, 3]), vec![1.0, 2.0, -3.0, 4.0, 5.0, 6.0]).unwrap(),
        );
        let z = tape.leaf(ArrayD::from_shape_vec(IxDyn(&[3]), vec![0.0, 1.0, 2.0]).unwrap());
        let body = || {
            let a = x * 2.0 + 1.0;
            if backward {
                // sqrt(0) is finite forward, its gradient is infinite.
                (a * z.sqrt()).sum_axes(&[-1], false)
            } else {
                (a.sin() * x.ln()).exp()
            }
        };
        let y = if fused { tape.fused(body) } else { body() };
        let e = match y.value() {
            Err(e) => e,
            Ok(_) => tape.backward(y.sum()).unwrap_err(),
        };
        e
    };
    for backward in [false, true] {
        let eager = report(false, backward);
        let fused = report(true, backward);
        assert_eq!(fused, eager, "backward {backward}");
        let want_pass = if backward {
            Pass::Backward
        } else {
            Pass::Forward
        };
        assert!(
            matches!(&fused, AutodiffError::Anomaly { pass, .. } if *pass == want_pass),
            "{fused}"
        );
    }
    let AutodiffError::Anomaly { op, .. } = report(true, false) else {
        unreachable!()
    };
    assert_eq!(op, "log");
}

/// Anomaly mode names the op inside a preaccumulated region (one input and one output
/// channel, the default strategy picks preaccumulation) as the eager tape does: `sqrt(x * x)`
/// at `x = 0` is finite forward and its backward infinite.
#[test]
fn anomaly_names_the_op_inside_a_preaccumulated_region() {
    let report = |fused: bool| {
        let tape = Tape::<f64>::new();
        tape.set_detect_anomaly(true);
        let mut x0: Tensor<f64> = Rng::new(2).normal_tensor(&[2000]);
        x0[[1500]] = 0.0;
        let x = tape.leaf(x0);
        let body = || ((x * x).sqrt() * 3.0).tanh();
        let y = if fused { tape.fused(body) } else { body() };
        y.value().unwrap();
        tape.backward(y.sum()).unwrap_err()
    };
    let eager = report(false);
    assert_eq!(report(true), eager);
    assert!(
        matches!(
            &eager,
            AutodiffError::Anomaly {
                op: "sqrt",
                pass: Pass::Backward,
                ..
            }
        ),
        "{eager}"
    );
}

/// An op the fuser does not handle (a matmul, a full sum, a reshape) computes the pending graph
/// before it and runs eagerly; the result equals the eager tape's.
#[test]
fn unsupported_ops_fall_back_to_eager() {
    let go = |fused: bool| {
        let tape = Tape::<f64>::new();
        let x = tape.leaf(Rng::new(5).normal_tensor(&[64, 3]));
        let m = tape.leaf(Rng::new(6).normal_tensor(&[3, 3]));
        let body = || {
            let a = (x * 1.5).tanh();
            let b = a.matmul(m); // not fused
            let c = (b + a).reshape(&[3, 64]).t(); // not fused
            let d = c.sigmoid() * a;
            d.sum_axes(&[0], false) + d.sum() // sum over a row axis, full sum: not fused
        };
        let y = if fused { tape.fused(body) } else { body() };
        let g = tape.backward(y.sum()).unwrap();
        (
            bits(&y.value().unwrap()),
            bits(g.get(x).unwrap()),
            bits(g.get(m).unwrap()),
        )
    };
    assert_eq!(go(true), go(false));
}

/// Shape errors inside a region are reported as eagerly, naming the op.
#[test]
fn bad_inputs_report_the_eager_error() {
    let tape = Tape::<f64>::new();
    let a = tape.leaf(Tensor::zeros(IxDyn(&[3, 2])));
    let b = tape.leaf(Tensor::zeros(IxDyn(&[4, 2])));
    let e = tape.fused(|| (a.exp() + b).value().unwrap_err());
    assert!(e.to_string().contains("add"), "{e}");
    let tape = Tape::<f64>::new();
    let a = tape.leaf(Tensor::zeros(IxDyn(&[3, 2])));
    let e = tape.fused(|| a.clamp(1.0, 0.0).value().unwrap_err());
    assert!(e.to_string().contains("clamp"), "{e}");
}

/// Finite differences on fused ops: the shader graph's gradient with respect to every input.
#[test]
fn gradcheck_fused_ops() {
    let small =
        |s: &[usize]| -> Vec<usize> { s.iter().map(|&d| if d == N { 5 } else { d }).collect() };
    let mut r = Rng::new(8);
    let xs: Vec<Tensor<f64>> = input_shapes()
        .iter()
        .map(|s| r.uniform_tensor(&small(s), 0.2, 1.5))
        .collect();
    let prog = shader_prog();
    let report = gradcheck(
        |t: &Tape<f64>, v: &[Var<'_, f64>]| {
            t.set_fused_chunk(4); // several chunks even at 5 rows
            let out = t.fused(|| {
                let mut vars = v.to_vec();
                for st in &prog {
                    apply(&mut vars, st);
                }
                vars
            });
            let last = out.len() - 1;
            t.materialize(&out[last - 2..]);
            let mut loss = t.scalar(0.0);
            for (k, o) in out[last - 2..].iter().enumerate() {
                loss = loss + (*o * (k as f64 + 1.5)).sin().sum();
            }
            loss
        },
        &xs,
        &GradcheckOptions::default(),
    )
    .unwrap();
    assert!(report.passed(), "{report}");
}

/// Pending variables report their shape without being computed; reading one computes it.
#[test]
fn pending_variables_have_shapes() {
    let tape = Tape::<f32>::new();
    let x = tape.leaf(Tensor::ones(IxDyn(&[10, 3])));
    let (y, z) = tape.fused(|| {
        let y = x.normalize(1e-6);
        (y, y.sum_axes(&[-1], false))
    });
    assert!(y.is_pending() && z.is_pending());
    assert_eq!(y.shape(), vec![10, 3]);
    assert_eq!(z.shape(), vec![10]);
    assert_eq!(z.len(), 10);
    assert_eq!(tape.num_ops(), 0);
    tape.materialize(&[y, z]);
    assert!(!y.is_pending() && !z.is_pending());
    assert_eq!(tape.num_ops(), 1);
    let s = 3f32.sqrt().recip();
    assert!((z.value().unwrap()[[0]] - 3.0 * s).abs() < 1e-6);
}

/// A step has no gradient: eager and fused, its output does not require one, and a loss that
/// reaches the input only through it leaves the input's gradient zero.
#[test]
fn heaviside_records_no_gradient() {
    let tape = Tape::<f64>::new();
    let x = tape.leaf(ArrayD::from_shape_vec(IxDyn(&[4, 1]), vec![-1.0, 0.0, 0.5, 2.0]).unwrap());
    let eager = x.heaviside();
    assert!(!eager.requires_grad());
    assert_eq!(
        eager.value().unwrap().iter().copied().collect::<Vec<_>>(),
        vec![0.0, 0.0, 1.0, 1.0]
    );
    let fused = tape.fused(|| {
        let y = (x * 2.0).heaviside();
        assert!(!y.requires_grad());
        y * x
    });
    let g = tape.backward(fused.sum()).unwrap();
    assert_eq!(
        g.wrt(x).iter().copied().collect::<Vec<_>>(),
        vec![0.0, 0.0, 1.0, 1.0]
    );
}
