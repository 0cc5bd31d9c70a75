//! The numerical stability suite: hard inputs through every raster method (`hard`, `tf_mesh`,
//! `opendr`, `nmr`, `deodr`, `softras`, `dibr`), forward and backward. Each case must give finite
//! images and finite gradients with respect to the clip positions and the colours, or a typed
//! error that names the problem; never a panic, a NaN or silent garbage.
//!
//! | case | promise |
//! |---|---|
//! | SoftRas sigma and gamma from 1e-2 to 1e-9, DIB-R delta likewise | finite; at 1e-9 the image equals the hard render (to 1e-3) at pixels 2 px from any edge |
//! | depth ranges 1e-3 to 1e5 (near, far, distance); two faces 1e-6 apart at depth 1e4 | finite; the nearer face wins |
//! | slivers (aspect ratio 1e6), zero-area triangles (collinear, coincident vertices) | finite; zero-area faces produce no fragments |
//! | vertices that coincide in screen space (PyTorch3D issue 110) | finite |
//! | vertices exactly on pixel centres and on 16-px tile borders | finite; a closed quad covers every pixel centre once |
//! | triangles crossing the near plane, `w` = 1e-12, 1e-300, 0, negative | finite; faces behind the eye render nothing |
//! | back faces, with and without culling | culled: nothing; not culled: rendered |
//! | a million faces over one pixel | finite, memory bounded |
//! | empty meshes (no faces; no vertices) | the background, zero gradients |
//! | NaN or Inf in positions or colours | a typed error naming the input |

use std::sync::Arc;

use autodiff::{Tape, Tensor};
use ndarray::{ArrayD, IxDyn};
use tapestry::render_ops::approx::{deodr, nmr, opendr, tf_mesh, ApproxSettings};
use tapestry::render_ops::blend::blend_hard;
use tapestry::render_ops::error::RenderError;
use tapestry::render_ops::interpolate::interpolate;
use tapestry::render_ops::raster::RasterSettings;
use tapestry::render_ops::rasterize::rasterize;
use tapestry::render_ops::soft::{dibr, softras, DibrSettings, SoftSettings};

#[derive(Clone, Copy, Debug, PartialEq)]
enum M {
    Hard,
    TfMesh,
    OpenDr,
    Nmr,
    Deodr,
    SoftRas,
    Dibr,
}

const ALL: [M; 7] = [
    M::Hard,
    M::TfMesh,
    M::OpenDr,
    M::Nmr,
    M::Deodr,
    M::SoftRas,
    M::Dibr,
];

/// Method parameters a case may change.
#[derive(Clone, Debug)]
struct Opts {
    w: usize,
    h: usize,
    sigma: f64,
    gamma: f64,
    delta: f64,
    k: usize,
    cull: bool,
    near: f64,
    far: f64,
}

impl Opts {
    fn new(w: usize, h: usize) -> Self {
        Opts {
            w,
            h,
            sigma: 1e-4,
            gamma: 1e-4,
            delta: 1e-4,
            k: 1,
            cull: false,
            near: 1.0,
            far: 100.0,
        }
    }
}

/// Image `[H, W, 4]` and gradients of `sum(image * weights)` with respect to clip positions and
/// colours, all in `f64`.
struct Out {
    img: Vec<f64>,
    g_clip: Vec<f64>,
    g_col: Vec<f64>,
}

fn t(rows: &[[f64; 4]]) -> Tensor<f64> {
    ArrayD::from_shape_vec(
        IxDyn(&[rows.len(), 4]),
        rows.iter().flatten().copied().collect(),
    )
    .unwrap()
}

fn colours(n: usize) -> Tensor<f64> {
    ArrayD::from_shape_fn(IxDyn(&[n, 3]), |i| {
        0.2 + 0.6 * (((i[0] * 7 + i[1] * 3) % 11) as f64 / 10.0)
    })
}

fn run(
    m: M,
    clip: &Tensor<f64>,
    cols: &Tensor<f64>,
    faces: &[[u32; 3]],
    o: &Opts,
) -> Result<Out, RenderError> {
    let tape = Tape::<f64>::new();
    let (c, a) = (tape.leaf(clip.clone()), tape.leaf(cols.clone()));
    let faces = Arc::new(faces.to_vec());
    let bg = vec![0.1, 0.2, 0.3];
    let img = match m {
        M::Hard => {
            let mut s = RasterSettings::new(o.w, o.h);
            s.faces_per_pixel = o.k;
            s.cull_backfaces = o.cull;
            let r = rasterize(c, faces, &s)?;
            blend_hard(interpolate(a, &r)?, &r.fragments, &bg)?
        }
        M::TfMesh | M::OpenDr | M::Nmr | M::Deodr => {
            let mut s = ApproxSettings::new(o.w, o.h);
            s.cull_backfaces = o.cull;
            s.background = bg;
            match m {
                M::TfMesh => tf_mesh(c, a, faces, &s)?,
                M::OpenDr => opendr(c, a, faces, &s)?,
                M::Nmr => nmr(c, a, faces, &s)?,
                _ => deodr(c, a, faces, &s)?,
            }
        }
        M::SoftRas => {
            let mut s = SoftSettings::new(o.w, o.h, o.near, o.far);
            s.sigma = o.sigma;
            s.gamma = o.gamma;
            s.background = bg;
            softras(c, a, faces, &s)?
        }
        M::Dibr => {
            let mut s = DibrSettings::new(o.w, o.h);
            s.delta = o.delta;
            s.cull_backfaces = o.cull;
            s.background = bg;
            dibr(c, a, faces, &s)?
        }
    };
    let v = img.value()?;
    let wts = ArrayD::from_shape_fn(v.raw_dim(), |i| {
        0.5 + ((i[0] * 3 + i[1] * 5 + i[2]) % 7) as f64 / 7.0
    });
    let g = tape.backward((img * tape.constant(wts)).sum())?;
    Ok(Out {
        img: v.iter().copied().collect(),
        g_clip: g.wrt(c).iter().copied().collect(),
        g_col: g.wrt(a).iter().copied().collect(),
    })
}

/// Runs every method; each must succeed with finite values.
fn all_finite(
    case: &str,
    clip: &Tensor<f64>,
    cols: &Tensor<f64>,
    faces: &[[u32; 3]],
    o: &Opts,
) -> Vec<(M, Out)> {
    ALL.iter()
        .map(|&m| {
            let out = run(m, clip, cols, faces, o)
                .unwrap_or_else(|e| panic!("{case}: {m:?} failed: {e}"));
            for (what, v) in [
                ("image", &out.img),
                ("dL/dclip", &out.g_clip),
                ("dL/dcolour", &out.g_col),
            ] {
                assert!(
                    v.iter().all(|x| x.is_finite()),
                    "{case}: {m:?} {what} not finite"
                );
            }
            (m, out)
        })
        .collect()
}

/// Clip row from NDC (x, y) and view depth w (OpenGL depth, near 1, far 100).
fn at(x: f64, y: f64, w: f64) -> [f64; 4] {
    let (n, f) = (1.0, 100.0);
    [x * w, y * w, ((f + n) * w - 2.0 * f * n) / (f - n), w]
}

/// A triangle covering the middle of the image.
fn triangle(w: f64) -> Tensor<f64> {
    t(&[at(-0.61, -0.53, w), at(0.57, -0.47, w), at(0.03, 0.66, w)])
}

#[test]
fn sigma_gamma_and_delta_down_to_1e_9() {
    let (w, h) = (24, 20);
    let clip = triangle(2.0);
    let cols = colours(3);
    let faces = [[0u32, 1, 2]];
    let hard = run(M::Hard, &clip, &cols, &faces, &Opts::new(w, h)).unwrap();
    for e in 2..=9 {
        let x = 10f64.powi(-e);
        let o = Opts {
            sigma: x,
            gamma: x,
            delta: x,
            ..Opts::new(w, h)
        };
        for m in [M::SoftRas, M::Dibr] {
            let out = run(m, &clip, &cols, &faces, &o).unwrap();
            for v in [&out.img, &out.g_clip, &out.g_col] {
                assert!(v.iter().all(|x| x.is_finite()), "{m:?} at {x:e}");
            }
            if e == 9 {
                // Away from edges (the pixel and its 5x5 neighbourhood agree in the hard
                // render's coverage), the soft image is the hard one.
                let cov = |r: usize, c: usize| hard.img[(r * w + c) * 4 + 3];
                let mut checked = 0;
                for r in 2..h - 2 {
                    for c in 2..w - 2 {
                        let same = (r - 2..=r + 2)
                            .all(|rr| (c - 2..=c + 2).all(|cc| cov(rr, cc) == cov(r, c)));
                        if !same {
                            continue;
                        }
                        checked += 1;
                        for ch in 0..4 {
                            let i = (r * w + c) * 4 + ch;
                            assert!(
                                (out.img[i] - hard.img[i]).abs() < 1e-3,
                                "{m:?} at {x:e}, pixel ({r}, {c}) channel {ch}: {} vs {}",
                                out.img[i],
                                hard.img[i]
                            );
                        }
                    }
                }
                assert!(checked > 100, "{checked}");
            }
        }
    }
}

#[test]
fn depth_ranges_from_1e_3_to_1e5() {
    let cols = colours(6);
    let faces = [[0u32, 1, 2], [3, 4, 5]];
    for (near, far, d) in [
        (1e-3, 1e5, 1e-2),
        (1e-3, 1e5, 1e4),
        (1e-3, 10.0, 5e-3),
        (1e2, 1e5, 5e4),
    ] {
        // The OpenGL depth of view depth `w` under (near, far).
        let z = |w: f64| ((far + near) * w - 2.0 * far * near) / (far - near);
        let row = |x: f64, y: f64, w: f64| [x * w, y * w, z(w), w];
        // Two overlapping triangles, the second 1e-6 (relative) nearer.
        let d2 = d * (1.0 - 1e-6);
        let clip = t(&[
            row(-0.6, -0.5, d),
            row(0.6, -0.5, d),
            row(0.0, 0.6, d),
            row(-0.5, -0.4, d2),
            row(0.5, -0.45, d2),
            row(0.05, 0.55, d2),
        ]);
        let o = Opts {
            near,
            far,
            ..Opts::new(16, 16)
        };
        let case = format!("near {near:e} far {far:e} depth {d:e}");
        let outs = all_finite(&case, &clip, &cols, &faces, &o);
        // The centre pixel shows the nearer (second) face's colours in the hard render.
        let hard = &outs[0].1;
        let tape = Tape::<f64>::new();
        let r = rasterize(
            tape.leaf(clip.clone()),
            Arc::new(faces.to_vec()),
            &RasterSettings::new(16, 16),
        )
        .unwrap();
        let centre = r.fragments.nearest(8 * 16 + 8).expect("covered");
        assert_eq!(centre.face, 1, "{case}: the nearer face wins");
        assert_eq!(hard.img[(8 * 16 + 8) * 4 + 3], 1.0);
    }
}

#[test]
fn slivers_and_zero_area_triangles() {
    let cols = colours(9);
    // A sliver of aspect ratio 1e6 across the image, a collinear triangle, a triangle with two
    // coincident vertices.
    let clip = t(&[
        at(-0.9, 0.1, 2.0),
        at(0.9, 0.1 + 1.8e-6, 2.0),
        at(0.0, 0.1 + 0.9e-6, 2.0),
        at(-0.5, -0.5, 2.0),
        at(0.0, 0.0, 2.0),
        at(0.5, 0.5, 2.0),
        at(0.2, -0.3, 2.0),
        at(0.2, -0.3, 2.0),
        at(0.6, 0.4, 2.0),
    ]);
    let faces = [[0u32, 1, 2], [3, 4, 5], [6, 7, 8]];
    let outs = all_finite("slivers", &clip, &cols, &faces, &Opts::new(32, 32));
    // The zero-area faces produce no fragments; the sliver covers at most one row of pixels.
    let tape = Tape::<f64>::new();
    let r = rasterize(
        tape.leaf(clip),
        Arc::new(faces.to_vec()),
        &RasterSettings::new(32, 32),
    )
    .unwrap();
    assert!(
        r.fragments.face.iter().all(|&f| f == 0),
        "zero-area faces made fragments"
    );
    assert!(r.fragments.len() <= 32);
    let _ = outs;
}

#[test]
fn vertices_coinciding_in_screen_space() {
    // PyTorch3D issue 110: distinct 3D points on one ray from the eye project to the same
    // screen position, making a face with zero screen area but non-zero 3D area, next to a
    // normal face sharing those vertices.
    let p = at(0.1, 0.2, 2.0);
    let q = at(0.1, 0.2, 3.0); // the same NDC, farther
    let clip = t(&[p, q, at(-0.5, -0.4, 2.5), at(0.6, -0.3, 2.5)]);
    let faces = [[0u32, 1, 2], [0, 2, 3], [1, 3, 2]];
    all_finite(
        "coincident screen vertices",
        &clip,
        &colours(4),
        &faces,
        &Opts::new(24, 24),
    );
}

#[test]
fn vertices_on_pixel_centres_and_tile_borders() {
    // A 32 x 32 image: pixel centres at NDC 2 (c + 0.5) / 32 - 1, the 16-px tile border at 0.
    let n = 32.0;
    let centre = |c: f64| 2.0 * (c + 0.5) / n - 1.0;
    let (x0, x1, y0, y1) = (centre(3.0), centre(16.0), centre(5.0), 0.0);
    let clip = t(&[
        at(x0, y0, 2.0),
        at(x1, y0, 2.0),
        at(x1, y1, 2.0),
        at(x0, y1, 2.0),
    ]);
    let faces = [[0u32, 1, 2], [0, 2, 3]];
    all_finite(
        "pixel centres",
        &clip,
        &colours(4),
        &faces,
        &Opts::new(32, 32),
    );
    // Watertight: every pixel centre of the quad's interior and its top-left edges is covered
    // exactly once (no double cover along the shared diagonal).
    let tape = Tape::<f64>::new();
    let r = rasterize(
        tape.leaf(clip),
        Arc::new(faces.to_vec()),
        &RasterSettings {
            faces_per_pixel: 2,
            ..RasterSettings::new(32, 32)
        },
    )
    .unwrap();
    assert!(
        (0..32 * 32).all(|p| r.fragments.count(p) <= 1),
        "a pixel covered twice"
    );
    assert!(r.fragments.len() > 100, "{}", r.fragments.len());
}

#[test]
fn near_plane_and_w_close_to_zero() {
    let cols = colours(3);
    let faces = [[0u32, 1, 2]];
    // Crossing the near plane: one vertex behind the eye.
    let crossing = t(&[
        at(-0.5, -0.5, 2.0),
        at(0.5, -0.5, 2.0),
        [0.0, 0.5, -3.0, -0.5],
    ]);
    all_finite(
        "crossing the near plane",
        &crossing,
        &cols,
        &faces,
        &Opts::new(16, 16),
    );
    for w in [1e-12, 1e-300, 0.0, -1e-12, -2.0] {
        let clip = t(&[
            at(-0.5, -0.5, 2.0),
            at(0.5, -0.5, 2.0),
            [0.0, 0.4 * w, -1.0, w],
        ]);
        all_finite(
            &format!("w = {w:e}"),
            &clip,
            &cols,
            &faces,
            &Opts::new(16, 16),
        );
    }
    // Wholly behind the eye: nothing is drawn, no gradient.
    let behind = t(&[
        [-0.5, -0.5, -3.0, -2.0],
        [0.5, -0.5, -3.0, -2.0],
        [0.0, 0.5, -3.0, -2.0],
    ]);
    for (m, out) in all_finite("behind the eye", &behind, &cols, &faces, &Opts::new(16, 16)) {
        assert!(
            out.img.chunks(4).all(|p| p[3] == 0.0),
            "{m:?} drew a face behind the eye"
        );
        assert!(out.g_col.iter().all(|&g| g == 0.0), "{m:?}");
    }
}

#[test]
fn back_faces_with_and_without_culling() {
    // Clockwise in NDC: a back face.
    let clip = t(&[at(-0.5, -0.5, 2.0), at(0.0, 0.6, 2.0), at(0.5, -0.5, 2.0)]);
    let faces = [[0u32, 1, 2]];
    let cols = colours(3);
    for cull in [false, true] {
        let o = Opts {
            cull,
            ..Opts::new(16, 16)
        };
        for (m, out) in all_finite("back face", &clip, &cols, &faces, &o) {
            let covered = out.img.chunks(4).filter(|p| p[3] > 0.5).count();
            // SoftRas has no culling setting: it always draws both sides.
            if cull && m != M::SoftRas {
                assert_eq!(covered, 0, "{m:?} drew a culled back face");
            } else {
                assert!(covered > 20, "{m:?} (cull {cull}) drew {covered} pixels");
            }
        }
    }
}

#[test]
fn a_million_faces_over_one_pixel() {
    // 1000 small triangles at different depths around the centre of an 8 x 8 image, each
    // repeated 1000 times: 1,000,000 faces over pixel (4, 4).
    let n = 1000;
    let c = 2.0 * 4.5 / 8.0 - 1.0;
    let mut rows = Vec::with_capacity(3 * n);
    for i in 0..n {
        let w = 2.0 + i as f64 * 1e-3;
        let s = 0.05 + 1e-5 * i as f64;
        rows.extend([at(c - s, -c - s, w), at(c + s, -c - s, w), at(c, -c + s, w)]);
    }
    let clip = t(&rows);
    let faces: Vec<[u32; 3]> = (0..n * n)
        .map(|k| {
            let i = (k % n) as u32;
            [3 * i, 3 * i + 1, 3 * i + 2]
        })
        .collect();
    let cols = colours(3 * n);
    for k in [1, 8] {
        let o = Opts {
            k,
            ..Opts::new(8, 8)
        };
        let out = run(M::Hard, &clip, &cols, &faces, &o).unwrap();
        assert!(out.img.iter().chain(&out.g_clip).all(|x| x.is_finite()));
        assert_eq!(out.img[(4 * 8 + 4) * 4 + 3], 1.0);
    }
    for m in [M::TfMesh, M::OpenDr, M::Nmr, M::Deodr, M::SoftRas, M::Dibr] {
        let out = run(m, &clip, &cols, &faces, &Opts::new(8, 8)).unwrap();
        for v in [&out.img, &out.g_clip, &out.g_col] {
            assert!(v.iter().all(|x| x.is_finite()), "{m:?}");
        }
    }
}

#[test]
fn empty_meshes_render_the_background() {
    let cols = colours(3);
    // Vertices but no faces.
    for (m, out) in all_finite("no faces", &triangle(2.0), &cols, &[], &Opts::new(8, 8)) {
        for p in out.img.chunks(4) {
            assert_eq!(&p[..3], &[0.1, 0.2, 0.3], "{m:?}");
            assert_eq!(p[3], 0.0, "{m:?}");
        }
        assert!(
            out.g_clip.iter().chain(&out.g_col).all(|&g| g == 0.0),
            "{m:?}"
        );
    }
    // No vertices at all.
    let none = ArrayD::zeros(IxDyn(&[0, 4]));
    let no_cols = ArrayD::zeros(IxDyn(&[0, 3]));
    for (m, out) in all_finite("no vertices", &none, &no_cols, &[], &Opts::new(8, 8)) {
        assert!(out.img.chunks(4).all(|p| p[3] == 0.0), "{m:?}");
    }
}

#[test]
fn nan_and_inf_inputs_are_typed_errors() {
    let faces = [[0u32, 1, 2]];
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let mut rows = [at(-0.5, -0.5, 2.0), at(0.5, -0.5, 2.0), at(0.0, 0.5, 2.0)];
        rows[1][0] = bad;
        let clip = t(&rows);
        for m in ALL {
            match run(m, &clip, &colours(3), &faces, &Opts::new(8, 8)) {
                Err(e) => {
                    let msg = e.to_string();
                    assert!(
                        msg.contains("finite") || msg.contains("NaN") || msg.contains("nan"),
                        "{m:?}: {msg}"
                    );
                }
                Ok(_) => panic!("{m:?} accepted a vertex at {bad}"),
            }
        }
    }
    // Non-finite colours propagate into the image of a covered pixel; the hard path refuses
    // nothing here (colours are shader data), so the check is that nothing panics and the
    // error-free result is flagged by anomaly mode when the user asks for it.
    let tape = Tape::<f64>::new();
    tape.set_detect_anomaly(true);
    let mut cols = colours(3);
    cols[[0, 0]] = f64::NAN;
    let c = tape.leaf(triangle(2.0));
    let a = tape.leaf(cols);
    let r = rasterize(c, Arc::new(faces.to_vec()), &RasterSettings::new(8, 8)).unwrap();
    let img = interpolate(a, &r).and_then(|i| blend_hard(i, &r.fragments, &[0.0; 3]));
    let err = match img {
        Err(e) => e.to_string(),
        Ok(v) => v.value().unwrap_err().to_string(),
    };
    assert!(
        err.contains("interpolate") || err.contains("NaN") || err.contains("anomaly"),
        "{err}"
    );
}
