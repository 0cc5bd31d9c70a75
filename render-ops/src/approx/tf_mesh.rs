//! The TF Mesh Renderer's gradients (K. Genova, F. Cole, A. Maschinot, A. Sarna, D. Vlasic and
//! W. T. Freeman, "Unsupervised Training for 3D Morphable Model Regression", CVPR 2018, its
//! differentiable rasterizer; section 4.4 of H. Kato et al., "Differentiable Rendering: A
//! Survey", 2020).
//!
//! # Forward
//!
//! The hard render: each pixel takes its nearest triangle `f` (z-buffer) and the
//! perspective-correct barycentrics `b(p)` of its centre, `I_p = sum_k b_k(p) A[f_k]`; pixels no
//! triangle covers show the background `B`. Alpha is the coverage. Bit-identical to
//! `rasterize` + `interpolate` + `blend_hard`.
//!
//! # Backward
//!
//! The triangle of every pixel is held fixed and the pixel's value is differentiated through
//! the barycentrics of its centre with respect to that triangle's vertices, computed without
//! clamping them to the triangle: barycentrics are *extrapolated* (negative components allowed)
//! for points outside it, so the surface is treated as locally flat (a plane through the
//! triangle) across occlusion boundaries.
//!
//! * **Covered pixels**: `dI_p/dv = sum_k A[f_k] db_k(p)/dv`, the interior gradient of the hard
//!   rasterizer ([`crate::raster::rasterize_backward`]): with `M` the `(x, y, w)` columns of the
//!   triangle's clip coordinates and `p~ = (x_ndc, y_ndc, 1)`, `u = M^-1 p~`, `b = u / sum(u)`.
//! * **Silhouette band.** A silhouette moving by `delta` pixels changes the pixels it sweeps,
//!   which the barycentrics of covered pixels cannot see; the extrapolated triangle supplies it.
//!   A pixel is modelled as partially covered, `I_p = B + alpha (F - B)`, with `alpha = 1/2 - s`
//!   the box-filter coverage of a straight edge at signed distance `s` (pixels, positive outside)
//!   from the pixel centre, for `|s| < 1/2`: a band one pixel wide centred on the silhouette.
//!   - A *background* pixel with a covered pixel among its 8 neighbours takes the triangle of a
//!     covered neighbour (among them, the one closest to the pixel centre) and its extrapolated
//!     barycentrics `b~(p)` (the formula above outside the triangle); `F = sum_k b~_k A[f_k]` is
//!     the colour of the surface continued flat past its edge, and `s` the distance from the
//!     pixel centre to that triangle, attained on edge `j`; where the closest point is inside
//!     the edge, `s = -b~_j h_j`, the extrapolated screen-space barycentric times the triangle's
//!     height over that edge.
//!   - A *covered* pixel with a background pixel among its 8 neighbours uses its own triangle's
//!     edge closest to that background neighbour (the silhouette edge), `s <= 0` its signed
//!     distance to the edge's line, and `F = I_p`.
//!
//!   With `a`, `c` the endpoints of the edge, `n` the unit vector from its closest point to the
//!   pixel centre (the outward normal) and `t` the parameter of that point, `ds/da = -n (1 - t)`
//!   and `ds/dc = -n t`. The forward keeps the hard value (`alpha` 0 or 1), so only the coverage
//!   term is differentiated: `dI_p/dv = (F - B) dalpha/dv` for the colour channels, `dalpha/dv`
//!   for the alpha channel, added to the interior term on covered pixels. Summed over the band,
//!   moving an edge by one pixel changes the image by one pixel's worth of `F - B` per pixel of
//!   edge length, as a box-filtered image would. Both sides are needed: where the target image
//!   wants the surface to recede, the background side has no residual and only the covered side
//!   sees it.
//!
//! Only silhouettes against the background get the band: where one surface occludes another,
//! both sides keep their interior gradients only. Gradients with respect to the attributes are
//! the exact ones of the forward.
//!
//! Deterministic: the interior part is [`crate::raster::rasterize_backward`] (fixed-order
//! reduction); the band contributions are computed per image row in parallel and summed in
//! pixel order.

use std::sync::Arc;

use autodiff::{BackwardCtx, Op, Real, Result as AdResult, Tensor, Var};
use rayon::prelude::*;

use super::{reduce_rows, sub, ApproxSettings, HardRender, Screen};
use crate::error::RenderError;

/// The 8 neighbours of a pixel, `(d_row, d_col)`, in the fixed order they are tried.
const NEIGHBOURS: [(isize, isize); 8] = [
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, -1),
    (0, 1),
    (1, -1),
    (1, 0),
    (1, 1),
];

/// Renders per-vertex attributes `[V, C]` over the faces from clip positions `[V, 4]` with the
/// TF Mesh Renderer's extrapolated-barycentric gradients: an image `[H, W, C + 1]` (attributes
/// over the background, then the coverage). See the [module documentation](self).
///
/// # Errors
/// Clip positions not `[V, 4]`, attributes not `[V, C]`, a background of another length than
/// `C` or not finite, and the rasterizer's errors (image size, face indices, non-finite
/// vertices).
pub fn tf_mesh<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &ApproxSettings,
) -> Result<Var<'t, T>, RenderError> {
    let op = TfMeshOp {
        hard: HardRender::new("tf_mesh", clip, attrs, faces, settings)?,
    };
    Ok(clip.tape().apply(op, &[clip, attrs]))
}

struct TfMeshOp<T: Real> {
    hard: HardRender<T>,
}

/// Where a pixel centre lies relative to a triangle: its signed distance and the closest
/// point of the boundary.
#[derive(Clone, Copy, Debug)]
struct Outside {
    /// Signed distance in pixels (positive outside).
    s: f64,
    /// The closest point lies on the edge opposite vertex `k`: from vertex `k + 1` to `k + 2`.
    k: usize,
    /// Parameter of the closest point along that edge, in `[0, 1]`.
    t: f64,
    /// Unit vector from the closest point towards the pixel centre when outside (the outward
    /// normal of the edge where the closest point is inside the edge), `(col, row)`.
    n: [f64; 2],
}

/// Signed distance from `p` to the triangle `v` (positive outside), attained at the point of
/// edge `k` closest to `p`; `None` for a degenerate triangle or `p` on its boundary.
fn outside(v: &[[f64; 2]; 3], area2: f64, p: [f64; 2]) -> Option<Outside> {
    let mut best: Option<Outside> = None;
    let mut d2min = f64::INFINITY;
    for k in 0..3 {
        let (a, b) = (v[(k + 1) % 3], v[(k + 2) % 3]);
        let e = sub(b, a);
        let len2 = e[0] * e[0] + e[1] * e[1];
        if !(len2 > 0.0) {
            continue;
        }
        let d = sub(p, a);
        let t = ((d[0] * e[0] + d[1] * e[1]) / len2).clamp(0.0, 1.0);
        let r = [d[0] - t * e[0], d[1] - t * e[1]];
        let d2 = r[0] * r[0] + r[1] * r[1];
        if d2 < d2min && d2 > 0.0 {
            d2min = d2;
            let dist = d2.sqrt();
            best = Some(Outside {
                s: dist,
                k,
                t,
                n: [r[0] / dist, r[1] / dist],
            });
        }
    }
    // Inside the triangle (e.g. a pixel centre on an edge left uncovered by the tie rule): the
    // distance is negative and the normal points out.
    let l = super::screen_bary(v, area2, p);
    if l.iter().all(|&x| x >= 0.0) {
        best = best.map(|o| Outside {
            s: -o.s,
            n: [-o.n[0], -o.n[1]],
            ..o
        });
    }
    best
}

/// Pixel index of the neighbour `(row + dr, col + dc)`, if inside the image.
fn neighbour(w: usize, h: usize, row: usize, col: usize, dr: isize, dc: isize) -> Option<usize> {
    let (r2, c2) = (row as isize + dr, col as isize + dc);
    (r2 >= 0 && c2 >= 0 && r2 < h as isize && c2 < w as isize)
        .then(|| r2 as usize * w + c2 as usize)
}

impl<T: Real> TfMeshOp<T> {
    /// The covered side of the band: pixel (row, col), covered by face `fq`, next to a
    /// background pixel. Its silhouette edge is the edge of `fq` closest to that background
    /// neighbour (among them, the edge closest to the pixel); within half a pixel of its line,
    /// `I = B + alpha (I - B)` with `alpha = 1/2 - s`, `s <= 0` the signed distance to the line.
    #[allow(clippy::too_many_arguments)]
    fn covered_edge(
        &self,
        screen: &Screen,
        img: &[f64],
        g: &[f64],
        fq: u32,
        row: usize,
        col: usize,
        out: &mut Vec<(u32, [f64; 2])>,
    ) {
        let fr = &self.hard.fragments;
        let (w, h) = (fr.width, fr.height);
        let f = self.hard.faces[fq as usize];
        let Some((v, area2)) = screen.triangle(f) else {
            return;
        };
        let pc = [col as f64, row as f64];
        let sgn = area2.signum();
        // (s, edge k, t, outward normal) of the best edge so far.
        let mut best: Option<(f64, usize, f64, [f64; 2])> = None;
        for (dr, dc) in NEIGHBOURS {
            let Some(q) = neighbour(w, h, row, col, dr, dc) else {
                continue;
            };
            if fr.count(q) > 0 {
                continue;
            }
            let qc = [(col as isize + dc) as f64, (row as isize + dr) as f64];
            let Some(o) = outside(&v, area2, qc) else {
                continue;
            };
            let (a, b) = (v[(o.k + 1) % 3], v[(o.k + 2) % 3]);
            let e = sub(b, a);
            let len2 = e[0] * e[0] + e[1] * e[1];
            let len = len2.sqrt();
            let n = [sgn * e[1] / len, -sgn * e[0] / len];
            let d = sub(pc, a);
            let s = n[0] * d[0] + n[1] * d[1];
            if best.is_none() || best.is_some_and(|b| s > b.0) {
                let t = ((d[0] * e[0] + d[1] * e[1]) / len2).clamp(0.0, 1.0);
                best = Some((s, o.k, t, n));
            }
        }
        let Some((s, k, t, n)) = best else {
            return;
        };
        if !(s > -0.5) {
            return;
        }
        let c = self.hard.background.len();
        let p = row * w + col;
        let gp = &g[p * (c + 1)..(p + 1) * (c + 1)];
        // dL/dalpha = sum_ch g_ch (I_ch - B_ch) + g_alpha, with I the pixel's colour.
        let mut ga = gp[c];
        for ch in 0..c {
            ga += gp[ch] * (img[p * (c + 1) + ch] - self.hard.background[ch].to_f64c());
        }
        if ga == 0.0 || !ga.is_finite() {
            return;
        }
        let (ia, ic) = (f[(k + 1) % 3], f[(k + 2) % 3]);
        out.push((ia, [ga * n[0] * (1.0 - t), ga * n[1] * (1.0 - t)]));
        out.push((ic, [ga * n[0] * t, ga * n[1] * t]));
    }

    /// Extrapolated barycentrics of face `f` at the centre of pixel (row, col): perspective-correct
    /// (`u = M^-1 p~`, `b = u / sum u`) or screen-space, following the settings.
    fn extrapolated(
        &self,
        screen: &Screen,
        f: [u32; 3],
        v: &[[f64; 2]; 3],
        area2: f64,
        row: usize,
        col: usize,
    ) -> Option<[f64; 3]> {
        if !self.hard.settings.perspective_correct {
            return Some(super::screen_bary(v, area2, [col as f64, row as f64]));
        }
        let (wf, hf) = (screen.width as f64, screen.height as f64);
        let p = [
            2.0 * (col as f64 + 0.5) / wf - 1.0,
            1.0 - 2.0 * (row as f64 + 0.5) / hf,
            1.0,
        ];
        let m = f.map(|i| {
            let c = screen.clip[i as usize];
            [c[0], c[1], c[3]]
        });
        let cr = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let c = [cr(m[1], m[2]), cr(m[2], m[0]), cr(m[0], m[1])];
        let u = [dot(c[0], p), dot(c[1], p), dot(c[2], p)];
        let sum = u[0] + u[1] + u[2];
        let b = u.map(|x| x / sum);
        b.iter().all(|x| x.is_finite()).then_some(b)
    }

    /// Band contributions `(vertex, d/d(col, row))` of the pixels of one image row.
    fn band_row(
        &self,
        screen: &Screen,
        attrs: &[f64],
        img: &[f64],
        g: &[f64],
        row: usize,
        out: &mut Vec<(u32, [f64; 2])>,
    ) {
        let fr = &self.hard.fragments;
        let (w, h) = (fr.width, fr.height);
        let c = self.hard.background.len();
        for col in 0..w {
            let p = row * w + col;
            let gp = &g[p * (c + 1)..(p + 1) * (c + 1)];
            if gp.iter().all(|&x| x == 0.0) {
                continue;
            }
            if let Some(fq) = fr.nearest(p).map(|x| x.face) {
                self.covered_edge(screen, img, g, fq, row, col, out);
                continue;
            }
            // Background pixel: the covered neighbour whose triangle passes closest.
            let mut best: Option<(u32, Outside, [[f64; 2]; 3], f64)> = None;
            for (dr, dc) in NEIGHBOURS {
                let Some(q) = neighbour(w, h, row, col, dr, dc) else {
                    continue;
                };
                let Some(fq) = fr.nearest(q).map(|x| x.face) else {
                    continue;
                };
                if best.is_some_and(|b| b.0 == fq) {
                    continue;
                }
                let Some((v, area2)) = screen.triangle(self.hard.faces[fq as usize]) else {
                    continue;
                };
                let Some(o) = outside(&v, area2, [col as f64, row as f64]) else {
                    continue;
                };
                if best.is_none() || best.is_some_and(|b| o.s < b.1.s) {
                    best = Some((fq, o, v, area2));
                }
            }
            let Some((fq, o, v, area2)) = best else {
                continue;
            };
            if !(o.s < 0.5) {
                continue;
            }
            let f = self.hard.faces[fq as usize];
            let Some(b) = self.extrapolated(screen, f, &v, area2, row, col) else {
                continue;
            };
            // dL/dalpha = sum_ch g_ch (F_ch - B_ch) + g_alpha.
            let mut ga = gp[c];
            for ch in 0..c {
                let fch: f64 = (0..3).map(|k| b[k] * attrs[f[k] as usize * c + ch]).sum();
                ga += gp[ch] * (fch - self.hard.background[ch].to_f64c());
            }
            if ga == 0.0 || !ga.is_finite() {
                continue;
            }
            // alpha = 1/2 - s: dalpha/da = n (1 - t), dalpha/dc = n t.
            let (ia, ic) = (f[(o.k + 1) % 3], f[(o.k + 2) % 3]);
            out.push((ia, [ga * o.n[0] * (1.0 - o.t), ga * o.n[1] * (1.0 - o.t)]));
            out.push((ic, [ga * o.n[0] * o.t, ga * o.n[1] * o.t]));
        }
    }
}

impl<T: Real> Op<T> for TfMeshOp<T> {
    fn name(&self) -> &'static str {
        "tf_mesh"
    }

    fn forward(&mut self, inputs: &[&Tensor<T>]) -> AdResult<Vec<Tensor<T>>> {
        self.hard.forward("tf_mesh", inputs)
    }

    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let fr = &self.hard.fragments;
        self.hard.backward("tf_mesh", ctx, |b| {
            // Band of background pixels along the silhouette.
            let band: Vec<Vec<(u32, [f64; 2])>> = (0..fr.height)
                .into_par_iter()
                .map(|row| {
                    let mut out = Vec::new();
                    self.band_row(&b.screen, &b.attrs, &b.img, &b.g, row, &mut out);
                    out
                })
                .collect();
            reduce_rows(&b.screen, band)
        })
    }
}
