//! Converts ICT-FaceKit (USC ICT, MIT licence) to a Tapestry model folder:
//!
//! ```text
//! cargo run -p tapestry-models --example convert_ict -- ICT_DIR [OUT_DIR [FIXTURE]]
//! ```
//!
//! `ICT_DIR` is a checkout of <https://github.com/ICT-VGL/ICT-FaceKit> (its `FaceXModel/`
//! folder is read); `OUT_DIR` defaults to `models/data/ict`, `FIXTURE` to
//! `models/tests/data/ict_fixture.json`. `scripts/convert_ict.sh` checks the pinned commit and
//! records the source hashes. The procedure is documented in `models/data/ict/README.md`:
//!
//! 1. the face area of the neutral mesh (ICT's "Full face area": vertices 0..9409, polygons
//!    0..9230), then the mouth socket and the two eyeballs; quads split along their shorter
//!    diagonal;
//! 2. identity mode `k` = `identity{k:03}.obj` minus the neutral mesh (ICT's own definition,
//!    `Scripts/face_model_io.py`), expression blendshape `e` = `{name}.obj` minus the neutral
//!    mesh, for the 53 names of `vertex_indices.json`; stored as float16 (the error is
//!    printed and stated in the README);
//! 3. the 468 MediaPipe landmarks as barycentric points on the ICT surface: the MediaPipe
//!    canonical mesh (the shipped model's mean) is aligned to the ICT mean by a similarity
//!    transform and a thin-plate spline through the 68 iBUG points (ICT's list against
//!    `fit::MEDIAPIPE_TO_IBUG68`), then each vertex is snapped to the closest ICT surface
//!    point; then refined where the detector (`models::detect`) puts them on frontal renders
//!    of the model ([`refine_by_detection`]);
//! 4. a test fixture: ground-truth positions computed from the OBJ text for a few vertices of
//!    the mean, of single OBJs and of random combinations.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use autodiff::rng::Rng;
use ndarray::{Array2, ArrayD, IxDyn};
use ndarray_npy::WriteNpyExt;
use serde_json::{json, Value};

/// ICT's "Full face area" (README, "Face Area Details").
const FACE_VERTICES: usize = 9409;
const FACE_POLYGONS: usize = 9230;
/// The kept geometries (ICT README, "Face Model Topology"): name, vertex range, polygon
/// range, region. The face area comes first, so its indices are ICT's.
const PARTS: [(&str, [usize; 2], [usize; 2], usize); 4] = [
    ("face", [0, 9409], [0, 9230], 0),
    ("mouth socket", [11248, 13294], [11144, 13226], 1),
    ("eyeball left", [21451, 23021], [21496, 23094], 2),
    ("eyeball right", [23021, 24591], [23094, 24692], 2),
];
/// ICT's "Narrow face area" (README, "Face Area Details"): polygons 0..6560 and vertices
/// 0..6706 of the face area; its triangles are the region `skin`, the rest of the face area
/// (forehead to the hairline's edge, temples, ears, jaw underside and neck) is `face_outer`.
const NARROW_FACE_POLYGONS: usize = 6560;
const NARROW_FACE_VERTICES: usize = 6706;
/// Region labels (the order of `regions` in `model.json`).
const FACE_OUTER: u8 = 3;
/// Radius of the iris (cm; human irises are 11-12 mm across).
const IRIS_RADIUS: f64 = 0.58;
/// Region names and mean albedo (linear RGB) of the regions other than skin.
const MOUTH: [f64; 3] = [0.12, 0.03, 0.03];
const SCLERA: [f64; 3] = [0.62, 0.58, 0.55];
const IRIS: [f64; 3] = [0.08, 0.05, 0.035];
/// ICT's 68 Multi-PIE landmarks (README, "Facial Landmarks"; `idx_to_landmark_verts`).
const ICT_IBUG68: [usize; 68] = [
    1225, 1888, 1052, 367, 1719, 1722, 2199, 1447, 966, 3661, 4390, 3927, 3924, 2608, 3272, 4088,
    3443, 268, 493, 1914, 2044, 1401, 3615, 4240, 4114, 2734, 2509, 978, 4527, 4942, 4857, 1140,
    2075, 1147, 4269, 3360, 1507, 1542, 1537, 1528, 1518, 1511, 3742, 3751, 3756, 3721, 3725, 3732,
    5708, 5695, 2081, 0, 4275, 6200, 6213, 6346, 6461, 5518, 5957, 5841, 5702, 5711, 5533, 6216,
    6207, 6470, 5517, 5966,
];
/// Expression weights are blendshape activations in [0, 1]; the prior's standard deviation.
const SIGMA_EXP: f64 = 0.5;
/// Mean skin albedo, linear RGB (the shipped MediaPipe model's skin colour).
const SKIN: [f64; 3] = [0.55, 0.36, 0.27];
/// Albedo basis: one constant colour offset per channel, this large at one sigma.
const ALBEDO_SIGMA: f64 = 0.1;

type Res<T> = Result<T, String>;

struct Obj {
    v: Vec<[f64; 3]>,
    vt: Vec<[f64; 2]>,
    /// Polygons as (vertex, uv) index lists, 0-based.
    f: Vec<Vec<(usize, usize)>>,
}

fn parse_obj(path: &Path, with_faces: bool) -> Res<Obj> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let bad = |n: usize| format!("{}:{}: bad line", path.display(), n + 1);
    let mut o = Obj {
        v: Vec::new(),
        vt: Vec::new(),
        f: Vec::new(),
    };
    for (n, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let mut p = [0.0; 3];
                for c in &mut p {
                    *c = it
                        .next()
                        .and_then(|s| s.parse().ok())
                        .ok_or_else(|| bad(n))?;
                }
                o.v.push(p);
            }
            Some("vt") if with_faces => {
                let mut p = [0.0; 2];
                for c in &mut p {
                    *c = it
                        .next()
                        .and_then(|s| s.parse().ok())
                        .ok_or_else(|| bad(n))?;
                }
                o.vt.push(p);
            }
            Some("f") if with_faces => {
                let poly = it
                    .map(|c| {
                        let mut s = c.split('/');
                        let v: usize = s.next()?.parse().ok()?;
                        let t: usize = s.next().unwrap_or("0").parse().ok()?;
                        Some((v.checked_sub(1)?, t.wrapping_sub(1)))
                    })
                    .collect::<Option<Vec<_>>>()
                    .ok_or_else(|| bad(n))?;
                o.f.push(poly);
            }
            _ => {}
        }
    }
    Ok(o)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// Polygons to triangles in the kept vertices' numbering (`map`: ICT index to kept index):
/// a quad is split along its shorter diagonal.
fn triangulate(
    v: &[[f64; 3]],
    polys: &[Vec<(usize, usize)>],
    map: &[Option<usize>],
) -> Res<Vec<[usize; 3]>> {
    let mut tris = Vec::new();
    for p in polys {
        let ids: Vec<usize> = p
            .iter()
            .map(|&(i, _)| map[i])
            .collect::<Option<_>>()
            .ok_or_else(|| format!("polygon {p:?} uses a vertex that is not kept"))?;
        match ids.len() {
            3 => tris.push([ids[0], ids[1], ids[2]]),
            4 => {
                let d02 = norm(sub(v[ids[0]], v[ids[2]]));
                let d13 = norm(sub(v[ids[1]], v[ids[3]]));
                if d02 <= d13 {
                    tris.push([ids[0], ids[1], ids[2]]);
                    tris.push([ids[0], ids[2], ids[3]]);
                } else {
                    tris.push([ids[0], ids[1], ids[3]]);
                    tris.push([ids[1], ids[2], ids[3]]);
                }
            }
            n => return Err(format!("a polygon with {n} corners")),
        }
    }
    Ok(tris)
}

/// The closest point of triangle `abc` to `p` as barycentric weights (Ericson, Real-Time
/// Collision Detection, 5.1.5).
fn closest_on_triangle(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return [0.0, 1.0, 0.0];
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let t = d1 / (d1 - d3);
        return [1.0 - t, t, 0.0];
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return [0.0, 0.0, 1.0];
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let t = d2 / (d2 - d6);
        return [1.0 - t, 0.0, t];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let t = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return [0.0, 1.0 - t, t];
    }
    let denom = 1.0 / (va + vb + vc);
    let w1 = vb * denom;
    let w2 = vc * denom;
    [1.0 - w1 - w2, w1, w2]
}

fn blend(w: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| w[0] * a[i] + w[1] * b[i] + w[2] * c[i])
}

/// Solves `a x = b` (dense, partial pivoting), `b` with several columns.
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<Vec<f64>>) -> Res<Vec<Vec<f64>>> {
    let n = a.len();
    for k in 0..n {
        let piv = (k..n)
            .max_by(|&i, &j| a[i][k].abs().total_cmp(&a[j][k].abs()))
            .ok_or("empty system")?;
        if a[piv][k].abs() < 1e-12 {
            return Err("singular system".into());
        }
        a.swap(k, piv);
        b.swap(k, piv);
        let (pivot_a, pivot_b) = (a[k].clone(), b[k].clone());
        for (ra, rb) in a.iter_mut().zip(b.iter_mut()).skip(k + 1) {
            let f = ra[k] / pivot_a[k];
            for (x, p) in ra.iter_mut().zip(&pivot_a).skip(k) {
                *x -= f * p;
            }
            for (x, p) in rb.iter_mut().zip(&pivot_b) {
                *x -= f * p;
            }
        }
    }
    for k in (0..n).rev() {
        for j in 0..b[k].len() {
            let s: f64 = (k + 1..n).map(|i| a[k][i] * b[i][j]).sum();
            b[k][j] = (b[k][j] - s) / a[k][k];
        }
    }
    Ok(b)
}

/// A 3-D thin-plate spline (kernel |r|) with an affine part through `src -> dst`.
fn thin_plate(src: &[[f64; 3]], dst: &[[f64; 3]]) -> Res<impl Fn([f64; 3]) -> [f64; 3]> {
    let n = src.len();
    let mut a = vec![vec![0.0; n + 4]; n + 4];
    let mut b = vec![vec![0.0; 3]; n + 4];
    for i in 0..n {
        for j in 0..n {
            a[i][j] = norm(sub(src[i], src[j]));
        }
        let row = [1.0, src[i][0], src[i][1], src[i][2]];
        for k in 0..4 {
            a[i][n + k] = row[k];
            a[n + k][i] = row[k];
        }
        b[i] = dst[i].to_vec();
    }
    let x = solve(a, b)?;
    let src = src.to_vec();
    Ok(move |p: [f64; 3]| {
        let mut out = [0.0; 3];
        for (i, s) in src.iter().enumerate() {
            let r = norm(sub(p, *s));
            for c in 0..3 {
                out[c] += x[i][c] * r;
            }
        }
        let row = [1.0, p[0], p[1], p[2]];
        for k in 0..4 {
            for c in 0..3 {
                out[c] += x[n + k][c] * row[k];
            }
        }
        out
    })
}

fn npy_f32(path: &Path, a: Array2<f64>) -> Res<()> {
    let f = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    a.mapv(|x| x as f32)
        .write_npy(std::io::BufWriter::new(f))
        .map_err(|e| format!("{}: {e}", path.display()))
}

fn npy_i32(path: &Path, a: Array2<i32>) -> Res<()> {
    let f = std::fs::File::create(path).map_err(|e| format!("{}: {e}", path.display()))?;
    a.write_npy(std::io::BufWriter::new(f))
        .map_err(|e| format!("{}: {e}", path.display()))
}

/// "median, 90%, max" of `d` (mm), for the converter's log.
fn quantiles_mm(mut d: Vec<f64>) -> String {
    d.sort_by(f64::total_cmp);
    let n = d.len();
    format!(
        "median {:.2} mm, 90% {:.2} mm, max {:.2} mm",
        d[n / 2],
        d[n * 9 / 10],
        d[n - 1]
    )
}

/// The closest point of the mesh `tris` over `v` to `p`: distance, triangle, weights.
fn closest_on_mesh(p: [f64; 3], v: &[[f64; 3]], tris: &[[usize; 3]]) -> (f64, usize, [f64; 3]) {
    let mut best = (f64::INFINITY, 0usize, [1.0, 0.0, 0.0]);
    for (f, t) in tris.iter().enumerate() {
        let (a, b, c) = (v[t[0]], v[t[1]], v[t[2]]);
        let w = closest_on_triangle(p, a, b, c);
        let d = norm(sub(p, blend(w, a, b, c)));
        if d < best.0 {
            best = (d, f, w);
        }
    }
    best
}

/// Detector-consistent landmarks: the model (just written to `out`) is rendered frontally
/// (384 x 384, front light, grey background) at the mean and at RENDERS - 1 random
/// identities; each detected landmark is lifted to the front-most face-area triangle under it
/// (2-D barycentrics; the closest triangle in the image where none covers it), carried to the
/// mean shape by its barycentrics, averaged over the renders and snapped to the surface. A
/// landmark the detector places more than MAX_SHIFT_MM away from the geometric one keeps the
/// geometric one.
fn refine_by_detection(
    out: &Path,
    mean: &[[f64; 3]],
    tris: &[[usize; 3]],
    geometric: &[(usize, [f64; 3])],
) -> Res<Vec<(usize, [f64; 3])>> {
    use models::fit::{FaceParams, FaceRenderer, RenderOptions};
    const RENDERS: u64 = 5;
    const SIZE: usize = 384;
    const MAX_SHIFT_MM: f64 = 15.0;
    let model: models::Morphable<f64> = models::Morphable::load(out).map_err(|e| e.to_string())?;
    let renderer =
        FaceRenderer::new(&model, RenderOptions::new(SIZE, SIZE)).map_err(|e| e.to_string())?;
    let landmarker = models::detect::Landmarker::new().map_err(|e| e.to_string())?;
    let mut sums = vec![[0.0; 3]; geometric.len()];
    let mut rng = Rng::new(468);
    for r in 0..RENDERS {
        let mut p = FaceParams::neutral(&model);
        if r > 0 {
            p.z_id = (0..model.n_id())
                .map(|_| rng.normal().clamp(-2.0, 2.0))
                .collect();
        }
        p.sh[2] = [0.35 / 0.488603; 3]; // light from the camera's side (+z)
        let (img, px) = renderer.render(&p).map_err(|e| e.to_string())?;
        let shape = model
            .eval_shape_standardized(&p.z_id, &p.z_exp)
            .map_err(|e| e.to_string())?;
        let rgb = ndarray::Array3::from_shape_fn((SIZE, SIZE, 3), |(y, x, c)| {
            img[[y, x, c]] + (1.0 - img[[y, x, 3]]) * 0.5
        });
        let faces = landmarker
            .detect_landmarks(rgb.view())
            .map_err(|e| format!("render {r}: {e}"))?;
        let lms = &faces.first().ok_or(format!("render {r}: no face"))?.points;
        if lms.nrows() != geometric.len() {
            return Err(format!("render {r}: {} landmarks", lms.nrows()));
        }
        for (i, sum) in sums.iter_mut().enumerate() {
            let q = [lms[[i, 0]], lms[[i, 1]], 0.0];
            // Front-most covering triangle (largest z of the model-space centroid: frontal
            // view), else the closest one in the image.
            let mut best: Option<(f64, usize, [f64; 3])> = None;
            let mut nearest = (f64::INFINITY, 0usize, [1.0, 0.0, 0.0]);
            for (f, t) in tris.iter().enumerate() {
                let c2 = |k: usize| [px[[t[k], 0]], px[[t[k], 1]], 0.0];
                let (a, b, c) = (c2(0), c2(1), c2(2));
                let w = closest_on_triangle(q, a, b, c);
                let d = norm(sub(q, blend(w, a, b, c)));
                if d < 1e-9 {
                    let z = (0..3).map(|k| shape[[t[k], 2]]).sum::<f64>();
                    if best.is_none_or(|(bz, _, _)| z > bz) {
                        best = Some((z, f, w));
                    }
                } else if d < nearest.0 {
                    nearest = (d, f, w);
                }
            }
            let (f, w) = best.map_or((nearest.1, nearest.2), |(_, f, w)| (f, w));
            let t = tris[f];
            let on_mean = blend(w, mean[t[0]], mean[t[1]], mean[t[2]]);
            for c in 0..3 {
                sum[c] += on_mean[c] / RENDERS as f64;
            }
        }
    }
    Ok(sums
        .iter()
        .zip(geometric)
        .map(|(p, &(f, w))| {
            let t = tris[f];
            let g = blend(w, mean[t[0]], mean[t[1]], mean[t[2]]);
            if 10.0 * norm(sub(*p, g)) > MAX_SHIFT_MM {
                (f, w)
            } else {
                let (_, f, w) = closest_on_mesh(*p, mean, tris);
                (f, w)
            }
        })
        .collect())
}

fn run() -> Res<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let ict = PathBuf::from(
        args.first()
            .ok_or("usage: convert_ict ICT_DIR [OUT_DIR [FIXTURE]]")?,
    )
    .join("FaceXModel");
    let crate_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let out = args
        .get(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| crate_dir.join("data/ict"));
    let fixture_path = args
        .get(2)
        .map(PathBuf::from)
        .unwrap_or_else(|| crate_dir.join("tests/data/ict_fixture.json"));
    std::fs::create_dir_all(&out).map_err(|e| e.to_string())?;

    // ---- mesh
    let neutral = parse_obj(&ict.join("generic_neutral_mesh.obj"), true)?;
    // kept[i]: the ICT index of kept vertex i; map: the inverse.
    let kept: Vec<usize> = PARTS.iter().flat_map(|p| p.1[0]..p.1[1]).collect();
    let mut map = vec![None; neutral.v.len()];
    for (i, &k) in kept.iter().enumerate() {
        map[k] = Some(i);
    }
    let n_kept = kept.len();
    let mean: Vec<[f64; 3]> = kept.iter().map(|&k| neutral.v[k]).collect();
    let mut tris = Vec::new();
    let mut labels = Vec::new();
    let mut polys = Vec::new();
    for (name, _, f, region) in PARTS {
        let t = triangulate(&mean, &neutral.f[f[0]..f[1]], &map)?;
        eprintln!("{name}: {} polygons -> {} triangles", f[1] - f[0], t.len());
        if region == 0 {
            let narrow = &neutral.f[f[0]..NARROW_FACE_POLYGONS];
            if let Some(v) = narrow
                .iter()
                .flatten()
                .map(|&(v, _)| v)
                .find(|&v| v >= NARROW_FACE_VERTICES)
            {
                return Err(format!("a narrow-face polygon uses vertex {v}"));
            }
            let n = triangulate(&mean, narrow, &map)?.len();
            eprintln!("narrow face: {} polygons -> {n} triangles", narrow.len());
            labels.extend(std::iter::repeat_n(0u8, n));
            labels.extend(std::iter::repeat_n(FACE_OUTER, t.len() - n));
        } else {
            labels.extend(std::iter::repeat_n(region as u8, t.len()));
        }
        tris.extend(t);
        polys.extend_from_slice(&neutral.f[f[0]..f[1]]);
    }
    let n_face_tris = labels
        .iter()
        .take_while(|&&l| l == 0 || l == FACE_OUTER)
        .count();
    // Orientation: the area-weighted normal of the face area must point to +z (the face looks
    // towards +z).
    let nz: f64 = tris[..n_face_tris]
        .iter()
        .map(|t| cross(sub(mean[t[1]], mean[t[0]]), sub(mean[t[2]], mean[t[0]]))[2])
        .sum();
    if nz < 0.0 {
        for t in &mut tris {
            t.swap(1, 2);
        }
    }
    eprintln!(
        "kept {} vertices, {} triangles (face area: {} vertices, {} polygons; normals {})",
        n_kept,
        tris.len(),
        FACE_VERTICES,
        FACE_POLYGONS,
        if nz < 0.0 { "flipped" } else { "kept" }
    );
    // Per-vertex uvs: the first uv seen at the vertex (seam vertices have several).
    let mut uv = vec![None; n_kept];
    let mut seams = 0usize;
    for p in &polys {
        for &(vi, ti) in p {
            let vi = map[vi].ok_or("a polygon outside the kept vertices")?;
            let t = *neutral.vt.get(ti).ok_or("a face without uvs")?;
            match uv[vi] {
                None => uv[vi] = Some(t),
                Some(u) if u != t => seams += 1,
                _ => {}
            }
        }
    }
    eprintln!("uvs: {seams} corner uvs differ from their vertex's first (seams)");

    // ---- bases
    let config: Value = serde_json::from_str(
        &std::fs::read_to_string(ict.join("vertex_indices.json")).map_err(|e| e.to_string())?,
    )
    .map_err(|e| e.to_string())?;
    let exp_names: Vec<String> = config["expressions"]
        .as_array()
        .ok_or("vertex_indices.json: no expressions")?
        .iter()
        .map(|v| v.as_str().map(String::from).ok_or("expression name"))
        .collect::<Result<_, _>>()?;
    let id_names: Vec<String> = (0..100).map(|k| format!("identity{k:03}")).collect();
    let read_deltas = |names: &[String]| -> Res<Vec<Vec<[f64; 3]>>> {
        names
            .iter()
            .map(|n| {
                let o = parse_obj(&ict.join(format!("{n}.obj")), false)?;
                if o.v.len() != neutral.v.len() {
                    return Err(format!("{n}.obj: {} vertices", o.v.len()));
                }
                Ok(kept
                    .iter()
                    .zip(&mean)
                    .map(|(&k, m)| sub(o.v[k], *m))
                    .collect())
            })
            .collect()
    };
    let id = read_deltas(&id_names)?;
    let exp = read_deltas(&exp_names)?;
    let to_basis = |modes: &[Vec<[f64; 3]>]| {
        let k = modes.len();
        ArrayD::from_shape_fn(IxDyn(&[n_kept, 3, k]), |ix| modes[ix[2]][ix[0]][ix[1]])
    };
    let (id_b, exp_b) = (to_basis(&id), to_basis(&exp));
    let q_err = |b: &ArrayD<f64>| {
        b.iter()
            .map(|&x| (half::f16::from_f64(x).to_f64() - x).abs())
            .fold(0.0f64, f64::max)
    };
    let max_abs = |b: &ArrayD<f64>| b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    eprintln!(
        "identity deltas: max |d| {:.3} cm, float16 error <= {:.2e} cm; expression deltas: max |d| {:.3} cm, float16 error <= {:.2e} cm",
        max_abs(&id_b),
        q_err(&id_b),
        max_abs(&exp_b),
        q_err(&exp_b)
    );
    models::io::write_f16_npy(&out.join("id_basis.npy"), &id_b).map_err(|e| e.to_string())?;
    models::io::write_f16_npy(&out.join("exp_basis.npy"), &exp_b).map_err(|e| e.to_string())?;
    npy_f32(
        &out.join("mean_shape.npy"),
        Array2::from_shape_fn((n_kept, 3), |(v, c)| mean[v][c]),
    )?;
    let mean_f32_err = mean
        .iter()
        .flatten()
        .map(|&x| (x as f32 as f64 - x).abs())
        .fold(0.0f64, f64::max);
    eprintln!("mean shape: float32 error <= {mean_f32_err:.2e} cm");
    npy_i32(
        &out.join("faces.npy"),
        Array2::from_shape_fn((tris.len(), 3), |(f, c)| tris[f][c] as i32),
    )?;
    npy_f32(
        &out.join("uvs.npy"),
        Array2::from_shape_fn((n_kept, 2), |(v, c)| uv[v].map_or(0.0, |t| t[c])),
    )?;
    let path = out.join("face_regions.npy");
    let f = std::fs::File::create(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    ndarray::Array1::from(labels.clone())
        .write_npy(std::io::BufWriter::new(f))
        .map_err(|e| format!("{}: {e}", path.display()))?;
    // ICT's iris mesh lies inside the sclera mesh, whose front is the cornea: the visible
    // colour is on the sclera. Its vertices within IRIS_RADIUS of the eye's axis (through the
    // front-most vertex, along +z: the neutral gaze) get the iris colour.
    let pupils: Vec<[f64; 3]> = [2, 3]
        .iter()
        .map(|&part| {
            let r = PARTS[part].1;
            let k = (r[0]..r[1])
                .max_by(|&a, &b| neutral.v[a][2].total_cmp(&neutral.v[b][2]))
                .expect("eyeball vertices");
            neutral.v[k]
        })
        .collect();
    let colour = |k: usize| -> [f64; 3] {
        if k < FACE_VERTICES {
            return SKIN;
        }
        if k < PARTS[2].1[0] {
            return MOUTH;
        }
        let p = pupils[usize::from(k >= PARTS[3].1[0])];
        let v = neutral.v[k];
        let lateral = (v[0] - p[0]).hypot(v[1] - p[1]);
        if lateral < IRIS_RADIUS && v[2] > p[2] - IRIS_RADIUS {
            IRIS
        } else {
            SCLERA
        }
    };
    npy_f32(
        &out.join("mean_albedo.npy"),
        Array2::from_shape_fn((n_kept, 3), |(v, c)| colour(kept[v])[c]),
    )?;
    // Unit columns on the skin: channel c constant 1/sqrt(V_face) on the face area, 0 on the
    // mouth and eyes; sigma so that one sigma is ALBEDO_SIGMA.
    let unit = 1.0 / (FACE_VERTICES as f64).sqrt();
    let albedo_basis = ArrayD::from_shape_fn(IxDyn(&[3 * n_kept, 3]), |ix| {
        if ix[0] % 3 == ix[1] && ix[0] / 3 < FACE_VERTICES {
            unit
        } else {
            0.0
        }
    });
    models::io::write_f16_npy(&out.join("albedo_basis.npy"), &albedo_basis)
        .map_err(|e| e.to_string())?;

    // ---- landmarks: MediaPipe 468 on the ICT surface
    let mp: models::Morphable<f64> = models::face::default_face();
    let mp_mean = mp.mean_shape(); // mm
    let mp_pt = |i: usize| -> [f64; 3] { std::array::from_fn(|c| mp_mean[[i, c]] / 10.0) };
    let src68: Vec<[f64; 3]> = models::fit::MEDIAPIPE_TO_IBUG68
        .iter()
        .map(|&(a, b)| {
            let (pa, pb) = (mp_pt(a), mp_pt(b));
            std::array::from_fn(|c| 0.5 * (pa[c] + pb[c]))
        })
        .collect();
    let dst68: Vec<[f64; 3]> = ICT_IBUG68.iter().map(|&i| mean[i]).collect();
    let sim = models::fit::umeyama(&src68, &dst68, true);
    let src68s: Vec<[f64; 3]> = src68.iter().map(|&p| sim.apply(p)).collect();
    let rms = |a: &[[f64; 3]], b: &[[f64; 3]]| {
        (a.iter()
            .zip(b)
            .map(|(p, q)| dot(sub(*p, *q), sub(*p, *q)))
            .sum::<f64>()
            / a.len() as f64)
            .sqrt()
    };
    eprintln!(
        "MediaPipe -> ICT: 68-point RMS after the similarity transform {:.2} mm",
        10.0 * rms(&src68s, &dst68)
    );
    let tps = thin_plate(&src68s, &dst68)?;
    let face_tris = &tris[..n_face_tris];
    let mut points = Vec::with_capacity(468);
    let mut snap = Vec::with_capacity(468);
    for i in 0..mp.n_vertices() {
        let (d, f, w) = closest_on_mesh(tps(sim.apply(mp_pt(i))), &mean, face_tris);
        snap.push(10.0 * d);
        points.push((f, w));
    }
    eprintln!(
        "MediaPipe vertices snapped to the ICT surface: {}",
        quantiles_mm(snap)
    );

    // ---- model.json
    let groups: BTreeMap<String, Vec<usize>> = mp.landmark_groups().clone();
    let model = json!({
        "format": "tapestry-morphable",
        "version": 1,
        "name": "ict-facekit-face",
        "description": "ICT-FaceKit (USC ICT, MIT licence, see LICENSE and NOTICE) face area, mouth socket and eyeballs: 100 identity PCA modes (weights ~ N(0, 1)) and 53 ARKit-style expression blendshapes, float16; constant albedo per region (skin, mouth, sclera, iris) and a skin colour basis; MediaPipe-468 landmarks as surface points. See models/data/ict/README.md.",
        "units": "cm",
        "basis_scaled": true,
        "n_vertices": n_kept,
        "n_faces": tris.len(),
        "n_id": id_names.len(),
        "n_exp": exp_names.len(),
        "n_albedo": 3,
        "files": {
            "mean_shape": "mean_shape.npy", "id_basis": "id_basis.npy", "exp_basis": "exp_basis.npy",
            "mean_albedo": "mean_albedo.npy", "albedo_basis": "albedo_basis.npy",
            "faces": "faces.npy", "uvs": "uvs.npy", "face_regions": "face_regions.npy"
        },
        "sigma_id": vec![1.0; id_names.len()],
        "sigma_exp": vec![SIGMA_EXP; exp_names.len()],
        "sigma_albedo": vec![ALBEDO_SIGMA / unit; 3],
        "landmark_points": points.iter().map(|(f, w)| json!([f, w[0], w[1], w[2]])).collect::<Vec<_>>(),
        "landmark_scheme": "mediapipe468",
        "landmark_groups": groups,
        "regions": [
            {"name": "skin"},
            {"name": "mouth_interior", "photometric": false},
            {"name": "eyes", "photometric": false},
            {"name": "face_outer", "photometric": false}
        ],
        "id_names": id_names,
        "exp_names": exp_names,
        "albedo_names": ["red", "green", "blue"],
    });
    std::fs::write(
        out.join("model.json"),
        serde_json::to_string(&model).map_err(|e| e.to_string())? + "\n",
    )
    .map_err(|e| e.to_string())?;

    // ---- landmarks, step 2: where the detector puts them on renders of the model
    let refined = refine_by_detection(&out, &mean, face_tris, &points)?;
    let moved: Vec<f64> = points
        .iter()
        .zip(&refined)
        .map(|(a, b)| {
            let at = |(f, w): &(usize, [f64; 3])| {
                let t = face_tris[*f];
                blend(*w, mean[t[0]], mean[t[1]], mean[t[2]])
            };
            10.0 * norm(sub(at(a), at(b)))
        })
        .collect();
    eprintln!("refined by detection: moved {}", quantiles_mm(moved));
    let mut model = model;
    model["landmark_points"] = refined
        .iter()
        .map(|(f, w)| json!([f, w[0], w[1], w[2]]))
        .collect();
    std::fs::write(
        out.join("model.json"),
        serde_json::to_string(&model).map_err(|e| e.to_string())? + "\n",
    )
    .map_err(|e| e.to_string())?;

    // ---- fixture: ground truth from the OBJ text (cm), for the test on a fresh clone
    let mut rng = Rng::new(29);
    let mut verts: Vec<usize> = ICT_IBUG68.to_vec();
    verts.extend((0..32).map(|_| rng.below(FACE_VERTICES)));
    verts.extend((0..12).map(|_| FACE_VERTICES + rng.below(n_kept - FACE_VERTICES)));
    let mut cases = Vec::new();
    let mut add = |name: String, alpha: Vec<f64>, beta: Vec<f64>| {
        let pos: Vec<[f64; 3]> = verts
            .iter()
            .map(|&v| {
                let mut p = mean[v];
                for (k, a) in alpha.iter().enumerate() {
                    p = std::array::from_fn(|c| p[c] + a * id[k][v][c]);
                }
                for (k, b) in beta.iter().enumerate() {
                    p = std::array::from_fn(|c| p[c] + b * exp[k][v][c]);
                }
                p
            })
            .collect();
        cases.push(json!({"name": name, "alpha": alpha, "beta": beta, "positions_cm": pos}));
    };
    let (n_id, n_exp) = (id_names.len(), exp_names.len());
    add("mean".into(), vec![0.0; n_id], vec![0.0; n_exp]);
    let one = |n: usize, k: usize| (0..n).map(|i| f64::from(u8::from(i == k))).collect();
    add("identity042".into(), one(n_id, 42), vec![0.0; n_exp]);
    add("jawOpen".into(), vec![0.0; n_id], one(n_exp, 26));
    for s in 0..3 {
        let alpha: Vec<f64> = (0..n_id)
            .map(|_| (rng.normal() * 1e4).round() / 1e4)
            .collect();
        let beta: Vec<f64> = (0..n_exp)
            .map(|_| {
                if rng.next_f64() < 0.3 {
                    (rng.next_f64() * 1e4).round() / 1e4
                } else {
                    0.0
                }
            })
            .collect();
        add(format!("random{s}"), alpha, beta);
    }
    let fixture = json!({
        "source": "ICT-FaceKit FaceXModel OBJs (see models/data/ict/SOURCES.sha256)",
        "vertices": verts,
        "cases": cases,
    });
    std::fs::write(
        &fixture_path,
        serde_json::to_string(&fixture).map_err(|e| e.to_string())? + "\n",
    )
    .map_err(|e| e.to_string())?;
    eprintln!("wrote {} and {}", out.display(), fixture_path.display());
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}
