//! The light array: white lights (on/off or PWM dimmable) and line lasers, each addressable by index.

pub mod sim;

use std::time::Duration;

use super::DeviceError;

/// An array of lights and line lasers behind one controller.
pub trait LightArray: Send + std::fmt::Debug {
    /// Number of white lights.
    fn light_count(&self) -> usize;

    /// Number of line lasers.
    fn laser_count(&self) -> usize;

    /// Set light `index` to `level` in 0..=1 (a plain on/off light is on for any level > 0).
    fn set_light(&mut self, index: usize, level: f32, timeout: Duration) -> Result<(), DeviceError>;

    /// Switch laser `index` on or off.
    fn set_laser(&mut self, index: usize, on: bool, timeout: Duration) -> Result<(), DeviceError>;

    /// Everything off. Called at the end of every scan, also after errors.
    fn all_off(&mut self, timeout: Duration) -> Result<(), DeviceError> {
        for i in 0..self.light_count() {
            self.set_light(i, 0.0, timeout)?;
        }
        for i in 0..self.laser_count() {
            self.set_laser(i, false, timeout)?;
        }
        Ok(())
    }
}
