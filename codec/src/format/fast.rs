//! The fast coder ([`super::CoderKind::Fast`]): the sigmap coder's quantization, octree order
//! and neighbour contexts, with positions and magnitudes coded by static Huffman tables instead
//! of adaptive binary decisions, so that a packet decodes with about two table look-ups and one
//! adaptive sign decision per coefficient.
//!
//! The sigmap coder spends about seven adaptive binary decisions per coefficient, each a
//! serial dependency through the range decoder and its model; that caps it near 6 M
//! coefficients/s per core. This coder reads one prefix code per occupied octree node of 2×2×2
//! cells or more and one per coefficient, for several times that speed at some cost in bytes
//! (measured in BENCHMARKS.md, "Decoding speed").
//!
//! A payload is two streams: a varint length, then the prefix-coded stream (MSB-first bits),
//! then the signs (adaptive binary range coding, reset per packet). Per packet, for each
//! substream (channel, band) that has parameters in the header: one raw "present" bit; for a
//! present substream, the dyadic octree over its tile-local band region (the region's
//! power-of-two bounding cube, at least 2 cells on a side). Every occupied node codes the 8-bit
//! mask of its occupied children (child i lies half an edge away by (i & 1, i >> 1 & 1,
//! i >> 2 & 1); children outside the region are never set) and visits them in bit order. A
//! node of 2×2×2 cells uses one of [`LEAF_MASK_TABLES`] tables, chosen by how many coded cells
//! of the substream touch its three lower faces; larger nodes share one table. A node of 2×2×2
//! cells is followed by its coefficients in bit order: for each, its step symbol from the value
//! table chosen by the mean bit length of its coded lower neighbours' steps (`value_table`),
//! then its sign in the sign stream (context: band and the signs of its three lower
//! neighbours, as the sigmap coder). A step symbol is q itself for q < 14, otherwise 13 + e
//! followed by the e − 1 low bits of q − 13, which has e bits. Steps and reconstruction are the
//! sigmap coder's ([`super::sigmap`]). The tables live in the header ([`FastTables`]), fitted
//! by the encoder to all of a file's packets, as the paper's coder does; packets stay
//! self-contained given the header.

use super::coefficient::{region_extent, Coefficient, PacketInput, SizeBreakdown};
use super::quant::Quantizer;
use super::{invalid, FormatError, Header};
use crate::entropy::bits::{BitReader, BitSink, BitWriter, WordReader};
use crate::entropy::huffman::{HuffmanCode, HuffmanDecoder};
use crate::entropy::range::{BitModel, RangeDecoder, RangeEncoder};
use crate::entropy::EntropyError;
use crate::layout::Band;
use rustc_hash::FxHashMap;
use std::cell::RefCell;
use std::sync::Arc;

/// Symbols of an occupancy-mask table (8-bit masks; 0 is never coded).
pub const MASK_ALPHABET: usize = 256;
/// Symbols of a value table: 14 direct steps and 50 escapes by bit length.
pub const VALUE_ALPHABET: usize = 64;
/// Mask tables of nodes of 2×2×2 cells, by the coded cells on their lower faces (none, 1–2,
/// 3–5, 6 or more). (Also splitting them by whether the parent band's cell over the node holds
/// a coefficient, as the sigmap coder's contexts do, saved 0.04 % of the decode bench's file
/// and cost 9 % of the decoding speed.)
pub const LEAF_MASK_TABLES: usize = 4;
/// Mask tables: the leaf tables, then one for larger nodes.
pub const MASK_TABLES: usize = LEAF_MASK_TABLES + 1;
/// Value tables: no coded lower neighbour, or 1 + the mean magnitude class of those coded
/// (`value_table`). (Separate tables for the finest and the coarser bands saved 0.15 % on
/// the decode bench's file, less than their header cost on small files.)
pub const VALUE_TABLES: usize = 16;
/// Sign contexts per band: each of the three lower neighbours is absent, positive or negative.
const SIGN_CONTEXTS: usize = 27;
/// Steps below this are a symbol of their own; larger ones are escaped by bit length.
const DIRECT_STEPS: u64 = 14;
/// Longest prefix code the encoder builds.
const MAX_CODE_LENGTH: u8 = 15;

/// The fast coder's prefix codes, stored in the header, with their decoders (built once, not
/// per packet).
#[derive(Debug, Clone)]
pub struct FastTables {
    /// Occupancy masks: [`LEAF_MASK_TABLES`] for nodes of 2×2×2 cells, then larger nodes.
    mask: [HuffmanCode; MASK_TABLES],
    /// Step symbols per value context.
    value: [HuffmanCode; VALUE_TABLES],
    decoders: Arc<Decoders>,
}

impl PartialEq for FastTables {
    fn eq(&self, other: &FastTables) -> bool {
        self.mask == other.mask && self.value == other.value
    }
}

impl FastTables {
    fn new(mask: [HuffmanCode; MASK_TABLES], value: [HuffmanCode; VALUE_TABLES]) -> FastTables {
        let decoders = Arc::new(Decoders {
            mask: std::array::from_fn(|t| HuffmanDecoder::new(&mask[t])),
            value: std::array::from_fn(|t| HuffmanDecoder::new(&value[t])),
        });
        FastTables {
            mask,
            value,
            decoders,
        }
    }

    /// Writes every table's code lengths.
    pub fn write(&self, sink: &mut impl BitSink) {
        for code in self.mask.iter().chain(&self.value) {
            code.write_lengths(sink);
        }
    }

    /// Reads tables written by [`FastTables::write`], validating every code.
    pub fn read(reader: &mut BitReader) -> Result<FastTables, EntropyError> {
        let mut mask = Vec::with_capacity(MASK_TABLES);
        for _ in 0..MASK_TABLES {
            mask.push(HuffmanCode::read_lengths(reader, MASK_ALPHABET)?);
        }
        let mut value = Vec::with_capacity(VALUE_TABLES);
        for _ in 0..VALUE_TABLES {
            value.push(HuffmanCode::read_lengths(reader, VALUE_ALPHABET)?);
        }
        Ok(FastTables::new(
            mask.try_into().expect("MASK_TABLES codes"),
            value.try_into().expect("VALUE_TABLES codes"),
        ))
    }
}

/// The magnitude class of a step, as its neighbours' contexts read it: its bit length (0 for
/// q = 0), at most 31. Logarithmic, so that the contexts follow the scale of the magnitudes,
/// which grows with the rate (a few steps at 0.1 % of the sample bytes, thousands at 5 %); the
/// sigmap coder's classes are coarser (0, 1, 2–4, 5 and above).
#[inline(always)]
fn bit_length_class(q: u64) -> u8 {
    (u64::BITS - q.leading_zeros()).min(31) as u8
}

/// The value table of a coefficient from its present lower neighbours' count `n` and summed
/// magnitude classes: 0 without neighbours, else 1 + their rounded mean class (at most
/// `VALUE_TABLES` − 2).
#[inline(always)]
fn value_table(n: usize, sum: usize) -> usize {
    let mean = match n {
        0 => return 0,
        1 => sum,
        2 => (sum + 1) >> 1,
        _ => (2 * sum + 3) / 6,
    };
    1 + mean.min(VALUE_TABLES - 2)
}

/// The step symbol of q and the raw bits that follow it (as many as [`raw_bits`] says).
fn step_symbol(q: u64) -> (usize, u64) {
    if q < DIRECT_STEPS {
        (q as usize, 0)
    } else {
        let r = q - DIRECT_STEPS + 1;
        let e = u64::BITS - r.leading_zeros();
        (
            (DIRECT_STEPS - 1) as usize + e as usize,
            r & ((1u64 << (e - 1)) - 1),
        )
    }
}

/// How many raw bits follow a step symbol.
fn raw_bits(symbol: usize) -> u32 {
    (symbol as u32).saturating_sub(DIRECT_STEPS as u32)
}

/// The step q of a step symbol and its raw bits: the inverse of [`step_symbol`].
#[inline(always)]
fn step_of(symbol: usize, raw: u64) -> u64 {
    if (symbol as u64) < DIRECT_STEPS {
        symbol as u64
    } else {
        (1u64 << raw_bits(symbol) | raw) + DIRECT_STEPS - 1
    }
}

/// The child mask bits whose children start inside a region of `extent` cells, for a node at
/// `o` with children of edge `h`. Children at the lower offsets start at `o`, inside.
#[inline(always)]
fn allowed_children(o: [u32; 3], h: u32, extent: [u32; 3]) -> u8 {
    let mut m = 0xFF;
    if o[0] + h >= extent[0] {
        m &= 0b0101_0101;
    }
    if o[1] + h >= extent[1] {
        m &= 0b0011_0011;
    }
    if o[2] + h >= extent[2] {
        m &= 0b0000_1111;
    }
    m
}

/// Offset of child `i` of a node whose children have edge `h`.
#[inline(always)]
fn child_origin(o: [u32; 3], i: u32, h: u32) -> [u32; 3] {
    [
        o[0] + (i & 1) * h,
        o[1] + ((i >> 1) & 1) * h,
        o[2] + ((i >> 2) & 1) * h,
    ]
}

/// log2 of the root node's edge: the region's power-of-two bounding cube, at least 2.
fn root_log(extent: [u32; 3]) -> u32 {
    let side = extent.iter().copied().max().unwrap_or(1).max(2);
    u32::BITS - (side - 1).leading_zeros()
}

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
struct CellMap {
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

/// Offset of a cell in its brick.
#[inline(always)]
fn brick_offset(c: [u32; 3]) -> usize {
    (c[0] & 3 | (c[1] & 3) << 2 | (c[2] & 3) << 4) as usize
}

impl CellMap {
    fn new() -> CellMap {
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
    fn reset(&mut self, extent: [u32; 3]) {
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

    #[inline(always)]
    fn insert(&mut self, c: [u32; 3], negative: bool, q: u64) {
        let v = 1 | (negative as u8) << 1 | bit_length_class(q) << 2;
        if self.use_directory {
            let b = self.brick(c);
            let mut slot = self.directory[b] as usize;
            if slot == 0 {
                slot = self.bricks.len() / 64;
                self.bricks.resize(self.bricks.len() + 64, 0);
                self.directory[b] = slot as u32;
                self.used.push(b as u32);
            }
            self.bricks[64 * slot + brick_offset(c)] = v;
        } else {
            self.sparse.insert(c, v);
        }
    }

    /// The cells of the brick at directory index `b` (the empty brick if none is coded).
    #[inline(always)]
    fn cells_of(&self, b: usize) -> &[u8] {
        let slot = self.directory[b] as usize;
        &self.bricks[64 * slot..64 * slot + 64]
    }

    /// The (sign, value) contexts of a cell: its three lower neighbours' signs (base 3) and the
    /// bucketed sum of their (1 + magnitude class).
    #[inline(always)]
    fn leaf_contexts(&self, c: [u32; 3]) -> (usize, usize) {
        let (x, y, z) = (c[0], c[1], c[2]);
        let (vx, vy, vz) = if self.use_directory {
            // Neighbours inside the cell's brick by offset, others from the brick below.
            // Scalars rather than coordinate arrays: copying arrays through the stack stalled
            // store forwarding here.
            let b = self.brick(c);
            let own = self.cells_of(b);
            let o = brick_offset(c);
            let vx = if x & 3 != 0 {
                own[o - 1]
            } else if x > 0 {
                self.cells_of(b - 1)[o + 3]
            } else {
                0
            };
            let vy = if y & 3 != 0 {
                own[o - 4]
            } else if y > 0 {
                self.cells_of(b - self.stride[0])[o + 12]
            } else {
                0
            };
            let vz = if z & 3 != 0 {
                own[o - 16]
            } else if z > 0 {
                self.cells_of(b - self.stride[1])[o + 48]
            } else {
                0
            };
            (vx, vy, vz)
        } else {
            let get = |dx: u32, dy: u32, dz: u32| {
                if x < dx || y < dy || z < dz {
                    0
                } else {
                    self.get([x - dx, y - dy, z - dz])
                }
            };
            (get(1, 0, 0), get(0, 1, 0), get(0, 0, 1))
        };
        let sign_of = |v: u8| {
            if v == 0 {
                0
            } else {
                1 + ((v >> 1) & 1) as usize
            }
        };
        let present = (vx != 0) as usize + (vy != 0) as usize + (vz != 0) as usize;
        let classes = (vx >> 2) as usize + (vy >> 2) as usize + (vz >> 2) as usize;
        (
            sign_of(vx) + 3 * sign_of(vy) + 9 * sign_of(vz),
            value_table(present, classes),
        )
    }

    /// The leaf-mask table of the node of 2×2×2 cells at `o` (even coordinates): by the coded
    /// cells just below its three lower faces (none, 1–2, 3–5, 6 or more).
    #[inline(always)]
    fn face_table(&self, o: [u32; 3]) -> usize {
        let (x, y, z) = (o[0], o[1], o[2]);
        let n = if self.use_directory {
            // A face's four cells lie in one brick (o is even, bricks are 4 cells wide), at
            // offsets 0 and 1, 4 or 16 along the face's two axes.
            let b = self.brick(o);
            let i = brick_offset(o);
            let face = |cells: &[u8], i: usize, u: usize, v: usize| {
                (cells[i] != 0) as u32
                    + (cells[i + u] != 0) as u32
                    + (cells[i + v] != 0) as u32
                    + (cells[i + u + v] != 0) as u32
            };
            let own = self.cells_of(b);
            let mut n = 0;
            if x & 3 != 0 {
                n += face(own, i - 1, 4, 16);
            } else if x > 0 {
                n += face(self.cells_of(b - 1), i + 3, 4, 16);
            }
            if y & 3 != 0 {
                n += face(own, i - 4, 1, 16);
            } else if y > 0 {
                n += face(self.cells_of(b - self.stride[0]), i + 12, 1, 16);
            }
            if z & 3 != 0 {
                n += face(own, i - 16, 1, 4);
            } else if z > 0 {
                n += face(self.cells_of(b - self.stride[1]), i + 48, 1, 4);
            }
            n
        } else {
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
            n
        };
        match n {
            0 => 0,
            1 | 2 => 1,
            3..=5 => 2,
            _ => 3,
        }
    }
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

/// One prefix-coded element of a packet's syntax, before the tables are fitted, packed in
/// 8 bytes (the encoder holds a whole file's, one or two per coefficient): bits 0–1 the kind
/// (present bit, mask, step), then the present bit, or the table in bits 2–5 and the mask in
/// bits 8–15, or the table in bits 2–5, the step symbol in bits 8–13 and its raw bits from bit
/// 14 (at most 49 of them, as many as [`raw_bits`] says).
#[derive(Debug, Clone, Copy)]
struct Symbol(u64);

const _: () = assert!(MASK_TABLES <= 16 && VALUE_TABLES <= 16 && VALUE_ALPHABET <= 64);

impl Symbol {
    const PRESENT: u64 = 0;
    const MASK: u64 = 1;
    const STEP: u64 = 2;

    fn present(present: bool) -> Symbol {
        Symbol(Self::PRESENT | (present as u64) << 2)
    }
    fn mask(table: usize, mask: u8) -> Symbol {
        Symbol(Self::MASK | (table as u64) << 2 | (mask as u64) << 8)
    }
    fn step(table: usize, symbol: usize, raw: u64) -> Symbol {
        debug_assert!(raw < 1 << raw_bits(symbol));
        Symbol(Self::STEP | (table as u64) << 2 | (symbol as u64) << 8 | raw << 14)
    }
    fn kind(self) -> u64 {
        self.0 & 3
    }
    fn table(self) -> usize {
        (self.0 >> 2 & 15) as usize
    }
    fn mask_bits(self) -> usize {
        (self.0 >> 8 & 0xFF) as usize
    }
    fn step_symbol(self) -> usize {
        (self.0 >> 8 & 63) as usize
    }
    fn raw(self) -> u64 {
        self.0 >> 14
    }
}

/// Symbol counts per table, over all packets.
struct Frequencies {
    mask: [Vec<u64>; MASK_TABLES],
    value: [Vec<u64>; VALUE_TABLES],
}

impl Frequencies {
    fn new() -> Frequencies {
        Frequencies {
            mask: std::array::from_fn(|_| vec![0; MASK_ALPHABET]),
            value: std::array::from_fn(|_| vec![0; VALUE_ALPHABET]),
        }
    }
    fn add(&mut self, symbols: &[Symbol]) {
        for &s in symbols {
            match s.kind() {
                Symbol::MASK => self.mask[s.table()][s.mask_bits()] += 1,
                Symbol::STEP => self.value[s.table()][s.step_symbol()] += 1,
                _ => {}
            }
        }
    }
    fn fit(&self) -> FastTables {
        FastTables::new(
            std::array::from_fn(|t| HuffmanCode::from_frequencies(&self.mask[t], MAX_CODE_LENGTH)),
            std::array::from_fn(|t| HuffmanCode::from_frequencies(&self.value[t], MAX_CODE_LENGTH)),
        )
    }
}

/// A packet being symbolized.
struct PacketCoder {
    symbols: Vec<Symbol>,
    signs: RangeEncoder,
    sign_models: Vec<BitModel>,
    map: CellMap,
    recon: Vec<Coefficient>,
}

/// The substream being coded or decoded.
struct Substream {
    bi: usize,
    quant: Quantizer,
    origin: [u32; 3],
    extent: [u32; 3],
    channel: u8,
    band: Band,
}

/// A coefficient to code: its octree key (interleaved cell bits, x lowest), cell and value.
type Keyed = (u64, [u32; 3], f32);

impl PacketCoder {
    fn node(&mut self, s: &Substream, pts: &[Keyed], o: [u32; 3], log: u32) {
        let shift = 3 * (log - 1);
        let child = |k: u64| ((k >> shift) & 7) as u32;
        let mask = pts.iter().fold(0u8, |m, p| m | 1 << child(p.0));
        let h = 1u32 << (log - 1);
        let table = if log > 1 {
            LEAF_MASK_TABLES
        } else {
            self.map.face_table(o)
        };
        self.symbols.push(Symbol::mask(table, mask));
        if log > 1 {
            let mut start = 0;
            while start < pts.len() {
                let c = child(pts[start].0);
                let end = start + pts[start..].partition_point(|p| child(p.0) == c);
                self.node(s, &pts[start..end], child_origin(o, c, h), log - 1);
                start = end;
            }
            return;
        }
        for &(_, cell, value) in pts {
            let negative = value < 0.0;
            let (q, magnitude) = s.quant.quantize((value as f64).abs());
            let (sc, vc) = self.map.leaf_contexts(cell);
            let (symbol, raw) = step_symbol(q);
            self.symbols.push(Symbol::step(vc, symbol, raw));
            self.signs
                .encode_bit(&mut self.sign_models[s.bi * SIGN_CONTEXTS + sc], negative);
            self.map.insert(cell, negative, q);
            let value = if negative { -magnitude } else { magnitude } as f32;
            self.recon.push(Coefficient::in_region(
                s.channel, s.band, s.origin, cell, value,
            ));
        }
    }
}

/// Interleaves the low `log` bits of a cell's coordinates, x lowest: octree order.
fn octree_key(cell: [u32; 3], log: u32) -> u64 {
    let mut k = 0u64;
    for bit in (0..log).rev() {
        for a in (0..3).rev() {
            k = k << 1 | ((cell[a] >> bit) & 1) as u64;
        }
    }
    k
}

/// A packet's symbolized form: prefix-coded symbols, the sign stream and the decoder's
/// reconstruction (in decode order).
struct Symbolized {
    symbols: Vec<Symbol>,
    signs: Vec<u8>,
    recon: Vec<Coefficient>,
}

fn symbolize(header: &Header, input: &PacketInput) -> Symbolized {
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let mut per_sub: Vec<Vec<&Coefficient>> = vec![Vec::new(); header.substream_count()];
    for c in &input.coefficients {
        per_sub[header.substream_id(c.channel as usize, c.band)].push(c);
    }
    let mut coder = PacketCoder {
        symbols: Vec::with_capacity(2 * input.coefficients.len() + per_sub.len()),
        signs: RangeEncoder::new(),
        sign_models: vec![BitModel::new(); nb * SIGN_CONTEXTS],
        map: CellMap::new(),
        recon: Vec::with_capacity(input.coefficients.len()),
    };
    for (sub, list) in per_sub.iter().enumerate() {
        if header.substreams[sub].is_none() {
            continue;
        }
        coder.symbols.push(Symbol::present(!list.is_empty()));
        if list.is_empty() {
            continue;
        }
        let bi = sub % nb;
        let band = bands[bi];
        let channel = (sub / nb) as u8;
        let (origin, extent) = region_extent(
            header,
            input.tile,
            band.level,
            header.geometry.band_dims(band),
        );
        let log = root_log(extent);
        let mut pts: Vec<Keyed> = list
            .iter()
            .map(|c| {
                let cell = [0, 1, 2].map(|a| c.pos[a] - origin[a]);
                (octree_key(cell, log), cell, c.value)
            })
            .collect();
        pts.sort_unstable_by_key(|p| p.0);
        let s = Substream {
            bi,
            quant: Quantizer::of(header, sub, input.layer),
            origin,
            extent,
            channel,
            band,
        };
        coder.map.reset(extent);
        coder.node(&s, &pts, [0; 3], log);
    }
    Symbolized {
        symbols: coder.symbols,
        signs: coder.signs.finish(),
        recon: coder.recon,
    }
}

/// Encodes packets: fits the tables to all of them (stored in `header.fast_tables`), then
/// writes each payload. Returns the payloads, the decoder's reconstructions and the breakdown
/// (exact code lengths, and the sign stream's bytes).
pub(crate) fn encode_packets(
    header: &mut Header,
    inputs: &[PacketInput],
) -> (Vec<Vec<u8>>, Vec<Vec<Coefficient>>, SizeBreakdown) {
    let header_ref = &*header;
    let code = |input: &PacketInput| symbolize(header_ref, input);
    #[cfg(feature = "rayon")]
    let symbolized: Vec<_> = {
        use rayon::prelude::*;
        inputs.par_iter().map(code).collect()
    };
    #[cfg(not(feature = "rayon"))]
    let symbolized: Vec<_> = inputs.iter().map(code).collect();
    let mut freqs = Frequencies::new();
    for p in &symbolized {
        freqs.add(&p.symbols);
    }
    let tables = freqs.fit();
    let mut bd = SizeBreakdown::default();
    let mut payloads = Vec::with_capacity(inputs.len());
    let mut recons = Vec::with_capacity(inputs.len());
    for p in symbolized {
        let mut w = BitWriter::with_capacity(p.symbols.len());
        for s in p.symbols {
            match s.kind() {
                Symbol::MASK => {
                    let code = &tables.mask[s.table()];
                    code.encode(s.mask_bits(), &mut w);
                    bd.position_bits += code.cost_bits(s.mask_bits()) as f64;
                }
                Symbol::STEP => {
                    let code = &tables.value[s.table()];
                    let (symbol, n) = (s.step_symbol(), raw_bits(s.step_symbol()));
                    code.encode(symbol, &mut w);
                    w.put_bits(s.raw(), n);
                    bd.value_bits += (code.cost_bits(symbol) + n) as f64;
                }
                _ => {
                    w.put_bit(s.0 >> 2 & 1 != 0);
                    bd.tag_bits += 1.0;
                }
            }
        }
        let prefix_coded = w.finish();
        let mut payload = super::bytes::ByteWriter::new();
        payload.varint(prefix_coded.len() as u64);
        payload.bytes(&prefix_coded);
        payload.bytes(&p.signs);
        let payload = payload.into_bytes();
        bd.sign_bits += 8.0 * p.signs.len() as f64;
        payloads.push(payload);
        recons.push(p.recon);
    }
    header.fast_tables = Some(tables);
    (payloads, recons, bd)
}

/// The decoders of a file's tables.
#[derive(Debug)]
struct Decoders {
    mask: [HuffmanDecoder; MASK_TABLES],
    value: [HuffmanDecoder; VALUE_TABLES],
}

/// A packet being decoded.
struct PacketDecoder<'a> {
    tables: &'a Decoders,
    reader: WordReader<'a>,
    signs: RangeDecoder<'a>,
    sign_models: Vec<BitModel>,
    map: CellMap,
    count: usize,
    out: Vec<Coefficient>,
    position_bits: u64,
}

impl PacketDecoder<'_> {
    #[cold]
    fn not_a_codeword(&self) -> FormatError {
        invalid(
            "packet",
            format!("no codeword at bit {}", self.reader.position()),
        )
    }

    fn node(&mut self, s: &Substream, o: [u32; 3], log: u32) -> Result<(), FormatError> {
        let h = 1u32 << (log - 1);
        let table = if log > 1 {
            LEAF_MASK_TABLES
        } else {
            self.map.face_table(o)
        };
        self.reader.refill();
        let (mask, len) = self.tables.mask[table]
            .decode_window(self.reader.peek())
            .ok_or_else(|| self.not_a_codeword())?;
        self.reader.consume(len);
        self.position_bits += len as u64;
        let mask = mask as u8;
        if mask == 0 || mask & !allowed_children(o, h, s.extent) != 0 {
            return Err(invalid(
                "packet",
                format!(
                    "occupancy mask {mask:#04x} at {o:?} (edge {}) outside the tile's band region",
                    2 * h
                ),
            ));
        }
        let mut m = mask as u32;
        if log > 1 {
            while m != 0 {
                let i = m.trailing_zeros();
                m &= m - 1;
                self.node(s, child_origin(o, i, h), log - 1)?;
            }
            return Ok(());
        }
        if self.out.len() + m.count_ones() as usize > self.count {
            return Err(invalid(
                "packet",
                "more coefficients than the packet declares",
            ));
        }
        if self.signs.overrun() || self.reader.overrun() {
            return Err(invalid(
                "packet",
                format!("the payload ends after {} coefficients", self.out.len()),
            ));
        }
        while m != 0 {
            let i = m.trailing_zeros();
            m &= m - 1;
            let cell = child_origin(o, i, 1);
            let (sc, vc) = self.map.leaf_contexts(cell);
            self.reader.refill();
            let (symbol, len) = self.tables.value[vc]
                .decode_window(self.reader.peek())
                .ok_or_else(|| self.not_a_codeword())?;
            self.reader.consume(len);
            // symbol < 64, so at most 49 raw bits: they fit a refilled buffer.
            let q = step_of(symbol, self.reader.get_bits(raw_bits(symbol)));
            let negative = self
                .signs
                .decode_bit(&mut self.sign_models[s.bi * SIGN_CONTEXTS + sc]);
            self.map.insert(cell, negative, q);
            let value = s.quant.signed_value(q, negative)?;
            self.out.push(Coefficient::in_region(
                s.channel, s.band, s.origin, cell, value,
            ));
        }
        Ok(())
    }
}

/// Decodes a fast-coded payload of `count` coefficients.
pub(crate) fn decode(
    header: &Header,
    tile: usize,
    layer: usize,
    count: usize,
    payload: &[u8],
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let tables = header
        .fast_tables
        .as_ref()
        .ok_or_else(|| invalid("header", "fast coder without tables"))?;
    let mut r = super::bytes::ByteReader::new(payload, "packet");
    let prefix_len = r.varint_max(payload.len() as u64, "prefix-coded stream length")? as usize;
    let prefix_coded = r.take(prefix_len)?;
    let signs = r.take(r.remaining())?;
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let mut d = PacketDecoder {
        reader: WordReader::new(prefix_coded),
        signs: RangeDecoder::new(signs),
        sign_models: vec![BitModel::new(); nb * SIGN_CONTEXTS],
        map: CellMap::new(),
        tables: &tables.decoders,
        count,
        // The count is bounded but may still be large for a hostile packet: grow as decoded.
        out: Vec::with_capacity(count.min(super::coefficient::INITIAL_CAPACITY)),
        position_bits: 0,
    };
    let mut present_bits = 0u64;
    for sub in 0..header.substream_count() {
        if header.substreams[sub].is_none() {
            continue;
        }
        present_bits += 1;
        if d.reader.get_bits(1) == 0 {
            continue;
        }
        let bi = sub % nb;
        let band = bands[bi];
        let channel = (sub / nb) as u8;
        let (origin, extent) =
            region_extent(header, tile, band.level, header.geometry.band_dims(band));
        if extent.contains(&0) {
            return Err(invalid(
                "packet",
                "substream present in an empty tile region",
            ));
        }
        let s = Substream {
            bi,
            quant: Quantizer::of(header, sub, layer),
            origin,
            extent,
            channel,
            band,
        };
        d.map.reset(extent);
        d.node(&s, [0; 3], root_log(extent))?;
    }
    if d.out.len() != count {
        return Err(invalid(
            "packet",
            format!(
                "decoded {} coefficients, header of the packet says {count}",
                d.out.len()
            ),
        ));
    }
    if d.reader.overrun() || d.reader.bits_remaining() >= 8 || d.signs.overrun() {
        return Err(invalid(
            "packet",
            "the streams' lengths do not match their coefficients",
        ));
    }
    let total = d.reader.position();
    bd.tag_bits += present_bits as f64;
    bd.position_bits += d.position_bits as f64;
    bd.value_bits += (total - present_bits - d.position_bits) as f64;
    bd.sign_bits += 8.0 * signs.len() as f64;
    Ok(d.out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn step_symbols_cover_every_step_and_decode_back() {
        let mut qs: Vec<u64> = (0..200).collect();
        qs.extend((14..50).map(|b| 1u64 << b));
        qs.extend([u32::MAX as u64, 1_000_000_000_000_000]);
        for q in qs {
            let (symbol, raw) = step_symbol(q);
            assert!(symbol < VALUE_ALPHABET, "q {q}");
            // q < 14 is its own symbol; above, q − 13 has e bits and e − 1 of them follow.
            let expected_raw_bits = if q < DIRECT_STEPS {
                0
            } else {
                u64::BITS - (q - (DIRECT_STEPS - 1)).leading_zeros() - 1
            };
            assert_eq!(raw_bits(symbol), expected_raw_bits, "q {q}");
            assert!(raw < 1 << expected_raw_bits);
            assert_eq!(step_of(symbol, raw), q);
            for table in [0, VALUE_TABLES - 1] {
                let packed = Symbol::step(table, symbol, raw);
                assert_eq!(packed.kind(), Symbol::STEP);
                assert_eq!(
                    (packed.table(), packed.step_symbol(), packed.raw()),
                    (table, symbol, raw)
                );
            }
        }
    }

    #[test]
    fn allowed_children_match_a_brute_force_check() {
        for extent in [[1, 1, 1], [2, 1, 5], [3, 3, 3], [7, 2, 9], [16, 16, 16]] {
            for log in 1..=4u32 {
                let h = 1 << (log - 1);
                let side = 2 * h;
                for ox in (0..extent[0]).step_by(side as usize) {
                    for oy in (0..extent[1]).step_by(side as usize) {
                        for oz in (0..extent[2]).step_by(side as usize) {
                            let o = [ox, oy, oz];
                            let brute = (0..8u32).fold(0u8, |m, i| {
                                let c = child_origin(o, i, h);
                                let inside = (0..3).all(|a| c[a] < extent[a]);
                                m | (inside as u8) << i
                            });
                            assert_eq!(allowed_children(o, h, extent), brute, "{o:?} {h}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn octree_keys_order_children_like_the_decoder() {
        // The decoder visits child i at child_origin(o, i, h) in increasing i; the encoder's
        // key order must be the same.
        let log = 3;
        let mut cells = Vec::new();
        for z in 0..8u32 {
            for y in 0..8u32 {
                for x in 0..8u32 {
                    cells.push([x, y, z]);
                }
            }
        }
        cells.sort_by_key(|&c| octree_key(c, log));
        let mut visit = Vec::new();
        fn walk(o: [u32; 3], log: u32, out: &mut Vec<[u32; 3]>) {
            if log == 0 {
                out.push(o);
                return;
            }
            let h = 1 << (log - 1);
            for i in 0..8 {
                walk(child_origin(o, i, h), log - 1, out);
            }
        }
        walk([0; 3], log, &mut visit);
        assert_eq!(cells, visit);
    }

    #[test]
    fn root_covers_the_region() {
        for (extent, log) in [
            ([1, 1, 1], 1),
            ([2, 1, 1], 1),
            ([3, 1, 1], 2),
            ([1, 1, 64], 6),
        ] {
            assert_eq!(root_log(extent), log, "{extent:?}");
        }
        for extent in [[5, 9, 17], [1, 1, 1000], [129, 2, 2]] {
            let side = 1u32 << root_log(extent);
            let largest = *extent.iter().max().unwrap();
            assert!(largest <= side && side < 2 * largest.max(2), "{extent:?}");
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
                assert_eq!(dense.leaf_contexts(c), want, "round {round} {c:?}");
                assert_eq!(sparse.leaf_contexts(c), want, "round {round} {c:?}");
                // Faces of the node of 2×2×2 cells at the even corner below c.
                let o = c.map(|v| v & !1);
                let touching = truth
                    .keys()
                    .filter(|p| {
                        (0..3).any(|a| {
                            o[a] > 0
                                && p[a] == o[a] - 1
                                && (0..3).all(|b| b == a || (p[b] >= o[b] && p[b] < o[b] + 2))
                        })
                    })
                    .count();
                let table = match touching {
                    0 => 0,
                    1 | 2 => 1,
                    3..=5 => 2,
                    _ => 3,
                };
                assert_eq!(dense.face_table(o), table, "round {round} {o:?}");
                assert_eq!(sparse.face_table(o), table, "round {round} {o:?}");
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
