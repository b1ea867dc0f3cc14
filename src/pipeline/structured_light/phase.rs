//! N-step phase shift with Gray-code or multi-frequency (temporal) unwrapping.
//!
//! Decoded coordinates follow [`ProjectorCoords`]: projector pixel `x` covers `[x, x + 1)`, its
//! centre is `x + 0.5`. The formulas below use the pixel index `x` (fringe phase 0 at the centre of
//! column 0); the decoder adds the half pixel at the end.
//!
//! **Patterns.** Phase image `k` of period `P` (pixels) shows
//! `I_k(x) = 127.5 + 127.5 cos(2π x / P - 2π k / N)`, `k = 0..N`, rounded to 8 bits. The camera
//! sees `A + B cos(θ - 2πk/N)` with `θ = 2π x / P`, so `S = Σ I_k sin(2πk/N) = (N/2) B sin θ`,
//! `C = Σ I_k cos(2πk/N) = (N/2) B cos θ`: the wrapped phase is `atan2(S, C)` and the modulation
//! `B = (2/N) sqrt(S² + C²)` (camera grey levels) says how well the pixel sees the fringes.
//!
//! **Gray-code unwrapping** ([`Unwrapping::GrayCode`]) adds the Gray code of the *half-period*
//! cell `j = floor(x / (P/2))`, one bit per image, most significant first (the complementary
//! Gray code idea: one bit finer than the period index). A bit is read against the pixel's own
//! fringe mean `A`, so no white/black or inverse images are needed. The period index `m` is the
//! one putting `x = θP/2π + mP` nearest the centre of cell `j`; a cell read one off at its
//! boundary is then still at most `P/4` from the truth, so stripe edges that are misaligned with
//! the fringe phase (blur, a bit flipped at a cell edge) never cost a period. Camera-side Gray
//! edges and phase wrap are never required to coincide.
//!
//! **Multi-frequency unwrapping** ([`Unwrapping::MultiFrequency`]) projects N steps at each of
//! 2-3 (or more) periods `P_0 < P_1 < … < P_k` with `P_k` longer than the axis: the coarsest phase
//! is absolute, and each finer phase takes the period index that puts it nearest the coarser
//! estimate (hierarchical temporal unwrapping). Each ratio `P_{i+1} / P_i` must stay well below
//! `π / σ_θ` for the phase noise `σ_θ` of the coarser level; ratios of 8 are a safe default.
//!
//! **Decoding** streams the images row by row (rayon over bands of rows): the sums `S`, `C`, `ΣI`
//! of a row are accumulated image by image in `f32` with one multiply-add each, so every image is
//! read once, sequentially; one `atan2` per pixel and frequency follows.

use rayon::prelude::*;

use super::coords::ProjectorCoords;
use crate::pipeline::simd::{has_avx2, run_simd};

/// Which projector axis a block of patterns codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    /// Projector columns (vertical fringes).
    Column,
    /// Projector rows (horizontal fringes).
    Row,
}

/// How the wrapped phase is made absolute.
#[derive(Debug, Clone, PartialEq)]
pub enum Unwrapping {
    /// Gray code of the half-period cells (complementary Gray code), read against the fringe mean.
    GrayCode,
    /// Further fringe periods, pixels, increasing, the last one longer than the coded axis.
    MultiFrequency {
        /// The coarser periods, pixels, strictly increasing and all longer than the base period.
        coarser_periods: Vec<f64>,
    },
}

/// Errors of the phase-shift layout and decoder.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PhaseError {
    /// Fewer than 3 phase steps.
    #[error("{steps} phase steps: at least 3 are needed")]
    Steps {
        /// The requested step count.
        steps: usize,
    },
    /// A period that is not finite and at least 2 pixels.
    #[error("fringe period {period} pixels: it must be finite and at least 2")]
    Period {
        /// The period, pixels.
        period: f64,
    },
    /// Multi-frequency periods not increasing, or the coarsest not longer than the axis.
    #[error("fringe periods {periods:?} pixels must increase and the last must exceed the axis length {axis} pixels")]
    Periods {
        /// All periods, base first, pixels.
        periods: Vec<f64>,
        /// The longest coded axis, projector pixels.
        axis: u32,
    },
    /// A projector side of 0 or more than 32768 pixels.
    #[error("projector resolution {width}x{height} pixels: each side must be 1..=32768")]
    Resolution {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// A pattern index beyond the sequence.
    #[error("pattern index {index} out of range: the sequence has {count} images")]
    Index {
        /// The index.
        index: usize,
        /// Images in the sequence.
        count: usize,
    },
    /// A pattern buffer of the wrong length.
    #[error("pattern buffer holds {found} bytes, the projector needs {expected}")]
    Buffer {
        /// `width * height`.
        expected: usize,
        /// The buffer's length.
        found: usize,
    },
    /// The number of captured images is not the sequence length.
    #[error("{found} images given, the pattern sequence has {expected}")]
    ImageCount {
        /// Images in the sequence.
        expected: usize,
        /// Images given.
        found: usize,
    },
    /// A captured image of the wrong size (or an empty camera).
    #[error("image {index} holds {found} bytes, a {width}x{height} camera image has {}", width * height)]
    ImageSize {
        /// Position in the sequence.
        index: usize,
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
        /// The buffer's length.
        found: usize,
    },
}

/// Thresholds of the phase decoder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhaseDecodeParams {
    /// A pixel is valid when the fringe modulation `B` of every frequency is at least this, 8-bit
    /// camera grey levels (the fringe amplitude: half of peak-to-peak).
    pub min_modulation: f32,
}

impl Default for PhaseDecodeParams {
    /// 8 grey levels of fringe amplitude.
    fn default() -> Self {
        Self { min_modulation: 8.0 }
    }
}

/// What one image of a phase-shift sequence shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PhaseImage {
    /// Fringes of `period` pixels shifted by step `step` of N along `axis`.
    Fringe {
        /// The coded axis.
        axis: Axis,
        /// Fringe period, projector pixels.
        period: f64,
        /// Phase step, `0..N`.
        step: usize,
    },
    /// Gray-code bit `bit` (0 = most significant) of the half-period cell along `axis`.
    GrayBit {
        /// The coded axis.
        axis: Axis,
        /// Bit position from the most significant, 0-based.
        bit: u32,
    },
}

/// An N-step phase-shift sequence for one projector resolution: the column block, then (when
/// rows are coded) the row block. Each block is the fringe images (period by period, base period
/// first, N steps each), then for Gray-code unwrapping the Gray bits.
#[derive(Debug, Clone, PartialEq)]
pub struct PhaseShiftPatterns {
    width: u32,
    height: u32,
    steps: usize,
    periods: Vec<f64>,
    gray: bool,
    rows: bool,
}

/// Bits needed to index `n` values (at least 1).
fn bits_for(n: u64) -> u32 {
    (64 - (n.max(2) - 1).leading_zeros()).max(1)
}

/// The `m` (at most `TILE`) pixels of `image` from `at` as a whole tile: borrowed when whole, else
/// copied into `pad` with zeros after them, so loops over a tile have a fixed trip count.
#[inline(always)]
fn tile_of<'a, const TILE: usize>(image: &'a [u8], at: usize, m: usize, pad: &'a mut [u8; TILE]) -> &'a [u8; TILE] {
    match <&[u8; TILE]>::try_from(&image[at..at + m]) {
        Ok(whole) => whole,
        Err(_) => {
            pad.fill(0);
            pad[..m].copy_from_slice(&image[at..at + m]);
            pad
        }
    }
}

/// Reflected binary Gray code back to the index.
#[inline]
fn gray_to_index(mut g: u32) -> u32 {
    g ^= g >> 16;
    g ^= g >> 8;
    g ^= g >> 4;
    g ^= g >> 2;
    g ^= g >> 1;
    g
}

/// The nearest integer to `x` (|x| < 2^31), by truncation so loops over it vectorise (`round`
/// is a library call without SSE4.1).
#[inline(always)]
fn nearest(x: f32) -> f32 {
    ((x + if x >= 0.0 { 0.5 } else { -0.5 }) as i32) as f32
}

/// `atan2(y, x)` in radians, within 1.2e-5 rad of the exact value (`0` at the origin), branch-free
/// so the compiler vectorises loops over it: the Abramowitz & Stegun 4.4.49 polynomial for the
/// arctangent of the smaller-over-larger ratio, then folded into the right octant. Libm's `atan2`
/// took most of the decoding time; 1.2e-5 rad is 3e-5 pixels of a 16-pixel fringe.
#[inline(always)]
fn fast_atan2(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    let a = if hi > 0.0 { lo / hi } else { 0.0 };
    let s = a * a;
    let mut r = a * (0.999_866 + s * (-0.330_299_5 + s * (0.180_141 + s * (-0.085_133 + s * 0.020_835_1))));
    r = if ay > ax { FRAC_PI_2 - r } else { r };
    r = if x < 0.0 { PI - r } else { r };
    if y < 0.0 {
        -r
    } else {
        r
    }
}

impl PhaseShiftPatterns {
    /// A sequence of `steps`-step fringes of `period` pixels on a `width` x `height` projector,
    /// coding columns (and rows when `rows`), unwrapped as `unwrapping` says.
    pub fn new(
        width: u32,
        height: u32,
        steps: usize,
        period: f64,
        unwrapping: Unwrapping,
        rows: bool,
    ) -> Result<Self, PhaseError> {
        if !(1..=32768).contains(&width) || !(1..=32768).contains(&height) {
            return Err(PhaseError::Resolution { width, height });
        }
        if steps < 3 {
            return Err(PhaseError::Steps { steps });
        }
        if !(period.is_finite() && period >= 2.0) {
            return Err(PhaseError::Period { period });
        }
        let mut periods = vec![period];
        let gray = match unwrapping {
            Unwrapping::GrayCode => true,
            Unwrapping::MultiFrequency { coarser_periods } => {
                periods.extend(coarser_periods);
                let axis = if rows { width.max(height) } else { width };
                let increasing = periods.windows(2).all(|w| w[1] > w[0]);
                let last = periods.last().copied().unwrap_or(period);
                if periods.len() < 2 || !increasing || !last.is_finite() || last <= f64::from(axis) {
                    return Err(PhaseError::Periods { periods, axis });
                }
                false
            }
        };
        Ok(Self { width, height, steps, periods, gray, rows })
    }

    /// Projector width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Projector height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Phase steps per period (N).
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The fringe periods, base (finest) first, projector pixels.
    pub fn periods(&self) -> &[f64] {
        &self.periods
    }

    /// Whether rows are coded too.
    pub fn codes_rows(&self) -> bool {
        self.rows
    }

    fn axis_len(&self, axis: Axis) -> u32 {
        match axis {
            Axis::Column => self.width,
            Axis::Row => self.height,
        }
    }

    /// Gray bits of the half-period cells along `axis` (0 for multi-frequency unwrapping).
    pub fn gray_bits(&self, axis: Axis) -> u32 {
        if !self.gray {
            return 0;
        }
        let cells = (f64::from(self.axis_len(axis)) / (self.periods[0] / 2.0)).ceil() as u64;
        bits_for(cells)
    }

    fn block_len(&self, axis: Axis) -> usize {
        self.steps * self.periods.len() + self.gray_bits(axis) as usize
    }

    /// Images in the sequence.
    pub fn count(&self) -> usize {
        self.block_len(Axis::Column) + if self.rows { self.block_len(Axis::Row) } else { 0 }
    }

    /// What image `index` shows.
    pub fn kind(&self, index: usize) -> Result<PhaseImage, PhaseError> {
        let count = self.count();
        if index >= count {
            return Err(PhaseError::Index { index, count });
        }
        let cl = self.block_len(Axis::Column);
        let (axis, i) = if index < cl { (Axis::Column, index) } else { (Axis::Row, index - cl) };
        let fringes = self.steps * self.periods.len();
        Ok(if i < fringes {
            PhaseImage::Fringe { axis, period: self.periods[i / self.steps], step: i % self.steps }
        } else {
            PhaseImage::GrayBit { axis, bit: (i - fringes) as u32 }
        })
    }

    /// The intensity (0..=1, linear in the wanted light) of image `kind` at projector index
    /// coordinate `t` along its axis.
    fn level(&self, kind: PhaseImage, t: u32) -> f64 {
        match kind {
            PhaseImage::Fringe { period, step, .. } => {
                let a = std::f64::consts::TAU * (f64::from(t) / period - step as f64 / self.steps as f64);
                0.5 + 0.5 * a.cos()
            }
            PhaseImage::GrayBit { axis, bit } => {
                let bits = self.gray_bits(axis);
                let cell = (f64::from(t) / (self.periods[0] / 2.0)).floor() as u32;
                let code = cell ^ (cell >> 1);
                f64::from((code >> (bits - 1 - bit)) & 1)
            }
        }
    }

    /// Renders image `index` into `out` (`width * height` 8-bit grey, row-major), mapping each
    /// wanted linear level `0..=255` through `lut` (the identity when `None`; a gamma
    /// pre-distortion from [`super::gamma::ResponseCurve::compensation_lut`] otherwise).
    pub fn render_into(&self, index: usize, out: &mut [u8], lut: Option<&[u8; 256]>) -> Result<(), PhaseError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if out.len() != w * h {
            return Err(PhaseError::Buffer { expected: w * h, found: out.len() });
        }
        let kind = self.kind(index)?;
        let axis = match kind {
            PhaseImage::Fringe { axis, .. } | PhaseImage::GrayBit { axis, .. } => axis,
        };
        let value = |t: u32| {
            let v = (self.level(kind, t) * 255.0).round().clamp(0.0, 255.0) as u8;
            lut.map_or(v, |l| l[v as usize])
        };
        match axis {
            Axis::Column => {
                let (first, rest) = out.split_at_mut(w);
                for (x, px) in first.iter_mut().enumerate() {
                    *px = value(x as u32);
                }
                for row in rest.chunks_exact_mut(w) {
                    row.copy_from_slice(first);
                }
            }
            Axis::Row => {
                for (y, row) in out.chunks_exact_mut(w).enumerate() {
                    row.fill(value(y as u32));
                }
            }
        }
        Ok(())
    }

    /// Image `index` as a new buffer (see [`Self::render_into`]).
    pub fn render(&self, index: usize, lut: Option<&[u8; 256]>) -> Result<Vec<u8>, PhaseError> {
        let mut out = vec![0u8; self.width as usize * self.height as usize];
        self.render_into(index, &mut out, lut)?;
        Ok(out)
    }

    /// Decodes a captured sequence (8-bit grey camera images of `width` x `height` pixels, in
    /// sequence order) into sub-pixel projector columns (and rows), `NaN` where a pixel's fringe
    /// modulation is below [`PhaseDecodeParams::min_modulation`] or the result leaves the projector.
    pub fn decode(
        &self,
        images: &[&[u8]],
        width: usize,
        height: usize,
        params: &PhaseDecodeParams,
    ) -> Result<ProjectorCoords, PhaseError> {
        if images.len() != self.count() {
            return Err(PhaseError::ImageCount { expected: self.count(), found: images.len() });
        }
        let n = width * height;
        if let Some((index, img)) = images.iter().enumerate().find(|(_, i)| i.len() != n || n == 0) {
            return Err(PhaseError::ImageSize { index, width, height, found: img.len() });
        }
        let cl = self.block_len(Axis::Column);
        let column = self.decode_axis(Axis::Column, &images[..cl], width, params);
        let row = self.rows.then(|| self.decode_axis(Axis::Row, &images[cl..], width, params));
        Ok(ProjectorCoords { width, height, column, row })
    }

    fn decode_axis(&self, axis: Axis, images: &[&[u8]], width: usize, params: &PhaseDecodeParams) -> Vec<f32> {
        let n = images.first().map_or(0, |i| i.len());
        // Every element is written below: zeroed memory (fresh pages, faulted in by the threads
        // that write them) instead of a fill on this thread.
        let mut out = vec![0f32; n];
        let steps = self.steps;
        let (sin, cos): (Vec<f32>, Vec<f32>) = (0..steps)
            .map(|k| {
                let d = std::f64::consts::TAU * k as f64 / steps as f64;
                (d.sin() as f32, d.cos() as f32)
            })
            .unzip();
        let bits = self.gray_bits(axis) as usize;
        let len = self.axis_len(axis) as f32;
        let min_b = params.min_modulation * steps as f32 / 2.0; // compared with sqrt(S² + C²)
        let min_b2 = min_b * min_b;
        let fringes = steps * self.periods.len();
        // Bands of rows are contiguous in every image, so each image is read as one long run;
        // within a band, tiles of `TILE` pixels keep their sums in registers / L1 across images.
        const BAND: usize = 16;
        const TILE: usize = 64;
        let cap = width * BAND;
        let periods = &self.periods;
        let last = periods.len() - 1;
        let inv = 1.0 / steps as f32;
        let (p0, half) = (periods[0] as f32, periods[0] as f32 / 2.0);
        let avx2 = has_avx2();
        out.par_chunks_mut(cap).enumerate().for_each(|(band, out_band)| {
            run_simd(
                avx2,
                #[inline(always)]
                || {
                    let base = band * cap;
                    for (t, out) in out_band.chunks_mut(TILE).enumerate() {
                        let m = out.len();
                        let at = base + t * TILE;
                        // Loops over whole tiles (the tail tile's unused lanes compute on zeros) have a fixed
                        // trip count and no bounds checks, so they vectorise.
                        let (mut ok, mut o, mut w) = ([true; TILE], [0f32; TILE], [0f32; TILE]);
                        let mut pad = [0u8; TILE];
                        // Coarse to fine: the coarsest phase is absolute, each finer one snaps to it.
                        for (f, &period) in periods.iter().enumerate().rev() {
                            let (mut s, mut c, mut sum) = ([0f32; TILE], [0f32; TILE], [0f32; TILE]);
                            for k in 0..steps {
                                let img = tile_of(images[f * steps + k], at, m, &mut pad);
                                let (sk, ck) = (sin[k], cos[k]);
                                for i in 0..TILE {
                                    let v = f32::from(img[i]);
                                    s[i] += v * sk;
                                    c[i] += v * ck;
                                    sum[i] += v;
                                }
                            }
                            let p = period as f32;
                            let scale = p / std::f32::consts::TAU;
                            for i in 0..TILE {
                                ok[i] &= s[i] * s[i] + c[i] * c[i] >= min_b2;
                                let a = fast_atan2(s[i], c[i]) * scale;
                                w[i] = if a < 0.0 { a + p } else { a };
                            }
                            if f < last {
                                for i in 0..TILE {
                                    o[i] = w[i] + p * nearest((o[i] - w[i]) / p);
                                }
                            } else if self.gray {
                                o = w; // unwrapped by the Gray bits below
                            } else {
                                // Absolute: the unused part of the period is centred around the axis.
                                let wrap = len + (p - len) / 2.0;
                                for i in 0..TILE {
                                    o[i] = if w[i] > wrap { w[i] - p } else { w[i] };
                                }
                            }
                            if f == 0 && self.gray {
                                // The fringe mean `A = ΣI / N` is each pixel's own bit threshold.
                                let mut code = [0u32; TILE];
                                let mut mean = [0f32; TILE];
                                for i in 0..TILE {
                                    mean[i] = sum[i] * inv;
                                }
                                for b in 0..bits {
                                    let img = tile_of(images[fringes + b], at, m, &mut pad);
                                    for i in 0..TILE {
                                        code[i] = (code[i] << 1) | u32::from(f32::from(img[i]) > mean[i]);
                                    }
                                }
                                for i in 0..TILE {
                                    let centre = (gray_to_index(code[i]) as f32 + 0.5) * half - 0.5;
                                    o[i] += p0 * nearest((centre - o[i]) / p0);
                                }
                            }
                        }
                        let mut done = [0f32; TILE];
                        for i in 0..TILE {
                            // Index coordinates to continuous ones (pixel centres at `x + 0.5`).
                            let v = o[i];
                            // `|`, not `||`: no branch, so the loop vectorises.
                            let off = !ok[i] | (v < -0.5) | (v > len - 0.5);
                            done[i] = if off { f32::NAN } else { v + 0.5 };
                        }
                        out.copy_from_slice(&done[..m]);
                    }
                },
            )
        });
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A camera that sees projector column `look(x)` in camera column `x`, 1 row per projector row.
    fn capture(p: &PhaseShiftPatterns, cw: usize, look: impl Fn(usize) -> f64, gain: f64, offset: f64) -> Vec<Vec<u8>> {
        let ch = p.height() as usize;
        (0..p.count())
            .map(|i| {
                let kind = p.kind(i).expect("in range");
                let mut img = vec![0u8; cw * ch];
                for y in 0..ch {
                    for x in 0..cw {
                        let t = look(x);
                        let level = match kind {
                            PhaseImage::Fringe { period, step, .. } => {
                                let a = std::f64::consts::TAU * (t / period - step as f64 / p.steps() as f64);
                                0.5 + 0.5 * a.cos()
                            }
                            PhaseImage::GrayBit { .. } => p.level(kind, t.round().max(0.0) as u32),
                        };
                        img[y * cw + x] = (offset + gain * level).round().clamp(0.0, 255.0) as u8;
                    }
                }
                img
            })
            .collect()
    }

    #[test]
    fn fast_atan2_is_within_its_bound_everywhere() {
        let mut worst = 0.0f64;
        for i in 0..20_000 {
            let t = i as f64 / 20_000.0 * std::f64::consts::TAU;
            for r in [1e-3, 0.7, 250.0] {
                let (y, x) = ((r * t.sin()) as f32, (r * t.cos()) as f32);
                let exact = f64::from(y).atan2(f64::from(x));
                let mut d = (f64::from(fast_atan2(y, x)) - exact).abs();
                d = d.min((d - std::f64::consts::TAU).abs()); // -π and π are the same angle
                worst = worst.max(d);
            }
        }
        assert!(worst < 1.2e-5, "worst error {worst} rad");
        assert_eq!(fast_atan2(0.0, 0.0), 0.0);
    }

    #[test]
    fn wrapped_phase_of_a_synthetic_sinusoid_gives_sub_pixel_columns() {
        for steps in [3, 4, 5, 8] {
            let p = PhaseShiftPatterns::new(200, 2, steps, 20.0, Unwrapping::GrayCode, false).expect("valid");
            // Camera column x sees projector column 0.37 x + 3.1 (continuous).
            let look = |x: usize| 0.37 * x as f64 + 3.1;
            let imgs = capture(&p, 500, look, 200.0, 20.0);
            let s: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
            let out = p.decode(&s, 500, 2, &PhaseDecodeParams::default()).expect("decodes");
            let mut worst = 0.0f64;
            for x in 0..500 {
                let t = look(x);
                if t > 199.0 {
                    continue;
                }
                let d = out.column[x] as f64;
                worst = worst.max((d - (t + 0.5)).abs());
            }
            assert!(worst < 0.15, "{steps} steps: worst column error {worst}");
            assert!(out.row.is_none());
        }
    }

    #[test]
    fn gray_unwrapping_survives_cells_read_one_off() {
        // The Gray bits are read at a camera column shifted by a quarter period: every cell edge is
        // misaligned with the fringe phase, and the result must still be exact.
        let p = PhaseShiftPatterns::new(256, 1, 4, 16.0, Unwrapping::GrayCode, false).expect("valid");
        assert_eq!(p.gray_bits(Axis::Column), 5);
        let imgs: Vec<Vec<u8>> = (0..p.count())
            .map(|i| {
                let kind = p.kind(i).expect("in range");
                (0..256u32)
                    .map(|x| {
                        let t = match kind {
                            PhaseImage::GrayBit { .. } => (x as i64 + if x % 2 == 0 { 3 } else { -3 }).clamp(0, 255),
                            _ => i64::from(x),
                        };
                        (20.0 + 200.0 * p.level(kind, t as u32)).round() as u8
                    })
                    .collect()
            })
            .collect();
        let s: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
        let out = p.decode(&s, 256, 1, &PhaseDecodeParams::default()).expect("decodes");
        for (x, &c) in out.column.iter().enumerate() {
            assert!((c - (x as f32 + 0.5)).abs() < 0.1, "column {x} decoded {c}");
        }
    }

    #[test]
    fn multi_frequency_unwrapping_and_rows() {
        let mf = Unwrapping::MultiFrequency { coarser_periods: vec![96.0, 700.0] };
        let p = PhaseShiftPatterns::new(640, 480, 4, 12.0, mf, true).expect("valid");
        assert_eq!(p.count(), 24);
        // Identity camera at the projector resolution.
        let imgs: Vec<Vec<u8>> = (0..p.count()).map(|i| p.render(i, None).expect("in range")).collect();
        let s: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
        let out = p.decode(&s, 640, 480, &PhaseDecodeParams::default()).expect("decodes");
        let rows = out.row.as_ref().expect("rows coded");
        for y in (0..480).step_by(7) {
            for x in 0..640 {
                let i = y * 640 + x;
                assert!((out.column[i] - (x as f32 + 0.5)).abs() < 0.1, "({x},{y}) column {}", out.column[i]);
                assert!((rows[i] - (y as f32 + 0.5)).abs() < 0.1, "({x},{y}) row {}", rows[i]);
            }
        }
    }

    /// A last tile cut short by the image's end (its missing pixels padded with zeros) decodes each
    /// of its pixels as a whole tile does: the first 150 pixels of a capture (two tiles of 64 and 22
    /// pixels) decoded on their own give, bit for bit, what the whole capture gives them.
    #[test]
    fn a_short_last_tile_decodes_like_a_whole_one() {
        let p = PhaseShiftPatterns::new(640, 480, 4, 16.0, Unwrapping::GrayCode, true).expect("valid");
        let imgs: Vec<Vec<u8>> = (0..p.count()).map(|i| p.render(i, None).expect("in range")).collect();
        let whole: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
        let full = p.decode(&whole, 640, 480, &PhaseDecodeParams::default()).expect("decodes");
        let short: Vec<&[u8]> = imgs.iter().map(|i| &i[..150]).collect();
        let part = p.decode(&short, 50, 3, &PhaseDecodeParams::default()).expect("decodes");
        assert_eq!(part.valid_count(), 150);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&part.column), bits(&full.column[..150]));
        let (part_rows, full_rows) = (part.row.as_ref().expect("rows"), full.row.as_ref().expect("rows"));
        assert_eq!(bits(part_rows), bits(&full_rows[..150]));
    }

    #[test]
    fn flat_pixels_are_invalid_and_bad_layouts_are_refused() {
        let p = PhaseShiftPatterns::new(64, 4, 3, 8.0, Unwrapping::GrayCode, false).expect("valid");
        let imgs = vec![vec![100u8; 64 * 4]; p.count()];
        let s: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
        let out = p.decode(&s, 64, 4, &PhaseDecodeParams::default()).expect("decodes");
        assert_eq!(out.valid_count(), 0);
        assert!(matches!(p.decode(&s[1..], 64, 4, &PhaseDecodeParams::default()), Err(PhaseError::ImageCount { .. })));
        assert!(matches!(p.decode(&s, 63, 4, &PhaseDecodeParams::default()), Err(PhaseError::ImageSize { .. })));
        assert_eq!(
            PhaseShiftPatterns::new(64, 4, 2, 8.0, Unwrapping::GrayCode, false),
            Err(PhaseError::Steps { steps: 2 })
        );
        let short = Unwrapping::MultiFrequency { coarser_periods: vec![40.0] };
        assert!(matches!(PhaseShiftPatterns::new(64, 4, 3, 8.0, short, false), Err(PhaseError::Periods { .. })));
        let down = Unwrapping::MultiFrequency { coarser_periods: vec![6.0, 100.0] };
        assert!(matches!(PhaseShiftPatterns::new(64, 4, 3, 8.0, down, false), Err(PhaseError::Periods { .. })));
        assert!(matches!(p.render(p.count(), None), Err(PhaseError::Index { .. })));
    }
}
