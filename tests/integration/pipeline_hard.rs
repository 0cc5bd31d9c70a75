//! The hard pipeline end to end: scene JSON -> clip -> rasterize -> interpolate -> blend,
//! against the peer kit's reference renders, and gradient-checked through the tape.

use crate::common;

use std::sync::Arc;

use tapestry::autodiff::gradcheck::{gradcheck, GradcheckOptions};
use tapestry::autodiff::rng::Rng;
use tapestry::autodiff::{Tape, Tensor, Var};
use tapestry::render_ops::blend::blend_hard;
use tapestry::render_ops::camera::Camera;
use tapestry::render_ops::interpolate::interpolate;
use tapestry::render_ops::io::read_npy;
use tapestry::render_ops::pipeline::Wrt;
use tapestry::render_ops::raster::RasterSettings;
use tapestry::render_ops::rasterize::{rasterize, render_attributes};
use tapestry::render_ops::scene::Scene;
use tapestry::render_ops::transform::to_clip;

#[test]
fn hard_render_matches_the_peer_reference() {
    let peers = common::peers_dir();
    let scene = Scene::<f64>::load(peers.join("scenes/ico5k_hard.json")).unwrap();
    let tape = Tape::new();
    let vars = scene.vars(&tape, Wrt::default());
    let img = scene.render(&vars).unwrap().value().unwrap();
    let reference: Tensor<f64> = read_npy(peers.join("reference/hard_image.npy")).unwrap();
    let ref_alpha: Tensor<f64> = read_npy(peers.join("reference/hard_alpha.npy")).unwrap();
    let (h, w) = (128, 128);
    let (mut inter, mut union, mut worst) = (0usize, 0usize, 0.0f64);
    for r in 0..h {
        for c in 0..w {
            let a = img[[r, c, 3]] > 0.5;
            let b = ref_alpha[[r, c, 0]] > 0.5;
            inter += (a && b) as usize;
            union += (a || b) as usize;
            if a && b {
                for ch in 0..3 {
                    worst = worst.max((img[[r, c, ch]] - reference[[r, c, ch]]).abs());
                }
            }
        }
    }
    let iou = inter as f64 / union as f64;
    assert!(iou >= 0.995, "silhouette IoU {iou}");
    assert!(
        worst <= 1e-4,
        "max colour difference on covered pixels {worst}"
    );
}

type SmallScene = (Tensor<f64>, Arc<Vec<[u32; 3]>>, Tensor<f64>, [[f64; 4]; 4]);

/// A small perspective scene with occlusion: two overlapping triangles and a quad.
fn small_scene() -> SmallScene {
    let pos = vec![
        -0.8, -0.7, 0.0, 0.7, -0.6, 0.1, -0.1, 0.8, -0.1, // front triangle
        -0.5, -0.2, -0.6, 0.9, 0.1, -0.5, 0.2, 0.9, -0.7, // behind, partly occluded
        -1.2, -1.1, -1.2, 1.3, -1.0, -1.3, 1.2, 1.2, -1.2, -1.1, 1.3, -1.1, // back quad
    ];
    let faces = vec![[0, 1, 2], [3, 4, 5], [6, 7, 8], [6, 8, 9]];
    let mut rng = Rng::new(11);
    let colors: Tensor<f64> = rng.uniform_tensor(&[10, 3], 0.1, 0.9);
    let cam = Camera::perspective_look_at(
        [0.3, 0.2, 3.0],
        [0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        0.9,
        1.0,
        0.5,
        20.0,
    )
    .unwrap();
    (
        Tensor::from_shape_vec(vec![10, 3], pos).unwrap(),
        Arc::new(faces),
        colors,
        cam.view_proj(),
    )
}

#[test]
fn hard_pipeline_gradcheck_positions_and_colors() {
    let (pos, faces, colors, vp) = small_scene();
    let settings = RasterSettings::new(20, 16);
    let mut rng = Rng::new(5);
    let weights: Tensor<f64> = rng.uniform_tensor(&[16, 20, 4], -1.0, 1.0);
    let opts = GradcheckOptions {
        eps: 1e-7,
        atol: 1e-6,
        rtol: 1e-4,
        ..Default::default()
    };
    let rep = gradcheck(
        |t: &Tape<f64>, v| {
            let clip = to_clip(v[0], &vp);
            let r = rasterize(clip, faces.clone(), &settings).unwrap();
            let c = interpolate(v[1], &r).unwrap();
            let img = blend_hard(c, &r.fragments, &[0.1, 0.2, 0.3]).unwrap();
            (img * t.constant(weights.clone())).sum()
        },
        &[pos, colors],
        &opts,
    )
    .unwrap();
    assert!(rep.passed(), "{rep}");
    // Not vacuous: the interior position gradient is substantial.
    let (pos, faces, colors, vp) = small_scene();
    let t = Tape::new();
    let (p, c) = (t.leaf(pos), t.leaf(colors));
    let r = rasterize(to_clip(p, &vp), faces, &settings).unwrap();
    let img = blend_hard(interpolate(c, &r).unwrap(), &r.fragments, &[0.1, 0.2, 0.3]).unwrap();
    let g = t.backward(img.square().sum()).unwrap().wrt(p);
    let norm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!(norm > 1e-2, "position gradient norm {norm}");
}

#[test]
fn hard_pipeline_f32_matches_f64() {
    let (pos, faces, colors, vp) = small_scene();
    let settings = RasterSettings::new(20, 16);
    macro_rules! pipeline {
        ($t:ty) => {
            |t: &Tape<$t>, v: &[tapestry::autodiff::Var<'_, $t>]| {
                let clip = to_clip(v[0], &vp);
                let r = rasterize(clip, faces.clone(), &settings).unwrap();
                let c = interpolate(v[1], &r).unwrap();
                let img = blend_hard(c, &r.fragments, &[0.0, 0.0, 0.0]).unwrap();
                let _ = t;
                img.square().sum()
            }
        };
    }
    let rep = tapestry::autodiff::gradcheck::compare_precision(
        pipeline!(f32),
        pipeline!(f64),
        &[pos, colors],
        3,
    )
    .unwrap();
    assert!(rep.max_rel() < 1e-4, "{rep:?}");
}

/// `render_attributes` without gradients (one pass, no fragment list) gives the image of
/// rasterize + interpolate + blend_hard bit for bit, in f32 and f64, perspective-correct and
/// screen-space, with `faces_per_pixel` 4 in the settings; with gradients it records that chain
/// and gives its gradients; bad shapes are typed errors.
#[test]
fn render_attributes_matches_the_three_ops() {
    let (pos, faces, colors, vp) = small_scene();
    fn split<'t>(
        p: Var<'t, f64>,
        c: Var<'t, f64>,
        faces: &Arc<Vec<[u32; 3]>>,
        vp: &[[f64; 4]; 4],
        s: &RasterSettings,
    ) -> Var<'t, f64> {
        let r = rasterize(to_clip(p, vp), faces.clone(), s).unwrap();
        blend_hard(interpolate(c, &r).unwrap(), &r.fragments, &[0.1, 0.2, 0.3]).unwrap()
    }
    for persp in [true, false] {
        let s = RasterSettings {
            perspective_correct: persp,
            faces_per_pixel: 4,
            ..RasterSettings::new(67, 45)
        };
        let s1 = RasterSettings {
            faces_per_pixel: 1,
            ..s
        };
        // f64, no gradients.
        let t = Tape::<f64>::new();
        let (p, c) = (t.constant(pos.clone()), t.constant(colors.clone()));
        let want = split(p, c, &faces, &vp, &s1).value().unwrap();
        let got = render_attributes(to_clip(p, &vp), c, faces.clone(), &s, &[0.1, 0.2, 0.3])
            .unwrap()
            .value()
            .unwrap();
        assert_eq!(got.shape(), [45, 67, 4]);
        assert!(got
            .iter()
            .zip(want.iter())
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        assert!(
            got.iter().filter(|&&a| a == 1.0).count() > 300,
            "covered pixels"
        );
        // f32, no gradients: the SIMD RGB path.
        let t32 = Tape::<f32>::new();
        let (p32, c32) = (
            t32.constant(pos.mapv(|x| x as f32)),
            t32.constant(colors.mapv(|x| x as f32)),
        );
        let r = rasterize(to_clip(p32, &vp), faces.clone(), &s1).unwrap();
        let want = blend_hard(
            interpolate(c32, &r).unwrap(),
            &r.fragments,
            &[0.1, 0.2, 0.3],
        )
        .unwrap()
        .value()
        .unwrap();
        let got = render_attributes(to_clip(p32, &vp), c32, faces.clone(), &s, &[0.1, 0.2, 0.3])
            .unwrap()
            .value()
            .unwrap();
        assert!(got
            .iter()
            .zip(want.iter())
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        // With gradients: the same image and the three ops' gradients.
        let mut rng = Rng::new(3);
        let weights: Tensor<f64> = rng.uniform_tensor(&[45, 67, 4], -1.0, 1.0);
        let grads = |direct: bool| {
            let t = Tape::<f64>::new();
            let (p, c) = (t.leaf(pos.clone()), t.leaf(colors.clone()));
            let img = if direct {
                render_attributes(to_clip(p, &vp), c, faces.clone(), &s, &[0.1, 0.2, 0.3]).unwrap()
            } else {
                split(p, c, &faces, &vp, &s1)
            };
            let g = t
                .backward((img * t.constant(weights.clone())).sum())
                .unwrap();
            (g.wrt(p), g.wrt(c))
        };
        let (want, got) = (grads(false), grads(true));
        assert_eq!(got, want);
        assert!(got.0.iter().any(|&x| x != 0.0));
    }
    let t = Tape::<f64>::new();
    let (p, c) = (t.constant(pos), t.constant(colors));
    let s = RasterSettings::new(8, 8);
    assert!(render_attributes(to_clip(p, &vp), c, faces.clone(), &s, &[0.0; 2]).is_err());
    assert!(render_attributes(p, c, faces.clone(), &s, &[0.0; 3]).is_err());
    // The settings are validated as given, `faces_per_pixel` included.
    let bad_k = RasterSettings {
        faces_per_pixel: 0,
        ..s
    };
    assert!(render_attributes(to_clip(p, &vp), c, faces, &bad_k, &[0.0; 3]).is_err());
}
