//! Synthetic fitting targets: a face with seeded random coefficients, pose and light, rendered
//! (supersampled, hard rasterization) with pixel noise, and its exact 2D landmarks.

use std::sync::Arc;

use autodiff::rng::Rng;
use ndarray::Array3;
use render_ops::scene::Method;

use super::render::{FaceRenderer, RenderOptions};
use super::texture::{bake_textured, render_textured, textured_faces};
use super::{FaceParams, FitError, FitTarget, DEFAULT_DISTANCE_MM, SH_Y00};
use crate::morphable::Morphable;

/// Settings of [`synthesize`].
#[derive(Clone, Debug, PartialEq)]
pub struct SynthOptions {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Seed of every random choice.
    pub seed: u64,
    /// Standard deviation of the Gaussian pixel noise (colour units).
    pub noise_std: f64,
    /// Samples per pixel along each axis (box-filtered, CONVENTIONS' reference image).
    pub supersample: usize,
    /// Largest |yaw| (rotation about y), degrees.
    pub max_yaw_deg: f64,
    /// Largest |pitch| (about x), degrees.
    pub max_pitch_deg: f64,
    /// Largest |roll| (about z), degrees.
    pub max_roll_deg: f64,
    /// Scale of the identity coefficients (standard normal times this, cut at +-2.5).
    pub id_scale: f64,
    /// Scale of the expression coefficients (cut at +-2.5 times this).
    pub exp_scale: f64,
    /// Scale of the albedo coefficients (cut at +-2 times this).
    pub albedo_scale: f64,
    /// A random albedo texture instead of the per-vertex albedo on the textured faces
    /// ([`super::textured_faces`]): its side in texels and the relative amplitude of its
    /// detail ([`random_texture`]); `None`: per-vertex albedo only.
    pub texture: Option<(usize, f64)>,
}

impl SynthOptions {
    /// Defaults for a `width x height` image: noise 0.01, 2 x 2 supersampling, yaw within
    /// +-30, pitch +-20, roll +-15 degrees, coefficients drawn from the model's priors.
    pub fn new(width: usize, height: usize, seed: u64) -> Self {
        SynthOptions {
            width,
            height,
            seed,
            noise_std: 0.01,
            supersample: 2,
            max_yaw_deg: 30.0,
            max_pitch_deg: 20.0,
            max_roll_deg: 15.0,
            id_scale: 1.0,
            exp_scale: 0.7,
            albedo_scale: 0.7,
            texture: None,
        }
    }
}

/// A synthetic target and the parameters that made it.
#[derive(Clone, Debug)]
pub struct Synthetic {
    /// The image (noisy, in [0, 1]) and its exact landmarks (the model's landmarks).
    pub target: FitTarget,
    /// The true parameters.
    pub truth: FaceParams,
    /// The true albedo texture `[S, S, 3]` ([`SynthOptions::texture`]).
    pub texture: Option<Array3<f64>>,
}

/// Rotation matrix `Ry(yaw) Rx(pitch) Rz(roll)` (radians) as an axis-angle vector.
pub fn euler_to_axis_angle(yaw: f64, pitch: f64, roll: f64) -> [f64; 3] {
    let (sy, cy) = yaw.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    let (sr, cr) = roll.sin_cos();
    let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
    let rx = [[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]];
    let rz = [[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]];
    let mul = |a: [[f64; 3]; 3], b: [[f64; 3]; 3]| {
        a.map(|row| [0, 1, 2].map(|j| (0..3).map(|k| row[k] * b[k][j]).sum::<f64>()))
    };
    let m = mul(mul(ry, rx), rz);
    let tr = m[0][0] + m[1][1] + m[2][2];
    let angle = ((tr - 1.0) * 0.5).clamp(-1.0, 1.0).acos();
    let v = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]];
    if angle < 1e-12 {
        return [0.5 * v[0], 0.5 * v[1], 0.5 * v[2]];
    }
    let f = angle / (2.0 * angle.sin());
    [f * v[0], f * v[1], f * v[2]]
}

fn clipped(rng: &mut Rng, scale: f64, cut: f64) -> f64 {
    scale * rng.normal().clamp(-cut, cut)
}

/// Synthesises a target from `model`: random coefficients (seeded), a random head pose,
/// random SH light, rendered with `hard` at `supersample^2` samples per pixel, box-filtered,
/// plus Gaussian pixel noise, clamped to [0, 1]; the landmarks are the exact projections of the
/// model's landmarks.
pub fn synthesize(model: &Morphable<f64>, o: &SynthOptions) -> Result<Synthetic, FitError> {
    if o.width == 0 || o.height == 0 || o.supersample == 0 {
        return Err(FitError::Invalid(format!(
            "synthetic image {}x{} with supersampling {} is empty",
            o.width, o.height, o.supersample
        )));
    }
    let mut rng = Rng::new(o.seed);
    let mut p = FaceParams::neutral(model);
    p.z_id = (0..model.n_id())
        .map(|_| clipped(&mut rng, o.id_scale, 2.5))
        .collect();
    p.z_exp = (0..model.n_exp())
        .map(|_| clipped(&mut rng, o.exp_scale, 2.5))
        .collect();
    p.z_albedo = (0..model.n_albedo())
        .map(|_| clipped(&mut rng, o.albedo_scale, 2.0))
        .collect();
    let yaw = rng.uniform(-o.max_yaw_deg, o.max_yaw_deg).to_radians();
    let pitch = rng.uniform(-o.max_pitch_deg, o.max_pitch_deg).to_radians();
    let roll = rng.uniform(-o.max_roll_deg, o.max_roll_deg).to_radians();
    p.rotation = euler_to_axis_angle(yaw, pitch, roll);
    p.translation = [
        rng.uniform(-15.0, 15.0),
        rng.uniform(-15.0, 15.0),
        -DEFAULT_DISTANCE_MM + rng.uniform(-40.0, 40.0),
    ];
    // Light: ambient irradiance 0.75..1.05 with a slight tint, a directional part of
    // 0.2..0.45 from the front hemisphere, small second-order terms.
    let ambient = rng.uniform(0.75, 1.05);
    let mut sh = [[0.0; 3]; 9];
    for v in sh[0].iter_mut() {
        *v = ambient * rng.uniform(0.95, 1.05) / SH_Y00;
    }
    let (lx, ly) = (rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.8));
    let lz = (1.0 - lx * lx - ly * ly).max(0.1).sqrt();
    let norm = (lx * lx + ly * ly + lz * lz).sqrt();
    let m = rng.uniform(0.2, 0.45) / 0.488603;
    let dir = [ly / norm, lz / norm, lx / norm]; // order of Y_1-1 (y), Y_10 (z), Y_11 (x)
    for (row, d) in sh[1..4].iter_mut().zip(dir) {
        *row = [m * d; 3];
    }
    for row in sh.iter_mut().skip(4) {
        let v = rng.uniform(-0.04, 0.04) / 1.092548;
        *row = [v; 3];
    }
    p.sh = sh;

    let ss = o.supersample;
    let mut ro = RenderOptions::new(o.width * ss, o.height * ss);
    ro.method = Method::Hard;
    let renderer = FaceRenderer::new(model, ro)?;
    let (mut big, px) = renderer.render(&p)?;
    let texture = match o.texture {
        Some((size, amplitude)) => {
            let t = random_texture(model, &p, size, amplitude, &mut rng)?;
            let textured = Arc::new(textured_faces(model));
            big = render_textured(&renderer, &p, &t.clone().into_dyn(), &textured)?;
            Some(t)
        }
        None => None,
    };
    let inv = 1.0 / (ss * ss) as f64;
    let mut img = Array3::<f64>::zeros((o.height, o.width, 3));
    for r in 0..o.height {
        for c in 0..o.width {
            for k in 0..3 {
                let mut s = 0.0;
                for i in 0..ss {
                    for j in 0..ss {
                        s += big[[r * ss + i, c * ss + j, k]];
                    }
                }
                let noisy = s * inv + o.noise_std * rng.normal();
                img[[r, c, k]] = noisy.clamp(0.0, 1.0);
            }
        }
    }
    let points = model.landmark_points();
    let landmarks = match points
        .iter()
        .map(|q| q.as_vertex())
        .collect::<Option<Vec<_>>>()
    {
        Some(vertices) => px.select(ndarray::Axis(0), &vertices),
        None => renderer.landmarks_px(&p, &points)?,
    } / ss as f64;
    Ok(Synthetic {
        target: FitTarget {
            image: img,
            landmarks,
            points,
        },
        truth: p,
        texture,
    })
}

/// A random albedo texture `[size, size, 3]`: the per-vertex albedo of `p` on the textured faces
/// baked into uv space ([`bake_textured`]) times `1 + d(u, v)`, clamped to [0, 1], where the detail `d` is a sum of
/// eight random plane waves (2 to 24 cycles across the uv square, random direction, phase and
/// per-channel weight) scaled so that `|d| <= amplitude`: freckle- to cheek-sized variation that
/// no per-vertex albedo on ICT's mesh represents exactly.
pub fn random_texture(
    model: &Morphable<f64>,
    p: &FaceParams,
    size: usize,
    amplitude: f64,
    rng: &mut Rng,
) -> Result<Array3<f64>, FitError> {
    if size < 2 || !(0.0..1.0).contains(&amplitude) {
        return Err(FitError::Invalid(format!(
            "random texture of side {size} and amplitude {amplitude}: need side >= 2 and amplitude in [0, 1)"
        )));
    }
    let baked = bake_textured(model, &textured_faces(model), &p.albedo(model)?, size)?;
    let waves: Vec<([f64; 2], f64, [f64; 3])> = (0..8)
        .map(|_| {
            let cycles = rng.uniform(2.0, 24.0);
            let angle = rng.uniform(0.0, std::f64::consts::TAU);
            let phase = rng.uniform(0.0, std::f64::consts::TAU);
            let w = [
                rng.uniform(0.5, 1.0),
                rng.uniform(0.5, 1.0),
                rng.uniform(0.5, 1.0),
            ];
            ([cycles * angle.cos(), cycles * angle.sin()], phase, w)
        })
        .collect();
    let scale = amplitude / waves.len() as f64;
    let n = size as f64;
    Ok(Array3::from_shape_fn((size, size, 3), |(r, c, k)| {
        let (u, v) = ((c as f64 + 0.5) / n, 1.0 - (r as f64 + 0.5) / n);
        let d: f64 = waves
            .iter()
            .map(|(f, phase, w)| {
                w[k] * (std::f64::consts::TAU * (f[0] * u + f[1] * v) + phase).sin()
            })
            .sum();
        (baked.texels[[r, c, k]] * (1.0 + scale * d)).clamp(0.0, 1.0)
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Without detail the random texture is the baked albedo of the textured faces; with it,
    /// every texel stays within the amplitude of that (before the clamp to [0, 1]); bad sizes
    /// and amplitudes are errors.
    #[test]
    fn random_texture_is_the_baked_albedo_times_bounded_detail() {
        let m = crate::face::default_face::<f64>();
        let p = FaceParams::neutral(&m);
        let baked = bake_textured(&m, &textured_faces(&m), &p.albedo(&m).unwrap(), 32).unwrap();
        let flat = random_texture(&m, &p, 32, 0.0, &mut Rng::new(1)).unwrap();
        assert_eq!(flat, baked.texels);
        let t = random_texture(&m, &p, 32, 0.3, &mut Rng::new(1)).unwrap();
        assert_ne!(t, baked.texels);
        for (x, b) in t.iter().zip(baked.texels.iter()) {
            let (lo, hi) = ((b * 0.7).max(0.0), (b * 1.3).min(1.0));
            assert!(
                *x >= lo - 1e-12 && *x <= hi + 1e-12,
                "{x} outside [{lo}, {hi}]"
            );
        }
        for (size, amp) in [(1, 0.1), (32, -0.1), (32, 1.0), (32, f64::NAN)] {
            assert!(random_texture(&m, &p, size, amp, &mut Rng::new(1)).is_err());
        }
    }
}
