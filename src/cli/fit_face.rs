//! `tapestry fit-face`: fits a morphable model (the shipped ICT-FaceKit model by default, the
//! small MediaPipe-mesh model with `--model mediapipe`, or any model folder given with
//! `--model`) to a synthetic target (default) or to a photo (PNG, JPEG or `.npy`,
//! any size) with 2D landmarks, and writes the fitted mesh (`fit.obj`, `fit.mtl`,
//! `albedo.png`), the landmarks (`landmarks.txt`, `detected_landmarks.txt`), the images
//! (`fit.png`, `overlay.png`, `compare.png`), `params.json`, `loss_curve.svg` and
//! `report.json` (docs/CONVENTIONS.md). Nothing is written unless the fit succeeded.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use models::fit::{
    self, Correspondence, FaceParams, FaceRenderer, FitOptions, FitResult, FitTarget,
    RenderOptions, StepRecord, SynthOptions,
};
use models::Morphable;
use ndarray::{s, Array2, Array3};
use render_ops::io::{read_image, write_png};
use render_ops::scene::Method;
use serde_json::json;

use super::CliError;

/// Arguments of `fit-face`.
#[derive(Debug, Clone)]
pub struct Args {
    /// Target photo; `None`: a synthetic target.
    pub target: Option<PathBuf>,
    /// Landmark file of the photo (overrides detection).
    pub landmarks: Option<PathBuf>,
    /// `ict`, `mediapipe` or a model folder; `None`: `ict`.
    pub model: Option<PathBuf>,
    /// Which face of the photo, largest first (detection); 0 with `--landmarks`.
    pub face: usize,
    /// Output folder.
    pub out: PathBuf,
    /// Iterations in all (half landmarks only, half all terms; a synthetic target's exact
    /// landmarks get at least [`fit::EXACT_LANDMARK_ITERS`] landmark steps).
    pub iters: usize,
    /// Seed of the synthetic target.
    pub seed: u64,
    /// Raster method name.
    pub method: String,
    /// Image size of the synthetic target; photos larger than this are resized (area
    /// filter, aspect kept) so that their longer side is this.
    pub size: usize,
    /// Side of the albedo texture of the detail stage, texels.
    pub texture_size: usize,
    /// Iterations of the detail stage (0: the model fit's albedo baked, not refined).
    pub texture_iters: usize,
}

/// Longest side of the image the detail stage fits (the input, area-resized if larger).
pub const TEXTURE_IMAGE_MAX: usize = 1024;

/// 2D landmarks of the target photo, in the photo's own pixels (x right, y down, origin at
/// the top-left corner, pixel centres at +0.5).
#[derive(Clone, Debug)]
pub struct Landmarks2D {
    /// Positions `[N, 2]`.
    pub points: Array2<f64>,
    /// Where they come from (the landmark file), named in errors.
    pub source: PathBuf,
}

fn parse_method(name: &str) -> Result<Method, CliError> {
    let m = Method::from_name(name).ok_or_else(|| {
        CliError::Message(format!(
            "--method '{name}': unknown raster method; one of {}",
            Method::ALL
                .into_iter()
                .chain(Method::RAY)
                .map(|m| m.name())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    })?;
    Ok(m)
}

fn err(e: impl std::fmt::Display) -> CliError {
    CliError::Message(e.to_string())
}

/// The target's landmarks, in the photo's pixels: the one place they come from. `--landmarks`
/// (`--face` must then be 0) is an override; without it `photo` (`[H, W, 3]`, the input's
/// pixels) goes to the face detector ([`models::detect`]: BlazeFace + the 468-point MediaPipe
/// face mesh) and `--face` picks one of its faces, largest first.
pub fn target_landmarks(
    args: &Args,
    photo: &Array3<f64>,
    given: Option<Landmarks2D>,
) -> Result<Landmarks2D, CliError> {
    let (h, w, _) = photo.dim();
    if let Some(lms) = given {
        if args.face != 0 {
            return Err(CliError::Message(format!(
                "--face {}: out of range: {} hold one face (use --face 0)",
                args.face,
                lms.source.display()
            )));
        }
        return Ok(lms);
    }
    match &args.landmarks {
        Some(path) => {
            if args.face != 0 {
                return Err(CliError::Message(format!(
                    "--face {}: out of range: --landmarks {} holds one face (use --face 0)",
                    args.face,
                    path.display()
                )));
            }
            let points = fit::read_landmarks(path).map_err(err)?;
            Ok(Landmarks2D {
                points,
                source: path.clone(),
            })
        }
        None => {
            let target = args.target.clone().unwrap_or_default();
            let faces = models::detect::detect_landmarks(photo.view()).map_err(|e| {
                CliError::Message(format!("--target {} ({w}x{h}): {e}", target.display()))
            })?;
            let n = faces.len();
            let face = faces.into_iter().nth(args.face).ok_or_else(|| {
                CliError::Message(format!(
                    "--face {}: out of range: {} has {n} face{} (largest first, from 0)",
                    args.face,
                    target.display(),
                    if n == 1 { "" } else { "s" }
                ))
            })?;
            Ok(Landmarks2D {
                points: face.points.slice(ndarray::s![.., 0..2]).to_owned(),
                source: target,
            })
        }
    }
}

/// A photo as fitted: the input `[H, W, 3]` and the image the fit sees (resized to fit
/// `size`), with the scale per axis from input to fit pixels.
struct Photo {
    input: Array3<f64>,
    fit: Array3<f64>,
    /// Fit pixels per input pixel, `[x, y]`.
    scale: [f64; 2],
}

/// Reads a photo as linear RGB `[H, W, 3]` (gray replicated, alpha dropped) and resizes it
/// (area filter) so that its longer side is at most `size`, keeping its aspect.
fn load_photo(path: &Path, size: usize) -> Result<Photo, CliError> {
    photo_from(read_image::<f64>(path)?, &path.display().to_string(), size)
}

/// [`load_photo`] of an image in memory (`name` in errors): `[H, W, C]`, `C` of 1 to 4.
fn photo_from(img: Array3<f64>, name: &str, size: usize) -> Result<Photo, CliError> {
    let (h, w, c) = img.dim();
    let input = Array3::from_shape_fn((h, w, 3), |(r, col, k)| {
        img[[r, col, if c >= 3 { k } else { 0 }]]
    });
    let too_small = || {
        CliError::Message(format!(
            "{name}: image {w}x{h} is too small (at least 16 pixels each way)"
        ))
    };
    if w < 16 || h < 16 {
        return Err(too_small());
    }
    if w.max(h) <= size {
        return Ok(Photo {
            fit: input.clone(),
            input,
            scale: [1.0, 1.0],
        });
    }
    let f = size as f64 / w.max(h) as f64;
    let (wo, ho) = (
        ((w as f64 * f).round() as usize).max(1),
        ((h as f64 * f).round() as usize).max(1),
    );
    if wo < 8 || ho < 8 {
        return Err(too_small());
    }
    Ok(Photo {
        fit: resize_area(&input, ho, wo),
        scale: [wo as f64 / w as f64, ho as f64 / h as f64],
        input,
    })
}

/// Input pixels and weights (overlap / footprint) of each of `n_out` output pixels along an
/// axis of `n_in` pixels: output pixel `j` covers `[j, j + 1) n_in / n_out`.
fn area_weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f64)>> {
    let r = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|j| {
            let (a, b) = (j as f64 * r, (j + 1) as f64 * r);
            let first = a.floor() as usize;
            let last = (b.ceil() as usize).min(n_in);
            (first..last)
                .filter_map(|i| {
                    let o = (b.min(i as f64 + 1.0) - a.max(i as f64)) / r;
                    (o > 0.0).then_some((i, o))
                })
                .collect()
        })
        .collect()
}

/// Area (box) resampling `[H, W, C]` to `[ho, wo, C]`: every output pixel is the mean of the
/// input over its footprint, pixels cut by the footprint's edge weighted by their overlap
/// (exact for any scale; no aliasing when shrinking). Separable, rows then columns.
pub fn resize_area(img: &Array3<f64>, ho: usize, wo: usize) -> Array3<f64> {
    let (h, w, c) = img.dim();
    let wx = area_weights(w, wo);
    let wy = area_weights(h, ho);
    let mut rows = Array3::<f64>::zeros((h, wo, c));
    for r in 0..h {
        for (j, ws) in wx.iter().enumerate() {
            for k in 0..c {
                rows[[r, j, k]] = ws.iter().map(|&(i, a)| a * img[[r, i, k]]).sum();
            }
        }
    }
    let mut out = Array3::<f64>::zeros((ho, wo, c));
    for (r, ws) in wy.iter().enumerate() {
        for j in 0..wo {
            for k in 0..c {
                out[[r, j, k]] = ws.iter().map(|&(i, a)| a * rows[[i, j, k]]).sum();
            }
        }
    }
    out
}

struct Progress {
    on: bool,
    landmark_iters: usize,
    total: usize,
}

impl Progress {
    fn report(&self, r: &StepRecord) {
        if !self.on {
            return;
        }
        let last = r.iter + 1 == self.landmark_iters || r.iter + 1 == self.total;
        if !r.iter.is_multiple_of(5) && !last {
            return;
        }
        let (name, i, n) = if r.stage == 1 {
            ("stage 1/2 landmarks", r.iter + 1, self.landmark_iters)
        } else {
            (
                "stage 2/2 all terms",
                r.iter + 1 - self.landmark_iters,
                self.total - self.landmark_iters,
            )
        };
        const WIDTH: usize = 24;
        let filled = (WIDTH * i).checked_div(n).unwrap_or(WIDTH).min(WIDTH);
        let bar: String = "#".repeat(filled) + &"-".repeat(WIDTH - filled);
        let mut e = std::io::stderr().lock();
        let _ = write!(
            e,
            "\r{name} [{bar}] {i:>4}/{n:<4} loss {:.4e}  landmark error {:.3} px   ",
            r.loss, r.landmark_error_px
        );
        if last {
            let _ = writeln!(e);
        }
        let _ = e.flush();
    }
}

/// What the fit is run on.
struct Prepared {
    target: FitTarget,
    /// The input image `[H, W, 3]` (the synthetic target itself when there is no photo).
    input: Array3<f64>,
    /// Fit pixels per input pixel `[x, y]`.
    scale: [f64; 2],
    /// The target landmarks used, in input pixels.
    detected: Array2<f64>,
    correspondence: String,
    truth: Option<FaceParams>,
    /// Seconds of loading (model, photo) and of the landmarks.
    load_seconds: f64,
    landmark_seconds: f64,
}

/// `--model`: `ict` (the default: the shipped ICT-FaceKit model, [`models::ict`]),
/// `mediapipe` (the small shipped model on the MediaPipe mesh, [`models::face`]) or a model
/// folder.
fn load_model(args: &Args) -> Result<Morphable<f64>, CliError> {
    let name = args.model.as_deref().unwrap_or(Path::new("ict"));
    let model = if name == Path::new("mediapipe") {
        Ok(models::face::default_face())
    } else if name == Path::new("ict") {
        models::ict::load_ict()
    } else {
        Morphable::<f64>::load(name)
    }
    .map_err(|e| CliError::Message(format!("--model {}: {e}", name.display())))?;
    if model.n_landmarks() == 0 {
        return Err(CliError::Message(format!(
            "--model {}: the model has no landmarks",
            name.display()
        )));
    }
    Ok(model)
}

fn prepare(
    args: &Args,
    model: &Morphable<f64>,
    given: Option<GivenTarget>,
    t0: Instant,
) -> Result<Prepared, CliError> {
    let given = match (given, &args.target) {
        (Some(g), _) => {
            let photo = photo_from(g.photo, "the target image", args.size)?;
            let lms = g.landmarks.map(|points| Landmarks2D {
                points,
                source: PathBuf::from("the given landmarks"),
            });
            Some((photo, lms))
        }
        (None, Some(img)) => Some((load_photo(img, args.size)?, None)),
        (None, None) => None,
    };
    match (given, &args.landmarks) {
        (Some((photo, given_lms)), _) => {
            let load_seconds = t0.elapsed().as_secs_f64();
            let t1 = Instant::now();
            let lms = target_landmarks(args, &photo.input, given_lms)?;
            let corr: Correspondence =
                fit::correspondence(model, lms.points.nrows(), &lms.source).map_err(err)?;
            let detected = corr.select(&lms.points);
            let mut landmarks = detected.clone();
            for mut row in landmarks.rows_mut() {
                row[0] *= photo.scale[0];
                row[1] *= photo.scale[1];
            }
            Ok(Prepared {
                target: FitTarget {
                    image: photo.fit,
                    landmarks,
                    points: corr.points,
                },
                input: photo.input,
                scale: photo.scale,
                detected,
                correspondence: corr.description,
                truth: None,
                load_seconds,
                landmark_seconds: t1.elapsed().as_secs_f64(),
            })
        }
        (None, None) => {
            if args.face != 0 {
                return Err(CliError::Message(format!(
                    "--face {}: out of range: a synthetic target has one face (use --face 0)",
                    args.face
                )));
            }
            let load_seconds = t0.elapsed().as_secs_f64();
            let t1 = Instant::now();
            let s = fit::synthesize(model, &SynthOptions::new(args.size, args.size, args.seed))
                .map_err(err)?;
            Ok(Prepared {
                input: s.target.image.clone(),
                scale: [1.0, 1.0],
                detected: s.target.landmarks.clone(),
                correspondence: format!(
                    "{} exact landmarks of the synthetic target",
                    s.target.points.len()
                ),
                target: s.target,
                truth: Some(s.truth),
                load_seconds,
                landmark_seconds: t1.elapsed().as_secs_f64(),
            })
        }
        (None, Some(_)) => Err(CliError::Message(
            "--landmarks needs --target (the photo they belong to)".into(),
        )),
    }
}

/// Fit pixels `[N, 2]` to input pixels.
fn to_input_px(px: &Array2<f64>, scale: [f64; 2]) -> Array2<f64> {
    let mut o = px.clone();
    for mut row in o.rows_mut() {
        row[0] /= scale[0];
        row[1] /= scale[1];
    }
    o
}

/// Every output file, made in memory before anything is written.
struct Outputs {
    pngs: Vec<(&'static str, Array3<f64>)>,
    texts: Vec<(&'static str, String)>,
}

/// A target given in memory instead of `--target` / `--landmarks` (the Python bindings).
#[derive(Clone, Debug)]
pub struct GivenTarget {
    /// The photo `[H, W, C]` (linear values in `[0, 1]`; `C` of 1 to 4: gray replicated,
    /// alpha dropped).
    pub photo: Array3<f64>,
    /// Its landmarks `[N, 2]` in the photo's pixels (as a landmark file holds them); `None`:
    /// detected.
    pub landmarks: Option<Array2<f64>>,
}

/// A finished fit, made in memory: what `fit-face` writes, and what the Python bindings return.
pub struct FaceFit {
    /// The fitted parameters.
    pub params: FaceParams,
    /// `params.json`.
    pub params_json: serde_json::Value,
    /// `report.json` (`total_seconds`: up to the end of the fit and its outputs).
    pub report: serde_json::Value,
    /// The fitted shape `[V, 3]` in model space (millimetres), as in `fit.obj`.
    pub vertices: Array2<f64>,
    /// The model's triangles.
    pub faces: Vec<[u32; 3]>,
    /// The fitted per-vertex albedo `[V, 3]`.
    pub albedo: Array2<f64>,
    /// The fit's render `[H, W, 4]` (RGBA) at the fit's size.
    pub image: Array3<f64>,
    outs: Outputs,
    start: Instant,
}

/// Runs `fit-face`: [`fit_face`], then writes its files and prints its summary.
pub fn run(args: &Args) -> Result<ExitCode, CliError> {
    let fit = fit_face(args, None)?;
    write_fit(args, fit)
}

/// The fit of `fit-face` without writing anything: the target is `given`, else `--target`
/// (with `--landmarks`), else synthetic.
pub fn fit_face(args: &Args, given: Option<GivenTarget>) -> Result<FaceFit, CliError> {
    let start = Instant::now();
    let method = parse_method(&args.method)?;
    if args.size < 16 {
        return Err(CliError::Message(format!(
            "--size {}: must be at least 16 pixels",
            args.size
        )));
    }
    if args.iters == 0 {
        return Err(CliError::Message("--iters must be at least 1".into()));
    }
    if !(2..=8192).contains(&args.texture_size) {
        return Err(CliError::Message(format!(
            "--texture-size {}: must be 2 to 8192 texels",
            args.texture_size
        )));
    }
    let model = load_model(args)?;
    let prep = prepare(args, &model, given, start)?;
    let target = &prep.target;
    let (h, w, _) = target.image.dim();
    let (hi, wi, _) = prep.input.dim();
    let mut opts = FitOptions::new(w, h, args.iters);
    if prep.truth.is_some() {
        // A synthetic target's landmarks are exact.
        opts = opts.with_exact_landmarks();
    }
    opts.render.method = method;
    // The photo's own aspect, so that fit pixels map back to input pixels by `scale`.
    opts.render.aspect = Some(wi as f64 / hi as f64);
    let progress = Progress {
        on: std::io::stderr().is_terminal(),
        landmark_iters: opts.landmark_iters,
        total: opts.landmark_iters + opts.full_iters,
    };
    let fit_start = Instant::now();
    // On a worker of rayon's global pool (`scope` runs its body on one), so that the fit's
    // parallel regions start and end without waking this thread each time.
    let result =
        rayon::scope(|_| fit::fit(&model, target, None, &opts, &mut |r| progress.report(r)))
            .map_err(err)?;
    let fit_seconds = fit_start.elapsed().as_secs_f64();

    let out_start = Instant::now();
    let renderer = FaceRenderer::new(&model, opts.render.clone()).map_err(err)?;
    let (img, _) = renderer.render(&result.params).map_err(err)?;
    let fitted_px = renderer
        .landmarks_px(&result.params, &target.points)
        .map_err(err)?;
    let fitted_in = to_input_px(&fitted_px, prep.scale);
    let lm_err = fit::landmark_error_px(&fitted_in, &prep.detected);
    // Inside the photometric mask (the pixels of the model's photometric regions).
    let rmse = fit::photometric_rmse(
        &renderer.render_photo(&result.params).map_err(err)?,
        &target.image,
    );
    let initial_in = to_input_px(
        &renderer
            .landmarks_px(&result.initial, &target.points)
            .map_err(err)?,
        prep.scale,
    );
    let lm_err0 = fit::landmark_error_px(&initial_in, &prep.detected);
    let mean_scale = 0.5 * (prep.scale[0] + prep.scale[1]);
    let n1 = opts.landmark_iters;
    let stage1_err = result
        .history
        .get(n1)
        .map(|r| r.landmark_error_px / mean_scale)
        .unwrap_or(lm_err);

    // The detail stage (models with uvs): a per-pixel albedo texture fitted at the input's
    // resolution, at most TEXTURE_IMAGE_MAX pixels on the longer side.
    let texture = if model.uvs().is_some() {
        let f = (TEXTURE_IMAGE_MAX as f64 / wi.max(hi) as f64).min(1.0);
        let (wt, ht) = (
            ((wi as f64 * f).round() as usize).max(1),
            ((hi as f64 * f).round() as usize).max(1),
        );
        let resized;
        let timg = if (wt, ht) == (wi, hi) {
            &prep.input
        } else {
            resized = resize_area(&prep.input, ht, wt);
            &resized
        };
        let mut ro = RenderOptions::new(wt, ht);
        ro.aspect = opts.render.aspect;
        let to = fit::TextureOptions {
            size: args.texture_size,
            iters: args.texture_iters,
            ..Default::default()
        };
        let t = rayon::scope(|_| fit::fit_texture(&model, &ro, &result.params, timg, &to))
            .map_err(err)?;
        Some((t, to))
    } else {
        None
    };

    // The fit drawn at the input's resolution (hard rasterization; textured when the detail
    // stage ran).
    let mut full = RenderOptions::new(wi, hi);
    full.aspect = opts.render.aspect;
    let full_renderer = FaceRenderer::new(&model, full).map_err(err)?;
    let full_img = match &texture {
        Some((t, _)) if t.image.dim().0 == hi && t.image.dim().1 == wi => t.image.clone(),
        Some((t, _)) => {
            let texels = t.texels.clone().into_dyn();
            fit::render_textured(&full_renderer, &result.params, &texels, &t.textured)
                .map_err(err)?
        }
        None if (wi, hi) == (w, h) && method == Method::Hard => img.clone(),
        None => full_renderer.render(&result.params).map_err(err)?.0,
    };
    // compare.png shows the fit inside the photometric mask only: the pixels it was asked to
    // match (ICT: the narrow face, without eyes and mouth socket).
    let photo_mask = full_renderer
        .render_photo(&result.params)
        .map_err(err)?
        .slice_move(s![.., .., 3]);
    let pjson = params_json(&model, &result.params, method, [w, h], [wi, hi]);
    let mut outs = Outputs {
        pngs: vec![
            ("fit.png", img.slice(s![.., .., 0..3]).to_owned()),
            (
                "overlay.png",
                overlay(&prep.input, &full_img, &prep.detected, &fitted_in),
            ),
            ("compare.png", compare(&prep.input, &full_img, &photo_mask)),
        ],
        texts: vec![
            ("landmarks.txt", points_text(&fitted_in)),
            ("detected_landmarks.txt", points_text(&prep.detected)),
            (
                "loss_curve.svg",
                loss_curve_svg(&result, opts.landmark_iters),
            ),
            (
                "params.json",
                serde_json::to_string_pretty(&pjson).expect("json"),
            ),
        ],
    };
    let (vertices, albedo) = mesh_outputs(
        &model,
        &result.params,
        texture.as_ref().map(|t| &t.0),
        &mut outs,
    )?;
    let outputs_seconds = out_start.elapsed().as_secs_f64();

    let n1f = opts.landmark_iters.max(1) as f64;
    let n2f = opts.full_iters.max(1) as f64;
    let mut report = json!({
        "method": method.name(),
        "model": model.name(),
        "iterations": opts.landmark_iters + opts.full_iters,
        "landmark_iterations": opts.landmark_iters,
        "full_iterations": opts.full_iters,
        "landmark_error_px": lm_err,
        "initial_landmark_error_px": lm_err0,
        "photometric_rmse": rmse,
        "seconds": fit_seconds,
        "total_seconds": 0.0,
        "stage_seconds": result.stage_seconds,
        "seconds_per_iteration": {
            "landmarks": result.stage_seconds[0] / n1f,
            "full": result.stage_seconds[1] / n2f,
        },
        "stages": [
            {"stage": "load", "seconds": prep.load_seconds},
            {"stage": "landmarks", "seconds": prep.landmark_seconds,
             "landmarks": target.points.len(), "correspondence": prep.correspondence},
            {"stage": "pose_init", "seconds": result.init_seconds,
             "landmark_error_px": lm_err0},
            {"stage": "stage1", "seconds": result.stage_seconds[0],
             "iterations": opts.landmark_iters, "landmark_error_px": stage1_err},
            {"stage": "stage2", "seconds": result.stage_seconds[1],
             "iterations": opts.full_iters, "landmark_error_px": lm_err,
             "photometric_rmse": rmse},
            {"stage": "texture", "seconds": texture.as_ref().map(|t| t.0.seconds),
             "photometric_rmse": texture.as_ref().map(|t| t.0.rmse_after)},
            {"stage": "outputs", "seconds": outputs_seconds},
        ],
        "width": w,
        "height": h,
        "input_width": wi,
        "input_height": hi,
        "landmarks": target.points.len(),
        "target": match (&args.target, prep.truth.is_some()) {
            (Some(p), _) => p.display().to_string(),
            (None, true) => "synthetic".to_string(),
            (None, false) => "array".to_string(),
        },
        "final_loss": result.history.last().map(|r| r.loss),
    });
    report["texture"] = match &texture {
        Some((t, o)) => json!({
            "options": o,
            "image_width": t.image.dim().1,
            "image_height": t.image.dim().0,
            "pixels": t.pixels,
            "seen_texels": t.seen.iter().filter(|&&b| b).count(),
            "photometric_rmse_before": t.rmse_before,
            "photometric_rmse_after": t.rmse_after,
            "seconds": t.seconds,
        }),
        None => json!({"skipped": "the model has no uvs"}),
    };
    if let Some(truth) = &prep.truth {
        let true_shape = truth.shape(&model).map_err(err)?;
        let fit_shape = result.params.shape(&model).map_err(err)?;
        let mean = model.mean_shape();
        report["seed"] = json!(args.seed);
        report["shape_error_mm"] = json!(fit::shape_error_mm(&fit_shape, &true_shape));
        report["shape_error_scale_aligned_mm"] =
            json!(fit::shape_error_scale_aligned_mm(&fit_shape, &true_shape));
        report["shape_error_rigid_aligned_mm"] =
            json!(fit::shape_error_rigid_aligned_mm(&fit_shape, &true_shape));
        report["mean_shape_error_mm"] = json!(fit::shape_error_mm(&mean, &true_shape));
    } else {
        report["image_scale"] = json!(prep.scale);
    }

    report["total_seconds"] = json!(start.elapsed().as_secs_f64());
    Ok(FaceFit {
        params_json: pjson,
        params: result.params,
        report,
        vertices,
        faces: model.faces().to_vec(),
        albedo,
        image: img,
        outs,
        start,
    })
}

/// Writes the files of a finished fit and prints its summary.
fn write_fit(args: &Args, fit: FaceFit) -> Result<ExitCode, CliError> {
    let FaceFit {
        mut report,
        outs,
        start,
        ..
    } = fit;
    let f = |k: &str| report[k].as_f64().unwrap_or(f64::NAN);
    let (lm_err, lm_err0, rmse, fit_seconds) = (
        f("landmark_error_px"),
        f("initial_landmark_error_px"),
        f("photometric_rmse"),
        f("seconds"),
    );
    let spi = &report["seconds_per_iteration"];
    let (spi1, spi2) = (
        spi["landmarks"].as_f64().unwrap_or(f64::NAN),
        spi["full"].as_f64().unwrap_or(f64::NAN),
    );
    let method = report["method"].as_str().unwrap_or_default().to_string();
    // Every input was good and the fit ran: only now the folder and the files.
    std::fs::create_dir_all(&args.out).map_err(|e| {
        CliError::Message(format!("{}: cannot create folder: {e}", args.out.display()))
    })?;
    let out = |name: &str| args.out.join(name);
    for (name, png) in &outs.pngs {
        write_png(out(name), png)?;
    }
    for (name, text) in &outs.texts {
        write_text(&out(name), text)?;
    }
    let total = start.elapsed().as_secs_f64();
    report["total_seconds"] = json!(total);
    write_text(
        &out("report.json"),
        &serde_json::to_string_pretty(&report).expect("json"),
    )?;

    println!("method: {method}");
    println!("landmark error: {lm_err:.3} px (initial {lm_err0:.2} px)");
    println!("photometric RMSE: {rmse:.4}");
    let tex = &report["texture"];
    if let (Some(a), Some(b)) = (
        tex["photometric_rmse_before"].as_f64(),
        tex["photometric_rmse_after"].as_f64(),
    ) {
        println!(
            "albedo texture: photometric RMSE {a:.4} -> {b:.4} at {}x{} ({:.2} s)",
            tex["image_width"],
            tex["image_height"],
            tex["seconds"].as_f64().unwrap_or(f64::NAN)
        );
    }
    if let Some(s) = report.get("shape_error_mm").and_then(|v| v.as_f64()) {
        println!(
            "shape error: {s:.3} mm, {:.3} mm after rigid alignment (mean shape: {:.3} mm)",
            report["shape_error_rigid_aligned_mm"]
                .as_f64()
                .unwrap_or(f64::NAN),
            report["mean_shape_error_mm"].as_f64().unwrap_or(f64::NAN)
        );
    }
    println!(
        "time: {fit_seconds:.2} s fit ({} iterations: {:.1} ms/iter landmarks, {:.1} ms/iter all terms), {total:.2} s in all",
        report["iterations"],
        1e3 * spi1,
        1e3 * spi2
    );
    println!("wrote {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

fn write_text(path: &Path, text: &str) -> Result<(), CliError> {
    std::fs::write(path, text)
        .map_err(|e| CliError::Message(format!("{}: cannot write: {e}", path.display())))
}

/// One `x y` line per point.
fn points_text(p: &Array2<f64>) -> String {
    p.rows()
        .into_iter()
        .map(|r| format!("{:.4} {:.4}\n", r[0], r[1]))
        .collect()
}

/// `fit.obj` (the fitted shape in model space, millimetres) and `fit.mtl` ([`fit::face_obj`]),
/// and `albedo.png` when the model has uvs.
fn mesh_outputs(
    model: &Morphable<f64>,
    p: &FaceParams,
    texture: Option<&fit::TextureFit>,
    outs: &mut Outputs,
) -> Result<(Array2<f64>, Array2<f64>), CliError> {
    let shape = p.shape(model).map_err(err)?;
    let albedo = p.albedo(model).map_err(err)?;
    let textured = match texture {
        Some(t) => t.textured.to_vec(),
        None => vec![false; model.n_faces()],
    };
    let files = fit::face_obj(model, &shape, &albedo, &textured, "fit.mtl", "albedo.png");
    if let Some(t) = texture {
        outs.pngs.push(("albedo.png", t.texels.clone()));
    }
    outs.texts.push(("fit.obj", files.obj));
    outs.texts.push(("fit.mtl", files.mtl));
    Ok((shape, albedo))
}

fn params_json(
    model: &Morphable<f64>,
    p: &FaceParams,
    method: Method,
    fit_size: [usize; 2],
    input_size: [usize; 2],
) -> serde_json::Value {
    let scaled = |z: &[f64], s: ndarray::ArrayView1<'_, f64>| -> Vec<f64> {
        z.iter().zip(s.iter()).map(|(a, b)| a * b).collect()
    };
    json!({
        "model": model.name(),
        "method": method.name(),
        "image": {"width": fit_size[0], "height": fit_size[1]},
        "input_image": {"width": input_size[0], "height": input_size[1]},
        "camera": {
            "view": "identity (camera at the origin looking down -z, y up)",
            "focal": p.focal,
            "fov_y_deg": p.fov_y_deg(),
            "aspect": input_size[0] as f64 / input_size[1] as f64,
            "near_mm": fit::NEAR_MM,
            "far_mm": fit::FAR_MM,
        },
        "rotation_axis_angle": p.rotation,
        "translation_mm": p.translation,
        "z_id": p.z_id,
        "z_exp": p.z_exp,
        "z_albedo": p.z_albedo,
        "alpha_id": scaled(&p.z_id, model.sigma_id()),
        "beta_exp": scaled(&p.z_exp, model.sigma_exp()),
        "gamma_albedo": scaled(&p.z_albedo, model.sigma_albedo()),
        "sh": p.sh,
    })
}

/// Input | fit (the render over the input where `mask` `[H, W]` covers it) | absolute
/// difference, side by side, each `[H, W, 3]`.
fn compare(input: &Array3<f64>, render: &Array3<f64>, mask: &Array2<f64>) -> Array3<f64> {
    let (h, w, _) = input.dim();
    let mut o = Array3::<f64>::zeros((h, 3 * w, 3));
    for r in 0..h {
        for c in 0..w {
            let a = mask[[r, c]];
            for k in 0..3 {
                let x = input[[r, c, k]];
                let f = (1.0 - a) * x + a * render[[r, c, k]];
                o[[r, c, k]] = x;
                o[[r, w + c, k]] = f;
                o[[r, 2 * w + c, k]] = (f - x).abs();
            }
        }
    }
    o
}

/// The fit blended over the target where it covers it, with the target landmarks (green)
/// and the fitted ones (red) drawn as dots.
fn overlay(
    target: &Array3<f64>,
    render: &Array3<f64>,
    target_lm: &Array2<f64>,
    fit_lm: &Array2<f64>,
) -> Array3<f64> {
    let (h, w, _) = target.dim();
    let mut o = target.clone();
    for r in 0..h {
        for c in 0..w {
            let a = 0.5 * render[[r, c, 3]];
            for k in 0..3 {
                o[[r, c, k]] = (1.0 - a) * target[[r, c, k]] + a * render[[r, c, k]];
            }
        }
    }
    let radius = (w.max(h) / 200) as isize;
    let mut dot = |p: ndarray::ArrayView1<'_, f64>, col: [f64; 3]| {
        let (x, y) = (p[0].floor() as isize, p[1].floor() as isize);
        for dy in -radius..=radius {
            for dx in -radius..=radius {
                if dx != 0 && dy != 0 {
                    continue;
                }
                let (xx, yy) = (x + dx, y + dy);
                if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                    for (k, v) in col.iter().enumerate() {
                        o[[yy as usize, xx as usize, k]] = *v;
                    }
                }
            }
        }
    };
    for p in target_lm.outer_iter() {
        dot(p, [0.0, 1.0, 0.0]);
    }
    for p in fit_lm.outer_iter() {
        dot(p, [1.0, 0.0, 0.0]);
    }
    o
}

/// A self-contained SVG line plot of the loss (log scale) against the iteration, with the
/// stage boundary marked.
fn loss_curve_svg(result: &FitResult, landmark_iters: usize) -> String {
    let (w, h) = (640.0, 400.0);
    let (l, r, t, b) = (70.0, 20.0, 30.0, 50.0);
    let losses: Vec<f64> = result
        .history
        .iter()
        .map(|s| s.loss.max(1e-300).log10())
        .collect();
    let n = losses.len().max(2) as f64 - 1.0;
    let lo = losses.iter().copied().fold(f64::INFINITY, f64::min).floor();
    let hi = losses
        .iter()
        .copied()
        .fold(f64::NEG_INFINITY, f64::max)
        .ceil();
    let (lo, hi) = if lo.is_finite() && hi > lo {
        (lo, hi)
    } else {
        (-1.0, 1.0)
    };
    let x = |i: f64| l + (w - l - r) * i / n;
    let y = |v: f64| t + (h - t - b) * (hi - v) / (hi - lo);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n<text x=\"{}\" y=\"18\" text-anchor=\"middle\" font-size=\"14\">fit-face loss</text>\n",
        w / 2.0
    );
    s += &format!(
        "<rect x=\"{l}\" y=\"{t}\" width=\"{}\" height=\"{}\" fill=\"none\" stroke=\"black\"/>\n",
        w - l - r,
        h - t - b
    );
    let mut e = lo as i64;
    while e as f64 <= hi {
        let yy = y(e as f64);
        s += &format!(
            "<line x1=\"{l}\" x2=\"{}\" y1=\"{yy:.1}\" y2=\"{yy:.1}\" stroke=\"#ddd\"/><text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">1e{e}</text>\n",
            w - r,
            l - 5.0,
            yy + 4.0
        );
        e += 1;
    }
    let ticks = 5;
    for k in 0..=ticks {
        let i = n * k as f64 / ticks as f64;
        s += &format!(
            "<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{}</text>\n",
            x(i),
            h - b + 18.0,
            i.round() as i64
        );
    }
    s += &format!(
        "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">iteration</text>\n",
        (l + w - r) / 2.0,
        h - 10.0
    );
    if landmark_iters > 0 && (landmark_iters as f64) < n {
        let xx = x(landmark_iters as f64 - 0.5);
        s += &format!(
            "<line x1=\"{xx:.1}\" x2=\"{xx:.1}\" y1=\"{t}\" y2=\"{}\" stroke=\"gray\" stroke-dasharray=\"4 3\"/><text x=\"{:.1}\" y=\"{}\" fill=\"gray\">stage 2: + photometric</text>\n",
            h - b,
            xx + 4.0,
            t + 14.0
        );
    }
    let pts: Vec<String> = losses
        .iter()
        .enumerate()
        .map(|(i, &v)| format!("{:.1},{:.1}", x(i as f64), y(v)))
        .collect();
    s += &format!(
        "<polyline fill=\"none\" stroke=\"#1f77b4\" stroke-width=\"1.5\" points=\"{}\"/>\n</svg>\n",
        pts.join(" ")
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn area_resize_keeps_means_and_matches_box_filters() {
        let img = Array3::from_shape_fn((12, 10, 3), |(r, c, k)| {
            ((r * 7 + c * 3 + k * 5) % 11) as f64 / 10.0
        });
        // An integer factor: the plain box mean.
        let half = resize_area(&img, 6, 5);
        for (r, c, k) in [(0, 0, 0), (3, 2, 1), (5, 4, 2)] {
            let want = (0..2)
                .flat_map(|i| (0..2).map(move |j| (i, j)))
                .map(|(i, j)| img[[2 * r + i, 2 * c + j, k]])
                .sum::<f64>()
                / 4.0;
            assert!((half[[r, c, k]] - want).abs() < 1e-12);
        }
        // Any factor: weights sum to 1 (constants stay) and the image mean is kept.
        let odd = resize_area(&img, 7, 3);
        let flat = resize_area(&Array3::from_elem((12, 10, 1), 0.3), 5, 7);
        assert!(flat.iter().all(|v| (v - 0.3).abs() < 1e-12));
        for k in 0..3 {
            let m_in = img.slice(s![.., .., k]).mean().unwrap();
            let m_out = odd.slice(s![.., .., k]).mean().unwrap();
            assert!((m_in - m_out).abs() < 1e-12, "{m_in} vs {m_out}");
        }
    }
}
