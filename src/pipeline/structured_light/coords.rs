//! Per-camera-pixel projector coordinates as continuous values: the common currency between every
//! structured-light decoder (Gray code, phase shift, colour stripes, sweeping stripe) and the
//! triangulation.
//!
//! Convention (the same as the camera models'): projector pixel `i` covers the continuous interval
//! `[i, i + 1)` in projector pixels, so its centre is `i + 0.5`; the coordinate `0.0` is the left
//! (top) edge of the projector's first column (row). A decoder that knows only the integer column
//! of a pixel reports its centre, `i + 0.5`; sub-pixel decoders (phase shift, stripe-edge
//! interpolation) report the fraction they measured. `NaN` marks a camera pixel without a
//! coordinate.

use super::decode::{ProjectorMap, INVALID};

/// Errors of [`ProjectorCoords::new`]: buffers that do not fit the camera size.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CoordsError {
    /// A buffer's length is not `width * height`.
    #[error("projector {field} buffer holds {found} values, a {width}x{height} camera image has {}", width * height)]
    Size {
        /// `"column"` or `"row"`.
        field: &'static str,
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
        /// The buffer's length.
        found: usize,
    },
}

/// Continuous projector coordinates per camera pixel, row-major (`width * height` entries), in
/// projector pixels (see the module docs for the convention); `NaN` where a pixel has none.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ProjectorCoords {
    /// Camera width, pixels.
    pub width: usize,
    /// Camera height, pixels.
    pub height: usize,
    /// Projector column coordinate per camera pixel, projector pixels (`NaN` = invalid).
    pub column: Vec<f32>,
    /// Projector row coordinate per camera pixel, projector pixels (`NaN` = invalid), when the
    /// coding measured rows; `None` for column-only codings (triangulate against column planes).
    pub row: Option<Vec<f32>>,
}

impl ProjectorCoords {
    /// Coordinates from buffers, checking their sizes against the `width` x `height` camera.
    pub fn new(width: usize, height: usize, column: Vec<f32>, row: Option<Vec<f32>>) -> Result<Self, CoordsError> {
        let n = width * height;
        if column.len() != n {
            return Err(CoordsError::Size { field: "column", width, height, found: column.len() });
        }
        if let Some(r) = &row {
            if r.len() != n {
                return Err(CoordsError::Size { field: "row", width, height, found: r.len() });
            }
        }
        Ok(ProjectorCoords { width, height, column, row })
    }

    /// The centres (`i + 0.5`) of the integer columns (and rows, if `with_rows`) of a decoded
    /// Gray/binary [`ProjectorMap`]; its [`INVALID`] pixels become `NaN`.
    pub fn from_map(map: &ProjectorMap, with_rows: bool) -> Self {
        let centre = |v: &u16| if *v == INVALID { f32::NAN } else { f32::from(*v) + 0.5 };
        ProjectorCoords {
            width: map.width(),
            height: map.height(),
            column: map.columns().iter().map(centre).collect(),
            row: with_rows.then(|| {
                // A pixel is valid only if both axes are: the map invalidates both together.
                map.rows().iter().map(centre).collect()
            }),
        }
    }

    /// Projector `(column, row)` at camera pixel `(x, y)` (row `None` for column-only codings), if
    /// the pixel is valid (finite column, and finite row when rows are present).
    pub fn get(&self, x: usize, y: usize) -> Option<(f32, Option<f32>)> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = y * self.width + x;
        let c = *self.column.get(i)?;
        if !c.is_finite() {
            return None;
        }
        match &self.row {
            None => Some((c, None)),
            Some(r) => {
                let r = *r.get(i)?;
                r.is_finite().then_some((c, Some(r)))
            }
        }
    }

    /// Number of valid camera pixels.
    pub fn valid_count(&self) -> usize {
        (0..self.height)
            .flat_map(|y| (0..self.width).map(move |x| (x, y)))
            .filter(|&(x, y)| self.get(x, y).is_some())
            .count()
    }

    /// Fraction of camera pixels that are valid, 0..=1 (0 for an empty image).
    pub fn valid_fraction(&self) -> f64 {
        match self.width * self.height {
            0 => 0.0,
            n => self.valid_count() as f64 / n as f64,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::structured_light::{decode, DecodeParams, GrayCodePatterns};

    #[test]
    fn sizes_are_checked() {
        assert!(ProjectorCoords::new(2, 2, vec![0.0; 4], None).is_ok());
        let e = ProjectorCoords::new(2, 2, vec![0.0; 3], None).expect_err("short column");
        assert!(matches!(e, CoordsError::Size { field: "column", found: 3, .. }));
        let e = ProjectorCoords::new(2, 2, vec![0.0; 4], Some(vec![0.0; 5])).expect_err("long row");
        assert!(matches!(e, CoordsError::Size { field: "row", found: 5, .. }));
    }

    #[test]
    fn from_map_gives_pixel_centres_and_nan_for_invalid() {
        // Camera = projector, 8x4, pixel-aligned: every pixel decodes to its own column/row, except
        // the last column, whose white and black images are made equal (unlit).
        let pats = GrayCodePatterns::new(8, 4).expect("patterns");
        let mut images: Vec<Vec<u8>> = (0..pats.count()).map(|i| pats.render(i).expect("render")).collect();
        for y in 0..4 {
            images[pats.white_index()][y * 8 + 7] = 0;
        }
        let refs: Vec<&[u8]> = images.iter().map(|v| v.as_slice()).collect();
        let mut map = ProjectorMap::new();
        decode(&pats, &refs, 8, 4, &DecodeParams::default(), &mut map).expect("decode");
        let c = ProjectorCoords::from_map(&map, true);
        assert_eq!(c.get(3, 2), Some((3.5, Some(2.5))));
        assert_eq!(c.get(7, 1), None);
        assert!(c.column[7].is_nan());
        assert_eq!(c.valid_count(), 28);
        let cols_only = ProjectorCoords::from_map(&map, false);
        assert_eq!(cols_only.get(0, 0), Some((0.5, None)));
        assert!((cols_only.valid_fraction() - 28.0 / 32.0).abs() < 1e-12);
    }
}
