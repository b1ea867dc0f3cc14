//! Per-pixel projector column and row from a captured pattern sequence.
//!
//! Written for memory bandwidth: the images are flat 8-bit buffers decoded in bands of rows (rayon
//! over bands). A band's rows are contiguous in every image, so one pass per pattern/inverse pair
//! streams two long runs the hardware prefetcher follows (row-sized runs switching between 42
//! images were too short for it), and nothing is allocated per pixel. Per pair the work stays in
//! 8-bit lanes (bit shifted into byte accumulators, margin kept as a running minimum), branch-free so
//! the compiler vectorises it; a cache line's worth of pixels that are all invalid is not read again.
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

    /// A map from its buffers (tests build maps without decoding images).
    #[cfg(test)]
    pub(crate) fn from_parts(width: usize, height: usize, column: Vec<u16>, row: Vec<u16>) -> Self {
        assert!(column.len() == width * height && row.len() == width * height);
        Self { width, height, column, row }
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

/// Decodes one pattern/inverse pair group (columns or rows) of one camera row into `code` (the
/// projector index, not yet range-checked), lowering each pixel's margin `m` to its weakest pair.
///
/// Everything per pair stays in 8-bit lanes (16 or 32 pixels per vector instruction): the bit is
/// `p -sat q != 0`, shifted into one of two byte accumulators (`hi` gets the bits above the last
/// 8), and the margin is `min(m, |p - q| | floor)`: one saturating subtraction each way, an or and a
/// min. Only the final Gray-to-index step widens to 16 bits, once per pixel and axis.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn decode_axis(
    pairs: &[(&[u8], &[u8])],
    coding: Coding,
    wt: u8,
    floor: u8,
    code: &mut [u16],
    m: &mut [u8],
    hi: &mut [u8],
    lo: &mut [u8],
) {
    let split = pairs.len().saturating_sub(8);
    hi.fill(0);
    lo.fill(0);
    for (k, &(p, q)) in pairs.iter().enumerate() {
        let acc: &mut [u8] = if k < split { hi } else { lo };
        let blocks = acc
            .chunks_mut(SKIP_BLOCK)
            .zip(m.chunks_mut(SKIP_BLOCK))
            .zip(p.chunks(SKIP_BLOCK))
            .zip(q.chunks(SKIP_BLOCK));
        for (((acc, m), p), q) in blocks {
            // A block whose pixels are all already invalid is not read: unlit background and
            // dark squares cost no memory traffic for the remaining pairs.
            if m.iter().fold(0u8, |a, &b| a.max(b)) < wt {
                continue;
            }
            for (((a, m), &p), &q) in acc.iter_mut().zip(m.iter_mut()).zip(p).zip(q) {
                let (d1, d2) = (p.saturating_sub(q), q.saturating_sub(p));
                *a = a.wrapping_add(*a) | u8::from(d1 != 0);
                *m = (*m).min(d1 | d2 | floor);
            }
        }
    }
    for ((c, &h), &l) in code.iter_mut().zip(hi.iter()).zip(lo.iter()) {
        *c = (u16::from(h) << 8) | u16::from(l);
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
}

/// What every row of one [`decode`] call shares.
struct RowJob<'a> {
    images: &'a [&'a [u8]],
    white: &'a [u8],
    black: &'a [u8],
    cb: usize,
    rb: usize,
    coding: Coding,
    pw: u32,
    ph: u32,
    bt: u8,
    wt: u8,
    floor: u8,
}

/// One row's outputs and a worker's scratch buffers (each `width` long).
struct RowBuffers<'b, 'a> {
    col: &'b mut [u16],
    row: &'b mut [u16],
    m: &'b mut [u8],
    hi: &'b mut [u8],
    lo: &'b mut [u8],
    pairs: &'b mut Vec<(&'a [u8], &'a [u8])>,
}

/// Decodes the camera row starting at pixel `off` into `b.col` and `b.row`; returns its valid
/// pixels.
#[inline(always)]
fn decode_row<'a>(job: &RowJob<'a>, off: usize, b: RowBuffers<'_, 'a>) -> usize {
    let RowBuffers { col, row, m, hi, lo, pairs } = b;
    let span = off..off + col.len();
    let (images, wt, floor) = (job.images, job.wt, job.floor);
    for ((m, &w), &k) in m.iter_mut().zip(&job.white[span.clone()]).zip(&job.black[span.clone()]) {
        *m = if w.abs_diff(k) > job.bt { 255 } else { 0 };
    }
    pairs.clear();
    pairs.extend((0..job.cb).map(|k| (&images[2 * k][span.clone()], &images[2 * k + 1][span.clone()])));
    decode_axis(pairs, job.coding, wt, floor, col, m, hi, lo);
    pairs.clear();
    pairs.extend((job.cb..job.cb + job.rb).map(|k| (&images[2 * k][span.clone()], &images[2 * k + 1][span.clone()])));
    decode_axis(pairs, job.coding, wt, floor, row, m, hi, lo);
    let mut valid = 0;
    for ((c, r), &m) in col.iter_mut().zip(row.iter_mut()).zip(m.iter()) {
        let ok = m >= wt && u32::from(*c) < job.pw && u32::from(*r) < job.ph;
        let keep = u16::from(ok).wrapping_neg(); // 0xffff keeps, 0 drops
        *c = (*c & keep) | !keep;
        *r = (*r & keep) | !keep;
        valid += usize::from(ok);
    }
    valid
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

    // A pixel's margin `m` starts at 255 when it is lit (`|white - black| > bt`) and 0 when not,
    // then drops to its weakest pair's `|pattern - inverse|`; it is valid when `m >= max(wt, 1)`.
    // With `wt = 0` every pair passes: `floor = 1` keeps lit pixels' margins at 1 or more.
    let floor = u8::from(wt == 0);
    let wt = wt.max(1);
    let job = RowJob { images, white, black, cb, rb, coding, pw, ph, bt, wt, floor };
    // Bands of rows keep rayon's overhead negligible against the per-row work.
    const BAND: usize = 32;
    let valid = out
        .column
        .par_chunks_mut(width * BAND)
        .zip(out.row.par_chunks_mut(width * BAND))
        .enumerate()
        .map_init(
            || (vec![0u8; 3 * width * BAND], Vec::with_capacity(cb.max(rb))),
            |(scratch, pairs), (band, (col, row))| {
                // The band's rows are contiguous in every image, so each pass streams one
                // `width * BAND` run per image: long enough for the hardware prefetcher.
                let n = col.len();
                let (m, rest) = scratch.split_at_mut(n);
                let (hi, lo) = rest.split_at_mut(n);
                let lo = &mut lo[..n];
                decode_row(&job, band * BAND * width, RowBuffers { col, row, m, hi: &mut hi[..n], lo, pairs })
            },
        )
        .sum();
    Ok(valid)
}
