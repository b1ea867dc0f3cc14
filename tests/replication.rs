//! Replication of finished scans to a real S3 server on 127.0.0.1, started and stopped by each
//! test: s3rver (npm), which keeps its objects in a directory (so a killed and restarted server
//! still has what it stored, as a real one does) and checks AWS signature V4 (so wrong
//! credentials are refused). The daemon and the CLI are the real binaries; objects are listed and
//! read back through the same object_store client as an independent check of what the server holds.
//!
//! When the server cannot be started these tests fail under `CI` (set by .ci/run) and are skipped
//! elsewhere.
#![cfg(feature = "s3")]

mod daemon_common;

use std::collections::BTreeMap;
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use daemon_common::{client, rig_from, scan_meta, spawn_with, wait_finished, wait_for};
use scanrig::archive::{Archive, Credentials};
use scanrig::config::replication::ReplicationConfig;

const BUCKET: &str = "scans";

/// A running s3rver, killed on drop.
struct S3Server {
    child: Option<Child>,
    port: u16,
    data: PathBuf,
}

impl Drop for S3Server {
    fn drop(&mut self) {
        self.kill();
    }
}

impl S3Server {
    /// Start s3rver on a free loopback port, its objects under `data`, with bucket `scans`.
    /// `None` (skip) when it is not installed, outside CI.
    fn start(data: &Path) -> Option<S3Server> {
        let port = std::net::TcpListener::bind("127.0.0.1:0").ok()?.local_addr().ok()?.port();
        let mut s = S3Server { child: None, port, data: data.to_owned() };
        match s.spawn() {
            Ok(()) => Some(s),
            Err(e) if std::env::var_os("CI").is_some() => panic!("cannot start the S3 server (s3rver): {e}"),
            Err(e) => {
                eprintln!("skipped: cannot start the S3 server (s3rver, `npm install -g s3rver`): {e}");
                None
            }
        }
    }

    fn spawn(&mut self) -> Result<(), String> {
        std::fs::create_dir_all(&self.data).map_err(|e| e.to_string())?;
        let child = Command::new(std::env::var("SCANRIG_S3RVER").unwrap_or_else(|_| "s3rver".into()))
            .args(["-d"])
            .arg(&self.data)
            .args(["-a", "127.0.0.1", "-p", &self.port.to_string(), "--silent", "--no-vhost-buckets"])
            .args(["--configure-bucket", BUCKET])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| e.to_string())?;
        self.child = Some(child);
        let t = Instant::now();
        while TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            if t.elapsed() > Duration::from_secs(20) {
                return Err("s3rver did not listen within 20 s".into());
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(())
    }

    /// SIGKILL: the server dies mid-request.
    fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    fn restart(&mut self) {
        self.kill();
        self.spawn().expect("restart s3rver");
    }

    fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }
}

/// A private credentials file.
fn credentials_file(dir: &Path, key_id: &str, secret: &str) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let p = dir.join("credentials");
    std::fs::write(&p, format!("[default]\naws_access_key_id = {key_id}\naws_secret_access_key = {secret}\n"))
        .expect("credentials");
    std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    p
}

/// A replication file for `server`; `extra` lines are appended.
fn replication_file(dir: &Path, server: &S3Server, key_id: &str, secret: &str, extra: &str) -> PathBuf {
    credentials_file(dir, key_id, secret);
    let p = dir.join("replication.toml");
    std::fs::write(
        &p,
        format!(
            "[replication]\nendpoint = \"{}\"\nbucket = \"{BUCKET}\"\nprefix = \"lab\"\ncredentials_file = \"credentials\"\n\
             allow_http = true\npart_size = 65536\nretry_initial_s = 0.2\nretry_max_s = 1.0\nrequest_timeout_s = 5\n{extra}",
            server.endpoint()
        ),
    )
    .expect("replication file");
    p
}

/// A small, quick simulated scan.
fn rig(dir: &Path) -> PathBuf {
    rig_from(dir, "simulated.toml", &[("positions = 24", "positions = 6"), ("resolution = 128", "resolution = 40")])
}

/// Every regular file under `dir`, relative `/`-separated path -> bytes.
fn local_files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    scanrig::archive::list_files(dir)
        .expect("list")
        .into_iter()
        .map(|p| {
            let bytes = std::fs::read(dir.join(&p)).expect("read");
            (p, bytes)
        })
        .collect()
}

/// A client of the server, independent of the daemon's.
fn archive(dir: &Path) -> Archive {
    let cfg = scanrig::config::replication::load_file(&dir.join("replication.toml")).expect("settings");
    let creds = Credentials::from_file(&dir.join("credentials"), "default").expect("credentials");
    Archive::open(&cfg, &creds).expect("client")
}

/// Every object under `prefix`, key -> bytes.
fn objects(a: &Archive, prefix: &str) -> BTreeMap<String, Vec<u8>> {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
    rt.block_on(async {
        let mut out = BTreeMap::new();
        for (key, _) in a.list(prefix).await.expect("list") {
            let bytes = a.get_bytes(&key).await.expect("get");
            out.insert(key, bytes);
        }
        out
    })
}

fn start_scan(c: &scanrig::service::client::Client) -> String {
    let started = c.post_json("/api/v1/scans", &serde_json::json!({})).expect("start");
    started["id"].as_str().expect("id").to_owned()
}

fn replication(c: &scanrig::service::client::Client, id: &str) -> serde_json::Value {
    c.get_json(&format!("/api/v1/scans/{id}")).expect("scan")["replication"].clone()
}

fn metric(c: &scanrig::service::client::Client, name: &str) -> u64 {
    let text = String::from_utf8(c.request("GET", "/metrics", None).expect("metrics").body).expect("utf8");
    text.lines()
        .find(|l| l.starts_with(&format!("{name}{{")))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{name} not in {text}"))
}

/// Objects of scan `id` equal its local files byte for byte (nothing missing, nothing extra), and
/// the manifest lists every file.
fn assert_replica_equals(objects: &BTreeMap<String, Vec<u8>>, scan_key: &str, local: &BTreeMap<String, Vec<u8>>) {
    let mut want: Vec<String> = local.keys().map(|p| format!("{scan_key}/{p}")).collect();
    want.push(format!("{scan_key}/manifest.json"));
    want.sort();
    let got: Vec<String> = objects.keys().cloned().collect();
    assert_eq!(got, want, "the bucket holds exactly the scan's files and its manifest");
    for (p, bytes) in local {
        assert!(objects[&format!("{scan_key}/{p}")] == *bytes, "{p} differs from its object");
    }
    let manifest: serde_json::Value =
        serde_json::from_slice(&objects[&format!("{scan_key}/manifest.json")]).expect("manifest");
    let listed: Vec<&str> =
        manifest["files"].as_array().expect("files").iter().filter_map(|f| f["path"].as_str()).collect();
    assert_eq!(listed, local.keys().map(String::as_str).collect::<Vec<_>>());
    for f in manifest["files"].as_array().expect("files") {
        let p = f["path"].as_str().expect("path");
        assert_eq!(f["sha256"].as_str().expect("sha"), scanrig::archive::sha256_hex(&local[p]), "{p}");
        assert_eq!(f["size"].as_u64(), Some(local[p].len() as u64), "{p}");
    }
}

#[test]
fn a_scan_replicates_byte_for_byte_and_reprocesses_from_the_bucket_as_from_disk() {
    let dir = tempfile::tempdir().expect("tempdir");
    let Some(server) = S3Server::start(&dir.path().join("s3")) else { return };
    let settings = replication_file(dir.path(), &server, "S3RVER", "S3RVER", "");
    let state = dir.path().join("state");
    let d = spawn_with(&rig(dir.path()), &state, dir.path(), &["--replication", settings.to_str().expect("utf8")], &[]);
    let c = client(&d);
    let id = start_scan(&c);
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");
    wait_for("the scan to replicate", Duration::from_secs(60), || replication(&c, &id)["state"] == "replicated");
    let r = replication(&c, &id);
    let local = local_files(&state.join("scans").join(&id));
    assert_eq!(r["files_total"].as_u64(), Some(local.len() as u64), "{r}");
    assert_eq!(r["files_done"], r["files_total"], "{r}");
    assert_eq!(r["url"], format!("s3://{BUCKET}/lab/simulated/{id}"), "{r}");
    assert_eq!(metric(&c, "scanrig_replication_files_total"), local.len() as u64);
    assert_eq!(metric(&c, "scanrig_replication_scans_total"), 1);
    assert_eq!(metric(&c, "scanrig_replication_queued"), 0);
    // Frames are larger than the 64 KiB parts: they went up in several parts.
    assert!(local.iter().any(|(p, b)| p.starts_with("frames/") && b.len() > 3 * 65536), "no multipart-sized frame");
    let a = archive(dir.path());
    let scan_key = format!("lab/simulated/{id}");
    assert_replica_equals(&objects(&a, &scan_key), &scan_key, &local);

    // Reprocess from the bucket and from disk: the same models; the result is stored beside the scan.
    let from_s3 = dir.path().join("from-s3");
    let from_disk = dir.path().join("from-disk");
    let url = format!("s3://{BUCKET}/{scan_key}");
    let out = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(["reconstruct", "--scan", &url, "--replication"])
        .arg(&settings)
        .args(["--resolution", "32", "--out"])
        .arg(&from_s3)
        .output()
        .expect("scanrig");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stored = stdout.lines().find_map(|l| l.strip_prefix("results in s3://")).expect("uploaded result URL");
    let out = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(["reconstruct", "--scan"])
        .arg(state.join("scans").join(&id))
        .args(["--resolution", "32", "--out"])
        .arg(&from_disk)
        .output()
        .expect("scanrig");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (s3_files, disk_files) = (local_files(&from_s3), local_files(&from_disk));
    let models: Vec<&String> = s3_files.keys().filter(|p| p.ends_with(".ply") || p.ends_with(".stl")).collect();
    assert!(models.len() >= 2, "{:?}", s3_files.keys());
    assert_eq!(s3_files.keys().collect::<Vec<_>>(), disk_files.keys().collect::<Vec<_>>());
    for p in models {
        assert!(s3_files[p] == disk_files[p], "{p}: reprocess from the bucket differs from reprocess from disk");
    }
    let result_key = stored.strip_prefix(&format!("{BUCKET}/")).expect("bucket").to_owned();
    assert!(result_key.starts_with(&format!("{scan_key}/reprocess-")), "{result_key}");
    assert_replica_equals(&objects(&a, &result_key), &result_key, &s3_files);
}

#[test]
fn server_killed_and_daemon_crashed_mid_upload_resume_with_nothing_lost_or_duplicated() {
    let dir = tempfile::tempdir().expect("tempdir");
    let Some(mut server) = S3Server::start(&dir.path().join("s3")) else { return };
    // 192 KiB/s: the scan (model.stl alone is 1.7 MB) takes seconds to upload, so both kills land
    // mid-upload.
    let settings = replication_file(
        dir.path(),
        &server,
        "S3RVER",
        "S3RVER",
        "max_rate_kib_per_s = 192\nprune = \"frames_after_verified\"\n",
    );
    let state = dir.path().join("state");
    let rig = rig(dir.path());
    let args = ["--replication", settings.to_str().expect("utf8")];
    let mut d = spawn_with(&rig, &state, dir.path(), &args, &[]);
    let c = client(&d);
    let id = start_scan(&c);
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");
    // What the scan holds, copied before the prune policy removes its frames.
    let local = local_files(&state.join("scans").join(&id));
    let n = local.len() as u64;

    // 1. The server dies mid-upload: the attempt fails with the reason in words, then resumes.
    wait_for("some files uploaded", Duration::from_secs(60), || replication(&c, &id)["files_done"].as_u64() >= Some(2));
    server.kill();
    wait_for("the failure in the status", Duration::from_secs(30), || replication(&c, &id)["state"] == "failed");
    let r = replication(&c, &id);
    assert!(r["error"].as_str().is_some_and(|e| e.contains("cannot reach the object store")), "{r}");
    let done_before = r["files_done"].as_u64().expect("files_done");
    assert!(done_before < n, "{r}");
    server.restart();
    wait_for("the upload to resume", Duration::from_secs(30), || {
        replication(&c, &id)["files_done"].as_u64() > Some(done_before + 1)
    });

    // 2. The daemon dies (SIGKILL) mid-upload: the queue on disk says which files are verified.
    d.child.kill().expect("kill");
    let _ = d.child.wait();
    let queue: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.join("replication/queue.json")).expect("queue")).expect("json");
    let verified =
        queue["scans"][0]["files"].as_array().expect("files").iter().filter(|f| f["verified"] == true).count() as u64;
    assert!(verified > done_before && verified < n, "verified {verified} of {n}");
    let d = spawn_with(&rig, &state, dir.path(), &args, &[]);
    let c = client(&d);
    wait_for("the scan to replicate", Duration::from_secs(60), || replication(&c, &id)["state"] == "replicated");
    // The new daemon uploaded exactly the files not verified before its predecessor died.
    assert_eq!(metric(&c, "scanrig_replication_files_total"), n - verified);
    let a = archive(dir.path());
    let scan_key = format!("lab/simulated/{id}");
    assert_replica_equals(&objects(&a, &scan_key), &scan_key, &local);

    // Pruned after the verified upload: frames gone locally, results kept.
    wait_for("the prune", Duration::from_secs(10), || replication(&c, &id)["pruned"] == true);
    let scan_dir = state.join("scans").join(&id);
    assert!(!scan_dir.join("frames").exists());
    assert!(scan_dir.join("report.json").is_file() && scan_dir.join("model.ply").is_file());
    assert_eq!(scan_meta(&c, &id)["status"], "complete");
}

#[test]
fn wrong_credentials_show_a_clear_error_keep_the_scan_and_never_show_the_secret() {
    let dir = tempfile::tempdir().expect("tempdir");
    let Some(server) = S3Server::start(&dir.path().join("s3")) else { return };
    // s3rver checks the access key id (an unknown one is refused: InvalidAccessKeyId) but not the
    // SigV4 signature, so the wrong credential here is a key id the server does not know.
    let secret = "wrong-Secret-7f3a9c";
    let settings = replication_file(dir.path(), &server, "NOT-A-KEY", secret, "prune = \"frames_after_verified\"\n");
    let state = dir.path().join("state");
    let d = spawn_with(
        &rig(dir.path()),
        &state,
        dir.path(),
        &["--replication", settings.to_str().expect("utf8")],
        &[("SCANRIG_LOG", "debug")],
    );
    let c = client(&d);
    let id = start_scan(&c);
    assert_eq!(wait_finished(&c, &id, Duration::from_secs(60))["status"], "complete");
    let t = Instant::now();
    while replication(&c, &id)["attempts"].as_u64() < Some(2) {
        assert!(t.elapsed() < Duration::from_secs(30), "no two failed attempts: {}\n{}", replication(&c, &id), d.log());
        std::thread::sleep(Duration::from_millis(20));
    }
    let r = replication(&c, &id);
    assert_eq!(r["state"], "failed", "{r}");
    let error = r["error"].as_str().expect("error");
    eprintln!("status of a refused credential: {r}");
    assert!(error.contains("the server refused the credentials"), "{error}");
    assert!(error.contains("InvalidAccessKeyId"), "{error}");
    assert_eq!(r["files_done"], 0, "{r}");
    assert!(metric(&c, "scanrig_replication_failures_total") >= 2);
    assert_eq!(metric(&c, "scanrig_replication_failing"), 1);
    // The local scan is kept whole (the prune policy only acts on verified uploads).
    assert!(!daemon_common::frames_on_disk(&state, &id).is_empty());
    assert_eq!(scan_meta(&c, &id)["status"], "complete");
    // Nothing reached the bucket (listed with the right credentials).
    let good = dir.path().join("good");
    std::fs::create_dir_all(&good).expect("mkdir");
    let cfg: ReplicationConfig = scanrig::config::replication::load_file(&settings).expect("settings");
    let creds = Credentials::from_file(&credentials_file(&good, "S3RVER", "S3RVER"), "default").expect("credentials");
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
    let listed = rt.block_on(Archive::open(&cfg, &creds).expect("client").list("lab")).expect("list");
    assert_eq!(listed, vec![], "objects uploaded with a refused credential");
    // The secret is in no status, metric or log line.
    let everything = format!(
        "{}{}{}{}",
        c.get_json(&format!("/api/v1/scans/{id}")).expect("scan"),
        c.get_json("/api/v1/status").expect("status"),
        String::from_utf8_lossy(&c.request("GET", "/metrics", None).expect("metrics").body),
        d.log()
    );
    assert!(d.log().contains("replication attempt failed"), "{}", d.log());
    assert!(!everything.contains(secret), "the secret leaked");

    // A bucket that does not exist, from the CLI: a clear error naming it.
    let url = format!("s3://no-such-bucket/lab/simulated/{id}");
    let out = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(["reconstruct", "--scan", &url, "--out"])
        .arg(dir.path().join("never"))
        .env("AWS_ENDPOINT_URL", server.endpoint())
        .env("AWS_ALLOW_HTTP", "true")
        .env("AWS_ACCESS_KEY_ID", "S3RVER")
        .env("AWS_SECRET_ACCESS_KEY", secret)
        .output()
        .expect("scanrig");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("the bucket does not exist") && stderr.contains("no-such-bucket"), "{stderr}");
    assert!(!stderr.contains(secret), "{stderr}");
}
