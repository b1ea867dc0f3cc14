//! Load test (ignored by default; run it by hand, once):
//!
//! ```text
//! cargo test --test daemon_load -- --ignored --nocapture
//! ```
//!
//! One real `scanrigd` on 127.0.0.1 and the simulated rig. A scan is run without load, then the
//! same scan again while 200 clients poll `GET /api/v1/status` and `GET /api/v1/scans/{id}` (each
//! client: one request, a pause, the other request, ...) for 30 s. Prints requests served,
//! errors, p50/p99/max latency and both scan durations; fails on any error or when the loaded scan
//! takes more than 25% longer. Traffic goes only to 127.0.0.1; the clients stop by themselves
//! after the load period and every wait is bounded.
//!
//! Knobs (environment): `LOAD_CLIENTS` (200), `LOAD_SECONDS` (30), `LOAD_PAUSE_MS` (100, each
//! client's pause between requests), `LOAD_POSITIONS` (100).

mod daemon_common;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use daemon_common::{client, rig_from, spawn, wait_for};
use scanrig::service::client::Client;

fn env_or(name: &str, default: u64) -> u64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// Start a scan and time it until it is no longer running.
fn timed_scan(c: &Client) -> (String, Duration) {
    let t = Instant::now();
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    wait_for("the scan", Duration::from_secs(300), || {
        c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["scan"]["status"] != "running"
    });
    let took = t.elapsed();
    let status = c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["scan"]["status"].clone();
    assert_eq!(status, "complete");
    (id, took)
}

fn percentile(sorted: &[u64], p: f64) -> u64 {
    if sorted.is_empty() {
        return 0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

#[test]
#[ignore = "load test: 30 s of traffic, run by hand"]
fn two_hundred_status_clients_during_a_scan() {
    let clients = env_or("LOAD_CLIENTS", 200).clamp(1, 1000) as usize;
    let seconds = env_or("LOAD_SECONDS", 30).clamp(1, 300);
    let pause = Duration::from_millis(env_or("LOAD_PAUSE_MS", 100).min(10_000));
    let positions = env_or("LOAD_POSITIONS", 100).clamp(3, 720).to_string();
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[("positions = 24", &format!("positions = {positions}")), ("settle_ms = 0", "settle_ms = 100")],
    );
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        daemon_common::device_states(&c).iter().all(|(_, s)| s == "connected")
    });

    let (_, quiet) = timed_scan(&c);
    eprintln!("scan without load: {:.2} s", quiet.as_secs_f64());

    // The loaded run: the clients start with the scan and stop after `seconds`.
    let stop = Arc::new(AtomicBool::new(false));
    let errors = Arc::new(AtomicU64::new(0));
    let scan_id = Arc::new(std::sync::Mutex::new(String::new()));
    let mut workers = Vec::new();
    for k in 0..clients {
        let (stop, errors, scan_id, addr) = (stop.clone(), errors.clone(), scan_id.clone(), d.addr.clone());
        workers.push(std::thread::spawn(move || {
            let c = Client::new(&addr, None).expect("client").with_timeout(Duration::from_secs(10));
            let mut lat_us = Vec::new();
            let mut n = k;
            // Spread the clients' first requests over one pause.
            std::thread::sleep(pause.mul_f64(k as f64 / clients as f64));
            while !stop.load(Ordering::SeqCst) {
                let id = scan_id.lock().map(|s| s.clone()).unwrap_or_default();
                let path = if n % 2 == 0 || id.is_empty() {
                    "/api/v1/status".to_owned()
                } else {
                    format!("/api/v1/scans/{id}")
                };
                let t = Instant::now();
                match c.get_json(&path) {
                    Ok(_) => lat_us.push(t.elapsed().as_micros() as u64),
                    Err(e) => {
                        if errors.fetch_add(1, Ordering::SeqCst) < 5 {
                            eprintln!("client {k}: {path}: {e}");
                        }
                    }
                }
                n += 1;
                std::thread::sleep(pause);
            }
            lat_us
        }));
    }
    let load_start = Instant::now();
    let t = Instant::now();
    let id =
        c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start")["id"].as_str().expect("id").to_owned();
    *scan_id.lock().expect("lock") = id.clone();
    let mut finished = None;
    while load_start.elapsed() < Duration::from_secs(seconds) || finished.is_none() {
        if finished.is_none()
            && c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["scan"]["status"] != "running"
        {
            finished = Some(t.elapsed());
        }
        if load_start.elapsed() >= Duration::from_secs(seconds) {
            stop.store(true, Ordering::SeqCst);
        }
        assert!(t.elapsed() < Duration::from_secs(300), "the loaded scan did not finish in 300 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    stop.store(true, Ordering::SeqCst);
    let load_time = load_start.elapsed();
    let mut lat: Vec<u64> = workers.into_iter().flat_map(|w| w.join().expect("client thread")).collect();
    lat.sort_unstable();
    let loaded = finished.expect("finished");
    let status = c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["scan"]["status"].clone();
    let errors = errors.load(Ordering::SeqCst);
    eprintln!(
        "{clients} clients, {:.1} s: {} requests served ({:.0}/s), {errors} errors, latency p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        load_time.as_secs_f64(),
        lat.len(),
        lat.len() as f64 / load_time.as_secs_f64(),
        percentile(&lat, 0.5) as f64 / 1000.0,
        percentile(&lat, 0.99) as f64 / 1000.0,
        lat.last().copied().unwrap_or(0) as f64 / 1000.0,
    );
    eprintln!(
        "scan without load {:.2} s, with load {:.2} s ({:+.1}%)",
        quiet.as_secs_f64(),
        loaded.as_secs_f64(),
        100.0 * (loaded.as_secs_f64() / quiet.as_secs_f64() - 1.0)
    );
    assert_eq!(status, "complete");
    assert_eq!(errors, 0);
    assert!(loaded.as_secs_f64() <= quiet.as_secs_f64() * 1.25, "the scan slowed down under load");
    assert!(d.log().lines().all(|l| !l.contains("ERROR")), "{}", d.log());
}

/// Count the parts of one `camera.mjpg` viewer until `stop`; a stream that ends or fails before
/// `stop` is an error. Returns (parts, errors) and the frame sequences received before `live_until`.
fn mjpeg_viewer(addr: &str, stop: &AtomicBool, live_until: Instant) -> (u64, u64, Vec<u64>) {
    let mut seqs = Vec::new();
    let (parts, errors) = mjpeg_parts(addr, stop, live_until, &mut seqs);
    (parts, errors, seqs)
}

fn mjpeg_parts(addr: &str, stop: &AtomicBool, live_until: Instant, seqs: &mut Vec<u64>) -> (u64, u64) {
    let c = Client::new(addr, None).expect("client").with_timeout(Duration::from_secs(10));
    let (status, _, mut body) = match c.open_stream("/api/v1/camera.mjpg?fps=5") {
        Ok(s) => s,
        Err(e) => {
            eprintln!("mjpeg viewer: {e}");
            return (0, 1);
        }
    };
    if status != 200 {
        return (0, 1);
    }
    let mut parts = 0;
    while !stop.load(Ordering::SeqCst) {
        match scanrig::service::client::read_multipart_part(&mut *body, "frame") {
            Ok(Some(p)) if p.body.starts_with(&[0xff, 0xd8]) => {
                parts += 1;
                if Instant::now() < live_until {
                    let seq = p
                        .headers
                        .iter()
                        .find(|(k, _)| k == "x-frame-sequence")
                        .and_then(|(_, v)| v.parse::<u64>().ok());
                    seqs.extend(seq);
                }
            }
            Ok(Some(_)) => return (parts, 1),
            Ok(None) => return (parts, u64::from(!stop.load(Ordering::SeqCst))),
            Err(e) => {
                eprintln!("mjpeg viewer: {e}");
                return (parts, u64::from(!stop.load(Ordering::SeqCst)));
            }
        }
    }
    (parts, 0)
}

/// Count the events of one `/events` client until `stop` (reads time out every second so that
/// the client notices `stop` with no event in flight). Returns (events, errors).
fn sse_client(addr: &str, stop: &AtomicBool) -> (u64, u64) {
    use std::io::BufRead;
    let c = Client::new(addr, None).expect("client").with_timeout(Duration::from_secs(1));
    let (status, _, mut body) = match c.open_stream("/api/v1/events") {
        Ok(s) => s,
        Err(e) => {
            eprintln!("sse client: {e}");
            return (0, 1);
        }
    };
    if status != 200 {
        return (0, 1);
    }
    let mut events = 0;
    let mut line = String::new();
    while !stop.load(Ordering::SeqCst) {
        line.clear();
        match body.read_line(&mut line) {
            Ok(0) => return (events, u64::from(!stop.load(Ordering::SeqCst))),
            Ok(_) if line.starts_with("event:") => events += 1,
            Ok(_) => {}
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(e) => {
                eprintln!("sse client: {e}");
                return (events, 1);
            }
        }
    }
    (events, 0)
}

/// 50 MJPEG viewers and 200 SSE clients (knobs `LOAD_MJPEG`, `LOAD_SSE`, `LOAD_SECONDS`,
/// `LOAD_POSITIONS`) for 30 s from the start of a scan; the same scan without them first. Prints
/// both scan times, parts and events received and errors; fails on any error or when the loaded
/// scan takes more than 25% longer.
#[test]
#[ignore = "load test: 30 s of streams, run by hand"]
fn fifty_mjpeg_viewers_and_two_hundred_sse_clients_during_a_scan() {
    let viewers = env_or("LOAD_MJPEG", 50).clamp(1, 500) as usize;
    let sse = env_or("LOAD_SSE", 200).clamp(1, 1000) as usize;
    let seconds = env_or("LOAD_SECONDS", 30).clamp(1, 300);
    let positions = env_or("LOAD_POSITIONS", 100).clamp(3, 720).to_string();
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[("positions = 24", &format!("positions = {positions}")), ("settle_ms = 0", "settle_ms = 100")],
    );
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        daemon_common::device_states(&c).iter().all(|(_, s)| s == "connected")
    });
    let (_, quiet) = timed_scan(&c);
    eprintln!("scan without streams: {:.2} s", quiet.as_secs_f64());

    let stop = Arc::new(AtomicBool::new(false));
    // 5 s of live view before the scan: the viewers share the captures.
    let live = Duration::from_secs(5);
    let live_until = Instant::now() + live;
    let mut mjpeg = Vec::new();
    for _ in 0..viewers {
        let (stop, addr) = (stop.clone(), d.addr.clone());
        mjpeg.push(std::thread::spawn(move || mjpeg_viewer(&addr, &stop, live_until)));
    }
    let mut events = Vec::new();
    for _ in 0..sse {
        let (stop, addr) = (stop.clone(), d.addr.clone());
        events.push(std::thread::spawn(move || sse_client(&addr, &stop)));
    }
    std::thread::sleep(live_until.saturating_duration_since(Instant::now()));
    let load_start = Instant::now();
    let (id, loaded) = timed_scan(&c);
    while load_start.elapsed() < Duration::from_secs(seconds) {
        std::thread::sleep(Duration::from_millis(50));
    }
    stop.store(true, Ordering::SeqCst);
    let (mut parts, mut mjpeg_errors) = (0, 0);
    let mut live_parts = 0;
    let mut distinct = std::collections::BTreeSet::new();
    for w in mjpeg {
        let (p, e, seqs) = w.join().expect("viewer thread");
        parts += p;
        mjpeg_errors += e;
        live_parts += seqs.len();
        distinct.extend(seqs);
    }
    eprintln!(
        "live view before the scan ({:.0} s, {viewers} viewers at 5 fps): {live_parts} parts of {} distinct captures ({:.1} captures/s)",
        live.as_secs_f64(),
        distinct.len(),
        distinct.len() as f64 / live.as_secs_f64()
    );
    let (mut got, mut sse_errors) = (0, 0);
    for w in events {
        let (n, e) = w.join().expect("sse thread");
        got += n;
        sse_errors += e;
    }
    let rss = std::fs::read_to_string(format!("/proc/{}/status", d.pid()))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM"))
                .map(|l| l.split_whitespace().skip(1).collect::<Vec<_>>().join(" "))
        })
        .map_or(String::new(), |v| format!("daemon peak RSS {v}"));
    eprintln!(
        "{viewers} MJPEG viewers: {parts} parts, {mjpeg_errors} errors; {sse} SSE clients: {got} events, {sse_errors} errors; {rss}"
    );
    eprintln!(
        "scan {id}: without streams {:.2} s, with them {:.2} s ({:+.1}%)",
        quiet.as_secs_f64(),
        loaded.as_secs_f64(),
        100.0 * (loaded.as_secs_f64() / quiet.as_secs_f64() - 1.0)
    );
    assert_eq!((mjpeg_errors, sse_errors), (0, 0));
    assert!(parts >= viewers as u64, "every viewer got frames");
    assert!(live_parts > distinct.len(), "the viewers shared captures");
    assert!(got >= sse as u64, "every SSE client got events");
    assert!(loaded.as_secs_f64() <= quiet.as_secs_f64() * 1.25, "the scan slowed down under the streams");
    assert!(d.log().lines().all(|l| !l.contains("ERROR")), "{}", d.log());
}
