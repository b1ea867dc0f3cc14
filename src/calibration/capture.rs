//! Captures of a chessboard by a simulated rig, for the calibration workflow: the rig file's camera
//! (intrinsics, distortion, pose, pixel noise) renders the board through
//! [`crate::sim::chessboard::render_board`], either held in front of the camera in a spread of tilts
//! (camera calibration) or lying on the turntable at several table angles (axis calibration).
//! Table angles are quantised to the simulated stepper's steps, as the real table would be.

use image::RgbImage;
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::geometry::{CameraModel, Pose};
use crate::sim::chessboard::{render_board, BoardMount, BoardScene, ChessboardTarget};
use crate::sim::FrameNoise;

/// Rays per pixel side when rendering calibration frames.
const SUPERSAMPLE: u32 = 3;

/// A simulated camera and the board it photographs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimBoardRig {
    /// The camera, posed in the rig frame.
    pub camera: CameraModel,
    /// Pixel noise standard deviation, 8-bit levels.
    pub noise_sigma: f64,
    /// Noise seed.
    pub seed: u64,
    /// The printed board.
    pub target: ChessboardTarget,
    /// Turntable steps per full turn (angles are rounded to a step); 0 = continuous.
    pub steps_per_turn: u32,
}

impl SimBoardRig {
    /// Board -> rig poses for `n` camera-calibration views: the board about 45 % of the image wide,
    /// its centre moved around the image and tilted up to about 30° in changing directions.
    pub fn camera_view_poses(&self, n: usize) -> Vec<Pose> {
        let t = &self.target;
        let i = &self.camera.intrinsics;
        let board_w = (t.cols + 1) as f64 * t.square_m;
        let dist = i.fx * board_w / (0.45 * self.camera.width as f64);
        let mid = board_middle(t);
        let cam_to_rig = self.camera.pose.rotation.transpose();
        (0..n)
            .map(|k| {
                let phase = k as f64 / n.max(1) as f64 * std::f64::consts::TAU;
                let tilt = 18.0 + 12.0 * ((k % 3) as f64 / 2.0);
                let (ax, ay) = (tilt * phase.cos(), tilt * phase.sin());
                let az = 20.0 * (2.0 * phase).sin();
                let r = Rotation3::from_euler_angles(ax.to_radians(), ay.to_radians(), az.to_radians()).into_inner();
                // The board centre wanders over the middle of the image (normalised offsets ±0.2 of
                // the field of view), opposite to its tilt so the near edge stays in view.
                let (ox, oy) = (-0.18 * phase.sin(), 0.15 * phase.cos());
                let w = self.camera.width as f64 / i.fx;
                let h = self.camera.height as f64 / i.fy;
                let centre = Vector3::new(
                    (ox * w + (self.camera.width as f64 / 2.0 - i.cx) / i.fx) * dist,
                    (oy * h + (self.camera.height as f64 / 2.0 - i.cy) / i.fy) * dist,
                    dist,
                );
                // Board -> camera, then camera -> rig.
                let (rb, tb) = (r, centre - r * mid);
                Pose { rotation: cam_to_rig * rb, translation: cam_to_rig * (tb - self.camera.pose.translation) }
            })
            .collect()
    }

    /// Board -> object pose of a board lying face up on the table, its centre `offset_m` from the
    /// axis, its origin `height_m` above the table top.
    pub fn lying_board_pose(&self, offset_m: [f64; 2], height_m: f64) -> Pose {
        let t = &self.target;
        let mid = board_middle(t);
        // Board x along object x, board y along -y, board z (into the board) down: the face is up.
        let r = Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0);
        Pose { rotation: r, translation: Vector3::new(offset_m[0], offset_m[1], height_m) - r * mid }
    }

    /// The table angle the simulated stepper actually reaches for `degrees`.
    pub fn reachable_angle(&self, degrees: f64) -> f64 {
        if self.steps_per_turn == 0 {
            return degrees;
        }
        let step = 360.0 / self.steps_per_turn as f64;
        (degrees / step).round() * step
    }

    /// Render the board fixed in the rig at `board_to_rig`; `sequence` numbers the frame's noise.
    pub fn render_fixed(&self, board_to_rig: &Pose, sequence: u64) -> RgbImage {
        self.render(BoardMount::Rig(*board_to_rig), 0.0, sequence)
    }

    /// Render the board mounted on the turntable at `board_to_object` with the table at `angle_deg`.
    pub fn render_on_table(&self, board_to_object: &Pose, angle_deg: f64, sequence: u64) -> RgbImage {
        self.render(BoardMount::Turntable(*board_to_object), angle_deg, sequence)
    }

    fn render(&self, mount: BoardMount, angle_deg: f64, sequence: u64) -> RgbImage {
        let scene = BoardScene { target: self.target, mount, illumination: 0.95, background: 0.3 };
        render_board(
            &self.camera,
            &scene,
            angle_deg,
            SUPERSAMPLE,
            FrameNoise { sigma: self.noise_sigma, seed: self.seed, sequence },
        )
    }
}

/// The middle of the inner-corner grid, board frame, metres.
fn board_middle(t: &ChessboardTarget) -> Vector3<f64> {
    Vector3::new(
        t.cols.saturating_sub(1) as f64 * t.square_m / 2.0,
        t.rows.saturating_sub(1) as f64 * t.square_m / 2.0,
        0.0,
    )
}
