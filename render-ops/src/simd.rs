#![allow(clippy::excessive_precision)] // polynomial coefficients as published
//! Eight-lane `f32` values for the `f32` fast paths (the hard rasterizer, `hard_grad`, the soft
//! rasterizers [`crate::soft::softras`], [`crate::soft::dibr`]):
//! plain arrays whose element-wise operations the compiler turns into 8-lane AVX vector
//! instructions inside functions compiled with `#[target_feature(enable = "avx2")]`, and into
//! SSE code (or scalar code) elsewhere, from the same source.
//!
//! Every operation is an IEEE single-precision operation per lane (no fused multiply-adds, no
//! reassociation, integer conversions through bit tricks rather than saturating casts), so
//! the AVX2 build and the portable fallback give bit-identical results; [`set_force_portable`]
//! makes the kernels take the fallback, for tests. The ray tracer's `f64` packets
//! ([`crate::raytrace`]) use the same lane helpers ([`lanes`], [`arr3`]), built for AVX-512 or
//! AVX2 by [`avx2_method`]`!(wide ..)`.

use std::ops::{Add, BitAnd, BitOr, Div, Mul, Neg, Not, Sub};
use std::sync::atomic::{AtomicBool, Ordering};

/// Lanes per vector.
pub(crate) const LANES: usize = 8;

/// Eight `f32` lanes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct F8(pub [f32; LANES]);

/// Eight lane masks, each all ones (true) or all zeros (false).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct M8(pub [u32; LANES]);

macro_rules! lanewise {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for F8 {
            type Output = F8;
            #[inline(always)]
            fn $f(self, o: F8) -> F8 {
                F8(lanes(|i| self.0[i] $op o.0[i]))
            }
        }
    };
}
lanewise!(Add, add, +);
lanewise!(Sub, sub, -);
lanewise!(Mul, mul, *);
lanewise!(Div, div, /);

impl Neg for F8 {
    type Output = F8;
    #[inline(always)]
    fn neg(self) -> F8 {
        F8(self.0.map(|x| -x))
    }
}

impl BitAnd for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitand(self, o: M8) -> M8 {
        M8(lanes(|i| self.0[i] & o.0[i]))
    }
}

impl BitOr for M8 {
    type Output = M8;
    #[inline(always)]
    fn bitor(self, o: M8) -> M8 {
        M8(lanes(|i| self.0[i] | o.0[i]))
    }
}

impl Not for M8 {
    type Output = M8;
    #[inline(always)]
    fn not(self) -> M8 {
        M8(self.0.map(|x| !x))
    }
}

/// `[f(0), .., f(7)]`, as a plain loop that is always inlined (`std::array::from_fn` may be
/// left out of line, and then it runs without the caller's target features).
#[inline(always)]
pub(crate) fn lanes<T: Copy + Default, F: FnMut(usize) -> T>(mut f: F) -> [T; LANES] {
    let mut o = [T::default(); LANES];
    for (i, v) in o.iter_mut().enumerate() {
        *v = f(i);
    }
    o
}

/// `[f(0), f(1), f(2)]`, always inlined (see [`lanes`]).
#[inline(always)]
pub(crate) fn arr3<T: Copy + Default, F: FnMut(usize) -> T>(mut f: F) -> [T; 3] {
    [f(0), f(1), f(2)]
}

#[inline(always)]
fn mask(b: bool) -> u32 {
    if b {
        u32::MAX
    } else {
        0
    }
}

impl M8 {
    /// Whether any lane is set.
    #[inline(always)]
    pub fn any(self) -> bool {
        self.0.iter().fold(0, |a, &b| a | b) != 0
    }

    /// Lane `l` set.
    #[inline(always)]
    pub fn lane(self, l: usize) -> bool {
        self.0[l] != 0
    }
}

/// `a` where `m` is set, else `b`. Written as a per-lane choice on the mask's sign bit
/// (every lane of an [`M8`] is all ones or all zeros, so this is the bitwise select), which
/// the compiler turns into one blend instruction instead of and, and-not and or.
#[inline(always)]
pub(crate) fn select(m: M8, a: F8, b: F8) -> F8 {
    F8(lanes(|i| if (m.0[i] as i32) < 0 { a.0[i] } else { b.0[i] }))
}

impl M8 {
    /// `a` where `self` is set, else `b` (as [`select`]).
    #[inline(always)]
    pub fn select(self, a: M8, b: M8) -> M8 {
        M8(lanes(|i| {
            if (self.0[i] as i32) < 0 {
                a.0[i]
            } else {
                b.0[i]
            }
        }))
    }
}

impl F8 {
    #[inline(always)]
    pub fn splat(x: f32) -> F8 {
        F8([x; LANES])
    }

    /// The first eight values of `s`.
    #[inline(always)]
    pub fn load(s: &[f32]) -> F8 {
        F8(s[..LANES].try_into().expect("eight values"))
    }

    /// Into the first eight values of `s`.
    #[inline(always)]
    pub fn store(self, s: &mut [f32]) {
        s[..LANES].copy_from_slice(&self.0);
    }

    /// `min(self, o)` per lane (`o` where either is NaN).
    #[inline(always)]
    pub fn min(self, o: F8) -> F8 {
        F8(lanes(|i| {
            if self.0[i] < o.0[i] {
                self.0[i]
            } else {
                o.0[i]
            }
        }))
    }

    /// `max(self, o)` per lane (`o` where either is NaN).
    #[inline(always)]
    pub fn max(self, o: F8) -> F8 {
        F8(lanes(|i| {
            if self.0[i] > o.0[i] {
                self.0[i]
            } else {
                o.0[i]
            }
        }))
    }

    #[inline(always)]
    pub fn abs(self) -> F8 {
        F8(self.0.map(|x| f32::from_bits(x.to_bits() & 0x7fff_ffff)))
    }

    #[inline(always)]
    pub fn lt(self, o: F8) -> M8 {
        M8(lanes(|i| mask(self.0[i] < o.0[i])))
    }

    #[inline(always)]
    pub fn le(self, o: F8) -> M8 {
        M8(lanes(|i| mask(self.0[i] <= o.0[i])))
    }

    #[inline(always)]
    pub fn gt(self, o: F8) -> M8 {
        M8(lanes(|i| mask(self.0[i] > o.0[i])))
    }

    #[inline(always)]
    pub fn ge(self, o: F8) -> M8 {
        M8(lanes(|i| mask(self.0[i] >= o.0[i])))
    }

    /// The lanes summed in `f64` in a fixed order (deterministic): lane `i` plus lane
    /// `i + 4`, then those four pairwise (the compiler's 4-lane `f64` vector code).
    #[inline(always)]
    pub fn sum_f64(self) -> f64 {
        let h = |i: usize| self.0[i] as f64 + self.0[i + 4] as f64;
        (h(0) + h(2)) + (h(1) + h(3))
    }
}

/// 1.5 * 2^23: `(t + MAGIC) - MAGIC` rounds `t` to the nearest integer, and the low bits of
/// `t + MAGIC` hold that integer, for |t| < 2^22 (no saturating float-to-int cast, which
/// compiles to scalar code per lane).
const MAGIC: f32 = 12_582_912.0;

/// Smallest argument of [`exp8`]: below it `e^x` is not a normal `f32`; callers treat
/// `x < EXP_MIN` as `e^x = 0` (a relative change below `1.2e-38` of the largest term of any
/// sum they take, see [`crate::soft::softras`]).
pub(crate) const EXP_MIN: f32 = -87.0;

/// `e^x` per lane for `x` in `[EXP_MIN, 88]` (clamped to it): Cody-Waite reduction `x = n ln 2
/// + r`, `|r| <= ln(2) / 2`, and Cephes' degree-7 minimax polynomial for `e^r` (as
/// `autodiff`'s vectorised `exp`), within 2 ulp of the exact value (tested).
#[inline(always)]
pub(crate) fn exp8(x: F8) -> F8 {
    F8(lanes(|i| {
        let x = x.0[i];
        let x = if x > EXP_MIN { x } else { EXP_MIN };
        let x = if x < 88.0 { x } else { 88.0 };
        let t = x * std::f32::consts::LOG2_E + MAGIC;
        let nf = t - MAGIC;
        let n = (t.to_bits() as i32).wrapping_sub(MAGIC.to_bits() as i32);
        let r = (x - nf * 0.693_359_4) - nf * -2.121_944_4e-4;
        let z = r * r;
        let p = (((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r
            + 4.166_579_6e-2)
            * r
            + 1.666_666_5e-1)
            * r
            + 5.000_000_1e-1)
            * z
            + r
            + 1.0;
        p * f32::from_bits((n.wrapping_add(127) as u32) << 23)
    }))
}

/// One instruction-set tier of a dispatched method: runs `$self.$imp(args..)` built with the
/// tier's target features (`avx512`: F, BW, DQ, VL; `avx2`) and returns, where the CPU has
/// them (runtime detection, [`use_avx512`] / [`use_avx2`]); else falls through.
macro_rules! simd_tier {
    (avx512, $($rest:tt)*) => {
        $crate::simd::simd_tier!(@ "avx512f,avx512bw,avx512dq,avx512vl", use_avx512, $($rest)*)
    };
    (avx2, $($rest:tt)*) => {
        $crate::simd::simd_tier!(@ "avx2", use_avx2, $($rest)*)
    };
    (@ $feat:literal, $detect:ident, $self:ident, $imp:ident, $op:ty, ($($a:ident: $t:ty),*)) => {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = $feat)]
            fn tier(op: &$op, $($a: $t),*) {
                op.$imp($($a),*)
            }
            if $crate::simd::$detect() {
                // SAFETY: the CPU has the tier's features (runtime detection in `$detect`).
                unsafe { tier($self, $($a),*) };
                return;
            }
        }
    };
}
pub(crate) use simd_tier;

/// Defines the method `$entry(&self, args..)` of `$op`, which runs `self.$imp(args..)` built
/// with AVX2 enabled where the CPU has it ([`use_avx2`]) and as portable code otherwise: the
/// same source, so the same bits (`$imp` must be `#[inline(always)]`). `wide` puts an AVX-512
/// build first ([`use_avx512`]), for kernels in `f64` lanes of eight (one AVX-512 register).
macro_rules! avx2_method {
    ($(#[$doc:meta])* $vis:vis fn $entry:ident => $imp:ident($($a:ident: $t:ty),* $(,)?) for $op:ty) => {
        $(#[$doc])*
        $vis fn $entry(&self, $($a: $t),*) {
            $crate::simd::simd_tier!(avx2, self, $imp, $op, ($($a: $t),*));
            self.$imp($($a),*)
        }
    };
    (wide $(#[$doc:meta])* $vis:vis fn $entry:ident => $imp:ident($($a:ident: $t:ty),* $(,)?) for $op:ty) => {
        $(#[$doc])*
        $vis fn $entry(&self, $($a: $t),*) {
            $crate::simd::simd_tier!(avx512, self, $imp, $op, ($($a: $t),*));
            $crate::simd::simd_tier!(avx2, self, $imp, $op, ($($a: $t),*));
            self.$imp($($a),*)
        }
    };
}
pub(crate) use avx2_method;

static FORCE_PORTABLE: AtomicBool = AtomicBool::new(false);

/// Makes the kernels take the portable build even where AVX2 is available (tests: both builds
/// must agree bit for bit).
#[cfg(test)]
pub(crate) fn set_force_portable(on: bool) {
    FORCE_PORTABLE.store(on, Ordering::Relaxed);
}

/// Whether the AVX2 builds of the kernels may run: the CPU has AVX2 (runtime detection) and
/// the portable build is not forced.
#[inline]
pub(crate) fn use_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        !FORCE_PORTABLE.load(Ordering::Relaxed) && std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether the AVX-512 builds (F, BW, DQ, VL) of the kernels that have one may run (as
/// [`use_avx2`]).
#[inline]
pub(crate) fn use_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        !FORCE_PORTABLE.load(Ordering::Relaxed)
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512dq")
            && std::arch::is_x86_feature_detected!("avx512vl")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::rng::Rng;

    /// [`exp8`] within 2 ulp of `f64::exp` rounded to `f32`, over its whole range.
    #[test]
    fn exp8_is_accurate() {
        let mut rng = Rng::new(9);
        let mut worst = 0.0f64;
        for _ in 0..20_000 {
            let xs = F8(std::array::from_fn(|_| rng.uniform(-87.0, 88.0) as f32));
            let e = exp8(xs);
            for l in 0..LANES {
                let exact = (xs.0[l] as f64).exp();
                let ulp = (exact as f32).abs() * f32::EPSILON;
                worst = worst.max((e.0[l] as f64 - exact).abs() / ulp as f64);
            }
        }
        assert!(worst <= 2.0, "{worst} ulp");
        assert_eq!(exp8(F8::splat(0.0)).0[0], 1.0);
    }

    #[test]
    fn select_and_compare() {
        let a = F8([0.0, 1.0, -1.0, 2.0, f32::INFINITY, -0.0, 3.0, 4.0]);
        let b = F8::splat(1.0);
        let m = a.lt(b);
        assert_eq!(
            select(m, a, b).0,
            [0.0, 1.0, -1.0, 1.0, 1.0, -0.0, 1.0, 1.0]
        );
        assert!(m.any() && !(m & !m).any());
        assert_eq!(a.min(b).0[3], 1.0);
        assert_eq!(a.max(b).0[3], 2.0);
    }
}
