//! The scalar trait: everything in Tapestry is generic over `f32` (speed) and `f64` (checking).

use std::fmt::{Debug, Display};
use std::iter::Sum;

use ndarray::{LinalgScalar, ScalarOperand};
use num_traits::{Float, FloatConst, FromPrimitive, NumAssign};

mod sealed {
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

/// A floating-point scalar the tape can differentiate: `f32` or `f64` (sealed).
pub trait Real:
    Float
    + FloatConst
    + FromPrimitive
    + NumAssign
    + LinalgScalar
    + ScalarOperand
    + Sum
    + Default
    + Debug
    + Display
    + Send
    + Sync
    + sealed::Sealed
    + 'static
{
    /// Name of the type, for reports ("f32" / "f64").
    const NAME: &'static str;
    /// Machine epsilon of the type.
    const EPS: Self;
    /// Converts from `f64` (rounding for `f32`).
    fn from_f64c(x: f64) -> Self;
    /// Converts to `f64` exactly.
    fn to_f64c(self) -> f64;
    /// `usize` to scalar.
    fn from_usize_c(n: usize) -> Self {
        Self::from_f64c(n as f64)
    }

    // Kernel hooks of the elementwise ops (see `crate::vmath`): `f32` swaps in vectorisable
    // polynomials, valid where the matching `k_*_ok` holds; elsewhere (and for `f64`, which
    // gradient checks rely on) the exact libm functions are used.
    #[doc(hidden)]
    const FAST_MATH: bool = false;
    #[doc(hidden)]
    #[inline(always)]
    fn k_sin(self) -> Self {
        self.sin()
    }
    #[doc(hidden)]
    #[inline(always)]
    fn k_cos(self) -> Self {
        self.cos()
    }
    /// `(k_sin, k_cos)` from one argument reduction (the same bits as the two calls).
    #[doc(hidden)]
    #[inline(always)]
    fn k_sincos(self) -> (Self, Self) {
        (self.k_sin(), self.k_cos())
    }
    #[doc(hidden)]
    #[inline(always)]
    fn k_trig_ok(self) -> bool {
        true
    }
    #[doc(hidden)]
    #[inline(always)]
    fn k_exp(self) -> Self {
        self.exp()
    }
    #[doc(hidden)]
    #[inline(always)]
    fn k_exp_ok(self) -> bool {
        true
    }
    #[doc(hidden)]
    #[inline(always)]
    fn k_tanh(self) -> Self {
        self.tanh()
    }
    #[doc(hidden)]
    #[inline(always)]
    fn k_sigmoid(self) -> Self {
        crate::ops::elementwise::sigmoid(self)
    }
    /// The slice as `f32` when `Self` is `f32`: the door to explicit-SIMD `f32` kernels.
    #[doc(hidden)]
    #[inline(always)]
    fn as_f32(_s: &[Self]) -> Option<&[f32]> {
        None
    }
    /// Mutable [`Real::as_f32`].
    #[doc(hidden)]
    #[inline(always)]
    fn as_f32_mut(_s: &mut [Self]) -> Option<&mut [f32]> {
        None
    }
}

impl Real for f32 {
    const NAME: &'static str = "f32";
    const EPS: Self = f32::EPSILON;
    const FAST_MATH: bool = true;
    #[inline(always)]
    fn k_sin(self) -> Self {
        crate::vmath::sin(self)
    }
    #[inline(always)]
    fn k_cos(self) -> Self {
        crate::vmath::cos(self)
    }
    #[inline(always)]
    fn k_sincos(self) -> (Self, Self) {
        crate::vmath::sincos(self)
    }
    #[inline(always)]
    fn k_trig_ok(self) -> bool {
        self.abs() <= crate::vmath::TRIG_MAX
    }
    #[inline(always)]
    fn k_exp(self) -> Self {
        crate::vmath::exp(self)
    }
    #[inline(always)]
    fn k_exp_ok(self) -> bool {
        (crate::vmath::EXP_MIN..=crate::vmath::EXP_MAX).contains(&self)
    }
    #[inline(always)]
    fn k_tanh(self) -> Self {
        crate::vmath::tanh(self)
    }
    #[inline(always)]
    fn k_sigmoid(self) -> Self {
        crate::vmath::sigmoid(self)
    }
    #[inline(always)]
    fn as_f32(s: &[Self]) -> Option<&[f32]> {
        Some(s)
    }
    #[inline(always)]
    fn as_f32_mut(s: &mut [Self]) -> Option<&mut [f32]> {
        Some(s)
    }
    #[inline(always)]
    fn from_f64c(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64c(self) -> f64 {
        self as f64
    }
}

impl Real for f64 {
    const NAME: &'static str = "f64";
    const EPS: Self = f64::EPSILON;
    #[inline(always)]
    fn from_f64c(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64c(self) -> f64 {
        self
    }
}

/// Shorthand for a scalar constant: `c::<T>(0.5)`.
#[inline(always)]
pub fn c<T: Real>(x: f64) -> T {
    T::from_f64c(x)
}
