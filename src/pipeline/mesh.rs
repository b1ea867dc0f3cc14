//! Surface extraction from an occupancy: a watertight, consistently oriented triangle mesh.
//!
//! The scalar field lives on the lattice of voxel centres, padded by one empty layer on every side so
//! the surface always closes. Its value is the occupancy (0 or 1), optionally box-smoothed over
//! `(2r+1)³` voxels (`smooth_radius = r`) so the mesh is not a staircase. The iso-surface at 0.5 of the
//! piecewise-linear interpolant is extracted by marching tetrahedra: each lattice cube is split into
//! six tetrahedra around its main diagonal (the Kuhn split, identical in every cube, so neighbouring
//! cubes split their shared faces the same way). This is the marching-cubes family without the
//! ambiguous cases of the 256-entry cube table: every edge of the result is shared by exactly two
//! triangles and the triangles are oriented with normals pointing out of the object. Because
//! `(2r+1)³` is odd no lattice value equals the iso-value exactly, so no vertex is degenerate.
//!
//! Cost follows the surface: only 8³ cell blocks whose neighbourhood holds both occupied and empty
//! voxels (or reaches the padding) are visited.
//!
//! On a binary occupancy every vertex sits at the middle of its lattice edge, so the surface is a
//! staircase of voxel faces. [`MeshParams::relax_iterations`] then relaxes it as a constrained
//! elastic surface net (Gibson, "Constrained elastic surface nets", MICCAI 1998): each vertex moves
//! towards the mean of its neighbours but stays on its own lattice edge, between the inside and the
//! outside lattice point it separates. The surface keeps separating exactly the same voxel centres
//! (it stays consistent with the occupancy), keeps its connectivity (closed and oriented), and lands
//! at sub-voxel positions instead of on the stairs.
//!
//! With [`MeshParams::remove_handles`] (on in [`MeshParams::smoothed`], what the scan methods use) the
//! occupancy first loses its voxel-scale handles ([`super::topology`]): a hole of a voxel or two
//! through a thin wall is plugged, a bridge a voxel or two thick over a groove is cut, changing only
//! voxels within one voxel of the surface; larger handles stay.

use std::collections::HashMap;

use rayon::prelude::*;

use super::occupancy::{Brick, Occupancy, BRICK};
use super::topology::{remove_small_handles, HandleRepair};

/// Parameters of [`extract_surface`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MeshParams {
    /// Box-smoothing radius, voxels (0 = none; at most [`MeshParams::MAX_SMOOTH_RADIUS`]).
    pub smooth_radius: u32,
    /// Constrained relaxation steps (module docs); 0 leaves every vertex where the interpolation put it.
    pub relax_iterations: u32,
    /// Remove voxel-scale handles (tunnels through thin walls, bridges over grooves) from the
    /// occupancy before meshing ([`remove_small_handles`]): the surface moves by at most about one
    /// voxel, only where that removes a handle.
    pub remove_handles: bool,
}

impl MeshParams {
    /// The largest supported smoothing radius, voxels.
    pub const MAX_SMOOTH_RADIUS: u32 = 7;
    /// Relaxation steps of [`MeshParams::smoothed`]: enough for the stairs of a voxel surface to settle
    /// (each step moves a vertex at most half-way to its neighbours' mean).
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

/// The six Kuhn tetrahedra of a cube, as corner offsets (bit 0: +x, bit 1: +y, bit 2: +z).
const TETS: [[u8; 4]; 6] = {
    let perms = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    let mut out = [[0u8; 4]; 6];
    let mut n = 0;
    while n < 6 {
        let p = perms[n];
        out[n] = [0, 1 << p[0], (1 << p[0]) | (1 << p[1]), 7];
        n += 1;
    }
    out
};

/// Output of one cell block: unique vertices as (edge key, lattice position), triangles as local indices.
type Part = (Vec<(u64, [f32; 3])>, Vec<[u32; 3]>);

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
        return march(occupancy, params).map(|mesh| (mesh, None));
    }
    let (repaired, stats) = remove_small_handles(occupancy);
    if stats.handles_removed() > 0 {
        tracing::info!(?stats, "voxel-scale handles removed before meshing");
    }
    march(&repaired, params).map(|mesh| (mesh, Some(stats)))
}

/// Marching tetrahedra and relaxation over `occupancy` as it is (`smooth_radius` already checked by
/// the caller).
fn march(occupancy: &Occupancy, params: &MeshParams) -> Result<TriangleMesh, MeshError> {
    let r = params.smooth_radius;
    if occupancy.grid().is_empty() {
        return Ok(TriangleMesh::default());
    }
    let r = r as i64;
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
    let parts: Vec<Part> = active.par_iter().map(|cb| march_block(occupancy, *cb, r, &dims)).collect();
    // Merge vertices shared between blocks by their edge key (each block's vertices are already unique).
    let mut keys: Vec<u64> = parts.iter().flat_map(|p| p.0.iter().map(|v| v.0)).collect();
    keys.par_sort_unstable();
    keys.dedup();
    if keys.len() > u32::MAX as usize {
        return Err(MeshError::TooLarge { vertices: keys.len() });
    }
    let grid = occupancy.grid();
    let s = grid.voxel_size;
    // Lattice positions first (relaxed there), metres at the end.
    let mut lattice = vec![[0f32; 3]; keys.len()];
    let mut triangles = Vec::with_capacity(parts.iter().map(|p| p.1.len()).sum());
    // Each block's vertices found among the keys side by side; the positions and triangles are
    // then gathered in block order.
    let globals: Vec<Vec<u32>> = parts
        .par_iter()
        .map(|(verts, _)| verts.iter().map(|(k, _)| keys.binary_search(k).unwrap_or(0) as u32).collect())
        .collect();
    for ((verts, tris), global) in parts.iter().zip(&globals) {
        for ((_, p), &g) in verts.iter().zip(global) {
            lattice[g as usize] = *p;
        }
        triangles.extend(tris.iter().map(|t| t.map(|i| global[i as usize])));
    }
    if params.relax_iterations > 0 {
        let pitch = [1u64, (dims[0] + 2) as u64, ((dims[0] + 2) * (dims[1] + 2)) as u64];
        relax_on_edges(&mut lattice, &keys, pitch, &triangles, params.relax_iterations);
    }
    let vertices =
        lattice.iter().map(|p| [0, 1, 2].map(|a| (grid.origin[a] + (p[a] as f64 - 0.5) * s) as f32)).collect();
    Ok(TriangleMesh { vertices, triangles, colors: None })
}

/// How far from either end of its lattice edge a relaxed vertex stays, as a fraction of the edge: keeps
/// every triangle non-degenerate.
const EDGE_MARGIN: f32 = 0.02;

/// Constrained relaxation (module docs): `lattice[v]` (lattice units) lies on the edge of `keys[v]`
/// (start point `key / 8` on the lattice of `pitch`, direction bits `key % 8`); each step moves it
/// half-way to the mean of its neighbours, projected back onto its edge and kept within
/// [`EDGE_MARGIN`] of its ends.
fn relax_on_edges(lattice: &mut [[f32; 3]], keys: &[u64], pitch: [u64; 3], triangles: &[[u32; 3]], iterations: u32) {
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
    let edges: Vec<([f32; 3], [f32; 3])> = keys
        .iter()
        .map(|&k| {
            let (lin, dir) = (k / 8, k % 8);
            let start = [lin % pitch[1], (lin / pitch[1]) % (pitch[2] / pitch[1]), lin / pitch[2]].map(|x| x as f32);
            let d = [0, 1, 2].map(|a| ((dir >> a) & 1) as f32);
            (start, d)
        })
        .collect();
    // Two buffers read and written in turn (a vertex without neighbours holds its start in both).
    let mut current = lattice.to_vec();
    let mut next = current.clone();
    for _ in 0..iterations {
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
            let (start, d) = edges[v];
            let target = [0, 1, 2].map(|a| 0.5 * (current[v][a] + mean[a] / ring.len() as f32));
            let d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            let t = (0..3).map(|a| (target[a] - start[a]) * d[a]).sum::<f32>() / d2;
            let t = t.clamp(EDGE_MARGIN, 1.0 - EDGE_MARGIN);
            *out = [0, 1, 2].map(|a| start[a] + t * d[a]);
        });
        std::mem::swap(&mut current, &mut next);
    }
    lattice.copy_from_slice(&current);
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

fn march_block(occ: &Occupancy, cb: [usize; 3], r: i64, dims: &[i64; 3]) -> Part {
    let base = cb.map(|c| (c * BRICK) as i64); // first lattice point
    let npts = [0, 1, 2].map(|a| ((dims[a] + 2) - base[a]).min(BRICK as i64 + 1) as usize);
    let ncells = npts.map(|n| n.saturating_sub(1));
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
    let e1 = [npts[0], ext[1], ext[2]];
    let sy = box_pass(&sx, e1, 1, w);
    let e2 = [npts[0], npts[1], ext[2]];
    let sums = box_pass(&sy, e2, 2, w);
    let total = (w * w * w) as f32;
    let at = |x: usize, y: usize, z: usize| sums[x + npts[0] * (y + npts[1] * z)];
    let inside = |s: u32| 2 * s as usize > w * w * w;
    let pitch = [1u64, (dims[0] + 2) as u64, ((dims[0] + 2) * (dims[1] + 2)) as u64];

    let mut verts: Vec<(u64, [f32; 3])> = Vec::new();
    let mut tris: Vec<[u32; 3]> = Vec::new();
    // Local vertex slot per (lattice point of this block, edge direction): u32::MAX = none yet.
    let mut slot = vec![u32::MAX; npts[0] * npts[1] * npts[2] * 8];
    for cz in 0..ncells[2] {
        for cy in 0..ncells[1] {
            for cx in 0..ncells[0] {
                let mut val = [0u32; 8];
                let mut mask = 0u8;
                for (n, v) in val.iter_mut().enumerate() {
                    *v = at(cx + (n & 1), cy + ((n >> 1) & 1), cz + ((n >> 2) & 1));
                    if inside(*v) {
                        mask |= 1 << n;
                    }
                }
                if mask == 0 || mask == 0xff {
                    continue;
                }
                let local = [cx, cy, cz];
                let cell = [base[0] + cx as i64, base[1] + cy as i64, base[2] + cz as i64];
                // Vertex on the cube edge between corners a and b (offset bit masks): (local index, position).
                let mut edge = |a: u8, b: u8| -> (u32, [f64; 3]) {
                    // Always interpolate from the subset corner (lower) to the superset one.
                    let (lo, hi) = if a & b == a { (a, b) } else { (b, a) };
                    let pl = [0, 1, 2].map(|k| (cell[k] + ((lo >> k) & 1) as i64) as f64);
                    let ph = [0, 1, 2].map(|k| (cell[k] + ((hi >> k) & 1) as i64) as f64);
                    let (fl, fh) = (val[lo as usize] as f32 / total, val[hi as usize] as f32 / total);
                    let t = ((0.5 - fl) / (fh - fl)) as f64;
                    let p = [0, 1, 2].map(|k| pl[k] + t * (ph[k] - pl[k]));
                    let l = [0, 1, 2].map(|k| local[k] + ((lo >> k) & 1) as usize);
                    let dir = (hi & !lo) as usize;
                    let si = (l[0] + npts[0] * (l[1] + npts[1] * l[2])) * 8 + dir;
                    if slot[si] == u32::MAX {
                        let lin = pl[0] as u64 * pitch[0] + pl[1] as u64 * pitch[1] + pl[2] as u64 * pitch[2];
                        slot[si] = verts.len() as u32;
                        verts.push((lin * 8 + dir as u64, p.map(|x| x as f32)));
                    }
                    (slot[si], p)
                };
                for tet in &TETS {
                    let (mut ins, mut outs) = ([0u8; 4], [0u8; 4]);
                    let (mut ni, mut no) = (0, 0);
                    for &c in tet {
                        if mask >> c & 1 == 1 {
                            ins[ni] = c;
                            ni += 1;
                        } else {
                            outs[no] = c;
                            no += 1;
                        }
                    }
                    if ni == 0 || no == 0 {
                        continue;
                    }
                    let probe = [0, 1, 2].map(|k| (cell[k] + ((ins[0] >> k) & 1) as i64) as f64);
                    let mut emit = |a: (u32, [f64; 3]), b: (u32, [f64; 3]), c: (u32, [f64; 3])| {
                        let (u, v) = (sub(b.1, a.1), sub(c.1, a.1));
                        let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
                        let d = sub(probe, a.1);
                        if n[0] * d[0] + n[1] * d[1] + n[2] * d[2] > 0.0 {
                            tris.push([a.0, c.0, b.0]);
                        } else {
                            tris.push([a.0, b.0, c.0]);
                        }
                    };
                    match ni {
                        1 => {
                            let i = ins[0];
                            let (a, b, c) = (edge(i, outs[0]), edge(i, outs[1]), edge(i, outs[2]));
                            emit(a, b, c);
                        }
                        3 => {
                            let o = outs[0];
                            let (a, b, c) = (edge(o, ins[0]), edge(o, ins[1]), edge(o, ins[2]));
                            emit(a, b, c);
                        }
                        _ => {
                            // Cyclic order around the quad: i0o0, i0o1, i1o1, i1o0.
                            let q0 = edge(ins[0], outs[0]);
                            let q1 = edge(ins[0], outs[1]);
                            let q2 = edge(ins[1], outs[1]);
                            let q3 = edge(ins[1], outs[0]);
                            emit(q0, q1, q2);
                            emit(q0, q2, q3);
                        }
                    }
                }
            }
        }
    }
    (verts, tris)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
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
    fn relaxation_leaves_the_stairs_for_sub_voxel_positions_on_their_edges() {
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
        assert!(after < 0.6 * before, "radial error {after} vs {before} on the stairs (voxel {voxel})");
        // Every vertex stays on its lattice edge: within half a diagonal of the stairs' vertex.
        for (a, b) in stairs.vertices.iter().zip(&relaxed.vertices) {
            let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt() as f64;
            assert!(d <= 0.5 * 3f64.sqrt() * voxel + 1e-6, "moved {d}");
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
