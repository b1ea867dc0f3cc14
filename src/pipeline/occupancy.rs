//! Voxel occupancy stored as 8³ bricks that are Empty, Full or Mixed (a 512-bit mask), grouped in
//! blocks of 4³ bricks (32³ voxels). Memory follows the surface, not the volume: only Mixed bricks
//! carry a bitmask, everything else is four bytes per brick.
//!
//! Voxel indices are those of [`VoxelGrid`]: voxel `(i, j, k)` has its centre at
//! `origin + (idx + 0.5) * voxel_size` (metres, in whatever frame the grid is in, usually the object frame).

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::geometry::VoxelGrid;

/// Edge of a brick, voxels.
pub const BRICK: usize = 8;
/// Edge of a block, bricks.
pub(crate) const BLOCK_BRICKS: usize = 4;
/// Edge of a block, voxels.
pub(crate) const BLOCK: usize = BRICK * BLOCK_BRICKS;
/// Bricks per block.
const BRICKS_PER_BLOCK: usize = BLOCK_BRICKS * BLOCK_BRICKS * BLOCK_BRICKS;

const EMPTY: u32 = 0;
const FULL: u32 = 1;

/// The 512 bits of one brick: word `z`, bit `x + 8 y` is voxel `(x, y, z)` of the brick.
pub type BrickBits = [u64; 8];

/// The state of one brick, as seen through [`Occupancy::brick`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Brick<'a> {
    /// No voxel occupied.
    Empty,
    /// Every voxel of the brick that lies inside the grid is occupied.
    Full,
    /// Some voxels occupied; the bits follow [`BrickBits`].
    Mixed(&'a BrickBits),
}

/// 4³ bricks with a pool of bitmasks for the Mixed ones. The pool and its free list are kept when
/// bricks change state, so a carver that is reset reuses them.
#[derive(Debug, Clone)]
pub(crate) struct Block {
    /// `EMPTY`, `FULL`, or `2 + slot` for a Mixed brick whose bits are `pool[slot]`.
    pub(crate) states: [u32; BRICKS_PER_BLOCK],
    pool: Vec<BrickBits>,
    free: Vec<u32>,
}

impl Block {
    fn new(state: u32) -> Block {
        Block { states: [state; BRICKS_PER_BLOCK], pool: Vec::new(), free: Vec::new() }
    }

    /// True when no brick of the block holds a voxel.
    #[inline]
    pub(crate) fn all_empty(&self) -> bool {
        self.states.iter().all(|&s| s == EMPTY)
    }

    /// The bits of local brick `b` (Full bricks give `valid`).
    #[inline]
    pub(crate) fn bits(&self, b: usize, valid: &BrickBits) -> BrickBits {
        match self.states[b] {
            EMPTY => [0; 8],
            FULL => *valid,
            s => self.pool[(s - 2) as usize],
        }
    }

    #[inline]
    pub(crate) fn is_empty_brick(&self, b: usize) -> bool {
        self.states[b] == EMPTY
    }

    fn release(&mut self, b: usize) {
        let s = self.states[b];
        if s >= 2 {
            self.free.push(s - 2);
        }
    }

    /// Store `bits` for local brick `b`, normalising to Empty / Full.
    pub(crate) fn set_bits(&mut self, b: usize, bits: &BrickBits, valid: &BrickBits) {
        if bits.iter().all(|&w| w == 0) {
            self.release(b);
            self.states[b] = EMPTY;
        } else if bits == valid {
            self.release(b);
            self.states[b] = FULL;
        } else {
            let s = self.states[b];
            if s >= 2 {
                self.pool[(s - 2) as usize] = *bits;
            } else {
                let slot = match self.free.pop() {
                    Some(slot) => {
                        self.pool[slot as usize] = *bits;
                        slot
                    }
                    None => {
                        self.pool.push(*bits);
                        (self.pool.len() - 1) as u32
                    }
                };
                self.states[b] = slot + 2;
            }
        }
    }

    /// Mark local brick `b` empty.
    #[inline]
    pub(crate) fn clear_brick(&mut self, b: usize) {
        self.release(b);
        self.states[b] = EMPTY;
    }

    fn reset(&mut self, state: u32) {
        self.states = [state; BRICKS_PER_BLOCK];
        self.pool.clear();
        self.free.clear();
    }
}

/// Occupancy of a [`VoxelGrid`], brick-compressed (see the module docs).
#[derive(Debug, Clone)]
pub struct Occupancy {
    grid: VoxelGrid,
    /// Blocks along x, y, z.
    block_dims: [usize; 3],
    blocks: Vec<Block>,
}

/// Overlap of a result with a ground truth on the same grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Overlap {
    /// |result ∩ truth| / |result ∪ truth| (1 when both are empty).
    pub iou: f64,
    /// Fraction of the truth's voxels that the result contains (1 when the truth is empty).
    pub containment: f64,
    /// Voxels in both.
    pub intersection: u64,
    /// Voxels in either.
    pub union: u64,
}

/// The two grids differ, so voxel-wise comparison is meaningless.
#[derive(Debug, thiserror::Error)]
#[error("the occupancies are on different grids ({a:?} and {b:?})")]
pub struct GridMismatch {
    /// First grid.
    pub a: VoxelGrid,
    /// Second grid.
    pub b: VoxelGrid,
}

impl Occupancy {
    fn with_state(grid: VoxelGrid, state: u32) -> Occupancy {
        let block_dims = grid.dims.map(|d| d.div_ceil(BLOCK));
        let mut occ = Occupancy {
            grid,
            block_dims,
            blocks: vec![Block::new(state); block_dims[0] * block_dims[1] * block_dims[2]],
        };
        occ.clear_outside_bricks();
        occ
    }

    /// Bricks of border blocks that lie wholly outside the grid are always Empty.
    fn clear_outside_bricks(&mut self) {
        let bd = self.grid.dims.map(|d| d.div_ceil(BRICK));
        let block_dims = self.block_dims;
        for (bi, block) in self.blocks.iter_mut().enumerate() {
            let bc = block_coords(bi, &block_dims);
            for (lb, state) in block.states.iter_mut().enumerate() {
                let l = local_brick_coords(lb);
                if (0..3).any(|a| bc[a] * BLOCK_BRICKS + l[a] >= bd[a]) {
                    *state = EMPTY;
                }
            }
        }
    }

    /// Every voxel of `grid` occupied (the start of carving).
    pub fn full(grid: VoxelGrid) -> Occupancy {
        Occupancy::with_state(grid, FULL)
    }

    /// No voxel occupied.
    pub fn empty(grid: VoxelGrid) -> Occupancy {
        Occupancy::with_state(grid, EMPTY)
    }

    /// Set every voxel occupied again, keeping the allocated buffers.
    pub fn fill(&mut self) {
        for b in &mut self.blocks {
            b.reset(FULL);
        }
        self.clear_outside_bricks();
    }

    /// Occupancy from a predicate on voxel centres (metres, the grid's frame), evaluated in parallel;
    /// e.g. the ground truth of a synthetic scene.
    pub fn from_fn<F>(grid: VoxelGrid, f: F) -> Occupancy
    where
        F: Fn(Vector3<f64>) -> bool + Sync,
    {
        Occupancy::from_index_fn(grid, |i, j, k| f(grid.centre(i, j, k)))
    }

    /// Occupancy from a predicate on voxel indices `(i, j, k)`, evaluated in parallel.
    pub fn from_index_fn<F>(grid: VoxelGrid, f: F) -> Occupancy
    where
        F: Fn(usize, usize, usize) -> bool + Sync,
    {
        let mut occ = Occupancy::empty(grid);
        let block_dims = occ.block_dims;
        let dims = grid.dims;
        occ.blocks.par_iter_mut().enumerate().for_each(|(bi, block)| {
            let bc = block_coords(bi, &block_dims);
            for lb in 0..BRICKS_PER_BLOCK {
                let o = brick_origin(&bc, lb);
                if (0..3).any(|a| o[a] >= dims[a]) {
                    continue;
                }
                let valid = valid_bits(&o, &dims);
                let mut bits = [0u64; 8];
                for (z, word) in bits.iter_mut().enumerate() {
                    for y in 0..BRICK {
                        for x in 0..BRICK {
                            let bit = 1u64 << (x + 8 * y);
                            if valid[z] & bit != 0 && f(o[0] + x, o[1] + y, o[2] + z) {
                                *word |= bit;
                            }
                        }
                    }
                }
                block.set_bits(lb, &bits, &valid);
            }
        });
        occ
    }

    /// The grid.
    pub fn grid(&self) -> &VoxelGrid {
        &self.grid
    }

    pub(crate) fn block_dims(&self) -> [usize; 3] {
        self.block_dims
    }

    pub(crate) fn blocks_mut(&mut self) -> &mut [Block] {
        &mut self.blocks
    }

    /// Bricks along x, y, z.
    pub fn brick_dims(&self) -> [usize; 3] {
        self.grid.dims.map(|d| d.div_ceil(BRICK))
    }

    /// Brick `(bx, by, bz)` (brick coordinates, each voxel index divided by 8). Out of range -> Empty.
    pub fn brick(&self, bx: usize, by: usize, bz: usize) -> Brick<'_> {
        let bd = self.brick_dims();
        if bx >= bd[0] || by >= bd[1] || bz >= bd[2] {
            return Brick::Empty;
        }
        let (bi, lb) = self.locate_brick([bx, by, bz]);
        let block = &self.blocks[bi];
        match block.states[lb] {
            EMPTY => Brick::Empty,
            FULL => Brick::Full,
            s => Brick::Mixed(&block.pool[(s - 2) as usize]),
        }
    }

    /// The bits of brick `b` (brick coordinates), with Full expanded and out-of-grid voxels zero.
    pub fn brick_bits(&self, b: [usize; 3]) -> BrickBits {
        match self.brick(b[0], b[1], b[2]) {
            Brick::Empty => [0; 8],
            Brick::Full => valid_bits(&b.map(|x| x * BRICK), &self.grid.dims),
            Brick::Mixed(bits) => *bits,
        }
    }

    fn locate_brick(&self, b: [usize; 3]) -> (usize, usize) {
        let bc = b.map(|x| x / BLOCK_BRICKS);
        let l = b.map(|x| x % BLOCK_BRICKS);
        let bi = bc[0] + self.block_dims[0] * (bc[1] + self.block_dims[1] * bc[2]);
        (bi, l[0] + BLOCK_BRICKS * (l[1] + BLOCK_BRICKS * l[2]))
    }

    /// Is voxel `(i, j, k)` occupied? Out-of-grid indices are not.
    pub fn get(&self, i: usize, j: usize, k: usize) -> bool {
        let d = self.grid.dims;
        if i >= d[0] || j >= d[1] || k >= d[2] {
            return false;
        }
        match self.brick(i / BRICK, j / BRICK, k / BRICK) {
            Brick::Empty => false,
            Brick::Full => true,
            Brick::Mixed(bits) => bits[k % BRICK] >> ((i % BRICK) + 8 * (j % BRICK)) & 1 == 1,
        }
    }

    /// Like [`Occupancy::get`] with signed indices (negative -> not occupied).
    pub fn get_signed(&self, i: i64, j: i64, k: i64) -> bool {
        i >= 0 && j >= 0 && k >= 0 && self.get(i as usize, j as usize, k as usize)
    }

    /// Number of occupied voxels.
    pub fn count(&self) -> u64 {
        let bd = self.brick_dims();
        let mut n = 0u64;
        for bz in 0..bd[2] {
            for by in 0..bd[1] {
                for bx in 0..bd[0] {
                    n += self.brick_bits([bx, by, bz]).iter().map(|w| w.count_ones() as u64).sum::<u64>();
                }
            }
        }
        n
    }

    /// Occupied volume, m³.
    pub fn volume_m3(&self) -> f64 {
        self.count() as f64 * self.grid.voxel_size.powi(3)
    }

    /// (empty, full, mixed) brick counts.
    pub fn brick_census(&self) -> (usize, usize, usize) {
        let bd = self.brick_dims();
        let (mut e, mut f, mut m) = (0, 0, 0);
        for bz in 0..bd[2] {
            for by in 0..bd[1] {
                for bx in 0..bd[0] {
                    match self.brick(bx, by, bz) {
                        Brick::Empty => e += 1,
                        Brick::Full => f += 1,
                        Brick::Mixed(_) => m += 1,
                    }
                }
            }
        }
        (e, f, m)
    }

    /// Bytes held by the occupancy (states and bitmask pools, capacities included).
    pub fn memory_bytes(&self) -> usize {
        self.blocks
            .iter()
            .map(|b| {
                std::mem::size_of::<Block>()
                    + b.pool.capacity() * std::mem::size_of::<BrickBits>()
                    + b.free.capacity() * 4
            })
            .sum()
    }

    /// Call `f(i, j, k)` for every occupied voxel, brick by brick (no particular global order).
    pub fn for_each_occupied(&self, mut f: impl FnMut(usize, usize, usize)) {
        let bd = self.brick_dims();
        for bz in 0..bd[2] {
            for by in 0..bd[1] {
                for bx in 0..bd[0] {
                    let bits = self.brick_bits([bx, by, bz]);
                    for (z, &w) in bits.iter().enumerate() {
                        let mut w = w;
                        while w != 0 {
                            let b = w.trailing_zeros() as usize;
                            w &= w - 1;
                            f(bx * BRICK + (b & 7), by * BRICK + (b >> 3), bz * BRICK + z);
                        }
                    }
                }
            }
        }
    }

    /// Indices of the occupied voxels that have at least one empty (or out-of-grid) face neighbour,
    /// in [`Occupancy::for_each_occupied`]'s order. Bricks are looked at side by side; an empty one,
    /// and a full one whose six face neighbours are full bricks of the grid, hold none.
    pub fn boundary_voxels(&self) -> Vec<[u32; 3]> {
        let bd = self.brick_dims();
        // `brick` is empty beyond the grid's far side; the near side is checked here.
        let full = |c: [usize; 3]| self.brick(c[0], c[1], c[2]) == Brick::Full;
        let enclosed = |c: [usize; 3]| {
            (0..3).all(|a| {
                let (mut lo, mut hi) = (c, c);
                hi[a] += 1;
                lo[a] = lo[a].wrapping_sub(1);
                c[a] > 0 && full(lo) && full(hi)
            })
        };
        let per_brick: Vec<Vec<[u32; 3]>> = (0..bd[0] * bd[1] * bd[2])
            .into_par_iter()
            .map(|b| {
                let c = [b % bd[0], b / bd[0] % bd[1], b / (bd[0] * bd[1])];
                match self.brick(c[0], c[1], c[2]) {
                    Brick::Empty => return Vec::new(),
                    Brick::Full if enclosed(c) => return Vec::new(),
                    _ => {}
                }
                let mut out = Vec::new();
                for (z, &w) in self.brick_bits(c).iter().enumerate() {
                    let mut w = w;
                    while w != 0 {
                        let bit = w.trailing_zeros() as usize;
                        w &= w - 1;
                        let v = [c[0] * BRICK + (bit & 7), c[1] * BRICK + (bit >> 3), c[2] * BRICK + z];
                        let (a, b, k) = (v[0] as i64, v[1] as i64, v[2] as i64);
                        let interior = self.get_signed(a - 1, b, k)
                            && self.get_signed(a + 1, b, k)
                            && self.get_signed(a, b - 1, k)
                            && self.get_signed(a, b + 1, k)
                            && self.get_signed(a, b, k - 1)
                            && self.get_signed(a, b, k + 1);
                        if !interior {
                            out.push(v.map(|x| x as u32));
                        }
                    }
                }
                out
            })
            .collect();
        per_brick.concat()
    }

    /// True when both occupancies are on the same grid and hold exactly the same voxels.
    pub fn same_voxels(&self, other: &Occupancy) -> bool {
        self.grid == other.grid && self.first_difference(other).is_none()
    }

    /// The first voxel (brick by brick) where the two differ; grids must be equal.
    pub fn first_difference(&self, other: &Occupancy) -> Option<[usize; 3]> {
        let bd = self.brick_dims();
        for bz in 0..bd[2] {
            for by in 0..bd[1] {
                for bx in 0..bd[0] {
                    let (a, b) = (self.brick_bits([bx, by, bz]), other.brick_bits([bx, by, bz]));
                    for z in 0..8 {
                        let d = a[z] ^ b[z];
                        if d != 0 {
                            let t = d.trailing_zeros() as usize;
                            return Some([bx * BRICK + (t & 7), by * BRICK + (t >> 3), bz * BRICK + z]);
                        }
                    }
                }
            }
        }
        None
    }

    /// Volumetric IoU of `self` (the result) against `truth`, and the fraction of truth voxels that
    /// the result contains.
    pub fn iou_and_containment(&self, truth: &Occupancy) -> Result<Overlap, GridMismatch> {
        if self.grid != truth.grid {
            return Err(GridMismatch { a: self.grid, b: truth.grid });
        }
        let bd = self.brick_dims();
        let (mut inter, mut uni, mut t) = (0u64, 0u64, 0u64);
        for bz in 0..bd[2] {
            for by in 0..bd[1] {
                for bx in 0..bd[0] {
                    let (a, b) = (self.brick_bits([bx, by, bz]), truth.brick_bits([bx, by, bz]));
                    for z in 0..8 {
                        inter += (a[z] & b[z]).count_ones() as u64;
                        uni += (a[z] | b[z]).count_ones() as u64;
                        t += b[z].count_ones() as u64;
                    }
                }
            }
        }
        Ok(Overlap {
            iou: if uni == 0 { 1.0 } else { inter as f64 / uni as f64 },
            containment: if t == 0 { 1.0 } else { inter as f64 / t as f64 },
            intersection: inter,
            union: uni,
        })
    }
}

/// Block coordinates of linear block index `bi`.
#[inline]
pub(crate) fn block_coords(bi: usize, block_dims: &[usize; 3]) -> [usize; 3] {
    [bi % block_dims[0], (bi / block_dims[0]) % block_dims[1], bi / (block_dims[0] * block_dims[1])]
}

/// Coordinates (bricks) of local brick `lb` within its block.
#[inline]
pub(crate) fn local_brick_coords(lb: usize) -> [usize; 3] {
    [lb % BLOCK_BRICKS, (lb / BLOCK_BRICKS) % BLOCK_BRICKS, lb / (BLOCK_BRICKS * BLOCK_BRICKS)]
}

/// Voxel origin of local brick `lb` of block `bc`.
#[inline]
pub(crate) fn brick_origin(bc: &[usize; 3], lb: usize) -> [usize; 3] {
    let l = local_brick_coords(lb);
    [0, 1, 2].map(|a| bc[a] * BLOCK + l[a] * BRICK)
}

/// Bits of the voxels of the brick at voxel origin `o` that lie inside a grid of `dims`.
pub(crate) fn valid_bits(o: &[usize; 3], dims: &[usize; 3]) -> BrickBits {
    let n = [0, 1, 2].map(|a| dims[a].saturating_sub(o[a]).min(BRICK));
    let row: u64 = if n[0] >= 8 { 0xff } else { (1u64 << n[0]) - 1 };
    let mut slice = 0u64;
    for y in 0..n[1] {
        slice |= row << (8 * y);
    }
    let mut bits = [0u64; 8];
    for w in bits.iter_mut().take(n[2]) {
        *w = slice;
    }
    bits
}

/// Bits of the sub-cube `[x0, x0+n) x [y0, y0+n) x [z0, z0+n)` of a brick (local voxel coordinates).
pub(crate) fn sub_cube_bits(x0: usize, y0: usize, z0: usize, n: usize) -> BrickBits {
    let row: u64 = if n >= 8 { 0xff } else { ((1u64 << n) - 1) << x0 };
    let mut slice = 0u64;
    for y in y0..y0 + n {
        slice |= row << (8 * y);
    }
    let mut bits = [0u64; 8];
    for w in bits.iter_mut().skip(z0).take(n) {
        *w = slice;
    }
    bits
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Aabb;

    fn grid(n: u32) -> VoxelGrid {
        VoxelGrid::from_resolution(&Aabb { min: [0.0; 3], max: [1.0, 0.7, 0.45] }, n)
    }

    /// The boundary voxels are those with an empty or out-of-grid face neighbour, in
    /// `for_each_occupied` order, whether their bricks are full, mixed or at the grid's edge.
    #[test]
    fn boundary_voxels_are_the_occupied_ones_beside_air_in_visiting_order() {
        let g = grid(37);
        // A slab through the grid's height (full bricks with full bricks on every side, and full
        // bricks at the grid's edge), a cylinder and scattered voxels.
        let occ = Occupancy::from_index_fn(g, |i, j, k| {
            (i < 30 && j < 24) || (i + 2 * j + 3 * k) % 11 == 0 || (i as f64 - 20.0).hypot(j as f64 - 10.0) < 3.0
        });
        let mut expected = Vec::new();
        occ.for_each_occupied(|i, j, k| {
            let (a, b, c) = (i as i64, j as i64, k as i64);
            let near = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
                .iter()
                .any(|&(x, y, z)| !occ.get_signed(a - x, b - y, c - z) || !occ.get_signed(a + x, b + y, c + z));
            if near {
                expected.push([i as u32, j as u32, k as u32]);
            }
        });
        let enclosed = |c: [usize; 3]| {
            let full = |d: [i64; 3]| {
                let n = [0, 1, 2].map(|a| c[a] as i64 + d[a]);
                n.iter().all(|&x| x >= 0) && occ.brick(n[0] as usize, n[1] as usize, n[2] as usize) == Brick::Full
            };
            full([0, 0, 0]) && [[1, 0, 0], [0, 1, 0], [0, 0, 1]].iter().all(|d| full(*d) && full(d.map(|x: i64| -x)))
        };
        assert!(enclosed([1, 1, 1]), "a full brick among full bricks");
        assert_eq!(occ.boundary_voxels(), expected);
    }

    #[test]
    fn from_fn_matches_the_predicate_and_counts() {
        let g = grid(37);
        let occ = Occupancy::from_fn(g, |p| (p - Vector3::new(0.5, 0.35, 0.2)).norm() < 0.2);
        let mut n = 0;
        for k in 0..g.dims[2] {
            for j in 0..g.dims[1] {
                for i in 0..g.dims[0] {
                    let inside = (g.centre(i, j, k) - Vector3::new(0.5, 0.35, 0.2)).norm() < 0.2;
                    assert_eq!(occ.get(i, j, k), inside, "{i} {j} {k}");
                    n += inside as u64;
                }
            }
        }
        assert!(n > 0);
        assert_eq!(occ.count(), n);
        assert!(!occ.get(g.dims[0], 0, 0));
    }

    #[test]
    fn full_grid_counts_every_voxel_and_normalises_bricks() {
        let g = grid(21);
        let full = Occupancy::full(g);
        assert_eq!(full.count() as usize, g.len());
        let same = Occupancy::from_fn(g, |_| true);
        assert!(same.same_voxels(&full));
        let (_, _, mixed) = same.brick_census();
        assert_eq!(mixed, 0, "a brick with all its in-grid voxels set must be Full");
        let o = full.iou_and_containment(&Occupancy::empty(g)).expect("same grid");
        assert_eq!(o.iou, 0.0);
        assert_eq!(o.containment, 1.0);
    }

    #[test]
    fn iou_and_containment_of_nested_sets() {
        let g = grid(30);
        let big = Occupancy::from_fn(g, |p| p.x < 0.6);
        let small = Occupancy::from_fn(g, |p| p.x < 0.3);
        let o = big.iou_and_containment(&small).expect("same grid");
        assert_eq!(o.containment, 1.0);
        assert!((o.iou - small.count() as f64 / big.count() as f64).abs() < 1e-12);
        let o = small.iou_and_containment(&big).expect("same grid");
        assert!(o.containment < 0.6);
        assert_eq!(big.first_difference(&big.clone()), None);
        assert!(big.first_difference(&small).is_some());
    }
}
