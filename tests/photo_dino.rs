//! Real data: photo-consistency on the Middlebury dino data set (dinoSparseRing, the 15 views with
//! usable silhouettes), in `../shared/data/middlebury-dino-sparse-ring` beside the checkout
//! (`SCANRIG_DINO_DIR` points elsewhere). Without the data the tests fail when `CI` is set and
//! otherwise print why and pass without checking.

use std::path::PathBuf;
use std::process::Command;

use scanrig::dataset::{self, DatasetOptions, MaskSource, ViewSelection};
use scanrig::geometry::{Aabb, VoxelGrid};
use scanrig::pipeline::{
    carve_photo, color_voxels_sweeps, colour_surface, measure_noise, reprojection_error, reprojection_iou, Occupancy,
    PhotoParams, PhotoView, SilhouetteParams, SpaceCarver, View,
};

/// The data set directory, or `None` (after saying why) when it is missing outside CI.
fn data_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("SCANRIG_DINO_DIR").map(PathBuf::from).unwrap_or_else(|| {
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/middlebury-dino-sparse-ring")
    });
    if dir.join("dinoSR_par.txt").is_file() {
        return Some(dir);
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "CI: the Middlebury dino is missing: {} has no dinoSR_par.txt",
        dir.display()
    );
    eprintln!(
        "skipped: {} has no dinoSR_par.txt (the Middlebury dino images are not in the repository)",
        dir.display()
    );
    None
}

/// `scanrig reconstruct` with the defaults of `[reconstruction.photo]` (the threshold derived from
/// the measured noise): the photo methods keep the plain hull's silhouette IoU and lower its
/// photometric re-projection error.
#[test]
fn dino_photo_carving_reprojects_better_than_the_hull() {
    let Some(dir) = data_dir() else { return };
    let resolution = if cfg!(debug_assertions) { "64" } else { "128" };
    let run_with = |method: &str, extra: &[&str]| {
        let out = tempfile::tempdir().expect("tempdir");
        let output = Command::new(env!("CARGO_BIN_EXE_scanrig"))
            .args(["reconstruct", "--method", method, "--resolution", resolution])
            .args(extra)
            .arg("--dataset")
            .arg(&dir)
            .arg("--views")
            .arg(dir.join("dinoSR_good_silhouette_images.txt"))
            .arg("--out")
            .arg(out.path())
            .output()
            .expect("run scanrig");
        assert!(output.status.success(), "{method} failed: {}", String::from_utf8_lossy(&output.stderr));
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.path().join("report.json")).expect("report")).expect("JSON");
        report
    };
    let run = |method: &str| run_with(method, &[]);
    let hull_iou = run("space-carving")["reprojection_iou_mean"].as_f64().expect("iou");
    for method in ["space-carving-photo", "voxel-coloring"] {
        let report = run(method);
        let model = report["photo"]["reprojection_error"].as_f64().expect("photo.reprojection_error");
        let hull = report["visual_hull"]["reprojection_error"].as_f64().expect("visual_hull.reprojection_error");
        let iou = report["reprojection_iou_mean"].as_f64().expect("iou");
        println!(
            "dino {resolution}^3 {method}: measured threshold {} levels ({}), {} views, photometric re-projection \
             error {model:.2} (visual hull coloured the same way {hull:.2}), carved {} of {} hull voxels, mean \
             silhouette IoU {iou:.4} (plain hull {hull_iou:.4})",
            report["photo"]["threshold"],
            report["photo"]["measured_noise"],
            report["photo"]["views"],
            report["photo"]["carved"],
            report["visual_hull"]["voxels"]
        );
        assert!(report["photo"]["measured_noise"].is_object(), "{method}: the default threshold is measured");
        // Every good view takes part; voxel colouring's ordinal sweeps cover each of them.
        assert_eq!(report["photo"]["views"].as_u64(), Some(15), "{method}");
        if method == "voxel-coloring" {
            let mut covered = [false; 15];
            for sweep in report["photo"]["ordinal_sweeps"].as_array().expect("photo.ordinal_sweeps") {
                for v in sweep["views"].as_array().expect("views") {
                    covered[v.as_u64().expect("index") as usize] = true;
                }
            }
            assert!(covered.iter().all(|&c| c), "a view in no sweep: {}", report["photo"]["ordinal_sweeps"]);
        }
        assert!(model < hull, "{method}: photo carving {model} is not below the hull's {hull}");
        assert!(iou >= hull_iou, "{method}: IoU {iou} below the plain hull's {hull_iou}");
    }
    // A fixed threshold is still there for the asking.
    let fixed = run_with("space-carving-photo", &["--photo", "threshold=22"]);
    assert_eq!(fixed["photo"]["threshold"].as_f64(), Some(22.0));
    assert!(fixed["photo"].get("measured_noise").is_none(), "{}", fixed["photo"]);
}

fn mean_iou(occupancy: &Occupancy, views: &[View<'_>]) -> f64 {
    let ious: Vec<f64> = reprojection_iou(occupancy, views).into_iter().flatten().collect();
    ious.iter().sum::<f64>() / ious.len().max(1) as f64
}

/// The photo methods with the threshold derived from the measured noise of the data (no fixed
/// number) and voxel colouring over the ordinal sweeps that cover every view: neither may lower
/// the silhouette re-projection IoU below the plain hull's, and both must lower its photometric
/// re-projection error.
#[test]
fn dino_photo_methods_with_measured_noise_do_no_harm() {
    let Some(dir) = data_dir() else { return };
    let data = dataset::load(&DatasetOptions {
        views: ViewSelection::File(dir.join("dinoSR_good_silhouette_images.txt")),
        dir,
        calibration: None,
        masks: MaskSource::Extract(SilhouetteParams::MIDDLEBURY),
        load_images: true,
    })
    .expect("dino loads");
    // The data set's tight box grown by 5 mm on every side (its README).
    let bbox = Aabb { min: [-0.066897, -0.023874, -0.062845], max: [0.015897, 0.073227, 0.020495] };
    let n = if cfg!(debug_assertions) { 64 } else { 128 };
    let grid = VoxelGrid::from_resolution(&bbox, n);
    let carving = data.carving_views();
    let mut carver = SpaceCarver::new(grid).expect("grid");
    carver.add_views(&carving).expect("carve");
    let hull = carver.into_occupancy();
    let views: Vec<PhotoView<'_>> = data
        .views
        .iter()
        .map(|v| PhotoView { camera: v.camera, image: v.image.as_ref().expect("images loaded"), mask: Some(&v.mask) })
        .collect();
    let defaults = PhotoParams::default();
    let noise = measure_noise(&hull, &views, &defaults).expect("noise");
    let params = defaults.with_measured_noise(&noise);
    println!("dino {n}^3: measured noise {noise:?}: threshold {:.2} levels", params.threshold);
    assert!(noise.voxels > 1000 && noise.image_sigma > 0.0);

    let hull_iou = mean_iou(&hull, &carving);
    let hull_err = reprojection_error(&grid, &colour_surface(&hull, &views, &params).expect("colours"), &views);
    println!(
        "dino {n}^3 hull: {} voxels, silhouette IoU {hull_iou:.4}, re-projection error {hull_err:.3}",
        hull.count()
    );
    for (name, model) in [
        ("space-carving-photo", carve_photo(&hull, &views, &params).expect("carves")),
        ("voxel-coloring (ordinal sweeps)", color_voxels_sweeps(&hull, &views, &params).expect("colours")),
    ] {
        let iou = mean_iou(&model.occupancy, &carving);
        let err = reprojection_error(&grid, &model.surface, &views);
        println!(
            "dino {n}^3 {name}: carved {} ({} sweeps), silhouette IoU {iou:.4}, re-projection error {err:.3}, {:.2} s",
            model.stats.carved, model.stats.sweeps, model.stats.seconds
        );
        assert!(model.stats.carved > 0, "{name} carved nothing");
        assert!(iou >= hull_iou, "{name}: IoU {iou} below the hull's {hull_iou}");
        assert!(err < hull_err, "{name}: re-projection error {err} not below the hull's {hull_err}");
    }
}
