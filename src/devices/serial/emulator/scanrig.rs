//! The scanrig protocol v1 board, as PROTOCOL.md specifies it.

use std::sync::Arc;
use std::time::{Duration, Instant};

use firmware_protocol::{
    realtime, BoardMessage, Caps, Command, CommandDecoder, DecodeError, ErrorCode, Event, Identity, Input, MotionState,
    OkPayload, Rejected, SafetyReason, Text, PROTOCOL_VERSION,
};

use super::{Action, BoardModel, EmulatedHardware, EmulatorSettings, Faults, Motion, MotionFault, OutKind, Outbox};

#[derive(Debug, Clone, Copy)]
struct RunningMotion {
    id: u16,
    motion: Motion,
}

pub(super) struct ScanrigBoard {
    s: EmulatorSettings,
    hw: Arc<dyn EmulatedHardware>,
    decoder: CommandDecoder,
    checksum_mode: bool,
    pos: i64,
    motion: Option<RunningMotion>,
    last_move: u16,
    /// Last numbered line executed and the reply it got.
    last_line: Option<(u16, BoardMessage)>,
    lasers_on_since: Vec<Option<Instant>>,
    motor_on: bool,
    motor_idle_since: Instant,
    last_host_byte: Instant,
    watchdog_tripped: bool,
    laser_s: u16,
    idle_ms: u32,
    watchdog_ms: u32,
}

impl ScanrigBoard {
    pub(super) fn new(s: EmulatorSettings, hw: Arc<dyn EmulatedHardware>) -> Self {
        let now = Instant::now();
        ScanrigBoard {
            s,
            hw,
            decoder: CommandDecoder::new(),
            checksum_mode: false,
            pos: 0,
            motion: None,
            last_move: 0,
            last_line: None,
            lasers_on_since: vec![None; usize::from(s.lasers)],
            motor_on: false,
            motor_idle_since: now,
            last_host_byte: now,
            watchdog_tripped: false,
            laser_s: 255,
            idle_ms: 10_000,
            watchdog_ms: 0,
        }
    }

    fn identity(&self) -> Identity {
        Identity {
            proto: PROTOCOL_VERSION,
            name: Text::from_str("scanrig-emulator"),
            fw: Text::from_str(env!("CARGO_PKG_VERSION")),
        }
    }

    fn send(&self, out: &mut Outbox, kind: OutKind, msg: &BoardMessage) {
        if let Ok(bytes) = msg.to_line(self.checksum_mode) {
            out.push(kind, bytes);
        }
    }

    fn angle_of(&self, steps: i64) -> f64 {
        steps as f64 * 360.0 / f64::from(self.s.steps_per_turn.max(1))
    }

    fn steps_of(&self, millideg: i32) -> i64 {
        (f64::from(millideg) / 1000.0 * f64::from(self.s.steps_per_turn) / 360.0).round() as i64
    }

    fn position(&self, now: Instant) -> i64 {
        self.motion.map_or(self.pos, |m| m.motion.position(now))
    }

    fn stop(&mut self, now: Instant, out: &mut Outbox) {
        if let Some(m) = self.motion.take() {
            self.pos = m.motion.position(now);
            self.hw.set_angle(self.angle_of(self.pos));
            let msg = BoardMessage::Event(Event::Stopped { id: m.id, pos: self.pos as i32 });
            self.send(out, OutKind::Completion, &msg);
        }
        self.motor_idle_since = now;
    }

    fn lasers_off(&mut self) {
        for (i, l) in self.lasers_on_since.iter_mut().enumerate() {
            if l.take().is_some() {
                self.hw.set_laser(i, false);
            }
        }
    }

    fn everything_off(&mut self, now: Instant, out: &mut Outbox) {
        self.stop(now, out);
        for i in 0..usize::from(self.s.lights) {
            self.hw.set_light(i, 0.0);
        }
        self.lasers_off();
        self.motor_on = false;
    }

    fn execute(
        &mut self,
        cmd: Command,
        now: Instant,
        out: &mut Outbox,
        faults: &Faults,
    ) -> Result<OkPayload, (ErrorCode, Text)> {
        let start_motion = |b: &mut Self, target: i64, out: &mut Outbox| {
            if b.motion.is_some() {
                return Err((ErrorCode::Busy, Text::from_str("busy")));
            }
            if target.abs() > i64::from(i32::MAX) {
                return Err((ErrorCode::BadArgument, Text::from_str("bad argument")));
            }
            b.last_move = b.last_move.checked_add(1).unwrap_or(1);
            b.motor_on = true;
            let motion = Motion::new(b.pos, target, now, &b.s, faults);
            b.motion = Some(RunningMotion { id: b.last_move, motion });
            let _ = out;
            Ok(OkPayload::MoveStarted { id: b.last_move, target: target as i32 })
        };
        match cmd {
            Command::Id => Ok(OkPayload::Identity(self.identity())),
            Command::Caps => Ok(OkPayload::Caps(Caps {
                steps_per_turn: self.s.steps_per_turn,
                lights: self.s.lights,
                lasers: self.s.lasers,
                pwm: true,
                home: false,
                trigger: true,
            })),
            Command::Pos => Ok(OkPayload::Position { steps: self.position(now) as i32, moving: self.motion.is_some() }),
            Command::Move(a) => {
                let target = self.steps_of(a.0);
                start_motion(self, target, out)
            }
            Command::Turn(a) => {
                let base = self.motion.map_or(self.pos, |m| m.motion.to);
                let target = base + self.steps_of(a.0);
                start_motion(self, target, out)
            }
            Command::Home => Err((ErrorCode::Unsupported, Text::from_str("no end stop"))),
            Command::Zero => {
                if self.motion.is_some() {
                    return Err((ErrorCode::Busy, Text::from_str("busy")));
                }
                self.pos = 0;
                Ok(OkPayload::Empty)
            }
            Command::Motor(on) => {
                if !on && self.motion.is_some() {
                    return Err((ErrorCode::Busy, Text::from_str("busy")));
                }
                self.motor_on = on;
                self.motor_idle_since = now;
                Ok(OkPayload::Empty)
            }
            Command::Light { index, level } => {
                if index >= self.s.lights {
                    return Err((ErrorCode::Unsupported, Text::from_str(&format!("no light {index}"))));
                }
                self.hw.set_light(usize::from(index), f32::from(level) / 255.0);
                Ok(OkPayload::Empty)
            }
            Command::Laser { index, on } => {
                let Some(slot) = self.lasers_on_since.get_mut(usize::from(index)) else {
                    return Err((ErrorCode::Unsupported, Text::from_str(&format!("no laser {index}"))));
                };
                *slot = on.then_some(now);
                self.hw.set_laser(usize::from(index), on);
                Ok(OkPayload::Empty)
            }
            Command::Trigger { .. } => Ok(OkPayload::Empty),
            Command::Safety { laser_s, idle_ms, watchdog_ms } => {
                self.laser_s = laser_s;
                self.idle_ms = idle_ms;
                self.watchdog_ms = watchdog_ms;
                Ok(OkPayload::Empty)
            }
            Command::Off => {
                self.everything_off(now, out);
                Ok(OkPayload::Empty)
            }
        }
    }
}

impl BoardModel for ScanrigBoard {
    fn banner(&mut self, out: &mut Outbox) {
        let msg = BoardMessage::Event(Event::Ready(self.identity()));
        self.send(out, OutKind::Other, &msg);
    }

    fn byte(&mut self, b: u8, now: Instant, out: &mut Outbox, faults: &Faults) -> Action {
        self.last_host_byte = now;
        self.watchdog_tripped = false;
        let Some(input) = self.decoder.push(b) else { return Action::None };
        match input {
            Input::RealTime(realtime::RESET) => return Action::Reset,
            Input::RealTime(realtime::STOP) => {
                self.stop(now, out);
                self.lasers_off();
            }
            Input::RealTime(_) => {
                let state = if self.motion.is_some() { MotionState::Moving } else { MotionState::Idle };
                let msg = BoardMessage::Event(Event::Status {
                    state,
                    pos: self.position(now) as i32,
                    last_move: self.last_move,
                });
                self.send(out, OutKind::Other, &msg);
            }
            Input::Line(Err(Rejected { line, error: e })) => {
                // The same short texts as the reference firmware.
                let text = match e {
                    DecodeError::Overflow => "line too long",
                    DecodeError::NotAscii => "not printable ASCII",
                    DecodeError::Checksum { .. } => "bad checksum",
                    DecodeError::Unknown => "unknown command",
                    DecodeError::BadArgument => "bad argument",
                };
                let msg = BoardMessage::Error { line, code: e.error_code(), text: Text::from_str(text) };
                self.send(out, OutKind::Reply, &msg);
            }
            Input::Line(Ok((framing, cmd))) => {
                if framing.checksum {
                    self.checksum_mode = true;
                }
                if let (Some(n), Some((last, reply))) = (framing.line, self.last_line) {
                    if n == last {
                        self.send(out, OutKind::Reply, &reply);
                        return Action::None;
                    }
                }
                if cmd.is_motion() && self.motion.is_none() {
                    match faults.on_motion() {
                        MotionFault::Reset => return Action::Reset,
                        MotionFault::Unplug => return Action::None,
                        MotionFault::None => {}
                    }
                }
                let line = framing.line;
                let reply = match self.execute(cmd, now, out, faults) {
                    Ok(payload) => BoardMessage::Ok { line, payload },
                    Err((code, text)) => BoardMessage::Error { line, code, text },
                };
                if let Some(n) = line {
                    self.last_line = Some((n, reply));
                }
                self.send(out, OutKind::Reply, &reply);
            }
        }
        Action::None
    }

    fn tick(&mut self, now: Instant, out: &mut Outbox, _faults: &Faults) {
        if let Some(m) = self.motion {
            if m.motion.done(now) {
                self.motion = None;
                self.pos = m.motion.to;
                self.motor_idle_since = now;
                self.hw.set_angle(self.angle_of(self.pos));
                let msg = BoardMessage::Event(Event::Done { id: m.id, pos: self.pos as i32 });
                self.send(out, OutKind::Completion, &msg);
            }
        }
        if self.laser_s > 0 {
            let limit = Duration::from_secs(u64::from(self.laser_s));
            for i in 0..self.lasers_on_since.len() {
                if self.lasers_on_since[i].is_some_and(|t| now.duration_since(t) >= limit) {
                    self.lasers_on_since[i] = None;
                    self.hw.set_laser(i, false);
                    self.send(
                        out,
                        OutKind::Other,
                        &BoardMessage::Event(Event::SafetyOff(SafetyReason::Laser(i as u8))),
                    );
                }
            }
        }
        if self.idle_ms > 0
            && self.motor_on
            && self.motion.is_none()
            && now.duration_since(self.motor_idle_since) >= Duration::from_millis(u64::from(self.idle_ms))
        {
            self.motor_on = false;
            self.send(out, OutKind::Other, &BoardMessage::Event(Event::SafetyOff(SafetyReason::MotorIdle)));
        }
        if self.watchdog_ms > 0
            && !self.watchdog_tripped
            && now.duration_since(self.last_host_byte) >= Duration::from_millis(u64::from(self.watchdog_ms))
        {
            self.watchdog_tripped = true;
            self.everything_off(now, out);
            self.send(out, OutKind::Other, &BoardMessage::Event(Event::SafetyOff(SafetyReason::Watchdog)));
        }
    }
}

impl std::fmt::Debug for ScanrigBoard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScanrigBoard").field("pos", &self.pos).field("last_move", &self.last_move).finish()
    }
}
