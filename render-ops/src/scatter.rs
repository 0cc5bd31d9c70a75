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

/// A map from `u32` keys (below `u32::MAX`) to dense indices `0, 1, ..` in order of insertion
/// (open addressing, kept at most half full: the table doubles when it would fill beyond),
/// cleared in time proportional to its length. Per-chunk scratch starts small, so that making
/// one (once per parallel task) costs little next to the chunk's work, and keeps its size
/// across the chunks of its task.
pub(crate) struct IndexMap {
    /// `(key, index)` per slot, `key == u32::MAX` where empty.
    slots: Vec<(u32, u32)>,
    /// The occupied slots, in order of insertion.
    used: Vec<u32>,
    /// `32 - log2(slots.len())`: the hash keeps the top bits of the product.
    shift: u32,
}

impl IndexMap {
    /// A map with room for `len` keys before it first grows.
    pub(crate) fn new(len: usize) -> Self {
        let cap = (2 * len).next_power_of_two().max(16);
        IndexMap {
            slots: vec![(u32::MAX, 0); cap],
            used: Vec::with_capacity(len),
            shift: 32 - cap.trailing_zeros(),
        }
    }

    /// The index of `key`, and whether it was inserted by this call (as index `len - 1`).
    #[inline]
    pub(crate) fn index(&mut self, key: u32) -> (usize, bool) {
        debug_assert!(key != u32::MAX);
        let mask = self.slots.len() - 1;
        let mut s = (key.wrapping_mul(0x9E37_79B9) >> self.shift) as usize;
        loop {
            let (k, v) = self.slots[s];
            if k == key {
                return (v as usize, false);
            }
            if k == u32::MAX {
                let v = self.used.len();
                if 2 * (v + 1) > self.slots.len() {
                    self.grow();
                    return self.index(key);
                }
                self.slots[s] = (key, v as u32);
                self.used.push(s as u32);
                return (v, true);
            }
            s = (s + 1) & mask;
        }
    }

    /// Doubles the table, re-inserting the keys with their indices in insertion order.
    #[cold]
    fn grow(&mut self) {
        let entries: Vec<(u32, u32)> = self.used.iter().map(|&s| self.slots[s as usize]).collect();
        let cap = 2 * self.slots.len();
        self.slots.clear();
        self.slots.resize(cap, (u32::MAX, 0));
        self.shift = 32 - cap.trailing_zeros();
        self.used.clear();
        let mask = cap - 1;
        for (key, v) in entries {
            let mut s = (key.wrapping_mul(0x9E37_79B9) >> self.shift) as usize;
            while self.slots[s].0 != u32::MAX {
                s = (s + 1) & mask;
            }
            self.slots[s] = (key, v);
            self.used.push(s as u32);
        }
    }

    pub(crate) fn clear(&mut self) {
        for &s in &self.used {
            self.slots[s as usize].0 = u32::MAX;
        }
        self.used.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::IndexMap;

    /// Indices follow insertion order through growth and clears; lookups find them again.
    #[test]
    fn index_map_keeps_insertion_order_through_growth() {
        let mut m = IndexMap::new(4);
        for round in 0..3u32 {
            let keys: Vec<u32> = (0..1000u32)
                .map(|i| i.wrapping_mul(2_654_435_761).wrapping_add(round) % 50_000)
                .collect();
            let mut want = Vec::new();
            for &k in &keys {
                let (i, new) = m.index(k);
                match want.iter().position(|&x| x == k) {
                    Some(p) => assert_eq!((i, new), (p, false)),
                    None => {
                        assert_eq!((i, new), (want.len(), true));
                        want.push(k);
                    }
                }
            }
            for (p, &k) in want.iter().enumerate() {
                assert_eq!(m.index(k), (p, false));
            }
            m.clear();
        }
    }
}
