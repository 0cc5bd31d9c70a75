//! A fitted face as Wavefront OBJ + MTL text: positions in model space, the model's uvs as
//! `vt` (corner `v/vt` indices equal, since the model has one uv per vertex), `mtllib`, and
//! one material per face group: `skin` (the textured faces of [`super::textured_faces`],
//! `map_Kd` the albedo texture) and one `region_<name>` per untextured region with `Kd` its
//! constant colour or the mean fitted albedo of its vertices (eyes, mouth interior). A model
//! without uvs gets its albedo as vertex colours (`v x y z r g b`) and one plain material.
//! Face order is the model's, so that Tapestry's OBJ loader
//! ([`render_ops::obj::parse_obj_str`], which ignores materials) reads back the model's
//! triangles.

use std::fmt::Write;

use ndarray::Array2;

use crate::morphable::Morphable;

/// The text of `fit.obj` and `fit.mtl` ([`face_obj`]).
#[derive(Clone, Debug, PartialEq)]
pub struct FaceObj {
    /// The OBJ file.
    pub obj: String,
    /// The MTL file.
    pub mtl: String,
}

/// The OBJ and MTL of `model` with `shape` `[V, 3]` and per-vertex `albedo` `[V, 3]`;
/// `textured` holds one flag per face; the OBJ names `mtl_file`, the MTL `texture_file`.
pub fn face_obj(
    model: &Morphable<f64>,
    shape: &Array2<f64>,
    albedo: &Array2<f64>,
    textured: &[bool],
    mtl_file: &str,
    texture_file: &str,
) -> FaceObj {
    let mut obj = format!(
        "# tapestry fit-face: the fitted {} in model space (millimetres, y up, facing +z)\nmtllib {mtl_file}\n",
        model.name()
    );
    let mut mtl = String::from("# tapestry fit-face\n");
    let uvs = model.uvs();
    let c = |x: f64| x.clamp(0.0, 1.0);
    for (i, v) in shape.rows().into_iter().enumerate() {
        let _ = write!(obj, "v {:.5} {:.5} {:.5}", v[0], v[1], v[2]);
        if uvs.is_none() {
            let a = albedo.row(i);
            let _ = write!(obj, " {:.4} {:.4} {:.4}", c(a[0]), c(a[1]), c(a[2]));
        }
        obj.push('\n');
    }
    let Some(uv) = uvs else {
        obj += "usemtl face\n";
        for f in model.faces() {
            let [a, b, c] = f.map(|x| x + 1);
            let _ = writeln!(obj, "f {a} {b} {c}");
        }
        mtl += "newmtl face\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\n";
        return FaceObj { obj, mtl };
    };
    for t in uv.rows() {
        let _ = writeln!(obj, "vt {:.6} {:.6}", t[0], t[1]);
    }
    // Material of each face: None for the texture, Some(region) otherwise.
    let regions = model.regions();
    let material = |f: usize| -> Option<usize> {
        (!textured.get(f).copied().unwrap_or(false)).then(|| model.face_regions()[f] as usize)
    };
    let mut used = vec![false; regions.len()];
    let mut skin = false;
    let mut current: Option<Option<usize>> = None;
    for (fi, f) in model.faces().iter().enumerate() {
        let m = material(fi);
        if current != Some(m) {
            match m {
                None => obj += "usemtl skin\n",
                Some(r) => {
                    let _ = writeln!(obj, "usemtl region_{}", regions[r].name);
                }
            }
            current = Some(m);
        }
        match m {
            None => skin = true,
            Some(r) => used[r] = true,
        }
        let [a, b, c] = f.map(|x| x + 1);
        let _ = writeln!(obj, "f {a}/{a} {b}/{b} {c}/{c}");
    }
    if skin {
        let _ = write!(
            mtl,
            "newmtl skin\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {texture_file}\n"
        );
    }
    for (r, region) in regions.iter().enumerate().filter(|(r, _)| used[*r]) {
        let kd = region.albedo.unwrap_or_else(|| {
            let mut seen = vec![false; albedo.nrows()];
            let (mut sum, mut n) = ([0.0; 3], 0.0);
            for (f, tri) in model.faces().iter().enumerate() {
                if model.face_regions()[f] as usize != r {
                    continue;
                }
                for &v in tri {
                    if !std::mem::replace(&mut seen[v as usize], true) {
                        for (k, s) in sum.iter_mut().enumerate() {
                            *s += albedo[[v as usize, k]];
                        }
                        n += 1.0;
                    }
                }
            }
            sum.map(|s| s / f64::max(n, 1.0))
        });
        let _ = write!(
            mtl,
            "newmtl region_{}\nKa 1 1 1\nKd {:.4} {:.4} {:.4}\nKs 0 0 0\nillum 1\n",
            region.name,
            c(kd[0]),
            c(kd[1]),
            c(kd[2])
        );
    }
    FaceObj { obj, mtl }
}
