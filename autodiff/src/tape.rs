//! The tape: an arena of recorded values and ops, walked once in reverse by `backward`.
//!
//! Define-by-run: build a fresh [`Tape`] for every evaluation, create leaves from parameter
//! tensors kept outside it, compose ops through [`Var`] handles, call [`Tape::backward`].
//!
//! Errors are *sticky*: an op whose inputs do not fit records the error on the tape and
//! returns a poisoned variable; every op fed a poisoned variable returns a poisoned one
//! without computing, and [`Var::value`], [`Tape::backward`] and [`Tape::vjp`] return the
//! first error. This lets `(a * b + c).exp().sum()` read like math without a `?` per op, while
//! never panicking and never hiding the failing op.

use std::cell::{Cell, RefCell};
use std::collections::HashMap;
use std::fmt;
use std::sync::Arc;

use ndarray::{ArrayD, IxDyn};
use smallvec::SmallVec;

use crate::error::{AutodiffError, Pass, Result};
use crate::fused::{Arg, Dag, DagNode, FusedBackward, Kind, DEFAULT_CHUNK};
use crate::ops::elementwise::{BinaryOp, MulSelfOp, UnaryOp, WhereOp};
use crate::ops::reduce::SumOp;
use crate::ops::shape::SliceOp;
use crate::ops::vector::NormalizeOp;
use crate::storage::{Buffer, Value};
use crate::tensor::{all_finite, scalar, Tensor, TensorView};
use crate::Real;

/// What an op's backward receives (`'v`: the life of the input values it views).
pub struct BackwardCtx<'a, 'v, T: Real> {
    /// Input values, in the order the op was applied to them.
    pub inputs: &'a [TensorView<'v, T>],
    /// Output values of the forward.
    pub outputs: &'a [&'a Tensor<T>],
    /// Gradient of the loss with respect to each output (zeros for outputs that did not
    /// reach the loss).
    pub grad_outputs: &'a [&'a Tensor<T>],
    /// Which inputs need a gradient; return `None` for the others and skip their work.
    pub needs_grad: &'a [bool],
}

/// The one op trait, for built-in and user ops alike: a forward and a hand-written backward
/// (a vector-Jacobian product). Non-differentiable data (integer ids, caches of the forward)
/// lives in the op's own fields, which the forward may fill.
pub trait Op<T: Real>: 'static {
    /// Name shown in errors, anomaly reports and gradcheck tables.
    fn name(&self) -> &'static str;
    /// Computes the outputs from the inputs. Shape problems are returned as errors.
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> Result<Vec<Tensor<T>>>;
    /// Returns, for every input, the gradient of the loss (same shape as the input), or `None`
    /// where `ctx.needs_grad` is false.
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> Result<Vec<Option<Tensor<T>>>>;
    /// [`Op::backward`] of a single-output op, given its output gradient by value: the tape
    /// drops it afterwards, so an op may compute an input's gradient in its buffer instead of
    /// allocating one (elementwise ops do). The default borrows it and calls
    /// [`Op::backward`]; an override must return the same values.
    fn backward_owned(
        &self,
        inputs: &[TensorView<'_, T>],
        outputs: &[&Tensor<T>],
        needs_grad: &[bool],
        grad_output: Tensor<T>,
    ) -> Result<Vec<Option<Tensor<T>>>> {
        self.backward(&BackwardCtx {
            inputs,
            outputs,
            grad_outputs: &[&grad_output],
            needs_grad,
        })
    }
}

struct Slot<T: Real> {
    value: Value<T>,
    requires_grad: bool,
    poisoned: bool,
    /// The op (index into `ops`) that produced this variable; `None` for leaves and constants.
    producer: Option<u32>,
    /// A node recorded in a fused region and not computed yet (index into `Inner::lazy`);
    /// `value` is then a placeholder.
    pending: Option<u32>,
}

/// An argument of a recorded (lazy) node.
#[derive(Clone, Copy)]
enum LazyArg {
    Slot(u32),
    /// A `where` mask (index into `Inner::masks`).
    Mask(u32),
}

/// An elementwise op recorded inside [`Tape::fused`] and not computed yet.
struct LazyNode<T> {
    kind: Kind<T>,
    args: SmallVec<[LazyArg; 3]>,
    shape: Vec<usize>,
}

struct Record<T: Real> {
    op: Box<dyn Op<T>>,
    inputs: SmallVec<[u32; 4]>,
    outputs: SmallVec<[u32; 2]>,
}

struct Inner<T: Real> {
    slots: Vec<Slot<T>>,
    ops: Vec<Record<T>>,
    error: Option<AutodiffError>,
    lazy: Vec<LazyNode<T>>,
    masks: Vec<Arc<ArrayD<bool>>>,
}

/// An arena of variables and the ops that produced them.
pub struct Tape<T: Real> {
    inner: RefCell<Inner<T>>,
    no_grad_depth: Cell<u32>,
    anomaly: Cell<bool>,
    fusing: Cell<u32>,
    fuse_chunk: Cell<usize>,
    fuse_backward: Cell<FusedBackward>,
}

impl<T: Real> Default for Tape<T> {
    fn default() -> Self {
        Self::new()
    }
}

/// A handle to a variable on a tape: cheap to copy, combined with operators and methods.
#[derive(Clone, Copy)]
pub struct Var<'t, T: Real> {
    tape: &'t Tape<T>,
    id: u32,
}

impl<T: Real> fmt::Debug for Var<'_, T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Var(#{} {:?})", self.id, self.shape())
    }
}

/// Gradients from one backward pass, indexed by variable.
pub struct Gradients<T: Real> {
    grads: Vec<Option<Tensor<T>>>,
}

impl<T: Real> fmt::Debug for Gradients<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let held: Vec<_> = self
            .grads
            .iter()
            .enumerate()
            .filter_map(|(i, g)| g.as_ref().map(|g| (i, g.shape().to_vec())))
            .collect();
        f.debug_struct("Gradients").field("held", &held).finish()
    }
}

impl<T: Real> Gradients<T> {
    /// Gradient of a leaf (or `None` if the loss does not depend on it or it does not
    /// require gradients).
    pub fn get(&self, v: Var<'_, T>) -> Option<&Tensor<T>> {
        self.grads.get(v.id as usize).and_then(|g| g.as_ref())
    }
    /// Gradient of a leaf, zeros of its shape where the loss does not depend on it.
    pub fn wrt(&self, v: Var<'_, T>) -> Tensor<T> {
        match self.get(v) {
            Some(g) => g.clone(),
            None => ArrayD::zeros(IxDyn(&v.shape())),
        }
    }
    /// Moves a leaf's gradient out.
    pub fn take(&mut self, v: Var<'_, T>) -> Option<Tensor<T>> {
        self.grads.get_mut(v.id as usize).and_then(|g| g.take())
    }
}

impl<T: Real> Tape<T> {
    /// An empty tape. The first tape of a process tunes glibc `malloc` so that the
    /// activations freed by one step are reused by the next (see `malloc.rs`; opt out with
    /// `TAPESTRY_MALLOC_TUNING=0`).
    pub fn new() -> Self {
        crate::malloc::tune();
        Tape {
            inner: RefCell::new(Inner {
                slots: Vec::new(),
                ops: Vec::new(),
                error: None,
                lazy: Vec::new(),
                masks: Vec::new(),
            }),
            no_grad_depth: Cell::new(0),
            anomaly: Cell::new(false),
            fusing: Cell::new(0),
            fuse_chunk: Cell::new(DEFAULT_CHUNK),
            fuse_backward: Cell::new(FusedBackward::Auto),
        }
    }

    /// An empty tape with room for `n` variables.
    pub fn with_capacity(n: usize) -> Self {
        let t = Self::new();
        t.inner.borrow_mut().slots.reserve(n);
        t.inner.borrow_mut().ops.reserve(n);
        t
    }

    /// Turns anomaly detection on or off (off by default): when on, the first op whose
    /// forward output or backward gradient holds a NaN or Inf is reported as
    /// [`AutodiffError::Anomaly`], naming the op, its node and its input shapes.
    pub fn set_detect_anomaly(&self, on: bool) {
        self.anomaly.set(on);
    }

    /// Number of variables recorded so far.
    pub fn len(&self) -> usize {
        self.inner.borrow().slots.len()
    }

    /// True when nothing is recorded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Number of ops recorded for backward (ops on constants only are not recorded).
    pub fn num_ops(&self) -> usize {
        self.inner.borrow().ops.len()
    }

    /// The first error recorded on this tape, if any.
    pub fn error(&self) -> Option<AutodiffError> {
        self.inner.borrow().error.clone()
    }

    fn push_slot(&self, value: Value<T>, requires_grad: bool) -> Var<'_, T> {
        let mut inner = self.inner.borrow_mut();
        let id = inner.slots.len() as u32;
        inner.slots.push(Slot {
            value,
            requires_grad,
            poisoned: false,
            producer: None,
            pending: None,
        });
        Var { tape: self, id }
    }

    /// A leaf variable; `requires_grad` says whether backward computes its gradient.
    pub fn var(&self, value: Tensor<T>, requires_grad: bool) -> Var<'_, T> {
        self.push_slot(Value::Owned(Arc::new(value)), requires_grad)
    }

    /// A leaf that requires gradients (a parameter).
    pub fn leaf(&self, value: Tensor<T>) -> Var<'_, T> {
        self.var(value, true)
    }

    /// A leaf sharing an existing tensor without copying it.
    pub fn var_shared(&self, value: Arc<Tensor<T>>, requires_grad: bool) -> Var<'_, T> {
        self.push_slot(Value::Owned(value), requires_grad)
    }

    /// A leaf reading `buffer` (row-major, of `shape`) in place, without copying it: ops see
    /// it as a view, and the tape keeps the buffer alive while it holds the variable. Its
    /// gradient, when `requires_grad`, is an owned tensor as for any leaf.
    pub fn var_borrowed(
        &self,
        shape: &[usize],
        buffer: Arc<dyn Buffer<T>>,
        requires_grad: bool,
    ) -> Result<Var<'_, T>> {
        let n: usize = shape.iter().product();
        if buffer.data().len() != n {
            return Err(AutodiffError::shape(
                "var_borrowed",
                &[shape],
                format!(
                    "a buffer of {} values for {n} elements",
                    buffer.data().len()
                ),
            ));
        }
        Ok(self.push_slot(Value::Borrowed(buffer, IxDyn(shape)), requires_grad))
    }

    /// A constant (no gradient).
    pub fn constant(&self, value: Tensor<T>) -> Var<'_, T> {
        self.var(value, false)
    }

    /// A 0-dimensional constant.
    pub fn scalar(&self, x: T) -> Var<'_, T> {
        self.constant(scalar(x))
    }

    /// A 0-dimensional constant from an `f64`.
    pub fn scalar_f64(&self, x: f64) -> Var<'_, T> {
        self.scalar(T::from_f64c(x))
    }

    /// Runs `f` with gradient recording off: ops inside produce constants.
    pub fn no_grad<R>(&self, f: impl FnOnce() -> R) -> R {
        // Restores the depth even when `f` unwinds.
        struct Guard<'a>(&'a Cell<u32>);
        impl Drop for Guard<'_> {
            fn drop(&mut self) {
                self.0.set(self.0.get() - 1);
            }
        }
        self.no_grad_depth.set(self.no_grad_depth.get() + 1);
        let _guard = Guard(&self.no_grad_depth);
        f()
    }

    /// True inside [`Tape::no_grad`].
    pub fn is_no_grad(&self) -> bool {
        self.no_grad_depth.get() > 0
    }

    /// A poisoned variable carrying `err` (the tape's first error, unless it already has one):
    /// how a function composed of tape ops reports inputs it cannot take, as an op would.
    pub fn poisoned(&self, err: AutodiffError) -> Var<'_, T> {
        self.poison(err, 1)[0]
    }

    fn poison(&self, err: AutodiffError, n_outputs: usize) -> SmallVec<[Var<'_, T>; 2]> {
        let mut inner = self.inner.borrow_mut();
        if inner.error.is_none() {
            inner.error = Some(err);
        }
        let empty = Arc::new(scalar(T::nan()));
        (0..n_outputs.max(1))
            .map(|_| {
                let id = inner.slots.len() as u32;
                inner.slots.push(Slot {
                    value: Value::Owned(empty.clone()),
                    requires_grad: false,
                    poisoned: true,
                    producer: None,
                    pending: None,
                });
                Var { tape: self, id }
            })
            .collect()
    }

    /// Records `op` applied to `inputs`; returns its outputs. `n_outputs` is the number of
    /// outputs the op produces (used to shape poisoned results when an input is poisoned); a
    /// forward returning another number of outputs poisons the tape with an
    /// [`AutodiffError::Op`] naming the op.
    pub fn apply_multi<'t, O: Op<T>>(
        &'t self,
        mut op: O,
        inputs: &[Var<'t, T>],
        n_outputs: usize,
    ) -> SmallVec<[Var<'t, T>; 2]> {
        // Pending (fused) inputs are computed first, in one fused op: this op then runs eagerly.
        let pending: SmallVec<[u32; 4]> = {
            let inner = self.inner.borrow();
            inputs
                .iter()
                .filter(|v| std::ptr::eq(v.tape, self))
                .filter(|v| inner.slots[v.id as usize].pending.is_some())
                .map(|v| v.id)
                .collect()
        };
        if !pending.is_empty() {
            self.materialize_ids(&pending);
        }
        let mut values: SmallVec<[Value<T>; 4]> = SmallVec::new();
        let mut requires_grad = false;
        {
            let inner = self.inner.borrow();
            for v in inputs {
                if !std::ptr::eq(v.tape, self) {
                    drop(inner);
                    return self.poison(
                        AutodiffError::Tape(format!("{}: input from another tape", op.name())),
                        n_outputs,
                    );
                }
                let s = &inner.slots[v.id as usize];
                if s.poisoned {
                    drop(inner);
                    return self.poison(AutodiffError::Tape("poisoned".into()), n_outputs);
                }
                requires_grad |= s.requires_grad;
                values.push(s.value.clone());
            }
        }
        requires_grad &= !self.is_no_grad();
        let refs: SmallVec<[TensorView<'_, T>; 4]> = values.iter().map(Value::view).collect();
        let outs = match op.forward(&refs) {
            Ok(o) if o.len() == n_outputs => o,
            Ok(o) => {
                let err = AutodiffError::Op {
                    op: op.name(),
                    detail: format!(
                        "forward returned {} outputs, {} expected",
                        o.len(),
                        n_outputs
                    ),
                };
                return self.poison(err, n_outputs);
            }
            Err(e) => return self.poison(e, n_outputs),
        };
        let mut inner = self.inner.borrow_mut();
        let first = inner.slots.len();
        if self.anomaly.get() && !outs.iter().all(all_finite) {
            let err = AutodiffError::Anomaly {
                op: op.name(),
                node: first,
                pass: Pass::Forward,
                input_shapes: refs.iter().map(|t| t.shape().to_vec()).collect(),
            };
            drop(inner);
            return self.poison(err, n_outputs);
        }
        let producer = if requires_grad {
            Some(inner.ops.len() as u32)
        } else {
            None
        };
        let mut vars = SmallVec::new();
        let mut out_ids = SmallVec::new();
        for o in outs {
            let id = inner.slots.len() as u32;
            inner.slots.push(Slot {
                value: Value::Owned(Arc::new(o)),
                requires_grad,
                poisoned: false,
                producer,
                pending: None,
            });
            out_ids.push(id);
            vars.push(Var { tape: self, id });
        }
        if requires_grad {
            inner.ops.push(Record {
                op: Box::new(op),
                inputs: inputs.iter().map(|v| v.id).collect(),
                outputs: out_ids,
            });
        }
        vars
    }

    /// Records a single-output op.
    pub fn apply<'t, O: Op<T>>(&'t self, op: O, inputs: &[Var<'t, T>]) -> Var<'t, T> {
        self.apply_multi(op, inputs, 1)[0]
    }

    /// Runs `f` as a fused region: elementwise and broadcast ops inside it (unary and binary
    /// math, `where_`, `x * x`, `sum_axes(&[-1], _)` and `normalize` over a last axis of at
    /// most [`crate::fused::MAX_LANE`]) are recorded, not computed, and the graph behind a
    /// variable becomes one [`crate::fused::FusedOp`] when its value is first needed: read,
    /// fed to any other op (which then runs eagerly: the fallback for ops the fuser does not
    /// handle), or asked for with [`Tape::materialize`]. Results equal the eager ops' (see
    /// the `fused` module for the bounds); code outside a region is unaffected.
    pub fn fused<R>(&self, f: impl FnOnce() -> R) -> R {
        struct Guard<'a>(&'a Cell<u32>);
        impl Drop for Guard<'_> {
            fn drop(&mut self) {
                self.0.set(self.0.get() - 1);
            }
        }
        self.fusing.set(self.fusing.get() + 1);
        let _guard = Guard(&self.fusing);
        f()
    }

    /// True inside [`Tape::fused`].
    pub fn is_fusing(&self) -> bool {
        self.fusing.get() > 0
    }

    /// Elements per chunk of the fused ops materialised from now on (default
    /// [`crate::fused::DEFAULT_CHUNK`]; at least one row). Results do not depend on it except
    /// for the summation order of gradients of inputs broadcast over rows.
    pub fn set_fused_chunk(&self, elems: usize) {
        self.fuse_chunk.set(elems.max(1));
    }

    /// How the fused ops materialised from now on prepare their backward (default
    /// [`FusedBackward::Auto`]: preaccumulate the per-row Jacobian of ops with one output
    /// channel and few inputs, recompute otherwise). Values do not depend on it; gradients
    /// agree within the bound in the `fused` module docs.
    pub fn set_fused_backward(&self, mode: FusedBackward) {
        self.fuse_backward.set(mode);
    }

    /// Computes the pending variables among `vars` together: one fused op for the graph
    /// behind all of them (shared intermediates computed once). Others are left as they are.
    pub fn materialize(&self, vars: &[Var<'_, T>]) {
        let ids: SmallVec<[u32; 4]> = vars
            .iter()
            .filter(|v| std::ptr::eq(v.tape, self) && v.is_pending())
            .map(|v| v.id)
            .collect();
        if !ids.is_empty() {
            self.materialize_ids(&ids);
        }
    }

    /// Records `kind` on `args` as a pending node when inside a fused region and the inputs
    /// fit; `None` tells the caller to run the eager op (which also reports bad inputs).
    pub(crate) fn record_lazy<'t>(
        &'t self,
        kind: Kind<T>,
        args: &[Var<'t, T>],
        mask: Option<&ArrayD<bool>>,
    ) -> Option<Var<'t, T>> {
        if !self.is_fusing() || args.iter().any(|v| !std::ptr::eq(v.tape, self)) {
            return None;
        }
        let shapes: SmallVec<[Vec<usize>; 3]> = args.iter().map(|v| v.shape()).collect();
        let shape = match kind {
            Kind::Unary(crate::ops::elementwise::Unary::Clamp(lo, hi))
                if lo.is_nan() || hi.is_nan() || lo > hi =>
            {
                return None
            }
            Kind::Unary(_) | Kind::MulSelf => shapes[0].clone(),
            Kind::Binary(b) => {
                crate::tensor::broadcast_shapes(b.name(), &shapes[0], &shapes[1]).ok()?
            }
            Kind::Select => {
                let s = crate::tensor::broadcast_shapes("where", &shapes[0], &shapes[1]).ok()?;
                crate::tensor::broadcast_shapes("where", &s, mask?.shape()).ok()?
            }
            Kind::SumLast(keep) => {
                let s = &shapes[0];
                let k = *s.last()?;
                if k > crate::fused::MAX_LANE {
                    return None;
                }
                let mut o = s[..s.len() - 1].to_vec();
                if keep {
                    o.push(1);
                }
                o
            }
            Kind::Normalize(eps) => {
                let k = *shapes[0].last()?;
                if eps.is_nan() || eps <= T::zero() || k > crate::fused::MAX_LANE {
                    return None;
                }
                shapes[0].clone()
            }
            Kind::SliceLast(a, b) => {
                let k = *shapes[0].last()?;
                if a >= b || b > k || k > crate::fused::MAX_LANE {
                    return None;
                }
                let mut o = shapes[0].clone();
                *o.last_mut()? = b - a;
                o
            }
        };
        let mut inner = self.inner.borrow_mut();
        let mut rg = false;
        for v in args {
            let s = &inner.slots[v.id as usize];
            if s.poisoned {
                return None;
            }
            rg |= s.requires_grad;
        }
        rg &= !self.is_no_grad() && !matches!(kind, Kind::Unary(k) if !k.has_gradient());
        let mut largs: SmallVec<[LazyArg; 3]> = SmallVec::new();
        if let Some(m) = mask {
            largs.push(LazyArg::Mask(inner.masks.len() as u32));
            inner.masks.push(Arc::new(m.clone()));
        }
        largs.extend(args.iter().map(|v| LazyArg::Slot(v.id)));
        let node = inner.lazy.len() as u32;
        inner.lazy.push(LazyNode {
            kind,
            args: largs,
            shape,
        });
        let id = inner.slots.len() as u32;
        let placeholder = match inner.slots.last() {
            Some(s) if s.pending.is_some() => s.value.clone(),
            _ => Value::Owned(Arc::new(scalar(T::nan()))),
        };
        inner.slots.push(Slot {
            value: placeholder,
            requires_grad: rg,
            poisoned: false,
            producer: None,
            pending: Some(node),
        });
        Some(Var { tape: self, id })
    }

    /// Computes the pending slots `targets` (and the pending graph behind them): one fused op
    /// when the graph fits the chunk scheme, else each target on its own, else the nodes one
    /// by one with the eager ops.
    pub(crate) fn materialize_ids(&self, targets: &[u32]) {
        let mut targets: Vec<u32> = targets.to_vec();
        targets.sort_unstable();
        targets.dedup();
        let (dag, ext_ids, order) = {
            let inner = self.inner.borrow();
            targets.retain(|&t| inner.slots[t as usize].pending.is_some());
            if targets.is_empty() {
                return;
            }
            // The pending slots behind the targets, in creation (topological) order.
            let mut seen: Vec<u32> = Vec::new();
            let mut stack = targets.clone();
            let mut mark: HashMap<u32, ()> = HashMap::new();
            while let Some(s) = stack.pop() {
                if mark.insert(s, ()).is_some() {
                    continue;
                }
                seen.push(s);
                let p = inner.slots[s as usize].pending.expect("pending") as usize;
                for a in &inner.lazy[p].args {
                    if let LazyArg::Slot(i) = *a {
                        if inner.slots[i as usize].pending.is_some() {
                            stack.push(i);
                        }
                    }
                }
            }
            seen.sort_unstable();
            let index: HashMap<u32, usize> =
                seen.iter().enumerate().map(|(k, &s)| (s, k)).collect();
            let mut ext_ids: Vec<u32> = Vec::new();
            let mut ext_index: HashMap<u32, usize> = HashMap::new();
            let mut data = Vec::new();
            let mut nodes = Vec::with_capacity(seen.len());
            let mut poisoned = false;
            for &s in &seen {
                let slot = &inner.slots[s as usize];
                let ln = &inner.lazy[slot.pending.expect("pending") as usize];
                let args = ln
                    .args
                    .iter()
                    .map(|a| match *a {
                        LazyArg::Slot(i) => match index.get(&i) {
                            Some(&k) => Arg::Node(k),
                            None => {
                                poisoned |= inner.slots[i as usize].poisoned;
                                Arg::Ext(*ext_index.entry(i).or_insert_with(|| {
                                    ext_ids.push(i);
                                    ext_ids.len() - 1
                                }))
                            }
                        },
                        LazyArg::Mask(m) => {
                            let mask = &inner.masks[m as usize];
                            data.push(mask.mapv(|b| if b { T::one() } else { T::zero() }));
                            Arg::Data(data.len() - 1)
                        }
                    })
                    .collect();
                nodes.push(DagNode {
                    slot: s,
                    kind: ln.kind,
                    args,
                    shape: ln.shape.clone(),
                    rg: slot.requires_grad,
                });
            }
            if poisoned {
                drop(inner);
                let err = AutodiffError::Tape("poisoned".into());
                self.poison_slots(&seen, err);
                return;
            }
            let ext_shapes = ext_ids
                .iter()
                .map(|&i| inner.slots[i as usize].value.shape().to_vec())
                .collect();
            let ext_rg = ext_ids
                .iter()
                .map(|&i| inner.slots[i as usize].requires_grad)
                .collect();
            let dag = Dag {
                nodes,
                ext_shapes,
                ext_rg,
                data,
                targets: targets.iter().map(|t| index[t]).collect(),
            };
            (dag, ext_ids, seen)
        };
        let mode = self.fuse_backward.get();
        match crate::fused::plan(dag, self.fuse_chunk.get(), self.anomaly.get(), mode) {
            Some(op) => self.record_into(op, &ext_ids, &targets),
            None if targets.len() > 1 => self.materialize_groups(&targets),
            None => {
                for s in order {
                    self.eager_node(s);
                }
            }
        }
    }

    /// Computes targets that do not fit one fused op: grouped by their number of rows, the
    /// pending nodes the groups share computed first (so that none is computed twice), then
    /// each group, in the order of their last targets.
    fn materialize_groups(&self, targets: &[u32]) {
        let (groups, shared) = {
            let inner = self.inner.borrow();
            let rows = |t: u32| {
                let p = inner.slots[t as usize].pending.expect("pending") as usize;
                inner.lazy[p].shape.first().copied()
            };
            let mut groups: Vec<(Option<usize>, Vec<u32>)> = Vec::new();
            for &t in targets {
                let r = rows(t);
                match groups.iter_mut().find(|g| g.0 == r) {
                    Some(g) => g.1.push(t),
                    None => groups.push((r, vec![t])),
                }
            }
            let mut count: HashMap<u32, usize> = HashMap::new();
            for (_, g) in &groups {
                let mut seen: HashMap<u32, ()> = HashMap::new();
                let mut stack = g.clone();
                while let Some(s) = stack.pop() {
                    if seen.insert(s, ()).is_some() {
                        continue;
                    }
                    *count.entry(s).or_default() += 1;
                    let p = inner.slots[s as usize].pending.expect("pending") as usize;
                    for a in &inner.lazy[p].args {
                        if let LazyArg::Slot(i) = *a {
                            if inner.slots[i as usize].pending.is_some() {
                                stack.push(i);
                            }
                        }
                    }
                }
            }
            let mut shared: Vec<u32> = count
                .into_iter()
                .filter(|&(_, c)| c > 1)
                .map(|(s, _)| s)
                .collect();
            shared.sort_unstable();
            let mut groups: Vec<Vec<u32>> = groups.into_iter().map(|g| g.1).collect();
            groups.sort_by_key(|g| g.iter().max().copied());
            (groups, shared)
        };
        if groups.len() == 1 {
            // Same rows, yet no plan: each target alone (the eager fallback when that fails
            // too computes the shared nodes once).
            for &t in targets {
                self.materialize_ids(&[t]);
            }
            return;
        }
        if !shared.is_empty() {
            self.materialize_ids(&shared);
        }
        for g in groups {
            self.materialize_ids(&g);
        }
    }

    /// Computes one pending slot with its eager op (its pending arguments must be computed).
    fn eager_node(&self, s: u32) {
        let (kind, args, mask, ndim) = {
            let inner = self.inner.borrow();
            let Some(p) = inner.slots[s as usize].pending else {
                return;
            };
            let ln = &inner.lazy[p as usize];
            let mut mask = None;
            let mut args: SmallVec<[u32; 3]> = SmallVec::new();
            for a in &ln.args {
                match *a {
                    LazyArg::Slot(i) => args.push(i),
                    LazyArg::Mask(m) => mask = Some(inner.masks[m as usize].clone()),
                }
            }
            let ndim = inner.slots[args[0] as usize].value.ndim();
            (ln.kind, args, mask, ndim)
        };
        match kind {
            Kind::Unary(k) => self.record_into(UnaryOp(k), &args, &[s]),
            Kind::Binary(b) => self.record_into(BinaryOp(b), &args, &[s]),
            Kind::MulSelf => self.record_into(MulSelfOp, &args, &[s]),
            Kind::Select => {
                let mask = (*mask.expect("where has a mask")).clone();
                self.record_into(WhereOp { mask }, &args, &[s])
            }
            Kind::SumLast(keep) => {
                let op = SumOp::new(Some(vec![ndim.saturating_sub(1)]), keep, false);
                self.record_into(op, &args, &[s])
            }
            Kind::Normalize(eps) => self.record_into(NormalizeOp { eps }, &args, &[s]),
            Kind::SliceLast(start, end) => {
                let op = SliceOp {
                    axis: ndim.saturating_sub(1),
                    start,
                    end,
                };
                self.record_into(op, &args, &[s])
            }
        }
    }

    /// Marks the pending slots `ids` poisoned and records `err` (if first).
    fn poison_slots(&self, ids: &[u32], err: AutodiffError) {
        let mut inner = self.inner.borrow_mut();
        if inner.error.is_none() {
            inner.error = Some(err);
        }
        for &i in ids {
            let s = &mut inner.slots[i as usize];
            s.poisoned = true;
            s.pending = None;
            s.requires_grad = false;
        }
    }

    /// Runs `op` on the (computed) slots `inputs` and stores its outputs in the pending slots
    /// `outs`, recording it for backward when one of them requires gradients.
    fn record_into<O: Op<T>>(&self, mut op: O, inputs: &[u32], outs: &[u32]) {
        let values: SmallVec<[Value<T>; 4]> = {
            let inner = self.inner.borrow();
            if inputs.iter().any(|&i| inner.slots[i as usize].poisoned) {
                drop(inner);
                return self.poison_slots(outs, AutodiffError::Tape("poisoned".into()));
            }
            inputs
                .iter()
                .map(|&i| inner.slots[i as usize].value.clone())
                .collect()
        };
        let refs: SmallVec<[TensorView<'_, T>; 4]> = values.iter().map(Value::view).collect();
        let vals = match op.forward(&refs) {
            Ok(v) if v.len() == outs.len() => v,
            Ok(v) => {
                let err = AutodiffError::Op {
                    op: op.name(),
                    detail: format!(
                        "forward returned {} outputs, {} expected",
                        v.len(),
                        outs.len()
                    ),
                };
                return self.poison_slots(outs, err);
            }
            Err(e) => return self.poison_slots(outs, e),
        };
        if self.anomaly.get() && !vals.iter().all(all_finite) {
            let err = AutodiffError::Anomaly {
                op: op.name(),
                node: outs[0] as usize,
                pass: Pass::Forward,
                input_shapes: refs.iter().map(|t| t.shape().to_vec()).collect(),
            };
            return self.poison_slots(outs, err);
        }
        let mut inner = self.inner.borrow_mut();
        let rg = outs.iter().any(|&o| inner.slots[o as usize].requires_grad);
        let producer = rg.then_some(inner.ops.len() as u32);
        for (&o, v) in outs.iter().zip(vals) {
            let s = &mut inner.slots[o as usize];
            s.value = Value::Owned(Arc::new(v));
            s.pending = None;
            s.producer = producer;
        }
        if rg {
            inner.ops.push(Record {
                op: Box::new(op),
                inputs: inputs.iter().copied().collect(),
                outputs: outs.iter().copied().collect(),
            });
        }
    }

    /// Gradients of a scalar (one-element) `loss` with respect to every leaf that requires them.
    pub fn backward(&self, loss: Var<'_, T>) -> Result<Gradients<T>> {
        let v = loss.value()?;
        if v.len() != 1 {
            return Err(AutodiffError::shape(
                "backward",
                &[v.shape()],
                "backward needs a one-element loss; use vjp for other outputs",
            ));
        }
        let seed = ArrayD::from_elem(IxDyn(v.shape()), T::one());
        self.vjp(loss, seed)
    }

    /// Vector-Jacobian product: gradients of `sum(output * grad_output)` with respect to every
    /// leaf that requires them.
    pub fn vjp(&self, output: Var<'_, T>, grad_output: Tensor<T>) -> Result<Gradients<T>> {
        let v = output.value()?;
        if v.shape() != grad_output.shape() {
            return Err(AutodiffError::shape(
                "vjp",
                &[v.shape(), grad_output.shape()],
                "grad_output must have the output's shape",
            ));
        }
        let inner = self.inner.borrow();
        let mut grads: Vec<Option<Tensor<T>>> = Vec::new();
        grads.resize_with(inner.slots.len(), || None);
        let out_slot = &inner.slots[output.id as usize];
        if !out_slot.requires_grad {
            return Ok(Gradients { grads });
        }
        let last_op = match out_slot.producer {
            Some(p) => p as usize + 1,
            None => {
                // The output is itself a leaf.
                grads[output.id as usize] = Some(grad_output);
                return Ok(Gradients { grads });
            }
        };
        grads[output.id as usize] = Some(grad_output);
        let mut needs: SmallVec<[bool; 4]> = SmallVec::new();
        for rec in inner.ops[..last_op].iter().rev() {
            if rec.outputs.iter().all(|&o| grads[o as usize].is_none()) {
                continue;
            }
            let out_vals: SmallVec<[&Tensor<T>; 2]> = rec
                .outputs
                .iter()
                .map(|&o| {
                    inner.slots[o as usize]
                        .value
                        .owned()
                        .expect("op outputs are owned")
                })
                .collect();
            let in_vals: SmallVec<[TensorView<'_, T>; 4]> = rec
                .inputs
                .iter()
                .map(|&i| inner.slots[i as usize].value.view())
                .collect();
            needs.clear();
            needs.extend(
                rec.inputs
                    .iter()
                    .map(|&i| inner.slots[i as usize].requires_grad),
            );
            let gins = if let [o] = rec.outputs[..] {
                // A single output's gradient is not needed after this op: hand it over, so
                // that elementwise backwards reuse its buffer.
                let g = grads[o as usize].take().expect("checked above");
                rec.op.backward_owned(&in_vals, &out_vals, &needs, g)?
            } else {
                // Missing output gradients of multi-output ops are zeros.
                let zeros: SmallVec<[Option<Tensor<T>>; 2]> = rec
                    .outputs
                    .iter()
                    .zip(&out_vals)
                    .map(|(&o, val)| {
                        grads[o as usize]
                            .is_none()
                            .then(|| ArrayD::zeros(IxDyn(val.shape())))
                    })
                    .collect();
                let gouts: SmallVec<[&Tensor<T>; 2]> = rec
                    .outputs
                    .iter()
                    .zip(&zeros)
                    .map(|(&o, z)| {
                        z.as_ref()
                            .unwrap_or_else(|| grads[o as usize].as_ref().unwrap())
                    })
                    .collect();
                let ctx = BackwardCtx {
                    inputs: &in_vals,
                    outputs: &out_vals,
                    grad_outputs: &gouts,
                    needs_grad: &needs,
                };
                rec.op.backward(&ctx)?
            };
            if gins.len() != rec.inputs.len() {
                return Err(AutodiffError::Op {
                    op: rec.op.name(),
                    detail: format!(
                        "backward returned {} gradients for {} inputs",
                        gins.len(),
                        rec.inputs.len()
                    ),
                });
            }
            // Intermediate gradients are no longer needed once consumed.
            for &o in &rec.outputs {
                grads[o as usize] = None;
            }
            for (k, (g, &inp)) in gins.into_iter().zip(&rec.inputs).enumerate() {
                let Some(g) = g else { continue };
                if !needs[k] {
                    continue;
                }
                let want = inner.slots[inp as usize].value.shape();
                if g.shape() != want {
                    return Err(AutodiffError::shape(
                        rec.op.name(),
                        &[want, g.shape()],
                        format!("backward returned a gradient of the wrong shape for input {k}"),
                    ));
                }
                if self.anomaly.get() && !all_finite(&g) {
                    return Err(AutodiffError::Anomaly {
                        op: rec.op.name(),
                        node: rec.outputs[0] as usize,
                        pass: Pass::Backward,
                        input_shapes: in_vals.iter().map(|t| t.shape().to_vec()).collect(),
                    });
                }
                match &mut grads[inp as usize] {
                    Some(acc) => crate::tensor::add_assign(acc, &g),
                    slot @ None => *slot = Some(g),
                }
            }
        }
        Ok(Gradients { grads })
    }
}

impl<'t, T: Real> Var<'t, T> {
    /// The tape this variable lives on.
    pub fn tape(&self) -> &'t Tape<T> {
        self.tape
    }
    /// Index of the variable on its tape.
    pub fn id(&self) -> usize {
        self.id as usize
    }
    /// The value, or the tape's first error if this variable was poisoned by it. A borrowed
    /// leaf ([`Tape::var_borrowed`]) is copied.
    pub fn value(&self) -> Result<Arc<Tensor<T>>> {
        Ok(self.value_ref()?.to_shared())
    }
    /// The value as stored, to read in place: unlike [`Var::value`], a borrowed leaf
    /// ([`Tape::var_borrowed`]) is not copied.
    pub fn value_ref(&self) -> Result<Value<T>> {
        if self.is_pending() {
            self.tape.materialize_ids(&[self.id]);
        }
        let inner = self.tape.inner.borrow();
        let s = &inner.slots[self.id as usize];
        if s.poisoned {
            return Err(inner
                .error
                .clone()
                .unwrap_or_else(|| AutodiffError::Tape("poisoned variable".into())));
        }
        Ok(s.value.clone())
    }
    /// The single element of a one-element variable.
    pub fn item(&self) -> Result<T> {
        let v = self.value()?;
        if v.len() != 1 {
            return Err(AutodiffError::shape(
                "item",
                &[v.shape()],
                "item needs one element",
            ));
        }
        Ok(*v.iter().next().expect("one element"))
    }
    /// Shape of the value (empty for scalars and poisoned variables).
    pub fn shape(&self) -> Vec<usize> {
        let inner = self.tape.inner.borrow();
        let s = &inner.slots[self.id as usize];
        match s.pending {
            Some(p) => inner.lazy[p as usize].shape.clone(),
            None => s.value.shape().to_vec(),
        }
    }
    /// Number of dimensions.
    pub fn ndim(&self) -> usize {
        let inner = self.tape.inner.borrow();
        let s = &inner.slots[self.id as usize];
        match s.pending {
            Some(p) => inner.lazy[p as usize].shape.len(),
            None => s.value.ndim(),
        }
    }
    /// Number of elements.
    pub fn len(&self) -> usize {
        let inner = self.tape.inner.borrow();
        let s = &inner.slots[self.id as usize];
        match s.pending {
            Some(p) => inner.lazy[p as usize].shape.iter().product(),
            None => s.value.len(),
        }
    }
    /// True for a variable recorded inside [`Tape::fused`] whose value is not computed yet
    /// (it is, in one fused op with the graph behind it, when first needed).
    pub fn is_pending(&self) -> bool {
        self.tape.inner.borrow().slots[self.id as usize]
            .pending
            .is_some()
    }
    /// True for zero-element variables.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Whether backward propagates into this variable.
    pub fn requires_grad(&self) -> bool {
        self.tape.inner.borrow().slots[self.id as usize].requires_grad
    }
    /// A constant sharing this variable's value: gradients stop here.
    pub fn detach(&self) -> Var<'t, T> {
        if self.is_pending() {
            self.tape.materialize_ids(&[self.id]);
        }
        let inner = self.tape.inner.borrow();
        let s = &inner.slots[self.id as usize];
        if s.poisoned {
            return *self;
        }
        let value = s.value.clone();
        drop(inner);
        self.tape.push_slot(value, false)
    }
}
