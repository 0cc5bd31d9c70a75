//! DEODR's discontinuity edge overdraw of a shaded image (M. de La Gorce, D. J. Fleet and
//! N. Paragios, "Model-Based 3D Hand Pose Estimation from Monocular Video", TPAMI 2011, section
//! 4; P. V. Sander et al., "Discontinuity Edge Overdraw", I3D 2001), composed as nvdiffrast
//! composes `antialias` (S. Laine et al., "Modular Primitives for High-Performance
//! Differentiable Rendering", SIGGRAPH Asia 2020, section 3.4: silhouette edges, the blend of
//! the colours on both sides by the edge's position, gradients to both colours and to the edge's
//! clip vertices).
//!
//! # Forward
//!
//! The silhouette edges, their order and their ramps are those of the fused
//! [`crate::approx::deodr()`] (see there): an edge is a silhouette edge when exactly one of the
//! faces sharing it faces the camera; edges are drawn from the farthest face to the nearest;
//! a pixel centre `p` with edge coordinates `0 <= t <= 1` along the edge and `0 <= s <
//! overdraw_px` across it (outwards), where the edge is nearer than the z-buffer, is blended
//!
//! `I_p <- T I_p + (1 - T) I_src`, `T = s / overdraw_px`,
//!
//! towards `I_src`, the shaded image at the pixel the edge's face shows just inside the edge
//! (the fused op uses the edge's interpolated attributes, which a shader does not have): of the
//! pixel nearest to `q = p - (s + 1/2) n` (half a pixel inside the edge, `n` its outward
//! normal) and its eight neighbours, the nearest to `q` whose centre is inside the edge and
//! whose nearest face is the edge's face or shares a vertex with it. Where there is none (a face
//! thinner than a pixel with no neighbour showing), the pixel is not overdrawn. All channels are
//! blended alike (the coverage channel of `blend_hard` towards the source's, 1).
//!
//! # Backward
//!
//! The exact derivative of that forward: per row, the layers of each pixel are replayed in
//! reverse, giving `dL/dI_src += (1 - T) dL/dI_p` (to the source pixel, which may lie in
//! another row), `dL/dT = dL/dI_p . (I_p^before - I_src)` and `dL/dI_p <- T dL/dI_p`; `T` is
//! differentiated with respect to the edge's screen positions and chained to clip `x`, `y`, `w`.
//! The edge set, the depth tests and the choice of source pixels are piecewise constant.
//!
//! Deterministic: rows in parallel, each row's edges in the global order; contributions reduced
//! in row order.

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::{grad_out, to_f64, BoundarySettings, Geometry};
use crate::approx::deodr::{column_range, edge_coords, silhouette_edges, Edge, EdgeSet};
use crate::approx::{clip_tensor, cross2, reduce_rows, Screen};
use crate::error::RenderError;
use crate::rasterize::Rasterized;

/// DEODR's edge overdraw of the shaded image `color` `[H, W, C]` drawn from `raster` (of clip
/// positions `clip` `[V, 4]`): an image `[H, W, C]`, antialiased along silhouette edges. See the
/// [module documentation](self).
///
/// # Errors
/// `color` not `[H, W, C]` at the rasterizer's size, `clip` not `[V, 4]` or too short for the
/// rasterized faces, `overdraw_px` negative or not finite.
pub fn deodr_antialias<'t, T: Real>(
    color: Var<'t, T>,
    raster: &Rasterized<'t, T>,
    clip: Var<'t, T>,
    settings: &BoundarySettings,
) -> Result<Var<'t, T>, RenderError> {
    let sigma = settings.overdraw_px;
    if !(sigma.is_finite() && sigma >= 0.0) {
        return Err(AutodiffError::invalid(
            "boundary::deodr_antialias",
            format!("overdraw_px must be finite and >= 0, got {sigma}"),
        )
        .into());
    }
    let geo = Geometry::new("boundary::deodr_antialias", color, raster, clip)?;
    let screen = geo.screen(&*clip.value()?);
    let fr = &geo.fragments;
    let edges = if sigma > 0.0 {
        silhouette_edges(&screen, &geo.welded, sigma)
    } else {
        EdgeSet::empty(fr.height)
    };
    let np = fr.num_pixels();
    let mut face_of = vec![u32::MAX; np];
    let mut depth = vec![f64::INFINITY; np];
    for p in 0..np {
        if let Some(f) = fr.nearest(p) {
            face_of[p] = f.face;
            depth[p] = f.depth.to_f64c();
        }
    }
    let op = DeodrOp {
        geo,
        screen,
        edges,
        sigma,
        face_of,
        depth,
    };
    Ok(color.tape().apply(op, &[color, clip]))
}

struct DeodrOp<T: Real> {
    geo: Geometry<T>,
    screen: Screen,
    edges: EdgeSet,
    sigma: f64,
    /// Per pixel, its nearest face (`u32::MAX`: none) and that fragment's NDC depth.
    face_of: Vec<u32>,
    depth: Vec<f64>,
}

/// One overdraw layer of a pixel.
struct Layer {
    x: usize,
    edge: u32,
    tr: f64,
    /// The source pixel (index in the image).
    src: usize,
}

impl<T: Real> DeodrOp<T> {
    /// The source pixel of a layer at pixel centre `(x, row)` with edge coordinate `s`, if any
    /// (see the module documentation).
    fn source(&self, e: &Edge, x: usize, row: usize, s: f64) -> Option<usize> {
        let (w, h) = (self.geo.fragments.width, self.geo.fragments.height);
        let q = [
            x as f64 - (s + 0.5) * e.n[0],
            row as f64 - (s + 0.5) * e.n[1],
        ];
        let (cx, cy) = (q[0].round(), q[1].round());
        let f = self.geo.welded[e.face as usize];
        let mut best: Option<(f64, usize)> = None;
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (px, py) = (cx + dx as f64, cy + dy as f64);
                if px < 0.0 || py < 0.0 || px >= w as f64 || py >= h as f64 {
                    continue;
                }
                let p = py as usize * w + px as usize;
                let fo = self.face_of[p];
                if fo == u32::MAX {
                    continue;
                }
                let g = self.geo.welded[fo as usize];
                if !(fo == e.face || g.iter().any(|v| f.contains(v))) {
                    continue;
                }
                // Inside the edge: on the other side of it than its normal.
                let d = [px - e.p0[0], py - e.p0[1]];
                if !(e.n[0] * d[0] + e.n[1] * d[1] < 0.0) {
                    continue;
                }
                let dist = (px - q[0]).powi(2) + (py - q[1]).powi(2);
                if best.is_none_or(|(b, bp)| dist < b || (dist == b && p < bp)) {
                    best = Some((dist, p));
                }
            }
        }
        best.map(|(_, p)| p)
    }

    /// The layers of row `row`, in drawing order.
    fn layers(&self, row: usize, out: &mut Vec<Layer>) {
        let w = self.geo.fragments.width;
        let rf = row as f64;
        for &ei in self.edges.row(row) {
            let e = &self.edges.edges[ei as usize];
            let Some((x0, x1)) = column_range(e, rf, self.sigma, w) else {
                continue;
            };
            for x in x0..=x1 {
                let (t, s) = edge_coords(e, x as f64, rf);
                if !((0.0..=1.0).contains(&t) && s >= 0.0 && s < self.sigma) {
                    continue;
                }
                let z = e.z[0] + t * (e.z[1] - e.z[0]);
                if !(z < self.depth[row * w + x]) {
                    continue;
                }
                let Some(src) = self.source(e, x, row, s) else {
                    continue;
                };
                out.push(Layer {
                    x,
                    edge: ei,
                    tr: s / self.sigma,
                    src,
                });
            }
        }
    }
}

/// A row's gradient contributions: positions `(vertex, d/d(col, row))`, and to source pixels
/// `(pixel, C values of dL/dI_src)`.
#[derive(Default)]
struct RowGrad {
    pos: Vec<(u32, [f64; 2])>,
    src_pixel: Vec<usize>,
    src_grad: Vec<f64>,
    /// `dL/dI` of the row's pixels before the overdraw (`W * C` values), when it has layers.
    row: Option<Vec<f64>>,
}

impl<T: Real> Op<T> for DeodrOp<T> {
    fn name(&self) -> &'static str {
        "boundary::deodr_antialias"
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let src = inputs[0].as_standard_layout();
        let src = src.as_slice().expect("standard");
        let mut img = src.to_vec();
        if self.edges.edges.is_empty() {
            return Ok(vec![
                ArrayD::from_shape_vec(IxDyn(inputs[0].shape()), img).expect("same shape")
            ]);
        }
        let c = self.geo.c;
        let w = self.geo.fragments.width;
        img.par_chunks_mut(w * c)
            .enumerate()
            .for_each_init(Vec::new, |layers, (row, out)| {
                layers.clear();
                self.layers(row, layers);
                for l in layers.iter() {
                    let tr = l.tr.to_f64c();
                    for ch in 0..c {
                        let v = out[l.x * c + ch].to_f64c();
                        let a = src[l.src * c + ch].to_f64c();
                        out[l.x * c + ch] = T::from_f64c(tr * v + (1.0 - tr) * a);
                    }
                }
            });
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(inputs[0].shape()), img).expect("same shape")
        ])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let c = self.geo.c;
        let (w, h) = (self.geo.fragments.width, self.geo.fragments.height);
        let src = to_f64(&ctx.inputs[0]);
        let g = grad_out(ctx);
        let rows: Vec<RowGrad> = (0..h)
            .into_par_iter()
            .map_init(Vec::new, |layers, row| {
                layers.clear();
                self.layers(row, layers);
                if layers.is_empty() {
                    return RowGrad::default();
                }
                // Replay: the value of each layer's pixel before it.
                let mut cur = src[row * w * c..(row + 1) * w * c].to_vec();
                let mut before = Vec::with_capacity(layers.len() * c);
                for l in layers.iter() {
                    before.extend_from_slice(&cur[l.x * c..(l.x + 1) * c]);
                    for ch in 0..c {
                        let a = src[l.src * c + ch];
                        let v = &mut cur[l.x * c + ch];
                        *v = l.tr * *v + (1.0 - l.tr) * a;
                    }
                }
                let mut gr = g[row * w * c..(row + 1) * w * c].to_vec();
                let mut out = RowGrad::default();
                let rf = row as f64;
                for (k, l) in layers.iter().enumerate().rev() {
                    let e = &self.edges.edges[l.edge as usize];
                    let gp = &mut gr[l.x * c..(l.x + 1) * c];
                    let b = &before[k * c..(k + 1) * c];
                    let mut gtr = 0.0;
                    out.src_pixel.push(l.src);
                    for ch in 0..c {
                        let a = src[l.src * c + ch];
                        gtr += gp[ch] * (b[ch] - a);
                        out.src_grad.push((1.0 - l.tr) * gp[ch]);
                        gp[ch] *= l.tr;
                    }
                    let gs = gtr / self.sigma;
                    if gs == 0.0 {
                        continue;
                    }
                    // s = sgn cross(e, d) / |e| with e = p1 - p0, d = p - p0.
                    let d = [l.x as f64 - e.p0[0], rf - e.p0[1]];
                    let s = e.sgn * cross2(e.e, d) / e.len;
                    let ds_de = [
                        e.sgn * d[1] / e.len - s * e.e[0] / e.len2,
                        -e.sgn * d[0] / e.len - s * e.e[1] / e.len2,
                    ];
                    let g1 = [gs * ds_de[0], gs * ds_de[1]];
                    let g0 = [-g1[0] - gs * e.n[0], -g1[1] - gs * e.n[1]];
                    out.pos.push((e.v[0], g0));
                    out.pos.push((e.v[1], g1));
                }
                out.row = Some(gr);
                out
            })
            .collect();
        let g_color = ctx.needs_grad[0].then(|| {
            let mut gc = g.clone();
            for (row, r) in rows.iter().enumerate() {
                if let Some(gr) = &r.row {
                    gc[row * w * c..(row + 1) * w * c].copy_from_slice(gr);
                }
            }
            for r in &rows {
                for (&p, v) in r.src_pixel.iter().zip(r.src_grad.chunks_exact(c)) {
                    for ch in 0..c {
                        gc[p * c + ch] += v[ch];
                    }
                }
            }
            ArrayD::from_shape_vec(
                IxDyn(ctx.inputs[0].shape()),
                gc.into_iter().map(T::from_f64c).collect(),
            )
            .expect("same shape")
        });
        let g_clip = ctx.needs_grad[1].then(|| {
            let pos = rows.into_iter().map(|r| r.pos).collect();
            clip_tensor(reduce_rows(&self.screen, pos))
        });
        Ok(vec![g_color, g_clip])
    }
}
