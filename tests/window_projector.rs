//! The window projector against a real X server: Xvfb with two screens, the window full-screen on
//! the second, every pattern of a Gray-code sequence read back from the server with `xwd` and
//! compared pixel for pixel, the refresh period measured from the server's presentation times, and
//! the server killed under it, also in the middle of a structured-light scan through the real binary
//! and under the real daemon, which reconnects the projector when the server returns.
//!
//! The test starts Xvfb itself (Debian `xvfb`; `xwd` from `x11-apps`) on a display number Xvfb picks
//! (`-displayfd`), listening on its Unix socket only.

#![cfg(feature = "x11")]

mod daemon_common;

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use scanrig::config::WindowProjectorConfig;
use scanrig::devices::projector::window::WindowProjector;
use scanrig::devices::{ErrorKind, Pattern, Projector};
use scanrig::pipeline::structured_light::GrayCodePatterns;

/// Xvfb (by default screen 0 at 640x480 and screen 1 at 800x600), killed on drop.
struct Xvfb {
    child: Option<Child>,
    display: String,
}

impl Xvfb {
    fn start() -> Self {
        Self::start_with(&["-screen", "0", "640x480x24", "-screen", "1", "800x600x24"])
    }

    fn start_with(screens: &[&str]) -> Self {
        Self::start_on(None, screens)
    }

    /// Xvfb on `display` (`:N`), or on a display number it picks; returns once it accepts
    /// connections (it writes its number to `-displayfd` then).
    fn start_on(display: Option<&str>, screens: &[&str]) -> Self {
        let mut child = Command::new("Xvfb")
            .args(display)
            .args(["-displayfd", "1", "-nolisten", "tcp", "-noreset"])
            .args(screens)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start Xvfb (Debian package xvfb): {e}"));
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("stdout")).read_line(&mut line).expect("Xvfb display number");
        let n: u32 = line.trim().parse().unwrap_or_else(|_| panic!("Xvfb printed {line:?}, not a display number"));
        Xvfb { child: Some(child), display: format!(":{n}") }
    }

    fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for Xvfb {
    fn drop(&mut self) {
        self.kill();
    }
}

fn config(display: &str, output: &str, width: u32, height: u32) -> WindowProjectorConfig {
    toml::from_str(&format!("display = \"{display}\"\noutput = \"{output}\"\nwidth = {width}\nheight = {height}"))
        .expect("projector config")
}

/// Screen `screen` of `display` as RGB, read by `xwd -root` and decoded from its XWD file.
fn xwd_rgb(display: &str, screen: u32) -> (u32, u32, Vec<u8>) {
    let out = Command::new("xwd")
        .args(["-root", "-silent", "-display", &format!("{display}.{screen}")])
        .output()
        .unwrap_or_else(|e| panic!("cannot run xwd (Debian package x11-apps): {e}"));
    assert!(out.status.success(), "xwd failed: {}", String::from_utf8_lossy(&out.stderr));
    let d = out.stdout;
    let word = |i: usize| u32::from_be_bytes([d[4 * i], d[4 * i + 1], d[4 * i + 2], d[4 * i + 3]]);
    let (header, version, format) = (word(0) as usize, word(1), word(2));
    assert_eq!((version, format), (7, 2), "XWD version 7, ZPixmap");
    let (width, height, byte_order, bpp, line) = (word(4), word(5), word(7), word(11), word(12) as usize);
    let masks = [word(14), word(15), word(16)];
    let ncolors = word(19) as usize;
    assert_eq!(bpp, 32, "a 24-bit screen is stored in 32-bit pixels");
    let data = &d[header + 12 * ncolors..];
    assert!(data.len() >= line * height as usize, "XWD image data is short");
    let mut rgb = Vec::with_capacity(3 * (width * height) as usize);
    for y in 0..height as usize {
        for x in 0..width as usize {
            let p = &data[y * line + 4 * x..y * line + 4 * x + 4];
            let v = if byte_order == 0 {
                u32::from_le_bytes([p[0], p[1], p[2], p[3]])
            } else {
                u32::from_be_bytes([p[0], p[1], p[2], p[3]])
            };
            for m in masks {
                rgb.push(((v & m) >> m.trailing_zeros()) as u8);
            }
        }
    }
    (width, height, rgb)
}

fn grey_to_rgb(width: u32, height: u32, grey: &[u8]) -> Pattern {
    Pattern { width, height, rgb: Arc::new(grey.iter().flat_map(|&v| [v, v, v]).collect()) }
}

#[test]
fn every_gray_pattern_reads_back_from_the_second_screen_pixel_for_pixel() {
    let mut x = Xvfb::start();
    let display = x.display.clone();

    // An output that does not exist: the error names the ones that do.
    let e = WindowProjector::open(&config(&display, "HDMI-9", 800, 600)).expect_err("no such output");
    assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");
    assert!(e.to_string().contains("outputs:"), "{e}");
    // Xvfb names each screen's output `screen`: a name on two screens is refused, screen:N is not.
    let e = WindowProjector::open(&config(&display, "screen", 800, 600)).expect_err("ambiguous name");
    assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");
    assert!(e.to_string().contains("is on 2 screens"), "{e}");
    // The wrong size for the output: refused.
    let e = WindowProjector::open(&config(&display, "screen:1", 640, 480)).expect_err("wrong size");
    assert_eq!(e.kind(), ErrorKind::InvalidConfig, "{e}");

    let mut projector = WindowProjector::open(&config(&display, "screen:1", 800, 600)).expect("window on screen 1");
    assert_eq!(projector.resolution(), (800, 600));
    assert_eq!(projector.placement().screen, 1);
    assert!(projector.uses_present(), "Xvfb has the Present extension");

    let gray = GrayCodePatterns::new(800, 600).expect("Gray patterns");
    let mut last_at: Option<Instant> = None;
    for i in 0..gray.count() {
        let pattern = grey_to_rgb(800, 600, &gray.render(i).expect("render"));
        let before = Instant::now();
        let at = projector.show(&pattern, Duration::from_secs(5)).expect("show");
        assert!(at >= before, "pattern {i}: reported on screen before it was submitted");
        assert!(Instant::now() >= at, "show returns once the pattern is on screen");
        if let Some(prev) = last_at {
            assert!(at > prev, "pattern {i}: presentations in order");
        }
        last_at = Some(at);
        let (w, h, rgb) = xwd_rgb(&display, 1);
        assert_eq!((w, h), (800, 600));
        if rgb != *pattern.rgb {
            let first = rgb.iter().zip(pattern.rgb.iter()).position(|(a, b)| a != b).unwrap_or(0) / 3;
            panic!("pattern {i}: pixel ({}, {}) differs", first % 800, first / 800);
        }
    }
    // Colour channels land where they should: red, green and blue from position.
    let mut rgb = Vec::with_capacity(800 * 600 * 3);
    for y in 0..600u32 {
        for x in 0..800u32 {
            rgb.extend_from_slice(&[(x % 256) as u8, (y % 256) as u8, ((x * 7 + y * 3) % 256) as u8]);
        }
    }
    let colour = Pattern { width: 800, height: 600, rgb: Arc::new(rgb) };
    projector.show(&colour, Duration::from_secs(5)).expect("show colour");
    assert!(xwd_rgb(&display, 1).2 == *colour.rgb, "colour pattern reads back");
    // Screen 0 was left alone.
    assert!(xwd_rgb(&display, 0).2.iter().all(|&v| v == 0), "nothing drawn on screen 0");

    let period = projector.measured_refresh_period().expect("refresh period from the presentation times");
    println!(
        "Xvfb presentation refresh period measured over {} patterns: {:.3} ms ({:.1} Hz)",
        gray.count() + 1,
        period.as_secs_f64() * 1e3,
        1.0 / period.as_secs_f64()
    );
    assert!(period > Duration::ZERO);

    projector.blank(Duration::from_secs(5)).expect("blank");
    assert!(xwd_rgb(&display, 1).2.iter().all(|&v| v == 0), "blank is black");

    // The X server goes away: a typed disconnect, not a hang or a panic.
    x.kill();
    let e = projector.show(&colour, Duration::from_secs(2)).expect_err("server gone");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    let e = WindowProjector::open(&config(&display, "screen:1", 800, 600)).expect_err("no server");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
}

#[test]
fn without_vsync_the_pattern_is_drawn_directly_and_still_reads_back() {
    let x = Xvfb::start();
    let mut c = config(&x.display, "screen:0", 640, 480);
    c.vsync = false;
    c.refresh_hz = 50.0;
    let mut projector = WindowProjector::open(&c).expect("window on screen 0");
    assert!(!projector.uses_present());
    let gray = GrayCodePatterns::new(640, 480).expect("Gray patterns");
    for i in [0, gray.count() / 2, gray.count() - 1] {
        let pattern = grey_to_rgb(640, 480, &gray.render(i).expect("render"));
        let before = Instant::now();
        let at = projector.show(&pattern, Duration::from_secs(5)).expect("show");
        assert!(at >= before + Duration::from_millis(20), "one assumed refresh (20 ms at 50 Hz) is allowed");
        assert!(xwd_rgb(&x.display, 0).2 == *pattern.rgb, "pattern {i} reads back");
    }
}

#[test]
fn killing_the_x_server_mid_scan_fails_the_scan_typed_and_keeps_the_frames() {
    let mut x = Xvfb::start_with(&["-screen", "0", "640x480x24", "-screen", "1", "512x384x24"]);
    let shipped = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/structured-light.toml");
    let text = std::fs::read_to_string(&shipped).expect("structured-light rig");
    let sim_projector = "[projector]\nkind = \"sim\"\nwidth = 512\nheight = 384\nintensity = 1.0\nlatency_ms = 30.0\nframe_period_ms = 16.667\n";
    assert!(text.contains(sim_projector), "the shipped rig changed; update this test");
    let window = format!(
        "[projector]\nkind = \"window\"\ndisplay = \"{}\"\noutput = \"screen:1\"\nwidth = 512\nheight = 384\n",
        x.display
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = dir.path().join("window.toml");
    std::fs::write(&rig, text.replace(sim_projector, &window).replace("resolution = 128", "resolution = 32"))
        .expect("write rig");
    let out = dir.path().join("out");
    let mut scan = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(["scan", "--rig"])
        .arg(&rig)
        .arg("--out")
        .arg(&out)
        .env("NO_COLOR", "1")
        .stderr(Stdio::piped())
        .spawn()
        .expect("start scanrig");
    // Two whole views (their patterns shown on the window, one frame each captured) on disk, then
    // the X server goes.
    let second = out.join("frames/pos_001.json");
    let deadline = Instant::now() + Duration::from_secs(120);
    while !second.exists() {
        assert!(Instant::now() < deadline, "no second view");
        assert!(scan.try_wait().expect("wait").is_none(), "scan ended before the X server was killed");
        std::thread::sleep(Duration::from_millis(10));
    }
    x.kill();
    let run = scan.wait_with_output().expect("scan ends");
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "the scan must fail:\n{log}");
    assert!(log.contains("projector: disconnected"), "a typed disconnect:\n{log}");
    assert!(!log.contains("panicked"), "{log}");
    assert!(!out.join("report.json").exists(), "no report for a failed scan");
    let mut views = 0;
    // Every complete view (its record written after its frames) keeps all its captures: 9 column
    // bit pairs, white and black.
    while out.join(format!("frames/pos_{views:03}.json")).exists() {
        for k in 0..20 {
            let img =
                image::open(out.join(format!("frames/pos_{views:03}_pattern_{k:02}.png"))).expect("kept frame decodes");
            assert_eq!(img.width(), 400);
        }
        views += 1;
    }
    assert!((2..16).contains(&views), "{views} views kept");
}

/// The shipped structured-light rig with the window projector on `display`'s screen 1 (512x384)
/// and a coarse grid, written to `dir/window.toml`.
fn window_rig(dir: &std::path::Path, display: &str, positions: u32) -> std::path::PathBuf {
    let shipped = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/structured-light.toml");
    let text = std::fs::read_to_string(&shipped).expect("structured-light rig");
    let sim_projector = "[projector]\nkind = \"sim\"\nwidth = 512\nheight = 384\nintensity = 1.0\nlatency_ms = 30.0\nframe_period_ms = 16.667\n";
    assert!(text.contains(sim_projector), "the shipped rig changed; update this test");
    assert!(text.contains("positions = 16\n"), "the shipped rig changed; update this test");
    let window = format!(
        "[projector]\nkind = \"window\"\ndisplay = \"{display}\"\noutput = \"screen:1\"\nwidth = 512\nheight = 384\n"
    );
    let rig = dir.join("window.toml");
    let text = text
        .replace(sim_projector, &window)
        .replace("resolution = 128", "resolution = 32")
        .replace("positions = 16\n", &format!("positions = {positions}\n"));
    std::fs::write(&rig, text).expect("write rig");
    rig
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

/// The complete views of a scan directory (record written after its 20 frames), each frame read.
fn complete_views(out: &std::path::Path) -> Vec<Vec<Vec<u8>>> {
    let mut views = Vec::new();
    while out.join(format!("frames/pos_{:03}.json", views.len())).exists() {
        let v = views.len();
        let frames: Vec<Vec<u8>> = (0..20)
            .map(|k| {
                let path = out.join(format!("frames/pos_{v:03}_pattern_{k:02}.png"));
                let img = image::open(&path).expect("kept frame decodes");
                assert_eq!(img.width(), 400);
                std::fs::read(&path).expect("frame")
            })
            .collect();
        views.push(frames);
    }
    views
}

#[test]
fn the_daemon_fails_a_scan_when_the_x_server_dies_and_reconnects_the_projector_when_it_returns() {
    const SCREENS: [&str; 6] = ["-screen", "0", "640x480x24", "-screen", "1", "512x384x24"];
    let mut x = Xvfb::start_with(&SCREENS);
    let display = x.display.clone();
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = window_rig(dir.path(), &display, 6);
    let mut d = daemon_common::spawn(&rig, dir.path());
    let c = daemon_common::client(&d);
    daemon_common::wait_for("the projector connected", Duration::from_secs(20), || {
        device(&c, "projector").0 == "connected"
    });

    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    let out = dir.path().join("scans").join(&id);
    // Two whole views on disk, then the X server goes.
    daemon_common::wait_for("a second view", Duration::from_secs(60), || out.join("frames/pos_001.json").exists());
    x.kill();

    let meta = daemon_common::wait_finished(&c, &id, Duration::from_secs(30));
    assert_eq!(meta["status"], "failed", "{meta}");
    let error = meta["error"].as_str().unwrap_or("");
    assert!(error.contains("projector: disconnected"), "not a typed projector disconnect: {error}");
    assert!(!out.join("report.json").exists(), "no report for a failed scan");
    let kept = complete_views(&out);
    assert!((2..6).contains(&kept.len()), "{} views kept", kept.len());

    daemon_common::wait_for("the projector shown disconnected", Duration::from_secs(20), || {
        let (state, _, e) = device(&c, "projector");
        state == "disconnected" && e.contains("projector: disconnected")
    });
    assert_eq!(device(&c, "projector").1, 0, "no reconnection yet");
    assert!(d.alive());

    // The X server comes back on the same display: the daemon reconnects the projector by itself.
    let _back = Xvfb::start_on(Some(&display), &SCREENS);
    daemon_common::wait_for("the projector reconnected", Duration::from_secs(30), || {
        device(&c, "projector").0 == "connected"
    });
    let (_, reconnects, last_error) = device(&c, "projector");
    assert_eq!((reconnects, last_error.as_str()), (1, ""));

    // The failed scan resumes on the new window and completes, reusing the kept views as they were.
    c.post_json(&format!("/api/v1/scans/{id}/resume"), &serde_json::json!({})).expect("resume");
    let meta = daemon_common::wait_finished(&c, &id, Duration::from_secs(60));
    assert_eq!(meta["status"], "complete", "{meta}");
    assert_eq!(meta["resumes"], 1, "{meta}");
    let views = complete_views(&out);
    assert_eq!(views.len(), 6);
    assert!(views[..kept.len()] == kept[..], "a kept view was changed by the resume");
    assert!(out.join("report.json").is_file());
    assert_eq!(device(&c, "projector").1, 1, "one reconnection");
    assert!(d.alive());
    println!(
        "X server killed after {} of 6 views; scan failed with: {error}; reconnected once; resumed to 6 views",
        kept.len()
    );
}
