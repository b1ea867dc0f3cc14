//! Soak: the real `scanrigd` on the simulated rig, a scan started every few seconds for
//! `SCANRIG_SOAK_SECS` seconds (default 600), while clients poll the status, list the scans and
//! download results. Resident memory and open descriptors must stay flat and nothing may fail.
//!
//! Ignored by default (it runs for minutes); `.ci/run` runs a 2-minute version:
//! `SCANRIG_SOAK_SECS=60 cargo test --release --test daemon_soak -- --ignored --nocapture`.

mod daemon_common;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use daemon_common::{client, device_states, rig_from, spawn, wait_finished, wait_for};
use scanrig::service::client::Client;

fn rss_kb(pid: i32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .expect("proc status")
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

fn open_fds(pid: i32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).expect("proc fd").count()
}

#[derive(Default)]
struct Counters {
    requests: AtomicU64,
    errors: AtomicU64,
    bytes: AtomicU64,
}

impl Counters {
    fn record(&self, what: &str, r: Result<scanrig::service::client::Response, scanrig::service::client::ClientError>) {
        self.requests.fetch_add(1, Ordering::Relaxed);
        match r {
            Ok(r) if (200..300).contains(&r.status) => {
                self.bytes.fetch_add(r.body.len() as u64, Ordering::Relaxed);
            }
            Ok(r) => {
                self.errors.fetch_add(1, Ordering::Relaxed);
                eprintln!("soak: {what}: HTTP {}: {}", r.status, String::from_utf8_lossy(&r.body));
            }
            Err(e) => {
                self.errors.fetch_add(1, Ordering::Relaxed);
                eprintln!("soak: {what}: {e}");
            }
        }
    }
}

#[test]
#[ignore = "runs for minutes; .ci/run runs it with SCANRIG_SOAK_SECS=60"]
fn soak_scans_polling_and_downloads_keep_memory_and_descriptors_flat() {
    let secs: u64 = std::env::var("SCANRIG_SOAK_SECS").ok().and_then(|v| v.parse().ok()).unwrap_or(600);
    let dir = tempfile::tempdir().expect("tempdir");
    let rig = rig_from(
        dir.path(),
        "simulated.toml",
        &[("positions = 24", "positions = 8"), ("resolution = 128", "resolution = 40")],
    );
    let d = spawn(&rig, dir.path());
    let c = client(&d);
    wait_for("devices connected", Duration::from_secs(10), || {
        device_states(&c).iter().all(|(_, st)| st == "connected")
    });
    let counters = Arc::new(Counters::default());
    let start_scan = |c: &Client| -> String {
        let r = c.raw("POST", "/api/v1/scans", Some(b"{}"));
        let id = r.as_ref().ok().and_then(|r| r.json().ok()).and_then(|v| v["id"].as_str().map(str::to_owned));
        counters.record("start", r);
        id.expect("a scan id")
    };
    // Warm-up: one scan, so that the first measurement is of a daemon that has done everything once.
    let first = start_scan(&c);
    assert_eq!(wait_finished(&c, &first, Duration::from_secs(60))["status"], "complete");
    let last_complete = Arc::new(Mutex::new(first));
    let (rss0, fds0) = (rss_kb(d.pid()), open_fds(d.pid()));

    let stop = Arc::new(AtomicBool::new(false));
    let mut clients = Vec::new();
    for k in 0..3 {
        let (stop, counters, last, addr) = (stop.clone(), counters.clone(), last_complete.clone(), d.addr.clone());
        clients.push(std::thread::spawn(move || {
            let c = Client::new(&addr, None).expect("client").with_timeout(Duration::from_secs(30));
            let mut n = 0u64;
            while !stop.load(Ordering::SeqCst) {
                n += 1;
                match k {
                    0 => counters.record("status", c.raw("GET", "/api/v1/status", None)),
                    1 => {
                        counters.record("list", c.raw("GET", "/api/v1/scans", None));
                        counters.record("devices", c.raw("GET", "/api/v1/devices", None));
                    }
                    _ => {
                        let id = last.lock().expect("lock").clone();
                        counters.record("model", c.raw("GET", &format!("/api/v1/scans/{id}/files/model.ply"), None));
                        let frame = format!("/api/v1/scans/{id}/files/frames/pos_{:03}.png", n % 8);
                        counters.record("frame", c.raw("GET", &frame, None));
                        counters.record("report", c.raw("GET", &format!("/api/v1/scans/{id}/files/report.json"), None));
                    }
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }));
    }

    let t0 = Instant::now();
    let mut scans = 1u64;
    // RSS after each scan: (seconds into the soak, kB).
    let mut rss_series = Vec::new();
    while t0.elapsed() < Duration::from_secs(secs) {
        let id = start_scan(&c);
        let meta = wait_finished(&c, &id, Duration::from_secs(120));
        assert_eq!(meta["status"], "complete", "{meta}");
        scans += 1;
        rss_series.push((t0.elapsed().as_secs(), rss_kb(d.pid())));
        *last_complete.lock().expect("lock") = id;
        std::thread::sleep(Duration::from_secs(2));
    }
    stop.store(true, Ordering::SeqCst);
    for t in clients {
        t.join().expect("client thread");
    }
    // Let finished connections close before counting descriptors (bounded).
    let mut fds1 = open_fds(d.pid());
    let settle = Instant::now();
    while fds1 > fds0 && settle.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(100));
        fds1 = open_fds(d.pid());
    }
    let rss1 = rss_kb(d.pid());
    let requests = counters.requests.load(Ordering::Relaxed);
    let errors = counters.errors.load(Ordering::Relaxed);
    let mb = counters.bytes.load(Ordering::Relaxed) as f64 / 1e6;
    eprintln!(
        "soak {secs} s: {scans} scans complete, {requests} requests ({mb:.1} MB served), {errors} errors; \
         RSS {rss0} kB -> {rss1} kB, open fds {fds0} -> {fds1}"
    );
    // The largest RSS in each minute, to tell growth from a plateau.
    let minutes: Vec<String> = (0..=secs / 60)
        .filter_map(|m| {
            let max = rss_series.iter().filter(|(t, _)| t / 60 == m).map(|&(_, r)| r).max()?;
            Some(format!("{m}: {max}"))
        })
        .collect();
    eprintln!("RSS (kB) by minute, largest after a scan: {}", minutes.join(", "));
    assert_eq!(errors, 0, "requests failed during the soak");
    assert!(fds1 <= fds0 + 2, "descriptors leak: {fds0} -> {fds1}");
    // Flat: allocator noise only, not a growth with the scans done (each scan holds ~4 MB of frames).
    assert!(rss1 <= rss0 + rss0 / 2 + 16 * 1024, "RSS grew: {rss0} kB -> {rss1} kB over {scans} scans");
    assert!(d.log().lines().all(|l| !l.contains("ERROR")), "errors in the daemon log:\n{}", d.log());
}
