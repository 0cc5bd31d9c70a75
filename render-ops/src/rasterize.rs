//! The rasterizer as a tape op: clip-space positions [V, 4] in, per-fragment barycentrics
//! `[N, 3]`, NDC depth `[N]` and view depth `[N]` out, with the packed fragment layout (which face
//! covers which pixel) kept beside them for the later stages. Backward gives the interior
//! gradients of the `hard` method (fragments keep their faces; barycentrics and depths move).

use std::sync::Arc;

use autodiff::{AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tensor, TensorView, Var};
use ndarray::{ArrayD, IxDyn};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::raster::{rasterize_backward_at, Fragments, RasterSettings};

/// Fragments of one rasterization as tape variables plus their fixed layout.
pub struct Rasterized<'t, T: Real> {
    /// Which face covers which pixel, packed (see [`Fragments`]).
    pub fragments: Arc<Fragments<T>>,
    /// Triangles that were rasterized.
    pub faces: Arc<Vec<[u32; 3]>>,
    /// Barycentrics per fragment [N, 3] (perspective-correct unless the settings say not).
    pub bary: Var<'t, T>,
    /// NDC depth per fragment `[N]`.
    pub depth: Var<'t, T>,
    /// View-space depth per fragment `[N]`.
    pub view_depth: Var<'t, T>,
    /// Light visibility per fragment `[N, L]` (1 lit, 0 in shadow; a constant), where the
    /// visibility method traces shadow rays (`raytrace`); columns: the directional lights,
    /// then the point lights, each in scene order (the order of [`crate::shade::Lights`]).
    pub visibility: Option<Var<'t, T>>,
}

/// Copies a [V, 4] tensor into per-vertex arrays.
pub fn clip_rows<T: Real, S: ndarray::Data<Elem = T>>(
    clip: &ndarray::ArrayBase<S, ndarray::IxDyn>,
) -> Result<Vec<[T; 4]>, RenderError> {
    if clip.ndim() != 2 || clip.shape()[1] != 4 {
        return Err(AutodiffError::shape(
            "rasterize",
            &[clip.shape()],
            "clip positions must be [V, 4]",
        )
        .into());
    }
    if let Some(s) = clip.as_slice() {
        return Ok(s
            .chunks_exact(4)
            .map(|r| [r[0], r[1], r[2], r[3]])
            .collect());
    }
    Ok(clip
        .outer_iter()
        .map(|r| [r[0], r[1], r[2], r[3]])
        .collect())
}

struct RasterizeOp<T: Real> {
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: RasterSettings,
    /// Each fragment's NDC point, where it is not its pixel centre ([`record_at`]).
    points: Option<Vec<[f64; 2]>>,
}

impl<T: Real> Op<T> for RasterizeOp<T> {
    fn name(&self) -> &'static str {
        "rasterize"
    }
    fn forward(&mut self, _inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let f = &self.fragments;
        let n = f.face.len();
        // The three copies in one parallel region (they are the op's only work).
        let (bary, (depth, vdepth)) = rayon::join(
            || par_copy(f.bary.as_flattened()),
            || rayon::join(|| par_copy(&f.depth), || par_copy(&f.view_depth)),
        );
        let bary = ArrayD::from_shape_vec(IxDyn(&[n, 3]), bary).expect("n x 3");
        let depth = ArrayD::from_shape_vec(IxDyn(&[n]), depth).expect("n");
        let vdepth = ArrayD::from_shape_vec(IxDyn(&[n]), vdepth).expect("n");
        Ok(vec![bary, depth, vdepth])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let clip = clip_rows(&ctx.inputs[0]).map_err(|e| AutodiffError::Op {
            op: "rasterize",
            detail: e.to_string(),
        })?;
        let gb = ctx.grad_outputs[0].as_standard_layout();
        let gbary: &[[T; 3]] = as_rows(gb.as_slice().expect("standard"));
        let gd = ctx.grad_outputs[1].as_standard_layout();
        let gv = ctx.grad_outputs[2].as_standard_layout();
        let gd = gd.as_slice().expect("standard");
        let gv = gv.as_slice().expect("standard");
        let any = |s: &[T]| s.iter().any(|v| *v != T::zero());
        let g = rasterize_backward_at(
            &clip,
            &self.faces,
            &self.fragments,
            gbary,
            any(gd).then_some(gd),
            any(gv).then_some(gv),
            &self.settings,
            self.points.as_deref(),
        )
        .map_err(|e| AutodiffError::Op {
            op: "rasterize",
            detail: e.to_string(),
        })?;
        let v = g.len();
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(&[v, 4]), g.into_iter().flatten().collect())
                .expect("v x 4"),
        )])
    }
}

/// The output gradient `i` of an op's backward as `f64` values in standard order.
pub(crate) fn grad_output_f64<T: Real>(ctx: &BackwardCtx<'_, '_, T>, i: usize) -> Vec<f64> {
    ctx.grad_outputs[i]
        .as_standard_layout()
        .iter()
        .map(|x| x.to_f64c())
        .collect()
}

/// The outputs of a stage that yields fragments: barycentrics `[N, 3]`, NDC depth `[N]`, view
/// depth `[N]` copied from `f`, then the per-fragment `extra` `[N]` (a soft probability, an
/// area).
pub(crate) fn fragment_outputs<T: Real>(f: &Fragments<T>, extra: Vec<T>) -> Vec<Tensor<T>> {
    let n = f.len();
    let bary =
        ArrayD::from_shape_vec(IxDyn(&[n, 3]), f.bary.as_flattened().to_vec()).expect("n x 3");
    let depth = ArrayD::from_shape_vec(IxDyn(&[n]), f.depth.clone()).expect("n");
    let vdepth = ArrayD::from_shape_vec(IxDyn(&[n]), f.view_depth.clone()).expect("n");
    let extra = ArrayD::from_shape_vec(IxDyn(&[n]), extra).expect("n");
    vec![bary, depth, vdepth, extra]
}

/// `s.to_vec()`, in parallel over large blocks (written once into uninitialised memory).
pub(crate) fn par_copy<T: Copy + Send + Sync>(s: &[T]) -> Vec<T> {
    const BLOCK: usize = 1 << 15;
    let mut v = Vec::with_capacity(s.len());
    v.spare_capacity_mut()[..s.len()]
        .par_chunks_mut(BLOCK)
        .zip(s.par_chunks(BLOCK))
        .for_each(|(d, s)| {
            for (d, &x) in d.iter_mut().zip(s) {
                d.write(x);
            }
        });
    // SAFETY: every one of the first `s.len()` elements was written above.
    unsafe { v.set_len(s.len()) };
    v
}

/// Views a flat slice of length 3N as N triples.
pub fn as_rows<T>(s: &[T]) -> &[[T; 3]] {
    as_arrays::<T, 3>(s)
}

/// Views a flat slice of length `N * M` as `M` arrays of `N` (`N >= 1`).
pub(crate) fn as_arrays<T, const N: usize>(s: &[T]) -> &[[T; N]] {
    assert!(N > 0);
    assert_eq!(s.len() % N, 0);
    // SAFETY: [T; N] has the layout of N consecutive T (same alignment), and the length is a
    // multiple of N.
    unsafe { std::slice::from_raw_parts(s.as_ptr() as *const [T; N], s.len() / N) }
}

/// Views a flat mutable slice of length `N * M` as `M` arrays of `N` (`N >= 1`).
pub(crate) fn as_arrays_mut<T, const N: usize>(s: &mut [T]) -> &mut [[T; N]] {
    assert!(N > 0);
    assert_eq!(s.len() % N, 0);
    // SAFETY: as `as_arrays`; the borrow is exclusive and moves into the result.
    unsafe { std::slice::from_raw_parts_mut(s.as_mut_ptr() as *mut [T; N], s.len() / N) }
}

/// The hard render of per-vertex attributes `attrs` `[V, C]` (vertex colours) over
/// `background` (`C` values): the image `[H, W, C + 1]` of [`rasterize`] +
/// [`interpolate`](crate::interpolate::interpolate) + [`blend_hard`](crate::blend::blend_hard),
/// last channel the coverage, with one fragment per pixel (`faces_per_pixel` is validated as
/// given, then ignored: only the nearest fragment is drawn).
///
/// When neither `clip` nor `attrs` requires gradients the image is made in one pass without a
/// fragment list ([`crate::raster::render_attributes_direct`]), the same image bit for bit and a
/// constant on the tape; otherwise through the three ops, whose backward gives the interior
/// gradients of the `hard` method.
///
/// # Errors
/// Shapes (`clip` not `[V, 4]`, `attrs` not `[V, C]`), and the rasterizer's errors.
pub fn render_attributes<'t, T: Real>(
    clip: Var<'t, T>,
    attrs: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RasterSettings,
    background: &[T],
) -> Result<Var<'t, T>, RenderError> {
    let (cs, as_) = (clip.shape(), attrs.shape());
    if cs.len() != 2
        || cs[1] != 4
        || as_.len() != 2
        || as_[0] != cs[0]
        || as_[1] != background.len()
    {
        return Err(AutodiffError::shape(
            "render_attributes",
            &[&cs, &as_],
            format!(
                "clip positions must be [V, 4] and attributes [V, {}] (one value per background channel)",
                background.len()
            ),
        )
        .into());
    }
    // The settings as given are checked (the same limits as `rasterize`, also on
    // `faces_per_pixel`), then one fragment per pixel is drawn.
    settings.validate()?;
    let s = RasterSettings {
        faces_per_pixel: 1,
        ..*settings
    };
    if clip.requires_grad() || attrs.requires_grad() {
        let r = rasterize(clip, faces, &s)?;
        let colors = crate::interpolate::interpolate(attrs, &r)?;
        return crate::blend::blend_hard(colors, &r.fragments, background);
    }
    let cv = clip.value_ref()?;
    let rows = clip_rows(&cv.view())?;
    let av = attrs.value_ref()?;
    let av = av.view();
    let a = av.as_standard_layout();
    let img = crate::raster::render_attributes_direct(
        &rows,
        &faces,
        a.as_slice().expect("standard layout"),
        background,
        &s,
    )?;
    let shape = [s.height, s.width, background.len() + 1];
    Ok(clip
        .tape()
        .constant(ArrayD::from_shape_vec(IxDyn(&shape), img).expect("h x w x (c + 1)")))
}

/// Rasterizes clip-space positions [V, 4] with the given faces (hard z-buffer, up to K
/// fragments per pixel), recording the op on the tape.
pub fn rasterize<'t, T: Real>(
    clip: Var<'t, T>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RasterSettings,
) -> Result<Rasterized<'t, T>, RenderError> {
    let rows = clip_rows(&clip.value_ref()?.view())?;
    let fragments = Arc::new(crate::raster::rasterize_fragments(&rows, &faces, settings)?);
    Ok(record(clip, fragments, faces, settings))
}

/// Records `fragments` of `faces` (computed by the caller from `clip`, each fragment's
/// barycentrics and depths those of its pixel centre) as the outputs of a rasterize op: their
/// backward is [`crate::raster::rasterize_backward`], which recomputes the barycentrics at the
/// pixel centre whether or not it lies inside the face (extrapolated barycentrics, as
/// `tf_mesh`'s silhouette band uses).
pub(crate) fn record<'t, T: Real>(
    clip: Var<'t, T>,
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RasterSettings,
) -> Rasterized<'t, T> {
    record_at(clip, fragments, faces, settings, None)
}

/// [`record`] for fragments whose barycentrics and depths are those of their own NDC point
/// `points[i]` (perspective-correct; the ray tracer's jittered samples,
/// [`crate::raytrace::stage`]): their backward takes the same product at that point.
pub(crate) fn record_at<'t, T: Real>(
    clip: Var<'t, T>,
    fragments: Arc<Fragments<T>>,
    faces: Arc<Vec<[u32; 3]>>,
    settings: &RasterSettings,
    points: Option<Vec<[f64; 2]>>,
) -> Rasterized<'t, T> {
    let op = RasterizeOp {
        fragments: fragments.clone(),
        faces: faces.clone(),
        settings: *settings,
        points,
    };
    let outs = clip.tape().apply_multi(op, &[clip], 3);
    Rasterized {
        fragments,
        faces,
        bary: outs[0],
        depth: outs[1],
        view_depth: outs[2],
        visibility: None,
    }
}
