//! The hierarchical carver against the dense reference on synthetic scenes rendered through known
//! cameras: with and without lens distortion, with the object partly out of frame, and with a camera
//! inside the grid (cells straddling the camera plane).

use scanrig::geometry::{Aabb, CameraModel, Intrinsics, Pose, Vector3, VoxelGrid};
use scanrig::pipeline::{carve_dense, reprojection_iou, Mask, Occupancy, SpaceCarver, View};

#[derive(Clone, Copy)]
enum Shape {
    Sphere { c: [f64; 3], r: f64 },
    Box { min: [f64; 3], max: [f64; 3] },
}

impl Shape {
    fn contains(&self, p: &Vector3<f64>) -> bool {
        match *self {
            Shape::Sphere { c, r } => (p - Vector3::from(c)).norm() < r,
            Shape::Box { min, max } => (0..3).all(|a| p[a] > min[a] && p[a] < max[a]),
        }
    }

    /// Does the ray `o + t d`, t > 0, hit the shape?
    fn hit(&self, o: &Vector3<f64>, d: &Vector3<f64>) -> bool {
        match *self {
            Shape::Sphere { c, r } => {
                let oc = o - Vector3::from(c);
                let b = oc.dot(d);
                let disc = b * b - (oc.norm_squared() - r * r);
                disc >= 0.0 && (-b + disc.sqrt()) > 0.0
            }
            Shape::Box { min, max } => {
                let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                for a in 0..3 {
                    let inv = 1.0 / d[a];
                    let (mut ta, mut tb) = ((min[a] - o[a]) * inv, (max[a] - o[a]) * inv);
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                    }
                    t0 = t0.max(ta);
                    t1 = t1.min(tb);
                }
                t0 <= t1
            }
        }
    }
}

fn scene() -> Vec<Shape> {
    vec![
        Shape::Sphere { c: [0.0, 0.0, 0.05], r: 0.04 },
        Shape::Sphere { c: [0.045, 0.02, 0.08], r: 0.02 },
        Shape::Box { min: [-0.06, -0.03, 0.0], max: [-0.02, 0.01, 0.03] },
        Shape::Sphere { c: [-0.01, -0.05, 0.1], r: 0.015 },
    ]
}

fn render(cam: &CameraModel, shapes: &[Shape]) -> Mask {
    let o = cam.centre();
    Mask::from_fn(cam.width, cam.height, |u, v| {
        let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
        shapes.iter().any(|s| s.hit(&o, &d))
    })
}

fn ring(n: usize, distance: f64, k1: f64, k2: f64, focal: f64) -> Vec<CameraModel> {
    (0..n)
        .map(|i| {
            let a = (i as f64 / n as f64) * std::f64::consts::TAU;
            let h = 0.05 + 0.12 * ((i % 3) as f64 - 1.0);
            let eye = Vector3::new(distance * a.cos(), distance * a.sin(), h);
            CameraModel {
                width: 160,
                height: 120,
                intrinsics: Intrinsics { k1, k2, ..Intrinsics::new(focal, focal, 80.0, 60.0) },
                pose: Pose::look_at(eye, Vector3::new(0.0, 0.0, 0.05), Vector3::z()),
            }
        })
        .collect()
}

fn grid(n: u32) -> VoxelGrid {
    VoxelGrid::from_resolution(&Aabb { min: [-0.08, -0.075, -0.01], max: [0.075, 0.07, 0.13] }, n)
}

fn check_exact(cams: &[CameraModel], n: u32, min_iou: f64) -> Occupancy {
    let shapes = scene();
    let masks: Vec<Mask> = cams.iter().map(|c| render(c, &shapes)).collect();
    let views: Vec<View> = cams.iter().zip(&masks).map(|(c, m)| View { camera: *c, mask: m }).collect();
    let g = grid(n);
    let dense = carve_dense(&g, &views).expect("dense");
    let mut carver = SpaceCarver::new(g).expect("carver");
    carver.add_views(&views).expect("batch");
    let diff = carver.occupancy().first_difference(&dense);
    assert_eq!(diff, None, "hierarchical and dense differ at voxel {diff:?}");
    // Incremental, one view at a time, on the same (reset) carver.
    carver.reset();
    for v in &views {
        carver.add_view(&v.camera, v.mask).expect("incremental");
    }
    assert!(carver.occupancy().same_voxels(&dense), "incremental result differs from dense");
    assert_eq!(carver.views_applied(), views.len());
    // The hull contains (nearly all of) the truth and is not trivially full.
    let truth = Occupancy::from_fn(g, |p| shapes.iter().any(|s| s.contains(&p)));
    let o = dense.iou_and_containment(&truth).expect("same grid");
    assert!(o.containment > 0.97, "containment {}", o.containment);
    assert!(o.iou > min_iou, "iou {}", o.iou);
    assert!(dense.count() < g.len() as u64 * 9 / 10);
    dense
}

#[test]
fn hierarchical_equals_dense_pinhole() {
    let occ = check_exact(&ring(12, 0.5, 0.0, 0.0, 300.0), 64, 0.3);
    let shapes = scene();
    let cams = ring(12, 0.5, 0.0, 0.0, 300.0);
    let masks: Vec<Mask> = cams.iter().map(|c| render(c, &shapes)).collect();
    let views: Vec<View> = cams.iter().zip(&masks).map(|(c, m)| View { camera: *c, mask: m }).collect();
    let ious = reprojection_iou(&occ, &views);
    let mean = ious.iter().map(|x| x.expect("same size")).sum::<f64>() / ious.len() as f64;
    assert!(mean > 0.9, "mean re-projection IoU {mean}");
}

#[test]
fn hierarchical_equals_dense_with_distortion() {
    check_exact(&ring(10, 0.45, -0.25, 0.08, 280.0), 57, 0.3);
    check_exact(&ring(7, 0.45, 0.15, -0.05, 250.0), 40, 0.3);
}

#[test]
fn hierarchical_equals_dense_with_tangential_and_k3_distortion() {
    // OpenCV's full five-term model: the carver's cells fall back to per-voxel tests where the
    // interval bound (radial k1, k2 only) does not hold, and must still equal the dense reference.
    let mut cams = ring(9, 0.45, -0.2, 0.05, 270.0);
    for (i, c) in cams.iter_mut().enumerate() {
        let s = if i % 2 == 0 { 1.0 } else { -1.0 };
        c.intrinsics = c.intrinsics.with_distortion([-0.2, 0.05, 2e-3 * s, -1.5e-3, 0.04 * s]);
    }
    check_exact(&cams, 48, 0.3);
}

#[test]
fn hierarchical_equals_dense_partly_out_of_frame() {
    // Close cameras with long lenses: the object overflows the image in every view.
    check_exact(&ring(9, 0.25, 0.0, 0.0, 420.0), 61, 0.1);
    check_exact(&ring(8, 0.22, -0.1, 0.0, 380.0), 48, 0.1);
}

#[test]
fn camera_inside_the_grid_keeps_what_is_behind_it() {
    let shapes = scene();
    let mut cams = ring(6, 0.5, 0.0, 0.0, 300.0);
    // A camera inside the grid box looking along +x: half of the grid is behind it.
    cams.push(CameraModel {
        width: 160,
        height: 120,
        intrinsics: Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 80.0,
            cy: 60.0,
            skew: 0.0,
            k1: 0.0,
            k2: 0.0,
            ..Intrinsics::default()
        },
        pose: Pose::look_at(Vector3::new(0.0, 0.06, 0.12), Vector3::new(0.1, 0.06, 0.12), Vector3::z()),
    });
    let masks: Vec<Mask> = cams.iter().map(|c| render(c, &shapes)).collect();
    let views: Vec<View> = cams.iter().zip(&masks).map(|(c, m)| View { camera: *c, mask: m }).collect();
    let g = grid(50);
    let dense = carve_dense(&g, &views).expect("dense");
    let mut carver = SpaceCarver::new(g).expect("carver");
    carver.add_views(&views).expect("carve");
    assert_eq!(carver.occupancy().first_difference(&dense), None);
}

#[test]
fn bad_input_is_a_typed_error() {
    let cams = ring(2, 0.5, 0.0, 0.0, 300.0);
    let small = Mask::from_fn(10, 10, |_, _| true);
    let mut carver = SpaceCarver::new(grid(16)).expect("carver");
    let e = carver.add_view(&cams[0], &small).expect_err("size mismatch");
    assert!(e.to_string().contains("mask is 10x10"), "{e}");
    let mut bad = cams[1];
    bad.intrinsics.fx = f64::NAN;
    let m = Mask::from_fn(160, 120, |_, _| true);
    assert!(carver.add_view(&bad, &m).is_err());
    let mut g = grid(16);
    g.dims = [0, 3, 3];
    assert!(SpaceCarver::new(g).is_err());
}
