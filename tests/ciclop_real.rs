//! Real frames of a Ciclop laser scanner (CC BY-SA 4.0, Jesus Arroyo Torrens / bq; see the data
//! set's README) through the real binary: `scanrig calibrate camera` on the 16 chessboard views
//! against the published intrinsics, `scanrig calibrate laser` on the board at two poses under both
//! lasers against the published laser planes and cloud, and `scanrig laser-view` on the bust with the stripe on the turntable
//! top checked against the published turntable plane.

mod shared_data;

use std::path::Path;
use std::process::{Command, Output};

fn scanrig(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_scanrig")).args(args).output().expect("run scanrig")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

fn figure(line: &str, key: &str) -> f64 {
    let at = line.find(key).unwrap_or_else(|| panic!("{key:?} in {line:?}")) + key.len();
    let tail = line[at..].trim_start();
    let end = tail.find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == 'e')).unwrap_or(tail.len());
    tail[..end].parse().unwrap_or_else(|_| panic!("number after {key:?} in {line:?}"))
}

/// Published laser plane (camera frame, mm) and turntable plane (normal, and `n · t` of the
/// published platform translation (4.427, 88.787, 318.281) mm).
const LASER_PLANE: &str = "0.84936,-0.00133,0.52781,160.235";
const TABLE_PLANE: &str = "0.0072119,-0.99925488,-0.03791666,-100.757";

#[test]
fn camera_laser_and_bust_view_agree_with_the_published_calibration() {
    let Some(dir) = shared_data::dataset("ciclop-laser-views") else { return };
    let tmp = tempfile::tempdir().expect("tempdir");
    let calib = tmp.path().join("ciclop.toml");

    // Camera: 16 views of 11x6 inner corners, 13 mm squares, OpenCV's five distortion terms.
    let o = scanrig(&[
        "calibrate",
        "camera",
        "--images",
        s(&dir.join("camera-calibration")),
        "--board",
        "11x6",
        "--square-mm",
        "13",
        "--distortion-terms",
        "5",
        "--out",
        s(&calib),
    ]);
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    println!("{out}");
    let line = out.lines().find(|l| l.starts_with("camera:")).expect("camera line");
    let (fx, fy, cx, k1) = (figure(line, "fx "), figure(line, "fy "), figure(line, "cx "), figure(line, "k1 "));
    let rms = figure(line, "RMS ");
    // Measured: fx 1430.82 fy 1431.44 cx 477.65 cy 642.70, k1 0.0259 k2 -0.208 k3 0.454, RMS 0.244 px
    // over 16 of 16 (published fx 1430.39 fy 1429.66, k1 0.0272 k2 -0.231 k3 0.509; their cx, cy
    // 636.40, 478.03 are a landscape frame's, i.e. our cy, cx).
    assert!(line.contains("over 16 of 16"), "{line}");
    assert!(rms < 0.35, "{line}");
    assert!((fx - 1430.39).abs() < 0.005 * 1430.39 && (fy - 1429.66).abs() < 0.005 * 1429.66, "{line}");
    assert!((cx - 478.53).abs() < 5.0, "{line}");
    assert!((k1 - 0.02719).abs() < 0.01, "{line}");
    let yaml = std::fs::read_to_string(calib.with_extension("yaml")).expect("OpenCV YAML written");
    assert!(yaml.starts_with("%YAML:1.0") && yaml.contains("distortion_coefficients: !!opencv-matrix"));

    // Laser on the board: two board poses, both lasers on. The "-x" pose's board is found in the
    // lit pattern.png of the same pose, the other pose's in its laser-off frame (red channel); the
    // two poses' stripes give both laser planes, ordered left to right.
    let board = dir.join("laser-on-board");
    let laser_step = |patterns: [&str; 2]| {
        let pattern = |p: &str| if p == "-" { "-".to_string() } else { s(&board.join(p)).to_string() };
        let (p0, p1) = (pattern(patterns[0]), pattern(patterns[1]));
        let o = scanrig(&[
            "calibrate",
            "laser",
            "--intrinsics",
            s(&calib),
            "--board",
            "11x6",
            "--square-mm",
            "13",
            "--laser",
            s(&board.join("laser-0-255-255-8.png")),
            s(&board.join("laser-0-255-255-8-x.png")),
            "--background",
            s(&board.join("laser-background-0-255-255-8.png")),
            s(&board.join("laser-background-0-255-255-8-x.png")),
            "--pattern",
            &p0,
            &p1,
            "--reference-plane",
            LASER_PLANE,
            "--reference-cloud",
            s(&board.join("horus-laser-cloud.ply")),
            "--out",
            s(&calib),
        ]);
        let out = String::from_utf8_lossy(&o.stdout).into_owned();
        assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
        println!("{out}");
        out
    };
    for (patterns, max_deg) in [(["-", "-"], 1.5), (["-", "pattern.png"], 1.5)] {
        let out = laser_step(patterns);
        assert_eq!(out.lines().filter(|l| l.contains("board found in")).count(), 2, "{out}");
        // Laser 1 (right of the camera) is the published one. Measured with pattern.png for the
        // "-x" pose: 0.952 deg, 0.652 mm; from the laser-off frames alone: 0.601 deg, 0.700 mm.
        let vs = out.lines().find(|l| l.contains("laser 1 vs published plane")).expect("laser 1 comparison");
        assert!(figure(vs, "published plane: ") < max_deg, "{vs}");
        assert!(figure(vs, "normals, ") < 1.5, "{vs}");
        let fit = out.lines().find(|l| l.starts_with("laser 1 plane")).expect("laser 1 plane");
        assert!(figure(fit, "RMS ") < 0.3 && fit.contains("from 2 poses"), "{fit}");
        // The authors' cloud (5,975 stripe points on their board poses) lies within 1 mm of our plane
        // (measured: mean 0.772 mm, RMS 0.800 mm with pattern.png; their own plane: RMS 0.093 mm).
        let cloud = out.lines().find(|l| l.contains("laser 1 vs reference cloud")).expect("cloud line");
        assert!(figure(cloud, "mean ").abs() < 1.0 && figure(cloud, "RMS ") < 1.0, "{cloud}");
        // Laser 0 (left) against the other laser's published plane (their worked example):
        // n = (-0.86952, -0.020884, 0.493456), d = 156.11 mm.
        let l0 = out.lines().find(|l| l.starts_with("laser 0 plane")).expect("laser 0 plane");
        let tail = &l0[l0.find("n = (").expect("n") + 5..];
        let n: Vec<f64> =
            tail[..tail.find(')').expect(")")].split(',').map(|t| t.trim().parse().expect("number")).collect();
        let other = [-0.86952, -0.020884, 0.493456];
        let len = other.iter().map(|x: &f64| x * x).sum::<f64>().sqrt();
        let cos = n.iter().zip(other).map(|(a, b)| a * b).sum::<f64>() / len;
        let angle = cos.clamp(-1.0, 1.0).acos().to_degrees();
        println!("laser 0 vs the other published plane: {angle:.3} deg, d {} mm vs 156.11", figure(l0, "d = "));
        assert!(angle < 1.5 && (figure(l0, "d = ") - 156.11).abs() < 4.0, "{l0}: {angle} deg");
    }
    // One board pose alone gives lines, not a plane: refused.
    let o = scanrig(&[
        "calibrate",
        "laser",
        "--intrinsics",
        s(&calib),
        "--board",
        "11x6",
        "--square-mm",
        "13",
        "--laser",
        s(&board.join("laser-0-255-255-8-x.png")),
        "--background",
        s(&board.join("laser-background-0-255-255-8-x.png")),
        "--out",
        s(&tmp.path().join("one-pose.toml")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success() && err.contains("two or more board poses"), "{err}");

    // The bust view triangulated on the published laser plane; the stripe on the turntable top lies on
    // the published turntable plane.
    let obj = dir.join("laser-on-object");
    let cloud = tmp.path().join("bust.ply");
    let o = scanrig(&[
        "laser-view",
        "--intrinsics",
        s(&calib),
        "--plane",
        LASER_PLANE,
        "--laser",
        s(&obj.join("laser.png")),
        "--background",
        s(&obj.join("laser_background.png")),
        "--texture",
        s(&obj.join("texture.png")),
        "--min-peak",
        "10",
        "--max-width-px",
        "20",
        "--check-plane",
        TABLE_PLANE,
        "--check-band-mm",
        "5",
        "--out",
        s(&cloud),
    ]);
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    println!("{out}");
    let head = out.lines().next().expect("summary");
    assert!(figure(head, "") > 1000.0, "{head}");
    let check = out.lines().find(|l| l.starts_with("check plane:")).expect("check line");
    // Measured: 105 points within 5 mm, residual mean -0.40 mm, RMS 2.70 mm.
    assert!(figure(check, "check plane: ") >= 50.0, "{check}");
    assert!(figure(check, "mean ").abs() < 1.5 && figure(check, "RMS ") < 3.5, "{check}");
    let bytes = std::fs::read(&cloud).expect("cloud");
    // The same view on our fitted plane (laser 1 of the calibration file just written).
    let o = scanrig(&[
        "laser-view",
        "--intrinsics",
        s(&calib),
        "--calibration",
        s(&calib),
        "--laser-index",
        "1",
        "--laser",
        s(&obj.join("laser.png")),
        "--background",
        s(&obj.join("laser_background.png")),
        "--min-peak",
        "10",
        "--max-width-px",
        "20",
        "--check-plane",
        TABLE_PLANE,
        "--check-band-mm",
        "5",
        "--out",
        s(&tmp.path().join("bust-ours.ply")),
    ]);
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    println!("{out}");
    let check = out.lines().find(|l| l.starts_with("check plane:")).expect("check line");
    // Measured: 101 points within 5 mm, residual mean -0.38 mm, RMS 2.98 mm.
    assert!(figure(check, "check plane: ") >= 50.0, "{check}");
    assert!(figure(check, "mean ").abs() < 1.5 && figure(check, "RMS ") < 3.5, "{check}");
    assert!(String::from_utf8_lossy(&bytes[..300.min(bytes.len())]).contains("property uchar red"));
}
