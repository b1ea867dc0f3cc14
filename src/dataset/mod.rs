//! Calibrated image sets on disk: cameras, view selections, images and silhouette masks.
//!
//! # Calibration files
//! - **Middlebury `*_par.txt`**: the first line is the view count `n`; then one line per view,
//!   `name k11 k12 k13 k21 k22 k23 k31 k32 k33 r11 r12 r13 r21 r22 r23 r31 r32 r33 t1 t2 t3`,
//!   with `P = K [R | t]` mapping the data set's world frame (metres) to pixels, origin top-left.
//! - **Projection matrices** (any other file): one line per image, `name p11 p12 p13 p14 p21 .. p34`
//!   (the 3x4 matrix row by row, 12 numbers). `P` is decomposed into `K`, `R`, `t` with an RQ
//!   decomposition (`K` upper triangular with a positive diagonal, `R` a rotation). Blank lines and
//!   lines starting with `#` are ignored.
//!
//! - **COLMAP text model**: a directory with `cameras.txt` and `images.txt` (see [`parse_colmap`]),
//!   with the models' lens distortion.
//! - **OpenCV FileStorage** (YAML `%YAML:1.0` or XML `<opencv_storage>`): one camera with its lens
//!   distortion (`camera_matrix`, `distortion_coefficients`), one view per row of
//!   `extrinsic_parameters` (Rodrigues vector, translation; as OpenCV's calibration sample writes
//!   them) and the views' image names in the string sequence `images` (see
//!   [`crate::calibration::opencv_yaml::parse_views`]).
//!
//! Cameras have no lens distortion in the first two formats. Image names are relative to the data set
//! directory.
//!
//! # View selections
//! Either a file with one image name per line (blank lines and `#` comments ignored), or a
//! comma-separated list of names.
//!
//! # Masks
//! Either read from a directory (a PNG with the image's stem, `stem.png`; any non-zero pixel is
//! object), or extracted from the images with [`SilhouetteParams`].

use std::path::{Path, PathBuf};

use image::RgbImage;
use nalgebra::{Matrix3, Vector3};

use crate::geometry::{Aabb, CameraModel, Intrinsics, Pose};
use crate::pipeline::{extract_silhouette, Mask, SilhouetteParams, View};

/// Errors of data set loading; each names the file and, for text files, the 1-based line.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A file could not be read.
    #[error("cannot read {path}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// An image could not be decoded (or is missing).
    #[error("cannot load image {path}")]
    Image {
        /// The image file.
        path: PathBuf,
        /// The decoder's error.
        #[source]
        source: image::ImageError,
    },
    /// An image listed in the calibration file does not exist.
    #[error("{calibration}:{line}: image {path} does not exist")]
    MissingImage {
        /// The calibration file.
        calibration: PathBuf,
        /// Line of the entry.
        line: usize,
        /// The missing image.
        path: PathBuf,
    },
    /// An image listed in the calibration file exists but is not a regular file (a device such as
    /// `/dev/zero`, a directory or a pipe), which would never decode or never end.
    #[error("{calibration}:{line}: image {path} is not a regular file ({kind})")]
    NotAFile {
        /// The calibration file.
        calibration: PathBuf,
        /// Line of the entry.
        line: usize,
        /// The image path.
        path: PathBuf,
        /// What it is instead.
        kind: &'static str,
    },
    /// A line has the wrong number of values.
    #[error("{path}:{line}: expected {expected} values, found {found}")]
    ValueCount {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// Values expected (including the name).
        expected: usize,
        /// Values found.
        found: usize,
    },
    /// A value is not a number.
    #[error("{path}:{line}: {token:?} is not a number")]
    BadNumber {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The offending token.
        token: String,
        /// The parse error.
        #[source]
        source: std::num::ParseFloatError,
    },
    /// The view count line is not a non-negative integer.
    #[error("{path}:{line}: {token:?} is not a view count")]
    BadCount {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The offending token.
        token: String,
        /// The parse error.
        #[source]
        source: std::num::ParseIntError,
    },
    /// An image size is not two positive whole numbers of pixels.
    #[error("{path}:{line}: image size {token:?} is not WIDTH HEIGHT in pixels")]
    BadSize {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The offending tokens.
        token: String,
    },
    /// A value is infinite or NaN.
    #[error("{path}:{line}: non-finite value {token:?}")]
    NonFinite {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The offending token.
        token: String,
    },
    /// The declared view count does not match the number of view lines.
    #[error("{path}: declares {declared} views but lists {found}")]
    ViewCount {
        /// The file.
        path: PathBuf,
        /// Count on the first line.
        declared: usize,
        /// View lines found.
        found: usize,
    },
    /// The projection matrix cannot be decomposed (rank-deficient left 3x3 block).
    #[error("{path}:{line}: degenerate projection matrix")]
    DegenerateProjection {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
    },
    /// An OpenCV FileStorage calibration is missing an entry or has a malformed one.
    #[error(transparent)]
    OpenCv(#[from] crate::calibration::opencv_xml::OpenCvXmlError),
    /// The calibration file lists no view.
    #[error("{path}: no views")]
    NoViews {
        /// The file.
        path: PathBuf,
    },
    /// A selected view is not in the calibration.
    #[error("{source_name}: view {name:?} is not in the calibration")]
    UnknownView {
        /// Where the selection came from (a file, or the list itself).
        source_name: String,
        /// The unknown name.
        name: String,
    },
    /// A mask's size differs from its image's.
    #[error("{path}: mask is {width}x{height} px but the image is {expected_width}x{expected_height} px")]
    ImageSize {
        /// The mask file.
        path: PathBuf,
        /// Mask width, px.
        width: u32,
        /// Mask height, px.
        height: u32,
        /// Image width, px.
        expected_width: u32,
        /// Image height, px.
        expected_height: u32,
    },
    /// An image (or its mask) is not the size its calibration is for.
    #[error("{calibration}:{line}: {path} is {width}x{height} px but the calibration is for {calibrated_width}x{calibrated_height} px")]
    CalibratedSize {
        /// The calibration file.
        calibration: PathBuf,
        /// Line of the view's entry.
        line: usize,
        /// The image file.
        path: PathBuf,
        /// Image width, px.
        width: u32,
        /// Image height, px.
        height: u32,
        /// Width in the calibration, px.
        calibrated_width: u32,
        /// Height in the calibration, px.
        calibrated_height: u32,
    },
    /// A COLMAP camera model this project's lens model cannot represent.
    #[error("{path}:{line}: camera model {model} is not supported (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV with k4..k6 = 0)")]
    UnsupportedCameraModel {
        /// The cameras.txt file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// The model name.
        model: String,
    },
    /// A depth map is not a single-channel 16-bit PNG.
    #[error("{path}: a depth map must be a single-channel 16-bit PNG in millimetres, found {found}")]
    DepthFormat {
        /// The file.
        path: PathBuf,
        /// What the file is.
        found: String,
    },
    /// No calibration file was given and none was found.
    #[error("{dir}: no calibration file (*_par.txt) found")]
    NoCalibration {
        /// The data set directory.
        dir: PathBuf,
    },
    /// No camera sees any part of the bounding box.
    #[error("no camera sees the bounding box {min:?} .. {max:?}")]
    BoxUnseen {
        /// Minimum corner, metres.
        min: [f64; 3],
        /// Maximum corner, metres.
        max: [f64; 3],
    },
}

/// One calibrated image, before its size is known.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// Image file name, relative to the data set directory.
    pub name: String,
    /// Intrinsics, pixels, with the file's lens distortion (none in the Middlebury and
    /// projection-matrix formats).
    pub intrinsics: Intrinsics,
    /// World -> camera, metres.
    pub pose: Pose,
    /// Line of the calibration file this came from (1-based).
    pub line: usize,
    /// The image size the calibration is for, pixels, when the file states it (COLMAP, OpenCV
    /// FileStorage with `image_width` / `image_height`); an image of another size is an error.
    pub size: Option<(u32, u32)>,
}

impl Calibration {
    /// The camera for an image of `width x height` pixels.
    pub fn camera(&self, width: u32, height: u32) -> CameraModel {
        CameraModel { width, height, intrinsics: self.intrinsics, pose: self.pose }
    }
}

fn read_text(path: &Path) -> Result<String, DatasetError> {
    std::fs::read_to_string(path).map_err(|source| DatasetError::Read { path: path.to_path_buf(), source })
}

fn parse_numbers(path: &Path, line: usize, tokens: &[&str]) -> Result<Vec<f64>, DatasetError> {
    tokens
        .iter()
        .map(|t| {
            let v: f64 = t.parse().map_err(|source| DatasetError::BadNumber {
                path: path.to_path_buf(),
                line,
                token: t.to_string(),
                source,
            })?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(DatasetError::NonFinite { path: path.to_path_buf(), line, token: t.to_string() })
            }
        })
        .collect()
}

/// Non-blank, non-comment lines with their 1-based numbers.
fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(n, l)| (n + 1, l.trim())).filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

/// Parse a Middlebury `*_par.txt` file's text; `path` is used in errors.
pub fn parse_par(text: &str, path: &Path) -> Result<Vec<Calibration>, DatasetError> {
    let mut lines = content_lines(text);
    let (count_line, count_text) = lines.next().ok_or_else(|| DatasetError::NoViews { path: path.to_path_buf() })?;
    let declared: usize = count_text.parse().map_err(|source| DatasetError::BadCount {
        path: path.to_path_buf(),
        line: count_line,
        token: count_text.to_string(),
        source,
    })?;
    let mut out = Vec::with_capacity(declared);
    for (line, l) in lines {
        let tokens: Vec<&str> = l.split_whitespace().collect();
        if tokens.len() != 22 {
            return Err(DatasetError::ValueCount { path: path.to_path_buf(), line, expected: 22, found: tokens.len() });
        }
        let v = parse_numbers(path, line, &tokens[1..])?;
        let k = Matrix3::from_row_slice(&v[0..9]);
        let r = Matrix3::from_row_slice(&v[9..18]);
        let t = Vector3::new(v[18], v[19], v[20]);
        if k[(2, 2)] == 0.0 {
            return Err(DatasetError::DegenerateProjection { path: path.to_path_buf(), line });
        }
        out.push(Calibration {
            name: tokens[0].to_string(),
            intrinsics: Intrinsics::from_matrix(&k),
            pose: Pose { rotation: r, translation: t },
            line,
            size: None,
        });
    }
    if out.len() != declared {
        return Err(DatasetError::ViewCount { path: path.to_path_buf(), declared, found: out.len() });
    }
    if out.is_empty() {
        return Err(DatasetError::NoViews { path: path.to_path_buf() });
    }
    Ok(out)
}

/// Decompose `P = K [R | t]` with the overall sign of `P` taken from the determinant of its left 3x3
/// block (right for a right-handed world frame; see [`decompose_projection_facing`] for the general
/// case). `None` when the block is singular.
pub fn decompose_projection(p: &nalgebra::Matrix3x4<f64>) -> Option<(Intrinsics, Pose)> {
    let det = p.fixed_view::<3, 3>(0, 0).determinant();
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    decompose_signed(&(p * det.signum()))
}

/// Decompose `P = K [R | t]` so that `scene` (a point of the scene, world frame) lies in front of the
/// camera: `P` is defined up to scale, and the sign of that scale is what says which way the camera
/// looks. `K` is upper triangular with a positive diagonal (normalised so `K33 = 1`); `R` is
/// orthogonal, a proper rotation for a right-handed world frame and a rotation times a mirror
/// (determinant -1) when the world frame is left-handed (published calibrations exist in mirrored
/// frames): projection, rays and carving work the same, the reconstruction comes out in that frame.
/// `None` when the block is singular or `scene` lies on the camera's focal plane.
pub fn decompose_projection_facing(p: &nalgebra::Matrix3x4<f64>, scene: &Vector3<f64>) -> Option<(Intrinsics, Pose)> {
    let w = (p * scene.push(1.0)).z;
    if !w.is_finite() || w == 0.0 {
        return None;
    }
    decompose_signed(&(p * w.signum()))
}

/// RQ decomposition of `P` as given (no sign change): `K` with positive diagonal, `R` orthogonal.
fn decompose_signed(p: &nalgebra::Matrix3x4<f64>) -> Option<(Intrinsics, Pose)> {
    let m: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
    let p4: Vector3<f64> = p.column(3).into_owned();
    let det = m.determinant();
    if !det.is_finite() || det.abs() < 1e-300 {
        return None;
    }
    let rows = [m.row(0).transpose(), m.row(1).transpose(), m.row(2).transpose()];
    let k33 = rows[2].norm();
    let r3 = rows[2] / k33;
    let k23 = rows[1].dot(&r3);
    let v2 = rows[1] - r3 * k23;
    let k22 = v2.norm();
    let r2 = v2 / k22;
    let k13 = rows[0].dot(&r3);
    let k12 = rows[0].dot(&r2);
    let v1 = rows[0] - r3 * k13 - r2 * k12;
    let k11 = v1.norm();
    let r1 = v1 / k11;
    if !(k11 > 0.0 && k22 > 0.0 && k33 > 0.0) {
        return None;
    }
    let k = Matrix3::new(k11, k12, k13, 0.0, k22, k23, 0.0, 0.0, k33);
    let t = k.try_inverse()? * p4;
    let rotation = Matrix3::from_rows(&[r1.transpose(), r2.transpose(), r3.transpose()]);
    Some((Intrinsics::from_matrix(&k), Pose { rotation, translation: t }))
}

/// The point nearest (least squares) to every camera's optical axis, world frame: where a set of
/// cameras looking at one object converge. Needs two or more cameras whose axes are not all
/// parallel; independent of the sign of each `P` (the axis is the line through the centre along the
/// third row of the left block). `None` otherwise.
pub fn axes_convergence_point(projections: &[nalgebra::Matrix3x4<f64>]) -> Option<Vector3<f64>> {
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for p in projections {
        let m: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
        let centre = -(m.try_inverse()? * p.column(3));
        let d = m.row(2).transpose().normalize();
        let proj = Matrix3::identity() - d * d.transpose();
        a += proj;
        b += proj * centre;
    }
    let eig = a.symmetric_eigen();
    let smallest = eig.eigenvalues.iter().copied().fold(f64::INFINITY, f64::min);
    let well_conditioned = smallest > 1e-6 * projections.len() as f64;
    if projections.len() < 2 || !well_conditioned {
        return None;
    }
    a.try_inverse().map(|inv| inv * b).filter(|x| x.iter().all(|v| v.is_finite()))
}

/// Parse a projection-matrix file's text (`name p11 .. p34` per line); `path` is used in errors.
///
/// Each `P` may carry either overall sign and the world frame may be left-handed: which way a camera
/// looks follows from the scene lying in front of it, the scene being where the cameras' optical
/// axes converge ([`axes_convergence_point`]). A file of one camera (or of parallel axes) falls back
/// to the determinant's sign, i.e. assumes a right-handed world frame.
pub fn parse_projections(text: &str, path: &Path) -> Result<Vec<Calibration>, DatasetError> {
    let mut raw = Vec::new();
    for (line, l) in content_lines(text) {
        let tokens: Vec<&str> = l.split_whitespace().collect();
        if tokens.len() != 13 {
            return Err(DatasetError::ValueCount { path: path.to_path_buf(), line, expected: 13, found: tokens.len() });
        }
        let v = parse_numbers(path, line, &tokens[1..])?;
        let p = nalgebra::Matrix3x4::from_row_slice(&v);
        if decompose_projection(&p).is_none() {
            return Err(DatasetError::DegenerateProjection { path: path.to_path_buf(), line });
        }
        raw.push((tokens[0].to_string(), p, line));
    }
    if raw.is_empty() {
        return Err(DatasetError::NoViews { path: path.to_path_buf() });
    }
    let ps: Vec<_> = raw.iter().map(|r| r.1).collect();
    let scene = axes_convergence_point(&ps);
    raw.into_iter()
        .map(|(name, p, line)| {
            let d = match &scene {
                Some(x) => decompose_projection_facing(&p, x),
                None => decompose_projection(&p),
            };
            let (intrinsics, pose) = d.ok_or(DatasetError::DegenerateProjection { path: path.to_path_buf(), line })?;
            Ok(Calibration { name, intrinsics, pose, line, size: None })
        })
        .collect()
}

/// Parse COLMAP's text model: `cameras.txt` (`CAMERA_ID MODEL WIDTH HEIGHT PARAMS..`; models
/// SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV with k4..k6 = 0) and
/// `images.txt` (pairs of lines, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` then the 2-D points,
/// ignored). The quaternion and translation are world -> camera (`x_cam = R x + t`), COLMAP's
/// convention; its pixel convention (the top-left pixel's centre at (0.5, 0.5)) is this project's.
/// Lines are named in errors by file and number.
pub fn parse_colmap(
    cameras: &str,
    cameras_path: &Path,
    images: &str,
    images_path: &Path,
) -> Result<Vec<Calibration>, DatasetError> {
    let mut cams = std::collections::HashMap::new();
    for (line, l) in content_lines(cameras) {
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 5 {
            return Err(DatasetError::ValueCount {
                path: cameras_path.to_path_buf(),
                line,
                expected: 5,
                found: t.len(),
            });
        }
        let v = parse_numbers(cameras_path, line, &t[4..])?;
        let need = |n: usize| {
            if v.len() == n {
                Ok(())
            } else {
                Err(DatasetError::ValueCount {
                    path: cameras_path.to_path_buf(),
                    line,
                    expected: 4 + n,
                    found: t.len(),
                })
            }
        };
        let intr =
            match t[1] {
                "SIMPLE_PINHOLE" => need(3).map(|_| Intrinsics::new(v[0], v[0], v[1], v[2]))?,
                "PINHOLE" => need(4).map(|_| Intrinsics::new(v[0], v[1], v[2], v[3]))?,
                "SIMPLE_RADIAL" => need(4)
                    .map(|_| Intrinsics::new(v[0], v[0], v[1], v[2]).with_distortion([v[3], 0.0, 0.0, 0.0, 0.0]))?,
                "RADIAL" => need(5)
                    .map(|_| Intrinsics::new(v[0], v[0], v[1], v[2]).with_distortion([v[3], v[4], 0.0, 0.0, 0.0]))?,
                "OPENCV" => need(8)
                    .map(|_| Intrinsics::new(v[0], v[1], v[2], v[3]).with_distortion([v[4], v[5], v[6], v[7], 0.0]))?,
                "FULL_OPENCV" if v.len() == 12 && v[9..12].iter().all(|x| *x == 0.0) => {
                    Intrinsics::new(v[0], v[1], v[2], v[3]).with_distortion([v[4], v[5], v[6], v[7], v[8]])
                }
                other => {
                    return Err(DatasetError::UnsupportedCameraModel {
                        path: cameras_path.to_path_buf(),
                        line,
                        model: other.to_string(),
                    })
                }
            };
        let size = (t[2].parse::<u32>().ok(), t[3].parse::<u32>().ok());
        let size = match size {
            (Some(w), Some(h)) if w > 0 && h > 0 => (w, h),
            _ => {
                return Err(DatasetError::BadSize {
                    path: cameras_path.to_path_buf(),
                    line,
                    token: format!("{} {}", t[2], t[3]),
                })
            }
        };
        cams.insert(t[0].to_string(), (intr, size));
    }
    let mut out = Vec::new();
    let mut expect_header = true;
    for (line, l) in images.lines().enumerate().map(|(n, l)| (n + 1, l.trim())) {
        if l.starts_with('#') {
            continue;
        }
        if !expect_header {
            expect_header = true; // the 2-D points line (possibly empty)
            continue;
        }
        if l.is_empty() {
            continue;
        }
        expect_header = false;
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 10 {
            return Err(DatasetError::ValueCount {
                path: images_path.to_path_buf(),
                line,
                expected: 10,
                found: t.len(),
            });
        }
        let v = parse_numbers(images_path, line, &t[1..8])?;
        let q = nalgebra::Quaternion::new(v[0], v[1], v[2], v[3]);
        let usable = q.norm() > 1e-12;
        if !usable {
            return Err(DatasetError::DegenerateProjection { path: images_path.to_path_buf(), line });
        }
        let rotation = nalgebra::UnitQuaternion::from_quaternion(q).to_rotation_matrix().into_inner();
        let (intrinsics, size) = *cams.get(t[8]).ok_or_else(|| DatasetError::UnknownView {
            source_name: format!(
                "{}:{line}: camera id {} is not in {}",
                images_path.display(),
                t[8],
                cameras_path.display()
            ),
            name: t[9..].join(" "),
        })?;
        out.push(Calibration {
            name: t[9..].join(" "),
            intrinsics,
            pose: Pose { rotation, translation: Vector3::new(v[4], v[5], v[6]) },
            line,
            size: Some(size),
        });
    }
    if out.is_empty() {
        return Err(DatasetError::NoViews { path: images_path.to_path_buf() });
    }
    Ok(out)
}

/// Read a calibration: a COLMAP text model when `path` is a directory holding `cameras.txt` and
/// `images.txt` (or one of those two files); otherwise a file: an OpenCV FileStorage file (YAML or
/// XML, see the module docs), in the Middlebury format when the first content line is a single
/// integer, projection matrices otherwise.
pub fn read_calibration(path: &Path) -> Result<Vec<Calibration>, DatasetError> {
    let colmap_dir = if path.is_dir() {
        Some(path.to_path_buf())
    } else {
        match path.file_name().and_then(|n| n.to_str()) {
            Some("cameras.txt" | "images.txt") => path.parent().map(Path::to_path_buf),
            _ => None,
        }
    };
    if let Some(dir) = colmap_dir {
        let (c, i) = (dir.join("cameras.txt"), dir.join("images.txt"));
        return parse_colmap(&read_text(&c)?, &c, &read_text(&i)?, &i);
    }
    let text = read_text(path)?;
    if crate::calibration::opencv_yaml::is_file_storage(&text) {
        let file = crate::calibration::opencv_yaml::parse_views(&text, path)?;
        let intrinsics = file.camera.intrinsics;
        return Ok(file
            .views
            .into_iter()
            .map(|v| Calibration { name: v.name, intrinsics, pose: v.pose, line: file.line, size: file.camera.size })
            .collect());
    }
    let first = content_lines(&text).next().map(|(_, l)| l.split_whitespace().count() == 1).unwrap_or(false);
    if first {
        parse_par(&text, path)
    } else {
        parse_projections(&text, path)
    }
}

/// Which views to use.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ViewSelection {
    /// Every calibrated view.
    All,
    /// A file with one image name per line.
    File(PathBuf),
    /// Image names.
    Names(Vec<String>),
}

impl ViewSelection {
    /// A path to an existing file (or any name ending in `.txt`, so that a missing list file is reported
    /// as such) selects from that file; anything else is a comma-separated list.
    pub fn parse(spec: &str) -> ViewSelection {
        let p = Path::new(spec);
        if p.is_file() || spec.ends_with(".txt") {
            ViewSelection::File(p.to_path_buf())
        } else {
            ViewSelection::Names(spec.split(',').map(|s| s.trim().to_string()).filter(|s| !s.is_empty()).collect())
        }
    }

    /// Keep the selected calibrations, in the selection's order.
    pub fn apply(&self, all: Vec<Calibration>) -> Result<Vec<Calibration>, DatasetError> {
        let (names, source_name): (Vec<String>, String) = match self {
            ViewSelection::All => return Ok(all),
            ViewSelection::File(p) => {
                let text = read_text(p)?;
                (content_lines(&text).map(|(_, l)| l.to_string()).collect(), p.display().to_string())
            }
            ViewSelection::Names(n) => (n.clone(), "view list".to_string()),
        };
        names
            .into_iter()
            .map(|name| {
                let stem = |s: &str| Path::new(s).file_stem().map(|x| x.to_os_string());
                all.iter()
                    .find(|c| c.name == name || stem(&c.name) == stem(&name))
                    .cloned()
                    .ok_or(DatasetError::UnknownView { source_name: source_name.clone(), name })
            })
            .collect()
    }
}

/// Where masks come from.
#[derive(Debug, Clone, PartialEq)]
pub enum MaskSource {
    /// Extract from the images with these parameters.
    Extract(SilhouetteParams),
    /// PNGs in this directory, `stem.png`, non-zero = object.
    Directory(PathBuf),
}

/// What to load.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetOptions {
    /// The data set directory (image names are relative to it).
    pub dir: PathBuf,
    /// The calibration file; `None` looks for the one `*_par.txt` in `dir`.
    pub calibration: Option<PathBuf>,
    /// Which views.
    pub views: ViewSelection,
    /// Where the masks come from.
    pub masks: MaskSource,
    /// Load the RGB images even when the masks come from a directory (for colour).
    pub load_images: bool,
}

/// One loaded view.
#[derive(Debug, Clone)]
pub struct DatasetView {
    /// Image name from the calibration.
    pub name: String,
    /// The camera, with the image size filled in.
    pub camera: CameraModel,
    /// The silhouette.
    pub mask: Mask,
    /// The image, when it was loaded.
    pub image: Option<RgbImage>,
}

/// A loaded calibrated image set.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// The views, in selection order.
    pub views: Vec<DatasetView>,
}

impl Dataset {
    /// Borrow the views for carving.
    pub fn carving_views(&self) -> Vec<View<'_>> {
        self.views.iter().map(|v| View { camera: v.camera, mask: &v.mask }).collect()
    }

    /// Fails when no camera sees any part of `bbox` (every corner behind the camera or the projected
    /// box missing the image).
    pub fn check_box_seen(&self, bbox: &Aabb) -> Result<(), DatasetError> {
        let seen = self.views.iter().any(|v| {
            let c = &v.camera;
            let pts: Vec<_> = bbox.corners().iter().filter_map(|p| c.project(p)).collect();
            if pts.is_empty() {
                return false; // the whole box is behind the camera
            }
            if pts.len() < 8 {
                return true; // the box straddles the camera plane: assume the camera sees part of it
            }
            let x0 = pts.iter().map(|q| q.x).fold(f64::INFINITY, f64::min);
            let x1 = pts.iter().map(|q| q.x).fold(f64::NEG_INFINITY, f64::max);
            let y0 = pts.iter().map(|q| q.y).fold(f64::INFINITY, f64::min);
            let y1 = pts.iter().map(|q| q.y).fold(f64::NEG_INFINITY, f64::max);
            x1 >= 0.0 && y1 >= 0.0 && x0 < c.width as f64 && y0 < c.height as f64
        });
        if seen {
            Ok(())
        } else {
            Err(DatasetError::BoxUnseen { min: bbox.min, max: bbox.max })
        }
    }
}

fn find_par(dir: &Path) -> Result<PathBuf, DatasetError> {
    let rd = std::fs::read_dir(dir).map_err(|source| DatasetError::Read { path: dir.to_path_buf(), source })?;
    let mut found: Vec<PathBuf> = rd
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.ends_with("_par.txt")))
        .collect();
    found.sort();
    found.into_iter().next().ok_or_else(|| DatasetError::NoCalibration { dir: dir.to_path_buf() })
}

/// Open an image of any format the project reads: PNG (8 or 16 bits per channel), JPEG, PNM
/// (PBM/PGM/PPM), TIFF and BMP, told apart by their content. Anything else, and any decoding error,
/// is a [`DatasetError::Image`] naming the file.
pub fn open_image(path: &Path) -> Result<image::DynamicImage, DatasetError> {
    let err = |source| DatasetError::Image { path: path.to_path_buf(), source };
    image::ImageReader::open(path)
        .map_err(|e| err(image::ImageError::IoError(e)))?
        .with_guessed_format()
        .map_err(|e| err(image::ImageError::IoError(e)))?
        .decode()
        .map_err(err)
}

/// Load an image as 8-bit RGB (16-bit images are scaled to 8 bits); see [`open_image`].
pub fn load_rgb(path: &Path) -> Result<RgbImage, DatasetError> {
    Ok(open_image(path)?.to_rgb8())
}

/// Load an image as 8-bit grey (luma); see [`open_image`].
pub fn load_gray(path: &Path) -> Result<image::GrayImage, DatasetError> {
    Ok(open_image(path)?.to_luma8())
}

/// Load a mask image (any format of [`open_image`]; any non-zero luma is object).
pub fn load_mask(path: &Path) -> Result<Mask, DatasetError> {
    let img = load_gray(path)?;
    let (w, h) = img.dimensions();
    Ok(Mask::from_fn(w, h, |u, v| img.get_pixel(u, v).0[0] != 0))
}

/// A depth map read from disk.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Depth along the optical axis (camera-frame `z`), metres, row-major; 0 = no measurement (as
    /// [`crate::pipeline::depth_fusion::Tsdf::integrate`] takes it).
    pub depth_m: Vec<f32>,
}

/// TUM RGB-D's and Open3D's depth scale: a 16-bit PNG value of 1000 is one metre.
pub const DEPTH_PNG_UNITS_PER_M: f32 = 1000.0;

/// Load a depth map stored as a single-channel 16-bit PNG in millimetres (`value / 1000` metres, 0 =
/// no measurement), the convention of TUM RGB-D and Open3D. Any other image (8-bit, colour, not a
/// PNG) is [`DatasetError::DepthFormat`] naming the file.
pub fn load_depth_png_mm(path: &Path) -> Result<DepthImage, DatasetError> {
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Read { path: path.to_path_buf(), source })?;
    let format = image::guess_format(&bytes).ok();
    if format != Some(image::ImageFormat::Png) {
        return Err(DatasetError::DepthFormat {
            path: path.to_path_buf(),
            found: format.map_or_else(|| "an unknown format".to_string(), |f| format!("{f:?}")),
        });
    }
    let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .map_err(|source| DatasetError::Image { path: path.to_path_buf(), source })?;
    match img {
        image::DynamicImage::ImageLuma16(buf) => {
            let (width, height) = buf.dimensions();
            let depth_m = buf.into_raw().into_iter().map(|v| v as f32 / DEPTH_PNG_UNITS_PER_M).collect();
            Ok(DepthImage { width, height, depth_m })
        }
        other => Err(DatasetError::DepthFormat {
            path: path.to_path_buf(),
            found: format!("a PNG of {:?} pixels", other.color()),
        }),
    }
}

/// Load a data set (see the module docs). Masks are extracted in parallel.
pub fn load(opts: &DatasetOptions) -> Result<Dataset, DatasetError> {
    use rayon::prelude::*;
    let cal_path = match &opts.calibration {
        Some(p) => p.clone(),
        None => find_par(&opts.dir)?,
    };
    let cals = opts.views.apply(read_calibration(&cal_path)?)?;
    if cals.is_empty() {
        return Err(DatasetError::NoViews { path: cal_path });
    }
    let views = cals
        .par_iter()
        .map(|cal| {
            let image_path = opts.dir.join(&cal.name);
            let need_image = opts.load_images || matches!(opts.masks, MaskSource::Extract(_));
            let image = if need_image {
                match std::fs::metadata(&image_path) {
                    Ok(m) if m.is_file() => {}
                    Ok(m) => {
                        use std::os::unix::fs::FileTypeExt;
                        let t = m.file_type();
                        let kind = if t.is_dir() {
                            "a directory"
                        } else if t.is_char_device() || t.is_block_device() {
                            "a device"
                        } else if t.is_fifo() {
                            "a pipe"
                        } else if t.is_socket() {
                            "a socket"
                        } else {
                            "not a plain file"
                        };
                        return Err(DatasetError::NotAFile {
                            calibration: cal_path.clone(),
                            line: cal.line,
                            path: image_path,
                            kind,
                        });
                    }
                    Err(_) => {
                        return Err(DatasetError::MissingImage {
                            calibration: cal_path.clone(),
                            line: cal.line,
                            path: image_path,
                        })
                    }
                }
                Some(load_rgb(&image_path)?)
            } else {
                None
            };
            let mask = match &opts.masks {
                MaskSource::Extract(params) => match &image {
                    Some(img) => extract_silhouette(img, params),
                    None => unreachable_mask(),
                },
                MaskSource::Directory(dir) => {
                    let stem = Path::new(&cal.name).file_stem().map(|s| s.to_os_string()).unwrap_or_default();
                    let mut file = stem;
                    file.push(".png");
                    let path = dir.join(file);
                    let mask = load_mask(&path)?;
                    if let Some(img) = &image {
                        if img.dimensions() != (mask.width(), mask.height()) {
                            return Err(DatasetError::ImageSize {
                                path,
                                width: mask.width(),
                                height: mask.height(),
                                expected_width: img.width(),
                                expected_height: img.height(),
                            });
                        }
                    }
                    mask
                }
            };
            if let Some((width, height)) = cal.size.filter(|&s| s != (mask.width(), mask.height())) {
                return Err(DatasetError::CalibratedSize {
                    calibration: cal_path.clone(),
                    line: cal.line,
                    path: image_path,
                    width: mask.width(),
                    height: mask.height(),
                    calibrated_width: width,
                    calibrated_height: height,
                });
            }
            Ok(DatasetView { name: cal.name.clone(), camera: cal.camera(mask.width(), mask.height()), mask, image })
        })
        .collect::<Result<Vec<_>, DatasetError>>()?;
    Ok(Dataset { views })
}

/// Never reached: images are always loaded when masks are extracted.
fn unreachable_mask() -> Mask {
    Mask::from_fn(0, 0, |_, _| false)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rq_decomposition_recovers_k_r_t() {
        let cam = CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics {
                fx: 900.0,
                fy: 880.0,
                cx: 300.0,
                cy: 250.0,
                skew: 1.5,
                k1: 0.0,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(Vector3::new(0.3, -0.4, 0.2), Vector3::new(0.0, 0.0, 0.05), Vector3::z()),
        };
        for scale in [1.0, -2.5, 0.01] {
            let p = cam.projection_matrix() * scale;
            let (k, pose) = decompose_projection(&p).expect("decomposes");
            assert!((k.fx - 900.0).abs() < 1e-6 && (k.fy - 880.0).abs() < 1e-6 && (k.skew - 1.5).abs() < 1e-6);
            assert!((k.cx - 300.0).abs() < 1e-6 && (k.cy - 250.0).abs() < 1e-6);
            assert!((pose.rotation - cam.pose.rotation).norm() < 1e-9);
            assert!((pose.translation - cam.pose.translation).norm() < 1e-9);
        }
        assert!(decompose_projection(&nalgebra::Matrix3x4::zeros()).is_none());
    }

    #[test]
    fn the_scene_decides_which_way_a_camera_looks() {
        let cam = CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics::new(900.0, 880.0, 300.0, 250.0),
            pose: Pose::look_at(Vector3::new(0.3, -0.4, 0.2), Vector3::new(0.0, 0.0, 0.05), Vector3::z()),
        };
        let scene = Vector3::new(0.01, 0.02, 0.06);
        // Mirrored world (x' = -x): P' = P diag(-1, 1, 1, 1) has a negative determinant with the
        // scene in front; either overall sign decomposes to a camera that sees the mirrored scene.
        let mut mirrored = cam.projection_matrix();
        mirrored.column_mut(0).neg_mut();
        let scene_m = Vector3::new(-scene.x, scene.y, scene.z);
        for p in [mirrored, -mirrored * 3.0] {
            let (k, pose) = decompose_projection_facing(&p, &scene_m).expect("decomposes");
            assert!((k.fx - 900.0).abs() < 1e-6 && (k.cy - 250.0).abs() < 1e-6);
            assert!((pose.rotation.determinant() + 1.0).abs() < 1e-9, "a mirror, not a rotation");
            let m = CameraModel { intrinsics: k, pose, ..cam };
            let a = cam.project(&scene).expect("in front");
            let b = m.project(&scene_m).expect("in front of the mirrored camera too");
            assert!((a - b).norm() < 1e-6, "{a} {b}");
        }
        // The determinant rule gets the mirrored camera backwards: the scene ends up behind it.
        let (k, pose) = decompose_projection(&mirrored).expect("decomposes");
        assert!(CameraModel { intrinsics: k, pose, ..cam }.project(&scene_m).is_none());
        // The axes of cameras around the object converge near it.
        let cams: Vec<_> = (0..6)
            .map(|i| {
                let a = i as f64;
                let eye = Vector3::new(0.5 * a.cos(), 0.5 * a.sin(), 0.2);
                CameraModel { pose: Pose::look_at(eye, scene, Vector3::z()), ..cam }.projection_matrix()
                    * if i % 2 == 0 { 1.0 } else { -1.0 }
            })
            .collect();
        let x = axes_convergence_point(&cams).expect("converge");
        assert!((x - scene).norm() < 1e-9, "{x}");
        assert!(axes_convergence_point(&cams[..1]).is_none());
    }

    #[test]
    fn colmap_text_model_matches_the_cameras_it_was_written_from() {
        let cam = CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics::new(900.0, 880.0, 300.0, 250.0).with_distortion([-0.1, 0.02, 1e-3, -1e-3, 0.0]),
            pose: Pose::look_at(Vector3::new(0.3, -0.4, 0.2), Vector3::new(0.0, 0.0, 0.05), Vector3::z()),
        };
        let q = nalgebra::UnitQuaternion::from_matrix(&cam.pose.rotation);
        let t = cam.pose.translation;
        let cameras = "# Camera list\n1 OPENCV 640 480 900 880 300 250 -0.1 0.02 0.001 -0.001\n2 SIMPLE_PINHOLE 640 480 500 320 240\n";
        let images = format!(
            "# Image list\n1 {} {} {} {} {} {} {} 1 a.png\n10 20 -1\n2 1 0 0 0 0 0 1 2 b c.png\n\n",
            q.w, q.i, q.j, q.k, t.x, t.y, t.z
        );
        let c = parse_colmap(cameras, Path::new("cameras.txt"), &images, Path::new("images.txt")).expect("parses");
        assert_eq!(c.len(), 2);
        assert_eq!(c[1].name, "b c.png");
        let m = c[0].camera(640, 480);
        let p = Vector3::new(0.01, 0.02, 0.04);
        let (a, b) = (cam.project(&p).expect("a"), m.project(&p).expect("b"));
        assert!((a - b).norm() < 1e-9, "{a} {b}");
        assert_eq!(c[1].intrinsics.fx, 500.0);
        let e = parse_colmap("1 FISHEYE 640 480 1 2 3 4\n", Path::new("cameras.txt"), &images, Path::new("images.txt"))
            .expect_err("model");
        assert!(e.to_string().starts_with("cameras.txt:1: camera model FISHEYE"), "{e}");
    }

    #[test]
    fn every_image_format_reads_and_depth_pngs_are_millimetres() {
        let dir = tempfile::tempdir().expect("tempdir");
        let rgb = RgbImage::from_fn(5, 4, |x, y| image::Rgb([x as u8 * 40, y as u8 * 60, 7]));
        // Saved under misleading extensions: the content decides the format.
        for (name, fmt) in [
            ("a.ppm", image::ImageFormat::Pnm),
            ("b.tif", image::ImageFormat::Tiff),
            ("c.bmp", image::ImageFormat::Bmp),
            ("d.img", image::ImageFormat::Png),
        ] {
            let path = dir.path().join(name);
            rgb.save_with_format(&path, fmt).expect("save");
            assert_eq!(load_rgb(&path).expect(name), rgb, "{name}");
        }
        let grey16 = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(3, 2, |x, y| {
            image::Luma([(x + 3 * y) as u16 * 1000])
        });
        let depth = dir.path().join("depth.png");
        grey16.save(&depth).expect("save 16-bit");
        let d = load_depth_png_mm(&depth).expect("depth");
        assert_eq!((d.width, d.height), (3, 2));
        assert_eq!(d.depth_m, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
        // A 16-bit PNG also reads as an image (scaled to 8 bits).
        assert_eq!(
            load_gray(&depth).expect("grey").get_pixel(2, 1).0[0],
            ((5000.0f64 / 65535.0) * 255.0).round() as u8
        );
        let e = load_depth_png_mm(&dir.path().join("a.ppm")).expect_err("not a PNG");
        assert!(matches!(e, DatasetError::DepthFormat { .. }) && e.to_string().contains("a.ppm"), "{e}");
        let e = load_depth_png_mm(&dir.path().join("d.img")).expect_err("8-bit RGB");
        assert!(e.to_string().contains("d.img") && e.to_string().contains("16-bit"), "{e}");
        let junk = dir.path().join("junk.png");
        std::fs::write(&junk, b"not an image at all").expect("write");
        let e = load_rgb(&junk).expect_err("junk");
        assert!(e.to_string().contains("junk.png"), "{e}");
    }

    #[test]
    fn par_errors_name_the_line() {
        let p = Path::new("x_par.txt");
        let ok = "1\nimg.png 1 0 2 0 1 3 0 0 1 1 0 0 0 1 0 0 0 1 0.1 0.2 0.3\n";
        let c = parse_par(ok, p).expect("parses");
        assert_eq!(c[0].intrinsics.cx, 2.0);
        assert_eq!(c[0].pose.translation.z, 0.3);
        let e = parse_par("2\nimg.png 1 0 2 0 1 3 0 0 1 1 0 0 0 1 0 0 0 1 0.1 0.2 0.3\n", p).expect_err("count");
        assert!(matches!(e, DatasetError::ViewCount { declared: 2, found: 1, .. }));
        let e = parse_par("1\nimg.png 1 0 2\n", p).expect_err("values");
        assert_eq!(e.to_string(), "x_par.txt:2: expected 22 values, found 4");
        let e = parse_par("1\nimg.png 1 0 2 0 1 3 0 0 1 1 0 0 0 1 0 0 0 1 0.1 NaN 0.3\n", p).expect_err("nan");
        assert!(matches!(e, DatasetError::NonFinite { line: 2, .. }));
        let e = parse_par("1\nimg.png 1 0 2 0 1 3 0 0 1 1 0 0 0 1 0 0 0 1 0.1 x 0.3\n", p).expect_err("nan");
        assert!(e.to_string().starts_with("x_par.txt:2:"));
        let e = parse_projections("# c\n\na 1 2 3\n", Path::new("p.txt")).expect_err("values");
        assert!(e.to_string().starts_with("p.txt:3:"));
    }

    #[test]
    fn view_selection_by_list() {
        let p = Path::new("x_par.txt");
        let text =
            "2\na.png 1 0 2 0 1 3 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\nb.png 1 0 2 0 1 3 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n";
        let all = parse_par(text, p).expect("parses");
        let sel = ViewSelection::parse("b.png, a").apply(all.clone()).expect("selects");
        assert_eq!(sel.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(), ["b.png", "a.png"]);
        assert!(ViewSelection::parse("c.png").apply(all).is_err());
    }
}
