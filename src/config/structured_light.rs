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
    /// N-step phase shift (`steps`, `periods_px`, `unwrapping`): sub-pixel columns (rows with `rows`).
    PhaseShift,
    /// One-shot De Bruijn colour stripes (`debruijn_colours`, `debruijn_window`, `stripe_px`): columns.
    #[serde(rename = "debruijn")]
    DeBruijn,
    /// A single stripe swept across the columns (`stripe_px`, `sweep_step_px`): sub-pixel columns.
    Sweep,
}

impl StripeCoding {
    /// Whether the coding is a Gray/binary stripe sequence (decoded with the thresholds, rows optional,
    /// stripe-edge sub-pixel columns).
    pub fn is_binary_stripes(self) -> bool {
        matches!(self, StripeCoding::Gray | StripeCoding::Binary)
    }
}

/// How the wrapped phase of `coding = "phase-shift"` is made absolute.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, serde::Serialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum PhaseUnwrapping {
    /// Gray code of the fringes' half-period cells (one period in `periods_px`).
    #[default]
    Gray,
    /// Further, coarser fringe periods (`periods_px` increasing, the last longer than the coded axis).
    MultiFrequency,
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
    /// Phase shift: phase steps per fringe period (>= 3).
    #[serde(default = "default_steps")]
    pub steps: usize,
    /// Phase shift: fringe periods, projector pixels; the first is the fine period. Gray unwrapping
    /// takes exactly one; multi-frequency takes two or more, increasing, the last longer than the
    /// coded axis.
    #[serde(default = "default_periods")]
    pub periods_px: Vec<f64>,
    /// Phase shift: `"gray"` (default) or `"multi-frequency"`.
    #[serde(default)]
    pub unwrapping: PhaseUnwrapping,
    /// Phase shift: a pixel is valid when every frequency's fringe amplitude is at least this, 8-bit grey levels.
    #[serde(default = "default_min_modulation")]
    pub min_modulation: f32,
    /// Before the scan, project uniform grey levels, fit the projector-camera response (gamma,
    /// black and white levels; reported in `report.json`) and pre-distort the phase-shift fringes
    /// with its inverse so they reach the camera as sinusoids.
    #[serde(default)]
    pub gamma_compensation: bool,
    /// Gamma measurement: pixels whose white minus black frame differ by less than this (8-bit grey)
    /// are left out of the fit (background, shadows).
    #[serde(default = "default_gamma_min_contrast")]
    pub gamma_min_contrast: f64,
    /// De Bruijn: colours (3..=6).
    #[serde(default = "default_colours")]
    pub debruijn_colours: usize,
    /// De Bruijn: stripes of a window that identify its position (1..=8).
    #[serde(default = "default_window")]
    pub debruijn_window: usize,
    /// De Bruijn stripe width, and the sweeping stripe's width, projector pixels.
    #[serde(default = "default_stripe_px")]
    pub stripe_px: u32,
    /// Sweep: projector columns the stripe moves per frame (1..=`stripe_px`).
    #[serde(default = "default_sweep_step")]
    pub sweep_step_px: u32,
    /// Sweep: minimum peak contrast of the stripe over the pixel's darkest frame, 8-bit grey levels.
    #[serde(default = "default_sweep_contrast")]
    pub sweep_min_contrast: u8,
    /// Camera exposure per pattern, milliseconds; must be a whole multiple (1, 2, ..) of
    /// `projector.frame_period_ms` so every exposure integrates whole projector refreshes. The
    /// sequencer keeps each pattern on screen this long after it appeared before showing the next.
    /// The simulated camera exposes instantaneously, so on a simulated rig this only paces the
    /// sequence. Unset (default): no hold.
    #[serde(default)]
    pub exposure_ms: Option<f64>,
}

fn default_steps() -> usize {
    4
}
fn default_periods() -> Vec<f64> {
    vec![16.0]
}
fn default_min_modulation() -> f32 {
    8.0
}
fn default_gamma_min_contrast() -> f64 {
    40.0
}
fn default_colours() -> usize {
    5
}
fn default_window() -> usize {
    3
}
fn default_stripe_px() -> u32 {
    4
}
fn default_sweep_step() -> u32 {
    2
}
fn default_sweep_contrast() -> u8 {
    20
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
            steps: default_steps(),
            periods_px: default_periods(),
            unwrapping: PhaseUnwrapping::default(),
            min_modulation: default_min_modulation(),
            gamma_compensation: false,
            gamma_min_contrast: default_gamma_min_contrast(),
            debruijn_colours: default_colours(),
            debruijn_window: default_window(),
            stripe_px: default_stripe_px(),
            sweep_step_px: default_sweep_step(),
            sweep_min_contrast: default_sweep_contrast(),
            exposure_ms: None,
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
    match &config.projector {
        None => bad("projector", "method \"structured-light\" needs a [projector]".into()),
        Some(p) if p.model().is_none() => bad(
            "projector",
            "method \"structured-light\" triangulates against the projector: give it [projector.calibration] \
             (`scanrig calibrate projector`)"
                .into(),
        ),
        Some(_) => {}
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
    if !(3..=64).contains(&s.outlier_neighbours) {
        bad(&key("outlier_neighbours"), format!("must be between 3 and 64, got {}", s.outlier_neighbours));
    }
    if !(s.outlier_std_ratio.is_finite() && s.outlier_std_ratio > 0.0) {
        bad(&key("outlier_std_ratio"), "must be a positive number".into());
    }
    if !(s.truncation_voxels.is_finite() && s.truncation_voxels > 0.0) {
        bad(&key("truncation_voxels"), "must be a positive number of voxels".into());
    }
    validate_coding(config, s, &mut |k, m| bad(&key(k), m));
}

/// The number of projector refreshes an exposure of `exposure_ms` spans, when it is a whole multiple
/// (1, 2, ..) of `frame_period_ms` within 1 % of a period; a projector without a refresh period
/// (`frame_period_ms = 0`) accepts any exposure as one frame.
pub fn exposure_frames(exposure_ms: f64, frame_period_ms: f64) -> Option<u32> {
    if !(exposure_ms.is_finite() && exposure_ms > 0.0) {
        return None;
    }
    if !(frame_period_ms.is_finite() && frame_period_ms > 0.0) {
        return Some(1);
    }
    let n = (exposure_ms / frame_period_ms).round();
    (n >= 1.0 && (exposure_ms - n * frame_period_ms).abs() <= 0.01 * frame_period_ms && n <= f64::from(u32::MAX))
        .then_some(n as u32)
}

/// Checks of the coding's own parameters (`bad` gets the key inside `[reconstruction.structured_light]`).
fn validate_coding(config: &RigConfig, s: &StructuredLightConfig, bad: &mut dyn FnMut(&str, String)) {
    let projector_width = config.projector.as_ref().map(|p| p.size().0);
    if s.rows && matches!(s.coding, StripeCoding::DeBruijn | StripeCoding::Sweep) {
        let name = if s.coding == StripeCoding::DeBruijn { "debruijn" } else { "sweep" };
        bad("rows", format!("coding = \"{name}\" codes columns only: set rows = false"));
    }
    match s.coding {
        StripeCoding::Gray | StripeCoding::Binary => {}
        StripeCoding::PhaseShift => {
            if !(3..=64).contains(&s.steps) {
                bad("steps", format!("must be 3..=64 phase steps, got {}", s.steps));
            }
            if s.periods_px.iter().any(|p| !(p.is_finite() && *p >= 2.0)) {
                bad("periods_px", format!("every period must be at least 2 projector pixels, got {:?}", s.periods_px));
            } else if !s.periods_px.windows(2).all(|w| w[1] > w[0]) {
                bad("periods_px", format!("periods must increase, got {:?}", s.periods_px));
            }
            match s.unwrapping {
                PhaseUnwrapping::Gray if s.periods_px.len() != 1 => {
                    bad("periods_px", format!("Gray-code unwrapping takes one period, got {}", s.periods_px.len()))
                }
                PhaseUnwrapping::MultiFrequency => {
                    let last = s.periods_px.last().copied().unwrap_or(0.0);
                    if s.periods_px.len() < 2 {
                        bad("periods_px", "multi-frequency unwrapping needs two or more periods".into());
                    } else if let Some(w) = projector_width.filter(|&w| last <= f64::from(w)) {
                        bad(
                            "periods_px",
                            format!("the last period ({last} px) must exceed the projector's width ({w} px)"),
                        );
                    }
                }
                PhaseUnwrapping::Gray => {}
            }
            if !(s.min_modulation.is_finite() && s.min_modulation >= 0.0) {
                bad("min_modulation", "must be a non-negative number of grey levels".into());
            }
        }
        StripeCoding::DeBruijn => {
            if !(3..=6).contains(&s.debruijn_colours) {
                bad("debruijn_colours", format!("must be 3..=6, got {}", s.debruijn_colours));
            }
            if !(1..=8).contains(&s.debruijn_window) {
                bad("debruijn_window", format!("must be 1..=8, got {}", s.debruijn_window));
            }
            if s.stripe_px == 0 {
                bad("stripe_px", "must be at least 1 projector pixel".into());
            }
        }
        StripeCoding::Sweep => {
            if s.stripe_px == 0 {
                bad("stripe_px", "must be at least 1 projector pixel".into());
            }
            if !(1..=s.stripe_px.max(1)).contains(&s.sweep_step_px) {
                bad("sweep_step_px", format!("must be 1..=stripe_px ({}), got {}", s.stripe_px, s.sweep_step_px));
            }
        }
    }
    if let Some(e) = s.exposure_ms {
        let period = config.projector.as_ref().map_or(0.0, ProjectorConfig::frame_period_ms);
        if !(e.is_finite() && e > 0.0 && e <= 10_000.0) {
            bad("exposure_ms", format!("must be 0 < exposure_ms <= 10000 milliseconds, got {e}"));
        } else if exposure_frames(e, period).is_none() {
            bad(
                "exposure_ms",
                format!(
                    "{e} ms is not a whole multiple of projector.frame_period_ms ({period} ms): \
                     use e.g. {} ms",
                    (e / period).round().max(1.0) * period
                ),
            );
        }
    }
    if s.gamma_compensation && !(s.gamma_min_contrast.is_finite() && s.gamma_min_contrast > 0.0) {
        bad("gamma_min_contrast", "must be a positive number of grey levels".into());
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use crate::config::ConfigError;
    use crate::rigfile::parse;

    fn shipped() -> String {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/structured-light.toml");
        std::fs::read_to_string(path).expect("shipped rig")
    }

    fn problems(text: &str) -> Vec<(String, Option<usize>)> {
        match parse(text, Path::new("rig.toml")) {
            Err(ConfigError::Invalid { problems, .. }) => problems.into_iter().map(|p| (p.key, p.line)).collect(),
            Err(e) => panic!("expected validation problems, got {e}"),
            Ok(_) => Vec::new(),
        }
    }

    #[test]
    fn the_shipped_rig_reads_its_settings() {
        let c = parse(&shipped(), Path::new("structured-light.toml")).expect("valid");
        assert_eq!(c.reconstruction.method.name(), "structured-light");
        let s = &c.reconstruction.structured_light;
        assert!(!s.rows && s.subpixel && s.free_below == 12);
        let Some(crate::config::ProjectorConfig::Sim(p)) = &c.projector else { panic!("projector") };
        assert_eq!((p.latency_ms, p.frame_period_ms), (30.0, 16.667));
    }

    #[test]
    fn bad_values_are_reported_with_key_and_line() {
        let text = shipped()
            .replace("latency_ms = 30.0", "latency_ms = -1.0")
            .replace("min_neighbours = 5", "min_neighbours = 9")
            .replace("truncation_voxels = 3.0", "truncation_voxels = 0.0");
        let p = problems(&text);
        let line_of = |needle: &str| text.lines().position(|l| l.starts_with(needle)).map(|i| i + 1);
        for (key, needle) in [
            ("projector.latency_ms", "latency_ms"),
            ("reconstruction.structured_light.min_neighbours", "min_neighbours"),
            ("reconstruction.structured_light.truncation_voxels", "truncation_voxels"),
        ] {
            assert!(p.contains(&(key.to_owned(), line_of(needle))), "{key} missing from {p:?}");
        }
    }

    #[test]
    fn outlier_neighbours_outside_what_the_cloud_accepts_are_refused_before_the_scan() {
        // The merged cloud's outlier test takes 3..=64 neighbours; a count outside that used to pass
        // here and fail the scan only after its last view.
        for k in [2, 65, 100] {
            let text =
                shipped().replace("min_neighbours = 5", &format!("min_neighbours = 5\noutlier_neighbours = {k}"));
            let line = text.lines().position(|l| l.starts_with("outlier_neighbours")).map(|i| i + 1);
            let key = "reconstruction.structured_light.outlier_neighbours".to_owned();
            assert_eq!(problems(&text), vec![(key, line)], "{k}");
        }
        for k in [3, 64] {
            let text =
                shipped().replace("min_neighbours = 5", &format!("min_neighbours = 5\noutlier_neighbours = {k}"));
            parse(&text, Path::new("rig.toml")).expect("within the cloud's range");
        }
    }

    #[test]
    fn the_method_needs_a_projector_and_unknown_keys_are_refused() {
        let text = shipped();
        let start = text.find("[projector]").expect("projector section");
        let end = text.find("[sim]").expect("sim section");
        let without = format!("{}{}", &text[..start], &text[end..]);
        assert!(problems(&without).iter().any(|(k, _)| k == "projector"), "{:?}", problems(&without));
        let typo = text.replace("subpixel = true", "sub_pixel = true");
        let err = parse(&typo, Path::new("rig.toml")).expect_err("unknown key");
        assert!(matches!(err, ConfigError::Invalid { .. }) && err.to_string().contains("sub_pixel"), "{err}");
    }

    fn shipped_phase() -> String {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/structured-light-phase.toml");
        std::fs::read_to_string(path).expect("shipped phase rig")
    }

    #[test]
    fn the_shipped_phase_rig_reads_its_coding() {
        let c = parse(&shipped_phase(), Path::new("structured-light-phase.toml")).expect("valid");
        let s = &c.reconstruction.structured_light;
        assert_eq!(s.coding, super::StripeCoding::PhaseShift);
        assert_eq!((s.steps, s.periods_px.as_slice(), s.unwrapping), (4, &[16.0][..], super::PhaseUnwrapping::Gray));
        assert!(s.gamma_compensation);
        assert_eq!(s.exposure_ms, Some(16.667));
        let Some(crate::config::ProjectorConfig::Sim(p)) = &c.projector else { panic!("projector") };
        assert_eq!(p.gamma, 2.2);
    }

    #[test]
    fn coding_parameters_are_checked_with_key_and_line() {
        let text = shipped_phase();
        let line_of = |t: &str, needle: &str| t.lines().position(|l| l.starts_with(needle)).map(|i| i + 1);
        let key = |k: &str| format!("reconstruction.structured_light.{k}");
        // Two periods with Gray unwrapping; two steps.
        let t = text.replace("periods_px = [16.0]", "periods_px = [16.0, 600.0]").replace("steps = 4", "steps = 2");
        let p = problems(&t);
        assert!(p.contains(&(key("periods_px"), line_of(&t, "periods_px"))), "{p:?}");
        assert!(p.contains(&(key("steps"), line_of(&t, "steps ="))), "{p:?}");
        // Multi-frequency whose last period does not cover the 512 columns.
        let t = text
            .replace("periods_px = [16.0]", "periods_px = [16.0, 128.0]")
            .replace("unwrapping = \"gray\"", "unwrapping = \"multi-frequency\"");
        assert!(problems(&t).contains(&(key("periods_px"), line_of(&t, "periods_px"))));
        let t = t.replace("128.0]", "128.0, 600.0]");
        assert!(problems(&t).is_empty(), "{:?}", problems(&t));
        // De Bruijn and the sweep code columns only; their own parameters are checked.
        let t = text
            .replace("coding = \"phase-shift\"", "coding = \"debruijn\"\ndebruijn_colours = 7")
            .replace("rows = false", "rows = true");
        let p = problems(&t);
        assert!(p.contains(&(key("rows"), line_of(&t, "rows"))), "{p:?}");
        assert!(p.contains(&(key("debruijn_colours"), line_of(&t, "debruijn_colours"))), "{p:?}");
        let t = text.replace("coding = \"phase-shift\"", "coding = \"sweep\"\nstripe_px = 2\nsweep_step_px = 3");
        assert!(problems(&t).contains(&(key("sweep_step_px"), line_of(&t, "sweep_step_px"))));
        let typo = text.replace("coding = \"phase-shift\"", "coding = \"phase\"");
        assert!(matches!(parse(&typo, Path::new("rig.toml")), Err(ConfigError::Parse { .. })));
    }

    #[test]
    fn exposures_are_whole_projector_refreshes() {
        use super::exposure_frames;
        assert_eq!(exposure_frames(16.667, 16.667), Some(1));
        assert_eq!(exposure_frames(33.3, 16.667), Some(2), "within 1 % of a period");
        assert_eq!(exposure_frames(20.0, 16.667), None);
        assert_eq!(exposure_frames(5.0, 16.667), None, "shorter than one refresh");
        assert_eq!(exposure_frames(5.0, 0.0), Some(1), "no refresh period: any exposure");
        assert_eq!(exposure_frames(-1.0, 16.667), None);
        let t = shipped_phase().replace("exposure_ms = 16.667", "exposure_ms = 25.0");
        let key = "reconstruction.structured_light.exposure_ms".to_owned();
        assert!(problems(&t).iter().any(|(k, l)| *k == key && l.is_some()), "{:?}", problems(&t));
    }
}
