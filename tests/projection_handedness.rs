//! Projection-matrix calibrations of either overall sign and of a mirrored (left-handed) world frame,
//! through the real `scanrig reconstruct --method space-carving` on the attributed Middlebury dino
//! fixture: which way a camera looks follows from the scene lying in front of it, so every variant
//! carves the same hull (mirrored in the mirrored frame).

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use scanrig::dataset;
use scanrig::geometry::Matrix3x4;

/// The tight box of the dino, metres; y is its longest side, so 64 voxels along y tile it exactly.
const BOX: [f64; 6] = [-0.061897, -0.018874, -0.057845, 0.010897, 0.068227, 0.015495];

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dino")
}

/// The 15 good views' `P = K [R | t]` from the par file.
fn projections() -> Vec<(String, Matrix3x4<f64>)> {
    let par = fixture().join("dinoSR_par.txt");
    let good = std::fs::read_to_string(fixture().join("dinoSR_good_silhouette_images.txt")).expect("view list");
    let good: HashSet<&str> = good.lines().map(str::trim).filter(|l| !l.is_empty()).collect();
    dataset::read_calibration(&par)
        .expect("par")
        .into_iter()
        .filter(|c| good.contains(c.name.as_str()))
        .map(|c| (c.name.clone(), c.camera(640, 480).projection_matrix()))
        .collect()
}

fn write_projections(path: &Path, ps: &[(String, Matrix3x4<f64>)]) {
    let mut text = String::from("# name p11 .. p34\n");
    for (name, p) in ps {
        text.push_str(name);
        for x in p.transpose().iter() {
            text.push_str(&format!(" {x:.17e}"));
        }
        text.push('\n');
    }
    std::fs::write(path, text).expect("write projections");
}

/// Run the binary; the occupied voxel centres of `voxels.ply`, quantised to 1 µm.
fn carve(calibration: &Path, bbox: [f64; 6], out: &Path) -> (u64, Vec<[i64; 3]>) {
    let bbox = bbox.iter().map(|v| format!("{v}")).collect::<Vec<_>>().join(",");
    let o = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .arg("reconstruct")
        .arg("--dataset")
        .arg(fixture())
        .arg("--calibration")
        .arg(calibration)
        .arg("--masks")
        .arg(fixture().join("masks"))
        .args(["--method", "space-carving", "--resolution", "64", "--bbox", &bbox])
        .arg("--out")
        .arg(out)
        .output()
        .expect("run scanrig");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).expect("report")).expect("json");
    let occupied = report["occupied_voxels"].as_u64().expect("count");
    let bytes = std::fs::read(out.join("voxels.ply")).expect("voxels.ply");
    let marker = b"end_header\n";
    let start = bytes.windows(marker.len()).position(|w| w == marker).expect("PLY header") + marker.len();
    let header = String::from_utf8_lossy(&bytes[..start]);
    let stride = if header.contains("property uchar red") { 15 } else { 12 };
    let mut pts: Vec<[i64; 3]> = bytes[start..]
        .chunks_exact(stride)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]) as f64;
            [f(0), f(4), f(8)].map(|v| (v * 1e6).round() as i64)
        })
        .collect();
    pts.sort_unstable();
    (occupied, pts)
}

#[test]
fn either_sign_and_a_mirrored_frame_carve_the_same_hull() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let ps = projections();
    assert_eq!(ps.len(), 15);

    let plain = tmp.path().join("plain.txt");
    write_projections(&plain, &ps);
    // Every other matrix negated and all scaled: P is defined up to a non-zero scale of either sign.
    let signs = tmp.path().join("signs.txt");
    let signed: Vec<_> =
        ps.iter().enumerate().map(|(i, (n, p))| (n.clone(), p * if i % 2 == 0 { -2.5 } else { 0.7 })).collect();
    write_projections(&signs, &signed);
    // A mirrored, left-handed world frame: y' = -y, so P' = P diag(1, -1, 1, 1); det of the left block
    // flips, yet the scene is still in front of every camera. Half of them negated as well.
    let mirror = tmp.path().join("mirror.txt");
    let mirrored: Vec<_> = ps
        .iter()
        .enumerate()
        .map(|(i, (n, p))| {
            let mut m = *p;
            m.column_mut(1).neg_mut();
            (n.clone(), if i % 3 == 0 { -m } else { m })
        })
        .collect();
    // What the old loader refused: a negative determinant while the dino (here its box centre, in
    // the mirrored frame) lies in front of the camera (positive third coordinate of P X).
    let centre = nalgebra::Vector4::new(-0.0255, -0.0247, -0.0212, 1.0);
    for (i, (_, m)) in mirrored.iter().enumerate().filter(|(i, _)| i % 3 != 0) {
        assert!(m.fixed_view::<3, 3>(0, 0).determinant() < 0.0 && (m * centre).z > 0.0, "view {i}");
    }
    write_projections(&mirror, &mirrored);

    let (n_plain, v_plain) = carve(&plain, BOX, &tmp.path().join("o1"));
    let (n_signs, v_signs) = carve(&signs, BOX, &tmp.path().join("o2"));
    let mbox = [BOX[0], -BOX[4], BOX[2], BOX[3], -BOX[1], BOX[5]];
    let (n_mirror, v_mirror) = carve(&mirror, mbox, &tmp.path().join("o3"));
    println!("occupied voxels: plain {n_plain}, mixed signs {n_signs}, mirrored frame {n_mirror}");
    // A real hull: a good part of the box, not all of it and not nothing.
    let total = 54 * 64 * 54;
    assert!(n_plain > total / 10 && n_plain < total / 2, "{n_plain} of {total}");
    assert_eq!(n_plain, n_signs);
    assert_eq!(v_plain, v_signs);
    assert_eq!(n_plain, n_mirror);
    let mut unmirrored: Vec<[i64; 3]> = v_mirror.iter().map(|p| [p[0], -p[1], p[2]]).collect();
    unmirrored.sort_unstable();
    let a: HashSet<_> = v_plain.iter().collect();
    let same = unmirrored.iter().filter(|p| a.contains(p)).count();
    // Centres agree to the µm rounding; allow a handful lost at rounding boundaries.
    assert!(same as f64 >= 0.999 * v_plain.len() as f64, "{same} of {} mirrored voxels coincide", v_plain.len());
}
