//! Bound to anything but loopback, `scanrigd` refuses to start without a bearer token, and with one
//! every request needs it. Traffic goes to 127.0.0.1 only (the daemon listens on 0.0.0.0).

use std::io::{BufRead, BufReader};
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

    let _ = child.kill();
    let _ = child.wait();
}
