//! Face detection and the 468 MediaPipe face-mesh landmarks in pure Rust: MediaPipe's
//! legacy static-image face-mesh pipeline (0.10.21) with its two networks converted to ONNX
//! and run by tract, embedded in the binary (Apache-2.0; `models/data/landmarker/`, whose
//! README gives provenance and the specification followed step by step).
//!
//! 1. [`Landmarker::detect`]: the image is letterboxed to a 128 x 128 tensor, the short-range
//!    BlazeFace detector (Bazarevsky et al. 2019) scores 896 anchors, the boxes above 0.5 are
//!    decoded and merged by weighted non-maximum suppression (IoU > 0.3) and mapped back to
//!    the image: a box and six keypoints per face.
//! 2. [`Landmarker::landmarks`]: a square 1.5 times the box's longer side, centred on the box
//!    and rotated by the eye-to-eye angle, is sampled into a 192 x 192 crop; the face-mesh
//!    model (Kartynnik et al. 2019) gives 468 points and a face-presence probability, mapped
//!    back through the same rotation.
//!
//! Samples are taken bilinearly from the image read as 8 bits and rounded to 8 bits, as
//! MediaPipe's CPU path does; on the kit's two photos the landmarks agree with MediaPipe's
//! within a tenth of a pixel (tests/detect.rs).
//!
//! Coordinates: pixels of the input image, origin at its top-left corner, pixel centres at
//! +0.5 (the landmark-file convention of [`crate::fit::read_landmarks`]). Landmark `i` is
//! vertex `i` of the shipped face model ([`crate::face`]). `z` is MediaPipe's relative depth
//! (smaller is nearer the camera, origin about the centre of the head) in the same pixel
//! scale as x and y.
//!
//! ```no_run
//! let img: ndarray::Array3<f64> = render_ops::io::read_image("photo.jpg").unwrap();
//! let faces = models::detect::detect_landmarks(img.view()).unwrap();
//! let nose_tip = faces[0].points.row(1);
//! println!("score {:.3}, nose tip at ({:.1}, {:.1})", faces[0].detection.score, nose_tip[0], nose_tip[1]);
//! ```

mod anchors;
mod blazeface;
mod crop;
mod decode;
mod face_mesh;
mod onnx;
#[cfg(test)]
mod testdata;

use std::sync::OnceLock;

use ndarray::{Array2, ArrayView3};
use thiserror::Error;

use blazeface::BlazeFace;
use crop::Roi;
use decode::{iou, RawDetection};
use face_mesh::FaceMesh;

pub use face_mesh::NUM_LANDMARKS;

/// The smallest accepted image side (pixels): a face in fewer pixels carries no landmark
/// detail.
pub const MIN_IMAGE_SIDE: usize = 16;
/// Landmarks are returned when the face-presence probability exceeds this (MediaPipe's
/// `min_tracking_confidence` default).
pub const MIN_PRESENCE: f64 = 0.5;
/// Two landmark crops whose axis-aligned IoU exceeds this are the same face: the later one
/// replaces the earlier (MediaPipe's `AssociationNormRectCalculator`).
pub const CROP_ASSOCIATION_IOU: f64 = 0.5;

/// Errors of detection, each one line.
#[derive(Debug, Error)]
pub enum DetectError {
    /// The detector found no face (or the landmark model rejected every crop).
    #[error("no face found")]
    NoFace,
    /// An image that cannot be used (shape, NaN, too small), or a detection that does not
    /// belong to one (non-finite coordinates); the message says which.
    #[error("{0}")]
    BadImage(String),
    /// A model failed to load or run.
    #[error("face model: {0}")]
    Model(String),
}

/// One detected face, in input-image pixel coordinates with pixel centres at +0.5
/// (landmark-file convention).
#[derive(Clone, Debug, PartialEq)]
pub struct FaceDetection {
    /// Detector confidence in (0.5, 1].
    pub score: f64,
    /// `xmin, ymin, xmax, ymax`.
    pub bbox: [f64; 4],
    /// Right eye, left eye, nose tip, mouth centre, right ear tragion, left ear tragion (the
    /// subject's right and left: keypoint 0 is normally on the image's left).
    pub keypoints: [[f64; 2]; 6],
}

impl FaceDetection {
    /// Area of the box (square pixels).
    pub fn area(&self) -> f64 {
        (self.bbox[2] - self.bbox[0]) * (self.bbox[3] - self.bbox[1])
    }
}

/// 468 MediaPipe face-mesh landmarks of one face.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceLandmarks {
    /// The detection whose crop gave the landmarks.
    pub detection: FaceDetection,
    /// `[468, 3]`: x, y in input-image pixels (centre +0.5), z relative depth in the same
    /// pixel scale.
    pub points: Array2<f64>,
    /// Face-presence probability of the crop (the landmarks are meaningful above 0.5).
    pub presence: f64,
}

/// The two runnable models (detector and face mesh), built from the embedded ONNX files.
/// Immutable: share one between threads.
pub struct Landmarker {
    detector: BlazeFace,
    mesh: FaceMesh,
}

impl std::fmt::Debug for Landmarker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Landmarker")
    }
}

/// Checks an `[H, W, 3]` image: three channels, both sides at least [`MIN_IMAGE_SIDE`],
/// every value finite (values outside [0, 1] are clamped when sampled).
fn check_image(image: &ArrayView3<'_, f64>) -> Result<(), DetectError> {
    let &[h, w, c] = image.shape() else {
        unreachable!("a 3-D view")
    };
    if c != 3 {
        return Err(DetectError::BadImage(format!(
            "image has {c} channel(s) ([{h}, {w}, {c}]); expected [H, W, 3] RGB (replicate a gray channel, drop alpha)"
        )));
    }
    if h < MIN_IMAGE_SIDE || w < MIN_IMAGE_SIDE {
        return Err(DetectError::BadImage(format!(
            "image of {w}x{h} pixels is too small; face detection needs at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE}"
        )));
    }
    if let Some((i, v)) = image.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        let (r, col) = (i / (w * 3), i / 3 % w);
        return Err(DetectError::BadImage(format!(
            "image value {v} at row {r}, column {col} is not finite"
        )));
    }
    Ok(())
}

/// Normalised image coordinates (OpenCV convention) to pixels with centres at +0.5.
fn to_pixels(d: &RawDetection, w: usize, h: usize) -> FaceDetection {
    let (w, h) = (w as f64, h as f64);
    FaceDetection {
        score: d.score,
        bbox: [
            d.bbox[0] * w + 0.5,
            d.bbox[1] * h + 0.5,
            d.bbox[2] * w + 0.5,
            d.bbox[3] * h + 0.5,
        ],
        keypoints: d.keypoints.map(|[x, y]| [x * w + 0.5, y * h + 0.5]),
    }
}

/// The landmark crop of a detection (pixels with centres at +0.5).
fn crop_of(det: &FaceDetection) -> Result<Roi, DetectError> {
    let finite = det.score.is_finite()
        && det
            .bbox
            .iter()
            .chain(det.keypoints.iter().flatten())
            .all(|v| v.is_finite());
    if !finite {
        return Err(DetectError::BadImage(format!(
            "detection {det:?} has a non-finite value"
        )));
    }
    let b = det.bbox.map(|v| v - 0.5);
    let k = det.keypoints.map(|[x, y]| [x - 0.5, y - 0.5]);
    Ok(Roi::from_detection(&b, k[0], k[1]))
}

impl Landmarker {
    /// Builds both models from the embedded ONNX files (about 0.1 s).
    pub fn new() -> Result<Self, DetectError> {
        Ok(Landmarker {
            detector: BlazeFace::new()?,
            mesh: FaceMesh::new()?,
        })
    }

    /// Faces in an `[H, W, 3]` RGB image with values in [0, 1] (as
    /// [`render_ops::io::read_image`] gives them: 8-bit / 255), sorted by score, descending;
    /// empty when there is none.
    pub fn detect(&self, image: ArrayView3<'_, f64>) -> Result<Vec<FaceDetection>, DetectError> {
        check_image(&image)?;
        let (h, w) = (image.shape()[0], image.shape()[1]);
        Ok(self
            .detector
            .detect(&image)?
            .iter()
            .map(|d| to_pixels(d, w, h))
            .collect())
    }

    /// The 468 landmarks of the face of `det` (a detection of this image), whatever the
    /// face presence (check [`FaceLandmarks::presence`]).
    pub fn landmarks(
        &self,
        image: ArrayView3<'_, f64>,
        det: &FaceDetection,
    ) -> Result<FaceLandmarks, DetectError> {
        check_image(&image)?;
        self.landmarks_checked(&image, det, &crop_of(det)?)
    }

    fn landmarks_checked(
        &self,
        image: &ArrayView3<'_, f64>,
        det: &FaceDetection,
        roi: &Roi,
    ) -> Result<FaceLandmarks, DetectError> {
        let (mut points, presence) = self.mesh.landmarks(image, roi)?;
        points.column_mut(0).mapv_inplace(|x| x + 0.5);
        points.column_mut(1).mapv_inplace(|y| y + 0.5);
        Ok(FaceLandmarks {
            detection: det.clone(),
            points,
            presence,
        })
    }

    /// Every face with presence above 0.5, largest box first; [`DetectError::NoFace`] when
    /// there is none (never an empty list). Crops overlapping an earlier one by IoU > 0.5
    /// replace it, as in MediaPipe with several faces.
    pub fn detect_landmarks(
        &self,
        image: ArrayView3<'_, f64>,
    ) -> Result<Vec<FaceLandmarks>, DetectError> {
        let dets = self.detect(image)?;
        let mut crops: Vec<(FaceDetection, Roi)> = Vec::new();
        for d in dets {
            let roi = crop_of(&d)?;
            let rect = |r: &Roi| {
                let half = r.size / 2.0;
                [r.cx - half, r.cy - half, r.cx + half, r.cy + half]
            };
            crops.retain(|(_, prev)| iou(&rect(prev), &rect(&roi)) <= CROP_ASSOCIATION_IOU);
            crops.push((d, roi));
        }
        let mut faces = Vec::new();
        for (d, roi) in &crops {
            let f = self.landmarks_checked(&image, d, roi)?;
            if f.presence > MIN_PRESENCE {
                faces.push(f);
            }
        }
        if faces.is_empty() {
            return Err(DetectError::NoFace);
        }
        faces.sort_by(|a, b| b.detection.area().total_cmp(&a.detection.area()));
        Ok(faces)
    }
}

/// [`Landmarker::detect_landmarks`] with a process-wide [`Landmarker`], built on first use;
/// [`DetectError::NoFace`] when no face is found.
pub fn detect_landmarks(image: ArrayView3<'_, f64>) -> Result<Vec<FaceLandmarks>, DetectError> {
    static CACHE: OnceLock<Result<Landmarker, String>> = OnceLock::new();
    let built = CACHE.get_or_init(|| {
        Landmarker::new().map_err(|e| match e {
            DetectError::Model(m) => m,
            other => other.to_string(),
        })
    });
    match built {
        Ok(l) => l.detect_landmarks(image),
        Err(m) => Err(DetectError::Model(m.clone())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    fn bad(img: &Array3<f64>) -> String {
        match check_image(&img.view()) {
            Err(DetectError::BadImage(m)) => m,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn bad_images_are_named() {
        assert!(check_image(&Array3::zeros((16, 20, 3)).view()).is_ok());
        assert!(bad(&Array3::zeros((20, 20, 1))).contains("1 channel(s)"));
        assert!(bad(&Array3::zeros((20, 20, 4))).contains("4 channel(s)"));
        assert!(bad(&Array3::zeros((15, 40, 3))).contains("40x15 pixels is too small"));
        assert!(bad(&Array3::zeros((0, 0, 3))).contains("too small"));
        let mut img = Array3::zeros((20, 30, 3));
        img[[7, 11, 2]] = f64::NAN;
        assert!(bad(&img).contains("row 7, column 11"), "{}", bad(&img));
        img[[7, 11, 2]] = 0.0;
        img[[0, 29, 0]] = f64::INFINITY;
        assert!(bad(&img).contains("row 0, column 29"));
        // Out-of-range but finite values are clamped, not refused.
        img[[0, 29, 0]] = 7.0;
        assert!(check_image(&img.view()).is_ok());
    }

    #[test]
    fn crop_of_a_detection_matches_the_reference_crop() {
        for name in ["camera", "grace_hopper"] {
            let img = testdata::photo(name);
            let (h, w) = (img.shape()[0], img.shape()[1]);
            let det = to_pixels(&testdata::reference_detection(name), w, h);
            let roi = crop_of(&det).unwrap();
            let r = testdata::reference_roi(name);
            assert!((roi.cx - r.cx).abs() < 1e-9, "{name}: {roi:?} vs {r:?}");
            assert!((roi.cy - r.cy).abs() < 1e-9, "{name}: {roi:?} vs {r:?}");
            assert!((roi.size - r.size).abs() < 1e-9, "{name}: {roi:?} vs {r:?}");
            assert!(
                (roi.rotation - r.rotation).abs() < 1e-12,
                "{name}: {roi:?} vs {r:?}"
            );
        }
        let mut det = to_pixels(&testdata::reference_detection("camera"), 512, 512);
        det.keypoints[1][0] = f64::NAN;
        assert!(matches!(crop_of(&det), Err(DetectError::BadImage(m)) if m.contains("non-finite")));
    }
}
