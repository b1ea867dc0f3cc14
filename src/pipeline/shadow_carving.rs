//! Shadow carving (Savarese, Andreetto, Rushmeier, Bernardini, Perona, "3D Reconstruction by Shadow
//! Carving", IJCV 2006): carve an upper bound of the object (the visual hull) further with the
//! self-shadows seen under point lights, which reveals concavities no silhouette can.
//!
//! # The rule, and why it is conservative
//! Take a camera `C`, a point light `L` and a pixel `p` that is dark under `L` (see
//! [`super::shadows`]). Let `Q` be the first point of the object on the ray from `C` through `p`.
//! `Q` is dark, so either the open segment `(Q, L)` meets the object (a cast shadow), or `Q` faces away
//! from `L` (an attached shadow) and then the segment enters the object right at `Q`. Either way
//! **the segment from `Q` to `L` meets the object**. The current estimate `U` contains the object, so
//! a point whose segment to `L` is free in `U` is free in the object too: such a point cannot be `Q`.
//!
//! Now let `V` be a voxel of `U` on that ray whose segment to `C` is free in `U` (it is on the surface
//! of `U` as seen by the camera: "the image shadow projected onto the current surface") and whose
//! segment to `L` is free in `U` (it is on the surface of `U` as seen by the light: it falls in the
//! shadow of the *virtual light image*, where the light would see the shadowed surface). Everything
//! between `C` and `V` is outside `U`, hence outside the object; `V` cannot be `Q`; so `Q`, the first
//! object point on the ray, lies beyond `V`, and `V` is empty. Remove it. Removing voxels frees
//! segments, so other voxels become visible from the camera or the light: repeat, sweeping over all
//! views, until a whole sweep removes nothing.
//!
//! # Discretisation
//! The object is in `U` voxel by voxel (a voxel is occupied when its centre is inside), not as a
//! continuous set, and a voxel covers a small cone of pixels. So: the segments are traced from the
//! voxel centre with an exact grid traversal (every voxel the segment passes through counts, not just
//! samples along it), which errs towards "blocked"; a voxel is tested only if its centre projects into
//! a shadow pixel of an *eroded* shadow mask (see [`super::shadows`]), so the whole neighbourhood of
//! the ray is in shadow and blurred or noisy shadow boundaries never carve; unknown pixels (dark,
//! specular) are never shadow. What the rule cannot carve is what no camera sees in shadow with a
//! light that sees it too: with few views or lights the result stays between the hull and the object.
//!
//! # Cost
//! Each candidate voxel (occupied in the hull, centre in a view's shadow) keeps, per view, the voxel
//! that blocked its camera and light segments and how far along they were free. Voxels are only ever
//! removed, so a segment free up to a point stays free there: a later sweep only re-checks the
//! blocker and, if it went, resumes the traversal from it. The work over all sweeps is therefore about
//! one traversal of each segment, not one per sweep. Candidates are tested in parallel (rayon) against
//! a snapshot; removals are applied after each view.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::occupancy::Occupancy;
use super::silhouette::Mask;
use crate::geometry::{CameraModel, VoxelGrid};

/// One camera view under one light, in the grid's frame (the object frame for a turntable angle).
#[derive(Debug, Clone, Copy)]
pub struct ShadowView<'a> {
    /// The camera, expressed in the grid's frame.
    pub camera: CameraModel,
    /// The light's position in the grid's frame, metres.
    pub light_m: Vector3<f64>,
    /// Pixels shadowed by this light (eroded, unknown pixels excluded); the camera's image size.
    pub shadow: &'a Mask,
}

/// Parameters of [`carve_shadows`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShadowCarveParams {
    /// Stop after this many sweeps over all views even if voxels still go (a safety bound; the carving
    /// normally converges much earlier).
    pub max_sweeps: u32,
}

impl Default for ShadowCarveParams {
    fn default() -> Self {
        ShadowCarveParams { max_sweeps: 500 }
    }
}

/// What [`carve_shadows`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct ShadowCarveStats {
    /// Voxels occupied before.
    pub initial: u64,
    /// Voxels removed.
    pub removed: u64,
    /// Sweeps over all views, the last one removing nothing (unless `max_sweeps` stopped it).
    pub sweeps: u32,
    /// Whether the last sweep removed nothing.
    pub converged: bool,
    /// (voxel, view) pairs tested: occupied voxels whose centre projects into the view's shadow.
    pub candidates: u64,
}

/// Errors of shadow carving.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShadowCarveError {
    /// A view's shadow mask is not the camera's image size.
    #[error("view {view}: shadow mask is {mask:?} pixels, the camera {camera:?}")]
    MaskSize {
        /// Index of the view.
        view: usize,
        /// Mask size (width, height).
        mask: (u32, u32),
        /// Camera image size (width, height).
        camera: (u32, u32),
    },
    /// A view's light position is not finite.
    #[error("view {view}: the light position is not finite")]
    BadLight {
        /// Index of the view.
        view: usize,
    },
    /// The grid is unusable.
    #[error("the voxel grid is unusable: dims {dims:?}, voxel size {voxel_size} m")]
    BadGrid {
        /// Voxels along x, y, z.
        dims: [usize; 3],
        /// Voxel edge, metres.
        voxel_size: f64,
    },
}

const NONE: u32 = u32::MAX;

/// Per (candidate voxel, view) state of the two segments.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    voxel: u32,
    cam: Segment,
    light: Segment,
}

/// How far along a segment is known free, and the voxel that blocked it there.
#[derive(Debug, Clone, Copy)]
struct Segment {
    free_to: f32,
    blocker: u32,
}

impl Segment {
    const UNTESTED: Segment = Segment { free_to: 0.0, blocker: NONE };
}

/// Carve the upper bound `hull` with the shadows of `views` until nothing more goes (see the module
/// documentation). Returns the carved occupancy (same grid) and what happened.
pub fn carve_shadows(
    hull: &Occupancy,
    views: &[ShadowView<'_>],
    params: &ShadowCarveParams,
) -> Result<(Occupancy, ShadowCarveStats), ShadowCarveError> {
    let grid = *hull.grid();
    if grid.is_empty() || !(grid.voxel_size.is_finite() && grid.voxel_size > 0.0) {
        return Err(ShadowCarveError::BadGrid { dims: grid.dims, voxel_size: grid.voxel_size });
    }
    for (view, v) in views.iter().enumerate() {
        let (cw, ch) = (v.camera.width, v.camera.height);
        if (v.shadow.width(), v.shadow.height()) != (cw, ch) {
            return Err(ShadowCarveError::MaskSize {
                view,
                mask: (v.shadow.width(), v.shadow.height()),
                camera: (cw, ch),
            });
        }
        if !v.light_m.iter().all(|x| x.is_finite()) {
            return Err(ShadowCarveError::BadLight { view });
        }
    }
    let dims = grid.dims;
    let mut occ = vec![0u8; grid.len()];
    let mut occupied = Vec::new();
    hull.for_each_occupied(|i, j, k| {
        let idx = grid.index(i, j, k);
        occ[idx] = 1;
        occupied.push(idx as u32);
    });
    let mut stats = ShadowCarveStats { initial: occupied.len() as u64, ..Default::default() };

    // Candidates per view: occupied voxels whose centre projects into the view's shadow. Views that
    // share a camera (one position under several lights) share the projection of the hull.
    let mut candidates: Vec<Vec<Candidate>> = Vec::with_capacity(views.len());
    let mut pixels: Vec<Option<(u32, u32)>> = Vec::new();
    for (i, v) in views.iter().enumerate() {
        if i == 0 || views[i - 1].camera != v.camera {
            pixels = occupied.par_iter().map(|&idx| v.camera.pixel_of(&voxel_centre(&grid, idx as usize))).collect();
        }
        candidates.push(
            occupied
                .par_iter()
                .zip(&pixels)
                .filter(|(_, px)| px.is_some_and(|(u, w)| v.shadow.get(u, w)))
                .map(|(&voxel, _)| Candidate { voxel, cam: Segment::UNTESTED, light: Segment::UNTESTED })
                .collect(),
        );
    }
    stats.candidates = candidates.iter().map(|c| c.len() as u64).sum();
    // Camera centres and lights in voxel coordinates (voxel (i, j, k) spans [i, i+1) x ...).
    let to_vox = |p: &Vector3<f64>| -> [f64; 3] { std::array::from_fn(|a| (p[a] - grid.origin[a]) / grid.voxel_size) };
    let targets: Vec<([f64; 3], [f64; 3])> =
        views.iter().map(|v| (to_vox(&v.camera.centre()), to_vox(&v.light_m))).collect();

    let mut remove = Vec::new();
    while stats.sweeps < params.max_sweeps {
        stats.sweeps += 1;
        let mut removed_in_sweep = 0u64;
        for (cands, &(cam, light)) in candidates.iter_mut().zip(&targets) {
            let occ_ref = &occ;
            remove.clear();
            remove.par_extend(cands.par_iter_mut().filter_map(|c| {
                let idx = c.voxel as usize;
                if occ_ref[idx] == 0 {
                    return None;
                }
                let start = index_centre(dims, idx);
                if !segment_free(occ_ref, dims, idx, &start, &cam, &mut c.cam) {
                    return None;
                }
                if !segment_free(occ_ref, dims, idx, &start, &light, &mut c.light) {
                    return None;
                }
                Some(c.voxel)
            }));
            for &idx in &remove {
                occ[idx as usize] = 0;
            }
            removed_in_sweep += remove.len() as u64;
            let occ_ref = &occ;
            cands.retain(|c| occ_ref[c.voxel as usize] != 0);
        }
        stats.removed += removed_in_sweep;
        tracing::debug!(sweep = stats.sweeps, removed = removed_in_sweep, "shadow carving sweep");
        if removed_in_sweep == 0 {
            stats.converged = true;
            break;
        }
    }
    let result = Occupancy::from_index_fn(grid, |i, j, k| occ[grid.index(i, j, k)] != 0);
    Ok((result, stats))
}

fn voxel_centre(grid: &VoxelGrid, idx: usize) -> Vector3<f64> {
    let [nx, ny, _] = grid.dims;
    grid.centre(idx % nx, (idx / nx) % ny, idx / (nx * ny))
}

fn index_centre(dims: [usize; 3], idx: usize) -> [f64; 3] {
    let [nx, ny, _] = dims;
    [(idx % nx) as f64 + 0.5, ((idx / nx) % ny) as f64 + 0.5, (idx / (nx * ny)) as f64 + 0.5]
}

/// Is the segment from `start` (the centre of voxel `own`) to `end` (voxel coordinates) free of
/// occupied voxels other than `own`? Uses and updates the cached progress `seg`.
fn segment_free(occ: &[u8], dims: [usize; 3], own: usize, start: &[f64; 3], end: &[f64; 3], seg: &mut Segment) -> bool {
    if seg.blocker != NONE {
        if occ[seg.blocker as usize] != 0 {
            return false;
        }
        seg.blocker = NONE;
    }
    match first_occupied(occ, dims, own, start, end, seg.free_to as f64) {
        Some((blocker, t)) => {
            seg.blocker = blocker as u32;
            // Resume a little before the blocker's entry so rounding never skips a voxel.
            seg.free_to = (t - 1e-4).max(0.0) as f32;
            false
        }
        None => {
            seg.free_to = 1.0;
            true
        }
    }
}

/// Grid traversal (Amanatides & Woo) of the segment `start + t·(end - start)`, `t` in `[t0, 1]`,
/// visiting every voxel the segment passes through. Returns the first occupied voxel other than
/// `own` and the parameter where the segment enters it. Outside the grid everything is empty; the
/// segment starts inside the grid and, the grid being convex, never re-enters it once it has left.
fn first_occupied(
    occ: &[u8],
    dims: [usize; 3],
    own: usize,
    start: &[f64; 3],
    end: &[f64; 3],
    t0: f64,
) -> Option<(usize, f64)> {
    let d: [f64; 3] = std::array::from_fn(|a| end[a] - start[a]);
    let p: [f64; 3] = std::array::from_fn(|a| start[a] + d[a] * t0);
    let mut cell: [i64; 3] = std::array::from_fn(|a| p[a].floor() as i64);
    let mut step = [0i64; 3];
    let mut t_max = [f64::INFINITY; 3];
    let mut t_delta = [f64::INFINITY; 3];
    for a in 0..3 {
        if d[a] > 0.0 {
            step[a] = 1;
            t_max[a] = t0 + ((cell[a] + 1) as f64 - p[a]) / d[a];
            t_delta[a] = 1.0 / d[a];
        } else if d[a] < 0.0 {
            step[a] = -1;
            t_max[a] = t0 + (cell[a] as f64 - p[a]) / d[a];
            t_delta[a] = -1.0 / d[a];
        }
    }
    let mut t = t0;
    loop {
        if (0..3).any(|a| cell[a] < 0 || cell[a] >= dims[a] as i64) {
            return None;
        }
        let idx = cell[0] as usize + dims[0] * (cell[1] as usize + dims[1] * cell[2] as usize);
        if idx != own && occ[idx] != 0 {
            return Some((idx, t));
        }
        let a = if t_max[0] <= t_max[1] && t_max[0] <= t_max[2] {
            0
        } else if t_max[1] <= t_max[2] {
            1
        } else {
            2
        };
        t = t_max[a];
        if t > 1.0 {
            return None;
        }
        cell[a] += step[a];
        t_max[a] += t_delta[a];
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, Intrinsics, Pose};

    fn grid(n: u32) -> VoxelGrid {
        VoxelGrid::from_resolution(&Aabb { min: [-0.05, -0.05, 0.0], max: [0.05, 0.05, 0.1] }, n)
    }

    fn camera(eye: Vector3<f64>) -> CameraModel {
        CameraModel {
            width: 160,
            height: 120,
            intrinsics: Intrinsics {
                fx: 200.0,
                fy: 200.0,
                cx: 80.0,
                cy: 60.0,
                skew: 0.0,
                k1: 0.0,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(eye, Vector3::new(0.0, 0.0, 0.05), Vector3::z()),
        }
    }

    #[test]
    fn traversal_finds_the_blocker_and_ignores_its_own_voxel() {
        let dims = [8, 8, 8];
        let at = |i: usize, j: usize, k: usize| i + 8 * (j + 8 * k);
        let mut occ = vec![0u8; 512];
        let own = at(1, 1, 1);
        occ[own] = 1;
        let wall = at(5, 1, 1);
        occ[wall] = 1;
        let start = [1.5, 1.5, 1.5];
        let hit = first_occupied(&occ, dims, own, &start, &[20.5, 1.5, 1.5], 0.0);
        assert_eq!(hit.map(|h| h.0), Some(wall));
        // Entry at x = 5: t = (5 - 1.5) / 19.
        let t = hit.map_or(0.0, |h| h.1);
        assert!((t - 3.5 / 19.0).abs() < 1e-12);
        assert_eq!(first_occupied(&occ, dims, own, &start, &[1.5, 20.5, 1.5], 0.0), None);
        // A diagonal segment passing through the corner-adjacent voxel is blocked by it.
        let mut occ2 = vec![0u8; 512];
        occ2[own] = 1;
        let diag = at(2, 2, 1);
        occ2[diag] = 1;
        assert_eq!(first_occupied(&occ2, dims, own, &start, &[6.5, 6.5, 1.5], 0.0).map(|h| h.0), Some(diag));
    }

    #[test]
    fn a_full_shadow_with_light_and_camera_outside_removes_only_exposed_layers() {
        // Without a shadow nothing goes; with the whole image in shadow and the light next to the
        // camera, every voxel both see goes, layer after layer, until the far side: the carving has
        // no evidence to stop (an image that is dark everywhere under a light that sees it means
        // there is nothing there).
        let g = grid(16);
        let hull = Occupancy::from_fn(g, |p| p.norm() < 0.03 || (p - Vector3::new(0.0, 0.0, 0.05)).norm() < 0.03);
        let cam = camera(Vector3::new(0.0, -0.4, 0.2));
        let none = Mask::from_fn(160, 120, |_, _| false);
        let views = [ShadowView { camera: cam, light_m: Vector3::new(0.05, -0.4, 0.2), shadow: &none }];
        let (out, stats) = carve_shadows(&hull, &views, &ShadowCarveParams::default()).expect("valid");
        assert!(out.same_voxels(&hull));
        assert_eq!(stats.removed, 0);
        assert!(stats.converged);
        let all = Mask::from_fn(160, 120, |_, _| true);
        let views = [ShadowView { camera: cam, light_m: Vector3::new(0.05, -0.4, 0.2), shadow: &all }];
        let (out, stats) = carve_shadows(&hull, &views, &ShadowCarveParams::default()).expect("valid");
        assert!(stats.removed > 0);
        assert_eq!(stats.removed + out.count(), hull.count());
    }

    #[test]
    fn a_light_that_cannot_see_the_surface_carves_nothing() {
        // Light below the table-level slab, camera above: the slab's top voxels see the camera but
        // every segment to the light crosses the slab.
        let g = grid(16);
        let hull = Occupancy::from_fn(g, |p| p.z < 0.02);
        let cam = camera(Vector3::new(0.0, -0.1, 0.4));
        let all = Mask::from_fn(160, 120, |_, _| true);
        let views = [ShadowView { camera: cam, light_m: Vector3::new(0.0, 0.0, -0.3), shadow: &all }];
        let (out, stats) = carve_shadows(&hull, &views, &ShadowCarveParams::default()).expect("valid");
        assert_eq!(stats.removed, 0);
        assert!(out.same_voxels(&hull));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let g = grid(8);
        let hull = Occupancy::full(g);
        let cam = camera(Vector3::new(0.0, -0.4, 0.2));
        let small = Mask::from_fn(10, 10, |_, _| true);
        let views = [ShadowView { camera: cam, light_m: Vector3::zeros(), shadow: &small }];
        assert!(matches!(
            carve_shadows(&hull, &views, &ShadowCarveParams::default()),
            Err(ShadowCarveError::MaskSize { view: 0, .. })
        ));
        let ok = Mask::from_fn(160, 120, |_, _| true);
        let views = [ShadowView { camera: cam, light_m: Vector3::new(f64::NAN, 0.0, 0.0), shadow: &ok }];
        assert!(matches!(
            carve_shadows(&hull, &views, &ShadowCarveParams::default()),
            Err(ShadowCarveError::BadLight { view: 0 })
        ));
    }
}
