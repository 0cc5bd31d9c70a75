//! `tapestry gradcheck`: the gradient checker over every built-in op (a table or JSON).

use std::process::ExitCode;

use autodiff::suite::{render_table, run_all};

use super::CliError;

/// Runs the suite (filtered by `op`), prints it, and fails when any case fails.
pub fn run(op: Option<&str>, json: bool) -> Result<ExitCode, CliError> {
    let results = run_all(op);
    if results.is_empty() {
        return Err(CliError::Message(format!(
            "gradcheck: no op matches '{}'",
            op.unwrap_or_default()
        )));
    }
    if json {
        let recs: Vec<serde_json::Value> = results
            .iter()
            .map(|r| {
                serde_json::json!({
                    "op": r.op,
                    "shapes": r.shapes,
                    "max_abs_err": r.max_abs_err,
                    "max_rel_err": r.max_rel_err,
                    "f32_rel": r.f32_rel,
                    "passed": r.passed,
                    "error": r.error,
                })
            })
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&recs).map_err(|e| CliError::Message(e.to_string()))?
        );
    } else {
        print!("{}", render_table(&results));
        let failed = results.iter().filter(|r| !r.passed).count();
        println!("{} passed, {} failed", results.len() - failed, failed);
    }
    Ok(if results.iter().all(|r| r.passed) {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
