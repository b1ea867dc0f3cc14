//! The GenICam camera driver through the real Aravis library against Aravis' fake GigE Vision camera
//! (`arv-fake-gv-camera-0.8`, Debian `aravis-tools`) on loopback: settings read back, software and
//! line triggers, disconnect and reconnect through the device trait, real scans through the real
//! binary, one of them with the camera killed half-way, and the same kill under the real daemon,
//! which reconnects the camera when it returns and resumes the failed scan.
//!
//! GigE Vision discovery broadcasts on every network interface, so each test re-runs itself in a
//! private network namespace that has only loopback (`unshare --net`, as root) and starts its own
//! fake camera there: nothing leaves the machine and tests do not see each other's cameras.

#![cfg(feature = "aravis")]

mod daemon_common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use scanrig::config::GenicamCameraConfig;
use scanrig::devices::camera::genicam::GenicamCamera;
use scanrig::devices::{Camera, ErrorKind};

const INSIDE: &str = "SCANRIG_TEST_PRIVATE_NETWORK";
const FAKE_CAMERA: &str = "arv-fake-gv-camera-0.8";

/// Runs `test` (this file's test of that name) again in a new network namespace with only loopback
/// up and returns false once it passed there; returns true inside it, where the test body runs.
fn private_network(test: &str) -> bool {
    if std::env::var_os(INSIDE).is_some() {
        let up = Command::new("ip").args(["link", "set", "lo", "up"]).status().expect("run ip");
        assert!(up.success(), "ip link set lo up failed");
        let dev = std::fs::read_to_string("/proc/net/dev").expect("/proc/net/dev");
        let interfaces: Vec<&str> = dev.lines().skip(2).filter_map(|l| l.split(':').next()).map(str::trim).collect();
        assert_eq!(interfaces, ["lo"], "the private namespace must have loopback only");
        return true;
    }
    let exe = std::env::current_exe().expect("test executable");
    let out = Command::new("unshare")
        .args(["--net", "--"])
        .arg(exe)
        .args([test, "--exact", "--nocapture", "--test-threads=1"])
        .env(INSIDE, "1")
        .output()
        .expect("run unshare (util-linux; needs root)");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{test} in a private network namespace failed:\n{stdout}\n{stderr}");
    assert!(stdout.contains("1 passed"), "{test} did not run in the namespace:\n{stdout}\n{stderr}");
    // The figures the test printed there (shown with --nocapture).
    print!("{stdout}");
    false
}

/// Aravis' fake GigE Vision camera listening on 127.0.0.1, stopped on drop.
struct FakeCamera {
    child: Option<Child>,
}

impl FakeCamera {
    fn start(serial: &str) -> Self {
        Self::start_with(serial, &[])
    }

    /// As [`FakeCamera::start`], with more arguments for the fake camera.
    fn start_with(serial: &str, args: &[&str]) -> Self {
        let child = Command::new(FAKE_CAMERA)
            .args(["-i", "127.0.0.1", "-s", serial])
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {FAKE_CAMERA} (Debian package aravis-tools): {e}"));
        // Ready once its GVCP socket (UDP 3956 = 0x0F74) is bound on 127.0.0.1.
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let udp = std::fs::read_to_string("/proc/net/udp").unwrap_or_default();
            if udp.contains("0100007F:0F74") {
                break;
            }
            assert!(Instant::now() < deadline, "{FAKE_CAMERA} did not bind 127.0.0.1:3956");
            std::thread::sleep(Duration::from_millis(20));
        }
        FakeCamera { child: Some(child) }
    }

    fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for FakeCamera {
    fn drop(&mut self) {
        self.kill();
    }
}

fn camera_config(extra: &str) -> GenicamCameraConfig {
    toml::from_str(&format!(
        r#"vendor = "Aravis"
model = "Fake"
serial = "SR0001"
width = 320
height = 240
{extra}
[calibration.intrinsics]
fx = 800.0
fy = 800.0
cx = 160.0
cy = 120.0
[calibration.pose]
eye_m = [0.0, -0.45, 0.20]
target_m = [0.0, 0.0, 0.035]
"#
    ))
    .expect("camera config")
}

#[test]
fn settings_read_back_and_software_triggers_give_one_fresh_frame_each() {
    if !private_network("settings_read_back_and_software_triggers_give_one_fresh_frame_each") {
        return;
    }
    let _fake = FakeCamera::start("SR0001");
    let config = camera_config(
        "pixel_format = \"Mono8\"\nexposure_us = 8000.0\ngain = 3.0\nfps = 25.0\ntrigger = \"software\"\nbuffers = 3",
    );
    let mut camera = GenicamCamera::open(&config).expect("open the fake camera by vendor/model/serial");
    let s = camera.settings().expect("connected").clone();
    assert_eq!(
        (s.vendor.as_str(), s.model.as_str(), s.serial.as_str(), s.width, s.height, s.pixel_format.as_str()),
        ("Aravis", "Fake", "SR0001", 320, 240, "Mono8")
    );
    assert_eq!((s.exposure_us, s.gain, s.fps), (8000.0, 3.0, 25.0), "{s:?}");
    assert_eq!((s.trigger_mode.as_str(), s.trigger_source.as_deref()), ("On", Some("Software")));

    let mut last = None;
    for i in 0..6u64 {
        let changed_at = Instant::now();
        let f = camera.capture(Duration::from_secs(5)).expect("frame");
        assert!(f.exposure_start >= changed_at, "frame {i} not fresh for a change just before capture");
        assert_eq!((f.image.width(), f.image.height()), (320, 240));
        if let Some(prev) = last {
            assert_eq!(f.sequence, prev + 1, "consecutive frame ids");
        }
        last = Some(f.sequence);
        // Mono8 expands to equal R, G and B; the fake camera's test image is not uniform.
        assert!(f.image.pixels().all(|p| p[0] == p[1] && p[1] == p[2]));
        assert!(f.image.pixels().any(|p| p[0] != f.image.get_pixel(0, 0)[0]), "a real image");
    }
    assert_eq!((camera.triggers(), camera.delivered(), camera.dropped_frames()), (6, 6, 0));
    // The stream completed the six captures and the frame(s) that showed, right after
    // AcquisitionStart, that the stream works.
    let stats = camera.statistics();
    assert!(camera.primed_frames() >= 1, "the stream was checked with a frame");
    assert_eq!((stats.completed, stats.failures, stats.underruns), (6 + camera.primed_frames(), 0, 0), "{stats:?}");

    // RGB8 and another exposure / gain / rate read back too (a second connection to the camera).
    drop(camera);
    let config = camera_config("pixel_format = \"RGB8\"\nexposure_us = 2500.0\ngain = 7.0\nfps = 10.0");
    let mut camera = GenicamCamera::open(&config).expect("open again");
    let s = camera.settings().expect("connected").clone();
    assert_eq!((s.pixel_format.as_str(), s.exposure_us, s.gain, s.fps), ("RGB8", 2500.0, 7.0, 10.0), "{s:?}");
    assert_eq!(s.trigger_mode, "Off");
    let f = camera.capture(Duration::from_secs(5)).expect("free-run frame");
    assert_eq!((f.image.width(), f.image.height()), (320, 240));
    assert_eq!(camera.triggers(), 0, "free run sends no trigger");
}

#[test]
fn a_line_trigger_is_configured_and_waits_for_its_pulse() {
    if !private_network("a_line_trigger_is_configured_and_waits_for_its_pulse") {
        return;
    }
    let _fake = FakeCamera::start("SR0001");
    let mut camera = GenicamCamera::open(&camera_config("trigger = \"line\"\ntrigger_line = \"Line0\"")).expect("open");
    let s = camera.settings().expect("connected").clone();
    assert_eq!(
        (s.trigger_mode.as_str(), s.trigger_source.as_deref(), s.trigger_activation.as_deref()),
        ("On", Some("Line0"), Some("RisingEdge"))
    );
    // Nothing pulses the fake camera's line: no frame, and the camera still answers (Timeout, not
    // Disconnected).
    let e = camera.capture(Duration::from_millis(400)).expect_err("no pulse, no frame");
    assert_eq!(e.kind(), ErrorKind::Timeout, "{e}");
    drop(camera);

    // The fake camera has no TriggerDelay and only a rising edge: typed configuration errors.
    let e = GenicamCamera::open(&camera_config("trigger = \"line\"\ntrigger_delay_us = 50.0")).expect_err("no delay");
    assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");
    assert!(e.to_string().contains("trigger_delay_us"), "{e}");
    let e = GenicamCamera::open(&camera_config("trigger = \"line\"\ntrigger_activation = \"falling-edge\""))
        .expect_err("no falling edge");
    assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");
    // A serial nobody has: Disconnected (absent), not a crash.
    let mut c = camera_config("");
    c.serial = Some("NOPE".into());
    assert_eq!(GenicamCamera::open(&c).expect_err("absent").kind(), ErrorKind::Disconnected);
}

#[test]
fn a_vanished_camera_is_disconnected_and_reconnects_when_it_returns() {
    if !private_network("a_vanished_camera_is_disconnected_and_reconnects_when_it_returns") {
        return;
    }
    let mut fake = FakeCamera::start("SR0001");
    let mut camera = GenicamCamera::open(&camera_config("trigger = \"software\"\nexposure_us = 4000.0")).expect("open");
    camera.capture(Duration::from_secs(5)).expect("frame before");
    fake.kill();
    let e = camera.capture(Duration::from_secs(3)).expect_err("camera gone");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    assert!(camera.settings().is_none(), "the connection is dropped");
    let e = camera.capture(Duration::from_millis(500)).expect_err("still gone");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");

    let _back = FakeCamera::start("SR0001");
    let deadline = Instant::now() + Duration::from_secs(20);
    let frame = loop {
        match camera.capture(Duration::from_secs(3)) {
            Ok(f) => break f,
            Err(e) => {
                assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
                assert!(Instant::now() < deadline, "no reconnect: {e}");
            }
        }
    };
    assert_eq!(frame.image.width(), 320);
    assert_eq!(camera.reconnects(), 1);
    let s = camera.settings().expect("reconnected");
    assert_eq!(s.exposure_us, 4000.0, "settings applied again after the reconnect");
}

const RIG: &str = r#"
[rig]
name = "genicam-fake"
description = "Aravis' fake GigE Vision camera on loopback over a simulated turntable"

[turntable]
kind = "sim"
real_time = REAL_TIME
speed_deg_per_s = 90.0

[camera]
kind = "genicam"
vendor = "Aravis"
model = "Fake"
serial = "SR0001"
width = 320
height = 240
pixel_format = "Mono8"
exposure_us = 8000.0
gain = 3.0
fps = 25.0
trigger = "software"
buffers = 4

[camera.calibration.intrinsics]
fx = 800.0
fy = 800.0
cx = 160.0
cy = 120.0

[camera.calibration.pose]
eye_m = [0.0, -0.45, 0.20]
target_m = [0.0, 0.0, 0.035]

[sim]
scene = "cup"

[scan]
positions = POSITIONS
settle_ms = 0

[reconstruction]
method = "space-carving"
bbox_min_m = [-0.045, -0.045, 0.0]
bbox_max_m = [0.045, 0.045, 0.09]
resolution = 24

# The fake camera's test image is not the cup: every pixel counts as object.
[reconstruction.silhouette]
threshold = 0.0
background = [0, 0, 0]
"#;

fn write_rig(dir: &Path, positions: u32, real_time: bool) -> PathBuf {
    let rig = dir.join("genicam.toml");
    let text = RIG.replace("POSITIONS", &positions.to_string()).replace("REAL_TIME", &real_time.to_string());
    std::fs::write(&rig, text).expect("write rig");
    rig
}

fn scan_command(rig: &Path, out: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_scanrig"));
    c.args(["scan", "--rig"]).arg(rig).arg("--out").arg(out);
    c.env("SCANRIG_LOG", "warn,scanrig::devices::camera::genicam=info").env("NO_COLOR", "1");
    c
}

/// The `key=value` number of the driver's closing log line.
fn closing_count(log: &str, key: &str) -> u64 {
    let line =
        log.lines().find(|l| l.contains("GenICam camera closed")).unwrap_or_else(|| panic!("no closing line:\n{log}"));
    let plain: String = {
        // Strip ANSI colour codes, if any.
        let mut out = String::new();
        let mut esc = false;
        for ch in line.chars() {
            match (esc, ch) {
                (false, '\u{1b}') => esc = true,
                (true, 'm') => esc = false,
                (true, _) => {}
                (false, c) => out.push(c),
            }
        }
        out
    };
    plain
        .split_whitespace()
        .find_map(|w| w.strip_prefix(&format!("{key}=")))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {key}= in {plain}"))
}

/// The positions whose frame is complete on disk (image decodes, metadata present), with their
/// sequence numbers.
fn frames_on_disk(out: &Path) -> Vec<(usize, u64)> {
    let mut found = Vec::new();
    for position in 0.. {
        let json = out.join(format!("frames/pos_{position:03}.json"));
        let Ok(text) = std::fs::read_to_string(&json) else { break };
        let meta: serde_json::Value = serde_json::from_str(&text).expect("frame metadata");
        let image = image::open(out.join(format!("frames/pos_{position:03}.png"))).expect("frame image decodes");
        assert_eq!((image.width(), image.height()), (320, 240));
        found.push((position, meta["sequence"].as_u64().expect("sequence")));
    }
    found
}

#[test]
fn a_scan_through_the_binary_captures_one_triggered_frame_per_position() {
    if !private_network("a_scan_through_the_binary_captures_one_triggered_frame_per_position") {
        return;
    }
    let _fake = FakeCamera::start("SR0001");
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = write_rig(dir.path(), 8, false);
    let out = dir.path().join("out");
    let run = scan_command(&rig, &out).output().expect("run scanrig");
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "scan failed:\n{log}");
    let frames = frames_on_disk(&out);
    assert_eq!(frames.len(), 8, "{frames:?}");
    assert!(frames.windows(2).all(|w| w[1].1 == w[0].1 + 1), "consecutive frame ids: {frames:?}");
    assert_eq!(closing_count(&log, "triggers"), 8, "{log}");
    assert_eq!(closing_count(&log, "delivered"), 8, "{log}");
    assert_eq!(closing_count(&log, "completed"), 8 + closing_count(&log, "primed"), "{log}");
    assert!(closing_count(&log, "primed") >= 1, "{log}");
    assert_eq!(closing_count(&log, "dropped") + closing_count(&log, "failures") + closing_count(&log, "underruns"), 0);
    assert!(out.join("report.json").is_file());
}

#[test]
fn killing_the_camera_mid_scan_fails_it_typed_and_keeps_the_frames() {
    if !private_network("killing_the_camera_mid_scan_fails_it_typed_and_keeps_the_frames") {
        return;
    }
    let mut fake = FakeCamera::start("SR0001");
    let dir = tempfile::tempdir().expect("tempdir");
    // 24 positions of 15 degrees at 90 degrees/s: about 4 s of real turning.
    let rig = write_rig(dir.path(), 24, true);
    let out = dir.path().join("out");
    let mut scan = scan_command(&rig, &out).stderr(Stdio::piped()).spawn().expect("start scanrig");
    let third = out.join("frames/pos_002.json");
    let deadline = Instant::now() + Duration::from_secs(60);
    while !third.exists() {
        assert!(Instant::now() < deadline, "no third frame");
        assert!(scan.try_wait().expect("wait").is_none(), "scan ended before the camera was killed");
        std::thread::sleep(Duration::from_millis(10));
    }
    fake.kill();
    let run = scan.wait_with_output().expect("scan ends");
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "the scan must fail:\n{log}");
    assert!(log.contains("camera: disconnected"), "a typed disconnect:\n{log}");
    assert!(!log.contains("panicked"), "{log}");
    let frames = frames_on_disk(&out);
    assert!((3..24).contains(&frames.len()), "{} frames kept", frames.len());
    assert!(!out.join("report.json").exists(), "no report for a failed scan");
    // Every frame it wrote was a triggered capture, and nothing half-written was left behind.
    assert_eq!(closing_count(&log, "delivered") as usize, frames.len(), "{log}");
    let pngs = std::fs::read_dir(out.join("frames"))
        .expect("frames dir")
        .filter(|e| e.as_ref().is_ok_and(|e| e.path().extension().is_some_and(|x| x == "png")));
    assert_eq!(pngs.count(), frames.len());
}

#[test]
fn a_camera_whose_stream_never_arrives_is_refused_at_connect() {
    if !private_network("a_camera_whose_stream_never_arrives_is_refused_at_connect") {
        return;
    }
    // The control channel answers, every stream packet is lost (as behind a firewall that drops
    // the camera's UDP stream): the camera must not pass for connected.
    let _fake = FakeCamera::start_with("SR0001", &["--gvsp-lost-ratio", "1000"]);
    let config = camera_config("pixel_format = \"Mono8\"\nfps = 25.0\ntrigger = \"software\"");
    let started = Instant::now();
    let e = GenicamCamera::open(&config).expect_err("a camera whose frames never arrive");
    let text = e.to_string();
    assert_eq!(e.kind(), ErrorKind::Protocol, "{text}");
    assert!(text.contains("no complete frame reached this host"), "{text}");
    assert!(text.contains("0 completed"), "{text}");
    assert!(started.elapsed() >= Duration::from_secs(3), "gave up before its timeout");
}

#[test]
fn scanrig_devices_lists_the_camera_with_its_rig_lines() {
    if !private_network("scanrig_devices_lists_the_camera_with_its_rig_lines") {
        return;
    }
    let _fake = FakeCamera::start("SR0042");
    let out = Command::new(env!("CARGO_BIN_EXE_scanrig")).arg("devices").output().expect("scanrig devices");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}");
    assert!(text.contains("GenICam cameras (1):"), "{text}");
    assert!(text.contains("serial \"SR0042\"  GigEVision 127.0.0.1"), "{text}");
    assert!(
        text.contains("kind = \"genicam\"\n    vendor = \"Aravis\"\n    model = \"Fake\"\n    serial = \"SR0042\""),
        "{text}"
    );
}

/// `(state, reconnects, last_error)` of device `name` in `GET /api/v1/devices`.
fn device(c: &scanrig::service::client::Client, name: &str) -> (String, u64, String) {
    let v = c.get_json("/api/v1/devices").expect("devices");
    let d = v["devices"].as_array().and_then(|a| a.iter().find(|d| d["name"] == name)).cloned().unwrap_or_default();
    (
        d["state"].as_str().unwrap_or("").to_owned(),
        d["reconnects"].as_u64().unwrap_or(0),
        d["last_error"].as_str().unwrap_or("").to_owned(),
    )
}

/// Wait until the daemon shows the camera connected, at most `limit` after `since`; on timeout the
/// panic gives the camera's state and the daemon's log.
fn wait_connected(c: &scanrig::service::client::Client, d: &daemon_common::Daemon, since: Instant, limit: Duration) {
    while device(c, "camera").0 != "connected" {
        assert!(
            since.elapsed() < limit,
            "the camera was not connected {limit:?} on: {:?}\n{}",
            device(c, "camera"),
            d.log()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn the_daemon_fails_a_scan_when_the_camera_vanishes_and_reconnects_it_when_it_returns() {
    if !private_network("the_daemon_fails_a_scan_when_the_camera_vanishes_and_reconnects_it_when_it_returns") {
        return;
    }
    let mut fake = FakeCamera::start("SR0001");
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = write_rig(dir.path(), 24, true);
    let mut d = daemon_common::spawn(&rig, dir.path());
    let c = daemon_common::client(&d);
    // The first connection: the fake camera is bound, but on a loaded machine (two of these tests
    // run at once, each with its camera and daemon) the daemon's first attempts may fail and back off
    // (up to 8 s apart). Say what the daemon logged if it never connects.
    wait_connected(&c, &d, Instant::now(), Duration::from_secs(60));

    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    let out = dir.path().join("scans").join(&id);
    let deadline = Instant::now() + Duration::from_secs(30);
    while !out.join("frames/pos_002.json").exists() && daemon_common::scan_meta(&c, &id)["status"] == "running" {
        assert!(Instant::now() < deadline, "no third frame in 30 s:\n{}", d.log());
        std::thread::sleep(Duration::from_millis(10));
    }
    let meta = daemon_common::scan_meta(&c, &id);
    assert_eq!(meta["status"], "running", "the scan ended before the camera was killed: {meta}\n{}", d.log());
    fake.kill();

    // The scan fails with the camera's disconnect in words; every frame it captured is on disk.
    let meta = daemon_common::wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "failed", "{meta}");
    let error = meta["error"].as_str().unwrap_or("");
    assert!(error.contains("camera: disconnected"), "not a typed camera disconnect: {error}");
    let kept = frames_on_disk(&out);
    assert!((3..24).contains(&kept.len()), "{} frames kept", kept.len());
    assert!(!out.join("report.json").exists(), "no report for a failed scan");
    let pngs = daemon_common::frames_on_disk(dir.path(), &id).iter().filter(|f| f.ends_with(".png")).count();
    assert_eq!(pngs, kept.len(), "a frame image without its metadata");
    let kept_bytes: Vec<Vec<u8>> = (0..kept.len())
        .map(|p| std::fs::read(out.join(format!("frames/pos_{p:03}.png"))).expect("kept frame"))
        .collect();

    // The camera is shown gone, with why; the daemon stays up.
    daemon_common::wait_for("the camera shown disconnected", Duration::from_secs(20), || {
        let (state, _, e) = device(&c, "camera");
        state == "disconnected" && e.contains("camera: disconnected")
    });
    // Every capture the driver delivered before the kill is one of the kept frames (the closing line
    // of the connection the scan used).
    let log = d.log();
    assert_eq!(closing_count(&log, "delivered") as usize, kept.len(), "{log}");
    assert_eq!(device(&c, "camera").1, 0, "no reconnection yet");
    assert!(d.alive());
    println!("devices while the camera is gone: {}", c.get_json("/api/v1/devices").expect("devices"));

    // The camera comes back (same serial): the daemon reconnects it by itself.
    let _back = FakeCamera::start("SR0001");
    let returned = Instant::now();
    // One reconnection attempt waits up to 8 s of backoff plus a discovery that finds nothing until
    // the camera answers: 13 s on an idle machine, more when two of these tests share two cores.
    wait_connected(&c, &d, returned, Duration::from_secs(90));
    println!("reconnected {:.1} s after the camera returned", returned.elapsed().as_secs_f64());
    let (_, reconnects, last_error) = device(&c, "camera");
    assert_eq!((reconnects, last_error.as_str()), (1, ""));

    // The failed scan resumes on the returned camera and completes: the kept frames are reused as
    // they were, the rest captured now.
    c.post_json(&format!("/api/v1/scans/{id}/resume"), &serde_json::json!({})).expect("resume");
    let meta = daemon_common::wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "complete", "{meta}\n{}", d.log());
    assert_eq!(meta["resumes"], 1, "{meta}");
    let frames = frames_on_disk(&out);
    assert_eq!(frames.len(), 24, "{frames:?}");
    for (p, bytes) in kept_bytes.iter().enumerate() {
        let now = std::fs::read(out.join(format!("frames/pos_{p:03}.png"))).expect("frame");
        assert!(now == *bytes, "kept frame {p} was changed by the resume");
    }
    assert_eq!(&frames[..kept.len()], &kept[..], "kept frames' metadata unchanged");
    assert!(out.join("report.json").is_file());
    assert_eq!(device(&c, "camera").1, 1, "one reconnection");
    assert!(d.alive());
    println!(
        "camera killed after {} of 24 frames; scan failed with: {error}; reconnected once; resumed to 24 frames",
        kept.len()
    );
}
