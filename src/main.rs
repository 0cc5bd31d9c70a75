//! The `tapestry` binary: parses the command line and prints errors as one line on stderr.

use std::process::ExitCode;

use clap::Parser;

/// Counts allocated bytes for the peak-memory column of `tapestry bench`.
#[global_allocator]
static ALLOC: tapestry::bench::alloc::CountingAlloc = tapestry::bench::alloc::CountingAlloc;

fn main() -> ExitCode {
    let cli = tapestry::cli::Cli::parse();
    match tapestry::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("tapestry: error: {e}");
            ExitCode::from(2)
        }
    }
}
