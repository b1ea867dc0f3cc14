//! A Horus (GRBL 0.9-derived) board as the field knows it: banner `Horus 0.2 ['$' for help]`, `ok`
//! meaning "queued" for motion, laser commands that wait for motion to end, `?` status reports.

use std::sync::Arc;
use std::time::Instant;

use super::{Action, BoardModel, EmulatedHardware, EmulatorSettings, Faults, Motion, MotionFault, OutKind, Outbox};

pub(super) struct HorusBoard {
    s: EmulatorSettings,
    hw: Arc<dyn EmulatedHardware>,
    line: Vec<u8>,
    pos: i64,
    motion: Option<Motion>,
    /// A command waiting for the motion to end before it runs (Horus's laser barrier).
    blocked: Option<Vec<u8>>,
    held: bool,
}

impl HorusBoard {
    pub(super) fn new(s: EmulatorSettings, hw: Arc<dyn EmulatedHardware>) -> Self {
        HorusBoard { s, hw, line: Vec::new(), pos: 0, motion: None, blocked: None, held: false }
    }

    fn steps_per_degree(&self) -> f64 {
        f64::from(self.s.steps_per_turn) / 360.0
    }

    fn degrees(&self, steps: i64) -> f64 {
        steps as f64 / self.steps_per_degree()
    }

    fn reply(out: &mut Outbox, text: &str) {
        out.push(OutKind::Reply, format!("{text}\r\n").into_bytes());
    }

    fn laser(&self, cmd: &str, on: bool, out: &mut Outbox) {
        match cmd.split_whitespace().nth(1).and_then(|t| t.strip_prefix('T')).and_then(|n| n.parse::<usize>().ok()) {
            Some(n) if n >= 1 && n <= usize::from(self.s.lasers) => {
                self.hw.set_laser(n - 1, on);
                Self::reply(out, "ok");
            }
            _ => Self::reply(out, "error: Invalid laser"),
        }
    }

    fn run_line(&mut self, line: &str, now: Instant, out: &mut Outbox, faults: &Faults) -> Action {
        let upper = line.trim().to_ascii_uppercase();
        let word = upper.split_whitespace().next().unwrap_or("");
        if matches!(word, "M70" | "M71" | "M50") && self.motion.is_some() {
            self.blocked = Some(upper.into_bytes());
            return Action::None;
        }
        match word {
            "" => {}
            "G1" | "G01" => {
                let x = upper.split_whitespace().find_map(|w| w.strip_prefix('X')).and_then(|v| v.parse::<f64>().ok());
                match x {
                    Some(deg) if deg.is_finite() && deg.abs() < 1e6 => {
                        match faults.on_motion() {
                            MotionFault::Reset => return Action::Reset,
                            MotionFault::Unplug => return Action::None,
                            MotionFault::None => {}
                        }
                        if self.motion.is_some() {
                            // GRBL queues; one queued move is enough for this emulator.
                            Self::reply(out, "error: Queue full");
                            return Action::None;
                        }
                        let target = (deg * self.steps_per_degree()).round() as i64;
                        self.motion = Some(Motion::new(self.pos, target, now, &self.s, faults));
                        Self::reply(out, "ok");
                    }
                    _ => Self::reply(out, "error: Bad number format"),
                }
            }
            "G50" => {
                self.pos = 0;
                Self::reply(out, "ok");
            }
            "M17" | "M18" => Self::reply(out, "ok"),
            "M70" => self.laser(&upper, false, out),
            "M71" => self.laser(&upper, true, out),
            "M50" => {
                out.push(OutKind::Other, b"0\r\n".to_vec());
                Self::reply(out, "ok");
            }
            "$$" => {
                out.push(
                    OutKind::Other,
                    format!("$100={:.3}\r\n$110=200.000\r\n", self.steps_per_degree()).into_bytes(),
                );
                Self::reply(out, "ok");
            }
            _ => Self::reply(out, "error: Unsupported statement"),
        }
        Action::None
    }
}

impl BoardModel for HorusBoard {
    fn banner(&mut self, out: &mut Outbox) {
        out.push(OutKind::Other, b"\r\nHorus 0.2 ['$' for help]\r\n".to_vec());
    }

    fn byte(&mut self, b: u8, now: Instant, out: &mut Outbox, faults: &Faults) -> Action {
        match b {
            b'?' => {
                let state = if self.motion.is_some() { "Run" } else { "Idle" };
                let pos = self.motion.map_or(self.pos, |m| m.position(now));
                let d = self.degrees(pos);
                out.push(
                    OutKind::Other,
                    format!("<{state},MPos:{d:.3},0.000,0.000,WPos:{d:.3},0.000,0.000>\r\n").into_bytes(),
                );
            }
            b'!' => self.held = true,
            b'~' => self.held = false,
            0x18 => return Action::Reset,
            b'\n' | b'\r' => {
                let line = String::from_utf8_lossy(&std::mem::take(&mut self.line)).into_owned();
                if !line.trim().is_empty() && self.blocked.is_none() {
                    return self.run_line(&line, now, out, faults);
                }
            }
            _ if self.line.len() < 80 => self.line.push(b),
            _ => {}
        }
        Action::None
    }

    fn tick(&mut self, now: Instant, out: &mut Outbox, faults: &Faults) {
        if self.held {
            return;
        }
        if let Some(m) = self.motion {
            if m.done(now) {
                self.motion = None;
                self.pos = m.to;
                self.hw.set_angle(self.degrees(self.pos));
                if let Some(cmd) = self.blocked.take() {
                    let line = String::from_utf8_lossy(&cmd).into_owned();
                    let _ = self.run_line(&line, now, out, faults);
                }
            }
        }
    }
}
