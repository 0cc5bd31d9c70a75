//! Parametric models for Tapestry: a linear (3DMM-style) morphable model of shape and
//! albedo ([`Morphable`]), its file layout ([`Morphable::load`], [`Morphable::save`]), two
//! shipped face models (the ICT-FaceKit scan-based model, [`ict`], and a small one built on the
//! MediaPipe canonical face mesh, [`face`]), and face detection
//! with the 468 MediaPipe face-mesh landmarks in pure Rust ([`detect`]).
//!
//! ```
//! use autodiff::{tensor, Tape};
//! let model = models::face::default_face::<f64>();
//! let tape = Tape::new();
//! let alpha = tape.leaf(tensor::from_vec(&[model.n_id()], vec![0.0; model.n_id()]).unwrap());
//! let beta = tape.leaf(tensor::from_vec(&[model.n_exp()], vec![0.0; model.n_exp()]).unwrap());
//! let shape = model.shape(&tape, alpha, beta); // [468, 3], millimetres
//! let loss = shape.square().sum() + model.id_prior(&tape, alpha) + model.exp_prior(&tape, beta);
//! let grads = tape.backward(loss).unwrap();
//! assert_eq!(grads.wrt(alpha).shape(), &[model.n_id()]);
//! ```
#![warn(missing_docs)]

pub mod detect;
pub mod error;
pub mod face;
pub mod fit;
pub mod ict;
pub mod io;
pub mod morphable;

pub use error::{ModelError, Result};
pub use morphable::{
    LandmarkPoint, LandmarkScheme, Morphable, MorphableParts, PointShape, Region, RegionSplit,
    SurfacePoint,
};
