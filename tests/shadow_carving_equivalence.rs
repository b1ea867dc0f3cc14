//! The surface-only, incremental shadow carving (`pipeline::carve_shadows`, `ShadowCarver`) against
//! the implementation it replaced (`benches/shadow_baseline.rs`: sweeps over every hull voxel in a
//! view's shadow), on a small bowl whose pit only the shadows can carve: the same voxels, whether the
//! views come all at once or position by position while the hull shrinks.

#[path = "../benches/shadow_baseline.rs"]
mod shadow_baseline;

use scanrig::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3, VoxelGrid};
use scanrig::pipeline::{carve_shadows, Mask, Occupancy, ShadowCarveParams, ShadowCarver, ShadowView};

const RADIUS: f64 = 0.035;
const PIT_RADIUS: f64 = 0.027;

fn centre() -> Vector3<f64> {
    Vector3::new(0.0, 0.0, 0.035)
}

fn bowl(p: &Vector3<f64>) -> bool {
    (p - centre()).norm() <= RADIUS && (p - Vector3::new(0.0, 0.0, 0.06)).norm() > PIT_RADIUS
}

fn around(az: f64, el: f64, dist: f64) -> Vector3<f64> {
    let (az, el) = (az.to_radians(), el.to_radians());
    centre() + Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin()) * dist
}

/// The bowl's shadows under `light` as `cam` sees them (marching the rays), eroded by 1 px.
fn shadow(cam: &CameraModel, light: &Vector3<f64>) -> Mask {
    let o = cam.centre();
    let raw = Mask::from_fn(cam.width, cam.height, |u, v| {
        let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5).normalize();
        let Some(t) = (300..700).map(|s| s as f64 * 1e-3).find(|&t| bowl(&(o + d * t))) else {
            return false;
        };
        let p = o + d * (t - 1e-3);
        let to_light = (light - p).normalize();
        (1..200).any(|s| bowl(&(p + to_light * (s as f64 * 5e-4))))
    });
    Mask::from_fn(cam.width, cam.height, |u, v| {
        u > 0
            && v > 0
            && u + 1 < cam.width
            && v + 1 < cam.height
            && (0..3).all(|dv| (0..3).all(|du| raw.get(u + du - 1, v + dv - 1)))
    })
}

#[test]
fn new_carving_equals_the_old_one_at_once_and_position_by_position() {
    let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.045, -0.045, 0.0], max: [0.045, 0.045, 0.09] }, 48);
    let vs = grid.voxel_size;
    // Where the two spheres meet.
    let rim = (RADIUS.powi(2) - PIT_RADIUS.powi(2)) / (2.0 * (0.06 - 0.035)) + (0.035 + 0.06) / 2.0;
    let hull = Occupancy::from_fn(grid, |p| (p - centre()).norm() <= RADIUS + vs && p.z <= rim + vs);
    let positions: Vec<(CameraModel, Vec<Vector3<f64>>)> = (0..6)
        .map(|i| {
            let az = i as f64 * 60.0;
            let cam = CameraModel {
                width: 160,
                height: 120,
                intrinsics: Intrinsics { fx: 300.0, fy: 300.0, cx: 80.0, cy: 60.0, ..Intrinsics::default() },
                pose: Pose::look_at(around(az, 56.0, 0.5), centre(), Vector3::z()),
            };
            let lights = [(180.0, 85.0), (240.0, 65.0), (0.0, 30.0)].iter().map(|&(d, el)| around(az + d, el, 0.5));
            (cam, lights.collect())
        })
        .collect();
    let masks: Vec<Vec<Mask>> =
        positions.iter().map(|(cam, lights)| lights.iter().map(|l| shadow(cam, l)).collect()).collect();
    let views: Vec<ShadowView<'_>> = positions
        .iter()
        .zip(&masks)
        .flat_map(|((cam, lights), ms)| {
            lights.iter().zip(ms).map(|(l, m)| ShadowView { camera: *cam, light_m: *l, shadow: m })
        })
        .collect();
    let params = ShadowCarveParams::default();
    let (old, old_stats) = shadow_baseline::carve_shadows_baseline(&hull, &views, &params);
    let (new, stats) = carve_shadows(&hull, &views, &params).expect("valid input");
    assert!(old_stats.removed > 50, "the case must carve: {} voxels", old_stats.removed);
    assert!(old_stats.converged && stats.converged);
    assert_eq!(new.first_difference(&old), None, "{} voxels removed, the old way {}", stats.removed, old_stats.removed);
    assert_eq!(stats.removed, old_stats.removed);
    // Position by position, the hull shrinking from a loose box to `hull` meanwhile.
    let looser = [
        Occupancy::from_fn(grid, |p| p.z <= rim + 4.0 * vs),
        Occupancy::from_fn(grid, |p| (p - centre()).norm() <= RADIUS + 4.0 * vs && p.z <= rim + 2.0 * vs),
    ];
    let mut carver = ShadowCarver::new(&looser[0], &params).expect("grid");
    for (i, ((cam, lights), ms)) in positions.iter().zip(&masks).enumerate() {
        match i {
            2 => carver.restrict(&looser[1]).expect("same grid"),
            5 => carver.restrict(&hull).expect("same grid"),
            _ => 0,
        };
        carver.add_position(*cam, lights.iter().copied().zip(ms.iter().cloned()).collect()).expect("valid");
    }
    assert_eq!(carver.occupancy().first_difference(&old), None);
    // The carving keeps the bowl.
    let truth = Occupancy::from_fn(grid, |p| bowl(&p));
    let fit = new.iou_and_containment(&truth).expect("same grid");
    let before = hull.iou_and_containment(&truth).expect("same grid");
    assert!(fit.iou > before.iou, "IoU {} -> {}", before.iou, fit.iou);
}
