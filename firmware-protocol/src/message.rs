//! What the board sends: terminal replies (`ok`, `error:<code>`) and events (`@...`).

use core::fmt::{self, Write};

use crate::framing::{parse_line_number, strip_checksum, words, write_line, Cursor, EncodeError, Framing};
use crate::number::{parse_flag, parse_i32, parse_uint};
use crate::text::Text;
use crate::DecodeError;

/// One line from the board.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BoardMessage {
    /// `ok[ N<n>][ payload]`: the command was done (or, for motion, accepted and started).
    Ok {
        /// The line number of the command this answers, when that command carried one.
        line: Option<u16>,
        /// What the command returns.
        payload: OkPayload,
    },
    /// `error:<code>[ N<n>][ text]`: the command was not done.
    Error {
        /// The line number of the command this answers, when that command carried one.
        line: Option<u16>,
        /// Why.
        code: ErrorCode,
        /// Free text for people.
        text: Text,
    },
    /// `@...`: something that happened, not an answer to a line.
    Event(Event),
}

impl BoardMessage {
    /// Whether this is a terminal reply (`ok` or `error`).
    pub fn is_terminal(&self) -> bool {
        !matches!(self, BoardMessage::Event(_))
    }
}

/// The data an `ok` carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OkPayload {
    /// Nothing.
    Empty,
    /// Answer to `ID`.
    Identity(Identity),
    /// Answer to `CAPS`.
    Caps(Caps),
    /// Answer to a motion command: `move=<id> target=<steps>`.
    MoveStarted {
        /// The motion's id, echoed by its completion event (1..=65535, wrapping, never 0).
        id: u16,
        /// Target position, steps from zero.
        target: i32,
    },
    /// Answer to `POS`: `pos=<steps> moving=<0|1>`.
    Position {
        /// Present position, steps from zero.
        steps: i32,
        /// Whether a motion is under way.
        moving: bool,
    },
}

/// A board's identity: banner and `ID` reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Identity {
    /// Protocol version the board speaks.
    pub proto: u16,
    /// Board name (one word).
    pub name: Text,
    /// Firmware version (one word).
    pub fw: Text,
}

/// What a board can do: the `CAPS` reply. Steps per turn is defined here and nowhere else.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Caps {
    /// Motor (micro-)steps per full turn of the table.
    pub steps_per_turn: u32,
    /// Number of white lights.
    pub lights: u8,
    /// Number of line lasers.
    pub lasers: u8,
    /// Whether lights take PWM levels (otherwise any level > 0 is on).
    pub pwm: bool,
    /// Whether there is an end stop for `HOME`.
    pub home: bool,
    /// Whether there is a camera trigger output for `TRIG`.
    pub trigger: bool,
}

/// Error codes of `error:<code>`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ErrorCode {
    /// 1: unknown command.
    UnknownCommand,
    /// 2: missing, extra or out-of-range argument.
    BadArgument,
    /// 3: a motion is under way.
    Busy,
    /// 4: the board has no such feature (no end stop, no such light).
    Unsupported,
    /// 5: checksum mismatch; the line was not executed.
    Checksum,
    /// 6: line number out of sequence; the line was not executed.
    LineNumber,
    /// 7: line too long; it was not executed.
    Overflow,
    /// 8: hardware fault (driver fault, end stop not found).
    Hardware,
    /// Any other code (from a newer board).
    Other(u16),
}

impl ErrorCode {
    /// The number on the wire.
    pub fn code(self) -> u16 {
        match self {
            ErrorCode::UnknownCommand => 1,
            ErrorCode::BadArgument => 2,
            ErrorCode::Busy => 3,
            ErrorCode::Unsupported => 4,
            ErrorCode::Checksum => 5,
            ErrorCode::LineNumber => 6,
            ErrorCode::Overflow => 7,
            ErrorCode::Hardware => 8,
            ErrorCode::Other(c) => c,
        }
    }

    /// The code for a wire number.
    pub fn from_code(code: u16) -> Self {
        match code {
            1 => ErrorCode::UnknownCommand,
            2 => ErrorCode::BadArgument,
            3 => ErrorCode::Busy,
            4 => ErrorCode::Unsupported,
            5 => ErrorCode::Checksum,
            6 => ErrorCode::LineNumber,
            7 => ErrorCode::Overflow,
            8 => ErrorCode::Hardware,
            c => ErrorCode::Other(c),
        }
    }

    /// Whether resending the same line may succeed (the line was damaged, not wrong).
    pub fn is_transmission(self) -> bool {
        matches!(self, ErrorCode::Checksum | ErrorCode::Overflow)
    }
}

/// Motion state in `@status`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MotionState {
    /// Not moving.
    Idle,
    /// Moving.
    Moving,
    /// Homing.
    Homing,
    /// Stopped by a fault; outputs are off.
    Fault,
}

impl MotionState {
    fn word(self) -> &'static str {
        match self {
            MotionState::Idle => "idle",
            MotionState::Moving => "moving",
            MotionState::Homing => "homing",
            MotionState::Fault => "fault",
        }
    }
}

/// Why the board switched something off by itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SafetyReason {
    /// `@off laser=<i>`: laser `i` was on longer than the laser limit.
    Laser(u8),
    /// `@off motor`: the motor was idle longer than the idle limit and was released.
    MotorIdle,
    /// `@off watchdog`: nothing came from the host within the watchdog time; everything is off.
    Watchdog,
}

/// Events: lines starting with `@`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// `@ready proto=.. name=.. fw=..`: the banner, sent after every power-up and reset.
    Ready(Identity),
    /// `@done move=<id> pos=<steps>`: motion `id` finished at `pos`.
    Done {
        /// The motion id from `ok move=<id>`.
        id: u16,
        /// Position, steps.
        pos: i32,
    },
    /// `@stopped move=<id> pos=<steps>`: motion `id` was cut short (stop byte, fault, `OFF`).
    Stopped {
        /// The motion id.
        id: u16,
        /// Position, steps.
        pos: i32,
    },
    /// `@status state=<s> pos=<steps> move=<id>`: answer to the `?` real-time byte; `move` is the
    /// id of the latest motion started (0 = none since reset).
    Status {
        /// Motion state.
        state: MotionState,
        /// Position, steps.
        pos: i32,
        /// Latest motion id.
        last_move: u16,
    },
    /// `@off ...`: a safety limit switched something off.
    SafetyOff(SafetyReason),
}

fn write_word(c: &mut Cursor<'_>, t: &Text) -> fmt::Result {
    if t.is_empty() {
        return c.write_str("-");
    }
    for b in t.as_str().bytes() {
        c.write_char(if b == b' ' || b == b'=' { '_' } else { char::from(b) })?;
    }
    Ok(())
}

fn write_identity(c: &mut Cursor<'_>, id: &Identity) -> fmt::Result {
    write!(c, "proto={} name=", id.proto)?;
    write_word(c, &id.name)?;
    c.write_str(" fw=")?;
    write_word(c, &id.fw)
}

impl BoardMessage {
    fn write_body(&self, c: &mut Cursor<'_>) -> fmt::Result {
        match self {
            BoardMessage::Ok { line, payload } => {
                c.write_str("ok")?;
                if let Some(n) = line {
                    write!(c, " N{n}")?;
                }
                match payload {
                    OkPayload::Empty => Ok(()),
                    OkPayload::Identity(id) => {
                        c.write_str(" ")?;
                        write_identity(c, id)
                    }
                    OkPayload::Caps(k) => write!(
                        c,
                        " steps={} lights={} lasers={} pwm={} home={} trigger={}",
                        k.steps_per_turn,
                        k.lights,
                        k.lasers,
                        u8::from(k.pwm),
                        u8::from(k.home),
                        u8::from(k.trigger)
                    ),
                    OkPayload::MoveStarted { id, target } => write!(c, " move={id} target={target}"),
                    OkPayload::Position { steps, moving } => write!(c, " pos={steps} moving={}", u8::from(*moving)),
                }
            }
            BoardMessage::Error { line, code, text } => {
                write!(c, "error:{}", code.code())?;
                if let Some(n) = line {
                    write!(c, " N{n}")?;
                }
                if !text.is_empty() {
                    write!(c, " {text}")?;
                }
                Ok(())
            }
            BoardMessage::Event(e) => match e {
                Event::Ready(id) => {
                    c.write_str("@ready ")?;
                    write_identity(c, id)
                }
                Event::Done { id, pos } => write!(c, "@done move={id} pos={pos}"),
                Event::Stopped { id, pos } => write!(c, "@stopped move={id} pos={pos}"),
                Event::Status { state, pos, last_move } => {
                    write!(c, "@status state={} pos={pos} move={last_move}", state.word())
                }
                Event::SafetyOff(SafetyReason::Laser(i)) => write!(c, "@off laser={i}"),
                Event::SafetyOff(SafetyReason::MotorIdle) => c.write_str("@off motor"),
                Event::SafetyOff(SafetyReason::Watchdog) => c.write_str("@off watchdog"),
            },
        }
    }

    /// Encode as one line (with `\n`) into `out`, with a checksum when `checksum`; returns the number
    /// of bytes written. The line number of a reply is part of the message, not of the framing.
    pub fn encode(&self, checksum: bool, out: &mut [u8]) -> Result<usize, EncodeError> {
        write_line(out, checksum, |c| self.write_body(c))
    }

    /// Encode into a new vector.
    #[cfg(feature = "std")]
    pub fn to_line(&self, checksum: bool) -> Result<Vec<u8>, EncodeError> {
        let mut buf = [0u8; crate::MAX_LINE + 1];
        let n = self.encode(checksum, &mut buf)?;
        Ok(buf[..n].to_vec())
    }

    /// Decode one line (without its terminator). The returned [`Framing`] says whether it carried a
    /// checksum and, for replies, the line number.
    pub fn decode(line: &[u8]) -> Result<(Framing, BoardMessage), DecodeError> {
        let (body, has_sum) = strip_checksum(line)?;
        let bad = DecodeError::BadArgument;
        if let Some(rest) = body.strip_prefix(b"error:") {
            let code_end = rest.iter().position(|&b| b == b' ').unwrap_or(rest.len());
            let code = parse_uint(&rest[..code_end], u64::from(u16::MAX)).ok_or(bad)? as u16;
            let mut rest = rest.get(code_end + 1..).unwrap_or(&[]);
            let mut line_no = None;
            let first_end = rest.iter().position(|&b| b == b' ').unwrap_or(rest.len());
            if let Some(n) = parse_line_number(&rest[..first_end]) {
                line_no = Some(n);
                rest = rest.get(first_end + 1..).unwrap_or(&[]);
            }
            if rest.len() > crate::text::TEXT_CAPACITY {
                return Err(bad);
            }
            let msg = BoardMessage::Error {
                line: line_no,
                code: ErrorCode::from_code(code),
                text: Text::from_bytes_lossy(rest),
            };
            return Ok((Framing { line: line_no, checksum: has_sum }, msg));
        }
        let (w, n) = words::<8>(body).ok_or(bad)?;
        let (head, args) = w[..n].split_first().ok_or(DecodeError::Unknown)?;
        let kv = Pairs::new(args).ok_or(bad)?;
        match *head {
            b"ok" => {
                let (line_no, kv) = match args.first().and_then(|a| parse_line_number(a)) {
                    Some(num) => (Some(num), Pairs::new(&args[1..]).ok_or(bad)?),
                    None => (None, kv),
                };
                let payload = if kv.is_empty() {
                    OkPayload::Empty
                } else if kv.has(b"proto") {
                    OkPayload::Identity(kv.identity()?)
                } else if kv.has(b"steps") {
                    kv.exactly(6)?;
                    OkPayload::Caps(Caps {
                        steps_per_turn: kv.uint(b"steps", u64::from(u32::MAX))? as u32,
                        lights: kv.uint(b"lights", 255)? as u8,
                        lasers: kv.uint(b"lasers", 255)? as u8,
                        pwm: kv.flag(b"pwm")?,
                        home: kv.flag(b"home")?,
                        trigger: kv.flag(b"trigger")?,
                    })
                } else if kv.has(b"move") {
                    kv.exactly(2)?;
                    OkPayload::MoveStarted { id: kv.id(b"move")?, target: kv.int(b"target")? }
                } else if kv.has(b"pos") {
                    kv.exactly(2)?;
                    OkPayload::Position { steps: kv.int(b"pos")?, moving: kv.flag(b"moving")? }
                } else {
                    return Err(bad);
                };
                Ok((Framing { line: line_no, checksum: has_sum }, BoardMessage::Ok { line: line_no, payload }))
            }
            b"@ready" => Ok(event(has_sum, Event::Ready(kv.identity()?))),
            b"@done" => {
                kv.exactly(2)?;
                Ok(event(has_sum, Event::Done { id: kv.id(b"move")?, pos: kv.int(b"pos")? }))
            }
            b"@stopped" => {
                kv.exactly(2)?;
                Ok(event(has_sum, Event::Stopped { id: kv.id(b"move")?, pos: kv.int(b"pos")? }))
            }
            b"@status" => {
                kv.exactly(3)?;
                let state = match kv.get(b"state").ok_or(bad)? {
                    b"idle" => MotionState::Idle,
                    b"moving" => MotionState::Moving,
                    b"homing" => MotionState::Homing,
                    b"fault" => MotionState::Fault,
                    _ => return Err(bad),
                };
                let last_move = kv.uint(b"move", u64::from(u16::MAX))? as u16;
                Ok(event(has_sum, Event::Status { state, pos: kv.int(b"pos")?, last_move }))
            }
            b"@off" => {
                let reason = match args {
                    [b"motor"] => SafetyReason::MotorIdle,
                    [b"watchdog"] => SafetyReason::Watchdog,
                    [_] => {
                        kv.exactly(1)?;
                        SafetyReason::Laser(kv.uint(b"laser", 255)? as u8)
                    }
                    _ => return Err(bad),
                };
                Ok(event(has_sum, Event::SafetyOff(reason)))
            }
            _ => Err(DecodeError::Unknown),
        }
    }
}

fn event(has_sum: bool, e: Event) -> (Framing, BoardMessage) {
    (Framing { line: None, checksum: has_sum }, BoardMessage::Event(e))
}

/// `key=value` words; bare words (like `motor`) are kept with an empty key so they can be matched
/// positionally but never satisfy a key lookup.
struct Pairs<'a> {
    items: [(&'a [u8], &'a [u8]); 8],
    len: usize,
}

impl<'a> Pairs<'a> {
    fn new(args: &[&'a [u8]]) -> Option<Self> {
        let mut p = Pairs { items: [(&[], &[]); 8], len: 0 };
        for a in args.iter().take(8) {
            p.items[p.len] = match a.iter().position(|&b| b == b'=') {
                Some(eq) => (&a[..eq], &a[eq + 1..]),
                None => (&[], a),
            };
            p.len += 1;
        }
        Some(p)
    }
    fn is_empty(&self) -> bool {
        self.len == 0
    }
    fn exactly(&self, n: usize) -> Result<(), DecodeError> {
        if self.len == n {
            Ok(())
        } else {
            Err(DecodeError::BadArgument)
        }
    }
    fn get(&self, key: &[u8]) -> Option<&'a [u8]> {
        self.items[..self.len].iter().find(|(k, _)| *k == key).map(|(_, v)| *v)
    }
    fn has(&self, key: &[u8]) -> bool {
        self.get(key).is_some()
    }
    fn uint(&self, key: &[u8], max: u64) -> Result<u64, DecodeError> {
        self.get(key).and_then(|v| parse_uint(v, max)).ok_or(DecodeError::BadArgument)
    }
    fn int(&self, key: &[u8]) -> Result<i32, DecodeError> {
        self.get(key).and_then(parse_i32).ok_or(DecodeError::BadArgument)
    }
    fn flag(&self, key: &[u8]) -> Result<bool, DecodeError> {
        self.get(key).and_then(parse_flag).ok_or(DecodeError::BadArgument)
    }
    fn id(&self, key: &[u8]) -> Result<u16, DecodeError> {
        match self.uint(key, u64::from(u16::MAX))? {
            0 => Err(DecodeError::BadArgument),
            v => Ok(v as u16),
        }
    }
    fn word(&self, key: &[u8]) -> Result<Text, DecodeError> {
        let v = self.get(key).filter(|v| !v.is_empty()).ok_or(DecodeError::BadArgument)?;
        if v.len() > crate::text::TEXT_CAPACITY {
            return Err(DecodeError::BadArgument);
        }
        Ok(if v == b"-" { Text::empty() } else { Text::from_bytes_lossy(v) })
    }
    fn identity(&self) -> Result<Identity, DecodeError> {
        self.exactly(3)?;
        Ok(Identity {
            proto: self.uint(b"proto", u64::from(u16::MAX))? as u16,
            name: self.word(b"name")?,
            fw: self.word(b"fw")?,
        })
    }
}
