//! Packed fragments: a CSR over pixels holding, for each covered pixel, its nearest fragments.

use std::mem::MaybeUninit;
use std::ops::Range;

use autodiff::Real;
use rayon::prelude::*;

use super::bin::Bins;
use super::clip::Rect;
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
        if let Some(p) = self
            .offsets
            .windows(2)
            .position(|w| w[1] < w[0] || (w[1] - w[0]) as usize > self.k)
        {
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
/// pixel), with their values computed by the tile pass while the faces' records are in cache;
/// assembly copies them, row segment by row segment, into the final arrays.
pub(crate) struct TileOut<T> {
    pub face: Vec<u32>,
    pub bary: Vec<[T; 3]>,
    pub depth: Vec<T>,
    pub view_depth: Vec<T>,
    pub dx: Vec<[T; 3]>,
    pub dy: Vec<[T; 3]>,
    /// Fragment count per local pixel (`local_row * TILE_SIZE + local_col`); empty if none.
    pub counts: Vec<u16>,
    /// `row_start[lr]..row_start[lr + 1]`: the fragments of local row `lr`.
    pub row_start: [u32; TILE_SIZE + 1],
}

impl<T: Real> TileOut<T> {
    pub fn empty() -> Self {
        Self {
            face: Vec::new(),
            bary: Vec::new(),
            depth: Vec::new(),
            view_depth: Vec::new(),
            dx: Vec::new(),
            dy: Vec::new(),
            counts: Vec::new(),
            row_start: [0; TILE_SIZE + 1],
        }
    }

    /// Number of fragments in local row `lr`.
    #[inline]
    fn row_len(&self, lr: usize) -> usize {
        (self.row_start[lr + 1] - self.row_start[lr]) as usize
    }

    /// Packs a dense K-buffer (`k` slots per local pixel of record ids, `+inf` depth when
    /// empty) of the tile `rect` and computes each fragment's values
    /// ([`super::edge::Setup::values`]).
    pub fn pack(
        depth: &[f64],
        idx: &[u32],
        bins: &Bins,
        rect: &Rect,
        k: usize,
        persp: bool,
    ) -> Self {
        let n = (rect.c1 - rect.c0) as usize + 1;
        let rows = (rect.r1 - rect.r0) as usize + 1;
        let mut out = Self::empty();
        let total = (0..rows)
            .map(|lr| {
                let p = lr * TILE_SIZE * k;
                depth[p..p + n * k].iter().filter(|d| **d <= 1.0).count()
            })
            .sum::<usize>();
        if total == 0 {
            return out;
        }
        out.face.reserve_exact(total);
        out.bary.reserve_exact(total);
        out.depth.reserve_exact(total);
        out.view_depth.reserve_exact(total);
        out.dx.reserve_exact(total);
        out.dy.reserve_exact(total);
        out.counts = vec![0; TILE_SIZE * TILE_SIZE];
        for lr in 0..rows {
            let p = lr * TILE_SIZE;
            let slots = p * k..(p + n) * k;
            let rf = (rect.r0 as usize + lr) as f64;
            for (j, ((cnt, dk), ik)) in out.counts[p..p + n]
                .iter_mut()
                .zip(depth[slots.clone()].chunks_exact(k))
                .zip(idx[slots].chunks_exact(k))
                .enumerate()
            {
                let col = (rect.c0 as usize + j) as f64;
                for (&d, &i) in dk.iter().zip(ik) {
                    if d > 1.0 {
                        break;
                    }
                    let rec = bins.rec(i);
                    let (bary, vd, dx, dy) = rec.st.values::<T>(col, rf, persp);
                    out.face.push(rec.face);
                    out.bary.push(bary);
                    out.depth.push(T::from_f64c(d));
                    out.view_depth.push(vd);
                    out.dx.push(dx);
                    out.dy.push(dy);
                    *cnt += 1;
                }
            }
            out.row_start[lr + 1] = out.face.len() as u32;
        }
        for lr in rows..TILE_SIZE {
            out.row_start[lr + 1] = out.row_start[rows];
        }
        out
    }
}

/// Copies `src` into the uninitialised `dst` (same length), as one `memcpy`.
#[inline]
fn write_copy<X: Copy>(dst: &mut [MaybeUninit<X>], src: &[X]) {
    assert_eq!(dst.len(), src.len());
    // SAFETY: both slices have `src.len()` elements, do not overlap (one is borrowed mutably),
    // and `MaybeUninit<X>` has the layout of `X`.
    unsafe { std::ptr::copy_nonoverlapping(src.as_ptr(), dst.as_mut_ptr().cast::<X>(), src.len()) }
}

/// Uninitialised output slices of one image row.
struct RowOut<'a, T> {
    row: usize,
    base: usize,
    offsets: &'a mut [u32],
    face: &'a mut [MaybeUninit<u32>],
    bary: &'a mut [MaybeUninit<[T; 3]>],
    depth: &'a mut [MaybeUninit<T>],
    view_depth: &'a mut [MaybeUninit<T>],
    dx: &'a mut [MaybeUninit<[T; 3]>],
    dy: &'a mut [MaybeUninit<[T; 3]>],
}

fn split_sizes<'a, X>(mut v: &'a mut [X], sizes: &[usize]) -> Vec<&'a mut [X]> {
    let mut out = Vec::with_capacity(sizes.len());
    for &n in sizes {
        let (a, b) = v.split_at_mut(n);
        out.push(a);
        v = b;
    }
    out
}

/// Assembles the tiles' fragments into the packed pixel-order layout (final arrays allocated
/// uninitialised and written once), in parallel over image rows (each a contiguous run of
/// pixels and fragments). The result does not depend on the thread count.
pub(crate) fn assemble<T: Real>(
    tiles: Vec<TileOut<T>>,
    bins: &Bins,
    s: &RasterSettings,
) -> Result<Fragments<T>, RasterError> {
    let (width, height, k) = (s.width, s.height, s.faces_per_pixel);
    let tx_n = bins.tiles_x;
    let row_frags: Vec<usize> = (0..height)
        .map(|r| {
            let (ty, lr) = (r / TILE_SIZE, r % TILE_SIZE);
            tiles[ty * tx_n..(ty + 1) * tx_n]
                .iter()
                .map(|t| t.row_len(lr))
                .sum::<usize>()
        })
        .collect();
    let total: usize = row_frags.iter().sum();
    if total > u32::MAX as usize {
        return Err(RasterError::TooManyFragments { fragments: total });
    }
    let mut offsets = vec![0u32; width * height + 1];
    offsets[width * height] = total as u32;
    let mut face = Vec::<u32>::with_capacity(total);
    let mut bary = Vec::<[T; 3]>::with_capacity(total);
    let mut depth = Vec::<T>::with_capacity(total);
    let mut view_depth = Vec::<T>::with_capacity(total);
    let mut dbary_dx = Vec::<[T; 3]>::with_capacity(total);
    let mut dbary_dy = Vec::<[T; 3]>::with_capacity(total);
    let mut bases = Vec::with_capacity(height);
    let mut acc = 0usize;
    for &n in &row_frags {
        bases.push(acc);
        acc += n;
    }
    let row_px = vec![width; height];
    let rows: Vec<RowOut<'_, T>> = split_sizes(&mut offsets[..width * height], &row_px)
        .into_iter()
        .zip(split_sizes(
            &mut face.spare_capacity_mut()[..total],
            &row_frags,
        ))
        .zip(split_sizes(
            &mut bary.spare_capacity_mut()[..total],
            &row_frags,
        ))
        .zip(split_sizes(
            &mut depth.spare_capacity_mut()[..total],
            &row_frags,
        ))
        .zip(split_sizes(
            &mut view_depth.spare_capacity_mut()[..total],
            &row_frags,
        ))
        .zip(split_sizes(
            &mut dbary_dx.spare_capacity_mut()[..total],
            &row_frags,
        ))
        .zip(split_sizes(
            &mut dbary_dy.spare_capacity_mut()[..total],
            &row_frags,
        ))
        .enumerate()
        .map(
            |(row, ((((((offsets, face), bary), depth), view_depth), dx), dy))| RowOut {
                row,
                base: bases[row],
                offsets,
                face,
                bary,
                depth,
                view_depth,
                dx,
                dy,
            },
        )
        .collect();
    rows.into_par_iter().with_min_len(4).for_each(|ro| {
        let (ty, lr) = (ro.row / TILE_SIZE, ro.row % TILE_SIZE);
        let mut pos = 0usize;
        for (tx, tile) in tiles[ty * tx_n..(ty + 1) * tx_n].iter().enumerate() {
            let c0 = tx * TILE_SIZE;
            let c1 = (c0 + TILE_SIZE).min(width);
            let offs = &mut ro.offsets[c0..c1];
            if tile.row_len(lr) == 0 {
                offs.fill((ro.base + pos) as u32);
                continue;
            }
            let (i0, n_row) = (tile.row_start[lr] as usize, tile.row_len(lr));
            let (src, dst) = (i0..i0 + n_row, pos..pos + n_row);
            write_copy(&mut ro.face[dst.clone()], &tile.face[src.clone()]);
            write_copy(&mut ro.bary[dst.clone()], &tile.bary[src.clone()]);
            write_copy(&mut ro.depth[dst.clone()], &tile.depth[src.clone()]);
            write_copy(
                &mut ro.view_depth[dst.clone()],
                &tile.view_depth[src.clone()],
            );
            write_copy(&mut ro.dx[dst.clone()], &tile.dx[src.clone()]);
            write_copy(&mut ro.dy[dst], &tile.dy[src]);
            let counts = &tile.counts[lr * TILE_SIZE..lr * TILE_SIZE + (c1 - c0)];
            for (o, &n) in offs.iter_mut().zip(counts) {
                *o = (ro.base + pos) as u32;
                pos += n as usize;
            }
        }
        // Every slot of the row was written (checked before the lengths are set below).
        assert_eq!(pos, ro.face.len(), "row {} fragment count", ro.row);
    });
    // SAFETY: the rows split `..total` of every array without overlap, and each row wrote
    // all of its slots (asserted above); a panic there propagates before this point.
    unsafe {
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
