//! Image and array files: PNG (8/16-bit in, 8-bit out) and `.npy` (float32/float64, C order).
//!
//! Images are `[H, W, C]` arrays, row 0 at the top, `C` = 1 (gray), 3 (RGB) or 4 (RGBA), values
//! linear floats nominally in [0, 1]. PNG writing clamps to [0, 1] and rounds to 8 bits with no
//! gamma (NaN is written as 0); reading maps 8-bit values `q` to `q / 255` and 16-bit ones to
//! `q / 65535`. Palette and low-bit-depth PNGs are expanded by the decoder; gray+alpha PNGs
//! (2 channels) are rejected.
//!
//! `.npy` files hold float32 or float64 arrays of any dimension in C order. Reading accepts either
//! dtype (either byte order, C or Fortran order) and converts to `T`; writing uses `T`'s dtype
//! (`<f4` for f32, `<f8` for f64) and C order.

use std::fs::File;
use std::io::{self, BufWriter};
use std::path::{Path, PathBuf};

use autodiff::Real;
use image::{ColorType, DynamicImage, ImageFormat, ImageReader};
use ndarray::{Array3, ArrayBase, ArrayD, Data, Dimension, Ix3};
use ndarray_npy::{ReadNpyError, ReadNpyExt, WriteNpyExt};
use thiserror::Error;

/// Errors of image and array I/O, each naming the file.
#[derive(Debug, Error)]
pub enum IoError {
    /// The file cannot be opened or read.
    #[error("{}: cannot read: {source}", .path.display())]
    Open {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: io::Error,
    },
    /// The file cannot be created or written.
    #[error("{}: cannot write: {source}", .path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Underlying error.
        source: io::Error,
    },
    /// Not a decodable PNG (corrupt, truncated, other format).
    #[error("{}: cannot decode PNG: {source}", .path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// Decoder error.
        source: image::ImageError,
    },
    /// PNG encoding failed.
    #[error("{}: cannot encode PNG: {source}", .path.display())]
    Encode {
        /// The file.
        path: PathBuf,
        /// Encoder error.
        source: image::ImageError,
    },
    /// A PNG pixel format other than 8/16-bit gray, RGB or RGBA.
    #[error("{}: unsupported PNG pixel format {format} ({channels} channel(s)); expected 8- or 16-bit gray (1), RGB (3) or RGBA (4)", .path.display())]
    PixelFormat {
        /// The file.
        path: PathBuf,
        /// The decoded format, e.g. `La8`.
        format: String,
        /// Its channel count.
        channels: u8,
    },
    /// An image array that is not `[H, W, C]` with `H, W > 0` and `C` in 1, 3, 4.
    #[error("{}: image array has shape {shape:?}; expected [H, W, C] with H, W > 0 and C = 1, 3 or 4", .path.display())]
    ImageShape {
        /// The file.
        path: PathBuf,
        /// The array's shape.
        shape: Vec<usize>,
    },
    /// Not a readable `.npy` file (bad header, truncated data, ...).
    #[error("{}: cannot read .npy: {message}", .path.display())]
    Npy {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A `.npy` dtype other than float32/float64.
    #[error("{}: .npy dtype {descr} is not float32 ('<f4') or float64 ('<f8')", .path.display())]
    Dtype {
        /// The file.
        path: PathBuf,
        /// The numpy type descriptor found, e.g. `'<i8'`.
        descr: String,
    },
    /// A `.npy` array of an unexpected shape.
    #[error("{}: array has shape {got:?}, expected {expected:?}", .path.display())]
    Shape {
        /// The file.
        path: PathBuf,
        /// The expected shape.
        expected: Vec<usize>,
        /// The shape found.
        got: Vec<usize>,
    },
    /// `.npy` writing failed.
    #[error("{}: cannot write .npy: {message}", .path.display())]
    NpyWrite {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// [`read_image`] got a file that is not `.png`, `.jpg`/`.jpeg` or `.npy`.
    #[error("{}: unknown image file type; expected a .png, .jpg or .npy file", .path.display())]
    Extension {
        /// The file.
        path: PathBuf,
    },
}

fn image_shape_ok(shape: &[usize]) -> bool {
    shape.len() == 3 && shape[0] > 0 && shape[1] > 0 && matches!(shape[2], 1 | 3 | 4)
}

/// Reads an 8- or 16-bit gray, RGB or RGBA PNG (or a JPEG: the format is taken from the file's
/// magic bytes) into `[H, W, C]` floats in [0, 1].
pub fn read_png<T: Real>(path: impl AsRef<Path>) -> Result<Array3<T>, IoError> {
    let path = path.as_ref();
    let open_err = |source| IoError::Open {
        path: path.to_path_buf(),
        source,
    };
    let reader = ImageReader::open(path).map_err(open_err)?;
    let mut reader = reader.with_guessed_format().map_err(open_err)?;
    if reader.format().is_none() {
        // Not recognised from the magic bytes: let the PNG decoder report what is wrong.
        reader.set_format(ImageFormat::Png);
    }
    // The file is open and its header read: an I/O error while decoding (e.g. an unexpected
    // end of file) means a truncated or corrupt image.
    let img = reader.decode().map_err(|source| IoError::Decode {
        path: path.to_path_buf(),
        source,
    })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let from8 = |data: &[u8], c: usize| {
        Array3::from_shape_vec(
            (h, w, c),
            data.iter()
                .map(|&q| T::from_f64c(q as f64 / 255.0))
                .collect(),
        )
    };
    let from16 = |data: &[u16], c: usize| {
        Array3::from_shape_vec(
            (h, w, c),
            data.iter()
                .map(|&q| T::from_f64c(q as f64 / 65535.0))
                .collect(),
        )
    };
    let arr = match &img {
        DynamicImage::ImageLuma8(b) => from8(b.as_raw(), 1),
        DynamicImage::ImageRgb8(b) => from8(b.as_raw(), 3),
        DynamicImage::ImageRgba8(b) => from8(b.as_raw(), 4),
        DynamicImage::ImageLuma16(b) => from16(b.as_raw(), 1),
        DynamicImage::ImageRgb16(b) => from16(b.as_raw(), 3),
        DynamicImage::ImageRgba16(b) => from16(b.as_raw(), 4),
        other => {
            let color: ColorType = other.color();
            return Err(IoError::PixelFormat {
                path: path.to_path_buf(),
                format: format!("{color:?}"),
                channels: color.channel_count(),
            });
        }
    };
    Ok(arr.expect("decoder buffer matches its dimensions"))
}

/// Writes `[H, W, C]` (C = 1, 3 or 4) as an 8-bit PNG: `round(clamp(x, 0, 1) * 255)`, no gamma,
/// NaN as 0.
pub fn write_png<T: Real, S: Data<Elem = T>>(
    path: impl AsRef<Path>,
    img: &ArrayBase<S, Ix3>,
) -> Result<(), IoError> {
    let path = path.as_ref();
    let shape = img.shape().to_vec();
    if !image_shape_ok(&shape) || shape[0] > u32::MAX as usize || shape[1] > u32::MAX as usize {
        return Err(IoError::ImageShape {
            path: path.to_path_buf(),
            shape,
        });
    }
    let color = match shape[2] {
        1 => ColorType::L8,
        3 => ColorType::Rgb8,
        _ => ColorType::Rgba8,
    };
    // Iteration in logical (row-major) order whatever the memory layout.
    let bytes: Vec<u8> = img.iter().map(|&x| quantize(x.to_f64c())).collect();
    image::save_buffer_with_format(
        path,
        &bytes,
        shape[1] as u32,
        shape[0] as u32,
        color,
        ImageFormat::Png,
    )
    .map_err(|source| match source {
        image::ImageError::IoError(source) => IoError::Write {
            path: path.to_path_buf(),
            source,
        },
        source => IoError::Encode {
            path: path.to_path_buf(),
            source,
        },
    })
}

/// `round(clamp(x, 0, 1) * 255)`, NaN to 0.
pub fn quantize(x: f64) -> u8 {
    if x.is_nan() {
        0
    } else {
        (x.clamp(0.0, 1.0) * 255.0).round() as u8
    }
}

/// Errors of parsing `.npy` bytes already read into memory: an I/O error there is a truncated
/// or malformed file, not an unreadable one.
fn npy_err(path: &Path, e: ReadNpyError) -> IoError {
    match e {
        ReadNpyError::Io(source) => IoError::Npy {
            path: path.to_path_buf(),
            message: format!("truncated or malformed file: {source}"),
        },
        ReadNpyError::WrongDescriptor(d) => IoError::Dtype {
            path: path.to_path_buf(),
            descr: d.to_string(),
        },
        e => IoError::Npy {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
    }
}

/// Reads a float32 or float64 `.npy` array of any dimension, converted to `T`, in standard
/// (C) layout. Other dtypes are [`IoError::Dtype`].
pub fn read_npy<T: Real>(path: impl AsRef<Path>) -> Result<ArrayD<T>, IoError> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| IoError::Open {
        path: path.to_path_buf(),
        source,
    })?;
    let arr: ArrayD<T> = match ArrayD::<f64>::read_npy(&bytes[..]) {
        Ok(a) => a.mapv(T::from_f64c),
        Err(ReadNpyError::WrongDescriptor(_)) => match ArrayD::<f32>::read_npy(&bytes[..]) {
            Ok(a) => a.mapv(|x| T::from_f64c(x as f64)),
            Err(e) => return Err(npy_err(path, e)),
        },
        Err(e) => return Err(npy_err(path, e)),
    };
    Ok(if arr.is_standard_layout() {
        arr
    } else {
        arr.as_standard_layout().into_owned()
    })
}

/// [`read_npy`], then checks the shape exactly (e.g. `&[2562, 3]`).
pub fn read_npy_shape<T: Real>(
    path: impl AsRef<Path>,
    expected: &[usize],
) -> Result<ArrayD<T>, IoError> {
    let path = path.as_ref();
    let arr = read_npy::<T>(path)?;
    if arr.shape() != expected {
        return Err(IoError::Shape {
            path: path.to_path_buf(),
            expected: expected.to_vec(),
            got: arr.shape().to_vec(),
        });
    }
    Ok(arr)
}

/// Writes an array of any dimension as `.npy` in `T`'s dtype, C order.
pub fn write_npy<T: Real, S: Data<Elem = T>, D: Dimension>(
    path: impl AsRef<Path>,
    arr: &ArrayBase<S, D>,
) -> Result<(), IoError> {
    let path = path.as_ref();
    let file = File::create(path).map_err(|source| IoError::Write {
        path: path.to_path_buf(),
        source,
    })?;
    let w = BufWriter::new(file);
    let result = if T::NAME == "f32" {
        let a = arr.mapv(|x| x.to_f64c() as f32);
        a.as_standard_layout().write_npy(w)
    } else {
        let a = arr.mapv(|x| x.to_f64c());
        a.as_standard_layout().write_npy(w)
    };
    result.map_err(|e| IoError::NpyWrite {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Reads an image `[H, W, C]` (C = 1, 3 or 4) from a `.png` or `.jpg`/`.jpeg` ([`read_png`],
/// which decodes either) or a `.npy` ([`read_npy`], which must be 3-D of that form), by file
/// extension (case-insensitive).
pub fn read_image<T: Real>(path: impl AsRef<Path>) -> Result<Array3<T>, IoError> {
    let path = path.as_ref();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    match ext.as_deref() {
        Some("png" | "jpg" | "jpeg") => read_png(path),
        Some("npy") => {
            let arr = read_npy::<T>(path)?;
            if !image_shape_ok(arr.shape()) {
                return Err(IoError::ImageShape {
                    path: path.to_path_buf(),
                    shape: arr.shape().to_vec(),
                });
            }
            Ok(arr.into_dimensionality::<Ix3>().expect("checked 3-D"))
        }
        _ => Err(IoError::Extension {
            path: path.to_path_buf(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array, IxDyn};

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("tapestry-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn png_round_trip_all_channel_counts() {
        for c in [1usize, 3, 4] {
            let img = Array3::<f64>::from_shape_fn((5, 7, c), |(r, col, k)| {
                (r * 7 * c + col * c + k) as f64 / 140.0
            });
            let p = tmp(&format!("rt{c}.png"));
            write_png(&p, &img).unwrap();
            let back: Array3<f64> = read_png(&p).unwrap();
            assert_eq!(back.shape(), &[5, 7, c]);
            for (a, b) in img.iter().zip(back.iter()) {
                assert!((a - b).abs() <= 0.5 / 255.0 + 1e-12, "{a} vs {b}");
            }
            // Quantised values survive exactly, also through f32 and a transposed view.
            let again: Array3<f32> = read_png(&p).unwrap();
            let p2 = tmp(&format!("rt{c}b.png"));
            write_png(&p2, &again.view()).unwrap();
            assert_eq!(read_png::<f32>(&p2).unwrap(), again);
        }
    }

    #[test]
    fn png_write_clamps_and_handles_nan() {
        let img = Array3::from_shape_vec((1, 4, 1), vec![-1.0, 2.0, f64::NAN, 0.5]).unwrap();
        let p = tmp("clamp.png");
        write_png(&p, &img).unwrap();
        let back: Array3<f64> = read_png(&p).unwrap();
        assert_eq!(
            back.iter().copied().collect::<Vec<_>>(),
            vec![0.0, 1.0, 0.0, 128.0 / 255.0]
        );
        assert_eq!(quantize(0.5), 128);
        // Non-standard layout: the logical order is written.
        let t = Array3::from_shape_fn((3, 2, 1), |(r, c, _)| (r * 2 + c) as f64 / 10.0);
        let f = t
            .clone()
            .reversed_axes()
            .as_standard_layout()
            .into_owned()
            .reversed_axes();
        assert!(!f.is_standard_layout());
        write_png(&p, &f).unwrap();
        let back: Array3<f64> = read_png(&p).unwrap();
        assert_eq!(back.map(|&x| quantize(x)), t.map(|&x| quantize(x)));
    }

    #[test]
    fn png_16_bit_and_bad_inputs() {
        let p = tmp("sixteen.png");
        let data: Vec<u16> = vec![0, 65535, 32768, 1000, 2000, 3000];
        let buf = image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(2, 1, data.clone()).unwrap();
        buf.save(&p).unwrap();
        let back: Array3<f64> = read_png(&p).unwrap();
        assert_eq!(back.shape(), &[1, 2, 3]);
        assert_eq!(back[[0, 0, 1]], 1.0);
        assert_eq!(back[[0, 1, 0]], 1000.0 / 65535.0);

        let la = tmp("la.png");
        image::GrayAlphaImage::new(2, 2).save(&la).unwrap();
        let e = read_png::<f64>(&la).unwrap_err();
        assert!(matches!(e, IoError::PixelFormat { channels: 2, .. }), "{e}");
        assert!(e.to_string().contains("la.png"));

        let bad = tmp("corrupt.png");
        std::fs::write(&bad, b"\x89PNG\r\n\x1a\nthis is not a png").unwrap();
        assert!(matches!(read_png::<f64>(&bad), Err(IoError::Decode { .. })));
        std::fs::write(&bad, b"plain text").unwrap();
        assert!(matches!(read_png::<f64>(&bad), Err(IoError::Decode { .. })));
        assert!(matches!(
            read_png::<f64>(tmp("missing.png")),
            Err(IoError::Open { .. })
        ));

        let two = Array3::<f64>::zeros((2, 2, 2));
        assert!(matches!(
            write_png(tmp("two.png"), &two),
            Err(IoError::ImageShape { .. })
        ));
        let empty = Array3::<f64>::zeros((0, 2, 3));
        assert!(matches!(
            write_png(tmp("empty.png"), &empty),
            Err(IoError::ImageShape { .. })
        ));
        let e = write_png(
            Path::new("/nonexistent/dir/x.png"),
            &Array3::<f64>::zeros((1, 1, 1)),
        )
        .unwrap_err();
        assert!(matches!(e, IoError::Write { .. }), "{e}");
    }

    #[test]
    fn npy_round_trips_any_dimension_and_converts_dtypes() {
        let a = Array::from_shape_fn(IxDyn(&[2, 3, 4, 2]), |ix| {
            (ix[0] * 100 + ix[1] * 10 + ix[2]) as f64 + 0.1 * ix[3] as f64
        });
        let p = tmp("a.npy");
        write_npy(&p, &a).unwrap();
        assert_eq!(read_npy::<f64>(&p).unwrap(), a);
        let as32: ArrayD<f32> = read_npy(&p).unwrap();
        assert_eq!(as32, a.mapv(|x| x as f32));
        let p32 = tmp("a32.npy");
        write_npy(&p32, &as32).unwrap();
        let header = std::fs::read(&p32).unwrap();
        let text = String::from_utf8_lossy(&header[..80]);
        assert!(
            text.contains("<f4") && text.contains("'fortran_order': False"),
            "{text}"
        );
        assert_eq!(read_npy::<f64>(&p32).unwrap(), as32.mapv(|x| x as f64));
        // Fortran-ordered input is written in C order and read back equal.
        let f = a.clone().reversed_axes();
        let pf = tmp("f.npy");
        write_npy(&pf, &f).unwrap();
        let text = String::from_utf8_lossy(&std::fs::read(&pf).unwrap()[..80]).to_string();
        assert!(text.contains("'fortran_order': False"), "{text}");
        assert_eq!(read_npy::<f64>(&pf).unwrap(), f);
        // 0-d and 1-d.
        let s = ndarray::arr0(2.5f64).into_dyn();
        write_npy(&p, &s).unwrap();
        assert_eq!(read_npy::<f64>(&p).unwrap(), s);
        assert!(read_npy_shape::<f64>(&p, &[]).is_ok());
    }

    #[test]
    fn npy_bad_inputs() {
        let p = tmp("int.npy");
        ndarray::arr1(&[1i64, 2, 3])
            .write_npy(File::create(&p).unwrap())
            .unwrap();
        let e = read_npy::<f64>(&p).unwrap_err();
        assert!(
            matches!(&e, IoError::Dtype { descr, .. } if descr.contains("i8")),
            "{e}"
        );
        assert!(e.to_string().contains("int.npy"));

        let p = tmp("shape.npy");
        write_npy(&p, &Array::<f64, _>::zeros((4, 3))).unwrap();
        let e = read_npy_shape::<f64>(&p, &[4, 2]).unwrap_err();
        assert!(matches!(e, IoError::Shape { .. }));
        assert!(
            e.to_string()
                .ends_with("array has shape [4, 3], expected [4, 2]"),
            "{e}"
        );
        assert!(matches!(
            read_image::<f64>(&p),
            Err(IoError::ImageShape { .. })
        ));

        let p = tmp("garbage.npy");
        std::fs::write(&p, b"\x93NUMPY garbage").unwrap();
        assert!(matches!(read_npy::<f64>(&p), Err(IoError::Npy { .. })));
        write_npy(&p, &Array::<f64, _>::zeros((8, 8))).unwrap();
        let mut bytes = std::fs::read(&p).unwrap();
        bytes.truncate(bytes.len() - 3);
        std::fs::write(&p, &bytes).unwrap();
        assert!(matches!(read_npy::<f64>(&p), Err(IoError::Npy { .. })));
        assert!(matches!(
            read_npy::<f64>(tmp("missing.npy")),
            Err(IoError::Open { .. })
        ));
        assert!(matches!(
            read_image::<f64>(tmp("x.tiff")),
            Err(IoError::Extension { .. })
        ));
    }

    #[test]
    fn read_image_dispatches_on_extension() {
        let img = Array3::<f64>::from_elem((2, 3, 4), 0.25);
        let p = tmp("img.NPY");
        write_npy(&p, &img).unwrap();
        assert_eq!(read_image::<f64>(&p).unwrap(), img);
        let q = tmp("img.png");
        write_png(&q, &img).unwrap();
        assert_eq!(read_image::<f64>(&q).unwrap().shape(), &[2, 3, 4]);
    }
}
