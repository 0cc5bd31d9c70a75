//! The short-range BlazeFace detector (Bazarevsky et al. 2019, "BlazeFace: Sub-millisecond
//! Neural Face Detection on Mobile GPUs"; MediaPipe `face_detection_short_range.tflite`,
//! converted to ONNX): a 128 x 128 letterboxed RGB image in [-1, 1] to 896 anchor boxes
//! with 6 keypoints each; kit README "Model 1".

use ndarray::ArrayView3;

use super::anchors::{ssd_anchors, DET_SIZE, NUM_ANCHORS};
use super::crop::{sample, Border, Roi};
use super::decode::NUM_COORDS;
use super::decode::{decode, unletterbox, weighted_nms, RawDetection, MIN_SCORE, NMS_IOU};
use super::onnx::Plan;
use super::DetectError;

/// The detector model, embedded (Apache-2.0, see `models/data/landmarker/NOTICE`).
pub const MODEL_ONNX: &[u8] =
    include_bytes!("../../data/landmarker/face_detection_short_range.onnx");

/// The runnable detector and its anchors.
pub(crate) struct BlazeFace {
    plan: Plan,
    anchors: Vec<[f64; 2]>,
}

/// The detector's raw outputs: `regressors` `[896 * 16]`, `classificators` `[896]` (logits).
pub(crate) struct RawOutputs {
    pub regressors: Vec<f32>,
    pub classificators: Vec<f32>,
}

/// 8-bit samples to the detector's input values `q * (2/255) - 1` (float32 arithmetic, as
/// MediaPipe's `output_tensor_float_range {min: -1 max: 1}`).
pub(crate) fn to_input(q: &[u8]) -> Vec<f32> {
    let scale = (2.0f64 / 255.0) as f32;
    q.iter().map(|&v| v as f32 * scale - 1.0).collect()
}

impl BlazeFace {
    /// Loads and optimises the embedded model.
    pub fn new() -> Result<Self, DetectError> {
        Ok(BlazeFace {
            plan: Plan::new("face detector", MODEL_ONNX, [1, DET_SIZE, DET_SIZE, 3])?,
            anchors: ssd_anchors(),
        })
    }

    /// Runs the network on an input tensor `[128 * 128 * 3]` (NHWC, values in [-1, 1]).
    pub fn run(&self, input: Vec<f32>) -> Result<RawOutputs, DetectError> {
        let mut out = self
            .plan
            .run(input, &[NUM_ANCHORS * NUM_COORDS, NUM_ANCHORS])?;
        let classificators = out.pop().expect("two outputs");
        let regressors = out.pop().expect("two outputs");
        Ok(RawOutputs {
            regressors,
            classificators,
        })
    }

    /// Decodes, merges (weighted NMS) and un-letterboxes raw outputs of a `width x height`
    /// image: detections in normalised image coordinates, by score, descending.
    pub fn postprocess(&self, raw: &RawOutputs, width: usize, height: usize) -> Vec<RawDetection> {
        let dets = decode(
            &raw.regressors,
            &raw.classificators,
            &self.anchors,
            MIN_SCORE,
        );
        weighted_nms(dets, NMS_IOU)
            .iter()
            .map(|d| unletterbox(d, width, height))
            .collect()
    }

    /// The detector tensor of an `[H, W, 3]` image in [0, 1] as 8-bit samples (letterbox,
    /// zero border).
    pub fn sample(image: &ArrayView3<'_, f64>) -> Vec<u8> {
        let (h, w) = (image.shape()[0], image.shape()[1]);
        sample(image, &Roi::letterbox(w, h), DET_SIZE, Border::Zero)
    }

    /// The whole detector stage on a checked image: normalised image coordinates.
    pub fn detect(&self, image: &ArrayView3<'_, f64>) -> Result<Vec<RawDetection>, DetectError> {
        let (h, w) = (image.shape()[0], image.shape()[1]);
        let raw = self.run(to_input(&Self::sample(image)))?;
        Ok(self.postprocess(&raw, w, h))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::testdata::{
        assert_close_model, assert_samples_match, npy, photo, png_u8, reference_detection,
    };

    #[test]
    fn synthetic_pattern_reproduces_tracts_reference_outputs() {
        let det = BlazeFace::new().unwrap();
        let raw = det
            .run(crate::detect::testdata::pattern(DET_SIZE, -1.0, 1.0))
            .unwrap();
        assert_close_model(
            &raw.regressors,
            &npy("synthetic_det_expected_regressors.npy"),
            "regressors",
        );
        assert_close_model(
            &raw.classificators,
            &npy("synthetic_det_expected_classificators.npy"),
            "classificators",
        );
        // Not a face: no anchor reaches 0.5.
        assert!(det.postprocess(&raw, 128, 128).is_empty());
    }

    #[test]
    fn photo_stages_reproduce_the_reference_pipeline() {
        let det = BlazeFace::new().unwrap();
        for name in ["camera", "grace_hopper"] {
            let img = photo(name);
            let (h, w) = (img.shape()[0], img.shape()[1]);
            // Letterbox sampling against the reference's rounded samples.
            let want = png_u8(&format!("{name}_det_input.png"));
            assert_samples_match(name, &BlazeFace::sample(&img.view()), &want);
            // The network on the reference input.
            let raw = det.run(to_input(&want)).unwrap();
            let regs = npy(&format!("{name}_det_expected_regressors.npy"));
            let cls = npy(&format!("{name}_det_expected_classificators.npy"));
            assert_close_model(&raw.regressors, &regs, "regressors");
            assert_close_model(&raw.classificators, &cls, "classificators");
            // Decoding, weighted NMS and projection of the reference outputs.
            let expected = RawOutputs {
                regressors: regs,
                classificators: cls,
            };
            let got = det.postprocess(&expected, w, h);
            let r = reference_detection(name);
            assert_eq!(got.len(), 1, "{name}: {got:?}");
            let g = &got[0];
            assert!(
                (g.score - r.score).abs() < 1e-12,
                "{name}: score {} vs {}",
                g.score,
                r.score
            );
            for k in 0..4 {
                assert!(
                    (g.bbox[k] - r.bbox[k]).abs() < 1e-12,
                    "{name}: box {:?} vs {:?}",
                    g.bbox,
                    r.bbox
                );
            }
            for k in 0..6 {
                for c in 0..2 {
                    assert!(
                        (g.keypoints[k][c] - r.keypoints[k][c]).abs() < 1e-12,
                        "{name}: keypoint {k}"
                    );
                }
            }
            // The whole stage from the photo.
            let d = det.detect(&img.view()).unwrap();
            assert_eq!(d.len(), 1);
            assert!((d[0].score - r.score).abs() < 1e-3);
            for k in 0..4 {
                assert!((d[0].bbox[k] - r.bbox[k]).abs() < 1e-3);
            }
        }
    }
}
