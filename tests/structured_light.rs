//! End-to-end structured light: the real `scanrig` binary scans the simulated rig (projector and
//! camera 70 degrees above the table, Gray-code columns, stripe-edge sub-pixel columns, TSDF fusion)
//! and the report, mesh and cloud are checked against the simulated ground truth: Chamfer distance
//! under 0.5 % of the object's bounding-box diagonal, and the concavity (the cup's pit, the block's
//! pit) recovered where the visual hull of the same views fills it.
//!
//! The rigs are derived from the shipped `config/rigs/structured-light.toml` with a fast projector
//! (1 ms lag instead of 30 ms) so the tests spend their time on rendering, not waiting, and fewer
//! positions / a coarser grid where the check allows it.

mod scan_common;

use std::path::Path;

use scan_common::{derived_rig, num, run_scan};

const SHIPPED: &str = "config/rigs/structured-light.toml";
const FAST_PROJECTOR: [(&str, &str); 2] =
    [("latency_ms = 30.0", "latency_ms = 1.0"), ("frame_period_ms = 16.667", "frame_period_ms = 0.5")];

/// Vertices of an OBJ file, metres.
fn obj_vertices(path: &Path) -> Vec<[f64; 3]> {
    let text = std::fs::read_to_string(path).expect("model.obj readable");
    text.lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().expect("number")).collect();
            [v[0], v[1], v[2]]
        })
        .collect()
}

/// The header of a binary PLY file, up to `end_header`.
fn ply_header(path: &Path) -> String {
    let bytes = std::fs::read(path).expect("ply readable");
    let end = bytes.windows(10).position(|w| w == b"end_header").expect("PLY header");
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

fn scan(replace: &[(&str, &str)]) -> (tempfile::TempDir, serde_json::Value) {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut all: Vec<(&str, &str)> = FAST_PROJECTOR.to_vec();
    all.extend_from_slice(replace);
    let rig = derived_rig(dir.path(), SHIPPED, &all);
    let report = run_scan(&rig, &dir.path().join("out"));
    (dir, report)
}

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn the_cup_is_within_half_a_percent_and_its_pit_is_open() {
    let (dir, report) = scan(&[("positions = 16", "positions = 12"), ("resolution = 128", "resolution = 96")]);
    let out = dir.path().join("out");
    assert_eq!(report["method"], "structured-light");
    assert_eq!(report["views"], 12);
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    let iou = num(&report, "ground_truth", "iou");
    let hull_iou = num(&report, "visual_hull", "iou");
    let point_error = num(&report, "structured_light", "point_error_mean_m");
    eprintln!(
        "cup: chamfer {:.3} mm = {chamfer_rel:.4} of the diagonal; IoU {iou:.3} (visual hull {hull_iou:.3}); \
         mean point error {:.3} mm; {} points",
        num(&report, "ground_truth", "chamfer_m") * 1e3,
        point_error * 1e3,
        report["structured_light"]["points"]
    );
    assert!(chamfer_rel < 0.005, "chamfer_rel {chamfer_rel}");
    assert!(iou > 0.95 && iou > hull_iou + 0.3, "IoU {iou} vs visual hull {hull_iou}");
    assert!(point_error < 0.0005, "mean point error {point_error} m");
    assert_eq!(report["structured_light"]["patterns_per_position"], 20, "9 column bit pairs + white + black");
    // Every capture is stored (resume, reprocessing): 20 per position, the last position's too.
    assert!(out.join("frames/pos_011_pattern_00.png").is_file() && out.join("frames/pos_011_pattern_19.png").is_file());
    assert!(out.join("frames/pos_011.json").is_file() && !out.join("frames/pos_011_pattern_20.png").exists());

    // The concavity: mesh on the pit's floor (z = 15 mm, r < 22 mm) and inner wall (r = 22 mm), none
    // in the pit's air. The visual hull has the pit filled to the rim.
    let v = obj_vertices(&out.join("model.obj"));
    let r = |p: &[f64; 3]| p[0].hypot(p[1]);
    let floor = v.iter().filter(|p| r(p) < 0.015 && (p[2] - 0.015).abs() < 0.0015).count();
    let wall = v.iter().filter(|p| (r(p) - 0.022).abs() < 0.0015 && p[2] > 0.025 && p[2] < 0.06).count();
    let in_air = v.iter().filter(|p| r(p) < 0.018 && p[2] > 0.02 && p[2] < 0.065).count();
    assert!(floor > 100 && wall > 1000, "{floor} vertices on the pit floor, {wall} on its wall");
    assert_eq!(in_air, 0, "{in_air} vertices inside the pit's air");

    // The merged cloud carries normals and colours.
    let header = ply_header(&out.join("cloud.ply"));
    for property in ["property float nx", "property uchar red"] {
        assert!(header.contains(property), "cloud.ply lacks `{property}`:\n{header}");
    }
}

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn the_pit_block_is_within_half_a_percent_and_its_pit_is_open() {
    let (dir, report) = scan(&[
        ("scene = \"cup\"", "scene = \"pit-block\""),
        ("positions = 16", "positions = 12"),
        ("resolution = 128", "resolution = 96"),
    ]);
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    let iou = num(&report, "ground_truth", "iou");
    let hull_iou = num(&report, "visual_hull", "iou");
    eprintln!("pit-block: chamfer_rel {chamfer_rel:.4}, IoU {iou:.3} (visual hull {hull_iou:.3})");
    assert!(chamfer_rel < 0.005, "chamfer_rel {chamfer_rel}");
    assert!(iou > hull_iou + 0.1, "IoU {iou} vs visual hull {hull_iou}");
    // The pit: 30 x 24 mm, floor at z = 20 mm, open at the top (z = 50 mm).
    let v = obj_vertices(&dir.path().join("out/model.obj"));
    let floor = v.iter().filter(|p| p[0].abs() < 0.012 && p[1].abs() < 0.009 && (p[2] - 0.02).abs() < 0.0015).count();
    let in_air = v.iter().filter(|p| p[0].abs() < 0.012 && p[1].abs() < 0.009 && p[2] > 0.025 && p[2] < 0.045).count();
    assert!(floor > 50, "{floor} vertices on the pit floor");
    assert_eq!(in_air, 0, "{in_air} vertices inside the pit's air");
}

/// Columns and rows: ray-ray triangulation instead of ray-plane.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn columns_and_rows_triangulate_ray_to_ray() {
    let (_dir, report) = scan(&[
        ("rows = false", "rows = true"),
        ("positions = 16", "positions = 8"),
        ("resolution = 128", "resolution = 96"),
    ]);
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    let point_error = num(&report, "structured_light", "point_error_mean_m");
    eprintln!("rows: chamfer_rel {chamfer_rel:.4}, mean point error {:.3} mm", point_error * 1e3);
    assert_eq!(report["structured_light"]["rows"], true);
    assert_eq!(report["structured_light"]["patterns_per_position"], 38, "9 column + 9 row bit pairs + white + black");
    assert!(chamfer_rel < 0.005, "chamfer_rel {chamfer_rel}");
    assert!(point_error < 0.0005, "mean point error {point_error} m");
}

/// Without stripe-edge interpolation (code centres only) the points are measurably worse: the
/// sub-pixel step is what the figures above rely on.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn stripe_edge_interpolation_beats_code_centres() {
    let small = [("positions = 16", "positions = 4"), ("resolution = 128", "resolution = 64")];
    let (_a, with) = scan(&small);
    let mut no_sub = small.to_vec();
    no_sub.push(("subpixel = true", "subpixel = false"));
    let (_b, without) = scan(&no_sub);
    let (e_with, e_without) =
        (num(&with, "structured_light", "point_error_mean_m"), num(&without, "structured_light", "point_error_mean_m"));
    eprintln!(
        "mean point error: {:.3} mm with stripe edges, {:.3} mm with code centres",
        e_with * 1e3,
        e_without * 1e3
    );
    assert!(e_with < 0.6 * e_without, "{e_with} vs {e_without}");
}
