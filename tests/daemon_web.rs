//! The web console in headless Chromium against a real `scanrigd` on 127.0.0.1, driven over the
//! DevTools protocol on a pipe (no extra crates, no network port for the browser). Every button is
//! pressed with a synthesized mouse click and its API call checked in the browser's network log;
//! the 3D view is checked on screenshots (live estimate while the scan runs, the mesh after it, an
//! orbit drag); nothing may log a console error or fail a request. Fails under CI (`CI` set) when
//! Chromium is missing; elsewhere it skips with a printed reason. Every wait is bounded.
//!
//! `SCANRIG_SCREENSHOTS=DIR` writes the page's screenshots (idle, mid-scan, result; desktop and
//! 390 px phone width) as PNGs into DIR: `docs/` holds the ones the README shows.

mod daemon_common;

use std::io::{Read, Write};
use std::os::fd::{FromRawFd, OwnedFd};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use daemon_common::{client, rig_from, scan_meta, spawn, wait_finished, wait_for};
use image::RgbImage;
use serde_json::{json, Value};

/// Desktop viewport, CSS pixels.
const DESKTOP: (u32, u32) = (1280, 900);
/// Phone viewport (an iPhone 12-14 in portrait), CSS pixels.
const PHONE: (u32, u32) = (390, 844);
/// The viewer's background colour (web/viewer.js `BACKGROUND`).
const BACKGROUND: [u8; 3] = [0x1d, 0x21, 0x27];

fn find_chromium() -> Option<String> {
    ["chromium", "chromium-browser", "google-chrome"].into_iter().map(str::to_owned).find(|name| {
        Command::new(name)
            .arg("--version")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    })
}

/// A headless browser with its DevTools pipe (fd 3 in, fd 4 out in the child), attached to one
/// page. Every message that is not an answer is kept in `events`, in arrival order.
struct Browser {
    child: Child,
    to: std::fs::File,
    from: Receiver<Value>,
    next_id: u64,
    session: Option<String>,
    events: Vec<Value>,
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn pipe() -> (OwnedFd, OwnedFd) {
    let mut fds = [0; 2];
    // SAFETY: pipe2 fills two fds we then own.
    assert_eq!(unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_CLOEXEC) }, 0);
    // SAFETY: both fds were just opened and are owned by nothing else.
    unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) }
}

impl Browser {
    fn launch(exe: &str, profile: &Path) -> Browser {
        use std::os::fd::AsRawFd;
        let (cmd_r, cmd_w) = pipe();
        let (ev_r, ev_w) = pipe();
        let (child_in, child_out) = (cmd_r.as_raw_fd(), ev_w.as_raw_fd());
        let mut command = Command::new(exe);
        command
            .args([
                "--headless",
                "--no-sandbox",
                // WebGL on the CPU (SwiftShader): no GPU on a CI machine.
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--hide-scrollbars",
                "--remote-debugging-pipe",
                "about:blank",
            ])
            .arg(format!("--window-size={},{}", DESKTOP.0, DESKTOP.1))
            .arg(format!("--user-data-dir={}", profile.display()))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(profile.with_extension("log")).map_or(Stdio::null(), Stdio::from));
        // SAFETY: only async-signal-safe calls (fcntl, dup2) between fork and exec.
        unsafe {
            command.pre_exec(move || {
                // Move both ends out of the way first (either may already be fd 3 or 4), then
                // place them; dup2 clears close-on-exec on the copies.
                let a = libc::fcntl(child_in, libc::F_DUPFD, 10);
                let b = libc::fcntl(child_out, libc::F_DUPFD, 10);
                if a < 0 || b < 0 || libc::dup2(a, 3) < 0 || libc::dup2(b, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = command.spawn().expect("spawn chromium");
        drop((cmd_r, ev_w));
        let (tx, from) = std::sync::mpsc::channel();
        let mut reader = std::fs::File::from(ev_r);
        std::thread::spawn(move || {
            let mut pending = Vec::new();
            let mut buf = [0u8; 65536];
            while let Ok(n) = reader.read(&mut buf) {
                if n == 0 {
                    break;
                }
                pending.extend_from_slice(&buf[..n]);
                while let Some(end) = pending.iter().position(|&b| b == 0) {
                    let msg: Vec<u8> = pending.drain(..=end).collect();
                    if let Ok(v) = serde_json::from_slice::<Value>(&msg[..end]) {
                        if tx.send(v).is_err() {
                            return;
                        }
                    }
                }
            }
        });
        Browser { child, to: std::fs::File::from(cmd_w), from, next_id: 0, session: None, events: Vec::new() }
    }

    /// Send a DevTools command (to the page once attached) and wait (bounded) for its result.
    fn call(&mut self, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = &self.session {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).expect("json");
        bytes.push(0);
        self.to.write_all(&bytes).expect("write to the browser");
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.from.recv_timeout(left) {
                Ok(v) if v["id"] == id => {
                    assert!(v.get("error").is_none(), "{method}: {v}");
                    return v["result"].clone();
                }
                Ok(v) => self.events.push(v),
                Err(RecvTimeoutError::Timeout) => panic!("no answer to {method} in 30 s"),
                Err(RecvTimeoutError::Disconnected) => panic!("the browser went away during {method}"),
            }
        }
    }

    /// Receive events for up to `d` without sending anything.
    fn pump(&mut self, d: Duration) {
        let deadline = Instant::now() + d;
        while let Ok(v) = self.from.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            self.events.push(v);
        }
    }

    /// Open `url` in a new page and attach to it with the domains the test reads enabled.
    fn open(&mut self, url: &str) {
        let target = self.call("Target.createTarget", json!({"url": "about:blank"}));
        let target = target["targetId"].as_str().expect("target").to_owned();
        let attached = self.call("Target.attachToTarget", json!({"targetId": target, "flatten": true}));
        self.session = Some(attached["sessionId"].as_str().expect("session").to_owned());
        for domain in ["Page.enable", "Runtime.enable", "Network.enable", "Log.enable"] {
            self.call(domain, json!({}));
        }
        self.viewport(DESKTOP);
        self.call("Page.navigate", json!({"url": url}));
    }

    fn viewport(&mut self, (w, h): (u32, u32)) {
        let mobile = w < 600;
        self.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": w, "height": h, "deviceScaleFactor": 1, "mobile": mobile}),
        );
    }

    /// Evaluate `js` in the page (awaiting a promise) and return its value, or the exception.
    fn try_eval(&mut self, js: &str) -> Result<Value, Value> {
        let r = self.call("Runtime.evaluate", json!({"expression": js, "returnByValue": true, "awaitPromise": true}));
        match r.get("exceptionDetails") {
            Some(e) => Err(e.clone()),
            None => Ok(r["result"]["value"].clone()),
        }
    }

    /// Evaluate `js` in the page (awaiting a promise) and return its value.
    fn eval(&mut self, js: &str) -> Value {
        self.try_eval(js).unwrap_or_else(|e| panic!("{js}: {e}"))
    }

    /// Poll `js` (every 50 ms, receiving events meanwhile) until it is truthy; panics after `limit`.
    fn wait_js(&mut self, what: &str, limit: Duration, js: &str) -> Value {
        let t = Instant::now();
        loop {
            // Before the page has loaded (or rendered the element) the expression may throw.
            let v = self.try_eval(js).unwrap_or(Value::Null);
            if !(v.is_null() || v == false || v == "" || v == 0) {
                return v;
            }
            assert!(t.elapsed() < limit, "timed out waiting for {what} ({js} = {v}); page: {}", self.page_text());
            self.pump(Duration::from_millis(50));
        }
    }

    fn page_text(&mut self) -> String {
        let r = self.call("Runtime.evaluate", json!({"expression": "document.body.innerText", "returnByValue": true}));
        r["result"]["value"].as_str().unwrap_or("").chars().take(3000).collect()
    }

    /// The element's box in viewport CSS pixels, after scrolling it to the middle of the window.
    fn rect(&mut self, selector: &str) -> (f64, f64, f64, f64) {
        let js = format!(
            "(() => {{ const e = document.querySelector({sel}); if (!e) return null; \
             e.scrollIntoView({{block: 'center', inline: 'center'}}); const r = e.getBoundingClientRect(); \
             return [r.x, r.y, r.width, r.height, e.disabled === true]; }})()",
            sel = json!(selector)
        );
        let v = self.eval(&js);
        let a =
            v.as_array().unwrap_or_else(|| panic!("no element {selector} on the page: {}", self.page_text())).clone();
        assert!(a[4] != true, "{selector} is disabled: {}", self.page_text());
        let f = |i: usize| a[i].as_f64().expect("number");
        (f(0), f(1), f(2), f(3))
    }

    fn mouse(&mut self, kind: &str, x: f64, y: f64, buttons: u32) {
        self.call(
            "Input.dispatchMouseEvent",
            json!({"type": kind, "x": x, "y": y, "button": if kind == "mouseMoved" && buttons == 0 { "none" } else { "left" },
                   "buttons": buttons, "clickCount": 1}),
        );
    }

    /// A real left click in the middle of the element.
    fn click(&mut self, selector: &str) {
        let (x, y, w, h) = self.rect(selector);
        let (cx, cy) = (x + w / 2.0, y + h / 2.0);
        self.mouse("mouseMoved", cx, cy, 0);
        self.mouse("mousePressed", cx, cy, 1);
        self.mouse("mouseReleased", cx, cy, 0);
    }

    /// A left-button drag across the element by `dx` pixels.
    fn drag(&mut self, selector: &str, dx: f64) {
        let (x, y, w, h) = self.rect(selector);
        let (cx, cy) = (x + w / 2.0, y + h / 2.0);
        self.mouse("mouseMoved", cx, cy, 0);
        self.mouse("mousePressed", cx, cy, 1);
        for k in 1..=10 {
            self.mouse("mouseMoved", cx + dx * f64::from(k) / 10.0, cy + 4.0 * f64::from(k), 1);
        }
        self.mouse("mouseReleased", cx + dx, cy + 40.0, 0);
    }

    fn set_value(&mut self, selector: &str, value: &str) {
        self.eval(&format!(
            "(() => {{ const e = document.querySelector({}); e.value = {}; e.dispatchEvent(new Event('change')); return true; }})()",
            json!(selector),
            json!(value)
        ));
    }

    /// A screenshot of the element (or the whole page), decoded.
    fn shot(&mut self, selector: Option<&str>) -> (RgbImage, Vec<u8>) {
        let params = match selector {
            Some(sel) => {
                let (x, y, w, h) = self.rect(sel);
                let scroll = self.eval("[window.scrollX, window.scrollY]");
                let (sx, sy) = (scroll[0].as_f64().unwrap_or(0.0), scroll[1].as_f64().unwrap_or(0.0));
                json!({"format": "png", "clip": {"x": x + sx, "y": y + sy, "width": w, "height": h, "scale": 1}})
            }
            None => json!({"format": "png", "captureBeyondViewport": true}),
        };
        let shot = self.call("Page.captureScreenshot", params);
        let png = base64_decode(shot["data"].as_str().expect("screenshot data"));
        (image::load_from_memory(&png).expect("screenshot PNG").to_rgb8(), png)
    }

    /// The network log so far: one entry per request.
    fn requests(&self) -> Vec<Req> {
        let mut out: Vec<Req> = Vec::new();
        for e in &self.events {
            let p = &e["params"];
            let id = p["requestId"].as_str().unwrap_or("");
            match e["method"].as_str() {
                Some("Network.requestWillBeSent") => out.push(Req {
                    id: id.to_owned(),
                    method: p["request"]["method"].as_str().unwrap_or("").to_owned(),
                    url: p["request"]["url"].as_str().unwrap_or("").to_owned(),
                    status: None,
                    failed: None,
                }),
                Some("Network.responseReceived") => {
                    if let Some(r) = out.iter_mut().rev().find(|r| r.id == id) {
                        r.status = p["response"]["status"].as_i64();
                    }
                }
                Some("Network.loadingFailed") if p["canceled"] != true => {
                    if let Some(r) = out.iter_mut().rev().find(|r| r.id == id) {
                        r.failed = Some(p["errorText"].as_str().unwrap_or("failed").to_owned());
                    }
                }
                _ => {}
            }
        }
        out
    }

    /// Wait until the page has sent `method` to a URL containing `path` (after `since` requests)
    /// and got an answer; returns its status.
    fn wait_request(&mut self, since: usize, method: &str, path: &str) -> i64 {
        let t = Instant::now();
        loop {
            let found = self.requests().into_iter().skip(since).find(|r| r.method == method && r.url.contains(path));
            if let Some(Req { status: Some(s), .. }) = found {
                return s;
            }
            assert!(
                t.elapsed() < Duration::from_secs(15),
                "the page sent no {method} {path} (or got no answer): {}",
                self.page_text()
            );
            self.pump(Duration::from_millis(30));
        }
    }

    /// Console errors and uncaught exceptions so far.
    fn errors(&self) -> Vec<String> {
        self.events
            .iter()
            .filter_map(|e| match e["method"].as_str() {
                Some("Runtime.consoleAPICalled") if e["params"]["type"] == "error" => {
                    Some(format!("console.error {}", e["params"]["args"]))
                }
                Some("Runtime.exceptionThrown") => Some(format!("exception {}", e["params"]["exceptionDetails"])),
                Some("Log.entryAdded") if e["params"]["entry"]["level"] == "error" => {
                    Some(format!("log {}", e["params"]["entry"]["text"]))
                }
                _ => None,
            })
            .collect()
    }
}

/// One request the page made.
#[derive(Debug, Clone)]
struct Req {
    id: String,
    method: String,
    url: String,
    status: Option<i64>,
    failed: Option<String>,
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        _ => 63,
    };
    let clean: Vec<u8> = s.bytes().filter(|&c| c != b'=' && !c.is_ascii_whitespace()).collect();
    let mut out = Vec::with_capacity(clean.len() * 3 / 4);
    for chunk in clean.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= u32::from(val(c)) << (18 - 6 * i);
        }
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    out
}

/// Pixels that are not the viewer's background (the grid, the axis and the model).
fn ink(img: &RgbImage) -> usize {
    img.pixels().filter(|p| p.0.iter().zip(BACKGROUND).map(|(&a, b)| a.abs_diff(b) as u32).sum::<u32>() > 40).count()
}

/// Pixels that differ between two same-sized pictures.
fn differing(a: &RgbImage, b: &RgbImage) -> usize {
    assert_eq!(a.dimensions(), b.dimensions(), "screenshots of one canvas");
    a.pixels().zip(b.pixels()).filter(|(p, q)| p.0.iter().zip(q.0).any(|(&x, y)| x.abs_diff(y) > 24)).count()
}

/// Where `SCANRIG_SCREENSHOTS` asks for the page's pictures, if it does.
fn screenshot_dir() -> Option<PathBuf> {
    std::env::var_os("SCANRIG_SCREENSHOTS").map(PathBuf::from)
}

/// Full-page screenshots at desktop and phone width (saved when asked); checks the page fits the
/// phone's width (nothing scrolls sideways).
fn page_shots(b: &mut Browser, name: &str) {
    let (desktop, png) = b.shot(None);
    let colours: std::collections::HashSet<[u8; 3]> = desktop.pixels().map(|p| p.0).collect();
    assert!(desktop.width() >= DESKTOP.0 && colours.len() > 50, "{name}: blank page ({} colours)", colours.len());
    if let Some(dir) = screenshot_dir() {
        std::fs::write(dir.join(format!("console-{name}-desktop.png")), png).expect("write screenshot");
    }
    b.viewport(PHONE);
    b.pump(Duration::from_millis(300));
    let wide = b.eval("document.documentElement.scrollWidth");
    assert!(wide.as_u64().unwrap_or(9999) <= u64::from(PHONE.0), "{name}: the page is {wide} px wide on a phone");
    if let Some(dir) = screenshot_dir() {
        let (_, png) = b.shot(None);
        std::fs::write(dir.join(format!("console-{name}-phone.png")), png).expect("write screenshot");
    }
    b.viewport(DESKTOP);
    b.pump(Duration::from_millis(300));
}

/// Whether the page shows the paused scan and the newest live estimate it was told about.
const SETTLED: &str = "(() => { const l = window.scanrig.live; return l.renders >= 1 && !l.fetching && !l.dirty && l.shown && l.event && l.shown.version === l.event.version && document.getElementById('msg').textContent.startsWith('Paused'); })()";

/// Wait until the page shows the pause and the newest estimate the daemon has for scan `id` (its
/// `x-model-version`): progress and model events reach the page on one stream but from two
/// sources, so "paused" can arrive before the last estimate does.
fn settle(b: &mut Browser, c: &scanrig::service::client::Client, id: &str) {
    let r = c.raw("GET", &format!("/api/v1/scans/{id}/live.ply"), None).expect("live model");
    assert_eq!(r.status, 200, "no live model for the paused scan");
    let version: u64 = r.header("x-model-version").and_then(|v| v.parse().ok()).expect("x-model-version");
    b.wait_js(
        &format!("the page to show the pause and estimate version {version}"),
        Duration::from_secs(20),
        &format!("{SETTLED} && window.scanrig.live.shown.version === {version}"),
    );
}

/// The viewer's model, as the page describes it.
const VIEWER_INFO: &str = "JSON.stringify(window.scanrig && document.getElementById('view') && \
     (() => { const v = document.getElementById('size').textContent; return { size: v, title: document.getElementById('viewer-title').textContent }; })())";

#[test]
fn the_console_drives_the_rig_and_shows_live_and_final_models_in_headless_chromium() {
    let Some(exe) = find_chromium() else {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must run this test, but no chromium found (apt-get install chromium)"
        );
        eprintln!("skipped: no chromium found (apt-get install chromium)");
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[("positions = 24", "positions = 8"), ("resolution = 128", "resolution = 40")],
    );
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    let t0 = Instant::now();
    let mut b = Browser::launch(&exe, &dir.path().join("profile"));
    b.open(&format!("http://{}/", d.addr));

    // Idle: the page knows the rig, its devices and methods; the camera streams; the viewer is
    // empty (grid and axis only).
    b.wait_js("the method list", Duration::from_secs(20), "document.getElementById('method').options.length === 7");
    b.wait_js("the devices", Duration::from_secs(10), "document.getElementById('devices').rows.length >= 4");
    let rig_line = b.eval("document.getElementById('rig').textContent");
    assert!(rig_line.as_str().is_some_and(|r| r.contains("simulated")), "{rig_line}");
    let offered = b.eval("[...document.getElementById('method').options].every(o => !o.disabled)");
    assert_eq!(offered, true, "every method runs on the simulated rig");
    b.wait_js("camera frames", Duration::from_secs(15), "document.getElementById('camera').naturalWidth");
    assert_eq!(b.eval("document.getElementById('camera').naturalWidth"), 640);
    let info = b.wait_js("the camera figures", Duration::from_secs(10), "document.getElementById('camera-info').textContent.includes('640 × 480') && document.getElementById('camera-info').textContent");
    eprintln!("camera: {info}");
    b.pump(Duration::from_millis(300));
    let (empty, _) = b.shot(Some("#view"));
    let grid_ink = ink(&empty);
    assert!(grid_ink > 500, "the grid is drawn: {grid_ink} pixels");
    page_shots(&mut b, "idle");

    eprintln!("{:.1} s: idle page checked", t0.elapsed().as_secs_f64());
    // Manual control: every button, each answered 200 and doing what it says.
    let n = b.requests().len();
    b.set_value("#turn-deg", "30");
    b.click("#turn");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/control/turntable"), 200);
    let angle =
        |c: &scanrig::service::client::Client| c.get_json("/api/v1/control").expect("control")["angle_deg"].as_f64();
    assert!(angle(&c).is_some_and(|a| (a - 30.0).abs() < 0.5), "{:?}", angle(&c));
    let n = b.requests().len();
    b.click("#home");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/control/turntable"), 200);
    assert!(angle(&c).is_some_and(|a| a.abs() < 0.5), "{:?}", angle(&c));
    for (what, path) in [("light", "/api/v1/control/light"), ("laser", "/api/v1/control/laser")] {
        let before = c.get_json("/api/v1/control").expect("control")[format!("{what}s")][0].as_bool();
        let n = b.requests().len();
        b.click(&format!("#{what}-0"));
        assert_eq!(b.wait_request(n, "POST", path), 200);
        let after = c.get_json("/api/v1/control").expect("control")[format!("{what}s")][0].as_bool();
        assert_eq!(after, before.map(|x| !x), "{what} 1 toggled");
        b.wait_js(
            "the toggle to show its state",
            Duration::from_secs(5),
            &format!("document.getElementById('{what}-0').getAttribute('aria-pressed') === '{}'", after == Some(true)),
        );
    }
    for (button, expect) in [("#show-pattern", "checker"), ("#show-colour", "colour #ff8000"), ("#blank", "blank")] {
        let n = b.requests().len();
        b.click(button);
        assert_eq!(b.wait_request(n, "POST", "/api/v1/control/projector"), 200);
        assert_eq!(c.get_json("/api/v1/control").expect("control")["projector"], expect, "{button}");
    }
    let n = b.requests().len();
    let reconnects = |c: &scanrig::service::client::Client| {
        c.get_json("/api/v1/devices").expect("devices")["devices"]
            .as_array()
            .and_then(|a| a.iter().find(|d| d["name"] == "turntable").map(|d| d["reconnects"].as_u64().unwrap_or(0)))
            .unwrap_or(0)
    };
    let before = reconnects(&c);
    b.click("#reconnect-turntable");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/devices/turntable/reconnect"), 202);
    wait_for("the turntable to reconnect", Duration::from_secs(10), || reconnects(&c) > before);
    b.wait_js(
        "the devices table to show the reconnect (SSE devices)",
        Duration::from_secs(10),
        &format!(
            "document.querySelector('#reconnect-turntable').closest('tr').cells[3].textContent === '{}'",
            reconnects(&c)
        ),
    );

    eprintln!("{:.1} s: manual control and reconnect checked", t0.elapsed().as_secs_f64());
    // A scan from the page: the live estimate is drawn while it runs and tightens view by view.
    b.eval("document.getElementById('method').value = 'space-carving'; true");
    // 24 views: time to pause it twice between views.
    b.set_value("#positions", "24");
    b.set_value("#resolution", "40");
    let n = b.requests().len();
    b.click("#start");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/scans"), 202);
    let id = c.get_json("/api/v1/scans").expect("list")["scans"][0]["id"].as_str().expect("id").to_owned();
    // Paused from what the daemon says (the page may lag behind a fast scan), then the page must
    // catch up with the newest estimate it was told about.
    let step = |c: &scanrig::service::client::Client| {
        c.get_json("/api/v1/status").expect("status")["progress"]["step"].as_u64().unwrap_or(0)
    };
    wait_for("two views", Duration::from_secs(30), || step(&c) >= 2);
    b.click("#pause");
    b.wait_request(n, "POST", &format!("/api/v1/scans/{id}/pause"));
    wait_for("the scan to pause", Duration::from_secs(30), || scan_meta(&c, &id)["status"] != "running");
    assert_eq!(scan_meta(&c, &id)["status"], "paused");
    settle(&mut b, &c, &id);
    let early = b.eval("JSON.stringify(window.scanrig.live.shown)");
    let early_size = b.eval(VIEWER_INFO);
    let (shot_a, _) = b.shot(Some("#view"));
    page_shots(&mut b, "midscan");
    let n = b.requests().len();
    b.click("#resume");
    assert_eq!(b.wait_request(n, "POST", &format!("/api/v1/scans/{id}/resume")), 202);
    let paused_at = step(&c);
    wait_for("three more views", Duration::from_secs(30), || step(&c) >= paused_at + 3);
    b.click("#pause");
    wait_for("the scan to pause again", Duration::from_secs(30), || scan_meta(&c, &id)["status"] != "running");
    settle(&mut b, &c, &id);
    let later = b.eval("JSON.stringify(window.scanrig.live.shown)");
    let later_size = b.eval(VIEWER_INFO);
    let (shot_b, _) = b.shot(Some("#view"));
    let position =
        |v: &Value| serde_json::from_str::<Value>(v.as_str().unwrap_or("{}")).unwrap_or_default()["position"].as_u64();
    assert!(position(&later) > position(&early), "the later estimate has more views: {early} -> {later}");
    let changed = differing(&shot_a, &shot_b);
    eprintln!("live estimate: {early} {early_size} -> {later} {later_size}; {changed} pixels changed");
    assert!(changed > 300, "the live view did not change between views: {changed} pixels");
    let n = b.requests().len();
    b.click("#resume");
    assert_eq!(b.wait_request(n, "POST", &format!("/api/v1/scans/{id}/resume")), 202);
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");

    eprintln!("{:.1} s: scan with live view done", t0.elapsed().as_secs_f64());
    // The result: the mesh replaces the estimate; an orbit drag and the arrow keys turn it.
    b.wait_js(
        "the mesh in the viewer",
        Duration::from_secs(20),
        &format!("window.scanrig.shownScan === '{id}' && document.getElementById('viewer-title').textContent.endsWith(': mesh')"),
    );
    b.pump(Duration::from_millis(200));
    let (mesh, _) = b.shot(Some("#view"));
    let mesh_ink = ink(&mesh);
    assert!(mesh_ink > grid_ink + 5000, "the mesh is drawn: {mesh_ink} pixels against {grid_ink} for the grid alone");
    let size = b.eval("document.getElementById('size').textContent");
    assert!(size.as_str().is_some_and(|s| s.contains(" mm ")), "{size}");
    eprintln!("{:.1} s: mesh shown", t0.elapsed().as_secs_f64());
    b.drag("#view", 160.0);
    b.pump(Duration::from_millis(200));
    let (turned, _) = b.shot(Some("#view"));
    let moved = differing(&mesh, &turned);
    assert!(moved > 2000, "the orbit drag changed {moved} pixels");
    b.eval("document.getElementById('view').focus(); true");
    b.call(
        "Input.dispatchKeyEvent",
        json!({"type": "keyDown", "key": "ArrowLeft", "code": "ArrowLeft", "windowsVirtualKeyCode": 37}),
    );
    b.call(
        "Input.dispatchKeyEvent",
        json!({"type": "keyUp", "key": "ArrowLeft", "code": "ArrowLeft", "windowsVirtualKeyCode": 37}),
    );
    b.pump(Duration::from_millis(200));
    let (keyed, _) = b.shot(Some("#view"));
    assert!(differing(&turned, &keyed) > 1000, "the arrow key did not orbit");
    eprintln!("{:.1} s: orbit and keys checked", t0.elapsed().as_secs_f64());
    for kind in ["points", "voxels", "mesh"] {
        b.click(&format!("input[name=kind][value={kind}]"));
        b.wait_js(
            &format!("the {kind} view"),
            Duration::from_secs(20),
            &format!(
                "document.getElementById('size').textContent.includes('{}')",
                if kind == "mesh" { "vertices" } else { kind }
            ),
        );
    }
    eprintln!("{:.1} s: views switched", t0.elapsed().as_secs_f64());
    b.click("#wireframe");
    b.click("#lighting");
    b.pump(Duration::from_millis(200));
    let (wire, _) = b.shot(Some("#view"));
    assert!(differing(&keyed, &wire) > 1000, "wireframe and unlit look like the lit solid");
    b.click("#wireframe");
    b.click("#lighting");
    b.eval("document.getElementById('reset-view').click(); true");
    b.pump(Duration::from_millis(300));
    eprintln!("{:.1} s: wireframe checked", t0.elapsed().as_secs_f64());
    page_shots(&mut b, "result");

    eprintln!("{:.1} s: viewer checked", t0.elapsed().as_secs_f64());
    // History: the card has a thumbnail, figures and downloads that answer 200.
    let card = format!("[data-scan=\"{id}\"]");
    b.wait_js(
        "the thumbnail",
        Duration::from_secs(10),
        &format!(
            "document.querySelector('{card} img.thumb') && document.querySelector('{card} img.thumb').naturalWidth"
        ),
    );
    let figures = b.wait_js(
        "the figures",
        Duration::from_secs(10),
        &format!("document.querySelector('{card} .figures').textContent"),
    );
    assert!(figures.as_str().is_some_and(|f| f.contains("24 views")), "{figures}");
    let downloads = b.eval(&format!(
        "Promise.all([...document.querySelectorAll('{card} a[download]')].map(a => fetch(a.href).then(async r => \
         [a.textContent, r.status, new Uint8Array(await r.arrayBuffer()).slice(0, 4).join(',')])))"
    ));
    let downloads = downloads.as_array().expect("downloads").clone();
    let labels: Vec<&str> = downloads.iter().filter_map(|d| d[0].as_str()).collect();
    assert_eq!(labels, ["PLY", "STL", "OBJ", "everything (zip)"], "{downloads:?}");
    assert!(downloads.iter().all(|d| d[1] == 200), "{downloads:?}");
    assert_eq!(downloads[3][2], "80,75,3,4", "the archive is a zip: {downloads:?}");

    eprintln!("{:.1} s: downloads checked", t0.elapsed().as_secs_f64());
    // Reprocess from the card with another resolution.
    b.click(&format!("{card} summary"));
    b.set_value(&format!("#rp-{id}-resolution"), "32");
    let n = b.requests().len();
    b.click(&format!("{card} .do-reprocess"));
    assert_eq!(b.wait_request(n, "POST", &format!("/api/v1/scans/{id}/reprocess")), 202);
    let mut again = String::new();
    wait_for("the reprocess scan", Duration::from_secs(10), || {
        let list = c.get_json("/api/v1/scans").expect("list");
        again = list["scans"]
            .as_array()
            .and_then(|a| a.iter().find(|s| s["reprocess_of"] == id.as_str()))
            .and_then(|s| s["id"].as_str())
            .unwrap_or("")
            .to_owned();
        !again.is_empty()
    });
    let done = wait_finished(&c, &again, Duration::from_secs(60));
    assert_eq!((done["status"].as_str(), done["resolution"].as_u64()), (Some("complete"), Some(32)), "{done}");

    // Cancel a scan, then delete it with the confirmation accepted: gone from the list and disk.
    eprintln!("{:.1} s: reprocessed", t0.elapsed().as_secs_f64());
    b.wait_js("the start button back", Duration::from_secs(20), "!document.getElementById('start').disabled");
    // Long enough to be cancelled while it runs.
    b.set_value("#positions", "120");
    b.set_value("#resolution", "24");
    let n = b.requests().len();
    b.click("#start");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/scans"), 202);
    b.wait_js(
        "the scan to run",
        Duration::from_secs(20),
        "window.scanrig.running && !document.getElementById('cancel').disabled",
    );
    assert_eq!(b.eval("document.getElementById('control-set').disabled"), true, "manual control is off during a scan");
    let doomed = b.eval("window.scanrig.progress.scan_id").as_str().expect("running id").to_owned();
    // A control pressed as the scan starts (forced here: the page disables them) is refused in words.
    let m = b.requests().len();
    b.eval("document.getElementById('control-set').disabled = false; document.getElementById('home').click(); true");
    assert_eq!(b.wait_request(m, "POST", "/api/v1/control/turntable"), 409);
    let refusal =
        b.wait_js("the refusal", Duration::from_secs(5), "document.getElementById('control-msg').textContent");
    assert!(refusal.as_str().is_some_and(|r| r.starts_with("Refused: a scan is running")), "{refusal}");
    let refused_from = m;
    b.click("#cancel");
    assert_eq!(b.wait_request(n, "POST", &format!("/api/v1/scans/{doomed}/cancel")), 200);
    assert_eq!(wait_finished(&c, &doomed, Duration::from_secs(30))["status"], "cancelled");
    assert!(dir.path().join("scans").join(&doomed).exists());
    let gone = format!("[data-scan=\"{doomed}\"]");
    b.wait_js(
        "the cancelled scan's card",
        Duration::from_secs(10),
        &format!("document.querySelector('{gone} .delete') && !document.querySelector('{gone} .delete').disabled"),
    );
    let n = b.requests().len();
    // Clicked from a timer: the confirm dialog blocks the page until it is answered.
    b.rect(&format!("{gone} .delete"));
    b.eval(&format!("setTimeout(() => document.querySelector('{gone} .delete').click(), 0); true"));
    let t = Instant::now();
    let dialog = loop {
        if let Some(e) = b.events.iter().find(|e| e["method"] == "Page.javascriptDialogOpening") {
            break e["params"].clone();
        }
        assert!(t.elapsed() < Duration::from_secs(10), "no confirmation dialog");
        b.pump(Duration::from_millis(30));
    };
    assert_eq!(dialog["type"], "confirm");
    assert!(dialog["message"].as_str().is_some_and(|m| m.contains(&doomed)), "{dialog}");
    b.call("Page.handleJavaScriptDialog", json!({"accept": true}));
    assert_eq!(b.wait_request(n, "DELETE", &format!("/api/v1/scans/{doomed}")), 204);
    b.wait_js("the card to go", Duration::from_secs(10), &format!("!document.querySelector('{gone}')"));
    assert!(!dir.path().join("scans").join(&doomed).exists(), "the scan directory is still on disk");
    let listed = c.get_json("/api/v1/scans").expect("list");
    assert!(!listed.to_string().contains(&doomed), "{listed}");

    // No request failed and nothing logged an error, over the whole session (but the refusal
    // provoked above, which the browser logs as a failed load).
    let failed: Vec<Req> = b
        .requests()
        .into_iter()
        .enumerate()
        .filter(|(i, r)| !(*i >= refused_from && r.url.ends_with("/control/turntable") && r.status == Some(409)))
        .map(|(_, r)| r)
        .filter(|r| r.failed.is_some() || r.status.is_some_and(|s| s >= 400))
        .collect();
    assert!(failed.is_empty(), "failed requests: {failed:#?}");
    let errors: Vec<String> = b.errors().into_iter().filter(|e| !e.contains("status of 409 (Conflict)")).collect();
    assert!(errors.is_empty(), "console errors: {errors:#?}");
    let external: Vec<Req> = b
        .requests()
        .into_iter()
        .filter(|r| !r.url.starts_with(&format!("http://{}/", d.addr)) && !r.url.starts_with("data:"))
        .collect();
    assert!(external.is_empty(), "requests off the daemon: {external:#?}");
    eprintln!(
        "{} requests, no error; mesh {mesh_ink} px, grid {grid_ink} px, drag moved {moved} px",
        b.requests().len()
    );
}

#[test]
fn static_files_are_served_from_the_binary_and_nothing_else() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(dir.path(), "simulated.toml", &[]);
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    let three = c.request("GET", "/web/vendor/three/build/three.module.js", None).expect("three.js");
    assert_eq!(three.status, 200);
    assert_eq!(three.header("content-type"), Some("text/javascript; charset=utf-8"));
    let licence = c.request("GET", "/web/vendor/three/LICENSE", None).expect("licence");
    assert!(String::from_utf8_lossy(&licence.body).contains("MIT"));
    let page = c.request("GET", "/", None).expect("page");
    assert!(String::from_utf8_lossy(&page.body).contains("/web/app.js"));
    for bad in [
        "/web/",
        "/web/nope.js",
        "/web/../Cargo.toml",
        "/web/%2e%2e/Cargo.toml",
        "/web/vendor/../app.js",
        "/web/app.js/",
    ] {
        let r = c.raw("GET", bad, None).expect("answer");
        assert_eq!(r.status, 404, "{bad}");
    }
}

#[test]
fn with_a_token_the_page_asks_for_it_once_and_its_session_carries_events_camera_and_models() {
    let Some(exe) = find_chromium() else {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI must run this test, but no chromium found (apt-get install chromium)"
        );
        eprintln!("skipped: no chromium found (apt-get install chromium)");
        return;
    };
    const TOKEN: &str = "console-token-5f0c2e9a81";
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[("positions = 24", "positions = 6"), ("resolution = 128", "resolution = 32")],
    );
    let d = daemon_common::spawn_with(&rig, dir.path(), dir.path(), &[], &[("SCANRIGD_TOKEN", TOKEN)]);
    let c = scanrig::service::client::Client::new(&d.addr, Some(TOKEN.into()))
        .expect("client")
        .with_timeout(Duration::from_secs(30));
    let mut b = Browser::launch(&exe, &dir.path().join("profile"));
    b.open(&format!("http://{}/", d.addr));

    // Before signing in the page shows only the sign-in form and asks for nothing it would be
    // refused (no camera stream, no event stream).
    b.wait_js(
        "the sign-in form",
        Duration::from_secs(20),
        "!document.getElementById('sign-in').hidden && document.getElementById('console').hidden",
    );
    b.pump(Duration::from_millis(500));
    let base = format!("http://{}", d.addr);
    for r in b.requests() {
        let path = r.url.strip_prefix(&base).unwrap_or(&r.url).to_owned();
        assert!(path == "/" || path.starts_with("/web/") || path == "/api/v1/session", "asked before sign-in: {r:?}");
        assert!(r.failed.is_none() && r.status.is_some_and(|s| s < 400), "{r:?}");
    }
    assert_eq!(b.eval("document.getElementById('camera').getAttribute('src')"), Value::Null);
    page_shots(&mut b, "sign-in");

    // A wrong token is refused in words and gives no session.
    let n = b.requests().len();
    b.set_value("#sign-in-token", "console-token-5f0c2e9a8");
    b.click("#sign-in-go");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/session"), 401);
    b.wait_js(
        "the refusal in words",
        Duration::from_secs(5),
        "document.getElementById('sign-in-msg').textContent.includes(\"not this daemon's access token\")",
    );
    assert_eq!(b.eval("fetch('/api/v1/status').then(r => r.status)"), 401);

    // The right one: the console comes up and every live part works through the cookie alone.
    let n = b.requests().len();
    b.set_value("#sign-in-token", TOKEN);
    b.click("#sign-in-go");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/session"), 200);
    b.wait_js("the method list", Duration::from_secs(20), "document.getElementById('method').options.length === 7");
    assert_eq!(
        b.eval("document.getElementById('sign-in').hidden && !document.getElementById('sign-out').hidden"),
        true
    );
    assert_eq!(b.eval("document.cookie.includes('scanrig_session')"), false, "the session cookie is HttpOnly");
    b.wait_js("camera frames", Duration::from_secs(15), "document.getElementById('camera').naturalWidth === 640");
    let n = b.requests().len();
    b.set_value("#method", "space-carving");
    b.click("#start");
    assert_eq!(b.wait_request(n, "POST", "/api/v1/scans"), 202);
    // Progress and the live estimate reach the page over the event stream, and the estimate's
    // PLY is fetched with the cookie.
    b.wait_js(
        "progress over the event stream",
        Duration::from_secs(60),
        "window.scanrig.progress && window.scanrig.progress.step > 0",
    );
    b.wait_js("a live estimate drawn", Duration::from_secs(60), "window.scanrig.live.renders > 0");
    let id = b.eval("window.scanrig.progress.scan_id").as_str().expect("scan id").to_owned();
    let done = wait_finished(&c, &id, Duration::from_secs(120));
    assert_eq!(done["status"], "complete", "{done}");
    b.wait_js(
        "the finished scan on the page",
        Duration::from_secs(30),
        &format!("document.querySelector('[data-scan=\"{id}\"]') && window.scanrig.progress.status === 'complete'"),
    );
    // The finished scan's mesh is opened in the viewer, also through the cookie.
    assert_eq!(b.wait_request(0, "GET", &format!("/api/v1/scans/{id}/model.ply")), 200);
    let events = b.requests().into_iter().find(|r| r.url.ends_with("/api/v1/events")).expect("an event stream");
    assert_eq!(events.status, Some(200), "{events:?}");

    // Signing out ends the session for this browser: the page asks again and the cookie is dead.
    let n = b.requests().len();
    b.click("#sign-out");
    assert_eq!(b.wait_request(n, "DELETE", "/api/v1/session"), 200);
    b.wait_js("the sign-in form again", Duration::from_secs(20), "!document.getElementById('sign-in').hidden");
    assert_eq!(b.eval("fetch('/api/v1/status').then(r => r.status)"), 401);

    let unexpected: Vec<Req> = b
        .requests()
        .into_iter()
        .filter(|r| r.failed.is_some() || r.status.is_some_and(|s| s >= 400))
        .filter(|r| !(r.url.ends_with("/api/v1/session") && r.status == Some(401)))
        .filter(|r| !(r.url.ends_with("/api/v1/status") && r.status == Some(401)))
        .collect();
    assert!(unexpected.is_empty(), "failed requests: {unexpected:#?}");
    let errors: Vec<String> = b.errors().into_iter().filter(|e| !e.contains("status of 401 (Unauthorized)")).collect();
    assert!(errors.is_empty(), "console errors: {errors:#?}");
}
