//! Per-pixel projector column and row from a captured pattern sequence.
//!
//! Written for memory bandwidth: the images are flat 8-bit buffers, each camera row is decoded on
//! its own (rayon over bands of rows), one pass per pattern/inverse pair streams the two image rows
//! once and shifts the bit into a 16-bit code per pixel, so the working set of a row stays in L1 and
//! nothing is allocated per pixel. The inner loops are branch-free so the compiler vectorises them.
//!
//! A camera pixel is valid when
//! - the white and black images differ by more than [`DecodeParams::black_threshold`] (it is lit
//!   by the projector: `|white - black| > black_threshold`, as the reference decoder does), and
//! - every pattern/inverse pair differs by at least [`DecodeParams::white_threshold`]
//!   (`|pattern - inverse| >= white_threshold`: the bit is read with a margin), and
//! - the decoded column and row lie inside the projector.

use rayon::prelude::*;

use super::patterns::{Coding, GrayCodePatterns};

/// Marks a pixel without a decoded projector coordinate in [`ProjectorMap`].
pub const INVALID: u16 = u16::MAX;

/// Thresholds of the decoder, in 8-bit grey levels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeParams {
    /// A pixel is lit when `|white - black|` exceeds this.
    pub black_threshold: u8,
    /// Every bit needs `|pattern - inverse|` of at least this.
    pub white_threshold: u8,
}

impl Default for DecodeParams {
    /// The thresholds the Gray-code chessboard capture was decoded with by its authors (40 and 5).
    fn default() -> Self {
        Self { black_threshold: 40, white_threshold: 5 }
    }
}

/// Errors of [`decode`]: the image set does not fit the pattern sequence.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The number of images is not the sequence length.
    #[error("{found} images given, the pattern sequence has {expected}")]
    ImageCount {
        /// Images the sequence has.
        expected: usize,
        /// Images given.
        found: usize,
    },
    /// An image buffer's length is not `width * height`.
    #[error("image {index} holds {found} bytes, a {width}x{height} camera image has {}", width * height)]
    ImageSize {
        /// Position of the image in the sequence.
        index: usize,
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
        /// The buffer's length.
        found: usize,
    },
    /// A zero camera width or height.
    #[error("camera image size {width}x{height} pixels is empty")]
    Empty {
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
    },
}

/// Decoded projector coordinates per camera pixel: row-major, `width * height` entries each,
/// [`INVALID`] where the pixel did not decode.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ProjectorMap {
    width: usize,
    height: usize,
    column: Vec<u16>,
    row: Vec<u16>,
}

impl ProjectorMap {
    /// An empty map; [`decode`] sizes it (and keeps its buffers across calls of the same size).
    pub fn new() -> Self {
        Self::default()
    }

    /// Camera width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Camera height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Projector column per camera pixel (projector pixels), [`INVALID`] if not decoded.
    pub fn columns(&self) -> &[u16] {
        &self.column
    }

    /// Projector row per camera pixel (projector pixels), [`INVALID`] if not decoded.
    pub fn rows(&self) -> &[u16] {
        &self.row
    }

    /// Projector `(column, row)` seen by camera pixel `(x, y)`, if it decoded.
    pub fn get(&self, x: usize, y: usize) -> Option<(u16, u16)> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = y * self.width + x;
        let c = *self.column.get(i)?;
        (c != INVALID).then(|| (c, self.row.get(i).copied().unwrap_or(INVALID)))
    }

    /// Number of camera pixels that decoded.
    pub fn valid_count(&self) -> usize {
        self.column.par_chunks(4096).map(|c| c.iter().filter(|&&v| v != INVALID).count()).sum()
    }

    /// Fraction of camera pixels that decoded, 0..=1 (0 for an empty map).
    pub fn valid_fraction(&self) -> f64 {
        match self.column.len() {
            0 => 0.0,
            n => self.valid_count() as f64 / n as f64,
        }
    }

    /// Horizontally adjacent camera pixel pairs that both decoded, and how many of them decode to
    /// projector columns at most `max_step` projector pixels apart: `(pairs, within)`.
    pub fn horizontal_consistency(&self, max_step: u16) -> (u64, u64) {
        if self.width < 2 {
            return (0, 0);
        }
        self.column
            .par_chunks(self.width)
            .map(|r| {
                let (mut pairs, mut within) = (0u64, 0u64);
                for w in r.windows(2) {
                    if w[0] != INVALID && w[1] != INVALID {
                        pairs += 1;
                        within += u64::from(w[0].abs_diff(w[1]) <= max_step);
                    }
                }
                (pairs, within)
            })
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }

    /// The sub-map of the camera rectangle `x0..x0+w`, `y0..y0+h` (clipped to the map).
    pub fn crop(&self, x0: usize, y0: usize, w: usize, h: usize) -> ProjectorMap {
        let x1 = (x0 + w).min(self.width);
        let y1 = (y0 + h).min(self.height);
        let (cw, ch) = (x1.saturating_sub(x0), y1.saturating_sub(y0));
        let mut out = ProjectorMap { width: cw, height: ch, column: Vec::new(), row: Vec::new() };
        for y in y0..y0 + ch {
            let s = y * self.width + x0;
            out.column.extend_from_slice(&self.column[s..s + cw]);
            out.row.extend_from_slice(&self.row[s..s + cw]);
        }
        out
    }
}

/// Pixels per block whose reads are skipped once every pixel in it is invalid (one cache line of
/// each 8-bit image row).
const SKIP_BLOCK: usize = 64;

/// Decodes one pattern/inverse pair group (columns or rows) of one camera row into `code`,
/// marking weak bits in `bad`, then turns the codes into indices and `>= limit` into bad.
#[inline]
fn decode_axis(pairs: &[(&[u8], &[u8])], coding: Coding, wt: u8, limit: u32, code: &mut [u16], bad: &mut [u8]) {
    code.fill(0);
    for &(p, q) in pairs {
        let blocks = code
            .chunks_mut(SKIP_BLOCK)
            .zip(bad.chunks_mut(SKIP_BLOCK))
            .zip(p.chunks(SKIP_BLOCK))
            .zip(q.chunks(SKIP_BLOCK));
        for (((code, bad), p), q) in blocks {
            // A block whose pixels are all already invalid is not read: unlit background and
            // dark squares cost no memory traffic for the remaining pairs.
            if bad.iter().all(|&b| b != 0) {
                continue;
            }
            for (((c, b), &p), &q) in code.iter_mut().zip(bad.iter_mut()).zip(p).zip(q) {
                *c = (*c << 1) | u16::from(p > q);
                *b |= u8::from(p.abs_diff(q) < wt);
            }
        }
    }
    if coding == Coding::Gray {
        for c in code.iter_mut() {
            let mut g = *c;
            g ^= g >> 1;
            g ^= g >> 2;
            g ^= g >> 4;
            g ^= g >> 8;
            *c = g;
        }
    }
    for (c, b) in code.iter().zip(bad.iter_mut()) {
        *b |= u8::from(u32::from(*c) >= limit);
    }
}

/// Decodes the capture `images` (the sequence of `patterns`, each a `width * height` 8-bit grey
/// camera image, row-major) into `out`, resizing it to the camera size if needed.
///
/// Returns the number of valid pixels. Errors when the image count or a buffer size is wrong.
pub fn decode(
    patterns: &GrayCodePatterns,
    images: &[&[u8]],
    width: usize,
    height: usize,
    params: &DecodeParams,
    out: &mut ProjectorMap,
) -> Result<usize, DecodeError> {
    if images.len() != patterns.count() {
        return Err(DecodeError::ImageCount { expected: patterns.count(), found: images.len() });
    }
    if width == 0 || height == 0 {
        return Err(DecodeError::Empty { width, height });
    }
    let n = width * height;
    if let Some((index, img)) = images.iter().enumerate().find(|(_, i)| i.len() != n) {
        return Err(DecodeError::ImageSize { index, width, height, found: img.len() });
    }
    if out.column.len() != n || out.row.len() != n {
        out.column = vec![0; n];
        out.row = vec![0; n];
    }
    out.width = width;
    out.height = height;

    let cb = patterns.column_bits() as usize;
    let rb = patterns.row_bits() as usize;
    let white = images[patterns.white_index()];
    let black = images[patterns.black_index()];
    let coding = patterns.coding();
    let (pw, ph) = (patterns.width(), patterns.height());
    let DecodeParams { black_threshold: bt, white_threshold: wt } = *params;

    // Bands of rows keep rayon's overhead negligible against the per-row work.
    const BAND: usize = 8;
    let valid = out
        .column
        .par_chunks_mut(width * BAND)
        .zip(out.row.par_chunks_mut(width * BAND))
        .enumerate()
        .map_init(
            || (vec![0u8; width], Vec::with_capacity(cb.max(rb))),
            |(bad, pairs), (band, (cols, rows))| {
                let mut valid = 0usize;
                for (i, (col, row)) in cols.chunks_exact_mut(width).zip(rows.chunks_exact_mut(width)).enumerate() {
                    let off = (band * BAND + i) * width;
                    let span = off..off + width;
                    for ((b, &w), &k) in bad.iter_mut().zip(&white[span.clone()]).zip(&black[span.clone()]) {
                        *b = u8::from(w.abs_diff(k) <= bt);
                    }
                    pairs.clear();
                    pairs.extend((0..cb).map(|k| (&images[2 * k][span.clone()], &images[2 * k + 1][span.clone()])));
                    decode_axis(pairs, coding, wt, pw, col, bad);
                    pairs.clear();
                    pairs.extend(
                        (cb..cb + rb).map(|k| (&images[2 * k][span.clone()], &images[2 * k + 1][span.clone()])),
                    );
                    decode_axis(pairs, coding, wt, ph, row, bad);
                    for ((c, r), &b) in col.iter_mut().zip(row.iter_mut()).zip(bad.iter()) {
                        let keep = u16::from(b == 0).wrapping_neg(); // 0xffff keeps, 0 drops
                        *c = (*c & keep) | !keep;
                        *r = (*r & keep) | !keep;
                        valid += usize::from(b == 0);
                    }
                }
                valid
            },
        )
        .sum();
    Ok(valid)
}
