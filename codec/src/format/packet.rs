//! Packets: self-contained runs of one tile's coefficients, and their two entropy coders.
//!
//! Syntax per packet (Table 3 of the paper): the coefficients are grouped into runs of equal
//! substream id (channel × band: type, depth and colour channel, run-length coded); per
//! coefficient the position as a signed delta from the previous coefficient's position (mapped
//! to this coefficient's level grid; clustering makes these short), a sign bit, and the
//! quantization step δ of its substream's chain ([`super::quant`]). With
//! [`CoderKind::Huffman`] the run tags, run lengths, position deltas and value steps are coded
//! with the four static tables of the header (magnitude categories + raw extra bits); with
//! [`CoderKind::Range`] the same syntax elements go through adaptive binary models that reset
//! at every packet.
//!
//! Framing: tile (varint), layer (u8), coefficient count (varint), energy summary, payload length
//! (varint), payload, CRC-32 of everything before it. The summary is a bit mask of the bands with
//! energy (⌈bands/8⌉ bytes, band b in bit b % 8 of byte b / 8); if any, the largest code
//! c = round(8·log2(energy)) as i16, then per band in the mask one byte, the amount its code lies
//! below the largest (energies more than 2^−31.9 below the packet's largest band read back as
//! that floor, which no priority can tell apart from nothing).

use super::bytes::{ByteReader, ByteWriter};
use super::quant::Chain;
use super::{invalid, CoderKind, FormatError, Header, HuffmanTables, CATEGORY_ALPHABET};
use crate::entropy::bits::{BitReader, BitSink, BitWriter};
use crate::entropy::category::{
    decode_signed, decode_unsigned, encode_signed, encode_unsigned, signed_category,
    unsigned_category,
};
use crate::entropy::huffman::{HuffmanCode, HuffmanDecoder};
use crate::entropy::range::{AdaptiveSintModel, AdaptiveUintModel, RangeDecoder, RangeEncoder};
use crate::layout::Band;

/// Most coefficients a packet may declare per payload byte (plus one byte's worth), so that a
/// small hostile packet cannot make the decoder allocate and loop for a huge declared count.
/// The Huffman and range syntaxes spend at least one bit per coefficient; the sigmap coder's
/// adaptive contexts can spend less on very regular data (and its range coder drops trailing
/// zero bytes), so it pads its payload with zero bytes, which decode as if absent, up to this
/// bound.
pub(crate) const MAX_COEFFICIENTS_PER_PAYLOAD_BYTE: usize = 64;

/// Most coefficients a packet decoder reserves room for before decoding any.
pub(crate) const INITIAL_CAPACITY: usize = 1 << 16;

/// One coefficient: which channel and band, its position in the band grid, its value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coefficient {
    /// Channel (0 for intensity volumes).
    pub channel: u8,
    /// Band (level, type).
    pub band: Band,
    /// Position in the band's coefficient grid (global, not tile-local).
    pub pos: [u32; 3],
    /// Value.
    pub value: f32,
}

impl Coefficient {
    /// Every coefficient of one channel's dense (Mallat-layout) array, in array order, zeros
    /// included: what a lossless stream of that channel would deliver.
    pub fn all_of(
        geometry: &crate::layout::Geometry,
        channel: u8,
        values: &[f64],
    ) -> Vec<Coefficient> {
        values
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let (band, pos) = geometry.locate(i);
                Coefficient {
                    channel,
                    band,
                    pos: pos.map(|p| p as u32),
                    value: *v as f32,
                }
            })
            .collect()
    }
}

/// A packet to encode: one tile's coefficients (exact values) in coding order.
#[derive(Debug, Clone)]
pub struct PacketInput {
    /// Tile index.
    pub tile: usize,
    /// Quality layer (rank of this packet within its tile).
    pub layer: usize,
    /// Coefficients in coding order.
    pub coefficients: Vec<Coefficient>,
}

/// Where the bits of the encoded packets went (paper Fig. 16).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SizeBreakdown {
    /// Bits spent on run tags and run lengths (type, depth, channel).
    pub tag_bits: f64,
    /// Bits spent on positions.
    pub position_bits: f64,
    /// Bits spent on signs.
    pub sign_bits: f64,
    /// Bits spent on value steps.
    pub value_bits: f64,
    /// Framing bytes (packet headers, summaries, lengths, checksums).
    pub framing_bytes: u64,
}

/// Result of encoding a set of packets.
#[derive(Debug, Clone)]
pub struct EncodedPackets {
    /// Packet bytes, in input order.
    pub packets: Vec<Vec<u8>>,
    /// The decoder's view of every packet's coefficients (quantized values), in input order.
    pub reconstruction: Vec<Vec<Coefficient>>,
    /// Where the payload bits went. Exact for Huffman; for the range coder the per-element split
    /// is the adaptive models' ideal cost, scaled to the actual payload size.
    pub breakdown: SizeBreakdown,
}

/// What decoding may cost a caller that decodes what others send: coefficients, and bytes of
/// memory for them (and, for a whole volume, for its reconstruction). Checked against what a
/// packet or file *declares* before anything is allocated or decoded, so a small hostile input
/// is refused at once with an error saying what it would have cost.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecodeBudget {
    /// Most coefficients one decode call may produce.
    pub max_coefficients: u64,
    /// Most bytes of memory one decode call may allocate for its results.
    pub max_bytes: u64,
}

impl Default for DecodeBudget {
    /// 256 M coefficients and 8 GiB: any volume this machine class compresses, while a
    /// hostile file declaring far more is refused.
    fn default() -> Self {
        DecodeBudget {
            max_coefficients: 1 << 28,
            max_bytes: 8 << 30,
        }
    }
}

impl DecodeBudget {
    /// No limit beyond the format's own bounds.
    pub const UNLIMITED: DecodeBudget = DecodeBudget {
        max_coefficients: u64::MAX,
        max_bytes: u64::MAX,
    };

    /// Checks `count` coefficients against the budget.
    pub fn check_coefficients(&self, count: u64) -> Result<(), FormatError> {
        let bytes = count.saturating_mul(std::mem::size_of::<Coefficient>() as u64);
        if count > self.max_coefficients {
            return Err(FormatError::OverBudget {
                what: "coefficients",
                need: count,
                budget: self.max_coefficients,
            });
        }
        self.check_bytes(bytes)
    }

    /// Checks `bytes` of memory against the budget.
    pub fn check_bytes(&self, bytes: u64) -> Result<(), FormatError> {
        if bytes > self.max_bytes {
            return Err(FormatError::OverBudget {
                what: "bytes of memory",
                need: bytes,
                budget: self.max_bytes,
            });
        }
        Ok(())
    }
}

/// The coefficient count a packet declares (after checking its framing and checksum, without
/// decoding its payload).
pub fn declared_count(header: &Header, bytes: &[u8]) -> Result<u64, FormatError> {
    Ok(read_framing(header, bytes)?.count as u64)
}

/// A decoded packet.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedPacket {
    /// Tile index.
    pub tile: usize,
    /// Layer.
    pub layer: usize,
    /// Energy (Σ w̃²·‖basis‖²·I over channels) per band with coefficients in this packet.
    pub summary: Vec<(Band, f64)>,
    /// Coefficients (quantized values).
    pub coefficients: Vec<Coefficient>,
    /// Where this packet's bits went (see [`SizeBreakdown`]).
    pub breakdown: SizeBreakdown,
}

/// Syntax elements of one coefficient, after quantization.
#[derive(Debug, Clone, Copy)]
struct Symbols {
    substream: usize,
    dpos: [i64; 3],
    negative: bool,
    step: i64,
}

/// Receives the syntax elements of a packet in coding order.
trait SyntaxSink {
    fn run(&mut self, substream: usize, length: u64);
    fn coefficient(&mut self, level: usize, band: usize, s: &Symbols);
}

/// Quantizes a packet and computes its syntax elements and reconstruction.
fn symbolize(header: &Header, input: &PacketInput) -> (Vec<Symbols>, Vec<Coefficient>) {
    let nsub = header.substream_count();
    let mut chains: Vec<Option<Chain>> = vec![None; nsub];
    let origin = header.tile_origin(input.tile);
    let mut prev_voxel = [0i64; 3];
    let mut syms = Vec::with_capacity(input.coefficients.len());
    let mut recon = Vec::with_capacity(input.coefficients.len());
    for c in &input.coefficients {
        let sub = header.substream_id(c.channel as usize, c.band);
        let params = header.substreams[sub].expect("substream of a coded coefficient has params");
        let chain = chains[sub].get_or_insert_with(|| {
            Chain::new(header.chain_start(sub, input.layer), params.delta as f64)
        });
        let (step, mag) = chain.encode((c.value as f64).abs());
        let level = c.band.level as u32;
        let mut dpos = [0i64; 3];
        for a in 0..3 {
            let local = c.pos[a] as i64 - (origin[a] >> level) as i64;
            dpos[a] = local - (prev_voxel[a] >> level);
            prev_voxel[a] = local << level;
        }
        let negative = c.value < 0.0;
        syms.push(Symbols {
            substream: sub,
            dpos,
            negative,
            step,
        });
        let v = if negative { -mag } else { mag } as f32;
        recon.push(Coefficient { value: v, ..*c });
    }
    (syms, recon)
}

/// Feeds a packet's symbols, grouped in runs, to a sink.
fn emit(header: &Header, syms: &[Symbols], sink: &mut impl SyntaxSink) {
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let mut i = 0;
    while i < syms.len() {
        let s = syms[i].substream;
        let mut j = i;
        while j < syms.len() && syms[j].substream == s {
            j += 1;
        }
        sink.run(s, (j - i) as u64);
        let band_index = s % nb;
        let level = bands[band_index].level as usize;
        for sym in &syms[i..j] {
            sink.coefficient(level, band_index, sym);
        }
        i = j;
    }
}

/// Symbol frequencies for building the Huffman tables.
struct Frequencies {
    tag: Vec<u64>,
    run: Vec<u64>,
    position: Vec<u64>,
    value: Vec<u64>,
}

impl SyntaxSink for Frequencies {
    fn run(&mut self, substream: usize, length: u64) {
        self.tag[substream] += 1;
        self.run[unsigned_category(length - 1).0 as usize] += 1;
    }
    fn coefficient(&mut self, _level: usize, _band: usize, s: &Symbols) {
        for d in s.dpos {
            self.position[signed_category(d).0 as usize] += 1;
        }
        self.value[signed_category(s.step).0 as usize] += 1;
    }
}

/// Emits Huffman-coded syntax into a bit sink, counting bits per element.
struct HuffmanSink<'a, S: BitSink> {
    tables: &'a HuffmanTables,
    bits: S,
    breakdown: SizeBreakdown,
}

impl<S: BitSink> SyntaxSink for HuffmanSink<'_, S> {
    fn run(&mut self, substream: usize, length: u64) {
        let b0 = self.bits.bits();
        self.tables.tag.encode(substream, &mut self.bits);
        encode_unsigned(&self.tables.run, length - 1, &mut self.bits);
        self.breakdown.tag_bits += (self.bits.bits() - b0) as f64;
    }
    fn coefficient(&mut self, _level: usize, _band: usize, s: &Symbols) {
        let b0 = self.bits.bits();
        for d in s.dpos {
            encode_signed(&self.tables.position, d, &mut self.bits);
        }
        let b1 = self.bits.bits();
        self.bits.put_bit(s.negative);
        let b2 = self.bits.bits();
        encode_signed(&self.tables.value, s.step, &mut self.bits);
        let b3 = self.bits.bits();
        self.breakdown.position_bits += (b1 - b0) as f64;
        self.breakdown.sign_bits += (b2 - b1) as f64;
        self.breakdown.value_bits += (b3 - b2) as f64;
    }
}

/// Adaptive models of the range coder, fresh for every packet.
struct RangeModels {
    tag: AdaptiveUintModel,
    run: AdaptiveUintModel,
    position: Vec<[AdaptiveSintModel; 3]>,
    value: Vec<AdaptiveSintModel>,
}

impl RangeModels {
    fn new(header: &Header) -> RangeModels {
        RangeModels {
            tag: AdaptiveUintModel::new(),
            run: AdaptiveUintModel::new(),
            position: (0..=header.geometry.levels)
                .map(|_| std::array::from_fn(|_| AdaptiveSintModel::new()))
                .collect(),
            value: (0..header.geometry.band_count())
                .map(|_| AdaptiveSintModel::new())
                .collect(),
        }
    }
}

struct RangeSink {
    models: RangeModels,
    enc: RangeEncoder,
    breakdown: SizeBreakdown,
}

impl SyntaxSink for RangeSink {
    fn run(&mut self, substream: usize, length: u64) {
        let b0 = self.enc.bits_spent();
        self.models.tag.encode(&mut self.enc, substream as u64);
        self.models.run.encode(&mut self.enc, length - 1);
        self.breakdown.tag_bits += self.enc.bits_spent() - b0;
    }
    fn coefficient(&mut self, level: usize, band: usize, s: &Symbols) {
        let b0 = self.enc.bits_spent();
        for (a, d) in s.dpos.iter().enumerate() {
            self.models.position[level][a].encode(&mut self.enc, *d);
        }
        let b1 = self.enc.bits_spent();
        self.enc.encode_bypass(s.negative as u64, 1);
        let b2 = self.enc.bits_spent();
        self.models.value[band].encode(&mut self.enc, s.step);
        let b3 = self.enc.bits_spent();
        self.breakdown.position_bits += b1 - b0;
        self.breakdown.sign_bits += b2 - b1;
        self.breakdown.value_bits += b3 - b2;
    }
}

/// Code for an energy in the summary: round(8·log2(E)), clamped to i16; 0 energy is omitted.
fn energy_code(e: f64) -> i16 {
    (8.0 * e.log2()).round().clamp(-32767.0, 32767.0) as i16
}

fn energy_from_code(c: i32) -> f64 {
    (c as f64 / 8.0).exp2()
}

/// Per-band energy summary of reconstructed coefficients.
fn summarize(header: &Header, coeffs: &[Coefficient]) -> Vec<(usize, f64)> {
    let nb = header.geometry.band_count();
    let mut e = vec![0.0f64; nb];
    for c in coeffs {
        let bi = header.geometry.band_index(c.band).expect("valid band");
        e[bi] += (c.value as f64).powi(2)
            * header.geometry.basis_norm2(c.band)
            * header.importance(c.channel as usize);
    }
    e.into_iter()
        .enumerate()
        .filter(|(_, v)| *v > 0.0 && v.is_finite())
        .collect()
}

fn frame(header: &Header, input: &PacketInput, recon: &[Coefficient], payload: &[u8]) -> Vec<u8> {
    let mut w = ByteWriter::new();
    w.varint(input.tile as u64);
    w.u8(input.layer as u8);
    w.varint(input.coefficients.len() as u64);
    let summary = summarize(header, recon);
    let nb = header.geometry.band_count();
    let mut mask = vec![0u8; nb.div_ceil(8)];
    for (bi, _) in &summary {
        mask[bi / 8] |= 1 << (bi % 8);
    }
    mask.iter().for_each(|m| w.u8(*m));
    if let Some(top) = summary.iter().map(|(_, e)| energy_code(*e)).max() {
        w.u16(top as u16);
        for (_, e) in &summary {
            w.u8((top as i32 - energy_code(*e) as i32).clamp(0, 255) as u8);
        }
    }
    w.varint(payload.len() as u64);
    w.bytes(payload);
    let crc = crc32fast::hash(w.as_slice());
    let mut bytes = w.into_bytes();
    bytes.extend_from_slice(&crc.to_le_bytes());
    bytes
}

/// Builds the Huffman tables for a set of packets (two-pass coding: the tables are fitted to the
/// symbols actually sent, as the paper does).
fn fit_tables(header: &Header, symbolized: &[Vec<Symbols>]) -> HuffmanTables {
    let mut f = Frequencies {
        tag: vec![0; header.substream_count()],
        run: vec![0; CATEGORY_ALPHABET],
        position: vec![0; CATEGORY_ALPHABET],
        value: vec![0; CATEGORY_ALPHABET],
    };
    for syms in symbolized {
        emit(header, syms, &mut f);
    }
    HuffmanTables {
        tag: HuffmanCode::from_frequencies(&f.tag, 15),
        run: HuffmanCode::from_frequencies(&f.run, 15),
        position: HuffmanCode::from_frequencies(&f.position, 15),
        value: HuffmanCode::from_frequencies(&f.value, 15),
    }
}

/// Frames coded payloads (in input order) into packets, adding their framing bytes to
/// `breakdown`.
fn frame_all(
    header: &Header,
    inputs: &[PacketInput],
    payloads: Vec<Vec<u8>>,
    reconstruction: Vec<Vec<Coefficient>>,
    mut breakdown: SizeBreakdown,
) -> EncodedPackets {
    let packets = inputs
        .iter()
        .zip(&payloads)
        .zip(&reconstruction)
        .map(|((input, payload), recon)| {
            let framed = frame(header, input, recon, payload);
            breakdown.framing_bytes += (framed.len() - payload.len()) as u64;
            framed
        })
        .collect();
    EncodedPackets {
        packets,
        reconstruction,
        breakdown,
    }
}

/// Quantizes and entropy-codes packets. For the Huffman coder the tables are fitted to these
/// packets and stored into `header.tables`; `header.substreams` must already hold the
/// quantization parameters of every substream that appears.
pub fn encode_packets(header: &mut Header, inputs: &[PacketInput]) -> EncodedPackets {
    let (symbolized, reconstruction): (Vec<_>, Vec<_>) = if header.coder.quantizes_by_threshold() {
        (Vec::new(), Vec::new())
    } else {
        inputs.iter().map(|p| symbolize(header, p)).unzip()
    };
    let mut breakdown = SizeBreakdown::default();
    let mut packets = Vec::with_capacity(inputs.len());
    header.fast_tables = None;
    match header.coder {
        CoderKind::Huffman => {
            let tables = fit_tables(header, &symbolized);
            header.tables = Some(tables.clone());
            for ((input, syms), recon) in inputs.iter().zip(&symbolized).zip(&reconstruction) {
                let mut sink = HuffmanSink {
                    tables: &tables,
                    bits: BitWriter::new(),
                    breakdown,
                };
                emit(header, syms, &mut sink);
                breakdown = sink.breakdown;
                let payload = sink.bits.finish();
                let framed = frame(header, input, recon, &payload);
                breakdown.framing_bytes += (framed.len() - payload.len()) as u64;
                packets.push(framed);
            }
        }
        CoderKind::Sigmap => {
            header.tables = None;
            let mut reconstruction = Vec::with_capacity(inputs.len());
            // Packets are independent: code them in parallel, keep them in input order.
            let code = |input: &PacketInput| {
                super::sigmap::encode(header, input.tile, input.layer, &input.coefficients)
            };
            #[cfg(feature = "rayon")]
            let coded: Vec<_> = {
                use rayon::prelude::*;
                inputs.par_iter().map(code).collect()
            };
            #[cfg(not(feature = "rayon"))]
            let coded: Vec<_> = inputs.iter().map(code).collect();
            let mut payloads = Vec::with_capacity(inputs.len());
            for (payload, recon, bd) in coded {
                breakdown.tag_bits += bd.tag_bits;
                breakdown.position_bits += bd.position_bits;
                breakdown.sign_bits += bd.sign_bits;
                breakdown.value_bits += bd.value_bits;
                payloads.push(payload);
                reconstruction.push(recon);
            }
            return frame_all(header, inputs, payloads, reconstruction, breakdown);
        }
        CoderKind::Fast => {
            header.tables = None;
            let (payloads, reconstruction, bd) = super::fast::encode_packets(header, inputs);
            return frame_all(header, inputs, payloads, reconstruction, bd);
        }
        CoderKind::Range => {
            header.tables = None;
            for ((input, syms), recon) in inputs.iter().zip(&symbolized).zip(&reconstruction) {
                let mut sink = RangeSink {
                    models: RangeModels::new(header),
                    enc: RangeEncoder::new(),
                    breakdown,
                };
                emit(header, syms, &mut sink);
                breakdown = sink.breakdown;
                let payload = sink.enc.finish();
                let framed = frame(header, input, recon, &payload);
                breakdown.framing_bytes += (framed.len() - payload.len()) as u64;
                packets.push(framed);
            }
        }
    }
    EncodedPackets {
        packets,
        reconstruction,
        breakdown,
    }
}

/// Reads the syntax of one packet.
trait SyntaxSource {
    /// Bits consumed so far (exact for Huffman, byte-granular for the range coder).
    fn bits_read(&self) -> f64;
    fn run(&mut self) -> Result<(usize, u64), FormatError>;
    fn dpos(&mut self, level: usize, axis: usize) -> Result<i64, FormatError>;
    fn sign(&mut self) -> Result<bool, FormatError>;
    fn step(&mut self, band: usize) -> Result<i64, FormatError>;
}

struct HuffmanSource<'a> {
    reader: BitReader<'a>,
    tag: HuffmanDecoder,
    run: HuffmanDecoder,
    position: HuffmanDecoder,
    value: HuffmanDecoder,
}

impl SyntaxSource for HuffmanSource<'_> {
    fn bits_read(&self) -> f64 {
        self.reader.position() as f64
    }
    fn run(&mut self) -> Result<(usize, u64), FormatError> {
        let tag = self.tag.decode(&mut self.reader)?;
        let len = decode_unsigned(&self.run, &mut self.reader)?;
        Ok((tag, len.saturating_add(1)))
    }
    fn dpos(&mut self, _level: usize, _axis: usize) -> Result<i64, FormatError> {
        Ok(decode_signed(&self.position, &mut self.reader)?)
    }
    fn sign(&mut self) -> Result<bool, FormatError> {
        Ok(self.reader.get_bit()?)
    }
    fn step(&mut self, _band: usize) -> Result<i64, FormatError> {
        Ok(decode_signed(&self.value, &mut self.reader)?)
    }
}

struct RangeSource<'a> {
    dec: RangeDecoder<'a>,
    models: RangeModels,
}

impl SyntaxSource for RangeSource<'_> {
    fn bits_read(&self) -> f64 {
        8.0 * self.dec.bytes_read() as f64
    }
    fn run(&mut self) -> Result<(usize, u64), FormatError> {
        let tag = self.models.tag.decode(&mut self.dec)?;
        let len = self.models.run.decode(&mut self.dec)?;
        let tag = usize::try_from(tag).map_err(|_| invalid("packet", "run tag too large"))?;
        Ok((tag, len.saturating_add(1)))
    }
    fn dpos(&mut self, level: usize, axis: usize) -> Result<i64, FormatError> {
        Ok(self.models.position[level][axis].decode(&mut self.dec)?)
    }
    fn sign(&mut self) -> Result<bool, FormatError> {
        Ok(self.dec.decode_bypass(1) != 0)
    }
    fn step(&mut self, band: usize) -> Result<i64, FormatError> {
        Ok(self.models.value[band].decode(&mut self.dec)?)
    }
}

/// A packet's framing: everything but the coded coefficients (cheap to read: a viewer or a
/// cache ranks packets by it before decoding any).
#[derive(Debug, Clone, PartialEq)]
pub struct PacketFraming<'a> {
    /// Tile index.
    pub tile: usize,
    /// Layer.
    pub layer: usize,
    /// Declared coefficient count (checked against the payload size and the tile's capacity).
    pub count: usize,
    /// Energy per band (see [`DecodedPacket::summary`]).
    pub summary: Vec<(Band, f64)>,
    /// The coded coefficients.
    pub payload: &'a [u8],
}

/// Reads and validates a packet's framing and checksum without decoding its coefficients.
pub fn read_framing<'a>(
    header: &Header,
    bytes: &'a [u8],
) -> Result<PacketFraming<'a>, FormatError> {
    const W: &str = "packet";
    if bytes.len() < 4 {
        return Err(FormatError::Truncated {
            what: W,
            needed: 4,
            available: bytes.len() as u64,
        });
    }
    let (body, crc) = bytes.split_at(bytes.len() - 4);
    let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    let computed = crc32fast::hash(body);
    if stored != computed {
        return Err(FormatError::Checksum {
            what: W,
            stored,
            computed,
        });
    }
    let mut r = ByteReader::new(body, W);
    let tile = r.varint_max(header.tile_count() as u64 - 1, "tile")? as usize;
    let layer = r.u8()? as usize;
    if layer >= header.layer_bounds.len() {
        return Err(invalid(
            W,
            format!("layer {layer} of {}", header.layer_bounds.len()),
        ));
    }
    let count = r.varint()?;
    let nb = header.geometry.band_count();
    let mut present = Vec::with_capacity(nb);
    for byte in 0..nb.div_ceil(8) {
        let m = r.u8()?;
        for bit in 0..8 {
            if m & (1 << bit) != 0 {
                let bi = 8 * byte + bit;
                if bi >= nb {
                    return Err(invalid(W, format!("summary names band {bi} of {nb}")));
                }
                present.push(bi);
            }
        }
    }
    let bands = header.geometry.bands();
    let mut summary = Vec::with_capacity(present.len());
    if !present.is_empty() {
        let top = r.u16()? as i16 as i32;
        for bi in present {
            let code = top - r.u8()? as i32;
            summary.push((bands[bi], energy_from_code(code)));
        }
    }
    let plen = r.varint()? as usize;
    let payload = r.take(plen)?;
    if r.remaining() != 0 {
        return Err(invalid(W, "bytes after the payload"));
    }
    // Bound the count by the payload (the encoders guarantee it: one bit per coefficient for the
    // paper's syntaxes, MAX_COEFFICIENTS_PER_PAYLOAD_BYTE for sigmap), and by the tile's
    // capacity: the wavelet transform is critically sampled, so a tile holds at most as many
    // coefficients per channel as it has voxels of the padded grid.
    let origin = header.tile_origin(tile);
    let capacity = (0..3)
        .map(|a| {
            let end = (origin[a] + header.tile).min(header.geometry.padded[a]);
            end.saturating_sub(origin[a]) as u64
        })
        .fold(header.channels as u64, u64::saturating_mul);
    let per_byte = match header.coder {
        CoderKind::Sigmap => MAX_COEFFICIENTS_PER_PAYLOAD_BYTE as u64,
        CoderKind::Huffman | CoderKind::Range | CoderKind::Fast => 8,
    };
    if count > per_byte.saturating_mul(plen as u64 + 1) || count > capacity {
        return Err(invalid(
            W,
            format!("{count} coefficients in a {plen}-byte payload (tile capacity {capacity})"),
        ));
    }
    Ok(PacketFraming {
        tile,
        layer,
        count: count as usize,
        summary,
        payload,
    })
}

/// Decodes one packet given the header, within the default [`DecodeBudget`]. Validates
/// framing, checksum, every index and every position; never panics on any input.
pub fn decode_packet(header: &Header, bytes: &[u8]) -> Result<DecodedPacket, FormatError> {
    decode_packet_within(header, bytes, &DecodeBudget::default())
}

/// Decodes one packet given the header, refusing it before decoding if its declared count is
/// over `budget`.
pub fn decode_packet_within(
    header: &Header,
    bytes: &[u8],
    budget: &DecodeBudget,
) -> Result<DecodedPacket, FormatError> {
    let PacketFraming {
        tile,
        layer,
        count,
        summary,
        payload,
    } = read_framing(header, bytes)?;
    budget.check_coefficients(count as u64)?;
    let plen = payload.len();
    let mut breakdown = SizeBreakdown {
        framing_bytes: (bytes.len() - plen) as u64,
        ..SizeBreakdown::default()
    };
    let coefficients = match header.coder {
        CoderKind::Huffman => {
            let t = header
                .tables
                .as_ref()
                .ok_or_else(|| invalid("header", "Huffman coder without tables"))?;
            let mut src = HuffmanSource {
                reader: BitReader::new(payload),
                tag: HuffmanDecoder::new(&t.tag),
                run: HuffmanDecoder::new(&t.run),
                position: HuffmanDecoder::new(&t.position),
                value: HuffmanDecoder::new(&t.value),
            };
            decode_syntax(header, tile, layer, count, &mut src, &mut breakdown)?
        }
        CoderKind::Sigmap => {
            super::sigmap::decode(header, tile, layer, count, payload, &mut breakdown)?
        }
        CoderKind::Fast => {
            super::fast::decode(header, tile, layer, count, payload, &mut breakdown)?
        }
        CoderKind::Range => {
            let mut src = RangeSource {
                dec: RangeDecoder::new(payload),
                models: RangeModels::new(header),
            };
            decode_syntax(header, tile, layer, count, &mut src, &mut breakdown)?
        }
    };
    Ok(DecodedPacket {
        tile,
        layer,
        summary,
        coefficients,
        breakdown,
    })
}

fn decode_syntax(
    header: &Header,
    tile: usize,
    layer: usize,
    count: usize,
    src: &mut impl SyntaxSource,
    bd: &mut SizeBreakdown,
) -> Result<Vec<Coefficient>, FormatError> {
    const W: &str = "packet";
    let nsub = header.substream_count();
    let nb = header.geometry.band_count();
    let bands = header.geometry.bands();
    let origin = header.tile_origin(tile);
    let mut chains: Vec<Option<Chain>> = vec![None; nsub];
    let mut prev_voxel = [0i64; 3];
    // The count is bounded but may still be large for a hostile packet: grow as decoded.
    let mut out = Vec::with_capacity(count.min(INITIAL_CAPACITY));
    while out.len() < count {
        let b0 = src.bits_read();
        let (sub, len) = src.run()?;
        bd.tag_bits += src.bits_read() - b0;
        if sub >= nsub {
            return Err(invalid(W, format!("substream {sub} of {nsub}")));
        }
        let Some(params) = header.substreams[sub] else {
            return Err(invalid(W, format!("substream {sub} has no parameters")));
        };
        if len > (count - out.len()) as u64 {
            return Err(invalid(
                W,
                format!("run of {len} exceeds the coefficient count"),
            ));
        }
        let (channel, band_index) = (sub / nb, sub % nb);
        let band = bands[band_index];
        let level = band.level as usize;
        let band_dims = header.geometry.band_dims(band);
        let chain = chains[sub]
            .get_or_insert_with(|| Chain::new(header.chain_start(sub, layer), params.delta as f64));
        for _ in 0..len {
            let b0 = src.bits_read();
            let mut pos = [0u32; 3];
            for a in 0..3 {
                let d = src.dpos(level, a)?;
                let local = (prev_voxel[a] >> level)
                    .checked_add(d)
                    .ok_or_else(|| invalid(W, "position delta overflows"))?;
                let lo = (origin[a] >> level) as i64;
                let hi = ((origin[a] + header.tile) >> level).min(band_dims[a]) as i64;
                if local < 0 || lo + local >= hi {
                    return Err(invalid(
                        W,
                        format!(
                            "position {local} on axis {a} outside tile band of {}",
                            hi - lo
                        ),
                    ));
                }
                pos[a] = (lo + local) as u32;
                prev_voxel[a] = local << level;
            }
            let b1 = src.bits_read();
            let negative = src.sign()?;
            let b2 = src.bits_read();
            let step = src.step(band_index)?;
            let b3 = src.bits_read();
            bd.position_bits += b1 - b0;
            bd.sign_bits += b2 - b1;
            bd.value_bits += b3 - b2;
            let mag = chain.decode(step)?;
            let v = if negative { -mag } else { mag } as f32;
            if !v.is_finite() {
                return Err(invalid(W, "decoded value is not finite"));
            }
            out.push(Coefficient {
                channel: channel as u8,
                band,
                pos,
                value: v,
            });
        }
    }
    Ok(out)
}

/// A packet that failed to decode, with its index in the file.
#[derive(Debug, thiserror::Error)]
#[error("packet {index}: {source}")]
pub struct PacketError {
    /// Packet index in the file.
    pub index: usize,
    /// What was wrong.
    #[source]
    pub source: FormatError,
}

/// Decodes `packets`, each on its own (in parallel with the `rayon` feature), within the
/// default [`DecodeBudget`]; the result is in input order. Errors name the packet's file index,
/// `first_index` being that of `packets[0]`.
pub fn decode_packets(
    header: &Header,
    packets: &[&[u8]],
    first_index: usize,
) -> Result<Vec<Vec<Coefficient>>, PacketError> {
    decode_packets_within(header, packets, first_index, &DecodeBudget::default())
}

/// [`decode_packets`] with a budget for all the packets together, checked against their
/// declared counts before any is decoded.
pub fn decode_packets_within(
    header: &Header,
    packets: &[&[u8]],
    first_index: usize,
    budget: &DecodeBudget,
) -> Result<Vec<Vec<Coefficient>>, PacketError> {
    let mut total = 0u64;
    for (i, p) in packets.iter().enumerate() {
        let fail = |source| PacketError {
            index: first_index + i,
            source,
        };
        total = total.saturating_add(declared_count(header, p).map_err(fail)?);
        budget.check_coefficients(total).map_err(fail)?;
    }
    let one = |(i, p): (usize, &&[u8])| {
        decode_packet_within(header, p, &DecodeBudget::UNLIMITED)
            .map(|d| d.coefficients)
            .map_err(|source| PacketError {
                index: first_index + i,
                source,
            })
    };
    #[cfg(feature = "rayon")]
    {
        use rayon::prelude::*;
        packets.par_iter().enumerate().map(one).collect()
    }
    #[cfg(not(feature = "rayon"))]
    {
        packets.iter().enumerate().map(one).collect()
    }
}
