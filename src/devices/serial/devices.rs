//! The [`Turntable`] and [`LightArray`] of a serial board, both over one [`SharedController`].

use std::time::Duration;

use super::controller::{lock, SharedController};
use crate::devices::{DeviceError, LightArray, Turntable};

/// The turntable of a serial board. Moves go to the absolute angle given (no wrapping to the short
/// way): a scan that counts up turns the table one way only.
#[derive(Debug)]
pub struct SerialTurntable {
    controller: SharedController,
    name: String,
    reverse: bool,
    steps_per_turn: u32,
}

impl SerialTurntable {
    /// The turntable of `controller`; `reverse` flips the direction for tables wired the other way.
    /// `steps_per_turn` is used until the first handshake tells the board's own value.
    pub fn new(controller: SharedController, reverse: bool, steps_per_turn: u32) -> Self {
        SerialTurntable { controller, name: "turntable".into(), reverse, steps_per_turn }
    }

    fn spt(&self) -> u32 {
        lock(&self.controller).info().map_or(self.steps_per_turn, |i| i.steps_per_turn).max(1)
    }

    fn sign(&self) -> f64 {
        if self.reverse {
            -1.0
        } else {
            1.0
        }
    }
}

impl Turntable for SerialTurntable {
    fn move_to(&mut self, degrees: f64, timeout: Duration) -> Result<(), DeviceError> {
        if !degrees.is_finite() || degrees.abs() > 1.0e6 {
            return Err(DeviceError::InvalidConfig {
                device: self.name.clone(),
                field: "angle",
                problem: format!("{degrees} degrees is not a usable angle"),
            });
        }
        let mut c = lock(&self.controller);
        let started = std::time::Instant::now();
        // Connect first so the board's own steps per turn is known before converting.
        if c.info().is_none() {
            c.with_link(|_, _, _| Ok(())).map_err(|e| e.into_device_error(&self.name))?;
        }
        let spt = c.info().map_or(self.steps_per_turn, |i| i.steps_per_turn).max(1);
        let steps = (self.sign() * degrees * f64::from(spt) / 360.0).round() as i64;
        c.move_to_steps(steps, timeout.saturating_sub(started.elapsed()))
            .map(drop)
            .map_err(|e| e.into_device_error(&self.name))
    }

    fn angle(&self) -> f64 {
        let steps = lock(&self.controller).position_steps();
        self.sign() * steps as f64 * 360.0 / f64::from(self.spt())
    }

    fn steps_per_turn(&self) -> u32 {
        self.spt()
    }

    fn park(&mut self, _timeout: Duration) -> Result<(), DeviceError> {
        lock(&self.controller).with_link(|d, l, _| d.motor(l, false)).map_err(|e| e.into_device_error(&self.name))
    }

    fn home(&mut self, timeout: Duration) -> Result<(), DeviceError> {
        lock(&self.controller).home(timeout).map_err(|e| e.into_device_error(&self.name))
    }
}

/// The lights and lasers of a serial board. Each switch is one exchange with the board, bounded by
/// the controller's `reply_timeout_ms` times `retries + 1`; the per-call `timeout` is not used.
#[derive(Debug)]
pub struct SerialLightArray {
    controller: SharedController,
    name: String,
    lights: usize,
    lasers: usize,
}

impl SerialLightArray {
    /// The light array of `controller`, with the counts the config declares (the board may have
    /// more; an index beyond the board's own count is refused).
    pub fn new(controller: SharedController, lights: usize, lasers: usize) -> Self {
        SerialLightArray { controller, name: "lights".into(), lights, lasers }
    }

    fn check(
        &self,
        what: &'static str,
        index: usize,
        ours: usize,
        board: impl Fn(&super::BoardInfo) -> usize,
    ) -> Result<(), DeviceError> {
        let c = lock(&self.controller);
        let limit = c.info().map_or(ours, |i| ours.min(board(i)));
        if index >= limit {
            return Err(DeviceError::InvalidConfig {
                device: self.name.clone(),
                field: what,
                problem: format!("index {index} is beyond the {limit} the rig and board have"),
            });
        }
        Ok(())
    }
}

impl LightArray for SerialLightArray {
    fn light_count(&self) -> usize {
        self.lights
    }

    fn laser_count(&self) -> usize {
        self.lasers
    }

    fn set_light(&mut self, index: usize, level: f32, _timeout: Duration) -> Result<(), DeviceError> {
        self.check("light", index, self.lights, |i| i.lights)?;
        let pwm = (level.clamp(0.0, 1.0) * 255.0).round() as u8;
        let pwm = if level > 0.0 { pwm.max(1) } else { 0 };
        lock(&self.controller)
            .with_link(|d, l, _| d.set_light(l, index, pwm))
            .map_err(|e| e.into_device_error(&self.name))
    }

    fn set_laser(&mut self, index: usize, on: bool, _timeout: Duration) -> Result<(), DeviceError> {
        self.check("laser", index, self.lasers, |i| i.lasers)?;
        lock(&self.controller)
            .with_link(|d, l, _| d.set_laser(l, index, on))
            .map_err(|e| e.into_device_error(&self.name))
    }

    fn all_off(&mut self, _timeout: Duration) -> Result<(), DeviceError> {
        let (lights, lasers) = (self.lights, self.lasers);
        lock(&self.controller)
            .with_link(|d, l, info| d.all_off(l, lights.min(info.lights), lasers.min(info.lasers)))
            .map_err(|e| e.into_device_error(&self.name))
    }
}
