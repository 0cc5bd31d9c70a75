//! `tapestry bench [--quick] [--json OUT.json] [--out DIR]`: speed against error for every
//! raster method, and scaling in faces, pixels and threads ([`crate::bench`]): a Markdown
//! table on stdout, the records as a JSON list, SVG charts.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use crate::bench::{self, BenchConfig};

use super::CliError;

/// Arguments of `bench`.
#[derive(Debug, Clone)]
pub struct Args {
    /// The quick configuration.
    pub quick: bool,
    /// The tiny (test) configuration.
    pub tiny: bool,
    /// JSON output.
    pub json: Option<PathBuf>,
    /// Chart folder.
    pub out: Option<PathBuf>,
}

/// Runs `bench`.
pub fn run(args: &Args) -> Result<ExitCode, CliError> {
    let config = if args.tiny {
        BenchConfig::tiny()
    } else if args.quick {
        BenchConfig::quick()
    } else {
        BenchConfig::full()
    };
    let show = std::io::stderr().is_terminal();
    let mut progress = |line: &str| {
        if show {
            let mut e = std::io::stderr().lock();
            let _ = write!(e, "\r\x1b[2K{line}");
            let _ = e.flush();
        }
    };
    let report = bench::run(&config, &mut progress)?;
    if show {
        eprintln!();
    }
    print!("{}", bench::markdown(&report, &config));
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report.records)
            .map_err(|e| CliError::Message(format!("JSON: {e}")))?;
        std::fs::write(path, text + "\n")
            .map_err(|e| CliError::Message(format!("{}: cannot write: {e}", path.display())))?;
    }
    if let Some(dir) = &args.out {
        for p in bench::plot::write_charts(&report, dir)? {
            println!("chart: {}", p.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}
