//! Tape benchmarks: per-op overhead, an elementwise chain against the copy bandwidth bound, and
//! a 3DMM linear model against the memory bound of reading its basis twice.
//!
//! ```text
//! RAYON_NUM_THREADS=1 cargo bench -p tapestry-autodiff --bench tape -- --warm-up-time 1 --measurement-time 3
//! RAYON_NUM_THREADS=2 cargo bench -p tapestry-autodiff --bench tape -- --warm-up-time 1 --measurement-time 3
//! ```
//!
//! (a) `scalar_chain`: record + backward of 10,000 ops on 0-d (and `[1]`) values; criterion's
//!     throughput line gives the time per op.
//! (b) `chain50`: 50 elementwise ops over 1e6 f32 cycling `[x * 1.01, x + 0.5, sin, tanh, x * x]`
//!     (as PyTorch's `bench_autograd_micro.py`), then `sum` and backward. Its least memory
//!     traffic, counted in passes over a 4 MB tensor (one read or one write of 1e6 f32):
//!     forward 50 x (read + write) + sum's read = 101; backward: the seed's write 1, per
//!     5-op cycle `x * x` 3 (read g, read x, write), `tanh` 3, `sin` 3, `x + 0.5` 2,
//!     `x * 1.01` 2, so 10 x 13 = 130; in all 232 passes = 928 MB. `copy_bound` copies a
//!     4 MB buffer 116 times (116 x (read + write) = 232 passes) around a 256 MB ring of
//!     buffers, larger than the last-level cache, so that it streams from memory as the chain
//!     (whose 50 saved activations take 200 MB) does.
//!     `fused_forward_backward_1e6_f32` runs the chain inside `Tape::fused` (one fused op);
//!     `fused_forward_no_grad_1e6_f32` its forward alone (the 50 ops' arithmetic, in cache).
//! (c) `3dmm`: `y = mean + B a` with V = 35,000 vertices, B = [3V, K] = [105000, 199] f32 (a
//!     constant shared with the tape, not copied), K = 199, loss `sum((y - target)^2)` (as
//!     PyTorch's benchmark) and its gradient with respect to `a`. The memory bound is reading
//!     B twice (forward `B a`, backward `B^T g`): 2 x 83.6 MB; `read_b_twice` measures that
//!     directly (two parallel summing passes over B, AVX2 where available).
//!
//! The parallel cases (b, c) run each iteration inside a rayon pool with its idle workers
//! polling (`Frames`), as the render benches' frames run and as PyTorch's OpenMP regions start
//! on the calling thread; the bounds are measured the same way.

use std::hint::black_box;
use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::rng::Rng;
use autodiff::tensor::scalar;
use autodiff::{Tape, Tensor, Var};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use rayon::prelude::*;

const SCALAR_OPS: usize = 10_000;

/// Runs each timed iteration of the parallel cases as the render benches run a frame: on a
/// worker of a rayon pool (`RAYON_NUM_THREADS` threads), so that a step's parallel
/// regions start on the calling thread, as an OpenMP region does on PyTorch's, instead of being
/// handed from the main thread to the pool and back (two thread wake-ups per region), with the
/// pool's other workers polling for work meanwhile (`autodiff::ActiveWait`, as in the render
/// benches' `frame_in`).
struct Frames(rayon::ThreadPool);

impl Frames {
    fn new() -> Self {
        Frames(
            rayon::ThreadPoolBuilder::new()
                .build()
                .expect("thread pool"),
        )
    }

    fn run<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.0.install(|| {
            let _hot = autodiff::ActiveWait::new();
            f()
        })
    }
}

fn scalar_chain_ops<'t>(x: Var<'t, f32>, w: Var<'t, f32>) -> Var<'t, f32> {
    let mut h = x;
    for i in 0..SCALAR_OPS {
        h = match i % 5 {
            0 => h * 1.01f32,
            1 => h + 0.5f32,
            2 => h.sin(),
            3 => h.tanh(),
            _ => h * w,
        };
    }
    h
}

fn bench_scalar_chain(c: &mut Criterion) {
    let mut g = c.benchmark_group("scalar_chain");
    g.throughput(Throughput::Elements(SCALAR_OPS as u64));
    for (name, shape) in [("0d", &[][..]), ("1", &[1][..])] {
        let x0: Tensor<f32> = ArrayD::from_elem(IxDyn(shape), 0.5);
        let w0: Tensor<f32> = ArrayD::from_elem(IxDyn(shape), 0.9);
        g.bench_function(format!("record_backward_10k_ops_{name}"), |b| {
            b.iter(|| {
                let tape = Tape::<f32>::with_capacity(SCALAR_OPS + 2);
                let x = tape.leaf(x0.clone());
                let w = tape.leaf(w0.clone());
                let h = scalar_chain_ops(x, w);
                let grads = tape.backward(h).unwrap();
                black_box(grads.get(x).map(|t| t.sum()))
            })
        });
        g.bench_function(format!("record_only_10k_ops_{name}"), |b| {
            b.iter(|| {
                let tape = Tape::<f32>::with_capacity(SCALAR_OPS + 2);
                let x = tape.leaf(x0.clone());
                let w = tape.leaf(w0.clone());
                black_box(scalar_chain_ops(x, w).item().unwrap())
            })
        });
    }
    g.bench_function("backward_only_10k_ops_0d", |b| {
        let tape = Tape::<f32>::with_capacity(SCALAR_OPS + 2);
        let x = tape.leaf(scalar(0.5));
        let w = tape.leaf(scalar(0.9));
        let h = scalar_chain_ops(x, w);
        b.iter(|| black_box(tape.backward(h).unwrap().get(x).map(|t| t.sum())))
    });
    g.finish();
}

const CHAIN_N: usize = 1_000_000;

fn chain50<'t>(x: Var<'t, f32>) -> Var<'t, f32> {
    let mut h = x;
    for i in 0..50 {
        h = match i % 5 {
            0 => h * 1.01f32,
            1 => h + 0.5f32,
            2 => h.sin(),
            3 => h.tanh(),
            _ => h * h,
        };
    }
    h
}

/// Copies `src` into `dst` (in parallel chunks when the pool has several threads).
fn par_copy(dst: &mut [f32], src: &[f32]) {
    dst.par_chunks_mut(1 << 16)
        .zip(src.par_chunks(1 << 16))
        .for_each(|(d, s)| d.copy_from_slice(s));
}

fn bench_chain50(c: &mut Criterion) {
    let mut g = c.benchmark_group("chain50");
    g.sample_size(10);
    let x0: Tensor<f32> = Rng::new(0).normal_tensor(&[CHAIN_N]);
    let frames = Frames::new();
    g.bench_function("forward_backward_1e6_f32", |b| {
        b.iter(|| {
            frames.run(|| {
                let tape = Tape::<f32>::new();
                let x = tape.leaf(x0.clone());
                let loss = chain50(x).sum();
                let grads = tape.backward(loss).unwrap();
                black_box(grads.get(x).map(|t| t[[0]]))
            })
        })
    });
    // The same chain inside `Tape::fused`: one fused op, evaluated in cache-sized chunks
    // (one input and one output channel: the forward reads x, writes y and carries the tangent
    // dy/dx beside the values, which it keeps; the backward is g * dy/dx).
    g.bench_function("fused_forward_backward_1e6_f32", |b| {
        b.iter(|| {
            frames.run(|| {
                let tape = Tape::<f32>::new();
                let x = tape.leaf(x0.clone());
                let loss = tape.fused(|| chain50(x)).sum();
                let grads = tape.backward(loss).unwrap();
                black_box(grads.get(x).map(|t| t[[0]]))
            })
        })
    });
    // Its forward alone (no gradient asked): the arithmetic of the 50 ops in cache.
    g.bench_function("fused_forward_no_grad_1e6_f32", |b| {
        b.iter(|| {
            frames.run(|| {
                let tape = Tape::<f32>::new();
                let x = tape.constant(x0.clone());
                black_box(tape.fused(|| chain50(x)).sum().item().unwrap())
            })
        })
    });
    g.bench_function("forward_no_grad_1e6_f32", |b| {
        b.iter(|| {
            frames.run(|| {
                let tape = Tape::<f32>::new();
                let x = tape.constant(x0.clone());
                black_box(chain50(x).sum().item().unwrap())
            })
        })
    });
    // 64 buffers of 4 MB = 256 MB, more than the last-level cache.
    let mut ring: Vec<Vec<f32>> = (0..64).map(|i| vec![i as f32; CHAIN_N]).collect();
    let mut at = 0usize;
    g.bench_function("copy_bound_116x4MB", |b| {
        b.iter(|| {
            frames.run(|| {
                for _ in 0..116 {
                    let (s, d) = (at % 64, (at + 1) % 64);
                    let (lo, hi) = ring.split_at_mut(d.max(s));
                    let (src, dst) = if s < d {
                        (&lo[s], &mut hi[0])
                    } else {
                        (&hi[0], &mut lo[d])
                    };
                    par_copy(dst, src);
                    at += 1;
                }
                black_box(ring[at % 64][7])
            })
        })
    });
    g.finish();
}

const V: usize = 35_000;
const K: usize = 199;

/// The 3DMM's residual `mean + B a - target` on `tape`, with `B`, `mean` and `target` shared
/// (not copied) and not requiring a gradient.
fn residual<'t>(
    tape: &'t Tape<f32>,
    [basis, mean, target]: [&Arc<Tensor<f32>>; 3],
    a: Var<'t, f32>,
) -> Var<'t, f32> {
    let shared = |x: &Arc<Tensor<f32>>| tape.var_shared(x.clone(), false);
    shared(mean) + shared(basis).matmul(a) - shared(target)
}

fn bench_3dmm(c: &mut Criterion) {
    let mut g = c.benchmark_group("3dmm");
    g.sample_size(20);
    let mut r = Rng::new(0);
    let frames = Frames::new();
    let basis: Arc<Tensor<f32>> = Arc::new(r.normal_tensor::<f32>(&[3 * V, K]).mapv(|v| v * 1e-3));
    let mean: Arc<Tensor<f32>> = Arc::new(r.normal_tensor(&[3 * V]));
    let target: Arc<Tensor<f32>> = Arc::new(r.normal_tensor(&[3 * V]));
    let alpha: Tensor<f32> = r.normal_tensor(&[K]);
    g.bench_function("forward_backward_V35000_K199", |b| {
        b.iter(|| {
            frames.run(|| {
                let tape = Tape::<f32>::new();
                let a = tape.leaf(alpha.clone());
                let loss = residual(&tape, [&basis, &mean, &target], a).square().sum();
                let grads = tape.backward(loss).unwrap();
                black_box(grads.get(a).map(|t| t[[0]]))
            })
        })
    });
    g.bench_function("forward_no_grad_V35000_K199", |b| {
        b.iter(|| {
            frames.run(|| {
                let tape = Tape::<f32>::new();
                let a = tape.constant(alpha.clone());
                let r = residual(&tape, [&basis, &mean, &target], a);
                black_box(r.square().sum().item().unwrap())
            })
        })
    });
    let bs = basis.as_slice().unwrap();
    g.bench_function("read_b_twice_bound", |b| {
        b.iter(|| {
            frames.run(|| {
                let mut total = 0.0f32;
                for _ in 0..2 {
                    total += bs.par_chunks(1 << 16).map(sum_f32).sum::<f32>();
                }
                black_box(total)
            })
        })
    });
    g.finish();
}

/// A plain summing read, the fastest this machine streams `f32` from memory: 4 x 8-lane AVX2
/// accumulators where the CPU has them (the bound must not be slower than the kernels it
/// bounds, which use AVX2), else 16 interleaved scalar sums.
fn sum_f32(xs: &[f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        #[target_feature(enable = "avx2")]
        unsafe fn wide(xs: &[f32]) -> f32 {
            use std::arch::x86_64::*;
            let mut it = xs.chunks_exact(32);
            let mut a = [_mm256_setzero_ps(); 4];
            for c in &mut it {
                for (j, aj) in a.iter_mut().enumerate() {
                    // SAFETY: 8 lanes inside the 32-value chunk.
                    *aj = _mm256_add_ps(*aj, unsafe { _mm256_loadu_ps(c.as_ptr().add(8 * j)) });
                }
            }
            let s = _mm256_add_ps(_mm256_add_ps(a[0], a[1]), _mm256_add_ps(a[2], a[3]));
            let mut lanes = [0.0f32; 8];
            // SAFETY: 8 lanes into an 8-value array.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), s) };
            lanes.iter().sum::<f32>() + it.remainder().iter().sum::<f32>()
        }
        // SAFETY: the CPU has AVX2.
        return unsafe { wide(xs) };
    }
    let mut acc = [0.0f32; 16];
    let mut it = xs.chunks_exact(16);
    for c in &mut it {
        for (a, v) in acc.iter_mut().zip(c) {
            *a += v;
        }
    }
    acc.iter().sum::<f32>() + it.remainder().iter().sum::<f32>()
}

criterion_group!(benches, bench_scalar_chain, bench_chain50, bench_3dmm);
criterion_main!(benches);
