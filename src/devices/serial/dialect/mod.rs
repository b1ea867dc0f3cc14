//! Dialects: how the abstract operations of a turntable-and-lights board become bytes for one family
//! of firmware. The [`SerialController`](super::SerialController) picks one from the config.

pub mod fabscan;
pub mod horus;
pub mod scanrig;

use std::time::Duration;

use super::error::LinkError;
use super::link::Link;

/// What a board is and can do, learnt in the handshake (or, for boards that cannot tell, from the
/// config).
#[derive(Debug, Clone, PartialEq)]
pub struct BoardInfo {
    /// Board name.
    pub name: String,
    /// Firmware version.
    pub firmware: String,
    /// Motor steps per full turn of the table.
    pub steps_per_turn: u32,
    /// Number of white lights.
    pub lights: usize,
    /// Number of line lasers.
    pub lasers: usize,
    /// Whether lights take PWM levels.
    pub pwm: bool,
    /// Whether `home` works.
    pub home: bool,
    /// Position after the handshake, steps from zero.
    pub position_steps: i64,
}

/// Timeouts and retry counts shared by all dialects.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    /// Longest wait for the reply to one line.
    pub reply_timeout: Duration,
    /// How often a line is sent again after a lost or damaged reply.
    pub retries: u32,
    /// Longest wait for the banner after opening the port (boards that reset when the port opens).
    pub boot: Duration,
    /// Handshake attempts before giving up.
    pub handshake_attempts: u32,
    /// During a motion, how long to wait without news before asking for status.
    pub poll_interval: Duration,
}

impl Default for Timing {
    fn default() -> Self {
        Timing {
            reply_timeout: Duration::from_millis(500),
            retries: 3,
            boot: Duration::from_millis(2500),
            handshake_attempts: 5,
            poll_interval: Duration::from_millis(250),
        }
    }
}

/// One firmware family. Methods are given the open link; every wait inside is bounded by the
/// [`Timing`] or the `timeout` argument.
pub trait Dialect: Send + std::fmt::Debug {
    /// The config name (`scanrig`, `horus`, `fabscan`).
    fn name(&self) -> &'static str;

    /// Bring a freshly opened link into a known state and learn what the board is.
    fn handshake(&mut self, link: &mut Link) -> Result<BoardInfo, LinkError>;

    /// Turn to `steps` (absolute, from zero) and return when the motion has *finished*; returns the
    /// position reached, steps.
    fn move_to(&mut self, link: &mut Link, steps: i64, timeout: Duration) -> Result<i64, LinkError>;

    /// Drive to the end stop and zero there; returns the position (0).
    fn home(&mut self, _link: &mut Link, _timeout: Duration) -> Result<i64, LinkError> {
        Err(LinkError::Board { code: 4, text: "no end stop".into() })
    }

    /// White light `index` to PWM `level` (0 = off, 255 = full).
    fn set_light(&mut self, link: &mut Link, index: usize, level: u8) -> Result<(), LinkError>;

    /// Line laser `index` on or off.
    fn set_laser(&mut self, link: &mut Link, index: usize, on: bool) -> Result<(), LinkError>;

    /// Release (`false`) or hold (`true`) the turntable motor.
    fn motor(&mut self, link: &mut Link, on: bool) -> Result<(), LinkError>;

    /// Every light and laser off, motion stopped.
    fn all_off(&mut self, link: &mut Link, lights: usize, lasers: usize) -> Result<(), LinkError> {
        for i in 0..lights {
            self.set_light(link, i, 0)?;
        }
        for i in 0..lasers {
            self.set_laser(link, i, false)?;
        }
        Ok(())
    }
}

/// Read bytes into a line (ended by `\n`, `\r` dropped) until `deadline`; lines longer than `max`
/// are cut. Used by the field dialects, whose lines are not the scanrig protocol's.
pub(crate) fn read_text_line(
    link: &mut Link,
    deadline: std::time::Instant,
    waiting_for: &'static str,
    timeout: Duration,
    max: usize,
) -> Result<String, LinkError> {
    let mut line = Vec::new();
    loop {
        match link.read_byte(deadline, waiting_for, timeout)? {
            b'\n' => return Ok(String::from_utf8_lossy(&line).into_owned()),
            b'\r' => {}
            b if line.len() < max => line.push(b),
            _ => {}
        }
    }
}
