//! Property tests of robustness (proptest, 64 cases a property): random triangle soups
//! (coordinates up to 1e6, slivers, coincident vertices, degenerate faces, `w` near 0 or
//! negative, the odd NaN or Inf) through the hard rasterizer, SoftRas, DIB-R and the exact
//! area sampler (`analytic`, whose coverage must also stay in [0, 1]), forward and
//! backward: no panic, and finite images or a typed error; random mutations of a valid OBJ
//! and of a valid scene JSON through the loaders (and small valid scenes through the renderer):
//! no panic.
//!
//! `ROBUST_CASES=5000 cargo test -p tapestry-render-ops --test integration proptest_robust::` runs more cases
//! (5000 a property take about 6 s in the dev profile). Shrunk failures are kept in
//! `proptest_robust.proptest-regressions` beside this file and re-run first.

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use proptest::prelude::*;
use render_ops::analytic::analytic_fragments;
use render_ops::blend::{blend_hard, blend_weighted};
use render_ops::error::RenderError;
use render_ops::interpolate::interpolate;
use render_ops::obj::parse_obj_str;
use render_ops::pipeline::Wrt;
use render_ops::raster::{RasterError, RasterSettings};
use render_ops::rasterize::rasterize;
use render_ops::scene::Scene;
use render_ops::soft::{dibr, softras, DibrSettings, SoftSettings};

// ---------------------------------------------------------------------------------------------
// Triangle soups.

/// A clip coordinate: mostly on screen, sometimes huge, tiny, zero, or (rarely) not finite.
fn coord() -> impl Strategy<Value = f64> {
    prop_oneof![
        6 => -2.0..2.0f64,
        2 => -1e6..1e6f64,
        1 => -1e-6..1e-6f64,
        1 => Just(0.0),
        1 => prop_oneof![Just(1e6), Just(-1e6), Just(1.0), Just(-1.0)],
    ]
}

/// A clip `w`: mostly positive, sometimes near 0 (either sign), negative or huge.
fn coord_w() -> impl Strategy<Value = f64> {
    prop_oneof![
        6 => 0.2..4.0f64,
        2 => -1e-7..1e-7f64,
        1 => Just(0.0),
        2 => -4.0..-1e-3f64,
        1 => prop_oneof![Just(1e6), Just(f64::MIN_POSITIVE), Just(-f64::MIN_POSITIVE)],
    ]
}

#[derive(Clone, Debug)]
struct Soup {
    clip: Vec<[f64; 4]>,
    faces: Vec<[u32; 3]>,
    width: usize,
    height: usize,
}

impl Soup {
    fn finite(&self) -> bool {
        self.clip.iter().flatten().all(|x| x.is_finite())
    }
}

fn soup() -> impl Strategy<Value = Soup> {
    (3usize..10, 1usize..40, 1usize..40)
        .prop_flat_map(|(nv, width, height)| {
            let vert = [
                coord().boxed(),
                coord().boxed(),
                coord().boxed(),
                coord_w().boxed(),
            ];
            (
                proptest::collection::vec(vert, nv),
                proptest::collection::vec([0..nv as u32, 0..nv as u32, 0..nv as u32], 1..24),
                // (a, b): vertex b copies vertex a (coincident vertices).
                proptest::collection::vec((0..nv, 0..nv), 0..3),
                // (a, b, c, t, eps): vertex c on the line a-b (a sliver), nudged by eps.
                proptest::collection::vec(
                    (0..nv, 0..nv, 0..nv, -2.0..2.0f64, -1e-9..1e-9f64),
                    0..3,
                ),
                // (vertex, coordinate, value): the odd non-finite coordinate.
                proptest::option::weighted(
                    0.05,
                    (
                        0..nv,
                        0..4usize,
                        prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY)],
                    ),
                ),
                Just((width, height)),
            )
        })
        .prop_map(|(mut clip, faces, copies, slivers, bad, (width, height))| {
            for (a, b) in copies {
                clip[b] = clip[a];
            }
            for (a, b, c, t, eps) in slivers {
                if c != a && c != b {
                    let (pa, pb) = (clip[a], clip[b]);
                    clip[c] = std::array::from_fn(|k| pa[k] + t * (pb[k] - pa[k]) + eps);
                }
            }
            if let Some((v, k, x)) = bad {
                clip[v][k] = x;
            }
            Soup {
                clip,
                faces,
                width,
                height,
            }
        })
}

fn tensor(rows: &[[f64; 4]]) -> ArrayD<f64> {
    ArrayD::from_shape_vec(
        IxDyn(&[rows.len(), 4]),
        rows.iter().flatten().copied().collect(),
    )
    .unwrap()
}

fn colors(nv: usize) -> ArrayD<f64> {
    ArrayD::from_shape_fn(IxDyn(&[nv, 3]), |i| ((i[0] * 3 + i[1]) % 7) as f64 / 7.0)
}

/// Checks an image and runs its backward: the image must be finite; the backward may return an
/// error but must not panic.
fn check_image_and_backward<'t>(
    what: &str,
    tape: &'t Tape<f64>,
    img: autodiff::Var<'t, f64>,
) -> Result<(), TestCaseError> {
    let v = img
        .value()
        .map_err(|e| TestCaseError::fail(format!("{what}: {e}")))?;
    prop_assert!(
        v.iter().all(|x| x.is_finite()),
        "{what}: non-finite image value"
    );
    let weights = ArrayD::from_shape_vec(
        IxDyn(v.shape()),
        (0..v.len()).map(|k| (k % 5) as f64 - 2.0).collect(),
    )
    .unwrap();
    let _ = tape.backward((img * tape.constant(weights)).sum());
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(std::env::var("ROBUST_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(64)))]

    #[test]
    fn hard_rasterizer_on_random_soups(s in soup(), k in 1usize..4, cull in any::<bool>(), persp in any::<bool>(), derivs in any::<bool>()) {
        let settings = RasterSettings {
            faces_per_pixel: k,
            cull_backfaces: cull,
            perspective_correct: persp,
            barycentric_derivatives: derivs,
            ..RasterSettings::new(s.width, s.height)
        };
        // The raw rasterizer: non-finite vertices are the one error these inputs can give.
        match render_ops::raster::rasterize_fragments(&s.clip, &s.faces, &settings) {
            Ok(fr) => {
                prop_assert!(s.finite());
                prop_assert!(fr.bary.iter().flatten().all(|x| x.is_finite()));
                prop_assert!(fr.depth.iter().chain(&fr.view_depth).all(|x| x.is_finite()));
                prop_assert!(fr.dbary_dx.iter().chain(&fr.dbary_dy).flatten().all(|x| x.is_finite()));
                prop_assert!(fr.face.iter().all(|&f| (f as usize) < s.faces.len()));
                prop_assert_eq!(fr.has_derivatives(), derivs || fr.is_empty());
                prop_assert!(fr.validate().is_ok());
            }
            Err(e) => {
                prop_assert!(!s.finite(), "finite input refused: {e}");
                prop_assert!(matches!(e, RasterError::NonFiniteVertex { .. }), "{e}");
            }
        }
        // Through the tape: rasterize, interpolate colours, blend; then backward.
        let tape = Tape::<f64>::new();
        let clip = tape.leaf(tensor(&s.clip));
        let col = tape.leaf(colors(s.clip.len()));
        let faces = Arc::new(s.faces.clone());
        let img = rasterize(clip, faces, &settings).and_then(|r| {
            let c = interpolate(col, &r)?;
            blend_hard(c, &r.fragments, &[0.1, 0.2, 0.3])
        });
        match img {
            Ok(img) => check_image_and_backward("hard", &tape, img)?,
            Err(e) => prop_assert!(
                !s.finite() && matches!(e, RenderError::Raster(RasterError::NonFiniteVertex { .. })),
                "{e}"
            ),
        }
    }

    #[test]
    fn softras_on_random_soups(s in soup(), sigma in prop_oneof![Just(1e-4), Just(1e-2)], persp in any::<bool>()) {
        let tape = Tape::<f64>::new();
        let clip = tape.leaf(tensor(&s.clip));
        let col = tape.leaf(colors(s.clip.len()));
        let mut settings = SoftSettings::new(s.width, s.height, 0.1, 10.0);
        settings.sigma = sigma;
        settings.gamma = 1e-3;
        settings.perspective_correct = persp;
        settings.background = vec![0.1, 0.2, 0.3];
        match softras(clip, col, Arc::new(s.faces.clone()), &settings) {
            Ok(img) => check_image_and_backward("softras", &tape, img)?,
            // Non-finite clip coordinates are refused, as by the hard rasterizer.
            Err(e) => prop_assert!(
                !s.finite() && matches!(e, RenderError::Raster(RasterError::NonFiniteVertex { .. })),
                "{e}"
            ),
        }
    }

    #[test]
    fn dibr_on_random_soups(s in soup(), delta in prop_oneof![Just(1.0 / 7000.0), Just(1e-2)], cull in any::<bool>()) {
        let tape = Tape::<f64>::new();
        let clip = tape.leaf(tensor(&s.clip));
        let col = tape.leaf(colors(s.clip.len()));
        let mut settings = DibrSettings::new(s.width, s.height);
        settings.delta = delta;
        settings.cull_backfaces = cull;
        match dibr(clip, col, Arc::new(s.faces.clone()), &settings) {
            Ok(img) => check_image_and_backward("dibr", &tape, img)?,
            // DIB-R's foreground is the hard rasterizer, which refuses non-finite vertices.
            Err(e) => prop_assert!(
                !s.finite() && matches!(e, RenderError::Raster(RasterError::NonFiniteVertex { .. })),
                "{e}"
            ),
        }
    }

    /// Exact area sampling: every pixel's coverage (the sum of its fragments' visible areas)
    /// in [0, 1] to rounding, every value finite, the backward without panic (as for the
    /// other methods here: vertices a hair behind the eye plane, `w ~ -1e-8`, can still give
    /// an infinite position gradient through `1 / (sum of edge functions)^2`).
    #[test]
    fn analytic_on_random_soups(s in soup(), cull in any::<bool>(), persp in any::<bool>()) {
        let tape = Tape::<f64>::new();
        let clip = tape.leaf(tensor(&s.clip));
        let col = tape.leaf(colors(s.clip.len()));
        let settings = RasterSettings {
            cull_backfaces: cull,
            perspective_correct: persp,
            ..RasterSettings::new(s.width, s.height)
        };
        let img = analytic_fragments(clip, Arc::new(s.faces.clone()), &settings).and_then(|a| {
            let c = interpolate(col, &a.raster)?;
            blend_weighted(c, a.weight, &a.raster.fragments, &[0.1, 0.2, 0.3])
        });
        let img = match img {
            Ok(img) => img,
            Err(e) => {
                prop_assert!(
                    !s.finite() && matches!(e, RenderError::Raster(RasterError::NonFiniteVertex { .. })),
                    "{e}"
                );
                return Ok(());
            }
        };
        let v = img.value().map_err(|e| TestCaseError::fail(e.to_string()))?;
        for cov in v.iter().skip(3).step_by(4) {
            // To rounding: 1e-6, since a vertex near the eye plane (w ~ 1e-8) gives edge lines
            // whose coefficients differ by 1e8, and the clipper's relative on-line tolerance
            // (1e-10) then moves piece boundaries by up to ~1e-9 px (seen: 1 + 1.1e-9).
            prop_assert!((-1e-6..=1.0 + 1e-6).contains(cov), "coverage {cov}");
        }
        check_image_and_backward("analytic", &tape, img)?;
    }
}

// ---------------------------------------------------------------------------------------------
// Loaders.

const OBJ: &str = "# a valid OBJ with every statement the loader knows
o thing
v 0 0 0 1 1 1
v 1 0 0 1 0 0
v 1 1 0 0 1 0
v 0 1 0 0.5 0.5 0.5
v 0.5 0.5 1 0 0 1
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
g side
s 1
usemtl red
f 1/1/1 2/2/1 3/3/1
f 1/1/1 3/3/1 4/4/1
f -5/-4/-1 -4/-3/-1 -1/-2/-1
f 1/1/1 2/2/1 3/3/1 4/4/1 5/1/1
";

/// Tokens that mutations insert.
const TOKENS: &[&str] = &[
    "",
    " ",
    "\t",
    "0",
    "-0",
    "1",
    "-1",
    "2",
    "7",
    "-6",
    "1e309",
    "-1e309",
    "1e-400",
    "nan",
    "inf",
    "-inf",
    "99999999999999999999",
    "4294967296",
    "1/2/3",
    "1//1",
    "//",
    "/",
    "1/",
    "/1",
    "a",
    "+",
    "-",
    "v",
    "vt",
    "vn",
    "f",
    "l",
    "p",
    "#",
    "\\",
    "\u{feff}",
    "é",
    "\0",
];

#[derive(Clone, Debug)]
enum Mutation {
    Delete(usize),
    Duplicate(usize),
    Swap(usize, usize),
    /// Replace token `t` of line `l` with `TOKENS[k]`.
    Token(usize, usize, usize),
    /// Insert `TOKENS[k]` as a new token at `t` of line `l`.
    Insert(usize, usize, usize),
    /// Cut line `l` at character `c`.
    Truncate(usize, usize),
    /// Insert a random character at character `c` of line `l`.
    Char(usize, usize, char),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let n = 64usize;
    prop_oneof![
        (0..n).prop_map(Mutation::Delete),
        (0..n).prop_map(Mutation::Duplicate),
        (0..n, 0..n).prop_map(|(a, b)| Mutation::Swap(a, b)),
        (0..n, 0..8usize, 0..TOKENS.len()).prop_map(|(l, t, k)| Mutation::Token(l, t, k)),
        (0..n, 0..8usize, 0..TOKENS.len()).prop_map(|(l, t, k)| Mutation::Insert(l, t, k)),
        (0..n, 0..40usize).prop_map(|(l, c)| Mutation::Truncate(l, c)),
        (0..n, 0..40usize, any::<char>()).prop_map(|(l, c, ch)| Mutation::Char(l, c, ch)),
    ]
}

fn mutate_lines(text: &str, muts: &[Mutation]) -> String {
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for m in muts {
        if lines.is_empty() {
            break;
        }
        let n = lines.len();
        match *m {
            Mutation::Delete(l) => {
                lines.remove(l % n);
            }
            Mutation::Duplicate(l) => {
                let x = lines[l % n].clone();
                lines.insert(l % n, x);
            }
            Mutation::Swap(a, b) => lines.swap(a % n, b % n),
            Mutation::Token(l, t, k) | Mutation::Insert(l, t, k) => {
                let mut toks: Vec<String> = lines[l % n].split(' ').map(str::to_string).collect();
                let t = t % (toks.len() + 1);
                if matches!(m, Mutation::Insert(..)) || t == toks.len() {
                    toks.insert(t, TOKENS[k].to_string());
                } else {
                    toks[t] = TOKENS[k].to_string();
                }
                lines[l % n] = toks.join(" ");
            }
            Mutation::Truncate(l, c) => {
                let line = &mut lines[l % n];
                *line = line.chars().take(c).collect();
            }
            Mutation::Char(l, c, ch) => {
                let line = &mut lines[l % n];
                let mut chars: Vec<char> = line.chars().collect();
                chars.insert(c.min(chars.len()), ch);
                *line = chars.into_iter().collect();
            }
        }
    }
    lines.join("\n")
}

/// A folder holding `tri.obj` and a 2 x 2 `tex.png`, for scene loading.
fn scene_dir() -> &'static PathBuf {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("tapestry-proptest-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(
            d.join("tri.obj"),
            "v -1 -1 0\nv 1 -1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n",
        )
        .unwrap();
        image::RgbImage::from_pixel(2, 2, image::Rgb([200, 100, 50]))
            .save(d.join("tex.png"))
            .unwrap();
        d
    })
}

const SCENE: &str = r#"{
  "mesh": "tri.obj",
  "texture": null,
  "camera": {"eye": [0, 0, 3], "at": [0, 0, 0], "up": [0, 1, 0], "fov_y_deg": 45, "near": 0.1, "far": 100},
  "image": {"width": 16, "height": 12, "background": [0, 0, 0]},
  "lights": [{"type": "directional", "direction": [0, 0, -1], "color": [1, 1, 1]}, {"type": "ambient", "color": [0.2, 0.2, 0.2]}],
  "material": {"shading": "phong", "kd": [0.8, 0.8, 0.8], "ks": [0.2, 0.2, 0.2], "shininess": 32},
  "raster": {"method": "softras", "sigma": 1e-4, "gamma": 1e-4, "eps": 1e-3, "threshold": 1e-4, "faces_per_pixel": null, "cull_backfaces": false, "perspective_correct": true}
}"#;

/// Values that scene mutations put in place of a JSON node.
fn json_value() -> impl Strategy<Value = serde_json::Value> {
    use serde_json::json;
    prop_oneof![
        Just(json!(null)),
        Just(json!(true)),
        Just(json!(0)),
        Just(json!(-1)),
        Just(json!(1e308)),
        Just(json!(-1e-300)),
        Just(json!(u64::MAX)),
        Just(json!(3.5)),
        Just(json!("")),
        Just(json!("tri.obj")),
        Just(json!("tex.png")),
        Just(json!("hard")),
        Just(json!("dibr")),
        Just(json!("sh")),
        Just(json!("directional")),
        Just(json!([])),
        Just(json!([0, 0, 0])),
        Just(json!([1, 2])),
        Just(json!([[0, 0, 0]])),
        Just(json!({})),
        Just(json!({"type": "point", "position": [0, 1, 2], "color": [1, 1, 1]})),
        Just(json!({"type": "sh", "coeffs": [[0.5, 0.5, 0.5]]})),
        (-1e3..1e3f64).prop_map(|x| json!(x)),
        (0u32..70000).prop_map(|x| json!(x)),
    ]
}

#[derive(Clone, Debug)]
enum JsonMutation {
    /// Replace the node reached by the path choices with a value.
    Replace(Vec<usize>, serde_json::Value),
    /// Remove the key (or array element) reached by the path choices.
    Remove(Vec<usize>),
    /// Add an unknown key to the object reached.
    AddKey(Vec<usize>, serde_json::Value),
}

fn json_mutation() -> impl Strategy<Value = JsonMutation> {
    let path = proptest::collection::vec(0..16usize, 0..4);
    prop_oneof![
        (path.clone(), json_value()).prop_map(|(p, v)| JsonMutation::Replace(p, v)),
        path.clone().prop_map(JsonMutation::Remove),
        (path, json_value()).prop_map(|(p, v)| JsonMutation::AddKey(p, v)),
    ]
}

/// Follows `path` (each choice modulo the children count) from `v`, stopping at a leaf or one
/// step early when `parent` is set; returns the node and the last choice.
fn walk<'a>(
    mut v: &'a mut serde_json::Value,
    path: &[usize],
    parent: bool,
) -> (&'a mut serde_json::Value, Option<usize>) {
    let stop = if parent {
        path.len().saturating_sub(1)
    } else {
        path.len()
    };
    for &c in &path[..stop] {
        let n = match &*v {
            serde_json::Value::Object(m) => m.len(),
            serde_json::Value::Array(a) => a.len(),
            _ => 0,
        };
        if n == 0 {
            return (v, None);
        }
        v = match v {
            serde_json::Value::Object(m) => m.values_mut().nth(c % n).unwrap(),
            serde_json::Value::Array(a) => &mut a[c % n],
            _ => unreachable!(),
        };
    }
    (v, path.get(stop).copied())
}

fn mutate_json(text: &str, muts: &[JsonMutation]) -> serde_json::Value {
    let mut v: serde_json::Value = serde_json::from_str(text).unwrap();
    for m in muts {
        match m {
            JsonMutation::Replace(p, x) => *walk(&mut v, p, false).0 = x.clone(),
            JsonMutation::Remove(p) => {
                if let (node, Some(c)) = walk(&mut v, p, true) {
                    match node {
                        serde_json::Value::Object(m) if !m.is_empty() => {
                            let k = m.keys().nth(c % m.len()).unwrap().clone();
                            m.remove(&k);
                        }
                        serde_json::Value::Array(a) if !a.is_empty() => {
                            let n = a.len();
                            a.remove(c % n);
                        }
                        _ => {}
                    }
                }
            }
            JsonMutation::AddKey(p, x) => {
                if let serde_json::Value::Object(m) = walk(&mut v, p, false).0 {
                    m.insert("unknown_key".into(), x.clone());
                }
            }
        }
    }
    v
}

/// Loads (and, when it is small, renders) a scene text: errors are fine, panics are not.
fn load_and_maybe_render(text: &str) {
    let Ok(scene) = Scene::<f64>::from_json(text, scene_dir(), "fuzz.json") else {
        return;
    };
    let (w, h) = (scene.desc.image.width, scene.desc.image.height);
    if (w as u64) * (h as u64) > 64 * 64 {
        return;
    }
    let tape = Tape::new();
    let vars = scene.vars(
        &tape,
        Wrt {
            positions: true,
            colors: true,
            ..Wrt::default()
        },
    );
    if let Ok(img) = scene.render(&vars) {
        if let Ok(v) = img.value() {
            assert_eq!(v.shape(), &[h as usize, w as usize, 4]);
        }
        let _ = tape.backward(img.sum());
    }
}

/// A case the fuzzer found (2026-11-29): the camera's target at `z = u64::MAX` (the scene
/// must load and render, or fail with an error, without a panic).
#[test]
fn a_camera_target_at_u64_max_renders_without_panicking() {
    let v = mutate_json(
        SCENE,
        &[JsonMutation::Replace(
            vec![0, 0, 2],
            serde_json::json!(u64::MAX),
        )],
    );
    load_and_maybe_render(&v.to_string());
}

#[test]
fn the_inputs_that_are_mutated_are_valid() {
    let m = parse_obj_str::<f64>(OBJ).unwrap();
    assert_eq!((m.positions.len(), m.faces.len()), (5, 6));
    let scene = Scene::<f64>::from_json(SCENE, scene_dir(), "base.json").unwrap();
    let tape = Tape::new();
    let img = scene.render(&scene.vars(&tape, Wrt::default())).unwrap();
    assert_eq!(img.value().unwrap().shape(), &[12, 16, 4]);
    // The mutators change their input.
    assert_ne!(mutate_lines(OBJ, &[Mutation::Delete(3)]), OBJ.trim_end());
    let v = mutate_json(SCENE, &[JsonMutation::Remove(vec![0])]);
    assert_ne!(v, serde_json::from_str::<serde_json::Value>(SCENE).unwrap());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(std::env::var("ROBUST_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(64)))]

    #[test]
    fn obj_loader_on_mutated_files(muts in proptest::collection::vec(mutation(), 1..6)) {
        let text = mutate_lines(OBJ, &muts);
        if let Ok(m) = parse_obj_str::<f64>(&text) {
            let nv = m.positions.len();
            prop_assert!(m.positions.iter().flatten().all(|x| x.is_finite()), "{text:?}");
            prop_assert!(m.faces.iter().flatten().all(|&i| (i as usize) < nv), "{text:?}");
        }
        let _ = parse_obj_str::<f32>(&text);
    }

    #[test]
    fn obj_loader_on_random_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let text = String::from_utf8_lossy(&bytes);
        let _ = parse_obj_str::<f64>(&text);
        // The same bytes behind a valid header.
        let _ = parse_obj_str::<f64>(&format!("v 0 0 0\nv 1 0 0\nv 0 1 0\n{text}"));
    }

    #[test]
    fn scene_loader_on_mutated_json(muts in proptest::collection::vec(json_mutation(), 1..4)) {
        let v = mutate_json(SCENE, &muts);
        load_and_maybe_render(&v.to_string());
    }

    #[test]
    fn scene_loader_on_mutated_text(muts in proptest::collection::vec(mutation(), 1..4)) {
        load_and_maybe_render(&mutate_lines(SCENE, &muts));
    }
}
