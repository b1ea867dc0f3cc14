//! The voxel grid: a regular lattice of cubic voxels over a box.

use nalgebra::Vector3;

use super::Aabb;

/// A grid of `dims[0] x dims[1] x dims[2]` cubic voxels of edge `voxel_size` metres, with its
/// minimum corner at `origin`. Voxel `(i, j, k)` has its centre at `origin + (idx + 0.5) * voxel_size`.
/// Linear index: `i + dims[0] * (j + dims[1] * k)` (x fastest).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VoxelGrid {
    /// Minimum corner, metres.
    pub origin: [f64; 3],
    /// Voxel edge, metres.
    pub voxel_size: f64,
    /// Voxels along x, y, z.
    pub dims: [usize; 3],
}

impl VoxelGrid {
    /// `n` voxels along the longest side of `bbox`, cubic voxels, `ceil(extent / size)` voxels along
    /// the other sides (the grid may reach slightly past the box's maximum there).
    pub fn from_resolution(bbox: &Aabb, n: u32) -> VoxelGrid {
        let e = bbox.extent();
        let longest = e[0].max(e[1]).max(e[2]);
        let voxel_size = longest / n as f64;
        let dims = e.map(|x| {
            let r = x / voxel_size;
            // Guard against 256.0000000001 for the longest side.
            let c = if (r - r.round()).abs() < 1e-9 * r.max(1.0) { r.round() } else { r.ceil() };
            (c as usize).max(1)
        });
        VoxelGrid { origin: bbox.min, voxel_size, dims }
    }

    /// Total number of voxels.
    pub fn len(&self) -> usize {
        self.dims[0] * self.dims[1] * self.dims[2]
    }

    /// True for a grid with no voxels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Linear index of voxel `(i, j, k)`.
    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// Centre of voxel `(i, j, k)`, metres.
    #[inline]
    pub fn centre(&self, i: usize, j: usize, k: usize) -> Vector3<f64> {
        Vector3::new(
            self.origin[0] + (i as f64 + 0.5) * self.voxel_size,
            self.origin[1] + (j as f64 + 0.5) * self.voxel_size,
            self.origin[2] + (k as f64 + 0.5) * self.voxel_size,
        )
    }

    /// The box the voxels cover (may reach past the requested box on the shorter sides).
    pub fn bbox(&self) -> Aabb {
        Aabb { min: self.origin, max: [0, 1, 2].map(|a| self.origin[a] + self.dims[a] as f64 * self.voxel_size) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dino_box_gives_the_reference_grid() {
        let bbox = Aabb { min: [-0.061897, -0.018874, -0.057845], max: [0.010897, 0.068227, 0.015495] };
        assert_eq!(VoxelGrid::from_resolution(&bbox, 256).dims, [214, 256, 216]);
    }
}
