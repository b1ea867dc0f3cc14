//! The daemon's scan job runs the silhouette pipeline; a rig whose method has its own acquisition
//! (shadow carving, depth fusion) is refused with a clear 422 instead of being scanned as something
//! else under that method's name.

mod daemon_common;

use std::path::Path;

use daemon_common::{client, spawn};

#[test]
fn methods_the_daemon_does_not_run_are_refused_not_substituted() {
    for rig in [
        "config/rigs/shadow-carving.toml",
        "config/rigs/depth-fusion.toml",
        "config/rigs/laser.toml",
        "config/rigs/structured-light.toml",
    ] {
        let dir = tempfile::tempdir().expect("tempdir");
        let d = spawn(&Path::new(env!("CARGO_MANIFEST_DIR")).join(rig), dir.path());
        let c = client(&d);
        let r = c.raw("POST", "/api/v1/scans", Some(b"{}")).expect("request");
        assert_eq!(r.status, 422, "{rig}: {}", String::from_utf8_lossy(&r.body));
        let body: serde_json::Value = serde_json::from_slice(&r.body).expect("JSON error");
        let message = body["error"]["message"].as_str().unwrap_or_default();
        assert!(message.contains("scanrig scan"), "{rig}: {message}");
        let scans = c.get_json("/api/v1/scans").expect("list");
        assert!(scans.to_string().matches("\"id\"").count() == 0, "{rig}: no scan may be created: {scans}");
    }
}
