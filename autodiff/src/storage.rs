//! What a tape slot holds: a tensor the tape owns, or a caller's buffer read in place.
//!
//! A borrowed leaf ([`crate::Tape::var_borrowed`]) lets a caller hand the tape memory it
//! already has (a numpy array in the Python bindings, a memory-mapped model) without a copy:
//! the tape keeps the [`Buffer`] alive for as long as it holds the slot, and ops read it as a
//! [`TensorView`], like any other input. Op outputs and gradients are always owned.

use std::sync::Arc;

use ndarray::{ArrayViewD, Dimension, IxDyn};

use crate::tensor::{Tensor, TensorView};
use crate::Real;

/// Row-major memory a tape may read in place. `data` must return the same slice on every call
/// for as long as the buffer lives (the tape builds views of it at each op).
pub trait Buffer<T>: Send + Sync + 'static {
    /// The elements, in row-major order.
    fn data(&self) -> &[T];
}

impl<T: Send + Sync + 'static> Buffer<T> for Vec<T> {
    fn data(&self) -> &[T] {
        self
    }
}

/// A slot's value ([`crate::Var::value_ref`]): a cheap handle (one `Arc`) to read in place.
#[derive(Clone)]
pub enum Value<T: Real> {
    /// A tensor the tape owns (op outputs, and leaves made from tensors).
    Owned(Arc<Tensor<T>>),
    /// A caller's buffer of the given shape (its length checked when the leaf was made).
    Borrowed(Arc<dyn Buffer<T>>, IxDyn),
}

impl<T: Real> Value<T> {
    /// The value as a view, without copying.
    pub fn view(&self) -> TensorView<'_, T> {
        match self {
            Value::Owned(t) => t.view(),
            Value::Borrowed(b, shape) => ArrayViewD::from_shape(shape.clone(), b.data())
                .expect("buffer length checked when the leaf was made"),
        }
    }

    /// The owned tensor of an op's output (outputs are never borrowed).
    pub(crate) fn owned(&self) -> Option<&Tensor<T>> {
        match self {
            Value::Owned(t) => Some(t),
            Value::Borrowed(..) => None,
        }
    }

    /// The value as a shared owned tensor: a borrowed buffer is copied.
    pub(crate) fn to_shared(&self) -> Arc<Tensor<T>> {
        match self {
            Value::Owned(t) => t.clone(),
            Value::Borrowed(..) => Arc::new(self.view().to_owned()),
        }
    }

    /// The shape.
    pub fn shape(&self) -> &[usize] {
        match self {
            Value::Owned(t) => t.shape(),
            Value::Borrowed(_, s) => s.slice(),
        }
    }

    /// The number of dimensions.
    pub fn ndim(&self) -> usize {
        self.shape().len()
    }

    /// The number of elements.
    pub fn len(&self) -> usize {
        self.shape().iter().product()
    }

    /// True for zero elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;
    use crate::tape::{BackwardCtx, Op, Tape};
    use crate::Result;

    /// Records the address of the data its input views (to prove no copy was made).
    struct Probe(Arc<AtomicUsize>);

    impl Op<f64> for Probe {
        fn name(&self) -> &'static str {
            "probe"
        }
        fn forward(&mut self, inputs: &[TensorView<'_, f64>]) -> Result<Vec<Tensor<f64>>> {
            self.0.store(inputs[0].as_ptr() as usize, Ordering::SeqCst);
            Ok(vec![inputs[0].mapv(|x| x * x)])
        }
        fn backward(&self, ctx: &BackwardCtx<'_, '_, f64>) -> Result<Vec<Option<Tensor<f64>>>> {
            self.0
                .store(ctx.inputs[0].as_ptr() as usize, Ordering::SeqCst);
            let g = ctx.grad_outputs[0] * &ctx.inputs[0].mapv(|x| 2.0 * x);
            Ok(vec![ctx.needs_grad[0].then_some(g)])
        }
    }

    #[test]
    fn borrowed_leaves_are_read_in_place_and_released_with_the_tape() {
        let data: Arc<Vec<f64>> = Arc::new(vec![1.0, -2.0, 3.0, 0.5, 4.0, -1.5]);
        let addr = data.as_ptr() as usize;
        let seen = Arc::new(AtomicUsize::new(0));
        {
            let tape = Tape::<f64>::new();
            let x = tape
                .var_borrowed(&[2, 3], data.clone(), true)
                .expect("6 values for [2, 3]");
            assert_eq!(x.shape(), vec![2, 3]);
            let y = tape.apply(Probe(seen.clone()), &[x]);
            assert_eq!(seen.load(Ordering::SeqCst), addr, "forward saw a copy");
            let loss = (y * 3.0).sum();
            assert_eq!(loss.item().unwrap(), 3.0 * 32.5);
            seen.store(0, Ordering::SeqCst);
            let g = tape.backward(loss).unwrap();
            assert_eq!(seen.load(Ordering::SeqCst), addr, "backward saw a copy");
            let gx = g.get(x).unwrap();
            for (gi, xi) in gx.iter().zip(data.iter()) {
                assert_eq!(*gi, 6.0 * xi);
            }
            // The same values through an owned leaf give the same bits.
            let t2 = Tape::<f64>::new();
            let x2 = t2.leaf(Tensor::from_shape_vec(vec![2, 3], data.to_vec()).unwrap());
            let l2 = (t2.apply(Probe(seen.clone()), &[x2]) * 3.0).sum();
            assert_eq!(l2.item().unwrap(), 3.0 * 32.5);
            assert_eq!(t2.backward(l2).unwrap().get(x2).unwrap(), gx);
            assert_eq!(Arc::strong_count(&data), 2, "the tape holds the buffer");
        }
        assert_eq!(Arc::strong_count(&data), 1, "the tape released the buffer");
    }

    #[test]
    fn a_buffer_of_the_wrong_length_is_an_error() {
        let tape = Tape::<f32>::new();
        let e = tape
            .var_borrowed(&[4], Arc::new(vec![1.0f32; 3]), false)
            .unwrap_err();
        assert!(e.to_string().contains("3 values for 4 elements"), "{e}");
    }
}
