//! The `nmr` raster method (Kato, Ushiku and Harada, "Neural 3D Mesh Renderer", CVPR 2018;
//! survey section 4.2, eq. 1-2): the forward is the hard render bit for bit, colour gradients
//! are the hard render's exact ones, the edge term on hand-built scenes (direction of the
//! silhouette pull along x and y, gating by the sign of the incoming gradient, uncovering from
//! inside, the two directions of eq. 2, the occlusion test), determinism across thread counts,
//! f32 against f64, and typed errors. Its descent-direction and pose-fit figures are in
//! `approx.rs` with the other approximate methods.

use std::sync::Arc;

use autodiff::{Real, Tape, Tensor};
use ndarray::{ArrayD, IxDyn};
use render_ops::approx::{nmr, ApproxSettings};
use render_ops::blend::blend_hard;
use render_ops::error::RenderError;
use render_ops::interpolate::interpolate;
use render_ops::mesh::Mesh;
use render_ops::raster::RasterError;
use render_ops::rasterize::rasterize;

use crate::common;
use common::{clip_row, perspective_clip, smooth_colours, t2, weights};

const BG: [f64; 3] = [0.1, 0.2, 0.3];

fn settings(w: usize, h: usize) -> ApproxSettings {
    let mut s = ApproxSettings::new(w, h);
    s.background = BG.to_vec();
    s
}

/// An icosphere (level 3) and a smaller one in front of it, seen in perspective: silhouettes
/// over the background, occlusion boundaries over a surface, and edges inside surfaces.
fn two_spheres() -> (Tensor<f64>, Tensor<f64>, Arc<Vec<[u32; 3]>>) {
    let mut mesh: Mesh<f64> = Mesh::icosphere(3, 1.0);
    let small: Mesh<f64> = Mesh::icosphere(2, 0.45);
    let base = mesh.positions.len() as u32;
    mesh.positions.extend(
        small
            .positions
            .iter()
            .map(|p| [p[0] + 0.55, p[1] + 0.25, p[2] + 0.9]),
    );
    mesh.faces
        .extend(small.faces.iter().map(|f| f.map(|i| i + base)));
    (
        perspective_clip(&mesh.positions, [0.13, 0.21, 3.6]),
        smooth_colours(&mesh.positions),
        Arc::new(mesh.faces.clone()),
    )
}

/// Image and the gradients (clip positions, colours) of `sum(weights * image)` or, with
/// `square`, of `sum((weights - image)^2)`, with `nmr` (or the hard pipeline), in `T`.
fn run<T: Real>(
    hard: bool,
    clip: &Tensor<f64>,
    cols: &Tensor<f64>,
    faces: &Arc<Vec<[u32; 3]>>,
    s: &ApproxSettings,
    wts: &[f64],
    square: bool,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let tape = Tape::<T>::new();
    let c = tape.leaf(clip.mapv(T::from_f64c));
    let a = tape.leaf(cols.mapv(T::from_f64c));
    let img = if hard {
        let r = rasterize(c, faces.clone(), &s.raster()).unwrap();
        let bg: Vec<T> = s.background.iter().map(|&b| T::from_f64c(b)).collect();
        blend_hard(interpolate(a, &r).unwrap(), &r.fragments, &bg).unwrap()
    } else {
        nmr(c, a, faces.clone(), s).unwrap()
    };
    let shape = img.value().unwrap().shape().to_vec();
    let w = tape.constant(
        ArrayD::from_shape_vec(
            IxDyn(&shape),
            wts.iter().map(|&x| T::from_f64c(x)).collect(),
        )
        .unwrap(),
    );
    let loss = if square {
        (img - w).square().sum()
    } else {
        (img * w).sum()
    };
    let g = tape.backward(loss).unwrap();
    let f = |t: &Tensor<T>| t.iter().map(|x| x.to_f64c()).collect::<Vec<_>>();
    (f(&img.value().unwrap()), f(&g.wrt(c)), f(&g.wrt(a)))
}

#[test]
fn forward_is_the_hard_render_bit_for_bit() {
    let (clip, cols, faces) = two_spheres();
    for (w, h) in [(48, 40), (64, 64)] {
        let s = settings(w, h);
        let wts = weights(w * h * 4);
        let (a, _, _) = run::<f64>(false, &clip, &cols, &faces, &s, &wts, false);
        let (b, _, _) = run::<f64>(true, &clip, &cols, &faces, &s, &wts, false);
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        let (a, _, _) = run::<f32>(false, &clip, &cols, &faces, &s, &wts, false);
        let (b, _, _) = run::<f32>(true, &clip, &cols, &faces, &s, &wts, false);
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        let covered = a.iter().skip(3).step_by(4).filter(|&&x| x == 1.0).count();
        assert!(covered > w * h / 5, "{covered}");
    }
}

#[test]
fn colour_gradients_are_the_hard_renders() {
    let (clip, cols, faces) = two_spheres();
    let s = settings(40, 40);
    let wts = weights(40 * 40 * 4);
    for square in [false, true] {
        let (_, gp, a) = run::<f64>(false, &clip, &cols, &faces, &s, &wts, square);
        let (_, _, b) = run::<f64>(true, &clip, &cols, &faces, &s, &wts, square);
        let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let diff = a
            .iter()
            .zip(&b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        assert!(scale > 1e-2 && diff <= 1e-12 * scale, "{diff} vs {scale}");
        assert!(gp.iter().all(|x| x.is_finite()) && gp.iter().any(|&x| x != 0.0));
    }
}

/// A single front-facing triangle of one colour over the background, 16 x 16 pixels (a pixel
/// is 0.125 NDC): vertex 1 is the right-most, vertex 2 the top-most.
fn triangle() -> (Tensor<f64>, Tensor<f64>, Arc<Vec<[u32; 3]>>) {
    let clip = t2(&[
        clip_row(-0.61, -0.52, 2.0),
        clip_row(0.37, 0.06, 2.0),
        clip_row(-0.47, 0.63, 2.0),
    ]);
    let cols = t2(&vec![vec![0.9, 0.8, 0.7]; 3]);
    (clip, cols, Arc::new(vec![[0, 1, 2]]))
}

/// Pixel `(col, row)` of NDC `(x, y)` in a 16 x 16 image.
fn px(x: f64, y: f64) -> (f64, f64) {
    ((x + 1.0) * 8.0 - 0.5, (1.0 - y) * 8.0 - 0.5)
}

/// The gradient `[V, 4]` of `sum(w * image)` with `w` = `sign` on the pixels `pick` selects
/// (every channel, alpha included) and 0 elsewhere, and the image's alpha.
fn pulled(
    clip: &Tensor<f64>,
    cols: &Tensor<f64>,
    faces: &Arc<Vec<[u32; 3]>>,
    sign: f64,
    pick: impl Fn(usize, usize, bool) -> bool,
) -> Vec<[f64; 4]> {
    let s = settings(16, 16);
    let (img, _, _) = run::<f64>(false, clip, cols, faces, &s, &vec![0.0; 16 * 16 * 4], false);
    let mut wts = vec![0.0; 16 * 16 * 4];
    let mut n = 0;
    for row in 0..16 {
        for col in 0..16 {
            let p = row * 16 + col;
            if pick(row, col, img[p * 4 + 3] == 1.0) {
                n += 1;
                wts[p * 4..p * 4 + 4].fill(sign);
            }
        }
    }
    assert!(n > 0, "no pixel picked");
    let (_, g, _) = run::<f64>(false, clip, cols, faces, &s, &wts, false);
    g.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect()
}

/// A loss that wants the background just right of the right-most vertex to take the face's
/// colour pulls that vertex right (dL/dx < 0); with the opposite sign, moving right would
/// raise the loss: the term is gated out and, as those pixels are uncovered (no interior
/// part), the whole gradient is zero.
#[test]
fn silhouette_pull_and_gating_along_x() {
    let (clip, cols, faces) = triangle();
    let (c1, r1) = px(0.37, 0.06);
    let pick = |row: usize, col: usize, covered: bool| {
        !covered && (row as f64 - r1).abs() <= 1.5 && col as f64 > c1 && (col as f64) < c1 + 3.0
    };
    let g = pulled(&clip, &cols, &faces, -1.0, pick);
    println!("pull right: {g:?}");
    assert!(g[1][0] < 0.0, "{g:?}");
    // The vertex with the most to do is the right-most one.
    assert!(g[1][0].abs() > g[0][0].abs() && g[1][0].abs() > g[2][0].abs());
    let g = pulled(&clip, &cols, &faces, 1.0, pick);
    assert!(g.iter().flatten().all(|&x| x == 0.0), "{g:?}");
}

/// The same along y: the background just above the top vertex pulls it up (dL/dy < 0, NDC y
/// points up); the opposite sign gives nothing.
#[test]
fn silhouette_pull_and_gating_along_y() {
    let (clip, cols, faces) = triangle();
    let (c2, r2) = px(-0.47, 0.63);
    let pick = |row: usize, col: usize, covered: bool| {
        !covered && (col as f64 - c2).abs() <= 1.5 && (row as f64) < r2 && row as f64 > r2 - 3.0
    };
    let g = pulled(&clip, &cols, &faces, -1.0, pick);
    println!("pull up: {g:?}");
    assert!(g[2][1] < 0.0, "{g:?}");
    let g = pulled(&clip, &cols, &faces, 1.0, pick);
    assert!(g.iter().flatten().all(|&x| x == 0.0), "{g:?}");
}

/// Covered pixels next to the right edge that should show the background: the right-most
/// vertex moves left (dL/dx > 0) to uncover them, the colour behind taken from across the edge.
/// With the opposite sign the edge term is gated out and only the interior (barycentric) part
/// is left, which is zero up to rounding for a face of one colour.
#[test]
fn uncovering_from_inside() {
    let (clip, cols, faces) = triangle();
    let (c1, r1) = px(0.37, 0.06);
    let pick = |row: usize, col: usize, covered: bool| {
        covered && (row as f64 - r1).abs() <= 1.5 && col as f64 > c1 - 4.0
    };
    let g = pulled(&clip, &cols, &faces, 1.0, pick);
    println!("uncover: {g:?}");
    assert!(g[1][0] > 0.0, "{g:?}");
    let scale = g[1][0];
    let g = pulled(&clip, &cols, &faces, -1.0, pick);
    assert!(
        g.iter().flatten().all(|&x| x.abs() < 1e-12 * scale),
        "{g:?}"
    );
}

/// Eq. 2: a covered pixel can be uncovered by moving a vertex either way. On a triangle
/// symmetric about a pixel column, with the loss on that column only, the apex's two x terms
/// (left edge moving right, right edge moving left) cancel, while the base vertices get
/// opposite x gradients (each moves inwards: the left one right, dL/dx < 0) and the apex a y
/// gradient (it moves down).
#[test]
fn both_directions_add_up() {
    // Column 8 has its centre at NDC x = 2 * 8.5 / 16 - 1 = 0.0625.
    let xc = 0.0625;
    let clip = t2(&[
        clip_row(xc - 0.4, -0.55, 2.0),
        clip_row(xc + 0.4, -0.55, 2.0),
        clip_row(xc, 0.58, 2.0),
    ]);
    let cols = t2(&vec![vec![0.9, 0.8, 0.7]; 3]);
    let faces = Arc::new(vec![[0, 1, 2]]);
    let g = pulled(&clip, &cols, &faces, 1.0, |_, col, covered| {
        covered && col == 8
    });
    println!("symmetric: {g:?}");
    let scale = g[0][0].abs();
    assert!(scale > 0.0);
    assert!(g[0][0] < 0.0 && g[1][0] > 0.0, "{g:?}");
    assert!((g[0][0] + g[1][0]).abs() < 1e-9 * scale, "{g:?}");
    assert!(g[2][0].abs() < 1e-9 * scale, "{g:?}");
    // Moving the apex down (NDC y decreasing) uncovers the column: dL/dy > 0.
    assert!(g[2][1] > 0.0, "{g:?}");
}

/// Occlusion: a face's edge sweeps only over pixels where it would be in front. Triangle A
/// (left) and a quad B (right) do not overlap on screen; the loss asks B's pixels right of A
/// for A's colour. With B nearer than A, A can take none of them: A's vertices get exactly
/// zero. With B farther, A's right-most vertex is pulled right.
#[test]
fn occluded_pixels_are_not_taken() {
    let cols_of = |n: usize| {
        let mut c = vec![vec![0.9, 0.8, 0.7]; 3];
        c.extend(vec![vec![0.2, 0.1, 0.6]; n - 3]);
        t2(&c)
    };
    let faces = Arc::new(vec![[0, 1, 2], [3, 4, 5], [3, 5, 6]]);
    let cols = cols_of(7);
    let scene = |wb: f64| {
        t2(&[
            clip_row(-0.81, -0.52, 3.0),
            clip_row(0.03, 0.06, 3.0),
            clip_row(-0.67, 0.63, 3.0),
            clip_row(0.27, -0.9, wb),
            clip_row(0.93, -0.9, wb),
            clip_row(0.93, 0.9, wb),
            clip_row(0.27, 0.9, wb),
        ])
    };
    let (c1, r1) = px(0.03, 0.06);
    // B's pixels on the rows of A's right-most vertex, a few pixels right of it.
    let pick = |row: usize, col: usize, covered: bool| {
        covered && (row as f64 - r1).abs() <= 1.5 && col as f64 > c1 && (col as f64) < c1 + 6.0
    };
    let front = pulled(&scene(1.5), &cols, &faces, -1.0, pick);
    println!("B in front: {front:?}");
    assert!(front[..3].iter().flatten().all(|&x| x == 0.0), "{front:?}");
    let behind = pulled(&scene(6.0), &cols, &faces, -1.0, pick);
    println!("B behind: {behind:?}");
    assert!(behind[1][0] < 0.0, "{behind:?}");
}

#[test]
fn bit_identical_on_1_2_and_8_threads() {
    let (clip, cols, faces) = two_spheres();
    let s = settings(64, 56);
    let wts = weights(64 * 56 * 4);
    let go = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| run::<f64>(false, &clip, &cols, &faces, &s, &wts, true))
    };
    let bits = |r: (Vec<f64>, Vec<f64>, Vec<f64>)| {
        [r.0, r.1, r.2].map(|v| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>())
    };
    let one = bits(go(1));
    let nonzero = one[1].iter().filter(|&&b| f64::from_bits(b) != 0.0).count();
    println!("{nonzero} non-zero position gradient entries");
    assert!(nonzero > 500, "{nonzero}");
    for n in [2, 8] {
        assert!(bits(go(n)) == one, "{n} threads differ from 1");
    }
}

#[test]
fn f32_agrees_with_f64() {
    let (clip, cols, faces) = two_spheres();
    let s = settings(48, 48);
    // A target: the render of the spheres moved a little.
    let shifted = clip.mapv(|x| x)
        + &ArrayD::from_shape_fn(clip.raw_dim(), |i| match i[1] {
            0 => 0.03 * clip[[i[0], 3]],
            1 => -0.02 * clip[[i[0], 3]],
            _ => 0.0,
        });
    let zero = vec![0.0; 48 * 48 * 4];
    let (target, _, _) = run::<f64>(false, &shifted, &cols, &faces, &s, &zero, false);
    let (_, a, ca) = run::<f64>(false, &clip, &cols, &faces, &s, &target, true);
    let (_, b, cb) = run::<f32>(false, &clip, &cols, &faces, &s, &target, true);
    let rel = |a: &[f64], b: &[f64]| {
        let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
        let n: f64 = a.iter().map(|x| x * x).sum();
        (d / n).sqrt()
    };
    let (rp, rc) = (rel(&a, &b), rel(&ca, &cb));
    println!("f32 vs f64: relative L2 difference: positions {rp:e}, colours {rc:e}");
    assert!(rp < 1e-3 && rc < 1e-4, "{rp} {rc}");
}

#[test]
fn bad_inputs_are_typed_errors() {
    let (clip, cols, faces) = triangle();
    let tape = Tape::<f64>::new();
    let (c, a) = (tape.leaf(clip.clone()), tape.leaf(cols));
    let s = settings(8, 8);
    let shape = |e: RenderError| {
        assert!(
            matches!(
                e,
                RenderError::Autodiff(autodiff::AutodiffError::Shape { .. })
            ),
            "{e:?}"
        )
    };
    shape(nmr(c.slice(1, 0, 3), a, faces.clone(), &s).unwrap_err());
    shape(nmr(c, a.slice(0, 0, 2), faces.clone(), &s).unwrap_err());
    let invalid = |e: RenderError| {
        assert!(
            matches!(
                e,
                RenderError::Autodiff(autodiff::AutodiffError::InvalidArgument { .. })
            ),
            "{e:?}"
        )
    };
    let mut s2 = s.clone();
    s2.background = vec![0.0; 2];
    invalid(nmr(c, a, faces.clone(), &s2).unwrap_err());
    s2.background = vec![0.0, f64::INFINITY, 0.0];
    invalid(nmr(c, a, faces.clone(), &s2).unwrap_err());
    let e = nmr(c, a, Arc::new(vec![[0, 1, 9]]), &s).unwrap_err();
    assert!(
        matches!(
            e,
            RenderError::Raster(RasterError::FaceIndexOutOfRange { index: 9, .. })
        ),
        "{e:?}"
    );
    assert!(e.to_string().contains('9'), "{e}");
    let e = nmr(c, a, faces.clone(), &settings(8, 0)).unwrap_err();
    assert!(
        matches!(e, RenderError::Raster(RasterError::EmptyImage { .. })),
        "{e:?}"
    );
    let mut bad = clip.clone();
    bad[[2, 1]] = f64::NAN;
    let e = nmr(tape.constant(bad), a, faces.clone(), &s).unwrap_err();
    assert!(
        matches!(
            e,
            RenderError::Raster(RasterError::NonFiniteVertex { vertex: 2, .. })
        ),
        "{e:?}"
    );
    // Only the inputs that need a gradient get one.
    let tape = Tape::<f64>::new();
    let (c, a) = (tape.constant(clip), tape.leaf(triangle().1));
    let img = nmr(c, a, faces, &s).unwrap();
    let g = tape.backward(img.square().sum()).unwrap();
    assert!(g.get(c).is_none());
    assert!(g.wrt(a).iter().any(|&x| x != 0.0));
}
