//! Binning faces into screen tiles by their clipped screen bounding boxes, with each binned
//! face's setup computed once.
//!
//! Faces are split into fixed-size chunks (a power of two that depends only on the face and
//! tile counts, never on the thread count); each chunk computes, in parallel and in face order,
//! the record ([`FaceRec`]: edge functions, depth plane, box) of every face that survives
//! culling, and a small CSR from tiles to its records. A tile's record list is the
//! concatenation over chunks in chunk order, so it is sorted by face index and identical for
//! any rayon pool. Records are read by the tile pass and by assembly from these contiguous
//! per-chunk arrays, not gathered per tile from the (arbitrarily ordered) faces and vertices.

use rayon::prelude::*;

use super::clip::{screen_bounds, Rect};
use super::edge::Setup;
use super::{RasterSettings, TILE_SIZE};

/// Per-face data of a binned face: its setup (edge functions for its whole box), NDC depth
/// plane `d = dz[0] col + dz[1] row + dz[2]`, pixel box and face index.
pub(crate) struct FaceRec {
    pub st: Setup,
    pub dz: [f64; 3],
    pub rect: Rect,
    pub face: u32,
}

/// Records and tile-to-record lists of one chunk of faces.
struct ChunkBins {
    /// `offsets[t]..offsets[t + 1]` index `list` for tile `t`.
    offsets: Vec<usize>,
    /// Global record ids ([`Bins::rec`]).
    list: Vec<u32>,
    recs: Vec<FaceRec>,
}

/// Faces binned per tile, as records.
pub(crate) struct Bins {
    pub tiles_x: usize,
    pub tiles_y: usize,
    /// `log2` of the chunk size: record id = `chunk << shift | index in chunk`.
    shift: u32,
    chunks: Vec<ChunkBins>,
}

impl Bins {
    /// Number of tiles.
    pub fn num_tiles(&self) -> usize {
        self.tiles_x * self.tiles_y
    }

    /// Record ids of the faces overlapping tile `t`, in increasing face order.
    #[inline]
    pub fn tile_faces(&self, t: usize) -> impl Iterator<Item = u32> + '_ {
        self.chunks.iter().flat_map(move |c| {
            let (s, e) = (c.offsets[t], c.offsets[t + 1]);
            c.list[s..e].iter().copied()
        })
    }

    /// The record with id `id`.
    #[inline(always)]
    pub fn rec(&self, id: u32) -> &FaceRec {
        let c = &self.chunks[(id >> self.shift) as usize];
        &c.recs[(id & ((1u32 << self.shift) - 1)) as usize]
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

/// Culls faces (frustum, degenerate, optionally back-facing), computes their screen boxes and
/// setups and bins them into tiles.
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
    // About 16 chunks or more (of 512 to 4096 faces), so that small meshes also split evenly
    // over the threads; larger chunks keep chunks x tiles counters bounded (about 4M) for
    // huge images.
    let chunk = (faces.len() / 16)
        .next_power_of_two()
        .clamp(512, 4096)
        .max((faces.len() as u128 * nt as u128 / (1u128 << 22)) as usize + 1)
        .next_power_of_two();
    let shift = chunk.trailing_zeros();
    let (w, h) = (s.width as u32, s.height as u32);
    let chunks: Vec<ChunkBins> = faces
        .par_chunks(chunk)
        .with_max_len(1)
        .enumerate()
        .map(|(ci, fs)| {
            let mut counts = vec![0usize; nt + 1];
            let mut recs = Vec::with_capacity(fs.len());
            for (k, f) in fs.iter().enumerate() {
                let idx = f.map(|i| i as usize);
                let oc = [outcodes[idx[0]], outcodes[idx[1]], outcodes[idx[2]]];
                let pj = [proj[idx[0]], proj[idx[1]], proj[idx[2]]];
                let Some(b) = screen_bounds(verts, idx, &pj, oc, w, h) else {
                    continue;
                };
                let v = idx.map(|i| verts[i]);
                // Degenerate faces (det M == 0) and slivers without usable barycentrics give
                // no setup and no fragments. The setup's error bounds hold over the whole box,
                // so one setup serves every tile.
                // Culled back faces (det M > 0 in the y-down screen frame) give none either.
                let Some(st) = Setup::new(&v, *f, b.c1 as f64, b.r1 as f64, s.cull_backfaces)
                else {
                    continue;
                };
                for ty in b.r0 as usize / TILE_SIZE..=b.r1 as usize / TILE_SIZE {
                    for tx in b.c0 as usize / TILE_SIZE..=b.c1 as usize / TILE_SIZE {
                        counts[ty * tiles_x + tx + 1] += 1;
                    }
                }
                recs.push(FaceRec {
                    dz: st.depth_plane(&v),
                    st,
                    rect: b,
                    face: (ci * chunk + k) as u32,
                });
            }
            for t in 0..nt {
                counts[t + 1] += counts[t];
            }
            let mut cursor = counts.clone();
            let mut list = vec![0u32; counts[nt]];
            let base = (ci << shift) as u32;
            for (k, r) in recs.iter().enumerate() {
                let r = &r.rect;
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
                list,
                recs,
            }
        })
        .collect();
    Bins {
        tiles_x,
        tiles_y,
        shift,
        chunks,
    }
}
