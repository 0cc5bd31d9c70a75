//! A bounding volume hierarchy over triangles, built with the binned surface area heuristic
//! (I. Wald, "On fast construction of SAH-based bounding volume hierarchies", IEEE RT 2007:
//! 16 bins per axis over the centroids, a split where `C = A_L N_L + A_R N_R` is least, leaves
//! of at most 4 triangles or where no split beats the leaf). Subtrees of more than
//! [`PARALLEL_MIN`] triangles build their two children in parallel (`rayon::join`); the tree
//! depends only on the triangles (the split choice, the partition and the node order are the
//! same on any thread count), so traversal results are deterministic.
//!
//! No crate: `bvh` (0.10) and `bvh-arena` build over `f32` AABBs with their own shape traits,
//! so hits would be `f32` and their barycentrics would not match the watertight `f64` test; the
//! ~250 lines here keep one `f64` triangle layout shared with [`super::intersect`].

use rayon::prelude::*;

use super::intersect::{Hit, Ray, Ray8, K8, V3};
use crate::simd::{lanes, LANES};

/// Subtrees with more triangles build their children in parallel.
pub const PARALLEL_MIN: usize = 4096;
const BINS: usize = 16;
const LEAF_MAX: usize = 4;

#[derive(Clone, Copy, Debug)]
struct Aabb {
    lo: V3,
    hi: V3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };
    fn grow(&mut self, p: &V3) {
        for k in 0..3 {
            self.lo[k] = self.lo[k].min(p[k]);
            self.hi[k] = self.hi[k].max(p[k]);
        }
    }
    fn join(&mut self, o: &Aabb) {
        for k in 0..3 {
            self.lo[k] = self.lo[k].min(o.lo[k]);
            self.hi[k] = self.hi[k].max(o.hi[k]);
        }
    }
    fn area(&self) -> f64 {
        let d = [0, 1, 2].map(|k| (self.hi[k] - self.lo[k]).max(0.0));
        d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    }
}

/// One node: a box and either two children (`count == 0`; the left child follows the node,
/// the right one is at `index`) or `count` triangles from `index` in [`Bvh::order`].
#[derive(Clone, Copy, Debug)]
struct Node {
    bounds: Aabb,
    index: u32,
    count: u32,
}

/// A BVH over a triangle soup, holding its own copy of the triangles in leaf order.
#[derive(Clone, Debug)]
pub struct Bvh {
    nodes: Vec<Node>,
    /// Face index of each triangle slot.
    pub order: Vec<u32>,
    tris: Vec<[V3; 3]>,
}

#[derive(Clone, Copy)]
struct Prim {
    bounds: Aabb,
    centroid: V3,
    face: u32,
}

/// The subtree over `prims`; `scratch` (as long as `prims`) holds the partition's right side.
fn build(prims: &mut [Prim], scratch: &mut [Prim]) -> Vec<Node> {
    let mut bounds = Aabb::EMPTY;
    let mut cb = Aabb::EMPTY;
    for p in prims.iter() {
        bounds.join(&p.bounds);
        cb.grow(&p.centroid);
    }
    let leaf = |bounds| {
        vec![Node {
            bounds,
            index: 0,
            count: prims.len() as u32,
        }]
    };
    if prims.len() <= LEAF_MAX {
        return leaf(bounds);
    }
    // Binned SAH over the centroid bounds, every axis.
    let mut best: Option<(f64, usize, usize)> = None;
    for axis in 0..3 {
        let (lo, hi) = (cb.lo[axis], cb.hi[axis]);
        if !(hi > lo) {
            continue;
        }
        let scale = BINS as f64 / (hi - lo);
        let bin_of = |c: f64| (((c - lo) * scale) as usize).min(BINS - 1);
        let mut bb = [Aabb::EMPTY; BINS];
        let mut n = [0usize; BINS];
        for p in prims.iter() {
            let b = bin_of(p.centroid[axis]);
            bb[b].join(&p.bounds);
            n[b] += 1;
        }
        let mut right_area = [0.0; BINS];
        let mut acc = Aabb::EMPTY;
        let mut cnt = 0;
        let mut right_n = [0usize; BINS];
        for b in (1..BINS).rev() {
            acc.join(&bb[b]);
            cnt += n[b];
            right_area[b] = acc.area();
            right_n[b] = cnt;
        }
        let mut left = Aabb::EMPTY;
        let mut ln = 0;
        for b in 0..BINS - 1 {
            left.join(&bb[b]);
            ln += n[b];
            if ln == 0 || right_n[b + 1] == 0 {
                continue;
            }
            let cost = left.area() * ln as f64 + right_area[b + 1] * right_n[b + 1] as f64;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, b));
            }
        }
    }
    let leaf_cost = bounds.area() * prims.len() as f64;
    let Some((cost, axis, split)) = best else {
        return leaf(bounds);
    };
    if prims.len() <= 16 && cost >= leaf_cost {
        return leaf(bounds);
    }
    let (lo, hi) = (cb.lo[axis], cb.hi[axis]);
    let scale = BINS as f64 / (hi - lo);
    let goes_left = |p: &Prim| (((p.centroid[axis] - lo) * scale) as usize).min(BINS - 1) <= split;
    // Stable partition (each side in its former order, so deterministic), in linear time: the
    // left side compacts in place, the right side waits in `scratch`.
    let (mut mid, mut nr) = (0, 0);
    for i in 0..prims.len() {
        let p = prims[i];
        if goes_left(&p) {
            prims[mid] = p;
            mid += 1;
        } else {
            scratch[nr] = p;
            nr += 1;
        }
    }
    prims[mid..].copy_from_slice(&scratch[..nr]);
    let (l, r) = prims.split_at_mut(mid);
    let (sl, sr) = scratch.split_at_mut(mid);
    let (left, right) = if l.len() + r.len() > PARALLEL_MIN {
        rayon::join(|| build(l, sl), || build(r, sr))
    } else {
        (build(l, sl), build(r, sr))
    };
    let mut nodes = Vec::with_capacity(1 + left.len() + right.len());
    nodes.push(Node {
        bounds,
        index: (1 + left.len()) as u32,
        count: 0,
    });
    nodes.extend(left);
    nodes.extend(right);
    nodes
}

/// Turns the subtree-relative indices of `build` into absolute ones: child pointers get the
/// subtree's offset, leaves their first triangle slot.
fn relocate(nodes: &mut [Node]) {
    fn walk(nodes: &mut [Node], at: usize, base: usize, first: &mut u32) {
        let n = nodes[at];
        if n.count > 0 {
            nodes[at].index = *first;
            *first += n.count;
            return;
        }
        let right = at + n.index as usize;
        nodes[at].index = (base + right) as u32;
        walk(nodes, at + 1, base, first);
        walk(nodes, right, base, first);
    }
    let mut first = 0;
    if !nodes.is_empty() {
        walk(nodes, 0, 0, &mut first);
    }
}

impl Bvh {
    /// Builds the hierarchy over `faces` of `positions`. Triangles with a non-finite vertex
    /// are left out (they can never be hit).
    pub fn new(positions: &[V3], faces: &[[u32; 3]]) -> Self {
        let mut prims: Vec<Prim> = faces
            .par_iter()
            .enumerate()
            .filter_map(|(f, tri)| {
                let v = tri.map(|i| positions[i as usize]);
                if !v.iter().flatten().all(|x| x.is_finite()) {
                    return None;
                }
                let mut b = Aabb::EMPTY;
                v.iter().for_each(|p| b.grow(p));
                let c = [0, 1, 2].map(|k| (v[0][k] + v[1][k] + v[2][k]) / 3.0);
                Some(Prim {
                    bounds: b,
                    centroid: c,
                    face: f as u32,
                })
            })
            .collect();
        let mut nodes = if prims.is_empty() {
            Vec::new()
        } else {
            let mut scratch = prims.clone();
            build(&mut prims, &mut scratch)
        };
        relocate(&mut nodes);
        let order: Vec<u32> = prims.iter().map(|p| p.face).collect();
        let tris = order
            .iter()
            .map(|&f| faces[f as usize].map(|i| positions[i as usize]))
            .collect();
        Bvh { nodes, order, tris }
    }

    /// Number of triangles in the tree.
    pub fn len(&self) -> usize {
        self.order.len()
    }

    /// No triangles.
    pub fn is_empty(&self) -> bool {
        self.order.is_empty()
    }

    /// The entry distance of `r` into box `b` within `[0, t_max]`, or infinity for a miss.
    #[inline(always)]
    fn slab(b: &Aabb, r: &Ray, t_max: f64) -> f64 {
        let mut t0 = 0.0f64;
        let mut t1 = t_max;
        for k in 0..3 {
            let a = (b.lo[k] - r.origin[k]) * r.inv_dir[k];
            let c = (b.hi[k] - r.origin[k]) * r.inv_dir[k];
            // NaN (0 * inf on a slab plane) keeps the other bound: the comparisons are false.
            let (n, f) = if a <= c { (a, c) } else { (c, a) };
            t0 = if n > t0 { n } else { t0 };
            t1 = if f < t1 { f } else { t1 };
        }
        // Conservative: a small relative slack so rays grazing a box face still enter it.
        if t0 <= t1 * (1.0 + 4.0 * f64::EPSILON) {
            t0
        } else {
            f64::INFINITY
        }
    }

    /// The nearest hit with `t_min < t < t_max`; ties in `t` go to the lower face index.
    pub fn closest(&self, r: &Ray, t_min: f64, t_max: f64) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut t_far = t_max;
        self.walk(r, &mut t_far, |slot, t_far| {
            if let Some((t, bary)) = r.intersect(&self.tris[slot], t_min, t_far.next_up()) {
                let face = self.order[slot];
                if (Hit { t, bary, face }).keep_if_nearer(&mut best, t_max) {
                    *t_far = t;
                }
            }
            false
        });
        best
    }

    /// Whether anything lies on the ray with `t_min < t < t_max` (shadow rays).
    pub fn occluded(&self, r: &Ray, t_min: f64, t_max: f64) -> bool {
        let mut t_far = t_max;
        let mut hit = false;
        self.walk(r, &mut t_far, |slot, t_far| {
            hit = r.intersect(&self.tris[slot], t_min, *t_far).is_some();
            hit
        });
        hit
    }

    /// [`Bvh::slab`] lane by lane: the lanes of `m` whose ray enters `b`.
    #[inline(always)]
    fn slab8(b: &Aabb, r: &Ray8, t_max: f64, m: K8) -> K8 {
        let mut t0 = [0.0f64; LANES];
        let mut t1 = [t_max; LANES];
        for k in 0..3 {
            let a = lanes(|i| (b.lo[k] - r.origin[k][i]) * r.inv_dir[k][i]);
            let c = lanes(|i| (b.hi[k] - r.origin[k][i]) * r.inv_dir[k][i]);
            t0 = lanes(|i| {
                let n = if a[i] <= c[i] { a[i] } else { c[i] };
                if n > t0[i] {
                    n
                } else {
                    t0[i]
                }
            });
            t1 = lanes(|i| {
                let f = if a[i] <= c[i] { c[i] } else { a[i] };
                if f < t1[i] {
                    f
                } else {
                    t1[i]
                }
            });
        }
        // `t0` is never NaN (it only takes values that compare above it), so `< inf` is the
        // scalar walk's finite test, as a plain comparison.
        lanes(|i| m[i] & (t0[i] <= t1[i] * (1.0 + 4.0 * f64::EPSILON)) & (t0[i] < f64::INFINITY))
    }

    /// [`Bvh::occluded`] for the `active` rays of a packet: which are blocked. A node is
    /// visited while any lane's own slab test enters it, with the other lanes masked off, so
    /// each lane tests exactly the triangles its scalar ray would (the scalar walk's entry
    /// distance check never prunes here: nothing lowers `t_max` while looking for any hit).
    #[inline(always)]
    pub fn occluded8(&self, r: &Ray8, t_min: f64, t_max: f64, active: K8) -> K8 {
        let mut blocked = [false; LANES];
        let Some(root) = self.nodes.first() else {
            return blocked;
        };
        let t_far = [t_max; LANES];
        let mut stack = [(0u32, [false; LANES]); 64];
        stack[0] = (0, Self::slab8(&root.bounds, r, t_max, active));
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            let (at, m) = stack[sp];
            let m = lanes(|i| m[i] & !blocked[i]);
            if !m.contains(&true) {
                continue;
            }
            let n = &self.nodes[at as usize];
            if n.count > 0 {
                for slot in n.index..n.index + n.count {
                    let live = lanes(|i| m[i] & !blocked[i]);
                    if !live.contains(&true) {
                        break;
                    }
                    let (hit, ..) = r.intersect(&self.tris[slot as usize], t_min, &t_far, live);
                    blocked = lanes(|i| blocked[i] | hit[i]);
                }
                continue;
            }
            for c in [at + 1, n.index] {
                let mc = Self::slab8(&self.nodes[c as usize].bounds, r, t_max, m);
                if mc.contains(&true) && sp < stack.len() {
                    stack[sp] = (c, mc);
                    sp += 1;
                }
            }
        }
        blocked
    }

    /// Front-to-back traversal; `leaf(slot, t_far)` returns true to stop. Each stacked node
    /// keeps its entry distance, so a subtree beyond the nearest hit found since it was pushed
    /// is skipped without touching it.
    #[inline]
    fn walk(&self, r: &Ray, t_far: &mut f64, mut leaf: impl FnMut(usize, &mut f64) -> bool) {
        if self.nodes.is_empty() || Self::slab(&self.nodes[0].bounds, r, *t_far).is_infinite() {
            return;
        }
        // The triangles of leaf `n`; true when `leaf` asks to stop.
        let mut scan = |n: &Node, t_far: &mut f64| {
            (n.index..n.index + n.count).any(|slot| leaf(slot as usize, t_far))
        };
        if self.nodes[0].count > 0 {
            // A one-leaf tree (a few triangles): no stack to set up.
            scan(&self.nodes[0], t_far);
            return;
        }
        let mut stack = [(0u32, 0.0f64); 64];
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            let (at, t_in) = stack[sp];
            if t_in > *t_far * (1.0 + 4.0 * f64::EPSILON) {
                continue;
            }
            let n = &self.nodes[at as usize];
            if n.count > 0 {
                if scan(n, t_far) {
                    return;
                }
                continue;
            }
            let (l, rr) = (at + 1, n.index);
            let tl = Self::slab(&self.nodes[l as usize].bounds, r, *t_far);
            let tr = Self::slab(&self.nodes[rr as usize].bounds, r, *t_far);
            // Push the farther child first so that the nearer one is visited first.
            let (near, far) = if tl <= tr {
                ((l, tl), (rr, tr))
            } else {
                ((rr, tr), (l, tl))
            };
            for c in [far, near] {
                if c.1.is_finite() && sp < stack.len() {
                    stack[sp] = c;
                    sp += 1;
                }
            }
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::raytrace::rng::{Counter, Stream};

    /// `n` random triangles `[3f, 3f + 1, 3f + 2]`: triangle `f`'s vertices lie within
    /// `size / 2` of `centre` per axis, `(centre, size) = place(numbers, f)`.
    pub(crate) fn soup_around(
        n: usize,
        seed: u64,
        mut place: impl FnMut(&mut Counter, usize) -> (V3, f64),
    ) -> (Vec<V3>, Vec<[u32; 3]>) {
        let mut c = Counter::new(seed, Stream::Pixel, 0);
        let mut pos = Vec::new();
        let mut faces = Vec::new();
        for f in 0..n {
            let (centre, size) = place(&mut c, f);
            for _ in 0..3 {
                pos.push([0, 1, 2].map(|k| centre[k] + size * (c.uniform() - 0.5)));
            }
            let b = 3 * f as u32;
            faces.push([b, b + 1, b + 2]);
        }
        (pos, faces)
    }

    fn soup(n: usize, seed: u64) -> (Vec<V3>, Vec<[u32; 3]>) {
        soup_around(n, seed, |c, _| {
            ([0, 1, 2].map(|_| c.uniform() * 4.0 - 2.0), 0.3)
        })
    }

    fn brute(pos: &[V3], faces: &[[u32; 3]], r: &Ray) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        for (f, tri) in faces.iter().enumerate() {
            let v = tri.map(|i| pos[i as usize]);
            if let Some((t, bary)) = r.intersect(&v, 1e-9, f64::INFINITY) {
                if best.is_none_or(|b| t < b.t) {
                    best = Some(Hit {
                        t,
                        bary,
                        face: f as u32,
                    });
                }
            }
        }
        best
    }

    #[test]
    fn closest_and_occluded_agree_with_brute_force_for_any_thread_count() {
        let (pos, faces) = soup(6000, 3);
        let bvh = Bvh::new(&pos, &faces);
        assert_eq!(bvh.len(), faces.len());
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let bvh1 = one.install(|| Bvh::new(&pos, &faces));
        assert_eq!(bvh1.order, bvh.order);
        let mut c = Counter::new(1, Stream::Pixel, 1);
        for _ in 0..400 {
            let o = [c.uniform() * 8.0 - 4.0, c.uniform() * 8.0 - 4.0, 5.0];
            let d = [c.uniform() - 0.5, c.uniform() - 0.5, -1.0];
            let r = Ray::new(o, d);
            let a = bvh.closest(&r, 1e-9, f64::INFINITY);
            let b = brute(&pos, &faces, &r);
            assert_eq!(a.map(|h| (h.face, h.t)), b.map(|h| (h.face, h.t)));
            assert_eq!(bvh.occluded(&r, 1e-9, f64::INFINITY), b.is_some());
            if let Some(h) = b {
                assert!(!bvh.occluded(&r, 1e-9, h.t * (1.0 - 1e-9)) || a.is_some());
            }
        }
    }

    #[test]
    fn empty_and_non_finite_inputs() {
        let bvh = Bvh::new(&[], &[]);
        assert!(bvh.is_empty());
        let r = Ray::new([0.0; 3], [0.0, 0.0, 1.0]);
        assert!(bvh.closest(&r, 0.0, 1.0).is_none());
        let pos = vec![[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [f64::NAN, 1.0, 1.0]];
        let bvh = Bvh::new(&pos, &[[0, 1, 2]]);
        assert!(bvh.is_empty());
    }
}
