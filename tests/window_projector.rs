//! The window projector against a real X server: Xvfb with two screens, the window full-screen on
//! the second, every pattern of a Gray-code sequence read back from the server with `xwd` and
//! compared pixel for pixel, the refresh period measured from the server's presentation times, and
//! the server killed under it, also in the middle of a structured-light scan through the real binary.
//!
//! The test starts Xvfb itself (Debian `xvfb`; `xwd` from `x11-apps`) on a display number Xvfb picks
//! (`-displayfd`), listening on its Unix socket only.

#![cfg(feature = "x11")]

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
        let mut child = Command::new("Xvfb")
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
