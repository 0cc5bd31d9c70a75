//! Packed fragments: a CSR over pixels holding, for each covered pixel, its nearest fragments.

use std::ops::Range;

use autodiff::Real;
use rayon::prelude::*;

use super::bin::{Bins, FaceRec};
use super::clip::Rect;
use super::edge::{sat, Setup};
use super::hard::Scratch;
use super::{RasterError, RasterSettings, TILE_SIZE};

/// Fragments of a rasterized image, packed: only covered pixels hold fragments.
///
/// The fragments of pixel `p = row * width + col` are `offsets[p]..offsets[p + 1]`, nearest
/// first (ties: lower face index first); every per-fragment array has `len()` entries.
#[derive(Clone, Debug, PartialEq)]
pub struct Fragments<T> {
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Most fragments a pixel may hold (`faces_per_pixel`).
    pub k: usize,
    /// `height * width + 1` offsets into the per-fragment arrays.
    pub offsets: Vec<u32>,
    /// Face index of each fragment.
    pub face: Vec<u32>,
    /// Barycentrics with respect to the original (unclipped) triangle: perspective-correct, or
    /// affine in screen space when `perspective_correct` is off.
    pub bary: Vec<[T; 3]>,
    /// NDC depth `z_clip / w_clip` at the fragment, in `[-1, 1]`; smaller is nearer.
    pub depth: Vec<T>,
    /// Interpolated `w_clip` (the view-space depth for a perspective camera).
    pub view_depth: Vec<T>,
    /// Derivative of `bary` per pixel step to the right (`col + 1`); empty when rasterized
    /// without [`RasterSettings::barycentric_derivatives`] ([`Fragments::has_derivatives`]).
    pub dbary_dx: Vec<[T; 3]>,
    /// Derivative of `bary` per pixel step down (`row + 1`); empty like `dbary_dx`.
    pub dbary_dy: Vec<[T; 3]>,
}

/// One fragment, as returned by [`Fragments::get`] and [`Fragments::iter_pixel`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fragment<T> {
    /// Index into the per-fragment arrays.
    pub index: usize,
    /// Face index.
    pub face: u32,
    /// Barycentrics of the face's vertices.
    pub bary: [T; 3],
    /// NDC depth.
    pub depth: T,
    /// Interpolated `w_clip`.
    pub view_depth: T,
    /// `d bary / d col`, if the fragments carry derivatives.
    pub dbary_dx: Option<[T; 3]>,
    /// `d bary / d row`, if the fragments carry derivatives.
    pub dbary_dy: Option<[T; 3]>,
}

/// Runs `frag(i, p, out)` for every fragment `i` of pixel `p`, in parallel over fixed chunks
/// of fragments (a pixel search per chunk, then a walk), each writing `per` values of the
/// returned `[N, per]` buffer.
pub(crate) fn per_fragment<T: Real, F>(f: &Fragments<T>, per: usize, frag: F) -> Vec<f64>
where
    F: Fn(usize, usize, &mut [f64]) + Sync,
{
    const CHUNK: usize = 2048;
    let mut out = vec![0.0; f.len() * per];
    out.par_chunks_mut(CHUNK * per)
        .enumerate()
        .for_each(|(blk, o)| {
            let i0 = blk * CHUNK;
            let mut p = f.pixel_of(i0);
            for (j, v) in o.chunks_mut(per).enumerate() {
                let i = i0 + j;
                while f.offsets[p + 1] as usize <= i {
                    p += 1;
                }
                frag(i, p, v);
            }
        });
    out
}

/// Walks the pixels of a run of fragments in order: the pixel `p` of the current fragment,
/// its row and column, and its centre in NDC (`x = (col + 0.5) sx - 1`, `y = 1 - (row + 0.5)
/// sy`, the conventions' pixel centres), advancing through `offsets` without divisions.
pub(crate) struct PixelCursor {
    pub p: usize,
    pub col: usize,
    row: usize,
    width: usize,
    sx: f64,
    sy: f64,
    py: f64,
}

impl PixelCursor {
    /// A cursor on the pixel of fragment `i`.
    pub(crate) fn new<T: Real>(f: &Fragments<T>, i: usize) -> Self {
        let p = f.pixel_of(i);
        let (row, col) = (p / f.width, p % f.width);
        let sy = 2.0 / f.height as f64;
        PixelCursor {
            p,
            col,
            row,
            width: f.width,
            sx: 2.0 / f.width as f64,
            sy,
            py: 1.0 - (row as f64 + 0.5) * sy,
        }
    }

    /// Moves to the pixel of fragment `i` (at or after the current one).
    #[inline(always)]
    pub(crate) fn advance(&mut self, offsets: &[u32], i: usize) {
        while offsets[self.p + 1] as usize <= i {
            self.p += 1;
            self.col += 1;
            if self.col == self.width {
                self.col = 0;
                self.row += 1;
                self.py = 1.0 - (self.row as f64 + 0.5) * self.sy;
            }
        }
    }

    /// The current pixel's centre in NDC.
    #[inline(always)]
    pub(crate) fn ndc(&self) -> [f64; 2] {
        // Through `i64` (the same value: columns are far below 2^63), one signed conversion
        // instead of the longer unsigned one.
        [(self.col as i64 as f64 + 0.5) * self.sx - 1.0, self.py]
    }
}

impl<T: Real> Fragments<T> {
    /// An image with no fragments.
    pub fn empty(width: usize, height: usize, k: usize) -> Self {
        Self {
            width,
            height,
            k,
            offsets: vec![0; width * height + 1],
            face: Vec::new(),
            bary: Vec::new(),
            depth: Vec::new(),
            view_depth: Vec::new(),
            dbary_dx: Vec::new(),
            dbary_dy: Vec::new(),
        }
    }

    /// Number of pixels, `width * height`.
    pub fn num_pixels(&self) -> usize {
        self.width * self.height
    }

    /// Total number of fragments.
    pub fn len(&self) -> usize {
        self.face.len()
    }

    /// No fragment at all.
    pub fn is_empty(&self) -> bool {
        self.face.is_empty()
    }

    /// Pixel index of `(row, col)`.
    pub fn pixel_index(&self, row: usize, col: usize) -> usize {
        row * self.width + col
    }

    /// `(row, col)` of pixel `p`.
    pub fn pixel_coords(&self, p: usize) -> (usize, usize) {
        (p / self.width, p % self.width)
    }

    /// Fragment indices of pixel `p`, nearest first.
    pub fn pixel_range(&self, p: usize) -> Range<usize> {
        self.offsets[p] as usize..self.offsets[p + 1] as usize
    }

    /// Number of fragments of pixel `p` (at most `k`).
    pub fn count(&self, p: usize) -> usize {
        (self.offsets[p + 1] - self.offsets[p]) as usize
    }

    /// Number of pixels with at least one fragment.
    pub fn covered_pixels(&self) -> usize {
        self.offsets.windows(2).filter(|w| w[1] > w[0]).count()
    }

    /// Fragment `i`.
    pub fn get(&self, i: usize) -> Fragment<T> {
        Fragment {
            index: i,
            face: self.face[i],
            bary: self.bary[i],
            depth: self.depth[i],
            view_depth: self.view_depth[i],
            dbary_dx: self.dbary_dx.get(i).copied(),
            dbary_dy: self.dbary_dy.get(i).copied(),
        }
    }

    /// Whether `dbary_dx` and `dbary_dy` are present (one entry per fragment), i.e. the
    /// fragments were rasterized with [`RasterSettings::barycentric_derivatives`].
    pub fn has_derivatives(&self) -> bool {
        self.dbary_dx.len() == self.len() && self.dbary_dy.len() == self.len()
    }

    /// Fragments of pixel `p`, nearest first.
    pub fn iter_pixel(&self, p: usize) -> impl ExactSizeIterator<Item = Fragment<T>> + '_ {
        self.pixel_range(p).map(move |i| self.get(i))
    }

    /// Nearest fragment of pixel `p`, if any.
    pub fn nearest(&self, p: usize) -> Option<Fragment<T>> {
        self.iter_pixel(p).next()
    }

    /// Pixel index of every fragment (the inverse of the CSR), for gathers and scatters.
    pub fn fragment_pixels(&self) -> Vec<u32> {
        let mut out = vec![0u32; self.len()];
        for p in 0..self.num_pixels() {
            out[self.pixel_range(p)].fill(p as u32);
        }
        out
    }

    /// Calls `f(pixel, fragment range)` for every covered pixel in pixel order.
    pub fn for_each_covered(&self, mut f: impl FnMut(usize, Range<usize>)) {
        for p in 0..self.num_pixels() {
            let r = self.pixel_range(p);
            if !r.is_empty() {
                f(p, r);
            }
        }
    }

    /// Pixel of fragment `i` (binary search in `offsets`).
    pub fn pixel_of(&self, i: usize) -> usize {
        self.offsets.partition_point(|&o| o as usize <= i) - 1
    }

    /// Checks the internal consistency of the layout (lengths, monotone offsets, `<= k` per
    /// pixel); the derivative arrays are either both present or both empty.
    pub fn validate(&self) -> Result<(), RasterError> {
        let bad = |m: String| Err(RasterError::FragmentsMismatch(m));
        let n = self.len();
        if self.offsets.len() != self.num_pixels() + 1 {
            return bad(format!(
                "offsets has length {}, expected {}",
                self.offsets.len(),
                self.num_pixels() + 1
            ));
        }
        if self.offsets[0] != 0 || *self.offsets.last().unwrap() as usize != n {
            return bad(format!("offsets must run from 0 to {n}"));
        }
        let o = &self.offsets;
        if let Some(p) = super::par_first_index(o.len() - 1, |p| {
            o[p + 1] < o[p] || (o[p + 1] - o[p]) as usize > self.k
        }) {
            return bad(format!("pixel {p} has a bad fragment range"));
        }
        let derivs = if self.dbary_dx.is_empty() && self.dbary_dy.is_empty() {
            0
        } else {
            n
        };
        for (what, len, want) in [
            ("bary", self.bary.len(), n),
            ("depth", self.depth.len(), n),
            ("view_depth", self.view_depth.len(), n),
            ("dbary_dx", self.dbary_dx.len(), derivs),
            ("dbary_dy", self.dbary_dy.len(), derivs),
        ] {
            if len != want {
                return bad(format!("{what} has length {len}, expected {want}"));
            }
        }
        Ok(())
    }
}

/// The fragments of one tile, packed in tile-local row-major pixel order (nearest first within a
/// pixel): each fragment's face record id ([`Bins::rec`]) and NDC depth.
pub(crate) struct TileFrags {
    pub idx: Vec<u32>,
    pub depth: Vec<f64>,
    /// Fragment count per local pixel (`local_row * TILE_SIZE + local_col`); empty if none.
    pub counts: Vec<u16>,
    /// `row_start[lr]..row_start[lr + 1]`: the fragments of local row `lr`.
    pub row_start: [u32; TILE_SIZE + 1],
}

impl TileFrags {
    pub fn empty() -> Self {
        Self {
            idx: Vec::new(),
            depth: Vec::new(),
            counts: Vec::new(),
            row_start: [0; TILE_SIZE + 1],
        }
    }

    /// Number of fragments in local row `lr`.
    #[inline]
    fn row_len(&self, lr: usize) -> usize {
        (self.row_start[lr + 1] - self.row_start[lr]) as usize
    }

    /// Packs the dense K-buffer of the tile `rect` (`k` slots per local pixel of record ids,
    /// `+inf` depth when empty; see [`Scratch`]) and resets it: only the tested column spans
    /// of each row are read and refilled with `+inf`, and the spans and counts are cleared.
    pub fn pack(sc: &mut Scratch, rect: &Rect, k: usize) -> Self {
        let rows = (rect.r1 - rect.r0) as usize + 1;
        let mut out = Self::empty();
        let total = sc.filled[..rows].iter().map(|&n| n as usize).sum::<usize>();
        if total > 0 {
            out.idx.reserve_exact(total);
            out.depth.reserve_exact(total);
            out.counts = vec![0; TILE_SIZE * TILE_SIZE];
        }
        for lr in 0..rows {
            let (c0, c1) = sc.span[lr];
            if sc.filled[lr] > 0 {
                let p = lr * TILE_SIZE;
                let cols = p + c0 as usize..p + c1 as usize;
                let slots = cols.start * k..cols.end * k;
                let (dk, ik) = (&sc.depth[slots.clone()], &sc.idx[slots]);
                if k == 1 {
                    // Compaction into the reserved capacity: every pixel writes the next slot,
                    // which only a filled slot (depth <= 1) keeps.
                    let (mut n, cap) = (out.idx.len(), out.idx.capacity());
                    let (idx, depth) = (
                        &mut out.idx.spare_capacity_mut()[..cap - n],
                        &mut out.depth.spare_capacity_mut()[..cap - n],
                    );
                    let base = n;
                    for ((cnt, &d), &i) in out.counts[cols].iter_mut().zip(dk).zip(ik) {
                        let filled = d <= 1.0;
                        if n - base < idx.len() {
                            idx[n - base].write(i);
                            depth[n - base].write(d);
                        }
                        *cnt = filled as u16;
                        n += filled as usize;
                    }
                    // SAFETY: the first `n` slots of both vectors are initialised: the
                    // earlier ones before, `base..n` above (each kept slot was written before
                    // `n` moved past it, and `n <= total`, the reserved capacity).
                    unsafe {
                        out.idx.set_len(n);
                        out.depth.set_len(n);
                    }
                } else {
                    for ((cnt, dk), ik) in out.counts[cols]
                        .iter_mut()
                        .zip(dk.chunks_exact(k))
                        .zip(ik.chunks_exact(k))
                    {
                        for (&d, &i) in dk.iter().zip(ik) {
                            if d > 1.0 {
                                break;
                            }
                            out.idx.push(i);
                            out.depth.push(d);
                            *cnt += 1;
                        }
                    }
                }
            }
            sc.reset_row(lr);
            out.row_start[lr + 1] = out.idx.len() as u32;
        }
        debug_assert_eq!(out.idx.len(), total);
        for lr in rows..TILE_SIZE {
            out.row_start[lr + 1] = out.row_start[rows];
        }
        out
    }
}

/// Raw pointers to the (uninitialised) output arrays, shared by the tiles of the assembly,
/// which write disjoint elements.
struct OutPtrs<T> {
    offsets: *mut u32,
    face: *mut u32,
    bary: *mut [T; 3],
    depth: *mut T,
    view_depth: *mut T,
    dx: *mut [T; 3],
    dy: *mut [T; 3],
}

impl<T> OutPtrs<T> {
    /// Writes the offset of pixel `p`.
    ///
    /// # Safety
    /// `p <= width * height`, and no other task writes or reads it.
    #[inline(always)]
    unsafe fn offset(&self, p: usize, v: u32) {
        unsafe { self.offsets.add(p).write(v) }
    }

    /// Writes fragment slot `i` (all but the derivatives).
    ///
    /// # Safety
    /// `i < total`, and no other task writes or reads it.
    #[inline(always)]
    unsafe fn fragment(&self, i: usize, face: u32, bary: [T; 3], depth: T, view_depth: T) {
        unsafe {
            self.face.add(i).write(face);
            self.bary.add(i).write(bary);
            self.depth.add(i).write(depth);
            self.view_depth.add(i).write(view_depth);
        }
    }

    /// Writes the derivatives of fragment slot `i`.
    ///
    /// # Safety
    /// As [`OutPtrs::fragment`], and the derivative arrays were allocated (with room for `i`).
    #[inline(always)]
    unsafe fn derivatives(&self, i: usize, dx: [T; 3], dy: [T; 3]) {
        unsafe {
            self.dx.add(i).write(dx);
            self.dy.add(i).write(dy);
        }
    }
}

// SAFETY: the pointers are only used to write elements that no other task reads or writes
// (see `assemble`), and `T` is `Send`.
unsafe impl<T: Send> Sync for OutPtrs<T> {}
unsafe impl<T: Send> Send for OutPtrs<T> {}

/// Longest run of [`write_run`]: a tile row's pixels.
const RUN: usize = TILE_SIZE;
// `write_run_avx2` loads whole groups of four columns.
const _: () = assert!(RUN.is_multiple_of(4));

/// Per-run constants of a face record's fragment values ([`RunConsts::values`]).
pub(crate) struct RunConsts {
    /// Row part of the edge functions ([`Setup::row`]).
    pub t: [f64; 3],
    /// Perspective-correct mode: `sum a_i`, `sum b_i`.
    sa: f64,
    sb: f64,
    /// Screen-space mode: `w_i / det`, and the constant derivatives `a_i w_i / det`,
    /// `b_i w_i / det`.
    pub sw: [f64; 3],
    ax: [f64; 3],
    by: [f64; 3],
}

impl RunConsts {
    /// The constants of mode `PERSP` for row `row` of setup `st` (runs are short for small
    /// faces: only the mode in use is computed).
    #[inline(always)]
    pub(crate) fn new<const PERSP: bool>(st: &Setup, row: f64) -> Self {
        let mut k = RunConsts {
            t: st.row(row),
            sa: 0.0,
            sb: 0.0,
            sw: [0.0; 3],
            ax: [0.0; 3],
            by: [0.0; 3],
        };
        if PERSP {
            (k.sa, k.sb) = (st.a[0] + st.a[1] + st.a[2], st.b[0] + st.b[1] + st.b[2]);
        } else {
            k.sw = [
                st.w[0] * st.inv_det,
                st.w[1] * st.inv_det,
                st.w[2] * st.inv_det,
            ];
            k.ax = [st.a[0] * k.sw[0], st.a[1] * k.sw[1], st.a[2] * k.sw[2]];
            k.by = [st.b[0] * k.sw[0], st.b[1] * k.sw[1], st.b[2] * k.sw[2]];
        }
        k
    }

    /// Barycentrics, view depth and barycentric derivatives of the fragment at column `col`.
    ///
    /// With `e_i = a_i col + (b_i row + c_i)` ([`Setup::eval`]), `inv = 1 / sum e`:
    /// perspective correct `b_i = e_i inv`, `d b_i / dcol = (a_i - b_i sum a) inv` (`b` for
    /// rows); screen-space `l_i = e_i w_i / det` with the constant derivatives `a_i w_i / det`,
    /// `b_i w_i / det`; view depth `sum_i (e_i inv) w_i` either way. This exact sequence of
    /// operations defines the values ([`write_run_avx2`] repeats it lane-wise).
    #[inline(always)]
    #[allow(clippy::type_complexity)]
    pub(crate) fn values<const PERSP: bool>(
        &self,
        st: &Setup,
        col: f64,
    ) -> ([f64; 3], f64, [f64; 3], [f64; 3]) {
        let e = st.eval(col, &self.t);
        let inv = 1.0 / (e[0] + e[1] + e[2]);
        let bp = [e[0] * inv, e[1] * inv, e[2] * inv];
        let vd = bp[0] * st.w[0] + bp[1] * st.w[1] + bp[2] * st.w[2];
        if PERSP {
            // d(e_i / sum e) = (de_i - b_i d(sum e)) / sum e, de_i/dcol = a_i, de_i/drow = b_i.
            let (sa, sb) = (self.sa, self.sb);
            (
                bp,
                vd,
                [
                    (st.a[0] - bp[0] * sa) * inv,
                    (st.a[1] - bp[1] * sa) * inv,
                    (st.a[2] - bp[2] * sa) * inv,
                ],
                [
                    (st.b[0] - bp[0] * sb) * inv,
                    (st.b[1] - bp[1] * sb) * inv,
                    (st.b[2] - bp[2] * sb) * inv,
                ],
            )
        } else {
            // Screen-space barycentrics lambda_i = e_i w_i / det are affine in the pixel.
            let sw = self.sw;
            (
                [e[0] * sw[0], e[1] * sw[1], e[2] * sw[2]],
                vd,
                self.ax,
                self.by,
            )
        }
    }
}

/// Whether every value that a fragment stores (its barycentrics, view depth and, with
/// `DERIV`, derivatives) lies within `T`'s finite range `m`, from one test on the sum of their
/// magnitudes (each at most the rounded sum, which is NaN or infinite when any value is).
/// When it fails, also for the rare in-range sets whose sum exceeds the range, the values are
/// saturated, which gives the same values wherever the plain conversion is finite.
#[inline(always)]
fn in_range<const DERIV: bool>(
    m: f64,
    bary: &[f64; 3],
    vd: f64,
    dx: &[f64; 3],
    dy: &[f64; 3],
) -> bool {
    let mut mag = vd.abs() + (bary[0].abs() + bary[1].abs() + bary[2].abs());
    if DERIV {
        mag +=
            (dx[0].abs() + dx[1].abs() + dx[2].abs()) + (dy[0].abs() + dy[1].abs() + dy[2].abs());
    }
    mag <= m
}

/// Writes fragment slot `i` of face `face` from `f64` values (NDC depth `d` in `[-1, 1]`),
/// converted to `T`, saturated unless `in_range` ([`in_range`]); the derivatives only with
/// `DERIV`.
///
/// # Safety
/// As [`OutPtrs::fragment`]; with `DERIV` the derivative arrays have room for slot `i`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn store<T: Real, const DERIV: bool>(
    out: &OutPtrs<T>,
    i: usize,
    face: u32,
    bary: [f64; 3],
    d: f64,
    vd: f64,
    dx: [f64; 3],
    dy: [f64; 3],
    in_range: bool,
) {
    let conv = |x: f64| if in_range { T::from_f64c(x) } else { sat(x) };
    // SAFETY: the caller's contract.
    unsafe {
        out.fragment(i, face, bary.map(conv), T::from_f64c(d), conv(vd));
        if DERIV {
            out.derivatives(i, dx.map(conv), dy.map(conv));
        }
    }
}

/// Computes and writes the values of a run of fragments of one face record (output slots
/// `pos..pos + cols.len()`, at columns `cols` of row `row`, with NDC depths `depth`):
/// barycentrics, view depth and (with `DERIV`) barycentric derivatives from the record's edge
/// functions ([`RunConsts::values`]). The row part of `e` and the per-face constants are
/// computed once per run. Every fragment must have `sum e > 0`. Values beyond the range of `T`
/// (only for slivers at the limits of `f64`) are saturated, NaN to zero, so they are always
/// finite.
///
/// # Safety
/// `cols.len() == depth.len()`, and the slots `pos..pos + cols.len()` lie below the
/// output's capacity and are written by no other task.
#[inline(always)]
unsafe fn write_run<T: Real, const PERSP: bool, const DERIV: bool>(
    rec: &FaceRec,
    cols: &[f64],
    row: f64,
    depth: &[f64],
    out: &OutPtrs<T>,
    pos: usize,
) {
    let st: &Setup = &rec.st;
    let k = RunConsts::new::<PERSP>(st, row);
    let m = T::max_value().to_f64c();
    for (j, (&col, &d)) in cols.iter().zip(depth).enumerate() {
        let (bary, vd, dx, dy) = k.values::<PERSP>(st, col);
        let ok = in_range::<DERIV>(m, &bary, vd, &dx, &dy);
        // SAFETY: slot `pos + j` is one of this run's (the caller's contract).
        unsafe { store::<T, DERIV>(out, pos + j, rec.face, bary, d, vd, dx, dy, ok) };
    }
}

/// [`write_run`] with AVX2, four fragments at a time, for the first `n` columns of `cols`:
/// each lane repeats [`RunConsts::values`] and [`in_range`] with the same IEEE operations in
/// the same order (no fused multiply-adds), so the values are bit-identical.
///
/// # Safety
/// As [`write_run`] for `cols[..n]`, and the CPU supports AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn write_run_avx2<T: Real, const PERSP: bool, const DERIV: bool>(
    rec: &FaceRec,
    cols: &[f64; RUN],
    n: usize,
    row: f64,
    depth: &[f64],
    out: &OutPtrs<T>,
    pos: usize,
) {
    use std::arch::x86_64::*;
    const L: usize = 4;
    let st: &Setup = &rec.st;
    let k = RunConsts::new::<PERSP>(st, row);
    let m = T::max_value().to_f64c();
    let v = |x: f64| _mm256_set1_pd(x);
    let (a, b, t, w) = (st.a.map(v), st.b.map(v), k.t.map(v), st.w.map(v));
    let (sa, sb, sw) = (v(k.sa), v(k.sb), k.sw.map(v));
    let one = v(1.0);
    let abs_mask = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
    let abs = |x: __m256d| _mm256_and_pd(x, abs_mask);
    let mv = v(m);
    // A run's columns are consecutive (a triangle's pixels in a row form an interval): the
    // lanes' columns are then made in registers. The caller has just stored `cols` one by
    // one, and a vector load of those pending narrower stores stalls store-to-load
    // forwarding (a fifth of this function's time); other runs load them.
    let contiguous = cols[n - 1] - cols[0] == (n - 1) as f64;
    let col0 = _mm256_add_pd(v(cols[0]), _mm256_setr_pd(0.0, 1.0, 2.0, 3.0));
    let mut j = 0;
    while j < n {
        let lanes = (n - j).min(L);
        // Lanes past the run hold columns computed and never stored.
        let col = if contiguous {
            _mm256_add_pd(col0, _mm256_set1_pd(j as f64))
        } else {
            // SAFETY: `j + 4 <= RUN` (`j < n <= RUN`, both multiples of 4).
            unsafe { _mm256_loadu_pd(cols.as_ptr().add(j)) }
        };
        let e = [0, 1, 2].map(|i| _mm256_add_pd(_mm256_mul_pd(a[i], col), t[i]));
        let inv = _mm256_div_pd(one, _mm256_add_pd(_mm256_add_pd(e[0], e[1]), e[2]));
        let bp = e.map(|ei| _mm256_mul_pd(ei, inv));
        let vd = _mm256_add_pd(
            _mm256_add_pd(_mm256_mul_pd(bp[0], w[0]), _mm256_mul_pd(bp[1], w[1])),
            _mm256_mul_pd(bp[2], w[2]),
        );
        let (bary, dx, dy) = if PERSP {
            (
                bp,
                [0, 1, 2]
                    .map(|i| _mm256_mul_pd(_mm256_sub_pd(a[i], _mm256_mul_pd(bp[i], sa)), inv)),
                [0, 1, 2]
                    .map(|i| _mm256_mul_pd(_mm256_sub_pd(b[i], _mm256_mul_pd(bp[i], sb)), inv)),
            )
        } else {
            (
                [0, 1, 2].map(|i| _mm256_mul_pd(e[i], sw[i])),
                k.ax.map(v),
                k.by.map(v),
            )
        };
        let sum3 = |x: [__m256d; 3]| _mm256_add_pd(_mm256_add_pd(abs(x[0]), abs(x[1])), abs(x[2]));
        let mut mag = _mm256_add_pd(abs(vd), sum3(bary));
        if DERIV {
            mag = _mm256_add_pd(mag, _mm256_add_pd(sum3(dx), sum3(dy)));
        }
        let ok = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(mag, mv));
        if std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>() && ok == 0b1111 {
            // f32 output, every lane in range: rounded four at a time (the same
            // round-to-nearest as `from_f64c`) and written from registers. Each slot's three
            // barycentrics (and derivatives) go out as one 16-byte store whose fourth value
            // falls on the next slot and is overwritten there; the last lane stores exactly
            // 12 bytes.
            let i = pos + j;
            let live = _mm256_cmpgt_epi64(
                _mm256_set1_epi64x(lanes as i64),
                _mm256_setr_epi64x(0, 1, 2, 3),
            );
            // SAFETY: `depth` holds the run's `n` depths, lanes `..lanes` of which are read
            // (masked-off lanes are not accessed).
            let d = unsafe { _mm256_maskload_pd(depth.as_ptr().add(j), live) };
            // Rows `[x0_l, x1_l, x2_l, pad_l]` of four lanes, written as `[f32; 3]` slots.
            let rows3 = |x: [__m256d; 3], pad: __m128, dst: *mut f32| {
                let (mut r0, mut r1, mut r2, mut r3) = (
                    _mm256_cvtpd_ps(x[0]),
                    _mm256_cvtpd_ps(x[1]),
                    _mm256_cvtpd_ps(x[2]),
                    pad,
                );
                _MM_TRANSPOSE4_PS(&mut r0, &mut r1, &mut r2, &mut r3);
                let rows = [r0, r1, r2, r3];
                for (l, &r) in rows.iter().enumerate().take(lanes) {
                    // SAFETY: slot `i + l` is the caller's; a 16-byte store reaches into slot
                    // `i + l + 1`, also the caller's, which is written after it.
                    unsafe {
                        let p = dst.add(3 * (i + l));
                        if l + 1 < lanes {
                            _mm_storeu_ps(p, r);
                        } else {
                            let lo = _mm_cvtsi128_si64(_mm_castps_si128(r));
                            p.cast::<i64>().write_unaligned(lo);
                            _mm_store_ss(p.add(2), _mm_movehl_ps(r, r));
                        }
                    }
                }
            };
            let vd32 = _mm256_cvtpd_ps(vd);
            rows3(bary, vd32, out.bary.cast());
            // Lanes `..lanes` of depth, view depth and face id, by masked stores.
            let mask = _mm_cmpgt_epi32(_mm_set1_epi32(lanes as i32), _mm_setr_epi32(0, 1, 2, 3));
            // SAFETY: slots `i..i + lanes` are the caller's; `T` is `f32`; masked-off lanes are
            // neither read nor written.
            unsafe {
                _mm_maskstore_ps(out.depth.cast::<f32>().add(i), mask, _mm256_cvtpd_ps(d));
                _mm_maskstore_ps(out.view_depth.cast::<f32>().add(i), mask, vd32);
                _mm_maskstore_epi32(
                    out.face.add(i).cast(),
                    mask,
                    _mm_set1_epi32(rec.face as i32),
                );
            }
            if DERIV {
                let z = _mm_setzero_ps();
                rows3(dx, z, out.dx.cast());
                rows3(dy, z, out.dy.cast());
            }
            j += L;
            continue;
        }
        let spill = |x: __m256d| {
            let mut r = [0.0; L];
            // SAFETY: `r` holds four f64.
            unsafe { _mm256_storeu_pd(r.as_mut_ptr(), x) };
            r
        };
        let (bary, vd) = (bary.map(spill), spill(vd));
        let (dx, dy) = if DERIV {
            (dx.map(spill), dy.map(spill))
        } else {
            ([[0.0; L]; 3], [[0.0; L]; 3])
        };
        let face = rec.face;
        let pick = |x: &[[f64; L]; 3], l: usize| [x[0][l], x[1][l], x[2][l]];
        for l in 0..lanes {
            let (b, d, x, y) = (pick(&bary, l), depth[j + l], pick(&dx, l), pick(&dy, l));
            let ok = ok & (1 << l) != 0;
            // SAFETY: slot `pos + j + l` is one of this run's (the caller's contract).
            unsafe { store::<T, DERIV>(out, pos + j + l, face, b, d, vd[l], x, y, ok) };
        }
        j += L;
    }
}

/// [`write_run`] (or [`write_run_avx2`] when `avx2`) for the mode `persp` / `derivs`, on
/// the first `n` columns of `cols`.
///
/// # Safety
/// As [`write_run`] for `cols[..n]`; `avx2` only when the CPU supports AVX2; with `derivs` the derivative
/// arrays have room for the run's slots.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
unsafe fn write_run_dispatch<T: Real>(
    avx2: bool,
    persp: bool,
    derivs: bool,
    rec: &FaceRec,
    cols: &[f64; RUN],
    n: usize,
    row: f64,
    depth: &[f64],
    out: &OutPtrs<T>,
    pos: usize,
) {
    macro_rules! go {
        ($p:literal, $d:literal) => {{
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the caller's contract.
                return unsafe { write_run_avx2::<T, $p, $d>(rec, cols, n, row, depth, out, pos) };
            }
            // SAFETY: the caller's contract.
            unsafe { write_run::<T, $p, $d>(rec, &cols[..n], row, depth, out, pos) }
        }};
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = avx2;
    match (persp, derivs) {
        (true, true) => go!(true, true),
        (true, false) => go!(true, false),
        (false, true) => go!(false, true),
        (false, false) => go!(false, false),
    }
}

/// Assembles the tiles' fragments into the packed pixel-order layout: computes where each
/// tile's local rows start in the output (prefix sums over image rows and, within a row,
/// over tiles), then computes every fragment's values (per run of one face's fragments in a
/// row, [`write_run`]) straight into the final arrays (allocated uninitialised, each element written once), in
/// parallel over tiles, whose face records are then a small working set. The result does not
/// depend on the thread count.
pub(crate) fn assemble<T: Real>(
    tiles: Vec<TileFrags>,
    bins: &Bins,
    s: &RasterSettings,
    avx2: bool,
) -> Result<Fragments<T>, RasterError> {
    let (width, height, k) = (s.width, s.height, s.faces_per_pixel);
    let (persp, derivs) = (s.perspective_correct, s.barycentric_derivatives);
    let tx_n = bins.tiles_x;
    // Output position of each tile's local rows, in row-major pixel order.
    let mut tile_pos = vec![[0usize; TILE_SIZE]; tiles.len()];
    let mut total = 0usize;
    for r in 0..height {
        let (ty, lr) = (r / TILE_SIZE, r % TILE_SIZE);
        for tx in 0..tx_n {
            let t = ty * tx_n + tx;
            tile_pos[t][lr] = total;
            total += tiles[t].row_len(lr);
        }
    }
    if total > u32::MAX as usize {
        return Err(RasterError::TooManyFragments { fragments: total });
    }
    let mut offsets = Vec::<u32>::with_capacity(width * height + 1);
    let mut face = Vec::<u32>::with_capacity(total);
    let mut bary = Vec::<[T; 3]>::with_capacity(total);
    let mut depth = Vec::<T>::with_capacity(total);
    let mut view_depth = Vec::<T>::with_capacity(total);
    let nd = if derivs { total } else { 0 };
    let mut dbary_dx = Vec::<[T; 3]>::with_capacity(nd);
    let mut dbary_dy = Vec::<[T; 3]>::with_capacity(nd);
    let out = OutPtrs {
        offsets: offsets.as_mut_ptr(),
        face: face.as_mut_ptr(),
        bary: bary.as_mut_ptr(),
        depth: depth.as_mut_ptr(),
        view_depth: view_depth.as_mut_ptr(),
        dx: dbary_dx.as_mut_ptr(),
        dy: dbary_dy.as_mut_ptr(),
    };
    let out = &out;
    let written: usize = (0..tiles.len())
        .into_par_iter()
        .map(|t| {
            let tile = &tiles[t];
            let rect = bins.tile_rect(t, width, height);
            let n = (rect.c1 - rect.c0) as usize + 1;
            let mut i = 0usize;
            for lr in 0..(rect.r1 - rect.r0) as usize + 1 {
                let row = rect.r0 as usize + lr;
                let rf = row as f64;
                let mut pos = tile_pos[t][lr];
                let first_px = row * width + rect.c0 as usize;
                if tile.row_len(lr) == 0 {
                    for j in 0..n {
                        // SAFETY: pixel `first_px + j` lies in this tile only, and is below
                        // `width * height`, within the capacity of `offsets`.
                        unsafe { out.offset(first_px + j, pos as u32) };
                    }
                    continue;
                }
                let counts = &tile.counts[lr * TILE_SIZE..lr * TILE_SIZE + n];
                // Writes the run of `cols.len()` fragments of face record `id` whose depths
                // start at the tile's fragment `i0` and whose output slots start at `p0`.
                let flush = |id: u32, cols: &[f64; RUN], n: usize, i0: usize, p0: usize| {
                    // SAFETY: `pos` runs over `tile_pos[t][lr]..` for this tile's
                    // `row_len(lr)` fragments of the row: a range of `..total` that no other
                    // tile or row has (prefix sums above), within the capacity; a run covers
                    // `p0..p0 + n` of it.
                    // `avx2` only with CPU support (`rasterize_with`), and the derivative arrays were allocated
                    // when `derivs`.
                    unsafe {
                        write_run_dispatch(
                            avx2,
                            persp,
                            derivs,
                            bins.rec(id),
                            cols,
                            n,
                            rf,
                            &tile.depth[i0..i0 + n],
                            out,
                            p0,
                        )
                    }
                };
                // Runs of consecutive fragments (in output order) of one face record get
                // their values together ([`write_run`]); a run never spans rows.
                let mut cols = [0.0f64; RUN];
                let mut run = 0usize;
                let (mut run_id, mut run_i, mut run_pos) = (u32::MAX, i, pos);
                for (j, &cnt) in counts.iter().enumerate() {
                    // SAFETY: pixel `first_px + j` lies in this tile only, and is below
                    // `width * height`, within the capacity of `offsets`.
                    unsafe { out.offset(first_px + j, pos as u32) };
                    let col = (rect.c0 as usize + j) as f64;
                    for _ in 0..cnt {
                        let id = tile.idx[i];
                        if id != run_id || run == RUN {
                            if run > 0 {
                                flush(run_id, &cols, run, run_i, run_pos);
                            }
                            (run_id, run, run_i, run_pos) = (id, 0, i, pos);
                        }
                        cols[run] = col;
                        run += 1;
                        pos += 1;
                        i += 1;
                    }
                }
                if run > 0 {
                    flush(run_id, &cols, run, run_i, run_pos);
                }
            }
            i
        })
        .sum();
    // Every tile wrote all its fragments (checked before the lengths are set).
    assert_eq!(written, total, "fragments written");
    // SAFETY: every pixel's offset (`width * height` of them, each in exactly one tile) and
    // every fragment slot `..total` (the tiles' fragments, `written == total`) was written
    // above; the last offset is written here.
    unsafe {
        offsets.as_mut_ptr().add(width * height).write(total as u32);
        offsets.set_len(width * height + 1);
        face.set_len(total);
        bary.set_len(total);
        depth.set_len(total);
        view_depth.set_len(total);
        dbary_dx.set_len(nd);
        dbary_dy.set_len(nd);
    }
    Ok(Fragments {
        width,
        height,
        k,
        offsets,
        face,
        bary,
        depth,
        view_depth,
        dbary_dx,
        dbary_dy,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Walking the fragments in order with [`PixelCursor::advance`] (over gaps of every
    /// length, including whole rows) lands on [`Fragments::pixel_of`] for every
    /// fragment, with the column, row and NDC centre of a cursor made there, for 1 and 3
    /// fragments per pixel and cursors started mid-way.
    #[test]
    fn cursor_matches_pixel_of() {
        let (w, h) = (37usize, 23usize);
        for (k, seed) in [(1usize, 1u64), (1, 2), (3, 3)] {
            let mut f = Fragments::<f32>::empty(w, h, k);
            let mut state = seed;
            let mut rnd = move || {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 33) as usize
            };
            let mut total = 0u32;
            for p in 0..w * h {
                f.offsets[p] = total;
                // Long gaps (a row and more) and random short ones.
                let covered = p % 97 < 40 && rnd() % 5 != 0;
                if covered {
                    total += 1 + (rnd() % k) as u32;
                }
            }
            f.offsets[w * h] = total;
            let n = total as usize;
            assert!(n > 100);
            for i0 in [0, n / 3, n - 1] {
                let mut cur = PixelCursor::new(&f, i0);
                for i in i0..n {
                    cur.advance(&f.offsets, i);
                    let want = PixelCursor::new(&f, i);
                    assert_eq!(cur.p, f.pixel_of(i), "k {k} fragment {i}");
                    assert_eq!((cur.col, cur.row), (want.col, want.row));
                    assert_eq!(cur.ndc().map(f64::to_bits), want.ndc().map(f64::to_bits));
                }
            }
        }
    }
}
