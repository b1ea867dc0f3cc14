//! FabScanPi firmware.
//!
//! Quirks handled here: the board echoes every byte and prints `>` when a line is done, never `ok`,
//! and never reports an error, so a reply is "everything up to the prompt" with the echo removed;
//! it loses bytes while it boots (the Arduino reset on open), so the handshake sends line breaks,
//! waits, and asks `M200` for the version, with retries; turntable moves are relative, in the
//! board's steps, and block until done, so the prompt is the completion and the host keeps the
//! absolute position. The field host scaled steps by a hidden factor; here the configured
//! `steps_per_turn` is the board's own unit, with no hidden scaling.

use std::time::{Duration, Instant};

use super::{BoardInfo, Dialect, Timing};
use crate::devices::serial::error::LinkError;
use crate::devices::serial::link::Link;

/// Longest output of one command before its prompt, bytes: a board that streams without ever
/// printing the prompt is a protocol error, not a growing buffer.
pub const MAX_REPLY: usize = 4096;

/// The FabScan dialect.
#[derive(Debug)]
pub struct FabScanDialect {
    timing: Timing,
    steps_per_turn: u32,
    lasers: usize,
    speed_steps_per_s: u32,
    position: i64,
}

impl FabScanDialect {
    /// A dialect for a board with `steps_per_turn` and `lasers` (up to 2) and one LED ring.
    pub fn new(timing: Timing, steps_per_turn: u32, lasers: usize, speed_deg_per_s: f64) -> Self {
        let speed = (speed_deg_per_s * f64::from(steps_per_turn) / 360.0).round().clamp(1.0, 1e6) as u32;
        FabScanDialect {
            timing,
            steps_per_turn: steps_per_turn.max(1),
            lasers: lasers.min(2),
            speed_steps_per_s: speed,
            position: 0,
        }
    }

    /// Send `line`, wait for the prompt, return the output without the echo.
    fn command(&mut self, link: &mut Link, line: &str, timeout: Duration) -> Result<Vec<String>, LinkError> {
        link.send(format!("{line}\n").as_bytes())?;
        let deadline = Instant::now() + timeout;
        let mut text = Vec::new();
        loop {
            let b = link.read_byte(deadline, "the prompt", timeout)?;
            if b == b'>' && (text.is_empty() || text.last() == Some(&b'\n')) {
                break;
            }
            if text.len() >= MAX_REPLY {
                // Drop the rest of the flood (bounded by the reply timeout) so that the next
                // command starts on a quiet line.
                link.discard_input(self.timing.reply_timeout)?;
                return Err(LinkError::Unexpected {
                    line: format!("more than {MAX_REPLY} bytes without the `>` prompt"),
                });
            }
            text.push(b);
        }
        let text = String::from_utf8_lossy(&text).into_owned();
        Ok(text
            .split(['\r', '\n'])
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.eq_ignore_ascii_case(line.trim()))
            .map(str::to_owned)
            .collect())
    }
}

impl Dialect for FabScanDialect {
    fn name(&self) -> &'static str {
        "fabscan"
    }

    fn handshake(&mut self, link: &mut Link) -> Result<BoardInfo, LinkError> {
        let mut last = LinkError::Timeout { waiting_for: "the M200 version", timeout: self.timing.reply_timeout };
        for attempt in 0..self.timing.handshake_attempts.max(1) {
            tracing::debug!(attempt, "fabscan handshake");
            link.send(b"\r\n\r\n")?;
            link.discard_input(self.timing.boot)?;
            match self.command(link, "M200", self.timing.reply_timeout) {
                Ok(lines) if !lines.is_empty() => {
                    let version = lines.join(" ");
                    self.position = 0;
                    return Ok(BoardInfo {
                        name: "fabscanpi".into(),
                        firmware: version,
                        steps_per_turn: self.steps_per_turn,
                        lights: 1,
                        lasers: self.lasers,
                        pwm: true,
                        home: false,
                        position_steps: 0,
                    });
                }
                Ok(_) => last = LinkError::Unexpected { line: "empty answer to M200".into() },
                Err(e @ LinkError::Timeout { .. }) => last = e,
                Err(e) => return Err(e),
            }
        }
        Err(last)
    }

    fn move_to(&mut self, link: &mut Link, steps: i64, timeout: Duration) -> Result<i64, LinkError> {
        let delta = steps - self.position;
        if delta != 0 {
            self.command(link, &format!("G01 T{delta} F{}", self.speed_steps_per_s), timeout)?;
            self.position = steps;
        }
        Ok(self.position)
    }

    fn set_light(&mut self, link: &mut Link, index: usize, level: u8) -> Result<(), LinkError> {
        if index != 0 {
            return Err(LinkError::Board { code: 4, text: format!("no light {index}: the LED ring is light 0") });
        }
        let line = if level == 0 { "M05".to_owned() } else { format!("M04 R{level} G{level} B{level}") };
        self.command(link, &line, self.timing.reply_timeout).map(drop)
    }

    fn set_laser(&mut self, link: &mut Link, index: usize, on: bool) -> Result<(), LinkError> {
        let code = match (index, on) {
            (0, true) => "M19",
            (0, false) => "M20",
            (1, true) if self.lasers > 1 => "M21",
            (1, false) if self.lasers > 1 => "M22",
            _ => return Err(LinkError::Board { code: 4, text: format!("no laser {index}") }),
        };
        self.command(link, code, self.timing.reply_timeout).map(drop)
    }

    fn motor(&mut self, link: &mut Link, on: bool) -> Result<(), LinkError> {
        self.command(link, if on { "M17" } else { "M18" }, self.timing.reply_timeout).map(drop)
    }
}
