//! The coded cells of the substream being coded or decoded ([`CellMap`]), in 4×4×4-cell bricks
//! found through a per-region directory (or a hash map for huge regions), and the contexts the
//! encoder and the decoder both read from them: a coefficient's sign and value contexts and a
//! leaf node's mask table.

use super::bit_length_class;
use rustc_hash::FxHashMap;
use std::cell::RefCell;

thread_local! {
    /// A decoding or encoding thread's brick directory, kept between packets so that a packet
    /// does not allocate and clear it for every region.
    static BRICK_SCRATCH: RefCell<Vec<u32>> = const { RefCell::new(Vec::new()) };
}

/// Largest number of 4×4×4-cell bricks a region may have for the brick directory; larger
/// regions use a hash map.
const DIRECTORY_MAX_BRICKS: usize = 1 << 22;

/// The coefficients of the substream being coded, by tile-local cell: 0 = none, otherwise
/// 1 | negative << 1 | class << 2.
///
/// Held as 4×4×4-cell bricks of 64 bytes (one cache line), allocated as coded cells reach
/// them, found through a directory with one entry per brick of the region (0 = the shared
/// empty brick). Octree order codes a brick's cells together and a cell's lower neighbours
/// outside its brick in bricks coded just before, so the bricks in use are few and adjacent in
/// memory, whatever the region's size; a plain byte per cell of a 64³ region is 16 times
/// larger and made decoding 20 % slower. Regions of more than [`DIRECTORY_MAX_BRICKS`] use a
/// hash map.
pub(super) struct CellMap {
    /// Brick slot in `bricks` per brick of the region (0: none coded).
    directory: Vec<u32>,
    /// Slot 0 is the empty brick; the rest are allocated in coding order.
    bricks: Vec<u8>,
    /// Directory entries to clear at the next reset.
    used: Vec<u32>,
    sparse: FxHashMap<[u32; 3], u8>,
    use_directory: bool,
    /// Directory strides of y and z.
    stride: [usize; 2],
}

/// A node of 2×2×2 cells in a directory map, ready to give its children's contexts
/// ([`CellMap::leaf_node`]): the same as [`CellMap::leaf_contexts`] gives, read from a copy of
/// the node's cells and of the cells just below its lower faces made once a node, which its
/// children's entries join as they are decoded ([`LeafNode::set`]).
pub(super) struct LeafNode {
    /// Index in the bricks of the node's origin cell.
    own: usize,
    /// The node's 2×2×2 cells and the 3×4 below its lower faces, cell (x, y, z) of the 3×3×3
    /// block at x + 3y + 9z, the node's own cells at 1 and 2 along every axis (a child's lower
    /// neighbour along an axis is then at a constant offset, 1, 3 or 9, below it: no case for
    /// whether it lies in the node). 32 bytes, so that masked indices need no bounds check.
    block: [u8; 32],
}

/// Where child `i` (`child_origin` order) of a node of 2×2×2 cells lies in
/// [`LeafNode::block`].
#[inline(always)]
fn block_of_child(i: u32) -> usize {
    // (1 + x) + 3 (1 + y) + 9 (1 + z) for the child's bits x, y, z.
    const BLOCK: [u8; 8] = [13, 14, 16, 17, 22, 23, 25, 26];
    BLOCK[(i & 7) as usize] as usize
}

/// Where child `i` of a node of 2×2×2 cells lies in its 4×4×4-cell brick, from the node's
/// origin cell.
#[inline(always)]
fn brick_offset_of_child(i: u32) -> usize {
    // x + 4y + 16z for the child's bits x, y, z.
    const OFFSET: [u8; 8] = [0, 1, 4, 5, 16, 17, 20, 21];
    OFFSET[(i & 7) as usize] as usize
}

impl LeafNode {
    /// [`CellMap::face_table`] of the node: its lower faces' cells, counted in the block.
    #[inline(always)]
    pub(super) fn face_table(&self) -> usize {
        // x = 0: (0, 1..2, 1..2); y = 0: (1..2, 0, 1..2); z = 0: (1..2, 1..2, 0).
        const FACES: [usize; 12] = [12, 15, 21, 24, 10, 11, 19, 20, 4, 5, 7, 8];
        let n = FACES
            .iter()
            .map(|&k| (self.block[k] != 0) as u32)
            .sum::<u32>();
        face_state_of_count(n)
    }

    /// The (sign, value) contexts of child `i` (`child_origin` order) and its index in the
    /// bricks, read from its siblings before it and the cells below the node.
    #[inline(always)]
    pub(super) fn contexts(&self, i: u32) -> (usize, usize, usize) {
        let b = block_of_child(i);
        let (sc, vc) = contexts_of_neighbours(
            self.block[(b - 1) & 31],
            self.block[(b - 3) & 31],
            self.block[(b - 9) & 31],
        );
        (sc, vc, self.own + brick_offset_of_child(i))
    }

    /// Enters child `i`'s map entry `v` ([`cell_entry`]) in the block, for its later siblings.
    #[inline(always)]
    pub(super) fn set(&mut self, i: u32, v: u8) {
        self.block[block_of_child(i) & 31] = v;
    }
}

/// A cell's map entry: 1 | negative << 1 | class << 2, below 128 (the class is at most 31).
#[inline(always)]
pub(super) fn cell_entry(negative: bool, q: u64) -> u8 {
    1 | (negative as u8) << 1 | bit_length_class(q) << 2
}

/// One lower neighbour's part of its cell's contexts, by its map entry, for the neighbour
/// along x, y and z: its sign (0 none, 1 positive, 2 negative) times 1, 3 or 9 in bits 0–4,
/// whether it is coded in bits 5–6, its magnitude class in bits 7 on. The three parts of a
/// cell add up to its sign context, its coded neighbours' count and their classes' sum
/// without a carry from one field into the next (26, 3 and 93 at most).
static NEIGHBOUR_TERMS: [[u32; 128]; 3] = {
    let mut t = [[0u32; 128]; 3];
    let weights = [1, 3, 9];
    let mut a = 0;
    while a < 3 {
        let mut v = 1;
        while v < 128 {
            let sign = (v & 1) + ((v >> 1) & 1);
            t[a][v] = (weights[a] * sign + (1 << 5) + ((v >> 2) << 7)) as u32;
            v += 1;
        }
        a += 1;
    }
    t
};

/// [`super::VALUE_TABLE_OF`] by the count and class sum fields of summed [`NEIGHBOUR_TERMS`]
/// (`sum >> 5`: count + 4 × classes).
static VALUE_TABLE_OF_TERMS: [u8; 512] = {
    let mut t = [0u8; 512];
    let mut k = 0;
    while k < 512 {
        let (n, classes) = (k & 3, k >> 2);
        if classes <= super::MAX_CLASS_SUM {
            t[k] = super::VALUE_TABLE_OF[n][classes];
        }
        k += 1;
    }
    t
};

/// The (sign, value) contexts of a cell from its three lower neighbours' entries: their signs
/// (base 3) and the value table of their count and summed magnitude classes. By table: the
/// signs and counts are as unpredictable as the data, and three lookups and two additions
/// replace the fields' arithmetic.
#[inline(always)]
fn contexts_of_neighbours(vx: u8, vy: u8, vz: u8) -> (usize, usize) {
    let sum = NEIGHBOUR_TERMS[0][(vx & 127) as usize]
        + NEIGHBOUR_TERMS[1][(vy & 127) as usize]
        + NEIGHBOUR_TERMS[2][(vz & 127) as usize];
    (
        (sum & 31) as usize,
        VALUE_TABLE_OF_TERMS[(sum >> 5) as usize & 511] as usize,
    )
}

/// Offset of a cell in its brick.
#[inline(always)]
fn brick_offset(c: [u32; 3]) -> usize {
    (c[0] & 3 | (c[1] & 3) << 2 | (c[2] & 3) << 4) as usize
}

impl CellMap {
    pub(super) fn new() -> CellMap {
        CellMap {
            directory: BRICK_SCRATCH.with(|s| std::mem::take(&mut *s.borrow_mut())),
            bricks: vec![0; 64],
            used: Vec::new(),
            sparse: FxHashMap::default(),
            use_directory: true,
            stride: [0; 2],
        }
    }

    /// Empties the map for a region of `extent` cells.
    pub(super) fn reset(&mut self, extent: [u32; 3]) {
        self.clear_directory();
        self.bricks.truncate(64);
        self.sparse.clear();
        let bricks = extent.map(|e| e.div_ceil(4) as usize);
        let count = bricks.iter().product::<usize>();
        self.use_directory = count <= DIRECTORY_MAX_BRICKS;
        if self.use_directory && self.directory.len() < count {
            self.directory.resize(count, 0);
        }
        self.stride = [bricks[0], bricks[0] * bricks[1]];
    }

    /// Zeroes the directory entries in use, so that the directory is all empty again.
    fn clear_directory(&mut self) {
        for &i in &self.used {
            self.directory[i as usize] = 0;
        }
        self.used.clear();
    }

    /// Directory index of the brick holding `c`.
    #[inline(always)]
    fn brick(&self, c: [u32; 3]) -> usize {
        (c[0] >> 2) as usize
            + (c[1] >> 2) as usize * self.stride[0]
            + (c[2] >> 2) as usize * self.stride[1]
    }

    #[inline(always)]
    fn get(&self, c: [u32; 3]) -> u8 {
        if self.use_directory {
            self.cells_of(self.brick(c))[brick_offset(c)]
        } else {
            self.sparse.get(&c).copied().unwrap_or(0)
        }
    }

    /// Enters cell `c`'s coefficient (its sign and step).
    pub(super) fn insert(&mut self, c: [u32; 3], negative: bool, q: u64) {
        let v = cell_entry(negative, q);
        if self.use_directory {
            let slot = self.allocate(self.brick(c));
            self.bricks[64 * slot + brick_offset(c)] = v;
        } else {
            self.sparse.insert(c, v);
        }
    }

    /// Enters entry `v` ([`cell_entry`]) at index `index` of the bricks, a child's of a
    /// [`CellMap::leaf_node`] (whose brick that allocated).
    #[inline(always)]
    pub(super) fn set_at(&mut self, index: usize, v: u8) {
        self.bricks[index] = v;
    }

    /// The cells of the brick at directory index `b` (the empty brick if none is coded).
    #[inline(always)]
    fn cells_of(&self, b: usize) -> &[u8] {
        let slot = self.directory[b] as usize;
        &self.bricks[64 * slot..64 * slot + 64]
    }

    /// The (sign, value) contexts of a cell: its three lower neighbours' signs (base 3) and the
    /// value table of their count and summed magnitude classes. The coders walk a directory
    /// map's nodes of 2×2×2 cells as [`CellMap::leaf_node`]s; this looks a cell up alone (a
    /// hashed map's cells, the tests).
    #[inline(always)]
    pub(super) fn leaf_contexts(&self, c: [u32; 3]) -> (usize, usize) {
        if self.use_directory {
            // As a child of its node of 2×2×2 cells.
            let i = c[0] & 1 | (c[1] & 1) << 1 | (c[2] & 1) << 2;
            let (sc, vc, _) = self.find_leaf(c.map(|v| v & !1), true).contexts(i);
            return (sc, vc);
        }
        let (x, y, z) = (c[0], c[1], c[2]);
        let get = |dx: u32, dy: u32, dz: u32| {
            if x < dx || y < dy || z < dz {
                0
            } else {
                self.get([x - dx, y - dy, z - dz])
            }
        };
        contexts_of_neighbours(get(1, 0, 0), get(0, 1, 0), get(0, 0, 1))
    }

    /// The node of 2×2×2 cells at `o` (even coordinates) made ready for its children's
    /// [`LeafNode::contexts`] as they are inserted: its brick allocated (so that the node's
    /// indices stay those of its cells) and its lower neighbours outside it found once for all
    /// its children. `None` for a hashed map (use [`CellMap::leaf_contexts`]).
    #[inline(always)]
    pub(super) fn leaf_node(&mut self, o: [u32; 3]) -> Option<LeafNode> {
        if !self.use_directory {
            return None;
        }
        self.allocate(self.brick(o));
        // A node is walked once: none of its cells is coded yet.
        Some(self.find_leaf(o, false))
    }

    /// The node of 2×2×2 cells at `o` (even coordinates) in a directory map, as it is now: a
    /// brick not yet allocated reads as the empty brick, so nothing may be inserted into it
    /// while this node is in use ([`CellMap::leaf_node`] allocates first). `with_own`: whether
    /// to read the node's own cells too (a cell's contexts looked up alone,
    /// [`CellMap::leaf_contexts`], need its siblings coded before it; a node being walked has
    /// none).
    #[inline(always)]
    fn find_leaf(&self, o: [u32; 3], with_own: bool) -> LeafNode {
        let b = self.brick(o);
        let offset = brick_offset(o);
        let own = 64 * self.directory[b] as usize + offset;
        // The cell below the node's origin cell along each axis: in the node's brick, in the
        // brick below, or (at the region's lower face) in the empty brick (slot 0). Whether
        // the node lies on its brick's lower face is even or odd with the data, so the choice
        // is made by a mask over both candidates, not by a branch (which mispredicted on half
        // the nodes: a fifth of the fast decoder's mispredictions). The brick below is read
        // from the directory either way (the node's own brick where there is none below); the
        // inside candidate wraps where it is discarded.
        let outside = |v: u32, step: usize, width: usize| -> usize {
            let below = b.wrapping_sub(step * usize::from(v >= 4));
            let at_face = if v > 0 {
                64 * self.directory[below] as usize + offset + 3 * width
            } else {
                offset
            };
            let on_face = usize::from(v & 3 == 0).wrapping_neg();
            (own.wrapping_sub(width) & !on_face) | (at_face & on_face)
        };
        let [x, y, z] = [
            outside(o[0], 1, 1),
            outside(o[1], self.stride[0], 4),
            outside(o[2], self.stride[1], 16),
        ];
        let cells = &self.bricks;
        let mut block = [0u8; 32];
        // Below the face x = 0: (0, y, z) for y, z in 1..=2; below y = 0 and z = 0 alike.
        for (k, d) in [(12, 0), (15, 4), (21, 16), (24, 20)] {
            block[k] = cells[x + d];
        }
        for (k, d) in [(10, 0), (11, 1), (19, 16), (20, 17)] {
            block[k] = cells[y + d];
        }
        for (k, d) in [(4, 0), (5, 1), (7, 4), (8, 5)] {
            block[k] = cells[z + d];
        }
        if with_own {
            for i in 0..8 {
                block[block_of_child(i)] = cells[own + brick_offset_of_child(i)];
            }
        }
        LeafNode { own, block }
    }

    /// The slot of brick `b`, allocated if none is coded yet.
    #[inline(always)]
    fn allocate(&mut self, b: usize) -> usize {
        let mut slot = self.directory[b] as usize;
        if slot == 0 {
            slot = self.bricks.len() / 64;
            self.bricks.resize(self.bricks.len() + 64, 0);
            self.directory[b] = slot as u32;
            self.used.push(b as u32);
        }
        slot
    }

    /// The leaf-mask table of the node of 2×2×2 cells at `o` (even coordinates): by the coded
    /// cells just below its three lower faces (none, 1–2, 3–5, 6 or more).
    #[inline(always)]
    pub(super) fn face_table(&self, o: [u32; 3]) -> usize {
        if self.use_directory {
            return self.find_leaf(o, false).face_table();
        }
        let mut n = 0;
        for a in 0..3 {
            if o[a] == 0 {
                continue;
            }
            let (b, c) = ((a + 1) % 3, (a + 2) % 3);
            for db in 0..2u32 {
                for dc in 0..2u32 {
                    let mut p = o;
                    p[a] -= 1;
                    p[b] += db;
                    p[c] += dc;
                    n += (self.get(p) != 0) as u32;
                }
            }
        }
        face_state_of_count(n)
    }
}

impl CellMap {
    /// The face states of the eight children (2×2×2 cells each) of the node of 4×4×4 cells at
    /// `o` (coordinates multiples of 4: one brick of the directory), child i at
    /// `child_origin(o, i, 2)`: by the coded cells just below each child's lower faces that
    /// lie outside the node (none, 1–2, 3–5, 6 or more), as [`CellMap::face_table`] counts
    /// them for a node of 2×2×2 cells. The faces inside the node are its siblings', coded
    /// after.
    pub(super) fn node4_face_states(&self, o: [u32; 3]) -> [usize; 8] {
        debug_assert!(o.iter().all(|&v| v % 4 == 0));
        // quadrant[a][j]: the coded cells of the 2×2 quadrant j of the node's lower face along
        // axis a, j by the halves of the face's two other axes, the first one lowest (the
        // child's bits on those axes).
        let mut quadrant = [[0u32; 4]; 3];
        if self.use_directory {
            // Each lower face is the facing plane of the brick below along its axis: x = 3
            // (offsets 3 + 4y + 16z), y = 3 (12 + x + 16z) or z = 3 (48 + x + 4y). A brick is
            // eight little-endian words (word k: bytes 8k..8k + 8) whose non-zero bytes are
            // counted a word at a time, under a mask of the quadrant's bytes.
            let b = self.brick(o);
            // Byte 7 of each word's byte set where the byte is not 0.
            let nonzero = |w: u64| {
                const LOW7: u64 = 0x7f7f_7f7f_7f7f_7f7f;
                ((w & LOW7).wrapping_add(LOW7) | w) & !LOW7
            };
            let words = |brick: usize| -> [u64; 8] {
                let cells = self.cells_of(brick);
                std::array::from_fn(|k| {
                    nonzero(u64::from_le_bytes(
                        cells[8 * k..8 * k + 8].try_into().expect("8 bytes"),
                    ))
                })
            };
            let count = |w: u64, mask: u64| (w & mask).count_ones();
            if o[0] > 0 {
                // Plane x = 3: row z is words 2z and 2z + 1, y = 0, 1 (2, 3) at bytes 3, 7.
                let w = words(b - 1);
                const X3: u64 = 0x8000_0000_8000_0000;
                for zh in 0..2 {
                    for yh in 0..2 {
                        quadrant[0][yh + 2 * zh] =
                            count(w[4 * zh + yh], X3) + count(w[4 * zh + 2 + yh], X3);
                    }
                }
            }
            if o[1] > 0 {
                // Plane y = 3: bytes 4..8 of word 2z + 1 hold x = 0..4.
                let w = words(b - self.stride[0]);
                const Y3: [u64; 2] = [0x0000_8080_0000_0000, 0x8080_0000_0000_0000];
                for zh in 0..2 {
                    for xh in 0..2 {
                        quadrant[1][xh + 2 * zh] =
                            count(w[4 * zh + 1], Y3[xh]) + count(w[4 * zh + 3], Y3[xh]);
                    }
                }
            }
            if o[2] > 0 {
                // Plane z = 3: words 6 (y = 0, 1) and 7 (y = 2, 3), x at byte x + 4(y & 1).
                let w = words(b - self.stride[1]);
                const Z3: [u64; 2] = [0x0000_8080_0000_8080, 0x8080_0000_8080_0000];
                for yh in 0..2 {
                    for xh in 0..2 {
                        quadrant[2][xh + 2 * yh] = count(w[6 + yh], Z3[xh]);
                    }
                }
            }
        } else {
            for a in 0..3 {
                if o[a] == 0 {
                    continue;
                }
                let (b, c) = ((a + 1) % 3, (a + 2) % 3);
                // The face's axes in increasing order, as the quadrant index takes them.
                let (first, second) = (b.min(c), b.max(c));
                for j in 0..4u32 {
                    for i in 0..4u32 {
                        let mut p = o;
                        p[a] -= 1;
                        p[first] += i;
                        p[second] += j;
                        quadrant[a][(i / 2 + 2 * (j / 2)) as usize] += (self.get(p) != 0) as u32;
                    }
                }
            }
        }
        std::array::from_fn(|child| {
            let half = [child & 1, child >> 1 & 1, child >> 2 & 1];
            let mut n = 0;
            if half[0] == 0 {
                n += quadrant[0][half[1] + 2 * half[2]];
            }
            if half[1] == 0 {
                n += quadrant[1][half[0] + 2 * half[2]];
            }
            if half[2] == 0 {
                n += quadrant[2][half[0] + 2 * half[1]];
            }
            face_state_of_count(n)
        })
    }
}

/// The face state of `n` coded cells below a box's lower faces (none, 1–2, 3–5, 6 or more).
#[inline(always)]
fn face_state_of_count(n: u32) -> usize {
    // Looked up rather than matched: the count is as unpredictable as the data. A box of
    // 2×2×2 cells has 12 cells below its faces.
    // (n is at most 12; the table's 16 entries make that check a mask.)
    const STATE: [u8; 16] = [0, 1, 1, 2, 2, 2, 3, 3, 3, 3, 3, 3, 3, 3, 3, 3];
    debug_assert!(n <= 12);
    STATE[(n & 15) as usize] as usize
}

impl Drop for CellMap {
    fn drop(&mut self) {
        self.clear_directory();
        let directory = std::mem::take(&mut self.directory);
        BRICK_SCRATCH.with(|s| {
            let mut s = s.borrow_mut();
            if s.len() < directory.len() {
                *s = directory;
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::super::{child_origin, VALUE_TABLES};
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The face state of the box of 2×2×2 cells at `c`, by brute force over the coded cells
    /// `truth`: those just below its lower faces along the axes `counted` picks (none, 1–2,
    /// 3–5, 6 or more).
    fn brute_face_state<V>(
        truth: &std::collections::HashMap<[u32; 3], V>,
        c: [u32; 3],
        counted: impl Fn(usize) -> bool,
    ) -> usize {
        let touching = truth
            .keys()
            .filter(|p| {
                (0..3).any(|a| {
                    counted(a)
                        && c[a] > 0
                        && p[a] == c[a] - 1
                        && (0..3).all(|b| b == a || (p[b] >= c[b] && p[b] < c[b] + 2))
                })
            })
            .count();
        match touching {
            0 => 0,
            1 | 2 => 1,
            3..=5 => 2,
            _ => 3,
        }
    }

    #[test]
    fn directory_and_hashed_cell_maps_give_brute_force_contexts() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for round in 0..30 {
            let extent = [0, 1, 2].map(|_| rng.gen_range(1..10u32));
            let mut dense = CellMap::new();
            dense.reset(extent);
            let mut sparse = CellMap::new();
            sparse.reset(extent);
            sparse.use_directory = false;
            let mut truth = std::collections::HashMap::new();
            for _ in 0..rng.gen_range(0..150) {
                let c = extent.map(|e| rng.gen_range(0..e));
                let negative = rng.gen_bool(0.5);
                let q = if rng.gen_bool(0.8) {
                    rng.gen_range(0..12u64)
                } else {
                    rng.gen_range(0..1u64 << 40)
                };
                dense.insert(c, negative, q);
                sparse.insert(c, negative, q);
                truth.insert(c, (negative, q));
            }
            for _ in 0..100 {
                let c = extent.map(|e| rng.gen_range(0..e));
                let mut sign = 0;
                let mut classes = Vec::new();
                for a in 0..3 {
                    if c[a] > 0 {
                        let mut below = c;
                        below[a] -= 1;
                        if let Some(&(n, q)) = truth.get(&below) {
                            sign += 3usize.pow(a as u32) * (1 + n as usize);
                            classes.push((u64::BITS - q.leading_zeros()).min(31) as f64);
                        }
                    }
                }
                let table = if classes.is_empty() {
                    0
                } else {
                    let mean = classes.iter().sum::<f64>() / classes.len() as f64;
                    1 + ((mean + 0.5).floor() as usize).min(VALUE_TABLES - 2)
                };
                let want = (sign, table);
                let (ds, dv) = dense.leaf_contexts(c);
                let (ss, sv) = sparse.leaf_contexts(c);
                assert_eq!((ds, dv), want, "round {round} {c:?}");
                assert_eq!((ss, sv), want, "round {round} {c:?}");
                // The node of 2×2×2 cells at the even corner below c gives c the same
                // contexts and place as a child.
                let o = c.map(|v| v & !1);
                let i = (c[0] - o[0]) | (c[1] - o[1]) << 1 | (c[2] - o[2]) << 2;
                let mut leaf = dense.leaf_node(o).expect("a directory map");
                // A walked node starts with its cells empty and learns them as its children
                // are decoded: here, those the map holds.
                for j in 0..8 {
                    leaf.set(j, dense.get(child_origin(o, j, 1)));
                }
                let (ls, lv, index) = leaf.contexts(i);
                assert_eq!((ls, lv), want, "round {round} {c:?} as child {i} of {o:?}");
                let slot = dense.directory[dense.brick(c)] as usize;
                assert_eq!(index, 64 * slot + brick_offset(c));
                assert!(sparse.leaf_node(o).is_none());
                // Faces of that node.
                let table = brute_face_state(&truth, o, |_| true);
                assert_eq!(dense.face_table(o), table, "round {round} {o:?}");
                assert_eq!(leaf.face_table(), table, "round {round} {o:?}");
                assert_eq!(sparse.face_table(o), table, "round {round} {o:?}");
            }
            // The face states of the children of a node of 4×4×4 cells: the coded cells
            // below each child's lower faces outside the node.
            for _ in 0..20 {
                let o = extent.map(|e| rng.gen_range(0..e) & !3);
                let want: [usize; 8] = std::array::from_fn(|i| {
                    let c = [0, 1, 2].map(|a| o[a] + 2 * (i as u32 >> a & 1));
                    brute_face_state(&truth, c, |a| c[a] == o[a])
                });
                assert_eq!(dense.node4_face_states(o), want, "round {round} {o:?}");
                assert_eq!(sparse.node4_face_states(o), want, "round {round} {o:?}");
            }
            // A reset forgets every cell.
            dense.reset(extent);
            for z in 0..extent[2] {
                for y in 0..extent[1] {
                    for x in 0..extent[0] {
                        assert_eq!(dense.get([x, y, z]), 0);
                    }
                }
            }
        }
    }
}
