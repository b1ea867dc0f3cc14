//! Surface extraction from an occupancy: a watertight, consistently oriented triangle mesh.
//!
//! The scalar field lives on the lattice of voxel centres, padded by one empty layer on every side so
//! the surface always closes. Its value is the occupancy (0 or 1), optionally box-smoothed over
//! `(2r+1)³` voxels (`smooth_radius = r`); a lattice point is *inside* when its value is above 0.5
//! (`(2r+1)³` is odd, so no value equals it). The surface is the dual of that inside set (a surface
//! net): every lattice edge between an inside and an outside point gets a quad (two triangles) whose
//! corners are vertices of the four lattice cells around the edge, oriented with its normal pointing
//! from the inside point to the outside one. A binary occupancy thus gives two triangles per exposed
//! voxel face, where marching tetrahedra gave about seven.
//!
//! A cell has one vertex per *fan* of its faces (the faces meeting at that cell's corner of the
//! surface), so that the mesh is a manifold with the topology of the inside set under the 14-adjacency
//! of the Kuhn (Freudenthal) triangulation ([`super::topology`], the topology the handle removal works
//! in): two points are neighbours when their offset is `±v`, `v ∈ {0,1}³ \ {0}`.
//! - Faces across a cell edge with two faces are in one fan.
//! - At a *critical* cell edge (its four lattice points alternate inside and outside) the Kuhn
//!   diagonal (offset `(1,1)` in the plane of the four points) joins one pair: the faces are paired
//!   around each point of the other value, which the surface thus wraps separately. Each such side
//!   gets a vertex of its own on the edge, so the two sheets meeting there share no vertex.
//! - A *tube* cell (its two points on the Kuhn diagonal `(1,1,1)` of one value, the six others of the
//!   other) joins the two fans of the diagonal's ends: each fan's corner is cut into a ring of three
//!   vertices and a band of six triangles joins the rings.
//!
//! A fan's vertex starts at the mean of the points where its faces' lattice edges cross the value
//! 0.5 (linear interpolation; the edges' middles on a binary occupancy), a critical-edge vertex at
//! the middle of its cell edge. [`MeshParams::relax_iterations`] then smooths the stairs of a voxel
//! surface away as a constrained elastic surface net (Gibson, "Constrained elastic surface nets",
//! MICCAI 1998) with Taubin's non-shrinking steps (Taubin, "A signal processing approach to fair
//! surface design", SIGGRAPH 1995): the steps alternately move every vertex towards the mean of its
//! neighbours and slightly further back, so that a sphere keeps its size, and every vertex stays
//! within half a voxel of its start box's centre on each axis (its cell, or its cell edge's middle).
//! Relaxation moves vertices only: the connectivity and the topology stay as extracted.
//!
//! Cost follows the surface: only 8³ cell blocks whose neighbourhood holds both occupied and empty
//! voxels (or reaches the padding) are visited, in parallel.
//!
//! With [`MeshParams::remove_handles`] (on in [`MeshParams::smoothed`], what the scan methods use) the
//! occupancy first loses its voxel-scale handles ([`super::topology`]): a hole of a voxel or two
//! through a thin wall is plugged, a bridge a voxel or two thick over a groove is cut, changing only
//! voxels within one voxel of the surface; larger handles stay.

use std::collections::HashMap;
use std::sync::OnceLock;
use std::time::Instant;

use nalgebra::Vector3;
use rayon::prelude::*;

use super::occupancy::{Brick, Occupancy, BRICK};
use super::topology::{kuhn_euler_characteristic, remove_small_handles, HandleRepair};

/// Parameters of [`extract_surface`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MeshParams {
    /// Box-smoothing radius, voxels (0 = none; at most [`MeshParams::MAX_SMOOTH_RADIUS`]).
    pub smooth_radius: u32,
    /// Constrained relaxation steps (module docs); 0 leaves every vertex where the extraction put it.
    pub relax_iterations: u32,
    /// Remove voxel-scale handles (tunnels through thin walls, bridges over grooves) from the
    /// occupancy before meshing ([`remove_small_handles`]): the surface moves by at most about one
    /// voxel, only where that removes a handle.
    pub remove_handles: bool,
}

impl MeshParams {
    /// The largest supported smoothing radius, voxels.
    pub const MAX_SMOOTH_RADIUS: u32 = 7;
    /// Relaxation steps of [`MeshParams::smoothed`]: eight pairs of Taubin steps, after which the
    /// stairs of a voxel sphere are gone (its radial error 0.11 voxel against 0.15 unrelaxed).
    pub const RELAX_ITERATIONS: u32 = 16;

    /// Voxel-scale handles removed, box smoothing of `smooth_radius` voxels, then
    /// [`MeshParams::RELAX_ITERATIONS`] relaxation steps: what the scan methods mesh with.
    pub fn smoothed(smooth_radius: u32) -> MeshParams {
        MeshParams { smooth_radius, relax_iterations: Self::RELAX_ITERATIONS, remove_handles: true }
    }
}

/// A triangle mesh in metres (the occupancy grid's frame), counter-clockwise triangles seen from
/// outside, optional per-vertex 8-bit RGB colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriangleMesh {
    /// Vertex positions, metres.
    pub vertices: Vec<[f32; 3]>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
    /// Per-vertex colours (same length as `vertices` when present).
    pub colors: Option<Vec<[u8; 3]>>,
}

impl TriangleMesh {
    /// Enclosed volume, m³ (divergence theorem; positive for outward normals).
    pub fn signed_volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.vertices[i as usize].map(f64::from));
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0]))
                    / 6.0
            })
            .sum()
    }

    /// Checks that the mesh is closed and consistently oriented: every directed edge appears exactly once
    /// and its reverse exactly once (so every undirected edge is shared by exactly two triangles).
    /// Returns the number of offending edges.
    pub fn open_or_misoriented_edges(&self) -> usize {
        // The directed edges as sorted keys (`from << 32 | to`), then each distinct one with its
        // count, looked up reversed by binary search.
        let mut keys: Vec<u64> = self
            .triangles
            .par_iter()
            .flat_map_iter(|t| (0..3).map(move |e| u64::from(t[e]) << 32 | u64::from(t[(e + 1) % 3])))
            .collect();
        keys.par_sort_unstable();
        let mut counted: Vec<(u64, u32)> = Vec::with_capacity(keys.len() / 2 + 1);
        for k in keys {
            match counted.last_mut() {
                Some((last, n)) if *last == k => *n += 1,
                _ => counted.push((k, 1)),
            }
        }
        let count_of = |k: u64| counted.binary_search_by_key(&k, |e| e.0).map_or(0, |i| counted[i].1);
        counted.par_iter().filter(|&&(k, n)| n != 1 || count_of(k.rotate_left(32)) != 1).count()
    }
}

/// Errors of surface extraction.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The smoothing radius is above the supported maximum.
    #[error("smoothing radius {radius} voxels is above the maximum of {max}")]
    SmoothRadius {
        /// Requested radius, voxels.
        radius: u32,
        /// Maximum, voxels.
        max: u32,
    },
    /// More vertices than 32-bit indices can address.
    #[error("the mesh has {vertices} vertices, more than 32-bit indices allow")]
    TooLarge {
        /// Vertex count.
        vertices: usize,
    },
}

/// Output of one cell block: unique vertices as (edge key, lattice position), triangles as local indices.
type Part = (Vec<(u64, [f32; 3])>, Vec<[u32; 3]>);

/// A cell block (its index along each axis) and its [`Part`].
type BlockPart = ([usize; 3], Part);

/// Extract the surface of `occupancy` (see the module docs).
pub fn extract_surface(occupancy: &Occupancy, params: &MeshParams) -> Result<TriangleMesh, MeshError> {
    extract_surface_reporting(occupancy, params).map(|(mesh, _)| mesh)
}

/// As [`extract_surface`], also returning what the handle removal changed (`None` when
/// [`MeshParams::remove_handles`] is off). The mesh is that of the repaired occupancy; the caller's
/// occupancy is left as it is.
pub fn extract_surface_reporting(
    occupancy: &Occupancy,
    params: &MeshParams,
) -> Result<(TriangleMesh, Option<HandleRepair>), MeshError> {
    if params.smooth_radius > MeshParams::MAX_SMOOTH_RADIUS {
        return Err(MeshError::SmoothRadius { radius: params.smooth_radius, max: MeshParams::MAX_SMOOTH_RADIUS });
    }
    if !params.remove_handles {
        return extract(occupancy, params).map(|mesh| (mesh, None));
    }
    // Unsmoothed, the surface has the topology of the Kuhn complex the repair works in, whose Euler
    // characteristic is the surface's components less its handles: one that is not positive means
    // a handle, and the repair comes first. Otherwise the surface is extracted and its genus counted
    // (before the relaxation, which moves vertices only). At genus zero the repair would return the
    // occupancy unchanged, so that mesh is the answer; so it is when the repair removes nothing;
    // else only the cell blocks near voxels the repair changed are extracted again.
    let unsmoothed = if params.smooth_radius == 0 && kuhn_euler_characteristic(occupancy) > 0 {
        let parts = block_parts(occupancy, 0, None);
        let merged = merge(&parts)?;
        let t = Instant::now();
        if closed_surface_genus(&merged.0) == Some(0) {
            let stats = HandleRepair { seconds: t.elapsed().as_secs_f64(), ..HandleRepair::default() };
            return Ok((finish(occupancy, params, merged), Some(stats)));
        }
        Some((parts, merged))
    } else {
        None
    };
    let (repaired, stats) = remove_small_handles(occupancy);
    if stats.handles_removed() > 0 {
        tracing::info!(?stats, "voxel-scale handles removed before meshing");
    }
    let mesh = match unsmoothed {
        Some((_, merged)) if stats.handles_removed() == 0 => finish(occupancy, params, merged),
        Some((parts, _)) => {
            let parts = block_parts(&repaired, 0, Some((occupancy, parts)));
            finish(&repaired, params, merge(&parts)?)
        }
        None => extract(&repaired, params)?,
    };
    Ok((mesh, Some(stats)))
}

/// The genus summed over the components of a closed mesh (every edge shared by two triangles, as
/// [`extract_surface`] makes it): each component's Euler characteristic is `2 - 2 genus`, and with
/// `3/2` edges per triangle `V - E + F = V - F/2` over all of them, so `4 genus = 4 components -
/// 2 V + F`. `None` when that is not a multiple of four (the mesh cannot be closed).
fn closed_surface_genus(mesh: &TriangleMesh) -> Option<i64> {
    let (_, parts) = components(mesh);
    let mut used = vec![false; mesh.vertices.len()];
    for t in &mesh.triangles {
        for &v in t {
            used[v as usize] = true;
        }
    }
    let vertices = used.iter().filter(|&&u| u).count() as i64;
    let four = 4 * parts.len() as i64 - 2 * vertices + mesh.triangles.len() as i64;
    (four % 4 == 0).then_some(four / 4)
}

/// Dual extraction and relaxation over `occupancy` as it is (`smooth_radius` already checked by
/// the caller).
fn extract(occupancy: &Occupancy, params: &MeshParams) -> Result<TriangleMesh, MeshError> {
    let parts = block_parts(occupancy, params.smooth_radius as i64, None);
    Ok(finish(occupancy, params, merge(&parts)?))
}

/// The active cell blocks of `occupancy` (z, then y, then x order) with their parts
/// ([`dual_block`], smoothing radius `r`). With `before`, an occupancy on the same grid and its
/// parts, a block whose voxels (its cells' lattice points, `r` voxels beyond) lie in bricks equal
/// in both keeps its part from before.
fn block_parts(occupancy: &Occupancy, r: i64, before: Option<(&Occupancy, Vec<BlockPart>)>) -> Vec<BlockPart> {
    if occupancy.grid().is_empty() {
        return Vec::new();
    }
    let dims = occupancy.grid().dims.map(|d| d as i64);
    // Lattice points p in [0, D+2) per axis (point p is voxel p-1); cells c in [0, D+1).
    let cell_blocks = dims.map(|d| ((d + 1) as usize).div_ceil(BRICK));
    let bd = occupancy.brick_dims();
    let mut active = Vec::new();
    for z in 0..cell_blocks[2] {
        for y in 0..cell_blocks[1] {
            for x in 0..cell_blocks[0] {
                if is_active(occupancy, [x, y, z], r, &dims, &bd) {
                    active.push([x, y, z]);
                }
            }
        }
    }
    // Block `cb` reads voxels [8 cb - 1 - r, 8 cb + 8 + r]: those of bricks cb - 1 - reach .. cb + 1 + reach.
    let reach = (r as usize).div_ceil(BRICK);
    let mut kept: HashMap<[usize; 3], Part> = match before {
        None => HashMap::new(),
        Some((old, parts)) => {
            // Each brick compared once.
            let changed: Vec<bool> = (0..bd[0] * bd[1] * bd[2])
                .into_par_iter()
                .map(|b| {
                    let c = [b % bd[0], b / bd[0] % bd[1], b / (bd[0] * bd[1])];
                    occupancy.brick(c[0], c[1], c[2]) != old.brick(c[0], c[1], c[2])
                })
                .collect();
            let near_change = |c: [usize; 3]| {
                let lo = c.map(|x| x.saturating_sub(1 + reach));
                let hi = [0, 1, 2].map(|a| (c[a] + 1 + reach).min(bd[a] - 1));
                (lo[2]..=hi[2])
                    .any(|z| (lo[1]..=hi[1]).any(|y| (lo[0]..=hi[0]).any(|x| changed[x + bd[0] * (y + bd[1] * z)])))
            };
            parts.into_iter().filter(|(cb, _)| !near_change(*cb)).collect()
        }
    };
    let mut parts: Vec<([usize; 3], Option<Part>)> = active.into_iter().map(|cb| (cb, kept.remove(&cb))).collect();
    parts
        .par_iter_mut()
        .filter(|(_, p)| p.is_none())
        .for_each(|(cb, p)| *p = Some(dual_block(occupancy, *cb, r, &dims)));
    parts.into_iter().map(|(cb, p)| (cb, p.unwrap_or_default())).collect()
}

/// The blocks' parts (in their order) merged into one mesh, positions in lattice units, with each
/// vertex's key (increasing).
fn merge(parts: &[BlockPart]) -> Result<(TriangleMesh, Vec<u64>), MeshError> {
    // Merge vertices shared between blocks by their key (each block's vertices are already unique).
    let mut keys: Vec<u64> = parts.iter().flat_map(|p| p.1 .0.iter().map(|v| v.0)).collect();
    keys.par_sort_unstable();
    keys.dedup();
    if keys.len() > u32::MAX as usize {
        return Err(MeshError::TooLarge { vertices: keys.len() });
    }
    let mut lattice = vec![[0f32; 3]; keys.len()];
    let mut triangles = Vec::with_capacity(parts.iter().map(|p| p.1 .1.len()).sum());
    // Each block's vertices found among the keys side by side; the positions and triangles are
    // then gathered in block order.
    let globals: Vec<Vec<u32>> = parts
        .par_iter()
        .map(|(_, (verts, _))| verts.iter().map(|(k, _)| keys.binary_search(k).unwrap_or(0) as u32).collect())
        .collect();
    for ((_, (verts, tris)), global) in parts.iter().zip(&globals) {
        for ((_, p), &g) in verts.iter().zip(global) {
            lattice[g as usize] = *p;
        }
        triangles.extend(tris.iter().map(|t| t.map(|i| global[i as usize])));
    }
    Ok((TriangleMesh { vertices: lattice, triangles, colors: None }, keys))
}

/// A [`merge`]d mesh of `occupancy`'s parts relaxed (`params`) and placed in metres.
fn finish(occupancy: &Occupancy, params: &MeshParams, (mut mesh, keys): (TriangleMesh, Vec<u64>)) -> TriangleMesh {
    let grid = occupancy.grid();
    let dims = grid.dims.map(|d| d as u64);
    if params.relax_iterations > 0 {
        let pitch = [1, dims[0] + 2, (dims[0] + 2) * (dims[1] + 2)];
        relax_in_cells(&mut mesh.vertices, &keys, pitch, &mesh.triangles, params.relax_iterations);
    }
    let s = grid.voxel_size;
    for p in &mut mesh.vertices {
        *p = [0, 1, 2].map(|a| (grid.origin[a] + (p[a] as f64 - 0.5) * s) as f32);
    }
    mesh
}

/// Vertex kinds in the low five bits of a vertex key (the cell's lattice index above them): a fan of
/// the cell (0-11, the index of one of its faces), the vertex of one side of a critical cell edge
/// (`CRITICAL + 4 axis + side`), a ring vertex of a tube (`RING + 2 axis + upper`).
const KIND_BITS: u64 = 5;
const CRITICAL: u8 = 12;
const RING: u8 = 24;

/// The centre of the box a vertex of kind `kind` stays in, lattice units, relative to its cell's
/// centre: the cell's centre for a fan, the middle of its edge for a critical-edge vertex, a quarter
/// of the way along its edge for a ring vertex (where the last two also start).
fn kind_offset(kind: u8) -> [f32; 3] {
    let mut o = [0f32; 3];
    if kind >= RING {
        let k = kind - RING;
        o[(k / 2) as usize] = if k % 2 == 1 { 0.25 } else { -0.25 };
    } else if kind >= CRITICAL {
        o[((kind - CRITICAL) / 4) as usize] = 0.5;
    }
    o
}

/// The centre (lattice units) of the box a vertex of `key` stays in: its cell's centre moved by
/// [`kind_offset`].
fn key_centre(key: u64, pitch: [u64; 3]) -> [f32; 3] {
    let (lin, kind) = (key >> KIND_BITS, (key & ((1 << KIND_BITS) - 1)) as u8);
    let cell = [lin % pitch[1], (lin / pitch[1]) % (pitch[2] / pitch[1]), lin / pitch[2]];
    let o = kind_offset(kind);
    [0, 1, 2].map(|a| cell[a] as f32 + 0.5 + o[a])
}

/// Step towards the neighbours' mean of the even relaxation steps (Taubin's lambda).
const TAUBIN_LAMBDA: f32 = 0.5;
/// Step of the odd relaxation steps (Taubin's mu, negative: away from the mean), slightly larger than
/// [`TAUBIN_LAMBDA`] so that a pair of steps keeps the surface's size instead of shrinking it.
const TAUBIN_MU: f32 = -0.53;

/// Constrained relaxation (module docs): step `i` moves every vertex by [`TAUBIN_LAMBDA`] (even `i`)
/// or [`TAUBIN_MU`] (odd `i`) times its offset to the mean of its neighbours, kept within half a
/// lattice unit of its box centre ([`key_centre`]) on every axis.
fn relax_in_cells(lattice: &mut [[f32; 3]], keys: &[u64], pitch: [u64; 3], triangles: &[[u32; 3]], iterations: u32) {
    let n = lattice.len();
    // Neighbours in compressed rows (each undirected edge appears in two triangles: both directions).
    let mut count = vec![0u32; n + 1];
    for t in triangles {
        for e in 0..3 {
            count[t[e] as usize + 1] += 1;
        }
    }
    for i in 0..n {
        count[i + 1] += count[i];
    }
    let mut fill = count.clone();
    let mut adj = vec![0u32; count[n] as usize];
    for t in triangles {
        for e in 0..3 {
            let (a, b) = (t[e] as usize, t[(e + 1) % 3]);
            adj[fill[a] as usize] = b;
            fill[a] += 1;
        }
    }
    let centres: Vec<[f32; 3]> = keys.par_iter().map(|&k| key_centre(k, pitch)).collect();
    // Two buffers read and written in turn (a vertex without neighbours holds its start in both).
    let mut current = lattice.to_vec();
    let mut next = current.clone();
    for it in 0..iterations {
        let step = if it % 2 == 0 { TAUBIN_LAMBDA } else { TAUBIN_MU };
        next.par_iter_mut().enumerate().for_each(|(v, out)| {
            let ring = &adj[count[v] as usize..count[v + 1] as usize];
            if ring.is_empty() {
                return;
            }
            let mut mean = [0f32; 3];
            for &u in ring {
                for a in 0..3 {
                    mean[a] += current[u as usize][a];
                }
            }
            let c = centres[v];
            *out = [0, 1, 2].map(|a| {
                (current[v][a] + step * (mean[a] / ring.len() as f32 - current[v][a])).clamp(c[a] - 0.5, c[a] + 0.5)
            });
        });
        std::mem::swap(&mut current, &mut next);
    }
    lattice.copy_from_slice(&current);
}

/// The cell's face between lattice points `s` and `s | 1 << a` (offset bit masks, bit `a` of `s`
/// clear), numbered `4 a + (the other two bits of s)`.
fn face_index(s: usize, a: usize) -> usize {
    let (u, w) = ((a + 1) % 3, (a + 2) % 3);
    a * 4 + ((s >> u) & 1) + 2 * ((s >> w) & 1)
}

/// Per configuration of a cell's eight lattice points (bit `s` set: point `s` inside), the fan of each
/// of its twelve faces: faces with the same entry share the cell's vertex (module docs). Two faces
/// across one of the cell's six half-edges are joined when that half-edge has two faces; at a
/// critical half-edge (four faces) the faces are paired around each point of the value the Kuhn
/// diagonal does not join.
fn fan_table() -> &'static [[u8; 12]; 256] {
    static TABLE: OnceLock<[[u8; 12]; 256]> = OnceLock::new();
    TABLE.get_or_init(|| {
        fn find(p: &mut [usize; 12], mut x: usize) -> usize {
            while p[x] != x {
                p[x] = p[p[x]];
                x = p[x];
            }
            x
        }
        std::array::from_fn(|m| {
            let inside = |s: usize| (m >> s) & 1 == 1;
            let mut parent: [usize; 12] = std::array::from_fn(|i| i);
            let union = |p: &mut [usize; 12], f: usize, g: usize| {
                let (rf, rg) = (find(p, f), find(p, g));
                p[rf] = rg;
            };
            for a in 0..3 {
                let (u, w) = ((a + 1) % 3, (a + 2) % 3);
                for side in 0..2 {
                    // The four points around the half-edge along axis `a` on this side, in cyclic order;
                    // points 0 and 2 are the ones the Kuhn diagonal joins.
                    let cyc = [(0, 0), (1, 0), (1, 1), (0, 1)].map(|(bu, bw)| (side << a) | (bu << u) | (bw << w));
                    // The faces between consecutive points of different values: (face, point, point).
                    let mut faces = Vec::new();
                    for i in 0..4 {
                        let (x, y) = (cyc[i], cyc[(i + 1) % 4]);
                        if inside(x) != inside(y) {
                            faces.push((face_index(x.min(y), (x ^ y).trailing_zeros() as usize), x, y));
                        }
                    }
                    if faces.len() == 2 {
                        union(&mut parent, faces[0].0, faces[1].0);
                    } else if faces.len() == 4 {
                        let joined = inside(cyc[0]);
                        for &v in cyc.iter().filter(|&&v| inside(v) != joined) {
                            let mine: Vec<usize> = faces.iter().filter(|f| f.1 == v || f.2 == v).map(|f| f.0).collect();
                            union(&mut parent, mine[0], mine[1]);
                        }
                    }
                }
            }
            std::array::from_fn(|f| find(&mut parent, f) as u8)
        })
    })
}

/// Is a cell of this configuration a tube: its two points on the Kuhn diagonal (0 and 7) of one
/// value, the six around it of the other?
fn is_tube(mask: u8) -> bool {
    mask == 0x81 || mask == 0x7e
}

/// Does the cell block `cb` (cells `[8 cb, 8 cb + 8)`) possibly hold surface?
fn is_active(occ: &Occupancy, cb: [usize; 3], r: i64, dims: &[i64; 3], bd: &[usize; 3]) -> bool {
    // Voxels that influence the block's lattice points.
    let lo = cb.map(|c| c as i64 * BRICK as i64 - 1 - r);
    let hi = cb.map(|c| c as i64 * BRICK as i64 + BRICK as i64 - 1 + r);
    let touches_padding = (0..3).any(|a| lo[a] < 0 || hi[a] >= dims[a]);
    let b0 = [0, 1, 2].map(|a| (lo[a].max(0) as usize / BRICK).min(bd[a] - 1));
    let b1 = [0, 1, 2].map(|a| (hi[a].min(dims[a] - 1).max(0) as usize / BRICK).min(bd[a] - 1));
    let (mut any_full, mut any_empty) = (false, false);
    for z in b0[2]..=b1[2] {
        for y in b0[1]..=b1[1] {
            for x in b0[0]..=b1[0] {
                match occ.brick(x, y, z) {
                    Brick::Empty => any_empty = true,
                    Brick::Full => any_full = true,
                    Brick::Mixed(_) => return true,
                }
            }
        }
    }
    any_full && (any_empty || touches_padding)
}

/// The dual surface of the cell block `cb` (cells `[8 cb, 8 cb + 8)`): the quads of the lattice
/// edges whose lowest cell is in the block, and a tube for each tube cell of the block. Vertices
/// of cells outside the block are computed here as well, identically (the merge keeps one).
fn dual_block(occ: &Occupancy, cb: [usize; 3], r: i64, dims: &[i64; 3]) -> Part {
    // The block's first cell and first lattice point.
    let base = cb.map(|c| (c * BRICK) as i64);
    // Lattice points of the block's cells and of the cells one beyond them.
    let npts = [0, 1, 2].map(|a| ((dims[a] + 2) - base[a]).min(BRICK as i64 + 2) as usize);
    let own = [0, 1, 2].map(|a| ((dims[a] + 1) - base[a]).min(BRICK as i64) as usize);
    // Raw occupancy over voxels [base-1-r, base-1+npts-1+r].
    let ext = npts.map(|n| n + 2 * r as usize);
    let v0 = base.map(|b| b - 1 - r);
    let mut raw = vec![0u32; ext[0] * ext[1] * ext[2]];
    for z in 0..ext[2] {
        for y in 0..ext[1] {
            for x in 0..ext[0] {
                if occ.get_signed(v0[0] + x as i64, v0[1] + y as i64, v0[2] + z as i64) {
                    raw[x + ext[0] * (y + ext[1] * z)] = 1;
                }
            }
        }
    }
    // Separable box sums: x, then y, then z, shrinking the extent by 2r each time.
    let w = 2 * r as usize + 1;
    let sx = box_pass(&raw, ext, 0, w);
    let sy = box_pass(&sx, [npts[0], ext[1], ext[2]], 1, w);
    let sums = box_pass(&sy, [npts[0], npts[1], ext[2]], 2, w);
    let total = (w * w * w) as f32;
    let value = |p: [usize; 3]| sums[p[0] + npts[0] * (p[1] + npts[1] * p[2])] as f32 / total;
    let inside = |p: [usize; 3]| value(p) > 0.5;
    let ncells = npts.map(|n| n - 1);
    let cell_at = |l: [usize; 3]| l[0] + ncells[0] * (l[1] + ncells[1] * l[2]);
    let mut masks = vec![0u8; ncells[0] * ncells[1] * ncells[2]];
    for z in 0..ncells[2] {
        for y in 0..ncells[1] {
            for x in 0..ncells[0] {
                let m = (0..8).filter(|&s| inside([x + (s & 1), y + ((s >> 1) & 1), z + ((s >> 2) & 1)]));
                masks[cell_at([x, y, z])] = m.fold(0u8, |acc, s| acc | 1 << s);
            }
        }
    }
    let table = fan_table();
    let pitch = [1u64, (dims[0] + 2) as u64, ((dims[0] + 2) * (dims[1] + 2)) as u64];
    let mut verts: Vec<(u64, [f32; 3])> = Vec::new();
    let mut tris: Vec<[u32; 3]> = Vec::new();
    // Local vertex per (cell of this block's extent, kind): u32::MAX = none yet.
    let mut slot = vec![u32::MAX; masks.len() << KIND_BITS];
    // The vertex of kind `kind` of local cell `l`, created on first use at its starting position
    // (lattice units): a fan at the mean of its faces' crossings, the others at their box centres.
    let mut vertex = |l: [usize; 3], kind: u8| -> u32 {
        let si = (cell_at(l) << KIND_BITS) | kind as usize;
        if slot[si] == u32::MAX {
            let cell = [0, 1, 2].map(|a| base[a] + l[a] as i64);
            let p = if kind < CRITICAL {
                let fans = &table[masks[cell_at(l)] as usize];
                let (mut sum, mut n) = ([0f32; 3], 0f32);
                for a in 0..3 {
                    for s in (0..8usize).filter(|s| s & (1 << a) == 0) {
                        let p0 = [0, 1, 2].map(|k| l[k] + ((s >> k) & 1));
                        let mut p1 = p0;
                        p1[a] += 1;
                        if fans[face_index(s, a)] != kind || inside(p0) == inside(p1) {
                            continue;
                        }
                        let (f0, f1) = (value(p0), value(p1));
                        let t = (0.5 - f0) / (f1 - f0);
                        for k in 0..3 {
                            sum[k] += (cell[k] + ((s >> k) & 1) as i64) as f32 + if k == a { t } else { 0.0 };
                        }
                        n += 1.0;
                    }
                }
                sum.map(|x| x / n)
            } else {
                let o = kind_offset(kind);
                [0, 1, 2].map(|a| cell[a] as f32 + 0.5 + o[a])
            };
            let lin = cell[0] as u64 * pitch[0] + cell[1] as u64 * pitch[1] + cell[2] as u64 * pitch[2];
            slot[si] = verts.len() as u32;
            verts.push(((lin << KIND_BITS) | kind as u64, p));
        }
        slot[si]
    };
    let mut poly: Vec<u32> = Vec::with_capacity(12);
    for z in 0..own[2] {
        for y in 0..own[1] {
            for x in 0..own[0] {
                let l = [x, y, z];
                for a in 0..3 {
                    let (u, w) = ((a + 1) % 3, (a + 2) % 3);
                    // The lattice edge from q along a; the four cells around it in cyclic order, their
                    // normal `e_u x e_w = e_a`, reversed when the inside point is the upper one.
                    let mut q = l;
                    q[u] += 1;
                    q[w] += 1;
                    let mut q1 = q;
                    q1[a] += 1;
                    let low_inside = inside(q);
                    if low_inside == inside(q1) {
                        continue;
                    }
                    let mut cells = [(0, 0), (1, 0), (1, 1), (0, 1)].map(|(du, dw)| {
                        let mut c = l;
                        c[u] += du;
                        c[w] += dw;
                        c
                    });
                    if !low_inside {
                        cells.swap(1, 3);
                    }
                    let (in_pt, out_pt) = if low_inside { (q, q1) } else { (q1, q) };
                    poly.clear();
                    let (mut first_mid, mut first_tube) = (None, None);
                    // Where each cell's vertices start in the polygon.
                    let mut starts = [0usize; 4];
                    for i in 0..4 {
                        starts[i] = poly.len();
                        let (c, prev, next) = (cells[i], cells[(i + 3) % 4], cells[(i + 1) % 4]);
                        let mask = masks[cell_at(c)];
                        if is_tube(mask) {
                            first_tube.get_or_insert(i);
                            for nb in [prev, next] {
                                let b = (0..3).find(|&k| nb[k] != c[k]).unwrap_or(0);
                                poly.push(vertex(c, RING + 2 * b as u8 + u8::from(nb[b] > c[b])));
                            }
                        } else {
                            let s = (0..3).fold(0, |acc, k| acc | (q[k] - c[k]) << k);
                            poly.push(vertex(c, table[mask as usize][face_index(s, a)]));
                        }
                        // The cell edge to the next cell: a vertex of this quad's side when critical.
                        let b = (0..3).find(|&k| next[k] != c[k]).unwrap_or(0);
                        let lo = if next[b] < c[b] { next } else { c };
                        let (b1, b2) = ((b + 1) % 3, (b + 2) % 3);
                        let around = [(0, 0), (1, 0), (1, 1), (0, 1)].map(|(d1, d2)| {
                            let mut p = lo;
                            p[b] += 1;
                            p[b1] += d1;
                            p[b2] += d2;
                            p
                        });
                        let v = around.map(inside);
                        if v[0] == v[2] && v[1] == v[3] && v[0] != v[1] {
                            // The points of the value the Kuhn diagonal does not join each get a side.
                            let side_pt = if v[0] { out_pt } else { in_pt };
                            let side = around.iter().position(|&p| p == side_pt).unwrap_or(0);
                            first_mid.get_or_insert(poly.len());
                            poly.push(vertex(lo, CRITICAL + 4 * b as u8 + side as u8));
                        }
                    }
                    // A fan from a critical-edge vertex (on a straight edge of the polygon), else from
                    // the cell across from a tube, else the quad split along its first diagonal.
                    let n = poly.len();
                    let from = match (first_mid, first_tube) {
                        (Some(f), _) => f,
                        (None, Some(t)) => starts[(t + 2) % 4],
                        (None, None) => 0,
                    };
                    for t in 1..n - 1 {
                        tris.push([poly[from], poly[(from + t) % n], poly[(from + t + 1) % n]]);
                    }
                }
                // A tube cell joins its two fans by a band of six triangles around its diagonal.
                let mask = masks[cell_at(l)];
                if is_tube(mask) {
                    let ring = |a: u8, upper: bool| RING + 2 * a + u8::from(upper);
                    let hex =
                        [ring(0, false), ring(2, true), ring(1, false), ring(0, true), ring(2, false), ring(1, true)];
                    let solid = mask == 0x81;
                    for i in 0..6 {
                        let k = [hex[i], hex[(i + 1) % 6], hex[(i + 2) % 6]];
                        let p = k.map(|kind| Vector3::from(kind_offset(kind)));
                        let normal = (p[1] - p[0]).cross(&(p[2] - p[0]));
                        // Away from the diagonal for a solid tube, towards it for an air tube.
                        let m = (p[0] + p[1] + p[2]) / 3.0;
                        let out = normal.dot(&(m - Vector3::repeat(m.sum() / 3.0)));
                        let ids = k.map(|kind| vertex(l, kind));
                        if (out > 0.0) == solid {
                            tris.push(ids);
                        } else {
                            tris.push([ids[0], ids[2], ids[1]]);
                        }
                    }
                }
            }
        }
    }
    (verts, tris)
}

/// Box sum of width `w` along `axis` over an `ext` volume; the result is `w - 1` shorter on that axis.
fn box_pass(src: &[u32], ext: [usize; 3], axis: usize, w: usize) -> Vec<u32> {
    let mut out_ext = ext;
    out_ext[axis] = ext[axis] + 1 - w;
    let mut out = vec![0u32; out_ext[0] * out_ext[1] * out_ext[2]];
    let stride = [1, ext[0], ext[0] * ext[1]];
    for z in 0..out_ext[2] {
        for y in 0..out_ext[1] {
            for x in 0..out_ext[0] {
                let start = x * stride[0] + y * stride[1] + z * stride[2];
                let s: u32 = (0..w).map(|t| src[start + t * stride[axis]]).sum();
                out[x + out_ext[0] * (y + out_ext[1] * z)] = s;
            }
        }
    }
    out
}

/// The connected component of each triangle (triangles sharing a vertex; `u32::MAX` for a triangle
/// with an index out of range) and the volume each component encloses (divergence theorem, m³).
fn components(mesh: &TriangleMesh) -> (Vec<u32>, HashMap<u32, f64>) {
    let n = mesh.vertices.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn find(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            let up = parent[parent[x as usize] as usize];
            parent[x as usize] = up;
            x = up;
        }
        x
    }
    let valid = |t: &[u32; 3]| t.iter().all(|&i| (i as usize) < n);
    for t in mesh.triangles.iter().filter(|t| valid(t)) {
        let a = find(&mut parent, t[0]);
        for &v in &t[1..] {
            let b = find(&mut parent, v);
            if a != b {
                parent[b as usize] = a;
            }
        }
    }
    // Each component's volume summed at its root (in triangle order), then gathered.
    let mut at_root = vec![0.0f64; n];
    let mut is_root = vec![false; n];
    let mut comp = Vec::with_capacity(mesh.triangles.len());
    for t in &mesh.triangles {
        if !valid(t) {
            comp.push(u32::MAX);
            continue;
        }
        let c = find(&mut parent, t[0]);
        let [a, b, d] = t.map(|i| mesh.vertices[i as usize].map(f64::from));
        let v = (a[0] * (b[1] * d[2] - b[2] * d[1]) - a[1] * (b[0] * d[2] - b[2] * d[0])
            + a[2] * (b[0] * d[1] - b[1] * d[0]))
            / 6.0;
        at_root[c as usize] += v;
        is_root[c as usize] = true;
        comp.push(c);
    }
    let volume = (0..n as u32).filter(|&c| is_root[c as usize]).map(|c| (c, at_root[c as usize])).collect();
    (comp, volume)
}

/// The topology of a mesh, for reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct MeshTopology {
    /// Triangles.
    pub triangles: usize,
    /// Vertices used by a triangle.
    pub vertices: usize,
    /// Undirected edges.
    pub edges: usize,
    /// Connected components (triangles sharing a vertex).
    pub components: usize,
    /// Components enclosing negative volume: the walls of internal cavities (outward normals).
    pub cavities: usize,
    /// Directed edges without exactly one opposite partner: 0 for a closed, consistently oriented mesh.
    pub open_or_misoriented_edges: usize,
    /// Euler characteristic V - E + F (2 for one closed surface without handles).
    pub euler_characteristic: i64,
    /// Handles (tunnels) of a single closed component, `(2 - euler_characteristic) / 2`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub genus: Option<i64>,
}

impl TriangleMesh {
    /// Components, cavities, open edges, Euler characteristic and genus (see [`MeshTopology`]).
    pub fn topology(&self) -> MeshTopology {
        let mut used = vec![false; self.vertices.len()];
        let mut edges: Vec<(u32, u32)> = Vec::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            for e in 0..3 {
                if let Some(u) = used.get_mut(t[e] as usize) {
                    *u = true;
                }
                let (a, b) = (t[e], t[(e + 1) % 3]);
                edges.push((a.min(b), a.max(b)));
            }
        }
        // The edges, the components and the open edges are counted side by side.
        let ((), ((_, volume), open)) = rayon::join(
            || {
                edges.par_sort_unstable();
                edges.dedup();
            },
            || rayon::join(|| components(self), || self.open_or_misoriented_edges()),
        );
        let vertices = used.iter().filter(|&&u| u).count();
        let euler = vertices as i64 - edges.len() as i64 + self.triangles.len() as i64;
        MeshTopology {
            triangles: self.triangles.len(),
            vertices,
            edges: edges.len(),
            components: volume.len(),
            cavities: volume.values().filter(|&&v| v < 0.0).count(),
            open_or_misoriented_edges: open,
            euler_characteristic: euler,
            genus: (volume.len() == 1 && open == 0).then_some((2 - euler) / 2),
        }
    }
}

/// What [`keep_main_component`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct MeshCleanStats {
    /// Connected components of the input (triangles sharing vertices).
    pub components: usize,
    /// Components removed that enclose positive volume: parts floating apart from the main one.
    pub floating_parts_removed: usize,
    /// Components removed that enclose negative volume: the inner walls of internal cavities.
    pub cavities_removed: usize,
    /// Triangles removed in all.
    pub triangles_removed: usize,
}

/// The mesh reduced to its main component: of the connected components (triangles sharing a
/// vertex), the one enclosing the largest volume (divergence theorem, outward normals) is kept;
/// every other one is dropped and counted, as a floating part when it encloses positive volume, as
/// an internal cavity when negative (a void's wall faces into the void). On a closed, consistently
/// oriented mesh such as [`extract_surface`]'s, the result is one closed component without
/// cavities. Vertices keep their order (unused ones are dropped), as do colours.
pub fn keep_main_component(mesh: &TriangleMesh) -> (TriangleMesh, MeshCleanStats) {
    let n = mesh.vertices.len();
    let (comp, volume) = components(mesh);
    let mut stats = MeshCleanStats { components: volume.len(), ..MeshCleanStats::default() };
    let Some((&main, _)) = volume.iter().max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(a.0))) else {
        return (TriangleMesh { colors: mesh.colors.clone(), ..TriangleMesh::default() }, stats);
    };
    for (&c, &v) in &volume {
        if c != main {
            if v >= 0.0 {
                stats.floating_parts_removed += 1;
            } else {
                stats.cavities_removed += 1;
            }
        }
    }
    let mut remap = vec![u32::MAX; n];
    let mut out = TriangleMesh::default();
    let mut colors = mesh.colors.as_ref().map(|_| Vec::new());
    for (t, &c) in mesh.triangles.iter().zip(&comp) {
        if c != main {
            stats.triangles_removed += 1;
            continue;
        }
        out.triangles.push(t.map(|i| {
            if remap[i as usize] == u32::MAX {
                remap[i as usize] = out.vertices.len() as u32;
                out.vertices.push(mesh.vertices[i as usize]);
                if let (Some(dst), Some(src)) = (colors.as_mut(), mesh.colors.as_ref()) {
                    dst.push(src.get(i as usize).copied().unwrap_or([128, 128, 128]));
                }
            }
            remap[i as usize]
        }));
    }
    out.colors = colors;
    (out, stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, VoxelGrid};
    use crate::sim::rng::mix;
    use nalgebra::Vector3;

    fn sphere(n: u32, radius: f64) -> Occupancy {
        let g = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0, 1.0, 0.8] }, n);
        Occupancy::from_fn(g, move |p| (p - Vector3::new(0.05, -0.1, 0.0)).norm() < radius)
    }

    /// The count of edges that are not used once each way, as a map of directed edges counts them.
    fn open_edges_by_map(mesh: &TriangleMesh) -> usize {
        let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &mesh.triangles {
            for e in 0..3 {
                *directed.entry((t[e], t[(e + 1) % 3])).or_insert(0) += 1;
            }
        }
        directed.iter().filter(|(&(a, b), &n)| n != 1 || directed.get(&(b, a)).copied() != Some(1)).count()
    }

    /// Open, flipped and repeated triangles are each counted as a map of directed edges counts them,
    /// and the topology sees the parts and the hole.
    #[test]
    fn open_and_misoriented_edges_are_counted_exactly() {
        let closed = extract_surface(&sphere(16, 0.6), &MeshParams::default()).expect("mesh");
        assert_eq!(closed.open_or_misoriented_edges(), 0);
        let mut broken = closed.clone();
        broken.triangles.remove(5);
        let flipped = broken.triangles[40];
        broken.triangles[40] = [flipped[0], flipped[2], flipped[1]];
        broken.triangles.push(broken.triangles[90]);
        // A second, open part far away: one lone triangle.
        let n = broken.vertices.len() as u32;
        broken.vertices.extend([[5.0, 0.0, 0.0], [6.0, 0.0, 0.0], [5.0, 1.0, 0.0]]);
        broken.triangles.push([n, n + 1, n + 2]);
        let open = broken.open_or_misoriented_edges();
        assert!(open >= 3 + 6 + 3 + 3, "{open}");
        assert_eq!(open, open_edges_by_map(&broken));
        let t = broken.topology();
        assert_eq!((t.components, t.open_or_misoriented_edges, t.genus), (2, open, None));
        assert_eq!(closed.topology().components, 1);
    }

    /// The handle repair is skipped exactly when the unsmoothed surface has genus zero or the repair
    /// removes nothing, and the mesh is then the one the repair path gives.
    #[test]
    fn the_handle_repair_runs_only_on_a_surface_with_handles() {
        let g = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.032; 3] }, 32);
        let at = |i: usize, j: usize, k: usize| [i, j, k].map(|x| x as f64 + 0.5);
        // A ball with a cavity: two surfaces, genus zero.
        let hollow = Occupancy::from_index_fn(g, |i, j, k| {
            let r = at(i, j, k).iter().map(|x| (x - 16.0).powi(2)).sum::<f64>().sqrt();
            r < 12.0 && r > 5.0
        });
        // Small cubes in the eight corners, beside the solids below so that the characteristic of
        // a solid with a handle is positive: the mesh is extracted before the repair.
        let cubes = |i: usize, j: usize, k: usize| [i, j, k].iter().all(|x| (1..4).contains(x) || (28..31).contains(x));
        // A ring with a wide hole and a thick bar: a real handle the repair keeps.
        let ring = |i, j, k| {
            let p = at(i, j, k);
            let q = ((p[0] - 16.0).hypot(p[1] - 16.0) - 10.0).hypot(p[2] - 16.0);
            q < 4.0
        };
        // A slab pierced by a one-voxel tunnel: a handle the repair plugs.
        let pierced =
            |i, j, k| (4..28).contains(&i) && (4..28).contains(&j) && (14..17).contains(&k) && !(i == 16 && j == 16);
        let alone_and_beside = |f: &(dyn Fn(usize, usize, usize) -> bool + Sync)| {
            [Occupancy::from_index_fn(g, f), Occupancy::from_index_fn(g, |i, j, k| f(i, j, k) || cubes(i, j, k))]
        };
        let [ring, ring_beside] = alone_and_beside(&ring);
        let [pierced, pierced_beside] = alone_and_beside(&pierced);
        let params = MeshParams::smoothed(0);
        let mut genus = Vec::new();
        let solids = [
            ("hollow", &hollow),
            ("ring", &ring),
            ("pierced", &pierced),
            ("ring beside cubes", &ring_beside),
            ("pierced beside cubes", &pierced_beside),
        ];
        for (name, occ) in solids {
            let plain = extract(occ, &params).expect("mesh");
            let (mesh, stats) = extract_surface_reporting(occ, &params).expect("mesh");
            let stats = stats.expect("repair on");
            let (repaired, by_repair) = remove_small_handles(occ);
            let expected = extract(&repaired, &params).expect("mesh");
            assert_eq!(
                (mesh.vertices.len(), mesh.triangles.len()),
                (expected.vertices.len(), expected.triangles.len()),
                "{name}"
            );
            assert!(mesh.vertices == expected.vertices && mesh.triangles == expected.triangles, "{name}");
            assert_eq!(stats.handles_removed(), by_repair.handles_removed(), "{name}");
            genus.push((
                kuhn_euler_characteristic(occ),
                closed_surface_genus(&plain),
                closed_surface_genus(&mesh),
                stats.handles_removed(),
            ));
            // The count agrees with the Euler characteristic of one closed component.
            let t = mesh.topology();
            if t.components == 1 {
                assert_eq!(t.genus, closed_surface_genus(&mesh), "{name}");
            }
        }
        let expected = [
            (2, Some(0), Some(0), 0),
            (0, Some(1), Some(1), 0),
            (0, Some(1), Some(0), 1),
            (8, Some(1), Some(1), 0),
            (8, Some(1), Some(0), 1),
        ];
        assert_eq!(genus, expected);
        // A mesh that cannot be closed has no genus.
        let lone = TriangleMesh {
            vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2]],
            colors: None,
        };
        assert_eq!(closed_surface_genus(&lone), None);
    }

    #[test]
    fn sphere_mesh_is_closed_oriented_and_has_the_right_volume() {
        for r in [0, 1, 2] {
            let occ = sphere(40, 0.6);
            let mesh =
                extract_surface(&occ, &MeshParams { smooth_radius: r, relax_iterations: 0, remove_handles: false })
                    .expect("mesh");
            assert!(!mesh.triangles.is_empty());
            assert_eq!(mesh.open_or_misoriented_edges(), 0, "radius {r}");
            let v = mesh.signed_volume();
            let truth = 4.0 / 3.0 * std::f64::consts::PI * 0.6f64.powi(3);
            assert!(v > 0.0, "normals must point outwards");
            assert!((v - truth).abs() / truth < 0.08, "radius {r}: {v} vs {truth}");
        }
    }

    #[test]
    fn relaxation_leaves_the_stairs_for_sub_voxel_positions_and_keeps_the_size() {
        let occ = sphere(40, 0.6);
        let centre = Vector3::new(0.05, -0.1, 0.0);
        let stairs =
            extract_surface(&occ, &MeshParams { smooth_radius: 0, relax_iterations: 0, remove_handles: false })
                .expect("mesh");
        let relaxed = extract_surface(&occ, &MeshParams::smoothed(0)).expect("mesh");
        assert_eq!(stairs.triangles, relaxed.triangles, "relaxation moves vertices only");
        assert_eq!(relaxed.topology().open_or_misoriented_edges, 0);
        assert_eq!((relaxed.topology().components, relaxed.topology().euler_characteristic), (1, 2));
        let rms = |m: &TriangleMesh| {
            let sum: f64 = m
                .vertices
                .iter()
                .map(|v| ((Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64) - centre).norm() - 0.6).powi(2))
                .sum();
            (sum / m.vertices.len() as f64).sqrt()
        };
        let voxel = occ.grid().voxel_size;
        let (before, after) = (rms(&stairs), rms(&relaxed));
        // Measured: 0.155 voxel on the stairs, 0.113 relaxed (plain halving steps shrank the sphere
        // to 0.25 voxel).
        assert!(
            after < 0.8 * before && after < 0.13 * voxel,
            "radial error {after} vs {before} on the stairs (voxel {voxel})"
        );
        // Relaxation keeps the size: the mean radius moves by less than a twentieth of a voxel.
        let mean = |m: &TriangleMesh| {
            let sum: f64 =
                m.vertices.iter().map(|v| (Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64) - centre).norm()).sum();
            sum / m.vertices.len() as f64
        };
        assert!((mean(&relaxed) - mean(&stairs)).abs() < 0.05 * voxel, "{} vs {}", mean(&relaxed), mean(&stairs));
        // Every vertex stays in its box: within a box diagonal of where the extraction put it.
        for (a, b) in stairs.vertices.iter().zip(&relaxed.vertices) {
            let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt() as f64;
            assert!(d <= 3f64.sqrt() * voxel + 1e-6, "moved {d}");
        }
    }

    /// Two triangles per exposed voxel face, and the topology of the Kuhn 14-adjacency: two voxels
    /// (or two empty voxels in a solid) meeting at an edge or a corner are one part exactly when their
    /// offset is a Kuhn diagonal (all its components of one sign), each way round.
    #[test]
    fn the_dual_surface_has_two_triangles_per_face_and_the_kuhn_topology() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.008; 3] }, 8);
        let mesh = |f: &(dyn Fn([i64; 3]) -> bool + Sync)| {
            let occ = Occupancy::from_index_fn(grid, |i, j, k| f([i, j, k].map(|x| x as i64)));
            extract_surface(&occ, &MeshParams { remove_handles: false, ..MeshParams::smoothed(0) }).expect("mesh")
        };
        let block = mesh(&|v| v.iter().all(|&x| (2..5).contains(&x)));
        assert_eq!(block.triangles.len(), 2 * 6 * 9);
        assert_eq!((block.topology().components, block.topology().euler_characteristic), (1, 2));
        let a = [3i64, 3, 3];
        let mut offsets = Vec::new();
        for n in 0..27 {
            let o = [n % 3 - 1, (n / 3) % 3 - 1, n / 9 - 1];
            if o.iter().filter(|&&x| x != 0).count() >= 2 {
                offsets.push(o);
            }
        }
        assert_eq!(offsets.len(), 20);
        let mut joined_count = 0;
        for o in offsets {
            let b = [0, 1, 2].map(|k| a[k] + o[k]);
            let joined = o.iter().all(|&x| x >= 0) || o.iter().all(|&x| x <= 0);
            joined_count += usize::from(joined);
            // Two solid voxels in the air.
            let solid = mesh(&|v| v == a || v == b).topology();
            assert_eq!(solid.open_or_misoriented_edges, 0, "{o:?}");
            let expected = if joined { (1, 2, 0) } else { (2, 4, 0) };
            assert_eq!((solid.components, solid.euler_characteristic, solid.cavities), expected, "solid {o:?}");
            // Two empty voxels in a solid: one cavity or two.
            let air = mesh(&|v| v != a && v != b && v.iter().all(|&x| (1..7).contains(&x))).topology();
            assert_eq!(air.open_or_misoriented_edges, 0, "{o:?}");
            let expected = if joined { (2, 4, 1) } else { (3, 6, 2) };
            assert_eq!((air.components, air.euler_characteristic, air.cavities), expected, "air {o:?}");
        }
        // The six face diagonals and the two main ones that Kuhn's 14 offsets hold.
        assert_eq!(joined_count, 8);
    }

    /// The Euler characteristic of the Kuhn complex spanned by the inside lattice points: its
    /// vertices, edges, triangles and tetrahedra are the chains `0 ⊂ a ⊂ b ⊂ c` of offset bit masks
    /// from a point (7 edge, 12 triangle and 6 tetrahedron kinds), counted where all their points are
    /// inside. The points are those of `occ` box-smoothed over `(2r+1)³` voxels, the padding empty.
    fn kuhn_euler(occ: &Occupancy, r: i64) -> i64 {
        let d = occ.grid().dims.map(|x| x as i64);
        let w = (2 * r + 1).pow(3);
        let inside = |p: [i64; 3]| {
            let mut n = 0;
            for z in -r..=r {
                for y in -r..=r {
                    for x in -r..=r {
                        n += i64::from(occ.get_signed(p[0] - 1 + x, p[1] - 1 + y, p[2] - 1 + z));
                    }
                }
            }
            2 * n > w
        };
        let at = |p: [i64; 3], m: usize| [0, 1, 2].map(|k| p[k] + ((m >> k) & 1) as i64);
        let subset = |a: usize, b: usize| a != b && a & b == a;
        let mut euler = 0;
        for z in 0..d[2] + 2 {
            for y in 0..d[1] + 2 {
                for x in 0..d[0] + 2 {
                    let p = [x, y, z];
                    if !inside(p) {
                        continue;
                    }
                    euler += 1;
                    for a in 1..8 {
                        if !inside(at(p, a)) {
                            continue;
                        }
                        euler -= 1;
                        for b in (1..8).filter(|&b| subset(a, b) && inside(at(p, b))) {
                            euler += 1;
                            euler -= (1..8).filter(|&c| subset(b, c) && inside(at(p, c))).count() as i64;
                        }
                    }
                }
            }
        }
        euler
    }

    /// On scattered voxels (half of them occupied, so every kind of critical edge and tube cell
    /// occurs), raw and box-smoothed, the surface is closed and oriented and bounds the Kuhn complex
    /// of the inside points: its Euler characteristic is twice the complex's, counted independently.
    #[test]
    fn the_surface_bounds_the_kuhn_complex_of_scattered_voxels() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.012; 3] }, 12);
        for seed in 0..4u64 {
            let occ = Occupancy::from_index_fn(grid, |i, j, k| {
                // Mixed so that neighbouring voxels are independent.
                let index = (i + 12 * j + 144 * k) as u64 + 1000 * seed;
                mix(index.wrapping_mul(0x9E37_79B9_7F4A_7C15)) >> 63 == 1
            });
            for r in [0u32, 1] {
                let params = MeshParams { smooth_radius: r, remove_handles: false, ..MeshParams::smoothed(r) };
                let topo = extract_surface(&occ, &params).expect("mesh").topology();
                assert_eq!(topo.open_or_misoriented_edges, 0, "seed {seed}, radius {r}");
                let complex = kuhn_euler(&occ, r as i64);
                assert_eq!(topo.euler_characteristic, 2 * complex, "seed {seed}, radius {r}: {topo:?}");
                if r == 0 {
                    assert_eq!(kuhn_euler_characteristic(&occ), complex, "seed {seed}");
                }
            }
        }
    }

    #[test]
    fn object_touching_the_grid_border_is_closed_by_the_padding() {
        let g = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [1.0; 3] }, 19);
        let occ = Occupancy::from_fn(g, |p| p.x < 0.7 || (p.y - 0.5).abs() < 0.1);
        let mesh = extract_surface(&occ, &MeshParams { smooth_radius: 1, relax_iterations: 0, remove_handles: false })
            .expect("mesh");
        assert_eq!(mesh.open_or_misoriented_edges(), 0);
        assert!(mesh.signed_volume() > 0.0);
        let full = extract_surface(&Occupancy::full(g), &MeshParams::default()).expect("mesh");
        assert_eq!(full.open_or_misoriented_edges(), 0);
        assert!(extract_surface(&occ, &MeshParams { smooth_radius: 99, relax_iterations: 0, remove_handles: false })
            .is_err());
    }

    #[test]
    fn main_component_drops_floating_parts_and_cavities() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.032; 3] }, 32);
        // A block with an internal void, and a small separate cube beside it.
        let occ = Occupancy::from_index_fn(grid, |i, j, k| {
            let block = (2..20).contains(&i) && (2..20).contains(&j) && (2..20).contains(&k);
            let void = (8..12).contains(&i) && (8..12).contains(&j) && (8..12).contains(&k);
            let cube = (25..29).contains(&i) && (25..29).contains(&j) && (25..29).contains(&k);
            (block && !void) || cube
        });
        let mesh = extract_surface(&occ, &MeshParams::default()).expect("mesh");
        let (clean, stats) = keep_main_component(&mesh);
        assert_eq!(stats.components, 3);
        assert_eq!((stats.floating_parts_removed, stats.cavities_removed), (1, 1));
        assert_eq!(stats.triangles_removed, mesh.triangles.len() - clean.triangles.len());
        assert_eq!(clean.open_or_misoriented_edges(), 0);
        let block = (18.0f64 * 0.001).powi(3);
        let v = clean.signed_volume();
        assert!((v - block).abs() < 0.05 * block, "volume {v} vs the block's {block}");
        assert!(clean.vertices.len() < mesh.vertices.len());
        let (again, s2) = keep_main_component(&clean);
        assert_eq!((s2.components, s2.triangles_removed, again.triangles.len()), (1, 0, clean.triangles.len()));
    }

    #[test]
    fn empty_occupancy_gives_an_empty_mesh() {
        let g = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [1.0; 3] }, 9);
        let mesh = extract_surface(&Occupancy::empty(g), &MeshParams::default()).expect("mesh");
        assert!(mesh.triangles.is_empty() && mesh.vertices.is_empty());
        let none = VoxelGrid { dims: [0, 4, 4], ..g };
        let mesh = extract_surface(&Occupancy::full(none), &MeshParams::default()).expect("mesh");
        assert!(mesh.triangles.is_empty());
    }
}
