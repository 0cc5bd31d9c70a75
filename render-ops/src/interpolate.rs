//! Per-fragment interpolation of vertex attributes: `a_n = sum_k b_nk A[f_n,k]` for fragment n
//! of face f_n with barycentrics b_n. Gradients flow to the attributes (summed in `f64` per run
//! of a face's fragments within fixed chunks, then per vertex in fragment order: deterministic)
//! and to the barycentrics (hence to positions).

use std::mem::MaybeUninit;
use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::raster::Fragments;
use crate::rasterize::{as_arrays, as_arrays_mut, as_rows, Rasterized};
use crate::scatter::scatter_face_corners;

struct InterpolateOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
}

const ROWS_PER_TASK: usize = 1024;

impl<T: Real> Op<T> for InterpolateOp<T> {
    fn name(&self) -> &'static str {
        "interpolate"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let (attr, bary) = (
            inputs[0].as_standard_layout(),
            inputs[1].as_standard_layout(),
        );
        let n = self.fragments.face.len();
        if attr.ndim() != 2 || bary.shape() != [n, 3] {
            return Err(AutodiffError::shape(
                "interpolate",
                &[attr.shape(), bary.shape()],
                format!("attributes must be [V, C] and barycentrics [{n}, 3]"),
            ));
        }
        let c = attr.shape()[1];
        let a = attr.as_slice().expect("standard");
        let b = bary.as_slice().expect("standard");
        let mut out = Vec::with_capacity(n * c);
        let o = &mut out.spare_capacity_mut()[..n * c];
        match c {
            3 => interpolate_rows::<T, 3>(&self.fragments.face, &self.faces, a, b, c, o),
            1 => interpolate_rows::<T, 1>(&self.fragments.face, &self.faces, a, b, c, o),
            2 => interpolate_rows::<T, 2>(&self.fragments.face, &self.faces, a, b, c, o),
            4 => interpolate_rows::<T, 4>(&self.fragments.face, &self.faces, a, b, c, o),
            _ => interpolate_rows::<T, 0>(&self.fragments.face, &self.faces, a, b, c, o),
        }
        // SAFETY: `interpolate_rows` wrote all `n * c` values.
        unsafe { out.set_len(n * c) };
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[n, c]), out).expect("n x c")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let attr = ctx.inputs[0].as_standard_layout();
        let bary = ctx.inputs[1].as_standard_layout();
        let g = ctx.grad_outputs[0].as_standard_layout();
        let (a, b, g) = (
            attr.as_slice().expect("std"),
            bary.as_slice().expect("std"),
            g.as_slice().expect("std"),
        );
        let c = attr.shape()[1];
        let n = self.fragments.face.len();
        let (ff, faces) = (&self.fragments.face[..], &self.faces[..]);
        let g_attr = ctx.needs_grad[0].then(|| {
            let ga = match c {
                3 => grad_attributes::<T, 3>(ff, faces, as_rows(b), g, c, a.len()),
                1 => grad_attributes::<T, 1>(ff, faces, as_rows(b), g, c, a.len()),
                2 => grad_attributes::<T, 2>(ff, faces, as_rows(b), g, c, a.len()),
                4 => grad_attributes::<T, 4>(ff, faces, as_rows(b), g, c, a.len()),
                _ => grad_attributes::<T, 0>(ff, faces, as_rows(b), g, c, a.len()),
            };
            ArrayD::from_shape_vec(IxDyn(attr.shape()), ga).expect("same shape")
        });
        let g_bary = ctx.needs_grad[1].then(|| {
            let mut gb = vec![T::zero(); 3 * n];
            let rows = as_arrays_mut::<T, 3>(&mut gb);
            match c {
                3 => grad_bary_rows::<T, 3>(ff, faces, a, g, c, rows),
                1 => grad_bary_rows::<T, 1>(ff, faces, a, g, c, rows),
                2 => grad_bary_rows::<T, 2>(ff, faces, a, g, c, rows),
                4 => grad_bary_rows::<T, 4>(ff, faces, a, g, c, rows),
                _ => grad_bary_rows::<T, 0>(ff, faces, a, g, c, rows),
            }
            ArrayD::from_shape_vec(IxDyn(&[n, 3]), gb).expect("n x 3")
        });
        Ok(vec![g_attr, g_bary])
    }
}

/// Fragments per parallel chunk of [`grad_attributes`].
const ATTR_CHUNK: usize = 4096;

/// `dL/dA[v] = sum_n sum_k [f_n,k = v] b_nk dL/da_n` for `C` channels (`C = 0`: `c`, known only
/// at run time), `len = V * c` values. Fixed chunks of fragments in parallel: within a chunk
/// each run of consecutive fragments of one face sums `b_k dL/da_n` per corner in `f64`
/// (fragments of a face are mostly adjacent), then every vertex adds the runs of its faces in
/// fragment order ([`scatter_face_corners`]); the chunking does not depend on the thread count,
/// so the result is bit-identical for any number of threads.
fn grad_attributes<T: Real, const C: usize>(
    frag_face: &[u32],
    faces: &[[u32; 3]],
    bary: &[[T; 3]],
    g: &[T],
    c: usize,
    len: usize,
) -> Vec<T> {
    let c = if C > 0 { C } else { c };
    if c == 0 {
        return vec![T::zero(); len];
    }
    let n = frag_face.len();
    // Per chunk: the faces of its runs, and `3 c` sums per run (corner-major).
    let runs: Vec<(Vec<u32>, Vec<f64>)> = (0..n.div_ceil(ATTR_CHUNK))
        .into_par_iter()
        .map(|ci| {
            let (i0, i1) = (ci * ATTR_CHUNK, ((ci + 1) * ATTR_CHUNK).min(n));
            // Room for runs of about two fragments (fine meshes) without regrowth.
            let runs = (i1 - i0) / 2 + 1;
            let (mut fs, mut vals) = (
                Vec::with_capacity(runs),
                Vec::<f64>::with_capacity(runs * 3 * c),
            );
            if C > 0 {
                // The run's sums in registers (`[corner][channel]`), written out when the face
                // changes.
                let g = &as_arrays::<T, C>(g)[i0..i1];
                let mut run = [[0.0f64; C]; 3];
                // Chunks are non-empty (`i0 < i1`).
                let mut cur = frag_face[i0];
                for ((&fi, b), gi) in frag_face[i0..i1].iter().zip(&bary[i0..i1]).zip(g) {
                    if fi != cur {
                        fs.push(cur);
                        vals.extend(run.iter().flatten());
                        run = [[0.0; C]; 3];
                        cur = fi;
                    }
                    for (rk, &bk) in run.iter_mut().zip(b) {
                        let bk = bk.to_f64c();
                        for (r, &gc) in rk.iter_mut().zip(gi) {
                            *r += bk * gc.to_f64c();
                        }
                    }
                }
                fs.push(cur);
                vals.extend(run.iter().flatten());
                return (fs, vals);
            }
            let mut cur = u32::MAX;
            for i in i0..i1 {
                let fi = frag_face[i];
                if fi != cur {
                    fs.push(fi);
                    vals.resize(vals.len() + 3 * c, 0.0);
                    cur = fi;
                }
                let at = vals.len() - 3 * c;
                let run = &mut vals[at..];
                let gi = &g[i * c..][..c];
                for (k, &bk) in bary[i].iter().enumerate() {
                    let bk = bk.to_f64c();
                    for (r, &gc) in run[k * c..][..c].iter_mut().zip(gi) {
                        *r += bk * gc.to_f64c();
                    }
                }
            }
            (fs, vals)
        })
        .collect();
    let mut acc = vec![0.0f64; len];
    scatter_face_corners(&mut acc, c, faces, || {
        runs.iter()
            .flat_map(move |(fs, vals)| fs.iter().copied().zip(vals.chunks_exact(3 * c)))
    });
    acc.into_iter().map(T::from_f64c).collect()
}

/// `dL/db_nk = A[f_n,k] . dL/da_n` for `C` channels (`C = 0`: `c`, known only at run time),
/// into `out` ([N] rows), in parallel over blocks of fragments.
fn grad_bary_rows<T: Real, const C: usize>(
    frag_face: &[u32],
    faces: &[[u32; 3]],
    a: &[T],
    g: &[T],
    c: usize,
    out: &mut [[T; 3]],
) {
    let c = if C > 0 { C } else { c };
    if c == 0 {
        // No channels: every `dL/db` is zero (as `out` is).
        return;
    }
    out.par_chunks_mut(ROWS_PER_TASK)
        .enumerate()
        .for_each(|(blk, chunk)| {
            let i0 = blk * ROWS_PER_TASK;
            if C > 0 {
                let (a, g) = (as_arrays::<T, C>(a), as_arrays::<T, C>(g));
                for ((o, &fi), gi) in chunk.iter_mut().zip(&frag_face[i0..]).zip(&g[i0..]) {
                    for (ok, &v) in o.iter_mut().zip(&faces[fi as usize]) {
                        let av = &a[v as usize];
                        let mut s = T::zero();
                        for ch in 0..C {
                            s += av[ch] * gi[ch];
                        }
                        *ok = s;
                    }
                }
                return;
            }
            for ((o, &fi), gi) in chunk
                .iter_mut()
                .zip(&frag_face[i0..])
                .zip(g[i0 * c..].chunks_exact(c))
            {
                let f = faces[fi as usize];
                for (ok, &v) in o.iter_mut().zip(&f) {
                    let av = &a[v as usize * c..][..c];
                    let mut s = T::zero();
                    for (&x, &y) in av.iter().zip(gi) {
                        s += x * y;
                    }
                    *ok = s;
                }
            }
        });
}

/// Interpolation of `C` channels (`C = 0`: `c`, known only at run time) into `out` ([N, C],
/// uninitialised, every value written), in parallel over blocks of fragments. With `C > 0`
/// attribute rows and output rows are `[T; C]` arrays (one bounds check per vertex, the
/// channel loop unrolled); every value is the same expression `b0 x0 + b1 x1 + b2 x2`.
fn interpolate_rows<T: Real, const C: usize>(
    frag_face: &[u32],
    faces: &[[u32; 3]],
    a: &[T],
    b: &[T],
    c: usize,
    out: &mut [MaybeUninit<T>],
) {
    let b3 = as_rows(b);
    if C > 0 {
        let a = as_arrays::<T, C>(a);
        as_arrays_mut::<MaybeUninit<T>, C>(out)
            .par_chunks_mut(ROWS_PER_TASK)
            .enumerate()
            .for_each(|(blk, chunk)| {
                let i0 = blk * ROWS_PER_TASK;
                let rows = chunk.iter_mut().zip(&b3[i0..]).zip(&frag_face[i0..]);
                // The corner rows of the current face: runs of fragments of one face (a row's
                // pixels of a triangle) look them up once.
                let mut cur = u32::MAX;
                let zero = [T::zero(); C];
                let (mut a0, mut a1, mut a2) = (&zero, &zero, &zero);
                for ((o, bi), &fi) in rows {
                    if fi != cur {
                        let f = faces[fi as usize];
                        (a0, a1, a2) = (&a[f[0] as usize], &a[f[1] as usize], &a[f[2] as usize]);
                        cur = fi;
                    }
                    for ch in 0..C {
                        o[ch].write(bi[0] * a0[ch] + bi[1] * a1[ch] + bi[2] * a2[ch]);
                    }
                }
            });
        return;
    }
    out.par_chunks_mut(ROWS_PER_TASK * c.max(1))
        .enumerate()
        .for_each(|(blk, chunk)| {
            // `chunk` is non-empty, so c >= 1.
            let i0 = blk * ROWS_PER_TASK;
            let rows = chunk
                .chunks_exact_mut(c)
                .zip(b3[i0..].iter())
                .zip(&frag_face[i0..]);
            for ((orow, bi), &fi) in rows {
                let f = faces[fi as usize];
                let a0 = &a[f[0] as usize * c..][..c];
                let a1 = &a[f[1] as usize * c..][..c];
                let a2 = &a[f[2] as usize * c..][..c];
                for (((o, &x0), &x1), &x2) in orow.iter_mut().zip(a0).zip(a1).zip(a2) {
                    o.write(bi[0] * x0 + bi[1] * x1 + bi[2] * x2);
                }
            }
        });
}

/// Vertex attributes [V, C] interpolated at every fragment: [N, C].
pub fn interpolate<'t, T: Real>(
    attributes: Var<'t, T>,
    r: &Rasterized<'t, T>,
) -> Result<Var<'t, T>, RenderError> {
    let shape = attributes.shape();
    let nv = r
        .faces
        .par_iter()
        .with_min_len(1 << 14)
        .map(|f| f[0].max(f[1]).max(f[2]) as usize + 1)
        .max()
        .unwrap_or(0);
    if shape.len() != 2 || shape[0] < nv {
        return Err(AutodiffError::shape(
            "interpolate",
            &[&shape],
            format!("attributes must be [V, C] with V >= {nv} (the faces' largest index + 1)"),
        )
        .into());
    }
    let op = InterpolateOp {
        fragments: r.fragments.clone(),
        faces: r.faces.clone(),
    };
    Ok(attributes.tape().apply(op, &[attributes, r.bary]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blend::blend_hard;
    use crate::raster::RasterSettings;
    use autodiff::Tape;

    /// The constant-channel paths (C = 1..4) and the run-time path (C = 5, 6) of interpolate
    /// and the hard blend give the defining expressions exactly.
    #[test]
    fn channel_paths_match_reference() {
        let clip = vec![
            -0.8, -0.7, 0.0, 1.0, 0.9, -0.6, 0.1, 1.0, 0.7, 0.8, 0.2, 1.2, -0.6, 0.9, -0.1, 1.0,
        ];
        let faces = Arc::new(vec![[0u32, 1, 2], [0, 2, 3], [1, 3, 0]]);
        let s = RasterSettings {
            faces_per_pixel: 2,
            ..RasterSettings::new(45, 38)
        };
        for c in 1..=6usize {
            let tape = Tape::<f32>::new();
            let cv = tape.var(
                ArrayD::from_shape_vec(IxDyn(&[4, 4]), clip.clone()).unwrap(),
                false,
            );
            let r = crate::rasterize::rasterize(cv, faces.clone(), &s).unwrap();
            let attr: Vec<f32> = (0..4 * c).map(|i| (i as f32 * 0.37).sin()).collect();
            let av = tape.var(
                ArrayD::from_shape_vec(IxDyn(&[4, c]), attr.clone()).unwrap(),
                false,
            );
            let out = interpolate(av, &r).unwrap();
            let ov = out.value().unwrap();
            let ov = ov.as_slice().unwrap();
            let fr = &r.fragments;
            assert!(fr.len() > 500);
            assert_eq!(ov.len(), fr.len() * c);
            for i in 0..fr.len() {
                let f = faces[fr.face[i] as usize].map(|v| v as usize);
                let b = fr.bary[i];
                for ch in 0..c {
                    let want = b[0] * attr[f[0] * c + ch]
                        + b[1] * attr[f[1] * c + ch]
                        + b[2] * attr[f[2] * c + ch];
                    assert_eq!(ov[i * c + ch].to_bits(), want.to_bits());
                }
            }
            let bg: Vec<f32> = (0..c).map(|i| -(i as f32) - 0.5).collect();
            let img = blend_hard(out, fr, &bg).unwrap().value().unwrap();
            let img = img.as_slice().unwrap();
            assert_eq!(img.len(), fr.num_pixels() * (c + 1));
            for p in 0..fr.num_pixels() {
                let px = &img[p * (c + 1)..(p + 1) * (c + 1)];
                match fr.nearest(p) {
                    Some(x) => {
                        assert_eq!(&px[..c], &ov[x.index * c..(x.index + 1) * c]);
                        assert_eq!(px[c], 1.0);
                    }
                    None => {
                        assert_eq!(&px[..c], &bg[..]);
                        assert_eq!(px[c], 0.0);
                    }
                }
            }
        }
    }

    /// The attribute backward of every channel path (C = 1..4 fixed, 5 at run time) against the
    /// defining sums in `f64` (`dL/dA[v] = sum b_k g`), on a sphere with several chunks of
    /// fragments; attribute and position gradients (through `dL/db_k = A[f_k] . g` and the
    /// rasterizer's backward) bit-identical on pools of 1, 2 and 3 threads.
    #[test]
    fn backward_matches_defining_sums_for_any_thread_count() {
        let mesh = crate::mesh::Mesh::<f64>::icosphere(3, 0.8);
        let nv = mesh.positions.len();
        let clip: Vec<f32> = mesh
            .positions
            .iter()
            .flat_map(|p| [p[0] as f32, p[1] as f32, p[2] as f32 * 0.5, 1.0])
            .collect();
        let faces = Arc::new(mesh.faces.clone());
        // Both layers of the sphere: runs of a face's fragments interleave with the other
        // layer's.
        let s = RasterSettings {
            faces_per_pixel: 2,
            ..RasterSettings::new(200, 160)
        };
        for c in 1..=5usize {
            let attr: Vec<f32> = (0..nv * c).map(|i| (i as f32 * 0.37).sin()).collect();
            let run = |threads: usize| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| {
                        let tape = Tape::<f32>::new();
                        let cv = tape.var(
                            ArrayD::from_shape_vec(IxDyn(&[nv, 4]), clip.clone()).unwrap(),
                            true,
                        );
                        let r = crate::rasterize::rasterize(cv, faces.clone(), &s).unwrap();
                        let av = tape.var(
                            ArrayD::from_shape_vec(IxDyn(&[nv, c]), attr.clone()).unwrap(),
                            true,
                        );
                        let out = interpolate(av, &r).unwrap();
                        let n = r.fragments.len();
                        let w: Vec<f32> = (0..n * c).map(|i| (i as f32 * 0.11).cos()).collect();
                        let wv = tape.constant(ArrayD::from_shape_vec(IxDyn(&[n, c]), w).unwrap());
                        let loss = (out * wv).sum();
                        let g = tape.backward(loss).unwrap();
                        let ga = g.get(av).unwrap().iter().copied().collect::<Vec<f32>>();
                        let gp = g.get(cv).unwrap().iter().map(|v| v.to_bits()).collect();
                        (r.fragments.clone(), ga, gp)
                    })
            };
            let (fr, ga, gp): (_, _, Vec<u32>) = run(1);
            assert!(fr.len() > 2 * ATTR_CHUNK, "{} fragments", fr.len());
            assert!(gp.iter().any(|&b| f32::from_bits(b) != 0.0));
            for t in [2, 3] {
                let (_, gt, gpt) = run(t);
                assert!(ga.iter().zip(&gt).all(|(x, y)| x.to_bits() == y.to_bits()));
                assert_eq!(gp, gpt);
            }
            let mut want = vec![0.0f64; nv * c];
            for i in 0..fr.len() {
                let f = faces[fr.face[i] as usize];
                for k in 0..3 {
                    for ch in 0..c {
                        let g = ((i * c + ch) as f32 * 0.11).cos() as f64;
                        want[f[k] as usize * c + ch] += fr.bary[i][k] as f64 * g;
                    }
                }
            }
            for (x, y) in ga.iter().zip(&want) {
                assert!(
                    (*x as f64 - y).abs() <= 1e-5 * (1.0 + y.abs()),
                    "{x} vs {y}"
                );
            }
        }
    }
}
