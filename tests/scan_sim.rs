//! End-to-end: the real `scanrig` binary scans the simulated rig and writes its results; the report
//! is checked against the simulated ground truth.

mod scan_common;

use scan_common::{derived_rig, repo, run_scan, scanrig};

fn gt(report: &serde_json::Value, key: &str) -> f64 {
    report["ground_truth"][key].as_f64().unwrap_or_else(|| panic!("ground_truth.{key} missing in {report}"))
}

/// 24 views at 128^3 on each solid: the visual hull contains the object; a convex solid is
/// recovered closely, the cup's pit is not (the gap shadow carving will close).
#[test]
fn simulated_scans_meet_the_visual_hull_bounds() {
    let mut ious = std::collections::BTreeMap::new();
    for (scene, base) in [
        ("sphere", "config/rigs/sim-sphere.toml"),
        ("box", "config/rigs/sim-box.toml"),
        ("cup", "config/rigs/simulated.toml"),
        ("textured-box", "config/rigs/sim-textured.toml"),
        ("pit-block", "config/rigs/sim-pit-block.toml"),
    ] {
        let dir = tempfile::tempdir().expect("tempdir");
        let rig = derived_rig(dir.path(), base, &[]);
        let out = dir.path().join("out");
        let report = run_scan(&rig, &out);
        assert_eq!(report["views"], 24, "{scene}");
        assert_eq!(report["method"], "space-carving");
        let res = report["resolution"].as_array().expect("resolution");
        assert_eq!(res.iter().filter_map(|v| v.as_u64()).max(), Some(128), "{scene}: {res:?}");
        let containment = gt(&report, "containment");
        assert!(containment >= 0.995, "{scene}: containment {containment} < 0.995");
        ious.insert(scene, gt(&report, "iou"));
        for f in ["model.ply", "model.stl", "model.obj", "voxels.ply", "frames/pos_000.png", "frames/pos_023.png"] {
            let len = std::fs::metadata(out.join(f)).map(|m| m.len()).unwrap_or(0);
            assert!(len > 0, "{scene}: {f} missing or empty");
        }
        let t = &report["timings_s"];
        for stage in ["capture", "silhouette", "carve", "mesh", "total"] {
            assert!(t[stage].as_f64().is_some_and(|v| v >= 0.0), "{scene}: timings_s.{stage} missing");
        }
    }
    // The convex solid is recovered closely.
    assert!(ious["sphere"] >= 0.90, "sphere: IoU {} < 0.90", ious["sphere"]);
    // Boxes are convex too, but a ring of 24 perspective views at one elevation leaves slivers
    // beside every face and a shallow roof over the top that no silhouette removes: the visual
    // hull of a box is looser than that of a sphere (about 0.89 here).
    for boxy in ["box", "textured-box"] {
        assert!(ious[boxy] >= 0.85, "{boxy}: IoU {} < 0.85", ious[boxy]);
    }
    assert!(
        ious["cup"] < 0.7 && ious["cup"] < ious["sphere"] && ious["cup"] < ious["box"],
        "the cup's pit should not be recovered: {ious:?}"
    );
    assert!(ious["pit-block"] < ious["box"], "the block's pit should not be recovered: {ious:?}");
}

#[test]
fn bad_rig_files_fail_clearly_and_write_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cases: &[(&[(&str, &str)], &str)] = &[
        (&[("positions = 24", "positions = 24\nspeed = 3")], "unknown field `speed`"),
        (&[("kind = \"sim\"", "kind = \"stepper-9000\"")], "stepper-9000"),
        (&[("resolution = 128", "resolution = 0")], "reconstruction.resolution"),
    ];
    for (i, (replace, expected)) in cases.iter().enumerate() {
        let sub = dir.path().join(format!("case{i}"));
        std::fs::create_dir_all(&sub).expect("mkdir");
        let rig = derived_rig(&sub, "config/rigs/simulated.toml", replace);
        let out = sub.join("out");
        let output = scanrig().args(["scan", "--rig"]).arg(&rig).arg("--out").arg(&out).output().expect("run");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "case {i} should fail");
        assert!(stderr.contains(expected), "case {i}: expected `{expected}` in: {stderr}");
        assert!(stderr.contains("rig.toml:"), "case {i}: the file and line should be named: {stderr}");
        assert!(!out.join("report.json").exists(), "case {i}: no result may be written");
    }
}

#[test]
fn unwritable_output_directory_is_a_clear_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let blocker = dir.path().join("a-file");
    std::fs::write(&blocker, b"not a directory").expect("write");
    let out = blocker.join("out");
    let output = scanrig()
        .args(["scan", "--rig"])
        .arg(repo("config/rigs/simulated.toml"))
        .arg("--out")
        .arg(&out)
        .output()
        .expect("run");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(stderr.contains("output directory") && stderr.contains("a-file"), "{stderr}");
}

#[test]
fn missing_rig_file_is_named() {
    let output = scanrig().args(["scan", "--rig", "no/such/rig.toml", "--out", "unused"]).output().expect("run");
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(stderr.contains("no/such/rig.toml"), "{stderr}");
}

/// Keep only the first `n` `[[lights.light]]` blocks of a rig file.
fn keep_lights(text: &str, n: usize) -> String {
    let mut parts = text.split("[[lights.light]]");
    let mut out = parts.next().unwrap_or_default().to_owned();
    for (i, block) in parts.enumerate() {
        if i < n {
            out.push_str("[[lights.light]]");
            out.push_str(block);
        } else {
            // Drop the light's own keys (up to the next blank line) but keep what follows it.
            let rest = block.split_once("\n\n").map_or("", |(_, r)| r);
            out.push_str("\n\n");
            out.push_str(rest);
        }
    }
    out
}

/// The whole scan through the real serial code path (a firmware emulator on a pseudo-terminal,
/// for each dialect) gives the same reconstruction as the directly simulated turntable. The field
/// dialects' boards have fewer white lights (Horus none, FabScan one LED ring), so each comparison
/// uses the lights its board has.
#[test]
fn serial_scans_reconstruct_exactly_like_direct_ones() {
    let serial_base = std::fs::read_to_string(repo("config/rigs/sim-serial.toml")).expect("sim-serial");
    let direct_base = std::fs::read_to_string(repo("config/rigs/simulated.toml")).expect("simulated");
    for (dialect, lights, plan) in
        [("scanrig", 4, "lights = [0, 1, 2, 3]"), ("horus", 0, "lights = []"), ("fabscan", 1, "lights = [0]")]
    {
        let dir = tempfile::tempdir().expect("tempdir");
        let serial = keep_lights(&serial_base, lights)
            .replace("port = \"emulator:scanrig\"", &format!("port = \"emulator:{dialect}\""))
            .replace("dialect = \"scanrig\"", &format!("dialect = \"{dialect}\"\nlasers = 1"))
            .replace("lights = [0, 1, 2, 3]", plan);
        let direct = direct_base.replace("lights = [0, 1, 2, 3]", plan);
        std::fs::write(dir.path().join("serial.toml"), serial).expect("write");
        std::fs::write(dir.path().join("direct.toml"), direct).expect("write");
        let a = run_scan(&dir.path().join("serial.toml"), &dir.path().join("serial-out"));
        let b = run_scan(&dir.path().join("direct.toml"), &dir.path().join("direct-out"));
        assert_eq!(a["views"], 24, "{dialect}");
        assert_eq!(a["occupied_voxels"], b["occupied_voxels"], "{dialect}: serial and direct scans differ");
        assert_eq!(gt(&a, "iou"), gt(&b, "iou"), "{dialect}");
        assert_eq!(gt(&a, "containment"), gt(&b, "containment"), "{dialect}");
        // Same frames, byte for byte.
        for pos in [0, 7, 23] {
            let f = format!("frames/pos_{pos:03}.png");
            let fa = std::fs::read(dir.path().join("serial-out").join(&f)).expect("frame");
            let fb = std::fs::read(dir.path().join("direct-out").join(&f)).expect("frame");
            assert!(fa == fb, "{dialect}: {f} differs");
        }
    }
}
