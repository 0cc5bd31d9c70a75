//! Differentiable texture sampling: nearest, bilinear and trilinear mip-mapped filtering with
//! repeat / clamp / mirror wrapping, gradients with respect to the texels `[H, W, C]`, the
//! texture coordinates `[N, 2]` and (trilinear) the screen-space uv derivatives `[N, 4]`.
//!
//! # Conventions
//! - Texels are `[H, W, C]`, row 0 at the top of the image (as PNG files and
//!   docs/CONVENTIONS.md images). Texture coordinates follow OpenGL and OBJ: `uv = (0, 0)` is the
//!   bottom-left corner of the image, `(1, 1)` the top-right; texel `(row r, col c)` has its
//!   centre at `u = (c + 0.5) / W`, `v = 1 - (r + 0.5) / H`.
//! - Wrap modes act on texel indices: `Repeat` (`i mod n`), `Clamp` (to `[0, n - 1]`, i.e.
//!   clamp to edge) and `Mirror` (mirrored repeat, period `2n`); uv far outside `[0, 1]` is
//!   fine (repeat of `u + k` equals `u` for integer `k`).
//! - Bilinear: the four texels around `(u W - 1/2, (1 - v) H - 1/2)` weighted by the
//!   fractional parts.
//! - Trilinear (L. Williams, "Pyramidal parametrics", SIGGRAPH 1983): a mip pyramid whose
//!   level `k + 1` has size `max(1, floor(H_k / 2)) x max(1, floor(W_k / 2))`, each texel the
//!   area-weighted box average of the level-`k` texels under its footprint (exactly the 2 x 2
//!   mean for even sizes; odd and non-power-of-two sizes get fractional weights, and a 1 x 1
//!   texture has one level). The level of detail follows the OpenGL specification:
//!   `lambda = log2(rho)`, `rho = max(|d(uW, vH)/dx|, |d(uW, vH)/dy|)` from the uv derivatives
//!   per pixel step `uv_da = (du/dx, dv/dx, du/dy, dv/dy)`; `lambda` is clamped to
//!   `[0, L - 1]` and the two nearest levels are blended linearly. Gradients flow into
//!   `uv_da` through `lambda` (zero where the clamp is active or `rho = 0`).
//!   [`crate::shade::uv_derivatives`] computes `uv_da` from the rasterizer's barycentric
//!   derivatives and a mesh's uvs.
//!
//! Nearest sampling is piecewise constant in uv: its uv gradient is zero.
//!
//! # Determinism
//! Texel gradients are accumulated by one sequential scatter in fragment order (then tap
//! order), and the pyramid's adjoint runs level by level in parallel over texel rows, each
//! texel gathering its coarse parents in a fixed order: no atomics, bit-identical results for
//! any number of threads. Per-fragment work (forward, uv gradients) is parallel over fixed
//! chunks of fragments.

use std::path::Path;

use autodiff::{
    tensor, AutodiffError, BackwardCtx, Op, Real, Result as AdResult, Tape, Tensor, TensorView, Var,
};
use ndarray::{ArrayD, CowArray, IxDyn};
use rayon::prelude::*;

use crate::io::{read_png, IoError};

/// Fragments per parallel task.
const CHUNK: usize = 1024;

/// Texture filtering.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum Filter {
    /// The texel containing the sample point.
    Nearest,
    /// Bilinear interpolation of the four nearest texels (level 0).
    #[default]
    Bilinear,
    /// Bilinear in the two nearest mip levels, blended linearly (Williams 1983).
    Trilinear,
}

/// Handling of texture coordinates outside `[0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum Wrap {
    /// Tile the texture.
    #[default]
    Repeat,
    /// Clamp to the edge texels.
    Clamp,
    /// Tile with every other copy mirrored.
    Mirror,
}

impl Wrap {
    /// The texel index that `i` reads in a dimension of size `n >= 1`.
    #[inline(always)]
    pub fn apply(self, i: i64, n: usize) -> usize {
        let n = n as i64;
        (match self {
            Wrap::Repeat => i.rem_euclid(n),
            Wrap::Clamp => i.clamp(0, n - 1),
            Wrap::Mirror => {
                let m = i.rem_euclid(2 * n);
                if m >= n {
                    2 * n - 1 - m
                } else {
                    m
                }
            }
        }) as usize
    }
}

/// Filter and wrap mode of a texture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub struct Sampler {
    /// Filtering.
    pub filter: Filter,
    /// Wrapping (both axes).
    pub wrap: Wrap,
}

impl Sampler {
    /// A sampler.
    pub fn new(filter: Filter, wrap: Wrap) -> Self {
        Sampler { filter, wrap }
    }
}

/// A texture on the tape: texels `[H, W, C]` and how to sample them.
#[derive(Clone, Copy, Debug)]
pub struct Texture<'t, T: Real> {
    /// Texels `[H, W, C]`, row 0 at the top.
    pub texels: Var<'t, T>,
    /// Filter and wrap mode.
    pub sampler: Sampler,
}

impl<'t, T: Real> Texture<'t, T> {
    /// A texture from texels `[H, W, C]`.
    pub fn new(texels: Var<'t, T>, sampler: Sampler) -> Self {
        Texture { texels, sampler }
    }

    /// A texture from a PNG file (values in [0, 1]); `requires_grad` makes it a parameter.
    pub fn from_png(
        tape: &'t Tape<T>,
        path: impl AsRef<Path>,
        sampler: Sampler,
        requires_grad: bool,
    ) -> Result<Self, IoError> {
        let texels = load_png(path)?;
        Ok(Texture::new(tape.var(texels, requires_grad), sampler))
    }

    /// Samples at `uv` `[N, 2]` (fused op); `uv_da` `[N, 4]` (see the module docs) selects
    /// the mip level of trilinear filtering, which without it uses level 0.
    pub fn sample(&self, uv: Var<'t, T>, uv_da: Option<Var<'t, T>>) -> Var<'t, T> {
        sample(self.texels, uv, uv_da, self.sampler)
    }

    /// [`Texture::sample`] composed from tape ops (reference).
    pub fn sample_composed(&self, uv: Var<'t, T>, uv_da: Option<Var<'t, T>>) -> Var<'t, T> {
        sample_composed(self.texels, uv, uv_da, self.sampler)
    }
}

/// Reads a PNG (8 or 16 bit, gray / RGB / RGBA) as texels `[H, W, C]` in [0, 1], no gamma
/// (through [`crate::io::read_png`]).
pub fn load_png<T: Real>(path: impl AsRef<Path>) -> Result<Tensor<T>, IoError> {
    Ok(read_png::<T>(path)?.into_dyn())
}

/// Sizes `(H_k, W_k)` of the mip levels of an `H x W` texture, level 0 first, down to 1 x 1.
pub fn mip_sizes(h: usize, w: usize) -> Vec<(usize, usize)> {
    let mut out = vec![(h, w)];
    let (mut h, mut w) = (h, w);
    while h > 1 || w > 1 {
        h = (h / 2).max(1);
        w = (w / 2).max(1);
        out.push((h, w));
    }
    out
}

/// 1D area weights of the box downsampling from `n` to `m` texels: for every output texel the
/// `(input texel, weight)` pairs under its footprint `[i n / m, (i + 1) n / m)` (weights sum
/// to one; exact rational arithmetic).
pub fn downsample_weights(n: usize, m: usize) -> Vec<Vec<(usize, f64)>> {
    (0..m)
        .map(|i| {
            // In units of 1/m of an input texel: footprint [i n, (i + 1) n), texel j [j m, (j + 1) m).
            let (lo, hi) = (i * n, (i + 1) * n);
            (lo / m..hi.div_ceil(m).min(n))
                .filter_map(|j| {
                    let ov = hi.min((j + 1) * m).saturating_sub(lo.max(j * m));
                    (ov > 0).then(|| (j, ov as f64 / n as f64))
                })
                .collect()
        })
        .collect()
}

/// The transpose of [`downsample_weights`]: for every input texel, `(output texel, weight)`.
fn upsample_weights(n: usize, m: usize) -> Vec<Vec<(usize, f64)>> {
    let mut t = vec![Vec::new(); n];
    for (i, taps) in downsample_weights(n, m).into_iter().enumerate() {
        for (j, w) in taps {
            t[j].push((i, w));
        }
    }
    t
}

/// One box-filter step `[h, w, c] -> [h', w', c]` on flat data.
fn downsample<T: Real>(
    src: &[T],
    (h, w): (usize, usize),
    (h2, w2): (usize, usize),
    c: usize,
) -> Vec<T> {
    let wy = downsample_weights(h, h2);
    let wx = downsample_weights(w, w2);
    let mut out = vec![T::zero(); h2 * w2 * c];
    out.par_chunks_mut(w2 * c).enumerate().for_each(|(i, row)| {
        for (j, px) in row.chunks_mut(c).enumerate() {
            for &(a, wa) in &wy[i] {
                for &(b, wb) in &wx[j] {
                    let wt = T::from_f64c(wa * wb);
                    let s = &src[(a * w + b) * c..(a * w + b + 1) * c];
                    for ch in 0..c {
                        px[ch] += wt * s[ch];
                    }
                }
            }
        }
    });
    out
}

/// The adjoint of [`downsample`]: adds `D^T g` to `dst`.
fn downsample_adjoint<T: Real>(
    g: &[T],
    (h, w): (usize, usize),
    (h2, w2): (usize, usize),
    c: usize,
    dst: &mut [T],
) {
    let ty = upsample_weights(h, h2);
    let tx = upsample_weights(w, w2);
    dst.par_chunks_mut(w * c).enumerate().for_each(|(a, row)| {
        for (b, px) in row.chunks_mut(c).enumerate() {
            for &(i, wa) in &ty[a] {
                for &(j, wb) in &tx[b] {
                    let wt = T::from_f64c(wa * wb);
                    let s = &g[(i * w2 + j) * c..(i * w2 + j + 1) * c];
                    for ch in 0..c {
                        px[ch] += wt * s[ch];
                    }
                }
            }
        }
    });
}

/// The mip pyramid of texels `[H, W, C]` (level 0 first), plain values.
pub fn mip_pyramid<T: Real>(texels: &Tensor<T>) -> Vec<Tensor<T>> {
    let s = texels.shape().to_vec();
    assert_eq!(s.len(), 3, "texels must be [H, W, C]");
    let sizes = mip_sizes(s[0], s[1]);
    let mut levels = vec![texels.as_standard_layout().into_owned()];
    for k in 1..sizes.len() {
        let d = downsample(
            levels[k - 1].as_slice().expect("std"),
            sizes[k - 1],
            sizes[k],
            s[2],
        );
        levels.push(
            ArrayD::from_shape_vec(IxDyn(&[sizes[k].0, sizes[k].1, s[2]]), d).expect("level size"),
        );
    }
    levels
}

/// Bilinear footprint of one sample in one level.
#[derive(Clone, Copy)]
struct Bilinear<T> {
    /// Texel indices (row * w + col) of t00, t01, t10, t11 (rows top, bottom; cols left, right).
    idx: [usize; 4],
    fx: T,
    fy: T,
}

impl<T: Real> Bilinear<T> {
    #[inline(always)]
    fn new(u: T, v: T, (h, w): (usize, usize), wrap: Wrap) -> Self {
        let half = T::from_f64c(0.5);
        let x = u * T::from_usize_c(w) - half;
        let y = (T::one() - v) * T::from_usize_c(h) - half;
        let (x0, y0) = (x.floor(), y.floor());
        let (xi, yi) = (x0.to_i64().unwrap_or(0), y0.to_i64().unwrap_or(0));
        let (c0, c1) = (wrap.apply(xi, w), wrap.apply(xi.saturating_add(1), w));
        let (r0, r1) = (wrap.apply(yi, h), wrap.apply(yi.saturating_add(1), h));
        Bilinear {
            idx: [r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1],
            fx: x - x0,
            fy: y - y0,
        }
    }

    #[inline(always)]
    fn weights(&self) -> [T; 4] {
        let one = T::one();
        let (fx, fy) = (self.fx, self.fy);
        [
            (one - fx) * (one - fy),
            fx * (one - fy),
            (one - fx) * fy,
            fx * fy,
        ]
    }
}

#[inline(always)]
fn nearest_index<T: Real>(u: T, v: T, (h, w): (usize, usize), wrap: Wrap) -> usize {
    let x = (u * T::from_usize_c(w)).floor().to_i64().unwrap_or(0);
    let y = ((T::one() - v) * T::from_usize_c(h))
        .floor()
        .to_i64()
        .unwrap_or(0);
    wrap.apply(y, h) * w + wrap.apply(x, w)
}

/// Level of detail of one sample: `(l0, f, lambda_active, drho2)`: blend `(1 - f)` of level
/// `l0` and `f` of `l0 + 1`; when `lambda_active` the derivative of `lambda` with respect to
/// `uv_da` is `drho2`.
struct Lod<T> {
    l0: usize,
    f: T,
    dlam: Option<[T; 4]>,
}

fn lod<T: Real>(da: [T; 4], (h, w): (usize, usize), levels: usize) -> Lod<T> {
    let (wf, hf) = (T::from_usize_c(w), T::from_usize_c(h));
    let (ax, ay, bx, by) = (da[0] * wf, da[1] * hf, da[2] * wf, da[3] * hf);
    let rx = ax * ax + ay * ay;
    let ry = bx * bx + by * by;
    let half = T::from_f64c(0.5);
    let m = if rx == ry {
        half * (rx + ry)
    } else {
        rx.max(ry)
    };
    let top = T::from_usize_c(levels - 1);
    let z = T::zero();
    if !(m > z) || levels == 1 {
        return Lod {
            l0: 0,
            f: z,
            dlam: None,
        };
    }
    let c = T::from_f64c(0.5 / std::f64::consts::LN_2);
    let lam = m.ln() * c;
    let lc = lam.max(z).min(top);
    let l0 = (lc.floor().to_usize().unwrap_or(0)).min(levels - 1);
    let f = if l0 == levels - 1 {
        z
    } else {
        lc - T::from_usize_c(l0)
    };
    let dlam = (lam >= z && lam <= top).then(|| {
        // d lambda / d m = c / m; d m / d rx = 1 (rx > ry), 1/2 on ties.
        let (sx, sy) = if rx == ry {
            (half, half)
        } else if rx > ry {
            (T::one(), z)
        } else {
            (z, T::one())
        };
        let k = c / m;
        let two = T::one() + T::one();
        [
            k * sx * two * ax * wf,
            k * sx * two * ay * hf,
            k * sy * two * bx * wf,
            k * sy * two * by * hf,
        ]
    });
    Lod { l0, f, dlam }
}

/// Value and uv derivatives of one level's bilinear sample, per channel.
struct LevelGrad<T> {
    val: Vec<T>,
    du: Vec<T>,
    dv: Vec<T>,
}

impl<T: Real> LevelGrad<T> {
    fn new(c: usize) -> Self {
        LevelGrad {
            val: vec![T::zero(); c],
            du: vec![T::zero(); c],
            dv: vec![T::zero(); c],
        }
    }
}

struct TextureOp<T: Real> {
    sampler: Sampler,
    /// Mip levels 1.. of the forward (level 0 is the input), trilinear only.
    pyramid: Vec<Vec<T>>,
    sizes: Vec<(usize, usize)>,
}

/// Inputs of one evaluation, standard layout.
struct View<'a, T> {
    n: usize,
    uv: &'a [T],
    da: Option<&'a [T]>,
}

impl<T: Real> TextureOp<T> {
    fn check(&self, inputs: &[CowArray<'_, T, IxDyn>]) -> AdResult<()> {
        let tex = &inputs[0];
        let ts = tex.shape();
        if ts.len() != 3 || ts.iter().any(|&d| d == 0) {
            return Err(AutodiffError::shape(
                "texture",
                &[ts],
                "texels must be [H, W, C] with H, W, C >= 1",
            ));
        }
        let us = inputs[1].shape();
        if us.len() != 2 || us[1] != 2 {
            return Err(AutodiffError::shape(
                "texture",
                &[ts, us],
                "uv must be [N, 2]",
            ));
        }
        if let Some(da) = inputs.get(2) {
            if da.shape() != [us[0], 4] {
                return Err(AutodiffError::shape(
                    "texture",
                    &[ts, us, da.shape()],
                    "uv derivatives must be [N, 4] (du/dx, dv/dx, du/dy, dv/dy)",
                ));
            }
        }
        Ok(())
    }

    fn level<'a>(&'a self, tex0: &'a [T], k: usize) -> &'a [T] {
        if k == 0 {
            tex0
        } else {
            &self.pyramid[k - 1]
        }
    }

    /// Calls `tap(level, texel index, weight)` for every texel sample `i` reads, in a fixed
    /// order, and returns the level blend.
    #[inline(always)]
    fn for_taps(&self, v: &View<'_, T>, i: usize, mut tap: impl FnMut(usize, usize, T)) {
        let (u, vv) = (v.uv[2 * i], v.uv[2 * i + 1]);
        let wrap = self.sampler.wrap;
        match self.sampler.filter {
            Filter::Nearest => tap(0, nearest_index(u, vv, self.sizes[0], wrap), T::one()),
            Filter::Bilinear => {
                let b = Bilinear::new(u, vv, self.sizes[0], wrap);
                for (k, w) in b.weights().into_iter().enumerate() {
                    tap(0, b.idx[k], w);
                }
            }
            Filter::Trilinear => {
                let l = self.lod_of(v, i);
                for (lev, lw) in [(l.l0, T::one() - l.f), (l.l0 + 1, l.f)] {
                    if lev >= self.sizes.len() || (lev > l.l0 && l.f == T::zero()) {
                        continue;
                    }
                    let b = Bilinear::new(u, vv, self.sizes[lev], wrap);
                    for (k, w) in b.weights().into_iter().enumerate() {
                        tap(lev, b.idx[k], lw * w);
                    }
                }
            }
        }
    }

    fn lod_of(&self, v: &View<'_, T>, i: usize) -> Lod<T> {
        match v.da {
            Some(da) => lod(
                [da[4 * i], da[4 * i + 1], da[4 * i + 2], da[4 * i + 3]],
                self.sizes[0],
                self.sizes.len(),
            ),
            None => Lod {
                l0: 0,
                f: T::zero(),
                dlam: None,
            },
        }
    }

    /// Bilinear value and its uv derivative (`d/du`, `d/dv` per channel) at one level.
    fn bilinear_grad(&self, tex: &[T], lev: usize, u: T, v: T, out: &mut LevelGrad<T>) {
        let c = out.val.len();
        let LevelGrad { val, du, dv } = out;
        let size = self.sizes[lev];
        let b = Bilinear::new(u, v, size, self.sampler.wrap);
        let w = b.weights();
        let one = T::one();
        let (wf, hf) = (T::from_usize_c(size.1), T::from_usize_c(size.0));
        for ch in 0..c {
            let t = [
                tex[b.idx[0] * c + ch],
                tex[b.idx[1] * c + ch],
                tex[b.idx[2] * c + ch],
                tex[b.idx[3] * c + ch],
            ];
            val[ch] = w[0] * t[0] + w[1] * t[1] + w[2] * t[2] + w[3] * t[3];
            // x = u W - 1/2, y = (1 - v) H - 1/2.
            du[ch] = wf * ((one - b.fy) * (t[1] - t[0]) + b.fy * (t[3] - t[2]));
            dv[ch] = -hf * ((one - b.fx) * (t[2] - t[0]) + b.fx * (t[3] - t[1]));
        }
    }
}

/// The inputs in standard (row-major contiguous) layout, borrowed when they already are (the
/// usual case: no copy of the texture per call).
fn std_inputs<'a, T: Real>(inputs: &'a [TensorView<'_, T>]) -> Vec<CowArray<'a, T, IxDyn>> {
    inputs.iter().map(|t| t.as_standard_layout()).collect()
}

impl<T: Real> Op<T> for TextureOp<T> {
    fn name(&self) -> &'static str {
        match self.sampler.filter {
            Filter::Nearest => "texture_nearest",
            Filter::Bilinear => "texture_bilinear",
            Filter::Trilinear => "texture_trilinear",
        }
    }

    fn forward(&mut self, inputs: &[TensorView<'_, T>]) -> AdResult<Vec<Tensor<T>>> {
        let ins = std_inputs(inputs);
        self.check(&ins)?;
        let ts = ins[0].shape();
        let (h, w, c) = (ts[0], ts[1], ts[2]);
        let tex0 = ins[0].as_slice().expect("std");
        self.sizes = if self.sampler.filter == Filter::Trilinear && ins.len() > 2 {
            mip_sizes(h, w)
        } else {
            vec![(h, w)]
        };
        self.pyramid.clear();
        for k in 1..self.sizes.len() {
            let prev = if k == 1 { tex0 } else { &self.pyramid[k - 2] };
            let d = downsample(prev, self.sizes[k - 1], self.sizes[k], c);
            self.pyramid.push(d);
        }
        let v = View {
            n: ins[1].shape()[0],
            uv: ins[1].as_slice().expect("std"),
            da: ins.get(2).map(|d| d.as_slice().expect("std")),
        };
        let this = &*self;
        let mut out = vec![T::zero(); v.n * c];
        out.par_chunks_mut(CHUNK * c)
            .enumerate()
            .for_each(|(blk, o)| {
                for (r, px) in o.chunks_mut(c).enumerate() {
                    let i = blk * CHUNK + r;
                    this.for_taps(&v, i, |lev, idx, wt| {
                        let t = &this.level(tex0, lev)[idx * c..(idx + 1) * c];
                        for ch in 0..c {
                            px[ch] += wt * t[ch];
                        }
                    });
                }
            });
        Ok(vec![
            ArrayD::from_shape_vec(IxDyn(&[v.n, c]), out).expect("n x c")
        ])
    }

    fn backward(&self, ctx: &BackwardCtx<'_, '_, T>) -> AdResult<Vec<Option<Tensor<T>>>> {
        let ins = std_inputs(ctx.inputs);
        let ts = ins[0].shape().to_vec();
        let c = ts[2];
        let tex0 = ins[0].as_slice().expect("std");
        let v = View {
            n: ins[1].shape()[0],
            uv: ins[1].as_slice().expect("std"),
            da: ins.get(2).map(|d| d.as_slice().expect("std")),
        };
        let g = ctx.grad_outputs[0].as_standard_layout();
        let g = g.as_slice().expect("std");
        let mut out: Vec<Option<Tensor<T>>> = vec![None; ins.len()];
        if ctx.needs_grad[0] {
            // Sequential scatter in fragment order: deterministic, no atomics.
            let mut levels: Vec<Vec<T>> = self
                .sizes
                .iter()
                .map(|&(h, w)| vec![T::zero(); h * w * c])
                .collect();
            for i in 0..v.n {
                let gi = &g[i * c..(i + 1) * c];
                self.for_taps(&v, i, |lev, idx, wt| {
                    let dst = &mut levels[lev][idx * c..(idx + 1) * c];
                    for ch in 0..c {
                        dst[ch] += wt * gi[ch];
                    }
                });
            }
            for k in (1..self.sizes.len()).rev() {
                let (coarse, fine) = {
                    let (a, b) = levels.split_at_mut(k);
                    (&b[0], &mut a[k - 1])
                };
                downsample_adjoint(coarse, self.sizes[k - 1], self.sizes[k], c, fine);
            }
            let g0 = levels.swap_remove(0);
            out[0] = Some(ArrayD::from_shape_vec(IxDyn(&ts), g0).expect("texel shape"));
        }
        let need_uv = ctx.needs_grad[1];
        let need_da = ins.len() > 2 && ctx.needs_grad[2];
        if need_uv || need_da {
            // Per fragment: [g_u, g_v, g_da (4)].
            let mut rows = vec![T::zero(); v.n * 6];
            if self.sampler.filter != Filter::Nearest {
                rows.par_chunks_mut(CHUNK * 6)
                    .enumerate()
                    .for_each(|(blk, o)| {
                        let mut l0g = LevelGrad::new(c);
                        let mut l1g = LevelGrad::new(c);
                        for (r, row) in o.chunks_mut(6).enumerate() {
                            let i = blk * CHUNK + r;
                            let gi = &g[i * c..(i + 1) * c];
                            let (u, vv) = (v.uv[2 * i], v.uv[2 * i + 1]);
                            let l = self.lod_of(&v, i);
                            let has1 = l.l0 + 1 < self.sizes.len()
                                && self.sampler.filter == Filter::Trilinear;
                            self.bilinear_grad(self.level(tex0, l.l0), l.l0, u, vv, &mut l0g);
                            if has1 {
                                self.bilinear_grad(
                                    self.level(tex0, l.l0 + 1),
                                    l.l0 + 1,
                                    u,
                                    vv,
                                    &mut l1g,
                                );
                            }
                            let (w0, w1) = (T::one() - l.f, l.f);
                            let (mut gu, mut gv, mut glam) = (T::zero(), T::zero(), T::zero());
                            for ch in 0..c {
                                let (a, b) = if has1 {
                                    (
                                        w0 * l0g.du[ch] + w1 * l1g.du[ch],
                                        w0 * l0g.dv[ch] + w1 * l1g.dv[ch],
                                    )
                                } else {
                                    (l0g.du[ch], l0g.dv[ch])
                                };
                                gu += gi[ch] * a;
                                gv += gi[ch] * b;
                                if has1 {
                                    glam += gi[ch] * (l1g.val[ch] - l0g.val[ch]);
                                }
                            }
                            row[0] = gu;
                            row[1] = gv;
                            if let Some(d) = l.dlam {
                                if has1 {
                                    for k in 0..4 {
                                        row[2 + k] = glam * d[k];
                                    }
                                }
                            }
                        }
                    });
            }
            if need_uv {
                let guv: Vec<T> = rows.chunks(6).flat_map(|r| [r[0], r[1]]).collect();
                out[1] = Some(ArrayD::from_shape_vec(IxDyn(&[v.n, 2]), guv).expect("n x 2"));
            }
            if need_da {
                let gda: Vec<T> = rows
                    .chunks(6)
                    .flat_map(|r| [r[2], r[3], r[4], r[5]])
                    .collect();
                out[2] = Some(ArrayD::from_shape_vec(IxDyn(&[v.n, 4]), gda).expect("n x 4"));
            }
        }
        Ok(out)
    }
}

/// Samples texels `[H, W, C]` at `uv` `[N, 2]`: `[N, C]` (fused op with a hand-written
/// backward; see the module docs). `uv_da` `[N, 4]` (du/dx, dv/dx, du/dy, dv/dy per pixel)
/// selects the trilinear mip level; other filters ignore it (but accept it).
pub fn sample<'t, T: Real>(
    texels: Var<'t, T>,
    uv: Var<'t, T>,
    uv_da: Option<Var<'t, T>>,
    sampler: Sampler,
) -> Var<'t, T> {
    let op = TextureOp {
        sampler,
        pyramid: Vec::new(),
        sizes: Vec::new(),
    };
    match uv_da {
        Some(da) if sampler.filter == Filter::Trilinear => {
            texels.tape().apply(op, &[texels, uv, da])
        }
        _ => texels.tape().apply(op, &[texels, uv]),
    }
}

/// One mip step `[h, w, c] -> [h', w', c]` composed from tape ops (two matrix products).
pub fn downsample_composed<'t, T: Real>(level: Var<'t, T>) -> Var<'t, T> {
    let t = level.tape();
    let s = level.shape();
    let (h, w, c) = (s[0], s[1], s[2]);
    let (h2, w2) = ((h / 2).max(1), (w / 2).max(1));
    let matrix = |n: usize, m: usize| {
        let mut a = ArrayD::<T>::zeros(IxDyn(&[m, n]));
        for (i, taps) in downsample_weights(n, m).into_iter().enumerate() {
            for (j, wt) in taps {
                a[[i, j]] = T::from_f64c(wt);
            }
        }
        t.constant(a)
    };
    // Rows: [h2, h] @ [h, w c] -> [h2, w, c]; then columns: [w2, w] @ [w, h2 c].
    let a = matrix(h, h2)
        .matmul(level.reshape(&[h, w * c]))
        .reshape(&[h2, w, c]);
    let b = a.permute(&[1, 0, 2]).reshape(&[w, h2 * c]);
    matrix(w, w2)
        .matmul(b)
        .reshape(&[w2, h2, c])
        .permute(&[1, 0, 2])
}

/// Bilinear (or nearest) sampling of one level, composed: indices from the values (data),
/// weights from `uv` through tape ops.
fn sample_level_composed<'t, T: Real>(
    level: Var<'t, T>,
    uv: Var<'t, T>,
    filter: Filter,
    wrap: Wrap,
) -> Var<'t, T> {
    let s = level.shape();
    let (h, w, c) = (s[0], s[1], s[2]);
    let flat = level.reshape(&[h * w, c]);
    let uvv = match uv.value_ref() {
        Ok(v) => v,
        Err(_) => return uv,
    };
    let uvv = uvv.view();
    let n = uvv.shape()[0];
    let us: Vec<T> = (0..n).map(|i| uvv[[i, 0]]).collect();
    let vs: Vec<T> = (0..n).map(|i| uvv[[i, 1]]).collect();
    if filter == Filter::Nearest {
        let idx: Vec<usize> = (0..n)
            .map(|i| nearest_index(us[i], vs[i], (h, w), wrap))
            .collect();
        return flat.index_select(0, &idx);
    }
    let taps: Vec<Bilinear<T>> = (0..n)
        .map(|i| Bilinear::new(us[i], vs[i], (h, w), wrap))
        .collect();
    let t = uv.tape();
    let column = |f: &dyn Fn(usize) -> T| {
        t.constant(ArrayD::from_shape_vec(IxDyn(&[n, 1]), (0..n).map(f).collect()).expect("n x 1"))
    };
    // fx = x - floor(x) with x = u W - 1/2; fy likewise with y = (1 - v) H - 1/2 (the floors
    // are constants).
    let half = T::from_f64c(0.5);
    let (wf, hf) = (T::from_usize_c(w), T::from_usize_c(h));
    let x = uv.slice(1, 0, 1) * wf - half;
    let y = (-uv.slice(1, 1, 2) + T::one()) * hf - half;
    let fx = x - column(&|i| (us[i] * wf - half).floor());
    let fy = y - column(&|i| ((T::one() - vs[i]) * hf - half).floor());
    let gx = -fx + T::one();
    let gy = -fy + T::one();
    let weights = [gx * gy, fx * gy, gx * fy, fx * fy];
    let mut out: Option<Var<'t, T>> = None;
    for (k, wk) in weights.into_iter().enumerate() {
        let idx: Vec<usize> = taps.iter().map(|b| b.idx[k]).collect();
        let term = flat.index_select(0, &idx) * wk;
        out = Some(match out {
            None => term,
            Some(o) => o + term,
        });
    }
    out.expect("four taps")
}

/// [`sample`] composed from tape ops (the reference): the pyramid by matrix products, taps by
/// `index_select`, weights and the level of detail by elementwise ops.
pub fn sample_composed<'t, T: Real>(
    texels: Var<'t, T>,
    uv: Var<'t, T>,
    uv_da: Option<Var<'t, T>>,
    sampler: Sampler,
) -> Var<'t, T> {
    let s = texels.shape();
    if s.len() != 3 {
        // Let the fused op report the bad shape.
        return sample(texels, uv, uv_da, sampler);
    }
    let (h, w) = (s[0], s[1]);
    let (Filter::Trilinear, Some(da)) = (sampler.filter, uv_da) else {
        let filter = if sampler.filter == Filter::Trilinear {
            Filter::Bilinear
        } else {
            sampler.filter
        };
        return sample_level_composed(texels, uv, filter, sampler.wrap);
    };
    let t = texels.tape();
    let sizes = mip_sizes(h, w);
    let nl = sizes.len();
    if nl == 1 {
        return sample_level_composed(texels, uv, Filter::Bilinear, sampler.wrap);
    }
    let mut levels = vec![texels];
    for _ in 1..nl {
        let prev = *levels.last().expect("level 0");
        levels.push(downsample_composed(prev));
    }
    let (wf, hf) = (T::from_usize_c(w), T::from_usize_c(h));
    let rx = (da.slice(1, 0, 1) * wf).square() + (da.slice(1, 1, 2) * hf).square();
    let ry = (da.slice(1, 2, 3) * wf).square() + (da.slice(1, 3, 4) * hf).square();
    let lam = rx.maximum(ry).ln() * T::from_f64c(0.5 / std::f64::consts::LN_2);
    let lam = lam.clamp(T::zero(), T::from_usize_c(nl - 1));
    let lv = match lam.value() {
        Ok(v) => v,
        Err(_) => return lam,
    };
    let l0: Vec<usize> = lv
        .iter()
        .map(|&x| x.floor().to_usize().unwrap_or(0).min(nl - 1))
        .collect();
    let n = l0.len();
    let f = lam
        - t.constant(
            ArrayD::from_shape_vec(
                IxDyn(&[n, 1]),
                l0.iter().map(|&l| T::from_usize_c(l)).collect(),
            )
            .expect("n x 1"),
        );
    let zero = t.constant(tensor::scalar(T::zero()));
    let mut out: Option<Var<'t, T>> = None;
    for (k, &level) in levels.iter().enumerate() {
        let is0 = ArrayD::from_shape_vec(IxDyn(&[n, 1]), l0.iter().map(|&l| l == k).collect())
            .expect("n x 1");
        let is1 = ArrayD::from_shape_vec(IxDyn(&[n, 1]), l0.iter().map(|&l| l + 1 == k).collect())
            .expect("n x 1");
        if !is0.iter().chain(is1.iter()).any(|&b| b) {
            continue;
        }
        let wk = (-f + T::one()).where_(is0, f.where_(is1, zero));
        let term = sample_level_composed(level, uv, Filter::Bilinear, sampler.wrap) * wk;
        out = Some(match out {
            None => term,
            Some(o) => o + term,
        });
    }
    out.expect("some level is used")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_modes() {
        assert_eq!(
            (-1..7)
                .map(|i| Wrap::Repeat.apply(i, 3))
                .collect::<Vec<_>>(),
            [2, 0, 1, 2, 0, 1, 2, 0]
        );
        assert_eq!(
            (-1..7).map(|i| Wrap::Clamp.apply(i, 3)).collect::<Vec<_>>(),
            [0, 0, 1, 2, 2, 2, 2, 2]
        );
        assert_eq!(
            (-1..7)
                .map(|i| Wrap::Mirror.apply(i, 3))
                .collect::<Vec<_>>(),
            [0, 0, 1, 2, 2, 1, 0, 0]
        );
        assert_eq!(Wrap::Mirror.apply(-4, 3), 2);
        assert_eq!(
            Wrap::Repeat.apply(i64::MIN, 5),
            i64::MIN.rem_euclid(5) as usize
        );
    }

    #[test]
    fn mip_sizes_and_weights() {
        assert_eq!(mip_sizes(1, 1), vec![(1, 1)]);
        assert_eq!(mip_sizes(8, 3), vec![(8, 3), (4, 1), (2, 1), (1, 1)]);
        let w = downsample_weights(4, 2);
        assert_eq!(w, vec![vec![(0, 0.5), (1, 0.5)], vec![(2, 0.5), (3, 0.5)]]);
        let w = downsample_weights(5, 2);
        assert_eq!(
            w,
            vec![
                vec![(0, 0.4), (1, 0.4), (2, 0.2)],
                vec![(2, 0.2), (3, 0.4), (4, 0.4)]
            ]
        );
        for (n, m) in [(7, 3), (3, 1), (1, 1), (9, 4)] {
            for taps in downsample_weights(n, m) {
                assert!((taps.iter().map(|t| t.1).sum::<f64>() - 1.0).abs() < 1e-15);
            }
        }
    }

    #[test]
    fn pyramid_preserves_the_mean() {
        let tex = ArrayD::from_shape_fn(IxDyn(&[6, 10, 2]), |i| {
            (i[0] * 10 + i[1]) as f64 + i[2] as f64 * 0.5
        });
        let p = mip_pyramid(&tex);
        assert_eq!(p.len(), 4);
        let m0 = tex.mean().unwrap();
        // Each level is the area average of the one above: means agree.
        for l in &p {
            assert!(
                (l.mean().unwrap() - m0).abs() < 1e-12,
                "{} {}",
                l.mean().unwrap(),
                m0
            );
        }
    }

    #[test]
    fn bilinear_hits_texel_centres() {
        let (h, w) = (4usize, 5usize);
        for r in 0..h {
            for c in 0..w {
                let u = (c as f64 + 0.5) / w as f64;
                let v = 1.0 - (r as f64 + 0.5) / h as f64;
                let b = Bilinear::new(u, v, (h, w), Wrap::Clamp);
                assert_eq!(b.idx[0], r * w + c);
                assert!(b.fx.abs() < 1e-12 && b.fy.abs() < 1e-12);
                assert_eq!(nearest_index(u, v, (h, w), Wrap::Clamp), r * w + c);
            }
        }
    }
}
