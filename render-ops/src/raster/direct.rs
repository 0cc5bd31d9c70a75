//! Direct hard render of per-vertex attributes (vertex colours): the tiled z-buffer pass of
//! [`super::hard`] with one fragment per pixel, followed in the same tile task by the
//! attribute interpolation and the hard blend, written straight into the image `[H, W, C + 1]`.
//!
//! It is the image of [`rasterize`](super::rasterize_fragments) (`K = 1`) +
//! [`interpolate`](crate::interpolate::interpolate) +
//! [`blend_hard`](crate::blend::blend_hard), bit for bit, for a forward that needs no
//! gradients: no packed fragment list, no `[N, C]` fragment colours, no second and third
//! pass over the image. The barycentrics are those of the fragments' `f64` edge functions
//! ([`RunConsts::values`], the same operations lane-wise in [`shade_run_avx2`]), rounded to
//! `T` as the fragments store them ([`sat`]); the colours are
//! `b_0 a_0 + b_1 a_1 + b_2 a_2` in `T` in that order, as `interpolate` computes them; a
//! covered pixel gets alpha 1, an empty one the background and alpha 0.

use autodiff::Real;
use rayon::prelude::*;

use super::bin::{Bins, FaceRec};
use super::clip::Rect;
use super::edge::sat;
use super::edge::Setup;
use super::fragments::RunConsts;
use super::hard::{prepare, z_test_tile, Ctx, NoShade, Scratch, ZShader, SPAN_LANES};
use super::{RasterError, RasterSettings, TILE_SIZE};

/// The hard render of per-vertex attributes `attrs` (`[V, C]` row-major, `C =
/// background.len()`) over `background`: an image `[H, W, C + 1]` (row-major, last channel
/// the coverage), equal bit for bit to [`rasterize`](super::rasterize_fragments) with one fragment per
/// pixel followed by [`interpolate`](crate::interpolate::interpolate) and
/// [`blend_hard`](crate::blend::blend_hard). `faces_per_pixel` is ignored (only the nearest
/// fragment is drawn); the other settings act as in the rasterizer. Parallel over tiles,
/// bit-identical for any number of threads.
///
/// # Errors
/// Those of [`rasterize`](super::rasterize_fragments), and attributes whose length is not
/// `V * background.len()`.
pub fn render_attributes_direct<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    attrs: &[T],
    background: &[T],
    s: &RasterSettings,
) -> Result<Vec<T>, RasterError> {
    render_attributes_with(clip, faces, attrs, background, s, true)
}

/// [`render_attributes_direct`], with the AVX2 kernels only if `avx2` (and the CPU has them).
pub(crate) fn render_attributes_with<T: Real>(
    clip: &[[T; 4]],
    faces: &[[u32; 3]],
    attrs: &[T],
    background: &[T],
    s: &RasterSettings,
    avx2: bool,
) -> Result<Vec<T>, RasterError> {
    let c = background.len();
    if attrs.len() != clip.len() * c {
        return Err(RasterError::LengthMismatch {
            what: "attributes (vertices x background channels)",
            got: attrs.len(),
            expected: clip.len() * c,
        });
    }
    let s1 = RasterSettings {
        faces_per_pixel: 1,
        ..*s
    };
    let (verts, bins, avx2) = prepare(clip, faces, &s1, avx2)?;
    let ctx = Ctx {
        verts: &verts,
        bins: &bins,
        s: &s1,
        avx2,
    };
    let (w, h) = (s.width, s.height);
    let n = w * h * (c + 1);
    let mut img = Vec::<T>::with_capacity(n);
    // One tile row of background pixels (alpha 0), copied into every tile row first.
    let mut bg_row = Vec::with_capacity(TILE_SIZE * (c + 1));
    for _ in 0..TILE_SIZE {
        bg_row.extend_from_slice(background);
        bg_row.push(T::zero());
    }
    let job = Shade {
        bins: &bins,
        faces,
        attrs,
        background,
        bg_row: &bg_row,
        width: w,
        persp: s.perspective_correct,
        avx2,
        out: img.as_mut_ptr(),
    };
    #[cfg(target_arch = "x86_64")]
    if avx2 && c == 3 && std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>() {
        // f32 RGB: shaded in the z-test ([`RgbShader`]).
        // SAFETY: `T` is `f32` (checked above), so the slices and the pointer are `f32` ones.
        let (attrs32, bg32, job32) = unsafe {
            (
                std::slice::from_raw_parts(attrs.as_ptr().cast::<f32>(), attrs.len()),
                std::slice::from_raw_parts(background.as_ptr().cast::<f32>(), 3),
                &*(&job as *const Shade<'_, T>).cast::<Shade<'_, f32>>(),
            )
        };
        macro_rules! go {
            ($p:literal) => {
                (0..bins.num_tiles()).into_par_iter().for_each(|t| {
                    Scratch::with(1, |sc| {
                        RgbShader::<$p>::with(faces, attrs32, bg32, |sh| {
                            let rect = bins.tile_rect(t, w, h);
                            let any = z_test_tile(t, &rect, &ctx, sc, sh);
                            // SAFETY: tile `t` writes only the pixels of its own rectangle
                            // (the tiles partition the image), below `w * h`, within the
                            // capacity.
                            unsafe { finish_tile(job32, &rect, any.then_some(sc), sh) };
                        })
                    })
                })
            };
        }
        if s.perspective_correct {
            go!(true)
        } else {
            go!(false)
        }
        // SAFETY: every pixel lies in exactly one tile, which wrote all its values.
        unsafe { img.set_len(n) };
        return Ok(img);
    }
    (0..bins.num_tiles()).into_par_iter().for_each(|t| {
        Scratch::with(1, |sc| {
            let rect = bins.tile_rect(t, w, h);
            let any = z_test_tile(t, &rect, &ctx, sc, &mut NoShade);
            // SAFETY: tile `t` writes only the pixels of its own rectangle (the tiles
            // partition the image), below `w * h`, within the capacity.
            unsafe { finish_tile(&job, &rect, any.then_some(sc), &mut Deferred) };
        })
    });
    // SAFETY: every pixel lies in exactly one tile, which wrote all its `c + 1` values.
    unsafe { img.set_len(n) };
    Ok(img)
}

/// Read-only inputs of the shading step and the image being written.
struct Shade<'a, T> {
    bins: &'a Bins,
    faces: &'a [[u32; 3]],
    attrs: &'a [T],
    background: &'a [T],
    /// [`TILE_SIZE`] background pixels (alpha 0).
    bg_row: &'a [T],
    width: usize,
    persp: bool,
    avx2: bool,
    /// The image, `[H, W, C + 1]`, uninitialised; each tile writes its own pixels.
    out: *mut T,
}

// SAFETY: `out` is only written at the pixels of the tile being shaded, which no other task
// reads or writes (see `render_attributes_with`); the rest is shared read-only data.
unsafe impl<T: Sync> Sync for Shade<'_, T> {}

/// How [`finish_tile`] writes a tile row.
trait RowShader<T> {
    /// Writes the `ncols` pixels of local row `lr` (image row `row`) of the tile starting at
    /// column `col0`, whose first pixel is at `dst`: the background and, from the K-buffer
    /// `sc` (`None`: no face was binned to the tile), the nearest fragment of every covered
    /// pixel.
    ///
    /// # Safety
    /// The row's pixels at `dst` are the caller's to write.
    #[allow(clippy::too_many_arguments)]
    unsafe fn row(
        &mut self,
        job: &Shade<'_, T>,
        sc: Option<&Scratch>,
        lr: usize,
        row: usize,
        ncols: usize,
        col0: u32,
        dst: *mut T,
    );
}

/// Writes the pixels of tile `rect` (row by row, [`RowShader::row`]) from the K-buffer `sc`
/// (`None`: no face was binned to the tile), whose tested spans it then resets for the next
/// tile (as [`super::fragments::TileFrags::pack`]).
///
/// # Safety
/// No other task reads or writes the tile's pixels of `job.out`.
unsafe fn finish_tile<T: Real, R: RowShader<T>>(
    job: &Shade<'_, T>,
    rect: &Rect,
    mut sc: Option<&mut Scratch>,
    shade: &mut R,
) {
    let p = job.background.len() + 1;
    let ncols = (rect.c1 - rect.c0) as usize + 1;
    for lr in 0..(rect.r1 - rect.r0) as usize + 1 {
        let row = rect.r0 as usize + lr;
        // SAFETY: the row's pixels `rect.c0..=rect.c1` are this tile's (the caller's
        // contract).
        unsafe {
            let dst = job.out.add((row * job.width + rect.c0 as usize) * p);
            shade.row(job, sc.as_deref(), lr, row, ncols, rect.c0, dst);
        }
        if let Some(sc) = sc.as_deref_mut() {
            sc.reset_row(lr);
        }
    }
}

/// Deferred shading: per run of consecutive covered pixels of one face record, the
/// barycentrics from its edge functions ([`shade_run`]).
struct Deferred;

impl<T: Real> RowShader<T> for Deferred {
    #[inline(always)]
    unsafe fn row(
        &mut self,
        job: &Shade<'_, T>,
        sc: Option<&Scratch>,
        lr: usize,
        row: usize,
        ncols: usize,
        col0: u32,
        dst: *mut T,
    ) {
        let p = job.background.len() + 1;
        // SAFETY: the row's `ncols` pixels are the caller's; `bg_row` holds `TILE_SIZE >=
        // ncols` pixels.
        unsafe { std::ptr::copy_nonoverlapping(job.bg_row.as_ptr(), dst, ncols * p) };
        let Some(sc) = sc.filter(|sc| sc.filled[lr] > 0) else {
            return;
        };
        let (c0, c1) = sc.span[lr];
        let (c0, c1) = (c0 as usize, c1 as usize);
        let base = lr * TILE_SIZE;
        let (d, ids) = (&sc.depth[base..base + TILE_SIZE], &sc.idx[base..]);
        let (mut j, end) = (c0, c1);
        while j < end {
            if !(d[j] <= 1.0) {
                j += 1;
                continue;
            }
            let id = ids[j];
            let mut e = j + 1;
            while e < end && d[e] <= 1.0 && ids[e] == id {
                e += 1;
            }
            let rec = job.bins.rec(id);
            // SAFETY: pixels `j..e` of the row are the caller's.
            unsafe { shade_run(job, rec, row as f64, col0 + j as u32, e - j, dst.add(j * p)) };
            j = e;
        }
    }
}

/// Writes the `n` covered pixels of face record `rec` at columns `col0..col0 + n` of `row`
/// (starting at `dst`), with [`shade_run_avx2`] when the CPU has AVX2.
///
/// # Safety
/// The `n` pixels at `dst` are the caller's to write.
#[inline(always)]
unsafe fn shade_run<T: Real>(
    job: &Shade<'_, T>,
    rec: &FaceRec,
    row: f64,
    col0: u32,
    n: usize,
    dst: *mut T,
) {
    macro_rules! go {
        ($p:literal) => {{
            #[cfg(target_arch = "x86_64")]
            if job.avx2 {
                // SAFETY: `avx2` only with CPU support (`prepare`); the caller's contract.
                return unsafe { shade_run_avx2::<T, $p>(job, rec, row, col0, n, dst) };
            }
            // SAFETY: the caller's contract.
            unsafe { shade_run_scalar::<T, $p>(job, rec, row, col0, n, dst) }
        }};
    }
    if job.persp {
        go!(true)
    } else {
        go!(false)
    }
}

/// The corner attribute rows of face `f` (`c` channels each).
#[inline(always)]
fn corners<T>(attrs: &[T], f: [u32; 3], c: usize) -> [&[T]; 3] {
    f.map(|v| &attrs[v as usize * c..][..c])
}

/// Writes one covered pixel: `b_0 a_0 + b_1 a_1 + b_2 a_2` per channel (as `interpolate`),
/// then alpha 1 (as `blend_hard`).
///
/// # Safety
/// The `c + 1` values at `dst` are the caller's to write.
#[inline(always)]
unsafe fn write_pixel<T: Real>(dst: *mut T, b: [T; 3], a: &[&[T]; 3], c: usize) {
    for ch in 0..c {
        // SAFETY: the caller's contract.
        unsafe {
            dst.add(ch)
                .write(b[0] * a[0][ch] + b[1] * a[1][ch] + b[2] * a[2][ch])
        };
    }
    // SAFETY: the caller's contract.
    unsafe { dst.add(c).write(T::one()) };
}

/// [`shade_run`] without SIMD: the fragments' barycentrics from [`RunConsts::values`].
///
/// # Safety
/// As [`shade_run`].
#[inline(always)]
unsafe fn shade_run_scalar<T: Real, const PERSP: bool>(
    job: &Shade<'_, T>,
    rec: &FaceRec,
    row: f64,
    col0: u32,
    n: usize,
    dst: *mut T,
) {
    let c = job.background.len();
    let a = corners(job.attrs, job.faces[rec.face as usize], c);
    let k = RunConsts::new::<PERSP>(&rec.st, row);
    for i in 0..n {
        let (bary, ..) = k.values::<PERSP>(&rec.st, (col0 as usize + i) as f64);
        // SAFETY: pixel `i` of the run is the caller's.
        unsafe { write_pixel(dst.add(i * (c + 1)), bary.map(sat::<T>), &a, c) };
    }
}

/// [`shade_run_scalar`] with AVX2, four pixels at a time: the barycentrics with the same
/// IEEE operations in the same order as [`RunConsts::values`] (no fused multiply-adds), so
/// the same bits. For `f32` RGB whose four barycentrics are in range (the rounding is then
/// [`sat`]'s), the colours are made in `f32` lanes (the same products and sums as
/// [`write_pixel`]) and the four RGBA pixels written from registers; otherwise per pixel.
///
/// # Safety
/// As [`shade_run`], and the CPU supports AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn shade_run_avx2<T: Real, const PERSP: bool>(
    job: &Shade<'_, T>,
    rec: &FaceRec,
    row: f64,
    col0: u32,
    n: usize,
    dst: *mut T,
) {
    use std::arch::x86_64::*;
    const L: usize = 4;
    let c = job.background.len();
    let st = &rec.st;
    let a = corners(job.attrs, job.faces[rec.face as usize], c);
    let k = RunConsts::new::<PERSP>(st, row);
    let v = |x: f64| _mm256_set1_pd(x);
    let (ea, et, sw) = (st.a.map(v), k.t.map(v), k.sw.map(v));
    let one = v(1.0);
    let abs_mask = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
    let mv = v(T::max_value().to_f64c());
    let in_range = |x: __m256d| _mm256_cmp_pd::<_CMP_LE_OQ>(_mm256_and_pd(x, abs_mask), mv);
    let rgb32 = std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>() && c == 3;
    // f32 RGB: the corners' channels broadcast to four lanes (unused otherwise).
    let ch = |v: usize, ch: usize| {
        if rgb32 {
            _mm_set1_ps(a[v][ch].to_f64c() as f32)
        } else {
            _mm_setzero_ps()
        }
    };
    let av = [0, 1, 2].map(|ch_| [ch(0, ch_), ch(1, ch_), ch(2, ch_)]);
    let alpha = _mm_set1_ps(1.0);
    let col_base = _mm256_add_pd(v(col0 as f64), _mm256_setr_pd(0.0, 1.0, 2.0, 3.0));
    let mut i = 0;
    while i < n {
        let lanes = (n - i).min(L);
        // Lanes past the run hold values computed and never written.
        let col = _mm256_add_pd(col_base, v(i as f64));
        let e = [0, 1, 2].map(|q| _mm256_add_pd(_mm256_mul_pd(ea[q], col), et[q]));
        let bary = if PERSP {
            let inv = _mm256_div_pd(one, _mm256_add_pd(_mm256_add_pd(e[0], e[1]), e[2]));
            e.map(|x| _mm256_mul_pd(x, inv))
        } else {
            [0, 1, 2].map(|q| _mm256_mul_pd(e[q], sw[q]))
        };
        let ok = _mm256_movemask_pd(_mm256_and_pd(
            _mm256_and_pd(in_range(bary[0]), in_range(bary[1])),
            in_range(bary[2]),
        ));
        let live = (1 << lanes) - 1;
        if rgb32 && ok & live == live {
            let b = bary.map(|x| _mm256_cvtpd_ps(x));
            let mut px = [0, 1, 2].map(|q| {
                let s = _mm_add_ps(_mm_mul_ps(b[0], av[q][0]), _mm_mul_ps(b[1], av[q][1]));
                _mm_add_ps(s, _mm_mul_ps(b[2], av[q][2]))
            });
            let mut w = alpha;
            let [r, g, bl] = &mut px;
            _MM_TRANSPOSE4_PS(r, g, bl, &mut w);
            let rows = [px[0], px[1], px[2], w];
            let d = dst.cast::<f32>();
            for (l, &r) in rows.iter().enumerate().take(lanes) {
                // SAFETY: pixel `i + l` of the run (four f32) is the caller's; `T` is f32.
                unsafe { _mm_storeu_ps(d.add(4 * (i + l)), r) };
            }
        } else {
            let spill = |x: __m256d| {
                let mut r = [0.0; L];
                // SAFETY: `r` holds four f64.
                unsafe { _mm256_storeu_pd(r.as_mut_ptr(), x) };
                r
            };
            let bary = bary.map(spill);
            for l in 0..lanes {
                let b = [bary[0][l], bary[1][l], bary[2][l]].map(sat::<T>);
                // SAFETY: pixel `i + l` of the run is the caller's.
                unsafe { write_pixel(dst.add((i + l) * (c + 1)), b, &a, c) };
            }
        }
        i += L;
    }
}

/// Immediate shading of `f32` RGB attributes in the z-test ([`ZShader`]): each fragment that
/// wins its pixel gets its colour at once, from the edge values the z-test has just computed,
/// into a per-tile colour buffer that [`finish_tile`] copies out for the covered pixels. The
/// same values as [`shade_run_avx2`]: barycentrics with [`RunConsts::values`]'s operations
/// (`e_i / sum e` or `e_i w_i / det`), rounded as [`sat`], colours as [`write_pixel`].
#[cfg(target_arch = "x86_64")]
struct RgbShader<'a, const PERSP: bool> {
    faces: &'a [[u32; 3]],
    /// `[V, 3]`.
    attrs: &'a [f32],
    /// Per K-buffer slot (local pixel) of the current tile: the RGBA of the last fragment
    /// that won it, the background (alpha 0) where none did. [`RowShader::row`] copies the
    /// rows out and resets their tested spans to the background.
    color: &'a mut [[f32; 4]],
    /// The background pixel.
    bg: [f32; 4],
    /// The current face: `w_i / det` (screen-space barycentrics) and its corners' colours.
    sw: [f64; 3],
    corners: [[f32; 3]; 3],
}

#[cfg(target_arch = "x86_64")]
thread_local! {
    /// This thread's [`RgbShader`] colour buffer between tile passes, all set to the
    /// background it holds.
    #[allow(clippy::type_complexity)]
    static COLOR: std::cell::RefCell<Option<(Vec<[f32; 4]>, [f32; 4])>> =
        const { std::cell::RefCell::new(None) };
}

#[cfg(target_arch = "x86_64")]
impl<const PERSP: bool> RgbShader<'_, PERSP> {
    /// Runs `f` with a shader whose colour buffer holds the background: this thread's cached
    /// buffer (a tile pass leaves it all background), refilled if it was left with another
    /// background (see [`Scratch::with`]).
    fn with<R>(
        faces: &[[u32; 3]],
        attrs: &[f32],
        bg: &[f32],
        f: impl FnOnce(&mut RgbShader<'_, PERSP>) -> R,
    ) -> R {
        let bg = [bg[0], bg[1], bg[2], 0.0];
        let (mut color, was) = COLOR
            .with(|c| c.borrow_mut().take())
            .unwrap_or_else(|| (vec![bg; TILE_SIZE * TILE_SIZE + SPAN_LANES], bg));
        if was.map(f32::to_bits) != bg.map(f32::to_bits) {
            color.fill(bg);
        }
        let r = f(&mut RgbShader {
            faces,
            attrs,
            color: &mut color,
            bg,
            sw: [0.0; 3],
            corners: [[0.0; 3]; 3],
        });
        // A panic in `f` drops the buffer instead of caching a dirty one.
        COLOR.with(|c| *c.borrow_mut() = Some((color, bg)));
        r
    }

    /// The colour of barycentrics `b` (rounded), alpha 1 ([`write_pixel`]).
    #[inline(always)]
    fn rgba(&self, b: [f32; 3]) -> [f32; 4] {
        let a = &self.corners;
        let ch = |c: usize| b[0] * a[0][c] + b[1] * a[1][c] + b[2] * a[2][c];
        [ch(0), ch(1), ch(2), 1.0]
    }
}

#[cfg(target_arch = "x86_64")]
impl<const PERSP: bool> ZShader for RgbShader<'_, PERSP> {
    const ACTIVE: bool = true;

    #[inline(always)]
    fn face(&mut self, rec: &FaceRec) {
        let st = &rec.st;
        // As `RunConsts::new`.
        self.sw = [
            st.w[0] * st.inv_det,
            st.w[1] * st.inv_det,
            st.w[2] * st.inv_det,
        ];
        self.corners = self.faces[rec.face as usize].map(|v| {
            let a = &self.attrs[v as usize * 3..][..3];
            [a[0], a[1], a[2]]
        });
    }

    #[inline(always)]
    unsafe fn lanes(
        &mut self,
        e: &[std::arch::x86_64::__m256d; 3],
        sum: std::arch::x86_64::__m256d,
        m: i32,
        slot: usize,
    ) {
        use std::arch::x86_64::*;
        let abs_mask = _mm256_castsi256_pd(_mm256_set1_epi64x(i64::MAX));
        let mv = _mm256_set1_pd(f32::MAX as f64);
        let in_range = |x: __m256d| _mm256_cmp_pd::<_CMP_LE_OQ>(_mm256_and_pd(x, abs_mask), mv);
        let (bary, inr) = if PERSP {
            let inv = _mm256_div_pd(_mm256_set1_pd(1.0), sum);
            // The winning lanes are certainly inside (`e_i > bnd_i > 0`) with `sum e > 0`, so
            // `0 < b_i <= 1` (each `e_i <= sum e`, rounding is monotonic) unless `1 / sum e`
            // overflows: one test instead of three.
            let finite = _mm256_cmp_pd::<_CMP_LE_OQ>(inv, _mm256_set1_pd(f64::MAX));
            (e.map(|x| _mm256_mul_pd(x, inv)), _mm256_movemask_pd(finite))
        } else {
            let b = [0, 1, 2].map(|q| _mm256_mul_pd(e[q], _mm256_set1_pd(self.sw[q])));
            let inr = _mm256_movemask_pd(_mm256_and_pd(
                _mm256_and_pd(in_range(b[0]), in_range(b[1])),
                in_range(b[2]),
            ));
            (b, inr)
        };
        if m & !inr != 0 {
            // A winning lane out of `f32`'s range (slivers at the limits of `f64`): per lane,
            // saturated.
            let spill = |x: __m256d| {
                let mut r = [0.0; SPAN_LANES];
                // SAFETY: `r` holds four f64.
                unsafe { _mm256_storeu_pd(r.as_mut_ptr(), x) };
                r
            };
            let b = bary.map(spill);
            for l in 0..SPAN_LANES {
                if m & (1 << l) != 0 {
                    let bl = [b[0][l], b[1][l], b[2][l]].map(sat::<f32>);
                    self.color[slot + l] = self.rgba(bl);
                }
            }
            return;
        }
        let dst = &mut self.color[slot..slot + SPAN_LANES];
        let b = bary.map(|x| _mm256_cvtpd_ps(x));
        let a = &self.corners;
        let mut px = [0, 1, 2].map(|c| {
            let t = |v: usize| _mm_mul_ps(b[v], _mm_set1_ps(a[v][c]));
            _mm_add_ps(_mm_add_ps(t(0), t(1)), t(2))
        });
        let mut w = _mm_set1_ps(1.0);
        let [r, g, bl] = &mut px;
        _MM_TRANSPOSE4_PS(r, g, bl, &mut w);
        let rows = [px[0], px[1], px[2], w];
        let d = dst.as_mut_ptr().cast::<f32>();
        if m == 0b1111 {
            for (l, &r) in rows.iter().enumerate() {
                // SAFETY: slot `slot + l` is in `dst` (four f32 each).
                unsafe { _mm_storeu_ps(d.add(4 * l), r) };
            }
        } else {
            for (l, &r) in rows.iter().enumerate() {
                if m & (1 << l) != 0 {
                    // SAFETY: as above.
                    unsafe { _mm_storeu_ps(d.add(4 * l), r) };
                }
            }
        }
    }

    #[inline(always)]
    fn pixel(&mut self, st: &Setup, col: f64, row: f64, slot: usize) {
        let (bary, ..) = RunConsts::new::<PERSP>(st, row).values::<PERSP>(st, col);
        self.color[slot] = self.rgba(bary.map(sat::<f32>));
    }
}

#[cfg(target_arch = "x86_64")]
impl<const PERSP: bool> RowShader<f32> for RgbShader<'_, PERSP> {
    #[inline(always)]
    unsafe fn row(
        &mut self,
        _job: &Shade<'_, f32>,
        sc: Option<&Scratch>,
        lr: usize,
        _row: usize,
        ncols: usize,
        _col0: u32,
        dst: *mut f32,
    ) {
        let base = lr * TILE_SIZE;
        // SAFETY: the row's `ncols` RGBA pixels are the caller's.
        unsafe {
            std::ptr::copy_nonoverlapping(
                self.color[base..base + ncols].as_ptr(),
                dst.cast::<[f32; 4]>(),
                ncols,
            )
        };
        if let Some(sc) = sc {
            let (c0, c1) = sc.span[lr];
            if c0 < c1 {
                self.color[base + c0 as usize..base + c1 as usize].fill(self.bg);
            }
        }
    }
}
