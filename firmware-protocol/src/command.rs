//! Commands: one line each, from the host to the board.

use core::fmt::Write;

use crate::framing::{parse_line_number, strip_checksum, words, write_line, Cursor, EncodeError, Framing};
use crate::number::{parse_flag, parse_uint, Millideg};
use crate::DecodeError;

/// A command line's body. Every command gets exactly one terminal reply (`ok ...` or
/// `error:<code> ...`); motion commands also produce one completion event later.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Command {
    /// `ID`: identity; answered `ok proto=.. name=.. fw=..`.
    Id,
    /// `CAPS`: capabilities; answered `ok steps=.. lights=.. lasers=.. pwm=.. home=.. trigger=..`.
    Caps,
    /// `POS`: position; answered `ok pos=<steps> moving=<0|1>`.
    Pos,
    /// `MOVE <deg>`: turn to an absolute angle, degrees counter-clockwise from zero.
    Move(Millideg),
    /// `TURN <deg>`: turn by a relative angle, degrees counter-clockwise.
    Turn(Millideg),
    /// `HOME`: drive to the end stop and zero there (boards without one answer `error:4`).
    Home,
    /// `ZERO`: make the present position zero.
    Zero,
    /// `MOTOR <0|1>`: release or hold the turntable motor.
    Motor(bool),
    /// `LIGHT <index> <level>`: white light `index` at PWM level 0..=255 (on/off boards: >0 is on).
    Light {
        /// Light index, from 0.
        index: u8,
        /// PWM level, 0 = off, 255 = full.
        level: u8,
    },
    /// `LASER <index> <0|1>`: line laser `index` off or on.
    Laser {
        /// Laser index, from 0.
        index: u8,
        /// On.
        on: bool,
    },
    /// `TRIG <ms>`: pulse the camera trigger output for `ms` milliseconds (1..=1000).
    Trigger {
        /// Pulse length, milliseconds.
        ms: u16,
    },
    /// `SAFE <laser_s> <idle_ms> <watchdog_ms>`: safety limits; 0 disables one.
    Safety {
        /// A laser switches itself off after this many seconds on.
        laser_s: u16,
        /// The motor is released after this many milliseconds without motion.
        idle_ms: u32,
        /// Everything goes off after this many milliseconds without a byte from the host.
        watchdog_ms: u32,
    },
    /// `OFF`: every light and laser off, motion stopped, motor released.
    Off,
}

impl Command {
    /// Whether the command starts a motion (and so ends with `@done` or `@stopped`).
    pub fn is_motion(&self) -> bool {
        matches!(self, Command::Move(_) | Command::Turn(_) | Command::Home)
    }

    fn write_body(&self, c: &mut Cursor<'_>) -> core::fmt::Result {
        match self {
            Command::Id => c.write_str("ID"),
            Command::Caps => c.write_str("CAPS"),
            Command::Pos => c.write_str("POS"),
            Command::Move(a) => write!(c, "MOVE {a}"),
            Command::Turn(a) => write!(c, "TURN {a}"),
            Command::Home => c.write_str("HOME"),
            Command::Zero => c.write_str("ZERO"),
            Command::Motor(on) => write!(c, "MOTOR {}", u8::from(*on)),
            Command::Light { index, level } => write!(c, "LIGHT {index} {level}"),
            Command::Laser { index, on } => write!(c, "LASER {index} {}", u8::from(*on)),
            Command::Trigger { ms } => write!(c, "TRIG {ms}"),
            Command::Safety { laser_s, idle_ms, watchdog_ms } => write!(c, "SAFE {laser_s} {idle_ms} {watchdog_ms}"),
            Command::Off => c.write_str("OFF"),
        }
    }

    /// Encode as one line (with `\n`) into `out`; returns the number of bytes written.
    pub fn encode(&self, framing: Framing, out: &mut [u8]) -> Result<usize, EncodeError> {
        write_line(out, framing.checksum, |c| {
            if let Some(n) = framing.line {
                write!(c, "N{n} ")?;
            }
            self.write_body(c)
        })
    }

    /// Encode into a new vector.
    #[cfg(feature = "std")]
    pub fn to_line(&self, framing: Framing) -> Result<Vec<u8>, EncodeError> {
        let mut buf = [0u8; crate::MAX_LINE + 1];
        let n = self.encode(framing, &mut buf)?;
        Ok(buf[..n].to_vec())
    }

    /// Decode one line (without its terminator).
    pub fn decode(line: &[u8]) -> Result<(Framing, Command), DecodeError> {
        let (body, has_sum) = strip_checksum(line)?;
        let (w, n) = words::<5>(body).ok_or(DecodeError::BadArgument)?;
        let (line_no, w) = match parse_line_number(w[0]) {
            Some(num) if n >= 2 => (Some(num), &w[1..n]),
            _ => (None, &w[..n]),
        };
        let framing = Framing { line: line_no, checksum: has_sum };
        let (name, args) = w.split_first().ok_or(DecodeError::Unknown)?;
        let bad = DecodeError::BadArgument;
        let uint = |i: usize, max: u64| args.get(i).and_then(|a| parse_uint(a, max)).ok_or(bad);
        let flag = |i: usize| args.get(i).and_then(|a| parse_flag(a)).ok_or(bad);
        let angle = |i: usize| args.get(i).and_then(|a| Millideg::parse(a)).ok_or(bad);
        let (cmd, want) = match *name {
            b"ID" => (Command::Id, 0),
            b"CAPS" => (Command::Caps, 0),
            b"POS" => (Command::Pos, 0),
            b"MOVE" => (Command::Move(angle(0)?), 1),
            b"TURN" => (Command::Turn(angle(0)?), 1),
            b"HOME" => (Command::Home, 0),
            b"ZERO" => (Command::Zero, 0),
            b"MOTOR" => (Command::Motor(flag(0)?), 1),
            b"LIGHT" => (Command::Light { index: uint(0, 255)? as u8, level: uint(1, 255)? as u8 }, 2),
            b"LASER" => (Command::Laser { index: uint(0, 255)? as u8, on: flag(1)? }, 2),
            b"TRIG" => {
                let ms = uint(0, 1000)? as u16;
                if ms == 0 {
                    return Err(bad);
                }
                (Command::Trigger { ms }, 1)
            }
            b"SAFE" => (
                Command::Safety {
                    laser_s: uint(0, u64::from(u16::MAX))? as u16,
                    idle_ms: uint(1, u64::from(u32::MAX))? as u32,
                    watchdog_ms: uint(2, u64::from(u32::MAX))? as u32,
                },
                3,
            ),
            b"OFF" => (Command::Off, 0),
            _ => return Err(DecodeError::Unknown),
        };
        if args.len() != want {
            return Err(bad);
        }
        Ok((framing, cmd))
    }
}
