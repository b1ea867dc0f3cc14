//! Integers and fixed-point degrees as they appear on the wire.

use core::fmt;

/// An angle in thousandths of a degree. On the wire it is a decimal number of degrees with at most
/// three digits after the point (`45`, `-7.5`, `0.125`); counter-clockwise seen from above is
/// positive. Fixed point keeps the wire text exact and lets 8-bit firmware work without floats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct Millideg(pub i32);

/// Largest magnitude of a wire angle, thousandths of a degree (one million degrees).
pub const MAX_MILLIDEG: i32 = 1_000_000_000;

impl Millideg {
    /// The nearest wire angle to `degrees`, or `None` when it is not finite or beyond ±1e6 degrees.
    pub fn from_degrees(degrees: f64) -> Option<Self> {
        if !degrees.is_finite() {
            return None;
        }
        let m = degrees * 1000.0;
        let r = if m >= 0.0 { (m + 0.5) as i64 } else { -((-m + 0.5) as i64) };
        if r.unsigned_abs() > MAX_MILLIDEG as u64 {
            return None;
        }
        Some(Millideg(r as i32))
    }

    /// The angle in degrees.
    pub fn degrees(self) -> f64 {
        f64::from(self.0) / 1000.0
    }

    /// Parse the wire form.
    pub fn parse(s: &[u8]) -> Option<Self> {
        let (neg, digits) = match s.split_first() {
            Some((b'-', rest)) => (true, rest),
            Some((b'+', rest)) => (false, rest),
            _ => (false, s),
        };
        let (int, frac) = match digits.iter().position(|&b| b == b'.') {
            Some(p) => (&digits[..p], &digits[p + 1..]),
            None => (digits, &digits[digits.len()..]),
        };
        if int.is_empty() || frac.len() > 3 || (digits.len() > int.len() && frac.is_empty()) {
            return None;
        }
        let whole = parse_u64(int)?;
        let mut milli = 0u64;
        for i in 0..3 {
            let d = match frac.get(i) {
                Some(&b) if b.is_ascii_digit() => u64::from(b - b'0'),
                Some(_) => return None,
                None => 0,
            };
            milli = milli * 10 + d;
        }
        let total = whole.checked_mul(1000)?.checked_add(milli)?;
        if total > MAX_MILLIDEG as u64 {
            return None;
        }
        let v = total as i32;
        Some(Millideg(if neg { -v } else { v }))
    }
}

impl fmt::Display for Millideg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let neg = self.0 < 0;
        let abs = self.0.unsigned_abs();
        let (whole, mut frac) = (abs / 1000, abs % 1000);
        if neg {
            f.write_str("-")?;
        }
        write!(f, "{whole}")?;
        if frac != 0 {
            let mut digits = 3;
            while frac % 10 == 0 {
                frac /= 10;
                digits -= 1;
            }
            write!(f, ".{frac:0digits$}")?;
        }
        Ok(())
    }
}

/// Parse an unsigned decimal of at most 10 digits (no sign, no leading `+`).
pub(crate) fn parse_u64(s: &[u8]) -> Option<u64> {
    if s.is_empty() || s.len() > 10 {
        return None;
    }
    let mut v = 0u64;
    for &b in s {
        if !b.is_ascii_digit() {
            return None;
        }
        v = v * 10 + u64::from(b - b'0');
    }
    Some(v)
}

/// Parse an unsigned decimal that must fit `max`.
pub(crate) fn parse_uint(s: &[u8], max: u64) -> Option<u64> {
    parse_u64(s).filter(|&v| v <= max)
}

/// Parse a signed decimal that fits an `i32`.
pub(crate) fn parse_i32(s: &[u8]) -> Option<i32> {
    let (neg, digits) = match s.split_first() {
        Some((b'-', rest)) => (true, rest),
        _ => (false, s),
    };
    let v = parse_u64(digits)?;
    let v = i64::try_from(v).ok()?;
    i32::try_from(if neg { -v } else { v }).ok()
}

/// Parse `0` or `1`.
pub(crate) fn parse_flag(s: &[u8]) -> Option<bool> {
    match s {
        b"0" => Some(false),
        b"1" => Some(true),
        _ => None,
    }
}
