//! The calibration workflow through the real `scanrig` binary on the shipped simulated rig
//! (`config/rigs/calibrate-sim.toml`): camera intrinsics from captured board views (also re-read
//! from a directory with bad images that must be rejected with a reason), the turntable axis, the
//! lights, and a rig file pointing at the resulting calibration file.

use std::path::{Path, PathBuf};
use std::process::Command;

use scanrig::calibration::file::CalibrationFile;
use scanrig::geometry::Vector3;
use scanrig::rigfile;

fn rig_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rigs/calibrate-sim.toml")
}

fn scanrig(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_scanrig")).args(args).output().expect("run scanrig");
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    (out.status.success(), text)
}

#[test]
fn calibrate_camera_turntable_and_lights_through_the_cli() {
    let dir = tempfile::tempdir().expect("tempdir");
    let calib = dir.path().join("calib.toml");
    let views = dir.path().join("views");
    let (c, r, v) = (calib.to_str().expect("utf-8"), rig_path(), views.to_str().expect("utf-8"));
    let r = r.to_str().expect("utf-8");
    let truth = rigfile::load(&rig_path()).expect("shipped rig").camera.model();

    // Camera, captured from the simulated rig.
    let (ok, text) = scanrig(&[
        "calibrate",
        "camera",
        "--rig",
        r,
        "--views",
        "12",
        "--board",
        "9x6",
        "--square-mm",
        "20",
        "--out",
        c,
        "--save-images",
        v,
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("view_00.png: re-projection RMS"), "{text}");
    let cam = CalibrationFile::load(&calib).expect("written").camera.expect("[camera]");
    let t = truth.intrinsics;
    for (name, got, want) in
        [("fx", cam.fx_px, t.fx), ("fy", cam.fy_px, t.fy), ("cx", cam.cx_px, t.cx), ("cy", cam.cy_px, t.cy)]
    {
        assert!(((got - want) / want).abs() < 0.005, "{name}: {got} vs {want}\n{text}");
    }
    assert!(cam.rms_px < 0.3, "{text}");

    // The saved views again from disk, with an empty frame and a cut-off board among them.
    image::GrayImage::from_pixel(640, 480, image::Luma([90])).save(views.join("blank.png")).expect("blank");
    let first = image::open(views.join("view_00.png")).expect("view").to_luma8();
    let mut cut = first.clone();
    for (x, _, p) in cut.enumerate_pixels_mut() {
        if x > 330 {
            *p = image::Luma([77]);
        }
    }
    cut.save(views.join("cut.png")).expect("cut");
    let c2 = dir.path().join("from-images.toml");
    let (ok, text) = scanrig(&[
        "calibrate",
        "camera",
        "--images",
        v,
        "--board",
        "9x6",
        "--square-mm",
        "20",
        "--out",
        c2.to_str().expect("utf-8"),
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("blank.png: rejected: no chessboard found"), "{text}");
    assert!(text.contains("cut.png: rejected: partial board"), "{text}");
    assert!(text.contains("over 12 of 14 images"), "{text}");

    // Turntable, with the intrinsics just calibrated.
    let (ok, text) = scanrig(&[
        "calibrate",
        "turntable",
        "--rig",
        r,
        "--views",
        "6",
        "--board",
        "9x6",
        "--square-mm",
        "20",
        "--out",
        c,
    ]);
    assert!(ok, "{text}");
    assert!(text.contains(&format!("intrinsics from {c}")), "{text}");
    let file = CalibrationFile::load(&calib).expect("updated");
    assert!(file.camera.is_some(), "the camera section is kept");
    let tt = file.turntable.expect("[turntable]");
    let axis_truth = truth.pose.rotation * Vector3::z();
    let axis_err = Vector3::from(tt.axis_camera).angle(&axis_truth).to_degrees();
    assert!(axis_err < 0.5, "axis error {axis_err} deg\n{text}");
    let centre_err = (tt.camera_pose().centre() - truth.centre()).norm();
    assert!(centre_err < 0.003, "camera centre error {centre_err} m\n{text}");

    // The same turntable views saved and read back from disk (angles from the names).
    let table = dir.path().join("table");
    let tv = table.to_str().expect("utf-8");
    let c3 = dir.path().join("table.toml");
    let (ok, text) = scanrig(&[
        "calibrate",
        "turntable",
        "--rig",
        r,
        "--views",
        "6",
        "--board",
        "9x6",
        "--square-mm",
        "20",
        "--out",
        c3.to_str().expect("utf-8"),
        "--intrinsics",
        c,
        "--save-images",
        tv,
    ]);
    assert!(ok, "{text}");
    std::fs::copy(table.join("angle_0.png"), table.join("no-angle.png")).expect("copy");
    let (ok, text) = scanrig(&[
        "calibrate",
        "turntable",
        "--images",
        tv,
        "--board",
        "9x6",
        "--square-mm",
        "20",
        "--out",
        c3.to_str().expect("utf-8"),
        "--intrinsics",
        c,
    ]);
    assert!(ok, "{text}");
    assert!(text.contains("no-angle.png: rejected: no table angle in the name"), "{text}");
    assert!(text.contains("angle_180.png: re-projection RMS"), "{text}");
    let from_disk = CalibrationFile::load(&c3).expect("written").turntable.expect("[turntable]");
    assert!(Vector3::from(from_disk.axis_camera).angle(&axis_truth).to_degrees() < 0.5, "{text}");

    // Lights, from a start 7 cm off.
    let (ok, text) =
        scanrig(&["calibrate", "lights", "--rig", r, "--views", "4", "--start-offset-mm", "40,-30,50", "--out", c]);
    assert!(ok, "{text}");
    let file = CalibrationFile::load(&calib).expect("updated");
    let rig = rigfile::load(&rig_path()).expect("rig");
    let nominal = &rig.lights.as_ref().expect("lights").lights;
    assert_eq!(file.lights.len(), nominal.len());
    for l in &file.lights {
        let err = (Vector3::from(l.position_m) - Vector3::from(nominal[l.index].position_m)).norm();
        assert!(err < 0.005, "light {}: {err} m\n{text}", l.index);
    }

    // A rig file pointing at the calibration file takes its camera and lights.
    let text = std::fs::read_to_string(rig_path()).expect("rig text");
    let with_calib = text.replacen("[rig]\n", "[rig]\ncalibration = \"calib.toml\"\n", 1);
    let rig_file = dir.path().join("rig.toml");
    std::fs::write(&rig_file, &with_calib).expect("rig file");
    let (ok, out) = scanrig(&["validate", "--rig", rig_file.to_str().expect("utf-8")]);
    assert!(ok, "{out}");
    let loaded = rigfile::load(&rig_file).expect("rig with calibration");
    let model = loaded.camera.model();
    assert_eq!(model.intrinsics.fx, cam.fx_px);
    assert!((model.centre() - truth.centre()).norm() < 0.003);
    let l0 = loaded.lights.as_ref().expect("lights").lights[0].position_m;
    assert_eq!(l0, file.lights[0].position_m);

    // A broken calibration file is reported with both files and lines.
    let broken = std::fs::read_to_string(&calib).expect("calib").replacen("fx_px = ", "fx_px = -", 1);
    std::fs::write(&calib, broken).expect("write");
    let (ok, out) = scanrig(&["validate", "--rig", rig_file.to_str().expect("utf-8")]);
    assert!(!ok);
    let line = with_calib.lines().position(|l| l.starts_with("calibration =")).expect("key") + 1;
    assert!(out.contains(&format!("rig.toml:{line}: `rig.calibration`: cannot use the calibration file")), "{out}");
    assert!(out.contains("calib.toml:9: `camera.fx_px`"), "{out}");
    assert!(out.contains("`camera.fx_px`: must be a positive number of pixels"), "{out}");
}
