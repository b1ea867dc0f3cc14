//! The simulated light array: the `[lights]` white lights and line lasers of the simulated world.

use std::time::Duration;

use crate::devices::DeviceError;
use crate::sim::SimWorld;

/// Simulated lights and lasers; switching one changes what the simulated cameras see from then on.
#[derive(Debug)]
pub struct SimLightArray {
    world: SimWorld,
}

impl SimLightArray {
    /// The lights and lasers of `world` (from the rig file's `[lights]`).
    pub fn new(world: SimWorld) -> Self {
        SimLightArray { world }
    }
}

impl super::LightArray for SimLightArray {
    fn light_count(&self) -> usize {
        self.world.renderer().lighting().lights.len()
    }

    fn laser_count(&self) -> usize {
        self.world.renderer().lighting().lasers.len()
    }

    fn set_light(&mut self, index: usize, level: f32, _timeout: Duration) -> Result<(), DeviceError> {
        self.world.set_light(index, level).map_err(|e| crate::devices::sim_device_error(&e, "lights", "light"))?;
        tracing::trace!(index, level, "light set");
        Ok(())
    }

    fn set_laser(&mut self, index: usize, on: bool, _timeout: Duration) -> Result<(), DeviceError> {
        self.world.set_laser(index, on).map_err(|e| crate::devices::sim_device_error(&e, "lights", "laser"))?;
        tracing::trace!(index, on, "laser set");
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::LightArray;
    use super::*;
    use crate::devices::ErrorKind;
    use crate::sim::tests::small_world;

    #[test]
    fn switches_reach_the_world_and_bad_indices_are_typed_errors() {
        let world = small_world("box");
        let mut l = SimLightArray::new(world.clone());
        let t = Duration::from_millis(10);
        assert_eq!(l.light_count(), 4);
        assert_eq!(l.laser_count(), 1);
        let before = world.change_count();
        l.set_light(2, 0.5, t).expect("light");
        l.set_laser(0, true, t).expect("laser");
        let s = world.snapshot();
        assert_eq!(s.light_levels[2], 0.5);
        assert!(s.lasers_on[0]);
        assert_eq!(s.changes, before + 2);
        assert_eq!(l.set_light(4, 1.0, t).expect_err("no light 4").kind(), ErrorKind::InvalidConfig);
        assert_eq!(l.set_laser(1, true, t).expect_err("no laser 1").kind(), ErrorKind::InvalidConfig);
        assert_eq!(l.set_light(0, f32::NAN, t).expect_err("bad level").kind(), ErrorKind::InvalidConfig);
        l.all_off(t).expect("all off");
        let s = world.snapshot();
        assert!(s.light_levels.iter().all(|&x| x == 0.0) && s.lasers_on.iter().all(|&x| !x));
    }
}
