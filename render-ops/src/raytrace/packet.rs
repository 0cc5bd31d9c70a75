//! The forward's samples traced and shaded eight at a time: a row's samples, in order, go in
//! packets of eight lanes (two pixels at 4 spp). Camera rays, hits, interpolation, Lambert,
//! Phong and Blinn-Phong shading under ambient, directional and point lights, and shadow rays
//! run lane-parallel in `f64` ([`Ray8`], [`ScreenGrid::closest8`], [`Bvh::occluded8`]): the
//! operations of the scalar sample ([`Scene::radiance`]) in the same order in every lane, so
//! the image is bit-identical to it (tested), built with AVX-512 or AVX2 where the CPU has
//! them. Area lights, SH lighting, and the rare packet whose rays do not share an axis
//! permutation or leave the image take the scalar samples. Ray packets as in I. Wald et al.,
//! "Interactive rendering with coherent ray tracing", Eurographics 2001, with the per-lane
//! masks of the packet traversal of Wald, Boulos, Shirley, "Ray tracing deformable scenes
//! using dynamic bounding volume hierarchies", ACM TOG 26(1), 2007.
//!
//! [`ScreenGrid::closest8`]: super::grid::ScreenGrid::closest8
//! [`Bvh::occluded8`]: super::bvh::Bvh::occluded8

use crate::scene::Shading;
use smallvec::SmallVec;

use crate::shade::{cross3, scale3, SAFE_EPS};
use crate::simd::{arr3, avx2_method, lanes, LANES};

use super::edges::face_normal;
use super::intersect::{Ray, Ray8, D8, K8, V3};
use super::op::Scene;
use super::rng::Counter;
use super::shading::{LightKind, LightSet};

/// Three coordinates of eight lanes.
type P3 = [D8; 3];

#[inline(always)]
fn splat(v: V3) -> P3 {
    arr3(|k| [v[k]; LANES])
}

#[inline(always)]
fn dot(a: &P3, b: &P3) -> D8 {
    lanes(|i| a[0][i] * b[0][i] + a[1][i] * b[1][i] + a[2][i] * b[2][i])
}

#[inline(always)]
fn add(a: &P3, b: &P3) -> P3 {
    arr3(|k| lanes(|i| a[k][i] + b[k][i]))
}

#[inline(always)]
fn sub(a: &P3, b: &P3) -> P3 {
    arr3(|k| lanes(|i| a[k][i] - b[k][i]))
}

/// `shade::normalize3` lane by lane: the unit vectors and the lengths.
#[inline(always)]
fn normalize(x: &P3) -> (P3, D8) {
    let len = lanes(|i| (x[0][i] * x[0][i] + x[1][i] * x[1][i] + x[2][i] * x[2][i]).sqrt());
    let d = lanes(|i| len[i].max(SAFE_EPS));
    (arr3(|k| lanes(|i| x[k][i] / d[i])), len)
}

/// A packet's shadow query ([`Shadow`](super::shading::Shadow) per lane).
#[derive(Clone, Copy)]
enum Shadow8 {
    /// Towards a point per lane.
    Toward(P3),
    /// Along one direction.
    Along(V3),
}

/// `sum_j a[tri_j] b_j` per lane, from zero (the scalar hit's interpolation). Where every
/// lane is on one face (the common case), its corners are read once.
#[inline(always)]
fn lerp(a: &[V3], tri: &[[u32; 3]; LANES], b: &P3) -> P3 {
    if tri.iter().all(|t| *t == tri[0]) {
        let v = tri[0].map(|j| a[j as usize]);
        return arr3(|k| {
            lanes(|i| ((0.0 + v[0][k] * b[0][i]) + v[1][k] * b[1][i]) + v[2][k] * b[2][i])
        });
    }
    arr3(|k| {
        lanes(|i| {
            let mut o = 0.0;
            for j in 0..3 {
                o += a[tri[i][j] as usize][k] * b[j][i];
            }
            o
        })
    })
}

/// `a` in the lanes of `m`, else `b`.
#[inline(always)]
fn select(m: K8, a: &P3, b: &P3) -> P3 {
    arr3(|k| lanes(|i| if m[i] { a[k][i] } else { b[k][i] }))
}

/// A packet of a row's samples, in order: pixel points, random numbers (the counter at the
/// area lights' dimensions) and columns.
struct Samples8 {
    u: [D8; 2],
    ctr: [Counter; LANES],
    col: [usize; LANES],
    active: K8,
}

/// The packets of row `r`'s `width x spp` samples, in order: each sample's column, index in
/// the pixel and stratum are stepped through, without dividing.
struct SampleWalk<'s, 'a> {
    sc: &'s Scene<'a>,
    r: usize,
    /// The next sample's index in the row, and its (column, index, stratum x, stratum y).
    s0: usize,
    at: (usize, usize, usize, usize),
}

impl<'s, 'a> SampleWalk<'s, 'a> {
    fn new(sc: &'s Scene<'a>, r: usize) -> Self {
        SampleWalk {
            sc,
            r,
            s0: 0,
            at: (0, 0, 0, 0),
        }
    }
}

impl Iterator for SampleWalk<'_, '_> {
    type Item = Samples8;

    /// The next packet (its lanes past the row's end inactive).
    #[inline(always)]
    fn next(&mut self) -> Option<Samples8> {
        let (sc, n) = (self.sc, self.sc.s.width * self.sc.s.spp);
        if self.s0 >= n {
            return None;
        }
        let active = lanes(|i| self.s0 + i < n);
        self.s0 += LANES;
        let mut at = [(0, 0, 0, 0); LANES];
        for (a, _) in at.iter_mut().zip(active).filter(|&(_, on)| on) {
            *a = self.at;
            let (c, k, kx, ky) = self.at;
            self.at = if k + 1 == sc.s.spp {
                (c + 1, 0, 0, 0)
            } else if kx + 1 == sc.strata.0 {
                (c, k + 1, 0, ky + 1)
            } else {
                (c, k + 1, kx + 1, ky)
            };
        }
        // The points and numbers lane by lane (no dependence between lanes: the hashes
        // vectorise). `lanes`, not `array::map`, whose closures may stay out of line, without
        // the target features.
        let pc = lanes(|i| {
            let (c, k, kx, ky) = at[i];
            sc.sample_at(self.r, c, k, (kx, ky))
        });
        Some(Samples8 {
            u: [lanes(|i| pc[i].0[0]), lanes(|i| pc[i].0[1])],
            ctr: lanes(|i| pc[i].1),
            col: lanes(|i| at[i].0),
            active,
        })
    }
}

impl Scene<'_> {
    /// Whether every light and the shading model have a packet path (else every sample is
    /// scalar).
    fn packets(&self, lights: &LightSet<'_>) -> bool {
        let shading = matches!(
            self.s.reflection.shading,
            Shading::None | Shading::Lambert | Shading::Phong | Shading::BlinnPhong
        );
        let unshaded = self.s.reflection.shading == Shading::None;
        shading
            && (unshaded
                || lights.kinds.iter().all(|k| {
                    matches!(
                        k,
                        LightKind::Ambient
                            | LightKind::Directional
                            | LightKind::Point
                            | LightKind::Area
                    )
                }))
    }

    avx2_method! {
        wide
        /// The sums over each pixel's samples of row `r` (RGB, coverage), added in sample
        /// order.
        pub(super) fn row_sums => row_sums_lanes(
            lights: &LightSet<'_>,
            r: usize,
            sums: &mut [[f64; 4]],
        ) for Scene<'_>
    }

    /// [`Scene::radiance`] of the samples at `u` in the `active` lanes: as one packet where
    /// `packets` ([`Scene::packets`]) and the rays allow, else one at a time.
    #[inline(always)]
    fn radiance_lanes(
        &self,
        lights: &LightSet<'_>,
        u: &[D8; 2],
        ctr: [Counter; LANES],
        active: K8,
        packets: bool,
    ) -> [D8; 4] {
        let packet = if packets {
            self.radiance8(lights, u, ctr, active)
        } else {
            None
        };
        packet.unwrap_or_else(|| {
            let mut v = [[0.0; LANES]; 4];
            for i in (0..LANES).filter(|&i| active[i]) {
                let c = self.radiance(lights, [u[0][i], u[1][i]], ctr[i], None, None);
                for ch in 0..4 {
                    v[ch][i] = c[ch];
                }
            }
            v
        })
    }

    #[inline(always)]
    fn row_sums_lanes(&self, lights: &LightSet<'_>, r: usize, sums: &mut [[f64; 4]]) {
        let packets = self.packets(lights);
        sums.fill([0.0; 4]);
        for p in SampleWalk::new(self, r) {
            let v = self.radiance_lanes(lights, &p.u, p.ctr, p.active, packets);
            for i in (0..LANES).filter(|&i| p.active[i]) {
                let sum = &mut sums[p.col[i]];
                for ch in 0..4 {
                    sum[ch] += v[ch][i];
                }
            }
        }
    }

    /// [`Scene::radiance`] of the samples at pixel points `u` in the `active` lanes (RGB,
    /// coverage), or `None` when the camera rays cannot go as one packet.
    #[inline(always)]
    fn radiance8(
        &self,
        lights: &LightSet<'_>,
        u: &[D8; 2],
        mut ctr: [Counter; LANES],
        active: K8,
    ) -> Option<[D8; 4]> {
        let (w, h) = (self.s.width as f64, self.s.height as f64);
        let dir = [
            lanes(|i| 2.0 * u[0][i] / w - 1.0),
            lanes(|i| 1.0 - 2.0 * u[1][i] / h),
            [1.0; LANES],
        ];
        let ray = Ray8::new([[0.0; LANES]; 3], dir, active)?;
        let (face, _, b) = self
            .primary
            .closest8(&ray, u, self.s.near, self.s.far, active)?;
        let hit = lanes(|i| active[i] && face[i] != u32::MAX);
        let bg = self.s.background;
        let mut out = [[bg[0]; LANES], [bg[1]; LANES], [bg[2]; LANES], [0.0; LANES]];
        let Some(first) = hit.iter().position(|&h| h) else {
            return Some(out);
        };
        let tri = lanes(|i| self.faces[face[if hit[i] { i } else { first }] as usize]);
        let albedo = lerp(&self.albedo, &tri, &b);
        let col = if self.s.reflection.shading == Shading::None {
            albedo
        } else {
            // Each area light's sample `(a, b)`, drawn in light order (`Scene::area_samples`).
            let mut ab = SmallVec::<[[D8; 2]; 2]>::new();
            for _ in 0..lights.n_area {
                let mut d = [[0.0; LANES]; 2];
                for (i, c) in ctr.iter_mut().enumerate() {
                    d[0][i] = c.uniform();
                    d[1][i] = c.uniform();
                }
                ab.push(d);
            }
            let (x, nraw) = (lerp(&self.world, &tri, &b), lerp(&self.normals, &tri, &b));
            self.shade8(lights, &tri, &x, &nraw, &albedo, &ab, hit)
        };
        for k in 0..3 {
            out[k] = lanes(|i| if hit[i] { col[k][i] } else { out[k][i] });
        }
        out[3] = lanes(|i| if hit[i] { 1.0 } else { 0.0 });
        Some(out)
    }

    /// `LightSet::shade` without gradients, for Lambert, Phong and Blinn-Phong under ambient,
    /// directional, point and area lights (area light `j` sampled at `area_ab[j]`), in the
    /// lanes of `hit` (faces `tri`).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn shade8(
        &self,
        lights: &LightSet<'_>,
        tri: &[[u32; 3]; LANES],
        x: &P3,
        nraw: &P3,
        albedo: &P3,
        area_ab: &[[D8; 2]],
        hit: K8,
    ) -> P3 {
        let m = &self.s.reflection;
        let ng: P3 = if tri.iter().all(|t| *t == tri[0]) {
            splat(face_normal(&self.world, &tri[0]))
        } else {
            let p = &self.world;
            let at = |i: usize, j: usize| p[tri[i][j] as usize];
            let e1: P3 = arr3(|k| lanes(|i| at(i, 1)[k] - at(i, 0)[k]));
            let e2: P3 = arr3(|k| lanes(|i| at(i, 2)[k] - at(i, 0)[k]));
            // `face_normal`: e1 x e2.
            [
                lanes(|i| e1[1][i] * e2[2][i] - e1[2][i] * e2[1][i]),
                lanes(|i| e1[2][i] * e2[0][i] - e1[0][i] * e2[2][i]),
                lanes(|i| e1[0][i] * e2[1][i] - e1[1][i] * e2[0][i]),
            ]
        };
        let n = normalize(nraw).0;
        let specular = matches!(m.shading, Shading::Phong | Shading::BlinnPhong);
        let v = if specular {
            normalize(&sub(&splat(self.s.eye), x)).0
        } else {
            splat([0.0; 3])
        };
        let ka = m.ka.map(splat).unwrap_or(*albedo);
        let rows = lights.rows;
        let mut col = splat([0.0; 3]);
        let mut area = area_ab.iter();
        for (li, kind) in lights.kinds.iter().enumerate() {
            let o = lights.offsets[li];
            // Direction to the light, shadow query, colour, and the lanes the light may reach.
            let (l, q, c, ndl, facing) = match kind {
                LightKind::Ambient => {
                    col = arr3(|k| lanes(|i| col[k][i] + ka[k][i] * rows[o][k]));
                    continue;
                }
                LightKind::Directional | LightKind::Point => {
                    let (l, q) = if *kind == LightKind::Directional {
                        (
                            splat(lights.toward[li].0),
                            Shadow8::Along(scale3(rows[o], -1.0)),
                        )
                    } else {
                        let p = splat(rows[o]);
                        (normalize(&sub(&p, x)).0, Shadow8::Toward(p))
                    };
                    let ndl = dot(&n, &l);
                    let facing = lanes(|i| hit[i] & !(ndl[i] <= 0.0));
                    (l, q, splat(rows[o + 1]), ndl, facing)
                }
                LightKind::Area => {
                    // One uniform area sample: a point light of colour `L max(-N_l . (p - x),
                    // 0) / |p - x|^3` at `p` (module docs of `shading`).
                    let Some(ab) = area.next() else { continue };
                    let lp: P3 = arr3(|k| {
                        lanes(|i| {
                            rows[o][k] + (rows[o + 1][k] * ab[0][i] + rows[o + 2][k] * ab[1][i])
                        })
                    });
                    let lraw = sub(&lp, x);
                    let (l, rl) = normalize(&lraw);
                    let nl = splat(cross3(rows[o + 1], rows[o + 2]));
                    let kk = lanes(|i| -dot(&nl, &lraw)[i]);
                    let ndl = dot(&n, &l);
                    let facing = lanes(|i| {
                        hit[i] & !((kk[i] <= 0.0) | (rl[i] <= SAFE_EPS) | (ndl[i] <= 0.0))
                    });
                    let f = lanes(|i| kk[i] / (rl[i] * rl[i] * rl[i]));
                    let c = arr3(|k| lanes(|i| rows[o + 3][k] * f[i]));
                    (l, Shadow8::Toward(lp), c, ndl, facing)
                }
                LightKind::Sh => continue,
            };
            if !facing.contains(&true) {
                continue;
            }
            let vis = self.visible8(x, &ng, q, facing);
            let on = lanes(|i| facing[i] & vis[i]);
            if !on.contains(&true) {
                continue;
            }
            // `term`: C (albedo n.l + ks spec).
            let base = match m.shading {
                Shading::Phong => {
                    let rh = arr3(|k| lanes(|i| n[k][i] * (ndl[i] + ndl[i]) - l[k][i]));
                    dot(&rh, &v)
                }
                Shading::BlinnPhong => dot(&n, &normalize(&add(&l, &v)).0),
                _ => [0.0; LANES],
            };
            let spec = lanes(|i| {
                if on[i] && base[i] > 0.0 {
                    base[i].powf(m.shininess)
                } else {
                    0.0
                }
            });
            let lit = arr3(|k| {
                lanes(|i| col[k][i] + c[k][i] * (albedo[k][i] * ndl[i] + m.ks[k] * spec[i]))
            });
            col = select(on, &lit, &col);
        }
        col
    }

    /// [`Scene::visible`] in the lanes of `want`: the same offset origins and shadow rays,
    /// traced as a packet where they share an axis permutation.
    #[inline(always)]
    fn visible8(&self, x: &P3, ng: &P3, q: Shadow8, want: K8) -> K8 {
        let Some(bvh) = &self.shadow else {
            return [true; LANES];
        };
        let (dir, t_max) = match q {
            Shadow8::Toward(p) => (sub(&p, x), 1.0 - 1e-9),
            Shadow8::Along(d) => (splat(d), f64::INFINITY),
        };
        let len = lanes(|i| dot(ng, ng)[i].sqrt());
        let side = dot(ng, &dir);
        let s = lanes(|i| {
            let side = if side[i] >= 0.0 { 1.0 } else { -1.0 };
            side * 1e-9 * self.scale / len[i]
        });
        let off = arr3(|k| lanes(|i| if len[i] > 0.0 { ng[k][i] * s[i] } else { 0.0 }));
        let o = add(x, &off);
        let dir = match q {
            Shadow8::Toward(p) => sub(&p, &o),
            Shadow8::Along(d) => splat(d),
        };
        let len2 = dot(&dir, &dir);
        let cast = lanes(|i| want[i] & (len2[i] != 0.0));
        if !cast.contains(&true) {
            return [true; LANES];
        }
        let blocked = match Ray8::new(o, dir, cast) {
            Some(r) => bvh.occluded8(&r, 0.0, t_max, cast),
            None => lanes(|i| {
                cast[i] && {
                    let r = Ray::new(arr3(|k| o[k][i]), arr3(|k| dir[k][i]));
                    bvh.occluded(&r, 0.0, t_max)
                }
            }),
        };
        lanes(|i| !blocked[i])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::mesh::Mesh;
    use crate::raytrace::{RaytraceSettings, Reflection};
    use crate::simd::set_force_portable;

    /// A ground plane and an icosphere (`subdiv`) above it, with flat normals up on the plane
    /// and the positions as normals on the sphere.
    fn scene(subdiv: u32) -> (Vec<V3>, Vec<[u32; 3]>, Vec<V3>, Vec<V3>) {
        let mut pos = vec![
            [-3.0, 0.0, -3.0],
            [3.0, 0.0, -3.0],
            [3.0, 0.0, 3.0],
            [-3.0, 0.0, 3.0],
        ];
        let mut faces = vec![[0, 2, 1], [0, 3, 2]];
        let mut normals = vec![[0.0, 1.0, 0.0]; 4];
        let ico = Mesh::<f64>::icosphere(subdiv, 0.8);
        for p in &ico.positions {
            pos.push([p[0], p[1] + 1.1, p[2]]);
            normals.push(*p);
        }
        faces.extend(ico.faces.iter().map(|f| f.map(|i| i + 4)));
        let albedo = (0..pos.len())
            .map(|i| [0.9, 0.3 + 0.1 * (i % 5) as f64, 0.5])
            .collect();
        (pos, faces, normals, albedo)
    }

    /// The scalar forward of row `r`: every sample through [`Scene::radiance`], summed per
    /// pixel in sample order.
    fn scalar_row(sc: &Scene<'_>, lights: &LightSet<'_>, r: usize) -> Vec<[f64; 4]> {
        let (w, spp) = (sc.s.width, sc.s.spp);
        (0..w)
            .map(|c| {
                let mut sum = [0.0; 4];
                for k in 0..spp {
                    let (u, ctr) = sc.sample(r * w + c, k);
                    let v = sc.radiance(lights, u, ctr, None, None);
                    for ch in 0..4 {
                        sum[ch] += v[ch];
                    }
                }
                sum
            })
            .collect()
    }

    /// Packet rows against scalar rows, bit for bit, in the AVX and the portable builds;
    /// returns the share of packets that went as packets (0 when the scene has no packet path).
    fn packet_share(s: &RaytraceSettings, subdiv: u32, rows: Vec<V3>) -> f64 {
        let (pos, faces, normals, albedo) = scene(subdiv);
        let view = ([0.3, 2.8, 4.0], [0.0, 0.7, 0.0]);
        compare(s, &pos, &faces, normals, albedo, rows, view)
    }

    /// [`packet_share`] of any scene, seen from `view = (eye, at)`.
    fn compare(
        s: &RaytraceSettings,
        pos: &[V3],
        faces: &[[u32; 3]],
        normals: Vec<V3>,
        albedo: Vec<V3>,
        rows: Vec<V3>,
        view: (V3, V3),
    ) -> f64 {
        let cam = Camera::perspective_look_at(
            view.0,
            view.1,
            [0.0, 1.0, 0.0],
            50f64.to_radians(),
            s.width as f64 / s.height as f64,
            s.near,
            s.far,
        )
        .unwrap();
        let clip = pos.iter().map(|p| cam.project(*p)).collect();
        let sc = Scene::build(s, faces, clip, pos.to_vec(), normals, albedo, rows);
        let lights = sc.lights();
        let w = s.width;
        for portable in [false, true] {
            set_force_portable(portable);
            for r in 0..s.height {
                let mut sums = vec![[f64::NAN; 4]; w];
                sc.row_sums(&lights, r, &mut sums);
                let want = scalar_row(&sc, &lights, r);
                for c in 0..w {
                    for ch in 0..4 {
                        assert_eq!(
                            sums[c][ch].to_bits(),
                            want[c][ch].to_bits(),
                            "{:?} row {r} col {c} ch {ch} portable {portable}: {} vs {}",
                            s.reflection.shading,
                            sums[c][ch],
                            want[c][ch]
                        );
                    }
                }
            }
            set_force_portable(false);
        }
        if !sc.packets(&lights) {
            return 0.0;
        }
        let (mut packets, mut total) = (0, 0);
        for r in 0..s.height {
            for p in SampleWalk::new(&sc, r) {
                total += 1;
                packets += sc.radiance8(&lights, &p.u, p.ctr, p.active).is_some() as usize;
            }
        }
        packets as f64 / total as f64
    }

    fn settings(shading: Shading, spp: usize, lights: Vec<LightKind>) -> RaytraceSettings {
        let mut s = RaytraceSettings::new(23, 17);
        s.spp = spp;
        s.seed = 3;
        s.background = [0.1, 0.2, 0.3];
        s.eye = [0.3, 2.8, 4.0];
        s.reflection = Reflection {
            shading,
            ks: [0.3, 0.2, 0.1],
            shininess: 12.0,
            ka: None,
        };
        s.lights = lights;
        s
    }

    #[test]
    fn packets_give_the_scalar_samples_bits_under_every_light_and_shading() {
        use LightKind::*;
        let kinds = vec![Ambient, Directional, Point];
        let rows = vec![
            [0.1, 0.1, 0.15],
            [0.3, -1.0, -0.2],
            [0.9, 0.8, 0.7],
            // A point light near the sphere: its shadow rays change dominant axis across a
            // packet, so some go as scalar rays.
            [0.2, 2.4, 0.5],
            [1.5, 1.4, 1.3],
        ];
        for shading in [
            Shading::None,
            Shading::Lambert,
            Shading::Phong,
            Shading::BlinnPhong,
        ] {
            for spp in [1, 3, 4] {
                let share = packet_share(&settings(shading, spp, kinds.clone()), 2, rows.clone());
                assert!(share > 0.95, "{shading:?} spp {spp}: {share}");
            }
        }
        // Many faces a tile (icosphere 4 in a small image); the ambient light's `ka`.
        let mut s = settings(Shading::Lambert, 4, kinds);
        s.reflection.ka = Some([0.2, 0.4, 0.6]);
        assert!(packet_share(&s, 4, rows) > 0.95);
    }

    #[test]
    fn random_soups_and_lights_give_the_scalar_bits() {
        use crate::raytrace::bvh::tests::soup_around;
        use crate::raytrace::rng::Stream;
        let mut c = Counter::new(11, Stream::Pixel, 0);
        let mut u = move || c.uniform();
        for case in 0..24usize {
            let (pos, faces) = soup_around(10 + 20 * case, case as u64, |c, _| {
                let p = [
                    4.0 * c.uniform() - 2.0,
                    2.0 * c.uniform(),
                    4.0 * c.uniform() - 2.0,
                ];
                (p, 0.05 + 2.0 * c.uniform())
            });
            // Normals of any length (some zero), albedo in [0, 1].
            let normals = (0..pos.len())
                .map(|i| {
                    if i % 7 == 0 {
                        [0.0; 3]
                    } else {
                        [u() - 0.5, u(), u() - 0.5]
                    }
                })
                .collect();
            let albedo = (0..pos.len()).map(|_| [u(), u(), u()]).collect();
            let shading = [
                Shading::None,
                Shading::Lambert,
                Shading::Phong,
                Shading::BlinnPhong,
            ][case % 4];
            let mut kinds = vec![LightKind::Ambient];
            let mut rows = vec![[0.1, 0.1, 0.1]];
            if case % 3 != 0 {
                kinds.push(LightKind::Directional);
                rows.extend([[u() - 0.5, -1.0, u() - 0.5], [1.0, 0.9, 0.8]]);
            }
            if case % 2 == 0 {
                // Among the triangles: shadow rays in every direction.
                kinds.push(LightKind::Point);
                rows.extend([[u() - 0.5, 0.5 + u(), u() - 0.5], [0.8, 0.8, 0.8]]);
            }
            if case % 5 < 2 {
                kinds.push(LightKind::Area);
                rows.extend([
                    [-0.5, 2.5, -0.5],
                    [1.0, 0.0, 0.0],
                    [0.0, 0.0, 1.0],
                    [3.0; 3],
                ]);
            }
            let mut s = settings(shading, 1 + case % 5, kinds);
            (s.width, s.height) = (5 + case % 11, 4 + (3 * case) % 13);
            s.seed = case as u64;
            let eye = [6.0 * u() - 3.0, 1.0 + 3.0 * u(), 2.5 + 2.0 * u()];
            compare(
                &s,
                &pos,
                &faces,
                normals,
                albedo,
                rows,
                (eye, [0.0, 0.8, 0.0]),
            );
        }
    }

    #[test]
    fn area_lights_go_as_packets_and_sh_lighting_takes_the_scalar_samples() {
        let s = settings(Shading::Phong, 2, vec![LightKind::Area, LightKind::Area]);
        let mut rows = vec![
            [-0.5, 3.0, -0.5],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
            [2.0, 2.0, 2.0],
        ];
        // A second emitter beside the sphere, facing it sideways.
        rows.extend([
            [1.5, 0.5, -0.5],
            [0.0, 0.0, 1.0],
            [0.0, 1.0, 0.0],
            [1.0, 0.5, 0.2],
        ]);
        assert!(packet_share(&s, 1, rows) > 0.95);
        let s = settings(Shading::Sh, 2, vec![LightKind::Sh]);
        let rows = (0..9).map(|j| [0.5 / (j + 1) as f64, 0.2, 0.1]).collect();
        assert_eq!(packet_share(&s, 1, rows), 0.0);
    }
}
