//! Tests of the hard rasterizer: watertightness, near plane, gradients, robustness, determinism.

use std::collections::HashMap;

use autodiff::Real;

use super::hard::rasterize_with;
use super::*;

// ---------------------------------------------------------------- helpers

/// SplitMix64: a tiny deterministic PRNG.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    fn f(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.f()
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm3(a: [f64; 3]) -> [f64; 3] {
    let l = dot3(a, a).sqrt();
    [a[0] / l, a[1] / l, a[2] / l]
}

/// Unit icosphere: an icosahedron subdivided `n` times (20 * 4^n faces), outward CCW faces.
fn icosphere(n: usize) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<[f64; 3]> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|&p| norm3(p))
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..n {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut nf = Vec::with_capacity(f.len() * 4);
        for &[a, b, c] in &f {
            let mut m = |x: u32, y: u32| {
                *mid.entry((x.min(y), x.max(y))).or_insert_with(|| {
                    let (p, q) = (v[x as usize], v[y as usize]);
                    v.push(norm3([p[0] + q[0], p[1] + q[1], p[2] + q[2]]));
                    (v.len() - 1) as u32
                })
            };
            let (ab, bc, ca) = (m(a, b), m(b, c), m(c, a));
            nf.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = nf;
    }
    for face in &mut f {
        let [a, b, c] = face.map(|i| v[i as usize]);
        if dot3(cross3(sub3(b, a), sub3(c, a)), a) < 0.0 {
            face.swap(1, 2);
        }
    }
    (v, f)
}

/// OpenGL perspective * look-at (row-major 4x4).
fn camera(
    eye: [f64; 3],
    at: [f64; 3],
    fovy_deg: f64,
    aspect: f64,
    n: f64,
    fa: f64,
) -> [[f64; 4]; 4] {
    let fwd = norm3(sub3(at, eye));
    let up = if fwd[1].abs() > 0.99 {
        [0.0, 0.0, 1.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let s = norm3(cross3(fwd, up));
    let u = cross3(s, fwd);
    let view = [
        [s[0], s[1], s[2], -dot3(s, eye)],
        [u[0], u[1], u[2], -dot3(u, eye)],
        [-fwd[0], -fwd[1], -fwd[2], dot3(fwd, eye)],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let f = 1.0 / (fovy_deg.to_radians() / 2.0).tan();
    let proj = [
        [f / aspect, 0.0, 0.0, 0.0],
        [0.0, f, 0.0, 0.0],
        [0.0, 0.0, (fa + n) / (n - fa), 2.0 * fa * n / (n - fa)],
        [0.0, 0.0, -1.0, 0.0],
    ];
    let mut m = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            m[i][j] = (0..4).map(|k| proj[i][k] * view[k][j]).sum();
        }
    }
    m
}

fn project<T: Real>(m: &[[f64; 4]; 4], pts: &[[f64; 3]]) -> Vec<[T; 4]> {
    pts.iter()
        .map(|p| {
            let h = [p[0], p[1], p[2], 1.0];
            [0, 1, 2, 3].map(|i| T::from_f64c((0..4).map(|k| m[i][k] * h[k]).sum()))
        })
        .collect()
}

fn settings(w: usize, h: usize, k: usize) -> RasterSettings {
    RasterSettings {
        faces_per_pixel: k,
        ..RasterSettings::new(w, h)
    }
}

fn counts<T: Real>(fr: &Fragments<T>) -> Vec<usize> {
    (0..fr.num_pixels()).map(|p| fr.count(p)).collect()
}

fn pixel_ndc(w: usize, h: usize, p: usize) -> (f64, f64) {
    let (r, c) = (p / w, p % w);
    (
        2.0 * (c as f64 + 0.5) / w as f64 - 1.0,
        1.0 - 2.0 * (r as f64 + 0.5) / h as f64,
    )
}

/// Every fragment is finite and, for perspective-correct barycentrics, `sum b_i clip_i` lies on
/// the pixel's ray with the stored depths (the barycentrics refer to the original triangle).
fn check_consistent<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    fr: &Fragments<T>,
    s: &RasterSettings,
    tol: f64,
) {
    fr.validate().unwrap();
    assert_eq!(fr.k, s.faces_per_pixel);
    for p in 0..fr.num_pixels() {
        let (nx, ny) = pixel_ndc(fr.width, fr.height, p);
        let mut last = f64::NEG_INFINITY;
        for f in fr.iter_pixel(p) {
            let vals: Vec<f64> = f
                .bary
                .iter()
                .chain(&f.dbary_dx.unwrap())
                .chain(&f.dbary_dy.unwrap())
                .chain([&f.depth, &f.view_depth])
                .map(|x| x.to_f64c())
                .collect();
            assert!(
                vals.iter().all(|x| x.is_finite()),
                "non-finite fragment {f:?}"
            );
            let d = f.depth.to_f64c();
            assert!((-1.0..=1.0).contains(&d), "depth {d} out of range");
            assert!(d >= last, "fragments not sorted by depth");
            last = d;
            if !s.perspective_correct {
                continue;
            }
            let b = f.bary.map(|x| x.to_f64c());
            assert!((b[0] + b[1] + b[2] - 1.0).abs() < tol, "bary sum {b:?}");
            assert!(b.iter().all(|&x| x >= -tol), "negative bary {b:?}");
            let face = faces[f.face as usize];
            let mut q = [0.0; 4];
            let mut scale = 0.0f64;
            for i in 0..3 {
                for (k, qk) in q.iter_mut().enumerate() {
                    let c = clip[face[i] as usize][k].to_f64c();
                    *qk += b[i] * c;
                    scale = scale.max(c.abs());
                }
            }
            let w = q[3];
            assert!(w > 0.0);
            let t = tol * scale.max(1.0) / w;
            assert!(
                (q[0] / w - nx).abs() < t && (q[1] / w - ny).abs() < t,
                "off the ray {q:?} vs {nx},{ny}"
            );
            assert!((q[2] / w - d).abs() < t, "depth {} vs {d}", q[2] / w);
            assert!(
                (w - f.view_depth.to_f64c()).abs() < tol * scale.max(1.0),
                "view depth"
            );
        }
    }
}

// ---------------------------------------------------------------- 1. watertightness

fn sphere_watertight<T: Real>() {
    let (v, f) = icosphere(4);
    assert_eq!(f.len(), 5120);
    let (w, h) = (160, 128);
    let m = camera(
        [0.0, 0.0, 3.0],
        [0.0; 3],
        48.9,
        w as f64 / h as f64,
        0.1,
        100.0,
    );
    let clip = project::<T>(&m, &v);
    // Inscribed radius of the polyhedron: distance from the centre to the nearest face plane.
    let r_in = f
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| v[i as usize]);
            dot3(norm3(cross3(sub3(b, a), sub3(c, a))), a)
        })
        .fold(f64::INFINITY, f64::min);
    let culled = rasterize_fragments(
        &clip,
        &f,
        &RasterSettings {
            cull_backfaces: true,
            ..settings(w, h, 4)
        },
    )
    .unwrap();
    let both = rasterize_fragments(&clip, &f, &settings(w, h, 4)).unwrap();
    let (cc, cb) = (counts(&culled), counts(&both));
    let tan = (48.9f64.to_radians() / 2.0).tan();
    let (mut inside, mut boundary) = (0, 0);
    for p in 0..w * h {
        let (nx, ny) = pixel_ndc(w, h, p);
        let d = [nx * tan * w as f64 / h as f64, ny * tan, -1.0];
        // Distance from the sphere centre (0, 0, -3) in view space to the pixel's ray.
        let dist = cross3(d, [0.0, 0.0, -3.0]);
        let dist = dot3(dist, dist).sqrt() / dot3(d, d).sqrt();
        assert!(
            cc[p] <= 1,
            "pixel {p} covered {} times by front faces",
            cc[p]
        );
        // A convex closed mesh: front and back layers cover exactly the same pixels.
        assert_eq!(
            cb[p],
            2 * cc[p],
            "pixel {p}: {} fragments, {} front",
            cb[p],
            cc[p]
        );
        if dist < r_in * 0.995 {
            assert_eq!(cc[p], 1, "hole at interior pixel {p}");
            inside += 1;
        } else if dist > 1.005 {
            assert_eq!(cc[p], 0);
        } else {
            boundary += 1;
        }
        if cb[p] == 2 {
            let (a, b) = (
                both.get(both.pixel_range(p).start),
                both.get(both.pixel_range(p).start + 1),
            );
            assert_eq!(
                a.face,
                culled.nearest(p).unwrap().face,
                "nearest is the front face"
            );
            assert!(a.depth < b.depth);
        }
    }
    assert!(
        inside > 5000 && boundary < inside / 5,
        "inside {inside} boundary {boundary}"
    );
    check_consistent(
        &clip,
        &f,
        &both,
        &settings(w, h, 4),
        if T::NAME == "f32" { 2e-3 } else { 1e-8 },
    );
    // K = 2 gives exactly front and back for interior pixels.
    let k2 = rasterize_fragments(&clip, &f, &settings(w, h, 2)).unwrap();
    assert_eq!(counts(&k2), cb);
}

#[test]
fn watertight_icosphere_f32() {
    sphere_watertight::<f32>();
}

#[test]
fn watertight_icosphere_f64() {
    sphere_watertight::<f64>();
}

/// A 50 x 50 grid of quads (5000 triangles) over more than the screen, jittered interior
/// vertices, random per-vertex w (so the homogeneous math is exercised), random diagonals.
fn grid_mesh<T: Real>(seed: u64, mirror: bool) -> (Vec<[T; 4]>, Vec<[u32; 3]>) {
    let mut rng = Rng(seed);
    let n = 50;
    let mut clip = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            let mut x = -1.05 + 2.1 * i as f64 / n as f64;
            let mut y = -1.05 + 2.1 * j as f64 / n as f64;
            if i > 0 && i < n && j > 0 && j < n {
                x += rng.range(-0.3, 0.3) * 2.1 / n as f64;
                y += rng.range(-0.3, 0.3) * 2.1 / n as f64;
            }
            if mirror {
                x = -x;
            }
            let w = rng.range(0.5, 3.0);
            let z = rng.range(-0.9, 0.9);
            clip.push([x * w, y * w, z * w, w].map(T::from_f64c));
        }
    }
    let mut faces = Vec::new();
    let id = |i: usize, j: usize| (j * (n + 1) + i) as u32;
    for j in 0..n {
        for i in 0..n {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            if rng.below(2) == 0 {
                faces.extend([[a, b, c], [a, c, d]]);
            } else {
                faces.extend([[a, b, d], [b, c, d]]);
            }
        }
    }
    (clip, faces)
}

fn grid_watertight<T: Real>() {
    for (seed, mirror) in [(1, false), (2, true)] {
        let (clip, faces) = grid_mesh::<T>(seed, mirror);
        assert_eq!(faces.len(), 5000);
        let s = settings(200, 150, 4);
        let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
        assert!(
            counts(&fr).iter().all(|&c| c == 1),
            "grid not covered exactly once"
        );
        assert_eq!(fr.covered_pixels(), 200 * 150);
        check_consistent(
            &clip,
            &faces,
            &fr,
            &s,
            if T::NAME == "f32" { 2e-3 } else { 1e-8 },
        );
        // Mirrored faces are clockwise (back faces) and culled.
        let culled = rasterize_fragments(
            &clip,
            &faces,
            &RasterSettings {
                cull_backfaces: true,
                ..s
            },
        )
        .unwrap();
        assert_eq!(culled.len(), if mirror { 0 } else { 200 * 150 });
    }
}

#[test]
fn watertight_jittered_grid_f32() {
    grid_watertight::<f32>();
}

#[test]
fn watertight_jittered_grid_f64() {
    grid_watertight::<f64>();
}

/// Vertices exactly on pixel centres, fans of 8 triangles meeting there and edges through pixel
/// centres: every tie is exact, so this exercises the exact predicates and the top-left rule.
fn pixel_aligned<T: Real>() {
    let (w, h) = (64usize, 32usize);
    let mut clip = Vec::new();
    let mut faces = Vec::new();
    let step = 4i32;
    let (nx, ny) = (20i32, 12i32);
    // Corners at pixel (col, row) = (-8 + 4i, -8 + 4j), centres at +2.
    let vid = |c: i32, r: i32, clip: &mut Vec<[T; 4]>| {
        let x = 2.0 * (c as f64 + 0.5) / w as f64 - 1.0;
        let y = 1.0 - 2.0 * (r as f64 + 0.5) / h as f64;
        // Varied w: with w = 1 or 2 every tie is exact in floating point; with the others the
        // vertices are a rounding error off the pixel centres, where plain f64 edge functions
        // leave holes or double coverage and only the exact predicates are right.
        let wv = [2.0, 1.0, 0.1, 3.0, 0.7, 1.3, 0.3][((c * 7 + r * 3).rem_euclid(7)) as usize];
        clip.push([x * wv, y * wv, 0.0, wv].map(T::from_f64c));
        (clip.len() - 1) as u32
    };
    let mut corner = vec![0u32; ((nx + 1) * (ny + 1)) as usize];
    for j in 0..=ny {
        for i in 0..=nx {
            corner[(j * (nx + 1) + i) as usize] = vid(-8 + step * i, -8 + step * j, &mut clip);
        }
    }
    for j in 0..ny {
        for i in 0..nx {
            let k = |a: i32, b: i32| corner[((j + b) * (nx + 1) + i + a) as usize];
            let m = vid(-8 + step * i + 2, -8 + step * j + 2, &mut clip);
            let (a, b, c, d) = (k(0, 1), k(1, 1), k(1, 0), k(0, 0)); // CCW in NDC (y up)
            faces.extend([[a, b, m], [b, c, m], [c, d, m], [d, a, m]]);
        }
    }
    let s = settings(w, h, 4);
    let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
    assert!(
        counts(&fr).iter().all(|&c| c == 1),
        "pixel-aligned mesh not covered exactly once"
    );
    check_consistent(
        &clip,
        &faces,
        &fr,
        &s,
        if T::NAME == "f32" { 1e-3 } else { 1e-9 },
    );
}

#[test]
fn watertight_pixel_aligned_ties() {
    pixel_aligned::<f32>();
    pixel_aligned::<f64>();
}

// ---------------------------------------------------------------- 2. near plane

fn ground_plane<T: Real>() {
    let (w, h) = (96, 64);
    let eye = [0.0, 1.0, 0.0];
    let (fovy, near) = (60.0f64, 0.1);
    let m = camera(
        eye,
        [0.0, 1.0, -1.0],
        fovy,
        w as f64 / h as f64,
        near,
        1000.0,
    );
    // 7 x 7 quads over [-100, 100]^2 at y = 0: the camera's foot is inside a quad, so triangles
    // have one or two vertices behind the eye (w < 0).
    let n = 7;
    let l = 100.0;
    let mut pts = Vec::new();
    for j in 0..=n {
        for i in 0..=n {
            pts.push([
                -l + 2.0 * l * i as f64 / n as f64,
                0.0,
                -l + 2.0 * l * j as f64 / n as f64,
            ]);
        }
    }
    let mut faces = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let id = |a: usize, b: usize| ((j + b) * (n + 1) + i + a) as u32;
            // Upward-facing (CCW seen from +y).
            faces.extend([
                [id(0, 0), id(0, 1), id(1, 1)],
                [id(0, 0), id(1, 1), id(1, 0)],
            ]);
        }
    }
    let clip = project::<T>(&m, &pts);
    assert!(
        clip.iter().any(|c| c[3].to_f64c() < 0.0),
        "some vertices are behind the eye"
    );
    let s = RasterSettings {
        cull_backfaces: true,
        ..settings(w, h, 2)
    };
    let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
    let tan = (fovy.to_radians() / 2.0).tan();
    let tol = if T::NAME == "f32" { 1e-3 } else { 1e-9 };
    let mut checked = 0;
    for p in 0..w * h {
        let (nx, ny) = pixel_ndc(w, h, p);
        let d = [nx * tan * w as f64 / h as f64, ny * tan, -1.0];
        if d[1] >= 0.0 {
            assert_eq!(fr.count(p), 0, "sky pixel {p} covered");
            continue;
        }
        let t = -eye[1] / d[1];
        let hit = [t * d[0], 0.0, -t];
        if hit[0].abs() > l - 1.0 || t > l - 1.0 {
            continue;
        }
        assert_eq!(fr.count(p), 1, "hole at ground pixel {p}");
        let f = fr.nearest(p).unwrap();
        assert!(
            (f.view_depth.to_f64c() - t).abs() < tol * t,
            "view depth {} vs {t}",
            f.view_depth
        );
        let face = faces[f.face as usize];
        let q = (0..3).fold([0.0; 3], |acc, i| {
            let v = pts[face[i] as usize];
            let b = f.bary[i].to_f64c();
            [acc[0] + b * v[0], acc[1] + b * v[1], acc[2] + b * v[2]]
        });
        let err = dot3(sub3(q, hit), sub3(q, hit)).sqrt();
        assert!(err < tol * 10.0 * t, "bary point {q:?} vs hit {hit:?}");
        checked += 1;
    }
    assert!(checked > w * h / 3, "{checked}");
    check_consistent(
        &clip,
        &faces,
        &fr,
        &s,
        if T::NAME == "f32" { 5e-3 } else { 1e-7 },
    );
    // Without culling and in screen-space mode it is still finite and hole-free.
    for persp in [true, false] {
        let s2 = RasterSettings {
            perspective_correct: persp,
            ..settings(w, h, 2)
        };
        let fr2 = rasterize_fragments(&clip, &faces, &s2).unwrap();
        assert_eq!(counts(&fr2), counts(&fr));
        check_consistent(&clip, &faces, &fr2, &s2, 1e-3);
    }
}

#[test]
fn near_plane_ground_f32() {
    ground_plane::<f32>();
}

#[test]
fn near_plane_ground_f64() {
    ground_plane::<f64>();
}

fn near_plane_corners<T: Real>() {
    let s = settings(32, 32, 2);
    let m = camera([0.0; 3], [0.0, 0.0, -1.0], 60.0, 1.0, 0.1, 100.0);
    // Wholly behind the camera (w < 0), and wholly between the eye and the near plane.
    for z in [5.0, -0.05] {
        let clip = project::<T>(&m, &[[-1.0, -1.0, z], [1.0, -1.0, z], [0.0, 1.0, z]]);
        assert!(rasterize_fragments(&clip, &[[0, 1, 2]], &s)
            .unwrap()
            .is_empty());
    }
    // A triangle through the eye (seen edge-on) and one containing it: nothing, no NaN.
    let clip = project::<T>(&m, &[[0.0, -1.0, 1.0], [0.0, -1.0, -1.0], [0.0, 1.0, -1.0]]);
    assert!(rasterize_fragments(&clip, &[[0, 1, 2]], &s)
        .unwrap()
        .is_empty());
    // Vertices at w = 1e-12, 0, -1e-12 and w = 1e-12 with z on the near plane.
    for (wv, zv) in [
        (1e-12, 0.0),
        (0.0, 0.0),
        (-1e-12, 0.0),
        (1e-12, -1e-12),
        (1e-300, 0.0),
    ] {
        let clip: Vec<[T; 4]> = [
            [0.5, 0.5, zv, wv],
            [-0.5, -0.5, 0.0, 1.0],
            [0.5, -0.5, 0.5, 1.0],
        ]
        .iter()
        .map(|c| c.map(T::from_f64c))
        .collect();
        for persp in [true, false] {
            let s = RasterSettings {
                perspective_correct: persp,
                ..s
            };
            let fr = rasterize_fragments(&clip, &[[0, 1, 2], [0, 2, 1]], &s).unwrap();
            assert!(!fr.is_empty());
            check_consistent(&clip, &[[0, 1, 2], [0, 2, 1]], &fr, &s, 1e-2);
            let g = vec![[T::one(); 3]; fr.len()];
            let d = vec![T::one(); fr.len()];
            rasterize_backward(
                &clip,
                &[[0, 1, 2], [0, 2, 1]],
                &fr,
                &g,
                Some(&d),
                Some(&d),
                &s,
            )
            .unwrap();
        }
    }
    // Two vertices behind the eye, one in front: a clipped triangle whose barycentrics refer to
    // the original vertices (checked by check_consistent's ray test).
    let pts = [[-2.0, -1.0, 3.0], [2.0, -1.0, 3.0], [0.0, 0.5, -4.0]];
    let clip = project::<T>(&m, &pts);
    let fr = rasterize_fragments(&clip, &[[0, 1, 2]], &s).unwrap();
    assert!(fr.len() > 100, "{}", fr.len());
    check_consistent(
        &clip,
        &[[0, 1, 2]],
        &fr,
        &s,
        if T::NAME == "f32" { 1e-3 } else { 1e-9 },
    );
    // And one behind, two in front.
    let pts = [[-2.0, -1.0, -3.0], [2.0, -1.0, -3.0], [0.0, 0.5, 4.0]];
    let clip = project::<T>(&m, &pts);
    let fr = rasterize_fragments(&clip, &[[0, 1, 2]], &s).unwrap();
    assert!(fr.len() > 100);
    check_consistent(
        &clip,
        &[[0, 1, 2]],
        &fr,
        &s,
        if T::NAME == "f32" { 1e-3 } else { 1e-9 },
    );
}

#[test]
fn near_plane_corner_cases() {
    near_plane_corners::<f32>();
    near_plane_corners::<f64>();
}

// ---------------------------------------------------------------- 3. gradients

/// Random small perspective scene: a few triangles plus one crossing the near plane.
fn small_scene(seed: u64) -> (Vec<[f64; 4]>, Vec<[u32; 3]>) {
    let mut rng = Rng(seed);
    let m = camera([0.0, 0.0, 3.0], [0.0; 3], 50.0, 1.0, 0.5, 20.0);
    let mut pts = Vec::new();
    let mut faces = Vec::new();
    for t in 0..5u32 {
        let c = [
            rng.range(-0.6, 0.6),
            rng.range(-0.6, 0.6),
            rng.range(-1.0, 1.0),
        ];
        for _ in 0..3 {
            pts.push([
                c[0] + rng.range(-0.8, 0.8),
                c[1] + rng.range(-0.8, 0.8),
                c[2] + rng.range(-0.5, 0.5),
            ]);
        }
        faces.push([3 * t, 3 * t + 1, 3 * t + 2]);
    }
    // Crosses the near plane (z_view = 2.5) and the eye plane.
    pts.extend([[-3.0, -1.5, 4.0], [1.0, 1.2, 2.2], [0.8, -1.0, -1.5]]);
    faces.push([15, 16, 17]);
    (project::<f64>(&m, &pts), faces)
}

fn gradcheck(persp: bool, seed: u64) {
    let (clip, faces) = small_scene(seed);
    let s = RasterSettings {
        perspective_correct: persp,
        ..settings(24, 20, 3)
    };
    let base = rasterize_fragments(&clip, &faces, &s).unwrap();
    let n = base.len();
    let mut rng = Rng(seed + 100);
    let gb: Vec<[f64; 3]> = (0..n)
        .map(|_| {
            [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
            ]
        })
        .collect();
    let gd: Vec<f64> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
    let gw: Vec<f64> = (0..n).map(|_| rng.range(-1.0, 1.0)).collect();
    let h = 1e-6;
    let mut runs = Vec::new();
    for v in 0..clip.len() {
        for q in 0..4 {
            let mut pair = Vec::new();
            for sign in [1.0, -1.0] {
                let mut c = clip.clone();
                c[v][q] += sign * h;
                pair.push(rasterize_fragments(&c, &faces, &s).unwrap());
            }
            runs.push(pair);
        }
    }
    // Interior fragments: same faces in the same order at their pixel under every perturbation.
    let mut stable = vec![true; n];
    for fr in runs.iter().flatten() {
        for p in 0..base.num_pixels() {
            let (a, b) = (base.pixel_range(p), fr.pixel_range(p));
            if base.face[a.clone()] != fr.face[b] {
                stable[a].fill(false);
            }
        }
    }
    let ns = stable.iter().filter(|&&x| x).count();
    assert!(ns > 150, "only {ns} stable fragments of {n}");
    assert!(
        (0..n).any(|i| stable[i] && base.face[i] == 5),
        "the near-crossing triangle has interior fragments"
    );
    let mask = |i: usize| if stable[i] { 1.0 } else { 0.0 };
    let gbm: Vec<[f64; 3]> = (0..n).map(|i| gb[i].map(|x| x * mask(i))).collect();
    let gdm: Vec<f64> = (0..n).map(|i| gd[i] * mask(i)).collect();
    let gwm: Vec<f64> = (0..n).map(|i| gw[i] * mask(i)).collect();
    // Each output separately, then all together.
    type Sel = (bool, bool, bool);
    for (ub, ud, uw) in [
        (true, false, false),
        (false, true, false),
        (false, false, true),
        (true, true, true),
    ] as [Sel; 4]
    {
        let zero3 = vec![[0.0; 3]; n];
        let an = rasterize_backward(
            &clip,
            &faces,
            &base,
            if ub { &gbm } else { &zero3 },
            ud.then_some(&gdm[..]),
            uw.then_some(&gwm[..]),
            &s,
        )
        .unwrap();
        let loss = |fr: &Fragments<f64>| -> f64 {
            let mut l = 0.0;
            for p in 0..base.num_pixels() {
                for (i, j) in base.pixel_range(p).zip(fr.pixel_range(p)) {
                    if !stable[i] {
                        continue;
                    }
                    if ub {
                        l += (0..3).map(|c| gb[i][c] * fr.bary[j][c]).sum::<f64>();
                    }
                    if ud {
                        l += gd[i] * fr.depth[j];
                    }
                    if uw {
                        l += gw[i] * fr.view_depth[j];
                    }
                }
            }
            l
        };
        let scale = an.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(scale > 1e-3, "trivial gradient");
        for v in 0..clip.len() {
            for q in 0..4 {
                let pair = &runs[v * 4 + q];
                let fd = (loss(&pair[0]) - loss(&pair[1])) / (2.0 * h);
                let err = (fd - an[v][q]).abs();
                assert!(
                    err <= 1e-5 * scale.max(1.0),
                    "persp={persp} sel={:?} d/dclip[{v}][{q}]: analytic {} fd {fd}",
                    (ub, ud, uw),
                    an[v][q]
                );
            }
        }
    }
}

#[test]
fn gradcheck_perspective_correct() {
    gradcheck(true, 7);
}

#[test]
fn gradcheck_screen_space() {
    gradcheck(false, 11);
}

/// `dbary_dx` / `dbary_dy` agree with differences of barycentrics between neighbouring pixels of
/// the same face. Along a row or column a perspective-correct barycentric is a ratio of affine
/// functions, for which `b(t + 1) - b(t)` is exactly the geometric mean of `b'(t)` and
/// `b'(t + 1)`; a screen-space one is affine, so the difference equals the derivative.
#[test]
fn bary_derivatives_match_neighbours() {
    let (clip, faces) = small_scene(3);
    for persp in [true, false] {
        let s = RasterSettings {
            perspective_correct: persp,
            ..settings(40, 40, 1)
        };
        let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
        let mut checked = 0;
        for r in 0..39 {
            for c in 0..39 {
                let at = |r: usize, c: usize| fr.nearest(r * 40 + c);
                let Some(m) = at(r, c) else { continue };
                for (n, horizontal) in [(at(r, c + 1), true), (at(r + 1, c), false)] {
                    let Some(n) = n else { continue };
                    if n.face != m.face {
                        continue;
                    }
                    for i in 0..3 {
                        let db = n.bary[i] - m.bary[i];
                        let (d0, d1) = if horizontal {
                            (m.dbary_dx.unwrap()[i], n.dbary_dx.unwrap()[i])
                        } else {
                            (m.dbary_dy.unwrap()[i], n.dbary_dy.unwrap()[i])
                        };
                        if persp {
                            let err = (db * db - d0 * d1).abs();
                            assert!(
                                err <= 1e-9 * (db * db + (d0 * d1).abs()) + 1e-15,
                                "{db} vs {d0}, {d1}"
                            );
                            assert!(db * d0 >= -1e-15, "sign {db} vs {d0}");
                        } else {
                            assert!((db - d0).abs() < 1e-12 && d0 == d1, "{db} vs {d0}, {d1}");
                        }
                    }
                    checked += 1;
                }
            }
        }
        assert!(checked > 200, "{checked}");
    }
}

// ---------------------------------------------------------------- 4. robustness

fn soup<T: Real>(seed: u64, nf: usize) -> (Vec<[T; 4]>, Vec<[u32; 3]>) {
    let mut rng = Rng(seed);
    let mut clip: Vec<[f64; 4]> = Vec::new();
    let mut faces = Vec::new();
    for _ in 0..nf {
        let scale = [1e-3, 1.0, 10.0, 1e3, 1e6][rng.below(5)];
        let base = clip.len() as u32;
        let mut p = [[0.0; 4]; 3];
        for v in &mut p {
            *v = [
                rng.range(-scale, scale),
                rng.range(-scale, scale),
                rng.range(-scale, scale),
                if rng.below(4) == 0 {
                    rng.range(-scale, scale)
                } else {
                    rng.range(0.0, scale)
                },
            ];
        }
        match rng.below(6) {
            0 => p[1] = p[0],                                            // coincident vertices
            1 => p[2] = [0, 1, 2, 3].map(|k| (p[0][k] + p[1][k]) * 0.5), // collinear
            2 => p[2] = [0, 1, 2, 3].map(|k| p[1][k] * (1.0 + 1e-12)),   // sliver
            3 => p[1][3] = [0.0, 1e-12, -1e-12][rng.below(3)],           // w ~ 0
            _ => {}
        }
        clip.extend(p);
        let mut f = [base, base + 1, base + 2];
        match rng.below(8) {
            0 => f[2] = f[0], // repeated index
            1 => f = [base, base + 1, rng.below(clip.len()) as u32],
            _ => {}
        }
        faces.push(f);
    }
    (clip.iter().map(|c| c.map(T::from_f64c)).collect(), faces)
}

/// An icosphere (subdivision 3) seen from a perspective camera plus [`soup`]`(seed, nf)`.
fn sphere_and_soup(seed: u64, nf: usize) -> (Vec<[f64; 4]>, Vec<[u32; 3]>) {
    let (v, f) = icosphere(3);
    let m = camera([0.3, 0.2, 2.5], [0.0; 3], 50.0, 1.0, 0.1, 100.0);
    let mut clip = project::<f64>(&m, &v);
    let mut faces = f;
    let (sc, sf) = soup::<f64>(seed, nf);
    let off = clip.len() as u32;
    clip.extend(sc);
    faces.extend(sf.iter().map(|t| t.map(|i| i + off)));
    (clip, faces)
}

fn soups<T: Real>() {
    for seed in 0..6 {
        let (clip, faces) = soup::<T>(seed, 300);
        for (k, cull, persp) in [(1, false, true), (3, true, true), (2, false, false)] {
            let s = RasterSettings {
                width: 61,
                height: 47,
                faces_per_pixel: k,
                cull_backfaces: cull,
                perspective_correct: persp,
                barycentric_derivatives: true,
            };
            let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
            fr.validate().unwrap();
            let all = fr
                .bary
                .iter()
                .chain(&fr.dbary_dx)
                .chain(&fr.dbary_dy)
                .flatten()
                .chain(&fr.depth)
                .chain(&fr.view_depth);
            assert!(all.into_iter().all(|x| x.is_finite()));
            assert!(fr.face.iter().all(|&f| (f as usize) < faces.len()));
            if T::NAME == "f64" {
                let g = vec![[T::one(); 3]; fr.len()];
                let d = vec![T::one(); fr.len()];
                let gr =
                    rasterize_backward(&clip, &faces, &fr, &g, Some(&d), Some(&d), &s).unwrap();
                assert!(gr.iter().flatten().all(|x| x.is_finite()));
            }
        }
    }
}

#[test]
fn random_soups_f32() {
    soups::<f32>();
}

#[test]
fn random_soups_f64() {
    soups::<f64>();
}

/// The per-thread K-buffer is reused across tiles and reset only where a tile touched it:
/// on one thread (every tile through the same buffer), each pixel's fragments are the `K`
/// nearest (ties: lower face first) of those that each face gives when rasterized alone.
#[test]
fn kbuffer_reuse_matches_faces_alone() {
    let (v, f) = icosphere(2);
    let m = camera([0.3, 0.2, 2.5], [0.0; 3], 50.0, 1.0, 0.1, 100.0);
    let mut clip = project::<f64>(&m, &v);
    let mut faces = f;
    let (sc, sf) = soup::<f64>(3, 120);
    let off = clip.len() as u32;
    clip.extend(sc);
    faces.extend(sf.iter().map(|t| t.map(|i| i + off)));
    for (k, cull) in [(1, false), (2, false), (3, true)] {
        let s = RasterSettings {
            cull_backfaces: cull,
            ..settings(97, 70, k)
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let fr = pool.install(|| rasterize_fragments(&clip, &faces, &s).unwrap());
        let mut cand: Vec<Vec<(f64, u32)>> = vec![Vec::new(); fr.num_pixels()];
        for fi in 0..faces.len() {
            let one = rasterize_fragments(&clip, &faces[fi..fi + 1], &s).unwrap();
            for (p, c) in cand.iter_mut().enumerate() {
                c.extend(one.iter_pixel(p).map(|x| (x.depth, fi as u32)));
            }
        }
        let mut total = 0;
        for (p, c) in cand.iter_mut().enumerate() {
            c.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            c.truncate(k);
            let got: Vec<(f64, u32)> = fr.iter_pixel(p).map(|x| (x.depth, x.face)).collect();
            assert_eq!(&got, c, "pixel {p}, k {k}");
            total += c.len();
        }
        assert!(total > 2000, "{total} fragments");
    }
}

// ---------------------------------------------------------------- 5. determinism

fn bits(fr: &Fragments<f64>) -> Vec<u64> {
    let mut out: Vec<u64> = fr.offsets.iter().map(|&x| x as u64).collect();
    out.extend(fr.face.iter().map(|&x| x as u64));
    out.extend(
        fr.bary
            .iter()
            .chain(&fr.dbary_dx)
            .chain(&fr.dbary_dy)
            .flatten()
            .chain(&fr.depth)
            .chain(&fr.view_depth)
            .map(|x| x.to_bits()),
    );
    out
}

#[test]
fn deterministic_across_thread_counts() {
    let (clip, faces) = sphere_and_soup(5, 200);
    let s = settings(100, 90, 3);
    let run = |n: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap();
        pool.install(|| {
            let fr = rasterize_fragments(&clip, &faces, &s).unwrap();
            let g: Vec<[f64; 3]> = (0..fr.len())
                .map(|i| [(i % 7) as f64 - 3.0, 0.5, -1.0])
                .collect();
            let d: Vec<f64> = (0..fr.len()).map(|i| (i % 5) as f64).collect();
            let gr = rasterize_backward(&clip, &faces, &fr, &g, Some(&d), Some(&d), &s).unwrap();
            (
                bits(&fr),
                gr.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>(),
            )
        })
    };
    let one = run(1);
    assert!(one.0.len() > 20000);
    assert_eq!(run(2), one);
    assert_eq!(run(8), one);
}

/// The AVX2 kernels (K = 1 span test, assembly) and the portable code give bit-identical
/// fragments, for both interpolation modes, with and without derivatives, `K` 1 and 3, in
/// `f32` and `f64`, on a sphere plus a triangle soup (slivers, huge coordinates, `w ~ 0`).
/// Without derivatives the fragments are those with derivatives less the derivative arrays.
#[test]
fn avx2_portable_and_derivative_free_fragments_agree() {
    fn check<T: Real>(clip: &[[T; 4]], faces: &[[u32; 3]]) {
        let mut n = 0;
        for (k, persp, cull) in [(1, true, false), (1, false, true), (3, true, false)] {
            let s = RasterSettings {
                cull_backfaces: cull,
                perspective_correct: persp,
                ..settings(101, 77, k)
            };
            let full = rasterize_with(clip, faces, &s, false).unwrap();
            assert_eq!(rasterize_with(clip, faces, &s, true).unwrap(), full);
            let bare = RasterSettings {
                barycentric_derivatives: false,
                ..s
            };
            let mut want = full.clone();
            (want.dbary_dx, want.dbary_dy) = (Vec::new(), Vec::new());
            for avx2 in [false, true] {
                let fr = rasterize_with(clip, faces, &bare, avx2).unwrap();
                fr.validate().unwrap();
                assert!(!fr.has_derivatives() && full.has_derivatives());
                assert_eq!(fr, want);
                assert_eq!(fr.get(0).dbary_dx, None);
            }
            n += full.len();
        }
        assert!(n > 10000, "{n} fragments");
    }
    let (clip, faces) = sphere_and_soup(7, 300);
    check::<f64>(&clip, &faces);
    let clip32: Vec<[f32; 4]> = clip.iter().map(|c| c.map(|x| x as f32)).collect();
    check::<f32>(&clip32, &faces);
}

/// The direct render ([`render_attributes_direct`]) is the image of the fragments' nearest
/// barycentrics interpolated as `interpolate` does (`b_0 a_0 + b_1 a_1 + b_2 a_2` in `T`) over
/// the background, alpha 1 where covered, bit for bit: `f32` and `f64`, 0, 1, 3 and 5
/// channels, both interpolation modes, culling, AVX2 and portable kernels, 1 and 3 threads, on
/// a sphere plus a triangle soup (slivers, huge coordinates, `w ~ 0`, vertices behind the
/// eye), with `faces_per_pixel` 3 in the settings (ignored: the nearest fragment is drawn).
#[test]
fn direct_render_matches_interpolated_nearest_fragments() {
    fn check<T: Real>(clip: &[[T; 4]], faces: &[[u32; 3]]) {
        let mut covered = 0;
        for c in [0usize, 1, 3, 5] {
            let mut rng = Rng(c as u64 + 11);
            let attrs: Vec<T> = (0..clip.len() * c)
                .map(|_| T::from_f64c(rng.range(-2.0, 3.0)))
                .collect();
            let bg: Vec<T> = (0..c)
                .map(|i| T::from_f64c(0.25 * i as f64 - 0.3))
                .collect();
            for (persp, cull) in [(true, false), (false, true), (true, true)] {
                let s = RasterSettings {
                    cull_backfaces: cull,
                    perspective_correct: persp,
                    barycentric_derivatives: false,
                    ..settings(101, 77, 1)
                };
                let fr = rasterize_with(clip, faces, &s, true).unwrap();
                let mut want = Vec::new();
                for p in 0..fr.num_pixels() {
                    match fr.nearest(p) {
                        Some(f) => {
                            let [a0, a1, a2] =
                                faces[f.face as usize].map(|v| &attrs[v as usize * c..][..c]);
                            let b = f.bary;
                            want.extend(
                                (0..c).map(|ch| b[0] * a0[ch] + b[1] * a1[ch] + b[2] * a2[ch]),
                            );
                            want.push(T::one());
                            covered += 1;
                        }
                        None => {
                            want.extend_from_slice(&bg);
                            want.push(T::zero());
                        }
                    }
                }
                let want: Vec<u64> = want.iter().map(|x| x.to_f64c().to_bits()).collect();
                let s3 = RasterSettings {
                    faces_per_pixel: 3,
                    ..s
                };
                for (avx2, threads) in [(true, 1), (true, 3), (false, 2)] {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(threads)
                        .build()
                        .unwrap();
                    let img = pool.install(|| {
                        direct::render_attributes_with(clip, faces, &attrs, &bg, &s3, avx2)
                    });
                    let got: Vec<u64> =
                        img.unwrap().iter().map(|x| x.to_f64c().to_bits()).collect();
                    assert!(got == want, "c {c} persp {persp} cull {cull} avx2 {avx2}");
                }
            }
        }
        assert!(covered > 20000, "{covered} covered pixels");
    }
    let (clip, faces) = sphere_and_soup(9, 300);
    check::<f64>(&clip, &faces);
    let clip32: Vec<[f32; 4]> = clip.iter().map(|c| c.map(|x| x as f32)).collect();
    check::<f32>(&clip32, &faces);
    // Typed errors: attributes of the wrong length, and the rasterizer's own.
    let s = settings(8, 8, 1);
    assert!(matches!(
        render_attributes_direct(&clip32, &faces, &[0.0f32; 5], &[0.0; 3], &s),
        Err(RasterError::LengthMismatch { .. })
    ));
    let bad = vec![[0u32, 1, clip32.len() as u32]];
    let attrs = vec![0.0f32; clip32.len() * 3];
    assert!(matches!(
        render_attributes_direct(&clip32, &bad, &attrs, &[0.0; 3], &s),
        Err(RasterError::FaceIndexOutOfRange { .. })
    ));
}

// ---------------------------------------------------------------- 6. errors

#[test]
fn typed_errors() {
    let clip = vec![
        [0.0f32, 0.0, 0.0, 1.0],
        [1.0, 0.0, 0.0, 1.0],
        [0.0, 1.0, 0.0, 1.0],
    ];
    let s = RasterSettings::default();
    assert_eq!(
        rasterize_fragments(&clip, &[[0, 1, 3]], &s).unwrap_err(),
        RasterError::FaceIndexOutOfRange {
            face: 0,
            index: 3,
            num_vertices: 3
        }
    );
    let mut bad = clip.clone();
    bad[1][2] = f32::NAN;
    assert!(matches!(
        rasterize_fragments(&bad, &[[0, 1, 2]], &s).unwrap_err(),
        RasterError::NonFiniteVertex { vertex: 1, .. }
    ));
    bad[1][2] = f32::INFINITY;
    assert!(matches!(
        rasterize_fragments(&bad, &[[0, 1, 2]], &s),
        Err(RasterError::NonFiniteVertex { vertex: 1, .. })
    ));
    assert_eq!(
        rasterize_fragments(&clip, &[[0, 1, 2]], &RasterSettings { width: 0, ..s }).unwrap_err(),
        RasterError::EmptyImage {
            width: 0,
            height: 256
        }
    );
    assert!(matches!(
        rasterize_fragments(
            &clip,
            &[[0, 1, 2]],
            &RasterSettings {
                faces_per_pixel: 0,
                ..s
            }
        ),
        Err(RasterError::BadFacesPerPixel { k: 0, .. })
    ));
    assert!(matches!(
        rasterize_fragments(
            &clip,
            &[[0, 1, 2]],
            &RasterSettings {
                width: 1 << 20,
                height: 1 << 12,
                ..s
            }
        ),
        Err(RasterError::ImageTooLarge { .. })
    ));
    assert!(matches!(
        rasterize_fragments(
            &clip,
            &[[0, 1, 2]],
            &RasterSettings {
                width: usize::MAX,
                height: 3,
                ..s
            }
        ),
        Err(RasterError::ImageTooLarge { .. })
    ));
    let fr = rasterize_fragments(&clip, &[[0, 1, 2]], &s).unwrap();
    assert!(!fr.is_empty());
    assert!(matches!(
        rasterize_backward(&clip, &[[0, 1, 2]], &fr, &[], None, None, &s),
        Err(RasterError::LengthMismatch {
            what: "grad_bary",
            ..
        })
    ));
    let g = vec![[0.0f32; 3]; fr.len()];
    assert!(matches!(
        rasterize_backward(&clip, &[[0, 1, 2]], &fr, &g, Some(&[1.0]), None, &s),
        Err(RasterError::LengthMismatch {
            what: "grad_depth",
            ..
        })
    ));
    assert!(matches!(
        rasterize_backward(
            &clip,
            &[[0, 1, 2]],
            &fr,
            &g,
            None,
            None,
            &RasterSettings { width: 8, ..s }
        ),
        Err(RasterError::FragmentsMismatch(_))
    ));
    let msg = rasterize_fragments(&clip, &[[0, 1, 2], [2, 7, 1]], &s)
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("face 1") && msg.contains("vertex 7") && msg.contains('3'),
        "{msg}"
    );
}

#[test]
fn fragment_helpers() {
    let clip = vec![
        [-1.0f64, -1.0, 0.0, 1.0],
        [1.0, -1.0, 0.0, 1.0],
        [-1.0, 1.0, 0.0, 1.0],
    ];
    let s = settings(8, 8, 1);
    let fr = rasterize_fragments(&clip, &[[0, 1, 2]], &s).unwrap();
    // The lower-left half: pixel (row r, col c) is inside iff c < r; the centres with c == r lie
    // exactly on the hypotenuse, a right/bottom edge that the top-left rule excludes.
    assert_eq!(fr.covered_pixels(), 28);
    assert_eq!(fr.len(), 28);
    assert!((0..8).all(|i| fr.count(fr.pixel_index(i, i)) == 0));
    let px = fr.fragment_pixels();
    for (i, &p) in px.iter().enumerate() {
        assert_eq!(fr.pixel_of(i), p as usize);
        assert!(fr.pixel_range(p as usize).contains(&i));
    }
    let p = fr.pixel_index(7, 0);
    assert_eq!(fr.pixel_coords(p), (7, 0));
    let f = fr.nearest(p).unwrap();
    assert_eq!(f.face, 0);
    // Pixel centre (-7/8, -7/8): b = (1 - (x+1)/2 - (y+1)/2, (x+1)/2, (y+1)/2).
    let b = [0.875, 0.0625, 0.0625];
    for i in 0..3 {
        assert!((f.bary[i] - b[i]).abs() < 1e-15);
        assert!((f.dbary_dx.unwrap()[i] - [-0.125, 0.125, 0.0][i]).abs() < 1e-15);
        assert!((f.dbary_dy.unwrap()[i] - [0.125, 0.0, -0.125][i]).abs() < 1e-15);
    }
    assert_eq!(f.depth, 0.0);
    assert_eq!(f.view_depth, 1.0);
    let mut n = 0;
    fr.for_each_covered(|_, r| n += r.len());
    assert_eq!(n, 28);
}
