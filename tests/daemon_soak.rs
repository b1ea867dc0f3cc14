//! Soak: the real `scanrigd` on the simulated rig, a scan started every few seconds for
//! `SCANRIG_SOAK_SECS` seconds (default 600), while clients poll the status, list the scans and
//! download results. Resident memory and open descriptors must stay flat and nothing may fail.
//!
//! Flat means: the median RSS of the last quarter of the run is at most [`FLAT_SLACK_KB`] above
//! the largest RSS from a fifth to half of the run (the plateau, after a fifth as warm-up), so
//! memory kept per scan or per request shows as growth, while a peak (a scan's frames meeting a
//! download) in the last quarter does not, nor the allocator's last growth in a short run's
//! plateau; and the descriptors counted with no client connected are the same at the end as after
//! the first scan.
//!
//! Ignored by default (it runs for minutes); `.ci/run` runs a two-minute version:
//! `SCANRIG_SOAK_SECS=120 cargo test --release --test daemon_soak -- --ignored --nocapture`.

mod daemon_common;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use daemon_common::{client, device_states, rig_from, spawn, wait_finished, wait_for};
use scanrig::service::client::Client;

/// How far the last quarter's median RSS may rise above the plateau's largest, kB. With the
/// daemon's two malloc arenas it stays below the plateau's largest (60 s: 27.6 MB against
/// 29.4 MB); a daemon made to keep 1 MB per completed scan goes past it within the 60 s run
/// (39.6 MB against 34.7 MB), 4.9 MB over the plateau: 2 MB of slack leaves room for the
/// allocator's noise on a loaded machine and still catches that.
const FLAT_SLACK_KB: u64 = 2048;

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

/// The daemon's descriptors once no request is in flight: the count, once it has held for 1 s
/// (connections just closed by a client take a moment to be closed by the server too); after
/// 10 s, the least count seen.
fn settled_fds(pid: i32) -> usize {
    let t = Instant::now();
    let (mut least, mut last, mut since) = (open_fds(pid), open_fds(pid), Instant::now());
    while since.elapsed() < Duration::from_secs(1) && t.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(50));
        let n = open_fds(pid);
        least = least.min(n);
        if n != last {
            (last, since) = (n, Instant::now());
        }
    }
    if since.elapsed() >= Duration::from_secs(1) {
        last
    } else {
        least
    }
}

/// The RSS samples taken between `from` and `to` seconds, sorted.
fn window(samples: &[(f64, u64)], from: f64, to: f64) -> Vec<u64> {
    let mut w: Vec<u64> = samples.iter().filter(|(t, _)| (from..to).contains(t)).map(|&(_, r)| r).collect();
    w.sort_unstable();
    w
}

/// Least, median and largest of a sorted window, for the log.
fn spread(w: &[u64]) -> String {
    format!("{} / {} / {} kB", w[0], w[w.len() / 2], w[w.len() - 1])
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
#[ignore = "runs for minutes; .ci/run runs it with SCANRIG_SOAK_SECS=120"]
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
    let (rss0, fds0) = (rss_kb(d.pid()), settled_fds(d.pid()));

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
    // RSS four times a second: (seconds into the soak, kB).
    let sampler = {
        let (stop, pid) = (stop.clone(), d.pid());
        std::thread::spawn(move || {
            let mut samples = Vec::new();
            while !stop.load(Ordering::SeqCst) {
                samples.push((t0.elapsed().as_secs_f64(), rss_kb(pid)));
                std::thread::sleep(Duration::from_millis(250));
            }
            samples
        })
    };
    let mut scans = 1u64;
    while t0.elapsed() < Duration::from_secs(secs) {
        let id = start_scan(&c);
        let meta = wait_finished(&c, &id, Duration::from_secs(120));
        assert_eq!(meta["status"], "complete", "{meta}");
        scans += 1;
        *last_complete.lock().expect("lock") = id;
        std::thread::sleep(Duration::from_secs(2));
    }
    let soaked = t0.elapsed().as_secs_f64();
    stop.store(true, Ordering::SeqCst);
    for t in clients {
        t.join().expect("client thread");
    }
    let samples = sampler.join().expect("sampler thread");
    let fds1 = settled_fds(d.pid());
    let rss1 = rss_kb(d.pid());
    let requests = counters.requests.load(Ordering::Relaxed);
    let errors = counters.errors.load(Ordering::Relaxed);
    let mb = counters.bytes.load(Ordering::Relaxed) as f64 / 1e6;
    eprintln!(
        "soak {secs} s: {scans} scans complete, {requests} requests ({mb:.1} MB served), {errors} errors; \
         RSS {rss0} kB -> {rss1} kB, open fds {fds0} -> {fds1}"
    );
    // The least, median and largest RSS of each minute, to tell growth from a plateau.
    let minutes: Vec<String> = (0..=secs / 60)
        .filter_map(|m| {
            let w = window(&samples, m as f64 * 60.0, (m + 1) as f64 * 60.0);
            (!w.is_empty()).then(|| format!("{m}: {}", spread(&w)))
        })
        .collect();
    eprintln!("RSS by minute (least / median / largest of {} samples): {}", samples.len(), minutes.join(", "));
    let (plateau, tail) = (window(&samples, 0.2 * soaked, 0.5 * soaked), window(&samples, 0.75 * soaked, soaked));
    assert!(!plateau.is_empty() && !tail.is_empty(), "too few RSS samples: {}", samples.len());
    eprintln!("RSS from 20 % to 50 % of the run: {}; last quarter: {}", spread(&plateau), spread(&tail));
    let (plateau, tail) = (plateau[plateau.len() - 1], tail[tail.len() / 2]);
    assert_eq!(errors, 0, "requests failed during the soak");
    assert_eq!(fds1, fds0, "open descriptors changed over {scans} scans: {fds0} -> {fds1}");
    assert!(
        tail <= plateau + FLAT_SLACK_KB,
        "RSS grew: the last quarter's median {tail} kB is over {FLAT_SLACK_KB} kB above the plateau's largest {plateau} kB \
         ({scans} scans, {requests} requests)"
    );
    assert!(d.log().lines().all(|l| !l.contains("ERROR")), "errors in the daemon log:\n{}", d.log());
}
