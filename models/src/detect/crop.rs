//! Image to model tensor: an oriented square of the image (the region of interest) sampled
//! bilinearly into an `n x n` RGB tensor, as MediaPipe's `ImageToTensorCalculator` does on
//! the CPU (`cv::warpPerspective`, `INTER_LINEAR`, on the 8-bit image: samples rounded to
//! 0..255); kit README steps 1 and 6, and the crop of a detection
//! (`DetectionsToRectsCalculator` + `RectTransformationCalculator`).
//!
//! Coordinates here are OpenCV pixel coordinates: integer values are pixel centres (the
//! public types add 0.5).

use ndarray::ArrayView3;
use rayon::prelude::*;

/// How taps outside the image read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Border {
    /// As 0 (black): the detector's letterbox (`BORDER_ZERO`).
    Zero,
    /// As the nearest edge pixel: the landmark crop (`BORDER_REPLICATE`).
    Replicate,
}

/// An oriented square of the image: centre, side and rotation (radians; positive turns the
/// crop's x axis from the image's x axis towards its y axis, i.e. clockwise on screen).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Roi {
    /// Centre x (pixels, OpenCV convention).
    pub cx: f64,
    /// Centre y.
    pub cy: f64,
    /// Side (pixels).
    pub size: f64,
    /// Rotation (radians).
    pub rotation: f64,
}

/// Scale of the detection box to the landmark crop (`scale_x = scale_y = 1.5`).
pub const CROP_SCALE: f64 = 1.5;

/// `a - 2 pi floor((a + pi) / (2 pi))`: the angle in [-pi, pi).
pub fn normalize_radians(a: f64) -> f64 {
    use std::f64::consts::PI;
    a - 2.0 * PI * ((a + PI) / (2.0 * PI)).floor()
}

impl Roi {
    /// The letterbox of the detector: the whole `width x height` image padded to the centred
    /// square of side `max(width, height)`.
    pub fn letterbox(width: usize, height: usize) -> Roi {
        Roi {
            cx: width as f64 / 2.0,
            cy: height as f64 / 2.0,
            size: width.max(height) as f64,
            rotation: 0.0,
        }
    }

    /// The landmark crop of a detection (box and eye keypoints in pixels): centred on the box,
    /// side 1.5 times the box's longer side, rotated by the angle of the right-eye to
    /// left-eye vector.
    pub fn from_detection(bbox: &[f64; 4], right_eye: [f64; 2], left_eye: [f64; 2]) -> Roi {
        let (w, h) = (bbox[2] - bbox[0], bbox[3] - bbox[1]);
        let rotation = normalize_radians(
            0.0 - (-(left_eye[1] - right_eye[1])).atan2(left_eye[0] - right_eye[0]),
        );
        Roi {
            cx: bbox[0] + w / 2.0,
            cy: bbox[1] + h / 2.0,
            size: CROP_SCALE * w.max(h),
            rotation,
        }
    }

    /// The image point sampled by tensor pixel `(u, v)` of an `n x n` tensor:
    /// `(cx, cy) + R(t) ((u/n - 0.5) L, (v/n - 0.5) L)`; also the map of the landmark model's
    /// outputs (crop pixels) back to the image.
    pub fn image_point(&self, u: f64, v: f64, n: usize) -> [f64; 2] {
        let (s, c) = self.rotation.sin_cos();
        let n = n as f64;
        let dx = (u / n - 0.5) * self.size;
        let dy = (v / n - 0.5) * self.size;
        [self.cx + c * dx - s * dy, self.cy + s * dx + c * dy]
    }
}

/// An `[H, W, 3]` image in [0, 1] read as 8-bit values (`round(255 x)`, clamped), the form
/// MediaPipe samples.
fn tap(image: &ArrayView3<'_, f64>, y: i64, x: i64, k: usize, border: Border) -> f64 {
    let (h, w) = (image.shape()[0] as i64, image.shape()[1] as i64);
    let inside = (0..w).contains(&x) && (0..h).contains(&y);
    if !inside && border == Border::Zero {
        return 0.0;
    }
    let (yy, xx) = (y.clamp(0, h - 1) as usize, x.clamp(0, w - 1) as usize);
    (image[[yy, xx, k]].clamp(0.0, 1.0) * 255.0).round()
}

/// Samples `roi` into an `n x n x 3` tensor of 8-bit values (row-major, RGB): bilinear
/// between the four pixels around each point of [`Roi::image_point`], rounded half to even and
/// clamped to 0..255. `image` is `[H, W, 3]` in [0, 1], non-empty and finite (the caller
/// checks).
pub fn sample(image: &ArrayView3<'_, f64>, roi: &Roi, n: usize, border: Border) -> Vec<u8> {
    let mut out = vec![0u8; n * n * 3];
    out.par_chunks_mut(n * 3).enumerate().for_each(|(v, row)| {
        for u in 0..n {
            let [x, y] = roi.image_point(u as f64, v as f64, n);
            let (x0, y0) = (x.floor(), y.floor());
            let (fx, fy) = (x - x0, y - y0);
            // Far outside the image every tap is a border tap: clamp before the cast.
            let (xi, yi) = (x0.clamp(-2.0, 1e15) as i64, y0.clamp(-2.0, 1e15) as i64);
            for k in 0..3 {
                let t = |dy: i64, dx: i64| tap(image, yi + dy, xi + dx, k, border);
                let val = t(0, 0) * (1.0 - fx) * (1.0 - fy)
                    + t(0, 1) * fx * (1.0 - fy)
                    + t(1, 0) * (1.0 - fx) * fy
                    + t(1, 1) * fx * fy;
                row[u * 3 + k] = val.round_ties_even().clamp(0.0, 255.0) as u8;
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    fn ramp(h: usize, w: usize) -> Array3<f64> {
        Array3::from_shape_fn((h, w, 3), |(r, c, k)| {
            ((r * 7 + c * 3 + k * 50) % 256) as f64 / 255.0
        })
    }

    #[test]
    fn identity_roi_reads_the_pixels() {
        // An 8 x 8 ROI over an 8 x 8 image: tensor pixel (u, v) samples image point
        // (u, v) exactly (centre 4, side 8: x = 4 + (u/8 - 0.5) 8 = u).
        let img = ramp(8, 8);
        let roi = Roi::letterbox(8, 8);
        let t = sample(&img.view(), &roi, 8, Border::Zero);
        for v in 0..8 {
            for u in 0..8 {
                for k in 0..3 {
                    assert_eq!(
                        t[(v * 8 + u) * 3 + k] as f64,
                        (img[[v, u, k]] * 255.0).round()
                    );
                }
            }
        }
    }

    #[test]
    fn letterbox_pads_with_zero_and_crop_replicates() {
        // 4 x 8 (H x W) white image: the square of side 8 covers rows -2..6.
        let img = Array3::from_elem((4, 8, 3), 1.0);
        let t = sample(&img.view(), &Roi::letterbox(8, 4), 8, Border::Zero);
        let at = |v: usize, u: usize| t[(v * 8 + u) * 3];
        assert_eq!(at(0, 3), 0); // row -2
        assert_eq!(at(1, 3), 0); // row -1: both taps outside
        assert_eq!(at(2, 3), 255);
        assert_eq!(at(5, 3), 255);
        assert_eq!(at(6, 3), 0); // row 4
        let r = sample(&img.view(), &Roi::letterbox(8, 4), 8, Border::Replicate);
        assert!(r.iter().all(|&x| x == 255));
        // Far outside: border taps only, no overflow.
        let far = Roi {
            cx: 1e300,
            cy: -1e300,
            size: 10.0,
            rotation: 0.3,
        };
        assert!(sample(&img.view(), &far, 4, Border::Replicate)
            .iter()
            .all(|&x| x == 255));
        assert!(sample(&img.view(), &far, 4, Border::Zero)
            .iter()
            .all(|&x| x == 0));
    }

    #[test]
    fn bilinear_weights_and_rounding() {
        // Two pixels 0 and 255 (well, 1.0): halfway is 127.5, which rounds half to even.
        let mut img = Array3::zeros((1, 2, 3));
        img[[0, 1, 0]] = 1.0;
        img[[0, 1, 1]] = 1.0;
        img[[0, 1, 2]] = 1.0;
        let roi = Roi {
            cx: 1.5,
            cy: 0.5,
            size: 2.0,
            rotation: 0.0,
        };
        // n = 2, side 2: u = 0 samples x = cx - 1 = 0.5.
        let t = sample(&img.view(), &roi, 2, Border::Replicate);
        assert_eq!(t[0], 128); // 127.5 -> 128 (even)
        let roi = Roi {
            cx: 0.25 + 1.0,
            ..roi
        };
        let t = sample(&img.view(), &roi, 2, Border::Replicate);
        assert_eq!(t[0], 64); // 0.25 * 255 = 63.75
    }

    #[test]
    fn rotation_follows_the_eye_vector() {
        // Left eye (image right) lower than the right eye: positive rotation.
        let roi = Roi::from_detection(&[0.0, 0.0, 10.0, 20.0], [2.0, 5.0], [8.0, 11.0]);
        assert!((roi.rotation - std::f64::consts::FRAC_PI_4).abs() < 1e-15);
        assert_eq!((roi.cx, roi.cy, roi.size), (5.0, 10.0, 30.0));
        // Level eyes: 0; eyes swapped (upside-down face): -pi, kept in [-pi, pi).
        let level = Roi::from_detection(&[0.0, 0.0, 1.0, 1.0], [0.0, 0.0], [1.0, 0.0]);
        assert_eq!(level.rotation, 0.0);
        let flipped = Roi::from_detection(&[0.0, 0.0, 1.0, 1.0], [1.0, 0.0], [0.0, 0.0]);
        assert!((flipped.rotation + std::f64::consts::PI).abs() < 1e-15);
        assert_eq!(
            normalize_radians(std::f64::consts::PI),
            -std::f64::consts::PI
        );
        // The tensor's x axis runs along the eye vector: (u, v) = (n, n/2) lies on it.
        let [x, y] = roi.image_point(4.0, 2.0, 4);
        let h = roi.size / 2.0 / std::f64::consts::SQRT_2;
        assert!((x - (5.0 + h)).abs() < 1e-12 && (y - (10.0 + h)).abs() < 1e-12);
    }
}
