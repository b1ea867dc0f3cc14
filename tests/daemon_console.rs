//! The console's API (issue 16) and its CLI against a real `scanrigd` on 127.0.0.1 with the
//! simulated rig: live MJPEG camera, manual control and its refusals while a scan runs, device
//! reconnection and the `devices` event, scan entries, thumbnails, display models, the zip archive
//! and deletion. Every wait is bounded.

mod daemon_common;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use daemon_common::{client, ok, rig_from, spawn, wait_finished, wait_for};
use scanrig::service::client::{read_multipart_part, stored_zip_entries, Client, MultipartPart};

/// The shipped simulated rig, 8 positions at resolution 40, with a settle time so that a scan
/// runs for a second or so.
fn rig_file(dir: &Path) -> PathBuf {
    rig_from(
        dir,
        "simulated.toml",
        &[
            ("positions = 24", "positions = 8"),
            ("settle_ms = 0", "settle_ms = 120"),
            ("resolution = 128", "resolution = 40"),
        ],
    )
}

fn connected(c: &Client) {
    wait_for("devices connected", Duration::from_secs(15), || {
        let s = c.get_json("/api/v1/devices").expect("devices");
        s["devices"].as_array().is_some_and(|a| !a.is_empty() && a.iter().all(|d| d["state"] == "connected"))
    });
}

fn header<'a>(p: &'a MultipartPart, name: &str) -> Option<&'a str> {
    p.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

/// A decoded live frame: its sequence and mean grey level.
fn decode(p: &MultipartPart) -> (u64, f64) {
    assert_eq!(header(p, "content-type"), Some("image/jpeg"));
    let seq = header(p, "x-frame-sequence").and_then(|s| s.parse().ok()).expect("sequence header");
    let img = image::load_from_memory_with_format(&p.body, image::ImageFormat::Jpeg).expect("a JPEG part").to_rgb8();
    assert_eq!((img.width(), img.height()), (640, 480));
    let mean = img.pixels().map(|px| f64::from(px[0]) + f64::from(px[1]) + f64::from(px[2])).sum::<f64>()
        / (3.0 * f64::from(img.width() * img.height()));
    (seq, mean)
}

/// Live parts as received: when, sequence, mean grey level.
type Parts = Arc<Mutex<Vec<(Instant, u64, f64)>>>;

/// `(status, error code, error message)` of a request.
fn answer(c: &Client, method: &str, path: &str, body: Option<&str>) -> (u16, String, String) {
    let r = c.raw(method, path, body.map(str::as_bytes)).expect("request");
    let v = r.json().unwrap_or_default();
    (
        r.status,
        v["error"]["code"].as_str().unwrap_or("").to_owned(),
        v["error"]["message"].as_str().unwrap_or("").to_owned(),
    )
}

/// Every file under `dir`, relative, sorted.
fn files_under(dir: &Path) -> Vec<String> {
    fn walk(d: &Path, prefix: &str, out: &mut Vec<String>) {
        for e in std::fs::read_dir(d).expect("read dir").flatten() {
            let name = format!("{prefix}{}", e.file_name().to_string_lossy());
            if e.file_type().expect("type").is_dir() {
                walk(&e.path(), &format!("{name}/"), out);
            } else {
                out.push(name);
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, "", &mut out);
    out.sort();
    out
}

#[test]
fn camera_control_scans_archive_and_delete() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_file(dir.path());
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    connected(&c);

    // Camera info and the control state at start: parked.
    let cam = c.get_json("/api/v1/camera").expect("camera");
    assert_eq!((cam["width"].as_u64(), cam["height"].as_u64()), (Some(640), Some(480)), "{cam}");
    assert_eq!(cam["streaming_paused"], false);
    assert_eq!(cam["kind"], "sim");
    assert!(cam["exposure_us"].is_null() && cam["gain_db"].is_null(), "the simulated camera has neither: {cam}");
    let state = c.get_json("/api/v1/control").expect("control");
    assert_eq!(state["lights"], serde_json::json!([false, false, false, false]), "{state}");
    assert_eq!(state["lasers"], serde_json::json!([false]));
    assert_eq!(state["projector"], "blank");

    // The MJPEG stream, read by a thread that records every part with when it arrived.
    let (status, headers, mut body) = c.open_stream("/api/v1/camera.mjpg?fps=10").expect("mjpeg");
    assert_eq!(status, 200);
    let ctype = headers.iter().find(|(k, _)| k == "content-type").map(|(_, v)| v.clone()).unwrap_or_default();
    assert_eq!(ctype, "multipart/x-mixed-replace; boundary=frame");
    let parts: Parts = Arc::default();
    let sink = parts.clone();
    std::thread::spawn(move || {
        while let Ok(Some(p)) = read_multipart_part(&mut *body, "frame") {
            let (seq, mean) = decode(&p);
            sink.lock().expect("lock").push((Instant::now(), seq, mean));
        }
    });
    let count = |parts: &Parts| parts.lock().expect("lock").len();
    wait_for("two live frames", Duration::from_secs(15), || count(&parts) >= 2);
    let dark = parts.lock().expect("lock").last().map(|p| p.2).expect("frame");

    // Manual control: a light on brightens the live picture; sequences only increase.
    let on = c.post_json("/api/v1/control/light", &serde_json::json!({"index": 0, "on": true})).expect("light");
    assert_eq!(on["lights"][0], true, "{on}");
    let n = count(&parts);
    // The camera's queue holds frames exposed before the switch (buffer_depth = 3): the lit one
    // comes a few parts later.
    wait_for("frames after the light", Duration::from_secs(15), || count(&parts) >= n + 6);
    let bright = parts.lock().expect("lock")[n..].iter().map(|p| p.2).fold(0.0, f64::max);
    assert!(bright > dark + 1.0, "the lit frame (mean {bright:.2}) is not brighter than the dark one ({dark:.2})");
    {
        let p = parts.lock().expect("lock");
        assert!(p.windows(2).all(|w| w[1].1 > w[0].1), "sequences not increasing");
    }
    let before = c.get_json("/api/v1/control").expect("control")["angle_deg"].as_f64().expect("angle");
    let turned = c.post_json("/api/v1/control/turntable", &serde_json::json!({"turn_deg": 90.0})).expect("turn");
    assert!((turned["angle_deg"].as_f64().expect("angle") - (before + 90.0)).abs() < 0.2, "{turned}");
    let homed = c.post_json("/api/v1/control/turntable", &serde_json::json!({"home": true})).expect("home");
    assert!(homed["angle_deg"].as_f64().expect("angle").abs() < 0.2, "{homed}");
    let laser = c.post_json("/api/v1/control/laser", &serde_json::json!({"index": 0, "on": true})).expect("laser");
    assert_eq!(laser["lasers"], serde_json::json!([true]));
    for (body, shown) in [
        (serde_json::json!({"pattern": "checker"}), "checker"),
        (serde_json::json!({"colour": [255, 0, 16]}), "colour #ff0010"),
        (serde_json::json!({"blank": true}), "blank"),
    ] {
        let s = c.post_json("/api/v1/control/projector", &body).expect("projector");
        assert_eq!(s["projector"], shown, "{body}");
    }

    // Bad bodies: 4xx whose message names the field.
    for (path, body, field) in [
        ("/api/v1/control/light", r#"{"index": 9, "on": true}"#, "light 9"),
        ("/api/v1/control/light", r#"{"index": 0}"#, "on"),
        ("/api/v1/control/laser", r#"{"index": 0, "on": "yes"}"#, "on"),
        ("/api/v1/control/turntable", r#"{}"#, "turn_deg"),
        ("/api/v1/control/turntable", r#"{"turn_deg": "far"}"#, "turn_deg"),
        ("/api/v1/control/turntable", r#"{"spin": 3}"#, "spin"),
        ("/api/v1/control/projector", r#"{"pattern": "zebra"}"#, "zebra"),
        ("/api/v1/control/projector", r#"{"colour": [300, 0, 0]}"#, "colour"),
        ("/api/v1/control/projector", r#"{"pattern": "gray", "blank": true}"#, "only one"),
    ] {
        let (status, code, message) = answer(&c, "POST", path, Some(body));
        assert_eq!(status, 422, "{path} {body}: {code} {message}");
        assert!(message.contains(field), "{path} {body}: `{message}` does not name {field}");
    }
    let (status, _, _) = answer(&c, "GET", "/api/v1/camera.mjpg?fps=0", None);
    assert_eq!(status, 422);
    let (status, code, _) = answer(&c, "POST", "/api/v1/devices/toaster/reconnect", None);
    assert_eq!((status, code.as_str()), (404, "not_found"));

    // Reconnecting the camera: 202, a `devices` event, the count goes up.
    let events: Arc<Mutex<Vec<serde_json::Value>>> = Arc::default();
    let seen = events.clone();
    let watcher = c.clone();
    std::thread::spawn(move || {
        let _ = watcher.watch_events(|name, v| {
            if name == "devices" {
                seen.lock().expect("lock").push(v.clone());
            }
            true
        });
    });
    std::thread::sleep(Duration::from_millis(300));
    let r = c.raw("POST", "/api/v1/devices/camera/reconnect", Some(b"{}")).expect("reconnect");
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    connected(&c);
    wait_for("a devices event", Duration::from_secs(10), || {
        events
            .lock()
            .expect("lock")
            .iter()
            .any(|v| v.as_array().is_some_and(|a| a.iter().any(|d| d["reconnects"] == 1)))
    });
    let after = c.get_json("/api/v1/control").expect("control");
    assert_eq!(after["lasers"], serde_json::json!([false]), "a reconnection leaves the rig parked: {after}");

    // A scan: every manual command is refused, the stream pauses (no new capture).
    let seq_before = parts.lock().expect("lock").last().map(|p| p.1).expect("frame");
    let scan = c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start");
    let id = scan["id"].as_str().expect("id").to_owned();
    let started = Instant::now();
    for (path, body) in [
        ("/api/v1/control/light", r#"{"index": 0, "on": true}"#),
        ("/api/v1/control/laser", r#"{"index": 0, "on": true}"#),
        ("/api/v1/control/turntable", r#"{"turn_deg": 10}"#),
        ("/api/v1/control/projector", r#"{"blank": true}"#),
        ("/api/v1/devices/camera/reconnect", "{}"),
    ] {
        let (status, code, message) = answer(&c, "POST", path, Some(body));
        assert_eq!((status, code.as_str()), (409, "scan_running"), "{path}: {message}");
        assert!(message.contains(&id), "{message}");
    }
    let (status, code, message) = answer(&c, "DELETE", &format!("/api/v1/scans/{id}"), None);
    assert_eq!((status, code.as_str()), (409, "wrong_state"), "{message}");
    assert!(message.contains("running") && message.contains("delete"), "{message}");
    assert_eq!(c.get_json("/api/v1/camera").expect("camera")["streaming_paused"], true);
    let meta = wait_finished(&c, &id, Duration::from_secs(60));
    let ended = Instant::now();
    assert_eq!(meta["status"], "complete", "{meta}");
    {
        let p = parts.lock().expect("lock");
        let margin = Duration::from_millis(400);
        let during: Vec<u64> =
            p.iter().filter(|(t, ..)| *t > started + margin && *t + margin < ended).map(|(_, s, _)| *s).collect();
        assert!(during.iter().all(|&s| s <= seq_before + 1), "live frames captured during the scan: {during:?}");
    }
    let n = count(&parts);
    wait_for("live frames after the scan", Duration::from_secs(15), || count(&parts) >= n + 2);
    let last = parts.lock().expect("lock").last().map(|p| p.1).expect("frame");
    assert!(last > seq_before + 8, "the stream resumed with new captures ({last} after {seq_before})");

    // The scan's entry.
    let list = c.get_json("/api/v1/scans").expect("scans");
    let entry =
        list["scans"].as_array().and_then(|a| a.iter().find(|e| e["id"] == id.as_str())).expect("listed").clone();
    assert_eq!(entry["status"], "complete");
    assert_eq!(entry["method"], "space-carving");
    let created = entry["created"].as_str().expect("created");
    assert!(created.len() == 20 && created.ends_with('Z') && created.as_bytes()[10] == b'T', "{created}");
    assert_eq!(entry["report"]["views"], 8, "{entry}");
    assert!(entry["report"]["mesh_triangles"].as_u64().is_some_and(|n| n > 0), "{entry}");
    assert!(entry["report"]["iou"].as_f64().is_some_and(|x| x > 0.3), "{entry}");
    let outputs: Vec<&str> = entry["outputs"].as_array().expect("outputs").iter().filter_map(|o| o.as_str()).collect();
    assert!(outputs.contains(&"model.stl") && outputs.contains(&"model.ply"), "{outputs:?}");
    let one = c.get_json(&format!("/api/v1/scans/{id}")).expect("scan");
    assert_eq!(one["scan"]["outputs"], entry["outputs"]);

    // Thumbnail: a JPEG at most 240 pixels wide.
    let r = c.request("GET", &format!("/api/v1/scans/{id}/thumbnail.jpg"), None).expect("thumbnail");
    let thumb = image::load_from_memory_with_format(&r.body, image::ImageFormat::Jpeg).expect("jpeg");
    assert_eq!((thumb.width(), thumb.height()), (240, 180));

    // Display models: the mesh within max_faces, the voxel centres within max_points.
    let full = scanrig::pipeline::display::read_ply(
        &std::fs::read(dir.path().join("scans").join(&id).join("model.ply")).expect("mesh"),
    )
    .expect("ply");
    let budget = (full.triangles.len() / 4).max(1);
    let r =
        c.request("GET", &format!("/api/v1/scans/{id}/model.ply?kind=mesh&max_faces={budget}"), None).expect("mesh");
    let mesh = scanrig::pipeline::display::read_ply(&r.body).expect("decimated PLY");
    assert!(
        !mesh.triangles.is_empty() && mesh.triangles.len() <= budget,
        "{} faces for {budget}",
        mesh.triangles.len()
    );
    let r = c.request("GET", &format!("/api/v1/scans/{id}/model.ply"), None).expect("mesh");
    assert_eq!(scanrig::pipeline::display::read_ply(&r.body).expect("PLY").triangles.len(), full.triangles.len());
    if outputs.contains(&"voxels.ply") {
        let r = c
            .request("GET", &format!("/api/v1/scans/{id}/model.ply?kind=voxels&max_points=100"), None)
            .expect("voxels");
        let v = scanrig::pipeline::display::read_ply(&r.body).expect("PLY");
        assert!(!v.vertices.is_empty() && v.vertices.len() <= 100, "{}", v.vertices.len());
    }
    if !outputs.contains(&"cloud.ply") {
        let (status, _, _) = answer(&c, "GET", &format!("/api/v1/scans/{id}/model.ply?kind=cloud"), None);
        assert_eq!(status, 404);
    }
    let (status, _, message) = answer(&c, "GET", &format!("/api/v1/scans/{id}/model.ply?max_faces=lots"), None);
    assert!((400..500).contains(&status) && message.contains("max_faces"), "{status} {message}");
    let (status, _, message) = answer(&c, "GET", &format!("/api/v1/scans/{id}/model.ply?kind=hologram"), None);
    assert!((400..500).contains(&status) && message.contains("hologram"), "{status} {message}");

    // Archive: passes `unzip -t` and holds the scan directory's files byte for byte.
    let zip = dir.path().join("scan.zip");
    c.download(&format!("/api/v1/scans/{id}/archive.zip"), &zip).expect("archive");
    let test = Command::new("unzip").arg("-t").arg(&zip).output().expect("unzip is installed");
    assert!(test.status.success(), "{}", String::from_utf8_lossy(&test.stdout));
    let bytes = std::fs::read(&zip).expect("zip");
    let entries = stored_zip_entries(&bytes).expect("entries");
    let scan_dir = dir.path().join("scans").join(&id);
    let mut names: Vec<String> = entries.iter().map(|(n, _)| n.clone()).collect();
    names.sort();
    assert_eq!(names, files_under(&scan_dir));
    assert!(names.iter().any(|n| n.starts_with("frames/pos_")), "{names:?}");
    for (name, data) in &entries {
        assert_eq!(*data, std::fs::read(scan_dir.join(name)).expect("file").as_slice(), "{name}");
    }

    // Delete: gone from disk and list; 404 after.
    let r = c.raw("DELETE", &format!("/api/v1/scans/{id}"), None).expect("delete");
    assert_eq!(r.status, 204);
    assert!(!scan_dir.exists());
    let list = c.get_json("/api/v1/scans").expect("scans");
    assert!(list["scans"].as_array().expect("list").iter().all(|e| e["id"] != id.as_str()));
    for (method, path) in [
        ("GET", format!("/api/v1/scans/{id}")),
        ("DELETE", format!("/api/v1/scans/{id}")),
        ("GET", format!("/api/v1/scans/{id}/archive.zip")),
        ("GET", format!("/api/v1/scans/{id}/thumbnail.jpg")),
        ("GET", format!("/api/v1/scans/{id}/model.ply")),
    ] {
        let (status, code, _) = answer(&c, method, &path, None);
        assert_eq!((status, code.as_str()), (404, "not_found"), "{method} {path}");
    }
}

/// Run `scanrig args... --daemon addr`, killed after 60 s.
fn cli(addr: &str, args: &[&str]) -> Output {
    daemon_common::cli(addr, args, Duration::from_secs(60))
}

/// The stderr of a command that must fail, checked for words rather than Rust debug names.
fn fails(out: &Output) -> String {
    assert!(!out.status.success(), "succeeded: {}", String::from_utf8_lossy(&out.stdout));
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    for debug in ["Api {", "NotFound", "WrongState", "Some(", "status: "] {
        assert!(!err.contains(debug), "a Rust debug name in: {err}");
    }
    err
}

#[test]
fn cli_scans_status_control_fetch_frames_and_delete() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_file(dir.path());
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    connected(&c);
    let a = d.addr.as_str();

    let out = ok(&cli(a, &["status"]));
    assert!(out.contains("rig simulated") && out.contains("no scan running"), "{out}");
    assert!(out.contains("camera") && out.contains("connected"), "{out}");
    let json: serde_json::Value = serde_json::from_str(&ok(&cli(a, &["status", "--json"]))).expect("status --json");
    assert_eq!(json["rig"], "simulated");

    let out = ok(&cli(a, &["control", "light", "1", "on"]));
    assert!(out.contains("lights: 0 off, 1 on, 2 off, 3 off"), "{out}");
    let out = ok(&cli(a, &["control", "turn", "-30"]));
    let angle: f64 = out
        .lines()
        .find_map(|l| l.strip_prefix("turntable at ")?.strip_suffix(" degrees")?.parse().ok())
        .expect("an angle line");
    assert!((angle + 30.0).abs() < 0.2 || (angle - 330.0).abs() < 0.2, "{out}");
    let out = ok(&cli(a, &["control", "projector", "--colour", "0,128,255"]));
    assert!(out.contains("projector: colour #0080ff"), "{out}");
    let err = fails(&cli(a, &["control", "laser", "5", "on"]));
    assert!(err.contains("there is no laser 5: the rig has 1"), "{err}");
    let err = fails(&cli(a, &["control", "projector", "--colour", "red"]));
    assert!(err.contains("--colour red"), "{err}");

    let out = ok(&cli(a, &["reconnect", "camera"]));
    assert!(out.contains("reconnecting camera") && out.contains("camera"), "{out}");
    connected(&c);
    let err = fails(&cli(a, &["reconnect", "toaster"]));
    assert!(err.contains("no device `toaster`"), "{err}");

    let out = ok(&cli(a, &["start", "--positions", "4", "--watch"]));
    let id = out.lines().next().and_then(|l| l.strip_prefix("started ")).expect("started line").to_owned();
    assert!(out.contains(&format!("{id} complete")), "{out}");

    let table = ok(&cli(a, &["scans"]));
    let header = table.lines().next().expect("header");
    assert!(header.starts_with("ID") && header.contains("METHOD") && header.contains("STATUS"), "{table}");
    let row = table.lines().find(|l| l.starts_with(&id)).expect("a row for the scan");
    assert!(row.contains("space-carving") && row.contains("complete"), "{row}");
    let views: Vec<&str> = row.split_whitespace().collect();
    assert_eq!(views[5], "4", "the views column: {row}");

    // fetch --frames: the whole directory, frames included, byte for byte.
    let fetched = dir.path().join("fetched");
    let out = ok(&cli(a, &["fetch", &id, "--out", fetched.to_str().expect("utf8"), "--frames"]));
    let scan_dir = dir.path().join("scans").join(&id);
    assert!(out.contains(&format!("files from {id}")), "{out}");
    assert_eq!(files_under(&fetched), files_under(&scan_dir));
    for f in files_under(&scan_dir) {
        let mut want = Vec::new();
        std::fs::File::open(scan_dir.join(&f)).expect("open").read_to_end(&mut want).expect("read");
        assert_eq!(std::fs::read(fetched.join(&f)).expect("fetched"), want, "{f}");
    }
    let kept = dir.path().join("kept");
    ok(&cli(a, &["fetch", &id, "--out", kept.to_str().expect("utf8"), "--archive"]));
    assert!(kept.join(format!("{id}.zip")).is_file());

    let out = ok(&cli(a, &["delete", &id]));
    assert!(out.contains(&format!("deleted {id}")), "{out}");
    assert!(!scan_dir.exists());
    let err = fails(&cli(a, &["delete", &id]));
    assert!(err.contains(&format!("no scan `{id}`")), "{err}");
    let err = fails(&cli(a, &["fetch", &id, "--out", fetched.to_str().expect("utf8"), "--frames"]));
    assert!(err.contains("404"), "{err}");
    assert!(ok(&cli(a, &["scans"])).contains("(no scans)"));
}
