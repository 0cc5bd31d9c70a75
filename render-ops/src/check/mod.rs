//! Gradient checking of whole pipelines: is the gradient of my loss, through my scene (or my
//! shader, or my op), right, and where is it wrong?
//!
//! - [`check_image_gradient`]: any closure that builds an image on the tape from one input
//!   tensor, checked against `f64` central differences of the loss
//!   `L = sum (image - target)^2` (the loss of `tapestry grad`). The input is split into
//!   *items*, the rows of its last axis (a vertex of `[V, 3]`, a texel of `[H, W, C]`, a light
//!   row of `[n, 3]`), so that the report can name the worst items; cosine similarity and
//!   relative L2 error are taken over every checked component.
//! - [`fd_rows`]: the central differences alone, per item with its own step, of any scalar
//!   function of the input (used for the area-integrated reference of [`scene`]).
//! - [`disagreement_map`]: per pixel, the analytic against the finite-difference contribution
//!   to the directional derivative of `L` along one random direction of the checked items, for
//!   a heat map ([`heat_png`]).
//! - [`scene`]: the scene check of `tapestry gradcheck SCENE.json --wrt ...` (vertex
//!   categories, the supersampled reference of docs/CONVENTIONS.md, per-method thresholds).
//! - [`cases`]: the rasterization and raster-method cases of the gradcheck [`Registry`]; with
//!   [`register`], every rendering case (`shade`, `texture`, `raster`, `method`).
//!
//! [`ScaleBackward`] is a deliberately wrong op (identity forward, backward scaled by a
//! factor): the checker's own test, and what `tapestry gradcheck` uses to show a failure.

pub mod cases;
pub mod scene;

use autodiff::rng::Rng;
use autodiff::suite::Registry;
use autodiff::{BackwardCtx, Op, Real, Result as AdResult, Tape, Tensor, TensorView, Var};
use ndarray::{Array2, Array3, ArrayD, IxDyn};
use rayon::prelude::*;

use crate::error::RenderError;

/// Adds every rendering case to `registry`: the shading and texture cases
/// ([`crate::shade::suite`], categories `shade` and `texture`), rasterization (`raster`) and
/// one small scene per raster method (`method`), see [`cases`].
pub fn register(registry: &mut Registry) {
    for c in crate::shade::suite::cases() {
        registry.add(c);
    }
    cases::register(registry);
}

/// Every registered case: the autodiff op cases ([`Registry::builtin`]) and the rendering
/// cases ([`register`]). `tapestry gradcheck --all` runs it; user code adds to it.
pub fn registry() -> Registry {
    let mut r = Registry::builtin();
    register(&mut r);
    r
}

/// Identity forward; the backward multiplies the output gradient by `factor`. With
/// `factor != 1` its backward is wrong on purpose: a pipeline containing it must fail a
/// gradient check (the checker's self-test).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScaleBackward {
    /// Factor applied to the gradient.
    pub factor: f64,
}

impl<T: Real> Op<T> for ScaleBackward {
    fn name(&self) -> &'static str {
        "scale_backward"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        Ok(vec![inputs[0].to_owned()])
    }
    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let f = T::from_f64c(self.factor);
        Ok(vec![
            ctx.needs_grad[0].then(|| ctx.grad_outputs[0].mapv(|g| g * f))
        ])
    }
}

/// `x` through [`ScaleBackward`] with `factor`.
pub fn scale_backward<'t, T: Real>(x: Var<'t, T>, factor: f64) -> Var<'t, T> {
    x.tape().apply(ScaleBackward { factor }, &[x])
}

/// Which items (rows of the input's last axis) a check covers.
#[derive(Clone, Debug, PartialEq)]
pub enum Items {
    /// Every item.
    All,
    /// At most this many, drawn without replacement with the check's seed (sorted).
    Random(usize),
    /// These items.
    List(Vec<usize>),
}

/// Settings of [`check_image_gradient`].
#[derive(Clone, Debug, PartialEq)]
pub struct CheckOptions {
    /// Central-difference step (input units).
    pub eps: f64,
    /// Relative tolerance per component.
    pub rtol: f64,
    /// Absolute tolerance per component, in units of `1 + max |numeric|` over the checked
    /// components (the loss scale varies with the image size).
    pub atol: f64,
    /// Which items to check.
    pub items: Items,
    /// Seed of [`Items::Random`] and of the heat map's direction.
    pub seed: u64,
}

impl Default for CheckOptions {
    fn default() -> Self {
        CheckOptions {
            eps: 1e-6,
            rtol: 1e-4,
            atol: 1e-6,
            items: Items::All,
            seed: 0,
        }
    }
}

/// One checked item.
#[derive(Clone, Debug, PartialEq)]
pub struct ItemCheck {
    /// Row index of the item (flat index over all axes but the last).
    pub item: usize,
    /// Analytic gradient of the item's components.
    pub analytic: Vec<f64>,
    /// Numeric gradient (central differences).
    pub numeric: Vec<f64>,
    /// `|analytic - numeric|` (L2 over the item's components).
    pub abs_err: f64,
    /// `abs_err / max(|numeric|, tiny)`.
    pub rel_err: f64,
    /// Every component within tolerance.
    pub passed: bool,
}

/// Result of comparing an analytic gradient with numeric ones over the checked items.
#[derive(Clone, Debug, PartialEq)]
pub struct CheckReport {
    /// The loss at the input.
    pub loss: f64,
    /// Checked items, in item order.
    pub items: Vec<ItemCheck>,
    /// Cosine similarity of the analytic and numeric gradients over every checked component
    /// (1 when both are zero, 0 when one is).
    pub cosine: f64,
    /// `|analytic - numeric| / |numeric|` over every checked component (0 when both are zero,
    /// infinite when only the numeric one is).
    pub rel_l2: f64,
    /// Largest component error.
    pub max_abs_err: f64,
    /// Tolerances used: `|a - n| <= atol_abs + rtol |n|` per component.
    pub rtol: f64,
    /// The absolute tolerance after scaling (`atol (1 + max |numeric|)`).
    pub atol_abs: f64,
    /// Every item passed.
    pub passed: bool,
}

impl CheckReport {
    /// Compares per-item gradients (`rows` item indices, `analytic` and `numeric` their
    /// components); `rtol`/`atol` as in [`CheckOptions`].
    pub fn compare(
        loss: f64,
        rows: &[usize],
        analytic: Vec<Vec<f64>>,
        numeric: Vec<Vec<f64>>,
        rtol: f64,
        atol: f64,
    ) -> CheckReport {
        let nmax = numeric.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        let atol_abs = atol * (1.0 + nmax);
        let mut max_abs_err = 0.0f64;
        let items: Vec<ItemCheck> = rows
            .iter()
            .zip(analytic.into_iter().zip(numeric))
            .map(|(&item, (a, n))| {
                let mut passed = true;
                let mut e2 = 0.0;
                let mut n2 = 0.0;
                for (x, y) in a.iter().zip(&n) {
                    let d = (x - y).abs();
                    // NaN never passes.
                    passed &= d <= atol_abs + rtol * y.abs();
                    max_abs_err = max_abs_err.max(if d.is_nan() { f64::INFINITY } else { d });
                    e2 += d * d;
                    n2 += y * y;
                }
                let abs_err = if e2.is_nan() {
                    f64::INFINITY
                } else {
                    e2.sqrt()
                };
                ItemCheck {
                    item,
                    rel_err: abs_err / n2.sqrt().max(1e-300),
                    abs_err,
                    analytic: a,
                    numeric: n,
                    passed,
                }
            })
            .collect();
        let (cosine, rel_l2) = cosine_rel_l2(
            items.iter().flat_map(|i| i.analytic.iter().copied()),
            items.iter().flat_map(|i| i.numeric.iter().copied()),
        );
        CheckReport {
            loss,
            passed: items.iter().all(|i| i.passed),
            items,
            cosine,
            rel_l2,
            max_abs_err,
            rtol,
            atol_abs,
        }
    }

    /// The `n` items with the largest absolute error, largest first.
    pub fn worst(&self, n: usize) -> Vec<&ItemCheck> {
        let mut v: Vec<&ItemCheck> = self.items.iter().collect();
        v.sort_by(|a, b| b.abs_err.total_cmp(&a.abs_err).then(a.item.cmp(&b.item)));
        v.truncate(n);
        v
    }
}

/// Cosine similarity and relative L2 error `|a - b| / |b|` of two vectors (`b` the
/// reference). Cosine 1 when both are zero, 0 when one is; relative error 0 when both are zero,
/// infinite when only `b` is.
pub fn cosine_rel_l2(
    a: impl IntoIterator<Item = f64>,
    b: impl IntoIterator<Item = f64>,
) -> (f64, f64) {
    let (mut ab, mut aa, mut bb, mut dd) = (0.0, 0.0, 0.0, 0.0);
    for (x, y) in a.into_iter().zip(b) {
        ab += x * y;
        aa += x * x;
        bb += y * y;
        dd += (x - y) * (x - y);
    }
    let cos = match (aa > 0.0, bb > 0.0) {
        (true, true) => ab / (aa.sqrt() * bb.sqrt()),
        (false, false) => 1.0,
        _ => 0.0,
    };
    let rel = if bb > 0.0 {
        dd.sqrt() / bb.sqrt()
    } else if dd > 0.0 {
        f64::INFINITY
    } else {
        0.0
    };
    (cos, rel)
}

/// The number of items (rows of the last axis) of a tensor and their length.
pub fn item_layout(shape: &[usize]) -> (usize, usize) {
    let k = shape.last().copied().unwrap_or(1).max(1);
    let n: usize = shape.iter().product();
    (n / k, k)
}

/// The rows `items` selects among `n` (sorted, in range).
pub fn select_items(items: &Items, n: usize, seed: u64) -> Result<Vec<usize>, RenderError> {
    match items {
        Items::All => Ok((0..n).collect()),
        Items::Random(m) => {
            let mut rng = Rng::new(seed);
            let mut all: Vec<usize> = (0..n).collect();
            let m = (*m).min(n);
            // Partial Fisher-Yates: the first m slots.
            for i in 0..m {
                let j = i + rng.below(n - i);
                all.swap(i, j);
            }
            let mut out = all[..m].to_vec();
            out.sort_unstable();
            Ok(out)
        }
        Items::List(v) => {
            if let Some(&bad) = v.iter().find(|&&i| i >= n) {
                return Err(RenderError::Unsupported(format!(
                    "gradient check: item {bad} out of range (the input has {n} items)"
                )));
            }
            let mut out = v.clone();
            out.sort_unstable();
            out.dedup();
            Ok(out)
        }
    }
}

/// Gives a closure the higher-ranked signature of a pipeline (`for<'t> Fn(&'t Tape<f64>,
/// Var<'t, f64>) -> Result<Var<'t, f64>, _>`), which Rust does not infer for closures on its
/// own: `pipeline(|t, x| Ok(x.sin()))`.
pub fn pipeline<F>(f: F) -> F
where
    F: for<'t> Fn(&'t Tape<f64>, Var<'t, f64>) -> Result<Var<'t, f64>, RenderError>,
{
    f
}

/// `sum (image - target)^2` on the tape, after checking the shapes.
fn loss_var<'t>(image: Var<'t, f64>, target: &Tensor<f64>) -> Result<Var<'t, f64>, RenderError> {
    let s = image.shape();
    if s != target.shape() {
        return Err(RenderError::Unsupported(format!(
            "gradient check: the image has shape {s:?} but the target {:?}",
            target.shape()
        )));
    }
    Ok(image.sum_squared_diff(image.tape().constant(target.clone())))
}

/// The image that `build` makes from `x` (the input requires a gradient, so that pipelines
/// that build differently with and without one, e.g. a camera on the tape, take the same path;
/// no backward is run).
pub fn eval_image<F>(build: &F, x: &Tensor<f64>) -> Result<Tensor<f64>, RenderError>
where
    F: for<'t> Fn(&'t Tape<f64>, Var<'t, f64>) -> Result<Var<'t, f64>, RenderError>,
{
    let tape = Tape::new();
    let img = build(&tape, tape.var(x.clone(), true))?;
    let v = img.value()?;
    Ok((*v).clone())
}

/// `sum (a - b)^2`.
pub fn sq_loss(a: &Tensor<f64>, b: &Tensor<f64>) -> f64 {
    a.iter().zip(b.iter()).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// Central differences `(f(x + h_i e) - f(x - h_i e)) / 2 h_i` of `f` for every component of
/// the items `rows` (rows of the last axis of `x`), item `rows[i]` with step `steps[i]`.
/// Evaluations run in parallel; the result does not depend on the thread count.
pub fn fd_rows<F>(
    f: F,
    x: &Tensor<f64>,
    rows: &[usize],
    steps: &[f64],
) -> Result<Vec<Vec<f64>>, RenderError>
where
    F: Fn(&Tensor<f64>) -> Result<f64, RenderError> + Sync,
{
    let (_, k) = item_layout(x.shape());
    if steps.len() != rows.len() || steps.iter().any(|h| !(h.is_finite() && *h > 0.0)) {
        return Err(RenderError::Unsupported(
            "gradient check: one finite step > 0 per item".into(),
        ));
    }
    let x = x.as_standard_layout().into_owned();
    let jobs: Vec<(usize, usize)> = (0..rows.len())
        .flat_map(|i| (0..k).map(move |j| (i, j)))
        .collect();
    let vals: Vec<f64> = jobs
        .par_iter()
        .map(|&(i, j)| {
            let at = rows[i] * k + j;
            let h = steps[i];
            let mut xp = x.clone();
            let x0 = xp.as_slice().expect("standard")[at];
            xp.as_slice_mut().expect("standard")[at] = x0 + h;
            let lp = f(&xp)?;
            xp.as_slice_mut().expect("standard")[at] = x0 - h;
            let lm = f(&xp)?;
            Ok((lp - lm) / (2.0 * h))
        })
        .collect::<Result<_, RenderError>>()?;
    Ok(vals.chunks(k).map(<[f64]>::to_vec).collect())
}

/// The analytic gradient of `sum (build(x) - target)^2` with respect to `x`, and the loss.
pub fn analytic_gradient<F>(
    build: &F,
    x: &Tensor<f64>,
    target: &Tensor<f64>,
) -> Result<(f64, Tensor<f64>), RenderError>
where
    F: for<'t> Fn(&'t Tape<f64>, Var<'t, f64>) -> Result<Var<'t, f64>, RenderError>,
{
    let tape = Tape::new();
    let leaf = tape.var(x.clone(), true);
    let loss = loss_var(build(&tape, leaf)?, target)?;
    let g = tape.backward(loss)?.wrt(leaf);
    Ok((loss.item()?, g))
}

/// Checks the gradient of `L = sum (build(x) - target)^2` with respect to `input` against
/// `f64` central differences (step `opts.eps`) over the items `opts.items`: per component
/// `|analytic - numeric| <= atol (1 + max |numeric|) + rtol |numeric|`, plus the cosine and
/// relative L2 error over all checked components. `build` is any pipeline that makes an image
/// (any shape equal to the target's) on the tape from the input: a scene render, a custom
/// shader, an op under test.
///
/// ```
/// use autodiff::Tensor;
/// use render_ops::check::{check_image_gradient, pipeline, scale_backward, CheckOptions};
/// use render_ops::error::RenderError;
/// let x = Tensor::from_shape_vec(ndarray::IxDyn(&[4, 3]), (0..12).map(|i| i as f64 / 12.0).collect()).unwrap();
/// let target = Tensor::zeros(ndarray::IxDyn(&[4, 3]));
/// let good = pipeline(|_, v| Ok(v.sin()));
/// assert!(check_image_gradient(good, &x, &target, &CheckOptions::default())?.passed);
/// let bad = pipeline(|_, v| Ok(scale_backward(v.sin(), 1.5)));
/// let rep = check_image_gradient(bad, &x, &target, &CheckOptions::default())?;
/// assert!(!rep.passed && (rep.items[3].analytic[0] / rep.items[3].numeric[0] - 1.5).abs() < 1e-6);
/// # Ok::<(), RenderError>(())
/// ```
pub fn check_image_gradient<F>(
    build: F,
    input: &Tensor<f64>,
    target: &Tensor<f64>,
    opts: &CheckOptions,
) -> Result<CheckReport, RenderError>
where
    F: for<'t> Fn(&'t Tape<f64>, Var<'t, f64>) -> Result<Var<'t, f64>, RenderError> + Sync,
{
    if !(opts.eps.is_finite() && opts.eps > 0.0) {
        return Err(RenderError::Unsupported(format!(
            "gradient check: eps = {} must be finite and > 0",
            opts.eps
        )));
    }
    let (n, _) = item_layout(input.shape());
    let rows = select_items(&opts.items, n, opts.seed)?;
    let (loss, g) = analytic_gradient(&build, input, target)?;
    let analytic = item_values(&g, &rows);
    let numeric = fd_rows(
        |x| Ok(sq_loss(&eval_image(&build, x)?, target)),
        input,
        &rows,
        &vec![opts.eps; rows.len()],
    )?;
    Ok(CheckReport::compare(
        loss, &rows, analytic, numeric, opts.rtol, opts.atol,
    ))
}

/// The components of the items `rows` of `g` (rows of its last axis).
pub fn item_values(g: &Tensor<f64>, rows: &[usize]) -> Vec<Vec<f64>> {
    let (_, k) = item_layout(g.shape());
    let g = g.as_standard_layout();
    let s = g.as_slice().expect("standard");
    rows.iter()
        .map(|&r| s[r * k..(r + 1) * k].to_vec())
        .collect()
}

/// Per-pixel disagreement `[H, W]` of the analytic and numeric directional derivatives of
/// `L = sum (image - target)^2` along `d` (a random normal direction over the items `rows`,
/// item `rows[i]` scaled by `steps[i]`, from `seed`):
/// - analytic contribution of pixel `p`: `g_p . d` with `g_p` the gradient of pixel `p`'s
///   loss terms (one vector-Jacobian product per pixel, on one tape of `build`);
/// - numeric: `((I+ - T)^2 - (I- - T)^2) / 2` summed over the pixel's channels, `I+-` the
///   image of `reference` at `x +- d` (the pipeline itself for smooth inputs, the
///   supersampled reference for positions and camera).
///
/// Both sum over the pixels to the directional derivative (analytic) and its central
/// difference (numeric). Returns `|analytic - numeric|` per pixel and the numeric
/// contributions (for scaling). The image must be `[H, W, C]`.
pub fn disagreement_map<F, G>(
    build: &F,
    reference: &G,
    x: &Tensor<f64>,
    target: &Tensor<f64>,
    rows: &[usize],
    steps: &[f64],
    seed: u64,
) -> Result<(Array2<f64>, Array2<f64>), RenderError>
where
    F: for<'t> Fn(&'t Tape<f64>, Var<'t, f64>) -> Result<Var<'t, f64>, RenderError>,
    G: Fn(&Tensor<f64>) -> Result<Tensor<f64>, RenderError>,
{
    let (_, k) = item_layout(x.shape());
    let mut rng = Rng::new(seed ^ 0x9e37_79b9_7f4a_7c15);
    let mut d = ArrayD::<f64>::zeros(IxDyn(x.shape()));
    {
        let ds = d.as_slice_mut().expect("fresh");
        for (&r, &h) in rows.iter().zip(steps) {
            for j in 0..k {
                ds[r * k + j] = rng.normal() * h;
            }
        }
    }
    let tape = Tape::new();
    let leaf = tape.var(x.clone(), true);
    let img = build(&tape, leaf)?;
    let iv = img.value()?;
    let s = iv.shape().to_vec();
    if s.len() != 3 || s != target.shape() {
        return Err(RenderError::Unsupported(format!(
            "gradient heat map: needs an image [H, W, C] of the target's shape {:?}, got {s:?}",
            target.shape()
        )));
    }
    let (h, w, c) = (s[0], s[1], s[2]);
    let resid: Vec<f64> = iv
        .iter()
        .zip(target.iter())
        .map(|(a, b)| 2.0 * (a - b))
        .collect();
    let mut analytic = Array2::<f64>::zeros((h, w));
    let mut v = ArrayD::<f64>::zeros(IxDyn(&s));
    for p in 0..h * w {
        let range = p * c..(p + 1) * c;
        if resid[range.clone()].iter().all(|&r| r == 0.0) {
            continue;
        }
        v.as_slice_mut().expect("fresh")[range.clone()].copy_from_slice(&resid[range.clone()]);
        let g = tape.vjp(img, v.clone())?.wrt(leaf);
        analytic[[p / w, p % w]] = g.iter().zip(d.iter()).map(|(a, b)| a * b).sum();
        v.as_slice_mut().expect("fresh")[range].fill(0.0);
    }
    let ip = reference(&(x + &d))?;
    let im = reference(&(x - &d))?;
    if ip.shape() != s.as_slice() || im.shape() != s.as_slice() {
        return Err(RenderError::Unsupported(format!(
            "gradient heat map: the reference image has shape {:?}, the pipeline's {s:?}",
            ip.shape()
        )));
    }
    let (ip, im) = (ip.as_standard_layout(), im.as_standard_layout());
    let (ps, ms) = (ip.as_slice().expect("std"), im.as_slice().expect("std"));
    let t = target.as_standard_layout();
    let ts = t.as_slice().expect("std");
    let numeric: Array2<f64> = Array2::from_shape_fn((h, w), |(r, col)| {
        let p = r * w + col;
        (p * c..(p + 1) * c)
            .map(|i| 0.5 * ((ps[i] - ts[i]).powi(2) - (ms[i] - ts[i]).powi(2)))
            .sum()
    });
    let diff: Array2<f64> = &analytic - &numeric;
    let diff = diff.mapv(f64::abs);
    Ok((diff, numeric))
}

/// A heat map image `[H, W, 3]` of `diff` scaled by the largest `|scale|` (black, red, yellow,
/// white as the disagreement grows to the largest numeric contribution and beyond).
pub fn heat_png(diff: &Array2<f64>, scale: &Array2<f64>) -> Array3<f64> {
    let m = scale.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let m = if m > 0.0 {
        m
    } else {
        diff.iter().fold(0.0f64, |m, x| m.max(*x)).max(1e-300)
    };
    let (h, w) = diff.dim();
    Array3::from_shape_fn((h, w, 3), |(r, c, k)| {
        let t = (diff[[r, c]] / m).clamp(0.0, 1.0) * 3.0;
        (t - k as f64).clamp(0.0, 1.0)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize) -> Tensor<f64> {
        ArrayD::from_shape_fn(IxDyn(&[n, 3]), |i| 0.1 + 0.05 * (i[0] * 3 + i[1]) as f64)
    }

    #[test]
    fn exact_pipeline_passes_and_wrong_backward_fails_at_the_scaled_items() {
        let x = grid(6);
        let target = ArrayD::from_elem(IxDyn(&[6, 3]), 0.3);
        let good = pipeline(|_, v| Ok(v.exp()));
        let r = check_image_gradient(good, &x, &target, &CheckOptions::default()).unwrap();
        assert!(
            r.passed && (r.cosine - 1.0).abs() < 1e-9 && r.rel_l2 < 1e-6,
            "{r:?}"
        );
        assert_eq!(r.items.len(), 6);
        // Backward off by 1.5 on rows 2..4 only: those items fail, they are the worst.
        let bad = pipeline(|t, v| {
            let a = v.slice(0, 0, 2);
            let b = scale_backward(v.slice(0, 2, 4), 1.5);
            let c = v.slice(0, 4, 6);
            Ok(t.concat(&[a, b, c], 0).exp())
        });
        let r = check_image_gradient(bad, &x, &target, &CheckOptions::default()).unwrap();
        assert!(!r.passed);
        let failed: Vec<usize> = r
            .items
            .iter()
            .filter(|i| !i.passed)
            .map(|i| i.item)
            .collect();
        assert_eq!(failed, vec![2, 3]);
        let mut worst: Vec<usize> = r.worst(2).iter().map(|i| i.item).collect();
        worst.sort_unstable();
        assert_eq!(worst, vec![2, 3]);
        for i in r.items.iter().filter(|i| !i.passed) {
            for (a, n) in i.analytic.iter().zip(&i.numeric) {
                assert!((a / n - 1.5).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn random_items_are_a_seeded_sorted_subset() {
        let a = select_items(&Items::Random(5), 40, 7).unwrap();
        assert_eq!(a, select_items(&Items::Random(5), 40, 7).unwrap());
        assert_eq!(a.len(), 5);
        assert!(a.windows(2).all(|w| w[0] < w[1]) && a[4] < 40);
        assert_eq!(
            select_items(&Items::Random(50), 4, 1).unwrap(),
            vec![0, 1, 2, 3]
        );
        assert!(select_items(&Items::List(vec![4]), 4, 0).is_err());
    }

    #[test]
    fn cosine_and_rel_l2_edge_cases() {
        assert_eq!(cosine_rel_l2([0.0, 0.0], [0.0, 0.0]), (1.0, 0.0));
        let (c, r) = cosine_rel_l2([1.0, 0.0], [0.0, 0.0]);
        assert_eq!((c, r), (0.0, f64::INFINITY));
        let (c, r) = cosine_rel_l2([2.0, 0.0], [1.0, 0.0]);
        assert!((c - 1.0).abs() < 1e-15 && (r - 1.0).abs() < 1e-15);
    }

    #[test]
    fn heat_map_sums_to_the_directional_derivative_and_finds_the_bad_pixels() {
        // A 2 x 3 "image" with one channel: pixel (1, 2)'s backward is scaled.
        let x = ArrayD::from_shape_fn(IxDyn(&[2, 3, 1]), |i| 0.2 + 0.1 * (i[0] * 3 + i[1]) as f64);
        let target = ArrayD::zeros(IxDyn(&[2, 3, 1]));
        let build = pipeline(|t, v| {
            let flat = v.reshape(&[6]);
            let a = flat.slice(0, 0, 5);
            let b = scale_backward(flat.slice(0, 5, 6), 2.0);
            Ok(t.concat(&[a, b], 0).sin().reshape(&[2, 3, 1]))
        });
        let reference = |x: &Tensor<f64>| eval_image(&build, x);
        let rows: Vec<usize> = (0..6).collect();
        let (diff, numeric) =
            disagreement_map(&build, &reference, &x, &target, &rows, &[1e-5; 6], 3).unwrap();
        for r in 0..2 {
            for c in 0..3 {
                let bad = (r, c) == (1, 2);
                assert_eq!(diff[[r, c]] > 1e-3 * numeric[[r, c]].abs(), bad, "{diff:?}");
            }
        }
        let png = heat_png(&diff, &numeric);
        assert_eq!(png.dim(), (2, 3, 3));
        assert!(png[[1, 2, 0]] > 0.0 && png[[0, 0, 0]] < 1e-3);
    }
}
