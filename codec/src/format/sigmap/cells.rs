//! The coded cells of the substream being coded, by tile-local cell (none, positive, negative):
//! dense 4×4×4 bricks up to a size, a hash map beyond; and what the contexts read from them: the
//! lower neighbours' signs, magnitude classes and face counts.

use super::octree::Box3;
use rustc_hash::FxHashMap;

/// States of a neighbourhood context: no such band, its region is empty, it holds a coefficient.
pub(super) const NEIGHBOUR_STATES: usize = 3;

/// Sign contexts per band: each of the three lower neighbours is absent, positive or negative.
pub(super) const SIGN_CONTEXTS: usize = 27;

/// Value contexts per band: the summed magnitude classes of the three lower neighbours
/// ([`CodedCells::leaf_contexts`]).
pub(super) const VALUE_CONTEXTS: usize = 8;

/// The magnitude class of a quantized magnitude q, as its neighbours' value contexts read it:
/// 0, 1, 2–4, 5 and above.
#[inline(always)]
pub(super) fn magnitude_class(q: u64) -> u8 {
    match q {
        0 => 0,
        1 => 1,
        2..=4 => 2,
        _ => 3,
    }
}

/// A single cell's three lower neighbours as its contexts read them
/// ([`CodedCells::neighbours`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct Neighbours {
    /// Absent, positive or negative, for x, y and z: `0..SIGN_CONTEXTS`.
    pub(super) signs: usize,
    /// The summed magnitude classes, bucketed: `0..VALUE_CONTEXTS`.
    pub(super) magnitudes: usize,
    /// How many are coded: 0–3.
    pub(super) coded: usize,
}

/// Occupancy states of a box's lower faces: no coded cell, one, two or three, four or more.
pub(super) const FACE_STATES: usize = 4;

/// The face state of `n` coded cells (or of a single cell's weighed neighbours): 0, 1, 2–3,
/// 4 and above. A table, since the count is as unpredictable as the data.
#[inline(always)]
pub(super) fn face_state_of_count(n: usize) -> usize {
    const STATE: [u8; 8] = [0, 1, 2, 2, 3, 3, 3, 3];
    STATE[n.min(7)] as usize
}

/// Largest box (in cells) whose lower faces are looked at; larger boxes use face state 0.
pub(super) const FACE_CONTEXT_MAX_CELLS: usize = 64;

/// Largest band region held densely (1⅛ bytes per cell in [`CodedCells`], about a byte per
/// cell in a [`Pyramid`]); larger regions use a hash map or a [`SignificanceGrid`].
pub(super) const DENSE_MAX_CELLS: usize = 1 << 22;

/// The coefficients of the substream being coded, by tile-local cell: 0 = none, 1 = positive,
/// 2 = negative.
///
/// Neighbouring coefficients of a semi-orthogonal spline band are strongly correlated (the
/// basis is not orthogonal within a level), and octree order codes a cell's lower neighbours
/// (−1 along x, y and z) before the cell (see [`Box3::children`]). So a coefficient's sign is
/// coded in the context of its three lower neighbours' signs, and a small box's occupancy in
/// the context of how many coded cells touch its lower faces. On the 128³ MNI volume the sign
/// contexts save a third of the sign bits (5–6 % of the file) and the face contexts a further
/// 4–5 %.
///
/// Regions up to [`DENSE_MAX_CELLS`] are held densely twice: as bit sets in 4×4×4-cell bricks
/// (one `u64` of "coded" bits per brick, x fastest inside a brick), where an octree box of up
/// to 64 cells is a dyadic cube of edge ≤ 4 inside one brick, so each of its lower faces is
/// one masked population count; and as a byte per cell (state and magnitude class), where a
/// leaf's three lower neighbours are three loads (lookups are the inner loop of both coders).
/// Larger regions, which a big single tile or a hostile header can declare, use a hash map
/// whose size follows the coefficients actually coded. Both answer the same.
#[derive(Default)]
pub(super) struct CodedCells {
    pub(super) extent: [u32; 3],
    /// Bricks per axis.
    pub(super) bricks: [usize; 3],
    pub(super) coded: Vec<u64>,
    /// What a leaf's contexts read of each cell, one byte per cell on the region's grid
    /// padded by one empty plane below each axis (so a cell's lower neighbours are three loads
    /// at fixed offsets, with no test for the region's edge): bits 0–1 the cell's state (0
    /// none, 1 positive, 2 negative), bits 2–4 what the value context adds for it (0 none, else
    /// 1 + its magnitude class). With the bricks that is 1⅛ bytes per cell, against half a
    /// byte for the sign and class bit planes it replaced, and each of a leaf's three
    /// neighbour lookups is one load instead of a branch and four words.
    pub(super) leaf: Vec<u8>,
    /// Strides of `leaf` along y and z (x is 1).
    pub(super) leaf_stride: [usize; 2],
    /// Bricks set since the last reset, to clear only those.
    pub(super) touched: Vec<usize>,
    /// `leaf` bytes set since the last reset.
    pub(super) touched_leaf: Vec<usize>,
    pub(super) sparse: FxHashMap<[u32; 3], u8>,
    pub(super) use_dense: bool,
}

/// Bit masks of a brick selecting the cells whose x (y, z) is in a 4-bit set, by that set.
static BRICK: [[u64; 16]; 3] = [
    brick_masks(0x1111_1111_1111_1111, 1),
    brick_masks(0x000F_000F_000F_000F, 4),
    brick_masks(0xFFFF, 16),
];

const fn brick_masks(plane: u64, stride: u32) -> [u64; 16] {
    let mut out = [0u64; 16];
    let mut set = 0;
    while set < 16 {
        let mut i = 0;
        while i < 4 {
            if set & (1 << i) != 0 {
                out[set] |= plane << (i * stride);
            }
            i += 1;
        }
        set += 1;
    }
    out
}

/// The set bits of three words: one population count in SWAR steps (the baseline x86-64 target
/// has no popcount instruction, and the three counts share the final multiply).
#[inline(always)]
pub(super) fn count_ones3(w: [u64; 3]) -> usize {
    const M1: u64 = 0x5555_5555_5555_5555;
    const M2: u64 = 0x3333_3333_3333_3333;
    const M4: u64 = 0x0F0F_0F0F_0F0F_0F0F;
    let nibbles = |x: u64| {
        let x = x - ((x >> 1) & M1);
        (x & M2) + ((x >> 2) & M2)
    };
    // Each nibble holds at most 3 · 4 = 12, each byte then at most 24.
    let sum = nibbles(w[0]) + nibbles(w[1]) + nibbles(w[2]);
    let bytes = (sum & M4) + ((sum >> 4) & M4);
    (bytes.wrapping_mul(0x0101_0101_0101_0101) >> 56) as usize
}

impl CodedCells {
    /// Forgets every cell and prepares for a region of `extent` cells.
    pub(super) fn reset(&mut self, extent: [u32; 3]) {
        self.reset_with_limit(extent, DENSE_MAX_CELLS);
    }

    pub(super) fn reset_with_limit(&mut self, extent: [u32; 3], dense_max: usize) {
        for &i in &self.touched {
            self.coded[i] = 0;
        }
        for &i in &self.touched_leaf {
            self.leaf[i] = 0;
        }
        self.touched.clear();
        self.touched_leaf.clear();
        self.sparse.clear();
        self.extent = extent;
        let cells = extent.iter().map(|&e| e as usize).product::<usize>();
        self.use_dense = cells <= dense_max;
        self.bricks = extent.map(|e| (e as usize).div_ceil(4));
        if self.use_dense {
            // Every word and byte is zero here, so a larger array may be a fresh one: the
            // allocator hands out zeroed pages without writing them.
            let bricks = self.bricks.iter().product::<usize>();
            if self.coded.len() < bricks {
                self.coded = vec![0; bricks];
            }
            let padded = extent.map(|e| e as usize + 1);
            self.leaf_stride = [padded[0], padded[0] * padded[1]];
            let bytes = padded.iter().product::<usize>();
            if self.leaf.len() < bytes {
                self.leaf = vec![0; bytes];
            }
        }
    }

    /// The brick of a cell and the cell's bit in it.
    #[inline(always)]
    fn locate(&self, c: [u32; 3]) -> (usize, u32) {
        let b = self.bricks;
        let i = (c[0] >> 2) as usize + b[0] * ((c[1] >> 2) as usize + b[1] * (c[2] >> 2) as usize);
        (i, (c[0] & 3) | (c[1] & 3) << 2 | (c[2] & 3) << 4)
    }

    /// A cell's byte in `leaf`.
    #[inline(always)]
    fn leaf_index(&self, c: [u32; 3]) -> usize {
        let [sy, sz] = self.leaf_stride;
        (c[0] as usize + 1) + sy * (c[1] as usize + 1) + sz * (c[2] as usize + 1)
    }

    pub(super) fn insert(&mut self, cell: [u32; 3], negative: bool, class: u8) {
        if self.use_dense {
            let (i, bit) = self.locate(cell);
            if self.coded[i] == 0 {
                self.touched.push(i);
            }
            self.coded[i] |= 1 << bit;
            let j = self.leaf_index(cell);
            self.leaf[j] = (1 + negative as u8) | (1 + class) << 2;
            self.touched_leaf.push(j);
        } else {
            self.sparse
                .insert(cell, (1 + negative as u8) | (class << 2));
        }
    }

    /// The state of a cell inside the region.
    #[inline(always)]
    pub(super) fn get(&self, cell: [u32; 3]) -> u8 {
        if self.use_dense {
            self.leaf[self.leaf_index(cell)] & 3
        } else {
            self.sparse.get(&cell).map_or(0, |v| v & 3)
        }
    }

    /// The sign context of `cell` in band index `band` ([`CodedCells::leaf_contexts`]).
    #[cfg(test)]
    pub(super) fn sign_context(&self, band: usize, cell: [u32; 3]) -> usize {
        self.leaf_contexts(band, cell).0
    }

    /// The value context of `cell` in band index `band` ([`CodedCells::leaf_contexts`]).
    #[cfg(test)]
    pub(super) fn value_context(&self, band: usize, cell: [u32; 3]) -> usize {
        self.leaf_contexts(band, cell).1
    }

    /// The sign and value contexts of `cell` in band index `band`, from its three lower
    /// neighbours ([`CodedCells::neighbours`]).
    #[cfg(test)]
    pub(super) fn leaf_contexts(&self, band: usize, cell: [u32; 3]) -> (usize, usize) {
        let n = self.neighbours(cell);
        (
            band * SIGN_CONTEXTS + n.signs,
            band * VALUE_CONTEXTS + n.magnitudes,
        )
    }

    /// What the contexts of a single cell read of its three lower neighbours, in one pass:
    /// whether each is absent, positive or negative (the sign context); the sum over them of
    /// 0 (absent) or 1 + its magnitude class, bucketed (the value context); and how many are
    /// coded (a single cell's face count).
    #[inline(always)]
    pub(super) fn neighbours(&self, cell: [u32; 3]) -> Neighbours {
        let mut state = 0;
        let mut sum = 0;
        let mut count = 0;
        if self.use_dense {
            // The lower neighbours lie one byte, one row and one plane back; below the
            // region's lower faces they are the padding's empty cells.
            let i = self.leaf_index(cell);
            let [sy, sz] = self.leaf_stride;
            for j in [i - 1, i - sy, i - sz] {
                let v = self.leaf[j];
                state = state * 3 + (v & 3) as usize;
                sum += (v >> 2) as usize;
                count += (v != 0) as usize;
            }
        } else {
            for a in 0..3 {
                let (s, m) = if cell[a] == 0 {
                    (0, 0)
                } else {
                    let mut below = cell;
                    below[a] -= 1;
                    self.sparse
                        .get(&below)
                        .map_or((0, 0), |&v| ((v & 3) as usize, 1 + (v >> 2) as usize))
                };
                state = state * 3 + s;
                sum += m;
                count += (s != 0) as usize;
            }
        }
        const BUCKET: [usize; 13] = [0, 1, 2, 3, 4, 5, 5, 6, 6, 6, 7, 7, 7];
        Neighbours {
            signs: state,
            magnitudes: BUCKET[sum],
            coded: count,
        }
    }

    /// The face state of a box of `cells` cells: how many coded cells touch its three lower
    /// faces (0, 1, 2–3, 4+); 0 for boxes above [`FACE_CONTEXT_MAX_CELLS`].
    #[inline(always)]
    pub(super) fn face_state(&self, b: &Box3, cells: usize) -> usize {
        if cells > FACE_CONTEXT_MAX_CELLS {
            return 0;
        }
        let n = if self.use_dense && b.scale <= 4 {
            // A cube of edge ≤ 4 at a multiple of its edge: inside one brick. Its lower face
            // along an axis is the box's first plane moved one cell down: in the same brick,
            // or, at the brick's edge, the last plane of the brick below.
            let lo = [b.lo[0] & 3, b.lo[1] & 3, b.lo[2] & 3];
            let span = |a: usize| (((1u32 << (b.hi[a] - b.lo[a])) - 1) << lo[a]) as usize;
            let span = [span(0), span(1), span(2)];
            let cube = BRICK[0][span[0]] & BRICK[1][span[1]] & BRICK[2][span[2]];
            let (i, _) = self.locate(b.lo);
            let stride = [1, self.bricks[0], self.bricks[0] * self.bricks[1]];
            let mut faces = [0u64; 3];
            for a in 0..3 {
                // Selected by masks rather than branches: which case holds follows the
                // octree's data-dependent descent.
                let plane = BRICK[a][1 << lo[a]];
                let first = cube & plane;
                let shift = 1 << (2 * a);
                let inside = lo[a] > 0;
                let below = usize::from(lo[a] == 0) & usize::from(b.lo[a] > 0);
                let word = self.coded[i - below * stride[a]];
                let into = (u64::from(inside)).wrapping_neg();
                let face = ((first >> shift) & into) | ((first << (3 * shift)) & !into);
                // No face below the region's lower edge.
                let keep = ((b.lo[a] > 0) as u64).wrapping_neg();
                faces[a] = word & face & keep;
            }
            count_ones3(faces)
        } else {
            let mut n = 0;
            for a in 0..3 {
                if b.lo[a] == 0 {
                    continue;
                }
                let (u, v) = ((a + 1) % 3, (a + 2) % 3);
                let mut c = [0u32; 3];
                c[a] = b.lo[a] - 1;
                for i in b.lo[u]..b.hi[u] {
                    c[u] = i;
                    for j in b.lo[v]..b.hi[v] {
                        c[v] = j;
                        n += (self.get(c) != 0) as usize;
                    }
                }
            }
            n
        };
        face_state_of_count(n)
    }
}
