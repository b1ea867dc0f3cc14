//! `scanrig reconstruct` through the real binary on the attributed Middlebury dino fixture
//! (calibration + the recipe masks of the 15 good views), and its errors on malformed inputs.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const TIGHT_BOX: &str = "-0.061897,-0.018874,-0.057845,0.010897,0.068227,0.015495";

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dino")
}

fn reconstruct(dataset: &Path, extra: &[&str], out: &Path) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_scanrig"));
    cmd.arg("reconstruct").arg("--dataset").arg(dataset).arg("--out").arg(out);
    cmd.args(extra);
    cmd.output().expect("run scanrig")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A copy of the fixture in a temp dir, with the par file rewritten by `edit`.
fn edited_fixture(dir: &Path, edit: impl Fn(&str) -> String) -> PathBuf {
    let data = dir.join("data");
    std::fs::create_dir_all(data.join("masks")).expect("mkdir");
    let par = std::fs::read_to_string(fixture().join("dinoSR_par.txt")).expect("par");
    std::fs::write(data.join("dinoSR_par.txt"), edit(&par)).expect("write par");
    for entry in std::fs::read_dir(fixture().join("masks")).expect("masks") {
        let entry = entry.expect("entry");
        std::fs::copy(entry.path(), data.join("masks").join(entry.file_name())).expect("copy mask");
    }
    data
}

#[test]
fn dino_at_256_matches_the_reference_and_writes_every_output() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    let views = fixture().join("dinoSR_good_silhouette_images.txt");
    let masks = fixture().join("masks");
    let o = reconstruct(
        &fixture(),
        &[
            "--method",
            "space-carving",
            "--resolution",
            "256",
            "--bbox",
            TIGHT_BOX,
            "--views",
            views.to_str().expect("utf-8"),
            "--masks",
            masks.to_str().expect("utf-8"),
        ],
        &out,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).expect("report")).expect("json");
    assert_eq!(report["resolution"], serde_json::json!([214, 256, 216]));
    assert_eq!(report["views"], 15);
    let occupied = report["occupied_voxels"].as_f64().expect("count");
    // The data set's reference figure for this grid and voxel test.
    assert!((occupied - 2_999_881.0).abs() <= 0.01 * 2_999_881.0, "occupied {occupied}");
    let ious: Vec<f64> =
        report["reprojection_iou"].as_array().expect("list").iter().filter_map(|v| v.as_f64()).collect();
    assert_eq!(ious.len(), 15);
    let mean = ious.iter().sum::<f64>() / 15.0;
    assert!(mean >= 0.97, "mean re-projection IoU {mean}");
    for f in ["model.ply", "model.stl", "model.obj", "voxels.ply"] {
        assert!(std::fs::metadata(out.join(f)).map(|m| m.len() > 0).unwrap_or(false), "{f}");
    }
}

#[test]
fn a_comma_separated_view_list_selects_views() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    let masks = fixture().join("masks");
    let o = reconstruct(
        &fixture(),
        &[
            "--resolution",
            "32",
            "--bbox",
            TIGHT_BOX,
            "--views",
            "dinoSR0001.png,dinoSR0005.png,dinoSR0009.png",
            "--masks",
            masks.to_str().expect("utf-8"),
        ],
        &out,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).expect("report")).expect("json");
    assert_eq!(report["views"], 3);
}

#[test]
fn malformed_inputs_name_the_file_and_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let masks_arg = |data: &Path| data.join("masks").to_str().expect("utf-8").to_owned();
    let views_arg = fixture().join("dinoSR_good_silhouette_images.txt").to_str().expect("utf-8").to_owned();

    // A value missing on line 3 (the second view).
    let sub = dir.path().join("short");
    let data = edited_fixture(&sub, |par| {
        let mut lines: Vec<String> = par.lines().map(str::to_owned).collect();
        let mut tokens: Vec<&str> = lines[2].split_whitespace().collect();
        tokens.pop();
        lines[2] = tokens.join(" ");
        lines.join("\n")
    });
    let o =
        reconstruct(&data, &["--resolution", "32", "--bbox", TIGHT_BOX, "--masks", &masks_arg(&data)], &sub.join("o"));
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("dinoSR_par.txt:3") && e.contains("expected"), "{e}");
    assert!(!sub.join("o/report.json").exists());

    // A non-finite number.
    let sub = dir.path().join("nan");
    let data = edited_fixture(&sub, |par| {
        let mut lines: Vec<String> = par.lines().map(str::to_owned).collect();
        let mut tokens: Vec<String> = lines[4].split_whitespace().map(str::to_owned).collect();
        tokens[5] = "inf".into();
        lines[4] = tokens.join(" ");
        lines.join("\n")
    });
    let o =
        reconstruct(&data, &["--resolution", "32", "--bbox", TIGHT_BOX, "--masks", &masks_arg(&data)], &sub.join("o"));
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("dinoSR_par.txt:5"), "{e}");

    // A declared count that does not match the views listed.
    let sub = dir.path().join("count");
    let data = edited_fixture(&sub, |par| {
        let mut lines: Vec<String> = par.lines().map(str::to_owned).collect();
        lines[0] = "17".into();
        lines.join("\n")
    });
    let o =
        reconstruct(&data, &["--resolution", "32", "--bbox", TIGHT_BOX, "--masks", &masks_arg(&data)], &sub.join("o"));
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("dinoSR_par.txt") && e.contains("17"), "{e}");

    // A missing mask (the images are not in the fixture, so masks stand in for them here).
    let sub = dir.path().join("missing");
    let data = edited_fixture(&sub, |par| par.to_owned());
    std::fs::remove_file(data.join("masks/dinoSR0004.png")).expect("remove");
    let o = reconstruct(
        &data,
        &["--resolution", "32", "--bbox", TIGHT_BOX, "--views", &views_arg, "--masks", &masks_arg(&data)],
        &sub.join("o"),
    );
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("dinoSR0004.png"), "{e}");

    // Missing images when silhouettes are to be extracted from them.
    let o = reconstruct(&data, &["--resolution", "32", "--bbox", TIGHT_BOX], &sub.join("o2"));
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("dinoSR_par.txt:") && e.contains("does not exist"), "{e}");

    // A box that misses the object (millimetres given as metres).
    let o = reconstruct(
        &data,
        &[
            "--resolution",
            "32",
            "--bbox",
            "10,10,10,11,11,11",
            "--views",
            &views_arg,
            "--masks",
            &masks_arg(&fixture()),
        ],
        &sub.join("o3"),
    );
    let e = stderr(&o);
    assert!(!o.status.success());
    assert!(e.contains("the box misses the object"), "{e}");

    // Bad arguments.
    let o = reconstruct(&data, &["--resolution", "32", "--bbox", "1,2,3"], &sub.join("o4"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--bbox"), "{}", stderr(&o));
    let o = reconstruct(&data, &["--resolution", "32", "--silhouette", "threshold=2"], &sub.join("o5"));
    assert!(!o.status.success());
    assert!(stderr(&o).contains("threshold"), "{}", stderr(&o));
}
