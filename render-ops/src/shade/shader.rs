//! Programmable shaders: a shader is a Rust closure from [`FragmentInputs`] (tape variables,
//! one row per fragment) to a colour (optionally with alpha). [`run_shader`] interpolates the
//! mesh attributes at the fragments of a [`Rasterized`] and calls it; [`render_shader`] also
//! composites the result into an image with the hard z-buffer blend.
//!
//! ```ignore
//! let img = render_shader(&raster, &mesh_attrs, eye, |f: &FragmentInputs<'_, f64>| {
//!     let ndv = (f.normal * f.view_dir).sum_axes(&[-1], true);
//!     let rim = (-ndv + 1.0).powf(4.0);
//!     f.sample(&texture) + rim
//! }, &[0.0, 0.0, 0.0])?;
//! ```
//!
//! The shader runs inside [`autodiff::Tape::fused`]: its elementwise and broadcast ops (the
//! arithmetic of a lighting model) become one fused tape op, evaluated chunk by chunk of
//! fragments without materialising intermediates, with results equal to the eager ops'.
//!
//! Everything in [`FragmentInputs`] is differentiable: gradients reach the mesh positions
//! (through the barycentrics and the vertex normals), normals, uvs, extra attributes,
//! textures and the eye. The screen-space uv derivatives `uv_da` are differentiable with
//! respect to the uvs; the barycentric derivatives they are built from are fixed data of the
//! rasterization (no gradient to positions through the mip level).

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::blend::blend_hard;
use crate::error::RenderError;
use crate::interpolate::interpolate;
use crate::raster::Fragments;
use crate::rasterize::Rasterized;
use crate::texture::Texture;

use super::normals::vertex_normals;
use super::phong::Surface;
use super::SAFE_EPS;

/// Per-vertex inputs of a shader, all `[V, *]` tape variables sharing the rasterized faces.
#[derive(Clone, Debug)]
pub struct MeshAttributes<'t, T: Real> {
    /// World-space positions `[V, 3]`.
    pub positions: Var<'t, T>,
    /// Vertex normals `[V, 3]`; `None`: area-weighted normals of `positions`
    /// ([`super::vertex_normals`]).
    pub normals: Option<Var<'t, T>>,
    /// Texture coordinates `[V, 2]` (needed by [`FragmentInputs::sample`]).
    pub uvs: Option<Var<'t, T>>,
    /// Further named attributes `[V, C]` (vertex colours, PNCC codes, ...).
    pub attributes: Vec<(String, Var<'t, T>)>,
}

impl<'t, T: Real> MeshAttributes<'t, T> {
    /// Positions only.
    pub fn new(positions: Var<'t, T>) -> Self {
        MeshAttributes {
            positions,
            normals: None,
            uvs: None,
            attributes: Vec::new(),
        }
    }
    /// Sets the vertex normals.
    pub fn with_normals(mut self, normals: Var<'t, T>) -> Self {
        self.normals = Some(normals);
        self
    }
    /// Sets the uvs.
    pub fn with_uvs(mut self, uvs: Var<'t, T>) -> Self {
        self.uvs = Some(uvs);
        self
    }
    /// Adds a named attribute `[V, C]`.
    pub fn with_attribute(mut self, name: impl Into<String>, values: Var<'t, T>) -> Self {
        self.attributes.push((name.into(), values));
        self
    }
}

/// What a shader sees: per-fragment tape variables, `N` rows (one per fragment of the
/// [`Rasterized`], in its packed order).
#[derive(Clone, Debug)]
pub struct FragmentInputs<'t, T: Real> {
    /// Interpolated world positions `[N, 3]`.
    pub position: Var<'t, T>,
    /// Interpolated, normalised normals `[N, 3]`.
    pub normal: Var<'t, T>,
    /// Unit direction from the surface to the eye `[N, 3]`.
    pub view_dir: Var<'t, T>,
    /// The eye `[3]`.
    pub eye: Var<'t, T>,
    /// Interpolated uvs `[N, 2]`, when the mesh has them.
    pub uv: Option<Var<'t, T>>,
    /// Screen-space uv derivatives `[N, 4]` = (du/dx, dv/dx, du/dy, dv/dy) per pixel step.
    pub uv_da: Option<Var<'t, T>>,
    /// NDC depth `[N]`.
    pub depth: Var<'t, T>,
    /// View-space depth `[N]`.
    pub view_depth: Var<'t, T>,
    /// The mesh's extra attributes, interpolated: `[N, C]` each.
    pub attributes: Vec<(String, Var<'t, T>)>,
    /// The packed fragments (face ids, pixels).
    pub fragments: Arc<Fragments<T>>,
    /// Light visibility `[N, L]` where the visibility method traces shadow rays
    /// ([`Rasterized::visibility`]); pass it to [`crate::shade::Surface::visibility`].
    pub visibility: Option<Var<'t, T>>,
}

/// An op that only reports an error (poisons its output).
struct FailOp(String);

impl<T: Real> Op<T> for FailOp {
    fn name(&self) -> &'static str {
        "shader"
    }
    fn forward(&mut self, _inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        Err(AutodiffError::Op {
            op: "shader",
            detail: self.0.clone(),
        })
    }
    fn backward(&self, _ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        Ok(Vec::new())
    }
}

impl<'t, T: Real> FragmentInputs<'t, T> {
    /// Number of fragments `N`.
    pub fn len(&self) -> usize {
        self.fragments.len()
    }

    /// No fragments.
    pub fn is_empty(&self) -> bool {
        self.fragments.is_empty()
    }

    /// A named attribute, interpolated.
    pub fn attribute(&self, name: &str) -> Option<Var<'t, T>> {
        self.attributes
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| *v)
    }

    /// Samples `texture` at the fragments' uvs (trilinear filtering picks the mip level from
    /// `uv_da`). Without uvs the result is poisoned with an error naming the problem.
    pub fn sample(&self, texture: &Texture<'t, T>) -> Var<'t, T> {
        match self.uv {
            Some(uv) => texture.sample(uv, self.uv_da),
            None => self.position.tape().apply(
                FailOp("texture sampled, but the mesh has no uvs".into()),
                &[],
            ),
        }
    }

    /// The surface for [`super::shade`] with the given albedo (`[N, 3]` or `[3]`).
    pub fn surface(&self, albedo: Var<'t, T>) -> Surface<'t, T> {
        Surface {
            position: self.position,
            normal: self.normal,
            albedo,
            visibility: self.visibility,
        }
    }
}

/// A shader's result: colours `[N, C]` and optionally an alpha `[N, 1]` (or `[N]`).
#[derive(Clone, Copy, Debug)]
pub struct ShaderOutput<'t, T: Real> {
    /// Colour `[N, C]`.
    pub color: Var<'t, T>,
    /// Opacity in [0, 1]; `None` is opaque.
    pub alpha: Option<Var<'t, T>>,
}

impl<'t, T: Real> From<Var<'t, T>> for ShaderOutput<'t, T> {
    fn from(color: Var<'t, T>) -> Self {
        ShaderOutput { color, alpha: None }
    }
}

impl<'t, T: Real> From<(Var<'t, T>, Var<'t, T>)> for ShaderOutput<'t, T> {
    fn from((color, alpha): (Var<'t, T>, Var<'t, T>)) -> Self {
        ShaderOutput {
            color,
            alpha: Some(alpha),
        }
    }
}

struct DerivOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
}

const ROWS: usize = 1024;

impl<T: Real> Op<T> for DerivOp<T> {
    fn name(&self) -> &'static str {
        "interpolate_derivatives"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let attr = inputs[0].as_standard_layout();
        let nv = self
            .faces
            .iter()
            .flatten()
            .map(|&i| i as usize + 1)
            .max()
            .unwrap_or(0);
        if attr.ndim() != 2 || attr.shape()[0] < nv {
            return Err(AutodiffError::shape(
                "interpolate_derivatives",
                &[attr.shape()],
                format!("attributes must be [V, C] with V >= {nv}"),
            ));
        }
        let c = attr.shape()[1];
        let a = attr.as_slice().expect("std");
        let f = &self.fragments;
        if !f.has_derivatives() {
            return Err(AutodiffError::invalid(
                "interpolate_derivatives",
                "the fragments carry no barycentric derivatives: rasterize with \
                 RasterSettings::barycentric_derivatives = true",
            ));
        }
        let n = f.len();
        let mut out = vec![T::zero(); 2 * n * c];
        if c > 0 {
            out.par_chunks_mut(ROWS * 2 * c)
                .enumerate()
                .for_each(|(blk, chunk)| {
                    for (r, o) in chunk.chunks_mut(2 * c).enumerate() {
                        let i = blk * ROWS + r;
                        let tri = self.faces[f.face[i] as usize];
                        let (dx, dy) = (f.dbary_dx[i], f.dbary_dy[i]);
                        for ch in 0..c {
                            let at = |k: usize| a[tri[k] as usize * c + ch];
                            o[ch] = dx[0] * at(0) + dx[1] * at(1) + dx[2] * at(2);
                            o[c + ch] = dy[0] * at(0) + dy[1] * at(1) + dy[2] * at(2);
                        }
                    }
                });
        }
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[n, 2 * c]), out).expect("n x 2c")
        ])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let shape = ctx.inputs[0].shape();
        let c = shape[1];
        let g = ctx.grad_outputs[0].as_standard_layout();
        let g = g.as_slice().expect("std");
        let f = &self.fragments;
        let mut ga = vec![T::zero(); shape[0] * c];
        // Sequential scatter in fragment order: deterministic.
        for i in 0..f.len() {
            let tri = self.faces[f.face[i] as usize];
            for k in 0..3 {
                let base = tri[k] as usize * c;
                for ch in 0..c {
                    ga[base + ch] += f.dbary_dx[i][k] * g[i * 2 * c + ch]
                        + f.dbary_dy[i][k] * g[i * 2 * c + c + ch];
                }
            }
        }
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(shape), ga).expect("attribute shape"),
        )])
    }
}

/// Screen-space derivatives of vertex attributes `[V, C]` at every fragment: `[N, 2C]`, the
/// `C` derivatives per pixel step right (`col + 1`) then the `C` per step down (`row + 1`),
/// chained from the rasterizer's barycentric derivatives. For uvs `[V, 2]` this is `uv_da`
/// = (du/dx, dv/dx, du/dy, dv/dy), the input of trilinear filtering. Differentiable with
/// respect to the attributes. Its value is an error when `r` was rasterized without
/// [`crate::raster::RasterSettings::barycentric_derivatives`].
pub fn uv_derivatives<'t, T: Real>(attributes: Var<'t, T>, r: &Rasterized<'t, T>) -> Var<'t, T> {
    let op = DerivOp {
        fragments: r.fragments.clone(),
        faces: r.faces.clone(),
    };
    attributes.tape().apply(op, &[attributes])
}

/// Interpolates `mesh` at the fragments of `r` and assembles the [`FragmentInputs`] seen from
/// `eye` (`[3]`).
pub fn fragment_inputs<'t, T: Real>(
    r: &Rasterized<'t, T>,
    mesh: &MeshAttributes<'t, T>,
    eye: Var<'t, T>,
) -> Result<FragmentInputs<'t, T>, RenderError> {
    let eps = T::from_f64c(SAFE_EPS);
    let position = interpolate(mesh.positions, r)?;
    let vn = match mesh.normals {
        Some(n) => n,
        None => vertex_normals(mesh.positions, &r.faces),
    };
    let normal = interpolate(vn, r)?.normalize(eps);
    let view_dir = (eye.reshape(&[3]) - position).normalize(eps);
    let (uv, uv_da) = match mesh.uvs {
        Some(uvs) => (Some(interpolate(uvs, r)?), Some(uv_derivatives(uvs, r))),
        None => (None, None),
    };
    let mut attributes = Vec::with_capacity(mesh.attributes.len());
    for (name, a) in &mesh.attributes {
        attributes.push((name.clone(), interpolate(*a, r)?));
    }
    let out = FragmentInputs {
        position,
        normal,
        view_dir,
        eye,
        uv,
        uv_da,
        depth: r.depth,
        view_depth: r.view_depth,
        attributes,
        fragments: r.fragments.clone(),
        visibility: r.visibility,
    };
    // Surface shape errors now rather than inside the shader.
    out.view_dir.value()?;
    if let Some(uv_da) = out.uv_da {
        uv_da.value()?;
    }
    Ok(out)
}

/// Runs `shader` on the fragments of `r` (see the module docs).
pub fn run_shader<'t, T, F, O>(
    r: &Rasterized<'t, T>,
    mesh: &MeshAttributes<'t, T>,
    eye: Var<'t, T>,
    shader: F,
) -> Result<ShaderOutput<'t, T>, RenderError>
where
    T: Real,
    F: FnOnce(&FragmentInputs<'t, T>) -> O,
    O: Into<ShaderOutput<'t, T>>,
{
    let inputs = fragment_inputs(r, mesh, eye)?;
    // The shader's elementwise ops run fused (one tape op evaluated in cache-sized chunks of
    // fragments, its backward recomputing them: see `autodiff::fused`); other ops inside it
    // run eagerly as before.
    let tape = eye.tape();
    let out: ShaderOutput<'t, T> = tape.fused(|| shader(&inputs).into());
    match out.alpha {
        Some(a) => tape.materialize(&[out.color, a]),
        None => tape.materialize(&[out.color]),
    }
    let cs = out.color.value()?.shape().to_vec();
    if cs.len() != 2 || cs[0] != inputs.len() {
        return Err(AutodiffError::shape(
            "shader",
            &[&cs],
            format!("the shader must return [{}, C] colours", inputs.len()),
        )
        .into());
    }
    if let Some(a) = out.alpha {
        let s = a.value()?.shape().to_vec();
        if s != [inputs.len(), 1] && s != [inputs.len()] {
            return Err(AutodiffError::shape(
                "shader",
                &[&s],
                format!("alpha must be [{}, 1]", inputs.len()),
            )
            .into());
        }
    }
    Ok(out)
}

/// Runs `shader` and composites its colours `[N, C]` over `background` (C values) with the
/// hard z-buffer blend: an image `[H, W, C + 1]` whose last channel is the coverage. With a
/// shader alpha `a`, the colour is `a c + (1 - a) background` and the last channel
/// `coverage * a`.
pub fn render_shader<'t, T, F, O>(
    r: &Rasterized<'t, T>,
    mesh: &MeshAttributes<'t, T>,
    eye: Var<'t, T>,
    shader: F,
    background: &[T],
) -> Result<Var<'t, T>, RenderError>
where
    T: Real,
    F: FnOnce(&FragmentInputs<'t, T>) -> O,
    O: Into<ShaderOutput<'t, T>>,
{
    let out = run_shader(r, mesh, eye, shader)?;
    let c = out.color.shape()[1];
    if background.len() != c {
        return Err(AutodiffError::shape(
            "render_shader",
            &[&out.color.shape(), &[background.len()]],
            "one background value per colour channel",
        )
        .into());
    }
    let Some(alpha) = out.alpha else {
        return blend_hard(out.color, &r.fragments, background);
    };
    let t = out.color.tape();
    let n = out.color.shape()[0];
    let a = alpha.reshape(&[n, 1]);
    let bg = t.constant(ArrayD::from_shape_vec(IxDyn(&[c]), background.to_vec()).expect("c"));
    let col = out.color * a + bg * (-a + T::one());
    let mut bg_alpha = background.to_vec();
    bg_alpha.push(T::zero());
    let img = blend_hard(t.concat(&[col, a], 1), &r.fragments, &bg_alpha)?;
    Ok(img.slice(2, 0, c + 1))
}
