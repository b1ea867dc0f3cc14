//! End-to-end tests of the real `scanrigd` binary on the simulated rig, over HTTP on 127.0.0.1.
//! Every wait is bounded.

mod daemon_common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use daemon_common::{client, frames_on_disk, rig_from, scan_meta, spawn, wait_for};
use scanrig::service::client::ClientError;

/// A rig file: the shipped simulated rig, smaller and with a settle time so a scan takes ~2 s.
fn rig_file(dir: &Path, settle_ms: u32) -> PathBuf {
    let settle = format!("settle_ms = {settle_ms}");
    rig_from(
        dir,
        "simulated.toml",
        &[("positions = 24", "positions = 8"), ("settle_ms = 0", &settle), ("resolution = 128", "resolution = 40")],
    )
}

fn scan_status(c: &scanrig::service::client::Client, id: &str) -> String {
    scan_meta(c, id)["status"].as_str().unwrap_or("").to_owned()
}

#[test]
fn start_watch_fetch_and_bad_requests() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_file(dir.path(), 20);
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    let status = c.get_json("/api/v1/status").expect("status");
    assert_eq!(status["rig"], "simulated");
    wait_for("devices connected", Duration::from_secs(10), || {
        let s = c.get_json("/api/v1/devices").expect("devices");
        s["devices"].as_array().is_some_and(|a| !a.is_empty() && a.iter().all(|d| d["state"] == "connected"))
    });

    // Malformed, unknown-field, invalid and oversize requests: 4xx with a JSON error.
    for (body, want) in [
        (&b"{not json"[..], 400),
        (&br#"{"positions": 8, "colour": "red"}"#[..], 422),
        (&br#"{"positions": 0}"#[..], 422),
        (&br#"{"resolution": 1}"#[..], 422),
        (&br#"{"method": "laser", "lights": [9]}"#[..], 422),
        (&br#"{"method": "telepathy"}"#[..], 422),
    ] {
        let r = c.raw("POST", "/api/v1/scans", Some(body)).expect("request");
        assert_eq!(r.status, want, "{}", String::from_utf8_lossy(body));
        let v = r.json().expect("json error body");
        assert!(v["error"]["code"].is_string() && v["error"]["message"].is_string(), "{v}");
    }
    let big = vec![b' '; 64 * 1024];
    let r = c.raw("POST", "/api/v1/scans", Some(&big)).expect("request");
    assert_eq!(r.status, 413);
    assert_eq!(r.json().expect("json")["error"]["code"], "too_large");
    let r = c.raw("GET", "/api/v1/scans/..%2Fetc/files/model.ply", None).expect("request");
    assert!((400..500).contains(&r.status));
    let r = c.raw("GET", "/api/v1/nothing", None).expect("request");
    assert_eq!(r.status, 404);
    assert_eq!(r.json().expect("json")["error"]["code"], "not_found");

    // A preview frame while idle.
    let r = c.request("GET", "/api/v1/preview", None).expect("preview");
    assert_eq!(r.header("content-type"), Some("image/png"));
    assert_eq!(&r.body[1..4], b"PNG");

    // Start, watch to the end, fetch.
    let started = c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start");
    let id = started["id"].as_str().expect("id").to_owned();
    let busy = c.request("POST", "/api/v1/scans", Some(b"{}"));
    assert!(matches!(busy, Err(ClientError::Api { status: 409, .. })), "{busy:?}");
    let mut seen_steps = Vec::new();
    let mut last = serde_json::Value::Null;
    c.watch(|p| {
        seen_steps.push(p["step"].as_u64().unwrap_or(0));
        last = p.clone();
        p["status"] == "running"
    })
    .expect("watch");
    assert_eq!(last["status"], "complete", "{last}");
    assert_eq!(last["step"], 8);
    assert!(seen_steps.windows(2).all(|w| w[0] <= w[1]), "progress went backwards: {seen_steps:?}");
    assert!(seen_steps.len() >= 3, "{seen_steps:?}");

    let out = dir.path().join("fetched");
    let files = scanrig::service::client::fetch_results(&c, &id, &out).expect("fetch");
    assert!(files.contains(&"model.ply"));
    let ply = std::fs::read(out.join("model.ply")).expect("ply");
    assert!(ply.starts_with(b"ply\n"));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).expect("report")).expect("json");
    assert_eq!(report["views"], 8);
    assert!(report["occupied_voxels"].as_u64().unwrap_or(0) > 100);
    assert_eq!(frames_on_disk(dir.path(), &id).len(), 16, "8 PNG + 8 JSON");

    let list = c.get_json("/api/v1/scans").expect("list");
    assert_eq!(list["scans"][0]["status"], "complete");
    let metrics = String::from_utf8(c.request("GET", "/metrics", None).expect("metrics").body).expect("utf8");
    assert!(metrics.contains("scanrig_frames_total{rig=\"simulated\"} 8\n"), "{metrics}");
    assert!(metrics.contains("scanrig_scans_completed_total{rig=\"simulated\"} 1\n"), "{metrics}");
}

#[test]
fn sigterm_mid_scan_parks_and_exits_within_the_deadline() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_file(dir.path(), 400);
    let mut d = spawn(&rig, dir.path());
    let c = client(&d);
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    wait_for("two frames", Duration::from_secs(20), || frames_on_disk(dir.path(), &id).len() >= 4);
    let pid = i32::try_from(d.child.id()).expect("pid");
    // SAFETY: sending a signal to our own child process.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGTERM) }, 0);
    let t = Instant::now();
    let status = loop {
        if let Some(s) = d.child.try_wait().expect("wait") {
            break s;
        }
        assert!(t.elapsed() < Duration::from_secs(6), "scanrigd did not exit within the deadline");
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "{status:?}");
    let log = std::fs::read_to_string(&d.stderr).expect("log");
    assert!(log.contains("rig parked"), "{log}");
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("scans").join(&id).join("meta.json")).expect("meta"))
            .expect("json");
    assert_eq!(meta["status"], "interrupted");
    assert!(!dir.path().join("scans").join(&id).join("report.json").exists());
}

#[test]
fn kill9_mid_scan_then_resume_gives_the_same_result() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_file(dir.path(), 250);
    // Noise-free frames: the resumed scan must then give exactly the uninterrupted scan's result
    // (with noise, the frames re-captured after the restart would get other noise).
    let text = std::fs::read_to_string(&rig).expect("rig");
    assert!(text.contains("noise_sigma = 1.0"));
    std::fs::write(&rig, text.replace("noise_sigma = 1.0", "noise_sigma = 0.0")).expect("write rig");
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).expect("state");
    let mut d = spawn(&rig, &state);
    let c = client(&d);
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    wait_for("three frames", Duration::from_secs(20), || frames_on_disk(&state, &id).len() >= 6);
    d.child.kill().expect("kill -9");
    let _ = d.child.wait();
    // Completed frames only: a kill -9 mid-write leaves the atomic writer's `.NAME.tmp-PID` file,
    // which the restarted daemon removes (it never was a frame).
    let before: Vec<String> = frames_on_disk(&state, &id).into_iter().filter(|n| !n.starts_with('.')).collect();

    let d = spawn(&rig, &state);
    let c = client(&d);
    assert_eq!(scan_status(&c, &id), "interrupted");
    // Nothing of the interrupted scan was lost.
    let after = frames_on_disk(&state, &id);
    assert!(before.iter().all(|f| after.contains(f)), "frames lost: {before:?} -> {after:?}");
    assert!(after.iter().all(|f| !f.starts_with('.')), "a temporary file left: {after:?}");
    let r = c.post_json(&format!("/api/v1/scans/{id}/resume"), &serde_json::json!({})).expect("resume");
    assert_eq!(r["resumes"], 1);
    wait_for("resumed scan to finish", Duration::from_secs(60), || scan_status(&c, &id) != "running");
    assert_eq!(scan_status(&c, &id), "complete");
    let frames = frames_on_disk(&state, &id);
    let expected: Vec<String> = (0..8).flat_map(|i| [format!("pos_{i:03}.json"), format!("pos_{i:03}.png")]).collect();
    assert_eq!(frames, expected, "every position exactly once");
    // Sequence numbers of the frames captured before the kill are unchanged (not re-captured).
    let resumed: serde_json::Value = c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["report"].clone();

    // The same scan without interruption.
    let id2 =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    wait_for("reference scan to finish", Duration::from_secs(60), || scan_status(&c, &id2) != "running");
    let reference: serde_json::Value = c.get_json(&format!("/api/v1/scans/{id2}")).expect("scan")["report"].clone();
    assert_eq!(resumed["views"], 8);
    assert_eq!(resumed["frames"]["views"], 8);
    assert_eq!(resumed["occupied_voxels"], reference["occupied_voxels"], "resumed vs uninterrupted");
    assert_eq!(resumed["ground_truth"], reference["ground_truth"], "resumed vs uninterrupted");
    assert_eq!(resumed["reprojection_iou"], reference["reprojection_iou"], "resumed vs uninterrupted");
}
