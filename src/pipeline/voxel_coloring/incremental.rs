//! The incremental item-buffer carver behind [`super::carve_photo`] (see the module docs there).
//!
//! State: the surface voxels as *slots* (a slot is never reused; a carved voxel's slot goes dead),
//! and per view the footprint of every slot (computed once, when the voxel reaches the surface) and
//! the item buffer of the live slots (per pixel the nearest: smallest centre depth, ties to the
//! smallest linear voxel index, which is the order the whole-surface renderer writes in). After an
//! iteration carves the set `C` and exposes the set `E` (occupied face neighbours of `C` not yet on
//! the surface):
//! - the pixels a voxel of `C` owned are reset, and the live slots whose footprint meets a 16x16
//!   tile holding a reset pixel are drawn again over them (a pixel no voxel of `C` owned already
//!   names the nearest of the old surface minus `C`, which no redraw can beat);
//! - the voxels of `E` are drawn over everything.
//!
//! The buffer is then exactly the item buffer of the new surface. A voxel's verdict depends only on
//! its 26-neighbourhood (the normal), on which of its footprint pixels it owns and on the images,
//! so the next iteration judges only the voxels of `E`, the live 26-neighbours of `C` and the owners
//! (old and new) of every pixel that changed hands: every other voxel would get the verdict it got
//! before, consistent. The result is the whole-surface iteration's, voxel for voxel.

use rayon::prelude::*;

use super::{restore_silhouettes, ColouredSurface, Dense, PhotoModel, PhotoStats, OCCUPIED};
use crate::geometry::VoxelGrid;
use crate::pipeline::occupancy::Occupancy;
use crate::pipeline::photo_consistency::{
    centre_sample, check_inputs, colour_spread, facing, is_consistent, ncc_pattern, normal_estimate, sample_view,
    surface_colour, touches_contour, Footprint, PhotoError, PhotoParams, PhotoView, ViewSample, VoxelCamera,
};

/// Bit of [`Dense::bits`]: the voxel has a slot (it is, or was, on the surface).
const SLOTTED: u8 = 4;
/// No slot.
const NONE: u32 = u32::MAX;
/// Tile edge, pixels, of the redraw bookkeeping.
const TILE: usize = 16;

/// A footprint as cached: the pixel rectangle `[x0, x1) x [y0, y1)` (empty when `x0 == x1`: the
/// voxel has no footprint in the view) and the centre's camera depth, metres.
#[derive(Debug, Clone, Copy, Default)]
struct Packed {
    x0: u16,
    x1: u16,
    y0: u16,
    y1: u16,
    depth: f32,
}

impl Packed {
    fn of(fp: Option<Footprint>) -> Packed {
        match fp {
            // Image sizes are checked to fit 16 bits before any footprint is packed.
            Some(f) => Packed { x0: f.x0 as u16, x1: f.x1 as u16, y0: f.y0 as u16, y1: f.y1 as u16, depth: f.depth },
            None => Packed::default(),
        }
    }

    #[inline]
    fn get(&self) -> Option<Footprint> {
        (self.x0 < self.x1).then_some(Footprint {
            depth: self.depth,
            x0: self.x0 as usize,
            x1: self.x1 as usize,
            y0: self.y0 as usize,
            y1: self.y1 as usize,
        })
    }
}

/// One view's cached footprints (by slot), item buffer and redraw tiles.
struct ViewState {
    fps: Vec<Packed>,
    depth: Vec<f32>,
    id: Vec<u32>,
    width: usize,
    tiles: Vec<bool>,
    tiles_w: usize,
}

impl ViewState {
    fn new(cam: &VoxelCamera) -> ViewState {
        let n = cam.width * cam.height;
        let tiles_w = cam.width.div_ceil(TILE);
        ViewState {
            fps: Vec::new(),
            depth: vec![f32::INFINITY; n],
            id: vec![NONE; n],
            width: cam.width,
            tiles: vec![false; tiles_w * cam.height.div_ceil(TILE)],
            tiles_w,
        }
    }

    /// Draw slot `s` (linear voxel indices by slot in `lins`) with the depth test; owners it
    /// displaces and `s` itself (when it wins a pixel) go to `marks` when `mark` is set.
    #[inline]
    fn draw(&mut self, s: u32, lins: &[u32], mark: bool, marks: &mut Vec<u32>) {
        let Some(fp) = self.fps[s as usize].get() else { return };
        let lin = lins[s as usize];
        let mut won = false;
        for y in fp.y0..fp.y1 {
            let row = y * self.width;
            for p in row + fp.x0..row + fp.x1 {
                let old = self.id[p];
                let beats =
                    fp.depth < self.depth[p] || (fp.depth == self.depth[p] && old != NONE && lin < lins[old as usize]);
                if beats {
                    if mark && old != NONE {
                        marks.push(old);
                    }
                    self.id[p] = s;
                    self.depth[p] = fp.depth;
                    won = true;
                }
            }
        }
        if mark && won {
            marks.push(s);
        }
    }

    /// Whether the footprint of slot `s` meets a flagged tile.
    #[inline]
    fn meets_flagged(&self, s: usize) -> bool {
        let Some(fp) = self.fps[s].get() else { return false };
        for ty in fp.y0 / TILE..=(fp.y1 - 1) / TILE {
            for tx in fp.x0 / TILE..=(fp.x1 - 1) / TILE {
                if self.tiles[ty * self.tiles_w + tx] {
                    return true;
                }
            }
        }
        false
    }

    /// Bring the item buffer from the old surface to the new one (see the module docs): `carved`
    /// slots went dead, `added` slots are new (their footprints already cached), `live` says which
    /// slots are live. Returns the slots whose owned pixels changed.
    fn update(&mut self, carved: &[u32], added: &[u32], live: &[bool], lins: &[u32]) -> Vec<u32> {
        let mut marks = Vec::new();
        let mut reset = Vec::new();
        for &s in carved {
            let Some(fp) = self.fps[s as usize].get() else { continue };
            for y in fp.y0..fp.y1 {
                for x in fp.x0..fp.x1 {
                    let p = y * self.width + x;
                    if self.id[p] == s {
                        self.id[p] = NONE;
                        self.depth[p] = f32::INFINITY;
                        reset.push(p);
                        self.tiles[(y / TILE) * self.tiles_w + x / TILE] = true;
                    }
                }
            }
        }
        if !reset.is_empty() {
            let first_added = added.first().map_or(live.len(), |&s| s as usize);
            for (s, &alive) in live.iter().enumerate().take(first_added) {
                if alive && self.meets_flagged(s) {
                    self.draw(s as u32, lins, false, &mut marks);
                }
            }
        }
        for &s in added {
            self.draw(s, lins, true, &mut marks);
        }
        for &p in &reset {
            if self.id[p] != NONE {
                marks.push(self.id[p]);
            }
            self.tiles[(p / self.width / TILE) * self.tiles_w + (p % self.width) / TILE] = false;
        }
        marks
    }
}

#[allow(clippy::too_many_arguments)] // one voxel's visit, kept as plain arguments
/// Per-view samples of slot `s` (voxel `v`) under the item buffers, views facing below `min_cos`
/// dropped; centre pixels when `colour`, NCC patterns when the parameters ask for them.
fn gather(
    cams: &[VoxelCamera],
    views: &[PhotoView<'_>],
    states: &[ViewState],
    v: [u32; 3],
    s: u32,
    normal: [f32; 3],
    params: &PhotoParams,
    colour: bool,
) -> (Vec<ViewSample>, Vec<[f32; 24]>) {
    let mut samples = Vec::new();
    let mut patterns = Vec::new();
    let want_ncc = !colour && params.min_ncc.is_some();
    for ((cam, view), st) in cams.iter().zip(views).zip(states) {
        let Some(fp) = st.fps[s as usize].get() else { continue };
        if facing(cam, cam.point(v, [0.0; 3]), normal) < params.min_cos {
            continue;
        }
        let visible = |x: usize, y: usize| st.id[y * st.width + x] == s;
        let (count, mean) = sample_view(cam, view, &fp, visible);
        if count > 0 {
            let centre = if colour { centre_sample(cam, view, v, visible) } else { None };
            samples.push(ViewSample { count, mean, centre });
            if want_ncc {
                if let Some(p) = ncc_pattern(cam, view, v, visible) {
                    patterns.push(p);
                }
            }
        }
    }
    (samples, patterns)
}

/// Whether slot `s` touches a view's silhouette contour on pixels it owns (see
/// `photo_consistency::touches_contour`): such voxels are kept.
fn on_rim(views: &[PhotoView<'_>], states: &[ViewState], s: u32) -> bool {
    views.iter().zip(states).any(|(view, st)| {
        st.fps[s as usize].get().is_some_and(|fp| touches_contour(view, &fp, |x, y| st.id[y * st.width + x] == s))
    })
}

/// The carver's state over one run.
struct Carver<'a> {
    cams: Vec<VoxelCamera>,
    views: &'a [PhotoView<'a>],
    dense: Dense,
    /// Voxel of each slot.
    voxels: Vec<[u32; 3]>,
    /// Linear index of each slot's voxel.
    lins: Vec<u32>,
    live: Vec<bool>,
    states: Vec<ViewState>,
}

impl<'a> Carver<'a> {
    fn new(start: &Occupancy, views: &'a [PhotoView<'a>]) -> Carver<'a> {
        let grid = *start.grid();
        let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
        let states = cams.iter().map(ViewState::new).collect();
        let mut c = Carver {
            cams,
            views,
            dense: Dense::from(start),
            voxels: Vec::new(),
            lins: Vec::new(),
            live: Vec::new(),
            states,
        };
        let surface = c.dense.surface();
        c.add(&surface);
        let all: Vec<u32> = (0..c.voxels.len() as u32).collect();
        let lins = &c.lins;
        c.states.par_iter_mut().for_each(|st| {
            let mut none = Vec::new();
            for &s in &all {
                st.draw(s, lins, false, &mut none);
            }
        });
        c
    }

    /// Give `voxels` (in increasing linear index) slots, with their footprints in every view.
    fn add(&mut self, voxels: &[[u32; 3]]) -> Vec<u32> {
        let first = self.voxels.len() as u32;
        for &v in voxels {
            let i = self.dense.index(v);
            self.dense.bits[i] |= SLOTTED;
            self.voxels.push(v);
            self.lins.push(i as u32);
            self.live.push(true);
        }
        self.states.par_iter_mut().zip(&self.cams).for_each(|(st, cam)| {
            st.fps.extend(voxels.iter().map(|&v| Packed::of(cam.footprint(v))));
        });
        (first..self.voxels.len() as u32).collect()
    }

    fn normal(&self, v: [u32; 3]) -> [f32; 3] {
        normal_estimate(&|i, j, k| self.dense.get(i, j, k), v)
    }

    fn consistent(&self, s: u32, params: &PhotoParams) -> bool {
        let v = self.voxels[s as usize];
        if on_rim(self.views, &self.states, s) {
            return true;
        }
        let (samples, patterns) = gather(&self.cams, self.views, &self.states, v, s, self.normal(v), params, false);
        is_consistent(&samples, &patterns, params)
    }

    /// Carve `carved` (live slots); returns the slots to judge next.
    fn carve(&mut self, carved: &[u32]) -> Vec<u32> {
        let dims = self.dense.dims.map(|d| d as i64);
        let inside = |u: [i64; 3]| (0..3).all(|a| u[a] >= 0 && u[a] < dims[a]);
        for &s in carved {
            self.live[s as usize] = false;
            self.dense.clear(self.voxels[s as usize]);
        }
        // Newly exposed voxels, in increasing linear index (the draw order of ties is by index anyway).
        let mut exposed: Vec<[u32; 3]> = Vec::new();
        let mut touched: Vec<u32> = Vec::new();
        for &s in carved {
            let v = self.voxels[s as usize].map(|x| x as i64);
            for dz in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let u = [v[0] + dx, v[1] + dy, v[2] + dz];
                        if !inside(u) {
                            continue;
                        }
                        let u = u.map(|x| x as u32);
                        let i = self.dense.index(u);
                        let b = self.dense.bits[i];
                        if b & OCCUPIED == 0 {
                            continue;
                        }
                        if b & SLOTTED != 0 {
                            touched.push(i as u32); // a 26-neighbour: its normal changed
                        } else if dx.abs() + dy.abs() + dz.abs() == 1 {
                            self.dense.bits[i] |= SLOTTED;
                            exposed.push(u);
                        }
                    }
                }
            }
        }
        for &v in &exposed {
            let i = self.dense.index(v);
            self.dense.bits[i] &= !SLOTTED; // `add` sets it again
        }
        exposed.sort_unstable_by_key(|&v| self.dense.index(v));
        let added = self.add(&exposed);
        let (live, lins) = (&self.live, &self.lins);
        let marks: Vec<Vec<u32>> = self.states.par_iter_mut().map(|st| st.update(carved, &added, live, lins)).collect();
        // Slots of the touched neighbours: binary search over the (sorted by slot, and slots are
        // handed out in batches of increasing index) is not possible across batches, so map them.
        let mut todo: Vec<u32> = added.clone();
        if !touched.is_empty() {
            touched.sort_unstable();
            touched.dedup();
            for (s, &lin) in self.lins.iter().enumerate() {
                if self.live[s] && touched.binary_search(&lin).is_ok() {
                    todo.push(s as u32);
                }
            }
        }
        todo.extend(marks.into_iter().flatten());
        todo.sort_unstable();
        todo.dedup();
        todo.retain(|&s| self.live[s as usize]);
        todo
    }

    fn coloured_surface(&self, params: &PhotoParams) -> ColouredSurface {
        let mut slots: Vec<u32> = (0..self.voxels.len() as u32).filter(|&s| self.live[s as usize]).collect();
        slots.sort_unstable_by_key(|&s| self.lins[s as usize]);
        let colours: Vec<([u8; 3], bool)> = slots
            .par_iter()
            .map(|&s| {
                let v = self.voxels[s as usize];
                let (samples, _) = gather(&self.cams, self.views, &self.states, v, s, self.normal(v), params, true);
                (surface_colour(&samples), !samples.is_empty())
            })
            .collect();
        ColouredSurface {
            voxels: slots.iter().map(|&s| self.voxels[s as usize]).collect(),
            colours: colours.iter().map(|c| c.0).collect(),
            seen: colours.iter().map(|c| c.1).collect(),
        }
    }
}

/// The colour spread between views (see `photo_consistency::colour_spread`) of every surface voxel
/// of `start` that at least `params.min_views` views see, under item buffers of that surface.
pub(super) fn surface_spreads(start: &Occupancy, views: &[PhotoView<'_>], params: &PhotoParams) -> Vec<f32> {
    let c = Carver::new(start, views);
    (0..c.voxels.len() as u32)
        .into_par_iter()
        .filter_map(|s| {
            let v = c.voxels[s as usize];
            let (samples, _) = gather(&c.cams, c.views, &c.states, v, s, c.normal(v), params, false);
            (samples.len() >= params.min_views).then(|| colour_spread(&samples))
        })
        .collect()
}

/// See [`super::carve_photo`].
pub(super) fn carve(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    let t = std::time::Instant::now();
    let grid: VoxelGrid = *start.grid();
    check_inputs(&grid, views, params)?;
    for (n, v) in views.iter().enumerate() {
        if v.camera.width > u16::MAX as u32 || v.camera.height > u16::MAX as u32 {
            return Err(PhotoError::ImageSize { view: n, width: v.camera.width, height: v.camera.height });
        }
    }
    let mut c = Carver::new(start, views);
    let mut stats = PhotoStats::default();
    let mut todo: Vec<u32> = (0..c.voxels.len() as u32).collect();
    while stats.iterations < params.max_iterations {
        stats.iterations += 1;
        let carved: Vec<u32> = {
            let c = &c;
            todo.par_iter().copied().filter(|&s| !c.consistent(s, params)).collect()
        };
        stats.visits += todo.len() as u64;
        tracing::debug!(iteration = stats.iterations, judged = todo.len(), carved = carved.len(), "photo carving");
        if carved.is_empty() {
            break;
        }
        stats.carved += carved.len() as u64;
        todo = c.carve(&carved);
    }
    let restored = restore_silhouettes(start, &mut c.dense, views);
    stats.carved -= restored;
    let occupancy = c.dense.to_occupancy(grid);
    let surface =
        if restored == 0 { c.coloured_surface(params) } else { super::colour_dense(&c.dense, &c.cams, views, params) };
    stats.seconds = t.elapsed().as_secs_f64();
    Ok(PhotoModel { occupancy, surface, stats })
}
