//! The scene check of `tapestry gradcheck SCENE.json --wrt INPUT`: the gradient of
//! `L = sum (render - target)^2` through a scene's pipeline ([`Scene::render`], its method)
//! with respect to one scene input, against finite differences.
//!
//! - **Own check** (every input): [`super::check_image_gradient`] against `f64` central
//!   differences of the method's own image, step [`SceneCheckOptions::eps`]. The image is
//!   smooth in colours, texels and light parameters, so agreement is exact up to `rtol`/`atol`
//!   for every method. For positions and camera the own image of `hard`, `deodr`, `softras`
//!   and `dibr` is differentiated exactly by their backward (hard: interior barycentrics, which
//!   is the derivative of its piecewise-smooth image wherever no pixel centre sits on an edge;
//!   deodr: the overdrawn image; soft methods: smooth images), so the own check is exact for
//!   them too; `tf_mesh`, `opendr` and `nmr` add approximate boundary terms that their own
//!   image does not have: for them it is reported, not required.
//! - **Reference check** (positions and camera): central differences of the area-integrated
//!   image of docs/CONVENTIONS.md, the hard render at `S W x S H` averaged over `S x S` blocks
//!   ([`supersampled_scene`], [`box_downsample`]), with a step of
//!   [`SceneCheckOptions::step_px`] pixels (per vertex: that many pixels of screen motion at
//!   the vertex; camera rows: that many pixels at the look-at distance), so that the image
//!   moves by whole sub-samples. Reported as cosine and relative L2 over all checked vertices
//!   and per vertex category; the methods with approximate boundary gradients must reach the
//!   cosine floor of [`Thresholds::for_method`].
//! - **Vertex categories** ([`vertex_categories`], from the hard render at `S W x S H`):
//!   *hidden*: no face of the vertex covers a sample; *silhouette*: a visible vertex of an
//!   edge between a front- and a back-facing face (screen-space winding) or of a boundary edge
//!   (one face); *occlusion contour*: any other visible vertex of a face that covers a sample
//!   next to (4-neighbour) a sample of a face sharing no vertex with it, that face being
//!   behind (a depth discontinuity with another surface behind); *interior*: the rest.
//! - **Items checked**: at most [`SceneCheckOptions::items`]. Vertex inputs (positions,
//!   colours) take a third from each visible category (seeded), the rest from the other
//!   visible vertices; hidden vertices are not checked. Texture: texels at random. Camera and
//!   lights: every row.
//! - **Target**: the given image (3 channels: compared with RGB; 4: RGBA), else
//!   [`default_target`], the scene's own image moved by one pixel right and down.

use std::path::PathBuf;

use autodiff::rng::Rng;
use autodiff::{Tape, Tensor, Var};
use ndarray::{Array2, Array3, ArrayD, IxDyn};
use serde_json::{json, Value};

use super::{
    analytic_gradient, cosine_rel_l2, disagreement_map, eval_image, fd_rows, item_layout,
    item_values, pipeline, scale_backward, select_items, sq_loss, CheckOptions, CheckReport, Items,
};
use crate::error::RenderError;
pub use crate::pipeline::SceneInput;
use crate::pipeline::Wrt;
use crate::raster::{rasterize_fragments, RasterSettings};
use crate::scene::{Method, Raster, Scene};

/// Where a vertex sits in the image (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum VertexCategory {
    /// On a silhouette or boundary edge, visible.
    Silhouette,
    /// Beside a depth discontinuity with another surface behind, visible.
    OcclusionContour,
    /// Visible, neither of the above.
    Interior,
    /// Covers no sample of the hard render.
    Hidden,
}

impl VertexCategory {
    /// The three visible categories, in report order.
    pub const VISIBLE: [VertexCategory; 3] = [
        VertexCategory::Silhouette,
        VertexCategory::OcclusionContour,
        VertexCategory::Interior,
    ];

    /// Name in reports.
    pub fn name(self) -> &'static str {
        match self {
            VertexCategory::Silhouette => "silhouette",
            VertexCategory::OcclusionContour => "occlusion_contour",
            VertexCategory::Interior => "interior",
            VertexCategory::Hidden => "hidden",
        }
    }
}

/// The scene at `S W x S H` with method `hard` (culling and interpolation mode kept), whose
/// `S x S` block averages ([`box_downsample`]) are the reference image of docs/CONVENTIONS.md.
pub fn supersampled_scene(scene: &Scene<f64>, samples: usize) -> Result<Scene<f64>, RenderError> {
    let s = samples.max(1);
    let mut big = scene.clone();
    big.desc.image.width = scene.desc.image.width * s as u32;
    big.desc.image.height = scene.desc.image.height * s as u32;
    let mut r = Raster::with_method(Method::Hard);
    r.cull_backfaces = scene.desc.raster.cull_backfaces;
    r.perspective_correct = scene.desc.raster.perspective_correct;
    big.desc.raster = r;
    big.camera = big.desc.camera()?;
    Ok(big)
}

/// Averages of the `S x S` blocks of an image `[S H, S W, C]`: `[H, W, C]`.
pub fn box_downsample(img: &Array3<f64>, samples: usize) -> Array3<f64> {
    let s = samples.max(1);
    let (bh, bw, c) = img.dim();
    let (h, w) = (bh / s, bw / s);
    let inv = 1.0 / (s * s) as f64;
    Array3::from_shape_fn((h, w, c), |(r, col, ch)| {
        let mut acc = 0.0;
        for i in 0..s {
            for j in 0..s {
                acc += img[[r * s + i, col * s + j, ch]];
            }
        }
        acc * inv
    })
}

/// The category of every mesh vertex (module docs), from the hard render of `scene`'s mesh
/// at `S W x S H`.
pub fn vertex_categories(
    scene: &Scene<f64>,
    samples: usize,
) -> Result<Vec<VertexCategory>, RenderError> {
    let s = samples.max(1);
    let (w, h) = (
        scene.desc.image.width as usize * s,
        scene.desc.image.height as usize * s,
    );
    let pos = &scene.mesh.positions;
    let faces = &scene.mesh.faces;
    let clip: Vec<[f64; 4]> = pos.iter().map(|&p| scene.camera.project(p)).collect();
    let mut settings = RasterSettings::new(w, h);
    settings.cull_backfaces = scene.desc.raster.cull_backfaces;
    let frags = rasterize_fragments(&clip, faces, &settings)?;
    let top: Vec<Option<(u32, f64)>> = (0..w * h)
        .map(|p| frags.nearest(p).map(|f| (f.face, f.depth)))
        .collect();
    let nv = pos.len();
    let mut visible = vec![false; nv];
    for &(f, _) in top.iter().flatten() {
        for &v in &faces[f as usize] {
            visible[v as usize] = true;
        }
    }
    // Silhouette edges: winding changes across the edge, or only one face has it.
    let winding: Vec<i8> = faces
        .iter()
        .map(|f| {
            let n: Vec<Option<[f64; 2]>> = f
                .iter()
                .map(|&v| {
                    let c = clip[v as usize];
                    (c[3] > 0.0).then(|| [c[0] / c[3], c[1] / c[3]])
                })
                .collect();
            match (n[0], n[1], n[2]) {
                (Some(a), Some(b), Some(c)) => {
                    let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
                    if area > 0.0 {
                        1
                    } else {
                        -1
                    }
                }
                _ => 0,
            }
        })
        .collect();
    let mut edges: std::collections::HashMap<(u32, u32), Vec<usize>> =
        std::collections::HashMap::new();
    for (fi, f) in faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            edges.entry((a.min(b), a.max(b))).or_default().push(fi);
        }
    }
    let mut silhouette = vec![false; nv];
    for (&(a, b), fs) in &edges {
        let mixed = fs.iter().any(|&f| winding[f] != winding[fs[0]]);
        if fs.len() == 1 || mixed {
            silhouette[a as usize] = true;
            silhouette[b as usize] = true;
        }
    }
    // Occlusion contours: neighbouring samples of faces sharing no vertex; the nearer face's
    // vertices.
    let mut contour = vec![false; nv];
    let share = |f: u32, g: u32| {
        let (a, b) = (faces[f as usize], faces[g as usize]);
        a.iter().any(|v| b.contains(v))
    };
    for r in 0..h {
        for c in 0..w {
            let Some((f, df)) = top[r * w + c] else {
                continue;
            };
            for (rr, cc) in [(r + 1, c), (r, c + 1)] {
                if rr >= h || cc >= w {
                    continue;
                }
                let Some((g, dg)) = top[rr * w + cc] else {
                    continue;
                };
                if f == g || share(f, g) {
                    continue;
                }
                let front = if df <= dg { f } else { g };
                for &v in &faces[front as usize] {
                    contour[v as usize] = true;
                }
            }
        }
    }
    Ok((0..nv)
        .map(|v| {
            if !visible[v] {
                VertexCategory::Hidden
            } else if silhouette[v] {
                VertexCategory::Silhouette
            } else if contour[v] {
                VertexCategory::OcclusionContour
            } else {
                VertexCategory::Interior
            }
        })
        .collect())
}

/// Pass criteria of a scene check.
#[derive(Clone, Debug, PartialEq)]
pub struct Thresholds {
    /// Whether the own check (analytic against differences of the method's own image) must
    /// pass within `rtol`/`atol`.
    pub own_exact: bool,
    /// Relative tolerance of the own check.
    pub rtol: f64,
    /// Absolute tolerance of the own check (times `1 + max |numeric|`).
    pub atol: f64,
    /// Smallest cosine with the reference gradient over all checked items (positions and
    /// camera); `None`: reported only.
    pub min_reference_cosine: Option<f64>,
}

impl Thresholds {
    /// The documented thresholds (docs/CONVENTIONS.md, `tapestry gradcheck --help`):
    /// - colours, texture, lights, every method: own check exact, `rtol 1e-4`, `atol 1e-6`;
    /// - positions and camera: `hard`, `deodr`, `softras`, `dibr`: own check exact,
    ///   `rtol 1e-3`, `atol 1e-5` (reference reported); `tf_mesh`, `opendr`, `nmr`: cosine
    ///   with the reference gradient at least 0.95 (camera) or 0.05 (positions), own check
    ///   reported.
    ///
    /// The floors come from measurement with margin: on the test scenes (32 x 32, an
    /// icosphere and two overlapping ones, S = 4 and 8) the camera cosines of the three were
    /// 0.988-0.998, and the per-vertex position cosines 0.12-0.60 (tf_mesh lowest, on the
    /// occluding spheres): per vertex, the boundary gradient lands on other vertices than the
    /// area-integrated one puts it on (the bench's pose-level cosines are 0.9-0.99). The
    /// position floor therefore catches a gradient of the wrong sign or an unrelated one, not
    /// an inaccurate one.
    pub fn for_method(method: Method, input: SceneInput) -> Self {
        if !input.is_geometric() {
            return Thresholds {
                own_exact: true,
                rtol: 1e-4,
                atol: 1e-6,
                min_reference_cosine: None,
            };
        }
        let approx = matches!(method, Method::TfMesh | Method::OpenDr | Method::Nmr);
        let floor = if input == SceneInput::Camera {
            0.95
        } else {
            0.05
        };
        Thresholds {
            own_exact: !approx,
            rtol: 1e-3,
            atol: 1e-5,
            min_reference_cosine: approx.then_some(floor),
        }
    }
}

/// Settings of [`check_scene`].
#[derive(Clone, Debug, PartialEq)]
pub struct SceneCheckOptions {
    /// The input.
    pub input: SceneInput,
    /// Reference (and categorisation) samples per pixel along each axis (`S`, default 8).
    pub samples: usize,
    /// At most this many items are checked (default 48).
    pub items: usize,
    /// Step of the own check (input units, default 1e-6).
    pub eps: f64,
    /// Step of the reference check, in pixels of screen motion (default 0.75).
    pub step_px: f64,
    /// Seed of the item choice and of the heat map direction.
    pub seed: u64,
    /// Compute the per-pixel disagreement map (one backward per pixel).
    pub heatmap: bool,
    /// Self-test: puts [`super::ScaleBackward`] with this factor on the input, so that the
    /// analytic gradient is off by it and the check must fail.
    pub backward_scale: Option<f64>,
    /// Overrides the thresholds of [`Thresholds::for_method`].
    pub thresholds: Option<Thresholds>,
}

impl SceneCheckOptions {
    /// Defaults for `input`.
    pub fn new(input: SceneInput) -> Self {
        SceneCheckOptions {
            input,
            samples: 8,
            items: 48,
            eps: 1e-6,
            step_px: 0.75,
            seed: 0,
            heatmap: false,
            backward_scale: None,
            thresholds: None,
        }
    }
}

/// One checked item of a scene check.
#[derive(Clone, Debug, PartialEq)]
pub struct ItemRecord {
    /// Item index (vertex, texel row-major, camera row, light row).
    pub item: usize,
    /// Vertex category (per-vertex inputs).
    pub category: Option<VertexCategory>,
    /// Screen position in pixels (per-vertex inputs; `None` behind the eye).
    pub pixel: Option<[f64; 2]>,
    /// Analytic gradient.
    pub analytic: Vec<f64>,
    /// Central differences of the method's own image.
    pub numeric: Vec<f64>,
    /// Central differences of the reference image (positions, camera).
    pub reference: Option<Vec<f64>>,
    /// The error that ranks it: `|analytic - numeric|`, or `|analytic - reference|` where the
    /// reference decides.
    pub error: f64,
    /// Within the own check's tolerance.
    pub own_passed: bool,
}

/// Cosine and relative L2 of one vertex category.
#[derive(Clone, Debug, PartialEq)]
pub struct CategoryStats {
    /// The category.
    pub category: VertexCategory,
    /// Checked vertices in it.
    pub count: usize,
    /// Against the own differences.
    pub cosine_own: f64,
    /// Against the own differences.
    pub rel_l2_own: f64,
    /// Against the reference differences (positions, camera).
    pub cosine_reference: Option<f64>,
    /// Against the reference differences.
    pub rel_l2_reference: Option<f64>,
}

/// The outcome of [`check_scene`].
#[derive(Clone, Debug)]
pub struct SceneCheck {
    /// The scene source.
    pub source: String,
    /// The input.
    pub input: SceneInput,
    /// The raster method.
    pub method: Method,
    /// Reference samples `S`.
    pub samples: usize,
    /// Criteria applied.
    pub thresholds: Thresholds,
    /// Analytic against the method's own differences.
    pub own: CheckReport,
    /// Analytic against the reference differences (positions, camera).
    pub reference: Option<CheckReport>,
    /// Per vertex category (per-vertex inputs), visible categories only.
    pub categories: Vec<CategoryStats>,
    /// Every checked item.
    pub items: Vec<ItemRecord>,
    /// Per-pixel disagreement and numeric contributions, when asked for.
    pub heatmap: Option<(Array2<f64>, Array2<f64>)>,
    /// Why it failed (empty when it passed).
    pub failures: Vec<String>,
}

impl SceneCheck {
    /// No failure.
    pub fn passed(&self) -> bool {
        self.failures.is_empty()
    }

    /// The `n` items with the largest ranking error, largest first.
    pub fn worst(&self, n: usize) -> Vec<&ItemRecord> {
        let mut v: Vec<&ItemRecord> = self.items.iter().collect();
        v.sort_by(|a, b| b.error.total_cmp(&a.error).then(a.item.cmp(&b.item)));
        v.truncate(n);
        v
    }

    /// The report as JSON (`--json`, `report.json`).
    pub fn to_json(&self, worst: usize) -> Value {
        let item = |r: &ItemRecord| {
            json!({
                "item": r.item,
                "category": r.category.map(VertexCategory::name),
                "pixel": r.pixel,
                "analytic": r.analytic,
                "numeric": r.numeric,
                "reference": r.reference,
                "error": finite_or_null(r.error),
                "own_passed": r.own_passed,
            })
        };
        let stats = |c: &CheckReport| {
            json!({
                "cosine": finite_or_null(c.cosine),
                "rel_l2": finite_or_null(c.rel_l2),
                "max_abs_err": finite_or_null(c.max_abs_err),
                "passed": c.passed,
            })
        };
        json!({
            "scene": self.source,
            "input": self.input.name(),
            "method": self.method.name(),
            "samples": self.samples,
            "passed": self.passed(),
            "failures": self.failures,
            "loss": self.own.loss,
            "thresholds": {
                "own_exact": self.thresholds.own_exact,
                "rtol": self.thresholds.rtol,
                "atol": self.thresholds.atol,
                "atol_abs": self.own.atol_abs,
                "min_reference_cosine": self.thresholds.min_reference_cosine,
            },
            "own": stats(&self.own),
            "reference": self.reference.as_ref().map(stats),
            "categories": self.categories.iter().map(|c| json!({
                "category": c.category.name(),
                "count": c.count,
                "cosine_own": finite_or_null(c.cosine_own),
                "rel_l2_own": finite_or_null(c.rel_l2_own),
                "cosine_reference": c.cosine_reference.and_then(finite_or_null),
                "rel_l2_reference": c.rel_l2_reference.and_then(finite_or_null),
            })).collect::<Vec<_>>(),
            "worst": self.worst(worst).into_iter().map(item).collect::<Vec<_>>(),
            "items": self.items.iter().map(item).collect::<Vec<_>>(),
        })
    }

    /// A text report: the verdict, the overall and per-category numbers, the worst items.
    pub fn render_text(&self, worst: usize) -> String {
        let mut out = format!(
            "gradcheck {} --wrt {} (method {}, {} items, loss {:.6e})\n",
            self.source,
            self.input.name(),
            self.method.name(),
            self.items.len(),
            self.own.loss
        );
        out.push_str(&format!(
            "  own finite differences:       cosine {:.6}  rel L2 {:.3e}  max abs err {:.3e}  {}\n",
            self.own.cosine,
            self.own.rel_l2,
            self.own.max_abs_err,
            match (self.own.passed, self.thresholds.own_exact) {
                (true, _) => "ok".to_string(),
                (false, true) => "FAIL".to_string(),
                (false, false) => "differs (approximate method: reported only)".to_string(),
            }
        ));
        if let Some(r) = &self.reference {
            out.push_str(&format!(
                "  reference ({s}x{s} supersampled): cosine {:.6}  rel L2 {:.3e}  {}\n",
                r.cosine,
                r.rel_l2,
                match self.thresholds.min_reference_cosine {
                    Some(c) if r.cosine >= c => format!("ok (>= {c})"),
                    Some(c) => format!("FAIL (< {c})"),
                    None => "reported only".into(),
                },
                s = self.samples,
            ));
        }
        if !self.categories.is_empty() {
            out.push_str(
                "  category           count  cosine own  rel L2 own  cosine ref  rel L2 ref\n",
            );
            for c in &self.categories {
                let opt = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.4}"));
                out.push_str(&format!(
                    "  {:<17}  {:>5}  {:>10.4}  {:>10.3e}  {:>10}  {:>10}\n",
                    c.category.name(),
                    c.count,
                    c.cosine_own,
                    c.rel_l2_own,
                    opt(c.cosine_reference),
                    opt(c.rel_l2_reference),
                ));
            }
        }
        out.push_str("  worst items:\n");
        for r in self.worst(worst) {
            let at = match (r.category, r.pixel) {
                (Some(c), Some(p)) => format!(" {} at pixel ({:.1}, {:.1})", c.name(), p[0], p[1]),
                (Some(c), None) => format!(" {}", c.name()),
                _ => String::new(),
            };
            let fmt = |v: &[f64]| {
                v.iter()
                    .map(|x| format!("{x:.4e}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            out.push_str(&format!(
                "    {} {}{}: analytic [{}] numeric [{}]{} error {:.3e}\n",
                item_noun(self.input),
                r.item,
                at,
                fmt(&r.analytic),
                fmt(&r.numeric),
                r.reference
                    .as_ref()
                    .map_or(String::new(), |v| format!(" reference [{}]", fmt(v))),
                r.error
            ));
        }
        if self.passed() {
            out.push_str("PASSED\n");
        } else {
            for f in &self.failures {
                out.push_str(&format!("FAILED: {f}\n"));
            }
        }
        out
    }
}

fn item_noun(input: SceneInput) -> &'static str {
    match input {
        SceneInput::Positions | SceneInput::Colors => "vertex",
        SceneInput::Texture => "texel",
        SceneInput::Camera => "camera row",
        SceneInput::Lights => "light row",
    }
}

fn finite_or_null(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// The value of a scene input.
pub fn input_value(scene: &Scene<f64>, input: SceneInput) -> Result<Tensor<f64>, RenderError> {
    let tape = Tape::new();
    let vars = scene.vars(&tape, input.wrt());
    let v = vars.input(input, &scene.source)?;
    let out = (*v.value()?).clone();
    Ok(out)
}

/// Renders `scene` with `x` as the value of `input` (through [`super::ScaleBackward`] when
/// `scale` is set), RGB only for a 3-channel target.
pub fn render_with<'t>(
    scene: &Scene<f64>,
    input: SceneInput,
    tape: &'t Tape<f64>,
    x: Var<'t, f64>,
    scale: Option<f64>,
    rgb_only: bool,
) -> Result<Var<'t, f64>, RenderError> {
    let mut vars = scene.vars(tape, Wrt::default());
    let x = match scale {
        Some(f) => scale_backward(x, f),
        None => x,
    };
    match input {
        SceneInput::Positions => vars.positions = x,
        SceneInput::Colors => vars.colors = x,
        SceneInput::Texture => vars.texture = Some(x),
        SceneInput::Camera => vars.camera = x,
        SceneInput::Lights => vars.lights = Some(x),
    }
    let img = scene.render(&vars)?;
    Ok(if rgb_only { img.slice(2, 0, 3) } else { img })
}

/// The default target: the scene's own image (RGBA `[H, W, 4]`) moved one pixel right and
/// one pixel down (the background, with alpha 0, shifted in), so that `dL/dI` is non-zero
/// along every edge and colour gradient, as for a small misalignment.
pub fn default_target(scene: &Scene<f64>) -> Result<Tensor<f64>, RenderError> {
    let tape = Tape::new();
    let vars = scene.vars(&tape, Wrt::default());
    let img = scene.render(&vars)?.value()?;
    let (h, w, c) = (img.shape()[0], img.shape()[1], img.shape()[2]);
    let bg = scene.desc.image.background;
    Ok(ArrayD::from_shape_fn(IxDyn(&[h, w, c]), |i| {
        let (r, col, ch) = (i[0], i[1], i[2]);
        if r >= 1 && col >= 1 {
            img[[r - 1, col - 1, ch]]
        } else if ch + 1 < c {
            bg.get(ch).copied().unwrap_or(0.0)
        } else {
            0.0
        }
    }))
}

/// World-space step that moves `p` by `px` pixels on screen (the largest motion along the
/// three axes), or `None` behind the eye.
fn pixel_step(scene: &Scene<f64>, p: [f64; 3], px: f64) -> Option<f64> {
    let (w, h) = (scene.desc.image.width, scene.desc.image.height);
    let a = scene.camera.project_pixel(p, w, h)?;
    let d = 1e-6;
    let mut most = 0.0f64;
    for k in 0..3 {
        let mut q = p;
        q[k] += d;
        let b = scene.camera.project_pixel(q, w, h)?;
        most = most.max(((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt() / d);
    }
    (most.is_finite() && most > 0.0).then(|| px / most)
}

/// Up to `n` vertices: a third from each visible category (seeded), the rest from the other
/// visible vertices; sorted.
fn stratified(cats: &[VertexCategory], n: usize, seed: u64) -> Vec<usize> {
    let mut rng = Rng::new(seed);
    let mut pools: Vec<Vec<usize>> = VertexCategory::VISIBLE
        .iter()
        .map(|&c| (0..cats.len()).filter(|&v| cats[v] == c).collect())
        .collect();
    for p in &mut pools {
        for i in (1..p.len()).rev() {
            p.swap(i, rng.below(i + 1));
        }
    }
    let share = n.div_ceil(3);
    let mut out: Vec<usize> = Vec::new();
    let mut rest: Vec<usize> = Vec::new();
    for p in &pools {
        let k = share.min(p.len());
        out.extend(&p[..k]);
        rest.extend(&p[k..]);
    }
    out.truncate(n);
    for i in (1..rest.len()).rev() {
        rest.swap(i, rng.below(i + 1));
    }
    let more = n.saturating_sub(out.len()).min(rest.len());
    out.extend(&rest[..more]);
    out.sort_unstable();
    out
}

/// Checks the gradient of `sum (render - target)^2` through `scene` with respect to
/// `opts.input` (module docs). `target`: `[H, W, 3]` or `[H, W, 4]`, else
/// [`default_target`].
pub fn check_scene(
    scene: &Scene<f64>,
    target: Option<&Tensor<f64>>,
    opts: &SceneCheckOptions,
) -> Result<SceneCheck, RenderError> {
    let input = opts.input;
    let (w, h) = (
        scene.desc.image.width as usize,
        scene.desc.image.height as usize,
    );
    let target = match target {
        Some(t) => {
            let s = t.shape();
            if s.len() != 3 || s[0] != h || s[1] != w || !(s[2] == 3 || s[2] == 4) {
                return Err(RenderError::Unsupported(format!(
                    "target shape {s:?} does not match the scene's image [{h}, {w}, 3 or 4]"
                )));
            }
            t.clone()
        }
        None => default_target(scene)?,
    };
    let rgb_only = target.shape()[2] == 3;
    if opts.samples == 0 || opts.items == 0 {
        return Err(RenderError::Unsupported(
            "gradcheck: --samples and --vertices must be at least 1".into(),
        ));
    }
    let x0 = input_value(scene, input)?;
    let (n_items, _) = item_layout(x0.shape());
    let cats = if input.is_per_vertex() {
        Some(vertex_categories(scene, opts.samples)?)
    } else {
        None
    };
    let rows = match &cats {
        Some(c) => stratified(c, opts.items, opts.seed),
        None if input == SceneInput::Texture => {
            select_items(&Items::Random(opts.items), n_items, opts.seed)?
        }
        None => (0..n_items).collect(),
    };
    if rows.is_empty() {
        return Err(RenderError::Unsupported(format!(
            "gradcheck: no visible vertex in {}: nothing to check",
            scene.source
        )));
    }
    let thresholds = opts
        .thresholds
        .clone()
        .unwrap_or_else(|| Thresholds::for_method(scene.desc.raster.method, input));
    let build = pipeline(|t, x| render_with(scene, input, t, x, opts.backward_scale, rgb_only));
    let big = if input.is_geometric() {
        Some(supersampled_scene(scene, opts.samples)?)
    } else {
        None
    };
    let own_opts = CheckOptions {
        eps: opts.eps,
        rtol: thresholds.rtol,
        atol: thresholds.atol,
        items: Items::List(rows.clone()),
        seed: opts.seed,
    };
    let (loss, g) = analytic_gradient(&build, &x0, &target)?;
    let analytic = item_values(&g, &rows);
    let numeric = fd_rows(
        |x| Ok(sq_loss(&eval_image(&build, x)?, &target)),
        &x0,
        &rows,
        &vec![own_opts.eps; rows.len()],
    )?;
    let own = CheckReport::compare(
        loss,
        &rows,
        analytic.clone(),
        numeric,
        own_opts.rtol,
        own_opts.atol,
    );

    // The area-integrated reference.
    let (reference, steps) = if let Some(big) = &big {
        let steps: Vec<f64> = match input {
            SceneInput::Positions => rows
                .iter()
                .map(|&v| {
                    pixel_step(scene, scene.mesh.positions[v], opts.step_px).ok_or_else(|| {
                        RenderError::Unsupported(format!(
                            "gradcheck: vertex {v} is behind the camera"
                        ))
                    })
                })
                .collect::<Result<_, _>>()?,
            _ => {
                let c = &scene.desc.camera;
                let dist = (0..3)
                    .map(|k| (c.eye[k] - c.at[k]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let px = 2.0 * dist * (c.fov_y_deg.to_radians() / 2.0).tan() / h as f64;
                vec![opts.step_px * px; rows.len()]
            }
        };
        let big_build = pipeline(move |t, x| render_with(big, input, t, x, None, rgb_only));
        let ref_image = move |x: &Tensor<f64>| -> Result<Tensor<f64>, RenderError> {
            let img = eval_image(&big_build, x)?;
            let img: Array3<f64> = img.into_dimensionality().map_err(|e| {
                RenderError::Unsupported(format!("reference image is not [H, W, C]: {e}"))
            })?;
            Ok(box_downsample(&img, opts.samples).into_dyn())
        };
        let ref_numeric = fd_rows(|x| Ok(sq_loss(&ref_image(x)?, &target)), &x0, &rows, &steps)?;
        let ref_loss = sq_loss(&ref_image(&x0)?, &target);
        let r = CheckReport::compare(
            ref_loss,
            &rows,
            analytic.clone(),
            ref_numeric,
            thresholds.rtol,
            thresholds.atol,
        );
        (Some((r, ref_image)), steps)
    } else {
        (None, vec![opts.eps; rows.len()])
    };

    let heatmap = if opts.heatmap {
        Some(match &reference {
            Some((_, ref_image)) => {
                disagreement_map(&build, ref_image, &x0, &target, &rows, &steps, opts.seed)?
            }
            None => disagreement_map(
                &build,
                &|x: &Tensor<f64>| eval_image(&build, x),
                &x0,
                &target,
                &rows,
                &steps,
                opts.seed,
            )?,
        })
    } else {
        None
    };
    let reference = reference.map(|(r, _)| r);

    let ref_decides = thresholds.min_reference_cosine.is_some();
    let items: Vec<ItemRecord> = own
        .items
        .iter()
        .enumerate()
        .map(|(i, it)| {
            let refv = reference.as_ref().map(|r| r.items[i].numeric.clone());
            let error = match (&reference, ref_decides) {
                (Some(r), true) => r.items[i].abs_err,
                _ => it.abs_err,
            };
            ItemRecord {
                item: it.item,
                category: cats.as_ref().map(|c| c[it.item]),
                pixel: input
                    .is_per_vertex()
                    .then(|| {
                        scene.camera.project_pixel(
                            scene.mesh.positions[it.item],
                            w as u32,
                            h as u32,
                        )
                    })
                    .flatten(),
                analytic: it.analytic.clone(),
                numeric: it.numeric.clone(),
                reference: refv,
                error,
                own_passed: it.passed,
            }
        })
        .collect();

    let categories = match &cats {
        Some(_) => VertexCategory::VISIBLE
            .iter()
            .filter_map(|&c| {
                let sel: Vec<&ItemRecord> =
                    items.iter().filter(|r| r.category == Some(c)).collect();
                if sel.is_empty() {
                    return None;
                }
                let a = || sel.iter().flat_map(|r| r.analytic.iter().copied());
                let (cosine_own, rel_l2_own) =
                    cosine_rel_l2(a(), sel.iter().flat_map(|r| r.numeric.iter().copied()));
                let refs = reference.as_ref().map(|_| {
                    cosine_rel_l2(
                        a(),
                        sel.iter()
                            .flat_map(|r| r.reference.iter().flatten().copied()),
                    )
                });
                Some(CategoryStats {
                    category: c,
                    count: sel.len(),
                    cosine_own,
                    rel_l2_own,
                    cosine_reference: refs.map(|r| r.0),
                    rel_l2_reference: refs.map(|r| r.1),
                })
            })
            .collect(),
        None => Vec::new(),
    };

    let mut failures = Vec::new();
    if thresholds.own_exact && !own.passed {
        let bad = own.items.iter().filter(|i| !i.passed).count();
        failures.push(format!(
            "{bad} of {} items differ from the finite differences of the method's own image by \
             more than atol {:.3e} + rtol {:e} |numeric|",
            own.items.len(),
            own.atol_abs,
            own.rtol
        ));
    }
    if let (Some(min), Some(r)) = (thresholds.min_reference_cosine, &reference) {
        if !(r.cosine >= min) {
            failures.push(format!(
                "cosine {:.4} with the {s}x{s} supersampled reference gradient is below {min}",
                r.cosine,
                s = opts.samples
            ));
        }
    }
    Ok(SceneCheck {
        source: scene.source.clone(),
        input,
        method: scene.desc.raster.method,
        samples: opts.samples,
        thresholds,
        own,
        reference,
        categories,
        items,
        heatmap,
        failures,
    })
}

/// Writes `disagreement.png` (when the check has a heat map) and `report.json` into `dir`.
pub fn write_outputs(
    check: &SceneCheck,
    dir: &std::path::Path,
    worst: usize,
) -> Result<Vec<PathBuf>, RenderError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| RenderError::Unsupported(format!("cannot create {}: {e}", dir.display())))?;
    let mut out = Vec::new();
    if let Some((diff, numeric)) = &check.heatmap {
        let p = dir.join("disagreement.png");
        crate::io::write_png(&p, &super::heat_png(diff, numeric))?;
        out.push(p);
    }
    let p = dir.join("report.json");
    let text = serde_json::to_string_pretty(&check.to_json(worst)).expect("JSON values");
    std::fs::write(&p, text)
        .map_err(|e| RenderError::Unsupported(format!("cannot write {}: {e}", p.display())))?;
    out.push(p);
    Ok(out)
}
