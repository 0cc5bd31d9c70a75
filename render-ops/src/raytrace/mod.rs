//! Differentiable ray tracing with edge sampling (the `raytrace` method): primary visibility,
//! direct lighting with shadow rays from directional, point and area lights, and gradients
//! that include the discontinuities of visibility (silhouettes, occlusion and shadow
//! boundaries). T.-M. Li, M. Aittala, F. Durand, J. Lehtinen, "Differentiable Monte Carlo ray
//! tracing through edge sampling", SIGGRAPH Asia 2018 (redner); survey section 5.1.
//!
//! # Forward
//! Each pixel is the box-filtered (area-averaged) image of docs/CONVENTIONS.md, estimated with
//! `spp` stratified samples (an `sx x sy` grid of strata, one jittered sample in each). Primary
//! rays are traced in the clip space of the camera: with `q = (clip.x, clip.y, clip.w)` (a
//! linear map of view space for a perspective camera) the ray of NDC point `(x, y)` is
//! `q = t (x, y, 1)` and `t` is the view depth, so hits are those of the rasterizer (same
//! barycentrics, near and far planes) and gradients reach the camera through the clip
//! positions. All camera rays leave the origin of that space, so their hits come from a
//! screen grid ([`grid`]) instead of a tree walk: the same hits as a BVH's. Shading happens in world space ([`shading`]: Lambert, Phong, Blinn-Phong, SH),
//! with one shadow ray per light and sample (an area light: one uniform area sample per pixel
//! sample) against a BVH of the world-space triangles ([`bvh`], watertight tests of
//! [`intersect`]). SH lighting is unshadowed. The emitter of an area light is not visible to the
//! camera. Random numbers are counter-based ([`rng`]): a render is a function of its inputs and
//! `seed`, the same for any thread count. The forward traces and shades a row's samples eight
//! at a time (`packet`) with the scalar sample's arithmetic in every lane: the same image, bit
//! for bit, as one sample at a time (which the backward re-traces).
//!
//! # Backward
//! * Interior: every sample's colour is differentiated through the shading (point, normals,
//!   albedo, light rows) and through its hit barycentrics: for a ray along `d` hitting the
//!   triangle `q_i` at `b`, with `N = e1 x e2`, `A = (e2 x N) / |N|^2`, `B = (N x e1) / |N|^2`,
//!   `G = (g_b1 - g_b0) A + (g_b2 - g_b0) B` and `H = G . d / (N . d)`, the gradient of vertex `i`
//!   is `b_i (H N - G)` (the hit moves along the ray, the barycentrics within the plane).
//! * Primary edges (Li et al. eq. 5-7): silhouette and boundary edges seen from the camera are
//!   sampled in proportion to their projected length; at the image point `u(s)` of edge point
//!   `s` the difference of the image on the two sides, `f(u - eps n) - f(u + eps n)`, times the
//!   normal velocity `cross(du/ds, du/dtheta)` (in pixel units, so the pixel integral is a
//!   mean) is the derivative of the pixel containing `u`.
//! * Shadow edges of point and directional lights: an occluder edge that is a silhouette seen
//!   from the light is sampled (by world length); the ray from the light through its point `p(s)`
//!   meets the receiver at `y`, projected to `u`; the same two-sided difference and normal
//!   velocity of `u`, now a function of the occluder edge, the light, the receiver triangle and
//!   the camera.
//! * Shadow edges of area lights (secondary visibility, Li et al. section 5): per pixel sample,
//!   `area_edge_samples` edges that are silhouettes seen from the shading point `x`, drawn by
//!   world length times 16 for the edges that cast a shadow from the light's centre or a
//!   corner (a defensive mixture: every edge keeps a positive weight, so the estimate stays
//!   unbiased); the ray from `x` through `p(s)` meets the light at `(a, b)`; the difference of
//!   the light's estimator on the two sides of the curve in `(a, b)` times the curve's normal
//!   velocity (a function of the edge, the light and `x`, whose motion on its receiver is
//!   included) is the derivative of the light integral.
//!
//! Gradients reach clip positions (primary hits and edges; hence the camera and vertex
//! positions through the tape), world positions, normals and albedo at the hits, and every
//! light row. An edge crossing the near plane contributes its part in front of it (sampled on
//! that part, weighted by its projected length).
//!
//! Not differentiated (left out, exactly): the eye position `RaytraceSettings::eye` is a
//! constant, so (1) the view direction of Phong / Blinn-Phong highlights does not move with
//! the camera (the specular term's gradient reaches the hit point, normal and albedo, but not
//! the eye), and (2) the camera's effect on the world shading point of area-light edge terms
//! is left out (the shading point's motion on its receiver is included); the primary hit
//! itself moves with the camera through the clip positions. The image edge that the near
//! plane cuts through a triangle (where the plane slices the mesh) has no edge term: it moves
//! with the camera and the vertices but is not sampled.

pub mod bvh;
pub mod edges;
pub mod grid;
pub mod intersect;
pub mod rng;
pub mod shading;
pub mod stage;

mod op;
mod packet;

pub use op::{raytrace, RaytraceSettings};
pub use shading::{LightKind, Reflection};
pub use stage::{blend_traced, raytrace_fragments, ShadowInputs, TracedFragments};
