//! Primary visibility through a screen-space grid. Camera rays share their origin: in the clip
//! space of [`super`] the ray of NDC point `(x, y)` is `q = t (x, y, 1)`, so its closest hit is
//! a 2D point query (which triangles' projections hold the point, and the nearest of them).
//! Each triangle is binned into square pixel tiles by the bounding box of the projection of
//! its part in front of the near plane, each tile's list is sorted by the triangles' least
//! depth, and a query runs the watertight test of [`super::intersect`] down its tile's list
//! until the next triangle's least depth is beyond the best hit: the same tests and the same
//! tie rule as [`Bvh::closest`], so exactly its hits, without the tree walk (tile binning as
//! in sort-middle rasterizers: S. Laine, T. Karras, "High-performance software rasterization
//! on GPUs", HPG 2011, section 3). Points outside the image (edge samples' side points at its
//! border) go to a BVH of the same triangles, built the first time one is asked.

use std::sync::OnceLock;

use rayon::prelude::*;

use super::bvh::Bvh;
use super::intersect::{Hit, Ray, Ray8, D8, K8, V3};
use crate::simd::{arr3, lanes, LANES};

/// Relative slack of the projected boxes and of the least depths (rounding of the watertight
/// test is below `1e-15` relative to the coordinates).
const SLACK: f64 = 1e-9;

/// One triangle of a tile's list: a lower bound of the depth `t` of any hit on it, and its
/// projected box (a cheap test before the watertight one).
#[derive(Clone, Copy, Debug)]
struct Entry {
    z: f64,
    bbox: [f64; 4],
    face: u32,
}

/// Triangles in clip space `(x, y, w)`, binned into square tiles of the `width x height` image.
pub struct ScreenGrid {
    width: f64,
    height: f64,
    tile: f64,
    tiles_x: usize,
    tiles_y: usize,
    /// Tile `i`'s entries are `entries[start[i]..start[i + 1]]`, by `(z, face)`.
    start: Vec<u32>,
    entries: Vec<Entry>,
    /// Triangle `f`'s vertices (face order).
    tris: Vec<[V3; 3]>,
    outside: OnceLock<Bvh>,
}

/// The part of triangle `v` with `w >= w0`, projected to pixel coordinates: its box
/// `[x0, x1, y0, y1]` (widened by the slack) and least `w`, or `None` when it has none or a
/// coordinate is not finite.
fn projected_box(v: &[V3; 3], w0: f64, width: f64, height: f64) -> Option<([f64; 4], f64)> {
    if !v.iter().flatten().all(|x| x.is_finite()) {
        return None;
    }
    // Sutherland-Hodgman against the one plane w = w0.
    let mut part = [[0.0; 3]; 4];
    let mut n = 0;
    for k in 0..3 {
        let (a, b) = (v[k], v[(k + 1) % 3]);
        if a[2] >= w0 {
            part[n] = a;
            n += 1;
        }
        if (a[2] >= w0) != (b[2] >= w0) {
            let s = (w0 - a[2]) / (b[2] - a[2]);
            part[n] = [a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1]), w0];
            n += 1;
        }
    }
    if n == 0 {
        return None;
    }
    let mut b = [
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    ];
    let mut z = f64::INFINITY;
    for p in &part[..n] {
        let px = (p[0] / p[2] + 1.0) * 0.5 * width;
        let py = (1.0 - p[1] / p[2]) * 0.5 * height;
        b = [b[0].min(px), b[1].max(px), b[2].min(py), b[3].max(py)];
        z = z.min(p[2]);
    }
    let scale = v.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
    let pad = |x: f64| SLACK * (1.0 + x.abs());
    let b = [
        b[0] - pad(b[0]),
        b[1] + pad(b[1]),
        b[2] - pad(b[2]),
        b[3] + pad(b[3]),
    ];
    b.iter()
        .all(|x| x.is_finite())
        .then_some((b, z - SLACK * scale))
}

impl ScreenGrid {
    /// Bins `faces` of clip-space points `q = (x, y, w)` for rays with `t > near` into tiles
    /// of the `width x height` image.
    pub fn new(q: &[V3], faces: &[[u32; 3]], width: usize, height: usize, near: f64) -> Self {
        let (wf, hf) = (width as f64, height as f64);
        let tris: Vec<[V3; 3]> = faces.iter().map(|f| f.map(|i| q[i as usize])).collect();
        let w0 = near * (1.0 - 1e-6);
        let boxes: Vec<Option<([f64; 4], f64)>> = tris
            .par_iter()
            .map(|v| {
                projected_box(v, w0, wf, hf)
                    .filter(|(b, _)| b[1] >= 0.0 && b[0] <= wf && b[3] >= 0.0 && b[2] <= hf)
            })
            .collect();
        // Tiles of the mean box side rounded down to a power of two, 4 to 64 pixels (on the
        // 5120-face sphere at 256 x 256, about 5 px: tiles of 4 px query 1.3x faster than 8
        // and 16, with twice and three times the entries), larger where the lists would be
        // long (below).
        let (sum, n) = boxes
            .iter()
            .flatten()
            .fold((0.0, 0usize), |(s, n), (b, _)| {
                (s + (b[1] - b[0]).min(wf) + (b[3] - b[2]).min(hf), n + 1)
            });
        let side = if n > 0 { sum / (2 * n) as f64 } else { 1.0 };
        let mut tile = ((side.max(1.0) as usize + 1).next_power_of_two() / 2).clamp(4, 64) as f64;
        // Tiles `a..=b` along an axis of `n` tiles of side `tile` that `[lo, hi]` covers.
        let range = |lo: f64, hi: f64, n: usize, tile: f64| {
            let a = (lo / tile).floor().max(0.0) as usize;
            let b = ((hi / tile).floor().max(0.0) as usize).min(n - 1);
            a.min(n - 1)..=b
        };
        let tiles = |tile: f64| {
            let n = |len: f64| (len / tile).ceil() as usize;
            (n(wf), n(hf))
        };
        // Few large triangles among many small ones would fill every small tile: double the
        // tiles until the lists hold at most 16 entries per triangle (plus one per tile).
        let entries_at = |tile: f64| {
            let (nx, ny) = tiles(tile);
            boxes
                .iter()
                .flatten()
                .map(|(b, _)| {
                    let span = |r: std::ops::RangeInclusive<usize>| r.end() + 1 - r.start();
                    span(range(b[0], b[1], nx, tile)) * span(range(b[2], b[3], ny, tile))
                })
                .sum::<usize>()
        };
        while tile < wf.max(hf) && entries_at(tile) > 16 * n + tiles(tile).0 * tiles(tile).1 {
            tile *= 2.0;
        }
        let (tiles_x, tiles_y) = tiles(tile);
        let range = |lo: f64, hi: f64, n: usize| range(lo, hi, n, tile);
        let mut count = vec![0u32; tiles_x * tiles_y + 1];
        for (b, _) in boxes.iter().flatten() {
            for ty in range(b[2], b[3], tiles_y) {
                for tx in range(b[0], b[1], tiles_x) {
                    count[ty * tiles_x + tx + 1] += 1;
                }
            }
        }
        for i in 1..count.len() {
            count[i] += count[i - 1];
        }
        let start = count;
        let mut fill = start.clone();
        let blank = Entry {
            z: 0.0,
            bbox: [0.0; 4],
            face: 0,
        };
        let mut entries = vec![blank; *start.last().unwrap() as usize];
        for (f, b) in boxes.iter().enumerate() {
            let Some((b, z)) = b else { continue };
            for ty in range(b[2], b[3], tiles_y) {
                for tx in range(b[0], b[1], tiles_x) {
                    let i = &mut fill[ty * tiles_x + tx];
                    entries[*i as usize] = Entry {
                        z: *z,
                        bbox: *b,
                        face: f as u32,
                    };
                    *i += 1;
                }
            }
        }
        // Each tile's list by (z, face): split the entries at the tiles' starts and sort them
        // in parallel (the order is a function of the lists, so deterministic).
        let mut lists: Vec<&mut [Entry]> = Vec::with_capacity(tiles_x * tiles_y);
        let mut rest = entries.as_mut_slice();
        for i in 0..tiles_x * tiles_y {
            let (a, b) = rest.split_at_mut((start[i + 1] - start[i]) as usize);
            lists.push(a);
            rest = b;
        }
        lists
            .par_iter_mut()
            .for_each(|l| l.sort_unstable_by(|a, b| a.z.total_cmp(&b.z).then(a.face.cmp(&b.face))));
        ScreenGrid {
            width: wf,
            height: hf,
            tile,
            tiles_x,
            tiles_y,
            start,
            entries,
            tris,
            outside: OnceLock::new(),
        }
    }

    /// The closest hit of the primary ray `r` through pixel point `u` (its NDC direction) with
    /// `t_min < t < t_max`; ties in `t` go to the lower face index. The same as
    /// [`Bvh::closest`] over the same triangles.
    pub fn closest(&self, r: &Ray, u: [f64; 2], t_min: f64, t_max: f64) -> Option<Hit> {
        if !(u[0] >= 0.0 && u[0] <= self.width && u[1] >= 0.0 && u[1] <= self.height) {
            return self
                .outside
                .get_or_init(|| {
                    // The triangles as an unwelded soup: face `f` is vertices `3f..3f + 3`.
                    let soup: Vec<V3> = self.tris.iter().flatten().copied().collect();
                    let faces: Vec<[u32; 3]> = (0..self.tris.len() as u32)
                        .map(|f| [3 * f, 3 * f + 1, 3 * f + 2])
                        .collect();
                    Bvh::new(&soup, &faces)
                })
                .closest(r, t_min, t_max);
        }
        let tx = ((u[0] / self.tile) as usize).min(self.tiles_x - 1);
        let ty = ((u[1] / self.tile) as usize).min(self.tiles_y - 1);
        let i = ty * self.tiles_x + tx;
        let list = &self.entries[self.start[i] as usize..self.start[i + 1] as usize];
        let mut best: Option<Hit> = None;
        let mut t_far = t_max;
        for e in list {
            if e.z > t_far {
                break;
            }
            let b = &e.bbox;
            if u[0] < b[0] || u[0] > b[1] || u[1] < b[2] || u[1] > b[3] {
                continue;
            }
            if let Some((t, bary)) =
                r.intersect(&self.tris[e.face as usize], t_min, t_far.next_up())
            {
                let face = e.face;
                if (Hit { t, bary, face }).keep_if_nearer(&mut best, t_max) {
                    t_far = t;
                }
            }
        }
        best
    }

    /// [`ScreenGrid::closest`] for the `active` camera rays of a packet through pixel points
    /// `u`: per lane the face hit (`u32::MAX` for none), its `t` and barycentrics. Lanes in
    /// one tile walk its list together, each with its own early exit and tie rule, so each
    /// gets its scalar ray's hit. `None` when an active point is outside the image (the caller
    /// traces the scalar rays).
    #[inline(always)]
    pub fn closest8(
        &self,
        r: &Ray8,
        u: &[D8; 2],
        t_min: f64,
        t_max: f64,
        active: K8,
    ) -> Option<([u32; LANES], D8, [D8; 3])> {
        let inside = |i: usize| {
            u[0][i] >= 0.0 && u[0][i] <= self.width && u[1][i] >= 0.0 && u[1][i] <= self.height
        };
        if (0..LANES).any(|i| active[i] && !inside(i)) {
            return None;
        }
        // `closest`'s tile index, in `f64` lanes (for `0 <= u`, `as usize` truncates, and the
        // indices are integers far below 2^53): one conversion per tile, not per lane.
        let (nx, ny) = (self.tiles_x as f64, self.tiles_y as f64);
        let tile = lanes(|i| {
            let tx = (u[0][i] / self.tile).trunc().min(nx - 1.0);
            let ty = (u[1][i] / self.tile).trunc().min(ny - 1.0);
            ty * nx + tx
        });
        let mut face = [u32::MAX; LANES];
        let mut best = [f64::INFINITY; LANES];
        // The winners' edge functions and their sum (divided once, at the end).
        let mut edge = [[0.0; LANES]; 3];
        let mut det = [1.0; LANES];
        let mut todo = active;
        while let Some(first) = todo.iter().position(|&a| a) {
            let ti = tile[first];
            let mine = lanes(|i| todo[i] && tile[i] == ti);
            todo = lanes(|i| todo[i] && !mine[i]);
            let ti = ti as usize;
            let list = &self.entries[self.start[ti] as usize..self.start[ti + 1] as usize];
            let mut t_far = [t_max; LANES];
            // `t_far.next_up()`, the test's bound, updated with `t_far`.
            let mut lim = lanes(|i| t_far[i].next_up());
            for e in list {
                let near = lanes(|i| mine[i] & !(e.z > t_far[i]));
                if !near.contains(&true) {
                    break;
                }
                let b = &e.bbox;
                let test = lanes(|i| {
                    near[i]
                        & !((u[0][i] < b[0])
                            | (u[0][i] > b[1])
                            | (u[1][i] < b[2])
                            | (u[1][i] > b[3]))
                });
                if !test.contains(&true) {
                    continue;
                }
                let (hit, t, uvw, d) = r.intersect(&self.tris[e.face as usize], t_min, &lim, test);
                // `Hit::keep_if_nearer`, lane by lane.
                let keep = lanes(|i| {
                    let nearer = (face[i] == u32::MAX)
                        | (t[i] < best[i])
                        | ((t[i] == best[i]) & (e.face < face[i]));
                    hit[i] & nearer & (t[i] < t_max)
                });
                if !keep.contains(&true) {
                    continue;
                }
                face = lanes(|i| if keep[i] { e.face } else { face[i] });
                best = lanes(|i| if keep[i] { t[i] } else { best[i] });
                t_far = lanes(|i| if keep[i] { t[i] } else { t_far[i] });
                lim = lanes(|i| if keep[i] { t[i].next_up() } else { lim[i] });
                det = lanes(|i| if keep[i] { d[i] } else { det[i] });
                edge = arr3(|k| lanes(|i| if keep[i] { uvw[k][i] } else { edge[k][i] }));
            }
        }
        let bary = arr3(|k| lanes(|i| edge[k][i] / det[i]));
        Some((face, best, bary))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raytrace::bvh::tests::soup_around;
    use crate::raytrace::rng::{Counter, Stream};

    /// A soup in clip space `(x, y, w)` in front of, across and behind the near plane, with
    /// degenerate and non-finite triangles, and some far outside the image.
    fn soup(n: usize, seed: u64) -> (Vec<V3>, Vec<[u32; 3]>) {
        let (mut pos, mut faces) = soup_around(n, seed, |c, f| {
            let w = 0.05 + 3.0 * c.uniform();
            let (x, y) = (c.uniform() * 3.0 - 1.5, c.uniform() * 3.0 - 1.5);
            ([x * w, y * w, w], if f % 7 == 0 { 1.5 } else { 0.2 })
        });
        for (f, face) in faces.iter_mut().enumerate() {
            match f % 23 {
                0 => face[1] = face[0],
                1 => pos[face[0] as usize][0] = f64::NAN,
                _ => {}
            }
        }
        // Two triangles sharing an edge through pixel corners, at one depth.
        let b = pos.len() as u32;
        pos.extend([
            [-0.5, -0.5, 1.0],
            [0.5, -0.5, 1.0],
            [0.5, 0.5, 1.0],
            [-0.5, 0.5, 1.0],
        ]);
        faces.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
        (pos, faces)
    }

    #[test]
    fn hits_are_those_of_the_bvh_inside_and_outside_the_image() {
        let (pos, faces) = soup(3000, 5);
        let (w, h, near) = (96usize, 64usize, 0.1);
        let grid = ScreenGrid::new(&pos, &faces, w, h, near);
        let bvh = Bvh::new(&pos, &faces);
        let mut c = Counter::new(2, Stream::Pixel, 7);
        let mut hits = 0;
        for k in 0..20000 {
            let u = match k % 5 {
                // Pixel corners and edges, tile borders, the image border, and beyond it.
                0 => [(c.uniform() * 97.0).floor(), (c.uniform() * 65.0).floor()],
                1 => [c.uniform() * 110.0 - 7.0, c.uniform() * 80.0 - 8.0],
                _ => [c.uniform() * 96.0, c.uniform() * 64.0],
            };
            let dir = [
                2.0 * u[0] / w as f64 - 1.0,
                1.0 - 2.0 * u[1] / h as f64,
                1.0,
            ];
            let r = Ray::new([0.0; 3], dir);
            let a = grid.closest(&r, u, near, 50.0);
            let b = bvh.closest(&r, near, 50.0);
            assert_eq!(a, b, "{u:?}");
            hits += a.is_some() as usize;
        }
        assert!(hits > 10000, "{hits}");
    }

    #[test]
    fn a_few_large_triangles_among_many_small_ones_keep_the_lists_short() {
        // 500 triangles of about a pixel and two that cover the 512 x 512 image: at the
        // small ones' 4 px tiles the two would add 2 x 16384 entries.
        let (mut pos, mut faces) = soup_around(500, 9, |c, _| {
            let (x, y) = (c.uniform() * 2.0 - 1.0, c.uniform() * 2.0 - 1.0);
            ([x, y, 1.0], 0.004)
        });
        let b = pos.len() as u32;
        pos.extend([[-3.0, -3.0, 2.0], [3.0, -3.0, 2.0], [0.0, 3.0, 2.0]]);
        pos.extend([[-3.0, 3.0, 2.5], [3.0, 3.0, 2.5], [0.0, -3.0, 2.5]]);
        faces.extend([[b, b + 1, b + 2], [b + 3, b + 4, b + 5]]);
        let (w, h) = (512usize, 512usize);
        let grid = ScreenGrid::new(&pos, &faces, w, h, 0.1);
        let tiles = grid.tiles_x * grid.tiles_y;
        assert!(grid.tile > 4.0, "{}", grid.tile);
        assert!(grid.entries.len() <= 16 * faces.len() + tiles);
        let bvh = Bvh::new(&pos, &faces);
        let mut c = Counter::new(4, Stream::Pixel, 2);
        for _ in 0..4000 {
            let u = [c.uniform() * w as f64, c.uniform() * h as f64];
            let dir = [
                2.0 * u[0] / w as f64 - 1.0,
                1.0 - 2.0 * u[1] / h as f64,
                1.0,
            ];
            let r = Ray::new([0.0; 3], dir);
            assert_eq!(grid.closest(&r, u, 0.1, 50.0), bvh.closest(&r, 0.1, 50.0));
        }
    }

    #[test]
    fn empty_scenes_and_tiny_images() {
        let grid = ScreenGrid::new(&[], &[], 1, 1, 0.1);
        let r = Ray::new([0.0; 3], [0.0, 0.0, 1.0]);
        assert!(grid.closest(&r, [0.5, 0.5], 0.1, 10.0).is_none());
        let pos = vec![[-1.0, -1.0, 1.0], [3.0, -1.0, 1.0], [-1.0, 3.0, 1.0]];
        let grid = ScreenGrid::new(&pos, &[[0, 1, 2]], 1, 1, 0.1);
        let h = grid.closest(&r, [0.5, 0.5], 0.1, 10.0).unwrap();
        assert_eq!((h.face, h.t), (0, 1.0));
    }
}
