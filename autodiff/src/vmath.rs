#![allow(clippy::excessive_precision)] // polynomial coefficients as published
//! Branch-free `f32` sin, cos, exp, tanh and sigmoid that the compiler vectorises over slices
//! (libm's scalar calls dominate elementwise chains otherwise).
//!
//! Cephes-style: Cody-Waite argument reduction and short minimax polynomials, written with
//! selects instead of branches, evaluated with fused multiply-adds (`mul_add`: one rounding
//! per Horner step, and half the instructions). Each function is accurate to a few ulp (the
//! tests state the bounds) on the range where the `k_*_ok` predicates of [`crate::Real`]
//! hold; outside it (huge arguments, NaN, infinities, where `exp` would overflow or go
//! subnormal) the kernels in [`crate::tensor`] recompute the element with the exact libm
//! function, so results never lose NaN or infinities.
//!
//! `mul_add` and `floor` are exact operations, so every compiled variant gives the same bits:
//! the AVX2 and AVX-512 kernels run them as single instructions; the baseline x86-64 target
//! (no FMA, no SSE4.1: CPUs before 2013) calls libm's `fmaf` and `floorf`, correct and slower.

/// 4 / pi.
const FOPI: f32 = 1.273_239_5;
/// pi / 4 split in three parts (exact products with small integers).
const DP1: f32 = 0.785_156_25;
const DP2: f32 = 2.418_756_5e-4;
const DP3: f32 = 3.774_895e-8;

/// Largest |x| for which [`sin`] and [`cos`] are used (Cephes' limit for the three-part
/// reduction in single precision).
pub const TRIG_MAX: f32 = 8192.0;
/// Range of [`exp`]: normal results only.
pub const EXP_MIN: f32 = -87.0;
/// Range of [`exp`].
pub const EXP_MAX: f32 = 88.0;

#[inline(always)]
fn sin_poly(r: f32, z: f32) -> f32 {
    let p = (-1.951_529_6e-4f32)
        .mul_add(z, 8.332_161e-3)
        .mul_add(z, -1.666_665_5e-1);
    p.mul_add(z * r, r)
}

#[inline(always)]
fn cos_poly(z: f32) -> f32 {
    2.443_315_7e-5f32
        .mul_add(z, -1.388_731_6e-3)
        .mul_add(z, 4.166_664_6e-2)
        .mul_add(z, -0.5)
        .mul_add(z, 1.0)
}

/// 1.5 * 2^23: for an integer-valued `k` with |k| < 2^22, the low 22 bits of
/// `(k + MAGIC).to_bits()` hold `k` (two's complement), and `k + MAGIC` is exact. Integer
/// parts travel this way rather than through `as i32`, whose saturating conversion compiles to
/// scalar code per lane (about 3x slower kernels); float adds and bit casts vectorise.
const MAGIC: f32 = 12_582_912.0;

/// Octant reduction of |x|: the reduced argument, its square and the (even) octant `j` as the
/// bits of `j + MAGIC` (test its low bits). `floor` is one instruction in the dispatched
/// kernels (SSE4.1 and later); the baseline target calls libm's, with the same bits.
#[inline(always)]
fn reduce(ax: f32) -> (f32, f32, u32) {
    // `min` maps NaN to TRIG_MAX (callers recompute NaN with libm).
    let ax = ax.min(TRIG_MAX);
    let jb = ((ax * FOPI).floor() + MAGIC).to_bits();
    let jb = jb + (jb & 1);
    let y = f32::from_bits(jb) - MAGIC;
    let r = (-y).mul_add(DP3, (-y).mul_add(DP2, (-y).mul_add(DP1, ax)));
    (r, r * r, jb)
}

/// sin x for |x| <= [`TRIG_MAX`].
#[inline(always)]
pub fn sin(x: f32) -> f32 {
    let (r, z, j) = reduce(x.abs());
    let v = if j & 2 != 0 {
        cos_poly(z)
    } else {
        sin_poly(r, z)
    };
    let flip = (j & 4 != 0) != x.is_sign_negative();
    if flip {
        -v
    } else {
        v
    }
}

/// cos x for |x| <= [`TRIG_MAX`].
#[inline(always)]
pub fn cos(x: f32) -> f32 {
    let (r, z, j) = reduce(x.abs());
    let v = if j & 2 != 0 {
        sin_poly(r, z)
    } else {
        cos_poly(z)
    };
    let flip = (j & 4 != 0) != (j & 2 != 0);
    if flip {
        -v
    } else {
        v
    }
}

/// (sin x, cos x) for |x| <= [`TRIG_MAX`] from one octant reduction: the same bits as
/// [`sin`] and [`cos`] (the same reduction, polynomials and signs), for the price of one
/// reduction and both polynomials. The fused evaluator keeps the cosine of a `sin` node as its
/// derivative for the backward sweep.
#[inline(always)]
pub fn sincos(x: f32) -> (f32, f32) {
    let (r, z, j) = reduce(x.abs());
    let (ps, pc) = (sin_poly(r, z), cos_poly(z));
    let swap = j & 2 != 0;
    let (s, c) = if swap { (pc, ps) } else { (ps, pc) };
    let s = if (j & 4 != 0) != x.is_sign_negative() {
        -s
    } else {
        s
    };
    let c = if (j & 4 != 0) != swap { -c } else { c };
    (s, c)
}

/// Cody-Waite reduction for [`exp`] and [`expm1_pos`]: `x = n ln 2 + r`, |r| <= ln 2 / 2, and
/// the polynomial part `p = e^r - 1 = r + r^2 P(r)` (Cephes expf's minimax `P`), accurate
/// relative to `e^r - 1` itself (no `1 +` inside), with `2^n`.
#[inline(always)]
fn exp_reduced(x: f32) -> (f32, f32) {
    // n = floor(x / ln 2 + 1/2); NaN gives some n (callers recompute NaN with libm).
    let nf = (x * std::f32::consts::LOG2_E + 0.5).floor();
    let r = (-nf).mul_add(-2.121_944_4e-4, (-nf).mul_add(0.693_359_4, x));
    let p = 1.987_569_1e-4f32
        .mul_add(r, 1.398_199_9e-3)
        .mul_add(r, 8.333_452e-3)
        .mul_add(r, 4.166_579_6e-2)
        .mul_add(r, 1.666_666_5e-1)
        .mul_add(r, 5.000_000_1e-1);
    // 2^n for n in the normal exponent range: the biased exponent n + 127 sits in the low
    // bits of `n + 127 + MAGIC` (see [`MAGIC`]).
    let scale = f32::from_bits((nf + (MAGIC + 127.0)).to_bits() << 23);
    (p.mul_add(r * r, r), scale)
}

/// e^x for x in [[`EXP_MIN`], [`EXP_MAX`]] (clamped to it).
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let (p, scale) = exp_reduced(x.clamp(EXP_MIN, EXP_MAX));
    (p + 1.0) * scale
}

/// e^a - 1 for a in [0, 20], accurate relative to the result for small `a` too:
/// `2^n (e^r - 1) + (2^n - 1)`.
#[inline(always)]
fn expm1_pos(a: f32) -> f32 {
    let (p, s) = exp_reduced(a);
    s.mul_add(p, s - 1.0)
}

/// tanh x (any x except NaN) from one formula, `sign(x) m / (m + 2)` with
/// `m = e^{2|x|} - 1`, branch-free so that loops over it vectorise: no cancellation near 0
/// (where `m` is accurate relative to itself), exactly +-1 beyond |x| = 10.
#[inline(always)]
pub fn tanh(x: f32) -> f32 {
    let m = expm1_pos(2.0 * x.abs().min(10.0));
    (m / (m + 2.0)).copysign(x)
}

/// The logistic function 1 / (1 + e^-x) for |x| <= -[`EXP_MIN`].
#[inline(always)]
pub fn sigmoid(x: f32) -> f32 {
    let e = exp(-x.abs());
    let r = 1.0 / (1.0 + e);
    if x >= 0.0 {
        r
    } else {
        e * r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in units in the last place between an f32 and the f64 reference.
    fn ulps(got: f32, want: f64) -> f64 {
        let w = want as f32;
        if got == w {
            return 0.0;
        }
        let ulp = (f32::from_bits(w.abs().to_bits() + 1) - w.abs()) as f64;
        (got as f64 - want).abs() / ulp
    }

    fn sweep(lo: f32, hi: f32, n: usize) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| lo + (hi - lo) * (i as f32 / n as f32))
    }

    #[test]
    fn trig_is_accurate() {
        let (mut ws, mut wc) = (0.0f64, 0.0f64);
        for x in sweep(-TRIG_MAX, TRIG_MAX, 2_000_000).chain(sweep(-10.0, 10.0, 200_000)) {
            // Absolute error near the zeros, relative elsewhere.
            let (s, c) = ((x as f64).sin(), (x as f64).cos());
            ws = ws.max(if s.abs() < 0.5 {
                ((sin(x) as f64) - s).abs() / 2f64.powi(-25)
            } else {
                ulps(sin(x), s)
            });
            wc = wc.max(if c.abs() < 0.5 {
                ((cos(x) as f64) - c).abs() / 2f64.powi(-25)
            } else {
                ulps(cos(x), c)
            });
        }
        // Measured: 1.49 and 1.48 (FMA Horner steps).
        assert!(ws <= 2.0 && wc <= 2.0, "sin {ws} cos {wc}");
        for x in [0.0f32, -0.0, 1e-30, -1e-30] {
            assert_eq!(sin(x).to_bits(), x.to_bits(), "{x}");
        }
    }

    /// `sincos` gives the bits of `sin` and `cos`.
    #[test]
    fn sincos_is_sin_and_cos() {
        for x in sweep(-TRIG_MAX, TRIG_MAX, 200_000).chain(sweep(-10.0, 10.0, 20_000)) {
            let (s, c) = sincos(x);
            assert_eq!(
                (s.to_bits(), c.to_bits()),
                (sin(x).to_bits(), cos(x).to_bits()),
                "{x}"
            );
        }
    }

    #[test]
    fn exp_tanh_sigmoid_are_accurate() {
        let mut w = [0.0f64; 3];
        for x in sweep(EXP_MIN, EXP_MAX, 2_000_000) {
            w[0] = w[0].max(ulps(exp(x), (x as f64).exp()));
        }
        for x in sweep(-12.0, 12.0, 2_000_000) {
            let t = (x as f64).tanh();
            w[1] = w[1].max(if t.abs() < 0.5 {
                ((tanh(x) as f64) - t).abs() / (t.abs() * 2f64.powi(-23)).max(1e-45)
            } else {
                ulps(tanh(x), t)
            });
            let s = 1.0 / (1.0 + (-(x as f64)).exp());
            w[2] = w[2].max(ulps(sigmoid(x), s));
        }
        // Measured: exp 0.99, tanh 1.49, sigmoid 2.66 ulp.
        assert!(
            w[0] <= 1.0 && w[1] <= 2.0 && w[2] <= 3.0,
            "exp {} tanh {} sigmoid {}",
            w[0],
            w[1],
            w[2]
        );
        assert_eq!(tanh(100.0), 1.0);
        assert_eq!(tanh(-100.0), -1.0);
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(sigmoid(0.0), 0.5);
    }

    /// tanh near 0 keeps full relative accuracy; NaN-free arguments give finite results.
    #[test]
    fn tanh_small_arguments() {
        for x in [1e-30f32, -1e-30, 1e-8, -3e-5, 0.01, 0.3] {
            let t = (x as f64).tanh();
            assert!(ulps(tanh(x), t) <= 2.0, "{x}");
        }
        assert_eq!(tanh(0.0).to_bits(), 0.0f32.to_bits());
        assert_eq!(tanh(-0.0).to_bits(), (-0.0f32).to_bits());
    }
}
