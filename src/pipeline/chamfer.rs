//! Symmetric Chamfer distance between point sets, and area-weighted point samples of a triangle mesh.
//!
//! Nearest neighbours come from a uniform voxel hash ([`PointIndex`]): points are bucketed in cubic
//! cells, a query visits shells of cells around its own cell, nearest first, and stops as soon as no
//! unvisited shell can hold a closer point. Queries run in parallel with rayon. Points are in metres,
//! in whatever frame both sets share.

use std::collections::HashMap;

use rayon::prelude::*;

use super::mesh::TriangleMesh;

/// A nearest-neighbour index over a fixed set of points (metres): a pyramid of voxel hashes, each
/// level's cells four times the size of the previous one's, so a query far from every point finds
/// its neighbour in a few shells of a coarse level instead of many empty shells of the finest.
#[derive(Debug, Clone)]
pub struct PointIndex {
    /// Finest first; the last level has cells at least as large as the points' bounding box.
    levels: Vec<Level>,
    len: usize,
}

#[derive(Debug, Clone)]
struct Level {
    cell_m: f32,
    cells: HashMap<[i32; 3], Vec<[f32; 3]>>,
    /// Smallest and largest occupied cell index per axis.
    cell_lo: [i32; 3],
    cell_hi: [i32; 3],
}

/// Shells searched on a level before moving to a coarser one.
const SHELLS_PER_LEVEL: i32 = 4;

impl Level {
    fn new(points: &[[f32; 3]], cell_m: f32) -> Level {
        let mut cells: HashMap<[i32; 3], Vec<[f32; 3]>> = HashMap::new();
        for p in points {
            cells.entry(cell_of(p, cell_m)).or_default().push(*p);
        }
        let (mut cell_lo, mut cell_hi) = ([i32::MAX; 3], [i32::MIN; 3]);
        for k in cells.keys() {
            for a in 0..3 {
                cell_lo[a] = cell_lo[a].min(k[a]);
                cell_hi[a] = cell_hi[a].max(k[a]);
            }
        }
        Level { cell_m, cells, cell_lo, cell_hi }
    }

    /// The nearest squared distance if it is certain after at most `max_shells` shells beyond the
    /// points' box (`None` if the search stopped before it was certain).
    fn search(&self, q: &[f32; 3], max_shells: i32) -> Option<f32> {
        let c = cell_of(q, self.cell_m);
        // Shells between q's cell and the points' box hold nothing.
        let offset = (0..3).map(|a| (self.cell_lo[a] - c[a]).max(c[a] - self.cell_hi[a]).max(0)).max().unwrap_or(0);
        let span = (0..3).map(|a| self.cell_hi[a] - self.cell_lo[a]).max().unwrap_or(0);
        let d2 = |p: &[f32; 3]| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
        let mut best2 = f32::INFINITY;
        let mut r = offset;
        loop {
            // Every point in shell r or beyond is at least (r - 1) cells away from q.
            let floor = (r - 1).max(0) as f32 * self.cell_m;
            if best2.is_finite() && floor * floor > best2 {
                return Some(best2);
            }
            if r > offset + span + 2 {
                // Every cell of the box was visited.
                return best2.is_finite().then_some(best2);
            }
            if r > offset + max_shells {
                return None;
            }
            for dz in -r..=r {
                for dy in -r..=r {
                    let on_face = dz.abs() == r || dy.abs() == r;
                    let step = if on_face || r == 0 { 1 } else { 2 * r };
                    let mut dx = -r;
                    while dx <= r {
                        if let Some(pts) = self.cells.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                            best2 = pts.iter().map(d2).fold(best2, f32::min);
                        }
                        dx += step;
                    }
                }
            }
            r += 1;
        }
    }
}

impl PointIndex {
    /// Index `points` (metres), the finest level sized for a few points per cell on a surface
    /// sample. Non-finite points are ignored.
    pub fn new(points: &[[f32; 3]]) -> PointIndex {
        let finite: Vec<[f32; 3]> = points.iter().copied().filter(|p| p.iter().all(|c| c.is_finite())).collect();
        if finite.is_empty() {
            return PointIndex { levels: Vec::new(), len: 0 };
        }
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for p in &finite {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let diag = ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt();
        // Surface samples: about n^(1/2) cells along the diagonal keeps a few points per cell.
        let per_side = (finite.len() as f32).sqrt().max(1.0);
        let mut cell_m = if diag > 0.0 { (diag / per_side).max(1e-6) } else { 1.0 };
        let mut levels = Vec::new();
        loop {
            levels.push(Level::new(&finite, cell_m));
            if cell_m >= diag || levels.len() >= 12 {
                break;
            }
            cell_m *= 4.0;
        }
        PointIndex { levels, len: finite.len() }
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when nothing is indexed.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Distance from `q` to the nearest indexed point, metres; `None` for an empty index or a
    /// non-finite query.
    pub fn nearest_distance(&self, q: &[f32; 3]) -> Option<f32> {
        if !q.iter().all(|c| c.is_finite()) {
            return None;
        }
        let (last, finer) = self.levels.split_last()?;
        finer
            .iter()
            .find_map(|level| level.search(q, SHELLS_PER_LEVEL))
            .or_else(|| last.search(q, i32::MAX / 4))
            .map(f32::sqrt)
    }
}

fn cell_of(p: &[f32; 3], cell: f32) -> [i32; 3] {
    p.map(|x| (x / cell).floor().clamp(i32::MIN as f32 / 2.0, i32::MAX as f32 / 2.0) as i32)
}

/// The Chamfer distance between point sets `a` and `b`, metres.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Chamfer {
    /// Mean distance from a point of `a` to its nearest point of `b`.
    pub a_to_b_m: f64,
    /// Mean distance from a point of `b` to its nearest point of `a`.
    pub b_to_a_m: f64,
    /// The symmetric Chamfer distance: the mean of the two directed means.
    pub symmetric_m: f64,
}

/// Symmetric Chamfer distance between `a` and `b` (metres, same frame); `None` if either is empty.
pub fn chamfer_distance(a: &[[f32; 3]], b: &[[f32; 3]]) -> Option<Chamfer> {
    let (ia, ib) = (PointIndex::new(a), PointIndex::new(b));
    let directed = |from: &[[f32; 3]], to: &PointIndex| -> Option<f64> {
        let (sum, n) = from
            .par_iter()
            .filter_map(|p| to.nearest_distance(p))
            .map(|d| (f64::from(d), 1usize))
            .reduce(|| (0.0, 0), |x, y| (x.0 + y.0, x.1 + y.1));
        (n > 0).then(|| sum / n as f64)
    };
    let a_to_b_m = directed(a, &ib)?;
    let b_to_a_m = directed(b, &ia)?;
    Some(Chamfer { a_to_b_m, b_to_a_m, symmetric_m: 0.5 * (a_to_b_m + b_to_a_m) })
}

/// `n` points on `mesh`, uniform by area (a triangle is picked with probability proportional to its
/// area, then a uniform point in it). Deterministic given `seed`. Empty for a mesh without area.
pub fn sample_mesh(mesh: &TriangleMesh, n: usize, seed: u64) -> Vec<[f32; 3]> {
    let vertex = |i: u32| mesh.vertices.get(i as usize).map(|v| v.map(f64::from));
    let tris: Vec<[[f64; 3]; 3]> =
        mesh.triangles.iter().filter_map(|t| Some([vertex(t[0])?, vertex(t[1])?, vertex(t[2])?])).collect();
    let mut cumulative = Vec::with_capacity(tris.len());
    let mut total = 0.0f64;
    for [a, b, c] in &tris {
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let x = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        let area = 0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
        total += if area.is_finite() { area } else { 0.0 };
        cumulative.push(total);
    }
    if total <= 0.0 {
        return Vec::new();
    }
    let mut state = seed ^ 0x9e37_79b9_7f4a_7c15;
    let mut next = move || {
        // SplitMix64.
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let pick = next() * total;
            let t = cumulative.partition_point(|&c| c <= pick).min(tris.len() - 1);
            let [a, b, c] = tris[t];
            let (mut r1, mut r2) = (next(), next());
            if r1 + r2 > 1.0 {
                (r1, r2) = (1.0 - r1, 1.0 - r2);
            }
            [0, 1, 2].map(|k| (a[k] + r1 * (b[k] - a[k]) + r2 * (c[k] - a[k])) as f32)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute_nearest(points: &[[f32; 3]], q: &[f32; 3]) -> f32 {
        points
            .iter()
            .map(|p| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt())
            .fold(f32::INFINITY, f32::min)
    }

    /// Points on a sphere of radius `r` (Fibonacci lattice).
    fn sphere(n: usize, r: f32) -> Vec<[f32; 3]> {
        let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
        (0..n)
            .map(|i| {
                let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
                let rho = (1.0 - z * z).sqrt();
                let phi = golden * i as f32;
                [r * rho * phi.cos(), r * rho * phi.sin(), r * z]
            })
            .collect()
    }

    #[test]
    fn nearest_matches_brute_force_inside_and_far_outside() {
        let pts = sphere(2000, 0.05);
        let index = PointIndex::new(&pts);
        assert_eq!(index.len(), 2000);
        for q in sphere(97, 0.047).into_iter().chain(sphere(13, 0.3)).chain([[0.0, 0.0, 0.0], [1.0, -2.0, 0.5]]) {
            let got = index.nearest_distance(&q).expect("non-empty");
            let want = brute_nearest(&pts, &q);
            assert!((got - want).abs() < 1e-6, "{q:?}: {got} vs {want}");
        }
        assert_eq!(PointIndex::new(&[]).nearest_distance(&[0.0; 3]), None);
    }

    #[test]
    fn concentric_spheres_are_their_radius_gap_apart() {
        // Dense samples of spheres of radius 5 cm and 5.2 cm: every nearest distance is about 2 mm.
        let a = sphere(20_000, 0.05);
        let b = sphere(20_000, 0.052);
        let c = chamfer_distance(&a, &b).expect("non-empty");
        assert!((c.a_to_b_m - 0.002).abs() < 2e-4, "{c:?}");
        assert!((c.b_to_a_m - 0.002).abs() < 2e-4, "{c:?}");
        // Identical sets are 0 apart; a set and a translated copy are the translation apart (at most).
        assert_eq!(chamfer_distance(&a, &a).expect("non-empty").symmetric_m, 0.0);
        let shifted: Vec<[f32; 3]> = a.iter().map(|p| [p[0] + 0.001, p[1], p[2]]).collect();
        let s = chamfer_distance(&a, &shifted).expect("non-empty").symmetric_m;
        assert!(s > 1e-4 && s <= 0.001 + 1e-6, "{s}");
        assert!(chamfer_distance(&a, &[]).is_none());
    }

    #[test]
    fn mesh_samples_are_uniform_by_area_and_on_the_triangles() {
        // Two triangles in the z = 0 plane, one with three times the other's area.
        let mesh = TriangleMesh {
            vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [3.0, 0.0, 0.0], [0.0, 3.0, 0.0]],
            triangles: vec![[0, 1, 2], [1, 3, 4]],
            colors: None,
        };
        // Areas: 0.5 and (first: (1,0),(3,0),(0,3)) = 0.5 * |(2,0) x (-1,3)| = 3.
        let pts = sample_mesh(&mesh, 35_000, 7);
        assert_eq!(pts.len(), 35_000);
        assert!(pts.iter().all(|p| p[2] == 0.0 && p[0] >= -1e-6 && p[1] >= -1e-6 && p[0] + p[1] <= 3.0 + 1e-5));
        let in_small = pts.iter().filter(|p| p[0] + p[1] <= 1.0).count() as f64 / pts.len() as f64;
        assert!((in_small - 0.5 / 3.5).abs() < 0.01, "{in_small}");
        assert_eq!(pts, sample_mesh(&mesh, 35_000, 7));
        assert!(sample_mesh(&TriangleMesh::default(), 10, 1).is_empty());
    }
}
