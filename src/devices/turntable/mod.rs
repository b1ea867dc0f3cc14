//! The turntable: a stepper that turns the object about the rig's `+z` axis.

pub mod sim;

use std::time::Duration;

use super::DeviceError;

/// A turntable. Angles are degrees in the object frame convention of [`crate::geometry`]:
/// counter-clockwise seen from above. Steps per turn is defined once, by the driver.
pub trait Turntable: Send + std::fmt::Debug {
    /// Turn to an absolute angle (degrees, any real value; the table takes the short way unless the
    /// driver says otherwise) and block until the motion has *finished* or `timeout` runs out.
    fn move_to(&mut self, degrees: f64, timeout: Duration) -> Result<(), DeviceError>;

    /// The angle the table is at, degrees, as last reported by the device (the commanded angle
    /// rounded to whole steps).
    fn angle(&self) -> f64;

    /// Motor steps (micro-steps) per full turn of the table.
    fn steps_per_turn(&self) -> u32;

    /// Park: stop, and release the motor so it does not heat. Called at the end of every scan,
    /// also after errors.
    fn park(&mut self, timeout: Duration) -> Result<(), DeviceError>;

    /// Drive to the end stop and zero there. Most turntables have no end stop.
    fn home(&mut self, _timeout: Duration) -> Result<(), DeviceError> {
        Err(DeviceError::unsupported("turntable", "homing"))
    }
}
