//! The significance-map coder ([`super::CoderKind::Sigmap`]), our improvement over the paper's
//! position-delta syntax: instead of coding each coefficient's position as a delta from the
//! previous one, a packet codes, per substream (channel, band), *which* cells of the tile's band
//! region hold a coefficient, by octree set partitioning with adaptive binary contexts (as in
//! SPECK-style wavelet coders), and each coefficient's magnitude as a uniform quantization step
//! above the layer's lower magnitude bound. Everything resets per packet, so packets stay
//! self-contained; coefficients come out in octree order (order within a packet carries no
//! meaning: the packet is the unit of progression).
//!
//! Per packet: for each substream that has parameters in the header, one adaptive "present" bit;
//! for a present substream, the octree over its tile-local band region: the dyadic octree of the
//! region's power-of-two bounding cube with the parts outside the region left out (so boxes
//! stay aligned whatever the region's size), and every child gets an adaptive "occupied" bit
//! (context: band, log2 of the child's size, whether the same cells hold a coefficient in the
//! parent band (same type, one level coarser) and in the cousin bands (earlier types of the
//! same level), as coded earlier in this packet, and, for small boxes, how many coded cells of
//! the same band touch its lower faces, weighted by magnitude class for a single cell from
//! version 6), except a last child implied occupied by its empty
//! siblings. A leaf is a coefficient: sign (adaptive, context: band and the signs of its three
//! lower neighbours) then q (adaptive exp-Golomb, context: band and the magnitude classes of
//! its three lower neighbours, from format version 6; band only before), reconstructed as
//! min(lb + (q + ½)·Δ, ub), where lb and ub are the layer's magnitude bounds of the substream
//! and Δ its step (exact f32 bits when Δ = 0).
//!
//! Format version 3 added the dyadic split, the sign contexts and the face contexts; they cut
//! the file by ~12 % at equal coefficients on the 128³ MNI volume (1.25 % and 5.85 % points).
//! Version 6 added the magnitude contexts: magnitudes cluster as positions do, so a
//! coefficient whose coded lower neighbours are large tends to be large, and a cell beside
//! large coefficients is likelier to hold one: each magnitude is coded in the context of its
//! lower neighbours' magnitude classes, and a single cell's occupancy weighs its face
//! neighbours by them (−2.0 % and a further −0.75 % of the decode bench's file at equal
//! coefficients; magnitudes take half or more of a file).

use super::coefficient::{region_extent, Coefficient, SizeBreakdown};
use super::quant::Quantizer;
use super::{invalid, FormatError, Header};
use crate::entropy::range::{AdaptiveUintModel, BitModel, RangeDecoder, RangeEncoder};
use crate::layout::Band;
use rustc_hash::FxHashMap;

/// Most size contexts per band (log2 of a box's cell count, clamped); a packet uses as many as
/// its tile's largest region needs ([`Models::new`]), so small tiles set up fewer models.
const MAX_SIZE_CONTEXTS: usize = 48;

/// States of a neighbourhood context: no such band, its region is empty, it holds a coefficient.
const NEIGHBOUR_STATES: usize = 3;

/// Sign contexts per band: each of the three lower neighbours is absent, positive or negative.
const SIGN_CONTEXTS: usize = 27;

/// The adaptive models of a packet, and the cells coded so far in the current substream.
struct Models {
    present: Vec<BitModel>,
    occupied: Vec<BitModel>,
    sign: Vec<BitModel>,
    value: Vec<AdaptiveUintModel>,
    coded: CodedCells,
    /// Size contexts per band: enough for the largest box of a tile region.
    size_contexts: usize,
    /// Value contexts per band: [`VALUE_CONTEXTS`], or 1 in files before
    /// [`super::MAGNITUDE_CONTEXTS_VERSION`].
    value_contexts: usize,
}

impl Models {
    fn new(header: &Header) -> Models {
        let nb = header.geometry.band_count();
        let tile_cells = (header.tile as u128).pow(3);
        let size_contexts =
            ((u128::BITS - tile_cells.leading_zeros()) as usize + 1).clamp(2, MAX_SIZE_CONTEXTS);
        let occupied = nb * size_contexts * NEIGHBOUR_STATES * NEIGHBOUR_STATES * FACE_STATES;
        let value_contexts = if header.version >= super::MAGNITUDE_CONTEXTS_VERSION {
            VALUE_CONTEXTS
        } else {
            1
        };
        Models {
            size_contexts,
            value_contexts,
            present: (0..nb).map(|_| BitModel::new()).collect(),
            occupied: (0..occupied).map(|_| BitModel::new()).collect(),
            sign: (0..nb * SIGN_CONTEXTS).map(|_| BitModel::new()).collect(),
            value: vec![AdaptiveUintModel::new(); nb * value_contexts],
            coded: CodedCells::default(),
        }
    }
}

/// Value contexts per band: the summed magnitude classes of the three lower neighbours
/// ([`CodedCells::leaf_contexts`]).
const VALUE_CONTEXTS: usize = 8;

/// The magnitude class of a quantized magnitude q, as its neighbours' value contexts read it:
/// 0, 1, 2–4, 5 and above.
#[inline(always)]
fn magnitude_class(q: u64) -> u8 {
    match q {
        0 => 0,
        1 => 1,
        2..=4 => 2,
        _ => 3,
    }
}

/// Occupancy states of a box's lower faces: no coded cell, one, two or three, four or more.
const FACE_STATES: usize = 4;

/// Largest box (in cells) whose lower faces are looked at; larger boxes use face state 0.
const FACE_CONTEXT_MAX_CELLS: usize = 64;

/// Largest band region held densely (a quarter byte per cell in [`CodedCells`], about a byte per
/// cell in a [`Pyramid`]); larger regions use a hash map or a [`SignificanceGrid`].
const DENSE_MAX_CELLS: usize = 1 << 22;

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
/// Regions up to [`DENSE_MAX_CELLS`] are dense bit sets in 4×4×4-cell bricks (one `u64` of
/// "coded" bits and one of "negative" bits per brick, x fastest inside a brick): an octree box
/// of up to 64 cells is a dyadic cube of edge ≤ 4 and lies in one brick, so each of its lower
/// faces is one masked population count (lookups are the inner loop of both coders). Larger
/// regions, which a big single tile or a hostile header can declare, use a hash map whose size
/// follows the coefficients actually coded. Both answer the same.
#[derive(Default)]
struct CodedCells {
    extent: [u32; 3],
    /// Bricks per axis.
    bricks: [usize; 3],
    coded: Vec<u64>,
    negative: Vec<u64>,
    /// The two bits of each coded cell's magnitude class ([`magnitude_class`]).
    class: [Vec<u64>; 2],
    /// Bricks set since the last reset, to clear only those.
    touched: Vec<usize>,
    sparse: FxHashMap<[u32; 3], u8>,
    use_dense: bool,
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
fn count_ones3(w: [u64; 3]) -> usize {
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
    fn reset(&mut self, extent: [u32; 3]) {
        self.reset_with_limit(extent, DENSE_MAX_CELLS);
    }

    fn reset_with_limit(&mut self, extent: [u32; 3], dense_max: usize) {
        for &i in &self.touched {
            self.coded[i] = 0;
            self.negative[i] = 0;
            self.class[0][i] = 0;
            self.class[1][i] = 0;
        }
        self.touched.clear();
        self.sparse.clear();
        self.extent = extent;
        let cells = extent.iter().map(|&e| e as usize).product::<usize>();
        self.use_dense = cells <= dense_max;
        self.bricks = extent.map(|e| (e as usize).div_ceil(4));
        let bricks = self.bricks.iter().product::<usize>();
        if self.use_dense && self.coded.len() < bricks {
            self.coded.resize(bricks, 0);
            self.negative.resize(bricks, 0);
            self.class[0].resize(bricks, 0);
            self.class[1].resize(bricks, 0);
        }
    }

    /// The brick of a cell and the cell's bit in it.
    #[inline(always)]
    fn locate(&self, c: [u32; 3]) -> (usize, u32) {
        let b = self.bricks;
        let i = (c[0] >> 2) as usize + b[0] * ((c[1] >> 2) as usize + b[1] * (c[2] >> 2) as usize);
        (i, (c[0] & 3) | (c[1] & 3) << 2 | (c[2] & 3) << 4)
    }

    fn insert(&mut self, cell: [u32; 3], negative: bool, class: u8) {
        if self.use_dense {
            let (i, bit) = self.locate(cell);
            if self.coded[i] == 0 {
                self.touched.push(i);
            }
            self.coded[i] |= 1 << bit;
            self.negative[i] = (self.negative[i] & !(1 << bit)) | (negative as u64) << bit;
            for (k, plane) in self.class.iter_mut().enumerate() {
                plane[i] = (plane[i] & !(1 << bit)) | (((class >> k) & 1) as u64) << bit;
            }
        } else {
            self.sparse
                .insert(cell, (1 + negative as u8) | (class << 2));
        }
    }

    /// The state of a cell inside the region.
    #[inline(always)]
    fn get(&self, cell: [u32; 3]) -> u8 {
        if self.use_dense {
            let (i, bit) = self.locate(cell);
            (((self.coded[i] >> bit) & 1) + ((self.negative[i] >> bit) & 1)) as u8
        } else {
            self.sparse.get(&cell).map_or(0, |v| v & 3)
        }
    }

    /// The sign context of `cell` in band index `band` ([`CodedCells::leaf_contexts`]).
    #[cfg(test)]
    fn sign_context(&self, band: usize, cell: [u32; 3]) -> usize {
        self.leaf_contexts(band, cell).0
    }

    /// The value context of `cell` in band index `band` ([`CodedCells::leaf_contexts`]).
    #[cfg(test)]
    fn value_context(&self, band: usize, cell: [u32; 3]) -> usize {
        self.leaf_contexts(band, cell).1
    }

    /// The sign and value contexts of `cell` in band index `band`, from its three lower
    /// neighbours: the sign context says whether each is absent, positive or negative; the
    /// value context sums 0 (absent) or 1 + its magnitude class over them, bucketed. One pass
    /// serves both, since both read the same neighbours.
    #[inline(always)]
    fn leaf_contexts(&self, band: usize, cell: [u32; 3]) -> (usize, usize) {
        let mut state = 0;
        let mut sum = 0;
        if self.use_dense {
            // The neighbour one cell down an axis: in the same brick, or at the brick's lower
            // edge the far plane of the brick below.
            let (i, bit) = self.locate(cell);
            let stride = [1, self.bricks[0], self.bricks[0] * self.bricks[1]];
            for a in 0..3 {
                let (s, m) = if cell[a] == 0 {
                    (0, 0)
                } else {
                    let step = 1u32 << (2 * a);
                    let (j, nbit) = if cell[a] & 3 != 0 {
                        (i, bit - step)
                    } else {
                        (i - stride[a], bit + 3 * step)
                    };
                    let coded = (self.coded[j] >> nbit) & 1;
                    let class =
                        ((self.class[0][j] >> nbit) & 1) | ((self.class[1][j] >> nbit) & 1) << 1;
                    (
                        coded + ((self.negative[j] >> nbit) & 1),
                        coded * (1 + class),
                    )
                };
                state = state * 3 + s as usize;
                sum += m as usize;
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
            }
        }
        const BUCKET: [usize; 13] = [0, 1, 2, 3, 4, 5, 5, 6, 6, 6, 7, 7, 7];
        (
            band * SIGN_CONTEXTS + state,
            band * VALUE_CONTEXTS + BUCKET[sum],
        )
    }

    /// The face state of a box of `cells` cells: how many coded cells touch its three lower
    /// faces (0, 1, 2–3, 4+); 0 for boxes above [`FACE_CONTEXT_MAX_CELLS`].
    #[inline(always)]
    fn face_state(&self, b: &Box3, cells: usize) -> usize {
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
                if b.lo[a] == 0 {
                    continue;
                }
                let plane = BRICK[a][1 << lo[a]];
                let first = cube & plane;
                let shift = 1 << (2 * a);
                let (word, face) = if lo[a] > 0 {
                    (self.coded[i], first >> shift)
                } else {
                    (self.coded[i - stride[a]], first << (3 * shift))
                };
                faces[a] = word & face;
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
        match n {
            0 => 0,
            1 => 1,
            2..=3 => 2,
            _ => 3,
        }
    }
}

impl Models {
    /// The sign and value models of a coefficient at `cell` of band index `band`
    /// ([`CodedCells::leaf_contexts`]; files before [`super::MAGNITUDE_CONTEXTS_VERSION`] have one
    /// value model per band).
    #[inline(always)]
    fn leaf_contexts(&self, band: usize, cell: [u32; 3]) -> (usize, usize) {
        let (sign, value) = self.coded.leaf_contexts(band, cell);
        if self.value_contexts == 1 {
            (sign, band)
        } else {
            (sign, value)
        }
    }

    /// The face state of a box of `cells` cells ([`CodedCells::face_state`]). From
    /// [`super::MAGNITUDE_CONTEXTS_VERSION`] a single cell's state weighs its coded lower
    /// neighbours by their magnitude classes instead of counting them (the sum of
    /// [`CodedCells::leaf_contexts`]: 0, 1, 2–3, 4 and above), since a cell beside large
    /// coefficients is likelier to hold one.
    #[inline(always)]
    fn face_state(&self, b: &Box3, cells: usize) -> usize {
        if cells == 1 && self.value_contexts != 1 {
            match self.coded.leaf_contexts(0, b.lo).1 {
                0 => 0,
                1 => 1,
                2 | 3 => 2,
                _ => 3,
            }
        } else {
            self.coded.face_state(b, cells)
        }
    }

    /// The occupancy context of a box: its band, the log2 of its cell count, the states of its
    /// parent region (same type one level coarser) and of its cousins (earlier types of the
    /// same level at the same cells), both as coded earlier in this packet, and its face state
    /// (coded cells of the same band touching its lower faces, [`CodedCells::face_state`]).
    fn occupancy_context(
        &self,
        band: usize,
        cells: usize,
        neighbours: (usize, usize),
        face: usize,
    ) -> usize {
        let lg = (usize::BITS - cells.leading_zeros()) as usize;
        let size = lg.min(self.size_contexts - 1);
        (((band * self.size_contexts + size) * NEIGHBOUR_STATES + neighbours.0) * NEIGHBOUR_STATES
            + neighbours.1)
            * FACE_STATES
            + face
    }
}

/// Most cells a [`SignificanceGrid`] holds (~5 MB): larger bounding boxes are coarsened.
const MAX_GRID_CELLS: usize = 1 << 20;

/// Which cells of one band's tile-local region hold a coefficient of this packet, as a 3D
/// prefix sum so that any box is counted in O(1). Its memory is bounded whatever a (possibly
/// hostile) packet holds: when the cells' bounding box exceeds [`MAX_GRID_CELLS`], the grid
/// records 2^shift-cell blocks instead, and a box query answers for the blocks it touches
/// (encoder and decoder build the same grid, so the contexts still agree).
struct SignificanceGrid {
    /// Grid size in (possibly coarsened) cells.
    dims: [usize; 3],
    /// Bounding box of the cells, in band coordinates.
    origin: [u32; 3],
    extent: [u64; 3],
    /// Coarsening: a grid cell covers 2^shift band cells per axis.
    shift: u32,
    /// The cells themselves (x fastest), for the frequent one-cell queries.
    cells: Vec<bool>,
    sums: Vec<u32>,
}

impl SignificanceGrid {
    /// The grid of `cells` (coordinates relative to `origin`); it spans only their bounding
    /// box, since every query outside it is empty anyway.
    fn new(origin: [u32; 3], cells: &[[u32; 3]]) -> Self {
        let mut lo = [u32::MAX; 3];
        let mut hi = [0u32; 3];
        for p in cells {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a] + 1);
            }
        }
        if cells.is_empty() {
            lo = [0; 3];
        }
        let extent = [0, 1, 2].map(|a| (hi[a] - lo[a]) as u64);
        let mut shift = 0u32;
        let coarse = |shift: u32| extent.map(|e| e.div_ceil(1 << shift) as usize);
        while coarse(shift).iter().map(|d| d + 1).product::<usize>() > MAX_GRID_CELLS {
            shift += 1;
        }
        let dims = coarse(shift);
        let origin = [0, 1, 2].map(|a| origin[a] + lo[a]);
        let [nx, ny, nz] = dims.map(|d| d + 1);
        let mut sums = vec![0u32; nx * ny * nz];
        let mut set = vec![false; dims[0] * dims[1] * dims[2]];
        let at = |x: usize, y: usize, z: usize| x + nx * (y + ny * z);
        for p in cells {
            let [x, y, z] = [0, 1, 2].map(|a| ((p[a] - lo[a]) >> shift) as usize);
            set[x + dims[0] * (y + dims[1] * z)] = true;
            sums[at(x + 1, y + 1, z + 1)] = 1;
        }
        // Separable running sums along x, then y, then z (3 adds per cell).
        for z in 1..nz {
            for y in 1..ny {
                let row = at(0, y, z);
                for x in 1..nx {
                    sums[row + x] += sums[row + x - 1];
                }
            }
        }
        for z in 1..nz {
            for y in 1..ny {
                let (row, prev) = (at(0, y, z), at(0, y - 1, z));
                for x in 1..nx {
                    sums[row + x] += sums[prev + x];
                }
            }
        }
        let slice = nx * ny;
        for i in slice..sums.len() {
            sums[i] += sums[i - slice];
        }
        SignificanceGrid {
            dims,
            origin,
            extent,
            shift,
            cells: set,
            sums,
        }
    }

    /// Whether any cell of the band-coordinate box [lo, hi) (clipped to the region) is set.
    fn any(&self, lo: [u64; 3], hi: [u64; 3]) -> bool {
        let mut l = [0usize; 3];
        let mut h = [0usize; 3];
        for a in 0..3 {
            let o = self.origin[a] as u64;
            let lc = lo[a].saturating_sub(o).min(self.extent[a]);
            let hc = hi[a].saturating_sub(o).min(self.extent[a]);
            if hc <= lc {
                return false;
            }
            l[a] = (lc >> self.shift) as usize;
            h[a] = (((hc - 1) >> self.shift) + 1) as usize;
        }
        if (0..3).all(|a| h[a] == l[a] + 1) {
            return self.cells[l[0] + self.dims[0] * (l[1] + self.dims[1] * l[2])];
        }
        let [nx, ny, _] = self.dims.map(|d| d + 1);
        let s = |x: usize, y: usize, z: usize| self.sums[x + nx * (y + ny * z)];
        let count = s(h[0], h[1], h[2])
            .wrapping_sub(s(l[0], h[1], h[2]))
            .wrapping_sub(s(h[0], l[1], h[2]))
            .wrapping_sub(s(h[0], h[1], l[2]))
            .wrapping_add(s(l[0], l[1], h[2]))
            .wrapping_add(s(l[0], h[1], l[2]))
            .wrapping_add(s(h[0], l[1], l[2]))
            .wrapping_sub(s(l[0], l[1], l[2]));
        count > 0
    }
}

/// Whether a [`SignificanceGrid`] over cells with bounding box [lo, hi) would be coarsened.
fn coarsened(lo: [u32; 3], hi: [u32; 3]) -> bool {
    (0..3)
        .map(|a| (hi[a] - lo[a]) as u128 + 1)
        .product::<u128>()
        > MAX_GRID_CELLS as u128
}

/// The exact occupancy of a set of cells of one tile-local band region, for the only queries
/// the octree makes of it: does any cell of the dyadic cube of edge 2^k at `lo` hold a
/// coefficient? Level k holds one byte per such cube (level 0 the cells), so a query is one
/// lookup and an insertion marks at most one byte per level; a set grows cell by cell, unlike
/// a [`SignificanceGrid`], which is rebuilt over its whole bounding box. It answers what an
/// uncoarsened [`SignificanceGrid`] answers for an octree box: a box is its dyadic cube
/// clipped to the region, and no cell lies outside the region.
struct Pyramid {
    /// Per level: its size in cubes, and where it starts in `bytes`.
    levels: Vec<([usize; 3], usize)>,
    bytes: Vec<u8>,
}

impl Pyramid {
    fn new(extent: [u32; 3]) -> Pyramid {
        let mut levels = Vec::new();
        let mut total = 0usize;
        for k in 0..u32::BITS {
            let d = extent.map(|e| (e as usize).div_ceil(1 << k).max(1));
            levels.push((d, total));
            total += d[0] * d[1] * d[2];
            if d == [1, 1, 1] {
                break;
            }
        }
        Pyramid {
            levels,
            bytes: vec![0; total],
        }
    }

    fn insert(&mut self, p: [u32; 3]) {
        for (k, &(d, offset)) in self.levels.iter().enumerate() {
            let q = [
                (p[0] >> k) as usize,
                (p[1] >> k) as usize,
                (p[2] >> k) as usize,
            ];
            let i = offset + q[0] + d[0] * (q[1] + d[1] * q[2]);
            if self.bytes[i] != 0 {
                // Every coarser cube holding this one is already marked.
                break;
            }
            self.bytes[i] = 1;
        }
    }

    /// Whether any cell of the cube of edge 2^k at `lo` (a multiple of 2^k) is in the set.
    #[inline]
    fn cube(&self, k: u32, lo: [u32; 3]) -> bool {
        let top = self.levels.len() - 1;
        let shr = |v: u32| v.checked_shr(k).unwrap_or(0) as usize;
        let q = [shr(lo[0]), shr(lo[1]), shr(lo[2])];
        let (d, offset) = self.levels[(k as usize).min(top)];
        if (0..3).any(|a| q[a] >= d[a]) {
            return false;
        }
        self.bytes[offset + q[0] + d[0] * (q[1] + d[1] * q[2])] != 0
    }
}

/// The cells of one band (or of a level's cousin bands) coded so far: a [`Pyramid`] when its
/// answers are those of the [`SignificanceGrid`] the format defines the contexts by (the grid
/// is not coarsened, the region is small enough to hold densely and, for a parent, its region
/// halves the finer level's), the grid itself otherwise.
enum CellSet {
    Exact(Pyramid),
    Grid(SignificanceGrid),
}

/// The parent and cousin sets of one band, as coded so far: `None` where the band has none
/// (state 0), `Some(None)` where that set is still empty.
struct Relatives<'a> {
    parent: Option<Option<&'a CellSet>>,
    cousin: Option<Option<&'a CellSet>>,
}

impl Relatives<'_> {
    /// Parent and cousin states of the box `b` (tile-local) of a band whose region starts at
    /// `origin`: 0 no such band, 1 nothing there, 2 a coefficient there.
    #[inline(always)]
    fn states(&self, origin: [u32; 3], b: &Box3) -> (usize, usize) {
        let k = b.scale.trailing_zeros();
        let glo = || [0, 1, 2].map(|a| (origin[a] + b.lo[a]) as u64);
        let ghi = || [0, 1, 2].map(|a| (origin[a] + b.hi[a]) as u64);
        let parent = match self.parent {
            None => 0,
            Some(None) => 1,
            // The box's parent cells are the cube of half its edge at half its corner.
            Some(Some(CellSet::Exact(p))) => {
                1 + p.cube(
                    k.saturating_sub(1),
                    [b.lo[0] >> 1, b.lo[1] >> 1, b.lo[2] >> 1],
                ) as usize
            }
            Some(Some(CellSet::Grid(g))) => {
                1 + g.any(glo().map(|v| v / 2), ghi().map(|v| v.div_ceil(2))) as usize
            }
        };
        let cousin = match self.cousin {
            None => 0,
            Some(None) => 1,
            Some(Some(CellSet::Exact(p))) => 1 + p.cube(k, b.lo) as usize,
            Some(Some(CellSet::Grid(g))) => 1 + g.any(glo(), ghi()) as usize,
        };
        (parent, cousin)
    }
}

/// A level's band region in the tile: origin (band coordinates) and extent in cells.
#[derive(Clone, Copy)]
struct Region {
    origin: [u32; 3],
    extent: [u32; 3],
}

/// The significance of the bands of the current channel coded so far in this packet, indexed
/// by band; what the occupancy contexts look at.
struct Neighbourhood<'h> {
    header: &'h Header,
    /// Per level: the tile's band region.
    regions: Vec<Region>,
    /// Per band index: its cells, kept for the next finer level's parent queries.
    grids: Vec<Option<CellSet>>,
    /// Per level: the union of the wavelet bands coded so far at that level.
    cousins: Vec<Option<CellSet>>,
    level_cells: Vec<Vec<[u32; 3]>>,
    /// Per level: the bounding box [lo, hi) of `level_cells`.
    level_bounds: Vec<([u32; 3], [u32; 3])>,
}

impl<'h> Neighbourhood<'h> {
    fn new(header: &'h Header, tile: usize) -> Self {
        let g = &header.geometry;
        let nb = g.band_count();
        let nl = g.levels + 1;
        let regions = (0..nl)
            .map(|l| {
                let band = Band {
                    level: l as u8,
                    kind: 1,
                };
                let (origin, root) = region(header, tile, l as u8, g.band_dims(band));
                Region {
                    origin,
                    extent: root.hi,
                }
            })
            .collect();
        Neighbourhood {
            header,
            regions,
            grids: (0..nb).map(|_| None).collect(),
            cousins: (0..nl).map(|_| None).collect(),
            level_cells: vec![Vec::new(); nl],
            level_bounds: vec![([u32::MAX; 3], [0; 3]); nl],
        }
    }

    fn reset(&mut self) {
        self.grids.iter_mut().for_each(|g| *g = None);
        self.cousins.iter_mut().for_each(|g| *g = None);
        self.level_cells.iter_mut().for_each(Vec::clear);
        self.level_bounds
            .iter_mut()
            .for_each(|b| *b = ([u32::MAX; 3], [0; 3]));
    }

    /// The sets the occupancy contexts of band index `bi` look at.
    fn relatives(&self, bi: usize, band: Band) -> Relatives<'_> {
        if band.kind == 0 {
            return Relatives {
                parent: None,
                cousin: None,
            };
        }
        Relatives {
            // The parent band (same type, one level coarser) comes 7 band indices earlier.
            parent: ((band.level as usize) < self.header.geometry.levels)
                .then(|| self.grids[bi - 7].as_ref()),
            cousin: (band.kind > 1).then(|| self.cousins[band.level as usize].as_ref()),
        }
    }

    /// Whether a set of `count` cells of level `l` with bounding box [lo, hi) is held as a
    /// [`Pyramid`]: its grid would not be coarsened, its region is small enough, the set is
    /// dense enough to pay for a region-sized pyramid (at least one cell per 8×8×8 block of the
    /// region, so at most ~512 bytes per cell: a sparse set's grid is sized by its bounding
    /// box, so a small packet does not allocate and clear its whole region), and (for a parent set) the finer level's region
    /// maps onto it by halving, so that the halved box is the parent cube. Both forms answer
    /// the same queries identically.
    fn exact(&self, l: usize, lo: [u32; 3], hi: [u32; 3], count: usize, parent: bool) -> bool {
        let r = self.regions[l];
        let cells: u128 = r.extent.iter().map(|&e| e as u128).product();
        if coarsened(lo, hi) || cells > DENSE_MAX_CELLS as u128 || (count as u128) * 512 < cells {
            return false;
        }
        if parent {
            let Some(child) = l.checked_sub(1).map(|c| self.regions[c]) else {
                return false;
            };
            return (0..3).all(|a| {
                child.origin[a] == 2 * r.origin[a] && child.extent[a].div_ceil(2) >= r.extent[a]
            });
        }
        true
    }

    /// Records the cells of `band` just coded; grids nobody will query are not built.
    fn record(&mut self, band: Band, origin: [u32; 3], cells: &[[u32; 3]]) {
        if band.kind == 0 || cells.is_empty() {
            return;
        }
        let l = band.level as usize;
        // Only the next coarser level's bands are parents of what follows; drop the rest.
        let geometry = &self.header.geometry;
        for (i, b) in geometry.bands().iter().enumerate() {
            if b.level as usize > l + 1 {
                self.grids[i] = None;
            }
        }
        for level in l + 1..self.cousins.len() {
            self.cousins[level] = None;
        }
        let (mut lo, mut hi) = ([u32::MAX; 3], [0u32; 3]);
        for p in cells {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a] + 1);
            }
        }
        if l > 1 {
            if let Some(i) = geometry.band_index(band) {
                let set = if self.exact(l, lo, hi, cells.len(), true) {
                    let mut p = Pyramid::new(self.regions[l].extent);
                    cells.iter().for_each(|c| p.insert(*c));
                    CellSet::Exact(p)
                } else {
                    CellSet::Grid(SignificanceGrid::new(origin, cells))
                };
                self.grids[i] = Some(set);
            }
        }
        if band.kind < 7 {
            self.level_cells[l].extend_from_slice(cells);
            let bounds = &mut self.level_bounds[l];
            for a in 0..3 {
                bounds.0[a] = bounds.0[a].min(lo[a]);
                bounds.1[a] = bounds.1[a].max(hi[a]);
            }
            let (lo, hi) = *bounds;
            let set = if self.exact(l, lo, hi, self.level_cells[l].len(), false) {
                match self.cousins[l].take() {
                    // The union only grows: add the new cells.
                    Some(CellSet::Exact(mut p)) => {
                        cells.iter().for_each(|c| p.insert(*c));
                        CellSet::Exact(p)
                    }
                    _ => {
                        let mut p = Pyramid::new(self.regions[l].extent);
                        self.level_cells[l].iter().for_each(|c| p.insert(*c));
                        CellSet::Exact(p)
                    }
                }
            } else {
                CellSet::Grid(SignificanceGrid::new(origin, &self.level_cells[l]))
            };
            self.cousins[l] = Some(set);
        }
    }
}

/// A box of the tile-local band grid: [lo, hi) per axis, inside the dyadic cube
/// [lo, lo + scale)³ of the virtual power-of-two octree over the region.
#[derive(Clone, Copy)]
struct Box3 {
    lo: [u32; 3],
    hi: [u32; 3],
    /// Edge of the dyadic cube holding the box (a power of two).
    scale: u32,
}

impl Box3 {
    /// The root box of a region of `extent` cells: the dyadic cube is the next power of two of
    /// the longest axis, so every box below it is aligned to the region's origin and cells
    /// beyond the region are never coded.
    fn root(extent: [u32; 3]) -> Box3 {
        let longest = extent.iter().copied().max().unwrap_or(0).max(1);
        Box3 {
            lo: [0; 3],
            hi: extent,
            scale: longest.next_power_of_two(),
        }
    }
    #[inline]
    fn cells(&self) -> usize {
        (self.hi[0] - self.lo[0]) as usize
            * (self.hi[1] - self.lo[1]) as usize
            * (self.hi[2] - self.lo[2]) as usize
    }
    /// The up to 8 children of the dyadic cube (halved on each axis that reaches past its
    /// middle; children wholly outside the region do not exist), in x-fastest order, without
    /// allocating. Halves the scale until some axis splits, so a box of several cells always
    /// has at least two children. Children come in Morton order: a cell's lower neighbours
    /// (−1 along any axis) are always visited before it.
    #[inline(always)]
    fn children(&self) -> ([Box3; 8], usize) {
        let mut splits = [[(0u32, 0u32); 2]; 3];
        let mut counts = [1usize; 3];
        let mut half = self.scale / 2;
        while half > 0 && (0..3).all(|a| self.hi[a] - self.lo[a] <= half) {
            half /= 2;
        }
        for a in 0..3 {
            let (lo, hi) = (self.lo[a], self.hi[a]);
            if half > 0 && hi - lo > half {
                let mid = lo + half;
                splits[a] = [(lo, mid), (mid, hi)];
                counts[a] = 2;
            } else {
                splits[a][0] = (lo, hi);
            }
        }
        let mut out = [*self; 8];
        let mut n = 0;
        for z in &splits[2][..counts[2]] {
            for y in &splits[1][..counts[1]] {
                for x in &splits[0][..counts[0]] {
                    out[n] = Box3 {
                        lo: [x.0, y.0, z.0],
                        hi: [x.1, y.1, z.1],
                        scale: half.max(1),
                    };
                    n += 1;
                }
            }
        }
        (out, n)
    }
    fn contains(&self, p: [u32; 3]) -> bool {
        (0..3).all(|a| p[a] >= self.lo[a] && p[a] < self.hi[a])
    }
}

fn region(header: &Header, tile: usize, level: u8, band_dims: [usize; 3]) -> ([u32; 3], Box3) {
    let (origin, extent) = region_extent(header, tile, level, band_dims);
    (origin, Box3::root(extent))
}

/// Encodes one packet's coefficients; returns payload, the decoder's reconstruction (in decode
/// order) and the bit breakdown (model-cost estimates scaled to the payload).
pub(crate) fn encode(
    header: &Header,
    tile: usize,
    layer: usize,
    coefficients: &[Coefficient],
) -> (Vec<u8>, Vec<Coefficient>, SizeBreakdown) {
    let mut enc = RangeEncoder::new();
    let mut m = Models::new(header);
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let mut per_sub: Vec<Vec<&Coefficient>> = vec![Vec::new(); header.substream_count()];
    for c in coefficients {
        per_sub[header.substream_id(c.channel as usize, c.band)].push(c);
    }
    let mut recon = Vec::with_capacity(coefficients.len());
    let mut bd = SizeBreakdown::default();
    let mut hood = Neighbourhood::new(header, tile);
    for (sub, list) in per_sub.iter().enumerate() {
        if sub % nb == 0 {
            hood.reset();
        }
        if header.substreams[sub].is_none() {
            continue;
        }
        let bi = sub % nb;
        let b0 = enc.bits_spent();
        enc.encode_bit(&mut m.present[bi], !list.is_empty());
        bd.tag_bits += enc.bits_spent() - b0;
        if list.is_empty() {
            continue;
        }
        let band = bands[bi];
        let (origin, root) = region(header, tile, band.level, header.geometry.band_dims(band));
        let quant = Quantizer::of(header, sub, layer);
        let pts: Vec<([u32; 3], f32)> = list
            .iter()
            .map(|c| {
                let p = [0, 1, 2].map(|a| c.pos[a] - origin[a]);
                (p, c.value)
            })
            .collect();
        let cells: Vec<[u32; 3]> = pts.iter().map(|(p, _)| *p).collect();
        let ctx = Ctx {
            bi,
            quant,
            origin,
            channel: (sub / nb) as u8,
            band,
            relatives: hood.relatives(bi, band),
        };
        m.coded.reset(root.hi);
        encode_box(&mut enc, &mut m, &ctx, root, pts, &mut recon, &mut bd);
        hood.record(band, origin, &cells);
    }
    let mut payload = enc.finish();
    // Keep the count within what the packet reader accepts for this payload size; the range
    // decoder reads missing bytes as zeros, so the padding decodes as if absent.
    let per_byte = super::coefficient::MAX_COEFFICIENTS_PER_PAYLOAD_BYTE;
    let min_len = coefficients.len().div_ceil(per_byte).saturating_sub(1);
    if payload.len() < min_len {
        payload.resize(min_len, 0);
    }
    (payload, recon, bd)
}

struct Ctx<'a> {
    bi: usize,
    quant: Quantizer,
    origin: [u32; 3],
    channel: u8,
    band: Band,
    relatives: Relatives<'a>,
}

fn encode_box(
    enc: &mut RangeEncoder,
    m: &mut Models,
    ctx: &Ctx,
    b: Box3,
    pts: Vec<([u32; 3], f32)>,
    recon: &mut Vec<Coefficient>,
    bd: &mut SizeBreakdown,
) {
    if b.cells() == 1 {
        let (p, v) = pts[0];
        let b0 = enc.bits_spent();
        let negative = v < 0.0;
        let (sc, vc) = m.leaf_contexts(ctx.bi, p);
        enc.encode_bit(&mut m.sign[sc], negative);
        let b1 = enc.bits_spent();
        let (q, mag) = ctx.quant.quantize((v as f64).abs());
        m.value[vc].encode(enc, q);
        m.coded.insert(p, negative, magnitude_class(q));
        bd.sign_bits += b1 - b0;
        bd.value_bits += enc.bits_spent() - b1;
        let value = if v < 0.0 { -mag } else { mag } as f32;
        recon.push(Coefficient {
            channel: ctx.channel,
            band: ctx.band,
            pos: [0, 1, 2].map(|a| p[a] + ctx.origin[a]),
            value,
        });
        return;
    }
    let (children, n) = b.children();
    let children = &children[..n];
    let mut parts: Vec<Vec<([u32; 3], f32)>> = vec![Vec::new(); n];
    for (p, v) in pts {
        let i = children
            .iter()
            .position(|c| c.contains(p))
            .expect("child covers point");
        parts[i].push((p, v));
    }
    let mut any_before = false;
    for (i, (&child, part)) in children.iter().zip(parts).enumerate() {
        let occupied = !part.is_empty();
        // The last child must be occupied if all its siblings are empty: not coded.
        if i + 1 < n || any_before {
            let b0 = enc.bits_spent();
            let states = ctx.relatives.states(ctx.origin, &child);
            let cells = child.cells();
            let face = m.face_state(&child, cells);
            let oc = m.occupancy_context(ctx.bi, cells, states, face);
            enc.encode_bit(&mut m.occupied[oc], occupied);
            bd.position_bits += enc.bits_spent() - b0;
        }
        any_before |= occupied;
        if occupied {
            encode_box(enc, m, ctx, child, part, recon, bd);
        }
    }
}

/// Payload bytes read per kind of syntax element while decoding.
#[derive(Default)]
struct Spent {
    tag: usize,
    position: usize,
    sign: usize,
    value: usize,
}

/// Decodes a sigmap payload of `count` coefficients.
pub(crate) fn decode(
    header: &Header,
    tile: usize,
    layer: usize,
    count: usize,
    payload: &[u8],
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let mut dec = RangeDecoder::new(payload);
    let mut m = Models::new(header);
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    // The count is bounded but may still be large for a hostile packet: grow as decoded.
    let mut out = Vec::with_capacity(count.min(super::coefficient::INITIAL_CAPACITY));
    let mut hood = Neighbourhood::new(header, tile);
    let mut spent = Spent::default();
    for sub in 0..header.substream_count() {
        if sub % nb == 0 {
            hood.reset();
        }
        if header.substreams[sub].is_none() {
            continue;
        }
        let bi = sub % nb;
        let b0 = dec.bytes_read();
        let present = dec.decode_bit(&mut m.present[bi]);
        spent.tag += dec.bytes_read() - b0;
        if !present {
            continue;
        }
        let band = bands[bi];
        let (origin, root) = region(header, tile, band.level, header.geometry.band_dims(band));
        if root.cells() == 0 {
            return Err(invalid(
                "packet",
                "substream present in an empty tile region",
            ));
        }
        let quant = Quantizer::of(header, sub, layer);
        let ctx = Ctx {
            bi,
            quant,
            origin,
            channel: (sub / nb) as u8,
            band,
            relatives: hood.relatives(bi, band),
        };
        let first = out.len();
        m.coded.reset(root.hi);
        decode_box(&mut dec, &mut m, &ctx, root, count, &mut out, &mut spent)?;
        let cells: Vec<[u32; 3]> = out[first..]
            .iter()
            .map(|c| [0, 1, 2].map(|a| c.pos[a] - origin[a]))
            .collect();
        hood.record(band, origin, &cells);
    }
    // Sums of whole bytes, as the per-symbol sums were: the same f64 values.
    bd.tag_bits += 8.0 * spent.tag as f64;
    bd.position_bits += 8.0 * spent.position as f64;
    bd.sign_bits += 8.0 * spent.sign as f64;
    bd.value_bits += 8.0 * spent.value as f64;
    if out.len() != count {
        return Err(invalid(
            "packet",
            format!(
                "decoded {} coefficients, header of the packet says {count}",
                out.len()
            ),
        ));
    }
    Ok(out)
}

fn decode_box(
    dec: &mut RangeDecoder,
    m: &mut Models,
    ctx: &Ctx,
    b: Box3,
    count: usize,
    out: &mut Vec<Coefficient>,
    spent: &mut Spent,
) -> Result<(), FormatError> {
    if out.len() >= count {
        return Err(invalid(
            "packet",
            "more coefficients than the packet declares",
        ));
    }
    if dec.overrun() {
        return Err(invalid(
            "packet",
            format!(
                "the payload ends after {} of {count} declared coefficients",
                out.len()
            ),
        ));
    }
    if b.cells() == 1 {
        let b0 = dec.bytes_read();
        let cell = b.lo;
        let (sc, vc) = m.leaf_contexts(ctx.bi, cell);
        let negative = dec.decode_bit(&mut m.sign[sc]);
        let b1 = dec.bytes_read();
        let q = m.value[vc].decode(dec)?;
        m.coded.insert(cell, negative, magnitude_class(q));
        spent.sign += b1 - b0;
        spent.value += dec.bytes_read() - b1;
        let mag = ctx.quant.dequantize(q)?;
        let value = if negative { -mag } else { mag } as f32;
        if !value.is_finite() {
            return Err(invalid("packet", "decoded value is not finite"));
        }
        out.push(Coefficient {
            channel: ctx.channel,
            band: ctx.band,
            pos: [
                b.lo[0] + ctx.origin[0],
                b.lo[1] + ctx.origin[1],
                b.lo[2] + ctx.origin[2],
            ],
            value,
        });
        return Ok(());
    }
    let (children, n) = b.children();
    let mut any_before = false;
    for (i, &child) in children[..n].iter().enumerate() {
        let occupied = if i + 1 < n || any_before {
            let b0 = dec.bytes_read();
            let states = ctx.relatives.states(ctx.origin, &child);
            let cells = child.cells();
            let face = m.face_state(&child, cells);
            let oc = m.occupancy_context(ctx.bi, cells, states, face);
            let o = dec.decode_bit(&mut m.occupied[oc]);
            spent.position += dec.bytes_read() - b0;
            o
        } else {
            true
        };
        any_before |= occupied;
        if occupied {
            decode_box(dec, m, ctx, child, count, out, spent)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn huge_bounding_boxes_are_coarsened_never_missing_a_cell() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..10 {
            let side = rng.gen_range(200..5000u32);
            let cells: Vec<[u32; 3]> = (0..rng.gen_range(2..40))
                .map(|_| [0, 1, 2].map(|_| rng.gen_range(0..side)))
                .collect();
            let grid = SignificanceGrid::new([3, 5, 7], &cells);
            assert!(grid.sums.len() <= MAX_GRID_CELLS && grid.cells.len() <= MAX_GRID_CELLS);
            for c in &cells {
                let g = [0, 1, 2].map(|a| (c[a] + [3, 5, 7][a]) as u64);
                assert!(grid.any(g, g.map(|v| v + 1)), "cell {c:?} missed");
                assert!(grid.any(g.map(|v| v.saturating_sub(9)), g.map(|v| v + 3)));
            }
            // Far outside the cells' bounding box nothing is set.
            let far = [u64::from(side) + 100; 3];
            assert!(!grid.any(far, far.map(|v| v + 50)));
        }
    }

    #[test]
    fn significance_grid_counts_boxes_like_a_brute_force_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..20 {
            let dims = [0, 1, 2].map(|_| rng.gen_range(1..9usize));
            let origin = [0, 1, 2].map(|_| rng.gen_range(0..5u32));
            let cells: Vec<[u32; 3]> = (0..rng.gen_range(0..12))
                .map(|_| [0, 1, 2].map(|a| rng.gen_range(0..dims[a] as u32)))
                .collect();
            let grid = SignificanceGrid::new(origin, &cells);
            for _ in 0..200 {
                // Boxes in band coordinates, partly or wholly outside the region.
                let lo = [0, 1, 2].map(|_| rng.gen_range(0..14u64));
                let hi = [0, 1, 2].map(|a| lo[a] + rng.gen_range(0..6u64));
                let brute = cells.iter().any(|c| {
                    (0..3).all(|a| {
                        let g = (c[a] + origin[a]) as u64;
                        g >= lo[a] && g < hi[a]
                    })
                });
                assert_eq!(
                    grid.any(lo, hi),
                    brute,
                    "{lo:?}..{hi:?} in {origin:?}+{dims:?}"
                );
            }
        }
    }

    /// Leaves of the octree over a region, in coding order.
    fn leaves(b: Box3, out: &mut Vec<[u32; 3]>) {
        if b.cells() == 1 {
            out.push(b.lo);
            return;
        }
        let (children, n) = b.children();
        assert!(n >= 2, "a box of {} cells must split", b.cells());
        for c in &children[..n] {
            assert!(c.cells() >= 1);
            assert!((0..3).all(|a| c.lo[a] >= b.lo[a] && c.hi[a] <= b.hi[a]));
            assert!((0..3).all(|a| c.hi[a] - c.lo[a] <= c.scale));
            leaves(*c, out);
        }
    }

    #[test]
    fn octree_visits_every_cell_once_after_its_lower_neighbours() {
        for extent in [
            [1, 1, 1],
            [1, 1, 9],
            [5, 7, 3],
            [13, 2, 6],
            [16, 16, 16],
            [17, 1, 33],
        ] {
            let mut order = Vec::new();
            leaves(Box3::root(extent), &mut order);
            let cells: usize = extent.iter().map(|&e| e as usize).product();
            assert_eq!(order.len(), cells, "{extent:?}");
            let mut rank = std::collections::HashMap::new();
            for (i, c) in order.iter().enumerate() {
                assert!((0..3).all(|a| c[a] < extent[a]), "{c:?} outside {extent:?}");
                assert!(rank.insert(*c, i).is_none(), "{c:?} visited twice");
            }
            for (c, &i) in &rank {
                for a in 0..3 {
                    if c[a] > 0 {
                        let mut below = *c;
                        below[a] -= 1;
                        assert!(rank[&below] < i, "{below:?} after {c:?} in {extent:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn coded_cells_dense_and_sparse_agree_with_a_brute_force_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut dense = CodedCells::default();
        let mut sparse = CodedCells::default();
        for round in 0..20 {
            let extent = [0, 1, 2].map(|_| rng.gen_range(1..12u32));
            dense.reset(extent);
            sparse.reset_with_limit(extent, 0);
            assert!(dense.use_dense && !sparse.use_dense);
            let mut inserted = std::collections::HashMap::new();
            for _ in 0..rng.gen_range(0..200) {
                let c = extent.map(|e| rng.gen_range(0..e));
                let negative = rng.gen_bool(0.5);
                let q = rng.gen_range(0..12u64);
                dense.insert(c, negative, magnitude_class(q));
                sparse.insert(c, negative, magnitude_class(q));
                inserted.insert(c, (negative, q));
            }
            for _ in 0..200 {
                let lo = extent.map(|e| rng.gen_range(0..e));
                let hi = [0, 1, 2].map(|a| rng.gen_range(lo[a] + 1..=extent[a]));
                let b = Box3 { lo, hi, scale: 16 };
                let c = lo;
                assert_eq!(dense.get(c), sparse.get(c));
                let want = inserted.get(&c).map_or(0, |&(n, _)| 1 + n as u8);
                assert_eq!(dense.get(c), want, "round {round}");
                assert_eq!(dense.sign_context(3, c), sparse.sign_context(3, c));
                // Brute force: 1 + the class of each coded lower neighbour, bucketed.
                let sum: usize = (0..3)
                    .filter(|&a| c[a] > 0)
                    .filter_map(|a| {
                        let mut below = c;
                        below[a] -= 1;
                        inserted.get(&below)
                    })
                    .map(|&(_, q)| 1 + magnitude_class(q) as usize)
                    .sum();
                let bucket = [0, 1, 2, 3, 4, 5, 5, 6, 6, 6, 7, 7, 7][sum];
                assert_eq!(dense.value_context(3, c), 3 * VALUE_CONTEXTS + bucket);
                assert_eq!(sparse.value_context(3, c), 3 * VALUE_CONTEXTS + bucket);
                assert_eq!(
                    dense.face_state(&b, b.cells()),
                    sparse.face_state(&b, b.cells())
                );
                // Brute force: coded cells just below one of the box's lower faces.
                let touching = inserted
                    .keys()
                    .filter(|p| {
                        (0..3).any(|a| {
                            lo[a] > 0
                                && p[a] == lo[a] - 1
                                && (0..3).all(|o| o == a || (p[o] >= lo[o] && p[o] < hi[o]))
                        })
                    })
                    .count();
                let expected = if b.cells() > FACE_CONTEXT_MAX_CELLS {
                    0
                } else {
                    match touching {
                        0 => 0,
                        1 => 1,
                        2..=3 => 2,
                        _ => 3,
                    }
                };
                assert_eq!(
                    dense.face_state(&b, b.cells()),
                    expected,
                    "{b:?}",
                    b = (lo, hi)
                );
            }
        }
        // A reset forgets every cell.
        let extent = dense.extent;
        dense.reset(extent);
        for z in 0..extent[2] {
            for y in 0..extent[1] {
                for x in 0..extent[0] {
                    assert_eq!(dense.get([x, y, z]), 0);
                }
            }
        }
    }

    /// Every box of the octree over a region (the coders query their children), in order.
    fn boxes(b: Box3, out: &mut Vec<Box3>) {
        out.push(b);
        if b.cells() > 1 {
            let (children, n) = b.children();
            for c in &children[..n] {
                boxes(*c, out);
            }
        }
    }

    fn random_cells(rng: &mut ChaCha8Rng, extent: [u32; 3], n: usize) -> Vec<[u32; 3]> {
        (0..n)
            .map(|_| extent.map(|e| rng.gen_range(0..e)))
            .collect()
    }

    #[test]
    fn pyramids_answer_octree_boxes_as_the_grid_does() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        for round in 0..40 {
            let extent = [0, 1, 2].map(|_| rng.gen_range(1..40u32));
            let origin = [0, 1, 2].map(|_| rng.gen_range(0..9u32) * 2);
            let n = rng.gen_range(0..(round % 5) * 30 + 2);
            let cells = random_cells(&mut rng, extent, n);
            let grid = SignificanceGrid::new(origin, &cells);
            assert_eq!(grid.shift, 0);
            let mut pyramid = Pyramid::new(extent);
            cells.iter().for_each(|c| pyramid.insert(*c));
            let mut all = Vec::new();
            boxes(Box3::root(extent), &mut all);
            for b in &all {
                let glo = [0, 1, 2].map(|a| (origin[a] + b.lo[a]) as u64);
                let ghi = [0, 1, 2].map(|a| (origin[a] + b.hi[a]) as u64);
                let k = b.scale.trailing_zeros();
                assert_eq!(
                    pyramid.cube(k, b.lo),
                    grid.any(glo, ghi),
                    "{extent:?} {:?}",
                    b.lo
                );
            }
            // As a parent: the finer level's region is twice this one (plus up to a cell).
            let child_extent = [0, 1, 2].map(|a| 2 * extent[a] - rng.gen_range(0..2u32));
            let child_origin = origin.map(|o| 2 * o);
            let mut all = Vec::new();
            boxes(Box3::root(child_extent), &mut all);
            for b in &all {
                let plo = [0, 1, 2].map(|a| (child_origin[a] + b.lo[a]) as u64 / 2);
                let phi = [0, 1, 2].map(|a| ((child_origin[a] + b.hi[a]) as u64).div_ceil(2));
                let k = b.scale.trailing_zeros();
                let half = [b.lo[0] >> 1, b.lo[1] >> 1, b.lo[2] >> 1];
                assert_eq!(
                    pyramid.cube(k.saturating_sub(1), half),
                    grid.any(plo, phi),
                    "parent of {:?} in {child_extent:?}",
                    b.lo
                );
            }
        }
    }

    #[test]
    fn brick_face_counts_match_the_map_on_octree_boxes() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        let mut dense = CodedCells::default();
        let mut sparse = CodedCells::default();
        for _ in 0..30 {
            let extent = [0, 1, 2].map(|_| rng.gen_range(1..30u32));
            dense.reset(extent);
            sparse.reset_with_limit(extent, 0);
            let cells: usize = extent.iter().map(|&e| e as usize).product();
            let n = rng.gen_range(0..=cells);
            for c in random_cells(&mut rng, extent, n) {
                let negative = rng.gen_bool(0.4);
                let class = rng.gen_range(0..4u8);
                dense.insert(c, negative, class);
                sparse.insert(c, negative, class);
            }
            let mut all = Vec::new();
            boxes(Box3::root(extent), &mut all);
            for b in &all {
                assert_eq!(
                    dense.face_state(b, b.cells()),
                    sparse.face_state(b, b.cells()),
                    "{:?}..{:?} in {extent:?}",
                    b.lo,
                    b.hi
                );
                if b.cells() == 1 {
                    assert_eq!(dense.sign_context(2, b.lo), sparse.sign_context(2, b.lo));
                    assert_eq!(dense.value_context(2, b.lo), sparse.value_context(2, b.lo));
                }
            }
        }
    }

    #[test]
    fn three_word_population_count() {
        let mut rng = ChaCha8Rng::seed_from_u64(29);
        for _ in 0..1000 {
            let w: [u64; 3] = [rng.gen(), rng.gen(), rng.gen()];
            let w = w.map(|v| v >> rng.gen_range(0..64));
            let want: u32 = w.iter().map(|v| v.count_ones()).sum();
            assert_eq!(count_ones3(w), want as usize);
        }
        assert_eq!(count_ones3([u64::MAX; 3]), 192);
    }
}
