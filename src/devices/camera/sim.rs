//! The simulated camera: renders the simulated world through its calibrated model, behind a driver
//! queue of `buffer_depth` buffers like a V4L2 stream.
//!
//! Each [`capture`](super::Camera::capture) exposes a new frame *now* (a snapshot of the world, then
//! `exposure_start = Instant::now()`), appends it to the queue, and returns the oldest queued frame,
//! rendered when it is returned. The stream starts on the first capture with the queue filled by
//! `buffer_depth - 1` exposures. So after a scene change the first `buffer_depth - 1` frames returned
//! are stale: they show the old state and their `exposure_start` is earlier than the change.
//! Sequence numbers count exposures from 0, one per exposure.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use crate::config::SimCameraConfig;
use crate::devices::DeviceError;
use crate::sim::{FrameNoise, RayTable, SimWorld, WorldState};

/// A queued exposure, rendered when it is dequeued.
#[derive(Debug)]
struct Exposure {
    sequence: u64,
    exposure_start: Instant,
    state: WorldState,
}

/// A simulated camera looking at the simulated world.
#[derive(Debug)]
pub struct SimCamera {
    world: SimWorld,
    rays: RayTable,
    buffer_depth: usize,
    noise_sigma: f64,
    seed: u64,
    queue: VecDeque<Exposure>,
    next_sequence: u64,
}

impl SimCamera {
    /// A camera with the `[camera]` calibration (rig frame), image size, buffer depth and noise.
    pub fn new(world: SimWorld, config: &SimCameraConfig) -> Self {
        let model = config.calibration.model(config.width, config.height);
        SimCamera {
            world,
            rays: RayTable::new(model),
            buffer_depth: config.buffer_depth.max(1) as usize,
            noise_sigma: if config.noise_sigma.is_finite() { config.noise_sigma.max(0.0) } else { 0.0 },
            seed: config.seed,
            queue: VecDeque::new(),
            next_sequence: 0,
        }
    }

    /// The camera model, rig frame.
    pub fn model(&self) -> &crate::geometry::CameraModel {
        self.rays.model()
    }

    fn expose(&mut self) {
        // The state at the exposure's start: every change made before it, and no pattern that the
        // projector shows only later.
        let (state, exposure_start) = self.world.snapshot_timed();
        self.queue.push_back(Exposure { sequence: self.next_sequence, exposure_start, state });
        self.next_sequence += 1;
    }
}

impl super::Camera for SimCamera {
    fn info(&self) -> super::CameraInfo {
        super::CameraInfo { width: self.rays.model().width, height: self.rays.model().height }
    }

    fn capture(&mut self, timeout: Duration) -> Result<super::Frame, DeviceError> {
        if timeout.is_zero() {
            return Err(DeviceError::Timeout { device: "camera".into(), waiting_for: "a frame", timeout });
        }
        if self.next_sequence == 0 {
            for _ in 1..self.buffer_depth {
                self.expose();
            }
        }
        self.expose();
        let Some(e) = self.queue.pop_front() else {
            return Err(DeviceError::Timeout { device: "camera".into(), waiting_for: "a frame", timeout });
        };
        let noise = FrameNoise { sigma: self.noise_sigma, seed: self.seed, sequence: e.sequence };
        let image = self.world.renderer().render_rgb(&self.rays, &e.state, noise);
        tracing::trace!(sequence = e.sequence, queued = self.queue.len(), "frame delivered");
        Ok(super::Frame { sequence: e.sequence, exposure_start: e.exposure_start, image })
    }
}

#[cfg(test)]
mod tests {
    use super::super::Camera;
    use super::*;
    use crate::devices::lights::sim::SimLightArray;
    use crate::devices::LightArray;
    use crate::sim::tests::small_rig;

    fn camera(scene: &str, depth: u32) -> (SimCamera, SimWorld) {
        let rig = small_rig(scene);
        let world = SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
        let crate::config::CameraConfig::Sim(mut c) = rig.camera.clone() else { panic!("simulated camera") };
        c.buffer_depth = depth;
        c.noise_sigma = 0.0;
        (SimCamera::new(world.clone(), &c), world)
    }

    #[test]
    fn a_light_switch_shows_only_after_the_stale_frames() {
        let (mut cam, world) = camera("box", 3);
        let mut lights = SimLightArray::new(world.clone());
        let t = Duration::from_secs(1);
        let dark = cam.capture(t).expect("frame");
        assert_eq!(dark.sequence, 0);
        cam.capture(t).expect("frame");
        lights.set_light(0, 1.0, t).expect("light on");
        let changed_at = Instant::now();
        let mut seqs = vec![];
        for i in 0..3 {
            let f = cam.capture(t).expect("frame");
            seqs.push(f.sequence);
            if i < 2 {
                assert!(f.exposure_start < changed_at, "frame {i} should be stale");
                assert_eq!(f.image, dark.image, "stale frame {i} must show the old state");
            } else {
                assert!(f.exposure_start >= changed_at, "frame {i} should be fresh");
                assert_ne!(f.image, dark.image, "the fresh frame must show the light");
                let sum = |im: &image::RgbImage| im.as_raw().iter().map(|&x| x as u64).sum::<u64>();
                assert!(sum(&f.image) > sum(&dark.image));
            }
        }
        assert_eq!(seqs, vec![2, 3, 4]);
    }

    #[test]
    fn buffer_depth_one_has_no_stale_frames_and_noise_is_seeded() {
        let (mut cam, world) = camera("box", 1);
        let t = Duration::from_secs(1);
        let a = cam.capture(t).expect("frame");
        world.set_light(1, 1.0).expect("light");
        let b = cam.capture(t).expect("frame");
        assert_ne!(a.image, b.image);
        assert_eq!(b.sequence, 1);
        assert_eq!(cam.capture(Duration::ZERO).expect_err("zero timeout").kind(), crate::devices::ErrorKind::Timeout);

        // Same seed and sequence: same noise; next sequence: different noise.
        let rig = small_rig("box");
        let crate::config::CameraConfig::Sim(mut c) = rig.camera.clone() else { panic!("simulated camera") };
        c.noise_sigma = 2.0;
        c.buffer_depth = 1;
        let mut n1 = SimCamera::new(world.clone(), &c);
        let mut n2 = SimCamera::new(world.clone(), &c);
        let f1 = n1.capture(t).expect("frame");
        let f2 = n2.capture(t).expect("frame");
        assert_eq!(f1.image, f2.image);
        let f3 = n1.capture(t).expect("frame");
        assert_ne!(f1.image, f3.image);
    }
}
