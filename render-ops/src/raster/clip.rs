//! Viewport transform, frustum outcodes and near/far polygon clipping for screen bounds.
//!
//! Only the *bounding box* of a triangle comes from clipping: coverage and barycentrics come from
//! the homogeneous edge functions of the original triangle (Olano and Greer 1997), and the
//! near/far planes are a per-fragment depth test. Triangles crossing `z = -w` or `z = w` are
//! clipped with Sutherland-Hodgman (1974) against those two planes so that the remaining polygon
//! has `w >= 0` and can be projected to a finite box.

use autodiff::Real;

/// Outcode bits of a clip-space vertex (outside the plane named).
pub(crate) const OUT_NEAR: u8 = 1;
pub(crate) const OUT_FAR: u8 = 2;
pub(crate) const OUT_LEFT: u8 = 4;
pub(crate) const OUT_RIGHT: u8 = 8;
pub(crate) const OUT_BOTTOM: u8 = 16;
pub(crate) const OUT_TOP: u8 = 32;

/// Inclusive pixel rectangle `[c0, c1] x [r0, r1]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Rect {
    pub c0: u32,
    pub c1: u32,
    pub r0: u32,
    pub r1: u32,
}

impl Rect {
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.c0 > self.c1 || self.r0 > self.r1
    }

    #[inline]
    pub fn intersect(&self, o: &Rect) -> Rect {
        Rect {
            c0: self.c0.max(o.c0),
            c1: self.c1.min(o.c1),
            r0: self.r0.max(o.r0),
            r1: self.r1.min(o.r1),
        }
    }
}

/// Transforms clip `(x, y, z, w)` to the screen frame `(X, Y, W, z)`, where a point projects to
/// pixel coordinates `(X / W, Y / W)` with pixel centres at integers (`col`, `row`, row 0 at the
/// top); also returns that projection (NaN when `W <= 0`) and the vertex's outcode.
///
/// `X = x W_img / 2 + w (W_img / 2 - 1/2)`, `Y = -y H_img / 2 + w (H_img / 2 - 1/2)`.
#[inline]
pub(crate) fn to_screen<T: Real>(
    c: &[T; 4],
    width: usize,
    height: usize,
) -> ([f64; 4], [f64; 2], u8) {
    let [x, y, z, w] = c.map(|v| v.to_f64c());
    let hw = width as f64 * 0.5;
    let hh = height as f64 * 0.5;
    let sx = x * hw + w * (hw - 0.5);
    let sy = -y * hh + w * (hh - 0.5);
    let mut oc = 0;
    if z < -w {
        oc |= OUT_NEAR;
    }
    if z > w {
        oc |= OUT_FAR;
    }
    if x < -w {
        oc |= OUT_LEFT;
    }
    if x > w {
        oc |= OUT_RIGHT;
    }
    if y < -w {
        oc |= OUT_BOTTOM;
    }
    if y > w {
        oc |= OUT_TOP;
    }
    let proj = if w > 0.0 {
        [sx / w, sy / w]
    } else {
        [f64::NAN; 2]
    };
    ([sx, sy, w, z], proj, oc)
}

/// Clips the polygon `inp[..n]` to `dist(v) >= 0` (Sutherland-Hodgman), writing to `out`.
pub(crate) fn clip_plane(
    inp: &[[f64; 4]; 5],
    n: usize,
    dist: impl Fn(&[f64; 4]) -> f64,
    out: &mut [[f64; 4]; 5],
) -> usize {
    let mut m = 0;
    for i in 0..n {
        let p = &inp[(i + n - 1) % n];
        let q = &inp[i];
        let (dp, dq) = (dist(p), dist(q));
        if (dp >= 0.0) != (dq >= 0.0) {
            let t = dp / (dp - dq);
            let mut r = [0.0; 4];
            for k in 0..4 {
                r[k] = p[k] + t * (q[k] - p[k]);
            }
            if m < 5 {
                out[m] = r;
                m += 1;
            }
        }
        if dq >= 0.0 && m < 5 {
            out[m] = *q;
            m += 1;
        }
    }
    m
}

/// `floor(x)` for `0 <= x < 2^32` (a truncating cast; baseline x86-64 has no `roundsd`).
#[inline(always)]
pub(crate) fn floor_u(x: f64) -> u32 {
    x as u32
}

/// `ceil(x)` for `0 <= x < 2^32`.
#[inline(always)]
pub(crate) fn ceil_u(x: f64) -> u32 {
    let f = x as u32;
    f + ((f as f64) < x) as u32
}

/// `min` without NaN handling (returns `b` when either is NaN).
#[inline(always)]
fn fmin(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// `max` without NaN handling (returns `b` when either is NaN).
#[inline(always)]
fn fmax(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

/// Pixel centres `[ceil(lo - pad), floor(hi + pad)]` clamped to `0..n`, `None` if there are
/// none. With `pad = 0` and `lo`, `hi` rounded projections this is exact: rounding is monotone
/// and pixel centres are representable, so no covered centre is lost.
#[inline]
fn px_range(lo: f64, hi: f64, n: u32, pad: f64) -> Option<(u32, u32)> {
    let last = (n - 1) as f64;
    if !(lo <= hi) {
        // NaN from overflow: stay conservative.
        return Some((0, n - 1));
    }
    let (lo, hi) = (lo - pad, hi + pad);
    if hi < 0.0 || lo > last {
        return None;
    }
    let (a, b) = (ceil_u(fmax(lo, 0.0)), floor_u(fmin(hi, last)));
    (a <= b).then_some((a, b))
}

/// Screen bounding box (inclusive pixel centres, clamped to the image) of the part of the
/// triangle inside the frustum, or `None` when it is culled (wholly outside one frustum plane,
/// or off screen). `verts[idx]`, `proj` and `oc` come from [`to_screen`]; `verts` is only read
/// for triangles crossing the near or far plane.
#[inline]
pub(crate) fn screen_bounds(
    verts: &[[f64; 4]],
    idx: [usize; 3],
    proj: &[[f64; 2]; 3],
    oc: [u8; 3],
    width: u32,
    height: u32,
) -> Option<Rect> {
    if oc[0] & oc[1] & oc[2] != 0 {
        return None;
    }
    let full = Rect {
        c0: 0,
        c1: width - 1,
        r0: 0,
        r1: height - 1,
    };
    let any = oc[0] | oc[1] | oc[2];
    let (x0, x1, y0, y1, pad);
    if any & (OUT_NEAR | OUT_FAR) == 0 {
        // Inside -w <= z <= w all w >= 0; w == 0 (a point at infinity, projected to NaN) gives
        // no usable box, so fall back to the whole screen (coverage stays exact).
        if proj.iter().flatten().any(|x| x.is_nan()) {
            return Some(full);
        }
        let [p, q, r] = proj;
        x0 = fmin(fmin(p[0], q[0]), r[0]);
        x1 = fmax(fmax(p[0], q[0]), r[0]);
        y0 = fmin(fmin(p[1], q[1]), r[1]);
        y1 = fmax(fmax(p[1], q[1]), r[1]);
        pad = 0.0;
    } else {
        let mut poly = [[0.0; 4]; 5];
        for (p, &i) in poly.iter_mut().zip(&idx) {
            *p = verts[i];
        }
        let mut n = 3;
        if any & OUT_NEAR != 0 {
            let mut out = [[0.0; 4]; 5];
            n = clip_plane(&poly, n, |p| p[3] + p[2], &mut out);
            poly = out;
        }
        if any & OUT_FAR != 0 {
            let mut out = [[0.0; 4]; 5];
            n = clip_plane(&poly, n, |p| p[2] - p[3], &mut out);
            poly = out;
        }
        if n == 0 {
            return None;
        }
        let (mut a0, mut a1, mut b0, mut b1) = (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        );
        for p in &poly[..n] {
            if !(p[2] > 0.0) {
                return Some(full);
            }
            let (x, y) = (p[0] / p[2], p[1] / p[2]);
            a0 = a0.min(x);
            a1 = a1.max(x);
            b0 = b0.min(y);
            b1 = b1.max(y);
        }
        (x0, x1, y0, y1) = (a0, a1, b0, b1);
        // Boxes of clipped polygons carry interpolation error: pad them by a pixel.
        pad = 1.0;
    }
    let (c0, c1) = px_range(x0, x1, width, pad)?;
    let (r0, r1) = px_range(y0, y1, height, pad)?;
    Some(Rect { c0, c1, r0, r1 })
}
