//! The face-mesh landmark model (Kartynnik et al. 2019, "Real-time Facial Surface Geometry
//! from Monocular Video on Mobile GPUs"; MediaPipe `face_landmark.tflite`, converted to
//! ONNX): a 192 x 192 RGB crop in [0, 1] to 468 points (x, y in crop pixels, z relative
//! depth) and a face-presence logit; kit README "Model 2", steps 6 to 8.

use ndarray::{Array2, ArrayView3};

use super::crop::{sample, Border, Roi};
use super::decode::sigmoid_clipped;
use super::onnx::Plan;
use super::DetectError;

/// Side of the landmark model's input (pixels).
pub const LM_SIZE: usize = 192;
/// Landmarks of the face mesh.
pub const NUM_LANDMARKS: usize = 468;

/// The landmark model, embedded (Apache-2.0, see `models/data/landmarker/NOTICE`).
pub const MODEL_ONNX: &[u8] = include_bytes!("../../data/landmarker/face_landmark.onnx");

/// The runnable landmark model.
pub(crate) struct FaceMesh {
    plan: Plan,
}

/// The landmark model's raw outputs: `landmarks` `[468 * 3]` (crop pixels), `face_flag`
/// (presence logit).
pub(crate) struct RawOutputs {
    pub landmarks: Vec<f32>,
    pub face_flag: f32,
}

/// 8-bit samples to the model's input values `q / 255` (float32).
pub(crate) fn to_input(q: &[u8]) -> Vec<f32> {
    q.iter().map(|&v| v as f32 / 255.0).collect()
}

impl FaceMesh {
    /// Loads and optimises the embedded model.
    pub fn new() -> Result<Self, DetectError> {
        Ok(FaceMesh {
            plan: Plan::new("face landmark model", MODEL_ONNX, [1, LM_SIZE, LM_SIZE, 3])?,
        })
    }

    /// Runs the network on an input tensor `[192 * 192 * 3]` (NHWC, values in [0, 1]).
    pub fn run(&self, input: Vec<f32>) -> Result<RawOutputs, DetectError> {
        let mut out = self.plan.run(input, &[NUM_LANDMARKS * 3, 1])?;
        let face_flag = out.pop().expect("two outputs")[0];
        let landmarks = out.pop().expect("two outputs");
        Ok(RawOutputs {
            landmarks,
            face_flag,
        })
    }

    /// The crop of `roi` as 8-bit samples (replicated border).
    pub fn sample(image: &ArrayView3<'_, f64>, roi: &Roi) -> Vec<u8> {
        sample(image, roi, LM_SIZE, Border::Replicate)
    }

    /// Landmarks `[468, 3]` in image pixels (OpenCV convention: integer values are pixel
    /// centres) and the presence probability: crop pixel `(x, y)` maps through
    /// [`Roi::image_point`], `z` scales by `L / 192`.
    pub fn project(raw: &RawOutputs, roi: &Roi) -> (Array2<f64>, f64) {
        let scale = roi.size / LM_SIZE as f64;
        let points = Array2::from_shape_fn((NUM_LANDMARKS, 3), |(i, c)| {
            let p = &raw.landmarks[3 * i..3 * i + 3];
            if c == 2 {
                p[2] as f64 * scale
            } else {
                roi.image_point(p[0] as f64, p[1] as f64, LM_SIZE)[c]
            }
        });
        (points, sigmoid_clipped(raw.face_flag as f64))
    }

    /// The whole landmark stage for one crop of a checked image.
    pub fn landmarks(
        &self,
        image: &ArrayView3<'_, f64>,
        roi: &Roi,
    ) -> Result<(Array2<f64>, f64), DetectError> {
        let raw = self.run(to_input(&Self::sample(image, roi)))?;
        Ok(Self::project(&raw, roi))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::testdata::{
        assert_close_model, assert_samples_match, expected, npy, photo, png_u8, reference_roi,
    };

    #[test]
    fn synthetic_pattern_reproduces_tracts_reference_outputs() {
        let mesh = FaceMesh::new().unwrap();
        let raw = mesh
            .run(crate::detect::testdata::pattern(LM_SIZE, 0.0, 1.0))
            .unwrap();
        assert_close_model(
            &raw.landmarks,
            &npy("synthetic_lm_expected_landmarks.npy"),
            "landmarks",
        );
        let flag = npy("synthetic_lm_expected_face_flag.npy");
        assert_close_model(&[raw.face_flag], &flag, "face flag");
        // Not a face: presence about 1.8e-5.
        let (_, presence) = FaceMesh::project(
            &raw,
            &Roi {
                cx: 0.0,
                cy: 0.0,
                size: 1.0,
                rotation: 0.0,
            },
        );
        assert!(presence < 1e-4, "{presence}");
    }

    #[test]
    fn photo_crops_reproduce_the_reference_pipeline() {
        let mesh = FaceMesh::new().unwrap();
        for name in ["camera", "grace_hopper"] {
            let img = photo(name);
            let roi = reference_roi(name);
            let want = png_u8(&format!("{name}_lm_input.png"));
            assert_samples_match(name, &FaceMesh::sample(&img.view(), &roi), &want);
            let raw = mesh.run(to_input(&want)).unwrap();
            let lms = npy(&format!("{name}_lm_expected_landmarks.npy"));
            let flag = npy(&format!("{name}_lm_expected_face_flag.npy"));
            assert_close_model(&raw.landmarks, &lms, "landmarks");
            assert_close_model(&[raw.face_flag], &flag, "face flag");
            // Projection of the reference outputs: the reference pipeline's distance to
            // MediaPipe's landmarks (whose file keeps 4 decimals) comes back.
            let (points, presence) = FaceMesh::project(
                &RawOutputs {
                    landmarks: lms,
                    face_flag: flag[0],
                },
                &roi,
            );
            let e = expected(name);
            let r = &e["reference_pipeline"];
            assert!((presence - r["face_presence"].as_f64().unwrap()).abs() < 1e-9);
            let mp = crate::fit::read_landmarks(crate::detect::testdata::path(&format!(
                "{name}_landmarks_px.txt"
            )))
            .unwrap();
            let d: Vec<f64> = (0..NUM_LANDMARKS)
                .map(|i| (points[[i, 0]] - mp[[i, 0]]).hypot(points[[i, 1]] - mp[[i, 1]]))
                .collect();
            let mean = d.iter().sum::<f64>() / d.len() as f64;
            let max = d.iter().fold(0f64, |a, &b| a.max(b));
            let dist = &r["landmark_px_distance_to_mediapipe"];
            assert!(
                (mean - dist["mean"].as_f64().unwrap()).abs() < 2e-4,
                "{name}: mean {mean}"
            );
            assert!(
                (max - dist["max"].as_f64().unwrap()).abs() < 2e-4,
                "{name}: max {max}"
            );
            // z: normalised z times the width, in pixels.
            let zn = e["expected_landmarks"]["landmarks_norm_xyz"][1][2]
                .as_f64()
                .unwrap();
            let w = img.shape()[1] as f64;
            assert!(
                (points[[1, 2]] - zn * w).abs() < 0.5,
                "{name}: z {} vs {}",
                points[[1, 2]],
                zn * w
            );
        }
    }
}
