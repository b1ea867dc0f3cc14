//! Loading calibrated image sets from disk: the projection-matrix format against the Middlebury one on
//! the dino fixture, and typed errors that name the file (and line) for broken data sets.

use std::path::{Path, PathBuf};

use nalgebra::Rotation3;
use scanrig::calibration::opencv_yaml;
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

/// OpenCV FileStorage with one camera and per-view extrinsics (`extrinsic_parameters`, Rodrigues
/// vector + translation per row, as OpenCV's calibration sample writes them) and an `images`
/// sequence, YAML and XML: the same hull as the Middlebury file it was written from. The stated
/// image size is checked against the masks.
#[test]
fn opencv_file_storage_with_per_view_extrinsics_gives_the_same_hull_as_the_par_file() {
    let dir = fixture_dir();
    let good = ViewSelection::File(dir.join("dinoSR_good_silhouette_images.txt"));
    let par = dataset::load(&options(dir.join("dinoSR_par.txt"), good)).expect("par");
    let k = par.views[0].camera.intrinsics;
    assert!(par.views.iter().all(|v| v.camera.intrinsics == k), "the dino has one camera");
    let rows: Vec<String> = par
        .views
        .iter()
        .map(|v| {
            let r = Rotation3::from_matrix(&v.camera.pose.rotation).scaled_axis();
            let t = v.camera.pose.translation;
            [r.x, r.y, r.z, t.x, t.y, t.z].map(|x| format!("{x:.17e}")).join(", ")
        })
        .collect();
    let names: Vec<&str> = par.views.iter().map(|v| v.name.as_str()).collect();
    let tmp = tempfile::tempdir().expect("tempdir");
    let camera = opencv_yaml::camera_yaml(&k, 640, 480, 0.0);
    let yaml = format!(
        "{camera}extrinsic_parameters: !!opencv-matrix\n   rows: {}\n   cols: 6\n   dt: d\n   data: [ {} ]\nimages:\n{}",
        rows.len(),
        rows.join(",\n       "),
        names.iter().map(|n| format!("   - \"{n}\"\n")).collect::<String>()
    );
    let d = k.distortion();
    let xml = format!(
        "<?xml version=\"1.0\"?>\n<opencv_storage>\n<image_width>640</image_width>\n<image_height>480</image_height>\n\
         <camera_matrix type_id=\"opencv-matrix\">\n  <rows>3</rows>\n  <cols>3</cols>\n  <dt>d</dt>\n  <data>\n    \
         {:.17e} {:.17e} {:.17e} 0. {:.17e} {:.17e} 0. 0. 1.</data></camera_matrix>\n\
         <distortion_coefficients type_id=\"opencv-matrix\">\n  <rows>5</rows>\n  <cols>1</cols>\n  <dt>d</dt>\n  \
         <data>{} {} {} {} {}</data></distortion_coefficients>\n\
         <extrinsic_parameters type_id=\"opencv-matrix\">\n  <rows>{}</rows>\n  <cols>6</cols>\n  <dt>d</dt>\n  \
         <data>\n    {}</data></extrinsic_parameters>\n<images>\n  {}</images>\n</opencv_storage>\n",
        k.fx,
        k.skew,
        k.cx - 0.5,
        k.fy,
        k.cy - 0.5,
        d[0],
        d[1],
        d[2],
        d[3],
        d[4],
        rows.len(),
        rows.join("\n    ").replace(',', ""),
        names.join(" ")
    );
    let grid = VoxelGrid::from_resolution(&DINO_BOX, 64);
    let mut reference = SpaceCarver::new(grid).expect("carver");
    reference.add_views(&par.carving_views()).expect("carve");
    for (file, text) in [("calib.yml", &yaml), ("calib.xml", &xml)] {
        let path = tmp.path().join(file);
        std::fs::write(&path, text).expect("write");
        let ds = dataset::load(&options(path.clone(), ViewSelection::All)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(ds.views.len(), 15, "{file}");
        for (a, b) in par.views.iter().zip(&ds.views) {
            assert_eq!(a.name, b.name);
            assert!((a.camera.intrinsics.cx - b.camera.intrinsics.cx).abs() < 1e-9, "{file}");
            assert!((a.camera.pose.translation - b.camera.pose.translation).norm() < 1e-12, "{file}");
            assert!((a.camera.pose.rotation - b.camera.pose.rotation).norm() < 1e-4, "{file}");
        }
        let mut carver = SpaceCarver::new(grid).expect("carver");
        carver.add_views(&ds.carving_views()).expect("carve");
        let o = reference.occupancy().iou_and_containment(carver.occupancy()).expect("same grid");
        assert!(o.iou > 0.9999, "{file}: {o:?}");
    }
    // Calibrated for another image size: an error naming the calibration and the mask.
    let path = tmp.path().join("half.yml");
    std::fs::write(&path, yaml.replace("image_width: 640", "image_width: 320")).expect("write");
    let e = dataset::load(&options(path, ViewSelection::All)).expect_err("size");
    assert!(matches!(e, DatasetError::CalibratedSize { width: 640, calibrated_width: 320, .. }), "{e}");
    assert!(e.to_string().contains("half.yml:") && e.to_string().contains("320x480"), "{e}");
    // One name short: the error names the file, the entry and both counts.
    let path = tmp.path().join("short.yml");
    std::fs::write(&path, yaml.replace(&format!("   - \"{}\"\n", names[14]), "")).expect("write");
    let e = dataset::read_calibration(&path).expect_err("short");
    let text = e.to_string();
    assert!(
        text.contains("short.yml:") && text.contains("images") && text.contains("14 image names for the 15"),
        "{text}"
    );
    // No names at all.
    let path = tmp.path().join("nameless.yml");
    std::fs::write(&path, &yaml[..yaml.find("images:").expect("images")]).expect("write");
    let text = dataset::read_calibration(&path).expect_err("nameless").to_string();
    assert!(text.contains("nameless.yml") && text.contains("images"), "{text}");
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
