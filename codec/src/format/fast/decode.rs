//! The fast coder's decoder: reads a payload's prefix-coded stream with the header's table
//! decoders and its sign stream, walking each present substream's octree, and checks that the
//! streams hold exactly the coefficients the packet declares.

use super::cells::CellMap;
use super::{
    allowed_children, child_origin, raw_bits, root_log, step_of, Decoders, Substream,
    LEAF_MASK_TABLES, SIGN_CONTEXTS,
};
use crate::entropy::bits::WordReader;
use crate::entropy::range::{BitModel, RangeDecoder};
use crate::format::coefficient::PacketFraming;
use crate::format::coefficient::{region_extent, Coefficient, SizeBreakdown};
use crate::format::quant::Quantizer;
use crate::format::{invalid, FormatError, Header};

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

/// Decodes a fast-coded payload of `packet.count` coefficients (a
/// [`crate::format::packet::PayloadDecoder`]).
pub(crate) fn decode(
    header: &Header,
    packet: &PacketFraming<'_>,
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    let (tile, layer, count, payload) = (packet.tile, packet.layer, packet.count, packet.payload);
    let tables = header
        .fast_tables
        .as_ref()
        .ok_or_else(|| invalid("header", "fast coder without tables"))?;
    let mut r = super::super::bytes::ByteReader::new(payload, "packet");
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
        out: Vec::with_capacity(count.min(super::super::coefficient::INITIAL_CAPACITY)),
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
