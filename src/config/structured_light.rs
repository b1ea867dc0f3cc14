//! `[reconstruction.structured_light]`: the settings of method `structured-light` (pattern coding,
//! decoder thresholds, triangulation and fusion), and their checks.

use serde::Deserialize;

use super::{Method, ProjectorConfig, RigConfig};

/// How projector indices are coded into stripe images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum StripeCoding {
    /// Reflected binary Gray code (a mis-read stripe edge costs one projector pixel).
    #[default]
    Gray,
    /// Plain binary.
    Binary,
}

/// `[reconstruction.structured_light]`.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct StructuredLightConfig {
    /// Stripe coding: `"gray"` (default) or `"binary"`.
    #[serde(default)]
    pub coding: StripeCoding,
    /// Also project row patterns and triangulate camera ray against projector ray (midpoint, with
    /// [`StructuredLightConfig::max_ray_gap_m`]); without rows (default) the camera ray is cut with the
    /// plane of the decoded projector column, and half the patterns are projected.
    #[serde(default)]
    pub rows: bool,
    /// A pixel is lit when its white and black frames differ by more than this, 8-bit grey levels.
    #[serde(default = "default_black_threshold")]
    pub black_threshold: u8,
    /// Every pattern/inverse pair must differ by at least this, 8-bit grey levels.
    #[serde(default = "default_white_threshold")]
    pub white_threshold: u8,
    /// Ray-ray triangulation: largest distance between the camera and projector rays, metres.
    #[serde(default = "default_max_ray_gap")]
    pub max_ray_gap_m: f64,
    /// Interpolate the projector column between the stripe edges seen along each camera row
    /// (sub-pixel); `false` uses the decoded column's centre (`index + 0.5`).
    #[serde(default = "yes")]
    pub subpixel: bool,
    /// A point is an outlier unless at least this many of its 8 range-image neighbours lie within
    /// [`StructuredLightConfig::neighbour_tolerance_m`] of it along the camera's view axis (0..=8).
    #[serde(default = "default_min_neighbours")]
    pub min_neighbours: u8,
    /// Depth difference to a range-image neighbour that still counts as the same surface, metres.
    #[serde(default = "default_neighbour_tolerance")]
    pub neighbour_tolerance_m: f64,
    /// Merged cloud: neighbours of the statistical outlier test.
    #[serde(default = "default_outlier_neighbours")]
    pub outlier_neighbours: usize,
    /// Merged cloud: a point is an outlier when its mean distance to its neighbours exceeds the
    /// cloud's mean of that figure by more than this many standard deviations.
    #[serde(default = "default_outlier_std_ratio")]
    pub outlier_std_ratio: f64,
    /// TSDF truncation distance, voxels of the reconstruction grid.
    #[serde(default = "default_truncation_voxels")]
    pub truncation_voxels: f64,
    /// A camera pixel without a point whose fully lit frame is darker than this (8-bit grey) saw the
    /// empty background, so its ray is free space in the fusion; other pixels without a point
    /// (projector shadows, weak codes) are unknown. 0 (default) treats every such pixel as unknown:
    /// only surface points then carve free space.
    #[serde(default)]
    pub free_below: u8,
}

fn default_black_threshold() -> u8 {
    40
}
fn default_white_threshold() -> u8 {
    5
}
fn default_max_ray_gap() -> f64 {
    0.002
}
fn yes() -> bool {
    true
}
fn default_min_neighbours() -> u8 {
    5
}
fn default_neighbour_tolerance() -> f64 {
    0.002
}
fn default_outlier_neighbours() -> usize {
    16
}
fn default_outlier_std_ratio() -> f64 {
    3.0
}
fn default_truncation_voxels() -> f64 {
    3.0
}

impl Default for StructuredLightConfig {
    fn default() -> Self {
        StructuredLightConfig {
            coding: StripeCoding::default(),
            rows: false,
            black_threshold: default_black_threshold(),
            white_threshold: default_white_threshold(),
            max_ray_gap_m: default_max_ray_gap(),
            subpixel: true,
            min_neighbours: default_min_neighbours(),
            neighbour_tolerance_m: default_neighbour_tolerance(),
            outlier_neighbours: default_outlier_neighbours(),
            outlier_std_ratio: default_outlier_std_ratio(),
            truncation_voxels: default_truncation_voxels(),
            free_below: 0,
        }
    }
}

/// Checks of method `structured-light` and of the projector's timing, reported through `bad(key, message)`.
pub(crate) fn validate(config: &RigConfig, bad: &mut dyn FnMut(&str, String)) {
    if let Some(ProjectorConfig::Sim(p)) = &config.projector {
        if !(p.latency_ms.is_finite() && (0.0..=10_000.0).contains(&p.latency_ms)) {
            bad("projector.latency_ms", format!("must be 0..=10000 milliseconds, got {}", p.latency_ms));
        }
        if !(p.frame_period_ms.is_finite() && (0.0..=1_000.0).contains(&p.frame_period_ms)) {
            bad("projector.frame_period_ms", format!("must be 0..=1000 milliseconds, got {}", p.frame_period_ms));
        }
    }
    if config.reconstruction.method != Method::StructuredLight {
        return;
    }
    if config.projector.is_none() {
        bad("projector", "method \"structured-light\" needs a [projector]".into());
    }
    let s = &config.reconstruction.structured_light;
    let key = |k: &str| format!("reconstruction.structured_light.{k}");
    if !(s.max_ray_gap_m.is_finite() && s.max_ray_gap_m > 0.0) {
        bad(&key("max_ray_gap_m"), "must be a positive number of metres".into());
    }
    if s.min_neighbours > 8 {
        bad(&key("min_neighbours"), format!("must be 0..=8, got {}", s.min_neighbours));
    }
    if !(s.neighbour_tolerance_m.is_finite() && s.neighbour_tolerance_m > 0.0) {
        bad(&key("neighbour_tolerance_m"), "must be a positive number of metres".into());
    }
    if !(1..=256).contains(&s.outlier_neighbours) {
        bad(&key("outlier_neighbours"), format!("must be 1..=256, got {}", s.outlier_neighbours));
    }
    if !(s.outlier_std_ratio.is_finite() && s.outlier_std_ratio > 0.0) {
        bad(&key("outlier_std_ratio"), "must be a positive number".into());
    }
    if !(s.truncation_voxels.is_finite() && s.truncation_voxels > 0.0) {
        bad(&key("truncation_voxels"), "must be a positive number of voxels".into());
    }
}
