//! Horus firmware (GRBL 0.9 derivative) used by Ciclop-style scanners.
//!
//! Quirks handled here: `ok` after `G1` means *queued*, not done, so completion is found by polling
//! `?` until the board reports `Idle` at the target; empty lines get no reply, so none are sent;
//! angles go on the wire as absolute degrees and the board's own step scaling (`$100`, steps per
//! degree) is checked against the configured steps per turn; lasers are numbered from 1 there.
//! Every wait is bounded, unlike the field host, which polls forever.

use std::time::{Duration, Instant};

use super::{read_text_line, BoardInfo, Dialect, Timing};
use crate::devices::serial::error::LinkError;
use crate::devices::serial::link::Link;

/// Most lines one command may print before its `ok`: a board that streams lines for ever is a
/// protocol error, not a growing list.
pub const MAX_LINES: usize = 64;

/// The Horus dialect.
#[derive(Debug)]
pub struct HorusDialect {
    timing: Timing,
    steps_per_turn: u32,
    lasers: usize,
    speed_deg_per_s: f64,
}

impl HorusDialect {
    /// A dialect for a board with `steps_per_turn` and `lasers`, turning at `speed_deg_per_s`.
    pub fn new(timing: Timing, steps_per_turn: u32, lasers: usize, speed_deg_per_s: f64) -> Self {
        HorusDialect { timing, steps_per_turn: steps_per_turn.max(1), lasers, speed_deg_per_s }
    }

    /// Send a line and collect the lines before its `ok`; `error:`/`ALARM:` become errors.
    fn command(&mut self, link: &mut Link, line: &str, timeout: Duration) -> Result<Vec<String>, LinkError> {
        link.send(format!("{line}\n").as_bytes())?;
        let deadline = Instant::now() + timeout;
        let mut lines = Vec::new();
        loop {
            let l = read_text_line(link, deadline, "a reply", timeout, 120)?;
            let t = after_noise(&l);
            if t == "ok" {
                return Ok(lines);
            } else if let Some(text) = t.strip_prefix("error:") {
                return Err(LinkError::Board { code: 2, text: text.trim().to_owned() });
            } else if let Some(text) = t.strip_prefix("ALARM:") {
                return Err(LinkError::Board { code: 8, text: text.trim().to_owned() });
            } else if t.starts_with("Horus") || t.starts_with("Grbl") {
                return Err(LinkError::BoardReset);
            } else if !t.is_empty() {
                if lines.len() >= MAX_LINES {
                    return Err(LinkError::Unexpected { line: format!("more than {MAX_LINES} lines without `ok`") });
                }
                lines.push(t.to_owned());
            }
        }
    }

    /// Ask `?` and return (idle, position in degrees).
    fn status(&mut self, link: &mut Link, timeout: Duration) -> Result<(bool, f64), LinkError> {
        link.send(b"?")?;
        let deadline = Instant::now() + timeout;
        loop {
            let l = read_text_line(link, deadline, "a status report", timeout, 160)?;
            let t = after_noise(&l);
            if t.starts_with("Horus") || t.starts_with("Grbl") {
                return Err(LinkError::BoardReset);
            }
            if let Some(body) = t.strip_prefix('<').and_then(|b| b.strip_suffix('>')) {
                let state = body.split([',', '|']).next().unwrap_or("");
                let x = body
                    .split("MPos:")
                    .nth(1)
                    .and_then(|p| p.split(',').next())
                    .and_then(|v| v.parse::<f64>().ok())
                    .ok_or_else(|| LinkError::Unexpected { line: t.to_owned() })?;
                return Ok((state == "Idle", x));
            }
        }
    }

    fn degrees_to_steps(&self, deg: f64) -> i64 {
        (deg * f64::from(self.steps_per_turn) / 360.0).round() as i64
    }
}

impl Dialect for HorusDialect {
    fn name(&self) -> &'static str {
        "horus"
    }

    fn handshake(&mut self, link: &mut Link) -> Result<BoardInfo, LinkError> {
        let mut last = LinkError::Timeout { waiting_for: "the Horus banner", timeout: self.timing.boot };
        for attempt in 0..self.timing.handshake_attempts.max(1) {
            if attempt > 0 {
                link.send(&[0x18])?;
            }
            let deadline = Instant::now() + self.timing.boot;
            let mut banner = None;
            while banner.is_none() {
                match read_text_line(link, deadline, "the Horus banner", self.timing.boot, 120) {
                    Ok(l) if l.contains("Horus") || l.contains("Grbl") => banner = Some(l.trim().to_owned()),
                    Ok(_) => {}
                    Err(LinkError::Timeout { .. }) => break,
                    Err(e) => return Err(e),
                }
            }
            // No banner: the board may not have been reset by the open; `$$` tells.
            let settings = match self.command(link, "$$", self.timing.reply_timeout) {
                Ok(s) => s,
                Err(e @ (LinkError::Timeout { .. } | LinkError::BoardReset)) => {
                    last = e;
                    continue;
                }
                Err(e) => return Err(e),
            };
            if let Some(spd) = settings.iter().find_map(|s| s.strip_prefix("$100=")).and_then(|v| v.parse::<f64>().ok())
            {
                let want = f64::from(self.steps_per_turn) / 360.0;
                if (spd - want).abs() > want * 0.005 {
                    return Err(LinkError::Mismatch {
                        problem: format!(
                            "board is set to {spd} steps per degree ($100), the config's steps_per_turn gives {want:.3}"
                        ),
                    });
                }
            }
            let (_, x) = self.status(link, self.timing.reply_timeout)?;
            return Ok(BoardInfo {
                name: banner.unwrap_or_else(|| "horus".into()),
                firmware: "grbl-0.9-derived".into(),
                steps_per_turn: self.steps_per_turn,
                lights: 0,
                lasers: self.lasers,
                pwm: false,
                home: false,
                position_steps: self.degrees_to_steps(x),
            });
        }
        Err(last)
    }

    fn move_to(&mut self, link: &mut Link, steps: i64, timeout: Duration) -> Result<i64, LinkError> {
        let deadline = Instant::now() + timeout;
        let deg = steps as f64 * 360.0 / f64::from(self.steps_per_turn);
        let feed = self.speed_deg_per_s * 60.0;
        self.command(link, &format!("G1 X{deg:.3} F{feed:.0}"), self.timing.reply_timeout.min(timeout))?;
        // `ok` only means queued: poll until the board is idle.
        loop {
            let now = Instant::now();
            if now >= deadline {
                let _ = link.send(b"!");
                return Err(LinkError::Timeout { waiting_for: "the motion to finish", timeout });
            }
            let (idle, x) = self.status(link, self.timing.reply_timeout.min(deadline - now))?;
            if idle {
                let reached = self.degrees_to_steps(x);
                if (reached - steps).abs() > 1 {
                    return Err(LinkError::Stopped { id: 0, pos: reached });
                }
                return Ok(reached);
            }
            std::thread::sleep(
                self.timing.poll_interval.min(Duration::from_millis(20)).min(deadline - Instant::now().min(deadline)),
            );
        }
    }

    fn set_light(&mut self, _link: &mut Link, _index: usize, _level: u8) -> Result<(), LinkError> {
        Err(LinkError::Board { code: 4, text: "Horus boards have no white lights".into() })
    }

    fn set_laser(&mut self, link: &mut Link, index: usize, on: bool) -> Result<(), LinkError> {
        if index >= self.lasers {
            return Err(LinkError::Board { code: 4, text: format!("no laser {index}") });
        }
        // The board runs laser commands after the queued motion: allow for that.
        let code = if on { 71 } else { 70 };
        self.command(link, &format!("M{code} T{}", index + 1), self.timing.reply_timeout * 4).map(drop)
    }

    fn motor(&mut self, link: &mut Link, on: bool) -> Result<(), LinkError> {
        self.command(link, if on { "M17" } else { "M18" }, self.timing.reply_timeout).map(drop)
    }
}

/// The part of a line after the last byte that line noise leaves (control or non-ASCII bytes, shown
/// as U+FFFD after lossy decoding), trimmed: GRBL-style boards cannot resend, so a reply glued to
/// noise is still read when it can be.
fn after_noise(line: &str) -> &str {
    let start = line
        .rfind(|c: char| c.is_control() || !c.is_ascii())
        .map_or(0, |i| i + line[i..].chars().next().map_or(1, char::len_utf8));
    line[start..].trim()
}

#[cfg(test)]
mod tests {
    use super::after_noise;

    #[test]
    fn noise_before_a_reply_is_cut_off() {
        assert_eq!(after_noise("ok"), "ok");
        assert_eq!(after_noise("\u{0}\u{FFFD}#~%\u{7f}ok"), "ok");
        assert_eq!(after_noise("  <Idle,MPos:1.000,0,0>  "), "<Idle,MPos:1.000,0,0>");
        assert_eq!(after_noise("\u{7f}"), "");
    }
}
