//! Bound to anything but loopback, `scanrigd` refuses to start without a bearer token, and with one
//! every request needs it. Traffic goes to 127.0.0.1 only (the daemon listens on 0.0.0.0).

use std::io::{BufRead, BufReader};
use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use scanrig::service::client::Client;

fn scanrigd(state: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_scanrigd"));
    c.args(["--listen", "0.0.0.0:0", "--shutdown-deadline", "5", "--config"])
        .arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml"))
        .arg("--state-dir")
        .arg(state)
        .env_remove("NOTIFY_SOCKET")
        .env_remove("SCANRIGD_TOKEN");
    c
}

#[test]
fn a_non_loopback_address_needs_a_token_and_every_request_carries_it() {
    let dir = tempfile::tempdir().expect("tempdir");

    // No token: refuse to start, saying why.
    let out = scanrigd(dir.path()).stdin(Stdio::null()).output().expect("run scanrigd");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("needs a bearer token"), "{stderr}");

    // With a token from a file.
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, "s3cret-token\n").expect("write token");
    std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(0o600)).expect("chmod");
    let mut child = scanrigd(dir.path())
        .arg("--token-file")
        .arg(&token_file)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
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
    let port = line.trim().rsplit(':').next().expect("port").to_owned();
    let addr = format!("127.0.0.1:{port}");

    let anonymous = Client::new(&addr, None).expect("client").with_timeout(Duration::from_secs(10));
    let r = anonymous.raw("GET", "/api/v1/status", None).expect("request");
    assert_eq!(r.status, 401);
    let body: serde_json::Value = serde_json::from_slice(&r.body).expect("JSON error");
    assert_eq!(body["error"]["code"], "unauthorized");

    let wrong = Client::new(&addr, Some("s3cret-tokeN".into())).expect("client").with_timeout(Duration::from_secs(10));
    assert_eq!(wrong.raw("GET", "/api/v1/status", None).expect("request").status, 401);

    let right = Client::new(&addr, Some("s3cret-token".into())).expect("client").with_timeout(Duration::from_secs(10));
    let r = right.raw("GET", "/api/v1/status", None).expect("request");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    // The CLI takes the token from a private file or SCANRIG_TOKEN; `--token` is gone.
    let scanrig = |args: &[&str], env: Option<&str>| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_scanrig"));
        c.args(args).args(["--daemon", &addr]).env_remove("SCANRIG_TOKEN");
        if let Some(t) = env {
            c.env("SCANRIG_TOKEN", t);
        }
        c.stdin(Stdio::null()).output().expect("run scanrig")
    };
    let out = scanrig(&["status", "--token", "s3cret-token"], None);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--token"), "{}", String::from_utf8_lossy(&out.stderr));
    let tf = token_file.to_str().expect("utf8");
    let out = scanrig(&["status", "--token-file", tf], None);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = scanrig(&["status"], Some("s3cret-token"));
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = scanrig(&["status"], Some("  "));
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("empty"), "{}", String::from_utf8_lossy(&out.stderr));

    let _ = child.kill();
    let _ = child.wait();
}

#[test]
fn empty_whitespace_and_readable_token_files_and_a_blank_environment_token_are_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let token_file = dir.path().join("token");
    for (text, mode, why) in [
        ("", 0o600, "empty"),
        (" \n\t\n", 0o600, "empty"),
        ("s3cret-token\n", 0o644, "readable by its group or others"),
        ("s3cret-token\n", 0o640, "readable by its group or others"),
    ] {
        std::fs::write(&token_file, text).expect("write token");
        std::fs::set_permissions(&token_file, std::fs::Permissions::from_mode(mode)).expect("chmod");
        let mut child = scanrigd(dir.path())
            .arg("--token-file")
            .arg(&token_file)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn scanrigd");
        let t = std::time::Instant::now();
        while child.try_wait().expect("wait").is_none() {
            if t.elapsed() > Duration::from_secs(20) {
                let _ = child.kill();
                let _ = child.wait();
                panic!("scanrigd started with a token file {text:?} mode {mode:o}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let out = child.wait_with_output().expect("output");
        assert!(!out.status.success());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(why), "{text:?} {mode:o}: {stderr}");
    }
    let out = scanrigd(dir.path()).env("SCANRIGD_TOKEN", " \t ").stdin(Stdio::null()).output().expect("run");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("empty"), "{}", String::from_utf8_lossy(&out.stderr));
}
