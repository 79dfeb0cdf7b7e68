//! The fast coder's decoder: reads a payload's symbols (a prefix-coded stream, or an rANS
//! stream and a raw stream, by format version) with the header's tables and its sign stream,
//! walking each present substream's octree, and checks that the streams hold exactly the
//! coefficients the packet declares.

use super::cells::{cell_entry, CellMap};
use super::{
    allowed_children, child_origin, masks_bit_by_bit, occupancy_table, occupied_lower_siblings,
    raw_bits, root_log, step_of, value_base, Decoders, StepTable, Substream, Tables,
    HALF_OCTAVE_STEPS, LEAF_MASK_TABLES, MASK_TABLES, OCCUPANCY_TABLES, OCTAVE_STEPS,
    SIGN_CONTEXTS,
};
use crate::entropy::bits::WordReader;
use crate::entropy::huffman::HuffmanDecoder;
use crate::entropy::range::{BitModel, RangeDecoder};
use crate::entropy::rans::{RansDecoder, RansTable};
use crate::format::coefficient::PacketFraming;
use crate::format::coefficient::{region_extent, Coefficient, SizeBreakdown};
use crate::format::quant::Quantizer;
use crate::format::{invalid, FormatError, Header, FAST_CONTEXTS_VERSION};

/// Where a packet's present bits, masks and steps come from: one implementation per payload
/// layout, so that the octree walk is written once and compiled for each.
trait SymbolSource {
    /// The next present bit.
    fn present(&mut self) -> bool;
    /// The next occupancy mask, from mask table `table`.
    fn mask(&mut self, table: usize) -> Result<u8, FormatError>;
    /// The next step, from value table `table` (its symbol, then its raw bits).
    fn step(&mut self, table: usize) -> Result<u64, FormatError>;
    /// The next child's occupancy, from occupancy table `table`.
    fn occupied(&mut self, table: usize) -> Result<bool, FormatError>;
    /// Whether a read went past the end of a stream.
    fn overrun(&self) -> bool;
    /// If the streams ended with their last symbol: their bits, and of those the masks'.
    fn end(self) -> Option<(f64, f64)>;
}

/// The prefix-coded stream of format versions before [`crate::format::RANS_VERSION`].
struct PrefixSource<'a> {
    tables: &'a Decoders,
    reader: WordReader<'a>,
    position_bits: u64,
}

impl PrefixSource<'_> {
    #[cold]
    fn not_a_codeword(&self) -> FormatError {
        invalid(
            "packet",
            format!("no codeword at bit {}", self.reader.position()),
        )
    }

    /// The next codeword's symbol and length.
    #[inline(always)]
    fn codeword(&mut self, code: &HuffmanDecoder) -> Result<(usize, u32), FormatError> {
        self.reader.refill();
        let (symbol, len) = code
            .decode_window(self.reader.peek())
            .ok_or_else(|| self.not_a_codeword())?;
        self.reader.consume(len);
        Ok((symbol, len))
    }
}

impl SymbolSource for PrefixSource<'_> {
    #[inline(always)]
    fn present(&mut self) -> bool {
        self.reader.get_bits(1) != 0
    }

    #[inline(always)]
    fn mask(&mut self, table: usize) -> Result<u8, FormatError> {
        let (mask, len) = self.codeword(&self.tables.mask[table])?;
        self.position_bits += len as u64;
        Ok(mask as u8)
    }

    #[inline(always)]
    fn step(&mut self, table: usize) -> Result<u64, FormatError> {
        let (symbol, _) = self.codeword(&self.tables.value[table])?;
        // symbol < 64, so at most 49 raw bits: they fit a refilled buffer.
        Ok(step_of(symbol, self.reader.get_bits(raw_bits(symbol))))
    }

    fn occupied(&mut self, _table: usize) -> Result<bool, FormatError> {
        // Prefix-coded files predate the occupancy symbols.
        Err(invalid(
            "packet",
            "an occupancy symbol in a prefix-coded file",
        ))
    }

    fn overrun(&self) -> bool {
        self.reader.overrun()
    }

    fn end(self) -> Option<(f64, f64)> {
        let ended = !self.reader.overrun() && self.reader.bits_remaining() < 8;
        ended.then(|| (self.reader.position() as f64, self.position_bits as f64))
    }
}

/// The rANS stream and the raw stream of format version [`crate::format::RANS_VERSION`] on.
struct RansSource<'a> {
    mask: &'a [RansTable; MASK_TABLES],
    value: &'a [RansTable],
    /// The occupancy tables' frequencies of 0 (binary tables need no more to decode,
    /// [`RansDecoder::decode_binary`]) and costs of 0 and 1 in 1/256 bits; the tables left
    /// empty have their bit set in `occupancy_empty` (all of them before
    /// [`crate::format::FAST_CONTEXTS_VERSION`]).
    occupancy_f0: [u32; OCCUPANCY_TABLES],
    occupancy_cost: [[u32; 2]; OCCUPANCY_TABLES],
    occupancy_empty: u32,
    /// The steps of the value symbols: in octaves, or in half octaves
    /// ([`crate::format::FAST_CONTEXTS_VERSION`] on).
    steps: &'static StepTable,
    ans: RansDecoder<'a>,
    raw: WordReader<'a>,
    ans_bytes: usize,
    raw_bytes: usize,
    /// The masks' cost in 1/256 bits.
    position_q8: u64,
}

#[cold]
fn empty_table(what: &str, table: usize) -> FormatError {
    invalid(
        "packet",
        format!("a symbol from {what} table {table}, which the header leaves empty"),
    )
}

impl SymbolSource for RansSource<'_> {
    #[inline(always)]
    fn present(&mut self) -> bool {
        self.raw.get_bits(1) != 0
    }

    #[inline(always)]
    fn mask(&mut self, table: usize) -> Result<u8, FormatError> {
        let t = &self.mask[table];
        let mask = self
            .ans
            .decode(t)
            .ok_or_else(|| empty_table("mask", table))?;
        self.position_q8 += t.cost_q8(mask) as u64;
        Ok(mask as u8)
    }

    #[inline(always)]
    fn step(&mut self, table: usize) -> Result<u64, FormatError> {
        let symbol = self
            .ans
            .decode(&self.value[table])
            .ok_or_else(|| empty_table("value", table))?;
        // A value table has at most 64 symbols (49 raw bits), or 113 in half octaves (48).
        let (base, raw_bits) = self.steps.get(symbol);
        self.raw.refill();
        Ok(base + self.raw.take_refilled(raw_bits))
    }

    #[inline(always)]
    fn occupied(&mut self, table: usize) -> Result<bool, FormatError> {
        let table = table % OCCUPANCY_TABLES;
        if self.occupancy_empty >> table & 1 != 0 {
            return Err(empty_table("occupancy", table));
        }
        let bit = self.ans.decode_binary(self.occupancy_f0[table]);
        self.position_q8 += self.occupancy_cost[table][bit as usize] as u64;
        Ok(bit)
    }

    fn overrun(&self) -> bool {
        self.ans.overrun() || self.raw.overrun()
    }

    fn end(self) -> Option<(f64, f64)> {
        let ended = self.ans.is_complete() && !self.raw.overrun() && self.raw.bits_remaining() < 8;
        ended.then(|| {
            (
                8.0 * (self.ans_bytes + self.raw_bytes) as f64,
                self.position_q8 as f64 / 256.0,
            )
        })
    }
}

/// A packet being decoded.
struct PacketDecoder<'a, S> {
    source: S,
    signs: RangeDecoder<'a>,
    sign_models: Vec<BitModel>,
    map: CellMap,
    count: usize,
    out: Vec<Coefficient>,
}

impl<S: SymbolSource> PacketDecoder<'_, S> {
    /// Decodes the node of edge 2^`log` at `o` (`log` ≥ 2; a root of 2×2×2 cells is a
    /// [`PacketDecoder::leaf`]), known to be occupied.
    fn node(&mut self, s: &Substream, o: [u32; 3], log: u32) -> Result<(), FormatError> {
        let h = 1u32 << (log - 1);
        let mask = if masks_bit_by_bit(s.sequential, log) {
            self.mask_bit_by_bit(s, o)?
        } else {
            let mask = self.source.mask(LEAF_MASK_TABLES)?;
            check_mask(mask, o, h, s.extent)?;
            mask
        };
        let mut m = mask as u32;
        // The nodes of 2×2×2 cells below a node of 4×4×4 are decoded in its loop rather than
        // by a call each (their count is most of the nodes').
        if log == 2 {
            while m != 0 {
                let i = m.trailing_zeros();
                m &= m - 1;
                self.leaf(s, child_origin(o, i, h))?;
            }
        } else {
            while m != 0 {
                let i = m.trailing_zeros();
                m &= m - 1;
                self.node(s, child_origin(o, i, h), log - 1)?;
            }
        }
        Ok(())
    }

    /// Decodes the node of 2×2×2 cells at `o`, known to be occupied: its mask, then each
    /// present cell's step and sign.
    #[inline(always)]
    fn leaf(&mut self, s: &Substream, o: [u32; 3]) -> Result<(), FormatError> {
        // The node finds the cells around it once, for its mask's table and its children's
        // contexts (a directory map; a hashed one looks each up).
        let mut leaf = self.map.leaf_node(o);
        let table = match &leaf {
            Some(leaf) => leaf.face_table(),
            None => self.map.face_table(o),
        };
        let mask = self.source.mask(table)?;
        check_mask(mask, o, 1, s.extent)?;
        let mut m = mask as u32;
        if self.out.len() + m.count_ones() as usize > self.count {
            return Err(invalid(
                "packet",
                "more coefficients than the packet declares",
            ));
        }
        if self.signs.overrun() || self.source.overrun() {
            return Err(invalid(
                "packet",
                format!("the payload ends after {} coefficients", self.out.len()),
            ));
        }
        let models = &mut self.sign_models[s.bi * SIGN_CONTEXTS..][..SIGN_CONTEXTS];
        while m != 0 {
            let i = m.trailing_zeros();
            m &= m - 1;
            let cell = child_origin(o, i, 1);
            let (sc, vc, index) = match &leaf {
                Some(leaf) => {
                    let (sc, vc, index) = leaf.contexts(i);
                    (sc, vc, Some(index))
                }
                None => {
                    let (sc, vc) = self.map.leaf_contexts(cell);
                    (sc, vc, None)
                }
            };
            let q = self.source.step(s.value_base + vc)?;
            let negative = self.signs.decode_bit(&mut models[sc]);
            match (&mut leaf, index) {
                (Some(leaf), Some(index)) => {
                    let v = cell_entry(negative, q);
                    leaf.set(i, v);
                    self.map.set_at(index, v);
                }
                _ => self.map.insert(cell, negative, q),
            }
            let value = s.quant.signed_value(q, negative)?;
            self.out.push(Coefficient::in_region(
                s.channel, s.band, s.origin, cell, value,
            ));
        }
        Ok(())
    }

    /// The occupancy mask of the node of 4×4×4 cells at `o`, bit by bit: each allowed
    /// child's bit from its occupancy table, but for a last child whose siblings are all
    /// empty (implied). Never empty, never outside the region.
    fn mask_bit_by_bit(&mut self, s: &Substream, o: [u32; 3]) -> Result<u8, FormatError> {
        let faces = self.map.node4_face_states(o);
        let mut m = allowed_children(o, 2, s.extent) as u32;
        let mut mask = 0u32;
        while m != 0 {
            let i = m.trailing_zeros();
            m &= m - 1;
            let occupied = if mask != 0 || m != 0 {
                let table = occupancy_table(faces[i as usize], occupied_lower_siblings(i, mask));
                self.source.occupied(table)?
            } else {
                true
            };
            mask |= (occupied as u32) << i;
        }
        Ok(mask as u8)
    }
}

/// Refuses an occupancy mask that is empty or names a child outside the region, of the node
/// of children of edge `h` at `o`.
#[inline(always)]
fn check_mask(mask: u8, o: [u32; 3], h: u32, extent: [u32; 3]) -> Result<(), FormatError> {
    if mask == 0 || mask & !allowed_children(o, h, extent) != 0 {
        return Err(mask_outside_region(mask, o, h));
    }
    Ok(())
}

#[cold]
fn mask_outside_region(mask: u8, o: [u32; 3], h: u32) -> FormatError {
    invalid(
        "packet",
        format!(
            "occupancy mask {mask:#04x} at {o:?} (edge {}) outside the tile's band region",
            2 * h
        ),
    )
}

/// Decodes a fast-coded payload of `packet.count` coefficients (a
/// [`crate::format::packet::PayloadDecoder`]).
pub(crate) fn decode(
    header: &Header,
    packet: &PacketFraming<'_>,
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let payload = packet.payload;
    let tables = header
        .fast_tables
        .as_ref()
        .ok_or_else(|| invalid("header", "fast coder without tables"))?;
    let mut r = super::super::bytes::ByteReader::new(payload, "packet");
    let first_len = r.varint_max(payload.len() as u64, "symbol stream length")? as usize;
    let first = r.take(first_len)?;
    match &*tables.0 {
        Tables::Prefix { decoders, .. } => {
            let signs = r.take(r.remaining())?;
            let source = PrefixSource {
                tables: decoders,
                reader: WordReader::new(first),
                position_bits: 0,
            };
            decode_with(header, packet, source, signs, bd)
        }
        Tables::Rans {
            mask,
            value,
            occupancy,
            ..
        } => {
            let raw_len = r.varint_max(r.remaining() as u64, "raw stream length")? as usize;
            let raw = r.take(raw_len)?;
            let signs = r.take(r.remaining())?;
            let used_occupancy = |t: usize| occupancy.get(t).filter(|t| !t.is_empty());
            let source = RansSource {
                mask,
                value,
                occupancy_f0: std::array::from_fn(|t| {
                    used_occupancy(t).map_or(0, |t| t.frequency(0))
                }),
                occupancy_cost: std::array::from_fn(|t| {
                    used_occupancy(t).map_or([0; 2], |t| [t.cost_q8(0), t.cost_q8(1)])
                }),
                occupancy_empty: (0..OCCUPANCY_TABLES)
                    .filter(|&t| used_occupancy(t).is_none())
                    .fold(0, |m, t| m | 1 << t),
                steps: if occupancy.is_empty() {
                    &OCTAVE_STEPS
                } else {
                    &HALF_OCTAVE_STEPS
                },
                ans: RansDecoder::new(first).map_err(|e| invalid("packet", e.to_string()))?,
                raw: WordReader::new(raw),
                ans_bytes: first.len(),
                raw_bytes: raw.len(),
                position_q8: 0,
            };
            decode_with(header, packet, source, signs, bd)
        }
    }
}

/// Walks a packet's substreams with its symbols from `source` and its signs from `signs`.
fn decode_with<S: SymbolSource>(
    header: &Header,
    packet: &PacketFraming<'_>,
    source: S,
    signs: &[u8],
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let (tile, layer, count) = (packet.tile, packet.layer, packet.count);
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let mut d = PacketDecoder {
        source,
        signs: RangeDecoder::new(signs),
        sign_models: vec![BitModel::new(); nb * SIGN_CONTEXTS],
        map: CellMap::new(),
        count,
        // The count is bounded but may still be large for a hostile packet: grow as decoded.
        out: Vec::with_capacity(count.min(super::super::coefficient::INITIAL_CAPACITY)),
    };
    let mut present_bits = 0u64;
    for sub in 0..header.substream_count() {
        if header.substreams[sub].is_none() {
            continue;
        }
        present_bits += 1;
        if !d.source.present() {
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
            sequential: header.version >= FAST_CONTEXTS_VERSION,
            value_base: value_base(header, band),
            quant: Quantizer::of(header, sub, layer),
            origin,
            extent,
            channel,
            band,
        };
        d.map.reset(extent);
        match root_log(extent) {
            1 => d.leaf(&s, [0; 3])?,
            log => d.node(&s, [0; 3], log)?,
        }
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
    let ended = if d.signs.overrun() {
        None
    } else {
        d.source.end()
    };
    let Some((total, position)) = ended else {
        return Err(invalid(
            "packet",
            "the streams' lengths do not match their coefficients",
        ));
    };
    bd.tag_bits += present_bits as f64;
    bd.position_bits += position;
    bd.value_bits += total - present_bits as f64 - position;
    bd.sign_bits += 8.0 * signs.len() as f64;
    Ok(d.out)
}
