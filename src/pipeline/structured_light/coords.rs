//! Decoded projector coordinates per camera pixel, as `f32` so sub-pixel decoders (phase shift,
//! stripe interpolation) and integer ones (Gray code) share one output type.

use super::decode::{ProjectorMap, INVALID};

/// Projector coordinates seen by each camera pixel, row-major `width * height`, in projector pixel
/// index coordinates (the centre of projector pixel `x` is at `x`); `NaN` where a pixel did not decode.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ProjectorCoords {
    /// Camera width, pixels.
    pub width: usize,
    /// Camera height, pixels.
    pub height: usize,
    /// Projector column per camera pixel, projector pixels (`NaN` = invalid).
    pub column: Vec<f32>,
    /// Projector row per camera pixel, projector pixels (`NaN` = invalid), when the coding has rows.
    pub row: Option<Vec<f32>>,
}

impl ProjectorCoords {
    /// Camera pixels whose column decoded.
    pub fn valid_count(&self) -> usize {
        self.column.iter().filter(|c| !c.is_nan()).count()
    }

    /// Fraction of camera pixels whose column decoded, 0..=1 (0 when empty).
    pub fn valid_fraction(&self) -> f64 {
        match self.column.len() {
            0 => 0.0,
            n => self.valid_count() as f64 / n as f64,
        }
    }
}

impl From<&ProjectorMap> for ProjectorCoords {
    /// The Gray-code map as coordinates: integer columns and rows, `INVALID` as `NaN`.
    fn from(map: &ProjectorMap) -> Self {
        let f = |v: &[u16]| v.iter().map(|&c| if c == INVALID { f32::NAN } else { f32::from(c) }).collect();
        ProjectorCoords { width: map.width(), height: map.height(), column: f(map.columns()), row: Some(f(map.rows())) }
    }
}
