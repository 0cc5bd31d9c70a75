//! Per-fragment interpolation of vertex attributes: `a_n = sum_k b_nk A[f_n,k]` for fragment n
//! of face f_n with barycentrics b_n. Gradients flow to the attributes (scatter-added in
//! fragment order, deterministic) and to the barycentrics (hence to positions).

use std::mem::MaybeUninit;
use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::raster::Fragments;
use crate::rasterize::{as_arrays, as_arrays_mut, as_rows, Rasterized};

struct InterpolateOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
}

const ROWS_PER_TASK: usize = 1024;

impl<T: Real> Op<T> for InterpolateOp<T> {
    fn name(&self) -> &'static str {
        "interpolate"
    }
    fn forward(&mut self, inputs: &[&Tensor<T>]) -> AdResult<Vec<Tensor<T>>> {
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
    fn backward(&self, ctx: &BackwardCtx<'_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
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
        let g_attr = ctx.needs_grad[0].then(|| {
            let mut ga = vec![T::zero(); a.len()];
            // Scatter in fragment order for every vertex, parallel over vertex blocks.
            let visit = |vr: std::ops::Range<usize>, out: &mut [T]| {
                for i in 0..n {
                    let f = self.faces[self.fragments.face[i] as usize];
                    for k in 0..3 {
                        let v = f[k] as usize;
                        if vr.contains(&v) {
                            let bk = b[3 * i + k];
                            let o = &mut out[(v - vr.start) * c..][..c];
                            for (o, &gc) in o.iter_mut().zip(&g[i * c..][..c]) {
                                *o += bk * gc;
                            }
                        }
                    }
                }
            };
            crate::scatter::scatter_by_vertex(&mut ga, c, visit);
            ArrayD::from_shape_vec(IxDyn(attr.shape()), ga).expect("same shape")
        });
        let g_bary = ctx.needs_grad[1].then(|| {
            let mut gb = vec![T::zero(); 3 * n];
            gb.par_chunks_mut(3 * ROWS_PER_TASK)
                .enumerate()
                .for_each(|(blk, chunk)| {
                    for (r, o) in chunk.chunks_mut(3).enumerate() {
                        let i = blk * ROWS_PER_TASK + r;
                        let f = self.faces[self.fragments.face[i] as usize];
                        for k in 0..3 {
                            let base = f[k] as usize * c;
                            o[k] = (0..c).map(|ch| a[base + ch] * g[i * c + ch]).sum();
                        }
                    }
                });
            ArrayD::from_shape_vec(IxDyn(&[n, 3]), gb).expect("n x 3")
        });
        Ok(vec![g_attr, g_bary])
    }
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
                for ((o, bi), &fi) in rows {
                    let f = faces[fi as usize];
                    let (a0, a1, a2) = (&a[f[0] as usize], &a[f[1] as usize], &a[f[2] as usize]);
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
}
