//! Deterministic parallel scatter-add into per-vertex rows ("owner computes").
//!
//! The vertex range is split into one contiguous block per rayon thread; every block scans all
//! contributions in their given order and adds only those of its own vertices. Each vertex
//! therefore sums its contributions in input order, exactly as the serial loop does, so the
//! result is bit-identical for any number of threads (one thread is the serial loop). The scan
//! is repeated per block, which is cheap next to the scattered adds it parallelises.

use std::ops::Range;

use rayon::prelude::*;

/// Fewest vertices per block: below this the split is not worth a task.
const MIN_BLOCK: usize = 1024;

/// Splits `acc` (`width` values per vertex) into per-thread vertex blocks and calls
/// `visit(vertices, block)` on each in parallel: `visit` must scan all contributions in a
/// fixed order and add those whose vertex `v` lies in `vertices` into
/// `block[(v - vertices.start) * width..]`.
pub(crate) fn scatter_by_vertex<A: Send>(
    acc: &mut [A],
    width: usize,
    visit: impl Fn(Range<usize>, &mut [A]) + Sync,
) {
    let nv = acc.len().checked_div(width).unwrap_or(0);
    let blocks = rayon::current_num_threads().min(nv / MIN_BLOCK).max(1);
    if blocks == 1 {
        visit(0..nv, acc);
        return;
    }
    let per = nv.div_ceil(blocks);
    acc.par_chunks_mut(per * width)
        .enumerate()
        .for_each(|(b, block)| {
            let v0 = b * per;
            visit(v0..v0 + block.len() / width, block)
        });
}

/// Adds per-face-corner values into per-vertex rows (`width` values per vertex) in a fixed
/// order: `items()` yields `(face, vals)`, `vals` holding `width` values for each of the face's
/// three corners (`3 * width`), which are added into the rows of the face's vertices. Every
/// vertex sums its contributions in the order of `items` (corners in order,
/// [`scatter_vertex_rows`]), so the result is bit-identical for any number of threads.
pub(crate) fn scatter_face_corners<'a, I>(
    acc: &mut [f64],
    width: usize,
    faces: &'a [[u32; 3]],
    items: impl Fn() -> I + Sync,
) where
    I: Iterator<Item = (u32, &'a [f64])>,
{
    if width == 0 {
        return;
    }
    scatter_vertex_rows(acc, width, || {
        items().flat_map(move |(fi, vals)| {
            faces[fi as usize]
                .iter()
                .zip(vals.chunks_exact(width))
                .map(|(&v, row)| (v, row))
        })
    });
}

/// Adds per-vertex rows (`width` values per vertex) in a fixed order: `items()` yields
/// `(vertex, vals)` with `width` values each. Every vertex sums its rows in the order of
/// `items` ([`scatter_by_vertex`]), so the result is bit-identical for any number of threads.
pub(crate) fn scatter_vertex_rows<'a, I>(
    acc: &mut [f64],
    width: usize,
    items: impl Fn() -> I + Sync,
) where
    I: Iterator<Item = (u32, &'a [f64])>,
{
    if width == 0 {
        return;
    }
    scatter_by_vertex(acc, width, |vr, out| {
        for (v, vals) in items() {
            let v = v as usize;
            if vr.contains(&v) {
                for (o, x) in out[(v - vr.start) * width..][..width].iter_mut().zip(vals) {
                    *o += x;
                }
            }
        }
    });
}
