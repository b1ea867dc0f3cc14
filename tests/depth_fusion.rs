//! End-to-end depth fusion: the real `scanrig` binary scans the shipped depth-fusion rig (the cup,
//! 24 depth frames from 70 degrees elevation) and the report and mesh are checked against the
//! simulated ground truth: Chamfer distance under 1 % of the cup's bounding-box diagonal, the voxel
//! solid well above the visual hull, and the pit open down to its floor.

mod scan_common;

use scan_common::{num, repo, run_scan};

use std::path::Path;

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

/// The shipped rig at its full 128³ resolution (release builds only: too slow in a debug build).
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn shipped_rig_fuses_the_cup_within_one_percent_and_opens_the_pit() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    let report = run_scan(&repo("config/rigs/depth-fusion.toml"), &out);
    assert_eq!(report["method"], "depth-fusion");
    assert_eq!(report["views"], 24);
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    let iou = num(&report, "ground_truth", "iou");
    let containment = num(&report, "ground_truth", "containment");
    let hull_iou = num(&report, "visual_hull", "iou");
    eprintln!(
        "chamfer {:.3} mm = {:.4} of the diagonal; IoU {iou:.3}, containment {containment:.3}; visual hull IoU {hull_iou:.3}",
        num(&report, "ground_truth", "chamfer_m") * 1e3,
        chamfer_rel
    );
    assert!(chamfer_rel < 0.01, "chamfer_rel {chamfer_rel}");
    assert!(iou > 0.85 && iou > hull_iou + 0.25, "IoU {iou} vs hull {hull_iou}");
    assert!(containment > 0.9, "containment {containment}");
    assert_eq!(report["depth_fusion"]["views"], 24);
    assert!(out.join("frames/pos_023_depth.png").is_file());

    // The concavity: the mesh has the pit's floor (z = 15 mm, radius 22 mm) and nothing in the air of
    // the pit away from its wall and floor.
    let v = obj_vertices(&out.join("model.obj"));
    let r = |p: &[f64; 3]| p[0].hypot(p[1]);
    let floor = v.iter().filter(|p| r(p) < 0.015 && (p[2] - 0.015).abs() < 0.0015).count();
    let in_air = v.iter().filter(|p| r(p) < 0.018 && p[2] > 0.02 && p[2] < 0.065).count();
    assert!(floor > 100, "{floor} vertices on the pit floor");
    assert_eq!(in_air, 0, "{in_air} vertices inside the pit's air");
}

/// A depth camera low over the table (about 20 degrees) never looks into the pit: the pit stays
/// filled, so the concavity check above is one a wrong viewpoint fails. Reduced resolution.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn a_low_depth_camera_leaves_the_pit_filled() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut text = std::fs::read_to_string(repo("config/rigs/depth-fusion.toml")).expect("shipped rig readable");
    for (from, to) in
        [("eye_m = [0.0, -0.1197, 0.3639]", "eye_m = [0.0, -0.33, 0.155]"), ("resolution = 128", "resolution = 96")]
    {
        assert!(text.contains(from), "no `{from}`");
        text = text.replacen(from, to, 1);
    }
    let rig = dir.path().join("rig.toml");
    std::fs::write(&rig, text).expect("write rig");
    let out = dir.path().join("out");
    let report = run_scan(&rig, &out);
    let iou = num(&report, "ground_truth", "iou");
    let chamfer_rel = num(&report, "ground_truth", "chamfer_rel");
    eprintln!("low camera: IoU {iou:.3}, chamfer_rel {chamfer_rel:.4}");
    let v = obj_vertices(&out.join("model.obj"));
    let floor = v.iter().filter(|p| p[0].hypot(p[1]) < 0.015 && (p[2] - 0.015).abs() < 0.0015).count();
    assert_eq!(floor, 0, "the pit floor cannot be seen from this low");
    assert!(iou < 0.8, "IoU {iou}");
}
