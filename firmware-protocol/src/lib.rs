//! The scanrig serial line protocol, version 1 (specified in `PROTOCOL.md` beside this crate): a
//! `no_std`, sans-IO codec for the host's commands and the board's replies and events.
//!
//! Nothing here touches a port or a clock. Bytes go in through [`BoardDecoder::push`] (host side) or
//! [`CommandDecoder::push`] (firmware side) and come out as typed values; values go out through
//! [`Command::encode`] and [`BoardMessage::encode`] into a caller's buffer. Every decoder accepts any
//! byte sequence: malformed lines become errors, and the next newline always brings the decoder back
//! in step.
#![cfg_attr(not(feature = "std"), no_std)]

mod command;
mod decoder;
mod framing;
mod message;
mod number;
mod text;

pub use command::Command;
pub use decoder::{BoardDecoder, CommandDecoder, DecodedMessage, Input, LineSplitter, Rejected, Split};
pub use framing::{checksum, EncodeError, Framing};
pub use message::{BoardMessage, Caps, ErrorCode, Event, Identity, MotionState, OkPayload, SafetyReason};
pub use number::Millideg;
pub use text::Text;

/// The protocol version this crate speaks, as announced in the banner and the `ID` reply.
pub const PROTOCOL_VERSION: u16 = 1;

/// Longest line, in bytes, not counting the line terminator. Longer lines are discarded whole and
/// answered with `error:7`.
pub const MAX_LINE: usize = 96;

/// Real-time bytes: single bytes the host sends outside of lines. The board acts on them at once, even
/// in the middle of a line, never echoes them and never counts them as part of a line.
pub mod realtime {
    /// `?`: the board answers with one `@status` event.
    pub const STATUS: u8 = b'?';
    /// `!`: stop the motion at once (the move ends with `@stopped`), lasers off.
    pub const STOP: u8 = b'!';
    /// Ctrl-X: soft reset; everything off, state forgotten, then the `@ready` banner.
    pub const RESET: u8 = 0x18;

    /// Whether `byte` is a real-time byte.
    pub fn is_realtime(byte: u8) -> bool {
        matches!(byte, STATUS | STOP | RESET)
    }
}

/// Why a line could not be decoded. The decoder has already skipped the whole line, so decoding
/// goes on with the next one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DecodeError {
    /// The line was longer than [`MAX_LINE`] bytes.
    Overflow,
    /// The line held a byte that is not printable ASCII.
    NotAscii,
    /// The line's checksum did not match its contents.
    Checksum {
        /// The checksum computed over the line.
        computed: u8,
        /// The checksum the line carried.
        carried: u8,
    },
    /// The first word is no known command or message.
    Unknown,
    /// A known command or message with missing, extra or out-of-range arguments.
    BadArgument,
}

impl DecodeError {
    /// The `error:<code>` a board answers to a command line that failed to decode this way.
    pub fn error_code(self) -> ErrorCode {
        match self {
            DecodeError::Overflow => ErrorCode::Overflow,
            DecodeError::NotAscii | DecodeError::Unknown => ErrorCode::UnknownCommand,
            DecodeError::Checksum { .. } => ErrorCode::Checksum,
            DecodeError::BadArgument => ErrorCode::BadArgument,
        }
    }
}

impl core::fmt::Display for DecodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            DecodeError::Overflow => write!(f, "line longer than {MAX_LINE} bytes"),
            DecodeError::NotAscii => write!(f, "line holds bytes that are not printable ASCII"),
            DecodeError::Checksum { computed, carried } => {
                write!(f, "checksum mismatch: line says {carried:02X}, contents give {computed:02X}")
            }
            DecodeError::Unknown => write!(f, "unknown command or message"),
            DecodeError::BadArgument => write!(f, "missing, extra or out-of-range argument"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for DecodeError {}
