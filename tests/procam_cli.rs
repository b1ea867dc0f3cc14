//! `scanrig calibrate projector` through the real binary on simulated Gray-code captures of a
//! chessboard written to disk (the small real fixture crop does not contain the whole board).

use std::path::Path;
use std::process::Command;

use nalgebra::{Matrix3, Rotation3, Vector3};
use scanrig::calibration::procam::rotation_difference_deg;
use scanrig::calibration::procam_file::read_procam_file;
use scanrig::calibration::procam_sim::SimProcam;
use scanrig::geometry::{CameraModel, Intrinsics, Pose};
use scanrig::pipeline::structured_light::GrayCodePatterns;
use scanrig::sim::chessboard::ChessboardTarget;

fn target() -> ChessboardTarget {
    ChessboardTarget { cols: 9, rows: 6, square_m: 0.025, border_m: 0.02, dark: 0.08, light: 0.9 }
}

fn sim() -> SimProcam {
    SimProcam {
        camera: CameraModel {
            width: 640,
            height: 480,
            intrinsics: Intrinsics {
                fx: 800.0,
                fy: 792.0,
                cx: 323.5,
                cy: 236.0,
                skew: 0.0,
                k1: -0.12,
                k2: 0.05,
                ..Intrinsics::default()
            },
            pose: Pose { rotation: Matrix3::identity(), translation: Vector3::zeros() },
        },
        projector: CameraModel {
            width: 320,
            height: 240,
            intrinsics: Intrinsics {
                fx: 420.0,
                fy: 415.0,
                cx: 166.0,
                cy: 131.5,
                skew: 0.0,
                k1: -0.06,
                k2: 0.02,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(
                Vector3::new(0.12, -0.02, 0.0),
                Vector3::new(0.0, 0.0, 0.6),
                Vector3::new(0.0, -1.0, 0.0),
            ),
        },
        target: target(),
        ambient: 0.1,
        projector_intensity: 0.85,
        background: 0.3,
        noise_sigma: 1.0,
        seed: 5,
        supersample: 2,
    }
}

/// Board -> rig (= camera) pose: the board's middle at `centre`, tilted by the angles (degrees).
fn pose(ax: f64, ay: f64, az: f64, centre: Vector3<f64>) -> Pose {
    let t = target();
    let r = Rotation3::from_euler_angles(ax.to_radians(), ay.to_radians(), az.to_radians()).into_inner();
    let mid = Vector3::new((t.cols - 1) as f64 * t.square_m / 2.0, (t.rows - 1) as f64 * t.square_m / 2.0, 0.0);
    Pose { rotation: r, translation: centre - r * mid }
}

fn write_capture(sim: &SimProcam, p: &Pose, k: u64, dir: &Path) {
    std::fs::create_dir_all(dir).expect("mkdir");
    let patterns = GrayCodePatterns::new(sim.projector.width, sim.projector.height).expect("patterns");
    let frames = sim.render_sequence(p, &patterns, k).expect("render");
    for (i, f) in frames.into_iter().enumerate() {
        let img = image::GrayImage::from_raw(sim.camera.width, sim.camera.height, f).expect("frame");
        img.save(dir.join(format!("graycode_{i:02}.png"))).expect("png");
    }
}

#[test]
fn calibrate_projector_cli_on_simulated_captures() {
    let sim = sim();
    let tmp = tempfile::tempdir().expect("tempdir");
    let v = Vector3::new;
    let poses = [
        pose(25.0, 0.0, 0.0, v(0.0, 0.0, 0.55)),
        pose(-25.0, 5.0, 3.0, v(0.02, 0.01, 0.5)),
        pose(0.0, 28.0, -4.0, v(-0.03, 0.0, 0.55)),
        pose(5.0, -30.0, 6.0, v(0.03, -0.02, 0.6)),
        pose(20.0, 20.0, 10.0, v(-0.06, -0.04, 0.6)),
        pose(-20.0, -20.0, -10.0, v(0.06, 0.04, 0.6)),
    ];
    let mut args: Vec<String> = vec!["calibrate".into(), "projector".into(), "--captures".into()];
    for (k, p) in poses.iter().enumerate() {
        let d = tmp.path().join(format!("capture_{k}"));
        write_capture(&sim, p, k as u64, &d);
        args.push(d.display().to_string());
    }
    let out = tmp.path().join("procam.toml");
    args.extend(
        ["--board", "9x6", "--square-mm", "25", "--projector", "320x240", "--out"].iter().map(|s| s.to_string()),
    );
    args.push(out.display().to_string());
    let run = Command::new(env!("CARGO_BIN_EXE_scanrig")).args(&args).output().expect("run scanrig");
    let stdout = String::from_utf8_lossy(&run.stdout);
    println!("{stdout}{}", String::from_utf8_lossy(&run.stderr));
    assert!(run.status.success());
    assert!(stdout.contains("re-projection RMS: camera"), "{stdout}");
    let f = read_procam_file(&out).expect("calibration file");
    let (ct, pt) = (sim.camera.intrinsics, sim.projector.intrinsics);
    for (name, got, want) in [
        ("camera fx", f.camera.fx, ct.fx),
        ("camera fy", f.camera.fy, ct.fy),
        ("projector fx", f.projector.fx, pt.fx),
        ("projector fy", f.projector.fy, pt.fy),
        ("projector cx", f.projector.cx, pt.cx),
        ("projector cy", f.projector.cy, pt.cy),
    ] {
        assert!(((got - want) / want).abs() < 0.01, "{name}: {got} vs {want}");
    }
    let r = Matrix3::from_row_slice(&f.rotation.concat());
    let truth = sim.projector.pose;
    let dr = rotation_difference_deg(&r, &truth.rotation);
    let dt = (Vector3::from(f.translation) - truth.translation).norm() / truth.translation.norm();
    assert!(dr < 0.3 && dt < 0.02, "rotation {dr} deg, translation {}%", 100.0 * dt);
    assert_eq!((f.views, f.projector_width, f.graycode_step), (6, 320, 1));

    // A capture with the wrong number of images is refused, naming the directory.
    let short = tmp.path().join("short");
    std::fs::create_dir_all(&short).expect("mkdir");
    std::fs::copy(tmp.path().join("capture_0/graycode_00.png"), short.join("graycode_00.png")).expect("copy");
    let run = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(["calibrate", "projector", "--captures"])
        .arg(&short)
        .args(["--board", "9x6", "--square-mm", "25", "--projector", "320x240", "--out"])
        .arg(tmp.path().join("x.toml"))
        .output()
        .expect("run scanrig");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(stderr.contains("short"), "{stderr}");
    assert!(!tmp.path().join("x.toml").exists());
}
