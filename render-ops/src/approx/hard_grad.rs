//! The exact gradient of the hard render ([`super::render_hard`]: per covered pixel
//! `I_p = sum_k b_k A[f_k]` from its nearest fragment) with respect to the attributes and,
//! with the visibility held fixed, the clip positions, in one pass over the fragments.
//!
//! `dL/dA[f_k] = sum_p b_k dL/dI_p` is exact. For the positions, `dL/db_k = dL/dI_p . A[f_k]`
//! goes through the rasterizer's barycentric backward (the interior gradient of
//! [`crate::raster::rasterize_backward`]), whose per-fragment products are summed per face in
//! the factored form of [`RunVjp`] and multiplied out once per face ([`FaceVjp::finish`]).
//!
//! Fragments are visited in fixed chunks of [`CHUNK`] in parallel. Within a chunk, each face
//! sums its fragments' factors in fragment order (its setup and the final product are made
//! once per face and chunk, however many runs of pixels the face has in it: on fine meshes
//! most runs are one or two pixels long), then each vertex sums its faces' contributions in
//! the order the faces were first met; every vertex then adds the chunks' sums in chunk order
//! (parallel over vertex blocks, [`scatter_vertex_rows`]). The chunking does not depend on the
//! number of threads, so the result is bit-identical for any number of threads.
//!
//! For 1 and 3 channels ([`chunk_sums`]), the face of the current run of fragments keeps its
//! sums in fixed-size locals ([`OpenFace`]) and writes them back when the face changes: the
//! same additions in the same order as the general loop ([`chunk_sums_dyn`]), without its
//! per-fragment indexing into the scratch; that loop is built with AVX2 where the CPU has it.
//!
//! With screen-space barycentrics (`persp = false`, DEODR's setting) the barycentrics are
//! affine in the pixel, so a face only sums its fragments' moments `sum (px, py, 1) dL/dI`,
//! and its factor sums and `dL/dA` are made from them once per face and chunk
//! ([`affine_factors`]).

use autodiff::Real;
use rayon::prelude::*;

use crate::raster::{FaceVjp, Fragments, PixelCursor, RunSetup, RunVjp};
use crate::scatter::{scatter_vertex_rows, IndexMap};
use crate::simd::use_avx2;

/// Fragments per parallel chunk.
const CHUNK: usize = 4096;

/// The gradients of the hard render, in `f64`: `dL/dclip` `[V]` and `dL/dA` `[V * C]`, each
/// only when asked for.
pub(crate) struct HardGrad {
    pub pos: Option<Vec<[f64; 4]>>,
    pub attr: Option<Vec<f64>>,
}

/// What one chunk contributes: the vertices its fragments' faces reach, in order of first
/// touch, and per vertex its `dL/dclip` and its `dL/dA` (`C` values), each when asked for.
struct ChunkSums {
    verts: Vec<u32>,
    pos: Vec<[f64; 4]>,
    attr: Vec<f64>,
}

/// Per-thread scratch of the chunks: the faces met in the chunk (in order of first touch)
/// with their setup, factor sums, attributes (`3 * C`, for the positions) and `dL/dA` (`3 *
/// C`), and the maps from face and vertex indices to their entries.
struct Scratch {
    face_ix: IndexMap,
    vert_ix: IndexMap,
    face: Vec<u32>,
    fv: Vec<FaceVjp>,
    acc: Vec<RunVjp>,
    a_face: Vec<f64>,
    ga: Vec<f64>,
    /// With screen-space barycentrics (`persp = false`): per face its fragments' moments
    /// `sum ptilde_j dL/dI_ch` (`3 * C`, `ptilde = (px, py, 1)`), from which
    /// [`affine_factors`] makes its factor sums and `dL/dA` once per face and chunk.
    mom: Vec<f64>,
    /// Per face: whether its `dL/dA` is summed per fragment from the stored barycentrics
    /// (perspective-correct barycentrics, or a face without a usable inverse), not from
    /// its moments.
    per_frag_b: Vec<bool>,
}

impl Scratch {
    fn new() -> Self {
        Scratch {
            // Grown as needed (a chunk of small faces meets a few hundred).
            face_ix: IndexMap::new(256),
            vert_ix: IndexMap::new(512),
            face: Vec::with_capacity(256),
            fv: Vec::with_capacity(256),
            acc: Vec::with_capacity(256),
            a_face: Vec::with_capacity(256 * 9),
            ga: Vec::with_capacity(256 * 9),
            mom: Vec::with_capacity(256 * 9),
            per_frag_b: Vec::with_capacity(256),
        }
    }

    /// The entry of face `fi` (`c` channels), made (zeroed sums, its setup and attributes)
    /// at its first fragment in the chunk.
    #[inline(always)]
    fn entry<T: Real>(&mut self, inp: &Inputs<'_, T>, fi: u32, c: usize) -> usize {
        let (e, new) = self.face_ix.index(fi);
        if new {
            let f = inp.faces[fi as usize];
            let v = f.map(|vi| inp.clip[vi as usize].map(|x| x.to_f64c()));
            let fv = FaceVjp::new(&v);
            self.face.push(fi);
            self.per_frag_b.push(inp.persp || !fv.invertible());
            self.fv.push(fv);
            self.acc.push(RunVjp::default());
            if inp.need_pos {
                for vi in f {
                    let a = &inp.attrs[vi as usize * c..][..c];
                    self.a_face.extend(a.iter().map(|x| x.to_f64c()));
                }
            }
            if inp.need_attr {
                self.ga.resize(self.ga.len() + 3 * c, 0.0);
            }
            if inp.moments() {
                self.mom.resize(self.mom.len() + 3 * c, 0.0);
            }
        }
        e
    }

    fn clear(&mut self) {
        self.face_ix.clear();
        self.vert_ix.clear();
        self.face.clear();
        self.fv.clear();
        self.acc.clear();
        self.a_face.clear();
        self.ga.clear();
        self.mom.clear();
        self.per_frag_b.clear();
    }
}

/// The inputs of one backward.
struct Inputs<'a, T> {
    clip: &'a [[T; 4]],
    faces: &'a [[u32; 3]],
    frags: &'a Fragments<T>,
    /// `[V * C]`.
    attrs: &'a [T],
    /// `dL/dI`, `[H * W * (C + 1)]` (the last channel, coverage, has no gradient to pass).
    g: &'a [T],
    /// Pixels (increasing) whose `dL/dI` is replaced, and their `C + 1` values each.
    over_pix: &'a [u32],
    over_val: &'a [f64],
    c: usize,
    persp: bool,
    need_pos: bool,
    need_attr: bool,
}

impl<T> Inputs<'_, T> {
    /// Whether the fragments' moments are summed (screen-space barycentrics, some gradient
    /// asked for): see [`affine_factors`].
    #[inline(always)]
    fn moments(&self) -> bool {
        !self.persp && (self.need_pos || self.need_attr)
    }
}

/// The gradient of the hard render of `attrs` (`[V * C]`) over `frags` (rasterized from
/// `clip` with `perspective_correct = persp`) for the image gradient `g` (`[H * W * (C + 1)]`),
/// replaced at the pixels of `over` (increasing pixel indices, `C + 1` values each). Only each
/// pixel's nearest fragment is used, as in the render.
#[allow(clippy::too_many_arguments)]
pub(crate) fn hard_grad<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    frags: &Fragments<T>,
    attrs: &[T],
    c: usize,
    g: &[T],
    over: (&[u32], &[f64]),
    persp: bool,
    need_pos: bool,
    need_attr: bool,
) -> HardGrad {
    let inp = Inputs {
        clip,
        faces,
        frags,
        attrs,
        g,
        over_pix: over.0,
        over_val: over.1,
        c,
        persp,
        need_pos,
        need_attr,
    };
    let n = frags.len();
    let avx2 = use_avx2();
    let chunks: Vec<ChunkSums> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map_init(Scratch::new, |sc, ci| {
            let (i0, i1) = (ci * CHUNK, ((ci + 1) * CHUNK).min(n));
            match (c, avx2) {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `avx2` says the CPU has AVX2.
                (3, true) => unsafe { chunk_sums_avx2::<T, 3>(&inp, sc, i0, i1) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: as above.
                (1, true) => unsafe { chunk_sums_avx2::<T, 1>(&inp, sc, i0, i1) },
                (3, _) => chunk_sums::<T, 3>(&inp, sc, i0, i1),
                (1, _) => chunk_sums::<T, 1>(&inp, sc, i0, i1),
                _ => chunk_sums_dyn(&inp, sc, i0, i1),
            }
        })
        .collect();
    let nv = clip.len();
    // The chunks' per-vertex sums, added in chunk order.
    let pos = need_pos.then(|| {
        let mut acc = vec![[0.0f64; 4]; nv];
        scatter_vertex_rows(acc.as_flattened_mut(), 4, || {
            chunks.iter().flat_map(|ch| {
                ch.verts
                    .iter()
                    .copied()
                    .zip(ch.pos.iter().map(|g| g.as_slice()))
            })
        });
        acc
    });
    let attr = need_attr.then(|| {
        let mut acc = vec![0.0f64; nv * c];
        scatter_vertex_rows(&mut acc, c, || {
            chunks
                .iter()
                .flat_map(|ch| ch.verts.iter().copied().zip(ch.attr.chunks_exact(c.max(1))))
        });
        acc
    });
    HardGrad { pos, attr }
}

/// The running sums of the face whose fragments are being visited ([`chunk_sums`]), kept in
/// locals while consecutive fragments belong to it, and its setup and attributes.
struct OpenFace<const C: usize> {
    /// The face (`u32::MAX`: none yet; [`IndexMap`] keys cannot be `u32::MAX` either).
    face: u32,
    /// Its entry in the scratch.
    e: usize,
    fv: RunSetup,
    /// The factor sums: the entry's `sc.acc[e]`, plus the fragments visited since opening.
    acc: RunVjp,
    /// The attributes of its three vertices (for the positions).
    a: [[f64; C]; 3],
    /// `dL/dA` of its three vertices: the entry's `sc.ga`, plus the fragments since opening.
    ga: [[f64; C]; 3],
    /// The moments (`persp = false`): the entry's `sc.mom`, plus the fragments since opening.
    mom: [[f64; C]; 3],
    /// The entry's `sc.per_frag_b`.
    per_frag_b: bool,
}

impl<const C: usize> OpenFace<C> {
    /// No face yet.
    fn none() -> Self {
        OpenFace {
            face: u32::MAX,
            e: 0,
            fv: FaceVjp::new(&[[0.0; 4]; 3]).run_setup(),
            acc: RunVjp::default(),
            a: [[0.0; C]; 3],
            ga: [[0.0; C]; 3],
            mom: [[0.0; C]; 3],
            per_frag_b: false,
        }
    }

    /// Writes the running sums back to the face's entry and opens face `fi`: its entry in
    /// the scratch (a new one, zeroed, at its first fragment in the chunk), and its running
    /// sums from there.
    #[inline(never)]
    fn switch<T: Real>(&mut self, inp: &Inputs<'_, T>, sc: &mut Scratch, fi: u32) {
        self.close(inp, sc);
        let e = sc.entry(inp, fi, C);
        self.face = fi;
        self.e = e;
        self.per_frag_b = sc.per_frag_b[e];
        if inp.need_pos && inp.persp {
            self.fv = sc.fv[e].run_setup();
            self.acc = sc.acc[e];
            self.a
                .as_flattened_mut()
                .copy_from_slice(&sc.a_face[e * 3 * C..][..3 * C]);
        }
        if inp.need_attr && self.per_frag_b {
            self.ga
                .as_flattened_mut()
                .copy_from_slice(&sc.ga[e * 3 * C..][..3 * C]);
        }
        if inp.moments() {
            self.mom
                .as_flattened_mut()
                .copy_from_slice(&sc.mom[e * 3 * C..][..3 * C]);
        }
    }

    /// Writes the running sums back to the face's entry.
    #[inline(always)]
    fn close(&self, inp: &Inputs<'_, impl Real>, sc: &mut Scratch) {
        if self.face == u32::MAX {
            return;
        }
        if inp.need_pos && inp.persp {
            sc.acc[self.e] = self.acc;
        }
        if inp.need_attr && self.per_frag_b {
            sc.ga[self.e * 3 * C..][..3 * C].copy_from_slice(self.ga.as_flattened());
        }
        if inp.moments() {
            sc.mom[self.e * 3 * C..][..3 * C].copy_from_slice(self.mom.as_flattened());
        }
    }
}

/// [`chunk_sums`] built with AVX2 (three-operand instructions and wider registers: fewer
/// moves for the same arithmetic, so the same bits; no FMA).
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn chunk_sums_avx2<T: Real, const C: usize>(
    inp: &Inputs<'_, T>,
    sc: &mut Scratch,
    i0: usize,
    i1: usize,
) -> ChunkSums {
    chunk_sums::<T, C>(inp, sc, i0, i1)
}

/// The per-vertex sums of fragments `i0..i1`, for `C` channels.
///
/// The face of the current run of fragments is held in an [`OpenFace`] (its setup, factor
/// sums, attributes and `dL/dA` sums in fixed-size locals, not in the scratch's vectors), and
/// written back to its entry when a fragment of another face comes: each face's sums still
/// start from its entry's and add its fragments in fragment order, as in [`chunk_sums_dyn`].
#[inline(always)]
fn chunk_sums<T: Real, const C: usize>(
    inp: &Inputs<'_, T>,
    sc: &mut Scratch,
    i0: usize,
    i1: usize,
) -> ChunkSums {
    let fr = inp.frags;
    sc.clear();
    let offsets = &fr.offsets[..];
    let (faces, bary) = (&fr.face[i0..i1], &fr.bary[i0..i1]);
    let mut px_at = PixelCursor::new(fr, i0);
    let mut cur = OpenFace::<C>::none();
    // The first replaced pixel not before the pixels seen so far: its index `ov` into
    // `over_pix` and its pixel `next_over` (`usize::MAX` when none). Pixels before it take
    // `dL/dI` from `g` after one comparison.
    let mut ov = inp.over_pix.partition_point(|&q| (q as usize) < px_at.p);
    let over_at = |ov: usize| inp.over_pix.get(ov).map_or(usize::MAX, |&q| q as usize);
    let mut next_over = over_at(ov);
    for (i, (&fi, b)) in (i0..i1).zip(faces.iter().zip(bary)) {
        px_at.advance(offsets, i);
        let p = px_at.p;
        if offsets[p] as usize != i {
            // Not the pixel's nearest fragment: the render does not show it.
            continue;
        }
        if fi != cur.face {
            cur.switch(inp, sc, fi);
        }
        // `dL/dI` of the pixel in `f64`.
        let gp: [f64; C] = if p < next_over {
            let g = &inp.g[p * (C + 1)..][..C];
            std::array::from_fn(|ch| g[ch].to_f64c())
        } else {
            while ov < inp.over_pix.len() && (inp.over_pix[ov] as usize) < p {
                ov += 1;
            }
            next_over = over_at(ov);
            if next_over == p {
                let g = &inp.over_val[ov * (C + 1)..][..C];
                std::array::from_fn(|ch| g[ch])
            } else {
                let g = &inp.g[p * (C + 1)..][..C];
                std::array::from_fn(|ch| g[ch].to_f64c())
            }
        };
        if inp.moments() {
            let [x, y] = px_at.ndc();
            for ch in 0..C {
                cur.mom[0][ch] += x * gp[ch];
                cur.mom[1][ch] += y * gp[ch];
                cur.mom[2][ch] += gp[ch];
            }
        }
        if inp.need_attr && cur.per_frag_b {
            let b = b.map(|x| x.to_f64c());
            for (row, bk) in cur.ga.iter_mut().zip(b) {
                for (o, g) in row.iter_mut().zip(gp) {
                    *o += bk * g;
                }
            }
        }
        if inp.need_pos && inp.persp {
            let mut gb = [0.0; 3];
            for (gk, a) in gb.iter_mut().zip(&cur.a) {
                for (g, a) in gp.iter().zip(a) {
                    *gk += g * a;
                }
            }
            cur.fv.accumulate(&mut cur.acc, px_at.ndc(), gb, inp.persp);
        }
    }
    cur.close(inp, sc);
    affine_factors(inp, sc, C);
    vertex_sums::<T, C>(inp, sc)
}

/// The per-vertex sums of fragments `i0..i1` for a channel count known only at run time
/// (`inp.c`; [`chunk_sums`] is the same for a fixed count).
fn chunk_sums_dyn<T: Real>(
    inp: &Inputs<'_, T>,
    sc: &mut Scratch,
    i0: usize,
    i1: usize,
) -> ChunkSums {
    let c = inp.c;
    let fr = inp.frags;
    sc.clear();
    // The face of the previous fragment and its entry: runs of one face skip the map.
    let mut cur: Option<(u32, usize)> = None;
    let mut px_at = PixelCursor::new(fr, i0);
    // `dL/dI` of the current pixel in `f64`.
    let mut gpf = vec![0.0f64; c];
    // The next replaced pixel at or after `p`.
    let mut ov = inp.over_pix.partition_point(|&q| (q as usize) < px_at.p);
    for i in i0..i1 {
        px_at.advance(&fr.offsets, i);
        let p = px_at.p;
        if fr.offsets[p] as usize != i {
            // Not the pixel's nearest fragment: the render does not show it.
            continue;
        }
        let fi = fr.face[i];
        let e = match cur {
            Some((cf, e)) if cf == fi => e,
            _ => {
                let e = sc.entry(inp, fi, c);
                cur = Some((fi, e));
                e
            }
        };
        while ov < inp.over_pix.len() && (inp.over_pix[ov] as usize) < p {
            ov += 1;
        }
        if ov < inp.over_pix.len() && inp.over_pix[ov] as usize == p {
            gpf.copy_from_slice(&inp.over_val[ov * (c + 1)..][..c]);
        } else {
            for (o, x) in gpf.iter_mut().zip(&inp.g[p * (c + 1)..][..c]) {
                *o = x.to_f64c();
            }
        }
        if inp.moments() {
            let [x, y] = px_at.ndc();
            let m = &mut sc.mom[e * 3 * c..][..3 * c];
            for (ch, g) in gpf.iter().enumerate() {
                m[ch] += x * g;
                m[c + ch] += y * g;
                m[2 * c + ch] += g;
            }
        }
        if inp.need_attr && sc.per_frag_b[e] && c > 0 {
            let b = fr.bary[i].map(|x| x.to_f64c());
            for (row, bk) in sc.ga[e * 3 * c..][..3 * c].chunks_exact_mut(c).zip(b) {
                for (o, g) in row.iter_mut().zip(&gpf) {
                    *o += bk * g;
                }
            }
        }
        if inp.need_pos && inp.persp {
            let mut gb = [0.0; 3];
            if c > 0 {
                for (gk, a) in gb
                    .iter_mut()
                    .zip(sc.a_face[e * 3 * c..][..3 * c].chunks_exact(c))
                {
                    for (g, a) in gpf.iter().zip(a) {
                        *gk += g * a;
                    }
                }
            }
            let px = px_at.ndc();
            sc.fv[e].accumulate(&mut sc.acc[e], px, gb, inp.persp);
        }
    }
    affine_factors(inp, sc, c);
    vertex_sums::<T, 0>(inp, sc)
}

/// With screen-space barycentrics (`persp = false`), each face's factor sums and `dL/dA`
/// from its fragments' moments (`sc.mom`, `c` channels), once per face and chunk instead of
/// per fragment. The barycentrics are affine in the pixel, `b_k = w_k u_k` with `u = M^-1
/// ptilde` ([`FaceVjp::screen_bary_sums`]), and `dL/dbary_i = sum_ch dL/dI_ch A_i,ch` is linear
/// in `dL/dI`: so `sum_frag b_k dL/dI_ch` and the per-fragment products of
/// [`crate::raster::RunSetup::accumulate`] are linear maps of the moments (the same sums,
/// added in another order; `T[j][i] = sum_ch mom[j][ch] A_i,ch` for the latter,
/// [`crate::raster::RunSetup::affine_sums`]). A face without a usable inverse gets no
/// position gradient ([`FaceVjp::finish`]) and sums its `dL/dA` per fragment instead.
fn affine_factors<T>(inp: &Inputs<'_, T>, sc: &mut Scratch, c: usize) {
    if !inp.moments() {
        return;
    }
    for e in 0..sc.face.len() {
        if sc.per_frag_b[e] {
            continue;
        }
        let mom = &sc.mom[e * 3 * c..][..3 * c];
        let fv = &sc.fv[e];
        if inp.need_pos {
            let a = &sc.a_face[e * 3 * c..][..3 * c];
            let t: [[f64; 3]; 3] = std::array::from_fn(|j| {
                std::array::from_fn(|i| {
                    let (m, a) = (&mom[j * c..][..c], &a[i * c..][..c]);
                    m.iter().zip(a).fold(0.0, |s, (m, a)| s + m * a)
                })
            });
            sc.acc[e] = fv.run_setup().affine_sums(&t);
        }
        if inp.need_attr {
            let ga = &mut sc.ga[e * 3 * c..][..3 * c];
            for ch in 0..c {
                let b = fv.screen_bary_sums([mom[ch], mom[c + ch], mom[2 * c + ch]]);
                for k in 0..3 {
                    ga[k * c + ch] = b[k];
                }
            }
        }
    }
}

/// The chunk's per-vertex sums from its faces' entries in `sc`: each face's `dL/dclip`
/// ([`FaceVjp::finish`]) and `dL/dA` added into its vertices' rows, faces in order of first
/// touch.
fn vertex_sums<T, const C: usize>(inp: &Inputs<'_, T>, sc: &mut Scratch) -> ChunkSums {
    let c = if C > 0 { C } else { inp.c };
    let nf = sc.face.len();
    let mut out = ChunkSums {
        verts: Vec::with_capacity(2 * nf),
        pos: Vec::with_capacity(if inp.need_pos { 2 * nf } else { 0 }),
        attr: Vec::with_capacity(if inp.need_attr { 2 * nf * c } else { 0 }),
    };
    for (e, &fi) in sc.face.iter().enumerate() {
        let pos = if inp.need_pos {
            sc.fv[e].finish(&sc.acc[e], inp.persp)
        } else {
            [[0.0; 4]; 3]
        };
        let f = inp.faces[fi as usize];
        for m in 0..3 {
            let (k, new) = sc.vert_ix.index(f[m]);
            if new {
                out.verts.push(f[m]);
                if inp.need_pos {
                    out.pos.push([0.0; 4]);
                }
                if inp.need_attr {
                    out.attr.resize(out.attr.len() + c, 0.0);
                }
            }
            if inp.need_pos {
                let o = &mut out.pos[k];
                for j in 0..4 {
                    o[j] += pos[m][j];
                }
            }
            if inp.need_attr {
                let o = &mut out.attr[k * c..][..c];
                let g = &sc.ga[(e * 3 + m) * c..][..c];
                for ch in 0..c {
                    o[ch] += g[ch];
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::Mesh;
    use crate::raster::{rasterize_fragments, RasterSettings};

    /// A sphere of 1280 faces in clip space: `x` scaled by `sx`, `w = wz z + w0`.
    fn sphere_clip(sx: f64, wz: f64, w0: f64) -> (Mesh<f64>, Vec<[f64; 4]>) {
        let mesh = Mesh::<f64>::icosphere(3, 0.9);
        let clip = mesh
            .positions
            .iter()
            .map(|p| [p[0] * sx, p[1] + 0.05, p[2] * 0.4 + 0.5, p[2] * wz + w0])
            .collect();
        (mesh, clip)
    }

    /// Chunk sums, as bits.
    fn bits(s: &ChunkSums) -> (Vec<u32>, Vec<u64>, Vec<u64>) {
        let f = |x: &f64| x.to_bits();
        let pos = s.pos.as_flattened().iter().map(f).collect();
        (s.verts.clone(), pos, s.attr.iter().map(f).collect())
    }

    /// The fixed-channel loop ([`chunk_sums`], and its AVX2 build where the CPU has AVX2)
    /// gives the same bits as the run-time-channel one ([`chunk_sums_dyn`]) on every chunk:
    /// 1 and 3 channels, screen-space and perspective-correct barycentrics, one and two
    /// fragments per pixel, some pixels' `dL/dI` replaced.
    #[test]
    fn fixed_channel_loop_matches_the_general_one() {
        let (mesh, clip) = sphere_clip(1.0, 0.2, 1.2);
        let nv = clip.len();
        let (w, h) = (150, 131);
        let wave = |i: usize, s: f64| ((i as f64 * s).sin() * 0.7) as f32;
        for k in [1, 2] {
            for persp in [false, true] {
                let s = RasterSettings {
                    faces_per_pixel: k,
                    perspective_correct: persp,
                    ..RasterSettings::new(w, h)
                };
                let clip32: Vec<[f32; 4]> = clip.iter().map(|v| v.map(|x| x as f32)).collect();
                let frags = rasterize_fragments(&clip32, &mesh.faces, &s).unwrap();
                assert!(frags.len() > CHUNK, "several chunks");
                for c in [1, 3] {
                    let attrs: Vec<f32> = (0..nv * c).map(|i| wave(i, 0.37)).collect();
                    let g: Vec<f32> = (0..w * h * (c + 1)).map(|i| wave(i, 1.3)).collect();
                    let over_pix: Vec<u32> = (0..w * h).step_by(7).map(|p| p as u32).collect();
                    let over_val: Vec<f64> = (0..over_pix.len() * (c + 1))
                        .map(|i| f64::from(wave(i, 0.9)))
                        .collect();
                    let inp = Inputs {
                        clip: &clip32,
                        faces: &mesh.faces,
                        frags: &frags,
                        attrs: &attrs,
                        g: &g,
                        over_pix: &over_pix,
                        over_val: &over_val,
                        c,
                        persp,
                        need_pos: true,
                        need_attr: true,
                    };
                    let mut sc = Scratch::new();
                    let n = frags.len();
                    for i0 in (0..n).step_by(CHUNK) {
                        let i1 = (i0 + CHUNK).min(n);
                        let want = bits(&chunk_sums_dyn(&inp, &mut sc, i0, i1));
                        let got = bits(&match c {
                            3 => chunk_sums::<f32, 3>(&inp, &mut sc, i0, i1),
                            _ => chunk_sums::<f32, 1>(&inp, &mut sc, i0, i1),
                        });
                        assert!(got == want, "k {k} persp {persp} c {c} chunk {i0}");
                        #[cfg(target_arch = "x86_64")]
                        if std::arch::is_x86_feature_detected!("avx2") {
                            // SAFETY: the CPU has AVX2.
                            let got = bits(&unsafe {
                                match c {
                                    3 => chunk_sums_avx2::<f32, 3>(&inp, &mut sc, i0, i1),
                                    _ => chunk_sums_avx2::<f32, 1>(&inp, &mut sc, i0, i1),
                                }
                            });
                            assert!(got == want, "AVX2: k {k} persp {persp} c {c} chunk {i0}");
                        }
                    }
                }
            }
        }
    }

    /// With screen-space barycentrics the moment form ([`affine_factors`]) gives the sums of
    /// the per-fragment definition (`dL/dA_k += b_k dL/dI` with the stored barycentrics,
    /// [`FaceVjp::accumulate`] per fragment) to rounding, in `f64`, for 1, 2 and 3 channels
    /// (fixed and run-time loops), with some pixels' `dL/dI` replaced.
    #[test]
    fn moments_give_the_per_fragment_sums() {
        let (mesh, clip) = sphere_clip(1.3, 0.3, 1.4);
        let nv = clip.len();
        let (w, h) = (97, 83);
        let wave = |i: usize, s: f64| (i as f64 * s).sin() * 0.7;
        let s = RasterSettings {
            perspective_correct: false,
            ..RasterSettings::new(w, h)
        };
        let frags = rasterize_fragments(&clip, &mesh.faces, &s).unwrap();
        let n = frags.len();
        for c in [1, 2, 3] {
            let attrs: Vec<f64> = (0..nv * c).map(|i| wave(i, 0.37)).collect();
            let g: Vec<f64> = (0..w * h * (c + 1)).map(|i| wave(i, 1.3)).collect();
            let over_pix: Vec<u32> = (0..w * h).step_by(5).map(|p| p as u32).collect();
            let over_val: Vec<f64> = (0..over_pix.len() * (c + 1))
                .map(|i| wave(i, 0.9))
                .collect();
            let inp = Inputs {
                clip: &clip,
                faces: &mesh.faces,
                frags: &frags,
                attrs: &attrs,
                g: &g,
                over_pix: &over_pix,
                over_val: &over_val,
                c,
                persp: false,
                need_pos: true,
                need_attr: true,
            };
            // The per-fragment definition, per vertex.
            let (mut want_pos, mut want_attr) = (vec![[0.0f64; 4]; nv], vec![0.0f64; nv * c]);
            let mut px_at = PixelCursor::new(&frags, 0);
            for i in 0..n {
                px_at.advance(&frags.offsets, i);
                let p = px_at.p;
                if frags.offsets[p] as usize != i {
                    continue;
                }
                let gp: Vec<f64> = match over_pix.binary_search(&(p as u32)) {
                    Ok(k) => over_val[k * (c + 1)..][..c].to_vec(),
                    Err(_) => g[p * (c + 1)..][..c].to_vec(),
                };
                let f = mesh.faces[frags.face[i] as usize];
                let fv = FaceVjp::new(&f.map(|v| clip[v as usize]));
                let gb = f.map(|v| (0..c).map(|ch| gp[ch] * attrs[v as usize * c + ch]).sum());
                let mut acc = RunVjp::default();
                fv.accumulate(&mut acc, px_at.ndc(), gb, false);
                for (m, d) in fv.finish(&acc, false).iter().enumerate() {
                    for j in 0..4 {
                        want_pos[f[m] as usize][j] += d[j];
                    }
                    for ch in 0..c {
                        want_attr[f[m] as usize * c + ch] += frags.bary[i][m] * gp[ch];
                    }
                }
            }
            let mut sc = Scratch::new();
            let (mut got_pos, mut got_attr) = (vec![[0.0f64; 4]; nv], vec![0.0f64; nv * c]);
            for i0 in (0..n).step_by(CHUNK / 4) {
                let i1 = (i0 + CHUNK / 4).min(n);
                let sums = match c {
                    3 => chunk_sums::<f64, 3>(&inp, &mut sc, i0, i1),
                    1 => chunk_sums::<f64, 1>(&inp, &mut sc, i0, i1),
                    _ => chunk_sums_dyn(&inp, &mut sc, i0, i1),
                };
                for (k, &v) in sums.verts.iter().enumerate() {
                    for j in 0..4 {
                        got_pos[v as usize][j] += sums.pos[k][j];
                    }
                    for ch in 0..c {
                        got_attr[v as usize * c + ch] += sums.attr[k * c + ch];
                    }
                }
            }
            let close = |a: &[f64], b: &[f64]| {
                let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                assert!(scale > 0.0);
                a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-10 * scale)
            };
            assert!(
                close(got_pos.as_flattened(), want_pos.as_flattened()),
                "pos, c {c}"
            );
            assert!(close(&got_attr, &want_attr), "attr, c {c}");
        }
    }
}
