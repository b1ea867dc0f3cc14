//! Mesh simplification by quadric error metrics (Garland & Heckbert, "Surface simplification using
//! quadric error metrics", SIGGRAPH 1997) with an explicit distance bound on every collapse, keeping a
//! closed mesh closed.
//!
//! Every vertex carries the quadric of the planes of its incident triangles (unweighted, unit
//! normals); an edge is collapsed into the point that minimises the sum of its ends' quadrics, the
//! cheapest edge first (to within 1/1024 of the bound). The quadric's value at a point is the sum of the squared distances to every
//! plane it holds, so it bounds the largest of them: a collapse is considered only while that sum
//! stays within the squared error bound. The planes alone do not bound the distance between the
//! surfaces, so each collapse is also checked against the original surface, both ways, before it is
//! made (as Garland & Heckbert's and Hoppe's per-face point tracking does):
//! - every original vertex belongs to one triangle of the simplified mesh, initially one it lies on;
//!   the points of the triangles a collapse changes must each lie within the bound of one of the new
//!   triangles (and move to it), so every original vertex stays within the bound of the simplified
//!   surface;
//! - the new vertex must lie within the bound of the original surface: of one of those original
//!   vertices, or else of one of the original triangles around them (a conservative test: a point
//!   that fails it may still be close to some other original triangle, and the collapse is refused).
//!
//! - the centroid of every new triangle and the middle of its edge leaving the new vertex must lie
//!   within the bound of the original surface, by the same conservative test: the insides of
//!   triangles are probed, not bounded (vertex checks alone let them out by 16 % of the bound on a
//!   real carved surface).
//!
//! The symmetric Hausdorff distance between the vertices of either mesh and the other surface is thus
//! within the bound by construction; [`simplify_within`] measures it at samples inside the triangles
//! and repairs what it finds beyond the bound. A collapse is also refused when it would
//! - break the manifold: the two ends must share exactly the two neighbours opposite the edge (the
//!   link condition), and the mesh keeps at least five vertices;
//! - leave the vertex with more than 16 neighbours (thin fans);
//! - fold a triangle over: every triangle that moves must keep its normal within 90 degrees of its
//!   old one and must not become degenerate.
//!
//! A mesh of at least 50,000 triangles is cut into boxes of equal vertex count (a k-d tree of median
//! cuts across the longest side; one box per 25,000 triangles, at most 1,024), simplified box by box
//! in parallel with the corners of the triangles that cross a cut held in place, and then the edges
//! at the cuts are queued on the whole mesh and collapsed in one pass under the same checks. K-d
//! cuts cross less of the surface than as many parallel slabs, so that last pass has fewer edges;
//! boxes of 25,000 triangles measured faster per triangle than boxes of 50,000 (a box's working set
//! then stays in cache), and a large mesh is no longer held to 16 bigger boxes: 54 boxes instead of
//! 16 took the cup's 1.35 million triangles at 256^3 from 1.2 s to 0.8 s of boxes, and 217 instead
//! of 16 its 5.4 million at 512^3 from 5.6 s to 2.6 s, while the pass at the cuts grew from 0.2 to
//! 0.35 s and from 0.6 to 1.4 s. The result depends on the mesh, not on the number of threads.
//!
//! Positions are metres in the mesh's own frame (worked in `f64` relative to the centroid).

use std::sync::atomic::{AtomicUsize, Ordering as AtomicOrdering};
use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Instant;

use rayon::prelude::*;

use super::chamfer::PointIndex;
use super::hausdorff::{hausdorff_outliers_to, point_triangle_distance2, Hausdorff, Reference};
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
        let (a, b, c, d, e, f) = (q[0], q[1], q[2], q[4], q[5], q[7]);
        // Cofactors of the symmetric matrix [a b c; b d e; c e f].
        let (c00, c01, c02) = (d * f - e * e, c * e - b * f, b * e - c * d);
        let det = a * c00 + b * c01 + c * c02;
        // A positive semi-definite matrix's determinant is the product of its eigenvalues and its
        // trace their sum: a determinant far below (trace / 3)^3 means a nearly flat direction.
        let scale = (a + d + f) / 3.0;
        if !(scale > 0.0 && det > 1e-6 * scale * scale * scale) {
            return None;
        }
        let (c11, c12, c22) = (a * f - c * c, b * c - a * e, a * d - b * b);
        let r = [-q[3], -q[6], -q[8]];
        let x = [
            (c00 * r[0] + c01 * r[1] + c02 * r[2]) / det,
            (c01 * r[0] + c11 * r[1] + c12 * r[2]) / det,
            (c02 * r[0] + c12 * r[1] + c22 * r[2]) / det,
        ];
        x.iter().all(|v| v.is_finite()).then_some(x)
    }
}

/// A queued edge collapse: the edge's ends and their versions when it was queued (stale once either
/// end changed).
type Candidate = (u32, u32, u32, u32);

/// Buckets of [`CollapseQueue`].
const BUCKETS: usize = 1024;

/// The queued collapses, cheapest first to within 1/[`BUCKETS`] of the error bound and first come
/// first served within that: a bucket queue over the square root of the quadric cost (a distance),
/// so that a push and a pop cost O(1) where a binary heap of the millions of (mostly stale)
/// candidates spent most of the time sifting.
struct CollapseQueue {
    buckets: Vec<Vec<Candidate>>,
    /// The next candidate of each bucket (those before it were popped).
    head: Vec<usize>,
    /// No candidate sits in a bucket below this one.
    low: usize,
    /// Bucket per unit of `sqrt(cost)`.
    scale: f64,
}

impl CollapseQueue {
    fn new(bound: f64) -> CollapseQueue {
        CollapseQueue {
            buckets: vec![Vec::new(); BUCKETS],
            head: vec![0; BUCKETS],
            low: BUCKETS,
            scale: BUCKETS as f64 / bound,
        }
    }

    fn push(&mut self, cost: f64, c: Candidate) {
        let k = ((cost.max(0.0).sqrt() * self.scale) as usize).min(BUCKETS - 1);
        self.buckets[k].push(c);
        self.low = self.low.min(k);
    }

    fn pop(&mut self) -> Option<Candidate> {
        while self.low < BUCKETS {
            let k = self.low;
            if let Some(&c) = self.buckets[k].get(self.head[k]) {
                self.head[k] += 1;
                return Some(c);
            }
            self.buckets[k].clear();
            self.head[k] = 0;
            self.low += 1;
        }
        None
    }
}

/// Most neighbours a vertex may have after a collapse: beyond this, fans of thin triangles grow
/// around one vertex (and every later check around it grows with them).
const MAX_VALENCE: usize = 16;

/// No entry (end of a point list, no face).
const NONE: u32 = u32::MAX;

/// Parameters of [`simplify`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimplifyParams {
    /// Largest distance, metres, between an original vertex and the simplified surface, between a
    /// simplified vertex and the original surface, and from a new vertex to a plane of the original
    /// triangles it replaces.
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
    /// Collapses within the quadric bound refused because an original vertex, the new vertex or a
    /// probe inside a new triangle would have been farther than the bound from the other surface.
    pub refused_by_distance: usize,
}

/// A triangle as it would be after a collapse: its index, corners and unit normal (metres).
#[derive(Debug, Clone, Copy)]
struct NewFace {
    id: u32,
    corners: [[f64; 3]; 3],
    normal: [f64; 3],
}

impl NewFace {
    /// Whether `x` lies within `sqrt(bound2)` of the triangle (the plane distance first, as a quick
    /// rejection).
    fn holds(&self, x: [f64; 3], bound2: f64) -> bool {
        let d = dot(self.normal, sub(x, self.corners[0]));
        d * d <= bound2 && point_triangle_distance2(x, &self.corners) <= bound2
    }
}

/// The input surface, never changed: what every collapse is checked against.
struct Original {
    /// Vertex positions, metres relative to the centroid.
    pos: Vec<[f64; 3]>,
    tris: Vec<[u32; 3]>,
    /// Triangles around each vertex: `around[start[v]..start[v + 1]]`.
    start: Vec<u32>,
    around: Vec<u32>,
}

impl Original {
    fn new(pos: Vec<[f64; 3]>, tris: Vec<[u32; 3]>) -> Original {
        let mut start = vec![0u32; pos.len() + 1];
        for t in &tris {
            for &v in t {
                start[v as usize + 1] += 1;
            }
        }
        for v in 0..pos.len() {
            start[v + 1] += start[v];
        }
        let mut around = vec![0u32; start[pos.len()] as usize];
        let mut fill = start.clone();
        for (ti, t) in tris.iter().enumerate() {
            for &v in t {
                around[fill[v as usize] as usize] = ti as u32;
                fill[v as usize] += 1;
            }
        }
        Original { pos, tris, start, around }
    }

    fn triangles_of(&self, v: u32) -> &[u32] {
        &self.around[self.start[v as usize] as usize..self.start[v as usize + 1] as usize]
    }

    /// Each triangle's plane quadric summed per vertex (unweighted, unit normals).
    fn quadrics(&self) -> Vec<Quadric> {
        let mut quadric = vec![Quadric::default(); self.pos.len()];
        for t in &self.tris {
            if let Some((normal, d)) = plane_of(&self.pos, t) {
                let q = Quadric::plane(normal, d);
                for &v in t {
                    quadric[v as usize].add(&q);
                }
            }
        }
        quadric
    }
}

/// The state of a simplification, to start or resume one: current positions, triangles, quadrics,
/// which vertices live, and the triangle each original vertex is tracked on (`NONE` for a vertex on
/// no triangle).
#[derive(Default)]
struct State {
    pos: Vec<[f64; 3]>,
    tris: Vec<[u32; 3]>,
    alive_tri: Vec<bool>,
    quadric: Vec<Quadric>,
    alive: Vec<bool>,
    home: Vec<u32>,
}

impl State {
    /// Nothing collapsed yet: every original vertex on its first triangle (distance 0).
    fn start(original: &Original, quadric: Vec<Quadric>) -> State {
        let home =
            (0..original.pos.len() as u32).map(|v| original.triangles_of(v).first().copied().unwrap_or(NONE)).collect();
        State {
            pos: original.pos.clone(),
            tris: original.tris.clone(),
            alive_tri: vec![true; original.tris.len()],
            quadric,
            alive: vec![true; original.pos.len()],
            home,
        }
    }
}

/// The mesh being simplified.
struct Work<'o> {
    original: &'o Original,
    /// Current vertex positions, relative to the centroid.
    pos: Vec<[f64; 3]>,
    tris: Vec<[u32; 3]>,
    alive_tri: Vec<bool>,
    /// Current triangles around each vertex.
    around: Vec<Vec<u32>>,
    /// The original vertices each current triangle holds, as singly linked lists: the first per
    /// triangle, the next per original vertex.
    first_point: Vec<u32>,
    next_point: Vec<u32>,
    quadric: Vec<Quadric>,
    version: Vec<u32>,
    alive: Vec<bool>,
    /// Vertices that may not move or go (on a region's seam while regions are simplified apart).
    locked: Vec<bool>,
    bound2: f64,
    // Scratch buffers, reused across collapses.
    shared: Vec<u32>,
    faces: Vec<NewFace>,
    points: Vec<(u32, u32)>,
    /// `points` grouped by new face: face `k`'s are `by_face[face_start[k]..face_start[k + 1]]`.
    by_face: Vec<u32>,
    face_start: Vec<u32>,
    /// The points' squared distances to a probe, with the points (see [`Work::near_original`]).
    by_gap: Vec<(f64, u32)>,
    ring_a: Vec<u32>,
    ring_b: Vec<u32>,
    /// Per vertex, the last ring gathering that met it (see [`Work::ring`]), and the current one.
    met: Vec<u32>,
    gathering: u32,
}

/// Why a collapse was not made.
enum Refusal {
    /// Stale, locked, not manifold, over the quadric bound or folding: nothing was measured.
    Shape,
    /// A vertex would leave the distance bound.
    Distance,
}

impl<'o> Work<'o> {
    fn new(original: &'o Original, state: State, locked: Vec<bool>, bound2: f64) -> Work<'o> {
        let State { pos, tris, alive_tri, quadric, alive, home } = state;
        let n = pos.len();
        let mut count = vec![0u32; n];
        for (t, _) in tris.iter().zip(&alive_tri).filter(|(_, &a)| a) {
            for &v in t {
                count[v as usize] += 1;
            }
        }
        let mut around: Vec<Vec<u32>> = count.iter().map(|&c| Vec::with_capacity(c as usize)).collect();
        for (ti, (t, _)) in tris.iter().zip(&alive_tri).enumerate().filter(|(_, (_, &a))| a) {
            for &v in t {
                around[v as usize].push(ti as u32);
            }
        }
        let mut first_point = vec![NONE; tris.len()];
        let mut next_point = vec![NONE; n];
        for (v, &t) in home.iter().enumerate() {
            if t != NONE {
                next_point[v] = first_point[t as usize];
                first_point[t as usize] = v as u32;
            }
        }
        Work {
            original,
            pos,
            tris,
            alive_tri,
            around,
            first_point,
            next_point,
            quadric,
            version: vec![0; n],
            alive,
            locked,
            bound2,
            shared: Vec::new(),
            faces: Vec::new(),
            points: Vec::new(),
            by_face: Vec::new(),
            face_start: Vec::new(),
            by_gap: Vec::new(),
            ring_a: Vec::new(),
            ring_b: Vec::new(),
            met: vec![0; n],
            gathering: 0,
        }
    }

    /// The state reached, to resume from (the triangle each original vertex is on read back from
    /// the lists).
    fn into_state(self) -> State {
        let mut home = vec![NONE; self.next_point.len()];
        for (t, &first) in self.first_point.iter().enumerate() {
            let mut x = first;
            while x != NONE {
                home[x as usize] = t as u32;
                x = self.next_point[x as usize];
            }
        }
        State {
            pos: self.pos,
            tris: self.tris,
            alive_tri: self.alive_tri,
            quadric: self.quadric,
            alive: self.alive,
            home,
        }
    }

    fn push(&self, queue: &mut CollapseQueue, a: u32, b: u32) {
        if self.locked[a as usize] || self.locked[b as usize] {
            return;
        }
        let (cost, _) = best_position(&self.pos, &self.quadric, a, b);
        if cost <= self.bound2 {
            queue.push(cost, (a, b, self.version[a as usize], self.version[b as usize]));
        }
    }

    /// Collapse the queued edges, cheapest first, until none is left; every collapse that passes the
    /// checks is made and each edge around its vertex queued again.
    fn run(&mut self, queue: &mut CollapseQueue, stats: &mut SimplifyStats) {
        let mut vertices_left = self.around.iter().filter(|r| !r.is_empty()).count();
        let mut ring = Vec::new();
        while let Some((a, b, va, vb)) = queue.pop() {
            let (ai, bi) = (a as usize, b as usize);
            // A collapse bumps both ends' versions, so a queued edge of a gone vertex is stale too.
            if self.version[ai] != va || self.version[bi] != vb {
                continue;
            }
            if vertices_left <= 4 {
                break;
            }
            match self.try_collapse(a, b) {
                Ok(()) => {}
                Err(Refusal::Shape) => continue,
                Err(Refusal::Distance) => {
                    stats.refused_by_distance += 1;
                    continue;
                }
            }
            vertices_left -= 1;
            stats.collapses += 1;
            self.ring(b, &mut ring);
            // In increasing index, the order the queue's ties were always pushed in.
            ring.sort_unstable();
            for &v in &ring {
                let (x, y) = if v < b { (v, b) } else { (b, v) };
                self.push(queue, x, y);
            }
        }
    }

    /// The distinct vertices of the current triangles around `v`, other than `v`, into `out` (in
    /// the order met); returns how many of them the previous call gathered too.
    fn ring(&mut self, v: u32, out: &mut Vec<u32>) -> usize {
        out.clear();
        if self.gathering == u32::MAX {
            self.restart_gatherings();
        }
        let previous = self.gathering;
        self.gathering += 1;
        let mut again = 0;
        for &t in &self.around[v as usize] {
            for x in self.tris[t as usize] {
                let m = &mut self.met[x as usize];
                if x != v && *m != self.gathering {
                    again += usize::from(*m == previous);
                    *m = self.gathering;
                    out.push(x);
                }
            }
        }
        again
    }

    /// Forget every vertex's gathering (before the count would wrap around).
    fn restart_gatherings(&mut self) {
        self.met.fill(0);
        self.gathering = 0;
    }

    /// Collapse `a` into `b` when every check passes (module docs).
    fn try_collapse(&mut self, a: u32, b: u32) -> Result<(), Refusal> {
        let (ai, bi) = (a as usize, b as usize);
        if self.locked[ai] || self.locked[bi] {
            return Err(Refusal::Shape);
        }
        // Link condition: the triangles on the edge are exactly two, and the ends share exactly their
        // two opposite vertices.
        self.shared.clear();
        self.shared.extend(self.around[ai].iter().copied().filter(|&t| self.tris[t as usize].contains(&b)));
        if self.shared.len() != 2 {
            return Err(Refusal::Shape);
        }
        // The two gatherings below are counted against each other: neither may restart the count.
        if self.gathering > u32::MAX - 2 {
            self.restart_gatherings();
        }
        let (mut ring_a, mut ring_b) = (std::mem::take(&mut self.ring_a), std::mem::take(&mut self.ring_b));
        self.ring(a, &mut ring_a);
        let common = self.ring(b, &mut ring_b);
        let valence = ring_a.len() + ring_b.len();
        (self.ring_a, self.ring_b) = (ring_a, ring_b);
        if common != 2 || valence - common - 2 > MAX_VALENCE {
            return Err(Refusal::Shape);
        }
        let (cost, p) = best_position(&self.pos, &self.quadric, a, b);
        if cost > self.bound2 {
            return Err(Refusal::Shape);
        }
        // The triangles that move, as they would be; none may fold over or degenerate.
        self.faces.clear();
        for &t in self.around[ai].iter().chain(&self.around[bi]) {
            // The ends share no triangle but the two on the edge (link condition), so none repeats.
            if self.shared.contains(&t) {
                continue;
            }
            let tri = self.tris[t as usize];
            let old = tri.map(|i| self.pos[i as usize]);
            let new = tri.map(|i| if i == a || i == b { p } else { self.pos[i as usize] });
            let (n0, n1) = (cross_of(&old), cross_of(&new));
            let (l0, l1) = (norm(n0), norm(n1));
            if l1 <= 1e-12 * l0.max(f64::MIN_POSITIVE) || dot(n0, n1) <= 0.0 {
                return Err(Refusal::Shape);
            }
            self.faces.push(NewFace { id: t, corners: new, normal: n1.map(|x| x / l1) });
        }
        // Every original vertex held by a changing triangle must stay within the bound of a new one:
        // its own triangle first (when it survives), then the others.
        self.points.clear();
        for &t in self.around[ai].iter().chain(self.around[bi].iter().filter(|t| !self.shared.contains(t))) {
            let own = self.faces.iter().position(|f| f.id == t);
            let mut x = self.first_point[t as usize];
            while x != NONE {
                let q = self.original.pos[x as usize];
                let home = own
                    .filter(|&k| self.faces[k].holds(q, self.bound2))
                    .or_else(|| self.faces.iter().position(|f| f.holds(q, self.bound2)));
                match home {
                    Some(k) => self.points.push((x, k as u32)),
                    None => return Err(Refusal::Distance),
                }
                x = self.next_point[x as usize];
            }
        }
        self.group_points_by_face();
        // The new vertex must lie within the bound of the original surface near those points, and so
        // must the inside of every new triangle, probed at its centroid and at the middle of its edge
        // leaving the new vertex (in a closed mesh each such edge leaves it in exactly one triangle).
        if !self.near_original(p, None) {
            return Err(Refusal::Distance);
        }
        for k in 0..self.faces.len() {
            let c = self.faces[k].corners;
            let centroid = [0, 1, 2].map(|i| (c[0][i] + c[1][i] + c[2][i]) / 3.0);
            let next = c[(c.iter().position(|&x| x == p).unwrap_or(0) + 1) % 3];
            let middle = [0, 1, 2].map(|i| 0.5 * (p[i] + next[i]));
            let face = Some(k as u32);
            if !self.near_original(centroid, face) || !self.near_original(middle, face) {
                return Err(Refusal::Distance);
            }
        }

        // Collapse a into b at p.
        for &t in self.around[ai].iter().chain(&self.around[bi]) {
            self.first_point[t as usize] = NONE;
        }
        for &(x, k) in &self.points {
            let t = self.faces[k as usize].id as usize;
            self.next_point[x as usize] = self.first_point[t];
            self.first_point[t] = x;
        }
        for &t in &self.shared {
            self.alive_tri[t as usize] = false;
        }
        let mut moved = std::mem::take(&mut self.around[ai]);
        moved.retain(|t| !self.shared.contains(t));
        for &t in &moved {
            for v in self.tris[t as usize].iter_mut() {
                if *v == a {
                    *v = b;
                }
            }
        }
        let shared = [self.shared[0], self.shared[1]];
        self.around[bi].retain(|t| !shared.contains(t));
        self.around[bi].extend_from_slice(&moved);
        moved.clear();
        self.around[ai] = moved;
        for t in shared {
            for v in self.tris[t as usize] {
                if v != a && v != b {
                    self.around[v as usize].retain(|&x| x != t);
                }
            }
        }
        self.alive[ai] = false;
        self.version[ai] += 1;
        self.pos[bi] = p;
        let qa = self.quadric[ai];
        self.quadric[bi].add(&qa);
        self.version[bi] += 1;
        Ok(())
    }

    /// Each original vertex's distance (metres) to the current triangle it is tracked on (infinite
    /// for a vertex on no triangle), the live triangles measured in parallel.
    fn tracked_distances(&self) -> Vec<f64> {
        let per_triangle: Vec<(u32, f64)> = (0..self.tris.len())
            .into_par_iter()
            .filter(|&t| self.alive_tri[t])
            .flat_map_iter(|t| {
                let corners = self.tris[t].map(|i| self.pos[i as usize]);
                let mut x = self.first_point[t];
                std::iter::from_fn(move || {
                    (x != NONE).then(|| {
                        let d = point_triangle_distance2(self.original.pos[x as usize], &corners).sqrt();
                        let here = (x, d);
                        x = self.next_point[x as usize];
                        here
                    })
                })
            })
            .collect();
        let mut out = vec![f64::INFINITY; self.next_point.len()];
        for (x, d) in per_triangle {
            out[x as usize] = d;
        }
        out
    }

    /// Fill `by_face` and `face_start` from `points` (a counting sort by face).
    fn group_points_by_face(&mut self) {
        let faces = self.faces.len();
        self.face_start.clear();
        self.face_start.resize(faces + 2, 0);
        for &(_, k) in &self.points {
            self.face_start[k as usize + 2] += 1;
        }
        for k in 2..faces + 2 {
            self.face_start[k] += self.face_start[k - 1];
        }
        self.by_face.clear();
        self.by_face.resize(self.points.len(), NONE);
        for &(x, k) in &self.points {
            let slot = &mut self.face_start[k as usize + 1];
            self.by_face[*slot as usize] = x;
            *slot += 1;
        }
        self.face_start.truncate(faces + 1);
    }

    /// Whether `p` lies within the bound of one of the original vertices gathered in `points`, or of
    /// an original triangle around one of them: the vertices gathered onto new face `face` first (all
    /// of them with `None`), then the others; then the triangles around the nearest of them all, then
    /// around the others, nearest first (the order changes only how soon a triangle within the bound
    /// is met, not the answer).
    fn near_original(&mut self, p: [f64; 3], face: Option<u32>) -> bool {
        let original = self.original;
        let gap_of = |x: u32| {
            let d = sub(p, original.pos[x as usize]);
            dot(d, d)
        };
        // Those on the face first: a probe inside a face is most often near one of them.
        let (lo, hi) = match face {
            Some(k) => (self.face_start[k as usize] as usize, self.face_start[k as usize + 1] as usize),
            None => (0, self.by_face.len()),
        };
        let own = &self.by_face[lo..hi];
        let mut nearest = (f64::INFINITY, NONE);
        for &x in own {
            let gap = gap_of(x);
            if gap <= self.bound2 {
                return true;
            }
            if gap < nearest.0 {
                nearest = (gap, x);
            }
        }
        for &x in self.by_face[..lo].iter().chain(&self.by_face[hi..]) {
            let gap = gap_of(x);
            if gap <= self.bound2 {
                return true;
            }
            if gap < nearest.0 {
                nearest = (gap, x);
            }
        }
        let bound2 = self.bound2;
        let near_triangles = |x: u32| {
            original.triangles_of(x).iter().any(|&t| {
                let tri = original.tris[t as usize].map(|i| original.pos[i as usize]);
                point_triangle_distance2(p, &tri) <= bound2
            })
        };
        let first = nearest.1;
        if first != NONE && near_triangles(first) {
            return true;
        }
        // Only here are the gaps kept, to order the rest by: on the shipped depth-fusion mesh, 3,031
        // of its 2.96 million probes (535,286 when the triangles of the nearest vertex on the probe's
        // own face were tried first, instead of the nearest of all).
        self.by_gap.clear();
        self.by_gap.extend(self.points.iter().map(|&(x, _)| (gap_of(x), x)));
        self.by_gap.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        self.by_gap.iter().any(|&(_, x)| x != first && near_triangles(x))
    }
}

/// Simplify a closed, consistently oriented mesh (module docs). Colours follow the surviving
/// vertices. An edge shared by other than two triangles is never collapsed, so an open or
/// non-manifold input stays valid but is simplified less.
pub fn simplify(mesh: &TriangleMesh, params: &SimplifyParams) -> (TriangleMesh, SimplifyStats) {
    simplify_in(mesh, params, regions_for(mesh))
}

/// The regions [`simplify`] cuts `mesh` into.
fn regions_for(mesh: &TriangleMesh) -> usize {
    (mesh.triangles.len() / REGION_TRIANGLES).clamp(1, MAX_REGIONS)
}

/// Triangles per region when [`simplify`] splits a mesh (fewer: one region, nothing split).
const REGION_TRIANGLES: usize = 25_000;

/// Most regions [`simplify`] splits a mesh into (at 25,000 triangles a region, 25.6 million
/// triangles).
const MAX_REGIONS: usize = 1024;

/// [`simplify`] with the mesh cut into `regions` boxes of equal vertex count ([`cut_boxes`]; 1: not
/// cut, every collapse made one after the other). Each box's triangles are simplified apart,
/// in parallel, with the vertices of the triangles that cross a cut locked; the collapses around the
/// cuts are then queued again on the whole mesh and made in one pass. Every collapse passes the same
/// checks either way, so the bound holds the same; the result depends on the number of regions, not
/// on the number of threads.
pub fn simplify_in(mesh: &TriangleMesh, params: &SimplifyParams, regions: usize) -> (TriangleMesh, SimplifyStats) {
    let (simple, stats, _, ()) = simplify_kept(mesh, params, regions, &vec![false; mesh.vertices.len()], false, || ());
    (simple, stats)
}

/// [`simplify_in`] with the vertices `keep` marks (indexed like `mesh.vertices`) neither moved nor
/// removed, and `beside` run on a core the simplification leaves idle: beside its serial last pass
/// (the whole mesh when it is not cut), or, when it is cut, from when the first thread finds no
/// region left to take (beside the last regions, then beside the pass at the cuts). With `bounds`, also each input
/// vertex's distance (metres) to the triangle of the result it is tracked on, an upper bound of its
/// distance to the result before the result's corners are rounded to `f32` (infinite for a vertex
/// on no triangle; empty without `bounds` or when nothing was simplified).
fn simplify_kept<R: Send>(
    mesh: &TriangleMesh,
    params: &SimplifyParams,
    regions: usize,
    keep: &[bool],
    bounds: bool,
    beside: impl FnOnce() -> R + Send,
) -> (TriangleMesh, SimplifyStats, Vec<f64>, R) {
    let mut stats = SimplifyStats { triangles_before: mesh.triangles.len(), ..SimplifyStats::default() };
    let n = mesh.vertices.len();
    let valid = mesh.triangles.iter().all(|t| t.iter().all(|&i| (i as usize) < n));
    let bound2 = params.max_error_m * params.max_error_m;
    if !(valid && bound2 > 0.0 && bound2.is_finite()) || mesh.triangles.is_empty() || n >= NONE as usize {
        stats.triangles_after = mesh.triangles.len();
        return (mesh.clone(), stats, Vec::new(), beside());
    }
    let centre = {
        let mut c = [0f64; 3];
        for v in &mesh.vertices {
            for a in 0..3 {
                c[a] += f64::from(v[a]);
            }
        }
        c.map(|x| x / n as f64)
    };
    let pos: Vec<[f64; 3]> = mesh.vertices.iter().map(|v| [0, 1, 2].map(|a| f64::from(v[a]) - centre[a])).collect();
    let original = Original::new(pos, mesh.triangles.clone());
    let quadric = original.quadrics();
    let state = State::start(&original, quadric);
    // The whole mesh, nothing locked: everything when it was not split, else the edges at the cuts.
    let whole_pass = |state: State, seam: &[bool], stats: &mut SimplifyStats| {
        let mut work = Work::new(&original, state, keep.to_vec(), bound2);
        let at_cuts = |a: u32, b: u32| seam.is_empty() || seam[a as usize] || seam[b as usize];
        work.run(&mut queue_edges(&work, params.max_error_m, at_cuts), stats);
        work
    };
    let (work, beside) = if regions > 1 {
        let split = Split::new(&original, regions);
        // Each region's result goes into the whole mesh's state as soon as it is done, so only the
        // regions being worked on hold a state of their own. Regions own disjoint vertices and
        // triangles, so the order they finish in does not change the result. Each thread takes
        // the next region until none is left; the one that finishes the last region makes the
        // pass at the cuts, and the first to find none left runs `beside` (so `beside` fills the
        // cores the last regions leave idle, then runs beside that pass).
        let shared = Mutex::new(state);
        let (next, finished) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let region_stats = Mutex::new(SimplifyStats::default());
        let beside = Mutex::new(Some(beside));
        let (beside_out, whole) = (Mutex::new(None), Mutex::new(None));
        let worker = || loop {
            let r = next.fetch_add(1, AtomicOrdering::Relaxed);
            if r >= regions {
                // Taken out of the lock first: held through `f`, it would keep the other threads,
                // blocked on it, from helping with the work `f` spawns.
                let f = lock(&beside).take();
                if let Some(f) = f {
                    *lock(&beside_out) = Some(f());
                }
                return;
            }
            let (sub, sub_state, sub_locked) = split.region(&original, &shared, r, keep);
            let mut work = Work::new(&sub, sub_state, sub_locked, bound2);
            let mut sub_stats = SimplifyStats::default();
            work.run(&mut queue_edges(&work, params.max_error_m, |_, _| true), &mut sub_stats);
            let sub_state = work.into_state();
            drop(sub);
            split.absorb(r, sub_state, &mut lock(&shared));
            {
                let mut total = lock(&region_stats);
                total.collapses += sub_stats.collapses;
                total.refused_by_distance += sub_stats.refused_by_distance;
            }
            if finished.fetch_add(1, AtomicOrdering::AcqRel) + 1 == regions {
                let state = std::mem::take(&mut *lock(&shared));
                let mut cut_stats = SimplifyStats::default();
                let work = whole_pass(state, &split.seam, &mut cut_stats);
                *lock(&whole) = Some((work, cut_stats));
            }
        };
        rayon::scope(|s| {
            for _ in 1..rayon::current_num_threads().clamp(1, regions) {
                s.spawn(|_| worker());
            }
            worker();
        });
        let region_stats = region_stats.into_inner().unwrap_or_else(PoisonError::into_inner);
        let (work, cut_stats) =
            whole.into_inner().unwrap_or_else(PoisonError::into_inner).expect("every region finished");
        stats.collapses += region_stats.collapses + cut_stats.collapses;
        stats.refused_by_distance += region_stats.refused_by_distance + cut_stats.refused_by_distance;
        (work, beside_out.into_inner().unwrap_or_else(PoisonError::into_inner).expect("a worker ran it"))
    } else {
        rayon::join(|| whole_pass(state, &[], &mut stats), beside)
    };
    // Compact.
    let mut remap = vec![NONE; n];
    let mut out = TriangleMesh::default();
    let mut colors = mesh.colors.as_ref().map(|_| Vec::new());
    for (t, _) in work.tris.iter().zip(&work.alive_tri).filter(|(_, &keep)| keep) {
        out.triangles.push(t.map(|i| {
            if remap[i as usize] == NONE {
                remap[i as usize] = out.vertices.len() as u32;
                out.vertices.push([0, 1, 2].map(|a| (work.pos[i as usize][a] + centre[a]) as f32));
                if let (Some(dst), Some(src)) = (colors.as_mut(), mesh.colors.as_ref()) {
                    dst.push(src.get(i as usize).copied().unwrap_or([128, 128, 128]));
                }
            }
            remap[i as usize]
        }));
    }
    out.colors = colors;
    stats.triangles_after = out.triangles.len();
    let tracked = if bounds { work.tracked_distances() } else { Vec::new() };
    (out, stats, tracked, beside)
}

/// The data behind `m`, also when a thread panicked holding it (the panic is propagated anyway).
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The edges `a < b` of the live triangles that `wanted` accepts, queued (those with a locked end
/// are not).
fn queue_edges(work: &Work<'_>, max_error_m: f64, wanted: impl Fn(u32, u32) -> bool) -> CollapseQueue {
    let mut queue = CollapseQueue::new(max_error_m);
    for (t, _) in work.tris.iter().zip(&work.alive_tri).filter(|(_, &a)| a) {
        for e in 0..3 {
            let (a, b) = (t[e], t[(e + 1) % 3]);
            if a < b && wanted(a, b) {
                work.push(&mut queue, a, b);
            }
        }
    }
    queue
}

/// A mesh cut into boxes for [`simplify_in`]: each vertex in one box, each triangle in the box of
/// its three corners or on a cut.
struct Split {
    /// The vertices (original indices) each region simplifies, and the triangles.
    vertices: Vec<Vec<u32>>,
    triangles: Vec<Vec<u32>>,
    /// Index of each vertex in its region's list (`NONE`: on no triangle of its region).
    local: Vec<u32>,
    /// Vertices of a triangle that crosses a cut.
    seam: Vec<bool>,
}

impl Split {
    fn new(original: &Original, regions: usize) -> Split {
        let n = original.pos.len();
        let mut region_of = vec![0u32; n];
        let mut order: Vec<u32> = (0..n as u32).collect();
        cut_boxes(&original.pos, &mut order, regions, 0, &mut region_of);
        let mut triangles = vec![Vec::new(); regions];
        let mut seam = vec![false; n];
        for (ti, t) in original.tris.iter().enumerate() {
            let r = region_of[t[0] as usize];
            if t.iter().all(|&v| region_of[v as usize] == r) {
                triangles[r as usize].push(ti as u32);
            } else {
                for &v in t {
                    seam[v as usize] = true;
                }
            }
        }
        let mut vertices = vec![Vec::new(); regions];
        let mut local = vec![NONE; n];
        for (r, tris) in triangles.iter().enumerate() {
            for &t in tris {
                for v in original.tris[t as usize] {
                    if local[v as usize] == NONE {
                        local[v as usize] = vertices[r].len() as u32;
                        vertices[r].push(v);
                    }
                }
            }
        }
        Split { vertices, triangles, local, seam }
    }

    /// Region `r` as a mesh of its own (its triangles, renumbered), its state and locked vertices:
    /// those on the seam and those `keep` marks (indexed like the whole mesh).
    /// The quadrics are read from the whole mesh's state (`shared`), locked only while they are
    /// copied.
    fn region(
        &self,
        original: &Original,
        shared: &Mutex<State>,
        r: usize,
        keep: &[bool],
    ) -> (Original, State, Vec<bool>) {
        let (vertices, triangles) = (&self.vertices[r], &self.triangles[r]);
        let tris: Vec<[u32; 3]> =
            triangles.iter().map(|&t| original.tris[t as usize].map(|v| self.local[v as usize])).collect();
        let sub = Original::new(vertices.iter().map(|&v| original.pos[v as usize]).collect(), tris);
        let quadric = {
            let guard = lock(shared);
            vertices.iter().map(|&v| guard.quadric[v as usize]).collect()
        };
        let sub_state = State::start(&sub, quadric);
        let locked = vertices.iter().map(|&v| self.seam[v as usize] || keep[v as usize]).collect();
        (sub, sub_state, locked)
    }

    /// Region `r`'s result written back into the whole mesh's state.
    fn absorb(&self, r: usize, sub: State, state: &mut State) {
        let (vertices, triangles) = (&self.vertices[r], &self.triangles[r]);
        for (l, &v) in vertices.iter().enumerate() {
            let v = v as usize;
            state.pos[v] = sub.pos[l];
            state.quadric[v] = sub.quadric[l];
            state.alive[v] = sub.alive[l];
            state.home[v] = triangles[sub.home[l] as usize];
        }
        for (l, &t) in triangles.iter().enumerate() {
            state.tris[t as usize] = sub.tris[l].map(|v| vertices[v as usize]);
            state.alive_tri[t as usize] = sub.alive_tri[l];
        }
    }
}

/// Give the vertices `order` lists regions `first..first + regions` (in `region_of`): the vertices
/// are cut at the median of the longest side of their bounding box, in proportion to the regions on
/// either side, and each side is cut again the same way (a k-d tree: the cuts cross the surface
/// over far less area than parallel slabs would).
fn cut_boxes(pos: &[[f64; 3]], order: &mut [u32], regions: usize, first: u32, region_of: &mut [u32]) {
    if regions <= 1 || order.len() < 2 {
        for &v in order.iter() {
            region_of[v as usize] = first;
        }
        return;
    }
    let (lo, hi) = order.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(lo, hi), &v| {
        let p = pos[v as usize];
        ([0, 1, 2].map(|k| lo[k].min(p[k])), [0, 1, 2].map(|k| hi[k].max(p[k])))
    });
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let left = regions / 2;
    let at = order.len() * left / regions;
    order.select_nth_unstable_by(at, |&a, &b| pos[a as usize][axis].total_cmp(&pos[b as usize][axis]).then(a.cmp(&b)));
    let (l, r) = order.split_at_mut(at);
    cut_boxes(pos, l, left, first, region_of);
    cut_boxes(pos, r, regions - left, first + left as u32, region_of);
}

/// The result of [`simplify_within`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Simplification {
    /// The error bound asked for, metres.
    pub max_error_m: f64,
    /// Triangle counts and collapses.
    #[serde(flatten)]
    pub stats: SimplifyStats,
    /// Sampled symmetric Hausdorff distance between the simplified and the unsimplified surface.
    pub hausdorff: Hausdorff,
    /// Whether the sampled distance is within the bound. The vertices are within it by construction;
    /// `false` means a sample inside a triangle is not even after [`MAX_REPAIRS`] repairs (or a
    /// fault), and the mesh is kept as made.
    pub within_bound: bool,
    /// Times the input was simplified again with the vertices around samples beyond the bound kept.
    pub repairs: usize,
    /// Wall-clock time of the simplification, seconds, with the input's half of the Hausdorff check
    /// (its index and samples) when that was prepared beside the simplification (inputs of at most a
    /// million triangles).
    pub simplify_s: f64,
    /// Wall-clock time of the Hausdorff check, seconds (without the input's half when that was
    /// prepared beside the simplification).
    pub check_s: f64,
}

/// Largest mesh, in triangles, whose half of the Hausdorff check [`simplify_within`] prepares
/// beside the simplification. Held while the simplifier runs, it adds to the peak memory about 60
/// bytes a triangle (52 for the packed triangle, plus its cell lists and the vertex samples), so at
/// most about 120 MB below this limit. It shortened the shipped 128^3 depth-fusion scan's wait, and
/// the cup's at 256^3 (1.35 million triangles: simplification and check 2.05 s -> 1.83 s on the
/// saved mesh, when the limit was one million). Above it, on the 512^3 cup's 5.4 million triangles
/// with up to 1,024 regions (the pass at the cuts then leaves a core idle for about 1.4 s):
/// simplification and check 6.3-6.4 s -> 5.7-6.9 s in two alternating pairs on the saved mesh, for
/// +570-576 MiB of peak RSS, so the limit stays.
const BESIDE_MAX_TRIANGLES: usize = 2_000_000;

/// Most times [`simplify_within`] simplifies again after its check found samples beyond the bound.
pub const MAX_REPAIRS: usize = 3;

/// Simplify `mesh` with every collapse bounded by `max_error_m` ([`simplify`]), then measure its
/// sampled symmetric Hausdorff distance to the input (`samples` area samples per surface plus every
/// vertex). Should a sample of either surface lie beyond the bound (inside a triangle: the vertices
/// are within it by construction), every input vertex within the simplified mesh's longest edge of
/// such a sample is kept in place and the input simplified again, at most [`MAX_REPAIRS`] times;
/// [`Simplification::within_bound`] says whether the last measurement confirms the bound (the last
/// mesh is kept either way). `None` when `max_error_m` is not positive (nothing is done).
pub fn simplify_within(
    mesh: &TriangleMesh,
    max_error_m: f64,
    samples: usize,
) -> Option<(TriangleMesh, Simplification)> {
    simplify_checked(mesh, max_error_m, samples, mesh.triangles.len() <= BESIDE_MAX_TRIANGLES)
}

/// [`simplify_within`], with the input's half of the check (its index and samples) prepared once and
/// kept across repairs: `beside` the first simplification (on a core it leaves idle, see
/// [`simplify_kept`]), or after it.
fn simplify_checked(
    mesh: &TriangleMesh,
    max_error_m: f64,
    samples: usize,
    beside: bool,
) -> Option<(TriangleMesh, Simplification)> {
    if !(max_error_m > 0.0 && max_error_m.is_finite()) {
        return None;
    }
    let params = SimplifyParams { max_error_m };
    let regions = regions_for(mesh);
    let mut keep = vec![false; mesh.vertices.len()];
    let t = Instant::now();
    let (mut simple, mut stats, mut tracked, early) =
        simplify_kept(mesh, &params, regions, &keep, true, || beside.then(|| Reference::new(mesh, samples)));
    let mut simplify_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let reference = early.unwrap_or_else(|| Reference::new(mesh, samples));
    let (mut check_s, mut repairs) = (t.elapsed().as_secs_f64(), 0);
    loop {
        let t = Instant::now();
        // Every input vertex is within its tracked distance of the result: only those that could
        // reach the largest distance of the samples are measured.
        let (hausdorff, far) = reference
            .as_ref()
            .and_then(|r| hausdorff_outliers_to(&simple, r, max_error_m, Some(&tracked)))
            .unwrap_or_default();
        check_s += t.elapsed().as_secs_f64();
        let within_bound = far.is_empty();
        if within_bound || repairs == MAX_REPAIRS || !keep_around(mesh, &simple, &far, &mut keep) {
            let s = Simplification { max_error_m, stats, hausdorff, within_bound, repairs, simplify_s, check_s };
            return Some((simple, s));
        }
        repairs += 1;
        let t = Instant::now();
        (simple, stats, tracked, ()) = simplify_kept(mesh, &params, regions, &keep, true, || ());
        simplify_s += t.elapsed().as_secs_f64();
    }
}

/// Mark in `keep` every vertex of `mesh` within the longest edge of `simple` of a point of `far`
/// (so no triangle that reaches such a point is made again); whether a vertex was newly marked.
fn keep_around(mesh: &TriangleMesh, simple: &TriangleMesh, far: &[[f32; 3]], keep: &mut [bool]) -> bool {
    let d2 = |a: [f32; 3], b: [f32; 3]| (0..3).map(|k| (f64::from(a[k]) - f64::from(b[k])).powi(2)).sum::<f64>();
    let reach2 = simple
        .triangles
        .iter()
        .flat_map(|t| (0..3).map(move |e| (t[e], t[(e + 1) % 3])))
        .map(|(a, b)| d2(simple.vertices[a as usize], simple.vertices[b as usize]))
        .fold(0.0, f64::max);
    let reach = reach2.sqrt() as f32;
    let far = PointIndex::new(far);
    let mut changed = false;
    for (v, k) in mesh.vertices.iter().zip(keep.iter_mut()) {
        if !*k && far.nearest_distance(v).is_some_and(|d| d <= reach) {
            *k = true;
            changed = true;
        }
    }
    changed
}

/// The cheapest point for collapsing edge `a`-`b` and its quadric cost: the quadric's minimiser when it
/// is well defined and near the edge, else the better of the ends and the midpoint.
fn best_position(pos: &[[f64; 3]], quadric: &[Quadric], a: u32, b: u32) -> (f64, [f64; 3]) {
    let q = Quadric::sum(&quadric[a as usize], &quadric[b as usize]);
    let (pa, pb) = (pos[a as usize], pos[b as usize]);
    let mid = [0, 1, 2].map(|k| 0.5 * (pa[k] + pb[k]));
    let len = norm(sub(pb, pa));
    let near = |p: &[f64; 3]| norm(sub(*p, mid)) <= 2.0 * len;
    // A well-conditioned quadric's minimiser is its global minimum: no other candidate is cheaper.
    if let Some(p) = q.minimiser().filter(near) {
        return (q.eval(p).max(0.0), p);
    }
    let mut best = (f64::INFINITY, mid);
    for p in [pa, pb, mid] {
        let c = q.eval(p);
        if c < best.0 {
            best = (c, p);
        }
    }
    (best.0.max(0.0), best.1)
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
    use crate::pipeline::{hausdorff_distance, hausdorff_outliers, TriangleIndex};

    fn mesh_of(occ: &Occupancy) -> TriangleMesh {
        extract_surface(occ, &MeshParams::smoothed(0)).expect("mesh")
    }

    #[test]
    fn an_edge_whose_ends_share_a_third_neighbour_is_not_collapsed() {
        // A triangular bipyramid: equator p, q, r (0, 1, 2), poles n and s (3, 4). The equator edge
        // p-q has the poles opposite it, and r is a third common neighbour of its ends: collapsing
        // it would leave two copies of the triangles around r. A pole edge n-p has only q and r.
        let pos = vec![[1.0, 0.0, 0.0], [-0.5, 0.87, 0.0], [-0.5, -0.87, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]];
        let tris = vec![[0, 1, 3], [1, 2, 3], [2, 0, 3], [1, 0, 4], [2, 1, 4], [0, 2, 4]];
        let original = Original::new(pos, tris);
        let quadric = original.quadrics();
        let state = State::start(&original, quadric);
        let mut work = Work::new(&original, state, vec![false; 5], 100.0);
        assert!(matches!(work.try_collapse(0, 1), Err(Refusal::Shape)));
        assert!(work.try_collapse(3, 0).is_ok());
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
            assert!(s.stats.triangles_after * 2 < s.stats.triangles_before, "{name}: {s:?}");
            assert!(s.hausdorff.symmetric_m <= bound, "{name}: {s:?}");
            let topo = simple.topology();
            assert_eq!(topo.open_or_misoriented_edges, 0, "{name}");
            assert_eq!((topo.components, topo.euler_characteristic), (1, euler), "{name}");
            assert!(simple.signed_volume() > 0.0);
            let (split, _) = simplify_in(&mesh, &SimplifyParams { max_error_m: bound }, 3);
            let topo = split.topology();
            assert_eq!((topo.components, topo.open_or_misoriented_edges, topo.euler_characteristic), (1, 0, euler));
        }
        assert!(simplify_within(&mesh_of(&Occupancy::full(grid)), 0.0, 100).is_none());
    }

    /// A sphere of radius 0.7 in a 40^3 grid over [-1, 1]^3, its vertices moved radially by
    /// deterministic noise spanning `voxels` voxels from lowest to highest.
    fn noisy_sphere(voxels: f64) -> (VoxelGrid, TriangleMesh) {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0; 3] }, 40);
        let mut mesh = mesh_of(&Occupancy::from_fn(grid, |p| p.norm() < 0.7));
        for (i, v) in mesh.vertices.iter_mut().enumerate() {
            *v = moved_radially(v.map(f64::from), i, voxels * grid.voxel_size);
        }
        (grid, mesh)
    }

    /// `p` (metres) moved away from the origin by deterministic noise of the point's `index`, within
    /// `span_m / 2` either way.
    fn moved_radially(p: [f64; 3], index: usize, span_m: f64) -> [f32; 3] {
        let h = (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40;
        let noise = (h as f64 / (1u64 << 24) as f64 - 0.5) * span_m;
        let r = p.iter().map(|x| x * x).sum::<f64>().sqrt();
        p.map(|x| (x * (1.0 + noise / r)) as f32)
    }

    /// Every vertex of either mesh lies within the bound of the other surface, exactly (not sampled),
    /// on a noisy surface where the quadric alone lets the surfaces drift apart.
    #[test]
    fn every_vertex_is_within_the_bound_of_the_other_surface() {
        let (grid, mesh) = noisy_sphere(0.2);
        let bound = 0.25 * grid.voxel_size;
        let slack = 1e-6;
        let to_mesh = TriangleIndex::new(&mesh).expect("triangles");
        // Whole, and cut into regions simplified apart (the seams then on the whole mesh). 24 regions
        // of about 300 triangles each (7,392 in all) stand for a large mesh cut into many boxes: far
        // more of the vertices lie on a cut than with 2 or 5.
        let mut counts = Vec::new();
        for regions in [1, 2, 5, 24] {
            let (simple, stats) = simplify_in(&mesh, &SimplifyParams { max_error_m: bound }, regions);
            assert!(stats.triangles_after * 3 < stats.triangles_before * 2, "{regions}: {stats:?}");
            let to_simple = TriangleIndex::new(&simple).expect("triangles");
            let worst = mesh.vertices.iter().map(|v| to_simple.distance(v.map(f64::from))).fold(0.0, f64::max);
            assert!(
                worst <= bound + slack,
                "{regions}: original vertex {worst} from the simplified surface, bound {bound}"
            );
            let worst = simple.vertices.iter().map(|v| to_mesh.distance(v.map(f64::from))).fold(0.0, f64::max);
            assert!(
                worst <= bound + slack,
                "{regions}: simplified vertex {worst} from the original surface, bound {bound}"
            );
            let topo = simple.topology();
            assert_eq!((topo.components, topo.open_or_misoriented_edges, topo.euler_characteristic), (1, 0, 2));
            counts.push(stats.triangles_after);
        }
        // The seams are simplified as well as the rest: within 5 % of the whole mesh's count.
        assert!(counts.iter().all(|&c| c * 20 <= counts[0] * 21), "{counts:?}");
    }

    /// The regions go to whichever thread is free and the pass at the cuts to the one that finishes
    /// the last: on 1, 2 or 3 threads the meshes, counts and measurements are the same.
    #[test]
    fn the_result_does_not_depend_on_the_threads() {
        let (grid, mesh) = noisy_sphere(0.2);
        let bound = 0.25 * grid.voxel_size;
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            pool.install(|| {
                let split = simplify_in(&mesh, &SimplifyParams { max_error_m: bound }, 5);
                let (checked, s) = simplify_checked(&mesh, bound, 20_000, true).expect("bound > 0");
                (split, checked, Simplification { simplify_s: 0.0, check_s: 0.0, ..s })
            })
        };
        let one = run(1);
        assert!(one.0 .1.collapses > 1000 && one.2.stats.collapses > 1000, "{:?}", one.2);
        for threads in [2, 3] {
            let other = run(threads);
            assert_eq!((&other.0 .0.vertices, &other.0 .0.triangles), (&one.0 .0.vertices, &one.0 .0.triangles));
            assert_eq!(other.0 .1, one.0 .1, "{threads} threads");
            assert_eq!((&other.1.vertices, &other.1.triangles), (&one.1.vertices, &one.1.triangles));
            assert_eq!(other.2, one.2, "{threads} threads");
        }
    }

    /// Each input vertex's tracked distance bounds its distance to the simplified surface (whole and
    /// in regions), so the check that skips the vertices those bounds keep below its maximum gives
    /// the figures and outliers of measuring every vertex.
    #[test]
    fn tracked_distances_bound_the_vertices_and_leave_the_check_unchanged() {
        let (grid, mesh) = noisy_sphere(0.2);
        let bound = 0.25 * grid.voxel_size;
        let params = SimplifyParams { max_error_m: bound };
        let keep = vec![false; mesh.vertices.len()];
        for regions in [1, 3] {
            let (simple, _, tracked, ()) = simplify_kept(&mesh, &params, regions, &keep, true, || ());
            assert_eq!(tracked.len(), mesh.vertices.len());
            let to_simple = TriangleIndex::new(&simple).expect("triangles");
            let slack = 1e-6 * grid.voxel_size;
            for (v, &t) in mesh.vertices.iter().zip(&tracked) {
                let d = to_simple.distance(v.map(f64::from));
                assert!(d <= t + slack && t <= bound, "{regions}: vertex at {d} tracked at {t}, bound {bound}");
            }
        }
        let (simple, s) = simplify_within(&mesh, bound, 20_000).expect("bound > 0");
        let (every, far) = hausdorff_outliers(&simple, &mesh, 20_000, bound).expect("triangles");
        assert_eq!(s.hausdorff, every);
        assert!(far.is_empty() && s.within_bound);
    }

    /// A sphere whose triangles are each split at their centroid, the centroids then moved radially
    /// by up to a voxel either way (spikes): a sample of the first pass still leaves the bound between
    /// the probes, and a repair brings every sample within the bound both ways. (The extracted meshes
    /// themselves, noisy or not, left no sample beyond the bound at radial noise of 0.05 to 4 voxels
    /// and bounds of 0.1 to 0.5 voxel.)
    #[test]
    fn triangle_insides_stay_within_the_bound_on_a_rough_surface() {
        let (grid, smooth) = noisy_sphere(0.0);
        let mut mesh = TriangleMesh { vertices: smooth.vertices.clone(), triangles: Vec::new(), colors: None };
        for t in &smooth.triangles {
            let c = [0, 1, 2].map(|a| t.iter().map(|&v| f64::from(smooth.vertices[v as usize][a])).sum::<f64>() / 3.0);
            let n = mesh.vertices.len() as u32;
            mesh.vertices.push(moved_radially(c, n as usize, 2.0 * grid.voxel_size));
            mesh.triangles.extend([[t[0], t[1], n], [t[1], t[2], n], [t[2], t[0], n]]);
        }
        let bound = 0.25 * grid.voxel_size;
        let (first, _) = simplify(&mesh, &SimplifyParams { max_error_m: bound });
        let (_, far) = hausdorff_outliers(&first, &mesh, 100_000, bound).expect("triangles");
        assert!(!far.is_empty(), "the first pass is within the bound: nothing here exercises a repair");
        let (simple, s) = simplify_within(&mesh, bound, 100_000).expect("bound > 0");
        assert!(s.within_bound && s.repairs >= 1, "{s:?}");
        assert!(s.hausdorff.symmetric_m <= bound && s.stats.collapses > 500, "{s:?}");
        // The input's half of the check prepared beside the first simplification or after it: the
        // same meshes and measurements through the repairs.
        for beside in [true, false] {
            let (other, o) = simplify_checked(&mesh, bound, 100_000, beside).expect("bound > 0");
            assert_eq!((&other.vertices, &other.triangles), (&simple.vertices, &simple.triangles), "beside {beside}");
            let untimed = |s: Simplification| Simplification { simplify_s: 0.0, check_s: 0.0, ..s };
            assert_eq!(untimed(o), untimed(s), "beside {beside}");
        }
    }

    /// Kept vertices neither move nor go, whole or cut into regions, and a repair keeps every vertex
    /// within the simplified mesh's longest edge of a far sample.
    #[test]
    fn kept_vertices_stay_where_they_are() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0; 3] }, 24);
        let mesh = mesh_of(&Occupancy::from_fn(grid, |p| p.norm() < 0.7));
        let bound = 0.25 * grid.voxel_size;
        let params = SimplifyParams { max_error_m: bound };
        let (free, _) = simplify_in(&mesh, &params, 1);
        let mut keep = vec![false; mesh.vertices.len()];
        let far = [mesh.vertices[0]];
        assert!(keep_around(&mesh, &free, &far, &mut keep));
        assert!(!keep_around(&mesh, &free, &far, &mut keep), "nothing new to keep");
        let kept: Vec<[f32; 3]> = mesh.vertices.iter().zip(&keep).filter(|(_, &k)| k).map(|(v, _)| *v).collect();
        assert!(kept.len() > 10 && kept.len() * 4 < mesh.vertices.len(), "{} kept", kept.len());
        for regions in [1, 3] {
            let (simple, stats, _, ()) = simplify_kept(&mesh, &params, regions, &keep, false, || ());
            assert!(stats.collapses > 0);
            for v in &kept {
                assert!(simple.vertices.contains(v), "{regions}: kept vertex {v:?} moved or went");
            }
        }
    }

    /// The cut keeps every triangle in one region or on a cut, and locks exactly the corners of the
    /// ones on a cut.
    #[test]
    fn a_split_covers_every_triangle_once() {
        let grid = VoxelGrid::from_resolution(&Aabb { min: [-1.0; 3], max: [1.0; 3] }, 24);
        let mesh = mesh_of(&Occupancy::from_fn(grid, |p| p.norm() < 0.7));
        let pos = mesh.vertices.iter().map(|v| v.map(f64::from)).collect();
        let original = Original::new(pos, mesh.triangles.clone());
        let split = Split::new(&original, 3);
        let mut seen = vec![0u32; mesh.triangles.len()];
        for (r, tris) in split.triangles.iter().enumerate() {
            assert!(tris.len() * 5 > mesh.triangles.len(), "region {r} holds {} triangles", tris.len());
            for &t in tris {
                seen[t as usize] += 1;
                assert!(mesh.triangles[t as usize]
                    .iter()
                    .all(|&v| split.vertices[r][split.local[v as usize] as usize] == v));
            }
        }
        for (t, &n) in seen.iter().enumerate() {
            let corners_locked = mesh.triangles[t].iter().all(|&v| split.seam[v as usize]);
            assert!(n == 1 || (n == 0 && corners_locked), "triangle {t} in {n} regions");
        }
        let on_cut = seen.iter().filter(|&&n| n == 0).count();
        assert!(on_cut > 0 && on_cut * 10 < mesh.triangles.len(), "{on_cut} triangles on the cuts");
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
