//! The fast coder ([`super::CoderKind::Fast`]): the sigmap coder's quantization, octree order
//! and neighbour contexts, with positions and magnitudes coded by static tables instead of
//! adaptive binary decisions, so that a packet decodes with about two table look-ups and one
//! adaptive sign decision per coefficient.
//!
//! The sigmap coder spends about seven adaptive binary decisions per coefficient, each a
//! serial dependency through the range decoder and its model; that caps it near 6 M
//! coefficients/s per core. This coder reads one symbol per occupied octree node of 2×2×2
//! cells or more and one per coefficient, for several times that speed at some cost in bytes
//! (measured in BENCHMARKS.md, "Decoding speed").
//!
//! The symbols: per packet, for each substream (channel, band) that has parameters in the
//! header, one raw "present" bit; for a present substream, the dyadic octree over its
//! tile-local band region (the region's power-of-two bounding cube, at least 2 cells on a
//! side). Every occupied node codes the 8-bit mask of its occupied children (child i lies half
//! an edge away by (i & 1, i >> 1 & 1, i >> 2 & 1); children outside the region are never
//! set) and visits them in bit order. A node of 2×2×2 cells uses one of [`LEAF_MASK_TABLES`]
//! tables, chosen by how many coded cells of the substream touch its three lower faces; larger
//! nodes share one table. A node of 2×2×2 cells is followed by its coefficients in bit order:
//! for each, its step symbol from the value table chosen by the mean bit length of its coded
//! lower neighbours' steps (`VALUE_TABLE_OF`), then its sign in the sign stream (context: band and
//! the signs of its three lower neighbours, as the sigmap coder). A step symbol is q itself for
//! q < 14, otherwise 13 + e followed by the e − 1 low bits of q − 13, which has e bits. Steps
//! and reconstruction are the sigmap coder's ([`super::sigmap`]). The tables live in the header
//! ([`FastTables`]), fitted by the encoder to all of a file's packets, as the paper's coder
//! does; packets stay self-contained given the header.
//!
//! The payload, before format version [`RANS_VERSION`]: a varint length, the prefix-coded
//! stream (MSB-first bits: the present bits, the masks' and steps' codewords, the steps' raw
//! bits, in syntax order), then the signs (adaptive binary range coding, reset per packet).
//! From it, the masks and step symbols are coded by rANS with static distributions
//! ([`crate::entropy::rans`], fractional code lengths where a prefix code spends at least a
//! bit on each): a varint length and the rANS stream, a varint length and the raw stream
//! (MSB-first: the present bits and the steps' raw bits, in syntax order), then the signs.
//!
//! From format version [`FAST_CONTEXTS_VERSION`] two more contexts: a node of 4×4×4 cells
//! codes its occupancy mask bit by bit, child by child, each bit a binary rANS symbol from one
//! of [`OCCUPANCY_TABLES`] tables chosen by the coded cells just below the child's lower faces
//! outside the node and by how many of its lower siblings are occupied (`occupancy_table`);
//! a last child whose siblings are all empty is implied. Then its children are visited as
//! before. A step of 14 or more is coded in half octaves: the symbol names the bit length of
//! q − 13 and the bit below its leading one, and one raw bit fewer follows
//! (`step_symbol_halves`). A joint 8-bit mask sees nothing of the node's surroundings, and
//! the cells at the lower faces are where occupancy is told; all eight bits are decoded
//! before any child, so that the decoder branches on no bit while it reads them. (Coding each
//! child's bit just before its subtree, so that its face state counts its earlier siblings'
//! cells, saved a further 0.5 % of MNI's bytes at 1.25 % but cost a quarter of the decoding
//! speed.)

pub mod builtin;
mod cells;
mod decode;
mod encode;

use super::quant::Quantizer;
use super::{FAST_CONTEXTS_VERSION, RANS_VERSION};
use crate::entropy::bits::{BitReader, BitSink};
use crate::entropy::huffman::{HuffmanCode, HuffmanDecoder};
use crate::entropy::rans::RansTable;
use crate::entropy::EntropyError;
use crate::layout::Band;
use std::sync::Arc;

pub(crate) use decode::decode;
pub(crate) use encode::encode_packets;

/// Symbols of an occupancy-mask table (8-bit masks; 0 is never coded).
pub const MASK_ALPHABET: usize = 256;
/// Symbols of a value table: 14 direct steps and 50 escapes by bit length.
pub const VALUE_ALPHABET: usize = 64;
/// Symbols of a value table from [`FAST_CONTEXTS_VERSION`]: 14 direct steps, then q − 13 = 1,
/// then two symbols per bit length 2 to 50 (the bit below the leading one).
pub const HALF_OCTAVE_VALUE_ALPHABET: usize = 113;
/// Binary occupancy tables from [`FAST_CONTEXTS_VERSION`] (`occupancy_table`): four face
/// states by the occupied lower siblings (0 to 3).
pub const OCCUPANCY_TABLES: usize = 16;
/// Mask tables of nodes of 2×2×2 cells, by the coded cells on their lower faces (none, 1–2,
/// 3–5, 6 or more). (Also splitting them by whether the parent band's cell over the node holds
/// a coefficient, as the sigmap coder's contexts do, saved 0.04 % of the decode bench's file
/// and cost 9 % of the decoding speed.)
pub const LEAF_MASK_TABLES: usize = 4;
/// Mask tables: the leaf tables, then one for larger nodes.
pub const MASK_TABLES: usize = LEAF_MASK_TABLES + 1;
/// Value tables: no coded lower neighbour, or 1 + the mean magnitude class of those coded
/// (`VALUE_TABLE_OF`). (Separate tables for the finest and the coarser bands saved 0.15 % on
/// the decode bench's file, less than their header cost on small files.)
pub const VALUE_TABLES: usize = 16;
/// Groups of value tables in rANS-coded files ([`RANS_VERSION`] on): the scaling band, the
/// wavelet bands of level 1, of level 2, and of the coarser levels. (Measured on MNI with the
/// tables fitted to the file, headers included: 1.0–1.2 % fewer bytes at 0.4–4 % of the
/// coefficients than one group; a group per band saved less, its headers cost more.)
pub const VALUE_GROUPS: usize = 4;
/// Value tables of an rANS-coded file: [`VALUE_TABLES`] contexts in each of the
/// [`VALUE_GROUPS`].
pub const RANS_VALUE_TABLES: usize = VALUE_TABLES * VALUE_GROUPS;
/// Sign contexts per band: each of the three lower neighbours is absent, positive or negative.
const SIGN_CONTEXTS: usize = 27;
/// Steps below this are a symbol of their own; larger ones are escaped by bit length.
const DIRECT_STEPS: u64 = 14;
/// Longest prefix code the encoder builds.
const MAX_CODE_LENGTH: u8 = 15;

/// The fast coder's tables, stored in the header and fitted by the encoder to all of a
/// file's packets: prefix codes before format version [`RANS_VERSION`], rANS distributions
/// from it. Shared, so that a clone of the header does not copy them.
#[derive(Debug, Clone)]
pub struct FastTables(Arc<Tables>);

// One per file, behind an `Arc`: the variants' sizes do not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug)]
enum Tables {
    /// Prefix codes with their decoders (built once, not per packet).
    Prefix {
        /// Occupancy masks: [`LEAF_MASK_TABLES`] for nodes of 2×2×2 cells, then larger nodes.
        mask: [HuffmanCode; MASK_TABLES],
        /// Step symbols per value context.
        value: [HuffmanCode; VALUE_TABLES],
        decoders: Decoders,
    },
    /// rANS distributions, the same contexts.
    Rans {
        mask: [RansTable; MASK_TABLES],
        /// [`RANS_VALUE_TABLES`] tables, group by group ([`value_group`]).
        value: Vec<RansTable>,
        /// From [`FAST_CONTEXTS_VERSION`]: [`OCCUPANCY_TABLES`] binary tables, and the value
        /// tables' alphabet is [`HALF_OCTAVE_VALUE_ALPHABET`]. Empty before.
        occupancy: Vec<RansTable>,
        /// From [`FAST_CONTEXTS_VERSION`]: bit t set where the header's table t (header
        /// order: masks, occupancy, values) is the built-in one ([`builtin`]), named rather
        /// than described.
        builtin: u128,
    },
}

impl PartialEq for FastTables {
    fn eq(&self, other: &FastTables) -> bool {
        match (&*self.0, &*other.0) {
            (
                Tables::Prefix { mask, value, .. },
                Tables::Prefix {
                    mask: m, value: v, ..
                },
            ) => mask == m && value == v,
            (
                Tables::Rans {
                    mask,
                    value,
                    occupancy,
                    builtin,
                },
                Tables::Rans {
                    mask: m,
                    value: v,
                    occupancy: o,
                    builtin: b,
                },
            ) => mask == m && value == v && occupancy == o && builtin == b,
            _ => false,
        }
    }
}

impl FastTables {
    fn prefix(mask: [HuffmanCode; MASK_TABLES], value: [HuffmanCode; VALUE_TABLES]) -> FastTables {
        let decoders = Decoders {
            mask: std::array::from_fn(|t| HuffmanDecoder::new(&mask[t])),
            value: std::array::from_fn(|t| HuffmanDecoder::new(&value[t])),
        };
        FastTables(Arc::new(Tables::Prefix {
            mask,
            value,
            decoders,
        }))
    }

    fn rans(
        mask: [RansTable; MASK_TABLES],
        value: Vec<RansTable>,
        occupancy: Vec<RansTable>,
        builtin: u128,
    ) -> FastTables {
        debug_assert_eq!(value.len(), RANS_VALUE_TABLES);
        debug_assert!(occupancy.is_empty() || occupancy.len() == OCCUPANCY_TABLES);
        debug_assert!(builtin == 0 || !occupancy.is_empty());
        FastTables(Arc::new(Tables::Rans {
            mask,
            value,
            occupancy,
            builtin,
        }))
    }

    /// How many of the header's tables are the built-in ones ([`builtin`]).
    pub fn builtin_count(&self) -> u32 {
        match &*self.0 {
            Tables::Rans { builtin, .. } => builtin.count_ones(),
            Tables::Prefix { .. } => 0,
        }
    }

    /// Whether these are rANS distributions (format version [`RANS_VERSION`] and later).
    pub fn is_rans(&self) -> bool {
        matches!(*self.0, Tables::Rans { .. })
    }

    /// Whether these are version [`FAST_CONTEXTS_VERSION`]'s tables (occupancy tables, value
    /// tables in half octaves).
    pub fn has_occupancy_tables(&self) -> bool {
        matches!(&*self.0, Tables::Rans { occupancy, .. } if !occupancy.is_empty())
    }

    /// Whether packets coded with these tables decode as a file of `version`: prefix codes
    /// before [`RANS_VERSION`], rANS without occupancy tables up to the version before
    /// [`FAST_CONTEXTS_VERSION`], with them from it.
    pub fn decode_as(&self, version: u16) -> bool {
        self.is_rans() == (version >= RANS_VERSION)
            && self.has_occupancy_tables() == (version >= FAST_CONTEXTS_VERSION)
    }

    /// Writes every table: code lengths, or for rANS a bit saying whether the table is used
    /// and the used tables' levels.
    pub fn write(&self, sink: &mut impl BitSink) {
        match &*self.0 {
            Tables::Prefix { mask, value, .. } => {
                for code in mask.iter().chain(value) {
                    code.write_lengths(sink);
                }
            }
            Tables::Rans {
                mask,
                value,
                occupancy,
                builtin,
            } => {
                // From FAST_CONTEXTS_VERSION (occupancy tables present) a used table's bit is
                // followed by one saying whether it is the built-in one.
                let named = !occupancy.is_empty();
                for (t, table) in mask.iter().chain(occupancy).chain(value).enumerate() {
                    sink.put_bit(!table.is_empty());
                    if table.is_empty() {
                        continue;
                    }
                    let is_builtin = builtin >> t & 1 != 0;
                    if named {
                        sink.put_bit(is_builtin);
                    }
                    if !is_builtin {
                        table.write_levels(sink);
                    }
                }
            }
        }
    }

    /// Reads tables written by [`FastTables::write`] for a file of `version`, validating
    /// every table.
    pub fn read(reader: &mut BitReader, version: u16) -> Result<FastTables, EntropyError> {
        if version >= RANS_VERSION {
            let contexts = version >= FAST_CONTEXTS_VERSION;
            let mut builtin_bits = 0u128;
            let mut t = 0;
            let mut read = |alphabet: usize| -> Result<RansTable, EntropyError> {
                let at = t;
                t += 1;
                if !reader.get_bit()? {
                    return RansTable::from_levels(&[], 1);
                }
                if contexts && reader.get_bit()? {
                    builtin_bits |= 1 << at;
                    return builtin::shipped()
                        .get(at)
                        .cloned()
                        .flatten()
                        .ok_or(EntropyError::NoBuiltinTable(at));
                }
                RansTable::read_levels(reader, alphabet)
            };
            let mut mask = Vec::with_capacity(MASK_TABLES);
            for _ in 0..MASK_TABLES {
                mask.push(read(MASK_ALPHABET)?);
            }
            let mut occupancy = Vec::new();
            if contexts {
                for _ in 0..OCCUPANCY_TABLES {
                    occupancy.push(read(2)?);
                }
            }
            let alphabet = if contexts {
                HALF_OCTAVE_VALUE_ALPHABET
            } else {
                VALUE_ALPHABET
            };
            let mut value = Vec::with_capacity(RANS_VALUE_TABLES);
            for _ in 0..RANS_VALUE_TABLES {
                value.push(read(alphabet)?);
            }
            return Ok(FastTables::rans(
                mask.try_into().expect("MASK_TABLES tables"),
                value,
                occupancy,
                builtin_bits,
            ));
        }
        let mut mask = Vec::with_capacity(MASK_TABLES);
        for _ in 0..MASK_TABLES {
            mask.push(HuffmanCode::read_lengths(reader, MASK_ALPHABET)?);
        }
        let mut value = Vec::with_capacity(VALUE_TABLES);
        for _ in 0..VALUE_TABLES {
            value.push(HuffmanCode::read_lengths(reader, VALUE_ALPHABET)?);
        }
        Ok(FastTables::prefix(
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

/// The largest sum of three neighbours' magnitude classes ([`bit_length_class`]).
const MAX_CLASS_SUM: usize = 3 * 31;

/// The value table of a coefficient by its present lower neighbours' count `n` (first index)
/// and summed magnitude classes (second): 0 without neighbours, else 1 + their rounded mean
/// class (at most `VALUE_TABLES` − 2). Looked up rather than computed by cases: the count is
/// as unpredictable as the data.
static VALUE_TABLE_OF: [[u8; MAX_CLASS_SUM + 1]; 4] = {
    let mut t = [[0u8; MAX_CLASS_SUM + 1]; 4];
    let mut n = 1;
    while n < 4 {
        let mut sum = 0;
        while sum <= MAX_CLASS_SUM {
            let mean = match n {
                1 => sum,
                2 => (sum + 1) >> 1,
                _ => (2 * sum + 3) / 6,
            };
            let mean = if mean < VALUE_TABLES - 2 {
                mean
            } else {
                VALUE_TABLES - 2
            };
            t[n][sum] = (1 + mean) as u8;
            sum += 1;
        }
        n += 1;
    }
    t
};

/// The group of a band's value tables in an rANS-coded file ([`VALUE_GROUPS`]).
fn value_group(band: Band) -> usize {
    if band.kind == 0 {
        0
    } else {
        (band.level as usize).clamp(1, VALUE_GROUPS - 1)
    }
}

/// The first of a band's value tables ([`Substream::value_base`]): its group's in an
/// rANS-coded file, 0 in a prefix-coded one (one group).
fn value_base(header: &super::Header, band: Band) -> usize {
    if header.version >= RANS_VERSION {
        VALUE_TABLES * value_group(band)
    } else {
        0
    }
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
const fn raw_bits(symbol: usize) -> u32 {
    (symbol as u32).saturating_sub(DIRECT_STEPS as u32)
}

/// The step symbol of q in half octaves ([`FAST_CONTEXTS_VERSION`] on) and the raw bits that
/// follow it (as many as [`raw_bits_halves`] says): q < 14 is its own symbol; above, r = q − 13
/// of e bits is symbol 14 for r = 1, else 15 + 2(e − 2) + the bit below r's leading one,
/// followed by r's e − 2 low bits. q ≤ 10^15 (the quantizer's bound) gives e ≤ 50, a symbol
/// below [`HALF_OCTAVE_VALUE_ALPHABET`].
fn step_symbol_halves(q: u64) -> (usize, u64) {
    if q < DIRECT_STEPS {
        return (q as usize, 0);
    }
    let r = q - DIRECT_STEPS + 1;
    let e = u64::BITS - r.leading_zeros();
    if e == 1 {
        return (DIRECT_STEPS as usize, 0);
    }
    let second = (r >> (e - 2)) & 1;
    (
        DIRECT_STEPS as usize + 1 + 2 * (e as usize - 2) + second as usize,
        r & ((1u64 << (e - 2)) - 1),
    )
}

/// How many raw bits follow a step symbol in half octaves.
#[inline(always)]
const fn raw_bits_halves(symbol: usize) -> u32 {
    ((symbol as u32).saturating_sub(DIRECT_STEPS as u32 + 1)) / 2
}

/// The step q of a half-octave step symbol and its raw bits: the inverse of
/// [`step_symbol_halves`].
const fn step_of_halves(symbol: usize, raw: u64) -> u64 {
    let s = symbol as u64;
    if s <= DIRECT_STEPS {
        return s;
    }
    let low = raw_bits_halves(symbol);
    let second = (s - DIRECT_STEPS - 1) & 1;
    ((2 | second) << low | raw) + DIRECT_STEPS - 1
}

/// A step symbol's smallest step and raw bit count, per symbol of the value alphabet, so
/// that the decoder reads a step as `base + raw` without a branch on the symbol (small and
/// escaped steps are mixed as the data are). Symbols past an alphabet never decode.
pub(super) struct StepTable {
    base: [u64; STEP_TABLE_SYMBOLS],
    raw_bits: [u8; STEP_TABLE_SYMBOLS],
}

/// Entries of a [`StepTable`]: a power of two above the larger alphabet,
/// [`HALF_OCTAVE_VALUE_ALPHABET`], so that a symbol indexes it masked, without a bounds check
/// (the tables' own alphabets keep symbols inside).
const STEP_TABLE_SYMBOLS: usize = 128;
const _: () = assert!(HALF_OCTAVE_VALUE_ALPHABET <= STEP_TABLE_SYMBOLS);

impl StepTable {
    const fn new(halves: bool) -> StepTable {
        let mut base = [0u64; STEP_TABLE_SYMBOLS];
        let mut raw = [0u8; STEP_TABLE_SYMBOLS];
        let mut s = 0;
        while s < STEP_TABLE_SYMBOLS {
            if halves && s < HALF_OCTAVE_VALUE_ALPHABET {
                base[s] = step_of_halves(s, 0);
                raw[s] = raw_bits_halves(s) as u8;
            } else if s < VALUE_ALPHABET {
                base[s] = step_of(s, 0);
                raw[s] = raw_bits(s) as u8;
            }
            s += 1;
        }
        StepTable {
            base,
            raw_bits: raw,
        }
    }

    /// The smallest step of `symbol` and how many raw bits follow it.
    #[inline(always)]
    pub(super) fn get(&self, symbol: usize) -> (u64, u32) {
        let s = symbol & (STEP_TABLE_SYMBOLS - 1);
        (self.base[s], self.raw_bits[s] as u32)
    }
}

/// Version 14's steps ([`step_symbol`]).
pub(super) static OCTAVE_STEPS: StepTable = StepTable::new(false);
/// Steps in half octaves ([`step_symbol_halves`]).
pub(super) static HALF_OCTAVE_STEPS: StepTable = StepTable::new(true);

/// The occupancy table of a child of a node of 4×4×4 cells ([`FAST_CONTEXTS_VERSION`] on): by
/// the child's face state outside the node (0–3, `CellMap::node4_face_states`) and how many
/// of its lower neighbours among its siblings (0–3) are occupied.
#[inline(always)]
fn occupancy_table(face: usize, occupied_lower_siblings: u32) -> usize {
    debug_assert!(face < 4 && occupied_lower_siblings < 4);
    4 * occupied_lower_siblings as usize + face
}

/// How many of child `i`'s lower neighbours among its siblings (child i with one of its set
/// bits cleared) are set in `mask`.
#[inline(always)]
fn occupied_lower_siblings(i: u32, mask: u32) -> u32 {
    // Looked up: a load in place of a dozen instructions for every occupancy bit.
    static TABLE: [[u8; 256]; 8] = {
        let mut t = [[0u8; 256]; 8];
        let mut i = 0;
        while i < 8 {
            let mut mask = 0;
            while mask < 256 {
                t[i][mask] = ((i & 1 & (mask >> (i ^ 1)))
                    + (i >> 1 & 1 & (mask >> (i ^ 2)))
                    + (i >> 2 & 1 & (mask >> (i ^ 4)))) as u8;
                mask += 1;
            }
            i += 1;
        }
        t
    };
    TABLE[(i & 7) as usize][(mask & 255) as usize] as u32
}

/// Whether a node of edge 2^`log` codes its children's occupancy bit by bit: nodes of 4×4×4
/// cells from [`FAST_CONTEXTS_VERSION`] ([`Substream::sequential`]).
#[inline(always)]
fn masks_bit_by_bit(sequential: bool, log: u32) -> bool {
    sequential && log == 2
}

/// The step q of a step symbol and its raw bits: the inverse of [`step_symbol`].
#[inline(always)]
const fn step_of(symbol: usize, raw: u64) -> u64 {
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

/// log2 of the root node's edge: the region's power-of-two bounding cube, an edge of at
/// least 2 (a log of at least 1: a root of 2×2×2 cells for a region of at most 2 a side).
fn root_log(extent: [u32; 3]) -> u32 {
    let side = extent.iter().copied().max().unwrap_or(1).max(2);
    u32::BITS - (side - 1).leading_zeros()
}

/// The substream being coded or decoded.
struct Substream {
    bi: usize,
    /// Whether the file is of [`FAST_CONTEXTS_VERSION`] or later (masks of nodes of 4×4×4
    /// cells bit by bit, steps in half octaves).
    sequential: bool,
    /// The first of this substream's value tables: its group's ([`value_group`]) in an
    /// rANS-coded file, 0 otherwise.
    value_base: usize,
    quant: Quantizer,
    origin: [u32; 3],
    extent: [u32; 3],
    channel: u8,
    band: Band,
}

/// The decoders of a file's tables.
#[derive(Debug)]
struct Decoders {
    mask: [HuffmanDecoder; MASK_TABLES],
    value: [HuffmanDecoder; VALUE_TABLES],
}

#[cfg(test)]
mod tests {
    use super::*;

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

    /// A version 15 table set with `tables` at their header indices (masks, occupancy,
    /// values) and every other table empty.
    fn table_set(tables: &[(usize, RansTable)], builtin: u128) -> FastTables {
        let at = |t: usize| {
            tables.iter().find(|(i, _)| *i == t).map_or_else(
                || RansTable::from_levels(&[], 1).unwrap(),
                |(_, x)| x.clone(),
            )
        };
        FastTables::rans(
            std::array::from_fn(at),
            (0..RANS_VALUE_TABLES)
                .map(|v| at(MASK_TABLES + OCCUPANCY_TABLES + v))
                .collect(),
            (0..OCCUPANCY_TABLES).map(|o| at(MASK_TABLES + o)).collect(),
            builtin,
        )
    }

    #[test]
    fn tables_named_built_in_read_back_and_unknown_ones_are_refused() {
        use crate::entropy::bits::BitWriter;
        let shipped = builtin::shipped();
        let named = shipped
            .iter()
            .position(Option::is_some)
            .expect("a built-in table");
        let own = MASK_TABLES + OCCUPANCY_TABLES; // the first value table
        let own_table = RansTable::from_counts(&[5, 1, 0, 2]);
        let set = table_set(
            &[(named, shipped[named].clone().unwrap()), (own, own_table)],
            1 << named,
        );
        assert_eq!(set.builtin_count(), 1);
        let mut w = BitWriter::new();
        set.write(&mut w);
        let bytes = w.finish();
        let read = FastTables::read(&mut BitReader::new(&bytes), FAST_CONTEXTS_VERSION).unwrap();
        assert_eq!(read, set);
        // A built-in table costs two bits in the header, whatever its size.
        let mut w = BitWriter::new();
        table_set(&[(named, shipped[named].clone().unwrap())], 0).write(&mut w);
        assert!(w.finish().len() > bytes.len());
        // A header naming a table this build holds none of is refused.
        if let Some(missing) = shipped.iter().position(Option::is_none) {
            let set = table_set(&[(missing, RansTable::from_counts(&[1, 1]))], 1 << missing);
            let mut w = BitWriter::new();
            set.write(&mut w);
            let bytes = w.finish();
            let e = FastTables::read(&mut BitReader::new(&bytes), FAST_CONTEXTS_VERSION);
            assert_eq!(e.unwrap_err(), EntropyError::NoBuiltinTable(missing));
        }
    }

    #[test]
    fn occupied_lower_siblings_count_the_set_neighbours_below() {
        for mask in 0..=255u32 {
            for i in 0..8u32 {
                let brute = (0..3)
                    .filter(|a| i >> a & 1 == 1 && mask >> (i ^ (1 << a)) & 1 == 1)
                    .count() as u32;
                assert_eq!(occupied_lower_siblings(i, mask), brute, "{mask:#x} {i}");
            }
        }
        // The tables cover every face state and count, each once.
        let mut seen = [false; OCCUPANCY_TABLES];
        for face in 0..4 {
            for n in 0..4 {
                let t = occupancy_table(face, n);
                assert!(!seen[t]);
                seen[t] = true;
            }
        }
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
}
