//! Chessboard detection and pose/intrinsics on a real capture: pose 0 of the MIT-licensed
//! projector-camera Gray-code sample set of kamino410/procam-calibration (camera 1280x1024,
//! chessboard 9x7 inner corners, 75 mm squares... the set states "75 units"; we take millimetres).
//!
//! Reads `../shared/data/procam-graycode-chessboard` (`capture_0/` and
//! `calibration_result.xml`; skips with a message when it is unset.

mod shared_data;

use std::path::PathBuf;

use scanrig::calibration::{
    calibrate_camera, detect_chessboard, estimate_pose, BoardSpec, CalibrationOptions, DetectOptions, PlanarView,
};
use scanrig::geometry::Intrinsics;

/// `../shared/data/procam-graycode-chessboard` (fails under CI when missing, see `shared_data`).
fn data_dir() -> Option<PathBuf> {
    shared_data::dataset("procam-graycode-chessboard")
}

/// The numbers of an OpenCV FileStorage matrix `<name ...><data> ... </data>`.
fn xml_matrix(xml: &str, name: &str) -> Vec<f64> {
    let start = xml.find(&format!("<{name} ")).unwrap_or_else(|| panic!("no <{name}> in calibration_result.xml"));
    let rest = &xml[start..];
    let a = rest.find("<data>").expect("<data>") + "<data>".len();
    let b = rest.find("</data>").expect("</data>");
    rest[a..b].split_whitespace().map(|t| t.parse::<f64>().expect("number")).collect()
}

#[test]
fn real_chessboard_is_detected_and_reprojects_with_published_intrinsics() {
    let Some(dir) = data_dir() else { return };
    let img = image::open(dir.join("capture_0/graycode_40.png")).expect("white image").to_luma8();
    let board = BoardSpec::new(9, 7, 0.075).expect("board");
    let det = detect_chessboard(&img, &board, &DetectOptions::default()).expect("board detected");
    assert_eq!(det.corners.len(), 63);
    let view = PlanarView { object: board.object_points(), image: det.corners.clone() };

    // Published intrinsics of this camera (from all 5 poses); our model keeps k1, k2 of its 5 terms.
    let xml = std::fs::read_to_string(dir.join("calibration_result.xml")).expect("calibration_result.xml");
    let k = xml_matrix(&xml, "cam_int");
    let d = xml_matrix(&xml, "cam_dist");
    let published =
        Intrinsics { fx: k[0], fy: k[4], cx: k[2], cy: k[5], skew: 0.0, k1: d[0], k2: d[1], ..Intrinsics::default() };
    let est = estimate_pose(&published, &view).expect("pose");
    println!(
        "real board: {} candidates, board origin at ({:.3}, {:.3}, {:.3}) m, RMS with published intrinsics {:.3} px",
        det.candidates, est.pose.translation.x, est.pose.translation.y, est.pose.translation.z, est.rms_px
    );
    assert!(est.rms_px < 1.5, "re-projection RMS {} px", est.rms_px);
    // The board is a couple of metres in front of the camera (75 mm squares spanning ~60 % of the image).
    assert!(est.pose.translation.z > 0.5 && est.pose.translation.z < 10.0, "{}", est.pose.translation);

    // One nearly fronto-parallel view with a fixed principal point: either a focal length near the
    // published one or a refusal naming the degeneracy, never a silent wrong answer far off.
    let opts = CalibrationOptions {
        fixed_principal_point: Some((published.cx, published.cy)),
        estimate_distortion: false,
        ..CalibrationOptions::default()
    };
    match calibrate_camera(std::slice::from_ref(&view), &opts) {
        Ok(cal) => println!(
            "single-view calibration (fixed principal point, no distortion): fx {:.1} fy {:.1} RMS {:.3} px",
            cal.intrinsics.fx, cal.intrinsics.fy, cal.rms_px
        ),
        Err(e) => println!("single-view calibration refused: {e}"),
    }
}
