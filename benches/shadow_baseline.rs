//! The shadow carving `scanrig::pipeline::carve_shadows` replaced (kept verbatim apart from input
//! validation), as the same-run baseline of `benches/methods.rs` and the reference of
//! `tests/shadow_carving_equivalence.rs`: candidates are every hull voxel whose centre projects into a
//! view's shadow, and sweeps over all views re-test every live candidate (re-checking its cached
//! blocker, resuming the traversal from just before it when it went) until a sweep removes nothing.

use rayon::prelude::*;

use scanrig::geometry::{Vector3, VoxelGrid};
use scanrig::pipeline::{Occupancy, ShadowCarveParams, ShadowCarveStats, ShadowView};

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
pub fn carve_shadows_baseline(
    hull: &Occupancy,
    views: &[ShadowView<'_>],
    params: &ShadowCarveParams,
) -> (Occupancy, ShadowCarveStats) {
    let grid = *hull.grid();
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
    (result, stats)
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
