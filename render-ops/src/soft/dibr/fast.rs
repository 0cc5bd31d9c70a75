//! The `f32` fast path of DIB-R's soft silhouette: the same forward and backward as the `f64`
//! evaluation of [`super`], with the per-pair work done eight pixels of a row span at a time in
//! single precision ([`crate::simd`], [`crate::soft::lanes`]), as SoftRas's fast path.
//!
//! Taken for `f32` tapes whose constants (`1 / delta`, the squared cut-off and `ln(1 /
//! threshold)`) are normal `f32` numbers ([`f32_range_ok`]). The forward runs over bands of
//! whole image rows in parallel (each face over the row spans of its cut-off region within the
//! band, in face order) and keeps each pixel's `P = prod_j f_j`, `f_j = 1 - e_j`, `e_j =
//! exp(-x_j)`, with the `f32` factors multiplied in `f64` (an `f32` product underflows where a
//! few dozen faces are near a pixel, as at 80k faces and 512 x 512); where `P >= 1/2` the
//! alpha is `-expm1(sum ln(1 - e_j))` with the logs taken in `f64` from the `f32` `e_j`, as the
//! `f64` path. The backward runs in parallel over faces, each re-evaluating its own pairs and
//! taking `prod_{k != j} f_k = P / f_j` (in `f64`) from the forward's `P` where `P` is a normal
//! `f64` number, and from the `f64` leave-one-out product of [`super`] elsewhere (no division
//! by a vanishing `f_j`: a factor that rounds to 0 in `f32` makes `P = 0`). Per-pixel products run in face
//! order and per-face sums in row-major order with a fixed lane order, so results are
//! bit-identical for any thread count, and the AVX2 and portable builds agree bit for bit.

use std::mem::MaybeUninit;

use super::{DibrAlphaOp, DibrSettings, Prep};
use crate::simd::{arr3, avx2_method, exp8, lanes, select, F8, LANES, M8};
use crate::soft::common::{closest_backward, exp};
use crate::soft::lanes::{add_closest_grad, band_rows, lanes_to, offsets, Edges8, Geom32};

/// [`Prep::p64`] of a pixel whose centre a face covers (alpha 1, no gradient).
pub(super) const COVERED64: f64 = -1.0;

/// Whether the settings' constants are normal `f32` numbers (`1 / delta`, the squared cut-off
/// and `ln(1 / threshold)`): otherwise the `f64` evaluation runs.
pub(super) fn f32_range_ok(s: &DibrSettings) -> bool {
    [1.0 / s.delta, s.cutoff_sq(), s.cutoff_x()]
        .iter()
        .all(|&v| v.abs() >= f32::MIN_POSITIVE as f64 && v.abs() <= f32::MAX as f64)
}

/// Constants of one render.
#[derive(Clone, Copy)]
struct K {
    inv_delta: f32,
    cut2: f32,
    xmax: f32,
}

impl K {
    fn new(s: &DibrSettings) -> Self {
        Self {
            inv_delta: (1.0 / s.delta) as f32,
            cut2: s.cutoff_sq() as f32,
            xmax: s.cutoff_x() as f32,
        }
    }
}

/// One face against eight pixel centres of a row chunk (as [`DibrAlphaOp::term`] per lane):
/// the lanes whose centre the face covers, the near lanes (outside, `0 < x <= ln(1 /
/// threshold)`) with `x = d^2 / delta`, the closest points on the edges and which edge is the
/// nearest (the first one winning ties).
struct Near8 {
    covered: M8,
    near: M8,
    x: F8,
    ed: Edges8,
    sel: [M8; 3],
}

/// [`Near8`] of face `g` at the pixel centres `(o_x + qx, o_y + qy)` of the lanes `valid`, or
/// `None` when no lane is covered or near.
#[inline(always)]
fn near8(g: &Geom32, qx: F8, qy: f32, valid: M8, k: &K) -> Option<Near8> {
    let zero = F8::splat(0.0);
    let w: [F8; 3] =
        arr3(|i| F8::splat(g.bw[i][0]) + F8::splat(g.bw[i][1]) * qx + F8::splat(g.bw[i][2] * qy));
    let inside = w[0].ge(zero) & w[1].ge(zero) & w[2].ge(zero);
    // Lower bound of the distance of an outside centre: beyond one of the edge lines.
    let dob = (-(w[0] * F8::splat(g.alt[0])))
        .max(-(w[1] * F8::splat(g.alt[1])))
        .max(-(w[2] * F8::splat(g.alt[2])));
    let cand = valid & !inside & (dob * dob).le(F8::splat(k.cut2));
    let inside = valid & inside;
    if !(inside | cand).any() {
        return None;
    }
    let ed = Edges8::new(g, qx, qy);
    let (d2o, sel) = ed.nearest();
    let x = d2o * F8::splat(k.inv_delta);
    Some(Near8 {
        covered: inside | (cand & x.le(zero)),
        near: cand & x.gt(zero) & x.le(F8::splat(k.xmax)),
        x,
        ed,
        sel,
    })
}

/// `(e, f) = (exp(-x), 1 - exp(-x))` of the near lanes, `(0, 1)` elsewhere.
#[inline(always)]
fn factors(n: &Near8) -> (F8, F8) {
    let e = select(n.near, exp8(-n.x), F8::splat(0.0));
    (e, F8::splat(1.0) - e)
}

/// One chunk of near pairs of the forward, for its faint-coverage pass: `e = exp(-x)` per lane
/// (0 on the other lanes).
#[derive(Clone, Copy)]
struct Chunk {
    lp: usize,
    e: F8,
}

/// Per-thread scratch of the `f32` forward (band-local row-major pixels, [`band_rows`] x
/// `width`, plus [`LANES`] of padding for chunks running past the last column).
pub(super) struct Scratch32 {
    chunks: Vec<Chunk>,
    prod: Vec<f64>,
    /// 1 where a face covers the pixel centre, else 0.
    cov: Vec<f32>,
    lsum: Vec<f64>,
}

impl Scratch32 {
    pub(super) fn new(width: usize) -> Self {
        let n = band_rows(width) * width + LANES;
        Self {
            chunks: Vec::with_capacity(n),
            prod: vec![0.0; n],
            cov: vec![0.0; n],
            lsum: vec![0.0; n],
        }
    }
}

impl DibrAlphaOp {
    avx2_method! {
        /// [`DibrAlphaOp::tile_samples`] and the alpha in `f32`, 8 pixels at a time, over band
        /// `band` of [`band_rows`] image rows with its faces `tf`
        /// ([`crate::soft::lanes::band_faces`]), into the band's rows of the alpha image (`img`)
        /// and of [`Prep::p64`] (`p64`).
        pub(super) fn band_forward32 => band_forward32_impl(
            prep: &Prep,
            band: usize,
            tf: &[u32],
            sc: &mut Scratch32,
            img: &mut [f32],
            p64: &mut [MaybeUninit<f64>],
        ) for DibrAlphaOp
    }

    #[inline(always)]
    fn band_forward32_impl(
        &self,
        prep: &Prep,
        band: usize,
        tf: &[u32],
        sc: &mut Scratch32,
        img: &mut [f32],
        p64: &mut [MaybeUninit<f64>],
    ) {
        let s = &self.s;
        let bins = &prep.bins;
        let pxp = &prep.pxp[..];
        let w = s.width;
        let rows = band_rows(w);
        let r_base = band * rows;
        let r_last = (r_base + rows).min(s.height) - 1;
        let np = (r_last + 1 - r_base) * w;
        let k = K::new(s);
        let Scratch32 {
            chunks,
            prod,
            cov,
            lsum,
        } = sc;
        let (prod, cov, lsum) = (
            &mut prod[..np + LANES],
            &mut cov[..np + LANES],
            &mut lsum[..np],
        );
        chunks.clear();
        prod.fill(1.0);
        cov.fill(0.0);
        lsum.fill(0.0);
        let one = F8::splat(1.0);
        // P = prod f over the faces in face order; covered centres marked (their later
        // factors are skipped, as the `f64` path does).
        for &fi in tf.iter() {
            let g = prep.g32[fi as usize];
            for (row, py, a, b) in bins.face_rows(fi as usize).within(r_base, r_last) {
                let qy = (py - g.o[1]) as f32;
                let mut cs = a;
                while cs <= b {
                    let lp = (row - r_base) * w + cs;
                    let cov8 = F8::load(&cov[lp..]);
                    let valid = lanes_to(cs, b) & cov8.lt(one);
                    if valid.any() {
                        if let Some(n) = near8(&g, offsets(pxp, cs, g.o[0]), qy, valid, &k) {
                            if n.covered.any() {
                                select(n.covered, one, cov8).store(&mut cov[lp..]);
                            }
                            if n.near.any() {
                                let (e, f) = factors(&n);
                                for (p, &f) in prod[lp..lp + LANES].iter_mut().zip(&f.0) {
                                    *p *= f as f64;
                                }
                                chunks.push(Chunk { lp, e });
                            }
                        }
                    }
                    cs += LANES;
                }
            }
        }
        // Faint coverage (P >= 1/2): sum ln(1 - e) in f64, in face order (near lanes lie in
        // their row's span, so within the band's pixels).
        for ck in chunks.iter() {
            let faint = ck.e.gt(F8::splat(0.0));
            if faint.any() {
                for l in 0..LANES {
                    if faint.lane(l) && prod[ck.lp + l] >= 0.5 {
                        lsum[ck.lp + l] += (-(ck.e.0[l] as f64)).ln_1p();
                    }
                }
            }
        }
        for (lp, (a, po)) in img[..np].iter_mut().zip(&mut p64[..np]).enumerate() {
            if cov[lp] != 0.0 {
                *a = 1.0;
                po.write(COVERED64);
                continue;
            }
            let p = prod[lp];
            *a = (if p < 0.5 { 1.0 - p } else { -lsum[lp].exp_m1() }) as f32;
            po.write(p);
        }
    }

    avx2_method! {
        /// [`DibrAlphaOp::face_gradient`] in `f32`, 8 pixels at a time (`gp`: the alpha
        /// gradient with covered pixels zeroed, padded by [`LANES`]): per-face sums in `f32`
        /// vectors, their lanes added in `f64` at the end.
        pub(super) fn face_gradient32 => face_gradient32_impl(
            prep: &Prep,
            fi: usize,
            gp: &[f32],
            acc: &mut [f64],
        ) for DibrAlphaOp
    }

    #[inline(always)]
    fn face_gradient32_impl(&self, prep: &Prep, fi: usize, gp: &[f32], acc: &mut [f64]) {
        let s = &self.s;
        let bins = &prep.bins;
        let rc = bins.rects[fi];
        if rc[0] > rc[1] {
            return;
        }
        let g = prep.g32[fi];
        let geom = &bins.geoms[fi];
        let k = K::new(s);
        let zero = F8::splat(0.0);
        // d(gA)/d(d2) = gA dA/dx / delta, times -2 for the closest point's vertices.
        let scale = F8::splat(-2.0 * k.inv_delta);
        let mut vgv = [[zero; 2]; 3];
        // Lanes where P is not a normal f64 number: the f64 leave-one-out product.
        let mut gv64 = [[0.0f64; 2]; 3];
        for (row, py, a, b) in bins.face_rows(fi) {
            let qy = (py - g.o[1]) as f32;
            let mut cs = a;
            while cs <= b {
                let pi = row * s.width + cs;
                let g8 = F8::load(&gp[pi..]);
                let valid = lanes_to(cs, b) & (g8.lt(zero) | g8.gt(zero));
                let col = cs;
                cs += LANES;
                if !valid.any() {
                    continue;
                }
                let Some(n) = near8(&g, offsets(&prep.pxp, col, g.o[0]), qy, valid, &k) else {
                    continue;
                };
                if !n.near.any() {
                    continue;
                }
                let (e, f) = factors(&n);
                let p8: &[f64; LANES] = prep.p64[pi..pi + LANES].try_into().expect("eight");
                let ok = M8(lanes(|l| {
                    if n.near.lane(l) && p8[l] >= f64::MIN_POSITIVE {
                        u32::MAX
                    } else {
                        0
                    }
                }));
                // dA/dx_j = -prod_{k != j} f_k e_j, the leave-one-out product in f64.
                let excl = F8(lanes(|l| {
                    if ok.lane(l) {
                        (p8[l] / f.0[l] as f64) as f32
                    } else {
                        0.0
                    }
                }));
                let gd2 = -(g8 * excl * e) * scale;
                add_closest_grad(&mut vgv, &n.sel, &n.ed.t, &n.ed.rx, &n.ed.ry, gd2);
                let rest = n.near & !ok;
                if rest.any() {
                    for l in 0..LANES {
                        if rest.lane(l) {
                            let c = col + l;
                            let q = geom.closest([bins.px[c], py]);
                            let x = q.d2 / s.delta;
                            let excl = self.leave_one_out(prep, fi, row, c);
                            let gx = -(g8.0[l] as f64) * excl * exp(-x);
                            closest_backward(&q, gx / s.delta, &mut gv64);
                        }
                    }
                }
            }
        }
        let gv = std::array::from_fn(|kk| {
            [
                vgv[kk][0].sum_f64() + gv64[kk][0],
                vgv[kk][1].sum_f64() + gv64[kk][1],
            ]
        });
        self.store_face_gradient(prep, fi, gv, acc);
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use autodiff::ndarray::{ArrayD, IxDyn};
    use autodiff::{Real, Tape};

    use crate::mesh::Mesh;
    use crate::simd::set_force_portable;
    use crate::soft::lanes::test_support::{peers_view_proj, rel_l2};
    use crate::soft::{dibr_alpha, DibrSettings};
    use crate::transform::to_clip;

    /// Alpha and position gradient of `faces` over `pos` under the peers' camera, loss
    /// `sum((alpha - 0.25)^2)`, on a `T` tape with `threads` threads (back faces culled with
    /// `cull`).
    fn render<T: Real>(
        pos: &[[f64; 3]],
        faces: &[[u32; 3]],
        size: usize,
        delta: f64,
        threads: usize,
        cull: bool,
    ) -> (Vec<f64>, Vec<f64>) {
        let p = ArrayD::from_shape_vec(
            IxDyn(&[pos.len(), 3]),
            pos.iter().flatten().map(|&x| T::from_f64c(x)).collect(),
        )
        .unwrap();
        let vp = peers_view_proj();
        let faces = Arc::new(faces.to_vec());
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let tape = Tape::<T>::new();
            let pv = tape.var(p.clone(), true);
            let mut s = DibrSettings::new(size, size);
            s.delta = delta;
            s.cull_backfaces = cull;
            let a = dibr_alpha(to_clip(pv, &vp), faces.clone(), &s).unwrap();
            let target = tape.constant(ArrayD::from_elem(IxDyn(&[size, size]), T::from_f64c(0.25)));
            let g = tape.backward((a - target).square().sum()).unwrap();
            let f = |t: &ArrayD<T>| t.iter().map(|x| x.to_f64c()).collect::<Vec<f64>>();
            (f(&a.value().unwrap()), f(g.get(pv).unwrap()))
        })
    }

    fn sphere(subdiv: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let m = Mesh::<f64>::icosphere(subdiv, 1.0);
        (m.positions.clone(), m.faces.clone())
    }

    fn max_diff(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
    }

    /// The `f32` fast path against the `f64` evaluation: alpha within `f32` precision (up to
    /// pairs at the cut-off), position gradients within a small relative error.
    #[test]
    fn f32_path_matches_f64() {
        for (subdiv, size, delta, cull) in [
            (2, 64, 1e-3, false),
            (3, 96, 1.43e-4, false),
            (4, 128, 3e-5, false),
            (3, 96, 1.43e-4, true),
        ] {
            let (pos, faces) = sphere(subdiv);
            let (a32, g32) = render::<f32>(&pos, &faces, size, delta, 2, cull);
            let (a64, g64) = render::<f64>(&pos, &faces, size, delta, 2, cull);
            let (da, eg) = (max_diff(&a32, &a64), rel_l2(&g32, &g64));
            eprintln!("subdiv {subdiv} size {size} delta {delta} cull {cull}: alpha {da:.2e}, grad l2 {eg:.2e}");
            assert!(g32.iter().all(|x| x.is_finite()));
            assert!(da < 1e-4, "alpha {da}");
            assert!(eg < 1e-4, "positions {eg}");
        }
    }

    /// Same bits for 1 and 3 threads and from the portable build, on an image whose height is
    /// not a multiple of the band height and whose width is not a multiple of 8.
    #[test]
    fn f32_path_deterministic() {
        let size = 75;
        assert_ne!(size % crate::soft::lanes::band_rows(size), 0);
        let (pos, faces) = sphere(3);
        let a = render::<f32>(&pos, &faces, size, 1.43e-4, 1, false);
        assert!(
            a == render::<f32>(&pos, &faces, size, 1.43e-4, 3, false),
            "3 threads differ"
        );
        set_force_portable(true);
        let b = render::<f32>(&pos, &faces, size, 1.43e-4, 2, false);
        set_force_portable(false);
        assert!(a == b, "portable build differs");
    }

    /// Alpha and clip-position gradient of one triangle given in clip space (`w = 1`, so NDC
    /// = clip), loss `sum((alpha - 0.25)^2)`.
    fn render_clip<T: Real>(clip: &[[f64; 4]], size: usize, delta: f64) -> (Vec<f64>, Vec<f64>) {
        let c = ArrayD::from_shape_vec(
            IxDyn(&[clip.len(), 4]),
            clip.iter().flatten().map(|&x| T::from_f64c(x)).collect(),
        )
        .unwrap();
        let tape = Tape::<T>::new();
        let cv = tape.var(c, true);
        let mut s = DibrSettings::new(size, size);
        s.delta = delta;
        let a = dibr_alpha(cv, Arc::new(vec![[0, 1, 2]]), &s).unwrap();
        let target = tape.constant(ArrayD::from_elem(IxDyn(&[size, size]), T::from_f64c(0.25)));
        let g = tape.backward((a - target).square().sum()).unwrap();
        let f = |t: &ArrayD<T>| t.iter().map(|x| x.to_f64c()).collect::<Vec<f64>>();
        (f(&a.value().unwrap()), f(g.get(cv).unwrap()))
    }

    /// A triangle whose edge runs 2^-23 NDC beside a column of pixel centres, the only pixels
    /// within the cut-off (delta 1e-6): there `x = d^2 / delta = 1.4e-8`, `f = 1 - e^-x` rounds
    /// to 0 in `f32` and makes `P = 0` (alpha exactly 1 where the `f64` alpha is below 1), and
    /// the backward takes the `f64` leave-one-out product instead of `P / f`: the whole
    /// gradient comes from those pixels, finite and as the `f64` evaluation's.
    #[test]
    fn vanishing_factor_takes_the_leave_one_out_product() {
        let size = 16;
        // 2^-23 beside the centre, exactly in f32 and f64 (the same input on both tapes).
        let x0 = crate::soft::common::pixel_centre(0, 8, size, size)[0] - (-23f64).exp2();
        let clip = [
            [x0, -0.5, 0.5, 1.0],
            [x0, 0.5, 0.5, 1.0],
            [-0.5, 0.0, 0.5, 1.0],
        ];
        let (a32, g32) = render_clip::<f32>(&clip, size, 1e-6);
        let (a64, g64) = render_clip::<f64>(&clip, size, 1e-6);
        assert!(g64.iter().any(|&g| g != 0.0));
        assert!(
            a32.iter().zip(&a64).any(|(&x, &y)| x == 1.0 && y < 1.0),
            "no pixel with a vanishing f32 factor"
        );
        assert!(g32.iter().all(|x| x.is_finite()));
        assert!(max_diff(&a32, &a64) < 1e-4);
        let eg = rel_l2(&g32, &g64);
        assert!(eg < 2e-4, "positions {eg}");
    }

    /// Settings outside `f32`'s range (here `1 / delta`) take the `f64` evaluation and stay
    /// finite.
    #[test]
    fn out_of_range_settings_take_the_f64_path() {
        let (pos, faces) = sphere(1);
        let (a, g) = render::<f32>(&pos, &faces, 32, 1e-40, 1, false);
        assert!(a.iter().chain(&g).all(|x| x.is_finite()));
    }
}
