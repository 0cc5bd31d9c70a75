//! Large inputs: a 2M-face mesh rasterizes at 2048 x 2048 with the hard method within bounded
//! memory (peak RSS read from /proc/self/status, VmHWM), forward and backward through the tape.
//! About 3 s in the test profile; `--nocapture` prints the timings and peak memory:
//! `cargo test -p tapestry-render-ops --test integration large:: -- --nocapture` (add `--release` for the
//! optimised timings).

use std::sync::Arc;
use std::time::Instant;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use render_ops::blend::blend_hard;
use render_ops::interpolate::interpolate;
use render_ops::raster::{rasterize_fragments as raster_raw, RasterSettings};
use render_ops::rasterize::rasterize;

/// Peak resident set size of this process so far, in MiB (VmHWM), where /proc has it.
fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// An `n x n` grid of quads (two triangles each) filling the NDC square, as clip coordinates
/// with a gentle depth slope: `(n + 1)^2` vertices, `2 n^2` faces, front-facing.
fn grid(n: u32) -> (Vec<[f64; 4]>, Vec<[u32; 3]>) {
    let m = n + 1;
    let c = |i: u32| 2.0 * i as f64 / n as f64 - 1.0;
    let mut clip = Vec::with_capacity((m * m) as usize);
    for j in 0..m {
        for i in 0..m {
            clip.push([c(i), c(j), 0.1 * c(i) - 0.2 * c(j), 1.0]);
        }
    }
    let mut faces = Vec::with_capacity((2 * n * n) as usize);
    for j in 0..n {
        for i in 0..n {
            let v00 = j * m + i;
            let (v10, v01) = (v00 + 1, v00 + m);
            faces.push([v00, v10, v01 + 1]);
            faces.push([v00, v01 + 1, v01]);
        }
    }
    (clip, faces)
}

#[test]
fn two_million_faces_at_2048_squared_hard() {
    let n = 1000; // 2,000,000 faces, 1,002,001 vertices
    let (clip, faces) = grid(n);
    assert_eq!(faces.len(), 2_000_000);
    let settings = RasterSettings::new(2048, 2048);
    let base = peak_rss_mib();

    // The rasterizer alone.
    let t0 = Instant::now();
    let fr = raster_raw(&clip, &faces, &settings).unwrap();
    let raster_s = t0.elapsed().as_secs_f64();
    // The grid covers the screen edge to edge and is watertight: one fragment per pixel.
    assert_eq!(fr.len(), 2048 * 2048);
    assert!(fr.offsets.windows(2).all(|w| w[1] - w[0] == 1));
    let after_raster = peak_rss_mib();
    drop(fr);

    // The same through the tape: rasterize, interpolate colours, blend, backward to the
    // positions and colours.
    let t0 = Instant::now();
    let tape = Tape::<f64>::new();
    let nv = clip.len();
    let cv = tape.leaf(
        ArrayD::from_shape_vec(IxDyn(&[nv, 4]), clip.iter().flatten().copied().collect()).unwrap(),
    );
    let colors = tape.leaf(ArrayD::from_shape_fn(IxDyn(&[nv, 3]), |i| {
        ((i[0] + i[1]) % 5) as f64 / 4.0
    }));
    let faces = Arc::new(faces);
    let r = rasterize(cv, faces, &settings).unwrap();
    let cols = interpolate(colors, &r).unwrap();
    let img = blend_hard(cols, &r.fragments, &[0.0, 0.0, 0.0]).unwrap();
    let v = img.value().unwrap();
    assert_eq!(v.shape(), &[2048, 2048, 4]);
    assert!(v.iter().all(|x| x.is_finite()));
    let forward_s = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let g = tape.backward(img.sum()).unwrap();
    let gc = g.get(colors).unwrap();
    // Each pixel's barycentrics sum to one: the colour gradient sums to the pixel count per
    // channel.
    let total: f64 = gc.iter().sum();
    assert!(
        (total - 3.0 * 2048.0 * 2048.0).abs() < 1e-3 * total,
        "{total}"
    );
    let backward_s = t1.elapsed().as_secs_f64();
    let after_tape = peak_rss_mib();

    eprintln!(
        "2M faces at 2048x2048 (hard): rasterize {raster_s:.2} s; tape forward (rasterize + \
         interpolate + blend) {forward_s:.2} s, backward {backward_s:.2} s; peak RSS MiB: \
         before {base:?}, after rasterize {after_raster:?}, after tape {after_tape:?}"
    );
    if let Some(peak) = after_tape {
        // Inputs (~100 MB), fragments (4M x 92 B), tape values and gradients: well under 4 GiB.
        assert!(peak < 4096.0, "peak RSS {peak} MiB");
    }
}
