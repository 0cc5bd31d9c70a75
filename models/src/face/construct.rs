//! Deterministic construction of the shipped face model (see `models/data/face/README.md`).

use std::collections::BTreeMap;

use ndarray::{Array1, Array2};

use super::geom::{add, centroid, cross, gram_schmidt, norm, scale, smoothstep, sub, Graph, V3};
use super::{CANONICAL_OBJ, CONTOURS_JSON};
use crate::error::{ModelError, Result};
use crate::morphable::{LandmarkScheme, Morphable, MorphableParts, Region};

const N_VERTICES: usize = 468;
const N_FACES: usize = 898;
/// The OBJ is in centimetres; the model in millimetres.
const OBJ_TO_MM: f64 = 10.0;

// Contours of the subject's right side (x < 0) and the midline, MediaPipe face-mesh indices.
// The left side is their mirror image (the mesh is exactly mirror-symmetric).
const RIGHT_EYE_UPPER: [usize; 9] = [33, 246, 161, 160, 159, 158, 157, 173, 133];
const RIGHT_EYE_LOWER: [usize; 9] = [33, 7, 163, 144, 145, 153, 154, 155, 133];
const RIGHT_BROW_UPPER: [usize; 5] = [70, 63, 105, 66, 107];
const RIGHT_BROW_LOWER: [usize; 5] = [46, 53, 52, 65, 55];
const LIPS_UPPER_OUTER: [usize; 11] = [61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291];
const LIPS_LOWER_OUTER: [usize; 11] = [61, 146, 91, 181, 84, 17, 314, 405, 321, 375, 291];
const LIPS_UPPER_INNER: [usize; 11] = [78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308];
const LIPS_LOWER_INNER: [usize; 11] = [78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308];
const NOSE_RIDGE: [usize; 10] = [168, 6, 197, 195, 5, 4, 1, 19, 94, 2];

// Anchor vertex sets (subject's right side and midline) of the regional fields.
const NOSE_TIP: &[usize] = &[4, 1, 44, 45, 19, 237, 220];
const NOSE_BRIDGE: &[usize] = &[168, 6, 197, 195, 5, 122, 196, 3];
const NOSE_ALA: &[usize] = &[98, 64, 129, 49, 48, 102, 219, 115];
const SUBNASALE: &[usize] = &[2, 94, 164, 167];
const CHIN: &[usize] = &[152, 175, 199, 200, 148, 171, 208, 201];
const JAW_ANGLE: &[usize] = &[172, 136, 58, 138, 135, 150];
const CHEEKBONE: &[usize] = &[117, 123, 50];
const CHEEK: &[usize] = &[205, 207, 216, 206, 187];
const LOWER_CHEEK: &[usize] = &[214, 192, 212, 210];
const TEMPLE: &[usize] = &[139, 71, 21, 162, 68];
const FOREHEAD: &[usize] = &[10, 151, 9, 108, 109, 69, 67, 104, 103];
const NASOLABIAL: &[usize] = &[206, 165, 92, 186, 216];
const MOUTH_CORNER: &[usize] = &[61, 78];

/// Region names of the shipped model, in label order.
pub const REGION_NAMES: [&str; 6] = [
    "skin",
    "lips",
    "mouth_interior",
    "eye_left",
    "eye_right",
    "brows",
];
const MOUTH_INTERIOR_ALBEDO: [f64; 3] = [0.08, 0.02, 0.02];
const EYE_ALBEDO: [f64; 3] = [0.30, 0.26, 0.24];

const SKIN: V3 = [0.55, 0.36, 0.27];
const LIP: V3 = [0.42, 0.17, 0.15];
const BROW: V3 = [0.12, 0.08, 0.06];
const LASH: V3 = [0.20, 0.14, 0.11];

fn invalid(detail: impl Into<String>) -> ModelError {
    ModelError::Invalid {
        file: "models/data/face".into(),
        detail: detail.into(),
    }
}

struct ObjMesh {
    p: Vec<V3>,
    uv: Vec<[f64; 2]>,
    faces: Vec<[usize; 3]>,
}

fn parse_obj(text: &str) -> Result<ObjMesh> {
    let mut p = vec![];
    let mut uv = vec![];
    let mut faces = vec![];
    let num = |s: Option<&str>, line: usize| -> Result<f64> {
        s.and_then(|x| x.parse::<f64>().ok())
            .ok_or_else(|| invalid(format!("canonical_face.obj line {line}: bad number")))
    };
    for (ln, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let x = num(it.next(), ln + 1)?;
                let y = num(it.next(), ln + 1)?;
                let z = num(it.next(), ln + 1)?;
                p.push([x * OBJ_TO_MM, y * OBJ_TO_MM, z * OBJ_TO_MM]);
            }
            Some("vt") => {
                let u = num(it.next(), ln + 1)?;
                let v = num(it.next(), ln + 1)?;
                uv.push([u, v]);
            }
            Some("f") => {
                let mut t = [0usize; 3];
                for c in t.iter_mut() {
                    let tok = it.next().ok_or_else(|| {
                        invalid(format!("canonical_face.obj line {}: short face", ln + 1))
                    })?;
                    let mut parts = tok.split('/');
                    let vi: usize = parts.next().and_then(|s| s.parse().ok()).unwrap_or(0);
                    let ti: usize = parts.next().and_then(|s| s.parse().ok()).unwrap_or(vi);
                    if vi == 0 || vi != ti {
                        return Err(invalid(format!(
                            "canonical_face.obj line {}: face corner {tok}: uv index must equal the vertex index",
                            ln + 1
                        )));
                    }
                    *c = vi - 1;
                }
                if it.next().is_some() {
                    return Err(invalid(format!(
                        "canonical_face.obj line {}: not a triangle",
                        ln + 1
                    )));
                }
                faces.push(t);
            }
            _ => {}
        }
    }
    if p.len() != N_VERTICES || uv.len() != N_VERTICES || faces.len() != N_FACES {
        return Err(invalid(format!(
            "canonical_face.obj: {} vertices, {} uvs, {} faces (expected {N_VERTICES}, {N_VERTICES}, {N_FACES})",
            p.len(),
            uv.len(),
            faces.len()
        )));
    }
    Ok(ObjMesh { p, uv, faces })
}

/// `mirror[v]`: the vertex at `v`'s position reflected in x = 0.
fn mirror_map(p: &[V3]) -> Result<Vec<usize>> {
    let mut m = Vec::with_capacity(p.len());
    for (i, q) in p.iter().enumerate() {
        let r = [-q[0], q[1], q[2]];
        let (j, d) = p
            .iter()
            .enumerate()
            .map(|(j, s)| (j, norm(sub(*s, r))))
            .fold(
                (usize::MAX, f64::INFINITY),
                |a, b| if b.1 < a.1 { b } else { a },
            );
        if d > 1e-3 {
            return Err(invalid(format!(
                "vertex {i} has no mirror image (nearest {d} mm away)"
            )));
        }
        m.push(j);
    }
    Ok(m)
}

/// Every contour (side 0 = subject's left, +x; side 1 = right).
struct Contours {
    eye_upper: [Vec<usize>; 2],
    eye_lower: [Vec<usize>; 2],
    brow_upper: [Vec<usize>; 2],
    brow_lower: [Vec<usize>; 2],
    oval: Vec<usize>,
    groups: BTreeMap<String, Vec<usize>>,
}

fn closed(a: &[usize], b: &[usize]) -> Vec<usize> {
    // a from one corner to the other, then b back (without repeating the corners when
    // they are shared).
    let mut l = a.to_vec();
    let inner: Vec<usize> = b.iter().rev().copied().filter(|x| !a.contains(x)).collect();
    l.extend(inner);
    l
}

fn dedup(v: &[usize]) -> Vec<usize> {
    let mut out: Vec<usize> = vec![];
    for &x in v {
        if !out.contains(&x) {
            out.push(x);
        }
    }
    out
}

fn contours(mirror: &[usize]) -> Result<Contours> {
    let json: BTreeMap<String, Vec<usize>> = serde_json::from_str(CONTOURS_JSON)
        .map_err(|e| invalid(format!("landmark_contours.json: {e}")))?;
    let mir = |v: &[usize]| -> Vec<usize> { v.iter().map(|&i| mirror[i]).collect() };
    let eye_upper = [mir(&RIGHT_EYE_UPPER), RIGHT_EYE_UPPER.to_vec()];
    let eye_lower = [mir(&RIGHT_EYE_LOWER), RIGHT_EYE_LOWER.to_vec()];
    let brow_upper = [mir(&RIGHT_BROW_UPPER), RIGHT_BROW_UPPER.to_vec()];
    let brow_lower = [mir(&RIGHT_BROW_LOWER), RIGHT_BROW_LOWER.to_vec()];
    for (a, b) in [
        (&LIPS_UPPER_OUTER[..], &LIPS_LOWER_OUTER[..]),
        (&LIPS_UPPER_INNER[..], &LIPS_LOWER_INNER[..]),
    ] {
        if mir(a) != a.iter().rev().copied().collect::<Vec<_>>()
            || mir(b) != b.iter().rev().copied().collect::<Vec<_>>()
        {
            return Err(invalid("lip contours are not mirror-symmetric"));
        }
    }
    // The JSON lists are the first vertex of each contour segment plus the last endpoint
    // (as in @tensorflow-models/face-landmarks-detection); check that ours agree.
    let get = |k: &str| {
        json.get(k)
            .cloned()
            .ok_or_else(|| invalid(format!("landmark_contours.json lacks {k}")))
    };
    let cat = |parts: &[&[usize]]| parts.concat();
    let expect = [
        (
            "lips",
            cat(&[
                &LIPS_LOWER_OUTER[..10],
                &LIPS_UPPER_OUTER[..10],
                &LIPS_LOWER_INNER[..10],
                &LIPS_UPPER_INNER[..10],
                &[308],
            ]),
        ),
        (
            "rightEye",
            cat(&[&eye_lower[1][..8], &eye_upper[1][..8], &[eye_upper[1][8]]]),
        ),
        (
            "leftEye",
            cat(&[&eye_lower[0][..8], &eye_upper[0][..8], &[eye_upper[0][8]]]),
        ),
        ("rightEyebrow", cat(&[&brow_lower[1][..4], &brow_upper[1]])),
        ("leftEyebrow", cat(&[&brow_lower[0][..4], &brow_upper[0]])),
    ];
    for (k, want) in &expect {
        if &get(k)? != want {
            return Err(invalid(format!(
                "landmark_contours.json: {k} disagrees with the built-in contours"
            )));
        }
    }
    let oval_json = get("faceOval")?;
    let oval = dedup(&oval_json);
    let mut groups = BTreeMap::new();
    let mut put = |k: &str, v: Vec<usize>| {
        groups.insert(k.to_string(), v);
    };
    put("lips_upper_outer", LIPS_UPPER_OUTER.to_vec());
    put("lips_lower_outer", LIPS_LOWER_OUTER.to_vec());
    put("lips_upper_inner", LIPS_UPPER_INNER.to_vec());
    put("lips_lower_inner", LIPS_LOWER_INNER.to_vec());
    put(
        "lips",
        dedup(&cat(&[
            &LIPS_UPPER_OUTER,
            &LIPS_LOWER_OUTER,
            &LIPS_UPPER_INNER,
            &LIPS_LOWER_INNER,
        ])),
    );
    for (s, side) in ["left", "right"].iter().enumerate() {
        put(&format!("{side}_eye_upper"), eye_upper[s].clone());
        put(&format!("{side}_eye_lower"), eye_lower[s].clone());
        put(
            &format!("{side}_eye"),
            dedup(&cat(&[&eye_lower[s], &eye_upper[s]])),
        );
        put(&format!("{side}_eyebrow_upper"), brow_upper[s].clone());
        put(&format!("{side}_eyebrow_lower"), brow_lower[s].clone());
        put(
            &format!("{side}_eyebrow"),
            cat(&[&brow_lower[s], &brow_upper[s]]),
        );
    }
    put("face_oval", oval.clone());
    put("nose_ridge", NOSE_RIDGE.to_vec());
    Ok(Contours {
        eye_upper,
        eye_lower,
        brow_upper,
        brow_lower,
        oval,
        groups,
    })
}

/// Triangle regions: flood fills inside the closed contours.
fn face_regions(faces: &[[usize; 3]], c: &Contours) -> Result<Vec<u16>> {
    use super::geom::inside_loop;
    let n = faces.len();
    let mut labels = vec![0u16; n];
    let seed_between = |lp: &[usize], a: &[usize], b: &[usize]| -> Result<usize> {
        // A triangle on the loop's vertices touching both sides (not only their shared corners).
        let only_a: Vec<usize> = a.iter().copied().filter(|x| !b.contains(x)).collect();
        let only_b: Vec<usize> = b.iter().copied().filter(|x| !a.contains(x)).collect();
        faces
            .iter()
            .position(|t| {
                t.iter().all(|x| lp.contains(x))
                    && t.iter().any(|x| only_a.contains(x))
                    && t.iter().any(|x| only_b.contains(x))
            })
            .ok_or_else(|| invalid("no triangle spans a contour opening"))
    };
    let mut fill = |lp: &[usize], seed: usize, label: u16, max: usize| -> Result<Vec<usize>> {
        let inside = inside_loop(faces, lp, seed);
        if inside.len() > max {
            return Err(invalid(format!(
                "flood fill of region {} escaped its contour",
                REGION_NAMES[label as usize]
            )));
        }
        for &f in &inside {
            labels[f] = label;
        }
        Ok(inside)
    };
    // Lips (inside the outer contour), then the mouth interior on top.
    let inner = closed(&LIPS_LOWER_INNER, &LIPS_UPPER_INNER);
    let outer = closed(&LIPS_LOWER_OUTER, &LIPS_UPPER_OUTER);
    let seed = faces
        .iter()
        .position(|t| t.contains(&13) && t.contains(&14))
        .ok_or_else(|| invalid("no triangle holds both inner-lip vertices 13 and 14"))?;
    fill(&outer, seed, 1, 150)?;
    // (The inner-lip contour must be spanned by triangles, as for the eyes.)
    seed_between(&inner, &LIPS_UPPER_INNER, &LIPS_LOWER_INNER)?;
    fill(&inner, seed, 2, 40)?;
    for s in 0..2 {
        let lp = closed(&c.eye_lower[s], &c.eye_upper[s]);
        let seed = seed_between(&lp, &c.eye_upper[s], &c.eye_lower[s])?;
        fill(&lp, seed, 3 + s as u16, 40)?;
        let lp = closed(&c.brow_lower[s], &c.brow_upper[s]);
        let seed = seed_between(&lp, &c.brow_upper[s], &c.brow_lower[s])?;
        fill(&lp, seed, 5, 40)?;
    }
    Ok(labels)
}

/// One designed component: its name and its raw field (displacement in mm, or colour, per
/// vertex, at +1 standard deviation before orthonormalisation).
struct Field {
    name: &'static str,
    d: Vec<V3>,
}

struct Ctx {
    p: Vec<V3>,
    mirror: Vec<usize>,
    /// Edge graph without the mouth-interior and eye-opening triangles.
    g: Graph,
    c: Contours,
    centre: V3,
    lip_verts: Vec<usize>,
}

impl Ctx {
    fn n(&self) -> usize {
        self.p.len()
    }
    fn mir(&self, set: &[usize]) -> Vec<usize> {
        set.iter().map(|&i| self.mirror[i]).collect()
    }
    fn field(&self, f: impl Fn(usize) -> V3) -> Vec<V3> {
        (0..self.n()).map(f).collect()
    }
    fn kern(&self, seeds: &[usize], r: f64) -> Vec<f64> {
        self.g.kernel(seeds, r)
    }
    /// A field on both sides: `f(v, s)` with `s = +1` on the subject's left (+x), `-1` on
    /// the right, weighted by the kernel of `right_seeds` and of their mirror image; the
    /// right side enters with sign `-1` when `asym`.
    fn sided(
        &self,
        right_seeds: &[usize],
        r: f64,
        asym: bool,
        f: impl Fn(usize, f64) -> V3,
    ) -> Vec<V3> {
        let kr = self.kern(right_seeds, r);
        let kl = self.kern(&self.mir(right_seeds), r);
        let sr = if asym { -1.0 } else { 1.0 };
        self.field(|v| add(scale(f(v, 1.0), kl[v]), scale(f(v, -1.0), kr[v] * sr)))
    }
    /// A kernel-weighted constant displacement.
    fn bump(&self, seeds: &[usize], r: f64, d: V3) -> Vec<V3> {
        let k = self.kern(seeds, r);
        self.field(|v| scale(d, k[v]))
    }
    fn both(&self, right: &[usize]) -> Vec<usize> {
        let mut s = right.to_vec();
        s.extend(self.mir(right));
        dedup(&s)
    }

    /// Lower-jaw weight: 1 on the lower lip and the lower face oval, 0 on the upper lip,
    /// the nose and above, harmonic in between.
    fn jaw_weight(&self) -> Vec<f64> {
        let n = self.n();
        let mut fixed: Vec<Option<[f64; 1]>> = vec![None; n];
        let corners = [61usize, 291, 78, 308];
        for (f, q) in fixed.iter_mut().zip(&self.p) {
            if q[1] > -12.0 {
                *f = Some([0.0]);
            }
        }
        for &v in &self.c.oval {
            let y = self.p[v][1];
            fixed[v] = Some([smoothstep((5.0 - y) / 60.0)]);
        }
        for &v in LIPS_UPPER_OUTER.iter().chain(&LIPS_UPPER_INNER) {
            if !corners.contains(&v) {
                fixed[v] = Some([0.0]);
            }
        }
        for &v in LIPS_LOWER_OUTER.iter().chain(&LIPS_LOWER_INNER) {
            if !corners.contains(&v) {
                fixed[v] = Some([1.0]);
            }
        }
        self.g.harmonic(&fixed).into_iter().map(|x| x[0]).collect()
    }

    /// Upper-lip weight: 1 on the upper lip contours, 0 on the lower lip, the face oval and
    /// above the nose base, harmonic in between.
    fn upper_lip_weight(&self) -> Vec<f64> {
        let n = self.n();
        let mut fixed: Vec<Option<[f64; 1]>> = vec![None; n];
        let corners = [61usize, 291, 78, 308];
        for (f, q) in fixed.iter_mut().zip(&self.p) {
            if q[1] > -12.0 {
                *f = Some([0.0]);
            }
        }
        for &v in &self.c.oval {
            fixed[v] = Some([0.0]);
        }
        for &v in LIPS_LOWER_OUTER.iter().chain(&LIPS_LOWER_INNER) {
            if !corners.contains(&v) {
                fixed[v] = Some([0.0]);
            }
        }
        for &v in LIPS_UPPER_OUTER.iter().chain(&LIPS_UPPER_INNER) {
            if !corners.contains(&v) {
                fixed[v] = Some([1.0]);
            }
        }
        self.g.harmonic(&fixed).into_iter().map(|x| x[0]).collect()
    }

    /// Eyelid motion of one side, harmonic around the eye: upper-lid contour vertex `j`
    /// moves `up_frac` of the way to lower-lid vertex `j`, the lower lid `lo_frac` of the way
    /// to the upper lid; the two eye corners follow their upper-lid neighbours by
    /// `corner_frac` of their displacement (so the corner wedges do not fold); the brow and
    /// everything farther than `radius` from the eye stay.
    fn eyelids(
        &self,
        side: usize,
        up_frac: f64,
        lo_frac: f64,
        corner_frac: f64,
        radius: f64,
    ) -> Vec<V3> {
        let n = self.n();
        let up = &self.c.eye_upper[side];
        let lo = &self.c.eye_lower[side];
        let ring = dedup(&[up.as_slice(), lo.as_slice()].concat());
        let d = self.g.geodesic(&ring);
        let mut fixed: Vec<Option<V3>> = vec![None; n];
        for v in 0..n {
            if d[v] >= radius {
                fixed[v] = Some([0.0; 3]);
            }
        }
        for &v in self.c.brow_upper[side]
            .iter()
            .chain(&self.c.brow_lower[side])
        {
            fixed[v] = Some([0.0; 3]);
        }
        let last = up.len() - 1;
        for (j, (&u, &l)) in up.iter().zip(lo).enumerate() {
            if j == 0 || j == last {
                continue;
            }
            let gap = sub(self.p[l], self.p[u]);
            fixed[u] = Some(scale(gap, up_frac));
            fixed[l] = Some(scale(gap, -lo_frac));
        }
        fixed[up[0]] = Some(scale(fixed[up[1]].expect("set"), corner_frac));
        fixed[up[last]] = Some(scale(fixed[up[last - 1]].expect("set"), corner_frac));
        self.g.harmonic(&fixed)
    }

    /// Vertices of the lips and mouth-interior triangles.
    fn lip_vertices(&self) -> Vec<usize> {
        self.lip_verts.clone()
    }
}

fn rigid_modes(p: &[V3], c: V3) -> Vec<Vec<f64>> {
    let mut modes = vec![];
    for axis in 0..3 {
        let mut e = [0.0; 3];
        e[axis] = 1.0;
        modes.push(p.iter().flat_map(|_| e).collect::<Vec<f64>>());
    }
    for axis in 0..3 {
        let mut w = [0.0; 3];
        w[axis] = 1.0;
        modes.push(
            p.iter()
                .flat_map(|&q| cross(w, sub(q, c)))
                .collect::<Vec<f64>>(),
        );
    }
    // Orthonormalise the rigid modes themselves.
    gram_schmidt(&[], &modes)
        .expect("rigid modes of a 3-D mesh are independent")
        .0
}

fn identity_fields(x: &Ctx) -> Vec<Field> {
    let c = x.centre;
    let p = &x.p;
    let sig = |t: f64| 1.0 / (1.0 + (-t).exp());
    let mut f = vec![];
    let mut push = |name: &'static str, d: Vec<V3>| f.push(Field { name, d });

    // Global shape.
    push("face_width", x.field(|v| [0.045 * p[v][0], 0.0, 0.0]));
    push(
        "face_height",
        x.field(|v| [0.0, 0.04 * (p[v][1] - c[1]), 0.0]),
    );
    push(
        "face_depth",
        x.field(|v| [0.0, 0.0, 0.05 * (p[v][2] - c[2])]),
    );
    push(
        "face_taper",
        x.field(|v| [0.035 * p[v][0] * (p[v][1] - c[1]) / 88.0, 0.0, 0.0]),
    );
    push(
        "face_roundness",
        x.field(|v| [0.0, 0.0, -3.0 * (p[v][0] / 77.0).powi(2)]),
    );
    push(
        "face_profile",
        x.field(|v| [0.0, 0.0, -3.0 * ((p[v][1] - c[1]) / 88.0).powi(2)]),
    );
    push(
        "lower_face_height",
        x.field(|v| [0.0, -4.0 * smoothstep((-21.0 - p[v][1]) / 70.0), 0.0]),
    );
    push(
        "forehead_height",
        x.field(|v| [0.0, 3.5 * smoothstep((p[v][1] - 40.0) / 40.0), 0.0]),
    );
    push(
        "width_asym",
        x.field(|v| [0.035 * p[v][0] * sig(p[v][0] / 8.0), 0.0, 0.0]),
    );
    push(
        "lower_face_shift",
        x.field(|v| [2.5 * smoothstep((-21.0 - p[v][1]) / 70.0), 0.0, 0.0]),
    );

    // Nose.
    push(
        "nose_length",
        x.bump(&x.both(NOSE_TIP), 20.0, [0.0, -2.5, 0.0]),
    );
    push(
        "nose_projection",
        x.bump(&x.both(NOSE_TIP), 24.0, [0.0, 0.0, 3.0]),
    );
    push(
        "nose_width",
        x.sided(NOSE_ALA, 14.0, false, |_, s| [1.5 * s, 0.0, 0.0]),
    );
    push("nose_bridge", x.bump(NOSE_BRIDGE, 16.0, [0.0, 0.0, 2.5]));
    push(
        "nose_tip_rotation",
        x.bump(&x.both(NOSE_TIP), 12.0, [0.0, 2.0, -1.0]),
    );
    let nose: Vec<usize> = x.both(&[NOSE_TIP, NOSE_BRIDGE, NOSE_ALA].concat());
    let cn = centroid(p, &nose);
    let kn = x.kern(&nose, 14.0);
    push("nose_size", x.field(|v| scale(sub(p[v], cn), 0.06 * kn[v])));
    push("nose_deviation", x.bump(&nose, 14.0, [2.0, 0.0, 0.0]));
    push(
        "nostril_height",
        x.bump(&x.both(SUBNASALE), 12.0, [0.0, 1.0, 0.4]),
    );

    // Mouth.
    let lips = x.lip_vertices();
    push(
        "mouth_width",
        x.sided(MOUTH_CORNER, 20.0, false, |_, s| [2.0 * s, 0.0, 0.0]),
    );
    let upper_lip: Vec<usize> = LIPS_UPPER_OUTER[1..10].to_vec();
    let lower_lip: Vec<usize> = LIPS_LOWER_OUTER[1..10].to_vec();
    push(
        "upper_lip_thickness",
        x.bump(&upper_lip, 10.0, [0.0, 1.0, 0.7]),
    );
    push(
        "lower_lip_thickness",
        x.bump(&lower_lip, 10.0, [0.0, -1.0, 0.7]),
    );
    push("mouth_height", x.bump(&lips, 25.0, [0.0, 2.0, 0.0]));
    push("mouth_protrusion", x.bump(&lips, 28.0, [0.0, 0.0, 2.5]));
    push("mouth_shift", x.bump(&lips, 18.0, [2.0, 0.0, 0.0]));
    push(
        "mouth_corner_asym",
        x.sided(MOUTH_CORNER, 18.0, true, |_, _| [0.0, 1.0, 0.0]),
    );

    // Chin and jaw.
    push("chin_height", x.bump(&x.both(CHIN), 25.0, [0.0, -3.0, 0.0]));
    push(
        "chin_projection",
        x.bump(&x.both(CHIN), 25.0, [0.0, 0.0, 3.5]),
    );
    let kc = x.kern(&x.both(CHIN), 25.0);
    push(
        "chin_width",
        x.field(|v| [0.15 * p[v][0] * kc[v], 0.0, 0.0]),
    );
    push(
        "chin_deviation",
        x.bump(&x.both(CHIN), 25.0, [2.5, 0.0, 0.0]),
    );
    push(
        "jaw_width",
        x.sided(JAW_ANGLE, 28.0, false, |_, s| [4.0 * s, 0.0, 0.0]),
    );
    push(
        "jaw_angle_height",
        x.sided(JAW_ANGLE, 28.0, false, |_, _| [0.0, 3.0, 0.0]),
    );
    push(
        "jaw_depth",
        x.sided(JAW_ANGLE, 28.0, false, |_, _| [0.0, 0.0, -3.0]),
    );
    push(
        "jaw_width_asym",
        x.sided(JAW_ANGLE, 28.0, true, |_, s| [3.0 * s, 0.0, 0.0]),
    );

    // Cheeks and temples.
    push(
        "cheekbone_width",
        x.sided(CHEEKBONE, 22.0, false, |_, s| [3.0 * s, 0.0, 0.0]),
    );
    push(
        "cheekbone_height",
        x.sided(CHEEKBONE, 22.0, false, |_, _| [0.0, 2.5, 0.0]),
    );
    push(
        "cheek_fullness",
        x.sided(CHEEK, 25.0, false, |_, _| [0.0, 0.0, 3.0]),
    );
    push(
        "cheek_hollow",
        x.sided(LOWER_CHEEK, 20.0, false, |_, s| [-s, 0.0, -3.0]),
    );
    push(
        "cheekbone_asym",
        x.sided(CHEEKBONE, 22.0, true, |_, s| [2.5 * s, 0.0, 0.0]),
    );
    push(
        "temple_width",
        x.sided(TEMPLE, 25.0, false, |_, s| [3.0 * s, 0.0, 0.0]),
    );
    push(
        "nasolabial_depth",
        x.sided(NASOLABIAL, 14.0, false, |_, _| [0.0, 0.0, 2.0]),
    );

    // Eyes.
    let eye_r: Vec<usize> = dedup(&[&RIGHT_EYE_UPPER[..], &RIGHT_EYE_LOWER].concat());
    let ce_r = centroid(p, &eye_r);
    let ce = |s: f64| [s * ce_r[0].abs(), ce_r[1], ce_r[2]];
    push(
        "eye_separation",
        x.sided(&eye_r, 16.0, false, |_, s| [1.5 * s, 0.0, 0.0]),
    );
    push(
        "eye_height",
        x.sided(&eye_r, 16.0, false, |_, _| [0.0, 1.5, 0.0]),
    );
    push(
        "eye_size",
        x.sided(&eye_r, 12.0, false, |v, s| scale(sub(p[v], ce(s)), 0.08)),
    );
    push(
        "eye_depth",
        x.sided(&eye_r, 18.0, false, |_, _| [0.0, 0.0, -2.0]),
    );
    push(
        "eye_tilt",
        x.sided(&eye_r, 10.0, false, |v, s| {
            let r = sub(p[v], ce(s));
            [-0.08 * s * r[1], 0.08 * s * r[0], 0.0]
        }),
    );
    push(
        "eye_height_asym",
        x.sided(&eye_r, 16.0, true, |_, _| [0.0, 1.2, 0.0]),
    );
    push(
        "eye_size_asym",
        x.sided(&eye_r, 12.0, true, |v, s| scale(sub(p[v], ce(s)), 0.06)),
    );

    // Brows and forehead.
    let brow_r: Vec<usize> = [&RIGHT_BROW_UPPER[..], &RIGHT_BROW_LOWER].concat();
    let cb_r = centroid(p, &brow_r);
    let cb = |s: f64| [s * cb_r[0].abs(), cb_r[1], cb_r[2]];
    push(
        "brow_height",
        x.sided(&brow_r, 18.0, false, |_, _| [0.0, 2.5, 0.0]),
    );
    push(
        "brow_ridge",
        x.sided(&brow_r, 18.0, false, |_, _| [0.0, 0.0, 3.0]),
    );
    push(
        "brow_tilt",
        x.sided(&brow_r, 14.0, false, |v, s| {
            let r = sub(p[v], cb(s));
            [-0.08 * s * r[1], 0.08 * s * r[0], 0.0]
        }),
    );
    push(
        "brow_separation",
        x.sided(&brow_r, 14.0, false, |_, s| [2.5 * s, 0.0, 0.0]),
    );
    push(
        "brow_height_asym",
        x.sided(&brow_r, 14.0, true, |_, _| [0.0, 2.5, 0.0]),
    );
    push(
        "forehead_slope",
        x.field(|v| [0.0, 0.0, -3.0 * smoothstep((p[v][1] - 35.0) / 50.0)]),
    );
    push(
        "forehead_width",
        x.field(|v| {
            [
                0.05 * p[v][0] * smoothstep((p[v][1] - 35.0) / 45.0),
                0.0,
                0.0,
            ]
        }),
    );
    let kf = x.kern(&x.both(FOREHEAD), 35.0);
    push(
        "forehead_roundness",
        x.field(|v| [0.0, 0.0, -2.5 * (p[v][0] / 50.0).powi(2) * kf[v]]),
    );
    f
}

fn expression_fields(x: &Ctx) -> Vec<Field> {
    let p = &x.p;
    let mut f = vec![];
    let mut push = |name: &'static str, d: Vec<V3>| f.push(Field { name, d });
    let w_jaw = x.jaw_weight();
    let w_up = x.upper_lip_weight();

    // Jaw drop: a rotation of the lower jaw about a transverse axis through an effective
    // hinge (the instantaneous centre of the mandible's rotation-plus-glide), weighted by the
    // lower-jaw weight, scaled so that the lower-lip midpoint (vertex 14) moves 5 mm; the
    // upper lip rises by 0.8 mm.
    let hinge = [0.0, -20.0, -20.0];
    let rot = |v: usize| cross([1.0, 0.0, 0.0], sub(p[v], hinge));
    let theta = 5.0 / norm(rot(14));
    push(
        "jaw_open",
        x.field(|v| {
            add(
                scale(rot(v), theta * w_jaw[v]),
                [0.0, 0.8 * w_up[v], 0.2 * w_up[v]],
            )
        }),
    );
    // Eyelids: at +2 sigma the upper lid reaches 90% of the way to the lower lid.
    push("eye_close_left", x.eyelids(0, 0.45, 0.0, 0.6, 18.0));
    push("eye_close_right", x.eyelids(1, 0.45, 0.0, 0.6, 18.0));
    let smile = |asym: bool| {
        let corner = x.sided(MOUTH_CORNER, 25.0, asym, |_, s| [2.5 * s, 2.5, -1.5]);
        let cheek = x.sided(CHEEK, 20.0, asym, |_, s| [0.5 * s, 1.5, 1.0]);
        corner
            .iter()
            .zip(&cheek)
            .map(|(&a, &b)| add(a, b))
            .collect::<Vec<V3>>()
    };
    push("smile", smile(false));
    let brows: Vec<usize> = x.both(&[&RIGHT_BROW_UPPER[..], &RIGHT_BROW_LOWER].concat());
    push("brow_raise", x.bump(&brows, 25.0, [0.0, 3.0, 0.3]));
    push(
        "brow_frown",
        x.sided(&[107, 66, 55, 65], 15.0, false, |_, s| {
            [-1.5 * s, -2.0, 0.5]
        }),
    );
    let lips = x.lip_vertices();
    let fwd = x.bump(&lips, 14.0, [0.0, 0.0, 3.0]);
    let inward = x.sided(MOUTH_CORNER, 15.0, false, |_, s| [-3.0 * s, 0.0, 1.0]);
    push(
        "mouth_pucker",
        fwd.iter().zip(&inward).map(|(&a, &b)| add(a, b)).collect(),
    );
    push(
        "mouth_frown",
        x.sided(MOUTH_CORNER, 20.0, false, |_, s| [0.5 * s, -2.5, -0.5]),
    );
    let upper_lip: Vec<usize> = LIPS_UPPER_OUTER[1..10].to_vec();
    let lip_up = x.bump(&upper_lip, 10.0, [0.0, 1.8, 0.5]);
    let ala_up = x.sided(NOSE_ALA, 8.0, false, |_, _| [0.0, 1.0, 0.0]);
    push(
        "upper_lip_raise",
        lip_up
            .iter()
            .zip(&ala_up)
            .map(|(&a, &b)| add(a, b))
            .collect(),
    );
    push(
        "cheek_puff",
        x.sided(LOWER_CHEEK, 25.0, false, |_, s| [3.0 * s, 0.0, 2.0]),
    );
    push("jaw_left", x.field(|v| [3.0 * w_jaw[v], 0.0, 0.0]));
    push("smile_asym", smile(true));
    push(
        "brow_raise_asym",
        x.sided(
            &[&RIGHT_BROW_UPPER[..], &RIGHT_BROW_LOWER].concat(),
            25.0,
            true,
            |_, _| [0.0, 2.5, 0.2],
        ),
    );
    // Lower lids up by 20% of the lid gap (both eyes).
    let l = x.eyelids(0, 0.0, 0.2, 0.0, 14.0);
    let r = x.eyelids(1, 0.0, 0.2, 0.0, 14.0);
    push(
        "eye_squint",
        l.iter().zip(&r).map(|(&a, &b)| add(a, b)).collect(),
    );
    push(
        "mouth_stretch",
        x.sided(MOUTH_CORNER, 18.0, false, |_, s| [3.0 * s, -0.5, -1.0]),
    );
    push("jaw_forward", x.field(|v| [0.0, 0.0, 2.5 * w_jaw[v]]));
    f
}

fn albedo_mean_and_fields(x: &Ctx, labels: &[u16], faces: &[[usize; 3]]) -> (Vec<V3>, Vec<Field>) {
    let n = x.n();
    // Fraction of each vertex's triangles that are lips or mouth interior.
    let mut lip_n = vec![0.0; n];
    let mut all_n = vec![0.0; n];
    for (t, &l) in faces.iter().zip(labels) {
        for &v in t {
            all_n[v] += 1.0;
            if l == 1 || l == 2 {
                lip_n[v] += 1.0;
            }
        }
    }
    let w_lip: Vec<f64> = (0..n)
        .map(|v| {
            if all_n[v] > 0.0 {
                lip_n[v] / all_n[v]
            } else {
                0.0
            }
        })
        .collect();
    let brow_set: Vec<usize> = x.both(&[&RIGHT_BROW_UPPER[..], &RIGHT_BROW_LOWER].concat());
    let w_brow = x.kern(&brow_set, 5.0);
    let lash_set: Vec<usize> = x.both(&RIGHT_EYE_UPPER[1..8]);
    let w_lash = x.kern(&lash_set, 2.0);
    let mix = |a: V3, b: V3, t: f64| add(scale(a, 1.0 - t), scale(b, t));
    let mean: Vec<V3> = (0..n)
        .map(|v| {
            let c = mix(SKIN, LIP, w_lip[v]);
            let c = mix(c, BROW, 0.85 * w_brow[v]);
            mix(c, LASH, 0.5 * w_lash[v])
        })
        .collect();
    let m = &mean;
    let mut f = vec![];
    let mut push = |name: &'static str, d: Vec<V3>| f.push(Field { name, d });
    let tint = |k: V3| x.field(|v| [m[v][0] * k[0], m[v][1] * k[1], m[v][2] * k[2]]);
    // Skin tone: melanin darkens blue and green more than red (the main axis of human skin
    // colour), then overall brightness, then haemoglobin redness, then a skin-only yellow.
    push("melanin", tint([-0.22, -0.28, -0.34]));
    push("brightness", tint([0.15, 0.15, 0.15]));
    push("redness", tint([0.05, -0.04, -0.02]));
    // Skin only (not lips or brows), so independent of the three global tints above.
    push(
        "skin_yellowness",
        x.field(|v| {
            let w = (1.0 - w_lip[v]) * (1.0 - w_brow[v]);
            [m[v][0] * 0.02 * w, m[v][1] * 0.025 * w, m[v][2] * -0.05 * w]
        }),
    );
    push(
        "lip_redness",
        x.field(|v| scale([0.06, -0.03, -0.01], w_lip[v])),
    );
    push(
        "lip_darkness",
        x.field(|v| scale([-0.06, -0.04, -0.03], w_lip[v])),
    );
    push(
        "brow_darkness",
        x.field(|v| scale([-0.06, -0.04, -0.03], w_brow[v])),
    );
    let cheek = x.sided(CHEEK, 25.0, false, |_, _| [0.03, -0.008, -0.004]);
    push("cheek_redness", cheek);
    push(
        "nose_redness",
        x.bump(&x.both(NOSE_TIP), 14.0, [0.03, -0.008, -0.004]),
    );
    // Beard shadow: chin, jaw and upper lip, not the lips themselves.
    let beard_seeds: Vec<usize> = x.both(&[CHIN, JAW_ANGLE, SUBNASALE, &[164, 167, 165]].concat());
    let kb = x.kern(&beard_seeds, 30.0);
    push(
        "beard_shadow",
        x.field(|v| scale([-0.04, -0.035, -0.025], kb[v] * (1.0 - w_lip[v]))),
    );
    let under_eye: Vec<usize> = RIGHT_EYE_LOWER[1..8].to_vec();
    push(
        "under_eye_darkness",
        x.sided(&under_eye, 10.0, false, |_, _| [-0.04, -0.04, -0.02]),
    );
    push(
        "forehead_brightness",
        x.bump(&x.both(FOREHEAD), 35.0, [0.04, 0.035, 0.03]),
    );
    let upper_lid: Vec<usize> = RIGHT_EYE_UPPER[1..8].to_vec();
    push(
        "eyelid_shadow",
        x.sided(&upper_lid, 9.0, false, |_, _| [-0.04, -0.045, -0.04]),
    );
    push(
        "temple_shadow",
        x.sided(TEMPLE, 30.0, false, |_, _| [-0.03, -0.03, -0.02]),
    );
    (mean, f)
}

/// Per-component information for documentation: name, sigma, largest per-vertex change at
/// +1 sigma, RMS per-vertex change at +1 sigma.
#[derive(Clone, Debug)]
pub struct ComponentInfo {
    /// `identity`, `expression` or `albedo`.
    pub kind: &'static str,
    /// Index within its basis.
    pub index: usize,
    /// Component name.
    pub name: String,
    /// Standard deviation of the coefficient (mm for shape, albedo units for albedo).
    pub sigma: f64,
    /// Largest per-vertex displacement (colour change) at +1 sigma.
    pub peak: f64,
    /// Root-mean-square per-vertex displacement (colour change) at +1 sigma.
    pub rms: f64,
}

/// Per-component table of a model (any model with names; unnamed components are `#k`).
pub fn component_table<T: autodiff::Real>(m: &Morphable<T>) -> Vec<ComponentInfo> {
    let mut out = vec![];
    let v = m.n_vertices();
    let mut add_basis = |kind: &'static str,
                         b: ndarray::ArrayView2<'_, T>,
                         s: ndarray::ArrayView1<'_, T>,
                         names: &[String]| {
        for k in 0..b.ncols() {
            let sk = s[k].to_f64c();
            let col = b.column(k);
            let mut peak = 0.0f64;
            let mut sum = 0.0;
            for i in 0..v {
                let d2: f64 = (0..3)
                    .map(|c| (col[3 * i + c].to_f64c() * sk).powi(2))
                    .sum();
                peak = peak.max(d2.sqrt());
                sum += d2;
            }
            out.push(ComponentInfo {
                kind,
                index: k,
                name: names.get(k).cloned().unwrap_or_else(|| format!("#{k}")),
                sigma: sk,
                peak,
                rms: (sum / v as f64).sqrt(),
            });
        }
    };
    add_basis("identity", m.id_basis(), m.sigma_id(), m.id_names());
    add_basis("expression", m.exp_basis(), m.sigma_exp(), m.exp_names());
    add_basis(
        "albedo",
        m.albedo_basis(),
        m.sigma_albedo(),
        m.albedo_names(),
    );
    out
}

fn flatten(d: &[V3]) -> Vec<f64> {
    d.iter().flat_map(|x| x.iter().copied()).collect()
}

/// Orthonormalises `fields` after `prefix`; the basis `[3V, K]` and `sigma_k = r_kk`.
fn orthonormal_basis(
    prefix: &[Vec<f64>],
    fields: &[Field],
) -> Result<(Array2<f64>, Array1<f64>, Vec<String>)> {
    let raw: Vec<Vec<f64>> = fields.iter().map(|f| flatten(&f.d)).collect();
    let (q, r) = gram_schmidt(prefix, &raw).map_err(|k| {
        invalid(format!(
            "component {} is linearly dependent on the earlier ones",
            fields[k].name
        ))
    })?;
    let rows = raw[0].len();
    let mut b = Array2::zeros((rows, q.len()));
    for (k, col) in q.iter().enumerate() {
        // Sign: the orthonormal column points along its field.
        let s = if col.iter().zip(&raw[k]).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
            -1.0
        } else {
            1.0
        };
        for (i, &x) in col.iter().enumerate() {
            b[[i, k]] = s * x;
        }
    }
    Ok((
        b,
        Array1::from(r),
        fields.iter().map(|f| f.name.to_string()).collect(),
    ))
}

/// Builds the shipped face model from the compiled-in MediaPipe mesh and contours,
/// deterministically, in `f64`.
pub fn build_face_model() -> Result<Morphable<f64>> {
    let obj = parse_obj(CANONICAL_OBJ)?;
    let mirror = mirror_map(&obj.p)?;
    let c = contours(&mirror)?;
    let labels = face_regions(&obj.faces, &c)?;
    let cut: Vec<bool> = labels.iter().map(|&l| l == 2 || l == 3 || l == 4).collect();
    let g = Graph::new(&obj.p, &obj.faces, &cut);
    let all: Vec<usize> = (0..obj.p.len()).collect();
    let centre = centroid(&obj.p, &all);
    let mut lip_verts: Vec<usize> = obj
        .faces
        .iter()
        .zip(&labels)
        .filter(|(_, &l)| l == 1 || l == 2)
        .flat_map(|(t, _)| t.iter().copied())
        .collect();
    lip_verts.sort_unstable();
    lip_verts.dedup();
    let x = Ctx {
        p: obj.p.clone(),
        mirror,
        g,
        c,
        centre,
        lip_verts,
    };

    let rigid = rigid_modes(&x.p, [0.0, centre[1], centre[2]]);
    let (id_basis, sigma_id, id_names) = orthonormal_basis(&rigid, &identity_fields(&x))?;
    let (exp_basis, sigma_exp, exp_names) = orthonormal_basis(&[], &expression_fields(&x))?;
    let (mean_alb, alb_fields) = albedo_mean_and_fields(&x, &labels, &obj.faces);
    let (albedo_basis, sigma_albedo, albedo_names) = orthonormal_basis(&[], &alb_fields)?;

    let n = x.n();
    let mean_shape = Array2::from_shape_fn((n, 3), |(i, k)| x.p[i][k]);
    let mean_albedo = Array2::from_shape_fn((n, 3), |(i, k)| mean_alb[i][k]);
    let uvs = Array2::from_shape_fn((n, 2), |(i, k)| obj.uv[i][k]);
    let regions = REGION_NAMES
        .iter()
        .map(|&name| Region {
            name: name.to_string(),
            albedo: match name {
                "mouth_interior" => Some(MOUTH_INTERIOR_ALBEDO),
                "eye_left" | "eye_right" => Some(EYE_ALBEDO),
                _ => None,
            },
            photometric: true,
        })
        .collect();
    let parts = MorphableParts {
        name: "tapestry-face-468".into(),
        description: "Designed 3DMM-style basis on the MediaPipe canonical face mesh (468 vertices, \
                      millimetres, y up, facing +z); see models/data/face/README.md. Mesh and contours: \
                      Apache-2.0, Copyright Google LLC (see NOTICE)."
            .into(),
        mean_shape,
        id_basis,
        sigma_id,
        exp_basis,
        sigma_exp,
        mean_albedo,
        albedo_basis,
        sigma_albedo,
        basis_scaled: false,
        faces: obj.faces.iter().map(|t| [t[0] as u32, t[1] as u32, t[2] as u32]).collect(),
        uvs: Some(uvs),
        landmarks: all,
        landmark_points: vec![],
        landmark_scheme: Some(LandmarkScheme::MediaPipe468),
        landmark_groups: x.c.groups.clone(),
        regions,
        face_regions: labels,
        id_names,
        exp_names,
        albedo_names,
    };
    Morphable::from_parts(parts)
}
