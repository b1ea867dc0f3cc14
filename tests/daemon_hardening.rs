//! Faults a rig box meets, against the real `scanrigd` binary on 127.0.0.1: a second daemon on one
//! state directory, half-sent requests at SIGTERM, previews flooding the device thread, slow
//! downloads of big files, malformed requests, and kill -9 with a paused scan and partial writes.
//! Every wait is bounded; nothing is checked against wall-clock time.

mod daemon_common;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use daemon_common::{client, device_states, frames_on_disk, rig_from, scan_meta, spawn, wait_finished, wait_for};

/// The simulated rig, small (8 positions, a coarse grid); `real_time` makes the turntable take
/// its real time per move, so a scan runs long enough to act on it.
fn small_sim(dir: &Path, real_time: bool) -> PathBuf {
    let rt = if real_time { "real_time = true" } else { "real_time = false" };
    rig_from(
        dir,
        "simulated.toml",
        &[("positions = 24", "positions = 8"), ("resolution = 128", "resolution = 40"), ("real_time = false", rt)],
    )
}

fn start(c: &scanrig::service::client::Client) -> String {
    c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned()
}

/// Wait (bounded) for a child to exit.
fn wait_exit(child: &mut std::process::Child, limit: Duration) -> Option<std::process::ExitStatus> {
    let t = Instant::now();
    while t.elapsed() < limit {
        if let Some(s) = child.try_wait().expect("try_wait") {
            return Some(s);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    None
}

/// Send `request` on a fresh connection and read the whole answer (the server closes it or sends
/// Content-Length bytes). Returns (status, lowercased head, body).
fn raw_http(addr: &str, request: &[u8]) -> (u16, String, Vec<u8>) {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(20))).expect("timeout");
    // The server may answer (and close) before it has read everything: ignore write errors.
    let _ = s.write_all(request);
    let mut buf = Vec::new();
    let mut chunk = [0u8; 8192];
    loop {
        match s.read(&mut chunk) {
            Ok(0) => break,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset && !buf.is_empty() => break,
            Err(e) => panic!("no complete answer: {e} (got {:?})", String::from_utf8_lossy(&buf)),
        }
        if let Some(end) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&buf[..end]).to_ascii_lowercase();
            let len = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .and_then(|v| v.trim().parse::<usize>().ok());
            if len.is_some_and(|len| buf.len() >= end + 4 + len) {
                break;
            }
        }
    }
    let end = buf.windows(4).position(|w| w == b"\r\n\r\n").expect("a response head");
    let head = String::from_utf8_lossy(&buf[..end]).to_ascii_lowercase();
    let status = head.split(' ').nth(1).and_then(|c| c.parse().ok()).expect("status");
    (status, head, buf[end + 4..].to_vec())
}

fn json_error(status: u16, body: &[u8]) -> serde_json::Value {
    let v: serde_json::Value = serde_json::from_slice(body)
        .unwrap_or_else(|e| panic!("{status}: body is not JSON ({e}): {:?}", String::from_utf8_lossy(body)));
    assert!(v["error"]["code"].is_string() && v["error"]["message"].is_string(), "{v}");
    v
}

#[test]
fn a_second_daemon_on_one_state_directory_refuses_to_start_and_names_the_holder() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_sim(dir.path(), true);
    let first = spawn(&rig, dir.path());
    let c = client(&first);
    let id = start(&c);

    let mut second = Command::new(env!("CARGO_BIN_EXE_scanrigd"))
        .args(["--listen", "127.0.0.1:0", "--shutdown-deadline", "5", "--config"])
        .arg(&rig)
        .arg("--state-dir")
        .arg(dir.path())
        .env_remove("NOTIFY_SOCKET")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn the second scanrigd");
    let status = wait_exit(&mut second, Duration::from_secs(20));
    if status.is_none() {
        let _ = second.kill();
        let _ = second.wait();
        panic!("a second scanrigd on the same state directory kept running");
    }
    let mut stderr = String::new();
    second.stderr.take().expect("stderr").read_to_string(&mut stderr).expect("stderr");
    assert!(!status.expect("status").success(), "{stderr}");
    assert!(stderr.contains(&format!("pid {}", first.pid())), "the holder is not named: {stderr}");
    // The first daemon's scan is untouched and finishes.
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");
}

#[test]
fn half_sent_requests_are_timed_out_and_do_not_delay_sigterm() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_sim(dir.path(), false);
    let mut d = spawn(&rig, dir.path());
    let half = |addr: &str| {
        let mut s = TcpStream::connect(addr).expect("connect");
        s.write_all(b"GET /api/v1/status HTTP/1.1\r\nHost: x\r\nX-Slow: ").expect("write");
        s
    };
    // The server closes a connection whose head does not arrive.
    let mut probe = half(&d.addr);
    probe.set_read_timeout(Some(Duration::from_secs(60))).expect("timeout");
    let mut buf = [0u8; 1024];
    match probe.read(&mut buf) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => {}
        Err(e) => panic!("a half-sent request was not timed out: {e}"),
    }
    // Five half-sent requests and an idle connection, then SIGTERM: a clean exit.
    let _held: Vec<TcpStream> =
        (0..5).map(|_| half(&d.addr)).chain([TcpStream::connect(&d.addr).expect("idle")]).collect();
    assert_eq!(client(&d).get_json("/api/v1/status").expect("status")["rig"], "simulated");
    // SAFETY: sending a signal to our own child process.
    assert_eq!(unsafe { libc::kill(d.pid(), libc::SIGTERM) }, 0);
    let status = wait_exit(&mut d.child, Duration::from_secs(30)).expect("scanrigd did not exit after SIGTERM");
    assert!(status.success(), "exit {status:?}: {}", d.log());
    assert!(!d.log().contains("did not finish"), "{}", d.log());
}

#[test]
fn a_flood_of_previews_never_starves_a_scan() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_sim(dir.path(), false);
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        device_states(&c).iter().all(|(_, st)| st == "connected")
    });
    let stop = Arc::new(AtomicBool::new(false));
    let served = Arc::new(AtomicUsize::new(0));
    let busy = Arc::new(AtomicUsize::new(0));
    let threads: Vec<_> = (0..40)
        .map(|_| {
            let (stop, served, busy, addr) = (stop.clone(), served.clone(), busy.clone(), d.addr.clone());
            std::thread::spawn(move || {
                let c = scanrig::service::client::Client::new(&addr, None)
                    .expect("client")
                    .with_timeout(Duration::from_secs(30));
                while !stop.load(Ordering::SeqCst) {
                    match c.raw("GET", "/api/v1/preview", None) {
                        Ok(r) if r.status == 200 => served.fetch_add(1, Ordering::SeqCst),
                        Ok(_) => busy.fetch_add(1, Ordering::SeqCst),
                        Err(_) => busy.fetch_add(1, Ordering::SeqCst),
                    };
                }
            })
        })
        .collect();
    wait_for("previews being served", Duration::from_secs(30), || served.load(Ordering::SeqCst) >= 40);
    let ids: Vec<String> = (0..3)
        .map(|_| {
            let id = start(&c);
            let meta = wait_finished(&c, &id, Duration::from_secs(60));
            assert_eq!(meta["status"], "complete", "a scan started during a preview flood: {meta}");
            id
        })
        .collect();
    stop.store(true, Ordering::SeqCst);
    for t in threads {
        t.join().expect("preview thread");
    }
    eprintln!(
        "{} previews served, {} refused, {} scans complete",
        served.load(Ordering::SeqCst),
        busy.load(Ordering::SeqCst),
        ids.len()
    );
}

/// Resident memory of `pid`, kB.
fn rss_kb(pid: i32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

#[test]
fn slow_downloads_of_a_big_file_keep_memory_bounded_and_deliver_every_byte() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_sim(dir.path(), false);
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    let id = start(&c);
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");
    // A 32 MiB model, as a fine mesh would be.
    const SIZE: usize = 32 << 20;
    let model: Vec<u8> = (0..SIZE).map(|i| (i % 251) as u8).collect();
    std::fs::write(dir.path().join("scans").join(&id).join("model.ply"), &model).expect("model");

    let before = rss_kb(d.pid());
    // Eight clients that read the first bytes and then stop reading.
    let slow: Vec<TcpStream> = (0..8)
        .map(|_| {
            let mut s = TcpStream::connect(&d.addr).expect("connect");
            s.set_read_timeout(Some(Duration::from_secs(30))).expect("timeout");
            write!(s, "GET /api/v1/scans/{id}/files/model.ply HTTP/1.1\r\nHost: x\r\n\r\n").expect("write");
            let mut first = [0u8; 4096];
            let n = s.read(&mut first).expect("first bytes");
            assert!(String::from_utf8_lossy(&first[..n]).starts_with("HTTP/1.1 200"));
            s
        })
        .collect();
    // The daemon answers meanwhile.
    assert_eq!(c.get_json("/api/v1/status").expect("status")["rig"], "simulated");
    let during = rss_kb(d.pid());
    let grown_mb = during.saturating_sub(before) as f64 / 1024.0;
    eprintln!("RSS {before} kB before, {during} kB with 8 stalled 32 MiB downloads (+{grown_mb:.1} MB)");
    // Reading the whole file per download would hold 8 x 32 MiB.
    assert!(grown_mb < 64.0, "RSS grew by {grown_mb:.1} MB for 8 stalled downloads");
    drop(slow);
    // A full download is byte-exact.
    let r = c.raw("GET", &format!("/api/v1/scans/{id}/files/model.ply"), None).expect("download");
    assert_eq!(r.status, 200);
    assert_eq!(r.body.len(), SIZE);
    assert!(r.body == model, "the downloaded model differs");
}

#[test]
fn every_error_is_json_and_huge_bodies_are_refused_at_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_sim(dir.path(), false);
    let d = spawn(&rig, dir.path());
    let addr = d.addr.clone();

    // A path that is not UTF-8 once decoded.
    let (status, _, body) =
        raw_http(&addr, b"GET /api/v1/scans/%FF%FE HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
    assert_eq!(status, 400);
    json_error(status, &body);

    // A 500 KB header: hyper's 431, with a JSON body.
    let big = format!("GET /api/v1/status HTTP/1.1\r\nHost: x\r\nX-Big: {}\r\n\r\n", "a".repeat(500_000));
    let (status, _, body) = raw_http(&addr, big.as_bytes());
    assert_eq!(status, 431);
    assert_eq!(json_error(status, &body)["error"]["code"], "headers_too_large");

    // A 70 KB request target: hyper's 414, with a JSON body.
    let long = format!("GET /api/v1/{} HTTP/1.1\r\nHost: x\r\n\r\n", "a".repeat(70_000));
    let (status, _, body) = raw_http(&addr, long.as_bytes());
    assert_eq!(status, 414);
    json_error(status, &body);

    // A body announced far larger than any route takes: 413 before any of it is sent.
    let (status, head, body) = raw_http(
        &addr,
        b"POST /api/v1/scans HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 99999999999\r\n\r\n",
    );
    assert_eq!(status, 413, "{head}");
    assert_eq!(json_error(status, &body)["error"]["code"], "too_large");

    // A method a route does not have.
    let (status, _, body) = raw_http(&addr, b"DELETE /api/v1/status HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
    assert_eq!(status, 405);
    json_error(status, &body);

    // A lights list that is too long is named as such.
    let c = client(&d);
    let lights: Vec<usize> = vec![0; 65];
    let r = c
        .raw("POST", "/api/v1/scans", Some(serde_json::json!({ "lights": lights }).to_string().as_bytes()))
        .expect("start");
    assert_eq!(r.status, 422);
    let v = json_error(r.status, &r.body);
    assert!(v["error"]["message"].as_str().unwrap_or("").contains("at most 64"), "{v}");
    let r = c.raw("POST", "/api/v1/scans", Some(br#"{"lights": [9]}"#)).expect("start");
    assert_eq!(r.status, 422);
    let v = json_error(r.status, &r.body);
    assert!(v["error"]["message"].as_str().unwrap_or("").contains("not one of the rig's lights"), "{v}");
    // The daemon is still fine.
    assert_eq!(c.get_json("/api/v1/status").expect("status")["rig"], "simulated");
}

#[test]
fn after_kill_9_partial_writes_are_removed_a_paused_scan_stays_paused_and_a_running_one_is_interrupted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = small_sim(dir.path(), true);
    let mut d = spawn(&rig, dir.path());
    let c = client(&d);
    let id = start(&c);
    wait_for("two frames", Duration::from_secs(30), || {
        frames_on_disk(dir.path(), &id).iter().filter(|f| f.ends_with(".png")).count() >= 2
    });
    c.post_json(&format!("/api/v1/scans/{id}/pause"), &serde_json::json!({})).expect("pause");
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(30))["status"], "paused");
    // A second scan that a crash caught running: its meta says `running`.
    let scans = dir.path().join("scans");
    let crashed = "scan-1-crashed";
    std::fs::create_dir_all(scans.join(crashed).join("frames")).expect("mkdir");
    // The stored meta.json of the paused scan (the served entry adds created, report, outputs).
    let mut meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(scans.join(&id).join("meta.json")).expect("meta")).expect("json");
    meta["id"] = crashed.into();
    meta["status"] = "running".into();
    std::fs::write(scans.join(crashed).join("meta.json"), meta.to_string()).expect("meta");
    // SAFETY: sending a signal to our own child process.
    assert_eq!(unsafe { libc::kill(d.pid(), libc::SIGKILL) }, 0);
    let _ = d.child.wait();
    // Partial writes an export and a frame write left when the process died.
    let temps = [
        scans.join(&id).join(".model.ply.tmp-99999"),
        scans.join(&id).join("frames").join(".pos_002.png.tmp-99999"),
        scans.join(crashed).join(".report.json.tmp-4242"),
    ];
    for t in &temps {
        std::fs::write(t, b"partial").expect("temp");
    }
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    for t in &temps {
        assert!(!t.exists(), "{} survived the restart", t.display());
    }
    assert_eq!(scan_meta(&c, &id)["status"], "paused", "a scan paused before the kill is still paused");
    assert_eq!(scan_meta(&c, crashed)["status"], "interrupted");
    // The paused one resumes to the end.
    let r = c.raw("POST", &format!("/api/v1/scans/{id}/resume"), None).expect("resume");
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let meta = wait_finished(&c, &id, Duration::from_secs(60));
    assert_eq!(meta["status"], "complete", "{meta}");
    assert_eq!(meta["resumes"], 1);
}
