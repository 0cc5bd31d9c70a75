//! Explicit `f32` kernels of the matrix-vector products `A x` and `A^T g` over a row-major
//! block of rows, for the memory-bound linear models (a 3DMM basis is tens of megabytes, read
//! once per product): AVX-512 where the CPU has it, else AVX2 + FMA, chosen at run time, with
//! the same bits either way (the AVX-512 forms add the same products in the same order; a test
//! holds them bit for bit).
//!
//! Both walk the block one row at a time, so the matrix is read as ONE sequential stream.
//! Measured on a 2-core AMD EPYC machine (`B` = [105000, 199] f32, 1 thread): a row-at-a-time
//! product streams `B` at the speed of a plain summing read (about 11-12 GB/s), while the same
//! arithmetic walking four consecutive rows side by side (four interleaved streams 796 bytes
//! apart) reaches only about 6-7 GB/s. A row of `K` values is `K / 8` full 8-lane vectors and
//! a masked tail, so no scalar remainder loop runs per row. The AVX-512 `A^T g` keeps the `K`
//! accumulators in registers across a block's rows, where the AVX2 kernel (16 registers)
//! loads and stores them on every row; the AVX-512 kernels also prefetch 4 KiB ahead of the
//! row they read (measured on an AVX-512 Xeon; the AVX2 kernels, measured on the AMD machine
//! at the summing read's speed without it, do not). The compiler's own vectorisation of the
//! generic kernels (in [`super::linalg`]) is kept for `f64` and for CPUs without AVX2 + FMA.

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    /// Eight lanes on, then eight off: `MASKS[8 - t..16 - t]` enables the first `t` lanes.
    static MASKS: [i32; 16] = [-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0];

    #[inline(always)]
    unsafe fn tail_mask(t: usize) -> __m256i {
        // SAFETY (caller): t <= 8, so the 8 lanes read lie inside MASKS.
        unsafe { _mm256_loadu_si256(MASKS.as_ptr().add(8 - t) as *const __m256i) }
    }

    #[inline(always)]
    pub(super) unsafe fn hsum(v: __m256) -> f32 {
        let h = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
        let h = _mm_hadd_ps(h, h);
        _mm_cvtss_f32(_mm_hadd_ps(h, h))
    }

    /// `ys[r] = rows[r] . x`; four accumulators per row (vector `c` into `c % 4`, enough
    /// independent FMA chains to cover the FMA latency), then the masked tail.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA; `rows.len() == ys.len() * x.len()`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn gemv_rows(rows: &[f32], x: &[f32], ys: &mut [f32]) {
        let k = x.len();
        let (full, t) = (k / 8, k % 8);
        // SAFETY: every pointer below stays inside `rows` (r < ys.len(), o + 8 <= full * 8 <=
        // k) or is a masked load whose enabled lanes are inside it (o + t == k).
        unsafe {
            let m = tail_mask(t);
            let xp = x.as_ptr();
            let xt = _mm256_maskload_ps(xp.add(full * 8), m);
            for (r, y) in ys.iter_mut().enumerate() {
                let p = rows.as_ptr().add(r * k);
                let mut a = [_mm256_setzero_ps(); 4];
                let mut c = 0;
                while c + 4 <= full {
                    for (j, aj) in a.iter_mut().enumerate() {
                        let o = 8 * (c + j);
                        *aj = _mm256_fmadd_ps(
                            _mm256_loadu_ps(p.add(o)),
                            _mm256_loadu_ps(xp.add(o)),
                            *aj,
                        );
                    }
                    c += 4;
                }
                while c < full {
                    let o = 8 * c;
                    a[c % 4] = _mm256_fmadd_ps(
                        _mm256_loadu_ps(p.add(o)),
                        _mm256_loadu_ps(xp.add(o)),
                        a[c % 4],
                    );
                    c += 1;
                }
                if t > 0 {
                    a[3] = _mm256_fmadd_ps(_mm256_maskload_ps(p.add(full * 8), m), xt, a[3]);
                }
                *y = hsum(_mm256_add_ps(
                    _mm256_add_ps(a[0], a[1]),
                    _mm256_add_ps(a[2], a[3]),
                ));
            }
        }
    }

    /// `acc += sum_r g[r] rows[r]`, row by row in order.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA; `rows.len() == g.len() * acc.len()`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn axpy_rows(rows: &[f32], g: &[f32], acc: &mut [f32]) {
        let k = acc.len();
        let (full, t) = (k / 8, k % 8);
        // SAFETY: as in `gemv_rows`; `acc` has k values.
        unsafe {
            let m = tail_mask(t);
            let ap = acc.as_mut_ptr();
            for (r, &gr) in g.iter().enumerate() {
                let p = rows.as_ptr().add(r * k);
                let gv = _mm256_set1_ps(gr);
                for c in 0..full {
                    let o = 8 * c;
                    let s =
                        _mm256_fmadd_ps(gv, _mm256_loadu_ps(p.add(o)), _mm256_loadu_ps(ap.add(o)));
                    _mm256_storeu_ps(ap.add(o), s);
                }
                if t > 0 {
                    let o = 8 * full;
                    let s = _mm256_fmadd_ps(
                        gv,
                        _mm256_maskload_ps(p.add(o), m),
                        _mm256_maskload_ps(ap.add(o), m),
                    );
                    _mm256_maskstore_ps(ap.add(o), m, s);
                }
            }
        }
    }
}

/// The AVX-512 forms of the two kernels, bit-identical to the AVX2 ones:
/// - `gemv_rows` keeps the AVX2 kernel's four 8-lane accumulators as two 16-lane ones
///   (`[a0 | a1]`, `[a2 | a3]`), so every lane sums the same products in the same order, and
///   reduces them in the same tree;
/// - `axpy_rows` adds `g[r] * rows[r]` to each `acc` value by one FMA per row in row order, as
///   the AVX2 kernel does, but holds up to 256 accumulators in registers across the block's
///   rows (the AVX2 kernel loads and stores `acc` on every row: its 16 registers cannot hold
///   a 3DMM's 199), so the only memory stream is the rows.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use std::arch::x86_64::*;

    /// How far ahead of the row being read the kernels prefetch, in bytes (rounded up to whole
    /// rows). The hardware prefetcher alone left the AVX-512 kernels at 1.2-1.7x the plain
    /// summing read at 2 threads on an AVX-512 Xeon; with software prefetch 4 KiB ahead they
    /// are at 1.06-1.20x (2048 and 8192 bytes measured no better).
    const PREFETCH_BYTES: usize = 4096;

    /// Rows of `k` values to prefetch ahead.
    #[inline(always)]
    fn rows_ahead(k: usize) -> usize {
        PREFETCH_BYTES.div_ceil(4 * k.max(1))
    }

    /// Prefetches the cache lines holding `n` values from `p` (a hint: it never faults, so `p`
    /// may lie past the end of the matrix).
    #[inline(always)]
    unsafe fn prefetch(p: *const f32, n: usize) {
        let b = p as *const i8;
        let mut at = 0;
        while at < 4 * n {
            // SAFETY: prefetching is a hint with no architectural effect, for any address.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(b.wrapping_add(at)) };
            at += 64;
        }
    }

    /// The upper 8 lanes (`_mm512_extractf32x8_ps` needs AVX-512DQ, which the kernels are not
    /// compiled for: it would be a call per row; the 64-bit extract of AVX-512F moves the same
    /// bits).
    #[inline(always)]
    fn upper(z: __m512) -> __m256 {
        // SAFETY (callers): compiled with AVX-512F.
        unsafe { _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(z))) }
    }

    /// The first `n` of 16 lanes.
    #[inline(always)]
    fn first(n: usize) -> __mmask16 {
        ((1u32 << n) - 1) as __mmask16
    }

    /// # Safety
    /// The CPU has AVX-512F, AVX2 and FMA; `rows.len() == ys.len() * x.len()`.
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub unsafe fn gemv_rows(rows: &[f32], x: &[f32], ys: &mut [f32]) {
        let k = x.len();
        // The AVX2 kernel's vectors: `full` of 8 lanes, in groups of four (`quads`), `left`
        // more, then a tail of `t` lanes into `a3`.
        let (full, t) = (k / 8, k % 8);
        let (quads, left) = (full / 4, full % 4);
        let o = 32 * quads;
        // Lanes of the leftover vectors: a0 (and a1) in `z0`, a2 in `z1`; the tail in `z1`'s
        // upper half, read from 8 values before the tail so that its lanes 8.. hold it.
        let (m0, m1) = match left {
            0 => (0, 0),
            1 => (first(8), 0),
            2 => (first(16), 0),
            _ => (first(16), first(8)),
        };
        let mt = first(8 + t) & !first(8);
        // SAFETY: unmasked loads read 16 values at `32 q (+ 16)` for q < quads (inside the
        // first 32 * quads <= k values); the masked loads' enabled lanes lie in `o..k`
        // (leftovers: o + 8 * left == 8 * full; tail: lanes 8..8 + t of `8 full - 8` are
        // `8 full .. k`); masked-off lanes are not read.
        unsafe {
            let xp = x.as_ptr();
            let x0 = _mm512_maskz_loadu_ps(m0, xp.add(o));
            let x1 = _mm512_maskz_loadu_ps(m1, xp.add(o + 16));
            let xt = _mm512_maskz_loadu_ps(mt, xp.add(8 * full).wrapping_sub(8));
            let ahead = rows_ahead(k) * k;
            for (r, y) in ys.iter_mut().enumerate() {
                let p = rows.as_ptr().add(r * k);
                prefetch(p.wrapping_add(ahead), k);
                let (mut z0, mut z1) = (_mm512_setzero_ps(), _mm512_setzero_ps());
                for q in 0..quads {
                    let o = 32 * q;
                    z0 = _mm512_fmadd_ps(_mm512_loadu_ps(p.add(o)), _mm512_loadu_ps(xp.add(o)), z0);
                    z1 = _mm512_fmadd_ps(
                        _mm512_loadu_ps(p.add(o + 16)),
                        _mm512_loadu_ps(xp.add(o + 16)),
                        z1,
                    );
                }
                z0 = _mm512_mask3_fmadd_ps(_mm512_maskz_loadu_ps(m0, p.add(o)), x0, z0, m0);
                z1 = _mm512_mask3_fmadd_ps(_mm512_maskz_loadu_ps(m1, p.add(o + 16)), x1, z1, m1);
                let pt = p.add(8 * full).wrapping_sub(8);
                z1 = _mm512_mask3_fmadd_ps(_mm512_maskz_loadu_ps(mt, pt), xt, z1, mt);
                // (a0 + a1) + (a2 + a3), then the AVX2 kernel's horizontal sum.
                let lo = _mm256_add_ps(_mm512_castps512_ps256(z0), upper(z0));
                let hi = _mm256_add_ps(_mm512_castps512_ps256(z1), upper(z1));
                *y = super::avx2::hsum(_mm256_add_ps(lo, hi));
            }
        }
    }

    /// `acc[..16 NV]` (the last vector masked by `mt`) `+= sum_r g[r] rows[r][..]`, with the
    /// accumulators in registers; row `r` starts at `rows + r * k`.
    #[inline(always)]
    unsafe fn axpy_panel<const NV: usize>(
        rows: *const f32,
        k: usize,
        g: &[f32],
        acc: *mut f32,
        mt: __mmask16,
    ) {
        let mask = |c: usize| if c + 1 == NV { mt } else { 0xffff };
        // SAFETY (caller): the panel's NV vectors (the last masked) lie inside every row and
        // inside `acc`.
        unsafe {
            let mut a = [_mm512_setzero_ps(); NV];
            for (c, ac) in a.iter_mut().enumerate() {
                *ac = _mm512_maskz_loadu_ps(mask(c), acc.add(16 * c));
            }
            let ahead = rows_ahead(k) * k;
            for (r, &gr) in g.iter().enumerate() {
                let p = rows.add(r * k);
                prefetch(p.wrapping_add(ahead), 16 * NV);
                let gv = _mm512_set1_ps(gr);
                for (c, ac) in a.iter_mut().enumerate() {
                    *ac = _mm512_fmadd_ps(gv, _mm512_maskz_loadu_ps(mask(c), p.add(16 * c)), *ac);
                }
            }
            for (c, ac) in a.iter().enumerate() {
                _mm512_mask_storeu_ps(acc.add(16 * c), mask(c), *ac);
            }
        }
    }

    /// # Safety
    /// The CPU has AVX-512F, AVX2 and FMA; `rows.len() == g.len() * acc.len()`.
    #[target_feature(enable = "avx512f,avx2,fma")]
    pub unsafe fn axpy_rows(rows: &[f32], g: &[f32], acc: &mut [f32]) {
        let k = acc.len();
        // Panels of up to 16 vectors (256 values) of every row.
        let mut c0 = 0;
        while c0 < k {
            let n = (k - c0).min(256);
            let nv = n.div_ceil(16);
            let mt = first(n - 16 * (nv - 1));
            // SAFETY: the panel is values c0..c0 + n of each row and of `acc`.
            unsafe {
                let (p, a) = (rows.as_ptr().add(c0), acc.as_mut_ptr().add(c0));
                macro_rules! panel {
                    ($($nv:literal)*) => {
                        match nv {
                            $($nv => axpy_panel::<$nv>(p, k, g, a, mt),)*
                            _ => unreachable!("1 to 16 vectors"),
                        }
                    };
                }
                panel!(1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16);
            }
            c0 += n;
        }
    }
}

/// Which explicit kernels run.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Isa {
    /// Neither: the generic kernels of [`super::linalg`] run.
    None,
    Avx2,
    Avx512,
}

/// The widest kernels this CPU can run (detected once).
fn isa() -> Isa {
    static ISA: std::sync::OnceLock<Isa> = std::sync::OnceLock::new();
    *ISA.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            if has!("avx2") && has!("fma") {
                return if has!("avx512f") {
                    Isa::Avx512
                } else {
                    Isa::Avx2
                };
            }
        }
        Isa::None
    })
}

/// Runs `$kernel($args)` from the module of `$isa`; `false` (nothing done) for
/// [`Isa::None`].
macro_rules! on_isa {
    ($isa:expr, $kernel:ident($($a:expr),*)) => {
        match $isa {
            Isa::None => false,
            // SAFETY: `isa` is this CPU's (or, in tests, one it runs), and the callers checked
            // the block's shape.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => {
                unsafe { avx2::$kernel($($a),*) };
                true
            }
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => {
                unsafe { avx512::$kernel($($a),*) };
                true
            }
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    };
}

/// `ys[r] = rows[r] . x` for consecutive rows of length `x.len()` with the kernels of `isa`;
/// `false` (nothing done) for [`Isa::None`].
fn gemv_rows_with(isa: Isa, rows: &[f32], x: &[f32], ys: &mut [f32]) -> bool {
    assert_eq!(rows.len(), ys.len() * x.len(), "gemv_rows: block shape");
    on_isa!(isa, gemv_rows(rows, x, ys))
}

/// `acc += sum_r g[r] rows[r]` for consecutive rows of length `acc.len()` with the kernels of
/// `isa`; `false` (nothing done) for [`Isa::None`].
fn axpy_rows_with(isa: Isa, rows: &[f32], g: &[f32], acc: &mut [f32]) -> bool {
    assert_eq!(rows.len(), g.len() * acc.len(), "axpy_rows: block shape");
    on_isa!(isa, axpy_rows(rows, g, acc))
}

/// `ys[r] = rows[r] . x` for consecutive rows of length `x.len()`, with the widest kernels
/// the CPU runs; `false` (nothing done) when it lacks AVX2 + FMA.
pub(crate) fn gemv_rows(rows: &[f32], x: &[f32], ys: &mut [f32]) -> bool {
    gemv_rows_with(isa(), rows, x, ys)
}

/// `acc += sum_r g[r] rows[r]` for consecutive rows of length `acc.len()`, with the widest
/// kernels the CPU runs; `false` (nothing done) when it lacks AVX2 + FMA.
pub(crate) fn axpy_rows(rows: &[f32], g: &[f32], acc: &mut [f32]) -> bool {
    axpy_rows_with(isa(), rows, g, acc)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// The kernels this CPU runs: AVX2, and AVX-512 where present.
    fn isas() -> Vec<Isa> {
        match isa() {
            Isa::None => vec![],
            Isa::Avx2 => vec![Isa::Avx2],
            Isa::Avx512 => vec![Isa::Avx2, Isa::Avx512],
        }
    }

    /// Both kernels against f64 sums, for every tail length, rows shorter than a vector and
    /// rows wider than one AVX-512 panel, on each instruction set the CPU runs.
    #[test]
    fn kernels_match_f64_sums() {
        assert!(
            !cfg!(target_arch = "x86_64") || isa() != Isa::None,
            "x86-64 without AVX2"
        );
        let mut r = Rng::new(5);
        for isa in isas() {
            for k in [
                1usize, 3, 7, 8, 9, 15, 16, 17, 24, 31, 32, 33, 199, 300, 513,
            ] {
                let m = 13;
                let a: Vec<f32> = (0..m * k).map(|_| r.normal() as f32).collect();
                let x: Vec<f32> = (0..k).map(|_| r.normal() as f32).collect();
                let g: Vec<f32> = (0..m).map(|_| r.normal() as f32).collect();
                let mut y = vec![0.0f32; m];
                assert!(gemv_rows_with(isa, &a, &x, &mut y));
                for (i, &yi) in y.iter().enumerate() {
                    let want: f64 = (0..k).map(|j| a[i * k + j] as f64 * x[j] as f64).sum();
                    let scale: f64 = (0..k).map(|j| (a[i * k + j] * x[j]).abs() as f64).sum();
                    assert!(
                        (yi as f64 - want).abs() <= 1e-6 * scale.max(1.0),
                        "{isa:?} k {k} row {i}"
                    );
                }
                let mut acc = vec![0.5f32; k];
                assert!(axpy_rows_with(isa, &a, &g, &mut acc));
                for (j, &v) in acc.iter().enumerate() {
                    let want: f64 = 0.5
                        + (0..m)
                            .map(|i| g[i] as f64 * a[i * k + j] as f64)
                            .sum::<f64>();
                    let scale: f64 = 0.5
                        + (0..m)
                            .map(|i| (g[i] * a[i * k + j]).abs() as f64)
                            .sum::<f64>();
                    assert!(
                        (v as f64 - want).abs() <= 1e-6 * scale,
                        "{isa:?} k {k} col {j}"
                    );
                }
            }
        }
    }

    /// The AVX-512 kernels give the AVX2 kernels' bits (the same sums in the same order).
    #[test]
    fn avx512_kernels_equal_avx2_bit_for_bit() {
        if isa() != Isa::Avx512 {
            eprintln!("no AVX-512 on this CPU: only the AVX2 kernels run");
            return;
        }
        let mut r = Rng::new(9);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for k in 1usize..=70 {
            for k in [k, k + 190, k + 250] {
                let m = 5;
                let a: Vec<f32> = (0..m * k).map(|_| r.normal() as f32).collect();
                let x: Vec<f32> = (0..k).map(|_| r.normal() as f32).collect();
                let g: Vec<f32> = (0..m).map(|_| r.normal() as f32).collect();
                let (mut y2, mut y5) = (vec![0.0f32; m], vec![0.0f32; m]);
                gemv_rows_with(Isa::Avx2, &a, &x, &mut y2);
                gemv_rows_with(Isa::Avx512, &a, &x, &mut y5);
                assert_eq!(bits(&y2), bits(&y5), "gemv k {k}");
                let (mut a2, mut a5) = (x.clone(), x.clone());
                axpy_rows_with(Isa::Avx2, &a, &g, &mut a2);
                axpy_rows_with(Isa::Avx512, &a, &g, &mut a5);
                assert_eq!(bits(&a2), bits(&a5), "axpy k {k}");
            }
        }
    }
}
