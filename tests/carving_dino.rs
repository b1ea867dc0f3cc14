//! Space carving on the Middlebury dino data set (dinoSparseRing), from the small fixture in
//! `tests/fixtures/dino/`: the calibration file, the list of the 15 views with usable silhouettes, and
//! the recipe masks (threshold 0.19 on max(R,G,B), dilate 10 px, erode 7 px) stored as 1-bit PNGs.

mod shared_data;

use std::path::{Path, PathBuf};

use scanrig::dataset::{self, Dataset, DatasetOptions, MaskSource, ViewSelection};
use scanrig::geometry::{Aabb, VoxelGrid};
use scanrig::pipeline::{
    carve_dense, extract_surface, reprojection_iou, MeshParams, Occupancy, SilhouetteParams, SpaceCarver,
};

/// The tight bounding box given with the data set, metres.
const DINO_BOX: Aabb = Aabb { min: [-0.061897, -0.018874, -0.057845], max: [0.010897, 0.068227, 0.015495] };

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dino")
}

fn fixture() -> Dataset {
    let dir = fixture_dir();
    dataset::load(&DatasetOptions {
        dir: dir.clone(),
        calibration: Some(dir.join("dinoSR_par.txt")),
        views: ViewSelection::File(dir.join("dinoSR_good_silhouette_images.txt")),
        masks: MaskSource::Directory(dir.join("masks")),
        load_images: false,
    })
    .expect("the dino fixture loads")
}

fn carve(ds: &Dataset, n: u32) -> Occupancy {
    let mut carver = SpaceCarver::new(VoxelGrid::from_resolution(&DINO_BOX, n)).expect("carver");
    carver.add_views(&ds.carving_views()).expect("carve");
    carver.into_occupancy()
}

#[test]
fn dino_fixture_has_the_fifteen_good_views() {
    let ds = fixture();
    assert_eq!(ds.views.len(), 15);
    assert!(ds.views.iter().all(|v| v.camera.width == 640 && v.camera.height == 480));
    assert!(ds.views.iter().all(|v| v.name != "dinoSR0006.png"));
    ds.check_box_seen(&DINO_BOX).expect("the cameras see the box");
    let far = Aabb { min: [10.0, 10.0, 10.0], max: [10.1, 10.1, 10.1] };
    assert!(ds.check_box_seen(&far).is_err());
}

#[test]
fn dino_hierarchical_equals_dense_at_128() {
    let ds = fixture();
    let grid = VoxelGrid::from_resolution(&DINO_BOX, 128);
    let dense = carve_dense(&grid, &ds.carving_views()).expect("dense");
    let hier = carve(&ds, 128);
    assert_eq!(hier.first_difference(&dense), None);
    // Incremental, as frames would arrive during a scan.
    let mut carver = SpaceCarver::new(grid).expect("carver");
    for v in &ds.views {
        carver.add_view(&v.camera, &v.mask).expect("add_view");
    }
    assert!(carver.occupancy().same_voxels(&dense));
    let count = dense.count();
    // 256 / 128 = 2: about an eighth of the 256 figure.
    assert!((300_000..450_000).contains(&count), "{count} voxels at 128");
}

#[test]
fn dino_at_256_matches_the_reference_count_and_reprojects() {
    let ds = fixture();
    let occ = carve(&ds, 256);
    assert_eq!(occ.grid().dims, [214, 256, 216]);
    let count = occ.count();
    let reference = 2_999_881f64;
    let rel = (count as f64 - reference).abs() / reference;
    println!("dino 256: {count} voxels (reference 2,999,881, {:.4}% off)", rel * 100.0);
    assert!(rel < 0.01, "{count} voxels, {:.3}% from the reference", rel * 100.0);
    let ious = reprojection_iou(&occ, &ds.carving_views());
    let mean = ious.iter().map(|x| x.expect("sizes match")).sum::<f64>() / ious.len() as f64;
    println!("dino 256: mean re-projection IoU {mean:.4}");
    assert!(mean >= 0.97, "mean re-projection IoU {mean}");
    let (_, _, mixed) = occ.brick_census();
    assert!(mixed > 0 && occ.memory_bytes() < 16 << 20, "{} bytes", occ.memory_bytes());
}

#[test]
fn dino_on_the_grown_box_matches_the_reference_count() {
    // The data set's box grown by 5 mm on every side, 256 voxels along its longest side.
    let grown = Aabb { min: DINO_BOX.min.map(|x| x - 0.005), max: DINO_BOX.max.map(|x| x + 0.005) };
    let ds = fixture();
    let mut carver = SpaceCarver::new(VoxelGrid::from_resolution(&grown, 256)).expect("carver");
    carver.add_views(&ds.carving_views()).expect("carve");
    assert_eq!(carver.grid().dims, [219, 256, 220]);
    let count = carver.occupancy().count();
    println!("dino grown box 256: {count} voxels (reference 2,237,853)");
    assert!((count as f64 - 2_237_853.0).abs() / 2_237_853.0 < 0.01, "{count}");
}

#[test]
fn dino_mesh_is_watertight() {
    let ds = fixture();
    let occ = carve(&ds, 96);
    let mesh = extract_surface(&occ, &MeshParams { smooth_radius: 1, relax_iterations: 0, remove_handles: false })
        .expect("mesh");
    assert_eq!(mesh.open_or_misoriented_edges(), 0);
    let v = mesh.signed_volume();
    let vox = occ.volume_m3();
    assert!(v > 0.0 && (v - vox).abs() / vox < 0.15, "mesh {v} m3, voxels {vox} m3");
}

/// The recipe masks extracted from the full data set (`../shared/data/middlebury-dino-sparse-ring`)
/// equal the stored fixture masks. With `SCANRIG_REGENERATE_DINO_MASKS=1` it first rewrites the
/// fixture masks from the data set.
#[test]
fn fixture_masks_match_the_data_set() {
    let Some(src) = shared_data::dataset("middlebury-dino-sparse-ring") else { return };
    let regenerate = std::env::var_os("SCANRIG_REGENERATE_DINO_MASKS").is_some();
    let ds = dataset::load(&DatasetOptions {
        dir: src.clone(),
        calibration: Some(src.join("dinoSR_par.txt")),
        views: ViewSelection::File(src.join("dinoSR_good_silhouette_images.txt")),
        masks: MaskSource::Extract(SilhouetteParams::MIDDLEBURY),
        load_images: false,
    })
    .expect("the full data set loads");
    let out = fixture_dir().join("masks");
    std::fs::create_dir_all(&out).expect("mask directory");
    for v in ds.views.iter().filter(|_| regenerate) {
        let stem = Path::new(&v.name).file_stem().and_then(|s| s.to_str()).expect("stem").to_string();
        let (w, h) = (v.mask.width(), v.mask.height());
        let mut packed = vec![0u8; (w as usize).div_ceil(8) * h as usize];
        let row = (w as usize).div_ceil(8);
        for y in 0..h {
            for x in 0..w {
                if v.mask.get(x, y) {
                    packed[y as usize * row + x as usize / 8] |= 0x80 >> (x % 8);
                }
            }
        }
        let file = std::fs::File::create(out.join(format!("{stem}.png"))).expect("create");
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::One);
        enc.set_compression(png::Compression::High);
        let mut writer = enc.write_header().expect("header");
        writer.write_image_data(&packed).expect("data");
    }
    let stored = fixture();
    for (a, b) in stored.views.iter().zip(&ds.views) {
        assert_eq!(a.mask, b.mask, "{}", a.name);
    }
}
