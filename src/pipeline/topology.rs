//! Removal of voxel-scale handles (tunnels and bridges) from an occupancy before it is meshed.
//!
//! A measured solid is noisy at the scale of a voxel: a wall two voxels thick gets a one-voxel hole
//! through it, a groove gets a one-voxel bridge over it. Each such defect is a handle of the surface
//! (genus +1, Euler characteristic -2) although the object has none there. This module removes them
//! by changing as few voxels as it can, only voxels within one voxel of the surface, and only where
//! the change removes a handle; every other voxel keeps its value.
//!
//! **Digital topology.** [`extract_surface`](super::extract_surface) meshes the occupancy with the
//! topology of the Kuhn (Freudenthal) triangulation of the lattice of voxel centres (its dual surface
//! joins and separates the sheets at each critical edge and corner as that triangulation does). Its
//! surface therefore has the topology of the simplicial complex spanned by the occupied voxels in that
//! triangulation, whose edges join a voxel to its 14 neighbours `±v`, `v ∈ {0,1}³ \ {0}` (both the
//! solid and the air use this 14-adjacency, which is why the pair is free of the paradoxes of
//! 6/26-connectivity). The link of a voxel (the neighbours and the triangles among them) is a
//! triangulated sphere; two neighbours are joined in it when their difference is itself one of the
//! 14 offsets. Changing one voxel leaves the topology of both the solid and the air unchanged (the
//! voxel is *simple*) exactly when its solid neighbours and its empty neighbours are both non-empty
//! and each connected in the link (on a sphere, a full subcomplex is contractible exactly when it
//! and its complement are non-empty and connected).
//!
//! **Handle removal** (in the spirit of the morphological topology corrections of Han, Xu and Prince,
//! "Topology correction in brain cortex segmentation using a multiscale, graph-based algorithm",
//! IEEE TMI 2002, and of homotopic growing and thinning constrained to a band, Bertrand and Couprie's
//! digital topology; written from their descriptions):
//!
//! 1. *Fill.* The candidates are the voxels a morphological closing (3×3×3 cube) adds: empty voxels
//!    next to the solid in a concavity at most two voxels wide, such as a hole through a thin wall or
//!    the gap under a bridge. The solid grows into the candidates through simple voxels (which
//!    changes nothing topologically) and through voxels whose solid neighbours are connected and
//!    whose empty neighbours form two or more groups that stay connected through the rest of the air
//!    (checked by a breadth-first search from each group, run in turn until they meet or one runs
//!    out): filling such a voxel closes a tunnel without enclosing a cavity or joining two parts.
//!    Then every added voxel that is simple is removed again, until none is; what stays is a thin
//!    plug in each closed tunnel.
//! 2. *Cut.* The same with solid and air exchanged: the candidates are the solid voxels a
//!    morphological opening removes (parts at most two voxels thick), the air grows into them where
//!    that cuts a bridge without splitting the solid or opening a cavity, and every cut voxel that is
//!    simple is given back.
//!
//! The two run in turn while a round cuts something (a cut can open the way for a fill; at most
//! three rounds). Each fill or cut lowers the genus by one per extra group, so the result never has
//! more handles than the input and has the same components and cavities; a voxel filled touches a
//! solid voxel of the input and a voxel cut an empty one (26-neighbourhood), so the surface moves by
//! at most about one voxel, and only where it plugs a tunnel or cuts a bridge; a phase that removes
//! no handle changes nothing. A real handle whose hole and whose bar are both wider than about two
//! voxels (a cup's handle, a torus) has no candidate that removes it and stays; a real bar or slot
//! thinner than that is taken for noise.

use std::collections::VecDeque;
use std::sync::OnceLock;
use std::time::Instant;

use rayon::prelude::*;

use super::occupancy::{Brick, Occupancy, BRICK};

/// Fill-and-cut rounds of [`remove_small_handles`] at most.
const MAX_ROUNDS: usize = 3;

/// What [`remove_small_handles`] changed.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct HandleRepair {
    /// Tunnels closed by filling (each lowers the genus by one).
    pub tunnels_filled: u64,
    /// Bridges cut (each lowers the genus by one).
    pub bridges_cut: u64,
    /// Empty voxels of the input made solid (the plugs).
    pub voxels_added: u64,
    /// Solid voxels of the input made empty (the cuts).
    pub voxels_removed: u64,
    /// Wall-clock time, seconds.
    pub seconds: f64,
}

impl HandleRepair {
    /// Handles removed in all, summed over the surface's components (a floating part that the mesh
    /// clean-up drops later may have had some): the genus drop, and half the Euler characteristic's
    /// rise.
    pub fn handles_removed(&self) -> u64 {
        self.tunnels_filled + self.bridges_cut
    }
}

/// The occupancy with its voxel-scale handles removed (module docs), and what changed. Same grid
/// (metres, its frame) as the input.
pub fn remove_small_handles(occupancy: &Occupancy) -> (Occupancy, HandleRepair) {
    remove_small_handles_with(occupancy, None)
}

/// [`remove_small_handles`] with the side searches of each repair using fixed components after
/// `label_after` voxels visited in all (`None`: as many as the volume has); the result does not
/// depend on it (the tests compare).
fn remove_small_handles_with(occupancy: &Occupancy, label_after: Option<usize>) -> (Occupancy, HandleRepair) {
    let t = Instant::now();
    let grid = *occupancy.grid();
    let mut stats = HandleRepair::default();
    if grid.is_empty() || occupancy.count() == 0 {
        stats.seconds = t.elapsed().as_secs_f64();
        return (occupancy.clone(), stats);
    }
    let mut v = Volume::new(occupancy);
    v.label_after = label_after.unwrap_or(v.cells.len());
    let original = v.cells.clone();
    // Every change stays next to the input's surface: a voxel filled touches a solid voxel of the
    // input, a voxel cut touches an empty one (26-neighbourhood), whatever the round.
    let near_solid = v.dilate(&original);
    let mut near_air: Option<Vec<u8>> = None;
    // A cut can open the way for a fill: another round after a round that cut something.
    for round in 0..MAX_ROUNDS {
        // Fill: grow the solid (value 1) into what a closing adds.
        let closing = if round == 0 { v.erode(&near_solid) } else { v.erode(&v.dilate(&v.cells)) };
        let allowed: Vec<bool> = (0..v.cells.len())
            .into_par_iter()
            .map(|i| closing[i] == 1 && near_solid[i] == 1 && v.cells[i] == 0 && v.inner(i))
            .collect();
        drop(closing);
        stats.tunnels_filled += v.repair(1, &allowed);
        // Cut: grow the air (value 0) into what an opening removes. In the first round every such
        // voxel touches the input's air already.
        let eroded = v.erode(&v.cells);
        let opening = v.dilate(&eroded);
        let near_air: &[u8] = if round == 0 { &[] } else { near_air.get_or_insert_with(|| v.erode(&original)) };
        let allowed: Vec<bool> = (0..v.cells.len())
            .into_par_iter()
            .map(|i| opening[i] == 0 && (round == 0 || near_air[i] == 0) && v.cells[i] == 1 && v.inner(i))
            .collect();
        let cut = v.repair(0, &allowed);
        stats.bridges_cut += cut;
        if cut == 0 {
            break;
        }
    }
    let (added, removed) = original
        .par_iter()
        .zip(&v.cells)
        .map(|(&a, &b)| (u64::from(a < b), u64::from(a > b)))
        .reduce(|| (0, 0), |x, y| (x.0 + y.0, x.1 + y.1));
    stats.voxels_added = added;
    stats.voxels_removed = removed;
    let out = if stats.handles_removed() == 0 {
        occupancy.clone()
    } else {
        let p = v.pitch;
        Occupancy::from_index_fn(grid, |i, j, k| v.cells[(i + 1) + p[1] * (j + 1) + p[2] * (k + 1)] == 1)
    };
    stats.seconds = t.elapsed().as_secs_f64();
    (out, stats)
}

/// The Euler characteristic of the Kuhn complex spanned by the occupied voxels (module docs), the
/// alternating count of its vertices, edges, triangles and tetrahedra. Each simplex is counted at
/// its lowest voxel `v`: its other voxels are `v + a`, `v + b`, ... for a chain `a < b < ...` of
/// offsets in `{0,1}³ \ {0}` ordered by inclusion. An occupied voxel whose seven forward neighbours
/// are all occupied contributes `1 - 7 + 12 - 6 = 0`, so only bricks that hold empty voxels or
/// border such bricks are visited: the cost follows the surface. The closed surface of the complex
/// has twice this characteristic; with its components (the solid's parts and cavities) it gives the
/// handles: `genus = components - characteristic`.
pub(crate) fn kuhn_euler_characteristic(occ: &Occupancy) -> i64 {
    // Per mask of occupied forward neighbours (bit n - 1 for offset n, bit a of n set: +1 along
    // axis a), the occupied voxel's count.
    let table: [i8; 128] = std::array::from_fn(|m| {
        let has = |n: usize| m >> (n - 1) & 1 == 1;
        let within = |a: usize, b: usize| a != b && a & b == a;
        let edges = (1..8).filter(|&n| has(n)).count() as i8;
        let triangles =
            (1..8).flat_map(|a| (1..8).map(move |b| (a, b))).filter(|&(a, b)| within(a, b) && has(a) && has(b)).count()
                as i8;
        let tetrahedra = [1, 2, 4]
            .into_iter()
            .flat_map(|a| [3, 5, 6].into_iter().map(move |b| (a, b)))
            .filter(|&(a, b)| within(a, b) && has(a) && has(b) && has(7))
            .count() as i8;
        1 - edges + triangles - tetrahedra
    });
    let bd = occ.brick_dims();
    // `brick` is empty beyond the grid.
    let full = |c: [usize; 3]| occ.brick(c[0], c[1], c[2]) == Brick::Full;
    (0..bd[0] * bd[1] * bd[2])
        .into_par_iter()
        .map(|b| {
            let c = [b % bd[0], b / bd[0] % bd[1], b / (bd[0] * bd[1])];
            match occ.brick(c[0], c[1], c[2]) {
                Brick::Empty => return 0,
                // A full brick's voxels all have their forward neighbours when the seven bricks
                // ahead of it are full too.
                Brick::Full if (1..8).all(|n| full([0, 1, 2].map(|a| c[a] + (n >> a & 1)))) => return 0,
                _ => {}
            }
            // The brick and one voxel beyond it along each axis.
            const W: usize = BRICK + 1;
            let base = c.map(|x| x * BRICK);
            let mut local = [false; W * W * W];
            for z in 0..W {
                for y in 0..W {
                    for x in 0..W {
                        local[x + W * (y + W * z)] = occ.get(base[0] + x, base[1] + y, base[2] + z);
                    }
                }
            }
            let mut sum = 0i64;
            for z in 0..BRICK {
                for y in 0..BRICK {
                    for x in 0..BRICK {
                        let i = x + W * (y + W * z);
                        if !local[i] {
                            continue;
                        }
                        let mask = (1..8).fold(0usize, |m, n| {
                            let o = (n & 1) + W * ((n >> 1 & 1) + W * (n >> 2 & 1));
                            m | usize::from(local[i + o]) << (n - 1)
                        });
                        sum += i64::from(table[mask]);
                    }
                }
            }
            sum
        })
        .sum()
}

/// The 14 lattice neighbours of the Kuhn triangulation, as offsets.
fn neighbour_offsets() -> [[i64; 3]; 14] {
    let mut out = [[0i64; 3]; 14];
    for n in 1..8usize {
        let v = [0, 1, 2].map(|a| ((n >> a) & 1) as i64);
        out[2 * (n - 1)] = v;
        out[2 * (n - 1) + 1] = v.map(|x| -x);
    }
    out
}

/// The link adjacency of the 14 neighbours: bit `b` of entry `a` set when neighbours `a` and `b`
/// span a triangle with the centre (their difference is itself one of the 14 offsets).
fn link_adjacency() -> &'static [u16; 14] {
    static ADJ: OnceLock<[u16; 14]> = OnceLock::new();
    ADJ.get_or_init(|| {
        let offs = neighbour_offsets();
        let mut adj = [0u16; 14];
        for a in 0..14 {
            for b in 0..14 {
                let d = [0, 1, 2].map(|k| offs[a][k] - offs[b][k]);
                if a != b && offs.contains(&d) {
                    adj[a] |= 1 << b;
                }
            }
        }
        adj
    })
}

/// Per configuration of the 14 neighbours (bit `n` set: neighbour `n` has the grown value), the
/// number of connected groups in the link of the neighbours with the grown value (low nibble) and
/// of those without (high nibble).
fn link_table() -> &'static [u8] {
    static TABLE: OnceLock<Vec<u8>> = OnceLock::new();
    TABLE.get_or_init(|| {
        (0..1u32 << 14)
            .map(|m| {
                let m = m as u16;
                let f = group_masks(m).len().min(15) as u8;
                let b = group_masks(!m & 0x3fff).len().min(15) as u8;
                f | (b << 4)
            })
            .collect()
    })
}

/// The connected groups (link adjacency) of the neighbours in `set`, as bit masks.
fn group_masks(set: u16) -> Vec<u16> {
    let adj = link_adjacency();
    let mut out = Vec::new();
    let mut left = set;
    while left != 0 {
        let mut group = left & left.wrapping_neg();
        loop {
            let mut grown = group;
            let mut bits = group;
            while bits != 0 {
                let b = bits.trailing_zeros();
                bits &= bits - 1;
                grown |= adj[b as usize] & set;
            }
            if grown == group {
                break;
            }
            group = grown;
        }
        left &= !group;
        out.push(group);
    }
    out
}

/// The occupancy as one byte per voxel (1 solid), padded by one empty layer on every side (the
/// layer [`extract_surface`](super::extract_surface) closes the surface with; never changed).
struct Volume {
    cells: Vec<u8>,
    /// Padded dimensions.
    dims: [usize; 3],
    /// Linear index steps along x, y, z.
    pitch: [usize; 3],
    /// Linear index offsets of the 14 neighbours.
    nb: [isize; 14],
    /// Search marks: the search that last reached each voxel and from which group.
    stamp: Vec<u32>,
    group: Vec<u8>,
    searches: u32,
    /// Components of the voxels one [`Volume::repair`] cannot change (see
    /// [`Volume::sides_stay_connected`]): a label per voxel, valid from `label_base` on (labels of an
    /// earlier repair are below it), labelled a component at a time as searches reach them.
    label: Vec<u32>,
    label_base: u32,
    next_label: u32,
    /// Voxels the side searches of one repair visit in all before they use the labels: labelling
    /// costs up to the volume once per repair, so it starts only once the searches have cost as much.
    label_after: usize,
    /// Voxels the side searches of the current repair have visited.
    repair_visits: usize,
}

impl Volume {
    fn new(occ: &Occupancy) -> Volume {
        let d = occ.grid().dims;
        let dims = d.map(|x| x + 2);
        let pitch = [1, dims[0], dims[0] * dims[1]];
        let mut cells = vec![0u8; dims[0] * dims[1] * dims[2]];
        occ.for_each_occupied(|i, j, k| cells[(i + 1) + pitch[1] * (j + 1) + pitch[2] * (k + 1)] = 1);
        let nb = neighbour_offsets()
            .map(|o| o[0] as isize + o[1] as isize * pitch[1] as isize + o[2] as isize * pitch[2] as isize);
        Volume {
            cells,
            dims,
            pitch,
            nb,
            stamp: Vec::new(),
            group: Vec::new(),
            searches: 0,
            label: Vec::new(),
            label_base: 1,
            next_label: 1,
            label_after: 0,
            repair_visits: 0,
        }
    }

    /// Is linear index `i` off the padding layer?
    fn inner(&self, i: usize) -> bool {
        let c = [i % self.pitch[1], (i / self.pitch[1]) % self.dims[1], i / self.pitch[2]];
        (0..3).all(|a| c[a] >= 1 && c[a] + 1 < self.dims[a])
    }

    /// Bit `n` set when neighbour `n` of `i` (an inner voxel) has value `value`.
    fn config(&self, i: usize, value: u8) -> u16 {
        let mut m = 0u16;
        for (n, &o) in self.nb.iter().enumerate() {
            if self.cells[(i as isize + o) as usize] == value {
                m |= 1 << n;
            }
        }
        m
    }

    /// Maximum (`max`) or minimum over the 3×3×3 cube around each voxel, out-of-volume values 0:
    /// one pass per axis, each combining whole rows (along `x`), rows of a slice (along `y`) or
    /// slices (along `z`) so that the loops run over contiguous bytes, rows or slices in parallel.
    /// Each pass writes its own buffer from the previous one (the third into the first's), so no
    /// buffer is copied on one core.
    fn cube_filter(&self, src: &[u8], max: bool) -> Vec<u8> {
        let [nx, ny, _] = self.dims;
        let slab = nx * ny;
        let op = |x: u8, y: u8| if max { x.max(y) } else { x.min(y) };
        // `out = op(out, row)`, or `out = op(out, 0)` for a row outside the volume.
        let fold = |out: &mut [u8], row: Option<&[u8]>| match row {
            Some(r) => out.iter_mut().zip(r).for_each(|(o, &v)| *o = op(*o, v)),
            None if max => {}
            None => out.fill(0),
        };
        // `out = op(a, b, c)`, element by element (a row or slice and its two neighbours).
        let three = |out: &mut [u8], a: &[u8], b: Option<&[u8]>, c: Option<&[u8]>| {
            out.copy_from_slice(a);
            fold(out, b);
            fold(out, c);
        };
        // Along x, within each row.
        let mut a = vec![0u8; src.len()];
        a.par_chunks_mut(nx).zip(src.par_chunks(nx)).for_each(|(out, row)| {
            out.copy_from_slice(row);
            if nx > 1 {
                fold(&mut out[1..], Some(&row[..nx - 1]));
                fold(&mut out[..nx - 1], Some(&row[1..]));
            }
            fold(&mut out[..1], None);
            fold(&mut out[nx - 1..], None);
        });
        // Along y, within each slice.
        let mut b = vec![0u8; src.len()];
        b.par_chunks_mut(slab).zip(a.par_chunks(slab)).for_each(|(out, s)| {
            for (y, o) in out.chunks_mut(nx).enumerate() {
                let prev = (y > 0).then(|| &s[(y - 1) * nx..y * nx]);
                let next = (y + 1 < ny).then(|| &s[(y + 1) * nx..(y + 2) * nx]);
                three(o, &s[y * nx..(y + 1) * nx], prev, next);
            }
        });
        // Along z, across slices, into the first pass's buffer (no longer needed).
        let slices = b.len() / slab.max(1);
        a.par_chunks_mut(slab).enumerate().for_each(|(z, o)| {
            let prev = (z > 0).then(|| &b[(z - 1) * slab..z * slab]);
            let next = (z + 1 < slices).then(|| &b[(z + 1) * slab..(z + 2) * slab]);
            three(o, &b[z * slab..(z + 1) * slab], prev, next);
        });
        a
    }

    fn dilate(&self, src: &[u8]) -> Vec<u8> {
        self.cube_filter(src, true)
    }

    fn erode(&self, src: &[u8]) -> Vec<u8> {
        self.cube_filter(src, false)
    }

    /// Grow the voxels of value `value` into `allowed` through simple voxels and handle-removing ones,
    /// then give back every grown voxel that is simple (module docs). Returns the handles removed; when
    /// there were none, nothing changes.
    fn repair(&mut self, value: u8, allowed: &[bool]) -> u64 {
        let table = link_table();
        let other = 1 - value;
        let mut queued = vec![false; self.cells.len()];
        let start: Vec<usize> = (0..allowed.len())
            .into_par_iter()
            .filter(|&i| allowed[i] && self.nb.iter().any(|&o| self.cells[(i as isize + o) as usize] == value))
            .collect();
        if start.is_empty() {
            return 0;
        }
        for &i in &start {
            queued[i] = true;
        }
        let mut queue: VecDeque<usize> = start.into();
        // Labels of an earlier repair describe other fixed voxels: start afresh.
        if self.next_label > u32::MAX / 2 {
            self.label.fill(0);
            self.next_label = 1;
        }
        self.label_base = self.next_label;
        self.repair_visits = 0;
        let mut grown = Vec::new();
        let mut handles = 0u64;
        while let Some(i) = queue.pop_front() {
            queued[i] = false;
            if self.cells[i] == value {
                continue;
            }
            let m = self.config(i, value);
            let t = table[m as usize];
            let (nf, nb) = (t & 15, t >> 4);
            if nf != 1 || nb == 0 {
                continue;
            }
            if nb > 1 {
                let sides = group_masks(!m & 0x3fff);
                if !self.sides_stay_connected(i, other, &sides, allowed) {
                    continue;
                }
                handles += u64::from(nb - 1);
            }
            self.cells[i] = value;
            grown.push(i);
            for &o in &self.nb {
                let j = (i as isize + o) as usize;
                if allowed[j] && self.cells[j] != value && !queued[j] {
                    queued[j] = true;
                    queue.push_back(j);
                }
            }
        }
        // Give back the grown voxels that are simple, until none is.
        let mut is_grown = vec![false; self.cells.len()];
        for &i in &grown {
            is_grown[i] = true;
            queued[i] = true;
            queue.push_back(i);
        }
        while let Some(i) = queue.pop_front() {
            queued[i] = false;
            if self.cells[i] != value {
                continue;
            }
            let t = table[self.config(i, value) as usize];
            if t & 15 != 1 || t >> 4 != 1 {
                continue;
            }
            self.cells[i] = other;
            for &o in &self.nb {
                let j = (i as isize + o) as usize;
                if is_grown[j] && self.cells[j] == value && !queued[j] {
                    queued[j] = true;
                    queue.push_back(j);
                }
            }
        }
        if handles == 0 {
            // Nothing to remove: whatever the give-back left over goes too (only grown voxels changed).
            for &i in &grown {
                self.cells[i] = other;
            }
            return 0;
        }
        handles
    }

    /// With `i` given the grown value, do the groups `sides` of its neighbours of value `other` (bit
    /// masks over the 14 neighbours) stay connected to each other through voxels of value `other`?
    /// One breadth-first search per group, run a voxel at a time in turn, until all have met or one
    /// has run out of voxels (it is enclosed).
    ///
    /// Voxels of value `other` outside `allowed` keep their value for the whole repair, so two
    /// groups whose searches reach the same component of them are connected: once the repair's
    /// searches have visited as many voxels as the volume has, the components they reach are
    /// labelled (each once per repair) and groups that reach the same one meet there. The searches
    /// are otherwise unchanged, so the answer is the same; it only comes sooner where the groups
    /// meet far away (around a wall on a fine grid, where each search had walked around it).
    fn sides_stay_connected(&mut self, i: usize, other: u8, sides: &[u16], allowed: &[bool]) -> bool {
        if self.stamp.is_empty() {
            self.stamp = vec![0; self.cells.len()];
            self.group = vec![0; self.cells.len()];
        }
        self.searches = self.searches.wrapping_add(1);
        if self.searches == 0 {
            self.stamp.fill(0);
            self.searches = 1;
        }
        let s = self.searches;
        let n = sides.len();
        let mut parent: Vec<usize> = (0..n).collect();
        fn find(p: &mut [usize], mut x: usize) -> usize {
            while p[x] != x {
                p[x] = p[p[x]];
                x = p[x];
            }
            x
        }
        self.stamp[i] = s;
        self.group[i] = u8::MAX;
        let mut queues: Vec<VecDeque<usize>> = vec![VecDeque::new(); n];
        for (g, &mask) in sides.iter().enumerate() {
            for (b, &o) in self.nb.iter().enumerate() {
                if mask >> b & 1 == 1 {
                    let j = (i as isize + o) as usize;
                    self.stamp[j] = s;
                    self.group[j] = g as u8;
                    queues[g].push_back(j);
                }
            }
        }
        let mut classes = n;
        let last = self.cells.len();
        // The group that first reached each fixed component, once searches are long.
        let mut owners: Vec<(u32, usize)> = Vec::new();
        loop {
            for g in 0..n {
                let Some(j) = queues[g].pop_front() else {
                    // Group g has run out: enclosed unless another group of its class still searches.
                    let root = find(&mut parent, g);
                    if (0..n).all(|h| find(&mut parent, h) != root || queues[h].is_empty()) {
                        return false;
                    }
                    continue;
                };
                for o in self.nb {
                    let k = j as isize + o;
                    if k < 0 || k as usize >= last {
                        continue;
                    }
                    let k = k as usize;
                    if self.cells[k] != other {
                        continue;
                    }
                    if self.stamp[k] == s {
                        let h = self.group[k];
                        if h != u8::MAX {
                            let (a, b) = (find(&mut parent, g), find(&mut parent, h as usize));
                            if a != b {
                                parent[a] = b;
                                classes -= 1;
                                if classes == 1 {
                                    return true;
                                }
                            }
                        }
                        continue;
                    }
                    self.stamp[k] = s;
                    self.group[k] = g as u8;
                    queues[g].push_back(k);
                    self.repair_visits += 1;
                    if self.repair_visits > self.label_after && !allowed[k] {
                        let c = self.component(k, other, allowed);
                        match owners.iter().find(|&&(d, _)| d == c) {
                            Some(&(_, h)) => {
                                let (a, b) = (find(&mut parent, g), find(&mut parent, h));
                                if a != b {
                                    parent[a] = b;
                                    classes -= 1;
                                    if classes == 1 {
                                        return true;
                                    }
                                }
                            }
                            None => owners.push((c, g)),
                        }
                    }
                }
            }
        }
    }

    /// The label of the component, through voxels of value `other` outside `allowed` (14-adjacency),
    /// that holds voxel `k` (one such voxel); the whole component is labelled the first time.
    fn component(&mut self, k: usize, other: u8, allowed: &[bool]) -> u32 {
        if self.label.is_empty() {
            self.label = vec![0; self.cells.len()];
        }
        if self.label[k] >= self.label_base {
            return self.label[k];
        }
        let c = self.next_label;
        self.next_label += 1;
        let last = self.cells.len();
        self.label[k] = c;
        let mut stack = vec![k];
        let nb = self.nb;
        while let Some(j) = stack.pop() {
            for &o in &nb {
                let x = j as isize + o;
                if x < 0 || x as usize >= last {
                    continue;
                }
                let x = x as usize;
                if self.cells[x] == other && !allowed[x] && self.label[x] < self.label_base {
                    self.label[x] = c;
                    stack.push(x);
                }
            }
        }
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, VoxelGrid};
    use crate::pipeline::{extract_surface, MeshParams};

    /// A 32³ grid of 1 mm voxels.
    fn grid() -> VoxelGrid {
        VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.032; 3] }, 32)
    }

    /// Genus of the closed mesh the scan methods make of `occ` (handle removal on), and without it.
    fn genus_with_and_without(occ: &Occupancy) -> (i64, i64) {
        let genus = |remove_handles: bool| {
            let params = MeshParams { remove_handles, ..MeshParams::smoothed(0) };
            let topo = extract_surface(occ, &params).expect("mesh").topology();
            assert_eq!((topo.components, topo.open_or_misoriented_edges), (1, 0), "{topo:?}");
            topo.genus.expect("one closed component")
        };
        (genus(true), genus(false))
    }

    /// The voxels where `a` and `b` differ.
    fn differences(a: &Occupancy, b: &Occupancy) -> Vec<[usize; 3]> {
        let d = a.grid().dims;
        let mut out = Vec::new();
        for k in 0..d[2] {
            for j in 0..d[1] {
                for i in 0..d[0] {
                    if a.get(i, j, k) != b.get(i, j, k) {
                        out.push([i, j, k]);
                    }
                }
            }
        }
        out
    }

    #[test]
    fn the_cube_filter_is_the_max_and_min_over_each_3x3x3_cube() {
        // Scattered patterns on an uneven grid (padding included), against the cube taken voxel by
        // voxel with out-of-volume values 0: a dense one, and sparse and nearly full ones, where
        // the maximum and the minimum of most cubes hang on a single voxel of them.
        let grid = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.011, 0.007, 0.005] }, 11);
        let hash = |p: nalgebra::Vector3<f64>| {
            let c = [p.x, p.y, p.z].map(|x| (x * 9e3) as i64);
            ((c[0] * 73_856_093) ^ (c[1] * 19_349_663) ^ (c[2] * 83_492_791)).rem_euclid(23)
        };
        let patterns = [
            Occupancy::from_fn(grid, |p| {
                ((p.x * 9e3) as i64 * 7 + (p.y * 9e3) as i64 * 3 + (p.z * 9e3) as i64) % 5 < 2
            }),
            Occupancy::from_fn(grid, |p| hash(p) == 0),
            Occupancy::from_fn(grid, |p| hash(p) != 0),
        ];
        for (occ, max) in patterns.iter().flat_map(|o| [(o, true), (o, false)]) {
            let v = Volume::new(occ);
            let d = v.dims;
            assert!(d[0] != d[1] && v.cells.contains(&1) && v.cells.contains(&0), "{d:?}");
            let got = v.cube_filter(&v.cells, max);
            for k in 0..d[2] {
                for j in 0..d[1] {
                    for i in 0..d[0] {
                        let mut want = if max { 0 } else { 1 };
                        for (dk, dj, di) in (0..27).map(|n| (n / 9, n / 3 % 3, n % 3)) {
                            let (x, y, z) = (i + di, j + dj, k + dk);
                            let inside = (1..=d[0]).contains(&x) && (1..=d[1]).contains(&y) && (1..=d[2]).contains(&z);
                            let c = if inside { v.cells[(x - 1) + d[0] * ((y - 1) + d[1] * (z - 1))] } else { 0 };
                            want = if max { want.max(c) } else { want.min(c) };
                        }
                        assert_eq!(got[i + d[0] * (j + d[1] * k)], want, "max {max} at {i} {j} {k}");
                    }
                }
            }
        }
    }

    #[test]
    fn link_of_a_voxel_is_a_sphere_and_simple_voxels_are_recognised() {
        let adj = link_adjacency();
        let edges: u32 = adj.iter().map(|m| m.count_ones()).sum::<u32>() / 2;
        assert_eq!(edges, 36, "14 vertices, 36 edges, 24 triangles: a sphere");
        let table = link_table();
        // One solid neighbour, or all but one: simple. None, or all: not.
        assert_eq!(table[1], 1 | (1 << 4));
        assert_eq!(table[0x3fff ^ 1], 1 | (1 << 4));
        assert_eq!(table[0] & 15, 0);
        assert_eq!(table[0x3fff] >> 4, 0);
        // +x and -x only: two solid groups (the voxel would join two parts).
        assert_eq!(table[0b11] & 15, 2);
    }

    #[test]
    fn a_voxel_scale_tunnel_through_a_thin_wall_is_plugged() {
        for hole in [1usize, 2] {
            // A wall two voxels thick with a hole of hole × hole voxels through it: a torus.
            let in_hole = move |i: usize, j: usize| (15..15 + hole).contains(&i) && (15..15 + hole).contains(&j);
            let occ = Occupancy::from_index_fn(grid(), move |i, j, k| {
                (4..28).contains(&i) && (4..28).contains(&j) && (10..12).contains(&k) && !in_hole(i, j)
            });
            assert_eq!(genus_with_and_without(&occ), (0, 1), "hole {hole}");
            let (repaired, stats) = remove_small_handles(&occ);
            assert_eq!((stats.tunnels_filled, stats.bridges_cut, stats.voxels_removed), (1, 0, 0), "{stats:?}");
            let changed = differences(&occ, &repaired);
            assert_eq!(changed.len() as u64, stats.voxels_added);
            assert!(!changed.is_empty(), "{stats:?}");
            // Only voxels of the hole are filled.
            assert!(changed.iter().all(|c| in_hole(c[0], c[1]) && (10..12).contains(&c[2])), "{changed:?}");
        }
    }

    #[test]
    fn searches_that_meet_in_fixed_components_give_the_same_answers() {
        // Labelling fixed components from the first voxel on and never: the same result, on a large
        // wall with a one-voxel hole (the sides meet around the wall), a hollow box with a one-voxel
        // hole (filling it would enclose the cavity: refused) and a noisy blob with many handles.
        let g64 = VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [0.064; 3] }, 64);
        let wall = Occupancy::from_index_fn(g64, |i, j, k| {
            (2..62).contains(&i) && (2..62).contains(&j) && (30..32).contains(&k) && !(i == 31 && j == 31)
        });
        let hollow = Occupancy::from_index_fn(g64, |i, j, k| {
            let outer = [i, j, k].iter().all(|x| (8..56).contains(x));
            let inner = [i, j, k].iter().all(|x| (10..54).contains(x));
            outer && !inner && !(i == 31 && j == 31 && k < 10)
        });
        let blob = Occupancy::from_index_fn(g64, |i, j, k| {
            let p = [i, j, k].map(|x| x as f64 - 31.5);
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            let noise = ((i * 7919 + j * 104_729 + k * 1_299_709) % 97) as f64 / 97.0;
            r < 24.0 && (r < 20.0 || noise < 0.55) && !(r < 17.0 && noise < 0.9)
        });
        for (name, occ, handles) in [("wall", &wall, Some(1)), ("hollow box", &hollow, Some(0)), ("blob", &blob, None)]
        {
            let (never, a) = remove_small_handles_with(occ, Some(usize::MAX));
            let (always, b) = remove_small_handles_with(occ, Some(0));
            assert_eq!(differences(&never, &always), Vec::<[usize; 3]>::new(), "{name}");
            let counts = |s: HandleRepair| (s.tunnels_filled, s.bridges_cut, s.voxels_added, s.voxels_removed);
            assert_eq!(counts(a), counts(b), "{name}");
            match handles {
                Some(h) => assert_eq!(a.handles_removed(), h, "{name}: {a:?}"),
                None => assert!(a.handles_removed() > 3, "{name}: {a:?}"),
            }
        }
    }

    #[test]
    fn a_thin_bridge_over_a_groove_is_cut() {
        // A block with a groove 8 voxels wide and 4 deep, spanned by a bridge one voxel square.
        let bridge = |i: usize, j: usize, k: usize| (12..20).contains(&i) && j == 15 && k == 13;
        let occ = Occupancy::from_index_fn(grid(), move |i, j, k| {
            let block = (4..28).contains(&i) && (4..28).contains(&j) && (4..14).contains(&k);
            let groove = (12..20).contains(&i) && (10..14).contains(&k);
            (block && !groove) || bridge(i, j, k)
        });
        assert_eq!(genus_with_and_without(&occ), (0, 1));
        let (repaired, stats) = remove_small_handles(&occ);
        assert_eq!((stats.tunnels_filled, stats.bridges_cut, stats.voxels_added), (0, 1, 0), "{stats:?}");
        let changed = differences(&occ, &repaired);
        assert_eq!(changed.len() as u64, stats.voxels_removed);
        assert!((1..=2).contains(&changed.len()), "{changed:?}");
        assert!(changed.iter().all(|c| bridge(c[0], c[1], c[2])), "{changed:?}");
    }

    #[test]
    fn a_real_handle_stays() {
        // A torus: tube radius 3.5 voxels, hole 11 voxels across.
        let occ = Occupancy::from_index_fn(grid(), |i, j, k| {
            let p = [i, j, k].map(|x| x as f64 + 0.5 - 16.0);
            let ring = (p[0].hypot(p[1]) - 9.0).hypot(p[2]);
            ring < 3.5
        });
        assert_eq!(genus_with_and_without(&occ), (1, 1));
        let (repaired, stats) = remove_small_handles(&occ);
        assert_eq!(stats.handles_removed(), 0, "{stats:?}");
        assert_eq!((stats.voxels_added, stats.voxels_removed), (0, 0));
        assert!(repaired.same_voxels(&occ));
    }

    #[test]
    fn empty_and_full_occupancies_pass_through() {
        for occ in [Occupancy::empty(grid()), Occupancy::full(grid())] {
            let (out, stats) = remove_small_handles(&occ);
            assert!(out.same_voxels(&occ));
            assert_eq!(stats.handles_removed() + stats.voxels_added + stats.voxels_removed, 0);
        }
    }
}
