//! `--repeat N` of `render` and `grad`: the in-process time of the command's work (no start-up,
//! scene parsing or file output), for side-by-side timings with in-process peers
//! (`scripts/compare_raytrace_mitsuba.py`).

use std::time::Instant;

use super::CliError;

/// User + system CPU seconds of this process so far (`/proc/self/stat` fields 14 and 15, in
/// clock ticks of 1/100 s, the Linux default `USER_HZ`), if readable.
fn process_cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name (field 2) is parenthesised and may hold spaces: split after it.
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let (u, k): (u64, u64) = (f.get(11)?.parse().ok()?, f.get(12)?.parse().ok()?);
    Some((u + k) as f64 / 100.0)
}

/// Runs `work` once for the command's output; with `repeat > 0`, runs it `repeat` more times
/// (results dropped) and prints one JSON line to stderr: the wall time of each repetition
/// (min, median, ms) and the process CPU time per repetition (ms, all threads; `null` where
/// `/proc` is not readable).
pub fn repeated<R>(
    repeat: usize,
    mut work: impl FnMut() -> Result<R, CliError>,
) -> Result<R, CliError> {
    let out = work()?;
    if repeat == 0 {
        return Ok(out);
    }
    let cpu0 = process_cpu_seconds();
    let mut wall = Vec::with_capacity(repeat);
    for _ in 0..repeat {
        let t0 = Instant::now();
        std::hint::black_box(work()?);
        wall.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let cpu = cpu0
        .zip(process_cpu_seconds())
        .map(|(a, b)| (b - a) * 1e3 / repeat as f64);
    wall.sort_by(f64::total_cmp);
    let line = serde_json::json!({
        "repeat": repeat,
        "wall_ms_min": wall[0],
        "wall_ms_median": wall[repeat / 2],
        "cpu_ms_mean": cpu,
    });
    eprintln!("{line}");
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repeats_the_work_and_returns_the_first_result() {
        let mut calls = 0;
        let r = repeated(3, || {
            calls += 1;
            Ok(calls)
        })
        .unwrap();
        assert_eq!((r, calls), (1, 4));
        assert!(process_cpu_seconds().is_some_and(|c| c >= 0.0));
        let e = repeated(2, || -> Result<(), CliError> {
            Err(CliError::Message("x".into()))
        });
        assert!(e.is_err());
    }
}
