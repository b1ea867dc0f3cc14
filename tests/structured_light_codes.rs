//! Every structured-light coding through the real `scanrig` binary: phase shift with the projector
//! response measured and compensated (a gamma-2.2 projector), one-shot De Bruijn colour stripes and
//! a sweeping stripe, each scanning the simulated cup; the report's Chamfer distance (relative to
//! the bounding-box diagonal) is checked against the simulated ground truth. Plus the exposure rule:
//! an exposure that is not a whole number of projector refreshes is refused naming both keys.
//!
//! The rigs are derived from the shipped `config/rigs/structured-light-phase.toml` with a fast
//! projector (1 ms lag, 0.5 ms refresh, one-refresh exposure) and a coarser grid, so the tests spend
//! their time rendering, not waiting. Figures in the assertions are the measured ones with a margin.

mod scan_common;

use scan_common::{derived_rig, num, run_scan, scanrig};

const SHIPPED: &str = "config/rigs/structured-light-phase.toml";
const FAST: [(&str, &str); 4] = [
    ("latency_ms = 30.0", "latency_ms = 1.0"),
    ("frame_period_ms = 16.667", "frame_period_ms = 0.5"),
    ("exposure_ms = 16.667", "exposure_ms = 0.5"),
    ("resolution = 128", "resolution = 96"),
];

/// The shipped phase-shift rig, made fast, with `replace` applied, scanned into a temporary directory.
fn scan(replace: &[(&str, &str)]) -> (tempfile::TempDir, serde_json::Value) {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut all: Vec<(&str, &str)> = FAST.to_vec();
    all.extend_from_slice(replace);
    let rig = derived_rig(dir.path(), SHIPPED, &all);
    let report = run_scan(&rig, &dir.path().join("out"));
    (dir, report)
}

/// `[reconstruction.structured_light]` of the shipped rig replaced by `coding` lines.
fn coding_section(lines: &str) -> (&'static str, String) {
    (
        "coding = \"phase-shift\"\nsteps = 4\nperiods_px = [16.0]\nunwrapping = \"gray\"\nmin_modulation = 8.0\n\
         gamma_compensation = true\n",
        lines.to_owned(),
    )
}

fn print(name: &str, report: &serde_json::Value) {
    eprintln!(
        "{name}: chamfer {:.3} mm = {:.4} of the diagonal; IoU {:.3}; mean point error {:.3} mm; \
         {} patterns per position; {:.1} % pixels decoded",
        num(report, "ground_truth", "chamfer_m") * 1e3,
        num(report, "ground_truth", "chamfer_rel"),
        num(report, "ground_truth", "iou"),
        num(report, "structured_light", "point_error_mean_m") * 1e3,
        report["structured_light"]["patterns_per_position"],
        num(report, "structured_light", "valid_fraction") * 100.0,
    );
}

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn phase_shift_with_gamma_compensation_scans_the_cup_within_half_a_percent() {
    let (dir, report) = scan(&[("positions = 16", "positions = 12")]);
    print("phase shift, gamma compensated", &report);
    let sl = &report["structured_light"];
    assert_eq!(sl["coding"], "phase-shift");
    assert_eq!(sl["phase"]["steps"], 4);
    assert_eq!(sl["phase"]["unwrapping"], "gray");
    // 4 fringes of 16 px, 6 Gray bits of the 64 half-period cells of 512 columns, one white frame.
    assert_eq!(sl["patterns_per_position"], 4 + 6 + 1);
    assert_eq!(sl["response"]["compensated"], true);
    let gamma = num(&report["structured_light"], "response", "gamma");
    eprintln!("fitted projector-to-camera gamma {gamma:.3} (projector gamma 2.2)");
    assert!((1.8..2.4).contains(&gamma), "fitted gamma {gamma}");
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    assert!(chamfer_rel < 0.0045, "chamfer_rel {chamfer_rel}");
    assert!(num(&report, "ground_truth", "iou") > 0.94);
    assert!(dir.path().join("out/frames/pos_011_pattern_10.png").is_file());
    assert!(dir.path().join("out/frames/prepare.json").is_file(), "the measured response is stored for resume");
}

/// Compensation matters: with 3-step fringes (4 steps cancel the second harmonic that gamma
/// adds, 3 do not) on the same gamma-2.2 projector, a few views triangulate clearly closer to the
/// truth with the fitted inverse applied to the fringes than without; a linear projector fits a
/// gamma near 1.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn gamma_compensation_lowers_the_phase_error_and_a_linear_projector_fits_near_one() {
    let few = ("positions = 16", "positions = 3");
    let three = ("steps = 4", "steps = 3");
    let (_a, with) = scan(&[few, three]);
    let (_b, without) = scan(&[few, three, ("gamma_compensation = true", "gamma_compensation = false")]);
    let (_c, linear) = scan(&[few, three, ("gamma = 2.2", "gamma = 1.0"), ("black_level = 0.02", "black_level = 0.0")]);
    let e = |r: &serde_json::Value| num(r, "structured_light", "point_error_mean_m");
    eprintln!(
        "mean point error: compensated {:.4} mm, uncompensated {:.4} mm; linear projector fits gamma {:.3}",
        e(&with) * 1e3,
        e(&without) * 1e3,
        num(&linear["structured_light"], "response", "gamma")
    );
    assert!(without["structured_light"]["response"].is_null(), "no measurement without compensation");
    // Measured: 0.814 mm compensated, 1.247 mm uncompensated.
    assert!(e(&with) < 0.8 * e(&without), "compensated {} m vs uncompensated {} m", e(&with), e(&without));
    let g = num(&linear["structured_light"], "response", "gamma");
    assert!((0.7..1.2).contains(&g), "linear projector fitted gamma {g}");
}

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn de_bruijn_one_shot_scans_the_cup() {
    let (from, to) = coding_section(
        "coding = \"debruijn\"\ndebruijn_colours = 6\ndebruijn_window = 3\nstripe_px = 5\ngamma_compensation = false\n",
    );
    let (_dir, report) = scan(&[("positions = 16", "positions = 12"), (from, &to)]);
    print("De Bruijn", &report);
    assert_eq!(report["structured_light"]["coding"], "debruijn");
    assert_eq!(report["structured_light"]["patterns_per_position"], 2, "one coded shot + the white frame");
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    assert!(chamfer_rel < DEBRUIJN_CHAMFER_REL, "chamfer_rel {chamfer_rel}");
}

/// What the one-shot coding reaches on the cup (measured, with a margin).
const DEBRUIJN_CHAMFER_REL: f64 = 0.008;

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn a_sweeping_stripe_scans_the_cup() {
    let (from, to) =
        coding_section("coding = \"sweep\"\nstripe_px = 4\nsweep_step_px = 2\ngamma_compensation = false\n");
    let (_dir, report) = scan(&[("positions = 16", "positions = 6"), (from, &to)]);
    print("sweeping stripe", &report);
    assert_eq!(report["structured_light"]["coding"], "sweep");
    assert_eq!(report["structured_light"]["patterns_per_position"], (512 - 4) / 2 + 1 + 1);
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    assert!(chamfer_rel < SWEEP_CHAMFER_REL, "chamfer_rel {chamfer_rel}");
}

/// What the sweep (4 px stripe, 2 px steps, 6 views) reaches on the cup (measured, with a margin).
const SWEEP_CHAMFER_REL: f64 = 0.015;

#[test]
fn an_exposure_that_is_not_whole_projector_refreshes_is_refused_naming_both_keys() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = derived_rig(dir.path(), SHIPPED, &[("exposure_ms = 16.667", "exposure_ms = 20.0")]);
    let out = scanrig().args(["validate", "--rig"]).arg(&rig).output().expect("run scanrig");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(!out.status.success(), "accepted: {text}");
    assert!(
        text.contains("reconstruction.structured_light.exposure_ms") && text.contains("projector.frame_period_ms"),
        "{text}"
    );
    let line = std::fs::read_to_string(&rig)
        .expect("rig")
        .lines()
        .position(|l| l.starts_with("exposure_ms"))
        .map(|i| i + 1)
        .expect("exposure line");
    assert!(text.contains(&format!("line {line}")), "no line {line} in {text}");
    let two = derived_rig(dir.path(), SHIPPED, &[("exposure_ms = 16.667", "exposure_ms = 33.334")]);
    let ok = scanrig().args(["validate", "--rig"]).arg(&two).output().expect("run scanrig");
    assert!(ok.status.success(), "two refreshes refused: {}", String::from_utf8_lossy(&ok.stderr));
}
