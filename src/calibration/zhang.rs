//! Plane-based camera calibration after Zhang (2000), "A flexible new technique for camera
//! calibration": a homography per view (normalised DLT), closed-form intrinsics from the
//! homographies (zero skew), board poses from the homographies, then Levenberg-Marquardt refinement
//! of `fx, fy, cx, cy, k1, k2` and every pose on the pixel re-projection error.
//!
//! Frames and units are those of the module [`crate::calibration`]: board points in metres on the
//! board plane `z = 0`, image points in pixels, poses board -> camera.

use nalgebra::{DVector, Matrix3, Point2, Rotation3, SymmetricEigen, Vector3, SVD};

use super::lm;
use super::{reprojection_rms_px, CalibrationError};
use crate::geometry::{Intrinsics, Pose};

/// Point pairs needed for a homography.
const MIN_POINTS: usize = 4;
/// A board tilted less than this (degrees) from the image plane in every view leaves the focal
/// length undetermined.
const MIN_MAX_TILT_DEG: f64 = 3.0;
/// LM iterations for a full calibration.
const DEFAULT_ITERATIONS: usize = 100;

/// The observations of one board view: board-frame points (metres, `z = 0`) and the pixels they
/// were seen at, in the same order.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PlanarView {
    /// Board-frame points, metres, all with `z = 0`.
    pub object: Vec<Vector3<f64>>,
    /// Their observed image positions, pixels (top-left origin).
    pub image: Vec<Point2<f64>>,
}

/// What [`calibrate_camera`] estimates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CalibrationOptions {
    /// Hold the principal point at this pixel position `(cx, cy)` instead of estimating it (needed
    /// when there are only one or two views).
    pub fixed_principal_point: Option<(f64, f64)>,
    /// Estimate the radial distortion `k1`, `k2`; when false every distortion term is held at 0.
    pub estimate_distortion: bool,
    /// With [`CalibrationOptions::estimate_distortion`], also estimate `p1`, `p2`, `k3` (OpenCV's
    /// five-term fit); when false they are held at 0.
    pub full_distortion: bool,
    /// Levenberg-Marquardt iteration limit.
    pub max_iterations: usize,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        CalibrationOptions {
            fixed_principal_point: None,
            estimate_distortion: true,
            full_distortion: false,
            max_iterations: DEFAULT_ITERATIONS,
        }
    }
}

/// A camera calibration from several board views.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraCalibrationResult {
    /// Intrinsics, pixels; skew 0; distortion as estimated (see [`CalibrationOptions`]).
    pub intrinsics: Intrinsics,
    /// Board -> camera pose of each view, metres, in input order.
    pub poses: Vec<Pose>,
    /// Re-projection RMS of each view, pixels.
    pub per_view_rms_px: Vec<f64>,
    /// Re-projection RMS over every point of every view, pixels.
    pub rms_px: f64,
}

/// A board pose from one view with known intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseEstimate {
    /// Board -> camera, metres.
    pub pose: Pose,
    /// Re-projection RMS, pixels.
    pub rms_px: f64,
}

/// Check a view's point lists: equal lengths, enough points, finite, on the plane `z = 0`, not
/// collinear.
fn check_view(view: usize, v: &PlanarView) -> Result<(), CalibrationError> {
    if v.object.len() != v.image.len() {
        return Err(CalibrationError::MismatchedPoints { view, object: v.object.len(), image: v.image.len() });
    }
    if v.object.len() < MIN_POINTS {
        return Err(CalibrationError::TooFewPoints { view, got: v.object.len(), need: MIN_POINTS });
    }
    for (index, (p, q)) in v.object.iter().zip(&v.image).enumerate() {
        if !(p.iter().all(|x| x.is_finite()) && q.x.is_finite() && q.y.is_finite()) {
            return Err(CalibrationError::NonFinite { view, index });
        }
        if p.z.abs() > 1e-9 {
            return Err(CalibrationError::NotPlanar { view, index, z: p.z });
        }
    }
    let obj: Vec<Point2<f64>> = v.object.iter().map(|p| Point2::new(p.x, p.y)).collect();
    if is_collinear(&obj) || is_collinear(&v.image) {
        return Err(CalibrationError::Collinear { view });
    }
    Ok(())
}

/// True when the points' spread across their best-fit line is below 1e-6 of their spread along it.
fn is_collinear(pts: &[Point2<f64>]) -> bool {
    let n = pts.len() as f64;
    let (mx, my) = pts.iter().fold((0.0, 0.0), |(a, b), p| (a + p.x / n, b + p.y / n));
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (dx, dy) = (p.x - mx, p.y - my);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    let tr = sxx + syy;
    let det = sxx * syy - sxy * sxy;
    let disc = (tr * tr / 4.0 - det).max(0.0).sqrt();
    let (big, small) = (tr / 2.0 + disc, tr / 2.0 - disc);
    big.is_nan() || big <= 0.0 || small <= 1e-12 * big
}

/// The similarity that moves the points' centroid to the origin and their mean distance from it
/// to √2 (Hartley normalisation).
fn normalising_transform(pts: &[Point2<f64>]) -> Matrix3<f64> {
    let n = pts.len() as f64;
    let (mx, my) = pts.iter().fold((0.0, 0.0), |(a, b), p| (a + p.x / n, b + p.y / n));
    let mean_d = pts.iter().map(|p| ((p.x - mx).powi(2) + (p.y - my).powi(2)).sqrt()).sum::<f64>() / n;
    let s = if mean_d > 0.0 { std::f64::consts::SQRT_2 / mean_d } else { 1.0 };
    Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0)
}

fn apply_h(h: &Matrix3<f64>, p: &Point2<f64>) -> Point2<f64> {
    let q = h * Vector3::new(p.x, p.y, 1.0);
    Point2::new(q.x / q.z, q.y / q.z)
}

/// The homography `H` with `dst ~ H·src` (homogeneous pixels or metres), by the normalised direct
/// linear transform; at least 4 point pairs, not collinear. `H[(2,2)] = 1` when it is not 0.
pub fn homography(src: &[Point2<f64>], dst: &[Point2<f64>]) -> Result<Matrix3<f64>, CalibrationError> {
    homography_of_view(0, src, dst)
}

fn homography_of_view(view: usize, src: &[Point2<f64>], dst: &[Point2<f64>]) -> Result<Matrix3<f64>, CalibrationError> {
    if src.len() != dst.len() {
        return Err(CalibrationError::MismatchedPoints { view, object: src.len(), image: dst.len() });
    }
    if src.len() < MIN_POINTS {
        return Err(CalibrationError::TooFewPoints { view, got: src.len(), need: MIN_POINTS });
    }
    if src.iter().chain(dst).any(|p| !(p.x.is_finite() && p.y.is_finite())) {
        let index = src.iter().zip(dst).position(|(a, b)| !(a.x + a.y + b.x + b.y).is_finite()).unwrap_or(0);
        return Err(CalibrationError::NonFinite { view, index });
    }
    if is_collinear(src) || is_collinear(dst) {
        return Err(CalibrationError::Collinear { view });
    }
    let (ts, td) = (normalising_transform(src), normalising_transform(dst));
    let mut ata = nalgebra::SMatrix::<f64, 9, 9>::zeros();
    for (a, b) in src.iter().zip(dst) {
        let (p, q) = (apply_h(&ts, a), apply_h(&td, b));
        let r1 = nalgebra::SVector::<f64, 9>::from([-p.x, -p.y, -1.0, 0.0, 0.0, 0.0, q.x * p.x, q.x * p.y, q.x]);
        let r2 = nalgebra::SVector::<f64, 9>::from([0.0, 0.0, 0.0, -p.x, -p.y, -1.0, q.y * p.x, q.y * p.y, q.y]);
        ata += r1 * r1.transpose() + r2 * r2.transpose();
    }
    let eig = SymmetricEigen::new(ata);
    let k = eig.eigenvalues.imin();
    let h = eig.eigenvectors.column(k);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let td_inv = td.try_inverse().ok_or(CalibrationError::Collinear { view })?;
    let hm = td_inv * hn * ts;
    let s = hm[(2, 2)];
    Ok(if s.abs() > 1e-300 { hm / s } else { hm / hm.norm() })
}

/// The rotation nearest to `m` (Frobenius norm).
pub(super) fn nearest_rotation(m: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = SVD::new(*m, true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else { return Matrix3::identity() };
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        u2.column_mut(2).neg_mut();
        r = u2 * vt;
    }
    r
}

/// Board -> camera pose from a homography board-plane (metres) -> image (pixels) and `K`.
fn pose_from_homography(h: &Matrix3<f64>, k_inv: &Matrix3<f64>) -> Pose {
    let m = k_inv * h;
    let (h1, h2, h3) = (m.column(0).into_owned(), m.column(1).into_owned(), m.column(2).into_owned());
    let mut lambda = 2.0 / (h1.norm() + h2.norm());
    if h3.z * lambda < 0.0 {
        // The board must be in front of the camera.
        lambda = -lambda;
    }
    let (r1, r2) = (h1 * lambda, h2 * lambda);
    let r3 = r1.cross(&r2);
    let r = nearest_rotation(&Matrix3::from_columns(&[r1, r2, r3]));
    Pose { rotation: r, translation: h3 * lambda }
}

/// Closed-form intrinsics (zero skew, no distortion) from homographies board -> normalised image
/// coordinates `n = N·pixel`. Returns `K` in those normalised coordinates.
fn closed_form_k(hs: &[Matrix3<f64>], fixed_pp: Option<Point2<f64>>) -> Result<Matrix3<f64>, CalibrationError> {
    let degenerate = CalibrationError::Degenerate {
        reason: "the views do not determine the focal lengths (boards parallel to each other or to the image \
                 plane); tilt the board differently in each view",
    };
    if let Some(pp) = fixed_pp {
        // With the principal point at the origin B = diag(B11, B22, B33).
        let shift = Matrix3::new(1.0, 0.0, -pp.x, 0.0, 1.0, -pp.y, 0.0, 0.0, 1.0);
        let mut vtv = Matrix3::zeros();
        for h in hs {
            let h = shift * h;
            let a = Vector3::new(h[(0, 0)] * h[(0, 1)], h[(1, 0)] * h[(1, 1)], h[(2, 0)] * h[(2, 1)]);
            let b = Vector3::new(
                h[(0, 0)].powi(2) - h[(0, 1)].powi(2),
                h[(1, 0)].powi(2) - h[(1, 1)].powi(2),
                h[(2, 0)].powi(2) - h[(2, 1)].powi(2),
            );
            let (a, b) = (a / a.norm().max(1e-300), b / b.norm().max(1e-300));
            vtv += a * a.transpose() + b * b.transpose();
        }
        let eig = SymmetricEigen::new(vtv);
        let mut ev: Vec<(f64, usize)> = eig.eigenvalues.iter().copied().zip(0..3).collect();
        ev.sort_by(|x, y| x.0.total_cmp(&y.0));
        if ev[1].0 <= 1e-9 * ev[2].0 {
            return Err(degenerate);
        }
        let b = eig.eigenvectors.column(ev[0].1);
        let (b11, b22, b33) = (b[0], b[1], b[2]);
        let (fx2, fy2) = (b33 / b11, b33 / b22);
        if !(fx2 > 0.0 && fy2 > 0.0 && fx2.is_finite() && fy2.is_finite()) {
            return Err(degenerate);
        }
        return Ok(Matrix3::new(fx2.sqrt(), 0.0, pp.x, 0.0, fy2.sqrt(), pp.y, 0.0, 0.0, 1.0));
    }
    let v = |h: &Matrix3<f64>, i: usize, j: usize| {
        nalgebra::SVector::<f64, 6>::from([
            h[(0, i)] * h[(0, j)],
            h[(0, i)] * h[(1, j)] + h[(1, i)] * h[(0, j)],
            h[(1, i)] * h[(1, j)],
            h[(2, i)] * h[(0, j)] + h[(0, i)] * h[(2, j)],
            h[(2, i)] * h[(1, j)] + h[(1, i)] * h[(2, j)],
            h[(2, i)] * h[(2, j)],
        ])
    };
    let mut vtv = nalgebra::SMatrix::<f64, 6, 6>::zeros();
    for h in hs {
        let a = v(h, 0, 1);
        let b = v(h, 0, 0) - v(h, 1, 1);
        let (a, b) = (a / a.norm().max(1e-300), b / b.norm().max(1e-300));
        vtv += a * a.transpose() + b * b.transpose();
    }
    // Zero skew: B12 = 0.
    vtv[(1, 1)] += 1.0;
    let eig = SymmetricEigen::new(vtv);
    let mut ev: Vec<(f64, usize)> = eig.eigenvalues.iter().copied().zip(0..6).collect();
    ev.sort_by(|x, y| x.0.total_cmp(&y.0));
    if ev[1].0 <= 1e-9 * ev[5].0 {
        return Err(degenerate);
    }
    let mut b = eig.eigenvectors.column(ev[0].1).into_owned();
    if b[0] < 0.0 {
        b = -b;
    }
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    if den.is_nan() || den <= 0.0 {
        return Err(degenerate);
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha2 = lambda / b11;
    let beta2 = lambda * b11 / den;
    if !(alpha2 > 0.0 && beta2 > 0.0 && alpha2.is_finite() && beta2.is_finite()) {
        return Err(degenerate);
    }
    let u0 = -b13 * alpha2 / lambda;
    Ok(Matrix3::new(alpha2.sqrt(), 0.0, u0, 0.0, beta2.sqrt(), v0, 0.0, 0.0, 1.0))
}

/// Rotation vector (axis times angle, radians) of a rotation matrix.
pub(super) fn rotation_vector(r: &Matrix3<f64>) -> Vector3<f64> {
    Rotation3::from_matrix_unchecked(*r).scaled_axis()
}

pub(super) fn pose_from_params(p: &[f64]) -> Pose {
    let rotation = Rotation3::from_scaled_axis(Vector3::new(p[0], p[1], p[2])).into_inner();
    Pose { rotation, translation: Vector3::new(p[3], p[4], p[5]) }
}

/// Residuals (projected - observed, pixels) of one view, written into `out[0..2n]`.
fn view_residuals(intr: &Intrinsics, pose: &Pose, view: &PlanarView, out: &mut [f64]) {
    for (k, (p, q)) in view.object.iter().zip(&view.image).enumerate() {
        let c = pose.apply(p);
        let (rx, ry) = if c.z > 1e-12 {
            let r = intr.normalised_to_pixel(c.x / c.z, c.y / c.z);
            (r.x - q.x, r.y - q.y)
        } else {
            // Behind the camera: a large residual steers the solver away.
            (1e6, 1e6)
        };
        out[2 * k] = rx;
        out[2 * k + 1] = ry;
    }
}

/// Intrinsic parameters of the refinement: fx fy cx cy k1 k2 p1 p2 k3.
const NI: usize = 9;

/// Calibrate a camera from views of a planar board: Zhang's closed form, then Levenberg-Marquardt
/// over `fx, fy, cx, cy` (unless [`CalibrationOptions::fixed_principal_point`]), `k1, k2` (if
/// [`CalibrationOptions::estimate_distortion`]), `p1, p2, k3` (if also
/// [`CalibrationOptions::full_distortion`]) and each view's pose. Needs at least 3 views with a
/// free principal point, 1 with a fixed one; the boards must be tilted (not all parallel to the
/// image plane or to each other).
pub fn calibrate_camera(
    views: &[PlanarView],
    options: &CalibrationOptions,
) -> Result<CameraCalibrationResult, CalibrationError> {
    let need = if options.fixed_principal_point.is_some() { 1 } else { 3 };
    if views.len() < need {
        return Err(CalibrationError::TooFewViews { got: views.len(), need });
    }
    for (i, v) in views.iter().enumerate() {
        check_view(i, v)?;
    }
    // Condition the closed form: image coordinates centred on the points and scaled to about ±1.
    let all: Vec<Point2<f64>> = views.iter().flat_map(|v| v.image.iter().copied()).collect();
    let (mut lo, mut hi) = (all[0], all[0]);
    for p in &all {
        lo = Point2::new(lo.x.min(p.x), lo.y.min(p.y));
        hi = Point2::new(hi.x.max(p.x), hi.y.max(p.y));
    }
    let s = 2.0 / (hi.x - lo.x).max(hi.y - lo.y).max(1e-9);
    let (ox, oy) = (0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y));
    let nmat = Matrix3::new(s, 0.0, -s * ox, 0.0, s, -s * oy, 0.0, 0.0, 1.0);
    let mut hs = Vec::with_capacity(views.len());
    for (i, v) in views.iter().enumerate() {
        let obj: Vec<Point2<f64>> = v.object.iter().map(|p| Point2::new(p.x, p.y)).collect();
        let img: Vec<Point2<f64>> = v.image.iter().map(|q| apply_h(&nmat, q)).collect();
        hs.push(homography_of_view(i, &obj, &img)?);
    }
    let fixed_pp_n = options.fixed_principal_point.map(|(cx, cy)| apply_h(&nmat, &Point2::new(cx, cy)));
    let kn = closed_form_k(&hs, fixed_pp_n)?;
    let n_inv = nmat.try_inverse().ok_or(CalibrationError::Degenerate { reason: "the image points coincide" })?;
    let k = n_inv * kn;
    let k_inv = k.try_inverse().ok_or(CalibrationError::Degenerate { reason: "singular camera matrix" })?;
    let mut init = Intrinsics::from_matrix(&k);
    init.skew = 0.0;
    if let Some((cx, cy)) = options.fixed_principal_point {
        init.cx = cx;
        init.cy = cy;
    }
    let poses: Vec<Pose> = hs.iter().map(|hn| pose_from_homography(&(n_inv * hn), &k_inv)).collect();

    // Parameters: fx fy cx cy k1 k2 p1 p2 k3, then per view rotation vector (3) and translation
    // (3, metres).
    let mut p0 = vec![init.fx, init.fy, init.cx, init.cy, 0.0, 0.0, 0.0, 0.0, 0.0];
    for pose in &poses {
        let r = rotation_vector(&pose.rotation);
        p0.extend_from_slice(&[r.x, r.y, r.z, pose.translation.x, pose.translation.y, pose.translation.z]);
    }
    let pp_step = if options.fixed_principal_point.is_some() { 0.0 } else { 1e-4 };
    let k_step = if options.estimate_distortion { 1e-7 } else { 0.0 };
    let full_step = if options.full_distortion { k_step } else { 0.0 };
    let mut steps = vec![1e-4, 1e-4, pp_step, pp_step, k_step, k_step, full_step, full_step, full_step];
    for pose in &poses {
        let t = pose.translation.norm().max(1e-3);
        steps.extend_from_slice(&[1e-7, 1e-7, 1e-7, 1e-7 * t, 1e-7 * t, 1e-7 * t]);
    }
    let offsets: Vec<usize> = views
        .iter()
        .scan(0usize, |acc, v| {
            let o = *acc;
            *acc += 2 * v.object.len();
            Some(o)
        })
        .collect();
    let m = 2 * all.len();
    let unpack =
        |p: &DVector<f64>| Intrinsics::new(p[0], p[1], p[2], p[3]).with_distortion([p[4], p[5], p[6], p[7], p[8]]);
    let res = lm::minimise(DVector::from_vec(p0), &steps, options.max_iterations, |p, r| {
        if r.len() != m {
            *r = DVector::zeros(m);
        }
        let intr = unpack(p);
        for (i, v) in views.iter().enumerate() {
            let pose = pose_from_params(&p.as_slice()[NI + 6 * i..NI + 6 + 6 * i]);
            let o = offsets[i];
            view_residuals(&intr, &pose, v, &mut r.as_mut_slice()[o..o + 2 * v.object.len()]);
        }
    });
    let intrinsics = unpack(&res.params);
    if !intrinsics.is_valid() {
        return Err(CalibrationError::Degenerate { reason: "the refinement diverged" });
    }
    let poses: Vec<Pose> =
        (0..views.len()).map(|i| pose_from_params(&res.params.as_slice()[NI + 6 * i..NI + 6 + 6 * i])).collect();
    let max_tilt =
        poses.iter().map(|p| p.rotation.column(2).z.abs().clamp(0.0, 1.0).acos().to_degrees()).fold(0.0, f64::max);
    if max_tilt < MIN_MAX_TILT_DEG {
        return Err(CalibrationError::Degenerate {
            reason: "every board is (nearly) parallel to the image plane, which leaves the focal length \
                     undetermined; tilt the board in some views",
        });
    }
    let per_view_rms_px: Vec<f64> =
        views.iter().zip(&poses).map(|(v, p)| reprojection_rms_px(&intrinsics, p, &v.object, &v.image)).collect();
    let rms_px = (res.cost / all.len() as f64).sqrt();
    Ok(CameraCalibrationResult { intrinsics, poses, per_view_rms_px, rms_px })
}

/// The board -> camera pose of one view with known intrinsics (planar PnP): a homography from the
/// board plane to undistorted normalised coordinates, decomposed, then refined by
/// Levenberg-Marquardt on the pixel re-projection error. At least 4 non-collinear points on `z = 0`.
pub fn estimate_pose(intrinsics: &Intrinsics, view: &PlanarView) -> Result<PoseEstimate, CalibrationError> {
    check_view(0, view)?;
    let obj: Vec<Point2<f64>> = view.object.iter().map(|p| Point2::new(p.x, p.y)).collect();
    let norm: Vec<Point2<f64>> = view
        .image
        .iter()
        .map(|q| {
            let (x, y) = intrinsics.pixel_to_normalised(q.x, q.y);
            Point2::new(x, y)
        })
        .collect();
    let h = homography_of_view(0, &obj, &norm)?;
    let pose0 = pose_from_homography(&h, &Matrix3::identity());
    let r = rotation_vector(&pose0.rotation);
    let t = pose0.translation;
    let p0 = DVector::from_vec(vec![r.x, r.y, r.z, t.x, t.y, t.z]);
    let ts = 1e-7 * t.norm().max(1e-3);
    let m = 2 * view.object.len();
    let res = lm::minimise(p0, &[1e-7, 1e-7, 1e-7, ts, ts, ts], 50, |p, out| {
        if out.len() != m {
            *out = DVector::zeros(m);
        }
        view_residuals(intrinsics, &pose_from_params(p.as_slice()), view, out.as_mut_slice());
    });
    let pose = pose_from_params(res.params.as_slice());
    if !(pose.rotation.iter().chain(pose.translation.iter()).all(|x| x.is_finite())) {
        return Err(CalibrationError::Degenerate { reason: "the pose refinement diverged" });
    }
    Ok(PoseEstimate { pose, rms_px: reprojection_rms_px(intrinsics, &pose, &view.object, &view.image) })
}
