//! The charts of `tapestry bench` (SVG, plotters): time against gradient error per method
//! (the Pareto chart), time against faces, time against pixels, speed-up against threads.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use plotters::prelude::*;

use super::{BenchError, Record, Report};

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

fn color_of(method: &str) -> RGBColor {
    let i = render_ops::scene::Method::ALL
        .iter()
        .position(|m| m.name() == method)
        .unwrap_or(0);
    PALETTE[i % PALETTE.len()]
}

fn err(e: impl std::fmt::Display) -> BenchError {
    BenchError::Message(format!("plot: {e}"))
}

/// Log-axis range covering `v` with a margin (positive values only).
fn log_range(v: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = v
        .filter(|x| x.is_finite() && *x > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(a, b), x| (a.min(x), b.max(x)));
    if !lo.is_finite() {
        return 1e-3..1.0;
    }
    (lo / 1.5)..(hi * 1.5)
}

type Series = BTreeMap<String, Vec<(f64, f64)>>;

fn line_chart(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &Series,
    log_x: bool,
) -> Result<(), BenchError> {
    let root = SVGBackend::new(path, (720, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let xs = series.values().flatten().map(|p| p.0);
    let ys = series.values().flatten().map(|p| p.1);
    let yr = log_range(ys);
    let mut builder = ChartBuilder::on(&root);
    builder
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60);
    macro_rules! draw {
        ($chart:expr) => {{
            let mut chart = $chart;
            chart
                .configure_mesh()
                .x_desc(x_desc)
                .y_desc(y_desc)
                .draw()
                .map_err(err)?;
            for (name, pts) in series {
                let method = name.split(' ').next().unwrap_or("");
                let c = color_of(method);
                let mut pts = pts.clone();
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                chart
                    .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
                    .map_err(err)?
                    .label(name.clone())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], c));
                chart
                    .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
                    .map_err(err)?;
            }
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .position(SeriesLabelPosition::UpperLeft)
                .draw()
                .map_err(err)?;
        }};
    }
    if log_x {
        let xr = log_range(xs);
        draw!(builder
            .build_cartesian_2d(xr.log_scale(), yr.log_scale())
            .map_err(err)?);
    } else {
        let (lo, hi) = xs.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(x), b.max(x))
        });
        let (lo, hi) = if lo.is_finite() {
            (lo - 0.25, hi + 0.25)
        } else {
            (0.0, 1.0)
        };
        draw!(builder
            .build_cartesian_2d(lo..hi, yr.log_scale())
            .map_err(err)?);
    }
    root.present().map_err(err)?;
    Ok(())
}

fn pareto(path: &Path, records: &[&Record]) -> Result<(), BenchError> {
    let root = SVGBackend::new(path, (720, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(err)?;
    let xr = log_range(records.iter().map(|r| r.forward_backward_s));
    let yr = log_range(records.iter().filter_map(|r| r.grad_rel_l2));
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "forward+backward time against gradient error (all scenes)",
            ("sans-serif", 18),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(xr.log_scale(), yr.log_scale())
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("forward+backward time (s)")
        .y_desc("gradient relative L2 error vs reference")
        .draw()
        .map_err(err)?;
    let mut by_method: BTreeMap<&str, Vec<(f64, f64)>> = BTreeMap::new();
    for r in records {
        if let Some(e) = r.grad_rel_l2.filter(|e| e.is_finite() && *e > 0.0) {
            by_method
                .entry(r.method.as_str())
                .or_default()
                .push((r.forward_backward_s, e));
        }
    }
    for (m, pts) in &by_method {
        let c = color_of(m);
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 4, c.filled())))
            .map_err(err)?
            .label(*m)
            .legend(move |(x, y)| Circle::new((x + 8, y), 4, c.filled()));
    }
    // The Pareto front over all records: no other record is both faster and more accurate.
    let mut all: Vec<(f64, f64)> = by_method.values().flatten().copied().collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut front = Vec::new();
    let mut best = f64::INFINITY;
    for p in all {
        if p.1 < best {
            best = p.1;
            front.push(p);
        }
    }
    chart
        .draw_series(LineSeries::new(front, BLACK.mix(0.5).stroke_width(1)))
        .map_err(err)?
        .label("Pareto front")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK.mix(0.5)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperRight)
        .draw()
        .map_err(err)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Writes `pareto.svg`, `faces.svg`, `pixels.svg` and `threads.svg` into `dir` and returns
/// their paths.
pub fn write_charts(report: &Report, dir: &Path) -> Result<Vec<PathBuf>, BenchError> {
    std::fs::create_dir_all(dir).map_err(|e| {
        BenchError::Message(format!("{}: cannot create folder: {e}", dir.display()))
    })?;
    let of =
        |kind: &str| -> Vec<&Record> { report.records.iter().filter(|r| r.kind == kind).collect() };
    let series = |kind: &str, x: &dyn Fn(&Record) -> f64| -> Series {
        let mut s = Series::new();
        for r in of(kind) {
            s.entry(r.method.clone())
                .or_default()
                .push((x(r), r.forward_backward_s));
        }
        s
    };
    let mut out = Vec::new();
    let p = dir.join("pareto.svg");
    pareto(&p, &of("accuracy"))?;
    out.push(p);
    let p = dir.join("faces.svg");
    line_chart(
        &p,
        "forward+backward time against faces (icosphere, 1 thread)",
        "faces",
        "time (s)",
        &series("faces", &|r| r.faces as f64),
        true,
    )?;
    out.push(p);
    let p = dir.join("pixels.svg");
    line_chart(
        &p,
        "forward+backward time against pixels (ico5k, 1 thread)",
        "pixels",
        "time (s)",
        &series("pixels", &|r| (r.width * r.height) as f64),
        true,
    )?;
    out.push(p);
    // Speed-up: time at 1 thread over time at n threads.
    let mut speed = Series::new();
    for (m, pts) in series("threads", &|r| r.threads as f64) {
        if let Some(&(_, t1)) = pts.iter().find(|p| p.0 == 1.0) {
            speed.insert(m, pts.iter().map(|&(n, t)| (n, t1 / t)).collect());
        }
    }
    let p = dir.join("threads.svg");
    line_chart(
        &p,
        "forward+backward speed-up against threads (ico5k)",
        "threads",
        "speed-up over 1 thread",
        &speed,
        false,
    )?;
    out.push(p);
    Ok(out)
}
