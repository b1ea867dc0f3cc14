//! Streaming decoders: bytes in, lines and typed values out, with resynchronisation at every newline.

use crate::command::Command;
use crate::framing::Framing;
use crate::message::BoardMessage;
use crate::{realtime, DecodeError, MAX_LINE};

/// What [`LineSplitter::push`] found.
#[derive(Debug, PartialEq, Eq)]
pub enum Split<'a> {
    /// No complete line yet.
    Pending,
    /// A complete, non-empty line, without its terminator (`\r` bytes are dropped).
    Line(&'a [u8]),
    /// A line longer than [`MAX_LINE`] ended; it was discarded.
    Overflow,
}

/// Cuts a byte stream into lines at `\n`, dropping `\r`, skipping empty lines, and discarding lines
/// longer than [`MAX_LINE`] whole. Whatever came before, the byte after the next `\n` starts a fresh
/// line, so garbage can cost at most the line it is in.
#[derive(Debug, Clone)]
pub struct LineSplitter {
    buf: [u8; MAX_LINE],
    len: usize,
    overflowed: bool,
    complete: bool,
}

impl Default for LineSplitter {
    fn default() -> Self {
        Self::new()
    }
}

impl LineSplitter {
    /// An empty splitter.
    pub const fn new() -> Self {
        LineSplitter { buf: [0; MAX_LINE], len: 0, overflowed: false, complete: false }
    }

    /// Forget any partial line.
    pub fn clear(&mut self) {
        self.len = 0;
        self.overflowed = false;
        self.complete = false;
    }

    /// Whether a partial line is buffered.
    pub fn has_partial(&self) -> bool {
        !self.complete && (self.len > 0 || self.overflowed)
    }

    /// Feed one byte.
    pub fn push(&mut self, byte: u8) -> Split<'_> {
        if self.complete {
            self.len = 0;
            self.complete = false;
        }
        match byte {
            b'\n' => {
                if self.overflowed {
                    self.overflowed = false;
                    self.len = 0;
                    Split::Overflow
                } else if self.len == 0 {
                    Split::Pending
                } else {
                    self.complete = true;
                    Split::Line(&self.buf[..self.len])
                }
            }
            b'\r' => Split::Pending,
            _ if self.overflowed => Split::Pending,
            b => {
                if self.len == MAX_LINE {
                    self.overflowed = true;
                    self.len = 0;
                } else {
                    self.buf[self.len] = b;
                    self.len += 1;
                }
                Split::Pending
            }
        }
    }
}

/// One decoded board line, with its framing, or why it could not be decoded.
pub type DecodedMessage = Result<(Framing, BoardMessage), DecodeError>;

/// Host side: decodes the board's lines.
#[derive(Debug, Clone, Default)]
pub struct BoardDecoder {
    lines: LineSplitter,
}

impl BoardDecoder {
    /// A fresh decoder.
    pub const fn new() -> Self {
        BoardDecoder { lines: LineSplitter::new() }
    }

    /// Forget any partial line (after a reconnect).
    pub fn clear(&mut self) {
        self.lines.clear();
    }

    /// Feed one byte; a complete line comes back decoded (or as the reason it could not be).
    pub fn push(&mut self, byte: u8) -> Option<DecodedMessage> {
        match self.lines.push(byte) {
            Split::Pending => None,
            Split::Overflow => Some(Err(DecodeError::Overflow)),
            Split::Line(l) => Some(BoardMessage::decode(l)),
        }
    }

    /// Feed bytes until one line completes. Returns how many bytes were used and the line's result,
    /// if one completed; call again with the rest.
    pub fn decode(&mut self, input: &[u8]) -> (usize, Option<DecodedMessage>) {
        for (i, &b) in input.iter().enumerate() {
            if let Some(r) = self.push(b) {
                return (i + 1, Some(r));
            }
        }
        (input.len(), None)
    }
}

/// A command line the board cannot execute, and the line number to answer with: the line's own
/// number when its checksum (if any) was good, so that `error:<code> N<n>` reaches the right request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rejected {
    /// The line's number, when it can be trusted.
    pub line: Option<u16>,
    /// Why the line was rejected.
    pub error: DecodeError,
}

/// What the board's [`CommandDecoder`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Input {
    /// A real-time byte (see [`realtime`]); act on it at once.
    RealTime(u8),
    /// A complete command line, or why it could not be decoded (answer `error:<code>`).
    Line(Result<(Framing, Command), Rejected>),
}

/// Firmware side: decodes the host's lines and picks out real-time bytes wherever they appear.
#[derive(Debug, Clone, Default)]
pub struct CommandDecoder {
    lines: LineSplitter,
}

impl CommandDecoder {
    /// A fresh decoder.
    pub const fn new() -> Self {
        CommandDecoder { lines: LineSplitter::new() }
    }

    /// Forget any partial line (after a reset).
    pub fn clear(&mut self) {
        self.lines.clear();
    }

    /// Feed one byte.
    pub fn push(&mut self, byte: u8) -> Option<Input> {
        if realtime::is_realtime(byte) {
            return Some(Input::RealTime(byte));
        }
        match self.lines.push(byte) {
            Split::Pending => None,
            Split::Overflow => Some(Input::Line(Err(Rejected { line: None, error: DecodeError::Overflow }))),
            Split::Line(l) => Some(Input::Line(Command::decode(l).map_err(|error| Rejected {
                line: match error {
                    DecodeError::Unknown | DecodeError::BadArgument => trusted_line_number(l),
                    _ => None,
                },
                error,
            }))),
        }
    }
}

/// The `N<n>` of a line whose checksum, if any, is good.
fn trusted_line_number(line: &[u8]) -> Option<u16> {
    let (body, _) = crate::framing::strip_checksum(line).ok()?;
    let first = body.split(|&b| b == b' ').next()?;
    crate::framing::parse_line_number(first)
}
