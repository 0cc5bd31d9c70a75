//! Face fitting by analysis-by-synthesis: a [`Morphable`] face is posed, shaded and rendered
//! on the tape, compared with a target image and 2D landmarks, and its parameters are
//! optimised with Adam.
//!
//! Parameters ([`FaceParams`]): rotation (axis-angle), translation (mm), focal length
//! (optional), standardised identity, expression and albedo coefficients (`alpha = sigma_id
//! z_id` etc.: the priors are then `sum z^2`, and one Adam step size suits every component) and
//! the 27 SH lighting coefficients (`[9, 3]`, CONVENTIONS).
//!
//! Loss (see [`LossWeights`]):
//!
//! ```text
//! E = w_photo  sum_p m_p rho(I_p - T_p) / (3 sum_p m_p)        rho(r) = sqrt(r^2 + eps^2) - eps
//!   + w_lmk    mean_l |x_l - y_l|^2 / s^2                      s = max(W, H) / 2 pixels
//!   + w_id sum z_id^2 + w_exp sum z_exp^2 + w_alb sum z_alb^2 + w_sh sum_{k>0} |sh_k|^2
//! ```
//!
//! with `m` the rendered face region (the render's alpha times the photometric weight, 1 on the
//! regions that are photometric and 0 on the others, such as ICT's eyes and the face area
//! outside its narrow face: [`FaceRenderer::photo_image`]; held constant in each step), `rho`
//! the Charbonnier penalty, `x_l` the projected landmark points and `y_l` the target
//! landmarks in pixels.
//!
//! Schedule ([`fit`]): the pose is initialised in closed form from the landmarks' centroid
//! and spread; stage 1 fits the pose from the landmarks alone (the first
//! [`FitOptions::pose_only_fraction`] of its iterations), then pose, identity and expression;
//! stage 2 fits every parameter with the photometric term added, after scaling the SH
//! coefficients so that the mean rendered colour matches the target's. Exact landmarks (a
//! synthetic target's) call for weaker shape priors and a converged stage 1
//! ([`FitOptions::with_exact_landmarks`]). Each stage uses fresh
//! Adam optimisers (one per parameter group, each with its own step size) with a cosine step
//! decay to 10 %. Parameters live outside the tape; every step builds a fresh tape.
//!
//! Every kernel involved reduces in a fixed order, so a fit gives bit-identical results for
//! any number of rayon threads. The fitting loop holds an [`autodiff::ActiveWait`]: the
//! current pool's other workers poll for work between the many short parallel regions of a
//! step instead of being parked and woken for each (call [`fit`] from inside the pool, as
//! `tapestry fit-face` does, so that the calling thread is a worker too).

mod align;
mod export;
mod landmarks;
mod render;
mod synth;
mod texture;

use std::time::Instant;

use autodiff::optim::Adam;
use autodiff::{AutodiffError, Tape, Tensor, TensorView};
use ndarray::{Array2, Array3, ArrayD, IxDyn};
use serde::{Deserialize, Serialize};
use thiserror::Error;

pub use align::{umeyama, Similarity};
pub use export::{face_obj, FaceObj};
pub use landmarks::{
    correspondence, read_landmarks, Correspondence, LandmarkFileError, MEDIAPIPE_TO_IBUG68,
};
pub use render::{
    Active, FaceRenderer, ParamVars, RenderOptions, SurfaceSamples, FAR_MM, NEAR_MM,
    TEXTURE_SAMPLER,
};
pub use synth::{euler_to_axis_angle, random_texture, synthesize, SynthOptions, Synthetic};
pub use texture::{
    bake_albedo, bake_textured, fit_texture, render_textured, texture_prior, textured_faces,
    BakedTexture, TextureFit, TextureOptions, UNTEXTURED_REGIONS,
};

use crate::morphable::{LandmarkPoint, Morphable, PointShape};

/// `Y_00` of the SH basis (CONVENTIONS).
pub const SH_Y00: f64 = 0.282095;

/// Errors of fitting.
#[derive(Debug, Error)]
pub enum FitError {
    /// A landmark file that cannot be used.
    #[error(transparent)]
    Landmarks(#[from] LandmarkFileError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] render_ops::error::RenderError),
    /// A tape error.
    #[error(transparent)]
    Autodiff(#[from] AutodiffError),
    /// A model error.
    #[error(transparent)]
    Model(#[from] crate::error::ModelError),
    /// Inconsistent inputs (image size, landmark count, ...).
    #[error("{0}")]
    Invalid(String),
}

/// Parameters of a posed, lit face (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FaceParams {
    /// Axis-angle rotation (radians) of the model about its origin.
    pub rotation: [f64; 3],
    /// Translation in millimetres (view space; `z < 0` is in front of the camera).
    pub translation: [f64; 3],
    /// Focal length `cot(fov_y / 2)`.
    pub focal: f64,
    /// Identity coefficients in standard deviations (`alpha = sigma_id * z_id`).
    pub z_id: Vec<f64>,
    /// Expression coefficients in standard deviations.
    pub z_exp: Vec<f64>,
    /// Albedo coefficients in standard deviations.
    pub z_albedo: Vec<f64>,
    /// SH coefficients, 9 rows of RGB (CONVENTIONS order).
    pub sh: [[f64; 3]; 9],
}

/// Default vertical field of view of the fitting camera, degrees.
pub const DEFAULT_FOV_Y_DEG: f64 = 26.0;
/// Default distance of the face from the camera, millimetres.
pub const DEFAULT_DISTANCE_MM: f64 = 600.0;

impl FaceParams {
    /// The mean face, unrotated, `DEFAULT_DISTANCE_MM` in front of the camera, lit by a white
    /// ambient light of irradiance 1, with the default field of view.
    pub fn neutral(model: &Morphable<f64>) -> Self {
        let mut sh = [[0.0; 3]; 9];
        sh[0] = [1.0 / SH_Y00; 3];
        FaceParams {
            rotation: [0.0; 3],
            translation: [0.0, 0.0, -DEFAULT_DISTANCE_MM],
            focal: focal_from_fov_deg(DEFAULT_FOV_Y_DEG),
            z_id: vec![0.0; model.n_id()],
            z_exp: vec![0.0; model.n_exp()],
            z_albedo: vec![0.0; model.n_albedo()],
            sh,
        }
    }

    /// The parameters as tensors, in the order rotation, translation, focal, z_id, z_exp,
    /// z_albedo, sh.
    pub fn tensors(&self) -> [Tensor<f64>; 7] {
        let v = |s: &[usize], d: Vec<f64>| ArrayD::from_shape_vec(IxDyn(s), d).expect("shape");
        [
            v(&[3], self.rotation.to_vec()),
            v(&[3], self.translation.to_vec()),
            v(&[1], vec![self.focal]),
            v(&[self.z_id.len()], self.z_id.clone()),
            v(&[self.z_exp.len()], self.z_exp.clone()),
            v(&[self.z_albedo.len()], self.z_albedo.clone()),
            v(&[9, 3], self.sh.iter().flatten().copied().collect()),
        ]
    }

    /// The inverse of [`FaceParams::tensors`].
    pub fn from_tensors(t: &[Tensor<f64>; 7]) -> Self {
        let flat = |x: &Tensor<f64>| x.iter().copied().collect::<Vec<f64>>();
        let a3 = |x: &Tensor<f64>| {
            let f = flat(x);
            [f[0], f[1], f[2]]
        };
        let s = flat(&t[6]);
        let mut sh = [[0.0; 3]; 9];
        for (k, row) in sh.iter_mut().enumerate() {
            row.copy_from_slice(&s[3 * k..3 * k + 3]);
        }
        FaceParams {
            rotation: a3(&t[0]),
            translation: a3(&t[1]),
            focal: flat(&t[2])[0],
            z_id: flat(&t[3]),
            z_exp: flat(&t[4]),
            z_albedo: flat(&t[5]),
            sh,
        }
    }

    /// Vertical field of view in degrees.
    pub fn fov_y_deg(&self) -> f64 {
        2.0 * (1.0 / self.focal).atan().to_degrees()
    }

    /// Model-space shape `[V, 3]` in millimetres.
    pub fn shape(&self, model: &Morphable<f64>) -> Result<Array2<f64>, FitError> {
        Ok(model.eval_shape_standardized(&self.z_id, &self.z_exp)?)
    }

    /// Per-vertex albedo `[V, 3]` of the fitted appearance.
    pub fn albedo(&self, model: &Morphable<f64>) -> Result<Array2<f64>, FitError> {
        let gamma: Vec<f64> = self
            .z_albedo
            .iter()
            .zip(model.sigma_albedo())
            .map(|(z, s)| z * s)
            .collect();
        Ok(model.eval_albedo(&gamma)?)
    }

    /// Checks the coefficient counts against `model` and that every value is finite.
    pub fn check(&self, model: &Morphable<f64>) -> Result<(), FitError> {
        for (what, n, want) in [
            ("z_id", self.z_id.len(), model.n_id()),
            ("z_exp", self.z_exp.len(), model.n_exp()),
            ("z_albedo", self.z_albedo.len(), model.n_albedo()),
        ] {
            if n != want {
                return Err(FitError::Invalid(format!(
                    "parameters: {what} has {n} coefficients, the model has {want}"
                )));
            }
        }
        let finite = self
            .tensors()
            .iter()
            .all(|t| t.iter().all(|v| v.is_finite()));
        if !finite || self.focal <= 0.0 {
            return Err(FitError::Invalid(
                "parameters: non-finite value or focal length <= 0".into(),
            ));
        }
        Ok(())
    }
}

/// `cot(fov_y / 2)` of a field of view in degrees.
pub fn focal_from_fov_deg(fov_y_deg: f64) -> f64 {
    1.0 / (0.5 * fov_y_deg.to_radians()).tan()
}

/// A fitting target: an RGB image and 2D landmarks on it.
#[derive(Clone, Debug)]
pub struct FitTarget {
    /// Linear RGB image `[H, W, 3]`.
    pub image: Array3<f64>,
    /// Landmark positions `[L, 2]` in pixels (x right, y down, pixel centres at +0.5).
    pub landmarks: Array2<f64>,
    /// The model point of each landmark (`L` entries): a vertex or a weighted sum of up to
    /// three vertices (a point on a triangle), interpolated on the tape.
    pub points: Vec<LandmarkPoint>,
}

/// Weights of the loss terms (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LossWeights {
    /// Photometric term (stage 2).
    pub photo: f64,
    /// Landmark term.
    pub landmarks: f64,
    /// Identity prior.
    pub id: f64,
    /// Expression prior.
    pub exp: f64,
    /// Albedo prior.
    pub albedo: f64,
    /// Penalty on the non-constant SH coefficients.
    pub sh: f64,
    /// Charbonnier `eps` of the photometric term (colour units).
    pub charbonnier_eps: f64,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            photo: 1.0,
            landmarks: 100.0,
            id: 1e-4,
            exp: 1e-4,
            albedo: 1e-5,
            sh: 1e-6,
            charbonnier_eps: 0.02,
        }
    }
}

/// Adam step sizes per parameter group (the step of each element is about this size).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StepSizes {
    /// Rotation, radians.
    pub rotation: f64,
    /// Translation, millimetres.
    pub translation: f64,
    /// Focal length.
    pub focal: f64,
    /// Identity and expression, standard deviations.
    pub shape: f64,
    /// Albedo, standard deviations.
    pub albedo: f64,
    /// SH coefficients.
    pub sh: f64,
}

impl Default for StepSizes {
    fn default() -> Self {
        StepSizes {
            rotation: 0.02,
            translation: 3.0,
            focal: 0.02,
            shape: 0.05,
            albedo: 0.05,
            sh: 0.05,
        }
    }
}

/// Settings of [`fit`].
#[derive(Clone, Debug, PartialEq)]
pub struct FitOptions {
    /// Renderer settings (image size, raster method, SoftRas parameters).
    pub render: RenderOptions,
    /// Stage 1 (landmarks only) iterations.
    pub landmark_iters: usize,
    /// Stage 2 (all terms) iterations.
    pub full_iters: usize,
    /// Fraction of stage 1 during which only the pose moves.
    pub pose_only_fraction: f64,
    /// Optimise the focal length too (stage 2 and the shape part of stage 1).
    pub fit_focal: bool,
    /// Loss weights.
    pub weights: LossWeights,
    /// Adam step sizes.
    pub steps: StepSizes,
    /// Final step size as a fraction of the initial one (cosine decay within each stage).
    pub final_step_fraction: f64,
}

impl FitOptions {
    /// Defaults for a `width x height` image: `iters` iterations in all, half of them per
    /// stage, `hard` rasterization.
    pub fn new(width: usize, height: usize, iters: usize) -> Self {
        let landmark_iters = iters.div_ceil(2);
        FitOptions {
            render: RenderOptions::new(width, height),
            landmark_iters,
            full_iters: iters - landmark_iters,
            pose_only_fraction: 0.3,
            fit_focal: false,
            weights: LossWeights::default(),
            steps: StepSizes::default(),
            final_step_fraction: 0.1,
        }
    }

    /// Settings for landmarks known exactly (a synthetic target's, [`synthesize`]): shape
    /// priors of [`EXACT_LANDMARK_PRIOR`] instead of the defaults, which suit detected landmarks
    /// (about 1-2 px of noise at 256 px), and stage 1 run to convergence
    /// ([`EXACT_LANDMARK_ITERS`] steps). The landmark fit of a 150-mode model is
    /// ill-conditioned: Adam needs thousands of steps to settle, each of which evaluates only
    /// the landmark points (ICT: 468 points, about 2 ms a step in the dev profile).
    pub fn with_exact_landmarks(mut self) -> Self {
        self.weights.id = EXACT_LANDMARK_PRIOR;
        self.weights.exp = EXACT_LANDMARK_PRIOR;
        self.landmark_iters = self.landmark_iters.max(EXACT_LANDMARK_ITERS);
        self
    }
}

/// Identity and expression prior weight for exact landmarks ([`FitOptions::with_exact_landmarks`]).
/// Measured on synthetic ICT targets at 64 px (seed 3, stage 1 run to convergence): the
/// default 1e-4 leaves 2.4 mm of vertex error over the face area, 1e-5 1.6 mm, 1e-6 1.0 mm.
pub const EXACT_LANDMARK_PRIOR: f64 = 1e-6;

/// Stage 1 steps for exact landmarks ([`FitOptions::with_exact_landmarks`]). Measured on
/// synthetic ICT targets at 64 px (seed 3, prior 1e-6, landmark stage alone): 1000 steps leave
/// 2.1 mm of vertex error over the face area, 3000 steps 1.0 mm.
pub const EXACT_LANDMARK_ITERS: usize = 3000;

/// One optimisation step's record.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StepRecord {
    /// Stage (1: landmarks, 2: all terms).
    pub stage: u8,
    /// Iteration counted over both stages.
    pub iter: usize,
    /// Total loss.
    pub loss: f64,
    /// Landmark term (unweighted: mean squared distance / s^2).
    pub landmark_term: f64,
    /// Photometric term (unweighted; 0 in stage 1).
    pub photo_term: f64,
    /// Mean landmark distance in pixels.
    pub landmark_error_px: f64,
}

/// The result of [`fit`].
#[derive(Clone, Debug)]
pub struct FitResult {
    /// The fitted parameters.
    pub params: FaceParams,
    /// The pose initialisation (closed form, before stage 1).
    pub initial: FaceParams,
    /// One record per step.
    pub history: Vec<StepRecord>,
    /// Seconds spent in the pose initialisation.
    pub init_seconds: f64,
    /// Seconds spent in stage 1 and stage 2.
    pub stage_seconds: [f64; 2],
}

/// Mean distance in pixels between two `[L, 2]` point sets.
pub fn landmark_error_px(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let n = a.nrows().max(1);
    a.outer_iter()
        .zip(b.outer_iter())
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt())
        .sum::<f64>()
        / n as f64
}

/// RMSE over the channels of the pixels that a render `[H, W, 4]` covers (alpha > 0.5)
/// against a target `[H, W, 3]`; `NaN` when nothing is covered.
pub fn photometric_rmse(render: &Array3<f64>, target: &Array3<f64>) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    let (h, w) = (render.shape()[0], render.shape()[1]);
    for r in 0..h {
        for c in 0..w {
            if render[[r, c, 3]] > 0.5 {
                for k in 0..3 {
                    s += (render[[r, c, k]] - target[[r, c, k]]).powi(2);
                }
                n += 3;
            }
        }
    }
    if n == 0 {
        f64::NAN
    } else {
        (s / n as f64).sqrt()
    }
}

/// Mean per-vertex distance (mm) between two shapes `[V, 3]`.
pub fn shape_error_mm(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let n = a.nrows().max(1);
    a.outer_iter()
        .zip(b.outer_iter())
        .map(|(p, q)| {
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .sum::<f64>()
        / n as f64
}

/// [`shape_error_mm`] after scaling `a` about the origin by the least-squares factor that best
/// matches `b`: the part of the error that the depth / size ambiguity of a single view does not
/// explain (see the fitting tests).
pub fn shape_error_scale_aligned_mm(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let ab: f64 = a.iter().zip(b.iter()).map(|(x, y)| x * y).sum();
    let aa: f64 = a.iter().map(|x| x * x).sum();
    let s = if aa > 0.0 { ab / aa } else { 1.0 };
    shape_error_mm(&(a * s), b)
}

/// [`shape_error_mm`] after the rigid transform that best aligns `a` with `b` ([`umeyama`]
/// without scale): the shape error that no head pose explains (the issue's "mean vertex error
/// after rigid alignment").
pub fn shape_error_rigid_aligned_mm(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let pts =
        |m: &Array2<f64>| -> Vec<[f64; 3]> { m.outer_iter().map(|r| [r[0], r[1], r[2]]).collect() };
    let (pa, pb) = (pts(a), pts(b));
    let t = umeyama(&pa, &pb, false);
    let moved = Array2::from_shape_fn(a.raw_dim(), |(i, c)| t.apply(pa[i])[c]);
    shape_error_mm(&moved, b)
}

/// Closed-form pose initialisation: the mean face, unrotated, translated so that its
/// projected landmarks have the target's centroid and spread.
pub fn initial_pose(
    model: &Morphable<f64>,
    target: &FitTarget,
    width: usize,
    height: usize,
    focal: f64,
) -> FaceParams {
    let mut p = FaceParams::neutral(model);
    p.focal = focal;
    let mean = model.mean_shape();
    let aspect = width as f64 / height as f64;
    let n = target.points.len().max(1) as f64;
    // Normalised image coordinates (X / D, Y / D) of the target landmarks.
    let norm: Vec<[f64; 2]> = target
        .landmarks
        .outer_iter()
        .map(|q| {
            let nx = 2.0 * q[0] / width as f64 - 1.0;
            let ny = 1.0 - 2.0 * q[1] / height as f64;
            [nx * aspect / focal, ny / focal]
        })
        .collect();
    let pts: Vec<[f64; 3]> = target
        .points
        .iter()
        .map(|q| {
            let x = q.eval(mean.view());
            [x[0], x[1], x[2]]
        })
        .collect();
    let c_img = [
        norm.iter().map(|a| a[0]).sum::<f64>() / n,
        norm.iter().map(|a| a[1]).sum::<f64>() / n,
    ];
    let c_mod = [0, 1, 2].map(|k| pts.iter().map(|a| a[k]).sum::<f64>() / n);
    let spread_img = (norm
        .iter()
        .map(|a| (a[0] - c_img[0]).powi(2) + (a[1] - c_img[1]).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    let spread_mod = (pts
        .iter()
        .map(|a| (a[0] - c_mod[0]).powi(2) + (a[1] - c_mod[1]).powi(2))
        .sum::<f64>()
        / n)
        .sqrt();
    if spread_img > 1e-9 && spread_mod > 1e-9 {
        let d = spread_mod / spread_img;
        p.translation = [
            c_img[0] * d - c_mod[0],
            c_img[1] * d - c_mod[1],
            -d - c_mod[2],
        ];
    }
    p
}

fn lr_at(base: f64, i: usize, n: usize, final_fraction: f64) -> f64 {
    let t = if n > 1 {
        i as f64 / (n - 1) as f64
    } else {
        1.0
    };
    base * (final_fraction
        + (1.0 - final_fraction) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos()))
}

/// Values of one evaluation of the loss.
struct Eval {
    loss: f64,
    landmark_term: f64,
    photo_term: f64,
    landmark_error_px: f64,
    grads: [Option<Tensor<f64>>; 7],
}

struct Problem<'a> {
    renderer: FaceRenderer<'a>,
    /// The model at the target's landmark points.
    points: PointShape<f64>,
    target: &'a FitTarget,
    target_px: std::sync::Arc<Tensor<f64>>,
    target_img: std::sync::Arc<Tensor<f64>>,
    weights: LossWeights,
}

impl Problem<'_> {
    fn eval(&self, p: &FaceParams, active: Active, photo: bool) -> Result<Eval, FitError> {
        let tape = Tape::with_capacity(256);
        let v = self.renderer.vars(&tape, p, active);
        let w = &self.weights;
        let o = &self.renderer.options;
        let s = 0.5 * o.width.max(o.height) as f64;
        let px = self.renderer.project_points_px(&self.points, &v)?;
        let y = tape.var_shared(self.target_px.clone(), false);
        let nl = self.target.points.len().max(1) as f64;
        let lmk = (px - y).square().sum() * (1.0 / (nl * s * s));
        let mut loss = lmk * w.landmarks;
        if active.shape {
            loss = loss + v.z_id.square().sum() * w.id + v.z_exp.square().sum() * w.exp;
        }
        let mut photo_term = None;
        if photo {
            let img = self.renderer.photo_image(self.renderer.posed(&v), &v)?;
            let ph = tape.apply(
                PhotoLossOp::new(self.target_img.clone(), w.charbonnier_eps),
                &[img],
            );
            loss = loss + ph * w.photo;
            photo_term = Some(ph);
            if active.appearance {
                let sh_rest = v.sh.slice(0, 1, 9);
                loss = loss + v.z_albedo.square().sum() * w.albedo + sh_rest.square().sum() * w.sh;
            }
        }
        let mut grads = tape.backward(loss)?;
        let px_val = px.value()?;
        let err = landmark_error_px(&render::to2(&px_val), &self.target.landmarks);
        let vars = [
            v.rotation,
            v.translation,
            v.focal,
            v.z_id,
            v.z_exp,
            v.z_albedo,
            v.sh,
        ];
        let g = vars.map(|x| grads.take(x));
        Ok(Eval {
            loss: loss.item()?,
            landmark_term: lmk.item()?,
            photo_term: match photo_term {
                Some(p) => p.item()?,
                None => 0.0,
            },
            landmark_error_px: err,
            grads: g,
        })
    }
}

/// The photometric term as one fused op: `sum_p m_p rho(I_p - T_p) / (3 sum_p m_p)` over the
/// RGB channels of an image `[H, W, C]` (`C >= 4`), with `m` the product of its channels after
/// RGB (alpha, or the photometric weight times alpha: [`FaceRenderer::photo_image`]) held
/// constant (no gradient flows into them) and `rho` the Charbonnier penalty. Zero when nothing
/// is covered. Fusing it avoids eight image-sized intermediates per step; the sum runs in a
/// fixed order.
struct PhotoLossOp {
    target: std::sync::Arc<Tensor<f64>>,
    eps: f64,
    /// `1 / (3 sum m)`, set by the forward.
    scale: f64,
}

impl PhotoLossOp {
    fn new(target: std::sync::Arc<Tensor<f64>>, eps: f64) -> Self {
        PhotoLossOp {
            target,
            eps,
            scale: 0.0,
        }
    }
}

impl autodiff::Op<f64> for PhotoLossOp {
    fn name(&self) -> &'static str {
        "face_photo_loss"
    }
    fn forward(&mut self, inputs: &[TensorView<'_, f64>]) -> autodiff::Result<Vec<Tensor<f64>>> {
        let img = inputs[0].as_standard_layout();
        let t = self.target.as_standard_layout();
        let s = img.shape();
        if s.len() != 3 || s[2] < 4 || t.shape() != [s[0], s[1], 3] {
            return Err(AutodiffError::shape(
                "face_photo_loss",
                &[s, t.shape()],
                "expected an image [H, W, C >= 4] and a target [H, W, 3]",
            ));
        }
        let (im, ts) = (img.as_slice().expect("std"), t.as_slice().expect("std"));
        let (mut sum, mut msum) = (0.0, 0.0);
        for (px, tp) in im.chunks_exact(s[2]).zip(ts.chunks_exact(3)) {
            let m: f64 = px[3..].iter().product();
            if m > 0.0 {
                msum += m;
                for (p, q) in px[..3].iter().zip(tp) {
                    let r = p - q;
                    sum += m * ((r * r + self.eps * self.eps).sqrt() - self.eps);
                }
            }
        }
        self.scale = if msum > 0.0 { 1.0 / (3.0 * msum) } else { 0.0 };
        Ok(vec![autodiff::tensor::scalar(sum * self.scale)])
    }
    fn backward(
        &self,
        ctx: &autodiff::BackwardCtx<'_, '_, f64>,
    ) -> autodiff::Result<Vec<Option<Tensor<f64>>>> {
        if !ctx.needs_grad[0] {
            return Ok(vec![None]);
        }
        let img = ctx.inputs[0].as_standard_layout();
        let t = self.target.as_standard_layout();
        let g = ctx.grad_outputs[0].iter().next().copied().unwrap_or(0.0) * self.scale;
        let (im, ts) = (img.as_slice().expect("std"), t.as_slice().expect("std"));
        let c = img.shape()[2];
        let mut out = vec![0.0; im.len()];
        for ((px, tp), o) in im
            .chunks_exact(c)
            .zip(ts.chunks_exact(3))
            .zip(out.chunks_exact_mut(c))
        {
            let m: f64 = px[3..].iter().product();
            if m > 0.0 {
                for ((ok, p), q) in o.iter_mut().zip(&px[..3]).zip(tp) {
                    let r = p - q;
                    *ok = g * m * r / (r * r + self.eps * self.eps).sqrt();
                }
            }
        }
        Ok(vec![Some(
            ArrayD::from_shape_vec(IxDyn(img.shape()), out).expect("same shape"),
        )])
    }
}

/// A group's Adam optimiser and which parameter tensor it moves.
struct Group {
    index: usize,
    base_lr: f64,
    adam: Adam<f64>,
}

fn groups(steps: &StepSizes, active: Active) -> Vec<Group> {
    let mut g = Vec::new();
    let mut add = |index: usize, lr: f64, on: bool| {
        if on {
            g.push(Group {
                index,
                base_lr: lr,
                adam: Adam::new(lr),
            });
        }
    };
    add(0, steps.rotation, active.pose);
    add(1, steps.translation, active.pose);
    add(2, steps.focal, active.focal);
    add(3, steps.shape, active.shape);
    add(4, steps.shape, active.shape);
    add(5, steps.albedo, active.appearance);
    add(6, steps.sh, active.appearance);
    g
}

/// Fits `model` to `target`, starting from the closed-form pose of [`initial_pose`] with
/// `focal` (or [`DEFAULT_FOV_Y_DEG`] when `None`). `progress` is called after every step.
pub fn fit(
    model: &Morphable<f64>,
    target: &FitTarget,
    focal: Option<f64>,
    options: &FitOptions,
    progress: &mut dyn FnMut(&StepRecord),
) -> Result<FitResult, FitError> {
    let o = &options.render;
    let (h, w) = (target.image.shape()[0], target.image.shape()[1]);
    if target.image.shape()[2] != 3 || h != o.height || w != o.width {
        return Err(FitError::Invalid(format!(
            "target image is {:?}, the fit renders [{}, {}, 3]",
            target.image.shape(),
            o.height,
            o.width
        )));
    }
    if target.landmarks.nrows() != target.points.len() || target.landmarks.ncols() != 2 {
        return Err(FitError::Invalid(format!(
            "{} landmark positions for {} landmark points",
            target.landmarks.nrows(),
            target.points.len()
        )));
    }
    if let Some(&v) = target
        .points
        .iter()
        .flat_map(|q| q.vertices.iter())
        .find(|&&v| v >= model.n_vertices())
    {
        return Err(FitError::Invalid(format!(
            "landmark vertex {v} out of range (the model has {} vertices)",
            model.n_vertices()
        )));
    }
    if target
        .points
        .iter()
        .any(|q| q.weights.iter().any(|w| !w.is_finite()))
    {
        return Err(FitError::Invalid(
            "landmark point weights hold non-finite values".into(),
        ));
    }
    if target.landmarks.iter().any(|v| !v.is_finite())
        || target.image.iter().any(|v| !v.is_finite())
    {
        return Err(FitError::Invalid("target holds non-finite values".into()));
    }
    let renderer = FaceRenderer::new(model, o.clone())?;
    let focal = focal.unwrap_or_else(|| focal_from_fov_deg(DEFAULT_FOV_Y_DEG));
    let t_init = Instant::now();
    let initial = initial_pose(model, target, w, h, focal);
    let init_seconds = t_init.elapsed().as_secs_f64();
    let problem = Problem {
        points: model.at_points(&target.points)?,
        renderer,
        target,
        target_px: std::sync::Arc::new(target.landmarks.clone().into_dyn()),
        target_img: std::sync::Arc::new(target.image.clone().into_dyn()),
        weights: options.weights.clone(),
    };
    let mut params = initial.clone();
    let mut history = Vec::new();
    let mut stage_seconds = [0.0; 2];
    let _hot = autodiff::ActiveWait::new();

    // Stage 1: landmarks only.
    let t0 = Instant::now();
    let n1 = options.landmark_iters;
    let pose_only = ((n1 as f64) * options.pose_only_fraction).round() as usize;
    let shape_active = Active {
        pose: true,
        focal: options.fit_focal,
        shape: true,
        appearance: false,
    };
    let pose_active = Active {
        pose: true,
        focal: false,
        shape: false,
        appearance: false,
    };
    let mut g_pose = groups(&options.steps, pose_active);
    let mut g_shape = groups(&options.steps, shape_active);
    for i in 0..n1 {
        let (active, gs, start, len) = if i < pose_only {
            (pose_active, &mut g_pose, 0, pose_only)
        } else {
            (shape_active, &mut g_shape, pose_only, n1 - pose_only)
        };
        let e = problem.eval(&params, active, false)?;
        step(
            &mut params,
            gs,
            &e,
            i - start,
            len,
            options.final_step_fraction,
        )?;
        let rec = StepRecord {
            stage: 1,
            iter: i,
            loss: e.loss,
            landmark_term: e.landmark_term,
            photo_term: 0.0,
            landmark_error_px: e.landmark_error_px,
        };
        progress(&rec);
        history.push(rec);
    }
    stage_seconds[0] = t0.elapsed().as_secs_f64();

    // Stage 2: all parameters, photometric term added.
    let t1 = Instant::now();
    let n2 = options.full_iters;
    if n2 > 0 {
        balance_light(&problem.renderer, &mut params, &target.image)?;
        let active = Active {
            pose: true,
            focal: options.fit_focal,
            shape: true,
            appearance: true,
        };
        let mut gs = groups(&options.steps, active);
        for i in 0..n2 {
            let e = problem.eval(&params, active, true)?;
            step(&mut params, &mut gs, &e, i, n2, options.final_step_fraction)?;
            let rec = StepRecord {
                stage: 2,
                iter: n1 + i,
                loss: e.loss,
                landmark_term: e.landmark_term,
                photo_term: e.photo_term,
                landmark_error_px: e.landmark_error_px,
            };
            progress(&rec);
            history.push(rec);
        }
    }
    stage_seconds[1] = t1.elapsed().as_secs_f64();
    Ok(FitResult {
        params,
        initial,
        history,
        init_seconds,
        stage_seconds,
    })
}

fn step(
    params: &mut FaceParams,
    groups: &mut [Group],
    e: &Eval,
    i: usize,
    n: usize,
    final_fraction: f64,
) -> Result<(), FitError> {
    let mut t = params.tensors();
    for g in groups.iter_mut() {
        g.adam.lr = lr_at(g.base_lr, i, n, final_fraction);
        let zero;
        let grad = match &e.grads[g.index] {
            Some(x) => x,
            None => {
                zero = Tensor::zeros(t[g.index].raw_dim());
                &zero
            }
        };
        g.adam.step([(&mut t[g.index], grad)])?;
    }
    *params = FaceParams::from_tensors(&t);
    if params.focal <= 0.0 {
        return Err(FitError::Invalid("the focal length went to <= 0".into()));
    }
    Ok(())
}

/// Scales the SH coefficients per channel so that the mean rendered colour over the covered
/// pixels of the photometric mask matches the target's there.
fn balance_light(
    renderer: &FaceRenderer<'_>,
    params: &mut FaceParams,
    target: &Array3<f64>,
) -> Result<(), FitError> {
    let img = renderer.render_photo(params)?;
    let (mut sr, mut st) = ([0.0; 3], [0.0; 3]);
    for ((r, c, k), &v) in img.indexed_iter() {
        if k < 3 && img[[r, c, 3]] > 0.5 {
            sr[k] += v;
            st[k] += target[[r, c, k]];
        }
    }
    for (k, (r, t)) in sr.iter().zip(st).enumerate() {
        if *r > 1e-9 && t > 1e-9 {
            let f = t / r;
            for row in params.sh.iter_mut() {
                row[k] *= f;
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::gradcheck::{gradcheck, GradcheckOptions};
    use autodiff::rng::Rng;

    /// The fused photometric term against composed ops, with alpha alone (`[H, W, 4]`) and
    /// with a photometric weight and alpha (`[H, W, 5]`), and its gradient (f64 finite
    /// differences).
    #[test]
    fn photo_loss_matches_composed_ops_and_gradcheck() {
        for extra in [1, 2] {
            let mut rng = Rng::new(4);
            let rgb: Tensor<f64> = rng.uniform_tensor(&[5, 6, 3], 0.0, 1.0);
            let mut weights: Tensor<f64> = rng.uniform_tensor(&[5, 6, extra], 0.0, 1.0);
            weights[[0, 0, 0]] = 0.0;
            if extra == 2 {
                weights[[1, 2, 0]] = 0.0;
            }
            let target = std::sync::Arc::new(rng.uniform_tensor::<f64>(&[5, 6, 3], 0.0, 1.0));
            let eps = 0.05;
            let op = |t: &std::sync::Arc<Tensor<f64>>| PhotoLossOp::new(t.clone(), eps);
            let m = weights.map_axis(ndarray::Axis(2), |w| w.iter().product::<f64>());
            let m = m.insert_axis(ndarray::Axis(2));
            let tape = Tape::new();
            let x = tape.leaf(rgb.clone());
            let a = tape.constant(weights.clone());
            let fused = tape.apply(op(&target), &[tape.concat(&[x, a], 2)]);
            let r = x - tape.constant((*target).clone());
            let rho = (r.square() + eps * eps).sqrt() - eps;
            let msum: f64 = m.iter().sum();
            let composed = (rho * tape.constant(m.clone())).sum() * (1.0 / (3.0 * msum));
            let (f, c) = (fused.item().unwrap(), composed.item().unwrap());
            assert!(
                (f - c).abs() < 1e-12 * c.abs().max(1.0),
                "{extra}: {f} vs {c}"
            );
            let rep = gradcheck(
                |t: &Tape<f64>, v| {
                    let a = t.constant(weights.clone());
                    t.apply(op(&target), &[t.concat(&[v[0], a], 2)])
                },
                &[rgb],
                &GradcheckOptions::default(),
            )
            .unwrap();
            assert!(rep.passed(), "{extra}: {rep}");
        }
    }

    #[test]
    fn euler_to_axis_angle_round_trips() {
        let r = euler_to_axis_angle(0.3, -0.2, 0.1);
        let tape = Tape::<f64>::new();
        let v = tape.constant(ArrayD::from_shape_vec(IxDyn(&[3]), r.to_vec()).unwrap());
        let m = render_ops::transform::axis_angle_to_matrix(v)
            .value()
            .unwrap();
        // Ry(0.3) Rx(-0.2) Rz(0.1), entry (1, 2) = -sin(pitch) = sin(0.2).
        assert!((m[[1, 2]] - 0.2f64.sin()).abs() < 1e-12, "{m}");
        let (cy, cp) = (0.3f64.cos(), 0.2f64.cos());
        assert!((m[[2, 2]] - cy * cp).abs() < 1e-12, "{m}");
    }
}
