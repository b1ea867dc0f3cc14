//! Photo-consistency: generalized space carving and voxel colouring at 128³ and 256³ on a synthetic
//! textured sphere (36 views of 640x480 on a ring, a solid colour checker painted analytically),
//! with silhouettes, starting from the sphere grown by three voxels so every run has layers to carve.
//! For each size, the multi-sweep space carving (`carve_photo`) and the baseline that re-renders
//! whole-surface item buffers every iteration (`carve_photo_surface`) run once each on the same
//! input in the same run, and one line per case prints time, iterations, visits, carved and the
//! ratio baseline / sweeps; voxel colouring on a 7-view arc is timed too. Criterion then measures
//! voxel colouring at 128³ (one space carving run takes seconds, so those are timed once).
//! `PHOTO_BENCH_SIZES=128` (comma-separated) limits the sizes.
//!
//! `cargo bench --bench photo`.

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion};
use image::RgbImage;
use scanrig::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3, VoxelGrid};
use scanrig::pipeline::voxel_coloring::carve_photo_surface;
use scanrig::pipeline::{carve_photo, color_voxels, Mask, Occupancy, PhotoParams, PhotoView};

const CENTRE: [f64; 3] = [0.0, 0.0, 0.04];
const RADIUS: f64 = 0.035;

fn colour(p: &Vector3<f64>) -> [u8; 3] {
    // A solid checker of 12 mm cells (texture far coarser than a voxel everywhere; longitude sectors
    // would converge at the poles below the sampling rate and make every view disagree there).
    let cell = |x: f64| ((x / 0.012).floor() as i64).rem_euclid(2);
    let (band, sector) = (cell(p.z), (cell(p.x) + cell(p.y)) % 2);
    match (band, sector) {
        (0, 0) => [220, 60, 50],
        (0, _) => [60, 180, 70],
        (_, 0) => [70, 90, 210],
        _ => [230, 210, 80],
    }
}

fn views(n: usize) -> (Vec<CameraModel>, Vec<RgbImage>) {
    let c = Vector3::from(CENTRE);
    let cams: Vec<CameraModel> = (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
            let eye = c + Vector3::new(0.42 * a.cos(), 0.42 * a.sin(), 0.16);
            CameraModel {
                width: 640,
                height: 480,
                intrinsics: Intrinsics {
                    fx: 1600.0,
                    fy: 1600.0,
                    cx: 320.0,
                    cy: 240.0,
                    skew: 0.0,
                    k1: 0.0,
                    k2: 0.0,
                    ..Intrinsics::default()
                },
                pose: Pose::look_at(eye, c, Vector3::z()),
            }
        })
        .collect();
    let images = cams
        .iter()
        .map(|cam| {
            let o = cam.centre();
            RgbImage::from_fn(640, 480, |u, v| {
                let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5).normalize();
                let oc = o - c;
                let b = oc.dot(&d);
                let disc = b * b - (oc.norm_squared() - RADIUS * RADIUS);
                if disc < 0.0 {
                    return image::Rgb([0, 0, 0]);
                }
                image::Rgb(colour(&(o + d * (-b - disc.sqrt()))))
            })
        })
        .collect();
    (cams, images)
}

fn start(n: u32) -> Occupancy {
    let bbox = Aabb { min: [-0.045, -0.045, -0.005], max: [0.045, 0.045, 0.085] };
    let grid = VoxelGrid::from_resolution(&bbox, n);
    let grow = RADIUS + 3.0 * grid.voxel_size;
    Occupancy::from_fn(grid, |p| (p - Vector3::from(CENTRE)).norm() <= grow)
}

fn bench(c: &mut Criterion) {
    let (cams, images) = views(36);
    // Silhouettes as a scan has them: background pixels are never sampled.
    let masks: Vec<Mask> =
        images.iter().map(|i| Mask::from_fn(640, 480, |u, v| i.get_pixel(u, v).0 != [0, 0, 0])).collect();
    let all: Vec<PhotoView<'_>> = cams
        .iter()
        .zip(&images)
        .zip(&masks)
        .map(|((c, i), m)| PhotoView { camera: *c, image: i, mask: Some(m) })
        .collect();
    let arc: Vec<PhotoView<'_>> = all.iter().take(7).copied().collect();
    let params = PhotoParams { threshold: 20.0, min_cos: 0.3, ..PhotoParams::default() };
    let sizes: Vec<u32> = std::env::var("PHOTO_BENCH_SIZES")
        .ok()
        .map(|v| v.split(',').filter_map(|x| x.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![128, 256]);
    for &n in &sizes {
        let s = start(n);
        let t = Instant::now();
        let m = carve_photo(&s, &all, &params).expect("carve");
        let sweeps = t.elapsed().as_secs_f64();
        println!(
            "space-carving-photo (six-direction sweeps) {n}^3, 36 views: {sweeps:.2} s, {} iterations ({} sweeps), \
             {} visits, {} carved of {}",
            m.stats.iterations,
            m.stats.sweeps,
            m.stats.visits,
            m.stats.carved,
            s.count()
        );
        let t = Instant::now();
        let b = carve_photo_surface(&s, &all, &params).expect("carve");
        let base = t.elapsed().as_secs_f64();
        println!(
            "space-carving-photo baseline (whole-surface item buffers) {n}^3, 36 views: {base:.2} s, {} iterations, \
             {} visits, {} carved; baseline / sweeps = {:.2}",
            b.stats.iterations,
            b.stats.visits,
            b.stats.carved,
            base / sweeps
        );
        let t = Instant::now();
        let m = color_voxels(&s, &arc, &params).expect("ordinal order");
        println!(
            "voxel-coloring {n}^3, 7 views: {:.2} s, {} layers, {} visits, {} carved",
            t.elapsed().as_secs_f64(),
            m.stats.iterations,
            m.stats.visits,
            m.stats.carved
        );
    }
    let s = start(128);
    let mut g = c.benchmark_group("photo");
    g.sample_size(10);
    g.bench_function("voxel_coloring_128", |b| b.iter(|| black_box(color_voxels(&s, &arc, &params))));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
