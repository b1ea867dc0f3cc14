//! End-to-end shadow carving: the real `scanrig` binary scans the shipped shadow-carving rig (the cup,
//! 24 positions x 4 lights) and the report is checked against the simulated ground truth; and the
//! 72 x 8 rig recovers more of the pit than the 24 x 4 one.

mod scan_common;

use scan_common::{derived_rig, num, repo, run_scan, scanrig};

struct Figures {
    hull_iou: f64,
    iou: f64,
    containment: f64,
    excess_removed: f64,
}

fn figures(report: &serde_json::Value) -> Figures {
    let truth = num(report, "ground_truth", "voxels");
    let hull = num(report, "visual_hull", "voxels");
    let result = report["occupied_voxels"].as_f64().expect("occupied_voxels");
    let f = Figures {
        hull_iou: num(report, "visual_hull", "iou"),
        iou: num(report, "ground_truth", "iou"),
        containment: num(report, "ground_truth", "containment"),
        // With containment 1 every removed voxel was excess.
        excess_removed: (hull - result) / (hull - truth),
    };
    eprintln!(
        "hull IoU {:.3} -> shadow IoU {:.3}, containment {:.4}, hull excess removed {:.2}, hull {} / result {} / truth {} voxels",
        f.hull_iou, f.iou, f.containment, f.excess_removed, hull, result, truth
    );
    f
}

/// The shipped 24 x 4 rig at its full 128³ resolution (release builds only: a debug build is too
/// slow for the renderer and the carving at this size).
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn shipped_rig_carves_the_pit_and_keeps_the_cup() {
    let dir = tempfile::tempdir().expect("tempdir");
    let report = run_scan(&repo("config/rigs/shadow-carving.toml"), &dir.path().join("out"));
    assert_eq!(report["method"], "shadow-carving");
    let f = figures(&report);
    assert!(num(&report, "visual_hull", "containment") > 0.999);
    assert!(f.containment >= 0.99, "containment {}", f.containment);
    assert!(f.iou > f.hull_iou + 0.15, "IoU {} vs hull {}", f.iou, f.hull_iou);
    assert!(f.excess_removed >= 0.5, "only {} of the hull's excess removed", f.excess_removed);
    assert!(num(&report, "visual_hull", "volume_m3") > report["volume_m3"].as_f64().expect("volume"));
    assert!(report["shadow_carving"]["converged"].as_bool().expect("converged"));
    assert!(dir.path().join("out/frames/pos_000_ambient.png").is_file());
    assert!(dir.path().join("out/frames/pos_023_light_3.png").is_file());
}

/// More views and more lights recover more (72 x 8 against 24 x 4), at 96³ and half-size images so
/// the test stays short; both rigs share the same camera.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn more_views_and_lights_recover_more() {
    let small = [
        ("resolution = 128", "resolution = 96"),
        ("width = 640", "width = 320"),
        ("height = 480", "height = 240"),
        ("fx = 900.0", "fx = 450.0"),
        ("fy = 900.0", "fy = 450.0"),
        ("cx = 320.0", "cx = 160.0"),
        ("cy = 240.0", "cy = 120.0"),
    ];
    let dir = tempfile::tempdir().expect("tempdir");
    let d24 = dir.path().join("24");
    let d72 = dir.path().join("72");
    std::fs::create_dir_all(&d24).expect("dir");
    std::fs::create_dir_all(&d72).expect("dir");
    let few = figures(&run_scan(&derived_rig(&d24, "config/rigs/shadow-carving.toml", &small), &d24.join("out")));
    let many = figures(&run_scan(&derived_rig(&d72, "config/rigs/shadow-carving-72x8.toml", &small), &d72.join("out")));
    assert!(few.containment >= 0.99 && many.containment >= 0.99);
    assert!(many.iou > few.iou + 0.01, "72x8 IoU {} vs 24x4 {}", many.iou, few.iou);
    assert!(many.excess_removed > few.excess_removed);
}

/// A shadow-carving rig naming no lights, or a light that does not exist, is refused before anything
/// runs, with the offending key.
#[test]
fn bad_shadow_lights_are_refused() {
    let cases = [
        ("shadow_lights = [0, 1, 2, 3]", "shadow_lights = [0, 7]", "scan.shadow_lights.1"),
        ("shadow_lights = [0, 1, 2, 3]", "shadow_lights = [1, 1]", "named twice"),
        ("shadow_lights = [0, 1, 2, 3]", "shadow_lights = []", "scan.shadow_lights"),
    ];
    for (from, to, expect) in cases {
        let dir = tempfile::tempdir().expect("tempdir");
        let rig = derived_rig(dir.path(), "config/rigs/shadow-carving.toml", &[(from, to)]);
        let out = dir.path().join("out");
        let output = scanrig().args(["scan", "--rig"]).arg(&rig).arg("--out").arg(&out).output().expect("run scanrig");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{to}: accepted");
        assert!(stderr.contains(expect), "{to}: stderr lacks `{expect}`: {stderr}");
        assert!(!out.join("report.json").exists());
    }
}
