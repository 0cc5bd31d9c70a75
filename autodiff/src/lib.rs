//! Reverse-mode automatic differentiation on a tape, generic over `f32` and `f64`.
//!
//! ```
//! use autodiff::{Tape, tensor};
//! let tape = Tape::<f64>::new();
//! let a = tape.leaf(tensor::from_vec(&[3], vec![1.0, 2.0, 3.0]).unwrap());
//! let b = tape.constant(tensor::from_vec(&[3], vec![0.5, 0.5, 0.5]).unwrap());
//! let loss = (a * b + 1.0).exp().sum();
//! let grads = tape.backward(loss).unwrap();
//! let ga = grads.get(a).unwrap();
//! assert!((ga[[0]] - 0.5 * (1.5f64).exp()).abs() < 1e-12);
//! ```
#![warn(missing_docs)]

pub mod active_wait;
pub mod error;
pub mod fused;
pub mod gradcheck;
mod malloc;
pub use malloc::tune as tune_malloc;
pub mod ops;
pub mod optim;
pub mod real;
pub mod rng;
pub mod storage;
pub mod suite;
pub mod tape;
pub mod tensor;
mod var_ops;
mod vmath;

pub use active_wait::ActiveWait;
pub use error::{AutodiffError, Pass, Result};
pub use ndarray;
pub use real::{c, Real};
pub use storage::{Buffer, Value};
pub use tape::{BackwardCtx, Gradients, Op, Tape, Var};
pub use tensor::{Tensor, TensorView};
