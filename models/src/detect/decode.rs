//! From the detector's raw outputs to face boxes: anchor decoding (MediaPipe
//! `TensorsToDetectionsCalculator`), weighted non-maximum suppression
//! (`NonMaxSuppressionCalculator`, `WEIGHTED`, IoU) and undoing the letterbox
//! (`DetectionProjectionCalculator`); kit README steps 3 to 5.

use super::anchors::{DET_SIZE, NUM_ANCHORS};

/// Values per anchor in the regressor output: box centre offset, size, 6 keypoints (x, y).
pub const NUM_COORDS: usize = 16;
/// Keypoints per detection: right eye, left eye, nose tip, mouth centre, right and left ear
/// tragion (the subject's right and left).
pub const NUM_KEYPOINTS: usize = 6;
/// `min_score_thresh` of the decoder (MediaPipe's `min_detection_confidence` default).
pub const MIN_SCORE: f64 = 0.5;
/// `min_suppression_threshold` of the weighted NMS: boxes with IoU above it are merged.
pub const NMS_IOU: f64 = 0.3;

/// One detection in normalised coordinates (x divided by the width, y by the height) of
/// either the detector tensor or, after [`unletterbox`], the image.
#[derive(Clone, Debug, PartialEq)]
pub struct RawDetection {
    /// Face probability (sigmoid of the logit).
    pub score: f64,
    /// `xmin, ymin, xmax, ymax`.
    pub bbox: [f64; 4],
    /// Keypoints `(x, y)`.
    pub keypoints: [[f64; 2]; NUM_KEYPOINTS],
}

/// `1 / (1 + exp(-clamp(x, -100, 100)))` (`score_clipping_thresh` 100).
pub fn sigmoid_clipped(logit: f64) -> f64 {
    1.0 / (1.0 + (-logit.clamp(-100.0, 100.0)).exp())
}

/// Decodes every anchor whose score is at least `min_score`, in anchor order: centre
/// `r[0..2] / 128 + anchor`, size `r[2..4] / 128` (anchor size 1), keypoints
/// `r[4 + 2k..6 + 2k] / 128 + anchor`. Boxes of negative size and any non-finite value are
/// dropped. `regressors` is `[896 * 16]`, `classificators` `[896]`, `anchors` `[896]`.
pub fn decode(
    regressors: &[f32],
    classificators: &[f32],
    anchors: &[[f64; 2]],
    min_score: f64,
) -> Vec<RawDetection> {
    debug_assert_eq!(regressors.len(), NUM_ANCHORS * NUM_COORDS);
    debug_assert_eq!(classificators.len(), NUM_ANCHORS);
    let scale = DET_SIZE as f64;
    let mut out = Vec::new();
    for (i, (&[ax, ay], &logit)) in anchors.iter().zip(classificators).enumerate() {
        let score = sigmoid_clipped(logit as f64);
        if score.is_nan() || score < min_score {
            continue;
        }
        let r = &regressors[i * NUM_COORDS..(i + 1) * NUM_COORDS];
        let v = |k: usize| r[k] as f64 / scale;
        let (xc, yc, w, h) = (v(0) + ax, v(1) + ay, v(2), v(3));
        if !(w >= 0.0 && h >= 0.0) {
            continue;
        }
        let d = RawDetection {
            score,
            bbox: [xc - w / 2.0, yc - h / 2.0, xc + w / 2.0, yc + h / 2.0],
            keypoints: std::array::from_fn(|k| [v(4 + 2 * k) + ax, v(5 + 2 * k) + ay]),
        };
        if d.bbox
            .iter()
            .chain(d.keypoints.iter().flatten())
            .all(|x| x.is_finite())
        {
            out.push(d);
        }
    }
    out
}

/// Intersection over union of two `xmin, ymin, xmax, ymax` boxes; 0 when they do not overlap
/// or the union is not positive.
pub fn iou(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let ix = a[2].min(b[2]) - a[0].max(b[0]);
    let iy = a[3].min(b[3]) - a[1].max(b[1]);
    if !(ix >= 0.0 && iy >= 0.0) {
        return 0.0;
    }
    let inter = ix * iy;
    let area = |r: &[f64; 4]| (r[2] - r[0]) * (r[3] - r[1]);
    let union = area(a) + area(b) - inter;
    if union > 0.0 {
        inter / union
    } else {
        0.0
    }
}

/// Weighted non-maximum suppression: sorted by score (descending; ties keep their input
/// order, where MediaPipe's unstable sort leaves it open), the best remaining detection takes
/// every remaining one with IoU above `threshold` (itself included) and becomes their
/// score-weighted mean box and keypoints, keeping its own score. Output by score, descending.
pub fn weighted_nms(mut dets: Vec<RawDetection>, threshold: f64) -> Vec<RawDetection> {
    dets.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut out = Vec::new();
    let mut remaining = dets;
    while let Some(top) = remaining.first().cloned() {
        let before = remaining.len();
        let (candidates, rest): (Vec<_>, Vec<_>) = remaining
            .into_iter()
            .partition(|d| iou(&d.bbox, &top.bbox) > threshold);
        let total: f64 = candidates.iter().map(|d| d.score).sum();
        let merged = if candidates.is_empty() || total.is_nan() || total <= 0.0 {
            top
        } else {
            let mean = |f: &dyn Fn(&RawDetection) -> f64| {
                candidates.iter().map(|d| d.score * f(d)).sum::<f64>() / total
            };
            RawDetection {
                score: top.score,
                bbox: std::array::from_fn(|k| mean(&|d| d.bbox[k])),
                keypoints: std::array::from_fn(|k| {
                    [mean(&|d| d.keypoints[k][0]), mean(&|d| d.keypoints[k][1])]
                }),
            }
        };
        out.push(merged);
        if rest.len() == before {
            break;
        }
        remaining = rest;
    }
    out
}

/// Undoes the letterbox of a `width x height` image padded to a centred square of side
/// `max(width, height)`: `x_img = (x - 0.5) S / W + 0.5`, `y_img = (y - 0.5) S / H + 0.5`.
pub fn unletterbox(d: &RawDetection, width: usize, height: usize) -> RawDetection {
    let s = width.max(height) as f64;
    let (sx, sy) = (s / width as f64, s / height as f64);
    let px = |x: f64| (x - 0.5) * sx + 0.5;
    let py = |y: f64| (y - 0.5) * sy + 0.5;
    RawDetection {
        score: d.score,
        bbox: [px(d.bbox[0]), py(d.bbox[1]), px(d.bbox[2]), py(d.bbox[3])],
        keypoints: d.keypoints.map(|[x, y]| [px(x), py(y)]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::anchors::ssd_anchors;

    fn det(score: f64, bbox: [f64; 4]) -> RawDetection {
        RawDetection {
            score,
            bbox,
            keypoints: [[bbox[0], bbox[1]]; NUM_KEYPOINTS],
        }
    }

    #[test]
    fn decode_follows_the_formulas_and_drops_bad_boxes() {
        let anchors = ssd_anchors();
        let mut reg = vec![0f32; NUM_ANCHORS * NUM_COORDS];
        let mut cls = vec![-5f32; NUM_ANCHORS];
        // Anchor 600: centre offset (6.4, -12.8) px, size 32 x 64, keypoint k at k px right.
        let i = 600;
        cls[i] = 2.0;
        let r = &mut reg[i * NUM_COORDS..(i + 1) * NUM_COORDS];
        r[..4].copy_from_slice(&[6.4, -12.8, 32.0, 64.0]);
        for k in 0..NUM_KEYPOINTS {
            r[4 + 2 * k] = k as f32;
        }
        // Anchor 10: negative width; anchor 11: NaN size; anchor 12: score exactly 0.5.
        cls[10] = 3.0;
        reg[10 * NUM_COORDS + 2] = -1.0;
        cls[11] = 3.0;
        reg[11 * NUM_COORDS + 3] = f32::NAN;
        cls[12] = 0.0;
        let d = decode(&reg, &cls, &anchors, MIN_SCORE);
        assert_eq!(d.len(), 2, "{d:?}");
        assert_eq!(d[0].score, 0.5);
        let [ax, ay] = anchors[i];
        let g = &d[1];
        assert!((g.score - 1.0 / (1.0 + (-2f64).exp())).abs() < 1e-15);
        let (xc, yc) = (6.4f32 as f64 / 128.0 + ax, -12.8f32 as f64 / 128.0 + ay);
        let want = [xc - 0.125, yc - 0.25, xc + 0.125, yc + 0.25];
        for (got, want) in g.bbox.iter().zip(want) {
            assert!((got - want).abs() < 1e-15);
        }
        for k in 0..NUM_KEYPOINTS {
            assert!((g.keypoints[k][0] - (k as f64 / 128.0 + ax)).abs() < 1e-15);
            assert_eq!(g.keypoints[k][1], ay);
        }
        // Clipped logits: no overflow, no NaN.
        assert_eq!(sigmoid_clipped(1e30), 1.0 / (1.0 + (-100f64).exp()));
        assert!(sigmoid_clipped(-1e30) > 0.0);
        assert!(sigmoid_clipped(f64::NAN).is_nan());
    }

    #[test]
    fn iou_cases() {
        let a = [0.0, 0.0, 2.0, 2.0];
        assert_eq!(iou(&a, &a), 1.0);
        assert_eq!(iou(&a, &[1.0, 0.0, 3.0, 2.0]), 2.0 / 6.0);
        assert_eq!(iou(&a, &[3.0, 3.0, 4.0, 4.0]), 0.0);
        assert_eq!(iou(&[0.0, 0.0, 0.0, 0.0], &[0.0, 0.0, 0.0, 0.0]), 0.0);
        assert_eq!(iou(&a, &[f64::NAN, 0.0, 1.0, 1.0]), 0.0);
    }

    #[test]
    fn weighted_nms_merges_overlaps_and_keeps_the_top_score() {
        let dets = vec![
            det(0.6, [0.1, 0.1, 0.3, 0.3]),
            det(0.9, [0.0, 0.0, 0.2, 0.2]),
            det(0.8, [0.7, 0.7, 0.9, 0.9]),
            // IoU with the 0.9 box: 0.01 / 0.07 < 0.3: a separate face.
            det(0.7, [0.1, 0.1, 0.3, 0.3]),
        ];
        let out = weighted_nms(dets, NMS_IOU);
        assert_eq!(out.len(), 3, "{out:?}");
        assert_eq!(
            out.iter().map(|d| d.score).collect::<Vec<_>>(),
            [0.9, 0.8, 0.7]
        );
        assert_eq!(out[0].bbox, [0.0, 0.0, 0.2, 0.2]);
        // 0.7 and 0.6 (identical boxes) merged: their weighted mean is the same box.
        assert!((out[2].bbox[0] - 0.1).abs() < 1e-15);
        // Two overlapping boxes: score-weighted mean.
        let out = weighted_nms(
            vec![
                det(0.75, [0.0, 0.0, 1.0, 1.0]),
                det(0.25, [0.1, 0.0, 1.1, 1.0]),
            ],
            NMS_IOU,
        );
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].score, 0.75);
        assert!((out[0].bbox[0] - 0.025).abs() < 1e-15);
        assert!((out[0].bbox[2] - 1.025).abs() < 1e-15);
        assert!((out[0].keypoints[0][0] - 0.025).abs() < 1e-15);
        assert!(weighted_nms(Vec::new(), NMS_IOU).is_empty());
        // A degenerate top (zero area: IoU 0 with everything, itself included) ends the loop.
        let out = weighted_nms(
            vec![
                det(0.9, [0.5, 0.5, 0.5, 0.5]),
                det(0.8, [0.0, 0.0, 1.0, 1.0]),
            ],
            NMS_IOU,
        );
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].score, 0.9);
    }

    #[test]
    fn unletterbox_maps_the_padded_square_back() {
        // 200 x 100 image: the square of side 200 has 50 px of padding above and below.
        let d = det(1.0, [0.0, 0.25, 1.0, 0.75]);
        let u = unletterbox(&d, 200, 100);
        assert_eq!(u.bbox, [0.0, 0.0, 1.0, 1.0]);
        assert_eq!(u.keypoints[0], [0.0, 0.0]);
        let u = unletterbox(&det(1.0, [0.25, 0.0, 0.75, 1.0]), 100, 200);
        assert_eq!(u.bbox, [0.0, 0.0, 1.0, 1.0]);
    }
}
