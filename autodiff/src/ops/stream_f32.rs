//! Explicit AVX2 + FMA `f32` kernels of the matrix-vector products `A x` and `A^T g` over a
//! row-major block of rows, for the memory-bound linear models (a 3DMM basis is tens of
//! megabytes, read once per product).
//!
//! Both walk the block one row at a time, so the matrix is read as ONE sequential stream.
//! Measured on this project's 2-core AMD EPYC machine (`B` = [105000, 199] f32, 1 thread):
//! a row-at-a-time product streams `B` at the speed of a plain summing read (about 11-12 GB/s),
//! while the same arithmetic walking four consecutive rows side by side (four interleaved
//! streams 796 bytes apart) reaches only about 6-7 GB/s. A row of `K` values is `K / 8` full
//! 8-lane vectors and a masked tail (`vmaskmovps`), so no scalar remainder loop runs per row.
//! The compiler's own vectorisation of the generic kernels (in [`super::linalg`]) is kept for
//! `f64` and for CPUs without AVX2 + FMA.

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
    unsafe fn hsum(v: __m256) -> f32 {
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

/// Whether the explicit kernels can run on this CPU.
#[inline]
fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `ys[r] = rows[r] . x` for consecutive rows of length `x.len()`; `false` (nothing done) when
/// the CPU lacks AVX2 + FMA.
pub(crate) fn gemv_rows(rows: &[f32], x: &[f32], ys: &mut [f32]) -> bool {
    assert_eq!(rows.len(), ys.len() * x.len(), "gemv_rows: block shape");
    if !available() {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the features are present and the shapes were checked above.
    unsafe {
        avx2::gemv_rows(rows, x, ys)
    };
    true
}

/// `acc += sum_r g[r] rows[r]` for consecutive rows of length `acc.len()`; `false` (nothing
/// done) when the CPU lacks AVX2 + FMA.
pub(crate) fn axpy_rows(rows: &[f32], g: &[f32], acc: &mut [f32]) -> bool {
    assert_eq!(rows.len(), g.len() * acc.len(), "axpy_rows: block shape");
    if !available() {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the features are present and the shapes were checked above.
    unsafe {
        avx2::axpy_rows(rows, g, acc)
    };
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Both kernels against f64 sums, for every tail length and for rows shorter than a vector.
    #[test]
    fn kernels_match_f64_sums() {
        if !available() {
            return;
        }
        let mut r = Rng::new(5);
        for k in [1usize, 3, 7, 8, 9, 15, 16, 17, 24, 31, 199] {
            let m = 13;
            let a: Vec<f32> = (0..m * k).map(|_| r.normal() as f32).collect();
            let x: Vec<f32> = (0..k).map(|_| r.normal() as f32).collect();
            let g: Vec<f32> = (0..m).map(|_| r.normal() as f32).collect();
            let mut y = vec![0.0f32; m];
            assert!(gemv_rows(&a, &x, &mut y));
            for (i, &yi) in y.iter().enumerate() {
                let want: f64 = (0..k).map(|j| a[i * k + j] as f64 * x[j] as f64).sum();
                let scale: f64 = (0..k).map(|j| (a[i * k + j] * x[j]).abs() as f64).sum();
                assert!(
                    (yi as f64 - want).abs() <= 1e-6 * scale.max(1.0),
                    "k {k} row {i}"
                );
            }
            let mut acc = vec![0.5f32; k];
            assert!(axpy_rows(&a, &g, &mut acc));
            for (j, &v) in acc.iter().enumerate() {
                let want: f64 = 0.5
                    + (0..m)
                        .map(|i| g[i] as f64 * a[i * k + j] as f64)
                        .sum::<f64>();
                let scale: f64 = 0.5
                    + (0..m)
                        .map(|i| (g[i] * a[i * k + j]).abs() as f64)
                        .sum::<f64>();
                assert!((v as f64 - want).abs() <= 1e-6 * scale, "k {k} col {j}");
            }
        }
    }
}
