//! The web page in headless Chromium against a real `scanrigd` on 127.0.0.1, driven over the
//! DevTools protocol on a pipe (no extra crates, no network port for the browser). After a scan
//! the page must show the rig, the devices, the finished progress, a camera preview and a drawn
//! 3D view. Skips with a printed reason when Chromium is not installed. Every wait is bounded.

mod daemon_common;

use std::io::{Read, Write};
use std::os::fd::{FromRawFd, OwnedFd};
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use daemon_common::{client, rig_from, spawn, wait_finished, wait_for};
use serde_json::{json, Value};

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

/// A headless browser with its DevTools pipe (fd 3 in, fd 4 out in the child).
struct Browser {
    child: Child,
    to: std::fs::File,
    from: Receiver<Value>,
    next_id: u64,
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
    fn launch(exe: &str, profile: &std::path::Path) -> Browser {
        use std::os::fd::AsRawFd;
        let (cmd_r, cmd_w) = pipe();
        let (ev_r, ev_w) = pipe();
        let (child_in, child_out) = (cmd_r.as_raw_fd(), ev_w.as_raw_fd());
        let mut command = Command::new(exe);
        command
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--window-size=1000,760",
                "--remote-debugging-pipe",
                "about:blank",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(profile.with_extension("log")).map_or(Stdio::null(), Stdio::from));
        // SAFETY: only async-signal-safe calls (dup2) between fork and exec.
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
        Browser { child, to: std::fs::File::from(cmd_w), from, next_id: 0 }
    }

    /// Send a DevTools command and wait (bounded) for its result.
    fn call(&mut self, session: Option<&str>, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).expect("json");
        bytes.push(0);
        self.to.write_all(&bytes).expect("write to the browser");
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.from.recv_timeout(left) {
                Ok(v) if v["id"] == id => {
                    assert!(v.get("error").is_none(), "{method}: {v}");
                    return v["result"].clone();
                }
                Ok(_) => {}
                Err(RecvTimeoutError::Timeout) => panic!("no answer to {method} in 20 s"),
                Err(RecvTimeoutError::Disconnected) => panic!("the browser went away during {method}"),
            }
        }
    }
}

/// What the page shows, read in the page.
const PAGE_STATE: &str = r#"(() => {
  const q = (id) => document.getElementById(id);
  const ink = (el, w, h) => {
    const c = document.createElement("canvas"); c.width = w; c.height = h;
    const x = c.getContext("2d"); x.drawImage(el, 0, 0, w, h);
    const d = x.getImageData(0, 0, w, h).data; let lit = 0, grey = 0;
    for (let i = 0; i < d.length; i += 4) {
      if (d[i] > 30 || d[i + 1] > 30 || d[i + 2] > 30) lit++;
      if (d[i] < 240 && d[i] === d[i + 1] && d[i + 1] === d[i + 2]) grey++;
    }
    return { lit, grey };
  };
  const img = q("preview"), view = q("view");
  return JSON.stringify({
    rig: q("rig").textContent, devices: q("devices").textContent, msg: q("msg").textContent,
    fill: q("fill").style.width,
    preview_w: img.complete ? img.naturalWidth : 0,
    preview: img.complete && img.naturalWidth ? ink(img, 160, 120) : null,
    view: ink(view, view.width, view.height),
  });
})()"#;

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

#[test]
fn the_web_page_shows_status_progress_preview_and_the_model_in_headless_chromium() {
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
    let id = c.post_json("/api/v1/scans", &json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(30))["status"], "complete");

    let profile = dir.path().join("profile");
    let mut b = Browser::launch(&exe, &profile);
    let target = b.call(None, "Target.createTarget", json!({"url": format!("http://{}/", d.addr)}));
    let target = target["targetId"].as_str().expect("target").to_owned();
    let attached = b.call(None, "Target.attachToTarget", json!({"targetId": target, "flatten": true}));
    let session = attached["sessionId"].as_str().expect("session").to_owned();

    let mut state = Value::Null;
    wait_for("the page to show the scan", Duration::from_secs(20), || {
        let r = b.call(Some(&session), "Runtime.evaluate", json!({"expression": PAGE_STATE, "returnByValue": true}));
        state = r["result"]["value"].as_str().and_then(|s| serde_json::from_str(s).ok()).unwrap_or(Value::Null);
        state["preview_w"].as_u64().unwrap_or(0) > 0 && state["view"]["grey"].as_u64().unwrap_or(0) > 500
    });
    assert!(state["rig"].as_str().is_some_and(|r| r.contains("rig simulated")), "{state}");
    let devices = state["devices"].as_str().unwrap_or("");
    assert!(devices.contains("turntable") && devices.contains("camera") && devices.contains("connected"), "{state}");
    assert!(state["msg"].as_str().is_some_and(|m| m.starts_with("complete")), "{state}");
    assert_eq!(state["fill"], "100%");
    assert_eq!(state["preview_w"], 640);
    // The preview is a camera frame with the lit object in it, not a blank image.
    assert!(state["preview"]["lit"].as_u64().unwrap_or(0) > 200, "{state}");
    // The 3D view has shaded triangles on it.
    assert!(state["view"]["grey"].as_u64().unwrap_or(0) > 500, "{state}");

    let shot = b.call(Some(&session), "Page.captureScreenshot", json!({"format": "png"}));
    let png = base64_decode(shot["data"].as_str().expect("screenshot data"));
    let img = image::load_from_memory(&png).expect("screenshot PNG").to_rgb8();
    let distinct: std::collections::HashSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    assert!(img.width() >= 800 && distinct.len() > 50, "blank screenshot: {} colours", distinct.len());
    if let Some(path) = std::env::var_os("SCANRIG_SCREENSHOT") {
        std::fs::write(path, &png).expect("write screenshot");
    }
    eprintln!("page state: {state}; screenshot {}x{}, {} colours", img.width(), img.height(), distinct.len());

    // The method choice: every method this rig can run is offered, and the one chosen is scanned.
    let eval = |b: &mut Browser, js: &str| -> Value {
        let r = b.call(Some(&session), "Runtime.evaluate", json!({"expression": js, "returnByValue": true}));
        r["result"]["value"].clone()
    };
    let mut offered = Value::Null;
    wait_for("the method list", Duration::from_secs(10), || {
        offered = eval(
            &mut b,
            "JSON.stringify([...document.getElementById('method').options].map(o => [o.value, o.disabled]))",
        );
        offered.as_str().is_some_and(|s| s.contains("laser"))
    });
    let offered: Vec<(String, bool)> = serde_json::from_str(offered.as_str().unwrap_or("[]")).expect("options");
    assert_eq!(offered.len(), 7, "{offered:?}");
    assert!(offered.iter().all(|(_, disabled)| !disabled), "every method runs on this rig: {offered:?}");
    eval(
        &mut b,
        "document.getElementById('method').value = 'depth-fusion'; \
         document.getElementById('positions').value = '6'; \
         document.getElementById('start').click(); 'clicked'",
    );
    let mut latest = Value::Null;
    wait_for("the scan started from the page", Duration::from_secs(20), || {
        let scans = c.get_json("/api/v1/scans").expect("list");
        latest = scans["scans"]
            .as_array()
            .and_then(|a| a.iter().find(|s| s["id"] != id.as_str()).cloned())
            .unwrap_or(Value::Null);
        !latest.is_null()
    });
    assert_eq!(latest["method"], "depth-fusion", "{latest}");
    assert_eq!(latest["positions"], 6, "{latest}");
    let new_id = latest["id"].as_str().expect("id").to_owned();
    assert_eq!(wait_finished(&c, &new_id, Duration::from_secs(60))["status"], "complete");
}
