//! Camera, turntable and light calibration.
//!
//! - [`detect`]: chessboard inner-corner detection with sub-pixel refinement, ordered as a grid.
//! - [`zhang`]: plane-based camera calibration (Zhang's method): homographies, closed-form
//!   intrinsics, extrinsics, then Levenberg-Marquardt refinement of the intrinsics, radial
//!   distortion (`k1`, `k2`, the model of [`crate::geometry::Intrinsics`]) and every board pose;
//!   and single-view pose estimation with known intrinsics ([`estimate_pose`]).
//! - [`turntable`]: the turntable axis, and so the camera's pose in the rig frame, from board poses
//!   at several table angles.
//! - [`capture`]: board captures by a simulated rig (the rig file's camera) for the workflow.
//!
//! # Frames and units
//! - **Board frame**: origin at inner corner `(0, 0)`, `+x` along the board's columns (index `i`),
//!   `+y` along its rows (index `j`), `+z = x × y` pointing into the board (away from a camera that
//!   sees its printed face). Inner corner `(i, j)` is at `(i·s, j·s, 0)` for square size `s` metres.
//!   The square whose corners are inner corners `(0,0)`, `(1,0)`, `(0,1)`, `(1,1)` is dark.
//! - Board poses are [`Pose`]s board -> camera (`x_cam = R·x_board + t`, metres).
//! - Image points are continuous pixel coordinates with the origin at the top-left corner of the
//!   image (pixel `(u, v)` covers `[u, u+1) × [v, v+1)`), as everywhere in [`crate::geometry`].

pub mod capture;
pub mod cli;
pub mod detect;
pub mod file;
pub mod laser_board;
mod lm;
pub mod opencv_xml;
pub mod opencv_yaml;
pub mod procam;
pub mod procam_cloud;
pub mod procam_file;
pub mod procam_sim;
pub mod turntable;
pub mod zhang;

pub use detect::{detect_chessboard, ChessboardDetection, DetectError, DetectOptions};
pub use turntable::{calibrate_turntable, TurntableCalibration, TurntableOptions, TurntableView};
pub use zhang::{
    calibrate_camera, estimate_pose, homography, CalibrationOptions, CameraCalibrationResult, PlanarView, PoseEstimate,
};

use nalgebra::{Point2, Vector3};

use crate::geometry::Pose;

/// A chessboard calibration target: `cols` x `rows` inner corners (where four squares meet) at a
/// spacing of `square_m` metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardSpec {
    /// Inner corners along the board's `x` axis (one fewer than squares in a row).
    pub cols: usize,
    /// Inner corners along the board's `y` axis.
    pub rows: usize,
    /// Edge of one square, metres.
    pub square_m: f64,
}

impl BoardSpec {
    /// A board of `cols` x `rows` inner corners and `square_m` metre squares; refuses fewer than 3
    /// corners along a side, or a square that is not a positive finite length.
    pub fn new(cols: usize, rows: usize, square_m: f64) -> Result<BoardSpec, CalibrationError> {
        if cols < 3 || rows < 3 {
            return Err(CalibrationError::BoardTooSmall { cols, rows });
        }
        if !(square_m.is_finite() && square_m > 0.0) {
            return Err(CalibrationError::BadSquareSize { square_m });
        }
        Ok(BoardSpec { cols, rows, square_m })
    }

    /// Number of inner corners.
    pub fn len(&self) -> usize {
        self.cols * self.rows
    }

    /// True when the board has no corners (never for a board made by [`BoardSpec::new`]).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The inner corners in the board frame, metres, row-major: index `j·cols + i` is corner `(i, j)`
    /// at `(i·s, j·s, 0)`. The same order as [`ChessboardDetection::corners`].
    pub fn object_points(&self) -> Vec<Vector3<f64>> {
        let mut out = Vec::with_capacity(self.len());
        for j in 0..self.rows {
            for i in 0..self.cols {
                out.push(Vector3::new(i as f64 * self.square_m, j as f64 * self.square_m, 0.0));
            }
        }
        out
    }
}

/// Re-projection error of points seen through a camera: RMS of the pixel distances between the
/// observed and the projected points.
pub fn reprojection_rms_px(
    intrinsics: &crate::geometry::Intrinsics,
    pose: &Pose,
    object: &[Vector3<f64>],
    image: &[Point2<f64>],
) -> f64 {
    if object.is_empty() {
        return 0.0;
    }
    let mut sum = 0.0;
    for (p, q) in object.iter().zip(image) {
        let c = pose.apply(p);
        let r = intrinsics.normalised_to_pixel(c.x / c.z, c.y / c.z);
        sum += (r - q).norm_squared();
    }
    (sum / object.len() as f64).sqrt()
}

/// Why a calibration could not be computed. Each names the view (0-based index into the input)
/// where one is at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    /// A board needs at least 3 inner corners along each side.
    #[error("a chessboard needs at least 3x3 inner corners, got {cols}x{rows}")]
    BoardTooSmall {
        /// Inner corners along x.
        cols: usize,
        /// Inner corners along y.
        rows: usize,
    },
    /// The square size is not a positive, finite length.
    #[error("the square size must be a positive length in metres, got {square_m}")]
    BadSquareSize {
        /// The size given, metres.
        square_m: f64,
    },
    /// Fewer views than the method needs.
    #[error("{need} views needed, got {got}")]
    TooFewViews {
        /// Views given.
        got: usize,
        /// Views needed.
        need: usize,
    },
    /// A view with fewer point pairs than a homography needs.
    #[error("view {view}: at least {need} points needed, got {got}")]
    TooFewPoints {
        /// The view.
        view: usize,
        /// Points given.
        got: usize,
        /// Points needed.
        need: usize,
    },
    /// Object and image point lists of different lengths.
    #[error("view {view}: {object} object points but {image} image points")]
    MismatchedPoints {
        /// The view.
        view: usize,
        /// Object points.
        object: usize,
        /// Image points.
        image: usize,
    },
    /// Object points off the board plane `z = 0`.
    #[error("view {view}: object point {index} has z = {z} m; board points must lie on z = 0")]
    NotPlanar {
        /// The view.
        view: usize,
        /// Index of the first such point.
        index: usize,
        /// Its z, metres.
        z: f64,
    },
    /// A NaN or infinite coordinate.
    #[error("view {view}: point {index} is not finite")]
    NonFinite {
        /// The view.
        view: usize,
        /// The point.
        index: usize,
    },
    /// The points of a view are (nearly) on one line, so they fix no homography.
    #[error("view {view}: the points are (nearly) collinear")]
    Collinear {
        /// The view.
        view: usize,
    },
    /// The views together do not determine the intrinsics.
    #[error("degenerate views: {reason}")]
    Degenerate {
        /// What is wrong, e.g. every board parallel to the image plane.
        reason: &'static str,
    },
}

#[cfg(test)]
mod procam_tests;
#[cfg(test)]
pub(crate) mod tests;
