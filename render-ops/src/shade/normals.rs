//! Differentiable geometric normals of a triangle mesh.
//!
//! For face `f = (a, b, c)` let `c_f = (p_b - p_a) x (p_c - p_a)`: its direction is the face
//! normal (outward for counter-clockwise faces) and its length twice the face's area.
//! - face normals: `n_f = c_f / max(|c_f|, eps)`;
//! - vertex normals, area weighted: `n_v = m_v / max(|m_v|, eps)` with `m_v = sum_{f ∋ v} c_f`
//!   (the sum of the unnormalised cross products weights each face by its area).
//!
//! Zero length is safe: a zero-area (degenerate) face has the normal `(0, 0, 0)`, as has a
//! vertex that no face uses or whose adjacent cross products cancel; their gradients are
//! `g / eps` (finite), never NaN. `eps` is [`super::SAFE_EPS`].
//!
//! The fused ops accumulate per-vertex sums through a vertex-to-face adjacency built in face
//! order and run in parallel over faces and vertices, so they are deterministic.

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use super::{acc3, cross3, normalize3, normalize3_vjp, scale3, sub3, SAFE_EPS, V3};

fn positions_of<T: Real, S: ndarray::Data<Elem = T>>(
    op: &'static str,
    p: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> AdResult<Vec<V3<T>>> {
    if p.ndim() != 2 || p.shape()[1] != 3 {
        return Err(AutodiffError::shape(
            op,
            &[p.shape()],
            "positions must be [V, 3]",
        ));
    }
    Ok(p.outer_iter().map(|r| [r[0], r[1], r[2]]).collect())
}

fn check_faces<T: Real, S: ndarray::Data<Elem = T>>(
    op: &'static str,
    faces: &[[u32; 3]],
    nv: usize,
    p: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> AdResult<()> {
    for (f, tri) in faces.iter().enumerate() {
        if let Some(&bad) = tri.iter().find(|&&i| i as usize >= nv) {
            return Err(AutodiffError::index(
                op,
                &[p.shape()],
                format!("face {f} refers to vertex {bad}, but there are only {nv} vertices"),
            ));
        }
    }
    Ok(())
}

/// Vertex-to-(face, corner) adjacency as a CSR, faces in increasing order.
struct Adjacency {
    offsets: Vec<u32>,
    /// `3 * face + corner`.
    entries: Vec<u32>,
}

impl Adjacency {
    fn new(faces: &[[u32; 3]], nv: usize) -> Self {
        let mut offsets = vec![0u32; nv + 1];
        for tri in faces {
            for &v in tri {
                offsets[v as usize + 1] += 1;
            }
        }
        for i in 0..nv {
            offsets[i + 1] += offsets[i];
        }
        let mut next = offsets.clone();
        let mut entries = vec![0u32; 3 * faces.len()];
        for (f, tri) in faces.iter().enumerate() {
            for (k, &v) in tri.iter().enumerate() {
                entries[next[v as usize] as usize] = (3 * f + k) as u32;
                next[v as usize] += 1;
            }
        }
        Adjacency { offsets, entries }
    }

    fn of(&self, v: usize) -> &[u32] {
        &self.entries[self.offsets[v] as usize..self.offsets[v + 1] as usize]
    }
}

fn face_cross<T: Real>(p: &[V3<T>], faces: &[[u32; 3]]) -> Vec<V3<T>> {
    faces
        .par_iter()
        .with_min_len(256)
        .map(|&[a, b, c]| {
            let pa = p[a as usize];
            cross3(sub3(p[b as usize], pa), sub3(p[c as usize], pa))
        })
        .collect()
}

/// Given `dL/dc_f` per face, `dL/dp` per vertex (summed over (face, corner) in face order).
fn cross_backward<T: Real>(
    p: &[V3<T>],
    faces: &[[u32; 3]],
    gc: &[V3<T>],
    adj: &Adjacency,
) -> Tensor<T> {
    // Per face and corner: c = e1 x e2, e1 = pb - pa, e2 = pc - pa;
    // ge1 = e2 x gc, ge2 = gc x e1; gpb = ge1, gpc = ge2, gpa = -(ge1 + ge2).
    let corner: Vec<[V3<T>; 3]> = faces
        .par_iter()
        .zip(gc.par_iter())
        .with_min_len(256)
        .map(|(&[a, b, c], &g)| {
            let pa = p[a as usize];
            let e1 = sub3(p[b as usize], pa);
            let e2 = sub3(p[c as usize], pa);
            let ge1 = cross3(e2, g);
            let ge2 = cross3(g, e1);
            [
                scale3(
                    [ge1[0] + ge2[0], ge1[1] + ge2[1], ge1[2] + ge2[2]],
                    -T::one(),
                ),
                ge1,
                ge2,
            ]
        })
        .collect();
    let gp: Vec<T> = (0..p.len())
        .into_par_iter()
        .with_min_len(256)
        .flat_map_iter(|v| {
            let mut s = [T::zero(); 3];
            for &e in adj.of(v) {
                acc3(&mut s, corner[e as usize / 3][e as usize % 3]);
            }
            s
        })
        .collect();
    ArrayD::from_shape_vec(IxDyn(&[p.len(), 3]), gp).expect("v x 3")
}

struct FaceNormalsOp<T: Real> {
    faces: Arc<Vec<[u32; 3]>>,
    eps: T,
    adj: Option<Adjacency>,
}

impl<T: Real> Op<T> for FaceNormalsOp<T> {
    fn name(&self) -> &'static str {
        "face_normals"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let p = positions_of("face_normals", &inputs[0])?;
        check_faces("face_normals", &self.faces, p.len(), &inputs[0])?;
        let c = face_cross(&p, &self.faces);
        let out: Vec<T> = c.iter().flat_map(|&x| normalize3(x, self.eps).0).collect();
        self.adj = Some(Adjacency::new(&self.faces, p.len()));
        Ok(vec![ArrayD::from_shape_vec(
            IxDyn(&[self.faces.len(), 3]),
            out,
        )
        .expect("f x 3")])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let p = positions_of("face_normals", &ctx.inputs[0])?;
        let c = face_cross(&p, &self.faces);
        let y = ctx.outputs[0].as_standard_layout();
        let g = ctx.grad_outputs[0].as_standard_layout();
        let (y, g) = (y.as_slice().expect("std"), g.as_slice().expect("std"));
        let gc: Vec<V3<T>> = (0..c.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|f| {
                let len = (c[f][0] * c[f][0] + c[f][1] * c[f][1] + c[f][2] * c[f][2]).sqrt();
                let yf = [y[3 * f], y[3 * f + 1], y[3 * f + 2]];
                let gf = [g[3 * f], g[3 * f + 1], g[3 * f + 2]];
                normalize3_vjp(len, yf, gf, self.eps)
            })
            .collect();
        let adj = self.adj.as_ref().expect("forward ran");
        Ok(vec![Some(cross_backward(&p, &self.faces, &gc, adj))])
    }
}

struct VertexNormalsOp<T: Real> {
    faces: Arc<Vec<[u32; 3]>>,
    eps: T,
    adj: Option<Adjacency>,
    /// Unnormalised vertex sums `m_v` of the forward.
    m: Vec<V3<T>>,
}

impl<T: Real> Op<T> for VertexNormalsOp<T> {
    fn name(&self) -> &'static str {
        "vertex_normals"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let p = positions_of("vertex_normals", &inputs[0])?;
        check_faces("vertex_normals", &self.faces, p.len(), &inputs[0])?;
        let c = face_cross(&p, &self.faces);
        let adj = Adjacency::new(&self.faces, p.len());
        self.m = (0..p.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|v| {
                let mut s = [T::zero(); 3];
                for &e in adj.of(v) {
                    acc3(&mut s, c[e as usize / 3]);
                }
                s
            })
            .collect();
        self.adj = Some(adj);
        let out: Vec<T> = self
            .m
            .iter()
            .flat_map(|&x| normalize3(x, self.eps).0)
            .collect();
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[p.len(), 3]), out).expect("v x 3")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let p = positions_of("vertex_normals", &ctx.inputs[0])?;
        let y = ctx.outputs[0].as_standard_layout();
        let g = ctx.grad_outputs[0].as_standard_layout();
        let (y, g) = (y.as_slice().expect("std"), g.as_slice().expect("std"));
        let gm: Vec<V3<T>> = (0..p.len())
            .into_par_iter()
            .with_min_len(256)
            .map(|v| {
                let m = self.m[v];
                let len = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
                normalize3_vjp(
                    len,
                    [y[3 * v], y[3 * v + 1], y[3 * v + 2]],
                    [g[3 * v], g[3 * v + 1], g[3 * v + 2]],
                    self.eps,
                )
            })
            .collect();
        let gc: Vec<V3<T>> = self
            .faces
            .par_iter()
            .with_min_len(256)
            .map(|&[a, b, c]| {
                let mut s = gm[a as usize];
                acc3(&mut s, gm[b as usize]);
                acc3(&mut s, gm[c as usize]);
                s
            })
            .collect();
        let adj = self.adj.as_ref().expect("forward ran");
        Ok(vec![Some(cross_backward(&p, &self.faces, &gc, adj))])
    }
}

/// Unit face normals `[F, 3]` of positions `[V, 3]` (fused op). Counter-clockwise faces give
/// outward normals; a zero-area face gives `(0, 0, 0)` (see the module docs).
pub fn face_normals<'t, T: Real>(positions: Var<'t, T>, faces: &Arc<Vec<[u32; 3]>>) -> Var<'t, T> {
    let op = FaceNormalsOp {
        faces: faces.clone(),
        eps: T::from_f64c(SAFE_EPS),
        adj: None,
    };
    positions.tape().apply(op, &[positions])
}

/// Area-weighted unit vertex normals `[V, 3]` of positions `[V, 3]` (fused op). A vertex
/// without faces (or whose weighted face normals cancel) gets `(0, 0, 0)`.
pub fn vertex_normals<'t, T: Real>(
    positions: Var<'t, T>,
    faces: &Arc<Vec<[u32; 3]>>,
) -> Var<'t, T> {
    let op = VertexNormalsOp {
        faces: faces.clone(),
        eps: T::from_f64c(SAFE_EPS),
        adj: None,
        m: Vec::new(),
    };
    positions.tape().apply(op, &[positions])
}

fn corner_indices(faces: &[[u32; 3]], k: usize) -> Vec<usize> {
    faces.iter().map(|f| f[k] as usize).collect()
}

fn unnormalised_cross<'t, T: Real>(positions: Var<'t, T>, faces: &[[u32; 3]]) -> Var<'t, T> {
    let pa = positions.index_select(0, &corner_indices(faces, 0));
    let pb = positions.index_select(0, &corner_indices(faces, 1));
    let pc = positions.index_select(0, &corner_indices(faces, 2));
    (pb - pa).cross(pc - pa)
}

/// [`face_normals`] composed from tape ops (`index_select`, `cross`, `normalize`).
pub fn face_normals_composed<'t, T: Real>(
    positions: Var<'t, T>,
    faces: &Arc<Vec<[u32; 3]>>,
) -> Var<'t, T> {
    unnormalised_cross(positions, faces).normalize(T::from_f64c(SAFE_EPS))
}

/// [`vertex_normals`] composed from tape ops (`cross`, `scatter_add`, `normalize`).
pub fn vertex_normals_composed<'t, T: Real>(
    positions: Var<'t, T>,
    faces: &Arc<Vec<[u32; 3]>>,
) -> Var<'t, T> {
    let t = positions.tape();
    let nv = positions.shape().first().copied().unwrap_or(0);
    let c = unnormalised_cross(positions, faces);
    let nf = faces.len();
    let index = ArrayD::from_shape_fn(IxDyn(&[3 * nf, 3]), |i| {
        faces[i[0] % nf][i[0] / nf] as usize
    });
    let m = t.concat(&[c, c, c], 0).scatter_add(0, index, nv);
    m.normalize(T::from_f64c(SAFE_EPS))
}
