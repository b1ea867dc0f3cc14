//! Depth-map fusion: a truncated signed distance field (TSDF) over the object-frame voxel grid,
//! integrated from depth maps taken at known turntable positions (projective TSDF, running weighted
//! average), then the solid and the surface read off its sign.
//!
//! For each voxel centre `p` and each depth map: project `p` into the depth camera (object frame),
//! read the measured depth `d` (metres along the optical axis) at its pixel, and take
//! `sdf = d - z_cam(p)`: positive in the free space in front of the surface, negative behind it.
//! Voxels with `sdf < -truncation` are hidden behind the surface in that view and get no update;
//! others get `clamp(sdf / truncation, -1, 1)` averaged with weight 1 per view (capped). Pixels
//! without a measurement either carve (the ray met nothing: free space, as on a simulated rig with an
//! empty background) or are ignored (a real sensor's dropout), see [`FusionParams::missing_is_free`].
//!
//! The solid ([`Tsdf::occupancy`]) is every voxel whose fused value is negative, plus every voxel no
//! view ever updated (hidden in every view, i.e. deep inside the object, or never in view): like
//! carving, what was never seen to be empty stays. The mesh is the occupancy's surface with its
//! vertices then moved onto the TSDF's zero crossing ([`Tsdf::refine_vertices`]), which gives
//! sub-voxel accuracy.

use rayon::prelude::*;

use super::mesh::TriangleMesh;
use super::occupancy::Occupancy;
use crate::geometry::{CameraModel, VoxelGrid};

/// Parameters of the fusion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusionParams {
    /// Truncation distance, metres (a few voxels).
    pub truncation_m: f64,
    /// Cap on a voxel's accumulated weight (views); older views then fade out.
    pub max_weight: f32,
    /// Whether a pixel without a measurement (depth 0) means "nothing along this ray" (free space)
    /// rather than "unknown".
    pub missing_is_free: bool,
}

/// Why a depth map was not fused.
#[derive(Debug, thiserror::Error)]
pub enum DepthFusionError {
    /// The depth buffer does not have `width * height` values.
    #[error("depth map of {len} values for a {width} x {height} camera")]
    DepthSize {
        /// Values given.
        len: usize,
        /// Camera width, pixels.
        width: u32,
        /// Camera height, pixels.
        height: u32,
    },
    /// The truncation distance is not a positive finite length.
    #[error("truncation distance {truncation_m} m is not positive and finite")]
    Truncation {
        /// The value given, metres.
        truncation_m: f64,
    },
    /// The grid has no voxels.
    #[error("the voxel grid is empty")]
    EmptyGrid,
}

/// What one integration did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IntegrateStats {
    /// Voxels updated by the view (in front of the surface or within the truncation band).
    pub updated: u64,
    /// Voxels within the truncation band of a measured surface.
    pub near_surface: u64,
}

/// A TSDF over an object-frame voxel grid: per voxel a value in [-1, 1] (signed distance over the
/// truncation distance, positive outside) and a weight (0 = never updated).
#[derive(Debug, Clone)]
pub struct Tsdf {
    grid: VoxelGrid,
    params: FusionParams,
    value: Vec<f32>,
    weight: Vec<f32>,
    views: usize,
}

impl Tsdf {
    /// An empty field over `grid` (every voxel unobserved).
    pub fn new(grid: VoxelGrid, params: FusionParams) -> Result<Tsdf, DepthFusionError> {
        if !(params.truncation_m.is_finite() && params.truncation_m > 0.0) {
            return Err(DepthFusionError::Truncation { truncation_m: params.truncation_m });
        }
        if grid.is_empty() {
            return Err(DepthFusionError::EmptyGrid);
        }
        let n = grid.len();
        Ok(Tsdf { grid, params, value: vec![1.0; n], weight: vec![0.0; n], views: 0 })
    }

    /// The grid.
    pub fn grid(&self) -> &VoxelGrid {
        &self.grid
    }

    /// Depth maps fused so far.
    pub fn views(&self) -> usize {
        self.views
    }

    /// The fused value of voxel `(i, j, k)` (signed distance / truncation, positive outside) and its
    /// weight (0 = never updated).
    pub fn get(&self, i: usize, j: usize, k: usize) -> (f32, f32) {
        let idx = self.grid.index(i, j, k);
        (self.value[idx], self.weight[idx])
    }

    /// Fuse one depth map: `depth_m` is row-major, `camera.width * camera.height` values, metres along
    /// the optical axis, 0 = no measurement, `NaN` = unknown (never carves, even with
    /// `missing_is_free`); `camera` is the depth camera in the grid's (object) frame, i.e. already
    /// turned with `for_turntable_angle`.
    pub fn integrate(&mut self, camera: &CameraModel, depth_m: &[f32]) -> Result<IntegrateStats, DepthFusionError> {
        let (w, h) = (camera.width, camera.height);
        if depth_m.len() != w as usize * h as usize {
            return Err(DepthFusionError::DepthSize { len: depth_m.len(), width: w, height: h });
        }
        let grid = self.grid;
        let trunc = self.params.truncation_m as f32;
        let max_weight = self.params.max_weight.max(1.0);
        let missing_is_free = self.params.missing_is_free;
        let slice = grid.dims[0] * grid.dims[1];
        let (updated, near_surface) = self
            .value
            .par_chunks_mut(slice)
            .zip(self.weight.par_chunks_mut(slice))
            .enumerate()
            .map(|(k, (values, weights))| {
                let (mut updated, mut near) = (0u64, 0u64);
                // Camera coordinates are affine in the voxel index: one step along x per voxel.
                let step = camera.pose.rotation.column(0) * grid.voxel_size;
                let intr = &camera.intrinsics;
                for j in 0..grid.dims[1] {
                    let row = camera.pose.apply(&grid.centre(0, j, k));
                    for i in 0..grid.dims[0] {
                        let c = row + step * i as f64;
                        if c.z <= 0.0 {
                            continue;
                        }
                        let z = c.z;
                        let q = intr.normalised_to_pixel(c.x / c.z, c.y / c.z);
                        let (uf, vf) = (q.x.floor(), q.y.floor());
                        if !(uf >= 0.0 && vf >= 0.0 && uf < w as f64 && vf < h as f64) {
                            continue;
                        }
                        let (u, v) = (uf as u32, vf as u32);
                        let d = depth_m[(v * w + u) as usize];
                        let sample = if d > 0.0 && d.is_finite() {
                            let sdf = d - z as f32;
                            if sdf < -trunc {
                                continue;
                            }
                            if sdf < trunc {
                                near += 1;
                            }
                            (sdf / trunc).clamp(-1.0, 1.0)
                        } else if missing_is_free && d == 0.0 {
                            1.0
                        } else {
                            continue;
                        };
                        let idx = i + grid.dims[0] * j;
                        let wt = weights[idx];
                        values[idx] = (values[idx] * wt + sample) / (wt + 1.0);
                        weights[idx] = (wt + 1.0).min(max_weight);
                        updated += 1;
                    }
                }
                (updated, near)
            })
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        self.views += 1;
        Ok(IntegrateStats { updated, near_surface })
    }

    /// The fused solid: voxels with a negative value, and voxels never updated (hidden in every view).
    pub fn occupancy(&self) -> Occupancy {
        Occupancy::from_index_fn(self.grid, |i, j, k| {
            let idx = self.grid.index(i, j, k);
            self.weight[idx] == 0.0 || self.value[idx] < 0.0
        })
    }

    /// The field at a point (metres, grid frame) by trilinear interpolation of voxel centres, with its
    /// gradient (per metre); `None` where any of the 8 voxels was never updated or lies outside the grid.
    pub fn sample(&self, p: &[f64; 3]) -> Option<(f64, [f64; 3])> {
        let g = &self.grid;
        let mut base = [0usize; 3];
        let mut f = [0.0f64; 3];
        for a in 0..3 {
            let x = (p[a] - g.origin[a]) / g.voxel_size - 0.5;
            if !x.is_finite() || x < 0.0 || x >= (g.dims[a] - 1) as f64 {
                return None;
            }
            base[a] = x.floor() as usize;
            f[a] = x - base[a] as f64;
        }
        let mut c = [0.0f64; 8];
        for (n, cv) in c.iter_mut().enumerate() {
            let idx = g.index(base[0] + (n & 1), base[1] + ((n >> 1) & 1), base[2] + ((n >> 2) & 1));
            if self.weight[idx] == 0.0 {
                return None;
            }
            *cv = f64::from(self.value[idx]);
        }
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let value = lerp(
            lerp(lerp(c[0], c[1], f[0]), lerp(c[2], c[3], f[0]), f[1]),
            lerp(lerp(c[4], c[5], f[0]), lerp(c[6], c[7], f[0]), f[1]),
            f[2],
        );
        let gx = lerp(lerp(c[1] - c[0], c[3] - c[2], f[1]), lerp(c[5] - c[4], c[7] - c[6], f[1]), f[2]);
        let gy = lerp(lerp(c[2] - c[0], c[3] - c[1], f[0]), lerp(c[6] - c[4], c[7] - c[5], f[0]), f[2]);
        let gz = lerp(lerp(c[4] - c[0], c[5] - c[1], f[0]), lerp(c[6] - c[2], c[7] - c[3], f[0]), f[1]);
        // Values are distances over the truncation; gradients per voxel -> per metre, in distance units.
        let scale = self.params.truncation_m;
        Some((value * scale, [gx, gy, gz].map(|d| d * scale / g.voxel_size)))
    }

    /// Move each mesh vertex onto the TSDF's zero crossing by a few Newton steps along the field's
    /// gradient, at most one voxel in total; vertices where the field is unknown, flat or inside the
    /// fully truncated region stay put. Returns how many vertices moved.
    pub fn refine_vertices(&self, mesh: &mut TriangleMesh) -> usize {
        let limit = self.grid.voxel_size;
        let trunc = self.params.truncation_m;
        let moved: usize = mesh
            .vertices
            .par_iter_mut()
            .map(|v| {
                let start = v.map(f64::from);
                let mut p = start;
                for _ in 0..3 {
                    let Some((d, g)) = self.sample(&p) else { break };
                    let g2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
                    if g2 < 0.05 || d.abs() >= 0.99 * trunc {
                        break;
                    }
                    p = [0, 1, 2].map(|a| p[a] - d * g[a] / g2);
                }
                let shift = ((p[0] - start[0]).powi(2) + (p[1] - start[1]).powi(2) + (p[2] - start[2]).powi(2)).sqrt();
                if shift > 0.0 && shift <= limit && p.iter().all(|x| x.is_finite()) {
                    *v = p.map(|x| x as f32);
                    1
                } else {
                    0
                }
            })
            .sum();
        moved
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;
    use crate::geometry::{Aabb, Intrinsics, Pose};
    use crate::pipeline::{extract_surface, MeshParams};

    const R: f64 = 0.03;

    /// Exact depth of a sphere of radius R at the origin, as the simulated depth camera would give.
    fn sphere_depth(cam: &CameraModel) -> Vec<f32> {
        let c = cam.centre();
        let mut out = vec![0.0f32; (cam.width * cam.height) as usize];
        for v in 0..cam.height {
            for u in 0..cam.width {
                let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5);
                let b = c.dot(&d);
                let disc = b * b - (c.norm_squared() - R * R);
                if disc >= 0.0 {
                    let t = -b - disc.sqrt();
                    out[(v * cam.width + u) as usize] = cam.pose.apply(&(c + d * t)).z as f32;
                }
            }
        }
        out
    }

    fn camera(angle_deg: f64) -> CameraModel {
        let rig = CameraModel {
            width: 160,
            height: 120,
            intrinsics: Intrinsics {
                fx: 300.0,
                fy: 300.0,
                cx: 80.0,
                cy: 60.0,
                skew: 0.0,
                k1: 0.0,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(Vector3::new(0.0, -0.25, 0.1), Vector3::zeros(), Vector3::z()),
        };
        rig.for_turntable_angle(angle_deg)
    }

    fn grid() -> VoxelGrid {
        VoxelGrid::from_resolution(&Aabb { min: [-0.04; 3], max: [0.04; 3] }, 48)
    }

    fn params() -> FusionParams {
        FusionParams { truncation_m: 3.0 * grid().voxel_size, max_weight: 64.0, missing_is_free: true }
    }

    #[test]
    fn fused_sphere_has_its_radius_and_its_volume() {
        let mut tsdf = Tsdf::new(grid(), params()).expect("tsdf");
        for i in 0..12 {
            let cam = camera(30.0 * i as f64);
            let stats = tsdf.integrate(&cam, &sphere_depth(&cam)).expect("integrate");
            assert!(stats.near_surface > 100 && stats.updated > stats.near_surface, "{stats:?}");
        }
        assert_eq!(tsdf.views(), 12);
        // Voxels in the truncation band carry the sign of their distance to the sphere, and a projective
        // distance is never shorter than the Euclidean one (up to noise of a voxel).
        let g = *tsdf.grid();
        let mut checked = 0;
        for k in 0..g.dims[2] {
            for j in 0..g.dims[1] {
                for i in 0..g.dims[0] {
                    let (value, weight) = tsdf.get(i, j, k);
                    let true_sdf = g.centre(i, j, k).norm() - R;
                    if weight >= 3.0 && true_sdf.abs() < params().truncation_m && true_sdf.abs() > 0.5 * g.voxel_size {
                        let got = f64::from(value) * params().truncation_m;
                        assert_eq!(got > 0.0, true_sdf > 0.0, "{i} {j} {k}: {got} vs {true_sdf}");
                        assert!(got.abs() > true_sdf.abs() - 0.5 * g.voxel_size, "{i} {j} {k}: {got} vs {true_sdf}");
                        checked += 1;
                    }
                }
            }
        }
        assert!(checked > 500, "{checked}");
        // The solid is the ball: volume within a few percent, no voxel far outside kept.
        let occ = tsdf.occupancy();
        let ball = 4.0 / 3.0 * std::f64::consts::PI * R.powi(3);
        assert!((occ.volume_m3() / ball - 1.0).abs() < 0.06, "{} vs {ball}", occ.volume_m3());
        // The refined mesh lies on the sphere to a fraction of a voxel.
        let mut mesh = extract_surface(&occ, &MeshParams { smooth_radius: 0, relax_iterations: 0 }).expect("mesh");
        let err = |m: &TriangleMesh| {
            m.vertices.iter().map(|v| (Vector3::new(v[0], v[1], v[2]).norm() as f64 - R).abs()).sum::<f64>()
                / m.vertices.len() as f64
        };
        let before = err(&mesh);
        let moved = tsdf.refine_vertices(&mut mesh);
        let after = err(&mesh);
        assert!(moved > mesh.vertices.len() / 2, "{moved} of {}", mesh.vertices.len());
        assert!(after < 0.15 * g.voxel_size && after < before, "mean error {after} m (before {before} m)");
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let mut tsdf = Tsdf::new(grid(), params()).expect("tsdf");
        assert!(matches!(tsdf.integrate(&camera(0.0), &[0.0; 5]), Err(DepthFusionError::DepthSize { len: 5, .. })));
        let bad = FusionParams { truncation_m: f64::NAN, ..params() };
        assert!(matches!(Tsdf::new(grid(), bad), Err(DepthFusionError::Truncation { .. })));
        // An unobserved field is all solid (nothing seen to be empty); an empty view carves everything
        // in view.
        assert_eq!(tsdf.occupancy().count(), grid().len() as u64);
        let cam = camera(0.0);
        tsdf.integrate(&cam, &vec![0.0; 160 * 120]).expect("integrate");
        assert!(tsdf.occupancy().count() < grid().len() as u64 / 2);
    }
}
