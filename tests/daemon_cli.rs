//! The `scanrig` client subcommands (status, start --watch, watch, pause, resume, cancel, fetch)
//! against a real `scanrigd` on 127.0.0.1. Every command and wait is bounded.

mod daemon_common;

use std::time::Duration;

use daemon_common::{cli, client, frames_on_disk, ok, rig_from, scan_meta, spawn, wait_for};

#[test]
fn cli_status_start_watch_pause_resume_cancel_fetch() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[
            ("positions = 24", "positions = 8"),
            ("resolution = 128", "resolution = 40"),
            ("settle_ms = 0", "settle_ms = 150"),
        ],
    );
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    let limit = Duration::from_secs(30);

    // status: the daemon's JSON status.
    let status: serde_json::Value =
        serde_json::from_str(&ok(&cli(&d.addr, &["status", "--json"], limit))).expect("status json");
    assert_eq!(status["rig"], "simulated");
    assert_eq!(status["defaults"]["positions"], 8);

    // start --watch: follows the scan to its end.
    let out = ok(&cli(&d.addr, &["start", "--positions", "4", "--watch"], limit));
    let id = out.lines().find_map(|l| l.strip_prefix("started ")).expect("started line").trim().to_owned();
    assert!(out.contains(&format!("{id} complete")), "{out}");
    assert_eq!(scan_meta(&c, &id)["status"], "complete");
    assert_eq!(scan_meta(&c, &id)["positions"], 4);

    // fetch: the results land in --out.
    let fetched = dir.path().join("fetched");
    let out = ok(&cli(&d.addr, &["fetch", &id, "--out", fetched.to_str().expect("utf8")], limit));
    assert!(out.contains("model.ply"), "{out}");
    assert!(std::fs::read(fetched.join("model.ply")).expect("ply").starts_with(b"ply\n"));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fetched.join("report.json")).expect("report")).expect("json");
    assert_eq!(report["views"], 4);

    // start (no watch), pause, resume, cancel.
    let out = ok(&cli(&d.addr, &["start"], limit));
    let id = out.lines().find_map(|l| l.strip_prefix("started ")).expect("started line").trim().to_owned();
    wait_for("a first frame", limit, || frames_on_disk(dir.path(), &id).len() >= 2);
    ok(&cli(&d.addr, &["pause", &id], limit));
    wait_for("paused", limit, || scan_meta(&c, &id)["status"] == "paused");
    let kept = frames_on_disk(dir.path(), &id).len();
    assert!(kept < 16, "paused after the end: {kept} files");
    ok(&cli(&d.addr, &["resume", &id], limit));
    assert_eq!(scan_meta(&c, &id)["resumes"], 1);
    wait_for("running again", limit, || scan_meta(&c, &id)["status"] == "running");
    ok(&cli(&d.addr, &["cancel", &id], limit));
    wait_for("cancelled", limit, || scan_meta(&c, &id)["status"] == "cancelled");
    assert!(frames_on_disk(dir.path(), &id).len() >= kept, "frames were lost");

    // watch with nothing running reports the last scan's outcome and returns.
    let out = ok(&cli(&d.addr, &["watch"], limit));
    assert!(out.contains(&format!("{id} cancelled")), "{out}");

    // Errors are reported with a non-zero exit: a scan that is not running, a daemon that is not there.
    let out = cli(&d.addr, &["pause", &id], limit);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr).to_lowercase();
    assert!(err.contains("wrong_state") && err.contains("cancelled"), "{err}");
    let out = cli("127.0.0.1:9", &["status"], limit);
    assert!(!out.status.success());

    // methods: every method this rig runs; start one by name, then reprocess it at another resolution.
    let out = ok(&cli(&d.addr, &["methods"], limit));
    assert_eq!(out.lines().filter(|l| l.ends_with(" available")).count(), 7, "{out}");
    let out = ok(&cli(&d.addr, &["start", "--method", "depth-fusion", "--positions", "4", "--watch"], limit));
    assert!(out.contains("method depth-fusion") && out.contains(" complete"), "{out}");
    let id = out.lines().find_map(|l| l.strip_prefix("started ")).expect("started line").trim().to_owned();
    let out = ok(&cli(&d.addr, &["reprocess", &id, "--resolution", "32", "--watch"], limit));
    let again = out.lines().find_map(|l| l.split_once(" as ").map(|(_, r)| r.trim().to_owned())).expect("new id");
    assert!(out.contains(&format!("{again} complete")), "{out}");
    let meta = scan_meta(&c, &again);
    assert_eq!((meta["reprocess_of"].as_str(), meta["resolution"].as_u64()), (Some(id.as_str()), Some(32)));
    let out = cli(&d.addr, &["start", "--method", "telepathy"], limit);
    assert!(!out.status.success(), "an unknown method is refused before any request");
}
