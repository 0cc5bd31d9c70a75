//! The `tapestry` command line (see CONVENTIONS.md): argument parsing and the commands.
//! Every command returns a typed error that `main` prints as one line on stderr.

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
}

/// The commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Render a scene JSON to a PNG (RGB over the background) and optionally a .npy ([H, W, 4] RGBA).
    Render {
        /// Scene JSON (CONVENTIONS.md).
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
    /// Anything else, with its message.
    #[error("{0}")]
    Message(String),
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
    }
}
