//! Shared helpers for the tests that run the real `scanrigd` binary on 127.0.0.1. Every wait is
//! bounded.
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use scanrig::service::client::Client;

/// A running daemon, killed when dropped.
pub struct Daemon {
    /// The process.
    pub child: Child,
    /// `host:port` it listens on.
    pub addr: String,
    /// Its log (stderr).
    pub stderr: PathBuf,
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Daemon {
    /// The daemon's log so far.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }

    /// Whether the process is still running.
    pub fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// The process id, for signals.
    pub fn pid(&self) -> i32 {
        i32::try_from(self.child.id()).expect("pid")
    }
}

/// The shipped rig file `name` with textual replacements applied (each must match), written to
/// `dir/rig.toml`.
pub fn rig_from(dir: &Path, name: &str, edits: &[(&str, &str)]) -> PathBuf {
    let base = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs").join(name))
        .expect("shipped rig file");
    let mut text = base;
    for (from, to) in edits {
        assert!(text.contains(from), "{name} has no `{from}`");
        text = text.replacen(from, to, 1);
    }
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).expect("write rig");
    path
}

/// Edits for [`rig_from`] that halve the shipped simulated rig's camera (320x240 pixels, the same
/// field of view): for tests that compare two runs of a job with each other rather than with the
/// truth, where the frames' size only costs time.
pub const HALF_SIZE_CAMERA: [(&str, &str); 6] = [
    ("width = 640", "width = 320"),
    ("height = 480", "height = 240"),
    ("fx = 1600.0", "fx = 800.0"),
    ("fy = 1600.0", "fy = 800.0"),
    ("cx = 320.0", "cx = 160.0"),
    ("cy = 240.0", "cy = 120.0"),
];

/// Start `scanrigd` on 127.0.0.1 with a free port; waits (bounded) for its "listening" line.
pub fn spawn(rig: &Path, state: &Path) -> Daemon {
    spawn_in(rig, state, state)
}

/// As [`spawn`], with the log written under `log_dir`.
pub fn spawn_in(rig: &Path, state: &Path, log_dir: &Path) -> Daemon {
    spawn_with(rig, state, log_dir, &[], &[("SCANRIG_LOG", "info")])
}

/// As [`spawn_in`], with more arguments and environment variables.
pub fn spawn_with(rig: &Path, state: &Path, log_dir: &Path, args: &[&str], envs: &[(&str, &str)]) -> Daemon {
    static N: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    let stderr = log_dir.join(format!("daemon-{}-{n}.log", std::process::id()));
    let log = std::fs::File::create(&stderr).expect("log");
    let mut child = Command::new(env!("CARGO_BIN_EXE_scanrigd"))
        .args(["--listen", "127.0.0.1:0", "--shutdown-deadline", "5", "--config"])
        .arg(rig)
        .arg("--state-dir")
        .arg(state)
        .args(args)
        .env("SCANRIG_LOG", "info")
        .envs(envs.iter().copied())
        .env_remove("NOTIFY_SOCKET")
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .expect("spawn scanrigd");
    let stdout = child.stdout.take().expect("stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = rx.recv_timeout(Duration::from_secs(20)).expect("scanrigd did not start in 20 s");
    let addr = line.trim().rsplit(' ').next().expect("address").to_owned();
    Daemon { child, addr, stderr }
}

/// A client of `d` with a 30 s timeout.
pub fn client(d: &Daemon) -> Client {
    Client::new(&d.addr, None).expect("client").with_timeout(Duration::from_secs(30))
}

/// Poll `f` every 20 ms until it holds; panics after `limit`.
pub fn wait_for(what: &str, limit: Duration, mut f: impl FnMut() -> bool) {
    let t = Instant::now();
    while !f() {
        assert!(t.elapsed() < limit, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The scan's `meta.json` as served.
pub fn scan_meta(c: &Client, id: &str) -> serde_json::Value {
    c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["scan"].clone()
}

/// Wait (bounded) until scan `id` is no longer running; returns its final metadata.
pub fn wait_finished(c: &Client, id: &str, limit: Duration) -> serde_json::Value {
    let mut meta = serde_json::Value::Null;
    wait_for("the scan to finish", limit, || {
        meta = scan_meta(c, id);
        meta["status"] != "running"
    });
    meta
}

/// The file names under a scan's `frames/`, sorted.
pub fn frames_on_disk(state: &Path, id: &str) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(state.join("scans").join(id).join("frames"))
        .map(|d| d.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    names.sort();
    names
}

/// `name -> state` of every device in `GET /api/v1/devices`.
pub fn device_states(c: &Client) -> Vec<(String, String)> {
    let v = c.get_json("/api/v1/devices").expect("devices");
    v["devices"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|d| (d["name"].as_str().unwrap_or("").to_owned(), d["state"].as_str().unwrap_or("").to_owned()))
                .collect()
        })
        .unwrap_or_default()
}

/// Run `scanrig args... --daemon addr`, killed after `limit`.
pub fn cli(addr: &str, args: &[&str], limit: Duration) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(args)
        .args(["--daemon", addr])
        .env_remove("SCANRIG_TOKEN")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn scanrig");
    let t = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if t.elapsed() > limit {
            let _ = child.kill();
            panic!("scanrig {args:?} did not finish in {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("output")
}

/// The stdout of a command that must have succeeded (panics with its output otherwise).
pub fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "exit {:?}\nstdout: {}\nstderr: {}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}
