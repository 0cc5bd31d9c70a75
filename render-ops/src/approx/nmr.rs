//! The Neural 3D Mesh Renderer's gradients (H. Kato, Y. Ushiku and T. Harada, "Neural 3D Mesh
//! Renderer", CVPR 2018, section 3.3, "Rasterization"; section 4.2 of H. Kato et al.,
//! "Differentiable Rendering: A Survey", 2020, eq. 1-2).
//!
//! # Forward
//!
//! The hard render (z-buffer, perspective-correct interpolation of the per-vertex attributes,
//! background where nothing is covered, alpha = coverage), bit-identical to `rasterize` +
//! `interpolate` + `blend_hard`: the image does not depend on the method, only its gradient.
//!
//! # Backward
//!
//! The hard image is piecewise constant in the vertex positions at occlusion boundaries. NMR
//! replaces the step a pixel `P_j` takes when an edge crosses its centre by a linear ramp:
//! moving vertex `v_i` along `x` from `x0` to the position `x1` where an edge of the moved
//! triangle reaches the pixel centre changes the pixel from `I_j` to `I_j'`, and
//!
//! `dI_j / dx_i = delta_I / delta_x`, `delta_I = I_j' - I_j`, `delta_x = x1 - x0`, kept only if
//! `delta_I . dL/dI_j < 0` (survey eq. 1),
//!
//! i.e. only where moving the vertex that way would lower the loss (the gating by the incoming
//! gradient; per pixel, `.` summing over the channels, alpha included). A pixel the face covers
//! can be uncovered by a move either way (its left and right boundaries): the two gated terms
//! are added (survey eq. 2). `y` is treated alike. The gradients with respect to the pixel
//! positions are chained to the clip coordinates `(x, y, w)` through the perspective divide and
//! the viewport (`Screen::px_to_clip`, as the other methods of [`crate::approx`]).
//!
//! It is computed per face, per scanline and per edge rather than per pixel and face: for
//! `x`-moves, each image row `r` that a (non-degenerate) face spans is crossed by two of its
//! edges, at `x_c` (the left or the right boundary of the face on that row). An edge from `a`
//! to `b` crosses at parameter `t = (r - y_a) / (y_b - y_a)`, which an `x`-move of either
//! endpoint does not change, so the crossing moves by `dx_c = (1 - t) dx_a + t dx_b`. Walking
//! the pixel centres `x` of the row away from the crossing:
//!
//! * **outward** (the pixels the edge sweeps when the face grows): from the first pixel past
//!   the crossing to the image border. The colour after is the face's own at the crossing point
//!   of the moved edge, which is the pixel centre once the edge has swept there: the edge's
//!   attributes at `t` (perspective-correct along the edge, as the face interpolates them;
//!   alpha 1). Occlusion: the face takes the pixel only where its NDC depth at that point
//!   (affine along the edge) is nearer than the z-buffer there. As in the paper's
//!   implementation, the sweep starts only from edges the face shows at: the pixel just inside
//!   the crossing must be the face's own (hidden and culled faces, whose edges change no pixel,
//!   get nothing);
//! * **inward** (the face's own pixels, uncovered when the edge recedes): the pixels of the row
//!   between this crossing and the other one that show the face. The colour after is what the
//!   pixel would show behind the face, taken as the current colour of the pixel just across
//!   the edge: the background at a silhouette, the occluded surface at an occlusion boundary,
//!   the neighbouring face at an edge inside a surface (the reference implementation's choice;
//!   one fragment per pixel keeps no "next fragment").
//!
//! With `d = x - x_c` (signed) and `delta_I . g` gated as above, `dL/dx_c` is the sum of
//! `(delta_I . g) / d` over both walks and `dL/dx_a = (1 - t) dL/dx_c`, `dL/dx_b = t dL/dx_c`
//! (the vertex moves `d / (1 - t)` for the crossing to move `d`). `y`-moves walk the columns
//! the same way.
//!
//! Bounds: the outward sweep stops at the image border, at most `W - 1` pixels along a row
//! (`H - 1` along a column), as in the reference implementation; the inward walk at the other
//! boundary of the face on that scanline. Far pixels count only where the loss asks for the
//! face's colour (the gating): that is what gives NMR a gradient towards a silhouette many
//! pixels away. On the small displacements of `render-ops/tests/approx.rs`, stopping the sweep
//! after 10 pixels changes the cosines there by at most 0.002 (after 3 pixels, by up to 0.05).
//!
//! `|d|` is taken at least [`MIN_DISTANCE_PX`] = 1/2: a pixel centre within half a pixel of
//! the edge, which the edge already passes through, counts as half a pixel away. Without a
//! floor a pixel centre on the edge divides by zero; the reference implementation adds an
//! `eps` of `1e-4` NDC (a hundredth of a pixel at 256 x 256), which leaves terms up to a
//! hundred times the others on the few pixels that an edge almost touches. Those spikes cost
//! descent direction: with a floor of 0.01 px the cosines to the box-filtered finite-difference
//! gradient in `render-ops/tests/approx.rs` are 0.433 / 0.842 / 0.670 / 0.245 (sphere / cube /
//! deformed sphere / face), with 1/2 px 0.556 / 0.920 / 0.691 / 0.388.
//!
//! Gradients of the pixel colours through the barycentrics of covered pixels (the smooth part,
//! which NMR's texture sampling also has) are the exact ones of the hard render (`interior_grad`
//! of [`crate::approx`], shared with `tf_mesh` and `deodr`): position gradients are that
//! interior part plus the edge part above; attribute gradients are exact.
//!
//! Differences from Kato et al. 2018 and their implementation: the outward colour after is the
//! face's interpolated attributes at the crossing point (the paper: the colour the face would
//! give the pixel; the implementation copies the colour of the face's pixel just inside the
//! edge), the outward sweep is depth-tested against the z-buffer (the implementation has no
//! occlusion test there), back faces are processed like front faces where they are visible
//! (the implementation always culls them; here `cull_backfaces` decides, as for the forward),
//! the image has an alpha channel whose change counts in `delta_I` like the colours, the
//! sweep distance has a half-pixel floor (above), and the image is the hard render at its own
//! size (the implementation renders at twice the size and averages 2 x 2 blocks by default).
//!
//! This op takes interpolated per-vertex attributes (colours, Gouraud shading evaluated at the
//! vertices): the colour a face would give an uncovered pixel is taken from its vertex
//! attributes. Over the image of any shader or texture, [`crate::boundary::nmr_antialias()`] takes it
//! from the shaded image instead.
//!
//! Cost: the outward sweeps dominate, one pass to the image border per scanline crossing of
//! every face shown at its edge. The sweeps read per-pixel data copied into row-major and
//! column-major lanes, so that both axes walk memory in order, and are processed scanline by
//! scanline so that a lane stays in cache for all the faces that reach it. Forward + backward
//! of the 5120-face sphere at 256 x 256 in f32 on one thread (`render-ops/benches/raster.rs`,
//! group `nmr_f32`, on a shared 2-core machine): 40 ms, against 16 ms for `deodr` and 11 ms for
//! the hard pipeline; 164 ms at 512 x 512.
//!
//! Deterministic: the edge contributions are computed per scanline in parallel (each
//! scanline's faces in face order) and reduced into the vertices in scanline order.

use std::sync::Arc;

use autodiff::{BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use rayon::prelude::*;

use super::{bin_by_lines, depth_buffer, edge_weights, ApproxSettings, HardRender, Screen};
use crate::error::RenderError;
use crate::raster::Fragments;

/// The smallest `|x - x_c|` (pixels) a pixel's term is divided by: a pixel centre within half
/// a pixel of the moving edge (a pixel the edge passes through) counts as half a pixel from
/// it, so that no term exceeds `2 |delta_I . g|`. See the module documentation.
pub const MIN_DISTANCE_PX: f64 = 0.5;

/// `face_of` value of a pixel that no face covers.
const NO_FACE: u32 = u32::MAX;

/// Renders per-vertex attributes `[V, C]` over the faces from clip positions `[V, 4]` with the
/// Neural 3D Mesh Renderer's approximate gradients: an image `[H, W, C + 1]` (attributes over
/// the background, then the coverage). See the [module documentation](self).
///
/// # Errors
/// Clip positions not `[V, 4]`, attributes not `[V, C]`, a background of another length than
/// `C` or not finite, and the rasterizer's errors (image size, face indices, non-finite
/// vertices).
pub fn nmr<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &ApproxSettings,
) -> Result<Var<'t, T>, RenderError> {
    let op = NmrOp {
        hard: HardRender::new("nmr", clip, attrs, faces, settings)?,
    };
    Ok(clip.tape().apply(op, &[clip, attrs]))
}

struct NmrOp<T: Real> {
    hard: HardRender<T>,
}

/// Per-pixel data the sweeps read, in `f64` (`nc = C + 1` channels).
struct Maps<'a> {
    width: usize,
    height: usize,
    nc: usize,
    /// The rendered image, `[H * W * nc]`.
    img: &'a [f64],
    /// Vertex attributes `[V * C]`; `None`: the outward sweep's colour after is the shaded
    /// colour of the face's pixel just inside the edge (`crate::boundary::nmr_antialias`).
    attrs: Option<&'a [f64]>,
    /// The sweeps' per-pixel data laid out along their scanlines, so that a sweep reads memory
    /// in order: rows (`[H][W]`) for x-moves, columns (`[W][H]`) for y-moves. Per pixel,
    /// `lane_stride(nc)` values: the face shown ([`NO_FACE`] where uncovered), the NDC
    /// depth of the nearest fragment (infinity where uncovered), then `dL/dI_ch, I_ch` for each
    /// channel.
    lanes: [Vec<f64>; 2],
}

/// Values per pixel in [`Maps::lanes`].
#[inline]
fn lane_stride(nc: usize) -> usize {
    2 + 2 * nc
}

/// The lanes of [`Maps`] from the face and depth buffers, `dL/dI` and the image.
fn lanes(
    width: usize,
    height: usize,
    nc: usize,
    face_of: &[u32],
    zbuf: &[f64],
    g: &[f64],
    img: &[f64],
) -> [Vec<f64>; 2] {
    let stride = lane_stride(nc);
    let fill = |p: usize, out: &mut [f64]| {
        out[0] = face_of[p] as f64;
        out[1] = zbuf[p];
        for ch in 0..nc {
            out[2 + 2 * ch] = g[p * nc + ch];
            out[3 + 2 * ch] = img[p * nc + ch];
        }
    };
    // `n` lanes of `len` pixels, pixel `(u, s)` of the image at `pixel(u, s)`.
    let lay = |n: usize, len: usize, pixel: &(dyn Fn(usize, usize) -> usize + Sync)| {
        let mut out = vec![0.0; n * len * stride];
        out.par_chunks_mut(len * stride)
            .enumerate()
            .for_each(|(u, lane)| {
                for (s, px) in lane.chunks_mut(stride).enumerate() {
                    fill(pixel(u, s), px);
                }
            });
        out
    };
    [
        lay(height, width, &|r, c| r * width + c),
        lay(width, height, &|c, r| r * width + c),
    ]
}

/// `sum_ch dL/dI_ch (after_ch - I_ch)` of a pixel's lane data `l`: the first-order change of
/// the loss if the pixel took the values `after`.
#[inline]
fn gain(l: &[f64], after: &[f64]) -> f64 {
    let mut d = 0.0;
    for (gi, a) in l[2..].chunks_exact(2).zip(after) {
        d += gi[0] * (a - gi[1]);
    }
    d
}

/// One boundary crossing of a face on a scanline.
#[derive(Clone, Copy)]
struct Crossing {
    /// The edge runs from the face's vertex `k` to vertex `k + 1`.
    k: usize,
    /// Parameter along the edge (0 at vertex `k`); `x`-moves (`y`-moves) leave it unchanged.
    t: f64,
    /// Position of the crossing along the scanline, in pixels.
    s: f64,
}

/// The signed distance `x - x_c` of a pixel centre from the crossing, at least
/// [`MIN_DISTANCE_PX`] in magnitude; `dir` is the side of the edge the pixel lies on (the sign
/// kept when `x` is 0).
#[inline]
fn distance(x: f64, dir: f64) -> f64 {
    if x.abs() < MIN_DISTANCE_PX {
        dir * MIN_DISTANCE_PX
    } else {
        x
    }
}

/// For one axis, the faces whose span reaches each scanline, in face order (CSR over the
/// scanlines: `faces[start[u]..start[u + 1]]`).
struct ScanlineBins {
    start: Vec<usize>,
    faces: Vec<u32>,
}

impl ScanlineBins {
    fn lane(&self, u: usize) -> &[u32] {
        &self.faces[self.start[u]..self.start[u + 1]]
    }
}

/// The screen positions of a face's vertices as `(s, u)`: `s` along `axis` (the direction of
/// the moves), `u` across it (the scanline coordinate).
#[inline]
fn along(v: &[[f64; 2]; 3], axis: usize) -> [[f64; 2]; 3] {
    v.map(|x| [x[axis], x[1 - axis]])
}

/// The scanlines `u0..=u1` (within `0..nu`) that a face with scanline coordinates `p[k][1]`
/// spans, if any.
#[inline]
fn scanline_range(p: &[[f64; 2]; 3], nu: usize) -> Option<(usize, usize)> {
    let lo = p.iter().map(|x| x[1]).fold(f64::INFINITY, f64::min);
    let hi = p.iter().map(|x| x[1]).fold(f64::NEG_INFINITY, f64::max);
    let (u0, u1) = (lo.ceil().max(0.0), hi.floor().min(nu as f64 - 1.0));
    (u0 <= u1).then_some((u0 as usize, u1 as usize))
}

/// The sum of the gated `(delta_I . g) / d` over the lane pixels `px` that `takes` accepts:
/// the first pixel at signed distance `d0` from the crossing, each next one `step` further,
/// `dir` the side of the edge they lie on, `after` the values they would take.
#[inline]
fn gated_sum<'a>(
    px: impl Iterator<Item = &'a [f64]>,
    d0: f64,
    step: f64,
    dir: f64,
    after: &[f64],
    takes: impl Fn(&[f64]) -> bool,
) -> f64 {
    let mut sum = 0.0;
    for (k, l) in px.enumerate() {
        if takes(l) {
            let d = gain(l, after);
            if d < 0.0 {
                sum += d / distance(d0 + step * k as f64, dir);
            }
        }
    }
    sum
}

/// The sweeps of one render: the faces drawn and the interpolation mode.
pub(crate) struct Sweeper<'a> {
    pub faces: &'a [[u32; 3]],
    pub persp: bool,
}

impl Sweeper<'_> {
    /// Bins the faces marked in `shown` by the scanlines of `axis` they span.
    fn bins(&self, screen: &Screen, shown: &[bool], axis: usize, nu: usize) -> ScanlineBins {
        let ranges: Vec<Option<(usize, usize)>> = (0..self.faces.len())
            .into_par_iter()
            .map(|fi| {
                if !shown[fi] {
                    return None;
                }
                let (v, _) = screen.triangle(self.faces[fi])?;
                scanline_range(&along(&v, axis), nu)
            })
            .collect();
        let (start, faces) = bin_by_lines(&ranges, nu);
        ScanlineBins { start, faces }
    }

    /// The contributions `(vertex, dL/ds)` of face `fi`'s two boundary crossings on scanline
    /// `ui` of `axis` (`s` the vertex coordinate along `axis`), appended to `out`. `after` is
    /// scratch of `C + 1` values.
    #[allow(clippy::too_many_arguments)]
    fn face_scanline(
        &self,
        screen: &Screen,
        m: &Maps<'_>,
        fi: u32,
        axis: usize,
        ui: usize,
        after: &mut [f64],
        out: &mut Vec<(u32, f64)>,
    ) {
        let f = self.faces[fi as usize];
        let Some((v, _)) = screen.triangle(f) else {
            return;
        };
        let p = along(&v, axis);
        let u = ui as f64;
        // The edges crossing scanline u, half-open in u (`min <= u < max`): exactly two or
        // none, so a vertex on the scanline counts once.
        let mut cr = [Crossing {
            k: 0,
            t: 0.0,
            s: 0.0,
        }; 2];
        let mut n = 0;
        for k in 0..3 {
            let (a, b) = (p[k], p[(k + 1) % 3]);
            if !((a[1] <= u && u < b[1]) || (b[1] <= u && u < a[1])) {
                continue;
            }
            let t = (u - a[1]) / (b[1] - a[1]);
            if n < 2 {
                cr[n] = Crossing {
                    k,
                    t,
                    s: a[0] + t * (b[0] - a[0]),
                };
            }
            n += 1;
        }
        if n != 2 || !(cr[0].s.is_finite() && cr[1].s.is_finite()) {
            return;
        }
        let (low, high) = if cr[0].s <= cr[1].s {
            (cr[0], cr[1])
        } else {
            (cr[1], cr[0])
        };
        for (side, c, other) in [(-1.0, low, high.s), (1.0, high, low.s)] {
            let sum = self.sweep(m, screen, f, fi, axis, ui, side, c, other, after);
            if sum != 0.0 {
                out.push((f[c.k], (1.0 - c.t) * sum));
                out.push((f[(c.k + 1) % 3], c.t * sum));
            }
        }
    }

    /// `dL/ds_c` of one crossing `c` (the boundary of face `fi` on scanline `ui` on side `side`:
    /// -1 low, +1 high; `other` the other boundary's position): the gated `(delta_I . g) / d`
    /// summed over the outward sweep and the inward walk.
    #[allow(clippy::too_many_arguments)]
    fn sweep(
        &self,
        m: &Maps<'_>,
        screen: &Screen,
        f: [u32; 3],
        fi: u32,
        axis: usize,
        ui: usize,
        side: f64,
        c: Crossing,
        other: f64,
        after: &mut [f64],
    ) -> f64 {
        let ns = if axis == 0 { m.width } else { m.height };
        let pix = |si: usize| {
            if axis == 0 {
                ui * m.width + si
            } else {
                si * m.width + ui
            }
        };
        let stride = lane_stride(m.nc);
        let lane = &m.lanes[axis][ui * ns * stride..(ui + 1) * ns * stride];
        let fi = fi as f64;
        let in_image = |x: f64| x >= 0.0 && x < ns as f64;
        // The pixel just inside the crossing, and the one just outside.
        let s_in = if side > 0.0 { c.s.floor() } else { c.s.ceil() };
        let s_out = s_in + side;
        let mut sum = 0.0;
        let nc = m.nc;
        let attrs_c = nc - 1;
        // Outward: pixels the face takes as the edge sweeps out, if it shows inside the edge.
        if in_image(s_in) && in_image(s_out) && lane[s_in as usize * stride] == fi {
            let (a, b) = (f[c.k] as usize, f[(c.k + 1) % 3] as usize);
            if let Some(attrs) = m.attrs {
                let (wt, _) = edge_weights([1.0 / screen.w[a], 1.0 / screen.w[b]], c.t, self.persp);
                for ch in 0..attrs_c {
                    after[ch] = wt[0] * attrs[a * attrs_c + ch] + wt[1] * attrs[b * attrs_c + ch];
                }
                after[attrs_c] = 1.0;
            } else {
                // The face's shaded colour at its pixel just inside the edge.
                let pi = pix(s_in as usize);
                after.copy_from_slice(&m.img[pi * nc..(pi + 1) * nc]);
            }
            let za = screen.clip[a][2] / screen.w[a];
            let zb = screen.clip[b][2] / screen.w[b];
            let z = za + c.t * (zb - za);
            // Up to the image border, the pixels the face would take: not its own, and where
            // it would be in front.
            let takes = |l: &[f64]| l[0] != fi && z < l[1];
            let so = s_out as usize;
            sum += if side > 0.0 {
                let px = lane[so * stride..].chunks_exact(stride);
                gated_sum(px, s_out - c.s, 1.0, 1.0, after, takes)
            } else {
                let px = lane[..(so + 1) * stride].rchunks_exact(stride);
                gated_sum(px, s_out - c.s, -1.0, -1.0, after, takes)
            };
        }
        // Inward: the face's pixels between the two boundaries, uncovered as the edge recedes;
        // what shows behind them is taken from the pixel just across the edge.
        if in_image(s_out) {
            let po = pix(s_out as usize);
            let behind = &m.img[po * nc..(po + 1) * nc];
            let (lo, hi) = if side > 0.0 {
                (other.ceil().max(0.0), s_in.min(ns as f64 - 1.0))
            } else {
                (s_in.max(0.0), other.floor().min(ns as f64 - 1.0))
            };
            if lo <= hi {
                let (lo, hi) = (lo as usize, hi as usize);
                let px = lane[lo * stride..(hi + 1) * stride].chunks_exact(stride);
                sum += gated_sum(px, lo as f64 - c.s, 1.0, -side, behind, |l| l[0] == fi);
            }
        }
        sum
    }
}

impl<T: Real> Op<T> for NmrOp<T> {
    fn name(&self) -> &'static str {
        "nmr"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        self.hard.forward("nmr", inputs)
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let fr = &self.hard.fragments;
        let sw = Sweeper {
            faces: &self.hard.faces,
            persp: self.hard.settings.perspective_correct,
        };
        self.hard.backward("nmr", ctx, |b| {
            sw.boundary(fr, &b.screen, &b.img, &b.g, Some(&b.attrs))
        })
    }
}

impl Sweeper<'_> {
    /// NMR's edge term: per-vertex clip gradients from the sweeps over the rendered image
    /// `img` (`[H * W * nc]`) with `dL/dI` `g`, the outward colours from `attrs` (per-vertex,
    /// `[V * (nc - 1)]`) or, when `None`, from the image.
    pub(crate) fn boundary<T: Real>(
        &self,
        fr: &Fragments<T>,
        screen: &Screen,
        img: &[f64],
        g: &[f64],
        attrs: Option<&[f64]>,
    ) -> Vec<[f64; 4]> {
        let nc = img.len() / fr.num_pixels().max(1);
        let face_of: Vec<u32> = (0..fr.num_pixels())
            .map(|p| fr.nearest(p).map_or(NO_FACE, |f| f.face))
            .collect();
        // Faces shown at no pixel have no edge to sweep from and no pixel to uncover.
        let mut shown = vec![false; self.faces.len()];
        for &f in &face_of {
            if f != NO_FACE {
                shown[f as usize] = true;
            }
        }
        let (w, h) = (fr.width, fr.height);
        let zbuf = depth_buffer(fr);
        let maps = Maps {
            width: w,
            height: h,
            nc,
            img,
            attrs,
            lanes: lanes(w, h, nc, &face_of, &zbuf, g, img),
        };
        // Per axis, the scanlines in parallel (each reads its lane of `maps` for all the
        // faces that reach it, in face order), reduced in scanline order.
        let mut acc = vec![[0.0f64; 2]; screen.px.len()];
        for axis in 0..2 {
            let nu = if axis == 0 { h } else { w };
            let bins = self.bins(screen, &shown, axis, nu);
            let per_lane: Vec<Vec<(u32, f64)>> = (0..nu)
                .into_par_iter()
                .map_init(
                    || vec![0.0; nc],
                    |after, ui| {
                        let mut out = Vec::new();
                        for &fi in bins.lane(ui) {
                            self.face_scanline(screen, &maps, fi, axis, ui, after, &mut out);
                        }
                        out
                    },
                )
                .collect();
            for lane in per_lane {
                for (v, g) in lane {
                    acc[v as usize][axis] += g;
                }
            }
        }
        screen.px_grads_to_clip(&acc)
    }
}
