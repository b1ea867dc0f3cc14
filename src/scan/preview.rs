//! Live previews: a compact point cloud of a job's current estimate, published while the views
//! arrive so a viewer can watch the hull tighten or the cloud grow. A flow says what its estimate
//! is ([`super::flow::ScanFlow::preview`]); the driver decides when to ask ([`LiveSpec`]) and
//! hands the cloud on as [`super::ScanEvent::Preview`].
//!
//! Every preview is in the object frame (the frame of the job's voxel grid, metres), at most
//! [`LiveSpec::max_points`] points, subsampled by a fixed stride so consecutive previews of an
//! unchanged estimate are identical.

use std::time::Duration;

use crate::pipeline::{Occupancy, PointCloud, Tsdf};

/// How a job publishes live previews.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LiveSpec {
    /// Most points in one preview.
    pub max_points: usize,
    /// Least time between two previews (the last view always gets one).
    pub min_interval: Duration,
}

impl Default for LiveSpec {
    /// 60 000 points (under 1 MB of binary PLY), at most four previews a second.
    fn default() -> Self {
        LiveSpec { max_points: 60_000, min_interval: Duration::from_millis(250) }
    }
}

/// Every `stride`-th of `n` items so that at most `max` remain (`max` 0 keeps none).
fn stride(n: usize, max: usize) -> usize {
    if max == 0 {
        usize::MAX
    } else {
        n.div_ceil(max).max(1)
    }
}

/// The centres of the boundary voxels of `solid` (occupied voxels with an empty or out-of-grid
/// face neighbour), object frame, metres; `None` when the solid is empty.
pub fn from_occupancy(solid: &Occupancy, max_points: usize) -> Option<PointCloud> {
    let boundary = solid.boundary_voxels();
    if boundary.is_empty() || max_points == 0 {
        return None;
    }
    let grid = solid.grid();
    let step = stride(boundary.len(), max_points);
    let points = boundary
        .iter()
        .step_by(step)
        .map(|&[i, j, k]| {
            let c = grid.centre(i as usize, j as usize, k as usize);
            [c.x as f32, c.y as f32, c.z as f32]
        })
        .collect();
    Some(PointCloud::from_points(points))
}

/// Points measured so far (object frame, metres) with their colours if known; `None` when there
/// are none.
pub fn from_points(points: &[[f32; 3]], colors: Option<&[[u8; 3]]>, max_points: usize) -> Option<PointCloud> {
    if points.is_empty() || max_points == 0 {
        return None;
    }
    let step = stride(points.len(), max_points);
    let pts: Vec<[f32; 3]> = points.iter().step_by(step).copied().collect();
    let cols = colors.filter(|c| c.len() == points.len()).map(|c| c.iter().step_by(step).copied().collect());
    // One colour per kept point by construction, so `from_parts` cannot refuse them.
    PointCloud::from_parts(pts, None, cols).ok()
}

/// The centres of the voxels of `tsdf` next to its zero crossing (measured, |signed distance| under
/// one voxel), object frame, metres; `None` before any depth map was fused.
pub fn from_tsdf(tsdf: &Tsdf, truncation_m: f64, max_points: usize) -> Option<PointCloud> {
    let grid = *tsdf.grid();
    let [nx, ny, nz] = grid.dims;
    // Values are signed distance / truncation: one voxel is voxel_size / truncation of that.
    let band = (grid.voxel_size / truncation_m.max(f64::MIN_POSITIVE)).min(1.0) as f32;
    let mut near = Vec::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let (d, w) = tsdf.get(i, j, k);
                if w > 0.0 && d.abs() < band {
                    let c = grid.centre(i, j, k);
                    near.push([c.x as f32, c.y as f32, c.z as f32]);
                }
            }
        }
    }
    from_points(&near, None, max_points)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, VoxelGrid};

    fn grid() -> VoxelGrid {
        VoxelGrid::from_resolution(&Aabb { min: [-0.05; 3], max: [0.05; 3] }, 20)
    }

    #[test]
    fn occupancy_preview_is_the_boundary_of_a_ball() {
        let g = grid();
        let ball = Occupancy::from_fn(g, |p| p.norm() < 0.03);
        let cloud = from_occupancy(&ball, 1_000_000).expect("a ball has a boundary");
        assert_eq!(cloud.len(), ball.boundary_voxels().len());
        // Boundary voxel centres lie within one voxel diagonal of the sphere.
        let tol = g.voxel_size * 3f64.sqrt();
        for p in cloud.points() {
            let r = (p[0] as f64).hypot(p[1] as f64).hypot(p[2] as f64);
            assert!((r - 0.03).abs() <= tol, "point at radius {r} m");
        }
        // Capped and deterministic.
        let small = from_occupancy(&ball, 100).expect("non-empty");
        assert!(small.len() <= 100 && small.len() >= 50, "{} points", small.len());
        assert_eq!(small.points(), from_occupancy(&ball, 100).expect("non-empty").points());
        assert!(from_occupancy(&Occupancy::empty(g), 100).is_none());
    }

    #[test]
    fn point_preview_keeps_colours_and_caps() {
        let pts: Vec<[f32; 3]> = (0..1000).map(|i| [i as f32, 0.0, 0.0]).collect();
        let cols: Vec<[u8; 3]> = (0..1000).map(|i| [(i % 256) as u8, 0, 0]).collect();
        let c = from_points(&pts, Some(&cols), 300).expect("non-empty");
        assert!(c.len() <= 300 && c.len() >= 250);
        let colours = c.colors().expect("colours kept");
        for (p, col) in c.points().iter().zip(colours) {
            assert_eq!((p[0] as usize % 256) as u8, col[0]);
        }
        assert!(from_points(&[], None, 10).is_none());
    }
}
