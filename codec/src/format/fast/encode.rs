//! The fast coder's encoder: symbolizes every packet (octree masks, step symbols, the sign
//! stream), fits the header's tables (prefix codes, or rANS distributions) to all of a file's
//! symbols, then writes each payload.

use super::builtin;
use super::cells::{cell_entry, CellMap};
use super::{
    allowed_children, child_origin, masks_bit_by_bit, occupancy_table, occupied_lower_siblings,
    raw_bits, raw_bits_halves, root_log, step_symbol, step_symbol_halves, value_base, FastTables,
    Substream, Tables, HALF_OCTAVE_VALUE_ALPHABET, LEAF_MASK_TABLES, MASK_ALPHABET, MASK_TABLES,
    MAX_CODE_LENGTH, OCCUPANCY_TABLES, RANS_VALUE_TABLES, SIGN_CONTEXTS, VALUE_ALPHABET,
    VALUE_TABLES,
};
use crate::entropy::bits::{BitSink, BitWriter};
use crate::entropy::huffman::HuffmanCode;
use crate::entropy::range::{BitModel, RangeEncoder};
use crate::entropy::rans::{RansEncoder, RansTable};
use crate::format::bytes::ByteWriter;
use crate::format::coefficient::{region_extent, Coefficient, PacketInput, SizeBreakdown};
use crate::format::morton;
use crate::format::quant::Quantizer;
use crate::format::Header;
use crate::format::{FAST_CONTEXTS_VERSION, RANS_VERSION};

/// One element of a packet's syntax, before the tables are fitted, packed in 8 bytes (the
/// encoder holds a whole file's, one or two per coefficient): bits 0–1 the kind (present bit,
/// mask, step, occupancy), then the present bit, or the table in bits 2–7 and the mask (or
/// the occupancy bit) in bits 8–15, or the table in bits 2–7, the step symbol in bits 8–14 and
/// its raw bits from bit 15 (at most 49 of them, as many as [`raw_bits`] or
/// [`raw_bits_halves`] says).
#[derive(Debug, Clone, Copy)]
struct Symbol(u64);

const _: () = assert!(
    MASK_TABLES <= 64
        && RANS_VALUE_TABLES <= 64
        && OCCUPANCY_TABLES <= 64
        && VALUE_ALPHABET <= 128
        && HALF_OCTAVE_VALUE_ALPHABET <= 128
);

impl Symbol {
    const PRESENT: u64 = 0;
    const MASK: u64 = 1;
    const STEP: u64 = 2;
    const OCCUPANCY: u64 = 3;

    fn present(present: bool) -> Symbol {
        Symbol(Self::PRESENT | (present as u64) << 2)
    }
    fn mask(table: usize, mask: u8) -> Symbol {
        Symbol(Self::MASK | (table as u64) << 2 | (mask as u64) << 8)
    }
    fn step(table: usize, symbol: usize, raw: u64) -> Symbol {
        // At most 49 raw bits (version 14's largest step symbol; 48 in half octaves).
        debug_assert!(raw < 1 << 49 && symbol < 128);
        Symbol(Self::STEP | (table as u64) << 2 | (symbol as u64) << 8 | raw << 15)
    }
    fn occupancy(table: usize, occupied: bool) -> Symbol {
        Symbol(Self::OCCUPANCY | (table as u64) << 2 | (occupied as u64) << 8)
    }
    fn kind(self) -> u64 {
        self.0 & 3
    }
    fn table(self) -> usize {
        (self.0 >> 2 & 63) as usize
    }
    fn mask_bits(self) -> usize {
        (self.0 >> 8 & 0xFF) as usize
    }
    fn step_symbol(self) -> usize {
        (self.0 >> 8 & 127) as usize
    }
    fn raw(self) -> u64 {
        self.0 >> 15
    }
}

/// Symbol counts per table, over all packets.
struct Frequencies {
    mask: [Vec<u64>; MASK_TABLES],
    /// [`RANS_VALUE_TABLES`] tables of the file's value alphabet; a prefix-coded file uses the
    /// first [`VALUE_TABLES`].
    value: Vec<Vec<u64>>,
    /// [`OCCUPANCY_TABLES`] binary tables ([`FAST_CONTEXTS_VERSION`] on).
    occupancy: Vec<[u64; 2]>,
}

impl Frequencies {
    fn new(value_alphabet: usize) -> Frequencies {
        Frequencies {
            mask: std::array::from_fn(|_| vec![0; MASK_ALPHABET]),
            value: vec![vec![0; value_alphabet]; RANS_VALUE_TABLES],
            occupancy: vec![[0; 2]; OCCUPANCY_TABLES],
        }
    }
    fn add(&mut self, symbols: &[Symbol]) {
        for &s in symbols {
            match s.kind() {
                Symbol::MASK => self.mask[s.table()][s.mask_bits()] += 1,
                Symbol::STEP => self.value[s.table()][s.step_symbol()] += 1,
                Symbol::OCCUPANCY => self.occupancy[s.table()][s.mask_bits()] += 1,
                _ => {}
            }
        }
    }
    /// Tables for these counts: prefix codes, or rANS distributions (with the occupancy
    /// tables when `contexts`).
    fn fit(&self, rans: bool, contexts: bool) -> FastTables {
        if rans && contexts {
            return self.fit_with_builtin();
        }
        if rans {
            return FastTables::rans(
                std::array::from_fn(|t| RansTable::from_counts(&self.mask[t])),
                self.value
                    .iter()
                    .map(|c| RansTable::from_counts(c))
                    .collect(),
                Vec::new(),
                0,
            );
        }
        debug_assert!(self.value[VALUE_TABLES..]
            .iter()
            .all(|c| c.iter().all(|&n| n == 0)));
        FastTables::prefix(
            std::array::from_fn(|t| HuffmanCode::from_frequencies(&self.mask[t], MAX_CODE_LENGTH)),
            std::array::from_fn(|t| HuffmanCode::from_frequencies(&self.value[t], MAX_CODE_LENGTH)),
        )
    }
}

impl Frequencies {
    /// Version [`FAST_CONTEXTS_VERSION`]'s tables: each the file's own distribution, or the
    /// built-in one ([`builtin`]) where that codes the table's symbols in no more bits than
    /// the file's own and its description. Records the counts for a [`builtin::Training`].
    fn fit_with_builtin(&self) -> FastTables {
        let counts: Vec<&[u64]> = self
            .mask
            .iter()
            .map(Vec::as_slice)
            .chain(self.occupancy.iter().map(|c| c.as_slice()))
            .chain(self.value.iter().map(Vec::as_slice))
            .collect();
        builtin::record(&counts);
        let shipped = builtin::shipped();
        let mut chosen_builtin = 0u128;
        let tables: Vec<RansTable> = counts
            .iter()
            .enumerate()
            .map(|(t, c)| {
                let own = RansTable::from_counts(c);
                if own.is_empty() {
                    return own;
                }
                let Some(Some(shipped)) = shipped.get(t) else {
                    return own;
                };
                let own_bits =
                    own.description_bits() as f64 + own.coded_bits(c).unwrap_or(f64::INFINITY);
                match shipped.coded_bits(c) {
                    Some(bits) if bits <= own_bits => {
                        chosen_builtin |= 1 << t;
                        shipped.clone()
                    }
                    _ => own,
                }
            })
            .collect();
        let mut tables = tables.into_iter();
        let mask: Vec<RansTable> = tables.by_ref().take(MASK_TABLES).collect();
        let occupancy: Vec<RansTable> = tables.by_ref().take(OCCUPANCY_TABLES).collect();
        let value: Vec<RansTable> = tables.collect();
        FastTables::rans(
            mask.try_into().expect("MASK_TABLES tables"),
            value,
            occupancy,
            chosen_builtin,
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

/// A coefficient to code: its cell and value (a substream's in Morton order).
type Keyed = ([u32; 3], f32);

impl PacketCoder {
    /// Codes the node of edge 2^`log` at `o` holding `pts` (at least one).
    fn node(&mut self, s: &Substream, pts: &[Keyed], o: [u32; 3], log: u32) {
        // The child holding a cell: its coordinates' bits at this node's split, x lowest.
        let child = |c: [u32; 3]| (0..3).map(|a| (c[a] >> (log - 1) & 1) << a).sum::<u32>();
        let mask = pts.iter().fold(0u8, |m, p| m | 1 << child(p.0));
        let h = 1u32 << (log - 1);
        // As the decoder's: a node of 2×2×2 cells finds the cells around it once.
        let mut leaf = if log == 1 {
            self.map.leaf_node(o)
        } else {
            None
        };
        if masks_bit_by_bit(s.sequential, log) {
            // As the decoder's `mask_bit_by_bit`.
            let faces = self.map.node4_face_states(o);
            let mut m = allowed_children(o, h, s.extent) as u32;
            let mut coded = 0u32;
            while m != 0 {
                let i = m.trailing_zeros();
                m &= m - 1;
                let occupied = mask >> i & 1 != 0;
                if coded != 0 || m != 0 {
                    let table =
                        occupancy_table(faces[i as usize], occupied_lower_siblings(i, coded));
                    self.symbols.push(Symbol::occupancy(table, occupied));
                }
                coded |= (occupied as u32) << i;
            }
            debug_assert_eq!(coded, mask as u32);
        } else {
            let table = match (&leaf, log) {
                (_, 2..) => LEAF_MASK_TABLES,
                (Some(leaf), _) => leaf.face_table(),
                (None, _) => self.map.face_table(o),
            };
            self.symbols.push(Symbol::mask(table, mask));
        }
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
        for &(cell, value) in pts {
            let negative = value < 0.0;
            let (q, magnitude) = s.quant.quantize((value as f64).abs());
            let i = child(cell);
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
            let (symbol, raw) = if s.sequential {
                step_symbol_halves(q)
            } else {
                step_symbol(q)
            };
            self.symbols
                .push(Symbol::step(s.value_base + vc, symbol, raw));
            self.signs
                .encode_bit(&mut self.sign_models[s.bi * SIGN_CONTEXTS + sc], negative);
            match (&mut leaf, index) {
                (Some(leaf), Some(index)) => {
                    let v = cell_entry(negative, q);
                    leaf.set(i, v);
                    self.map.set_at(index, v);
                }
                _ => self.map.insert(cell, negative, q),
            }
            let value = if negative { -magnitude } else { magnitude } as f32;
            self.recon.push(Coefficient::in_region(
                s.channel, s.band, s.origin, cell, value,
            ));
        }
    }
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
            .map(|c| ([0, 1, 2].map(|a| c.pos[a] - origin[a]), c.value))
            .collect();
        morton::sort_by_cell(&mut pts, log, |p| p.0);
        let s = Substream {
            bi,
            sequential: header.version >= FAST_CONTEXTS_VERSION,
            value_base: value_base(header, band),
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
    let contexts = header.version >= FAST_CONTEXTS_VERSION;
    let mut freqs = Frequencies::new(if contexts {
        HALF_OCTAVE_VALUE_ALPHABET
    } else {
        VALUE_ALPHABET
    });
    for p in &symbolized {
        freqs.add(&p.symbols);
    }
    let tables = freqs.fit(header.version >= RANS_VERSION, contexts);
    let mut bd = SizeBreakdown::default();
    let mut payloads = Vec::with_capacity(inputs.len());
    let mut recons = Vec::with_capacity(inputs.len());
    for p in symbolized {
        let payload = match &*tables.0 {
            Tables::Prefix { mask, value, .. } => {
                write_prefix_coded(mask, value, p.symbols, &mut bd)
            }
            Tables::Rans {
                mask,
                value,
                occupancy,
                ..
            } => write_rans_coded(mask, value, occupancy, p.symbols, &mut bd),
        };
        let mut payload = payload;
        payload.bytes(&p.signs);
        bd.sign_bits += 8.0 * p.signs.len() as f64;
        payloads.push(payload.into_bytes());
        recons.push(p.recon);
    }
    header.fast_tables = Some(tables);
    (payloads, recons, bd)
}

/// A payload's symbols as one prefix-coded stream (before format version
/// [`super::super::RANS_VERSION`]), after its varint length.
fn write_prefix_coded(
    mask: &[HuffmanCode; MASK_TABLES],
    value: &[HuffmanCode; VALUE_TABLES],
    symbols: Vec<Symbol>,
    bd: &mut SizeBreakdown,
) -> ByteWriter {
    let mut w = BitWriter::with_capacity(symbols.len());
    for s in symbols {
        match s.kind() {
            Symbol::MASK => {
                let code = &mask[s.table()];
                code.encode(s.mask_bits(), &mut w);
                bd.position_bits += code.cost_bits(s.mask_bits()) as f64;
            }
            Symbol::STEP => {
                let code = &value[s.table()];
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
    let mut payload = ByteWriter::new();
    payload.varint(prefix_coded.len() as u64);
    payload.bytes(&prefix_coded);
    payload
}

/// A payload's symbols as an rANS stream and a raw stream, each after its varint length. The
/// breakdown charges masks their exact costs, present bits one bit each, and the rest of both
/// streams (the steps and their raw bits, the final state, padding) to values.
fn write_rans_coded(
    mask: &[RansTable; MASK_TABLES],
    value: &[RansTable],
    occupancy: &[RansTable],
    symbols: Vec<Symbol>,
    bd: &mut SizeBreakdown,
) -> ByteWriter {
    let mut ans = RansEncoder::with_capacity(symbols.len());
    let mut raw = BitWriter::new();
    let (mut tag_bits, mut position_bits) = (0.0, 0.0);
    for s in symbols {
        match s.kind() {
            Symbol::MASK => {
                let table = &mask[s.table()];
                ans.put(table, s.mask_bits());
                position_bits += table.cost_bits(s.mask_bits());
            }
            Symbol::STEP => {
                ans.put(&value[s.table()], s.step_symbol());
                let n = if occupancy.is_empty() {
                    raw_bits(s.step_symbol())
                } else {
                    raw_bits_halves(s.step_symbol())
                };
                raw.put_bits(s.raw(), n);
            }
            Symbol::OCCUPANCY => {
                let table = &occupancy[s.table()];
                ans.put(table, s.mask_bits());
                position_bits += table.cost_bits(s.mask_bits());
            }
            _ => {
                raw.put_bit(s.0 >> 2 & 1 != 0);
                tag_bits += 1.0;
            }
        }
    }
    let (ans, raw) = (ans.finish(), raw.finish());
    let total = 8.0 * (ans.len() + raw.len()) as f64;
    bd.tag_bits += tag_bits;
    bd.position_bits += position_bits;
    bd.value_bits += total - tag_bits - position_bits;
    let mut payload = ByteWriter::new();
    payload.varint(ans.len() as u64);
    payload.bytes(&ans);
    payload.varint(raw.len() as u64);
    payload.bytes(&raw);
    payload
}

#[cfg(test)]
mod tests {
    use super::super::{step_of, DIRECT_STEPS};
    use super::*;

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
            for table in [0, VALUE_TABLES - 1, RANS_VALUE_TABLES - 1] {
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
    fn half_octave_step_symbols_cover_every_step_and_decode_back() {
        use super::super::{step_of_halves, HALF_OCTAVE_STEPS, OCTAVE_STEPS};
        let mut qs: Vec<u64> = (0..300).collect();
        for b in 4..50 {
            qs.extend([(1u64 << b) - 1, 1 << b, (1 << b) + 1, 3 << (b - 1)]);
        }
        qs.extend([999_999_999_999_999, 1_000_000_000_000_000]);
        let mut last = 0;
        for q in qs {
            let (symbol, raw) = step_symbol_halves(q);
            assert!(symbol < HALF_OCTAVE_VALUE_ALPHABET, "q {q}");
            assert!(raw < 1 << raw_bits_halves(symbol), "q {q}");
            assert_eq!(step_of_halves(symbol, raw), q);
            // The decoder's table reads the same step.
            let (base, n) = HALF_OCTAVE_STEPS.get(symbol);
            assert_eq!((base + raw, n), (q, raw_bits_halves(symbol)), "q {q}");
            // Symbols grow with q, and one raw bit fewer than version 14's follows a large
            // step.
            assert!(symbol >= last || q < 300, "q {q}");
            last = last.max(symbol);
            if q >= 16 {
                let (s14, _) = step_symbol(q);
                assert_eq!(raw_bits_halves(symbol) + 1, raw_bits(s14), "q {q}");
            }
            let packed = Symbol::step(RANS_VALUE_TABLES - 1, symbol, raw);
            assert_eq!(
                (packed.table(), packed.step_symbol(), packed.raw()),
                (RANS_VALUE_TABLES - 1, symbol, raw)
            );
            let (s14, raw14) = step_symbol(q);
            let (base, n) = OCTAVE_STEPS.get(s14);
            assert_eq!((base + raw14, n), (q, raw_bits(s14)), "q {q}");
        }
    }

    #[test]
    fn morton_order_orders_children_like_the_decoder() {
        // The decoder visits child i at child_origin(o, i, h) in increasing i; the encoder's
        // Morton order must be the same.
        let log = 3;
        let mut cells = Vec::new();
        for z in 0..8u32 {
            for y in 0..8u32 {
                for x in 0..8u32 {
                    cells.push([x, y, z]);
                }
            }
        }
        morton::sort_by_cell(&mut cells, log, |&c| c);
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
}
