//! Line framing: optional line numbers and checksums, and a bounded writer for encoding.

use core::fmt;

use crate::number::parse_uint;
use crate::DecodeError;

/// The checksum of a line: XOR of every byte before the `*`.
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0, |acc, b| acc ^ b)
}

/// How a line is framed on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Framing {
    /// The line number (`N<n>`), 0..=65535, if the line carries one.
    pub line: Option<u16>,
    /// Whether the line ends with `*<two hex digits>`.
    pub checksum: bool,
}

impl Framing {
    /// No line number, no checksum.
    pub const PLAIN: Framing = Framing { line: None, checksum: false };
}

/// Why encoding failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EncodeError {
    /// The output buffer is too small for the line.
    BufferTooSmall,
    /// The encoded line would be longer than [`crate::MAX_LINE`].
    LineTooLong,
}

impl fmt::Display for EncodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            EncodeError::BufferTooSmall => f.write_str("output buffer too small"),
            EncodeError::LineTooLong => write!(f, "line longer than {} bytes", crate::MAX_LINE),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for EncodeError {}

/// A `fmt::Write` into a byte slice that fails instead of growing.
pub(crate) struct Cursor<'a> {
    buf: &'a mut [u8],
    len: usize,
}

impl<'a> Cursor<'a> {
    pub(crate) fn new(buf: &'a mut [u8]) -> Self {
        Cursor { buf, len: 0 }
    }
}

impl fmt::Write for Cursor<'_> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        let end = self.len.checked_add(s.len()).ok_or(fmt::Error)?;
        let dst = self.buf.get_mut(self.len..end).ok_or(fmt::Error)?;
        dst.copy_from_slice(s.as_bytes());
        self.len = end;
        Ok(())
    }
}

/// Write one line: the body written by `body`, then `*hh` when `checksum`, then `\n`. Returns the
/// number of bytes written.
pub(crate) fn write_line(
    out: &mut [u8],
    checksum_on: bool,
    body: impl FnOnce(&mut Cursor<'_>) -> fmt::Result,
) -> Result<usize, EncodeError> {
    let mut c = Cursor::new(out);
    body(&mut c).map_err(|_| EncodeError::BufferTooSmall)?;
    let body_len = c.len;
    if checksum_on {
        let sum = checksum(&c.buf[..body_len]);
        fmt::Write::write_fmt(&mut c, format_args!("*{sum:02X}")).map_err(|_| EncodeError::BufferTooSmall)?;
    }
    if c.len > crate::MAX_LINE {
        return Err(EncodeError::LineTooLong);
    }
    fmt::Write::write_str(&mut c, "\n").map_err(|_| EncodeError::BufferTooSmall)?;
    Ok(c.len)
}

/// Check a received line (terminator already removed): printable ASCII, and a valid checksum if it
/// carries one. Returns the body without the checksum and whether there was one.
pub(crate) fn strip_checksum(line: &[u8]) -> Result<(&[u8], bool), DecodeError> {
    if !line.iter().all(|b| (0x20..0x7f).contains(b)) {
        return Err(DecodeError::NotAscii);
    }
    match line.iter().rposition(|&b| b == b'*') {
        None => Ok((line, false)),
        Some(star) => {
            let hex = &line[star + 1..];
            let carried = match hex {
                [h, l] => hex_val(*h).zip(hex_val(*l)).map(|(h, l)| h << 4 | l),
                _ => None,
            }
            .ok_or(DecodeError::BadArgument)?;
            let body = &line[..star];
            let computed = checksum(body);
            if computed != carried {
                return Err(DecodeError::Checksum { computed, carried });
            }
            Ok((body, true))
        }
    }
}

fn hex_val(b: u8) -> Option<u8> {
    match b {
        b'0'..=b'9' => Some(b - b'0'),
        b'A'..=b'F' => Some(b - b'A' + 10),
        b'a'..=b'f' => Some(b - b'a' + 10),
        _ => None,
    }
}

/// Parse an `N<n>` token.
pub(crate) fn parse_line_number(token: &[u8]) -> Option<u16> {
    match token.split_first() {
        Some((b'N', digits)) => parse_uint(digits, u64::from(u16::MAX)).map(|v| v as u16),
        _ => None,
    }
}

/// Split on single spaces into at most `N` words; `None` when there are more, or empty words
/// (double spaces, leading or trailing space).
pub(crate) fn words<const N: usize>(body: &[u8]) -> Option<([&[u8]; N], usize)> {
    let mut out: [&[u8]; N] = [&[]; N];
    let mut n = 0;
    if body.is_empty() {
        return Some((out, 0));
    }
    for w in body.split(|&b| b == b' ') {
        if w.is_empty() || n == N {
            return None;
        }
        out[n] = w;
        n += 1;
    }
    Some((out, n))
}
