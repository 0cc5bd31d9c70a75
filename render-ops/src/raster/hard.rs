//! The hard rasterizer: tiled z-buffer forward with K nearest fragments, and the interior
//! (fixed-visibility) vector-Jacobian product of barycentrics and depths.

use autodiff::Real;
use rayon::prelude::*;

use super::bin::{bin_faces, Bins, FaceRec};
use super::clip::{ceil_u, floor_u, to_screen, Rect};
use super::edge::Setup;
use super::fragments::{assemble, Fragments, PixelCursor, TileFrags};
use super::{par_first_index, validate_inputs, RasterError, RasterSettings, TILE_SIZE};
use crate::scatter::{scatter_face_corners, IndexMap};
use crate::simd::use_avx2;

/// Per-thread dense K-buffer of a tile, reused across tiles: `k` slots per local pixel
/// (`local_row * TILE_SIZE + local_col`) of NDC depth (`+inf` when empty) and index into the
/// tile's setups, nearest first; per local row, the local columns `span[lr].0..span[lr].1`
/// that were tested (the only ones that can hold fragments) and the number of filled slots.
/// Between tiles every slot is empty and every span is empty: [`TileFrags::pack`] reads and
/// resets only the spans.
pub(crate) struct Scratch {
    pub depth: Vec<f64>,
    pub idx: Vec<u32>,
    pub span: [(u32, u32); TILE_SIZE],
    pub filled: [u32; TILE_SIZE],
    /// The record ids of the current tile's faces (read ahead to prefetch their records).
    ids: Vec<u32>,
    /// Slots per pixel.
    k: usize,
}

thread_local! {
    /// This thread's clean [`Scratch`] between tile passes ([`Scratch::with`]).
    static SCRATCH: std::cell::RefCell<Option<Scratch>> = const { std::cell::RefCell::new(None) };
}

impl Scratch {
    /// Runs `f` with a clean scratch of `k` slots per pixel: this thread's cached one when it
    /// has one of that size (a tile pass leaves it clean), else a new one; kept for the next
    /// call on this thread. Rayon's `map_init` would make one per split job, several per
    /// frame and thread, each some 12 KiB (`K = 1`) to fill.
    pub(crate) fn with<R>(k: usize, f: impl FnOnce(&mut Scratch) -> R) -> R {
        let cached = SCRATCH.with(|c| c.borrow_mut().take().filter(|s| s.k == k));
        let mut sc = cached.unwrap_or_else(|| Scratch::new(k));
        // A panic in `f` drops the scratch instead of caching a dirty one.
        let r = f(&mut sc);
        SCRATCH.with(|c| *c.borrow_mut() = Some(sc));
        r
    }

    pub(crate) fn new(k: usize) -> Self {
        // Padding for the lane groups of `z_test_span_k1` (stays empty).
        let n = TILE_SIZE * TILE_SIZE * k + SPAN_LANES;
        Self {
            depth: vec![f64::INFINITY; n],
            idx: vec![0; n],
            span: [(TILE_SIZE as u32, 0); TILE_SIZE],
            filled: [0; TILE_SIZE],
            ids: Vec::new(),
            k,
        }
    }

    /// Empties local row `lr` after a tile: refills its tested span with `+inf` and clears the
    /// span and the filled count ([`TileFrags::pack`], the direct render's `finish_tile`).
    #[inline(always)]
    pub(crate) fn reset_row(&mut self, lr: usize) {
        let (c0, c1) = self.span[lr];
        if c0 < c1 {
            let (k, p) = (self.k, lr * TILE_SIZE);
            self.depth[(p + c0 as usize) * k..(p + c1 as usize) * k].fill(f64::INFINITY);
        }
        self.span[lr] = (TILE_SIZE as u32, 0);
        self.filled[lr] = 0;
    }

    /// Records that local columns `c0..=c1` of local row `lr` are tested.
    #[inline(always)]
    fn touch(&mut self, lr: usize, c0: u32, c1: u32) {
        let sp = &mut self.span[lr];
        sp.0 = sp.0.min(c0);
        sp.1 = sp.1.max(c1 + 1);
    }
}

/// Read-only inputs of the tile pass.
pub(crate) struct Ctx<'a> {
    pub verts: &'a [[f64; 4]],
    pub bins: &'a Bins,
    pub s: &'a RasterSettings,
    /// Whether the AVX2 span test may run ([`use_avx2`]).
    pub avx2: bool,
}

/// Rasterizes clip-space triangles into the `K` nearest fragments per pixel.
///
/// `clip` holds the clip-space position `(x, y, z, w)` of every vertex, `faces` counter-clockwise
/// (front-facing) vertex triples. See the [module documentation](super) for the method: 2D
/// homogeneous rasterization (Olano and Greer 1997) with exact Pineda edge functions and the
/// top-left rule, near/far planes as a per-fragment test on NDC depth, `32 x 32` tiles in
/// parallel. Fragments keep the barycentrics of the original triangle also when it crosses the
/// near plane; in screen-space mode (`perspective_correct == false`) they are the affine
/// barycentrics of the projected vertices (for a triangle crossing the eye plane `w = 0` these
/// leave `[0, 1]`). Output is bit-identical for any number of rayon threads.
///
/// # Errors
/// Empty or too large images, `faces_per_pixel` out of range, face indices out of range,
/// non-finite clip coordinates, and more fragments than `u32` offsets hold.
pub fn rasterize_fragments<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    s: &RasterSettings,
) -> Result<Fragments<T>, RasterError> {
    rasterize_with(clip, faces, s, use_avx2())
}

/// [`rasterize_fragments`], with the AVX2 kernels (the K = 1 span test and assembly) when `avx2`
/// (bit-identical results either way).
pub(crate) fn rasterize_with<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    s: &RasterSettings,
    avx2: bool,
) -> Result<Fragments<T>, RasterError> {
    let (verts, bins, avx2) = prepare(clip, faces, s, avx2)?;
    let ctx = Ctx {
        verts: &verts,
        bins: &bins,
        s,
        avx2,
    };
    let tiles: Vec<TileFrags> = (0..bins.num_tiles())
        .into_par_iter()
        .map(|t| {
            Scratch::with(s.faces_per_pixel, |sc| {
                let rect = bins.tile_rect(t, s.width, s.height);
                if z_test_tile(t, &rect, &ctx, sc, &mut NoShade) {
                    TileFrags::pack(sc, &rect, s.faces_per_pixel)
                } else {
                    TileFrags::empty()
                }
            })
        })
        .collect();
    assemble(tiles, &bins, s, avx2)
}

/// Validates the inputs, maps the vertices to screen space and bins the faces into tiles:
/// the set-up shared by [`rasterize_fragments`] and the direct render ([`super::direct`]). Returns the
/// vertices (`f64` clip coordinates), the bins, and whether the AVX2 kernels may run (`avx2`
/// and the CPU has them).
pub(crate) fn prepare<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    s: &RasterSettings,
    avx2: bool,
) -> Result<(Vec<[f64; 4]>, Bins, bool), RasterError> {
    // The AVX2 kernels only where the CPU has them.
    let avx2 = avx2 && use_avx2();
    validate_inputs(clip, faces, s)?;
    autodiff::tune_malloc();
    let nv = clip.len();
    // Written once each in parallel (not zeroed first on one thread).
    let mut verts = Vec::<[f64; 4]>::with_capacity(nv);
    let mut proj = Vec::<[f64; 2]>::with_capacity(nv);
    let mut outcodes = Vec::<u8>::with_capacity(nv);
    verts.spare_capacity_mut()[..nv]
        .par_iter_mut()
        .zip(proj.spare_capacity_mut()[..nv].par_iter_mut())
        .zip(outcodes.spare_capacity_mut()[..nv].par_iter_mut())
        .zip(clip.par_iter())
        .with_min_len(4096)
        .for_each(|(((v, p), o), c)| {
            let (sv, sp, so) = to_screen(c, s.width, s.height);
            v.write(sv);
            p.write(sp);
            o.write(so);
        });
    // SAFETY: all `nv` elements of each were written above.
    unsafe {
        verts.set_len(nv);
        proj.set_len(nv);
        outcodes.set_len(nv);
    }
    let bins = bin_faces(&verts, &proj, &outcodes, faces, s);
    Ok((verts, bins, avx2))
}

/// Z-buffers the faces binned to tile `t` (pixel rectangle `rect`) into the K-buffer of
/// `sc` ([`Scratch`]); false when no face is binned to the tile (nothing was touched).
pub(crate) fn z_test_tile<S: ZShader>(
    t: usize,
    rect: &Rect,
    ctx: &Ctx<'_>,
    sc: &mut Scratch,
    shader: &mut S,
) -> bool {
    let (s, verts) = (ctx.s, ctx.verts);
    let k = s.faces_per_pixel;
    let mut ids = std::mem::take(&mut sc.ids);
    ids.clear();
    ids.extend(ctx.bins.tile_faces(t));
    let any = !ids.is_empty();
    for (j, &id) in ids.iter().enumerate() {
        // On fine meshes a tile's records lie far apart in memory (faces in index order):
        // fetch a few records ahead so that their cache misses overlap.
        if let Some(&next) = ids.get(j + PREFETCH_AHEAD) {
            prefetch_record(ctx.bins.rec(next));
        }
        let rec = ctx.bins.rec(id);
        let r = rec.rect.intersect(rect);
        if r.is_empty() {
            continue;
        }
        if S::ACTIVE {
            shader.face(rec);
        }
        z_test_face(
            &rec.st, &rec.dz, &r, rect, verts, sc, id, k, ctx.avx2, shader,
        );
    }
    sc.ids = ids;
    any
}

/// Records ahead of the current one that [`z_test_tile`] prefetches.
const PREFETCH_AHEAD: usize = 4;

/// Asks the CPU to start loading every cache line of a face record (no effect on results).
#[inline(always)]
fn prefetch_record(rec: &FaceRec) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let p = (rec as *const FaceRec).cast::<i8>();
        for off in (0..std::mem::size_of::<FaceRec>()).step_by(64) {
            // SAFETY: `p + off` lies inside the record (a prefetch never faults anyway, and
            // SSE, which has it, is part of the x86-64 baseline).
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.add(off)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = rec;
}

/// Immediate shading hooked into the z-test, for the direct render's fast path
/// ([`super::direct`]): every fragment is shaded at the moment it wins its pixel's depth test,
/// so a pixel's last shaded value is that of its nearest fragment. The rasterizer passes
/// [`NoShade`], whose hooks are compiled out (`ACTIVE == false`).
pub(crate) trait ZShader {
    /// Whether the hooks are called.
    const ACTIVE: bool;
    /// Face record `rec` is about to be z-tested.
    fn face(&mut self, rec: &FaceRec);
    /// The lanes `m` (bit `l`: lane `l`) of the group of four pixels at K-buffer slots
    /// `slot..slot + 4` won their depth tests, with edge values `e` and their sum `sum`
    /// ([`Setup::eval`], as [`z_test_span_k1`] computes them).
    ///
    /// # Safety
    /// The CPU supports AVX2; the slots are the current tile's.
    #[cfg(target_arch = "x86_64")]
    unsafe fn lanes(
        &mut self,
        e: &[std::arch::x86_64::__m256d; 3],
        sum: std::arch::x86_64::__m256d,
        m: i32,
        slot: usize,
    );
    /// Pixel `(col, row)` (K-buffer slot `slot`) of the face with setup `st` has just become
    /// the nearest in the exact per-pixel test ([`test_pixel`]).
    fn pixel(&mut self, st: &Setup, col: f64, row: f64, slot: usize);
}

/// No shading: the rasterizer's z-test.
pub(crate) struct NoShade;

impl ZShader for NoShade {
    const ACTIVE: bool = false;
    #[inline(always)]
    fn face(&mut self, _: &FaceRec) {}
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn lanes(
        &mut self,
        _: &[std::arch::x86_64::__m256d; 3],
        _: std::arch::x86_64::__m256d,
        _: i32,
        _: usize,
    ) {
    }
    #[inline(always)]
    fn pixel(&mut self, _: &Setup, _: f64, _: f64, _: usize) {}
}

/// Tests the pixels of `r` (inside tile `rect`) against one face (setup `st`, NDC depth plane
/// `dz`, [`Setup::depth_plane`]) and inserts its fragments into the K-buffer under record id
/// `li`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn z_test_face<S: ZShader>(
    st: &Setup,
    dz: &[f64; 3],
    r: &Rect,
    rect: &Rect,
    verts: &[[f64; 4]],
    sc: &mut Scratch,
    li: u32,
    k: usize,
    avx2: bool,
    shader: &mut S,
) {
    #[cfg(not(target_arch = "x86_64"))]
    let _ = avx2;
    // The near and far planes are the per-fragment test -1 <= d <= 1 on the depth plane.
    let (w, h) = (r.c1 - r.c0 + 1, r.r1 - r.r0 + 1);
    if w * h <= 4 {
        // Tiny boxes: test every pixel, cheaper than setting up row spans.
        for row in r.r0..=r.r1 {
            let rf = row as f64;
            let tr = st.row(rf);
            let dr = dz[1] * rf + dz[2];
            let lr = (row - rect.r0) as usize;
            sc.touch(lr, r.c0 - rect.c0, r.c1 - rect.c0);
            let first = lr * TILE_SIZE + (r.c0 - rect.c0) as usize;
            for (j, col) in (r.c0..r.c1 + 1).enumerate() {
                let p = (first + j) * k;
                test_pixel(
                    st, verts, sc, k, li, &tr, dr, dz[0], col as f64, rf, p, lr, shader,
                );
            }
        }
        return;
    }
    // Row spans. A covered pixel has a_i col + b_i row + c_i >= -bnd_i in real arithmetic on the
    // computed coefficients (the bound covers their rounding), i.e. col >= al_i + be_i row for
    // a_i > 0 and col <= al_i + be_i row for a_i < 0, with al_i = (-bnd_i - c_i) / a_i and
    // be_i = -b_i / a_i; the margin covers the few ulps of computing that bound in f64 (NaN
    // bounds are ignored by the comparisons, which is conservative). Edges with a_i == 0 bound
    // the rows instead. Pixels in a span still get the exact test.
    let bnd = st.bnd;
    let (mut r0, mut r1) = (r.r0 as f64, r.r1 as f64);
    let mut lal = [f64::NEG_INFINITY; 3];
    let mut lbe = [0.0; 3];
    let mut ral = [f64::INFINITY; 3];
    let mut rbe = [0.0; 3];
    for i in 0..3 {
        let (a, b) = (st.a[i], st.b[i]);
        let num = -bnd[i] - st.c[i];
        if a != 0.0 {
            let ia = 1.0 / a;
            let (al, be) = (num * ia, -b * ia);
            let m = 1e-12 * (al.abs() + be.abs() * r1) + 1e-9;
            if a > 0.0 {
                lal[i] = al - m;
                lbe[i] = be;
            } else {
                ral[i] = al + m;
                rbe[i] = be;
            }
        } else if b != 0.0 {
            let q = num / b;
            let m = 1e-12 * q.abs() + 1e-9;
            if b > 0.0 {
                r0 = if q - m > r0 { q - m } else { r0 };
            } else {
                r1 = if q + m < r1 { q + m } else { r1 };
            }
        } else if num > 0.0 {
            return;
        }
    }
    if !(r0 <= r1) {
        return;
    }
    let spans = RowSpans {
        lal,
        lbe,
        ral,
        rbe,
        rows: ceil_u(r0)..floor_u(r1) + 1,
        c0: r.c0 as f64,
        c1: r.c1 as f64,
    };
    #[cfg(target_arch = "x86_64")]
    if k == 1 && avx2 {
        // SAFETY: `avx2` is set only when the CPU has AVX2 (`use_avx2`).
        unsafe { z_test_rows_k1(st, dz, &spans, rect, verts, sc, li, shader) };
        return;
    }
    for row in spans.rows.clone() {
        let Some((cl, cr)) = spans.row(row) else {
            continue;
        };
        let rf = row as f64;
        let tr = st.row(rf);
        let dr = dz[1] * rf + dz[2];
        let lr = (row - rect.r0) as usize;
        sc.touch(lr, cl - rect.c0, cr - rect.c0);
        let first = lr * TILE_SIZE + (cl - rect.c0) as usize;
        for (j, col) in (cl..cr + 1).enumerate() {
            let p = (first + j) * k;
            test_pixel(
                st, verts, sc, k, li, &tr, dr, dz[0], col as f64, rf, p, lr, shader,
            );
        }
    }
}

/// The rows of a face's box (within one tile) and, per row, the columns that may be covered
/// ([`z_test_face`]): `al_i + be_i row` bounds from the left (`lal`, `lbe`) or right (`ral`,
/// `rbe`), within `c0..=c1`.
struct RowSpans {
    lal: [f64; 3],
    lbe: [f64; 3],
    ral: [f64; 3],
    rbe: [f64; 3],
    rows: std::ops::Range<u32>,
    c0: f64,
    c1: f64,
}

impl RowSpans {
    /// The first and last column of row `row` that may be covered, if any.
    #[inline(always)]
    fn row(&self, row: u32) -> Option<(u32, u32)> {
        let rf = row as f64;
        let mut lo = self.c0;
        let mut hi = self.c1;
        for i in 0..3 {
            let ql = self.lal[i] + self.lbe[i] * rf;
            let qr = self.ral[i] + self.rbe[i] * rf;
            lo = if ql > lo { ql } else { lo };
            hi = if qr < hi { qr } else { hi };
        }
        if !(lo <= hi) {
            return None;
        }
        // c0 <= lo <= hi <= c1 here.
        let (cl, cr) = (ceil_u(lo), floor_u(hi));
        (cl <= cr).then_some((cl, cr))
    }

    /// [`RowSpans::row`] for the four rows `row..row + 4` at once with AVX2, one row per
    /// lane: the same products and sums, and the same `max` / `min` sequence over the edges
    /// (`max_pd(q, lo)` is `q > lo ? q : lo`, so a NaN bound is dropped as in the scalar
    /// comparison), the columns rounded with `roundpd`. Returns the first and last columns
    /// per row and a mask whose bit `l` says that row `row + l` has a span (the columns of the
    /// others are unspecified). The same spans, bit for bit.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    #[inline]
    fn rows4_avx2(&self, v: &SpanVecs, row: u32) -> ([i32; 4], [i32; 4], i32) {
        use std::arch::x86_64::*;
        let rf = _mm256_add_pd(
            _mm256_set1_pd(row as f64),
            _mm256_setr_pd(0.0, 1.0, 2.0, 3.0),
        );
        let (mut lo, mut hi) = (v.c0, v.c1);
        for i in 0..3 {
            let ql = _mm256_add_pd(v.lal[i], _mm256_mul_pd(v.lbe[i], rf));
            let qr = _mm256_add_pd(v.ral[i], _mm256_mul_pd(v.rbe[i], rf));
            lo = _mm256_max_pd(ql, lo);
            hi = _mm256_min_pd(qr, hi);
        }
        let some = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(lo, hi));
        // Where lo <= hi: c0 <= lo <= hi <= c1 (columns, below 2^31).
        let cl = _mm256_cvttpd_epi32(_mm256_ceil_pd(lo));
        let cr = _mm256_cvttpd_epi32(_mm256_floor_pd(hi));
        let empty = _mm_movemask_ps(_mm_castsi128_ps(_mm_cmpgt_epi32(cl, cr)));
        let (mut a, mut b) = ([0i32; 4], [0i32; 4]);
        // SAFETY: `a` and `b` hold four i32.
        unsafe {
            _mm_storeu_si128(a.as_mut_ptr().cast(), cl);
            _mm_storeu_si128(b.as_mut_ptr().cast(), cr);
        }
        (a, b, some & !empty)
    }
}

/// A face's [`RowSpans`] bounds broadcast for [`RowSpans::rows4_avx2`] (one row per lane).
#[cfg(target_arch = "x86_64")]
struct SpanVecs {
    lal: [std::arch::x86_64::__m256d; 3],
    lbe: [std::arch::x86_64::__m256d; 3],
    ral: [std::arch::x86_64::__m256d; 3],
    rbe: [std::arch::x86_64::__m256d; 3],
    c0: std::arch::x86_64::__m256d,
    c1: std::arch::x86_64::__m256d,
}

#[cfg(target_arch = "x86_64")]
impl SpanVecs {
    /// # Safety
    /// The CPU must support AVX.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn new(s: &RowSpans) -> Self {
        use std::arch::x86_64::*;
        let v = |x: [f64; 3]| x.map(|x| _mm256_set1_pd(x));
        SpanVecs {
            lal: v(s.lal),
            lbe: v(s.lbe),
            ral: v(s.ral),
            rbe: v(s.rbe),
            c0: _mm256_set1_pd(s.c0),
            c1: _mm256_set1_pd(s.c1),
        }
    }
}

/// The row loop of [`z_test_face`] for `K = 1` with AVX2: each row's span goes through
/// [`z_test_span_k1`] (inlined here, with the face's constants kept across rows), and the
/// pixels it leaves ambiguous through the exact [`test_pixel`].
///
/// # Safety
/// The CPU must support AVX2; `sc` is a `K = 1` scratch.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn z_test_rows_k1<S: ZShader>(
    st: &Setup,
    dz: &[f64; 3],
    spans: &RowSpans,
    rect: &Rect,
    verts: &[[f64; 4]],
    sc: &mut Scratch,
    li: u32,
    shader: &mut S,
) {
    use std::arch::x86_64::*;
    let sv = SpanVecs::new(spans);
    // The row parts `b_i row + c_i` and `dz_1 row + dz_2` are made in vector registers from
    // broadcasts (the same products and sums as `Setup::row`): scalar results spilled to
    // the stack and reloaded as vectors stall store-to-load forwarding.
    let (b, c) = (
        st.b.map(|x| _mm256_set1_pd(x)),
        st.c.map(|x| _mm256_set1_pd(x)),
    );
    let (dz1, dz2) = (_mm256_set1_pd(dz[1]), _mm256_set1_pd(dz[2]));
    // The spans of four rows at a time (independent of each other, unlike the row bodies).
    let (mut quad, mut spans4) = (u32::MAX, ([0i32; 4], [0i32; 4], 0i32));
    for row in spans.rows.clone() {
        let q = row & !3;
        if q != quad {
            (quad, spans4) = (q, spans.rows4_avx2(&sv, q));
        }
        let l = (row - q) as usize;
        if spans4.2 & (1 << l) == 0 {
            continue;
        }
        let (cl, cr) = (spans4.0[l] as u32, spans4.1[l] as u32);
        let rf = row as f64;
        let rv = _mm256_set1_pd(rf);
        let t = [0, 1, 2].map(|i| _mm256_add_pd(_mm256_mul_pd(b[i], rv), c[i]));
        let drv = _mm256_add_pd(_mm256_mul_pd(dz1, rv), dz2);
        let lr = (row - rect.r0) as usize;
        sc.touch(lr, cl - rect.c0, cr - rect.c0);
        let first = lr * TILE_SIZE + (cl - rect.c0) as usize;
        // The K-buffer has SPAN_LANES slots of padding past the last pixel.
        let n = (cr - cl) as usize + 1;
        let slots = first..first + n.next_multiple_of(SPAN_LANES);
        // SAFETY: the CPU has AVX2 (the caller's contract).
        let (filled, ambiguous) = unsafe {
            z_test_span_k1(
                st,
                &t,
                drv,
                dz[0],
                cl,
                n,
                &mut sc.depth[slots.clone()],
                &mut sc.idx[slots],
                li,
                shader,
                first,
            )
        };
        sc.filled[lr] += filled;
        if ambiguous {
            // The pixels the filter could not settle, exactly (rare: pixels within a few
            // ulps of an edge); the others were settled above.
            let (tr, dr) = (st.row(rf), dz[1] * rf + dz[2]);
            for (j, col) in (cl..cr + 1).enumerate() {
                if ambiguous_pixel(st, &st.eval(col as f64, &tr)) {
                    let p = first + j;
                    test_pixel(
                        st, verts, sc, 1, li, &tr, dr, dz[0], col as f64, rf, p, lr, shader,
                    );
                }
            }
        }
    }
}

/// Whether the filter leaves pixel coverage open: not certainly inside (`e_i > bnd_i` for
/// all `i`) and not certainly outside (`e_i < -bnd_i` for some `i`).
#[inline(always)]
fn ambiguous_pixel(st: &Setup, e: &[f64; 3]) -> bool {
    let bnd = &st.bnd;
    let inside = (e[0] > bnd[0]) & (e[1] > bnd[1]) & (e[2] > bnd[2]);
    let outside = (e[0] < -bnd[0]) | (e[1] < -bnd[1]) | (e[2] < -bnd[2]);
    !inside & !outside
}

/// Pixels [`z_test_span_k1`] tests together.
pub(crate) const SPAN_LANES: usize = 4;

/// [`test_pixel`] for `K = 1` over the `n` pixels `c0..c0 + n` of one row (row part `t` of
/// the edge functions and `dr` of the depth plane `dza col + dr`, broadcast; K-buffer slots `depth` and `idx`, one per
/// pixel) with AVX2, [`SPAN_LANES`] pixels at a time, for the pixels the filter settles. The
/// slices must hold `n` rounded up to a multiple of [`SPAN_LANES`] slots; lanes past `n` store
/// back what they read. Returns the number of slots filled for the first time and whether some
/// pixel was [ambiguous](ambiguous_pixel): those are left untouched for the exact test. Each
/// lane computes [`test_pixel`]'s edge values, depth and comparisons with the same IEEE
/// operations in the same order (no fused multiply-adds), so the results are bit-identical.
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn z_test_span_k1<S: ZShader>(
    st: &Setup,
    t: &[std::arch::x86_64::__m256d; 3],
    dr: std::arch::x86_64::__m256d,
    dza: f64,
    c0: u32,
    n: usize,
    depth: &mut [f64],
    idx: &mut [u32],
    li: u32,
    shader: &mut S,
    slot0: usize,
) -> (u32, bool) {
    use std::arch::x86_64::*;
    let groups = n.div_ceil(SPAN_LANES);
    assert!(depth.len() >= groups * SPAN_LANES && idx.len() >= groups * SPAN_LANES);
    let a = st.a.map(|x| _mm256_set1_pd(x));
    let hi = st.bnd.map(|x| _mm256_set1_pd(x));
    let lo = st.bnd.map(|x| _mm256_set1_pd(-x));
    let dza = _mm256_set1_pd(dza);
    let (one, m_one, zero) = (
        _mm256_set1_pd(1.0),
        _mm256_set1_pd(-1.0),
        _mm256_setzero_pd(),
    );
    let (inf, four) = (_mm256_set1_pd(f64::INFINITY), _mm256_set1_pd(4.0));
    let li32 = _mm_set1_epi32(li as i32);
    // Lane l of group g is pixel j = 4 g + l at column c0 + j (exact in f64).
    let mut jv = _mm256_set_pd(3.0, 2.0, 1.0, 0.0);
    let mut col = _mm256_add_pd(_mm256_set1_pd(c0 as f64), jv);
    let nv = _mm256_set1_pd(n as f64);
    let (mut filled, mut ambiguous) = (0u32, 0i32);
    for g in 0..groups {
        let j = g * SPAN_LANES;
        // Setup::eval: a_i col + (b_i row + c_i).
        let e0 = _mm256_add_pd(_mm256_mul_pd(a[0], col), t[0]);
        let e1 = _mm256_add_pd(_mm256_mul_pd(a[1], col), t[1]);
        let e2 = _mm256_add_pd(_mm256_mul_pd(a[2], col), t[2]);
        let inside = _mm256_and_pd(
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_GT_OQ>(e0, hi[0]),
                _mm256_cmp_pd::<_CMP_GT_OQ>(e1, hi[1]),
            ),
            _mm256_cmp_pd::<_CMP_GT_OQ>(e2, hi[2]),
        );
        let outside = _mm256_or_pd(
            _mm256_or_pd(
                _mm256_cmp_pd::<_CMP_LT_OQ>(e0, lo[0]),
                _mm256_cmp_pd::<_CMP_LT_OQ>(e1, lo[1]),
            ),
            _mm256_cmp_pd::<_CMP_LT_OQ>(e2, lo[2]),
        );
        let live = _mm256_cmp_pd::<_CMP_LT_OQ>(jv, nv);
        // live & !inside & !outside
        let amb = _mm256_andnot_pd(outside, _mm256_andnot_pd(inside, live));
        ambiguous |= _mm256_movemask_pd(amb);
        let d = _mm256_add_pd(_mm256_mul_pd(dza, col), dr);
        // SAFETY: `j + 4 <= groups * 4 <= depth.len()` (asserted above).
        let old = unsafe { _mm256_loadu_pd(depth.as_ptr().add(j)) };
        let sum = _mm256_add_pd(_mm256_add_pd(e0, e1), e2);
        let ok = _mm256_and_pd(
            _mm256_and_pd(
                _mm256_and_pd(live, inside),
                _mm256_and_pd(
                    _mm256_cmp_pd::<_CMP_GE_OQ>(d, m_one),
                    _mm256_cmp_pd::<_CMP_LE_OQ>(d, one),
                ),
            ),
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_LT_OQ>(d, old),
                _mm256_cmp_pd::<_CMP_GT_OQ>(sum, zero),
            ),
        );
        let m = _mm256_movemask_pd(ok);
        if m != 0 {
            if !S::ACTIVE {
                // (A shader does not read the counts.)
                let fresh = _mm256_and_pd(ok, _mm256_cmp_pd::<_CMP_EQ_OQ>(old, inf));
                filled += _mm256_movemask_pd(fresh).count_ones();
            }
            // SAFETY: as for the load.
            unsafe { _mm256_storeu_pd(depth.as_mut_ptr().add(j), _mm256_blendv_pd(old, d, ok)) };
            // The low halves of the 64-bit lane masks, as four 32-bit masks.
            let ok32 = _mm256_castsi256_si128(_mm256_permutevar8x32_epi32(
                _mm256_castpd_si256(ok),
                _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6),
            ));
            // SAFETY: `j + 4 <= idx.len()` (asserted above).
            unsafe { _mm_maskstore_epi32(idx.as_mut_ptr().add(j).cast(), ok32, li32) };
            if S::ACTIVE {
                // SAFETY: the CPU has AVX2 (the caller's contract); slots `slot0 + j..+4`
                // are the group's.
                unsafe { shader.lanes(&[e0, e1, e2], sum, m, slot0 + j) };
            }
        }
        col = _mm256_add_pd(col, four);
        jv = _mm256_add_pd(jv, four);
    }
    (filled, ambiguous != 0)
}

/// Coverage, depth and K-buffer insertion of one pixel (K-buffer slots `p..p + k`, local row
/// `lr`, whose filled-slot count it keeps). A fragment that becomes the pixel's nearest goes
/// to `shader` ([`ZShader::pixel`]).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn test_pixel<S: ZShader>(
    st: &Setup,
    verts: &[[f64; 4]],
    sc: &mut Scratch,
    k: usize,
    li: u32,
    tr: &[f64; 3],
    dr: f64,
    dza: f64,
    col: f64,
    rf: f64,
    p: usize,
    lr: usize,
    shader: &mut S,
) {
    let bnd = &st.bnd;
    let e = st.eval(col, tr);
    // Outside the band |e_i| <= bnd_i the f64 sign is the exact sign.
    let certain_in = (e[0] > bnd[0]) & (e[1] > bnd[1]) & (e[2] > bnd[2]);
    if !certain_in {
        if (e[0] < -bnd[0]) | (e[1] < -bnd[1]) | (e[2] < -bnd[2]) {
            return;
        }
        if !st.covered_exact(verts, &e, col, rf) {
            return;
        }
    }
    let d = dza * col + dr;
    // Near and far planes; empty K-buffer slots hold +inf. sum e > 0 holds exactly for
    // covered pixels; its f64 value fails only for slivers at the precision limit, whose
    // barycentrics could not be normalised.
    if !((-1.0..=1.0).contains(&d) && d < sc.depth[p + k - 1] && e[0] + e[1] + e[2] > 0.0) {
        return;
    }
    // A slot is filled unless the pixel's last slot was (its fragment then drops out).
    sc.filled[lr] += (sc.depth[p + k - 1] == f64::INFINITY) as u32;
    // Insertion keeping earlier (lower-index) faces first among equal depths.
    let mut i = p + k - 1;
    while i > p && sc.depth[i - 1] > d {
        sc.depth[i] = sc.depth[i - 1];
        sc.idx[i] = sc.idx[i - 1];
        i -= 1;
    }
    sc.depth[i] = d;
    sc.idx[i] = li;
    if S::ACTIVE && i == p {
        shader.pixel(st, col, rf, p);
    }
}

/// Vector-Jacobian product of [`rasterize_fragments`] with the visibility (which face each fragment
/// belongs to) held fixed: the interior gradient of the hard rasterizer.
///
/// `grad_bary[i]` is `dL/dbary` of fragment `i` (its three components are independent outputs);
/// `grad_depth` and `grad_view_depth` optionally give `dL/ddepth` (NDC) and `dL/dview_depth`.
/// Returns `dL/dclip` for every vertex, `[x, y, z, w]`. Barycentrics and depths are recomputed
/// in `f64` from `clip` at each fragment's pixel centre, following `s.perspective_correct`:
/// with `M` the `(x, y, w)` columns of the face and `p` the pixel in NDC, `u = M^-1 p`,
/// `b = u / sum(u)`, `view_depth = 1 / sum(u)`, screen-space barycentrics `u_i w_i`, and
/// `dL/dM = -M^-T (dL/du) u^T`.
///
/// Contributions are computed in parallel over fixed chunks of 4096 fragments; within a chunk
/// the contributions of each face are summed (in fragment order; without depth gradients in
/// the factored form of `RunVjp`, multiplied out once per face and chunk), and the faces'
/// sums are added into the output in chunk order, so the result is bit-identical for any
/// number of threads. Divisions by `det M` are products with its reciprocal, computed once per
/// face and chunk.
///
/// # Errors
/// As [`rasterize_fragments`], plus gradient arrays whose lengths differ from `frags.len()` and fragments
/// that do not match the settings or faces.
pub fn rasterize_backward<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    frags: &Fragments<T>,
    grad_bary: &[[T; 3]],
    grad_depth: Option<&[T]>,
    grad_view_depth: Option<&[T]>,
    s: &RasterSettings,
) -> Result<Vec<[T; 4]>, RasterError> {
    rasterize_backward_at(
        clip,
        faces,
        frags,
        grad_bary,
        grad_depth,
        grad_view_depth,
        s,
        None,
    )
}

/// [`rasterize_backward`] with each fragment's barycentrics taken at its own NDC point
/// `points[i]` instead of its pixel centre (the ray tracer's jittered samples,
/// [`crate::raytrace::stage`]).
#[allow(clippy::too_many_arguments)]
pub(crate) fn rasterize_backward_at<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    frags: &Fragments<T>,
    grad_bary: &[[T; 3]],
    grad_depth: Option<&[T]>,
    grad_view_depth: Option<&[T]>,
    s: &RasterSettings,
    points: Option<&[[f64; 2]]>,
) -> Result<Vec<[T; 4]>, RasterError> {
    validate_inputs(clip, faces, s)?;
    if frags.width != s.width || frags.height != s.height {
        return Err(RasterError::FragmentsMismatch(format!(
            "fragments are {}x{}, settings say {}x{}",
            frags.width, frags.height, s.width, s.height
        )));
    }
    frags.validate()?;
    let n = frags.len();
    if let Some(i) = par_first_index(n, |i| frags.face[i] as usize >= faces.len()) {
        return Err(RasterError::FragmentsMismatch(format!(
            "fragment {i} has face {} but there are {} faces",
            frags.face[i],
            faces.len()
        )));
    }
    let check = |what, got: usize| {
        if got == n {
            Ok(())
        } else {
            Err(RasterError::LengthMismatch {
                what,
                got,
                expected: n,
            })
        }
    };
    check("grad_bary", grad_bary.len())?;
    if let Some(p) = points {
        check("points", p.len())?;
    }
    if let Some(g) = grad_depth {
        check("grad_depth", g.len())?;
    }
    if let Some(g) = grad_view_depth {
        check("grad_view_depth", g.len())?;
    }

    const BLOCK: usize = 1 << 15;
    let mut acc = vec![[0.0f64; 4]; clip.len()];
    let depth_grads = grad_depth.is_some() || grad_view_depth.is_some();
    let mut start = 0;
    while start < n {
        let end = (start + BLOCK).min(n);
        // Per fixed chunk of fragments, one contribution per face met in it (in order of first
        // touch), the sum of its fragments' products in fragment order: without depth
        // gradients the factored sum (`RunVjp`) multiplied out once per face and chunk. The
        // chunking does not depend on the thread count.
        let sums: Vec<Vec<(u32, [[f64; 4]; 3])>> = (0..(end - start).div_ceil(BWD_CHUNK))
            .into_par_iter()
            .map_init(BwdScratch::new, |sc, ci| {
                let i0 = start + ci * BWD_CHUNK;
                let i1 = (i0 + BWD_CHUNK).min(end);
                sc.clear();
                let mut px_at = PixelCursor::new(frags, i0);
                // The previous fragment's face and entry: runs of one face skip the map.
                let mut cur = (u32::MAX, 0usize);
                for i in i0..i1 {
                    px_at.advance(&frags.offsets, i);
                    let px = match points {
                        Some(p) => p[i],
                        None => px_at.ndc(),
                    };
                    let fi = frags.face[i];
                    if fi != cur.0 {
                        let (e, new) = sc.face_ix.index(fi);
                        if new {
                            let f = faces[fi as usize];
                            let v = f.map(|vi| clip[vi as usize].map(|x| x.to_f64c()));
                            sc.out.push((fi, [[0.0; 4]; 3]));
                            sc.fv.push(FaceVjp::new(&v));
                            sc.acc.push(RunVjp::default());
                        }
                        cur = (fi, e);
                    }
                    let e = cur.1;
                    let gb = grad_bary[i].map(|x| x.to_f64c());
                    if depth_grads {
                        let gd = grad_depth.map_or(0.0, |g| g[i].to_f64c());
                        let gw = grad_view_depth.map_or(0.0, |g| g[i].to_f64c());
                        let g = sc.fv[e].vjp(px, gb, gd, gw, s.perspective_correct);
                        let o = &mut sc.out[e].1;
                        for m in 0..3 {
                            for q in 0..4 {
                                o[m][q] += g[m][q];
                            }
                        }
                    } else {
                        sc.fv[e].accumulate(&mut sc.acc[e], px, gb, s.perspective_correct);
                    }
                }
                if !depth_grads {
                    for ((_, o), (fv, a)) in sc.out.iter_mut().zip(sc.fv.iter().zip(&sc.acc)) {
                        *o = fv.finish(a, s.perspective_correct);
                    }
                }
                std::mem::take(&mut sc.out)
            })
            .collect();
        // Fixed-order reduction: every vertex sums its contributions in chunk order
        // (parallel over vertex blocks, `scatter_face_corners`).
        scatter_face_corners(acc.as_flattened_mut(), 4, faces, || {
            sums.iter().flatten().map(|(fi, g)| (*fi, g.as_flattened()))
        });
        start = end;
    }
    Ok(acc.into_iter().map(|a| a.map(T::from_f64c)).collect())
}

/// Fragments per parallel chunk of [`rasterize_backward`].
const BWD_CHUNK: usize = 4096;

/// Per-thread scratch of [`rasterize_backward`]'s chunks: the faces met in the chunk (in order
/// of first touch) with their contribution, setup and factor sums, and the map from face index
/// to entry.
struct BwdScratch {
    face_ix: IndexMap,
    out: Vec<(u32, [[f64; 4]; 3])>,
    fv: Vec<FaceVjp>,
    acc: Vec<RunVjp>,
}

impl BwdScratch {
    fn new() -> Self {
        BwdScratch {
            face_ix: IndexMap::new(256),
            out: Vec::new(),
            fv: Vec::new(),
            acc: Vec::new(),
        }
    }

    fn clear(&mut self) {
        self.face_ix.clear();
        self.out.clear();
        self.fv.clear();
        self.acc.clear();
    }
}

#[inline]
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The per-face part of [`FaceVjp::vjp`]: the face's clip vertices, the cofactor columns
/// `c_i = v_{i+1} x v_{i+2}` over `(x, y, w)` and `det M`.
pub(crate) struct FaceVjp {
    v: [[f64; 4]; 3],
    c: [[f64; 3]; 3],
    det: f64,
    /// `1 / det`: the divisions by `det` of [`fragment_vjp`] are products with it.
    inv_det: f64,
}

/// The sum of [`FaceVjp::vjp`] without depth gradients over a run of fragments of one face,
/// factored. Each fragment's product is linear in the cofactors over `det`:
/// `dL/d(x, y, w)_m = (sum_i K_mi c_i) / det` with `K_mi = b_m (g . b - g_i)` when
/// barycentrics are perspective-correct, and `K_mi = -u_m g_i w_i` (plus `u_m g_m` on
/// `dL/dw_m`) in screen space. The run sums the 3x3 factors `K` (and `u_m g_i`), and
/// [`FaceVjp::finish`] multiplies by the cofactors once.
#[derive(Clone, Copy, Default)]
pub(crate) struct RunVjp {
    k: [[f64; 3]; 3],
}

/// The part of a [`FaceVjp`] that the per-fragment [`FaceVjp::accumulate`] reads (the cofactor
/// columns and `1 / det`), small enough to copy into locals for a run of fragments
/// ([`FaceVjp::run_setup`]).
#[derive(Clone, Copy)]
pub(crate) struct RunSetup {
    c: [[f64; 3]; 3],
    inv_det: f64,
}

impl RunSetup {
    /// The factor sums [`accumulate`](Self::accumulate) reaches with `persp = false` over a
    /// run of fragments, from their moments `t[j][i] = sum_frag ptilde_j dL/dbary_i`
    /// (`ptilde = (px, py, 1)`): the screen-space weights `u` are affine in `ptilde`, so
    /// `sum u_m dL/dbary_i = inv_det sum_j c[m][j] t[j][i]` (the same sum, added in
    /// another order).
    #[inline(always)]
    pub(crate) fn affine_sums(&self, t: &[[f64; 3]; 3]) -> RunVjp {
        let c = &self.c;
        RunVjp {
            k: [0, 1, 2].map(|m| {
                [0, 1, 2].map(|i| {
                    (c[m][0] * t[0][i] + c[m][1] * t[1][i] + c[m][2] * t[2][i]) * self.inv_det
                })
            }),
        }
    }

    /// Adds the factors of one fragment at NDC pixel `px` with `dL/dbary = gb` (no depth
    /// gradients) to the run's sum `acc` ([`RunVjp`]).
    #[inline(always)]
    pub(crate) fn accumulate(&self, acc: &mut RunVjp, px: [f64; 2], gb: [f64; 3], persp: bool) {
        let c = &self.c;
        let u = [0, 1, 2].map(|i| (c[i][0] * px[0] + c[i][1] * px[1] + c[i][2]) * self.inv_det);
        if persp {
            let w_frag = 1.0 / (u[0] + u[1] + u[2]);
            let b = u.map(|x| x * w_frag);
            let s = dot(gb, b);
            for m in 0..3 {
                for i in 0..3 {
                    acc.k[m][i] += b[m] * (s - gb[i]);
                }
            }
        } else {
            for m in 0..3 {
                for i in 0..3 {
                    acc.k[m][i] += u[m] * gb[i];
                }
            }
        }
    }
}

impl FaceVjp {
    /// The per-face setup from the clip coordinates of its three vertices.
    pub(crate) fn new(v: &[[f64; 4]; 3]) -> Self {
        let col = |i: usize| [v[i][0], v[i][1], v[i][3]];
        let c = [
            cross(col(1), col(2)),
            cross(col(2), col(0)),
            cross(col(0), col(1)),
        ];
        let det = dot(col(0), c[0]);
        FaceVjp {
            v: *v,
            c,
            det,
            inv_det: 1.0 / det,
        }
    }

    /// Whether the face has a usable inverse (`det M` finite, non-zero, not subnormal);
    /// a face without one gets no gradient.
    #[inline]
    pub(crate) fn invertible(&self) -> bool {
        self.det != 0.0 && self.det.is_finite() && self.inv_det.is_finite()
    }

    /// `dL/d(clip of the face's three vertices)` of one fragment at NDC pixel `px`.
    ///
    /// With `M = [v0 v1 v2]` over `(x, y, w)`, `u = M^-1 p`, `W = 1 / sum u` (view depth),
    /// `b = W u`, `Z = b . z`, `D = Z / W` (NDC depth). For `L(b, W, D)`:
    /// `dL/dM = b_m M^-T k` per column with `k = (g_b . b + g_W W) 1 - g_b` (after folding the
    /// depth gradient into `g_b += g_D z / W`, `g_W -= g_D D / W`), and `dL/dz_m = g_D b_m / W`.
    /// For screen-space barycentrics `l_i = u_i w_i`: `dL/dv_m -= u_m M^-T (g_l * w)`,
    /// `dL/dw_m += g_l,m u_m`.
    fn vjp(&self, px: [f64; 2], gb: [f64; 3], gd: f64, gw: f64, persp: bool) -> [[f64; 4]; 3] {
        fragment_vjp(
            &self.v,
            &self.c,
            self.det,
            self.inv_det,
            px,
            gb,
            gd,
            gw,
            persp,
        )
    }

    /// Adds the factors of one fragment at NDC pixel `px` with `dL/dbary = gb` (no depth
    /// gradients) to the run's sum `acc` ([`RunVjp`]): [`RunSetup::accumulate`].
    #[inline(always)]
    pub(crate) fn accumulate(&self, acc: &mut RunVjp, px: [f64; 2], gb: [f64; 3], persp: bool) {
        self.run_setup().accumulate(acc, px, gb, persp);
    }

    /// `sum_frag b_k g` over a run of fragments with screen-space barycentrics `b`, from the
    /// moments `m = (sum px g, sum py g, sum g)` of their values `g` at NDC pixels
    /// `(px, py)`: `b_k = w_k u_k` with `u = M^-1 (px, py, 1)` (`M u = ptilde` and its `w` row
    /// makes `sum w_k u_k = 1`), affine in the pixel.
    #[inline(always)]
    pub(crate) fn screen_bary_sums(&self, m: [f64; 3]) -> [f64; 3] {
        let c = &self.c;
        [0, 1, 2].map(|k| {
            self.v[k][3] * ((c[k][0] * m[0] + c[k][1] * m[1] + c[k][2] * m[2]) * self.inv_det)
        })
    }

    /// What [`FaceVjp::accumulate`] reads, as a small copy.
    #[inline(always)]
    pub(crate) fn run_setup(&self) -> RunSetup {
        RunSetup {
            c: self.c,
            inv_det: self.inv_det,
        }
    }

    /// The run's gradient `dL/d(clip)` of the face's three vertices from its factors `acc`.
    pub(crate) fn finish(&self, acc: &RunVjp, persp: bool) -> [[f64; 4]; 3] {
        let mut out = [[0.0; 4]; 3];
        if !self.invertible() {
            return out;
        }
        let w = [self.v[0][3], self.v[1][3], self.v[2][3]];
        for m in 0..3 {
            let k = if persp {
                acc.k[m]
            } else {
                [0, 1, 2].map(|i| -acc.k[m][i] * w[i])
            };
            let q = vec_mat_over(&k, &self.c, self.inv_det);
            out[m] = [q[0], q[1], 0.0, q[2]];
            if !persp {
                out[m][3] += acc.k[m][m];
            }
        }
        out
    }
}

/// `(v^T C) / det` (as a product with `inv_det = 1 / det`) for the cofactor matrix `C` of a
/// face's clip-space vertex matrix: the gradient of the edge-function coefficients from the
/// gradient `v` of the corners' weights.
#[inline(always)]
fn vec_mat_over(v: &[f64; 3], c: &[[f64; 3]; 3], inv_det: f64) -> [f64; 3] {
    let mut q = [0.0; 3];
    for i in 0..3 {
        for a in 0..3 {
            q[a] += v[i] * c[i][a];
        }
    }
    q.map(|x| x * inv_det)
}

/// The body of [`FaceVjp::vjp`].
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn fragment_vjp(
    v: &[[f64; 4]; 3],
    c: &[[f64; 3]; 3],
    det: f64,
    inv_det: f64,
    px: [f64; 2],
    gb: [f64; 3],
    gd: f64,
    gw: f64,
    persp: bool,
) -> [[f64; 4]; 3] {
    let mut out = [[0.0; 4]; 3];
    if det == 0.0 || !det.is_finite() || !inv_det.is_finite() {
        return out;
    }
    let p = [px[0], px[1], 1.0];
    let u = [
        dot(c[0], p) * inv_det,
        dot(c[1], p) * inv_det,
        dot(c[2], p) * inv_det,
    ];
    let w = [v[0][3], v[1][3], v[2][3]];
    {
        let w_frag = 1.0 / (u[0] + u[1] + u[2]);
        let b = u.map(|x| x * w_frag);
        let z = [v[0][2], v[1][2], v[2][2]];
        let mut g = if persp { gb } else { [0.0; 3] };
        let d = dot(b, z) / w_frag;
        for i in 0..3 {
            g[i] += gd * z[i] / w_frag;
        }
        let g_w = gw - gd * d / w_frag;
        let s = dot(g, b) + g_w * w_frag;
        let q = vec_mat_over(&[s - g[0], s - g[1], s - g[2]], c, inv_det);
        for m in 0..3 {
            out[m][0] = b[m] * q[0];
            out[m][1] = b[m] * q[1];
            out[m][3] = b[m] * q[2];
            out[m][2] = gd * b[m] / w_frag;
        }
    }
    if !persp {
        let ql = vec_mat_over(&[gb[0] * w[0], gb[1] * w[1], gb[2] * w[2]], c, inv_det);
        for m in 0..3 {
            out[m][0] -= u[m] * ql[0];
            out[m][1] -= u[m] * ql[1];
            out[m][3] -= u[m] * ql[2] - gb[m] * u[m];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in `[-1, 1)` (a 64-bit LCG).
    fn values(seed: u64) -> impl FnMut() -> f64 {
        let mut x = seed;
        move || {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (x >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    /// [`RowSpans::rows4_avx2`] gives [`RowSpans::row`]'s span on every row, also for bounds
    /// that are infinite, NaN, far outside the tile or cross it (empty spans).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_row_span_matches_scalar() {
        if !use_avx2() {
            return;
        }
        let mut r = values(11);
        let pick = |r: &mut dyn FnMut() -> f64| -> f64 {
            let u = r();
            match ((u + 1.0) * 8.0) as u32 {
                0 => f64::NAN,
                1 => f64::INFINITY,
                2 => f64::NEG_INFINITY,
                3 => 1e300 * r(),
                4 => -0.0,
                _ => 40.0 * r() + 16.0,
            }
        };
        for _ in 0..2000 {
            let mut arr = || [0; 3].map(|_| pick(&mut r));
            let (lal, ral) = (arr(), arr());
            let mut small = || [0; 3].map(|_| if r() > 0.0 { 3.0 * r() } else { 0.0 });
            let (lbe, rbe) = (small(), small());
            let c0 = ((r() + 1.0) * 16.0).floor();
            let c1 = c0 + ((r() + 1.0) * 16.0).floor();
            let spans = RowSpans {
                lal,
                lbe,
                ral,
                rbe,
                rows: 0..32,
                c0,
                c1,
            };
            // SAFETY: the CPU has AVX2 (checked above).
            let sv = unsafe { SpanVecs::new(&spans) };
            for row in spans.rows.clone() {
                let q = row & !3;
                // SAFETY: as above.
                let (cl, cr, some) = unsafe { spans.rows4_avx2(&sv, q) };
                let l = (row - q) as usize;
                let v = (some & (1 << l) != 0).then(|| (cl[l] as u32, cr[l] as u32));
                assert_eq!(
                    v,
                    spans.row(row),
                    "{lal:?} {lbe:?} {ral:?} {rbe:?} {c0} {c1} row {row}"
                );
            }
        }
    }

    /// The factored run sum of [`FaceVjp::accumulate`] / [`FaceVjp::finish`] equals the sum of
    /// the per-fragment products [`FaceVjp::vjp`] without depth gradients, for both
    /// interpolation modes.
    #[test]
    fn factored_run_sum_matches_per_fragment_products() {
        let mut r = values(7);
        for trial in 0..50 {
            let persp = trial % 2 == 0;
            // A face in front of the camera (w in [1, 3]) whose screen triangle contains the
            // NDC points drawn below only roughly: the identity is algebraic.
            let v: [[f64; 4]; 3] = [[-0.8, -0.7], [0.9, -0.6], [0.1, 0.8]].map(|xy| {
                let w = 2.0 + r();
                [(xy[0] + 0.1 * r()) * w, (xy[1] + 0.1 * r()) * w, r(), w]
            });
            let fv = FaceVjp::new(&v);
            let mut acc = RunVjp::default();
            let mut want = [[0.0; 4]; 3];
            for _ in 0..(1 + trial % 9) {
                let px = [0.3 * r(), 0.3 * r()];
                let gb = [r(), r(), r()];
                fv.accumulate(&mut acc, px, gb, persp);
                let g = fv.vjp(px, gb, 0.0, 0.0, persp);
                for m in 0..3 {
                    for q in 0..4 {
                        want[m][q] += g[m][q];
                    }
                }
            }
            let got = fv.finish(&acc, persp);
            let scale = want.iter().flatten().fold(0.0f64, |a, x| a.max(x.abs()));
            for m in 0..3 {
                for q in 0..4 {
                    assert!(
                        (got[m][q] - want[m][q]).abs() <= 1e-12 * scale.max(1.0),
                        "trial {trial} persp {persp}: [{m}][{q}] {} vs {}",
                        got[m][q],
                        want[m][q]
                    );
                }
            }
        }
    }

    /// A face without a usable inverse (zero determinant) gets no gradient from either form.
    #[test]
    fn singular_face_gets_no_gradient() {
        let v = [
            [0.0, 0.0, 0.0, 1.0],
            [1.0, 1.0, 0.0, 1.0],
            [2.0, 2.0, 0.0, 1.0],
        ];
        let fv = FaceVjp::new(&v);
        let mut acc = RunVjp::default();
        fv.accumulate(&mut acc, [0.1, 0.2], [1.0, 2.0, 3.0], true);
        assert_eq!(fv.finish(&acc, true), [[0.0; 4]; 3]);
        assert_eq!(
            fv.vjp([0.1, 0.2], [1.0, 2.0, 3.0], 1.0, 1.0, true),
            [[0.0; 4]; 3]
        );
    }
}
