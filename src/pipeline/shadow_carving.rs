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
//! # Cost, and carving while the views arrive
//! [`ShadowCarver`] keeps the estimate as one flat byte per voxel and works on the surface only: a
//! voxel can pass the camera test only if the first voxel its segment enters, a face neighbour, is
//! empty (or outside the grid), so only voxels with an empty face neighbour get candidates (voxel,
//! view) at all; an interior voxel gets its candidates when a neighbour goes. A candidate traces its
//! camera segment, then its light segment; when one is blocked the candidate waits on the blocking
//! voxel (a list per voxel) and is re-tested only when that voxel goes, resuming the traversal right
//! after it (the traversal is replayed arithmetically up to the blocker, so it visits exactly the
//! voxels of a traversal from the start). Nothing is re-tested that cannot have changed, so the work
//! is about one traversal of each segment that can matter, with no sweeps over all candidates.
//! Candidates are tested in parallel (rayon) against the current estimate in rounds; a round's
//! removals are applied after it, and the candidates they free and the voxels they expose make the
//! next round.
//!
//! Voxels are only ever removed and the test of a voxel only gets easier when others go, so the
//! carving converges to the same set whatever the order: the largest subset of the start that no
//! test removes from. That makes it incremental: [`ShadowCarver::add_position`] carves with one
//! turntable position's views as soon as its frames are in, against the visual hull so far (an
//! upper bound of the final one), and [`ShadowCarver::restrict`] removes what a newer hull removed.
//! After the last position the result equals carving the final hull with all views at once
//! ([`carve_shadows`]). Traversals stay in `f64`, as before, so they visit the same voxels.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::occupancy::{Occupancy, BRICK};
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
    /// Stop after this many rounds of re-tests within one update even if voxels still go (a safety
    /// bound; the carving normally converges much earlier), leaving `converged` false.
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
    /// Rounds of re-tests (candidates tested in parallel, then their removals applied), over all
    /// updates.
    pub sweeps: u32,
    /// Whether every update ran until nothing more could go (no `max_sweeps` stop).
    pub converged: bool,
    /// (voxel, view) pairs tested: surface voxels whose centre projects into the view's shadow.
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
    /// A hull given to [`ShadowCarver::restrict`] is on another grid.
    #[error("the hull's grid ({hull:?} voxels) is not the carver's ({carver:?})")]
    GridMismatch {
        /// The hull's voxels along x, y, z.
        hull: [usize; 3],
        /// The carver's.
        carver: [usize; 3],
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

/// No voxel, no candidate; as a segment state: known free.
const NONE: u32 = u32::MAX;

/// Voxel states in [`ShadowCarver`]'s flat grid.
const EMPTY: u8 = 0;
/// Occupied, every face neighbour occupied: no candidates yet (it cannot see the camera).
const INTERIOR: u8 = 1;
/// Occupied with an empty face neighbour (or on the grid's border): its candidates exist.
const SURFACE: u8 = 2;

/// One (voxel, view) test and how far along its segments it got.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    voxel: u32,
    view: u32,
    /// Traversal steps to the voxel blocking the camera segment, or [`NONE`] once it is free.
    cam: u32,
    /// Traversal steps to the voxel blocking the light segment.
    light: u32,
}

/// What testing a candidate found.
#[derive(Debug, Clone, Copy)]
enum Outcome {
    /// Its voxel went already.
    Gone,
    /// Blocked by this voxel; wait until it goes.
    Blocked(u32),
    /// Both segments free: the voxel goes.
    Carve,
}

/// One turntable position: a camera and the views of its lights.
#[derive(Debug, Clone)]
struct Station {
    camera: CameraModel,
    /// Index of its first view; its lights are the views from there on.
    first_view: u32,
    shadows: Vec<Mask>,
}

/// Shadow carving that takes the views as they arrive (see the module documentation): start from an
/// upper bound, [`add_position`](ShadowCarver::add_position) per turntable position,
/// [`restrict`](ShadowCarver::restrict) whenever the upper bound shrinks, and
/// [`occupancy`](ShadowCarver::occupancy) for the result. Every call leaves the estimate converged
/// for the views given so far.
#[derive(Debug, Clone)]
pub struct ShadowCarver {
    grid: VoxelGrid,
    params: ShadowCarveParams,
    /// Per voxel: [`EMPTY`], [`INTERIOR`] or [`SURFACE`].
    occ: Vec<u8>,
    stations: Vec<Station>,
    /// Per view: camera centre and light, voxel coordinates (voxel (i, j, k) spans [i, i+1) x ...).
    targets: Vec<([f64; 3], [f64; 3])>,
    candidates: Vec<Candidate>,
    /// Per voxel: the first candidate waiting for it to go; `next` chains the rest.
    waiting: Vec<u32>,
    next: Vec<u32>,
    /// The surface voxels (a superset: entries that went are dropped lazily).
    surface: Vec<u32>,
    /// A camera lies inside the grid: every occupied voxel may see it, so every one is a candidate.
    all_candidates: bool,
    stats: ShadowCarveStats,
}

impl ShadowCarver {
    /// Start from the upper bound `hull` (e.g. the visual hull of the views so far).
    pub fn new(hull: &Occupancy, params: &ShadowCarveParams) -> Result<ShadowCarver, ShadowCarveError> {
        let grid = *hull.grid();
        if grid.is_empty() || !(grid.voxel_size.is_finite() && grid.voxel_size > 0.0) || grid.len() >= NONE as usize {
            return Err(ShadowCarveError::BadGrid { dims: grid.dims, voxel_size: grid.voxel_size });
        }
        let mut occ = vec![EMPTY; grid.len()];
        let mut initial = 0u64;
        hull.for_each_occupied(|i, j, k| {
            occ[grid.index(i, j, k)] = INTERIOR;
            initial += 1;
        });
        let mut carver = ShadowCarver {
            grid,
            params: *params,
            occ,
            stations: Vec::new(),
            targets: Vec::new(),
            candidates: Vec::new(),
            waiting: vec![NONE; grid.len()],
            next: Vec::new(),
            surface: Vec::new(),
            all_candidates: false,
            stats: ShadowCarveStats { initial, converged: true, ..Default::default() },
        };
        // The surface: occupied voxels with an empty or out-of-grid face neighbour.
        let dims = grid.dims;
        let occ = &carver.occ;
        carver.surface = (0..grid.len() as u32)
            .into_par_iter()
            .filter(|&v| {
                occ[v as usize] != EMPTY && face_neighbours(dims, v as usize).any(|n| n.is_none_or(|n| occ[n] == EMPTY))
            })
            .collect();
        for &v in &carver.surface {
            carver.occ[v as usize] = SURFACE;
        }
        Ok(carver)
    }

    /// The grid.
    pub fn grid(&self) -> &VoxelGrid {
        &self.grid
    }

    /// What happened so far; `removed` counts the voxels the shadows removed (not those
    /// [`restrict`](ShadowCarver::restrict) removed).
    pub fn stats(&self) -> ShadowCarveStats {
        self.stats
    }

    /// Number of occupied voxels.
    pub fn count(&self) -> u64 {
        self.occ.par_iter().filter(|&&o| o != EMPTY).count() as u64
    }

    /// The current estimate.
    pub fn occupancy(&self) -> Occupancy {
        let grid = self.grid;
        Occupancy::from_index_fn(grid, |i, j, k| self.occ[grid.index(i, j, k)] != EMPTY)
    }

    /// Carve with one camera position's views: `camera` in the grid's frame, and per light its
    /// position (grid frame, metres) and shadow mask (camera image size). Returns the voxels removed.
    pub fn add_position(
        &mut self,
        camera: CameraModel,
        lights: Vec<(Vector3<f64>, Mask)>,
    ) -> Result<u64, ShadowCarveError> {
        let first_view = self.targets.len();
        for (l, (light, shadow)) in lights.iter().enumerate() {
            let view = first_view + l;
            if (shadow.width(), shadow.height()) != (camera.width, camera.height) {
                return Err(ShadowCarveError::MaskSize {
                    view,
                    mask: (shadow.width(), shadow.height()),
                    camera: (camera.width, camera.height),
                });
            }
            if !light.iter().all(|x| x.is_finite()) {
                return Err(ShadowCarveError::BadLight { view });
            }
        }
        if lights.is_empty() {
            return Ok(0);
        }
        let before = self.stats.removed;
        let cam = self.to_vox(&camera.centre());
        for (light, _) in &lights {
            let light = self.to_vox(light);
            self.targets.push((cam, light));
        }
        let station =
            Station { camera, first_view: first_view as u32, shadows: lights.into_iter().map(|(_, m)| m).collect() };
        let inside = (0..3).all(|a| cam[a] >= 0.0 && cam[a] <= self.grid.dims[a] as f64);
        let mut pending = Vec::new();
        if inside && !self.all_candidates {
            // Every occupied voxel may see this camera: all become candidates, for every view.
            self.all_candidates = true;
            let occ = &self.occ;
            let all: Vec<u32> = (0..occ.len() as u32).filter(|&v| occ[v as usize] == INTERIOR).collect();
            for &v in &all {
                self.occ[v as usize] = SURFACE;
            }
            let (grid, stations) = (&self.grid, &self.stations);
            let fresh: Vec<Candidate> = all
                .par_iter()
                .flat_map_iter(|&v| stations.iter().flat_map(move |s| station_candidates(grid, s, v)))
                .collect();
            self.surface.extend_from_slice(&all);
            pending = self.push_candidates(fresh);
        }
        self.stations.push(station);
        // The surface's candidates for the new views.
        let occ = &self.occ;
        self.surface.retain(|&v| occ[v as usize] != EMPTY);
        let station = self.stations.last().expect("pushed above");
        let grid = self.grid;
        let fresh: Vec<Candidate> =
            self.surface.par_iter().flat_map_iter(|&v| station_candidates(&grid, station, v)).collect();
        pending.extend(self.push_candidates(fresh));
        self.settle(pending);
        Ok(self.stats.removed - before)
    }

    /// Remove every voxel that `hull` (same grid) does not hold, e.g. after the visual hull took a
    /// new silhouette, and carve what that frees. Returns the voxels removed by the shadows.
    pub fn restrict(&mut self, hull: &Occupancy) -> Result<u64, ShadowCarveError> {
        if hull.grid() != &self.grid {
            return Err(ShadowCarveError::GridMismatch { hull: hull.grid().dims, carver: self.grid.dims });
        }
        let before = self.stats.removed;
        let dims = self.grid.dims;
        let bd = hull.brick_dims();
        let occ = &self.occ;
        // Brick by brick: a brick the hull holds whole, or that is empty here, costs one test.
        let gone: Vec<u32> = (0..bd[0] * bd[1] * bd[2])
            .into_par_iter()
            .flat_map_iter(|b| {
                let bc = [b % bd[0], (b / bd[0]) % bd[1], b / (bd[0] * bd[1])];
                let bits = hull.brick_bits(bc);
                let o = bc.map(|x| x * BRICK);
                let mut out = Vec::new();
                for (z, &word) in bits.iter().enumerate() {
                    let k = o[2] + z;
                    if k >= dims[2] {
                        break;
                    }
                    for y in 0..BRICK {
                        let j = o[1] + y;
                        if j >= dims[1] {
                            break;
                        }
                        let row = (word >> (8 * y)) as u8;
                        if row == 0xff {
                            continue;
                        }
                        for x in 0..BRICK.min(dims[0] - o[0]) {
                            let v = o[0] + x + dims[0] * (j + dims[1] * k);
                            if row >> x & 1 == 0 && occ[v] != EMPTY {
                                out.push(v as u32);
                            }
                        }
                    }
                }
                out
            })
            .collect();
        for &v in &gone {
            self.occ[v as usize] = EMPTY;
        }
        let pending = self.after_removal(&gone);
        self.settle(pending);
        Ok(self.stats.removed - before)
    }

    fn to_vox(&self, p: &Vector3<f64>) -> [f64; 3] {
        std::array::from_fn(|a| (p[a] - self.grid.origin[a]) / self.grid.voxel_size)
    }

    /// Append candidates; returns their ids.
    fn push_candidates(&mut self, fresh: Vec<Candidate>) -> Vec<u32> {
        let first = self.candidates.len() as u32;
        self.stats.candidates += fresh.len() as u64;
        self.candidates.extend(fresh);
        self.next.resize(self.candidates.len(), NONE);
        (first..self.candidates.len() as u32).collect()
    }

    /// After `gone` were emptied: the candidates that waited on them, and candidates for the voxels
    /// they exposed.
    fn after_removal(&mut self, gone: &[u32]) -> Vec<u32> {
        let mut pending = Vec::new();
        let mut exposed = Vec::new();
        let dims = self.grid.dims;
        for &b in gone {
            let mut c = std::mem::replace(&mut self.waiting[b as usize], NONE);
            while c != NONE {
                pending.push(c);
                c = self.next[c as usize];
            }
            for n in face_neighbours(dims, b as usize).flatten() {
                if self.occ[n] == INTERIOR {
                    self.occ[n] = SURFACE;
                    exposed.push(n as u32);
                }
            }
        }
        if !exposed.is_empty() {
            let (grid, stations) = (&self.grid, &self.stations);
            let fresh: Vec<Candidate> = exposed
                .par_iter()
                .flat_map_iter(|&v| stations.iter().flat_map(move |s| station_candidates(grid, s, v)))
                .collect();
            self.surface.extend_from_slice(&exposed);
            pending.extend(self.push_candidates(fresh));
        }
        pending
    }

    /// Test `pending` in rounds until no candidate can go.
    fn settle(&mut self, mut pending: Vec<u32>) {
        let mut rounds = 0;
        let dims = self.grid.dims;
        while !pending.is_empty() {
            if rounds == self.params.max_sweeps {
                self.stats.converged = false;
                tracing::warn!(rounds, pending = pending.len(), "shadow carving stopped before converging");
                return;
            }
            rounds += 1;
            self.stats.sweeps += 1;
            let (occ, targets, candidates) = (&self.occ, &self.targets, &self.candidates);
            let tested: Vec<(Candidate, Outcome)> = pending
                .par_iter()
                .map(|&c| {
                    let mut cand = candidates[c as usize];
                    let outcome = test(occ, dims, &targets[cand.view as usize], &mut cand);
                    (cand, outcome)
                })
                .collect();
            let mut gone = Vec::new();
            for (&c, (cand, outcome)) in pending.iter().zip(tested) {
                self.candidates[c as usize] = cand;
                match outcome {
                    Outcome::Gone => {}
                    Outcome::Blocked(b) => {
                        self.next[c as usize] = self.waiting[b as usize];
                        self.waiting[b as usize] = c;
                    }
                    Outcome::Carve => {
                        if self.occ[cand.voxel as usize] != EMPTY {
                            self.occ[cand.voxel as usize] = EMPTY;
                            gone.push(cand.voxel);
                        }
                    }
                }
            }
            self.stats.removed += gone.len() as u64;
            tracing::trace!(round = rounds, tested = pending.len(), removed = gone.len(), "shadow carving round");
            pending = self.after_removal(&gone);
        }
    }
}

/// The candidates of voxel `v` under the views of `station`: one per light whose shadow its centre
/// projects into.
fn station_candidates<'a>(grid: &VoxelGrid, station: &'a Station, v: u32) -> impl Iterator<Item = Candidate> + 'a {
    let px = station.camera.pixel_of(&voxel_centre(grid, v as usize));
    station.shadows.iter().enumerate().filter_map(move |(l, shadow)| {
        let (u, w) = px?;
        shadow.get(u, w).then_some(Candidate { voxel: v, view: station.first_view + l as u32, cam: 0, light: 0 })
    })
}

/// Test one candidate against `occ`, resuming its segments where they were blocked.
fn test(occ: &[u8], dims: [usize; 3], &(cam, light): &([f64; 3], [f64; 3]), c: &mut Candidate) -> Outcome {
    let idx = c.voxel as usize;
    if occ[idx] == EMPTY {
        return Outcome::Gone;
    }
    let start = index_centre(dims, idx);
    if c.cam != NONE {
        match first_occupied(occ, dims, &start, &cam, c.cam) {
            Some((b, steps)) => {
                c.cam = steps;
                return Outcome::Blocked(b as u32);
            }
            None => c.cam = NONE,
        }
    }
    match first_occupied(occ, dims, &start, &light, c.light) {
        Some((b, steps)) => {
            c.light = steps;
            Outcome::Blocked(b as u32)
        }
        None => Outcome::Carve,
    }
}

/// The six face neighbours of voxel `v`; `None` for those outside the grid.
fn face_neighbours(dims: [usize; 3], v: usize) -> impl Iterator<Item = Option<usize>> {
    let [nx, ny, nz] = dims;
    let (i, j, k) = (v % nx, (v / nx) % ny, v / (nx * ny));
    let plane = nx * ny;
    [
        (i > 0).then(|| v - 1),
        (i + 1 < nx).then(|| v + 1),
        (j > 0).then(|| v - nx),
        (j + 1 < ny).then(|| v + nx),
        (k > 0).then(|| v - plane),
        (k + 1 < nz).then(|| v + plane),
    ]
    .into_iter()
}

/// Carve the upper bound `hull` with the shadows of `views` until nothing more goes (see the module
/// documentation). Returns the carved occupancy (same grid) and what happened. Consecutive views
/// with the same camera are one position of a [`ShadowCarver`].
pub fn carve_shadows(
    hull: &Occupancy,
    views: &[ShadowView<'_>],
    params: &ShadowCarveParams,
) -> Result<(Occupancy, ShadowCarveStats), ShadowCarveError> {
    let mut carver = ShadowCarver::new(hull, params)?;
    let mut first = 0;
    while first < views.len() {
        let camera = views[first].camera;
        let end = views[first..].iter().position(|v| v.camera != camera).map_or(views.len(), |n| first + n);
        let lights = views[first..end].iter().map(|v| (v.light_m, v.shadow.clone())).collect();
        carver.add_position(camera, lights)?;
        first = end;
    }
    Ok((carver.occupancy(), carver.stats()))
}

fn voxel_centre(grid: &VoxelGrid, idx: usize) -> Vector3<f64> {
    let [nx, ny, _] = grid.dims;
    grid.centre(idx % nx, (idx / nx) % ny, idx / (nx * ny))
}

fn index_centre(dims: [usize; 3], idx: usize) -> [f64; 3] {
    let [nx, ny, _] = dims;
    [(idx % nx) as f64 + 0.5, ((idx / nx) % ny) as f64 + 0.5, (idx / (nx * ny)) as f64 + 0.5]
}

/// Grid traversal (Amanatides & Woo) of the segment `start + t·(end - start)`, `t` in `[0, 1]`,
/// visiting every voxel the segment passes through; `start` is the centre of the voxel it starts in,
/// which never blocks. Returns the first occupied voxel after the first `resume` steps (the voxels up
/// to there are known free, or were the blocker that has gone) and the steps taken to reach it.
/// Resuming replays the steps arithmetically, so the voxels visited are exactly those of a traversal
/// from the start. Outside the grid everything is empty; the segment starts inside the grid and, the
/// grid being convex, never re-enters it once it has left.
fn first_occupied(occ: &[u8], dims: [usize; 3], start: &[f64; 3], end: &[f64; 3], resume: u32) -> Option<(usize, u32)> {
    let d: [f64; 3] = std::array::from_fn(|a| end[a] - start[a]);
    let p = *start;
    let mut cell: [i64; 3] = std::array::from_fn(|a| p[a].floor() as i64);
    let mut step = [0i64; 3];
    let mut t_max = [f64::INFINITY; 3];
    let mut t_delta = [f64::INFINITY; 3];
    for a in 0..3 {
        if d[a] > 0.0 {
            step[a] = 1;
            t_max[a] = ((cell[a] + 1) as f64 - p[a]) / d[a];
            t_delta[a] = 1.0 / d[a];
        } else if d[a] < 0.0 {
            step[a] = -1;
            t_max[a] = (cell[a] as f64 - p[a]) / d[a];
            t_delta[a] = -1.0 / d[a];
        }
    }
    let mut steps = 0u32;
    loop {
        if steps > resume {
            if (0..3).any(|a| cell[a] < 0 || cell[a] >= dims[a] as i64) {
                return None;
            }
            let idx = cell[0] as usize + dims[0] * (cell[1] as usize + dims[1] * cell[2] as usize);
            if occ[idx] != EMPTY {
                return Some((idx, steps));
            }
        }
        let a = if t_max[0] <= t_max[1] && t_max[0] <= t_max[2] {
            0
        } else if t_max[1] <= t_max[2] {
            1
        } else {
            2
        };
        if t_max[a] > 1.0 {
            return None;
        }
        cell[a] += step[a];
        t_max[a] += t_delta[a];
        steps += 1;
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
        let hit = first_occupied(&occ, dims, &start, &[20.5, 1.5, 1.5], 0);
        // Cells x = 2, 3, 4, 5: the wall is four steps along.
        assert_eq!(hit, Some((wall, 4)));
        assert_eq!(first_occupied(&occ, dims, &start, &[1.5, 20.5, 1.5], 0), None);
        // Once the wall has gone, resuming after it finds the next blocker, as a fresh traversal does.
        let far = at(7, 1, 1);
        occ[far] = 1;
        occ[wall] = 0;
        assert_eq!(first_occupied(&occ, dims, &start, &[20.5, 1.5, 1.5], 4), Some((far, 6)));
        assert_eq!(first_occupied(&occ, dims, &start, &[20.5, 1.5, 1.5], 0), Some((far, 6)));
        // A diagonal segment passing through the corner-adjacent voxel is blocked by it.
        let mut occ2 = vec![0u8; 512];
        occ2[own] = 1;
        let diag = at(2, 2, 1);
        occ2[diag] = 1;
        assert_eq!(first_occupied(&occ2, dims, &start, &[6.5, 6.5, 1.5], 0).map(|h| h.0), Some(diag));
    }

    #[test]
    fn carving_position_by_position_while_the_hull_shrinks_equals_carving_at_the_end() {
        // A bowl (a sphere with a spherical pit in its top) under a ring of cameras and lights: the
        // hulls shrink from a loose box to the bowl's own bounding cylinder while positions arrive;
        // carving as they come and restricting to each newer hull gives the same voxels as carving
        // the last hull with every view.
        let g = grid(24);
        let c = Vector3::new(0.0, 0.0, 0.045);
        let bowl = |p: Vector3<f64>| (p - c).norm() < 0.035 && (p - Vector3::new(0.0, 0.0, 0.085)).norm() > 0.03;
        let hulls = [
            Occupancy::from_fn(g, |p| p.z < 0.09),
            Occupancy::from_fn(g, |p| p.z < 0.085 && p.x.abs() < 0.04),
            Occupancy::from_fn(g, |p| p.z < 0.082 && p.xy().norm() < 0.037),
        ];
        let positions: Vec<(CameraModel, Vec<Vector3<f64>>)> = (0..6)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 6.0;
                let cam = camera(Vector3::new(0.3 * a.cos(), 0.3 * a.sin(), 0.3));
                let lights = (0..2)
                    .map(|l| {
                        let b = a + 0.8 + l as f64 * 1.9;
                        Vector3::new(0.25 * b.cos(), 0.25 * b.sin(), 0.2)
                    })
                    .collect();
                (cam, lights)
            })
            .collect();
        // Shadow: pixels whose ray meets the bowl at a point from which the light is blocked by it.
        let shadow = |cam: &CameraModel, light: &Vector3<f64>| {
            let o = cam.centre();
            Mask::from_fn(160, 120, |u, v| {
                let d = cam.pixel_ray(u as f64 + 0.5, v as f64 + 0.5).normalize();
                let Some(t) = (200..600).map(|s| s as f64 * 1e-3).find(|&t| bowl(o + d * t)) else {
                    return false;
                };
                let p = o + d * (t - 1e-3);
                let to = light - p;
                (1..200).any(|s| bowl(p + to * (s as f64 / 200.0)))
            })
        };
        let masks: Vec<Vec<Mask>> =
            positions.iter().map(|(cam, lights)| lights.iter().map(|l| shadow(cam, l)).collect()).collect();
        let views: Vec<ShadowView<'_>> = positions
            .iter()
            .zip(&masks)
            .flat_map(|((cam, lights), ms)| {
                lights.iter().zip(ms).map(|(l, m)| ShadowView { camera: *cam, light_m: *l, shadow: m })
            })
            .collect();
        let (at_end, stats) = carve_shadows(&hulls[2], &views, &ShadowCarveParams::default()).expect("valid");
        assert!(stats.removed > 0, "the test must carve something");
        let mut carver = ShadowCarver::new(&hulls[0], &ShadowCarveParams::default()).expect("valid");
        for (i, ((cam, lights), ms)) in positions.iter().zip(&masks).enumerate() {
            carver.restrict(&hulls[(i / 2).min(2)]).expect("same grid");
            carver.add_position(*cam, lights.iter().copied().zip(ms.iter().cloned()).collect()).expect("valid");
        }
        carver.restrict(&hulls[2]).expect("same grid");
        let streamed = carver.occupancy();
        assert_eq!(streamed.first_difference(&at_end), None);
        assert!(carver.stats().converged);
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
