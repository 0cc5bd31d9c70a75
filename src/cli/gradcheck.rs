//! `tapestry gradcheck`: the gradient checker over every registered case (a table or JSON),
//! or over one scene's pipeline with respect to one input (`render_ops::check::scene`).

use std::path::PathBuf;
use std::process::ExitCode;

use autodiff::suite::render_table;
use autodiff::suite::CaseResult;
use render_ops::check::scene::{
    check_scene, write_outputs, SceneCheck, SceneCheckOptions, SceneInput,
};
use render_ops::io::read_image;
use render_ops::scene::{Method, Scene};

use super::CliError;

/// Worst items listed in the reports.
pub const WORST: usize = 10;

/// Runs the registered cases (filtered by `op`), prints them, and fails when any case fails.
pub fn run(op: Option<&str>, json: bool) -> Result<ExitCode, CliError> {
    let results = render_ops::check::registry().run(op);
    if results.is_empty() {
        return Err(CliError::Message(format!(
            "gradcheck: no op matches '{}'",
            op.unwrap_or_default()
        )));
    }
    if json {
        let recs: Vec<serde_json::Value> = results.iter().map(case_json).collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&recs).map_err(|e| CliError::Message(e.to_string()))?
        );
    } else {
        print!("{}", render_table(&results));
    }
    Ok(if results.iter().all(|r| r.passed) {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// One registered case's result as the JSON record of `gradcheck --json`.
pub fn case_json(r: &CaseResult) -> serde_json::Value {
    serde_json::json!({
        "op": r.op,
        "category": r.category,
        "shapes": r.shapes,
        "max_abs_err": r.max_abs_err,
        "max_rel_err": r.max_rel_err,
        "f32_rel": r.f32_rel,
        "passed": r.passed,
        "error": r.error,
    })
}

/// Arguments of the scene check.
#[derive(Clone, Debug)]
pub struct SceneArgs {
    /// Scene JSON.
    pub scene: PathBuf,
    /// The input checked.
    pub wrt: SceneInput,
    /// Target image.
    pub target: Option<PathBuf>,
    /// Method override.
    pub method: Option<String>,
    /// Reference samples per pixel along each axis.
    pub samples: usize,
    /// Most items checked.
    pub vertices: usize,
    /// Output folder (heat map, report.json).
    pub out: Option<PathBuf>,
    /// Self-test factor on the input's gradient.
    pub backward_scale: Option<f64>,
    /// JSON instead of text.
    pub json: bool,
}

/// Checks a scene's gradient, prints the report, writes the outputs; exit code 1 on failure.
pub fn run_scene(a: &SceneArgs) -> Result<ExitCode, CliError> {
    let check = check_scene_args(a)?;
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&check.to_json(WORST))
                .map_err(|e| CliError::Message(e.to_string()))?
        );
    } else {
        print!("{}", check.render_text(WORST));
    }
    if let Some(dir) = &a.out {
        for p in write_outputs(&check, dir, WORST)? {
            eprintln!("wrote {}", p.display());
        }
    }
    Ok(if check.passed() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

/// The scene check of `a` (nothing printed or written).
pub fn check_scene_args(a: &SceneArgs) -> Result<SceneCheck, CliError> {
    let mut scene = Scene::<f64>::load(&a.scene)?;
    if let Some(m) = &a.method {
        let method = Method::from_name(m).ok_or_else(|| {
            let names: Vec<&str> = Method::ALL
                .iter()
                .chain(&Method::RAY)
                .map(|m| m.name())
                .collect();
            CliError::Message(format!(
                "--method '{m}': expected one of {}",
                names.join(", ")
            ))
        })?;
        scene.desc.raster.method = method;
    }
    let target = match &a.target {
        Some(p) => Some(read_image::<f64>(p)?.into_dyn()),
        None => None,
    };
    let input = a.wrt;
    if a.backward_scale.is_some_and(|f| !f.is_finite()) {
        return Err(CliError::Message(
            "--self-test-backward-scale must be finite".into(),
        ));
    }
    let mut opts = SceneCheckOptions::new(input);
    opts.samples = a.samples;
    opts.items = a.vertices;
    opts.heatmap = a.out.is_some();
    opts.backward_scale = a.backward_scale;
    Ok(check_scene(&scene, target.as_ref(), &opts)?)
}
