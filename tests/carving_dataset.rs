//! Loading calibrated image sets from disk: the projection-matrix format against the Middlebury one on
//! the dino fixture, and typed errors that name the file (and line) for broken data sets.

use std::path::{Path, PathBuf};

use scanrig::dataset::{self, DatasetError, DatasetOptions, MaskSource, ViewSelection};
use scanrig::geometry::{Aabb, VoxelGrid};
use scanrig::pipeline::{SilhouetteParams, SpaceCarver};

const DINO_BOX: Aabb = Aabb { min: [-0.061897, -0.018874, -0.057845], max: [0.010897, 0.068227, 0.015495] };

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dino")
}

fn options(calibration: PathBuf, views: ViewSelection) -> DatasetOptions {
    let dir = fixture_dir();
    DatasetOptions {
        dir: dir.clone(),
        calibration: Some(calibration),
        views,
        masks: MaskSource::Directory(dir.join("masks")),
        load_images: false,
    }
}

#[test]
fn projection_matrix_file_gives_the_same_hull_as_the_par_file() {
    let dir = fixture_dir();
    let good = ViewSelection::File(dir.join("dinoSR_good_silhouette_images.txt"));
    let par = dataset::load(&options(dir.join("dinoSR_par.txt"), good.clone())).expect("par");
    // Write P = K [R | t] of every view, scaled by an arbitrary negative factor (P is defined up to scale).
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut text = String::from("# name p11 .. p34\n");
    for v in &par.views {
        let p = v.camera.projection_matrix() * -3.0;
        text.push_str(&v.name);
        for x in p.transpose().iter() {
            text.push_str(&format!(" {x:.17e}"));
        }
        text.push('\n');
    }
    let file = tmp.path().join("projections.txt");
    std::fs::write(&file, text).expect("write");
    let proj = dataset::load(&options(file, ViewSelection::All)).expect("projections");
    assert_eq!(proj.views.len(), 15);
    for (a, b) in par.views.iter().zip(&proj.views) {
        // The data set's rotations are orthonormal to about 1e-6 only, so K, R, t agree to that order.
        let (ka, kb) = (a.camera.intrinsics, b.camera.intrinsics);
        assert!((ka.fx - kb.fx).abs() / ka.fx < 1e-4, "{} {}", ka.fx, kb.fx);
        assert!((ka.cy - kb.cy).abs() < 0.05, "{} {}", ka.cy, kb.cy);
        assert!((a.camera.pose.rotation - b.camera.pose.rotation).norm() < 1e-4);
        assert!((a.camera.pose.translation - b.camera.pose.translation).norm() < 1e-4);
        // The decomposition reproduces P up to scale.
        let pa = a.camera.projection_matrix().normalize();
        let pb = b.camera.projection_matrix().normalize();
        assert!((pa - pb).norm() < 1e-9, "{pa} {pb}");
    }
    let grid = VoxelGrid::from_resolution(&DINO_BOX, 64);
    let mut c1 = SpaceCarver::new(grid).expect("carver");
    c1.add_views(&par.carving_views()).expect("carve");
    let mut c2 = SpaceCarver::new(grid).expect("carver");
    c2.add_views(&proj.carving_views()).expect("carve");
    let o = c1.occupancy().iou_and_containment(c2.occupancy()).expect("same grid");
    assert!(o.iou > 0.9999, "{o:?}");
}

#[test]
fn view_list_selects_and_orders_views() {
    let dir = fixture_dir();
    let ds = dataset::load(&options(dir.join("dinoSR_par.txt"), ViewSelection::parse("dinoSR0003.png,dinoSR0001")))
        .expect("loads");
    let names: Vec<&str> = ds.views.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(names, ["dinoSR0003.png", "dinoSR0001.png"]);
    let e = dataset::load(&options(dir.join("dinoSR_par.txt"), ViewSelection::parse("dinoSR0099.png")))
        .expect_err("unknown view");
    assert!(matches!(e, DatasetError::UnknownView { .. }), "{e}");
}

#[test]
fn missing_images_name_the_calibration_line() {
    // The fixture has masks but no images: extracting silhouettes must fail on the first listed image.
    let dir = fixture_dir();
    let mut opts = options(dir.join("dinoSR_par.txt"), ViewSelection::parse("dinoSR0002.png"));
    opts.masks = MaskSource::Extract(SilhouetteParams::MIDDLEBURY);
    let e = dataset::load(&opts).expect_err("no images in the fixture");
    let text = e.to_string();
    assert!(matches!(e, DatasetError::MissingImage { line: 3, .. }), "{text}");
    assert!(text.contains("dinoSR_par.txt:3") && text.contains("dinoSR0002.png"), "{text}");
}

#[test]
fn broken_files_give_typed_errors_naming_the_file() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let d = tmp.path();
    // A 4x3 image and a 5x3 mask for it.
    image::RgbImage::from_pixel(4, 3, image::Rgb([200, 200, 200])).save(d.join("a.png")).expect("save image");
    std::fs::create_dir(d.join("masks")).expect("mkdir");
    image::GrayImage::from_pixel(5, 3, image::Luma([255])).save(d.join("masks/a.png")).expect("save mask");
    let par = d.join("x_par.txt");
    std::fs::write(&par, "1\na.png 10 0 2 0 10 1.5 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n").expect("write");
    let opts = DatasetOptions {
        dir: d.to_path_buf(),
        calibration: None, // found as the one *_par.txt
        views: ViewSelection::All,
        masks: MaskSource::Directory(d.join("masks")),
        load_images: true,
    };
    let e = dataset::load(&opts).expect_err("size mismatch");
    assert!(matches!(e, DatasetError::ImageSize { width: 5, expected_width: 4, .. }), "{e}");
    assert!(e.to_string().contains("masks/a.png") || e.to_string().contains("masks\\a.png"), "{e}");

    std::fs::write(&par, "2\na.png 10 0 2 0 10 1.5 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1\n").expect("write");
    let e = dataset::load(&opts).expect_err("count");
    assert!(matches!(e, DatasetError::ViewCount { declared: 2, found: 1, .. }), "{e}");

    std::fs::write(&par, "1\na.png 10 0 2 0 10 1.5 0 0 1 1 0 0 0 1 0 0 0 1 0 inf 1\n").expect("write");
    let e = dataset::load(&opts).expect_err("non-finite");
    assert!(e.to_string().contains("x_par.txt:2"), "{e}");

    let proj = d.join("p.txt");
    std::fs::write(&proj, "a.png 1 2 3 4 5 6 7 8 9 10 11\n").expect("write");
    let e = dataset::read_calibration(&proj).expect_err("11 numbers");
    assert!(matches!(e, DatasetError::ValueCount { line: 1, expected: 13, found: 12, .. }), "{e}");
    std::fs::write(&proj, "a.png 1 2 3 4 2 4 6 8 0 0 1 0\n").expect("write");
    assert!(matches!(dataset::read_calibration(&proj), Err(DatasetError::DegenerateProjection { line: 1, .. })));

    let e = dataset::load(&DatasetOptions { dir: d.join("nowhere"), ..opts.clone() }).expect_err("no dir");
    assert!(matches!(e, DatasetError::Read { .. }), "{e}");
    std::fs::remove_file(&par).expect("rm");
    let e = dataset::load(&opts).expect_err("no calibration");
    assert!(matches!(e, DatasetError::NoCalibration { .. }), "{e}");
}
