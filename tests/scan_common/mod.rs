//! Shared helpers for the tests that run the real `scanrig scan` on shipped rig files.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// A path inside the repository.
pub fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The `scanrig` binary under test.
pub fn scanrig() -> Command {
    Command::new(env!("CARGO_BIN_EXE_scanrig"))
}

/// A rig file derived from the shipped `base` (a path inside the repository) with textual
/// replacements (each must match), written to `dir/rig.toml`.
pub fn derived_rig(dir: &Path, base: &str, replace: &[(&str, &str)]) -> PathBuf {
    let mut text = std::fs::read_to_string(repo(base)).expect("shipped rig readable");
    for (from, to) in replace {
        assert!(text.contains(from), "{base} has no `{from}`");
        text = text.replacen(from, to, 1);
    }
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).expect("write rig");
    path
}

/// Run `scanrig scan --rig RIG --out OUT`, which must succeed, and return its report.json.
pub fn run_scan(rig: &Path, out: &Path) -> serde_json::Value {
    let output = scanrig().args(["scan", "--rig"]).arg(rig).arg("--out").arg(out).output().expect("run scanrig");
    assert!(
        output.status.success(),
        "scan failed:\nstdout: {}\nstderr: {}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&std::fs::read(out.join("report.json")).expect("report.json written"))
        .expect("report.json is JSON")
}

/// `report[section][key]` as a number; panics naming it when absent.
pub fn num(report: &serde_json::Value, section: &str, key: &str) -> f64 {
    report[section][key].as_f64().unwrap_or_else(|| panic!("{section}.{key} missing in {report}"))
}

/// A rig file derived from the rig file at `base` (any path) with textual replacements (each must
/// match), written to `dir/rig.toml`.
pub fn derived_rig_from(base: &Path, dir: &Path, replace: &[(&str, &str)]) -> PathBuf {
    let mut text = std::fs::read_to_string(base).expect("rig readable");
    for (from, to) in replace {
        assert!(text.contains(from), "{} has no `{from}`", base.display());
        text = text.replacen(from, to, 1);
    }
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).expect("write rig");
    path
}
