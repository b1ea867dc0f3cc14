//! Camera intrinsics in OpenCV FileStorage files, YAML (`%YAML:1.0`, `!!opencv-matrix`) and XML
//! (`<opencv_storage>`), as OpenCV's calibration sample and most tools write them.
//!
//! - Read: the camera matrix under one of `camera_matrix`, `cameraMatrix`, `K`, `cam_int`, `M1`, and
//!   the distortion under one of `distortion_coefficients`, `distCoeffs`, `dist_coeffs`, `D`,
//!   `cam_dist`, `D1` (4, 5, 8, 12 or 14 terms; the first five are `k1 k2 p1 p2 k3` and any further
//!   rational/prism/tilt term must be 0); `image_width` / `image_height` when present.
//! - Write ([`camera_yaml`]): `image_width`, `image_height`, `camera_matrix`,
//!   `distortion_coefficients` (5 terms), `avg_reprojection_error`.
//!
//! Pixel convention: OpenCV puts pixel centres at integer coordinates, this project at `+0.5` (see
//! [`crate::geometry`]); reading adds 0.5 to `cx`, `cy`, writing subtracts it.

use std::path::Path;

use super::opencv_xml::{read_matrix, OpenCvMatrix, OpenCvXmlError};
use crate::geometry::Intrinsics;

const K_NAMES: [&str; 5] = ["camera_matrix", "cameraMatrix", "K", "cam_int", "M1"];
const D_NAMES: [&str; 6] = ["distortion_coefficients", "distCoeffs", "dist_coeffs", "D", "cam_dist", "D1"];

/// A camera read from a FileStorage file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpenCvCamera {
    /// Intrinsics, this project's pixel convention.
    pub intrinsics: Intrinsics,
    /// `image_width`, `image_height` when the file has them, pixels.
    pub size: Option<(u32, u32)>,
}

/// The YAML matrix `name: !!opencv-matrix` (rows, cols, data: [..]) of `text`.
pub fn read_yaml_matrix(text: &str, path: &Path, name: &str) -> Result<OpenCvMatrix, OpenCvXmlError> {
    let key = format!("{name}:");
    let start = text
        .lines()
        .enumerate()
        .find(|(_, l)| l.trim_start().starts_with(&key) && l.contains("opencv-matrix") && !l.starts_with(' '))
        .map(|(i, _)| i)
        .ok_or_else(|| OpenCvXmlError::Missing { path: path.to_path_buf(), field: name.into() })?;
    let line = start + 1;
    let bad = |reason: String| OpenCvXmlError::Malformed { path: path.to_path_buf(), line, field: name.into(), reason };
    let body: Vec<&str> = text.lines().skip(start + 1).collect();
    let field = |f: &str| -> Result<usize, OpenCvXmlError> {
        body.iter()
            .take_while(|l| l.starts_with(' ') || l.trim().is_empty())
            .find_map(|l| l.trim().strip_prefix(&format!("{f}:")).map(|v| v.trim().to_string()))
            .ok_or_else(|| bad(format!("no {f}")))?
            .parse()
            .map_err(|_| bad(format!("{f} is not a count")))
    };
    let (rows, cols) = (field("rows")?, field("cols")?);
    let joined = body.join("\n");
    let a = joined.find("data:").ok_or_else(|| bad("no data".into()))?;
    let open = a + joined[a..].find('[').ok_or_else(|| bad("data is not a [list]".into()))?;
    let close = open + joined[open..].find(']').ok_or_else(|| bad("unterminated data list".into()))?;
    let data = joined[open + 1..close]
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
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

fn is_yaml(text: &str) -> bool {
    let t = text.trim_start();
    t.starts_with("%YAML") || (!t.starts_with('<') && t.contains("opencv-matrix"))
}

fn find_any(text: &str, path: &Path, names: &[&str]) -> Result<OpenCvMatrix, OpenCvXmlError> {
    for n in names {
        let r = if is_yaml(text) { read_yaml_matrix(text, path, n) } else { read_matrix(text, path, n) };
        match r {
            Err(OpenCvXmlError::Missing { .. }) => continue,
            other => return other,
        }
    }
    Err(OpenCvXmlError::Missing { path: path.to_path_buf(), field: names.join(" | ") })
}

fn scalar(text: &str, name: &str) -> Option<u32> {
    if is_yaml(text) {
        text.lines().find_map(|l| l.strip_prefix(&format!("{name}:")).and_then(|v| v.trim().parse().ok()))
    } else {
        let open = format!("<{name}>");
        let a = text.find(&open)? + open.len();
        let b = a + text[a..].find('<')?;
        text[a..b].trim().parse().ok()
    }
}

/// Parse a FileStorage file's camera (`path` names it in errors).
pub fn parse_camera(text: &str, path: &Path) -> Result<OpenCvCamera, OpenCvXmlError> {
    let k = find_any(text, path, &K_NAMES)?;
    let bad = |m: &OpenCvMatrix, field: &str, reason: String| OpenCvXmlError::Malformed {
        path: path.to_path_buf(),
        line: m.line,
        field: field.into(),
        reason,
    };
    if (k.rows, k.cols) != (3, 3) {
        return Err(bad(&k, "camera_matrix", format!("a camera matrix is 3x3, got {}x{}", k.rows, k.cols)));
    }
    let d = match find_any(text, path, &D_NAMES) {
        Ok(d) => d.data.clone(),
        Err(OpenCvXmlError::Missing { .. }) => Vec::new(),
        Err(e) => return Err(e),
    };
    if !matches!(d.len(), 0 | 4 | 5 | 8 | 12 | 14) {
        return Err(bad(&k, "distortion_coefficients", format!("{} terms (expected 4, 5, 8, 12 or 14)", d.len())));
    }
    if d.iter().skip(5).any(|v| *v != 0.0) {
        return Err(bad(
            &k,
            "distortion_coefficients",
            "rational, thin-prism or tilt terms (beyond k1 k2 p1 p2 k3) are not supported".into(),
        ));
    }
    let term = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let intrinsics = Intrinsics {
        fx: k.data[0],
        fy: k.data[4],
        cx: k.data[2] + 0.5,
        cy: k.data[5] + 0.5,
        skew: k.data[1],
        ..Intrinsics::default()
    }
    .with_distortion([term(0), term(1), term(2), term(3), term(4)]);
    if !intrinsics.is_valid() {
        return Err(bad(&k, "camera_matrix", "focal lengths must be positive".into()));
    }
    let size = scalar(text, "image_width").zip(scalar(text, "image_height"));
    Ok(OpenCvCamera { intrinsics, size })
}

/// Read a FileStorage file's camera (YAML or XML).
pub fn load_camera(path: &Path) -> Result<OpenCvCamera, OpenCvXmlError> {
    let text =
        std::fs::read_to_string(path).map_err(|source| OpenCvXmlError::Io { path: path.to_path_buf(), source })?;
    parse_camera(&text, path)
}

/// A FileStorage YAML text of a calibrated camera (OpenCV's calibration sample's keys).
pub fn camera_yaml(i: &Intrinsics, width: u32, height: u32, rms_px: f64) -> String {
    let d = i.distortion();
    format!(
        "%YAML:1.0\n---\nimage_width: {width}\nimage_height: {height}\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ {:.17e}, {:.17e}, {:.17e}, 0., {:.17e}, {:.17e}, 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ {:.17e}, {:.17e}, {:.17e}, {:.17e}, {:.17e} ]\navg_reprojection_error: {rms_px:.17e}\n",
        i.fx,
        i.skew,
        i.cx - 0.5,
        i.fy,
        i.cy - 0.5,
        d[0],
        d[1],
        d[2],
        d[3],
        d[4]
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaml_round_trips_and_xml_reads() {
        let i = Intrinsics::new(1430.4, 1429.7, 480.5, 640.25).with_distortion([0.027, -0.23, -7.1e-5, 8.7e-4, 0.51]);
        let text = camera_yaml(&i, 960, 1280, 0.31);
        let back = parse_camera(&text, Path::new("c.yaml")).expect("yaml");
        assert_eq!(back.size, Some((960, 1280)));
        let (a, b) = (back.intrinsics, i);
        assert!((a.fx - b.fx).abs() < 1e-9 && (a.cx - b.cx).abs() < 1e-9 && (a.k3 - b.k3).abs() < 1e-12, "{a:?}");
        let xml = "<?xml version=\"1.0\"?>\n<opencv_storage>\n<image_width>640</image_width>\n<image_height>480</image_height>\n<cameraMatrix type_id=\"opencv-matrix\">\n  <rows>3</rows>\n  <cols>3</cols>\n  <dt>d</dt>\n  <data>\n    800. 0. 319.5 0. 790. 239.5 0. 0. 1.</data></cameraMatrix>\n<distCoeffs type_id=\"opencv-matrix\">\n  <rows>5</rows>\n  <cols>1</cols>\n  <dt>d</dt>\n  <data>\n    -0.1 0.01 0. 0. 0.</data></distCoeffs>\n</opencv_storage>\n";
        let c = parse_camera(xml, Path::new("c.xml")).expect("xml");
        assert_eq!(c.size, Some((640, 480)));
        assert_eq!((c.intrinsics.cx, c.intrinsics.cy, c.intrinsics.k1), (320.0, 240.0, -0.1));
        let e = parse_camera(
            "%YAML:1.0\nK: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 2 ]\n",
            Path::new("k.yaml"),
        )
        .expect_err("short");
        assert!(e.to_string().starts_with("k.yaml:2:"), "{e}");
    }
}
