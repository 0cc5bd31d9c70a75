//! A linear (3DMM-style) morphable model: shape and albedo as means plus linear bases.
//!
//! ```text
//! shape  = mean_shape  + B_id alpha + B_exp beta      [V, 3], millimetres
//! albedo = mean_albedo + B_alb gamma                   [V, 3], linear RGB
//! ```
//!
//! Bases are stored as `[3V, K]` matrices whose row `3 v + c` is coordinate `c` (x, y, z or
//! r, g, b) of vertex `v` (the BFM layout; FLAME's `[V, 3, K]` is the same memory order).
//! In the shipped model (and in BFM-style models) the basis columns are orthonormal
//! (`B^T B = I`) and the coefficients carry the units: `alpha_k` is a length in millimetres,
//! the L2 norm of the displacement it causes over all `3V` coordinates, and `sigma_id[k]` is
//! its standard deviation. A model may instead carry the scale in the basis
//! ([`Morphable::basis_scaled`], FLAME style: unit-less coefficients, `sigma = 1`).
//!
//! Evaluation on the tape ([`Morphable::shape`], [`Morphable::albedo`]) records one
//! matrix-vector product per basis with the basis as a shared constant (no copy per tape);
//! the tape's matvec is parallel and deterministic.

use std::collections::BTreeMap;
use std::sync::Arc;

use autodiff::{Real, Tape, Tensor, Var};
use ndarray::{Array1, Array2, ArrayD, ArrayView1, ArrayView2, Ix1, Ix2, IxDyn};

use crate::error::{ModelError, Result};

/// A named group of triangles (skin, lips, mouth interior, ...). Regions with an `albedo`
/// are drawn with that constant colour instead of the per-vertex albedo when the mesh is
/// split with [`Morphable::region_split`] (the mouth interior and the eye openings of the
/// shipped model share their vertices with the surrounding skin). Regions that are not
/// `photometric` are rendered (they occlude) but their pixels are left out of a fit's
/// photometric term and RMSE (the ICT model's eyes, mouth socket and the face area outside
/// ICT's narrow face: hair, hats, collars and unmodelled eyes must not bias the skin).
#[derive(Clone, Debug, PartialEq)]
pub struct Region {
    /// Name, unique within the model.
    pub name: String,
    /// Constant linear-RGB albedo of the region's triangles, if it has its own.
    pub albedo: Option<[f64; 3]>,
    /// Whether a fit's photometric term uses the pixels this region covers.
    pub photometric: bool,
}

impl Region {
    /// A photometric region without its own albedo.
    pub fn new(name: impl Into<String>) -> Self {
        Region {
            name: name.into(),
            albedo: None,
            photometric: true,
        }
    }
}

/// How a model's landmarks are numbered (`landmark_scheme` in `model.json`): which 2D
/// landmark detector's points they correspond to, one to one and in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LandmarkScheme {
    /// The 468 points of MediaPipe's face mesh, in MediaPipe's order.
    MediaPipe468,
    /// The 68 points of the iBUG 300-W / Multi-PIE markup (dlib's 68), in that order.
    Ibug68,
}

impl LandmarkScheme {
    /// Every scheme.
    pub const ALL: [LandmarkScheme; 2] = [LandmarkScheme::MediaPipe468, LandmarkScheme::Ibug68];

    /// The `model.json` name: `mediapipe468` or `ibug68`.
    pub fn name(self) -> &'static str {
        match self {
            LandmarkScheme::MediaPipe468 => "mediapipe468",
            LandmarkScheme::Ibug68 => "ibug68",
        }
    }

    /// The scheme called `name` (see [`LandmarkScheme::name`]).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }

    /// Number of landmarks of the scheme.
    pub fn count(self) -> usize {
        match self {
            LandmarkScheme::MediaPipe468 => 468,
            LandmarkScheme::Ibug68 => 68,
        }
    }
}

/// A point on the model's surface: barycentric `weights` of the corners of triangle `face`
/// (`model.json`'s `landmark_points` rows `[face, w0, w1, w2]`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// Triangle index.
    pub face: usize,
    /// Weights of the triangle's three corners, in the triangle's vertex order (sum 1).
    pub weights: [f64; 3],
}

/// A landmark as a weighted sum of (up to) three model vertices: a vertex (weights `[1, 0,
/// 0]`), a point on a triangle, or the mean of two vertices. Its position is the same
/// weighted sum of the (posed) vertex positions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LandmarkPoint {
    /// The vertices.
    pub vertices: [usize; 3],
    /// Their weights.
    pub weights: [f64; 3],
}

impl LandmarkPoint {
    /// The landmark at vertex `v`.
    pub fn vertex(v: usize) -> Self {
        LandmarkPoint {
            vertices: [v; 3],
            weights: [1.0, 0.0, 0.0],
        }
    }

    /// The vertex, if this landmark is exactly one vertex.
    pub fn as_vertex(&self) -> Option<usize> {
        let w = self.weights;
        (w == [1.0, 0.0, 0.0]).then_some(self.vertices[0])
    }

    /// The weighted sum of the rows `vertices` of `positions` `[V, C]`.
    pub fn eval<T: Real>(&self, positions: ArrayView2<'_, T>) -> Vec<T> {
        let c = positions.ncols();
        (0..c)
            .map(|k| {
                self.vertices
                    .iter()
                    .zip(self.weights)
                    .fold(T::zero(), |acc, (&v, w)| {
                        acc + positions[[v, k]] * T::from_f64c(w)
                    })
            })
            .collect()
    }
}

/// The plain arrays a [`Morphable`] is built from (see [`Morphable::from_parts`]).
#[derive(Clone, Debug)]
pub struct MorphableParts<T: Real> {
    /// Model name.
    pub name: String,
    /// Free text (origin, construction, licence).
    pub description: String,
    /// Mean shape `[V, 3]` in millimetres.
    pub mean_shape: Array2<T>,
    /// Identity basis `[3V, K_id]`.
    pub id_basis: Array2<T>,
    /// Standard deviations of the identity coefficients `[K_id]`.
    pub sigma_id: Array1<T>,
    /// Expression basis `[3V, K_exp]` (`K_exp` may be 0).
    pub exp_basis: Array2<T>,
    /// Standard deviations of the expression coefficients `[K_exp]`.
    pub sigma_exp: Array1<T>,
    /// Mean albedo `[V, 3]`, linear RGB.
    pub mean_albedo: Array2<T>,
    /// Albedo basis `[3V, K_alb]` (`K_alb` may be 0).
    pub albedo_basis: Array2<T>,
    /// Standard deviations of the albedo coefficients `[K_alb]`.
    pub sigma_albedo: Array1<T>,
    /// Whether the bases carry the scale (coefficients unit-less) instead of the
    /// coefficients (orthonormal bases, coefficients in millimetres / albedo units).
    pub basis_scaled: bool,
    /// Triangles `[F]`, counter-clockwise seen from outside.
    pub faces: Vec<[u32; 3]>,
    /// Texture coordinates `[V, 2]`, if any.
    pub uvs: Option<Array2<T>>,
    /// Landmark vertex indices (the shipped model: every vertex, in order); empty when the
    /// landmarks are `landmark_points`.
    pub landmarks: Vec<usize>,
    /// Landmarks as points on triangles (empty: the landmarks are `landmarks`).
    pub landmark_points: Vec<SurfacePoint>,
    /// Which detector's numbering the landmarks follow, if known.
    pub landmark_scheme: Option<LandmarkScheme>,
    /// Named groups of vertex indices (contours).
    pub landmark_groups: BTreeMap<String, Vec<usize>>,
    /// Triangle regions; region 0 is the default.
    pub regions: Vec<Region>,
    /// Region label of every triangle `[F]` (empty: all 0).
    pub face_regions: Vec<u16>,
    /// Names of the identity components (empty or `K_id`).
    pub id_names: Vec<String>,
    /// Names of the expression components (empty or `K_exp`).
    pub exp_names: Vec<String>,
    /// Names of the albedo components (empty or `K_alb`).
    pub albedo_names: Vec<String>,
}

/// What each array is called in error messages (file names when loading).
#[derive(Clone, Debug)]
pub(crate) struct Labels {
    pub mean_shape: String,
    pub id_basis: String,
    pub sigma_id: String,
    pub exp_basis: String,
    pub sigma_exp: String,
    pub mean_albedo: String,
    pub albedo_basis: String,
    pub sigma_albedo: String,
    pub faces: String,
    pub uvs: String,
    pub landmarks: String,
    pub landmark_points: String,
    pub groups: String,
    pub face_regions: String,
    pub names: String,
}

impl Default for Labels {
    fn default() -> Self {
        Labels {
            mean_shape: "mean_shape".into(),
            id_basis: "id_basis".into(),
            sigma_id: "sigma_id".into(),
            exp_basis: "exp_basis".into(),
            sigma_exp: "sigma_exp".into(),
            mean_albedo: "mean_albedo".into(),
            albedo_basis: "albedo_basis".into(),
            sigma_albedo: "sigma_albedo".into(),
            faces: "faces".into(),
            uvs: "uvs".into(),
            landmarks: "landmarks".into(),
            landmark_points: "landmark_points".into(),
            groups: "landmark_groups".into(),
            face_regions: "face_regions".into(),
            names: "component names".into(),
        }
    }
}

/// A linear morphable model of shape and albedo over a fixed triangle mesh, generic over
/// `f32` and `f64`. Cheap to clone (the large arrays are shared).
#[derive(Clone, Debug)]
pub struct Morphable<T: Real> {
    name: String,
    description: String,
    n_vertices: usize,
    /// `[3V]`
    mean_shape: Arc<Tensor<T>>,
    /// `[3V, K_id]`
    id_basis: Arc<Tensor<T>>,
    sigma_id: Arc<Tensor<T>>,
    inv_sigma_id: Arc<Tensor<T>>,
    exp_basis: Arc<Tensor<T>>,
    sigma_exp: Arc<Tensor<T>>,
    inv_sigma_exp: Arc<Tensor<T>>,
    mean_albedo: Arc<Tensor<T>>,
    albedo_basis: Arc<Tensor<T>>,
    sigma_albedo: Arc<Tensor<T>>,
    inv_sigma_albedo: Arc<Tensor<T>>,
    basis_scaled: bool,
    faces: Arc<Vec<[u32; 3]>>,
    uvs: Option<Arc<Array2<T>>>,
    landmarks: Arc<Vec<usize>>,
    landmark_points: Arc<Vec<SurfacePoint>>,
    landmark_scheme: Option<LandmarkScheme>,
    landmark_groups: Arc<BTreeMap<String, Vec<usize>>>,
    regions: Arc<Vec<Region>>,
    face_regions: Arc<Vec<u16>>,
    id_names: Arc<Vec<String>>,
    exp_names: Arc<Vec<String>>,
    albedo_names: Arc<Vec<String>>,
}

fn check_finite<T: Real>(label: &str, a: impl IntoIterator<Item = T>) -> Result<()> {
    for (i, v) in a.into_iter().enumerate() {
        if !v.is_finite() {
            return Err(ModelError::NonFinite {
                file: label.to_string(),
                index: i,
                value: v.to_f64c(),
            });
        }
    }
    Ok(())
}

fn check_sigma<T: Real>(label: &str, s: &Array1<T>, k: usize, basis_label: &str) -> Result<()> {
    if s.len() != k {
        return Err(ModelError::Dimension {
            file: label.to_string(),
            what: format!("length of the standard deviations (columns of {basis_label})"),
            expected: k,
            found: s.len(),
        });
    }
    check_finite(label, s.iter().copied())?;
    if let Some((i, &v)) = s.iter().enumerate().find(|(_, &v)| v <= T::zero()) {
        return Err(ModelError::BadSigma {
            file: label.to_string(),
            index: i,
            value: v.to_f64c(),
        });
    }
    Ok(())
}

fn check_basis<T: Real>(label: &str, b: &Array2<T>, v: usize) -> Result<()> {
    if b.nrows() != 3 * v {
        return Err(ModelError::Dimension {
            file: label.to_string(),
            what: "rows (3 * n_vertices)".into(),
            expected: 3 * v,
            found: b.nrows(),
        });
    }
    check_finite(label, b.iter().copied())
}

fn check_index(label: &str, what: &str, position: usize, index: usize, bound: usize) -> Result<()> {
    if index >= bound {
        return Err(ModelError::IndexOutOfRange {
            file: label.to_string(),
            what: what.to_string(),
            position,
            index: index as i64,
            bound,
        });
    }
    Ok(())
}

fn check_names(label: &str, which: &str, names: &[String], k: usize) -> Result<()> {
    if !names.is_empty() && names.len() != k {
        return Err(ModelError::Dimension {
            file: label.to_string(),
            what: format!("number of {which} names"),
            expected: k,
            found: names.len(),
        });
    }
    Ok(())
}

fn inv<T: Real>(s: &Array1<T>) -> Arc<Tensor<T>> {
    Arc::new(s.mapv(|v| v.recip()).into_dyn())
}

fn flat<T: Real>(a: &Array2<T>) -> Arc<Tensor<T>> {
    let v: Vec<T> = a.iter().copied().collect();
    Arc::new(ArrayD::from_shape_vec(IxDyn(&[v.len()]), v).expect("length"))
}

fn std2<T: Real>(a: &Array2<T>) -> Arc<Tensor<T>> {
    Arc::new(a.as_standard_layout().into_owned().into_dyn())
}

fn view2<T: Real>(t: &Tensor<T>) -> ArrayView2<'_, T> {
    t.view().into_dimensionality::<Ix2>().expect("2-d")
}

fn view1<T: Real>(t: &Tensor<T>) -> ArrayView1<'_, T> {
    t.view().into_dimensionality::<Ix1>().expect("1-d")
}

/// `mean + B x` in plain arithmetic (f64 accumulation is not needed: same order as the tape).
fn affine<T: Real>(
    mean: &Tensor<T>,
    basis: &Tensor<T>,
    x: &[T],
    what: &'static str,
    v: usize,
) -> Result<Array2<T>> {
    let b = view2(basis);
    if x.len() != b.ncols() {
        return Err(ModelError::Coefficients {
            what,
            expected: b.ncols(),
            found: x.len(),
        });
    }
    let y = autodiff::ops::linalg::gemv(&b, &ArrayView1::from(x));
    let out = &view1(mean) + &y;
    Ok(out.into_shape_with_order((v, 3)).expect("3V"))
}

impl<T: Real> Morphable<T> {
    /// Builds a model from plain arrays, checking every dimension, index and value.
    pub fn from_parts(parts: MorphableParts<T>) -> Result<Self> {
        Self::from_parts_labelled(parts, &Labels::default())
    }

    pub(crate) fn from_parts_labelled(p: MorphableParts<T>, l: &Labels) -> Result<Self> {
        if p.mean_shape.ncols() != 3 {
            return Err(ModelError::Shape {
                file: l.mean_shape.clone(),
                shape: p.mean_shape.shape().to_vec(),
                expected: "[V, 3]".into(),
            });
        }
        let v = p.mean_shape.nrows();
        if v == 0 {
            return Err(ModelError::Invalid {
                file: l.mean_shape.clone(),
                detail: "the model has no vertices".into(),
            });
        }
        check_finite(&l.mean_shape, p.mean_shape.iter().copied())?;
        check_basis(&l.id_basis, &p.id_basis, v)?;
        check_sigma(&l.sigma_id, &p.sigma_id, p.id_basis.ncols(), &l.id_basis)?;
        check_basis(&l.exp_basis, &p.exp_basis, v)?;
        check_sigma(
            &l.sigma_exp,
            &p.sigma_exp,
            p.exp_basis.ncols(),
            &l.exp_basis,
        )?;
        if p.mean_albedo.shape() != [v, 3] {
            return Err(ModelError::Shape {
                file: l.mean_albedo.clone(),
                shape: p.mean_albedo.shape().to_vec(),
                expected: format!("[{v}, 3] (n_vertices = {v})"),
            });
        }
        check_finite(&l.mean_albedo, p.mean_albedo.iter().copied())?;
        check_basis(&l.albedo_basis, &p.albedo_basis, v)?;
        check_sigma(
            &l.sigma_albedo,
            &p.sigma_albedo,
            p.albedo_basis.ncols(),
            &l.albedo_basis,
        )?;
        if p.faces.is_empty() {
            return Err(ModelError::Invalid {
                file: l.faces.clone(),
                detail: "the model has no triangles".into(),
            });
        }
        for (i, f) in p.faces.iter().enumerate() {
            for (c, &ix) in f.iter().enumerate() {
                check_index(&l.faces, "vertex index", 3 * i + c, ix as usize, v)?;
            }
        }
        if let Some(uv) = &p.uvs {
            if uv.shape() != [v, 2] {
                return Err(ModelError::Shape {
                    file: l.uvs.clone(),
                    shape: uv.shape().to_vec(),
                    expected: format!("[{v}, 2] (n_vertices = {v})"),
                });
            }
            check_finite(&l.uvs, uv.iter().copied())?;
        }
        for (i, &ix) in p.landmarks.iter().enumerate() {
            check_index(&l.landmarks, "landmark vertex index", i, ix, v)?;
        }
        if !p.landmark_points.is_empty() && !p.landmarks.is_empty() {
            return Err(ModelError::Invalid {
                file: l.landmark_points.clone(),
                detail: "give the landmarks either as vertices or as points on triangles, not both"
                    .into(),
            });
        }
        for (i, q) in p.landmark_points.iter().enumerate() {
            check_index(
                &l.landmark_points,
                "triangle index",
                i,
                q.face,
                p.faces.len(),
            )?;
            let sum: f64 = q.weights.iter().sum();
            if q.weights.iter().any(|w| !w.is_finite()) || (sum - 1.0).abs() > 1e-4 {
                return Err(ModelError::Invalid {
                    file: l.landmark_points.clone(),
                    detail: format!(
                        "point {i}: barycentric weights {:?} must be finite and sum to 1",
                        q.weights
                    ),
                });
            }
        }
        if let Some(scheme) = p.landmark_scheme {
            let n = p.landmarks.len().max(p.landmark_points.len());
            if n != scheme.count() {
                return Err(ModelError::Invalid {
                    file: l.landmarks.clone(),
                    detail: format!(
                        "landmark_scheme {:?} has {} landmarks, the model gives {n}",
                        scheme.name(),
                        scheme.count()
                    ),
                });
            }
        }
        for (name, g) in &p.landmark_groups {
            for (i, &ix) in g.iter().enumerate() {
                check_index(
                    &format!("{}: group {name:?}", l.groups),
                    "vertex index",
                    i,
                    ix,
                    v,
                )?;
            }
        }
        let mut regions = p.regions;
        if regions.is_empty() {
            regions.push(Region::new("default"));
        }
        for (i, r) in regions.iter().enumerate() {
            if regions[..i].iter().any(|q| q.name == r.name) {
                return Err(ModelError::Invalid {
                    file: l.face_regions.clone(),
                    detail: format!("region name {:?} appears twice", r.name),
                });
            }
            if let Some(a) = r.albedo {
                check_finite(
                    &format!("{}: albedo of region {:?}", l.face_regions, r.name),
                    a,
                )?;
            }
        }
        let face_regions = if p.face_regions.is_empty() {
            vec![0u16; p.faces.len()]
        } else {
            if p.face_regions.len() != p.faces.len() {
                return Err(ModelError::Dimension {
                    file: l.face_regions.clone(),
                    what: "length (n_faces)".into(),
                    expected: p.faces.len(),
                    found: p.face_regions.len(),
                });
            }
            for (i, &r) in p.face_regions.iter().enumerate() {
                check_index(
                    &l.face_regions,
                    "region label",
                    i,
                    r as usize,
                    regions.len(),
                )?;
            }
            p.face_regions
        };
        check_names(&l.names, "identity", &p.id_names, p.id_basis.ncols())?;
        check_names(&l.names, "expression", &p.exp_names, p.exp_basis.ncols())?;
        check_names(&l.names, "albedo", &p.albedo_names, p.albedo_basis.ncols())?;
        Ok(Morphable {
            name: p.name,
            description: p.description,
            n_vertices: v,
            mean_shape: flat(&p.mean_shape),
            id_basis: std2(&p.id_basis),
            inv_sigma_id: inv(&p.sigma_id),
            sigma_id: Arc::new(p.sigma_id.into_dyn()),
            exp_basis: std2(&p.exp_basis),
            inv_sigma_exp: inv(&p.sigma_exp),
            sigma_exp: Arc::new(p.sigma_exp.into_dyn()),
            mean_albedo: flat(&p.mean_albedo),
            albedo_basis: std2(&p.albedo_basis),
            inv_sigma_albedo: inv(&p.sigma_albedo),
            sigma_albedo: Arc::new(p.sigma_albedo.into_dyn()),
            basis_scaled: p.basis_scaled,
            faces: Arc::new(p.faces),
            uvs: p.uvs.map(Arc::new),
            landmarks: Arc::new(p.landmarks),
            landmark_points: Arc::new(p.landmark_points),
            landmark_scheme: p.landmark_scheme,
            landmark_groups: Arc::new(p.landmark_groups),
            regions: Arc::new(regions),
            face_regions: Arc::new(face_regions),
            id_names: Arc::new(p.id_names),
            exp_names: Arc::new(p.exp_names),
            albedo_names: Arc::new(p.albedo_names),
        })
    }

    /// The plain arrays of this model (copies).
    pub fn to_parts(&self) -> MorphableParts<T> {
        MorphableParts {
            name: self.name.clone(),
            description: self.description.clone(),
            mean_shape: self.mean_shape(),
            id_basis: self.id_basis().to_owned(),
            sigma_id: self.sigma_id().to_owned(),
            exp_basis: self.exp_basis().to_owned(),
            sigma_exp: self.sigma_exp().to_owned(),
            mean_albedo: self.mean_albedo(),
            albedo_basis: self.albedo_basis().to_owned(),
            sigma_albedo: self.sigma_albedo().to_owned(),
            basis_scaled: self.basis_scaled,
            faces: (*self.faces).clone(),
            uvs: self.uvs.as_deref().cloned(),
            landmarks: (*self.landmarks).clone(),
            landmark_points: (*self.landmark_points).clone(),
            landmark_scheme: self.landmark_scheme,
            landmark_groups: (*self.landmark_groups).clone(),
            regions: (*self.regions).clone(),
            face_regions: (*self.face_regions).clone(),
            id_names: (*self.id_names).clone(),
            exp_names: (*self.exp_names).clone(),
            albedo_names: (*self.albedo_names).clone(),
        }
    }

    /// The same model in another precision.
    pub fn cast<U: Real>(&self) -> Morphable<U> {
        let p = self.to_parts();
        let c2 = |a: &Array2<T>| a.mapv(|x| U::from_f64c(x.to_f64c()));
        let c1 = |a: &Array1<T>| a.mapv(|x| U::from_f64c(x.to_f64c()));
        let q = MorphableParts {
            name: p.name,
            description: p.description,
            mean_shape: c2(&p.mean_shape),
            id_basis: c2(&p.id_basis),
            sigma_id: c1(&p.sigma_id),
            exp_basis: c2(&p.exp_basis),
            sigma_exp: c1(&p.sigma_exp),
            mean_albedo: c2(&p.mean_albedo),
            albedo_basis: c2(&p.albedo_basis),
            sigma_albedo: c1(&p.sigma_albedo),
            basis_scaled: p.basis_scaled,
            faces: p.faces,
            uvs: p.uvs.as_ref().map(c2),
            landmarks: p.landmarks,
            landmark_points: p.landmark_points,
            landmark_scheme: p.landmark_scheme,
            landmark_groups: p.landmark_groups,
            regions: p.regions,
            face_regions: p.face_regions,
            id_names: p.id_names,
            exp_names: p.exp_names,
            albedo_names: p.albedo_names,
        };
        Morphable::from_parts(q).expect("a valid model stays valid in another precision")
    }

    /// The model restricted to its first `k_id`, `k_exp` and `k_albedo` components (each
    /// clamped to what the model has), e.g. for coarse-to-fine fitting.
    pub fn truncated(&self, k_id: usize, k_exp: usize, k_albedo: usize) -> Self {
        let mut p = self.to_parts();
        let k_id = k_id.min(self.n_id());
        let k_exp = k_exp.min(self.n_exp());
        let k_alb = k_albedo.min(self.n_albedo());
        let cut2 = |a: &Array2<T>, k: usize| a.slice(ndarray::s![.., ..k]).to_owned();
        let cut1 = |a: &Array1<T>, k: usize| a.slice(ndarray::s![..k]).to_owned();
        p.id_basis = cut2(&p.id_basis, k_id);
        p.sigma_id = cut1(&p.sigma_id, k_id);
        p.exp_basis = cut2(&p.exp_basis, k_exp);
        p.sigma_exp = cut1(&p.sigma_exp, k_exp);
        p.albedo_basis = cut2(&p.albedo_basis, k_alb);
        p.sigma_albedo = cut1(&p.sigma_albedo, k_alb);
        p.id_names
            .truncate(if p.id_names.is_empty() { 0 } else { k_id });
        p.exp_names
            .truncate(if p.exp_names.is_empty() { 0 } else { k_exp });
        p.albedo_names
            .truncate(if p.albedo_names.is_empty() { 0 } else { k_alb });
        Morphable::from_parts(p).expect("a truncated valid model is valid")
    }

    // ---------------------------------------------------------------- accessors

    /// Model name.
    pub fn name(&self) -> &str {
        &self.name
    }
    /// Free-text description.
    pub fn description(&self) -> &str {
        &self.description
    }
    /// Number of vertices `V`.
    pub fn n_vertices(&self) -> usize {
        self.n_vertices
    }
    /// Number of triangles `F`.
    pub fn n_faces(&self) -> usize {
        self.faces.len()
    }
    /// Number of identity components `K_id`.
    pub fn n_id(&self) -> usize {
        self.id_basis.shape()[1]
    }
    /// Number of expression components `K_exp`.
    pub fn n_exp(&self) -> usize {
        self.exp_basis.shape()[1]
    }
    /// Number of albedo components `K_alb`.
    pub fn n_albedo(&self) -> usize {
        self.albedo_basis.shape()[1]
    }
    /// Mean shape `[V, 3]` (millimetres).
    pub fn mean_shape(&self) -> Array2<T> {
        view1(&self.mean_shape)
            .to_owned()
            .into_shape_with_order((self.n_vertices, 3))
            .expect("3V")
    }
    /// Identity basis `[3V, K_id]`.
    pub fn id_basis(&self) -> ArrayView2<'_, T> {
        view2(&self.id_basis)
    }
    /// Expression basis `[3V, K_exp]`.
    pub fn exp_basis(&self) -> ArrayView2<'_, T> {
        view2(&self.exp_basis)
    }
    /// Albedo basis `[3V, K_alb]`.
    pub fn albedo_basis(&self) -> ArrayView2<'_, T> {
        view2(&self.albedo_basis)
    }
    /// Standard deviations of the identity coefficients.
    pub fn sigma_id(&self) -> ArrayView1<'_, T> {
        view1(&self.sigma_id)
    }
    /// Standard deviations of the expression coefficients.
    pub fn sigma_exp(&self) -> ArrayView1<'_, T> {
        view1(&self.sigma_exp)
    }
    /// Standard deviations of the albedo coefficients.
    pub fn sigma_albedo(&self) -> ArrayView1<'_, T> {
        view1(&self.sigma_albedo)
    }
    /// Mean albedo `[V, 3]`.
    pub fn mean_albedo(&self) -> Array2<T> {
        view1(&self.mean_albedo)
            .to_owned()
            .into_shape_with_order((self.n_vertices, 3))
            .expect("3V")
    }
    /// Whether the bases carry the scale (unit-less coefficients) rather than the
    /// coefficients (orthonormal bases). False for the shipped model.
    pub fn basis_scaled(&self) -> bool {
        self.basis_scaled
    }
    /// Triangles, counter-clockwise seen from outside (from +z for the face).
    pub fn faces(&self) -> &[[u32; 3]] {
        &self.faces
    }
    /// Triangles as a `[F, 3]` array.
    pub fn faces_array(&self) -> Array2<u32> {
        Array2::from_shape_fn((self.faces.len(), 3), |(i, c)| self.faces[i][c])
    }
    /// Texture coordinates `[V, 2]`, if the model has them.
    pub fn uvs(&self) -> Option<&Array2<T>> {
        self.uvs.as_deref()
    }
    /// Landmark vertex indices (empty when the landmarks are points on triangles, see
    /// [`Morphable::surface_landmarks`]).
    pub fn landmarks(&self) -> &[usize] {
        &self.landmarks
    }
    /// Landmarks given as points on triangles (empty when they are vertices).
    pub fn surface_landmarks(&self) -> &[SurfacePoint] {
        &self.landmark_points
    }
    /// Which detector's numbering the landmarks follow, if the model says.
    pub fn landmark_scheme(&self) -> Option<LandmarkScheme> {
        self.landmark_scheme
    }
    /// Number of landmarks (vertices or surface points).
    pub fn n_landmarks(&self) -> usize {
        self.landmarks.len().max(self.landmark_points.len())
    }
    /// Every landmark as a [`LandmarkPoint`] (vertex landmarks, or the corners and weights of
    /// the surface points), in landmark order.
    pub fn landmark_points(&self) -> Vec<LandmarkPoint> {
        if self.landmark_points.is_empty() {
            self.landmarks
                .iter()
                .map(|&v| LandmarkPoint::vertex(v))
                .collect()
        } else {
            self.landmark_points
                .iter()
                .map(|q| LandmarkPoint {
                    vertices: self.faces[q.face].map(|x| x as usize),
                    weights: q.weights,
                })
                .collect()
        }
    }
    /// All named landmark groups.
    pub fn landmark_groups(&self) -> &BTreeMap<String, Vec<usize>> {
        &self.landmark_groups
    }
    /// One named landmark group.
    pub fn group(&self, name: &str) -> Option<&[usize]> {
        self.landmark_groups.get(name).map(|g| g.as_slice())
    }
    /// The triangle regions (index = label).
    pub fn regions(&self) -> &[Region] {
        &self.regions
    }
    /// Label of the region called `name`.
    pub fn region_label(&self, name: &str) -> Option<u16> {
        self.regions
            .iter()
            .position(|r| r.name == name)
            .map(|i| i as u16)
    }
    /// Region label of every triangle.
    pub fn face_regions(&self) -> &[u16] {
        &self.face_regions
    }
    /// One flag per triangle: whether its region is photometric ([`Region::photometric`]).
    pub fn photometric_faces(&self) -> Vec<bool> {
        self.face_regions
            .iter()
            .map(|&r| self.regions[r as usize].photometric)
            .collect()
    }
    /// Indices of the triangles in region `name` (empty if there is no such region).
    pub fn faces_in_region(&self, name: &str) -> Vec<usize> {
        match self.region_label(name) {
            Some(l) => (0..self.faces.len())
                .filter(|&i| self.face_regions[i] == l)
                .collect(),
            None => vec![],
        }
    }
    /// Names of the identity components (may be empty).
    pub fn id_names(&self) -> &[String] {
        &self.id_names
    }
    /// Names of the expression components (may be empty).
    pub fn exp_names(&self) -> &[String] {
        &self.exp_names
    }
    /// Names of the albedo components (may be empty).
    pub fn albedo_names(&self) -> &[String] {
        &self.albedo_names
    }
    /// Index of the identity component called `name`.
    pub fn id_index(&self, name: &str) -> Option<usize> {
        self.id_names.iter().position(|n| n == name)
    }
    /// Index of the expression component called `name`.
    pub fn exp_index(&self, name: &str) -> Option<usize> {
        self.exp_names.iter().position(|n| n == name)
    }
    /// Index of the albedo component called `name`.
    pub fn albedo_index(&self, name: &str) -> Option<usize> {
        self.albedo_names.iter().position(|n| n == name)
    }

    // ---------------------------------------------------------------- tape evaluation

    fn constant<'t>(&self, tape: &'t Tape<T>, a: &Arc<Tensor<T>>) -> Var<'t, T> {
        tape.var_shared(a.clone(), false)
    }

    /// Shape `mean + B_id alpha + B_exp beta` as a `[V, 3]` variable (millimetres);
    /// `alpha` is `[K_id]`, `beta` is `[K_exp]`. Wrong lengths poison the tape with a
    /// matmul shape error (reported by `value()` / `backward`).
    pub fn shape<'t>(&self, tape: &'t Tape<T>, alpha: Var<'t, T>, beta: Var<'t, T>) -> Var<'t, T> {
        linear_shape(
            tape,
            [&self.mean_shape, &self.id_basis, &self.exp_basis],
            alpha,
            beta,
        )
    }

    /// The shape model at surface `points` (see [`PointShape`]): what a landmark term needs,
    /// without the other vertices. Errors for a vertex index out of range.
    pub fn at_points(&self, points: &[LandmarkPoint]) -> Result<PointShape<T>> {
        for (i, &x) in points.iter().flat_map(|p| p.vertices.iter()).enumerate() {
            check_index("landmark points", "vertex index", i, x, self.n_vertices)?;
        }
        // Row `3 p + c` of a point basis: `sum_k w_k` row `3 v_k + c` of the vertex basis.
        let combine = |b: &Tensor<T>| -> Tensor<T> {
            let k = if b.ndim() == 2 { b.shape()[1] } else { 1 };
            let bs = b.as_slice().expect("standard layout");
            let mut out = vec![T::zero(); 3 * points.len() * k];
            for (p, rows) in points.iter().zip(out.chunks_exact_mut(3 * k)) {
                for (&vi, &w) in p.vertices.iter().zip(&p.weights) {
                    if w == 0.0 {
                        continue;
                    }
                    let w = T::from_f64c(w);
                    let src = &bs[3 * vi * k..3 * (vi + 1) * k];
                    for (o, &x) in rows.iter_mut().zip(src) {
                        *o += w * x;
                    }
                }
            }
            let shape: Vec<usize> = if b.ndim() == 2 {
                vec![3 * points.len(), k]
            } else {
                vec![3 * points.len()]
            };
            ArrayD::from_shape_vec(IxDyn(&shape), out).expect("rows")
        };
        Ok(PointShape {
            mean: Arc::new(combine(&self.mean_shape)),
            id_basis: Arc::new(combine(&self.id_basis)),
            exp_basis: Arc::new(combine(&self.exp_basis)),
            sigma_id: self.sigma_id.clone(),
            sigma_exp: self.sigma_exp.clone(),
        })
    }

    /// Shape without expression, `mean + B_id alpha`, `[V, 3]`.
    pub fn shape_identity<'t>(&self, tape: &'t Tape<T>, alpha: Var<'t, T>) -> Var<'t, T> {
        let mean = self.constant(tape, &self.mean_shape);
        let id = self.constant(tape, &self.id_basis).matmul(alpha);
        (mean + id).reshape(&[self.n_vertices, 3])
    }

    /// Shape from standardised coefficients: `alpha = sigma_id * z_id`, `beta = sigma_exp *
    /// z_exp` (a well-conditioned parametrisation for optimisers).
    pub fn shape_standardized<'t>(
        &self,
        tape: &'t Tape<T>,
        z_id: Var<'t, T>,
        z_exp: Var<'t, T>,
    ) -> Var<'t, T> {
        let a = z_id * self.constant(tape, &self.sigma_id);
        let b = z_exp * self.constant(tape, &self.sigma_exp);
        self.shape(tape, a, b)
    }

    /// Albedo `mean_albedo + B_alb gamma` as a `[V, 3]` variable.
    pub fn albedo<'t>(&self, tape: &'t Tape<T>, gamma: Var<'t, T>) -> Var<'t, T> {
        let mean = self.constant(tape, &self.mean_albedo);
        let d = self.constant(tape, &self.albedo_basis).matmul(gamma);
        (mean + d).reshape(&[self.n_vertices, 3])
    }

    /// Albedo from standardised coefficients, `gamma = sigma_albedo * z`.
    pub fn albedo_standardized<'t>(&self, tape: &'t Tape<T>, z: Var<'t, T>) -> Var<'t, T> {
        let g = z * self.constant(tape, &self.sigma_albedo);
        self.albedo(tape, g)
    }

    fn prior<'t>(
        &self,
        tape: &'t Tape<T>,
        x: Var<'t, T>,
        inv_sigma: &Arc<Tensor<T>>,
    ) -> Var<'t, T> {
        (x * self.constant(tape, inv_sigma)).square().sum()
    }

    /// Identity prior `sum_k (alpha_k / sigma_id_k)^2` (a 0-d variable; the negative log of
    /// the Gaussian prior up to a factor 1/2 and a constant).
    pub fn id_prior<'t>(&self, tape: &'t Tape<T>, alpha: Var<'t, T>) -> Var<'t, T> {
        self.prior(tape, alpha, &self.inv_sigma_id)
    }
    /// Expression prior `sum_k (beta_k / sigma_exp_k)^2`.
    pub fn exp_prior<'t>(&self, tape: &'t Tape<T>, beta: Var<'t, T>) -> Var<'t, T> {
        self.prior(tape, beta, &self.inv_sigma_exp)
    }
    /// Albedo prior `sum_k (gamma_k / sigma_albedo_k)^2`.
    pub fn albedo_prior<'t>(&self, tape: &'t Tape<T>, gamma: Var<'t, T>) -> Var<'t, T> {
        self.prior(tape, gamma, &self.inv_sigma_albedo)
    }

    /// Landmark positions `[L, 3]` of a `[V, 3]` shape (vertices picked, or surface points
    /// interpolated: [`landmark_combination`]).
    pub fn landmark_positions<'t>(&self, shape: Var<'t, T>) -> Var<'t, T> {
        if self.landmark_points.is_empty() {
            shape.index_select(0, &self.landmarks)
        } else {
            landmark_combination(shape, &self.landmark_points())
        }
    }

    /// Positions `[n, 3]` of the vertices of a named group, if it exists.
    pub fn group_positions<'t>(&self, shape: Var<'t, T>, name: &str) -> Option<Var<'t, T>> {
        self.group(name).map(|g| shape.index_select(0, g))
    }

    // ---------------------------------------------------------------- plain evaluation

    /// Shape `[V, 3]` without a tape.
    pub fn eval_shape(&self, alpha: &[T], beta: &[T]) -> Result<Array2<T>> {
        let s = affine(
            &self.mean_shape,
            &self.id_basis,
            alpha,
            "alpha",
            self.n_vertices,
        )?;
        let b = view2(&self.exp_basis);
        if beta.len() != b.ncols() {
            return Err(ModelError::Coefficients {
                what: "beta",
                expected: b.ncols(),
                found: beta.len(),
            });
        }
        let e = autodiff::ops::linalg::gemv(&b, &ArrayView1::from(beta));
        let e = e.into_shape_with_order((self.n_vertices, 3)).expect("3V");
        Ok(s + e)
    }

    /// Albedo `[V, 3]` without a tape.
    pub fn eval_albedo(&self, gamma: &[T]) -> Result<Array2<T>> {
        affine(
            &self.mean_albedo,
            &self.albedo_basis,
            gamma,
            "gamma",
            self.n_vertices,
        )
    }

    /// Shape with coefficients given in standard deviations (`alpha = sigma_id * z_id`).
    pub fn eval_shape_standardized(&self, z_id: &[T], z_exp: &[T]) -> Result<Array2<T>> {
        let a: Vec<T> = z_id
            .iter()
            .zip(self.sigma_id())
            .map(|(&z, &s)| z * s)
            .collect();
        let b: Vec<T> = z_exp
            .iter()
            .zip(self.sigma_exp())
            .map(|(&z, &s)| z * s)
            .collect();
        if a.len() != z_id.len() || a.len() != self.n_id() {
            return Err(ModelError::Coefficients {
                what: "z_id",
                expected: self.n_id(),
                found: z_id.len(),
            });
        }
        if b.len() != z_exp.len() || b.len() != self.n_exp() {
            return Err(ModelError::Coefficients {
                what: "z_exp",
                expected: self.n_exp(),
                found: z_exp.len(),
            });
        }
        self.eval_shape(&a, &b)
    }

    /// Plain prior values `(identity, expression, albedo)` of coefficient vectors.
    pub fn eval_priors(&self, alpha: &[T], beta: &[T], gamma: &[T]) -> Result<(T, T, T)> {
        let p = |x: &[T], s: ArrayView1<'_, T>, what: &'static str| -> Result<T> {
            if x.len() != s.len() {
                return Err(ModelError::Coefficients {
                    what,
                    expected: s.len(),
                    found: x.len(),
                });
            }
            Ok(x.iter().zip(s).map(|(&a, &s)| (a / s) * (a / s)).sum())
        };
        Ok((
            p(alpha, self.sigma_id(), "alpha")?,
            p(beta, self.sigma_exp(), "beta")?,
            p(gamma, self.sigma_albedo(), "gamma")?,
        ))
    }

    // ---------------------------------------------------------------- rendering helpers

    /// A render topology in which every region with its own albedo gets its own copies of
    /// its vertices, so that its triangles can be coloured independently of the skin they
    /// share vertices with, and the vertices that photometric and non-photometric triangles
    /// share are copied for the latter, so that an interpolated per-vertex weight is exactly
    /// 1 on photometric triangles and 0 on the others (see [`RegionSplit`]).
    pub fn region_split(&self) -> RegionSplit<T> {
        let v = self.n_vertices;
        let mut vertex_map: Vec<usize> = (0..v).collect();
        let mut colors: Vec<Option<[f64; 3]>> = vec![None; v];
        let mut faces = (*self.faces).clone();
        for (label, region) in self.regions.iter().enumerate() {
            let Some(col) = region.albedo else { continue };
            let mut copy: BTreeMap<u32, u32> = BTreeMap::new();
            for (f, tri) in faces.iter_mut().enumerate() {
                if self.face_regions[f] as usize != label {
                    continue;
                }
                for ix in tri.iter_mut() {
                    let n = *copy.entry(*ix).or_insert_with(|| {
                        vertex_map.push(*ix as usize);
                        colors.push(Some(col));
                        (vertex_map.len() - 1) as u32
                    });
                    *ix = n;
                }
            }
        }
        // Photometric split: a render vertex used by both kinds of triangle gets a copy for
        // the non-photometric ones.
        let photometric = self.photometric_faces();
        let n0 = vertex_map.len();
        let mut used = vec![[false; 2]; n0];
        for (f, tri) in faces.iter().enumerate() {
            for &ix in tri {
                used[ix as usize][usize::from(photometric[f])] = true;
            }
        }
        let mut copy: BTreeMap<u32, u32> = BTreeMap::new();
        for (f, tri) in faces.iter_mut().enumerate() {
            if photometric[f] {
                continue;
            }
            for ix in tri.iter_mut() {
                if used[*ix as usize] == [true, true] {
                    *ix = *copy.entry(*ix).or_insert_with(|| {
                        vertex_map.push(vertex_map[*ix as usize]);
                        colors.push(colors[*ix as usize]);
                        (vertex_map.len() - 1) as u32
                    });
                }
            }
        }
        let photo_weight = used.iter().any(|u| u[0]).then(|| {
            let w = (0..vertex_map.len())
                .map(|i| T::from_f64c(if i < n0 && used[i][1] { 1.0 } else { 0.0 }))
                .collect();
            Arc::new(ArrayD::from_shape_vec(IxDyn(&[vertex_map.len(), 1]), w).expect("shape"))
        });
        let n = vertex_map.len();
        let mask = ArrayD::from_shape_fn(IxDyn(&[n, 3]), |i| colors[i[0]].is_none());
        let fill = ArrayD::from_shape_fn(IxDyn(&[n, 3]), |i| {
            T::from_f64c(colors[i[0]].map(|c| c[i[1]]).unwrap_or(0.0))
        });
        RegionSplit {
            vertex_map,
            faces,
            mask,
            fill: Arc::new(fill),
            photo_weight,
        }
    }
}

/// `mean + B_id alpha + B_exp beta` on the tape, reshaped to `[N, 3]`: `parts` are the mean
/// `[3N]` and the two bases `[3N, K]` (shared constants).
fn linear_shape<'t, T: Real>(
    tape: &'t Tape<T>,
    parts: [&Arc<Tensor<T>>; 3],
    alpha: Var<'t, T>,
    beta: Var<'t, T>,
) -> Var<'t, T> {
    let [mean, id, exp] = parts.map(|a| tape.var_shared(a.clone(), false));
    let n = mean.shape()[0] / 3;
    (mean + id.matmul(alpha) + exp.matmul(beta)).reshape(&[n, 3])
}

/// A shape model restricted to surface points (landmarks): a point is a fixed weighted sum
/// of up to three vertices, so its position is linear in the coefficients with the vertex
/// basis rows combined by the same weights. A landmark term then costs `3L x K` instead of
/// `3V x K` per product (ICT: 468 points against 14,595 vertices), with the same values up to
/// rounding ([`Morphable::at_points`]).
#[derive(Clone, Debug)]
pub struct PointShape<T: Real> {
    mean: Arc<Tensor<T>>,
    id_basis: Arc<Tensor<T>>,
    exp_basis: Arc<Tensor<T>>,
    sigma_id: Arc<Tensor<T>>,
    sigma_exp: Arc<Tensor<T>>,
}

impl<T: Real> PointShape<T> {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.mean.len() / 3
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.mean.is_empty()
    }

    /// Point positions `[N, 3]` from standardised coefficients (as
    /// [`Morphable::shape_standardized`]).
    pub fn shape_standardized<'t>(
        &self,
        tape: &'t Tape<T>,
        z_id: Var<'t, T>,
        z_exp: Var<'t, T>,
    ) -> Var<'t, T> {
        let a = z_id * tape.var_shared(self.sigma_id.clone(), false);
        let b = z_exp * tape.var_shared(self.sigma_exp.clone(), false);
        linear_shape(tape, [&self.mean, &self.id_basis, &self.exp_basis], a, b)
    }
}

/// Positions `[L, C]` of landmark points from per-vertex positions `[V, C]` on the tape:
/// `sum_k w_k x[v_k]` (three gathers, each times a constant weight column). When every point
/// is a vertex it is one gather, the same values bit for bit.
pub fn landmark_combination<'t, T: Real>(
    positions: Var<'t, T>,
    points: &[LandmarkPoint],
) -> Var<'t, T> {
    if let Some(v) = points
        .iter()
        .map(|p| p.as_vertex())
        .collect::<Option<Vec<usize>>>()
    {
        return positions.index_select(0, &v);
    }
    let tape = positions.tape();
    let c = positions.shape().get(1).copied().unwrap_or(1);
    let mut sum: Option<Var<'t, T>> = None;
    for k in 0..3 {
        let idx: Vec<usize> = points.iter().map(|p| p.vertices[k]).collect();
        let w = ArrayD::from_shape_fn(IxDyn(&[points.len(), c]), |i| {
            T::from_f64c(points[i[0]].weights[k])
        });
        let term = positions.index_select(0, &idx) * tape.constant(w);
        sum = Some(match sum {
            Some(s) => s + term,
            None => term,
        });
    }
    sum.expect("three terms")
}

/// A copy of the model's topology in which regions with their own albedo (mouth interior,
/// eye openings) have their own vertices: `vertex_map[i]` is the model vertex that render
/// vertex `i` copies (the first `V` are the model's vertices, in order), `faces` index render
/// vertices. Positions, normals and uvs are gathered through `vertex_map`; albedo is gathered
/// and overwritten with the region colours.
#[derive(Clone, Debug)]
pub struct RegionSplit<T: Real> {
    /// Model vertex of every render vertex.
    pub vertex_map: Vec<usize>,
    /// Triangles over render vertices (same order and count as the model's).
    pub faces: Vec<[u32; 3]>,
    mask: ArrayD<bool>,
    fill: Arc<Tensor<T>>,
    photo_weight: Option<Arc<Tensor<T>>>,
}

impl<T: Real> RegionSplit<T> {
    /// Number of render vertices.
    pub fn n_vertices(&self) -> usize {
        self.vertex_map.len()
    }
    /// Any per-vertex attribute `[V, C]` gathered to render vertices `[V', C]`.
    pub fn gather<'t>(&self, attr: Var<'t, T>) -> Var<'t, T> {
        attr.index_select(0, &self.vertex_map)
    }
    /// Albedo `[V, 3]` to render vertices `[V', 3]`, with region colours on the copies.
    pub fn albedo<'t>(&self, albedo: Var<'t, T>) -> Var<'t, T> {
        let tape = albedo.tape();
        let fill = tape.var_shared(self.fill.clone(), false);
        self.gather(albedo).where_(self.mask.clone(), fill)
    }
    /// The photometric weight `[V', 1]` of the render vertices (1 on the vertices of
    /// photometric triangles, 0 on the others' own copies), or `None` when every region is
    /// photometric.
    pub fn photo_weight(&self) -> Option<&Arc<Tensor<T>>> {
        self.photo_weight.as_ref()
    }
    /// Plain version of [`RegionSplit::gather`].
    pub fn gather_plain<A: Clone>(&self, attr: &Array2<A>) -> Array2<A> {
        attr.select(ndarray::Axis(0), &self.vertex_map)
    }
    /// Plain version of [`RegionSplit::albedo`].
    pub fn albedo_plain(&self, albedo: &Array2<T>) -> Array2<T> {
        let mut a = self.gather_plain(albedo);
        for ((i, c), v) in a.indexed_iter_mut() {
            if !self.mask[[i, c]] {
                *v = self.fill[[i, c]];
            }
        }
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use autodiff::gradcheck::{gradcheck, GradcheckOptions};
    use autodiff::rng::Rng;

    /// A barycentric point on `first`, a vertex, and a point on an edge (one weight 0).
    fn mixed_points(first: [usize; 3]) -> Vec<LandmarkPoint> {
        vec![
            LandmarkPoint {
                vertices: first,
                weights: [0.2, 0.3, 0.5],
            },
            LandmarkPoint::vertex(4),
            LandmarkPoint {
                vertices: [1, 3, 1],
                weights: [0.5, 0.5, 0.0],
            },
        ]
    }

    #[test]
    fn landmark_combination_is_the_weighted_sum_and_gradchecks() {
        let mut rng = Rng::new(7);
        let x: Tensor<f64> = rng.uniform_tensor(&[6, 3], -1.0, 1.0);
        let points = mixed_points([0, 2, 5]);
        let tape = Tape::new();
        let got = landmark_combination(tape.constant(x.clone()), &points)
            .value()
            .unwrap();
        let x2 = x.view().into_dimensionality::<Ix2>().unwrap();
        for (i, p) in points.iter().enumerate() {
            let want = p.eval(x2);
            for k in 0..3 {
                assert!((got[[i, k]] - want[k]).abs() < 1e-15);
            }
        }
        // Vertices only: one gather, bit for bit.
        let v = [LandmarkPoint::vertex(3), LandmarkPoint::vertex(0)];
        let g = landmark_combination(tape.constant(x.clone()), &v)
            .value()
            .unwrap();
        assert_eq!(
            g.index_axis(ndarray::Axis(0), 0),
            x.index_axis(ndarray::Axis(0), 3)
        );
        let rep = gradcheck(
            |_t: &Tape<f64>, v| landmark_combination(v[0], &points).square().sum(),
            &[x],
            &GradcheckOptions::default(),
        )
        .unwrap();
        assert!(rep.passed(), "{rep}");
    }

    /// The model at surface points gives the same positions as the full shape combined at
    /// those points, and the same coefficient gradients (the shipped model, f64).
    #[test]
    fn point_shape_matches_the_full_shape_at_the_points() {
        let m: Morphable<f64> = crate::face::default_face();
        let points = mixed_points([10, 200, 467]);
        let pm = m.at_points(&points).unwrap();
        assert_eq!(pm.len(), 3);
        let mut rng = Rng::new(3);
        let zi: Tensor<f64> = rng.uniform_tensor(&[m.n_id()], -2.0, 2.0);
        let ze: Tensor<f64> = rng.uniform_tensor(&[m.n_exp()], -2.0, 2.0);
        let w: Tensor<f64> = rng.uniform_tensor(&[3, 3], -1.0, 1.0);
        let run = |full: bool| {
            let tape = Tape::new();
            let (a, b) = (tape.leaf(zi.clone()), tape.leaf(ze.clone()));
            let x = if full {
                landmark_combination(m.shape_standardized(&tape, a, b), &points)
            } else {
                pm.shape_standardized(&tape, a, b)
            };
            let loss = (x * tape.constant(w.clone())).sum();
            let mut g = tape.backward(loss).unwrap();
            let x = x.value().unwrap().as_ref().clone();
            (x, g.take(a).unwrap(), g.take(b).unwrap())
        };
        let (full, fast) = (run(true), run(false));
        let close = |p: &Tensor<f64>, q: &Tensor<f64>| {
            p.iter()
                .zip(q.iter())
                .all(|(x, y)| (x - y).abs() < 1e-9 * (1.0 + x.abs()))
        };
        assert!(close(&full.0, &fast.0), "{} vs {}", full.0, fast.0);
        assert!(close(&full.1, &fast.1));
        assert!(close(&full.2, &fast.2));
        let bad = [LandmarkPoint::vertex(m.n_vertices())];
        assert!(matches!(
            m.at_points(&bad),
            Err(ModelError::IndexOutOfRange { .. })
        ));
    }
}
