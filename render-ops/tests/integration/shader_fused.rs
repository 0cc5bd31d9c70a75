//! `render_shader` runs the user's shader fused (`autodiff::Tape::fused`): the image and the
//! gradients equal the eager composition (`fragment_inputs` + the shader + `blend_hard`) in f64
//! and f32 (bit for bit, except the gradients of shader parameters broadcast over fragments,
//! summed per chunk then over chunks: within 1e-12 relative in f64, 1e-4 in f32, sums of
//! some 2,000 fragments with cancellation), and a shader with ops the fuser
//! does not handle (a matmul, a concat) still works, giving the eager result.

use std::sync::Arc;

use crate::common::scenes::ToonScene;
use autodiff::{Real, Tape, Tensor, Var};
use ndarray::IxDyn;
use render_ops::blend::blend_hard;
use render_ops::mesh::Mesh;
use render_ops::raster::RasterSettings;
use render_ops::rasterize::rasterize;
use render_ops::shade::{fragment_inputs, render_shader, FragmentInputs, MeshAttributes};
use render_ops::transform::to_clip;

/// The toon/rim shader of `examples/custom_shader.rs`.
fn toon_rim<'t, T: Real>(f: &FragmentInputs<'t, T>, th: Var<'t, T>, rim: Var<'t, T>) -> Var<'t, T> {
    let t = f.position.tape();
    let c = |x: f64| T::from_f64c(x);
    let vec3 =
        |a: [f64; 3]| t.constant(Tensor::from_shape_vec(IxDyn(&[3]), a.map(c).to_vec()).unwrap());
    let to_light = vec3([-0.4, 0.6, 0.7]).normalize(c(1e-12));
    let ndl = (f.normal * to_light).sum_axes(&[-1], true);
    let step = ((ndl - th) * c(1.0 / 0.08)).sigmoid();
    let diffuse = vec3([0.9, 0.45, 0.3]) * (step * c(0.75) + c(0.2));
    let ndv = (f.normal * f.view_dir).sum_axes(&[-1], true);
    let fresnel = (-ndv + c(1.0)).relu().powf(c(5.0)) * c(0.96) + c(0.04);
    diffuse + fresnel * rim * vec3([0.3, 0.6, 1.0])
}

/// A shader mixing fused arithmetic with ops the fuser does not handle.
fn mixed<'t, T: Real>(f: &FragmentInputs<'t, T>, th: Var<'t, T>, rim: Var<'t, T>) -> Var<'t, T> {
    let t = f.position.tape();
    let m = t.constant(Tensor::from_shape_fn(IxDyn(&[3, 3]), |i| {
        T::from_f64c(0.1 * (i[0] * 3 + i[1]) as f64 - 0.3)
    }));
    let a = (f.normal * th).tanh();
    let b = a.matmul(m); // eager
    let c = (b * f.view_dir + rim).sigmoid();
    let d = t.concat(&[c.slice(-1, 0, 2), a.slice(-1, 2, 3)], 1); // eager
    d * c + a
}

/// A shader: fragment inputs and the two parameters (threshold, rim) to colours.
type Shader<T> = for<'t> fn(&FragmentInputs<'t, T>, Var<'t, T>, Var<'t, T>) -> Var<'t, T>;

struct Out<T> {
    img: Tensor<T>,
    grads: Vec<Tensor<T>>,
}

fn render<T: Real>(fused: bool, shader: Shader<T>) -> Out<T> {
    let mesh = Mesh::<f64>::icosphere(2, 1.0);
    let cam = ToonScene::camera();
    let faces = Arc::new(mesh.faces.clone());
    let tape = Tape::<T>::new();
    let pos = tape.leaf(
        Tensor::from_shape_vec(
            IxDyn(&[mesh.positions.len(), 3]),
            mesh.positions
                .iter()
                .flatten()
                .map(|&x| T::from_f64c(x))
                .collect(),
        )
        .unwrap(),
    );
    let th = tape.leaf(Tensor::from_elem(IxDyn(&[1]), T::from_f64c(0.3)));
    let rim = tape.leaf(Tensor::from_elem(IxDyn(&[1]), T::from_f64c(0.8)));
    let r = rasterize(
        to_clip(pos, &cam.view_proj()),
        faces,
        &RasterSettings::new(64, 64),
    )
    .unwrap();
    let eye = tape.constant(
        Tensor::from_shape_vec(IxDyn(&[3]), cam.eye().map(T::from_f64c).to_vec()).unwrap(),
    );
    let attrs = MeshAttributes::new(pos);
    let bg = [T::from_f64c(0.05); 3];
    let img = if fused {
        render_shader(&r, &attrs, eye, |f| shader(f, th, rim), &bg).unwrap()
    } else {
        let f = fragment_inputs(&r, &attrs, eye).unwrap();
        blend_hard(shader(&f, th, rim), &r.fragments, &bg).unwrap()
    };
    let w = tape.constant(autodiff::rng::Rng::new(3).normal_tensor(&img.shape()));
    let g = tape.backward((img * w).sum()).unwrap();
    Out {
        img: (*img.value().unwrap()).clone(),
        grads: vec![g.wrt(pos), g.wrt(th), g.wrt(rim)],
    }
}

fn assert_bits<T: Real>(a: &Tensor<T>, b: &Tensor<T>, what: &str) {
    assert_eq!(a.shape(), b.shape());
    for (i, (x, y)) in a.iter().zip(b.iter()).enumerate() {
        assert!(
            x.to_f64c().to_bits() == y.to_f64c().to_bits(),
            "{what} ({}): element {i}: {x} vs {y}",
            T::NAME
        );
    }
}

fn compare<T: Real>(shader: Shader<T>, rtol: f64) {
    let (f, e) = (render::<T>(true, shader), render::<T>(false, shader));
    assert!(f.img.iter().any(|&v| v != T::zero()));
    assert_bits(&f.img, &e.img, "image");
    assert_bits(&f.grads[0], &e.grads[0], "position gradient");
    for k in 1..3 {
        let (a, b) = (f.grads[k][[0]].to_f64c(), e.grads[k][[0]].to_f64c());
        assert!(
            b != 0.0 && (a - b).abs() <= rtol * b.abs(),
            "parameter {k}: {a} vs {b}"
        );
    }
}

#[test]
fn render_shader_fused_equals_eager() {
    compare::<f64>(toon_rim, 1e-12);
    compare::<f32>(toon_rim, 1e-4);
}

#[test]
fn unsupported_ops_inside_a_shader_fall_back_to_eager() {
    compare::<f64>(mixed, 1e-12);
    compare::<f32>(mixed, 1e-4);
}
