//! Point clouds: points with optional normals and colours, merged over views, cleaned, and meshed.
//!
//! A [`PointCloud`] holds points in metres. Its frame is whatever its producer says; the scan flows
//! build each view's points in the rig frame and turn them into the object frame (fixed to the
//! turntable top, see [`crate::geometry`]) with [`PointCloud::rig_to_object`] before merging.
//!
//! - Nearest neighbours come from [`KnnIndex`], a dense array of uniform cells with a shell search
//!   (exact: ties go to the lower point index).
//! - Normals ([`PointCloud::estimate_normals`]): the eigenvector of the smallest eigenvalue of the
//!   covariance of the `k` nearest points (PCA), flipped to face the point's viewpoint (the sensor
//!   that saw it).
//! - Statistical outlier removal ([`PointCloud::inlier_mask`]): a point whose mean distance to
//!   its `k` nearest neighbours exceeds the mean of that figure over the cloud by more than `s`
//!   standard deviations is an outlier.
//! - Voxel downsampling ([`PointCloud::voxel_downsample`]): one point per occupied cubic cell, the
//!   mean of its points (normals averaged and renormalised, colours averaged).
//! - Meshing ([`mesh_from_cloud`]): a signed distance to the oriented points (Hoppe et al. 1992,
//!   "Surface reconstruction from unorganized points", smoothed as an implicit moving least-squares
//!   average of the tangent planes of the `k` nearest points) is evaluated on the voxels of a band
//!   around the points; every other voxel takes the side of the tangent plane of its nearest point
//!   (Hoppe's sign; the nearest point found by a Dijkstra wave from the band, a vector distance
//!   transform) up to a reach; beyond it, voxels the grid's outer faces (other than its floor) reach
//!   through unlabelled voxels are outside and enclosed ones inside; small inside blobs and enclosed
//!   outside bubbles are flipped. The inside voxels form an
//!   [`Occupancy`] whose surface is extracted as a dual surface net ([`extract_surface`], closed and
//!   consistently oriented); each vertex is then moved onto the zero crossing of the signed distance
//!   by Newton steps (until the distance is within [`NEWTON_TOLERANCE_VOXELS`] of a voxel edge), for
//!   sub-voxel accuracy.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::path::Path;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rayon::prelude::*;

use super::export::ExportError;
use super::mesh::{extract_surface_reporting, MeshError, MeshParams, TriangleMesh};
use super::occupancy::Occupancy;
use super::topology::HandleRepair;
use crate::atomic::write_atomic_with;
use crate::geometry::{turntable_rotation, Aabb, VoxelGrid};

/// Errors of point-cloud operations; each names the offending value.
#[derive(Debug, thiserror::Error)]
pub enum CloudError {
    /// An attribute (normals or colours) does not have one entry per point.
    #[error("{attribute}: {len} values for {points} points")]
    AttributeLength {
        /// `"normals"` or `"colours"`.
        attribute: &'static str,
        /// Values given.
        len: usize,
        /// Points in the cloud.
        points: usize,
    },
    /// A parameter is out of its range.
    #[error("parameter {name} = {value} is out of range ({expected})")]
    Parameter {
        /// The parameter's name.
        name: &'static str,
        /// The value given.
        value: f64,
        /// What is accepted.
        expected: &'static str,
    },
    /// The operation needs normals and the cloud has none.
    #[error("the point cloud has no normals (estimate them first)")]
    NoNormals,
    /// No point of the cloud lies in the grid, so there is no surface to mesh.
    #[error("no point of the cloud lies inside the grid")]
    NoPointsInGrid,
    /// A free-space mask does not have one entry per voxel of the grid.
    #[error("free-space mask has {given} entries for a grid of {expected} voxels")]
    FreeSpaceSize {
        /// Entries given.
        given: usize,
        /// Voxels in the grid.
        expected: usize,
    },
    /// Surface extraction failed.
    #[error("surface extraction failed")]
    Mesh(#[from] MeshError),
}

/// Points (metres) with optional per-point unit normals and 8-bit RGB colours. Each attribute is
/// either absent or has exactly one entry per point.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    points: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    colors: Option<Vec<[u8; 3]>>,
}

impl PointCloud {
    /// An empty cloud.
    pub fn new() -> PointCloud {
        PointCloud::default()
    }

    /// A cloud of bare points (metres), without normals or colours.
    pub fn from_points(points: Vec<[f32; 3]>) -> PointCloud {
        PointCloud { points, normals: None, colors: None }
    }

    /// A cloud from its parts: points (metres), unit normals, colours; each attribute must have one
    /// entry per point.
    pub fn from_parts(
        points: Vec<[f32; 3]>,
        normals: Option<Vec<[f32; 3]>>,
        colors: Option<Vec<[u8; 3]>>,
    ) -> Result<PointCloud, CloudError> {
        let n = points.len();
        if let Some(v) = normals.as_ref().filter(|v| v.len() != n) {
            return Err(CloudError::AttributeLength { attribute: "normals", len: v.len(), points: n });
        }
        if let Some(v) = colors.as_ref().filter(|v| v.len() != n) {
            return Err(CloudError::AttributeLength { attribute: "colours", len: v.len(), points: n });
        }
        Ok(PointCloud { points, normals, colors })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True for a cloud without points.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points, metres.
    pub fn points(&self) -> &[[f32; 3]] {
        &self.points
    }

    /// The unit normals, one per point, if the cloud has them.
    pub fn normals(&self) -> Option<&[[f32; 3]]> {
        self.normals.as_deref()
    }

    /// The colours, one per point, if the cloud has them.
    pub fn colors(&self) -> Option<&[[u8; 3]]> {
        self.colors.as_deref()
    }

    /// Replace the normals (one unit vector per point).
    pub fn set_normals(&mut self, normals: Vec<[f32; 3]>) -> Result<(), CloudError> {
        if normals.len() != self.points.len() {
            return Err(CloudError::AttributeLength { attribute: "normals", len: normals.len(), points: self.len() });
        }
        self.normals = Some(normals);
        Ok(())
    }

    /// The bounding box of the points (metres, the cloud's frame); `None` for an empty cloud.
    pub fn bbox(&self) -> Option<Aabb> {
        let first = self.points.first()?;
        let (mut min, mut max) = (first.map(f64::from), first.map(f64::from));
        for p in &self.points {
            for a in 0..3 {
                min[a] = min[a].min(f64::from(p[a]));
                max[a] = max[a].max(f64::from(p[a]));
            }
        }
        Some(Aabb { min, max })
    }

    /// Append `other`'s points. An attribute survives only if both clouds have it (an empty cloud
    /// takes `other`'s attributes), so the result never mixes points with and without normals.
    pub fn extend(&mut self, other: PointCloud) {
        if self.points.is_empty() {
            *self = other;
            return;
        }
        if other.points.is_empty() {
            return;
        }
        self.points.extend(other.points);
        self.normals = match (self.normals.take(), other.normals) {
            (Some(mut a), Some(b)) => {
                a.extend(b);
                Some(a)
            }
            _ => None,
        };
        self.colors = match (self.colors.take(), other.colors) {
            (Some(mut a), Some(b)) => {
                a.extend(b);
                Some(a)
            }
            _ => None,
        };
    }

    /// Merge clouds in order (see [`PointCloud::extend`] for attributes).
    pub fn merge(clouds: impl IntoIterator<Item = PointCloud>) -> PointCloud {
        let mut out = PointCloud::new();
        for c in clouds {
            out.extend(c);
        }
        out
    }

    /// Apply the rigid transform `p -> rotation * p + translation` (metres) to the points, and the
    /// rotation to the normals. `rotation` must be a rotation matrix.
    pub fn transform(&mut self, rotation: &Matrix3<f64>, translation: &Vector3<f64>) {
        let r = rotation.cast::<f32>();
        let t = translation.cast::<f32>();
        self.points.par_iter_mut().for_each(|p| {
            let q = r * Vector3::from(*p) + t;
            *p = [q.x, q.y, q.z];
        });
        if let Some(ns) = self.normals.as_mut() {
            ns.par_iter_mut().for_each(|n| {
                let q = r * Vector3::from(*n);
                *n = [q.x, q.y, q.z];
            });
        }
    }

    /// Turn points from the rig frame into the object frame at turntable angle `table_angle_deg`
    /// (degrees, counter-clockwise seen from above): `p_obj = Rz(-θ) · p_rig`.
    pub fn rig_to_object(&mut self, table_angle_deg: f64) {
        self.transform(&turntable_rotation(-table_angle_deg), &Vector3::zeros());
    }

    /// Keep the points whose entry in `keep` is true (one entry per point; missing entries drop).
    pub fn retain_mask(&mut self, keep: &[bool]) {
        let pick = |n: usize| keep.get(n).copied().unwrap_or(false);
        fn filter<T: Copy>(v: &mut Vec<T>, pick: &impl Fn(usize) -> bool) {
            let mut n = 0;
            v.retain(|_| {
                n += 1;
                pick(n - 1)
            });
        }
        filter(&mut self.points, &pick);
        if let Some(v) = self.normals.as_mut() {
            filter(v, &pick);
        }
        if let Some(v) = self.colors.as_mut() {
            filter(v, &pick);
        }
    }

    /// Estimate a unit normal per point: PCA over the point and its `k - 1` nearest neighbours (`k` in
    /// 3..=64), the direction of least variance, flipped to face `viewpoint(i)` (metres, the cloud's
    /// frame: the sensor that saw point `i`). Where the neighbours lie along a line (the middle
    /// variance below [`LINEAR_RATIO`] of the largest, as on one densely sampled laser stripe) the
    /// PCA is repeated over 64 neighbours, which reach the adjacent stripes. Points without enough
    /// neighbours get the unit vector towards their viewpoint.
    pub fn estimate_normals<F>(&mut self, k: usize, viewpoint: F) -> Result<(), CloudError>
    where
        F: Fn(usize) -> [f32; 3] + Sync,
    {
        check_k(k)?;
        let index = KnnIndex::new(&self.points);
        let normals = index.map_points(|i, p, buf| {
            index.k_nearest(p, k, buf);
            let view = (Vector3::from(viewpoint(i)) - Vector3::from(*p)).cast::<f64>();
            let mut n = if buf.len() >= 3 { pca_normal(&self.points, buf) } else { None };
            if k < MAX_K && matches!(n, Some((_, true))) {
                index.k_nearest(p, MAX_K, buf);
                n = pca_normal(&self.points, buf);
            }
            let n = n.map(|(n, _)| n);
            let n = n.unwrap_or_else(|| view.try_normalize(0.0).unwrap_or(Vector3::z()));
            let n = if n.dot(&view) < 0.0 { -n } else { n };
            [n.x as f32, n.y as f32, n.z as f32]
        });
        self.normals = Some(normals);
        Ok(())
    }

    /// The mean distance (metres) from each point to its `k` nearest other points (`k` in 3..=64);
    /// `f32::INFINITY` for a point with no other point.
    pub fn mean_neighbour_distances(&self, k: usize) -> Result<Vec<f32>, CloudError> {
        check_k(k)?;
        let index = KnnIndex::new(&self.points);
        Ok(index.map_points(|_, p, buf| {
            index.k_nearest(p, k + 1, buf);
            // The first neighbour is the point itself (or a duplicate at distance 0).
            let others = &buf[1.min(buf.len())..];
            if others.is_empty() {
                f32::INFINITY
            } else {
                others.iter().map(|(d2, _)| d2.sqrt()).sum::<f32>() / others.len() as f32
            }
        }))
    }

    /// The statistical inliers: `true` for a point to keep. A point is an outlier when its mean distance
    /// to its `k` nearest neighbours exceeds `mean + std_ratio * sigma` of that figure over the cloud.
    pub fn inlier_mask(&self, k: usize, std_ratio: f64) -> Result<Vec<bool>, CloudError> {
        if !(std_ratio.is_finite() && std_ratio > 0.0) {
            return Err(CloudError::Parameter { name: "std_ratio", value: std_ratio, expected: "positive, finite" });
        }
        let d = self.mean_neighbour_distances(k)?;
        let finite: Vec<f64> = d.iter().filter(|x| x.is_finite()).map(|&x| f64::from(x)).collect();
        if finite.is_empty() {
            return Ok(vec![false; d.len()]);
        }
        let mean = finite.iter().sum::<f64>() / finite.len() as f64;
        let var = finite.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / finite.len() as f64;
        let limit = mean + std_ratio * var.sqrt();
        Ok(d.iter().map(|&x| f64::from(x) <= limit).collect())
    }

    /// Remove statistical outliers (see [`PointCloud::inlier_mask`]); returns how many
    /// points were removed.
    pub fn remove_statistical_outliers(&mut self, k: usize, std_ratio: f64) -> Result<usize, CloudError> {
        let keep = self.inlier_mask(k, std_ratio)?;
        let before = self.len();
        self.retain_mask(&keep);
        Ok(before - self.len())
    }

    /// One point per occupied cube of edge `voxel_m` metres (cubes aligned to the frame's origin):
    /// the mean of its points, normals summed and renormalised, colours averaged. Output ordered by
    /// cube (z, then y, then x), so it does not depend on the input order's cubes.
    pub fn voxel_downsample(&self, voxel_m: f64) -> Result<PointCloud, CloudError> {
        if !(voxel_m.is_finite() && voxel_m > 0.0) {
            return Err(CloudError::Parameter { name: "voxel_m", value: voxel_m, expected: "positive, finite" });
        }
        #[derive(Default)]
        struct Acc {
            p: [f64; 3],
            n: [f64; 3],
            c: [u32; 3],
            count: u32,
        }
        let mut cells: HashMap<[i64; 3], Acc> = HashMap::new();
        for (i, p) in self.points.iter().enumerate() {
            if !p.iter().all(|x| x.is_finite()) {
                continue;
            }
            let key = p.map(|x| (f64::from(x) / voxel_m).floor() as i64);
            let acc = cells.entry(key).or_default();
            for a in 0..3 {
                acc.p[a] += f64::from(p[a]);
                if let Some(ns) = &self.normals {
                    acc.n[a] += f64::from(ns[i][a]);
                }
                if let Some(cs) = &self.colors {
                    acc.c[a] += u32::from(cs[i][a]);
                }
            }
            acc.count += 1;
        }
        let mut cells: Vec<([i64; 3], Acc)> = cells.into_iter().collect();
        cells.sort_unstable_by_key(|(k, _)| [k[2], k[1], k[0]]);
        let points = cells.iter().map(|(_, a)| a.p.map(|x| (x / f64::from(a.count)) as f32)).collect();
        let normals = self.normals.as_ref().map(|_| {
            cells
                .iter()
                .map(|(_, a)| {
                    let n = Vector3::from(a.n).try_normalize(0.0).unwrap_or(Vector3::z());
                    [n.x as f32, n.y as f32, n.z as f32]
                })
                .collect()
        });
        let colors = self
            .colors
            .as_ref()
            .map(|_| cells.iter().map(|(_, a)| a.c.map(|x| ((x + a.count / 2) / a.count).min(255) as u8)).collect());
        Ok(PointCloud { points, normals, colors })
    }

    /// Encode as binary little-endian PLY into `w`: `x y z` (float, metres), then `nx ny nz`
    /// (float) and `red green blue` (uchar) when present.
    pub fn encode_ply<W: std::io::Write>(&self, w: &mut W) -> std::io::Result<()> {
        w.write_all(b"ply\nformat binary_little_endian 1.0\ncomment scanrig point cloud, metres\n")?;
        writeln!(w, "element vertex {}", self.points.len())?;
        w.write_all(b"property float x\nproperty float y\nproperty float z\n")?;
        if self.normals.is_some() {
            w.write_all(b"property float nx\nproperty float ny\nproperty float nz\n")?;
        }
        if self.colors.is_some() {
            w.write_all(b"property uchar red\nproperty uchar green\nproperty uchar blue\n")?;
        }
        w.write_all(b"end_header\n")?;
        for (i, p) in self.points.iter().enumerate() {
            let mut rec = [0u8; 27];
            let mut len = 0;
            let normal = self.normals.as_ref().map(|ns| ns[i]);
            for x in p.iter().chain(normal.iter().flatten()) {
                rec[len..len + 4].copy_from_slice(&x.to_le_bytes());
                len += 4;
            }
            if let Some(cs) = &self.colors {
                rec[len..len + 3].copy_from_slice(&cs[i]);
                len += 3;
            }
            w.write_all(&rec[..len])?;
        }
        Ok(())
    }

    /// Everything [`PointCloud::encode_ply`] writes, in memory (for a download).
    pub fn ply_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(300 + self.points.len() * 27);
        self.encode_ply(&mut out).expect("writing into memory cannot fail");
        out
    }

    /// Write as binary PLY (see [`PointCloud::encode_ply`]), atomically, streamed to the file.
    pub fn write_ply(&self, path: &Path) -> Result<(), ExportError> {
        Ok(write_atomic_with(path, |w| self.encode_ply(w))?)
    }
}

fn check_k(k: usize) -> Result<(), CloudError> {
    if (3..=MAX_K).contains(&k) {
        Ok(())
    } else {
        Err(CloudError::Parameter { name: "k", value: k as f64, expected: "3..=64 neighbours" })
    }
}

/// A point of a cloud being meshed needs this many other points within [`SUPPORT_KERNELS`] kernel
/// widths, or it is left out as stray.
const SUPPORT_NEIGHBOURS: usize = 3;
/// See [`SUPPORT_NEIGHBOURS`].
const SUPPORT_KERNELS: f64 = 3.0;

/// The Newton refinement of a mesh vertex stops once the signed distance there is within this many
/// voxel edges of zero (the next step would move it less than about that far).
pub const NEWTON_TOLERANCE_VOXELS: f64 = 1e-4;

/// Largest neighbour count of the k-nearest-neighbour operations.
const MAX_K: usize = 64;

/// A neighbourhood whose middle principal variance is below this fraction of the largest counts as
/// a line (see [`PointCloud::estimate_normals`]).
pub const LINEAR_RATIO: f64 = 0.05;

/// The direction of least variance of the points `neighbours` index (unit, unoriented), and whether
/// the neighbourhood is linear (see [`LINEAR_RATIO`]).
fn pca_normal(points: &[[f32; 3]], neighbours: &[(f32, u32)]) -> Option<(Vector3<f64>, bool)> {
    let n = neighbours.len() as f64;
    let mut mean = Vector3::zeros();
    for (_, i) in neighbours {
        mean += Vector3::from(points[*i as usize]).cast::<f64>();
    }
    mean /= n;
    let mut cov = Matrix3::zeros();
    for (_, i) in neighbours {
        let d = Vector3::from(points[*i as usize]).cast::<f64>() - mean;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov);
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let linear = eig.eigenvalues[idx[1]] < LINEAR_RATIO * eig.eigenvalues[idx[2]];
    let v = eig.eigenvectors.column(idx[0]).into_owned();
    v.try_normalize(1e-12).map(|v| (v, linear))
}

/// A k-nearest-neighbour index over a fixed set of points (metres): a dense array of cubic cells
/// over the points' bounding box, queried by visiting shells of cells around the query's cell until
/// no unvisited shell can hold a closer point. Points are stored grouped by cell, cells in `x`-fastest
/// order, so a row of cells along `x` is one contiguous run of points. Results are exact and do not
/// depend on the cell size: ties in distance go to the lower point index.
#[derive(Debug, Clone)]
pub struct KnnIndex {
    cell_m: f32,
    /// Cell coordinates of the array's first cell (the lowest occupied cell on each axis).
    cell_lo: [i32; 3],
    /// Cells of the array along each axis.
    dims: [usize; 3],
    /// `starts[c]..starts[c + 1]` is cell `c`'s range in `order` and `sorted` (cell index
    /// `x + dims[0] * (y + dims[1] * z)`, relative to `cell_lo`); one more entry than cells.
    starts: Vec<u32>,
    /// Point indices grouped by cell.
    order: Vec<u32>,
    /// The points of `order`, in that order (metres).
    sorted: Vec<[f32; 3]>,
    /// The points, in input order.
    points: Vec<[f32; 3]>,
}

/// The cell array of a [`KnnIndex`] holds at most this many cells per indexed point (plus
/// [`MIN_CELL_BUDGET`]); sparser points get larger cells.
const CELLS_PER_POINT: usize = 32;
/// See [`CELLS_PER_POINT`].
const MIN_CELL_BUDGET: usize = 1 << 15;

impl KnnIndex {
    /// Index `points` with cells of about twice the mean spacing of a surface sample (the bounding
    /// box diagonal over the square root of the count). Non-finite points are never returned.
    pub fn new(points: &[[f32; 3]]) -> KnnIndex {
        let cloud = PointCloud::from_points(points.to_vec());
        let diag = cloud.bbox().map(|b| b.diagonal()).unwrap_or(0.0) as f32;
        let n = points.len().max(1) as f32;
        let cell = if diag.is_finite() && diag > 0.0 { (2.0 * diag / n.sqrt()).max(1e-6) } else { 1.0 };
        KnnIndex::with_cell(cloud.points, cell)
    }

    /// Index `points` with cubic cells of `cell_m` metres (positive; enlarged so the cell array over
    /// the points' bounding box holds at most [`CELLS_PER_POINT`] cells per point).
    pub fn with_cell(points: Vec<[f32; 3]>, cell_m: f32) -> KnnIndex {
        let mut cell_m = if cell_m.is_finite() && cell_m > 0.0 { cell_m } else { 1.0 };
        let finite = |p: &&[f32; 3]| p.iter().all(|x| x.is_finite());
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        let mut count = 0usize;
        for p in points.iter().filter(finite) {
            count += 1;
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let budget = CELLS_PER_POINT * count + MIN_CELL_BUDGET;
        let (cell_lo, dims) = loop {
            let cl = lo.map(|x| cell_coord(x, cell_m));
            let ch = hi.map(|x| cell_coord(x, cell_m));
            let dims =
                [0, 1, 2].map(|a| if count == 0 { 0 } else { (i64::from(ch[a]) - i64::from(cl[a]) + 1) as usize });
            let cells = dims.iter().map(|&d| d as f64).product::<f64>();
            if cells <= budget as f64 {
                break (cl, dims);
            }
            // Too many cells: enlarge them (at least 10% a step, so the loop ends).
            cell_m *= ((cells / budget as f64).cbrt() as f32).max(1.1);
        };
        let ncells = dims[0] * dims[1] * dims[2];
        let linear = |p: &[f32; 3]| -> usize {
            let c = [0, 1, 2].map(|a| (cell_coord(p[a], cell_m) - cell_lo[a]) as usize);
            c[0] + dims[0] * (c[1] + dims[1] * c[2])
        };
        // Counting sort of the finite points by cell (stable: input order within a cell).
        let mut starts = vec![0u32; ncells + 1];
        let cell_of: Vec<u32> = points.iter().map(|p| if finite(&p) { linear(p) as u32 } else { u32::MAX }).collect();
        for &c in cell_of.iter().filter(|&&c| c != u32::MAX) {
            starts[c as usize + 1] += 1;
        }
        for c in 0..ncells {
            starts[c + 1] += starts[c];
        }
        let mut fill = starts.clone();
        let mut order = vec![0u32; count];
        for (i, &c) in cell_of.iter().enumerate().filter(|(_, &c)| c != u32::MAX) {
            order[fill[c as usize] as usize] = i as u32;
            fill[c as usize] += 1;
        }
        let sorted = order.iter().map(|&i| points[i as usize]).collect();
        KnnIndex { cell_m, cell_lo, dims, starts, order, sorted, points }
    }

    /// The indexed points, metres.
    pub fn points(&self) -> &[[f32; 3]] {
        &self.points
    }

    /// `f(i, point, scratch)` of every indexed point `i`, in the points' order. The finite points are
    /// visited cell by cell, in parallel, so that consecutive queries about them read the same cells;
    /// the others (which no query finds) one by one after them.
    pub fn map_points<T, F>(&self, f: F) -> Vec<T>
    where
        T: Send,
        F: Fn(usize, &[f32; 3], &mut Vec<(f32, u32)>) -> T + Sync,
    {
        let measured: Vec<T> =
            self.sorted.par_iter().zip(&self.order).map_init(Vec::new, |buf, (p, &i)| f(i as usize, p, buf)).collect();
        let mut out: Vec<Option<T>> = (0..self.points.len()).map(|_| None).collect();
        for (&i, m) in self.order.iter().zip(measured) {
            out[i as usize] = Some(m);
        }
        let mut buf = Vec::new();
        out.into_iter().enumerate().map(|(i, m)| m.unwrap_or_else(|| f(i, &self.points[i], &mut buf))).collect()
    }

    /// The `k` points nearest to `q` as `(squared distance m², index)`, nearest first, into `out`
    /// (cleared first; fewer than `k` if the index holds fewer finite points).
    pub fn k_nearest(&self, q: &[f32; 3], k: usize, out: &mut Vec<(f32, u32)>) {
        self.k_nearest_within(q, k, f32::INFINITY, out);
    }

    /// As [`KnnIndex::k_nearest`], but only points within `max_m` metres of `q`.
    ///
    /// The cells are searched in growing shells around `q`'s cell. The candidates of a shell are
    /// appended unsorted and cut down to the `k` best (by squared distance, then index: a total
    /// order, so the answer does not depend on the cells' order) only between shells and when the
    /// buffer grows long, instead of being insertion-sorted one by one.
    pub fn k_nearest_within(&self, q: &[f32; 3], k: usize, max_m: f32, out: &mut Vec<(f32, u32)>) {
        out.clear();
        let max2 = max_m * max_m;
        if k == 0 || self.order.is_empty() || !q.iter().all(|x| x.is_finite()) {
            return;
        }
        // The k-th best candidate so far (only a candidate better than it can enter), once known.
        let mut worst: Option<(f32, u32)> = None;
        // The query's cell, relative to the array (may lie outside it).
        let c = [0, 1, 2].map(|a| i64::from(cell_coord(q[a], self.cell_m)) - i64::from(self.cell_lo[a]));
        let d = self.dims.map(|x| x as i64);
        // Distance from q to the faces of its own cell.
        let own = (0..3)
            .map(|a| {
                let lo = (c[a] + i64::from(self.cell_lo[a])) as f32 * self.cell_m;
                (q[a] - lo).min(lo + self.cell_m - q[a]).max(0.0)
            })
            .fold(f32::INFINITY, f32::min);
        let reach = (0..3).map(|a| c[a].abs().max((d[a] - 1 - c[a]).abs())).max().unwrap_or(0);
        // Shells wholly between q and the occupied cells hold nothing.
        let offset = (0..3).map(|a| (-c[a]).max(c[a] - (d[a] - 1)).max(0)).max().unwrap_or(0);
        if offset.saturating_mul(offset).saturating_mul(24) > self.order.len() as i64 {
            // Far from every point: scanning all points is cheaper than the empty shells.
            self.offer_range(q, 0, self.order.len(), k, max2, &mut worst, out);
            keep_best(out, k, &mut worst);
            out.sort_unstable_by_key(rank);
            return;
        }
        let mut r = offset;
        loop {
            if r > 0 {
                let floor = (r - 1) as f32 * self.cell_m + own;
                if floor > max_m {
                    break;
                }
                keep_best(out, k, &mut worst);
                // `worst` is known once `k` candidates are (and `out` holds exactly those).
                if worst.is_some_and(|w| w.0 <= floor * floor) {
                    break;
                }
            }
            if r > reach {
                break;
            }
            // The shell's cells inside the array: full rows on its faces, the two end cells elsewhere.
            let (x0, x1) = ((c[0] - r).max(0), (c[0] + r).min(d[0] - 1));
            for z in (c[2] - r).max(0)..=(c[2] + r).min(d[2] - 1) {
                for y in (c[1] - r).max(0)..=(c[1] + r).min(d[1] - 1) {
                    let row = (y + d[1] * z) * d[0];
                    if r == 0 || (z - c[2]).abs() == r || (y - c[1]).abs() == r {
                        if x0 <= x1 {
                            let (s, e) = (self.starts[(row + x0) as usize], self.starts[(row + x1 + 1) as usize]);
                            self.offer_range(q, s as usize, e as usize, k, max2, &mut worst, out);
                        }
                    } else {
                        for x in [c[0] - r, c[0] + r] {
                            if (0..d[0]).contains(&x) {
                                let cell = (row + x) as usize;
                                let (s, e) = (self.starts[cell], self.starts[cell + 1]);
                                self.offer_range(q, s as usize, e as usize, k, max2, &mut worst, out);
                            }
                        }
                    }
                }
            }
            r += 1;
        }
        keep_best(out, k, &mut worst);
        out.sort_unstable_by_key(rank);
    }

    /// Append to `out` the points `sorted[s..e]` within `sqrt(max2)` metres of `q` that beat
    /// `worst`; the buffer is cut back to the `k` best ([`keep_best`]) whenever it reaches
    /// [`CANDIDATES_PER_K`] times `k` (at least [`MIN_CANDIDATES`]).
    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn offer_range(
        &self,
        q: &[f32; 3],
        s: usize,
        e: usize,
        k: usize,
        max2: f32,
        worst: &mut Option<(f32, u32)>,
        out: &mut Vec<(f32, u32)>,
    ) {
        let mut limit = worst.map_or(max2, |w| w.0.min(max2));
        for (p, &i) in self.sorted[s..e].iter().zip(&self.order[s..e]) {
            let d2 = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
            // `limit` admits ties with the worst; the index decides those.
            if d2 > limit || worst.is_some_and(|w| rank(&(d2, i)) >= rank(&w)) {
                continue;
            }
            out.push((d2, i));
            if out.len() >= (CANDIDATES_PER_K * k).max(MIN_CANDIDATES) {
                keep_best(out, k, worst);
                limit = worst.map_or(max2, |w| w.0.min(max2));
            }
        }
    }
}

/// A [`KnnIndex`] query's candidate buffer is cut back to its `k` best when it holds this many
/// times `k` (and at least [`MIN_CANDIDATES`]).
const CANDIDATES_PER_K: usize = 8;
/// See [`CANDIDATES_PER_K`].
const MIN_CANDIDATES: usize = 32;

/// The order of `(squared distance, index)` candidates as one integer: nearer first, then lower
/// index. A squared distance is never negative, and the bits of a non-negative `f32` order as it does.
#[inline]
fn rank(c: &(f32, u32)) -> u64 {
    u64::from(c.0.to_bits()) << 32 | u64::from(c.1)
}

/// Keep the `k` best of the candidates in `out` (unordered) and, when there are `k`, set `worst`
/// to the `k`-th.
#[inline]
fn keep_best(out: &mut Vec<(f32, u32)>, k: usize, worst: &mut Option<(f32, u32)>) {
    if out.len() > k {
        out.select_nth_unstable_by_key(k - 1, rank);
        out.truncate(k);
        *worst = Some(out[k - 1]);
    } else if out.len() == k && worst.is_none() {
        *worst = out.iter().copied().max_by_key(rank);
    }
}

/// Whether voxel `(i, j, k)` lies on a face of the grid that is seeded "outside".
fn on_seeded_face(grid: &VoxelGrid, params: &CloudMeshParams, i: usize, j: usize, k: usize) -> bool {
    let d = grid.dims;
    i == 0 || j == 0 || i + 1 == d[0] || j + 1 == d[1] || k + 1 == d[2] || (k == 0 && !params.floor_is_support)
}

/// Flip small components of `label` (-1 inside, +1 outside; see [`CloudMeshParams`]); returns the
/// voxels flipped.
fn drop_small_components(label: &mut [i8], grid: &VoxelGrid, params: &CloudMeshParams) -> u64 {
    if params.min_component_fraction <= 0.0 {
        return 0;
    }
    let d = grid.dims;
    let mut comp = vec![u32::MAX; label.len()];
    // Per component: sign, size, touches a seeded face.
    let mut comps: Vec<(i8, u64, bool)> = Vec::new();
    let mut stack = Vec::new();
    for start in 0..label.len() {
        if comp[start] != u32::MAX {
            continue;
        }
        let id = comps.len() as u32;
        let s = label[start];
        let (mut size, mut open) = (0u64, false);
        comp[start] = id;
        stack.push(start);
        while let Some(idx) = stack.pop() {
            size += 1;
            let (i, j, k) = (idx % d[0], (idx / d[0]) % d[1], idx / (d[0] * d[1]));
            open |= on_seeded_face(grid, params, i, j, k);
            let mut nbrs = [usize::MAX; 6];
            if i > 0 {
                nbrs[0] = idx - 1;
            }
            if i + 1 < d[0] {
                nbrs[1] = idx + 1;
            }
            if j > 0 {
                nbrs[2] = idx - d[0];
            }
            if j + 1 < d[1] {
                nbrs[3] = idx + d[0];
            }
            if k > 0 {
                nbrs[4] = idx - d[0] * d[1];
            }
            if k + 1 < d[2] {
                nbrs[5] = idx + d[0] * d[1];
            }
            for n in nbrs {
                if n != usize::MAX && comp[n] == u32::MAX && label[n] == s {
                    comp[n] = id;
                    stack.push(n);
                }
            }
        }
        comps.push((s, size, open));
    }
    let largest = comps.iter().filter(|c| c.0 < 0).map(|c| c.1).max().unwrap_or(0);
    let limit = (params.min_component_fraction * largest as f64).ceil() as u64;
    let flip: Vec<bool> = comps.iter().map(|&(s, size, open)| size < limit && !(s > 0 && open)).collect();
    let mut flipped = 0;
    for (l, c) in label.iter_mut().zip(&comp) {
        if flip[*c as usize] {
            *l = -*l;
            flipped += 1;
        }
    }
    flipped
}

fn dist(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The cell coordinate of `x` (metres) along one axis with cells of `cell` metres, clamped to
/// `±2^29` so sums of coordinates stay in range.
fn cell_coord(x: f32, cell: f32) -> i32 {
    (x / cell).floor().clamp(i32::MIN as f32 / 4.0, i32::MAX as f32 / 4.0) as i32
}

/// Parameters of [`mesh_from_cloud`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CloudMeshParams {
    /// Oriented points averaged per signed-distance evaluation (3..=64).
    pub k: usize,
    /// Width of the Gaussian weight of a tangent plane by its point's distance, metres; `None`: one
    /// voxel edge.
    pub kernel_m: Option<f64>,
    /// Half-width of the band of voxels around the points where the signed distance is evaluated, in
    /// voxel edges (at least 1).
    pub band_voxels: f64,
    /// Whether the grid's floor (its `z`-minimum face) is left unseeded, as for an object standing on
    /// the turntable top: the floor is then closed by the grid's boundary instead of being "outside".
    pub floor_is_support: bool,
    /// How far from the band a voxel takes the side of its nearest point's tangent plane (Hoppe's
    /// sign), voxel edges. Hoppe's sign closes holes in the sampling flat (an unseen patch of a
    /// floor); the limit keeps a stray point from claiming a large region. Beyond it, a voxel is
    /// outside if the seeded outer faces reach it through such voxels, else inside (enclosed).
    pub hoppe_reach_voxels: f64,
    /// Connected inside components (6-connected voxels) smaller than this fraction of the largest are
    /// dropped (blobs around stray points), and outside components enclosed by the surface that are
    /// smaller are filled (bubbles); 0 keeps everything.
    pub min_component_fraction: f64,
}

impl Default for CloudMeshParams {
    fn default() -> Self {
        CloudMeshParams {
            k: 8,
            kernel_m: None,
            band_voxels: 2.0,
            floor_is_support: true,
            hoppe_reach_voxels: 8.0,
            min_component_fraction: 0.02,
        }
    }
}

/// What [`mesh_from_cloud`] did, for reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct CloudMeshStats {
    /// Voxels where the signed distance was evaluated.
    pub band_voxels: u64,
    /// Voxels inside the surface.
    pub inside_voxels: u64,
    /// Voxels of small inside or enclosed outside components that were flipped.
    pub flipped_voxels: u64,
    /// Mesh vertices moved onto the zero crossing.
    pub refined_vertices: u64,
    /// Voxel-scale handles removed from the inside voxels before meshing (the returned solid is
    /// the one before).
    pub handles: HandleRepair,
}

/// Call `visit` with the index of each voxel of `grid` the line from `p` along the unit direction
/// `d` crosses (see [`SightLineCounts`]; metres, the grid's frame), sampled every half voxel edge
/// from `skip_m` metres on until it leaves the grid; a voxel may come more than once. Nothing for a
/// non-finite point or direction.
fn for_each_voxel_on_sight_line(
    grid: &VoxelGrid,
    p: &[f32; 3],
    d: &[f32; 3],
    skip_m: f64,
    mut visit: impl FnMut(usize),
) {
    let vs = grid.voxel_size;
    let step = 0.5 * vs;
    let dims = grid.dims;
    let p = p.map(f64::from);
    let d = d.map(f64::from);
    if !p.iter().chain(&d).all(|x| x.is_finite()) {
        return;
    }
    let mut t = skip_m.max(0.0);
    // The ray leaves the grid's box for good once it is outside and moving away on some axis.
    loop {
        let q = [0, 1, 2].map(|a| (p[a] + t * d[a] - grid.origin[a]) / vs);
        let leaving = (0..3).any(|a| (q[a] < 0.0 && d[a] <= 0.0) || (q[a] >= dims[a] as f64 && d[a] >= 0.0));
        if leaving || t > 1e3 {
            break;
        }
        if (0..3).all(|a| q[a] >= 0.0 && q[a] < dims[a] as f64) {
            visit(grid.index(q[0] as usize, q[1] as usize, q[2] as usize));
        }
        t += step;
    }
}

/// Lines of sight gathered as the points arrive: the line from each point towards a viewpoint whose
/// line to the point is known to be clear (the camera that saw it, or the light source that lit it),
/// given as the unit direction from the point to that viewpoint (the grid's frame). The first
/// `skip_m` metres next to the point are left alone (the point's own noise); the line is followed,
/// in steps of half a voxel edge, until it leaves the grid, so the viewpoints must lie outside the
/// grid; non-finite points or directions add nothing. Per voxel, how many lines cross it is kept, so
/// the lines of points later found to be outliers can be taken out again;
/// [`SightLineCounts::mark_free`] then marks the voxels the remaining lines cross.
#[derive(Debug, Clone)]
pub struct SightLineCounts {
    grid: VoxelGrid,
    skip_m: f64,
    /// Lines crossing each voxel (each line counted once per voxel).
    counts: Vec<u32>,
}

impl SightLineCounts {
    /// No lines yet, on `grid`; each line skips its first `skip_m` metres.
    pub fn new(grid: &VoxelGrid, skip_m: f64) -> SightLineCounts {
        SightLineCounts { grid: *grid, skip_m, counts: vec![0; grid.len()] }
    }

    /// Count the line from each point (metres, the grid's frame) along its unit direction in
    /// `towards` (one per point).
    pub fn add(&mut self, points: &[[f32; 3]], towards: &[[f32; 3]]) -> Result<(), CloudError> {
        self.update(points, towards, true)
    }

    /// Take back lines counted by [`SightLineCounts::add`] (the same points and directions).
    pub fn remove(&mut self, points: &[[f32; 3]], towards: &[[f32; 3]]) -> Result<(), CloudError> {
        self.update(points, towards, false)
    }

    fn update(&mut self, points: &[[f32; 3]], towards: &[[f32; 3]], add: bool) -> Result<(), CloudError> {
        if towards.len() != points.len() {
            return Err(CloudError::AttributeLength { attribute: "normals", len: towards.len(), points: points.len() });
        }
        for (p, d) in points.iter().zip(towards) {
            // A line's samples in one voxel come in a row (a straight line, convex voxels):
            // counting only changes of voxel counts each voxel once per line.
            let mut last = usize::MAX;
            for_each_voxel_on_sight_line(&self.grid, p, d, self.skip_m, |idx| {
                if idx != last {
                    let c = &mut self.counts[idx];
                    *c = if add { c.saturating_add(1) } else { c.saturating_sub(1) };
                    last = idx;
                }
            });
        }
        Ok(())
    }

    /// Set `free[idx]` (one entry per voxel of the grid) for every voxel a counted line crosses.
    pub fn mark_free(&self, free: &mut [bool]) -> Result<(), CloudError> {
        if free.len() != self.counts.len() {
            return Err(CloudError::FreeSpaceSize { given: free.len(), expected: self.counts.len() });
        }
        for (f, &c) in free.iter_mut().zip(&self.counts) {
            *f |= c > 0;
        }
        Ok(())
    }
}

/// A min-priority queue of `(squared distance m², voxel index)` entries, popped by distance then
/// index, as a binary heap of the pairs would pop them. Entries fall into buckets by distance (a
/// monotone map, so every entry of a bucket comes before those of the next), the pair packed into
/// one `u64`. A bucket's entries are only appended until it comes up; it is then sorted once and
/// drained in order. An entry pushed into the bucket being drained, or into an earlier one (a
/// voxel reached again, nearer), goes into a small binary heap that is drained beside it.
struct BucketQueue {
    /// The entries of the buckets after `current`, unordered.
    buckets: Vec<Vec<u64>>,
    /// Bucket `current`'s entries as it came up, ascending; `sorted[head..]` are still queued.
    sorted: Vec<u64>,
    head: usize,
    /// Entries pushed into bucket `current` or an earlier one after it came up.
    late: BinaryHeap<Reverse<u64>>,
    /// Buckets per m² of squared distance.
    scale: f32,
    /// The bucket being drained (`None` before the first pop).
    current: Option<usize>,
}

/// Buckets of a [`BucketQueue`].
const QUEUE_BUCKETS: usize = 4096;

impl BucketQueue {
    /// Buckets spread over squared distances `0..=max_d2` (m²); larger ones share the last bucket.
    fn new(max_d2: f32) -> BucketQueue {
        let scale = if max_d2.is_finite() && max_d2 > 0.0 { QUEUE_BUCKETS as f32 / max_d2 } else { 0.0 };
        BucketQueue {
            buckets: vec![Vec::new(); QUEUE_BUCKETS],
            sorted: Vec::new(),
            head: 0,
            late: BinaryHeap::new(),
            scale,
            current: None,
        }
    }

    /// Add an entry; `d2` must be non-negative (the bits of non-negative floats order as they do).
    fn push(&mut self, d2: f32, idx: u32) {
        let b = ((d2 * self.scale) as usize).min(QUEUE_BUCKETS - 1);
        let key = (u64::from(d2.to_bits()) << 32) | u64::from(idx);
        match self.current {
            Some(c) if b <= c => self.late.push(Reverse(key)),
            _ => self.buckets[b].push(key),
        }
    }

    /// Remove the least entry.
    fn pop(&mut self) -> Option<(f32, u32)> {
        let unpack = |key: u64| (f32::from_bits((key >> 32) as u32), key as u32);
        loop {
            // Every entry left in the buckets comes after both of these.
            let next = self.sorted.get(self.head).copied();
            match (next, self.late.peek()) {
                (Some(a), Some(&Reverse(b))) if b < a => {
                    self.late.pop();
                    return Some(unpack(b));
                }
                (Some(a), _) => {
                    self.head += 1;
                    return Some(unpack(a));
                }
                (None, Some(&Reverse(b))) => {
                    self.late.pop();
                    return Some(unpack(b));
                }
                (None, None) => {}
            }
            // Bring up the next bucket holding entries.
            let from = self.current.map_or(0, |c| c + 1);
            let b = (from..QUEUE_BUCKETS).find(|&b| !self.buckets[b].is_empty())?;
            std::mem::swap(&mut self.sorted, &mut self.buckets[b]);
            self.buckets[b].clear();
            self.sorted.sort_unstable();
            self.head = 0;
            self.current = Some(b);
        }
    }
}

/// The signed distance field of an oriented cloud (module docs), metres, positive outside.
struct SignedDistance {
    index: KnnIndex,
    normals: Vec<[f32; 3]>,
    k: usize,
    inv_h2: f32,
    /// Points farther than this (metres) are not consulted.
    max_m: f32,
}

/// The points nearest to an origin, gathered once so that evaluations of a [`SignedDistance`] near
/// it need no search of the index.
struct Neighbourhood {
    /// Metres, the cloud's frame.
    origin: [f32; 3],
    /// Every indexed point not in `near` is at least this far from `origin`, metres.
    reach_m: f32,
    /// `(squared distance from origin m², point index)`, nearest first.
    near: Vec<(f32, u32)>,
}

impl Neighbourhood {
    fn new() -> Neighbourhood {
        Neighbourhood { origin: [0.0; 3], reach_m: 0.0, near: Vec::new() }
    }
}

impl SignedDistance {
    /// Signed distance and its gradient direction (the weighted mean normal) at `p`.
    fn eval(&self, p: &[f32; 3], buf: &mut Vec<(f32, u32)>) -> Option<(f32, [f32; 3])> {
        self.index.k_nearest_within(p, self.k, self.max_m, buf);
        self.weigh(p, buf)
    }

    /// Gather into `hood` the `2k` points nearest to `origin` (metres) within `radius_m` metres.
    fn gather(&self, origin: &[f32; 3], radius_m: f32, hood: &mut Neighbourhood) {
        let count = (2 * self.k).min(MAX_K);
        self.index.k_nearest_within(origin, count, radius_m, &mut hood.near);
        hood.origin = *origin;
        hood.reach_m = if hood.near.len() < count { radius_m } else { hood.near[count - 1].0.sqrt() };
    }

    /// As [`SignedDistance::eval`], the same to the last bit, taking the `k` nearest points from
    /// `hood` when it provably holds them (`p` close enough to its origin), else from the index.
    fn eval_near(&self, p: &[f32; 3], hood: &Neighbourhood, buf: &mut Vec<(f32, u32)>) -> Option<(f32, [f32; 3])> {
        // Every point outside `hood` is farther than `clear` from p (the margin covers rounding).
        let clear = hood.reach_m - dist(p, &hood.origin) - 1e-4 * self.max_m;
        if clear > 0.0 {
            buf.clear();
            let max2 = self.max_m * self.max_m;
            for &(_, i) in &hood.near {
                // The index's own arithmetic, so the distances are bit for bit its.
                let x = &self.index.points[i as usize];
                let d2 = (x[0] - p[0]).powi(2) + (x[1] - p[1]).powi(2) + (x[2] - p[2]).powi(2);
                if d2 <= max2 && (buf.len() < self.k || (d2, i) < buf[buf.len() - 1]) {
                    let at = buf.partition_point(|e| (e.0, e.1) < (d2, i));
                    buf.insert(at, (d2, i));
                    buf.truncate(self.k);
                }
            }
            let complete = if buf.len() == self.k { buf[self.k - 1].0 <= clear * clear } else { clear >= self.max_m };
            if complete {
                return self.weigh(p, buf);
            }
        }
        self.eval(p, buf)
    }

    /// The signed distance and gradient at `p` from its nearest points `buf` (as the index gives them).
    fn weigh(&self, p: &[f32; 3], buf: &[(f32, u32)]) -> Option<(f32, [f32; 3])> {
        let d0 = buf.first()?.0;
        let (mut num, mut den, mut g) = (0.0f32, 0.0f32, [0.0f32; 3]);
        for &(d2, i) in buf.iter() {
            let w = (-(d2 - d0) * self.inv_h2).exp();
            let x = &self.index.points[i as usize];
            let n = &self.normals[i as usize];
            num += w * ((p[0] - x[0]) * n[0] + (p[1] - x[1]) * n[1] + (p[2] - x[2]) * n[2]);
            den += w;
            for a in 0..3 {
                g[a] += w * n[a];
            }
        }
        (den > 0.0).then(|| (num / den, g.map(|x| x / den)))
    }
}

/// A closed, consistently oriented mesh of the surface of an oriented cloud (module docs), on the
/// voxels of `grid` (metres, the cloud's frame; its floor is the turntable top when
/// `floor_is_support`). The cloud must have normals pointing out of the object.
pub fn mesh_from_cloud(
    cloud: &PointCloud,
    grid: &VoxelGrid,
    params: &CloudMeshParams,
) -> Result<(TriangleMesh, CloudMeshStats), CloudError> {
    solid_and_mesh_from_cloud(cloud, grid, params).map(|(_, mesh, stats)| (mesh, stats))
}

/// As [`mesh_from_cloud`], also returning the solid the mesh bounds (the inside voxels of `grid`, before
/// the voxel-scale handles are removed for meshing; see [`CloudMeshStats::handles`]).
pub fn solid_and_mesh_from_cloud(
    cloud: &PointCloud,
    grid: &VoxelGrid,
    params: &CloudMeshParams,
) -> Result<(Occupancy, TriangleMesh, CloudMeshStats), CloudError> {
    solid_and_mesh_from_cloud_with_free_space(cloud, grid, params, None)
}

/// As [`solid_and_mesh_from_cloud`], with voxels known to be empty: `free[grid.index(i, j, k)]` is
/// true for a voxel seen to be air (outside the silhouettes' visual hull, or crossed by a line of
/// sight to a surface point). Beyond the band, a free voxel is outside whatever the nearest tangent
/// plane says, and the outer air spreads into the unlabelled voxels (farther than
/// `hoppe_reach_voxels` from every point) only through free ones: a patch of the surface the scan
/// never sampled, wider than the Hoppe reach, then no longer lets the outside into the object; the
/// unseen patch is closed by the free space around it. `None` behaves as
/// [`solid_and_mesh_from_cloud`] (every unlabelled voxel is passable).
pub fn solid_and_mesh_from_cloud_with_free_space(
    cloud: &PointCloud,
    grid: &VoxelGrid,
    params: &CloudMeshParams,
    free: Option<&[bool]>,
) -> Result<(Occupancy, TriangleMesh, CloudMeshStats), CloudError> {
    if let Some(f) = free {
        if f.len() != grid.len() {
            return Err(CloudError::FreeSpaceSize { given: f.len(), expected: grid.len() });
        }
    }
    if grid.len() > u32::MAX as usize {
        return Err(CloudError::Parameter {
            name: "grid voxels",
            value: grid.len() as f64,
            expected: "at most 2^32 - 1",
        });
    }
    check_k(params.k)?;
    let normals = cloud.normals().ok_or(CloudError::NoNormals)?;
    if !(params.band_voxels.is_finite() && params.band_voxels >= 1.0) {
        return Err(CloudError::Parameter { name: "band_voxels", value: params.band_voxels, expected: ">= 1" });
    }
    if !(params.hoppe_reach_voxels.is_finite() && params.hoppe_reach_voxels >= 0.0) {
        let value = params.hoppe_reach_voxels;
        return Err(CloudError::Parameter { name: "hoppe_reach_voxels", value, expected: ">= 0" });
    }
    if !(params.min_component_fraction.is_finite() && (0.0..=1.0).contains(&params.min_component_fraction)) {
        let value = params.min_component_fraction;
        return Err(CloudError::Parameter { name: "min_component_fraction", value, expected: "0..=1" });
    }
    let h = params.kernel_m.unwrap_or(grid.voxel_size);
    if !(h.is_finite() && h > 0.0) {
        return Err(CloudError::Parameter { name: "kernel_m", value: h, expected: "positive, finite" });
    }
    // Points without support (fewer than SUPPORT_NEIGHBOURS others within SUPPORT_KERNELS kernel
    // widths) are stray: they would put a patch of surface of their own into the field.
    let all = KnnIndex::new(cloud.points());
    let support_m = (SUPPORT_KERNELS * h) as f32;
    let supported: Vec<bool> = all.map_points(|_, p, buf| {
        all.k_nearest_within(p, SUPPORT_NEIGHBOURS + 1, support_m, buf);
        buf.len() > SUPPORT_NEIGHBOURS
    });
    drop(all);
    let kept =
        |v: &[[f32; 3]]| -> Vec<[f32; 3]> { v.iter().zip(&supported).filter(|(_, &s)| s).map(|(x, _)| *x).collect() };
    let sdf = SignedDistance {
        index: KnnIndex::new(&kept(cloud.points())),
        normals: kept(normals),
        k: params.k,
        inv_h2: (1.0 / (h * h)) as f32,
        // Band voxels and refined vertices lie within the band (plus a voxel) of their nearest point,
        // and a point 3 kernel widths farther than the nearest weighs less than e^-9.
        max_m: ((params.band_voxels + 1.0) * grid.voxel_size + 3.0 * h) as f32,
    };
    let vs = grid.voxel_size;
    let dims = grid.dims;
    // 1. The band: voxels whose centre is within band_voxels edges of a point.
    let band_m = params.band_voxels * vs;
    let reach = params.band_voxels.ceil() as i64;
    let mut in_band = vec![false; grid.len()];
    for p in sdf.index.points() {
        let f = [0, 1, 2].map(|a| (f64::from(p[a]) - grid.origin[a]) / vs - 0.5);
        if !f.iter().all(|x| x.is_finite()) {
            continue;
        }
        let base = f.map(|x| x.round() as i64);
        for dz in -reach..=reach {
            for dy in -reach..=reach {
                for dx in -reach..=reach {
                    let v = [base[0] + dx, base[1] + dy, base[2] + dz];
                    if (0..3).any(|a| v[a] < 0 || v[a] >= dims[a] as i64) {
                        continue;
                    }
                    let d2: f64 = (0..3).map(|a| ((v[a] as f64 - f[a]) * vs).powi(2)).sum();
                    if d2 <= band_m * band_m {
                        in_band[grid.index(v[0] as usize, v[1] as usize, v[2] as usize)] = true;
                    }
                }
            }
        }
    }
    let band: Vec<usize> = (0..grid.len()).filter(|&i| in_band[i]).collect();
    if band.is_empty() {
        return Err(CloudError::NoPointsInGrid);
    }
    let unravel = |idx: usize| [idx % dims[0], (idx / dims[0]) % dims[1], idx / (dims[0] * dims[1])];
    // 2. Signs on the band, and each band voxel's nearest point.
    let band_eval: Vec<(i8, u32, f32)> = band
        .par_iter()
        .map_init(Vec::new, |buf, &idx| {
            let [i, j, k] = unravel(idx);
            let c = grid.centre(i, j, k);
            let sign = match sdf.eval(&[c.x as f32, c.y as f32, c.z as f32], buf) {
                Some((d, _)) if d < 0.0 => -1,
                _ => 1,
            };
            let (d2, near) = buf.first().copied().unwrap_or((f32::INFINITY, u32::MAX));
            (sign, near, d2)
        })
        .collect();
    // 3. Every other voxel takes the side of the tangent plane of its nearest point (Hoppe's sign),
    //    the nearest point found by a Dijkstra wave over the voxels from the band (a vector distance
    //    transform), up to `hoppe_reach_voxels` from the band.
    let mut label = vec![0i8; grid.len()];
    // Per voxel, side by side so that the wave reads both in one access: the squared distance (m²)
    // to its nearest point found so far, and that point (`NO_POINT`: none), with `BAND` set on the
    // band's voxels (the wave starts from them and never enters them).
    const BAND: u32 = 1 << 31;
    const NO_POINT: u32 = BAND - 1;
    let points = sdf.index.points();
    if points.len() >= NO_POINT as usize {
        return Err(CloudError::Parameter {
            name: "cloud points",
            value: points.len() as f64,
            expected: "fewer than 2^31 - 1",
        });
    }
    let mut wave = vec![(f32::INFINITY, NO_POINT); grid.len()];
    let reach2 = ((params.hoppe_reach_voxels * vs).powi(2)) as f32;
    let mut heap = BucketQueue::new(reach2);
    for (&idx, &(sign, p, d2)) in band.iter().zip(&band_eval) {
        label[idx] = sign;
        wave[idx].1 = BAND | NO_POINT;
        if p != u32::MAX {
            wave[idx] = (d2, BAND | p);
            heap.push(d2, idx as u32);
        }
    }
    let normals = &sdf.normals;
    // Voxel centres per axis, as `grid.centre` gives them in f32.
    let centres: [Vec<f32>; 3] =
        [0, 1, 2].map(|a| (0..dims[a]).map(|i| (grid.origin[a] + (i as f64 + 0.5) * grid.voxel_size) as f32).collect());
    while let Some((d2, idx)) = heap.pop() {
        let idx = idx as usize;
        let (best, from) = wave[idx];
        if d2 > best {
            continue;
        }
        let from = from & !BAND;
        let [i, j, k] = unravel(idx);
        let p = points[from as usize];
        let mut offer = |n: usize, c: [usize; 3]| {
            let w = &mut wave[n];
            if w.1 & BAND != 0 {
                return;
            }
            let q = [centres[0][c[0]], centres[1][c[1]], centres[2][c[2]]];
            let d2 = (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2);
            if d2 < w.0 && d2 <= reach2 {
                *w = (d2, from);
                heap.push(d2, n as u32);
            }
        };
        if i > 0 {
            offer(idx - 1, [i - 1, j, k]);
        }
        if i + 1 < dims[0] {
            offer(idx + 1, [i + 1, j, k]);
        }
        if j > 0 {
            offer(idx - dims[0], [i, j - 1, k]);
        }
        if j + 1 < dims[1] {
            offer(idx + dims[0], [i, j + 1, k]);
        }
        if k > 0 {
            offer(idx - dims[0] * dims[1], [i, j, k - 1]);
        }
        if k + 1 < dims[2] {
            offer(idx + dims[0] * dims[1], [i, j, k + 1]);
        }
    }
    label.par_iter_mut().zip(&wave).enumerate().for_each(|(idx, (l, &(_, from)))| {
        if from & BAND != 0 || from == NO_POINT {
            return;
        }
        let [i, j, k] = unravel(idx);
        let c = grid.centre(i, j, k);
        let (x, n) = (points[from as usize], normals[from as usize]);
        let d = (c.x as f32 - x[0]) * n[0] + (c.y as f32 - x[1]) * n[1] + (c.z as f32 - x[2]) * n[2];
        *l = if d < 0.0 { -1 } else { 1 };
    });
    drop(wave);
    // 4. Beyond that reach: what the seeded outer faces reach through unlabelled voxels is outside
    //    (the air around the object and in its open concavities), the rest is enclosed: inside.
    //    With free space given, the outer air would spread only through free voxels, and every free
    //    voxel off the band is made outside below whatever its label: the flood would change
    //    nothing, so it runs only without.
    if free.is_none() {
        let mut queue = VecDeque::with_capacity(grid.len() / 4);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let idx = grid.index(i, j, k);
                    if label[idx] == 0 && on_seeded_face(grid, params, i, j, k) {
                        label[idx] = 1;
                        queue.push_back(idx);
                    }
                }
            }
        }
        while let Some(idx) = queue.pop_front() {
            let [i, j, k] = unravel(idx);
            let mut visit = |n: usize| {
                if label[n] == 0 {
                    label[n] = 1;
                    queue.push_back(n);
                }
            };
            if i > 0 {
                visit(idx - 1);
            }
            if i + 1 < dims[0] {
                visit(idx + 1);
            }
            if j > 0 {
                visit(idx - dims[0]);
            }
            if j + 1 < dims[1] {
                visit(idx + dims[0]);
            }
            if k > 0 {
                visit(idx - dims[0] * dims[1]);
            }
            if k + 1 < dims[2] {
                visit(idx + dims[0] * dims[1]);
            }
        }
    }
    for l in label.iter_mut().filter(|l| **l == 0) {
        *l = -1;
    }
    // Air seen by the cameras overrides the tangent planes off the band (e.g. the plane of a face
    // extended past the edge next to an unsampled patch of the neighbouring face).
    if let Some(f) = free {
        for (idx, l) in label.iter_mut().enumerate() {
            if f[idx] && !in_band[idx] {
                *l = 1;
            }
        }
    }
    let flipped = drop_small_components(&mut label, grid, params);
    let occupancy = Occupancy::from_index_fn(*grid, |i, j, k| label[grid.index(i, j, k)] < 0);
    let inside_voxels = occupancy.count();
    // 4. Surface, then vertices onto the zero crossing (at most one voxel edge).
    let (mut mesh, handles) = extract_surface_reporting(&occupancy, &MeshParams::smoothed(0))?;
    let limit = vs as f32;
    let converged = (NEWTON_TOLERANCE_VOXELS * vs) as f32;
    let refined: usize = mesh
        .vertices
        .par_iter_mut()
        .map_init(
            || (Vec::new(), Neighbourhood::new()),
            |(buf, hood), v| {
                let start = *v;
                let mut p = *v;
                // Every evaluation lies within `limit` of the start: one search serves them all.
                sdf.gather(&start, sdf.max_m + limit, hood);
                for _ in 0..4 {
                    let Some((d, g)) = sdf.eval_near(&p, hood, buf) else { break };
                    let g2 = g[0] * g[0] + g[1] * g[1] + g[2] * g[2];
                    if g2 < 0.05 || d.abs() <= converged {
                        break;
                    }
                    p = [0, 1, 2].map(|a| p[a] - d * g[a] / g2);
                    if dist(&p, &start) > limit {
                        break;
                    }
                }
                let shift = dist(&p, &start);
                if shift > 0.0 && shift <= limit && p.iter().all(|x| x.is_finite()) {
                    *v = p;
                    1
                } else {
                    0
                }
            },
        )
        .sum();
    let stats = CloudMeshStats {
        band_voxels: band.len() as u64,
        inside_voxels,
        flipped_voxels: flipped,
        refined_vertices: refined as u64,
        handles: handles.unwrap_or_default(),
    };
    Ok((occupancy, mesh, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::chamfer_distance;

    /// A small deterministic generator (SplitMix64) for test noise, uniform in [0, 1).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
        }
        fn gauss(&mut self) -> f32 {
            let (u, v) = (self.next().max(1e-7), self.next());
            (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
        }
    }

    /// Fibonacci points on a sphere of radius `r` centred at `c`, with radial Gaussian noise `sigma`.
    fn sphere(n: usize, r: f32, c: [f32; 3], sigma: f32, rng: &mut Rng) -> Vec<[f32; 3]> {
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        (0..n)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
                let rho = (1.0 - z * z).sqrt();
                let phi = golden * i as f32;
                let rr = r + sigma * rng.gauss();
                [c[0] + rr * rho * phi.cos(), c[1] + rr * rho * phi.sin(), c[2] + rr * z]
            })
            .collect()
    }

    fn brute_knn(points: &[[f32; 3]], q: &[f32; 3], k: usize) -> Vec<f32> {
        let mut d: Vec<f32> =
            points.iter().map(|p| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).collect();
        d.sort_by(f32::total_cmp);
        d.truncate(k);
        d
    }

    #[test]
    fn knn_matches_brute_force() {
        let mut rng = Rng(3);
        let pts = sphere(3000, 0.05, [0.0; 3], 0.001, &mut rng);
        let index = KnnIndex::new(&pts);
        let mut buf = Vec::new();
        let queries = sphere(50, 0.049, [0.0; 3], 0.0, &mut rng).into_iter().chain([[0.0; 3], [0.3, -0.2, 0.1]]);
        for q in queries {
            index.k_nearest(&q, 12, &mut buf);
            let got: Vec<f32> = buf.iter().map(|e| e.0).collect();
            assert_eq!(got, brute_knn(&pts, &q, 12), "{q:?}");
        }
        index.k_nearest(&[f32::NAN, 0.0, 0.0], 4, &mut buf);
        assert!(buf.is_empty());
        KnnIndex::new(&pts[..2]).k_nearest(&[0.0; 3], 5, &mut buf);
        assert_eq!(buf.len(), 2);
    }

    #[test]
    fn knn_is_exact_for_sparse_and_tied_points() {
        // Two clusters 2 km apart with 1 mm cells: the cell array would be far too large, so the
        // cells grow; the answers stay exact.
        let mut rng = Rng(7);
        let mut pts = sphere(500, 0.01, [0.0; 3], 0.0, &mut rng);
        pts.extend(sphere(500, 0.01, [2000.0, 0.0, -5.0], 0.0, &mut rng));
        pts.push([f32::NAN, 0.0, 0.0]);
        let index = KnnIndex::with_cell(pts.clone(), 0.001);
        let mut buf = Vec::new();
        for q in [[0.0, 0.0, 0.011], [2000.0, 0.01, -5.0], [1000.0, 0.0, 0.0], [-3.0, 4.0, 1.0]] {
            index.k_nearest(&q, 9, &mut buf);
            let got: Vec<f32> = buf.iter().map(|e| e.0).collect();
            assert_eq!(got, brute_knn(&pts[..1000], &q, 9), "{q:?}");
        }
        // Equal distances go to the lower index, whatever the cells.
        let tied = vec![[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        for cell in [0.1, 0.7, 5.0] {
            KnnIndex::with_cell(tied.clone(), cell).k_nearest(&[0.0; 3], 3, &mut buf);
            assert_eq!(buf.iter().map(|e| e.1).collect::<Vec<_>>(), vec![0, 1, 2], "cell {cell}");
            KnnIndex::with_cell(tied.clone(), cell).k_nearest_within(&[0.0; 3], 3, 0.9, &mut buf);
            assert!(buf.is_empty());
        }
        KnnIndex::with_cell(Vec::new(), 0.1).k_nearest(&[0.0; 3], 3, &mut buf);
        assert!(buf.is_empty());
    }

    /// Many equal distances and many candidates per cell (a lattice in large cells, so the
    /// candidate buffer is cut back inside a cell): the answer is the brute force's, indices and
    /// order too, with and without a radius.
    #[test]
    fn knn_keeps_the_k_best_by_distance_then_index_through_crowded_cells() {
        let mut pts = Vec::new();
        for z in 0..12 {
            for y in 0..12 {
                for x in 0..12 {
                    pts.push([x as f32 * 0.01, y as f32 * 0.01, z as f32 * 0.01]);
                }
            }
        }
        // Duplicates: the same distance from every query, told apart by index alone.
        pts.extend_from_within(..200);
        let brute = |q: &[f32; 3], k: usize, max_m: f32| -> Vec<(f32, u32)> {
            let mut d: Vec<(f32, u32)> = pts
                .iter()
                .enumerate()
                .map(|(i, p)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2), i as u32))
                .filter(|e| e.0 <= max_m * max_m)
                .collect();
            d.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            d.truncate(k);
            d
        };
        let mut buf = Vec::new();
        for cell in [0.005, 0.035, 0.2] {
            let index = KnnIndex::with_cell(pts.clone(), cell);
            for q in [[0.05, 0.05, 0.05], [0.055, 0.05, 0.0], [0.0, 0.0, 0.0], [0.3, -0.1, 0.05]] {
                for k in [1, 6, 17, 64] {
                    for max_m in [f32::INFINITY, 0.021] {
                        index.k_nearest_within(&q, k, max_m, &mut buf);
                        assert_eq!(buf, brute(&q, k, max_m), "cell {cell} q {q:?} k {k} max {max_m}");
                    }
                }
            }
        }
    }

    #[test]
    fn map_points_answers_in_the_points_order_non_finite_ones_too() {
        let mut rng = Rng(3);
        let mut pts: Vec<[f32; 3]> = (0..500).map(|_| [rng.next(), rng.next(), rng.next()]).collect();
        pts[7] = [f32::NAN, 0.0, 0.0];
        pts[300] = [0.0, f32::INFINITY, 0.0];
        let index = KnnIndex::new(&pts);
        let mut buf = Vec::new();
        let one_by_one: Vec<(usize, Vec<(f32, u32)>)> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| {
                index.k_nearest(p, 5, &mut buf);
                (i, buf.clone())
            })
            .collect();
        let mapped = index.map_points(|i, p, buf| {
            index.k_nearest(p, 5, buf);
            (i, buf.clone())
        });
        assert_eq!(mapped, one_by_one);
        assert!(mapped[7].1.is_empty() && mapped[300].1.is_empty() && mapped[8].1.len() == 5);
    }

    #[test]
    fn bucket_queue_pops_as_a_binary_heap() {
        let mut rng = Rng(17);
        let mut queue = BucketQueue::new(1e-4);
        let mut heap = BinaryHeap::new();
        let push = |d2: f32, i: u32, queue: &mut BucketQueue, heap: &mut BinaryHeap<Reverse<(u32, u32)>>| {
            queue.push(d2, i);
            heap.push(Reverse((d2.to_bits(), i)));
        };
        for i in 0..2000 {
            // Squared distances within and beyond the buckets' span, some equal.
            let d2 = if i % 10 == 0 { 5e-5 } else { 2e-4 * rng.next() };
            push(d2, i, &mut queue, &mut heap);
        }
        let mut popped = 0;
        while let Some(Reverse((bits, i))) = heap.pop() {
            assert_eq!(queue.pop(), Some((f32::from_bits(bits), i)));
            popped += 1;
            // Later entries below the last one popped, as the distance transform makes them, and
            // just above it (into the bucket being drained).
            if popped % 7 == 0 && popped < 3000 {
                let d2 = f32::from_bits(bits) * rng.next();
                push(d2, 10_000 + popped, &mut queue, &mut heap);
            }
            if popped % 5 == 0 && popped < 3000 {
                let d2 = f32::from_bits(bits) * (1.0 + 1e-4 * rng.next());
                push(d2, 20_000 + popped, &mut queue, &mut heap);
            }
        }
        assert_eq!(queue.pop(), None);
        assert!(popped > 2800, "{popped}");
    }

    /// The definition [`SightLineCounts`] must match: every voxel each line crosses, marked directly.
    fn mark_lines_of_sight(
        grid: &VoxelGrid,
        points: &[[f32; 3]],
        towards: &[[f32; 3]],
        skip_m: f64,
        free: &mut [bool],
    ) {
        for (p, d) in points.iter().zip(towards) {
            for_each_voxel_on_sight_line(grid, p, d, skip_m, |idx| free[idx] = true);
        }
    }

    #[test]
    fn sight_line_counts_match_marking_the_kept_points() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.02; 3] }, 20);
        let mut rng = Rng(13);
        let points: Vec<[f32; 3]> =
            (0..300).map(|_| [0.02 * rng.next(), 0.02 * rng.next(), 0.01 * rng.next()]).collect();
        let towards: Vec<[f32; 3]> = (0..300)
            .map(|_| {
                let d = Vector3::new(rng.next() - 0.5, rng.next() - 0.5, 1.0).normalize();
                [d.x, d.y, d.z]
            })
            .collect();
        let keep: Vec<bool> = (0..300).map(|i| i % 7 != 3).collect();
        let pick = |v: &[[f32; 3]], want: bool| -> Vec<[f32; 3]> {
            v.iter().zip(&keep).filter(|(_, &k)| k == want).map(|(x, _)| *x).collect()
        };
        let mut expected = vec![false; grid.len()];
        mark_lines_of_sight(&grid, &pick(&points, true), &pick(&towards, true), 0.002, &mut expected);
        // Added in two batches, the dropped points' lines taken out again.
        let mut counts = SightLineCounts::new(&grid, 0.002);
        counts.add(&points[..100], &towards[..100]).expect("sizes");
        counts.add(&points[100..], &towards[100..]).expect("sizes");
        counts.remove(&pick(&points, false), &pick(&towards, false)).expect("sizes");
        let mut free = vec![false; grid.len()];
        counts.mark_free(&mut free).expect("size");
        assert_eq!(free, expected);
        assert!(free.iter().filter(|&&f| f).count() > 100);
        assert!(counts.add(&points, &towards[1..]).is_err());
        assert!(counts.mark_free(&mut free[1..]).is_err());
    }

    #[test]
    fn plane_normals_face_the_viewpoint_and_outliers_go() {
        // A noisy 10 cm square in the plane z = 0.02, plus 20 points scattered well off it.
        let mut rng = Rng(11);
        let mut pts = Vec::new();
        for j in 0..60 {
            for i in 0..60 {
                pts.push([i as f32 * 0.0017, j as f32 * 0.0017, 0.02 + 0.0001 * rng.gauss()]);
            }
        }
        let clean = pts.len();
        for _ in 0..20 {
            pts.push([0.1 * rng.next(), 0.1 * rng.next(), 0.03 + 0.05 * rng.next()]);
        }
        let mut cloud = PointCloud::from_points(pts);
        let removed = cloud.remove_statistical_outliers(10, 2.0).expect("params");
        assert!(removed >= 20 && removed < 20 + clean / 50, "{removed}");
        assert!(cloud.points().iter().all(|p| (p[2] - 0.02).abs() < 0.001));
        // Seen from below: every normal is -z.
        cloud.estimate_normals(12, |_| [0.05, 0.05, -1.0]).expect("params");
        let normals = cloud.normals().expect("estimated");
        assert!(normals.iter().all(|n| n[2] < -0.99), "{:?}", normals.iter().map(|n| n[2]).fold(0.0, f32::max));
        assert!(matches!(cloud.estimate_normals(2, |_| [0.0; 3]), Err(CloudError::Parameter { name: "k", .. })));
        assert!(matches!(
            cloud.remove_statistical_outliers(8, f64::NAN),
            Err(CloudError::Parameter { name: "std_ratio", .. })
        ));
    }

    #[test]
    fn merge_transform_downsample_and_ply() {
        let a = PointCloud::from_parts(vec![[1.0, 0.0, 0.5]], Some(vec![[1.0, 0.0, 0.0]]), Some(vec![[10, 20, 30]]))
            .expect("lengths");
        let b = PointCloud::from_parts(vec![[1.0, 0.001, 0.5]], Some(vec![[0.0, 1.0, 0.0]]), Some(vec![[30, 40, 50]]))
            .expect("lengths");
        assert!(matches!(
            PointCloud::from_parts(vec![[0.0; 3]], None, Some(vec![])),
            Err(CloudError::AttributeLength { attribute: "colours", len: 0, points: 1 })
        ));
        let mut m = PointCloud::merge([a.clone(), b]);
        assert_eq!(m.len(), 2);
        // Rig -> object at 90 degrees: a rig point on +x was on -y of the object.
        m.rig_to_object(90.0);
        let p = m.points()[0];
        assert!((p[0] - 0.0).abs() < 1e-6 && (p[1] + 1.0).abs() < 1e-6 && p[2] == 0.5, "{p:?}");
        let n = m.normals().expect("normals")[0];
        assert!((n[1] + 1.0).abs() < 1e-6, "{n:?}");
        // One cube of 1 cm holds both: their mean, mean colour, renormalised mean normal.
        let d = m.voxel_downsample(0.01).expect("voxel");
        assert_eq!(d.len(), 1);
        assert_eq!(d.colors().expect("colours")[0], [20, 30, 40]);
        let n = d.normals().expect("normals")[0];
        assert!((n[0] - 0.5f32.sqrt()).abs() < 1e-5 && (n[1] + 0.5f32.sqrt()).abs() < 1e-5, "{n:?}");
        // Attributes survive a merge only if both sides have them.
        let bare = PointCloud::merge([a, PointCloud::from_points(vec![[0.0; 3]])]);
        assert!(bare.normals().is_none() && bare.colors().is_none() && bare.len() == 2);
        // PLY: header names the properties, 27 bytes per point.
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("cloud.ply");
        m.write_ply(&path).expect("write");
        let bytes = std::fs::read(&path).expect("read");
        let end = bytes.windows(11).position(|w| w == b"end_header\n").expect("header") + 11;
        let header = std::str::from_utf8(&bytes[..end]).expect("ascii");
        assert!(header.contains("element vertex 2") && header.contains("property float nx"));
        assert!(header.contains("property uchar red"));
        assert_eq!(bytes.len() - end, 2 * 27);
        assert_eq!(&bytes[end + 24..end + 27], &[10, 20, 30]);
    }

    #[test]
    fn noisy_sphere_with_outliers_meshes_closed_and_within_target() {
        // A 3 cm sphere standing on the floor (centre z = 3 cm), 0.1 mm noise, 2% outliers.
        let (r, c) = (0.03f32, [0.0f32, 0.0, 0.03]);
        let mut rng = Rng(5);
        let mut pts = sphere(30_000, r, c, 0.0001, &mut rng);
        for _ in 0..600 {
            pts.push([0.08 * rng.next() - 0.04, 0.08 * rng.next() - 0.04, 0.07 * rng.next()]);
        }
        let mut cloud = PointCloud::from_points(pts);
        let removed = cloud.remove_statistical_outliers(16, 2.0).expect("params");
        assert!(removed >= 450, "{removed}");
        // Viewpoints outside the sphere along each point's radius.
        let pts = cloud.points().to_vec();
        cloud.estimate_normals(16, |i| [0, 1, 2].map(|a| c[a] + 3.0 * (pts[i][a] - c[a]))).expect("params");
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.036, -0.036, 0.0], max: [0.036, 0.036, 0.066] }, 60);
        let (mesh, stats) = mesh_from_cloud(&cloud, &grid, &CloudMeshParams::default()).expect("mesh");
        assert_eq!(mesh.open_or_misoriented_edges(), 0);
        assert!(stats.refined_vertices as usize > mesh.vertices.len() * 9 / 10, "{stats:?}");
        let ball = 4.0 / 3.0 * std::f64::consts::PI * f64::from(r).powi(3);
        assert!((mesh.signed_volume() / ball - 1.0).abs() < 0.02, "{} vs {ball}", mesh.signed_volume());
        let truth = sphere(40_000, r, c, 0.0, &mut rng);
        let samples = crate::pipeline::sample_mesh(&mesh, 40_000, 1);
        let ch = chamfer_distance(&samples, &truth).expect("non-empty");
        let diag = 2.0 * f64::from(r) * 3f64.sqrt();
        assert!(ch.symmetric_m / diag < 0.005, "{ch:?}, relative {}", ch.symmetric_m / diag);
        // Every vertex on the sphere to well under a voxel (1.2 mm); the Chamfer figure above is
        // dominated by the spacing of the two samples.
        let radial: Vec<f32> = mesh.vertices.iter().map(|v| (dist(v, &c) - r).abs()).collect();
        let mean = radial.iter().sum::<f32>() / radial.len() as f32;
        assert!(mean < 5e-5 && radial.iter().all(|&e| e < 6e-4), "mean {mean} m");
        assert!(stats.flipped_voxels > 0, "{stats:?}");
        // Without normals there is nothing to mesh.
        let bare = PointCloud::from_points(cloud.points().to_vec());
        assert!(matches!(mesh_from_cloud(&bare, &grid, &CloudMeshParams::default()), Err(CloudError::NoNormals)));
    }

    /// Points on the faces of the 40 mm cube `|x|, |y| <= 20 mm, 0 <= z <= 40 mm` (floor face
    /// excluded: it stands on the table) with their outward normals, about one per millimetre, except
    /// a 28 mm wide strip of the `+x` face that the scan never saw.
    fn cube_with_unseen_strip() -> PointCloud {
        let (h, n) = (0.02f32, 41);
        let (mut pts, mut nrm) = (Vec::new(), Vec::new());
        for a in 0..n {
            for b in 0..n {
                let (u, v) = (-h + 2.0 * h * a as f32 / (n - 1) as f32, 2.0 * h * b as f32 / (n - 1) as f32);
                let (s, t) = (u, v - h);
                pts.push([s, t, 2.0 * h]);
                nrm.push([0.0, 0.0, 1.0]);
                pts.push([-h, u, v]);
                nrm.push([-1.0, 0.0, 0.0]);
                if u < -0.008 {
                    pts.push([h, u, v]);
                    nrm.push([1.0, 0.0, 0.0]);
                }
                pts.push([u, -h, v]);
                nrm.push([0.0, -1.0, 0.0]);
                pts.push([u, h, v]);
                nrm.push([0.0, 1.0, 0.0]);
            }
        }
        PointCloud::from_parts(pts, Some(nrm), None).expect("one normal per point")
    }

    #[test]
    fn free_space_closes_an_unseen_strip_wider_than_the_hoppe_reach() {
        let cloud = cube_with_unseen_strip();
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.03, -0.03, 0.0], max: [0.03, 0.03, 0.05] }, 60);
        let params = CloudMeshParams::default();
        let cube = 0.04f64.powi(3);
        // Without free space the outer air flows in through the strip (8 mm reach, 28 mm strip):
        // only a shell remains.
        let (open, _, _) = solid_and_mesh_from_cloud(&cloud, &grid, &params).expect("mesh");
        assert!(open.volume_m3() < 0.8 * cube, "{} vs {cube}", open.volume_m3());
        // The air around the cube as a visual hull would give it (voxel centres outside the cube).
        let d = grid.dims;
        let free: Vec<bool> = (0..grid.len())
            .map(|idx| {
                let c = grid.centre(idx % d[0], (idx / d[0]) % d[1], idx / (d[0] * d[1]));
                c.x.abs() > 0.02 || c.y.abs() > 0.02 || c.z > 0.04
            })
            .collect();
        let (solid, mesh, _) =
            solid_and_mesh_from_cloud_with_free_space(&cloud, &grid, &params, Some(&free)).expect("mesh");
        assert_eq!(mesh.open_or_misoriented_edges(), 0);
        assert!((solid.volume_m3() / cube - 1.0).abs() < 0.03, "{} vs {cube}", solid.volume_m3());
        assert!((mesh.signed_volume() / cube - 1.0).abs() < 0.03, "{} vs {cube}", mesh.signed_volume());
        let off = |v: &[f32; 3]| (v[0].abs() - 0.02).max(v[1].abs() - 0.02).max(v[2] - 0.04).max(-v[2]).abs();
        // The unseen strip is flat to within a voxel; next to the seen faces' edges the band keeps
        // their planes' sign (free space does not override the band), up to 2 voxels off.
        let far = mesh.vertices.iter().filter(|v| off(v) > 0.001).count();
        let worst = mesh.vertices.iter().map(off).fold(0.0f32, f32::max);
        assert!(far * 20 < mesh.vertices.len() && worst < 0.0025, "{far} of {}, worst {worst} m", mesh.vertices.len());
        let strip = |v: &&[f32; 3]| v[0] > 0.019 && v[1] > -0.004 && v[1] < 0.016 && v[2] > 0.004 && v[2] < 0.036;
        let in_strip: Vec<f32> = mesh.vertices.iter().filter(strip).map(off).collect();
        assert!(in_strip.len() > 500 && in_strip.iter().all(|&e| e < 0.001), "{} strip vertices", in_strip.len());
        // A mask of the wrong size is refused.
        assert!(matches!(
            solid_and_mesh_from_cloud_with_free_space(&cloud, &grid, &params, Some(&free[1..])),
            Err(CloudError::FreeSpaceSize { .. })
        ));
    }

    #[test]
    fn lines_of_sight_mark_the_air_between_point_and_viewpoint() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.01; 3] }, 10);
        let mut free = vec![false; grid.len()];
        // A point in voxel (5, 5, 2) seen from straight above; the first 2 mm are skipped.
        let mut lines = SightLineCounts::new(&grid, 0.002);
        lines.add(&[[0.0055, 0.0055, 0.0025]], &[[0.0, 0.0, 1.0]]).expect("sizes");
        lines.mark_free(&mut free).expect("size");
        let marked: Vec<usize> = (0..10).filter(|&k| free[grid.index(5, 5, k)]).collect();
        assert_eq!(marked, vec![4, 5, 6, 7, 8, 9]);
        assert_eq!(free.iter().filter(|&&f| f).count(), 6);
        // Non-finite input adds nothing; mismatched lengths are errors.
        lines.add(&[[f32::NAN; 3]], &[[0.0, 0.0, 1.0]]).expect("sizes");
        lines.mark_free(&mut free).expect("size");
        assert_eq!(free.iter().filter(|&&f| f).count(), 6);
        assert!(lines.add(&[[0.0; 3]], &[]).is_err());
        assert!(lines.mark_free(&mut free[1..]).is_err());
    }
}
