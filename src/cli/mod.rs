//! The `tapestry` command line (see docs/CONVENTIONS.md): argument parsing and the commands.
//! Every command returns a typed error that `main` prints as one line on stderr.

mod bench;
mod fit_face;
mod grad;
mod gradcheck;
mod render;

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
    },
    /// Run the finite-difference gradient checker over the built-in and rendering ops.
    Gradcheck {
        /// Only the cases whose op name matches.
        #[arg(long, conflicts_with = "all")]
        op: Option<String>,
        /// Every case (the default when --op is not given).
        #[arg(long)]
        all: bool,
        /// Print a JSON list of records instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Fit a morphable model (the shipped face model by default) to a synthetic target
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
        /// Model folder (models/README.md layout); default: the shipped face model.
        #[arg(long)]
        model: Option<PathBuf>,
        /// Which face of the photo, counted from the largest (0); must be 0 with --landmarks.
        #[arg(long, default_value_t = 0)]
        face: usize,
        /// Output folder.
        #[arg(long, default_value = "fit-face-out")]
        out: PathBuf,
        /// Iterations in all: the first half fits landmarks only, the second all terms.
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
        Command::Render { scene, out, npy } => render::run(&scene, &out, npy.as_deref()),
        Command::Grad {
            scene,
            target,
            wrt,
            out,
        } => grad::run(&scene, &target, wrt, &out),
        Command::Gradcheck { op, all: _, json } => gradcheck::run(op.as_deref(), json),
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
