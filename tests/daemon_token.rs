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

/// Start `cmd` (a [`scanrigd`] command) and wait for the address it prints; returns the child
/// and `127.0.0.1:PORT` (it listens on every interface, tests talk to loopback only).
fn start(mut cmd: Command) -> (std::process::Child, String) {
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::null()).spawn().expect("spawn scanrigd");
    let stdout = child.stdout.take().expect("stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let line = rx.recv_timeout(Duration::from_secs(20)).expect("scanrigd did not start in 20 s");
    let port = line.trim().rsplit(':').next().expect("port").to_owned();
    (child, format!("127.0.0.1:{port}"))
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
    let mut cmd = scanrigd(dir.path());
    cmd.arg("--token-file").arg(&token_file);
    let (mut child, addr) = start(cmd);

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

/// One request over a fresh connection with the given extra header lines; returns the status,
/// the header lines and the body (of a stream, such as the camera or the events: nothing, the
/// head is enough).
fn http(addr: &str, method: &str, path: &str, headers: &[&str], body: Option<&str>) -> (u16, Vec<String>, String) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(10))).expect("timeout");
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for h in headers {
        req.push_str(h);
        req.push_str("\r\n");
    }
    if let Some(b) = body {
        req.push_str(&format!("Content-Type: application/json\r\nContent-Length: {}\r\n", b.len()));
    }
    req.push_str("\r\n");
    req.push_str(body.unwrap_or(""));
    s.write_all(req.as_bytes()).expect("send");
    let mut reader = BufReader::new(s);
    let mut status_line = String::new();
    reader.read_line(&mut status_line).expect("status line");
    let status = status_line.split(' ').nth(1).and_then(|c| c.parse().ok()).expect("status");
    let mut lines = Vec::new();
    loop {
        let mut l = String::new();
        reader.read_line(&mut l).expect("header line");
        let l = l.trim_end().to_owned();
        if l.is_empty() {
            break;
        }
        lines.push(l);
    }
    let len = lines
        .iter()
        .find_map(|h| h.to_ascii_lowercase().strip_prefix("content-length:").map(|v| v.trim().parse::<u64>()))
        .and_then(Result::ok);
    let mut text = Vec::new();
    if let Some(n) = len {
        reader.take(n).read_to_end(&mut text).expect("body");
    }
    (status, lines, String::from_utf8_lossy(&text).into_owned())
}

#[test]
fn a_browser_signs_in_with_the_token_and_its_session_cookie_is_checked_like_the_token() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut cmd = scanrigd(dir.path());
    cmd.env("SCANRIGD_TOKEN", "s3cret-token");
    let (mut child, addr) = start(cmd);
    let origin = format!("Origin: http://{addr}");

    // Open without a credential: the page and its files (so it can show the sign-in form) and
    // the session endpoint; nothing else.
    assert_eq!(http(&addr, "GET", "/", &[], None).0, 200);
    assert_eq!(http(&addr, "GET", "/web/app.js", &[], None).0, 200);
    let (status, _, body) = http(&addr, "GET", "/api/v1/session", &[], None);
    assert_eq!(status, 200);
    let v: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    assert_eq!((v["required"].as_bool(), v["authenticated"].as_bool()), (Some(true), Some(false)), "{v}");
    assert_eq!(http(&addr, "GET", "/api/v1/camera.mjpg", &[], None).0, 401);
    assert_eq!(http(&addr, "GET", "/api/v1/events", &[], None).0, 401);

    // A wrong token: 401 after a pause, no cookie; malformed bodies are refused in words.
    let t = std::time::Instant::now();
    let (status, headers, body) =
        http(&addr, "POST", "/api/v1/session", &[&origin], Some(r#"{"token":"s3cret-tokeN"}"#));
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("wrong_token"), "{body}");
    assert!(!headers.iter().any(|h| h.to_ascii_lowercase().starts_with("set-cookie")), "{headers:?}");
    assert!(t.elapsed() >= Duration::from_millis(900), "a wrong token is answered at once");
    let (status, _, body) = http(&addr, "POST", "/api/v1/session", &[], Some(r#"{"tokn":"x"}"#));
    assert_eq!(status, 422, "{body}");
    assert!(body.contains("tokn"), "{body}");
    // A sign-in posted from another site's page is refused before the token is looked at.
    let (status, _, body) =
        http(&addr, "POST", "/api/v1/session", &["Origin: http://evil.example"], Some(r#"{"token":"s3cret-token"}"#));
    assert_eq!(status, 403, "{body}");

    // The right token (white space around it ignored, as in token files): an HttpOnly,
    // SameSite=Strict cookie holding a random id, not the token.
    let (status, headers, body) =
        http(&addr, "POST", "/api/v1/session", &[&origin], Some(r#"{"token":" s3cret-token\n"}"#));
    assert_eq!(status, 200, "{body}");
    let set = headers.iter().find(|h| h.to_ascii_lowercase().starts_with("set-cookie:")).expect("a cookie");
    assert!(set.contains("HttpOnly") && set.contains("SameSite=Strict") && set.contains("Path=/"), "{set}");
    assert!(!set.contains("s3cret"), "the cookie must not hold the token: {set}");
    let id = set.split_once('=').and_then(|(_, v)| v.split(';').next()).expect("cookie value").to_owned();
    assert_eq!(id.len(), 64, "{set}");
    let cookie = format!("Cookie: other=1; scanrig_session={id}");

    // The cookie opens what the token opens, the live parts included.
    let (status, _, body) = http(&addr, "GET", "/api/v1/session", &[&cookie], None);
    assert_eq!(status, 200);
    assert!(body.contains(r#""authenticated":true"#), "{body}");
    assert_eq!(http(&addr, "GET", "/api/v1/status", &[&cookie], None).0, 200);
    let (status, headers, _) = http(&addr, "GET", "/api/v1/camera.mjpg", &[&cookie], None);
    assert_eq!(status, 200);
    assert!(headers.iter().any(|h| h.contains("multipart/x-mixed-replace")), "{headers:?}");
    let (status, headers, _) = http(&addr, "GET", "/api/v1/events", &[&cookie], None);
    assert_eq!(status, 200);
    assert!(headers.iter().any(|h| h.contains("text/event-stream")), "{headers:?}");
    // Changes made with the cookie must come from the daemon's own page.
    let turn = Some(r#"{"turn_deg": 10}"#);
    let (status, _, body) =
        http(&addr, "POST", "/api/v1/control/turntable", &[&cookie, "Origin: http://evil.example"], turn);
    assert_eq!(status, 403, "{body}");
    assert!(body.contains("cross_origin"), "{body}");
    let (status, _, body) =
        http(&addr, "POST", "/api/v1/control/turntable", &[&cookie, "Sec-Fetch-Site: cross-site"], turn);
    assert_eq!(status, 403, "{body}");
    let (status, _, body) = http(&addr, "POST", "/api/v1/control/turntable", &[&cookie, &origin], turn);
    assert_eq!(status, 200, "{body}");
    // A made-up or truncated id is no session.
    let forged = format!("Cookie: scanrig_session={}", "0".repeat(64));
    assert_eq!(http(&addr, "GET", "/api/v1/status", &[&forged], None).0, 401);
    let cut = format!("Cookie: scanrig_session={}", &id[..32]);
    assert_eq!(http(&addr, "GET", "/api/v1/status", &[&cut], None).0, 401);

    // Signing out ends the session and clears the cookie.
    let (status, headers, _) = http(&addr, "DELETE", "/api/v1/session", &[&cookie, &origin], None);
    assert_eq!(status, 200);
    assert!(headers.iter().any(|h| h.to_ascii_lowercase().starts_with("set-cookie") && h.contains("Max-Age=0")));
    assert_eq!(http(&addr, "GET", "/api/v1/status", &[&cookie], None).0, 401);
    assert_eq!(http(&addr, "GET", "/api/v1/camera.mjpg", &[&cookie], None).0, 401);

    let _ = child.kill();
    let _ = child.wait();
}
