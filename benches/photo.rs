//! Photo-consistency: generalized space carving and voxel colouring at 128³ and 256³ on a synthetic
//! textured sphere (36 views of 640x480 on a ring, a solid colour checker painted analytically),
//! with silhouettes, starting from the sphere grown by three voxels so every run has layers to carve.
//! For each size, the incremental space carving (`carve_photo`) and the multi-sweep carver it
//! replaced (`carve_photo_sweeps`, the baseline) run once each on the same input in the same run;
//! voxel colouring on a 7-view arc (`color_voxels`) against the version that visits every voxel
//! (`color_voxels_every_voxel`). One line per case prints time, iterations, visits, carved and the
//! voxels where the two results differ, and a `PERF` line (JSON) with the ratio baseline / ours for
//! `benches/perf_table.py`, and the IoU of each result with the true sphere. Criterion then measures
//! voxel colouring at 128³ (one space carving run takes seconds, so those are timed once).
//! `PHOTO_BENCH_SIZES=128` (comma-separated) limits the sizes; `PHOTO_BENCH_NO_BASELINE=1` skips the
//! baselines (the multi-sweep carver takes minutes at 256³).
//!
//! `cargo bench --bench photo`.

use std::hint::black_box;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion};
use image::RgbImage;
use scanrig::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3, VoxelGrid};
use scanrig::pipeline::voxel_coloring::{carve_photo_sweeps, color_voxels_every_voxel};
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

/// The sphere of radius `r` on the bench's `n`³ grid.
fn sphere(n: u32, r: f64) -> Occupancy {
    let bbox = Aabb { min: [-0.045, -0.045, -0.005], max: [0.045, 0.045, 0.085] };
    let grid = VoxelGrid::from_resolution(&bbox, n);
    Occupancy::from_fn(grid, |p| (p - Vector3::from(CENTRE)).norm() <= r)
}

/// The start: the sphere grown by three voxels.
fn start(n: u32) -> Occupancy {
    let voxel = sphere(n, RADIUS).grid().voxel_size;
    sphere(n, RADIUS + 3.0 * voxel)
}

/// Voxels in one occupancy and not the other.
fn differing(a: &Occupancy, b: &Occupancy) -> u64 {
    let d = a.grid().dims;
    let mut n = 0;
    for k in 0..d[2] {
        for j in 0..d[1] {
            for i in 0..d[0] {
                n += u64::from(a.get(i, j, k) != b.get(i, j, k));
            }
        }
    }
    n
}

/// One line `benches/perf_table.py` reads: method, case, our time and the baseline's, seconds.
fn perf_line(method: &str, case: &str, ours: f64, baseline: &str, base: f64) {
    println!(
        "PERF {}",
        serde_json::json!({"method": method, "case": case, "ours_s": ours, "peer": baseline, "peer_s": base,
            "ratio": base / ours})
    );
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
    let skip_baseline = std::env::var_os("PHOTO_BENCH_NO_BASELINE").is_some();
    for &n in &sizes {
        let s = start(n);
        let t = Instant::now();
        let m = carve_photo(&s, &all, &params).expect("carve");
        let ours = t.elapsed().as_secs_f64();
        let truth = sphere(n, RADIUS);
        let iou = |o: &Occupancy| o.iou_and_containment(&truth).map_or(f64::NAN, |x| x.iou);
        println!(
            "space-carving-photo (incremental item buffers) {n}^3, 36 views: {ours:.3} s, {} iterations, {} visits, \
             {} carved of {}; IoU with the true sphere {:.4} (start {:.4})",
            m.stats.iterations,
            m.stats.visits,
            m.stats.carved,
            s.count(),
            iou(&m.occupancy),
            iou(&s)
        );
        if !skip_baseline {
            let t = Instant::now();
            let b = carve_photo_sweeps(&s, &all, &params).expect("carve");
            let base = t.elapsed().as_secs_f64();
            let diff = differing(&m.occupancy, &b.occupancy);
            println!(
                "space-carving-photo baseline (multi-sweep, before) {n}^3, 36 views: {base:.2} s, {} iterations \
                 ({} sweeps), {} visits, {} carved; voxels differing from ours {diff}; IoU with the true sphere {:.4}",
                b.stats.iterations,
                b.stats.sweeps,
                b.stats.visits,
                b.stats.carved,
                iou(&b.occupancy)
            );
            perf_line("space-carving-photo", &format!("{n}^3, 36 views 640x480"), ours, "multi-sweep (before)", base);
        }
        let t = Instant::now();
        let m = color_voxels(&s, &arc, &params).expect("ordinal order");
        let ours = t.elapsed().as_secs_f64();
        println!(
            "voxel-coloring {n}^3, 7 views: {ours:.3} s, {} layers, {} visits, {} carved",
            m.stats.iterations, m.stats.visits, m.stats.carved
        );
        if !skip_baseline {
            let t = Instant::now();
            let b = color_voxels_every_voxel(&s, &arc, &params).expect("ordinal order");
            let base = t.elapsed().as_secs_f64();
            println!(
                "voxel-coloring baseline (every voxel, before) {n}^3, 7 views: {base:.3} s, {} visits, {} carved; \
                 voxels differing from ours {}",
                b.stats.visits,
                b.stats.carved,
                differing(&m.occupancy, &b.occupancy)
            );
            perf_line("voxel-coloring", &format!("{n}^3, 7 views 640x480"), ours, "every voxel (before)", base);
        }
    }
    let s = start(128);
    let mut g = c.benchmark_group("photo");
    g.sample_size(10);
    g.bench_function("voxel_coloring_128", |b| b.iter(|| black_box(color_voxels(&s, &arc, &params))));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
