//! The incremental item-buffer carver behind [`super::carve_photo`] (see the module docs there).
//!
//! State: the surface voxels as *slots* (a slot is never reused; a carved voxel's slot goes dead),
//! and per view the footprint of every slot (computed once, when the voxel reaches the surface),
//! the item buffer of the live slots (per pixel the nearest: smallest centre depth, ties to the
//! smallest linear voxel index, which is the order the whole-surface renderer writes in), per 8x8
//! pixel tile the slots whose footprints meet it, and per slot its *sample*: the count, mean colour
//! and contour-band flag of the footprint pixels it owns (`photo_consistency::ViewPixels`). After
//! an iteration carves the set `C` and exposes the set `E` (occupied face neighbours of `C` not yet
//! on the surface):
//! - the pixels a voxel of `C` owned are reset, and the live slots listed in a tile holding a reset
//!   pixel are drawn again over them (a pixel no voxel of `C` owned already names the nearest of
//!   the old surface minus `C`, which no redraw can beat);
//! - the voxels of `E` are drawn over everything;
//! - every live slot that gained or lost a pixel in the view is sampled again (in that view only).
//!
//! The buffer is then exactly the item buffer of the new surface, and every sample is what sampling
//! it afresh would give. A voxel's verdict depends only on its 26-neighbourhood (the normal) and on
//! its samples, so the next iteration judges only the voxels of `E`, the live 26-neighbours of `C`
//! and the owners (old and new) of every pixel that changed hands: every other voxel would get the
//! verdict it got before, consistent. Judging reads the cached samples, not the pixels (the NCC
//! patterns, when asked for, are read from the pixels). The result is the whole-surface
//! iteration's, voxel for voxel.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use rayon::prelude::*;

use super::{restore_silhouettes, ColouredSurface, Dense, PhotoModel, PhotoStats, SeenBy, OCCUPIED};
use crate::geometry::VoxelGrid;
use crate::pipeline::occupancy::Occupancy;
use crate::pipeline::photo_consistency::{
    centre_sample, check_inputs, colour_spread, facing, is_consistent, ncc_pattern, normal_estimate, surface_colour,
    Footprint, FootprintSample, PhotoError, PhotoParams, PhotoView, ViewPixels, ViewSample, VoxelCamera,
};

/// Bit of [`Dense::bits`]: the voxel has a slot (it is, or was, on the surface).
const SLOTTED: u8 = 4;
/// No slot.
const NONE: u32 = u32::MAX;
/// Tile edge, pixels, of the redraw bookkeeping.
const TILE: usize = 8;

/// Linear voxel index -> slot. A multiplicative hash spreads the indices well enough; the standard
/// SipHash would cost more than the lookups it serves.
type SlotMap = HashMap<u32, u32, BuildHasherDefault<LinHasher>>;

/// The hasher of [`SlotMap`]: one multiplication by an odd 64-bit constant (Fibonacci hashing).
#[derive(Default)]
struct LinHasher(u64);

impl Hasher for LinHasher {
    fn finish(&self) -> u64 {
        // The table takes its bucket from the low bits: fold the well-mixed high half into them.
        self.0 ^ (self.0 >> 32)
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }

    fn write_u32(&mut self, x: u32) {
        self.0 = (self.0 ^ u64::from(x)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

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

/// One view's cached footprints and samples (by slot), item buffer and redraw tiles.
struct ViewState {
    fps: Vec<Packed>,
    /// Per slot, its visible footprint pixels in this view under the current item buffer (kept up
    /// to date for the live slots whose owned pixels change).
    samples: Vec<FootprintSample>,
    depth: Vec<f32>,
    id: Vec<u32>,
    width: usize,
    /// Per redraw tile, whether it holds a pixel reset in the current update.
    tiles: Vec<bool>,
    tiles_w: usize,
    /// Per redraw tile, the slots whose footprints meet it, with their footprints (dead slots
    /// dropped as they are met). Empty, like `tiles`, in a state that is only measured, never
    /// updated (see [`Carver::checked`]).
    tile_slots: Vec<Vec<(u32, Packed)>>,
}

impl ViewState {
    /// An empty state of `cam`'s view, with its redraw tiles when `carving`.
    fn new(cam: &VoxelCamera, carving: bool) -> ViewState {
        let n = cam.width * cam.height;
        let tiles_w = cam.width.div_ceil(TILE);
        let tiles = if carving { tiles_w * cam.height.div_ceil(TILE) } else { 0 };
        ViewState {
            fps: Vec::new(),
            samples: Vec::new(),
            depth: vec![f32::INFINITY; n],
            id: vec![NONE; n],
            width: cam.width,
            tiles: vec![false; tiles],
            tiles_w,
            tile_slots: vec![Vec::new(); tiles],
        }
    }

    /// Cache the footprints of new slots `first..` and enter them in the tiles they meet (when the
    /// state has tiles).
    fn extend(&mut self, cam: &VoxelCamera, first: u32, voxels: &[[u32; 3]]) {
        let tiled = !self.tile_slots.is_empty();
        for (s, &v) in (first..).zip(voxels) {
            let packed = Packed::of(cam.footprint(v));
            self.fps.push(packed);
            let Some(fp) = packed.get().filter(|_| tiled) else { continue };
            for ty in fp.y0 / TILE..=(fp.y1 - 1) / TILE {
                for tx in fp.x0 / TILE..=(fp.x1 - 1) / TILE {
                    self.tile_slots[ty * self.tiles_w + tx].push((s, packed));
                }
            }
        }
    }

    /// Draw slot `s` (linear voxel indices by slot in `lins`) with the depth test; owners it
    /// displaces and `s` itself (when it wins a pixel) go to `marks` when `mark` is set.
    #[inline]
    fn draw(&mut self, s: u32, lins: &[u32], mark: bool, marks: &mut Vec<u32>) {
        let fp = self.fps[s as usize];
        self.draw_packed(s, fp, lins, mark, marks);
    }

    /// [`Self::draw`] with slot `s`'s footprint given.
    #[inline]
    fn draw_packed(&mut self, s: u32, fp: Packed, lins: &[u32], mark: bool, marks: &mut Vec<u32>) {
        let Some(fp) = fp.get() else { return };
        let mut won = false;
        for y in fp.y0..fp.y1 {
            let row = y * self.width;
            for p in row + fp.x0..row + fp.x1 {
                let old = self.id[p];
                let beats = fp.depth < self.depth[p]
                    || (fp.depth == self.depth[p] && old != NONE && lins[s as usize] < lins[old as usize]);
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

    /// Bring the item buffer from the old surface to the new one (see the module docs): `carved`
    /// slots went dead, `added` slots are new (their footprints already cached), `live` says which
    /// slots are live. Re-samples and returns the live slots whose owned pixels changed (sorted).
    fn update(&mut self, px: &ViewPixels<'_>, carved: &[u32], added: &[u32], live: &[bool], lins: &[u32]) -> Vec<u32> {
        debug_assert!(!self.tile_slots.is_empty(), "a state built without redraw tiles is never updated");
        let mut marks = Vec::new();
        let mut reset = Vec::new();
        let mut flagged = Vec::new();
        for &s in carved {
            let Some(fp) = self.fps[s as usize].get() else { continue };
            for y in fp.y0..fp.y1 {
                for x in fp.x0..fp.x1 {
                    let p = y * self.width + x;
                    if self.id[p] == s {
                        self.id[p] = NONE;
                        self.depth[p] = f32::INFINITY;
                        reset.push(p);
                        let t = (y / TILE) * self.tiles_w + x / TILE;
                        if !self.tiles[t] {
                            self.tiles[t] = true;
                            flagged.push(t);
                        }
                    }
                }
            }
        }
        // Slots older than this update's additions whose footprints meet a flagged tile are drawn
        // again (a slot meeting several such tiles is drawn more than once, which changes nothing:
        // the depth test with its index tie-break does not depend on the drawing order).
        let first_added = added.first().map_or(live.len(), |&s| s as usize) as u32;
        for &t in &flagged {
            let mut slots = std::mem::take(&mut self.tile_slots[t]);
            slots.retain(|&(s, _)| live[s as usize]);
            for &(s, fp) in &slots {
                if s < first_added {
                    self.draw_packed(s, fp, lins, false, &mut marks);
                }
            }
            self.tile_slots[t] = slots;
            self.tiles[t] = false;
        }
        for &s in added {
            self.draw(s, lins, true, &mut marks);
        }
        for &p in &reset {
            if self.id[p] != NONE {
                marks.push(self.id[p]);
            }
        }
        marks.sort_unstable();
        marks.dedup();
        marks.retain(|&s| live[s as usize]);
        self.samples.resize(live.len(), FootprintSample::default());
        for &s in &marks {
            self.resample(px, s);
        }
        marks
    }

    /// Sample slot `s`'s visible footprint pixels again.
    fn resample(&mut self, px: &ViewPixels<'_>, s: u32) {
        self.samples[s as usize] = match self.fps[s as usize].get() {
            Some(fp) => px.sample(&fp, |p| self.id[p] == s),
            None => FootprintSample::default(),
        };
    }
}

/// Per-view samples of slot `s` (voxel `v`) from the cached samples, with the views facing below
/// `min_cos` dropped and the centre pixels read (for colouring).
fn colour_samples(
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    states: &[ViewState],
    v: [u32; 3],
    s: u32,
    normal: [f32; 3],
    params: &PhotoParams,
) -> Vec<ViewSample> {
    let mut samples = Vec::new();
    for ((cam, px), st) in cams.iter().zip(pixels).zip(states) {
        let FootprintSample { count, mean, .. } = st.samples[s as usize];
        if count == 0 || facing(cam, cam.point(v, [0.0; 3]), normal) < params.min_cos {
            continue;
        }
        samples.push(ViewSample { count, mean, centre: centre_sample(cam, px, v, |p| st.id[p] == s) });
    }
    samples
}

/// The verdict on slot `s` (voxel `v`, estimated outward normal `normal`) from its cached
/// per-view samples: `None` when a view sees it on its silhouette's contour band (such voxels are
/// kept, see `photo_consistency::ViewPixels`), else its per-view samples (views facing below
/// `min_cos` dropped) and NCC patterns when the parameters ask for them.
fn judge_samples(
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    states: &[ViewState],
    v: [u32; 3],
    s: u32,
    normal: [f32; 3],
    params: &PhotoParams,
) -> Option<(Vec<ViewSample>, Vec<[f32; 24]>)> {
    let mut samples = Vec::with_capacity(cams.len());
    let mut patterns = Vec::new();
    for ((cam, px), st) in cams.iter().zip(pixels).zip(states) {
        let FootprintSample { count, mean, rim } = st.samples[s as usize];
        if rim {
            return None;
        }
        if count == 0 || facing(cam, cam.point(v, [0.0; 3]), normal) < params.min_cos {
            continue;
        }
        samples.push(ViewSample { count, mean, centre: None });
        if params.min_ncc.is_some() {
            if let Some(p) = ncc_pattern(cam, px, v, |p| st.id[p] == s) {
                patterns.push(p);
            }
        }
    }
    Some((samples, patterns))
}

/// The carver's state over one run.
pub(super) struct Carver<'a> {
    cams: Vec<VoxelCamera>,
    pixels: Vec<ViewPixels<'a>>,
    dense: Dense,
    /// Voxel of each slot.
    voxels: Vec<[u32; 3]>,
    /// Linear index of each slot's voxel.
    lins: Vec<u32>,
    /// The slot of each slotted voxel, by linear index.
    slot_of: SlotMap,
    live: Vec<bool>,
    states: Vec<ViewState>,
    /// Slots given to the start's surface (the first ones).
    start_slots: usize,
}

impl<'a> Carver<'a> {
    /// The state of `start` in `views` after checking the inputs (`check_inputs`, and image sizes
    /// that fit the packed footprints' 16 bits). `carving`: the state will be carved, so each view
    /// keeps its redraw tiles (the slots meeting each 8x8 pixel tile, 16 bytes an entry: 47 MB for
    /// the shipped voxel-colouring rig's hull in 36 views); a state that is only measured (the
    /// noise, the start's colours) goes without them.
    pub(super) fn checked(
        start: &Occupancy,
        views: &'a [PhotoView<'a>],
        params: &PhotoParams,
        carving: bool,
    ) -> Result<Carver<'a>, PhotoError> {
        check_inputs(start.grid(), views, params)?;
        for (n, v) in views.iter().enumerate() {
            if v.camera.width > u16::MAX as u32 || v.camera.height > u16::MAX as u32 {
                return Err(PhotoError::ImageSize { view: n, width: v.camera.width, height: v.camera.height });
            }
        }
        Ok(Carver::new(start, views, carving))
    }

    fn new(start: &Occupancy, views: &'a [PhotoView<'a>], carving: bool) -> Carver<'a> {
        let grid = *start.grid();
        let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
        // Each view's item buffer is a fresh 8 bytes a pixel: the page faults of zeroing them are
        // shared between the cores.
        let states = cams.par_iter().map(|cam| ViewState::new(cam, carving)).collect();
        let mut c = Carver {
            cams,
            pixels: ViewPixels::all(views),
            dense: Dense::from(start),
            voxels: Vec::new(),
            lins: Vec::new(),
            slot_of: SlotMap::default(),
            live: Vec::new(),
            states,
            start_slots: 0,
        };
        let surface = c.dense.surface();
        c.add(&surface);
        c.start_slots = surface.len();
        let all: Vec<u32> = (0..c.voxels.len() as u32).collect();
        let lins = &c.lins;
        c.states.par_iter_mut().zip(&c.pixels).for_each(|(st, px)| {
            let mut none = Vec::new();
            for &s in &all {
                st.draw(s, lins, false, &mut none);
            }
            st.samples = vec![FootprintSample::default(); all.len()];
            for &s in &all {
                st.resample(px, s);
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
            self.slot_of.insert(i as u32, self.voxels.len() as u32);
            self.voxels.push(v);
            self.lins.push(i as u32);
            self.live.push(true);
        }
        self.states.par_iter_mut().zip(&self.cams).for_each(|(st, cam)| st.extend(cam, first, voxels));
        (first..self.voxels.len() as u32).collect()
    }

    fn normal(&self, v: [u32; 3]) -> [f32; 3] {
        normal_estimate(&|i, j, k| self.dense.get(i, j, k), v)
    }

    fn consistent(&self, s: u32, params: &PhotoParams) -> bool {
        let v = self.voxels[s as usize];
        judge_samples(&self.cams, &self.pixels, &self.states, v, s, self.normal(v), params)
            .is_none_or(|(samples, patterns)| is_consistent(&samples, &patterns, params))
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
        let marks: Vec<Vec<u32>> = self
            .states
            .par_iter_mut()
            .zip(&self.pixels)
            .map(|(st, px)| st.update(px, carved, &added, live, lins))
            .collect();
        // The live slots among the added ones, the touched neighbours and the marked owners, in
        // increasing slot order (without a pass over every slot: this runs on one core).
        let mut todo: Vec<u32> = added;
        todo.extend(touched.iter().map(|lin| self.slot_of[lin]));
        todo.extend(marks.into_iter().flatten());
        todo.retain(|&s| self.live[s as usize]);
        todo.sort_unstable();
        todo.dedup();
        todo
    }

    /// The live slots' voxels coloured (in increasing linear index), and their re-projection error
    /// in `views` through the views' item buffers (which are those of the live slots).
    fn coloured_surface_with_error(&self, views: &[PhotoView<'_>], params: &PhotoParams) -> (ColouredSurface, f64) {
        let mut slots: Vec<u32> = (0..self.voxels.len() as u32).filter(|&s| self.live[s as usize]).collect();
        slots.sort_unstable_by_key(|&s| self.lins[s as usize]);
        let colours: Vec<([u8; 3], bool)> = slots
            .par_iter()
            .map(|&s| {
                let v = self.voxels[s as usize];
                let samples = colour_samples(&self.cams, &self.pixels, &self.states, v, s, self.normal(v), params);
                (surface_colour(&samples), !samples.is_empty())
            })
            .collect();
        // Colours by slot, for the item buffers (dead slots own no pixel).
        let mut by_slot = vec![[0u8; 3]; self.voxels.len()];
        for (&s, c) in slots.iter().zip(&colours) {
            by_slot[s as usize] = c.0;
        }
        let ids: Vec<&[u32]> = self.states.iter().map(|st| st.id.as_slice()).collect();
        let error = super::reprojection_error_in(&by_slot, views, &ids);
        let surface = ColouredSurface {
            voxels: slots.iter().map(|&s| self.voxels[s as usize]).collect(),
            colours: colours.iter().map(|c| c.0).collect(),
            seen: colours.iter().map(|c| c.1).collect(),
        };
        (surface, error)
    }
}

/// The colour spread between views (see `photo_consistency::colour_spread`) of every surface voxel
/// of `start` that at least `params.min_views` views see, under item buffers of that surface; and
/// that surface coloured as `super::colour_surface` colours it, with its re-projection error in
/// `views` (the same item buffers, so the same figures).
pub(super) fn surface_spreads(
    c: &Carver<'_>,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> (Vec<f32>, ColouredSurface, f64) {
    let per_voxel: Vec<([u8; 3], bool, Option<f32>)> = (0..c.voxels.len() as u32)
        .into_par_iter()
        .map(|s| {
            let v = c.voxels[s as usize];
            let samples = colour_samples(&c.cams, &c.pixels, &c.states, v, s, c.normal(v), params);
            let spread = (samples.len() >= params.min_views).then(|| colour_spread(&samples));
            (surface_colour(&samples), !samples.is_empty(), spread)
        })
        .collect();
    let spreads = per_voxel.iter().filter_map(|p| p.2).collect();
    // Slots were handed out in surface order (increasing linear index) and none is dead, so slot
    // numbers are indices into the surface and the view states' buffers are its item buffers.
    let surface = ColouredSurface {
        voxels: c.voxels.clone(),
        colours: per_voxel.iter().map(|p| p.0).collect(),
        seen: per_voxel.iter().map(|p| p.1).collect(),
    };
    let ids: Vec<&[u32]> = c.states.iter().map(|st| st.id.as_slice()).collect();
    let error = super::reprojection_error_in(&surface.colours, views, &ids);
    (spreads, surface, error)
}

/// See [`super::carve_photo`].
pub(super) fn carve(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    let t = std::time::Instant::now();
    let c = Carver::checked(start, views, params, true)?;
    Ok(carve_from(c, start, views, params, t))
}

/// [`carve`] from `c`, the untouched state of `start` in `views` (inputs checked, also with
/// `params`); the model's `seconds` count from `t`.
pub(super) fn carve_from(
    mut c: Carver<'_>,
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
    t: std::time::Instant,
) -> PhotoModel {
    let grid: VoxelGrid = *start.grid();
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
    let seen = SeenBy { ids: c.states.iter().map(|st| st.id.as_slice()).collect(), voxels: &c.voxels };
    // The start's boundary is its surface: the first slots.
    let start_boundary = &c.voxels[..c.start_slots];
    let restored = restore_silhouettes(start, start_boundary, &mut c.dense, views, Some(seen));
    stats.carved -= restored;
    let occupancy = c.dense.to_occupancy(grid);
    let (surface, reprojection_error) = if restored == 0 {
        // The item buffers are still those of the result's surface.
        c.coloured_surface_with_error(views, params)
    } else {
        super::colour_dense_with_error(&c.dense, &c.cams, &c.pixels, views, params)
    };
    stats.seconds = t.elapsed().as_secs_f64();
    PhotoModel { occupancy, surface, stats, reprojection_error }
}
