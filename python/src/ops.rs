//! The functional API: each op a forward function over numpy arrays and a vector-Jacobian
//! product `*_vjp(..., grad_out, needs=None)` that returns the gradient of
//! `sum(output * grad_out)` with respect to each differentiable input (`None` for the inputs
//! that `needs` marks False), so that any autodiff framework can wrap them.
//!
//! Both run the library's ops on a fresh tape: the forward with constant inputs (the ops'
//! no-gradient fast paths), the VJP with the needed inputs as variables, the forward again
//! (deterministic, so the same fragments) and one reverse walk ([`autodiff::Tape::vjp`], or
//! for several outputs the gradient of `sum_i <out_i, g_i>`, whose seed is exactly each `g_i`).

use std::sync::Arc;

use autodiff::{Real, Tape, Tensor, Var};
use numpy::Element;
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use render_ops::error::RenderError;
use render_ops::raster::Fragments as RawFragments;
use render_ops::scene::Method;
use render_ops::shade::lights::{
    AmbientLight, DirectionalLight, Lights, Material, PointLight, Reflectance,
};
use render_ops::shade::phong::Surface;
use render_ops::texture::{Filter, Sampler, Wrap};
use render_ops::{MethodSettings, Rasterized};

use crate::array::{
    check_shape, dtype_of, faces as read_faces, floats, to_numpy, with_dtype, Floats,
};
use crate::to_py;

/// Builds an op's outputs from its inputs on a tape.
pub(crate) type Build<T> = dyn for<'t> Fn(&'t Tape<T>, &[Var<'t, T>]) -> Result<Vec<Var<'t, T>>, RenderError>
    + Send
    + Sync;

/// The op's outputs with constant inputs.
pub(crate) fn forward<T: Real>(
    inputs: Vec<Floats<T>>,
    build: &Build<T>,
) -> Result<Vec<Tensor<T>>, String> {
    let tape = Tape::new();
    let vars: Vec<Var<'_, T>> = inputs.iter().map(|x| x.var(&tape, false)).collect();
    let outs = build(&tape, &vars).map_err(|e| e.to_string())?;
    let vals = outs
        .iter()
        .map(|o| o.value().map_err(|e| e.to_string()))
        .collect::<Result<Vec<_>, _>>()?;
    drop(vars);
    drop(tape);
    // The tape is gone: each value is usually held only here now, so no copy.
    Ok(vals.into_iter().map(Arc::unwrap_or_clone).collect())
}

/// The gradients of `sum_i <out_i, grads_i>` with respect to the inputs marked in `needs`.
/// A single output's gradient is copied once (the reverse walk reuses the seed's buffer).
pub(crate) fn vjp<T: Real>(
    inputs: Vec<Floats<T>>,
    needs: &[bool],
    build: &Build<T>,
    grads: Vec<Floats<T>>,
) -> Result<Vec<Option<Tensor<T>>>, String> {
    let tape = Tape::new();
    let vars: Vec<Var<'_, T>> = inputs
        .iter()
        .zip(needs)
        .map(|(x, &n)| x.var(&tape, n))
        .collect();
    let outs = build(&tape, &vars).map_err(|e| e.to_string())?;
    if outs.len() != grads.len() {
        return Err(format!(
            "{} output gradients for {} outputs",
            grads.len(),
            outs.len()
        ));
    }
    for (i, (o, g)) in outs.iter().zip(&grads).enumerate() {
        if o.shape() != g.shape() {
            return Err(format!(
                "grad_out{}: shape {:?}, expected the output's shape {:?}",
                if outs.len() > 1 {
                    format!("[{i}]")
                } else {
                    String::new()
                },
                g.shape(),
                o.shape()
            ));
        }
    }
    let gr = if outs.len() == 1 {
        tape.vjp(outs[0], grads[0].to_tensor())
    } else {
        let mut total: Option<Var<'_, T>> = None;
        for (o, g) in outs.iter().zip(&grads) {
            let term = (*o * g.var(&tape, false)).sum();
            total = Some(match total {
                Some(t) => t + term,
                None => term,
            });
        }
        tape.backward(total.expect("outputs"))
    }
    .map_err(|e| e.to_string())?;
    Ok(vars
        .iter()
        .zip(needs)
        .map(|(v, &n)| n.then(|| gr.wrt(*v)))
        .collect())
}

/// `needs` as given (one flag per differentiable input), or all true.
fn needs_of(needs: Option<Vec<bool>>, n: usize, names: &str) -> PyResult<Vec<bool>> {
    match needs {
        None => Ok(vec![true; n]),
        Some(v) if v.len() == n => Ok(v),
        Some(v) => Err(PyValueError::new_err(format!(
            "needs: {} flags, expected {n} ({names})",
            v.len()
        ))),
    }
}

fn grads_tuple<'py, T: Element>(
    py: Python<'py>,
    gs: Vec<Option<Tensor<T>>>,
) -> Vec<Option<Bound<'py, PyAny>>> {
    gs.into_iter().map(|g| g.map(|g| to_numpy(py, g))).collect()
}

fn one<T>(mut v: Vec<T>) -> T {
    v.swap_remove(0)
}

// ---------------------------------------------------------------------------------------
// Settings of the methods (a dict from Python).

const SETTINGS: &str = "width, height, method, background, faces_per_pixel, cull_backfaces, perspective_correct, sigma, gamma, eps, threshold, delta, overdraw_px, near, far";

/// A method's settings from a dict: `width` and `height` required, `method` (default "hard"),
/// the rest as in [`MethodSettings`] (defaults: [`MethodSettings::new`]).
pub(crate) fn method_settings(d: &Bound<'_, PyDict>) -> PyResult<MethodSettings> {
    let get = |k: &str| d.get_item(k);
    let req = |k: &str| -> PyResult<usize> {
        get(k)?
            .ok_or_else(|| PyValueError::new_err(format!("settings: '{k}' is required")))?
            .extract()
    };
    let (w, h) = (req("width")?, req("height")?);
    let method = match get("method")? {
        None => Method::Hard,
        Some(m) => {
            let name: String = m.extract()?;
            Method::from_name(&name).ok_or_else(|| {
                PyValueError::new_err(format!(
                    "method '{name}': expected one of {}",
                    Method::ALL.map(|m| m.name()).join(", ")
                ))
            })?
        }
    };
    let mut s = MethodSettings::new(method, w, h);
    for (k, v) in d.iter() {
        let k: String = k.extract()?;
        match k.as_str() {
            "width" | "height" | "method" => {}
            "background" => s.view.background = v.extract()?,
            "faces_per_pixel" => {
                let n: usize = v.extract()?;
                s.faces_per_pixel = n;
                s.soft_faces_per_pixel = Some(n);
            }
            "cull_backfaces" => s.view.cull_backfaces = v.extract()?,
            "perspective_correct" => s.view.perspective_correct = v.extract()?,
            "sigma" => s.sigma = v.extract()?,
            "gamma" => s.gamma = v.extract()?,
            "eps" => s.eps = v.extract()?,
            "threshold" => s.threshold = v.extract()?,
            "delta" => s.delta = v.extract()?,
            "overdraw_px" => s.overdraw_px = v.extract()?,
            "near" => s.near = v.extract()?,
            "far" => s.far = v.extract()?,
            _ => {
                return Err(PyValueError::new_err(format!(
                    "settings: unknown '{k}'; one of {SETTINGS}"
                )))
            }
        }
    }
    if s.view.background.iter().any(|b| !b.is_finite()) {
        return Err(PyValueError::new_err("settings: background must be finite"));
    }
    Ok(s)
}

// ---------------------------------------------------------------------------------------
// render: each method's render of per-vertex colours.

fn render_build<T: Real>(faces: Arc<Vec<[u32; 3]>>, s: MethodSettings) -> Box<Build<T>> {
    Box::new(move |_, v| {
        Ok(vec![render_ops::render_vertex_colors(
            v[0],
            v[1],
            faces.clone(),
            &s,
        )?])
    })
}

/// The colours' channel count must match the background's (zeros when not given).
fn fit_background(s: &mut MethodSettings, c: usize) -> PyResult<()> {
    if s.view.background.is_empty() {
        s.view.background = vec![0.0; c];
    }
    if s.view.background.len() != c {
        return Err(PyValueError::new_err(format!(
            "settings: background has {} values, colors have {c} channels",
            s.view.background.len()
        )));
    }
    Ok(())
}

/// render(clip, faces, colors, settings)
/// The image [H, W, C + 1] of per-vertex colours [V, C] over `faces` from clip positions
/// [V, 4] with a method and its settings (`render_ops::methods::render_vertex_colors`).
#[pyfunction]
fn render<'py>(
    py: Python<'py>,
    clip: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    colors: &Bound<'py, PyAny>,
    settings: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyAny>> {
    let mut s = method_settings(settings)?;
    let f = Arc::new(read_faces(faces)?);
    with_dtype!(dtype_of("clip", clip)?, T => {
        let c = floats::<T>("clip", clip, &[None, Some(4)], "[V, 4]")?;
        let col = floats::<T>("colors", colors, &[Some(c.shape()[0]), None], "[V, C] (V of clip)")?;
        fit_background(&mut s, col.shape()[1])?;
        let b = render_build::<T>(f, s);
        let out = py.detach(|| forward(vec![c, col], &*b)).map_err(to_py)?;
        Ok(to_numpy(py, one(out)))
    })
}

/// render_vjp(clip, faces, colors, grad_out, settings, needs=None) -> (grad_clip, grad_colors)
#[pyfunction]
#[pyo3(signature = (clip, faces, colors, grad_out, settings, needs = None))]
fn render_vjp<'py>(
    py: Python<'py>,
    clip: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    colors: &Bound<'py, PyAny>,
    grad_out: &Bound<'py, PyAny>,
    settings: &Bound<'py, PyDict>,
    needs: Option<Vec<bool>>,
) -> PyResult<Vec<Option<Bound<'py, PyAny>>>> {
    let mut s = method_settings(settings)?;
    let needs = needs_of(needs, 2, "clip, colors")?;
    let f = Arc::new(read_faces(faces)?);
    with_dtype!(dtype_of("clip", clip)?, T => {
        let c = floats::<T>("clip", clip, &[None, Some(4)], "[V, 4]")?;
        let col = floats::<T>("colors", colors, &[Some(c.shape()[0]), None], "[V, C] (V of clip)")?;
        fit_background(&mut s, col.shape()[1])?;
        let g = floats::<T>("grad_out", grad_out, &[None, None, None], "[H, W, C + 1]")?;
        let b = render_build::<T>(f, s);
        let gs = py.detach(|| vjp(vec![c, col], &needs, &*b, vec![g])).map_err(to_py)?;
        Ok(grads_tuple(py, gs))
    })
}

// ---------------------------------------------------------------------------------------
// rasterize, interpolate, blend: the fragment pipeline.

enum AnyFragments {
    F32(Arc<RawFragments<f32>>),
    F64(Arc<RawFragments<f64>>),
}

/// The fragments of one rasterization: which face covers which pixel (packed per pixel,
/// `offsets` [H*W + 1] into the per-fragment arrays `face` [N], `bary` [N, 3], `depth` [N],
/// `view_depth` [N]), and the triangles rasterized.
#[pyclass(frozen, module = "tapestry")]
pub struct Fragments {
    frags: AnyFragments,
    faces: Arc<Vec<[u32; 3]>>,
}

/// Shares the fragments of dtype `T` (a `TypeError` for the other dtype).
trait FragmentsOf: Real + Element {
    fn of(f: &Fragments) -> PyResult<Arc<RawFragments<Self>>>;
    fn wrap(f: Arc<RawFragments<Self>>) -> AnyFragments;
}

impl FragmentsOf for f32 {
    fn of(f: &Fragments) -> PyResult<Arc<RawFragments<f32>>> {
        match &f.frags {
            AnyFragments::F32(x) => Ok(x.clone()),
            AnyFragments::F64(_) => Err(PyTypeError::new_err(
                "fragments: float64 fragments with float32 arrays (the float inputs of one call share a dtype)",
            )),
        }
    }
    fn wrap(f: Arc<RawFragments<f32>>) -> AnyFragments {
        AnyFragments::F32(f)
    }
}

impl FragmentsOf for f64 {
    fn of(f: &Fragments) -> PyResult<Arc<RawFragments<f64>>> {
        match &f.frags {
            AnyFragments::F64(x) => Ok(x.clone()),
            AnyFragments::F32(_) => Err(PyTypeError::new_err(
                "fragments: float32 fragments with float64 arrays (the float inputs of one call share a dtype)",
            )),
        }
    }
    fn wrap(f: Arc<RawFragments<f64>>) -> AnyFragments {
        AnyFragments::F64(f)
    }
}

fn field<'py, T: Element + Copy>(py: Python<'py>, v: Vec<T>, shape: &[usize]) -> Bound<'py, PyAny> {
    to_numpy(
        py,
        ndarray::ArrayD::from_shape_vec(ndarray::IxDyn(shape), v).expect("shape"),
    )
}

macro_rules! on_fragments {
    ($self:expr, $f:ident => $body:expr) => {
        match &$self.frags {
            AnyFragments::F32($f) => $body,
            AnyFragments::F64($f) => $body,
        }
    };
}

#[pymethods]
impl Fragments {
    /// Image width.
    #[getter]
    fn width(&self) -> usize {
        on_fragments!(self, f => f.width)
    }
    /// Image height.
    #[getter]
    fn height(&self) -> usize {
        on_fragments!(self, f => f.height)
    }
    /// Number of fragments N.
    fn __len__(&self) -> usize {
        on_fragments!(self, f => f.face.len())
    }
    /// Offsets [H*W + 1] (int64): pixel p's fragments are offsets[p]:offsets[p + 1], nearest first.
    #[getter]
    fn offsets<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        on_fragments!(self, f => field(py, f.offsets.iter().map(|&x| x as i64).collect(), &[f.offsets.len()]))
    }
    /// Face index of each fragment [N] (int64).
    #[getter]
    fn face<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        on_fragments!(self, f => field(py, f.face.iter().map(|&x| x as i64).collect(), &[f.face.len()]))
    }
    /// Barycentrics [N, 3] (a copy).
    #[getter]
    fn bary<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        on_fragments!(self, f => field(py, f.bary.iter().flatten().copied().collect(), &[f.bary.len(), 3]))
    }
    /// NDC depth [N] (a copy).
    #[getter]
    fn depth<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        on_fragments!(self, f => field(py, f.depth.clone(), &[f.depth.len()]))
    }
    /// View depth (w_clip) [N] (a copy).
    #[getter]
    fn view_depth<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        on_fragments!(self, f => field(py, f.view_depth.clone(), &[f.view_depth.len()]))
    }
    /// The triangles rasterized [F, 3] (int64).
    #[getter]
    fn faces<'py>(&self, py: Python<'py>) -> Bound<'py, PyAny> {
        field(
            py,
            self.faces.iter().flatten().map(|&x| x as i64).collect(),
            &[self.faces.len(), 3],
        )
    }
    /// "float32" or "float64".
    #[getter]
    fn dtype(&self) -> &'static str {
        match self.frags {
            AnyFragments::F32(_) => "float32",
            AnyFragments::F64(_) => "float64",
        }
    }
    fn __repr__(&self) -> String {
        format!(
            "Fragments({}x{}, {} fragments, {})",
            self.width(),
            self.height(),
            self.__len__(),
            self.dtype()
        )
    }
}

fn raster_build<T: Real>(faces: Arc<Vec<[u32; 3]>>, s: MethodSettings) -> Box<Build<T>> {
    Box::new(move |_, v| {
        let r = render_ops::rasterize(v[0], faces.clone(), &s.raster())?;
        Ok(vec![r.bary, r.depth, r.view_depth])
    })
}

/// rasterize(clip, faces, settings) -> Fragments
/// Hard rasterization of clip positions [V, 4] (settings: width, height, faces_per_pixel,
/// cull_backfaces, perspective_correct).
#[pyfunction]
fn rasterize<'py>(
    py: Python<'py>,
    clip: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    settings: &Bound<'py, PyDict>,
) -> PyResult<Fragments> {
    let s = method_settings(settings)?;
    let f = Arc::new(read_faces(faces)?);
    with_dtype!(dtype_of("clip", clip)?, T => {
        let c = floats::<T>("clip", clip, &[None, Some(4)], "[V, 4]")?;
        let f2 = f.clone();
        let frags = py
            .detach(move || -> Result<_, String> {
                let tape = Tape::new();
                let r = render_ops::rasterize(c.var(&tape, false), f2, &s.raster()).map_err(|e| e.to_string())?;
                Ok(r.fragments.clone())
            })
            .map_err(to_py)?;
        Ok(Fragments { frags: <T as FragmentsOf>::wrap(frags), faces: f })
    })
}

/// rasterize_vjp(clip, faces, settings, grad_bary, grad_depth, grad_view_depth) -> grad_clip
/// (the interior gradient: fragments keep their faces; barycentrics and depths move).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn rasterize_vjp<'py>(
    py: Python<'py>,
    clip: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    settings: &Bound<'py, PyDict>,
    grad_bary: &Bound<'py, PyAny>,
    grad_depth: &Bound<'py, PyAny>,
    grad_view_depth: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyAny>> {
    let s = method_settings(settings)?;
    let f = Arc::new(read_faces(faces)?);
    with_dtype!(dtype_of("clip", clip)?, T => {
        let c = floats::<T>("clip", clip, &[None, Some(4)], "[V, 4]")?;
        let gb = floats::<T>("grad_bary", grad_bary, &[None, Some(3)], "[N, 3]")?;
        let gd = floats::<T>("grad_depth", grad_depth, &[None], "[N]")?;
        let gv = floats::<T>("grad_view_depth", grad_view_depth, &[None], "[N]")?;
        let b = raster_build::<T>(f, s);
        let gs = py.detach(|| vjp(vec![c], &[true], &*b, vec![gb, gd, gv])).map_err(to_py)?;
        Ok(to_numpy(py, one(gs).expect("needed")))
    })
}

/// The fragments of `frags` with barycentrics `bary` (a variable) as a [`Rasterized`].
fn rasterized<'t, T: FragmentsOf>(
    tape: &'t Tape<T>,
    frags: &Arc<RawFragments<T>>,
    faces: &Arc<Vec<[u32; 3]>>,
    bary: Var<'t, T>,
) -> Rasterized<'t, T> {
    let n = frags.face.len();
    let empty = || tape.constant(ndarray::ArrayD::zeros(ndarray::IxDyn(&[n])));
    Rasterized {
        fragments: frags.clone(),
        faces: faces.clone(),
        bary,
        depth: empty(),
        view_depth: empty(),
        visibility: None,
    }
}

fn bary_input<T: FragmentsOf>(
    fr: &Fragments,
    bary: Option<&Bound<'_, PyAny>>,
) -> PyResult<Floats<T>> {
    let f = T::of(fr)?;
    let n = f.face.len();
    match bary {
        Some(b) => floats::<T>("bary", b, &[Some(n), Some(3)], "[N, 3] (N fragments)"),
        None => Ok(Floats::owned(
            vec![n, 3],
            f.bary.iter().flatten().copied().collect(),
        )),
    }
}

fn interpolate_build<T: FragmentsOf>(fr: &Fragments) -> PyResult<Box<Build<T>>> {
    let (frags, faces) = (T::of(fr)?, fr.faces.clone());
    Ok(Box::new(move |tape, v| {
        let r = rasterized(tape, &frags, &faces, v[1]);
        Ok(vec![render_ops::interpolate(v[0], &r)?])
    }))
}

/// interpolate(attributes, fragments, bary=None) -> [N, C]
/// Vertex attributes [V, C] at every fragment; `bary` [N, 3] defaults to the fragments' own.
#[pyfunction]
#[pyo3(signature = (attributes, fragments, bary = None))]
fn interpolate<'py>(
    py: Python<'py>,
    attributes: &Bound<'py, PyAny>,
    fragments: &Fragments,
    bary: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    with_dtype!(dtype_of("attributes", attributes)?, T => {
        let a = floats::<T>("attributes", attributes, &[None, None], "[V, C]")?;
        let b = bary_input::<T>(fragments, bary)?;
        let build = interpolate_build::<T>(fragments)?;
        let out = py.detach(|| forward(vec![a, b], &*build)).map_err(to_py)?;
        Ok(to_numpy(py, one(out)))
    })
}

/// interpolate_vjp(attributes, fragments, grad_out, bary=None, needs=None) -> (grad_attributes, grad_bary)
#[pyfunction]
#[pyo3(signature = (attributes, fragments, grad_out, bary = None, needs = None))]
fn interpolate_vjp<'py>(
    py: Python<'py>,
    attributes: &Bound<'py, PyAny>,
    fragments: &Fragments,
    grad_out: &Bound<'py, PyAny>,
    bary: Option<&Bound<'py, PyAny>>,
    needs: Option<Vec<bool>>,
) -> PyResult<Vec<Option<Bound<'py, PyAny>>>> {
    let needs = needs_of(needs, 2, "attributes, bary")?;
    with_dtype!(dtype_of("attributes", attributes)?, T => {
        let a = floats::<T>("attributes", attributes, &[None, None], "[V, C]")?;
        let b = bary_input::<T>(fragments, bary)?;
        let g = floats::<T>("grad_out", grad_out, &[None, None], "[N, C]")?;
        let build = interpolate_build::<T>(fragments)?;
        let gs = py.detach(|| vjp(vec![a, b], &needs, &*build, vec![g])).map_err(to_py)?;
        Ok(grads_tuple(py, gs))
    })
}

fn blend_build<T: FragmentsOf>(fr: &Fragments, background: Vec<f64>) -> PyResult<Box<Build<T>>> {
    let frags = T::of(fr)?;
    Ok(Box::new(move |_, v| {
        let bg: Vec<T> = background.iter().map(|&b| T::from_f64c(b)).collect();
        Ok(vec![render_ops::blend_hard(v[0], &frags, &bg)?])
    }))
}

fn background_of(background: Option<Vec<f64>>, c: usize) -> PyResult<Vec<f64>> {
    let bg = background.unwrap_or_else(|| vec![0.0; c]);
    if bg.len() != c || bg.iter().any(|b| !b.is_finite()) {
        return Err(PyValueError::new_err(format!(
            "background: {} values, expected {c} finite values (one per colour channel)",
            bg.len()
        )));
    }
    Ok(bg)
}

/// blend(colors, fragments, background=None) -> [H, W, C + 1]
/// Hard z-buffer compositing of fragment colours [N, C] over the background (C values,
/// default zeros); the last channel is the coverage.
#[pyfunction]
#[pyo3(signature = (colors, fragments, background = None))]
fn blend<'py>(
    py: Python<'py>,
    colors: &Bound<'py, PyAny>,
    fragments: &Fragments,
    background: Option<Vec<f64>>,
) -> PyResult<Bound<'py, PyAny>> {
    with_dtype!(dtype_of("colors", colors)?, T => {
        let c = floats::<T>("colors", colors, &[Some(fragments.__len__()), None], "[N, C] (N fragments)")?;
        let build = blend_build::<T>(fragments, background_of(background, c.shape()[1])?)?;
        let out = py.detach(|| forward(vec![c], &*build)).map_err(to_py)?;
        Ok(to_numpy(py, one(out)))
    })
}

/// blend_vjp(colors, fragments, grad_out, background=None) -> grad_colors
#[pyfunction]
#[pyo3(signature = (colors, fragments, grad_out, background = None))]
fn blend_vjp<'py>(
    py: Python<'py>,
    colors: &Bound<'py, PyAny>,
    fragments: &Fragments,
    grad_out: &Bound<'py, PyAny>,
    background: Option<Vec<f64>>,
) -> PyResult<Bound<'py, PyAny>> {
    with_dtype!(dtype_of("colors", colors)?, T => {
        let c = floats::<T>("colors", colors, &[Some(fragments.__len__()), None], "[N, C] (N fragments)")?;
        let g = floats::<T>("grad_out", grad_out, &[None, None, None], "[H, W, C + 1]")?;
        let build = blend_build::<T>(fragments, background_of(background, c.shape()[1])?)?;
        let gs = py.detach(|| vjp(vec![c], &[true], &*build, vec![g])).map_err(to_py)?;
        Ok(to_numpy(py, one(gs).expect("needed")))
    })
}

// ---------------------------------------------------------------------------------------
// texture, shade_sh, shade_phong: fragment-stage ops.

fn sampler(filter: &str, wrap: &str) -> PyResult<Sampler> {
    let filter = match filter {
        "nearest" => Filter::Nearest,
        "bilinear" => Filter::Bilinear,
        _ => {
            return Err(PyValueError::new_err(format!(
                "filter '{filter}': expected 'nearest' or 'bilinear'"
            )))
        }
    };
    let wrap = match wrap {
        "repeat" => Wrap::Repeat,
        "clamp" => Wrap::Clamp,
        "mirror" => Wrap::Mirror,
        _ => {
            return Err(PyValueError::new_err(format!(
                "wrap '{wrap}': expected 'repeat', 'clamp' or 'mirror'"
            )))
        }
    };
    Ok(Sampler::new(filter, wrap))
}

fn texture_build<T: Real>(s: Sampler) -> Box<Build<T>> {
    Box::new(move |_, v| Ok(vec![render_ops::texture::sample(v[0], v[1], None, s)]))
}

/// texture(texels, uv, filter="bilinear", wrap="repeat") -> [N, C]
/// Samples texels [H, W, C] (row 0 at the top) at uv [N, 2] (u right, v up, in [0, 1]).
#[pyfunction]
#[pyo3(signature = (texels, uv, filter = "bilinear", wrap = "repeat"))]
fn texture<'py>(
    py: Python<'py>,
    texels: &Bound<'py, PyAny>,
    uv: &Bound<'py, PyAny>,
    filter: &str,
    wrap: &str,
) -> PyResult<Bound<'py, PyAny>> {
    let s = sampler(filter, wrap)?;
    with_dtype!(dtype_of("texels", texels)?, T => {
        let t = floats::<T>("texels", texels, &[None, None, None], "[H, W, C]")?;
        let u = floats::<T>("uv", uv, &[None, Some(2)], "[N, 2]")?;
        let b = texture_build::<T>(s);
        let out = py.detach(|| forward(vec![t, u], &*b)).map_err(to_py)?;
        Ok(to_numpy(py, one(out)))
    })
}

/// texture_vjp(texels, uv, grad_out, filter="bilinear", wrap="repeat", needs=None) -> (grad_texels, grad_uv)
#[pyfunction]
#[pyo3(signature = (texels, uv, grad_out, filter = "bilinear", wrap = "repeat", needs = None))]
fn texture_vjp<'py>(
    py: Python<'py>,
    texels: &Bound<'py, PyAny>,
    uv: &Bound<'py, PyAny>,
    grad_out: &Bound<'py, PyAny>,
    filter: &str,
    wrap: &str,
    needs: Option<Vec<bool>>,
) -> PyResult<Vec<Option<Bound<'py, PyAny>>>> {
    let s = sampler(filter, wrap)?;
    let needs = needs_of(needs, 2, "texels, uv")?;
    with_dtype!(dtype_of("texels", texels)?, T => {
        let t = floats::<T>("texels", texels, &[None, None, None], "[H, W, C]")?;
        let u = floats::<T>("uv", uv, &[None, Some(2)], "[N, 2]")?;
        let g = floats::<T>("grad_out", grad_out, &[None, None], "[N, C]")?;
        let b = texture_build::<T>(s);
        let gs = py.detach(|| vjp(vec![t, u], &needs, &*b, vec![g])).map_err(to_py)?;
        Ok(grads_tuple(py, gs))
    })
}

fn sh_build<T: Real>() -> Box<Build<T>> {
    Box::new(|_, v| Ok(vec![render_ops::shade::sh_shade(v[0], v[1], v[2])]))
}

fn sh_inputs<T: Element + Real>(
    normal: &Bound<'_, PyAny>,
    albedo: &Bound<'_, PyAny>,
    coeffs: &Bound<'_, PyAny>,
) -> PyResult<Vec<Floats<T>>> {
    let n = floats::<T>("normal", normal, &[None, Some(3)], "[N, 3]")?;
    let a = floats::<T>("albedo", albedo, &[None, None], "[N, 3]")
        .or_else(|_| floats::<T>("albedo", albedo, &[Some(3)], "[N, 3] or [3]"))?;
    if a.ndim() == 2 {
        check_shape(
            "albedo",
            a.shape(),
            &[Some(n.shape()[0]), Some(3)],
            "[N, 3] (N of normal) or [3]",
        )?;
    }
    let c = floats::<T>("coeffs", coeffs, &[Some(9), Some(3)], "[9, 3]")?;
    Ok(vec![n, a, c])
}

/// shade_sh(normal, albedo, coeffs) -> [N, 3]
/// Order-2 spherical-harmonics lighting of normals [N, 3] (any length), albedo [N, 3] or
/// [3] and coefficients [9, 3] (docs/CONVENTIONS.md order).
#[pyfunction]
fn shade_sh<'py>(
    py: Python<'py>,
    normal: &Bound<'py, PyAny>,
    albedo: &Bound<'py, PyAny>,
    coeffs: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyAny>> {
    with_dtype!(dtype_of("normal", normal)?, T => {
        let ins = sh_inputs::<T>(normal, albedo, coeffs)?;
        let b = sh_build::<T>();
        let out = py.detach(|| forward(ins, &*b)).map_err(to_py)?;
        Ok(to_numpy(py, one(out)))
    })
}

/// shade_sh_vjp(normal, albedo, coeffs, grad_out, needs=None) -> (grad_normal, grad_albedo, grad_coeffs)
#[pyfunction]
#[pyo3(signature = (normal, albedo, coeffs, grad_out, needs = None))]
fn shade_sh_vjp<'py>(
    py: Python<'py>,
    normal: &Bound<'py, PyAny>,
    albedo: &Bound<'py, PyAny>,
    coeffs: &Bound<'py, PyAny>,
    grad_out: &Bound<'py, PyAny>,
    needs: Option<Vec<bool>>,
) -> PyResult<Vec<Option<Bound<'py, PyAny>>>> {
    let needs = needs_of(needs, 3, "normal, albedo, coeffs")?;
    with_dtype!(dtype_of("normal", normal)?, T => {
        let ins = sh_inputs::<T>(normal, albedo, coeffs)?;
        let g = floats::<T>("grad_out", grad_out, &[None, Some(3)], "[N, 3]")?;
        let b = sh_build::<T>();
        let gs = py.detach(|| vjp(ins, &needs, &*b, vec![g])).map_err(to_py)?;
        Ok(grads_tuple(py, gs))
    })
}

const PHONG_INPUTS: [&str; 11] = [
    "position",
    "normal",
    "albedo",
    "eye",
    "ambient",
    "light_dir",
    "light_color",
    "ks",
    "shininess",
    "point_position",
    "point_color",
];

fn reflectance(model: &str) -> PyResult<Reflectance> {
    match model {
        "lambert" => Ok(Reflectance::Lambert),
        "phong" => Ok(Reflectance::Phong),
        "blinn_phong" => Ok(Reflectance::BlinnPhong),
        _ => Err(PyValueError::new_err(format!(
            "model '{model}': expected 'lambert', 'phong' or 'blinn_phong'"
        ))),
    }
}

/// The rows `[3]` of a `[L, 3]` variable, one per light.
fn light_rows<'t, T: Real>(x: Var<'t, T>) -> impl Iterator<Item = Var<'t, T>> {
    (0..x.shape()[0]).map(move |l| x.slice(0, l, l + 1))
}

/// `render_ops::shade::shade` over the inputs of [`phong_inputs`]: the nine of
/// `PHONG_INPUTS`, then the point lights' positions and colours when given.
fn phong_build<T: Real>(model: Reflectance) -> Box<Build<T>> {
    Box::new(move |_, v| {
        let surface = Surface {
            position: v[0],
            normal: v[1],
            albedo: v[2],
            visibility: None,
        };
        let lights = Lights {
            ambient: vec![AmbientLight { color: v[4] }],
            directional: light_rows(v[5])
                .zip(light_rows(v[6]))
                .map(|(direction, color)| DirectionalLight { direction, color })
                .collect(),
            point: match v.get(9..11) {
                Some(&[p, c]) => light_rows(p)
                    .zip(light_rows(c))
                    .map(|(position, color)| PointLight { position, color })
                    .collect(),
                _ => Vec::new(),
            },
            sh: None,
        };
        let material = Material {
            model,
            ka: None,
            ks: v[7],
            shininess: v[8],
        };
        Ok(vec![render_ops::shade::shade(
            &surface, &material, &lights, v[3],
        )])
    })
}

/// The inputs of `shade_phong`, checked: the nine of `PHONG_INPUTS`, then `point_position`
/// and `point_color` `[P, 3]` when given (both or neither).
#[allow(clippy::too_many_arguments)]
fn phong_inputs<T: Element + Real>(
    position: &Bound<'_, PyAny>,
    normal: &Bound<'_, PyAny>,
    albedo: &Bound<'_, PyAny>,
    eye: &Bound<'_, PyAny>,
    ambient: &Bound<'_, PyAny>,
    light_dir: &Bound<'_, PyAny>,
    light_color: &Bound<'_, PyAny>,
    ks: &Bound<'_, PyAny>,
    shininess: &Bound<'_, PyAny>,
    point_position: Option<&Bound<'_, PyAny>>,
    point_color: Option<&Bound<'_, PyAny>>,
) -> PyResult<Vec<Floats<T>>> {
    let p = floats::<T>("position", position, &[None, Some(3)], "[N, 3]")?;
    let n = p.shape()[0];
    let nrm = floats::<T>(
        "normal",
        normal,
        &[Some(n), Some(3)],
        "[N, 3] (N of position)",
    )?;
    let a = floats::<T>(
        "albedo",
        albedo,
        &[Some(n), Some(3)],
        "[N, 3] (N of position)",
    )?;
    let e = floats::<T>("eye", eye, &[Some(3)], "[3]")?;
    let am = floats::<T>("ambient", ambient, &[Some(3)], "[3]")?;
    let ld = floats::<T>("light_dir", light_dir, &[None, Some(3)], "[L, 3]")?;
    let lc = floats::<T>(
        "light_color",
        light_color,
        &[Some(ld.shape()[0]), Some(3)],
        "[L, 3] (L of light_dir)",
    )?;
    let k = floats::<T>("ks", ks, &[Some(3)], "[3]")?;
    let s = floats::<T>("shininess", shininess, &[Some(1)], "[1]")?;
    let mut ins = vec![p, nrm, a, e, am, ld, lc, k, s];
    match (point_position, point_color) {
        (None, None) => {}
        (Some(pp), Some(pc)) => {
            let pp = floats::<T>("point_position", pp, &[None, Some(3)], "[P, 3]")?;
            let pc = floats::<T>(
                "point_color",
                pc,
                &[Some(pp.shape()[0]), Some(3)],
                "[P, 3] (P of point_position)",
            )?;
            ins.extend([pp, pc]);
        }
        _ => {
            return Err(PyValueError::new_err(
                "point_position and point_color: give both or neither",
            ))
        }
    }
    Ok(ins)
}

/// shade_phong(position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess, model="lambert", point_position=None, point_color=None) -> [N, 3]
/// The fused Lambert / Phong / Blinn-Phong model at fragments (positions, normals, albedo
/// [N, 3]) seen from `eye` [3], lit by an ambient colour [3], directional lights
/// (directions and colours [L, 3], L may be 0) and point lights (positions and colours
/// [P, 3], no distance fall-off); `ks` [3] and `shininess` [1] for the specular models.
#[pyfunction]
#[pyo3(signature = (position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess, model = "lambert", point_position = None, point_color = None))]
#[allow(clippy::too_many_arguments)]
fn shade_phong<'py>(
    py: Python<'py>,
    position: &Bound<'py, PyAny>,
    normal: &Bound<'py, PyAny>,
    albedo: &Bound<'py, PyAny>,
    eye: &Bound<'py, PyAny>,
    ambient: &Bound<'py, PyAny>,
    light_dir: &Bound<'py, PyAny>,
    light_color: &Bound<'py, PyAny>,
    ks: &Bound<'py, PyAny>,
    shininess: &Bound<'py, PyAny>,
    model: &str,
    point_position: Option<&Bound<'py, PyAny>>,
    point_color: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let m = reflectance(model)?;
    with_dtype!(dtype_of("position", position)?, T => {
        let ins = phong_inputs::<T>(position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess, point_position, point_color)?;
        let b = phong_build::<T>(m);
        let out = py.detach(|| forward(ins, &*b)).map_err(to_py)?;
        Ok(to_numpy(py, one(out)))
    })
}

/// shade_phong_vjp(position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess, grad_out, model="lambert", needs=None, point_position=None, point_color=None)
/// -> the gradients of the nine inputs, in order, then of point_position and point_color
/// when given (`needs`: one flag for each of these).
#[pyfunction]
#[pyo3(signature = (position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess, grad_out, model = "lambert", needs = None, point_position = None, point_color = None))]
#[allow(clippy::too_many_arguments)]
fn shade_phong_vjp<'py>(
    py: Python<'py>,
    position: &Bound<'py, PyAny>,
    normal: &Bound<'py, PyAny>,
    albedo: &Bound<'py, PyAny>,
    eye: &Bound<'py, PyAny>,
    ambient: &Bound<'py, PyAny>,
    light_dir: &Bound<'py, PyAny>,
    light_color: &Bound<'py, PyAny>,
    ks: &Bound<'py, PyAny>,
    shininess: &Bound<'py, PyAny>,
    grad_out: &Bound<'py, PyAny>,
    model: &str,
    needs: Option<Vec<bool>>,
    point_position: Option<&Bound<'py, PyAny>>,
    point_color: Option<&Bound<'py, PyAny>>,
) -> PyResult<Vec<Option<Bound<'py, PyAny>>>> {
    let m = reflectance(model)?;
    with_dtype!(dtype_of("position", position)?, T => {
        let ins = phong_inputs::<T>(position, normal, albedo, eye, ambient, light_dir, light_color, ks, shininess, point_position, point_color)?;
        let needs = needs_of(needs, ins.len(), &PHONG_INPUTS[..ins.len()].join(", "))?;
        let g = floats::<T>("grad_out", grad_out, &[None, Some(3)], "[N, 3]")?;
        let b = phong_build::<T>(m);
        let gs = py.detach(|| vjp(ins, &needs, &*b, vec![g])).map_err(to_py)?;
        Ok(grads_tuple(py, gs))
    })
}

/// perspective_look_at(eye, at, up, fov_y_deg, aspect, near, far) -> [4, 4]
/// The clip matrix P V of a camera (row-major: clip = M @ [x, y, z, 1]), as a scene's camera.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn perspective_look_at<'py>(
    py: Python<'py>,
    eye: [f64; 3],
    at: [f64; 3],
    up: [f64; 3],
    fov_y_deg: f64,
    aspect: f64,
    near: f64,
    far: f64,
) -> PyResult<Bound<'py, PyAny>> {
    let cam = render_ops::Camera::perspective_look_at(
        eye,
        at,
        up,
        fov_y_deg.to_radians(),
        aspect,
        near,
        far,
    )
    .map_err(to_py)?;
    let m = cam.view_proj();
    Ok(field(
        py,
        m.iter().flatten().copied().collect::<Vec<f64>>(),
        &[4, 4],
    ))
}

/// _time_render(clip, faces, colors, settings, repeats) -> [seconds of each call]
/// The Rust-side time of each of `repeats` calls of `render` without the binding (inputs already
/// tensors, outputs kept in Rust), for the overhead benchmark (python/bench/overhead.py).
#[pyfunction]
fn _time_render<'py>(
    py: Python<'py>,
    clip: &Bound<'py, PyAny>,
    faces: &Bound<'py, PyAny>,
    colors: &Bound<'py, PyAny>,
    settings: &Bound<'py, PyDict>,
    repeats: usize,
) -> PyResult<Vec<f64>> {
    let mut s = method_settings(settings)?;
    let f = Arc::new(read_faces(faces)?);
    let c = floats::<f32>("clip", clip, &[None, Some(4)], "[V, 4]")?;
    let col = floats::<f32>("colors", colors, &[Some(c.shape()[0]), None], "[V, C]")?;
    fit_background(&mut s, col.shape()[1])?;
    let b = render_build::<f32>(f, s);
    py.detach(|| -> Result<Vec<f64>, String> {
        (0..repeats.max(1))
            .map(|_| {
                let t0 = std::time::Instant::now();
                std::hint::black_box(forward(vec![c.clone(), col.clone()], &*b)?);
                Ok(t0.elapsed().as_secs_f64())
            })
            .collect()
    })
    .map_err(to_py)
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Fragments>()?;
    // The raster methods of the registry (`render_ops::scene::Method::ALL`), in its order.
    m.add(
        "METHODS",
        pyo3::types::PyTuple::new(m.py(), Method::ALL.map(|x| x.name()))?,
    )?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(render_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize, m)?)?;
    m.add_function(wrap_pyfunction!(rasterize_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate, m)?)?;
    m.add_function(wrap_pyfunction!(interpolate_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(blend, m)?)?;
    m.add_function(wrap_pyfunction!(blend_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(texture, m)?)?;
    m.add_function(wrap_pyfunction!(texture_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(shade_sh, m)?)?;
    m.add_function(wrap_pyfunction!(shade_sh_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(shade_phong, m)?)?;
    m.add_function(wrap_pyfunction!(shade_phong_vjp, m)?)?;
    m.add_function(wrap_pyfunction!(perspective_look_at, m)?)?;
    m.add_function(wrap_pyfunction!(_time_render, m)?)?;
    Ok(())
}
