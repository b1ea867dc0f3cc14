//! Sampled Hausdorff distance between two triangle surfaces, point-to-triangle exact.
//!
//! Each surface is sampled at its vertices plus area-uniform points ([`super::chamfer::sample_mesh`]);
//! each sample's distance to the other surface is the exact distance to its nearest triangle, found
//! through a dense uniform grid of triangle bounding boxes searched in growing shells of cells. The
//! directed distance is the largest over the samples (a lower bound of the true directed Hausdorff
//! distance that converges as the samples grow dense), the symmetric one the larger of both.
//!
//! A caller that already bounds the distance of a surface's vertices to the other surface (a
//! simplification tracks every input vertex on a triangle of its output) passes the bounds to
//! [`hausdorff_outliers_to`]: a vertex whose bound cannot reach the largest distance the area samples
//! measured, nor the outlier threshold, is then not measured, which leaves the maxima and the
//! outliers as they were and spares most of the queries.

use std::cmp::Ordering;

use rayon::prelude::*;

use super::chamfer::sample_mesh;
use super::mesh::TriangleMesh;

/// A sampled symmetric Hausdorff distance, metres.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Hausdorff {
    /// Largest distance from a sample of the first surface to the second.
    pub forward_m: f64,
    /// Largest distance from a sample of the second surface to the first.
    pub backward_m: f64,
    /// The larger of both.
    pub symmetric_m: f64,
    /// Mean distance over the area samples of both directions (the vertices count in the maxima
    /// only: they are as many as the mesh is fine, not as its area is large).
    pub mean_m: f64,
    /// Samples per direction: the surface's vertices plus its area samples (a vertex whose distance
    /// a caller's bound keeps below the maximum counts without being measured).
    pub samples: [usize; 2],
}

/// Nearest-triangle queries over one mesh (module docs): a dense grid of cells, each listing the
/// triangles whose bounding box reaches it (flat arrays). The triangles are stored once each, packed
/// (corners as the mesh holds them, in `f32`, and a bounding sphere in `f32`: 52 bytes a triangle
/// where `f64` copies took 104) and ordered by the cell of their centroid, so a cell's triangles sit
/// close together in memory. Distances are computed in `f64` from those corners, exactly as before.
#[derive(Debug)]
pub struct TriangleIndex<'a> {
    mesh: &'a TriangleMesh,
    /// The indexed triangles in cell order.
    tris: Vec<Packed>,
    /// Cell edge, metres.
    cell: f64,
    /// Corner of cell `[0, 0, 0]`, metres.
    origin: [f64; 3],
    /// Cells per axis.
    dims: [i32; 3],
    /// The triangles of cell `c` are `items[start[c]..start[c + 1]]` (indices into `tris`).
    start: Vec<u32>,
    items: Vec<u32>,
}

/// One indexed triangle: its corners exactly as the mesh stores them (metres) and a sphere around
/// it (centre and radius, metres; the radius rounded up so that the sphere holds every point of the
/// triangle), to skip the exact distance to triangles that cannot be nearer than the nearest found.
#[derive(Debug, Clone, Copy)]
struct Packed {
    corners: [[f32; 3]; 3],
    centre: [f32; 3],
    radius: f32,
}

impl Packed {
    fn new(corners: [[f32; 3]; 3]) -> Packed {
        let c = corners.map(|p| p.map(f64::from));
        let centre = [0, 1, 2].map(|k| ((c[0][k] + c[1][k] + c[2][k]) / 3.0) as f32);
        let r2 = c.iter().map(|p| dist2(*p, centre.map(f64::from))).fold(0.0, f64::max);
        // f32 keeps 24 bits: a millionth more rounds to a value at or above the exact radius.
        Packed { corners, centre, radius: (r2.sqrt() * (1.0 + 1e-6)) as f32 }
    }

    fn corners(&self) -> [[f64; 3]; 3] {
        self.corners.map(|p| p.map(f64::from))
    }
}

/// Most cells per axis of a [`TriangleIndex`].
const MAX_CELLS_PER_AXIS: f64 = 256.0;

impl<'a> TriangleIndex<'a> {
    /// Index the triangles of `mesh` (those with indices out of range are left out); `None` when none is left.
    ///
    /// The per-triangle steps run in parallel; the sums and the cell lists are made in triangle
    /// order, so the index is the same on any number of threads.
    pub fn new(mesh: &'a TriangleMesh) -> Option<TriangleIndex<'a>> {
        let n = mesh.vertices.len();
        let packed: Vec<Packed> = mesh
            .triangles
            .par_iter()
            .filter(|t| t.iter().all(|&i| (i as usize) < n))
            .map(|t| Packed::new(t.map(|i| mesh.vertices[i as usize])))
            .collect();
        if packed.is_empty() {
            return None;
        }
        // Cell edge: twice the mean bounding-box extent of a triangle, so a triangle spans few cells.
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        let mut extent = 0.0;
        for p in &packed {
            let (a, b) = bbox(&p.corners());
            for k in 0..3 {
                lo[k] = lo[k].min(a[k]);
                hi[k] = hi[k].max(b[k]);
                extent += b[k] - a[k];
            }
        }
        if !(0..3).all(|k| lo[k].is_finite() && hi[k].is_finite()) {
            return None;
        }
        let span = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
        let cell = (2.0 * extent / (3 * packed.len()) as f64).max(span / MAX_CELLS_PER_AXIS).max(1e-9);
        let dims = [0, 1, 2].map(|k| (((hi[k] - lo[k]) / cell).floor() as i32 + 1).max(1));
        let mut index =
            TriangleIndex { mesh, tris: Vec::new(), cell, origin: lo, dims, start: Vec::new(), items: Vec::new() };
        let cells = dims.iter().map(|&d| d as usize).product::<usize>();
        // The triangles in the order of their centroid's cell (a counting sort).
        let home: Vec<u32> = packed
            .par_iter()
            .map(|p| index.cell_index(index.clamped_cell_of(p.centre.map(f64::from))) as u32)
            .collect();
        let mut count = vec![0u32; cells + 1];
        for &h in &home {
            count[h as usize + 1] += 1;
        }
        for i in 0..cells {
            count[i + 1] += count[i];
        }
        let mut order = vec![0u32; packed.len()];
        for (t, &h) in home.iter().enumerate() {
            order[count[h as usize] as usize] = t as u32;
            count[h as usize] += 1;
        }
        drop(home);
        index.tris = order.par_iter().map(|&t| packed[t as usize]).collect();
        drop(packed);
        // Each cell's list of the triangles whose bounding box reaches it: the box's cell ranges
        // found side by side, then counted and filled in triangle order.
        let ranges: Vec<[[i32; 3]; 2]> = index.tris.par_iter().map(|p| index.cell_range(&p.corners())).collect();
        count.fill(0);
        for r in &ranges {
            index.for_cells_in(r, |i| count[i] += 1);
        }
        let mut total = 0u32;
        for c in count.iter_mut() {
            let k = *c;
            *c = total;
            total += k;
        }
        let mut fill = count.clone();
        let mut items = vec![0u32; total as usize];
        for (t, r) in ranges.iter().enumerate() {
            index.for_cells_in(r, |i| {
                items[fill[i] as usize] = t as u32;
                fill[i] += 1;
            });
        }
        index.start = count;
        index.items = items;
        Some(index)
    }

    /// The mesh indexed.
    pub fn mesh(&self) -> &TriangleMesh {
        self.mesh
    }

    fn cell_of(&self, p: [f64; 3]) -> [i32; 3] {
        [0, 1, 2].map(|k| self.cell_of_axis(p[k], k))
    }

    /// The cell of `p`, clamped to the grid.
    fn clamped_cell_of(&self, p: [f64; 3]) -> [i32; 3] {
        let c = self.cell_of(p);
        [0, 1, 2].map(|k| c[k].clamp(0, self.dims[k] - 1))
    }

    /// The cell index along axis `k` of coordinate `x` (metres), unclamped to the grid.
    fn cell_of_axis(&self, x: f64, k: usize) -> i32 {
        // `floor` without the library call: truncate, then step down for negative fractions.
        let f = ((x - self.origin[k]) / self.cell).clamp(-1e9, 1e9);
        let t = f as i32;
        t - i32::from(f64::from(t) > f)
    }

    fn cell_index(&self, c: [i32; 3]) -> usize {
        (c[0] as usize) + self.dims[0] as usize * ((c[1] as usize) + self.dims[1] as usize * c[2] as usize)
    }

    /// The first and last cell (clamped to the grid) the triangle's bounding box reaches.
    fn cell_range(&self, corners: &[[f64; 3]; 3]) -> [[i32; 3]; 2] {
        let (a, b) = bbox(corners);
        [self.clamped_cell_of(a), self.clamped_cell_of(b)]
    }

    /// Call `f` with the index of every cell from `ca` to `cb` (a [`Self::cell_range`]).
    fn for_cells_in(&self, [ca, cb]: &[[i32; 3]; 2], mut f: impl FnMut(usize)) {
        for z in ca[2]..=cb[2] {
            for y in ca[1]..=cb[1] {
                for x in ca[0]..=cb[0] {
                    f(self.cell_index([x, y, z]));
                }
            }
        }
    }

    /// Distance from `q` to the nearest triangle, metres.
    ///
    /// The cells are searched in growing shells around `q`'s cell until a triangle is found; every
    /// triangle nearer than that one has a point inside the box of half-width that distance around
    /// `q`, and is listed in the cell holding that point, so searching the cells of that box once
    /// more finds the nearest.
    pub fn distance(&self, q: [f64; 3]) -> f64 {
        self.nearest(q, NO_HINT).0
    }

    /// [`Self::distance`] and the nearest triangle (an index into `tris`; [`NO_HINT`] when there is
    /// none), starting from triangle `hint` when it is within a cell edge of `q`: triangles whose
    /// sphere is beyond it are skipped without their exact distance. Any hint gives the smallest
    /// of the triangles' distances, as no hint does: the search only skips a triangle whose sphere
    /// says it cannot be nearer than one already measured (a test that, as before, rounds only
    /// where two triangles are within rounding of the same distance).
    fn nearest(&self, q: [f64; 3], hint: u32) -> (f64, u32) {
        let c = self.cell_of(q);
        let mut best = Best { d2: f64::INFINITY, d: f64::INFINITY, tri: NO_HINT };
        if let Some(p) = self.tris.get(hint as usize) {
            let d2 = point_triangle_distance2(q, &p.corners());
            if d2 <= self.cell * self.cell {
                best.offer(d2, hint);
            }
        }
        let reach = (0..3).map(|k| (c[k]).abs().max((self.dims[k] - 1 - c[k]).abs())).max().unwrap_or(0);
        let mut searched = 0;
        for r in 0..=reach {
            searched = r;
            let lo = [0, 1, 2].map(|k| (c[k] - r).max(0));
            let hi = [0, 1, 2].map(|k| (c[k] + r).min(self.dims[k] - 1));
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    let inner = (z - c[2]).abs() < r && (y - c[1]).abs() < r;
                    let mut x = lo[0];
                    while x <= hi[0] {
                        // Inside the shell's block only its two x faces are on the shell.
                        if inner && (x - c[0]).abs() < r {
                            x = c[0] + r;
                            continue;
                        }
                        self.search_cell(q, self.cell_index([x, y, z]), &mut best);
                        x += 1;
                    }
                }
            }
            if best.d.is_finite() {
                break;
            }
        }
        if !best.d.is_finite() {
            return (f64::INFINITY, NO_HINT);
        }
        // The box around q of half-width the distance found, less the block of shells searched.
        let d = best.d;
        let lo = [0, 1, 2].map(|k| self.cell_of_axis(q[k] - d, k).max(0));
        let hi = [0, 1, 2].map(|k| self.cell_of_axis(q[k] + d, k).min(self.dims[k] - 1));
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let inner = (z - c[2]).abs() <= searched && (y - c[1]).abs() <= searched;
                for x in lo[0]..=hi[0] {
                    if inner && (x - c[0]).abs() <= searched {
                        continue;
                    }
                    self.search_cell(q, self.cell_index([x, y, z]), &mut best);
                }
            }
        }
        (best.d, best.tri)
    }

    /// [`Self::distance`] of each point (metres), in the points' order. The points are measured in
    /// the order of the cells they fall in, so that neighbouring queries read the same triangles
    /// (the area samples come in random order, and a large mesh's index does not fit in a cache),
    /// each starting from the nearest triangle of the point before it ([`Self::nearest`]'s hint).
    pub fn distances(&self, points: &[[f32; 3]]) -> Vec<f64> {
        let mut order: Vec<u64> = points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let cell = self.cell_index(self.clamped_cell_of(p.map(f64::from)));
                (cell as u64) << 32 | i as u64
            })
            .collect();
        order.par_sort_unstable();
        let measured: Vec<f64> = order
            .par_chunks(HINTED_RUN)
            .flat_map_iter(|run| {
                let mut hint = NO_HINT;
                run.iter().map(move |&key| {
                    let (d, t) = self.nearest(points[(key & 0xffff_ffff) as usize].map(f64::from), hint);
                    hint = t;
                    d
                })
            })
            .collect();
        let mut d = vec![0.0; points.len()];
        for (&key, m) in order.iter().zip(measured) {
            d[(key & 0xffff_ffff) as usize] = m;
        }
        d
    }

    /// Fold the triangles of cell `i` into `best`, skipping those whose bounding sphere is farther
    /// than the nearest found.
    fn search_cell(&self, q: [f64; 3], i: usize, best: &mut Best) {
        for &t in &self.items[self.start[i] as usize..self.start[i + 1] as usize] {
            let p = &self.tris[t as usize];
            let reach = f64::from(p.radius) + best.d;
            if dist2(q, p.centre.map(f64::from)) >= reach * reach {
                continue;
            }
            best.offer(point_triangle_distance2(q, &p.corners()), t);
        }
    }
}

/// No triangle: a search without a hint, or one that found nothing.
const NO_HINT: u32 = u32::MAX;

/// Queries measured one after the other, each from the previous one's nearest triangle, by
/// [`TriangleIndex::distances`] (runs are measured in parallel).
const HINTED_RUN: usize = 512;

/// The nearest triangle found so far: its squared distance (metres²), the distance, and its index.
struct Best {
    d2: f64,
    d: f64,
    tri: u32,
}

impl Best {
    /// Keep triangle `tri` at squared distance `d2` when it is nearer than the one held (the
    /// smallest squared distance wins, whatever the order of the offers).
    #[inline]
    fn offer(&mut self, d2: f64, tri: u32) {
        if d2 < self.d2 {
            (self.d2, self.d, self.tri) = (d2, d2.sqrt(), tri);
        }
    }
}

/// The sampled symmetric Hausdorff distance between `a` and `b` (module docs), with `samples` area
/// samples per surface besides its vertices; `None` when either has no triangle.
pub fn hausdorff_distance(a: &TriangleMesh, b: &TriangleMesh, samples: usize) -> Option<Hausdorff> {
    hausdorff_outliers(a, b, samples, f64::INFINITY).map(|(h, _)| h)
}

/// [`hausdorff_distance`], and the samples of either surface (metres, the meshes' frame) farther
/// than `beyond_m` from the other one.
pub fn hausdorff_outliers(
    a: &TriangleMesh,
    b: &TriangleMesh,
    samples: usize,
    beyond_m: f64,
) -> Option<(Hausdorff, Vec<[f32; 3]>)> {
    hausdorff_outliers_to(a, &Reference::new(b, samples)?, beyond_m, None)
}

/// A surface prepared to be measured against by [`hausdorff_outliers_to`]: its triangle index and
/// its own samples (its vertices, then its area samples; metres, the mesh's frame). Preparing it
/// depends on that surface alone, so a caller that knows it early (a simplification's input) can
/// prepare it while the other surface is still being made.
#[derive(Debug)]
pub struct Reference<'a> {
    index: TriangleIndex<'a>,
    points: Vec<[f32; 3]>,
    /// The first `vertices` of `points` are the mesh's vertices.
    vertices: usize,
    /// Area samples per surface, for the other surface too.
    samples: usize,
}

/// Seeds of the area samples of the measured surface and of the reference.
const SEEDS: [u64; 2] = [11, 12];

impl<'a> Reference<'a> {
    /// Index `mesh` and sample it at its vertices plus `samples` area samples; `None` when it has no
    /// triangle.
    pub fn new(mesh: &'a TriangleMesh, samples: usize) -> Option<Reference<'a>> {
        let (index, area) = rayon::join(|| TriangleIndex::new(mesh), || sample_mesh(mesh, samples, SEEDS[1]));
        let mut points = Vec::with_capacity(mesh.vertices.len() + area.len());
        points.extend_from_slice(&mesh.vertices);
        points.extend(area);
        Some(Reference { index: index?, points, vertices: mesh.vertices.len(), samples })
    }
}

/// [`hausdorff_outliers`] with the second surface prepared ([`Reference`]); `a` gets as many area
/// samples as the reference has. `b_vertex_bounds`, when given, holds for each vertex of the
/// reference an upper bound, metres, of its distance to `a` (module docs): a vertex whose bound
/// stays below both the largest distance of the reference's area samples and `beyond_m` is not
/// measured. The bounds may be short of the true distances by the rounding of `a`'s corners to `f32`
/// (they are taken as that much larger).
pub fn hausdorff_outliers_to(
    a: &TriangleMesh,
    b: &Reference<'_>,
    beyond_m: f64,
    b_vertex_bounds: Option<&[f64]>,
) -> Option<(Hausdorff, Vec<[f32; 3]>)> {
    // Each direction starts as soon as its own part is ready: `a`'s samples are measured against
    // the reference while `a` is indexed for the reference's samples.
    let (to_b, to_a) = rayon::join(
        || {
            let mut pts: Vec<[f32; 3]> = a.vertices.clone();
            pts.extend(sample_mesh(a, b.samples, SEEDS[0]));
            let d = b.index.distances(&pts);
            Directed::of(&pts, &d, a.vertices.len(), beyond_m)
        },
        || {
            let ia = TriangleIndex::new(a)?;
            let (vertices, area) = b.points.split_at(b.vertices);
            let d = ia.distances(area);
            let from_area = Directed::of(area, &d, 0, beyond_m);
            // A vertex is measured unless its bound keeps it below what the area samples reached
            // and below the outlier threshold.
            let reach = from_area.max.min(beyond_m);
            let slack = rounding_of(a);
            let measured: Vec<[f32; 3]> = match b_vertex_bounds {
                Some(bounds) if bounds.len() == vertices.len() => vertices
                    .iter()
                    .zip(bounds)
                    // A NaN bound bounds nothing: measured too.
                    .filter(|(_, &bound)| matches!((bound + slack).partial_cmp(&reach), Some(Ordering::Greater) | None))
                    .map(|(p, _)| *p)
                    .collect(),
                _ => vertices.to_vec(),
            };
            let d = ia.distances(&measured);
            let from_vertices = Directed::of(&measured, &d, measured.len(), beyond_m);
            Some(from_area.with(from_vertices, vertices.len()))
        },
    );
    let (f, g) = (to_b, to_a?);
    let h = Hausdorff {
        forward_m: f.max,
        backward_m: g.max,
        symmetric_m: f.max.max(g.max),
        mean_m: (f.area_sum + g.area_sum) / (f.area_n + g.area_n).max(1) as f64,
        samples: [f.points, g.points],
    };
    let mut far = f.far;
    far.extend(g.far);
    Some((h, far))
}

/// One direction's figures over a set of points (metres).
struct Directed {
    max: f64,
    /// Sum and count of the area samples' distances (the points after the vertices).
    area_sum: f64,
    area_n: usize,
    /// Points the direction covers (measured or bounded).
    points: usize,
    far: Vec<[f32; 3]>,
}

impl Directed {
    /// The figures of `pts` at distances `d`, the first `vertices` of them vertices.
    fn of(pts: &[[f32; 3]], d: &[f64], vertices: usize, beyond_m: f64) -> Directed {
        let area = &d[vertices.min(d.len())..];
        Directed {
            max: d.iter().copied().fold(0.0, f64::max),
            area_sum: area.iter().sum(),
            area_n: area.len(),
            points: pts.len(),
            far: pts.iter().zip(d).filter(|(_, &x)| x > beyond_m).map(|(p, _)| *p).collect(),
        }
    }

    /// These area samples' figures with the measured vertices' (`v`, all vertices) added, the
    /// direction covering `vertices` vertices besides the samples.
    fn with(mut self, v: Directed, vertices: usize) -> Directed {
        self.max = self.max.max(v.max);
        self.points += vertices;
        self.far.extend(v.far);
        self
    }
}

/// How far, metres, rounding the corners of `mesh` to `f32` may have moved any point of its
/// triangles: half a unit in the last place of its largest coordinate on each axis, taken twice.
fn rounding_of(mesh: &TriangleMesh) -> f64 {
    let largest = mesh.vertices.iter().flatten().fold(0.0f64, |m, &x| m.max(f64::from(x).abs()));
    largest * f64::from(f32::EPSILON) * 3f64.sqrt()
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

fn bbox(tri: &[[f64; 3]; 3]) -> ([f64; 3], [f64; 3]) {
    let lo = [0, 1, 2].map(|k| tri[0][k].min(tri[1][k]).min(tri[2][k]));
    let hi = [0, 1, 2].map(|k| tri[0][k].max(tri[1][k]).max(tri[2][k]));
    (lo, hi)
}

/// Squared distance from `p` to the triangle `t` (Ericson, "Real-Time Collision Detection", 5.1.5).
pub fn point_triangle_distance2(p: [f64; 3], t: &[[f64; 3]; 3]) -> f64 {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let [a, b, c] = *t;
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let d2 = |q: [f64; 3]| {
        let v = sub(p, q);
        dot(v, v)
    };
    let lerp = |x: [f64; 3], y: [f64; 3], s: f64| [0, 1, 2].map(|k| x[k] + s * (y[k] - x[k]));
    let (d1, d2_) = (dot(ab, ap), dot(ac, ap));
    if d1 <= 0.0 && d2_ <= 0.0 {
        return d2(a);
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return d2(b);
    }
    let vc = d1 * d4 - d3 * d2_;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return d2(lerp(a, b, d1 / (d1 - d3)));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return d2(c);
    }
    let vb = d5 * d2_ - d1 * d6;
    if vb <= 0.0 && d2_ >= 0.0 && d6 <= 0.0 {
        return d2(lerp(a, c, d2_ / (d2_ - d6)));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return d2(lerp(b, c, (d4 - d3) / ((d4 - d3) + (d5 - d6))));
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    d2([0, 1, 2].map(|k| a[k] + ab[k] * v + ac[k] * w))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An axis-aligned cube of edge `s` centred at `c`, 12 outward triangles.
    fn cube(c: [f32; 3], s: f32) -> TriangleMesh {
        let h = s / 2.0;
        let vertices = (0..8).map(|n| [0, 1, 2].map(|k| c[k] + if (n >> k) & 1 == 1 { h } else { -h })).collect();
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let triangles = quads.iter().flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        TriangleMesh { vertices, triangles, colors: None }
    }

    #[test]
    fn point_triangle_distance_in_every_region() {
        let t = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let cases = [
            ([0.2, 0.2, 0.5], 0.25),
            ([-1.0, -1.0, 0.0], 2.0),
            ([2.0, 0.0, 0.0], 1.0),
            ([0.5, -2.0, 0.0], 4.0),
            ([1.0, 1.0, 0.0], 0.5),
            ([-3.0, 0.5, 1.0], 10.0),
        ];
        for (p, d2) in cases {
            assert!((point_triangle_distance2(p, &t) - d2).abs() < 1e-12, "{p:?}");
        }
    }

    /// The grid search gives the brute-force nearest distance, for points near the surface (where
    /// the box search decides), inside, and far outside the grid.
    #[test]
    fn the_index_finds_the_nearest_triangle() {
        use crate::geometry::{Aabb, VoxelGrid};
        use crate::pipeline::{extract_surface, MeshParams, Occupancy};
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0; 3] }, 24);
        let occ = Occupancy::from_fn(grid, |p| (p.x / 0.8).powi(2) + (p.y / 0.5).powi(2) + (p.z / 0.6).powi(2) < 1.0);
        let mesh = extract_surface(&occ, &MeshParams::default()).expect("mesh");
        let index = TriangleIndex::new(&mesh).expect("triangles");
        let mut rng = crate::sim::rng::SplitMix64::new(7);
        let mut next = |scale: f64| (rng.next_f64() - 0.5) * 2.0 * scale;
        let mut near = 0;
        let mut queries = Vec::new();
        for i in 0..600 {
            let scale = [0.05, 1.0, 4.0][i % 3];
            let v = mesh.vertices[(i * 37) % mesh.vertices.len()].map(f64::from);
            let q = if i % 3 == 0 { [0, 1, 2].map(|k| v[k] + next(scale)) } else { [0, 1, 2].map(|_| next(scale)) };
            let brute = mesh
                .triangles
                .iter()
                .map(|t| point_triangle_distance2(q, &t.map(|j| mesh.vertices[j as usize].map(f64::from))))
                .fold(f64::INFINITY, f64::min)
                .sqrt();
            assert!((index.distance(q) - brute).abs() <= 1e-12, "{q:?}: {} vs {brute}", index.distance(q));
            near += usize::from(brute < 0.05);
            queries.push(q.map(|x| x as f32));
        }
        assert!(near > 150, "{near} points near the surface");
        // Measured in cell order, each from the nearest triangle of the query before it (a hint
        // that is often not the answer: the queries are scattered), returned in the queries' order.
        let one_by_one: Vec<f64> = queries.iter().map(|q| index.distance(q.map(f64::from))).collect();
        assert_eq!(index.distances(&queries), one_by_one);
    }

    /// The index holds every triangle once, in the order of its centroid's cell, and each cell
    /// lists exactly the triangles whose bounding box reaches it, in that order; built on one
    /// thread or on three, it is the same.
    #[test]
    fn the_index_is_its_definition_on_any_number_of_threads() {
        use crate::geometry::{Aabb, VoxelGrid};
        use crate::pipeline::{extract_surface, MeshParams, Occupancy};
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0; 3] }, 20);
        let occ = Occupancy::from_fn(grid, |p| (p.x / 0.8).powi(2) + (p.y / 0.5).powi(2) + (p.z / 0.6).powi(2) < 1.0);
        let mesh = extract_surface(&occ, &MeshParams::default()).expect("mesh");
        let built: Vec<TriangleIndex<'_>> = [1, 3]
            .map(|threads| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
                pool.install(|| TriangleIndex::new(&mesh).expect("triangles"))
            })
            .into();
        let index = &built[0];
        let corners = |i: &TriangleIndex<'_>| i.tris.iter().map(|p| p.corners).collect::<Vec<_>>();
        assert_eq!(corners(&built[1]), corners(index));
        assert_eq!((&built[1].start, &built[1].items), (&index.start, &index.items));
        assert_eq!((built[1].cell, built[1].dims, built[1].origin), (index.cell, index.dims, index.origin));
        // Every triangle once, by its centroid's cell.
        let mut theirs: Vec<[[f32; 3]; 3]> =
            mesh.triangles.iter().map(|t| t.map(|i| mesh.vertices[i as usize])).collect();
        let mut ours = corners(index);
        let key = |c: &[[f32; 3]; 3]| c.map(|p| p.map(f32::to_bits));
        theirs.sort_by_key(key);
        ours.sort_by_key(key);
        assert_eq!(ours, theirs);
        let home: Vec<usize> =
            index.tris.iter().map(|p| index.cell_index(index.clamped_cell_of(p.centre.map(f64::from)))).collect();
        assert!(home.windows(2).all(|w| w[0] <= w[1]), "triangles out of cell order");
        // Each cell's list, by the definition.
        let cells = index.dims.iter().map(|&d| d as usize).product::<usize>();
        let mut listed = 0;
        for c in 0..cells {
            let xyz = [0, 1, 2].map(|k| {
                let below: i32 = index.dims[..k].iter().product();
                (c as i32 / below) % index.dims[k]
            });
            // A triangle reaches the cell when, on every axis, the cells of its bounding box's ends
            // (the floor of the offset over the cell edge, clamped to the grid) hold the cell's.
            let expected: Vec<u32> = (0..index.tris.len() as u32)
                .filter(|&t| {
                    let c = index.tris[t as usize].corners;
                    (0..3).all(|k| {
                        let cell_of = |x: f32| {
                            let f = ((f64::from(x) - index.origin[k]) / index.cell).floor();
                            (f as i32).clamp(0, index.dims[k] - 1)
                        };
                        let (lo, hi) =
                            c.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), p| (l.min(p[k]), h.max(p[k])));
                        (cell_of(lo)..=cell_of(hi)).contains(&xyz[k])
                    })
                })
                .collect();
            assert_eq!(&index.items[index.start[c] as usize..index.start[c + 1] as usize], &expected[..], "cell {c}");
            listed += expected.len();
        }
        assert_eq!(listed, index.items.len());
        assert!(index.tris.len() > 1000 && cells > 100, "{} triangles, {cells} cells", index.tris.len());
    }

    /// Vertex bounds spare the vertices that cannot reach the maximum or the outlier threshold and
    /// change no figure, while a vertex whose bound reaches either is measured. Bounds below the
    /// truth (a caller's error) show that the bounded vertices really go unmeasured.
    #[test]
    fn vertex_bounds_spare_queries_without_changing_the_figures() {
        let outer = cube([0.0, 0.0, 0.0], 2.0);
        // The inner cube with one corner pushed in to 0.9 from the outer surface: that vertex, not
        // an area sample, is the farthest point of the inner surface.
        let mut inner = cube([0.0, 0.0, 0.0], 1.0);
        inner.vertices[0] = [-0.1, -0.1, -0.1];
        let reference = Reference::new(&inner, 2_000).expect("triangles");
        let to_outer = TriangleIndex::new(&outer).expect("triangles");
        let exact: Vec<f64> = inner.vertices.iter().map(|v| to_outer.distance(v.map(f64::from))).collect();
        let sorted = |mut f: Vec<[f32; 3]>| {
            f.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
            f
        };
        // With outliers asked for (beyond 0.6) and without (every distance within infinity).
        for beyond in [0.6, f64::INFINITY] {
            let (plain, plain_far) = hausdorff_outliers_to(&outer, &reference, beyond, None).expect("distance");
            let (bounded, far) = hausdorff_outliers_to(&outer, &reference, beyond, Some(&exact)).expect("distance");
            assert_eq!(bounded, plain, "beyond {beyond}");
            assert_eq!(sorted(far), sorted(plain_far), "beyond {beyond}");
            assert!((plain.backward_m - 0.9).abs() < 1e-6, "{plain:?}");
        }
        let beyond = 0.6;
        let (plain, plain_far) = hausdorff_outliers_to(&outer, &reference, beyond, None).expect("distance");
        assert!(plain_far.contains(&inner.vertices[0]));
        // Bounds of zero: no vertex is measured, so the pushed-in corner is neither the maximum nor
        // an outlier, though every vertex still counts.
        let (blind, blind_far) = hausdorff_outliers_to(&outer, &reference, beyond, Some(&[0.0; 8])).expect("distance");
        assert!(blind.backward_m < 0.9 - 1e-4, "{blind:?}");
        assert!(!blind_far.contains(&inner.vertices[0]));
        assert_eq!((blind.forward_m, blind.samples), (plain.forward_m, plain.samples));
        // Bounds of the wrong length are ignored.
        let (short, _) = hausdorff_outliers_to(&outer, &reference, beyond, Some(&[0.0; 3])).expect("distance");
        assert_eq!(short, plain);
    }

    #[test]
    fn nested_cubes_are_half_the_edge_difference_apart() {
        let outer = cube([0.1, -0.2, 0.3], 2.0);
        let inner = cube([0.1, -0.2, 0.3], 1.0);
        let h = hausdorff_distance(&outer, &inner, 5_000).expect("distance");
        // The outer cube's corners are sqrt(3)/2 from the inner one's corners; every inner point is
        // 0.5 from the outer surface.
        assert!((h.forward_m - 0.75f64.sqrt()).abs() < 1e-5, "{h:?}");
        assert!((h.backward_m - 0.5).abs() < 1e-5, "{h:?}");
        assert_eq!(h.symmetric_m, h.forward_m);
        assert_eq!(h.samples, [5_008, 5_008]);
        let same = hausdorff_distance(&outer, &outer, 1_000).expect("distance");
        assert!(same.symmetric_m < 1e-6);
        let shifted = cube([0.1, -0.2, 0.35], 2.0);
        let s = hausdorff_distance(&outer, &shifted, 5_000).expect("distance");
        assert!((s.symmetric_m - 0.05).abs() < 1e-5, "{s:?}");
        assert!(hausdorff_distance(&outer, &TriangleMesh::default(), 10).is_none());
    }
}
