//! Projector-camera calibration against simulated Gray-code captures of a chessboard (real
//! renderer term, real decoder, real detector, real maths).

use nalgebra::{Matrix3, Point2, Vector3};

use super::procam::*;
use super::procam_sim::SimProcam;
use super::tests::{calibration_poses, camera, target};
use super::BoardSpec;
use crate::geometry::{CameraModel, Intrinsics, Pose};
use crate::pipeline::structured_light::GrayCodePatterns;

fn projector_truth() -> Intrinsics {
    Intrinsics { fx: 420.0, fy: 415.0, cx: 166.0, cy: 131.5, skew: 0.0, k1: -0.06, k2: 0.02, ..Intrinsics::default() }
}

/// The projector 12 cm to the camera's right and 2 cm above it, aimed at the boards' middle.
fn projector() -> CameraModel {
    CameraModel {
        width: 320,
        height: 240,
        intrinsics: projector_truth(),
        pose: Pose::look_at(Vector3::new(0.12, -0.02, 0.0), Vector3::new(0.0, 0.0, 0.6), Vector3::new(0.0, -1.0, 0.0)),
    }
}

fn sim() -> SimProcam {
    SimProcam {
        camera: camera(),
        projector: projector(),
        target: target(),
        ambient: 0.1,
        projector_intensity: 0.85,
        background: 0.3,
        noise_sigma: 1.0,
        seed: 11,
        supersample: 2,
    }
}

fn board() -> BoardSpec {
    let t = target();
    BoardSpec::new(t.cols, t.rows, t.square_m).expect("board")
}

/// Render, decode and detect pose `k`.
fn view(sim: &SimProcam, pose: &Pose, k: u64) -> (ProcamView, ProcamViewStats) {
    let patterns = GrayCodePatterns::new(sim.projector.width, sim.projector.height).expect("patterns");
    let frames = sim.render_sequence(pose, &patterns, k).expect("render");
    let slices: Vec<&[u8]> = frames.iter().map(|f| f.as_slice()).collect();
    let (w, h) = (sim.camera.width as usize, sim.camera.height as usize);
    procam_view_from_frames(&slices, w, h, &patterns, &board(), &ProcamViewOptions::default())
        .unwrap_or_else(|e| panic!("pose {k}: {e}"))
}

/// Projector <- camera of the simulated rig (camera at the rig origin).
fn stereo_truth() -> Pose {
    let c = camera().pose;
    let p = projector().pose;
    let rt = c.rotation.transpose();
    Pose { rotation: p.rotation * rt, translation: p.translation - p.rotation * rt * c.translation }
}

#[test]
fn local_homography_recovers_a_projective_map_to_sub_pixel() {
    // A camera -> projector homography, decoded (rounded down to whole projector pixels) everywhere
    // except a dark quadrant, as around a chessboard corner.
    let h = Matrix3::new(1.1, 0.05, 30.0, -0.03, 0.95, 40.0, 1e-4, -5e-5, 1.0);
    let (w, ht) = (200usize, 160usize);
    let mut cols = vec![u16::MAX; w * ht];
    let mut rows = vec![u16::MAX; w * ht];
    let corner = Point2::new(100.3, 80.7);
    for y in 0..ht {
        for x in 0..w {
            let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
            if (cx < corner.x) == (cy < corner.y) {
                continue; // dark square: not decoded
            }
            let q = h * Vector3::new(cx, cy, 1.0);
            cols[y * w + x] = (q.x / q.z).floor() as u16;
            rows[y * w + x] = (q.y / q.z).floor() as u16;
        }
    }
    // One gross decoding error inside the window must be rejected.
    cols[82 * w + 110] = 900;
    let got =
        projector_corners_in(w, ht, &cols, &rows, &[corner, Point2::new(3.0, 3.0)], &LocalHomographyOptions::default());
    let want = h * Vector3::new(corner.x, corner.y, 1.0);
    let want = Point2::new(want.x / want.z, want.y / want.z);
    let c = got[0].expect("corner placed");
    println!(
        "local homography: error {:.4} px, {} inliers, fit RMS {:.3} px",
        (c.point - want).norm(),
        c.inliers,
        c.rms_px
    );
    assert!((c.point - want).norm() < 0.05, "{:?} vs {want:?}", c.point);
    assert!(c.inliers < 21 * 41 + 10, "the outlier was kept: {}", c.inliers);
    // A window at the image corner that is entirely dark has too few decoded pixels.
    assert!(got[1].is_none());
}

#[test]
fn calibrates_simulated_projector_and_camera_within_one_percent() {
    let sim = sim();
    let poses: Vec<Pose> = calibration_poses(&target()).into_iter().take(8).collect();
    let mut views = Vec::new();
    for (k, p) in poses.iter().enumerate() {
        let (v, s) = view(&sim, p, k as u64);
        println!(
            "pose {k}: {:.1}% decoded, {}/{} corners in the projector, {:.0} px per fit, fit RMS {:.3} px",
            100.0 * s.valid_fraction,
            s.projector_corners,
            s.camera_corners,
            s.mean_inliers,
            s.mean_fit_rms_px
        );
        assert!(s.projector_corners >= s.camera_corners * 3 / 4, "pose {k}: {s:?}");
        views.push(v);
    }
    let cal = calibrate_procam(&views, &ProcamOptions::default()).expect("calibrates");
    let (c, p) = (cal.camera, cal.projector);
    let (ct, pt) = (camera().intrinsics, projector_truth());
    println!(
        "camera fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} (truth {} {} {} {} {}); projector fx {:.2} fy {:.2} cx {:.2} cy {:.2} k1 {:.4} (truth {} {} {} {} {})",
        c.fx, c.fy, c.cx, c.cy, c.k1, ct.fx, ct.fy, ct.cx, ct.cy, ct.k1, p.fx, p.fy, p.cx, p.cy, p.k1, pt.fx, pt.fy, pt.cx, pt.cy, pt.k1
    );
    let truth = stereo_truth();
    let dr = rotation_difference_deg(&cal.rotation, &truth.rotation);
    let dt = (cal.translation - truth.translation).norm() / truth.translation.norm();
    println!(
        "stereo: rotation off by {dr:.4} deg, translation {:?} vs {:?} ({:.3}%); RMS camera {:.3} px, projector {:.3} px",
        cal.translation.as_slice(),
        truth.translation.as_slice(),
        100.0 * dt,
        cal.camera_rms_px,
        cal.projector_rms_px
    );
    for (name, got, want) in [
        ("camera fx", c.fx, ct.fx),
        ("camera fy", c.fy, ct.fy),
        ("camera cx", c.cx, ct.cx),
        ("camera cy", c.cy, ct.cy),
        ("projector fx", p.fx, pt.fx),
        ("projector fy", p.fy, pt.fy),
        ("projector cx", p.cx, pt.cx),
        ("projector cy", p.cy, pt.cy),
    ] {
        assert!(((got - want) / want).abs() < 0.01, "{name}: {got} vs {want}");
    }
    assert!(dr < 0.3, "rotation off by {dr} deg");
    assert!(dt < 0.02, "translation off by {}%", 100.0 * dt);
    assert!(cal.camera_rms_px < 0.3 && cal.projector_rms_px < 0.3, "{} {}", cal.camera_rms_px, cal.projector_rms_px);
}

#[test]
fn single_pose_extrinsics_with_known_intrinsics() {
    let sim = sim();
    let pose = calibration_poses(&target())[4];
    let (v, _) = view(&sim, &pose, 4);
    let opts = ProcamOptions {
        camera: Some(camera().intrinsics),
        projector: Some(projector_truth()),
        ..ProcamOptions::default()
    };
    let cal = calibrate_procam(std::slice::from_ref(&v), &opts).expect("calibrates");
    let truth = stereo_truth();
    let dr = rotation_difference_deg(&cal.rotation, &truth.rotation);
    let dt = (cal.translation - truth.translation).norm() / truth.translation.norm();
    println!("single pose: rotation off by {dr:.4} deg, translation by {:.3}%", 100.0 * dt);
    assert!(dr < 0.5 && dt < 0.03, "{dr} deg, {dt}");
    // Without both lenses a single view cannot calibrate.
    let e = calibrate_procam(std::slice::from_ref(&v), &ProcamOptions::default()).expect_err("must be refused");
    assert!(matches!(e, super::CalibrationError::TooFewViews { got: 1, need: 3 }), "{e}");
}

#[test]
fn lens_distortion_round_trips_and_matches_intrinsics() {
    let l = Intrinsics {
        fx: 900.0,
        fy: 880.0,
        cx: 320.0,
        cy: 250.0,
        skew: 0.0,
        k1: -0.2,
        k2: 0.1,
        p1: 1e-3,
        p2: -2e-3,
        k3: 0.3,
    };
    for (x, y) in [(0.1, -0.2), (-0.3, 0.25), (0.0, 0.0)] {
        let q = l.normalised_to_pixel(x, y);
        let (bx, by) = l.pixel_to_normalised(q.x, q.y);
        assert!((bx - x).abs() < 1e-9 && (by - y).abs() < 1e-9, "{bx} {by}");
    }
    let i = projector_truth();
    let a = i.normalised_to_pixel(0.2, -0.1);
    let b = i.normalised_to_pixel(0.2, -0.1);
    assert!((a - b).norm() < 1e-12);
}

#[test]
fn bad_views_are_refused_naming_the_view() {
    let board = board();
    let lens = camera().intrinsics;
    let obj = board.object_points();
    let pose = calibration_poses(&target())[0];
    let cam: Vec<Point2<f64>> = obj
        .iter()
        .map(|p| {
            let c = pose.apply(p);
            camera().intrinsics.normalised_to_pixel(c.x / c.z, c.y / c.z)
        })
        .collect();
    let proj: Vec<Option<ProjectorCorner>> =
        cam.iter().map(|p| Some(ProjectorCorner { point: *p, inliers: 100, rms_px: 0.1 })).collect();
    let good = ProcamView::new(&obj, &cam, &proj);
    let opts = ProcamOptions { camera: Some(lens), projector: Some(lens), ..ProcamOptions::default() };
    // Too few projector corners in view 1.
    let few: Vec<Option<ProjectorCorner>> =
        proj.iter().enumerate().map(|(i, p)| if i < 3 { *p } else { None }).collect();
    let e = calibrate_procam(&[good.clone(), ProcamView::new(&obj, &cam, &few)], &opts).expect_err("refused");
    assert!(matches!(e, super::CalibrationError::TooFewPoints { view: 1, got: 3, need: 4 }), "{e}");
    // A non-finite camera corner in view 1, with fixed intrinsics.
    let mut nan = good.clone();
    nan.camera.image[5].x = f64::NAN;
    let e = calibrate_procam(&[good.clone(), nan], &opts).expect_err("refused");
    assert!(matches!(e, super::CalibrationError::NonFinite { view: 1, index: 5 }), "{e}");
    // No views at all.
    let e = calibrate_procam(&[], &opts).expect_err("refused");
    assert!(matches!(e, super::CalibrationError::TooFewViews { got: 0, need: 1 }), "{e}");
    // Non-finite given intrinsics.
    let bad = ProcamOptions { camera: Some(Intrinsics { fx: f64::NAN, ..lens }), ..opts };
    assert!(calibrate_procam(std::slice::from_ref(&good), &bad).is_err());
}
