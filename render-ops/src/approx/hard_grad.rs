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

use autodiff::Real;
use rayon::prelude::*;

use crate::raster::{FaceVjp, Fragments, PixelCursor, RunVjp};
use crate::scatter::{scatter_vertex_rows, IndexMap};

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
}

impl Scratch {
    fn new() -> Self {
        Scratch {
            face_ix: IndexMap::new(CHUNK),
            vert_ix: IndexMap::new(3 * CHUNK),
            face: Vec::new(),
            fv: Vec::new(),
            acc: Vec::new(),
            a_face: Vec::new(),
            ga: Vec::new(),
        }
    }

    fn clear(&mut self) {
        self.face_ix.clear();
        self.vert_ix.clear();
        self.face.clear();
        self.fv.clear();
        self.acc.clear();
        self.a_face.clear();
        self.ga.clear();
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
    let chunks: Vec<ChunkSums> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map_init(Scratch::new, |sc, ci| {
            let (i0, i1) = (ci * CHUNK, ((ci + 1) * CHUNK).min(n));
            match c {
                3 => chunk_sums::<T, 3>(&inp, sc, i0, i1),
                1 => chunk_sums::<T, 1>(&inp, sc, i0, i1),
                _ => chunk_sums::<T, 0>(&inp, sc, i0, i1),
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

/// The per-vertex sums of fragments `i0..i1`, for `C` channels (`C = 0`: `inp.c`, known at run
/// time).
fn chunk_sums<T: Real, const C: usize>(
    inp: &Inputs<'_, T>,
    sc: &mut Scratch,
    i0: usize,
    i1: usize,
) -> ChunkSums {
    let c = if C > 0 { C } else { inp.c };
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
                let (e, new) = sc.face_ix.index(fi);
                if new {
                    let f = inp.faces[fi as usize];
                    let v = f.map(|vi| inp.clip[vi as usize].map(|x| x.to_f64c()));
                    sc.face.push(fi);
                    sc.fv.push(FaceVjp::new(&v));
                    sc.acc.push(RunVjp::default());
                    if inp.need_pos {
                        for vi in f {
                            sc.a_face.extend(
                                inp.attrs[vi as usize * c..][..c]
                                    .iter()
                                    .map(|x| x.to_f64c()),
                            );
                        }
                    }
                    if inp.need_attr {
                        sc.ga.resize(sc.ga.len() + 3 * c, 0.0);
                    }
                }
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
        if inp.need_attr && c > 0 {
            let b = fr.bary[i].map(|x| x.to_f64c());
            for (row, bk) in sc.ga[e * 3 * c..][..3 * c].chunks_exact_mut(c).zip(b) {
                for (o, g) in row.iter_mut().zip(&gpf) {
                    *o += bk * g;
                }
            }
        }
        if inp.need_pos {
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
    vertex_sums::<T, C>(inp, sc)
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
