//! Real data: generalized space carving by photo-consistency on the Middlebury dino data set
//! (dinoSparseRing, the 15 views with usable silhouettes). The images are not in the repository:
//! point `SCANRIG_DINO_DIR` at the data set directory (holding `dinoSR_par.txt`, the PNGs and
//! `dinoSR_good_silhouette_images.txt`); without it the test prints why and passes without checking.

use std::path::PathBuf;
use std::process::Command;

#[test]
fn dino_photo_carving_reprojects_better_than_the_hull() {
    let Some(dir) = std::env::var_os("SCANRIG_DINO_DIR").map(PathBuf::from) else {
        eprintln!("skipped: SCANRIG_DINO_DIR is not set (the Middlebury dino images are not in the repository)");
        return;
    };
    if !dir.join("dinoSR_par.txt").is_file() {
        eprintln!("skipped: {} has no dinoSR_par.txt", dir.display());
        return;
    }
    let out = tempfile::tempdir().expect("tempdir");
    let resolution = if cfg!(debug_assertions) { "64" } else { "128" };
    let output = Command::new(env!("CARGO_BIN_EXE_scanrig"))
        .args(["reconstruct", "--method", "space-carving-photo", "--resolution", resolution])
        // The defaults of `[reconstruction.photo]` (threshold 22, min_cos 0.4), as on the simulated rigs.
        .arg("--dataset")
        .arg(&dir)
        .arg("--views")
        .arg(dir.join("dinoSR_good_silhouette_images.txt"))
        .arg("--out")
        .arg(out.path())
        .output()
        .expect("run scanrig");
    assert!(output.status.success(), "reconstruct failed: {}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.path().join("report.json")).expect("report")).expect("JSON");
    let model = report["photo"]["reprojection_error"].as_f64().expect("photo.reprojection_error");
    let hull = report["visual_hull"]["reprojection_error"].as_f64().expect("visual_hull.reprojection_error");
    println!(
        "dino {resolution}^3: photometric re-projection error {model:.2} (visual hull coloured the same way {hull:.2}), \
         carved {} of {} hull voxels, mean silhouette IoU {}",
        report["photo"]["carved"], report["visual_hull"]["voxels"], report["reprojection_iou_mean"]
    );
    assert!(model < hull, "photo carving {model} is not below the hull's {hull}");
    // Carving must not eat the object: silhouettes still match.
    assert!(report["reprojection_iou_mean"].as_f64().expect("iou") > 0.9);
}
