//! The `f32` fast path of SoftRas: the same forward and backward as the `f64` evaluation of
//! [`super`], with the per-pair work done eight pixels at a time along each row span in single
//! precision ([`crate::simd`]).
//!
//! Taken for `f32` tapes with at most [`FAST_MAX_C`] attribute channels and screen-space
//! interpolation (`perspective_correct` off) whose constants are normal `f32` numbers
//! ([`f32_range_ok`]); `f64` tapes (gradient checking) and the other settings keep the scalar
//! `f64` evaluation.
//!
//! Lanes are 8 consecutive columns of one image row, from the first column of a row span on
//! (the lanes past the span are masked). Per face the geometry is taken relative to its first
//! vertex (pixel offsets are formed in `f64` and rounded once), so no coordinate loses more than an `f32`
//! rounding. Depth enters the blend through `u = (z - near) / (far - near) = 1 - zn`, whose
//! per-pixel minimum `u_min = 1 - m` is accumulated instead of `m`: `(zn_f - m) / gamma =
//! (u_min - u_f) / gamma` then has an absolute error of a few `f32` roundings of `u` (about
//! `1e-9`) divided by `gamma`, not of `zn ~ 1`. Per-pixel sums run in face order (each tile's
//! pairs are kept as 8-lane chunks in tile face order), per-face gradient sums in row-major
//! order within each face with a fixed lane order, so results are bit-identical for any
//! thread count, and the AVX2 and portable builds agree bit for bit.
//!
//! Truncation beyond the `f64` path: a depth weight `e_f = exp((zn_f - m) / gamma)` below
//! `e^-87` (the smallest normal `f32` range) is taken as 0. Some pair at the pixel (or the
//! background, when `m = eps`) has `zn_f = m`, i.e. `e_f = 1`; a dropped term is therefore
//! below `1.7e-38` times the largest `e` of the normaliser and changes `I` and its gradient
//! by less than that relative amount times `1 / D` of the largest term, far below `f32`
//! precision for any `D >= threshold >= 1e-30`.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use super::{Prep, SoftRasOp, PIX_STATS};
use crate::simd::{arr3, exp8, select, use_avx2, EXP_MIN, F8, LANES, M8};
use crate::soft::common::exp;
use crate::soft::lanes::{add_closest_grad, band_rows, lanes_to, offsets, Edges8, Geom32};

/// Most attribute channels the fast path handles (per-face accumulators are fixed arrays).
pub(super) const FAST_MAX_C: usize = 4;

/// Constants of one render.
#[derive(Clone, Copy)]
struct K {
    inv_sigma: f32,
    cut2: f32,
    near: f32,
    zscale: f32,
}

/// Eight (face, pixel) pairs of one row chunk: the lanes `keep` are kept (pixel within the
/// row span, centre inside the triangle or within the cut-off, clipped barycentrics that
/// normalise); the others hold neutral finite values (`D = 0`, `wn = z = 0`, `u = +inf`).
#[derive(Clone, Copy)]
struct Pair8 {
    keep: M8,
    /// `x = s d^2 / sigma`.
    x: F8,
    /// Barycentrics, raw and clipped-renormalised; `1 / sum` of the clipped ones.
    w: [F8; 3],
    wn: [F8; 3],
    inv_sumwc: F8,
    /// View depth and `u = (z - near) / (far - near)`.
    z: F8,
    u: F8,
    /// Per edge: closest parameter `t` and offset `r = q - closest point`.
    t: [F8; 3],
    rx: [F8; 3],
    ry: [F8; 3],
    /// The edge of the closest boundary point (as [`FaceGeom::closest_inside`] for an inside
    /// centre off the boundary, as [`FaceGeom::closest`] otherwise).
    sel: [M8; 3],
}

/// The pairs of face `g` with the pixel centres `(o_x + qx, o_y + qy)` of the lanes `valid`,
/// or `None` when none is kept (eq. (1) of the paper, `D = sigmoid(s d^2 / sigma)`; see
/// [`SoftRasOp::pair`]).
#[inline(always)]
fn pair8(g: &Geom32, qx: F8, qy: f32, valid: M8, k: &K) -> Option<Pair8> {
    let zero = F8::splat(0.0);
    let one = F8::splat(1.0);
    let w: [F8; 3] =
        arr3(|i| F8::splat(g.bw[i][0]) + F8::splat(g.bw[i][1]) * qx + F8::splat(g.bw[i][2] * qy));
    let inside = w[0].ge(zero) & w[1].ge(zero) & w[2].ge(zero);
    let da: [F8; 3] = arr3(|i| w[i] * F8::splat(g.alt[i]));
    let din = da[0].min(da[1]).min(da[2]);
    let dob = (-da[0]).max(-da[1]).max(-da[2]);
    let cut2 = F8::splat(k.cut2);
    if !(valid & (inside | (dob * dob).le(cut2))).any() {
        return None;
    }
    let ed = Edges8::new(g, qx, qy);
    // Closest point on each edge, and the nearest edge.
    let Edges8 { t, rx, ry, .. } = ed;
    let (d2o, out_sel) = ed.nearest();
    let inv_sigma = F8::splat(k.inv_sigma);
    let x = select(inside, din * din * inv_sigma, -(d2o * inv_sigma));
    // Inside: the foot on the nearest edge line, i.e. the edge opposite the smallest
    // w_k alt_k (k = 0 -> edge 1, 1 -> 2, 2 -> 0).
    let k0 = da[0].le(da[1]) & da[0].le(da[2]);
    let k1 = !k0 & da[1].le(da[2]);
    let k2 = !k0 & !k1;
    let use_in = x.gt(zero);
    let sel = [
        select_m(use_in, k2, out_sel[0]),
        select_m(use_in, k0, out_sel[1]),
        select_m(use_in, k1, out_sel[2]),
    ];
    let wc = w.map(|x| x.max(zero).min(one));
    let sumwc = wc[0] + wc[1] + wc[2];
    let keep = valid & (inside | d2o.le(cut2)) & sumwc.gt(zero);
    if !keep.any() {
        return None;
    }
    let inv_sumwc = select(keep, one / sumwc, zero);
    let wn = wc.map(|x| x * inv_sumwc);
    let s = wn[0] * F8::splat(g.inv_d[0])
        + wn[1] * F8::splat(g.inv_d[1])
        + wn[2] * F8::splat(g.inv_d[2]);
    let z = select(keep, one / s, zero);
    let u = select(
        keep,
        (z - F8::splat(k.near)) * F8::splat(k.zscale),
        F8::splat(f32::INFINITY),
    );
    Some(Pair8 {
        keep,
        x,
        w,
        wn,
        inv_sumwc,
        z,
        u,
        t,
        rx,
        ry,
        sel,
    })
}

#[inline(always)]
fn select_m(m: M8, a: M8, b: M8) -> M8 {
    m.select(a, b)
}

/// `(D, 1 - D)` of the kept lanes from one exponential (0 and 1 elsewhere).
#[inline(always)]
fn sigmoid8(p: &Pair8) -> (F8, F8) {
    let e = exp8(-p.x.abs());
    let one = F8::splat(1.0);
    let r = one / (one + e);
    let pos = p.x.ge(F8::splat(0.0));
    let dd = select(pos, r, e * r);
    let omd = select(pos, e * r, r);
    (select(p.keep, dd, F8::splat(0.0)), select(p.keep, omd, one))
}

/// One 8-lane chunk of kept pairs of the forward's first pass, for the second.
#[derive(Clone, Copy)]
struct Chunk {
    /// Tile-local index of lane 0 (row-major, 16 a row).
    lp: usize,
    dd: F8,
    u: F8,
    wn: [F8; 3],
}

/// Per-thread scratch of the `f32` forward (band-local row-major pixels, [`band_rows`] x
/// `width`).
/// The per-pixel arrays hold [`LANES`] more values: a chunk starts at the first column of a
/// row span, and its lanes past the span (masked, adding neutral values) may run into the next
/// row or, on the last row, into this padding.
pub(super) struct Scratch32 {
    chunks: Vec<Chunk>,
    runs: Vec<usize>,
    count: Vec<f32>,
    umin: Vec<f32>,
    prod: Vec<f32>,
    zsum: Vec<f32>,
    lsum: Vec<f64>,
    /// Attribute sums, channel-planar (`ch * (band_rows * width + LANES) + lp`).
    col: Vec<f32>,
}

impl Scratch32 {
    pub(super) fn new(c: usize, width: usize) -> Self {
        let n = band_rows(width) * width + LANES;
        Self {
            // Room for a few chunks per band pixel (sigma 1e-4 at 256 x 256 keeps about one).
            chunks: Vec::with_capacity(n),
            runs: Vec::new(),
            count: vec![0.0; n],
            umin: vec![0.0; n],
            prod: vec![0.0; n],
            zsum: vec![0.0; n],
            lsum: vec![0.0; n],
            col: vec![0.0; c * n],
        }
    }
}

/// `m = max(eps, max_f zn_f)` of a pixel from its `u_min` (start value `u0 = 1 - eps` in
/// `f32`).
#[inline]
fn pixel_m(umin: f32, u0: f32, eps: f64) -> f64 {
    if umin >= u0 {
        eps
    } else {
        1.0 - umin as f64
    }
}

/// Whether the settings' constants are normal `f32` numbers (`1 / sigma`, `1 / gamma`, the
/// depth range and its inverse): otherwise the `f64` evaluation runs.
pub(super) fn f32_range_ok(s: &super::SoftSettings) -> bool {
    let zs = 1.0 / (s.far - s.near);
    [1.0 / s.sigma, 1.0 / s.gamma, s.near, s.far, zs, 1.0 - s.eps]
        .iter()
        .all(|&v| v == 0.0 || (v.abs() >= f32::MIN_POSITIVE as f64 && v.abs() <= f32::MAX as f64))
}

/// Defines the method `$entry(&self, prep, args..)`, which runs `$imp::<C>(prep, args..)` built
/// once per channel count `C` (0-3, else [`FAST_MAX_C`]), so that the per-channel loops unroll
/// and their accumulators can stay in registers, and, where the CPU has it, with AVX2 enabled
/// (the same code: bit-identical to the portable build).
macro_rules! channel_kernel {
    ($(#[$doc:meta])* fn $entry:ident => $imp:ident($($a:ident: $t:ty),* $(,)?)) => {
        $(#[$doc])*
        pub(super) fn $entry(&self, prep: &Prep, $($a: $t),*) {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2")]
            fn avx2<const C: usize>(op: &SoftRasOp, prep: &Prep, $($a: $t),*) {
                op.$imp::<C>(prep, $($a),*)
            }
            fn pick<const C: usize>(op: &SoftRasOp, prep: &Prep, $($a: $t),*) {
                #[cfg(target_arch = "x86_64")]
                if use_avx2() {
                    // SAFETY: the CPU has AVX2 (runtime detection in `use_avx2`).
                    unsafe { avx2::<C>(op, prep, $($a),*) };
                    return;
                }
                op.$imp::<C>(prep, $($a),*)
            }
            match prep.channels {
                0 => pick::<0>(self, prep, $($a),*),
                1 => pick::<1>(self, prep, $($a),*),
                2 => pick::<2>(self, prep, $($a),*),
                3 => pick::<3>(self, prep, $($a),*),
                _ => pick::<FAST_MAX_C>(self, prep, $($a),*),
            }
        }
    };
}

impl SoftRasOp {
    fn consts(&self) -> K {
        let s = &self.s;
        K {
            inv_sigma: (1.0 / s.sigma) as f32,
            cut2: s.cutoff_sq() as f32,
            near: s.near as f32,
            zscale: (1.0 / (s.far - s.near)) as f32,
        }
    }

    channel_kernel! {
        /// [`SoftRasOp::tile_forward`] in `f32`, 8 pixels at a time, over band `band` of
        /// [`band_rows`] image rows with its faces `tf` ([`crate::soft::lanes::band_faces`]), into the band's rows of
        /// the image (`img`, `C + 1` values a pixel) and of [`Prep::pix`] (`pix`).
        fn band_forward32 => band_forward32_impl(
            band: usize,
            tf: &[u32],
            sc: &mut Scratch32,
            img: &mut [f32],
            pix: &mut [MaybeUninit<f64>],
        )
    }

    #[inline(always)]
    fn band_forward32_impl<const C: usize>(
        &self,
        prep: &Prep,
        band: usize,
        tf: &[u32],
        sc: &mut Scratch32,
        img: &mut [f32],
        pix: &mut [MaybeUninit<f64>],
    ) {
        let s = &self.s;
        let c = C;
        debug_assert_eq!(prep.channels, C);
        let bins = &prep.bins;
        let pxp = &prep.pxp[..];
        let w = s.width;
        let rows = band_rows(w);
        let r_base = band * rows;
        let r_last = (r_base + rows).min(s.height) - 1;
        // Band pixels, and the per-pixel scratch stride.
        let np = (r_last + 1 - r_base) * w;
        let bp = rows * w + LANES;
        let k = self.consts();
        let inv_gamma = F8::splat((1.0 / s.gamma) as f32);
        // The scratch as local slices (their lengths and addresses stay in registers).
        let Scratch32 {
            chunks,
            runs,
            count,
            umin,
            prod,
            zsum,
            lsum,
            col,
        } = sc;
        let (count, umin, prod) = (
            &mut count[..np + LANES],
            &mut umin[..np + LANES],
            &mut prod[..np + LANES],
        );
        let (zsum, lsum, col) = (
            &mut zsum[..np + LANES],
            &mut lsum[..np + LANES],
            &mut col[..c * bp],
        );
        chunks.clear();
        runs.clear();
        count.fill(0.0);
        umin.fill((1.0 - s.eps) as f32);
        prod.fill(1.0);
        // Pass 1: pairs, u_min and P.
        for &fi in tf.iter() {
            runs.push(chunks.len());
            let g = prep.g32[fi as usize];
            for (row, py, a, b) in bins.face_rows(fi as usize).within(r_base, r_last) {
                let qy = (py - g.o[1]) as f32;
                let mut cs = a;
                while cs <= b {
                    let valid = lanes_to(cs, b);
                    if let Some(p) = pair8(&g, offsets(pxp, cs, g.o[0]), qy, valid, &k) {
                        let (dd, omd) = sigmoid8(&p);
                        let lp = (row - r_base) * w + cs;
                        let ones = select(p.keep, F8::splat(1.0), F8::splat(0.0));
                        (F8::load(&count[lp..]) + ones).store(&mut count[lp..]);
                        F8::load(&umin[lp..]).min(p.u).store(&mut umin[lp..]);
                        (F8::load(&prod[lp..]) * omd).store(&mut prod[lp..]);
                        chunks.push(Chunk {
                            lp,
                            dd,
                            u: p.u,
                            wn: p.wn,
                        });
                    }
                    cs += LANES;
                }
            }
        }
        runs.push(chunks.len());
        // Background terms, e_b = exp((eps - m) / gamma), m = 1 - u_min (exactly eps where
        // no face has zn > eps, u_min still at its start value).
        let u0 = (1.0 - s.eps) as f32;
        for lp in 0..np {
            // exp(0) = 1 where m = eps (no face in front of the background).
            let eb = if umin[lp] >= u0 {
                1.0
            } else {
                exp((s.eps - pixel_m(umin[lp], u0, s.eps)) / s.gamma)
            };
            zsum[lp] = eb as f32;
            lsum[lp] = 0.0;
            for ch in 0..c {
                col[ch * bp + lp] = (eb * s.background.get(ch).copied().unwrap_or(0.0)) as f32;
            }
        }
        // Pass 2: the blend (eq. (6)), e_f = exp((u_min - u_f) / gamma).
        let mut fa = [[F8::default(); FAST_MAX_C]; 3];
        for (li, &fi) in tf.iter().enumerate() {
            let chunks = &chunks[runs[li]..runs[li + 1]];
            if chunks.is_empty() {
                continue;
            }
            let f = self.faces[fi as usize];
            for kk in 0..3 {
                for ch in 0..c {
                    fa[kk][ch] = F8::splat(prep.attrs[f[kk] as usize * c + ch] as f32);
                }
            }
            for ck in chunks {
                let lp = ck.lp;
                let tt = (F8::load(&umin[lp..]) - ck.u) * inv_gamma;
                let under = tt.lt(F8::splat(EXP_MIN));
                // Occluded faces (every e_f 0) add exact zeros: skipped, exponential included.
                let we = if (!under).any() {
                    ck.dd * select(under, F8::splat(0.0), exp8(tt))
                } else {
                    F8::splat(0.0)
                };
                if we.gt(F8::splat(0.0)).any() {
                    (F8::load(&zsum[lp..]) + we).store(&mut zsum[lp..]);
                    for ch in 0..c {
                        let a = ck.wn[0] * fa[0][ch] + ck.wn[1] * fa[1][ch] + ck.wn[2] * fa[2][ch];
                        let o = ch * bp + lp;
                        (F8::load(&col[o..]) + we * a).store(&mut col[o..]);
                    }
                }
                // Faint coverage (P >= 1/2): sum log1p(-D) in f64 for the silhouette.
                let faint = F8::load(&prod[lp..]).ge(F8::splat(0.5)) & ck.dd.gt(F8::splat(0.0));
                if faint.any() {
                    for l in 0..LANES {
                        if faint.lane(l) {
                            lsum[lp + l] += (-(ck.dd.0[l] as f64)).ln_1p();
                        }
                    }
                }
            }
        }
        // The band's rows of the image and of the per-pixel aggregate. Pixels no pair reaches
        // get the background and `Z = 0`, which makes the backward skip them ([`Planes`]).
        let pstride = PIX_STATS + c;
        let bg: [f64; FAST_MAX_C] =
            std::array::from_fn(|ch| s.background.get(ch).copied().unwrap_or(0.0));
        let pixels = img[..np * (c + 1)]
            .chunks_exact_mut(c + 1)
            .zip(pix[..np * pstride].chunks_exact_mut(pstride))
            .enumerate();
        for (lp, (io, po)) in pixels {
            if count[lp] == 0.0 {
                for ch in 0..c {
                    io[ch] = bg[ch] as f32;
                    po[PIX_STATS + ch].write(bg[ch]);
                }
                io[c] = 0.0;
                po[0].write(s.eps);
                po[1].write(0.0);
                po[2].write(1.0);
                continue;
            }
            let z = zsum[lp] as f64;
            for ch in 0..c {
                let v = col[ch * bp + lp] as f64 / z;
                io[ch] = v as f32;
                po[PIX_STATS + ch].write(v);
            }
            let p = prod[lp] as f64;
            io[c] = (if p < 0.5 { 1.0 - p } else { -lsum[lp].exp_m1() }) as f32;
            po[0].write(pixel_m(umin[lp], u0, s.eps));
            po[1].write(z);
            po[2].write(p);
        }
    }
}

/// The backward's per-pixel values for the `f32` path, planar (`plane * n + pixel`, `n` the
/// pixel count plus [`LANES`] of padding): the `C` attribute gradients `g`, then `g_alpha P`,
/// `g . I`, `1 / Z` and `u_min = 1 - m` (`-inf` where `g` is 0 or no pair was kept at the pixel:
/// it is skipped, and its other values are 0).
pub(super) struct Planes {
    pub v: Vec<f32>,
    pub n: usize,
}

impl Planes {
    /// From the forward's per-pixel aggregate and the output gradient `go` (`[H, W, C + 1]`,
    /// row-major, the `f32` tape's own values: no `f64` copy of the image gradient).
    pub(super) fn new(prep: &Prep, go: &[f32]) -> Self {
        match prep.channels {
            0 => Self::build::<0>(prep, go),
            1 => Self::build::<1>(prep, go),
            2 => Self::build::<2>(prep, go),
            3 => Self::build::<3>(prep, go),
            _ => Self::build::<FAST_MAX_C>(prep, go),
        }
    }

    /// [`Planes::new`] for `C` channels (the per-channel loops unroll).
    fn build<const C: usize>(prep: &Prep, go: &[f32]) -> Self {
        debug_assert_eq!(prep.channels, C);
        let pstride = PIX_STATS + C;
        let pixels = go.len() / (C + 1);
        let n = pixels + LANES;
        // Every value is written exactly once below (no image-sized zeroing first).
        let mut v: Vec<f32> = Vec::with_capacity((C + 4) * n);
        // Blocks of pixels in parallel, each writing its part of every plane (the values
        // depend on their pixel only); the padding here.
        const BLOCK: usize = 4096;
        let mut blocks: Vec<Vec<&mut [MaybeUninit<f32>]>> = (0..pixels.div_ceil(BLOCK))
            .map(|_| Vec::with_capacity(C + 4))
            .collect();
        for (i, plane) in v.spare_capacity_mut()[..(C + 4) * n]
            .chunks_mut(n)
            .enumerate()
        {
            let pad = if i == C + 3 { f32::NEG_INFINITY } else { 0.0 };
            for x in &mut plane[pixels..] {
                x.write(pad);
            }
            for (b, part) in plane[..pixels].chunks_mut(BLOCK).enumerate() {
                blocks[b].push(part);
            }
        }
        blocks.into_par_iter().enumerate().for_each(|(b, mut out)| {
            let p0 = b * BLOCK;
            let len = out[0].len();
            let gs = go[p0 * (C + 1)..(p0 + len) * (C + 1)].chunks_exact(C + 1);
            let sts = prep.pix[p0 * pstride..(p0 + len) * pstride].chunks_exact(pstride);
            for (j, (g, st)) in gs.zip(sts).enumerate() {
                // Pixels where no pair was kept (the forward leaves Z = 0) are skipped
                // too.
                if g.iter().all(|&x| x == 0.0) || !(st[1] > 0.0) {
                    for plane in out[..C + 3].iter_mut() {
                        plane[j].write(0.0);
                    }
                    out[C + 3][j].write(f32::NEG_INFINITY);
                    continue;
                }
                let mut gi = 0.0;
                for ch in 0..C {
                    out[ch][j].write(g[ch]);
                    gi += g[ch] as f64 * st[PIX_STATS + ch];
                }
                out[C][j].write((g[C] as f64 * st[2]) as f32);
                out[C + 1][j].write(gi as f32);
                out[C + 2][j].write((1.0 / st[1]) as f32);
                out[C + 3][j].write((1.0 - st[0]) as f32);
            }
        });
        // SAFETY: the capacity is at least (C + 4) n, and each of those values was written
        // above: every plane's padding by the loop over planes, and its `pixels` values by
        // the block of their pixel (every pixel, skipped or not, writes all C + 4 planes).
        unsafe { v.set_len((C + 4) * n) };
        Self { v, n }
    }
}

impl SoftRasOp {
    channel_kernel! {
        /// [`SoftRasOp::face_gradient`] in `f32`, 8 pixels at a time: per-face sums in `f32`
        /// vectors, their lanes added in `f64` at the end.
        fn face_gradient32 => face_gradient32_impl(
            pxp: &[f64],
            fi: usize,
            pl: &Planes,
            acc: &mut [f64],
        )
    }

    #[inline(always)]
    fn face_gradient32_impl<const C: usize>(
        &self,
        prep: &Prep,
        pxp: &[f64],
        fi: usize,
        pl: &Planes,
        acc: &mut [f64],
    ) {
        let s = &self.s;
        let bins = &prep.bins;
        let rc = bins.rects[fi];
        if rc[0] > rc[1] {
            return;
        }
        let c = C;
        debug_assert_eq!(prep.channels, C);
        let stride = 4 + c;
        let f = self.faces[fi];
        let geom = &bins.geoms[fi];
        let g = prep.g32[fi];
        let k = self.consts();
        let inv_area = F8::splat((1.0 / geom.area) as f32);
        let inv_gamma = F8::splat((1.0 / s.gamma) as f32);
        let inv_sigma = F8::splat(k.inv_sigma);
        let zscale = F8::splat(k.zscale);
        let zero = F8::splat(0.0);
        let one = F8::splat(1.0);
        let mut fa = [[zero; FAST_MAX_C]; 3];
        for kk in 0..3 {
            for ch in 0..c {
                fa[kk][ch] = F8::splat(prep.attrs[f[kk] as usize * c + ch] as f32);
            }
        }
        let inv_d = g.inv_d.map(F8::splat);
        let n = pl.n;
        let plane = |i: usize, pi: usize| F8::load(&pl.v[i * n + pi..]);
        // Per-lane sums over the face's pairs: NDC and view-depth gradients of the vertices,
        // attributes (each term carries an f32 rounding already, so summing in f32 adds an
        // error of the same order relative to the sum of the terms' magnitudes).
        let mut vgv = [[zero; 2]; 3];
        let mut vgdep = [zero; 3];
        let mut vgattr = [[zero; FAST_MAX_C]; 3];
        for (row, py, a, b) in bins.face_rows(fi) {
            let qy = (py - g.o[1]) as f32;
            let mut cs = a;
            while cs <= b {
                let pi = row * s.width + cs;
                let um = plane(c + 3, pi);
                let valid = lanes_to(cs, b) & um.gt(F8::splat(f32::NEG_INFINITY));
                let col = cs;
                cs += LANES;
                if !valid.any() {
                    continue;
                }
                let qx = offsets(pxp, col, g.o[0]);
                let Some(q) = pair8(&g, qx, qy, valid, &k) else {
                    continue;
                };
                let (dd, omd) = sigmoid8(&q);
                let tt = (um - q.u) * inv_gamma;
                let under = tt.lt(F8::splat(EXP_MIN)) | !q.keep;
                // (The exponential only where some lane's weight is not 0.)
                let ef = if (!under).any() {
                    select(under, zero, exp8(tt))
                } else {
                    zero
                };
                let ga_prod = plane(c, pi);
                // Where every lane's depth weight is 0 (occluded faces: e_f below e^-87) the
                // blend terms vanish exactly; only the silhouette term remains.
                let blend = (ef.gt(zero) & q.keep).any();
                let mut gch = [zero; FAST_MAX_C];
                let (mut gx, mut gscale, mut g_zn) =
                    (select(q.keep, ga_prod * dd, zero), zero, zero);
                if blend {
                    let (g_img, inv_z) = (plane(c + 1, pi), plane(c + 2, pi));
                    // g . (a_f - I).
                    let mut cdiff = -g_img;
                    for ch in 0..c {
                        gch[ch] = plane(ch, pi);
                        let af = q.wn[0] * fa[0][ch] + q.wn[1] * fa[1][ch] + q.wn[2] * fa[2][ch];
                        cdiff = cdiff + gch[ch] * af;
                    }
                    // (Masked lanes may read other pixels' values: zeroed by selects.)
                    let gblend = select(q.keep, ef * cdiff * inv_z, zero);
                    gscale = select(q.keep, dd * ef * inv_z, zero);
                    gx = select(q.keep, gblend * dd * omd + ga_prod * dd, zero);
                    g_zn = dd * gblend * inv_gamma;
                }
                // Coverage: d(d2) through the closest boundary point.
                let sign = select(q.x.ge(zero), one, -one);
                let gd2 = gx * sign * inv_sigma * F8::splat(-2.0);
                add_closest_grad(&mut vgv, &q.sel, &q.t, &q.rx, &q.ry, gd2);
                if !blend {
                    continue;
                }
                // Depth and attributes.
                let gz = -(g_zn * zscale);
                let mut gwn = [zero; 3];
                for ch in 0..c {
                    let gc = gch[ch] * gscale;
                    for kk in 0..3 {
                        gwn[kk] = gwn[kk] + gc * fa[kk][ch];
                        vgattr[kk][ch] = vgattr[kk][ch] + gc * q.wn[kk];
                    }
                }
                let gzinv = -(q.z * q.z * gz);
                for kk in 0..3 {
                    gwn[kk] = gwn[kk] + gzinv * inv_d[kk];
                    vgdep[kk] = vgdep[kk] - gzinv * q.wn[kk] * inv_d[kk] * inv_d[kk];
                }
                // Clip-and-renormalise, then raw barycentrics w_k = n_k / sum n.
                let dot = gwn[0] * q.wn[0] + gwn[1] * q.wn[1] + gwn[2] * q.wn[2];
                let gw: [F8; 3] = arr3(|kk| {
                    let open = q.w[kk].gt(zero) & q.w[kk].lt(one);
                    select(open, (gwn[kk] - dot) * q.inv_sumwc, zero)
                });
                let dot2 = gw[0] * q.w[0] + gw[1] * q.w[1] + gw[2] * q.w[2];
                for kk in 0..3 {
                    let gn = (gw[kk] - dot2) * inv_area;
                    let (i, j) = ((kk + 1) % 3, (kk + 2) % 3);
                    // a = v_i - p, b = v_j - p (relative to the first vertex).
                    let (ax, ay) = (F8::splat(g.v[i][0]) - qx, F8::splat(g.v[i][1] - qy));
                    let (bx, by) = (F8::splat(g.v[j][0]) - qx, F8::splat(g.v[j][1] - qy));
                    vgv[i][0] = vgv[i][0] + gn * by;
                    vgv[i][1] = vgv[i][1] - gn * bx;
                    vgv[j][0] = vgv[j][0] - gn * ay;
                    vgv[j][1] = vgv[j][1] + gn * ax;
                }
            }
        }
        // Lanes summed in f64 in a fixed order.
        let mut gv = [[0.0f64; 2]; 3];
        let mut gdep = [0.0f64; 3];
        let mut gattr = [[0.0f64; FAST_MAX_C]; 3];
        for kk in 0..3 {
            gv[kk] = [vgv[kk][0].sum_f64(), vgv[kk][1].sum_f64()];
            gdep[kk] = vgdep[kk].sum_f64();
            for ch in 0..c {
                gattr[kk][ch] = vgattr[kk][ch].sum_f64();
            }
        }
        for kk in 0..3 {
            let gc =
                crate::soft::common::ndc_to_clip(gv[kk], geom.v[kk], prep.depth[f[kk] as usize]);
            let o = kk * stride;
            acc[o] += gc[0];
            acc[o + 1] += gc[1];
            acc[o + 3] += gc[2] + gdep[kk];
            for ch in 0..c {
                acc[o + 4 + ch] += gattr[kk][ch];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use autodiff::ndarray::{ArrayD, IxDyn};
    use autodiff::{Real, Tape};

    use crate::mesh::Mesh;
    use crate::simd::set_force_portable;
    use crate::soft::lanes::test_support::{peers_view_proj, rel_l2};
    use crate::soft::{softras, SoftSettings};
    use crate::transform::to_clip;

    /// Image, position gradient and colour gradient of the bench scene (an icosphere under the
    /// peers' camera, per-vertex colours, loss `sum((image - 0.25)^2)`) on a `T` tape.
    fn render<T: Real>(
        subdiv: u32,
        size: usize,
        sigma: f64,
        threads: usize,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let mesh = Mesh::<f64>::icosphere(subdiv, 1.0);
        let nv = mesh.positions.len();
        let pos = ArrayD::from_shape_vec(
            IxDyn(&[nv, 3]),
            mesh.positions
                .iter()
                .flatten()
                .map(|&x| T::from_f64c(x))
                .collect(),
        )
        .unwrap();
        let col = pos.mapv(|x| T::from_f64c(0.5 + 0.5 * x.to_f64c()));
        let faces = Arc::new(mesh.faces.clone());
        let vp = peers_view_proj();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let tape = Tape::<T>::new();
            let p = tape.var(pos.clone(), true);
            let c = tape.var(col.clone(), true);
            let clip = to_clip(p, &vp);
            let mut s = SoftSettings::new(size, size, 1.0, 100.0);
            s.sigma = sigma;
            s.background = vec![0.1, 0.2, 0.3];
            let img = softras(clip, c, faces.clone(), &s).unwrap();
            let target = tape.constant(ArrayD::from_elem(
                IxDyn(&[size, size, 4]),
                T::from_f64c(0.25),
            ));
            let g = tape.backward((img - target).square().sum()).unwrap();
            let f = |t: &ArrayD<T>| t.iter().map(|x| x.to_f64c()).collect::<Vec<f64>>();
            (
                f(&img.value().unwrap()),
                f(g.get(p).unwrap()),
                f(g.get(c).unwrap()),
            )
        })
    }

    /// Largest difference relative to the largest magnitude of `b`.
    fn rel_max(a: &[f64], b: &[f64]) -> f64 {
        let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        a.iter()
            .zip(b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
            / scale
    }

    /// The `f32` fast path against the `f64` evaluation: images within `f32` precision (up to
    /// pairs at the cut-off, whose coverage is the threshold), gradients within a small
    /// relative error of the whole gradient.
    #[test]
    fn f32_path_matches_f64() {
        for (subdiv, size, sigma) in [(2, 64, 1e-3), (3, 96, 1e-4), (4, 128, 1e-5)] {
            let (i32_, gp32, gc32) = render::<f32>(subdiv, size, sigma, 2);
            let (i64_, gp64, gc64) = render::<f64>(subdiv, size, sigma, 2);
            let di = i32_
                .iter()
                .zip(&i64_)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            let (ep, ec) = (rel_l2(&gp32, &gp64), rel_l2(&gc32, &gc64));
            let (mp, mc) = (rel_max(&gp32, &gp64), rel_max(&gc32, &gc64));
            eprintln!("subdiv {subdiv} size {size} sigma {sigma}: image {di:.2e}, grad pos l2 {ep:.2e} max {mp:.2e}, col l2 {ec:.2e} max {mc:.2e}");
            assert!(gp32.iter().chain(&gc32).all(|x| x.is_finite()));
            assert!(di < 1e-4, "image {di}");
            assert!(ep < 2e-4 && mp < 5e-4, "positions {ep} {mp}");
            assert!(ec < 1e-5 && mc < 2e-5, "colours {ec} {mc}");
        }
    }

    /// An image whose height is not a multiple of the forward's [`crate::soft::lanes::band_rows`] (a
    /// partial last band) and whose width is not a multiple of 8 (chunks running into the
    /// padding): the same bits for 1 and 3 threads and from the portable build, and the
    /// `f64` evaluation's image and gradients within the tolerances above.
    #[test]
    fn f32_path_partial_band() {
        let size = 75;
        assert_ne!(size % crate::soft::lanes::band_rows(size), 0);
        let a = render::<f32>(3, size, 1e-4, 1);
        assert!(a == render::<f32>(3, size, 1e-4, 3), "3 threads differ");
        set_force_portable(true);
        let b = render::<f32>(3, size, 1e-4, 2);
        set_force_portable(false);
        assert!(a == b, "portable build differs");
        let (i64_, gp64, gc64) = render::<f64>(3, size, 1e-4, 2);
        let di =
            a.0.iter()
                .zip(&i64_)
                .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        assert!(di < 1e-4, "image {di}");
        let (ep, ec) = (rel_l2(&a.1, &gp64), rel_l2(&a.2, &gc64));
        assert!(ep < 2e-4 && ec < 1e-5, "positions {ep}, colours {ec}");
    }

    /// Settings outside `f32`'s range (here `1 / sigma`) take the `f64` evaluation and stay
    /// finite.
    #[test]
    fn out_of_range_settings_take_the_f64_path() {
        let (img, gp, gc) = render::<f32>(1, 32, 1e-40, 1);
        assert!(img.iter().chain(&gp).chain(&gc).all(|x| x.is_finite()));
    }

    /// The fast path gives the same bits for 1, 2 and 3 threads, and from its AVX2 and
    /// portable builds.
    #[test]
    fn f32_path_deterministic() {
        let a = render::<f32>(3, 80, 1e-4, 1);
        for threads in [2, 3] {
            let b = render::<f32>(3, 80, 1e-4, threads);
            assert!(a == b, "{threads} threads differ");
        }
        set_force_portable(true);
        let b = render::<f32>(3, 80, 1e-4, 2);
        set_force_portable(false);
        assert!(a == b, "portable build differs");
    }
}
