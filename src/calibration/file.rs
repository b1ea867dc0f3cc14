//! The calibration file: versioned TOML written by `scanrig calibrate` and read through a rig
//! file's `[rig] calibration = "path"` (relative to the rig file). Units are in the key names.
//!
//! ```toml
//! format_version = 1
//!
//! [camera]            # intrinsics, pixels; k1 k2 p1 p2 k3 Brown-Conrady distortion (OpenCV's)
//! width_px = 640
//! height_px = 480
//! fx_px = 700.1
//! fy_px = 699.8
//! cx_px = 318.2
//! cy_px = 243.1
//! k1 = -0.08
//! k2 = 0.02
//! p1 = 0.0           # optional, 0 when absent (as p2, k3)
//! rms_px = 0.09        # re-projection RMS of the calibration
//! views = 12           # board views used
//!
//! [turntable]         # the rig frame seen from the camera (see calibration::turntable)
//! axis_camera = [0.0, -0.63, -0.77]
//! origin_camera_m = [0.0, 0.0, 0.52]
//! camera_rotation = [[1, 0, 0], [0, -0.77, 0.63], [0, -0.63, -0.77]]   # rig -> camera, rows
//! camera_translation_m = [0.0, 0.0, 0.52]
//! circle_rms_m = 5e-5
//! max_angle_error_deg = 0.01
//! views = 10
//!
//! [[lights]]          # rig frame
//! index = 0
//! position_m = [-0.15, -0.45, 0.2]
//! rms_levels = 1.2
//! pixels = 5000
//! ```

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::atomic::{write_atomic, AtomicWriteError};
use crate::geometry::{Intrinsics, Matrix3, Pose, Vector3};

/// The file format version this code reads and writes.
pub const FORMAT_VERSION: u32 = 1;

/// A whole calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// Format version; must be [`FORMAT_VERSION`].
    pub format_version: u32,
    /// `[camera]`: intrinsics.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraSection>,
    /// `[turntable]`: axis and the camera's pose in the rig frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub turntable: Option<TurntableSection>,
    /// `[[lights]]`: calibrated white-light positions.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lights: Vec<LightSection>,
    /// `[[lasers]]`: calibrated laser planes, camera frame.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub lasers: Vec<LaserSection>,
}

impl Default for CalibrationFile {
    fn default() -> Self {
        CalibrationFile {
            format_version: FORMAT_VERSION,
            camera: None,
            turntable: None,
            lights: Vec::new(),
            lasers: Vec::new(),
        }
    }
}

/// `[camera]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    /// Image width the intrinsics are for, pixels.
    pub width_px: u32,
    /// Image height, pixels.
    pub height_px: u32,
    /// Focal length along x, pixels.
    pub fx_px: f64,
    /// Focal length along y, pixels.
    pub fy_px: f64,
    /// Principal point x, pixels (top-left origin).
    pub cx_px: f64,
    /// Principal point y, pixels.
    pub cy_px: f64,
    /// First radial distortion coefficient (dimensionless).
    pub k1: f64,
    /// Second radial distortion coefficient (dimensionless).
    pub k2: f64,
    /// First tangential distortion coefficient (OpenCV's p1; 0 when absent).
    #[serde(default)]
    pub p1: f64,
    /// Second tangential distortion coefficient (OpenCV's p2; 0 when absent).
    #[serde(default)]
    pub p2: f64,
    /// Radial distortion coefficient of r⁶ (OpenCV's k3; 0 when absent).
    #[serde(default)]
    pub k3: f64,
    /// Re-projection RMS of the calibration, pixels.
    pub rms_px: f64,
    /// Board views used.
    pub views: usize,
}

impl CameraSection {
    /// The intrinsics (skew 0).
    pub fn intrinsics(&self) -> Intrinsics {
        Intrinsics {
            fx: self.fx_px,
            fy: self.fy_px,
            cx: self.cx_px,
            cy: self.cy_px,
            skew: 0.0,
            k1: self.k1,
            k2: self.k2,
            p1: self.p1,
            p2: self.p2,
            k3: self.k3,
        }
    }
}

/// `[turntable]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TurntableSection {
    /// Unit turntable axis (rig `+z`), camera frame.
    pub axis_camera: [f64; 3],
    /// Rig origin (axis at the table top), camera frame, metres.
    pub origin_camera_m: [f64; 3],
    /// Rotation rig -> camera, row-major.
    pub camera_rotation: [[f64; 3]; 3],
    /// Translation rig -> camera, metres (the rig origin in the camera frame).
    pub camera_translation_m: [f64; 3],
    /// RMS distance of the board origin from its circle about the axis, metres.
    pub circle_rms_m: f64,
    /// Largest difference between a measured and a commanded turn, degrees.
    pub max_angle_error_deg: f64,
    /// Views used.
    pub views: usize,
}

impl TurntableSection {
    /// The camera's pose, rig -> camera.
    pub fn camera_pose(&self) -> Pose {
        Pose {
            rotation: Matrix3::from_fn(|r, c| self.camera_rotation[r][c]),
            translation: Vector3::from(self.camera_translation_m),
        }
    }
}

/// `[[lights]]`: one calibrated white light.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightSection {
    /// Index of the light in the rig file's `[[lights.light]]`.
    pub index: usize,
    /// Position, rig frame, metres.
    pub position_m: [f64; 3],
    /// RMS shading residual of the fit, 8-bit levels (R + G + B).
    pub rms_levels: f64,
    /// Sphere pixels used.
    pub pixels: usize,
}

/// `[[lasers]]`: one calibrated laser plane `normal_camera · X = offset_camera_m` in the camera frame
/// (OpenCV axes, metres), from `scanrig calibrate laser`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaserSection {
    /// Index of the laser (the rig file's order).
    pub index: usize,
    /// Unit normal of the plane, camera frame.
    pub normal_camera: [f64; 3],
    /// Signed distance of the plane from the camera centre along the normal, metres.
    pub offset_camera_m: f64,
    /// RMS distance of the stripe points from the plane, metres.
    pub rms_m: f64,
    /// Stripe points fitted (inliers).
    pub points: usize,
}

/// Why a calibration file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationFileError {
    /// The file could not be read.
    #[error("{path}: cannot read calibration file")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// Not TOML, or not this schema.
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// The parser's message.
        message: String,
    },
    /// A value that parses but cannot be used.
    #[error("{path}:{line}: `{key}`: {message}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// 1-based line of the key (1 when it is not in the file).
        line: usize,
        /// Dotted key.
        key: String,
        /// What is wrong.
        message: String,
    },
    /// An OpenCV FileStorage file that is not a usable camera calibration.
    #[error("{}: not a usable OpenCV camera calibration", path.display())]
    FileStorage {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: Box<super::opencv_xml::OpenCvXmlError>,
    },
    /// Serialising failed (a value TOML cannot hold).
    #[error("{path}: cannot encode calibration: {message}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's message.
        message: String,
    },
    /// Writing failed.
    #[error(transparent)]
    Write(#[from] AtomicWriteError),
}

fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.bytes().filter(|&b| b == b'\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

/// 1-based line of the dotted `key` (tables, array-of-tables by index), or 1.
fn key_line(text: &str, key: &str) -> usize {
    let Ok(doc) = toml_edit::Document::parse(text) else { return 1 };
    let mut table: &dyn toml_edit::TableLike = doc.as_table();
    let mut line = 1;
    let parts: Vec<&str> = key.split('.').collect();
    let mut k = 0;
    while k < parts.len() {
        let Some((kk, item)) = table.get_key_value(parts[k]) else { break };
        if let Some(s) = kk.span() {
            line = line_col(text, s.start).0;
        }
        match item {
            toml_edit::Item::ArrayOfTables(a) => {
                let Some(t) = parts.get(k + 1).and_then(|i| i.parse::<usize>().ok()).and_then(|i| a.get(i)) else {
                    break;
                };
                if let Some(s) = t.span() {
                    line = line_col(text, s.start).0;
                }
                table = t;
                k += 2;
            }
            other => match other.as_table_like() {
                Some(t) => {
                    table = t;
                    k += 1;
                }
                None => break,
            },
        }
    }
    line
}

impl CalibrationFile {
    /// Every problem with the values (version, finiteness, ranges) as `(key, message)`.
    fn problems(&self) -> Vec<(String, String)> {
        let mut out = Vec::new();
        let mut bad = |k: &str, m: String| out.push((k.to_owned(), m));
        if self.format_version != FORMAT_VERSION {
            bad(
                "format_version",
                format!("version {} is not supported (this build reads {FORMAT_VERSION})", self.format_version),
            );
        }
        if let Some(c) = &self.camera {
            for (k, v) in [("fx_px", c.fx_px), ("fy_px", c.fy_px)] {
                if !(v.is_finite() && v > 0.0) {
                    bad(&format!("camera.{k}"), format!("must be a positive number of pixels, got {v}"));
                }
            }
            for (k, v) in [("cx_px", c.cx_px), ("cy_px", c.cy_px), ("k1", c.k1), ("k2", c.k2), ("rms_px", c.rms_px)] {
                if !v.is_finite() {
                    bad(&format!("camera.{k}"), format!("must be finite, got {v}"));
                }
            }
            if c.width_px == 0 || c.height_px == 0 {
                bad("camera.width_px", "image size must be at least 1x1 pixels".into());
            }
        }
        if let Some(t) = &self.turntable {
            let r = t.camera_pose().rotation;
            let finite = r.iter().chain(t.camera_translation_m.iter()).all(|v| v.is_finite());
            if !finite || (r * r.transpose() - Matrix3::identity()).norm() > 1e-6 || r.determinant() < 0.0 {
                bad("turntable.camera_rotation", "must be a rotation matrix (orthonormal rows, determinant 1)".into());
            }
            if !t.camera_translation_m.iter().all(|v| v.is_finite()) {
                bad("turntable.camera_translation_m", "must be finite".into());
            }
        }
        for (i, l) in self.lights.iter().enumerate() {
            if !l.position_m.iter().all(|v| v.is_finite()) {
                bad(&format!("lights.{i}.position_m"), "must be finite".into());
            }
        }
        out
    }

    /// Parse calibration-file text; `path` is only used in messages.
    pub fn parse(text: &str, path: &Path) -> Result<CalibrationFile, CalibrationFileError> {
        let file: CalibrationFile = toml::from_str(text).map_err(|e| {
            let (line, column) = e.span().map(|s| line_col(text, s.start)).unwrap_or((1, 1));
            CalibrationFileError::Parse { path: path.to_owned(), line, column, message: e.message().trim().to_owned() }
        })?;
        if let Some((key, message)) = file.problems().into_iter().next() {
            return Err(CalibrationFileError::Invalid {
                path: path.to_owned(),
                line: key_line(text, &key),
                key,
                message,
            });
        }
        Ok(file)
    }

    /// Read and check a calibration file.
    pub fn load(path: &Path) -> Result<CalibrationFile, CalibrationFileError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| CalibrationFileError::Read { path: path.to_owned(), source })?;
        CalibrationFile::parse(&text, path)
    }

    /// Read `path` if it exists (to update it), else an empty file.
    pub fn load_or_default(path: &Path) -> Result<CalibrationFile, CalibrationFileError> {
        if path.exists() {
            CalibrationFile::load(path)
        } else {
            Ok(CalibrationFile::default())
        }
    }

    /// Write the file atomically (temporary file, fsync, rename).
    pub fn save(&self, path: &Path) -> Result<(), CalibrationFileError> {
        let body = toml::to_string(self)
            .map_err(|e| CalibrationFileError::Encode { path: path.to_owned(), message: e.to_string() })?;
        let text = format!(
            "# scanrig calibration file. Units: pixels (_px), metres (_m), degrees (_deg).\n\
             # Frames: camera = OpenCV (x right, y down, z forward); rig = origin on the turntable axis at the\n\
             # table top, +z up the axis.\n{body}"
        );
        write_atomic(path, text.as_bytes())?;
        Ok(())
    }
}

/// Load the calibration file at `path` and apply it to `rig`: the camera's intrinsics from
/// `[camera]` (the image size must match), its rig-frame pose from `[turntable]`, light positions
/// from `[[lights]]` (by index). Sections that are absent leave the rig's values alone.
///
/// An OpenCV FileStorage file (YAML or XML, see [`super::opencv_yaml::parse_calibration`]) is
/// taken as well: its camera matrix and distortion set the intrinsics (its `image_width`,
/// `image_height`, when present, must match the camera), its pose (`R`, `T`), when present, the
/// camera's rig-frame pose.
pub fn apply_to_rig(path: &Path, rig: &mut crate::config::RigConfig) -> Result<(), CalibrationFileError> {
    let text =
        std::fs::read_to_string(path).map_err(|source| CalibrationFileError::Read { path: path.to_owned(), source })?;
    if super::opencv_yaml::is_file_storage(&text) {
        return apply_file_storage(&text, path, rig);
    }
    let file = CalibrationFile::parse(&text, path)?;
    let invalid = |key: &str, message: String| CalibrationFileError::Invalid {
        path: path.to_owned(),
        line: key_line(&text, key),
        key: key.to_owned(),
        message,
    };
    let (width, height) = rig.camera.size();
    let cam = rig.camera.calibration_mut();
    if let Some(c) = &file.camera {
        if (c.width_px, c.height_px) != (width, height) {
            return Err(invalid(
                "camera.width_px",
                format!(
                    "calibrated for {}x{} pixels but the rig's camera is {}x{}",
                    c.width_px, c.height_px, width, height
                ),
            ));
        }
        cam.intrinsics = c.intrinsics();
    }
    if let Some(t) = &file.turntable {
        cam.pose =
            crate::config::PoseConfig::Matrix { rotation: t.camera_rotation, translation_m: t.camera_translation_m };
    }
    for (i, l) in file.lights.iter().enumerate() {
        let count = rig.lights.as_ref().map_or(0, |x| x.lights.len());
        match rig.lights.as_mut().and_then(|x| x.lights.get_mut(l.index)) {
            Some(light) => light.position_m = l.position_m,
            None => {
                return Err(invalid(
                    &format!("lights.{i}.index"),
                    format!("light {} does not exist: the rig has {count} light(s)", l.index),
                ))
            }
        }
    }
    Ok(())
}

/// [`apply_to_rig`] for an OpenCV FileStorage file.
fn apply_file_storage(text: &str, path: &Path, rig: &mut crate::config::RigConfig) -> Result<(), CalibrationFileError> {
    let c = super::opencv_yaml::parse_calibration(text, path)
        .map_err(|e| CalibrationFileError::FileStorage { path: path.to_owned(), source: Box::new(e) })?;
    let size = rig.camera.size();
    if let Some((w, h)) = c.camera.size.filter(|s| *s != size) {
        return Err(CalibrationFileError::Invalid {
            path: path.to_owned(),
            line: text.lines().position(|l| l.contains("image_width")).map_or(1, |i| i + 1),
            key: "image_width".into(),
            message: format!("calibrated for {w}x{h} pixels but the rig's camera is {}x{}", size.0, size.1),
        });
    }
    let cam = rig.camera.calibration_mut();
    cam.intrinsics = c.camera.intrinsics;
    if let Some(p) = c.pose {
        let r = p.rotation;
        cam.pose = crate::config::PoseConfig::Matrix {
            rotation: [0, 1, 2].map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]),
            translation_m: p.translation.into(),
        };
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> CalibrationFile {
        CalibrationFile {
            format_version: FORMAT_VERSION,
            camera: Some(CameraSection {
                width_px: 640,
                height_px: 480,
                fx_px: 700.5,
                fy_px: 699.0,
                cx_px: 320.25,
                cy_px: 240.5,
                k1: -0.08,
                k2: 0.02,
                p1: 1e-4,
                p2: -2e-4,
                k3: 0.01,
                rms_px: 0.09,
                views: 12,
            }),
            turntable: Some(TurntableSection {
                axis_camera: [0.0, -0.6, -0.8],
                origin_camera_m: [0.0, 0.0, 0.5],
                camera_rotation: [[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]],
                camera_translation_m: [0.0, 0.0, 0.5],
                circle_rms_m: 1e-4,
                max_angle_error_deg: 0.01,
                views: 10,
            }),
            lights: vec![LightSection { index: 1, position_m: [0.1, -0.4, 0.2], rms_levels: 1.0, pixels: 400 }],
            lasers: vec![LaserSection {
                index: 0,
                normal_camera: [0.8, 0.0, 0.6],
                offset_camera_m: 0.16,
                rms_m: 2e-4,
                points: 900,
            }],
        }
    }

    #[test]
    fn round_trips_through_an_atomic_write() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("calib.toml");
        sample().save(&path).expect("save");
        assert_eq!(CalibrationFile::load(&path).expect("load"), sample());
    }

    #[test]
    fn errors_name_file_and_line() {
        let text = toml::to_string(&sample()).expect("encode").replace("fx_px = 700.5", "fx_px = -3.0");
        let err = CalibrationFile::parse(&text, Path::new("c.toml")).expect_err("negative focal length");
        let line = text.lines().position(|l| l.starts_with("fx_px")).expect("line") + 1;
        assert_eq!(
            err.to_string(),
            format!("c.toml:{line}: `camera.fx_px`: must be a positive number of pixels, got -3")
        );
        let text = toml::to_string(&sample()).expect("encode").replace("format_version = 1", "format_version = 2");
        let err = CalibrationFile::parse(&text, Path::new("c.toml")).expect_err("future version");
        assert!(err.to_string().starts_with("c.toml:1: `format_version`"), "{err}");
        let err =
            CalibrationFile::parse("format_version = 1\nfocal = 3\n", Path::new("c.toml")).expect_err("unknown key");
        assert!(err.to_string().starts_with("c.toml:2:"), "{err}");
    }
}
