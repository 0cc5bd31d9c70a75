//! Wavefront OBJ meshes: `v x y z [w | r g b]`, `vt u [v [w]]`, `vn x y z` and `f` lines
//! (`v`, `v/vt`, `v//vn`, `v/vt/vn` corners, 1-based or negative relative indices, polygons
//! fan-triangulated), read into a [`Mesh`] with **vertex order equal to the file's `v` order**.
//!
//! # Why not `tobj::load_obj` directly
//! The syntax accepted is tobj's (docs/CONVENTIONS.md: "OBJ via tobj"), and the tests check that the
//! triangles agree with tobj's on the peer meshes. But tobj 4 cannot give what Tapestry needs:
//! without `single_index` it still renumbers positions per object in order of first use (so a
//! `[V, 3]` gradient would not be in file order, and unused vertices vanish), it stores `f32`
//! unless built with its `use_f64` feature (the peer meshes carry 17 digits so that f64 loading
//! is exact), and its errors carry no line numbers. So this module parses the few OBJ statements
//! itself, in one pass, in the precision of `T`:
//! - positions (and colours, when every `v` line has them) in file order, unused ones kept;
//! - `vt` / `vn` kept with their own index buffers (`uv_faces`, `normal_faces`) when the faces
//!   use them; a file whose faces mix corners with and without `vt` (or `vn`) is an error;
//! - `v x y z w` divides by `w` (as tobj does); points (`p`), lines (`l`), groups, objects,
//!   materials and smoothing groups are ignored;
//! - every malformed line is an [`ObjError`] naming the file, the line and the bad token.

use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Write};
use std::path::Path;

use autodiff::Real;
use thiserror::Error;

use crate::mesh::{Mesh, MeshError};

/// Errors of OBJ reading and writing; `file` is the path (or `<string>`), `line` 1-based.
#[derive(Debug, Error)]
pub enum ObjError {
    /// The file cannot be opened.
    #[error("{file}: cannot open OBJ file: {source}")]
    Open {
        /// File name.
        file: String,
        /// Underlying error.
        source: io::Error,
    },
    /// Reading failed part-way (I/O error, invalid UTF-8).
    #[error("{file}:{line}: cannot read line: {source}")]
    Read {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// Underlying error.
        source: io::Error,
    },
    /// A token that should be a number is not one.
    #[error("{file}:{line}: bad number '{token}' in a '{keyword}' statement")]
    BadNumber {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// `v`, `vt` or `vn`.
        keyword: &'static str,
        /// The token.
        token: String,
    },
    /// A number is NaN or infinite.
    #[error("{file}:{line}: non-finite number '{token}' in a '{keyword}' statement")]
    NonFinite {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// `v`, `vt` or `vn`.
        keyword: &'static str,
        /// The token.
        token: String,
    },
    /// A statement has the wrong number of values.
    #[error("{file}:{line}: '{keyword}' has {got} values, expected {expected}")]
    ValueCount {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// `v`, `vt` or `vn`.
        keyword: &'static str,
        /// Values found.
        got: usize,
        /// What is allowed.
        expected: &'static str,
    },
    /// `v x y z w` with `w = 0`.
    #[error("{file}:{line}: 'v' has homogeneous coordinate w = 0")]
    ZeroW {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
    },
    /// A face corner that is not `v`, `v/vt`, `v//vn` or `v/vt/vn` with non-zero integers.
    #[error("{file}:{line}: bad face corner '{token}': {reason}")]
    BadIndex {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// The corner token.
        token: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// A face index points to no element.
    #[error(
        "{file}:{line}: '{kind}' index {index} is out of range: {count} '{kind}' lines defined"
    )]
    IndexOutOfRange {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// The statement indexed: "v", "vt" or "vn".
        kind: &'static str,
        /// The index as written in the file.
        index: i64,
        /// How many such elements exist (before this line, for negative indices).
        count: usize,
    },
    /// A face with fewer than 3 corners.
    #[error("{file}:{line}: face has {got} corner(s), need at least 3")]
    TooFewCorners {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// Corners found.
        got: usize,
    },
    /// Faces (or vertices) disagree on whether an attribute is present.
    #[error("{file}:{line}: {what}")]
    Inconsistent {
        /// File name.
        file: String,
        /// Line number.
        line: usize,
        /// Description.
        what: String,
    },
    /// The file defines no faces.
    #[error("{file}: no faces ('f' lines) found ({vertices} vertices)")]
    NoFaces {
        /// File name.
        file: String,
        /// Number of `v` lines.
        vertices: usize,
    },
    /// More vertices than `u32` indices can address.
    #[error("{file}: {count} vertices, more than u32 indices can address")]
    TooManyVertices {
        /// File name.
        file: String,
        /// Number of `v` lines.
        count: usize,
    },
    /// The parsed mesh does not validate (should not happen after the line checks).
    #[error("{file}: {source}")]
    Mesh {
        /// File name.
        file: String,
        /// The mesh problem.
        source: MeshError,
    },
    /// Writing failed.
    #[error("{file}: cannot write OBJ file: {source}")]
    Write {
        /// File name.
        file: String,
        /// Underlying error.
        source: io::Error,
    },
}

/// Loads an OBJ file (see the module docs). Relative paths are relative to the process's
/// working directory.
pub fn load_obj<T: Real>(path: impl AsRef<Path>) -> Result<Mesh<T>, ObjError> {
    let path = path.as_ref();
    let file = path.display().to_string();
    let f = File::open(path).map_err(|source| ObjError::Open {
        file: file.clone(),
        source,
    })?;
    read_obj(BufReader::new(f), &file)
}

/// Parses OBJ text held in memory; errors name the file `<string>`.
pub fn parse_obj_str<T: Real>(text: &str) -> Result<Mesh<T>, ObjError> {
    read_obj(text.as_bytes(), "<string>")
}

/// A parsed number in the precision of `T`, as f64 (exact for both types).
fn parse_real<T: Real>(token: &str) -> Option<f64> {
    if T::NAME == "f32" {
        token.parse::<f32>().ok().map(f64::from)
    } else {
        token.parse::<f64>().ok()
    }
}

/// A face corner's indices resolved to 0-based, `None` where absent.
#[derive(Clone, Copy)]
struct Corner {
    v: u32,
    vt: Option<u32>,
    vn: Option<u32>,
}

/// An index that referred past the elements defined so far (legal in tobj; checked at the end).
struct ForwardRef {
    line: usize,
    kind: &'static str,
    index: i64,
}

struct Parser<'a, T: Real> {
    file: &'a str,
    line: usize,
    positions: Vec<[T; 3]>,
    colors: Vec<[T; 3]>,
    /// Line of the first `v` statement and whether it had a colour.
    color_mode: Option<(usize, bool)>,
    uvs: Vec<[T; 2]>,
    normals: Vec<[T; 3]>,
    faces: Vec<[u32; 3]>,
    uv_faces: Vec<[u32; 3]>,
    normal_faces: Vec<[u32; 3]>,
    /// Line of the first face and whether it had (vt, vn).
    face_mode: Option<(usize, bool, bool)>,
    forward: Vec<ForwardRef>,
    corners: Vec<Corner>,
}

impl<T: Real> Parser<'_, T> {
    fn numbers<const N: usize>(
        &self,
        keyword: &'static str,
        tokens: &[&str],
        allowed: &[usize],
        expected: &'static str,
    ) -> Result<[f64; N], ObjError> {
        if !allowed.contains(&tokens.len()) {
            return Err(ObjError::ValueCount {
                file: self.file.to_string(),
                line: self.line,
                keyword,
                got: tokens.len(),
                expected,
            });
        }
        let mut out = [0.0; N];
        for (k, tok) in tokens.iter().enumerate() {
            let x = parse_real::<T>(tok).ok_or_else(|| ObjError::BadNumber {
                file: self.file.to_string(),
                line: self.line,
                keyword,
                token: tok.to_string(),
            })?;
            if !x.is_finite() {
                return Err(ObjError::NonFinite {
                    file: self.file.to_string(),
                    line: self.line,
                    keyword,
                    token: tok.to_string(),
                });
            }
            out[k] = x;
        }
        Ok(out)
    }

    fn vertex(&mut self, tokens: &[&str]) -> Result<(), ObjError> {
        let vals: [f64; 6] = self.numbers(
            "v",
            tokens,
            &[3, 4, 6],
            "3 (x y z), 4 (x y z w) or 6 (x y z r g b)",
        )?;
        let has_color = tokens.len() == 6;
        match self.color_mode {
            None => self.color_mode = Some((self.line, has_color)),
            Some((first, mode)) if mode != has_color => {
                let (with, without) = if has_color {
                    (self.line, first)
                } else {
                    (first, self.line)
                };
                return Err(ObjError::Inconsistent {
                    file: self.file.to_string(),
                    line: self.line,
                    what: format!(
                        "vertex colours must be given for all vertices or none: the 'v' on line {with} has r g b, the one on line {without} has not"
                    ),
                });
            }
            Some(_) => {}
        }
        let mut p = [vals[0], vals[1], vals[2]];
        if tokens.len() == 4 {
            let w = vals[3];
            if w == 0.0 {
                return Err(ObjError::ZeroW {
                    file: self.file.to_string(),
                    line: self.line,
                });
            }
            p = p.map(|x| x / w);
        }
        self.positions.push(p.map(T::from_f64c));
        if has_color {
            self.colors
                .push([vals[3], vals[4], vals[5]].map(T::from_f64c));
        }
        Ok(())
    }

    /// Resolves one OBJ index (1-based or negative) against `count` elements defined so far.
    fn index(
        &mut self,
        token: &str,
        part: &str,
        kind: &'static str,
        count: usize,
    ) -> Result<u32, ObjError> {
        let (file, line) = (self.file, self.line);
        let bad = |reason| ObjError::BadIndex {
            file: file.to_string(),
            line,
            token: token.to_string(),
            reason,
        };
        let x: i64 = part.parse().map_err(|_| bad("indices must be integers"))?;
        let resolved = match x {
            0 => return Err(bad("OBJ indices start at 1 (0 is invalid)")),
            x if x < 0 => count as i64 + x,
            x => x - 1,
        };
        if resolved < 0 {
            return Err(ObjError::IndexOutOfRange {
                file: file.to_string(),
                line,
                kind,
                index: x,
                count,
            });
        }
        if resolved > u32::MAX as i64 {
            return Err(bad("index too large"));
        }
        if resolved as usize >= count {
            self.forward.push(ForwardRef {
                line,
                kind,
                index: x,
            });
        }
        Ok(resolved as u32)
    }

    fn face(&mut self, tokens: &[&str]) -> Result<(), ObjError> {
        if tokens.len() < 3 {
            return Err(ObjError::TooFewCorners {
                file: self.file.to_string(),
                line: self.line,
                got: tokens.len(),
            });
        }
        let (file, line) = (self.file, self.line);
        let mut corners = std::mem::take(&mut self.corners);
        corners.clear();
        for &tok in tokens {
            let parts: Vec<&str> = tok.split('/').collect();
            let bad = |reason| ObjError::BadIndex {
                file: file.to_string(),
                line,
                token: tok.to_string(),
                reason,
            };
            if parts.len() > 3 {
                return Err(bad("expected v, v/vt, v//vn or v/vt/vn"));
            }
            if parts[0].is_empty() {
                return Err(bad("the vertex index is missing"));
            }
            if parts.len() == 2 && parts[1].is_empty() {
                return Err(bad("empty texture coordinate index"));
            }
            let v = self.index(tok, parts[0], "v", self.positions.len())?;
            let vt = match parts.get(1) {
                Some(s) if !s.is_empty() => Some(self.index(tok, s, "vt", self.uvs.len())?),
                _ => None,
            };
            let vn = match parts.get(2) {
                Some(s) if !s.is_empty() => Some(self.index(tok, s, "vn", self.normals.len())?),
                Some(_) => return Err(bad("empty normal index")),
                None => None,
            };
            corners.push(Corner { v, vt, vn });
        }
        let has_vt = corners[0].vt.is_some();
        let has_vn = corners[0].vn.is_some();
        if corners
            .iter()
            .any(|c| c.vt.is_some() != has_vt || c.vn.is_some() != has_vn)
        {
            return Err(ObjError::Inconsistent {
                file: self.file.to_string(),
                line: self.line,
                what: "face mixes corners with and without texture coordinates or normals".into(),
            });
        }
        match self.face_mode {
            None => self.face_mode = Some((self.line, has_vt, has_vn)),
            Some((first, t, n)) if (t, n) != (has_vt, has_vn) => {
                let (what, this_has) = if t != has_vt {
                    ("texture coordinates (vt)", has_vt)
                } else {
                    ("normals (vn)", has_vn)
                };
                let (with, without) = if this_has {
                    (line, first)
                } else {
                    (first, line)
                };
                return Err(ObjError::Inconsistent {
                    file: file.to_string(),
                    line,
                    what: format!(
                        "faces must all use {what} or none: the face on line {with} does, the one on line {without} does not"
                    ),
                });
            }
            Some(_) => {}
        }
        for i in 1..corners.len() - 1 {
            let tri = [corners[0], corners[i], corners[i + 1]];
            self.faces.push(tri.map(|c| c.v));
            if has_vt {
                self.uv_faces.push(tri.map(|c| c.vt.unwrap_or(0)));
            }
            if has_vn {
                self.normal_faces.push(tri.map(|c| c.vn.unwrap_or(0)));
            }
        }
        self.corners = corners;
        Ok(())
    }

    fn statement(&mut self, text: &str) -> Result<(), ObjError> {
        let text = text.split('#').next().unwrap_or("");
        let mut it = text.split_whitespace();
        let Some(keyword) = it.next() else {
            return Ok(());
        };
        let tokens: Vec<&str> = it.collect();
        match keyword {
            "v" => self.vertex(&tokens),
            "vt" => {
                let vals: [f64; 3] =
                    self.numbers("vt", &tokens, &[1, 2, 3], "1 to 3 (u [v [w]])")?;
                self.uvs.push([vals[0], vals[1]].map(T::from_f64c));
                Ok(())
            }
            "vn" => {
                let vals: [f64; 3] = self.numbers("vn", &tokens, &[3], "3 (x y z)")?;
                self.normals.push(vals.map(T::from_f64c));
                Ok(())
            }
            "f" => self.face(&tokens),
            // o, g, s, usemtl, mtllib, l, p, vp and anything else: not geometry we keep.
            _ => Ok(()),
        }
    }

    fn finish(mut self) -> Result<Mesh<T>, ObjError> {
        let file = self.file.to_string();
        if self.positions.len() > u32::MAX as usize {
            return Err(ObjError::TooManyVertices {
                file,
                count: self.positions.len(),
            });
        }
        for r in &self.forward {
            let count = match r.kind {
                "v" => self.positions.len(),
                "vt" => self.uvs.len(),
                _ => self.normals.len(),
            };
            if r.index as usize > count {
                return Err(ObjError::IndexOutOfRange {
                    file,
                    line: r.line,
                    kind: r.kind,
                    index: r.index,
                    count,
                });
            }
        }
        if self.faces.is_empty() {
            return Err(ObjError::NoFaces {
                file,
                vertices: self.positions.len(),
            });
        }
        let (has_vt, has_vn) = self
            .face_mode
            .map(|(_, t, n)| (t, n))
            .unwrap_or((false, false));
        if !has_vt {
            self.uvs.clear();
        }
        if !has_vn {
            self.normals.clear();
        }
        let mesh = Mesh {
            positions: self.positions,
            faces: self.faces,
            uvs: self.uvs,
            uv_faces: self.uv_faces,
            normals: self.normals,
            normal_faces: self.normal_faces,
            colors: self.colors,
        };
        mesh.validate()
            .map_err(|source| ObjError::Mesh { file, source })?;
        Ok(mesh)
    }
}

/// Parses OBJ text from any reader; `file` names the source in error messages.
pub fn read_obj<T: Real, R: BufRead>(reader: R, file: &str) -> Result<Mesh<T>, ObjError> {
    let mut p = Parser::<T> {
        file,
        line: 0,
        positions: Vec::new(),
        colors: Vec::new(),
        color_mode: None,
        uvs: Vec::new(),
        normals: Vec::new(),
        faces: Vec::new(),
        uv_faces: Vec::new(),
        normal_faces: Vec::new(),
        face_mode: None,
        forward: Vec::new(),
        corners: Vec::new(),
    };
    for (i, line) in reader.lines().enumerate() {
        p.line = i + 1;
        let line = line.map_err(|source| ObjError::Read {
            file: file.to_string(),
            line: i + 1,
            source,
        })?;
        p.statement(&line)?;
    }
    p.finish()
}

/// Writes a mesh as OBJ: `v x y z [r g b]` (shortest round-trip decimals, so f64 and f32 values
/// read back bit for bit), `vt`, `vn`, and 1-based `f` lines with the matching corner form.
pub fn write_obj_to<T: Real, W: Write>(mut w: W, mesh: &Mesh<T>) -> io::Result<()> {
    let num = |x: T| -> String {
        // Debug of f32/f64 is the shortest string that parses back to the same value.
        if T::NAME == "f32" {
            format!("{:?}", x.to_f64c() as f32)
        } else {
            format!("{:?}", x.to_f64c())
        }
    };
    let has_colors = mesh.colors.len() == mesh.positions.len() && mesh.has_colors();
    for (i, p) in mesh.positions.iter().enumerate() {
        write!(w, "v {} {} {}", num(p[0]), num(p[1]), num(p[2]))?;
        if has_colors {
            let c = mesh.colors[i];
            write!(w, " {} {} {}", num(c[0]), num(c[1]), num(c[2]))?;
        }
        writeln!(w)?;
    }
    let has_vt = mesh.has_uvs() && mesh.uv_faces.len() == mesh.faces.len();
    let has_vn = mesh.has_normals() && mesh.normal_faces.len() == mesh.faces.len();
    if has_vt {
        for t in &mesh.uvs {
            writeln!(w, "vt {} {}", num(t[0]), num(t[1]))?;
        }
    }
    if has_vn {
        for n in &mesh.normals {
            writeln!(w, "vn {} {} {}", num(n[0]), num(n[1]), num(n[2]))?;
        }
    }
    for (fi, f) in mesh.faces.iter().enumerate() {
        write!(w, "f")?;
        for (k, &v) in f.iter().enumerate() {
            let v = v + 1;
            match (has_vt, has_vn) {
                (false, false) => write!(w, " {v}")?,
                (true, false) => write!(w, " {v}/{}", mesh.uv_faces[fi][k] + 1)?,
                (false, true) => write!(w, " {v}//{}", mesh.normal_faces[fi][k] + 1)?,
                (true, true) => write!(
                    w,
                    " {v}/{}/{}",
                    mesh.uv_faces[fi][k] + 1,
                    mesh.normal_faces[fi][k] + 1
                )?,
            }
        }
        writeln!(w)?;
    }
    w.flush()
}

/// Writes a mesh to an OBJ file (see [`write_obj_to`]).
pub fn write_obj<T: Real>(path: impl AsRef<Path>, mesh: &Mesh<T>) -> Result<(), ObjError> {
    let path = path.as_ref();
    let err = |source| ObjError::Write {
        file: path.display().to_string(),
        source,
    };
    let f = File::create(path).map_err(err)?;
    write_obj_to(BufWriter::new(f), mesh).map_err(err)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> ObjError {
        parse_obj_str::<f64>(text).unwrap_err()
    }

    #[test]
    fn parses_all_corner_forms_polygons_and_negative_indices() {
        let text = "\
# a quad and a pentagon
o first
v 0 0 0 1 0 0
v 1 0 0 0 1 0
v 1 1 0 0 0 1
v 0 1 0 0.5 0.5 0.5
v 0.5 2 0 1 1 1
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 1
vn 0 0 1
g second
usemtl stuff
s off
f 1/1/1 2/2/1 3/3/1 4/4/1
f -5/-5/-1 -4/-4/-1 -3/-3/-1 -1/-1/-1 -2/-2/-1
l 1 2
";
        let m = parse_obj_str::<f64>(text).unwrap();
        assert_eq!(m.vertex_count(), 5);
        assert_eq!(m.colors[3], [0.5, 0.5, 0.5]);
        assert_eq!(
            m.faces,
            vec![[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 4], [0, 4, 3]]
        );
        assert_eq!(m.uv_faces, m.faces);
        assert_eq!(m.normal_faces, vec![[0, 0, 0]; 5]);
        assert_eq!(m.uvs[4], [0.5, 1.0]);
    }

    #[test]
    fn unused_attributes_dropped_unused_vertices_kept_w_divides() {
        let m = parse_obj_str::<f32>(
            "v 2 4 6 2\nv 1 0 0\nv 0 1 0\nv 9 9 9\nvt 0 0\nvn 0 0 1\nf 1 2 3\n",
        )
        .unwrap();
        assert_eq!(m.vertex_count(), 4);
        assert_eq!(m.positions[0], [1.0, 2.0, 3.0]);
        assert!(m.uvs.is_empty() && m.uv_faces.is_empty());
        assert!(m.normals.is_empty() && m.normal_faces.is_empty());
        assert!(m.colors.is_empty());
        // v//vn form, forward references are fine when resolved by the end.
        let m = parse_obj_str::<f64>("f 1//1 2//1 3//1\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\n")
            .unwrap();
        assert_eq!(m.normal_faces, vec![[0, 0, 0]]);
        assert!(m.uvs.is_empty());
    }

    #[test]
    fn malformed_files_are_typed_errors_with_line_numbers() {
        let e = err("v 0 0 0\nv 1 x 0\n");
        assert!(
            matches!(&e, ObjError::BadNumber { line: 2, keyword: "v", token, .. } if token == "x"),
            "{e}"
        );
        assert_eq!(
            e.to_string(),
            "<string>:2: bad number 'x' in a 'v' statement"
        );

        let e = err("v 0 0\n");
        assert!(
            matches!(
                e,
                ObjError::ValueCount {
                    line: 1,
                    got: 2,
                    ..
                }
            ),
            "{e}"
        );
        let e = err("v 0 0 0 1 1\n");
        assert!(matches!(e, ObjError::ValueCount { got: 5, .. }), "{e}");
        assert!(matches!(
            err("v 0 0 0 0\n"),
            ObjError::ZeroW { line: 1, .. }
        ));
        assert!(matches!(
            err("v nan 0 0\n"),
            ObjError::NonFinite { line: 1, .. }
        ));
        assert!(matches!(
            err("vn 0 0\n"),
            ObjError::ValueCount { keyword: "vn", .. }
        ));
        assert!(matches!(
            err("vt a b\n"),
            ObjError::BadNumber { keyword: "vt", .. }
        ));

        let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        let e = err(&format!("{tri}f 1 2 4\n"));
        assert!(
            matches!(
                e,
                ObjError::IndexOutOfRange {
                    line: 4,
                    index: 4,
                    count: 3,
                    kind: "v",
                    ..
                }
            ),
            "{e}"
        );
        assert_eq!(
            e.to_string(),
            "<string>:4: 'v' index 4 is out of range: 3 'v' lines defined"
        );
        let e = err(&format!("{tri}f 1 2 -4\n"));
        assert!(
            matches!(
                e,
                ObjError::IndexOutOfRange {
                    index: -4,
                    count: 3,
                    ..
                }
            ),
            "{e}"
        );
        let e = err(&format!("{tri}f 0 1 2\n"));
        assert!(matches!(e, ObjError::BadIndex { line: 4, .. }), "{e}");
        assert!(e.to_string().contains("start at 1"));
        assert!(matches!(
            err(&format!("{tri}f 1 2 3.5\n")),
            ObjError::BadIndex { .. }
        ));
        assert!(matches!(
            err(&format!("{tri}f 1 2 a\n")),
            ObjError::BadIndex { .. }
        ));
        assert!(matches!(
            err(&format!("{tri}f 1/1/1/1 2 3\n")),
            ObjError::BadIndex { .. }
        ));
        assert!(matches!(
            err(&format!("{tri}f 1 2\n")),
            ObjError::TooFewCorners { got: 2, .. }
        ));
        assert!(matches!(
            err(&format!("{tri}vt 0 0\nf 1/1 2/9 3/1\n")),
            ObjError::IndexOutOfRange {
                kind: "vt",
                index: 9,
                ..
            }
        ));
        assert!(matches!(
            err(&format!("{tri}vt 0 0\nf 1/1 2 3/1\n")),
            ObjError::Inconsistent { line: 5, .. }
        ));
        let e = err(&format!("{tri}vt 0 0\nf 1/1 2/1 3/1\nf 1 2 3\n"));
        assert!(matches!(e, ObjError::Inconsistent { line: 6, .. }), "{e}");
        assert!(e.to_string().contains("line 5"), "{e}");
        let e = err("v 0 0 0 1 1 1\nv 1 0 0\n");
        assert!(matches!(e, ObjError::Inconsistent { line: 2, .. }), "{e}");
        assert!(matches!(err(tri), ObjError::NoFaces { vertices: 3, .. }));
        assert!(matches!(err(""), ObjError::NoFaces { vertices: 0, .. }));
        let bad_utf8: &[u8] = b"v 0 0 0\n\xff\xfe\n";
        assert!(matches!(
            read_obj::<f64, _>(bad_utf8, "x.obj"),
            Err(ObjError::Read { line: 2, .. })
        ));
        let e = load_obj::<f64>("/nonexistent/dir/mesh.obj").unwrap_err();
        assert!(matches!(e, ObjError::Open { .. }));
        assert!(e.to_string().contains("/nonexistent/dir/mesh.obj"));
    }

    #[test]
    fn write_then_read_round_trips_exactly() {
        let mut m = Mesh::<f64>::cube();
        m.colors = (0..8).map(|i| [i as f64 / 7.0, 0.1, 1.0 / 3.0]).collect();
        m.positions[0][0] = -1.0 / 3.0;
        let mut buf = Vec::new();
        write_obj_to(&mut buf, &m).unwrap();
        let back = read_obj::<f64, _>(&buf[..], "buf").unwrap();
        assert_eq!(back, m);
        let m32 = m.cast::<f32>();
        let mut buf = Vec::new();
        write_obj_to(&mut buf, &m32).unwrap();
        assert_eq!(read_obj::<f32, _>(&buf[..], "buf").unwrap(), m32);
        let g = Mesh::<f64>::grid_plane(2);
        let mut buf = Vec::new();
        write_obj_to(&mut buf, &g).unwrap();
        assert_eq!(read_obj::<f64, _>(&buf[..], "buf").unwrap(), g);
    }

    /// The triangles agree with tobj's (which renumbers vertices, hence the comparison through
    /// the positions), on a file with objects, quads, polygons and negative indices.
    #[test]
    fn triangles_agree_with_tobj() {
        let text = "o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 9 9 9\nf 1 2 3 4\no b\nv 0 0 1\nv 1 0 1\nv 2 1 1\nv 1 2 1\nv 0 1 1\nf -5 -4 -3 -2 -1\nf 6 3 2\n";
        let ours = parse_obj_str::<f32>(text).unwrap();
        let opts = tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ignore_points: true,
            ignore_lines: true,
        };
        let (models, _) =
            tobj::load_obj_buf(&mut text.as_bytes(), &opts, |_| Ok(Default::default())).unwrap();
        let mut theirs: Vec<[[f32; 3]; 3]> = Vec::new();
        for model in &models {
            let m = &model.mesh;
            for tri in m.indices.chunks(3) {
                theirs.push(std::array::from_fn(|k| {
                    let i = tri[k] as usize;
                    [
                        m.positions[3 * i],
                        m.positions[3 * i + 1],
                        m.positions[3 * i + 2],
                    ]
                }));
            }
        }
        let ours_tris: Vec<[[f32; 3]; 3]> = ours
            .faces
            .iter()
            .map(|f| f.map(|i| ours.positions[i as usize]))
            .collect();
        assert_eq!(ours_tris, theirs);
        assert_eq!(ours.vertex_count(), 10);
    }
}
