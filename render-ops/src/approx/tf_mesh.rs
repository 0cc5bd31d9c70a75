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
//!
//! # Composed form: extrapolated barycentrics through rasterize / interpolate
//!
//! [`tf_mesh()`] is the fast path over per-vertex attributes. For any shader (textures,
//! per-pixel lighting, a user's closure) [`rasterize_extrapolated`] gives, besides the hard
//! rasterization, the band as a second rasterization: one fragment per band pixel, on a
//! background pixel the covered neighbour's face with the extrapolated barycentrics `b~(p)`,
//! depth and view depth of the face's plane there, on a covered pixel its own fragment; its
//! barycentrics and depths are tape variables differentiable with respect to the clip
//! positions (the backward of the rasterizer, which recomputes them at the pixel centre
//! without clamping), and its coverage `alpha = 1/2 - s` is a third. The shader runs on both
//! rasterizations unchanged (interpolate, texture, shade), giving the hard colours and
//! `F` per band pixel, and [`blend_band`] composites `blend_hard` of the hard colours plus
//! `(alpha - alpha0) (F - B)` with `alpha0` alpha's value held constant: the hard image in
//! the forward, the band term `(F - B) dalpha` in the backward. On per-vertex colours it gives
//! the fused op's image bit for bit and its gradients to rounding, except at covered pixels
//! whose closest point on the silhouette edge lies past the edge's end (the fused op clamps
//! the edge parameter there, the composed coverage differentiates the line distance exactly).

use std::sync::Arc;

use autodiff::{BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use rayon::prelude::*;

use super::{reduce_rows, sub, ApproxSettings, HardRender, Screen};
use crate::blend::blend_hard;
use crate::error::RenderError;
use crate::raster::{Fragments, RasterSettings};
use crate::rasterize::{rasterize, record, Rasterized};

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

/// The covered side of the band at pixel (row, col), covered by face `fq`, next to a
/// background pixel: the edge of `fq` closest to a background neighbour (among them, the edge
/// whose line passes closest to the pixel centre), as `(s, k, t, n)`: `s <= 0` the signed
/// distance of the pixel centre to the edge's line, `k` the edge (opposite vertex `k`), `t` the
/// parameter of the closest point clamped to `[0, 1]`, `n` the outward unit normal.
fn covered_side<T: Real>(
    faces: &[[u32; 3]],
    fr: &Fragments<T>,
    screen: &Screen,
    fq: u32,
    row: usize,
    col: usize,
) -> Option<(f64, usize, f64, [f64; 2])> {
    let (w, h) = (fr.width, fr.height);
    let (v, area2) = screen.triangle(faces[fq as usize])?;
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
    best
}

/// The background side of the band at pixel (row, col), covered by no face: the covered
/// neighbour whose triangle passes closest to the pixel centre, as (face, where the centre
/// lies relative to it, its pixel positions, doubled signed area).
fn background_side<T: Real>(
    faces: &[[u32; 3]],
    fr: &Fragments<T>,
    screen: &Screen,
    row: usize,
    col: usize,
) -> Option<(u32, Outside, [[f64; 2]; 3], f64)> {
    let (w, h) = (fr.width, fr.height);
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
        let Some((v, area2)) = screen.triangle(faces[fq as usize]) else {
            continue;
        };
        let Some(o) = outside(&v, area2, [col as f64, row as f64]) else {
            continue;
        };
        if best.is_none() || best.is_some_and(|b| o.s < b.1.s) {
            best = Some((fq, o, v, area2));
        }
    }
    best
}

/// Extrapolated barycentrics of face `f` at the centre of pixel (row, col), with their
/// derivatives per pixel step right and down: perspective-correct (`u = M^-1 p~`,
/// `b = u / sum u`) or screen-space (`persp` false). Also the NDC depth `sum u_k z_k` and the
/// view depth `1 / sum u` of the plane through the triangle at that pixel.
pub(crate) fn extrapolated(
    screen: &Screen,
    f: [u32; 3],
    v: &[[f64; 2]; 3],
    area2: f64,
    row: usize,
    col: usize,
    persp: bool,
) -> Option<([f64; 3], Extrapolated)> {
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
    let bp = u.map(|x| x / sum);
    // `u` is `det M` times `M^-1 p~`; its `w` row sums to `det M`.
    let det: f64 = (0..3).map(|k| u[k] * m[k][2]).sum();
    let z: f64 = (0..3)
        .map(|k| u[k] * screen.clip[f[k] as usize][2])
        .sum::<f64>()
        / det;
    let (b, dx, dy) = if persp {
        // d u / d col = c[k][0] 2 / W, d u / d row = -c[k][1] 2 / H.
        let du = |j: usize, scale: f64| {
            let d = [c[0][j] * scale, c[1][j] * scale, c[2][j] * scale];
            let ds = d[0] + d[1] + d[2];
            [0, 1, 2].map(|k| (d[k] - bp[k] * ds) / sum)
        };
        (bp, du(0, 2.0 / wf), du(1, -2.0 / hf))
    } else {
        let b = super::screen_bary(v, area2, [col as f64, row as f64]);
        let e = |k: usize| sub(v[(k + 2) % 3], v[(k + 1) % 3]);
        (
            b,
            [0, 1, 2].map(|k| -e(k)[1] / area2),
            [0, 1, 2].map(|k| e(k)[0] / area2),
        )
    };
    let x = Extrapolated {
        depth: z,
        view_depth: det / sum,
        dbary_dx: dx,
        dbary_dy: dy,
    };
    let finite = b.iter().chain(&dx).chain(&dy).all(|x| x.is_finite())
        && x.depth.is_finite()
        && x.view_depth.is_finite();
    finite.then_some((b, x))
}

/// What [`extrapolated`] gives besides the barycentrics.
pub(crate) struct Extrapolated {
    depth: f64,
    view_depth: f64,
    dbary_dx: [f64; 3],
    dbary_dy: [f64; 3],
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
        let w = fr.width;
        let f = self.hard.faces[fq as usize];
        let Some((s, k, t, n)) = covered_side(&self.hard.faces, fr, screen, fq, row, col) else {
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
        let w = fr.width;
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
            let Some((fq, o, v, area2)) = background_side(&self.hard.faces, fr, screen, row, col)
            else {
                continue;
            };
            if !(o.s < 0.5) {
                continue;
            }
            let f = self.hard.faces[fq as usize];
            let persp = self.hard.settings.perspective_correct;
            let Some((b, _)) = extrapolated(screen, f, &v, area2, row, col, persp) else {
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

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        self.hard.forward("tf_mesh", inputs)
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
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

// ---------------------------------------------------------------------------------------------
// The composed form: extrapolated barycentrics through rasterize / interpolate.

/// Which side of the silhouette band a band fragment lies on.
#[derive(Clone, Copy, Debug)]
enum Side {
    /// A background pixel next to a covered one: the distance to the face (positive).
    Background,
    /// A covered pixel next to a background one: the signed distance to the line of edge `k`
    /// (opposite vertex `k`) of its own face (negative).
    Covered(usize),
}

/// The TF Mesh Renderer's rasterization ([`rasterize_extrapolated`]): the hard fragments, the
/// fragments of the silhouette band with extrapolated barycentrics, and the band's coverage.
pub struct ExtrapolatedRaster<'t, T: Real> {
    /// The hard rasterization (the nearest fragment of each pixel).
    pub raster: Rasterized<'t, T>,
    /// One fragment per pixel of the silhouette band: on a background pixel, the face of the
    /// covered neighbour whose triangle passes closest with its extrapolated barycentrics
    /// (negative components outside the face), depth and view depth of the face's plane there;
    /// on a covered pixel, its own fragment. Barycentrics and depths are differentiable with
    /// respect to the clip positions ([`crate::raster::rasterize_backward`], which recomputes
    /// them at the pixel centre without clamping).
    pub band: Rasterized<'t, T>,
    /// Per band fragment `[M]`: the box-filter coverage `1/2 - s` of the pixel by the edge
    /// at signed distance `s` (pixels, positive outside), a function of the clip positions.
    pub coverage: Var<'t, T>,
}

/// Rasterizes clip positions `[V, 4]` TF-Mesh style: the hard fragments (one per pixel) plus
/// the one-pixel silhouette band of the [module documentation](self), whose fragments carry
/// extrapolated barycentrics, so any shader run on [`ExtrapolatedRaster::band`] (interpolate,
/// texture, lighting) sees the surface continued flat past its silhouette. [`blend_band`]
/// composites the shaded fragments: the hard image forward, with the band's coverage change
/// in the backward. `faces_per_pixel` is ignored (one fragment per pixel).
///
/// # Errors
/// The rasterizer's errors.
pub fn rasterize_extrapolated<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RasterSettings,
) -> Result<ExtrapolatedRaster<'t, T>, RenderError> {
    let s = RasterSettings {
        faces_per_pixel: 1,
        ..*settings
    };
    let raster = rasterize(clip, faces.clone(), &s)?;
    let fr = &*raster.fragments;
    let (w, h) = (fr.width, fr.height);
    let screen = Screen::new(&*clip.value()?, w, h);
    let derivs = fr.has_derivatives();
    let to_t = |x: [f64; 3]| x.map(T::from_f64c);
    // Per row: (pixel, face, side, bary, depth, view depth, d bary / d col, d bary / d row).
    type BandFrag<T> = (u32, u32, Side, [T; 3], T, T, [T; 3], [T; 3]);
    let rows: Vec<Vec<BandFrag<T>>> = (0..h)
        .into_par_iter()
        .map(|row| {
            let mut out = Vec::new();
            for col in 0..w {
                let p = row * w + col;
                if let Some(x) = fr.nearest(p) {
                    let Some((sd, k, _, _)) = covered_side(&faces, fr, &screen, x.face, row, col)
                    else {
                        continue;
                    };
                    if sd > -0.5 {
                        let zero = [T::zero(); 3];
                        out.push((
                            p as u32,
                            x.face,
                            Side::Covered(k),
                            x.bary,
                            x.depth,
                            x.view_depth,
                            x.dbary_dx.unwrap_or(zero),
                            x.dbary_dy.unwrap_or(zero),
                        ));
                    }
                    continue;
                }
                let Some((fq, o, v, area2)) = background_side(&faces, fr, &screen, row, col) else {
                    continue;
                };
                if !(o.s < 0.5) {
                    continue;
                }
                let f = faces[fq as usize];
                let persp = s.perspective_correct;
                let Some((b, e)) = extrapolated(&screen, f, &v, area2, row, col, persp) else {
                    continue;
                };
                out.push((
                    p as u32,
                    fq,
                    Side::Background,
                    to_t(b),
                    T::from_f64c(e.depth),
                    T::from_f64c(e.view_depth),
                    to_t(e.dbary_dx),
                    to_t(e.dbary_dy),
                ));
            }
            out
        })
        .collect();
    let mut band = Fragments::empty(w, h, 1);
    let mut sides = Vec::new();
    let mut count = vec![0u32; w * h];
    for (p, face, side, b, d, vd, dx, dy) in rows.into_iter().flatten() {
        count[p as usize] = 1;
        sides.push((p, face, side));
        band.face.push(face);
        band.bary.push(b);
        band.depth.push(d);
        band.view_depth.push(vd);
        if derivs {
            band.dbary_dx.push(dx);
            band.dbary_dy.push(dy);
        }
    }
    for p in 0..w * h {
        band.offsets[p + 1] = band.offsets[p] + count[p];
    }
    let band = record(clip, Arc::new(band), faces.clone(), &s);
    let coverage = clip.tape().apply(
        BandCoverage {
            faces,
            sides,
            width: w,
            height: h,
        },
        &[clip],
    );
    Ok(ExtrapolatedRaster {
        raster,
        band,
        coverage,
    })
}

/// Composites the shaded hard fragments `colors` `[N, C]` and band fragments `band_colors`
/// `[M, C]` of `r` over `background` (`C` values): the image `[H, W, C + 1]` of
/// [`blend_hard`] (bit for bit), plus, on each band pixel, `(a - a0) (F - B)` on the colour
/// channels and `a - a0` on the alpha, with `a` the band's coverage and `a0` its value held
/// constant: zero in the forward, the coverage change `(F - B) da` in the backward, as the
/// fused [`tf_mesh`] gives it (F the band fragment's shaded colour).
///
/// # Errors
/// Shapes: `colors` not `[N, C]` for the hard fragments, `band_colors` not `[M, C]` for the
/// band's, a background of another length than `C`.
pub fn blend_band<'t, T: Real>(
    colors: Var<'t, T>,
    band_colors: Var<'t, T>,
    r: &ExtrapolatedRaster<'t, T>,
    background: &[T],
) -> Result<Var<'t, T>, RenderError> {
    let t = colors.tape();
    let c = background.len();
    let m = r.band.fragments.len();
    let bs = band_colors.shape();
    if bs.len() != 2 || bs[0] != m || bs[1] != c {
        return Err(autodiff::AutodiffError::shape(
            "tf_mesh blend_band",
            &[&bs],
            format!("band colours must be [{m}, {c}] (band fragments, background channels)"),
        )
        .into());
    }
    let image = blend_hard(colors, &r.raster.fragments, background)?;
    if m == 0 {
        return Ok(image);
    }
    let held = t.constant((*r.coverage.value()?).clone());
    let d = (r.coverage - held).reshape(&[m, 1]);
    let bg = t.constant(
        ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(&[c]), background.to_vec()).expect("c"),
    );
    let rgb = d * (band_colors - bg);
    let contrib = t.concat(&[rgb, d], 1);
    let band_img = blend_hard(contrib, &r.band.fragments, &vec![T::zero(); c + 1])?;
    Ok(image + band_img.slice(2, 0, c + 1))
}

/// The band's coverage `1/2 - s` per band fragment as a function of the clip positions: for
/// background pixels `s` is the distance to the face (the closest point on its boundary,
/// [`outside`]), for covered pixels the signed distance to the line of their silhouette edge.
/// Backward: `da/dv_a = n (1 - t)`, `da/dv_c = n t` for the edge's endpoints (pixel units,
/// `n` the outward normal, `t` the closest point's parameter), chained to clip coordinates and
/// reduced in row order.
struct BandCoverage {
    faces: Arc<Vec<[u32; 3]>>,
    sides: Vec<(u32, u32, Side)>,
    width: usize,
    height: usize,
}

impl BandCoverage {
    /// `(coverage, [(vertex, d coverage / d (col, row)); 2])` of band fragment `i`.
    fn eval(&self, screen: &Screen, i: usize) -> (f64, [(u32, [f64; 2]); 2]) {
        let (p, face, side) = self.sides[i];
        let f = self.faces[face as usize];
        let (row, col) = (p as usize / self.width, p as usize % self.width);
        let pc = [col as f64, row as f64];
        let none = (0.0, [(f[0], [0.0; 2]), (f[1], [0.0; 2])]);
        let Some((v, area2)) = screen.triangle(f) else {
            return none;
        };
        let (s, k, t, n) = match side {
            Side::Background => {
                let Some(o) = outside(&v, area2, pc) else {
                    return none;
                };
                (o.s, o.k, o.t, o.n)
            }
            Side::Covered(k) => {
                let a = v[(k + 1) % 3];
                let e = sub(v[(k + 2) % 3], a);
                let len2 = e[0] * e[0] + e[1] * e[1];
                let len = len2.sqrt();
                let sgn = area2.signum();
                let n = [sgn * e[1] / len, -sgn * e[0] / len];
                let d = sub(pc, a);
                let t = (d[0] * e[0] + d[1] * e[1]) / len2;
                (n[0] * d[0] + n[1] * d[1], k, t, n)
            }
        };
        let (ia, ic) = (f[(k + 1) % 3], f[(k + 2) % 3]);
        (
            0.5 - s,
            [
                (ia, [n[0] * (1.0 - t), n[1] * (1.0 - t)]),
                (ic, [n[0] * t, n[1] * t]),
            ],
        )
    }

    /// Band fragments of each image row.
    fn row_ranges(&self) -> Vec<std::ops::Range<usize>> {
        let mut out = Vec::with_capacity(self.height);
        let mut i = 0;
        for row in 0..self.height {
            let start = i;
            while i < self.sides.len() && (self.sides[i].0 as usize) < (row + 1) * self.width {
                i += 1;
            }
            out.push(start..i);
        }
        out
    }
}

impl<T: Real> Op<T> for BandCoverage {
    fn name(&self) -> &'static str {
        "tf_mesh_band_coverage"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let screen = Screen::new(&inputs[0], self.width, self.height);
        let a: Vec<f64> = (0..self.sides.len())
            .into_par_iter()
            .map(|i| self.eval(&screen, i).0)
            .collect();
        Ok(vec![super::tensor_f64(&[a.len()], a)])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let screen = Screen::new(&ctx.inputs[0], self.width, self.height);
        let g = super::grad_f64(ctx);
        let rows: Vec<Vec<(u32, [f64; 2])>> = self
            .row_ranges()
            .into_par_iter()
            .map(|r| {
                let mut out = Vec::new();
                for i in r {
                    if g[i] == 0.0 {
                        continue;
                    }
                    for (v, d) in self.eval(&screen, i).1 {
                        out.push((v, [g[i] * d[0], g[i] * d[1]]));
                    }
                }
                out
            })
            .collect();
        Ok(vec![Some(super::clip_tensor(reduce_rows(&screen, rows)))])
    }
}
