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

use std::ops::Range;

use rayon::prelude::*;

use super::mesh::TriangleMesh;
use super::occupancy::Occupancy;
use super::simd::has_avx2;
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
    /// The depth map is too large for the `f32` projection (pixel coordinates must stay below 2^23,
    /// pixel indices below 2^31).
    #[error("a {width} x {height} depth map is too large to fuse")]
    ImageTooLarge {
        /// Camera width, pixels.
        width: u32,
        /// Camera height, pixels.
        height: u32,
    },
}

/// What one integration did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IntegrateStats {
    /// Voxels updated by the view (in front of the surface or within the truncation band).
    pub updated: u64,
    /// Voxels within the truncation band of a measured surface.
    pub near_surface: u64,
    /// Bricks of 8³ voxels (fewer at the grid's far faces) left alone without projecting a voxel:
    /// outside the image, behind the camera, or hidden more than the truncation behind the surface.
    pub bricks_skipped: u64,
    /// Bricks of 8³ voxels given the free-space sample without projecting a voxel.
    pub bricks_free: u64,
}

/// A TSDF over an object-frame voxel grid: per voxel a value in [-1, 1] (signed distance over the
/// truncation distance, positive outside) and a weight (0 = never updated).
///
/// Storage follows the surface: the grid is cut into bricks of `BRICK`³ voxels, and only a brick some
/// view updated voxel by voxel holds its voxels' values and weights. Every other brick is described by
/// its count of free-space samples alone (its voxels all have value 1 and that many samples' weight, or
/// none), so a view that settles a brick as a whole writes one counter, and memory grows with the
/// bricks near the measured surface, not with the volume.
#[derive(Debug, Clone)]
pub struct Tsdf {
    grid: VoxelGrid,
    params: FusionParams,
    /// Per slab of `BRICK` slices of constant `z`, the voxels of its bricks that hold them.
    slabs: Vec<SlabStore>,
    /// Per brick of `BRICK`³ voxels (x fastest), free-space samples given to the whole brick and not
    /// yet folded into its voxels: they are folded in, one by one with the same arithmetic, before the
    /// brick is next updated voxel by voxel, and on the fly when a voxel is read.
    pending: Vec<u32>,
    views: usize,
}

/// The stored bricks of one slab.
#[derive(Debug, Clone, Default)]
struct SlabStore {
    /// Per brick of the slab (x fastest), its index in `values` and `weights`, or `NO_BRICK`.
    slot: Vec<u32>,
    /// Per stored brick, each voxel's value as of the brick's last settling, at
    /// `x + BRICK * (y + BRICK * z)` (brick-local; voxels past the grid's end unused).
    values: Vec<[f32; BRICK_VOXELS]>,
    /// The same for the weights.
    weights: Vec<[f32; BRICK_VOXELS]>,
}

impl SlabStore {
    /// Store brick `b`'s voxels, which had none stored.
    fn insert(&mut self, b: usize, values: &[f32; BRICK_VOXELS], weights: &[f32; BRICK_VOXELS]) {
        self.slot[b] = self.values.len() as u32;
        self.values.push(*values);
        self.weights.push(*weights);
    }

    /// Brick `b`'s stored values and weights, if it has them.
    fn brick_mut(&mut self, b: usize) -> Option<(&mut [f32; BRICK_VOXELS], &mut [f32; BRICK_VOXELS])> {
        let s = self.slot[b];
        (s != NO_BRICK).then(|| (&mut self.values[s as usize], &mut self.weights[s as usize]))
    }
}

/// A brick without stored voxels.
const NO_BRICK: u32 = u32::MAX;

/// Voxels of a brick.
const BRICK_VOXELS: usize = BRICK * BRICK * BRICK;

impl Tsdf {
    /// An empty field over `grid` (every voxel unobserved).
    pub fn new(grid: VoxelGrid, params: FusionParams) -> Result<Tsdf, DepthFusionError> {
        if !(params.truncation_m.is_finite() && params.truncation_m > 0.0) {
            return Err(DepthFusionError::Truncation { truncation_m: params.truncation_m });
        }
        if grid.is_empty() {
            return Err(DepthFusionError::EmptyGrid);
        }
        let [nbx, nby, nbz] = grid.dims.map(|d| d.div_ceil(BRICK));
        let slab = SlabStore { slot: vec![NO_BRICK; nbx * nby], ..SlabStore::default() };
        Ok(Tsdf { grid, params, slabs: vec![slab; nbz], pending: vec![0; nbx * nby * nbz], views: 0 })
    }

    /// The grid.
    pub fn grid(&self) -> &VoxelGrid {
        &self.grid
    }

    /// Depth maps fused so far.
    pub fn views(&self) -> usize {
        self.views
    }

    /// Bricks of `BRICK`³ voxels that store their voxels (some view updated them voxel by voxel), and
    /// all bricks of the grid.
    pub fn stored_bricks(&self) -> (usize, usize) {
        (self.slabs.iter().map(|s| s.values.len()).sum(), self.pending.len())
    }

    /// Bytes the field holds: the stored bricks' values and weights, and per brick its slot and its
    /// pending count.
    pub fn memory_bytes(&self) -> usize {
        let (stored, bricks) = self.stored_bricks();
        stored * BRICK_VOXELS * 2 * std::mem::size_of::<f32>() + bricks * 2 * std::mem::size_of::<u32>()
    }

    /// The fused value of voxel `(i, j, k)` (signed distance / truncation, positive outside) and its
    /// weight (0 = never updated).
    pub fn get(&self, i: usize, j: usize, k: usize) -> (f32, f32) {
        self.voxel(i, j, k)
    }

    /// Voxel `(i, j, k)`'s value and weight, with its brick's pending free-space samples folded in.
    #[inline]
    fn voxel(&self, i: usize, j: usize, k: usize) -> (f32, f32) {
        let [nbx, nby] = [0, 1].map(|a| self.grid.dims[a].div_ceil(BRICK));
        let b = i / BRICK + nbx * (j / BRICK);
        let pending = self.pending[b + nbx * nby * (k / BRICK)];
        let store = &self.slabs[k / BRICK];
        let (mut value, mut weight) = match store.slot[b] {
            NO_BRICK => (1.0, 0.0),
            s => {
                let at = i % BRICK + BRICK * (j % BRICK + BRICK * (k % BRICK));
                (store.values[s as usize][at], store.weights[s as usize][at])
            }
        };
        settle(&mut value, &mut weight, pending, self.params.max_weight.max(1.0));
        (value, weight)
    }

    /// Fuse one depth map: `depth_m` is row-major, `camera.width * camera.height` values, metres along
    /// the optical axis, 0 = no measurement, `NaN` = unknown (never carves, even with
    /// `missing_is_free`); `camera` is the depth camera in the grid's (object) frame, i.e. already
    /// turned with `for_turntable_angle`.
    ///
    /// The grid is cut into bricks of 8³ voxels. Without lens distortion each brick is first settled
    /// as a whole where that is exact: a brick every voxel of which would get no update (outside the
    /// image, behind the camera, or more than the truncation behind the measured surface everywhere it
    /// projects) is skipped, and a brick every voxel of which would get the free-space sample (every
    /// pixel it projects onto is empty or measures a surface more than the truncation behind it) only
    /// counts that sample as pending, without being projected or written; pending samples are folded
    /// into the brick's voxels, in order and with the same arithmetic, before the brick is next
    /// updated voxel by voxel, and on the fly when a voxel is read. The other bricks go through
    /// the per-voxel path: slabs of `BRICK` slices run in parallel; within a brick each row of voxels
    /// along `x` is done in three passes over small buffers: project (camera coordinates are affine in
    /// the voxel index, so a row is `start + i * step`: a few multiply-adds and one reciprocal per voxel
    /// in `f32`, vectorised), look the depth up (the one gather, scalar), and update value and weight
    /// without branches (vectorised). A brick gets stored voxels (see [`Tsdf`]) the first time this
    /// path updates one of them. The result is the same, bit for bit, as projecting every voxel.
    /// On x86-64 CPUs with AVX2 the same code runs compiled for 256-bit vectors (chosen at run time; the
    /// arithmetic, without fused multiply-adds, rounds the same).
    pub fn integrate(&mut self, camera: &CameraModel, depth_m: &[f32]) -> Result<IntegrateStats, DepthFusionError> {
        self.integrate_with(camera, depth_m, true)
    }

    /// [`Tsdf::integrate`], with the brick culling on or off (off: every voxel is projected).
    fn integrate_with(
        &mut self,
        camera: &CameraModel,
        depth_m: &[f32],
        cull: bool,
    ) -> Result<IntegrateStats, DepthFusionError> {
        let (w, h) = (camera.width, camera.height);
        if depth_m.len() != w as usize * h as usize {
            return Err(DepthFusionError::DepthSize { len: depth_m.len(), width: w, height: h });
        }
        if w.max(h) >= 1 << 23 || depth_m.len() > i32::MAX as usize {
            return Err(DepthFusionError::ImageTooLarge { width: w, height: h });
        }
        let grid = self.grid;
        let update = Update {
            trunc: self.params.truncation_m as f32,
            inv_trunc: (1.0 / self.params.truncation_m) as f32,
            max_weight: self.params.max_weight.max(1.0),
            missing_is_free: self.params.missing_is_free,
        };
        let distorted = camera.intrinsics.has_distortion();
        let culler = (cull && !distorted)
            .then(|| BrickCuller::new(camera, &grid, depth_m, self.params.truncation_m, self.params.missing_is_free));
        let slabs = SlabFusion {
            camera,
            grid,
            projection: RowProjection::new(camera, &grid),
            update,
            distorted,
            culler: culler.as_ref(),
            depth_m,
        };
        let avx2 = has_avx2();
        let [nx, ny, _] = grid.dims;
        let stats = self
            .slabs
            .par_iter_mut()
            .zip(self.pending.par_chunks_mut(nx.div_ceil(BRICK) * ny.div_ceil(BRICK)))
            .enumerate()
            .map_init(
                || (RowBuffers::new(nx), Box::new(([1.0; BRICK_VOXELS], [0.0; BRICK_VOXELS]))),
                |(buf, scratch), (kb, (store, pending))| {
                    let slab = Slab { kb, store, pending };
                    #[cfg(target_arch = "x86_64")]
                    if avx2 {
                        // SAFETY: the CPU supports AVX2 (checked at run time by `has_avx2`).
                        return unsafe { slabs.fuse_avx2(slab, buf, scratch) };
                    }
                    slabs.fuse(slab, buf, scratch)
                },
            )
            .reduce(IntegrateStats::default, |a, b| IntegrateStats {
                updated: a.updated + b.updated,
                near_surface: a.near_surface + b.near_surface,
                bricks_skipped: a.bricks_skipped + b.bricks_skipped,
                bricks_free: a.bricks_free + b.bricks_free,
            });
        self.views += 1;
        Ok(stats)
    }

    /// The fused solid: voxels with a negative value, and voxels never updated (hidden in every view).
    pub fn occupancy(&self) -> Occupancy {
        Occupancy::from_index_fn(self.grid, |i, j, k| {
            let (value, weight) = self.voxel(i, j, k);
            weight == 0.0 || value < 0.0
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
            let (value, weight) = self.voxel(base[0] + (n & 1), base[1] + ((n >> 1) & 1), base[2] + ((n >> 2) & 1));
            if weight == 0.0 {
                return None;
            }
            *cv = f64::from(value);
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

/// Edge of a brick, voxels: the block the culling settles at once, and the depth of the slabs that run
/// in parallel.
const BRICK: usize = 8;
/// Edge of a depth tile, pixels: the block of the per-view depth summary the culling reads.
const TILE: usize = 8;
/// A brick whose projection spans more tiles than this is done voxel by voxel (its summary would cost
/// more than it saves).
const MAX_TILES: usize = 1024;

/// What one view does to a whole brick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Brick {
    /// No voxel is updated.
    Skip,
    /// Every voxel gets the free-space sample (1).
    Free,
    /// Anything else: voxel by voxel.
    Mixed,
}

/// One slab of `BRICK` slices of constant `z` (fewer in the last): its stored bricks and pending
/// free-space samples.
#[derive(Debug)]
struct Slab<'a> {
    /// The slab's index: slices `kb * BRICK ..`.
    kb: usize,
    store: &'a mut SlabStore,
    /// Per brick of the slab, `x` fastest.
    pending: &'a mut [u32],
}

/// One view's fusion of a slab of `BRICK` slices of constant `z`: what every slab shares.
#[derive(Debug, Clone, Copy)]
struct SlabFusion<'a> {
    /// The depth camera in the grid's frame.
    camera: &'a CameraModel,
    grid: VoxelGrid,
    projection: RowProjection,
    update: Update,
    /// Whether the camera has lens distortion (then nothing is culled).
    distorted: bool,
    /// The view's brick culling; `None` projects every voxel.
    culler: Option<&'a BrickCuller>,
    /// The depth map, metres, row-major.
    depth_m: &'a [f32],
}

impl SlabFusion<'_> {
    /// [`SlabFusion::fuse`] compiled for 256-bit vectors (see [`super::simd`]). A function of its
    /// own rather than [`super::simd::run_simd`]'s closure: through the closure the voxel loop was
    /// left unvectorised (fusion took twice as long).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn fuse_avx2(&self, slab: Slab<'_>, buf: &mut RowBuffers, scratch: &mut Scratch) -> IntegrateStats {
        self.fuse(slab, buf, scratch)
    }

    /// Fuse one slab. A brick given the free-space sample only counts it as pending; a brick done
    /// voxel by voxel gets its voxels stored if it had none, and first folds in what it has pending.
    #[inline(always)]
    fn fuse(&self, slab: Slab<'_>, buf: &mut RowBuffers, scratch: &mut Scratch) -> IntegrateStats {
        let Slab { kb, store, pending } = slab;
        let [nx, ny, nz] = self.grid.dims;
        let (nbx, nby) = (nx.div_ceil(BRICK), ny.div_ceil(BRICK));
        let depth = (nz - kb * BRICK).min(BRICK);
        let mut stats = IntegrateStats::default();
        for jb in 0..nby {
            for ib in 0..nbx {
                let brick = match self.culler {
                    Some(culler) => culler.classify([ib, jb, kb]),
                    None => Brick::Mixed,
                };
                let b = ib + nbx * jb;
                let (i0, i1) = (ib * BRICK, ((ib + 1) * BRICK).min(nx));
                let (j0, j1) = (jb * BRICK, ((jb + 1) * BRICK).min(ny));
                match brick {
                    Brick::Skip => stats.bricks_skipped += 1,
                    Brick::Free => {
                        stats.bricks_free += 1;
                        stats.updated += ((i1 - i0) * (j1 - j0) * depth) as u64;
                        // Fold in what is pending before the count would overflow.
                        if pending[b] == u32::MAX {
                            if store.slot[b] == NO_BRICK {
                                store.insert(b, &[1.0; BRICK_VOXELS], &[0.0; BRICK_VOXELS]);
                            }
                            let (values, weights) = store.brick_mut(b).expect("stored");
                            settle_run(values, weights, pending[b], self.update.max_weight);
                            pending[b] = 0;
                        }
                        pending[b] += 1;
                    }
                    Brick::Mixed => {
                        // A brick without stored voxels is worked in scratch and stored only if a
                        // voxel of it was updated (a brick whose rectangle only grazes the
                        // silhouette often has none).
                        let stored = store.slot[b] != NO_BRICK;
                        let (values, weights) = match store.brick_mut(b) {
                            Some(brick) => brick,
                            None => {
                                scratch.0.fill(1.0);
                                scratch.1.fill(0.0);
                                (&mut scratch.0, &mut scratch.1)
                            }
                        };
                        if pending[b] > 0 {
                            settle_run(values, weights, pending[b], self.update.max_weight);
                        }
                        let mut updated = 0;
                        for dk in 0..depth {
                            for j in j0..j1 {
                                let at = BRICK * ((j - j0) + BRICK * dk);
                                let n = i1 - i0;
                                let (v, w) = (&mut values[at..at + n], &mut weights[at..at + n]);
                                let (u, near) = self.voxels(j, kb * BRICK + dk, i0..i1, v, w, buf);
                                updated += u;
                                stats.near_surface += u64::from(near);
                            }
                        }
                        stats.updated += u64::from(updated);
                        if stored {
                            pending[b] = 0;
                        } else if updated > 0 {
                            store.insert(b, &scratch.0, &scratch.1);
                            pending[b] = 0;
                        }
                    }
                }
            }
        }
        stats
    }

    /// Voxels `range` of row `(j, k)`, whose values and weights are given, one by one: project, look
    /// the depth up, update. Returns the voxels updated and those within the truncation band.
    #[inline(always)]
    fn voxels(
        &self,
        j: usize,
        k: usize,
        range: Range<usize>,
        values: &mut [f32],
        weights: &mut [f32],
        buf: &mut RowBuffers,
    ) -> (u32, u32) {
        // From the row's first centre whatever part of the row is done, so that every voxel projects
        // the same way, culled or not.
        let start = self.camera.pose.apply(&self.grid.centre(0, j, k)).map(|c| c as f32);
        let start = [start.x, start.y, start.z];
        let ramp = &buf.ramp[range.clone()];
        let (pixel, z, depth) = (&mut buf.pixel[range.clone()], &mut buf.z[range.clone()], &mut buf.depth[range]);
        let inside = if self.distorted {
            self.projection.project::<true>(start, ramp, pixel, z)
        } else {
            self.projection.project::<false>(start, ramp, pixel, z)
        };
        if !inside {
            return (0, 0);
        }
        for (d, &p) in depth.iter_mut().zip(pixel.iter()) {
            // -1 (outside) becomes usize::MAX: no pixel.
            *d = self.depth_m.get(p as usize).copied().unwrap_or(f32::NAN);
        }
        self.update.row(values, weights, depth, z)
    }
}

/// One view's means to settle whole bricks without projecting their voxels, for a camera without lens
/// distortion (a box in front of a pinhole camera projects inside the rectangle of its corners'
/// projections).
///
/// The depth map is summarised per tile of `TILE` x `TILE` pixels by the smallest and largest "key"
/// of its pixels: the measured depth (metres), `+inf` for an empty pixel that carves (depth 0 with
/// `missing_is_free`), `-inf` for a pixel that updates nothing (unknown, invalid, or empty without
/// `missing_is_free`). A voxel at camera depth `z` on a pixel whose key is at least `z + truncation`
/// gets the free-space sample; on a pixel whose key is below `z - truncation` it gets no update. A
/// brick spans camera depths `[z_min, z_max]` and a rectangle of pixels (widened by the `f32`
/// projection's rounding): it is skipped when the rectangle misses the image or every tile it touches
/// has its largest key below `z_min - truncation`, and gets the free-space sample when the rectangle
/// lies in the image and every tile has its smallest key at least `z_max + truncation`. Both bounds
/// are widened by the `f32` rounding of the per-voxel path, so the outcome is the one that path
/// gives, voxel for voxel.
#[derive(Debug)]
struct BrickCuller {
    camera: CameraModel,
    /// Voxels along x, y, z.
    dims: [usize; 3],
    /// Camera coordinates of voxel `(0, 0, 0)`'s centre, metres.
    origin: [f64; 3],
    /// Camera-frame step from one voxel to the next along the grid's x, y and z, metres.
    axes: [[f64; 3]; 3],
    /// Truncation distance, metres.
    trunc_m: f64,
    /// Bound on the error of the per-voxel path's `f32` camera coordinates (and on the rounding of
    /// the truncation), metres, with a wide safety factor.
    pad_m: f64,
    /// Largest absolute camera coordinate of a voxel centre, metres.
    scale_m: f64,
    tiles_x: usize,
    key_min: Vec<f32>,
    key_max: Vec<f32>,
}

impl BrickCuller {
    fn new(
        camera: &CameraModel,
        grid: &VoxelGrid,
        depth_m: &[f32],
        trunc_m: f64,
        missing_is_free: bool,
    ) -> BrickCuller {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let (tiles_x, tiles_y) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let mut key_min = vec![f32::INFINITY; tiles_x * tiles_y];
        let mut key_max = vec![f32::NEG_INFINITY; tiles_x * tiles_y];
        // Per band of tile rows: each column's extremes down the band (vectorised), then per tile.
        key_min.par_chunks_mut(tiles_x).zip(key_max.par_chunks_mut(tiles_x)).enumerate().for_each_init(
            || (vec![0.0f32; w], vec![0.0f32; w]),
            |(column_min, column_max), (ty, (mins, maxs))| {
                column_min.fill(f32::INFINITY);
                column_max.fill(f32::NEG_INFINITY);
                for row in depth_m.chunks_exact(w).skip(ty * TILE).take(TILE) {
                    for ((lo, hi), &d) in column_min.iter_mut().zip(column_max.iter_mut()).zip(row) {
                        let key = pixel_key(d, missing_is_free);
                        *lo = if key < *lo { key } else { *lo };
                        *hi = if key > *hi { key } else { *hi };
                    }
                }
                for ((lo, hi), (column_min, column_max)) in
                    mins.iter_mut().zip(maxs.iter_mut()).zip(column_min.chunks(TILE).zip(column_max.chunks(TILE)))
                {
                    *lo = column_min.iter().fold(f32::INFINITY, |a, &b| if b < a { b } else { a });
                    *hi = column_max.iter().fold(f32::NEG_INFINITY, |a, &b| if b > a { b } else { a });
                }
            },
        );
        // Camera coordinates are affine in the voxel index: their extremes are at the grid's corners.
        let [nx, ny, nz] = grid.dims;
        let scale_m = (0..8)
            .map(|n| {
                let c = grid.centre(
                    if n & 1 == 0 { 0 } else { nx - 1 },
                    if n & 2 == 0 { 0 } else { ny - 1 },
                    if n & 4 == 0 { 0 } else { nz - 1 },
                );
                camera.pose.apply(&c).amax()
            })
            .fold(0.0, f64::max);
        let origin = camera.pose.apply(&grid.centre(0, 0, 0));
        let axes = [0, 1, 2].map(|a| {
            let step = camera.pose.rotation.column(a) * grid.voxel_size;
            [step.x, step.y, step.z]
        });
        BrickCuller {
            camera: *camera,
            dims: grid.dims,
            origin: [origin.x, origin.y, origin.z],
            axes,
            trunc_m,
            pad_m: 1e-5 * (scale_m + trunc_m),
            scale_m,
            tiles_x,
            key_min,
            key_max,
        }
    }

    /// What the view does to brick `b` (voxels `b * BRICK ..` along each axis).
    fn classify(&self, b: [usize; 3]) -> Brick {
        // Camera coordinates of the brick's corner voxel centres: affine in the voxel index (plain
        // loops over fixed-size arrays, which the compiler unrolls).
        let mut ends = [[[0.0f64; 3]; 2]; 3];
        for (a, [first_end, last_end]) in ends.iter_mut().enumerate() {
            let first = (b[a] * BRICK) as f64;
            let last = (((b[a] + 1) * BRICK).min(self.dims[a]) - 1) as f64;
            for ((f, l), &step) in first_end.iter_mut().zip(last_end.iter_mut()).zip(&self.axes[a]) {
                *f = first * step;
                *l = last * step;
            }
        }
        let mut corners = [[0.0f64; 3]; 8];
        let (mut z_min, mut z_max) = (f64::INFINITY, f64::NEG_INFINITY);
        for (n, corner) in corners.iter_mut().enumerate() {
            let (ex, ey, ez) = (&ends[0][n & 1], &ends[1][(n >> 1) & 1], &ends[2][(n >> 2) & 1]);
            for (c, out) in corner.iter_mut().enumerate() {
                *out = self.origin[c] + ex[c] + ey[c] + ez[c];
            }
            z_min = z_min.min(corner[2]);
            z_max = z_max.max(corner[2]);
        }
        if z_max < -self.pad_m {
            return Brick::Skip; // behind the camera
        }
        // Across the camera plane, too close for the pixel bound below, or not finite.
        if !(z_min > 1e-3 * self.scale_m && z_max.is_finite()) {
            return Brick::Mixed;
        }
        let i = &self.camera.intrinsics;
        let (mut u_min, mut u_max, mut v_min, mut v_max) =
            (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        let mut slope = 0.0f64;
        for &[x, y, z] in &corners {
            let r = 1.0 / z;
            let (x, y) = (x * r, y * r);
            let (u, v) = (i.fx * x + i.skew * y + i.cx, i.fy * y + i.cy);
            u_min = if u < u_min { u } else { u_min };
            u_max = if u > u_max { u } else { u_max };
            v_min = if v < v_min { v } else { v_min };
            v_max = if v > v_max { v } else { v_max };
            let s = x.abs() + y.abs();
            slope = if s > slope { s } else { slope };
        }
        // Pixel error of the f32 projection: coordinates off by `pad_m`, divided by `z`.
        let pad_px = 0.01 + (i.fx.abs() + i.fy.abs() + i.skew.abs()) * self.pad_m / z_min * (1.0 + slope);
        let (u0, u1, v0, v1) = (u_min - pad_px, u_max + pad_px, v_min - pad_px, v_max + pad_px);
        let (width, height) = (f64::from(self.camera.width), f64::from(self.camera.height));
        if !(u0.is_finite() && u1.is_finite() && v0.is_finite() && v1.is_finite()) {
            return Brick::Mixed;
        }
        if u1 < 0.0 || v1 < 0.0 || u0 >= width || v0 >= height {
            return Brick::Skip; // outside the image
        }
        let in_image = u0 >= 0.0 && v0 >= 0.0 && u1 < width && v1 < height;
        // The tiles of the pixels the brick can land on (floor of non-negative values).
        let (tx0, tx1) = (u0.max(0.0) as usize / TILE, u1.min(width - 1.0) as usize / TILE);
        let (ty0, ty1) = (v0.max(0.0) as usize / TILE, v1.min(height - 1.0) as usize / TILE);
        if (tx1 - tx0 + 1) * (ty1 - ty0 + 1) > MAX_TILES {
            return Brick::Mixed;
        }
        let (mut key_min, mut key_max) = (f32::INFINITY, f32::NEG_INFINITY);
        for ty in ty0..=ty1 {
            let at = ty * self.tiles_x;
            for (lo, hi) in self.key_min[at + tx0..=at + tx1].iter().zip(&self.key_max[at + tx0..=at + tx1]) {
                key_min = key_min.min(*lo);
                key_max = key_max.max(*hi);
            }
        }
        let band = self.trunc_m + self.pad_m;
        if f64::from(key_max) < z_min - band {
            Brick::Skip // hidden behind the surface wherever it lands
        } else if in_image && f64::from(key_min) >= z_max + band {
            Brick::Free
        } else {
            Brick::Mixed
        }
    }
}

/// Scratch for one row of voxels along `x`, reused over a slab.
#[derive(Debug)]
struct RowBuffers {
    /// 0, 1, 2, ...: the voxel index as `f32`.
    ramp: Vec<f32>,
    /// Depth-map index of each voxel's pixel, -1 when behind the camera or outside the image.
    pixel: Vec<i32>,
    /// Camera `z` of each voxel centre, metres.
    z: Vec<f32>,
    /// The depth read at each voxel's pixel (`NaN` for none).
    depth: Vec<f32>,
}

/// Values and weights of a brick without stored voxels, while a view updates it.
type Scratch = ([f32; BRICK_VOXELS], [f32; BRICK_VOXELS]);

impl RowBuffers {
    fn new(n: usize) -> RowBuffers {
        RowBuffers { ramp: (0..n).map(|i| i as f32).collect(), pixel: vec![0; n], z: vec![0.0; n], depth: vec![0.0; n] }
    }
}

/// One view's projection of rows of voxel centres, in `f32`: camera coordinates are affine in the
/// voxel index, so voxel `i` of a row is `start + i * step`.
#[derive(Debug, Clone, Copy)]
struct RowProjection {
    /// Camera-frame step from one voxel to the next along `x`, metres.
    step: [f32; 3],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    skew: f32,
    k1: f32,
    k2: f32,
    k3: f32,
    p1: f32,
    p2: f32,
    width: f32,
    height: f32,
    row_pixels: u32,
}

impl RowProjection {
    fn new(camera: &CameraModel, grid: &VoxelGrid) -> RowProjection {
        let step = camera.pose.rotation.column(0) * grid.voxel_size;
        let i = &camera.intrinsics;
        RowProjection {
            step: [step.x as f32, step.y as f32, step.z as f32],
            fx: i.fx as f32,
            fy: i.fy as f32,
            cx: i.cx as f32,
            cy: i.cy as f32,
            skew: i.skew as f32,
            k1: i.k1 as f32,
            k2: i.k2 as f32,
            k3: i.k3 as f32,
            p1: i.p1 as f32,
            p2: i.p2 as f32,
            width: camera.width as f32,
            height: camera.height as f32,
            row_pixels: camera.width,
        }
    }

    /// Camera `z` and depth-map index (-1: behind the camera or outside the image) of each voxel of
    /// the row whose first centre is at `start` (camera frame); whether any voxel lands in the image.
    /// `DISTORT` applies the lens distortion ([`crate::geometry::Intrinsics::distort`]).
    #[inline(always)]
    fn project<const DISTORT: bool>(&self, start: [f32; 3], ramp: &[f32], pixel: &mut [i32], z: &mut [f32]) -> bool {
        let mut inside = 0u32;
        for ((&t, p), zo) in ramp.iter().zip(pixel.iter_mut()).zip(z.iter_mut()) {
            let xc = start[0] + self.step[0] * t;
            let yc = start[1] + self.step[1] * t;
            let zc = start[2] + self.step[2] * t;
            let r = 1.0 / zc;
            let (mut x, mut y) = (xc * r, yc * r);
            if DISTORT {
                let r2 = x * x + y * y;
                let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
                let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
                let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
                (x, y) = (xd, yd);
            }
            let u = self.fx * x + self.skew * y + self.cx;
            let v = self.fy * y + self.cy;
            let ok = (zc > 0.0) & (u >= 0.0) & (v >= 0.0) & (u < self.width) & (v < self.height);
            // Wrapping keeps the discarded coordinates (NaN, huge) from overflowing.
            let index = floor_u32(v).wrapping_mul(self.row_pixels).wrapping_add(floor_u32(u));
            *p = if ok { index as i32 } else { -1 };
            *zo = zc;
            inside += u32::from(ok);
        }
        inside > 0
    }
}

/// The per-voxel update of one view.
#[derive(Debug, Clone, Copy)]
struct Update {
    trunc: f32,
    inv_trunc: f32,
    max_weight: f32,
    missing_is_free: bool,
}

impl Update {
    /// Fold one row's depth samples (`NaN` = no pixel) at camera depths `z` into its values and
    /// weights, without branches (indexed loop over equal-length slices and bit-mask selects, which
    /// the compiler vectorises); returns the voxels updated and those within the truncation band.
    #[inline(always)]
    fn row(&self, values: &mut [f32], weights: &mut [f32], depth: &[f32], z: &[f32]) -> (u32, u32) {
        let (mut updated, mut near) = (0u32, 0u32);
        let n = values.len().min(weights.len()).min(depth.len()).min(z.len());
        let (values, weights, depth, z) = (&mut values[..n], &mut weights[..n], &depth[..n], &z[..n]);
        for i in 0..n {
            let d = depth[i];
            let measured = (d > 0.0) & (d < f32::INFINITY);
            let sdf = d - z[i];
            // Hidden more than the truncation behind the surface: no update.
            let hit = measured & (sdf >= -self.trunc);
            let fuse = hit | (self.missing_is_free & (d == 0.0));
            let sample = if measured { (sdf * self.inv_trunc).clamp(-1.0, 1.0) } else { 1.0 };
            let (v, wt) = (values[i], weights[i]);
            let fused = (v * wt + sample) / (wt + 1.0);
            // Select by bit mask (all ones where the voxel keeps its old state), which vectorises.
            let keep = u32::from(fuse).wrapping_sub(1);
            values[i] = f32::from_bits((fused.to_bits() & !keep) | (v.to_bits() & keep));
            weights[i] = f32::from_bits(((wt + 1.0).min(self.max_weight).to_bits() & !keep) | (wt.to_bits() & keep));
            updated += u32::from(fuse);
            near += u32::from(hit & (sdf < self.trunc));
        }
        (updated, near)
    }
}

/// Fold `count` free-space samples into one voxel's `value` and `weight`: what [`Update::row`] does,
/// `count` times, to a voxel on an empty pixel or in front of the surface by at least the truncation,
/// with the same arithmetic. A value of exactly 1 stays 1 (`(w + 1) / (w + 1)`), and weights are whole
/// numbers or the cap, exact in `f32` below 2^24, so that common case is done in one step.
#[inline(always)]
fn settle(value: &mut f32, weight: &mut f32, count: u32, max_weight: f32) {
    if count == 0 {
        return;
    }
    if *value == 1.0 && f64::from(*weight) + f64::from(count) <= 16_777_216.0 {
        *weight = (*weight + count as f32).min(max_weight);
        return;
    }
    for _ in 0..count {
        let (v, wt) = (*value, *weight);
        *value = (v * wt + 1.0) / (wt + 1.0);
        *weight = (wt + 1.0).min(max_weight);
    }
}

/// [`settle`] over a run of voxels; when every value is 1 and every weight small enough (the common
/// case, far from any surface), only the weights change, in one vectorised pass.
#[inline(always)]
fn settle_run(values: &mut [f32], weights: &mut [f32], count: u32, max_weight: f32) {
    const EXACT: u32 = 1 << 24;
    if count <= EXACT {
        let limit = (EXACT - count) as f32;
        let ones = values.iter().fold(true, |all, &v| all & (v == 1.0));
        let small = weights.iter().fold(true, |all, &w| all & (w <= limit));
        if ones && small {
            let count = count as f32;
            for w in weights.iter_mut() {
                *w = (*w + count).min(max_weight);
            }
            return;
        }
    }
    for (v, w) in values.iter_mut().zip(weights.iter_mut()) {
        settle(v, w, count, max_weight);
    }
}

/// A pixel's key for [`BrickCuller`]: its measured depth (metres), `+inf` for an empty pixel that
/// carves, `-inf` for a pixel that updates nothing; without branches.
#[inline(always)]
fn pixel_key(d: f32, missing_is_free: bool) -> f32 {
    let measured = (d > 0.0) & (d < f32::INFINITY);
    let other = if missing_is_free & (d == 0.0) { f32::INFINITY } else { f32::NEG_INFINITY };
    if measured {
        d
    } else {
        other
    }
}

/// `floor(x)` for `0 <= x < 2^23` without a float-to-integer conversion (which SSE2 cannot vectorise
/// with Rust's saturating semantics): adding 2^23 rounds `x` to an integer held in the mantissa.
/// Other inputs give unspecified values.
#[inline(always)]
fn floor_u32(x: f32) -> u32 {
    const MAGIC: f32 = 8_388_608.0;
    let big = x + MAGIC;
    let rounded = big.to_bits().wrapping_sub(MAGIC.to_bits());
    rounded.wrapping_sub(u32::from(big - MAGIC > x))
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

    /// Only the bricks some view updated voxel by voxel store voxels; the rest cost two counters
    /// each. With dropouts ignored (a real sensor's) the stored bricks are those near the surface and
    /// those a view cannot settle whole at its tiles' resolution; carving the empty background too
    /// updates the silhouette's cone of bricks in front of and around the object in every view, so
    /// more are stored, but not all.
    #[test]
    fn storage_follows_the_surface() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.08; 3], max: [0.08; 3] }, 96);
        let dense = grid.len() * 2 * std::mem::size_of::<f32>();
        for (missing_is_free, at_most) in [(false, 0.4), (true, 0.9)] {
            let mut tsdf = Tsdf::new(grid, FusionParams { missing_is_free, ..params() }).expect("tsdf");
            assert_eq!(tsdf.stored_bricks(), (0, 12 * 12 * 12));
            for i in 0..8 {
                let cam = camera(45.0 * i as f64);
                tsdf.integrate(&cam, &sphere_depth(&cam)).expect("integrate");
            }
            let (stored, bricks) = tsdf.stored_bricks();
            assert!(stored > 50 && (stored as f64) < at_most * bricks as f64, "{stored} of {bricks} bricks stored");
            let bytes = tsdf.memory_bytes() as f64;
            assert!(bytes < at_most * dense as f64, "{bytes} bytes, dense {dense}");
        }
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
        let mut mesh =
            extract_surface(&occ, &MeshParams { smooth_radius: 0, relax_iterations: 0, remove_handles: false })
                .expect("mesh");
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

    /// The per-voxel definition of [`Tsdf::integrate`], in `f64`: every voxel centre projected on its
    /// own. It also marks the voxels whose outcome in some view rests on a tie that the fast path's
    /// `f32` may break the other way (a projection within `EDGE_PX` of a pixel edge, a signed distance
    /// within `EDGE_M` of minus the truncation); the comparison skips those.
    struct Reference {
        grid: VoxelGrid,
        params: FusionParams,
        value: Vec<f64>,
        weight: Vec<f64>,
        tied: Vec<bool>,
    }

    const EDGE_PX: f64 = 5e-4;
    const EDGE_M: f64 = 1e-6;

    impl Reference {
        fn new(grid: VoxelGrid, params: FusionParams) -> Reference {
            let n = grid.len();
            Reference { grid, params, value: vec![1.0; n], weight: vec![0.0; n], tied: vec![false; n] }
        }

        /// The view's stats, and how many voxels it tied.
        fn integrate(&mut self, cam: &CameraModel, depth: &[f32]) -> (IntegrateStats, u64) {
            let g = self.grid;
            let trunc = self.params.truncation_m;
            let max_weight = f64::from(self.params.max_weight.max(1.0));
            let (mut stats, mut tied) = (IntegrateStats::default(), 0);
            for k in 0..g.dims[2] {
                for j in 0..g.dims[1] {
                    for i in 0..g.dims[0] {
                        let idx = g.index(i, j, k);
                        let c = cam.pose.apply(&g.centre(i, j, k));
                        if c.z <= 0.0 {
                            continue;
                        }
                        let q = cam.intrinsics.normalised_to_pixel(c.x / c.z, c.y / c.z);
                        let on_edge = |x: f64| (x - x.round()).abs() < EDGE_PX;
                        if on_edge(q.x) || on_edge(q.y) {
                            self.tied[idx] = true;
                            tied += 1;
                        }
                        if !(q.x >= 0.0 && q.y >= 0.0 && q.x < f64::from(cam.width) && q.y < f64::from(cam.height)) {
                            continue;
                        }
                        let d = depth[q.y as usize * cam.width as usize + q.x as usize];
                        let sample = if d > 0.0 && d.is_finite() {
                            let sdf = f64::from(d) - c.z;
                            if (sdf + trunc).abs() < EDGE_M {
                                self.tied[idx] = true;
                                tied += 1;
                            }
                            if sdf < -trunc {
                                continue;
                            }
                            if sdf < trunc {
                                stats.near_surface += 1;
                            }
                            (sdf / trunc).clamp(-1.0, 1.0)
                        } else if self.params.missing_is_free && d == 0.0 {
                            1.0
                        } else {
                            continue;
                        };
                        let wt = self.weight[idx];
                        self.value[idx] = (self.value[idx] * wt + sample) / (wt + 1.0);
                        self.weight[idx] = (wt + 1.0).min(max_weight);
                        stats.updated += 1;
                    }
                }
            }
            (stats, tied)
        }
    }

    /// Fuses the views into a [`Tsdf`] and into the [`Reference`] and compares them voxel by voxel;
    /// returns the voxels compared.
    fn matches_reference(grid: VoxelGrid, params: FusionParams, views: &[(CameraModel, Vec<f32>)]) -> usize {
        let mut fast = Tsdf::new(grid, params).expect("tsdf");
        let mut reference = Reference::new(grid, params);
        for (n, (cam, depth)) in views.iter().enumerate() {
            let got = fast.integrate(cam, depth).expect("integrate");
            let (want, tied) = reference.integrate(cam, depth);
            assert!(want.updated > 0, "view {n} updates nothing: a useless case");
            for (a, b) in [(got.updated, want.updated), (got.near_surface, want.near_surface)] {
                assert!(a.abs_diff(b) <= tied, "view {n}: {got:?} vs {want:?} ({tied} tied)");
            }
        }
        let mut compared = 0;
        for k in 0..grid.dims[2] {
            for j in 0..grid.dims[1] {
                for i in 0..grid.dims[0] {
                    let idx = grid.index(i, j, k);
                    if reference.tied[idx] {
                        continue;
                    }
                    let (value, weight) = fast.get(i, j, k);
                    let (want_value, want_weight) = (reference.value[idx], reference.weight[idx]);
                    assert_eq!(f64::from(weight), want_weight, "weight of {i} {j} {k}");
                    assert!(
                        (f64::from(value) - want_value).abs() < 1e-4,
                        "value of {i} {j} {k}: {value} vs {want_value}"
                    );
                    compared += 1;
                }
            }
        }
        compared
    }

    #[test]
    fn fast_integrate_matches_the_per_voxel_definition() {
        // A box whose sides differ, so x, y and z cannot be mixed up unnoticed.
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.04, -0.036, -0.03], max: [0.04, 0.04, 0.034] }, 40);
        assert!(grid.dims[0] != grid.dims[1] && grid.dims[1] != grid.dims[2], "{:?}", grid.dims);
        let params = FusionParams { truncation_m: 3.0 * grid.voxel_size, max_weight: 5.0, missing_is_free: true };

        // A ring of views around the sphere, empty background carving.
        let ring: Vec<_> = (0..8)
            .map(|i| {
                let cam = camera(45.0 * i as f64 + 10.0);
                let depth = sphere_depth(&cam);
                (cam, depth)
            })
            .collect();
        let n = matches_reference(grid, params, &ring);
        assert!(n > grid.len() * 9 / 10, "{n} of {} voxels compared", grid.len());

        // Lens distortion and skew, a camera so close that the grid overflows the image and part of
        // it lies behind the camera, dropouts (0, ignored here), unknown (NaN) and invalid pixels.
        let mut close = CameraModel {
            intrinsics: Intrinsics {
                skew: 0.7,
                ..Intrinsics::new(300.0, 290.0, 82.0, 57.0).with_distortion([-0.21, 0.05, 0.001, -0.002, 0.01])
            },
            pose: Pose::look_at(Vector3::new(0.01, -0.034, 0.012), Vector3::zeros(), Vector3::z()),
            ..camera(0.0)
        };
        let mut views = Vec::new();
        for angle in [0.0, 20.0, 200.0] {
            close = close.for_turntable_angle(angle);
            let mut depth = sphere_depth(&close);
            for (n, d) in depth.iter_mut().enumerate() {
                match n % 97 {
                    0 => *d = f32::NAN,
                    1 => *d = -0.1,
                    2 => *d = f32::INFINITY,
                    3 => *d = 0.0,
                    _ => {}
                }
            }
            views.push((close, depth));
        }
        views.push(ring[3].clone());
        for missing_is_free in [false, true] {
            let n = matches_reference(grid, FusionParams { missing_is_free, ..params }, &views);
            assert!(n > grid.len() * 8 / 10, "{n} of {} voxels compared", grid.len());
        }
    }

    /// Fuses the views with the brick culling and without it, and requires the same stats and the same
    /// field, bit for bit, after every view; returns the bricks skipped and the bricks given the
    /// free-space sample over all views (so a caller can tell the culling acted).
    fn culling_matches_unculled(
        grid: VoxelGrid,
        params: FusionParams,
        views: &[(CameraModel, Vec<f32>)],
    ) -> (u64, u64) {
        let mut culled = Tsdf::new(grid, params).expect("tsdf");
        let mut full = Tsdf::new(grid, params).expect("tsdf");
        let (mut skipped, mut free) = (0, 0);
        for (n, (cam, depth)) in views.iter().enumerate() {
            let got = culled.integrate(cam, depth).expect("integrate");
            let want = full.integrate_with(cam, depth, false).expect("integrate");
            assert_eq!((want.bricks_skipped, want.bricks_free), (0, 0));
            assert_eq!((got.updated, got.near_surface), (want.updated, want.near_surface), "view {n}");
            skipped += got.bricks_skipped;
            free += got.bricks_free;
            for k in 0..grid.dims[2] {
                for j in 0..grid.dims[1] {
                    for i in 0..grid.dims[0] {
                        let (a, b) = (culled.get(i, j, k), full.get(i, j, k));
                        assert!(
                            a.0.to_bits() == b.0.to_bits() && a.1.to_bits() == b.1.to_bits(),
                            "view {n}, voxel {i} {j} {k}: culled {a:?}, every voxel {b:?}"
                        );
                    }
                }
            }
        }
        // The readers fold pending free-space samples in the same way.
        let (a, b) = (culled.occupancy(), full.occupancy());
        assert_eq!(a.count(), b.count());
        for k in 0..grid.dims[2] {
            for j in 0..grid.dims[1] {
                for i in 0..grid.dims[0] {
                    assert_eq!(a.get(i, j, k), b.get(i, j, k), "occupancy of {i} {j} {k}");
                }
            }
        }
        let mut sampled = 0;
        for n in 0..2000 {
            // Points spiralling over a sphere a little larger than the scenes' (where the field is known).
            let (t, phi) = (n as f64 / 2000.0, n as f64 * 2.399_963);
            let (z, r) = (1.0 - 2.0 * t, (1.0 - (1.0 - 2.0 * t).powi(2)).sqrt());
            let p = [r * phi.cos(), r * phi.sin(), z].map(|c| c * (R + 0.002));
            let got = culled.sample(&p);
            assert_eq!(got, full.sample(&p), "sample at {p:?}");
            sampled += usize::from(got.is_some());
        }
        assert!(sampled > 100, "{sampled} points sampled");
        (skipped, free)
    }

    #[test]
    fn culling_whole_bricks_changes_no_voxel() {
        // Dimensions that are not multiples of the brick, so partial bricks occur on three faces.
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.04, -0.036, -0.03], max: [0.04, 0.04, 0.034] }, 44);
        assert!(grid.dims.iter().any(|&d| d % BRICK != 0), "{:?}", grid.dims);
        let params = FusionParams { truncation_m: 3.0 * grid.voxel_size, max_weight: 4.0, missing_is_free: true };

        // The sphere on an empty background (carving) from a ring of views.
        let ring: Vec<_> = (0..6)
            .map(|i| {
                let cam = camera(60.0 * i as f64 + 5.0);
                let depth = sphere_depth(&cam);
                (cam, depth)
            })
            .collect();
        // The sphere before a wall that cuts through the grid (bricks hidden behind it), with holes
        // (rectangles of dropouts, unknown and invalid pixels, stray single dropouts, some on the
        // sphere's rim), a depth step across the image, and an empty view.
        let mut views = Vec::new();
        for (n, angle) in [0.0, 75.0, 150.0, 290.0].into_iter().enumerate() {
            let cam = camera(angle);
            let mut depth = sphere_depth(&cam);
            let wall = cam.pose.apply(&Vector3::zeros()).z as f32 + 0.012 - 0.004 * n as f32;
            for v in 0..cam.height as usize {
                for u in 0..cam.width as usize {
                    let d = &mut depth[v * cam.width as usize + u];
                    if *d == 0.0 {
                        *d = if u < 100 { wall } else { wall - 0.03 };
                    }
                    match (u / 10, v / 10) {
                        (3, 2..=4) => *d = 0.0,
                        (8, 5) | (9, 5) => *d = f32::NAN,
                        (12, 8) => *d = -1.0,
                        (13, 8) => *d = f32::INFINITY,
                        _ if (u * 7 + v * 13) % 89 == 0 => *d = 0.0,
                        _ => {}
                    }
                }
            }
            views.push((cam, depth));
        }
        views.push((camera(33.0), vec![0.0; 160 * 120]));
        // A close camera with skew (no distortion): the grid spills out of the image and part of it
        // lies behind the camera.
        let close = CameraModel {
            intrinsics: Intrinsics { skew: 0.7, ..Intrinsics::new(300.0, 290.0, 82.0, 57.0) },
            pose: Pose::look_at(Vector3::new(0.01, -0.034, 0.012), Vector3::zeros(), Vector3::z()),
            ..camera(0.0)
        };
        for angle in [0.0, 130.0] {
            let cam = close.for_turntable_angle(angle);
            let mut depth = sphere_depth(&cam);
            for (n, d) in depth.iter_mut().enumerate() {
                if n % 61 == 0 {
                    *d = 0.0;
                }
            }
            views.push((cam, depth));
        }
        views.extend(ring.iter().cloned());
        for missing_is_free in [true, false] {
            let params = FusionParams { missing_is_free, ..params };
            let (skipped, free) = culling_matches_unculled(grid, params, &ring);
            assert!(skipped > 0 && free > 0, "ring: {skipped} skipped, {free} free bricks");
            let (skipped, free) = culling_matches_unculled(grid, params, &views);
            // Without `missing_is_free` the stray dropouts leave few tiles that carve whole.
            assert!(skipped > 100 && free > 0, "holes: {skipped} skipped, {free} free bricks");
        }
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
