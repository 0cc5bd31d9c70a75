//! Peak memory and per-frame time of one soft-rasterizer configuration, forward + backward, on
//! the bench scene (`render-ops/benches/soft.rs`: the peers' icosphere and camera, f32,
//! per-vertex colours, RGBA, gradient of `sum((image - 0.25)^2)` (fused, shared target) w.r.t.
//! positions and colours; each frame under `ActiveWait`, as the bench's `frame_in`).
//! One configuration per process, so the peak resident set (`VmHWM` of `/proc/self/status`)
//! belongs to it alone. CPU time (`/proc/self/stat`) is printed beside wall time because on a
//! shared machine wall time is inflated by other processes' load while CPU time mostly is not.
//!
//! ```text
//! cargo run --release -p tapestry-render-ops --example soft_peak_memory -- \
//!     [--subdiv 6] [--size 512] [--sigma 1e-4] [--method softras|dibr] [--iters 3] [--threads 2]
//! ```

#[path = "../benches/common/mod.rs"]
mod common;

use std::sync::Arc;
use std::time::Instant;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use common::{frame_in, peer_scene, peers_view_proj, pool, PeerScene};
use render_ops::soft::{dibr, softras, DibrSettings, SoftSettings};
use render_ops::transform::to_clip;

/// A field of `/proc/self/status` in kB (`VmHWM`: peak resident set), if readable.
fn status_kb(key: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// User + system CPU seconds of this process so far (`/proc/self/stat` fields 14 and 15, in
/// clock ticks of 1/100 s, the Linux default `USER_HZ`), if readable.
fn cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The command name (field 2) is parenthesised and may hold spaces: split after it.
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let (u, k): (u64, u64) = (f.get(11)?.parse().ok()?, f.get(12)?.parse().ok()?);
    Some((u + k) as f64 / 100.0)
}

fn main() {
    let mut subdiv = 6u32;
    let mut size = 512usize;
    let mut sigma = 1e-4f64;
    let mut method = String::from("softras");
    let mut iters = 3usize;
    let mut threads = 2usize;
    let args: Vec<String> = std::env::args().skip(1).collect();
    for pair in args.chunks(2) {
        let val = pair
            .get(1)
            .unwrap_or_else(|| panic!("{} needs a value", pair[0]));
        match pair[0].as_str() {
            "--subdiv" => subdiv = val.parse().expect("--subdiv N"),
            "--size" => size = val.parse().expect("--size N"),
            "--sigma" => sigma = val.parse().expect("--sigma X"),
            "--method" => method = val.clone(),
            "--iters" => iters = val.parse().expect("--iters N"),
            "--threads" => threads = val.parse().expect("--threads N"),
            other => panic!("unknown option {other}"),
        }
    }
    assert!(iters > 0, "--iters must be at least 1");
    let pool = pool(threads);
    let PeerScene { pos, col, faces } = peer_scene(subdiv);
    let nv = pos.shape()[0];
    let view_proj = peers_view_proj();
    let target = Arc::new(ArrayD::from_elem(IxDyn(&[size, size, 4]), 0.25f32));
    let rss_before = status_kb("VmHWM:").unwrap_or(0);

    let mut wall = Vec::with_capacity(iters);
    let cpu0 = cpu_seconds();
    for _ in 0..iters {
        let t0 = Instant::now();
        let grad_len = frame_in(&pool, || {
            let tape = Tape::<f32>::new();
            let p = tape.var(pos.clone(), true);
            let c = tape.var(col.clone(), true);
            let clip = to_clip(p, &view_proj);
            let img = match method.as_str() {
                "softras" => {
                    let mut s = SoftSettings::new(size, size, 1.0, 100.0);
                    s.sigma = sigma;
                    s.gamma = 1e-4;
                    softras(clip, c, faces.clone(), &s).expect("softras")
                }
                "dibr" => {
                    dibr(clip, c, faces.clone(), &DibrSettings::new(size, size)).expect("dibr")
                }
                other => panic!("unknown method {other} (softras | dibr)"),
            };
            let loss = img.sum_squared_diff(tape.var_shared(target.clone(), false));
            let grads = tape.backward(loss).expect("backward");
            let g = grads.get(p).expect("position gradient");
            assert!(g.iter().all(|v| v.is_finite()), "non-finite gradient");
            g.len()
        });
        assert_eq!(grad_len, nv * 3);
        wall.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let cpu = match (cpu0, cpu_seconds()) {
        (Some(a), Some(b)) => format!("{:.0} ms", (b - a) * 1e3 / iters as f64),
        _ => "n/a".into(),
    };
    wall.sort_by(f64::total_cmp);
    let peak =
        status_kb("VmHWM:").map_or("n/a".into(), |k| format!("{:.1} MiB", k as f64 / 1024.0));
    let sigma = if method == "softras" {
        format!(", sigma {sigma:e}")
    } else {
        String::new()
    };
    println!(
        "{method} forward+backward, {} faces, {size}x{size}{sigma}, {threads} threads, \
         {iters} frames: wall min {:.0} ms / median {:.0} ms, CPU {cpu} per frame; \
         peak RSS {peak} ({:.1} MiB before the first frame)",
        faces.len(),
        wall[0],
        wall[wall.len() / 2],
        rss_before as f64 / 1024.0,
    );
}
