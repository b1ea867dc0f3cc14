//! Simulated projector-camera captures of a chessboard: the printed board of
//! [`crate::sim::chessboard`] seen by a simulated camera and lit by a simulated projector showing a
//! Gray-code sequence, with the light model of the scan renderer ([`crate::sim::render`]):
//! a board point of reflectance `a` lit by projector pixel value `P` (0..255) renders at
//! `a · (ambient + intensity · P/255 · cosθ · (REFERENCE_DISTANCE_M / d)²)` of full scale, `θ` the
//! angle between the board normal and the direction to the projector, `d` the distance to it. Each camera pixel averages `n x n` rays through
//! its area, and each ray's board point takes the value of the projector pixel it falls in (a real
//! projector shows each pixel as a uniform square), so stripe and square edges are anti-aliased as a
//! sensor integrates light. Frames are 8-bit grey with seeded Gaussian noise.
//!
//! Frames: camera and projector are [`CameraModel`]s posed in the rig frame (metres); the board pose
//! maps board -> rig. The board's printed face must face both devices.

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::geometry::{CameraModel, Pose};
use crate::pipeline::structured_light::{GrayCodePatterns, PatternError};
use crate::sim::chessboard::ChessboardTarget;
use crate::sim::render::REFERENCE_DISTANCE_M;
use crate::sim::rng::gaussian3;

/// A simulated camera, projector and printed board.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimProcam {
    /// The camera, posed in the rig frame.
    pub camera: CameraModel,
    /// The projector as an inverse camera (its pattern size is its image size), posed in the rig frame.
    pub projector: CameraModel,
    /// The printed board.
    pub target: ChessboardTarget,
    /// Light on the board besides the projector, fraction of full scale for reflectance 1.
    pub ambient: f64,
    /// Projector brightness: a white projector pixel on reflectance 1 adds this fraction of full scale.
    pub projector_intensity: f64,
    /// Grey level (0..1 of full scale) where camera rays miss the board.
    pub background: f64,
    /// Pixel noise standard deviation, 8-bit levels.
    pub noise_sigma: f64,
    /// Noise seed.
    pub seed: u64,
    /// Rays per camera pixel side.
    pub supersample: u32,
}

/// What one camera ray sees: the board's reflectance and the projector pixel lighting that point.
#[derive(Clone, Copy)]
struct RaySample {
    /// Reflectance; negative where the ray misses the board.
    albedo: f32,
    /// `cosθ · (REFERENCE_DISTANCE_M / d)²` towards the projector.
    falloff: f32,
    /// Index into the projector image, or `u32::MAX` where the projector does not light the point.
    projector_pixel: u32,
}

impl SimProcam {
    /// The camera frames of the whole Gray-code sequence `patterns` (projected by this projector,
    /// whose size must match) with the board at `board_to_rig`: one `width * height` grey buffer
    /// per pattern, in sequence order. `pose_index` varies the noise between poses.
    pub fn render_sequence(
        &self,
        board_to_rig: &Pose,
        patterns: &GrayCodePatterns,
        pose_index: u64,
    ) -> Result<Vec<Vec<u8>>, PatternError> {
        let (pw, ph) = (self.projector.width, self.projector.height);
        if patterns.width() != pw || patterns.height() != ph {
            return Err(PatternError::Buffer {
                expected: pw as usize * ph as usize,
                found: patterns.width() as usize * patterns.height() as usize,
            });
        }
        let samples = self.trace(board_to_rig);
        let n = self.supersample.max(1) as usize;
        let per_pixel = n * n;
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let mut frames = Vec::with_capacity(patterns.count());
        for index in 0..patterns.count() {
            let pattern = patterns.render(index)?;
            let mut frame = vec![0u8; w * h];
            frame.par_chunks_mut(w.max(1)).enumerate().for_each(|(v, row)| {
                for (u, px) in row.iter_mut().enumerate() {
                    let pixel = v * w + u;
                    let mut acc = 0.0f32;
                    for s in &samples[pixel * per_pixel..(pixel + 1) * per_pixel] {
                        acc += if s.albedo < 0.0 {
                            self.background as f32
                        } else {
                            let lit = pattern.get(s.projector_pixel as usize).map_or(0.0, |&p| p as f32 / 255.0);
                            s.albedo * (self.ambient as f32 + self.projector_intensity as f32 * lit * s.falloff)
                        };
                    }
                    let noise = if self.noise_sigma > 0.0 {
                        self.noise_sigma as f32
                            * gaussian3(self.seed, pose_index * 1000 + index as u64, pixel as u64)[0]
                    } else {
                        0.0
                    };
                    *px = (acc / per_pixel as f32 * 255.0 + noise).round().clamp(0.0, 255.0) as u8;
                }
            });
            frames.push(frame);
        }
        Ok(frames)
    }

    /// Cast every camera sub-pixel ray at the board: its reflectance (negative where it misses) and
    /// the projector pixel lighting the point hit.
    fn trace(&self, board_to_rig: &Pose) -> Vec<RaySample> {
        let cam = &self.camera;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n = self.supersample.max(1) as usize;
        let rt = board_to_rig.rotation.transpose();
        let origin_b = rt * (cam.centre() - board_to_rig.translation);
        // The projector lights the printed face only if it is on the same side of the board as the camera.
        let proj_b = rt * (self.projector.centre() - board_to_rig.translation);
        let same_side = proj_b.z * origin_b.z > 0.0;
        let (pw, ph) = (self.projector.width as f64, self.projector.height as f64);
        let mut out = vec![RaySample { albedo: -1.0, falloff: 0.0, projector_pixel: u32::MAX }; w * h * n * n];
        out.par_chunks_mut((w * n * n).max(1)).enumerate().for_each(|(v, row)| {
            for u in 0..w {
                for sv in 0..n {
                    for su in 0..n {
                        let (pu, pv) =
                            (u as f64 + (su as f64 + 0.5) / n as f64, v as f64 + (sv as f64 + 0.5) / n as f64);
                        let d: Vector3<f64> = rt * cam.pixel_ray(pu, pv);
                        if d.z.abs() < 1e-12 {
                            continue;
                        }
                        let s = -origin_b.z / d.z;
                        if s <= 0.0 {
                            continue;
                        }
                        let p = origin_b + d * s;
                        let Some(a) = self.target.albedo(p.x, p.y) else { continue };
                        let p_rig = board_to_rig.apply(&p);
                        let projector_pixel = match self.projector.project(&p_rig) {
                            Some(q) if same_side && q.x >= 0.0 && q.y >= 0.0 && q.x < pw && q.y < ph => {
                                q.y.floor() as u32 * self.projector.width + q.x.floor() as u32
                            }
                            _ => u32::MAX,
                        };
                        // The board normal is the board's z axis; the projector lies on the lit side.
                        let to_proj = proj_b - p;
                        let d = to_proj.norm().max(1e-9);
                        let falloff = (to_proj.z.abs() / d) * (REFERENCE_DISTANCE_M / d).powi(2);
                        row[u * n * n + sv * n + su] =
                            RaySample { albedo: a as f32, falloff: falloff as f32, projector_pixel };
                    }
                }
            }
        });
        out
    }
}
