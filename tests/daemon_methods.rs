//! One scan job for every method: a daemon on one rig with every device runs each of the seven
//! methods by request, one after another, without a restart, and each result equals the one
//! `scanrig scan` gives on the same rig file (noise off, so the frames are the same); a method the
//! rig cannot run is refused with a 422 naming what is missing; `GET /api/v1/methods` says which.

mod daemon_common;
mod scan_common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use daemon_common::{client, rig_from, spawn, wait_finished};

/// The shipped simulated rig (every device) made small and noise-free: the daemon's result is
/// compared with the CLI's, not with the truth, so small frames and few positions suffice.
fn small_rig(dir: &Path) -> PathBuf {
    let mut edits = vec![
        ("positions = 24", "positions = 8"),
        ("resolution = 128", "resolution = 40"),
        ("noise_sigma = 1.0", "noise_sigma = 0.0"),
        ("noise_sigma_m = 0.0005", "noise_sigma_m = 0.0"),
    ];
    edits.extend(daemon_common::HALF_SIZE_CAMERA);
    rig_from(dir, "simulated.toml", &edits)
}

const METHODS: [&str; 7] = [
    "space-carving",
    "shadow-carving",
    "voxel-coloring",
    "space-carving-photo",
    "depth-fusion",
    "structured-light",
    "laser",
];

/// The figures of a report that must not depend on who ran the job (no timings, no paths).
fn figures(report: &serde_json::Value) -> serde_json::Value {
    serde_json::json!({
        "method": report["method"],
        "views": report["views"],
        "resolution": report["resolution"],
        "occupied_voxels": report["occupied_voxels"],
        "mesh_triangles": report["mesh_triangles"],
        "reprojection_iou": report["reprojection_iou"],
        "ground_truth": report["ground_truth"],
        "visual_hull": report["visual_hull"],
    })
}

#[test]
fn every_method_runs_in_one_daemon_and_equals_the_cli_scan() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_rig(dir.path());
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).expect("state");
    let d = spawn(&rig, &state);
    let c = client(&d);

    let methods = c.get_json("/api/v1/methods").expect("methods");
    for m in METHODS {
        let entry = methods["methods"]
            .as_array()
            .and_then(|a| a.iter().find(|e| e["method"] == m))
            .unwrap_or_else(|| panic!("{m} not listed: {methods}"));
        assert_eq!(entry["available"], true, "{m}: {entry}");
    }

    for m in METHODS {
        let started = c.post_json("/api/v1/scans", &serde_json::json!({ "method": m })).expect("start");
        assert_eq!(started["method"], m);
        let id = started["id"].as_str().expect("id").to_owned();
        let meta = wait_finished(&c, &id, Duration::from_secs(240));
        assert_eq!(meta["status"], "complete", "{m}: {meta}");
        let daemon = c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["report"].clone();

        // The same rig file with the method set, through `scanrig scan`.
        let cli_dir = dir.path().join(m);
        std::fs::create_dir_all(&cli_dir).expect("dir");
        let cli_rig = scan_common::derived_rig_from(
            &rig,
            &cli_dir,
            &[("method = \"space-carving\"", &format!("method = \"{m}\""))],
        );
        let cli = scan_common::run_scan(&cli_rig, &cli_dir.join("out"));
        assert_eq!(figures(&daemon), figures(&cli), "{m}: daemon vs scanrig scan");
        assert_eq!(daemon["method"], m);
        assert!(daemon["ground_truth"]["iou"].as_f64().unwrap_or(0.0) > 0.3, "{m}: {}", daemon["ground_truth"]);
        eprintln!(
            "{m}: IoU {} containment {} ({} voxels) daemon = CLI",
            daemon["ground_truth"]["iou"], daemon["ground_truth"]["containment"], daemon["occupied_voxels"]
        );
    }
}

#[test]
fn a_method_the_rig_cannot_run_is_refused_naming_the_missing_device() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The simulated rig without its projector and its depth camera.
    let text = std::fs::read_to_string(small_rig(dir.path())).expect("rig");
    let (head, rest) = text.split_once("[projector]").expect("a projector section");
    let (_, tail) = rest.split_once("[sim]").expect("a sim section");
    let rig = dir.path().join("partial.toml");
    std::fs::write(&rig, format!("{head}[sim]{tail}")).expect("write");
    let d = spawn(&rig, dir.path());
    let c = client(&d);

    for (m, missing) in [("depth-fusion", "depth_camera"), ("structured-light", "projector")] {
        let r = c.raw("POST", "/api/v1/scans", Some(format!("{{\"method\": \"{m}\"}}").as_bytes())).expect("request");
        assert_eq!(r.status, 422, "{m}: {}", String::from_utf8_lossy(&r.body));
        let body: serde_json::Value = serde_json::from_slice(&r.body).expect("JSON error");
        let message = body["error"]["message"].as_str().unwrap_or_default();
        assert!(message.contains(missing), "{m}: {message}");
    }
    let methods = c.get_json("/api/v1/methods").expect("methods");
    let entry = |m: &str| methods["methods"].as_array().and_then(|a| a.iter().find(|e| e["method"] == m)).cloned();
    let depth = entry("depth-fusion").expect("listed");
    assert_eq!(depth["available"], false);
    assert!(depth["missing"].to_string().contains("depth_camera"), "{depth}");
    assert_eq!(entry("space-carving").expect("listed")["available"], true);
    let r = c.raw("POST", "/api/v1/scans", Some(b"{\"method\": \"telepathy\"}")).expect("request");
    assert_eq!(r.status, 422, "an unknown method: {}", String::from_utf8_lossy(&r.body));
    let scans = c.get_json("/api/v1/scans").expect("list");
    assert_eq!(scans["scans"].as_array().map(Vec::len), Some(0), "no scan may be created: {scans}");
    // Overrides go through the rig file's validation: the same limits.
    let r = c.raw("POST", "/api/v1/scans", Some(b"{\"resolution\": 1}")).expect("request");
    assert_eq!(r.status, 422);
    assert!(String::from_utf8_lossy(&r.body).contains("reconstruction.resolution"));
}
