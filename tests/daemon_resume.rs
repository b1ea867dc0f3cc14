//! Resume and reprocess for every method through the real daemon: a scan killed with SIGKILL mid-way
//! is resumed after a restart, replaying the views on disk and acquiring only the missing ones, and
//! its result equals an uninterrupted scan's; a stored scan reprocessed with its own settings gives the
//! identical result, with another resolution a valid new one beside it, the original untouched.

mod daemon_common;

use std::path::{Path, PathBuf};
use std::time::Duration;

use daemon_common::{client, rig_from, scan_meta, spawn, wait_finished, wait_for};

/// The simulated rig (every device), small, noise-free and slow enough to be killed mid-scan.
/// Resumed results are compared with uninterrupted ones, not with the truth: small frames suffice.
fn rig(dir: &Path) -> PathBuf {
    let mut edits = vec![
        ("positions = 24", "positions = 8"),
        ("resolution = 128", "resolution = 40"),
        ("settle_ms = 0", "settle_ms = 150"),
        ("noise_sigma = 1.0", "noise_sigma = 0.0"),
        ("noise_sigma_m = 0.0005", "noise_sigma_m = 0.0"),
    ];
    edits.extend(daemon_common::HALF_SIZE_CAMERA);
    rig_from(dir, "simulated.toml", &edits)
}

/// The position records (`pos_NNN.json`) of a scan on disk, sorted.
fn records(state: &Path, id: &str) -> Vec<String> {
    daemon_common::frames_on_disk(state, id)
        .into_iter()
        .filter(|n| n.len() == "pos_000.json".len() && n.ends_with(".json"))
        .collect()
}

/// What every position of `method` stores, besides its record (`patterns` frames per position for
/// structured light).
fn files_of(method: &str, position: usize, patterns: usize) -> Vec<String> {
    let p = format!("pos_{position:03}");
    match method {
        "shadow-carving" => {
            let mut v = vec![format!("{p}_ambient.png")];
            v.extend((0..4).map(|l| format!("{p}_light_{l}.png")));
            v
        }
        "depth-fusion" => vec![format!("{p}_depth.png")],
        "laser" => vec![format!("{p}_laser_0.png"), format!("{p}_off.png")],
        "structured-light" => (0..patterns).map(|k| format!("{p}_pattern_{k:02}.png")).collect(),
        _ => vec![format!("{p}.png")],
    }
}

fn figures(report: &serde_json::Value) -> serde_json::Value {
    serde_json::json!({
        "views": report["views"],
        "occupied_voxels": report["occupied_voxels"],
        "mesh_triangles": report["mesh_triangles"],
        "reprojection_iou": report["reprojection_iou"],
        "ground_truth": report["ground_truth"],
    })
}

fn report_of(c: &scanrig::service::client::Client, id: &str) -> serde_json::Value {
    c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["report"].clone()
}

#[test]
fn kill9_mid_scan_then_resume_equals_an_uninterrupted_scan_for_every_acquisition() {
    for method in ["shadow-carving", "structured-light", "laser", "depth-fusion"] {
        let dir = tempfile::tempdir().expect("tempdir");
        let rig = rig(dir.path());
        let state = dir.path().join("state");
        std::fs::create_dir_all(&state).expect("state");
        let mut d = spawn(&rig, &state);
        let c = client(&d);
        let body = serde_json::json!({ "method": method });
        let id = c.post_json("/api/v1/scans", &body).expect("start")["id"].as_str().expect("id").to_owned();
        // The progress names what the method is doing (a pattern stays on screen for a frame, long
        // enough to be seen; a light switch is over at once).
        let expected_stage = if method == "structured-light" { "projecting pattern " } else { "" };
        if !expected_stage.is_empty() {
            let mut seen = String::new();
            wait_for("a method's own stage in the progress", Duration::from_secs(60), || {
                seen = c.get_json("/api/v1/status").expect("status")["progress"]["stage"]
                    .as_str()
                    .unwrap_or("")
                    .to_owned();
                seen.starts_with(expected_stage)
            });
            eprintln!("{method}: progress stage {seen:?}");
        }
        wait_for("three positions on disk", Duration::from_secs(60), || records(&state, &id).len() >= 3);
        d.child.kill().expect("kill -9");
        let _ = d.child.wait();
        let before = records(&state, &id).len();
        assert!(before < 8, "{method}: the scan finished before the kill");

        let d = spawn(&rig, &state);
        let c = client(&d);
        assert_eq!(scan_meta(&c, &id)["status"], "interrupted", "{method}");
        c.post_json(&format!("/api/v1/scans/{id}/resume"), &serde_json::json!({})).expect("resume");
        let meta = wait_finished(&c, &id, Duration::from_secs(120));
        assert_eq!(meta["status"], "complete", "{method}: {meta}\n{}", d.log());
        let resumed = report_of(&c, &id);
        // Every position on disk exactly once: its files and its record, nothing else.
        let patterns = resumed["structured_light"]["patterns_per_position"].as_u64().unwrap_or(0) as usize;
        let mut expected: Vec<String> = (0..8)
            .flat_map(|i| {
                let mut v = files_of(method, i, patterns);
                v.push(format!("pos_{i:03}.json"));
                v
            })
            .collect();
        expected.sort();
        assert_eq!(daemon_common::frames_on_disk(&state, &id), expected, "{method}: every view exactly once");
        assert_eq!(resumed["frames"]["views"], 8, "{method}");

        let id2 = c.post_json("/api/v1/scans", &body).expect("start")["id"].as_str().expect("id").to_owned();
        assert_eq!(wait_finished(&c, &id2, Duration::from_secs(120))["status"], "complete");
        let reference = report_of(&c, &id2);
        assert_eq!(figures(&resumed), figures(&reference), "{method}: resumed after {before} vs uninterrupted");
        eprintln!("{method}: killed after {before} of 8 positions; resumed result = uninterrupted result");
    }
}

#[test]
fn reprocess_over_http_gives_the_same_result_and_a_finer_grid_beside_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[("positions = 24", "positions = 8"), ("resolution = 128", "resolution = 40")],
    );
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).expect("state");
    let d = spawn(&rig, &state);
    let c = client(&d);
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");
    let original = report_of(&c, &id);
    let original_bytes = std::fs::read(state.join("scans").join(&id).join("model.ply")).expect("mesh");

    let same = c.post_json(&format!("/api/v1/scans/{id}/reprocess"), &serde_json::json!({})).expect("reprocess");
    assert_eq!(same["reprocess_of"], id.as_str());
    let same_id = same["id"].as_str().expect("id").to_owned();
    assert_eq!(wait_finished(&c, &same_id, Duration::from_secs(60))["status"], "complete");
    let again = report_of(&c, &same_id);
    assert_eq!(figures(&again), figures(&original), "reprocessed with its own settings");
    let again_bytes = std::fs::read(state.join("scans").join(&same_id).join("model.ply")).expect("mesh");
    assert_eq!(again_bytes, original_bytes, "the same mesh, byte for byte");

    let body = serde_json::json!({ "resolution": 64, "smooth_radius": 1 });
    let finer = c.post_json(&format!("/api/v1/scans/{id}/reprocess"), &body).expect("reprocess");
    let finer_id = finer["id"].as_str().expect("id").to_owned();
    assert_eq!(wait_finished(&c, &finer_id, Duration::from_secs(120))["status"], "complete");
    let finer = report_of(&c, &finer_id);
    assert_eq!(finer["method"], "space-carving");
    assert_eq!(finer["resolution"][0], 64);
    assert!(finer["ground_truth"]["iou"].as_f64().unwrap_or(0.0) > 0.5, "{}", finer["ground_truth"]);
    assert_eq!(finer["views"], 8);
    // The original is untouched.
    assert_eq!(report_of(&c, &id), original);
    assert_eq!(std::fs::read(state.join("scans").join(&id).join("model.ply")).expect("mesh"), original_bytes);
    // A depth-fusion reprocess of a silhouette scan has no views to work on: refused.
    let r = c
        .raw("POST", &format!("/api/v1/scans/{id}/reprocess"), Some(b"{\"method\": \"depth-fusion\"}"))
        .expect("request");
    assert_eq!(r.status, 422, "{}", String::from_utf8_lossy(&r.body));
}
