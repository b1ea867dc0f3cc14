//! Binary and Gray-code stripe patterns for a projector, with inverses.
//!
//! The sequence is the one the Gray-code capture in the test fixtures was taken with: for every
//! column bit, most significant first, a pattern and its inverse; then the same for the row bits;
//! then an all-white and an all-black image. A column bit `k` of projector pixel `(x, y)` is bit
//! `k` of the code of `x` (Gray or plain binary); rows likewise with `y`. Images are 8-bit grey,
//! row-major, `width * height` bytes, origin top-left, projector pixels.

/// How a projector column or row index is turned into stripe bits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Coding {
    /// Reflected binary Gray code: neighbouring indices differ in one bit, so a mis-read stripe
    /// edge costs at most one index.
    #[default]
    Gray,
    /// Plain binary.
    Binary,
}

impl Coding {
    /// The code word of index `i`.
    pub fn encode(self, i: u32) -> u32 {
        match self {
            Coding::Gray => i ^ (i >> 1),
            Coding::Binary => i,
        }
    }

    /// The index of code word `c` (inverse of [`Coding::encode`]).
    pub fn decode(self, c: u32) -> u32 {
        match self {
            Coding::Gray => {
                let mut b = c;
                b ^= b >> 16;
                b ^= b >> 8;
                b ^= b >> 4;
                b ^= b >> 2;
                b ^= b >> 1;
                b
            }
            Coding::Binary => c,
        }
    }
}

/// Errors of pattern layout construction.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PatternError {
    /// The projector resolution is zero or too large to index with 16 bits.
    #[error("projector resolution {width}x{height} pixels: each side must be 1..=32768")]
    Resolution {
        /// Projector width, pixels.
        width: u32,
        /// Projector height, pixels.
        height: u32,
    },
    /// A pattern index beyond the sequence.
    #[error("pattern index {index} out of range: the sequence has {count} images")]
    Index {
        /// The requested index.
        index: usize,
        /// Images in the sequence.
        count: usize,
    },
    /// An output buffer of the wrong length.
    #[error("pattern buffer holds {found} bytes, the projector needs {expected}")]
    Buffer {
        /// `width * height`.
        expected: usize,
        /// The buffer's length.
        found: usize,
    },
}

/// What one image of the sequence shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PatternKind {
    /// Stripes of column bit `bit` (0 = most significant); `inverse` swaps black and white.
    Column {
        /// Bit position from the most significant bit, 0-based.
        bit: u32,
        /// Whether this is the inverted image of the pair.
        inverse: bool,
    },
    /// Stripes of row bit `bit` (0 = most significant); `inverse` swaps black and white.
    Row {
        /// Bit position from the most significant bit, 0-based.
        bit: u32,
        /// Whether this is the inverted image of the pair.
        inverse: bool,
    },
    /// All pixels at full intensity.
    White,
    /// All pixels off.
    Black,
}

/// The pattern sequence for one projector resolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GrayCodePatterns {
    width: u32,
    height: u32,
    col_bits: u32,
    row_bits: u32,
    coding: Coding,
}

/// Bits needed to index `n` values (`ceil(log2 n)`, at least 1).
fn bits_for(n: u32) -> u32 {
    (32 - (n.max(2) - 1).leading_zeros()).max(1)
}

impl GrayCodePatterns {
    /// The sequence for a `width` x `height` pixel projector with Gray coding.
    pub fn new(width: u32, height: u32) -> Result<Self, PatternError> {
        Self::with_coding(width, height, Coding::Gray)
    }

    /// The sequence for a `width` x `height` pixel projector with the given coding.
    pub fn with_coding(width: u32, height: u32, coding: Coding) -> Result<Self, PatternError> {
        if !(1..=32768).contains(&width) || !(1..=32768).contains(&height) {
            return Err(PatternError::Resolution { width, height });
        }
        Ok(Self { width, height, col_bits: bits_for(width), row_bits: bits_for(height), coding })
    }

    /// Projector width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Projector height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Bits coding a column (`ceil(log2 width)`).
    pub fn column_bits(&self) -> u32 {
        self.col_bits
    }

    /// Bits coding a row (`ceil(log2 height)`).
    pub fn row_bits(&self) -> u32 {
        self.row_bits
    }

    /// The coding of indices into bits.
    pub fn coding(&self) -> Coding {
        self.coding
    }

    /// Images in the sequence: `2 * (column_bits + row_bits) + 2`.
    pub fn count(&self) -> usize {
        2 * (self.col_bits + self.row_bits) as usize + 2
    }

    /// Index of the all-white image.
    pub fn white_index(&self) -> usize {
        self.count() - 2
    }

    /// Index of the all-black image.
    pub fn black_index(&self) -> usize {
        self.count() - 1
    }

    /// What image `index` of the sequence shows.
    pub fn kind(&self, index: usize) -> Result<PatternKind, PatternError> {
        let count = self.count();
        let pairs_c = self.col_bits as usize;
        let pairs = pairs_c + self.row_bits as usize;
        let inverse = index % 2 == 1;
        Ok(match index {
            i if i < 2 * pairs_c => PatternKind::Column { bit: (i / 2) as u32, inverse },
            i if i < 2 * pairs => PatternKind::Row { bit: (i / 2 - pairs_c) as u32, inverse },
            i if i == 2 * pairs => PatternKind::White,
            i if i == 2 * pairs + 1 => PatternKind::Black,
            _ => return Err(PatternError::Index { index, count }),
        })
    }

    /// Renders image `index` into `out` (`width * height` bytes, row-major; 255 lit, 0 dark).
    pub fn render_into(&self, index: usize, out: &mut [u8]) -> Result<(), PatternError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if out.len() != w * h {
            return Err(PatternError::Buffer { expected: w * h, found: out.len() });
        }
        let lit = |on: bool, inverse: bool| if on != inverse { 255u8 } else { 0u8 };
        match self.kind(index)? {
            PatternKind::White => out.fill(255),
            PatternKind::Black => out.fill(0),
            PatternKind::Column { bit, inverse } => {
                let shift = self.col_bits - 1 - bit;
                let (first, rest) = out.split_at_mut(w);
                for (x, px) in first.iter_mut().enumerate() {
                    *px = lit((self.coding.encode(x as u32) >> shift) & 1 == 1, inverse);
                }
                for row in rest.chunks_exact_mut(w) {
                    row.copy_from_slice(first);
                }
            }
            PatternKind::Row { bit, inverse } => {
                let shift = self.row_bits - 1 - bit;
                for (y, row) in out.chunks_exact_mut(w).enumerate() {
                    row.fill(lit((self.coding.encode(y as u32) >> shift) & 1 == 1, inverse));
                }
            }
        }
        Ok(())
    }

    /// Image `index` as a new `width * height` byte buffer.
    pub fn render(&self, index: usize) -> Result<Vec<u8>, PatternError> {
        let mut out = vec![0u8; self.width as usize * self.height as usize];
        self.render_into(index, &mut out)?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gray_round_trips_and_neighbours_differ_in_one_bit() {
        for i in 0..70_000u32 {
            let g = Coding::Gray.encode(i);
            assert_eq!(Coding::Gray.decode(g), i);
            assert_eq!((g ^ Coding::Gray.encode(i + 1)).count_ones(), 1);
        }
    }

    #[test]
    fn layout_counts_bits() {
        let p = GrayCodePatterns::new(1024, 768).expect("valid");
        assert_eq!((p.column_bits(), p.row_bits(), p.count()), (10, 10, 42));
        let p = GrayCodePatterns::new(1920, 1080).expect("valid");
        assert_eq!((p.column_bits(), p.row_bits(), p.count()), (11, 11, 46));
        assert_eq!(p.kind(46), Err(PatternError::Index { index: 46, count: 46 }));
        assert!(GrayCodePatterns::new(0, 10).is_err());
        let p = GrayCodePatterns::new(1, 1).expect("valid");
        assert_eq!(p.count(), 6, "a one-pixel projector still needs one bit per axis");
    }

    #[test]
    fn inverse_is_complement() {
        let p = GrayCodePatterns::new(37, 23).expect("valid");
        for pair in 0..(p.count() - 2) / 2 {
            let a = p.render(2 * pair).expect("in range");
            let b = p.render(2 * pair + 1).expect("in range");
            assert!(a.iter().zip(&b).all(|(x, y)| x ^ y == 255));
        }
        assert!(p.render(p.white_index()).expect("in range").iter().all(|&v| v == 255));
        assert!(p.render(p.black_index()).expect("in range").iter().all(|&v| v == 0));
        assert!(matches!(p.render_into(0, &mut [0u8; 3]), Err(PatternError::Buffer { .. })));
    }
}
