//! The simulated projector: puts its pattern into the simulated world, where the renderer projects it
//! onto the scene through the projector's calibrated model.

use std::time::{Duration, Instant};

use crate::config::SimProjectorConfig;
use crate::devices::DeviceError;
use crate::sim::SimWorld;

/// A simulated projector of `width` x `height` pixels.
#[derive(Debug)]
pub struct SimProjector {
    world: SimWorld,
    width: u32,
    height: u32,
}

impl SimProjector {
    /// The projector of `world` (its geometry comes from the same `[projector]` section).
    pub fn new(world: SimWorld, config: &SimProjectorConfig) -> Self {
        SimProjector { world, width: config.width, height: config.height }
    }
}

impl super::Projector for SimProjector {
    fn resolution(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    fn show(&mut self, pattern: &super::Pattern, _timeout: Duration) -> Result<Instant, DeviceError> {
        self.world.set_pattern(Some(pattern.clone())).map_err(|e| e.to_device_error("projector", "pattern"))?;
        // On screen from now: any frame exposed after this instant shows the pattern.
        Ok(Instant::now())
    }

    fn blank(&mut self, _timeout: Duration) -> Result<(), DeviceError> {
        self.world.set_pattern(None).map_err(|e| e.to_device_error("projector", "pattern"))
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
        assert!(world.snapshot().pattern.is_some());
        let err = p.show(&Pattern::uniform(w + 1, h, [0, 0, 0]), t).expect_err("wrong size");
        assert_eq!(err.kind(), ErrorKind::InvalidConfig);
        p.blank(t).expect("blank");
        assert!(world.snapshot().pattern.is_none());
    }
}
