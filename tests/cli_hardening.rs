//! The `scanrig` CLI on inputs that must be refused clearly: `scan --out` into an existing result,
//! and a data set whose image is a device (`/dev/zero`).

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Run `scanrig args...`, killed after `limit`.
fn scanrig(args: &[&std::ffi::OsStr], limit: Duration) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(args)
        .stdin(Stdio::null())
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

fn os(s: &str) -> &std::ffi::OsStr {
    std::ffi::OsStr::new(s)
}

#[test]
fn scan_into_an_existing_result_is_refused_unless_forced() {
    let dir = tempfile::tempdir().expect("tempdir");
    let base =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml")).expect("rig");
    let rig = dir.path().join("rig.toml");
    std::fs::write(
        &rig,
        base.replacen("positions = 24", "positions = 4", 1).replacen("resolution = 128", "resolution = 24", 1),
    )
    .expect("write rig");
    let out = dir.path().join("out");
    std::fs::create_dir_all(&out).expect("mkdir");
    std::fs::write(out.join("report.json"), b"{\"earlier\": true}").expect("report");
    let args = [os("scan"), os("--rig"), rig.as_os_str(), os("--out"), out.as_os_str()];
    let o = scanrig(&args, Duration::from_secs(120));
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("--force") && stderr.contains("report.json"), "{stderr}");
    assert_eq!(std::fs::read(out.join("report.json")).expect("report"), b"{\"earlier\": true}");

    let mut forced = args.to_vec();
    forced.push(os("--force"));
    let o = scanrig(&forced, Duration::from_secs(300));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).expect("report")).expect("json");
    assert!(report.get("earlier").is_none() && report["views"] == 4, "{report}");
}

#[test]
fn a_device_as_an_image_is_named_as_not_a_regular_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    // One Middlebury-style view whose image is a link to /dev/zero.
    std::fs::write(d.join("set_par.txt"), "1\nzero.png 1000 0 320 0 1000 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n")
        .expect("par");
    std::os::unix::fs::symlink("/dev/zero", d.join("zero.png")).expect("symlink");
    let o = scanrig(
        &[
            os("reconstruct"),
            os("--dataset"),
            d.as_os_str(),
            os("--resolution"),
            os("16"),
            os("--bbox"),
            os("-0.1,-0.1,0.9,0.1,0.1,1.1"),
            os("--out"),
            d.join("out").as_os_str(),
        ],
        Duration::from_secs(60),
    );
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("not a regular file") && stderr.contains("a device"), "{stderr}");
    assert!(!stderr.contains("does not exist"), "{stderr}");
}

#[test]
fn validate_names_every_unknown_key_and_a_misspelled_section_with_lines_and_refuses_a_huge_grid() {
    let dir = tempfile::tempdir().expect("tempdir");
    let base =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/simulated.toml")).expect("rig");
    let text = base.replacen("[scan]\n", "[scan]\npositons = 3\nstart_degs = 1.0\n", 1).replacen(
        "[reconstruction]\n",
        "[reconstuction]\n",
        1,
    );
    let rig = dir.path().join("rig.toml");
    std::fs::write(&rig, &text).expect("write");
    let line_of = |needle: &str| text.lines().position(|l| l.starts_with(needle)).expect("needle") + 1;
    let o = scanrig(&[os("validate"), os("--rig"), rig.as_os_str()], Duration::from_secs(30));
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    for (key, line) in [
        ("scan.positons", line_of("positons")),
        ("scan.start_degs", line_of("start_degs")),
        ("reconstuction", line_of("[reconstuction]")),
    ] {
        assert!(stderr.contains(&format!("line {line}: `{key}`")), "{key} at line {line}: {stderr}");
    }

    std::fs::write(&rig, base.replacen("resolution = 128", "resolution = 4096", 1)).expect("write");
    let o = scanrig(&[os("validate"), os("--rig"), rig.as_os_str()], Duration::from_secs(30));
    assert!(!o.status.success());
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(stderr.contains("resolution 4096 needs about") && stderr.contains("memory_budget_mb"), "{stderr}");
}
