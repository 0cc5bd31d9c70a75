//! Eight-lane row chunks shared by the soft rasterizers' `f32` fast paths
//! ([`super::softras`], [`super::dibr`]): per-face `f32` geometry relative to the first vertex,
//! chunks of 8 consecutive pixels of a row span (lane masks, pixel offsets), and the bands of
//! whole image rows the forwards run over in parallel.

use rayon::prelude::*;

use super::common::{FaceGeom, TileBins};
use crate::simd::{arr3, select, F8, LANES, M8};

/// Image rows per band of the forward ([`band_rows`]): the forward runs over bands of whole
/// image rows in parallel (not over 16 x 16 tiles as the `f64` evaluation), so that no row
/// span is cut at tile columns into more 8-pixel chunks, and each band writes its own rows of
/// the image and of the per-pixel aggregate directly. A band holds about `BAND_PIXELS` pixels
/// (8 rows at 256 pixels a row, fewer rows for wider images), so that its per-pixel scratch
/// and its list of kept chunks stay cache-sized.
const BAND_PIXELS: usize = 2048;

/// Rows per band for images `width` pixels wide (1 to 8).
pub(crate) fn band_rows(width: usize) -> usize {
    (BAND_PIXELS / width.max(1)).clamp(1, 8)
}

/// One face's screen geometry in `f32`, relative to its first vertex `o` (set up once per
/// forward for every face, [`geoms32`]).
#[derive(Clone, Copy)]
pub(crate) struct Geom32 {
    /// First vertex (origin of the relative coordinates), NDC, `f64`.
    pub(crate) o: [f64; 2],
    /// `w_k(q) = bw[k][0] + bw[k][1] q_x + bw[k][2] q_y`, `q = p - o`.
    pub(crate) bw: [[f32; 3]; 3],
    pub(crate) alt: [f32; 3],
    /// Vertices relative to `o`.
    pub(crate) v: [[f32; 2]; 3],
    /// Edge `k`: `v[k + 1] - v[k]`.
    pub(crate) e: [[f32; 2]; 3],
    pub(crate) inv_ee: [f32; 3],
    pub(crate) inv_d: [f32; 3],
}

impl Geom32 {
    #[inline(always)]
    pub(crate) fn new(g: &FaceGeom) -> Self {
        let o = g.v[0];
        let v = g.v.map(|q| [(q[0] - o[0]) as f32, (q[1] - o[1]) as f32]);
        let e = arr3(|k| {
            let (a, b) = (g.v[k], g.v[(k + 1) % 3]);
            [(b[0] - a[0]) as f32, (b[1] - a[1]) as f32]
        });
        Self {
            o,
            bw: g.bw.map(|b| b.map(|x| x as f32)),
            alt: g.alt.map(|x| x as f32),
            v,
            e,
            inv_ee: g.inv_ee.map(|x| x as f32),
            inv_d: g.inv_d.map(|x| x as f32),
        }
    }
}

/// [`Geom32`] of every face of `bins` (in parallel; skipped faces get that of the default
/// geometry, never read).
pub(crate) fn geoms32(bins: &TileBins) -> Vec<Geom32> {
    bins.geoms
        .par_iter()
        .with_min_len(1024)
        .map(Geom32::new)
        .collect()
}

/// Eight set lanes, then eight clear: `HEAD[8 - n..16 - n]` sets the first `n` lanes.
static HEAD: [u32; 2 * LANES] = [
    u32::MAX,
    u32::MAX,
    u32::MAX,
    u32::MAX,
    u32::MAX,
    u32::MAX,
    u32::MAX,
    u32::MAX,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
];

/// Lanes `0..=b - cs` of the chunk starting at column `cs <= b` (the columns up to `b`).
#[inline(always)]
pub(crate) fn lanes_to(cs: usize, b: usize) -> M8 {
    let n = (b + 1 - cs).min(LANES);
    M8(HEAD[LANES - n..2 * LANES - n]
        .try_into()
        .expect("eight lanes"))
}

/// Pixel offsets `px[cs + l] - o_x` in `f64`, rounded to `f32` once.
#[inline(always)]
pub(crate) fn offsets(px: &[f64], cs: usize, ox: f64) -> F8 {
    let p: &[f64; LANES] = px[cs..cs + LANES].try_into().expect("eight columns");
    F8(p.map(|x| (x - ox) as f32))
}

/// The faces whose boxes reach each band of `rows` image rows, in face order.
pub(crate) fn band_faces(bins: &TileBins, height: usize, rows: usize) -> Vec<Vec<u32>> {
    let mut bands = vec![Vec::new(); height.div_ceil(rows)];
    for (fi, r) in bins.rects.iter().enumerate() {
        if r[0] <= r[1] {
            for band in bands[r[2] as usize / rows..=r[3] as usize / rows].iter_mut() {
                band.push(fi as u32);
            }
        }
    }
    bands
}

/// Column centres `px` padded with 8 more (extrapolated) for whole chunks at the right edge.
pub(crate) fn padded_px(px: &[f64]) -> Vec<f64> {
    let n = px.len();
    let d = if n > 1 { px[1] - px[0] } else { 1.0 };
    px.iter()
        .copied()
        .chain((0..LANES).map(|i| px[n - 1] + d * (i + 1) as f64))
        .collect()
}

/// The closest points of eight pixel centres `(o_x + qx, o_y + qy)` on the three edges of a
/// face (edge `i` from vertex `i` to vertex `i + 1`): per edge the clamped parameter `t`, the
/// offset `r = q - closest point` and its squared length.
#[derive(Clone, Copy)]
pub(crate) struct Edges8 {
    pub(crate) t: [F8; 3],
    pub(crate) rx: [F8; 3],
    pub(crate) ry: [F8; 3],
    pub(crate) d2: [F8; 3],
}

impl Edges8 {
    #[inline(always)]
    pub(crate) fn new(g: &Geom32, qx: F8, qy: f32) -> Self {
        let (zero, one) = (F8::splat(0.0), F8::splat(1.0));
        let mut o = Self {
            t: [zero; 3],
            rx: [zero; 3],
            ry: [zero; 3],
            d2: [zero; 3],
        };
        for i in 0..3 {
            let apx = qx - F8::splat(g.v[i][0]);
            let apy = F8::splat(qy - g.v[i][1]);
            let (ex, ey) = (F8::splat(g.e[i][0]), F8::splat(g.e[i][1]));
            o.t[i] = ((apx * ex + apy * ey) * F8::splat(g.inv_ee[i]))
                .max(zero)
                .min(one);
            o.rx[i] = apx - o.t[i] * ex;
            o.ry[i] = apy - o.t[i] * ey;
            o.d2[i] = o.rx[i] * o.rx[i] + o.ry[i] * o.ry[i];
        }
        o
    }

    /// The squared distance to the nearest edge and which edge that is (one mask per edge,
    /// the first one winning ties).
    #[inline(always)]
    pub(crate) fn nearest(&self) -> (F8, [M8; 3]) {
        let d2 = &self.d2;
        let o1 = d2[1].lt(d2[0]);
        let b01 = select(o1, d2[1], d2[0]);
        let o2 = d2[2].lt(b01);
        (select(o2, d2[2], b01), [!o1 & !o2, o1 & !o2, o2])
    }
}

/// Adds `gd2 d(d^2)/dv` to the per-lane NDC vertex gradients `vgv` through the closest point
/// on edge `e` of the lanes `sel[e]` (`-2 (1 - t) r` to its first vertex, `-2 t r` to its
/// second: the factor `-2` is in `gd2`).
#[inline(always)]
pub(crate) fn add_closest_grad(
    vgv: &mut [[F8; 2]; 3],
    sel: &[M8; 3],
    t: &[F8; 3],
    rx: &[F8; 3],
    ry: &[F8; 3],
    gd2: F8,
) {
    let (zero, one) = (F8::splat(0.0), F8::splat(1.0));
    for e in 0..3 {
        let ce = select(sel[e], gd2, zero);
        let (ci, cj) = (ce * (one - t[e]), ce * t[e]);
        let j = (e + 1) % 3;
        vgv[e][0] = vgv[e][0] + ci * rx[e];
        vgv[e][1] = vgv[e][1] + ci * ry[e];
        vgv[j][0] = vgv[j][0] + cj * rx[e];
        vgv[j][1] = vgv[j][1] + cj * ry[e];
    }
}

/// Shared by the fast paths' tests.
#[cfg(test)]
pub(crate) mod test_support {
    use crate::camera::Camera;

    /// The peer kit's camera (as `benches/common`): eye `(0.3, 0.2, -3)` looking at the
    /// origin, y down, square image, near 1, far 100.
    pub(crate) fn peers_view_proj() -> [[f64; 4]; 4] {
        Camera::perspective_look_at(
            [0.3, 0.2, -3.0],
            [0.0; 3],
            [0.0, -1.0, 0.0],
            2.0 * (0.5f64 / 1.1).atan(),
            1.0,
            1.0,
            100.0,
        )
        .unwrap()
        .view_proj()
    }

    /// `sqrt(sum (a - b)^2 / sum b^2)`.
    pub(crate) fn rel_l2(a: &[f64], b: &[f64]) -> f64 {
        let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
        let n: f64 = b.iter().map(|y| y * y).sum();
        (d / n).sqrt()
    }
}
