//! The `tapestry` command line (see docs/CONVENTIONS.md): argument parsing and the commands.
//! Every command returns a typed error that `main` prints as one line on stderr.

mod bench;
pub mod fit_face;
mod grad;
pub mod gradcheck;
mod landmarks;
mod render;
mod timing;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use thiserror::Error;

/// Differentiable rendering: render scenes, take gradients of image losses, check gradients.
#[derive(Debug, Parser)]
#[command(name = "tapestry", version, about, long_about = None)]
pub struct Cli {
    /// The command.
    #[command(subcommand)]
    pub command: Command,
}

/// What a `grad` gradient is taken with respect to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum WrtArg {
    /// Vertex positions, written as [V, 3].
    Positions,
    /// Vertex colours, written as [V, 3].
    Colors,
    /// Texture texels, written as [H, W, C] (the scene needs a texture).
    Texture,
    /// Camera eye and look-at point, written as [2, 3] (rows eye, at).
    Camera,
    /// Light parameters, written as [n, 3]: every light in scene order (ambient: colour;
    /// directional: direction, colour; point: position, colour; sh: 9 rows).
    Lights,
}

impl From<WrtArg> for render_ops::pipeline::SceneInput {
    fn from(w: WrtArg) -> Self {
        use render_ops::pipeline::SceneInput as I;
        match w {
            WrtArg::Positions => I::Positions,
            WrtArg::Colors => I::Colors,
            WrtArg::Texture => I::Texture,
            WrtArg::Camera => I::Camera,
            WrtArg::Lights => I::Lights,
        }
    }
}

/// The commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Render a scene JSON to a PNG (RGB over the background) and optionally a .npy ([H, W, 4] RGBA).
    Render {
        /// Scene JSON (docs/CONVENTIONS.md).
        scene: PathBuf,
        /// Output PNG.
        #[arg(long)]
        out: PathBuf,
        /// Also write the float RGBA image [H, W, 4] as .npy.
        #[arg(long)]
        npy: Option<PathBuf>,
        /// Render N more times in process and print their timings as one JSON line on stderr
        /// (wall min and median, CPU per render; no start-up, parsing or file output).
        #[arg(long, default_value_t = 0, value_name = "N")]
        repeat: usize,
    },
    /// Gradient of L = sum (render - target)^2 with respect to a scene input, written as .npy.
    Grad {
        /// Scene JSON.
        scene: PathBuf,
        /// Target image: PNG or .npy [H, W, 3] (compared with RGB) or [H, W, 4] (RGBA).
        #[arg(long)]
        target: PathBuf,
        /// The input to differentiate.
        #[arg(long, value_enum)]
        wrt: WrtArg,
        /// Output .npy in the input's shape.
        #[arg(long)]
        out: PathBuf,
        /// Compute the gradient N more times in process and print their timings as one JSON
        /// line on stderr (as `render --repeat`).
        #[arg(long, default_value_t = 0, value_name = "N")]
        repeat: usize,
    },
    /// Check gradients against finite differences: every registered case (autodiff ops,
    /// shading, texture, rasterization, each raster method), or the gradient of
    /// L = sum (render - target)^2 through a scene's pipeline with respect to one input.
    ///
    /// Scene check (SCENE.json --wrt INPUT): the analytic gradient against f64 central
    /// differences of the method's own image (colors, texture, lights: every method must
    /// agree within rtol 1e-4, atol 1e-6 (1 + max|numeric|); positions, camera: hard, deodr,
    /// softras, dibr within rtol 1e-3, atol 1e-5 (1 + max|numeric|)), and for positions and
    /// camera against central differences (0.75 px steps) of the S x S supersampled hard
    /// render: tf_mesh, opendr and nmr need cosine >= 0.95 (camera) or >= 0.05 (positions,
    /// per-vertex; measured 0.12-0.60) there, reported for the others.
    /// Cosine and relative L2 overall and per vertex category (silhouette, occlusion contour,
    /// interior), and the worst items with their screen positions. Exit code 1 on failure.
    #[command(verbatim_doc_comment)]
    Gradcheck {
        /// Scene JSON to check (with --wrt); without it, the registered cases are run.
        #[arg(conflicts_with_all = ["op", "all"], requires = "wrt")]
        scene: Option<PathBuf>,
        /// The scene input to check.
        #[arg(long, value_enum, requires = "scene")]
        wrt: Option<WrtArg>,
        /// Target image (PNG or .npy [H, W, 3] or [H, W, 4]); default: the scene's own image
        /// moved one pixel right and down.
        #[arg(long, requires = "scene")]
        target: Option<PathBuf>,
        /// Method instead of the scene's (hard, tf_mesh, opendr, nmr, softras, dibr, deodr,
        /// analytic, raytrace).
        #[arg(long, requires = "scene")]
        method: Option<String>,
        /// Reference samples per pixel along each axis (S x S supersampled hard render).
        #[arg(long, default_value_t = 8, requires = "scene")]
        samples: usize,
        /// At most this many items (vertices, texels) are checked; vertices are drawn evenly
        /// from the silhouette, occlusion-contour and interior ones.
        #[arg(long, default_value_t = 48, requires = "scene")]
        vertices: usize,
        /// Write disagreement.png (per-pixel heat map) and report.json into this folder.
        #[arg(long, requires = "scene")]
        out: Option<PathBuf>,
        /// Self-test of the checker: scale the input's gradient by this factor (a wrong
        /// backward), so the check must fail.
        #[arg(long, hide = true, requires = "scene")]
        self_test_backward_scale: Option<f64>,
        /// Only the registered cases matching NAME (full name, base name, category, or a part
        /// of the name).
        #[arg(long, conflicts_with = "all")]
        op: Option<String>,
        /// Every registered case (the default without --op or a scene).
        #[arg(long)]
        all: bool,
        /// Print JSON instead of a table (cases: a list of records; scene: one report).
        #[arg(long)]
        json: bool,
    },
    /// Fit a morphable model (the shipped ICT-FaceKit model by default) to a synthetic target
    /// (default) or to a photo with 2D landmarks; writes the fitted mesh (fit.obj, fit.mtl,
    /// albedo.png), landmarks.txt, detected_landmarks.txt, fit.png, overlay.png, compare.png,
    /// params.json, loss_curve.svg and report.json.
    FitFace {
        /// Target photo (PNG, JPEG, or .npy [H, W, C]; any size, gray or colour); without it a
        /// synthetic target is made.
        #[arg(long)]
        target: Option<PathBuf>,
        /// Landmarks of the photo: one `x y` line per landmark in the photo's pixels (468
        /// MediaPipe face-mesh points, 68 iBUG points, or one per model landmark / vertex).
        #[arg(long, requires = "target")]
        landmarks: Option<PathBuf>,
        /// Model: `ict` (default; the ICT-FaceKit model, models/data/ict), `mediapipe` (the
        /// small, fast MediaPipe-mesh model) or a model folder (models/README.md layout).
        #[arg(long)]
        model: Option<PathBuf>,
        /// Which face of the photo, counted from the largest (0); must be 0 with --landmarks.
        #[arg(long, default_value_t = 0)]
        face: usize,
        /// Output folder.
        #[arg(long, default_value = "fit-face-out")]
        out: PathBuf,
        /// Iterations in all: the first half fits landmarks only, the second all terms (a
        /// synthetic target's exact landmarks: at least 3000 landmark steps, weak shape priors).
        #[arg(long, default_value_t = 200)]
        iters: usize,
        /// Seed of the synthetic target.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Raster method (hard, softras, dibr).
        #[arg(long, default_value = "hard")]
        method: String,
        /// Size in pixels of the synthetic target (square); photos larger than this are
        /// resized (area filter, aspect kept) so that their longer side is this.
        #[arg(long, default_value_t = 256)]
        size: usize,
        /// Side of the albedo texture (albedo.png) fitted after the model fit, texels.
        #[arg(long, default_value_t = 512)]
        texture_size: usize,
        /// Iterations of the albedo-texture stage (0: the fitted model albedo, baked).
        #[arg(long, default_value_t = 30)]
        texture_iters: usize,
    },
    /// Detect faces in a photo and their 468 MediaPipe face-mesh landmarks; prints the faces
    /// and their scores, writes the landmark file (as `fit-face --landmarks` reads it) and an
    /// overlay.
    Landmarks {
        /// The photo (PNG, JPEG, or .npy [H, W, C]).
        photo: PathBuf,
        /// Write the landmarks: 468 `x y` lines, pixels, pixel centres at +0.5.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the photo with the boxes and the landmarks drawn as a PNG.
        #[arg(long)]
        overlay: Option<PathBuf>,
        /// Which face --out and --overlay use: 0 is the largest.
        #[arg(long, default_value_t = 0)]
        face: usize,
        /// Print the faces (score, presence, box, keypoints, landmarks x y z) as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Speed against error for every raster method (against a supersampled reference image
    /// and its finite-difference pose gradient), and scaling in faces, pixels and threads:
    /// a Markdown table, a JSON list of records, SVG charts.
    Bench {
        /// The quick configuration (under 2 minutes on 2 cores; 8x8 reference samples).
        #[arg(long)]
        quick: bool,
        /// A configuration of a few seconds (tests).
        #[arg(long, hide = true, conflicts_with = "quick")]
        tiny: bool,
        /// Write the records as a JSON list.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Write the charts (pareto.svg, faces.svg, pixels.svg, threads.svg) into this folder.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// Errors of the command line, each printed as one line.
#[derive(Debug, Error)]
pub enum CliError {
    /// A rendering error (scene, mesh, image, tape).
    #[error(transparent)]
    Render(#[from] render_ops::error::RenderError),
    /// A tape error.
    #[error(transparent)]
    Autodiff(#[from] autodiff::AutodiffError),
    /// Image and array files.
    #[error(transparent)]
    Io(#[from] render_ops::io::IoError),
    /// Scene files.
    #[error(transparent)]
    Scene(#[from] render_ops::scene::SceneError),
    /// The bench (boxed: its scene errors are large).
    #[error(transparent)]
    Bench(Box<crate::bench::BenchError>),
    /// Anything else, with its message.
    #[error("{0}")]
    Message(String),
}

impl From<crate::bench::BenchError> for CliError {
    fn from(e: crate::bench::BenchError) -> Self {
        CliError::Bench(Box::new(e))
    }
}

/// Runs a parsed command line.
pub fn run(cli: Cli) -> Result<ExitCode, CliError> {
    match cli.command {
        Command::Render {
            scene,
            out,
            npy,
            repeat,
        } => render::run(&scene, &out, npy.as_deref(), repeat),
        Command::Grad {
            scene,
            target,
            wrt,
            out,
            repeat,
        } => grad::run(&scene, &target, wrt, &out, repeat),
        Command::Gradcheck {
            scene: Some(scene),
            wrt,
            target,
            method,
            samples,
            vertices,
            out,
            self_test_backward_scale,
            json,
            ..
        } => gradcheck::run_scene(&gradcheck::SceneArgs {
            scene,
            wrt: wrt
                .ok_or_else(|| CliError::Message("gradcheck: a scene needs --wrt".into()))?
                .into(),
            target,
            method,
            samples,
            vertices,
            out,
            backward_scale: self_test_backward_scale,
            json,
        }),
        Command::Gradcheck { op, json, .. } => gradcheck::run(op.as_deref(), json),
        Command::FitFace {
            target,
            landmarks,
            model,
            face,
            out,
            iters,
            seed,
            method,
            size,
            texture_size,
            texture_iters,
        } => fit_face::run(&fit_face::Args {
            target,
            landmarks,
            model,
            face,
            out,
            iters,
            seed,
            method,
            size,
            texture_size,
            texture_iters,
        }),
        Command::Landmarks {
            photo,
            out,
            overlay,
            face,
            json,
        } => landmarks::run(&landmarks::Args {
            photo,
            out,
            overlay,
            face,
            json,
        }),
        Command::Bench {
            quick,
            tiny,
            json,
            out,
        } => bench::run(&bench::Args {
            quick,
            tiny,
            json,
            out,
        }),
    }
}
