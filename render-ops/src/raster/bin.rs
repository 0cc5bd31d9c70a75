//! Binning faces into screen tiles by their clipped screen bounding boxes.
//!
//! Faces are split into fixed-size chunks (the size depends only on the face and tile counts,
//! never on the thread count); each chunk builds, in parallel, a small CSR from tiles to its faces
//! in increasing face order. A tile's face list is the concatenation over chunks in chunk order,
//! so it is sorted by face index and identical for any rayon pool.

use rayon::prelude::*;

use super::clip::{screen_bounds, Rect};
use super::edge::orientation;
use super::{RasterSettings, TILE_SIZE};

/// Tile-to-face lists of one chunk of faces.
struct ChunkBins {
    /// `offsets[t]..offsets[t + 1]` index `faces` for tile `t`.
    offsets: Vec<usize>,
    faces: Vec<u32>,
}

/// Faces binned per tile, plus each face's pixel bounding box.
pub(crate) struct Bins {
    pub tiles_x: usize,
    pub tiles_y: usize,
    /// Pixel bounding box of each face (empty when culled).
    pub rects: Vec<Rect>,
    chunks: Vec<ChunkBins>,
}

impl Bins {
    /// Number of tiles.
    pub fn num_tiles(&self) -> usize {
        self.tiles_x * self.tiles_y
    }

    /// Faces overlapping tile `t`, in increasing face order.
    #[inline]
    pub fn tile_faces(&self, t: usize) -> impl Iterator<Item = u32> + '_ {
        self.chunks.iter().flat_map(move |c| {
            let (s, e) = (c.offsets[t], c.offsets[t + 1]);
            c.faces[s..e].iter().copied()
        })
    }

    /// Pixel rectangle of tile `t`.
    pub fn tile_rect(&self, t: usize, width: usize, height: usize) -> Rect {
        let (tx, ty) = (t % self.tiles_x, t / self.tiles_x);
        let (c0, r0) = (tx * TILE_SIZE, ty * TILE_SIZE);
        Rect {
            c0: c0 as u32,
            c1: ((c0 + TILE_SIZE).min(width) - 1) as u32,
            r0: r0 as u32,
            r1: ((r0 + TILE_SIZE).min(height) - 1) as u32,
        }
    }
}

/// Culls faces (frustum, degenerate, optionally back-facing), computes their screen boxes and bins
/// them into tiles.
pub(crate) fn bin_faces(
    verts: &[[f64; 4]],
    proj: &[[f64; 2]],
    outcodes: &[u8],
    faces: &[[u32; 3]],
    s: &RasterSettings,
) -> Bins {
    let tiles_x = s.width.div_ceil(TILE_SIZE);
    let tiles_y = s.height.div_ceil(TILE_SIZE);
    let nt = tiles_x * tiles_y;
    // Keep chunks x tiles counters bounded (about 4M) for huge images.
    let chunk = 4096usize.max((faces.len() as u128 * nt as u128 / (1u128 << 22)) as usize + 1);
    let (w, h) = (s.width as u32, s.height as u32);
    let mut rects = vec![Rect::EMPTY; faces.len()];
    let chunks: Vec<ChunkBins> = rects
        .par_chunks_mut(chunk)
        .zip(faces.par_chunks(chunk))
        .enumerate()
        .map(|(ci, (rects, fs))| {
            let mut counts = vec![0usize; nt + 1];
            for (r, f) in rects.iter_mut().zip(fs) {
                let idx = f.map(|i| i as usize);
                let oc = [outcodes[idx[0]], outcodes[idx[1]], outcodes[idx[2]]];
                let pj = [proj[idx[0]], proj[idx[1]], proj[idx[2]]];
                let Some(b) = screen_bounds(verts, idx, &pj, oc, w, h) else {
                    continue;
                };
                // Front faces have det M < 0 in the y-down screen frame. (Degenerate faces,
                // det M == 0, are dropped by the tile pass's setup.)
                if s.cull_backfaces && orientation(&idx.map(|i| verts[i])) >= 0 {
                    continue;
                }
                *r = b;
                for ty in b.r0 as usize / TILE_SIZE..=b.r1 as usize / TILE_SIZE {
                    for tx in b.c0 as usize / TILE_SIZE..=b.c1 as usize / TILE_SIZE {
                        counts[ty * tiles_x + tx + 1] += 1;
                    }
                }
            }
            for t in 0..nt {
                counts[t + 1] += counts[t];
            }
            let mut cursor = counts.clone();
            let mut list = vec![0u32; counts[nt]];
            let base = (ci * chunk) as u32;
            for (k, r) in rects.iter().enumerate() {
                if r.is_empty() {
                    continue;
                }
                for ty in r.r0 as usize / TILE_SIZE..=r.r1 as usize / TILE_SIZE {
                    for tx in r.c0 as usize / TILE_SIZE..=r.c1 as usize / TILE_SIZE {
                        let t = ty * tiles_x + tx;
                        list[cursor[t]] = base + k as u32;
                        cursor[t] += 1;
                    }
                }
            }
            ChunkBins {
                offsets: counts,
                faces: list,
            }
        })
        .collect();
    Bins {
        tiles_x,
        tiles_y,
        rects,
        chunks,
    }
}
