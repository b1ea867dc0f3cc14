//! Projector-camera calibration after Moreno & Taubin (2012), "Simple, accurate, and robust
//! projector-camera calibration".
//!
//! 1. The camera sees a chessboard lit by a Gray-code sequence; every camera pixel is decoded into
//!    the projector column and row that lit it ([`crate::pipeline::structured_light::decode`]).
//! 2. Around each chessboard corner found in the camera image, a **local homography** from camera
//!    pixels to projector pixels is fitted to the decoded pixels of a window (least squares, with
//!    outliers rejected and a minimum count of decoded pixels) and applied to the corner: the corner's
//!    projector coordinate, sub-pixel. The board is planar, so near the corner the camera-to-projector
//!    map is a homography even under lens distortion (which is smooth over a small window).
//! 3. The projector is then calibrated as an inverse camera: Zhang's method
//!    ([`super::calibrate_camera`]) on the projector corners of several board poses.
//! 4. Stereo extrinsics projector <- camera (`x_proj = R·x_cam + t`) are initialised from the
//!    per-pose board poses and refined jointly by Levenberg-Marquardt over `R`, `t` and every board
//!    pose, on the pixel re-projection errors in both devices, intrinsics held fixed.
//!
//! # Conventions
//! - Camera pixels: pixel `(x, y)` covers `[x, x+1) × [y, y+1)` (its centre is `(x + 0.5, y + 0.5)`),
//!   as everywhere in [`crate::geometry`]; projector pixels likewise: decoded column `c` and row `r`
//!   stand for the projector point `(c + 0.5, r + 0.5)`.
//! - Board frame and board poses as in [`crate::calibration`]; lengths are in the unit of the board's
//!   square size (metres for the rig; any unit works, translations come out in it).
//! - Both devices' lenses are [`crate::geometry::Intrinsics`], the project's one lens model: the
//!   five-term Brown-Conrady model (`k1 k2 p1 p2 k3`, OpenCV's order) that published
//!   projector-camera calibrations use.

use nalgebra::{DVector, Matrix3, Point2, Vector3};

use super::lm;
use super::zhang::{nearest_rotation, pose_from_params as pose_from, rotation_vector as rvec};
use super::{calibrate_camera, estimate_pose, homography, CalibrationError, CalibrationOptions, PlanarView};
use crate::geometry::{Intrinsics, Pose};
use crate::pipeline::structured_light::{ProjectorMap, INVALID};

/// Tunables of [`projector_corners`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalHomographyOptions {
    /// Half-size of the square camera window around each corner, pixels (the window is
    /// `2·half + 1` pixels wide).
    pub half_window_px: u32,
    /// Fewest decoded pixels a window needs (after outlier rejection) to place a corner.
    pub min_valid: usize,
    /// Decoded pixels farther than this from the fitted homography's prediction are dropped and the
    /// homography refitted, projector pixels (also at least 3 robust standard deviations).
    pub outlier_px: f64,
    /// Projector pixels per Gray-code pixel (the "graycode step": patterns rendered at
    /// `1/step` of the projector's resolution and shown enlarged). Decoded code `c` covers projector
    /// pixels `[step·c, step·(c+1))`, so it stands for the projector coordinate `step·(c + 0.5)`.
    pub graycode_step: u32,
}

impl Default for LocalHomographyOptions {
    fn default() -> Self {
        LocalHomographyOptions { half_window_px: 20, min_valid: 60, outlier_px: 1.5, graycode_step: 1 }
    }
}

/// One corner's projector coordinate from a local homography.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectorCorner {
    /// Projector pixel coordinate (top-left origin, pixel centres at `+0.5`).
    pub point: Point2<f64>,
    /// Decoded pixels the final homography was fitted on.
    pub inliers: usize,
    /// RMS distance of those pixels from the homography's prediction, projector pixels.
    pub rms_px: f64,
}

/// The projector coordinate of each camera corner (pixels, top-left origin, centres at `+0.5`) by a
/// local homography fitted on the decoded pixels of `map` around it; `None` where the window holds
/// fewer than [`LocalHomographyOptions::min_valid`] decoded pixels or they fix no homography.
pub fn projector_corners(
    map: &ProjectorMap,
    corners: &[Point2<f64>],
    opts: &LocalHomographyOptions,
) -> Vec<Option<ProjectorCorner>> {
    projector_corners_in(map.width(), map.height(), map.columns(), map.rows(), corners, opts)
}

/// [`projector_corners`] on raw row-major column and row maps of a `width x height` camera.
pub(crate) fn projector_corners_in(
    width: usize,
    height: usize,
    cols: &[u16],
    rows: &[u16],
    corners: &[Point2<f64>],
    opts: &LocalHomographyOptions,
) -> Vec<Option<ProjectorCorner>> {
    if cols.len() != width * height || rows.len() != width * height {
        return vec![None; corners.len()];
    }
    corners.iter().map(|c| projector_corner(width, height, cols, rows, c, opts)).collect()
}

fn projector_corner(
    width: usize,
    height: usize,
    cols: &[u16],
    rows: &[u16],
    corner: &Point2<f64>,
    opts: &LocalHomographyOptions,
) -> Option<ProjectorCorner> {
    if !(corner.x.is_finite() && corner.y.is_finite()) {
        return None;
    }
    let (w, h) = (width as i64, height as i64);
    let step = opts.graycode_step.max(1) as f64;
    let half = opts.half_window_px as i64;
    // The camera pixel containing the corner.
    let (px, py) = (corner.x.floor() as i64, corner.y.floor() as i64);
    let (x0, x1) = ((px - half).max(0), (px + half).min(w - 1));
    let (y0, y1) = ((py - half).max(0), (py + half).min(h - 1));
    if x0 > x1 || y0 > y1 {
        return None;
    }
    let mut src = Vec::new();
    let mut dst = Vec::new();
    for y in y0..=y1 {
        for x in x0..=x1 {
            let i = (y * w + x) as usize;
            let (c, r) = (cols[i], rows[i]);
            if c == INVALID || r == INVALID {
                continue;
            }
            // Camera coordinates relative to the corner keep the fit well conditioned.
            src.push(Point2::new(x as f64 + 0.5 - corner.x, y as f64 + 0.5 - corner.y));
            dst.push(Point2::new(step * (c as f64 + 0.5), step * (r as f64 + 0.5)));
        }
    }
    let need = opts.min_valid.max(4);
    let mut keep: Vec<bool> = vec![true; src.len()];
    for _ in 0..4 {
        let (s, d): (Vec<_>, Vec<_>) =
            src.iter().zip(&dst).zip(&keep).filter(|(_, &k)| k).map(|((a, b), _)| (*a, *b)).unzip();
        if s.len() < need {
            return None;
        }
        let hm = homography(&s, &d).ok()?;
        let err: Vec<f64> = src.iter().zip(&dst).map(|(a, b)| (apply(&hm, a) - b).norm()).collect();
        let mut kept: Vec<f64> = err.iter().zip(&keep).filter(|(_, &k)| k).map(|(e, _)| *e).collect();
        kept.sort_by(f64::total_cmp);
        let median = kept[kept.len() / 2];
        // 1.4826·median is the standard deviation of a Gaussian with that median absolute residual.
        let limit = opts.outlier_px.max(3.0 * 1.4826 * median);
        let new_keep: Vec<bool> = err.iter().map(|e| e.is_finite() && *e <= limit).collect();
        if new_keep == keep {
            let n = kept.len();
            let rms = (kept.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt();
            let point = apply(&hm, &Point2::origin());
            return (point.x.is_finite() && point.y.is_finite()).then_some(ProjectorCorner {
                point,
                inliers: n,
                rms_px: rms,
            });
        }
        keep = new_keep;
    }
    // Not settled after the rejection rounds: fit once more on the last inlier set.
    let (s, d): (Vec<_>, Vec<_>) =
        src.iter().zip(&dst).zip(&keep).filter(|(_, &k)| k).map(|((a, b), _)| (*a, *b)).unzip();
    if s.len() < need {
        return None;
    }
    let hm = homography(&s, &d).ok()?;
    let rms = (s.iter().zip(&d).map(|(a, b)| (apply(&hm, a) - b).norm_squared()).sum::<f64>() / s.len() as f64).sqrt();
    let point = apply(&hm, &Point2::origin());
    (point.x.is_finite() && point.y.is_finite()).then_some(ProjectorCorner { point, inliers: s.len(), rms_px: rms })
}

fn apply(h: &Matrix3<f64>, p: &Point2<f64>) -> Point2<f64> {
    let q = h * Vector3::new(p.x, p.y, 1.0);
    Point2::new(q.x / q.z, q.y / q.z)
}

/// One board pose seen by the camera and (through the decoded Gray code) by the projector.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ProcamView {
    /// Board points and their camera pixels (every detected corner).
    pub camera: PlanarView,
    /// Board points and their projector pixels (the corners whose local homography succeeded).
    pub projector: PlanarView,
}

impl ProcamView {
    /// Build a view from the board's object points, the detected camera corners (same order) and
    /// their projector corners from [`projector_corners`].
    pub fn new(object: &[Vector3<f64>], camera: &[Point2<f64>], projector: &[Option<ProjectorCorner>]) -> ProcamView {
        let cam = PlanarView { object: object.to_vec(), image: camera.to_vec() };
        let mut proj = PlanarView::default();
        for (o, p) in object.iter().zip(projector) {
            if let Some(p) = p {
                proj.object.push(*o);
                proj.image.push(p.point);
            }
        }
        ProcamView { camera: cam, projector: proj }
    }
}

/// What [`calibrate_procam`] estimates and what it holds fixed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcamOptions {
    /// Camera intrinsics to hold fixed; `None` calibrates them from the views (Zhang, at least 3).
    pub camera: Option<Intrinsics>,
    /// Projector intrinsics to hold fixed; `None` calibrates them from the views' projector corners.
    pub projector: Option<Intrinsics>,
    /// Options of the per-device Zhang calibrations.
    pub zhang: CalibrationOptions,
    /// Hold projector <- camera at this transform (only the board poses are refined), to measure
    /// how well a given calibration, e.g. a published one, explains the views.
    pub fixed_stereo: Option<Pose>,
    /// Levenberg-Marquardt iterations of the joint stereo refinement.
    pub max_iterations: usize,
}

impl Default for ProcamOptions {
    fn default() -> Self {
        ProcamOptions {
            camera: None,
            projector: None,
            zhang: CalibrationOptions::default(),
            fixed_stereo: None,
            max_iterations: 100,
        }
    }
}

/// A projector-camera calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct ProcamCalibration {
    /// Camera intrinsics, pixels.
    pub camera: Intrinsics,
    /// Projector intrinsics, projector pixels.
    pub projector: Intrinsics,
    /// Projector <- camera: `x_proj = rotation · x_cam + translation`.
    pub rotation: Matrix3<f64>,
    /// Translation projector <- camera, in the unit of the board's square size.
    pub translation: Vector3<f64>,
    /// Board -> camera pose of each view after the joint refinement.
    pub board_poses: Vec<Pose>,
    /// Camera re-projection RMS over every corner of every view, pixels.
    pub camera_rms_px: f64,
    /// Projector re-projection RMS over every projector corner, projector pixels.
    pub projector_rms_px: f64,
    /// Re-projection RMS over both devices' points together, pixels.
    pub rms_px: f64,
    /// Corners used: camera, projector.
    pub points: (usize, usize),
}

fn compose(a: &Pose, b: &Pose) -> Pose {
    // a ∘ b: first b, then a.
    Pose { rotation: a.rotation * b.rotation, translation: a.rotation * b.translation + a.translation }
}

fn inverse(p: &Pose) -> Pose {
    let rt = p.rotation.transpose();
    Pose { rotation: rt, translation: -(rt * p.translation) }
}

/// Angle of the rotation `a·bᵀ` (how far apart two rotations are), degrees.
pub fn rotation_difference_deg(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    let c = ((a * b.transpose()).trace() - 1.0) / 2.0;
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// Residuals (projected - observed, pixels) of `view` through `lens` at `pose`, appended to `out`.
fn push_residuals(lens: &Intrinsics, pose: &Pose, view: &PlanarView, out: &mut Vec<f64>) {
    for (p, q) in view.object.iter().zip(&view.image) {
        let c = pose.apply(p);
        if c.z > 1e-12 {
            let r = lens.normalised_to_pixel(c.x / c.z, c.y / c.z);
            out.push(r.x - q.x);
            out.push(r.y - q.y);
        } else {
            out.push(1e6);
            out.push(1e6);
        }
    }
}

fn rms(res: &[f64]) -> f64 {
    if res.is_empty() {
        return 0.0;
    }
    (res.iter().map(|r| r * r).sum::<f64>() / (res.len() / 2) as f64).sqrt()
}

/// The board -> device pose of one view through a lens with five-term distortion: the observed
/// pixels are undistorted to ideal pixels, posed by [`estimate_pose`] with the distortion-free
/// intrinsics, then refined on the distorted re-projection error.
pub fn estimate_pose_lens(lens: &Intrinsics, view: &PlanarView) -> Result<Pose, CalibrationError> {
    let k = lens.pinhole();
    let ideal: Vec<Point2<f64>> = view
        .image
        .iter()
        .map(|q| {
            let (x, y) = lens.pixel_to_normalised(q.x, q.y);
            k.normalised_to_pixel(x, y)
        })
        .collect();
    let init = estimate_pose(&k, &PlanarView { object: view.object.clone(), image: ideal })?.pose;
    let r = rvec(&init.rotation);
    let t = init.translation;
    let ts = 1e-7 * t.norm().max(1e-3);
    let res = lm::minimise(
        DVector::from_vec(vec![r.x, r.y, r.z, t.x, t.y, t.z]),
        &[1e-7, 1e-7, 1e-7, ts, ts, ts],
        50,
        |p, out| {
            let mut v = Vec::with_capacity(2 * view.object.len());
            push_residuals(lens, &pose_from(p.as_slice()), view, &mut v);
            *out = DVector::from_vec(v);
        },
    );
    let pose = pose_from(res.params.as_slice());
    if !pose.rotation.iter().chain(pose.translation.iter()).all(|x| x.is_finite()) {
        return Err(CalibrationError::Degenerate { reason: "the pose refinement diverged" });
    }
    Ok(pose)
}

/// Calibrate a projector-camera pair from board views: each device's intrinsics (fixed when given in
/// `opts`, else Zhang's method on that device's corners), then the projector <- camera rotation and
/// translation, initialised from the per-view board poses (rotation: the rotation nearest to the sum
/// of the per-view estimates; translation: their mean) and refined jointly with every board pose by
/// Levenberg-Marquardt on both devices' pixel re-projection errors, intrinsics fixed.
///
/// One view suffices when both lenses are given; a device to be calibrated needs at least 3 views
/// (or 1 with [`CalibrationOptions::fixed_principal_point`]). Errors name the view at fault.
pub fn calibrate_procam(views: &[ProcamView], opts: &ProcamOptions) -> Result<ProcamCalibration, CalibrationError> {
    if views.is_empty() {
        return Err(CalibrationError::TooFewViews { got: 0, need: 1 });
    }
    for (i, v) in views.iter().enumerate() {
        if v.projector.object.len() < 4 {
            return Err(CalibrationError::TooFewPoints { view: i, got: v.projector.object.len(), need: 4 });
        }
    }
    let cam_views: Vec<PlanarView> = views.iter().map(|v| v.camera.clone()).collect();
    let proj_views: Vec<PlanarView> = views.iter().map(|v| v.projector.clone()).collect();
    let device = |given: Option<Intrinsics>, vs: &[PlanarView]| -> Result<(Intrinsics, Vec<Pose>), CalibrationError> {
        match given {
            Some(lens) => {
                if !lens.is_valid() {
                    return Err(CalibrationError::Degenerate { reason: "the given intrinsics are not finite" });
                }
                let poses = vs
                    .iter()
                    .enumerate()
                    .map(|(i, v)| estimate_pose_lens(&lens, v).map_err(|e| in_view(e, i)))
                    .collect::<Result<Vec<_>, _>>()?;
                Ok((lens, poses))
            }
            None => {
                let cal = calibrate_camera(vs, &opts.zhang)?;
                Ok((cal.intrinsics, cal.poses))
            }
        }
    };
    let (cam, cam_poses) = device(opts.camera, &cam_views)?;
    let (proj, proj_poses) = device(opts.projector, &proj_views)?;

    // Initial stereo transform: projector <- camera = (board -> projector) ∘ (board -> camera)⁻¹.
    let mut rsum = Matrix3::zeros();
    let mut tsum = Vector3::zeros();
    for (c, p) in cam_poses.iter().zip(&proj_poses) {
        let s = compose(p, &inverse(c));
        rsum += s.rotation;
        tsum += s.translation;
    }
    let (r0, t0) = match opts.fixed_stereo {
        Some(s) => (s.rotation, s.translation),
        None => (nearest_rotation(&rsum), tsum / views.len() as f64),
    };

    // Parameters: stereo rvec, t; then each view's board -> camera rvec, t.
    let scale = t0.norm().max(cam_poses.iter().map(|p| p.translation.norm()).fold(0.0, f64::max)).max(1e-6);
    let r = rvec(&r0);
    let mut p0 = vec![r.x, r.y, r.z, t0.x, t0.y, t0.z];
    for c in &cam_poses {
        let r = rvec(&c.rotation);
        p0.extend_from_slice(&[r.x, r.y, r.z, c.translation.x, c.translation.y, c.translation.z]);
    }
    let ts = 1e-7 * scale;
    let fixed = opts.fixed_stereo.is_some();
    let steps: Vec<f64> = (0..p0.len())
        .map(|k| match (k < 6 && fixed, k % 6 < 3) {
            (true, _) => 0.0,
            (false, true) => 1e-7,
            (false, false) => ts,
        })
        .collect();
    let residuals = |p: &DVector<f64>, out: &mut Vec<f64>| -> (usize, usize) {
        out.clear();
        let stereo = pose_from(&p.as_slice()[0..6]);
        for (i, v) in views.iter().enumerate() {
            let bc = pose_from(&p.as_slice()[6 + 6 * i..12 + 6 * i]);
            push_residuals(&cam, &bc, &v.camera, out);
        }
        let ncam = out.len();
        for (i, v) in views.iter().enumerate() {
            let bc = pose_from(&p.as_slice()[6 + 6 * i..12 + 6 * i]);
            push_residuals(&proj, &compose(&stereo, &bc), &v.projector, out);
        }
        (ncam, out.len() - ncam)
    };
    let mut buf = Vec::new();
    let res = lm::minimise(DVector::from_vec(p0), &steps, opts.max_iterations, |p, out| {
        residuals(p, &mut buf);
        if out.len() != buf.len() {
            *out = DVector::zeros(buf.len());
        }
        out.as_mut_slice().copy_from_slice(&buf);
    });
    if !res.params.iter().all(|x| x.is_finite()) {
        return Err(CalibrationError::Degenerate { reason: "the stereo refinement diverged" });
    }
    let mut all = Vec::new();
    let (ncam, nproj) = residuals(&res.params, &mut all);
    let stereo = pose_from(&res.params.as_slice()[0..6]);
    let board_poses = (0..views.len()).map(|i| pose_from(&res.params.as_slice()[6 + 6 * i..12 + 6 * i])).collect();
    Ok(ProcamCalibration {
        camera: cam,
        projector: proj,
        rotation: stereo.rotation,
        translation: stereo.translation,
        board_poses,
        camera_rms_px: rms(&all[..ncam]),
        projector_rms_px: rms(&all[ncam..]),
        rms_px: rms(&all),
        points: (ncam / 2, nproj / 2),
    })
}

/// Why a captured Gray-code sequence gave no usable view.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProcamViewError {
    /// The images do not fit the pattern sequence.
    #[error("decoding the Gray code")]
    Decode(#[from] crate::pipeline::structured_light::DecodeError),
    /// The chessboard was not found in the all-white image.
    #[error("no usable chessboard in the all-white image (sequence image {white_index})")]
    Detect {
        /// Index of the all-white image in the sequence.
        white_index: usize,
        /// The detector's reason.
        #[source]
        source: super::DetectError,
    },
    /// Too few corners got a projector coordinate (too little of the board decoded).
    #[error("only {got} of {total} corners got a projector coordinate (need at least {need}); the projector must light the board")]
    TooFewProjectorCorners {
        /// Corners with a projector coordinate.
        got: usize,
        /// Corners detected.
        total: usize,
        /// Needed.
        need: usize,
    },
}

/// Figures of one decoded view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcamViewStats {
    /// Fraction of camera pixels with a decoded projector column and row.
    pub valid_fraction: f64,
    /// Chessboard corners detected in the camera image.
    pub camera_corners: usize,
    /// Corners whose local homography succeeded.
    pub projector_corners: usize,
    /// Mean decoded pixels per local homography.
    pub mean_inliers: f64,
    /// Mean RMS of the local homography fits, projector pixels.
    pub mean_fit_rms_px: f64,
}

/// Settings for turning a captured sequence into a [`ProcamView`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ProcamViewOptions {
    /// Gray-code decoder thresholds.
    pub decode: crate::pipeline::structured_light::DecodeParams,
    /// Chessboard detector tunables.
    pub detect: super::DetectOptions,
    /// Local homography tunables.
    pub local: LocalHomographyOptions,
}

/// Decode one captured sequence (`frames`: the images of `patterns` in order, each `width x height`
/// 8-bit grey, row-major), find the board in its all-white image and give each corner its projector
/// coordinate by a local homography. Needs at least 4 projector corners.
pub fn procam_view_from_frames(
    frames: &[&[u8]],
    width: usize,
    height: usize,
    patterns: &crate::pipeline::structured_light::GrayCodePatterns,
    board: &super::BoardSpec,
    opts: &ProcamViewOptions,
) -> Result<(ProcamView, ProcamViewStats), ProcamViewError> {
    let mut map = ProjectorMap::new();
    crate::pipeline::structured_light::decode(patterns, frames, width, height, &opts.decode, &mut map)?;
    let white_index = patterns.white_index();
    let white = image::GrayImage::from_raw(width as u32, height as u32, frames[white_index].to_vec()).ok_or(
        ProcamViewError::Decode(crate::pipeline::structured_light::DecodeError::ImageSize {
            index: white_index,
            width,
            height,
            found: frames[white_index].len(),
        }),
    )?;
    let det = super::detect_chessboard(&white, board, &opts.detect)
        .map_err(|source| ProcamViewError::Detect { white_index, source })?;
    let pc = projector_corners(&map, &det.corners, &opts.local);
    let found: Vec<&ProjectorCorner> = pc.iter().flatten().collect();
    if found.len() < 4 {
        return Err(ProcamViewError::TooFewProjectorCorners { got: found.len(), total: pc.len(), need: 4 });
    }
    let n = found.len() as f64;
    let stats = ProcamViewStats {
        valid_fraction: map.valid_fraction(),
        camera_corners: det.corners.len(),
        projector_corners: found.len(),
        mean_inliers: found.iter().map(|c| c.inliers as f64).sum::<f64>() / n,
        mean_fit_rms_px: found.iter().map(|c| c.rms_px).sum::<f64>() / n,
    };
    Ok((ProcamView::new(&board.object_points(), &det.corners, &pc), stats))
}

/// The error `e` of a single-view computation, renumbered to name view `i` of the input.
fn in_view(e: CalibrationError, i: usize) -> CalibrationError {
    use CalibrationError as E;
    match e {
        E::TooFewPoints { got, need, .. } => E::TooFewPoints { view: i, got, need },
        E::MismatchedPoints { object, image, .. } => E::MismatchedPoints { view: i, object, image },
        E::NotPlanar { index, z, .. } => E::NotPlanar { view: i, index, z },
        E::NonFinite { index, .. } => E::NonFinite { view: i, index },
        E::Collinear { .. } => E::Collinear { view: i },
        other => other,
    }
}
