//! Laser-plane calibration from a chessboard under the laser (`scanrig calibrate laser`), and one
//! real laser view triangulated into a coloured cloud (`scanrig laser-view`).
//!
//! For each laser-on / laser-off pair of frames of a board: the board is found in the laser-off
//! frame and posed with the camera's intrinsics ([`super::estimate_pose`]); the stripe is detected
//! in the difference ([`crate::pipeline::laser::detect_stripe`]); the peaks inside the board's
//! inner corners are undistorted into rays and intersected with the board's plane. One pose's
//! points are lines (one per laser) on its board; the laser planes are the planes that two or more
//! poses' points share ([`crate::pipeline::laser::fit_planes_across`]: RANSAC over triples from two
//! poses, then least squares over the inliers, one plane after another).
//!
//! Frame: the camera frame (OpenCV axes: `+x` right, `+y` down, `+z` forward), metres.

use std::path::{Path, PathBuf};

use image::RgbImage;
use nalgebra::{Matrix3, Point2, Vector3};

use super::detect::{detect_chessboard, to_gray, DetectOptions};
use super::{estimate_pose, BoardSpec, PlanarView};
use crate::geometry::{CameraModel, Intrinsics, Pose};
use crate::pipeline::laser::{detect_stripe, fit_planes_across, Plane, PlaneFit, PlaneFitParams, StripeParams};

/// Why a laser step failed; each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum LaserBoardError {
    /// An image could not be read.
    #[error("{}", path.display())]
    Image {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: crate::dataset::DatasetError,
    },
    /// The board was not found in a laser-off frame.
    #[error("{}: no board", path.display())]
    Detect {
        /// The frame.
        path: PathBuf,
        /// The cause.
        #[source]
        source: super::DetectError,
    },
    /// The board could not be posed.
    #[error("{}: board pose", path.display())]
    Pose {
        /// The frame.
        path: PathBuf,
        /// The cause.
        #[source]
        source: super::CalibrationError,
    },
    /// Stripe detection or the plane fit failed.
    #[error("{}: laser", path.display())]
    Laser {
        /// The frame (or the last one, for the fit).
        path: PathBuf,
        /// The cause.
        #[source]
        source: crate::pipeline::laser::LaserError,
    },
    /// A PLY file could not be read.
    #[error("{}: {reason}", path.display())]
    Ply {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

fn rgb(path: &Path) -> Result<RgbImage, LaserBoardError> {
    crate::dataset::load_rgb(path).map_err(|source| LaserBoardError::Image { path: path.to_path_buf(), source })
}

/// The camera at the origin of its own frame.
pub fn camera_at_origin(intrinsics: Intrinsics, width: u32, height: u32) -> CameraModel {
    CameraModel {
        width,
        height,
        intrinsics,
        pose: Pose { rotation: Matrix3::identity(), translation: Vector3::zeros() },
    }
}

/// One board pair's result.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardLaserView {
    /// The laser-on frame.
    pub laser: PathBuf,
    /// The frame the board was found in.
    pub board_frame: PathBuf,
    /// Board -> camera pose, metres.
    pub pose: Pose,
    /// Board pose re-projection RMS, pixels.
    pub pose_rms_px: f64,
    /// Stripe peaks detected in the whole frame.
    pub peaks: usize,
    /// Stripe points on the board (inside its inner corners), camera frame, metres.
    pub points: Vec<Vector3<f64>>,
}

fn inside_quad(q: &[Point2<f64>; 4], p: &Point2<f64>) -> bool {
    let mut sign = 0.0;
    for i in 0..4 {
        let (a, b) = (q[i], q[(i + 1) % 4]);
        let c = (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x);
        if c != 0.0 {
            if sign != 0.0 && c.signum() != sign {
                return false;
            }
            sign = c.signum();
        }
    }
    true
}

/// Grey levels stretched linearly so the 1st and 99th percentiles map to 0 and 255.
pub fn stretch(img: &image::GrayImage) -> image::GrayImage {
    let mut hist = [0usize; 256];
    for p in img.as_raw() {
        hist[*p as usize] += 1;
    }
    let n = img.as_raw().len();
    let level = |frac: f64| {
        let target = (frac * n as f64) as usize;
        let mut acc = 0;
        for (v, h) in hist.iter().enumerate() {
            acc += h;
            if acc > target {
                return v as f64;
            }
        }
        255.0
    };
    let (lo, hi) = (level(0.01), level(0.99));
    let scale = if hi > lo { 255.0 / (hi - lo) } else { 1.0 };
    let mut out = img.clone();
    for p in out.iter_mut() {
        *p = ((f64::from(*p) - lo) * scale).round().clamp(0.0, 255.0) as u8;
    }
    out
}

/// The stripe points on the board of one laser-on / laser-off pair. The board is found in `pattern`
/// (a well-lit frame of the same pose) when given, else in the contrast-stretched laser frames.
pub fn board_laser_view(
    intrinsics: &Intrinsics,
    board: &BoardSpec,
    laser: &Path,
    background: &Path,
    pattern: Option<&Path>,
    colour: [u8; 3],
    stripe: &StripeParams,
) -> Result<BoardLaserView, LaserBoardError> {
    let on = rgb(laser)?;
    let off = rgb(background)?;
    // Laser frames are exposed for the laser, so the board is dark: stretch the contrast, and try
    // the red channel (a red laser's frames are often exposed for red) and more smoothing.
    let red = |img: &RgbImage| {
        image::GrayImage::from_fn(img.width(), img.height(), |x, y| image::Luma([img.get_pixel(x, y).0[0]]))
    };
    let board_frame = match pattern {
        Some(p) => vec![(p.to_path_buf(), to_gray(&rgb(p)?))],
        None => vec![
            (background.to_path_buf(), stretch(&to_gray(&off))),
            (background.to_path_buf(), stretch(&red(&off))),
            (laser.to_path_buf(), stretch(&to_gray(&on))),
            (laser.to_path_buf(), stretch(&red(&on))),
        ],
    };
    let mut found = None;
    let mut first_err = None;
    'search: for (path, g) in &board_frame {
        // Larger rings suit the large squares of a board close to the camera (and skip the noise
        // that stretching a dark frame brings out).
        for (sigma_px, min_contrast, ring_radius_px) in [
            (1.5, 20.0, 5.0),
            (2.5, 20.0, 5.0),
            (2.5, 10.0, 5.0),
            (4.0, 10.0, 5.0),
            (2.5, 10.0, 8.0),
            (4.0, 10.0, 12.0),
            (6.0, 8.0, 5.0),
            (8.0, 6.0, 5.0),
        ] {
            let opts = DetectOptions { sigma_px, min_contrast, ring_radius_px, ..DetectOptions::default() };
            match detect_chessboard(g, board, &opts) {
                Ok(d) => {
                    found = Some((path.clone(), d));
                    break 'search;
                }
                Err(e) => {
                    first_err.get_or_insert((path.clone(), e));
                }
            }
        }
    }
    let (board_path, det) = match (found, first_err) {
        (Some(f), _) => f,
        (None, Some((path, source))) => return Err(LaserBoardError::Detect { path, source }),
        (None, None) => unreachable_detect(background)?,
    };
    let est = estimate_pose(intrinsics, &PlanarView { object: board.object_points(), image: det.corners.clone() })
        .map_err(|source| LaserBoardError::Pose { path: board_path.clone(), source })?;
    let peaks = detect_stripe(&off, &on, colour, stripe)
        .map_err(|source| LaserBoardError::Laser { path: laser.to_path_buf(), source })?;
    let c = &det.corners;
    let (nc, nr) = (board.cols, board.rows);
    let quad = [c[0], c[nc - 1], c[nr * nc - 1], c[(nr - 1) * nc]];
    let n = est.pose.rotation.column(2).into_owned();
    let plane = Plane { normal: n.into(), offset_m: n.dot(&est.pose.translation) };
    let cam = camera_at_origin(*intrinsics, on.width(), on.height());
    let points = peaks
        .iter()
        .filter(|pk| inside_quad(&quad, &Point2::new(pk.u, f64::from(pk.v) + 0.5)))
        .filter_map(|pk| plane.intersect(&Vector3::zeros(), &cam.pixel_ray(pk.u, f64::from(pk.v) + 0.5)))
        .collect();
    Ok(BoardLaserView {
        laser: laser.to_path_buf(),
        board_frame: board_path,
        pose: est.pose,
        pose_rms_px: est.rms_px,
        peaks: peaks.len(),
        points,
    })
}

/// The board search always tries at least one frame; this only keeps the types honest.
fn unreachable_detect(background: &Path) -> Result<(PathBuf, super::ChessboardDetection), LaserBoardError> {
    Err(LaserBoardError::Ply { path: background.to_path_buf(), reason: "no frame to find the board in".into() })
}

/// The laser planes in the board views' stripe points (camera frame, metres): every plane that two
/// or more board poses each give `min_per_pose` points within `inlier_m`
/// ([`crate::pipeline::laser::fit_planes_across`]; one pose's stripes are lines on its board, and a
/// frame may show several lasers' stripes). Normals point away from the camera (`+z`), as published
/// calibrations give them, and the planes are ordered by the normal's `x`: a laser left of the
/// camera (its plane's normal pointing left) first.
pub fn fit_laser_planes(
    views: &[BoardLaserView],
    inlier_m: f64,
    min_per_pose: usize,
    max_planes: usize,
) -> Result<Vec<PlaneFit>, LaserBoardError> {
    let sets: Vec<Vec<Vector3<f64>>> = views.iter().map(|v| v.points.clone()).collect();
    let path = views.last().map(|v| v.laser.clone()).unwrap_or_default();
    let params = PlaneFitParams { inlier_m, iterations: 3000, ..PlaneFitParams::default() };
    let mut fits = fit_planes_across(&sets, &params, min_per_pose, max_planes)
        .map_err(|source| LaserBoardError::Laser { path, source })?;
    for f in &mut fits {
        if f.plane.normal[2] < 0.0 {
            f.plane = Plane { normal: f.plane.normal.map(|x| -x), offset_m: -f.plane.offset_m };
        }
    }
    fits.sort_by(|a, b| a.plane.normal[0].total_cmp(&b.plane.normal[0]));
    Ok(fits)
}

/// The `x y z` of every vertex of a PLY file (binary little-endian or ASCII; the first three
/// vertex properties must be `x y z` as float or double; other vertex properties are skipped).
pub fn read_ply_xyz(path: &Path) -> Result<Vec<Vector3<f64>>, LaserBoardError> {
    let bad = |reason: String| LaserBoardError::Ply { path: path.to_path_buf(), reason };
    let bytes = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
    let marker = b"end_header";
    let end = bytes.windows(marker.len()).position(|w| w == marker).ok_or_else(|| bad("no end_header".into()))?;
    let mut body = end + marker.len();
    while body < bytes.len() && bytes[body] != b'\n' {
        body += 1;
    }
    body += 1;
    let header = String::from_utf8_lossy(&bytes[..end]).into_owned();
    let ascii = header.contains("format ascii");
    if !ascii && !header.contains("format binary_little_endian") {
        return Err(bad("only ASCII and binary little-endian PLY are read".into()));
    }
    let mut count = None;
    let mut props: Vec<(String, String)> = Vec::new();
    let mut in_vertex = false;
    for l in header.lines() {
        let t: Vec<&str> = l.split_whitespace().collect();
        match t.as_slice() {
            ["element", "vertex", n] => {
                count = n.parse::<usize>().ok();
                in_vertex = true;
            }
            ["element", ..] => in_vertex = false,
            ["property", ty, name] if in_vertex => props.push((ty.to_string(), name.to_string())),
            _ => {}
        }
    }
    let count = count.ok_or_else(|| bad("no vertex element".into()))?;
    if props.len() < 3 || props[0].1 != "x" || props[1].1 != "y" || props[2].1 != "z" {
        return Err(bad("the first vertex properties must be x y z".into()));
    }
    let size = |ty: &str| match ty {
        "char" | "uchar" | "int8" | "uint8" => Some(1),
        "short" | "ushort" | "int16" | "uint16" => Some(2),
        "int" | "uint" | "float" | "int32" | "uint32" | "float32" => Some(4),
        "double" | "float64" => Some(8),
        _ => None,
    };
    let mut out = Vec::with_capacity(count);
    if ascii {
        let text = String::from_utf8_lossy(&bytes[body..]);
        for (i, l) in text.lines().take(count).enumerate() {
            let v: Vec<f64> = l.split_whitespace().take(3).filter_map(|t| t.parse().ok()).collect();
            if v.len() != 3 {
                return Err(bad(format!("vertex {i}: not three numbers")));
            }
            out.push(Vector3::new(v[0], v[1], v[2]));
        }
    } else {
        let sizes: Vec<usize> = props
            .iter()
            .map(|(t, _)| size(t))
            .collect::<Option<_>>()
            .ok_or_else(|| bad("unknown property type".into()))?;
        let stride: usize = sizes.iter().sum();
        let data = &bytes[body..];
        if data.len() < stride * count {
            return Err(bad(format!("{} bytes for {count} vertices of {stride} bytes", data.len())));
        }
        for v in data.chunks_exact(stride).take(count) {
            let mut xyz = [0.0; 3];
            let mut off = 0;
            for (k, x) in xyz.iter_mut().enumerate() {
                *x = match sizes[k] {
                    4 => f32::from_le_bytes([v[off], v[off + 1], v[off + 2], v[off + 3]]) as f64,
                    8 => f64::from_le_bytes(v[off..off + 8].try_into().map_err(|_| bad("short vertex".into()))?),
                    _ => return Err(bad("x y z must be float or double".into())),
                };
                off += sizes[k];
            }
            out.push(Vector3::new(xyz[0], xyz[1], xyz[2]));
        }
    }
    Ok(out)
}

/// One laser view triangulated on a laser plane.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserViewCloud {
    /// Stripe peaks detected.
    pub peaks: usize,
    /// Points, camera frame, metres.
    pub points: Vec<Vector3<f64>>,
    /// Colour of each point from the texture frame.
    pub colours: Vec<[u8; 3]>,
}

/// Detect the stripe of a laser-on / laser-off pair and triangulate it on `plane` (camera frame),
/// colouring each point from `texture` (a frame under white light, optional; else the laser-off
/// frame).
pub fn laser_view(
    intrinsics: &Intrinsics,
    plane: &Plane,
    laser: &Path,
    background: &Path,
    texture: Option<&Path>,
    colour: [u8; 3],
    stripe: &StripeParams,
) -> Result<LaserViewCloud, LaserBoardError> {
    let on = rgb(laser)?;
    let off = rgb(background)?;
    let tex = match texture {
        Some(t) => rgb(t)?,
        None => off.clone(),
    };
    let peaks = detect_stripe(&off, &on, colour, stripe)
        .map_err(|source| LaserBoardError::Laser { path: laser.to_path_buf(), source })?;
    let cam = camera_at_origin(*intrinsics, on.width(), on.height());
    let mut points = Vec::new();
    let mut colours = Vec::new();
    for pk in &peaks {
        let Some(p) = plane.intersect(&Vector3::zeros(), &cam.pixel_ray(pk.u, f64::from(pk.v) + 0.5)) else {
            continue;
        };
        let (x, y) =
            ((pk.u.floor() as u32).min(tex.width().saturating_sub(1)), pk.v.min(tex.height().saturating_sub(1)));
        points.push(p);
        colours.push(tex.get_pixel(x, y).0);
    }
    Ok(LaserViewCloud { peaks: peaks.len(), points, colours })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_reader_reads_binary_and_ascii() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("a.ply");
        let pts = [[1.0f32, 2.0, 3.0], [-4.0, 5.5, 6.0]];
        std::fs::write(&p, crate::pipeline::export::ply_points_bytes(&pts, Some(&vec![[1, 2, 3], [4, 5, 6]])))
            .expect("write");
        let r = read_ply_xyz(&p).expect("binary");
        assert_eq!(r, vec![Vector3::new(1.0, 2.0, 3.0), Vector3::new(-4.0, 5.5, 6.0)]);
        let q = dir.path().join("b.ply");
        std::fs::write(&q, "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n")
            .expect("write");
        assert_eq!(read_ply_xyz(&q).expect("ascii"), vec![Vector3::new(1.0, 2.0, 3.0)]);
        std::fs::write(&q, "ply\nformat ascii 1.0\nend_header\n").expect("write");
        assert!(read_ply_xyz(&q).expect_err("no vertices").to_string().contains("b.ply"));
    }
}
