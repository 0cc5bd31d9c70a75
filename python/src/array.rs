//! numpy arrays in and out: dtype and shape checks with clear messages, float inputs read in
//! place where numpy's layout allows (else copied once), faces as `u32` triangles, and outputs
//! moved into numpy.

use std::sync::Arc;

use autodiff::{Buffer, Real, Tape, Tensor, Var};
use ndarray::{ArrayD, IxDyn};
use numpy::{
    Element, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use render_ops::RenderError;

/// The float dtype of one call (every float input of a call has it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dt {
    F32,
    F64,
}

/// Runs `$body` with `$T` the scalar type of `$dt`.
macro_rules! with_dtype {
    ($dt:expr, $T:ident => $body:expr) => {
        match $dt {
            $crate::array::Dt::F32 => {
                type $T = f32;
                $body
            }
            $crate::array::Dt::F64 => {
                type $T = f64;
                $body
            }
        }
    };
}
pub(crate) use with_dtype;

fn untyped<'a, 'py>(
    name: &str,
    obj: &'a Bound<'py, PyAny>,
) -> PyResult<&'a Bound<'py, PyUntypedArray>> {
    obj.cast::<PyUntypedArray>().map_err(|_| {
        let ty = obj
            .get_type()
            .name()
            .map(|n| n.to_string())
            .unwrap_or_else(|_| "?".into());
        PyTypeError::new_err(format!("{name}: expected a numpy array, got {ty}"))
    })
}

/// The float dtype of `obj` (`float32` or `float64`), else a `TypeError`.
pub fn dtype_of(name: &str, obj: &Bound<'_, PyAny>) -> PyResult<Dt> {
    let a = untyped(name, obj)?;
    let py = obj.py();
    let dt = a.dtype();
    if dt.is_equiv_to(&numpy::dtype::<f64>(py)) {
        Ok(Dt::F64)
    } else if dt.is_equiv_to(&numpy::dtype::<f32>(py)) {
        Ok(Dt::F32)
    } else {
        Err(PyTypeError::new_err(format!(
            "{name}: dtype {dt}, expected float32 or float64"
        )))
    }
}

/// Checks `shape` against `want` (`None`: any size), naming the pattern `pattern` in the error.
pub fn check_shape(
    name: &str,
    shape: &[usize],
    want: &[Option<usize>],
    pattern: &str,
) -> PyResult<()> {
    let ok = shape.len() == want.len()
        && shape
            .iter()
            .zip(want)
            .all(|(&s, w)| w.is_none_or(|w| w == s));
    if ok {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!(
            "{name}: shape {shape:?}, expected {pattern}"
        )))
    }
}

/// A float input on its way to the tape: the numpy array's own memory when it is C-contiguous
/// and aligned (read in place, no copy), else one copy in logical order. Cloning shares it.
#[derive(Clone)]
pub struct Floats<T: Real> {
    shape: Vec<usize>,
    buf: Arc<dyn Buffer<T>>,
}

impl<T: Real> Floats<T> {
    /// Row-major values of `shape` that the binding made itself (defaults, not user input).
    pub fn owned(shape: Vec<usize>, data: Vec<T>) -> Self {
        debug_assert_eq!(shape.iter().product::<usize>(), data.len());
        Floats {
            shape,
            buf: Arc::new(data),
        }
    }

    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    pub fn ndim(&self) -> usize {
        self.shape.len()
    }

    /// A variable on `tape` reading these values in place ([`Tape::var_borrowed`]).
    pub fn var<'t>(&self, tape: &'t Tape<T>, requires_grad: bool) -> Var<'t, T> {
        tape.var_borrowed(&self.shape, self.buf.clone(), requires_grad)
            .expect("length matches the shape by construction")
    }

    /// An owned copy (a reverse walk's seed, whose buffer the backward reuses in place).
    pub fn to_tensor(&self) -> Tensor<T> {
        ArrayD::from_shape_vec(IxDyn(&self.shape), self.buf.data().to_vec())
            .expect("length matches the shape by construction")
    }
}

/// Whether `floats` reads `array` in place (a test hook: `tapestry._tapestry._reads_in_place`).
#[pyfunction]
pub fn _reads_in_place(array: &Bound<'_, PyAny>) -> PyResult<bool> {
    let any = vec![None; untyped("array", array)?.ndim()];
    with_dtype!(dtype_of("array", array)?, T => {
        let f = floats::<T>("array", array, &any, "any")?;
        Ok(std::ptr::eq(f.buf.data().as_ptr(), array.cast::<PyArrayDyn<T>>()?.data()))
    })
}

/// A numpy array's data, read in place. The array is kept alive by the reference held here, so
/// its memory stays allocated for as long as a tape holds the buffer; the binding never writes
/// through it. As with numpy's own GIL-releasing functions, Python code must not write to an
/// input array from another thread while a call that reads it runs.
struct NumpyBuffer<T> {
    _array: Py<PyArrayDyn<T>>,
    ptr: *const T,
    len: usize,
}

// SAFETY: the pointer is only read (`data`), and the memory it points to lives as long as
// `_array` (a strong reference, itself Send + Sync).
unsafe impl<T: Sync> Send for NumpyBuffer<T> {}
unsafe impl<T: Sync> Sync for NumpyBuffer<T> {}

impl<T: Real> Buffer<T> for NumpyBuffer<T> {
    fn data(&self) -> &[T] {
        // SAFETY: `ptr` is non-null, aligned and points to `len` initialised elements of a
        // C-contiguous array (checked in `floats`) that `_array` keeps alive.
        unsafe { std::slice::from_raw_parts(self.ptr, self.len) }
    }
}

/// A finite float input of dtype `T` and shape `want`. C-contiguous, aligned arrays are read in
/// place (zero-copy); other layouts are copied once (by `numpy.require(x, dtype, "CA")`).
pub fn floats<T: Element + Real>(
    name: &'static str,
    obj: &Bound<'_, PyAny>,
    want: &[Option<usize>],
    pattern: &str,
) -> PyResult<Floats<T>> {
    let a = untyped(name, obj)?;
    let py = obj.py();
    if !a.dtype().is_equiv_to(&numpy::dtype::<T>(py)) {
        return Err(PyTypeError::new_err(format!(
            "{name}: dtype {}, expected {} (the float inputs of one call share a dtype)",
            a.dtype(),
            numpy::dtype::<T>(py)
        )));
    }
    check_shape(name, a.shape(), want, pattern)?;
    let shape = a.shape().to_vec();
    let len: usize = shape.iter().product();
    let readable = |arr: &Bound<'_, PyArrayDyn<T>>| {
        let ptr = arr.data() as *const T;
        arr.is_c_contiguous()
            && !ptr.is_null()
            && (ptr as usize).is_multiple_of(std::mem::align_of::<T>())
    };
    let mut arr = obj.cast::<PyArrayDyn<T>>()?.clone();
    if !readable(&arr) {
        // The one copy: numpy's own, into a C-contiguous aligned array (Fortran order, slices,
        // negative, zero or unaligned strides).
        let np = py.import("numpy")?;
        arr = np
            .call_method1("require", (obj, numpy::dtype::<T>(py), "CA"))?
            .cast_into::<PyArrayDyn<T>>()?;
    }
    let buf: Arc<dyn Buffer<T>> = if len == 0 {
        Arc::new(Vec::<T>::new())
    } else if readable(&arr) {
        let ptr = arr.data() as *const T;
        Arc::new(NumpyBuffer {
            _array: arr.unbind(),
            ptr,
            len,
        })
    } else {
        return Err(PyValueError::new_err(format!(
            "{name}: numpy could not give a C-contiguous aligned copy"
        )));
    };
    // NaN or Inf would otherwise reach an image silently: named like the library does (a
    // flat scan first; the indexed search only for the message).
    let t = ndarray::ArrayViewD::from_shape(IxDyn(&shape), buf.data()).expect("shape");
    if !autodiff::tensor::all_finite(&t) {
        RenderError::check_finite(name, &t).map_err(crate::to_py)?;
    }
    Ok(Floats { shape, buf })
}

/// Triangles `[F, 3]` of any integer dtype as `u32` vertex indices (one copy).
///
/// C-contiguous `int64`, `int32` and `uint32` arrays (numpy's and torch's defaults) are read in
/// place: one range check over the flat slice, then one converting copy. Any other integer
/// dtype or layout goes through numpy's `ascontiguousarray(faces, "int64")` first.
pub fn faces(obj: &Bound<'_, PyAny>) -> PyResult<Vec<[u32; 3]>> {
    let a = untyped("faces", obj)?;
    check_shape("faces", a.shape(), &[None, Some(3)], "[F, 3]")?;
    let kind = a.dtype().kind();
    if kind != b'i' && kind != b'u' {
        return Err(PyTypeError::new_err(format!(
            "faces: dtype {}, expected an integer dtype",
            a.dtype()
        )));
    }
    if let Some(t) = c_slice::<i64, _>(obj, triangles) {
        return t;
    }
    if let Some(t) = c_slice::<i32, _>(obj, triangles) {
        return t;
    }
    if let Some(t) = c_slice::<u32, _>(obj, |flat| {
        Ok(flat.chunks_exact(3).map(|f| [f[0], f[1], f[2]]).collect())
    }) {
        return t;
    }
    let np = obj.py().import("numpy")?;
    let i64s = np.call_method1("ascontiguousarray", (obj, "int64"))?;
    let arr = i64s.cast::<PyArrayDyn<i64>>()?.readonly();
    triangles(arr.as_slice()?)
}

/// `f` over the flat data of `obj` when it is a C-contiguous array of dtype `T`, read in place.
fn c_slice<T: Element, R>(obj: &Bound<'_, PyAny>, f: impl FnOnce(&[T]) -> R) -> Option<R> {
    let r = obj.cast::<PyArrayDyn<T>>().ok()?.try_readonly().ok()?;
    if !r.is_c_contiguous() {
        return None;
    }
    Some(f(r.as_slice().ok()?))
}

/// Flat signed indices as `u32` triangles: a branch-free range check over the whole slice (the
/// indexed search runs only to name the first bad index), then the converting copy.
fn triangles<I: Copy + Into<i64>>(flat: &[I]) -> PyResult<Vec<[u32; 3]>> {
    let in_range = |x: I| (0..=i64::from(u32::MAX)).contains(&x.into());
    if !flat.iter().fold(true, |ok, &x| ok & in_range(x)) {
        let i = flat.iter().position(|&x| !in_range(x)).unwrap_or(0);
        let x: i64 = flat[i].into();
        return Err(PyValueError::new_err(format!(
            "faces[{}, {}] = {x}: vertex indices must be in [0, 2^32)",
            i / 3,
            i % 3
        )));
    }
    Ok(flat
        .chunks_exact(3)
        .map(|f| [f[0].into() as u32, f[1].into() as u32, f[2].into() as u32])
        .collect())
}

/// An owned tensor moved into a numpy array (no copy).
pub fn to_numpy<'py, T: Element>(py: Python<'py>, t: Tensor<T>) -> Bound<'py, PyAny> {
    numpy::PyArray::from_owned_array(py, t).into_any()
}
