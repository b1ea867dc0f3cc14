//! One interface over every structured-light coding: how many images, what image `i` shows, and
//! the decode of the captured images into [`ProjectorCoords`]. Patterns and captures are 8-bit RGB,
//! row-major (`3 * width * height` bytes); grey codings project grey and read the captures' luma.

use super::coords::ProjectorCoords;
use super::debruijn::{DeBruijnDecodeParams, DeBruijnError, DeBruijnStripes};
use super::decode::{decode, DecodeError, DecodeParams, ProjectorMap};
use super::patterns::{GrayCodePatterns, PatternError};
use super::phase::{PhaseDecodeParams, PhaseError, PhaseShiftPatterns};
use super::stripe::{StripeError, SweepingStripe};

/// A coding with its decoder settings.
#[derive(Debug, Clone, PartialEq)]
pub enum PatternSet {
    /// Gray code (or binary) with inverses, white and black: integer columns and rows.
    Gray(GrayCodePatterns, DecodeParams),
    /// N-step phase shift with Gray-code or multi-frequency unwrapping: sub-pixel columns (rows).
    PhaseShift(PhaseShiftPatterns, PhaseDecodeParams),
    /// One-shot De Bruijn colour stripes: columns.
    DeBruijn(DeBruijnStripes, DeBruijnDecodeParams),
    /// A single sweeping stripe: sub-pixel columns; the value is the minimum peak contrast, grey levels.
    SweepingStripe(SweepingStripe, u8),
}

/// Errors of [`PatternSet`], wrapping the coding's own error.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodesError {
    /// Gray-code layout.
    #[error(transparent)]
    Gray(#[from] PatternError),
    /// Gray-code decoding.
    #[error(transparent)]
    GrayDecode(#[from] DecodeError),
    /// Phase shift.
    #[error(transparent)]
    Phase(#[from] PhaseError),
    /// De Bruijn stripes.
    #[error(transparent)]
    DeBruijn(#[from] DeBruijnError),
    /// Sweeping stripe.
    #[error(transparent)]
    Stripe(#[from] StripeError),
    /// Not one capture per pattern, or a capture of the wrong size.
    #[error("{found} captures of {bytes} bytes for {expected} patterns of a {width}x{height} RGB camera")]
    Captures {
        /// Patterns in the set.
        expected: usize,
        /// Captures given.
        found: usize,
        /// Bytes of the first wrong capture (or of the first one).
        bytes: usize,
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
    },
}

/// Grey to RGB, each value on all three channels.
fn grey_to_rgb(g: &[u8]) -> Vec<u8> {
    g.iter().flat_map(|&v| [v, v, v]).collect()
}

/// Integer luma of RGB (Rec. 601 weights, as the image crate's grey conversion).
fn luma(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3)
        .map(|p| ((u32::from(p[0]) * 299 + u32::from(p[1]) * 587 + u32::from(p[2]) * 114 + 500) / 1000) as u8)
        .collect()
}

impl PatternSet {
    /// Projector resolution (width, height), pixels.
    pub fn resolution(&self) -> (u32, u32) {
        match self {
            PatternSet::Gray(p, _) => (p.width(), p.height()),
            PatternSet::PhaseShift(p, _) => (p.width(), p.height()),
            PatternSet::DeBruijn(p, _) => (p.width(), p.height()),
            PatternSet::SweepingStripe(p, _) => (p.width(), p.height()),
        }
    }

    /// Images in the sequence.
    pub fn count(&self) -> usize {
        match self {
            PatternSet::Gray(p, _) => p.count(),
            PatternSet::PhaseShift(p, _) => p.count(),
            PatternSet::DeBruijn(..) => 1,
            PatternSet::SweepingStripe(p, _) => p.count(),
        }
    }

    /// Pattern `index` as RGB bytes (`3 * width * height`), each grey level mapped through `lut`
    /// when given (gamma pre-distortion; binary patterns pass unchanged through a monotone LUT
    /// that keeps 0 and 255).
    pub fn render_rgb(&self, index: usize, lut: Option<&[u8; 256]>) -> Result<Vec<u8>, CodesError> {
        let map = |v: Vec<u8>| match lut {
            Some(l) => v.into_iter().map(|x| l[x as usize]).collect(),
            None => v,
        };
        Ok(match self {
            PatternSet::Gray(p, _) => grey_to_rgb(&map(p.render(index)?)),
            PatternSet::PhaseShift(p, _) => grey_to_rgb(&p.render(index, lut)?),
            PatternSet::DeBruijn(p, _) => {
                if index != 0 {
                    return Err(CodesError::Stripe(StripeError::Index { index, count: 1 }));
                }
                map(p.render())
            }
            PatternSet::SweepingStripe(p, _) => grey_to_rgb(&map(p.render(index)?)),
        })
    }

    /// Decodes the captures (RGB, `3 * width * height` bytes each, in sequence order).
    pub fn decode(&self, captures: &[&[u8]], width: usize, height: usize) -> Result<ProjectorCoords, CodesError> {
        let bad = captures.iter().find(|c| c.len() != 3 * width * height);
        if captures.len() != self.count() || bad.is_some() {
            return Err(CodesError::Captures {
                expected: self.count(),
                found: captures.len(),
                bytes: bad.or(captures.first()).map_or(0, |c| c.len()),
                width,
                height,
            });
        }
        let grey: Vec<Vec<u8>> = match self {
            PatternSet::DeBruijn(..) => Vec::new(), // decodes the colour capture itself
            _ => captures.iter().map(|c| luma(c)).collect(),
        };
        let g: Vec<&[u8]> = grey.iter().map(Vec::as_slice).collect();
        Ok(match self {
            PatternSet::Gray(p, prm) => {
                let mut map = ProjectorMap::new();
                decode(p, &g, width, height, prm, &mut map)?;
                ProjectorCoords::from_map(&map, true)
            }
            PatternSet::PhaseShift(p, prm) => p.decode(&g, width, height, prm)?,
            PatternSet::SweepingStripe(p, c) => p.decode(&g, width, height, *c)?,
            PatternSet::DeBruijn(p, prm) => p.decode(captures[0], width, height, prm)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Renders every pattern and "captures" it with a camera identical to the projector.
    fn identity(set: &PatternSet) -> Vec<Vec<u8>> {
        (0..set.count()).map(|i| set.render_rgb(i, None).expect("in range")).collect()
    }

    #[test]
    fn gray_set_round_trips_to_pixel_centres_and_checks_captures() {
        let set = PatternSet::Gray(GrayCodePatterns::new(40, 24).expect("valid"), DecodeParams::default());
        assert_eq!(set.resolution(), (40, 24));
        let caps = identity(&set);
        let c: Vec<&[u8]> = caps.iter().map(Vec::as_slice).collect();
        let out = set.decode(&c, 40, 24).expect("decodes");
        assert_eq!(out.get(13, 7), Some((13.5, Some(7.5))));
        assert!(matches!(set.decode(&c[1..], 40, 24), Err(CodesError::Captures { .. })));
        assert!(matches!(set.decode(&c, 41, 24), Err(CodesError::Captures { .. })));
    }

    #[test]
    fn phase_and_stripe_sets_round_trip_and_de_bruijn_has_one_pattern() {
        let phase =
            PhaseShiftPatterns::new(64, 16, 4, 8.0, super::super::phase::Unwrapping::GrayCode, true).expect("valid");
        let set = PatternSet::PhaseShift(phase, PhaseDecodeParams::default());
        let caps = identity(&set);
        let c: Vec<&[u8]> = caps.iter().map(Vec::as_slice).collect();
        let out = set.decode(&c, 64, 16).expect("decodes");
        let (col, row) = out.get(21, 9).expect("valid");
        assert!((col - 21.5).abs() < 0.05 && (row.expect("rows") - 9.5).abs() < 0.05, "{col} {row:?}");

        let set = PatternSet::SweepingStripe(SweepingStripe::new(64, 4, 3, 1).expect("valid"), 20);
        let caps = identity(&set);
        let c: Vec<&[u8]> = caps.iter().map(Vec::as_slice).collect();
        let out = set.decode(&c, 64, 4).expect("decodes");
        assert!((out.column[30] - 30.5).abs() < 0.05, "{}", out.column[30]);

        let db = DeBruijnStripes::new(64, 4, 5, 3, 4).expect("valid");
        let set = PatternSet::DeBruijn(db, DeBruijnDecodeParams::default());
        assert_eq!(set.count(), 1);
        assert!(set.render_rgb(1, None).is_err());
    }
}
