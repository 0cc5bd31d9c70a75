//! A shader that is not built in: a soft toon step (two diffuse bands blended by a sigmoid)
//! plus a Schlick-Fresnel rim light, written as a closure over `FragmentInputs`.
//!
//! The example
//! 1. renders it on an icosphere and writes `out/custom_shader.png`;
//! 2. gradient-checks the whole pipeline (rasterize + interpolate + shader + hard blend) in
//!    f64 on interior pixels, with respect to the vertex positions and the shader parameters;
//! 3. fits the toon threshold back from a rendered image with Adam.
//!
//! `cargo run --release --example custom_shader`

use std::sync::Arc;

use tapestry::autodiff::gradcheck::{gradcheck, GradcheckOptions};
use tapestry::autodiff::optim::Adam;
use tapestry::autodiff::rng::Rng;
use tapestry::autodiff::{Real, Tape, Tensor, Var};
use tapestry::render_ops::camera::Camera;
use tapestry::render_ops::mesh::Mesh;
use tapestry::render_ops::raster::RasterSettings;
use tapestry::render_ops::rasterize::rasterize;
use tapestry::render_ops::shade::{render_shader, FragmentInputs, MeshAttributes};
use tapestry::render_ops::transform::to_clip;

type Error = Box<dyn std::error::Error>;

/// Parameters of the shader, as tape variables (so they can be fitted).
struct ToonRim<'t, T: Real> {
    /// Toon step position in `n . l` ([1]).
    threshold: Var<'t, T>,
    /// Rim strength ([1]).
    rim: Var<'t, T>,
}

/// The custom shader: `albedo * (dark + (lit - dark) * sigmoid((n.l - threshold) / softness))
/// + rim * rim_colour * (F0 + (1 - F0) (1 - n.v)^5)` (Schlick's Fresnel approximation).
fn toon_rim<'t, T: Real>(f: &FragmentInputs<'t, T>, p: &ToonRim<'t, T>) -> Var<'t, T> {
    let t = f.position.tape();
    let c = |x: f64| T::from_f64c(x);
    let vec3 = |a: [f64; 3]| {
        t.constant(Tensor::from_shape_vec(ndarray::IxDyn(&[3]), a.map(c).to_vec()).unwrap())
    };
    // Light from the upper left front.
    let to_light = vec3([-0.4, 0.6, 0.7]).normalize(c(1e-12));
    let ndl = (f.normal * to_light).sum_axes(&[-1], true);
    let step = ((ndl - p.threshold) * c(1.0 / 0.08)).sigmoid();
    let albedo = vec3([0.9, 0.45, 0.3]);
    let diffuse = albedo * (step * c(0.75) + c(0.2));
    let ndv = (f.normal * f.view_dir).sum_axes(&[-1], true);
    let fresnel = (-ndv + c(1.0)).relu().powf(c(5.0)) * c(0.96) + c(0.04);
    diffuse + fresnel * p.rim * vec3([0.3, 0.6, 1.0])
}

fn scalar<T: Real>(x: f64) -> Tensor<T> {
    Tensor::from_elem(ndarray::IxDyn(&[1]), T::from_f64c(x))
}

/// Renders the mesh with the shader: `[H, W, 4]`.
fn render<'t, T: Real>(
    positions: Var<'t, T>,
    faces: &Arc<Vec<[u32; 3]>>,
    cam: &Camera,
    size: usize,
    params: &ToonRim<'t, T>,
) -> Result<Var<'t, T>, Error> {
    let t = positions.tape();
    let clip = to_clip(positions, &cam.view_proj());
    let r = rasterize(clip, faces.clone(), &RasterSettings::new(size, size))?;
    let eye = t.constant(Tensor::from_shape_vec(
        ndarray::IxDyn(&[3]),
        cam.eye().map(T::from_f64c).to_vec(),
    )?);
    let mesh = MeshAttributes::new(positions);
    let bg = [T::from_f64c(0.05); 3];
    Ok(render_shader(&r, &mesh, eye, |f| toon_rim(f, params), &bg)?)
}

fn positions<T: Real>(mesh: &Mesh<f64>) -> Tensor<T> {
    Tensor::from_shape_vec(
        ndarray::IxDyn(&[mesh.positions.len(), 3]),
        mesh.positions
            .iter()
            .flatten()
            .map(|&x| T::from_f64c(x))
            .collect(),
    )
    .expect("v x 3")
}

fn main() -> Result<(), Error> {
    let cam = Camera::perspective_look_at(
        [0.0, 0.2, 3.0],
        [0.0; 3],
        [0.0, 1.0, 0.0],
        45f64.to_radians(),
        1.0,
        0.5,
        10.0,
    )?;

    // 1. Render.
    let mesh = Mesh::<f64>::icosphere(4, 1.0);
    let faces = Arc::new(mesh.faces.clone());
    let tape = Tape::<f32>::new();
    let params = ToonRim {
        threshold: tape.leaf(scalar(0.3)),
        rim: tape.leaf(scalar(0.8)),
    };
    let img = render(tape.constant(positions(&mesh)), &faces, &cam, 256, &params)?.value()?;
    std::fs::create_dir_all("out")?;
    let rgb = img
        .slice(ndarray::s![.., .., 0..3])
        .into_dimensionality::<ndarray::Ix3>()?;
    tapestry::render_ops::io::write_png("out/custom_shader.png", &rgb)?;
    println!("wrote out/custom_shader.png (256 x 256)");

    // 2. End-to-end gradient check in f64 on interior pixels (pixels whose fragment is at least
    // 0.05 inside its face in barycentric terms, so small moves do not change coverage).
    let small = Mesh::<f64>::icosphere(1, 1.0);
    let sfaces = Arc::new(small.faces.clone());
    let size = 24;
    let weights = {
        let t = Tape::<f64>::new();
        let r = rasterize(
            to_clip(t.constant(positions(&small)), &cam.view_proj()),
            sfaces.clone(),
            &RasterSettings::new(size, size),
        )?;
        let f = &r.fragments;
        let mut rng = Rng::new(7);
        let mut w = Tensor::<f64>::zeros(ndarray::IxDyn(&[size, size, 4]));
        for p in 0..f.num_pixels() {
            if let Some(fr) = f.nearest(p) {
                if fr.bary.iter().all(|&b| b > 0.05) {
                    let (row, col) = f.pixel_coords(p);
                    for k in 0..4 {
                        w[[row, col, k]] = rng.normal();
                    }
                }
            }
        }
        w
    };
    let report = gradcheck(
        |t: &Tape<f64>, v: &[Var<'_, f64>]| {
            let p = ToonRim {
                threshold: v[1],
                rim: v[2],
            };
            let img = render(v[0], &sfaces, &cam, size, &p).expect("render");
            (img * t.constant(weights.clone())).sum()
        },
        &[positions(&small), scalar(0.25), scalar(0.7)],
        &GradcheckOptions::default(),
    )?;
    print!("gradcheck (positions, threshold, rim):\n{report}");
    if !report.passed() {
        return Err("gradient check failed".into());
    }

    // 3. Fit the toon threshold from an image rendered with threshold 0.3 (start at -0.2).
    let size = 64;
    let target = {
        let t = Tape::<f64>::new();
        let p = ToonRim {
            threshold: t.constant(scalar(0.3)),
            rim: t.constant(scalar(0.8)),
        };
        (*render(t.constant(positions(&mesh)), &faces, &cam, size, &p)?.value()?).clone()
    };
    let mut threshold = scalar::<f64>(-0.2);
    let mut adam = Adam::new(0.02);
    for it in 0..150 {
        let t = Tape::<f64>::new();
        let p = ToonRim {
            threshold: t.leaf(threshold.clone()),
            rim: t.constant(scalar(0.8)),
        };
        let img = render(t.constant(positions(&mesh)), &faces, &cam, size, &p)?;
        let loss = (img - t.constant(target.clone())).square().mean();
        let g = t.backward(loss)?.wrt(p.threshold);
        adam.step([(&mut threshold, &g)])?;
        if it % 30 == 0 {
            println!(
                "iter {it:3}: loss {:.3e}, threshold {:.4}",
                loss.item()?,
                threshold[0]
            );
        }
    }
    println!("fitted threshold {:.4} (truth 0.3)", threshold[0]);
    if (threshold[0] - 0.3).abs() > 1e-2 {
        return Err("the threshold fit did not converge".into());
    }
    Ok(())
}
