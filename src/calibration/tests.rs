//! Calibration tests against boards rendered by the simulator (real detector, real maths).

use nalgebra::{Matrix3, Point2, Rotation3, Vector3};

use super::*;
use crate::geometry::{CameraModel, Intrinsics, Pose};
use crate::sim::chessboard::{render_board, BoardMount, BoardScene, ChessboardTarget};
use crate::sim::FrameNoise;

pub(crate) fn truth_intrinsics() -> Intrinsics {
    Intrinsics { fx: 800.0, fy: 792.0, cx: 323.5, cy: 236.0, skew: 0.0, k1: -0.12, k2: 0.05, ..Intrinsics::default() }
}

/// The camera at the rig origin looking down +z (rig frame = camera frame), so board poses are
/// board -> camera.
pub(crate) fn camera() -> CameraModel {
    CameraModel {
        width: 640,
        height: 480,
        intrinsics: truth_intrinsics(),
        pose: Pose { rotation: Matrix3::identity(), translation: Vector3::zeros() },
    }
}

pub(crate) fn target() -> ChessboardTarget {
    ChessboardTarget { cols: 9, rows: 6, square_m: 0.025, border_m: 0.02, dark: 0.08, light: 0.9 }
}

/// Board -> camera pose putting the board centre at `centre` (camera frame, metres) tilted by the
/// given angles (degrees) about the camera's x, y and z axes.
pub(crate) fn board_pose(t: &ChessboardTarget, ax: f64, ay: f64, az: f64, centre: Vector3<f64>) -> Pose {
    let r = Rotation3::from_euler_angles(ax.to_radians(), ay.to_radians(), az.to_radians()).into_inner();
    let mid = Vector3::new((t.cols - 1) as f64 * t.square_m / 2.0, (t.rows - 1) as f64 * t.square_m / 2.0, 0.0);
    Pose { rotation: r, translation: centre - r * mid }
}

pub(crate) fn calibration_poses(t: &ChessboardTarget) -> Vec<Pose> {
    let v = Vector3::new;
    [
        (25.0, 0.0, 0.0, v(0.0, 0.0, 0.55)),
        (-25.0, 5.0, 3.0, v(0.02, 0.01, 0.5)),
        (0.0, 28.0, -4.0, v(-0.03, 0.0, 0.55)),
        (5.0, -30.0, 6.0, v(0.03, -0.02, 0.6)),
        (20.0, 20.0, 10.0, v(-0.06, -0.04, 0.6)),
        (-20.0, -20.0, -10.0, v(0.06, 0.04, 0.6)),
        (15.0, -15.0, 25.0, v(0.05, -0.05, 0.65)),
        (-15.0, 18.0, -20.0, v(-0.05, 0.05, 0.6)),
        (30.0, 10.0, 0.0, v(0.0, 0.06, 0.55)),
        (-30.0, -10.0, 0.0, v(0.0, -0.06, 0.6)),
        (10.0, 30.0, 15.0, v(0.08, 0.0, 0.65)),
        (8.0, -25.0, -15.0, v(-0.08, 0.02, 0.6)),
    ]
    .into_iter()
    .map(|(ax, ay, az, c)| board_pose(t, ax, ay, az, c))
    .collect()
}

pub(crate) fn render(pose: &Pose, seq: u64) -> image::GrayImage {
    let scene = BoardScene { target: target(), mount: BoardMount::Rig(*pose), illumination: 0.95, background: 0.35 };
    let rgb = render_board(&camera(), &scene, 0.0, 3, FrameNoise { sigma: 1.0, seed: 7, sequence: seq });
    detect::to_gray(&rgb)
}

fn spec() -> BoardSpec {
    let t = target();
    BoardSpec::new(t.cols, t.rows, t.square_m).expect("valid board")
}

fn project_all(intr: &Intrinsics, pose: &Pose, pts: &[Vector3<f64>]) -> Vec<Point2<f64>> {
    pts.iter()
        .map(|p| {
            let c = pose.apply(p);
            intr.normalised_to_pixel(c.x / c.z, c.y / c.z)
        })
        .collect()
}

#[test]
fn detects_rendered_corners_in_board_order_to_subpixel_accuracy() {
    let board = spec();
    let pose = calibration_poses(&target())[4];
    let det = detect_chessboard(&render(&pose, 1), &board, &DetectOptions::default()).expect("board found");
    let truth = project_all(&truth_intrinsics(), &pose, &board.object_points());
    let rms =
        (det.corners.iter().zip(&truth).map(|(a, b)| (a - b).norm_squared()).sum::<f64>() / truth.len() as f64).sqrt();
    println!("rendered corners vs projected truth: RMS {rms:.3} px");
    assert!(rms < 0.15, "corner RMS error {rms} px");
}

#[test]
fn calibrates_simulated_camera_within_half_a_percent() {
    let board = spec();
    let views: Vec<PlanarView> = calibration_poses(&target())
        .iter()
        .enumerate()
        .map(|(k, pose)| {
            let det = detect_chessboard(&render(pose, k as u64), &board, &DetectOptions::default())
                .unwrap_or_else(|e| panic!("view {k}: {e}"));
            PlanarView { object: board.object_points(), image: det.corners }
        })
        .collect();
    let cal = calibrate_camera(&views, &CalibrationOptions::default()).expect("calibrates");
    let (t, e) = (truth_intrinsics(), cal.intrinsics);
    println!(
        "sim calibration from {} views: fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} k2 {:.4}, RMS {:.3} px (truth {t:?})",
        views.len(),
        e.fx,
        e.fy,
        e.cx,
        e.cy,
        e.k1,
        e.k2,
        cal.rms_px
    );
    for (name, got, want) in [("fx", e.fx, t.fx), ("fy", e.fy, t.fy), ("cx", e.cx, t.cx), ("cy", e.cy, t.cy)] {
        assert!(((got - want) / want).abs() < 0.005, "{name}: {got} vs {want}");
    }
    assert!((e.k1 - t.k1).abs() < 0.02 && (e.k2 - t.k2).abs() < 0.05, "k1 {} k2 {}", e.k1, e.k2);
    assert!(cal.rms_px < 0.3, "rms {}", cal.rms_px);
    assert_eq!(cal.per_view_rms_px.len(), views.len());
    // Poses match the simulated ones.
    for (got, want) in cal.poses.iter().zip(calibration_poses(&target())) {
        assert!((got.translation - want.translation).norm() < 0.003, "{} vs {}", got.translation, want.translation);
    }
}

#[test]
fn single_view_pose_with_known_intrinsics() {
    let board = spec();
    let pose = calibration_poses(&target())[2];
    let det = detect_chessboard(&render(&pose, 3), &board, &DetectOptions::default()).expect("board found");
    let est = estimate_pose(&truth_intrinsics(), &PlanarView { object: board.object_points(), image: det.corners })
        .expect("pose");
    let dr = Rotation3::from_matrix_unchecked(est.pose.rotation.transpose() * pose.rotation).angle().to_degrees();
    assert!(dr < 0.2, "rotation error {dr} deg");
    assert!((est.pose.translation - pose.translation).norm() < 0.002, "{}", est.pose.translation);
    assert!(est.rms_px < 0.3, "rms {}", est.rms_px);
}

#[test]
fn exact_points_recover_exact_intrinsics() {
    let board = spec();
    let t = truth_intrinsics();
    let views: Vec<PlanarView> = calibration_poses(&target())
        .iter()
        .map(|p| PlanarView { object: board.object_points(), image: project_all(&t, p, &board.object_points()) })
        .collect();
    let cal = calibrate_camera(&views, &CalibrationOptions::default()).expect("calibrates");
    let e = cal.intrinsics;
    assert!((e.fx - t.fx).abs() < 1e-4 && (e.cy - t.cy).abs() < 1e-4 && (e.k1 - t.k1).abs() < 1e-6, "{e:?}");
    assert!(cal.rms_px < 1e-6);
}

#[test]
fn partial_board_is_rejected_with_the_reason() {
    // Shifted so the right part of the board leaves the image.
    let pose = board_pose(&target(), 0.0, 10.0, 0.0, Vector3::new(0.15, 0.0, 0.5));
    let err = detect_chessboard(&render(&pose, 9), &spec(), &DetectOptions::default()).expect_err("partial");
    assert!(matches!(err, DetectError::PartialBoard { .. }), "{err}");
    assert!(err.to_string().contains("partial board"));
}

#[test]
fn empty_image_is_rejected() {
    let img = image::GrayImage::from_pixel(200, 150, image::Luma([120]));
    let err = detect_chessboard(&img, &spec(), &DetectOptions::default()).expect_err("nothing there");
    assert!(matches!(err, DetectError::NoBoard { .. }), "{err}");
}

#[test]
fn degenerate_inputs_are_refused_with_a_reason() {
    let board = spec();
    let t = truth_intrinsics();
    let flat: Vec<PlanarView> = [0.0, 20.0, 45.0, 90.0]
        .iter()
        .map(|&az| {
            let p = board_pose(&target(), 0.0, 0.0, az, Vector3::new(0.0, 0.0, 0.5));
            PlanarView { object: board.object_points(), image: project_all(&t, &p, &board.object_points()) }
        })
        .collect();
    let err = calibrate_camera(&flat, &CalibrationOptions::default()).expect_err("fronto-parallel");
    assert!(matches!(err, CalibrationError::Degenerate { .. }), "{err}");
    let err = calibrate_camera(&flat[..2], &CalibrationOptions::default()).expect_err("two views");
    assert_eq!(err, CalibrationError::TooFewViews { got: 2, need: 3 });
    let line = PlanarView {
        object: (0..6).map(|i| Vector3::new(i as f64 * 0.01, 0.0, 0.0)).collect(),
        image: (0..6).map(|i| Point2::new(100.0 + i as f64 * 10.0, 50.0)).collect(),
    };
    assert_eq!(estimate_pose(&t, &line).expect_err("collinear"), CalibrationError::Collinear { view: 0 });
    let short = PlanarView { object: board.object_points()[..3].to_vec(), image: flat[0].image[..3].to_vec() };
    assert!(matches!(estimate_pose(&t, &short), Err(CalibrationError::TooFewPoints { got: 3, .. })));
}

fn turntable_rig() -> capture::SimBoardRig {
    let camera = CameraModel {
        width: 640,
        height: 480,
        intrinsics: Intrinsics {
            fx: 700.0,
            fy: 700.0,
            cx: 318.0,
            cy: 243.0,
            skew: 0.0,
            k1: -0.08,
            k2: 0.02,
            ..Intrinsics::default()
        },
        // The camera in the rig's x = 0 plane at negative y: the yaw convention of `turntable`.
        pose: Pose::look_at(Vector3::new(0.0, -0.40, 0.33), Vector3::new(0.0, 0.0, 0.01), Vector3::z()),
    };
    let target = ChessboardTarget { cols: 9, rows: 6, square_m: 0.02, border_m: 0.015, dark: 0.08, light: 0.9 };
    capture::SimBoardRig { camera, noise_sigma: 1.0, seed: 5, target, steps_per_turn: 3200 }
}

#[test]
fn turntable_axis_and_camera_pose_are_recovered() {
    let rig = turntable_rig();
    let t = rig.target;
    let board = BoardSpec::new(t.cols, t.rows, t.square_m).expect("board");
    let height = 0.002;
    let on_table = rig.lying_board_pose([0.012, -0.008], height);
    let views: Vec<TurntableView> = (0..10)
        .map(|k| {
            let angle = rig.reachable_angle(k as f64 * 36.0);
            let img = detect::to_gray(&rig.render_on_table(&on_table, angle, k));
            let det = detect_chessboard(&img, &board, &DetectOptions::default())
                .unwrap_or_else(|e| panic!("angle {angle}: {e}"));
            TurntableView { angle_deg: angle, view: PlanarView { object: board.object_points(), image: det.corners } }
        })
        .collect();
    let cal = calibrate_turntable(&rig.camera.intrinsics, &views, &TurntableOptions { board_origin_height_m: height })
        .expect("axis");
    let truth_axis = rig.camera.pose.rotation * Vector3::z();
    let axis_err = cal.axis_camera.angle(&truth_axis).to_degrees();
    let origin_err = (cal.origin_camera_m - rig.camera.pose.translation).norm();
    let rot_err = Rotation3::from_matrix_unchecked(cal.camera_pose.rotation.transpose() * rig.camera.pose.rotation)
        .angle()
        .to_degrees();
    println!(
        "turntable: axis error {axis_err:.3} deg, origin error {:.2} mm, camera rotation error {rot_err:.3} deg, \
         circle RMS {:.2} mm, max angle error {:.3} deg",
        origin_err * 1e3,
        cal.circle_rms_m * 1e3,
        cal.max_angle_error_deg
    );
    assert!(axis_err < 0.5, "axis error {axis_err} deg");
    assert!(origin_err < 0.003, "origin error {origin_err} m");
    assert!(rot_err < 0.5, "camera rotation error {rot_err} deg");
}

#[test]
fn camera_calibration_from_generated_rig_views() {
    let rig = turntable_rig();
    let t = rig.target;
    let board = BoardSpec::new(t.cols, t.rows, t.square_m).expect("board");
    let views: Vec<PlanarView> = rig
        .camera_view_poses(12)
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let img = detect::to_gray(&rig.render_fixed(p, k as u64));
            let det =
                detect_chessboard(&img, &board, &DetectOptions::default()).unwrap_or_else(|e| panic!("view {k}: {e}"));
            PlanarView { object: board.object_points(), image: det.corners }
        })
        .collect();
    let cal = calibrate_camera(&views, &CalibrationOptions::default()).expect("calibrates");
    let (e, tr) = (cal.intrinsics, rig.camera.intrinsics);
    for (name, got, want) in [("fx", e.fx, tr.fx), ("fy", e.fy, tr.fy), ("cx", e.cx, tr.cx), ("cy", e.cy, tr.cy)] {
        assert!(((got - want) / want).abs() < 0.005, "{name}: {got} vs {want}");
    }
}

#[test]
fn board_turned_a_quarter_keeps_its_corner_order() {
    // Rows and columns swap in the image; the colouring (9 + 6 odd) still fixes the origin.
    let board = spec();
    for az in [90.0, 180.0, -90.0] {
        let pose = board_pose(&target(), 10.0, -10.0, az, Vector3::new(0.0, 0.0, 0.6));
        let det = detect_chessboard(&render(&pose, 4), &board, &DetectOptions::default()).expect("board found");
        let truth = project_all(&truth_intrinsics(), &pose, &board.object_points());
        let worst = det.corners.iter().zip(&truth).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        assert!(worst < 0.5, "turned {az} deg: worst corner {worst} px");
    }
}

#[test]
fn blurred_capture_is_rejected() {
    let pose = calibration_poses(&target())[0];
    let sharp = render(&pose, 5);
    let blurred = image::imageops::blur(&sharp, 8.0);
    let err = detect_chessboard(&blurred, &spec(), &DetectOptions::default()).expect_err("too blurred");
    assert!(matches!(err, DetectError::NoBoard { .. } | DetectError::PartialBoard { .. }), "{err}");
}
