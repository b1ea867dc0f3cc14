//! The simulated projector: puts its pattern into the simulated world, where the renderer projects it
//! onto the scene through the projector's calibrated model.

use std::time::{Duration, Instant};

use crate::config::SimProjectorConfig;
use crate::devices::DeviceError;
use crate::sim::SimWorld;

/// The light a projector emits for each input grey level: `black_level + (1 - black_level) ·
/// (v / 255)^gamma`, as a fraction of full white. The simulated projector applies it to every
/// pattern it shows (rounded back to 8 bits), so patterns meet a real projector's non-linearity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectorResponse {
    /// Exponent (1 = linear).
    pub gamma: f64,
    /// Light of a black input, fraction 0..1 of full white.
    pub black_level: f64,
}

impl ProjectorResponse {
    /// A linear projector with a true black.
    pub const LINEAR: ProjectorResponse = ProjectorResponse { gamma: 1.0, black_level: 0.0 };

    /// The emitted level (8-bit scale) for each input level.
    pub fn lut(&self) -> [u8; 256] {
        let mut lut = [0u8; 256];
        for (v, o) in lut.iter_mut().enumerate() {
            let light = self.black_level + (1.0 - self.black_level) * (v as f64 / 255.0).powf(self.gamma);
            *o = (255.0 * light).round().clamp(0.0, 255.0) as u8;
        }
        lut
    }
}

/// A simulated projector of `width` x `height` pixels with an input lag and a refresh period: a
/// pattern handed to [`show`](super::Projector::show) appears at the first refresh (a multiple of
/// `frame_period` after the projector started) at or after `latency` has passed, and cameras exposing
/// before that still see the previous pattern.
#[derive(Debug)]
pub struct SimProjector {
    world: SimWorld,
    width: u32,
    height: u32,
    latency: Duration,
    frame_period: Duration,
    started: Instant,
    /// `None` for a linear projector with a true black (patterns pass unchanged).
    lut: Option<[u8; 256]>,
}

impl SimProjector {
    /// The projector of `world` (its geometry comes from the same `[projector]` section, its timing
    /// from `latency_ms` and `frame_period_ms`, negative or non-finite values counting as 0; its
    /// response from `gamma` and `black_level`).
    pub fn new(world: SimWorld, config: &SimProjectorConfig) -> Self {
        let ms = |v: f64| if v.is_finite() && v > 0.0 { Duration::from_secs_f64(v / 1000.0) } else { Duration::ZERO };
        let response = ProjectorResponse { gamma: config.gamma, black_level: config.black_level };
        SimProjector {
            latency: ms(config.latency_ms),
            frame_period: ms(config.frame_period_ms),
            ..Self::with_response(world, config.width, config.height, response)
        }
    }

    /// A `width` x `height` pixel projector of `world` with the given response and no latency.
    pub fn with_response(world: SimWorld, width: u32, height: u32, response: ProjectorResponse) -> Self {
        let lut = (response != ProjectorResponse::LINEAR).then(|| response.lut());
        SimProjector {
            world,
            width,
            height,
            latency: Duration::ZERO,
            frame_period: Duration::ZERO,
            started: Instant::now(),
            lut,
        }
    }

    /// When a pattern handed over at `now` appears: the first refresh at or after `now + latency`.
    fn visible_at(&self, now: Instant) -> Instant {
        let ready = now + self.latency;
        if self.frame_period.is_zero() {
            return ready;
        }
        let since = ready.duration_since(self.started).as_nanos();
        let period = self.frame_period.as_nanos();
        let frames = since.div_ceil(period);
        let offset = u64::try_from(frames * period).unwrap_or(u64::MAX);
        self.started + Duration::from_nanos(offset)
    }
}

impl super::Projector for SimProjector {
    fn resolution(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn show(&mut self, pattern: &super::Pattern, _timeout: Duration) -> Result<Instant, DeviceError> {
        let shown = match &self.lut {
            None => pattern.clone(),
            Some(lut) => super::Pattern {
                width: pattern.width,
                height: pattern.height,
                rgb: std::sync::Arc::new(pattern.rgb.iter().map(|&v| lut[v as usize]).collect()),
            },
        };
        let at = self.visible_at(Instant::now());
        self.world
            .set_pattern_at(Some(shown), at)
            .map_err(|e| crate::devices::sim_device_error(&e, "projector", "pattern"))?;
        Ok(at)
    }

    fn blank(&mut self, _timeout: Duration) -> Result<(), DeviceError> {
        // Parking must not leave a pattern pending: black from now on, whatever the latency.
        self.world.set_pattern(None).map_err(|e| crate::devices::sim_device_error(&e, "projector", "pattern"))
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Pattern, Projector};
    use super::*;
    use crate::devices::ErrorKind;
    use crate::sim::tests::small_rig;

    #[test]
    fn show_checks_the_size_and_blank_clears() {
        let rig = small_rig("box");
        let world = crate::sim::SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
        let Some(crate::config::ProjectorConfig::Sim(pc)) = rig.projector.as_ref() else {
            panic!("simulated projector")
        };
        let mut p = SimProjector::new(world.clone(), pc);
        let (w, h) = p.resolution();
        let t = Duration::from_millis(10);
        let before = Instant::now();
        let at = p.show(&Pattern::uniform(w, h, [255, 255, 255]), t).expect("show");
        assert!(at >= before);
        while Instant::now() < at {
            std::thread::sleep(at - Instant::now());
        }
        assert!(world.snapshot().pattern.is_some());
        let err = p.show(&Pattern::uniform(w + 1, h, [0, 0, 0]), t).expect_err("wrong size");
        assert_eq!(err.kind(), ErrorKind::InvalidConfig);
        p.blank(t).expect("blank");
        assert!(world.snapshot().pattern.is_none());
    }

    #[test]
    fn a_pattern_appears_only_after_the_latency_at_a_refresh() {
        let rig = small_rig("box");
        let world = crate::sim::SimWorld::from_config(rig.sim.as_ref().expect("sim"), &rig).expect("world");
        let Some(crate::config::ProjectorConfig::Sim(pc)) = rig.projector.as_ref() else {
            panic!("the rig has a simulated projector")
        };
        let mut pc = pc.clone();
        pc.latency_ms = 30.0;
        pc.frame_period_ms = 7.0;
        let mut p = SimProjector::new(world.clone(), &pc);
        let (w, h) = p.resolution();
        let t = Duration::from_millis(10);
        let handed = Instant::now();
        let at = p.show(&Pattern::uniform(w, h, [255, 255, 255]), t).expect("show");
        assert!(at >= handed + Duration::from_millis(30), "latency honoured");
        assert!(at < Instant::now() + Duration::from_millis(38), "at most one refresh period more");
        // On a refresh: a whole number of periods after the projector started.
        assert_eq!(at.duration_since(p.started).as_nanos() % 7_000_000, 0);
        let (state, when) = world.snapshot_timed();
        assert!(when < at && state.pattern.is_none(), "not on screen yet");
        std::thread::sleep(at.saturating_duration_since(Instant::now()));
        let (state, when) = world.snapshot_timed();
        assert!(when >= at && state.pattern.is_some(), "on screen from `at`");
        p.blank(t).expect("blank");
        assert!(world.snapshot().pattern.is_none());
    }
}
