//! A FabScanPi board as the field knows it: it echoes every byte, prints `>` when a line is done,
//! never says `ok` or reports an error, and blocks in turntable moves given in steps.

use std::sync::Arc;
use std::time::Instant;

use super::{Action, BoardModel, EmulatedHardware, EmulatorSettings, Faults, Motion, MotionFault, OutKind, Outbox};

pub(super) struct FabScanBoard {
    s: EmulatorSettings,
    hw: Arc<dyn EmulatedHardware>,
    line: Vec<u8>,
    pos: i64,
    motion: Option<Motion>,
}

impl FabScanBoard {
    pub(super) fn new(s: EmulatorSettings, hw: Arc<dyn EmulatedHardware>) -> Self {
        FabScanBoard { s, hw, line: Vec::new(), pos: 0, motion: None }
    }

    fn arg(words: &[&str], key: char) -> Option<i64> {
        words.iter().find_map(|w| w.strip_prefix(key)).and_then(|v| v.parse().ok())
    }

    fn run_line(&mut self, line: &str, now: Instant, out: &mut Outbox, faults: &Faults) -> Action {
        let upper = line.trim().to_ascii_uppercase();
        let words: Vec<&str> = upper.split_whitespace().collect();
        let prompt = |out: &mut Outbox| out.push(OutKind::Reply, b"\r\n>".to_vec());
        match words.first().copied().unwrap_or("") {
            "G01" | "G02" | "G1" | "G2" => {
                if let Some(t) = Self::arg(&words, 'T') {
                    match faults.on_motion() {
                        MotionFault::Reset => return Action::Reset,
                        MotionFault::Unplug => return Action::None,
                        MotionFault::None => {}
                    }
                    // Blocks: the prompt comes when the motion has ended.
                    self.motion = Some(Motion::new(self.pos, self.pos + t, now, &self.s, faults));
                    return Action::None;
                }
            }
            "M19" => self.hw.set_laser(0, true),
            "M20" => self.hw.set_laser(0, false),
            "M21" if self.s.lasers > 1 => self.hw.set_laser(1, true),
            "M22" if self.s.lasers > 1 => self.hw.set_laser(1, false),
            "M04" => {
                let level = ['R', 'G', 'B'].iter().filter_map(|&k| Self::arg(&words, k)).max().unwrap_or(0);
                self.hw.set_light(0, level.clamp(0, 255) as f32 / 255.0);
            }
            "M05" => self.hw.set_light(0, 0.0),
            "M200" => out.push(OutKind::Other, b"\r\nv.20190101-emu".to_vec()),
            "M201" => out.push(OutKind::Other, b"\r\nFabScanPi-emu".to_vec()),
            // M17/M18 motor, M23/M24 fan, anything unknown: silently accepted, as the firmware does.
            _ => {}
        }
        prompt(out);
        Action::None
    }
}

impl BoardModel for FabScanBoard {
    fn banner(&mut self, _out: &mut Outbox) {}

    fn byte(&mut self, b: u8, now: Instant, out: &mut Outbox, faults: &Faults) -> Action {
        if self.motion.is_some() {
            // Busy in a blocking move: bytes are lost, as on the real board.
            return Action::None;
        }
        out.push(OutKind::Other, vec![b]);
        match b {
            b'\n' | b'\r' => {
                let line = String::from_utf8_lossy(&std::mem::take(&mut self.line)).into_owned();
                if !line.trim().is_empty() {
                    return self.run_line(&line, now, out, faults);
                }
            }
            _ if self.line.len() < 80 => self.line.push(b),
            _ => {}
        }
        Action::None
    }

    fn tick(&mut self, now: Instant, out: &mut Outbox, _faults: &Faults) {
        if let Some(m) = self.motion {
            if m.done(now) {
                self.motion = None;
                self.pos = m.to;
                self.hw.set_angle(self.pos as f64 * 360.0 / f64::from(self.s.steps_per_turn.max(1)));
                out.push(OutKind::Completion, b"\r\n>".to_vec());
            }
        }
    }
}
