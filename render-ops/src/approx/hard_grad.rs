//! The exact gradient of the hard render ([`super::render_hard`]: per covered pixel
//! `I_p = sum_k b_k A[f_k]` from its nearest fragment) with respect to the attributes and,
//! with the visibility held fixed, the clip positions, in one pass over the fragments.
//!
//! `dL/dA[f_k] = sum_p b_k dL/dI_p` is exact. For the positions, `dL/db_k = dL/dI_p . A[f_k]`
//! goes through the rasterizer's barycentric backward (the interior gradient of
//! [`crate::raster::rasterize_backward`]), whose per-fragment products are summed per run in
//! the factored form of [`RunVjp`].
//!
//! Deterministic: fragments are visited in fixed chunks of 512 in parallel; within a chunk
//! each run of consecutive fragments of one face sums its contributions in fragment order, and
//! every vertex then adds the runs' sums in fragment order (parallel over vertex blocks,
//! [`scatter_face_corners`]), so the result is bit-identical for any number of threads.

use autodiff::Real;
use rayon::prelude::*;

use crate::raster::{FaceVjp, Fragments, RunVjp};
use crate::scatter::scatter_face_corners;

/// Fragments per parallel chunk.
const CHUNK: usize = 512;

/// The gradients of the hard render, in `f64`: `dL/dclip` `[V]` and `dL/dA` `[V * C]`, each
/// only when asked for.
pub(crate) struct HardGrad {
    pub pos: Option<Vec<[f64; 4]>>,
    pub attr: Option<Vec<f64>>,
}

/// What one chunk's runs contribute: per run its face, and (when asked for) the run's
/// `dL/dclip` of the face's vertices and its `dL/dA` of the face's vertices (`3 * C`).
struct Runs {
    face: Vec<u32>,
    pos: Vec<[[f64; 4]; 3]>,
    attr: Vec<f64>,
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
    let runs: Vec<Runs> = (0..n.div_ceil(CHUNK))
        .into_par_iter()
        .map(|ci| {
            let (i0, i1) = (ci * CHUNK, ((ci + 1) * CHUNK).min(n));
            match c {
                3 => chunk_runs::<T, 3>(&inp, i0, i1),
                1 => chunk_runs::<T, 1>(&inp, i0, i1),
                _ => chunk_runs::<T, 0>(&inp, i0, i1),
            }
        })
        .collect();
    let nv = clip.len();
    let pos = need_pos.then(|| {
        let mut acc = vec![[0.0f64; 4]; nv];
        scatter_face_corners(acc.as_flattened_mut(), 4, faces, || {
            runs.iter().flat_map(|r| {
                r.face
                    .iter()
                    .copied()
                    .zip(r.pos.iter().map(|g| g.as_flattened()))
            })
        });
        acc
    });
    let attr = need_attr.then(|| {
        let mut acc = vec![0.0f64; nv * c];
        scatter_face_corners(&mut acc, c, faces, || {
            runs.iter()
                .flat_map(|r| r.face.iter().copied().zip(r.attr.chunks_exact(3 * c)))
        });
        acc
    });
    HardGrad { pos, attr }
}

/// The runs of fragments `i0..i1`, for `C` channels (`C = 0`: `inp.c`, known at run time).
fn chunk_runs<T: Real, const C: usize>(inp: &Inputs<'_, T>, i0: usize, i1: usize) -> Runs {
    let c = if C > 0 { C } else { inp.c };
    let fr = inp.frags;
    let (wf, hf) = (fr.width as f64, fr.height as f64);
    // At most one run per fragment: no regrowth.
    let n = i1 - i0;
    let mut out = Runs {
        face: Vec::with_capacity(n),
        pos: Vec::with_capacity(if inp.need_pos { n } else { 0 }),
        attr: Vec::with_capacity(if inp.need_attr { 3 * c * n } else { 0 }),
    };
    // The current run: its face, the face's attributes (`3 * C`), setup and sums.
    let mut cur: Option<(u32, FaceVjp)> = None;
    let mut a_face = vec![0.0f64; 3 * c];
    let mut ga = vec![0.0f64; 3 * c];
    let mut acc = RunVjp::default();
    let flush = |out: &mut Runs, cur: &Option<(u32, FaceVjp)>, acc: &RunVjp, ga: &[f64]| {
        if let Some((fi, fv)) = cur {
            out.face.push(*fi);
            if inp.need_pos {
                out.pos.push(fv.finish(acc, inp.persp));
            }
            if inp.need_attr {
                out.attr.extend_from_slice(ga);
            }
        }
    };
    // Pixel centres in NDC: `x = (col + 0.5) sx - 1`, `y = 1 - (row + 0.5) sy`.
    let (sx, sy) = (2.0 / wf, 2.0 / hf);
    let mut p = fr.pixel_of(i0);
    let (mut row, mut col) = (p / fr.width, p % fr.width);
    let mut py = 1.0 - (row as f64 + 0.5) * sy;
    // `dL/dI` of the current pixel in `f64`.
    let mut gpf = vec![0.0f64; c];
    // The next replaced pixel at or after `p`.
    let mut ov = inp.over_pix.partition_point(|&q| (q as usize) < p);
    for i in i0..i1 {
        while fr.offsets[p + 1] as usize <= i {
            p += 1;
            col += 1;
            if col == fr.width {
                col = 0;
                row += 1;
                py = 1.0 - (row as f64 + 0.5) * sy;
            }
        }
        if fr.offsets[p] as usize != i {
            // Not the pixel's nearest fragment: the render does not show it.
            continue;
        }
        let fi = fr.face[i];
        if !matches!(&cur, Some((cf, _)) if *cf == fi) {
            flush(&mut out, &cur, &acc, &ga);
            let f = inp.faces[fi as usize];
            let v = f.map(|vi| inp.clip[vi as usize].map(|x| x.to_f64c()));
            if inp.need_pos {
                for (k, &vi) in f.iter().enumerate() {
                    for ch in 0..c {
                        a_face[k * c + ch] = inp.attrs[vi as usize * c + ch].to_f64c();
                    }
                }
            }
            cur = Some((fi, FaceVjp::new(&v)));
            acc = RunVjp::default();
            ga.fill(0.0);
        }
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
            for (row, bk) in ga.chunks_exact_mut(c).zip(b) {
                for (o, g) in row.iter_mut().zip(&gpf) {
                    *o += bk * g;
                }
            }
        }
        if inp.need_pos {
            let mut gb = [0.0; 3];
            for (gk, a) in gb.iter_mut().zip(a_face.chunks_exact(c.max(1))) {
                for (g, a) in gpf.iter().zip(a) {
                    *gk += g * a;
                }
            }
            let px = [(col as f64 + 0.5) * sx - 1.0, py];
            let fv = &cur.as_ref().expect("a run").1;
            fv.accumulate(&mut acc, px, gb, inp.persp);
        }
    }
    flush(&mut out, &cur, &acc, &ga);
    out
}
