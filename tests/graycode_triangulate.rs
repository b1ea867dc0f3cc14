//! `scanrig triangulate` through the real binary on the MIT-licensed Gray-code chessboard capture of
//! kamino410/procam-calibration (pose 0; camera 1280x1024, projector 1024x768 shown with Gray-code
//! step 2, board 9x7 inner corners of 75 units) with its published `calibration_result.xml`: the
//! board's points lie on a plane, and triangulated neighbouring corners are one square apart.

mod shared_data;

use std::process::Command;

fn figure(line: &str, key: &str) -> f64 {
    let at = line.find(key).unwrap_or_else(|| panic!("{key:?} in {line:?}")) + key.len();
    let tail = line[at..].trim_start();
    let end = tail.find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-')).unwrap_or(tail.len());
    tail[..end].parse().unwrap_or_else(|_| panic!("number after {key:?} in {line:?}"))
}

#[test]
fn the_real_capture_triangulates_to_a_flat_board_with_true_corner_spacing() {
    let Some(dir) = shared_data::dataset("procam-graycode-chessboard") else { return };
    let tmp = tempfile::tempdir().expect("tempdir");
    let out = tmp.path().join("cloud.ply");
    let o = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .arg("triangulate")
        .arg("--images")
        .arg(dir.join("capture_0"))
        .arg("--procam")
        .arg(dir.join("calibration_result.xml"))
        .args(["--projector", "1024x768", "--graycode-step", "2", "--board", "9x7", "--square", "75", "--out"])
        .arg(&out)
        .output()
        .expect("run scanrig");
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}\n{}", stdout, String::from_utf8_lossy(&o.stderr));
    println!("{stdout}");
    let head = stdout.lines().next().expect("summary");
    let points = figure(head, "decoded, ");
    assert!(points > 300_000.0, "{head}");
    let board = stdout.lines().find(|l| l.starts_with("board plane:")).expect("board line");
    let plane_rms = figure(board, "RMS ");
    let corners = figure(board, "corners: ");
    let spacing = figure(board, "spacing mean ");
    let max_err = figure(board, "max error ");
    // Measured: plane RMS 2.02 units at ~3700 units distance; 63 corners, 110 pairs, mean spacing
    // 75.10, largest error 0.62 %.
    assert!(plane_rms < 3.0, "{board}");
    assert_eq!(corners, 63.0, "{board}");
    assert!((spacing - 75.0).abs() < 0.01 * 75.0, "{board}");
    assert!(max_err < 2.0, "every neighbouring corner pair within 2 % of the square: {board}");
    // The cloud file holds those points.
    let bytes = std::fs::read(&out).expect("cloud");
    let header = String::from_utf8_lossy(&bytes[..200.min(bytes.len())]);
    assert!(header.contains(&format!("element vertex {}", points as u64)), "{header}");
}
