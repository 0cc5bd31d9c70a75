//! The soft rasterization stage: per pixel, the fragments that matter to a soft method (every
//! face within the coverage cut-off, or the nearest K of them), as a sparse, pixel-major
//! fragment list ([`crate::raster::Fragments`]: CSR offsets per pixel, face ids, clipped
//! barycentrics, NDC and view depths) with each fragment's coverage probability. The
//! barycentrics, depths and probabilities are tape variables with an exact backward to the
//! clip positions, so that interpolation ([`crate::interpolate::interpolate`]), texture
//! sampling and any shader ([`crate::shade::run_shader`], [`crate::shade::fragment_inputs`])
//! run per fragment unchanged, and a blend op ([`super::aggregate`]) aggregates them.
//!
//! Per face `f` and pixel centre `p` (NDC), with `d` the distance from `p` to the projected
//! triangle's boundary and `s = +1` inside, `-1` outside ([`Coverage`]):
//! - SoftRas (Liu et al. 2019, eq. 1): `D = sigmoid(s d^2 / sigma)`;
//! - DIB-R (Chen et al. 2019): `D = 1` inside, `exp(-d^2 / delta)` outside.
//!
//! Outside pairs with `D < threshold` are dropped (a cut-off distance, the same that bins the
//! faces into tiles, [`super::common::TileBins`]). Barycentrics are the screen-space
//! barycentrics of `p` clipped to `[0, 1]` and renormalised (SoftRas), perspective-correct when
//! asked; the view depth is `z = 1 / sum_k wn_k / z_k`, the NDC depth `sum_k wn_k z_k^ndc`.
//! Per pixel the fragments are sorted nearest first (view depth, then face id), and with
//! `max_faces = Some(K)` only the K nearest are kept. The per-pair geometry and its backward
//! are those of the fused SoftRas op ([`super::softras`]: `pair`, `pair_backward`,
//! `signed_distance_backward`), not a second copy.
//!
//! Memory: the fragment list holds one entry per kept (face, pixel) pair (a face id, three
//! barycentrics, two depths and a probability, and their tape copies: about 60 bytes in `f32`).
//! The number of pairs is bounded before anything is allocated by the sum over faces of their
//! pixel boxes expanded by the cut-off (or by `K x pixels` when smaller), which must not exceed
//! [`MAX_SOFT_FRAGMENTS`] ([`RasterError::TooLarge`] otherwise). No faces x pixels array is
//! ever formed.
//!
//! Evaluation: the forward runs in parallel over 16 x 16 tiles (each face over the row spans of
//! its cut-off region) and assembles the list in parallel over image rows; the backward runs
//! in parallel over fixed chunks of fragments, each fragment re-evaluating its pair, and adds
//! the per-fragment corner gradients to the vertices in fragment order
//! ([`crate::scatter`]), so results are bit-identical for any thread count.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::common::{
    check_memory_projected, ndc_to_clip, signed_distance_backward, Projected, TileBins, TILE,
};
use super::softras::{attr_weights, coverage_sigmoid, pair_backward, Pair, SoftRasOp};
use crate::error::RenderError;
use crate::raster::{Fragments, RasterError};
use crate::rasterize::{fragment_outputs, grad_output_f64, Rasterized};
use crate::scatter::scatter_face_corners;

/// Most (face, pixel) fragments one soft stage may produce (2^25, about 2 GB of fragment data
/// and tape copies in `f32`), bounded before allocation as the module documentation says.
pub const MAX_SOFT_FRAGMENTS: usize = 1 << 25;

/// The coverage probability of a face at a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Coverage {
    /// SoftRas (Liu et al. 2019, eq. 1): `D = sigmoid(s d^2 / sigma)`, `sigma` in squared NDC
    /// units.
    Sigmoid {
        /// Sharpness (default 1e-4).
        sigma: f64,
    },
    /// DIB-R (Chen et al. 2019): `D = 1` inside, `exp(-d^2 / delta)` outside.
    Exp {
        /// Sharpness in squared NDC units ([`crate::scene::DEFAULT_DIBR_DELTA`]).
        delta: f64,
    },
}

impl Coverage {
    /// The scale `sigma` or `delta`.
    fn scale(self) -> f64 {
        match self {
            Coverage::Sigmoid { sigma } => sigma,
            Coverage::Exp { delta } => delta,
        }
    }
}

/// Settings of [`soft_fragments`].
#[derive(Clone, Debug, PartialEq)]
pub struct SoftStageSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// The coverage model.
    pub coverage: Coverage,
    /// Outside pairs with a coverage below this are dropped (in `(0, 1)`; default 1e-4).
    pub threshold: f64,
    /// Keep only the nearest K fragments of every pixel (`None`: all within the cut-off).
    pub max_faces: Option<usize>,
    /// Perspective-correct barycentrics (default `false`, as SoftRas).
    pub perspective_correct: bool,
    /// Drop clockwise (back) faces.
    pub cull_backfaces: bool,
    /// Also give the fragments' screen-space barycentric derivatives (for texture filtering:
    /// those of the unclipped barycentrics, fixed data without a gradient).
    pub barycentric_derivatives: bool,
}

impl SoftStageSettings {
    /// Defaults (threshold 1e-4, all fragments within the cut-off, screen-space barycentrics).
    pub fn new(width: usize, height: usize, coverage: Coverage) -> Self {
        Self {
            width,
            height,
            coverage,
            threshold: 1e-4,
            max_faces: None,
            perspective_correct: false,
            cull_backfaces: false,
            barycentric_derivatives: false,
        }
    }

    /// Squared cut-off distance (NDC units) at which an outside face's coverage falls to
    /// `threshold`: `sigma ln(1 / threshold - 1)` (SoftRas), `delta ln(1 / threshold)` (DIB-R).
    pub fn cutoff_sq(&self) -> f64 {
        match self.coverage {
            Coverage::Sigmoid { sigma } => (sigma * (1.0 / self.threshold - 1.0).ln()).max(0.0),
            Coverage::Exp { delta } => delta * -self.threshold.ln(),
        }
    }

    fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        let sc = self.coverage.scale();
        if !(sc > 0.0 && sc.is_finite()) {
            return Err(format!("sigma / delta must be finite and > 0, got {sc}"));
        }
        if !(self.threshold > 0.0 && self.threshold < 1.0) {
            return Err(format!(
                "threshold must lie strictly between 0 and 1, got {}",
                self.threshold
            ));
        }
        if self.max_faces == Some(0) {
            return Err("max_faces must be at least 1".into());
        }
        Ok(())
    }
}

/// The output of [`soft_fragments`]: the fragments as a [`Rasterized`] (so that
/// [`crate::interpolate::interpolate`], [`crate::shade::fragment_inputs`] and shaders take it
/// as they take the hard rasterizer's), with per fragment its coverage probability.
pub struct SoftFragments<'t, T: Real> {
    /// Fragments (pixel-major, nearest first per pixel), faces, clipped barycentrics `[N, 3]`,
    /// NDC depth `[N]` and view depth `[N]` (tape variables).
    pub raster: Rasterized<'t, T>,
    /// Coverage probability `D` per fragment `[N]` (tape variable).
    pub prob: Var<'t, T>,
}

/// Runs the soft rasterization stage over clip positions `[V, 4]` (see the module
/// documentation), recording one tape op with four outputs (barycentrics, NDC depth, view
/// depth, probability). Faces with a vertex at `w <= 0` are skipped.
///
/// # Errors
/// Shapes, settings, face indices, non-finite clip coordinates, and
/// [`RasterError::TooLarge`] when the pair bound exceeds [`MAX_SOFT_FRAGMENTS`] or the tile
/// lists [`super::MAX_SOFT_BIN_ENTRIES`].
pub fn soft_fragments<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &SoftStageSettings,
) -> Result<SoftFragments<'t, T>, RenderError> {
    const OP: &str = "soft_fragments";
    let cs = clip.shape();
    if cs.len() != 2 || cs[1] != 4 {
        return Err(AutodiffError::shape(OP, &[&cs], "clip positions must be [V, 4]").into());
    }
    settings
        .validate()
        .map_err(|m| AutodiffError::invalid(OP, m))?;
    let v = cs[0] as u32;
    if let Some(f) = faces.iter().find(|f| f.iter().any(|&i| i >= v)) {
        return Err(
            AutodiffError::invalid(OP, format!("face {f:?} indexes past {v} vertices")).into(),
        );
    }
    let s = settings;
    let dmax = s.cutoff_sq().sqrt();
    let pre = check_memory_projected(OP, &clip, &faces, s.width, s.height, dmax, s.cull_backfaces)?;
    let cv = clip.value_ref()?;
    let cv = cv.view();
    let Projected { ndc, depth, rects } = match pre {
        Some(p) => p,
        None => {
            // Only reached for values the check leaves to the op (it refused the rest).
            return Err(
                AutodiffError::shape(OP, &[cv.shape()], "clip positions must be [V, 4]").into(),
            );
        }
    };
    // The pair bound: every face's expanded pixel box, or K per pixel.
    let boxes: u128 = rects
        .iter()
        .filter(|r| r[0] <= r[1])
        .map(|r| ((r[1] - r[0] + 1) * (r[3] - r[2] + 1)) as u128)
        .sum();
    let pixels = (s.width * s.height) as u128;
    let bound = match s.max_faces {
        Some(k) => boxes.min(k as u128 * pixels),
        None => boxes,
    }
    .min(usize::MAX as u128) as usize;
    if bound > MAX_SOFT_FRAGMENTS {
        return Err(RasterError::TooLarge {
            request: format!(
                "{OP} of {} faces at {}x{} with a cut-off of {dmax:.3e} NDC units",
                faces.len(),
                s.width,
                s.height
            ),
            what: "soft fragments (faces' pixel boxes within the cut-off)",
            needed: bound,
            limit: MAX_SOFT_FRAGMENTS,
        }
        .into());
    }
    let ndc_z: Vec<f64> = cv
        .outer_iter()
        .map(|r| r[2].to_f64c() / r[3].to_f64c())
        .collect();
    let bins = TileBins::with_rects(&ndc, &depth, &faces, s.width, s.height, dmax, rects, true);
    let (fr, prob) = build::<T>(&bins, &faces, &ndc_z, s);
    let fragments = Arc::new(fr);
    let op = StageOp {
        fragments: fragments.clone(),
        prob,
        faces: faces.clone(),
        ndc,
        depth,
        ndc_z,
        bins,
        s: s.clone(),
    };
    let outs = clip.tape().apply_multi(op, &[clip], 4);
    Ok(SoftFragments {
        raster: Rasterized {
            fragments,
            faces,
            bary: outs[0],
            depth: outs[1],
            view_depth: outs[2],
            visibility: None,
        },
        prob: outs[3],
    })
}

/// One kept pair of a tile, before assembly.
#[derive(Clone, Copy)]
struct Rec {
    /// Tile-local pixel (row-major).
    lp: u16,
    face: u32,
    bary: [f64; 3],
    ndc_z: f64,
    z: f64,
    prob: f64,
    dbary: [[f64; 3]; 2],
}

/// The pair of face `fi` at pixel centre `p` under `s`, and its coverage `D`, or `None` when
/// dropped. Inside means `x >= 0` with every screen barycentric `>= 0`.
#[inline(always)]
fn eval_pair(
    bins: &TileBins,
    fi: usize,
    p: [f64; 2],
    s: &SoftStageSettings,
    inv_scale: f64,
    cut2: f64,
) -> Option<(Pair, f64, bool)> {
    let g = &bins.geoms[fi];
    let q = SoftRasOp::pair(g, p, inv_scale, cut2)?;
    let inside = q.w.iter().all(|&x| x >= 0.0);
    let d = match s.coverage {
        Coverage::Sigmoid { .. } => coverage_sigmoid(q.x).0,
        Coverage::Exp { .. } => {
            if inside {
                1.0
            } else {
                super::common::exp(q.x)
            }
        }
    };
    // The pair keeps outside pairs within the cut-off distance, where D >= threshold.
    Some((q, d, inside))
}

/// Screen-space derivatives per pixel step right and down of the (unclipped) barycentrics used
/// to interpolate: affine ones, or perspective-correct `b_k = (w_k / z_k) / sum_j w_j / z_j`.
fn bary_derivatives(
    g: &super::common::FaceGeom,
    q: &Pair,
    perspective: bool,
    dpx: f64,
    dpy: f64,
) -> [[f64; 3]; 2] {
    let dw = [
        g.bw.map(|b| b[1] * dpx),
        // A step down lowers NDC y by dpy.
        g.bw.map(|b| -b[2] * dpy),
    ];
    if !perspective {
        return dw;
    }
    let u = [0, 1, 2].map(|k| q.w[k] * g.inv_d[k]);
    let su: f64 = u.iter().sum();
    if su == 0.0 || !su.is_finite() {
        return dw;
    }
    dw.map(|d| {
        let du = [0, 1, 2].map(|k| d[k] * g.inv_d[k]);
        let sdu: f64 = du.iter().sum();
        [0, 1, 2].map(|k| (du[k] - u[k] / su * sdu) / su)
    })
}

type Built<T> = (Fragments<T>, Vec<f64>);

/// The forward: tiles in parallel, then the pixel-major list in parallel over image rows.
/// Returns the fragments and the probabilities.
fn build<T: Real>(
    bins: &TileBins,
    faces: &[[u32; 3]],
    ndc_z: &[f64],
    s: &SoftStageSettings,
) -> Built<T> {
    let (w, h) = (s.width, s.height);
    let inv_scale = 1.0 / s.coverage.scale();
    let cut2 = s.cutoff_sq();
    let (dpx, dpy) = (2.0 / w as f64, 2.0 / h as f64);
    let tiles: Vec<(Vec<Rec>, Vec<u32>)> = (0..bins.tiles.len())
        .into_par_iter()
        .map(|t| {
            let mut recs = Vec::new();
            let (c_base, r_base) = ((t % bins.tiles_x) * TILE, (t / bins.tiles_x) * TILE);
            for &fi in &bins.tiles[t] {
                let fi = fi as usize;
                let Some([c0, c1, r0, r1]) = bins.face_in_tile(fi, t, w, h) else {
                    continue;
                };
                let g = &bins.geoms[fi];
                let f = faces[fi];
                let span = bins.span(fi);
                for row in r0..=r1 {
                    let py = bins.py[row];
                    let Some((a, b)) = span.row(py, c0, c1) else {
                        continue;
                    };
                    for col in a..=b {
                        let p = [bins.px[col], py];
                        let Some((q, d, _)) = eval_pair(bins, fi, p, s, inv_scale, cut2) else {
                            continue;
                        };
                        let nz = q.wn[0] * ndc_z[f[0] as usize]
                            + q.wn[1] * ndc_z[f[1] as usize]
                            + q.wn[2] * ndc_z[f[2] as usize];
                        let dbary = if s.barycentric_derivatives {
                            bary_derivatives(g, &q, s.perspective_correct, dpx, dpy)
                        } else {
                            [[0.0; 3]; 2]
                        };
                        recs.push(Rec {
                            lp: ((row - r_base) * TILE + col - c_base) as u16,
                            face: fi as u32,
                            bary: attr_weights(g, &q, s.perspective_correct),
                            ndc_z: nz,
                            z: q.z,
                            prob: d,
                            dbary,
                        });
                    }
                }
            }
            // Per pixel (a counting sort of indices by tile pixel), nearest first (view depth,
            // then face) within each pixel's short list; K nearest when asked.
            let mut start = [0u32; TILE * TILE + 1];
            for r in &recs {
                start[r.lp as usize + 1] += 1;
            }
            for lp in 0..TILE * TILE {
                start[lp + 1] += start[lp];
            }
            let mut fill = start;
            let mut order = vec![0u32; recs.len()];
            for (i, r) in recs.iter().enumerate() {
                order[fill[r.lp as usize] as usize] = i as u32;
                fill[r.lp as usize] += 1;
            }
            let mut count = vec![0u32; TILE * TILE];
            let mut kept = Vec::with_capacity(recs.len());
            for lp in 0..TILE * TILE {
                let idx = &mut order[start[lp] as usize..start[lp + 1] as usize];
                idx.sort_unstable_by(|&a, &b| {
                    let (a, b) = (&recs[a as usize], &recs[b as usize]);
                    a.z.total_cmp(&b.z).then(a.face.cmp(&b.face))
                });
                let k = s.max_faces.map_or(idx.len(), |k| k.min(idx.len()));
                count[lp] = k as u32;
                kept.extend(idx[..k].iter().map(|&i| recs[i as usize]));
            }
            (kept, count)
        })
        .collect();
    // Offsets, row-major over pixels.
    let mut offsets = vec![0u32; w * h + 1];
    for row in 0..h {
        for col in 0..w {
            let t = (row / TILE) * bins.tiles_x + col / TILE;
            let c = tiles[t].1[(row % TILE) * TILE + col % TILE];
            let p = row * w + col;
            offsets[p + 1] = offsets[p] + c;
        }
    }
    let n = offsets[w * h] as usize;
    let k = (0..w * h)
        .map(|p| (offsets[p + 1] - offsets[p]) as usize)
        .max()
        .unwrap_or(0);
    let mut face = vec![0u32; n];
    let mut bary = vec![[T::zero(); 3]; n];
    let mut depth = vec![T::zero(); n];
    let mut vdepth = vec![T::zero(); n];
    let mut prob = vec![0.0f64; n];
    let nd = if s.barycentric_derivatives { n } else { 0 };
    let mut ddx = vec![[T::zero(); 3]; nd];
    let mut ddy = vec![[T::zero(); 3]; nd];
    // Per image row, its slices of every array, then rows in parallel.
    {
        let mut rows = Vec::with_capacity(h);
        let (mut fa, mut ba, mut da, mut va, mut pa) = (
            &mut face[..],
            &mut bary[..],
            &mut depth[..],
            &mut vdepth[..],
            &mut prob[..],
        );
        let (mut xa, mut ya) = (&mut ddx[..], &mut ddy[..]);
        for row in 0..h {
            let len = (offsets[(row + 1) * w] - offsets[row * w]) as usize;
            let (f0, f1) = std::mem::take(&mut fa).split_at_mut(len);
            let (b0, b1) = std::mem::take(&mut ba).split_at_mut(len);
            let (d0, d1) = std::mem::take(&mut da).split_at_mut(len);
            let (v0, v1) = std::mem::take(&mut va).split_at_mut(len);
            let (p0, p1) = std::mem::take(&mut pa).split_at_mut(len);
            let dl = if nd > 0 { len } else { 0 };
            let (x0, x1) = std::mem::take(&mut xa).split_at_mut(dl);
            let (y0, y1) = std::mem::take(&mut ya).split_at_mut(dl);
            rows.push((row, f0, b0, d0, v0, p0, x0, y0));
            (fa, ba, da, va, pa, xa, ya) = (f1, b1, d1, v1, p1, x1, y1);
        }
        rows.into_par_iter().for_each(|(row, f, b, d, v, p, x, y)| {
            let mut i = 0;
            let ty = row / TILE;
            for tx in 0..bins.tiles_x {
                let (recs, count) = &tiles[ty * bins.tiles_x + tx];
                if recs.is_empty() {
                    continue;
                }
                // The tile's records of this row: after those of the rows above.
                let lr = row % TILE;
                let start: usize = count[..lr * TILE].iter().map(|&c| c as usize).sum();
                let len: usize = count[lr * TILE..(lr + 1) * TILE]
                    .iter()
                    .map(|&c| c as usize)
                    .sum();
                for r in &recs[start..start + len] {
                    f[i] = r.face;
                    b[i] = r.bary.map(T::from_f64c);
                    d[i] = T::from_f64c(r.ndc_z);
                    v[i] = T::from_f64c(r.z);
                    p[i] = r.prob;
                    if !x.is_empty() {
                        x[i] = r.dbary[0].map(T::from_f64c);
                        y[i] = r.dbary[1].map(T::from_f64c);
                    }
                    i += 1;
                }
            }
        });
    }
    let fr = Fragments {
        width: w,
        height: h,
        k,
        offsets,
        face,
        bary,
        depth,
        view_depth: vdepth,
        dbary_dx: ddx,
        dbary_dy: ddy,
    };
    (fr, prob)
}

struct StageOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    prob: Vec<f64>,
    faces: Arc<Vec<[u32; 3]>>,
    ndc: Vec<[f64; 2]>,
    depth: Vec<f64>,
    ndc_z: Vec<f64>,
    bins: TileBins,
    s: SoftStageSettings,
}

/// Fragments per backward task.
const CHUNK: usize = 2048;

impl<T: Real> Op<T> for StageOp<T> {
    fn name(&self) -> &'static str {
        "soft_fragments"
    }

    fn forward(&mut self, _inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let prob = self.prob.iter().map(|&x| T::from_f64c(x)).collect();
        Ok(fragment_outputs(&self.fragments, prob))
    }

    /// Per fragment: its pair re-evaluated, the gradients of its barycentrics (through
    /// perspective weights, view depth, clipping and the raw barycentrics), depths and coverage
    /// (through the closest boundary point) chained to its face's NDC vertices and view
    /// depths, then to clip coordinates; corner gradients added to vertices in fragment order.
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let f = &self.fragments;
        let n = f.len();
        let get = |i: usize| grad_output_f64(ctx, i);
        let (gb, gd, gv, gp) = (get(0), get(1), get(2), get(3));
        let s = &self.s;
        let (w, inv_scale, cut2) = (s.width, 1.0 / s.coverage.scale(), s.cutoff_sq());
        // Per fragment, [dX, dY, dZ, dW] of its face's three corners.
        let mut corner = vec![0.0f64; n * 12];
        corner
            .par_chunks_mut(CHUNK * 12)
            .enumerate()
            .for_each(|(blk, out)| {
                let i0 = blk * CHUNK;
                let mut p = f.pixel_of(i0);
                for (j, acc) in out.chunks_mut(12).enumerate() {
                    let i = i0 + j;
                    while f.offsets[p + 1] as usize <= i {
                        p += 1;
                    }
                    let gbi = [gb[3 * i], gb[3 * i + 1], gb[3 * i + 2]];
                    if gbi == [0.0; 3] && gd[i] == 0.0 && gv[i] == 0.0 && gp[i] == 0.0 {
                        continue;
                    }
                    let fi = f.face[i] as usize;
                    let (row, col) = (p / w, p % w);
                    let pc = [self.bins.px[col], self.bins.py[row]];
                    let Some((q, d, inside)) = eval_pair(&self.bins, fi, pc, s, inv_scale, cut2)
                    else {
                        continue;
                    };
                    self.fragment_gradient(
                        fi,
                        pc,
                        &q,
                        d,
                        inside,
                        [gbi, [gd[i], gv[i], gp[i]]],
                        acc,
                    );
                }
            });
        let nv = self.ndc.len();
        let mut g = vec![0.0f64; nv * 4];
        let ff = &f.face;
        scatter_face_corners(&mut g, 4, &self.faces, || {
            ff.iter()
                .zip(corner.chunks_exact(12))
                .map(|(&fi, c)| (fi, c))
        });
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(&[nv, 4]), g.into_iter().map(T::from_f64c).collect())
                .expect("v x 4"),
        )])
    }
}

impl<T: Real> StageOp<T> {
    /// One fragment's corner gradients `acc` (`[dX, dY, dZ, dW]` x 3) from the gradients of
    /// its barycentrics `g[0]` and of its NDC depth, view depth and coverage `g[1]`.
    #[allow(clippy::too_many_arguments)]
    fn fragment_gradient(
        &self,
        fi: usize,
        p: [f64; 2],
        q: &Pair,
        d: f64,
        inside: bool,
        g: [[f64; 3]; 2],
        acc: &mut [f64],
    ) {
        let s = &self.s;
        let geom = &self.bins.geoms[fi];
        let f = self.faces[fi];
        let [gbary, [g_ndcz, g_z, g_prob]] = g;
        let mut gv = [[0.0f64; 2]; 3];
        let mut gdep = [0.0f64; 3];
        let mut gzc = [0.0f64; 3];
        // Coverage: D(x), x = s d^2 / scale.
        let gx = match s.coverage {
            Coverage::Sigmoid { .. } => g_prob * d * (1.0 - d),
            Coverage::Exp { .. } => {
                if inside {
                    0.0
                } else {
                    g_prob * d
                }
            }
        };
        let g = gx / s.coverage.scale();
        signed_distance_backward(geom, p, q.x, &q.w, &q.closest, g, &mut gv);
        // Barycentrics: wn, or wp_k = wn_k z / z_k.
        let mut gwn = [0.0f64; 3];
        let mut gz = g_z;
        if s.perspective_correct {
            for k in 0..3 {
                let inv = geom.inv_d[k];
                gwn[k] += gbary[k] * inv * q.z;
                gz += gbary[k] * q.wn[k] * inv;
                gdep[k] -= gbary[k] * q.wn[k] * q.z * inv * inv;
            }
        } else {
            gwn = gbary;
        }
        // NDC depth sum_k wn_k z_k / w_k.
        if g_ndcz != 0.0 {
            for k in 0..3 {
                let nz = self.ndc_z[f[k] as usize];
                gwn[k] += g_ndcz * nz;
                let wk = self.depth[f[k] as usize];
                gzc[k] += g_ndcz * q.wn[k] / wk;
                gdep[k] -= g_ndcz * q.wn[k] * nz / wk;
            }
        }
        pair_backward(geom, q, p, gwn, gz, 1.0 / geom.area, &mut gv, &mut gdep);
        for k in 0..3 {
            let vi = f[k] as usize;
            let c = ndc_to_clip(gv[k], self.ndc[vi], self.depth[vi]);
            acc[4 * k] += c[0];
            acc[4 * k + 1] += c[1];
            acc[4 * k + 2] += gzc[k];
            acc[4 * k + 3] += c[2] + gdep[k];
        }
    }
}
