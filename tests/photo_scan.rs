//! End-to-end: the real `scanrig` binary scans the simulated cup (colour bands, an open pit) with the
//! photo-consistency methods; the report is checked against the simulated ground truth and the visual
//! hull, and the outputs are checked for colours.

mod scan_common;

use scan_common::{derived_rig, num, repo, run_scan};

use std::path::Path;

fn header(path: &Path) -> String {
    let bytes = std::fs::read(path).expect("file written");
    let end = bytes.windows(10).position(|w| w == b"end_header").expect("PLY header");
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

/// Checks shared by both methods; returns (IoU, hull IoU, containment, colour error).
fn check(report: &serde_json::Value, out: &Path, method: &str) -> (f64, f64, f64, f64) {
    assert_eq!(report["method"], method);
    let iou = num(report, "ground_truth", "iou");
    let hull = num(report, "visual_hull", "iou");
    let containment = num(report, "ground_truth", "containment");
    let colour = num(report, "ground_truth", "colour_error");
    let reproj = num(report, "photo", "reprojection_error");
    let hull_reproj = num(report, "visual_hull", "reprojection_error");
    println!(
        "{method}: IoU {iou:.4} (hull {hull:.4}), containment {containment:.4}, colour error {colour:.2}/255 \
         (hull {:.2}), re-projection error {reproj:.2} (hull {hull_reproj:.2}), carved {}, {} s",
        num(report, "visual_hull", "colour_error"),
        report["photo"]["carved"],
        report["timings_s"]["total"]
    );
    assert!(num(report, "photo", "carved") > 0.0, "nothing carved");
    assert!(containment >= 0.98, "containment {containment}");
    assert!((0.0..255.0).contains(&colour));
    // Coloured outputs.
    assert!(header(&out.join("model.ply")).contains("property uchar red"));
    assert!(header(&out.join("voxels.ply")).contains("property uchar red"));
    let obj = std::fs::read_to_string(out.join("model.obj")).expect("obj");
    let v = obj.lines().find(|l| l.starts_with("v ")).expect("a vertex");
    assert_eq!(v.split_whitespace().count(), 7, "OBJ vertex without colour: {v}");
    (iou, hull, containment, colour)
}

/// Small grid, runs in every profile. At 64^3 (1.4 mm voxels, about 5 px) the carving stays inside
/// the object but removes too little of the pit to lift the IoU above the hull's (measured: 0.550 vs
/// 0.553); the shipped 128^3 rig below checks that.
#[test]
fn space_carving_photo_carves_inside_the_object_at_64() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig =
        derived_rig(dir.path(), "config/rigs/space-carving-photo.toml", &[("resolution = 128", "resolution = 64")]);
    let out = dir.path().join("out");
    let report = run_scan(&rig, &out);
    check(&report, &out, "space-carving-photo");
    assert!(num(&report, "photo", "reprojection_error") < num(&report, "visual_hull", "reprojection_error"));
}

/// The shipped rig at 128^3: the acceptance figures.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn space_carving_photo_on_the_shipped_rig() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    let report = run_scan(&repo("config/rigs/space-carving-photo.toml"), &out);
    let (iou, hull, _, colour) = check(&report, &out, "space-carving-photo");
    assert!(iou > hull, "IoU {iou} not above the visual hull's {hull}");
    assert!(colour < 10.0, "colour error {colour}");
    // Incremental carving: converged well before the cap, each iteration judging only the voxels
    // whose inputs changed (fewer visits than iterations x the hull's surface).
    let iterations = num(&report, "photo", "iterations");
    assert!((1.0..500.0).contains(&iterations), "{iterations} iterations");
    assert!(num(&report, "photo", "visits") < iterations * num(&report, "visual_hull", "voxels"));
}

/// Voxel colouring over ordinal sweeps: every one of the 36 views is used, each in a sweep along
/// which it is in front of the working volume; each sweep visits a hull voxel at most once.
#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: run with --release")]
fn voxel_coloring_on_the_shipped_rig() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    let report = run_scan(&repo("config/rigs/voxel-coloring.toml"), &out);
    let (iou, hull, _, _) = check(&report, &out, "voxel-coloring");
    assert!(iou > hull, "IoU {iou} not above the visual hull's {hull}");
    assert_eq!(num(&report, "photo", "views"), 36.0);
    let sweeps = report["photo"]["ordinal_sweeps"].as_array().expect("photo.ordinal_sweeps");
    assert_eq!(sweeps.len() as f64, num(&report, "photo", "sweeps"));
    assert!(sweeps.len() >= 2, "a ring needs several sweeps: {sweeps:?}");
    let mut covered = [false; 36];
    for s in sweeps {
        let views = s["views"].as_array().expect("views");
        assert!(views.len() >= 2 && views.len() < 36, "{s}");
        for v in views {
            covered[v.as_u64().expect("index") as usize] = true;
        }
    }
    assert!(covered.iter().all(|&c| c), "a view in no sweep: {sweeps:?}");
    let visits = num(&report, "photo", "visits");
    assert!(visits <= sweeps.len() as f64 * num(&report, "visual_hull", "voxels"), "{visits} visits");
}
