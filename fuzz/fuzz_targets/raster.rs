//! The rasterizers (hard, SoftRas, DIB-R) on arbitrary triangle soups: the bytes become clip
//! coordinates (any f64 bit pattern, NaN and Inf included), faces, an image size and settings.
//! Every call returns finite images or a typed error, and its backward never panics.
#![no_main]

use std::sync::Arc;

use arbitrary::{Arbitrary, Unstructured};
use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::Tape;
use libfuzzer_sys::fuzz_target;
use render_ops::blend::blend_hard;
use render_ops::interpolate::interpolate;
use render_ops::raster::RasterSettings;
use render_ops::rasterize::rasterize;
use render_ops::soft::{dibr, softras, DibrSettings, SoftSettings};

#[derive(Debug)]
struct Soup {
    clip: Vec<[f64; 4]>,
    faces: Vec<[u32; 3]>,
    width: usize,
    height: usize,
    k: usize,
    cull: bool,
    sigma: f64,
}

impl<'a> Arbitrary<'a> for Soup {
    fn arbitrary(u: &mut Unstructured<'a>) -> arbitrary::Result<Self> {
        let nv = u.int_in_range(1..=16usize)?;
        let mut clip = Vec::with_capacity(nv);
        for _ in 0..nv {
            let mut v = [0.0; 4];
            for x in &mut v {
                // Mostly small on-screen values, otherwise any bit pattern.
                *x = if u.ratio(3, 4)? {
                    f64::from(u.int_in_range(-400i32..=400)?) / 100.0
                } else {
                    f64::from_bits(u.arbitrary()?)
                };
            }
            clip.push(v);
        }
        let nf = u.int_in_range(0..=32usize)?;
        let mut faces = Vec::with_capacity(nf);
        for _ in 0..nf {
            // Indices in range, so that errors come from the geometry, not the topology.
            let mut f = [0u32; 3];
            for i in &mut f {
                *i = u.int_in_range(0..=nv as u32 - 1)?;
            }
            faces.push(f);
        }
        Ok(Soup {
            clip,
            faces,
            width: u.int_in_range(1..=48)?,
            height: u.int_in_range(1..=48)?,
            k: u.int_in_range(1..=4)?,
            cull: u.arbitrary()?,
            sigma: [1e-4, 1e-3, 1e-2][u.int_in_range(0..=2usize)?],
        })
    }
}

fn check(tape: &Tape<f64>, img: autodiff::Var<'_, f64>) {
    let v = img.value().expect("an op that returned Ok has a value");
    assert!(v.iter().all(|x| x.is_finite()), "non-finite image");
    let _ = tape.backward(img.sum());
}

fuzz_target!(|s: Soup| {
    let nv = s.clip.len();
    let clip_t =
        ArrayD::from_shape_vec(IxDyn(&[nv, 4]), s.clip.iter().flatten().copied().collect())
            .unwrap();
    let cols = ArrayD::from_shape_fn(IxDyn(&[nv, 3]), |i| ((i[0] + i[1]) % 3) as f64 / 2.0);
    let faces = Arc::new(s.faces.clone());

    // Hard.
    let settings = RasterSettings {
        faces_per_pixel: s.k,
        cull_backfaces: s.cull,
        ..RasterSettings::new(s.width, s.height)
    };
    let tape = Tape::<f64>::new();
    let clip = tape.leaf(clip_t.clone());
    let col = tape.leaf(cols.clone());
    let img = rasterize(clip, faces.clone(), &settings).and_then(|r| {
        let c = interpolate(col, &r)?;
        blend_hard(c, &r.fragments, &[0.0, 0.0, 0.0])
    });
    if let Ok(img) = img {
        check(&tape, img);
    }

    // SoftRas.
    let tape = Tape::<f64>::new();
    let clip = tape.leaf(clip_t.clone());
    let col = tape.leaf(cols.clone());
    let mut ss = SoftSettings::new(s.width, s.height, 0.1, 10.0);
    ss.sigma = s.sigma;
    if let Ok(img) = softras(clip, col, faces.clone(), &ss) {
        check(&tape, img);
    }

    // DIB-R.
    let tape = Tape::<f64>::new();
    let clip = tape.leaf(clip_t);
    let col = tape.leaf(cols);
    let mut ds = DibrSettings::new(s.width, s.height);
    ds.cull_backfaces = s.cull;
    if let Ok(img) = dibr(clip, col, faces, &ds) {
        check(&tape, img);
    }
});
