//! Shape and colour from photo-consistency: voxel colouring with the ordinal visibility constraint
//! (Seitz & Dyer 1999) and generalized space carving (Kutulakos & Seitz 2000), both starting from a
//! given occupancy (the visual hull when silhouettes exist, else a full grid). The consistency test,
//! footprints and item buffers are in [`super::photo_consistency`].
//!
//! # Generalized space carving ([`carve_photo`])
//! Any camera placement. Each iteration judges surface voxels against every view through item
//! buffers of the whole current surface (per pixel the nearest surface voxel, see
//! [`super::photo_consistency`]) and carves every inconsistent one at once; iterations repeat until
//! one carves nothing (or `max_iterations`): generalized voxel colouring with item buffers
//! (Culbertson, Malzbender & Slabaugh 1999). It works on the surface only and incrementally
//! (`incremental.rs`): every footprint is projected once, when its voxel reaches the surface; the
//! item buffers are updated, not re-rendered, as voxels go (only pixels the carved voxels owned are
//! redrawn, from the surface voxels whose footprints meet them, plus the newly exposed voxels); and
//! an iteration judges only the voxels whose inputs changed (newly exposed, a carved 26-neighbour,
//! or a pixel that changed hands), since every other voxel would get the verdict it got before.
//! Empty and interior voxels are never visited. The result is voxel for voxel the result of
//! [`carve_photo_surface`], which re-renders and re-judges the whole surface every iteration; the
//! cost is O(surface x views) for the first iteration and O(changed x views) for each one after.
//! The result only ever loses voxels of the start, so with the visual hull as the start it lies
//! inside the hull.
//!
//! Benchmark baselines, kept for `benches/photo.rs` only: [`carve_photo_surface`] (the same result,
//! everything recomputed every iteration) and [`carve_photo_sweeps`], the multi-sweep space carving
//! of Kutulakos & Seitz that `carve_photo` was before. One iteration of the latter is six plane
//! sweeps, along +x, -x, +y, -y, +z and -z; a sweep visits the layers of voxels perpendicular to its
//! axis in order and judges a layer only against the cameras *in front of* it, with per-sweep item
//! buffers grown layer by layer (see `SAMPLE_HALF_EDGE` for its sampling footprint); voxels judged
//! in two or more sweeps are judged again on the union of their views.
//!
//! # Voxel colouring ([`color_voxels`])
//! Cameras all on the near side of a plane in front of the volume: the sweep direction `d` is the
//! unit vector from the cameras' mean centre to the grid's centre, and every camera centre `c` must
//! satisfy `d·c < min over the volume of d·x` (else [`PhotoError::NoOrdinalOrder`]). Then an occluder
//! always has a smaller `d·x` than what it hides, so voxels are visited once, in layers of increasing
//! `d·x` (one voxel thick). A voxel is judged on the pixels of its footprint not yet claimed by a
//! kept voxel of an earlier layer; a consistent voxel claims its footprint when its layer is done,
//! an inconsistent one is carved, and a voxel no longer seen by any view is kept unjudged (the
//! interior). Cost: O(voxels × views), one visit each.
//!
//! # Colours
//! [`colour_surface`] colours the surface voxels of an occupancy from the views that see them (item
//! buffers of the final surface) and face them: the mean of the pixels their centres project into
//! (see `photo_consistency::surface_colour`). [`reprojection_error`] renders such a coloured
//! surface back into the views and measures the photometric error against the images.

use std::collections::HashMap;
use std::time::Instant;

use rayon::prelude::*;

use super::occupancy::Occupancy;
use super::photo_consistency::{
    centre_sample, check_inputs, facing, image_noise_sigma, is_consistent, ncc_pattern, normal_estimate,
    render_item_buffers, surface_colour, Footprint, FootprintSample, ItemBuffer, PhotoError, PhotoNoise, PhotoParams,
    PhotoView, ViewPixels, ViewSample, VoxelCamera,
};
use crate::geometry::round::floor_f32;
use crate::geometry::VoxelGrid;

mod incremental;
mod layered;

/// Surface voxels with colours.
#[derive(Debug, Clone, PartialEq)]
pub struct ColouredSurface {
    /// Surface voxel indices `(i, j, k)`: occupied with an empty or out-of-grid face neighbour.
    pub voxels: Vec<[u32; 3]>,
    /// Their colours, 8-bit RGB ([`super::photo_consistency::UNSEEN_COLOUR`] when no view sees them).
    pub colours: Vec<[u8; 3]>,
    /// Whether some view sees each voxel.
    pub seen: Vec<bool>,
}

/// What a photo-consistency reconstruction did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct PhotoStats {
    /// Iterations (generalized space carving) or layers (voxel colouring).
    pub iterations: usize,
    /// Plane sweeps (the multi-sweep carver: six per iteration; voxel colouring over ordinal sweeps:
    /// one per direction; otherwise 0).
    pub sweeps: usize,
    /// Voxels judged (visits).
    pub visits: u64,
    /// Voxels carved.
    pub carved: u64,
    /// Wall-clock time, seconds.
    pub seconds: f64,
}

/// The result: occupancy and coloured surface.
#[derive(Debug, Clone)]
pub struct PhotoModel {
    /// The carved occupancy.
    pub occupancy: Occupancy,
    /// Its coloured surface.
    pub surface: ColouredSurface,
    /// Counters.
    pub stats: PhotoStats,
    /// Photometric re-projection error of `surface` in the views it was made from (see
    /// [`reprojection_error`]), mean absolute difference per channel, 8-bit levels.
    pub reprojection_error: f64,
}

/// Bit of [`Dense::bits`]: the voxel is occupied.
const OCCUPIED: u8 = 1;
/// Bit of [`Dense::bits`]: the voxel is queued (or was judged) in the current sweep.
const QUEUED: u8 = 2;

/// A dense byte occupancy for carving in place ([`OCCUPIED`], [`QUEUED`] bits).
struct Dense {
    dims: [usize; 3],
    bits: Vec<u8>,
}

impl Dense {
    fn from(occ: &Occupancy) -> Dense {
        let dims = occ.grid().dims;
        let mut bits = vec![0u8; dims[0] * dims[1] * dims[2]];
        occ.for_each_occupied(|i, j, k| bits[i + dims[0] * (j + dims[1] * k)] = OCCUPIED);
        Dense { dims, bits }
    }

    #[inline]
    fn get(&self, i: i64, j: i64, k: i64) -> bool {
        let d = self.dims;
        if i < 0 || j < 0 || k < 0 || i >= d[0] as i64 || j >= d[1] as i64 || k >= d[2] as i64 {
            return false;
        }
        self.bits[i as usize + d[0] * (j as usize + d[1] * k as usize)] & OCCUPIED != 0
    }

    #[inline]
    fn index(&self, v: [u32; 3]) -> usize {
        v[0] as usize + self.dims[0] * (v[1] as usize + self.dims[1] * v[2] as usize)
    }

    fn clear(&mut self, v: [u32; 3]) {
        let i = self.index(v);
        self.bits[i] = 0;
    }

    /// Occupied with an empty or out-of-grid face neighbour.
    fn is_surface(&self, v: [u32; 3]) -> bool {
        let (a, b, c) = (v[0] as i64, v[1] as i64, v[2] as i64);
        self.get(a, b, c)
            && !(self.get(a - 1, b, c)
                && self.get(a + 1, b, c)
                && self.get(a, b - 1, c)
                && self.get(a, b + 1, c)
                && self.get(a, b, c - 1)
                && self.get(a, b, c + 1))
    }

    fn surface(&self) -> Vec<[u32; 3]> {
        let d = self.dims;
        (0..d[2])
            .into_par_iter()
            .flat_map_iter(|k| {
                let mut out = Vec::new();
                for j in 0..d[1] {
                    for i in 0..d[0] {
                        let v = [i as u32, j as u32, k as u32];
                        if self.is_surface(v) {
                            out.push(v);
                        }
                    }
                }
                out
            })
            .collect()
    }

    fn to_occupancy(&self, grid: VoxelGrid) -> Occupancy {
        Occupancy::from_index_fn(grid, |i, j, k| self.get(i as i64, j as i64, k as i64))
    }
}

#[allow(clippy::too_many_arguments)] // the loop state of one voxel's visit, kept as plain arguments
/// Per-view samples of surface voxel `idx` under item buffers (views facing below `min_cos` dropped),
/// and NCC patterns when asked for.
fn gather(
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    buffers: &[ItemBuffer],
    v: [u32; 3],
    idx: u32,
    normal: [f32; 3],
    params: &PhotoParams,
    want_ncc: bool,
) -> (Vec<ViewSample>, Vec<[f32; 24]>) {
    let mut samples = Vec::new();
    let mut patterns = Vec::new();
    for ((cam, px), buf) in cams.iter().zip(pixels).zip(buffers) {
        let cos = facing(cam, cam.point(v, [0.0; 3]), normal);
        if cos < params.min_cos {
            continue;
        }
        let Some(fp) = cam.footprint(v) else { continue };
        let visible = |p: usize| buf.at(p) == idx;
        let FootprintSample { count, mean, .. } = px.sample(&fp, visible);
        if count > 0 {
            let centre = centre_sample(cam, px, v, visible);
            samples.push(ViewSample { count, mean, centre });
            if want_ncc {
                if let Some(p) = ncc_pattern(cam, px, v, visible) {
                    patterns.push(p);
                }
            }
        }
    }
    (samples, patterns)
}

/// Generalized space carving from `start` by re-rendering whole-surface item buffers and re-judging
/// every surface voxel every iteration: [`carve_photo`]'s result without its bookkeeping, kept as a
/// benchmark baseline and as the reference its tests compare with (see the module docs).
pub fn carve_photo_surface(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    let t = Instant::now();
    let grid = *start.grid();
    check_inputs(&grid, views, params)?;
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    let pixels = ViewPixels::all(views);
    let mut dense = Dense::from(start);
    let mut stats = PhotoStats::default();
    while stats.iterations < params.max_iterations {
        stats.iterations += 1;
        let surface = dense.surface();
        let buffers = render_item_buffers(&cams, &surface);
        let occ = |i, j, k| dense.get(i, j, k);
        let carve: Vec<[u32; 3]> = surface
            .par_iter()
            .enumerate()
            .filter_map(|(idx, &v)| {
                let on_rim = cams.iter().zip(&pixels).zip(&buffers).any(|((cam, px), buf)| {
                    cam.footprint(v).is_some_and(|fp| px.sample(&fp, |p| buf.at(p) == idx as u32).rim)
                });
                if on_rim {
                    return None;
                }
                let normal = normal_estimate(&occ, v);
                let (samples, patterns) =
                    gather(&cams, &pixels, &buffers, v, idx as u32, normal, params, params.min_ncc.is_some());
                (!is_consistent(&samples, &patterns, params)).then_some(v)
            })
            .collect();
        stats.visits += surface.len() as u64;
        tracing::debug!(iteration = stats.iterations, surface = surface.len(), carved = carve.len(), "photo carving");
        if carve.is_empty() {
            break;
        }
        stats.carved += carve.len() as u64;
        for v in carve {
            dense.clear(v);
        }
    }
    let (restored, surface, reprojection_error) = restore_and_colour(start, &mut dense, &cams, &pixels, views, params);
    stats.carved -= restored;
    let occupancy = dense.to_occupancy(grid);
    stats.seconds = t.elapsed().as_secs_f64();
    Ok(PhotoModel { occupancy, surface, stats, reprojection_error })
}

/// Generalized space carving from `start` on the surface only, incrementally (see the module docs):
/// the voxels [`carve_photo_surface`] carves, at a fraction of its cost.
pub fn carve_photo(start: &Occupancy, views: &[PhotoView<'_>], params: &PhotoParams) -> Result<PhotoModel, PhotoError> {
    incremental::carve(start, views, params)
}

/// The views (index, sample) a kept voxel was judged on in the sweeps of one iteration, and a bit
/// per sweep that judged it.
type SweepRecord = HashMap<usize, (u8, Vec<(u32, ViewSample)>)>;

/// Generalized space carving from `start` by multi-sweep space carving (Kutulakos & Seitz; see the
/// module docs): the implementation [`carve_photo`] replaced, kept as the benchmark baseline.
pub fn carve_photo_sweeps(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    let t = Instant::now();
    let grid = *start.grid();
    check_inputs(&grid, views, params)?;
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    let pixels = ViewPixels::all(views);
    let mut dense = Dense::from(start);
    let mut stats = PhotoStats::default();
    let mut buffers: Vec<SweepBuffer> = cams.iter().map(SweepBuffer::new).collect();
    while stats.iterations < params.max_iterations {
        stats.iterations += 1;
        let mut record = SweepRecord::new();
        let mut carved = 0u64;
        for (n, (axis, forward)) in
            [(0, true), (0, false), (1, true), (1, false), (2, true), (2, false)].into_iter().enumerate()
        {
            let sweep = Sweep { axis, forward, id: n as u8 };
            let c = sweep.run(&mut dense, &grid, &cams, &pixels, params, &mut buffers, &mut record, &mut stats);
            tracing::debug!(iteration = stats.iterations, axis, forward, carved = c, "photo carving: sweep");
            carved += c;
            stats.sweeps += 1;
        }
        // Voxels judged in several sweeps: judged again on the union of their views.
        let multi: Vec<(usize, Vec<ViewSample>)> = record
            .into_iter()
            .filter(|(_, (sweeps, _))| sweeps.count_ones() >= 2)
            .map(|(i, (_, s))| (i, s.into_iter().map(|(_, s)| s).collect()))
            .collect();
        let dims = dense.dims;
        let at = |i: usize| [i % dims[0], i / dims[0] % dims[1], i / (dims[0] * dims[1])].map(|x| x as u32);
        let reject: Vec<[u32; 3]> = multi
            .par_iter()
            .filter(|(i, samples)| dense.is_surface(at(*i)) && !is_consistent(samples, &[], params))
            .map(|(i, _)| at(*i))
            .collect();
        stats.visits += multi.len() as u64;
        tracing::debug!(
            iteration = stats.iterations,
            judged = multi.len(),
            carved = reject.len(),
            "photo carving: all views"
        );
        carved += reject.len() as u64;
        for v in reject {
            dense.clear(v);
        }
        stats.carved += carved;
        tracing::debug!(iteration = stats.iterations, carved, "photo carving: six sweeps");
        if carved == 0 {
            break;
        }
    }
    let occupancy = dense.to_occupancy(grid);
    let (surface, reprojection_error) = colour_dense_with_error(&dense, &cams, &pixels, views, params);
    stats.seconds = t.elapsed().as_secs_f64();
    Ok(PhotoModel { occupancy, surface, stats, reprojection_error })
}

/// One plane sweep of [`carve_photo_sweeps`]: along grid axis `axis` (0 = x), towards increasing index when
/// `forward`; `id` (0..6) marks the voxels it judged in a [`SweepRecord`].
struct Sweep {
    axis: usize,
    forward: bool,
    id: u8,
}

impl Sweep {
    /// Run the sweep over `dense`, returning the number of voxels carved.
    #[allow(clippy::too_many_arguments)] // the sweep's inputs and the two accumulators it updates
    fn run(
        &self,
        dense: &mut Dense,
        grid: &VoxelGrid,
        cams: &[VoxelCamera],
        pixels: &[ViewPixels<'_>],
        params: &PhotoParams,
        buffers: &mut [SweepBuffer],
        record: &mut SweepRecord,
        stats: &mut PhotoStats,
    ) -> u64 {
        let axis = self.axis;
        let n = dense.dims[axis];
        // The current surface, bucketed by layer; QUEUED marks voxels this sweep has taken up.
        let mut buckets: Vec<Vec<[u32; 3]>> = vec![Vec::new(); n];
        for v in dense.surface() {
            let i = dense.index(v);
            dense.bits[i] |= QUEUED;
            buckets[v[axis] as usize].push(v);
        }
        buffers.par_iter_mut().for_each(|b| b.claimed.fill(f32::INFINITY));
        let later = |a: usize, b: usize| if self.forward { a > b } else { a < b };
        let order: Vec<usize> = if self.forward { (0..n).collect() } else { (0..n).rev().collect() };
        let mut carved = 0u64;
        for layer in order {
            // The layer's near face, and the cameras strictly in front of it.
            let face = grid.origin[axis] + (layer + usize::from(!self.forward)) as f64 * grid.voxel_size;
            let active: Vec<bool> = cams
                .iter()
                .map(|c| {
                    let x = c.centre[axis] as f64;
                    if self.forward {
                        x < face
                    } else {
                        x > face
                    }
                })
                .collect();
            let mut pass = std::mem::take(&mut buckets[layer]);
            let mut kept: Vec<[u32; 3]> = Vec::new();
            while !pass.is_empty() {
                // Item buffers of the layer (its kept voxels and this pass's), for occlusion inside it.
                let first = kept.len();
                kept.extend_from_slice(&pass);
                buffers.par_iter_mut().zip(cams).zip(&active).filter(|(_, &a)| a).for_each(|((b, cam), _)| {
                    b.render_layer(cam, &kept);
                });
                kept.truncate(first);
                let verdicts: Vec<(bool, Vec<(u32, ViewSample)>)> = {
                    let dense = &*dense;
                    let buffers = &*buffers;
                    let active = &active;
                    pass.par_iter()
                        .enumerate()
                        .map(|(n, &v)| judge(dense, cams, pixels, buffers, active, v, (first + n) as u32, params))
                        .collect()
                };
                stats.visits += pass.len() as u64;
                let mut next = Vec::new();
                for (&v, (ok, samples)) in pass.iter().zip(verdicts) {
                    if ok {
                        kept.push(v);
                        if !samples.is_empty() {
                            merge(record.entry(dense.index(v)).or_default(), self.id, samples);
                        }
                        continue;
                    }
                    dense.clear(v);
                    carved += 1;
                    for (a, d) in [(0, -1i64), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1)] {
                        let mut u = v.map(|x| x as i64);
                        u[a] += d;
                        if u.iter().zip(&dense.dims).any(|(&x, &m)| x < 0 || x >= m as i64) {
                            continue;
                        }
                        let u = u.map(|x| x as u32);
                        let i = dense.index(u);
                        if dense.bits[i] != OCCUPIED {
                            continue; // empty, or already taken up by this sweep
                        }
                        let ul = u[axis] as usize;
                        if ul == layer {
                            dense.bits[i] |= QUEUED;
                            next.push(u);
                        } else if later(ul, layer) {
                            dense.bits[i] |= QUEUED;
                            buckets[ul].push(u);
                        } // an earlier layer: the next sweep finds it on the surface
                    }
                }
                pass = next;
            }
            // The layer's kept voxels claim their footprints in the cameras in front of it.
            buffers.par_iter_mut().zip(cams).zip(&active).filter(|(_, &a)| a).for_each(|((b, cam), _)| {
                for &v in &kept {
                    b.claim(cam, v);
                }
            });
        }
        for b in dense.bits.iter_mut() {
            *b &= OCCUPIED;
        }
        carved
    }
}

/// Add one sweep's samples of a voxel to its record: one sample per view, the one with more pixels.
fn merge(entry: &mut (u8, Vec<(u32, ViewSample)>), sweep: u8, samples: Vec<(u32, ViewSample)>) {
    entry.0 |= 1 << sweep;
    for (view, s) in samples {
        match entry.1.iter_mut().find(|(w, _)| *w == view) {
            Some((_, old)) if old.count < s.count => *old = s,
            Some(_) => {}
            None => entry.1.push((view, s)),
        }
    }
}

/// One camera's visibility state in a sweep: per pixel, the nearest camera depth (metres) of the kept
/// voxels of earlier layers whose footprints cover it (an item buffer grown layer by layer; infinity
/// where none does), and an item buffer of the current layer's voxels (valid where `stamp` is the
/// current pass's).
struct SweepBuffer {
    claimed: Vec<f32>,
    stamp: Vec<u32>,
    depth: Vec<f32>,
    id: Vec<u32>,
    pass: u32,
}

impl SweepBuffer {
    fn new(cam: &VoxelCamera) -> SweepBuffer {
        let n = cam.width * cam.height;
        SweepBuffer { claimed: vec![f32::INFINITY; n], stamp: vec![0; n], depth: vec![0.0; n], id: vec![0; n], pass: 0 }
    }

    /// Render the item buffer of `voxels` (one layer) over the pixels earlier layers leave visible:
    /// each pixel names the nearest voxel (camera depth of its centre) whose footprint covers it.
    fn render_layer(&mut self, cam: &VoxelCamera, voxels: &[[u32; 3]]) {
        self.pass = self.pass.wrapping_add(1);
        if self.pass == 0 {
            self.stamp.fill(0);
            self.pass = 1;
        }
        for (idx, &v) in voxels.iter().enumerate() {
            let Some(fp) = cam.footprint(v) else { continue };
            for y in fp.y0..fp.y1 {
                for p in y * cam.width + fp.x0..y * cam.width + fp.x1 {
                    if fp.depth < self.claimed[p] && (self.stamp[p] != self.pass || fp.depth < self.depth[p]) {
                        self.stamp[p] = self.pass;
                        self.depth[p] = fp.depth;
                        self.id[p] = idx as u32;
                    }
                }
            }
        }
    }

    /// Voxel `v` (kept in its layer) joins the earlier layers' item buffer.
    fn claim(&mut self, cam: &VoxelCamera, v: [u32; 3]) {
        if let Some(fp) = cam.footprint(v) {
            for y in fp.y0..fp.y1 {
                for c in &mut self.claimed[y * cam.width + fp.x0..y * cam.width + fp.x1] {
                    *c = c.min(fp.depth);
                }
            }
        }
    }

    /// True when the current layer's item buffer names voxel `idx` in pixel `p` (so no earlier layer
    /// covers it nearer).
    #[inline]
    fn owns(&self, p: usize, idx: u32) -> bool {
        self.stamp[p] == self.pass && self.id[p] == idx
    }
}

/// Half-edge (voxel units) of the central cube whose footprint a sweep samples: the full voxel's
/// footprint rectangle reaches into its neighbours, and a sweep hands the pixels it shares with
/// neighbours of later layers to the voxel, which biases the sample towards them differently in each
/// view (on the bench's textured sphere at 64^3 a full-voxel sample let the downward sweep tunnel
/// through the whole sphere, containment 0.002; the central half-cube: 0.965 at 64^3, 0.999 at
/// 128^3). Item buffers still use full footprints.
const SAMPLE_HALF_EDGE: f32 = 0.25;

/// Judge voxel `v` (number `idx` in its layer's item buffers) against the `active` views on the
/// pixels it owns: (consistent, the samples with their view indices).
#[allow(clippy::too_many_arguments)] // one voxel's visit, kept as plain arguments
fn judge(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    buffers: &[SweepBuffer],
    active: &[bool],
    v: [u32; 3],
    idx: u32,
    params: &PhotoParams,
) -> (bool, Vec<(u32, ViewSample)>) {
    let normal = normal_estimate(&|i, j, k| dense.get(i, j, k), v);
    let mut samples = Vec::new();
    let mut patterns = Vec::new();
    for (n, ((cam, px), buf)) in cams.iter().zip(pixels).zip(buffers).enumerate() {
        if !active[n] {
            continue;
        }
        let cos = facing(cam, cam.point(v, [0.0; 3]), normal);
        if cos < params.min_cos {
            continue;
        }
        let Some(fp) = cam.footprint_of_cube(v, SAMPLE_HALF_EDGE) else { continue };
        let visible = |p: usize| buf.owns(p, idx);
        let FootprintSample { count, mean, .. } = px.sample(&fp, visible);
        if count > 0 {
            samples.push((n as u32, ViewSample { count, mean, centre: None }));
            if params.min_ncc.is_some() {
                if let Some(p) = ncc_pattern(cam, px, v, visible) {
                    patterns.push(p);
                }
            }
        }
    }
    let plain: Vec<ViewSample> = samples.iter().map(|s| s.1).collect();
    (is_consistent(&plain, &patterns, params), samples)
}

/// The voxel colouring sweep direction for these cameras, checked against the ordinal visibility
/// constraint (see the module docs): a unit vector, grid frame.
pub fn ordinal_direction(grid: &VoxelGrid, views: &[PhotoView<'_>]) -> Result<[f64; 3], PhotoError> {
    let b = grid.bbox();
    let centre = nalgebra::Vector3::from([0, 1, 2].map(|a| 0.5 * (b.min[a] + b.max[a])));
    let mean = views.iter().map(|v| v.camera.centre()).sum::<nalgebra::Vector3<f64>>() / views.len().max(1) as f64;
    let d = (centre - mean).try_normalize(1e-12).unwrap_or_else(nalgebra::Vector3::z);
    let near = b.corners().iter().map(|c| d.dot(c)).fold(f64::INFINITY, f64::min);
    for (n, v) in views.iter().enumerate() {
        if d.dot(&v.camera.centre()) >= near {
            return Err(PhotoError::NoOrdinalOrder { view: n, direction: [d.x, d.y, d.z] });
        }
    }
    Ok([d.x, d.y, d.z])
}

/// Voxel colouring's verdict on voxel `v` against the pixels of its footprints not yet `claimed`:
/// `Some(true)` consistent and seen, `Some(false)` inconsistent, `None` seen by no view.
fn colouring_verdict(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    claimed: &[Vec<bool>],
    v: [u32; 3],
    params: &PhotoParams,
) -> Option<bool> {
    colouring_verdict_in(dense, cams, pixels, claimed, v, params, 0..cams.len(), |_, _| {})
}

/// [`colouring_verdict`] consulting only `views` (increasing indices): the same verdict whenever
/// every view left out has none of `v`'s footprint pixels both unclaimed and inside its silhouette
/// (such a view contributes no sample and no contour-band pixel). `footprint` is called with each
/// consulted view's index and `v`'s footprint there (views where a corner is behind the camera
/// have none), in the order of `views`; not at all when none of `views` faces `v` (cosine below
/// `params.min_cos`), whose verdict is then `None` whatever the pixels.
#[allow(clippy::too_many_arguments)] // one voxel's visit, kept as plain arguments
fn colouring_verdict_in(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    claimed: &[Vec<bool>],
    v: [u32; 3],
    params: &PhotoParams,
    views: impl Iterator<Item = usize> + Clone,
    mut footprint: impl FnMut(usize, &Footprint),
) -> Option<bool> {
    let normal = normal_estimate(&|i, j, k| dense.get(i, j, k), v);
    // Only a view facing the voxel gives a sample: without one the verdict is `None` whatever the
    // pixels, and no footprint is needed (a voxel whose normal points away from every view of a
    // sweep is common: the far side of the object).
    if !views.clone().any(|n| facing(&cams[n], cams[n].point(v, [0.0; 3]), normal) >= params.min_cos) {
        return None;
    }
    let mut samples = Vec::new();
    let mut patterns = Vec::new();
    let mut rim = false;
    for n in views {
        let (cam, px, marks) = (&cams[n], &pixels[n], &claimed[n]);
        let Some(fp) = cam.footprint(v) else { continue };
        footprint(n, &fp);
        let visible = |p: usize| !marks[p];
        let FootprintSample { count, mean, rim: on_rim } = px.sample(&fp, visible);
        rim |= on_rim;
        if count > 0 && facing(cam, cam.point(v, [0.0; 3]), normal) >= params.min_cos {
            samples.push(ViewSample { count, mean, centre: None });
            if params.min_ncc.is_some() {
                if let Some(p) = ncc_pattern(cam, px, v, visible) {
                    patterns.push(p);
                }
            }
        }
    }
    if samples.is_empty() {
        None
    } else {
        // A voxel on a silhouette's outline is kept (and claims its pixels) whatever its colours.
        Some(rim || is_consistent(&samples, &patterns, params))
    }
}

/// A consistent voxel `v` claims its footprints.
fn claim(cams: &[VoxelCamera], claimed: &mut [Vec<bool>], v: [u32; 3]) {
    for (cam, marks) in cams.iter().zip(claimed.iter_mut()) {
        if let Some(fp) = cam.footprint(v) {
            claim_rect(cam.width, marks, [fp.x0, fp.x1, fp.y0, fp.y1]);
        }
    }
}

/// Claim the pixel rectangle `[x0, x1) x [y0, y1)` in one view (`marks`: that view's claimed
/// pixels, row-major, `width` pixels a row).
fn claim_rect(width: usize, marks: &mut [bool], [x0, x1, y0, y1]: [usize; 4]) {
    for y in y0..y1 {
        marks[y * width + x0..y * width + x1].fill(true);
    }
}

/// Voxel colouring with the ordinal visibility constraint from `start`, on the surface only (see
/// the module docs): the voxels [`color_voxels_every_voxel`] carves.
pub fn color_voxels(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    layered::color(start, views, params)
}

/// One voxel colouring sweep of [`color_voxels_sweeps`]: a direction and the views that satisfy the
/// ordinal visibility constraint along it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OrdinalSweep {
    /// Sweep direction, unit vector, grid frame.
    pub direction: [f64; 3],
    /// Indices of the views in front of the working volume along it.
    pub views: Vec<usize>,
}

/// Sweeps that let voxel colouring use views all around the object: candidate directions are the
/// directions from each camera centre to the grid's centre; along a direction `d` the views whose
/// centre `c` has `d·c` below the volume's smallest `d·x` satisfy the ordinal visibility constraint.
/// Directions are chosen greedily, each adding the most views no chosen sweep has (ties: the
/// larger set), until every view that some direction admits is in a sweep; sweeps with fewer than
/// `min_views` views are left out.
pub fn ordinal_sweeps(grid: &VoxelGrid, views: &[PhotoView<'_>], min_views: usize) -> Vec<OrdinalSweep> {
    let b = grid.bbox();
    let centre = nalgebra::Vector3::from([0, 1, 2].map(|a| 0.5 * (b.min[a] + b.max[a])));
    let corners = b.corners();
    let candidates: Vec<(nalgebra::Vector3<f64>, Vec<usize>)> = views
        .iter()
        .filter_map(|v| (centre - v.camera.centre()).try_normalize(1e-12))
        .map(|d| {
            let near = corners.iter().map(|c| d.dot(c)).fold(f64::INFINITY, f64::min);
            let admitted = (0..views.len()).filter(|&n| d.dot(&views[n].camera.centre()) < near).collect();
            (d, admitted)
        })
        .filter(|(_, s): &(_, Vec<usize>)| s.len() >= min_views)
        .collect();
    let mut covered = vec![false; views.len()];
    let mut out = Vec::new();
    loop {
        let best = candidates
            .iter()
            .map(|(d, s)| (s.iter().filter(|&&n| !covered[n]).count(), s.len(), d, s))
            .filter(|c| c.0 > 0)
            .max_by_key(|c| (c.0, c.1));
        let Some((_, _, d, s)) = best else { break };
        for &n in s {
            covered[n] = true;
        }
        out.push(OrdinalSweep { direction: [d.x, d.y, d.z], views: s.clone() });
    }
    out
}

/// Voxel colouring with views all around: one [`color_voxels`] sweep per [`ordinal_sweeps`] entry,
/// each from the previous one's result with the views that satisfy the ordinal visibility
/// constraint along its direction; the result is coloured from every view. Counters add up over
/// the sweeps (`sweeps` counts them). [`PhotoError::NoOrdinalOrder`] when no direction admits
/// `min_views` views.
pub fn color_voxels_sweeps(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    let t = Instant::now();
    let grid = *start.grid();
    check_inputs(&grid, views, params)?;
    let sweeps = ordinal_sweeps(&grid, views, params.min_views);
    if sweeps.is_empty() {
        let d = ordinal_direction(&grid, views).err();
        return Err(d.unwrap_or(PhotoError::NoOrdinalOrder { view: 0, direction: [0.0; 3] }));
    }
    // Each view's pixels are classified once, for every sweep it is in and the colouring.
    let pixels = ViewPixels::all(views);
    let mut occupancy = start.clone();
    let mut stats = PhotoStats::default();
    for sweep in &sweeps {
        let used: Vec<PhotoView<'_>> = sweep.views.iter().map(|&n| views[n]).collect();
        let used_pixels: Vec<ViewPixels<'_>> = sweep.views.iter().map(|&n| pixels[n].clone()).collect();
        let (mut dense, mut s) = layered::color_along(&occupancy, &used, &used_pixels, params, sweep.direction);
        s.carved -= restore_silhouettes(&occupancy, &occupancy.boundary_voxels(), &mut dense, &used, None);
        tracing::debug!(direction = ?sweep.direction, views = used.len(), carved = s.carved, "voxel colouring sweep");
        stats.iterations += s.iterations;
        stats.visits += s.visits;
        stats.carved += s.carved;
        stats.sweeps += 1;
        occupancy = dense.to_occupancy(grid);
    }
    let mut dense = Dense::from(&occupancy);
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    let (restored, surface, reprojection_error) = restore_and_colour(start, &mut dense, &cams, &pixels, views, params);
    stats.carved -= restored;
    let occupancy = dense.to_occupancy(grid);
    stats.seconds = t.elapsed().as_secs_f64();
    Ok(PhotoModel { occupancy, surface, stats, reprojection_error })
}

/// The measured noise of `views` for photo-consistency from `start` (the visual hull): the image
/// noise of each view ([`super::photo_consistency::image_noise_sigma`]) and the distribution of the
/// colour spread over the start's surface voxels that `params.min_views` views see (item-buffer
/// visibility, views facing below `params.min_cos` left out, as the carvers judge). Use it through
/// [`PhotoParams::with_measured_noise`].
pub fn measure_noise(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoNoise, PhotoError> {
    measure_noise_and_colour(start, views, params).map(|m| m.0)
}

/// [`measure_noise`], with the start's surface coloured as [`colour_surface`] colours it and that
/// surface's [`reprojection_error`] in `views`: the noise is measured through the same item buffers
/// and per-view samples, so the colours and the error come at little extra cost.
pub fn measure_noise_and_colour(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<(PhotoNoise, ColouredSurface, f64), PhotoError> {
    measured_start(start, views, params, false).map(|(_, noise, surface, error)| (noise, surface, error))
}

/// The carver's state of `start` (checked against `views` and `params`), with the noise, the
/// colouring of the start's surface and its re-projection error measured through it: the shared
/// first step of [`measure_noise_and_colour`] and [`carve_photo_measured`]; `carving` as
/// `incremental::Carver::checked` takes it (only a state that will be carved needs its tiles).
fn measured_start<'a>(
    start: &Occupancy,
    views: &'a [PhotoView<'a>],
    params: &PhotoParams,
    carving: bool,
) -> Result<(incremental::Carver<'a>, PhotoNoise, ColouredSurface, f64), PhotoError> {
    let c = incremental::Carver::checked(start, views, params, carving)?;
    let (spreads, surface, error) = incremental::surface_spreads(&c, views, params);
    Ok((c, noise_of(views, spreads), surface, error))
}

/// Generalized space carving ([`carve_photo`]) with the threshold measured on `start` first:
/// [`measure_noise_and_colour`], then [`carve_photo`] with `params.with_measured_noise`, giving
/// the same noise, colouring of the start, error and model as those two calls, with the carver's
/// state of the start (its surface's footprints, item buffers and samples in every view) built
/// once for both. The model's `seconds` count from the start of the measurement.
pub fn carve_photo_measured(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<(PhotoNoise, ColouredSurface, f64, PhotoModel), PhotoError> {
    let t = Instant::now();
    let (c, noise, surface, error) = measured_start(start, views, params, true)?;
    let measured = params.with_measured_noise(&noise);
    check_inputs(start.grid(), views, &measured)?;
    let model = incremental::carve_from(c, start, views, &measured, t);
    Ok((noise, surface, error, model))
}

/// The noise of `views` from the colour spreads of the start's surface voxels (see
/// [`measure_noise`]).
fn noise_of(views: &[PhotoView<'_>], mut spreads: Vec<f32>) -> PhotoNoise {
    let median = |x: &mut Vec<f32>| {
        if x.is_empty() {
            return 0.0;
        }
        x.sort_unstable_by(f32::total_cmp);
        x[x.len() / 2]
    };
    let mut sigmas: Vec<f32> = views.iter().filter_map(image_noise_sigma).collect();
    let image_sigma = median(&mut sigmas);
    let voxels = spreads.len();
    let spread_median = median(&mut spreads);
    let mut dev: Vec<f32> = spreads.iter().map(|s| (s - spread_median).abs()).collect();
    let spread_mad = median(&mut dev);
    PhotoNoise { image_sigma, spread_median, spread_mad, voxels }
}

/// Voxel colouring with the ordinal visibility constraint from `start`, visiting every voxel of the
/// start (see the module docs): what [`color_voxels`] was before, kept as its benchmark baseline
/// and test reference.
pub fn color_voxels_every_voxel(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    let t = Instant::now();
    let grid = *start.grid();
    check_inputs(&grid, views, params)?;
    let d = ordinal_direction(&grid, views)?.map(|x| x as f32);
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    let pixels = ViewPixels::all(views);
    let mut dense = Dense::from(start);

    // Layers of increasing d·x, one voxel thick.
    let mut voxels: Vec<(i32, [u32; 3])> = Vec::new();
    start.for_each_occupied(|i, j, k| {
        let key = floor_f32(d[0] * i as f32 + d[1] * j as f32 + d[2] * k as f32) as i32;
        voxels.push((key, [i as u32, j as u32, k as u32]));
    });
    voxels.sort_unstable_by_key(|&(key, v)| (key, v[2], v[1], v[0]));
    let mut claimed: Vec<Vec<bool>> = cams.iter().map(|c| vec![false; c.width * c.height]).collect();
    let mut stats = PhotoStats::default();
    let mut start_idx = 0;
    while start_idx < voxels.len() {
        let key = voxels[start_idx].0;
        let end = start_idx + voxels[start_idx..].iter().take_while(|(k, _)| *k == key).count();
        let layer = &voxels[start_idx..end];
        stats.iterations += 1;
        // Verdicts: Some(true) consistent and seen, Some(false) carved, None unseen.
        let verdicts: Vec<Option<bool>> =
            layer.par_iter().map(|&(_, v)| colouring_verdict(&dense, &cams, &pixels, &claimed, v, params)).collect();
        stats.visits += layer.len() as u64;
        for (&(_, v), verdict) in layer.iter().zip(&verdicts) {
            match verdict {
                Some(false) => {
                    dense.clear(v);
                    stats.carved += 1;
                }
                Some(true) => claim(&cams, &mut claimed, v),
                None => {}
            }
        }
        start_idx = end;
    }
    let (restored, surface, reprojection_error) = restore_and_colour(start, &mut dense, &cams, &pixels, views, params);
    stats.carved -= restored;
    let occupancy = dense.to_occupancy(grid);
    stats.seconds = t.elapsed().as_secs_f64();
    Ok(PhotoModel { occupancy, surface, stats, reprojection_error })
}

/// What a carver knows of its result's surface in each view: per pixel (row-major) the surface
/// voxel seen there, as an index into `voxels` or [`ItemBuffer::NONE`]; `ids` follows the views.
pub(super) struct SeenBy<'a> {
    pub(super) ids: Vec<&'a [u32]>,
    pub(super) voxels: &'a [[u32; 3]],
}

/// Give back carved voxels of `start` where the result's silhouette lost pixels: in each view with
/// a mask, the pixels inside it that the start's re-projection covers and the result's does not
/// (both splatted from their surface voxels as [`super::space_carving::reproject`] does, in `f32`:
/// `VoxelCamera::cover`); every carved voxel whose footprint, slightly grown, meets such a pixel is
/// restored, until no pixel is lost (at most four rounds). Since the start's coverage of those
/// pixels came from its boundary voxels, which are either still there or restored, the result's
/// silhouettes then cover every in-mask pixel the start's did, and cover nothing the start's did
/// not: its re-projection IoU is at least the start's. Returns the voxels restored.
///
/// Only the start's boundary voxels that were carved can lose pixels: one still occupied is still
/// on the boundary (carving only empties its neighbours) and covers what it covered. So only their
/// pixels are candidates, and a candidate covered by the voxel `seen` names there (the result's
/// surface as it is on entry) is not lost; the whole surface is splatted only in the views where
/// a candidate is left. Either way the lost pixels are exactly those above. `start_boundary` lists
/// the start's boundary voxels (`Occupancy::boundary_voxels`, in any order).
fn restore_silhouettes(
    start: &Occupancy,
    start_boundary: &[[u32; 3]],
    dense: &mut Dense,
    views: &[PhotoView<'_>],
    mut seen: Option<SeenBy<'_>>,
) -> u64 {
    let grid = *start.grid();
    let masked: Vec<usize> = (0..views.len()).filter(|&n| views[n].mask.is_some()).collect();
    if masked.is_empty() {
        return 0;
    }
    let cams: Vec<VoxelCamera> = masked.iter().map(|&n| VoxelCamera::new(&views[n].camera, &grid)).collect();
    let mut restored = 0u64;
    for _ in 0..4 {
        let lost = lost_pixels(start_boundary, dense, views, &masked, &cams, seen.as_ref());
        // The surface has changed once a voxel is restored.
        seen = None;
        if lost.iter().all(|l| !l.iter().any(|&b| b)) {
            break;
        }
        let mut carved: Vec<[u32; 3]> = Vec::new();
        start.for_each_occupied(|i, j, k| {
            if !dense.get(i as i64, j as i64, k as i64) {
                carved.push([i as u32, j as u32, k as u32]);
            }
        });
        let back: Vec<[u32; 3]> = carved
            .par_iter()
            .copied()
            .filter(|&v| {
                cams.iter().zip(&lost).any(|(cam, l)| {
                    cam.footprint_of_cube(v, 0.6)
                        .is_some_and(|fp| (fp.y0..fp.y1).any(|y| (fp.x0..fp.x1).any(|x| l[y * cam.width + x])))
                })
            })
            .collect();
        if back.is_empty() {
            break;
        }
        for v in &back {
            let i = dense.index(*v);
            dense.bits[i] |= OCCUPIED;
        }
        restored += back.len() as u64;
    }
    restored
}

/// Per masked view (`masked` indexes `views`, `cams` follows it), per pixel: inside the mask,
/// covered by the start's boundary voxels and not by `dense`'s surface voxels (see
/// [`restore_silhouettes`], which also says why only the carved boundary voxels are splatted and
/// what `seen`, describing `dense`'s surface, saves).
fn lost_pixels(
    start_boundary: &[[u32; 3]],
    dense: &Dense,
    views: &[PhotoView<'_>],
    masked: &[usize],
    cams: &[VoxelCamera],
    seen: Option<&SeenBy<'_>>,
) -> Vec<Vec<bool>> {
    let gone: Vec<[u32; 3]> =
        start_boundary.iter().copied().filter(|v| !dense.get(v[0] as i64, v[1] as i64, v[2] as i64)).collect();
    let mut lost: Vec<Vec<bool>> = masked
        .par_iter()
        .zip(cams)
        .map(|(&n, cam)| {
            let m = views[n].mask.expect("masked views only").data();
            let mut lost = cam.cover(&gone);
            for (l, &m) in lost.iter_mut().zip(m) {
                *l &= m != 0;
            }
            if let Some(seen) = seen {
                for (p, l) in lost.iter_mut().enumerate().filter(|(_, l)| **l) {
                    let s = seen.ids[n][p];
                    if s != ItemBuffer::NONE && cam.covers(seen.voxels[s as usize], p % cam.width, p / cam.width) {
                        *l = false;
                    }
                }
            }
            lost
        })
        .collect();
    if lost.iter().any(|l| l.iter().any(|&b| b)) {
        let boundary = dense.surface();
        lost.par_iter_mut().zip(cams).filter(|(l, _)| l.iter().any(|&b| b)).for_each(|(l, cam)| {
            for (l, now) in l.iter_mut().zip(cam.cover(&boundary)) {
                *l &= !now;
            }
        });
    }
    lost
}

fn colour_dense(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    params: &PhotoParams,
) -> ColouredSurface {
    let voxels = dense.surface();
    let buffers = render_item_buffers(cams, &voxels);
    colour_buffers(dense, cams, pixels, params, voxels, &buffers)
}

/// [`colour_dense`] with `dense`'s surface voxels and their item buffers (by index into `voxels`)
/// given.
fn colour_buffers(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    params: &PhotoParams,
    voxels: Vec<[u32; 3]>,
    buffers: &[ItemBuffer],
) -> ColouredSurface {
    let occ = |i, j, k| dense.get(i, j, k);
    let colours: Vec<([u8; 3], bool)> = voxels
        .par_iter()
        .enumerate()
        .map(|(idx, &v)| {
            let normal = normal_estimate(&occ, v);
            let (samples, _) = gather(cams, pixels, buffers, v, idx as u32, normal, params, false);
            (surface_colour(&samples), !samples.is_empty())
        })
        .collect();
    ColouredSurface {
        voxels,
        colours: colours.iter().map(|c| c.0).collect(),
        seen: colours.iter().map(|c| c.1).collect(),
    }
}

/// [`colour_buffers`] and the coloured surface's re-projection error in `views` through the same
/// item buffers.
fn colour_buffers_with_error(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    views: &[PhotoView<'_>],
    params: &PhotoParams,
    voxels: Vec<[u32; 3]>,
    buffers: &[ItemBuffer],
) -> (ColouredSurface, f64) {
    let surface = colour_buffers(dense, cams, pixels, params, voxels, buffers);
    let ids: Vec<&[u32]> = buffers.iter().map(ItemBuffer::ids).collect();
    let error = reprojection_error_in(&surface.colours, views, &ids);
    (surface, error)
}

/// The coloured surface of `dense` and its re-projection error in `views`, from one set of item
/// buffers.
fn colour_dense_with_error(
    dense: &Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> (ColouredSurface, f64) {
    let voxels = dense.surface();
    let buffers = render_item_buffers(cams, &voxels);
    colour_buffers_with_error(dense, cams, pixels, views, params, voxels, &buffers)
}

/// [`restore_silhouettes`] on `dense` (carved from `start`), then the coloured surface and its
/// re-projection error ([`colour_dense_with_error`]). The item buffers of the carved surface are
/// rendered once: they tell the restoration which pixels that surface still covers, and when
/// nothing is restored they are the colouring's too. Returns the voxels restored as well.
fn restore_and_colour(
    start: &Occupancy,
    dense: &mut Dense,
    cams: &[VoxelCamera],
    pixels: &[ViewPixels<'_>],
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> (u64, ColouredSurface, f64) {
    let voxels = dense.surface();
    let buffers = render_item_buffers(cams, &voxels);
    let seen = SeenBy { ids: buffers.iter().map(ItemBuffer::ids).collect(), voxels: &voxels };
    let restored = restore_silhouettes(start, &start.boundary_voxels(), dense, views, Some(seen));
    let (surface, error) = if restored > 0 {
        colour_dense_with_error(dense, cams, pixels, views, params)
    } else {
        colour_buffers_with_error(dense, cams, pixels, views, params, voxels, &buffers)
    };
    (restored, surface, error)
}

/// Colour the surface of `occupancy` from `views` the way the photo methods colour their results
/// (item-buffer visibility, the mean centre pixel over the views facing the voxel; `params.min_cos`
/// applies).
pub fn colour_surface(
    occupancy: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<ColouredSurface, PhotoError> {
    let grid = *occupancy.grid();
    check_inputs(&grid, views, params)?;
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    Ok(colour_dense(&Dense::from(occupancy), &cams, &ViewPixels::all(views), params))
}

/// Photometric re-projection error of a coloured surface on `grid`: each view's item buffer of the
/// surface voxels, painted with their colours (pixels no voxel covers are black), is compared with
/// the image over the pixels inside the view's mask or covered by the model; the mean absolute
/// difference per channel (8-bit levels) over all such pixels of all views. Views without a mask
/// count covered pixels only.
pub fn reprojection_error(grid: &VoxelGrid, surface: &ColouredSurface, views: &[PhotoView<'_>]) -> f64 {
    mean_error(views.par_iter().map(|view| {
        if view.image.dimensions() != (view.camera.width, view.camera.height) {
            return (0.0, 0);
        }
        let buf = ItemBuffer::render(&VoxelCamera::new(&view.camera, grid), &surface.voxels);
        view_error(&surface.colours, view, buf.ids())
    }))
}

/// [`reprojection_error`] with each view's item buffer of the surface given: `ids[n]` holds, per
/// pixel of view `n` (row-major), the index into `colours` of the colour of the voxel seen there
/// or [`ItemBuffer::NONE`].
fn reprojection_error_in(colours: &[[u8; 3]], views: &[PhotoView<'_>], ids: &[&[u32]]) -> f64 {
    mean_error(views.par_iter().zip(ids).map(|(view, ids)| {
        if view.image.dimensions() != (view.camera.width, view.camera.height) {
            return (0.0, 0);
        }
        view_error(colours, view, ids)
    }))
}

/// The mean of per-view (sum of absolute differences, values) pairs; 0 without values.
fn mean_error(per_view: impl ParallelIterator<Item = (f64, u64)>) -> f64 {
    let (sum, n) = per_view.reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

/// One view's sum of absolute differences (8-bit levels) between its image and the surface painted
/// with `colours` through item buffer `ids` (see [`reprojection_error_in`]), and the number of
/// values summed.
fn view_error(colours: &[[u8; 3]], view: &PhotoView<'_>, ids: &[u32]) -> (f64, u64) {
    let (w, h) = (view.camera.width as usize, view.camera.height as usize);
    let img = view.image.as_raw();
    let (mut sum, mut n) = (0f64, 0u64);
    for y in 0..h {
        for x in 0..w {
            let id = ids.get(y * w + x).copied().unwrap_or(ItemBuffer::NONE);
            let inside = view.mask.is_some_and(|m| m.get(x as u32, y as u32));
            if id == ItemBuffer::NONE && !inside {
                continue;
            }
            let model = colours.get(id as usize).copied().unwrap_or([0, 0, 0]);
            let p = 3 * (y * w + x);
            for c in 0..3 {
                sum += (img[p + c] as f64 - model[c] as f64).abs();
            }
            n += 3;
        }
    }
    (sum, n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, CameraModel, Intrinsics, Pose};
    use image::RgbImage;
    use nalgebra::Vector3;

    const N: u32 = 24;

    fn grid() -> VoxelGrid {
        VoxelGrid::from_resolution(&Aabb { min: [-0.03, -0.03, 0.0], max: [0.03, 0.03, 0.06] }, N)
    }

    /// A block with an open pit from the top; the pit is what silhouettes cannot remove.
    fn in_block(i: usize, j: usize, k: usize) -> bool {
        let r = 4..20;
        r.contains(&i) && r.contains(&j) && (2..18).contains(&k)
    }
    fn in_pit(i: usize, j: usize, k: usize) -> bool {
        (8..16).contains(&i) && (8..16).contains(&j) && (10..18).contains(&k)
    }

    /// Colour by height in bands of two voxels, plus a distinct pit floor.
    fn colour(v: [u32; 3]) -> [u8; 3] {
        if v[2] == 9 && (8..16).contains(&v[0]) && (8..16).contains(&v[1]) {
            return [40, 200, 60];
        }
        if (v[2] / 2) % 2 == 0 {
            [220, 180, 120]
        } else {
            [150, 60, 50]
        }
    }

    fn camera(azimuth_deg: f64, elevation_deg: f64) -> CameraModel {
        let (a, e) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
        let target = Vector3::new(0.0, 0.0, 0.03);
        let eye = target + 0.3 * Vector3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin());
        CameraModel {
            width: 160,
            height: 160,
            intrinsics: Intrinsics {
                fx: 300.0,
                fy: 300.0,
                cx: 80.0,
                cy: 80.0,
                skew: 0.0,
                k1: 0.0,
                k2: 0.0,
                ..Intrinsics::default()
            },
            pose: Pose::look_at(eye, target, Vector3::z()),
        }
    }

    /// Images of the truth: its surface voxels painted through an item buffer.
    fn render(truth: &Occupancy, cams: &[CameraModel]) -> Vec<RgbImage> {
        let g = *truth.grid();
        let voxels = truth.boundary_voxels();
        cams.iter()
            .map(|c| {
                let vc = VoxelCamera::new(c, &g);
                let buf = ItemBuffer::render(&vc, &voxels);
                RgbImage::from_fn(c.width, c.height, |x, y| {
                    let id = buf.get(x as usize, y as usize);
                    image::Rgb(voxels.get(id as usize).map_or([0, 0, 0], |&v| colour(v)))
                })
            })
            .collect()
    }

    fn scene() -> (Occupancy, Occupancy) {
        let truth = Occupancy::from_index_fn(grid(), |i, j, k| in_block(i, j, k) && !in_pit(i, j, k));
        let hull = Occupancy::from_index_fn(grid(), in_block);
        (truth, hull)
    }

    #[test]
    fn space_carving_removes_the_pit_the_hull_keeps_and_colours_the_surface() {
        let (truth, hull) = scene();
        let cams: Vec<CameraModel> = (0..12).map(|n| camera(n as f64 * 30.0, 55.0)).collect();
        let images = render(&truth, &cams);
        let views: Vec<PhotoView<'_>> =
            cams.iter().zip(&images).map(|(c, i)| PhotoView { camera: *c, image: i, mask: None }).collect();
        let params = PhotoParams { threshold: 10.0, min_cos: 0.0, ..PhotoParams::default() };
        let model = carve_photo(&hull, &views, &params).expect("carves");
        let before = hull.iou_and_containment(&truth).expect("same grid");
        let after = model.occupancy.iou_and_containment(&truth).expect("same grid");
        assert!(after.iou > before.iou + 0.02, "IoU {} -> {}", before.iou, after.iou);
        assert!(after.containment >= 0.98, "containment {}", after.containment);
        assert!(model.stats.carved > 0 && model.stats.iterations >= 2);
        // The incremental carver carves exactly what re-judging the whole surface every iteration
        // carves, in as many iterations, and colours the result the same, with fewer visits.
        let base = carve_photo_surface(&hull, &views, &params).expect("carves");
        assert_eq!(model.occupancy.first_difference(&base.occupancy), None);
        assert_eq!(model.surface, base.surface);
        assert_eq!((model.stats.iterations, model.stats.carved), (base.stats.iterations, base.stats.carved));
        assert!(model.stats.visits < base.stats.visits, "{} vs {}", model.stats.visits, base.stats.visits);
        // The multi-sweep baseline reaches a comparable result.
        let sweeps = carve_photo_sweeps(&hull, &views, &params).expect("carves");
        assert_eq!(sweeps.stats.sweeps, 6 * sweeps.stats.iterations, "six plane sweeps per iteration");
        let b = sweeps.occupancy.iou_and_containment(&truth).expect("same grid");
        assert!(
            b.iou > before.iou + 0.02 && b.containment >= 0.98,
            "sweeps IoU {} containment {}",
            b.iou,
            b.containment
        );
        // Seen surface voxels of the truth take their true colour.
        let (mut err, mut n) = (0f64, 0usize);
        for ((v, c), &seen) in model.surface.voxels.iter().zip(&model.surface.colours).zip(&model.surface.seen) {
            if seen && truth.get(v[0] as usize, v[1] as usize, v[2] as usize) {
                let t = colour(*v);
                err += (0..3).map(|ch| (c[ch] as f64 - t[ch] as f64).abs()).sum::<f64>() / 3.0;
                n += 1;
            }
        }
        assert!(n > 100);
        assert!(err / n as f64 <= 20.0, "mean colour error {}", err / n as f64);
        // The coloured result re-projects better than the hull coloured the same way.
        let hull_surface = colour_surface(&hull, &views, &params).expect("colours");
        let e_hull = reprojection_error(&grid(), &hull_surface, &views);
        let e_model = reprojection_error(&grid(), &model.surface, &views);
        assert!(e_model < e_hull, "re-projection {e_model} vs hull {e_hull}");
    }

    #[test]
    fn a_sweep_consults_only_the_cameras_in_front_of_its_layers() {
        let (truth, hull) = scene();
        // Every camera is above the volume's top (z = 0.06 m): the upward sweep has none in front of
        // any layer and cannot carve; the downward sweep has all of them and carves into the pit.
        let cams: Vec<CameraModel> = (0..12).map(|n| camera(n as f64 * 30.0, 55.0)).collect();
        assert!(cams.iter().all(|c| c.centre().z > 0.06));
        let images = render(&truth, &cams);
        let views: Vec<PhotoView<'_>> =
            cams.iter().zip(&images).map(|(c, i)| PhotoView { camera: *c, image: i, mask: None }).collect();
        let params = PhotoParams { threshold: 10.0, min_cos: 0.0, ..PhotoParams::default() };
        let g = grid();
        let vcams: Vec<VoxelCamera> = cams.iter().map(|c| VoxelCamera::new(c, &g)).collect();
        let run = |forward: bool| {
            let mut dense = Dense::from(&hull);
            let mut buffers: Vec<SweepBuffer> = vcams.iter().map(SweepBuffer::new).collect();
            let mut record = SweepRecord::new();
            let mut stats = PhotoStats::default();
            let sweep = Sweep { axis: 2, forward, id: 0 };
            let carved = sweep.run(
                &mut dense,
                &g,
                &vcams,
                &ViewPixels::all(&views),
                &params,
                &mut buffers,
                &mut record,
                &mut stats,
            );
            // Each surface voxel is visited once, plus the ones carving exposed.
            assert!(stats.visits >= hull.boundary_voxels().len() as u64);
            assert!(stats.visits <= hull.boundary_voxels().len() as u64 + carved * 6);
            (carved, record.len())
        };
        let (up, up_judged) = run(true);
        assert_eq!((up, up_judged), (0, 0), "no camera is below any layer");
        let (down, down_judged) = run(false);
        assert!(down > 100, "the downward sweep carves into the pit: {down}");
        assert!(down_judged > 0);
    }

    #[test]
    fn a_colouring_verdict_takes_footprints_only_for_a_voxel_some_view_faces() {
        let (truth, hull) = scene();
        // Every camera looks down from 55 degrees: none faces the block's bottom.
        let cams: Vec<CameraModel> = (0..12).map(|n| camera(n as f64 * 30.0, 55.0)).collect();
        let images = render(&truth, &cams);
        let views: Vec<PhotoView<'_>> =
            cams.iter().zip(&images).map(|(c, i)| PhotoView { camera: *c, image: i, mask: None }).collect();
        let params = PhotoParams { threshold: 10.0, min_cos: 0.4, ..PhotoParams::default() };
        let g = grid();
        let vcams: Vec<VoxelCamera> = cams.iter().map(|c| VoxelCamera::new(c, &g)).collect();
        let pixels = ViewPixels::all(&views);
        let claimed: Vec<Vec<bool>> = vcams.iter().map(|c| vec![false; c.width * c.height]).collect();
        let dense = Dense::from(&hull);
        let verdict = |v: [u32; 3]| {
            let mut footprints = 0;
            let verdict =
                colouring_verdict_in(&dense, &vcams, &pixels, &claimed, v, &params, 0..vcams.len(), |_, _| {
                    footprints += 1
                });
            (verdict, footprints)
        };
        // The middle of the bottom face: its normal points down, away from every view. Left unseen,
        // and not one footprint taken.
        assert_eq!(normal_estimate(&|i, j, k| dense.get(i, j, k), [12, 12, 2]), [0.0, 0.0, -1.0]);
        assert_eq!(verdict([12, 12, 2]), (None, 0));
        // A voxel of the top face beside the pit faces every view: judged, with a footprint in each.
        let (top, footprints) = verdict([5, 12, 17]);
        assert!(top.is_some());
        assert_eq!(footprints, vcams.len());
    }

    #[test]
    fn voxel_colouring_visits_each_voxel_once_from_one_side() {
        let (truth, hull) = scene();
        let cams: Vec<CameraModel> = (0..5).map(|n| camera(-40.0 + n as f64 * 20.0, 55.0)).collect();
        let images = render(&truth, &cams);
        let views: Vec<PhotoView<'_>> =
            cams.iter().zip(&images).map(|(c, i)| PhotoView { camera: *c, image: i, mask: None }).collect();
        let params = PhotoParams { threshold: 10.0, min_cos: 0.0, ..PhotoParams::default() };
        let model = color_voxels(&hull, &views, &params).expect("ordinal order holds");
        let every = color_voxels_every_voxel(&hull, &views, &params).expect("ordinal order holds");
        assert_eq!(every.stats.visits, hull.count());
        // The surface-only sweep: the same voxels and colours, fewer visits.
        assert_eq!(model.occupancy.first_difference(&every.occupancy), None);
        assert_eq!(model.surface, every.surface);
        assert_eq!(model.stats.carved, every.stats.carved);
        assert!(model.stats.visits < hull.count(), "{} visits of {}", model.stats.visits, hull.count());
        let before = hull.iou_and_containment(&truth).expect("same grid");
        let after = model.occupancy.iou_and_containment(&truth).expect("same grid");
        assert!(after.iou > before.iou, "IoU {} -> {}", before.iou, after.iou);
        assert!(after.containment >= 0.98, "containment {}", after.containment);

        // A full ring level with the object has no ordinal order (a ring above the volume's top has:
        // a top-down sweep).
        let ring: Vec<CameraModel> = (0..6).map(|n| camera(n as f64 * 60.0, 0.0)).collect();
        let img = RgbImage::new(160, 160);
        let ring_views: Vec<PhotoView<'_>> =
            ring.iter().map(|c| PhotoView { camera: *c, image: &img, mask: None }).collect();
        assert!(matches!(color_voxels(&hull, &ring_views, &params), Err(PhotoError::NoOrdinalOrder { .. })));
    }

    #[test]
    fn voxel_colouring_through_a_distorting_lens_with_silhouettes_matches_every_voxel() {
        use crate::pipeline::silhouette::Mask;
        let (truth, hull) = scene();
        let cams: Vec<CameraModel> = (0..5)
            .map(|n| {
                let mut c = camera(-40.0 + n as f64 * 20.0, 55.0);
                (c.intrinsics.k1, c.intrinsics.k2, c.intrinsics.p1) = (-0.05, 0.02, 0.002);
                c
            })
            .collect();
        let images = render(&truth, &cams);
        let boundary = truth.boundary_voxels();
        let masks: Vec<Mask> = cams
            .iter()
            .map(|c| {
                let cover = VoxelCamera::new(c, &grid()).cover(&boundary);
                Mask::from_fn(c.width, c.height, |x, y| cover[(y * c.width + x) as usize])
            })
            .collect();
        let views: Vec<PhotoView<'_>> = cams
            .iter()
            .zip(&images)
            .zip(&masks)
            .map(|((c, i), m)| PhotoView { camera: *c, image: i, mask: Some(m) })
            .collect();
        let params = PhotoParams { threshold: 10.0, min_cos: 0.0, ..PhotoParams::default() };
        let model = color_voxels(&hull, &views, &params).expect("ordinal order holds");
        let every = color_voxels_every_voxel(&hull, &views, &params).expect("ordinal order holds");
        assert!(every.stats.carved > 0);
        assert_eq!(model.occupancy.first_difference(&every.occupancy), None);
        assert_eq!(model.surface, every.surface);
        assert_eq!(model.stats.carved, every.stats.carved);
        // Bricks are dropped (or views closed) through the lens too: fewer voxels are visited.
        assert!(model.stats.visits < hull.count(), "{} visits of {}", model.stats.visits, hull.count());
    }

    #[test]
    fn colours_and_errors_from_shared_item_buffers_equal_rendering_them_again() {
        let (truth, hull) = scene();
        let cams: Vec<CameraModel> = (0..5).map(|n| camera(-40.0 + n as f64 * 20.0, 55.0)).collect();
        let images = render(&truth, &cams);
        let views: Vec<PhotoView<'_>> =
            cams.iter().zip(&images).map(|(c, i)| PhotoView { camera: *c, image: i, mask: None }).collect();
        let params = PhotoParams { threshold: 10.0, min_cos: 0.2, ..PhotoParams::default() };
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * b.abs().max(1.0);
        // The noise measurement's colouring of the start is colour_surface's.
        let (noise, surface, error) = measure_noise_and_colour(&hull, &views, &params).expect("measures");
        assert_eq!(noise, measure_noise(&hull, &views, &params).expect("measures"));
        // Measuring and carving on one state gives what the two calls give.
        let (n2, s2, e2, m2) = carve_photo_measured(&hull, &views, &params).expect("measures and carves");
        let m1 = carve_photo(&hull, &views, &params.with_measured_noise(&noise)).expect("carves");
        assert_eq!((n2, &s2, e2.to_bits()), (noise, &surface, error.to_bits()));
        let voxels = |o: &Occupancy| {
            let mut v = Vec::new();
            o.for_each_occupied(|i, j, k| v.push([i, j, k]));
            v
        };
        assert_eq!(voxels(&m2.occupancy), voxels(&m1.occupancy));
        assert!(m1.stats.carved > 0, "the measured threshold carves here");
        assert_eq!(
            (m2.stats.carved, m2.stats.iterations, m2.stats.visits),
            (m1.stats.carved, m1.stats.iterations, m1.stats.visits)
        );
        assert_eq!((&m2.surface, m2.reprojection_error.to_bits()), (&m1.surface, m1.reprojection_error.to_bits()));
        assert_eq!(surface, colour_surface(&hull, &views, &params).expect("colours"));
        assert!(close(error, reprojection_error(&grid(), &surface, &views)), "{error}");
        // Each method's error is its surface's.
        let models = [
            color_voxels(&hull, &views, &params).expect("ordinal order holds"),
            color_voxels_every_voxel(&hull, &views, &params).expect("ordinal order holds"),
            carve_photo(&hull, &views, &params).expect("carves"),
            carve_photo_surface(&hull, &views, &params).expect("carves"),
        ];
        for m in &models {
            assert!(m.stats.carved > 0);
            let want = reprojection_error(&grid(), &m.surface, &views);
            assert!(close(m.reprojection_error, want), "{} vs {want}", m.reprojection_error);
        }
    }

    #[test]
    fn lost_pixels_are_the_starts_cover_the_surface_misses_with_or_without_item_buffers() {
        use crate::pipeline::silhouette::Mask;
        let (_, hull) = scene();
        let g = grid();
        // Near and far cameras: far ones see a voxel as about a pixel, where a footprint and a
        // cover differ most.
        let cams: Vec<CameraModel> = (0..8)
            .map(|n| {
                let mut c = camera(n as f64 * 45.0 + 10.0, 20.0 + 5.0 * n as f64);
                if n % 2 == 1 {
                    c.intrinsics.fx = 110.0;
                    c.intrinsics.fy = 110.0;
                }
                c
            })
            .collect();
        let vcams: Vec<VoxelCamera> = cams.iter().map(|c| VoxelCamera::new(c, &g)).collect();
        let start_boundary = hull.boundary_voxels();
        // Masks: the start's own silhouettes, so every pixel only a carved voxel covered is lost.
        let masks: Vec<Mask> = vcams
            .iter()
            .map(|vc| {
                let cover = vc.cover(&start_boundary);
                Mask::from_fn(160, 160, |x, y| cover[y as usize * 160 + x as usize])
            })
            .collect();
        let images = vec![RgbImage::new(160, 160); cams.len()];
        let views: Vec<PhotoView<'_>> =
            (0..cams.len()).map(|n| PhotoView { camera: cams[n], image: &images[n], mask: Some(&masks[n]) }).collect();
        // The pit carved, and a column and a slanted slice of the block's side.
        let result = Occupancy::from_index_fn(g, |i, j, k| {
            in_block(i, j, k) && !in_pit(i, j, k) && !(i >= 17 && j >= 16) && i + k < 30
        });
        let dense = Dense::from(&result);
        let surface = dense.surface();
        let buffers = render_item_buffers(&vcams, &surface);
        let seen = SeenBy { ids: buffers.iter().map(ItemBuffer::ids).collect(), voxels: &surface };
        let masked: Vec<usize> = (0..views.len()).collect();
        let with = lost_pixels(&start_boundary, &dense, &views, &masked, &vcams, Some(&seen));
        let without = lost_pixels(&start_boundary, &dense, &views, &masked, &vcams, None);
        // Item buffers that name the wrong voxel everywhere save nothing but change nothing either:
        // a pixel counts as covered only when the voxel named there covers it.
        let first = vec![0u32; 160 * 160];
        let wrong = SeenBy { ids: vec![first.as_slice(); cams.len()], voxels: &surface };
        let misled = lost_pixels(&start_boundary, &dense, &views, &masked, &vcams, Some(&wrong));
        let mut lost = 0;
        for (n, cam) in vcams.iter().enumerate() {
            let (before, after) = (cam.cover(&start_boundary), cam.cover(&surface));
            let m = masks[n].data();
            let want: Vec<bool> = (0..before.len()).map(|p| m[p] != 0 && before[p] && !after[p]).collect();
            assert_eq!(with[n], want, "view {n}, with item buffers");
            assert_eq!(without[n], want, "view {n}, without");
            assert_eq!(misled[n], want, "view {n}, with wrong item buffers");
            lost += want.iter().filter(|&&b| b).count();
        }
        assert!(lost > 100, "the carved side loses pixels: {lost}");
        // Restoring gives every one of them back.
        let mut restored = Dense::from(&result);
        assert!(restore_silhouettes(&hull, &start_boundary, &mut restored, &views, Some(seen)) > 0);
        let left = lost_pixels(&start_boundary, &restored, &views, &masked, &vcams, None);
        assert!(left.iter().flatten().all(|&b| !b));
    }

    #[test]
    fn bad_inputs_are_errors_not_panics() {
        let (_, hull) = scene();
        let small = RgbImage::new(10, 10);
        let views = [PhotoView { camera: camera(0.0, 30.0), image: &small, mask: None }];
        let p = PhotoParams::default();
        assert!(matches!(carve_photo(&hull, &views, &p), Err(PhotoError::ImageSize { view: 0, .. })));
        let img = RgbImage::new(160, 160);
        let ok = [PhotoView { camera: camera(0.0, 30.0), image: &img, mask: None }];
        let bad = PhotoParams { min_views: 1, ..p };
        assert!(matches!(carve_photo(&hull, &ok, &bad), Err(PhotoError::BadParams { .. })));
        let mut cam = camera(0.0, 30.0);
        cam.intrinsics.fx = f64::NAN;
        let nan = [PhotoView { camera: cam, image: &img, mask: None }];
        assert!(matches!(carve_photo(&hull, &nan, &p), Err(PhotoError::BadCamera { view: 0 })));
        // No views: nothing to judge, the start is returned.
        let model = carve_photo(&hull, &[], &p).expect("no views");
        assert!(model.occupancy.same_voxels(&hull));
    }
}
