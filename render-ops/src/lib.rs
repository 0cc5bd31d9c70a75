//! Rendering ops: cameras, meshes, the rasterizer and every stage of a differentiable render,
//! each an `autodiff::Op` with a hand-written backward, composed into pipelines on the tape.
//!
//! # Module map, by pipeline stage
//!
//! | stage | modules |
//! |---|---|
//! | inputs | [`camera`], [`mesh`], [`obj`], [`io`] (PNG, `.npy`), [`scene`] (the scene JSON) |
//! | vertex stage | [`transform`] (rotations, projections to clip space), [`shade::normals`] |
//! | visibility: the method registry | [`methods`] (name, kind, exactness, settings and the two entry points of each of the eight methods) |
//! | visibility: kernels | [`raster`] (hard rasterizer: tiles, edge functions, packed [`raster::Fragments`], backward, direct render), [`soft`] (SoftRas, DIB-R), [`analytic`] (exact area sampling) |
//! | visibility: tape ops | [`rasterize`](mod@rasterize) (fragments as tape variables), [`approx`] (fused `tf_mesh`, `opendr`, `nmr`, `deodr` over per-vertex colours; `tf_mesh`'s extrapolated rasterization) |
//! | fragment stage | [`interpolate`](mod@interpolate), [`texture`], [`shade`] (lights, Phong family, SH, programmable shaders, auxiliary outputs) |
//! | blend and boundary | [`blend`] (hard z-buffer blend, area-weighted blend), [`boundary`] (`deodr`, `opendr`, `nmr` over any shaded image) |
//! | wiring | [`pipeline`] (`Scene::render`: the scene JSON through the registry) |
//! | checking | [`check`] (gradient checks against finite differences and supersampled references, the gradcheck registry) |
//! | shared kernels | `simd` (eight-lane `f32` arithmetic, bit-identical with and without AVX2), `scatter` (deterministic scatter-add) |
//! | errors | [`error`] |
//!
//! The main entry points are re-exported here: [`rasterize()`], [`interpolate()`],
//! [`blend_hard`], [`render_shader`], [`render_vertex_colors`], [`render_fragments`],
//! [`Scene`], [`Method`]. The data flow and how to add a method are in `ARCHITECTURE.md`.
// Index loops mirror the papers' per-vertex/per-channel equations; the backward closures'
// types are spelled out where they are built.
#![allow(
    clippy::needless_range_loop,
    clippy::type_complexity,
    clippy::neg_cmp_op_on_partial_ord,
    clippy::manual_contains
)]
pub mod analytic;
pub mod approx;
pub mod blend;
pub mod boundary;
pub mod camera;
pub mod check;
pub mod error;
pub mod interpolate;
pub mod io;
pub mod mesh;
pub mod methods;
pub mod obj;
pub mod pipeline;
pub mod raster;
pub mod rasterize;
pub mod raytrace;
mod scatter;
pub mod scene;
pub mod shade;
pub(crate) mod simd;
pub mod soft;
pub mod texture;
pub mod transform;

pub use blend::blend_hard;
pub use camera::Camera;
pub use error::RenderError;
pub use interpolate::interpolate;
pub use mesh::Mesh;
pub use methods::{
    render_fragments, render_vertex_colors, Kind, MethodInfo, MethodSettings, ViewSettings,
};
pub use raster::{Fragments, RasterSettings};
pub use rasterize::{rasterize, render_attributes, Rasterized};
pub use scene::{Method, Scene};
pub use shade::{fragment_inputs, render_shader, FragmentInputs, MeshAttributes};
pub use texture::Texture;
pub use transform::to_clip;
