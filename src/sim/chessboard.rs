//! A planar chessboard calibration target, rendered through a simulated camera (same intrinsics,
//! distortion and pixel noise as the scan renders), fixed in the rig or lying/standing on the
//! turntable so that it turns with the table.
//!
//! Board frame: origin at inner corner `(0, 0)`, `x` along the columns, `y` along the rows, the
//! printed face towards `-z` seen from the camera; inner corner `(i, j)` at `(i·s, j·s, 0)` metres.
//! The printed board has `(cols + 1) x (rows + 1)` squares; the square between inner corners
//! `(0,0)` and `(1,1)` is dark (the convention of [`crate::calibration`]). A white border of
//! `border_m` surrounds the squares. Each pixel averages `n x n` rays through its area, so edges are
//! anti-aliased as a real sensor integrates light.

use image::RgbImage;
use nalgebra::Vector3;
use rayon::prelude::*;

use super::render::FrameNoise;
use super::rng::gaussian3;
use crate::geometry::{turntable_rotation, CameraModel, Pose};

/// The printed target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChessboardTarget {
    /// Inner corners along the board's `x` axis.
    pub cols: usize,
    /// Inner corners along the board's `y` axis.
    pub rows: usize,
    /// Square edge, metres.
    pub square_m: f64,
    /// White paper around the squares, metres.
    pub border_m: f64,
    /// Reflectance of the dark squares, 0..1.
    pub dark: f64,
    /// Reflectance of the light squares and the border, 0..1.
    pub light: f64,
}

impl ChessboardTarget {
    /// Reflectance at board-frame point `(x, y)` metres; `None` off the paper.
    pub fn albedo(&self, x: f64, y: f64) -> Option<f64> {
        let s = self.square_m;
        let (x0, x1) = (-s - self.border_m, (self.cols as f64) * s + self.border_m);
        let (y0, y1) = (-s - self.border_m, (self.rows as f64) * s + self.border_m);
        if x < x0 || x > x1 || y < y0 || y > y1 {
            return None;
        }
        let (a, b) = ((x / s).floor(), (y / s).floor());
        let on_squares = a >= -1.0 && a < self.cols as f64 && b >= -1.0 && b < self.rows as f64;
        if on_squares && (a + b).rem_euclid(2.0) == 0.0 {
            Some(self.dark)
        } else {
            Some(self.light)
        }
    }
}

/// Where the board is mounted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BoardMount {
    /// Fixed in the rig: the pose maps board -> rig frame.
    Rig(Pose),
    /// On the turntable: the pose maps board -> object frame, so the board turns with the table.
    Turntable(Pose),
}

/// How a board frame is lit and what lies behind it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardScene {
    /// The board.
    pub target: ChessboardTarget,
    /// Its mounting and pose (`x_frame = R·x_board + t`, metres).
    pub mount: BoardMount,
    /// Illumination: a reflectance of 1 renders at this fraction of full scale.
    pub illumination: f64,
    /// Grey level (0..1 of full scale) where rays miss the board.
    pub background: f64,
}

/// Render the board as the camera `camera` (posed in the rig frame) sees it with the turntable at
/// `turntable_deg` degrees: 8-bit grey replicated to RGB, `supersample²` rays per pixel, Gaussian
/// pixel noise `noise` as in [`super::Renderer::render_rgb`].
pub fn render_board(
    camera: &CameraModel,
    scene: &BoardScene,
    turntable_deg: f64,
    supersample: u32,
    noise: FrameNoise,
) -> RgbImage {
    let (w, h) = (camera.width, camera.height);
    let n = supersample.max(1);
    // Board -> rig: for a turntable mount, object -> rig is Rz(θ).
    let (r, t) = match scene.mount {
        BoardMount::Rig(p) => (p.rotation, p.translation),
        BoardMount::Turntable(p) => {
            let rz = turntable_rotation(turntable_deg);
            (rz * p.rotation, rz * p.translation)
        }
    };
    let rt = r.transpose();
    let origin_b = rt * (camera.centre() - t);
    let row_len = 3 * w as usize;
    let mut buf = vec![0u8; row_len * h as usize];
    let sigma = noise.sigma as f32;
    buf.par_chunks_mut(row_len.max(1)).enumerate().for_each(|(v, row)| {
        for u in 0..w {
            let mut acc = 0.0;
            for sv in 0..n {
                for su in 0..n {
                    let (pu, pv) = (u as f64 + (su as f64 + 0.5) / n as f64, v as f64 + (sv as f64 + 0.5) / n as f64);
                    let d: Vector3<f64> = rt * camera.pixel_ray(pu, pv);
                    let value = if d.z.abs() < 1e-12 {
                        scene.background
                    } else {
                        let s = -origin_b.z / d.z;
                        let p = origin_b + d * s;
                        match (s > 0.0).then(|| scene.target.albedo(p.x, p.y)).flatten() {
                            Some(a) => a * scene.illumination,
                            None => scene.background,
                        }
                    };
                    acc += value;
                }
            }
            let g = if sigma > 0.0 {
                gaussian3(noise.seed, noise.sequence, v as u64 * w as u64 + u as u64)[0]
            } else {
                0.0
            };
            let x = (acc / (n * n) as f64) as f32 * 255.0 + sigma * g;
            let level = x.round().clamp(0.0, 255.0) as u8;
            row[3 * u as usize..3 * u as usize + 3].fill(level);
        }
    });
    RgbImage::from_raw(w, h, buf).unwrap_or_else(|| RgbImage::new(w, h))
}
