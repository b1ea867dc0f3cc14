//! Camera intrinsics in OpenCV FileStorage files, YAML (`%YAML:1.0`, `!!opencv-matrix`) and XML
//! (`<opencv_storage>`), as OpenCV's calibration sample and most tools write them.
//!
//! - Read: the camera matrix under one of `camera_matrix`, `cameraMatrix`, `K`, `cam_int`, `M1`, and
//!   the distortion under one of `distortion_coefficients`, `distCoeffs`, `dist_coeffs`, `D`,
//!   `cam_dist`, `D1` (4, 5, 8, 12 or 14 terms; the first five are `k1 k2 p1 p2 k3` and any further
//!   rational/prism/tilt term must be 0); `image_width` / `image_height` when present.
//! - Read several views of one camera ([`parse_views`]): OpenCV's calibration sample's
//!   `extrinsic_parameters` (one row per view: Rodrigues vector, translation) with the views' image
//!   names in the string sequence `images`, as OpenCV's `imagelist_creator` writes it.
//! - Write ([`camera_yaml`]): `image_width`, `image_height`, `camera_matrix`,
//!   `distortion_coefficients` (5 terms), `avg_reprojection_error`.
//!
//! Pixel convention: OpenCV puts pixel centres at integer coordinates, this project at `+0.5` (see
//! [`crate::geometry`]); reading adds 0.5 to `cx`, `cy`, writing subtracts it.

use std::path::Path;

use super::opencv_xml::{element, lens, read_matrix, OpenCvMatrix, OpenCvXmlError};
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::geometry::{Intrinsics, Pose};

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

/// Whether `text` is an OpenCV FileStorage file (YAML `%YAML:1.0` or XML `<opencv_storage>`).
pub fn is_file_storage(text: &str) -> bool {
    let t = text.trim_start();
    t.starts_with("%YAML") || ((t.starts_with("<?xml") || t.starts_with('<')) && t.contains("<opencv_storage"))
}

/// The matrix `name` of a FileStorage file, YAML or XML (told apart by content).
pub fn read_any_matrix(text: &str, path: &Path, name: &str) -> Result<OpenCvMatrix, OpenCvXmlError> {
    if is_yaml(text) {
        read_yaml_matrix(text, path, name)
    } else {
        read_matrix(text, path, name)
    }
}

/// The first of `names` present (its name and matrix).
fn find_any<'n>(text: &str, path: &Path, names: &[&'n str]) -> Result<(&'n str, OpenCvMatrix), OpenCvXmlError> {
    for n in names {
        match read_any_matrix(text, path, n) {
            Err(OpenCvXmlError::Missing { .. }) => continue,
            other => return other.map(|m| (*n, m)),
        }
    }
    Err(OpenCvXmlError::Missing { path: path.to_path_buf(), field: names.join(" | ") })
}

/// The top-level scalar `name` of a FileStorage file, YAML (`name: value`) or XML
/// (`<name>value</name>`), when present and a number.
pub fn scalar(text: &str, name: &str) -> Option<f64> {
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
    let (k_name, k) = find_any(text, path, &K_NAMES)?;
    let d = match find_any(text, path, &D_NAMES) {
        Ok((_, d)) => Some(d),
        Err(OpenCvXmlError::Missing { .. }) => None,
        Err(e) => return Err(e),
    };
    let intrinsics = lens(path, k_name, &k, d.as_ref())?;
    let dim = |n: &str| scalar(text, n).filter(|v| *v >= 1.0 && v.fract() == 0.0 && *v <= f64::from(u32::MAX));
    let size = dim("image_width").zip(dim("image_height")).map(|(w, h)| (w as u32, h as u32));
    Ok(OpenCvCamera { intrinsics, size })
}

/// The rotation of `v` (9 values row-major, or a Rodrigues vector of 3, radians) from the matrix `m`
/// named `name`; an error naming the file and line when it is neither or not a rotation.
fn rotation(path: &Path, name: &str, m: &OpenCvMatrix, v: &[f64]) -> Result<Matrix3<f64>, OpenCvXmlError> {
    let bad = |reason: String| OpenCvXmlError::Malformed {
        path: path.to_path_buf(),
        line: m.line,
        field: name.into(),
        reason,
    };
    let r = match v.len() {
        9 => Matrix3::from_row_slice(v),
        3 => *Rotation3::new(Vector3::new(v[0], v[1], v[2])).matrix(),
        n => return Err(bad(format!("a rotation is 3x3 or a Rodrigues vector of 3, got {n} values"))),
    };
    let orth = (r.transpose() * r - Matrix3::identity()).norm();
    if orth > 1e-3 || r.determinant() < 0.0 {
        return Err(bad(format!("not a rotation (|RᵀR - I| = {orth:.2e})")));
    }
    Ok(r)
}

/// A FileStorage camera and, when the file has one, its pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpenCvCalibration {
    /// The camera.
    pub camera: OpenCvCamera,
    /// Rig (turntable) frame -> camera frame, `x_cam = R x_rig + t`, metres.
    pub pose: Option<Pose>,
}

const R_NAMES: [&str; 3] = ["R", "rotation", "rvec"];
const T_NAMES: [&str; 3] = ["T", "translation", "tvec"];

/// Parse a FileStorage file's camera and pose (`path` names it in errors). The pose, rig
/// (turntable) frame -> camera frame in metres, is read from `R` | `rotation` | `rvec` (a 3x3
/// rotation or a Rodrigues vector of 3) with `T` | `translation` | `tvec` (3 values), else from
/// `extrinsic_parameters` when it holds one view (1x6: Rodrigues vector, translation), as OpenCV's
/// calibration sample writes it for a single view.
pub fn parse_calibration(text: &str, path: &Path) -> Result<OpenCvCalibration, OpenCvXmlError> {
    let camera = parse_camera(text, path)?;
    let bad = |m: &OpenCvMatrix, field: &str, reason: String| OpenCvXmlError::Malformed {
        path: path.to_path_buf(),
        line: m.line,
        field: field.into(),
        reason,
    };
    let optional = |names: &[&'static str]| match find_any(text, path, names) {
        Ok(x) => Ok(Some(x)),
        Err(OpenCvXmlError::Missing { .. }) => Ok(None),
        Err(e) => Err(e),
    };
    let pose = match (optional(&R_NAMES)?, optional(&T_NAMES)?) {
        (Some((rn, r)), Some((tn, t))) => {
            if t.data.len() != 3 {
                return Err(bad(&t, tn, format!("a translation has 3 values, got {}", t.data.len())));
            }
            Some(Pose { rotation: rotation(path, rn, &r, &r.data)?, translation: Vector3::from_column_slice(&t.data) })
        }
        (Some((n, m)), None) | (None, Some((n, m))) => {
            return Err(bad(&m, n, "a pose needs both a rotation (R) and a translation (T)".into()))
        }
        (None, None) => match optional(&["extrinsic_parameters"])? {
            Some((n, e)) if e.data.len() == 6 => Some(Pose {
                rotation: rotation(path, n, &e, &e.data[..3])?,
                translation: Vector3::from_column_slice(&e.data[3..]),
            }),
            _ => None,
        },
    };
    Ok(OpenCvCalibration { camera, pose })
}

/// One view of an [`OpenCvViews`] file.
#[derive(Debug, Clone, PartialEq)]
pub struct OpenCvView {
    /// Image file name, as the file lists it.
    pub name: String,
    /// World (board) frame -> camera frame, `x_cam = R x_world + t`; translation in the file's
    /// length unit (metres when the board's square size was given in metres).
    pub pose: Pose,
}

/// One camera seen in several views, read from a FileStorage file (see [`parse_views`]).
#[derive(Debug, Clone, PartialEq)]
pub struct OpenCvViews {
    /// The camera, this project's pixel convention.
    pub camera: OpenCvCamera,
    /// The views, in the file's order.
    pub views: Vec<OpenCvView>,
    /// 1-based line of `extrinsic_parameters`.
    pub line: usize,
}

/// The string sequence `name` of a FileStorage file: YAML `name:` followed by `- item` lines or an
/// inline `[ "a", "b" ]`; XML `<name>a "b c"</name>` (whitespace-separated, quoted when an item holds
/// a space). `None` when the file has no such entry; the 1-based line of the entry with the items.
pub fn read_string_list(text: &str, name: &str) -> Option<(Vec<String>, usize)> {
    let unquote = |t: &str| t.trim().trim_matches('"').trim_matches('\'').to_string();
    if is_yaml(text) {
        let key = format!("{name}:");
        let lines: Vec<&str> = text.lines().collect();
        let start = lines.iter().position(|l| l.starts_with(&key))?;
        let rest = lines[start][key.len()..].trim();
        let items = if let Some(inline) = rest.strip_prefix('[') {
            let inline = inline.trim_end().trim_end_matches(']');
            inline.split(',').map(unquote).filter(|t| !t.is_empty()).collect()
        } else {
            lines[start + 1..]
                .iter()
                .take_while(|l| l.starts_with(' ') || l.starts_with('-') || l.trim().is_empty())
                .filter_map(|l| l.trim().strip_prefix('-').map(unquote))
                .collect()
        };
        return Some((items, start + 1));
    }
    let (body, line) = element(text, name)?;
    let mut items = Vec::new();
    let mut chars = body.trim().chars().peekable();
    while let Some(&c) = chars.peek() {
        if c.is_whitespace() {
            chars.next();
        } else if c == '"' {
            chars.next();
            items.push(chars.by_ref().take_while(|&c| c != '"').collect());
        } else {
            let mut item = String::new();
            while let Some(&c) = chars.peek() {
                if c.is_whitespace() {
                    break;
                }
                item.push(c);
                chars.next();
            }
            items.push(item);
        }
    }
    Some((items, line))
}

/// Parse a FileStorage file holding one camera and several views of it (`path` names it in
/// errors): the camera as [`parse_camera`] reads it, `extrinsic_parameters` (N x 6: each row a
/// Rodrigues vector, radians, and a translation, world -> camera, as OpenCV's calibration sample
/// writes it) and the image names of the N views in the string sequence `images`, in the same
/// order.
pub fn parse_views(text: &str, path: &Path) -> Result<OpenCvViews, OpenCvXmlError> {
    let camera = parse_camera(text, path)?;
    let field = "extrinsic_parameters";
    let e = read_any_matrix(text, path, field)?;
    let bad = |line: usize, field: &str, reason: String| OpenCvXmlError::Malformed {
        path: path.to_path_buf(),
        line,
        field: field.into(),
        reason,
    };
    if e.cols != 6 || e.rows == 0 {
        return Err(bad(
            e.line,
            field,
            format!("one row of 6 (Rodrigues vector, translation) per view, got {}x{}", e.rows, e.cols),
        ));
    }
    let (names, names_line) = read_string_list(text, "images").ok_or_else(|| OpenCvXmlError::Missing {
        path: path.to_path_buf(),
        field: "images (the views' image names, one per row of extrinsic_parameters)".into(),
    })?;
    if names.len() != e.rows {
        return Err(bad(
            names_line,
            "images",
            format!("{} image names for the {} views of extrinsic_parameters (line {})", names.len(), e.rows, e.line),
        ));
    }
    let views = names
        .into_iter()
        .zip(e.data.chunks_exact(6))
        .map(|(name, row)| {
            Ok(OpenCvView {
                name,
                pose: Pose {
                    rotation: rotation(path, field, &e, &row[..3])?,
                    translation: Vector3::from_column_slice(&row[3..]),
                },
            })
        })
        .collect::<Result<Vec<_>, OpenCvXmlError>>()?;
    Ok(OpenCvViews { camera, views, line: e.line })
}

/// Read a FileStorage file's camera and pose (see [`parse_calibration`]).
pub fn load_calibration(path: &Path) -> Result<OpenCvCalibration, OpenCvXmlError> {
    let text =
        std::fs::read_to_string(path).map_err(|source| OpenCvXmlError::Io { path: path.to_path_buf(), source })?;
    parse_calibration(&text, path)
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
    fn poses_read_from_r_t_rodrigues_or_one_view_extrinsics() {
        let i = Intrinsics::new(800.0, 800.0, 320.5, 240.5);
        let cam = camera_yaml(&i, 640, 480, 0.1);
        let m = |name: &str, r: usize, c: usize, v: &str| {
            format!("{name}: !!opencv-matrix\n   rows: {r}\n   cols: {c}\n   dt: d\n   data: [ {v} ]\n")
        };
        let p = Path::new("c.yaml");
        assert_eq!(parse_calibration(&cam, p).expect("no pose").pose, None);
        let rt = format!("{cam}{}{}", m("R", 3, 3, "1, 0, 0, 0, 0, -1, 0, 1, 0"), m("T", 3, 1, "0.1, 0.2, 0.5"));
        let pose = parse_calibration(&rt, p).expect("R T").pose.expect("pose");
        assert_eq!(pose.rotation[(1, 2)], -1.0);
        assert_eq!(pose.translation, Vector3::new(0.1, 0.2, 0.5));
        // The same rotation as a Rodrigues vector (90 degrees about x), and as one view's extrinsics.
        let h = std::f64::consts::FRAC_PI_2;
        let rv = format!("{cam}{}{}", m("rvec", 3, 1, &format!("{h}, 0, 0")), m("tvec", 3, 1, "0.1, 0.2, 0.5"));
        let a = parse_calibration(&rv, p).expect("rvec").pose.expect("pose");
        assert!((a.rotation - pose.rotation).norm() < 1e-12, "{a:?}");
        let ex = format!("{cam}{}", m("extrinsic_parameters", 1, 6, &format!("{h}, 0, 0, 0.1, 0.2, 0.5")));
        let b = parse_calibration(&ex, p).expect("extrinsics").pose.expect("pose");
        assert!((b.rotation - pose.rotation).norm() < 1e-12 && b.translation == pose.translation);
        let half = format!("{cam}{}", m("R", 3, 3, "1, 0, 0, 0, 1, 0, 0, 0, 1"));
        assert!(parse_calibration(&half, p).expect_err("R alone").to_string().contains("translation"));
        let skew = format!("{cam}{}{}", m("R", 3, 3, "2, 0, 0, 0, 1, 0, 0, 0, 1"), m("T", 3, 1, "0, 0, 1"));
        assert!(parse_calibration(&skew, p).expect_err("not a rotation").to_string().contains("not a rotation"));
        assert!(
            is_file_storage(&cam) && is_file_storage("<?xml version=\"1.0\"?>\n<opencv_storage>\n</opencv_storage>")
        );
        assert!(!is_file_storage("format_version = 1\n"));
    }

    #[test]
    fn string_lists_read_in_every_layout_opencv_writes() {
        let block = "%YAML:1.0\nimages:\n   - \"a 1.png\"\n   - b.png\nnext: 1\n";
        assert_eq!(read_string_list(block, "images"), Some((vec!["a 1.png".into(), "b.png".into()], 2)));
        let inline = "%YAML:1.0\nx: 2\nimages: [ \"a.png\", 'b.png' ]\n";
        assert_eq!(read_string_list(inline, "images"), Some((vec!["a.png".into(), "b.png".into()], 3)));
        let xml =
            "<?xml version=\"1.0\"?>\n<opencv_storage>\n<images>\n  \"a 1.png\" b.png</images>\n</opencv_storage>\n";
        assert_eq!(read_string_list(xml, "images"), Some((vec!["a 1.png".into(), "b.png".into()], 3)));
        assert_eq!(read_string_list(block, "names"), None);
        // Views: a row of six per view, as many names as rows; a bad rotation names the line.
        let cam = camera_yaml(&Intrinsics::new(800.0, 800.0, 320.5, 240.5), 640, 480, 0.1);
        let ex = |rows: usize, data: &str| {
            format!("{cam}extrinsic_parameters: !!opencv-matrix\n   rows: {rows}\n   cols: 6\n   dt: d\n   data: [ {data} ]\n")
        };
        let two = format!("{}images:\n   - a.png\n   - b.png\n", ex(2, "0, 0, 0, 0, 0, 1, 0, 0.5, 0, 0.1, 0, 1"));
        let v = parse_views(&two, Path::new("v.yml")).expect("two views");
        assert_eq!(v.views.len(), 2);
        assert_eq!((v.views[1].name.as_str(), v.views[1].pose.translation.x), ("b.png", 0.1));
        assert!((v.views[1].pose.rotation[(0, 2)] - 0.5f64.sin()).abs() < 1e-12);
        let e = parse_views(&format!("{}images: [ a.png ]\n", ex(1, "0, 0, 0, 0, 0, 1, 0, 0, 0")), Path::new("v.yml"))
            .expect_err("9 columns");
        assert!(e.to_string().contains("extrinsic_parameters"), "{e}");
    }

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
