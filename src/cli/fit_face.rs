//! `tapestry fit-face`: fits the shipped face model to a synthetic target (default) or to a
//! photo with 2D landmarks, and writes `params.json`, `fit.png`, `overlay.png`,
//! `loss_curve.svg` and `report.json` (docs/CONVENTIONS.md).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use models::fit::{
    self, FaceParams, FaceRenderer, FitOptions, FitResult, FitTarget, StepRecord, SynthOptions,
};
use models::Morphable;
use ndarray::{Array2, Array3};
use render_ops::io::{read_image, write_png};
use render_ops::scene::Method;
use serde_json::json;

use super::CliError;

/// Arguments of `fit-face`.
#[derive(Debug, Clone)]
pub struct Args {
    /// Target photo; `None`: a synthetic target.
    pub target: Option<PathBuf>,
    /// Landmark file of the photo.
    pub landmarks: Option<PathBuf>,
    /// Output folder.
    pub out: PathBuf,
    /// Iterations in all (half landmarks only, half all terms).
    pub iters: usize,
    /// Seed of the synthetic target.
    pub seed: u64,
    /// Raster method name.
    pub method: String,
    /// Image size of the synthetic target; photos larger than this are box-downscaled by an
    /// integer factor to at most this size.
    pub size: usize,
}

fn parse_method(name: &str) -> Result<Method, CliError> {
    let m = Method::from_name(name).ok_or_else(|| {
        CliError::Message(format!(
            "--method '{name}': unknown raster method; one of {}",
            Method::ALL.map(|m| m.name()).join(", ")
        ))
    })?;
    fit::check_method(m).map_err(|e| CliError::Message(format!("--method: {e}")))?;
    Ok(m)
}

fn err(e: impl std::fmt::Display) -> CliError {
    CliError::Message(e.to_string())
}

/// The photo as linear RGB `[H, W, 3]` (gray replicated, alpha dropped), box-downscaled by an
/// integer factor so that it fits in `size`; the factor is returned.
fn load_photo(path: &Path, size: usize) -> Result<(Array3<f64>, usize), CliError> {
    let img = read_image::<f64>(path)?;
    let (h, w, c) = img.dim();
    let k = w.max(h).div_ceil(size.max(1)).max(1);
    let (ho, wo) = (h / k, w / k);
    if ho == 0 || wo == 0 {
        return Err(CliError::Message(format!(
            "{}: image {w}x{h} is too small",
            path.display()
        )));
    }
    let mut out = Array3::<f64>::zeros((ho, wo, 3));
    let inv = 1.0 / (k * k) as f64;
    for r in 0..ho {
        for col in 0..wo {
            for ch in 0..3 {
                let src = if c >= 3 { ch } else { 0 };
                let mut s = 0.0;
                for i in 0..k {
                    for j in 0..k {
                        s += img[[r * k + i, col * k + j, src]];
                    }
                }
                out[[r, col, ch]] = s * inv;
            }
        }
    }
    Ok((out, k))
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
        if !r.iter.is_multiple_of(10) && !last {
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
        let mut e = std::io::stderr().lock();
        let _ = write!(
            e,
            "\r{name}: {i:>4}/{n:<4} loss {:.4e}  landmark error {:.3} px   ",
            r.loss, r.landmark_error_px
        );
        if last {
            let _ = writeln!(e);
        }
        let _ = e.flush();
    }
}

/// Runs `fit-face`.
pub fn run(args: &Args) -> Result<ExitCode, CliError> {
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
    let model: Morphable<f64> = models::face::default_face();
    let (target, truth, scale) = match (&args.target, &args.landmarks) {
        (Some(img), Some(lm)) => {
            let lms = fit::read_landmarks(lm).map_err(err)?;
            let vertices = fit::landmark_vertices(&model, lms.nrows(), lm).map_err(err)?;
            let (image, k) = load_photo(img, args.size)?;
            let landmarks = lms / k as f64;
            let t = FitTarget {
                image,
                landmarks,
                vertices,
            };
            (t, None, k as f64)
        }
        (None, None) => {
            let s = fit::synthesize(&model, &SynthOptions::new(args.size, args.size, args.seed))
                .map_err(err)?;
            (s.target, Some(s.truth), 1.0)
        }
        (Some(_), None) => {
            return Err(CliError::Message(
                "--target needs --landmarks (one `x y` line per landmark)".into(),
            ))
        }
        (None, Some(_)) => {
            return Err(CliError::Message(
                "--landmarks needs --target (the photo they belong to)".into(),
            ))
        }
    };
    let (h, w, _) = target.image.dim();
    let mut opts = FitOptions::new(w, h, args.iters);
    opts.render.method = method;
    let progress = Progress {
        on: std::io::stderr().is_terminal(),
        landmark_iters: opts.landmark_iters,
        total: args.iters,
    };
    let fit_start = Instant::now();
    // On a worker of rayon's global pool (`scope` runs its body on one), so that the fit's
    // parallel regions start and end without waking this thread each time.
    let result =
        rayon::scope(|_| fit::fit(&model, &target, None, &opts, &mut |r| progress.report(r)))
            .map_err(err)?;
    let fit_seconds = fit_start.elapsed().as_secs_f64();

    let renderer = FaceRenderer::new(&model, opts.render.clone()).map_err(err)?;
    let (img, px) = renderer.render(&result.params).map_err(err)?;
    let fitted_lm = px.select(ndarray::Axis(0), &target.vertices);
    let lm_err = fit::landmark_error_px(&fitted_lm, &target.landmarks) * scale;
    let rmse = fit::photometric_rmse(&img, &target.image);
    let (_, px0) = renderer.render(&result.initial).map_err(err)?;
    let lm_err0 = fit::landmark_error_px(
        &px0.select(ndarray::Axis(0), &target.vertices),
        &target.landmarks,
    ) * scale;

    std::fs::create_dir_all(&args.out).map_err(|e| {
        CliError::Message(format!("{}: cannot create folder: {e}", args.out.display()))
    })?;
    let out = |name: &str| args.out.join(name);
    write_png(out("fit.png"), &img.slice(ndarray::s![.., .., 0..3]))?;
    write_png(
        out("overlay.png"),
        &overlay(&target.image, &img, &target.landmarks, &fitted_lm),
    )?;
    write_text(
        &out("loss_curve.svg"),
        &loss_curve_svg(&result, opts.landmark_iters),
    )?;
    write_text(
        &out("params.json"),
        &serde_json::to_string_pretty(&params_json(&model, &result.params, method, w, h))
            .expect("json"),
    )?;

    let n1 = opts.landmark_iters.max(1) as f64;
    let n2 = opts.full_iters.max(1) as f64;
    let mut report = json!({
        "method": method.name(),
        "iterations": args.iters,
        "landmark_iterations": opts.landmark_iters,
        "full_iterations": opts.full_iters,
        "landmark_error_px": lm_err,
        "initial_landmark_error_px": lm_err0,
        "photometric_rmse": rmse,
        "seconds": fit_seconds,
        "total_seconds": 0.0,
        "stage_seconds": result.stage_seconds,
        "seconds_per_iteration": {
            "landmarks": result.stage_seconds[0] / n1,
            "full": result.stage_seconds[1] / n2,
        },
        "width": w,
        "height": h,
        "landmarks": target.vertices.len(),
        "target": match &args.target {
            Some(p) => p.display().to_string(),
            None => "synthetic".to_string(),
        },
        "final_loss": result.history.last().map(|r| r.loss),
    });
    if let Some(truth) = &truth {
        let true_shape = truth.shape(&model).map_err(err)?;
        let fit_shape = result.params.shape(&model).map_err(err)?;
        let mean = model.mean_shape();
        report["seed"] = json!(args.seed);
        report["shape_error_mm"] = json!(fit::shape_error_mm(&fit_shape, &true_shape));
        report["shape_error_scale_aligned_mm"] =
            json!(fit::shape_error_scale_aligned_mm(&fit_shape, &true_shape));
        report["mean_shape_error_mm"] = json!(fit::shape_error_mm(&mean, &true_shape));
    } else {
        report["image_scale"] = json!(scale);
    }
    let total = start.elapsed().as_secs_f64();
    report["total_seconds"] = json!(total);
    write_text(
        &out("report.json"),
        &serde_json::to_string_pretty(&report).expect("json"),
    )?;

    println!("method: {}", method.name());
    println!("landmark error: {lm_err:.3} px (initial {lm_err0:.2} px)");
    println!("photometric RMSE: {rmse:.4}");
    if let Some(s) = report.get("shape_error_mm").and_then(|v| v.as_f64()) {
        println!(
            "shape error: {s:.3} mm (mean shape: {:.3} mm)",
            report["mean_shape_error_mm"].as_f64().unwrap_or(f64::NAN)
        );
    }
    println!(
        "time: {fit_seconds:.2} s fit ({} iterations: {:.1} ms/iter landmarks, {:.1} ms/iter all terms), {total:.2} s in all",
        args.iters,
        1e3 * result.stage_seconds[0] / n1,
        1e3 * result.stage_seconds[1] / n2
    );
    println!("wrote {}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

fn write_text(path: &Path, text: &str) -> Result<(), CliError> {
    std::fs::write(path, text)
        .map_err(|e| CliError::Message(format!("{}: cannot write: {e}", path.display())))
}

fn params_json(
    model: &Morphable<f64>,
    p: &FaceParams,
    method: Method,
    w: usize,
    h: usize,
) -> serde_json::Value {
    let scaled = |z: &[f64], s: ndarray::ArrayView1<'_, f64>| -> Vec<f64> {
        z.iter().zip(s.iter()).map(|(a, b)| a * b).collect()
    };
    json!({
        "model": model.name(),
        "method": method.name(),
        "image": {"width": w, "height": h},
        "camera": {
            "view": "identity (camera at the origin looking down -z, y up)",
            "focal": p.focal,
            "fov_y_deg": p.fov_y_deg(),
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
    let radius: isize = if w.max(h) >= 200 { 1 } else { 0 };
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
