//! `systemd-analyze verify` accepts the shipped unit (with ExecStart pointed at the binary under
//! test, since /usr/local/bin/scanrigd is not installed here). Skipped, saying so, where
//! systemd-analyze is absent.

use std::path::Path;
use std::process::Command;

#[test]
fn systemd_analyze_verify_accepts_the_unit() {
    let unit = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("systemd/scanrigd.service"))
        .expect("unit file");
    for directive in ["Type=notify", "WatchdogSec=", "Restart=on-failure", "ProtectSystem=strict", "PrivateTmp=true"] {
        assert!(unit.contains(directive), "the unit lacks {directive}");
    }
    if Command::new("systemd-analyze").arg("--version").output().is_err() {
        assert!(std::env::var_os("CI").is_none(), "CI must run this test, but systemd-analyze is not installed");
        eprintln!("skipped: systemd-analyze is not installed");
        return;
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("scanrigd.service");
    std::fs::write(&path, unit.replace("/usr/local/bin/scanrigd", env!("CARGO_BIN_EXE_scanrigd"))).expect("write");
    let out = Command::new("systemd-analyze").arg("verify").arg(&path).output().expect("run systemd-analyze");
    assert!(
        out.status.success(),
        "systemd-analyze verify failed:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
