//! A short, fixed-capacity ASCII string for names and error texts (no allocation).

use core::fmt;

/// Capacity of a [`Text`], bytes.
pub const TEXT_CAPACITY: usize = 48;

/// Printable ASCII text of at most [`TEXT_CAPACITY`] bytes. Building one never fails: longer input is
/// cut, and bytes that could break a line (control bytes, non-ASCII, `*` which starts a checksum) are
/// replaced by `_`.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Text {
    buf: [u8; TEXT_CAPACITY],
    len: u8,
}

impl Text {
    /// The empty text.
    pub const fn empty() -> Self {
        Text { buf: [0; TEXT_CAPACITY], len: 0 }
    }

    /// Text from bytes, cut and cleaned as described on [`Text`].
    pub fn from_bytes_lossy(bytes: &[u8]) -> Self {
        let mut t = Text::empty();
        for &b in bytes.iter().take(TEXT_CAPACITY) {
            let clean = if (0x20..0x7f).contains(&b) && b != b'*' { b } else { b'_' };
            t.buf[t.len as usize] = clean;
            t.len += 1;
        }
        t
    }

    /// Text from a string, cut and cleaned as described on [`Text`].
    #[allow(clippy::should_implement_trait)]
    pub fn from_str(s: &str) -> Self {
        Self::from_bytes_lossy(s.as_bytes())
    }

    /// The text.
    pub fn as_str(&self) -> &str {
        // Only printable ASCII is ever stored, so this cannot fail; fall back to "" regardless.
        core::str::from_utf8(&self.buf[..self.len as usize]).unwrap_or("")
    }

    /// Whether the text is empty.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl Default for Text {
    fn default() -> Self {
        Text::empty()
    }
}

impl fmt::Debug for Text {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        fmt::Debug::fmt(self.as_str(), f)
    }
}

impl fmt::Display for Text {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}
