//! Mesh simplification by quadric error metrics (Garland & Heckbert, "Surface simplification using
//! quadric error metrics", SIGGRAPH 1997), to an error bound, keeping a closed mesh closed.
//!
//! Every vertex carries the quadric of the planes of its incident triangles (unweighted, unit
//! normals); an edge is collapsed into the point that minimises the sum of its ends' quadrics, the
//! cheapest edge first. The quadric's value at a point is the sum of the squared distances to every
//! plane it holds, so it bounds the largest of them: a collapse is made only while that sum stays
//! within the squared error bound, i.e. the new vertex lies within the bound of every plane of the
//! original triangles it stands for. A collapse is also refused when it would
//! - break the manifold: the two ends must share exactly the two neighbours opposite the edge (the
//!   link condition), and a closed component keeps at least five vertices;
//! - fold a triangle over: every triangle that moves must keep its normal within 90 degrees of its
//!   old one and must not become degenerate.
//!
//! [`simplify_within`] checks the result against the unsimplified surface by the sampled symmetric
//! Hausdorff distance ([`super::hausdorff`]) and simplifies again with half the bound while the
//! bound is exceeded, so the reported distance is within the stated bound.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use super::hausdorff::{hausdorff_distance, Hausdorff};
use super::mesh::TriangleMesh;

/// A symmetric 4x4 quadric `[A b; b' c]`, stored as its 10 upper-triangle coefficients.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Quadric([f64; 10]);

impl Quadric {
    /// The squared distance to the plane `n . x + d = 0` (`n` of unit length).
    fn plane(n: [f64; 3], d: f64) -> Quadric {
        let [a, b, c] = n;
        Quadric([a * a, a * b, a * c, a * d, b * b, b * c, b * d, c * c, c * d, d * d])
    }

    fn add(&mut self, o: &Quadric) {
        for (x, y) in self.0.iter_mut().zip(&o.0) {
            *x += y;
        }
    }

    fn sum(a: &Quadric, b: &Quadric) -> Quadric {
        let mut q = *a;
        q.add(b);
        q
    }

    /// The quadric's value at `p`: the sum of squared plane distances.
    fn eval(&self, p: [f64; 3]) -> f64 {
        let q = &self.0;
        let [x, y, z] = p;
        q[0] * x * x
            + 2.0 * q[1] * x * y
            + 2.0 * q[2] * x * z
            + 2.0 * q[3] * x
            + q[4] * y * y
            + 2.0 * q[5] * y * z
            + 2.0 * q[6] * y
            + q[7] * z * z
            + 2.0 * q[8] * z
            + q[9]
    }

    /// The point minimising the quadric, when its 3x3 part is well conditioned.
    fn minimiser(&self) -> Option<[f64; 3]> {
        let q = &self.0;
        let a = nalgebra::Matrix3::new(q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7]);
        // A positive semi-definite matrix's determinant is the product of its eigenvalues and its
        // trace their sum: a determinant far below (trace / 3)^3 means a nearly flat direction.
        let scale = (q[0] + q[4] + q[7]) / 3.0;
        if !(scale > 0.0 && a.determinant() > 1e-6 * scale * scale * scale) {
            return None;
        }
        let x = a.try_inverse()? * nalgebra::Vector3::new(-q[3], -q[6], -q[8]);
        x.iter().all(|v| v.is_finite()).then(|| [x[0], x[1], x[2]])
    }
}

/// A queued edge collapse: cost (f64 bits, non-negative so they order as the values), the edge's ends
/// and their versions when it was queued (stale once either end changed).
type Candidate = (u64, u32, u32, u32, u32);

/// Parameters of [`simplify`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimplifyParams {
    /// Largest distance from a new vertex to a plane of the original triangles it replaces, metres.
    pub max_error_m: f64,
}

/// What [`simplify`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct SimplifyStats {
    /// Triangles before.
    pub triangles_before: usize,
    /// Triangles after.
    pub triangles_after: usize,
    /// Edges collapsed.
    pub collapses: usize,
}

/// Simplify a closed, consistently oriented mesh (module docs). Colours follow the surviving
/// vertices. An edge shared by other than two triangles is never collapsed, so an open or
/// non-manifold input stays valid but is simplified less.
pub fn simplify(mesh: &TriangleMesh, params: &SimplifyParams) -> (TriangleMesh, SimplifyStats) {
    let mut stats = SimplifyStats { triangles_before: mesh.triangles.len(), ..SimplifyStats::default() };
    let n = mesh.vertices.len();
    let valid = mesh.triangles.iter().all(|t| t.iter().all(|&i| (i as usize) < n));
    let bound2 = params.max_error_m * params.max_error_m;
    if !(valid && bound2 > 0.0 && bound2.is_finite()) || mesh.triangles.is_empty() {
        stats.triangles_after = mesh.triangles.len();
        return (mesh.clone(), stats);
    }
    // Work relative to the centroid, in f64.
    let centre = {
        let mut c = [0f64; 3];
        for v in &mesh.vertices {
            for a in 0..3 {
                c[a] += f64::from(v[a]);
            }
        }
        c.map(|x| x / n.max(1) as f64)
    };
    let mut pos: Vec<[f64; 3]> = mesh.vertices.iter().map(|v| [0, 1, 2].map(|a| f64::from(v[a]) - centre[a])).collect();
    let mut tris: Vec<[u32; 3]> = mesh.triangles.clone();
    let mut alive_tri = vec![true; tris.len()];
    let mut quadric = vec![Quadric::default(); n];
    let mut around: Vec<Vec<u32>> = vec![Vec::new(); n];
    for (ti, t) in tris.iter().enumerate() {
        if let Some((normal, d)) = plane_of(&pos, t) {
            let q = Quadric::plane(normal, d);
            for &v in t {
                quadric[v as usize].add(&q);
            }
        }
        for &v in t {
            around[v as usize].push(ti as u32);
        }
    }
    let mut version = vec![0u32; n];
    let mut alive = vec![true; n];
    let mut heap: BinaryHeap<Reverse<Candidate>> = BinaryHeap::new();
    let push = |heap: &mut BinaryHeap<_>, pos: &[[f64; 3]], quadric: &[Quadric], version: &[u32], a: u32, b: u32| {
        let (cost, _) = best_position(pos, quadric, a, b);
        if cost <= bound2 {
            heap.push(Reverse((cost.max(0.0).to_bits(), a, b, version[a as usize], version[b as usize])));
        }
    };
    for t in &tris {
        for e in 0..3 {
            let (a, b) = (t[e], t[(e + 1) % 3]);
            if a < b {
                push(&mut heap, &pos, &quadric, &version, a, b);
            }
        }
    }
    let mut vertices_left = around.iter().filter(|r| !r.is_empty()).count();
    let mut ring_a: Vec<u32> = Vec::new();
    let mut ring_b: Vec<u32> = Vec::new();
    while let Some(Reverse((_, a, b, va, vb))) = heap.pop() {
        let (ai, bi) = (a as usize, b as usize);
        if !alive[ai] || !alive[bi] || version[ai] != va || version[bi] != vb {
            continue;
        }
        if vertices_left <= 4 {
            break;
        }
        // Link condition: the triangles on the edge are exactly two, and the ends share exactly their
        // two opposite vertices.
        let shared: Vec<u32> = around[ai].iter().copied().filter(|&t| tris[t as usize].contains(&b)).collect();
        if shared.len() != 2 {
            continue;
        }
        neighbours(&tris, &around[ai], a, &mut ring_a);
        neighbours(&tris, &around[bi], b, &mut ring_b);
        let common = ring_a.iter().filter(|v| ring_b.binary_search(v).is_ok()).count();
        if common != 2 {
            continue;
        }
        let (cost, p) = best_position(&pos, &quadric, a, b);
        if cost > bound2 {
            continue;
        }
        // No triangle that moves may fold over or degenerate.
        let folds = [a, b].iter().any(|&v| {
            around[v as usize].iter().filter(|t| !shared.contains(t)).any(|&t| {
                let tri = tris[t as usize];
                let old = tri.map(|i| pos[i as usize]);
                let new = tri.map(|i| if i == a || i == b { p } else { pos[i as usize] });
                let (n0, n1) = (cross_of(&old), cross_of(&new));
                let (l0, l1) = (norm(n0), norm(n1));
                l1 <= 1e-12 * l0.max(f64::MIN_POSITIVE) || dot(n0, n1) <= 0.0
            })
        });
        if folds {
            continue;
        }
        // Collapse a into b at p.
        for &t in &shared {
            alive_tri[t as usize] = false;
        }
        let moved: Vec<u32> = around[ai].iter().copied().filter(|t| !shared.contains(t)).collect();
        for &t in &moved {
            for v in tris[t as usize].iter_mut() {
                if *v == a {
                    *v = b;
                }
            }
        }
        let mut merged: Vec<u32> = around[bi].iter().copied().filter(|t| !shared.contains(t)).collect();
        merged.extend(moved);
        around[bi] = merged;
        around[ai].clear();
        for &t in &shared {
            for &v in &tris[t as usize] {
                if v != a && v != b {
                    around[v as usize].retain(|&x| x != t);
                }
            }
        }
        alive[ai] = false;
        pos[bi] = p;
        let qa = quadric[ai];
        quadric[bi].add(&qa);
        version[bi] += 1;
        vertices_left -= 1;
        stats.collapses += 1;
        neighbours(&tris, &around[bi], b, &mut ring_b);
        for &v in &ring_b {
            let (x, y) = if v < b { (v, b) } else { (b, v) };
            push(&mut heap, &pos, &quadric, &version, x, y);
        }
    }
    // Compact.
    let mut remap = vec![u32::MAX; n];
    let mut out = TriangleMesh::default();
    let mut colors = mesh.colors.as_ref().map(|_| Vec::new());
    for (t, _) in tris.iter().zip(&alive_tri).filter(|(_, &keep)| keep) {
        out.triangles.push(t.map(|i| {
            if remap[i as usize] == u32::MAX {
                remap[i as usize] = out.vertices.len() as u32;
                out.vertices.push([0, 1, 2].map(|a| (pos[i as usize][a] + centre[a]) as f32));
                if let (Some(dst), Some(src)) = (colors.as_mut(), mesh.colors.as_ref()) {
                    dst.push(src.get(i as usize).copied().unwrap_or([128, 128, 128]));
                }
            }
            remap[i as usize]
        }));
    }
    out.colors = colors;
    stats.triangles_after = out.triangles.len();
    (out, stats)
}

/// The result of [`simplify_within`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Simplification {
    /// The error bound asked for, metres.
    pub max_error_m: f64,
    /// The plane-distance bound of the simplification that was kept, metres (the asked bound, halved
    /// once per retry).
    pub used_error_m: f64,
    /// Triangle counts and collapses of the kept simplification.
    #[serde(flatten)]
    pub stats: SimplifyStats,
    /// Sampled symmetric Hausdorff distance between the simplified and the unsimplified surface.
    pub hausdorff: Hausdorff,
}

/// Simplifications tried by [`simplify_within`] before it gives up and keeps the mesh as it is.
const ATTEMPTS: usize = 4;

/// Simplify `mesh` so that its sampled symmetric Hausdorff distance to the input (`samples` area
/// samples per surface plus every vertex) is at most `max_error_m`: [`simplify`] with that bound,
/// then with half of it while the distance exceeds the bound; after [`ATTEMPTS`] the input is kept
/// unchanged (distance 0). `None` when `max_error_m` is not positive (nothing is done).
pub fn simplify_within(
    mesh: &TriangleMesh,
    max_error_m: f64,
    samples: usize,
) -> Option<(TriangleMesh, Simplification)> {
    if !(max_error_m > 0.0 && max_error_m.is_finite()) {
        return None;
    }
    let mut bound = max_error_m;
    for _ in 0..ATTEMPTS {
        let (simple, stats) = simplify(mesh, &SimplifyParams { max_error_m: bound });
        let hausdorff = hausdorff_distance(&simple, mesh, samples).unwrap_or_default();
        if hausdorff.symmetric_m <= max_error_m {
            return Some((simple, Simplification { max_error_m, used_error_m: bound, stats, hausdorff }));
        }
        bound *= 0.5;
    }
    let stats =
        SimplifyStats { triangles_before: mesh.triangles.len(), triangles_after: mesh.triangles.len(), collapses: 0 };
    Some((mesh.clone(), Simplification { max_error_m, used_error_m: 0.0, stats, hausdorff: Hausdorff::default() }))
}

/// The cheapest point for collapsing edge `a`-`b` and its quadric cost: the quadric's minimiser when it
/// is well defined and near the edge, else the better of the ends and the midpoint.
fn best_position(pos: &[[f64; 3]], quadric: &[Quadric], a: u32, b: u32) -> (f64, [f64; 3]) {
    let q = Quadric::sum(&quadric[a as usize], &quadric[b as usize]);
    let (pa, pb) = (pos[a as usize], pos[b as usize]);
    let mid = [0, 1, 2].map(|k| 0.5 * (pa[k] + pb[k]));
    let len = norm(sub(pb, pa));
    let mut best = (f64::INFINITY, mid);
    let near = |p: &[f64; 3]| norm(sub(*p, mid)) <= 2.0 * len;
    for p in q.minimiser().filter(near).into_iter().chain([pa, pb, mid]) {
        let c = q.eval(p);
        if c < best.0 {
            best = (c, p);
        }
    }
    (best.0.max(0.0), best.1)
}

/// The distinct vertices of `tris` (indices into `all`) other than `v`, sorted.
fn neighbours(all: &[[u32; 3]], tris: &[u32], v: u32, out: &mut Vec<u32>) {
    out.clear();
    for &t in tris {
        out.extend(all[t as usize].iter().copied().filter(|&x| x != v));
    }
    out.sort_unstable();
    out.dedup();
}

/// Unit normal and offset of a triangle's plane; `None` for a degenerate triangle.
fn plane_of(pos: &[[f64; 3]], t: &[u32; 3]) -> Option<([f64; 3], f64)> {
    let n = cross_of(&t.map(|i| pos[i as usize]));
    let l = norm(n);
    if !(l > 0.0 && l.is_finite()) {
        return None;
    }
    let n = n.map(|x| x / l);
    Some((n, -dot(n, pos[t[0] as usize])))
}

fn cross_of(p: &[[f64; 3]; 3]) -> [f64; 3] {
    let (u, v) = (sub(p[1], p[0]), sub(p[2], p[0]));
    [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, VoxelGrid};
    use crate::pipeline::{extract_surface, MeshParams, Occupancy};

    fn mesh_of(occ: &Occupancy) -> TriangleMesh {
        extract_surface(occ, &MeshParams::smoothed(0)).expect("mesh")
    }

    #[test]
    fn a_box_simplifies_to_few_triangles_and_stays_closed() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.03; 3] }, 30);
        let occ = Occupancy::from_index_fn(grid, |i, j, k| {
            (4..26).contains(&i) && (6..24).contains(&j) && (3..20).contains(&k)
        });
        let mesh = extract_surface(&occ, &MeshParams::default()).expect("mesh");
        let bound = 0.25 * grid.voxel_size;
        let (simple, stats) = simplify(&mesh, &SimplifyParams { max_error_m: bound });
        assert_eq!(stats.triangles_before, mesh.triangles.len());
        assert_eq!(stats.triangles_after, simple.triangles.len());
        assert!(simple.triangles.len() * 20 < mesh.triangles.len(), "{stats:?}");
        let topo = simple.topology();
        assert_eq!((topo.components, topo.open_or_misoriented_edges, topo.euler_characteristic), (1, 0, 2));
        let v0 = mesh.signed_volume();
        assert!((simple.signed_volume() - v0).abs() < 0.02 * v0);
        let h = hausdorff_distance(&simple, &mesh, 20_000).expect("distance");
        assert!(h.symmetric_m <= bound * 1.01, "{h:?} vs {bound}");
    }

    #[test]
    fn a_sphere_and_a_torus_keep_their_topology_within_the_bound() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0; 3] }, 40);
        let sphere = Occupancy::from_fn(grid, |p| p.norm() < 0.7);
        let torus = Occupancy::from_fn(grid, |p| {
            let r = (p.x * p.x + p.y * p.y).sqrt() - 0.55;
            r * r + p.z * p.z < 0.25 * 0.25
        });
        for (name, occ, euler) in [("sphere", sphere, 2), ("torus", torus, 0)] {
            let mesh = mesh_of(&occ);
            let bound = 0.2 * grid.voxel_size;
            let (simple, s) = simplify_within(&mesh, bound, 20_000).expect("bound > 0");
            assert!(s.stats.triangles_after * 3 < s.stats.triangles_before, "{name}: {s:?}");
            assert!(s.hausdorff.symmetric_m <= bound, "{name}: {s:?}");
            let topo = simple.topology();
            assert_eq!(topo.open_or_misoriented_edges, 0, "{name}");
            assert_eq!((topo.components, topo.euler_characteristic), (1, euler), "{name}");
            assert!(simple.signed_volume() > 0.0);
        }
        assert!(simplify_within(&mesh_of(&Occupancy::full(grid)), 0.0, 100).is_none());
    }

    #[test]
    fn colours_follow_the_surviving_vertices() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [1.0; 3] }, 12);
        let occ = Occupancy::from_index_fn(grid, |i, j, k| (2..10).contains(&i) && (2..10).contains(&j) && k < 9);
        let mut mesh = extract_surface(&occ, &MeshParams::default()).expect("mesh");
        mesh.colors = Some(vec![[10, 20, 30]; mesh.vertices.len()]);
        let (simple, _) = simplify(&mesh, &SimplifyParams { max_error_m: 0.01 });
        let colours = simple.colors.as_ref().expect("colours");
        assert_eq!(colours.len(), simple.vertices.len());
        assert!(colours.iter().all(|c| *c == [10, 20, 30]));
    }
}
