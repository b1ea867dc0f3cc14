//! The scanrig protocol v1 (`firmware-protocol/PROTOCOL.md`): line numbers and checksums on every
//! line, retries that the board answers without acting twice, explicit motion completion.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use firmware_protocol::{
    realtime, BoardDecoder, BoardMessage, Command, DecodeError, Event, Framing, Millideg, MotionState, OkPayload,
    SafetyReason, PROTOCOL_VERSION,
};

use super::{BoardInfo, Dialect, Timing};
use crate::devices::serial::error::LinkError;
use crate::devices::serial::link::Link;

/// Safety limits sent to the board with `SAFE` after every handshake.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SafetyLimits {
    /// Laser auto-off, seconds (0 = none).
    pub laser_s: u16,
    /// Motor release after this idle time, milliseconds (0 = never).
    pub idle_ms: u32,
    /// Everything off after this much host silence, milliseconds (0 = off).
    pub watchdog_ms: u32,
}

impl Default for SafetyLimits {
    fn default() -> Self {
        SafetyLimits { laser_s: 255, idle_ms: 10_000, watchdog_ms: 0 }
    }
}

/// The scanrig dialect.
#[derive(Debug)]
pub struct ScanrigDialect {
    timing: Timing,
    checksum: bool,
    safety: SafetyLimits,
    next_line: u16,
    decoder: BoardDecoder,
    events: VecDeque<Event>,
    steps_per_turn: u32,
}

impl ScanrigDialect {
    /// A dialect with these timings; `checksum` adds a checksum to every line.
    pub fn new(timing: Timing, checksum: bool, safety: SafetyLimits) -> Self {
        ScanrigDialect {
            timing,
            checksum,
            safety,
            next_line: 1,
            decoder: BoardDecoder::new(),
            events: VecDeque::new(),
            steps_per_turn: 0,
        }
    }

    fn read_message(
        &mut self,
        link: &mut Link,
        deadline: Instant,
        waiting_for: &'static str,
        timeout: Duration,
    ) -> Result<Result<BoardMessage, DecodeError>, LinkError> {
        loop {
            let b = link.read_byte(deadline, waiting_for, timeout)?;
            if let Some(r) = self.decoder.push(b) {
                if let Err(e) = &r {
                    tracing::debug!(error = %e, "undecodable line from board");
                }
                return Ok(r.map(|(_, m)| m));
            }
        }
    }

    fn note_event(&mut self, e: Event) -> Result<(), LinkError> {
        match e {
            Event::Ready(_) => return Err(LinkError::BoardReset),
            Event::SafetyOff(r) => match r {
                SafetyReason::Laser(i) => tracing::warn!(laser = i, "board switched a laser off (time limit)"),
                SafetyReason::MotorIdle => tracing::debug!("board released the idle motor"),
                SafetyReason::Watchdog => tracing::warn!("board watchdog: everything off after host silence"),
            },
            Event::Status { .. } => {}
            Event::Done { .. } | Event::Stopped { .. } => {
                if self.events.len() >= 16 {
                    self.events.pop_front();
                }
                self.events.push_back(e);
            }
        }
        Ok(())
    }

    /// Send one command and wait for its terminal reply, resending the same line number after a lost
    /// or damaged reply.
    pub fn exchange(&mut self, link: &mut Link, cmd: Command) -> Result<OkPayload, LinkError> {
        let n = self.next_line;
        self.next_line = self.next_line.checked_add(1).unwrap_or(1);
        let line = cmd
            .to_line(Framing { line: Some(n), checksum: self.checksum })
            .map_err(|_| LinkError::Unexpected { line: format!("{cmd:?} does not fit a line") })?;
        let timeout = self.timing.reply_timeout;
        let mut last = LinkError::Timeout { waiting_for: "a reply", timeout };
        for attempt in 0..=self.timing.retries {
            if attempt > 0 {
                tracing::debug!(attempt, line = n, error = %last, "resending line");
            }
            link.send(&line)?;
            let deadline = Instant::now() + timeout;
            loop {
                match self.read_message(link, deadline, "a reply", timeout) {
                    Err(e @ LinkError::Timeout { .. }) => {
                        last = e;
                        break;
                    }
                    Err(e) => return Err(e),
                    Ok(Err(source)) => {
                        last = LinkError::Decode { source };
                        break;
                    }
                    Ok(Ok(BoardMessage::Ok { line: Some(m), payload })) if m == n => return Ok(payload),
                    Ok(Ok(BoardMessage::Error { line, code, text })) if line == Some(n) || line.is_none() => {
                        if code.is_transmission() {
                            last = LinkError::Board { code: code.code(), text: text.to_string() };
                            break;
                        }
                        if line.is_none() {
                            // Not ours: a stale answer to a damaged earlier line.
                            continue;
                        }
                        return Err(LinkError::Board { code: code.code(), text: text.to_string() });
                    }
                    Ok(Ok(BoardMessage::Event(e))) => self.note_event(e)?,
                    Ok(Ok(other)) => tracing::debug!(?other, "ignoring a stale reply"),
                }
            }
        }
        Err(last)
    }

    fn await_motion(&mut self, link: &mut Link, id: u16, timeout: Duration) -> Result<i64, LinkError> {
        let deadline = Instant::now() + timeout;
        loop {
            while let Some(e) = self.events.pop_front() {
                match e {
                    Event::Done { id: got, pos } if got == id => return Ok(i64::from(pos)),
                    Event::Stopped { id: got, pos } if got == id => {
                        return Err(LinkError::Stopped { id, pos: pos.into() })
                    }
                    _ => {}
                }
            }
            let now = Instant::now();
            if now >= deadline {
                // Never leave a table turning that the host no longer waits for.
                let _ = link.send(&[realtime::STOP]);
                return Err(LinkError::Timeout { waiting_for: "the motion to finish", timeout });
            }
            let poll_deadline = deadline.min(now + self.timing.poll_interval);
            match self.read_message(link, poll_deadline, "the motion to finish", timeout) {
                Err(LinkError::Timeout { .. }) => {
                    if Instant::now() < deadline {
                        // No news for a while: the completion event may have been lost. Ask.
                        link.send(&[realtime::STATUS])?;
                    }
                }
                Err(e) => return Err(e),
                Ok(Err(_)) => {}
                Ok(Ok(BoardMessage::Event(Event::Status { state: MotionState::Idle, pos, last_move })))
                    if last_move == id =>
                {
                    tracing::debug!(id, "completion recovered from a status report");
                    return Ok(i64::from(pos));
                }
                Ok(Ok(BoardMessage::Event(Event::Status { state: MotionState::Fault, pos, .. }))) => {
                    return Err(LinkError::Stopped { id, pos: pos.into() })
                }
                Ok(Ok(BoardMessage::Event(e))) => self.note_event(e)?,
                Ok(Ok(other)) => tracing::debug!(?other, "ignoring a stale reply during motion"),
            }
        }
    }

    fn steps_to_angle(&self, steps: i64) -> Result<Millideg, LinkError> {
        let deg = steps as f64 * 360.0 / f64::from(self.steps_per_turn.max(1));
        Millideg::from_degrees(deg)
            .ok_or(LinkError::Unexpected { line: format!("target {steps} steps is out of range") })
    }
}

impl Dialect for ScanrigDialect {
    fn name(&self) -> &'static str {
        "scanrig"
    }

    fn handshake(&mut self, link: &mut Link) -> Result<BoardInfo, LinkError> {
        let mut last = LinkError::Timeout { waiting_for: "the banner", timeout: self.timing.boot };
        for attempt in 0..self.timing.handshake_attempts.max(1) {
            self.decoder.clear();
            self.events.clear();
            if attempt > 0 {
                tracing::debug!(attempt, error = %last, "handshake retry: resetting the board");
                link.send(&[realtime::RESET])?;
            }
            // A board that resets when the port opens sends its banner when it has booted.
            let deadline = Instant::now() + self.timing.boot;
            loop {
                match self.read_message(link, deadline, "the banner", self.timing.boot) {
                    Ok(Ok(BoardMessage::Event(Event::Ready(_)))) => break,
                    Ok(_) => {}
                    Err(LinkError::Timeout { .. }) => break,
                    Err(e) => return Err(e),
                }
            }
            let result = (|| {
                let id = match self.exchange(link, Command::Id)? {
                    OkPayload::Identity(id) => id,
                    other => return Err(LinkError::Unexpected { line: format!("{other:?} in answer to ID") }),
                };
                if id.proto != PROTOCOL_VERSION {
                    return Err(LinkError::Mismatch {
                        problem: format!("board speaks protocol {}, this host speaks {PROTOCOL_VERSION}", id.proto),
                    });
                }
                let caps = match self.exchange(link, Command::Caps)? {
                    OkPayload::Caps(c) => c,
                    other => return Err(LinkError::Unexpected { line: format!("{other:?} in answer to CAPS") }),
                };
                if caps.steps_per_turn == 0 {
                    return Err(LinkError::Mismatch { problem: "board reports 0 steps per turn".into() });
                }
                let s = self.safety;
                self.exchange(
                    link,
                    Command::Safety { laser_s: s.laser_s, idle_ms: s.idle_ms, watchdog_ms: s.watchdog_ms },
                )?;
                let pos = match self.exchange(link, Command::Pos)? {
                    OkPayload::Position { steps, .. } => steps,
                    other => return Err(LinkError::Unexpected { line: format!("{other:?} in answer to POS") }),
                };
                self.steps_per_turn = caps.steps_per_turn;
                Ok(BoardInfo {
                    name: id.name.to_string(),
                    firmware: id.fw.to_string(),
                    steps_per_turn: caps.steps_per_turn,
                    lights: usize::from(caps.lights),
                    lasers: usize::from(caps.lasers),
                    pwm: caps.pwm,
                    home: caps.home,
                    position_steps: i64::from(pos),
                })
            })();
            match result {
                Ok(info) => return Ok(info),
                Err(e @ (LinkError::Timeout { .. } | LinkError::Decode { .. } | LinkError::BoardReset)) => last = e,
                Err(e) => return Err(e),
            }
        }
        Err(last)
    }

    fn move_to(&mut self, link: &mut Link, steps: i64, timeout: Duration) -> Result<i64, LinkError> {
        let angle = self.steps_to_angle(steps)?;
        let started = Instant::now();
        let id = match self.exchange(link, Command::Move(angle))? {
            OkPayload::MoveStarted { id, .. } => id,
            other => return Err(LinkError::Unexpected { line: format!("{other:?} in answer to MOVE") }),
        };
        self.await_motion(link, id, timeout.saturating_sub(started.elapsed()))
    }

    fn home(&mut self, link: &mut Link, timeout: Duration) -> Result<i64, LinkError> {
        let started = Instant::now();
        let id = match self.exchange(link, Command::Home)? {
            OkPayload::MoveStarted { id, .. } => id,
            other => return Err(LinkError::Unexpected { line: format!("{other:?} in answer to HOME") }),
        };
        self.await_motion(link, id, timeout.saturating_sub(started.elapsed()))
    }

    fn set_light(&mut self, link: &mut Link, index: usize, level: u8) -> Result<(), LinkError> {
        let index = u8::try_from(index).map_err(|_| LinkError::Board { code: 4, text: "no such light".into() })?;
        self.exchange(link, Command::Light { index, level }).map(drop)
    }

    fn set_laser(&mut self, link: &mut Link, index: usize, on: bool) -> Result<(), LinkError> {
        let index = u8::try_from(index).map_err(|_| LinkError::Board { code: 4, text: "no such laser".into() })?;
        self.exchange(link, Command::Laser { index, on }).map(drop)
    }

    fn motor(&mut self, link: &mut Link, on: bool) -> Result<(), LinkError> {
        self.exchange(link, Command::Motor(on)).map(drop)
    }

    fn all_off(&mut self, link: &mut Link, _lights: usize, _lasers: usize) -> Result<(), LinkError> {
        self.exchange(link, Command::Off).map(drop)
    }
}
