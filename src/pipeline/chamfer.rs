//! Symmetric Chamfer distance between point sets, and area-weighted point samples of a triangle mesh.
//!
//! Nearest neighbours come from a kd-tree ([`PointIndex`]), so a query far from the other set (a
//! poor reconstruction) costs no more than a near one. Queries run in parallel with rayon. Points are in metres,
//! in whatever frame both sets share.

use rayon::prelude::*;

use super::mesh::TriangleMesh;

/// A nearest-neighbour index over a fixed point set (metres): a balanced kd-tree stored in place
/// (the median of each range splits it along the range's widest axis), so a query costs about
/// log2(n) steps however far it is from the points. Non-finite points are left out.
#[derive(Debug, Clone)]
pub struct PointIndex {
    /// The points, reordered into the tree: the node of range `lo..hi` is at `(lo + hi) / 2`.
    points: Vec<[f32; 3]>,
    /// The split axis of each node, by position in `points`.
    axes: Vec<u8>,
}

impl PointIndex {
    /// Index `points`.
    pub fn new(points: &[[f32; 3]]) -> PointIndex {
        let mut pts: Vec<[f32; 3]> = points.iter().copied().filter(|p| p.iter().all(|c| c.is_finite())).collect();
        let mut axes = vec![0u8; pts.len()];
        build(&mut pts, &mut axes);
        PointIndex { points: pts, axes }
    }

    /// Points indexed.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether the index holds no point.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Distance from `q` to the nearest indexed point, metres; `None` for an empty index or a
    /// non-finite query.
    pub fn nearest_distance(&self, q: &[f32; 3]) -> Option<f32> {
        if self.points.is_empty() || !q.iter().all(|c| c.is_finite()) {
            return None;
        }
        let mut best = f32::INFINITY;
        self.search(q, 0, self.points.len(), &mut best);
        Some(best.sqrt())
    }

    fn search(&self, q: &[f32; 3], lo: usize, hi: usize, best: &mut f32) {
        if lo >= hi {
            return;
        }
        let mid = (lo + hi) / 2;
        let p = &self.points[mid];
        let d2 = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
        if d2 < *best {
            *best = d2;
        }
        let axis = self.axes[mid] as usize;
        let diff = q[axis] - p[axis];
        let (near, far) = if diff < 0.0 { ((lo, mid), (mid + 1, hi)) } else { ((mid + 1, hi), (lo, mid)) };
        self.search(q, near.0, near.1, best);
        if diff * diff < *best {
            self.search(q, far.0, far.1, best);
        }
    }
}

/// Arrange `pts` as an implicit kd-tree (see [`PointIndex`]), recording each node's axis.
fn build(pts: &mut [[f32; 3]], axes: &mut [u8]) {
    if pts.len() <= 1 {
        return;
    }
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in pts.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let mid = pts.len() / 2;
    pts.select_nth_unstable_by(mid, |x, y| x[axis].total_cmp(&y[axis]));
    axes[mid] = axis as u8;
    let (left, rest) = pts.split_at_mut(mid);
    let (left_axes, rest_axes) = axes.split_at_mut(mid);
    build(left, left_axes);
    build(&mut rest[1..], &mut rest_axes[1..]);
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
    let corners = |t: &[u32; 3]| Some([vertex(t[0])?, vertex(t[1])?, vertex(t[2])?]);
    // A triangle with a corner out of range counts as no area, so it is never picked.
    let mut cumulative = Vec::with_capacity(mesh.triangles.len());
    let mut total = 0.0f64;
    // The last triangle with area: a pick rounded up to the total lands on it.
    let mut last = 0;
    for (i, t) in mesh.triangles.iter().enumerate() {
        if let Some([a, b, c]) = corners(t) {
            let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let x = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
            let area = 0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
            if area.is_finite() && area > 0.0 {
                total += area;
                last = i;
            }
        }
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
        .filter_map(|_| {
            let pick = next() * total;
            let t = cumulative.partition_point(|&c| c <= pick).min(last);
            let [a, b, c] = corners(&mesh.triangles[t])?;
            let (mut r1, mut r2) = (next(), next());
            if r1 + r2 > 1.0 {
                (r1, r2) = (1.0 - r1, 1.0 - r2);
            }
            Some([0, 1, 2].map(|k| (a[k] + r1 * (b[k] - a[k]) + r2 * (c[k] - a[k])) as f32))
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
