//! Turntable axis calibration: a board lying (or standing) on the turntable, seen by a camera of
//! known intrinsics at several table angles, gives one board pose per angle ([`estimate_pose`]).
//! Every pair of poses differs by a rotation about the table's axis; the axis direction is the
//! weighted mean of those rotation axes, and a point on it is the least-squares fixed point of the
//! relative motions (`(I - Q)·p = s` for each motion `x -> Q·x + s`), pinned along the axis to the
//! plane of the board origin. That gives the rig frame in camera coordinates:
//!
//! - origin: on the axis at the table top (the board origin's height above the table,
//!   [`TurntableOptions::board_origin_height_m`], is subtracted along the axis);
//! - `+z`: the axis, pointing so that increasing table angles turn counter-clockwise seen from above
//!   (the convention of [`crate::geometry`]);
//! - `+y`: horizontal, from the camera towards the axis (so the camera lies in the rig's `x = 0`
//!   plane at negative `y`, as in the shipped rigs); `+x = y × z`.
//!
//! All lengths are metres, angles degrees; "camera frame" is the OpenCV convention of
//! [`crate::geometry`].

use nalgebra::{Matrix3, Rotation3, Vector3};

use super::zhang::{estimate_pose, PlanarView};
use super::CalibrationError;
use crate::geometry::{Intrinsics, Pose};

/// One capture: the commanded table angle and the board seen there.
#[derive(Debug, Clone, PartialEq)]
pub struct TurntableView {
    /// Turntable angle, degrees (counter-clockwise seen from above).
    pub angle_deg: f64,
    /// Board corners (board frame, metres) and where they were seen (pixels).
    pub view: PlanarView,
}

/// Settings of [`calibrate_turntable`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TurntableOptions {
    /// Height of the board's origin above the table top, metres (the board's thickness for a board
    /// lying flat, 0 for a thin print).
    pub board_origin_height_m: f64,
}

/// The fitted turntable.
#[derive(Debug, Clone, PartialEq)]
pub struct TurntableCalibration {
    /// Unit axis direction (rig `+z`), camera frame.
    pub axis_camera: Vector3<f64>,
    /// The rig origin (axis at the table top), camera frame, metres.
    pub origin_camera_m: Vector3<f64>,
    /// The camera's pose in the rig frame (rig -> camera), metres.
    pub camera_pose: Pose,
    /// Board pose (board -> camera) at each view, in input order.
    pub board_poses: Vec<Pose>,
    /// Re-projection RMS of each view's pose, pixels.
    pub per_view_rms_px: Vec<f64>,
    /// RMS over the views of the board origin's distance from its fitted circle about the axis,
    /// metres.
    pub circle_rms_m: f64,
    /// Largest difference between a measured rotation between two views and the commanded one,
    /// degrees.
    pub max_angle_error_deg: f64,
}

/// Wrap an angle difference into `(-180, 180]` degrees.
fn wrap_deg(a: f64) -> f64 {
    let r = a.rem_euclid(360.0);
    if r > 180.0 {
        r - 360.0
    } else {
        r
    }
}

/// Fit the turntable axis from board views at known table angles (see the module docs). Needs at
/// least 3 views spanning more than 10 degrees.
pub fn calibrate_turntable(
    intrinsics: &Intrinsics,
    views: &[TurntableView],
    options: &TurntableOptions,
) -> Result<TurntableCalibration, CalibrationError> {
    if views.len() < 3 {
        return Err(CalibrationError::TooFewViews { got: views.len(), need: 3 });
    }
    let mut poses = Vec::with_capacity(views.len());
    let mut rms = Vec::with_capacity(views.len());
    for (i, v) in views.iter().enumerate() {
        if !v.angle_deg.is_finite() {
            return Err(CalibrationError::NonFinite { view: i, index: 0 });
        }
        let est = estimate_pose(intrinsics, &v.view).map_err(|e| renumber(e, i))?;
        poses.push(est.pose);
        rms.push(est.rms_px);
    }
    // Axis: mean of the relative rotation axes, each signed by its commanded turn and weighted by
    // the sine of the turn (small turns say little about the axis).
    let mut axis_sum = Vector3::zeros();
    let mut max_angle_error_deg: f64 = 0.0;
    let mut pairs = 0;
    for k in 0..views.len() {
        for l in k + 1..views.len() {
            let d = wrap_deg(views[l].angle_deg - views[k].angle_deg);
            if d.abs() < 5.0 {
                continue;
            }
            let q = Rotation3::from_matrix_unchecked(poses[l].rotation * poses[k].rotation.transpose());
            let Some((axis, angle)) = q.axis_angle() else { continue };
            let signed = if d > 0.0 { axis.into_inner() } else { -axis.into_inner() };
            axis_sum += signed * angle.sin().abs().max(1e-3);
            max_angle_error_deg = max_angle_error_deg.max((angle.to_degrees() - d.abs()).abs());
            pairs += 1;
        }
    }
    if pairs == 0 || axis_sum.norm() < 1e-9 {
        return Err(CalibrationError::Degenerate {
            reason: "the views do not turn the board: use table angles more than 10 degrees apart",
        });
    }
    let axis = axis_sum.normalize();
    // A point on the axis: fixed point of every relative motion from view 0, plus the plane of the
    // board origins.
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    let (r0, t0) = (poses[0].rotation, poses[0].translation);
    for p in &poses[1..] {
        let q = p.rotation * r0.transpose();
        let s = p.translation - q * t0;
        let m = Matrix3::identity() - q;
        a += m.transpose() * m;
        b += m.transpose() * s;
    }
    let mean_origin = poses.iter().map(|p| p.translation).sum::<Vector3<f64>>() / poses.len() as f64;
    let w = a.norm().max(1e-12);
    a += axis * axis.transpose() * w;
    b += axis * axis.dot(&mean_origin) * w;
    let point = a.lu().solve(&b).ok_or(CalibrationError::Degenerate { reason: "the axis position is undetermined" })?;
    // Circle residual of the board origins about the axis.
    let radii: Vec<f64> = poses
        .iter()
        .map(|p| {
            let v = p.translation - point;
            (v - axis * axis.dot(&v)).norm()
        })
        .collect();
    let mean_r = radii.iter().sum::<f64>() / radii.len() as f64;
    let circle_rms_m = (radii.iter().map(|r| (r - mean_r).powi(2)).sum::<f64>() / radii.len() as f64).sqrt();

    let origin = point - axis * options.board_origin_height_m;
    // Rig axes in camera coordinates.
    let to_camera = -origin;
    let horizontal = to_camera - axis * axis.dot(&to_camera);
    if horizontal.norm() < 1e-9 {
        return Err(CalibrationError::Degenerate {
            reason: "the camera looks straight down the axis, which leaves the rig's x direction undefined",
        });
    }
    let y = -horizontal.normalize();
    let x = y.cross(&axis);
    let rotation = Matrix3::from_columns(&[x, y, axis]);
    Ok(TurntableCalibration {
        axis_camera: axis,
        origin_camera_m: origin,
        camera_pose: Pose { rotation, translation: origin },
        board_poses: poses,
        per_view_rms_px: rms,
        circle_rms_m,
        max_angle_error_deg,
    })
}

/// A single-view error from [`estimate_pose`] (always view 0) renumbered to the view it came from.
fn renumber(e: CalibrationError, view: usize) -> CalibrationError {
    match e {
        CalibrationError::TooFewPoints { got, need, .. } => CalibrationError::TooFewPoints { view, got, need },
        CalibrationError::MismatchedPoints { object, image, .. } => {
            CalibrationError::MismatchedPoints { view, object, image }
        }
        CalibrationError::NotPlanar { index, z, .. } => CalibrationError::NotPlanar { view, index, z },
        CalibrationError::NonFinite { index, .. } => CalibrationError::NonFinite { view, index },
        CalibrationError::Collinear { .. } => CalibrationError::Collinear { view },
        other => other,
    }
}
