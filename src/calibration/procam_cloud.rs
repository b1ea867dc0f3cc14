//! A real structured-light capture triangulated with its projector-camera calibration into a point
//! cloud (`scanrig triangulate`), and the figures that check it on a chessboard: the plane-fit RMS of
//! the board's points and the distances between triangulated neighbouring corners against the
//! square size.
//!
//! # Frames and units
//! The camera frame is the reference frame (camera at the origin, OpenCV axes: `+x` right, `+y` down,
//! `+z` forward); the projector is posed by the calibration's projector <- camera rotation and
//! translation. Lengths come out in the unit of the calibration's translation (the unit of the
//! square size it was calibrated with: millimetres for a board measured in millimetres).
//!
//! # Projector coordinates
//! A decoded Gray code `c` of a sequence shown enlarged by `graycode_step` covers projector pixels
//! `[step·c, step·(c+1))`; the dense cloud uses stripe-edge interpolation
//! ([`crate::pipeline::structured_light::interpolate_stripe_edges`]) scaled by the step; corners get
//! their projector coordinate from the local homography of [`super::procam::projector_corners`].

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Point2, Vector3};

use super::opencv_xml::ReferenceCalibration;
use super::procam::{procam_view_from_frames, ProcamViewOptions};
use super::procam_file::{read_procam_file, ProcamFile, ProcamFileError};
use super::BoardSpec;
use crate::geometry::{CameraModel, Pose};
use crate::pipeline::export::write_ply_points;
use crate::pipeline::structured_light::{
    decode, interpolate_stripe_edges, load_capture_dir, GrayCodePatterns, ProjectorCoords, ProjectorMap,
    TriangulationParams, Triangulator,
};

impl ProcamFile {
    /// A procam file from a published OpenCV `calibration_result.xml`: the reference has no projector
    /// size, so the Gray-code pattern size (projector pixels / step) and the step are given.
    pub fn from_reference(r: &ReferenceCalibration, patterns: (u32, u32), graycode_step: u32) -> ProcamFile {
        let m = r.rotation;
        let step = graycode_step.max(1);
        ProcamFile {
            camera: r.camera,
            projector: r.projector,
            projector_width: patterns.0 * step,
            projector_height: patterns.1 * step,
            graycode_step: step,
            rotation: [
                [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
                [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
                [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
            ],
            translation: [r.translation.x, r.translation.y, r.translation.z],
            camera_rms_px: r.rms_px.unwrap_or(f64::NAN),
            projector_rms_px: r.rms_px.unwrap_or(f64::NAN),
            views: 0,
        }
    }

    /// The camera (at the origin of its own frame) and the projector posed projector <- camera, for
    /// a camera image of `width x height` pixels.
    pub fn models(&self, width: u32, height: u32) -> (CameraModel, CameraModel) {
        let camera = CameraModel {
            width,
            height,
            intrinsics: self.camera,
            pose: Pose { rotation: Matrix3::identity(), translation: Vector3::zeros() },
        };
        let r = self.rotation;
        let projector = CameraModel {
            width: self.projector_width,
            height: self.projector_height,
            intrinsics: self.projector,
            pose: Pose {
                rotation: Matrix3::new(r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2]),
                translation: Vector3::new(self.translation[0], self.translation[1], self.translation[2]),
            },
        };
        (camera, projector)
    }
}

/// Read a projector-camera calibration: a TOML file written by `scanrig calibrate projector`, or an
/// OpenCV FileStorage XML `calibration_result.xml` (recognised by its `<?xml` / `<opencv_storage>`
/// start), for which `patterns` and `graycode_step` say the projector's size.
pub fn load_procam(path: &Path, patterns: (u32, u32), graycode_step: u32) -> Result<ProcamFile, ProcamFileError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| ProcamFileError::ReadFile { path: path.to_path_buf(), reason: e.to_string() })?;
    let head = text.trim_start();
    if head.starts_with("<?xml") || head.starts_with("<opencv_storage") {
        let r = ReferenceCalibration::parse(&text, path)?;
        Ok(ProcamFile::from_reference(&r, patterns, graycode_step))
    } else {
        read_procam_file(path)
    }
}

/// Apply a procam file (TOML of `scanrig calibrate projector`, translation in metres) to a rig's fbdev
/// projector: its intrinsics, and its rig-frame pose `x_proj = R_pc (R_c x + t_c) + t_pc` from the
/// file's projector <- camera transform and the rig camera's pose. The file's projector size must be
/// the rig's.
pub fn apply_procam_to_rig(path: &Path, rig: &mut crate::config::RigConfig) -> Result<(), ProcamFileError> {
    use crate::config::{CameraCalibration, PoseConfig, ProjectorConfig};
    let file = read_procam_file(path)?;
    let camera = rig.camera.model();
    let Some(ProjectorConfig::Fbdev(p)) = rig.projector.as_mut() else { return Ok(()) };
    if (file.projector_width, file.projector_height) != (p.width, p.height) {
        return Err(ProcamFileError::ReadFile {
            path: path.to_path_buf(),
            reason: format!(
                "calibrated for a {}x{} projector but the rig's is {}x{}",
                file.projector_width, file.projector_height, p.width, p.height
            ),
        });
    }
    if !file.projector.is_valid() {
        return Err(ProcamFileError::ReadFile {
            path: path.to_path_buf(),
            reason: "projector: focal lengths must be positive and every value finite".into(),
        });
    }
    let (_, proj_in_camera) = file.models(camera.width, camera.height);
    let (r_pc, t_pc) = (proj_in_camera.pose.rotation, proj_in_camera.pose.translation);
    let rotation = r_pc * camera.pose.rotation;
    let translation = r_pc * camera.pose.translation + t_pc;
    p.calibration = Some(CameraCalibration {
        intrinsics: file.projector,
        pose: PoseConfig::Matrix {
            rotation: [
                [rotation[(0, 0)], rotation[(0, 1)], rotation[(0, 2)]],
                [rotation[(1, 0)], rotation[(1, 1)], rotation[(1, 2)]],
                [rotation[(2, 0)], rotation[(2, 1)], rotation[(2, 2)]],
            ],
            translation_m: [translation.x, translation.y, translation.z],
        },
    });
    Ok(())
}

/// What `scanrig triangulate` does.
#[derive(Debug, Clone, PartialEq)]
pub struct TriangulateRequest {
    /// The captured Gray-code sequence (pattern/inverse pairs, columns then rows, then white, black).
    pub images: PathBuf,
    /// The projector-camera calibration ([`load_procam`]).
    pub procam: PathBuf,
    /// Gray-code pattern size, projector pixels / step.
    pub patterns: (u32, u32),
    /// Projector pixels per Gray-code pixel (for an XML calibration; a TOML one carries its own).
    pub graycode_step: u32,
    /// Decoder thresholds and, when [`TriangulateRequest::board`] is set, corner detection options.
    pub view: ProcamViewOptions,
    /// The chessboard in view, square size in the calibration's length unit, to measure the cloud.
    pub board: Option<BoardSpec>,
    /// Output point cloud (binary PLY, coloured by the white frame).
    pub out: PathBuf,
}

/// The chessboard checks of a triangulated capture.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardCheck {
    /// Cloud points inside the board's outer corners.
    pub plane_points: usize,
    /// RMS distance of those points from their least-squares plane, calibration units.
    pub plane_rms: f64,
    /// Largest distance from the plane among them, calibration units.
    pub plane_max: f64,
    /// Corners triangulated (camera corner ray with its projector corner ray).
    pub corners: usize,
    /// Neighbouring corner pairs measured (along rows and columns).
    pub pairs: usize,
    /// Mean distance between neighbouring corners, calibration units.
    pub spacing_mean: f64,
    /// Largest `|distance - square| / square` over the pairs, fraction.
    pub spacing_max_rel_error: f64,
    /// RMS of `distance - square`, calibration units.
    pub spacing_rms: f64,
    /// Mean gap between the camera and projector rays of the corners, calibration units.
    pub corner_ray_gap_mean: f64,
}

/// The result of [`run_triangulate`].
#[derive(Debug, Clone, PartialEq)]
pub struct TriangulateReport {
    /// Camera image size, pixels.
    pub camera_size: (u32, u32),
    /// Fraction of camera pixels decoded on every bit.
    pub decoded_fraction: f64,
    /// Points written.
    pub points: usize,
    /// Points removed by the neighbour test.
    pub outliers: usize,
    /// The board checks, when a board was given.
    pub board: Option<BoardCheck>,
}

/// Least-squares plane of `pts` (`(normal, centroid)`); `None` for fewer than 3 points.
pub fn fit_plane(pts: &[Vector3<f64>]) -> Option<(Vector3<f64>, Vector3<f64>)> {
    if pts.len() < 3 {
        return None;
    }
    let c = pts.iter().sum::<Vector3<f64>>() / pts.len() as f64;
    let mut cov = Matrix3::zeros();
    for p in pts {
        let d = p - c;
        cov += d * d.transpose();
    }
    let e = cov.symmetric_eigen();
    let (i, _) = e.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    Some((e.eigenvectors.column(i).normalize(), c))
}

/// Closest-point midpoint of two rays and their gap; `None` when parallel or behind either origin.
fn ray_midpoint(
    o1: &Vector3<f64>,
    d1: &Vector3<f64>,
    o2: &Vector3<f64>,
    d2: &Vector3<f64>,
) -> Option<(Vector3<f64>, f64)> {
    let w = o1 - o2;
    let b = d1.dot(d2);
    let (dd, e) = (d1.dot(&w), d2.dot(&w));
    let den = 1.0 - b * b;
    if den < 1e-12 {
        return None;
    }
    let s = (b * e - dd) / den;
    let t = (e - b * dd) / den;
    if s <= 0.0 || t <= 0.0 {
        return None;
    }
    let (p1, p2) = (o1 + d1 * s, o2 + d2 * t);
    Some(((p1 + p2) * 0.5, (p1 - p2).norm()))
}

/// True when `p` lies inside the convex quadrilateral `q` (in order around it).
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

/// Decode, triangulate and write the cloud; with a board, measure it.
pub fn run_triangulate(req: &TriangulateRequest) -> Result<TriangulateReport, ProcamFileError> {
    let procam = load_procam(&req.procam, req.patterns, req.graycode_step)?;
    let step = procam.graycode_step.max(1);
    let patterns =
        GrayCodePatterns::new(procam.projector_width.div_ceil(step), procam.projector_height.div_ceil(step))?;
    let cap = load_capture_dir(&req.images, patterns.count())
        .map_err(|source| ProcamFileError::Capture { dir: req.images.clone(), source })?;
    let (w, h) = (cap.width as u32, cap.height as u32);
    let (camera, projector) = procam.models(w, h);
    let frames = cap.slices();
    let mut map = ProjectorMap::new();
    decode(&patterns, &frames, cap.width, cap.height, &req.view.decode, &mut map).map_err(|e| {
        ProcamFileError::View { dir: req.images.clone(), source: super::procam::ProcamViewError::Decode(e) }
    })?;
    let sub = interpolate_stripe_edges(&map, true);
    let scale = |v: Vec<f32>| v.into_iter().map(|x| x * step as f32).collect::<Vec<f32>>();
    let coords =
        ProjectorCoords { width: sub.width, height: sub.height, column: scale(sub.column), row: sub.row.map(scale) };
    // Tolerances in the calibration's unit, relative to the baseline (the unit is not known).
    let baseline = projector.centre().norm();
    let params = TriangulationParams {
        max_ray_gap_m: 0.01 * baseline,
        min_neighbours: 5,
        neighbour_tolerance_m: 0.02 * baseline,
    };
    let white_index = patterns.white_index();
    let white_grey = image::GrayImage::from_raw(w, h, cap.images[white_index].clone()).ok_or_else(|| {
        ProcamFileError::ReadFile { path: cap.paths[white_index].clone(), reason: "image size".into() }
    })?;
    let white = image::DynamicImage::ImageLuma8(white_grey).to_rgb8();
    let range = Triangulator::new(&camera, &projector)
        .and_then(|mut t| t.triangulate(&coords, Some(&white), &params))
        .map_err(|e| ProcamFileError::ReadFile { path: req.procam.clone(), reason: format!("triangulation: {e}") })?;
    let (pts, colours): (Vec<[f32; 3]>, Vec<[u8; 3]>) = range.valid_points().map(|(p, _, c)| (p, c)).unzip();
    write_ply_points(&req.out, &pts, Some(&colours))?;

    let board = match &req.board {
        None => None,
        Some(board) => {
            let (view, _) = procam_view_from_frames(&frames, cap.width, cap.height, &patterns, board, &req.view)
                .map_err(|source| ProcamFileError::View { dir: req.images.clone(), source })?;
            Some(check_board(&camera, &projector, board, &view, &range)?)
        }
    };
    Ok(TriangulateReport {
        camera_size: (w, h),
        decoded_fraction: map.valid_fraction(),
        points: pts.len(),
        outliers: range.outliers,
        board,
    })
}

fn check_board(
    camera: &CameraModel,
    projector: &CameraModel,
    board: &BoardSpec,
    view: &super::procam::ProcamView,
    range: &crate::pipeline::structured_light::RangeImage,
) -> Result<BoardCheck, ProcamFileError> {
    let few = || {
        ProcamFileError::Calibration(super::CalibrationError::Degenerate {
            reason: "too few board points for the board check",
        })
    };
    // Plane: cloud points whose camera pixel lies inside the outer corners.
    let cam = &view.camera.image;
    let (c, r) = (board.cols, board.rows);
    let quad = [cam[0], cam[c - 1], cam[r * c - 1], cam[(r - 1) * c]];
    let mut inside = Vec::new();
    for y in 0..range.height as usize {
        for x in 0..range.width as usize {
            let i = y * range.width as usize + x;
            if range.depth_m[i] > 0.0 && inside_quad(&quad, &Point2::new(x as f64 + 0.5, y as f64 + 0.5)) {
                let p = range.points[i];
                inside.push(Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64));
            }
        }
    }
    let (n, centroid) = fit_plane(&inside).ok_or_else(few)?;
    let dists: Vec<f64> = inside.iter().map(|p| (p - centroid).dot(&n)).collect();
    let plane_rms = (dists.iter().map(|d| d * d).sum::<f64>() / dists.len() as f64).sqrt();
    let plane_max = dists.iter().fold(0.0f64, |m, d| m.max(d.abs()));

    // Corners: camera ray of each detected corner with the projector ray of its projector corner.
    let (o, po) = (camera.centre(), projector.centre());
    let mut corner3: Vec<Option<Vector3<f64>>> = vec![None; board.len()];
    let mut gaps = Vec::new();
    for (obj, q) in view.projector.object.iter().zip(&view.projector.image) {
        let Some(k) = view.camera.object.iter().position(|b| (b - obj).norm() < 1e-9) else { continue };
        let u = cam[k];
        let d1 = camera.pixel_ray(u.x, u.y);
        let d2 = projector.pixel_ray(q.x, q.y);
        if let Some((p, gap)) = ray_midpoint(&o, &d1, &po, &d2) {
            corner3[k] = Some(p);
            gaps.push(gap);
        }
    }
    let mut spacing = Vec::new();
    for j in 0..r {
        for i in 0..c {
            let k = j * c + i;
            for nb in [(i + 1 < c).then_some(k + 1), (j + 1 < r).then_some(k + c)].into_iter().flatten() {
                if let (Some(a), Some(b)) = (corner3[k], corner3[nb]) {
                    spacing.push((a - b).norm());
                }
            }
        }
    }
    if spacing.is_empty() {
        return Err(few());
    }
    let s = board.square_m;
    Ok(BoardCheck {
        plane_points: inside.len(),
        plane_rms,
        plane_max,
        corners: gaps.len(),
        pairs: spacing.len(),
        spacing_mean: spacing.iter().sum::<f64>() / spacing.len() as f64,
        spacing_max_rel_error: spacing.iter().map(|d| (d - s).abs() / s).fold(0.0, f64::max),
        spacing_rms: (spacing.iter().map(|d| (d - s).powi(2)).sum::<f64>() / spacing.len() as f64).sqrt(),
        corner_ray_gap_mean: gaps.iter().sum::<f64>() / gaps.len() as f64,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_fit_and_quad_test() {
        let pts: Vec<Vector3<f64>> =
            (0..20).map(|i| Vector3::new(i as f64, (i * 7 % 5) as f64, 2.0 * i as f64 + 3.0)).collect();
        // All on the plane z = 2x + 3 (y free).
        let (n, c) = fit_plane(&pts).expect("plane");
        for p in &pts {
            assert!((p - c).dot(&n).abs() < 1e-9);
        }
        let q = [Point2::new(0.0, 0.0), Point2::new(10.0, 0.0), Point2::new(10.0, 10.0), Point2::new(0.0, 10.0)];
        assert!(inside_quad(&q, &Point2::new(5.0, 5.0)));
        assert!(!inside_quad(&q, &Point2::new(11.0, 5.0)));
        let (m, gap) = ray_midpoint(
            &Vector3::zeros(),
            &Vector3::z(),
            &Vector3::new(1.0, 0.0, 0.0),
            &Vector3::new(-1.0, 0.0, 1.0).normalize(),
        )
        .expect("meet");
        assert!((m - Vector3::new(0.0, 0.0, 1.0)).norm() < 1e-12 && gap < 1e-12);
    }
}
