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
    /// Derivative of `bary` per pixel step to the right (`col + 1`).
    pub dbary_dx: Vec<[T; 3]>,
    /// Derivative of `bary` per pixel step down (`row + 1`).
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
    /// `d bary / d col`.
    pub dbary_dx: [T; 3],
    /// `d bary / d row`.
    pub dbary_dy: [T; 3],
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
            dbary_dx: self.dbary_dx[i],
            dbary_dy: self.dbary_dy[i],
        }
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

    /// Checks the internal consistency of the layout (lengths, monotone offsets, `<= k` per pixel).
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
        for (what, len) in [
            ("bary", self.bary.len()),
            ("depth", self.depth.len()),
            ("view_depth", self.view_depth.len()),
            ("dbary_dx", self.dbary_dx.len()),
            ("dbary_dy", self.dbary_dy.len()),
        ] {
            if len != n {
                return bad(format!("{what} has length {len}, expected {n}"));
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
                    for ((cnt, &d), &i) in out.counts[cols].iter_mut().zip(dk).zip(ik) {
                        if d <= 1.0 {
                            out.idx.push(i);
                            out.depth.push(d);
                            *cnt = 1;
                        }
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
            if c0 < c1 {
                let p = lr * TILE_SIZE;
                sc.depth[(p + c0 as usize) * k..(p + c1 as usize) * k].fill(f64::INFINITY);
            }
            sc.span[lr] = (TILE_SIZE as u32, 0);
            sc.filled[lr] = 0;
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

    /// Writes fragment slot `i`.
    ///
    /// # Safety
    /// `i < total`, and no other task writes or reads it.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    unsafe fn fragment(
        &self,
        i: usize,
        face: u32,
        bary: [T; 3],
        depth: T,
        view_depth: T,
        dx: [T; 3],
        dy: [T; 3],
    ) {
        unsafe {
            self.face.add(i).write(face);
            self.bary.add(i).write(bary);
            self.depth.add(i).write(depth);
            self.view_depth.add(i).write(view_depth);
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

/// Computes and writes the values of a run of fragments of one face record (output slots
/// `pos..pos + cols.len()`, at columns `cols` of row `row`, with NDC depths `depth`):
/// barycentrics, view depth and barycentric derivatives from the record's edge functions.
///
/// With `e_i = a_i col + (b_i row + c_i)` ([`Setup::eval`]), `inv = 1 / sum e`: perspective
/// correct `b_i = e_i inv`, `d b_i / dcol = (a_i - b_i sum a) inv` (`b` for rows); screen-space
/// `l_i = e_i w_i / det` with the constant derivatives `a_i w_i / det`, `b_i w_i / det`; view
/// depth `sum_i (e_i inv) w_i` either way. The row part of `e` and the per-face constants are
/// computed once per run; every fragment's values are the same expressions as computed per
/// fragment. Every fragment must have `sum e > 0`. Values beyond the range of `T` (only for
/// slivers at the limits of `f64`) are saturated, NaN to zero, so they are always finite.
///
/// # Safety
/// `cols.len() == depth.len()`, and the slots `pos..pos + cols.len()` lie below the
/// output's capacity and are written by no other task.
#[inline(always)]
unsafe fn write_run<T: Real>(
    rec: &FaceRec,
    cols: &[f64],
    row: f64,
    persp: bool,
    depth: &[f64],
    out: &OutPtrs<T>,
    pos: usize,
) {
    let st: &Setup = &rec.st;
    // Per run: the row part of the edge functions and the per-face constants.
    let t = st.row(row);
    // Only the constants of the mode in use (runs are short for small faces).
    let (mut sa, mut sb) = (0.0, 0.0);
    let (mut sw, mut ax, mut by) = ([0.0; 3], [0.0; 3], [0.0; 3]);
    if persp {
        (sa, sb) = (st.a[0] + st.a[1] + st.a[2], st.b[0] + st.b[1] + st.b[2]);
    } else {
        sw = [
            st.w[0] * st.inv_det,
            st.w[1] * st.inv_det,
            st.w[2] * st.inv_det,
        ];
        ax = [st.a[0] * sw[0], st.a[1] * sw[1], st.a[2] * sw[2]];
        by = [st.b[0] * sw[0], st.b[1] * sw[1], st.b[2] * sw[2]];
    }
    let m = T::max_value().to_f64c();
    for (j, (&col, &d)) in cols.iter().zip(depth).enumerate() {
        let e = st.eval(col, &t);
        let inv = 1.0 / (e[0] + e[1] + e[2]);
        let bp = [e[0] * inv, e[1] * inv, e[2] * inv];
        let vd = bp[0] * st.w[0] + bp[1] * st.w[1] + bp[2] * st.w[2];
        let (bary, dx, dy) = if persp {
            // d(e_i / sum e) = (de_i - b_i d(sum e)) / sum e, de_i/dcol = a_i, de_i/drow = b_i.
            (
                bp,
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
            ([e[0] * sw[0], e[1] * sw[1], e[2] * sw[2]], ax, by)
        };
        // Every value within T's finite range converts to a finite value. One test on the sum
        // of the magnitudes (each at most the rounded sum, which is NaN or infinite when any
        // value is) covers all ten; the saturating path, taken also for the rare in-range sets
        // whose sum exceeds the range, gives the same values wherever the plain conversion is
        // finite.
        let mag = (vd.abs() + (bary[0].abs() + bary[1].abs() + bary[2].abs()))
            + ((dx[0].abs() + dx[1].abs() + dx[2].abs())
                + (dy[0].abs() + dy[1].abs() + dy[2].abs()));
        let ok = mag <= m;
        let vals = if ok {
            (
                bary.map(T::from_f64c),
                T::from_f64c(vd),
                dx.map(T::from_f64c),
                dy.map(T::from_f64c),
            )
        } else {
            (bary.map(sat), sat(vd), dx.map(sat), dy.map(sat))
        };
        // SAFETY: slot `pos + j` is one of this run's (the caller's contract).
        unsafe {
            out.fragment(
                pos + j,
                rec.face,
                vals.0,
                T::from_f64c(d),
                vals.1,
                vals.2,
                vals.3,
            )
        };
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
) -> Result<Fragments<T>, RasterError> {
    let (width, height, k) = (s.width, s.height, s.faces_per_pixel);
    let persp = s.perspective_correct;
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
    let mut dbary_dx = Vec::<[T; 3]>::with_capacity(total);
    let mut dbary_dy = Vec::<[T; 3]>::with_capacity(total);
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
                let flush = |id: u32, cols: &[f64], i0: usize, p0: usize| {
                    // SAFETY: `pos` runs over `tile_pos[t][lr]..` for this tile's
                    // `row_len(lr)` fragments of the row: a range of `..total` that no other
                    // tile or row has (prefix sums above), within the capacity; a run covers
                    // `p0..p0 + cols.len()` of it.
                    unsafe {
                        write_run(
                            bins.rec(id),
                            cols,
                            rf,
                            persp,
                            &tile.depth[i0..i0 + cols.len()],
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
                                flush(run_id, &cols[..run], run_i, run_pos);
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
                    flush(run_id, &cols[..run], run_i, run_pos);
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
        dbary_dx.set_len(total);
        dbary_dy.set_len(total);
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
