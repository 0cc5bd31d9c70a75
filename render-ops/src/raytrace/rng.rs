//! Counter-based random numbers: every sample's numbers are a hash of (seed, stream, index,
//! dimension), so a render is the same for any thread count and any evaluation order (the
//! backward re-draws exactly the forward's numbers). Salmon et al., "Parallel random numbers:
//! as easy as 1, 2, 3", SC 2011 (counter-based generators); the mixing function is
//! SplitMix64's finaliser (Steele et al., OOPSLA 2014).

/// Independent streams of one render.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u64)]
pub enum Stream {
    /// Pixel samples: index = pixel * spp + sample; dimensions 0, 1 the jitter inside the
    /// sample's stratum, then two per area light.
    Pixel = 1,
    /// Primary edge samples: index = sample; dimensions: edge, position on it, then two per
    /// area light for the side evaluations.
    PrimaryEdge = 2,
    /// Shadow-edge samples of point and directional lights.
    ShadowEdge = 3,
    /// Secondary (area-light) edge samples: index = (pixel * spp + sample) * M + m.
    AreaEdge = 4,
}

#[inline(always)]
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The key of `stream` under `seed` (see [`Counter::at`]).
pub fn stream_key(seed: u64, stream: Stream) -> u64 {
    mix(seed ^ mix(stream as u64))
}

/// A point of the counter space: draws dimension after dimension.
#[derive(Clone, Copy, Debug, Default)]
pub struct Counter {
    key: u64,
    dim: u64,
}

impl Counter {
    /// The numbers of `index` in `stream` under `seed`.
    pub fn new(seed: u64, stream: Stream, index: u64) -> Self {
        Counter::at(stream_key(seed, stream), index)
    }

    /// The numbers of `index` in the stream of key `key` ([`stream_key`], hoisted out of
    /// per-sample loops): the same as [`Counter::new`].
    #[inline]
    pub fn at(key: u64, index: u64) -> Self {
        Counter {
            key: mix(key ^ index),
            dim: 0,
        }
    }

    /// The next uniform number in `[0, 1)` (53 bits).
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        let h = mix(self.key ^ self.dim.wrapping_mul(0xD1B5_4A32_D192_ED03));
        self.dim += 1;
        (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Skips `n` dimensions.
    pub fn skip(&mut self, n: u64) {
        self.dim += n;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_uniform_and_depend_on_every_coordinate() {
        let mut c = Counter::new(7, Stream::Pixel, 3);
        let xs: Vec<f64> = (0..20000).map(|_| c.uniform()).collect();
        assert!(xs.iter().all(|&x| (0.0..1.0).contains(&x)));
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        // 10 bins, chi-square with 9 degrees of freedom well below its 0.999 quantile (27.9).
        let mut bins = [0usize; 10];
        for x in &xs {
            bins[(x * 10.0) as usize] += 1;
        }
        let chi: f64 = bins
            .iter()
            .map(|&b| (b as f64 - 2000.0).powi(2) / 2000.0)
            .sum();
        assert!(chi < 27.9, "{chi} {bins:?}");
        let first = |seed, s, i| Counter::new(seed, s, i).uniform();
        let base = first(7, Stream::Pixel, 3);
        assert_eq!(base, xs[0]);
        assert_ne!(base, first(8, Stream::Pixel, 3));
        assert_ne!(base, first(7, Stream::PrimaryEdge, 3));
        assert_ne!(base, first(7, Stream::Pixel, 4));
    }
}
