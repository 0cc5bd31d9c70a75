//! Every input boundary returns a typed error (never a panic), whose variant and message say
//! what is wrong: scene JSON (unknown keys, wrong types, missing keys and files), OBJ (malformed
//! lines, bad indices), PNG (corrupt bytes, unexpected channel counts), .npy (dtype, shape),
//! tensors given to the rendering ops (shape mismatches, bad indices, non-finite vertices) and
//! requests too large for memory (refused before allocating).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use autodiff::ndarray::{ArrayD, IxDyn};
use autodiff::{AutodiffError, Tape};
use render_ops::error::RenderError;
use render_ops::io::{read_image, read_npy, read_npy_shape, read_png, write_npy, IoError};
use render_ops::obj::{parse_obj_str, ObjError};
use render_ops::raster::{RasterError, RasterSettings, MAX_FRAGMENT_SLOTS};
use render_ops::rasterize::rasterize;
use render_ops::scene::{Scene, SceneDesc, SceneError};
use render_ops::soft::{dibr, softras, DibrSettings, SoftSettings, MAX_SOFT_BIN_ENTRIES};

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("tapestry-typed-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

const TRI: &str = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";

const SCENE: &str = r#"{"mesh": "tri.obj",
  "camera": {"eye": [0, 0, 3], "at": [0, 0, 0], "fov_y_deg": 45},
  "image": {"width": 8, "height": 8}}"#;

fn scene_err(text: &str, base: &Path) -> SceneError {
    match Scene::<f64>::from_json(text, base, "s.json") {
        Ok(_) => panic!("expected an error for {text}"),
        Err(e) => e,
    }
}

#[test]
fn scene_json_errors() {
    let d = dir("scene");
    std::fs::write(d.join("tri.obj"), TRI).unwrap();
    assert!(Scene::<f64>::from_json(SCENE, &d, "s.json").is_ok());

    // (text, key path the message must name, another fragment it must hold)
    let cases = [
        (
            SCENE.replace("\"mesh\"", "\"oops\": 1, \"mesh\""),
            "oops",
            "unknown field",
        ),
        (
            SCENE.replace("\"fov_y_deg\"", "\"zoom\": 2, \"fov_y_deg\""),
            "camera",
            "zoom",
        ),
        (
            SCENE.replace("\"width\": 8", "\"width\": \"eight\""),
            "image.width",
            "invalid type",
        ),
        (
            SCENE.replace("[0, 0, 3]", "[0, 0]"),
            "camera.eye",
            "invalid length",
        ),
        (
            SCENE.replace("\"mesh\": \"tri.obj\",", ""),
            "mesh",
            "missing field",
        ),
        (SCENE[..SCENE.len() - 3].to_string(), "s.json", "EOF"),
        (
            SCENE.replace("\"image\"", "\"raster\": {\"method\": \"soft\"}, \"image\""),
            "raster.method",
            "unknown variant",
        ),
    ];
    for (text, key, part) in &cases {
        let e = scene_err(text, &d);
        assert!(matches!(e, SceneError::Json { .. }), "{e:?}");
        let m = e.to_string();
        assert!(m.starts_with("s.json: "), "{m}");
        assert!(
            m.contains(key) && m.contains(part),
            "{m} lacks {key} / {part}"
        );
        assert_eq!(m.lines().count(), 1, "{m}");
    }
    // Well-typed but invalid values name the key and the rule.
    let e = scene_err(&SCENE.replace("\"width\": 8", "\"width\": 0"), &d);
    assert!(
        matches!(&e, SceneError::Invalid { key, .. } if key == "image.width"),
        "{e:?}"
    );
    // Missing files: the scene itself, its mesh, its texture.
    let e = Scene::<f64>::load(d.join("none.json")).unwrap_err();
    assert!(matches!(e, SceneError::Read { .. }) && e.to_string().contains("none.json"));
    let e = scene_err(&SCENE.replace("tri.obj", "gone.obj"), &d);
    assert!(
        matches!(
            &e,
            SceneError::Mesh {
                source: ObjError::Open { .. },
                ..
            }
        ) && e.to_string().contains("gone.obj"),
        "{e}"
    );
    let e = scene_err(
        &SCENE.replace("\"image\"", "\"texture\": \"gone.png\", \"image\""),
        &d,
    );
    assert!(
        matches!(
            &e,
            SceneError::Texture {
                source: IoError::Open { .. },
                ..
            }
        ) && e.to_string().contains("gone.png"),
        "{e}"
    );
    // A mesh that is there but malformed, a texture that is there but corrupt.
    std::fs::write(d.join("bad.obj"), "v 0 0 zero\nf 1 2 3\n").unwrap();
    let e = scene_err(&SCENE.replace("tri.obj", "bad.obj"), &d);
    assert!(
        matches!(
            &e,
            SceneError::Mesh {
                source: ObjError::BadNumber { line: 1, .. },
                ..
            }
        ),
        "{e}"
    );
    std::fs::write(d.join("bad.png"), b"\x89PNG\r\n\x1a\ngarbage").unwrap();
    let e = scene_err(
        &SCENE.replace("\"image\"", "\"texture\": \"bad.png\", \"image\""),
        &d,
    );
    assert!(
        matches!(
            &e,
            SceneError::Texture {
                source: IoError::Decode { .. },
                ..
            }
        ),
        "{e}"
    );
    // A scene file that is not UTF-8.
    std::fs::write(d.join("latin1.json"), b"{\"mesh\": \"\xe9.obj\"}").unwrap();
    let e = Scene::<f64>::load(d.join("latin1.json")).unwrap_err();
    assert!(matches!(e, SceneError::Read { .. }), "{e}");
    // Parsing alone (no files) reports the same JSON errors.
    assert!(matches!(
        SceneDesc::parse("[1, 2]", "x.json"),
        Err(SceneError::Json { .. })
    ));
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn obj_errors() {
    /// (OBJ text, the expected variant, a fragment of the message)
    type Case = (&'static str, fn(&ObjError) -> bool, &'static str);
    let cases: Vec<Case> = vec![
        (
            "v 0 0 x\n",
            |e| matches!(e, ObjError::BadNumber { line: 1, token, .. } if token == "x"),
            ":1:",
        ),
        (
            "v 0 0\nv 1 0 0\n",
            |e| matches!(e, ObjError::ValueCount { line: 1, .. }),
            "values",
        ),
        (
            "v 0 0 nan\n",
            |e| matches!(e, ObjError::NonFinite { line: 1, .. }),
            "non-finite",
        ),
        (
            "v 0 0 0 0\n",
            |e| matches!(e, ObjError::ZeroW { line: 1, .. }),
            "w = 0",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
            |e| {
                matches!(
                    e,
                    ObjError::IndexOutOfRange {
                        line: 4,
                        index: 4,
                        count: 3,
                        ..
                    }
                )
            },
            "out of range",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n",
            |e| matches!(e, ObjError::IndexOutOfRange { line: 4, .. }),
            "out of range",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
            |e| matches!(e, ObjError::BadIndex { line: 4, .. }),
            "bad face corner",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 a\n",
            |e| matches!(e, ObjError::BadIndex { line: 4, .. }),
            "bad face corner",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999\n",
            |e| {
                matches!(
                    e,
                    ObjError::BadIndex { line: 4, .. } | ObjError::IndexOutOfRange { line: 4, .. }
                )
            },
            ":4:",
        ),
        (
            "v 0 0 0\nv 1 0 0\nf 1 2\n",
            |e| {
                matches!(
                    e,
                    ObjError::TooFewCorners {
                        line: 3,
                        got: 2,
                        ..
                    }
                )
            },
            "corner",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
            |e| matches!(e, ObjError::NoFaces { vertices: 3, .. }),
            "no faces",
        ),
        (
            "",
            |e| matches!(e, ObjError::NoFaces { vertices: 0, .. }),
            "no faces",
        ),
    ];
    for (text, is_expected, part) in cases {
        let e = match parse_obj_str::<f64>(text) {
            Ok(_) => panic!("expected an error for {text:?}"),
            Err(e) => e,
        };
        assert!(is_expected(&e), "{text:?}: {e:?}");
        let m = e.to_string();
        assert!(m.contains(part), "{text:?}: {m} lacks {part:?}");
        assert_eq!(m.lines().count(), 1, "{m}");
    }
    // A file that is not there names the file.
    let e = render_ops::obj::load_obj::<f64>("/nonexistent/m.obj").unwrap_err();
    assert!(matches!(e, ObjError::Open { .. }) && e.to_string().contains("/nonexistent/m.obj"));
}

#[test]
fn png_errors() {
    let d = dir("png");
    // A valid PNG, then the same bytes truncated, bit-flipped and replaced by text.
    let p = d.join("ok.png");
    image::RgbImage::from_fn(16, 16, |x, y| image::Rgb([x as u8 * 9, y as u8 * 9, 7]))
        .save(&p)
        .unwrap();
    assert_eq!(read_png::<f64>(&p).unwrap().shape(), &[16, 16, 3]);
    let good = std::fs::read(&p).unwrap();
    let mut flipped = good.clone();
    let n = flipped.len();
    for b in &mut flipped[n / 2..n / 2 + 8] {
        *b ^= 0x5a;
    }
    for (name, bytes) in [
        ("truncated.png", good[..good.len() / 2].to_vec()),
        ("header_only.png", good[..8].to_vec()),
        ("flipped.png", flipped),
        ("text.png", b"not a png at all".to_vec()),
        ("empty.png", Vec::new()),
    ] {
        let q = d.join(name);
        std::fs::write(&q, bytes).unwrap();
        let e = read_png::<f64>(&q).unwrap_err();
        assert!(matches!(e, IoError::Decode { .. }), "{name}: {e:?}");
        assert!(e.to_string().contains(name), "{e}");
    }
    // Two channels (gray + alpha) is not an image channel count the pipeline takes.
    let q = d.join("la.png");
    image::GrayAlphaImage::new(3, 2).save(&q).unwrap();
    let e = read_image::<f64>(&q).unwrap_err();
    assert!(
        matches!(e, IoError::PixelFormat { channels: 2, .. }),
        "{e:?}"
    );
    assert!(e.to_string().contains("2 channel"), "{e}");
    // A missing file.
    assert!(matches!(
        read_png::<f64>(d.join("missing.png")),
        Err(IoError::Open { .. })
    ));
    std::fs::remove_dir_all(&d).ok();
}

/// A version-1 .npy file with the given dtype descriptor, shape and raw data.
fn npy_bytes(descr: &str, shape: &[usize], data: &[u8]) -> Vec<u8> {
    let shape_s = match shape {
        [n] => format!("({n},)"),
        s => format!(
            "({})",
            s.iter()
                .map(|x| x.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_s}, }}");
    // Pad so that magic, version, length and header fill a multiple of 64 bytes.
    let pad = 63 - (10 + header.len()) % 64;
    header.push_str(&" ".repeat(pad));
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(data);
    out
}

#[test]
fn npy_errors() {
    let d = dir("npy");
    let p = d.join("a.npy");
    // The helper writes what read_npy accepts.
    let data: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    std::fs::write(&p, npy_bytes("<f4", &[2, 3], &data)).unwrap();
    assert_eq!(read_npy::<f64>(&p).unwrap().shape(), &[2, 3]);

    for descr in ["<i4", "|u1", "|b1", "<c16", "<U3"] {
        std::fs::write(&p, npy_bytes(descr, &[2], &[0u8; 32])).unwrap();
        let e = read_npy::<f64>(&p).unwrap_err();
        assert!(
            matches!(&e, IoError::Dtype { descr: got, .. } if !got.is_empty()),
            "{descr}: {e:?}"
        );
        assert!(e.to_string().contains("dtype"), "{e}");
    }
    // Shapes: a wrong exact shape, a non-image array read as an image, a header promising more
    // data than the file holds.
    write_npy(&p, &ArrayD::<f64>::zeros(IxDyn(&[5, 3]))).unwrap();
    let e = read_npy_shape::<f64>(&p, &[4, 3]).unwrap_err();
    assert!(matches!(e, IoError::Shape { .. }), "{e:?}");
    assert!(
        e.to_string().contains("[5, 3]") && e.to_string().contains("[4, 3]"),
        "{e}"
    );
    for shape in [vec![5, 3], vec![2, 2, 2], vec![2, 2, 3, 1], vec![0, 2, 3]] {
        write_npy(&p, &ArrayD::<f64>::zeros(IxDyn(&shape))).unwrap();
        assert!(
            matches!(read_image::<f64>(&p), Err(IoError::ImageShape { .. })),
            "{shape:?}"
        );
    }
    std::fs::write(&p, npy_bytes("<f8", &[1000, 1000], &[0u8; 64])).unwrap();
    assert!(matches!(read_npy::<f64>(&p), Err(IoError::Npy { .. })));
    std::fs::write(&p, b"\x93NUMPY\x01\x00\xff\xff{").unwrap();
    assert!(matches!(read_npy::<f64>(&p), Err(IoError::Npy { .. })));
    std::fs::remove_dir_all(&d).ok();
}

fn tensor(shape: &[usize], v: impl Fn(usize) -> f64) -> ArrayD<f64> {
    let n = shape.iter().product();
    ArrayD::from_shape_vec(IxDyn(shape), (0..n).map(v).collect()).unwrap()
}

#[test]
fn tensor_shape_and_index_errors_of_the_rendering_ops() {
    let tape = Tape::<f64>::new();
    let faces = Arc::new(vec![[0u32, 1, 2]]);
    let clip4 = tape.leaf(tensor(&[3, 4], |i| {
        [0.0, 0.0, 0.0, 1.0][i % 4] + i as f64 * 0.1
    }));
    let clip3 = tape.leaf(tensor(&[3, 3], |_| 1.0));
    let attrs = tape.leaf(tensor(&[3, 3], |_| 0.5));
    let attrs_short = tape.leaf(tensor(&[2, 3], |_| 0.5));
    let rs = RasterSettings::new(8, 8);
    let soft = SoftSettings::new(8, 8, 0.1, 10.0);
    let ds = DibrSettings::new(8, 8);

    let is_shape = |e: &RenderError, op: &str| matches!(e, RenderError::Autodiff(AutodiffError::Shape { op: o, .. }) if *o == op);
    let e = rasterize(clip3, faces.clone(), &rs).err().unwrap();
    assert!(e.to_string().contains("[3, 3]"), "{e}");
    let e = softras(clip3, attrs, faces.clone(), &soft).unwrap_err();
    assert!(
        is_shape(&e, "softras") && e.to_string().contains("[3, 3]"),
        "{e}"
    );
    let e = softras(clip4, attrs_short, faces.clone(), &soft).unwrap_err();
    assert!(
        is_shape(&e, "softras") && e.to_string().contains("[2, 3]"),
        "{e}"
    );
    let e = dibr(clip3, attrs, faces.clone(), &ds).unwrap_err();
    assert!(is_shape(&e, "dibr"), "{e}");
    let e = dibr(clip4, attrs_short, faces.clone(), &ds).unwrap_err();
    assert!(is_shape(&e, "dibr"), "{e}");

    // A face index past the vertices.
    let bad_faces = Arc::new(vec![[0u32, 1, 3]]);
    let e = rasterize(clip4, bad_faces.clone(), &rs).err().unwrap();
    assert!(
        matches!(
            e,
            RenderError::Raster(RasterError::FaceIndexOutOfRange {
                face: 0,
                index: 3,
                num_vertices: 3
            })
        ),
        "{e}"
    );
    assert!(softras(clip4, attrs, bad_faces.clone(), &soft)
        .unwrap_err()
        .to_string()
        .contains("indexes past 3 vertices"));
    assert!(dibr(clip4, attrs, bad_faces, &ds)
        .unwrap_err()
        .to_string()
        .contains("indexes past 3 vertices"));

    // A non-finite vertex.
    let nan = tape.leaf(tensor(&[3, 4], |i| if i == 5 { f64::NAN } else { 1.0 }));
    let e = rasterize(nan, faces.clone(), &rs).err().unwrap();
    assert!(
        matches!(
            e,
            RenderError::Raster(RasterError::NonFiniteVertex { vertex: 1, .. })
        ),
        "{e}"
    );
    // Bad settings.
    let mut s = soft.clone();
    s.sigma = -1.0;
    assert!(softras(clip4, attrs, faces.clone(), &s)
        .unwrap_err()
        .to_string()
        .contains("sigma"));
    let mut d = ds.clone();
    d.threshold = 1.5;
    assert!(dibr(clip4, attrs, faces, &d)
        .unwrap_err()
        .to_string()
        .contains("threshold"));
}

#[test]
fn requests_too_large_for_memory_are_refused_before_allocating() {
    // Hard: width x height x faces_per_pixel fragment slots.
    let mut s = RasterSettings::new(2048, 2048);
    assert!(s.validate().is_ok());
    s.faces_per_pixel = 32;
    let e = s.validate().unwrap_err();
    assert_eq!(
        e,
        RasterError::TooLarge {
            request: "a 2048x2048 image with faces_per_pixel 32".into(),
            what: "fragment slots (width x height x faces_per_pixel)",
            needed: 2048 * 2048 * 32,
            limit: MAX_FRAGMENT_SLOTS,
        }
    );
    let m = e.to_string();
    assert!(
        m.contains("2048x2048") && m.contains("134217728") && m.contains("67108864"),
        "{m}"
    );
    // 16384 x 16384 pixels (a quarter of a gigapixel) with one face per pixel; the check runs
    // before rasterizing, so this returns at once with no allocation of the image.
    let tape = Tape::<f64>::new();
    let clip = tape.leaf(tensor(&[3, 4], |i| {
        [
            [-1.0, -1.0, 0.0, 1.0],
            [1.0, -1.0, 0.0, 1.0],
            [0.0, 1.0, 0.0, 1.0],
        ][i / 4][i % 4]
    }));
    let faces = Arc::new(vec![[0u32, 1, 2]]);
    let e = rasterize(clip, faces.clone(), &RasterSettings::new(16384, 16384))
        .err()
        .unwrap();
    assert!(
        matches!(e, RenderError::Raster(RasterError::TooLarge { needed, .. }) if needed == 1 << 28),
        "{e}"
    );

    // Soft: the image itself, and the per-tile face lists.
    let attrs = tape.leaf(tensor(&[3, 3], |_| 0.5));
    let e = softras(
        clip,
        attrs,
        faces.clone(),
        &SoftSettings::new(16384, 16384, 0.1, 10.0),
    )
    .unwrap_err();
    assert!(
        matches!(
            &e,
            RenderError::Raster(RasterError::TooLarge { what: "pixels", .. })
        ),
        "{e}"
    );
    // threshold 0: every face reaches every pixel, so 20000 faces x 64 x 64 tiles at 1024^2
    // (82M list entries) is refused, while the default cut-off is fine.
    let n = 20_000;
    let many = Arc::new(vec![[0u32, 1, 2]; n]);
    let mut ss = SoftSettings::new(1024, 1024, 0.1, 10.0);
    ss.threshold = 0.0;
    let e = softras(clip, attrs, many.clone(), &ss).unwrap_err();
    match &e {
        RenderError::Raster(RasterError::TooLarge {
            needed,
            limit,
            what,
            ..
        }) => {
            assert_eq!(*needed, n * 64 * 64);
            assert_eq!(*limit, MAX_SOFT_BIN_ENTRIES);
            assert!(what.contains("face list"));
        }
        other => panic!("expected TooLarge, got {other}"),
    }
    assert!(e.to_string().contains("softras of 20000 faces"), "{e}");
    // DIB-R with a huge delta: the cut-off covers the screen.
    let mut d = DibrSettings::new(1024, 1024);
    d.delta = 1e3;
    let e = render_ops::soft::dibr_alpha(clip, many, &d).unwrap_err();
    assert!(
        matches!(&e, RenderError::Raster(RasterError::TooLarge { needed, .. }) if *needed == n * 64 * 64),
        "{e}"
    );
    // Reasonable requests still pass.
    let small = SoftSettings::new(64, 64, 0.1, 10.0);
    assert!(softras(clip, attrs, faces, &small).is_ok());
}
