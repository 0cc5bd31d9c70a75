//! Triangle meshes: the plain (non-differentiable) data container every renderer stage reads.
//!
//! A [`Mesh`] stores positions and triangles with 0-based `u32` indices. Texture coordinates and
//! normals may have their own index buffers (as in OBJ, where a vertex on a uv seam keeps one
//! position but has several uvs); [`Mesh::unified`] splits such vertices so that one index buffer
//! serves all attributes, and remembers which position each new vertex came from so gradients can
//! be summed back onto the original `[V, 3]` positions.
//!
//! Optional attributes are "absent" when their vector is empty: `uvs` + `uv_faces`,
//! `normals` + `normal_faces`, per-vertex `colors` (one per position).
//!
//! Front faces are counter-clockwise seen from outside (docs/CONVENTIONS.md), which the procedural
//! constructors ([`Mesh::icosphere`], [`Mesh::cube`], [`Mesh::grid_plane`]) follow.

use std::collections::HashMap;

use autodiff::Real;
use thiserror::Error;

/// A problem found by [`Mesh::validate`], naming the offending buffer, entry and value.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum MeshError {
    /// No vertices or no faces.
    #[error("empty mesh: {vertices} vertices and {faces} faces (need at least one of each)")]
    Empty {
        /// Number of positions.
        vertices: usize,
        /// Number of triangles.
        faces: usize,
    },
    /// An index in `faces`, `uv_faces` or `normal_faces` points past its attribute buffer.
    #[error("{buffer}[{face}][{corner}] = {index} is out of range for {len} {target}")]
    IndexOutOfRange {
        /// The index buffer: "faces", "uv_faces" or "normal_faces".
        buffer: &'static str,
        /// Triangle number (0-based).
        face: usize,
        /// Corner of that triangle (0, 1 or 2).
        corner: usize,
        /// The bad index.
        index: u32,
        /// Length of the attribute buffer it indexes.
        len: usize,
        /// What the buffer holds: "positions", "uvs" or "normals".
        target: &'static str,
    },
    /// A NaN or infinite coordinate.
    #[error("{attribute}[{index}] = {value} is not finite")]
    NonFinite {
        /// "positions", "uvs", "normals" or "colors".
        attribute: &'static str,
        /// Entry number (0-based).
        index: usize,
        /// The entry, formatted.
        value: String,
    },
    /// `colors` is neither empty nor one per vertex.
    #[error("colors has {colors} entries but the mesh has {vertices} vertices (need one colour per vertex, or none)")]
    ColorCount {
        /// Number of colours.
        colors: usize,
        /// Number of positions.
        vertices: usize,
    },
    /// An attribute index buffer does not have one triangle per face.
    #[error("{buffer} has {got} triangles but faces has {faces} ({buffer} must match faces one to one when {attribute} are given)")]
    FaceCount {
        /// "uv_faces" or "normal_faces".
        buffer: &'static str,
        /// "uvs" or "normals".
        attribute: &'static str,
        /// Triangles in that buffer.
        got: usize,
        /// Triangles in `faces`.
        faces: usize,
    },
}

/// A triangle mesh (see the module docs for the attribute layout).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Mesh<T: Real> {
    /// Vertex positions `[V]` (in file order when loaded from OBJ).
    pub positions: Vec<[T; 3]>,
    /// Triangles `[F]`, 0-based indices into `positions`, counter-clockwise seen from the front.
    pub faces: Vec<[u32; 3]>,
    /// Texture coordinates (empty: none).
    pub uvs: Vec<[T; 2]>,
    /// Triangles indexing `uvs`, one per face (empty when `uvs` is).
    pub uv_faces: Vec<[u32; 3]>,
    /// Normals (empty: none).
    pub normals: Vec<[T; 3]>,
    /// Triangles indexing `normals`, one per face (empty when `normals` is).
    pub normal_faces: Vec<[u32; 3]>,
    /// Per-vertex linear RGB colours, one per position (empty: none).
    pub colors: Vec<[T; 3]>,
}

/// A mesh whose attributes all share `mesh.faces` (see [`Mesh::unified`]).
#[derive(Debug, Clone, PartialEq)]
pub struct UnifiedMesh<T: Real> {
    /// The split mesh: `uv_faces` and `normal_faces` equal `faces` (or are empty), `uvs`,
    /// `normals` and `colors` are per vertex.
    pub mesh: Mesh<T>,
    /// For each vertex of `mesh`, the index of the source position it copies. The first `V`
    /// entries are `0..V` (source vertex `i` stays vertex `i`); split-off copies follow.
    pub position_index: Vec<u32>,
}

impl<T: Real> UnifiedMesh<T> {
    /// Sums per-vertex values of the unified mesh (e.g. position gradients `[V', 3]`) back onto
    /// the source positions (`[V, 3]`, `V = source vertex count`).
    ///
    /// # Panics
    /// If `per_vertex.len()` differs from the unified vertex count.
    pub fn accumulate<const N: usize>(
        &self,
        per_vertex: &[[T; N]],
        source_vertices: usize,
    ) -> Vec<[T; N]> {
        assert_eq!(
            per_vertex.len(),
            self.position_index.len(),
            "accumulate: one value per unified vertex expected"
        );
        let mut out = vec![[T::zero(); N]; source_vertices];
        for (value, &p) in per_vertex.iter().zip(&self.position_index) {
            let acc = &mut out[p as usize];
            for k in 0..N {
                acc[k] += value[k];
            }
        }
        out
    }

    /// Copies per-source-position values (e.g. positions being optimised) onto the unified
    /// vertices.
    pub fn gather<A: Copy>(&self, per_position: &[A]) -> Vec<A> {
        self.position_index
            .iter()
            .map(|&p| per_position[p as usize])
            .collect()
    }
}

fn fmt_entry<T: Real, const N: usize>(v: &[T; N]) -> String {
    let parts: Vec<String> = v.iter().map(|x| format!("{x}")).collect();
    format!("[{}]", parts.join(", "))
}

fn check_finite<T: Real, const N: usize>(
    attribute: &'static str,
    values: &[[T; N]],
) -> Result<(), MeshError> {
    match values.iter().position(|v| v.iter().any(|x| !x.is_finite())) {
        Some(index) => Err(MeshError::NonFinite {
            attribute,
            index,
            value: fmt_entry(&values[index]),
        }),
        None => Ok(()),
    }
}

fn check_indices(
    buffer: &'static str,
    target: &'static str,
    tris: &[[u32; 3]],
    len: usize,
) -> Result<(), MeshError> {
    for (face, tri) in tris.iter().enumerate() {
        for (corner, &index) in tri.iter().enumerate() {
            if index as usize >= len {
                return Err(MeshError::IndexOutOfRange {
                    buffer,
                    face,
                    corner,
                    index,
                    len,
                    target,
                });
            }
        }
    }
    Ok(())
}

fn check_attribute_faces(
    buffer: &'static str,
    attribute: &'static str,
    values_len: usize,
    tris: &[[u32; 3]],
    faces: usize,
) -> Result<(), MeshError> {
    if (values_len > 0 || !tris.is_empty()) && tris.len() != faces {
        return Err(MeshError::FaceCount {
            buffer,
            attribute,
            got: tris.len(),
            faces,
        });
    }
    Ok(())
}

impl<T: Real> Mesh<T> {
    /// A mesh with positions and faces only.
    pub fn new(positions: Vec<[T; 3]>, faces: Vec<[u32; 3]>) -> Self {
        Mesh {
            positions,
            faces,
            ..Default::default()
        }
    }

    /// Sets per-vertex colours (builder style; checked by [`Mesh::validate`]).
    pub fn with_colors(mut self, colors: Vec<[T; 3]>) -> Self {
        self.colors = colors;
        self
    }

    /// Number of positions `V`.
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }

    /// Number of triangles `F`.
    pub fn face_count(&self) -> usize {
        self.faces.len()
    }

    /// Whether texture coordinates are present.
    pub fn has_uvs(&self) -> bool {
        !self.uvs.is_empty()
    }

    /// Whether normals are present.
    pub fn has_normals(&self) -> bool {
        !self.normals.is_empty()
    }

    /// Whether per-vertex colours are present.
    pub fn has_colors(&self) -> bool {
        !self.colors.is_empty()
    }

    /// Checks the mesh: at least one vertex and one face, every index in range, every coordinate
    /// finite, attribute index buffers one triangle per face, colours one per vertex.
    /// Degenerate (zero-area) triangles are allowed; see [`Mesh::degenerate_faces`].
    pub fn validate(&self) -> Result<(), MeshError> {
        let (v, f) = (self.positions.len(), self.faces.len());
        if v == 0 || f == 0 {
            return Err(MeshError::Empty {
                vertices: v,
                faces: f,
            });
        }
        check_finite("positions", &self.positions)?;
        check_indices("faces", "positions", &self.faces, v)?;
        check_attribute_faces("uv_faces", "uvs", self.uvs.len(), &self.uv_faces, f)?;
        check_finite("uvs", &self.uvs)?;
        check_indices("uv_faces", "uvs", &self.uv_faces, self.uvs.len())?;
        check_attribute_faces(
            "normal_faces",
            "normals",
            self.normals.len(),
            &self.normal_faces,
            f,
        )?;
        check_finite("normals", &self.normals)?;
        check_indices(
            "normal_faces",
            "normals",
            &self.normal_faces,
            self.normals.len(),
        )?;
        if !self.colors.is_empty() && self.colors.len() != v {
            return Err(MeshError::ColorCount {
                colors: self.colors.len(),
                vertices: v,
            });
        }
        check_finite("colors", &self.colors)?;
        Ok(())
    }

    /// Indices of the degenerate triangles: a repeated vertex index, or twice the area at most
    /// `4 eps_T` times the squared longest edge (collinear corners up to rounding; `eps_T` is the
    /// machine epsilon of `T`). Computed in f64. Faces with out-of-range indices are skipped
    /// (they are [`Mesh::validate`]'s business). The rasterizer drops such faces; this list is
    /// for diagnostics.
    pub fn degenerate_faces(&self) -> Vec<usize> {
        let tol = 4.0 * T::EPS.to_f64c();
        let get = |i: u32| -> Option<[f64; 3]> {
            self.positions
                .get(i as usize)
                .map(|p| [p[0].to_f64c(), p[1].to_f64c(), p[2].to_f64c()])
        };
        let mut out = Vec::new();
        for (fi, &[a, b, c]) in self.faces.iter().enumerate() {
            let (Some(pa), Some(pb), Some(pc)) = (get(a), get(b), get(c)) else {
                continue;
            };
            if a == b || b == c || a == c {
                out.push(fi);
                continue;
            }
            let sub = |p: [f64; 3], q: [f64; 3]| [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
            let dot = |p: [f64; 3], q: [f64; 3]| p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
            let (e0, e1, e2) = (sub(pb, pa), sub(pc, pa), sub(pc, pb));
            let cr = [
                e0[1] * e1[2] - e0[2] * e1[1],
                e0[2] * e1[0] - e0[0] * e1[2],
                e0[0] * e1[1] - e0[1] * e1[0],
            ];
            let twice_area = dot(cr, cr).sqrt();
            let longest2 = dot(e0, e0).max(dot(e1, e1)).max(dot(e2, e2));
            let proper = twice_area > tol * longest2; // false for NaN coordinates too
            if !proper {
                out.push(fi);
            }
        }
        out
    }

    /// Converts the scalar type (f32 <-> f64; f64 -> f32 rounds to nearest).
    pub fn cast<U: Real>(&self) -> Mesh<U> {
        fn conv<T: Real, U: Real, const N: usize>(v: &[[T; N]]) -> Vec<[U; N]> {
            v.iter()
                .map(|a| a.map(|x| U::from_f64c(x.to_f64c())))
                .collect()
        }
        Mesh {
            positions: conv(&self.positions),
            faces: self.faces.clone(),
            uvs: conv(&self.uvs),
            uv_faces: self.uv_faces.clone(),
            normals: conv(&self.normals),
            normal_faces: self.normal_faces.clone(),
            colors: conv(&self.colors),
        }
    }

    /// Splits vertices whose corners carry different uvs or normals (seams, sharp edges) so one
    /// index buffer serves positions, uvs, normals and colours, as a GPU-style renderer needs.
    ///
    /// Source vertex `i` stays vertex `i` (with the uv/normal of its first use in face order;
    /// unused vertices get zero uv/normal); each further distinct combination becomes a new vertex
    /// appended after the first `V`. [`UnifiedMesh::position_index`] maps every vertex back to its
    /// source position, and [`UnifiedMesh::accumulate`] sums gradients back. A mesh without
    /// seams comes back unchanged (identity mapping). Fails when the mesh does not validate.
    pub fn unified(&self) -> Result<UnifiedMesh<T>, MeshError> {
        self.validate()?;
        const NONE: u32 = u32::MAX;
        let v = self.positions.len();
        let (has_uv, has_n) = (self.has_uvs(), self.has_normals());
        // first[p]: the (uv, normal) attribute pair that source vertex p keeps.
        let mut first: Vec<Option<(u32, u32)>> = vec![None; v];
        let mut extra: HashMap<(u32, u32, u32), u32> = HashMap::new();
        let mut position_index: Vec<u32> = (0..v as u32).collect();
        let mut attrs: Vec<(u32, u32)> = Vec::new(); // attributes of the split-off vertices
        let mut faces = Vec::with_capacity(self.faces.len());
        for (fi, tri) in self.faces.iter().enumerate() {
            let mut out = [0u32; 3];
            for (k, &p) in tri.iter().enumerate() {
                let t = if has_uv { self.uv_faces[fi][k] } else { NONE };
                let n = if has_n {
                    self.normal_faces[fi][k]
                } else {
                    NONE
                };
                out[k] = match first[p as usize] {
                    None => {
                        first[p as usize] = Some((t, n));
                        p
                    }
                    Some(pair) if pair == (t, n) => p,
                    Some(_) => *extra.entry((p, t, n)).or_insert_with(|| {
                        position_index.push(p);
                        attrs.push((t, n));
                        (position_index.len() - 1) as u32
                    }),
                };
            }
            faces.push(out);
        }
        let attr_of = |i: usize| -> (u32, u32) {
            if i < v {
                first[i].unwrap_or((NONE, NONE))
            } else {
                attrs[i - v]
            }
        };
        let count = position_index.len();
        let positions = position_index
            .iter()
            .map(|&p| self.positions[p as usize])
            .collect();
        let uvs = if has_uv {
            (0..count)
                .map(|i| match attr_of(i).0 {
                    NONE => [T::zero(); 2],
                    t => self.uvs[t as usize],
                })
                .collect()
        } else {
            Vec::new()
        };
        let normals = if has_n {
            (0..count)
                .map(|i| match attr_of(i).1 {
                    NONE => [T::zero(); 3],
                    n => self.normals[n as usize],
                })
                .collect()
        } else {
            Vec::new()
        };
        let colors = if self.has_colors() {
            position_index
                .iter()
                .map(|&p| self.colors[p as usize])
                .collect()
        } else {
            Vec::new()
        };
        let uv_faces = if has_uv { faces.clone() } else { Vec::new() };
        let normal_faces = if has_n { faces.clone() } else { Vec::new() };
        Ok(UnifiedMesh {
            mesh: Mesh {
                positions,
                faces,
                uvs,
                uv_faces,
                normals,
                normal_faces,
                colors,
            },
            position_index,
        })
    }

    /// A latitude-longitude sphere of `radius` about the origin with `stacks` rings of faces
    /// from pole to pole (y up) and `slices` around, counter-clockwise seen from outside, with
    /// uvs (`u` around from the +z axis, `v` from 1 at the north pole to 0 at the south)
    /// indexed by `uv_faces`: the seam at `u = 0 / 1` and the poles hold several uvs per
    /// position ([`Mesh::unified`] splits them). No normals or colours.
    pub fn uv_sphere(stacks: usize, slices: usize, radius: T) -> Self {
        use std::f64::consts::{PI, TAU};
        let (stacks, slices) = (stacks.max(2), slices.max(3));
        let r = radius.to_f64c();
        let mut positions = vec![[T::zero(), radius, T::zero()]];
        for i in 1..stacks {
            let th = PI * i as f64 / stacks as f64;
            for j in 0..slices {
                let ph = TAU * j as f64 / slices as f64;
                positions.push(
                    [th.sin() * ph.sin(), th.cos(), th.sin() * ph.cos()]
                        .map(|x| T::from_f64c(r * x)),
                );
            }
        }
        positions.push([T::zero(), -radius, T::zero()]);
        let last = positions.len() as u32 - 1;
        let pid = |i: usize, j: usize| -> u32 {
            match i {
                0 => 0,
                i if i == stacks => last,
                i => (1 + (i - 1) * slices + j % slices) as u32,
            }
        };
        let mut uvs = Vec::with_capacity((stacks + 1) * (slices + 1));
        for i in 0..=stacks {
            for j in 0..=slices {
                uvs.push([
                    T::from_f64c(j as f64 / slices as f64),
                    T::from_f64c(1.0 - i as f64 / stacks as f64),
                ]);
            }
        }
        let tid = |i: usize, j: usize| (i * (slices + 1) + j) as u32;
        let (mut faces, mut uv_faces) = (Vec::new(), Vec::new());
        for i in 0..stacks {
            for j in 0..slices {
                for q in [
                    [(i, j), (i + 1, j), (i + 1, j + 1)],
                    [(i, j), (i + 1, j + 1), (i, j + 1)],
                ] {
                    let f = q.map(|(a, b)| pid(a, b));
                    if f[0] == f[1] || f[1] == f[2] || f[0] == f[2] {
                        continue;
                    }
                    faces.push(f);
                    uv_faces.push(q.map(|(a, b)| tid(a, b)));
                }
            }
        }
        Mesh {
            positions,
            faces,
            uvs,
            uv_faces,
            normals: Vec::new(),
            normal_faces: Vec::new(),
            colors: Vec::new(),
        }
    }

    /// A subdivided icosahedron on the sphere of `radius` about the origin, counter-clockwise
    /// seen from outside: `10 * 4^s + 2` vertices and `20 * 4^s` faces (s = 4: 2562 / 5120,
    /// s = 6: 40962 / 81920). No uvs, normals or colours.
    ///
    /// The construction is exactly that of `peers/scene_gen.py` (same base icosahedron, edge
    /// midpoints appended in lexicographic order of their sorted endpoint pairs, the four child
    /// triangles of all faces grouped by kind, the same f64 arithmetic), so
    /// `Mesh::<f64>::icosphere(4, 1.0)` reproduces the positions and faces of
    /// `peers/scenes/ico5k.obj` bit for bit.
    pub fn icosphere(subdivisions: u32, radius: T) -> Self {
        let p = (1.0 + 5f64.sqrt()) / 2.0;
        let base: [[f64; 3]; 12] = [
            [-1.0, p, 0.0],
            [1.0, p, 0.0],
            [-1.0, -p, 0.0],
            [1.0, -p, 0.0],
            [0.0, -1.0, p],
            [0.0, 1.0, p],
            [0.0, -1.0, -p],
            [0.0, 1.0, -p],
            [p, 0.0, -1.0],
            [p, 0.0, 1.0],
            [-p, 0.0, -1.0],
            [-p, 0.0, 1.0],
        ];
        let normalize = |v: [f64; 3]| {
            // numpy: sqrt((x*x + y*y) + z*z), then a division per component.
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            [v[0] / n, v[1] / n, v[2] / n]
        };
        let mut verts: Vec<[f64; 3]> = base.iter().map(|&v| normalize(v)).collect();
        let mut faces: Vec<[u32; 3]> = vec![
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ];
        for _ in 0..subdivisions {
            let nf = faces.len();
            let key = |a: u32, b: u32| if a < b { (a, b) } else { (b, a) };
            let mut edges: Vec<(u32, u32)> = Vec::with_capacity(3 * nf);
            for &[a, b, c] in &faces {
                edges.push(key(a, b));
                edges.push(key(b, c));
                edges.push(key(c, a));
            }
            edges.sort_unstable();
            edges.dedup();
            let nv = verts.len() as u32;
            for &(a, b) in &edges {
                let (va, vb) = (verts[a as usize], verts[b as usize]);
                verts.push(normalize([
                    0.5 * (va[0] + vb[0]),
                    0.5 * (va[1] + vb[1]),
                    0.5 * (va[2] + vb[2]),
                ]));
            }
            let mid =
                |a: u32, b: u32| nv + edges.binary_search(&key(a, b)).expect("edge listed") as u32;
            let mut next = vec![[0u32; 3]; 4 * nf];
            for (i, &[a, b, c]) in faces.iter().enumerate() {
                let (m01, m12, m20) = (mid(a, b), mid(b, c), mid(c, a));
                next[i] = [a, m01, m20];
                next[nf + i] = [b, m12, m01];
                next[2 * nf + i] = [c, m20, m12];
                next[3 * nf + i] = [m01, m12, m20];
            }
            faces = next;
        }
        let r = radius.to_f64c();
        let positions = verts
            .iter()
            .map(|v| v.map(|x| T::from_f64c(x * r)))
            .collect();
        Mesh::new(positions, faces)
    }

    /// The cube `[-1, 1]^3` with sharp edges: 8 shared positions (watertight), 12 triangles
    /// counter-clockwise seen from outside, 6 face normals indexed by `normal_faces`, and uvs
    /// (each square face maps to the unit square) indexed by `uv_faces`. [`Mesh::unified`] turns
    /// it into the usual 24-vertex cube.
    pub fn cube() -> Self {
        let pos_index =
            |x: bool, y: bool, z: bool| (x as u32) | ((y as u32) << 1) | ((z as u32) << 2);
        let positions = (0..8u32)
            .map(|i| {
                let s = |bit: u32| if i & bit != 0 { T::one() } else { -T::one() };
                [s(1), s(2), s(4)]
            })
            .collect();
        let uvs = vec![
            [T::zero(), T::zero()],
            [T::one(), T::zero()],
            [T::one(), T::one()],
            [T::zero(), T::one()],
        ];
        let mut normals = Vec::new();
        let (mut faces, mut uv_faces, mut normal_faces) = (Vec::new(), Vec::new(), Vec::new());
        for axis in 0..3usize {
            for positive in [false, true] {
                // Tangent axes u, v with u x v = +axis; corners (-,-), (+,-), (+,+), (-,+) run
                // counter-clockwise about +axis, reversed for the negative side.
                let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
                // On the negative side the texture's u runs along -u so that it is not mirrored
                // when seen from outside.
                let mut quad = [(false, false), (true, false), (true, true), (false, true)];
                if !positive {
                    quad.reverse();
                }
                let corners: Vec<u32> = quad
                    .iter()
                    .map(|&(su, sv)| {
                        let mut bits = [false; 3];
                        bits[axis] = positive;
                        bits[u] = su;
                        bits[v] = sv;
                        pos_index(bits[0], bits[1], bits[2])
                    })
                    .collect();
                let uv_ids: Vec<u32> = quad
                    .iter()
                    .map(|&(su, sv)| match (su == positive, sv) {
                        (false, false) => 0,
                        (true, false) => 1,
                        (true, true) => 2,
                        (false, true) => 3,
                    })
                    .collect();
                let n = normals.len() as u32;
                let mut normal = [T::zero(); 3];
                normal[axis] = if positive { T::one() } else { -T::one() };
                normals.push(normal);
                for (a, b, c) in [(0, 1, 2), (0, 2, 3)] {
                    faces.push([corners[a], corners[b], corners[c]]);
                    uv_faces.push([uv_ids[a], uv_ids[b], uv_ids[c]]);
                    normal_faces.push([n, n, n]);
                }
            }
        }
        Mesh {
            positions,
            faces,
            uvs,
            uv_faces,
            normals,
            normal_faces,
            colors: Vec::new(),
        }
    }

    /// The square `[-1, 1]^2` in the plane z = 0 cut into `n x n` cells of two triangles each,
    /// facing +z (counter-clockwise seen from +z): `(n+1)^2` vertices in row-major order (y, then
    /// x, both increasing), `2 n^2` faces, per-vertex uvs `((x+1)/2, (y+1)/2)` and the single
    /// normal (0, 0, 1). `n = 0` is treated as 1.
    pub fn grid_plane(n: u32) -> Self {
        let n = n.max(1);
        let m = n + 1;
        let coord = |i: u32| T::from_f64c(2.0 * i as f64 / n as f64 - 1.0);
        let unit = |i: u32| T::from_f64c(i as f64 / n as f64);
        let mut positions = Vec::with_capacity((m * m) as usize);
        let mut uvs = Vec::with_capacity((m * m) as usize);
        for j in 0..m {
            for i in 0..m {
                positions.push([coord(i), coord(j), T::zero()]);
                uvs.push([unit(i), unit(j)]);
            }
        }
        let mut faces = Vec::with_capacity((2 * n * n) as usize);
        for j in 0..n {
            for i in 0..n {
                let v00 = j * m + i;
                let (v10, v01) = (v00 + 1, v00 + m);
                let v11 = v01 + 1;
                faces.push([v00, v10, v11]);
                faces.push([v00, v11, v01]);
            }
        }
        Mesh {
            positions,
            uv_faces: faces.clone(),
            normal_faces: vec![[0, 0, 0]; faces.len()],
            faces,
            uvs,
            normals: vec![[T::zero(), T::zero(), T::one()]],
            colors: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn signed_volume(m: &Mesh<f64>) -> f64 {
        m.faces
            .iter()
            .map(|&[a, b, c]| {
                let (p, q, r) = (
                    m.positions[a as usize],
                    m.positions[b as usize],
                    m.positions[c as usize],
                );
                p[0] * (q[1] * r[2] - q[2] * r[1]) - p[1] * (q[0] * r[2] - q[2] * r[0])
                    + p[2] * (q[0] * r[1] - q[1] * r[0])
            })
            .sum::<f64>()
            / 6.0
    }

    #[test]
    fn icosphere_counts_orientation_and_radius() {
        for (s, v, f) in [(0, 12, 20), (1, 42, 80), (4, 2562, 5120)] {
            let m = Mesh::<f64>::icosphere(s, 2.0);
            assert_eq!((m.vertex_count(), m.face_count()), (v, f));
            m.validate().unwrap();
            assert!(m.degenerate_faces().is_empty());
            assert!(signed_volume(&m) > 0.0);
            for p in &m.positions {
                let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
                assert!((r - 2.0).abs() < 1e-12);
            }
            // Closed and consistently oriented: every directed edge appears once.
            let mut directed = std::collections::HashSet::new();
            for &[a, b, c] in &m.faces {
                for e in [(a, b), (b, c), (c, a)] {
                    assert!(directed.insert(e), "edge {e:?} twice");
                }
            }
            for &(a, b) in &directed {
                assert!(directed.contains(&(b, a)));
            }
        }
    }

    #[test]
    fn icosphere_level6_counts() {
        let m = Mesh::<f32>::icosphere(6, 1.0);
        assert_eq!((m.vertex_count(), m.face_count()), (40962, 81920));
    }

    #[test]
    fn cube_is_closed_ccw_and_unifies_to_24_vertices() {
        let m = Mesh::<f64>::cube();
        m.validate().unwrap();
        assert_eq!((m.vertex_count(), m.face_count()), (8, 12));
        assert!((signed_volume(&m) - 8.0).abs() < 1e-12);
        // Each face normal agrees with the winding.
        for (fi, &[a, b, c]) in m.faces.iter().enumerate() {
            let (p, q, r) = (
                m.positions[a as usize],
                m.positions[b as usize],
                m.positions[c as usize],
            );
            let e1 = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
            let e2 = [r[0] - p[0], r[1] - p[1], r[2] - p[2]];
            let cr = [
                e1[1] * e2[2] - e1[2] * e2[1],
                e1[2] * e2[0] - e1[0] * e2[2],
                e1[0] * e2[1] - e1[1] * e2[0],
            ];
            let n = m.normals[m.normal_faces[fi][0] as usize];
            assert!(
                cr[0] * n[0] + cr[1] * n[1] + cr[2] * n[2] > 0.0,
                "face {fi}"
            );
            // uvs wind the same way, i.e. textures are not mirrored seen from outside.
            let [ta, tb, tc] = m.uv_faces[fi].map(|t| m.uvs[t as usize]);
            let uv_area = (tb[0] - ta[0]) * (tc[1] - ta[1]) - (tb[1] - ta[1]) * (tc[0] - ta[0]);
            assert!(uv_area > 0.0, "face {fi}: uv area {uv_area}");
        }
        let u = m.unified().unwrap();
        assert_eq!(u.mesh.vertex_count(), 24);
        assert_eq!(u.mesh.face_count(), 12);
        u.mesh.validate().unwrap();
        assert_eq!(u.mesh.uv_faces, u.mesh.faces);
        assert_eq!(u.mesh.normal_faces, u.mesh.faces);
        for (fi, tri) in u.mesh.faces.iter().enumerate() {
            for (k, &corner) in tri.iter().enumerate() {
                let i = corner as usize;
                assert_eq!(u.mesh.positions[i], m.positions[m.faces[fi][k] as usize]);
                assert_eq!(u.mesh.uvs[i], m.uvs[m.uv_faces[fi][k] as usize]);
                assert_eq!(u.mesh.normals[i], m.normals[m.normal_faces[fi][k] as usize]);
                assert_eq!(u.position_index[i], m.faces[fi][k]);
            }
        }
        assert_eq!(&u.position_index[..8], &[0, 1, 2, 3, 4, 5, 6, 7]);
        // Each position is split 3 ways, so the gradients of the copies add up.
        let ones = vec![[1.0f64; 3]; 24];
        assert_eq!(u.accumulate(&ones, 8), vec![[3.0; 3]; 8]);
        assert_eq!(u.gather(&m.positions), u.mesh.positions);
    }

    #[test]
    fn unified_without_seams_is_identity() {
        let m = Mesh::<f64>::grid_plane(3).with_colors(vec![[0.5; 3]; 16]);
        m.validate().unwrap();
        let u = m.unified().unwrap();
        let mut expected = m.clone();
        expected.normals = vec![[0.0, 0.0, 1.0]; m.vertex_count()];
        expected.normal_faces = m.faces.clone();
        assert_eq!(u.mesh, expected);
        assert_eq!(u.position_index, (0..16).collect::<Vec<u32>>());
    }

    #[test]
    fn grid_plane_counts_and_facing() {
        let m = Mesh::<f32>::grid_plane(4);
        m.validate().unwrap();
        assert_eq!((m.vertex_count(), m.face_count()), (25, 32));
        for &[a, b, c] in &m.faces {
            let (p, q, r) = (
                m.positions[a as usize],
                m.positions[b as usize],
                m.positions[c as usize],
            );
            let z = (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]);
            assert!(z > 0.0);
        }
        assert_eq!(Mesh::<f64>::grid_plane(0).face_count(), 2);
    }

    #[test]
    fn validate_reports_the_bad_entry() {
        let good = Mesh::<f64>::new(
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            vec![[0, 1, 2]],
        );
        good.validate().unwrap();

        let e = Mesh::<f64>::new(vec![], vec![]).validate().unwrap_err();
        assert_eq!(
            e,
            MeshError::Empty {
                vertices: 0,
                faces: 0
            }
        );
        assert!(e.to_string().contains("0 vertices"));

        let mut m = good.clone();
        m.faces.push([0, 2, 7]);
        let e = m.validate().unwrap_err();
        assert_eq!(
            e.to_string(),
            "faces[1][2] = 7 is out of range for 3 positions"
        );

        let mut m = good.clone();
        m.positions[1][2] = f64::NAN;
        let e = m.validate().unwrap_err();
        assert!(
            matches!(
                e,
                MeshError::NonFinite {
                    attribute: "positions",
                    index: 1,
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("positions[1]"));

        let m = good.clone().with_colors(vec![[1.0; 3]; 2]);
        assert_eq!(
            m.validate().unwrap_err(),
            MeshError::ColorCount {
                colors: 2,
                vertices: 3
            }
        );

        let mut m = good.clone();
        m.uvs = vec![[0.0, 0.0]];
        assert!(matches!(
            m.validate().unwrap_err(),
            MeshError::FaceCount {
                buffer: "uv_faces",
                got: 0,
                faces: 1,
                ..
            }
        ));
        m.uv_faces = vec![[0, 0, 1]];
        assert_eq!(
            m.validate().unwrap_err().to_string(),
            "uv_faces[0][2] = 1 is out of range for 1 uvs"
        );

        let mut m = good.clone();
        m.normal_faces = vec![[0, 0, 0]];
        assert!(matches!(
            m.validate().unwrap_err(),
            MeshError::IndexOutOfRange {
                buffer: "normal_faces",
                len: 0,
                ..
            }
        ));
        m.normal_faces.push([0, 0, 0]);
        assert!(matches!(
            m.validate().unwrap_err(),
            MeshError::FaceCount {
                buffer: "normal_faces",
                got: 2,
                ..
            }
        ));
        m.normal_faces.pop();
        m.normals = vec![[0.0, 0.0, f64::INFINITY]];
        assert!(matches!(
            m.validate().unwrap_err(),
            MeshError::NonFinite {
                attribute: "normals",
                index: 0,
                ..
            }
        ));
        assert!(m.unified().is_err());
    }

    #[test]
    fn degenerate_faces_are_listed_not_rejected() {
        let m = Mesh::<f64>::new(
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [2.0, 0.0, 0.0],
                [0.1, 0.0, 0.0],
            ],
            vec![[0, 1, 2], [0, 1, 3], [0, 0, 2], [0, 4, 1], [1, 2, 3]],
        );
        m.validate().unwrap();
        assert_eq!(m.degenerate_faces(), vec![1, 2, 3]);
    }

    #[test]
    fn cast_round_trips_through_f32() {
        let m = Mesh::<f64>::cube();
        let m32: Mesh<f32> = m.cast();
        assert_eq!(m32.positions[7], [1.0f32, 1.0, 1.0]);
        assert_eq!(m32.cast::<f64>(), m);
        let ico = Mesh::<f64>::icosphere(1, 1.0);
        let back = ico.cast::<f32>().cast::<f64>();
        for (a, b) in ico.positions.iter().zip(&back.positions) {
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() < 1e-7);
            }
        }
    }
}
