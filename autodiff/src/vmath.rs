#![allow(clippy::excessive_precision)] // polynomial coefficients as published
#![allow(clippy::needless_range_loop)] // `&x[..n]` re-slices: no bounds checks, loops vectorise
//! Branch-free `f32` sin, cos, exp, tanh and sigmoid that the compiler vectorises over slices
//! (libm's scalar calls dominate elementwise chains otherwise).
//!
//! Cephes-style: Cody-Waite argument reduction and short minimax polynomials, written with
//! selects instead of branches. Each function is accurate to a few ulp on the range where
//! [`in_range`]-style predicates hold; outside it (huge arguments, NaN, infinities, where `exp`
//! would overflow or go subnormal) the kernels in [`crate::tensor`] recompute the element with
//! the exact libm function, so results never lose NaN or infinities.

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
    ((-1.951_529_6e-4 * z + 8.332_161e-3) * z - 1.666_665_5e-1) * z * r + r
}

#[inline(always)]
fn cos_poly(z: f32) -> f32 {
    ((2.443_315_7e-5 * z - 1.388_731_6e-3) * z + 4.166_664_6e-2) * z * z - 0.5 * z + 1.0
}

/// 1.5 * 2^23: `(t + MAGIC) - MAGIC` rounds `t` to the nearest integer, and the low bits of
/// `t + MAGIC` hold that integer, for |t| < 2^22.
const MAGIC: f32 = 12_582_912.0;

/// floor(t) as an integer, for |t| < 2^22, without `as i32`: Rust's saturating float-to-int
/// cast compiles to scalar code per lane, which kept these kernels from vectorising (about 3x
/// slower). Float adds and bit casts vectorise on every target.
#[inline(always)]
fn floor_i32(t: f32) -> i32 {
    let r = (t + MAGIC) - MAGIC;
    let f = r - if r > t { 1.0 } else { 0.0 };
    ((f + MAGIC).to_bits() as i32).wrapping_sub(MAGIC.to_bits() as i32)
}

/// Octant reduction of |x|: the reduced argument, its square and the (even) octant.
#[inline(always)]
fn reduce(ax: f32) -> (f32, f32, i32) {
    // `min` maps NaN to TRIG_MAX (callers recompute NaN with libm).
    let ax = ax.min(TRIG_MAX);
    let mut j = floor_i32(ax * FOPI);
    j += j & 1;
    let y = j as f32;
    let r = ((ax - y * DP1) - y * DP2) - y * DP3;
    (r, r * r, j)
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
    let flip = (j & 4 != 0) != (x < 0.0);
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
    let s = if (j & 4 != 0) != (x < 0.0) { -s } else { s };
    let c = if (j & 4 != 0) != swap { -c } else { c };
    (s, c)
}

/// e^x for x in [[`EXP_MIN`], [`EXP_MAX`]] (clamped to it).
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let x = x.clamp(EXP_MIN, EXP_MAX);
    // n = round(x / ln 2) without a call to floor (not vectorisable on baseline x86-64).
    let t = x * std::f32::consts::LOG2_E + 0.5;
    // NaN gives some n; callers recompute NaN with libm.
    let n = floor_i32(t);
    let nf = n as f32;
    let r = (x - nf * 0.693_359_4) - nf * -2.121_944_4e-4;
    let z = r * r;
    let p = (((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2)
        * r
        + 1.666_666_5e-1)
        * r
        + 5.000_000_1e-1)
        * z
        + r
        + 1.0;
    p * f32::from_bits((n.wrapping_add(127) as u32) << 23)
}

/// Below this |x|, [`tanh`] uses its odd polynomial ([`tanh_small`]), else [`tanh_big`].
pub const TANH_SMALL: f32 = 0.625;

/// tanh x for |x| < [`TANH_SMALL`]: odd polynomial (Cephes tanhf).
#[inline(always)]
pub fn tanh_small(x: f32) -> f32 {
    let z = x * x;
    ((((-5.704_988_7e-3 * z + 2.063_908_9e-2) * z - 5.373_971_6e-2) * z + 1.333_144_2e-1) * z
        - 3.333_328_2e-1)
        * z
        * x
        + x
}

/// tanh x for |x| >= [`TANH_SMALL`] (any x except NaN): sign(x) (1 - 2 / (e^{2|x|} + 1)),
/// exactly 1 in f32 beyond |x| = 10.
#[inline(always)]
pub fn tanh_big(x: f32) -> f32 {
    let e = exp(2.0 * x.abs().min(10.0));
    let big = 1.0 - 2.0 / (e + 1.0);
    if x < 0.0 {
        -big
    } else {
        big
    }
}

/// tanh x (any x except NaN): [`tanh_small`] or [`tanh_big`], both evaluated and one selected
/// (branch-free, so that loops over it vectorise).
#[inline(always)]
pub fn tanh(x: f32) -> f32 {
    let (small, big) = (tanh_small(x), tanh_big(x));
    if x.abs() < TANH_SMALL {
        small
    } else {
        big
    }
}

/// `o[i] = tanh(x[i])` (bit for bit as [`tanh`], NaN kept): when every |x| lies on one side of
/// [`TANH_SMALL`] only that side's formula is evaluated (the exp and the division of
/// [`tanh_big`] are three quarters of [`tanh`]'s work; arguments of one chunk often share a
/// side); otherwise [`tanh`] per element and libm's for NaN.
#[inline(always)]
pub fn tanh_slice(o: &mut [f32], x: &[f32]) {
    let n = o.len();
    let x = &x[..n];
    // Comparisons with NaN are false: a NaN makes both flags false.
    let (small, big) = x.iter().fold((true, true), |(s, b), &v| {
        (s & (v.abs() < TANH_SMALL), b & (v.abs() >= TANH_SMALL))
    });
    if big {
        for i in 0..n {
            o[i] = tanh_big(x[i]);
        }
    } else if small {
        for i in 0..n {
            o[i] = tanh_small(x[i]);
        }
    } else {
        let mut finite = true;
        for i in 0..n {
            o[i] = tanh(x[i]);
            finite &= !x[i].is_nan();
        }
        if !finite {
            for i in 0..n {
                if x[i].is_nan() {
                    o[i] = x[i].tanh();
                }
            }
        }
    }
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
        assert!(ws <= 4.0 && wc <= 4.0, "sin {ws} cos {wc}");
        for x in [0.0f32, -0.0, 1e-30, 1.0, -1.0] {
            assert_eq!(sin(x), x.sin(), "{x}");
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
        assert!(
            w[0] <= 2.0 && w[1] <= 4.0 && w[2] <= 4.0,
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

    /// The one-sided paths of `tanh_slice` give `tanh`'s bits; NaN stays NaN.
    #[test]
    fn tanh_slice_is_tanh() {
        let small: Vec<f32> = sweep(-0.62, 0.62, 999).collect();
        let big: Vec<f32> = sweep(0.625, 12.0, 999)
            .chain(sweep(-12.0, -0.625, 999))
            .collect();
        let mut mixed: Vec<f32> = sweep(-3.0, 3.0, 999).collect();
        mixed[17] = f32::NAN;
        for x in [small, big, mixed] {
            let mut o = vec![0.0f32; x.len()];
            tanh_slice(&mut o, &x);
            for (&o, &x) in o.iter().zip(&x) {
                if x.is_nan() {
                    assert!(o.is_nan());
                } else {
                    assert_eq!(o.to_bits(), tanh(x).to_bits(), "{x}");
                }
            }
        }
    }
}
