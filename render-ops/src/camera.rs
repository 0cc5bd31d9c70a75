//! Non-differentiable camera setup in f64 (OpenGL conventions, docs/CONVENTIONS.md).
//!
//! World and view space are right-handed with y up; the camera looks down -z in view space.
//! `clip = P * V * [x, y, z, 1]`, `ndc = clip.xyz / clip.w`, visible where `-1 <= ndc <= 1`.
//! Pixel coordinates (continuous, origin at the top-left image corner, pixel centres at +0.5):
//! `u = (ndc.x + 1) W / 2`, `v = (1 - ndc.y) H / 2` ([`ndc_to_pixel`]).
//!
//! Matrices are [`glam::DMat4`] (column-major storage); the `*_rows` accessors and
//! [`Camera::view_proj`] return plain row-major `[[f64; 4]; 4]` (`m[row][col]`), the layout the
//! differentiable vertex stage copies into a tensor. Differentiable camera parametrisations
//! (rotations, intrinsics as tape variables) live elsewhere and must agree with these matrices.

use glam::{DMat4, DVec3, DVec4};
use thiserror::Error;

/// An invalid camera parameter; messages name the parameter, its value and what is allowed.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CameraError {
    /// NaN or infinite input.
    #[error("camera: {param} = {value} is not finite")]
    NonFinite {
        /// Parameter name.
        param: &'static str,
        /// The value (the first non-finite component of a vector).
        value: f64,
    },
    /// Perspective near plane at or behind the eye.
    #[error("camera: near = {near} must be > 0 for a perspective projection")]
    NearNotPositive {
        /// The near distance.
        near: f64,
    },
    /// Far plane not beyond the near plane.
    #[error("camera: far = {far} must be greater than near = {near}")]
    FarNotBeyondNear {
        /// The near distance.
        near: f64,
        /// The far distance.
        far: f64,
    },
    /// Vertical field of view outside (0, pi).
    #[error("camera: fov_y = {fov_y_rad} rad ({} deg) must lie strictly between 0 and pi (180 deg)", .fov_y_rad.to_degrees())]
    FovOutOfRange {
        /// The field of view in radians.
        fov_y_rad: f64,
    },
    /// Aspect ratio not positive.
    #[error("camera: aspect = {aspect} must be > 0")]
    AspectNotPositive {
        /// The aspect ratio (width / height).
        aspect: f64,
    },
    /// `eye == at`: no view direction.
    #[error("camera: eye = {eye:?} equals at: no view direction")]
    EyeEqualsAt {
        /// The eye position.
        eye: [f64; 3],
    },
    /// `up` is zero or parallel to the view direction.
    #[error("camera: up = {up:?} is zero or parallel to the view direction {direction:?}")]
    UpParallel {
        /// The up vector.
        up: [f64; 3],
        /// The unit view direction `(at - eye) / |at - eye|`.
        direction: [f64; 3],
    },
    /// An empty orthographic extent (`left >= right`, ...).
    #[error("camera: {lo_name} = {lo} must be less than {hi_name} = {hi}")]
    EmptyRange {
        /// Lower bound's name ("left", "bottom", "near").
        lo_name: &'static str,
        /// Lower bound.
        lo: f64,
        /// Upper bound's name.
        hi_name: &'static str,
        /// Upper bound.
        hi: f64,
    },
    /// Weak-perspective scale not positive.
    #[error("camera: scale = {scale} must be > 0")]
    ScaleNotPositive {
        /// The scale.
        scale: f64,
    },
}

fn finite(param: &'static str, values: &[f64]) -> Result<(), CameraError> {
    match values.iter().find(|x| !x.is_finite()) {
        Some(&value) => Err(CameraError::NonFinite { param, value }),
        None => Ok(()),
    }
}

/// Row-major `[[f64; 4]; 4]` of a glam matrix.
pub fn to_rows(m: &DMat4) -> [[f64; 4]; 4] {
    m.transpose().to_cols_array_2d()
}

/// glam matrix from row-major `[[f64; 4]; 4]`.
pub fn from_rows(rows: &[[f64; 4]; 4]) -> DMat4 {
    DMat4::from_cols_array_2d(rows).transpose()
}

/// The right-handed view matrix of `gluLookAt(eye, at, up)`: with `f = (at - eye) / |at - eye|`,
/// `s = (f x up) / |f x up|`, `u = s x f`,
/// ```text
/// V = | s.x   s.y   s.z  -s.eye |
///     | u.x   u.y   u.z  -u.eye |
///     |-f.x  -f.y  -f.z   f.eye |
///     |  0     0     0      1   |
/// ```
/// so the camera sits at the origin of view space looking down -z, with `up` projecting onto +y.
/// Errors: non-finite input, `eye == at`, `up` zero or parallel to `at - eye`.
pub fn look_at(eye: [f64; 3], at: [f64; 3], up: [f64; 3]) -> Result<DMat4, CameraError> {
    finite("eye", &eye)?;
    finite("at", &at)?;
    finite("up", &up)?;
    let (e, a, up_v) = (DVec3::from(eye), DVec3::from(at), DVec3::from(up));
    let d = a - e;
    let len = d.length();
    if len == 0.0 {
        return Err(CameraError::EyeEqualsAt { eye });
    }
    let f = d / len;
    let s = f.cross(up_v);
    let up_len = up_v.length();
    // |f x up| = |up| sin(angle): parallel when the sine is below ~1e-12.
    if up_len == 0.0 || s.length() <= 1e-12 * up_len {
        return Err(CameraError::UpParallel {
            up,
            direction: f.to_array(),
        });
    }
    let s = s.normalize();
    let u = s.cross(f);
    Ok(from_rows(&[
        [s.x, s.y, s.z, -s.dot(e)],
        [u.x, u.y, u.z, -u.dot(e)],
        [-f.x, -f.y, -f.z, f.dot(e)],
        [0.0, 0.0, 0.0, 1.0],
    ]))
}

/// The OpenGL perspective matrix of `gluPerspective(fovy, aspect, zNear, zFar)` (with `fovy` in
/// radians here): with `c = cot(fov_y / 2)`,
/// ```text
/// P = | c/aspect  0        0                       0               |
///     |   0       c        0                       0               |
///     |   0       0   (far+near)/(near-far)   2 far near/(near-far) |
///     |   0       0       -1                       0               |
/// ```
/// so `clip.w` is the view depth `d = -z_view` and `ndc.z` runs from -1 at `near` to +1 at
/// `far`. Errors: non-finite input, `fov_y` outside (0, pi), `aspect <= 0`, `near <= 0`,
/// `far <= near`.
pub fn perspective(fov_y_rad: f64, aspect: f64, near: f64, far: f64) -> Result<DMat4, CameraError> {
    finite("fov_y", &[fov_y_rad])?;
    finite("aspect", &[aspect])?;
    finite("near", &[near])?;
    finite("far", &[far])?;
    if !(fov_y_rad > 0.0 && fov_y_rad < std::f64::consts::PI) {
        return Err(CameraError::FovOutOfRange { fov_y_rad });
    }
    if aspect <= 0.0 {
        return Err(CameraError::AspectNotPositive { aspect });
    }
    if near <= 0.0 {
        return Err(CameraError::NearNotPositive { near });
    }
    if far <= near {
        return Err(CameraError::FarNotBeyondNear { near, far });
    }
    let c = 1.0 / (fov_y_rad / 2.0).tan();
    Ok(from_rows(&[
        [c / aspect, 0.0, 0.0, 0.0],
        [0.0, c, 0.0, 0.0],
        [
            0.0,
            0.0,
            (far + near) / (near - far),
            2.0 * far * near / (near - far),
        ],
        [0.0, 0.0, -1.0, 0.0],
    ]))
}

/// The OpenGL orthographic matrix of `glOrtho(left, right, bottom, top, nearVal, farVal)`:
/// ```text
/// P = | 2/(r-l)    0        0       -(r+l)/(r-l) |
///     |   0     2/(t-b)     0       -(t+b)/(t-b) |
///     |   0        0    -2/(f-n)    -(f+n)/(f-n) |
///     |   0        0        0             1      |
/// ```
/// (`near`/`far` are distances along -z and may be negative, as in glOrtho; `clip.w = 1`).
/// Errors: non-finite input, `left >= right`, `bottom >= top`, `near >= far`.
pub fn orthographic(
    left: f64,
    right: f64,
    bottom: f64,
    top: f64,
    near: f64,
    far: f64,
) -> Result<DMat4, CameraError> {
    for (name, v) in [
        ("left", left),
        ("right", right),
        ("bottom", bottom),
        ("top", top),
        ("near", near),
        ("far", far),
    ] {
        finite(name, &[v])?;
    }
    for (lo_name, lo, hi_name, hi) in [
        ("left", left, "right", right),
        ("bottom", bottom, "top", top),
        ("near", near, "far", far),
    ] {
        if lo >= hi {
            return Err(CameraError::EmptyRange {
                lo_name,
                lo,
                hi_name,
                hi,
            });
        }
    }
    let (rl, tb, fmn) = (right - left, top - bottom, far - near);
    Ok(from_rows(&[
        [2.0 / rl, 0.0, 0.0, -(right + left) / rl],
        [0.0, 2.0 / tb, 0.0, -(top + bottom) / tb],
        [0.0, 0.0, -2.0 / fmn, -(far + near) / fmn],
        [0.0, 0.0, 0.0, 1.0],
    ]))
}

/// Weak perspective (scaled orthographic, as in 3DMM face fitting): `ndc.x = scale x_view + tx`,
/// `ndc.y = scale y_view + ty`, depth as in [`orthographic`] (linear in `-z_view` from -1 at
/// `near` to +1 at `far`):
/// ```text
/// P = | s  0      0           tx       |
///     | 0  s      0           ty       |
///     | 0  0  -2/(f-n)   -(f+n)/(f-n)  |
///     | 0  0      0            1       |
/// ```
/// This is `glOrtho` with `left = (-1 - tx)/s`, `right = (1 - tx)/s` (likewise bottom/top).
/// Errors: non-finite input, `scale <= 0`, `near >= far`.
pub fn weak_perspective(
    scale: f64,
    tx: f64,
    ty: f64,
    near: f64,
    far: f64,
) -> Result<DMat4, CameraError> {
    for (name, v) in [
        ("scale", scale),
        ("tx", tx),
        ("ty", ty),
        ("near", near),
        ("far", far),
    ] {
        finite(name, &[v])?;
    }
    if scale <= 0.0 {
        return Err(CameraError::ScaleNotPositive { scale });
    }
    if near >= far {
        return Err(CameraError::EmptyRange {
            lo_name: "near",
            lo: near,
            hi_name: "far",
            hi: far,
        });
    }
    let fmn = far - near;
    Ok(from_rows(&[
        [scale, 0.0, 0.0, tx],
        [0.0, scale, 0.0, ty],
        [0.0, 0.0, -2.0 / fmn, -(far + near) / fmn],
        [0.0, 0.0, 0.0, 1.0],
    ]))
}

/// A projection and its parameters (angles in radians).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Projection {
    /// [`perspective`].
    Perspective {
        /// Vertical field of view, radians, in (0, pi).
        fov_y: f64,
        /// Width / height.
        aspect: f64,
        /// Near plane distance (> 0).
        near: f64,
        /// Far plane distance (> near).
        far: f64,
    },
    /// [`orthographic`].
    Orthographic {
        /// Left plane.
        left: f64,
        /// Right plane.
        right: f64,
        /// Bottom plane.
        bottom: f64,
        /// Top plane.
        top: f64,
        /// Near plane distance.
        near: f64,
        /// Far plane distance.
        far: f64,
    },
    /// [`weak_perspective`].
    WeakPerspective {
        /// Scale from view units to NDC.
        scale: f64,
        /// NDC x offset.
        tx: f64,
        /// NDC y offset.
        ty: f64,
        /// Near plane distance.
        near: f64,
        /// Far plane distance.
        far: f64,
    },
}

impl Projection {
    /// The 4x4 matrix (validating the parameters).
    pub fn matrix(&self) -> Result<DMat4, CameraError> {
        match *self {
            Projection::Perspective {
                fov_y,
                aspect,
                near,
                far,
            } => perspective(fov_y, aspect, near, far),
            Projection::Orthographic {
                left,
                right,
                bottom,
                top,
                near,
                far,
            } => orthographic(left, right, bottom, top, near, far),
            Projection::WeakPerspective {
                scale,
                tx,
                ty,
                near,
                far,
            } => weak_perspective(scale, tx, ty, near, far),
        }
    }

    /// Near plane distance.
    pub fn near(&self) -> f64 {
        match *self {
            Projection::Perspective { near, .. }
            | Projection::Orthographic { near, .. }
            | Projection::WeakPerspective { near, .. } => near,
        }
    }

    /// Far plane distance.
    pub fn far(&self) -> f64 {
        match *self {
            Projection::Perspective { far, .. }
            | Projection::Orthographic { far, .. }
            | Projection::WeakPerspective { far, .. } => far,
        }
    }

    /// Whether `clip.w` varies with depth (perspective division matters).
    pub fn is_perspective(&self) -> bool {
        matches!(self, Projection::Perspective { .. })
    }
}

/// The OpenCV form of a perspective camera: `p_cam = R p + t` (x right, y down, z forward),
/// `u = K[0] . p_cam / z`, `v = K[1] . p_cam / z` in the pixel coordinates of [`ndc_to_pixel`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpenCvCamera {
    /// Intrinsics `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.
    pub k: [[f64; 3]; 3],
    /// Rotation, row-major.
    pub r: [[f64; 3]; 3],
    /// Translation.
    pub t: [f64; 3],
}

/// A validated view + projection pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    view: DMat4,
    projection: Projection,
    proj: DMat4,
    view_proj: DMat4,
}

impl Camera {
    /// Combines a view matrix (must be finite) with a projection (validated).
    pub fn new(view: DMat4, projection: Projection) -> Result<Self, CameraError> {
        finite("view", &view.to_cols_array())?;
        let proj = projection.matrix()?;
        Ok(Camera {
            view,
            projection,
            proj,
            view_proj: proj * view,
        })
    }

    /// [`look_at`] + a projection.
    pub fn look_at(
        eye: [f64; 3],
        at: [f64; 3],
        up: [f64; 3],
        projection: Projection,
    ) -> Result<Self, CameraError> {
        Self::new(look_at(eye, at, up)?, projection)
    }

    /// [`look_at`] + [`perspective`]: the camera of a scene JSON (with `fov_y` in radians).
    pub fn perspective_look_at(
        eye: [f64; 3],
        at: [f64; 3],
        up: [f64; 3],
        fov_y_rad: f64,
        aspect: f64,
        near: f64,
        far: f64,
    ) -> Result<Self, CameraError> {
        Self::look_at(
            eye,
            at,
            up,
            Projection::Perspective {
                fov_y: fov_y_rad,
                aspect,
                near,
                far,
            },
        )
    }

    /// The view matrix `V`.
    pub fn view(&self) -> DMat4 {
        self.view
    }

    /// The projection matrix `P`.
    pub fn proj(&self) -> DMat4 {
        self.proj
    }

    /// The projection parameters.
    pub fn projection(&self) -> &Projection {
        &self.projection
    }

    /// `P * V` as a glam matrix.
    pub fn view_proj_mat(&self) -> DMat4 {
        self.view_proj
    }

    /// `P * V`, row-major (`m[row][col]`): `clip = m * [x, y, z, 1]`.
    pub fn view_proj(&self) -> [[f64; 4]; 4] {
        to_rows(&self.view_proj)
    }

    /// `V`, row-major.
    pub fn view_rows(&self) -> [[f64; 4]; 4] {
        to_rows(&self.view)
    }

    /// `P`, row-major.
    pub fn proj_rows(&self) -> [[f64; 4]; 4] {
        to_rows(&self.proj)
    }

    /// The eye position in world space (the inverse view transform of the origin).
    pub fn eye(&self) -> [f64; 3] {
        self.view.inverse().transform_point3(DVec3::ZERO).to_array()
    }

    /// Clip coordinates `P V [p, 1]`.
    pub fn project(&self, point: [f64; 3]) -> [f64; 4] {
        (self.view_proj * DVec4::new(point[0], point[1], point[2], 1.0)).to_array()
    }

    /// Normalised device coordinates `clip.xyz / clip.w`, or `None` when `clip.w <= 0` (at or
    /// behind the eye of a perspective camera).
    pub fn project_ndc(&self, point: [f64; 3]) -> Option<[f64; 3]> {
        let c = self.project(point);
        (c[3] > 0.0).then(|| [c[0] / c[3], c[1] / c[3], c[2] / c[3]])
    }

    /// Continuous pixel coordinates `[u, v]` of a point in a `width x height` image (see
    /// [`ndc_to_pixel`]), or `None` behind the eye.
    pub fn project_pixel(&self, point: [f64; 3], width: u32, height: u32) -> Option<[f64; 2]> {
        self.project_ndc(point)
            .map(|n| ndc_to_pixel([n[0], n[1]], width, height))
    }

    /// View depth `d = -z_view` (distance along the viewing direction).
    pub fn view_depth(&self, point: [f64; 3]) -> f64 {
        -self.view.transform_point3(DVec3::from(point)).z
    }

    /// Normalised depth `z01 = (d - near) / (far - near)` used by soft blending.
    pub fn z01(&self, point: [f64; 3]) -> f64 {
        let (n, f) = (self.projection.near(), self.projection.far());
        (self.view_depth(point) - n) / (f - n)
    }

    /// The equivalent OpenCV camera for a `width x height` image (perspective only; `None`
    /// otherwise): `R = diag(1,-1,-1) V[:3,:3]`, `t = diag(1,-1,-1) V[:3,3]`,
    /// `fx = P[0][0] W / 2`, `fy = P[1][1] H / 2`, `cx = W / 2`, `cy = H / 2`.
    pub fn opencv(&self, width: u32, height: u32) -> Option<OpenCvCamera> {
        if !self.projection.is_perspective() {
            return None;
        }
        let (v, p) = (self.view_rows(), self.proj_rows());
        let (w, h) = (width as f64, height as f64);
        let sign = [1.0, -1.0, -1.0];
        Some(OpenCvCamera {
            k: [
                [p[0][0] * w / 2.0, 0.0, w / 2.0],
                [0.0, p[1][1] * h / 2.0, h / 2.0],
                [0.0, 0.0, 1.0],
            ],
            r: std::array::from_fn(|i| std::array::from_fn(|j| sign[i] * v[i][j])),
            t: std::array::from_fn(|i| sign[i] * v[i][3]),
        })
    }
}

/// NDC `(x, y)` to continuous pixel coordinates `[u, v]`: `u = (x + 1) W / 2`,
/// `v = (1 - y) H / 2` (origin at the top-left image corner; pixel `(row r, col c)` has its centre
/// at `(c + 0.5, r + 0.5)`).
pub fn ndc_to_pixel(ndc: [f64; 2], width: u32, height: u32) -> [f64; 2] {
    [
        (ndc[0] + 1.0) * (width as f64 / 2.0),
        (1.0 - ndc[1]) * (height as f64 / 2.0),
    ]
}

/// Inverse of [`ndc_to_pixel`].
pub fn pixel_to_ndc(pixel: [f64; 2], width: u32, height: u32) -> [f64; 2] {
    [
        2.0 * pixel[0] / width as f64 - 1.0,
        1.0 - 2.0 * pixel[1] / height as f64,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    #[test]
    fn look_at_matches_glam_and_maps_eye_and_target() {
        let (eye, at, up) = ([1.0, 2.0, 3.0], [0.5, -1.0, 0.0], [0.0, 1.0, 0.0]);
        let v = look_at(eye, at, up).unwrap();
        let g = DMat4::look_at_rh(eye.into(), at.into(), up.into());
        assert!(close(&v.to_cols_array(), &g.to_cols_array(), 1e-14));
        assert!(close(
            &v.transform_point3(eye.into()).to_array(),
            &[0.0; 3],
            1e-14
        ));
        let d = ((0.5f64).powi(2) + 9.0 + 9.0).sqrt();
        assert!(close(
            &v.transform_point3(at.into()).to_array(),
            &[0.0, 0.0, -d],
            1e-14
        ));
        let cam = Camera::look_at(
            eye,
            at,
            up,
            Projection::Orthographic {
                left: -1.0,
                right: 1.0,
                bottom: -1.0,
                top: 1.0,
                near: 0.1,
                far: 10.0,
            },
        )
        .unwrap();
        assert!(close(&cam.eye(), &eye, 1e-14));
        assert!((cam.view_depth(at) - d).abs() < 1e-14);
    }

    #[test]
    fn perspective_matches_glam_and_maps_near_far() {
        let p = perspective(0.8, 1.5, 0.5, 20.0).unwrap();
        let g = DMat4::perspective_rh_gl(0.8, 1.5, 0.5, 20.0);
        assert!(close(&p.to_cols_array(), &g.to_cols_array(), 1e-14));
        let cam = Camera::new(
            DMat4::IDENTITY,
            Projection::Perspective {
                fov_y: 0.8,
                aspect: 1.5,
                near: 0.5,
                far: 20.0,
            },
        )
        .unwrap();
        assert!((cam.project_ndc([0.0, 0.0, -0.5]).unwrap()[2] + 1.0).abs() < 1e-14);
        assert!((cam.project_ndc([0.0, 0.0, -20.0]).unwrap()[2] - 1.0).abs() < 1e-12);
        assert!((cam.z01([0.0, 0.0, -0.5])).abs() < 1e-15);
        assert!((cam.z01([0.0, 0.0, -20.0]) - 1.0).abs() < 1e-15);
        // The top of the frustum at depth 2 maps to ndc.y = 1, i.e. pixel row 0.
        let y = 2.0 * (0.4f64).tan();
        let n = cam.project_ndc([0.0, y, -2.0]).unwrap();
        assert!((n[1] - 1.0).abs() < 1e-14);
        assert!(close(
            &cam.project_pixel([0.0, y, -2.0], 30, 20).unwrap(),
            &[15.0, 0.0],
            1e-12
        ));
        assert_eq!(cam.project_ndc([0.0, 0.0, 1.0]), None);
        assert_eq!(cam.view_proj()[3], [0.0, 0.0, -1.0, 0.0]);
    }

    #[test]
    fn orthographic_and_weak_perspective() {
        let o = orthographic(-2.0, 4.0, -1.0, 3.0, 0.5, 10.0).unwrap();
        let g = DMat4::orthographic_rh_gl(-2.0, 4.0, -1.0, 3.0, 0.5, 10.0);
        assert!(close(&o.to_cols_array(), &g.to_cols_array(), 1e-15));
        let (s, tx, ty) = (0.25, 0.1, -0.3);
        let w = weak_perspective(s, tx, ty, 0.5, 10.0).unwrap();
        let equiv = orthographic(
            (-1.0 - tx) / s,
            (1.0 - tx) / s,
            (-1.0 - ty) / s,
            (1.0 - ty) / s,
            0.5,
            10.0,
        )
        .unwrap();
        assert!(close(&w.to_cols_array(), &equiv.to_cols_array(), 1e-14));
        let cam = Camera::new(
            DMat4::IDENTITY,
            Projection::WeakPerspective {
                scale: s,
                tx,
                ty,
                near: 0.5,
                far: 10.0,
            },
        )
        .unwrap();
        let c = cam.project([2.0, 4.0, -3.0]);
        assert!(close(
            &c,
            &[0.5 + tx, 1.0 + ty, 2.0 * 2.5 / 9.5 - 1.0, 1.0],
            1e-14
        ));
        assert!(cam.opencv(10, 10).is_none());
    }

    #[test]
    fn rows_are_row_major() {
        let m = from_rows(&[
            [1.0, 2.0, 3.0, 4.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]);
        assert_eq!(m.transform_point3(DVec3::ZERO).x, 4.0);
        assert_eq!(to_rows(&m)[0], [1.0, 2.0, 3.0, 4.0]);
        assert_eq!(
            pixel_to_ndc(ndc_to_pixel([0.25, -0.5], 64, 32), 64, 32),
            [0.25, -0.5]
        );
        // Pixel (row 0, col 0)'s centre.
        assert_eq!(
            ndc_to_pixel([2.0 * 0.5 / 4.0 - 1.0, 1.0 - 2.0 * 0.5 / 2.0], 4, 2),
            [0.5, 0.5]
        );
    }

    #[test]
    fn invalid_parameters_are_errors() {
        use CameraError::*;
        let pi = std::f64::consts::PI;
        assert_eq!(
            perspective(1.0, 1.0, 0.0, 10.0),
            Err(NearNotPositive { near: 0.0 })
        );
        assert_eq!(
            perspective(1.0, 1.0, -1.0, 10.0),
            Err(NearNotPositive { near: -1.0 })
        );
        assert_eq!(
            perspective(1.0, 1.0, 1.0, 1.0),
            Err(FarNotBeyondNear {
                near: 1.0,
                far: 1.0
            })
        );
        assert!(matches!(
            perspective(0.0, 1.0, 1.0, 2.0),
            Err(FovOutOfRange { .. })
        ));
        assert!(matches!(
            perspective(pi, 1.0, 1.0, 2.0),
            Err(FovOutOfRange { .. })
        ));
        assert!(matches!(
            perspective(1.0, 0.0, 1.0, 2.0),
            Err(AspectNotPositive { .. })
        ));
        let e = perspective(f64::NAN, 1.0, 1.0, 2.0).unwrap_err();
        assert!(matches!(e, NonFinite { param: "fov_y", .. }));
        assert!(e.to_string().contains("fov_y = NaN"), "{e}");
        assert!(matches!(
            perspective(1.0, 1.0, 1.0, f64::INFINITY),
            Err(NonFinite { param: "far", .. })
        ));
        let e = look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]).unwrap_err();
        assert!(matches!(e, UpParallel { .. }));
        assert!(e.to_string().contains("parallel"), "{e}");
        assert!(matches!(
            look_at([0.0; 3], [0.0, 0.0, -1.0], [0.0; 3]),
            Err(UpParallel { .. })
        ));
        assert!(matches!(
            look_at([1.0; 3], [1.0; 3], [0.0, 1.0, 0.0]),
            Err(EyeEqualsAt { .. })
        ));
        assert!(matches!(
            look_at([0.0, f64::NAN, 0.0], [1.0; 3], [0.0, 1.0, 0.0]),
            Err(NonFinite { param: "eye", .. })
        ));
        assert!(matches!(
            orthographic(1.0, -1.0, -1.0, 1.0, 0.0, 1.0),
            Err(EmptyRange {
                lo_name: "left",
                hi_name: "right",
                ..
            })
        ));
        assert!(matches!(
            orthographic(-1.0, 1.0, -1.0, 1.0, 2.0, 1.0),
            Err(EmptyRange {
                lo_name: "near",
                ..
            })
        ));
        assert!(matches!(
            weak_perspective(0.0, 0.0, 0.0, 0.0, 1.0),
            Err(ScaleNotPositive { .. })
        ));
        let mut bad_view = DMat4::IDENTITY;
        bad_view.x_axis.x = f64::NAN;
        assert!(matches!(
            Camera::new(
                bad_view,
                Projection::Perspective {
                    fov_y: 1.0,
                    aspect: 1.0,
                    near: 1.0,
                    far: 2.0
                }
            ),
            Err(NonFinite { param: "view", .. })
        ));
    }
}
