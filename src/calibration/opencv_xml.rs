//! A reader for the subset of OpenCV's XML `FileStorage` format that calibrations are published
//! in (the YAML syntax is [`super::opencv_yaml`]'s; both share [`OpenCvMatrix`] and [`lens`]): top-level `<name type_id="opencv-matrix">` elements with `<rows>`, `<cols>`,
//! `<dt>d</dt>` and whitespace-separated `<data>`, and top-level scalars `<name>value</name>`.
//!
//! [`ReferenceCalibration::parse`] reads (from XML or YAML) the projector-camera result of the `procam-calibration`
//! tool: `cam_int`, `cam_dist`, `proj_int`, `proj_dist` (3x3 matrices and `k1 k2 p1 p2 k3`),
//! `roration` (sic; `rotation` is accepted too) and `translation` (projector <- camera).
//! OpenCV puts pixel centres at integer coordinates; this project puts them at `+0.5` (see
//! [`crate::geometry`]), so the principal points are shifted by half a pixel on reading.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};

use crate::geometry::Intrinsics;

/// Why a FileStorage file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum OpenCvXmlError {
    /// The file could not be read.
    #[error("cannot read {}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// A needed element is missing.
    #[error("{}: no element <{field}>", path.display())]
    Missing {
        /// The file.
        path: PathBuf,
        /// The element's name.
        field: String,
    },
    /// An element is malformed.
    #[error("{}:{line}: <{field}>: {reason}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// 1-based line of the element's start.
        line: usize,
        /// The element's name.
        field: String,
        /// What is wrong.
        reason: String,
    },
}

/// A matrix element of a FileStorage file.
#[derive(Debug, Clone, PartialEq)]
pub struct OpenCvMatrix {
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Row-major values.
    pub data: Vec<f64>,
    /// 1-based line where the element starts.
    pub line: usize,
}

/// The text between `<tag>` and `</tag>` inside `s`, if present.
fn inner<'a>(s: &'a str, tag: &str) -> Option<&'a str> {
    let open = format!("<{tag}>");
    let a = s.find(&open)? + open.len();
    let b = a + s[a..].find(&format!("</{tag}>"))?;
    Some(&s[a..b])
}

/// Byte range of the body of the top-level element `name` (between its start tag's `>` and its end
/// tag) and the line it starts on.
pub(super) fn element<'a>(text: &'a str, name: &str) -> Option<(&'a str, usize)> {
    let mut from = 0;
    while let Some(off) = text[from..].find(&format!("<{name}")) {
        let start = from + off;
        let after = start + 1 + name.len();
        // The name must end here (`<cam_int>` or `<cam_int type_id=...>`), not be a prefix.
        if matches!(text.as_bytes().get(after), Some(b'>') | Some(b' ') | Some(b'\t') | Some(b'\n') | Some(b'\r')) {
            let gt = after + text[after..].find('>')?;
            let close = format!("</{name}>");
            let end = gt + 1 + text[gt + 1..].find(&close)?;
            let line = 1 + text[..start].bytes().filter(|&b| b == b'\n').count();
            return Some((&text[gt + 1..end], line));
        }
        from = after;
    }
    None
}

/// Read the matrix element `name` from the FileStorage `text` (of the file `path`, for errors).
pub fn read_matrix(text: &str, path: &Path, name: &str) -> Result<OpenCvMatrix, OpenCvXmlError> {
    let (body, line) =
        element(text, name).ok_or_else(|| OpenCvXmlError::Missing { path: path.to_path_buf(), field: name.into() })?;
    let bad = |reason: String| OpenCvXmlError::Malformed { path: path.to_path_buf(), line, field: name.into(), reason };
    let int = |tag: &str| -> Result<usize, OpenCvXmlError> {
        let s = inner(body, tag).ok_or_else(|| bad(format!("no <{tag}>")))?;
        s.trim().parse::<usize>().map_err(|_| bad(format!("<{tag}> is not a count: {:?}", s.trim())))
    };
    let rows = int("rows")?;
    let cols = int("cols")?;
    let data_s = inner(body, "data").ok_or_else(|| bad("no <data>".into()))?;
    let data = data_s
        .split_whitespace()
        .map(|t| t.parse::<f64>().map_err(|_| bad(format!("{t:?} is not a number"))))
        .collect::<Result<Vec<f64>, _>>()?;
    if data.len() != rows * cols {
        return Err(bad(format!("{} values for a {rows}x{cols} matrix", data.len())));
    }
    if let Some(v) = data.iter().find(|v| !v.is_finite()) {
        return Err(bad(format!("non-finite value {v}")));
    }
    Ok(OpenCvMatrix { rows, cols, data, line })
}

/// The lens of a FileStorage camera matrix `k` (3x3, named `k_name` in errors) and distortion
/// `d` (`k1 k2 p1 p2 k3` then OpenCV's rational, thin-prism and tilt terms, which must be 0; 4, 5,
/// 8, 12 or 14 terms, or none), with the principal point shifted to this project's pixel centres.
pub fn lens(
    path: &Path,
    k_name: &str,
    k: &OpenCvMatrix,
    d: Option<&OpenCvMatrix>,
) -> Result<Intrinsics, OpenCvXmlError> {
    let bad = |line: usize, reason: String| OpenCvXmlError::Malformed {
        path: path.to_path_buf(),
        line,
        field: k_name.into(),
        reason,
    };
    if (k.rows, k.cols) != (3, 3) {
        return Err(bad(k.line, format!("a camera matrix is 3x3, got {}x{}", k.rows, k.cols)));
    }
    let terms = d.map_or(&[][..], |d| &d.data[..]);
    let d_line = d.map_or(k.line, |d| d.line);
    if !matches!(terms.len(), 0 | 4 | 5 | 8 | 12 | 14) {
        return Err(bad(d_line, format!("{} distortion terms (expected 4, 5, 8, 12 or 14)", terms.len())));
    }
    if terms.iter().skip(5).any(|v| *v != 0.0) {
        return Err(bad(
            d_line,
            "rational, thin-prism or tilt distortion terms (beyond k1 k2 p1 p2 k3) are not supported".into(),
        ));
    }
    let term = |i: usize| terms.get(i).copied().unwrap_or(0.0);
    let lens = Intrinsics {
        fx: k.data[0],
        fy: k.data[4],
        cx: k.data[2] + 0.5,
        cy: k.data[5] + 0.5,
        skew: k.data[1],
        ..Intrinsics::default()
    }
    .with_distortion([term(0), term(1), term(2), term(3), term(4)]);
    if !lens.is_valid() {
        return Err(bad(k.line, "focal lengths must be positive".into()));
    }
    Ok(lens)
}

/// A published projector-camera calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceCalibration {
    /// Camera intrinsics (principal point shifted to this project's pixel-centre convention).
    pub camera: Intrinsics,
    /// Projector intrinsics (likewise).
    pub projector: Intrinsics,
    /// Rotation projector <- camera.
    pub rotation: Matrix3<f64>,
    /// Translation projector <- camera, in the unit of the board used (the set's square size).
    pub translation: Vector3<f64>,
    /// The published overall re-projection RMS, pixels, when the file has `<rms>`.
    pub rms_px: Option<f64>,
}

impl ReferenceCalibration {
    /// Read a `calibration_result.xml` file.
    pub fn load(path: &Path) -> Result<ReferenceCalibration, OpenCvXmlError> {
        let text =
            std::fs::read_to_string(path).map_err(|source| OpenCvXmlError::Io { path: path.to_path_buf(), source })?;
        Self::parse(&text, path)
    }

    /// Parse the text of a `calibration_result.xml` file (`path` names it in errors).
    pub fn parse(text: &str, path: &Path) -> Result<ReferenceCalibration, OpenCvXmlError> {
        let read = |name: &str| super::opencv_yaml::read_any_matrix(text, path, name);
        let lens = |k_name: &str, d_name: &str| -> Result<Intrinsics, OpenCvXmlError> {
            let d = read(d_name)?;
            if !matches!(d.data.len(), 4 | 5) {
                return Err(OpenCvXmlError::Malformed {
                    path: path.to_path_buf(),
                    line: d.line,
                    field: d_name.into(),
                    reason: format!("expected 4 or 5 distortion terms (k1 k2 p1 p2 [k3]), got {}", d.data.len()),
                });
            }
            lens(path, k_name, &read(k_name)?, Some(&d))
        };
        let camera = lens("cam_int", "cam_dist")?;
        let projector = lens("proj_int", "proj_dist")?;
        let r = match read("roration") {
            Err(OpenCvXmlError::Missing { .. }) => read("rotation")?,
            other => other?,
        };
        let t = read("translation")?;
        if (r.rows, r.cols) != (3, 3) {
            return Err(OpenCvXmlError::Malformed {
                path: path.to_path_buf(),
                line: r.line,
                field: "roration".into(),
                reason: format!("a rotation is 3x3, got {}x{}", r.rows, r.cols),
            });
        }
        if t.data.len() != 3 {
            return Err(OpenCvXmlError::Malformed {
                path: path.to_path_buf(),
                line: t.line,
                field: "translation".into(),
                reason: format!("a translation has 3 values, got {}", t.data.len()),
            });
        }
        let rotation = Matrix3::from_row_slice(&r.data);
        let orth = (rotation.transpose() * rotation - Matrix3::identity()).norm();
        if orth > 1e-3 || rotation.determinant() < 0.0 {
            return Err(OpenCvXmlError::Malformed {
                path: path.to_path_buf(),
                line: r.line,
                field: "roration".into(),
                reason: format!("not a rotation (|RᵀR - I| = {orth:.2e})"),
            });
        }
        let rms_px = super::opencv_yaml::scalar(text, "rms");
        Ok(ReferenceCalibration {
            camera,
            projector,
            rotation,
            translation: Vector3::from_column_slice(&t.data),
            rms_px,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SAMPLE: &str = r#"<?xml version="1.0"?>
<opencv_storage>
<rms>8.5e-01</rms>
<cam_int type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    1000. 0. 320. 0.
    1010. 240. 0. 0. 1.</data></cam_int>
<cam_dist type_id="opencv-matrix">
  <rows>1</rows><cols>5</cols><dt>d</dt>
  <data>-0.1 0.05 0.001 -0.002 0.3</data></cam_dist>
<proj_int type_id="opencv-matrix">
  <rows>3</rows><cols>3</cols><dt>d</dt>
  <data>2000. 0. 512. 0. 2000. 700. 0. 0. 1.</data></proj_int>
<proj_dist type_id="opencv-matrix">
  <rows>1</rows><cols>5</cols><dt>d</dt>
  <data>0 0 0 0 0</data></proj_dist>
<roration type_id="opencv-matrix">
  <rows>3</rows><cols>3</cols><dt>d</dt>
  <data>1 0 0 0 1 0 0 0 1</data></roration>
<translation type_id="opencv-matrix">
  <rows>3</rows><cols>1</cols><dt>d</dt>
  <data>100 -600 -100</data></translation>
</opencv_storage>
"#;

    #[test]
    fn reads_the_published_fields_with_the_pixel_centre_shift() {
        let c = ReferenceCalibration::parse(SAMPLE, Path::new("c.xml")).expect("parses");
        assert_eq!((c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy), (1000.0, 1010.0, 320.5, 240.5));
        assert_eq!((c.camera.k1, c.camera.k2, c.camera.p1, c.camera.p2, c.camera.k3), (-0.1, 0.05, 0.001, -0.002, 0.3));
        assert_eq!(c.projector.cy, 700.5);
        assert_eq!(c.translation, Vector3::new(100.0, -600.0, -100.0));
        assert_eq!(c.rotation, Matrix3::identity());
        assert_eq!(c.rms_px, Some(0.85));
    }

    #[test]
    fn errors_name_the_field_and_line() {
        let missing = SAMPLE.replace("proj_dist", "proj_distortion");
        let e = ReferenceCalibration::parse(&missing, Path::new("c.xml")).expect_err("must be refused");
        assert!(e.to_string().contains("<proj_dist>"), "{e}");
        let short = SAMPLE.replace("<data>100 -600 -100</data>", "<data>100 -600</data>");
        let e = ReferenceCalibration::parse(&short, Path::new("c.xml")).expect_err("must be refused");
        let msg = e.to_string();
        assert!(msg.contains("c.xml:23") && msg.contains("<translation>") && msg.contains("2 values"), "{msg}");
        let nan = SAMPLE.replace("1000. 0. 320.", "1000. 0. abc");
        let e = ReferenceCalibration::parse(&nan, Path::new("c.xml")).expect_err("must be refused");
        assert!(e.to_string().contains("\"abc\" is not a number"), "{e}");
        let not_rot = SAMPLE.replace("<data>1 0 0 0 1 0 0 0 1</data>", "<data>2 0 0 0 1 0 0 0 1</data>");
        let e = ReferenceCalibration::parse(&not_rot, Path::new("c.xml")).expect_err("must be refused");
        assert!(e.to_string().contains("not a rotation"), "{e}");
        let io = ReferenceCalibration::load(Path::new("/nonexistent/c.xml")).expect_err("must be refused");
        assert!(matches!(io, OpenCvXmlError::Io { .. }));
    }
}
