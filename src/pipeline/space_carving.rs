//! Space carving (the visual hull) against silhouette masks.
//!
//! # The voxel test
//! A voxel is kept iff its **centre** projects inside the silhouette in every view that sees it. A view
//! in which the centre is behind the camera (camera-frame `z <= 0`) or falls outside the image does not
//! carve it. A projected point `(x, y)` falls in pixel `(floor x, floor y)`.
//!
//! The projection of voxel `(i, j, k)` is evaluated by one function (`Projector::project_index`), shared by
//! the dense reference and the hierarchical carver: camera coordinates `c = a + i·dᵢ + j·dⱼ + k·dₖ`
//! in `f32` (without distortion the rows are those of `P = K[R|t]` so `c` is homogeneous pixels;
//! with distortion they are those of `[R|t]` and the two-term radial model and `K` follow, in `f32`).
//! Both carvers therefore agree voxel for voxel by construction, provided the cell test is conservative.
//!
//! # The hierarchical (octree) test
//! A cell of voxels is bounded by the box of its voxel centres. Its eight corners are projected in
//! `f64` with the same affine coefficients. While every corner is in front of the camera the pinhole
//! image of the box lies within the rectangle of the corner images (a linear-fractional map takes its
//! extremes over a box at corners); with distortion the rectangle of normalised coordinates is pushed
//! through the distortion by interval arithmetic, which bounds every point of it. The rectangle is then
//! grown by a margin that exceeds the `f32` rounding of the per-voxel evaluation (a relative `1e-6` of
//! the magnitudes involved plus `1e-3` px; the `f32` evaluation errs by a few `1e-7` relative). So
//! every voxel centre's computed pixel lies inside the rectangle.
//! Against a per-view summed-area table of the mask:
//! - every pixel of the rectangle that lies in the image is object -> the view keeps the whole cell;
//! - the rectangle is wholly inside the image and holds no object pixel -> the cell is carved;
//! - otherwise the cell is subdivided, carrying only the undecided views.
//!
//! Cells go 32³ (a block) -> 16³ -> 8³ (a brick) -> 4³ -> single voxels (per-voxel test, four voxels
//! of a row projected together, early exit once the row is carved). The view that carved the last cell
//! is tried first in the next one. Each view's verdict on a cell is sound on its own, so neither the
//! order of views nor the hint changes the result.

use nalgebra::{Matrix3x4, Vector4};
use rayon::prelude::*;

use super::occupancy::{
    block_coords, brick_origin, sub_cube_bits, valid_bits, Block, Occupancy, BLOCK, BLOCK_BRICKS, BRICK,
};
use super::photo_consistency::VoxelCamera;
use super::silhouette::Mask;
use crate::geometry::round::floor_f64;
use crate::geometry::{CameraModel, VoxelGrid};

/// A calibrated silhouette: a camera (already in the grid's frame, e.g. the object frame for a
/// turntable angle) and its mask.
#[derive(Debug, Clone, Copy)]
pub struct View<'a> {
    /// The camera, expressed in the grid's frame.
    pub camera: CameraModel,
    /// The silhouette; its size must equal the camera's image size.
    pub mask: &'a Mask,
}

/// Errors of space carving.
#[derive(Debug, thiserror::Error)]
pub enum CarveError {
    /// The grid has no voxels or a non-finite / non-positive voxel size.
    #[error("the voxel grid is unusable: dims {dims:?}, voxel size {voxel_size} m")]
    BadGrid {
        /// Voxels along x, y, z.
        dims: [usize; 3],
        /// Voxel edge, metres.
        voxel_size: f64,
    },
    /// A view's mask is not the camera's image size.
    #[error(
        "view {view}: mask is {mask_width}x{mask_height} px but the camera image is {camera_width}x{camera_height} px"
    )]
    MaskSize {
        /// Index of the view in the call.
        view: usize,
        /// Mask width, px.
        mask_width: u32,
        /// Mask height, px.
        mask_height: u32,
        /// Camera width, px.
        camera_width: u32,
        /// Camera height, px.
        camera_height: u32,
    },
    /// A camera has non-finite parameters.
    #[error("view {view}: the camera has non-finite parameters")]
    BadCamera {
        /// Index of the view in the call.
        view: usize,
    },
    /// More views in one batch than the carver supports.
    #[error("{count} views in one batch; at most {max} are supported")]
    TooManyViews {
        /// Views given.
        count: usize,
        /// The limit.
        max: usize,
    },
}

const MAX_VIEWS: usize = u16::MAX as usize;

#[derive(Debug, Clone, Copy)]
struct Distortion {
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    skew: f32,
    k1: f32,
    k2: f32,
    p1: f32,
    p2: f32,
    k3: f32,
}

impl Distortion {
    /// True when only the radial `k1`, `k2` terms are non-zero (cell bounds are exact for those).
    fn radial_k1_k2_only(&self) -> bool {
        self.p1 == 0.0 && self.p2 == 0.0 && self.k3 == 0.0
    }
}

/// Per-view projection of voxel indices (see the module docs).
#[derive(Debug, Clone)]
pub(crate) struct Projector {
    a: [f32; 3],
    /// `d[axis][component]`.
    d: [[f32; 3]; 3],
    dist: Option<Distortion>,
    width: usize,
    wf: f32,
    hf: f32,
    /// Magnitude scales of the three components over the grid (for rounding margins).
    scale: [f64; 3],
}

impl Projector {
    pub(crate) fn new(camera: &CameraModel, grid: &VoxelGrid) -> Projector {
        let intr = &camera.intrinsics;
        let m: Matrix3x4<f64> = if intr.has_distortion() {
            let mut rt = Matrix3x4::zeros();
            rt.fixed_view_mut::<3, 3>(0, 0).copy_from(&camera.pose.rotation);
            rt.fixed_view_mut::<3, 1>(0, 3).copy_from(&camera.pose.translation);
            rt
        } else {
            camera.projection_matrix()
        };
        let s = grid.voxel_size;
        let first = Vector4::new(grid.origin[0] + 0.5 * s, grid.origin[1] + 0.5 * s, grid.origin[2] + 0.5 * s, 1.0);
        let a0 = m * first;
        let a = [a0.x as f32, a0.y as f32, a0.z as f32];
        let d = [0, 1, 2].map(|axis| [0, 1, 2].map(|c| (m[(c, axis)] * s) as f32));
        let nmax = grid.dims.iter().copied().max().unwrap_or(1) as f64;
        let scale = [0, 1, 2]
            .map(|c| (a[c] as f64).abs() + nmax * (0..3).map(|axis| (d[axis][c] as f64).abs()).sum::<f64>() + 1e-30);
        let dist = intr.has_distortion().then_some(Distortion {
            fx: intr.fx as f32,
            fy: intr.fy as f32,
            cx: intr.cx as f32,
            cy: intr.cy as f32,
            skew: intr.skew as f32,
            k1: intr.k1 as f32,
            k2: intr.k2 as f32,
            p1: intr.p1 as f32,
            p2: intr.p2 as f32,
            k3: intr.k3 as f32,
        });
        Projector { a, d, dist, width: camera.width as usize, wf: camera.width as f32, hf: camera.height as f32, scale }
    }

    /// Camera depth `z` and continuous pixel coordinates of voxel `(fi, fj, fk)`'s centre: the one
    /// formula every carver uses (see the module docs).
    #[inline(always)]
    fn project_index(&self, fi: f32, fj: f32, fk: f32) -> (f32, f32, f32) {
        let d = &self.d;
        let x = self.a[0] + fi * d[0][0] + fj * d[1][0] + fk * d[2][0];
        let y = self.a[1] + fi * d[0][1] + fj * d[1][1] + fk * d[2][1];
        let z = self.a[2] + fi * d[0][2] + fj * d[1][2] + fk * d[2][2];
        let (u, v) = match &self.dist {
            None => (x / z, y / z),
            Some(p) => {
                let (xn, yn) = (x / z, y / z);
                let r2 = xn * xn + yn * yn;
                // Brown-Conrady, as geometry::Intrinsics::distort.
                let f = 1.0 + r2 * (p.k1 + r2 * (p.k2 + r2 * p.k3));
                let xd = xn * f + 2.0 * p.p1 * xn * yn + p.p2 * (r2 + 2.0 * xn * xn);
                let yd = yn * f + p.p1 * (r2 + 2.0 * yn * yn) + 2.0 * p.p2 * xn * yn;
                (p.fx * xd + p.skew * yd + p.cx, p.fy * yd + p.cy)
            }
        };
        (z, u, v)
    }

    /// The pixel voxel `(i, j, k)`'s centre falls in, `None` when behind the camera or outside the image.
    #[inline(always)]
    pub(crate) fn pixel(&self, i: usize, j: usize, k: usize) -> Option<(usize, usize)> {
        let (z, u, v) = self.project_index(i as f32, j as f32, k as f32);
        // `z > 0` is false for NaN too. floor(u) is in [0, W) exactly when u is in [0, W) (W an
        // integer), and truncation equals floor for non-negative values: no floorf call in the hot loop.
        if z > 0.0 && u >= 0.0 && v >= 0.0 && u < self.wf && v < self.hf {
            Some((u as usize, v as usize))
        } else {
            None
        }
    }

    /// Which of the four voxels `(i0 + l, j, k)`, `l = 0..4`, the view keeps, as bit `l`. Same test as
    /// [`Projector::keeps`] lane by lane (the four projections are independent, so they vectorise).
    #[inline(always)]
    fn keeps4(&self, mask: &[u8], i0: usize, j: usize, k: usize) -> u64 {
        let (fj, fk) = (j as f32, k as f32);
        let mut zuv = [(0f32, 0f32, 0f32); 4];
        for (l, q) in zuv.iter_mut().enumerate() {
            *q = self.project_index((i0 + l) as f32, fj, fk);
        }
        let mut out = 0u64;
        for (l, &(z, u, v)) in zuv.iter().enumerate() {
            let kept = if z > 0.0 && u >= 0.0 && v >= 0.0 && u < self.wf && v < self.hf {
                mask[v as usize * self.width + u as usize] != 0
            } else {
                true
            };
            out |= (kept as u64) << l;
        }
        out
    }

    /// Does the view keep voxel `(i, j, k)`?
    #[inline(always)]
    pub(crate) fn keeps(&self, mask: &[u8], i: usize, j: usize, k: usize) -> bool {
        match self.pixel(i, j, k) {
            None => true,
            Some((u, v)) => mask[v * self.width + u] != 0,
        }
    }

    /// A conservative pixel rectangle `[x0, x1] x [y0, y1]` (continuous coordinates) holding the computed
    /// pixel of every voxel centre in `[lo, hi]` (inclusive indices), or `Behind` / `Unknown`.
    fn cell_bound(&self, lo: [usize; 3], hi: [usize; 3]) -> CellBound {
        // Corner `lo` and the three edge vectors of the box of centres; corners by addition.
        let mut base = [0f64; 3];
        let mut edges = [[0f64; 3]; 3];
        for c in 0..3 {
            base[c] = self.a[c] as f64
                + lo[0] as f64 * self.d[0][c] as f64
                + lo[1] as f64 * self.d[1][c] as f64
                + lo[2] as f64 * self.d[2][c] as f64;
            for (axis, e) in edges.iter_mut().enumerate() {
                e[c] = (hi[axis] - lo[axis]) as f64 * self.d[axis][c] as f64;
            }
        }
        let mut pts = [[0f64; 3]; 8];
        let mut zmin = f64::INFINITY;
        let mut zmax = f64::NEG_INFINITY;
        for (n, p) in pts.iter_mut().enumerate() {
            for (c, pc) in p.iter_mut().enumerate() {
                let mut v = base[c];
                for (axis, e) in edges.iter().enumerate() {
                    if n >> axis & 1 == 1 {
                        v += e[c];
                    }
                }
                *pc = v;
            }
            zmin = zmin.min(p[2]);
            zmax = zmax.max(p[2]);
        }
        let zeps = 1e-5 * self.scale[2];
        if zmax < -zeps {
            return CellBound::Behind;
        }
        if zmin.partial_cmp(&zeps) != Some(std::cmp::Ordering::Greater) {
            return CellBound::Unknown;
        }
        let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        for p in &pts {
            let inv = 1.0 / p[2];
            let (x, y) = (p[0] * inv, p[1] * inv);
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        // Rounding margin of the f32 evaluation of x/z and y/z.
        let ex = 1e-6 * (self.scale[0] + x0.abs().max(x1.abs()) * self.scale[2]) / zmin;
        let ey = 1e-6 * (self.scale[1] + y0.abs().max(y1.abs()) * self.scale[2]) / zmin;
        let (x0, x1, y0, y1) = (x0 - ex, x1 + ex, y0 - ey, y1 + ey);
        let rect = match &self.dist {
            None => [x0 - 1e-3, x1 + 1e-3, y0 - 1e-3, y1 + 1e-3],
            Some(p) if p.radial_k1_k2_only() => distorted_rect(p, [x0, x1, y0, y1]),
            // Tangential or r⁶ terms: no interval bound here; the cell is refined down to voxels,
            // which use the exact per-voxel projection.
            Some(_) => return CellBound::Unknown,
        };
        if rect.iter().all(|v| v.is_finite()) {
            CellBound::Rect(rect)
        } else {
            CellBound::Unknown
        }
    }
}

/// Push a normalised rectangle through the radial distortion and `K` by interval arithmetic.
fn distorted_rect(p: &Distortion, [x0, x1, y0, y1]: [f64; 4]) -> [f64; 4] {
    let closest = |a: f64, b: f64| if a <= 0.0 && b >= 0.0 { 0.0 } else { a.abs().min(b.abs()) };
    let smin = closest(x0, x1).powi(2) + closest(y0, y1).powi(2);
    let smax = x0.abs().max(x1.abs()).powi(2) + y0.abs().max(y1.abs()).powi(2);
    let (k1, k2) = (p.k1 as f64, p.k2 as f64);
    let f = |s: f64| 1.0 + k1 * s + k2 * s * s;
    let mut fmin = f(smin).min(f(smax));
    let mut fmax = f(smin).max(f(smax));
    if k2 != 0.0 {
        let sv = -k1 / (2.0 * k2);
        if sv > smin && sv < smax {
            fmin = fmin.min(f(sv));
            fmax = fmax.max(f(sv));
        }
    }
    let mul = |a0: f64, a1: f64, b0: f64, b1: f64| {
        let c = [a0 * b0, a0 * b1, a1 * b0, a1 * b1];
        (c.iter().copied().fold(f64::INFINITY, f64::min), c.iter().copied().fold(f64::NEG_INFINITY, f64::max))
    };
    let (xd0, xd1) = mul(x0, x1, fmin, fmax);
    let (yd0, yd1) = mul(y0, y1, fmin, fmax);
    let scale = |k: f64, a: f64, b: f64| if k >= 0.0 { (k * a, k * b) } else { (k * b, k * a) };
    let (ux0, ux1) = scale(p.fx as f64, xd0, xd1);
    let (us0, us1) = scale(p.skew as f64, yd0, yd1);
    let (vy0, vy1) = scale(p.fy as f64, yd0, yd1);
    let (u0, u1) = (ux0 + us0 + p.cx as f64, ux1 + us1 + p.cx as f64);
    let (v0, v1) = (vy0 + p.cy as f64, vy1 + p.cy as f64);
    let eu = 1e-6 * (ux0.abs().max(ux1.abs()) + us0.abs().max(us1.abs()) + (p.cx as f64).abs()) + 1e-3;
    let ev = 1e-6 * (vy0.abs().max(vy1.abs()) + (p.cy as f64).abs()) + 1e-3;
    [u0 - eu, u1 + eu, v0 - ev, v1 + ev]
}

#[derive(Debug, Clone, Copy)]
enum CellBound {
    /// Every centre is behind the camera.
    Behind,
    /// Cannot bound (the cell straddles the camera plane).
    Unknown,
    /// `[x0, x1, y0, y1]`, continuous pixels.
    Rect([f64; 4]),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Verdict {
    Keep,
    Carve,
    Undecided,
}

/// Summed-area table of a mask: `(w+1) x (h+1)` counts of object pixels.
fn build_sat(mask: &Mask, sat: &mut Vec<u32>) {
    let (w, h) = (mask.width() as usize, mask.height() as usize);
    sat.clear();
    sat.resize((w + 1) * (h + 1), 0);
    let data = mask.data();
    for y in 0..h {
        let mut run = 0u32;
        let (prev, cur) = sat.split_at_mut((y + 1) * (w + 1));
        let prev = &prev[y * (w + 1)..];
        for x in 0..w {
            run += data[y * w + x] as u32;
            cur[x + 1] = prev[x + 1] + run;
        }
    }
}

/// Classify a cell for one view against its summed-area table.
#[inline]
fn classify(p: &Projector, sat: &[u32], lo: [usize; 3], hi: [usize; 3]) -> Verdict {
    let r = match p.cell_bound(lo, hi) {
        CellBound::Behind => return Verdict::Keep,
        CellBound::Unknown => return Verdict::Undecided,
        CellBound::Rect(r) => r,
    };
    let (w, h) = (p.wf as f64, p.hf as f64);
    let (u0, u1, v0, v1) = (floor_f64(r[0]), floor_f64(r[1]), floor_f64(r[2]), floor_f64(r[3]));
    let inside = u0 >= 0.0 && v0 >= 0.0 && u1 < w && v1 < h;
    let (cu0, cu1) = (u0.max(0.0), u1.min(w - 1.0));
    let (cv0, cv1) = (v0.max(0.0), v1.min(h - 1.0));
    if cu0 > cu1 || cv0 > cv1 {
        // Every centre projects outside the image: the view does not carve.
        return Verdict::Keep;
    }
    let (a, b, c, d) = (cu0 as usize, cu1 as usize + 1, cv0 as usize, cv1 as usize + 1);
    let stride = p.width + 1;
    let count = sat[d * stride + b] + sat[c * stride + a] - sat[c * stride + b] - sat[d * stride + a];
    let area = ((b - a) * (d - c)) as u32;
    if count == area {
        Verdict::Keep
    } else if count == 0 && inside {
        Verdict::Carve
    } else {
        Verdict::Undecided
    }
}

/// What one carving call did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CarveStats {
    /// Views applied in this call.
    pub views: usize,
    /// Occupied voxels after the call.
    pub occupied: u64,
}

/// The dense reference carver: every voxel tested against every view (early exit on the first view
/// that carves it), in parallel. Same voxel test as [`SpaceCarver`].
pub fn carve_dense(grid: &VoxelGrid, views: &[View<'_>]) -> Result<Occupancy, CarveError> {
    check_grid(grid)?;
    check_views(views)?;
    let projectors: Vec<Projector> = views.iter().map(|v| Projector::new(&v.camera, grid)).collect();
    let masks: Vec<&[u8]> = views.iter().map(|v| v.mask.data()).collect();
    Ok(Occupancy::from_index_fn(*grid, |i, j, k| projectors.iter().zip(&masks).all(|(p, m)| p.keeps(m, i, j, k))))
}

fn check_grid(grid: &VoxelGrid) -> Result<(), CarveError> {
    if grid.is_empty()
        || !(grid.voxel_size.is_finite() && grid.voxel_size > 0.0)
        || grid.origin.iter().any(|o| !o.is_finite())
    {
        return Err(CarveError::BadGrid { dims: grid.dims, voxel_size: grid.voxel_size });
    }
    Ok(())
}

fn check_views(views: &[View<'_>]) -> Result<(), CarveError> {
    if views.len() > MAX_VIEWS {
        return Err(CarveError::TooManyViews { count: views.len(), max: MAX_VIEWS });
    }
    for (n, v) in views.iter().enumerate() {
        let c = &v.camera;
        if v.mask.width() != c.width || v.mask.height() != c.height {
            return Err(CarveError::MaskSize {
                view: n,
                mask_width: v.mask.width(),
                mask_height: v.mask.height(),
                camera_width: c.width,
                camera_height: c.height,
            });
        }
        if !c.is_finite() {
            return Err(CarveError::BadCamera { view: n });
        }
    }
    Ok(())
}

/// The hierarchical space carver. It keeps its occupancy and its per-view buffers (summed-area tables)
/// between calls: create it once per grid, call [`SpaceCarver::add_view`] as frames arrive (each call
/// carves the current result with one more view) or [`SpaceCarver::add_views`] with every view at once,
/// and [`SpaceCarver::reset`] to start a new scan on the same grid.
#[derive(Debug)]
pub struct SpaceCarver {
    occupancy: Occupancy,
    sats: Vec<Vec<u32>>,
    views_applied: usize,
}

struct PassCtx<'a> {
    projectors: &'a [Projector],
    sats: &'a [Vec<u32>],
    masks: &'a [&'a [u8]],
    dims: [usize; 3],
    block_dims: [usize; 3],
}

/// Per-task scratch: candidate view lists per octree level.
struct Scratch {
    lists: Vec<Vec<u16>>,
    /// The view that carved the last carved cell (`u16::MAX`: none yet).
    hint: u16,
}

/// Levels: 0 block (32), 1 (16), 2 brick (8), 3 (4), 4 voxels.
const LEVELS: usize = 5;

impl SpaceCarver {
    /// A carver over `grid`, every voxel occupied.
    pub fn new(grid: VoxelGrid) -> Result<SpaceCarver, CarveError> {
        check_grid(&grid)?;
        Ok(SpaceCarver { occupancy: Occupancy::full(grid), sats: Vec::new(), views_applied: 0 })
    }

    /// The grid.
    pub fn grid(&self) -> &VoxelGrid {
        self.occupancy.grid()
    }

    /// Every voxel occupied again; buffers are kept.
    pub fn reset(&mut self) {
        self.occupancy.fill();
        self.views_applied = 0;
    }

    /// Views applied since creation or the last reset.
    pub fn views_applied(&self) -> usize {
        self.views_applied
    }

    /// The current result.
    pub fn occupancy(&self) -> &Occupancy {
        &self.occupancy
    }

    /// The result, consuming the carver.
    pub fn into_occupancy(self) -> Occupancy {
        self.occupancy
    }

    /// Carve the current result with one more view.
    pub fn add_view(&mut self, camera: &CameraModel, mask: &Mask) -> Result<CarveStats, CarveError> {
        self.add_views(&[View { camera: *camera, mask }])
    }

    /// Carve the current result with every view of `views` in one hierarchical pass.
    pub fn add_views(&mut self, views: &[View<'_>]) -> Result<CarveStats, CarveError> {
        check_views(views)?;
        if views.is_empty() {
            return Ok(CarveStats { views: 0, occupied: self.occupancy.count() });
        }
        let grid = *self.occupancy.grid();
        let projectors: Vec<Projector> = views.iter().map(|v| Projector::new(&v.camera, &grid)).collect();
        if self.sats.len() < views.len() {
            self.sats.resize_with(views.len(), Vec::new);
        }
        self.sats[..views.len()].par_iter_mut().zip(views.par_iter()).for_each(|(sat, v)| build_sat(v.mask, sat));
        let masks: Vec<&[u8]> = views.iter().map(|v| v.mask.data()).collect();
        let ctx = PassCtx {
            projectors: &projectors,
            sats: &self.sats[..views.len()],
            masks: &masks,
            dims: grid.dims,
            block_dims: self.occupancy.block_dims(),
        };
        let n = views.len();
        self.occupancy.blocks_mut().par_iter_mut().enumerate().for_each_init(
            || Scratch { lists: (0..LEVELS).map(|_| Vec::with_capacity(n)).collect(), hint: u16::MAX },
            |scratch, (bi, block)| carve_block(&ctx, bi, block, scratch),
        );
        self.views_applied += n;
        tracing::debug!(views = n, total = self.views_applied, "carved");
        Ok(CarveStats { views: n, occupied: self.occupancy.count() })
    }
}

fn carve_block(ctx: &PassCtx<'_>, bi: usize, block: &mut Block, scratch: &mut Scratch) {
    if block.all_empty() {
        return;
    }
    let bc = block_coords(bi, &ctx.block_dims);
    let origin = bc.map(|c| c * BLOCK);
    scratch.lists[0].clear();
    scratch.lists[0].extend(0..ctx.projectors.len() as u16);
    carve_cell(ctx, block, scratch, 0, origin, bc);
}

/// Filter the candidate views of `level` for the cell `[lo, hi]` into `level + 1`.
/// Returns false when some view carves the whole cell.
fn filter_views(ctx: &PassCtx<'_>, scratch: &mut Scratch, level: usize, lo: [usize; 3], hi: [usize; 3]) -> bool {
    // Neighbouring cells tend to be carved by the same view: try the last carving view first. Every
    // verdict is sound on its own, so testing a view that is no longer a candidate is harmless.
    let hint = scratch.hint;
    let mut hint_verdict = Verdict::Keep;
    if (hint as usize) < ctx.projectors.len() {
        hint_verdict = classify(&ctx.projectors[hint as usize], &ctx.sats[hint as usize], lo, hi);
        if hint_verdict == Verdict::Carve {
            return false;
        }
    }
    let (cur, next) = scratch.lists.split_at_mut(level + 1);
    let (cur, next) = (&cur[level], &mut next[0]);
    next.clear();
    for &v in cur {
        let v_us = v as usize;
        let verdict = if v == hint { hint_verdict } else { classify(&ctx.projectors[v_us], &ctx.sats[v_us], lo, hi) };
        match verdict {
            Verdict::Keep => {}
            Verdict::Carve => {
                scratch.hint = v;
                return false;
            }
            Verdict::Undecided => next.push(v),
        }
    }
    true
}

/// A cell above brick level (level 0: 32³, level 1: 16³) starting at voxel `o`.
fn carve_cell(
    ctx: &PassCtx<'_>,
    block: &mut Block,
    scratch: &mut Scratch,
    level: usize,
    o: [usize; 3],
    bc: [usize; 3],
) {
    let size = BLOCK >> level;
    if (0..3).any(|a| o[a] >= ctx.dims[a]) {
        return;
    }
    let hi = [0, 1, 2].map(|a| (o[a] + size).min(ctx.dims[a]) - 1);
    // Local bricks of this cell.
    let nb = size / BRICK;
    let lb0 = [0, 1, 2].map(|a| (o[a] - bc[a] * BLOCK) / BRICK);
    let local =
        |x: usize, y: usize, z: usize| (lb0[0] + x) + BLOCK_BRICKS * ((lb0[1] + y) + BLOCK_BRICKS * (lb0[2] + z));
    if nb > 1 {
        let mut any = false;
        for z in 0..nb {
            for y in 0..nb {
                for x in 0..nb {
                    any |= !block.is_empty_brick(local(x, y, z));
                }
            }
        }
        if !any {
            return;
        }
    } else if block.is_empty_brick(local(0, 0, 0)) {
        return;
    }
    if !filter_views(ctx, scratch, level, o, hi) {
        for z in 0..nb {
            for y in 0..nb {
                for x in 0..nb {
                    block.clear_brick(local(x, y, z));
                }
            }
        }
        return;
    }
    if scratch.lists[level + 1].is_empty() {
        return;
    }
    if size > BRICK {
        let h = size / 2;
        for n in 0..8 {
            let child = [o[0] + (n & 1) * h, o[1] + ((n >> 1) & 1) * h, o[2] + ((n >> 2) & 1) * h];
            carve_cell(ctx, block, scratch, level + 1, child, bc);
        }
    } else {
        carve_brick(ctx, block, scratch, level + 1, o, local(0, 0, 0));
    }
}

/// Inside a brick at voxel `o` (local brick `lb`); candidate views are in `scratch.lists[level]`.
fn carve_brick(ctx: &PassCtx<'_>, block: &mut Block, scratch: &mut Scratch, level: usize, o: [usize; 3], lb: usize) {
    debug_assert_eq!(brick_origin(&block_coords_of(o), lb), o);
    let valid = valid_bits(&o, &ctx.dims);
    let mut bits = block.bits(lb, &valid);
    for n in 0..8 {
        let s = [(n & 1) * 4, ((n >> 1) & 1) * 4, ((n >> 2) & 1) * 4];
        let sub = sub_cube_bits(s[0], s[1], s[2], 4);
        if (0..8).all(|z| bits[z] & sub[z] == 0) {
            continue;
        }
        let lo = [o[0] + s[0], o[1] + s[1], o[2] + s[2]];
        let hi = [0, 1, 2].map(|a| (lo[a] + 4).min(ctx.dims[a]) - 1);
        if !filter_views(ctx, scratch, level, lo, hi) {
            for z in 0..8 {
                bits[z] &= !sub[z];
            }
            continue;
        }
        let cand = &scratch.lists[level + 1];
        if cand.is_empty() {
            continue;
        }
        // Row by row (four voxels along x, projected together), with an early exit once the row is empty.
        for (z, word) in bits.iter_mut().enumerate().skip(s[2]).take(4) {
            for y in s[1]..s[1] + 4 {
                let shift = 8 * y + s[0];
                let mut row = (*word >> shift) & 0xf;
                for &v in cand.iter() {
                    if row == 0 {
                        break;
                    }
                    row &= ctx.projectors[v as usize].keeps4(ctx.masks[v as usize], o[0] + s[0], o[1] + y, o[2] + z);
                }
                *word = (*word & !(0xf << shift)) | (row << shift);
            }
        }
    }
    block.set_bits(lb, &bits, &valid);
}

#[inline]
fn block_coords_of(o: [usize; 3]) -> [usize; 3] {
    o.map(|x| x / BLOCK)
}

/// The footprint-splatted re-projection of `occupancy` into `camera`: every boundary voxel's cube is
/// projected (its eight corners) and the pixels whose centres lie in the bounding rectangle of the
/// corner images are set, plus the pixel of the voxel centre. Voxels with any corner behind the camera
/// are skipped. Interior voxels are skipped: the projection of a solid is covered by the footprints of
/// the voxels on its boundary. Projected in `f32` through the full lens model, as the photo methods'
/// item buffers cover pixels (`photo_consistency::VoxelCamera::cover`): a pixel whose centre lies
/// within rounding of a rectangle's edge may differ from an `f64` projection (the test below bounds
/// how many). Any order of `boundary` gives the same mask.
pub fn reproject(occupancy: &Occupancy, boundary: &[[u32; 3]], camera: &CameraModel) -> Mask {
    let cover = VoxelCamera::new(camera, occupancy.grid()).cover(boundary);
    Mask::from_raw(camera.width, camera.height, cover.into_iter().map(u8::from).collect())
        .unwrap_or_else(|_| Mask::from_fn(0, 0, |_, _| false))
}

/// Silhouette re-projection IoU per view (footprints splatted, see [`reproject`]); views whose mask
/// size differs from the camera's give `None`.
pub fn reprojection_iou(occupancy: &Occupancy, views: &[View<'_>]) -> Vec<Option<f64>> {
    let boundary = occupancy.boundary_voxels();
    views.par_iter().map(|v| reproject(occupancy, &boundary, &v.camera).iou(v.mask)).collect()
}

#[cfg(test)]
mod reproject_tests {
    use super::*;
    use crate::geometry::{Aabb, Intrinsics, Pose};
    use nalgebra::{Point2, Vector3};

    /// The `f32` splat gives the footprints of projecting each voxel's eight corners on its own in
    /// `f64`, through a distorting lens and a pinhole, but for pixels whose centre lies within
    /// rounding of a rectangle's edge; and it does not depend on the order of the voxels.
    #[test]
    fn reprojection_matches_projecting_every_corner_in_f64() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-0.05; 3], max: [0.05; 3] }, 40);
        let solid = Occupancy::from_fn(grid, |p| p.norm() < 0.04 && p.z < 0.025);
        let lens = Intrinsics::new(900.0, 900.0, 320.0, 240.0).with_distortion([-0.1, 0.01, 1e-3, -2e-3, 0.02]);
        let pinhole = Intrinsics::new(700.0, 690.0, 311.0, 247.0);
        for intrinsics in [lens, pinhole] {
            let camera = CameraModel {
                intrinsics,
                pose: Pose::look_at(Vector3::new(0.25, -0.3, 0.15), Vector3::zeros(), Vector3::z()),
                width: 640,
                height: 480,
            };
            reprojection_matches_f64(&solid, &camera);
        }
    }

    fn reprojection_matches_f64(solid: &Occupancy, camera: &CameraModel) {
        let grid = *solid.grid();
        let boundary = solid.boundary_voxels();
        let ours = reproject(solid, &boundary, camera);
        let (o, s) = (grid.origin, grid.voxel_size);
        let mut reference = vec![false; 640 * 480];
        for v in &boundary {
            let corners: Vec<Point2<f64>> = (0..8u32)
                .map(|n| {
                    let l = [0, 1, 2].map(|a| f64::from(v[a] + (n >> a & 1)));
                    camera.project(&Vector3::new(o[0] + l[0] * s, o[1] + l[1] * s, o[2] + l[2] * s)).expect("in front")
                })
                .collect();
            let (x0, x1) =
                corners.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), q| (a.min(q.x), b.max(q.x)));
            let (y0, y1) =
                corners.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), q| (a.min(q.y), b.max(q.y)));
            let span = |a: f64, b: f64, n: usize| (a.floor().max(0.0) as usize)..(b.ceil().max(0.0) as usize).min(n);
            for y in span(y0, y1, 480) {
                for x in span(x0, x1, 640) {
                    let (u, w) = (x as f64 + 0.5, y as f64 + 0.5);
                    if (x0..=x1).contains(&u) && (y0..=y1).contains(&w) {
                        reference[y * 640 + x] = true;
                    }
                }
            }
            let c = grid.centre(v[0] as usize, v[1] as usize, v[2] as usize);
            if let Some((u, w)) = camera.pixel_of(&c) {
                reference[w as usize * 640 + u as usize] = true;
            }
        }
        let set = reference.iter().filter(|&&r| r).count();
        assert!(set > 5_000, "{set} pixels");
        let differ = (0..480u32)
            .flat_map(|y| (0..640u32).map(move |x| (x, y)))
            .filter(|&(x, y)| ours.get(x, y) != reference[(y * 640 + x) as usize])
            .count();
        assert!(differ * 1000 <= set, "{differ} of {set} pixels differ");
        // In z order, or any other: the same.
        let mut sorted = boundary.clone();
        sorted.sort_unstable_by_key(|v| [v[2], v[1], v[0]]);
        let again = reproject(solid, &sorted, camera);
        let differ = (0..480u32)
            .flat_map(|y| (0..640u32).map(move |x| (x, y)))
            .filter(|&(x, y)| ours.get(x, y) != again.get(x, y))
            .count();
        assert_eq!(differ, 0, "{differ} pixels differ in z order");
    }
}
