//! The Kinect v1 driver through the real libfreenect API under fakenect (Debian `libfreenect-bin`):
//! the simulated depth camera's view is recorded in fakenect's format (raw 11-bit disparity, as the
//! device encodes it), and a depth-fusion scan with `kind = "freenect"` runs through the real binary
//! under the package's `fakenect` wrapper. The model it fuses is compared with the one the simulated
//! depth camera gives in the same rig.
//!
//! The scene is the simulated sphere on the turntable axis: every turntable angle shows it the same,
//! so one recorded view replayed in a loop is the right view at every position (fakenect replays at
//! the recorded pace, independent of the turntable).

#![cfg(feature = "freenect")]

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use scanrig::devices::depth::kinect::{disparity_to_m, m_to_disparity, write_fakenect_recording};

const RIG: &str = r#"
[rig]
name = "kinect-sphere"
description = "A Kinect-sized depth camera over the simulated sphere on a turntable"

[turntable]
kind = "sim"
real_time = false

[camera]
kind = "sim"
width = 64
height = 48

[camera.calibration.intrinsics]
fx = 80.0
fy = 80.0
cx = 32.0
cy = 24.0

[camera.calibration.pose]
eye_m = [0.0, -0.45, 0.20]
target_m = [0.0, 0.0, 0.035]

DEPTH_CAMERA

[depth_camera.calibration.intrinsics]
fx = 1200.0
fy = 1200.0
cx = 320.0
cy = 240.0

[depth_camera.calibration.pose]
eye_m = [0.0, -0.1197, 0.3639]
target_m = [0.0, 0.0, 0.035]

[sim]
scene = "sphere"

[scan]
positions = 8
settle_ms = 0

[reconstruction]
method = "depth-fusion"
bbox_min_m = [-0.045, -0.045, 0.0]
bbox_max_m = [0.045, 0.045, 0.09]
resolution = 64

[reconstruction.depth_fusion]
truncation_voxels = 3.0
missing_is_free = true
"#;

const SIM_DEPTH: &str = "[depth_camera]\nkind = \"sim\"\nwidth = 640\nheight = 480";
const FREENECT_DEPTH: &str = "[depth_camera]\nkind = \"freenect\"\ndepth_format = \"disparity\"";

fn ground_truth(out: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(out.join("report.json")).expect("report.json");
    let report: serde_json::Value = serde_json::from_str(&text).expect("report");
    report["ground_truth"].clone()
}

fn figure(gt: &serde_json::Value, key: &str) -> f64 {
    gt[key].as_f64().unwrap_or_else(|| panic!("no ground_truth.{key} in {gt}"))
}

#[test]
fn a_scan_under_fakenect_fuses_the_model_the_simulated_depth_camera_gives() {
    let dir = tempfile::tempdir().expect("tempdir");
    let sim_rig = dir.path().join("sim.toml");
    std::fs::write(&sim_rig, RIG.replace("DEPTH_CAMERA", SIM_DEPTH)).expect("write");
    let kinect_rig = dir.path().join("kinect.toml");
    std::fs::write(&kinect_rig, RIG.replace("DEPTH_CAMERA", FREENECT_DEPTH)).expect("write");

    // The simulated depth camera's view at angle 0, recorded as the Kinect would send it.
    let config = scanrig::rigfile::load(&sim_rig).expect("sim rig");
    let mut rig = scanrig::devices::build_rig(&config).expect("sim devices");
    let depth = rig.depth_camera.as_mut().expect("depth camera").capture_depth(Duration::from_secs(5)).expect("depth");
    assert_eq!((depth.width, depth.height), (640, 480));
    let measured = depth.depth_m.iter().filter(|&&z| z > 0.0).count();
    assert!(measured > 10_000, "the sphere fills part of the view: {measured} pixels");
    // Worst-case depth error of the 11-bit encoding over this view (half a disparity step).
    let worst = depth
        .depth_m
        .iter()
        .filter(|&&z| z > 0.0)
        .map(|&z| (disparity_to_m(m_to_disparity(z)) - z).abs())
        .fold(0.0f32, f32::max);
    let recording = dir.path().join("recording");
    // 30 frames/s for 40 s, the one view linked again each frame.
    write_fakenect_recording(&recording, &[(640, 480, &depth.depth_m)], 1.0 / 30.0, 1200).expect("recording");
    drop(rig);

    let scan = |rig: &Path, out: &Path, fakenect: bool| {
        let mut c = if fakenect {
            let mut c = Command::new("fakenect");
            c.arg(&recording).arg(env!("CARGO_BIN_EXE_scanrig"));
            c
        } else {
            Command::new(env!("CARGO_BIN_EXE_scanrig"))
        };
        c.args(["scan", "--rig"]).arg(rig).arg("--out").arg(out);
        let run = c.output().unwrap_or_else(|e| panic!("cannot run (fakenect is in Debian libfreenect-bin): {e}"));
        let log = String::from_utf8_lossy(&run.stderr).into_owned();
        assert!(run.status.success(), "scan failed:\n{log}");
        log
    };
    let sim_out = dir.path().join("sim");
    scan(&sim_rig, &sim_out, false);
    let kinect_out = dir.path().join("kinect");
    let log = scan(&kinect_rig, &kinect_out, true);

    // The Kinect scan really went through libfreenect's depth files: 8 depth maps on disk.
    for p in 0..8 {
        assert!(kinect_out.join(format!("frames/pos_{p:03}_depth.png")).is_file(), "depth map {p}:\n{log}");
    }
    let (a, b) = (ground_truth(&sim_out), ground_truth(&kinect_out));
    println!("11-bit encoding: worst depth error {:.3} mm over {measured} pixels", worst * 1e3);
    println!("simulated depth camera: {a}");
    println!("Kinect under fakenect:  {b}");
    for key in ["iou", "containment"] {
        let (x, y) = (figure(&a, key), figure(&b, key));
        assert!(x > 0.8, "the simulated scan itself must be good: {key} {x}");
        assert!((x - y).abs() < 0.02, "{key}: simulated {x}, Kinect under fakenect {y}");
    }
    let (x, y) = (figure(&a, "chamfer_m"), figure(&b, "chamfer_m"));
    assert!((x - y).abs() < 1e-4, "Chamfer distance: simulated {x} m, Kinect under fakenect {y} m");
}
