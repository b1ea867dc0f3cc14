//! The simulated depth camera: depth along its optical axis rendered from the simulated world, with
//! optional seeded Gaussian noise on measured pixels.

use std::time::{Duration, Instant};

use crate::config::SimDepthCameraConfig;
use crate::devices::DeviceError;
use crate::sim::rng::gaussian as rng_gaussian;
use crate::sim::{RayTable, SimWorld};

/// A simulated depth camera.
#[derive(Debug)]
pub struct SimDepthCamera {
    world: SimWorld,
    rays: RayTable,
    noise_sigma_m: f64,
    seed: u64,
    next_sequence: u64,
}

impl SimDepthCamera {
    /// A depth camera with the `[depth_camera]` calibration (rig frame), size and noise.
    pub fn new(world: SimWorld, config: &SimDepthCameraConfig) -> Self {
        SimDepthCamera {
            world,
            rays: RayTable::new(config.calibration.model(config.width, config.height)),
            noise_sigma_m: if config.noise_sigma_m.is_finite() { config.noise_sigma_m.max(0.0) } else { 0.0 },
            seed: config.seed,
            next_sequence: 0,
        }
    }

    /// The camera model, rig frame.
    pub fn model(&self) -> &crate::geometry::CameraModel {
        self.rays.model()
    }
}

impl super::DepthCamera for SimDepthCamera {
    fn resolution(&self) -> (u32, u32) {
        (self.rays.model().width, self.rays.model().height)
    }

    fn capture_depth(&mut self, timeout: Duration) -> Result<super::DepthFrame, DeviceError> {
        if timeout.is_zero() {
            return Err(DeviceError::Timeout { device: "depth_camera".into(), waiting_for: "a frame", timeout });
        }
        let angle = self.world.snapshot().turntable_deg;
        let exposure_start = Instant::now();
        let sequence = self.next_sequence;
        self.next_sequence += 1;
        let mut depth_m = self.world.renderer().render_depth(&self.rays, angle);
        if self.noise_sigma_m > 0.0 {
            let sigma = self.noise_sigma_m as f32;
            for (i, z) in depth_m.iter_mut().enumerate() {
                if *z > 0.0 {
                    *z = (*z + sigma * rng_gaussian(self.seed, sequence, i as u64)).max(f32::MIN_POSITIVE);
                }
            }
        }
        let (width, height) = self.resolution();
        Ok(super::DepthFrame { sequence, exposure_start, width, height, depth_m })
    }
}

#[cfg(test)]
mod tests {
    use super::super::DepthCamera;
    use super::*;
    use crate::sim::tests::small_rig;

    #[test]
    fn depth_agrees_with_ray_intersection() {
        let rig = small_rig("cup");
        let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
        let Some(crate::config::DepthCameraConfig::Sim(c)) = rig.depth_camera.as_ref() else {
            panic!("simulated depth camera")
        };
        let mut c = c.clone();
        c.noise_sigma_m = 0.0;
        let mut cam = SimDepthCamera::new(world.clone(), &c);
        world.set_turntable_angle(30.0);
        let f = cam.capture_depth(Duration::from_secs(1)).expect("frame");
        let m = cam.model().for_turntable_angle(30.0);
        let (mut hits, mut misses) = (0, 0);
        for v in (0..f.height).step_by(3) {
            for u in (0..f.width).step_by(3) {
                let z = f.depth_m[(v * f.width + u) as usize];
                let d = m.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                match world.scene().intersect(&m.centre(), &d, 0.0, 10.0) {
                    Some(h) => {
                        hits += 1;
                        let zc = m.pose.apply(&h.point).z;
                        assert!((z as f64 - zc).abs() < 1e-5, "({u},{v}): {z} vs {zc}");
                    }
                    None => {
                        misses += 1;
                        assert_eq!(z, 0.0);
                    }
                }
            }
        }
        assert!(hits > 50 && misses > 50, "hits {hits} misses {misses}");

        // Noise is seeded: same seed and sequence, same frame; measured pixels move by about sigma.
        let mut noisy_cfg = c.clone();
        noisy_cfg.noise_sigma_m = 0.001;
        let mut a = SimDepthCamera::new(world.clone(), &noisy_cfg);
        let mut b = SimDepthCamera::new(world.clone(), &noisy_cfg);
        let fa = a.capture_depth(Duration::from_secs(1)).expect("frame");
        let fb = b.capture_depth(Duration::from_secs(1)).expect("frame");
        assert_eq!(fa.depth_m, fb.depth_m);
        let diffs: Vec<f64> =
            fa.depth_m.iter().zip(&f.depth_m).filter(|(_, &z)| z > 0.0).map(|(&n, &z)| (n - z) as f64).collect();
        let rms = (diffs.iter().map(|d| d * d).sum::<f64>() / diffs.len() as f64).sqrt();
        assert!((rms - 0.001).abs() < 0.0002, "rms {rms}");
    }
}
