//! Fused evaluation of elementwise graphs: inside [`crate::Tape::fused`], elementwise and
//! broadcast ops (unary, binary, `where`, `x * x`, sums, normalisation and slices over a short
//! last axis) are not computed but recorded as nodes of a small expression graph. When a value is
//! needed (read, fed to an op the fuser does not handle, or asked for with
//! [`crate::Tape::materialize`]) the graph behind it becomes ONE tape op, [`FusedOp`], that
//! evaluates it chunk by chunk, so that a chunk's intermediates stay in cache and are never
//! written to memory. Its backward is prepared in one of two ways ([`FusedBackward`]): it
//! recomputes each chunk's forward in cache and runs the chain rule there (the op stores only
//! its inputs and outputs: checkpointing at chunk granularity), or, for ops with few input and
//! output channels, the forward also computes the per-row Jacobian (preaccumulation, by
//! forward-mode tangents or by reverse sweeps with unit seeds) and keeps it, so that the
//! backward is `g J`.
//!
//! Layout: every node is either *row-varying* (its axis 0 is the fused op's row axis of length
//! `N`, the outputs' first dimension, sliced into chunks of whole rows) or *row-invariant* (it
//! does not depend on the row, and is recomputed whole in every chunk: small vectors such as a
//! light direction). Chunk boundaries depend only on the shapes and the chunk size, never on
//! the thread count, so results are deterministic for any rayon pool.
//!
//! Accuracy against the eager tape: every node applies the eager op's per-element formula in
//! the same order (the f32 polynomial kernels of `vmath` where the eager op uses them), so
//! values are bit-identical in f32 and f64, and so are the gradients of row-varying inputs.
//! The gradient of a row-invariant input broadcast over rows (a colour `[3]` times `[N, 3]`) is
//! summed per chunk (in independent partial sums, so that the sum vectorises) and the chunk
//! sums are added in chunk order, where eager sums all `N` rows in one sequence: the two orders
//! differ by rounding only (for `n` rows, within the usual `n eps` relative bound of a sum).
//!
//! Broadcasts are read without index maps where they have a shape of their own: one value per
//! row spread over the row (`[N, 1]` as `[N, 3]`), and the same values on every row (`[3]` as
//! `[N, 3]`); lane loops of width 1 to 4 (sums, normalisation) are compiled for their width, so
//! that they vectorise across rows. A row-varying gradient that depends on such a sum (the
//! tape reduces `x` over all rows to `s`, and a fused op uses `s` again with `x`) inherits the
//! rounding and is equal to the same bound, not bit for bit. A fused op is recorded on the tape
//! when it is materialised, so contributions from several ops may reach a shared input in another
//! order than on the eager tape: equal up to the rounding of those terms' sum.
//!
//! A preaccumulated gradient is `g * (d_L * ... * d_1)` (the reverse sweep's products with
//! seed 1, or the tangents' `(d_1 * d_2) * ... * d_L`, then the output gradient) where eager
//! computes `((g * d_L) * ...) * d_1` with the same factors: bit for bit when `g` = 1 (a `sum`
//! after the op) and the sweep is reverse, otherwise within `2 (L + 1) u` relative along a
//! chain of `L` ops (`u` the unit roundoff); where paths join, the sums `sum_o g_o J_o` (and
//! the tangents' sums) round in another order than eager's single sweep, so the difference is
//! a few ulp of the largest adjoint inside the graph (which `normalize` near a zero vector
//! makes up to `1 / eps` times `|g|`). Gradients of row inputs stay bit-identical across
//! thread counts and chunk sizes (each row's Jacobian comes from its own elements).

// Kernels index re-sliced slices of one length (`&a[..n]`): bounds checks vanish and the
// loops vectorise.
#![allow(clippy::needless_range_loop)]

use std::borrow::Cow;

use rayon::prelude::*;
use smallvec::SmallVec;

use crate::error::{AutodiffError, Pass, Result};
use crate::ops::elementwise::{heaviside, sigmoid, Binary, Unary};
use crate::tape::{BackwardCtx, Op};
use crate::tensor::{Tensor, TensorView, PAR_MIN_LEN};
use crate::Real;

/// Elements per chunk by default (per row-varying node; with ~50 nodes of f32 this keeps a
/// chunk's values within a 256 KiB L2 share).
pub const DEFAULT_CHUNK: usize = 1024;

/// Widest last axis a fused reduction (`sum_axes(&[-1])`, `normalize`) accepts.
pub const MAX_LANE: usize = 8;

/// Largest row-invariant node (elements) the fuser recomputes in every chunk.
const INV_MAX: usize = 4096;

/// Most input channels (elements per row of the inputs that require a gradient) of a fused op
/// that [`FusedBackward::Auto`] preaccumulates.
pub const PREACC_MAX_IN: usize = 4;

/// How a fused op prepares its backward.
///
/// - `Recompute`: the op keeps only its inputs and outputs; the backward recomputes each
///   chunk's forward in cache, then sweeps it in reverse (checkpointing at chunk granularity).
/// - `Preaccumulate`: the forward computes each chunk's per-row Jacobian `d out / d in`
///   (`n_in x n_out` values per row, Griewank & Walther, *Evaluating Derivatives*, 2nd ed.,
///   2008, sec. 10.2 "preaccumulation") and keeps it; the backward is the product `g J`,
///   memory-bound, with no recompute. The Jacobian comes from whichever direction needs
///   fewer passes: forward-mode tangents, one per input channel, each node's computed right
///   after its value while that is in cache (a `sin`, `cos`, `tanh`, `exp` or `sigmoid` in
///   the same loop as its value, when there is one input channel), or reverse sweeps after the
///   chunk's forward, one per output channel with a unit seed (ties: forward).
///   Only for ops whose inputs that require a gradient all vary by row (a per-row Jacobian
///   with respect to a broadcast input would need its sum over rows deferred to the seed).
/// - `Auto` (default): `Preaccumulate` when the op has one output channel (`[N]` or `[N, 1]`
///   outputs, one per row, that carry a gradient) and at most [`PREACC_MAX_IN`] input
///   channels: one pass per input channel or one sweep in the forward replaces the
///   backward's recompute plus a sweep, and its Jacobian (at most 4 values per row) is no
///   more bytes than the inputs a recompute reads again. `Recompute` otherwise.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FusedBackward {
    /// Preaccumulate by the rule above.
    #[default]
    Auto,
    /// Always recompute in the backward.
    Recompute,
    /// Preaccumulate wherever the inputs allow it, in the direction with fewer sweeps
    /// (tests and measurements).
    Preaccumulate,
    /// Preaccumulate wherever the inputs allow it, by forward-mode tangents (one per input
    /// channel, carried beside the values).
    PreaccumulateForward,
    /// Preaccumulate wherever the inputs allow it, by reverse sweeps (one per output channel,
    /// after each chunk's forward).
    PreaccumulateReverse,
}

/// What a recorded node computes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Kind<T> {
    Unary(Unary<T>),
    Binary(Binary),
    /// `x * x` of one variable (the eager `MulSelfOp`).
    MulSelf,
    /// `where(mask, a, b)`; the mask is the first argument, a non-differentiable 0/1 tensor.
    Select,
    /// Sum over the last axis (`keepdim`).
    SumLast(bool),
    /// `x / max(|x|, eps)` along the last axis.
    Normalize(T),
    /// Lanes `start..end` of the last axis (`x[..., start..end]`: a shader's `n.x`).
    SliceLast(usize, usize),
}

impl<T: Real> Kind<T> {
    pub(crate) fn name(&self) -> &'static str {
        match self {
            Kind::Unary(u) => u.name(),
            Kind::Binary(b) => b.name(),
            Kind::MulSelf => "mul",
            Kind::Select => "where",
            Kind::SumLast(_) => "sum",
            Kind::Normalize(_) => "normalize",
            Kind::SliceLast(..) => "slice",
        }
    }
}

/// An argument of a node in a [`Dag`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Arg {
    /// A materialised tape variable (index into [`Dag::ext_shapes`]).
    Ext(usize),
    /// Non-differentiable data owned by the op (index into [`Dag::data`]).
    Data(usize),
    /// An earlier node.
    Node(usize),
}

/// One node of a [`Dag`].
pub(crate) struct DagNode<T> {
    pub slot: u32,
    pub kind: Kind<T>,
    pub args: SmallVec<[Arg; 3]>,
    pub shape: Vec<usize>,
    pub rg: bool,
}

/// The pending graph behind some targets, as the tape hands it to [`plan`]: nodes in
/// creation (topological) order.
pub(crate) struct Dag<T> {
    pub nodes: Vec<DagNode<T>>,
    pub ext_shapes: Vec<Vec<usize>>,
    /// Whether each tape input requires a gradient.
    pub ext_rg: Vec<bool>,
    pub data: Vec<Tensor<T>>,
    /// Node indices of the outputs.
    pub targets: Vec<usize>,
}

/// How a node reads an argument in a chunk.
#[derive(Clone, Debug)]
enum Access {
    /// Same local layout as the node's output.
    Full,
    /// A single value broadcast everywhere.
    Scalar,
    /// One value per row, spread over the row's `w` elements (`[N, 1]` read as `[N, 3]`).
    Spread,
    /// The same `w` values on every row, `map[j]` of the argument (a `[3]` colour read as
    /// `[N, 3]`).
    Tile { map: Vec<u32> },
    /// General broadcast: output element `r * w + j` reads argument element
    /// `r * rstride + map[j]`.
    Expand { map: Vec<u32>, rstride: usize },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Src {
    /// External: tape input or data (inputs first).
    Ext(usize),
    Node(usize),
}

struct PNode<T> {
    kind: Kind<T>,
    args: SmallVec<[(Src, Access); 3]>,
    row: bool,
    /// Elements per row when row-varying, all elements otherwise.
    w: usize,
    /// Lane width of reductions (the argument's last axis).
    lane: usize,
    live: bool,
    slot: u32,
    arg_shapes: Vec<Vec<usize>>,
}

#[derive(Clone, Copy)]
struct ExtInfo {
    row: bool,
    w: usize,
}

/// One output channel of a preaccumulated op: lane `lane` of the `w` elements per row of
/// output `out` (node `node`).
#[derive(Clone, Copy)]
struct Channel {
    out: usize,
    node: usize,
    lane: usize,
    w: usize,
}

/// The preaccumulation plan of a fused op and, once the forward ran, its Jacobians.
struct Preacc<T> {
    channels: Vec<Channel>,
    /// The inputs whose Jacobian is kept (they require a gradient and reach an output).
    needs: Vec<bool>,
    /// The input channels `(input, lane)` of the inputs in `needs`, in order.
    inputs: Vec<(usize, usize)>,
    /// Forward mode: one tangent per input channel, carried beside the values node by node
    /// (when there are no more input channels than output channels); else one reverse sweep
    /// per output channel after the forward.
    tangents: bool,
    /// Per input `k` with `needs[k]`: `d out_o / d in_k[c]` at index `(r * n_out + o) * w_k + c`
    /// for row `r`, output channel `o`, input lane `c`.
    jac: Vec<Option<Vec<T>>>,
}

/// The tape op of a fused region (see the module docs).
pub struct FusedOp<T: Real> {
    nodes: Vec<PNode<T>>,
    ext: Vec<ExtInfo>,
    n_in: usize,
    data: Vec<Vec<T>>,
    out_nodes: Vec<usize>,
    out_shapes: Vec<Vec<usize>>,
    ext_live: Vec<bool>,
    n_rows: usize,
    rows_per_chunk: usize,
    anomaly: bool,
    preacc: Option<Preacc<T>>,
}

/// `shape` padded with leading ones to `rank`.
fn padded(shape: &[usize], rank: usize) -> Vec<usize> {
    let mut p = vec![1; rank - shape.len()];
    p.extend_from_slice(shape);
    p
}

/// Access of an argument `a` (shape, row) by an elementwise node of `out` (shape, row).
fn access(out: &[usize], out_row: bool, a: &[usize], a_row: bool) -> Access {
    let alen: usize = a.iter().product();
    if a == out && a_row == out_row {
        return Access::Full;
    }
    if alen == 1 && !a_row {
        return Access::Scalar;
    }
    let r = out.len();
    let p = padded(a, r);
    // Row-major strides of the padded argument, zero along broadcast axes.
    let mut strides = vec![0usize; r];
    let mut s = 1;
    for d in (0..r).rev() {
        strides[d] = if p[d] == 1 && out[d] != 1 { 0 } else { s };
        s *= p[d];
    }
    let first = usize::from(out_row);
    let inner = &out[first..];
    let w: usize = inner.iter().product();
    let mut map = Vec::with_capacity(w);
    let mut idx = vec![0usize; inner.len()];
    for _ in 0..w {
        let off: usize = idx
            .iter()
            .zip(&strides[first..])
            .map(|(&i, &st)| i * st)
            .sum();
        map.push(off as u32);
        for d in (0..inner.len()).rev() {
            idx[d] += 1;
            if idx[d] < inner[d] {
                break;
            }
            idx[d] = 0;
        }
    }
    let rstride = if out_row && a_row { strides[0] } else { 0 };
    if rstride == 0 {
        Access::Tile { map }
    } else if rstride == 1 && map.iter().all(|&m| m == 0) {
        Access::Spread
    } else {
        Access::Expand { map, rstride }
    }
}

/// Runs `$body` with the lane width `$k` bound to a constant for the common widths 1 to 4
/// (loops over a lane then unroll, and vectorise across rows), else to its runtime value.
macro_rules! with_lane {
    ($k:ident, $body:expr) => {
        match $k {
            1 => {
                let $k = 1;
                $body
            }
            2 => {
                let $k = 2;
                $body
            }
            3 => {
                let $k = 3;
                $body
            }
            4 => {
                let $k = 4;
                $body
            }
            _ => $body,
        }
    };
}

/// `o[r * w + j] = a[r]`: one value per row spread over its `w` elements.
#[inline(always)]
fn spread<T: Real>(o: &mut [T], a: &[T], w: usize) {
    with_lane!(w, {
        for (o, &v) in o.chunks_exact_mut(w).zip(a) {
            o.iter_mut().for_each(|o| *o = v);
        }
    })
}

/// `o[r] = ((0 + x[r w]) + x[r w + 1]) + ...`: each row's `w` values summed in order (the
/// eager sum over the last axis, and the eager reduction of a spread gradient).
#[inline(always)]
fn sum_rows<T: Real>(o: &mut [T], x: &[T], w: usize) {
    with_lane!(w, {
        for (o, lane) in o.iter_mut().zip(x.chunks_exact(w)) {
            let mut acc = T::zero();
            for &v in lane {
                acc += v;
            }
            *o = acc;
        }
    })
}

/// Lanes of the blocked column sums in [`sum_columns`] (a multiple of every lane width 1 to 4,
/// 6, 8, 12 and 16).
const COL_BLOCK: usize = 48;

/// `r[map[j]] += sum_rows x[row * w + j]` (`r` zeroed by the caller), the reduction of a tiled
/// gradient: blocks of `COL_BLOCK` values are added lane-wise into independent partial sums
/// (vectorised), folded in lane order, then the rows left over. A fixed order for a chunk, not
/// the eager row-by-row order: the difference is rounding (module docs).
#[inline(always)]
fn sum_columns<T: Real>(r: &mut [T], x: &[T], map: &[u32]) {
    let w = map.len();
    let mut rest = x;
    if COL_BLOCK.is_multiple_of(w) && x.len() >= 2 * COL_BLOCK {
        let mut acc = [T::zero(); COL_BLOCK];
        let mut blocks = x.chunks_exact(COL_BLOCK);
        for b in &mut blocks {
            for (a, &v) in acc.iter_mut().zip(b) {
                *a += v;
            }
        }
        for (i, &a) in acc.iter().enumerate() {
            r[map[i % w] as usize] += a;
        }
        rest = blocks.remainder();
    }
    for row in rest.chunks_exact(w) {
        for (&v, &m) in row.iter().zip(map) {
            r[m as usize] += v;
        }
    }
}

/// The sum of `x` (a scalar's broadcast gradient): in order for short `x`, else in
/// [`crate::tensor::sum_slice`]'s fixed vectorised order.
#[inline(always)]
fn sum_all<T: Real>(x: &[T]) -> T {
    if x.len() < 64 {
        let mut a = T::zero();
        for &v in x {
            a += v;
        }
        return a;
    }
    crate::tensor::sum_slice(x)
}

/// Plans the fused op of `dag`, or `None` when its shapes do not fit the row/chunk scheme
/// (the caller then evaluates the nodes eagerly).
pub(crate) fn plan<T: Real>(
    dag: Dag<T>,
    chunk: usize,
    anomaly: bool,
    mode: FusedBackward,
) -> Option<FusedOp<T>> {
    let nn = dag.nodes.len();
    let n_in = dag.ext_shapes.len();
    let first = &dag.nodes[dag.targets[0]].shape;
    let n_rows = if first.is_empty() { 1 } else { first[0] };
    // Empty outputs (no fragments in view) have no rows to chunk: eager ops handle them.
    if dag
        .targets
        .iter()
        .any(|&t| dag.nodes[t].shape.iter().product::<usize>() == 0)
    {
        return None;
    }
    for &t in &dag.targets {
        let s = &dag.nodes[t].shape;
        if s.is_empty() != first.is_empty() || (!s.is_empty() && s[0] != n_rows) {
            return None;
        }
    }
    let rowed = n_rows > 1;
    // Roles, assigned from the outputs down: None = not yet reached.
    let mut role: Vec<Option<bool>> = vec![None; nn];
    let mut ext_role: Vec<Option<bool>> = vec![None; n_in + dag.data.len()];
    for &t in &dag.targets {
        role[t] = Some(rowed);
    }
    let ext_shape = |a: Arg| -> &[usize] {
        match a {
            Arg::Ext(k) => &dag.ext_shapes[k],
            Arg::Data(d) => dag.data[d].shape(),
            Arg::Node(j) => &dag.nodes[j].shape,
        }
    };
    for j in (0..nn).rev() {
        let node = &dag.nodes[j];
        let row = role[j]?;
        for &a in &node.args {
            let s = ext_shape(a);
            let want = if !row {
                false
            } else {
                match node.kind {
                    Kind::SumLast(_) | Kind::Normalize(_) | Kind::SliceLast(..) => {
                        if s.len() < 2 {
                            return None;
                        }
                        true
                    }
                    _ => s.len() == node.shape.len() && s[0] == n_rows,
                }
            };
            let slot = match a {
                Arg::Ext(k) => &mut ext_role[k],
                Arg::Data(d) => &mut ext_role[n_in + d],
                Arg::Node(i) => &mut role[i],
            };
            match *slot {
                None => *slot = Some(want),
                Some(r) if r != want => return None,
                _ => {}
            }
        }
    }
    // Sizes: row-invariant nodes are recomputed per chunk.
    let mut inv_total = 0usize;
    let mut max_w = 1usize;
    for (j, n) in dag.nodes.iter().enumerate() {
        let len: usize = n.shape.iter().product();
        if role[j] == Some(true) {
            max_w = max_w.max(len / n_rows.max(1));
        } else {
            inv_total += len;
        }
    }
    if rowed && inv_total > INV_MAX {
        return None;
    }
    let rows_per_chunk = if rowed {
        (chunk.max(1) / max_w).max(1)
    } else {
        1
    };
    let n_chunks = n_rows.div_ceil(rows_per_chunk).max(1);
    let ext: Vec<ExtInfo> = (0..n_in + dag.data.len())
        .map(|k| {
            let s: &[usize] = if k < n_in {
                &dag.ext_shapes[k]
            } else {
                dag.data[k - n_in].shape()
            };
            let len: usize = s.iter().product();
            let row = ext_role[k] == Some(true);
            ExtInfo {
                row,
                w: if row { len / n_rows } else { len },
            }
        })
        .collect();
    // Per-chunk partial gradients of row-invariant inputs must stay small.
    let inv_in: usize = (0..n_in).filter(|&k| !ext[k].row).map(|k| ext[k].w).sum();
    if rowed && inv_in.saturating_mul(n_chunks) > 1 << 24 {
        return None;
    }
    // Liveness for the backward: a node's gradient is nonzero only along rg nodes.
    let mut live = vec![false; nn];
    for &t in &dag.targets {
        live[t] = dag.nodes[t].rg;
    }
    for j in (0..nn).rev() {
        if !live[j] {
            continue;
        }
        for &a in &dag.nodes[j].args {
            if let Arg::Node(i) = a {
                live[i] |= dag.nodes[i].rg;
            }
        }
    }
    let mut ext_live = vec![false; n_in];
    let mut nodes = Vec::with_capacity(nn);
    for (j, n) in dag.nodes.iter().enumerate() {
        let row = role[j] == Some(true);
        let len: usize = n.shape.iter().product();
        let w = if row { len / n_rows } else { len };
        let mut args = SmallVec::new();
        let mut arg_shapes = Vec::new();
        let mut lane = 1;
        for &a in &n.args {
            let s = ext_shape(a);
            arg_shapes.push(s.to_vec());
            let (src, arow) = match a {
                Arg::Ext(k) => {
                    if live[j] {
                        ext_live[k] = true;
                    }
                    (Src::Ext(k), ext[k].row)
                }
                Arg::Data(d) => (Src::Ext(n_in + d), ext[n_in + d].row),
                Arg::Node(i) => (Src::Node(i), role[i] == Some(true)),
            };
            let acc = match n.kind {
                Kind::SumLast(_) | Kind::Normalize(_) | Kind::SliceLast(..) => {
                    lane = *s.last().expect("checked at record time");
                    Access::Full
                }
                _ => access(&n.shape, row, s, arow),
            };
            args.push((src, acc));
        }
        nodes.push(PNode {
            kind: n.kind,
            args,
            row,
            w,
            lane,
            live: live[j],
            slot: n.slot,
            arg_shapes: arg_shapes
                .into_iter()
                .enumerate()
                .filter(|&(k, _)| !(n.kind == Kind::Select && k == 0))
                .map(|(_, s)| s)
                .collect(),
        });
    }
    let preacc = preaccumulation(&dag, &ext, &ext_live, rowed, &nodes, mode);
    Some(FusedOp {
        nodes,
        ext,
        n_in,
        data: dag
            .data
            .into_iter()
            .map(|d| d.as_standard_layout().iter().copied().collect())
            .collect(),
        out_nodes: dag.targets.clone(),
        out_shapes: dag
            .targets
            .iter()
            .map(|&t| dag.nodes[t].shape.clone())
            .collect(),
        ext_live,
        n_rows,
        rows_per_chunk,
        anomaly,
        preacc,
    })
}

/// The preaccumulation plan of a fused op under `mode` (see [`FusedBackward`]), or `None`
/// when its backward recomputes.
fn preaccumulation<T: Real>(
    dag: &Dag<T>,
    ext: &[ExtInfo],
    ext_live: &[bool],
    rowed: bool,
    nodes: &[PNode<T>],
    mode: FusedBackward,
) -> Option<Preacc<T>> {
    if mode == FusedBackward::Recompute || !rowed {
        return None;
    }
    let needs: Vec<bool> = (0..ext_live.len())
        .map(|k| ext_live[k] && dag.ext_rg[k])
        .collect();
    if needs.iter().zip(ext).any(|(&n, e)| n && !e.row) {
        return None;
    }
    let n_in: usize = needs
        .iter()
        .zip(ext)
        .filter(|(&n, _)| n)
        .map(|(_, e)| e.w)
        .sum();
    let mut channels = Vec::new();
    for (out, &node) in dag.targets.iter().enumerate() {
        let nd = &nodes[node];
        if nd.live {
            channels.extend((0..nd.w).map(|lane| Channel {
                out,
                node,
                lane,
                w: nd.w,
            }));
        }
    }
    let auto = channels.len() == 1 && n_in <= PREACC_MAX_IN;
    if n_in == 0 || channels.is_empty() || (mode == FusedBackward::Auto && !auto) {
        return None;
    }
    let inputs: Vec<(usize, usize)> = (0..needs.len())
        .filter(|&k| needs[k])
        .flat_map(|k| (0..ext[k].w).map(move |lane| (k, lane)))
        .collect();
    Some(Preacc {
        tangents: match mode {
            FusedBackward::PreaccumulateForward => true,
            FusedBackward::PreaccumulateReverse => false,
            _ => inputs.len() <= channels.len(),
        },
        channels,
        needs,
        inputs,
        jac: Vec::new(),
    })
}

/// An operand of a kernel: a slice of the output's length, or one value.
#[derive(Clone, Copy)]
enum Opd<'a, T> {
    S(&'a [T]),
    C(T),
}

impl<T: Real> Opd<'_, T> {
    #[inline(always)]
    fn at(&self, i: usize) -> T {
        match *self {
            Opd::S(s) => s[i],
            Opd::C(c) => c,
        }
    }
}

/// `o[i] = f(a[i], b[i])`, with the scalar cases as their own loops (vectorisable).
#[inline(always)]
fn ew2<T: Real>(o: &mut [T], a: Opd<T>, b: Opd<T>, f: impl Fn(T, T) -> T) {
    let n = o.len();
    match (a, b) {
        (Opd::S(a), Opd::S(b)) => {
            let (a, b) = (&a[..n], &b[..n]);
            for i in 0..n {
                o[i] = f(a[i], b[i]);
            }
        }
        (Opd::S(a), Opd::C(b)) => {
            let a = &a[..n];
            for i in 0..n {
                o[i] = f(a[i], b);
            }
        }
        (Opd::C(a), Opd::S(b)) => {
            let b = &b[..n];
            for i in 0..n {
                o[i] = f(a, b[i]);
            }
        }
        (Opd::C(a), Opd::C(b)) => o.iter_mut().for_each(|o| *o = f(a, b)),
    }
}

/// `o[i] = f(g[i], a[i], b[i])`.
#[inline(always)]
fn ew3<T: Real>(o: &mut [T], g: &[T], a: Opd<T>, b: Opd<T>, f: impl Fn(T, T, T) -> T) {
    let n = o.len();
    let g = &g[..n];
    match (a, b) {
        (Opd::S(a), Opd::S(b)) => {
            let (a, b) = (&a[..n], &b[..n]);
            for i in 0..n {
                o[i] = f(g[i], a[i], b[i]);
            }
        }
        (Opd::S(a), Opd::C(b)) => {
            let a = &a[..n];
            for i in 0..n {
                o[i] = f(g[i], a[i], b);
            }
        }
        (Opd::C(a), Opd::S(b)) => {
            let b = &b[..n];
            for i in 0..n {
                o[i] = f(g[i], a, b[i]);
            }
        }
        (Opd::C(a), Opd::C(b)) => {
            for i in 0..n {
                o[i] = f(g[i], a, b);
            }
        }
    }
}

/// `o[i] = f(x[i])` with the fast `f32` kernel where `ok`, `exact` elsewhere (as the eager
/// `map1_fast`).
#[inline(always)]
fn ew1_fast<T: Real>(
    o: &mut [T],
    x: &[T],
    fast: impl Fn(T) -> T,
    ok: impl Fn(T) -> bool,
    exact: impl Fn(T) -> T,
) {
    let n = o.len();
    let x = &x[..n];
    if T::FAST_MATH {
        for i in 0..n {
            o[i] = fast(x[i]);
        }
        if !x.iter().fold(true, |acc, &v| acc & ok(v)) {
            for i in 0..n {
                if !ok(x[i]) {
                    o[i] = exact(x[i]);
                }
            }
        }
    } else {
        for i in 0..n {
            o[i] = exact(x[i]);
        }
    }
}

/// `o[i] = f(g[i], x[i])` fast where `ok(x)`, exact elsewhere (as the eager `map2_fast`).
#[inline(always)]
fn ew2_fast<T: Real>(
    o: &mut [T],
    g: &[T],
    x: &[T],
    fast: impl Fn(T, T) -> T,
    ok: impl Fn(T) -> bool,
    exact: impl Fn(T, T) -> T,
) {
    let n = o.len();
    let (g, x) = (&g[..n], &x[..n]);
    if T::FAST_MATH {
        for i in 0..n {
            o[i] = fast(g[i], x[i]);
        }
        if !x.iter().fold(true, |acc, &v| acc & ok(v)) {
            for i in 0..n {
                if !ok(x[i]) {
                    o[i] = exact(g[i], x[i]);
                }
            }
        }
    } else {
        for i in 0..n {
            o[i] = exact(g[i], x[i]);
        }
    }
}

#[inline(always)]
fn unary_fwd<T: Real>(k: Unary<T>, o: &mut [T], x: &[T]) {
    let z = T::zero();
    let x = Opd::S(x);
    let d = Opd::C(z);
    match k {
        Unary::Neg => ew2(o, x, d, |v, _| -v),
        Unary::Exp => ew1_fast(o, at_s(x), T::k_exp, T::k_exp_ok, T::exp),
        Unary::Log => ew2(o, x, d, |v, _| v.ln()),
        Unary::Sqrt => ew2(o, x, d, |v, _| v.sqrt()),
        Unary::Sin => ew1_fast(o, at_s(x), T::k_sin, T::k_trig_ok, T::sin),
        Unary::Cos => ew1_fast(o, at_s(x), T::k_cos, T::k_trig_ok, T::cos),
        Unary::Tanh => ew1_fast(o, at_s(x), T::k_tanh, |v| !v.is_nan(), T::tanh),
        Unary::Sigmoid => ew1_fast(o, at_s(x), T::k_sigmoid, |v| (-v.abs()).k_exp_ok(), sigmoid),
        Unary::Relu => ew2(o, x, d, |v, z| if v < z { z } else { v }),
        Unary::Abs => ew2(o, x, d, |v, _| v.abs()),
        Unary::Square => ew2(o, x, d, |v, _| v * v),
        Unary::Recip => ew2(o, x, d, |v, _| v.recip()),
        Unary::AddScalar(c) => ew2(o, x, Opd::C(c), |v, c| v + c),
        Unary::MulScalar(c) => ew2(o, x, Opd::C(c), |v, c| v * c),
        Unary::RSubScalar(c) => ew2(o, x, Opd::C(c), |v, c| c - v),
        Unary::RDivScalar(c) => ew2(o, x, Opd::C(c), |v, c| c / v),
        Unary::PowScalar(c) => ew2(o, x, Opd::C(c), |v, c| v.powf(c)),
        Unary::ScalarPow(c) => ew2(o, x, Opd::C(c), |v, c| c.powf(v)),
        Unary::Clamp(lo, hi) => ew2(o, x, d, |v, _| {
            if v < lo {
                lo
            } else if v > hi {
                hi
            } else {
                v
            }
        }),
        Unary::Heaviside => ew2(o, x, d, |v, _| heaviside(v)),
    }
}

/// `o = sin x` and `put(i, cos x)` (with `cos`: `o = cos x`, `put(i, sin x)`) from one
/// argument reduction: the bits of `unary_fwd`'s `sin` and `cos` (fast kernels where
/// `k_trig_ok`, libm elsewhere), with the derivative's factor handed to `put` (kept for the
/// backward sweep, or multiplied into a tangent at once).
#[inline(always)]
fn sincos_fwd<T: Real>(o: &mut [T], x: &[T], cos: bool, mut put: impl FnMut(usize, T)) {
    let n = o.len();
    let x = &x[..n];
    let pick = |(s, c): (T, T)| if cos { (c, s) } else { (s, c) };
    let exact = |v: T| pick((v.sin(), v.cos()));
    if T::FAST_MATH {
        for i in 0..n {
            let d;
            (o[i], d) = pick(x[i].k_sincos());
            put(i, d);
        }
        if !x.iter().fold(true, |acc, &v| acc & v.k_trig_ok()) {
            for i in 0..n {
                if !x[i].k_trig_ok() {
                    let d;
                    (o[i], d) = exact(x[i]);
                    put(i, d);
                }
            }
        }
    } else {
        for i in 0..n {
            let d;
            (o[i], d) = exact(x[i]);
            put(i, d);
        }
    }
}

/// `o = f(x)` and the tangent `to = der(t, x, o)` in one loop, with the fast `f32` kernel where
/// `ok` and `exact` elsewhere (as [`ew1_fast`]).
#[inline(always)]
fn ew1_fast_tangent<T: Real>(
    (o, to): (&mut [T], &mut [T]),
    (x, t): (&[T], &[T]),
    fast: impl Fn(T) -> T,
    ok: impl Fn(T) -> bool,
    exact: impl Fn(T) -> T,
    der: impl Fn(T, T, T) -> T,
) {
    let n = o.len();
    let (to, x, t) = (&mut to[..n], &x[..n], &t[..n]);
    if !T::FAST_MATH {
        for i in 0..n {
            o[i] = exact(x[i]);
            to[i] = der(t[i], x[i], o[i]);
        }
        return;
    }
    for i in 0..n {
        o[i] = fast(x[i]);
        to[i] = der(t[i], x[i], o[i]);
    }
    if !x.iter().fold(true, |acc, &v| acc & ok(v)) {
        for i in 0..n {
            if !ok(x[i]) {
                o[i] = exact(x[i]);
                to[i] = der(t[i], x[i], o[i]);
            }
        }
    }
}

/// `o = f(x)` and `to = t f'(x)` in one pass for the unary ops whose value is a polynomial
/// kernel (`sin`, `cos`, `tanh`, `exp`, `sigmoid`): the tangent's loads, product and store
/// run beside the polynomial's arithmetic instead of in a pass of their own. The factors are
/// `unary_bwd`'s, so the bits equal the value pass followed by the tangent pass. `false`
/// (nothing written) for the other ops.
#[inline(always)]
fn unary_fwd_tangent<T: Real>(
    k: Unary<T>,
    (o, to): (&mut [T], &mut [T]),
    x: &[T],
    t: &[T],
) -> bool {
    let one = T::one();
    match k {
        Unary::Sin | Unary::Cos => {
            let to = &mut to[..o.len()];
            let t = &t[..o.len()];
            if k == Unary::Cos {
                sincos_fwd(o, x, true, |i, s| to[i] = -t[i] * s);
            } else {
                sincos_fwd(o, x, false, |i, c| to[i] = t[i] * c);
            }
        }
        Unary::Tanh => ew1_fast_tangent(
            (o, to),
            (x, t),
            T::k_tanh,
            |v| !v.is_nan(),
            T::tanh,
            |g, _, y| g * (one - y * y),
        ),
        Unary::Exp => {
            ew1_fast_tangent((o, to), (x, t), T::k_exp, T::k_exp_ok, T::exp, |g, _, y| {
                g * y
            })
        }
        Unary::Sigmoid => ew1_fast_tangent(
            (o, to),
            (x, t),
            T::k_sigmoid,
            |v| (-v.abs()).k_exp_ok(),
            sigmoid,
            |g, _, y| g * y * (one - y),
        ),
        _ => return false,
    }
    true
}

#[inline(always)]
fn at_s<T>(x: Opd<'_, T>) -> &[T] {
    match x {
        Opd::S(s) => s,
        Opd::C(_) => unreachable!("unary arguments are full slices"),
    }
}

/// The input's gradient contribution of a unary node (the eager `UnaryOp::grad` formulas).
#[inline(always)]
fn unary_bwd<T: Real>(k: Unary<T>, o: &mut [T], g: &[T], x: &[T], y: &[T]) {
    let (z, one, two) = (T::zero(), T::one(), T::one() + T::one());
    let (xs, ys) = (Opd::S(x), Opd::S(y));
    let d = Opd::C(z);
    match k {
        Unary::Neg => ew3(o, g, d, d, |g, _, _| -g),
        Unary::Exp => ew3(o, g, ys, d, |g, y, _| g * y),
        Unary::Log => ew3(o, g, xs, d, |g, x, _| g / x),
        Unary::Sqrt => ew3(o, g, ys, d, |g, y, _| g / (two * y)),
        Unary::Sin => ew2_fast(
            o,
            g,
            x,
            |g, x| g * x.k_cos(),
            |x| x.k_trig_ok(),
            |g, x| g * x.cos(),
        ),
        Unary::Cos => ew2_fast(
            o,
            g,
            x,
            |g, x| -g * x.k_sin(),
            |x| x.k_trig_ok(),
            |g, x| -g * x.sin(),
        ),
        Unary::Tanh => ew3(o, g, ys, d, |g, y, _| g * (one - y * y)),
        Unary::Sigmoid => ew3(o, g, ys, d, |g, y, _| g * y * (one - y)),
        Unary::Relu => ew3(o, g, xs, d, |g, x, z| if x > z { g } else { z }),
        Unary::Abs => ew3(o, g, xs, d, |g, x, z| {
            g * x.signum() * T::from_f64c((x != z) as u8 as f64)
        }),
        Unary::Square => ew3(o, g, xs, d, |g, x, _| two * g * x),
        Unary::Recip => ew3(o, g, ys, d, |g, y, _| -g * y * y),
        Unary::AddScalar(_) => ew3(o, g, d, d, |g, _, _| g),
        Unary::MulScalar(c) => ew3(o, g, d, d, |g, _, _| g * c),
        Unary::RSubScalar(_) => ew3(o, g, d, d, |g, _, _| -g),
        Unary::RDivScalar(_) => ew3(o, g, xs, ys, |g, x, y| -g * y / x),
        Unary::PowScalar(c) => ew3(o, g, xs, d, |g, x, z| {
            if c == z {
                z
            } else {
                g * c * x.powf(c - one)
            }
        }),
        Unary::ScalarPow(c) => ew3(o, g, ys, d, |g, y, _| g * y * c.ln()),
        Unary::Clamp(lo, hi) => ew3(
            o,
            g,
            xs,
            d,
            |g, x, z| {
                if x >= lo && x <= hi {
                    g
                } else {
                    z
                }
            },
        ),
        Unary::Heaviside => ew3(o, g, d, d, |_, _, z| z),
    }
}

/// `o = g * d` for `sin` (`d = cos x`, kept by the forward) and `o = -g * d` for `cos`
/// (`d = sin x`): the sweep's product with the derivative's kept factor.
#[inline(always)]
fn sincos_bwd<T: Real>(cos: bool, o: &mut [T], g: &[T], d: &[T]) {
    let (d, z) = (Opd::S(d), Opd::C(T::zero()));
    if cos {
        ew3(o, g, d, z, |g, s, _| -g * s)
    } else {
        ew3(o, g, d, z, |g, c, _| g * c)
    }
}

/// `o = 2 g x`, the derivative of `x * x` (as the eager `MulSelfOp`: `t = g x; t + t`).
#[inline(always)]
fn mulself_bwd<T: Real>(o: &mut [T], g: &[T], x: Opd<T>) {
    ew3(o, g, x, Opd::C(T::zero()), |g, x, _| {
        let t = g * x;
        t + t
    })
}

/// `o = (g - y (y . g)) / |x|` per lane group of `k` (`g / eps` where `|x| <= eps`): the
/// product of `g` with the Jacobian of `y = x / max(|x|, eps)`, which is symmetric, so the
/// same formula gives the reverse sweep's `g J` and the forward tangent `J t`.
#[inline(always)]
fn normalize_bwd<T: Real>(o: &mut [T], g: &[T], x: &[T], y: &[T], k: usize, eps: T) {
    with_lane!(k, {
        for (((o, x), y), g) in o
            .chunks_exact_mut(k)
            .zip(x.chunks_exact(k))
            .zip(y.chunks_exact(k))
            .zip(g.chunks_exact(k))
        {
            let len = x.iter().map(|&v| v * v).sum::<T>().sqrt();
            if len > eps {
                let yg: T = y.iter().zip(g.iter()).map(|(&a, &b)| a * b).sum();
                for ((o, &yv), &gv) in o.iter_mut().zip(y).zip(g) {
                    *o = (gv - yv * yg) / len;
                }
            } else {
                for (o, &gv) in o.iter_mut().zip(g) {
                    *o = gv / eps;
                }
            }
        }
    });
}

/// `o[r, ..] = x[r, a..b]` for rows of `k` lanes (`x[..., a..b]`, and its tangent).
#[inline(always)]
fn slice_lanes<T: Real>(o: &mut [T], x: &[T], k: usize, (a, b): (usize, usize)) {
    for (o, lane) in o.chunks_exact_mut(b - a).zip(x.chunks_exact(k)) {
        o.copy_from_slice(&lane[a..b]);
    }
}

/// A unit seed for one channel: `rows` rows of `w` values, 1 at `lane` and 0 elsewhere.
fn unit_seed<T: Real>(v: &mut Vec<T>, rows: usize, w: usize, lane: usize) {
    let seed = sized(v, rows * w);
    if w == 1 {
        seed.fill(T::one());
    } else {
        seed.fill(T::zero());
        seed[lane..]
            .iter_mut()
            .step_by(w)
            .for_each(|v| *v = T::one());
    }
}

#[inline(always)]
fn binary_fwd<T: Real>(k: Binary, o: &mut [T], a: Opd<T>, b: Opd<T>) {
    let half = T::from_f64c(0.5);
    match k {
        Binary::Add => ew2(o, a, b, |x, y| x + y),
        Binary::Sub => ew2(o, a, b, |x, y| x - y),
        Binary::Mul => ew2(o, a, b, |x, y| x * y),
        Binary::Div => ew2(o, a, b, |x, y| x / y),
        Binary::Pow => ew2(o, a, b, |x, y| x.powf(y)),
        Binary::Min => ew2(o, a, b, |x, y| {
            if x < y {
                x
            } else if y < x {
                y
            } else {
                half * (x + y)
            }
        }),
        Binary::Max => ew2(o, a, b, |x, y| {
            if x > y {
                x
            } else if y > x {
                y
            } else {
                half * (x + y)
            }
        }),
    }
}

/// Gradient contribution to argument `k` of a binary node (the eager `BinaryOp::grads`
/// formulas), in the output's layout.
#[inline(always)]
fn binary_bwd<T: Real>(kind: Binary, k: usize, o: &mut [T], g: &[T], a: Opd<T>, b: Opd<T>) {
    let (z, one, half) = (T::zero(), T::one(), T::from_f64c(0.5));
    match (kind, k) {
        (Binary::Add, _) | (Binary::Sub, 0) => ew3(o, g, a, b, |g, _, _| g),
        (Binary::Sub, _) => ew3(o, g, a, b, |g, _, _| -g),
        (Binary::Mul, 0) => ew3(o, g, a, b, |g, _, b| g * b),
        (Binary::Mul, _) => ew3(o, g, a, b, |g, a, _| g * a),
        (Binary::Div, 0) => ew3(o, g, a, b, |g, _, b| g / b),
        (Binary::Div, _) => ew3(o, g, a, b, |g, a, b| -g * a / (b * b)),
        (Binary::Pow, 0) => ew3(
            o,
            g,
            a,
            b,
            |g, a, b| {
                if b == z {
                    z
                } else {
                    g * b * a.powf(b - one)
                }
            },
        ),
        (Binary::Pow, _) => ew3(
            o,
            g,
            a,
            b,
            |g, a, b| {
                if a == z {
                    z
                } else {
                    g * a.powf(b) * a.ln()
                }
            },
        ),
        (Binary::Min | Binary::Max, _) => {
            let want_less = (kind == Binary::Min) == (k == 0);
            ew3(o, g, a, b, |g, a, b| {
                if a == b {
                    g * half
                } else if (a < b) == want_less {
                    g
                } else {
                    z
                }
            })
        }
    }
}

/// An argument's values `base` read in a node's layout (local length `n`, `w` elements per
/// row) through its access: the slice itself, one value, or a broadcast expanded into `buf`.
#[inline(always)]
fn gather<'a, T: Real>(
    base: &'a [T],
    acc: &Access,
    n: usize,
    w: usize,
    buf: &'a mut Vec<T>,
) -> Opd<'a, T> {
    match acc {
        Access::Full => Opd::S(base),
        Access::Scalar if n > 1 => Opd::C(base[0]),
        Access::Scalar => Opd::S(&base[..1]),
        Access::Spread => {
            spread(sized(buf, n), base, w);
            Opd::S(&buf[..])
        }
        Access::Tile { map } => {
            // The first row, then doubling copies (one row pattern for every row).
            let o = sized(buf, n);
            for (o, &m) in o.iter_mut().zip(map) {
                *o = base[m as usize];
            }
            let mut filled = map.len().min(n);
            while filled < n {
                let c = filled.min(n - filled);
                o.copy_within(0..c, filled);
                filled += c;
            }
            Opd::S(&buf[..])
        }
        Access::Expand { map, rstride } => {
            let o = sized(buf, n);
            let rows = n / w.max(1);
            for r in 0..rows {
                let src = &base[r * rstride..];
                for (o, &m) in o[r * w..(r + 1) * w].iter_mut().zip(map) {
                    *o = src[m as usize];
                }
            }
            Opd::S(&buf[..])
        }
    }
}

/// [`Scratch::tat`] of a tangent known to be zero.
const ZERO: u32 = u32::MAX;

/// What a chunk's forward computes besides the values.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Keep {
    /// The values only.
    Values,
    /// The factors a reverse sweep reuses (`cos x` of a live `sin`, `sin x` of `cos`).
    Derivs,
    /// Those, and the forward-mode tangents of the preaccumulation, node by node.
    Tangents,
}

/// Per-thread buffers of the chunk interpreter.
struct Scratch<T> {
    vals: Vec<Vec<T>>,
    /// Derivatives kept by a forward for the sweep that follows (`cos x` of a `sin` node);
    /// `dset` flags the nodes that have one.
    derivs: Vec<Vec<T>>,
    dset: Vec<bool>,
    grads: Vec<Vec<T>>,
    gset: Vec<bool>,
    egrads: Vec<Vec<T>>,
    eset: Vec<bool>,
    exp: [Vec<T>; 3],
    tmp: Vec<T>,
    red: Vec<T>,
    /// Forward-mode tangents (preaccumulation with [`Preacc::tangents`]): `d node_j / d
    /// channel q` on the chunk is `tans[q][tat[q][j]]`, or zero where `tat[q][j]` is [`ZERO`]
    /// (a node holds its own tangent, or, for `x + c`, its argument's); `seeds[q]` the unit
    /// seed of channel `q`; `tgat` the arguments' tangents expanded by a broadcast.
    tans: Vec<Vec<Vec<T>>>,
    tat: Vec<Vec<u32>>,
    seeds: Vec<Vec<T>>,
    tgat: [Vec<T>; 2],
}

impl<T: Real> Scratch<T> {
    fn new(nodes: usize, ext: usize, channels: usize) -> Self {
        Scratch {
            vals: (0..nodes).map(|_| Vec::new()).collect(),
            derivs: (0..nodes).map(|_| Vec::new()).collect(),
            dset: vec![false; nodes],
            grads: (0..nodes).map(|_| Vec::new()).collect(),
            gset: vec![false; nodes],
            egrads: (0..ext).map(|_| Vec::new()).collect(),
            eset: vec![false; ext],
            exp: [Vec::new(), Vec::new(), Vec::new()],
            tmp: Vec::new(),
            red: Vec::new(),
            tans: (0..channels)
                .map(|_| (0..nodes).map(|_| Vec::new()).collect())
                .collect(),
            tat: vec![vec![ZERO; nodes]; channels],
            seeds: (0..channels).map(|_| Vec::new()).collect(),
            tgat: [Vec::new(), Vec::new()],
        }
    }
}

fn sized<T: Real>(v: &mut Vec<T>, n: usize) -> &mut [T] {
    if v.len() != n {
        v.resize(n, T::zero());
    }
    &mut v[..]
}

/// Rows `r0..r1` of one chunk and the external values.
struct Chunk<'a, T> {
    ext: &'a [&'a [T]],
    r0: usize,
    r1: usize,
}

impl<T: Real> FusedOp<T> {
    fn local_len(&self, row: bool, w: usize, c: &Chunk<'_, T>) -> usize {
        if row {
            (c.r1 - c.r0) * w
        } else {
            w
        }
    }

    fn ext_slice<'a>(&self, k: usize, c: &Chunk<'a, T>) -> &'a [T] {
        let e = self.ext[k];
        if e.row {
            &c.ext[k][c.r0 * e.w..c.r1 * e.w]
        } else {
            c.ext[k]
        }
    }

    /// The operand of argument `(src, acc)` of a node with local length `n`: expanded into
    /// `buf` when the access is a general broadcast.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn operand<'a>(
        &self,
        src: Src,
        acc: &Access,
        n: usize,
        w: usize,
        vals: &'a [Vec<T>],
        c: &Chunk<'a, T>,
        buf: &'a mut Vec<T>,
    ) -> Opd<'a, T> {
        let base: &'a [T] = match src {
            Src::Ext(k) => self.ext_slice(k, c),
            Src::Node(i) => &vals[i],
        };
        gather(base, acc, n, w, buf)
    }

    /// The forward-mode tangent of argument `(src, acc)` in the node's layout (as
    /// [`Self::operand`] reads its value), for the input channel whose input is `k_in` and whose
    /// chunk of seed values is `seed`; `None` when it is zero (the argument does not depend on
    /// that input).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn tangent_operand<'a>(
        &self,
        src: Src,
        acc: &Access,
        n: usize,
        w: usize,
        (k_in, seed): (usize, &'a [T]),
        tans: &'a [Vec<T>],
        tat: &[u32],
        buf: &'a mut Vec<T>,
    ) -> Option<&'a [T]> {
        let base: &'a [T] = match src {
            Src::Ext(k) if k == k_in => seed,
            Src::Node(i) if tat[i] != ZERO => &tans[tat[i] as usize],
            _ => return None,
        };
        if let Access::Scalar = acc {
            let b = sized(buf, n);
            b.fill(base[0]);
            return Some(b);
        }
        Some(at_s(gather(base, acc, n, w, buf)))
    }

    /// Evaluates every node on one chunk into `s.vals`; with anomaly checks on, returns the
    /// first node holding a non-finite value. With `keep` beyond the values, live `sin` and
    /// `cos` nodes also keep their derivative's factor in `s.derivs`, and with
    /// [`Keep::Tangents`] every node's tangents follow its value (while it is in cache).
    #[inline(always)]
    fn eval_forward(&self, c: &Chunk<'_, T>, s: &mut Scratch<T>, keep: Keep) -> Option<usize> {
        let mut bad = None;
        let tangents = match &self.preacc {
            Some(p) if keep == Keep::Tangents => {
                for (q, &(k, lane)) in p.inputs.iter().enumerate() {
                    // The same pattern for every chunk of the same length.
                    let w = self.ext[k].w;
                    if s.seeds[q].len() != (c.r1 - c.r0) * w {
                        unit_seed(&mut s.seeds[q], c.r1 - c.r0, w, lane);
                    }
                }
                Some(p)
            }
            _ => None,
        };
        for (j, nd) in self.nodes.iter().enumerate() {
            s.dset[j] = false;
            // One input channel: a polynomial op computes its tangent in the same loop.
            let with_tangent = match tangents {
                Some(p) if p.inputs.len() == 1 => self.unary_with_tangent(j, p.inputs[0].0, c, s),
                _ => false,
            };
            let [e0, e1, e2] = &mut s.exp;
            let n = self.local_len(nd.row, nd.w, c);
            let (done, rest) = s.vals.split_at_mut(j);
            let out = sized(&mut rest[0], n);
            let done: &[Vec<T>] = done;
            match nd.kind {
                _ if with_tangent => {}
                Kind::Unary(k @ (Unary::Sin | Unary::Cos)) if keep != Keep::Values && nd.live => {
                    let x = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    let d = sized(&mut s.derivs[j], n);
                    sincos_fwd(out, at_s(x), k == Unary::Cos, |i, v| d[i] = v);
                    s.dset[j] = true;
                }
                Kind::Unary(k) => {
                    let x = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    unary_fwd(k, out, at_s(x));
                }
                Kind::Binary(k) => {
                    let a = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    let b = self.operand(nd.args[1].0, &nd.args[1].1, n, nd.w, done, c, e1);
                    binary_fwd(k, out, a, b);
                }
                Kind::MulSelf => {
                    let x = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    ew2(out, x, x, |x, y| x * y);
                }
                Kind::Select => {
                    let m = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    let a = self.operand(nd.args[1].0, &nd.args[1].1, n, nd.w, done, c, e1);
                    let b = self.operand(nd.args[2].0, &nd.args[2].1, n, nd.w, done, c, e2);
                    let z = T::zero();
                    for (i, o) in out.iter_mut().enumerate() {
                        *o = if m.at(i) != z { a.at(i) } else { b.at(i) };
                    }
                }
                Kind::SumLast(_) => {
                    let x = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    sum_rows(out, at_s(x), nd.lane);
                }
                Kind::SliceLast(a, b) => {
                    let x = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    slice_lanes(out, at_s(x), nd.lane, (a, b));
                }
                Kind::Normalize(eps) => {
                    let x = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, done, c, e0);
                    let x = at_s(x);
                    let k = nd.lane;
                    with_lane!(k, {
                        for (o, lane) in out.chunks_exact_mut(k).zip(x.chunks_exact(k)) {
                            let len = lane.iter().map(|&v| v * v).sum::<T>().sqrt();
                            let nrm = if len < eps { eps } else { len };
                            for (o, &v) in o.iter_mut().zip(lane) {
                                *o = v / nrm;
                            }
                        }
                    })
                }
            }
            if self.anomaly && bad.is_none() && !out.iter().all(|v| v.is_finite()) {
                bad = Some(j);
            }
            if let (Some(p), false) = (tangents, with_tangent) {
                self.eval_tangents(p, j, c, s);
            }
        }
        bad
    }

    /// Node `j`'s value and its tangent for the one input channel (input `k_in`) in one pass,
    /// when it is a polynomial unary op ([`unary_fwd_tangent`]) whose argument has a tangent;
    /// `false` (nothing computed) otherwise.
    #[inline(always)]
    fn unary_with_tangent(
        &self,
        j: usize,
        k_in: usize,
        c: &Chunk<'_, T>,
        s: &mut Scratch<T>,
    ) -> bool {
        let nd = &self.nodes[j];
        let (Kind::Unary(k), (src, Access::Full), true) = (nd.kind, &nd.args[0], nd.live) else {
            return false;
        };
        let Scratch {
            vals,
            tans,
            tat,
            seeds,
            ..
        } = s;
        let (tat, (tdone, trest)) = (&mut tat[0], tans[0].split_at_mut(j));
        let (done, rest) = vals.split_at_mut(j);
        let (x, t): (&[T], &[T]) = match *src {
            Src::Ext(e) if e == k_in => (self.ext_slice(e, c), &seeds[0]),
            Src::Node(i) if tat[i] != ZERO => (&done[i], &tdone[tat[i] as usize]),
            _ => return false,
        };
        let n = self.local_len(nd.row, nd.w, c);
        let (o, to) = (sized(&mut rest[0], n), sized(&mut trest[0], n));
        if !unary_fwd_tangent(k, (o, to), x, t) {
            return false;
        }
        tat[j] = j as u32;
        true
    }

    /// Forward-mode derivatives of node `j`, whose value is computed: for every input channel
    /// `q` of the preaccumulation, `s.tans[q][j] = d node_j / d channel q` on the chunk (Griewank
    /// & Walther, sec. 3.1, tangent propagation). The per-element factors are the reverse
    /// sweep's: an elementwise node's Jacobian is diagonal and `normalize`'s symmetric, so `J t`
    /// is the sweep's formula with `g = t`; broadcasts read an argument's tangent as they read
    /// its value; a sum over lanes sums tangents, and a slice slices them. Tangents known to be
    /// zero (of nodes that do not depend on the channel's input) are flagged, not computed.
    #[inline(always)]
    fn eval_tangents(&self, p: &Preacc<T>, j: usize, c: &Chunk<'_, T>, s: &mut Scratch<T>) {
        let nd = &self.nodes[j];
        let Scratch {
            vals,
            derivs,
            dset,
            exp: [e0, e1, _],
            tmp,
            tans,
            tat,
            seeds,
            tgat: [t0, t1],
            ..
        } = s;
        let n = self.local_len(nd.row, nd.w, c);
        let vals: &[Vec<T>] = vals;
        let y = &vals[j][..n];
        let z = T::zero();
        for (q, &(k_in, _)) in p.inputs.iter().enumerate() {
            let tat = &mut tat[q];
            tat[j] = ZERO;
            if !nd.live {
                continue;
            }
            if let (Kind::Unary(Unary::AddScalar(_)), (Src::Node(i), Access::Full)) =
                (nd.kind, &nd.args[0])
            {
                // d(x + c) = dx: the argument's tangent, not a copy of it.
                tat[j] = tat[*i];
                continue;
            }
            let (done, rest) = tans[q].split_at_mut(j);
            let done: &[Vec<T>] = done;
            let seed = (k_in, &seeds[q][..]);
            macro_rules! tan {
                ($i:expr, $buf:expr) => {
                    self.tangent_operand(
                        nd.args[$i].0,
                        &nd.args[$i].1,
                        n,
                        nd.w,
                        seed,
                        done,
                        tat,
                        $buf,
                    )
                };
            }
            macro_rules! val {
                ($i:expr, $buf:expr) => {
                    self.operand(nd.args[$i].0, &nd.args[$i].1, n, nd.w, vals, c, $buf)
                };
            }
            let out = sized(&mut rest[0], n);
            // Closures would be compiled apart from the multiversioned caller: plain matches.
            let set = match nd.kind {
                Kind::Unary(k) => match tan!(0, t0) {
                    Some(t) if dset[j] => {
                        sincos_bwd(k == Unary::Cos, out, t, &derivs[j]);
                        true
                    }
                    Some(t) => {
                        unary_bwd(k, out, t, at_s(val!(0, e0)), y);
                        true
                    }
                    None => false,
                },
                Kind::Binary(kind) => {
                    let (ta, tb) = (tan!(0, t0), tan!(1, t1));
                    let (a, b) = (val!(0, e0), val!(1, e1));
                    match (ta, tb) {
                        (Some(ta), Some(tb)) => {
                            binary_bwd(kind, 0, out, ta, a, b);
                            let u = sized(tmp, n);
                            binary_bwd(kind, 1, u, tb, a, b);
                            for (o, &v) in out.iter_mut().zip(&u[..]) {
                                *o += v;
                            }
                            true
                        }
                        (Some(ta), None) => {
                            binary_bwd(kind, 0, out, ta, a, b);
                            true
                        }
                        (None, Some(tb)) => {
                            binary_bwd(kind, 1, out, tb, a, b);
                            true
                        }
                        (None, None) => false,
                    }
                }
                Kind::MulSelf => match tan!(0, t0) {
                    Some(t) => {
                        mulself_bwd(out, t, val!(0, e0));
                        true
                    }
                    None => false,
                },
                Kind::Select => {
                    let (ta, tb) = (tan!(1, t0), tan!(2, t1));
                    if ta.is_some() || tb.is_some() {
                        let m = val!(0, e0);
                        for (i, o) in out.iter_mut().enumerate() {
                            let t = if m.at(i) != z { ta } else { tb };
                            *o = match t {
                                Some(t) => t[i],
                                None => z,
                            };
                        }
                        true
                    } else {
                        false
                    }
                }
                Kind::SumLast(_) => match tan!(0, t0) {
                    Some(t) => {
                        sum_rows(out, t, nd.lane);
                        true
                    }
                    None => false,
                },
                Kind::SliceLast(a, b) => match tan!(0, t0) {
                    Some(t) => {
                        slice_lanes(out, t, nd.lane, (a, b));
                        true
                    }
                    None => false,
                },
                Kind::Normalize(eps) => match tan!(0, t0) {
                    Some(t) => {
                        normalize_bwd(out, t, at_s(val!(0, e0)), y, nd.lane, eps);
                        true
                    }
                    None => false,
                },
            };
            if set {
                tat[j] = j as u32;
            }
        }
    }

    /// Adds a gradient contribution `contrib` (in the node's output layout) to argument
    /// `(src, acc)`: reduced to the argument's layout first, then stored or added (as the
    /// eager tape's `sum_to_shape` and accumulation).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn accumulate(
        &self,
        src: Src,
        acc: &Access,
        w: usize,
        contrib: &[T],
        grads: &mut [Vec<T>],
        gset: &mut [bool],
        s_egrads: &mut [Vec<T>],
        s_eset: &mut [bool],
        red: &mut Vec<T>,
        c: &Chunk<'_, T>,
    ) {
        let (buf, set, alen) = match src {
            Src::Ext(k) => {
                let e = self.ext[k];
                (
                    &mut s_egrads[k],
                    &mut s_eset[k],
                    self.local_len(e.row, e.w, c),
                )
            }
            Src::Node(i) => {
                let nd = &self.nodes[i];
                (&mut grads[i], &mut gset[i], self.local_len(nd.row, nd.w, c))
            }
        };
        let reduced: &[T] = match acc {
            Access::Full => contrib,
            Access::Scalar => {
                let r = sized(red, 1);
                r[0] = sum_all(contrib);
                r
            }
            Access::Spread => {
                let r = sized(red, alen);
                sum_rows(r, contrib, w);
                r
            }
            Access::Tile { map } => {
                let r = sized(red, alen);
                r.iter_mut().for_each(|v| *v = T::zero());
                sum_columns(r, contrib, map);
                r
            }
            Access::Expand { map, rstride } => {
                let r = sized(red, alen);
                r.iter_mut().for_each(|v| *v = T::zero());
                let rows = contrib.len() / w.max(1);
                for row in 0..rows {
                    let g = &contrib[row * w..(row + 1) * w];
                    let base = row * rstride;
                    for (&gv, &m) in g.iter().zip(map) {
                        r[base + m as usize] += gv;
                    }
                }
                r
            }
        };
        if *set {
            for (a, &v) in buf.iter_mut().zip(reduced) {
                *a += v;
            }
        } else {
            sized(buf, alen).copy_from_slice(&reduced[..alen]);
            *set = true;
        }
    }

    /// The reverse sweep over one chunk whose forward is in `s.vals` and whose output
    /// gradients are in `s.grads` (flags `s.gset`); external gradients end in `s.egrads`.
    /// With anomaly checks on, returns the last node (first in the sweep) whose backward gave
    /// a non-finite value.
    #[inline(always)]
    fn eval_backward(&self, c: &Chunk<'_, T>, s: &mut Scratch<T>, needs: &[bool]) -> Option<usize> {
        let mut bad = None;
        let Scratch {
            vals,
            derivs,
            dset,
            grads,
            gset,
            egrads,
            eset,
            exp,
            tmp,
            red,
            ..
        } = s;
        let [e0, e1, e2] = exp;
        for (j, nd) in self.nodes.iter().enumerate().rev() {
            if !nd.live || !gset[j] {
                continue;
            }
            let n = self.local_len(nd.row, nd.w, c);
            let (gbelow, grest) = grads.split_at_mut(j);
            let g: &[T] = &grest[0][..n];
            let (gsb, _) = gset.split_at_mut(j);
            let vals: &[Vec<T>] = vals;
            let y: &[T] = &vals[j];
            let wants = |src: Src| match src {
                Src::Ext(k) => k < self.n_in && needs[k],
                Src::Node(i) => self.nodes[i].live,
            };
            let mut check = |v: &[T]| {
                if self.anomaly && bad.is_none() && !v.iter().all(|v| v.is_finite()) {
                    bad = Some(j);
                }
            };
            macro_rules! give {
                ($src:expr, $acc:expr, $contrib:expr) => {{
                    let contrib: &[T] = $contrib;
                    check(contrib);
                    // The first contribution to an argument of the node's own layout is
                    // the argument's gradient: `tmp` takes its place (no copy).
                    match ($src, $acc) {
                        (Src::Node(i), Access::Full) if !gsb[i] => {
                            std::mem::swap(&mut gbelow[i], tmp);
                            gsb[i] = true;
                        }
                        (Src::Ext(k), Access::Full) if !eset[k] => {
                            std::mem::swap(&mut egrads[k], tmp);
                            eset[k] = true;
                        }
                        _ => self.accumulate(
                            $src, $acc, nd.w, contrib, gbelow, gsb, egrads, eset, red, c,
                        ),
                    }
                }};
            }
            match nd.kind {
                Kind::Unary(Unary::AddScalar(_)) => {
                    let (src, acc) = (nd.args[0].0, &nd.args[0].1);
                    if wants(src) {
                        // d(x + c)/dx = 1: the node's gradient is the argument's contribution,
                        // moved rather than copied (the sweep visits the node once).
                        std::mem::swap(&mut grest[0], tmp);
                        give!(src, acc, &tmp[..n]);
                    }
                }
                Kind::Unary(k) => {
                    let (src, acc) = (nd.args[0].0, &nd.args[0].1);
                    if wants(src) {
                        let t = sized(tmp, n);
                        if dset[j] {
                            // The factor the forward kept: `cos x` of `sin`, `sin x` of `cos`.
                            sincos_bwd(k == Unary::Cos, t, g, &derivs[j]);
                        } else {
                            let x = at_s(self.operand(src, acc, n, nd.w, vals, c, e0));
                            unary_bwd(k, t, g, x, y);
                        }
                        give!(src, acc, t);
                    }
                }
                Kind::Binary(kind) => {
                    let a = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, vals, c, e0);
                    let b = self.operand(nd.args[1].0, &nd.args[1].1, n, nd.w, vals, c, e1);
                    for k in 0..2 {
                        let (src, acc) = (nd.args[k].0, &nd.args[k].1);
                        if wants(src) {
                            let t = sized(tmp, n);
                            binary_bwd(kind, k, t, g, a, b);
                            give!(src, acc, t);
                        }
                    }
                }
                Kind::MulSelf => {
                    let (src, acc) = (nd.args[0].0, &nd.args[0].1);
                    if wants(src) {
                        let x = self.operand(src, acc, n, nd.w, vals, c, e0);
                        let t = sized(tmp, n);
                        mulself_bwd(t, g, x);
                        give!(src, acc, t);
                    }
                }
                Kind::Select => {
                    let m = self.operand(nd.args[0].0, &nd.args[0].1, n, nd.w, vals, c, e0);
                    let z = T::zero();
                    for k in 1..3 {
                        let (src, acc) = (nd.args[k].0, &nd.args[k].1);
                        if wants(src) {
                            let take = k == 1;
                            let t = sized(tmp, n);
                            for (i, o) in t.iter_mut().enumerate() {
                                *o = if (m.at(i) != z) == take { g[i] } else { z };
                            }
                            give!(src, acc, t);
                        }
                    }
                }
                Kind::SumLast(_) => {
                    let (src, acc) = (nd.args[0].0, &nd.args[0].1);
                    if wants(src) {
                        let k = nd.lane;
                        let t = sized(tmp, n * k);
                        spread(t, g, k);
                        give!(src, acc, t);
                    }
                }
                Kind::SliceLast(a, b) => {
                    let (src, acc) = (nd.args[0].0, &nd.args[0].1);
                    if wants(src) {
                        let k = nd.lane;
                        let t = sized(tmp, n / (b - a) * k);
                        for (o, gv) in t.chunks_exact_mut(k).zip(g.chunks_exact(b - a)) {
                            o[..a].iter_mut().for_each(|o| *o = T::zero());
                            o[a..b].copy_from_slice(gv);
                            o[b..].iter_mut().for_each(|o| *o = T::zero());
                        }
                        give!(src, acc, t);
                    }
                }
                Kind::Normalize(eps) => {
                    let (src, acc) = (nd.args[0].0, &nd.args[0].1);
                    if wants(src) {
                        let x = at_s(self.operand(src, acc, n, nd.w, vals, c, e2));
                        let t = sized(tmp, n);
                        normalize_bwd(t, g, x, y, nd.lane, eps);
                        give!(src, acc, t);
                    }
                }
            }
        }
        bad
    }

    fn n_chunks(&self) -> usize {
        self.n_rows.div_ceil(self.rows_per_chunk).max(1)
    }

    fn chunk<'a>(&self, i: usize, ext: &'a [&'a [T]]) -> Chunk<'a, T> {
        let r0 = i * self.rows_per_chunk;
        Chunk {
            ext,
            r0,
            r1: (r0 + self.rows_per_chunk).min(self.n_rows.max(1)),
        }
    }

    /// Runs `f` over the chunks (in parallel when the work is large), results in chunk order.
    fn over_chunks<R: Send>(&self, f: impl Fn(usize, &mut Scratch<T>) -> R + Sync) -> Vec<R> {
        let nc = self.n_chunks();
        let work: usize = self
            .nodes
            .iter()
            .map(|n| if n.row { n.w * self.n_rows } else { n.w })
            .sum();
        let channels = self
            .preacc
            .as_ref()
            .filter(|p| p.tangents)
            .map_or(0, |p| p.inputs.len());
        let make = || Scratch::new(self.nodes.len(), self.ext.len(), channels);
        if nc > 1 && work >= PAR_MIN_LEN {
            (0..nc)
                .into_par_iter()
                .map_init(make, |s, i| f(i, s))
                .collect()
        } else {
            let mut s = make();
            (0..nc).map(|i| f(i, &mut s)).collect()
        }
    }

    fn ext_values<'a>(&'a self, inputs: &'a [Cow<'a, [T]>]) -> Vec<&'a [T]> {
        inputs
            .iter()
            .map(|c| &c[..])
            .chain(self.data.iter().map(|d| &d[..]))
            .collect()
    }

    fn anomaly_error(&self, j: usize, pass: Pass) -> AutodiffError {
        let nd = &self.nodes[j];
        AutodiffError::Anomaly {
            op: nd.kind.name(),
            node: nd.slot as usize,
            pass,
            input_shapes: nd.arg_shapes.clone(),
        }
    }
}

/// A raw pointer shared by the chunks, each writing its own disjoint range.
#[derive(Clone, Copy)]
struct SyncPtr<T>(*mut T);
// SAFETY: chunks write disjoint ranges (their own rows) and the buffer outlives the loop.
unsafe impl<T: Send> Send for SyncPtr<T> {}
// SAFETY: as above.
unsafe impl<T: Send> Sync for SyncPtr<T> {}

impl<T> SyncPtr<T> {
    /// # Safety
    /// `at..at + src.len()` lies in the buffer and no other thread writes it.
    unsafe fn write(self, at: usize, src: &[T])
    where
        T: Copy,
    {
        std::ptr::copy_nonoverlapping(src.as_ptr(), self.0.add(at), src.len());
    }
}

/// Flat row-major values of the inputs.
fn flat<'a, T: Real>(inputs: &'a [TensorView<'_, T>]) -> Vec<Cow<'a, [T]>> {
    inputs.iter().map(flat_one).collect()
}

/// One tensor's elements in row-major order: borrowed when its layout is standard.
fn flat_one<T: Real, S: ndarray::Data<Elem = T>>(
    t: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> Cow<'_, [T]> {
    match t.as_slice() {
        Some(s) => Cow::Borrowed(s),
        None => Cow::Owned(t.iter().copied().collect()),
    }
}

/// The chunk interpreter compiled for the baseline target, AVX2 + FMA and AVX-512 (chosen at
/// run time; the same IEEE operations in each, so the same bits).
macro_rules! multiversion {
    ($name:ident, $body:ident, ($($a:ident: $t:ty),*) -> $r:ty) => {
        fn $name<T: Real>(op: &FusedOp<T>, $($a: $t),*) -> $r {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
                unsafe fn wide512<T: Real>(op: &FusedOp<T>, $($a: $t),*) -> $r {
                    op.$body($($a),*)
                }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide<T: Real>(op: &FusedOp<T>, $($a: $t),*) -> $r {
                    op.$body($($a),*)
                }
                if std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512vl")
                    && std::arch::is_x86_feature_detected!("avx512dq")
                    && std::arch::is_x86_feature_detected!("avx512bw")
                {
                    // SAFETY: the CPU has the features `wide512` is compiled for.
                    return unsafe { wide512(op, $($a),*) };
                }
                if std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
                {
                    // SAFETY: the CPU has the features `wide` is compiled for.
                    return unsafe { wide(op, $($a),*) };
                }
            }
            op.$body($($a),*)
        }
    };
}

multiversion!(forward_chunk, eval_forward, (c: &Chunk<'_, T>, s: &mut Scratch<T>, keep: Keep) -> Option<usize>);
multiversion!(backward_chunk, eval_backward, (c: &Chunk<'_, T>, s: &mut Scratch<T>, needs: &[bool]) -> Option<usize>);

impl<T: Real> Op<T> for FusedOp<T> {
    fn name(&self) -> &'static str {
        "fused"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>> {
        let this = &*self;
        let flat = flat(inputs);
        let ext = this.ext_values(&flat);
        let mut outs: Vec<Vec<T>> = this
            .out_shapes
            .iter()
            .map(|s| Vec::with_capacity(s.iter().product()))
            .collect();
        let ptrs: Vec<SyncPtr<T>> = outs.iter_mut().map(|o| SyncPtr(o.as_mut_ptr())).collect();
        // The Jacobians of a preaccumulated op, `n_rows x n_out x w` per input that needs one.
        let n_out = this.preacc.as_ref().map_or(0, |p| p.channels.len());
        let mut jac: Vec<Option<Vec<T>>> = match &this.preacc {
            Some(p) => (0..this.n_in)
                .map(|k| {
                    p.needs[k].then(|| Vec::with_capacity(this.n_rows * n_out * this.ext[k].w))
                })
                .collect(),
            None => Vec::new(),
        };
        let jptrs: Vec<Option<SyncPtr<T>>> = jac
            .iter_mut()
            .map(|j| j.as_mut().map(|j| SyncPtr(j.as_mut_ptr())))
            .collect();
        let bad = this.over_chunks(|i, s| {
            let c = this.chunk(i, &ext);
            let keep = match &this.preacc {
                Some(p) if p.tangents => Keep::Tangents,
                Some(_) => Keep::Derivs,
                None => Keep::Values,
            };
            let bad = forward_chunk(this, &c, s, keep);
            for (&j, p) in this.out_nodes.iter().zip(&ptrs) {
                let nd = &this.nodes[j];
                let at = if nd.row { c.r0 * nd.w } else { 0 };
                // SAFETY: rows r0..r1 of this output are written by this chunk only; the
                // buffer has room for all rows.
                unsafe { p.write(at, &s.vals[j]) };
            }
            if let Some(p) = &this.preacc {
                this.preaccumulate_chunk(p, &c, s, &jptrs);
            }
            bad
        });
        if let Some(j) = bad.into_iter().flatten().min() {
            return Err(this.anomaly_error(j, Pass::Forward));
        }
        let outs = outs
            .into_iter()
            .zip(&this.out_shapes)
            .map(|(mut v, shape)| {
                // SAFETY: every chunk wrote its rows of every output, which cover all of it
                // (non-row outputs exist only with one chunk).
                unsafe { v.set_len(shape.iter().product()) };
                Tensor::from_shape_vec(ndarray::IxDyn(shape), v).expect("output shape")
            })
            .collect();
        if let Some(p) = &mut self.preacc {
            for (k, j) in jac.iter_mut().enumerate() {
                if let Some(j) = j {
                    // SAFETY: every chunk wrote its rows of every kept Jacobian.
                    unsafe { j.set_len(self.n_rows * n_out * self.ext[k].w) };
                }
            }
            p.jac = jac;
        }
        Ok(outs)
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let needs: Vec<bool> = (0..self.n_in)
            .map(|k| ctx.needs_grad[k] && self.ext_live[k])
            .collect();
        let Some(grads) = self
            .preacc
            .as_ref()
            .and_then(|p| self.backward_preaccumulated(p, ctx, &needs))
        else {
            return self.backward_recompute(ctx);
        };
        if self.anomaly
            && grads
                .iter()
                .flatten()
                .any(|g| !g.iter().all(|v| v.is_finite()))
        {
            // Name the node as the eager tape would: the chunks' reverse sweeps with the
            // actual output gradients.
            return self.backward_recompute(ctx);
        }
        Ok(grads
            .into_iter()
            .zip(ctx.inputs)
            .map(|(g, x)| {
                g.map(|g| Tensor::from_shape_vec(ndarray::IxDyn(x.shape()), g).expect("shape"))
            })
            .collect())
    }
}

impl<T: Real> FusedOp<T> {
    /// The sweeps of a preaccumulated op over one chunk whose forward is in `s`: one per
    /// output channel, seeded with ones at that channel; the inputs' gradients it leaves are
    /// the chunk's rows of the Jacobian for that channel. (Non-finite derivatives are named,
    /// with anomaly checks on, by the backward.)
    fn preaccumulate_chunk(
        &self,
        p: &Preacc<T>,
        c: &Chunk<'_, T>,
        s: &mut Scratch<T>,
        jptrs: &[Option<SyncPtr<T>>],
    ) {
        let (n_out, rows) = (p.channels.len(), c.r1 - c.r0);
        if p.tangents {
            // The forward left `d out / d in` in the tangents: entry (row, output channel,
            // input channel) is lane `ch.lane` of the output node's tangent for channel `q`.
            for (o, ch) in p.channels.iter().enumerate() {
                for (q, &(k, lane)) in p.inputs.iter().enumerate() {
                    let ptr = jptrs[k].expect("a Jacobian for every input channel");
                    let w = self.ext[k].w;
                    let at = s.tat[q][ch.node];
                    let t = (at != ZERO).then(|| &s.tans[q][at as usize][..rows * ch.w]);
                    match t {
                        // SAFETY: this chunk's rows of the Jacobian, written by this chunk only.
                        Some(t) if n_out == 1 && w == 1 && ch.w == 1 => unsafe {
                            ptr.write(c.r0, t)
                        },
                        _ => {
                            for r in 0..rows {
                                let v = t.map_or(T::zero(), |t| t[r * ch.w + ch.lane]);
                                // SAFETY: as above, entry (r0 + r, o, lane).
                                unsafe { ptr.write(((c.r0 + r) * n_out + o) * w + lane, &[v]) };
                            }
                        }
                    }
                }
            }
            return;
        }
        for (o, ch) in p.channels.iter().enumerate() {
            s.gset.iter_mut().for_each(|f| *f = false);
            s.eset.iter_mut().for_each(|f| *f = false);
            unit_seed(&mut s.grads[ch.node], rows, ch.w, ch.lane);
            s.gset[ch.node] = true;
            backward_chunk(self, c, s, &p.needs);
            for (k, ptr) in jptrs.iter().enumerate() {
                let Some(ptr) = *ptr else { continue };
                let w = self.ext[k].w;
                if !s.eset[k] {
                    sized(&mut s.egrads[k], rows * w).fill(T::zero());
                }
                let src = &s.egrads[k][..rows * w];
                if n_out == 1 {
                    // SAFETY: this chunk's rows of the Jacobian, written by this chunk only.
                    unsafe { ptr.write(c.r0 * w, src) };
                } else {
                    for r in 0..rows {
                        let at = ((c.r0 + r) * n_out + o) * w;
                        // SAFETY: as above, channel `o` of row `r0 + r`.
                        unsafe { ptr.write(at, &src[r * w..(r + 1) * w]) };
                    }
                }
            }
        }
    }

    /// The backward of a preaccumulated op: `g_in[r, c] = sum_o g_o[r] J[r, o, c]` (output
    /// channels in order), in parallel over blocks of rows (elementwise: the same bits for any
    /// thread count); `None` when an input needs a gradient the forward kept no Jacobian for.
    fn backward_preaccumulated(
        &self,
        p: &Preacc<T>,
        ctx: &BackwardCtx<'_, '_, T>,
        needs: &[bool],
    ) -> Option<Vec<Option<Vec<T>>>> {
        if p.jac.is_empty() || needs.iter().zip(&p.jac).any(|(&n, j)| n && j.is_none()) {
            return None;
        }
        /// Rows per parallel task.
        const BLOCK: usize = 1 << 14;
        let gouts = flat_refs(ctx.grad_outputs);
        let n_out = p.channels.len();
        let grads = (0..self.n_in)
            .map(|k| {
                if !needs[k] {
                    return None;
                }
                let jac = p.jac[k].as_deref().expect("checked above");
                let w = self.ext[k].w;
                let mut gx: Vec<T> = Vec::with_capacity(self.n_rows * w);
                let spare = &mut gx.spare_capacity_mut()[..self.n_rows * w];
                spare
                    .par_chunks_mut(BLOCK * w)
                    .enumerate()
                    .for_each(|(b, gxb)| {
                        let r0 = b * BLOCK;
                        let ch0 = p.channels[0];
                        if n_out == 1 && ch0.w == 1 && w == 1 {
                            let (g, jac) = (&gouts[ch0.out][r0..], &jac[r0..]);
                            for ((o, &g), &j) in gxb.iter_mut().zip(g).zip(jac) {
                                o.write(g * j);
                            }
                            return;
                        }
                        for (e, o) in gxb.iter_mut().enumerate() {
                            let (r, c) = (r0 + e / w, e % w);
                            let term = |o: usize, ch: &Channel| {
                                gouts[ch.out][r * ch.w + ch.lane] * jac[(r * n_out + o) * w + c]
                            };
                            let mut acc = term(0, &ch0);
                            for (o, ch) in p.channels.iter().enumerate().skip(1) {
                                acc += term(o, ch);
                            }
                            o.write(acc);
                        }
                    });
                // SAFETY: the blocks wrote every element.
                unsafe { gx.set_len(self.n_rows * w) };
                Some(gx)
            })
            .collect();
        Some(grads)
    }

    fn backward_recompute(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>> {
        let flat = flat(ctx.inputs);
        let ext = self.ext_values(&flat);
        let gouts: Vec<Cow<'_, [T]>> = flat_refs(ctx.grad_outputs);
        let needs: Vec<bool> = (0..self.n_in)
            .map(|k| ctx.needs_grad[k] && self.ext_live[k])
            .collect();
        let mut row_grads: Vec<Option<Vec<T>>> = (0..self.n_in)
            .map(|k| {
                (needs[k] && self.ext[k].row)
                    .then(|| Vec::with_capacity(self.ext[k].w * self.n_rows))
            })
            .collect();
        let ptrs: Vec<Option<SyncPtr<T>>> = row_grads
            .iter_mut()
            .map(|g| g.as_mut().map(|g| SyncPtr(g.as_mut_ptr())))
            .collect();
        let results = self.over_chunks(|i, s| {
            let c = self.chunk(i, &ext);
            forward_chunk(self, &c, s, Keep::Derivs);
            s.gset.iter_mut().for_each(|f| *f = false);
            s.eset.iter_mut().for_each(|f| *f = false);
            for (&j, g) in self.out_nodes.iter().zip(&gouts) {
                let nd = &self.nodes[j];
                if !nd.live {
                    continue;
                }
                let n = self.local_len(nd.row, nd.w, &c);
                let at = if nd.row { c.r0 * nd.w } else { 0 };
                let part = &g[at..at + n];
                if s.gset[j] {
                    for (a, &v) in s.grads[j].iter_mut().zip(part) {
                        *a += v;
                    }
                } else {
                    sized(&mut s.grads[j], n).copy_from_slice(part);
                    s.gset[j] = true;
                }
            }
            let bad = backward_chunk(self, &c, s, &needs);
            let mut partials: Vec<Option<Vec<T>>> = Vec::new();
            for k in 0..self.n_in {
                if !needs[k] {
                    partials.push(None);
                    continue;
                }
                let e = self.ext[k];
                let n = self.local_len(e.row, e.w, &c);
                if !s.eset[k] {
                    sized(&mut s.egrads[k], n)
                        .iter_mut()
                        .for_each(|v| *v = T::zero());
                }
                if e.row {
                    let p = ptrs[k].expect("row gradient buffer");
                    // SAFETY: this chunk's rows of input k, written by this chunk only.
                    unsafe { p.write(c.r0 * e.w, &s.egrads[k][..n]) };
                    partials.push(None);
                } else {
                    partials.push(Some(s.egrads[k][..n].to_vec()));
                }
            }
            (bad, partials)
        });
        if let Some(j) = results.iter().filter_map(|r| r.0).max() {
            return Err(self.anomaly_error(j, Pass::Backward));
        }
        let mut out = Vec::with_capacity(self.n_in);
        let mut results = results;
        for k in 0..self.n_in {
            if !needs[k] {
                out.push(None);
                continue;
            }
            let shape = ctx.inputs[k].shape();
            let v = if let Some(mut g) = row_grads[k].take() {
                // SAFETY: every chunk wrote its rows of this gradient.
                unsafe { g.set_len(self.ext[k].w * self.n_rows) };
                g
            } else {
                // Row-invariant input: per-chunk partial sums added in chunk order.
                let mut acc: Option<Vec<T>> = None;
                for r in results.iter_mut() {
                    let p = r.1[k].take().expect("partial of a needed input");
                    match &mut acc {
                        None => acc = Some(p),
                        Some(a) => a.iter_mut().zip(&p).for_each(|(a, &v)| *a += v),
                    }
                }
                acc.expect("at least one chunk")
            };
            out.push(Some(
                Tensor::from_shape_vec(ndarray::IxDyn(shape), v).expect("input shape"),
            ));
        }
        Ok(out)
    }
}

fn flat_refs<'a, T: Real>(ts: &[&'a Tensor<T>]) -> Vec<Cow<'a, [T]>> {
    ts.iter().map(|t| flat_one(*t)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// A region over zero rows (no fragments in view) is evaluated eagerly: empty values and
    /// zero gradients of the inputs' shapes, in every backward mode, no panic.
    #[test]
    fn a_region_over_zero_rows_gives_empty_values_and_zero_gradients() {
        for mode in [
            FusedBackward::Recompute,
            FusedBackward::Preaccumulate,
            FusedBackward::PreaccumulateForward,
        ] {
            let t = crate::Tape::<f64>::new();
            t.set_fused_backward(mode);
            let normal = t.var(crate::tensor::from_vec(&[0, 3], vec![]).unwrap(), true);
            let light = t.var(
                crate::tensor::from_vec(&[3], vec![0.3, -0.6, 0.9]).unwrap(),
                true,
            );
            let y = t.fused(|| {
                let n = normal.normalize(0.5);
                ((n * light).sum_axes(&[-1], false)).sin()
            });
            assert_eq!(y.value().unwrap().shape(), &[0]);
            let g = t.backward(y.sum()).unwrap();
            assert_eq!(g.wrt(normal).shape(), &[0, 3]);
            assert_eq!(g.wrt(light).iter().copied().collect::<Vec<_>>(), [0.0; 3]);
        }
    }

    /// The one-loop value and tangent of the polynomial unary ops give the bits of the value
    /// pass followed by the tangent pass (`unary_fwd`, then `unary_bwd`), in `f32` (the fast
    /// kernels, with arguments outside their range and NaN, which take libm) and `f64`.
    #[test]
    fn value_and_tangent_in_one_loop_equal_two_passes() {
        fn check<T: Real>() {
            let mut x: Vec<T> = Rng::new(1).normal_tensor(&[999]).iter().copied().collect();
            for (i, v) in [1e5, f64::NAN, -100.0, 100.0, 0.0, -0.0]
                .into_iter()
                .enumerate()
            {
                x[3 + i] = T::from_f64c(v);
            }
            x.iter_mut().skip(20).for_each(|v| *v *= T::from_f64c(6.0));
            let t: Vec<T> = Rng::new(2).normal_tensor(&[999]).iter().copied().collect();
            let same = |a: &[T], b: &[T]| {
                a.iter().zip(b).all(|(&u, &v)| {
                    u.to_f64c().to_bits() == v.to_f64c().to_bits() || (u.is_nan() && v.is_nan())
                })
            };
            let n = x.len();
            for k in [
                Unary::Sin,
                Unary::Cos,
                Unary::Tanh,
                Unary::Exp,
                Unary::Sigmoid,
            ] {
                let (mut o, mut to) = (vec![T::zero(); n], vec![T::zero(); n]);
                assert!(unary_fwd_tangent(k, (&mut o, &mut to), &x, &t));
                let (mut y, mut ty) = (vec![T::zero(); n], vec![T::zero(); n]);
                unary_fwd(k, &mut y, &x);
                unary_bwd(k, &mut ty, &t, &x, &y);
                assert!(same(&o, &y), "{} {k:?} value", T::NAME);
                assert!(same(&to, &ty), "{} {k:?} tangent", T::NAME);
            }
            let (mut o, mut to) = (vec![T::zero(); n], vec![T::zero(); n]);
            assert!(!unary_fwd_tangent(Unary::Log, (&mut o, &mut to), &x, &t));
        }
        check::<f32>();
        check::<f64>();
    }
}
