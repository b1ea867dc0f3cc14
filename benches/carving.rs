//! Space carving: hierarchical (octree over brick occupancy) against the dense per-voxel reference, on the
//! Middlebury dino (15 views, recipe masks from the test fixture, the data set's tight box) and on a
//! synthetic seven-sphere scene (640x480 masks, cameras on a ring). Prints one summary line per case
//! with the ratio; criterion then measures the hierarchical carver with a few samples.
//!
//! `cargo bench --bench carving`. The carver is created once per grid and reset between runs (its
//! buffers are reused); the summed-area tables are rebuilt on every run and counted in the carve time.

use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion};
use scanrig::dataset::{self, DatasetOptions, MaskSource, ViewSelection};
use scanrig::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3, VoxelGrid};
use scanrig::pipeline::{carve_dense, extract_surface, Mask, MeshParams, SpaceCarver, View};

const DINO_BOX: Aabb = Aabb { min: [-0.061897, -0.018874, -0.057845], max: [0.010897, 0.068227, 0.015495] };

struct Scene {
    cams: Vec<CameraModel>,
    masks: Vec<Mask>,
}

impl Scene {
    fn views(&self) -> Vec<View<'_>> {
        self.cams.iter().zip(&self.masks).map(|(c, m)| View { camera: *c, mask: m }).collect()
    }
}

fn dino() -> Scene {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/dino");
    let ds = dataset::load(&DatasetOptions {
        dir: dir.clone(),
        calibration: Some(dir.join("dinoSR_par.txt")),
        views: ViewSelection::File(dir.join("dinoSR_good_silhouette_images.txt")),
        masks: MaskSource::Directory(dir.join("masks")),
        load_images: false,
    })
    .expect("dino fixture");
    Scene { cams: ds.views.iter().map(|v| v.camera).collect(), masks: ds.views.into_iter().map(|v| v.mask).collect() }
}

const SPHERES: [([f64; 3], f64); 7] = [
    ([0.0, 0.0, 0.05], 0.035),
    ([0.04, 0.01, 0.07], 0.02),
    ([-0.035, 0.02, 0.03], 0.025),
    ([0.01, -0.04, 0.09], 0.015),
    ([-0.02, -0.03, 0.0], 0.02),
    ([0.03, 0.035, 0.01], 0.018),
    ([-0.01, 0.045, 0.1], 0.012),
];

fn synthetic(n_views: usize) -> Scene {
    let cams: Vec<CameraModel> = (0..n_views)
        .map(|i| {
            let a = i as f64 / n_views as f64 * std::f64::consts::TAU;
            let h = 0.05 + 0.15 * ((i % 3) as f64 - 1.0);
            CameraModel {
                width: 640,
                height: 480,
                intrinsics: Intrinsics {
                    fx: 1400.0,
                    fy: 1400.0,
                    cx: 320.0,
                    cy: 240.0,
                    skew: 0.0,
                    k1: 0.0,
                    k2: 0.0,
                    ..Intrinsics::default()
                },
                pose: Pose::look_at(
                    Vector3::new(0.5 * a.cos(), 0.5 * a.sin(), h),
                    Vector3::new(0.0, 0.0, 0.05),
                    Vector3::z(),
                ),
            }
        })
        .collect();
    let masks = cams
        .iter()
        .map(|c| {
            let o = c.centre();
            Mask::from_fn(c.width, c.height, |u, v| {
                let d = c.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                SPHERES.iter().any(|&(s, r)| {
                    let oc = o - Vector3::from(s);
                    let b = oc.dot(&d);
                    b * b - (oc.norm_squared() - r * r) >= 0.0
                })
            })
        })
        .collect();
    Scene { cams, masks }
}

const SYNTH_BOX: Aabb = Aabb { min: [-0.065, -0.06, -0.025], max: [0.065, 0.07, 0.115] };

fn time_hier(carver: &mut SpaceCarver, views: &[View<'_>], runs: usize) -> (Duration, u64) {
    let mut best = Duration::MAX;
    let mut count = 0;
    for _ in 0..runs {
        carver.reset();
        let t = Instant::now();
        let stats = carver.add_views(views).expect("carve");
        best = best.min(t.elapsed());
        count = stats.occupied;
    }
    (best, count)
}

fn time_dense(grid: &VoxelGrid, views: &[View<'_>], runs: usize) -> (Duration, u64) {
    let mut best = Duration::MAX;
    let mut count = 0;
    for _ in 0..runs {
        let t = Instant::now();
        let occ = carve_dense(grid, views).expect("dense");
        best = best.min(t.elapsed());
        count = occ.count();
    }
    (best, count)
}

fn summary(name: &str, scene: &Scene, bbox: &Aabb, n: u32, dense_runs: usize) {
    let views = scene.views();
    let grid = VoxelGrid::from_resolution(bbox, n);
    let mut carver = SpaceCarver::new(grid).expect("carver");
    let (h, hc) = time_hier(&mut carver, &views, 5);
    let (d, dc) = time_dense(&grid, &views, dense_runs);
    let same = if hc == dc { "same count" } else { "COUNTS DIFFER" };
    println!(
        "{name} {n}^3 ({}x{}x{}, {} views): hierarchical {:.1} ms, dense {:.1} ms, ratio {:.1} ({hc} voxels, {same}, {} KiB)",
        grid.dims[0],
        grid.dims[1],
        grid.dims[2],
        views.len(),
        h.as_secs_f64() * 1e3,
        d.as_secs_f64() * 1e3,
        d.as_secs_f64() / h.as_secs_f64(),
        carver.occupancy().memory_bytes() / 1024,
    );
}

fn benches(c: &mut Criterion) {
    println!("threads: {}", rayon::current_num_threads());
    let dino = dino();
    let s24 = synthetic(24);
    let s72 = synthetic(72);
    summary("dino", &dino, &DINO_BOX, 128, 3);
    summary("dino", &dino, &DINO_BOX, 256, 2);
    summary("dino", &dino, &DINO_BOX, 512, 1);
    summary("synthetic", &s24, &SYNTH_BOX, 128, 3);
    summary("synthetic", &s24, &SYNTH_BOX, 256, 2);
    summary("synthetic", &s72, &SYNTH_BOX, 512, 1);

    {
        let mut carver = SpaceCarver::new(VoxelGrid::from_resolution(&DINO_BOX, 256)).expect("carver");
        carver.add_views(&dino.views()).expect("carve");
        let t = Instant::now();
        let mesh = extract_surface(
            carver.occupancy(),
            &MeshParams { smooth_radius: 1, relax_iterations: 0, remove_handles: false },
        )
        .expect("mesh");
        println!(
            "dino 256^3 surface (smooth radius 1): {} triangles in {:.1} ms",
            mesh.triangles.len(),
            t.elapsed().as_secs_f64() * 1e3
        );
    }

    let mut group = c.benchmark_group("carving");
    group.sample_size(10).warm_up_time(Duration::from_millis(300)).measurement_time(Duration::from_secs(2));
    for (name, scene, bbox, n) in [
        ("dino_256", &dino, &DINO_BOX, 256u32),
        ("dino_512", &dino, &DINO_BOX, 512),
        ("synthetic24_256", &s24, &SYNTH_BOX, 256),
        ("synthetic72_512", &s72, &SYNTH_BOX, 512),
    ] {
        let views = scene.views();
        let mut carver = SpaceCarver::new(VoxelGrid::from_resolution(bbox, n)).expect("carver");
        group.bench_function(format!("hierarchical_{name}"), |b| {
            b.iter(|| {
                carver.reset();
                black_box(carver.add_views(&views).expect("carve"))
            })
        });
    }
    let views = dino.views();
    let grid = VoxelGrid::from_resolution(&DINO_BOX, 128);
    group.bench_function("dense_dino_128", |b| b.iter(|| black_box(carve_dense(&grid, &views).expect("dense"))));
    group.finish();
}

criterion_group!(carving, benches);
criterion_main!(carving);
